"""The frame solver's second starting point: non-negative L1 deconvolution of the frame.

The pursuit (:mod:`sparseloc.solvers.frame_mp`) picks atoms one peak at a time: in a crowd an
engineered PSF's template also matches light of two neighbours (a double helix's template
matches any two lobes at its lobe distance), and the fits started there can stay in that
wrong arrangement. The deconvolution weighs every atom against all the others at once,

    minimise  1/2 sum((y - b - A x)^2 / v) + sum(lambda * x)   over  x >= 0,

with ``A`` the dictionary (templates centred on every pixel), ``v`` the noise variance of each
pixel and ``lambda`` each atom's detection threshold: ``min_snr`` noise standard deviations of
its correlation, as in the pursuit. It is solved by FISTA (Beck & Teboulle 2009) over one
template per z plane; its peaks start a second frame fit, and
:func:`~sparseloc.solvers.frame_compose.likelier_per_region` keeps, region by region, the
likelier of the two fits.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import fft as sfft
from scipy import ndimage as ndi

from ..detect import circular_shape
from ..psf.base import PSFModel
from .emitters import Emitters
from .frame_mp import FrameTemplates, frame_templates, in_tiles
from .variance import read_variance_crop

__all__ = ["L1_ITERATIONS", "Convolver", "l1_starts", "l1_templates", "tiled_l1_starts"]

#: FISTA iterations: the peaks only start fits, and more iterations did not give better
#: starts (``docs/benchmarks/second_start.txt``).
L1_ITERATIONS = 100
#: Power iterations that estimate the step (the largest eigenvalue of ``A' W A``).
_POWER_ITERATIONS = 15


def l1_templates(model: PSFModel, templates: FrameTemplates) -> FrameTemplates:
    """The deconvolution's dictionary: one template per pixel (no sub-pixel phases) and planes
    twice as far apart as the pursuit's, over the same z range and template size (its atoms
    only start fits; 4-8x fewer templates make each iteration as much cheaper)."""
    zs = np.unique(templates.z)
    dz = 2.0 * float(np.min(np.diff(zs))) if zs.size > 1 else 1.0
    return frame_templates(
        model,
        templates.pixel_size,
        dxy=templates.pixel_size,
        dz=dz,
        z_range=(float(zs[0]), float(zs[-1])) if zs.size > 1 else None,
        size=templates.images.shape[-1],
    )


class Convolver:
    """The dictionary as an operator on one frame shape: ``forward`` renders atom amplitudes
    (J, rows, cols) into an image, ``adjoint`` correlates an image with every template. FFTs
    in single precision, of the circular length that is exact for outputs kept at the frame's
    pixels (:func:`~sparseloc.detect.circular_shape`); atoms are centred on every pixel of
    the frame and their light outside it is lost."""

    def __init__(self, templates: NDArray, shape: tuple[int, int]) -> None:
        self.width = templates.shape[-1]
        self.h = self.width // 2
        self.shape = shape
        self.fshape = circular_shape(shape, self.width)
        self.ft = sfft.rfft2(templates, s=self.fshape).astype(np.complex64)
        # the adjoint is the convolution with the flipped templates: its outputs then lie at
        # the same offset as the forward's, a slice rather than a gather
        self.ft_flipped = sfft.rfft2(templates[:, ::-1, ::-1], s=self.fshape).astype(np.complex64)

    def _crop(self, full: NDArray, offset: int) -> NDArray:
        rows, cols = self.shape
        return full[..., offset : offset + rows, offset : offset + cols]

    def forward(self, x: NDArray) -> NDArray:
        """(rows, cols): the sum of every atom's template times its amplitude."""
        fx = sfft.rfft2(x.astype(np.float32, copy=False), s=self.fshape)
        return self._crop(sfft.irfft2((fx * self.ft).sum(axis=0), s=self.fshape), self.h)

    def adjoint(self, img: NDArray) -> NDArray:
        """(J, rows, cols): the image's correlation with each template centred on each pixel."""
        f = sfft.rfft2(img.astype(np.float32, copy=False), s=self.fshape)
        # the flipped template's centre lies at width - 1 - h (h itself for an odd width)
        offset = self.width - 1 - self.h
        return self._crop(sfft.irfft2(f[None] * self.ft_flipped, s=self.fshape), offset)


