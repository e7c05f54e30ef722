"""Super-resolution rendering of localization tables and a Fourier ring correlation estimate.

Rendering
    Every localization is drawn as a normalised Gaussian whose widths are its own uncertainties
    (``sigma_x_nm``, ``sigma_y_nm``, ``sigma_z_nm``), never narrower than a floor
    (``sigma_min_nm``, default half a render pixel, so no spot falls between pixels). Each spot
    integrates to one: images count localizations (per pixel or voxel), they are not weighted by
    photons. Missing, NaN or non-positive uncertainties fall back to ``default_sigma_nm``
    (lateral, 15 nm) and 2.5 times that axially.

    Speed comes from a few width levels: a geometric grid per axis (ratio
    :data:`SIGMA_BIN_RATIO`, sqrt(2), starting at the smallest width). Each localization is
    shared between the two levels around its width, with weights chosen so that its variance is
    exactly its own (``w lo^2 + (1 - w) hi^2 = sigma^2``): every spot keeps its mass, centroid
    and second moment per axis, and its shape is a mixture of two Gaussians whose widths differ
    by sqrt(2) (peak within about +5 % per axis of the true Gaussian's). Then, for each
    combination of levels, the cheaper of two methods (by measured costs) draws its share:

    * *filter*: bilinear deposit on the pixel grid (cloud-in-cell: the centroid stays exact)
      over the group's bounding box, then one :func:`scipy.ndimage.gaussian_filter` whose
      variance is the level's minus the mean variance the bilinear deposit adds (px^2 / 6 on
      average). Cost ~ pixels, so it wins for dense groups (1e6 localizations of one width on
      25 Mpx: about 2 s on one core).
    * *splat*: a separable Gaussian patch per localization (sampled at pixel centres,
      normalised to one) added with vectorised NumPy. Cost ~ localizations x patch area, so it
      wins for small or sparse groups.

    The two agree to about 1 % of the peak for widths of 2 px and more; below about 1 px the
    pixel grid dominates either way (up to ~25 % per-pixel differences, same mass and centroid).
    Spots are cut at :data:`TRUNCATE` standard deviations; mass that falls outside the image is
    lost. Images larger than :data:`MAX_PIXELS` pixels are refused.

Resolution
    :func:`frc` computes the Fourier ring correlation of two half data sets (Nieuwenhuizen et
    al., Nat. Methods 10, 557, 2013) and reports the inverse of the spatial frequency where the
    smoothed curve first falls below 1/7.

Coordinates follow the localization tables: nm, ``x`` to the right, ``y`` down, the outer corner
of pixel (0, 0) at the origin of the extent. A 2D image's ``extent`` is ``(h0, h1, v0, v1)``:
the nm positions of its outer edges along its horizontal (columns) and vertical (rows) axes;
row 0 lies at ``v0``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy import ndimage as ndi

__all__ = [
    "FRC_THRESHOLD",
    "MAX_PIXELS",
    "SIGMA_BIN_RATIO",
    "TRUNCATE",
    "FRCResult",
    "Rendered",
    "frc",
    "intensity_scale",
    "plot_frc",
    "plot_projections",
    "render_gaussian",
    "render_volume",
    "to_rgb",
    "write_volume_tiff",
]

log = logging.getLogger(__name__)

#: Largest image or volume (pixels or voxels) any function here will allocate.
MAX_PIXELS: int = 200_000_000
#: Ratio between neighbouring width bins (per axis) of the grouped rendering.
SIGMA_BIN_RATIO: float = math.sqrt(2.0)
#: Spots are cut at this many standard deviations.
TRUNCATE: float = 4.0
#: The FRC threshold (Nieuwenhuizen et al. 2013).
FRC_THRESHOLD: float = 1.0 / 7.0
#: Axial default width as a multiple of the lateral one when a table has no ``sigma_z_nm``.
AXIAL_DEFAULT_FACTOR: float = 2.5

_PROJECTIONS: dict[str, tuple[str, str]] = {"xy": ("x", "y"), "xz": ("x", "z"), "yz": ("y", "z")}
_POS = {"x": "x_nm", "y": "y_nm", "z": "z_nm"}
_SIG = {"x": "sigma_x_nm", "y": "sigma_y_nm", "z": "sigma_z_nm"}
# Relative density below which the mean depth of a pixel is left undefined (NaN).
_DEPTH_FLOOR = 1e-6
# Splat work is chunked to about this many patch values at once (memory ~ 100 MB).
_SPLAT_CHUNK = 4_000_000


@dataclass(frozen=True)
class Rendered:
    """A rendered 2D image.

    Attributes
    ----------
    density : ndarray, shape (rows, cols), float32
        Localizations per pixel (each spot integrates to one).
    depth : ndarray, shape (rows, cols), float32, or None
        Density-weighted mean z (nm) of each pixel, NaN where the density is negligible; only
        for the ``xy`` projection of a table with ``z_nm``.
    extent : (float, float, float, float)
        ``(h0, h1, v0, v1)``: nm positions of the outer edges along the horizontal (columns) and
        vertical (rows) axes; row 0 is at ``v0``.
    px_nm : float
        Pixel size (nm), the same along both axes.
    projection : str
        ``"xy"``, ``"xz"`` or ``"yz"``.
    axes : (str, str)
        Names of the horizontal and vertical axes, e.g. ``("x", "z")``.
    n_locs : int
        Localizations drawn (rows with finite coordinates).
    """

    density: NDArray[np.float32]
    depth: NDArray[np.float32] | None
    extent: tuple[float, float, float, float]
    px_nm: float
    projection: str
    axes: tuple[str, str]
    n_locs: int = 0


@dataclass(frozen=True)
class FRCResult:
    """Fourier ring correlation of two half data sets.

    Attributes
    ----------
    frequency : ndarray, shape (n_rings,)
        Ring centres (1/nm), from the first non-zero ring up to the Nyquist frequency.
    curve : ndarray, shape (n_rings,)
        Smoothed FRC.
    curve_raw : ndarray, shape (n_rings,)
        FRC before smoothing.
    resolution_nm : float
        ``1 / q`` at the first crossing of ``threshold`` (nm), NaN when there is none.
    threshold : float
        The threshold (1/7).
    warning : str
        Why ``resolution_nm`` is NaN; empty otherwise.
    n_halves : (int, int)
        Localizations in each half.
    px_nm : float
        Pixel size of the half images (nm).
    split : str
        ``"blocks"`` or ``"random"``.
    """

    frequency: NDArray[np.float64]
    curve: NDArray[np.float64]
    curve_raw: NDArray[np.float64]
    resolution_nm: float
    threshold: float = FRC_THRESHOLD
    warning: str = ""
    n_halves: tuple[int, int] = (0, 0)
    px_nm: float = float("nan")
    split: str = "blocks"
    extra: dict[str, Any] = field(default_factory=dict)


# -- input checks ------------------------------------------------------------------------------


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number of nm, got {value!r}")
    return v


def _check_table(locs: pd.DataFrame, axes: tuple[str, ...]) -> None:
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(f"expected a localization table (DataFrame), got {type(locs).__name__}")
    for a in axes:
        if _POS[a] not in locs.columns:
            raise ValueError(f"the localization table has no column {_POS[a]!r}")
    if len(locs) == 0:
        raise ValueError("the localization table is empty: there is nothing to render")


def _finite_rows(locs: pd.DataFrame, axes: tuple[str, ...]) -> tuple[NDArray, NDArray[np.bool_]]:
    """Positions (n, len(axes)) in nm of the rows whose coordinates are all finite."""
    pos = np.column_stack([locs[_POS[a]].to_numpy(dtype=np.float64) for a in axes])
    ok = np.all(np.isfinite(pos), axis=1)
    if not ok.all():
        log.info(
            "skipping %d of %d localizations with non-finite coordinates", (~ok).sum(), ok.size
        )
    if not ok.any():
        raise ValueError(f"none of the {ok.size} localizations has finite coordinates")
    return pos[ok], ok


def _widths(
    locs: pd.DataFrame,
    axes: tuple[str, ...],
    ok: NDArray[np.bool_],
    default_nm: float,
    floors_nm: tuple[float, ...],
) -> NDArray[np.float64]:
    """Per-localization widths (n, len(axes)) in nm: the table's uncertainties where usable,
    else the default (lateral) or ``AXIAL_DEFAULT_FACTOR`` times it (z), at least the floor."""
    out = np.empty((int(ok.sum()), len(axes)))
    for j, a in enumerate(axes):
        fallback = default_nm * (AXIAL_DEFAULT_FACTOR if a == "z" else 1.0)
        col = _SIG[a]
        if col in locs.columns:
            s = locs[col].to_numpy(dtype=np.float64)[ok]
            s = np.where(np.isfinite(s) & (s > 0), s, fallback)
        else:
            s = np.full(out.shape[0], fallback)
        out[:, j] = np.maximum(s, floors_nm[j])
    return out


def _axis_grid(
    pos: NDArray, sig: NDArray, step: float, given: tuple[float, float] | None, name: str
) -> tuple[float, int]:
    """Start (nm) and number of pixels along one axis.

    Without ``given`` the data range padded by TRUNCATE (4) 95th-percentile widths, snapped to
    multiples of ``step`` so that images with the same pixel size share a grid; with ``given``
    its start, and its end moved up to a whole number of pixels."""
    if given is None:
        pad = TRUNCATE * float(np.percentile(sig, 95))
        lo = math.floor((float(pos.min()) - pad) / step) * step
        n = max(1, math.ceil((float(pos.max()) + pad - lo) / step))
        return lo, n
    lo, hi = (float(v) for v in given)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"the {name} extent must run from low to high nm, got {lo:g}..{hi:g}")
    return lo, max(1, math.ceil((hi - lo) / step - 1e-9))


def _default_extent(
    locs: pd.DataFrame, axes: tuple[str, str], px: float, default_sigma_nm: float = 15.0
) -> tuple[float, float, float, float]:
    """The extent :func:`render_gaussian` would choose for ``locs`` (nm)."""
    pos, ok = _finite_rows(locs, axes)
    sig = _widths(locs, axes, ok, default_sigma_nm, (px / 2, px / 2))
    h0, nh = _axis_grid(pos[:, 0], sig[:, 0], px, None, axes[0])
    v0, nv = _axis_grid(pos[:, 1], sig[:, 1], px, None, axes[1])
    return (h0, h0 + nh * px, v0, v0 + nv * px)


def _check_size(shape: tuple[int, ...], what: str) -> None:
    total = math.prod(shape)
    if total > MAX_PIXELS:
        dims = " x ".join(str(s) for s in shape)
        raise ValueError(
            f"the {what} would have {dims} = {total:.3g} pixels, over the cap of "
            f"{MAX_PIXELS:.3g}: use larger pixels or a smaller extent"
        )


# -- the accumulation core ---------------------------------------------------------------------


def _strides(shape: tuple[int, ...]) -> NDArray[np.int64]:
    return np.array([math.prod(shape[a + 1 :]) for a in range(len(shape))], dtype=np.int64)


def _filter_group(
    p: NDArray, level: NDArray, v: NDArray, box: tuple[int, ...], scratch: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Bilinear deposit of a group over its box, then one Gaussian filter.

    ``p`` (n, d) positions in pixels relative to the box, ``level`` (d,) the group's width in
    pixels, ``v`` (m, n) weights, ``scratch`` a flat float32 buffer of at least m * prod(box)
    values (reused between groups: fresh image-sized arrays cost as much time in page faults
    as the filtering itself). Returns a (m, *box) view of ``scratch``."""
    d = p.shape[1]
    m = v.shape[0]
    u = p - 0.5  # pixel centres sit at integer u
    i0 = np.floor(u).astype(np.int64)
    f = u - i0
    size = math.prod(box)
    strides = _strides(box)
    hist = scratch[: m * size].reshape(m, size)
    hist[:] = 0.0
    for corner in product((0, 1), repeat=d):
        c = np.array(corner, dtype=bool)
        ii = i0 + c
        w = np.prod(np.where(c, f, 1.0 - f), axis=1)
        ok = np.all((ii >= 0) & (ii < np.array(box)), axis=1)
        flat = ii[ok] @ strides
        for j in range(m):
            np.add.at(hist[j], flat, (w[ok] * v[j, ok]).astype(np.float32))
    hist = hist.reshape(m, *box)
    # Each spot should have variance level^2; the bilinear deposit already adds f (1 - f) per
    # axis (px^2 / 6 on average), so the filter supplies the rest.
    var = level**2 - np.average(f * (1.0 - f), axis=0, weights=np.abs(v[0]) + 1e-300)
    width = np.sqrt(np.maximum(var, 0.0))
    # In place: the 1D passes work through line buffers.
    return ndi.gaussian_filter(
        hist, sigma=(0.0, *width), mode="constant", truncate=TRUNCATE, output=hist
    )


