"""What the drift methods share: the result they return, the reading of a localization table
and the checks of their parameters.

Lengths are in nm, frames are 0-based integers. :mod:`sparseloc.drift` re-exports
:class:`DriftResult`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

__all__ = ["DriftLocs", "DriftResult", "positive", "read_locs"]


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

    def range_text(self, digits: int = 1) -> str:
        """The estimate's range over the movie per axis, e.g. "x 41.7 nm, y 31.3 nm, z 14.9
        nm"; a z the estimate left alone is named so, not read as a measured zero ("z not
        corrected (unreliable)" where it was estimated and dropped, else "z not
        estimated")."""
        span = np.ptp(self.drift, axis=0)
        text = f"x {span[0]:.{digits}f} nm, y {span[1]:.{digits}f} nm"
        if self.details.get("z_estimated", True):
            return f"{text}, z {span[2]:.{digits}f} nm"
        dropped = self.details.get("z_dropped")
        return f"{text}, z {'not corrected (unreliable)' if dropped else 'not estimated'}"


@dataclass
class DriftLocs:
    """The usable rows of a localization table, as arrays (see :func:`read_locs`)."""

    frame: NDArray[np.int64]
    xyz: NDArray[np.float64]  # (N, 3); z column 0 where has_z is False
    has_z: bool
    sigma_lat: float | None  # median lateral precision (nm) from the table, if any
    sigma_z: float | None
    n_input: int


def read_locs(locs: pd.DataFrame, *, all_flags: bool = False) -> DriftLocs:
    """Usable rows as arrays: those of :func:`sparseloc.postprocess.select_usable` (flag "ok"
    unless ``all_flags``, coordinates finite and within bounds) with a finite frame and z."""
    from .postprocess import select_usable

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
    locs = select_usable(locs, all_flags=all_flags).locs
    keep = np.ones(len(locs), dtype=bool)
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
    return DriftLocs(frame[keep].astype(np.int64), xyz, has_z, sigma_lat, sigma_z, n_input)


def positive(name: str, value: float) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is finite and > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v
