"""Measured PSF: a 3D cubic B-spline through a calibrated z-stack (Babcock & Zhuang 2017).

The stack holds the pixel-integrated image of one emitter at the centre of its ROI for each
z plane, at the camera's pixel size, normalised to one photon per plane. The model is the
tensor-product cubic B-spline interpolant of that stack: continuous in x, y and z, with
analytic derivatives, exact at the stack's samples.

Why not ``scipy.ndimage.map_coordinates``: every pixel of a window sees the *same* sub-pixel
fraction of the emitter's shift, so the spline weights along x and y are four numbers per
emitter, shared by all pixels. An image is then a weighted sum of four planes (z), of four
shifted columns (x) and of four shifted rows (y): three cheap gathers, and the derivatives
come from the same gathers with derivative weights. This is tens of times faster than a
per-pixel evaluation and gives d/dx, d/dy, d/dz for free.

The model is tied to its pixel size: asking for another pixel size is an error, since a
pixel-integrated image cannot be re-binned exactly.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import time

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..engine import kernels
from ._spline_kernel import spline_images
from .base import PSFBase, check_pixel_size, energy_radius

__all__ = ["SplinePSF", "bspline_terms", "bspline_weights", "table_coords"]

log = logging.getLogger(__name__)

_TABLE_PLANES = 16  # planes rendered at once by SplinePSF.from_model
_Z_EXTRA = 3  # planes tabulated beyond a model's z range (see SplinePSF.from_model)
_PAD = 3  # zero pixels around the stack so the spline falls smoothly to zero at the ROI edge


def bspline_terms(f):
    """The eight numbers of :func:`bspline_weights` (four weights, four derivatives) at ``f``.

    Arithmetic only, so the same source serves NumPy arrays, PyTorch tensors and numba
    scalars (:mod:`sparseloc.psf._spline_numba` compiles it): one definition of the spline.
    """
    g = 1.0 - f
    f2 = f * f
    f3 = f2 * f
    return (
        g * g * g / 6.0,
        (3.0 * f3 - 6.0 * f2 + 4.0) / 6.0,
        (-3.0 * f3 + 3.0 * f2 + 3.0 * f + 1.0) / 6.0,
        f3 / 6.0,
        -(g * g) / 2.0,
        (3.0 * f2 - 4.0 * f) / 2.0,
        (-3.0 * f2 + 2.0 * f + 1.0) / 2.0,
        f2 / 2.0,
    )


def bspline_weights(f: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Cubic B-spline weights of the four neighbours ``i-1, i, i+1, i+2`` at fraction ``f``.

    Parameters
    ----------
    f : ndarray, shape (K,)
        Fractional position in [0, 1) between node ``i`` and ``i + 1``.

    Returns
    -------
    w, dw : ndarray, shape (K, 4)
        Weights and their derivatives with respect to ``f``.
    """
    t = bspline_terms(np.asarray(f, dtype=np.float64))
    return np.stack(t[:4], axis=-1), np.stack(t[4:], axis=-1)


def table_coords(geo, x, y, z, ox=0.0, oy=0.0):
    """Fractional plane index ``tz`` and the position ``(tx, ty)`` of pixel (0, 0)'s centre in
    padded-stack nodes, from :meth:`SplinePSF.node_geometry` (window corners ``ox, oy`` nm
    added to the geometry's own). Arithmetic and ``clip`` only: NumPy arrays and PyTorch
    tensors both work, and the compiled fit repeats the same expressions."""
    tz = ((z - geo[6]) / geo[7]).clip(0.0, geo[8])
    tx = geo[0] + ((ox + geo[4]) - x) * geo[2] / geo[3]
    ty = geo[1] + ((oy + geo[5]) - y) * geo[2] / geo[3]
    return tz, tx, ty