def _splat_group(
    p: NDArray, s: NDArray, v: NDArray, box: tuple[int, ...], radius: NDArray, out: NDArray
) -> None:
    """Add a separable Gaussian patch per entry to ``out`` (m, *box), sampled at pixel centres
    and normalised to one; ``s`` (n, d) widths in pixels, ``radius`` (d,) half-widths."""
    n, d = p.shape
    per = int(np.prod(2 * radius + 1))
    # Sorted along the first axis, each chunk touches a narrow band of rows.
    order = np.argsort(p[:, 0], kind="stable")
    p, s, v = p[order], s[order], v[:, order]
    row_size = math.prod(box[1:])
    strides = _strides(box)
    chunk = max(1, _SPLAT_CHUNK // per)
    for start in range(0, n, chunk):
        sl = slice(start, start + chunk)
        pc, sc = p[sl], s[sl]
        c = pc.shape[0]
        w_all = np.ones((c, 1))
        i_all = np.zeros((c, 1), dtype=np.int64)
        for a in range(d):
            offsets = np.arange(-radius[a], radius[a] + 1)
            pix = np.floor(pc[:, a]).astype(np.int64)[:, None] + offsets
            w = np.exp(-0.5 * ((pix + 0.5 - pc[:, a, None]) / sc[:, a, None]) ** 2)
            w /= w.sum(axis=1, keepdims=True)
            inside = (pix >= 0) & (pix < box[a])
            w = np.where(inside, w, 0.0)  # mass off the image is lost, as for the filter path
            pix = np.clip(pix, 0, box[a] - 1)
            w_all = (w_all[:, :, None] * w[:, None, :]).reshape(c, -1)
            i_all = (i_all[:, :, None] + (pix * strides[a])[:, None, :]).reshape(c, -1)
        flat = i_all.ravel()
        r0 = int(flat.min()) // row_size
        r1 = int(flat.max()) // row_size + 1
        band = (r1 - r0) * row_size
        for j in range(v.shape[0]):
            wj = (w_all * v[j, sl, None]).ravel()
            if band <= 8 * flat.size + 100_000:
                acc = np.bincount(flat - r0 * row_size, weights=wj, minlength=band)
                out[j, r0:r1] += acc.reshape(r1 - r0, *box[1:]).astype(np.float32)
            else:  # a few spots far apart: scattered adds beat a large empty band
                np.add.at(out[j], np.unravel_index(flat, box), wj.astype(np.float32))


def _levels(sig: NDArray, ratio: float) -> tuple[NDArray, NDArray, NDArray]:
    """Split each width between the two neighbouring levels of a geometric grid.

    Returns the grid start ``s0`` (d,), the lower level index ``k`` (n, d) and the weight of
    the lower level ``w`` (n, d), chosen so that ``w lo^2 + (1 - w) hi^2 = sig^2``: each spot
    becomes a two-Gaussian mixture per axis with its own variance."""
    s0 = sig.min(axis=0)
    k = np.floor(np.log(sig / s0) / math.log(ratio) + 1e-12).astype(np.int64)
    lo = s0 * ratio**k
    hi = lo * ratio
    w = np.clip((hi**2 - sig**2) / (hi**2 - lo**2), 0.0, 1.0)
    return s0, k, w


def _accumulate(
    pos: NDArray,
    sig: NDArray,
    shape: tuple[int, ...],
    values: NDArray,
    *,
    method: str = "auto",
    ratio: float = SIGMA_BIN_RATIO,
) -> NDArray[np.float32]:
    """Sum of normalised Gaussians on a pixel grid.

    Parameters
    ----------
    pos : ndarray, shape (n, d)
        Positions in pixel units along the array axes (pixel ``i`` spans ``[i, i + 1)``).
    sig : ndarray, shape (n, d)
        Widths (standard deviations) in pixels, all positive.
    shape : tuple of d ints
        Output shape.
    values : ndarray, shape (m, n)
        Weights; output ``j`` is the sum of spots weighted by ``values[j]``.
    method : {"auto", "filter", "splat"}
        Force one method (for tests); ``"auto"`` picks the cheaper per width level.
    ratio : float
        Ratio of neighbouring width levels per axis.

    Returns
    -------
    ndarray, shape (m, *shape), float32
    """
    d = len(shape)
    out = np.zeros((values.shape[0], *shape), dtype=np.float32)
    radius_all = np.ceil(TRUNCATE * sig).astype(np.int64) + 1
    # Spots entirely off the image cost time and stretch their level's box: drop them.
    keep = np.all((pos > -radius_all) & (pos < np.array(shape) + radius_all), axis=1)
    pos, sig, values = pos[keep], sig[keep], values[:, keep]
    if pos.shape[0] == 0:
        return out
    s0, k, w_lo = _levels(sig, ratio)
    # Entries: every localization on each combination of its lower/upper level per axis.
    ent_idx, ent_key, ent_w = [], [], []
    span = k.max(axis=0) + 2
    for corner in product((0, 1), repeat=d):
        c = np.array(corner)
        w = np.prod(np.where(c.astype(bool), 1.0 - w_lo, w_lo), axis=1)
        sel = np.flatnonzero(w > 1e-9)
        key = np.zeros(sel.size, dtype=np.int64)
        for a in range(d):
            key = key * int(span[a]) + k[sel, a] + c[a]
        ent_idx.append(sel)
        ent_key.append(key)
        ent_w.append(w[sel])
    idx_all = np.concatenate(ent_idx)
    key_all = np.concatenate(ent_key)
    w_all = np.concatenate(ent_w)
    order = np.argsort(key_all, kind="stable")
    cuts = np.flatnonzero(np.diff(key_all[order])) + 1
    scratch: NDArray[np.float32] | None = None
    for grp in np.split(order, cuts):
        key = int(key_all[grp[0]])
        lev = np.empty(d, dtype=np.int64)
        for a in range(d - 1, -1, -1):
            key, lev[a] = divmod(key, int(span[a]))
        level = s0 * ratio**lev
        idx = idx_all[grp]
        p = pos[idx]
        v = values[:, idx] * w_all[grp]
        radius = np.ceil(TRUNCATE * level).astype(np.int64)
        lo = np.maximum(np.floor(p.min(axis=0)).astype(np.int64) - radius - 1, 0)
        hi = np.minimum(np.floor(p.max(axis=0)).astype(np.int64) + radius + 2, shape)
        if np.any(hi <= lo):
            continue
        box = tuple(int(b) for b in hi - lo)
        taps = 2 * radius + 1
        # Measured costs (ns) of the two methods, per output channel.
        cost_filter = math.prod(box) * (6.0 + 0.6 * int(taps.sum())) + 60.0 * len(idx)
        cost_splat = 22.0 * len(idx) * int(np.prod(taps))
        use = method if method != "auto" else ("splat" if cost_splat < cost_filter else "filter")
        view = out[(slice(None), *(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True)))]
        if use == "filter":
            if scratch is None:
                scratch = np.empty(out.size, dtype=np.float32)
            view += _filter_group(p - lo, level, v, box, scratch)
        else:
            widths = np.broadcast_to(level, p.shape)
            _splat_group(p - lo, widths, v, box, radius, view)
    return out


