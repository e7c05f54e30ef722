"""The bead average made a model stack: cleaned, and smoothed along z as far as the beads say.

Fine z steps give each plane of the beads' average its own photon noise, and that noise, in
the model's z derivative, costs axial precision; smoothing along z (a cubic Savitzky-Golay
filter, as SMAP's smoothing spline) removes it but flattens what changes within the window.
The best window depends on the beads' brightness and number and on the PSF, so the beads
choose it (:func:`choose_window`): they are split into groups, each group's beads are compared
with the model made from the other beads at every candidate window, and the window with the
smallest noise-weighted misfit wins. A held-out bead's noise is independent of the model it is
compared with, so its misfit is its own noise, the same at every window, plus the model's
departure from the true PSF, which is what the window trades: noise against flattening.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import savgol_filter

__all__ = [
    "FOLDS",
    "WINDOWS",
    "ZWindow",
    "choose_window",
    "clean_average",
    "fallback_window",
    "smooth_along_z",
]

#: Candidate smoothing windows (planes, odd); 0 (none) is always a candidate.
WINDOWS = (5, 7, 9, 11, 13, 17, 21, 25, 31, 41, 51, 61, 81, 101)
#: The beads are held out in at most this many groups (each bead alone where there are fewer).
FOLDS = 5


def clean_average(avg: NDArray[np.float64]) -> NDArray[np.float64]:
    """Subtract each plane's residual background (median of the ROI border), clip what falls
    below zero and normalise.

    The clip: after the background's subtraction half the dark pixels hold noise below zero,
    and a model of light cannot be negative (simulations refuse it, fits on it give NaN).
    """
    border = np.concatenate(
        [avg[:, 0, :], avg[:, -1, :], avg[:, 1:-1, 0], avg[:, 1:-1, -1]], axis=1
    )
    out = np.maximum(avg - np.median(border, axis=1)[:, None, None], 0.0)
    sums = out.sum(axis=(1, 2), keepdims=True)
    if np.any(sums <= 0):
        raise ValueError(
            "a plane of the averaged bead stack holds no signal; the beads are too dim or the "
            "z range runs far beyond where they can be seen"
        )
    return out / sums


def smooth_along_z(stack: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """``stack`` (Nz, ...) smoothed along its first axis by a cubic Savitzky-Golay filter of
    ``window`` planes (odd, at least 5); unchanged for ``window`` 0."""
    if window == 0:
        return stack
    return savgol_filter(stack, window, 3, axis=0, mode="interp")


def fallback_window(step: float, n_planes: int) -> int:
    """The window where the beads cannot choose (one bead): about 80 nm of ``step`` nm
    planes, none for steps of 30 nm or more or for fewer than 5 planes."""
    if step >= 30.0:
        return 0
    win = round(80.0 / step) | 1
    return win if 5 <= win <= n_planes else 0


@dataclass(frozen=True)
class ZWindow:
    """The window the beads chose.

    Attributes
    ----------
    window : int
        Planes (0: no smoothing).
    candidates : tuple of int
        The windows tried.
    misfit : ndarray, shape (len(candidates),)
        The held-out beads' noise-weighted misfit at each window, less the smallest.
    """

    window: int
    candidates: tuple[int, ...]
    misfit: NDArray[np.float64]


def choose_window(
    aligned: NDArray[np.float64],
    keep: NDArray[np.bool_],
    share: NDArray[np.float64],
    variance: Callable[[NDArray[np.float64]], NDArray[np.float64]],
) -> ZWindow:
    """Choose the smoothing window along z by cross-validation over the beads.

    Parameters
    ----------
    aligned : ndarray, shape (B, Nz, R, R)
        The registered beads (photons less the frame's background) on the model's planes;
        B >= 2.
    keep : ndarray of bool, shape (B, Nz, R, R)
        The voxels the average keeps (a neighbour's light is neither averaged nor compared).
    share : ndarray, shape (B, 1, 1, 1)
        Each bead's light over the beads' mean, the average's weights.
    variance : callable
        The camera's variance (photons^2) of voxels of expected light ``fit`` (Nz, R, R;
        photons less background).

    Returns
    -------
    ZWindow
    """
    n_beads, n_planes = aligned.shape[:2]
    if n_beads < 2:
        raise ValueError("choosing the smoothing needs two beads or more")
    candidates = (0, *(w for w in WINDOWS if w <= n_planes))
    misfit = np.zeros(len(candidates))
    groups = np.arange(n_beads) % min(FOLDS, n_beads)
    for g in range(groups.max() + 1):
        train = groups != g
        light = (aligned[train] * keep[train]).sum(axis=0)
        weight = (share[train] * keep[train]).sum(axis=0)
        base = clean_average(light / np.maximum(weight, 1e-12))
        for k, window in enumerate(candidates):
            model = clean_average(smooth_along_z(base, window)) if window else base
            for b in np.flatnonzero(~train):
                misfit[k] += _misfit(aligned[b], keep[b], model, variance)
    best = int(np.argmin(misfit))
    return ZWindow(candidates[best], candidates, misfit - misfit[best])


def _misfit(
    bead: NDArray[np.float64],
    keep: NDArray[np.bool_],
    model: NDArray[np.float64],
    variance: Callable[[NDArray[np.float64]], NDArray[np.float64]],
) -> float:
    """Chi-square of one bead (Nz, R, R) against ``model`` with a least-squares scale and
    offset per plane, over the voxels of ``keep``."""
    m = model.reshape(model.shape[0], -1)
    x = bead.reshape(bead.shape[0], -1)
    mc = m - m.mean(axis=1, keepdims=True)
    xm = x.mean(axis=1, keepdims=True)
    scale = (mc * (x - xm)).sum(axis=1, keepdims=True) / np.maximum(
        (mc**2).sum(axis=1, keepdims=True), 1e-300
    )
    fit = scale * mc + xm
    var = variance(fit.reshape(bead.shape)).reshape(fit.shape)
    return float((((x - fit) ** 2 / var) * keep.reshape(fit.shape)).sum())