class SplinePSF(PSFBase):
    """PSF from a measured (or simulated) z-stack, interpolated by a cubic B-spline.

    Parameters
    ----------
    stack : ndarray, shape (Nz, R, C)
        Image of one emitter per plane (any scale; each plane is normalised to sum to one
        photon unless ``normalise=False``). The emitter sits at the centre of the ROI: at
        column ``(C - 1) / 2`` and row ``(R - 1) / 2`` in pixel-centre coordinates unless
        ``centre`` says otherwise.
    pixel_size : float
        Pixel size (nm) the stack was recorded at; the model only renders at this size.
    z : array_like, shape (Nz,)
        Evenly spaced plane positions (nm), increasing.
    z_range : (float, float), optional
        Valid axial range (nm); default the stack's span.
    centre : (float, float), optional
        Emitter position (row, col) in the stack's pixel-centre coordinates.
    name : str
        Label for plots and files.
    normalise : bool
        Scale every plane to a sum of one photon.
    oversample : int
        Lateral samples per pixel of the stack: ``stack[:, i, j]`` is the pixel value at an
        offset of ``(j - centre_col) / oversample`` pixels between pixel centre and emitter.
        A bead stack has 1; a table of a theoretical model may use 2-3 to cut the
        interpolation error (cubic: about 2^4 less per doubling).
    """

    def __init__(
        self,
        stack: ArrayLike,
        pixel_size: float,
        z: ArrayLike,
        *,
        z_range: tuple[float, float] | None = None,
        centre: tuple[float, float] | None = None,
        name: str = "spline",
        normalise: bool = True,
        oversample: int = 1,
    ) -> None:
        super().__init__()
        from scipy.ndimage import spline_filter

        s = np.asarray(stack, dtype=np.float64)
        if s.ndim != 3:
            raise ValueError(
                f"a spline PSF needs a (planes, rows, cols) stack, got shape {s.shape}"
            )
        if s.shape[0] < 4 or min(s.shape[1:]) < 5:
            raise ValueError(
                f"a spline PSF needs at least 4 planes of 5x5 pixels, got shape {s.shape}"
            )
        if not np.all(np.isfinite(s)):
            raise ValueError("the PSF stack contains NaN or inf values")
        zz = np.asarray(z, dtype=np.float64).ravel()
        if zz.size != s.shape[0]:
            raise ValueError(f"z has {zz.size} values but the stack has {s.shape[0]} planes")
        dz = np.diff(zz)
        if np.any(dz <= 0):
            raise ValueError("the z positions of the stack must increase")
        if np.ptp(dz) > 1e-3 * dz.mean():
            raise ValueError("the z positions of the stack must be evenly spaced; resample first")
        self.pixel_size = check_pixel_size(pixel_size)
        self.oversample = int(oversample)
        if self.oversample < 1:
            raise ValueError(f"oversample must be a positive integer, got {oversample}")
        if normalise:
            # Each pixel of an image is sampled oversample^2 times (once per phase).
            sums = s.sum(axis=(1, 2), keepdims=True) / self.oversample**2
            if np.any(sums <= 0):
                raise ValueError("every plane of the PSF stack must hold a positive total")
            s = s / sums
        self.stack = s
        self.z = zz
        self.z_step = float(dz.mean())
        self.name = name
        _, nr, nc = s.shape
        self.centre = (
            ((nr - 1) / 2.0, (nc - 1) / 2.0) if centre is None else tuple(map(float, centre))
        )
        lo, hi = float(zz[0]), float(zz[-1])
        if z_range is None:
            self._z_range = (lo, hi)
        else:
            zr = (float(z_range[0]), float(z_range[1]))
            if not (lo - 1e-6 <= zr[0] < zr[1] <= hi + 1e-6):
                raise ValueError(
                    f"z_range {zr} must lie within the stack's span [{lo:.1f}, {hi:.1f}] nm"
                )
            self._z_range = zr
        padded = np.pad(s, ((0, 0), (_PAD, _PAD), (_PAD, _PAD)))
        coef = spline_filter(padded, order=3, mode="mirror")
        # Mirror one plane at each z end (the filter's boundary condition) and append one zero
        # row and column: gathers send every out-of-ROI index there.
        coef = np.concatenate([coef[1:2], coef, coef[-2:-1]], axis=0)
        coef = np.pad(coef, ((0, 0), (0, 1), (0, 1)))
        self._coef = coef
        self._ny = nr + 2 * _PAD
        self._nx = nc + 2 * _PAD

    def within(self, z_range: tuple[float, float] | None) -> SplinePSF:
        """This table with its valid z range narrowed to ``z_range`` (nm): a shallow copy
        that renders the same images (a table's images depend on its planes, not on its
        range), so that the fits and dictionaries, which read ``z_range``, stay inside it.
        The table itself where ``z_range`` is None or its own.

        Raises
        ------
        ValueError
            Where ``z_range`` is not an increasing pair within the table's range.
        """
        if z_range is None:
            return self
        lo, hi = self.z_range
        zr = (float(z_range[0]), float(z_range[1]))
        if zr == (lo, hi):
            return self
        tol = 1e-9 * max(1.0, abs(lo), abs(hi))
        if not (lo - tol <= zr[0] < zr[1] <= hi + tol):
            raise ValueError(
                f"the z range [{zr[0]:.1f}, {zr[1]:.1f}] nm must be an increasing pair within "
                f"the PSF model's [{lo:.1f}, {hi:.1f}] nm"
            )
        narrowed = copy.copy(self)
        narrowed._z_range = zr
        return narrowed

    def __repr__(self) -> str:
        nz, nr, nc = self.stack.shape
        return (
            f"SplinePSF(name={self.name!r}, planes={nz}, roi={nr}x{nc}, "
            f"pixel_size={self.pixel_size}, z_range={self.z_range})"
        )

    @classmethod
    def from_model(
        cls,
        model,
        pixel_size: float,
        *,
        roi: int,
        z_step: float = 10.0,
        z_range: tuple[float, float] | None = None,
        oversample: int = 2,
        cache: bool = True,
    ) -> SplinePSF:
        """Tabulate any model (e.g. a pupil model) as a spline: the same images, much faster.

        The model is rendered once, at its ROI centre, on planes ``z_step`` apart; the spline
        then interpolates between planes and pixel shifts (errors of ~1 % of the peak at
        100 nm pixels for a double helix). Photon scale is the model's (no per-plane
        normalisation), so photon counts keep their meaning. Rendering a pupil model's table
        takes seconds: it is logged, and the table is kept in a disk cache keyed by the
        model's content hash and the table's parameters (:mod:`sparseloc.psf.cache`), from
        which later calls read it. The table keeps the model as its ``source`` (its light
        beyond the table: :mod:`sparseloc.solvers.halo`) and the model's ``model_error`` and
        ``error_table`` where it has them (a calibrated pupil's error on its beads).

        Parameters
        ----------
        model : PSFModel
            The model to tabulate.
        pixel_size : float
            Pixel size (nm); the table only renders at this size.
        roi : int
            Side (px) of the tabulated image; emitters more than ``roi / 2`` pixels from a
            pixel contribute nothing to it. Use at least twice the window size.
        z_step : float
            Plane spacing (nm).
        z_range : (float, float), optional
            Default the model's.
        oversample : int
            Lateral samples per pixel (2: errors ~0.3 % of the peak for a double helix at
            160 nm pixels, against ~5 % with 1).
        cache : bool
            Read the table from the disk cache, or save it there once rendered.
        """
        px = check_pixel_size(pixel_size)
        lo, hi = model.z_range if z_range is None else z_range
        mlo, mhi = model.z_range
        if not (mlo - 1e-6 <= lo < hi <= mhi + 1e-6):
            raise ValueError(
                f"z_range ({lo:g}, {hi:g}) nm must lie within the model's ({mlo:g}, {mhi:g}) nm"
            )
        zs, render = _table_planes(model, lo, hi, z_step)
        roi = int(roi) | 1
        s = int(oversample)
        stack = _cached_table(model, render, zs, roi, px, s) if cache else None
        if stack is None:
            stack = _render_table(render, zs, roi, px, s)
        centre = (float(s * (roi // 2)), float(s * (roi // 2)))
        out = cls(
            stack,
            px,
            zs,
            centre=centre,
            z_range=(lo, hi),
            name=f"{getattr(model, 'name', 'psf')}",
            normalise=False,
            oversample=s,
        )
        out.source = model
        # a table of a calibrated model errs as that model does on its beads (its
        # ``model_error`` and ``error_table``, where it has them)
        for attr in ("model_error", "error_table"):
            if getattr(model, attr, None) is not None:
                setattr(out, attr, getattr(model, attr))
        return out

    @property
    def pixel_centre(self) -> tuple[float, float]:
        """The emitter's position (row, col) in pixels of the stack's frame: ``centre`` over
        ``oversample`` (an image of ``stack.shape / oversample`` pixels holds it there)."""
        return (self.centre[0] / self.oversample, self.centre[1] / self.oversample)

    @property
    def content_hash(self) -> str:
        """SHA-256 (16 hex digits) of the stack, z and pixel size: identifies a calibration."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.stack, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.z, dtype="<f8").tobytes())
        h.update(np.float64(self.pixel_size).tobytes())
        h.update(np.array([*self.centre, self.oversample], dtype="<f8").tobytes())
        return h.hexdigest()[:16]

    def _check_pixel(self, pixel_size: float) -> None:
        if abs(pixel_size - self.pixel_size) > 1e-3 * self.pixel_size:
            raise ValueError(
                f"this PSF was calibrated at {self.pixel_size:g} nm pixels but "
                f"{pixel_size:g} nm was asked for; calibrate at the data's pixel size"
            )

    def _axis(self, t: NDArray[np.float64], n: int, length: int, nodes: int, stride: int = 1):
        """Indices (K, n, 4) into an axis of ``nodes`` coefficients (+1 zero) and weights.

        Pixel ``j`` sits at knot ``t + stride * j``: the same fraction for every pixel.
        """
        i0 = np.floor(t)
        w, dw = bspline_weights(t - i0)
        idx = (
            i0.astype(np.int64)[:, None, None]
            + stride * np.arange(n)[None, :, None]
            + np.arange(-1, 3)
        )
        idx = np.where((idx >= 0) & (idx < nodes), idx, length - 1)
        return idx, w, dw

    def node_geometry(self, origin: tuple[float, float], pixel_size: float) -> NDArray[np.float64]:
        """Where a window sits in the coefficient table: the nine numbers
        ``(col of the stack centre, its row, oversample, pixel size, x and y (nm) of pixel
        (0, 0)'s centre, z of plane 0, plane step, largest plane index)``.

        :meth:`node_coords` turns them into table coordinates; the compiled fit
        (:mod:`sparseloc.solvers._fit_numba`) reads the same array.
        """
        p = float(pixel_size)
        return np.array(
            [
                self.centre[1] + _PAD,
                self.centre[0] + _PAD,
                float(self.oversample),
                p,
                float(origin[0]) + 0.5 * p,
                float(origin[1]) + 0.5 * p,
                float(self.z[0]),
                self.z_step,
                self.stack.shape[0] - 1 - 1e-9,
            ]
        )

    def node_coords(self, x, y, z, origin: tuple[float, float], pixel_size: float):
        """Table coordinates ``(tz, tx, ty)`` of K emitters on a window (see
        :func:`table_coords`)."""
        return table_coords(self.node_geometry(origin, pixel_size), x, y, z)

    def _images(self, x, y, z, shape, pixel_size, origin, derivatives):
        self._check_pixel(pixel_size)
        rows, cols = shape
        p = pixel_size
        k = len(x)
        # z: fractional plane index; the coefficient array has one mirrored plane in front.
        tz, tx, ty = self.node_coords(x, y, z, origin, p)
        os_ = self.oversample
        kern = kernels()
        if kern is not None:
            out, raw = spline_images(
                kern.spline, self._coef, tz, tx, ty, (rows, cols), os_, derivatives
            )
            if not derivatives:
                return out
            raw[:, :2] *= -os_ / p
            raw[:, 2] /= self.z_step
            return out, raw
        iz = np.floor(tz).astype(np.int64)
        wz, dwz = bspline_weights(tz - iz)
        ix, wx, dwx = self._axis(tx, cols, self._nx + 1, self._nx, os_)
        iy, wy, dwy = self._axis(ty, rows, self._ny + 1, self._ny, os_)
        out = np.empty((k, rows, cols))
        der = np.empty((k, 3, rows, cols)) if derivatives else None
        chunk = max(1, int(4e7 // (self._coef[0].size * 8 * 4)))
        for s0 in range(0, k, chunk):
            sl = slice(s0, min(s0 + chunk, k))
            kk = np.arange(sl.stop - sl.start)
            planes = self._coef[iz[sl, None] + np.arange(4)]  # (k, 4, Ny+1, Nx+1)
            pz = np.einsum("km,kmyx->kyx", wz[sl], planes)
            # Gather columns: (k, cols, 4, Ny+1) then weight along the 4 neighbours.
            gx = pz[kk[:, None, None], :, ix[sl]]
            a = np.einsum("kcmy,km->kyc", gx, wx[sl])
            gy = a[kk[:, None, None], iy[sl]]  # (k, rows, 4, cols)
            out[sl] = np.einsum("krmc,km->krc", gy, wy[sl])
            if derivatives:
                ax = np.einsum("kcmy,km->kyc", gx, dwx[sl])
                der[sl, 0] = (
                    -np.einsum("krmc,km->krc", ax[kk[:, None, None], iy[sl]], wy[sl]) * os_ / p
                )
                der[sl, 1] = -np.einsum("krmc,km->krc", gy, dwy[sl]) * os_ / p
                dpz = np.einsum("km,kmyx->kyx", dwz[sl], planes)
                az = np.einsum("kcmy,km->kyc", dpz[kk[:, None, None], :, ix[sl]], wx[sl])
                der[sl, 2] = (
                    np.einsum("krmc,km->krc", az[kk[:, None, None], iy[sl]], wy[sl]) / self.z_step
                )
        if derivatives:
            return out, der
        return out

    def zero_beyond(self, pixel_size: float) -> tuple[float, float]:
        """Distances (nm; rows' axis, columns' axis) from the emitter beyond which a pixel
        centre gets exactly zero light: the coefficient table ends there.

        The frame solver sums neighbours' light from one image per emitter over this box
        instead of rendering all of them into every window (the same values).
        """
        px = check_pixel_size(pixel_size)
        self._check_pixel(px)
        os_ = self.oversample
        out = []
        for centre, n in ((self.centre[0], self._ny), (self.centre[1], self._nx)):
            c = centre + _PAD  # the emitter's node
            # node coordinate t reads coefficients floor(t) - 1 .. floor(t) + 2, all zero
            # unless -2 <= t < n + 1
            out.append((max(c + 2.0, n + 1.0 - c) / os_) * px)
        return out[0], out[1]

    def roi_half(self, pixel_size: float) -> float:
        """Distance (nm) from the emitter to the nearest edge of the stack the table was
        made from (its ROI): beyond it the table holds no data, only its taper to zero."""
        px = check_pixel_size(pixel_size)
        self._check_pixel(px)
        ny, nx = self._ny - 2 * _PAD, self._nx - 2 * _PAD
        (cy, cx), os_ = self.centre, self.oversample
        return min(cy, ny - 1 - cy, cx, nx - 1 - cx) / os_ * px

    def support_radius(
        self,
        pixel_size: float,
        fraction: float = 0.95,
        *,
        z_range: tuple[float, float] | None = None,
    ) -> float:
        """Radius (nm) holding ``fraction`` of each plane's photons (largest over planes).

        Computed from the stack itself (which holds all of the model's photons), at the
        calibrated pixel size.
        """
        px = check_pixel_size(pixel_size)
        self._check_pixel(px)
        if not 0 < fraction <= 1:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        lo, hi = self.z_range if z_range is None else z_range
        sel = (self.z >= lo - 1e-6) & (self.z <= hi + 1e-6)
        planes = self.stack[sel] if sel.any() else self.stack
        nr, nc = self.stack.shape[1:]
        rr = (np.arange(nr) - self.centre[0])[:, None]
        cc = (np.arange(nc) - self.centre[1])[None, :]
        r = np.hypot(rr, cc).ravel() * px / self.oversample
        return energy_radius(planes, r, fraction) + px


def _table_planes(model, lo: float, hi: float, z_step: float):
    """The planes (nm) to tabulate ``model`` on, ``z_step`` apart over ``[lo, hi]``, and the
    function that renders them.

    The spline's z boundary mirrors the end planes, which zeroes d/dz at the range's ends
    (and is 27 % off one plane in): a fit starting there cannot move. Models that render
    beyond their range (all of this package's) get _Z_EXTRA planes more at each end.
    """
    n = max(4, int(np.ceil((hi - lo) / z_step)) + 1)
    zs = np.linspace(lo, hi, n)
    render = model.images
    if isinstance(model, PSFBase) and not isinstance(model, SplinePSF):
        dz = zs[1] - zs[0]
        below = lo - dz * np.arange(_Z_EXTRA, 0, -1)
        below = below[model.renders_beyond_range(below)]
        zs = np.concatenate([below, zs, hi + dz * np.arange(1, _Z_EXTRA + 1)])

        def render(x, y, z, shape, pixel_size):
            return model._images(x, y, z, shape, pixel_size, (0.0, 0.0), False)

    return zs, render


def _cached_table(model, render, zs: NDArray[np.float64], roi: int, px: float, s: int) -> NDArray:
    """The table's stack from the disk cache, or rendered (logged: a pupil model takes
    seconds) and saved there."""
    from . import cache

    key = cache.table_key(model, px, zs, roi, s)
    name = str(getattr(model, "name", "psf"))
    path = cache.table_path(key, name)
    stack = cache.load_table(path, key, zs, (zs.size, roi * s, roi * s))
    if stack is not None:
        log.debug("read the spline table of the PSF model %r from the cache: %s", name, path)
        return stack
    log.info(
        "tabulating the PSF model %r as a spline table (%d planes of %dx%d px); this is done "
        "once (seconds for a pupil model) and kept in the cache folder %s",
        name,
        zs.size,
        roi,
        roi,
        path.parent,
    )
    t0 = time.perf_counter()
    stack = _render_table(render, zs, roi, px, s)
    if cache.save_table(path, key, zs, stack):
        log.info("tabulated in %.0f s; saved as %s", time.perf_counter() - t0, path)
    return stack


def _render_table(render, zs: NDArray[np.float64], roi: int, px: float, s: int) -> NDArray:
    """The stack (planes, roi * s, roi * s) of an emitter at the centre of pixel ``roi // 2``
    on planes ``zs``, ``s`` lateral phases per pixel interleaved."""
    n = zs.size
    c = roi * px / 2.0  # the centre of pixel roi // 2
    stack = np.empty((n, roi * s, roi * s))
    for a in range(s):  # x phase: the emitter moves left by a/s px, offsets grow by a/s
        for b in range(s):
            # A pupil model works on large complex fields per plane: render a few planes
            # at a time to bound the memory.
            for z0 in range(0, n, _TABLE_PLANES):
                z1 = min(z0 + _TABLE_PLANES, n)
                k = z1 - z0
                stack[z0:z1, b::s, a::s] = render(
                    np.full(k, c - a * px / s),
                    np.full(k, c - b * px / s),
                    zs[z0:z1],
                    (roi, roi),
                    px,
                )
    return stack