# -- 2D rendering ------------------------------------------------------------------------------


def render_gaussian(
    locs: pd.DataFrame,
    *,
    px_nm: float = 10.0,
    projection: str = "xy",
    extent: tuple[float, float, float, float] | None = None,
    sigma_min_nm: float | None = None,
    default_sigma_nm: float = 15.0,
) -> Rendered:
    """Render localizations as Gaussians of their own uncertainties.

    Parameters
    ----------
    locs : DataFrame
        Localization table; needs ``x_nm``, ``y_nm`` (and ``z_nm`` for ``xz``/``yz`` and for the
        depth image). Widths from ``sigma_x_nm``, ``sigma_y_nm``, ``sigma_z_nm`` where present
        and positive. Rows with non-finite coordinates are skipped.
    px_nm : float
        Pixel size (nm), both axes.
    projection : {"xy", "xz", "yz"}
        Image plane; the horizontal axis is the first letter.
    extent : (h0, h1, v0, v1), optional
        Image edges (nm) along the horizontal and vertical axes; the far edges move up to a whole
        number of pixels. Default: the data bounds padded by four (95th-percentile) widths,
        snapped to multiples of ``px_nm``. Give one extent to several calls to share a frame.
    sigma_min_nm : float, optional
        Smallest spot width (nm); default ``px_nm / 2``.
    default_sigma_nm : float
        Lateral width (nm) where the table has none; the axial one is 2.5 times this.

    Returns
    -------
    Rendered
        ``density`` (rows, cols) in localizations per pixel; ``depth`` the density-weighted
        mean z (nm) for ``xy`` when the table has ``z_nm``, else None.

    Raises
    ------
    ValueError
        Empty table, missing columns, non-positive sizes, a bad extent or projection, or an
        image over :data:`MAX_PIXELS`.
    """
    if projection not in _PROJECTIONS:
        raise ValueError(f"projection must be one of {sorted(_PROJECTIONS)}, got {projection!r}")
    px = _positive(px_nm, "px_nm")
    _positive(default_sigma_nm, "default_sigma_nm")
    floor = px / 2 if sigma_min_nm is None else _positive(sigma_min_nm, "sigma_min_nm")
    h, v = _PROJECTIONS[projection]
    _check_table(locs, (h, v))
    with_depth = projection == "xy" and "z_nm" in locs.columns
    pos, ok = _finite_rows(locs, (h, v))
    sig = _widths(locs, (h, v), ok, default_sigma_nm, (floor, floor))
    if extent is not None and len(extent) != 4:
        raise ValueError(f"extent must be (h0, h1, v0, v1) in nm, got {extent!r}")
    h0, nh = _axis_grid(pos[:, 0], sig[:, 0], px, None if extent is None else extent[:2], h)
    v0, nv = _axis_grid(pos[:, 1], sig[:, 1], px, None if extent is None else extent[2:], v)
    _check_size((nv, nh), f"{projection} image")

    values = [np.ones(pos.shape[0])]
    if with_depth:
        z = locs["z_nm"].to_numpy(dtype=np.float64)[ok]
        with_depth = bool(np.isfinite(z).any())
        if with_depth:
            good = np.isfinite(z)
            values = [np.ones(pos.shape[0]), np.where(good, z, 0.0)]
            if not good.all():
                # A localization without a depth counts in the density, not in the mean depth.
                values.append(good.astype(float))
    grid_pos = np.column_stack([(pos[:, 1] - v0) / px, (pos[:, 0] - h0) / px])
    grid_sig = np.column_stack([sig[:, 1], sig[:, 0]]) / px
    img = _accumulate(grid_pos, grid_sig, (nv, nh), np.array(values))
    density = img[0]
    depth = None
    if with_depth:
        weight = img[2] if img.shape[0] > 2 else density
        floor_d = _DEPTH_FLOOR * max(float(weight.max()), 1e-30)
        with np.errstate(invalid="ignore", divide="ignore"):
            depth = np.where(weight > floor_d, img[1] / weight, np.nan).astype(np.float32)
    log.debug("rendered %d localizations %s on %d x %d px", pos.shape[0], projection, nv, nh)
    return Rendered(
        density=density,
        depth=depth,
        extent=(h0, h0 + nh * px, v0, v0 + nv * px),
        px_nm=px,
        projection=projection,
        axes=(h, v),
        n_locs=int(pos.shape[0]),
    )


