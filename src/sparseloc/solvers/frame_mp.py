"""The frame solver's starting point: greedy matching pursuit over a whole frame.

The dictionary is a set of shifted templates (sub-pixel phases x z planes). Each cycle
correlates the residual with every template through one FFT per template (all atoms of a
template are one convolution), keeps the strongest significant peaks that are far enough apart
not to be pieces of one another, then refits all the amplitudes jointly (non-negative least
squares) and updates the residual. :func:`tiled_pursuit` runs it on large frames in tiles.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import fft as sfft
from scipy import ndimage as ndi

from ..detect import circular_shape
from ..engine import kernels
from ..psf.base import PSFModel, energy_radius
from .emitters import Emitters
from .nnls import sparse_nnls

log = logging.getLogger(__name__)

__all__ = [
    "Correlator",
    "FrameTemplates",
    "frame_pursuit",
    "frame_templates",
    "in_tiles",
    "tiled_pursuit",
]


@dataclass(frozen=True)
class FrameTemplates:
    """Unit-photon images of one emitter per (sub-pixel phase, z plane).

    Attributes
    ----------
    images : ndarray, shape (J, T, T)
        Emitter near the centre of pixel (T // 2, T // 2), offset by ``(dx, dy)``.
    dx, dy : ndarray, shape (J,)
        Offsets (nm) from that pixel's centre.
    z : ndarray, shape (J,)
        Axial positions (nm).
    pixel_size : float
        Pixel size (nm).
    core_radius : float
        Radius (pixels) holding half of the light of the broadest plane: peaks closer than
        twice this are not accepted in the same pursuit cycle.
    radius90 : float
        Radius (pixels) holding 90 % of the light of the broadest plane.
    typical_radius : float
        Radius (pixels) holding half of the light of a typical plane: the median over the
        planes of each one's half-light radius (a pupil double helix's broadest planes, at
        the ends of its range, hold their light in a halo twice as wide as its middle ones).
    """

    images: NDArray[np.float64]
    dx: NDArray[np.float64]
    dy: NDArray[np.float64]
    z: NDArray[np.float64]
    pixel_size: float
    core_radius: float
    radius90: float
    typical_radius: float = float("nan")


def frame_templates(
    model: PSFModel,
    pixel_size: float,
    *,
    dxy: float,
    dz: float,
    z_range: tuple[float, float] | None = None,
    size: int | None = None,
) -> FrameTemplates:
    """Templates of the pursuit: ``pixel_size / dxy`` phases per axis times the z planes.

    Parameters
    ----------
    model : PSFModel
        The PSF model.
    pixel_size : float
        Pixel size (nm).
    dxy, dz : float
        Lateral step (nm, must divide the pixel) and axial step (nm).
    z_range : (float, float), optional
        Axial range (nm); default the model's.
    size : int, optional
        Template side (pixels, odd); default twice the radius holding 90 % of the light
        plus one, at most 41.
    """
    px = float(pixel_size)
    if not dxy > 0:
        raise ValueError(f"the lateral step must be > 0 nm, got {dxy}")
    phases = round(px / dxy)
    if phases < 1 or abs(phases * dxy - px) > 1e-6 * px:
        raise ValueError(f"the lateral step {dxy} nm must divide the pixel ({px} nm)")
    if dz <= 0:
        raise ValueError(f"the axial step must be > 0 nm, got {dz}")
    lo, hi = model.z_range if z_range is None else z_range
    if not lo < hi:
        raise ValueError(f"z_range must be (z_min, z_max) with z_min < z_max, got {(lo, hi)}")
    zs = np.linspace(lo, hi, int(np.ceil((hi - lo) / dz - 1e-9)) + 1)
    probe = 61
    c = probe * px / 2
    imgs = model.images(np.full(zs.size, c), np.full(zs.size, c), zs, (probe, probe), px)
    rr = np.hypot(*np.meshgrid(np.arange(probe) - probe // 2, np.arange(probe) - probe // 2))
    r90 = energy_radius(imgs, rr.ravel(), 0.9)
    if size is None:
        size = int(min(2 * np.ceil(r90) + 1, 41))
    if size < 3 or size % 2 == 0:
        raise ValueError(f"template size must be odd and >= 3, got {size}")
    r50 = energy_radius(imgs, rr.ravel(), 0.5)
    typical = float(np.median([energy_radius(im[None], rr.ravel(), 0.5) for im in imgs]))
    offs = ((np.arange(phases) + 0.5) / phases - 0.5) * px
    dx, dy, zz = (a.ravel() for a in np.meshgrid(offs, offs, zs, indexing="ij"))
    centre = (size // 2 + 0.5) * px
    images = model.images(centre + dx, centre + dy, zz, (size, size), px)
    return FrameTemplates(images, dx, dy, zz, px, float(r50), float(r90), typical)


class Correlator:
    """FFT correlation of one frame shape with every template (and its square).

    Memory: the templates' spectra are kept in single precision and correlations are formed
    ``batch`` templates at a time, so a large frame with many templates stays within a few
    hundred MB (scores need ~1e-6 relative precision, not 1e-15).
    """

    def __init__(self, templates: FrameTemplates, shape: tuple[int, int], batch: int = 16):
        t = templates.images
        self.h = t.shape[-1] // 2
        self.shape = shape
        self.batch = int(batch)
        self.fshape = circular_shape(shape, t.shape[-1])
        self._flipped = t[:, ::-1, ::-1]
        self.ft = sfft.rfft2(self._flipped, s=self.fshape).astype(np.complex64)
        self.norm2 = np.empty((t.shape[0], *shape), dtype=np.float32)
        for j0, part in self._batches(np.ones(shape), True):
            self.norm2[j0 : j0 + len(part)] = part
        self.inv_norm = (1.0 / np.sqrt(np.maximum(self.norm2, 1e-12))).astype(np.float32)
        # One kernel for local means of the variance: the templates' mean square, normalised.
        sq = (self._flipped**2).mean(axis=0)
        self.fw = sfft.rfft2(sq / sq.sum(), s=self.fshape)
        self.wsum = np.maximum(self._smooth(np.ones(shape)), 1e-12)

    def local_mean(self, img: NDArray) -> NDArray[np.float64]:
        """(rows, cols): ``img`` averaged with the templates' mean square as weights (over
        the pixels inside the frame)."""
        return self._smooth(img) / self.wsum

    def _smooth(self, img: NDArray) -> NDArray[np.float64]:
        f = sfft.rfft2(img, s=self.fshape)
        full = sfft.irfft2(f * self.fw, s=self.fshape)
        h, (rows, cols) = self.h, self.shape
        return full[h : h + rows, h : h + cols]

    def _batches(self, img: NDArray, squared: bool, crop: bool = True):
        """``(j0, correlations)`` per batch of templates: cropped to the frame's pixels, or
        with ``crop=False`` the whole circular correlation (the frame's pixels start at
        ``[h, h]``)."""
        f = sfft.rfft2(img, s=self.fshape)
        if not squared:
            # single precision like the spectra: the inverse FFTs run at twice the speed
            f = f.astype(np.complex64)
        h, (rows, cols) = self.h, self.shape
        n = self.ft.shape[0]
        for j0 in range(0, n, self.batch):
            j1 = min(j0 + self.batch, n)
            ft = sfft.rfft2(self._flipped[j0:j1] ** 2, s=self.fshape) if squared else self.ft[j0:j1]
            full = sfft.irfft2(f[None] * ft, s=self.fshape)
            yield j0, (full[:, h : h + rows, h : h + cols] if crop else full)

    def correlate(self, img: NDArray, squared: bool = False) -> NDArray[np.float64]:
        """(J, rows, cols): sum over the template of ``img`` times the template (or its
        square), the template centred on each pixel; pixels outside the frame count zero.
        Computed in single precision (returned as float64) except for the squares."""
        out = np.empty((self.ft.shape[0], *self.shape))
        for j0, part in self._batches(img, squared):
            out[j0 : j0 + len(part)] = part
        return out

    def best(self, img: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Per pixel, the template whose normalised correlation with ``img`` is largest.

        Returns ``(score, j, corr, norm2)`` at that template, each (rows, cols): the score is
        ``corr / sqrt(norm2)`` (matching pursuit's choice). The numba engine selects in one
        compiled loop (the same result as the NumPy gathers; :mod:`sparseloc.engine`).
        """
        kern = kernels()
        if kern is not None:
            select = kern.select_best
            # the kernel's running best is single precision (its values are): converted once
            sb = np.full(self.shape, -np.inf, dtype=np.float32)
            jb = np.zeros(self.shape, dtype=np.int32)
            cb = np.zeros(self.shape, dtype=np.float32)
            for j0, full in self._batches(img, False, crop=False):
                select(full, self.h, self.inv_norm[j0 : j0 + len(full)], j0, sb, jb, cb)
            sb, jb, cb = sb.astype(np.float64), jb.astype(np.intp), cb.astype(np.float64)
        else:
            sb = np.full(self.shape, -np.inf)
            jb = np.zeros(self.shape, dtype=np.intp)
            cb = np.zeros(self.shape)
            for j0, part in self._batches(img, False):
                inv = self.inv_norm[j0 : j0 + len(part)]
                score = part * inv
                k = np.argmax(score, axis=0)
                s = np.take_along_axis(score, k[None], 0)[0]
                better = s > sb
                sb[better] = s[better]
                jb[better] = (j0 + k)[better]
                cb[better] = np.take_along_axis(part, k[None], 0)[0][better]
        nb = np.take_along_axis(self.norm2, jb[None], 0)[0].astype(np.float64)
        return sb, jb, cb, nb


