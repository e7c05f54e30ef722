"""A bead calibration's model on a grid finer than the camera's pixels (an effective PSF).

Each bead's pixels sample the pixel-integrated PSF at the bead's own sub-pixel offset. Where
the pixels are coarse for the PSF (160 nm pixels and a high-NA objective sample it below its
optical Nyquist rate), beads registered by resampling their pixels do not agree and their
average is blurred (``docs/benchmarks/calibration_pixel_phase.txt``). Here the model is a grid
of :data:`OVERSAMPLE` nodes per pixel and axis, fitted to every bead's samples at their own
offsets (the "effective PSF" of Anderson & King 2000): starting from the pixel model, each
round renders every bead with the grid's cubic spline at its registered position (a scale and
a background per plane fitted linearly) and moves each node by the mean residual, in the
model's units, of the samples around it (each sample spread over its four nodes with bilinear
weights, the sums smoothed over half a node: a node is set by several samples, not by the
noise of one). The beads' registration (their shifts) is the calibration's own.

The grid has ``OVERSAMPLE**2`` times the pixels' voxels; it is fitted only where the pixels
undersample the PSF (:func:`undersampled`: the beads' images hold light next to the pixels'
Nyquist frequency) and the beads give each of its phases (sub-pixel offsets)
:data:`BEADS_PER_PHASE` beads on average. Where the pixels sample the PSF finely the pixel
model holds all there is, and the grid's extra freedom would only fit the beads' noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, map_coordinates, spline_filter

__all__ = [
    "BAND_POWER",
    "BEADS_PER_PHASE",
    "OVERSAMPLE",
    "ROUNDS",
    "oversampled_model",
    "phases_spread",
    "undersampled",
    "worth_oversampling",
]

#: Grid nodes per pixel and axis of a calibrated model.
OVERSAMPLE = 2
#: Smoothing (nodes, Gaussian sigma) of the back-projected residuals' sums.
SMOOTH = 0.5
#: Rounds of the residuals' back-projection onto the grid.
ROUNDS = 10
#: Beads per sub-pixel phase of the grid, on average, below which it is not fitted.
BEADS_PER_PHASE = 1


def phases_spread(offsets: NDArray[np.float64], oversample: int = OVERSAMPLE) -> bool:
    """Whether the beads' sub-pixel positions ``offsets`` (B, 2; pixels, any whole-pixel
    part) differ along each axis by more than half the grid's node spacing (their smallest
    arc on the pixel's circle of phases spans over ``1 / (2 oversample)`` px). Beads that all
    sit at one phase sample the grid's nodes between phases at none: the grid then holds the
    smoothing's guess there, and its misfit to the beads says nothing about it."""
    phases = np.mod(np.asarray(offsets, dtype=np.float64).reshape(-1, 2), 1.0)
    if len(phases) < 2:
        return False
    for axis in range(2):
        p = np.sort(phases[:, axis])
        gaps = np.diff(np.append(p, p[0] + 1.0))
        if 1.0 - gaps.max() <= 0.5 / oversample:
            return False
    return True


def worth_oversampling(n_beads: int, oversample: int = OVERSAMPLE) -> bool:
    """Whether ``n_beads`` beads sample each of the grid's ``oversample**2`` phases
    :data:`BEADS_PER_PHASE` times on average."""
    return n_beads >= BEADS_PER_PHASE * oversample**2


def oversampled_model(
    clean: NDArray[np.float64],
    beads: list[tuple[NDArray[np.float64], float, float]],
    oversample: int = OVERSAMPLE,
    rounds: int = ROUNDS,
) -> NDArray[np.float64]:
    """The model stack on a grid of ``oversample`` nodes per pixel, fitted to the beads.

    Parameters
    ----------
    clean : ndarray, shape (Nz, R, C)
        The pixel model (each plane summing to one photon); its voxel ``(r, c)`` is the
        pixel value of an emitter at the model's centre, offset ``(r, c)`` minus that centre.
    beads : list of (ndarray (Nz, R, C), float, float)
        Each bead's ROI stack (photons, on the model's planes) and its shift ``(dy, dx)``
        (pixels) from the model's frame: its ROI pixel ``(r, c)`` lies at ``(r - dy, c - dx)``
        in the model's frame.
    oversample : int
        Nodes per pixel and axis.
    rounds : int
        Rounds of back-projection.

    Returns
    -------
    ndarray, shape (Nz, R * oversample, C * oversample)
        Node ``(u, v)`` is the model at ``(u, v) / oversample`` in the pixel model's frame:
        a :class:`~sparseloc.psf.spline.SplinePSF` with ``oversample`` and the centre times
        ``oversample``. Each plane sums to ``oversample**2`` (one photon per phase) and
        keeps the pixel model's mean level along its border; dark nodes hold the beads'
        noise about it, negative values too (the caller clips them after its smoothing).
    """
    o = int(oversample)
    nz = clean.shape[0]
    grid = _upsampled(clean, o)
    shape = grid.shape[1:]
    samples = [_sample_coords(d, dy, dx, o, shape) for d, dy, dx in beads]
    floor = _border_mean(grid)
    for _ in range(rounds):
        acc = np.zeros_like(grid)
        cnt = np.zeros_like(grid)
        for k in range(nz):
            coef = spline_filter(grid[k], order=3, mode="mirror")
            for (data, _, _), (gy, gx, ok) in zip(beads, samples, strict=True):
                _back_project(coef, data[k][ok], gy, gx, acc[k], cnt[k])
        acc = gaussian_filter(acc, (0.0, SMOOTH, SMOOTH), mode="constant")
        cnt = gaussian_filter(cnt, (0.0, SMOOTH, SMOOTH), mode="constant")
        seen = cnt > 1e-3
        grid = grid + np.where(seen, acc / np.where(seen, cnt, 1.0), 0.0)
        # The beads' fitted backgrounds cannot tell the model's floor from their own, so the
        # residuals leave it where it is; it stays the pixel model's. (A clip at zero here
        # would raise the dark nodes' noise, round by round, into a floor: a model broader
        # than the PSF.)
        grid += (floor - _border_mean(grid))[:, None, None]
        grid *= o * o / grid.sum(axis=(1, 2), keepdims=True)
    return grid


