"""The calibration's own model error: how far the beads depart from the model beyond noise.

Each used bead is fitted with the finished model (one shift for the whole stack, a scale and
an offset per plane). Per plane, the residual power left over the Poisson variance expected
from the fitted light and the frame's background, divided by the power of the fitted signal,
is the squared relative model error ``e(z)^2``: the model error a localization meets is a
per-pixel standard deviation of about ``e * signal``.

The model is made from the beads, so it follows part of each bead's own noise: a fraction
``h`` (its self-influence) at that bead: ``1 / n`` for a plain average of ``n`` beads, less
where the model is smoothed along z, more where it is refined on a grid finer than the pixels
(each fine sample rests on a few beads). A bead's expected residual power is then
``var (1 - h)`` plus the power of the model's systematic departure from the true PSF, which
is what this module measures: ``h`` is measured on the finished model (:func:`self_influence`)
rather than assumed. (The noise the model holds, ``h var`` per pixel, is left out: it is
fine-grained, and the count selection's allowance is for structure that reads as an emitter.)

The error is also kept pixel by pixel (:attr:`ModelError.table`): a model's error is not
proportional to its signal everywhere (a calibrated double helix errs most in its dim wings),
and the solvers' allowance for it (:mod:`sparseloc.solvers.variance`) sums it where it is.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter

from .psf.spline import SplinePSF

__all__ = [
    "EXTRAPOLATE_STEPS",
    "MAX_MODEL_ERROR",
    "ModelError",
    "bead_errors",
    "bead_model_error",
    "plane_fits",
    "self_influence",
    "served_images",
    "served_planes",
]

#: A calibration whose model error exceeds this fraction of the signal is refused: its model
#: would leave more than a quarter of a bead's signal power unexplained.
MAX_MODEL_ERROR = 0.5


@dataclass
class ModelError:
    """The model error of a calibration.

    Attributes
    ----------
    overall : float
        ``sqrt(sum_z excess(z) / sum_z signal(z))``: the relative error over all planes.
    per_plane : ndarray, shape (Nz,)
        ``e(z)`` of each of the model's planes (NaN where no bead covers the plane).
    table : SplinePSF or None
        The error pixel by pixel: the beads' residual variance about the model beyond the
        Poisson noise, per photon squared, tabulated like the PSF (an emitter of ``N`` photons
        at ``x, y, z`` has error variance ``table.render(x, y, z, N**2)`` photons^2 per
        pixel); None where fewer than 4 planes are covered.
    influence : float
        The model's self-influence the error was measured with (``influence`` of
        :func:`bead_model_error`).
    """

    overall: float
    per_plane: NDArray[np.float64]
    table: SplinePSF | None = None
    influence: float = 0.0


def bead_model_error(
    psf: SplinePSF,
    rois: list[NDArray[np.float64]],
    shifts: list[NDArray[np.float64]],
    zplanes: NDArray[np.float64],
    background: NDArray[np.float64],
    masks: list[NDArray[np.bool_]] | None = None,
    noise: tuple[float, float] = (1.0, 0.0),
    influence: float = 0.0,
) -> ModelError:
    """Measure the model error of ``psf`` on the beads it was made from.

    Parameters
    ----------
    psf : SplinePSF
        The finished model.
    rois : list of ndarray, each shape (Nz, R, R)
        Each used bead's ROI stack in photons less the frame's background, on ``zplanes``.
    shifts : list of ndarray, each shape (3,)
        Each bead's x, y, z (nm) relative to its ROI's centre and the planes' z.
    zplanes : ndarray, shape (Nz,)
        The z (nm) of the ROI stacks' planes; only those the model serves are used
        (:func:`served_planes`).
    background : ndarray, shape (Nz,)
        Each plane's frame background (photons/pixel), part of the noise variance.
    masks : list of ndarray of bool, each shape (Nz, R, R), optional
        The voxels of each ROI to measure on (default all): light that a bead's ROI holds
        and the other beads' do not is not the model's error.
    noise : (float, float)
        The camera's variance in photons^2 as ``a * mu + b`` for ``mu`` expected photons
        (default photon counting): an EMCCD's excess noise or read noise is not the model's
        error either.
    influence : float
        The model's self-influence ``h`` (:func:`self_influence`): each bead's residual
        power less ``var (1 - h)`` is the model's error at that bead. 0 where the model is
        not cross-checked (one bead: its residual then says nothing of its error).

    Returns
    -------
    ModelError
    """
    nz = zplanes.size
    excess = np.zeros(nz)
    signal = np.zeros(nz)
    maps, count = np.zeros((nz, *rois[0].shape[1:])), np.zeros((nz, *rois[0].shape[1:]))
    if masks is None:
        masks = [np.ones(roi.shape, dtype=bool) for roi in rois]
    kept = 1.0 - influence  # the share of a bead's noise variance its residual holds
    for roi, shift, mask in zip(rois, shifts, masks, strict=True):
        res2, var, sig2, ok, bead_map = _bead_residual(
            psf, roi, shift, zplanes, background, mask, noise, kept
        )
        excess[ok] += res2[ok] - kept * var[ok]
        signal[ok] += sig2[ok]
        maps[ok] += bead_map[ok]
        count[ok] += mask[ok]
    table = _error_table(psf, maps, count, zplanes, shifts)
    covered = signal > 0
    per_plane = np.full(nz, np.nan)
    per_plane[covered] = np.sqrt(np.maximum(excess[covered], 0.0) / signal[covered])
    total = float(signal[covered].sum())
    overall = float(np.sqrt(max(excess[covered].sum(), 0.0) / total)) if total > 0 else np.nan
    lo, hi = psf.z_range
    inside = (zplanes >= lo - 1e-6) & (zplanes <= hi + 1e-6)
    return ModelError(overall, per_plane[inside], table, influence)


def bead_errors(
    psf: SplinePSF,
    rois: list[NDArray[np.float64]],
    shifts: list[NDArray[np.float64]],
    zplanes: NDArray[np.float64],
    background: NDArray[np.float64],
    masks: list[NDArray[np.bool_]],
    noise: tuple[float, float] = (1.0, 0.0),
) -> NDArray[np.float64]:
    """Each bead's own model error: :func:`bead_model_error`'s overall figure measured on
    that bead alone, so a bead unlike the others (two beads seen as one, dirt) stands out.
    ``psf`` here is the beads' plain average (the outlier test's), which follows ``1 / n``
    of each of its ``n`` beads' noise: the residual power is scaled by ``n / (n - 1)``.

    Parameters are those of :func:`bead_model_error` (``masks`` required).

    Returns
    -------
    ndarray, shape (n,)
        Relative errors (NaN for a bead with no plane in the model's range).
    """
    n = len(rois)
    scale = n / (n - 1) if n > 1 else 1.0
    out = np.full(n, np.nan)
    for k, (roi, shift, mask) in enumerate(zip(rois, shifts, masks, strict=True)):
        res2, var, sig2, ok, _ = _bead_residual(psf, roi, shift, zplanes, background, mask, noise)
        if sig2[ok].sum() > 0:
            out[k] = np.sqrt(max((res2[ok] * scale - var[ok]).sum(), 0.0) / sig2[ok].sum())
    return out


#: The perturbation that measures the model's self-influence, in standard deviations of the
#: camera's noise: small, so that the model's non-linear steps (the robust average, the clip
#: at zero) meet it as they meet a little more noise.
PERTURBATION = 0.3


def self_influence(
    psf: SplinePSF,
    rebuild: Callable[[list[NDArray[np.float64]]], SplinePSF],
    rois: list[NDArray[np.float64]],
    shifts: list[NDArray[np.float64]],
    zplanes: NDArray[np.float64],
    background: NDArray[np.float64],
    masks: list[NDArray[np.bool_]],
    noise: tuple[float, float] = (1.0, 0.0),
    seed: int = 0,
) -> float:
    """The share ``h`` of a bead's own noise that the model follows at that bead, measured:
    each bead's ROI gets independent Gaussian noise of :data:`PERTURBATION` times the
    camera's standard deviation, the model is made again from the perturbed ROIs, and ``h``
    is how much of the perturbation each bead's plane fits (:func:`plane_fits`) follow, over
    the voxels of ``masks``, weighted as the residual power is (by the noise variance).

    Parameters are those of :func:`bead_model_error`; ``rebuild(rois)`` makes the model from
    the ROIs ``rois`` (the same beads, shifts and steps as ``psf``).

    Returns
    -------
    float
        ``h`` in [0, 1]: about ``1 / n`` for a plain average of ``n`` beads, less where the
        model averages over neighbouring planes, more on a grid finer than the pixels.
    """
    rng = np.random.default_rng(seed)
    before, perturbed = [], []
    for roi, shift in zip(rois, shifts, strict=True):
        idx, fit = _plane_model(psf, roi, shift, zplanes)
        var = _noise_variance(fit, background[idx, None, None], noise)
        d = np.zeros(roi.shape)
        d[idx] = PERTURBATION * np.sqrt(var) * rng.standard_normal(fit.shape)
        before.append((idx, fit))
        perturbed.append(d)
    other = rebuild([roi + d for roi, d in zip(rois, perturbed, strict=True)])
    num = den = 0.0
    for roi, shift, mask, d, (idx, fit) in zip(rois, shifts, masks, perturbed, before, strict=True):
        idx2, fit2 = _plane_model(other, roi + d, shift, zplanes)
        both, i1, i2 = np.intersect1d(idx, idx2, return_indices=True)
        keep, dd = mask[both], d[both]
        num += float(np.sum(((fit2[i2] - fit[i1]) * dd)[keep]))
        den += float(np.sum((dd**2)[keep]))
    return float(np.clip(num / den, 0.0, 1.0)) if den > 0 else 0.0


def _noise_variance(
    fit: NDArray[np.float64], background: ArrayLike, noise: tuple[float, float]
) -> NDArray[np.float64]:
    """The camera's variance (photons^2) of a bead's voxels: ``a * mu + b`` (``noise``) for
    the fitted light ``fit`` plus the frame's ``background``."""
    return noise[0] * np.maximum(fit + background, 0.0) + noise[1]


def _plane_model(
    psf: SplinePSF, roi: NDArray[np.float64], shift: NDArray[np.float64], zplanes: NDArray
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """The planes of :func:`plane_fits` and the fitted light on them (planes, R, R)."""
    idx, imgs, scale, offset = plane_fits(psf, roi, shift, zplanes)
    return idx, scale[:, None, None] * imgs + offset[:, None, None]


#: How far (steps) a bead's stack may be extrapolated past its end planes for the model to
#: keep them (:func:`sparseloc.calibrate._model_planes`), and so how far beyond its range the
#: model serves a plane (:func:`served_planes`), both continued linearly from the two end
#: planes: there the linear extrapolation's error, d (d + step) f'' / 2 at a distance d, is
#: at most that of linear interpolation half-way between planes, step^2 f'' / 8 (the
#: model's cubic interpolation inside its range errs less).
EXTRAPOLATE_STEPS = (np.sqrt(2.0) - 1.0) / 2.0


def served_planes(
    z: NDArray[np.float64], z_range: tuple[float, float], zplanes: NDArray[np.float64]
) -> NDArray[np.intp]:
    """The planes whose z (nm; a bead's planes ``zplanes`` moved by its z shift) a model of
    ``z_range`` serves: those inside the range, and those at most :data:`EXTRAPOLATE_STEPS`
    of the planes' step beyond it (a bead whose height differs from the beads' mean by a
    fraction of a step), drawn by :func:`served_images`."""
    lo, hi = z_range
    reach = EXTRAPOLATE_STEPS * _step(zplanes) + 1e-9
    return np.flatnonzero((z >= lo - reach) & (z <= hi + reach))


def served_images(
    psf: SplinePSF,
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    z: NDArray[np.float64],
    shape: tuple[int, int],
) -> NDArray[np.float64]:
    """``psf.images`` of emitters at ``x``, ``y``, ``z`` (nm, (n,); z of
    :func:`served_planes`) on ``shape`` pixels, continued linearly beyond the model's range
    from its two end planes (as a bead's stack is, :func:`sparseloc.calibrate._z_extended`;
    a model without planes, a fitted pupil, repeats its end plane): (n, rows, cols)."""
    lo, hi = psf.z_range
    p = psf.pixel_size
    zc = np.clip(z, lo, hi)
    imgs = psf.images(x, y, zc, shape, p)
    past = np.flatnonzero(zc != z)
    step = float(getattr(psf, "z_step", 0.0) or 0.0)
    if past.size == 0 or step <= 0:
        return imgs
    inner = np.clip(zc[past] - np.sign(z[past] - zc[past]) * step, lo, hi)
    gap = np.abs(zc[past] - inner)
    t = np.where(gap > 0, np.abs(z[past] - zc[past]) / np.where(gap > 0, gap, 1.0), 0.0)
    t = t[:, None, None]
    imgs[past] = (1.0 + t) * imgs[past] - t * psf.images(x[past], y[past], inner, shape, p)
    return imgs


def _step(zplanes: NDArray[np.float64]) -> float:
    """The planes' step (nm; 0 for one plane)."""
    return abs(float(np.median(np.diff(zplanes)))) if zplanes.size > 1 else 0.0


def plane_fits(
    psf: SplinePSF,
    roi: NDArray[np.float64],
    shift: NDArray[np.float64],
    zplanes: NDArray[np.float64],
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """A bead against the model, plane by plane: the model at the bead's ``shift`` (x, y, z nm
    from the ROI's centre) with a least-squares scale and offset per plane.

    Returns
    -------
    idx : ndarray of int
        The planes of ``roi`` (Nz, R, R) whose shifted z the model serves
        (:func:`served_planes`).
    images : ndarray, shape (len(idx), R, R)
        The model's unit-photon images on those planes.
    scale, offset : ndarray, shape (len(idx),)
        Photons and background (photons/pixel) of each plane's fit.
    """
    _, h, w = roi.shape
    p = psf.pixel_size
    z = zplanes + shift[2]
    idx = served_planes(z, psf.z_range, zplanes)
    if idx.size == 0:
        return idx, np.zeros((0, h, w)), np.zeros(0), np.zeros(0)
    imgs = served_images(
        psf,
        np.full(idx.size, w * p / 2 + shift[0]),
        np.full(idx.size, h * p / 2 + shift[1]),
        z[idx],
        (h, w),
    )
    scale, offset = np.zeros(idx.size), np.zeros(idx.size)
    for j, (k, m) in enumerate(zip(idx, imgs, strict=True)):
        design = np.stack([m.ravel(), np.ones(m.size)], axis=1)
        (scale[j], offset[j]), *_ = np.linalg.lstsq(design, roi[k].ravel(), rcond=None)
    return idx, imgs, scale, offset


def _bead_residual(
    psf: SplinePSF,
    roi: NDArray[np.float64],
    shift: NDArray[np.float64],
    zplanes: NDArray[np.float64],
    background: NDArray[np.float64],
    mask: NDArray[np.bool_],
    camera_noise: tuple[float, float] = (1.0, 0.0),
    kept: float = 1.0,
) -> tuple[NDArray, NDArray, NDArray, NDArray[np.bool_], NDArray]:
    """Per plane: the residual power, the expected noise power and the signal power of one
    bead against the model (:func:`plane_fits`) over the voxels of ``mask`` (the camera's
    noise ``a * mu + b``: ``camera_noise``), which planes count, and the residual's excess
    over ``kept`` times the noise pixel by pixel per photon squared (planes, rows, cols; 0
    outside ``mask``)."""
    nz = roi.shape[0]
    res2, noise, sig2 = np.zeros(nz), np.zeros(nz), np.zeros(nz)
    excess = np.zeros(roi.shape)
    ok = np.zeros(nz, bool)
    idx, imgs, scale, offset = plane_fits(psf, roi, shift, zplanes)
    for k, m, a, b in zip(idx, imgs, scale, offset, strict=True):
        fit = a * m + b
        keep = mask[k]
        r2 = (roi[k] - fit) ** 2
        var = _noise_variance(fit, background[k], camera_noise)
        res2[k], noise[k] = float(np.sum(r2[keep])), float(np.sum(var[keep]))
        sig2[k] = float(np.sum((a * m)[keep] ** 2))
        ok[k] = True
        if a > 0:
            excess[k] = np.where(keep, (r2 - kept * var) / a**2, 0.0)
    return res2, noise, sig2, ok, excess


#: Smoothing (planes, pixels, pixels) of the error table: each pixel's variance comes from a
#: few beads, so neighbouring planes and pixels are averaged (Gaussian standard deviations).
ERROR_TABLE_SMOOTHING = (2.0, 1.0, 1.0)


def _clipped_keeping_total(var: NDArray[np.float64]) -> NDArray[np.float64]:
    """The smoothed excess ``var`` (planes, rows, cols) clipped at zero and scaled back to its
    total before the clip (zero where that total is not positive).

    Where the beads are dim, each voxel's excess is mostly noise about zero; the clip alone
    would keep its positive half everywhere, an allowance for an error the beads do not show.
    The total is the unbiased measure of how much error there is, pooled over the planes as
    the model error is (one plane's total is itself noise there); the clip only says where
    the error lies."""
    kept = np.maximum(var, 0.0)
    held = float(kept.sum())
    return kept * (max(float(var.sum()), 0.0) / held if held > 0 else 0.0)


def _error_table(
    psf: SplinePSF,
    maps: NDArray,
    count: NDArray,
    zplanes: NDArray[np.float64],
    shifts: list[NDArray[np.float64]],
) -> SplinePSF | None:
    """:attr:`ModelError.table` from the beads' excess maps summed over ``count`` beads per
    voxel."""
    covered = np.flatnonzero(count.reshape(count.shape[0], -1).max(axis=1) > 0)
    if covered.size < 4:
        return None
    var = np.zeros_like(maps)
    var[covered] = maps[covered] / np.maximum(count[covered], 1)
    var = _clipped_keeping_total(gaussian_filter(var, ERROR_TABLE_SMOOTHING, mode="nearest"))
    sl = slice(covered.min(), covered.max() + 1)
    # the beads sit at the ROIs' centres plus their shifts; the table is centred on their mean
    _, h, w = maps.shape
    sx, sy = np.mean([s[:2] for s in shifts], axis=0) / psf.pixel_size
    centre = ((h - 1) / 2.0 + sy, (w - 1) / 2.0 + sx)
    return SplinePSF(var[sl], psf.pixel_size, zplanes[sl], centre=centre, normalise=False,
                     name=f"{psf.name} error")  # fmt: skip
