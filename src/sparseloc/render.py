"""Super-resolution rendering of localization tables.

Rendering
    Every localization is drawn as a normalised Gaussian whose widths are its own uncertainties
    (``sigma_x_nm``, ``sigma_y_nm``, ``sigma_z_nm``), never narrower than a floor
    (``sigma_min_nm``, default half a render pixel, so no spot falls between pixels). Each spot
    integrates to one: images count localizations (per pixel or voxel), they are not weighted by
    photons. Missing, NaN or non-positive uncertainties (``localize`` writes NaN for flagged
    fits) are drawn at ``default_sigma_nm`` (lateral, 15 nm) and 2.5 times that axially.

Memory
    The image is sized by the positions and the pixel size, never by the widths: widths wider
    than the data's range do not pad the extent (:func:`~sparseloc.render_grid.axis_grid`) and
    spots wider than the image are left out (:mod:`sparseloc.render_accumulate`).
    Which rows to draw (flag "ok" by default, finite coordinates) is the caller's choice, by
    the rule of :func:`sparseloc.postprocess.select_usable`.

    Spots of similar widths are drawn together (:mod:`sparseloc.render_accumulate`), each
    localization shared between the two width levels around its own (ratio
    :data:`SIGMA_BIN_RATIO`) so that it keeps its mass, centroid and variance per axis.
    Spots are cut at :data:`TRUNCATE` standard deviations; mass that falls outside the image is
    lost. Images larger than :data:`MAX_PIXELS` pixels are refused.

Resolution
    :func:`frc` (Fourier ring correlation, :mod:`sparseloc.frc`) is re-exported here with
    :class:`FRCResult`, :func:`plot_frc` and :data:`FRC_THRESHOLD`.

Coordinates follow the localization tables: nm, ``x`` to the right, ``y`` down, the outer corner
of pixel (0, 0) at the origin of the extent. A 2D image's ``extent`` is ``(h0, h1, v0, v1)``:
the nm positions of its outer edges along its horizontal (columns) and vertical (rows) axes;
row 0 lies at ``v0``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .frc import FRC_THRESHOLD, FRCResult, frc, frc_report, plot_frc
from .render_accumulate import SIGMA_BIN_RATIO
from .render_accumulate import accumulate as _accumulate
from .render_grid import AXIAL_DEFAULT_FACTOR as AXIAL_DEFAULT_FACTOR  # public name, kept here
from .render_grid import (
    MAX_PIXELS,
    SIGMA_COLUMNS,
    TRUNCATE,
    axis_grid,
    check_size,
    check_table,
    finite_rows,
    positive_nm,
    widths,
)

__all__ = [
    "DEPTH_CMAP",
    "FRC_THRESHOLD",
    "MAX_PIXELS",
    "SIGMA_BIN_RATIO",
    "TRUNCATE",
    "FRCResult",
    "Projections",
    "Rendered",
    "frc",
    "frc_report",
    "intensity_scale",
    "plot_frc",
    "plot_projections",
    "render_gaussian",
    "render_projections",
    "render_volume",
    "to_rgb",
    "write_volume_tiff",
]

log = logging.getLogger(__name__)

#: Colour map of depth (z) in every figure: renders, overlays, reports.
DEPTH_CMAP: str = "turbo"

_PROJECTIONS: dict[str, tuple[str, str]] = {"xy": ("x", "y"), "xz": ("x", "z"), "yz": ("y", "z")}
# Relative density below which the mean depth of a pixel is left undefined (NaN).
_DEPTH_FLOOR = 1e-6


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
    px = positive_nm(px_nm, "px_nm")
    positive_nm(default_sigma_nm, "default_sigma_nm")
    floor = px / 2 if sigma_min_nm is None else positive_nm(sigma_min_nm, "sigma_min_nm")
    h, v = _PROJECTIONS[projection]
    check_table(locs, (h, v))
    with_depth = projection == "xy" and "z_nm" in locs.columns
    pos, ok = finite_rows(locs, (h, v))
    sig = widths(locs, (h, v), ok, default_sigma_nm, (floor, floor))
    if extent is not None and len(extent) != 4:
        raise ValueError(f"extent must be (h0, h1, v0, v1) in nm, got {extent!r}")
    h0, nh = axis_grid(pos[:, 0], sig[:, 0], px, None if extent is None else extent[:2], h)
    v0, nv = axis_grid(pos[:, 1], sig[:, 1], px, None if extent is None else extent[2:], v)
    check_size((nv, nh), f"{projection} image")
    values = _depth_channels(locs, ok, pos.shape[0]) if with_depth else None
    with_depth = values is not None
    if values is None:
        values = [np.ones(pos.shape[0])]
    grid_pos = np.column_stack([(pos[:, 1] - v0) / px, (pos[:, 0] - h0) / px])
    grid_sig = np.column_stack([sig[:, 1], sig[:, 0]]) / px
    img = _accumulate(grid_pos, grid_sig, (nv, nh), np.array(values))
    log.debug("rendered %d localizations %s on %d x %d px", pos.shape[0], projection, nv, nh)
    return Rendered(
        density=img[0],
        depth=_mean_depth(img) if with_depth else None,
        extent=(h0, h0 + nh * px, v0, v0 + nv * px),
        px_nm=px,
        projection=projection,
        axes=(h, v),
        n_locs=int(pos.shape[0]),
    )


def _depth_channels(locs: pd.DataFrame, ok: NDArray[np.bool_], n: int) -> list[NDArray] | None:
    """Weights of the density, of z, and (when some z are missing) of the localizations with
    a depth, for the ``n`` rows ``ok``; None when no row has a finite ``z_nm``."""
    z = locs["z_nm"].to_numpy(dtype=np.float64)[ok]
    if not bool(np.isfinite(z).any()):
        return None
    good = np.isfinite(z)
    values = [np.ones(n), np.where(good, z, 0.0)]
    if not good.all():
        # A localization without a depth counts in the density, not in the mean depth.
        values.append(good.astype(float))
    return values


def _mean_depth(img: NDArray[np.float32]) -> NDArray[np.float32]:
    """Density-weighted mean z (nm) per pixel of the channels of :func:`_depth_channels`;
    NaN where the weight is negligible."""
    weight = img[2] if img.shape[0] > 2 else img[0]
    floor_d = _DEPTH_FLOOR * max(float(weight.max()), 1e-30)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > floor_d, img[1] / weight, np.nan).astype(np.float32)


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
    cmap: str = DEPTH_CMAP,
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
    top = intensity_scale(rendered, saturate) if vmax is None else positive_nm(vmax, "vmax")
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
    px = positive_nm(px_nm, "px_nm")
    pz = positive_nm(pz_nm, "pz_nm")
    positive_nm(default_sigma_nm, "default_sigma_nm")
    axes = ("x", "y", "z")
    check_table(locs, axes)
    pos, ok = finite_rows(locs, axes)
    sig = widths(locs, axes, ok, default_sigma_nm, (px / 2, px / 2, pz / 2))
    if extent is not None and len(extent) != 4:
        raise ValueError(f"extent must be (x0, x1, y0, y1) in nm, got {extent!r}")
    x0, nx = axis_grid(pos[:, 0], sig[:, 0], px, None if extent is None else extent[:2], "x")
    y0, ny = axis_grid(pos[:, 1], sig[:, 1], px, None if extent is None else extent[2:], "y")
    if z_range is not None and len(z_range) != 2:
        raise ValueError(f"z_range must be (z0, z1) in nm, got {z_range!r}")
    z0, nz = axis_grid(pos[:, 2], sig[:, 2], pz, z_range, "z")
    check_size((nz, ny, nx), "volume")
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

    px = positive_nm(px_nm, "px_nm")
    pz = positive_nm(pz_nm, "pz_nm")
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


# -- figures -----------------------------------------------------------------------------------


def _default_extent(
    locs: pd.DataFrame, axes: tuple[str, str], px: float, default_sigma_nm: float = 15.0
) -> tuple[float, float, float, float]:
    """The extent :func:`render_gaussian` would choose for ``locs`` (nm)."""
    pos, ok = finite_rows(locs, axes)
    sig = widths(locs, axes, ok, default_sigma_nm, (px / 2, px / 2))
    h0, nh = axis_grid(pos[:, 0], sig[:, 0], px, None, axes[0])
    v0, nv = axis_grid(pos[:, 1], sig[:, 1], px, None, axes[1])
    return (h0, h0 + nh * px, v0, v0 + nv * px)


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
    from .plotting import save_figure

    tables, px, ext, z_range, zpad, is3d = _projection_frame(locs, truth, px_nm, z_range)
    panels = [_render_panel(label, t, px, ext, z_range, zpad, is3d) for label, t in tables]
    fig = _projections_figure(panels, ext, px, z_range, is3d, title)
    return save_figure(fig, path, dpi=150)


@dataclass(frozen=True)
class Projections:
    """The images of :func:`plot_projections` for one table.

    Attributes
    ----------
    xy : Rendered
        The xy render (density and mean depth).
    xz, yz : Rendered or None
        The side projections (None for a table without z).
    z_range : (float, float) or None
        Depths (nm) at the ends of the colour map.
    px_nm : float
        Render pixel (nm).
    """

    xy: Rendered
    xz: Rendered | None
    yz: Rendered | None
    z_range: tuple[float, float] | None
    px_nm: float


def render_projections(
    locs: pd.DataFrame,
    *,
    px_nm: float | None = None,
    z_range: tuple[float, float] | None = None,
) -> Projections:
    """The xy, xz and yz renders that :func:`plot_projections` draws, as arrays.

    Parameters
    ----------
    locs : DataFrame
        Localization table.
    px_nm : float, optional
        Render pixel (nm); default as :func:`plot_projections` chooses it.
    z_range : (float, float), optional
        Colour scale and side-panel depth range (nm); default the 0.5..99.5th percentile of z.

    Returns
    -------
    Projections
        Colour them with :func:`to_rgb` and ``z_range``.
    """
    _, px, ext, z_range, zpad, is3d = _projection_frame(locs, None, px_nm, z_range)
    _, xy, sides = _render_panel("localizations", locs, px, ext, z_range, zpad, is3d)
    xz, yz = sides if sides is not None else (None, None)
    return Projections(xy, xz, yz, z_range, px)


def _projection_frame(
    locs: pd.DataFrame,
    truth: pd.DataFrame | None,
    px_nm: float | None,
    z_range: tuple[float, float] | None,
) -> tuple[list, float, tuple[float, float, float, float], Any, float, bool]:
    """What every panel of the projections shares: the labelled tables, the render pixel
    (nm), the xy extent, the depth range, the side panels' depth padding (nm) and whether
    the tables are 3D."""
    check_table(locs, ("x", "y"))
    tables = [("localizations", locs)]
    if truth is not None:
        check_table(truth, ("x", "y"))
        tables.append(("ground truth", truth))
    is3d = all(
        "z_nm" in t.columns and np.isfinite(t["z_nm"].to_numpy(float)).any() for _, t in tables
    )
    both = pd.concat([t[["x_nm", "y_nm"]] for _, t in tables])
    span = float(max(np.ptp(both["x_nm"].dropna()), np.ptp(both["y_nm"].dropna()), 1.0))
    px = _auto_px(locs, span) if px_nm is None else positive_nm(px_nm, "px_nm")
    medians = _median_widths(locs)
    if truth is not None:  # drawn with the localizations' typical spot size
        tables[1] = ("ground truth", truth.assign(**{SIGMA_COLUMNS[a]: medians[a] for a in "xyz"}))
    # One frame for every panel: the union of the tables' default extents.
    exts = [_default_extent(t, ("x", "y"), px) for _, t in tables]
    ext = (
        min(e[0] for e in exts),
        max(e[1] for e in exts),
        min(e[2] for e in exts),
        max(e[3] for e in exts),
    )
    z_range = _projection_z_range(locs, z_range, is3d)
    return tables, px, ext, z_range, 3.0 * medians["z"], is3d


def _median_widths(locs: pd.DataFrame) -> dict[str, float]:
    """Median finite positive uncertainty (nm) per axis; 15 nm laterally, 2.5 times that in z,
    where the table has none."""
    medians = {}
    for a in ("x", "y", "z"):
        col = SIGMA_COLUMNS[a]
        vals = locs[col].to_numpy(float) if col in locs else np.zeros(0)
        vals = vals[np.isfinite(vals) & (vals > 0)]
        medians[a] = float(np.median(vals)) if vals.size else 15.0 * (2.5 if a == "z" else 1.0)
    return medians


def _projection_z_range(
    locs: pd.DataFrame, z_range: tuple[float, float] | None, is3d: bool
) -> tuple[float, float] | None:
    """``z_range`` checked, by default (3D tables) the 0.5..99.5th percentile of z."""
    if z_range is None and is3d:
        z = locs["z_nm"].to_numpy(float)
        z = z[np.isfinite(z)]
        z_range = tuple(float(v) for v in np.percentile(z, [0.5, 99.5]))
        if not z_range[1] > z_range[0]:
            z_range = (z_range[0] - 50.0, z_range[0] + 50.0)
    if z_range is not None and not float(z_range[1]) > float(z_range[0]):
        raise ValueError(f"z_range must run from low to high nm, got {z_range!r}")
    return z_range


def _render_panel(
    label: str,
    t: pd.DataFrame,
    px: float,
    ext: tuple[float, float, float, float],
    z_range: tuple[float, float] | None,
    zpad: float,
    is3d: bool,
) -> tuple[str, Rendered, tuple[Rendered, Rendered] | None]:
    """The xy image of one table on the extent ``ext`` and, in 3D, its xz and yz images over
    ``z_range`` padded by ``zpad`` nm."""
    xy = render_gaussian(t, px_nm=px, extent=ext)
    if not is3d:
        return label, xy, None
    zext = (z_range[0] - zpad, z_range[1] + zpad)
    xz = render_gaussian(t, px_nm=px, projection="xz", extent=(*ext[:2], *zext))
    yz = render_gaussian(t, px_nm=px, projection="yz", extent=(*ext[2:], *zext))
    return label, xy, (xz, yz)


@dataclass(frozen=True)
class _Layout:
    """Where the axes of the projections figure go, in inches: placed by hand so that the xy
    panel keeps equal scales in x and y and the side panels line up with it exactly."""

    w_in: float  # xy panel width
    h_in: float  # xy panel height
    s_in: float  # side panel depth (0 in 2D)
    n_panels: int
    is3d: bool
    title: bool
    gap: float = 0.12
    left: float = 0.75
    bottom: float = 0.6
    top: float = 0.55
    between: float = 0.95

    @property
    def block(self) -> float:
        """Width of one table's panels."""
        return self.w_in + (self.gap + self.s_in if self.is3d else 0.0)

    @property
    def panels_right(self) -> float:
        """Right edge of the last table's panels."""
        return self.left + self.n_panels * self.block + (self.n_panels - 1) * self.between

    @property
    def fig_w(self) -> float:
        return self.panels_right + (1.1 if self.is3d else 0.3)

    @property
    def fig_h(self) -> float:
        side = self.s_in + self.gap if self.is3d else 0.0
        return self.bottom + side + self.h_in + self.top + (0.3 if self.title else 0.0)

    @property
    def y_xy(self) -> float:
        """Bottom of the xy panels."""
        return self.bottom + (self.s_in + self.gap if self.is3d else 0.0)

    def rect(self, x: float, y: float, w: float, h: float) -> list[float]:
        """An axes rectangle in inches as fractions of the figure."""
        return [x / self.fig_w, y / self.fig_h, w / self.fig_w, h / self.fig_h]