def _step(conv: Convolver, w: NDArray) -> float:
    """1 / L for FISTA, L the largest eigenvalue of ``A' W A`` by power iteration (5 % margin)."""
    x = np.random.default_rng(0).random((conv.ft.shape[0], *conv.shape)).astype(np.float32)
    norm = 1.0
    for _ in range(_POWER_ITERATIONS):
        x = conv.adjoint(w * conv.forward(x))
        norm = float(np.sqrt(np.sum(x.astype(np.float64) ** 2)))
        x /= max(norm, 1e-30)
    return 1.0 / (1.05 * max(norm, 1e-30))


def _fista(conv: Convolver, y: NDArray, w: NDArray, lam: NDArray, iterations: int) -> NDArray:
    """Atom amplitudes (J, rows, cols) minimising the weighted L1 problem of the module notes."""
    step = _step(conv, w)
    x = np.zeros((conv.ft.shape[0], *conv.shape), np.float32)
    z, t = x.copy(), 1.0
    for _ in range(iterations):
        # x_new = max(z - step (grad + lam), 0), in the gradient's own array
        x_new = conv.adjoint(w * (conv.forward(z) - y))
        x_new += lam
        x_new *= -step
        x_new += z
        np.maximum(x_new, 0.0, out=x_new)
        t_new = (1.0 + np.sqrt(1.0 + 4.0 * t * t)) / 2.0
        # z = x_new + (t - 1) / t_new (x_new - x), in x's array (x is not needed after)
        np.subtract(x_new, x, out=x)
        x *= (t - 1.0) / t_new
        x += x_new
        z, x, t = x, x_new, t_new
    return x


def _separated_maxima(total: NDArray, size: int, floor: float) -> NDArray[np.intp]:
    """Pixels (K, 2) of the local maxima of ``total`` over ``size`` x ``size`` pixels above
    ``floor``, strongest first, none within ``size // 2`` pixels (per axis) of a stronger one.

    Maxima that tie are one peak, the first in raster order: a lone atom's 3 x 3 sum is flat,
    and which of its pixels equal the local maximum depends on the last bits of the sums, so
    without this rule rounding alone gave one start or several at one place.
    """
    top = np.argwhere((total == ndi.maximum_filter(total, size=size)) & (total > floor))
    order = np.lexsort((np.arange(len(top)), -total[top[:, 0], top[:, 1]]))
    half = size // 2
    taken = np.zeros(total.shape, dtype=bool)  # within half of a kept peak
    kept = []
    for r, c in top[order]:
        if not taken[r, c]:
            kept.append((r, c))
            taken[max(r - half, 0) : r + half + 1, max(c - half, 0) : c + half + 1] = True
    return np.array(kept, dtype=np.intp).reshape(-1, 2)


