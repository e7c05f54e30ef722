"""Background, candidate detection and windows for whole frames.

- Background: a temporal percentile over a sliding block of frames follows slow changes while
  ignoring blinking molecules (a pixel is dark most of the time), then a small spatial smoothing;
  the bumps of molecules that stay on for much of the block are capped (:func:`capped_bumps`).
- Candidates: the background-subtracted frame is correlated with the z-averaged PSF (a matched
  filter for an engineered PSF: a double helix's two lobes give one peak, not two) and local
  maxima whose signal-to-noise ratio exceeds ``threshold`` are kept.
- Windows: the frame is tiled by *cores* of ``window - 2 * margin`` pixels; each core has one
  window of ``window`` pixels around it (shifted inward at frame edges). A window is solved when
  a candidate lies in or next to its core, and a localization is kept only if it falls in the
  core of the window that found it. Cores partition the frame, so nothing is counted twice and
  nothing is lost at window or frame edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import fft as sfft
from scipy import ndimage as ndi
from scipy.special import ndtri

from .engine import kernels
from .psf.base import PSFModel

__all__ = [
    "Tile",
    "background_trend",
    "capped_bumps",
    "circular_shape",
    "detect_candidates",
    "spatial_background",
    "temporal_background",
    "temporal_backgrounds",
    "tiles",
    "z_averaged_psf",
]


def temporal_background(
    frames: NDArray,
    *,
    percentile: float = 30.0,
    smooth: float = 1.0,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.float64]:
    """Background of the middle of a block of frames: a per-pixel percentile over the block.

    Parameters
    ----------
    frames : ndarray, shape (n, rows, cols)
        A block of frames in photons centred on the frame(s) of interest.
    percentile : float
        Per-pixel percentile over time (below 50 because molecules only add light); corrected
        for the camera's spread so that a constant background comes out unbiased.
    smooth : float
        Gaussian smoothing (pixels) of the result.
    noise_factor : float
        Variance per expected photon (2 for EMCCD data: excess noise).
    read_variance : float or ndarray, shape (rows, cols)
        Read-noise variance per pixel (photons^2).

    Returns
    -------
    ndarray, shape (rows, cols)
        Background in photons per pixel.
    """
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim != 3:
        raise ValueError(f"frames must be (n, rows, cols), got shape {arr.shape}")
    q = np.percentile(arr, percentile, axis=0)
    bg = _mean_below_percentile(q, percentile, noise_factor, read_variance)
    return ndi.gaussian_filter(bg, smooth) if smooth > 0 else bg


def temporal_backgrounds(
    frames: NDArray,
    centres: NDArray,
    half: int,
    *,
    percentile: float = 30.0,
    smooth: float = 1.0,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.float64]:
    """:func:`temporal_background` of several frames of one block at once.

    Parameters
    ----------
    frames : ndarray, shape (n, rows, cols)
        A block of frames in photons.
    centres : array of int, shape (K,)
        Increasing indices into ``frames``; frame ``c``'s background comes from
        ``frames[max(c - half, 0) : min(c + half + 1, n)]``.
    half : int
        Frames on either side.
    percentile, smooth, noise_factor, read_variance
        As in :func:`temporal_background`.

    Returns
    -------
    ndarray, shape (K, rows, cols)
        The same numbers as :func:`temporal_background` of each window; the numba engine
        slides a sorted window per pixel instead of sorting each window.
    """
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim != 3:
        raise ValueError(f"frames must be (n, rows, cols), got shape {arr.shape}")
    centres = np.asarray(centres, dtype=np.int64)
    k = kernels()
    if k is None:
        n = len(arr)
        return (
            np.stack(
                [
                    temporal_background(
                        arr[max(c - half, 0) : min(c + half + 1, n)],
                        percentile=percentile,
                        smooth=smooth,
                        noise_factor=noise_factor,
                        read_variance=read_variance,
                    )
                    for c in centres
                ]
            )
            if len(centres)
            else np.zeros((0, *arr.shape[1:]))
        )
    raw = np.empty((len(centres), *arr.shape[1:]))
    k.percentiles(np.ascontiguousarray(arr), centres, int(half), float(percentile), raw)
    bg = _mean_below_percentile(raw, percentile, noise_factor, read_variance)
    if smooth > 0:
        bg = np.stack([ndi.gaussian_filter(b, smooth) for b in bg]) if len(bg) else bg
    return bg


def _mean_below_percentile(
    q: NDArray[np.float64],
    percentile: float,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.float64]:
    """The mean photon count whose ``percentile`` is ``q``, for counts of variance
    ``noise_factor * lam + read_variance`` (Poisson: 1 and 0; EMCCD: 2; sCMOS: its read noise).

    A low percentile sits below the mean: with ``q = lam + z sd(lam)`` (normal approximation,
    ``z`` the standard normal quantile), ``lam = q + z^2 F / 2 - z sqrt(F q + z^2 F^2 / 4 + r)``;
    for Poisson counts ``(sqrt(z^2/4 + q) - z/2)^2``. Read noise widens the spread, so a
    correction for shot noise alone would leave the background too low.
    """
    z = float(ndtri(percentile / 100.0))
    f = float(noise_factor)
    r = np.maximum(np.asarray(read_variance, dtype=np.float64), 0.0)
    root = np.sqrt(np.maximum(f * q + z * z * f * f / 4 + r, z * z * f * f / 4))
    return np.maximum(q + z * z * f / 2 - z * root, 0.0)


def spatial_background(
    frame: NDArray,
    *,
    percentile: float = 20.0,
    block: int = 16,
    smooth: float = 2.0,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.float64]:
    """Background of one frame from its darker pixels: for movies too short for time.

    A per-block percentile (blocks of ``block`` pixels), corrected for the camera's spread as
    in :func:`temporal_background`, interpolated back to full size and smoothed. It follows
    changes on scales of a few blocks; molecules brighten only part of each block.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        One frame in photons.
    percentile : float
        Percentile of each block.
    block : int
        Block side (pixels).
    smooth : float
        Gaussian smoothing (pixels) of the result.
    noise_factor, read_variance
        As in :func:`temporal_background` (a read-variance map is averaged over each block).

    Returns
    -------
    ndarray, shape (rows, cols)
    """
    arr = np.asarray(frame, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {arr.shape}")
    redges, cedges = _block_edges(arr.shape[0], block), _block_edges(arr.shape[1], block)
    q = _edge_statistic(arr[None], redges, cedges, np.percentile, percentile)
    rv = _block_read_variance(read_variance, arr.shape, redges, cedges)
    lam = _mean_below_percentile(q, percentile, noise_factor, rv)
    bg = _block_interpolated(lam, arr.shape)[0]
    return ndi.gaussian_filter(bg, smooth) if smooth > 0 else bg


#: Blocks per side of a frame over which :func:`background_trend` reads the background.
TREND_BLOCKS = 8
#: A block whose light, averaged over the frames, lies this many of its standard deviations
#: above the trend holds light of the sample (a bead, its halo) and is left out of the trend.
TREND_OUTLIER = 3.0
#: Fits of the trend, each without the blocks the one before found lit.
TREND_ROUNDS = 6


def background_trend(
    frames: NDArray,
    *,
    percentile: float = 20.0,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.float64]:
    """The smooth change of each frame's background across the field, less its mean: a tilt
    under a bead scan, which a single level per frame leaves in every bead's image as a ramp
    that moves its light's centroid.

    Each frame's background is read per block (up to :data:`TREND_BLOCKS` a side, 4 pixels
    at least; the ``percentile`` of its pixels, corrected for the camera's spread as in
    :func:`spatial_background`). The blocks that hold the sample's light are found on the
    blocks' mean over the frames by :func:`_unlit_blocks` (rounds of planes from the
    blocks' median on, each leaving out the blocks :data:`TREND_OUTLIER` of their noise's
    standard deviations above it); a plane, then a quadratic (4 blocks a side or more), is
    admitted where an F test on the unlit blocks calls for it (:func:`_significant_terms`),
    so a flat background gives no trend; and each frame's trend is fitted on those blocks.
    Nothing on fewer than 2 blocks a side. Where fewer than 6 blocks are left unlit (a
    background curved far off any plane, an illumination profile, or a field full of
    light), one profile for every frame is read from the blocks whose light stays through
    the scan (:func:`_curved_trend`), and none where they show no broad one.

    Parameters
    ----------
    frames : ndarray, shape (K, rows, cols)
        Frames in photons.
    percentile, noise_factor, read_variance
        As in :func:`spatial_background` (a read-variance map is averaged over each block).

    Returns
    -------
    ndarray, shape (K, rows, cols)
        The trend of each frame (photons/pixel), zero mean over the frame.
    """
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim != 3:
        raise ValueError(f"frames must be (n, rows, cols), got shape {arr.shape}")
    k, rows, cols = arr.shape
    nbr, nbc = min(TREND_BLOCKS, rows // 4), min(TREND_BLOCKS, cols // 4)
    if min(nbr, nbc) < 2:
        return np.zeros_like(arr)
    redges, cedges = _edges(rows, nbr), _edges(cols, nbc)
    q = _edge_statistic(arr, redges, cedges, np.percentile, percentile)
    rv = _block_read_variance(read_variance, arr.shape[1:], redges, cedges)
    lam = _mean_below_percentile(q, percentile, noise_factor, rv)
    u = (0.5 * (redges[:-1] + redges[1:]) - rows / 2) / rows
    v = (0.5 * (cedges[:-1] + cedges[1:]) - cols / 2) / cols
    degree = 2 if min(u.size, v.size) >= 4 else 1
    basis = _surface_basis(u[:, None], v[None, :], degree).reshape(-1, u.size * v.size).T
    # a block's percentile varies about 1.4x as much as its mean (a normal's 20th percentile)
    pixels = np.outer(np.diff(redges), np.diff(cedges)).ravel()
    mean = lam.mean(axis=0).ravel()
    var = noise_factor * np.maximum(mean, 1e-3) + np.broadcast_to(rv, lam.shape[1:]).ravel()
    sd = 1.4 * np.sqrt(var / (pixels * k))
    keep, terms = _unlit_blocks(basis, mean, sd)
    if keep is None:  # the planes leave too little unlit: a curved profile, or light everywhere
        return _curved_trend(arr, noise_factor, read_variance)
    if terms == 1:
        return np.zeros_like(arr)
    basis = basis[:, :terms]
    coef = np.linalg.lstsq(basis[keep], lam.reshape(k, -1)[:, keep].T, rcond=None)[0]
    pix = _surface_basis(
        ((np.arange(rows) + 0.5 - rows / 2) / rows)[:, None],
        ((np.arange(cols) + 0.5 - cols / 2) / cols)[None, :],
        degree,
    )
    out = np.tensordot(coef.T, pix[:terms], axes=1)  # (K, rows, cols)
    return out - out.mean(axis=(1, 2), keepdims=True)


def _surface_basis(u: NDArray, v: NDArray, degree: int) -> NDArray[np.float64]:
    """The polynomial terms of ``degree`` (1 or 2) in row and column coordinates ``u``, ``v``
    (broadcast together): shape (terms, *broadcast shape)."""
    u, v = np.broadcast_arrays(u, v)
    terms = [np.ones_like(u), u, v]
    if degree == 2:
        terms += [u * u, u * v, v * v]
    return np.stack(terms)


#: The false-alarm rate of the F test that admits a tilt, then a curvature, into the trend:
#: a trend found in a flat scan changes its model for nothing.
TREND_ALPHA = 1e-4


def _significant_terms(basis: NDArray, values: NDArray) -> int:
    """How many of the surface's terms (1: a constant, 3: a plane, 6: a quadratic) the blocks'
    ``values`` (N,) call for: each larger surface where an F test at :data:`TREND_ALPHA`
    finds it explains them better than the one before (a faint halo far from the beads, or
    the noise of blocks on one side of the field, is no tilt to extrapolate across it)."""
    from scipy.stats import f as f_dist

    n = len(values)
    rss = {}
    for p in (1, 3, 6):
        if p <= basis.shape[1] and n > p:
            resid = values - basis[:, :p] @ np.linalg.lstsq(basis[:, :p], values, rcond=None)[0]
            rss[p] = float(resid @ resid)
    chosen = 1
    for p in (3, 6):
        if p not in rss:
            break
        stat = (rss[chosen] - rss[p]) / (p - chosen) / max(rss[p] / (n - p), 1e-300)
        if stat <= f_dist.isf(TREND_ALPHA, p - chosen, n - p):
            break
        chosen = p
    return chosen


def _unlit_blocks(basis: NDArray, values: NDArray, sd: NDArray) -> tuple[NDArray | None, int]:
    """The blocks (of ``values`` (N,), standard deviations ``sd``) that hold no light of
    the sample, and how many terms of ``basis`` (N, terms; a constant and a plane first)
    the trend through them needs (:func:`_significant_terms`). From the blocks' median on,
    rounds of planes fitted to the blocks the last fit left unlit (not
    :data:`TREND_OUTLIER` standard deviations above it): a first fit through every block
    would bend towards the sample's light and leave its fainter parts (a wide PSF's halo)
    in, and a curved one would swing where the unlit blocks leave gaps. None (and 1) where
    fewer than twice the plane's terms would be left: light fills the field, or no plane
    follows the background."""
    plane = basis[:, :3]
    fit = np.full(len(values), np.median(values))
    keep = np.zeros(len(values), dtype=bool)
    for _ in range(TREND_ROUNDS):
        unlit = values - fit <= TREND_OUTLIER * sd
        if unlit.sum() < 2 * plane.shape[1]:
            return None, 1  # too little background to read with planes
        if np.array_equal(unlit, keep):
            break
        keep = unlit
        fit = plane @ np.linalg.lstsq(plane[keep], values[keep], rcond=None)[0]
    if keep.sum() < 2 * basis.shape[1]:
        basis = plane  # too few blocks for a curvature
    return keep, _significant_terms(basis[keep], values[keep])


#: Block side (pixels) over which :func:`_curved_trend` reads an illumination profile, and
#: the most blocks a side (larger blocks on larger frames keep the spline's solve small).
PROFILE_BLOCK, PROFILE_BLOCKS = 8, 32

#: A profile is read only where a quadratic across the field holds this fraction of the
#: steady blocks' spread (per degree of freedom): an illumination is broad, while the halos
#: of beads that stay through a scan rise and fall from bead to bead (measured: 0.83-0.99
#: under illumination profiles, -0.09-0.41 on flat crowded scans;
#: docs/benchmarks/background_trend.txt).
PROFILE_BROAD = 0.8


def _curved_trend(
    arr: NDArray, noise_factor: float, read_variance: float | NDArray
) -> NDArray[np.float64]:
    """The trend of frames ``arr`` (K, rows, cols) whose background no plane follows (an
    illumination profile), zero mean over each frame.

    A bead's light changes through a scan (its image defocuses) while the illumination
    stays: the blocks of :data:`PROFILE_BLOCK` pixels (at most :data:`PROFILE_BLOCKS` a
    side) whose light is steady
    (:func:`_steady_blocks`) hold the illumination, and the halos of beads that stay too.
    Where at least 12 are steady, in every quarter of the field, their levels differ more
    than their noise allows (a chi-square test at :data:`TREND_ALPHA`) and a quadratic
    across the field holds :data:`PROFILE_BROAD` of their spread (per degree of freedom), a
    smooth surface (a thin-plate spline) through them is every frame's trend; else none.
    An illumination that bleaches through the scan leaves only its dim blocks steady and is
    read in part, the same for every frame.
    """
    from scipy.interpolate import RBFInterpolator
    from scipy.stats import chi2

    k, rows, cols = arr.shape
    nbr, nbc = (int(np.clip(n // PROFILE_BLOCK, 2, PROFILE_BLOCKS)) for n in (rows, cols))
    redges, cedges = _edges(rows, nbr), _edges(cols, nbc)
    means = _edge_statistic(arr, redges, cedges, np.mean).reshape(k, -1)
    pixels = np.outer(np.diff(redges), np.diff(cedges)).ravel()
    rv = np.ravel(_block_read_variance(read_variance, arr.shape[1:], redges, cedges))
    var = (noise_factor * np.maximum(means, 1e-3) + rv) / pixels  # of each block mean
    steady = _steady_blocks(means, var)
    n = int(steady.sum())
    u = np.repeat(0.5 * (redges[:-1] + redges[1:]), nbc)[steady] / rows - 0.5
    v = np.tile(0.5 * (cedges[:-1] + cedges[1:]), nbr)[steady] / cols - 0.5
    # every quarter of the field holds steady blocks: the spline interpolates, not extrapolates
    if n < 12 or len({(a > 0, b > 0) for a, b in zip(u, v, strict=True)}) < 4:
        return np.zeros_like(arr)
    values, spread = means.mean(axis=0)[steady], var[:, steady].mean(axis=0) / k
    mean = np.average(values, weights=1.0 / spread)
    if np.sum((values - mean) ** 2 / spread) <= chi2.isf(TREND_ALPHA, n - 1):
        return np.zeros_like(arr)
    quadratic = _surface_basis(u, v, 2).T
    rest = values - quadratic @ np.linalg.lstsq(quadratic, values, rcond=None)[0]
    if np.sum(rest**2) / (n - 6) > (1.0 - PROFILE_BROAD) * np.sum((values - values.mean()) ** 2) / (
        n - 1
    ):
        return np.zeros_like(arr)
    try:
        surface = RBFInterpolator(
            np.column_stack([u, v]), values, kernel="thin_plate_spline", smoothing=1e-3 * n
        )
    except np.linalg.LinAlgError:  # steady blocks on one line: no surface to draw
        return np.zeros_like(arr)
    # the surface at the centres of 4-pixel blocks, bilinear between them
    fr, fc = _edges(rows, max(1, rows // 4)), _edges(cols, max(1, cols // 4))
    cu, cv = np.meshgrid(
        0.5 * (fr[:-1] + fr[1:]) / rows - 0.5, 0.5 * (fc[:-1] + fc[1:]) / cols - 0.5, indexing="ij"
    )
    fine = surface(np.column_stack([cu.ravel(), cv.ravel()])).reshape(1, *cu.shape)
    shape = _block_interpolated(fine, (rows, cols))[0]
    return np.broadcast_to(shape - shape.mean(), arr.shape).copy()


def _steady_blocks(means: NDArray, var: NDArray) -> NDArray[np.bool_]:
    """The blocks whose means ``means`` (K frames, N blocks; variances ``var``) stay at their
    mean over the frames, less each frame's median change over the blocks (a background
    level that rises or falls with the frames), within the noise: a chi-square test at
    :data:`TREND_ALPHA`. Returns a mask (N,)."""
    from scipy.stats import chi2

    level = means.mean(axis=0)
    shift = np.median(means - level, axis=1, keepdims=True)
    change = ((means - level - shift) ** 2 / var).sum(axis=0)
    return change < chi2.isf(TREND_ALPHA, len(means) - 1)


def _block_edges(n: int, block: int) -> NDArray[np.int64]:
    """Edges of about ``n / block`` equal blocks of ``n`` pixels (at least one block)."""
    return _edges(n, max(1, round(n / block)))


def _edges(n: int, nb: int) -> NDArray[np.int64]:
    """Edges of ``nb`` equal blocks of ``n`` pixels."""
    return np.linspace(0, n, nb + 1).round().astype(np.int64)


def _block_statistic(arr: NDArray, block: int, statistic, *args) -> NDArray[np.float64]:
    """``statistic(values, *args, axis=(1, 2))`` of each block of ``block`` pixels of each
    image of ``arr`` (K, rows, cols): shape (K, row blocks, column blocks)."""
    redges, cedges = _block_edges(arr.shape[1], block), _block_edges(arr.shape[2], block)
    return _edge_statistic(arr, redges, cedges, statistic, *args)


def _edge_statistic(arr: NDArray, redges, cedges, statistic, *args) -> NDArray[np.float64]:
    """:func:`_block_statistic` of the blocks between row edges ``redges`` and column edges
    ``cedges``."""
    q = np.empty((len(arr), len(redges) - 1, len(cedges) - 1))
    for i in range(q.shape[1]):
        for j in range(q.shape[2]):
            part = arr[:, redges[i] : redges[i + 1], cedges[j] : cedges[j + 1]]
            q[:, i, j] = statistic(part, *args, axis=(1, 2))
    return q


def _block_read_variance(
    read_variance: float | NDArray, shape: tuple[int, int], redges: NDArray, cedges: NDArray
) -> NDArray[np.float64]:
    """A read-variance map (photons^2; a scalar or broadcast to ``shape``) averaged over each
    block between row edges ``redges`` and column edges ``cedges``: (row blocks, column
    blocks), or the scalar as given."""
    rv = np.asarray(read_variance, dtype=np.float64)
    if not rv.ndim:
        return rv
    return _edge_statistic(np.broadcast_to(rv, shape)[None], redges, cedges, np.mean)[0]


def _interpolation_matrix(n: int, nb: int) -> NDArray[np.float64]:
    """(n, nb) weights taking values at the centres of ``nb`` equal blocks of ``n`` pixels to
    every pixel: linear between the centres, constant beyond the outer ones."""
    edges = _edges(n, nb)
    centres = 0.5 * (edges[:-1] + edges[1:]) - 0.5
    pos = np.interp(np.arange(n), centres, np.arange(nb))
    lo = np.minimum(np.floor(pos).astype(np.int64), nb - 1)
    hi = np.minimum(lo + 1, nb - 1)
    w = np.zeros((n, nb))
    frac = pos - lo
    np.add.at(w, (np.arange(n), lo), 1.0 - frac)
    np.add.at(w, (np.arange(n), hi), frac)
    return w


def _block_interpolated(q: NDArray, shape: tuple[int, int]) -> NDArray[np.float64]:
    """Block values ``q`` (K, row blocks, column blocks) at every pixel of ``shape``
    (bilinear between the block centres, constant beyond the outer ones): (K, rows, cols)."""
    wr = _interpolation_matrix(shape[0], q.shape[1])
    wc = _interpolation_matrix(shape[1], q.shape[2])
    cols = (q.reshape(-1, q.shape[2]) @ wc.T).reshape(len(q), q.shape[1], shape[1])
    return np.ascontiguousarray(np.tensordot(wr, cols, axes=([1], [1])).transpose(1, 0, 2))


#: The cap of :func:`capped_bumps` above the local median, in robust standard deviations of
#: the background estimate. On a background without bumps the cap then lowers the estimate by
#: 0.08 of its standard deviation on average (``E[max(0, e - 1)]`` for a normal ``e``), so
#: it costs nothing where no molecule stays on.
BUMP_ALLOWANCE = 1.0


def capped_bumps(
    backgrounds: NDArray, block: int, allowance: float = BUMP_ALLOWANCE
) -> NDArray[np.float64]:
    """Backgrounds with bumps the size of one emitter's image capped.

    A temporal percentile takes in a molecule that stays on for about a third of its window
    or more: its image becomes a bump of the background, and the detection, which sees the
    frame less the background, then misses the molecule. A microscope's background varies on
    larger scales than one emitter's image, so each background is capped at its median over
    blocks of ``block`` pixels (an image's width; interpolated between the block centres)
    plus ``allowance`` times the robust standard deviation of the background about that
    median (1.4826 times the median absolute deviation). A background's own structure
    narrower than a block and brighter than the allowance is lowered too.

    Parameters
    ----------
    backgrounds : ndarray, shape (K, rows, cols)
        Backgrounds (photons/pixel), one per frame.
    block : int
        Block side (pixels): the width of one emitter's image.
    allowance : float
        The cap above the local median, in standard deviations of the background.

    Returns
    -------
    ndarray, shape (K, rows, cols)
        The capped backgrounds (photons/pixel).

    Raises
    ------
    ValueError
        For a shape other than (K, rows, cols), a block below 1 pixel, a negative allowance
        or a value that is not finite.
    """
    bg = np.asarray(backgrounds, dtype=np.float64)
    if bg.ndim != 3:
        raise ValueError(f"backgrounds must be (K, rows, cols), got shape {bg.shape}")
    if not block >= 1 or not allowance >= 0:
        raise ValueError(
            f"the block must be >= 1 px and the allowance >= 0, got {block} and {allowance}"
        )
    if not np.all(np.isfinite(bg)):
        raise ValueError("the backgrounds must be finite")
    if len(bg) == 0:
        return bg.copy()
    local = _block_interpolated(_block_statistic(bg, int(block), np.median), bg.shape[1:])
    # the spread from about 16,000 pixels of each background: precise to about 1 %
    step = max(1, int(np.sqrt(bg.shape[1] * bg.shape[2] / 16384)))
    d = (bg - local)[:, ::step, ::step]
    spread = 1.4826 * np.median(np.abs(d - np.median(d, axis=(1, 2), keepdims=True)), axis=(1, 2))
    return np.minimum(bg, local + allowance * spread[:, None, None])


def z_averaged_psf(
    model: PSFModel, pixel_size: float, z_range: tuple[float, float], size: int, n_planes: int = 9
) -> NDArray[np.float64]:
    """The model's image averaged over ``n_planes`` z planes, centred in ``size x size``."""
    half = size * pixel_size / 2
    zs = np.linspace(*z_range, n_planes)
    imgs = model.images(
        np.full(n_planes, half), np.full(n_planes, half), zs, (size, size), pixel_size
    )
    return imgs.mean(axis=0)


def detect_candidates(
    frame: NDArray,
    background: NDArray | float,
    template: NDArray,
    *,
    threshold: float = 5.0,
    min_distance: int | None = None,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
    return_plane: bool = False,
    cache: dict | None = None,
) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Candidate emitter positions (row, col in pixels) in one frame.

    The signal-to-noise map is ``corr / sqrt(var)`` with ``corr`` the correlation of
    ``frame - background`` with ``template`` and ``var`` its variance under the background:
    ``sum(template^2 (noise_factor * background + read_variance))`` over the template's
    pixels (``noise_factor``: shot-noise variance per expected photon, 2 for EMCCD data;
    ``read_variance``: sCMOS read noise in photons^2, a scalar or a map of the frame's
    shape). A stack of templates (one per z plane, say) gives the largest signal-to-noise
    over them at each pixel. Local maxima above ``threshold`` are returned, strongest first.
    Maxima closer than ``min_distance`` pixels to a stronger one are dropped (default: the
    radius of the (mean) template's part above half its maximum, so a double helix's lobes
    give one candidate). With ``return_plane`` the index of each candidate's best template
    comes too. ``cache``: a dict kept between calls with the same templates, which holds
    their spectra per frame shape.
    """
    f = np.asarray(frame, dtype=np.float64)
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    stack = np.asarray(template, dtype=np.float64)
    stack = stack[None] if stack.ndim == 2 else stack
    stack = stack / stack.sum(axis=(1, 2), keepdims=True)
    if min_distance is None:
        t = stack.mean(axis=0)
        min_distance = max(2, int(np.ceil(np.sqrt(np.count_nonzero(t > 0.5 * t.max()) / np.pi))))
    rv = np.broadcast_to(np.asarray(read_variance, dtype=np.float64), f.shape)
    noise = float(noise_factor) * np.maximum(bg, 1e-3) + rv
    corr = _correlations(f - bg, stack, cache)
    sq, scale = _variance_weights(stack)
    var = _correlations(noise, sq[None], cache, np.float64)[0]
    # corr_p / sqrt(var scale_p): the pixel's 1 / sqrt(var) is common to the planes, so the
    # best plane is the one of largest corr_p / sqrt(scale_p)
    weighted = corr * (1.0 / np.sqrt(scale))[:, None, None]
    snr = weighted.max(axis=0) / np.sqrt(np.maximum(var, 1e-12))
    peaks = (ndi.maximum_filter(snr, size=2 * min_distance + 1) == snr) & (snr > threshold)
    rc = np.argwhere(peaks)
    order = np.argsort(-snr[peaks])
    rc = rc[order]
    if return_plane:
        plane = np.argmax(weighted[:, rc[:, 0], rc[:, 1]], axis=0)
        return rc.astype(np.float64), plane
    return rc.astype(np.float64)


def _variance_weights(stack: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The variance of each plane's correlation, ``sum(t^2 noise)`` over its pixels, as one
    convolution of the noise with the planes' mean ``t^2`` (returned first) scaled by each
    plane's ``sum(t^2)`` over that mean's (returned second): exact for one template or a
    uniform noise, and a frame's noise varies slowly across a PSF."""
    sq = (stack**2).mean(axis=0)
    return sq, (stack**2).sum(axis=(1, 2)) / sq.sum()


def snr_at(d: NDArray, noise: NDArray, template: NDArray, rc: NDArray) -> NDArray[np.float64]:
    """The signal-to-noise of :func:`detect_candidates` at pixels ``rc`` (K, 2 integers) only:
    ``d`` is the frame less its known light (rows, cols), ``noise`` the variance per pixel
    (``noise_factor * background + read_variance``), ``template`` one image or a stack
    (largest over the stack). Direct sums over each template's pixels, for a few pixels
    where the map's FFTs would cost more."""
    stack = np.asarray(template, dtype=np.float64)
    stack = stack[None] if stack.ndim == 2 else stack
    stack = stack / stack.sum(axis=(1, 2), keepdims=True)
    sq, scale = _variance_weights(stack)
    t = stack.shape[-1]
    h = (t - 1) // 2
    dp = np.pad(np.asarray(d, dtype=np.float64), h)
    npad = np.pad(np.asarray(noise, dtype=np.float64), h)
    r = np.asarray(rc, dtype=int).reshape(-1, 2)
    rows = r[:, 0, None] + np.arange(t)[None, :]
    cols = r[:, 1, None] + np.arange(t)[None, :]
    pd_ = dp[rows[:, :, None], cols[:, None, :]].reshape(len(r), -1)
    pn = npad[rows[:, :, None], cols[:, None, :]].reshape(len(r), -1)
    corr = pd_ @ stack.reshape(len(stack), -1).T  # (K, P)
    var = (pn @ sq.ravel())[:, None] * scale[None, :]
    return np.max(corr / np.sqrt(np.maximum(var, 1e-12)), axis=1)


def circular_shape(shape: tuple[int, ...], width: int) -> tuple[int, ...]:
    """FFT lengths for the correlations (or convolutions) of an image of ``shape`` with
    templates ``width`` pixels wide whose outputs are kept at the image's own pixels.

    The full linear result is ``n + width - 1`` long and the image's pixels start at the
    template's centre offset ``(width - 1) // 2`` or ``width // 2``; a circular result of
    length ``>= n + width // 2`` wraps its tail only onto outputs before that offset, which
    are not kept. So that length, rounded up to a fast one, is exact and needs fewer points:
    a 64 px crop with 41 px templates, 84 a side instead of 108.

    Parameters
    ----------
    shape : tuple of int
        The image's shape (pixels).
    width : int
        The templates' width (pixels).

    Returns
    -------
    tuple of int
        The FFT length per axis.
    """
    return tuple(sfft.next_fast_len(int(n) + int(width) // 2, real=True) for n in shape)


def _correlations(
    d: NDArray, stack: NDArray, cache: dict | None, dtype: type = np.float32
) -> NDArray[np.float64]:
    """Correlations (P, rows, cols) of ``d`` with each template of ``stack`` (P, T, T),
    centred as ``fftconvolve(..., mode="same")`` with the flipped template; the templates'
    spectra are kept in ``cache`` per frame shape and precision. In single precision by
    default: a signal-to-noise needs a few digits, and the transforms take half the time;
    ``dtype=np.float64`` for the variance map, whose square root divides every plane."""
    rows, cols = d.shape
    h = (stack.shape[-1] - 1) // 2
    shape = circular_shape(d.shape, stack.shape[-1])
    key = (d.shape, np.dtype(dtype).name, stack.shape)
    spectra = None if cache is None else cache.get(key)
    if spectra is None:
        spectra = sfft.rfft2(stack[:, ::-1, ::-1].astype(dtype), shape)
        if cache is not None:
            cache[key] = spectra
    full = sfft.irfft2(sfft.rfft2(d.astype(dtype), shape)[None] * spectra, shape)
    return full[:, h : h + rows, h : h + cols]


@dataclass(frozen=True)
class Tile:
    """One window of a frame and the core it owns (pixel index ranges, end exclusive)."""

    index: int
    row0: int
    col0: int
    core_rows: tuple[int, int]
    core_cols: tuple[int, int]

    def owns(self, x_nm: NDArray, y_nm: NDArray, pixel_size: float) -> NDArray[np.bool_]:
        """Whether positions (nm, frame coordinates) fall in this tile's core."""
        c = np.asarray(x_nm) / pixel_size
        r = np.asarray(y_nm) / pixel_size
        return (
            (r >= self.core_rows[0])
            & (r < self.core_rows[1])
            & (c >= self.core_cols[0])
            & (c < self.core_cols[1])
        )


def _axis_tiles(n: int, window: int, core: int) -> list[tuple[int, int, int]]:
    """(window start, core start, core end) along one axis; cores partition [0, n)."""
    margin = (window - core) // 2
    out = []
    start = 0
    while start < n:
        end = min(start + core, n)
        w0 = int(np.clip(start - margin, 0, n - window))
        out.append((w0, start, end))
        start = end
    return out


def tiles(shape: tuple[int, int], window: int, margin: int) -> list[Tile]:
    """Windows of ``window`` pixels whose cores (``window - 2*margin``) partition the frame.

    Raises ``ValueError`` if the frame is smaller than one window.
    """
    rows, cols = shape
    if rows < window or cols < window:
        raise ValueError(
            f"the frames ({rows}x{cols} px) are smaller than one window ({window}x{window} px)"
        )
    core = window - 2 * margin
    if core < 1:
        raise ValueError(f"margin {margin} leaves no core in a {window} px window")
    out = []
    for r0, rs, re in _axis_tiles(rows, window, core):
        for c0, cs, ce in _axis_tiles(cols, window, core):
            out.append(Tile(len(out), r0, c0, (rs, re), (cs, ce)))
    return out
