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
Each group's model rests on fewer beads than the final one, so the choice leans a little
towards wider windows (most with two beads, each then predicted from the other alone); and
where the model is refined on a grid finer than the pixels, the window chosen on the pixels'
average is applied to that grid.
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
    "kept_mean",
    "model_stack",
    "smooth_along_z",
    "smoothing_nm",
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

    Parameters
    ----------
    avg : ndarray, shape (Nz, R, R)
        A bead average (photons less the frame's background).

    Returns
    -------
    ndarray, shape (Nz, R, R)
        Each plane non-negative and summing to one.

    Raises
    ------
    ValueError
        Where a plane holds no light above its border.
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


def kept_mean(
    stacks: NDArray[np.float64], keep: NDArray[np.bool_], share: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The beads' mean over the voxels each keeps: each voxel the sum of the kept beads' light
    over their share of the beads' total light, so brighter beads weigh more, as in the plain
    mean (which it equals where every voxel is kept).

    Parameters
    ----------
    stacks : ndarray, shape (B, Nz, R, R)
        Registered beads (photons less the frame's background).
    keep : ndarray of bool, shape (B, Nz, R, R)
        The voxels to average.
    share : ndarray, shape (B, 1, 1, 1)
        Each bead's light over the beads' mean.

    Returns
    -------
    ndarray, shape (Nz, R, R)
    """
    light = np.zeros(stacks.shape[1:])
    weight = np.zeros(stacks.shape[1:])
    for bead, kept, w in zip(stacks, keep, share, strict=True):
        light += np.where(kept, bead, 0.0)
        weight += w * kept
    return light / np.maximum(weight, 1e-12)


def smooth_along_z(stack: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """``stack`` (Nz, ...) smoothed along its first axis by a cubic Savitzky-Golay filter of
    ``window`` planes (odd, at least 5); unchanged for ``window`` 0."""
    if window == 0:
        return stack
    return savgol_filter(stack, window, 3, axis=0, mode="interp")


def model_stack(avg: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """The model stack of a bead average ``avg`` (Nz, R, R; photons less background): cleaned
    (:func:`clean_average`) and smoothed along z over ``window`` planes (0: not smoothed)."""
    return _smoothed(clean_average(avg), window)


def _smoothed(clean: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """A cleaned average smoothed along z over ``window`` planes and cleaned again."""
    return clean_average(smooth_along_z(clean, window)) if window else clean


def fallback_window(step: float, n_planes: int) -> int:
    """The window (planes) where the beads cannot choose (one bead): about 80 nm of ``step``
    nm planes; none for steps of 30 nm or more or where ``n_planes`` is too few."""
    if step >= 30.0:
        return 0
    win = round(80.0 / step) | 1
    return win if 5 <= win <= n_planes else 0


def smoothing_nm(window: int, step: float) -> float:
    """The z span (nm) of a smoothing window of ``window`` planes ``step`` nm apart: from its
    first plane to its last."""
    return max(window - 1, 0) * step


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

    Raises
    ------
    ValueError
        For fewer than two beads, or where a group's model has a plane without light.
    """
    n_beads, n_planes = aligned.shape[:2]
    if n_beads < 2:
        raise ValueError("choosing the smoothing needs two beads or more")
    candidates = (0, *(w for w in WINDOWS if w <= n_planes))
    misfit = np.zeros(len(candidates))
    groups = np.arange(n_beads) % min(FOLDS, n_beads)
    for g in range(groups.max() + 1):
        train = np.flatnonzero(groups != g)
        base = clean_average(kept_mean(aligned[train], keep[train], share[train]))
        models = [_smoothed(base, window) for window in candidates]
        for b in np.flatnonzero(groups == g):
            for k, model in enumerate(models):
                # each window's fit weighs its own residuals: weights from the unsmoothed
                # model's fit would carry that model's noise into every window's score
                fit = _plane_fit(aligned[b], keep[b], model)
                chi2 = (aligned[b] - fit) ** 2 / variance(fit)
                misfit[k] += float(np.sum(np.where(keep[b], chi2, 0.0)))
    best = int(np.argmin(misfit))
    return ZWindow(candidates[best], candidates, misfit - misfit[best])


def _plane_fit(
    bead: NDArray[np.float64], keep: NDArray[np.bool_], model: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``model`` (Nz, R, R) fitted to ``bead`` plane by plane, a least-squares scale and
    offset over the voxels of ``keep``."""
    shape = bead.shape
    w = keep.reshape(shape[0], -1).astype(np.float64)
    m = model.reshape(shape[0], -1)
    x = bead.reshape(shape[0], -1)
    n = np.maximum(w.sum(axis=1, keepdims=True), 1.0)
    mm = (w * m).sum(axis=1, keepdims=True) / n
    xm = (w * x).sum(axis=1, keepdims=True) / n
    mc = m - mm
    scale = (w * mc * (x - xm)).sum(axis=1, keepdims=True) / np.maximum(
        (w * mc**2).sum(axis=1, keepdims=True), 1e-300
    )
    return (scale * mc + xm).reshape(shape)
