"""PSF calibration from bead z-stacks: find beads, register, average, build a spline model.

The steps (each a function over NumPy arrays; file reading only in :func:`calibrate_file`):

1. ADU to photons; per-frame background (median of the frame: beads cover a small fraction
   of the field); see :mod:`sparseloc.calibrate_scan`.
2. Find beads on the z-averaged frame, smoothed at the scale of the PSF. An engineered PSF
   (double helix, tetrapod) may show several maxima per bead; maxima closer than half an ROI
   are merged and the bead's centre is the centroid of its z-averaged image (the midpoint of
   a double helix's lobes).
3. ROI size from the PSF's light: it holds 99 % of a plane's light on average, of the light
   that stands above the frame's background around the brightest beads
   (:mod:`sparseloc.calibrate_crowd`), unless given. A halo fainter than the background's
   noise is not measured: fitted photons count the light inside the model.
4. Reject beads too close to the edge, beads whose cores overlap another's, saturated beads,
   and, after registration, beads whose registered stack differs from the others' average far
   more than the rest (outliers: dirt, aggregates, a bead stuck to another one).
5. Register beads to each other in x, y, z with sub-pixel accuracy by fitting each bead with
   the spline model of the current average (Gauss-Newton on shift and scale), resample, and
   average weighted by brightness; repeat. Where beads lie closer than an ROI, each bead's
   ROI is cleaned of its neighbours' modelled light and the beads are registered again.
6. Subtract what is left of the background (the median of the ROI's border per plane),
   normalise each plane to one photon, smooth along z as far as the beads say
   (:mod:`sparseloc.calibrate_zsmooth`), and build a :class:`~sparseloc.psf.spline.SplinePSF`,
   cut where the beads' light falls below the model's noise (dim beads; the model is then
   smaller than the ROI, :attr:`Calibration.emitter_pixel`).

Optionally the pupil phase is fitted to the averaged stack (:mod:`sparseloc.psf.retrieval`).

Coordinates (design.md): ``z = (slice - z0_slice) * z_step`` with ``z0_slice`` the middle slice
by default, or the z of each frame from a file. The lateral origin of the model is the centroid
of the z-averaged bead image.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from .calibrate_crowd import (
    REPEATED_LIGHT,
    ROI_ENERGY_LEAST,
    LightProfile,
    light_profile,
    neighbour_light,
    plane_photons,
    repeated_light,
)
from .calibrate_error import (
    EXTRAPOLATE_STEPS,
    MAX_MODEL_ERROR,
    bead_errors,
    bead_model_error,
    self_influence,
)
from .calibrate_oversample import (
    OVERSAMPLE,
    oversampled_model,
    phases_spread,
    undersampled,
    worth_oversampling,
)
from .calibrate_scan import (
    BeadScan,
    frame_background,
    read_bead_positions,
    read_scan,
    read_z_file,
)
from .calibrate_zsmooth import (
    choose_window,
    clean_average,
    fallback_window,
    kept_mean,
    model_stack,
    smooth_along_z,
    smoothing_nm,
)
from .camera import Camera, camera_mismatch, photon_noise
from .psf.base import PSFModel
from .psf.spline import SplinePSF
from .psf.symmetry import mirror_warning, ncc_planes

__all__ = [
    "Calibration",
    "calibrate_beads",
    "calibrate_file",
    "detection_sigma",
    "find_beads",
    "read_bead_positions",
    "read_z_file",
]

log = logging.getLogger(__name__)

BEAD_COLUMNS = [
    "x_nm",
    "y_nm",
    "used",
    "reason",
    "photons",
    "shift_x_nm",
    "shift_y_nm",
    "shift_z_nm",
    "residual",
]


@dataclass
class Calibration:
    """The result of a bead calibration.

    Attributes
    ----------
    psf : SplinePSF
        The measured model (unit photons per plane, at ``pixel_size``); it may be smaller
        than ``average`` (cut where the beads' light falls below its noise).
    average : ndarray, shape (Nz, R, R)
        Registered, averaged, background-subtracted bead stack at the camera's pixels, each
        plane summing to one (the model refines it on a finer grid, see ``psf.oversample``).
    z : ndarray, shape (Nz,)
        Plane positions (nm).
    pixel_size : float
        Pixel size (nm).
    beads : DataFrame
        One row per bead found: position (nm, native coordinates), ``used``, the rejection
        ``reason`` (empty when used), photons per plane, fitted shifts (nm) and the ``residual``:
        the bead's own model error against the beads' average, beyond the camera's noise
        (NaN where fewer than 3 beads were compared).
    projection : ndarray, shape (H, W)
        The z-averaged background-subtracted frame, for the diagnostic figure.
    bead_ncc : ndarray, shape (n_used, Nz)
        Normalised cross-correlation of each registered bead with the average, per plane.
    pupil : RetrievalResult or None
        Pupil phase fitted to ``average`` when asked for.
    params : dict
        The parameters the calibration ran with.
    """

    psf: SplinePSF
    average: NDArray[np.float64]
    z: NDArray[np.float64]
    pixel_size: float
    beads: pd.DataFrame
    projection: NDArray[np.float64]
    pupil: Any = None
    params: dict[str, Any] = field(default_factory=dict)
    bead_ncc: NDArray[np.float64] | None = None
    #: The beads a model's error is measured on (not written to the calibration file).
    evidence: Any = field(default=None, repr=False, compare=False)

    @property
    def model_cut(self) -> int | None:
        """The model's side (px) where it is cut to its light, smaller than ``average``'s
        ROI; else None."""
        side = int(self.params.get("roi_size_px", self.average.shape[1]))
        return side if side < self.average.shape[1] else None

    @property
    def emitter_pixel(self) -> tuple[float, float]:
        """The emitter's position (row, col; px) in ``average``'s frame. A model cut to its
        light is smaller than ``average`` and holds it elsewhere in its own frame
        (``params["model_shift_px"]`` apart)."""
        dr, dc = self.params.get("model_shift_px", (0.0, 0.0))
        r, c = self.psf.pixel_centre
        return (r + dr, c + dc)

    @property
    def content_hash(self) -> str:
        """Hash of the spline model's data (see :attr:`SplinePSF.content_hash`)."""
        return self.psf.content_hash

    @property
    def n_used(self) -> int:
        return int(self.beads["used"].sum())


def _centroid(img: NDArray[np.float64], r: float, c: float, radius: float) -> tuple[float, float]:
    """Centroid of the positive part of ``img`` in a disc; iterated so it settles."""
    rows, cols = np.indices(img.shape)
    for _ in range(5):
        m = (rows - r) ** 2 + (cols - c) ** 2 <= radius**2
        w = np.clip(img, 0, None) * m
        s = w.sum()
        if s <= 0:
            break
        r_new, c_new = (w * rows).sum() / s, (w * cols).sum() / s
        if abs(r_new - r) < 1e-3 and abs(c_new - c) < 1e-3:
            r, c = r_new, c_new
            break
        r, c = r_new, c_new
    return float(r), float(c)


def _maxima(sm: NDArray[np.float64], sigma: float) -> NDArray[np.bool_]:
    """The local maxima (bool, ``sm``'s shape) of a frame smoothed by ``sigma`` px, over a
    neighbourhood of that smoothing's width."""
    from scipy.ndimage import maximum_filter

    return sm == maximum_filter(sm, size=int(2 * np.ceil(sigma) + 1))


def _brightness_scale(
    sm: NDArray[np.float64],
    peaks: NDArray[np.bool_],
    radius: float,
    saturated: NDArray[np.bool_] | None = None,
) -> float:
    """The brightness the bead detection's threshold is a fraction of: the brightest of the
    smoothed frame ``sm``'s maxima ``peaks`` (:func:`_maxima`) farther than ``radius`` px
    from every ``saturated`` pixel (a saturated bead, unusable and brighter than any, would
    hide every usable one); the brightest maximum where none is saturated or every one is
    near."""
    from scipy.ndimage import distance_transform_edt

    vals = sm[peaks]
    if saturated is not None:
        mask = np.asarray(saturated, dtype=bool)
        if mask.shape != sm.shape:
            raise ValueError(
                f"the saturation mask's shape {mask.shape} is not the frame's {sm.shape}"
            )
        if mask.any():
            far = distance_transform_edt(~mask)[peaks] > radius
            vals = vals[far] if far.any() else vals
    return float(vals.max()) if vals.size else 0.0


def find_beads(
    projection: NDArray[np.float64],
    *,
    sigma: float = 3.0,
    threshold: float = 0.2,
    merge_radius: float = 6.0,
    saturated: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """Bead centres (row, col in pixels) on a z-averaged, background-subtracted frame.

    Parameters
    ----------
    projection : ndarray, shape (H, W)
        z-averaged frame in photons, background subtracted.
    sigma : float
        Gaussian smoothing (px) before looking for maxima: at the scale of the PSF, so a
        double helix's ring of lobe positions becomes one hill.
    threshold : float
        Keep maxima above this fraction of the brightest one that is not a saturated bead's
        (:func:`_brightness_scale`), and above 6 robust standard deviations of the smoothed
        frame's noise.
    merge_radius : float
        Maxima closer than this (px) are one bead.
    saturated : ndarray of bool, shape (H, W), optional
        Pixels saturated in some frame: a maximum within ``merge_radius`` of one is found
        but does not set the brightness the threshold is a fraction of (a saturated bead,
        unusable and brighter than any, would hide every usable one).

    Returns
    -------
    ndarray, shape (n, 2)
        Centroids (row, col), brightest first.
    """
    sm, floor = _smoothed_light(projection, sigma)
    maxima = _maxima(sm, sigma)
    rr, cc = np.nonzero(maxima & (sm > floor))
    if rr.size == 0:
        return np.zeros((0, 2))
    vals = sm[rr, cc]
    keep = vals >= threshold * _brightness_scale(sm, maxima, merge_radius, saturated)
    rr, cc, vals = rr[keep], cc[keep], vals[keep]
    order = np.argsort(-vals)
    centres: list[tuple[float, float]] = []
    for r, c in zip(rr[order], cc[order], strict=True):
        if all((r - r0) ** 2 + (c - c0) ** 2 > merge_radius**2 for r0, c0 in centres):
            centres.append((float(r), float(c)))
    out = [_centroid(projection, r, c, merge_radius) for r, c in centres]
    # Centroids of merged maxima may land on one another: merge again.
    merged: list[tuple[float, float]] = []
    for r, c in out:
        if all((r - r0) ** 2 + (c - c0) ** 2 > (merge_radius / 2) ** 2 for r0, c0 in merged):
            merged.append((r, c))
    return np.array(merged, dtype=np.float64).reshape(-1, 2)


def _smoothed_light(
    projection: NDArray[np.float64], sigma: float
) -> tuple[NDArray[np.float64], float]:
    """The projection smoothed by a Gaussian of ``sigma`` px, and the level a bead's light
    must pass there: 6 robust standard deviations of the smoothed frame's noise above its
    median."""
    from scipy.ndimage import gaussian_filter

    sm = gaussian_filter(projection, sigma)
    # Pixel noise from the high-pass part of the frame (robust to the beads' light), scaled
    # by the Gaussian's noise gain 1 / (2 sqrt(pi) sigma).
    hp = projection - gaussian_filter(projection, 1.0)
    noise = 1.4826 * np.median(np.abs(hp - np.median(hp))) / (2 * np.sqrt(np.pi) * sigma) + 1e-12
    return sm, float(np.median(sm) + 6 * noise)


def _listed_beads(
    found: NDArray[np.float64],
    known: ArrayLike,
    projection: NDArray[np.float64],
    p: float,
    detect_sigma: float,
    threshold: float,
    roi_size: int | None,
    saturated: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """The beads where their positions are known: each listed position's bead, then the beads
    found that no position lists.

    The detection finds beads by their light, which an engineered PSF spreads around the
    emitter, and it merges beads closer than its merge radius (a false bead between them).
    With the positions known, each listed bead's light lies at its position plus one offset
    that every bead shares (one PSF): the median offset of the positions' nearest beads
    found. A listed bead is the bead found within a match tolerance
    (:func:`_match_tolerance`) of where its light lies, else, where the detection found none
    of its own, that place, if the smoothed light there passes the detection's bar. A bead
    found near one position only but farther than the tolerance, or a position without
    light, means a wrong file: refused. A position whose light would lie outside the frame
    is left out (a file of a larger field). A bead found within the merge radius of a
    position and claimed by none is the detection's merge of listed beads: left out; one
    farther from every position is a bead the file does not list: kept, so that its light is
    modelled where it falls on a listed bead's ROI.

    Returns
    -------
    centres : ndarray, shape (n, 2)
        Bead centres (row, col; px): the listed beads in the file's order, then the others.
    listed : ndarray of int, shape (K,)
        Each position's index in ``centres`` (-1 where it was left out; positions listed
        twice share one).
    """
    xy_all = np.asarray(known, dtype=np.float64).reshape(-1, 2)
    xy, twin = np.unique(np.round(xy_all, 1), axis=0, return_inverse=True)
    want = np.c_[xy[:, 1] / p - 0.5, xy[:, 0] / p - 0.5]
    merge = _merge_radius(detect_sigma, roi_size)
    d = np.hypot(*(want[:, None, :] - found[None, :, :]).transpose(2, 0, 1))
    close = np.flatnonzero(d.min(axis=1) <= merge)
    if close.size == 0:
        raise ValueError(
            "none of the bead file's positions lies near a bead found; check the file's units "
            "and origin"
        )
    shift = np.median(found[np.argmin(d[close], axis=1)] - want[close], axis=0)
    expect = want + shift
    d = np.hypot(*(expect[:, None, :] - found[None, :, :]).transpose(2, 0, 1))
    claims = (d <= merge).sum(axis=0)  # positions within the merge radius of each bead found
    tol = _match_tolerance(d, claims, merge)
    sm, floor = _smoothed_light(projection, detect_sigma)
    scale = _brightness_scale(sm, _maxima(sm, detect_sigma), merge, saturated)
    bar = max(floor, threshold * scale)
    centres: list[NDArray[np.float64]] = []
    index = np.full(len(xy), -1)
    taken: set[int] = set()
    for k in range(len(xy)):
        j = int(np.argmin(d[k]))
        if d[k, j] <= tol and j not in taken:
            index[k] = len(centres)
            centres.append(found[j])
            taken.add(j)
            continue
        r, c = np.round(expect[k]).astype(int)
        if not (0 <= r < sm.shape[0] and 0 <= c < sm.shape[1]):
            log.warning("bead position (%.0f, %.0f) nm lies outside the stack: left out", *xy[k])
            continue
        if (d[k, j] <= merge and claims[j] == 1) or sm[r, c] <= bar:
            raise ValueError(
                f"bead position ({xy[k, 0]:.0f}, {xy[k, 1]:.0f}) nm of the bead file is more "
                f"than {tol:.3g} px from every bead found; check the file's units and origin"
            )
        index[k] = len(centres)
        centres.append(expect[k])
    if not centres:
        raise ValueError("every position of the bead file lies outside the stack")
    unlisted = [found[j] for j in range(len(found)) if j not in taken and claims[j] == 0]
    out = np.array(centres + unlisted, dtype=np.float64).reshape(-1, 2)
    return out, index[twin.ravel()]


def _match_tolerance(d: NDArray[np.float64], claims: NDArray[np.intp], merge: float) -> float:
    """How far (px) a listed position may lie from its bead found: :data:`BEAD_MATCH_PX`, or
    the 99 % distance of the beads' own scatter about the shared offset where it is wider
    (an engineered PSF's light, cut by the detection's disc, centres a bead within a pixel or
    two), up to half the merge radius. The scatter is the median distance of the positions
    from their nearest bead found, over the positions near a bead found that no other
    position claims (not the detection's merges), where there are :data:`SCATTER_BEADS` or
    more: for a 2-D Gaussian scatter of sigma per axis, the median distance is 1.177 sigma
    and the 99 % distance 3.03 sigma."""
    nearest = np.argmin(d, axis=1)
    dist = d[np.arange(len(d)), nearest]
    alone = (dist <= merge) & (claims[nearest] == 1)
    if alone.sum() < SCATTER_BEADS:
        return BEAD_MATCH_PX
    wide = 3.03 / 1.177 * float(np.median(dist[alone]))
    return float(np.clip(wide, BEAD_MATCH_PX, max(BEAD_MATCH_PX, merge / 2.0)))


#: Fewest listed beads, each near a bead found of its own, that measure the beads' scatter
#: about their positions (fewer: the match tolerance stays :data:`BEAD_MATCH_PX`).
SCATTER_BEADS = 4


def _roi(stack: NDArray[np.float64], r: int, c: int, half: int) -> NDArray[np.float64]:
    return stack[:, r - half : r + half + 1, c - half : c + half + 1]


def _fit_shift(
    model: PSFModel, data: NDArray[np.float64], z: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """Fit ``data ~ a * model(x0 + dx, y0 + dy, z + dz) + b``; return (dx, dy, dz) nm and a.

    Gauss-Newton on the shift with the scale and offset solved linearly at each step.
    """
    _, h, w = data.shape
    p = model.pixel_size
    x0, y0 = w * p / 2, h * p / 2
    shift = np.zeros(3)
    zlo, zhi = model.z_range
    a = 1.0
    for _ in range(20):
        zz = z + shift[2]
        # only planes inside the range: beyond it the model's z derivative says nothing
        ok = (zz >= zlo) & (zz <= zhi)
        if ok.sum() < 4:
            break
        img, der = model.images(
            np.full(ok.sum(), x0 + shift[0]),
            np.full(ok.sum(), y0 + shift[1]),
            zz[ok],
            (h, w),
            p,
            derivatives=True,
        )
        d = data[ok].ravel()
        m = img.ravel()
        design = np.stack([m, np.ones_like(m)], axis=1)
        (a, b), *_ = np.linalg.lstsq(design, d, rcond=None)
        res = d - a * m - b
        jac = np.stack([a * der[:, i].ravel() for i in range(3)], axis=1)
        # Project out the linear parameters' directions (variable projection, first order).
        q, _ = np.linalg.qr(design)
        jac = jac - q @ (q.T @ jac)
        step, *_ = np.linalg.lstsq(jac, res, rcond=None)
        step = np.clip(step, -0.5 * p, 0.5 * p)
        shift += step
        if np.all(np.abs(step) < 0.01):
            break
    return shift, float(a)


#: Planes added at each end of a stack before it is shifted along z: the cubic spline's
#: boundary condition reaches in by a factor 0.27 a plane, so six leave about 1e-4 of a
#: plane's change at the ends.
Z_PAD = 6


def _z_extended(stack: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """``stack`` (Z, H, W) with ``n`` planes added at each end, continued linearly from its
    two end planes; (Z + 2n, H, W)."""
    k = np.arange(1, n + 1, dtype=np.float64)[:, None, None]
    below = stack[0] + k[::-1] * (stack[0] - stack[1])
    above = stack[-1] + k * (stack[-1] - stack[-2])
    return np.concatenate([below, stack, above])


def _shift_stack(
    stack: NDArray[np.float64],
    shift_nm: NDArray[np.float64],
    pixel_size: float,
    z_step: float,
    extend: bool = True,
) -> NDArray[np.float64]:
    """Resample a bead stack so that its bead moves by ``-shift`` (x, y, z in nm); beyond its
    end planes continued along its end slopes (``extend``; a mask repeats its end planes)."""
    from scipy.ndimage import shift as nd_shift

    # data[k, r, c] ~ model(x0 + dx, y0 + dy, z_k + dz): an image displaced by +dx and seen
    # dz further along z. Aligned[k, r, c] = data[k - dz/step, r + dy/p, c + dx/p].
    s = (-shift_nm[2] / z_step, shift_nm[1] / pixel_size, shift_nm[0] / pixel_size)
    if stack.shape[0] < 2 or not extend:
        return nd_shift(stack, [-v for v in s], order=3, mode="nearest")
    # Beyond its first and last planes a bead's stack continues along its end slopes, so an
    # end plane moved by a fraction of a step is extrapolated rather than repeated.
    n = Z_PAD
    moved = nd_shift(_z_extended(stack, n), [-v for v in s], order=3, mode="nearest")
    return moved[n:-n]


def calibrate_beads(
    stack: ArrayLike,
    pixel_size: float,
    z_step: float | None = None,
    *,
    z: ArrayLike | None = None,
    valid: ArrayLike | None = None,
    z0_slice: float | None = None,
    offset: float = 0.0,
    gain: float = 1.0,
    roi_size: int | None = None,
    saturation: float | None = None,
    threshold: float = 0.2,
    detect_sigma: float | None = None,
    min_beads: int = 1,
    iterations: int = 3,
    name: str = "spline",
    fit_pupil: bool = False,
    pupil_options: dict[str, Any] | None = None,
    z_smooth: bool = True,
    beads: ArrayLike | None = None,
    progress: Callable[[], None] | None = None,
    camera: Camera | None = None,
) -> Calibration:
    """Build a measured PSF model from a bead z-stack.

    Parameters
    ----------
    stack : array_like, shape (Nz, H, W)
        Camera frames (ADU) of a field of beads scanned through focus, one frame per z.
    pixel_size : float
        Pixel size in sample space (nm).
    z_step : float, optional
        Stage step between frames (nm); needed unless ``z`` is given.
    z : array_like, shape (Nz,), optional
        The z (nm) of each frame, for uneven scans (resampled to an even grid of step
        ``z_step`` or the median step).
    valid : array_like of bool, shape (Nz,), optional
        Frames to use (with ``z``).
    z0_slice : float, optional
        Slice index of z = 0 (default the middle slice); ignored when ``z`` is given.
    offset, gain : float
        Camera offset (ADU) and conversion gain (photons per ADU).
    roi_size : int, optional
        ROI side (px, odd); default from the PSF's measured extent.
    saturation : float, optional
        ADU at which the camera saturates; default the integer type's maximum.
    threshold : float
        Bead detection threshold, a fraction of the brightest bead that is not saturated.
    detect_sigma : float, optional
        Smoothing (px) for bead detection; default :func:`detection_sigma` of the pixel
        size (the scale of a PSF, so a double helix's ring of lobe positions is one bead).
    min_beads : int
        Fewest usable beads to accept. One bead is accepted where its frames agree as a
        bead scan's do; its model error is then not cross-checked against other beads
        (``params["bead_warning"]`` says so).
    iterations : int
        Rounds of registration.
    name : str
        Name of the model.
    z_smooth : bool
        Smooth the average along z (a cubic Savitzky-Golay filter) so the model's
        z-derivative does not follow photon noise; the beads choose the window by
        cross-validation (:mod:`sparseloc.calibrate_zsmooth`); one bead gets about 80 nm,
        none for steps of 30 nm or more.
    beads : array_like, shape (B, 2), optional
        The beads' known x, y (nm, native coordinates; :func:`read_bead_positions`): the
        listed positions are the beads, also where the detection merges two or misses one
        (beads found that the file does not list count as well; :func:`_listed_beads`), and
        the model's lateral origin is the emitter, placed so the listed beads used sit at
        their known positions on average. Without them it is the centroid of the z-averaged
        image.
    fit_pupil : bool
        Also fit the pupil phase to the average (``pupil_options`` go to
        :func:`sparseloc.psf.retrieval.fit_pupil`: ``na``, ``wavelength``, ...).
    progress : callable, optional
        Called with no argument between the steps of the work (and after each bead's
        registration); an exception it raises stops the calibration (a viewer's Cancel).
    camera : Camera, optional
        The camera that ``offset`` and ``gain`` describe: its gain is checked against the
        stack's own noise (:func:`sparseloc.camera.camera_mismatch`), a disagreement kept in
        ``params["camera_warning"]`` ("" where they agree). An sCMOS camera's per-pixel maps
        convert the stack (``offset`` and ``gain`` are then their medians,
        :func:`~sparseloc.calibrate_scan.scan_conversion`); that check, which reads one
        offset and gain from the stack's mean-variance line, is left out there.

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        For a stack that is not 3-D or has one frame, a bad z step, no usable beads, fewer
        than ``min_beads``, all beads saturated, NaNs; each message says what to try.
    """
    noise = photon_noise(camera)
    scan = read_scan(
        stack, pixel_size, z_step, z, valid, z0_slice, offset, gain, saturation, camera, noise
    )
    if detect_sigma is None:
        detect_sigma = detection_sigma(scan.pixel_size)
    cal = _calibrate_scan(
        scan,
        roi_size,
        threshold,
        detect_sigma,
        min_beads,
        iterations,
        name,
        z_smooth,
        beads,
        progress or (lambda: None),
        noise,
    )
    if fit_pupil:
        cal.pupil = _fit_pupil_in_frame(cal, pupil_options)
        _pupil_model_error(cal)
    if camera is not None and camera.map_shape is None:
        cal.params["camera_warning"] = camera_mismatch(stack, camera)
    log.info("calibrated from %d of %d beads, %d planes", cal.n_used, len(cal.beads), cal.z.size)
    return cal


# -- from the scan to the model -------------------------------------------------------------


def _calibrate_scan(
    scan: BeadScan,
    roi_size: int | None,
    threshold: float,
    detect_sigma: float,
    min_beads: int,
    iterations: int,
    name: str,
    z_smooth: bool,
    known: ArrayLike | None = None,
    tick: Callable[[], None] = lambda: None,
    noise: tuple[float, float] = (1.0, 0.0),
) -> Calibration:
    """Find the beads, vet them, register and average them, and build the spline model;
    ``tick()`` between the steps."""
    p, step = scan.pixel_size, scan.step
    saturated = _saturated_pixels(scan)
    centres = _detect(scan.projection, detect_sigma, threshold, roi_size, saturated)
    listed = None
    if known is not None:
        centres, listed = _listed_beads(
            centres, known, scan.projection, p, detect_sigma, threshold, roi_size, saturated
        )
    tick()
    camera = CameraNoise(*noise, scan.background)
    variance = camera.sd(np.zeros((scan.data.shape[0], 1, 1)))[:, 0, 0] ** 2
    roi, half, profile = _roi_size(scan.data, centres, roi_size, variance)
    # Beads share one PSF, so a neighbour's light can be modelled and removed; only beads
    # whose cores overlap are rejected.
    core = profile.core if profile is not None else half / 2.0
    reason, used = _vet_beads(centres, half, 2.0 * max(core, 1.0), scan)
    nb = centres.shape[0]
    _enough_beads(used, nb, min_beads, scan, centres, half)
    residual = dict.fromkeys(range(nb), np.nan)
    stacks = _BeadStacks(scan.data, centres, used, half, p, step)
    stacks.tick = tick
    stacks.noise = camera
    neighbours = _neighbour_pairs(centres, reason, roi)
    stacks.crowded = set(neighbours)
    avg = stacks.register(used, scan.zplanes, iterations, name)
    rounds = (stacks, scan, centres, neighbours, iterations, name)
    avg = _neighbour_rounds(*rounds, used, avg)
    tick()
    n_vetted = len(used)
    used, avg = _drop_outliers(
        stacks, used, avg, reason, residual, scan, iterations, min_beads, name, noise
    )
    if len(used) < n_vetted:
        # the neighbours' light was modelled with the outliers in the model: again without
        avg = _neighbour_rounds(*rounds, used, avg)
    _enough_beads(used, nb, min_beads, scan, centres, half)
    max_dz = max(abs(stacks.shifts[i][2]) for i in used)
    sl, zplanes = _model_planes(scan.zplanes, max_dz, step)
    zwin = _z_window(stacks, used, sl, step) if z_smooth else 0
    clean = model_stack(avg[sl], zwin)
    bead_ncc = np.array([ncc_planes(stacks.aligned(i)[sl], clean) for i in used])
    # Lateral origin: the centroid of the z-averaged image (the lobes' midpoint for a DH), or
    # the emitter itself where the beads' positions are known.
    proj = clean.mean(axis=0)
    centre = _centroid(proj, half, half, half)
    origin: dict[str, Any] = {"lateral_origin": "centroid"}
    if known is not None:
        table = _bead_table(centres, used, reason, residual, stacks, centre, half)
        centre, origin = _centre_on_beads(table, used, known, listed, p, centre)
    cr, cc = centre
    origin["centroid_over_z_nm"] = _centroid_over_z(clean, centre, half, p)
    # The model ends where its light falls below its noise (dim beads), or at the ROI.
    model_half = half
    if roi_size is None and profile is not None and profile.reach is not None:
        model_half = int(np.clip(profile.reach, ROI_HALF[0], half))
        log.info(
            "model cropped to %d x %d px: beyond it, the beads' light lies below the model's "
            "pixel noise (the crop holds %.1f %% of a plane's measured light)",
            2 * model_half + 1,
            2 * model_half + 1,
            100 * profile.held(model_half)[0],
        )
    psf = _cropped(_spline_model(clean, stacks, used, sl, zwin, zplanes, centre, name), model_half)
    tick()

    def rebuild(rois: list[NDArray[np.float64]]) -> SplinePSF:
        """The model made again, as ``psf`` was, from the used beads' ROIs ``rois``."""
        again = copy.copy(stacks)
        again.rois = {**stacks.rois, **dict(zip(used, rois, strict=True))}
        smooth = model_stack(again.average(used)[sl], zwin)
        model = _spline_model(smooth, again, used, sl, zwin, zplanes, centre, name)
        return _cropped(model, model_half)

    evidence = _BeadEvidence.of(stacks, used, scan, noise)
    error = _model_error(psf, evidence, scan, rebuild)
    psf.model_error = error.overall  # the solvers' allowance (sparseloc.solvers.variance)
    params = {
        "pixel_size_nm": p,
        "z_step_nm": step,
        "roi_size_px": 2 * model_half + 1,
        "bead_roi_size_px": roi,
        "model_shift_px": [cr - psf.pixel_centre[0], cc - psf.pixel_centre[1]],
        "offset_adu": float(scan.offset),
        "photons_per_adu": float(scan.gain),
        "threshold": float(threshold),
        "detect_sigma_px": float(detect_sigma),
        "iterations": int(iterations),
        "z_smooth_planes": int(zwin),
        "n_beads_found": nb,
        "defective_pixels": scan.defects,
        "background": float(np.median(scan.background)) if scan.background is not None else 0.0,
        "background_trend": scan.trend,
        "clipped_adu": None if scan.clipped is None else scan.clipped[0],
        "clipped_values": 0 if scan.clipped is None else scan.clipped[1],
        "bead_height_spread_nm": float(max_dz),
        "scan_z_range_nm": [float(scan.zplanes[0]), float(scan.zplanes[-1])],
        "n_beads_used": len(used),
        "roi_energy_fraction": _held(profile, model_half),
        "n_beads_with_neighbours": sum(1 for i in used if neighbours.get(i)),
        "model_error": error.overall,
        "model_error_z": [float(v) for v in error.per_plane],
        "model_self_influence": float(error.influence),
        "bead_warning": ONE_BEAD_WARNING if len(used) == 1 else "",
        "mirror_warning": mirror_warning(psf, p),
        "cluster_warning": _cluster_warning(stacks, used, centres),
        "phase_warning": _phase_warning(stacks, used, psf),
        **origin,
    }
    return Calibration(
        psf=psf,
        average=clean,
        z=zplanes,
        pixel_size=p,
        beads=_bead_table(centres, used, reason, residual, stacks, (cr, cc), half),
        projection=scan.projection,
        params=params,
        bead_ncc=bead_ncc,
        evidence=evidence,
    )


def _phase_warning(stacks: _BeadStacks, used: list[int], psf: SplinePSF) -> str:
    """A sentence where the model is on a grid finer than the pixels and the used beads all
    sit at one sub-pixel phase (:func:`~sparseloc.calibrate_oversample.phases_spread`): no
    bead samples the grid's nodes between phases, which hold an interpolation (still closer
    to the PSF than the pixel model's, docs/benchmarks/calibration_pixel_phase.txt), and the
    model error measured on the beads says nothing of them; "" otherwise."""
    offsets = np.array([stacks.shifts[i][:2] / stacks.p for i in used])
    o = psf.oversample
    if o == 1 or phases_spread(offsets, o):
        return ""
    axes = [a for a, k in (("x", 1), ("y", 0)) if not phases_spread(offsets[:, [k, k]], o)]
    return (
        f"the {len(used)} beads used sit at nearly one sub-pixel position along "
        f"{' and '.join(axes)} (within {0.5 / o:.2g} px of one another, modulo whole pixels): "
        "the model between pixel phases is interpolated, not measured, and the model error "
        "says nothing of it; beads at scattered positions measure it (emitters fit it worse "
        "than the error suggests: localize's model check tells)"
    )


def _cluster_warning(stacks: _BeadStacks, used: list[int], centres: NDArray[np.float64]) -> str:
    """A sentence naming the used beads whose ROI, cleaned of the neighbours found, holds one
    image repeated at a fixed offset in every plane (:func:`repeated_light`): beads closer
    than the detection can tell apart, found as one; "" where none does."""
    p = stacks.p
    found = []
    for i in used:
        several, lag = _holds_several(stacks.rois[i])
        if several:
            r, c = centres[i]
            x, y = (c + 0.5) * p, (r + 0.5) * p
            found.append(f"at x {x:.0f}, y {y:.0f} nm, repeated {lag * p:.0f} nm away")
    if not found:
        return ""
    which = (
        f"the bead used holds one image ({found[0]})"
        if len(used) == 1
        else f"{len(found)} of the {len(used)} beads used hold one image ({'; '.join(found)})"
    )
    whole = "the model is that cluster's image" if len(found) == len(used) else "the model holds it"
    return (
        f"{which} in every plane: several beads closer than the detection can part, found as "
        f"one, and {whole}; check PSF.png, and image a sparser bead sample"
    )


@dataclass(frozen=True)
class _BeadEvidence:
    """What a model's error is measured on: the used beads' ROI stacks (photons less the
    frame's background), the voxels of each that are its own light (``masks``), the planes'
    z and background, and the camera's noise ``a * mu + b`` (:func:`photon_noise`)."""

    rois: list[NDArray[np.float64]]
    masks: list[NDArray[np.bool_]]
    zplanes: NDArray[np.float64]
    background: NDArray[np.float64]
    noise: tuple[float, float]

    @classmethod
    def of(cls, stacks: _BeadStacks, used: list[int], scan: BeadScan, noise) -> _BeadEvidence:
        bg = scan.background if scan.background is not None else np.zeros(scan.zplanes.size)
        rois = [stacks.rois[i] for i in used]
        # the voxels the average left out of a bead (another's light) are no error of the model
        return cls(rois, stacks.kept_in_rois(used), scan.zplanes, bg, tuple(noise))

    def shifts(self, model: PSFModel) -> list[NDArray[np.float64]]:
        """Each bead's x, y, z (nm) against ``model`` (:func:`_fit_shift`)."""
        return [_fit_shift(model, roi, self.zplanes)[0] for roi in self.rois]

    def model_error(self, model: PSFModel, influence: float = 0.0, shifts=None):
        """``model``'s error on these beads
        (:func:`~sparseloc.calibrate_error.bead_model_error`), with the beads' ``shifts``
        against it where already fitted."""
        shifts = self.shifts(model) if shifts is None else shifts
        args = (self.zplanes, self.background, self.masks, self.noise, influence)
        return bead_model_error(model, self.rois, shifts, *args)


def _model_error(
    psf: SplinePSF,
    evidence: _BeadEvidence,
    scan: BeadScan,
    rebuild: Callable[[list[NDArray[np.float64]]], SplinePSF] | None = None,
):
    """The finished model's error on its beads (:mod:`sparseloc.calibrate_error`) beyond the
    camera's noise, overall and as the model's ``error_table``; ``ValueError`` when it is
    too large to trust. ``rebuild(rois)`` makes the model again from the used beads' ROIs:
    with two beads or more, how much of each bead's noise the model follows is measured with
    it (:func:`~sparseloc.calibrate_error.self_influence`)."""
    ev = evidence
    shifts = ev.shifts(psf)
    h = 0.0
    if rebuild is not None and len(ev.rois) > 1:
        args = (ev.zplanes, ev.background, ev.masks, ev.noise)
        h = self_influence(psf, rebuild, ev.rois, shifts, *args)
    error = ev.model_error(psf, h, shifts)
    psf.error_table = error.table
    log.info(
        "model error: %.1f %% of the signal per pixel (rms over planes); the model follows "
        "%.2f of a bead's own noise",
        100 * error.overall,
        error.influence,
    )
    if not error.overall <= MAX_MODEL_ERROR:
        hint = _not_a_scan(scan, ev.rois) or (
            "check the z step or z file, the camera offset, and that the beads are single and "
            "not drifting"
        )
        raise ValueError(
            f"the beads depart from their average by {100 * error.overall:.0f} % of the signal "
            f"(more than {100 * MAX_MODEL_ERROR:.0f} %), too much to trust the model: {hint}"
        )
    return error


#: Bead detection smooths the stack's z-average with a Gaussian of this width (nm), and at
#: least :data:`DETECTION_SIGMA_PX` pixels, and merges maxima within three times it: the
#: scale of a PSF (about 1.3 times a high-NA objective's lambda / 2 NA), at which a double
#: helix's ring of lobe positions is one hill whatever the pixel size.
DETECTION_SIGMA_NM = 300.0
#: The fewest pixels of that smoothing (the scale on pixels of 100 nm and larger).
DETECTION_SIGMA_PX = 3.0


def detection_sigma(pixel_size: float) -> float:
    """The bead detection's smoothing (px) on pixels of ``pixel_size`` nm:
    :data:`DETECTION_SIGMA_NM` in pixels, at least :data:`DETECTION_SIGMA_PX`."""
    return max(DETECTION_SIGMA_PX, DETECTION_SIGMA_NM / float(pixel_size))


def _saturated_pixels(scan: BeadScan) -> NDArray[np.bool_] | None:
    """The pixels (H, W) saturated in some frame of the scan; None where the camera's
    saturation is not known."""
    if scan.saturation is None:
        return None
    return np.asarray(scan.sat_frames.max(axis=0) >= scan.saturation)


def _detect(
    projection: NDArray[np.float64],
    detect_sigma: float,
    threshold: float,
    roi_size: int | None,
    saturated: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """Bead centres (row, col; px) on the z-averaged frame, the threshold a fraction of the
    brightest bead that is not ``saturated``'s; ``ValueError`` when none."""
    merge = _merge_radius(detect_sigma, roi_size)
    centres = find_beads(
        projection, sigma=detect_sigma, threshold=threshold, merge_radius=merge,
        saturated=saturated,
    )  # fmt: skip
    if centres.shape[0] == 0:
        raise ValueError(
            "no beads found in the stack; check the offset, use a lower --threshold, or "
            "check that the file is a bead z-scan"
        )
    return centres


def _merge_radius(detect_sigma: float, roi_size: int | None) -> float:
    """How close (px) two maxima of the smoothed projection are one bead's."""
    return max(3.0 * detect_sigma, (roi_size or 0) / 2.0)


#: Smallest and largest half side (px) of the automatic ROI and of a model cut to its light.
ROI_HALF = (5, 40)


def _roi_size(
    data: NDArray[np.float64],
    centres: NDArray[np.float64],
    roi_size: int | None,
    variance: NDArray[np.float64] | float = 0.0,
) -> tuple[int, int, LightProfile | None]:
    """ROI side and half side (px), ``roi_size`` made odd or sized to hold
    :data:`~sparseloc.calibrate_crowd.ROI_ENERGY` of the light of the brightest beads, and
    the light profile it came from (None where no bead leaves room to measure it).
    ``variance``: each plane's pixel variance (photons^2), which bounds how far the profile
    is measured."""
    profile = _light_profile(data, centres, variance)
    if roi_size is None:
        half = _fitting_half(profile, centres, data.shape[1:]) if profile is not None else 8
        roi = 2 * half + 1
        if profile is not None:
            mean, least = profile.held(half)
            log.info(
                "ROI %d x %d px holds %.1f %% of a plane's measured light (at least %.1f %%)",
                roi,
                roi,
                100 * mean,
                100 * least,
            )
    else:
        roi = int(roi_size)
        if roi < 7:
            raise ValueError(f"--roi-size must be at least 7 px, got {roi_size}")
        roi += 1 - roi % 2
        half = roi // 2
    return roi, half, profile


def _fitting_half(
    profile: LightProfile, centres: NDArray[np.float64], shape: tuple[int, int]
) -> int:
    """The automatic ROI's half side (px): the radius holding
    :data:`~sparseloc.calibrate_crowd.ROI_ENERGY` of a plane's light, or, where beads lie
    nearer the frame's edge than that, the largest radius down to the one holding
    :data:`~sparseloc.calibrate_crowd.ROI_ENERGY_LEAST` that fits the most beads' ROIs
    inside the frame."""
    full = int(np.clip(profile.half, *ROI_HALF))
    least = int(np.clip(profile.radius(ROI_ENERGY_LEAST), ROI_HALF[0], full))
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    # beads that overlap another (rejected whatever the ROI, see _vet_beads) do not count
    gaps = np.hypot(*(centres[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(gaps, np.inf)
    alone = gaps.min(axis=1, initial=np.inf) >= 2.0 * max(profile.core, 1.0)
    pixels = np.round(centres[alone]).astype(int)
    fits = {h: sum(_roi_inside(r, c, h, shape) for r, c in pixels) for h in range(least, full + 1)}
    most = max(fits.values())
    half = max(h for h, n in fits.items() if n == most)
    if half < full:
        log.info(
            "ROI %d x %d px instead of %d x %d px: %d bead(s) more fit inside the frame",
            2 * half + 1,
            2 * half + 1,
            2 * full + 1,
            2 * full + 1,
            most - fits[full],
        )
    return half


def _light_profile(
    data: NDArray[np.float64], centres: NDArray[np.float64], variance: NDArray | float = 0.0
) -> LightProfile | None:
    """The light profile of the brightest of the five brightest beads that leaves the most
    room around it (up to 40 px; :func:`~sparseloc.calibrate_crowd.light_profile`, its
    neighbours and the noise ``variance`` bound it too), or None."""
    h, w = data.shape[1:]
    max_r = int(min(ROI_HALF[1], max(6, min(h, w) // 2 - 1)))
    best: tuple[int, int] | None = None
    for i, (r, c) in enumerate(centres[:5]):
        ri, ci = int(np.round(r)), int(np.round(c))
        rad = min(max_r, ri, ci, h - 1 - ri, w - 1 - ci)
        if rad >= 6 and (best is None or rad > best[0]):
            best = (rad, i)
    if best is None:
        return None
    rad, i = best
    others = np.delete(centres, i, axis=0)
    return light_profile(data, tuple(centres[i]), others, rad, variance)


#: Most rounds of removing the neighbours' modelled light and registering again; fewer once
#: two rounds running move no bead and not the model's origin by :data:`NEIGHBOUR_TOLERANCE`
#: (nm); the origin may still creep by a few nm in all (crowded_bead_origin.txt). Each
#: round removes part of the light the model still holds of the beads' neighbours, so where
#: every bead sees a neighbour the model's light, and its centroid, settle over many rounds,
#: well after the beads' positions (docs/benchmarks/crowded_bead_origin.txt).
NEIGHBOUR_ROUNDS = 30
NEIGHBOUR_TOLERANCE = 1.0
#: Weight of a round's new estimate of the light to remove from a bead's ROI against the last
#: round's. Each round's model holds what the last round left of the neighbours' light, and
#: where neighbours are close and bright undamped rounds swing ever wider until the model
#: fails (docs/benchmarks/crowded_bead_origin.txt).
DAMPING = 0.5


def _held(profile: LightProfile | None, half: int) -> list[float] | None:
    """Mean and smallest fraction of a plane's light the ROI holds, where measured."""
    return None if profile is None else [round(v, 4) for v in profile.held(half)]


def _neighbour_pairs(
    centres: NDArray[np.float64], reason: list[str], roi: int
) -> dict[int, list[int]]:
    """For each usable bead, the other beads whose ROI overlaps its ROI (those at the frame's
    edge too: their light reaches inward): the ROI holds all but a percent of a bead's light,
    so farther beads do not reach it."""
    out: dict[int, list[int]] = {}
    ok = list(range(len(centres)))
    for i in range(len(centres)):
        if reason[i]:
            continue
        gap = np.abs(centres[ok] - centres[i]).max(axis=1)
        near = [j for j, g in zip(ok, gap, strict=True) if j != i and g < roi]
        if near:
            out[i] = near
    return out


#: The smallest half side (px) of the ROI a bead at the frame's edge is fitted in to model
#: its light on its neighbours; a bead nearer the edge than this is left out.
EDGE_FIT_HALF = 3


def _neighbour_rounds(
    stacks: _BeadStacks,
    scan: BeadScan,
    centres: NDArray[np.float64],
    neighbours: dict[int, list[int]],
    iterations: int,
    name: str,
    used: list[int],
    avg: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Rounds of :func:`_without_neighbours` until, two rounds running, no bead and not the
    average's light centroid moves by :data:`NEIGHBOUR_TOLERANCE` (the damped rounds can
    move little once and more again; at most :data:`NEIGHBOUR_ROUNDS`); the registered
    average."""
    before, still = None, 0
    for _ in range(NEIGHBOUR_ROUNDS if neighbours else 0):
        avg = _without_neighbours(stacks, scan, centres, used, neighbours, avg, iterations, name)
        now = _round_state(stacks, centres, used, avg)
        moved = before is None or np.abs(now - before).max() >= NEIGHBOUR_TOLERANCE
        still = 0 if moved else still + 1
        if still == 2:
            break
        before = now
    return avg


def _round_state(
    stacks: _BeadStacks, centres: NDArray[np.float64], used: list[int], avg: NDArray[np.float64]
) -> NDArray[np.float64]:
    """What a round of neighbour removal moves (nm): the beads' lateral positions about their
    mean, and the light centroid of the average's z projection (the model's origin) in the
    frame. The average's frame may drift with all the beads' shifts at once, which moves
    nothing; the beads' z shifts wander by a few nm from round to round on real beads
    (registration noise) and move no origin."""
    h = stacks.half
    row, col = _centroid(clean_average(avg).mean(axis=0), h, h, h)
    pos = stacks.positions(used, centres)[:, :2]
    mean = pos.mean(axis=0)
    origin = [col * stacks.p + mean[0], row * stacks.p + mean[1]]
    return np.concatenate([(pos - mean).ravel(), origin])


def _without_neighbours(
    stacks: _BeadStacks,
    scan: BeadScan,
    centres: NDArray[np.float64],
    used: list[int],
    neighbours: dict[int, list[int]],
    avg: NDArray[np.float64],
    iterations: int,
    name: str,
) -> NDArray[np.float64]:
    """Clean each usable bead's ROI of its neighbours' light, modelled with the current
    average at their fitted positions and brightness, and of the frame's residual background
    (what every bead's modelled light leaves of each plane, :func:`_residual_background`),
    and register the beads again; the registered average. The light removed is the mean of
    this round's estimate and the last round's (:data:`DAMPING`) where the ROI has not moved.

    The neighbours' model is the average as it is, each plane scaled to one photon: the
    border's median, which a model subtracts as background (:func:`clean_average`), is light
    of a wide PSF's halo, and a neighbour's halo is most of what it shines into the ROI."""
    p, half = stacks.p, stacks.half
    model = _halo_model(avg, p, scan.zplanes, name)
    placed = _placed_beads(stacks, scan, centres, model)
    residual = _residual_background(scan, model, list(placed.values()), half)
    h, w = scan.projection.shape
    for i in used:
        _recentre(stacks, centres, i, (h, w))
        ri, ci = (int(v) for v in np.round(centres[i]))
        light = neighbour_light(
            model,
            (ri - half, ci - half, 2 * half + 1),
            [placed[j] for j in neighbours.get(i, []) if j in placed],
            scan.zplanes,
        )
        removed = light + residual[:, None, None]
        last = stacks.removed.get(i)
        if last is not None and last[0] == (ri, ci):
            removed = DAMPING * removed + (1.0 - DAMPING) * last[1]
        stacks.removed[i] = ((ri, ci), removed)
        stacks.rois[i] = _roi(scan.data, ri, ci, half) - removed
    # the shifts are already close: one round against the current average refines them
    return stacks.register(used, scan.zplanes, 1, name, reference=avg)


def _halo_model(
    avg: NDArray[np.float64], p: float, zplanes: NDArray[np.float64], name: str
) -> SplinePSF:
    """The average ``avg`` (Nz, R, R) as a model of a bead's light, each plane scaled to one
    photon, neither clipped nor cut by a border background (:func:`_without_neighbours`)."""
    light = np.nan_to_num(avg)
    total = light.sum(axis=(1, 2), keepdims=True)
    light = np.where(total > 0, light / np.where(total > 0, total, 1.0), 0.0)
    return SplinePSF(light, p, zplanes, normalise=False, name=name)


def _placed_beads(
    stacks: _BeadStacks, scan: BeadScan, centres: NDArray[np.float64], model: SplinePSF
) -> dict[int, tuple[float, float, float, NDArray[np.float64]]]:
    """Every bead's position (x, y nm in the frame), z shift (nm) and photons per plane under
    ``model``: a used bead's from its registration, another's (rejected, or at the frame's
    edge, fitted in the largest ROI around it inside the frame) from a fit; a bead nearer the
    edge than :data:`EDGE_FIT_HALF` is left out."""
    p, half = stacks.p, stacks.half
    h, w = scan.projection.shape
    placed: dict[int, tuple[float, float, float, NDArray[np.float64]]] = {}
    for j in range(len(centres)):
        ri, ci = (int(v) for v in np.round(centres[j]))
        if j in stacks.shifts:  # a used bead (an outlier's shift is dropped)
            roi, shift = stacks.rois[j], stacks.shifts[j]
        else:  # a bead that is not used still shines on its neighbours
            inner = min(half, ri, ci, h - 1 - ri, w - 1 - ci)
            if inner < EDGE_FIT_HALF:
                continue
            roi = _roi(scan.data, ri, ci, inner)
            shift = _fit_shift(model, roi, scan.zplanes)[0]
        photons = plane_photons(model, roi, shift, scan.zplanes)
        placed[j] = ((ci + 0.5) * p + shift[0], (ri + 0.5) * p + shift[1], shift[2], photons)
    return placed


def _residual_background(
    scan: BeadScan,
    model: SplinePSF,
    placed: list[tuple[float, float, float, NDArray[np.float64]]],
    half: int,
) -> NDArray[np.float64]:
    """Each plane's background left in the scan (photons/pixel, (Nz,)): the median of the
    frame less every placed bead's modelled light. The scan's own background is each frame's
    median, which in a crowded field holds the beads' halos."""
    h, w = scan.projection.shape
    p, side = model.pixel_size, 2 * half + 1
    windows = []  # each bead's light in the ROI around its pixel: (first row, first col, light)
    for bead in placed:
        r0, c0 = int(bead[1] // p) - half, int(bead[0] // p) - half
        if -side <= r0 <= h and -side <= c0 <= w:  # else no pixel of it lies in the frame
            windows.append((r0, c0, neighbour_light(model, (r0, c0, side), [bead], scan.zplanes)))
    out = np.zeros(scan.zplanes.size)
    for k in range(out.size):  # a frame of light a plane at a time, not a second scan
        light = np.zeros((h + 2 * side, w + 2 * side))
        for r0, c0, img in windows:
            light[r0 + side : r0 + 2 * side, c0 + side : c0 + 2 * side] += img[k]
        left = scan.data[k] - light[side : side + h, side : side + w]
        out[k] = frame_background(left[None])[0]  # the scan's own rule for a frame's background
    return out


def _recentre(
    stacks: _BeadStacks, centres: NDArray[np.float64], i: int, shape: tuple[int, int]
) -> None:
    """Move bead ``i``'s ROI to the pixel nearest its fitted position (a neighbour's light
    pulls the detected centroid), keeping its position: its centre and shift change by the
    same whole pixels. The ROI must stay inside the frame."""
    p, half = stacks.p, stacks.half
    ri, ci = (int(v) for v in np.round(centres[i]))
    dr = int(np.round(stacks.shifts[i][1] / p))
    dc = int(np.round(stacks.shifts[i][0] / p))
    r, c = ri + dr, ci + dc
    if (dr or dc) and half <= r < shape[0] - half and half <= c < shape[1] - half:
        centres[i] = (r, c)
        moved = np.array([dc * p, dr * p, 0.0])
        stacks.shifts[i] = stacks.shifts[i] - moved
        # a registration started afresh (after outliers are dropped) starts from this ROI
        stacks.init_shift[i] = stacks.init_shift[i] - moved


def _vet_beads(
    centres: NDArray[np.float64], half: int, min_distance: float, scan: BeadScan
) -> tuple[list[str], list[int]]:
    """The rejection reason of each bead ("" when usable: not at the edge, not closer than
    ``min_distance`` px to another bead, not saturated) and the usable ones; ``ValueError``
    when none is."""
    nb = centres.shape[0]
    reason = [""] * nb
    for i, (r, c) in enumerate(centres):
        ri, ci = int(np.round(r)), int(np.round(c))
        if not _roi_inside(ri, ci, half, scan.projection.shape):
            reason[i] = "edge"
            continue
        d = np.hypot(*(centres - centres[i]).T)
        d[i] = np.inf
        if np.any(d < min_distance):
            reason[i] = "too close to another bead"
            continue
        if scan.saturation is not None:
            sub = scan.sat_frames[:, ri - half : ri + half + 1, ci - half : ci + half + 1]
            if np.any(sub >= scan.saturation):
                reason[i] = "saturated"
    used = [i for i in range(nb) if not reason[i]]
    if not used:
        counts = {r: reason.count(r) for r in set(reason)}
        detail = ", ".join(f"{v} {k}" for k, v in counts.items())
        sparser = "image a sparser bead sample or pass a smaller --roi-size"
        edge = "image the beads farther from the frame's edge"
        if half > ROI_HALF[0]:
            edge += f" or pass a --roi-size below {2 * half + 1} px"
        remedies = {
            "saturated": "lower the laser power, the exposure or an EMCCD's EM gain",
            "edge": edge,
            "too close to another bead": sparser,
        }
        hint = "; ".join(dict.fromkeys(v for k, v in remedies.items() if k in counts))
        hint = _not_a_scan(scan, _whole_rois(scan, centres, half)) or hint
        raise ValueError(f"found {nb} bead(s) but none is usable ({detail}); {hint}")
    return reason, used


def _enough_beads(
    used: list[int],
    nb: int,
    min_beads: int,
    scan: BeadScan,
    centres: NDArray[np.float64],
    half: int,
) -> None:
    """``ValueError`` when fewer than ``min_beads`` of the ``nb`` beads found are usable, or
    when one is and the spots change from frame to frame as a single-molecule movie's do
    (with one bead nothing else cross-checks the model)."""
    few = len(used) < min_beads
    if few or len(used) == 1:
        hint = _not_a_scan(scan, _whole_rois(scan, centres, half))
        if few or hint:
            hint = hint or (
                f"a calibration needs at least {min_beads} to average and cross-check: image "
                "more beads in the field"
            )
            raise ValueError(f"only {len(used)} usable bead(s) (of {nb} found); {hint}")


#: What a calibration from one bead says: nothing measured its model against another bead.
ONE_BEAD_WARNING = (
    "calibrated from one bead: the model is that bead, so its error against other beads "
    "(a PSF that changes over the field, a bad bead) is not measured and the count selection "
    "allows for none; image more beads for a cross-checked model"
)


#: Agreement of consecutive frames (their correlation over the one the noise allows) below
#: which a spot is not a fixed bead: a z-scan's beads agree near 1, a single-molecule movie's
#: spots far less (docs/benchmarks/scan_agreement.txt).
SCAN_AGREEMENT: float = 0.9


def _not_a_scan(scan: BeadScan, rois: list[NDArray[np.float64]]) -> str:
    """A clause saying the file looks like a single-molecule movie, where the spots' ROIs
    ``rois`` (each (Nz, n, n), photons less background) change from frame to frame more than
    their noise explains; "" otherwise."""
    agreement = _frame_agreement(rois, scan.background)
    if not np.isfinite(agreement) or agreement >= SCAN_AGREEMENT:
        return ""
    return (
        f"the spots found change from frame to frame (consecutive frames agree at "
        f"{agreement:.2f} of what their noise allows; a bead z-scan's at about 1): is the file "
        "a single-molecule movie? calibrate takes a z-stack of fixed beads"
    )


def _whole_rois(
    scan: BeadScan, centres: NDArray[np.float64], half: int
) -> list[NDArray[np.float64]]:
    """The ROI stacks of the beads whose ROI lies inside the frame."""
    out = []
    for r, c in centres:
        ri, ci = int(np.round(r)), int(np.round(c))
        if _roi_inside(ri, ci, half, scan.projection.shape):
            out.append(_roi(scan.data, ri, ci, half))
    return out


def _roi_inside(ri: int, ci: int, half: int, shape: tuple[int, int]) -> bool:
    """Whether the ROI of half side ``half`` around pixel (ri, ci) lies inside the frame."""
    h, w = shape
    return ri - half >= 0 and ci - half >= 0 and ri + half < h and ci + half < w


def _frame_agreement(
    rois: list[NDArray[np.float64]], background: NDArray[np.float64] | None
) -> float:
    """Median over the ROIs and consecutive frames of their correlation divided by the
    correlation that Poisson noise leaves to an unchanged image; NaN without a ROI."""
    values = []
    for sub in rois:
        a = sub.reshape(sub.shape[0], -1)
        bg = np.zeros(a.shape[0]) if background is None else background
        noise = np.clip(a + bg[:, None], 0.0, None).mean(axis=1)
        a = a - a.mean(axis=1, keepdims=True)
        power = (a**2).mean(axis=1)
        ncc = (a[1:] * a[:-1]).mean(axis=1) / np.sqrt(np.maximum(power[1:] * power[:-1], 1e-300))
        held = np.clip(1.0 - noise / np.maximum(power, 1e-300), 1e-9, None)
        values.append(ncc / np.sqrt(held[1:] * held[:-1]))
    return float(np.median(np.concatenate(values))) if values else float("nan")


class _BeadStacks:
    """The ROI stacks of the usable beads and their shifts (x, y, z; nm) from the ROIs'
    centre pixels to the common average."""

    def __init__(
        self,
        data: NDArray[np.float64],
        centres: NDArray[np.float64],
        used: list[int],
        half: int,
        p: float,
        step: float,
    ) -> None:
        self.p, self.step, self.half = p, step, half
        self.rois: dict[int, NDArray[np.float64]] = {}
        self.shifts: dict[int, NDArray[np.float64]] = {}
        for i in used:
            r, c = centres[i]
            ri, ci = int(np.round(r)), int(np.round(c))
            self.rois[i] = _roi(data, ri, ci, half).copy()
            self.shifts[i] = np.array([(c - ci) * p, (r - ri) * p, 0.0])
        self.photons = {i: float(self.rois[i].sum() / self.rois[i].shape[0]) for i in used}
        self.init_shift = {i: v.copy() for i, v in self.shifts.items()}
        self.tick: Callable[[], None] = lambda: None  # called after each bead's registration
        # beads whose ROI holds another bead's light: their voxels may disagree with the PSF
        self.crowded: set[int] = set()
        self.noise: CameraNoise | None = None  # the robust average's noise floor
        # the light last removed from each bead's ROI: its first row and column, the light
        self.removed: dict[int, tuple[tuple[int, int], NDArray[np.float64]]] = {}

    def positions(self, ids: list[int], centres: NDArray[np.float64]) -> NDArray[np.float64]:
        """Beads ``ids``' x, y, z (nm; frame x, y from the ROIs' centre pixels ``centres``
        plus their shifts; z their shift)."""
        return np.array(
            [
                (np.round(centres[i][1]) * self.p, np.round(centres[i][0]) * self.p, 0.0)
                + self.shifts[i]
                for i in ids
            ]
        )

    def aligned(self, i: int) -> NDArray[np.float64]:
        """Bead ``i``'s stack resampled onto the average's frame."""
        return _shift_stack(self.rois[i], self.shifts[i], self.p, self.step)

    def kept_in_rois(self, ids: list[int]) -> list[NDArray[np.bool_]]:
        """Each bead's voxels that agree with the other beads' (:func:`robust_keep` of the
        registered stacks), on its own ROI's pixels and planes."""
        stack = np.stack([self.aligned(i) for i in ids])
        keep = robust_keep(stack, self._suspects(ids), self.noise)
        out = []
        for i, k in zip(ids, keep, strict=True):
            s = self.shifts[i]
            back = _shift_stack(k.astype(np.float64), -np.asarray(s), self.p, self.step, False)
            out.append(back > 0.5)
        return out

    def average(self, ids: list[int]) -> NDArray[np.float64]:
        """The registered beads' average, robust where there are enough of them
        (:func:`robust_average`)."""
        stack = np.stack([self.aligned(i) for i in ids])
        return robust_average(stack, self._suspects(ids), self.noise)

    def _suspects(self, ids: list[int]) -> NDArray[np.bool_]:
        """Which of the beads ``ids`` have neighbours in their ROI."""
        return np.array([i in self.crowded for i in ids], dtype=bool)

    def register(
        self,
        ids: list[int],
        zplanes: NDArray[np.float64],
        iterations: int,
        name: str,
        reference: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """Fit every bead's shift to the spline of the current average, ``iterations`` times,
        and return the registered average; start from ``reference`` (an average registered
        before) when given."""
        from scipy.ndimage import gaussian_filter

        avg = reference
        if avg is None:
            # First reference: one bead alone, of median brightness (the brightest may be two
            # beads seen as one). An average of unregistered beads is blurred in z, and
            # registering to a blurred reference shrinks the shifts (slow convergence).
            ranked = sorted(ids, key=lambda i: self.photons[i])
            first = ranked[len(ranked) // 2]
            self.shifts[first] = self.init_shift[first].copy()
            avg = self.aligned(first)
        for _ in range(max(1, iterations)):
            # A noisy reference has noisy derivatives, and a least-squares fit against it
            # shrinks the shifts (regression dilution); a light symmetric smoothing removes
            # most of that noise without moving the reference's centre.
            smooth = gaussian_filter(avg, (1.0, 0.5, 0.5), mode="nearest")
            ref = SplinePSF(clean_average(smooth), self.p, zplanes, normalise=False, name=name)
            for i in ids:
                self.shifts[i], _ = _fit_shift(ref, self.rois[i], zplanes)
                self.tick()
            # Keep the scan's z frame: the beads' mean z is z = 0.
            mean_z = np.mean([self.shifts[i][2] for i in ids])
            for i in ids:
                self.shifts[i] = self.shifts[i] - np.array([0.0, 0.0, mean_z])
            avg = self.average(ids)
        return avg


#: Beads needed for the robust average (:func:`robust_average`); fewer are averaged plainly.
ROBUST_BEADS = 5
#: A bead's voxel farther than this many robust standard deviations from the beads' median
#: is left out of the average.
ROBUST_CLIP = 3.0


def robust_keep(
    stacks: NDArray[np.float64], suspects: NDArray[np.bool_], noise: CameraNoise | None = None
) -> NDArray[np.bool_]:
    """Which voxels of registered bead stacks (B, Nz, R, R; photons less background) to
    average: light that a bead's ROI holds and the other beads' do not (a neighbour's, an
    undetected bead's) is not the PSF.

    A voxel of a bead of ``suspects`` (B,) (beads with a neighbour in their ROI) is left out
    where it lies more than :data:`ROBUST_CLIP` robust standard deviations from the beads'
    median, each stack scaled to the beads' mean total light; the other beads' voxels are all
    kept, and every voxel where fewer than :data:`ROBUST_BEADS` beads are averaged (the
    median of two or three says nothing about outliers). The robust standard deviation is
    the median absolute deviation over the beads, at least the camera's noise of that bead's
    voxel (``noise``: its light and the frame's background; photon counting without it):
    the deviation of a handful of beads is itself noisy, and an EMCCD's skewed noise makes
    it small beside the noise's tail, which a tighter clip would cut from the average and
    from the model error's residuals.
    """
    keep = np.ones(stacks.shape, dtype=bool)
    if stacks.shape[0] < ROBUST_BEADS or not np.any(suspects):
        return keep
    scale = _light_scale(stacks)
    scaled = stacks * scale
    med = np.median(scaled, axis=0)
    mad = 1.4826 * np.median(np.abs(scaled - med), axis=0)
    sd = np.maximum(mad, (noise or CameraNoise()).sd(med / scale) * scale)
    keep[suspects] = (np.abs(scaled - med) <= ROBUST_CLIP * sd)[suspects]
    return keep


@dataclass(frozen=True)
class CameraNoise:
    """The camera's noise in a bead stack: variance ``a * mu + b`` (photons^2) for ``mu``
    expected photons (:func:`photon_noise`), with each plane's frame ``background``
    (photons/pixel, (Nz,)) on top of the light of the stacks, which have it subtracted."""

    a: float = 1.0
    b: float = 0.0
    background: NDArray[np.float64] | None = None

    def sd(self, light: NDArray[np.float64]) -> NDArray[np.float64]:
        """Standard deviation (photons) of voxels of ``light`` (..., Nz, R, R; photons less
        background): at least that of one photon."""
        bg = 0.0 if self.background is None else self.background[:, None, None]
        return np.sqrt(self.a * np.maximum(light + bg, 1.0) + self.b)


def _light_scale(stacks: NDArray[np.float64]) -> NDArray[np.float64]:
    """Factors (B, 1, 1, 1) that scale each bead stack to the beads' mean total light."""
    total = np.maximum(stacks.sum(axis=tuple(range(1, stacks.ndim)), keepdims=True), 1e-12)
    return total.mean() / total


def robust_average(
    stacks: NDArray[np.float64], suspects: NDArray[np.bool_], noise: CameraNoise | None = None
) -> NDArray[np.float64]:
    """The mean of registered bead stacks (B, Nz, R, R) over the voxels :func:`robust_keep`
    keeps (:func:`~sparseloc.calibrate_zsmooth.kept_mean`); ``noise`` as in
    :func:`robust_keep`."""
    keep = robust_keep(stacks, suspects, noise)
    if keep.all():
        return stacks.mean(axis=0)
    return kept_mean(stacks, keep, 1.0 / _light_scale(stacks))


def _drop_outliers(
    stacks: _BeadStacks,
    used: list[int],
    avg: NDArray[np.float64],
    reason: list[str],
    residual: dict[int, float],
    scan: BeadScan,
    iterations: int,
    min_beads: int,
    name: str,
    noise: tuple[float, float] = (1.0, 0.0),
) -> tuple[list[int], NDArray[np.float64]]:
    """Drop clear outliers among the registered beads (dirt, aggregates, two beads seen as
    one) and register the rest again; returns the beads kept and their average.

    A bead's ``residual`` is its own model error against the beads' average
    (:func:`~sparseloc.calibrate_error.bead_errors`: beyond the camera's ``noise``, on the
    voxels the average keeps, so a neighbour's light does not count); an outlier departs
    from the model by more than :data:`OUTLIER_FLOOR` and by far more than the beads'
    median. Where more than :data:`OUTLIER_SHARE` of the beads would go, none does: the
    beads then differ as a population (a PSF that changes over the field), which the model
    error measures, not as a few bad ones."""
    # The rest are registered again from scratch, so that nothing fitted against a bad bead
    # remains.
    for _ in range(3):
        if len(used) < 3:
            break
        residual.update(_bead_errors(stacks, used, avg, scan, name, noise))
        res = np.array([residual[i] for i in used])
        med = np.median(res)
        mad = 1.4826 * np.median(np.abs(res - med))
        bar = max(med + 5 * mad, 1.5 * med, OUTLIER_FLOOR)
        bad = [i for i in used if residual[i] > bar]
        few = len(bad) <= OUTLIER_SHARE * len(used)  # else the field's PSF varies
        if not bad or not few or len(used) - len(bad) < max(min_beads, 1):
            break
        for i in bad:
            reason[i] = _outlier_reason(stacks.rois[i])
            stacks.shifts.pop(i, None)
        used = [i for i in used if i not in bad]
        avg = stacks.register(used, scan.zplanes, iterations, name)
    return used, avg


def _outlier_reason(roi: NDArray[np.float64]) -> str:
    """Why an outlier departs from the beads' model: its ROI (Nz, R, R) holds several beads
    found as one (:func:`_holds_several`), or something else (dirt, an aggregate)."""
    return "two beads found as one" if _holds_several(roi)[0] else "outlier"


def _holds_several(roi: NDArray[np.float64]) -> tuple[bool, float]:
    """Whether a bead's ROI (Nz, R, R) holds one image repeated at a fixed offset in every
    plane (:func:`repeated_light`: beads closer than the detection parts), and that offset
    (px)."""
    share, lag = repeated_light(roi)
    return share > REPEATED_LIGHT, lag


#: A bead whose own model error is below this fraction of its signal is no outlier, however
#: far the others' median lies below it: model errors of a tenth are the field's ordinary
#: spread (a PSF that changes over the field, a neighbour's residual light).
OUTLIER_FLOOR = 0.1
#: The largest share of the beads that the outlier test drops in one round.
OUTLIER_SHARE = 1.0 / 3.0


def _bead_errors(
    stacks: _BeadStacks,
    used: list[int],
    avg: NDArray[np.float64],
    scan: BeadScan,
    name: str,
    noise: tuple[float, float],
) -> dict[int, float]:
    """Each used bead's own model error against the current average (see
    :func:`_drop_outliers`)."""
    model = SplinePSF(clean_average(avg), stacks.p, scan.zplanes, name=name)
    ev = _BeadEvidence.of(stacks, used, scan, noise)
    shifts = [stacks.shifts[i] for i in used]
    errors = bead_errors(model, ev.rois, shifts, ev.zplanes, ev.background, ev.masks, ev.noise)
    return dict(zip(used, (float(e) for e in errors), strict=True))


def _cropped(psf: SplinePSF, half: int) -> SplinePSF:
    """``psf`` cut to ``half`` px on each side of its centre's pixel (each plane summing to one
    photon again); ``psf`` itself where it is no larger. An oversampled model keeps the
    samples up to half a pixel past ``half``, those an emitter's sub-pixel phases render."""
    o = psf.oversample
    if 2 * half + 1 >= min(psf.stack.shape[1:]) / o:
        return psf
    keep = half * o + o // 2
    rc = [int(np.round(c)) for c in psf.centre]
    lo = [max(c - keep, 0) for c in rc]
    hi = [min(c + keep + 1, n) for c, n in zip(rc, psf.stack.shape[1:], strict=True)]
    stack = psf.stack[:, lo[0] : hi[0], lo[1] : hi[1]]
    centre = (psf.centre[0] - lo[0], psf.centre[1] - lo[1])
    return SplinePSF(stack, psf.pixel_size, psf.z, centre=centre, name=psf.name, oversample=o)


def _spline_model(
    clean: NDArray[np.float64],
    stacks: _BeadStacks,
    used: list[int],
    sl: slice,
    zwin: int,
    zplanes: NDArray[np.float64],
    centre: tuple[float, float],
    name: str,
) -> SplinePSF:
    """The spline model: where the pixels undersample the beads' PSF and there are enough
    beads, the average ``clean`` refined on a grid finer than the pixels by the used beads
    (:mod:`sparseloc.calibrate_oversample`; a crowded bead's ROI holds it less its neighbours'
    modelled light) and smoothed along z as the average was; else the average itself."""
    p, step = stacks.p, stacks.step
    cr, cc = centre
    if not (worth_oversampling(len(used)) and undersampled([stacks.rois[i] for i in used])):
        return SplinePSF(clean, p, zplanes, centre=(cr, cc), name=name)
    beads = [
        (_shift_stack(stacks.rois[i], np.array([0.0, 0.0, stacks.shifts[i][2]]), p, step)[sl],
         stacks.shifts[i][1] / p, stacks.shifts[i][0] / p)
        for i in used
    ]  # fmt: skip
    o = OVERSAMPLE
    grid = oversampled_model(clean, beads, o)
    if zwin:
        grid = smooth_along_z(grid, zwin)
    # clipped after the smoothing, which averages the dark nodes' noise first
    grid = np.maximum(grid, 0.0)
    grid *= o * o / grid.sum(axis=(1, 2), keepdims=True)
    return SplinePSF(grid, p, zplanes, centre=(cr * o, cc * o), name=name, oversample=o)


def _model_planes(
    zplanes: NDArray[np.float64], max_dz: float, step: float
) -> tuple[slice, NDArray[np.float64]]:
    """The planes of the average the model keeps: those no bead's z shift pushed beyond its
    data (extrapolated along its end slopes, :func:`_z_extended`) by more than
    :data:`~sparseloc.calibrate_error.EXTRAPOLATE_STEPS` of a step (all where too few would
    be left), and their z."""
    trim = max(int(np.ceil(max_dz / step - EXTRAPOLATE_STEPS - 1e-6)), 0)
    if zplanes.size - 2 * trim < 4:
        trim = 0
    sl = slice(trim, zplanes.size - trim)
    return sl, zplanes[sl]


def _z_window(stacks: _BeadStacks, used: list[int], sl: slice, step: float) -> int:
    """The model's smoothing along z (planes): chosen by the beads where there are two or
    more (:func:`~sparseloc.calibrate_zsmooth.choose_window`), else
    :func:`~sparseloc.calibrate_zsmooth.fallback_window` (about 80 nm, none for steps of
    30 nm or more)."""
    fallback = fallback_window(step, sl.stop - sl.start)
    if len(used) < 2:
        return fallback
    aligned = np.stack([stacks.aligned(i) for i in used])
    noise = stacks.noise or CameraNoise()
    keep = robust_keep(aligned, stacks._suspects(used), noise)[:, sl]
    share = 1.0 / _light_scale(aligned)
    if noise.background is not None:
        noise = replace(noise, background=noise.background[sl])
    try:
        choice = choose_window(aligned[:, sl], keep, share, lambda fit: noise.sd(fit) ** 2)
    except ValueError:  # a group of beads left a plane without light: the beads cannot tell
        return fallback
    log.info(
        "smoothing along z: %d planes (%.0f nm), chosen by cross-validation over %d beads",
        choice.window,
        smoothing_nm(choice.window, step),
        len(used),
    )
    return choice.window


def _bead_table(
    centres: NDArray[np.float64],
    used: list[int],
    reason: list[str],
    residual: dict[int, float],
    stacks: _BeadStacks,
    centre: tuple[float, float],
    half: int,
) -> pd.DataFrame:
    """One row per bead found (:data:`BEAD_COLUMNS`). Positions of registered beads: the
    fitted shift from the ROI's centre pixel, in the model's frame (its ``centre``, row and
    col in px); of the others, the detected centre."""
    nb = centres.shape[0]
    p = stacks.p
    cr, cc = centre
    shifts = stacks.shifts
    bx = (np.round(centres[:, 1]) + 0.5) * p + (cc - half) * p
    by = (np.round(centres[:, 0]) + 0.5) * p + (cr - half) * p
    for i in used:
        bx[i] += shifts[i][0]
        by[i] += shifts[i][1]
    unreg = [i for i in range(nb) if i not in used]
    bx[unreg] = (centres[unreg, 1] + 0.5) * p
    by[unreg] = (centres[unreg, 0] + 0.5) * p
    return pd.DataFrame(
        {
            "x_nm": bx,
            "y_nm": by,
            "used": [i in used for i in range(nb)],
            "reason": reason,
            "photons": [stacks.photons.get(i, np.nan) for i in range(nb)],
            "shift_x_nm": [shifts[i][0] if i in shifts else np.nan for i in range(nb)],
            "shift_y_nm": [shifts[i][1] if i in shifts else np.nan for i in range(nb)],
            "shift_z_nm": [shifts[i][2] if i in shifts else np.nan for i in range(nb)],
            "residual": [residual[i] for i in range(nb)],
        },
        columns=BEAD_COLUMNS,
    )


def _centroid_over_z(
    stack: NDArray[np.float64], centre: tuple[float, float], half: int, p: float
) -> dict[str, list[float]]:
    """How far each plane's light centroid lies from the model's lateral origin (nm): the
    smallest and largest offset in x and in y over the planes. A localization's position is
    the origin's, so this is the bias a model centred elsewhere than the emitter carries."""
    cr, cc = centre
    offsets = np.array([_centroid(plane, cr, cc, half) for plane in stack])
    dy = (offsets[:, 0] - cr) * p
    dx = (offsets[:, 1] - cc) * p
    return {"x": [float(dx.min()), float(dx.max())], "y": [float(dy.min()), float(dy.max())]}


#: A known bead position farther than this (pixels) from every bead found matches none, unless
#: the beads found scatter more about their positions (:func:`_match_tolerance`).
BEAD_MATCH_PX = 2.0


def _centre_on_beads(
    table: pd.DataFrame,
    used: list[int],
    known: ArrayLike,
    listed: NDArray[np.intp],
    p: float,
    centre: tuple[float, float],
) -> tuple[tuple[float, float], dict[str, Any]]:
    """The model centre (row, col in px) that puts the registered beads at their ``known``
    positions (B, 2; x, y nm) on average, and what that moved (for the calibration's record).

    ``listed``: each known position's bead (:func:`_listed_beads`); the used beads among
    them fix the offset of the light's centroid from the emitter.
    """
    xy = np.asarray(known, dtype=np.float64).reshape(-1, 2)
    first = {int(i): k for k, i in reversed(list(enumerate(listed)))}  # a twin once
    pairs = [(k, i) for i, k in first.items() if i in used]
    if not pairs:
        raise ValueError("none of the bead file's positions is a bead the calibration used")
    model_xy = table[["x_nm", "y_nm"]].to_numpy()
    off = np.array([model_xy[i] - xy[k] for k, i in pairs])  # centroid minus emitter (nm)
    dx, dy = off.mean(axis=0)
    spread = off - off.mean(axis=0)
    cr, cc = centre
    record = {
        "lateral_origin": "beads",
        "n_beads_known": len(pairs),
        "centroid_offset_nm": [float(dx), float(dy)],
        "bead_position_rms_nm": float(np.sqrt(np.mean(np.sum(spread**2, axis=1)))),
    }
    log.info(
        "model origin on %d known bead position(s): the light's centroid lies at %+.1f, "
        "%+.1f nm (x, y) from the emitter (rms over beads %.1f nm)",
        len(pairs),
        dx,
        dy,
        record["bead_position_rms_nm"],
    )
    return (cr - dy / p, cc - dx / p), record


def _fit_pupil_in_frame(cal: Calibration, pupil_options: dict[str, Any] | None) -> Any:
    """The pupil phase fitted to the registered average (at the camera's pixels), with its
    ``frame_model`` in the spline's frame: an emitter at (x, y, z) renders its image where
    the spline puts it (lateral origin at the spline's centre, z = 0 at the scan's zero)."""
    from .psf.base import ShiftedPSF
    from .psf.retrieval import fit_pupil as _fit_pupil

    zplanes, p = cal.z, cal.pixel_size
    opts = dict(pupil_options or {})
    opts.setdefault("z_range", (float(zplanes[0]) - 500.0, float(zplanes[-1]) + 500.0))
    res = _fit_pupil(cal.average, zplanes, p, **opts)
    cr, cc = cal.emitter_pixel
    xc, yc = (cc + 0.5) * p, (cr + 0.5) * p
    res.frame_model = ShiftedPSF(
        res.psf, res.x0 - xc, res.y0 - yc, res.z0, z_range=(zplanes[0], zplanes[-1])
    )
    return res


def _pupil_model_error(cal: Calibration) -> None:
    """The fitted pupil's own error on the beads (its ``model_error`` and ``error_table``, as
    the spline's): a pupil of few terms misses what the beads show that they do not hold.
    Not measured (the spline's kept) where the beads were not kept or one bead was used."""
    fm = getattr(cal.pupil, "frame_model", None)
    if fm is None or cal.evidence is None or len(cal.evidence.rois) < 2:
        return
    fm.pixel_size = cal.pixel_size
    error = cal.evidence.model_error(fm)
    if error.table is not None:
        error.table.name = f"{cal.psf.name} pupil error"
    for holder in (cal.pupil, fm):  # the fit's result, and the model an API user may pass on
        holder.model_error, holder.error_table = error.overall, error.table
    cal.params["pupil_model_error"] = error.overall
    log.info("pupil model error: %.1f %% of the signal per pixel", 100 * error.overall)


def calibrate_file(
    path: str | Path,
    pixel_size: float,
    z_step: float | None = None,
    *,
    z_file: str | Path | None = None,
    **kwargs: Any,
) -> Calibration:
    """:func:`calibrate_beads` on a TIFF bead stack, with the file's pixel size checked.

    ``z_file`` is a CSV of per-frame z (see :func:`read_z_file`). Other keyword arguments go
    to :func:`calibrate_beads`.
    """
    from .config import pixel_sizes_differ
    from .io.movie import Movie

    with Movie.open(path) as movie:
        meta_px = movie.pixel_size
        if meta_px is not None and pixel_sizes_differ(pixel_size, meta_px):
            raise ValueError(
                f"--pixel-size {pixel_size:g} nm disagrees with the {meta_px:g} nm in "
                f"{Path(path).name}'s metadata; check the objective and camera"
            )
        stack = movie.frames()
    if stack.ndim == 2:
        stack = stack[None]
    if z_file is not None:
        z, valid = read_z_file(z_file)
        kwargs.update(z=z, valid=valid)
    kwargs.setdefault("name", Path(path).stem)
    cal = calibrate_beads(stack, pixel_size, z_step, **kwargs)
    cal.params["source"] = Path(path).name
    if z_file is not None:
        cal.params["z_file"] = Path(z_file).name
    return cal