def _layout(panels: list, ext: tuple[float, ...], is3d: bool, title: str) -> _Layout:
    """Panel sizes for a figure about 6 inches across the xy panel and its side panel."""
    w_nm, h_nm = ext[1] - ext[0], ext[3] - ext[2]
    s_nm = 0.0
    if is3d:
        s_nm = max(panels[0][2][0].extent[3] - panels[0][2][0].extent[2], 0.25 * max(w_nm, h_nm))
    k = 6.0 / max(w_nm + s_nm, h_nm + s_nm)  # inches per nm
    return _Layout(w_nm * k, h_nm * k, s_nm * k, len(panels), is3d, bool(title))


def _dark_axes(ax, xlabel: str = "", ylabel: str = "") -> None:
    """White ticks and labels on a black panel."""
    ax.set_facecolor("black")
    ax.tick_params(colors="white", labelsize=8)
    for sp in ax.spines.values():
        sp.set_color("0.5")
    ax.set_xlabel(xlabel, color="white")
    ax.set_ylabel(ylabel, color="white")


def _projections_figure(
    panels: list,
    ext: tuple[float, float, float, float],
    px: float,
    z_range: tuple[float, float] | None,
    is3d: bool,
    title: str,
):
    """The figure of :func:`plot_projections` from the rendered panels."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    lay = _layout(panels, ext, is3d, title)
    fig = Figure(figsize=(lay.fig_w, lay.fig_h), facecolor="black")
    cmap = DEPTH_CMAP
    um = (ext[0] / 1000, ext[1] / 1000, ext[3] / 1000, ext[2] / 1000)
    for i, (label, xy, side) in enumerate(panels):
        x_xy = lay.left + i * (lay.block + lay.between)
        ax = fig.add_axes(lay.rect(x_xy, lay.y_xy, lay.w_in, lay.h_in))
        ax.imshow(
            to_rgb(xy, z_range=z_range, cmap=cmap),
            extent=um,
            interpolation="nearest",
            aspect="auto",
        )
        _dark_axes(ax, "" if is3d else "x (µm)", "y (µm)")
        _bar(ax, um[1] - um[0], um[2] - um[3], um[0], um[2], 1000.0)
        ax.set_title(f"{label} ({xy.n_locs:,}, {px:g} nm px)", color="white", fontsize=10)
        if side is not None:
            _draw_sides(fig, lay, ax, x_xy, side, um, z_range, cmap)
    if is3d:
        cax = fig.add_axes(lay.rect(lay.panels_right + 0.15, lay.y_xy, 0.18, lay.h_in))
        sm = ScalarMappable(norm=Normalize(*z_range), cmap=colormaps[cmap])
        cb = fig.colorbar(sm, cax=cax)
        cb.set_label("z (nm)", color="white")
        cb.ax.tick_params(colors="white", labelsize=8)
        cb.outline.set_edgecolor("0.5")
    if title:
        fig.suptitle(title, color="white", fontsize=11, y=1 - 0.12 / lay.fig_h, va="top")
    return fig


def _draw_sides(
    fig,
    lay: _Layout,
    ax,
    x_xy: float,
    side: tuple[Rendered, Rendered],
    um: tuple[float, float, float, float],
    z_range: tuple[float, float] | None,
    cmap: str,
) -> None:
    """The xz panel below the xy axes ``ax`` (z up) and the yz panel at its right."""
    xz, yz = side
    zl, zh = xz.extent[2], xz.extent[3]
    ax_xz = fig.add_axes(lay.rect(x_xy, lay.bottom, lay.w_in, lay.s_in), sharex=ax)
    ax_xz.imshow(
        to_rgb(xz, z_range=z_range, cmap=cmap),
        origin="lower",
        extent=(um[0], um[1], zl, zh),
        interpolation="nearest",
        aspect="auto",
    )
    _dark_axes(ax_xz, "x (µm)", "z (nm)")
    ax_yz = fig.add_axes(
        lay.rect(x_xy + lay.w_in + lay.gap, lay.y_xy, lay.s_in, lay.h_in), sharey=ax
    )
    ax_yz.imshow(
        to_rgb(yz, z_range=z_range, cmap=cmap).transpose(1, 0, 2),
        origin="upper",
        extent=(zl, zh, um[2], um[3]),
        interpolation="nearest",
        aspect="auto",
    )
    _dark_axes(ax_yz, "z (nm)")
    ax_yz.tick_params(labelleft=False)
    ax.tick_params(labelbottom=False)