def _place(templates: FrameTemplates, atoms: list[tuple[int, int, int]], shape):
    """Sparse (pixels, K) matrix whose columns are the atoms' images in the frame."""
    from scipy.sparse import csc_matrix

    rows, cols = shape
    h = templates.images.shape[-1] // 2
    idx, val, ptr = [], [], [0]
    for j, r, c in atoms:
        r0, r1 = max(r - h, 0), min(r + h + 1, rows)
        c0, c1 = max(c - h, 0), min(c + h + 1, cols)
        block = templates.images[j, r0 - r + h : r1 - r + h, c0 - c + h : c1 - c + h]
        idx.append((np.arange(r0, r1)[:, None] * cols + np.arange(c0, c1)[None, :]).ravel())
        val.append(block.ravel())
        ptr.append(ptr[-1] + block.size)
    return csc_matrix(
        (np.concatenate(val), np.concatenate(idx), np.array(ptr)), shape=(rows * cols, len(atoms))
    )


class _Exclusion:
    """The pixels closer than ``distance`` (pixels, exclusive) to an atom placed this cycle:
    a candidate there is refused in constant time, as a comparison with every atom placed
    would refuse it (a cycle of a dense 512 x 512 px frame places hundreds)."""

    def __init__(self, shape: tuple[int, int], distance: float) -> None:
        self.blocked = np.zeros(shape, dtype=bool)
        h = int(np.ceil(distance))
        dr, dc = np.mgrid[-h : h + 1, -h : h + 1]
        self.disc = dr**2 + dc**2 < distance**2
        self.h = h

    def near(self, r: int, c: int) -> bool:
        return bool(self.blocked[r, c])

    def add(self, r: int, c: int) -> None:
        h, (rows, cols) = self.h, self.blocked.shape
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, rows), max(c - h, 0), min(c + h + 1, cols)
        d = self.disc[r0 - r + h : r1 - r + h, c0 - c + h : c1 - c + h]
        self.blocked[r0:r1, c0:c1] |= d


