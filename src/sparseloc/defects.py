"""Defective camera pixels (hot or stuck): found from the data, replaced by their neighbours.

A hot pixel (dark current) or a stuck one holds a level of its own in every frame. Over the
frames its median (for a movie the background, as emitters blink; for a bead scan the
z-averaged beads) stands above its neighbours' by more than light through an objective can:
a diffraction-limited spot centred on a pixel still puts a share of its light into its
neighbours (:func:`sharpest_ratio`). A pixel whose median rises above its darkest neighbour's
by more than that ratio times its brightest neighbour's rise, and significantly
(:data:`SIGNIFICANCE` standard errors of a median of the frames' noise), is defective; in each
frame it takes the median of its usable neighbours (:func:`replace_defects`). Two defective
pixels side by side hide each other and stay.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage as ndi
from scipy.special import erf

__all__ = [
    "NA_MAX",
    "SIGNIFICANCE",
    "WAVELENGTH_MIN_NM",
    "defective_pixels",
    "replace_defects",
    "sharpest_ratio",
]

#: The sharpest image an objective forms: the shortest emission wavelength (nm) and the
#: largest numerical aperture of localization microscopy. Its Gaussian core has a sigma of
#: 0.21 wavelength / NA (55 nm).
WAVELENGTH_MIN_NM = 450.0
NA_MAX = 1.7

#: Standard errors by which a pixel's median must exceed what light could put there: at
#: 5, about one pixel in three million of a defect-free camera is taken for defective.
SIGNIFICANCE = 5.0

_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=bool)


def sharpest_ratio(pixel_size: float) -> float:
    """The most a pixel's light can rise above its darkest neighbour's, in units of its
    brightest neighbour's rise, for light through an objective: a spot of
    :data:`WAVELENGTH_MIN_NM` and :data:`NA_MAX` centred on the pixel, whose light per axis
    is ``c`` in the pixel and ``s`` in the next one: ``(c^2 - s^2) / (c s - s^2) = c / s + 1``
    (about 2.8 at 65 nm pixels, 4.5 at 100 nm, 12 at 160 nm, 120 at 267 nm).

    Parameters
    ----------
    pixel_size : float
        Pixel size in the sample (nm).
    """
    sigma = 0.21 * WAVELENGTH_MIN_NM / NA_MAX / float(pixel_size) * np.sqrt(2.0)
    centre = erf(0.5 / sigma)
    side = 0.5 * (erf(1.5 / sigma) - centre)
    return float(centre / max(side, 1e-12) + 1.0)


def defective_pixels(
    frames: ArrayLike,
    pixel_size: float,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
) -> NDArray[np.bool_]:
    """The pixels whose median over ``frames`` no light could give (see the module notes).

    Parameters
    ----------
    frames : array_like, shape (n, rows, cols)
        Frames in photons (offset removed), a movie's or a bead scan's.
    pixel_size : float
        Pixel size (nm).
    noise_factor : float
        The camera's variance per expected photon (2 for an EMCCD).
    read_variance : float or ndarray, shape (rows, cols)
        Read-noise variance (photons^2).

    Returns
    -------
    ndarray of bool, shape (rows, cols)
    """
    a = np.asarray(frames, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    n = a.shape[0]
    med = np.median(a, axis=0)
    # Light and background measured from the darkest neighbour up: a level taken higher (a
    # local median inside a bright image) would let a bright pixel of that image pass.
    floor = ndi.minimum_filter(med, footprint=_RING, mode="nearest")
    brightest = ndi.maximum_filter(med, footprint=_RING, mode="constant", cval=-np.inf)
    rise = med - floor
    neighbour = np.maximum(brightest - floor, 0.0)
    # The standard error of a median of n frames (sqrt(pi / 2) that of a mean): from the
    # camera's noise model, from the neighbours' own spread over the frames where it is
    # larger (a camera described wrongly), and from the medians' spread over the frame where
    # that is larger (emitters' light passing through the pixels).
    model = noise_factor * np.maximum(floor, 1.0) + np.asarray(read_variance, dtype=np.float64)
    spread = (1.4826 * ndi.median_filter(np.median(np.abs(a - med), axis=0), size=3)) ** 2
    error = np.sqrt(np.pi / 2.0 * np.maximum(model, spread) / n)
    local = med - ndi.median_filter(med, size=5, mode="nearest")
    error = np.maximum(error, 1.4826 * np.median(np.abs(local - np.median(local))))
    bar = sharpest_ratio(pixel_size) * neighbour + SIGNIFICANCE * error
    return rise > bar


def replace_defects(frames: ArrayLike, mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``frames`` (n, rows, cols) or one frame with each pixel of ``mask`` (rows, cols) set,
    frame by frame, to the median of its neighbours outside the mask (a copy)."""
    a = np.array(frames, dtype=np.float64)
    if not mask.any():
        return a
    one = a.ndim == 2
    if one:
        a = a[None]
    rows, cols = mask.shape
    for r, c in zip(*np.nonzero(mask), strict=True):
        rr, cc = np.mgrid[max(r - 1, 0) : min(r + 2, rows), max(c - 1, 0) : min(c + 2, cols)]
        good = ~mask[rr, cc]
        if good.any():
            a[:, r, c] = np.median(a[:, rr[good], cc[good]], axis=1)
    return a[0] if one else a
