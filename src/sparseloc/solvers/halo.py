"""The halo of bright emitters: the light their model holds beyond the spline table's.

The frame solver renders each emitter with the run's spline table of the model, which ends a
few pixels past a template's reach, and leaves the rest of its light (a few to 25 % of a
pupil model's, in rings out to several um) to the background estimate. For ordinary
emitters that light lies far below the noise. Around an emitter of 10^5 photons it is a ring
brighter than the background, which neither a spatial nor a temporal background follows,
and which the detection reads as a ring of emitters (``docs/benchmarks/halo.txt``). So
where an emitter's halo, its model's image less its table's, could reach the detection's
threshold on its own, the halo is rendered and the frame solved again with it known: in
every window's known light and under every detection.

The halo is rendered at each bright emitter's position (a hard-edged pupil's rings have
fringes a few pixels apart). A bead calibration is its own table: it has no halo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import fftconvolve

from ..psf.base import PSFModel
from ..psf.spline import SplinePSF

__all__ = ["EDGE_PX", "HALO_PLANES", "HALO_RADIUS_NM", "Halo", "halo_of"]

#: Farthest (nm) from an emitter a halo is rendered: a pupil model's rings hold about 1 % of
#: its light beyond 8 um, and spread over a disc that wide it sits far below any noise.
HALO_RADIUS_NM = 8000.0

#: z planes over the model's range at which the halo's detectability is measured.
HALO_PLANES = 21

#: Pixels at the edge of a bead calibration's ROI whose light stands for the light beyond it:
#: the ring one pixel past the ROI is as wide (a pixel either way of the emitter's sub-pixel
#: position), and one pixel alone would read the ROI's noisiest ring.
EDGE_PX = 2


@dataclass(frozen=True)
class Halo:
    """How detectable a model's light beyond its spline table's is, per photon.

    Attributes
    ----------
    z : ndarray, shape (P,)
        The planes (nm) at which it was measured.
    response : ndarray, shape (P,)
        The detection's largest signal-to-noise of one photon's halo at each plane, under a
        noise variance of 1 photon^2 per pixel (divide by the noise's standard deviation).
    peak : ndarray, shape (D,)
        The largest light (per photon) of the model's pixels at a box distance of at least
        d pixels from the emitter's, over the planes, for d = 0 .. D - 1.
    gain : float
        The detection's largest signal-to-noise of a uniform light of 1 photon per pixel
        under unit noise (a bound on what light of at most that level anywhere gives).
    """

    z: NDArray[np.float64]
    response: NDArray[np.float64]
    peak: NDArray[np.float64]
    gain: float

    @classmethod
    def measure(
        cls,
        model: PSFModel,
        table: PSFModel,
        pixel_size: float,
        planes: NDArray,
        z_range: tuple[float, float] | None = None,
    ) -> Halo:
        """Measure ``model``'s halo, its images less those of its spline ``table``, on
        pixels of ``pixel_size`` nm against the detection's templates ``planes`` (P, T, T)
        over ``z_range`` (default the model's)."""
        px = float(pixel_size)
        half = int(np.ceil(HALO_RADIUS_NM / px))
        n = 2 * half + 1
        zr = z_range or model.z_range
        z = np.linspace(zr[0], zr[1], HALO_PLANES)
        centre = np.full(z.size, (half + 0.5) * px)
        imgs = np.asarray(model.images(centre, centre, z, (n, n), px), dtype=np.float64)
        halos = imgs - np.asarray(table.images(centre, centre, z, (n, n), px))
        return cls.of_images(z, imgs, halos, planes)

    @classmethod
    def at_roi_edge(
        cls,
        table: SplinePSF,
        pixel_size: float,
        planes: NDArray,
        z_range: tuple[float, float] | None = None,
    ) -> Halo:
        """For a model known only within its ROI (a bead calibration's table): the light of
        the ROI's outermost :data:`EDGE_PX` pixels around the emitter, a stand-in for the
        light just beyond it (a PSF's light does not stop where a ROI does)."""
        px = float(pixel_size)
        h = int(np.floor(table.roi_half(px) / px + 1e-9))
        half = h + 1
        n = 2 * half + 1
        zr = z_range or table.z_range
        z = np.linspace(zr[0], zr[1], HALO_PLANES)
        centre = np.full(z.size, (half + 0.5) * px)
        imgs = np.asarray(table.images(centre, centre, z, (n, n), px), dtype=np.float64)
        yy, xx = np.mgrid[:n, :n]
        dist = np.maximum(np.abs(yy - half), np.abs(xx - half))
        edge = (dist > h - EDGE_PX) & (dist <= h)
        return cls.of_images(z, imgs, imgs * edge, planes)

    @classmethod
    def of_images(cls, z: NDArray, imgs: NDArray, halos: NDArray, planes: NDArray) -> Halo:
        """From one photon's images (P, n, n; the emitter at the middle pixel's centre) at
        the planes ``z`` and their halos (the same shape), against the detection's
        templates ``planes``."""
        n = imgs.shape[-1]
        half = n // 2
        yy, xx = np.mgrid[:n, :n]
        dist = np.maximum(np.abs(yy - half), np.abs(xx - half))
        ring = imgs.max(axis=0)
        peak = np.array([ring[dist >= d].max() for d in range(half + 1)])
        peak = np.maximum.accumulate(peak[::-1])[::-1]
        t = np.asarray(planes, dtype=np.float64)
        t = t / t.sum(axis=(1, 2), keepdims=True)
        norms = np.sqrt((t**2).sum(axis=(1, 2)))
        response = np.zeros(z.size)
        if np.abs(halos).max() > 0:
            for tj, nj in zip(t, norms, strict=True):
                corr = fftconvolve(halos, tj[None, ::-1, ::-1], mode="same", axes=(1, 2))
                response = np.maximum(response, corr.max(axis=(1, 2)) / nj)
        return cls(np.asarray(z, dtype=np.float64), response, peak, float(1.0 / norms.min()))

    def detectable(self, z: NDArray, photons: NDArray, sigma: NDArray, threshold: float):
        """Which emitters' halos reach the detection's ``threshold`` on their own: ``z``
        (nm), ``photons`` and the noise's standard deviation ``sigma`` (photons/pixel) at
        each. (An emitter the count selection adds must pass its bar, some 9 standard
        deviations for a known image against the detection's 4-5: a halo below the
        detection's threshold would need the noise's help by 4 more.)"""
        snr = np.asarray(photons) * np.interp(z, self.z, self.response) / np.asarray(sigma)
        return snr >= threshold

    def extent(self, photons: float, sigma: float, threshold: float) -> int:
        """Box half-width (px) of the halo to render for an emitter of ``photons`` over a
        noise of standard deviation ``sigma``: out to where no pixel's light could bring the
        detection to ``threshold`` (at most the measured extent)."""
        bound = photons * self.peak * self.gain / sigma
        faint = np.flatnonzero(bound < threshold)
        return int(faint[0]) if faint.size else self.peak.size - 1


def halo_of(
    halo: Halo,
    model: PSFModel,
    table: PSFModel,
    emitters: NDArray,
    noise: NDArray,
    pixel_size: float,
    threshold: float,
    counted: int | None = None,
) -> NDArray[np.float64] | None:
    """The halo light (rows, cols; photons/pixel) of the emitters (K, 4; nm, photons) whose
    halo could be detected: each one's image from ``model`` less that from its spline
    ``table``, out to :meth:`Halo.extent`; where the table's light is counted only within
    ``counted`` pixels of the emitter's pixel (a frame check's boxes), less that part of
    it. ``noise``: the noise variance (photons^2) per pixel of the frame; ``threshold``:
    the detection's. None where no emitter's halo is detectable."""
    em = np.asarray(emitters, dtype=np.float64).reshape(-1, 4)
    em = em[np.all(np.isfinite(em), axis=1)]
    rows, cols = noise.shape
    px = float(pixel_size)
    if not len(em) or halo.response.max() <= 0:
        return None
    r = np.clip((em[:, 1] // px).astype(int), 0, rows - 1)
    c = np.clip((em[:, 0] // px).astype(int), 0, cols - 1)
    sigma = np.sqrt(np.maximum(noise[r, c], 1e-3))
    bright = np.flatnonzero(halo.detectable(em[:, 2], em[:, 3], sigma, threshold))
    if not bright.size:
        return None
    out = np.zeros((rows, cols))
    for k in bright:
        half = halo.extent(em[k, 3], sigma[k], threshold)
        cy, cx = int(r[k]), int(c[k])
        r0, r1 = max(cy - half, 0), min(cy + half + 1, rows)
        c0, c1 = max(cx - half, 0), min(cx + half + 1, cols)
        args = ([em[k, 0]], [em[k, 1]], [em[k, 2]], [em[k, 3]], (r1 - r0, c1 - c0), px)
        origin = (c0 * px, r0 * px)
        known = table.render(*args, origin=origin)
        if counted is not None:
            rr, cc = np.ogrid[r0:r1, c0:c1]
            known *= (np.abs(rr - cy) <= counted) & (np.abs(cc - cx) <= counted)
        out[r0:r1, c0:c1] += model.render(*args, origin=origin) - known
    return out