def frame_pursuit(
    frame: NDArray,
    background: NDArray | float,
    templates: FrameTemplates,
    *,
    min_snr: float = 5.0,
    min_photons: float = 100.0,
    max_cycles: int = 10,
    max_emitters: int | None = None,
    per_cycle: int | None = None,
    exclusion: float | None = None,
    noise_factor: float = 1.0,
    read_variance: float | NDArray = 0.0,
    correlator: Correlator | None = None,
) -> Emitters:
    """Emitters of one frame by matching pursuit over the whole frame.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        One frame in photons.
    background : ndarray or float
        Background (photons/pixel), a map or a constant.
    templates : FrameTemplates
        The pursuit's dictionary (see :func:`frame_templates`).
    min_snr : float
        A new emitter's correlation must exceed ``min_snr`` times its Poisson standard
        deviation.
    min_photons : float
        Smallest amplitude (photons) of a new emitter.
    max_cycles : int
        Cap on correlate-select-refit cycles.
    max_emitters : int, optional
        Cap on the count (default: one per 16 pixels).
    per_cycle, exclusion : optional
        At most ``per_cycle`` new emitters per cycle, at least ``exclusion`` pixels apart
        (default: twice the templates' core radius).
    noise_factor : float
        Variance per expected photon (2 for EMCCD data: excess noise).
    read_variance : float or ndarray, shape (rows, cols)
        Read-noise variance per pixel (photons^2) added to the shot noise (sCMOS).
    correlator : optional
        A correlator built for this frame shape and templates (reused across frames).

    Returns
    -------
    Emitters
        Positions (nm, frame coordinates: pixel (0, 0) spans 0..pixel_size) on the pursuit's
        grid, and photons.
    """
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {f.shape}")
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    cor = correlator or Correlator(templates, f.shape)
    if cor.shape != f.shape:
        raise ValueError(f"the correlator was built for {cor.shape}, not {f.shape}")
    rows, cols = f.shape
    cap = max(1, rows * cols // 16) if max_emitters is None else max_emitters
    y = f - bg
    atoms: list[tuple[int, int, int]] = []
    amps = np.zeros(0)
    model = np.zeros_like(y)
    excl = max(2.0, 2.0 * templates.core_radius) if exclusion is None else exclusion
    rv = np.asarray(read_variance, dtype=np.float64)
    if rv.ndim:
        # sum(t^2 var_read) over each atom's pixels, as a local mean like the shot noise's.
        rv = cor.local_mean(np.broadcast_to(rv, f.shape))
    per_cycle = cap if per_cycle is None else per_cycle
    for _ in range(max_cycles):
        sb, jb, cb, nb = cor.best(y - model)
        # Poisson variance of the correlation, sum(t^2 mu), as (local mean of mu) x sum(t^2):
        # one FFT instead of one per template.
        vb = (cor.local_mean(np.maximum(bg + model, 1e-3)) * noise_factor + rv) * nb
        ok = (cb / np.sqrt(np.maximum(vb, 1e-12)) > min_snr) & (cb / nb > min_photons)
        peaks = ok & (ndi.maximum_filter(sb, size=3, mode="constant", cval=-np.inf) == sb)
        rc = np.argwhere(peaks)
        if len(rc) == 0:
            break
        order = np.argsort(-sb[peaks])
        new: list[tuple[int, int, int]] = []
        taken = _Exclusion(f.shape, excl)
        for r, c in rc[order]:
            if len(atoms) + len(new) >= cap or len(new) >= per_cycle:
                break
            if taken.near(r, c):
                continue
            taken.add(r, c)
            new.append((int(jb[r, c]), int(r), int(c)))
        if not new:
            break
        atoms += new
        a = _place(templates, atoms, f.shape)
        amps = sparse_nnls(a, y.ravel())
        keep = amps > 0.5 * min_photons
        atoms = [at for at, k in zip(atoms, keep, strict=True) if k]
        amps = amps[keep]
        model = (a[:, keep] @ amps).reshape(f.shape) if len(atoms) else np.zeros_like(y)
        if len(atoms) >= cap:
            break
    if not atoms:
        return Emitters.empty()
    j, r, c = (np.array(v) for v in zip(*atoms, strict=True))
    px = templates.pixel_size
    return Emitters(
        (c + 0.5) * px + templates.dx[j],
        (r + 0.5) * px + templates.dy[j],
        templates.z[j].astype(np.float64),
        amps.astype(np.float64),
    )


def tiled_pursuit(
    frame: NDArray,
    background: NDArray | float,
    templates: FrameTemplates,
    *,
    max_pixels: int = 512 * 512,
    core: int = 256,
    correlators: dict | None = None,
    **kwargs,
) -> Emitters:
    """:func:`frame_pursuit` on the whole frame, or on overlapping tiles of a large one.

    The pursuit keeps a correlation per template over the whole frame; a 2048 x 2048 sCMOS
    frame would need several GB. Frames above ``max_pixels`` are cut into cores of ``core``
    pixels, each searched with a margin of one template width around it (so it sees the
    whole image of any emitter in it and of its neighbours) and keeping the emitters in its
    core. The tiles at the far edges are shifted inwards so that every tile has the same
    shape: one correlator serves them all. ``correlators`` caches correlators per shape
    across frames.
    """
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim != 2:
        raise ValueError(f"frame must be 2-D, got shape {f.shape}")
    cache = {} if correlators is None else correlators
    rows, cols = f.shape
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    rv = np.asarray(kwargs.pop("read_variance", 0.0), dtype=np.float64)
    rv_map = np.broadcast_to(rv, f.shape) if rv.ndim else None

    def run(sub, sub_bg, window=(slice(None), slice(None))):
        cor = cache.get(sub.shape)
        if cor is None:
            cor = cache[sub.shape] = Correlator(templates, sub.shape)
        sub_rv = rv if rv_map is None else rv_map[window]
        return frame_pursuit(sub, sub_bg, templates, correlator=cor, read_variance=sub_rv, **kwargs)

    if rows * cols <= max_pixels:
        return run(f, bg)

    def run_window(window: tuple[slice, slice]) -> NDArray:
        return run(f[window], bg[window], window).as_array().reshape(-1, 4)

    px = templates.pixel_size
    return Emitters.from_array(in_tiles(run_window, f.shape, px, core, templates.images.shape[-1]))


def in_tiles(run, shape: tuple[int, int], pixel_size: float, core: int, margin: int) -> NDArray:
    """Emitters (K, 4) of a large frame found tile by tile: ``run(window)`` finds those of
    the frame's pixels ``window`` (a pair of slices) in the window's coordinates (nm); each
    tile's core of ``core`` pixels is searched with ``margin`` pixels around it and keeps the
    emitters inside the core. The tiles at the far edges are shifted inwards so that every
    tile has the same shape."""
    rows, cols = shape
    px = pixel_size
    wr, wc = min(rows, core + 2 * margin), min(cols, core + 2 * margin)
    parts = [np.zeros((0, 4))]
    for r0 in range(0, rows, core):
        for c0 in range(0, cols, core):
            r1, c1 = min(r0 + core, rows), min(c0 + core, cols)
            ra = int(np.clip(r0 - margin, 0, rows - wr))
            ca = int(np.clip(c0 - margin, 0, cols - wc))
            e = np.array(run((slice(ra, ra + wr), slice(ca, ca + wc))), dtype=np.float64)
            e = e.reshape(-1, 4)
            e[:, 0] += ca * px
            e[:, 1] += ra * px
            inside = (e[:, 0] >= c0 * px) & (e[:, 0] < c1 * px)
            inside &= (e[:, 1] >= r0 * px) & (e[:, 1] < r1 * px)
            parts.append(e[inside])
    return np.vstack(parts)
