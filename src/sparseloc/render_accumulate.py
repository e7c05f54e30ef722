"""Sums of normalised Gaussians on a pixel grid: the drawing engine of :mod:`sparseloc.render`.

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
  average). Cost ~ pixels, so it wins for dense groups.
* *splat*: a separable Gaussian patch per localization (sampled at pixel centres,
  normalised to one) added with vectorised NumPy. Cost ~ localizations x patch area, so it
  wins for small or sparse groups.

The two agree to about 1 % of the peak for widths of 2 px and more; below about 1 px the
pixel grid dominates either way (up to ~25 % per-pixel differences, same mass and centroid).

Spots are cut at :data:`~sparseloc.render_grid.TRUNCATE` standard deviations; mass that falls
outside the image is lost.
"""

from __future__ import annotations

import math
from itertools import product

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage as ndi

from .render_grid import TRUNCATE

__all__ = ["SIGMA_BIN_RATIO", "accumulate"]

#: Ratio between neighbouring width bins (per axis) of the grouped rendering.
SIGMA_BIN_RATIO: float = math.sqrt(2.0)
# Splat work is chunked to about this many patch values at once (memory ~ 100 MB).
_SPLAT_CHUNK = 4_000_000


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


def accumulate(
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
    # A spot wider than the image along an axis puts less than 1/size of its mass on any
    # pixel row there: it is left out, so that memory and time are bounded by the image and
    # not by the widths (a doubtful fit's uncertainty can reach 1e9 nm).
    narrow = np.all(np.isfinite(sig) & (sig <= np.array(shape, dtype=np.float64)), axis=1)
    pos, sig, values = pos[narrow], sig[narrow], values[:, narrow]
    radius_all = np.ceil(TRUNCATE * sig).astype(np.int64) + 1
    # Spots entirely off the image cost time and stretch their level's box: drop them.
    keep = np.all((pos > -radius_all) & (pos < np.array(shape) + radius_all), axis=1)
    pos, sig, values = pos[keep], sig[keep], values[:, keep]
    if pos.shape[0] == 0:
        return out
    s0, k, w_lo = _levels(sig, ratio)
    idx_all, key_all, w_all, span = _level_entries(k, w_lo)
    order = np.argsort(key_all, kind="stable")
    cuts = np.flatnonzero(np.diff(key_all[order])) + 1
    scratch: NDArray[np.float32] | None = None
    for grp in np.split(order, cuts):
        key = int(key_all[grp[0]])
        lev = np.empty(d, dtype=np.int64)
        for a in range(d - 1, -1, -1):
            key, lev[a] = divmod(key, int(span[a]))
        idx = idx_all[grp]
        v = values[:, idx] * w_all[grp]
        scratch = _draw_group(out, pos[idx], s0 * ratio**lev, v, method, scratch)
    return out


def _level_entries(k: NDArray, w_lo: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Every localization on each combination of its lower/upper level per axis (``k`` (n, d)
    lower levels, ``w_lo`` (n, d) their weights): the row of each entry, its level key, its
    weight, and the span of the levels per axis that the key encodes."""
    d = k.shape[1]
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
    return np.concatenate(ent_idx), np.concatenate(ent_key), np.concatenate(ent_w), span


def _draw_group(
    out: NDArray[np.float32],
    p: NDArray,
    level: NDArray,
    v: NDArray,
    method: str,
    scratch: NDArray[np.float32] | None,
) -> NDArray[np.float32] | None:
    """Add spots of one width ``level`` (d,) px at ``p`` (n, d) px with weights ``v`` (m, n)
    to ``out`` by the cheaper method (or ``method``); returns the filter's scratch buffer."""
    shape = out.shape[1:]
    radius = np.ceil(TRUNCATE * level).astype(np.int64)
    lo = np.maximum(np.floor(p.min(axis=0)).astype(np.int64) - radius - 1, 0)
    hi = np.minimum(np.floor(p.max(axis=0)).astype(np.int64) + radius + 2, shape)
    if np.any(hi <= lo):
        return scratch
    box = tuple(int(b) for b in hi - lo)
    taps = 2 * radius + 1
    # Measured costs (ns) of the two methods, per output channel.
    cost_filter = math.prod(box) * (6.0 + 0.6 * int(taps.sum())) + 60.0 * len(p)
    cost_splat = 22.0 * len(p) * int(np.prod(taps))
    use = method if method != "auto" else ("splat" if cost_splat < cost_filter else "filter")
    view = out[(slice(None), *(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True)))]
    if use == "filter":
        if scratch is None:
            scratch = np.empty(out.size, dtype=np.float32)
        view += _filter_group(p - lo, level, v, box, scratch)
    else:
        _splat_group(p - lo, np.broadcast_to(level, p.shape), v, box, radius, view)
    return scratch
