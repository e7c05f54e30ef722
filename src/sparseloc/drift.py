"""Drift correction of localization tables: redundant cross-correlation and fiducials.

Sign convention: if the sample moves so that a molecule truly at ``p`` appears at
``p + d(frame)``, the estimated drift is ``d(frame)`` and :func:`apply_drift` subtracts it.
Drift is only defined up to a constant; every estimate here is referenced to the first frame of
the table (``drift[0] == 0``).

Methods
-------
:func:`rcc_drift`
    Redundant cross-correlation (RCC; Wang et al., Opt. Express 22, 15982, 2014). The frames
    are split into ``segments`` consecutive blocks of (nearly) equal length. Each block is
    rendered as an xy histogram (``bin_nm`` bins) blurred by a Gaussian of about the
    localization precision; every pair ``i < j`` is cross-correlated by FFT inside
    ``+-max_shift_nm``, and the peak is located to sub-bin precision by a least-squares
    quadratic fit to the logarithm of the 3 x 3 bins around the maximum (exact for a Gaussian
    peak of any orientation, which matters for the elongated peaks of filaments). The system
    ``s_j - s_i = d_ij`` is solved by least squares with ``s_0 = 0``; pairs whose residual
    exceeds ``max(3 x 1.4826 MAD of the residuals, one bin)`` in any axis are dropped one at a
    time, worst first, re-solving after each. z is then estimated the same way from the
    xy-corrected localizations: for every pair the z histograms of coincident xy bins are
    correlated at zero xy shift (a 3D correlation restricted to the known xy alignment, held
    as sparse matrices so that memory does not grow with the field).

    The segment shifts, placed at the mean frame of each segment's localizations, are
    interpolated to every frame by a natural cubic spline (smooth like real stage drift, no
    kinks at segment centres, and it follows curvature better than straight lines); before the
    first and after the last segment centre the spline's end tangent is extended linearly, so
    the half segment at each end keeps drifting instead of freezing (which would offset the
    whole curve once it is referenced to frame 0). Two segments give a straight line.
:func:`fiducial_drift`
    Tracks of spots present in most frames (beads), averaged; see
    :mod:`sparseloc.drift_fiducial`.

Both return a :class:`DriftResult` (defined in :mod:`sparseloc.drift_common`) whose
``reliable`` flag and ``warnings`` say when the estimate should not be trusted. Lengths are in
nm, frames are 0-based integers.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d
from scipy.sparse.csgraph import connected_components

from .drift_common import DriftLocs, DriftResult, positive, read_locs
from .drift_fiducial import fiducial_drift

__all__ = [
    "DriftResult",
    "apply_drift",
    "fiducial_drift",
    "lateral_only",
    "no_drift_caution",
    "plot_drift",
    "rcc_drift",
    "smooth_p",
]

log = logging.getLogger(__name__)

#: Pairs whose correlation peak is less than this many robust noise units above the median of
#: the correlation window are not used: unstructured localizations give 2-5 over a +-1 um
#: window (a few sparse ones more, which the consistency test then catches).
MIN_PEAK_CONTRAST: float = 6.0
#: Pairs are rejected while their least-squares residual exceeds this many robust residual
#: scales (1.4826 MAD) in any axis, and one histogram bin (``bin_nm`` or ``z_bin_nm``):
#: residuals below a bin are the sub-bin fit's own noise, not inconsistency.
OUTLIER_SIGMAS: float = 3.0
#: The robust noise of a correlation is measured over at least +-this many nm (the window the
#: contrast threshold was calibrated on), however small ``max_shift_nm`` is.
NOISE_WINDOW_NM: float = 1000.0
#: The estimate is flagged unreliable when more than this fraction of the pairs is not used.
MAX_REJECTED_FRACTION: float = 1.0 / 3.0
#: Cached FFT spectra of all segments may take this many bytes; beyond it each pair's spectra
#: are recomputed (slower, memory of three images only).
SPECTRA_BUDGET_BYTES: int = 128 * 2**20
#: Largest xy correlation image (pixels): 8192^2 float32 is 256 MiB.
MAX_IMAGE_PIXELS: int = 8192 * 8192

# --------------------------------------------------------------------------------------------
# RCC
# --------------------------------------------------------------------------------------------


def rcc_drift(
    locs: pd.DataFrame,
    *,
    segments: int = 10,
    bin_nm: float = 20.0,
    z_bin_nm: float = 50.0,
    blur_nm: float | None = None,
    max_shift_nm: float = 1000.0,
    estimate_z: bool = True,
    min_locs_per_segment: int = 200,
    all_flags: bool = False,
    log_warnings: bool = True,
) -> DriftResult:
    """Drift by redundant cross-correlation of time segments (RCC).

    The method is described in the module docstring: the segments' images are correlated in
    pairs, the pair shifts are solved for segment shifts with inconsistent pairs rejected, and
    the segment shifts are interpolated to every frame; z follows the same way.

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``frame, x_nm, y_nm`` (``z_nm`` optional). The rows
        of :func:`sparseloc.postprocess.select_usable` (flag "ok" unless ``all_flags``, sane
        coordinates) with a finite frame and z are used.
    segments : int
        Number of time segments (>= 2; at least 3 for a cross-checked result).
    bin_nm : float
        xy histogram bin (nm).
    z_bin_nm : float
        z histogram bin (nm).
    blur_nm : float, optional
        Gaussian blur (sigma, nm) of the xy images; default the median of ``sigma_x_nm`` and
        ``sigma_y_nm`` where the table has them, else ``bin_nm``. Raised to at least
        ``bin_nm / 2`` because the sub-bin fit needs a peak a few bins wide. The z blur is the
        median ``sigma_z_nm``, else ``z_bin_nm`` (at least ``z_bin_nm / 2``).
    max_shift_nm : float
        Largest shift between two segments that is searched (nm), per axis.
    estimate_z : bool
        Estimate z drift (only when the table has a non-constant ``z_nm``).
    min_locs_per_segment : int
        Fewest localizations a segment may hold; with fewer, the number of segments is reduced
        (with a warning).
    all_flags : bool
        Use rows flagged other than "ok" too.
    log_warnings : bool
        Log each of the result's ``warnings`` (False: the caller shows them itself, e.g. in a
        refusal or a report, where logged as well they would be said twice).

    Returns
    -------
    DriftResult
        ``method="rcc"``; zero at the first frame. ``reliable`` is False (with ``warnings``)
        when fewer than 3 segments remain, or, separately for xy and z: the pairs with a valid
        peak do not link every segment; more than a third of the pairs had no valid peak
        (contrast below :data:`MIN_PEAK_CONTRAST`, or at the ``max_shift_nm`` limit) or were
        rejected as inconsistent; the robust residual scale of the pairs kept exceeds one bin
        (``bin_nm``, ``z_bin_nm``); a segment is left with fewer than 2 consistent pairs; or
        two segment shifts differ by more than ``max_shift_nm`` less one bin.
        ``details["reliable_xy"]`` and ``details["reliable_z"]`` give the verdict per stage.

    Raises
    ------
    ValueError
        For an empty table, bad parameters, fewer frames than segments, or too few
        localizations for two segments of ``min_locs_per_segment``.
    """
    p = _rcc_params(segments, bin_nm, z_bin_nm, blur_nm, max_shift_nm, min_locs_per_segment)
    data = read_locs(locs, all_flags=all_flags)
    warnings: list[str] = []
    seg = _segments(data.frame, p.segments, p.min_locs, warnings)
    blur = p.blur_nm if p.blur_nm is not None else (data.sigma_lat or p.bin_nm)
    blur = max(float(blur), 0.5 * p.bin_nm)
    shifts = np.zeros((seg.n_seg, 3))
    xy = _rcc_xy(data, seg, p, blur, warnings)
    shifts[:, :2] = xy.shifts
    z = _rcc_z(data, seg, shifts[:, :2], p, blur, estimate_z, warnings)
    shifts[:, 2] = z.shifts[:, 0]
    for w in warnings if log_warnings else ():
        log.warning("rcc_drift: %s", w)
    return _rcc_result(data, seg, shifts, xy, z, p, blur, warnings)


@dataclass(frozen=True)
class _RccParams:
    """The checked parameters of :func:`rcc_drift` (lengths in nm)."""

    segments: int
    bin_nm: float
    z_bin_nm: float
    blur_nm: float | None
    max_shift_nm: float
    min_locs: int


def _rcc_params(
    segments: int,
    bin_nm: float,
    z_bin_nm: float,
    blur_nm: float | None,
    max_shift_nm: float,
    min_locs_per_segment: int,
) -> _RccParams:
    """The parameters of :func:`rcc_drift`, checked; ``ValueError`` naming a bad one."""
    if int(segments) != segments or segments < 2:
        raise ValueError(f"segments must be an integer >= 2, got {segments!r}")
    segments = int(segments)
    bin_nm = positive("bin_nm", bin_nm)
    z_bin_nm = positive("z_bin_nm", z_bin_nm)
    max_shift_nm = positive("max_shift_nm", max_shift_nm)
    if blur_nm is not None and blur_nm != 0:
        blur_nm = positive("blur_nm", blur_nm)
    if max_shift_nm < 3 * bin_nm:
        raise ValueError(
            f"max_shift_nm ({max_shift_nm:g}) must be at least 3 bins ({3 * bin_nm:g} nm)"
        )
    if int(min_locs_per_segment) != min_locs_per_segment or min_locs_per_segment < 1:
        raise ValueError(
            f"min_locs_per_segment must be a positive integer, got {min_locs_per_segment!r}"
        )
    return _RccParams(segments, bin_nm, z_bin_nm, blur_nm, max_shift_nm, int(min_locs_per_segment))


@dataclass
class _Segments:
    """The time segments of an RCC estimate."""

    f0: int  # first frame of the table
    f1: int  # last frame
    index: NDArray  # (N,) segment of each localization
    n_seg: int
    counts: NDArray  # (S,) localizations per segment
    centres: NDArray  # (S,) mean frame of each segment's localizations
    pairs: NDArray  # (P, 2) segment indices i < j of every pair


def _segments(frame: NDArray, segments: int, min_locs: int, warnings: list[str]) -> _Segments:
    """Cut the frames into segments (fewer than asked when some would hold too few
    localizations) and list their pairs; warns when fewer than 3 remain."""
    f0, f1 = int(frame.min()), int(frame.max())
    n_frames = f1 - f0 + 1
    if n_frames < 2:
        raise ValueError(
            f"the table spans one frame ({f0}); drift needs localizations in at least 2 frames"
        )
    if n_frames < segments:
        raise ValueError(
            f"the table spans {n_frames} frames ({f0}..{f1}), fewer than the {segments} "
            f"segments asked for; use between 2 and {n_frames} segments (drift --segments)"
        )
    seg, n_seg = _choose_segments(frame, f0, n_frames, segments, min_locs, warnings)
    counts = np.bincount(seg, minlength=n_seg)
    centres = np.bincount(seg, weights=frame, minlength=n_seg) / counts
    pairs = np.array([(i, j) for i in range(n_seg) for j in range(i + 1, n_seg)], dtype=np.int64)
    if n_seg < 3:
        warnings.append(
            f"only {n_seg} segments: the single pair cannot be cross-checked (need >= 3)"
        )
    return _Segments(f0, f1, seg, n_seg, counts, centres, pairs)


@dataclass
class _Stage:
    """One stage of an RCC estimate (xy or z): what each pair measured and the solution."""

    d: NDArray  # (P, D) measured pair shifts (nm), NaN where no valid peak was found
    contrast: NDArray  # (P,) peak contrast in robust noise units
    used: NDArray  # (P,) whether each pair entered the final solution
    residuals: NDArray  # (P, D) against the final solution (nm)
    shifts: NDArray  # (S, D) segment shifts (nm)
    scale: float  # robust residual scale (nm) of the pairs used
    reliable: bool
    details: dict[str, Any]  # entries of DriftResult.details that only this stage knows


def _rcc_xy(
    data: DriftLocs, seg: _Segments, p: _RccParams, blur: float, warnings: list[str]
) -> _Stage:
    """The xy stage: correlate every pair of segment images and solve for the shifts."""
    d_xy, contrast_xy, valid_xy, grid = _pair_shifts_xy(
        data.xyz[:, :2], seg.index, seg.n_seg, seg.pairs, p.bin_nm, blur, p.max_shift_nm
    )
    sol = _solve(seg.n_seg, seg.pairs, d_xy, valid_xy, floor=p.bin_nm)
    ok = _check(sol, valid_xy, seg.n_seg, p.max_shift_nm, p.bin_nm, "xy", warnings)
    return _Stage(
        d_xy, contrast_xy, sol.used, sol.residuals, sol.shifts, sol.scale, ok, {"image_shape": grid}
    )


def _rcc_z(
    data: DriftLocs,
    seg: _Segments,
    xy_shifts: NDArray,
    p: _RccParams,
    blur: float,
    estimate_z: bool,
    warnings: list[str],
) -> _Stage:
    """The z stage, on the localizations corrected by the xy segment shifts (S, 2); all NaN
    and zero shifts when z is not estimated."""
    n_pairs, n_seg = len(seg.pairs), seg.n_seg
    if not (estimate_z and data.has_z):
        if estimate_z:
            log.info("rcc_drift: the table has no (non-constant) z_nm; z drift not estimated")
        return _Stage(
            d=np.full((n_pairs, 1), np.nan),
            contrast=np.full(n_pairs, np.nan),
            used=np.zeros(n_pairs, dtype=bool),
            residuals=np.full((n_pairs, 1), np.nan),
            shifts=np.zeros((n_seg, 1)),
            scale=math.nan,
            reliable=True,
            details={"z_estimated": False},
        )
    corr_xy = data.xyz[:, :2] - _interpolate(seg.centres, xy_shifts, data.frame)
    blur_z = max(float(data.sigma_z or p.z_bin_nm), 0.5 * p.z_bin_nm)
    xy_bin_z = max(2.0 * p.bin_nm, 4.0 * blur)
    d_z, contrast_z, valid_z = _pair_shifts_z(
        corr_xy,
        data.xyz[:, 2],
        seg.index,
        n_seg,
        seg.pairs,
        xy_bin_z,
        p.z_bin_nm,
        blur_z,
        p.max_shift_nm,
    )
    sol = _solve(n_seg, seg.pairs, d_z, valid_z, floor=p.z_bin_nm)
    ok = _check(sol, valid_z, n_seg, p.max_shift_nm, p.z_bin_nm, "z", warnings)
    if not ok:
        warnings.append(
            "z: too few reliable z correlations; use fewer segments (more localizations in "
            "each), or estimate x and y only (drift --no-z)"
        )
    details = {
        "z_estimated": True,
        "reliable_z": bool(ok),
        "blur_z_nm": blur_z,
        "xy_bin_for_z_nm": xy_bin_z,
        "residual_scale_z_nm": sol.scale,
        "pairs_used_z": int(sol.used.sum()),
    }
    return _Stage(d_z, contrast_z, sol.used, sol.residuals, sol.shifts, sol.scale, ok, details)


#: One-sided significance of the successive-difference test in :func:`no_drift_caution`.
NO_DRIFT_P = 0.01


def smooth_p(shifts: NDArray) -> NDArray[np.float64]:
    """(D,): for each axis, how likely segment shifts this smooth are as independent noise.

    Von Neumann's ratio ``eta = sum (s[j+1] - s[j])^2 / sum (s[j] - mean)^2`` is about 2 for
    independent values and small for a drift (a drift changes little from one segment to the
    next); under independence it is about normal with mean 2 and variance
    ``4 (S - 2) / (S^2 - 1)``. Its smallest possible value, ``4 sin^2(pi / 2S)``, is that of
    the smoothest series: with few segments even a straight line is not told apart from noise
    (at :data:`NO_DRIFT_P`, fewer than 6 segments), and the answer is NaN, as for a constant
    axis.

    Parameters
    ----------
    shifts : ndarray, shape (S, D)
        Segment shifts (nm), in time order.

    Returns
    -------
    ndarray, shape (D,)
        The one-sided chance of a ratio this small under independence, per axis.
    """
    from scipy.stats import norm

    s = np.asarray(shifts, dtype=np.float64)
    n = s.shape[0]
    if n < 3:
        return np.full(s.shape[1], np.nan)
    sd = np.sqrt(4.0 * (n - 2) / (n * n - 1.0))
    if norm.cdf((4.0 * np.sin(np.pi / (2 * n)) ** 2 - 2.0) / sd) >= NO_DRIFT_P:
        return np.full(s.shape[1], np.nan)
    dev = np.sum((s - s.mean(axis=0)) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        eta = np.sum(np.diff(s, axis=0) ** 2, axis=0) / dev
    return np.where(dev > 0, norm.cdf((eta - 2.0) / sd), np.nan)


def no_drift_caution(result: DriftResult) -> str | None:
    """A caution when an RCC estimate's segment shifts look like independent noise in every
    axis, not like a drift (:func:`smooth_p` above :data:`NO_DRIFT_P`): the apparent shifts
    of segments that hold different molecules; correcting then moves the table by them.
    None otherwise, for fiducial estimates and where the segments are too few to tell
    (:func:`smooth_p`).

    Parameters
    ----------
    result : DriftResult
        A drift estimate.

    Returns
    -------
    str or None
        One sentence, or None.
    """
    shifts = result.segment_shifts
    if result.method != "rcc" or shifts is None:
        return None
    axes = 3 if result.details.get("z_estimated") else 2
    p = smooth_p(shifts[:, :axes])
    if np.any(~np.isfinite(p)) or np.any(p < NO_DRIFT_P):
        return None
    names = "x, y and z" if axes == 3 else "x and y"
    return (
        f"the {len(shifts)} segments' shifts vary from one segment to the next like noise in "
        f"{names}, not like a drift: this table may not drift, and the correction moves it by "
        "that noise"
    )


def lateral_only(result: DriftResult) -> DriftResult | None:
    """An RCC estimate whose x and y passed their checks but z did not, with z left alone
    (``dz`` = 0) and the z warnings moved to ``details["z_dropped"]``; None for any other
    estimate (reliable, or unreliable in x and y)."""
    d = result.details
    if result.reliable or not d.get("reliable_xy") or d.get("reliable_z", True):
        return None
    if d.get("segments", 0) < 3:
        return None
    drift = result.drift.copy()
    drift[:, 2] = 0.0
    z_notes = [w for w in result.warnings if w.startswith("z:")]
    rest = [w for w in result.warnings if not w.startswith("z:")]
    return replace(
        result,
        drift=drift,
        reliable=not rest,
        warnings=rest,
        details={**d, "z_estimated": False, "z_dropped": z_notes},
    )


def _rcc_result(
    data: DriftLocs,
    seg: _Segments,
    shifts: NDArray,
    xy: _Stage,
    z: _Stage,
    p: _RccParams,
    blur: float,
    warnings: list[str],
) -> DriftResult:
    """The segment shifts (S, 3) interpolated to every frame, referenced to the first one."""
    frames = np.arange(seg.f0, seg.f1 + 1)
    curve = _interpolate(seg.centres, shifts, frames)
    ref = curve[0].copy()  # drift is defined up to a constant: zero at the first frame
    return DriftResult(
        frames=frames,
        drift=curve - ref,
        method="rcc",
        reliable=bool(seg.n_seg >= 3 and xy.reliable and z.reliable),
        warnings=warnings,
        segment_frames=seg.centres,
        segment_shifts=shifts - ref,
        pairs=seg.pairs,
        pair_shifts=np.concatenate([xy.d, z.d], axis=1),
        pair_residuals=np.concatenate([xy.residuals, z.residuals], axis=1),
        pair_used=np.stack([xy.used, z.used], axis=1),
        pair_contrast=np.stack([xy.contrast, z.contrast], axis=1),
        details={
            "segments_requested": p.segments,
            "segments": seg.n_seg,
            "locs_per_segment": seg.counts.tolist(),
            "locs_used": int(data.frame.size),
            "locs_input": data.n_input,
            "bin_nm": p.bin_nm,
            "blur_nm": blur,
            "z_bin_nm": p.z_bin_nm,
            "max_shift_nm": p.max_shift_nm,
            **xy.details,
            "reliable_xy": bool(xy.reliable),
            "residual_scale_xy_nm": xy.scale,
            "pairs": len(seg.pairs),
            "pairs_used_xy": int(xy.used.sum()),
            **z.details,
        },
    )


def _segment_index(frame: NDArray, f0: int, n_frames: int, n_seg: int) -> NDArray[np.int64]:
    """Segment of each frame: ``n_seg`` consecutive blocks of (nearly) equal frame count."""
    return ((frame - f0) * n_seg // n_frames).astype(np.int64)


def _choose_segments(
    frame: NDArray, f0: int, n_frames: int, segments: int, min_locs: int, warnings: list[str]
) -> tuple[NDArray[np.int64], int]:
    """Largest segment count <= ``segments`` whose every segment has ``min_locs`` locs."""
    n = frame.size
    n_seg = segments
    first_counts = None
    while n_seg >= 2:
        seg = _segment_index(frame, f0, n_frames, n_seg)
        counts = np.bincount(seg, minlength=n_seg)
        if first_counts is None:
            first_counts = counts
        if counts.min() >= min_locs:
            break
        n_seg = min(n_seg - 1, n // min_locs)
    else:
        raise ValueError(
            f"too few localizations for drift correction: {n} usable in frames "
            f"{f0}..{f0 + n_frames - 1}; RCC needs at least 2 time segments of {min_locs} "
            f"localizations each (the emptiest of {segments} segments held "
            f"{int(first_counts.min())})"
        )
    if n_seg < segments:
        warnings.append(
            f"reduced segments from {segments} to {n_seg}: with {segments} the emptiest segment "
            f"held {int(first_counts.min())} localizations (fewer than the {min_locs} needed)"
        )
    return seg, n_seg


def _pair_shifts_xy(
    xy: NDArray,
    seg: NDArray,
    n_seg: int,
    pairs: NDArray,
    bin_nm: float,
    blur_nm: float,
    max_shift_nm: float,
) -> tuple[NDArray, NDArray, NDArray, tuple[int, int]]:
    """Measured shift (P, 2) nm, contrast (P,) and validity (P,) of every pair."""
    lo = xy.min(axis=0)
    ix = np.floor((xy[:, 0] - lo[0]) / bin_nm).astype(np.int64)
    iy = np.floor((xy[:, 1] - lo[1]) / bin_nm).astype(np.int64)
    nx, ny = int(ix.max()) + 1, int(iy.max()) + 1
    m = math.ceil(max_shift_nm / bin_nm) + 1  # +1: the 3x3 fit needs a ring outside
    mw = max(m, math.ceil(NOISE_WINDOW_NM / bin_nm) + 1)  # window for the noise estimate
    sig = blur_nm / bin_nm
    # zero padding so that circular correlation does not alias within +-mw (blur widens it)
    pad = mw + math.ceil(4 * math.sqrt(2) * sig) + 1
    shape = (sfft.next_fast_len(ny + pad, real=True), sfft.next_fast_len(nx + pad, real=True))
    if shape[0] * shape[1] > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"the field ({nx * bin_nm:.0f} x {ny * bin_nm:.0f} nm) in {bin_nm:g} nm bins needs "
            f"{shape[1]} x {shape[0]} bin images, above {MAX_IMAGE_PIXELS} pixels: use a "
            "larger bin (drift --bin-nm)"
        )
    # Gaussian blur of each image as a transfer function (sigma in bins, frequencies in cycles
    # per bin); applied to both images it blurs the correlation by sigma * sqrt(2).
    fy = sfft.fftfreq(shape[0]).astype(np.float32)
    fx = sfft.rfftfreq(shape[1]).astype(np.float32)
    gy = np.exp(-2 * np.pi**2 * sig**2 * fy**2)
    gx = np.exp(-2 * np.pi**2 * sig**2 * fx**2)
    flat = iy * nx + ix

    def spectrum(k: int) -> NDArray:
        img = np.bincount(flat[seg == k], minlength=nx * ny).astype(np.float32).reshape(ny, nx)
        spec = sfft.rfft2(img, s=shape, workers=-1)
        spec *= gy[:, None]
        spec *= gx[None, :]
        return spec

    spec_bytes = n_seg * shape[0] * (shape[1] // 2 + 1) * 8
    cache = spec_bytes <= SPECTRA_BUDGET_BYTES
    if not cache:
        log.info(
            "rcc_drift: spectra of %d segments would take %.0f MiB; recomputing per pair",
            n_seg,
            spec_bytes / 2**20,
        )
    specs = [spectrum(k) for k in range(n_seg)] if cache else None
    idx_y = np.arange(-mw, mw + 1) % shape[0]
    idx_x = np.arange(-mw, mw + 1) % shape[1]
    d = np.full((len(pairs), 2), np.nan)
    contrast = np.zeros(len(pairs))
    valid = np.zeros(len(pairs), dtype=bool)
    for p, (i, j) in enumerate(pairs):
        si = specs[i] if specs is not None else spectrum(i)
        sj = specs[j] if specs is not None else spectrum(j)
        # c[s] = sum_p A(p) B(p + s): peaks at the displacement of segment j relative to i
        full = sfft.irfft2(np.conj(si) * sj, s=shape, workers=-1)
        crop = full[np.ix_(idx_y, idx_x)].astype(np.float64)
        peak, contrast[p] = _peak_2d(crop, m)
        if peak is not None:
            d[p] = (peak[1] - m) * bin_nm, (peak[0] - m) * bin_nm
            valid[p] = contrast[p] >= MIN_PEAK_CONTRAST
    return d, contrast, valid, shape


def _robust_contrast(window: NDArray, peak_value: float) -> float:
    """Peak height above the window median, in robust noise units (1.4826 MAD, else std)."""
    base = float(np.median(window))
    noise = 1.4826 * float(np.median(np.abs(window - base)))
    if noise <= 0:
        noise = float(np.std(window))
    if noise <= 0:
        return 0.0
    return (peak_value - base) / noise


# least-squares fit of a + b x + c y + d x^2 + e x y + f y^2 to a 3 x 3 neighbourhood
_GY, _GX = np.mgrid[-1:2, -1:2]
_QUAD = np.stack(
    [np.ones(9), _GX.ravel(), _GY.ravel(), _GX.ravel() ** 2, (_GX * _GY).ravel(), _GY.ravel() ** 2],
    axis=1,
)
_QUAD_PINV = np.linalg.pinv(_QUAD)


def _peak_2d(crop: NDArray, m: int) -> tuple[tuple[float, float] | None, float]:
    """Maximum of the central ``(2m + 1)^2`` bins of the square ``crop``: its sub-bin (row,
    col) in those bins, or None on their border; and its contrast against the whole crop."""
    off0 = (crop.shape[0] - (2 * m + 1)) // 2
    inner = crop[off0 : off0 + 2 * m + 1, off0 : off0 + 2 * m + 1]
    r, c = np.unravel_index(int(np.argmax(inner)), inner.shape)
    top = float(inner[r, c])
    contrast = _robust_contrast(crop, top)
    if not (0 < r < 2 * m and 0 < c < 2 * m) or top <= 0:
        return None, contrast  # at the +-max_shift limit: the true peak may lie beyond
    nb = inner[r - 1 : r + 2, c - 1 : c + 2]
    # log of a Gaussian peak is exactly quadratic
    logv = np.log(np.maximum(nb, top * 1e-6)).ravel()
    _, b, cy, dxx, exy, fyy = _QUAD_PINV @ logv
    hess = np.array([[2 * dxx, exy], [exy, 2 * fyy]])
    off = None
    if np.all(np.linalg.eigvalsh(hess) < 0):
        off = -np.linalg.solve(hess, [b, cy])
        if np.any(np.abs(off) > 1.0):
            off = None
    if off is None:  # not a clean maximum: separable 1D fits through the maximum
        off = np.array([_parabola(logv[3], logv[4], logv[5]), _parabola(logv[1], logv[4], logv[7])])
    return (r + float(off[1]), c + float(off[0])), contrast


def _parabola(left: float, mid: float, right: float) -> float:
    """Vertex offset (bins, within +-0.5) of the parabola through three equally spaced points."""
    den = left - 2 * mid + right
    if den >= 0:
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def _pair_shifts_z(
    xy: NDArray,
    z: NDArray,
    seg: NDArray,
    n_seg: int,
    pairs: NDArray,
    xy_bin: float,
    z_bin: float,
    blur_z: float,
    max_shift_nm: float,
) -> tuple[NDArray, NDArray, NDArray]:
    """z shift (P, 1) nm, contrast (P,) and validity (P,) of every pair, at zero xy shift."""
    lo = xy.min(axis=0)
    ix = np.floor((xy[:, 0] - lo[0]) / xy_bin).astype(np.int64)
    iy = np.floor((xy[:, 1] - lo[1]) / xy_bin).astype(np.int64)
    pix = iy * (int(ix.max()) + 1) + ix
    n_pix = int(pix.max()) + 1
    iz = np.floor((z - z.min()) / z_bin).astype(np.int64)
    nz = int(iz.max()) + 1
    # one sparse (xy bin) x (z bin) histogram per segment; coincidences of the same xy bin only
    mats = []
    for k in range(n_seg):
        sel = seg == k
        mats.append(
            sparse.csr_matrix((np.ones(int(sel.sum())), (pix[sel], iz[sel])), shape=(n_pix, nz))
        )
    m = min(math.ceil(max_shift_nm / z_bin) + 1, nz - 1)
    mw = min(max(m, math.ceil(NOISE_WINDOW_NM / z_bin) + 1), nz - 1)
    sig = math.sqrt(2) * blur_z / z_bin  # blur of the correlation, bins
    d = np.full((len(pairs), 1), np.nan)
    contrast = np.zeros(len(pairs))
    valid = np.zeros(len(pairs), dtype=bool)
    if m < 2:
        return d, contrast, valid  # the z range spans fewer than 3 bins
    for p, (i, j) in enumerate(pairs):
        # Coincidences at z bins (a in i, b in j), kept sparse (one far z outlier must not
        # make an nz x nz array); the lag of C[a, b] is b - a, shifted to >= 0.
        cm = (mats[i].T @ mats[j]).tocoo()
        corr = np.bincount(cm.col - cm.row + nz - 1, weights=cm.data, minlength=2 * nz - 1)
        corr = gaussian_filter1d(corr, sig, mode="constant")
        inner = corr[nz - 1 - m : nz + m]
        r = int(np.argmax(inner))
        top = float(inner[r])
        contrast[p] = _robust_contrast(corr[nz - 1 - mw : nz + mw], top)
        if 0 < r < inner.size - 1 and top > 0:
            logv = np.log(np.maximum(inner[r - 1 : r + 2], top * 1e-6))
            d[p, 0] = (r - m + _parabola(*logv)) * z_bin
            valid[p] = contrast[p] >= MIN_PEAK_CONTRAST
    return d, contrast, valid


@dataclass
class _Solution:
    shifts: NDArray  # (S, D)
    used: NDArray  # (P,) bool
    residuals: NDArray  # (P, D)
    scale: float  # robust residual scale (nm) of the used pairs
    connected: bool  # every segment linked to segment 0 through used pairs
    removed: int  # pairs rejected as inconsistent
    links: NDArray  # (S,) used pairs that involve each segment


def _solve(n_seg: int, pairs: NDArray, d: NDArray, valid: NDArray, floor: float) -> _Solution:
    """Least squares ``s_j - s_i = d_ij`` (``s_0 = 0``) with iterative outlier rejection."""
    n_dim = d.shape[1]
    used = valid.copy()
    removed = 0
    design = np.zeros((len(pairs), n_seg))
    design[np.arange(len(pairs)), pairs[:, 1]] = 1.0
    design[np.arange(len(pairs)), pairs[:, 0]] = -1.0

    def connected(mask: NDArray) -> bool:
        if n_seg == 1:
            return True
        pr = pairs[mask]
        graph = sparse.coo_matrix((np.ones(len(pr)), (pr[:, 0], pr[:, 1])), (n_seg, n_seg))
        return connected_components(graph, directed=False)[0] == 1

    def lstsq(mask: NDArray) -> NDArray:
        s = np.zeros((n_seg, n_dim))
        if mask.any():
            sol, *_ = np.linalg.lstsq(design[mask][:, 1:], d[mask], rcond=None)
            s[1:] = sol
        return s

    is_connected = connected(used)
    shifts = lstsq(used)
    while True:
        resid = np.where(used[:, None], d - (shifts[pairs[:, 1]] - shifts[pairs[:, 0]]), np.nan)
        r_used = resid[used]
        scale = 1.4826 * float(np.median(np.abs(r_used))) if r_used.size else math.nan
        if not is_connected or used.sum() <= n_seg - 1:
            break  # no redundancy left to judge consistency with
        thresh = max(OUTLIER_SIGMAS * scale, floor)
        worst_val = np.nanmax(np.abs(resid), axis=1, initial=0.0)
        worst = int(np.argmax(np.where(used, worst_val, -1.0)))
        if worst_val[worst] <= thresh:
            break
        trial = used.copy()
        trial[worst] = False
        if not connected(trial):
            break  # keep the pair: dropping it would leave a segment undetermined
        used = trial
        removed += 1
        shifts = lstsq(used)
    # residuals of every measured pair (rejected ones too) against the final solution
    pred = shifts[pairs[:, 1]] - shifts[pairs[:, 0]]
    residuals = d - pred
    links = np.bincount(pairs[used].ravel(), minlength=n_seg)
    return _Solution(shifts, used, residuals, scale, is_connected, removed, links)


def _check(
    sol: _Solution,
    valid: NDArray,
    n_seg: int,
    max_shift_nm: float,
    floor: float,
    axis: str,
    warnings: list[str],
) -> bool:
    """Append warnings for an untrustworthy solution; return whether it is reliable."""
    n_pairs = valid.size
    ok = True
    if not sol.connected:
        warnings.append(
            f"{axis}: only {int(valid.sum())} of {n_pairs} segment pairs gave a valid "
            "correlation peak and they do not link every segment: some segment shifts are "
            "undetermined"
        )
        return False
    n_bad = n_pairs - int(sol.used.sum())
    if n_pairs >= 3 and n_bad > MAX_REJECTED_FRACTION * n_pairs:
        warnings.append(
            f"{axis}: {n_bad} of {n_pairs} segment pairs were not used "
            f"({n_pairs - int(valid.sum())} without a clear correlation peak, {sol.removed} "
            "inconsistent with the others; "
            f"robust residual scale {sol.scale:.1f} nm)"
        )
        ok = False
    if n_seg >= 3 and sol.scale > floor:
        warnings.append(
            f"{axis}: the segment pairs disagree: robust residual scale {sol.scale:.1f} nm "
            f"exceeds one bin ({floor:g} nm)"
        )
        ok = False
    if n_seg >= 3:
        links = sol.links
        weak = np.nonzero(links < 2)[0]
        if weak.size:
            warnings.append(
                f"{axis}: segment(s) {', '.join(map(str, weak.tolist()))} rest on fewer than 2 "
                "consistent pairs: their shifts cannot be cross-checked"
            )
            ok = False
    # a pair whose solved shift lies within a bin of the searched window's edge cannot have
    # been measured (the sub-bin fit needs a ring of bins inside the window)
    span = float(np.max(np.abs(sol.shifts.max(axis=0) - sol.shifts.min(axis=0))))
    if span > max_shift_nm - floor:
        warnings.append(
            f"{axis}: the segment shifts span {span:.0f} nm, reaching the searched "
            f"+-{max_shift_nm:g} nm: pairs further apart cannot be measured (the Python API's "
            "rcc_drift can raise max_shift_nm)"
        )
        ok = False
    return ok


def _interpolate(centres: NDArray, values: NDArray, frames: ArrayLike) -> NDArray:
    """Segment values (S, D) at ``centres`` (S,) evaluated at ``frames``: natural cubic spline
    inside, the end tangents extended linearly outside (a straight line for two segments)."""
    t = np.asarray(frames, dtype=np.float64)
    if centres.size == 1:
        return np.repeat(values[:1], t.size, axis=0)
    if centres.size == 2:
        slope = (values[1] - values[0]) / (centres[1] - centres[0])
        return values[0] + (t - centres[0])[:, None] * slope
    spline = CubicSpline(centres, values, axis=0, bc_type="natural")
    lo, hi = centres[0], centres[-1]
    out = spline(np.clip(t, lo, hi))
    below, above = t < lo, t > hi
    if below.any():
        out[below] += (t[below] - lo)[:, None] * spline(lo, 1)
    if above.any():
        out[above] += (t[above] - hi)[:, None] * spline(hi, 1)
    return out


# --------------------------------------------------------------------------------------------
# applying
# --------------------------------------------------------------------------------------------


def apply_drift(locs: pd.DataFrame, drift: DriftResult) -> pd.DataFrame:
    """Subtract a drift estimate from a localization table.

    Parameters
    ----------
    locs : DataFrame
        Table with at least ``frame, x_nm, y_nm`` (nm); ``z_nm`` is corrected where present.
    drift : DriftResult
        The estimate; frames outside its range take the drift of the nearest end.

    Returns
    -------
    DataFrame
        A copy with ``x_nm, y_nm`` (and ``z_nm``) minus the drift of each row's frame; the input
        is not modified.
    """
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(
            f"the localization table must be a pandas DataFrame, got {type(locs).__name__}"
        )
    if not isinstance(drift, DriftResult):
        raise ValueError(f"drift must be a DriftResult, got {type(drift).__name__}")
    missing = [c for c in ("frame", "x_nm", "y_nm") if c not in locs.columns]
    if missing:
        raise ValueError(f"the localization table is missing the column(s) {', '.join(missing)}")
    out = locs.copy()
    if len(out) == 0:
        return out
    frame = pd.to_numeric(out["frame"], errors="coerce").to_numpy(dtype=np.float64)
    shift = drift.at(frame)  # NaN frames give NaN positions rather than a silent wrong value
    for k, col in enumerate(("x_nm", "y_nm", "z_nm")):
        if col in out.columns:
            out[col] = out[col].to_numpy(dtype=np.float64) - shift[:, k]
    return out


# --------------------------------------------------------------------------------------------
# plot
# --------------------------------------------------------------------------------------------


def plot_drift(
    drift: DriftResult,
    path: str | Path,
    *,
    truth: NDArray | None = None,
    dpi: int = 120,
) -> Path:
    """Drift curves x, y, z (nm) against frame, written atomically to ``path``.

    Parameters
    ----------
    drift : DriftResult
        The estimate; its segment shifts (RCC) are drawn as markers, its per-frame raw drift
        (fiducials) as faint points.
    path : str or Path
        Output image (format from the suffix, e.g. ``.png``).
    truth : ndarray, shape (F, 2) or (F, 3), optional
        True drift (nm) at ``drift.frames``, drawn dashed; shifted to zero at the first frame
        like the estimate.
    dpi : int
        Resolution.

    Returns
    -------
    Path
        ``path``.
    """
    from matplotlib.figure import Figure

    from .plotting import save_figure

    if truth is not None:
        truth = np.asarray(truth, dtype=np.float64)
        if truth.ndim != 2 or truth.shape[0] != drift.frames.size or truth.shape[1] not in (2, 3):
            raise ValueError(
                f"truth must have shape ({drift.frames.size}, 2 or 3) to match the drift's "
                f"frames, got {truth.shape}"
            )
        truth = truth - truth[0]
    fig = Figure(figsize=(7.0, 4.0))
    ax = fig.subplots()
    colours = ("C0", "C1", "C2")
    z_dropped = bool(drift.details.get("z_dropped"))  # estimated, found unreliable, not applied
    z_off = not drift.details.get("z_estimated", True)
    for k, name in enumerate("xyz"):
        c = colours[k]
        label = f"d{name}"
        if k == 2 and z_off:
            label += " (not corrected: unreliable)" if z_dropped else " (not estimated)"
        points = not (k == 2 and z_off)  # a rejected z's segment shifts are not the drift
        if points and drift.raw_drift is not None:
            ax.plot(drift.frames, drift.raw_drift[:, k], ",", color=c, alpha=0.3)
        ax.plot(drift.frames, drift.drift[:, k], color=c, lw=1.5, label=label)
        if points and drift.segment_frames is not None and drift.segment_shifts is not None:
            ax.plot(drift.segment_frames, drift.segment_shifts[:, k], "o", color=c, ms=4)
        if truth is not None and k < truth.shape[1]:
            ax.plot(drift.frames, truth[:, k], "--", color=c, lw=1, label=f"d{name} truth")
    ax.set_xlabel("frame")
    ax.set_ylabel("drift (nm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    status = "reliable" if drift.reliable else "UNRELIABLE"
    if drift.reliable and z_dropped:
        status = "x and y reliable; z unreliable, not corrected"
    ax.set_title(f"{drift.method} drift ({status})", fontsize=9)
    return save_figure(fig, path, dpi)