def intensity_scale(rendered: Rendered | NDArray, saturate: float = 99.5) -> float:
    """The density that maps to full brightness: the ``saturate`` percentile of the non-zero
    pixels (those above 1e-6 of the maximum, so that float round-off does not count).

    Parameters
    ----------
    rendered : Rendered or ndarray, shape (rows, cols)
        An image or its density.
    saturate : float
        Percentile in (0, 100].

    Returns
    -------
    float
        Density (localizations per pixel); 1.0 for an empty image.
    """
    s = float(saturate)
    if not (0 < s <= 100):
        raise ValueError(f"saturate must be a percentile in (0, 100], got {saturate!r}")
    d = np.asarray(rendered.density if isinstance(rendered, Rendered) else rendered)
    top = float(d.max()) if d.size else 0.0
    if not top > 0:
        return 1.0
    return float(np.percentile(d[d > _DEPTH_FLOOR * top], s))


def to_rgb(
    rendered: Rendered,
    *,
    z_range: tuple[float, float] | None = None,
    cmap: str = "turbo",
    gamma: float = 1.0,
    saturate: float = 99.5,
    vmax: float | None = None,
) -> NDArray[np.float32]:
    """Colour image: hue from depth, brightness from density.

    Brightness is ``clip(density / vmax, 0, 1) ** gamma``, one rule for every projection.
    Hue: the mean depth for ``xy`` (grey when the table had no z); for ``xz`` and ``yz`` the z
    of each row, so that the colours match the ``xy`` image's.

    Parameters
    ----------
    rendered : Rendered
        From :func:`render_gaussian`.
    z_range : (float, float), optional
        Depths (nm) at the ends of the colour map; default the 1st..99th percentile of the
        depth over pixels brighter than 5 % of ``vmax`` (``xy``) or the image's z extent.
    cmap : str
        matplotlib colour map name.
    gamma : float
        Brightness exponent (> 0); below 1 lifts faint structure.
    saturate : float
        Percentile used for ``vmax`` when it is not given (see :func:`intensity_scale`).
    vmax : float, optional
        Density at full brightness; pass the same value to several images to compare them.

    Returns
    -------
    ndarray, shape (rows, cols, 3), float32
        RGB in [0, 1].
    """
    from matplotlib import colormaps

    g = float(gamma)
    if not (math.isfinite(g) and g > 0):
        raise ValueError(f"gamma must be a positive number, got {gamma!r}")
    top = intensity_scale(rendered, saturate) if vmax is None else _positive(vmax, "vmax")
    dens = rendered.density
    bright = np.clip(dens / top, 0.0, 1.0) ** g
    if rendered.projection != "xy":
        _, _, v0, v1 = rendered.extent
        rows = dens.shape[0]
        zc = v0 + (np.arange(rows) + 0.5) * rendered.px_nm
        hue = np.broadcast_to(zc[:, None], dens.shape)
        lo, hi = (v0, v1) if z_range is None else z_range
    elif rendered.depth is not None:
        hue = rendered.depth
        if z_range is None:
            sel = np.isfinite(hue) & (dens > 0.05 * top)
            vals = hue[sel] if sel.any() else hue[np.isfinite(hue)]
            lo, hi = np.percentile(vals, [1, 99]) if vals.size else (0.0, 1.0)
        else:
            lo, hi = z_range
    else:
        return np.repeat(bright[..., None], 3, axis=2).astype(np.float32)
    lo, hi = float(lo), float(hi)
    if not hi > lo:
        hi = lo + 1.0
    t = np.clip((np.nan_to_num(hue, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    rgb = colormaps[cmap](t)[..., :3]
    return (rgb * bright[..., None]).astype(np.float32)


# -- 3D rendering ------------------------------------------------------------------------------


def render_volume(
    locs: pd.DataFrame,
    *,
    px_nm: float = 20.0,
    pz_nm: float = 50.0,
    extent: tuple[float, float, float, float] | None = None,
    z_range: tuple[float, float] | None = None,
    default_sigma_nm: float = 15.0,
) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Render localizations as 3D Gaussians of their own uncertainties.

    Widths follow :func:`render_gaussian` (floors: half a voxel along each axis).

    Parameters
    ----------
    locs : DataFrame
        Needs ``x_nm``, ``y_nm``, ``z_nm``.
    px_nm, pz_nm : float
        Lateral and axial voxel size (nm).
    extent : (x0, x1, y0, y1), optional
        Lateral edges (nm); default the data bounds padded as in :func:`render_gaussian`.
    z_range : (z0, z1), optional
        Axial edges (nm); default the data range padded likewise.
    default_sigma_nm : float
        Lateral width (nm) where the table has none; 2.5 times this axially.

    Returns
    -------
    volume : ndarray, shape (nz, ny, nx), float32
        Localizations per voxel; slice ``k`` spans ``z0 + [k, k + 1) * pz_nm``.
    meta : dict
        ``extent_nm`` (x0, x1, y0, y1, z0, z1), ``px_nm``, ``pz_nm``, ``z0_nm``, ``axes``
        ("z", "y", "x"), ``n_locs``.
    """
    px = _positive(px_nm, "px_nm")
    pz = _positive(pz_nm, "pz_nm")
    _positive(default_sigma_nm, "default_sigma_nm")
    axes = ("x", "y", "z")
    _check_table(locs, axes)
    pos, ok = _finite_rows(locs, axes)
    sig = _widths(locs, axes, ok, default_sigma_nm, (px / 2, px / 2, pz / 2))
    if extent is not None and len(extent) != 4:
        raise ValueError(f"extent must be (x0, x1, y0, y1) in nm, got {extent!r}")
    x0, nx = _axis_grid(pos[:, 0], sig[:, 0], px, None if extent is None else extent[:2], "x")
    y0, ny = _axis_grid(pos[:, 1], sig[:, 1], px, None if extent is None else extent[2:], "y")
    if z_range is not None and len(z_range) != 2:
        raise ValueError(f"z_range must be (z0, z1) in nm, got {z_range!r}")
    z0, nz = _axis_grid(pos[:, 2], sig[:, 2], pz, z_range, "z")
    _check_size((nz, ny, nx), "volume")
    grid_pos = np.column_stack(
        [(pos[:, 2] - z0) / pz, (pos[:, 1] - y0) / px, (pos[:, 0] - x0) / px]
    )
    grid_sig = sig[:, ::-1] / np.array([pz, px, px])
    vol = _accumulate(grid_pos, grid_sig, (nz, ny, nx), np.ones((1, pos.shape[0])))[0]
    meta = {
        "extent_nm": (x0, x0 + nx * px, y0, y0 + ny * px, z0, z0 + nz * pz),
        "px_nm": px,
        "pz_nm": pz,
        "z0_nm": z0,
        "axes": ("z", "y", "x"),
        "n_locs": int(pos.shape[0]),
    }
    return vol, meta


def write_volume_tiff(
    path: str | Path, volume: NDArray, px_nm: float, pz_nm: float, z0_nm: float = 0.0
) -> Path:
    """Write a volume as an ImageJ TIFF stack (float32), atomically.

    The lateral resolution is stored in pixels per um, the slice spacing in um and the unit as
    ``um``; ``zorigin`` (slices) puts slice ``k``'s centre at ``z0_nm + (k + 0.5) pz_nm`` in
    ImageJ's calibrated z, and ``z0_nm`` is kept as an extra key.

    Parameters
    ----------
    path : str or Path
        Destination ``.tif``; its folder must exist.
    volume : ndarray, shape (nz, ny, nx)
        From :func:`render_volume`.
    px_nm, pz_nm : float
        Lateral and axial voxel size (nm).
    z0_nm : float
        z (nm) of the lower edge of slice 0.

    Returns
    -------
    Path
    """
    import tifffile

    from .io.atomic import atomic_path

    px = _positive(px_nm, "px_nm")
    pz = _positive(pz_nm, "pz_nm")
    vol = np.asarray(volume)
    if vol.ndim != 3 or min(vol.shape) == 0:
        raise ValueError(f"volume must have shape (nz, ny, nx) with no empty axis, got {vol.shape}")
    z0 = float(z0_nm)
    if not math.isfinite(z0):
        raise ValueError(f"z0_nm must be a finite number of nm, got {z0_nm!r}")
    meta = {
        "axes": "ZYX",
        "spacing": pz / 1000.0,
        "unit": "um",
        "zorigin": -(z0 / pz) - 0.5,
        "z0_nm": z0,
    }
    with atomic_path(path) as tmp:
        tifffile.imwrite(
            tmp,
            vol.astype(np.float32),
            imagej=True,
            resolution=(1000.0 / px, 1000.0 / px),
            metadata=meta,
        )
    log.info("wrote %s: %d x %d x %d voxels", path, *vol.shape)
    return Path(path)


# -- Fourier ring correlation ------------------------------------------------------------------


def frc(
    locs: pd.DataFrame,
    *,
    px_nm: float = 5.0,
    split: str = "blocks",
    n_blocks: int = 20,
    seed: int = 0,
    extent: tuple[float, float, float, float] | None = None,
    smooth_rings: float | None = None,
) -> FRCResult:
    """Fourier ring correlation resolution of a 2D (xy) localization set.

    The localizations are split in two halves, each is binned on the same grid (counts per
    ``px_nm`` pixel), and the FRC of the two images is computed over rings one frequency step
    wide (``1 / (max(rows, cols) px_nm)``) from the first ring up to Nyquist. The curve is
    smoothed with a Gaussian over ``smooth_rings`` rings; the resolution is ``1 / q`` where the
    smoothed curve first falls below 1/7, linearly interpolated between rings.

    Splits: ``"blocks"`` (default) cuts the frame range into ``n_blocks`` equal blocks of
    consecutive frames and gives even blocks to one half, odd to the other, so that a
    molecule's repeated localizations in consecutive frames stay together (splitting them
    correlates the halves' noise and makes the resolution look too good). ``"random"`` assigns
    localizations at random (balanced, seeded) and is optimistic for such data.

    A set with no structure finer than the field (e.g. uniform random points) correlates only
    at the lowest frequencies, where the two halves share the field's outline; its curve drops
    below 1/7 within the first few rings and the "resolution" is a sizeable fraction of the
    field. When the curve is below 1/7 already at the first ring, or never falls below it,
    ``resolution_nm`` is NaN and ``warning`` says why.

    Parameters
    ----------
    locs : DataFrame
        Needs ``x_nm``, ``y_nm``, and ``frame`` for ``split="blocks"``.
    px_nm : float
        Bin size (nm); should be a few times finer than the resolution.
    split : {"blocks", "random"}
    n_blocks : int
        Number of frame blocks (at least 2).
    seed : int
        Seed of the random split.
    extent : (x0, x1, y0, y1), optional
        Image edges (nm); default the data bounds plus two pixels.
    smooth_rings : float, optional
        Standard deviation (rings) of the smoothing; default ``max(1, n_rings / 100)``.

    Returns
    -------
    FRCResult
    """
    from scipy import fft

    px = _positive(px_nm, "px_nm")
    if split not in ("blocks", "random"):
        raise ValueError(f"split must be 'blocks' or 'random', got {split!r}")
    _check_table(locs, ("x", "y"))
    pos, ok = _finite_rows(locs, ("x", "y"))
    n = pos.shape[0]
    if split == "blocks":
        if int(n_blocks) < 2:
            raise ValueError(f"n_blocks must be at least 2, got {n_blocks!r}")
        if "frame" not in locs.columns:
            raise ValueError("split='blocks' needs a 'frame' column; use split='random'")
        frames = locs["frame"].to_numpy()[ok].astype(np.int64)
        f0, f1 = int(frames.min()), int(frames.max())
        # Fewer frames than blocks: one block per frame (else short tables fall in one half).
        nb = min(int(n_blocks), f1 - f0 + 1)
        block = (frames - f0) * nb // (f1 - f0 + 1)
        half = (block % 2).astype(bool)
    else:
        half = np.random.default_rng(seed).permutation(n) % 2 == 1
    counts = (int((~half).sum()), int(half.sum()))
    if min(counts) == 0:
        raise ValueError(
            f"the {split} split left the halves with {counts[0]} and {counts[1]} localizations; "
            "FRC needs both (frames span "
            + (f"{f0}..{f1}" if split == "blocks" else "n/a")
            + "; try split='random')"
        )
    if extent is None:
        lo, hi = pos.min(axis=0) - 2 * px, pos.max(axis=0) + 2 * px
        x0 = math.floor(lo[0] / px) * px
        y0 = math.floor(lo[1] / px) * px
        nx = max(2, math.ceil((hi[0] - x0) / px))
        ny = max(2, math.ceil((hi[1] - y0) / px))
    else:
        if len(extent) != 4:
            raise ValueError(f"extent must be (x0, x1, y0, y1) in nm, got {extent!r}")
        x0, nx = _axis_grid(pos[:, 0], np.zeros(1), px, extent[:2], "x")
        y0, ny = _axis_grid(pos[:, 1], np.zeros(1), px, extent[2:], "y")
    # Zero padding to fast FFT sizes changes nothing: both images are zero there.
    shape = (fft.next_fast_len(ny, real=True), fft.next_fast_len(nx, real=True))
    _check_size(shape, "FRC image")
    col = np.floor((pos[:, 0] - x0) / px).astype(np.int64)
    row = np.floor((pos[:, 1] - y0) / px).astype(np.int64)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    if not inside.all():
        log.info("FRC: %d localizations outside the extent are ignored", (~inside).sum())
    flat = row * shape[1] + col
    spectra = []
    for sel in (~half & inside, half & inside):
        img = np.zeros(shape[0] * shape[1], dtype=np.float32)
        np.add.at(img, flat[sel], 1.0)
        spectra.append(fft.rfft2(img.reshape(shape), workers=-1))
        del img
    qy = np.fft.fftfreq(shape[0], d=px)
    qx = np.fft.rfftfreq(shape[1], d=px)
    dq = 1.0 / (max(shape) * px)
    n_rings = math.floor(0.5 / px / dq)
    # rfft2 holds half the plane: every column but the first (and the Nyquist one, for even
    # widths) stands for itself and its mirror image.
    mult = np.full(qx.size, 2.0)
    mult[0] = 1.0
    if shape[1] % 2 == 0:
        mult[-1] = 1.0
    sums = np.zeros((3, n_rings + 1))
    step = max(1, 4_000_000 // qx.size)  # row blocks bound the memory of the ring sums
    for r0 in range(0, shape[0], step):
        a, b = spectra[0][r0 : r0 + step], spectra[1][r0 : r0 + step]
        ring = np.rint(np.hypot(qy[r0 : r0 + step, None], qx[None, :]) / dq).astype(np.int64)
        keep = ring <= n_rings
        r = ring[keep]
        m = np.broadcast_to(mult, ring.shape)[keep]
        a, b = a[keep], b[keep]
        for j, prod_ in enumerate(
            (a.real * b.real + a.imag * b.imag, a.real**2 + a.imag**2, b.real**2 + b.imag**2)
        ):
            sums[j] += np.bincount(r, weights=m * prod_, minlength=n_rings + 1)
    num, p1, p2 = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        raw = (num / np.sqrt(p1 * p2))[1:]
    raw = np.nan_to_num(raw, nan=0.0)
    freq = np.arange(1, n_rings + 1) * dq
    width = max(1.0, n_rings / 100.0) if smooth_rings is None else float(smooth_rings)
    curve = ndi.gaussian_filter1d(raw, width, mode="nearest") if width > 0 else raw.copy()
    thr = FRC_THRESHOLD
    below = np.flatnonzero(curve < thr)
    warning = ""
    if below.size == 0:
        warning = (
            f"the FRC never falls below 1/7 up to the Nyquist frequency 1/{2 * px:g} nm: the "
            "resolution is finer than two bins; use a smaller px_nm"
        )
        res = float("nan")
    elif below[0] == 0:
        warning = (
            f"the FRC is below 1/7 already at the lowest frequency (1/{1 / freq[0]:.0f} nm): "
            "the two halves share no structure"
        )
        res = float("nan")
    else:
        k = int(below[0])
        c0, c1 = curve[k - 1], curve[k]
        q = freq[k - 1] + (c0 - thr) / (c0 - c1) * (freq[k] - freq[k - 1])
        res = float(1.0 / q)
    if warning:
        log.warning("FRC: %s", warning)
    return FRCResult(
        frequency=freq,
        curve=curve,
        curve_raw=raw,
        resolution_nm=res,
        threshold=thr,
        warning=warning,
        n_halves=counts,
        px_nm=px,
        split=split,
        extra={"extent_nm": (x0, x0 + nx * px, y0, y0 + ny * px), "smooth_rings": width},
    )


# -- figures -----------------------------------------------------------------------------------


def plot_frc(result: FRCResult, path: str | Path) -> Path:
    """Plot an FRC curve (raw and smoothed) with the 1/7 threshold and the resolution.

    Parameters
    ----------
    result : FRCResult
        From :func:`frc`.
    path : str or Path
        Output image (e.g. ``.png``), written atomically.

    Returns
    -------
    Path
    """
    from matplotlib.figure import Figure

    from .plotting import save_figure

    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    ax = fig.subplots()
    q = result.frequency * 1000.0  # 1/um reads better than 1/nm
    ax.plot(q, result.curve_raw, color="0.7", lw=0.8, label="FRC")
    ax.plot(q, result.curve, color="tab:blue", lw=1.6, label="smoothed")
    ax.axhline(result.threshold, color="tab:red", ls="--", lw=1.0, label="1/7")
    if math.isfinite(result.resolution_nm):
        ax.axvline(1000.0 / result.resolution_nm, color="tab:green", lw=1.0)
        title = f"FRC resolution {result.resolution_nm:.1f} nm"
    else:
        title = "FRC resolution not determined"
        ax.text(0.02, 0.04, result.warning, transform=ax.transAxes, fontsize=7, wrap=True)
    ax.set_xlabel("spatial frequency (1/µm)")
    ax.set_ylabel("FRC")
    ax.set_ylim(-0.2, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    n0, n1 = result.n_halves
    ax.set_title(f"{title}  ({result.split} split, {n0:,} / {n1:,} locs)", fontsize=10)
    return save_figure(fig, path)


def _nice_up(value: float) -> float:
    """Smallest 1, 2, 2.5 or 5 times a power of ten at or above ``value``."""
    exp = 10.0 ** math.floor(math.log10(value))
    return next(m * exp for m in (1, 2, 2.5, 5, 10) if m * exp >= value * (1 - 1e-9))


def _auto_px(locs: pd.DataFrame, span_nm: float) -> float:
    """Half the median lateral uncertainty, coarsened so that the image is at most ~2000 px."""
    cols = [locs[c].to_numpy(dtype=float) for c in ("sigma_x_nm", "sigma_y_nm") if c in locs]
    sig = np.concatenate(cols) if cols else np.zeros(0)
    sig = sig[np.isfinite(sig) & (sig > 0)]
    med = float(np.median(sig)) if sig.size else 15.0
    return _nice_up(max(med / 2.0, span_nm / 2000.0))


def _bar(ax, width: float, height: float, x0: float, y_bottom: float, scale: float) -> None:
    """White scale bar about a fifth of the panel wide, bottom left; axes in ``scale`` nm."""
    length_nm = _nice_up(0.2 * width * scale) if width > 0 else 1.0
    if length_nm > 0.3 * width * scale:
        length_nm /= 2
    label = f"{length_nm / 1000:g} µm" if length_nm >= 1000 else f"{length_nm:g} nm"
    xs = x0 + 0.05 * width
    ys = y_bottom - 0.06 * height
    ax.plot([xs, xs + length_nm / scale], [ys, ys], color="white", lw=3, solid_capstyle="butt")
    ax.text(
        xs + length_nm / scale / 2,
        ys - 0.02 * height,
        label,
        color="white",
        ha="center",
        va="bottom",
        fontsize=9,
    )


def plot_projections(
    locs: pd.DataFrame,
    path: str | Path,
    *,
    px_nm: float | None = None,
    z_range: tuple[float, float] | None = None,
    title: str = "",
    truth: pd.DataFrame | None = None,
) -> Path:
    """Figure of the xy render coloured by depth with its xz and yz side projections.

    The xy panel (x, y in µm, y down) has a white scale bar and a colour bar "z (nm)"; the yz
    projection stands at its right (z to the right) and the xz one below it (z up), on a black
    background. Every panel is scaled by the same rule (:func:`intensity_scale`, 99.5th
    percentile). The side panels are stretched along z to at least a quarter of the field so
    that they stay readable. A table without ``z_nm`` gives the xy panel alone, in grey.
    With ``truth`` the ground truth follows at the right, rendered on the same grid with the
    localizations' median uncertainties as spot sizes.

    Parameters
    ----------
    locs : DataFrame
        Localization table.
    path : str or Path
        Output image, written atomically.
    px_nm : float, optional
        Render pixel (nm); default half the median lateral uncertainty (15 nm when there is
        none), coarsened to a 1-2-2.5-5 value so that the image is at most about 2000 px.
    z_range : (float, float), optional
        Colour scale and side-panel depth range (nm); default the 0.5..99.5th percentile of z.
    title : str
        Figure title.
    truth : DataFrame, optional
        Ground-truth positions.

    Returns
    -------
    Path
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from .plotting import save_figure

    _check_table(locs, ("x", "y"))
    tables = [("localizations", locs)]
    if truth is not None:
        _check_table(truth, ("x", "y"))
        tables.append(("ground truth", truth))
    is3d = all(
        "z_nm" in t.columns and np.isfinite(t["z_nm"].to_numpy(float)).any() for _, t in tables
    )
    both = pd.concat([t[["x_nm", "y_nm"]] for _, t in tables])
    span = float(max(np.ptp(both["x_nm"].dropna()), np.ptp(both["y_nm"].dropna()), 1.0))
    px = _auto_px(locs, span) if px_nm is None else _positive(px_nm, "px_nm")
    medians = {}
    for a in ("x", "y", "z"):
        col = _SIG[a]
        vals = locs[col].to_numpy(float) if col in locs else np.zeros(0)
        vals = vals[np.isfinite(vals) & (vals > 0)]
        medians[a] = float(np.median(vals)) if vals.size else 15.0 * (2.5 if a == "z" else 1.0)
    if truth is not None:  # drawn with the localizations' typical spot size
        tables[1] = ("ground truth", truth.assign(**{_SIG[a]: medians[a] for a in "xyz"}))
    # One frame for every panel: the union of the tables' default extents.
    exts = [_default_extent(t, ("x", "y"), px) for _, t in tables]
    ext = (
        min(e[0] for e in exts),
        max(e[1] for e in exts),
        min(e[2] for e in exts),
        max(e[3] for e in exts),
    )
    if z_range is None and is3d:
        z = locs["z_nm"].to_numpy(float)
        z = z[np.isfinite(z)]
        z_range = tuple(float(v) for v in np.percentile(z, [0.5, 99.5]))
        if not z_range[1] > z_range[0]:
            z_range = (z_range[0] - 50.0, z_range[0] + 50.0)
    if z_range is not None and not float(z_range[1]) > float(z_range[0]):
        raise ValueError(f"z_range must run from low to high nm, got {z_range!r}")

    panels = []
    for label, t in tables:
        xy = render_gaussian(t, px_nm=px, extent=ext)
        side = None
        if is3d:
            zpad = 3.0 * medians["z"]
            zext = (z_range[0] - zpad, z_range[1] + zpad)
            xz = render_gaussian(t, px_nm=px, projection="xz", extent=(*ext[:2], *zext))
            yz = render_gaussian(t, px_nm=px, projection="yz", extent=(*ext[2:], *zext))
            side = (xz, yz)
        panels.append((label, xy, side))

    w_nm, h_nm = ext[1] - ext[0], ext[3] - ext[2]
    s_nm = 0.0
    if is3d:
        s_nm = max(panels[0][2][0].extent[3] - panels[0][2][0].extent[2], 0.25 * max(w_nm, h_nm))
    # Axes placed by hand (inches) so that the xy panel keeps equal scales in x and y and the
    # side panels line up with it exactly.
    k = 6.0 / max(w_nm + s_nm, h_nm + s_nm)  # inches per nm
    w_in, h_in, s_in = w_nm * k, h_nm * k, s_nm * k
    gap, left, bottom, top, between = 0.12, 0.75, 0.6, 0.55, 0.95
    block = w_in + (gap + s_in if is3d else 0.0)
    fig_w = left + len(panels) * block + (len(panels) - 1) * between + (1.1 if is3d else 0.3)
    fig_h = bottom + (s_in + gap if is3d else 0.0) + h_in + top + (0.3 if title else 0.0)
    fig = Figure(figsize=(fig_w, fig_h), facecolor="black")

    def rect(x: float, y: float, w: float, h: float) -> list[float]:
        return [x / fig_w, y / fig_h, w / fig_w, h / fig_h]

    cmap = "turbo"
    um = (ext[0] / 1000, ext[1] / 1000, ext[3] / 1000, ext[2] / 1000)
    y_xy = bottom + (s_in + gap if is3d else 0.0)

    def style(ax, xlabel: str = "", ylabel: str = "") -> None:
        ax.set_facecolor("black")
        ax.tick_params(colors="white", labelsize=8)
        for sp in ax.spines.values():
            sp.set_color("0.5")
        ax.set_xlabel(xlabel, color="white")
        ax.set_ylabel(ylabel, color="white")

    for i, (label, xy, side) in enumerate(panels):
        x_xy = left + i * (block + between)
        ax = fig.add_axes(rect(x_xy, y_xy, w_in, h_in))
        ax.imshow(
            to_rgb(xy, z_range=z_range, cmap=cmap),
            extent=um,
            interpolation="nearest",
            aspect="auto",
        )
        style(ax, "" if is3d else "x (µm)", "y (µm)")
        _bar(ax, um[1] - um[0], um[2] - um[3], um[0], um[2], 1000.0)
        ax.set_title(f"{label} ({xy.n_locs:,}, {px:g} nm px)", color="white", fontsize=10)
        if side is None:
            continue
        xz, yz = side
        zl, zh = xz.extent[2], xz.extent[3]
        ax_xz = fig.add_axes(rect(x_xy, bottom, w_in, s_in), sharex=ax)
        ax_xz.imshow(
            to_rgb(xz, z_range=z_range, cmap=cmap),
            origin="lower",
            extent=(um[0], um[1], zl, zh),
            interpolation="nearest",
            aspect="auto",
        )
        style(ax_xz, "x (µm)", "z (nm)")
        ax_yz = fig.add_axes(rect(x_xy + w_in + gap, y_xy, s_in, h_in), sharey=ax)
        ax_yz.imshow(
            to_rgb(yz, z_range=z_range, cmap=cmap).transpose(1, 0, 2),
            origin="upper",
            extent=(zl, zh, um[2], um[3]),
            interpolation="nearest",
            aspect="auto",
        )
        style(ax_yz, "z (nm)")
        ax_yz.tick_params(labelleft=False)
        ax.tick_params(labelbottom=False)
    if is3d:
        x_cb = left + len(panels) * block + (len(panels) - 1) * between + 0.15
        cax = fig.add_axes(rect(x_cb, y_xy, 0.18, h_in))
        sm = ScalarMappable(norm=Normalize(*z_range), cmap=colormaps[cmap])
        cb = fig.colorbar(sm, cax=cax)
        cb.set_label("z (nm)", color="white")
        cb.ax.tick_params(colors="white", labelsize=8)
        cb.outline.set_edgecolor("0.5")
    if title:
        fig.suptitle(title, color="white", fontsize=11, y=1 - 0.12 / fig_h, va="top")
    return save_figure(fig, path, dpi=150)