def _peaks(x: NDArray, templates: FrameTemplates, size: int, min_photons: float) -> NDArray:
    """Emitters (K, 4) at the peaks of the amplitudes summed over templates and 3 x 3 pixels
    (:func:`_separated_maxima` over ``size`` x ``size`` pixels with at least
    ``min_photons``): each the
    amplitude-weighted mean position of the atoms of its 3 x 3 pixels on the planes within
    one plane of its strongest atom, with their summed amplitude."""
    px = templates.pixel_size
    total = ndi.uniform_filter(x.sum(axis=0).astype(np.float64), 3) * 9.0
    peaks = _separated_maxima(total, size, min_photons)
    zs = np.unique(templates.z)
    dz = float(np.min(np.diff(zs))) if zs.size > 1 else 0.0
    rows, cols = total.shape
    out = []
    for r, c in peaks.reshape(-1, 2):
        r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, rows), max(c - 1, 0), min(c + 2, cols)
        a = x[:, r0:r1, c0:c1]
        strongest = int(np.argmax(a.reshape(len(a), -1).max(axis=1)))
        near = np.abs(templates.z - templates.z[strongest]) <= 1.01 * dz
        a = np.where(near[:, None, None], a, 0.0)
        jj, rr, cc = np.nonzero(a > 0)
        wts = a[jj, rr, cc].astype(np.float64)
        xs = (c0 + cc + 0.5) * px + templates.dx[jj]
        ys = (r0 + rr + 0.5) * px + templates.dy[jj]
        out.append(
            [
                np.average(xs, weights=wts),
                np.average(ys, weights=wts),
                np.average(templates.z[jj], weights=wts),
                wts.sum(),
            ]
        )
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def l1_starts(
    frame: NDArray,
    background: NDArray | float,
    templates: FrameTemplates,
    *,
    peak_radius: float,
    min_snr: float = 5.0,
    min_photons: float = 100.0,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
    iterations: int = L1_ITERATIONS,
    convolver: Convolver | None = None,
) -> Emitters:
    """Emitters of one frame at the peaks of its non-negative L1 deconvolution.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        One frame in photons.
    background : ndarray or float
        Background (photons/pixel).
    templates : FrameTemplates
        The dictionary (:func:`l1_templates`).
    peak_radius : float
        Peaks closer than this (pixels) are one emitter: the PSF's typical half-light radius.
    min_snr : float
        Each atom's threshold ``lambda``: this many noise standard deviations of its
        correlation with the data.
    min_photons : float
        Smallest amplitude (photons) of a peak.
    noise_factor : float
        Variance per expected photon (2 for EMCCD data).
    read_variance : float or ndarray, shape (rows, cols)
        Read-noise variance (photons^2) added to the shot noise.
    iterations : int
        FISTA iterations.
    convolver : Convolver, optional
        The dictionary's operator for this frame shape (reused across frames).

    Returns
    -------
    Emitters
        Starting positions (nm, frame coordinates) and photons.
    """
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {f.shape}")
    conv = convolver or Convolver(templates.images, f.shape)
    if conv.shape != f.shape:
        raise ValueError(f"the convolver was built for {conv.shape}, not {f.shape}")
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    y = f - bg
    # each pixel's variance: shot noise of the background and the local light, and read noise
    light = np.maximum(ndi.uniform_filter(y, 5), 0.0)
    v = np.maximum(noise_factor * (bg + light) + np.asarray(read_variance, dtype=np.float64), 1.0)
    w = (1.0 / v).astype(np.float32)
    t2 = np.sum(templates.images.astype(np.float64) ** 2, axis=(1, 2))
    lam = (min_snr * np.sqrt(t2[:, None, None] * w[None])).astype(np.float32)
    x = _fista(conv, y.astype(np.float32), w, lam, iterations)
    size = 2 * round(float(peak_radius)) + 1
    return Emitters.from_array(_peaks(x, templates, max(size, 3), min_photons))


def tiled_l1_starts(
    frame: NDArray,
    background: NDArray | float,
    templates: FrameTemplates,
    *,
    max_pixels: int = 512 * 512,
    core: int = 256,
    convolvers: dict | None = None,
    **kwargs,
) -> Emitters:
    """:func:`l1_starts` on the whole frame, or on overlapping tiles of a large one (the
    amplitudes of every template over a 2048 x 2048 frame would take GB): cores of ``core``
    pixels, each solved with a margin of one template width and keeping its own peaks, as
    :func:`~sparseloc.solvers.frame_mp.tiled_pursuit` does. ``convolvers`` caches the
    operators per shape across frames."""
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {f.shape}")
    cache = {} if convolvers is None else convolvers
    rows, cols = f.shape
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    rv = np.asarray(kwargs.pop("read_variance", 0.0), dtype=np.float64)

    def run(window: tuple[slice, slice]) -> NDArray:
        sub = f[window]
        conv = cache.get(sub.shape)
        if conv is None:
            conv = cache[sub.shape] = Convolver(templates.images, sub.shape)
        rows_, cols_ = window
        sub_rv = read_variance_crop(rv, f.shape, (rows_.start, rows_.stop, cols_.start, cols_.stop))
        found = l1_starts(
            sub, bg[window], templates, convolver=conv, read_variance=sub_rv, **kwargs
        )
        return found.as_array().reshape(-1, 4)

    if rows * cols <= max_pixels:
        return Emitters.from_array(run((slice(None), slice(None))))
    m = templates.images.shape[-1]
    return Emitters.from_array(in_tiles(run, f.shape, templates.pixel_size, core, m))
