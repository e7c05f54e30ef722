"""Overcomplete dictionaries of shifted PSFs, stored by their structure.

An atom is the unit-photon image, in a window of ``rows x cols`` pixels, of an emitter at one
point of a 3D grid (transverse step ``dxy``, axial step ``dz``). With ``s = pixel_size / dxy``
an integer, the grid point ``i = (q + margin) * s + p`` along x lies at sub-pixel phase ``p`` of
pixel ``q``; every atom with the same (phase_y, phase_x, z) is the same *template* shifted by a
whole number of pixels. So the dictionary stores ``nz * s * s`` templates on a canvas of
``(2*rows - 1 + 2*margin) x (2*cols - 1 + 2*margin)`` pixels and each atom is a crop of one of
them. The paper's fine dictionary (1,270,016 atoms) is 10,496 templates of 21 x 21 pixels:
37 MB instead of the 1.2 GB dense matrix.

Both operators are cross-correlations of a window-sized array with the templates, done for all
templates at once with FFTs of the canvas size (no wrap-around: the valid part of a circular
correlation of a W-array with a (2W-1)-template is exact):

- ``rmatvec(image)[t, a]  = sum_r image[r] * T_t[r + a]``  (correlation with every atom)
- ``matvec(coef)[r]       = sum_t sum_a g_t[a] * T_t[r + a]`` with ``g`` the coefficients
  reordered by template and reversed shift.

Coefficients are in photons (atoms are unit-photon images, not unit-norm); ``norms`` gives each
atom's Euclidean norm for normalised correlations.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray

from .psf.base import PSFModel, check_pixel_size, check_shape

log = logging.getLogger(__name__)

__all__ = [
    "DenseDictionary",
    "Dictionary",
    "check_window",
    "dictionary_memory",
]

DEFAULT_MAX_MEMORY = 4 * 1024**3  # bytes
#: An emitter at the window centre must leave at least this fraction of its photons in the window.
MIN_WINDOW_FRACTION = 0.3


def _grid_counts(
    shape: tuple[int, int],
    pixel_size: float,
    dxy: float,
    dz: float,
    z_range: tuple[float, float],
    margin: int,
) -> tuple[int, int, int, int]:
    ratio = pixel_size / dxy
    s = round(ratio)
    if s < 1 or abs(ratio - s) > 1e-6 * ratio:
        raise ValueError(
            f"pixel_size / dxy must be a whole number (got {pixel_size:g} / {dxy:g} = {ratio:.4g})"
        )
    if dz <= 0:
        raise ValueError(f"dz must be > 0 nm, got {dz}")
    span = z_range[1] - z_range[0]
    if span < 0:
        raise ValueError(f"z_range must be (z_min, z_max) with z_min <= z_max, got {z_range}")
    nz = math.floor(span / dz + 1e-9) + 1
    rows, cols = shape
    return s, nz, (rows + 2 * margin) * s, (cols + 2 * margin) * s


def dictionary_memory(
    shape: tuple[int, int] | int,
    pixel_size: float,
    dxy: float,
    dz: float,
    z_range: tuple[float, float],
    *,
    margin: int = 0,
    batch: int = 1,
) -> int:
    """Bytes a structured :class:`Dictionary` needs (templates, their spectra, one correlation).

    Parameters
    ----------
    shape : int or (rows, cols)
        Window in pixels.
    pixel_size, dxy, dz : float
        Pixel size, transverse and axial grid steps (nm).
    z_range : (float, float)
        Axial extent of the grid (nm).
    margin : int
        Extra pixels of grid on each side of the window.
    batch : int
        Windows correlated at once (the correlation output grows with it).
    """
    shp = check_shape((shape, shape) if np.isscalar(shape) else shape)
    s, nz, ny, nx = _grid_counts(shp, pixel_size, dxy, dz, z_range, margin)
    cr, cc = 2 * shp[0] - 1 + 2 * margin, 2 * shp[1] - 1 + 2 * margin
    n_t = nz * s * s
    templates = n_t * cr * cc * 8
    spectra = n_t * cr * (cc // 2 + 1) * 16
    out = batch * nz * ny * nx * 8 * 2  # correlation result and its reordering
    return int(templates + spectra + out + spectra * batch)


def check_window(window: ArrayLike, shape: tuple[int, int] | None = None) -> NDArray[np.float64]:
    """Validate an image window: 2-D (or a stack of 2-D), finite, of the expected shape."""
    arr = np.asarray(window, dtype=np.float64)
    if arr.ndim not in (2, 3):
        raise ValueError(f"a window must be a 2-D image (rows, cols), got {arr.ndim} dimension(s)")
    if shape is not None and arr.shape[-2:] != tuple(shape):
        raise ValueError(f"the window is {arr.shape[-2:]} pixels; the dictionary expects {shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("the window contains NaN or inf values")
    return arr


@dataclass(frozen=True)
class GridSpec:
    """Positions (nm) of the dictionary's grid: ``x[ix]``, ``y[iy]``, ``z[iz]``."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    dxy: float
    dz: float

    @property
    def shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx)."""
        return self.z.size, self.y.size, self.x.size

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def positions(self, index: ArrayLike) -> NDArray[np.float64]:
        """(x, y, z) nm of flat atom indices, shape (n, 3)."""
        iz, iy, ix = np.unravel_index(np.asarray(index, dtype=np.int64), self.shape)
        return np.stack([self.x[ix], self.y[iy], self.z[iz]], axis=-1)


class Dictionary:
    """Structured dictionary of a PSF model on a 3D grid covering a window.

    Parameters
    ----------
    model : PSFModel
        Any PSF model (pupil, analytic, calibrated).
    shape : int or (rows, cols)
        Window size in pixels.
    pixel_size : float
        Pixel size (nm).
    dxy : float
        Transverse grid step (nm); ``pixel_size / dxy`` must be a whole number.
    dz : float
        Axial grid step (nm).
    z_range : (float, float), optional
        Axial extent of the grid (nm); default: the model's range. Planes are
        ``z_min, z_min + dz, ...`` up to ``z_max``.
    margin : int
        Extend the grid this many pixels beyond each window edge (emitters just outside the
        window still shine into it).
    origin : (float, float)
        Position (nm) of the window's outer corner, x then y.
    max_memory : int
        Refuse (``ValueError``) to build a dictionary whose :func:`dictionary_memory` exceeds
        this many bytes.

    Notes
    -----
    Grid positions: ``x_i = origin_x - margin * pixel_size + (i + 0.5) * dxy`` (same for y),
    ``z_k = z_min + k * dz``. Coefficient arrays have shape ``(nz, ny, nx)``; flat indices
    follow C order over that shape.
    """

    def __init__(
        self,
        model: PSFModel,
        shape: int | tuple[int, int],
        pixel_size: float,
        dxy: float,
        dz: float,
        z_range: tuple[float, float] | None = None,
        *,
        margin: int = 0,
        origin: tuple[float, float] = (0.0, 0.0),
        max_memory: int = DEFAULT_MAX_MEMORY,
    ) -> None:
        shp = check_shape((shape, shape) if np.isscalar(shape) else shape)
        px = check_pixel_size(pixel_size)
        if dxy <= 0:
            raise ValueError(f"dxy must be > 0 nm, got {dxy}")
        if margin < 0:
            raise ValueError(f"margin must be >= 0 pixels, got {margin}")
        zr = model.z_range if z_range is None else (float(z_range[0]), float(z_range[1]))
        lo, hi = model.z_range
        if zr[0] < lo - 1e-9 or zr[1] > hi + 1e-9:
            raise ValueError(
                f"z_range {zr} nm lies outside the model's valid range [{lo:g}, {hi:g}] nm"
            )
        s, nz, ny, nx = _grid_counts(shp, px, dxy, dz, zr, margin)
        need = dictionary_memory(shp, px, dxy, dz, zr, margin=margin)
        if need > max_memory:
            raise ValueError(
                f"the dictionary ({nz * ny * nx:,} atoms) needs {need / 1024**3:.2f} GB, more "
                f"than max_memory = {max_memory / 1024**3:.2f} GB; use a coarser grid, a smaller "
                f"window or raise max_memory"
            )
        self.model = model
        self.shape = shp
        self.pixel_size = px
        self.margin = int(margin)
        self.origin = (float(origin[0]), float(origin[1]))
        self.s = s
        rows, cols = shp
        ox = self.origin[0] - margin * px
        oy = self.origin[1] - margin * px
        zs = zr[0] + dz * np.arange(nz)
        self.grid = GridSpec(
            x=ox + (np.arange(nx) + 0.5) * dxy,
            y=oy + (np.arange(ny) + 0.5) * dxy,
            z=zs,
            dxy=float(dxy),
            dz=float(dz),
        )
        self._check_support(zs)
        # Canvas: an emitter at phase p of pixel q = 0 sees window pixel c at canvas column
        # c + cols - 1 + margin - q; q runs over [-margin, cols - 1 + margin].
        self.canvas = (2 * rows - 1 + 2 * margin, 2 * cols - 1 + 2 * margin)
        self.n_shift = (rows + 2 * margin, cols + 2 * margin)
        phase = (np.arange(s) + 0.5) * dxy
        corner = (
            -(cols - 1 + margin) * px + self.origin[0],
            -(rows - 1 + margin) * px + self.origin[1],
        )
        log.info("building %d templates (%d atoms)", nz * s * s, self.size)
        self.templates = self._render_templates(
            phase + self.origin[0], phase + self.origin[1], zs, corner
        )  # (nz, s, s, CR, CC): z, phase_y, phase_x
        self._spectra = sfft.rfft2(self.templates, axes=(-2, -1), workers=-1)
        self._norms: NDArray[np.float64] | None = None
        self._sums: NDArray[np.float64] | None = None
        self._qerr: float | None = None

    # -- construction ------------------------------------------------------------------------
    def _render_templates(self, px_pos, py_pos, zs, corner) -> NDArray[np.float64]:
        grid_fn = getattr(self.model, "images_on_grid", None)
        if grid_fn is not None:
            return grid_fn(px_pos, py_pos, zs, self.canvas, self.pixel_size, origin=corner)
        xx, yy = np.meshgrid(px_pos, py_pos)
        out = np.empty((zs.size, self.s, self.s, *self.canvas))
        for iz, z in enumerate(zs):
            imgs = self.model.images(
                xx.ravel(),
                yy.ravel(),
                np.full(xx.size, z),
                self.canvas,
                self.pixel_size,
                origin=corner,
            )
            out[iz] = imgs.reshape(self.s, self.s, *self.canvas)
        return out

    def _check_support(self, zs: NDArray[np.float64]) -> None:
        rows, cols = self.shape
        px = self.pixel_size
        zsel = zs[np.unique(np.linspace(0, zs.size - 1, min(zs.size, 5)).round().astype(int))]
        cx = self.origin[0] + cols * px / 2
        cy = self.origin[1] + rows * px / 2
        imgs = self.model.images(
            np.full(zsel.size, cx), np.full(zsel.size, cy), zsel, self.shape, px, origin=self.origin
        )
        frac = imgs.sum(axis=(1, 2))
        if frac.min() < MIN_WINDOW_FRACTION:
            worst = int(np.argmin(frac))
            raise ValueError(
                f"the {rows}x{cols} px window ({cols * px:.0f} x {rows * px:.0f} nm) is smaller "
                f"than the PSF: it holds only {100 * frac[worst]:.0f} % of a centred emitter's "
                f"photons at z = {zsel[worst]:.0f} nm (at least {100 * MIN_WINDOW_FRACTION:.0f} % "
                f"needed); use a larger window"
            )

    # -- structure ---------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Number of atoms."""
        return self.grid.size

    @property
    def coef_shape(self) -> tuple[int, int, int]:
        """(nz, ny, nx)."""
        return self.grid.shape

    def memory(self) -> int:
        """Bytes held by the templates and their spectra."""
        return int(self.templates.nbytes + self._spectra.nbytes)

    def _to_template_order(self, coef: NDArray) -> NDArray:
        """(..., nz, ny, nx) -> (..., nz, s, s, Ay, Ax) with shifts reversed (a = last - q)."""
        nz = self.grid.z.size
        ay, ax = self.n_shift
        c = coef.reshape(*coef.shape[:-3], nz, ay, self.s, ax, self.s)
        c = c[..., ::-1, :, ::-1, :]
        return np.moveaxis(c, (-4, -2), (-2, -1))  # (..., nz, py, px, a_y, a_x)

    def _from_template_order(self, corr: NDArray) -> NDArray:
        """Inverse of :meth:`_to_template_order`."""
        nz = self.grid.z.size
        c = np.moveaxis(corr, (-2, -1), (-4, -2))  # (..., nz, a_y, py, a_x, px)
        c = c[..., ::-1, :, ::-1, :]
        return np.ascontiguousarray(c).reshape(*corr.shape[:-5], nz, *self.grid.shape[1:])

    # -- operators ---------------------------------------------------------------------------
    def rmatvec(self, image: ArrayLike) -> NDArray[np.float64]:
        """Correlation of a window with every atom.

        Parameters
        ----------
        image : ndarray, shape (rows, cols) or (n, rows, cols)
            Window(s) in photons.

        Returns
        -------
        ndarray, shape (nz, ny, nx) or (n, nz, ny, nx)
            ``<atom, image>`` for every atom.
        """
        img = check_window(image, self.shape)
        batch = img.ndim == 3
        imgs = img if batch else img[None]
        fi = sfft.rfft2(imgs, s=self.canvas, axes=(-2, -1), workers=-1)
        ay, ax = self.n_shift
        out = np.empty((imgs.shape[0], *self.coef_shape))
        for b in range(imgs.shape[0]):
            prod = self._spectra * fi[b].conj()
            corr = sfft.irfft2(prod, s=self.canvas, axes=(-2, -1), workers=-1)[..., :ay, :ax]
            out[b] = self._from_template_order(corr)
        return out if batch else out[0]

    def matvec(self, coef: ArrayLike) -> NDArray[np.float64]:
        """Image (photons per pixel) ``sum_i coef_i * atom_i``.

        Parameters
        ----------
        coef : ndarray, shape (nz, ny, nx) or (size,)
            Coefficients in photons.

        Returns
        -------
        ndarray, shape (rows, cols)
        """
        c = np.asarray(coef, dtype=np.float64)
        if c.size != self.size:
            raise ValueError(f"coef has {c.size} values; the dictionary has {self.size} atoms")
        g = self._to_template_order(c.reshape(self.coef_shape))
        nz, s = self.grid.z.size, self.s
        cr, cc = self.canvas
        padded = np.zeros((nz, s, s, cr, cc))
        padded[..., : g.shape[-2], : g.shape[-1]] = g
        fg = sfft.rfft2(padded, axes=(-2, -1), workers=-1)
        total = (self._spectra * fg.conj()).sum(axis=(0, 1, 2))
        img = sfft.irfft2(total, s=self.canvas, workers=-1)
        return img[: self.shape[0], : self.shape[1]]

    def atoms(self, index: ArrayLike) -> NDArray[np.float64]:
        """Images of the atoms with the given flat indices: shape (n, rows, cols)."""
        idx = np.atleast_1d(np.asarray(index, dtype=np.int64))
        if np.any((idx < 0) | (idx >= self.size)):
            raise ValueError(f"atom indices must be in [0, {self.size})")
        iz, iy, ix = np.unravel_index(idx, self.coef_shape)
        py, qy = iy % self.s, iy // self.s
        px, qx = ix % self.s, ix // self.s
        rows, cols = self.shape
        # window pixel r sits at canvas row r + rows - 1 + margin - q = r + rows - 1 + 2m - (q + m)
        oy = rows - 1 + 2 * self.margin - qy
        ox = cols - 1 + 2 * self.margin - qx
        r = np.arange(rows)
        c = np.arange(cols)
        return self.templates[
            iz[:, None, None],
            py[:, None, None],
            px[:, None, None],
            oy[:, None, None] + r[None, :, None],
            ox[:, None, None] + c[None, None, :],
        ]

    @property
    def norms(self) -> NDArray[np.float64]:
        """Euclidean norm of every atom, shape (nz, ny, nx)."""
        if self._norms is None:
            sq = sfft.rfft2(self.templates**2, axes=(-2, -1), workers=-1)
            ones = sfft.rfft2(np.ones(self.shape), s=self.canvas, workers=-1)
            ay, ax = self.n_shift
            corr = sfft.irfft2(sq * ones.conj(), s=self.canvas, axes=(-2, -1), workers=-1)
            self._norms = np.sqrt(np.maximum(self._from_template_order(corr[..., :ay, :ax]), 0))
        return self._norms

    @property
    def sums(self) -> NDArray[np.float64]:
        """Sum of every atom's pixels (photons in the window per photon), shape (nz, ny, nx)."""
        if self._sums is None:
            self._sums = self.rmatvec(np.ones(self.shape))
        return self._sums

    def positions(self, index: ArrayLike) -> NDArray[np.float64]:
        """(x, y, z) in nm of flat atom indices, shape (n, 3)."""
        return self.grid.positions(index)

    def nearest_index(self, x: ArrayLike, y: ArrayLike, z: ArrayLike) -> NDArray[np.int64]:
        """Flat index of the grid atom nearest to each position (nm), clipped to the grid."""
        g = self.grid
        ix = np.clip(np.rint((np.asarray(x) - g.x[0]) / g.dxy).astype(int), 0, g.x.size - 1)
        iy = np.clip(np.rint((np.asarray(y) - g.y[0]) / g.dxy).astype(int), 0, g.y.size - 1)
        iz = np.clip(np.rint((np.asarray(z) - g.z[0]) / g.dz).astype(int), 0, g.z.size - 1)
        return np.ravel_multi_index((iz, iy, ix), self.coef_shape)

    def neighbourhood(self, k: int, reach: tuple[int, int]) -> NDArray[np.int64]:
        """Flat indices of the atoms within ``reach`` (lateral, axial) grid steps of atom k."""
        iz, iy, ix = np.unravel_index(k, self.coef_shape)
        nz, ny, nx = self.coef_shape
        rz = np.arange(max(iz - reach[1], 0), min(iz + reach[1] + 1, nz))
        ry = np.arange(max(iy - reach[0], 0), min(iy + reach[0] + 1, ny))
        rx = np.arange(max(ix - reach[0], 0), min(ix + reach[0] + 1, nx))
        zz, yy, xx = np.meshgrid(rz, ry, rx, indexing="ij")
        return np.ravel_multi_index((zz.ravel(), yy.ravel(), xx.ravel()), self.coef_shape)

    @property
    def quantization_error(self) -> float:
        """Relative error of the grid: the median of ``||image - a * best_atom|| / ||image||``
        over 24 random off-grid emitters in the window centre (seeded, computed once).

        The coarse paper grid (80 nm / 120 nm) leaves about 17 % of an emitter's signal norm
        unexplained, the fine one (10 nm / 15 nm) about 2 %. Stopping rules use it to tell
        grid mismatch from a missing emitter.
        """
        if self._qerr is None:
            rng = np.random.default_rng(12345)
            rows, cols = self.shape
            px = self.pixel_size
            g = self.grid
            n = 24
            x = self.origin[0] + rng.uniform(0.35, 0.65, n) * cols * px
            y = self.origin[1] + rng.uniform(0.35, 0.65, n) * rows * px
            z = rng.uniform(g.z[0], g.z[-1], n) if g.z.size > 1 else np.full(n, g.z[0])
            imgs = self.model.images(x, y, z, self.shape, px, origin=self.origin)
            # The best atom for an emitter is one of its grid neighbours: search the 3x3x3
            # grid points around it instead of correlating with the whole dictionary.
            nearest = self.nearest_index(x, y, z)
            rel = np.empty(n)
            for j in range(n):
                cand = self.neighbourhood(int(nearest[j]), (1, 1))
                atoms = self.atoms(cand).reshape(cand.size, -1)
                img = imgs[j].ravel()
                amp = atoms @ img / np.einsum("ij,ij->i", atoms, atoms)
                resid = np.linalg.norm(img[None] - amp[:, None] * atoms, axis=1)
                rel[j] = resid.min() / np.linalg.norm(img)
            self._qerr = float(np.median(rel))
        return self._qerr

    # -- dense and restricted views --------------------------------------------------------------
    def dense(self, index: ArrayLike | None = None, *, max_memory: int = 2 * 1024**3) -> NDArray:
        """Dense matrix (rows*cols, n) of all atoms or of the given flat indices.

        Raises ``ValueError`` if it would exceed ``max_memory`` bytes.
        """
        idx = np.arange(self.size) if index is None else np.asarray(index, dtype=np.int64)
        need = idx.size * self.shape[0] * self.shape[1] * 8
        if need > max_memory:
            raise ValueError(
                f"a dense matrix of {idx.size:,} atoms needs {need / 1024**3:.2f} GB "
                f"(max_memory {max_memory / 1024**3:.2f} GB)"
            )
        out = np.empty((self.shape[0] * self.shape[1], idx.size))
        for start in range(0, idx.size, 65536):
            part = idx[start : start + 65536]
            out[:, start : start + part.size] = self.atoms(part).reshape(part.size, -1).T
        return out

    def restrict(self, mask: ArrayLike) -> DenseDictionary:
        """Sub-dictionary of the atoms where ``mask`` (bool, shape (nz, ny, nx)) is true."""
        m = np.asarray(mask, dtype=bool)
        if m.shape != self.coef_shape:
            raise ValueError(f"mask has shape {m.shape}; expected {self.coef_shape}")
        idx = np.flatnonzero(m)
        return DenseDictionary(
            self.dense(idx),
            self.positions(idx),
            self.shape,
            index=idx,
            steps=(self.grid.dxy, self.grid.dz),
        )

    def box_mask(self, centres: ArrayLike, half_width: tuple[float, float, float]) -> NDArray:
        """Boolean mask (nz, ny, nx) of atoms within boxes ``|x - xc| <= hx`` etc. of any centre.

        Parameters
        ----------
        centres : ndarray, shape (k, 3)
            Box centres (x, y, z) in nm.
        half_width : (hx, hy, hz)
            Box half-widths in nm.
        """
        cen = np.atleast_2d(np.asarray(centres, dtype=np.float64))
        g = self.grid
        hx, hy, hz = half_width
        tol = 1e-6
        mask = np.zeros(self.coef_shape, dtype=bool)
        for xc, yc, zc in cen:
            mx = np.abs(g.x - xc) <= hx + tol
            my = np.abs(g.y - yc) <= hy + tol
            mz = np.abs(g.z - zc) <= hz + tol
            mask |= mz[:, None, None] & my[None, :, None] & mx[None, None, :]
        return mask


