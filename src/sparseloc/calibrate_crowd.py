"""Bead calibration in crowded fields: an ROI sized to the PSF's light, and neighbours' light.

Real bead slides are crowded, and an engineered PSF (double helix, tetrapod) is microns wide.

- **ROI**: the light profile around the brightest beads (ring means over z-smoothed planes,
  leaving out pixels nearer another bead, out to where the camera's noise would swamp what a
  ring's remaining pixels say) gives the fraction of a plane's light within each radius; the
  ROI's half side is the smallest radius that holds :data:`ROI_ENERGY` of it on average over
  the planes, and the PSF's core is the radius that holds half of it. The model is cut
  where the light a model of the beads would hold falls below its pixel noise (dim beads).
- **Neighbours**: beads closer than an ROI are used. All beads share one PSF, so each bead's
  ROI is cleaned of its neighbours' modelled light (the current model at the neighbours'
  fitted positions and per-plane brightness), and the beads are registered again; only beads
  whose cores overlap (closer than two core radii) are rejected.
- **Clusters**: beads closer than the detection's scale are found as one bead. One bead's
  image changes with z (lobes turn, spread or stretch), so each plane's autocorrelation has
  its side peaks at lags that move; a cluster's image is the same PSF repeated at offsets
  fixed for every plane, so the autocorrelation averaged over the planes keeps a side peak
  there, of height ``b1 b2 / (b1^2 + b2^2)`` of the central one (0.5 for two equal beads).
  :func:`repeated_light` measures it and :data:`REPEATED_LIGHT` bounds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import maximum_filter

from .calibrate_error import plane_fits, served_images, served_planes
from .psf.spline import SplinePSF

__all__ = [
    "REPEATED_LIGHT",
    "ROI_ENERGY",
    "ROI_ENERGY_LEAST",
    "LightProfile",
    "light_profile",
    "neighbour_light",
    "plane_photons",
    "repeated_light",
]

#: Fraction of a plane's light the automatic ROI holds (on average over the planes): light left
#: outside the model is missing from every fit's photons and costs precision.
ROI_ENERGY = 0.99
#: The least fraction the automatic ROI holds where beads near the frame's edge would not fit
#: in an ROI of :data:`ROI_ENERGY`: more beads average the model's noise and let its error be
#: measured bead against bead, but the light left out costs precision and photons (below it,
#: six beads localized no better than one bead's 99 %: hidden_data_rehearsal.txt, C).
ROI_ENERGY_LEAST = 0.97


@dataclass
class LightProfile:
    """How a bead's light spreads: radii (px) and the fraction of light within them.

    Attributes
    ----------
    half : int
        Smallest radius holding :data:`ROI_ENERGY` of the light (mean over planes).
    core : float
        Radius holding half of the light (mean over planes).
    fraction : ndarray, shape (R + 1,)
        Mean over planes of the fraction of light within each radius 0..R.
    fraction_min : ndarray, shape (R + 1,)
        The smallest fraction over the planes at each radius.
    reach : int or None
        One pixel (the emitter's sub-pixel offset) past the last ring whose light a model
        averaged over the beads holds above its pixel noise, where that is inside ``half``;
        else None.
    """

    half: int
    core: float
    fraction: NDArray[np.float64]
    fraction_min: NDArray[np.float64]
    reach: int | None = None

    def held(self, half: int) -> tuple[float, float]:
        """Mean and smallest fraction of a plane's light within ``half`` px."""
        k = int(min(max(half, 0), self.fraction.size - 1))
        return float(self.fraction[k]), float(self.fraction_min[k])

    def radius(self, fraction: float) -> int:
        """Smallest radius (px) holding ``fraction`` of a plane's light on average (the
        largest radius measured where none does)."""
        hold = self.fraction >= fraction
        return int(np.argmax(hold)) if hold.any() else self.fraction.size - 1


def light_profile(
    data: NDArray[np.float64],
    centre: tuple[float, float],
    others: NDArray[np.float64],
    max_radius: int,
    variance: NDArray[np.float64] | float = 0.0,
) -> LightProfile:
    """The light profile of the bead at ``centre`` (row, col; px) in the stack ``data``
    (Nz, H, W; photons less background), out to ``max_radius`` px or less.

    Pixels nearer one of ``others`` (n, 2; row, col) than to this bead are left out, and a
    ring's light is its mean over the bead's own pixels times the whole ring. Where part of
    a ring is the neighbours', that mean comes from fewer pixels: the profile goes on only
    while the noise (``variance``: each plane's pixel variance in photons^2, scalar or
    (Nz,)) leaves the ring's light known to better than the share of the light the ROI may
    leave out (``1 - ROI_ENERGY`` of the light measured so far), as it is for bright beads;
    farther out it would measure noise.

    The profile's ``reach`` is where a model's light ends: the last ring whose light power
    per pixel stands above the pixel noise variance of an average of all the beads found
    (this one and ``others``, each smoothed over the profile's planes); past it a model pixel
    would hold more noise than light, and each fit would carry that noise (dim beads). The
    power is the product of this bead's pixels with the mean of the other beads' windows
    (their noises are independent, so the product's mean is the light's power, but for a
    third bead's light in a window), on the median plane; it sees a double helix's lobes,
    which a ring's mean dilutes."""
    from scipy.ndimage import uniform_filter1d

    r0, c0 = int(np.round(centre[0])), int(np.round(centre[1]))
    rad = max_radius
    sub = data[:, r0 - rad : r0 + rad + 1, c0 - rad : c0 + rad + 1]
    window = min(5, sub.shape[0])
    sub = uniform_filter1d(sub, window, axis=0)
    var = np.broadcast_to(np.asarray(variance, dtype=np.float64), (sub.shape[0],)) / window
    rows, cols = np.indices(sub.shape[1:])
    rows = rows + r0 - rad
    cols = cols + c0 - rad
    dist = np.hypot(rows - centre[0], cols - centre[1])
    mine = np.ones(dist.shape, bool)
    for r, c in np.asarray(others, float).reshape(-1, 2):
        mine &= dist <= np.hypot(rows - r, cols - c)
    ring = np.round(dist).astype(int).ravel()
    mine = mine.ravel()
    flat = sub.reshape(sub.shape[0], -1)
    partner = _partner_mean(data, sub, others, rad, window)
    energy = np.zeros((sub.shape[0], rad + 1))
    power = np.full(rad + 1, np.nan)  # (nan: a ring without pixels; inf: one not judged)
    for k in range(rad + 1):
        own = np.flatnonzero((ring == k) & mine)
        n_ring = int(np.count_nonzero(ring == k))
        if k and not _measured(own.size, n_ring, var, energy[:, :k].sum(axis=1)):
            energy, power = energy[:, :k], power[:k]
            break
        if own.size:  # (ring 0 may hold no pixel centre)
            energy[:, k] = np.clip(flat[:, own].mean(axis=1), 0.0, None) * n_ring
            both = own[np.isfinite(partner[0, own])]
            power[k] = (
                np.median((flat[:, both] * partner[:, both]).mean(axis=1)) if both.size else np.inf
            )
    rad = energy.shape[1] - 1
    cum = np.cumsum(energy, axis=1)
    total = np.maximum(cum[:, -1:], 1e-12)
    frac = cum / total
    mean = frac.mean(axis=0)
    half = int(np.argmax(mean >= ROI_ENERGY)) if np.any(mean >= ROI_ENERGY) else rad
    core = float(np.argmax(mean >= 0.5))
    # A model's light stands above its noise out to the last ring ``above`` (a ring that
    # cannot be judged counts as above); one pixel more for the emitter's sub-pixel offset.
    # The noise is a lower bound on the model's (fewer beads may be used, and fewer planes
    # smoothed), so the cut errs toward keeping light.
    n_beads = 1 + np.asarray(others).reshape(-1, 2).shape[0]
    above = np.flatnonzero(power >= np.median(var) / n_beads)
    reach = int(above[-1]) + 1 if np.median(var) > 0 and above.size else half
    return LightProfile(half, core, mean, frac.min(axis=0), reach if reach < half else None)


def _partner_mean(
    data: NDArray[np.float64],
    sub: NDArray[np.float64],
    others: NDArray[np.float64],
    rad: int,
    window: int,
) -> NDArray[np.float64]:
    """The mean (Nz, side * side) of the other beads' windows of half side ``rad`` around
    their centres ``others``, each smoothed over ``window`` planes and scaled to the light of
    ``sub`` (Nz, side, side); NaN where no other bead's window lies in the frame."""
    from scipy.ndimage import uniform_filter1d

    nz, h, w = data.shape
    side = 2 * rad + 1
    light = float(np.clip(sub, 0.0, None).sum())
    acc, count = np.zeros(sub.shape), np.zeros(sub.shape[1:])
    for r, c in np.asarray(others, float).reshape(-1, 2):
        ri, ci = int(np.round(r)), int(np.round(c))
        top, left = max(ri - rad, 0), max(ci - rad, 0)
        bottom, right = min(ri + rad + 1, h), min(ci + rad + 1, w)
        if bottom <= top or right <= left:
            continue
        win = uniform_filter1d(data[:, top:bottom, left:right], window, axis=0)
        own = float(np.clip(win, 0.0, None).sum())
        if own <= 0 or light <= 0:
            continue
        rows = slice(top - (ri - rad), side - (ri + rad + 1 - bottom))
        cols = slice(left - (ci - rad), side - (ci + rad + 1 - right))
        acc[:, rows, cols] += win * (light / own)
        count[rows, cols] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return (acc / count).reshape(nz, -1)


def _measured(n_own: int, n_ring: int, var: NDArray, light: NDArray) -> bool:
    """Whether a ring of ``n_ring`` pixels, ``n_own`` of them the bead's, is measured: all
    its pixels are the bead's, or the light it extrapolates from them (its standard error,
    from each plane's pixel variance ``var`` (Nz,)) is known to better than
    ``1 - ROI_ENERGY`` of the ``light`` (Nz,) of the rings inside it, on the median plane."""
    if n_own == n_ring:
        return True
    if n_own == 0:
        return False
    error = n_ring * np.sqrt(var / n_own)
    return bool(np.median(error) <= (1.0 - ROI_ENERGY) * np.median(light))


def neighbour_light(
    model: SplinePSF,
    window: tuple[int, int, int],
    neighbours: list[tuple[float, float, float, NDArray[np.float64]]],
    zplanes: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The modelled light of ``neighbours`` in one bead's ROI stack.

    Parameters
    ----------
    model : SplinePSF
        The current PSF (unit photons per plane).
    window : (int, int, int)
        The ROI's first row, first column and side (px).
    neighbours : list of (x nm, y nm, dz nm, photons per plane (Nz,))
        Each neighbour's position in the frame, its z shift and its brightness per plane.
    zplanes : ndarray, shape (Nz,)
        The planes' z (nm).

    Returns
    -------
    ndarray, shape (Nz, side, side)
        Photons per pixel.
    """
    r0, c0, side = window
    p = model.pixel_size
    out = np.zeros((zplanes.size, side, side))
    for x, y, dz, photons in neighbours:
        z = zplanes + dz
        ok = served_planes(z, model.z_range, zplanes)
        if not ok.size:
            continue
        n = ok.size
        xs, ys = np.full(n, x - c0 * p), np.full(n, y - r0 * p)
        imgs = served_images(model, xs, ys, z[ok], (side, side))
        out[ok] += imgs * photons[ok, None, None]
    return out


def plane_photons(
    model: SplinePSF,
    roi: NDArray[np.float64],
    shift: NDArray[np.float64],
    zplanes: NDArray[np.float64],
) -> NDArray[np.float64]:
    """A bead's photons per plane: the model's least-squares scale on each plane of ``roi``
    (:func:`~sparseloc.calibrate_error.plane_fits`; 0 where the model does not reach)."""
    out = np.zeros(roi.shape[0])
    idx, _, scale, _ = plane_fits(model, roi, shift, zplanes)
    out[idx] = np.maximum(scale, 0.0)
    return out


#: The autocorrelation's side peak (a fraction of its central one, averaged over the planes)
#: above which a bead's ROI holds the same image repeated at a fixed offset, several beads:
#: two equal beads give 0.5, a brighter and a dimmer one less; a single bead far less, its
#: lobes moving with z (docs/benchmarks/repeated_light.txt).
REPEATED_LIGHT = 0.45


def repeated_light(stack: NDArray[np.float64]) -> tuple[float, float]:
    """How much of a bead's image repeats at one fixed offset over the planes.

    Parameters
    ----------
    stack : ndarray, shape (Nz, R, R)
        The bead's ROI in photons less the background.

    Returns
    -------
    (float, float)
        The highest side peak (a local maximum at least 2 px from the centre) of the
        planes' autocorrelations, each over its central value, averaged over the planes;
        and its lag (px). (0, 0) where there is none.
    """
    s = np.asarray(stack, dtype=np.float64)
    n_r, n_c = s.shape[1:]
    f = np.fft.rfft2(s, s=(2 * n_r, 2 * n_c))  # zero-padded: no wrap-around
    auto = np.fft.irfft2(np.abs(f) ** 2, s=(2 * n_r, 2 * n_c))
    centre = auto[:, :1, :1]
    planes = centre[:, 0, 0] > 0
    if not planes.any():
        return 0.0, 0.0
    mean = np.fft.fftshift((auto[planes] / centre[planes]).mean(axis=0))
    rows, cols = np.indices(mean.shape)
    lag = np.hypot(rows - n_r, cols - n_c)
    side = (mean == maximum_filter(mean, size=3)) & (lag >= 2.0)
    if not side.any():
        return 0.0, 0.0
    i = int(np.argmax(np.where(side, mean, -np.inf)))
    return float(max(mean.flat[i], 0.0)), float(lag.flat[i])
