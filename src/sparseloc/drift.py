"""Drift correction of localization tables: redundant cross-correlation and fiducials.

Sign convention: if the sample moves so that a molecule truly at ``p`` appears at
``p + d(frame)``, the estimated drift is ``d(frame)`` and :func:`apply_drift` subtracts it.
Drift is only defined up to a constant; every estimate here is referenced to the first frame of
the table (``drift[0] == 0``).

Methods
-------
:func:`rcc_drift`
    Redundant cross-correlation (RCC; Wang et al., Opt. Express 22, 15982, 2014): the movie is
    split into time segments, each rendered as a histogram image; every pair of segments is
    cross-correlated, the over-determined system ``s_j - s_i = d_ij`` is solved by least squares
    with iterative rejection of inconsistent pairs, and the segment shifts are interpolated to
    every frame. z follows from the xy-corrected localizations.
:func:`fiducial_drift`
    Tracks of spots present in most frames (beads), averaged.

Both return a :class:`DriftResult` whose ``reliable`` flag and ``warnings`` say when the
estimate should not be trusted. Lengths are in nm, frames are 0-based integers.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray
from scipy import sparse
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d, median_filter, uniform_filter1d
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["DriftResult", "apply_drift", "fiducial_drift", "plot_drift", "rcc_drift"]

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
# result
# --------------------------------------------------------------------------------------------


@dataclass
class DriftResult:
    """A drift estimate for every frame of a localization table.

    Attributes
    ----------
    frames : ndarray of int, shape (F,)
        Every frame from the table's first to its last.
    drift : ndarray of float, shape (F, 3)
        ``dx, dy, dz`` (nm) to subtract from the localizations of each frame; zero at
        ``frames[0]``. ``dz`` is zero where z was not estimated (2D tables).
    method : str
        ``"rcc"`` or ``"fiducial"``.
    reliable : bool
        False when a check failed; ``warnings`` says which.
    warnings : list of str
        Human-readable notes (also logged); non-empty whenever ``reliable`` is False.
    segment_frames : ndarray, shape (S,), optional
        RCC: mean frame of each time segment's localizations.
    segment_shifts : ndarray, shape (S, 3), optional
        RCC: shift of each segment (nm), in the same reference as ``drift``.
    pairs : ndarray of int, shape (P, 2), optional
        RCC: segment indices ``i < j`` of every correlated pair.
    pair_shifts : ndarray, shape (P, 3), optional
        RCC: measured ``d_ij`` (nm), NaN where no valid peak was found.
    pair_residuals : ndarray, shape (P, 3), optional
        RCC: ``d_ij - (s_j - s_i)`` (nm) of the final solution.
    pair_used : ndarray of bool, shape (P, 2), optional
        RCC: whether each pair entered the final xy (column 0) and z (column 1) solution.
    pair_contrast : ndarray, shape (P, 2), optional
        RCC: peak height above the window median in robust noise units, xy and z.
    fiducials : ndarray, shape (K, 3), optional
        Fiducial: median position of each fiducial (nm).
    raw_drift : ndarray, shape (F, 3), optional
        Fiducial: per-frame drift before smoothing (NaN in frames without a fiducial).
    details : dict
        Parameters in effect and summary numbers (bins, blur, residual scales, counts).
    """

    frames: NDArray[np.int64]
    drift: NDArray[np.float64]
    method: str
    reliable: bool = True
    warnings: list[str] = field(default_factory=list)
    segment_frames: NDArray[np.float64] | None = None
    segment_shifts: NDArray[np.float64] | None = None
    pairs: NDArray[np.int64] | None = None
    pair_shifts: NDArray[np.float64] | None = None
    pair_residuals: NDArray[np.float64] | None = None
    pair_used: NDArray[np.bool_] | None = None
    pair_contrast: NDArray[np.float64] | None = None
    fiducials: NDArray[np.float64] | None = None
    raw_drift: NDArray[np.float64] | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.frames = np.asarray(self.frames, dtype=np.int64)
        self.drift = np.asarray(self.drift, dtype=np.float64)
        if self.frames.ndim != 1 or self.frames.size == 0:
            raise ValueError(f"frames must be a non-empty 1D array, got shape {self.frames.shape}")
        if self.drift.shape != (self.frames.size, 3):
            raise ValueError(
                f"drift must have shape ({self.frames.size}, 3) for {self.frames.size} frames, "
                f"got {self.drift.shape}"
            )

    def at(self, frames: ArrayLike) -> NDArray[np.float64]:
        """Drift at arbitrary frames, clamped to the first / last frame outside the range.

        Parameters
        ----------
        frames : array_like, shape (N,)
            Frame numbers (integers or fractional).

        Returns
        -------
        ndarray, shape (N, 3)
            ``dx, dy, dz`` in nm.
        """
        f = np.atleast_1d(np.asarray(frames, dtype=np.float64))
        if f.ndim != 1:
            raise ValueError(f"frames must be a 1D array, got shape {f.shape}")
        ref = self.frames.astype(np.float64)
        # np.interp holds the end values outside the range: the clamping we want.
        return np.stack([np.interp(f, ref, self.drift[:, k]) for k in range(3)], axis=1)


# --------------------------------------------------------------------------------------------
# input
# --------------------------------------------------------------------------------------------


@dataclass
class _Locs:
    frame: NDArray[np.int64]
    xyz: NDArray[np.float64]  # (N, 3); z column 0 where has_z is False
    has_z: bool
    sigma_lat: float | None  # median lateral precision (nm) from the table, if any
    sigma_z: float | None
    n_input: int


def _read_locs(locs: pd.DataFrame) -> _Locs:
    """Usable rows (flag "ok" where the column exists, finite positions) as arrays."""
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(
            f"the localization table must be a pandas DataFrame, got {type(locs).__name__}"
        )
    missing = [c for c in ("frame", "x_nm", "y_nm") if c not in locs.columns]
    if missing:
        raise ValueError(f"the localization table is missing the column(s) {', '.join(missing)}")
    n_input = len(locs)
    if n_input == 0:
        raise ValueError("the localization table is empty (0 rows): nothing to estimate drift from")
    keep = np.ones(n_input, dtype=bool)
    if "flag" in locs.columns:
        keep &= locs["flag"].astype(str).to_numpy() == "ok"
    try:
        frame = pd.to_numeric(locs["frame"]).to_numpy(dtype=np.float64)
        x = pd.to_numeric(locs["x_nm"]).to_numpy(dtype=np.float64)
        y = pd.to_numeric(locs["y_nm"]).to_numpy(dtype=np.float64)
        z = pd.to_numeric(locs["z_nm"]).to_numpy(dtype=np.float64) if "z_nm" in locs else None
    except (ValueError, TypeError) as exc:
        raise ValueError("frame, x_nm, y_nm and z_nm must hold numbers") from exc
    keep &= np.isfinite(frame) & np.isfinite(x) & np.isfinite(y)
    if z is not None:
        keep &= np.isfinite(z)
    if not keep.any():
        raise ValueError(
            f"none of the {n_input} localizations is usable (flag 'ok' and finite frame and "
            "positions)"
        )
    if np.any(frame[keep] != np.round(frame[keep])):
        raise ValueError("the frame column must hold whole numbers")
    # a z column that is constant (e.g. 0 filled in by complete_locs for 2D data) carries no z
    has_z = z is not None and float(np.ptp(z[keep])) > 0.0
    xyz = np.zeros((int(keep.sum()), 3))
    xyz[:, 0], xyz[:, 1] = x[keep], y[keep]
    if has_z:
        xyz[:, 2] = z[keep]

    def _median(cols: tuple[str, ...]) -> float | None:
        vals = [pd.to_numeric(locs[c], errors="coerce").to_numpy(float)[keep] for c in cols]
        allv = np.concatenate(vals) if vals else np.empty(0)
        allv = allv[np.isfinite(allv) & (allv > 0)]
        return float(np.median(allv)) if allv.size else None

    lat_cols = tuple(c for c in ("sigma_x_nm", "sigma_y_nm") if c in locs.columns)
    sigma_lat = _median(lat_cols) if lat_cols else None
    sigma_z = _median(("sigma_z_nm",)) if "sigma_z_nm" in locs.columns and has_z else None
    return _Locs(frame[keep].astype(np.int64), xyz, has_z, sigma_lat, sigma_z, n_input)


def _positive(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


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
) -> DriftResult:
    """Drift by redundant cross-correlation of time segments (RCC).

    The frames are split into ``segments`` consecutive blocks of (nearly) equal length. Each
    block is rendered as an xy histogram (``bin_nm`` bins) blurred by a Gaussian of about the
    localization precision; every pair ``i < j`` is cross-correlated by FFT inside
    ``+-max_shift_nm``, and the peak is located to sub-bin precision by a least-squares
    quadratic fit to the logarithm of the 3 x 3 bins around the maximum (exact for a Gaussian
    peak of any orientation, which matters for the elongated peaks of filaments). The system
    ``s_j - s_i = d_ij`` is solved by least squares with ``s_0 = 0``; pairs whose residual
    exceeds ``max(3 x 1.4826 MAD of the residuals, one bin)`` in any axis are dropped one at a
    time, worst first, re-solving after each. z is then estimated the same way from the
    xy-corrected localizations: for every pair the z histograms of coincident xy bins are
    correlated at zero xy shift (a 3D correlation restricted to the known xy alignment, held as
    sparse matrices so that memory does not grow with the field).

    The segment shifts, placed at the mean frame of each segment's localizations, are
    interpolated to every frame by a natural cubic spline (smooth like real stage drift, no kinks
    at segment centres, and it follows curvature better than straight lines); before the first
    and after the last segment centre the spline's end tangent is extended linearly, so the half
    segment at each end keeps drifting instead of freezing (which would offset the whole curve
    once it is referenced to frame 0). Two segments give a straight line.

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``frame, x_nm, y_nm`` (``z_nm`` optional). Only rows
        with ``flag == "ok"`` (where the column exists) and finite positions are used.
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
    if int(segments) != segments or segments < 2:
        raise ValueError(f"segments must be an integer >= 2, got {segments!r}")
    segments = int(segments)
    bin_nm = _positive("bin_nm", bin_nm)
    z_bin_nm = _positive("z_bin_nm", z_bin_nm)
    max_shift_nm = _positive("max_shift_nm", max_shift_nm)
    if blur_nm is not None and blur_nm != 0:
        blur_nm = _positive("blur_nm", blur_nm)
    if max_shift_nm < 3 * bin_nm:
        raise ValueError(
            f"max_shift_nm ({max_shift_nm:g}) must be at least 3 bins ({3 * bin_nm:g} nm)"
        )
    if int(min_locs_per_segment) != min_locs_per_segment or min_locs_per_segment < 1:
        raise ValueError(
            f"min_locs_per_segment must be a positive integer, got {min_locs_per_segment!r}"
        )
    data = _read_locs(locs)
    f0, f1 = int(data.frame.min()), int(data.frame.max())
    n_frames = f1 - f0 + 1
    if n_frames < segments:
        raise ValueError(
            f"the table spans {n_frames} frame(s) ({f0}..{f1}), fewer than segments={segments}; "
            f"use at most {n_frames} segments"
        )
    warnings: list[str] = []
    reliable = True
    seg, n_seg = _choose_segments(
        data.frame, f0, n_frames, segments, int(min_locs_per_segment), warnings
    )
    counts = np.bincount(seg, minlength=n_seg)
    centres = np.bincount(seg, weights=data.frame, minlength=n_seg) / counts

    blur = blur_nm if blur_nm is not None else (data.sigma_lat or bin_nm)
    blur = max(float(blur), 0.5 * bin_nm)
    pairs = np.array([(i, j) for i in range(n_seg) for j in range(i + 1, n_seg)], dtype=np.int64)
    n_pairs = len(pairs)
    if n_seg < 3:
        reliable = False
        warnings.append(
            f"only {n_seg} segments: the single pair cannot be cross-checked (need >= 3)"
        )

    # -- xy ---------------------------------------------------------------------------------
    d_xy, contrast_xy, valid_xy, grid = _pair_shifts_xy(
        data.xyz[:, :2], seg, n_seg, pairs, bin_nm, blur, max_shift_nm
    )
    sol_xy = _solve(n_seg, pairs, d_xy, valid_xy, floor=bin_nm)
    ok_xy = _check(sol_xy, valid_xy, n_seg, max_shift_nm, bin_nm, "xy", warnings)
    reliable &= ok_xy
    shifts = np.zeros((n_seg, 3))
    shifts[:, :2] = sol_xy.shifts

    # -- z ----------------------------------------------------------------------------------
    d_z = np.full((n_pairs, 1), np.nan)
    contrast_z = np.full(n_pairs, np.nan)
    used_z = np.zeros(n_pairs, dtype=bool)
    resid_z = np.full((n_pairs, 1), np.nan)
    z_details: dict[str, Any] = {"z_estimated": False}
    if estimate_z and data.has_z:
        corr_xy = data.xyz[:, :2] - _interpolate(centres, shifts[:, :2], data.frame)
        blur_z = max(float(data.sigma_z or z_bin_nm), 0.5 * z_bin_nm)
        xy_bin_z = max(2.0 * bin_nm, 4.0 * blur)
        d_z, contrast_z, valid_z = _pair_shifts_z(
            corr_xy, data.xyz[:, 2], seg, n_seg, pairs, xy_bin_z, z_bin_nm, blur_z, max_shift_nm
        )
        sol_z = _solve(n_seg, pairs, d_z, valid_z, floor=z_bin_nm)
        ok_z = _check(sol_z, valid_z, n_seg, max_shift_nm, z_bin_nm, "z", warnings)
        if not ok_z:
            warnings.append("z: pass estimate_z=False (drift --no-z) for an xy-only estimate")
        reliable &= ok_z
        shifts[:, 2] = sol_z.shifts[:, 0]
        used_z, resid_z = sol_z.used, sol_z.residuals
        z_details = {
            "z_estimated": True,
            "reliable_z": bool(ok_z),
            "blur_z_nm": blur_z,
            "xy_bin_for_z_nm": xy_bin_z,
            "residual_scale_z_nm": sol_z.scale,
            "pairs_used_z": int(sol_z.used.sum()),
        }
    elif estimate_z:
        log.info("rcc_drift: the table has no (non-constant) z_nm; z drift not estimated")

    frames = np.arange(f0, f1 + 1)
    curve = _interpolate(centres, shifts, frames)
    ref = curve[0].copy()  # drift is defined up to a constant: zero at the first frame
    drift = curve - ref
    for w in warnings:
        log.warning("rcc_drift: %s", w)
    return DriftResult(
        frames=frames,
        drift=drift,
        method="rcc",
        reliable=bool(reliable),
        warnings=warnings,
        segment_frames=centres,
        segment_shifts=shifts - ref,
        pairs=pairs,
        pair_shifts=np.concatenate([d_xy, d_z], axis=1),
        pair_residuals=np.concatenate([sol_xy.residuals, resid_z], axis=1),
        pair_used=np.stack([sol_xy.used, used_z], axis=1),
        pair_contrast=np.stack([contrast_xy, contrast_z], axis=1),
        details={
            "segments_requested": segments,
            "segments": n_seg,
            "locs_per_segment": counts.tolist(),
            "locs_used": int(data.frame.size),
            "locs_input": data.n_input,
            "bin_nm": bin_nm,
            "blur_nm": blur,
            "z_bin_nm": z_bin_nm,
            "max_shift_nm": max_shift_nm,
            "image_shape": grid,
            "reliable_xy": bool(ok_xy),
            "residual_scale_xy_nm": sol_xy.scale,
            "pairs": n_pairs,
            "pairs_used_xy": int(sol_xy.used.sum()),
            **z_details,
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
            f"{f0}..{f0 + n_frames - 1}; RCC needs at least 2 time segments of "
            f"min_locs_per_segment={min_locs} (the emptiest of {segments} segments held "
            f"{int(first_counts.min())})"
        )
    if n_seg < segments:
        warnings.append(
            f"reduced segments from {segments} to {n_seg}: with {segments} the emptiest segment "
            f"held {int(first_counts.min())} localizations (< min_locs_per_segment={min_locs})"
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
            f"the field ({nx * bin_nm:.0f} x {ny * bin_nm:.0f} nm) at bin_nm={bin_nm:g} needs "
            f"{shape[1]} x {shape[0]} bin images, above {MAX_IMAGE_PIXELS} pixels: raise bin_nm"
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
            f"+-max_shift_nm={max_shift_nm:g} nm: pairs further apart cannot be measured; "
            "raise max_shift_nm"
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
# fiducials
# --------------------------------------------------------------------------------------------


def fiducial_drift(
    locs: pd.DataFrame,
    *,
    radius_nm: float = 150.0,
    min_fraction: float = 0.8,
    smooth_frames: int = 25,
) -> DriftResult:
    """Drift from fiducials: spots present in at least ``min_fraction`` of the frames.

    Fiducials are found as tracks, so that they are followed even when the drift carries them
    further than ``radius_nm``. The movie is cut into windows of ``smooth_frames`` frames (at
    least 5), in which the drift is much smaller than ``radius_nm``. In each window, spots are
    groups of localizations within ``radius_nm / 2`` (tight, so that a stretch of labelled
    structure rarely qualifies) present in at least ``0.75 x min_fraction`` of the window's
    frames (lenient: the strict test follows). Spots of windows up to 5 apart and within
    ``radius_nm / 2`` of each other are linked into tracks (nearest pairs first, one spot per
    track and window). Every frame then takes, per track, the localization nearest to the
    track's interpolated position, within ``radius_nm``. A track is a fiducial when it has such
    a localization in at least ``min_fraction`` of all frames and is point-like: its robust
    scatter about its own running median is below ``radius_nm / 5`` per axis (a patch of
    blinking molecules scatters over the whole radius); localizations more than 4 scatters
    from that running median (a neighbouring molecule in a frame that misses the fiducial) are
    dropped. Any spot that passes is fixed to the sample, so at very high duty cycles a small
    group of quasi-permanently emitting molecules can serve as a (noisier) fiducial too.

    The drift of a frame is the mean over the fiducials present of (position - that fiducial's
    median position); frames without any fiducial are interpolated linearly; the curve is then
    smoothed by a running median (robust to a wrong match) followed by a running mean (which
    removes the median's steps), both over ``smooth_frames`` frames, and referenced to zero at
    the first frame.

    Parameters
    ----------
    locs : DataFrame
        Table with at least ``frame, x_nm, y_nm`` (``z_nm`` optional; nm). Rows with a flag
        other than "ok" are ignored.
    radius_nm : float
        Grouping radius (nm): larger than the localization scatter of a fiducial, smaller than
        the distance between fiducials.
    min_fraction : float
        Fraction of the frames (0..1] a fiducial must be found in.
    smooth_frames : int
        Length of the running filters and of the detection windows (frames).

    Returns
    -------
    DriftResult
        ``method="fiducial"``, with ``fiducials`` (median positions) and ``raw_drift``.
        ``reliable`` is False when the fiducials disagree with each other by more than
        ``radius_nm / 5`` RMS after smoothing, or fewer than ``min_fraction`` of the frames
        contain any fiducial; a single fiducial only adds a warning.

    Raises
    ------
    ValueError
        For bad parameters or input, or when no fiducial is found (the message lists how many
        frames the best candidates were present in).
    """
    radius_nm = _positive("radius_nm", radius_nm)
    if not (math.isfinite(min_fraction) and 0 < min_fraction <= 1):
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction!r}")
    if int(smooth_frames) != smooth_frames or smooth_frames < 1:
        raise ValueError(f"smooth_frames must be a positive integer, got {smooth_frames!r}")
    smooth_frames = int(smooth_frames)
    data = _read_locs(locs)
    f0, f1 = int(data.frame.min()), int(data.frame.max())
    n_frames = f1 - f0 + 1
    fi = data.frame - f0
    order = np.argsort(fi, kind="stable")
    fi, xyz = fi[order], data.xyz[order]
    xy = xyz[:, :2]

    # -- spots per window -------------------------------------------------------------------
    win_len = min(max(smooth_frames, 5), n_frames)
    n_win = -(-n_frames // win_len)
    bounds = np.searchsorted(fi, np.arange(n_win + 1) * win_len)
    spot_xy, spot_win, spot_n = [], [], []
    for w in range(n_win):
        a, b = bounds[w], bounds[w + 1]
        if b - a == 0:
            continue
        frames_in_win = min(win_len, n_frames - w * win_len)
        need = max(2, math.ceil(0.75 * min_fraction * frames_in_win))
        for centre, n_present in _window_spots(xy[a:b], fi[a:b], 0.5 * radius_nm, need):
            spot_xy.append(centre)
            spot_win.append(w)
            spot_n.append(n_present)
    if not spot_xy:
        raise ValueError(
            f"no fiducial found: no group of localizations within radius_nm={radius_nm:g} is "
            f"present in {0.75 * min_fraction:.0%} of the frames of any {win_len}-frame window "
            f"({data.frame.size} localizations in {n_frames} frames)"
        )
    spot_xy_a, spot_win_a, spot_n_a = np.asarray(spot_xy), np.asarray(spot_win), np.asarray(spot_n)
    tracks = _link_spots(spot_xy_a, spot_win_a, 0.5 * radius_nm, gap=5)

    # -- match every frame to each track ----------------------------------------------------
    all_frames = np.arange(n_frames, dtype=np.float64)
    win_centre = (np.arange(n_win) + 0.5) * win_len - 0.5
    min_windows = 0.5 * min_fraction * n_win
    need_frames = math.ceil(min_fraction * n_frames)
    max_scatter = radius_nm / 5
    candidates: list[tuple[int, float]] = []  # (frames present, scatter nm) of each track tried
    fid_pos: list[NDArray] = []
    for track in tracks:
        wins = spot_win_a[track]
        if wins.size < min_windows:
            # seen in too few windows to be present in min_fraction of the frames; its spots'
            # frame counts stand in for its presence in the error message
            candidates.append((int(spot_n_a[track].sum()), math.nan))
            continue
        px = np.interp(all_frames, win_centre[wins], spot_xy_a[track, 0])
        py = np.interp(all_frames, win_centre[wins], spot_xy_a[track, 1])
        dist = np.hypot(xy[:, 0] - px[fi], xy[:, 1] - py[fi])
        near = np.nonzero(dist <= radius_nm)[0]
        near = near[np.lexsort((dist[near], fi[near]))]
        first = near[np.unique(fi[near], return_index=True)[1]]  # nearest one per frame
        pos = np.full((n_frames, 3), np.nan)
        pos[fi[first]] = xyz[first]
        scatter, outlier = _track_scatter(pos[:, :2], smooth_frames)
        pos[outlier] = np.nan  # e.g. a nearby molecule in a frame that misses the fiducial
        present = int(np.isfinite(pos[:, 0]).sum())
        candidates.append((present, scatter))
        if present >= need_frames and scatter < max_scatter:
            fid_pos.append(pos)
    if not fid_pos:
        best = sorted(candidates, reverse=True)[:5]
        listed = (
            ", ".join(
                f"{n} frames" + (f" (scatter {sc:.0f} nm)" if math.isfinite(sc) else "")
                for n, sc in best
            )
            or "none"
        )
        raise ValueError(
            f"no fiducial found: a fiducial must be present in >= {need_frames} of the "
            f"{n_frames} frames (min_fraction={min_fraction:g}) with a scatter below "
            f"{max_scatter:.0f} nm (radius_nm / 5); the best candidates: {listed}"
        )

    # -- drift ------------------------------------------------------------------------------
    pos_all = np.stack(fid_pos)  # (K, F, 3); z is 0 for 2D tables
    medians = np.nanmedian(pos_all, axis=1)  # (K, 3)
    dev = pos_all - medians[:, None, :]
    count = np.sum(np.isfinite(dev[..., 0]), axis=0)
    have = count > 0
    raw = np.full((n_frames, 3), np.nan)
    raw[have] = np.nansum(dev[:, have], axis=0) / count[have, None]
    smooth = _smooth(_fill_gaps(raw), smooth_frames)
    ref = smooth[0].copy()  # drift is defined up to a constant: zero at the first frame
    drift = smooth - ref

    warnings: list[str] = []
    reliable = True
    n_fid = len(fid_pos)
    spread = math.nan
    if n_fid == 1:
        warnings.append("a single fiducial: its drift cannot be cross-checked against another")
    else:
        # each fiducial's own smoothed lateral track against the combined one
        own = np.stack([_smooth(_fill_gaps(d[:, :2]), smooth_frames) for d in dev])
        spread = float(np.sqrt(np.mean((own - smooth[None, :, :2]) ** 2)))
        if spread > radius_nm / 5:
            warnings.append(
                f"the {n_fid} fiducials disagree by {spread:.0f} nm RMS (> radius_nm / 5 = "
                f"{radius_nm / 5:.0f} nm): some may not be fixed to the sample"
            )
            reliable = False
    covered = int(have.sum())
    if covered < need_frames:
        warnings.append(
            f"only {covered} of {n_frames} frames contain a fiducial; the rest are interpolated"
        )
        reliable = False
    for w in warnings:
        log.warning("fiducial_drift: %s", w)
    return DriftResult(
        frames=np.arange(f0, f1 + 1),
        drift=drift,
        method="fiducial",
        reliable=reliable,
        warnings=warnings,
        fiducials=medians,
        raw_drift=raw - ref,
        details={
            "fiducials": n_fid,
            "frames_present": [int(np.isfinite(p[:, 0]).sum()) for p in fid_pos],
            "frames_covered": covered,
            "tracks": len(candidates),
            "disagreement_nm": spread,
            "radius_nm": radius_nm,
            "min_fraction": min_fraction,
            "smooth_frames": smooth_frames,
            "z_estimated": data.has_z,
        },
    )


def _window_spots(
    xy: NDArray, frame: NDArray, radius: float, need: int
) -> list[tuple[NDArray, int]]:
    """Groups of localizations within ``radius`` present in >= ``need`` frames: (median
    position, frames present) of each, seeded greedily from the most crowded localization."""
    tree = cKDTree(xy)
    counts = tree.query_ball_point(xy, radius, return_length=True)
    used = np.zeros(len(xy), dtype=bool)
    spots = []
    for i in np.argsort(-counts, kind="stable"):
        if counts[i] < need:
            break  # sorted: no later seed has enough neighbours
        if used[i]:
            continue
        nb = np.asarray(tree.query_ball_point(xy[i], radius), dtype=np.int64)
        nb = nb[~used[nb]]
        n_present = np.unique(frame[nb]).size
        if n_present >= need:
            spots.append((np.median(xy[nb], axis=0), n_present))
            used[nb] = True
    return spots


def _link_spots(centre: NDArray, win: NDArray, max_step: float, gap: int) -> list[NDArray]:
    """Tracks through the windows: each spot joins the nearest track (within ``max_step``, last
    seen at most ``gap`` windows earlier; nearest pairs first) or starts a new one. Returns the
    spot indices of every track, one spot per window, in window order."""
    tracks: list[list[int]] = []
    for w in np.unique(win):
        cur = np.nonzero(win == w)[0]
        active = [t for t, members in enumerate(tracks) if w - win[members[-1]] <= gap]
        taken_t: set[int] = set()
        taken_s: set[int] = set()
        if active:
            last = centre[[tracks[t][-1] for t in active]]
            dist = np.hypot(*(last[:, None, :] - centre[cur][None, :, :]).transpose(2, 0, 1))
            for flat in np.argsort(dist, axis=None):
                a, b = np.unravel_index(flat, dist.shape)
                if dist[a, b] > max_step:
                    break  # sorted: every later pair is further apart
                if a in taken_t or b in taken_s:
                    continue
                taken_t.add(a)
                taken_s.add(b)
                tracks[active[a]].append(int(cur[b]))
        tracks.extend([int(cur[b])] for b in range(cur.size) if b not in taken_s)
    return [np.asarray(members, dtype=np.int64) for members in tracks]


def _track_scatter(pos: NDArray, smooth_frames: int) -> tuple[float, NDArray[np.bool_]]:
    """Robust scatter (nm, worst axis) of a track's positions (F, 2) about their running
    median, and which frames lie more than 4 scatters (at least 10 nm) from it."""
    ok = np.isfinite(pos[:, 0])
    outlier = np.zeros(pos.shape[0], dtype=bool)
    if ok.sum() < 3:
        return math.inf, outlier
    p = pos[ok]
    size = min(max(smooth_frames, 3), p.shape[0])
    resid = p - median_filter(p, size=(size, 1), mode="mirror")
    resid -= np.median(resid, axis=0)
    per_axis = 1.4826 * np.median(np.abs(resid), axis=0)
    outlier[ok] = np.any(np.abs(resid) > np.maximum(4 * per_axis, 10.0), axis=1)
    return float(np.max(per_axis)), outlier


def _fill_gaps(values: NDArray) -> NDArray:
    """Rows (frames) of ``values`` (F, D) that are NaN, linearly interpolated from the others
    (held constant beyond the first / last finite row)."""
    ok = np.isfinite(values[:, 0])
    t = np.arange(values.shape[0], dtype=np.float64)
    return np.stack([np.interp(t, t[ok], values[ok, k]) for k in range(values.shape[1])], axis=1)


def _smooth(values: NDArray, size: int) -> NDArray:
    """Running median then running mean over ``size`` frames along axis 0."""
    size = min(size, values.shape[0])
    if size <= 1:
        return values.copy()
    out = median_filter(values, size=(size, 1), mode="mirror")
    return uniform_filter1d(out, size, axis=0, mode="mirror")


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
    for k, name in enumerate("xyz"):
        c = colours[k]
        if drift.raw_drift is not None:
            ax.plot(drift.frames, drift.raw_drift[:, k], ",", color=c, alpha=0.3)
        label = f"d{name}"
        if k == 2 and not drift.details.get("z_estimated", True):
            label += " (not estimated)"
        ax.plot(drift.frames, drift.drift[:, k], color=c, lw=1.5, label=label)
        if drift.segment_frames is not None and drift.segment_shifts is not None:
            ax.plot(drift.segment_frames, drift.segment_shifts[:, k], "o", color=c, ms=4)
        if truth is not None and k < truth.shape[1]:
            ax.plot(drift.frames, truth[:, k], "--", color=c, lw=1, label=f"d{name} truth")
    ax.set_xlabel("frame")
    ax.set_ylabel("drift (nm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    status = "reliable" if drift.reliable else "UNRELIABLE"
    ax.set_title(f"{drift.method} drift ({status})", fontsize=9)
    return save_figure(fig, path, dpi)