class DenseDictionary:
    """A dictionary held as a dense matrix (small or restricted dictionaries, and the reference).

    Parameters
    ----------
    matrix : ndarray, shape (rows*cols, n)
        Atoms as columns (unit-photon images, flattened in C order).
    positions : ndarray, shape (n, 3)
        (x, y, z) of each atom in nm.
    shape : (rows, cols)
        Window shape.
    index : ndarray, shape (n,), optional
        Flat indices of these atoms in a parent :class:`Dictionary`.
    steps : (dxy, dz), optional
        Grid steps (nm) of the atoms, used to group coefficients into emitters.
    """

    def __init__(
        self,
        matrix: NDArray,
        positions: NDArray,
        shape: tuple[int, int],
        *,
        index: NDArray | None = None,
        steps: tuple[float, float] | None = None,
    ) -> None:
        self.matrix = np.ascontiguousarray(matrix, dtype=np.float64)
        self.atom_positions = np.asarray(positions, dtype=np.float64)
        self.shape = check_shape(shape)
        if self.matrix.shape != (self.shape[0] * self.shape[1], len(self.atom_positions)):
            raise ValueError(
                f"matrix shape {self.matrix.shape} does not match {len(self.atom_positions)} "
                f"positions and a {self.shape} window"
            )
        self.index = index
        self.steps = steps
        self._norms = np.linalg.norm(self.matrix, axis=0)

    @classmethod
    def from_model(
        cls,
        model: PSFModel,
        positions: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> DenseDictionary:
        """Render every atom directly with the model (the reference path)."""
        pos = np.atleast_2d(np.asarray(positions, dtype=np.float64))
        imgs = model.images(pos[:, 0], pos[:, 1], pos[:, 2], shape, pixel_size, origin=origin)
        return cls(imgs.reshape(len(pos), -1).T, pos, shape)

    @property
    def size(self) -> int:
        return self.matrix.shape[1]

    @property
    def sums(self) -> NDArray[np.float64]:
        """Sum of every atom's pixels, shape (n,)."""
        return self.matrix.sum(axis=0)

    #: Relative grid error (see :attr:`Dictionary.quantization_error`); 0 unless set.
    quantization_error: float = 0.0

    @property
    def norms(self) -> NDArray[np.float64]:
        return self._norms

    def positions(self, index: ArrayLike) -> NDArray[np.float64]:
        return self.atom_positions[np.asarray(index, dtype=np.int64)]

    def rmatvec(self, image: ArrayLike) -> NDArray[np.float64]:
        """Correlations ``A.T @ image`` (image (rows, cols) or (n, rows, cols))."""
        img = check_window(image, self.shape)
        flat = img.reshape(*img.shape[:-2], -1)
        return flat @ self.matrix

    def matvec(self, coef: ArrayLike) -> NDArray[np.float64]:
        """Image ``A @ coef`` of shape (rows, cols)."""
        c = np.asarray(coef, dtype=np.float64).ravel()
        if c.size != self.size:
            raise ValueError(f"coef has {c.size} values; the dictionary has {self.size} atoms")
        return (self.matrix @ c).reshape(self.shape)

    def atoms(self, index: ArrayLike) -> NDArray[np.float64]:
        idx = np.atleast_1d(np.asarray(index, dtype=np.int64))
        return self.matrix[:, idx].T.reshape(idx.size, *self.shape)