def _border_mean(stack: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each plane's mean over its outermost rows and columns (Nz,)."""
    edge = np.ones(stack.shape[1:], bool)
    edge[1:-1, 1:-1] = False
    return stack[:, edge].mean(axis=1)


def _upsampled(clean: NDArray[np.float64], o: int) -> NDArray[np.float64]:
    """The pixel model's cubic spline at every node: the first grid."""
    nz, rows, cols = clean.shape
    u, v = np.mgrid[0 : rows * o, 0 : cols * o] / o
    out = np.stack([map_coordinates(clean[k], [u, v], order=3, mode="nearest") for k in range(nz)])
    out = np.maximum(out, 0.0)
    return out * (o * o / out.sum(axis=(1, 2), keepdims=True))


def _sample_coords(data: NDArray, dy: float, dx: float, o: int, shape: tuple[int, int]):
    """A bead's samples on the grid: their grid coordinates and which samples fall inside
    the grid."""
    rows, cols = data.shape[1:]
    r, c = np.mgrid[0:rows, 0:cols]
    gy = (o * (r - dy)).ravel()
    gx = (o * (c - dx)).ravel()
    ok = (gy >= 0) & (gy <= shape[0] - 1) & (gx >= 0) & (gx <= shape[1] - 1)
    return gy[ok], gx[ok], ok.reshape(rows, cols)


def _back_project(coef, values, gy, gx, acc, cnt) -> None:
    """One plane of one bead: its scale and background fitted to the model's samples, the
    residual (model units) spread over each sample's four nodes with bilinear weights."""
    model = map_coordinates(coef, [gy, gx], order=3, prefilter=False, mode="mirror")
    design = np.column_stack([model, np.ones_like(model)])
    (scale, background), *_ = np.linalg.lstsq(design, values, rcond=None)
    if not scale > 0:
        return
    residual = (values - background) / scale - model
    r0 = np.minimum(np.floor(gy).astype(np.intp), acc.shape[0] - 2)
    c0 = np.minimum(np.floor(gx).astype(np.intp), acc.shape[1] - 2)
    fy, fx = gy - r0, gx - c0
    for dr, dc, w in ((0, 0, (1 - fy) * (1 - fx)), (0, 1, (1 - fy) * fx),
                      (1, 0, fy * (1 - fx)), (1, 1, fy * fx)):  # fmt: skip
        np.add.at(acc, (r0 + dr, c0 + dc), w * residual)
        np.add.at(cnt, (r0 + dr, c0 + dc), w)


#: The band of spatial frequencies (cycles per pixel, along either axis) next to the pixels'
#: Nyquist frequency of 0.5 where a well-sampled PSF holds no light.
NEAR_NYQUIST = 0.45
#: Standard errors by which the beads' power in that band must exceed the noise's.
SIGNIFICANCE = 5.0
#: The beads' power in that band over the noise's at least: a ratio of 2 means their light
#: there equals the noise (a signal-to-noise ratio of one per frequency). Fainter aliased
#: light than one bead's noise is not worth the grid's freedom, which a few beads' noise fills.
BAND_POWER = 2.0


def undersampled(rois: list[NDArray[np.float64]]) -> bool:
    """Whether the pixels sample the beads' PSF below its optical Nyquist rate: their images
    hold power at frequencies of :data:`NEAR_NYQUIST` cycles per pixel and more, at least
    :data:`BAND_POWER` times the noise's there and beyond it by :data:`SIGNIFICANCE`
    standard errors.

    A PSF whose optical cutoff lies below ``NEAR_NYQUIST`` leaves only noise there, whatever
    its shape; one that reaches past 0.5 cycles per pixel is aliased, and beads at different
    sub-pixel phases then disagree once resampled. The noise's power is the data's own: that
    of the difference of neighbouring planes over sqrt(2) (a PSF changes little from one
    plane to the next; what it does change counts as noise, against the grid). The planes
    are the brighter half of each bead's, Hann-windowed against edge leakage; the test takes
    one standard error of ``1 / sqrt(planes)`` (an upper bound: each plane averages many
    frequencies).

    Parameters
    ----------
    rois : list of ndarray, shape (Nz, R, R)
        The beads' ROI stacks (photons).
    """
    ratios = []
    for roi in rois:
        n = roi.shape[-1]
        w = np.outer(np.hanning(n + 2)[1:-1], np.hanning(n + 2)[1:-1])
        f = np.abs(np.fft.fftfreq(n))
        band = np.maximum(f[:, None], f[None, :]) >= NEAR_NYQUIST
        if not band.any() or roi.shape[0] < 2:
            continue
        bright = np.argsort(roi[:-1].max(axis=(1, 2)))[::-1][: max(1, roi.shape[0] // 2)]
        for k in bright:
            signal = np.abs(np.fft.fft2((roi[k] - np.median(roi[k])) * w)) ** 2
            noise = np.abs(np.fft.fft2((roi[k + 1] - roi[k]) * w)) ** 2 / 2.0
            level = float(noise[band].mean())
            if level > 0:
                ratios.append(float(signal[band].mean()) / level)
    if not ratios:
        return False
    bar = max(BAND_POWER, 1.0 + SIGNIFICANCE / np.sqrt(len(ratios)))
    return float(np.mean(ratios)) > bar
