"""The PSF protocol every model satisfies, and shared helpers.

Units: positions in nm, photons in photons, images in expected photons per pixel.
Coordinates follow design.md: the window's outer corner of pixel (0, 0) sits at ``origin``
(default (0, 0)); the centre of pixel (r, c) is at ``x = origin_x + (c + 0.5) * pixel_size``,
``y = origin_y + (r + 0.5) * pixel_size``; ``x`` runs along columns, ``y`` along rows.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "PSFBase",
    "PSFModel",
    "ShiftedPSF",
    "as_emitters",
    "check_pixel_size",
    "check_shape",
    "light_radius",
    "parse_pair",
    "pixel_centres",
]

T = TypeVar("T")


@runtime_checkable
class PSFModel(Protocol):
    """What the dictionary, the solvers, the simulator and the CRLB need from a PSF.

    Every method takes emitter positions ``x, y, z`` (nm, arrays of shape ``(K,)``), a window
    ``shape = (rows, cols)`` and a ``pixel_size`` (nm), and an optional ``origin`` (nm, x then y)
    of the window's outer corner.
    """

    name: str

    @property
    def z_range(self) -> tuple[float, float]:
        """Valid axial range ``(z_min, z_max)`` in nm (inclusive)."""
        ...

    def images(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
        derivatives: bool = False,
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unit-photon images ``(K, rows, cols)``; with ``derivatives`` also ``(K, 3, rows, cols)``
        holding d/dx, d/dy, d/dz (per nm) of each unit-photon image."""
        ...

    def render(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        photons: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> NDArray[np.float64]:
        """Expected photons per pixel ``(rows, cols)`` of K emitters (no background)."""
        ...

    def gradients(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        photons: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> NDArray[np.float64]:
        """Derivatives ``(K, 4, rows, cols)`` of the rendered image with respect to each emitter's
        x, y, z (photons per pixel per nm) and photons (per photon)."""
        ...

    def support_radius(
        self,
        pixel_size: float,
        fraction: float = 0.95,
        *,
        z_range: tuple[float, float] | None = None,
    ) -> float:
        """Radius (nm) around the emitter that holds ``fraction`` of its image at the z of its
        widest image in ``z_range`` (default: the model's)."""
        ...


def check_pixel_size(pixel_size: float) -> float:
    """Return ``pixel_size`` as float or raise a ``ValueError`` naming it."""
    p = float(pixel_size)
    if not np.isfinite(p) or p <= 0:
        raise ValueError(f"pixel_size must be a positive number of nm, got {pixel_size!r}")
    return p


def parse_pair(value: Any, convert: Callable[[Any], T], error: str) -> tuple[T, T]:
    """``value`` as two items converted by ``convert``; ``ValueError(error)`` when it does not
    hold exactly two items or one of them does not convert."""
    try:
        a, b = (convert(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ValueError(error) from exc
    return a, b


def check_shape(shape: tuple[int, int]) -> tuple[int, int]:
    """Return a validated ``(rows, cols)`` window shape."""
    error = f"shape must be (rows, cols) of positive integers, got {shape!r}"
    rows, cols = parse_pair(shape, int, error)
    if rows <= 0 or cols <= 0:
        raise ValueError(error)
    return rows, cols


def as_emitters(
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    z_range: tuple[float, float] | None = None,
    photons: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], ...]:
    """Broadcast emitter parameters to 1-D float arrays of one length and validate them.

    Raises ``ValueError`` naming the argument when a value is not finite, a z lies outside
    ``z_range`` (nm) or a photon count is negative.
    """
    arrays = [np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (x, y, z)]
    if photons is not None:
        arrays.append(np.atleast_1d(np.asarray(photons, dtype=np.float64)))
    try:
        arrays = list(np.broadcast_arrays(*arrays))
    except ValueError as exc:
        raise ValueError("x, y, z (and photons) must have the same length") from exc
    names = ["x", "y", "z", "photons"]
    for name, arr in zip(names, arrays, strict=False):
        if arr.ndim != 1:
            raise ValueError(f"{name} must be a scalar or a 1-D array, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite (no NaN or inf)")
    if z_range is not None:
        z = arrays[2]
        lo, hi = z_range
        tol = 1e-9 * max(1.0, abs(lo), abs(hi))
        bad = (z < lo - tol) | (z > hi + tol)
        if np.any(bad):
            raise ValueError(
                f"z = {z[bad][0]:.1f} nm is outside the model's valid range [{lo:.1f}, {hi:.1f}] nm"
            )
    if photons is not None and np.any(arrays[3] < 0):
        raise ValueError("photons must be >= 0")
    return tuple(np.ascontiguousarray(a) for a in arrays)


def energy_radius(images: NDArray[np.float64], r: NDArray[np.float64], fraction: float) -> float:
    """Largest radius over ``images`` (K, rows, cols) holding ``fraction`` of each image's
    (positive) energy; ``r`` gives each pixel's distance from the emitter, flattened."""
    order = np.argsort(r)
    radius = 0.0
    for img in images:
        cum = np.cumsum(np.clip(img.ravel()[order], 0, None))
        idx = int(np.searchsorted(cum, fraction * cum[-1]))
        radius = max(radius, float(r[order[min(idx, r.size - 1)]]))
    return radius


def light_radius(
    model: PSFModel, pixel_size: float, z_range: tuple[float, float] | None = None
) -> int:
    """Radius (whole pixels) of the disc holding 90 % of an emitter's light at the z of its
    widest image in ``z_range`` (default: the model's; :meth:`PSFModel.support_radius`)."""
    return int(np.ceil(model.support_radius(pixel_size, 0.9, z_range=z_range) / pixel_size))


def pixel_centres(n: int, pixel_size: float, origin: float = 0.0) -> NDArray[np.float64]:
    """Centres (nm) of ``n`` pixels of size ``pixel_size`` starting at ``origin``."""
    return origin + (np.arange(n, dtype=np.float64) + 0.5) * pixel_size


class PSFBase:
    """Shared behaviour: ``render`` and ``gradients`` from ``images``; support radius.

    Subclasses implement ``_images(x, y, z, shape, pixel_size, origin, derivatives)`` on
    validated arrays and set ``name`` and ``_z_range``.
    """

    name: str = "psf"
    _z_range: tuple[float, float] = (-1000.0, 1000.0)

    def __init__(self) -> None:
        self._support_cache: dict[tuple, float] = {}

    @property
    def z_range(self) -> tuple[float, float]:
        return self._z_range

    # -- the one method subclasses provide -------------------------------------------------
    def _images(
        self,
        x: NDArray[np.float64],
        y: NDArray[np.float64],
        z: NDArray[np.float64],
        shape: tuple[int, int],
        pixel_size: float,
        origin: tuple[float, float],
        derivatives: bool,
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        raise NotImplementedError

    def renders_beyond_range(self, z: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which of these z (nm) outside the valid range the model can still render
        physically (used to tabulate a margin of planes); all of them unless a subclass
        knows better."""
        return np.ones(np.shape(z), dtype=bool)

    # -- public API ------------------------------------------------------------------------
    def images(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
        derivatives: bool = False,
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unit-photon images of K emitters.

        Parameters
        ----------
        x, y, z : array_like, shape (K,)
            Emitter positions in nm (x along columns, y along rows, z from focus).
        shape : (rows, cols)
            Window shape in pixels.
        pixel_size : float
            Pixel size in nm (sample space).
        origin : (float, float)
            Position (nm) of the window's outer corner of pixel (0, 0), x then y.
        derivatives : bool
            Also return derivatives with respect to x, y, z.

        Returns
        -------
        images : ndarray, shape (K, rows, cols)
            Expected photons per pixel for one photon per emitter.
        derivs : ndarray, shape (K, 3, rows, cols)
            Only with ``derivatives``: d/dx, d/dy, d/dz in photons per pixel per nm.
        """
        xs, ys, zs = as_emitters(x, y, z, self.z_range)
        return self._images(xs, ys, zs, *self._check_window(shape, pixel_size, origin), derivatives)

    @staticmethod
    def _check_window(
        shape: tuple[int, int], pixel_size: float, origin: tuple[float, float]
    ) -> tuple[tuple[int, int], float, tuple[float, float]]:
        ox, oy = (float(o) for o in origin)
        if not (np.isfinite(ox) and np.isfinite(oy)):
            raise ValueError(f"origin must be two finite numbers (nm), got {origin!r}")
        return check_shape(shape), check_pixel_size(pixel_size), (ox, oy)

    def _checked_images(self, x, y, z, photons, shape, pixel_size, origin, derivatives):
        """Validated emitters ``(x, y, z, photons)`` and their :meth:`_images`."""
        xs, ys, zs, ns = as_emitters(x, y, z, self.z_range, photons)
        window = self._check_window(shape, pixel_size, origin)
        return (xs, ys, zs, ns), self._images(xs, ys, zs, *window, derivatives)

    def render(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        photons: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> NDArray[np.float64]:
        """Expected photons per pixel, shape ``(rows, cols)``, of K emitters without background.

        See :meth:`images` for the parameters; ``photons`` has shape (K,).
        """
        (_, _, _, ns), imgs = self._checked_images(
            x, y, z, photons, shape, pixel_size, origin, False
        )
        return np.tensordot(ns, imgs, axes=(0, 0))

    def gradients(
        self,
        x: ArrayLike,
        y: ArrayLike,
        z: ArrayLike,
        photons: ArrayLike,
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> NDArray[np.float64]:
        """Derivatives of the rendered image, shape ``(K, 4, rows, cols)``.

        Index 0..2 are d/dx, d/dy, d/dz (photons per pixel per nm) and 3 is d/dphotons.
        """
        (_, _, _, ns), (imgs, der) = self._checked_images(
            x, y, z, photons, shape, pixel_size, origin, True
        )
        out = np.empty((len(ns), 4, *imgs.shape[1:]))
        out[:, :3] = der * ns[:, None, None, None]
        out[:, 3] = imgs
        return out

    def support_radius(
        self,
        pixel_size: float,
        fraction: float = 0.95,
        *,
        z_range: tuple[float, float] | None = None,
    ) -> float:
        """Radius (nm) of the disc around the emitter that holds most of its image.

        The largest radius over 9 planes across ``z_range`` (default: the model's) that holds
        ``fraction`` of the
        energy found within an 8 um field. (A hard-edged pupil's halo falls as 1/r^3 and holds a
        few per cent of the photons out to many microns; it is left out on purpose.) Used to size
        simulation patches and window margins; computed once per pixel size and fraction.
        """
        px = check_pixel_size(pixel_size)
        if not 0 < fraction <= 1:
            raise ValueError(f"fraction must be in (0, 1], got {fraction}")
        cache = self.__dict__.setdefault("_support_cache", {})
        zr = self.z_range if z_range is None else (float(z_range[0]), float(z_range[1]))
        key = (round(px, 6), round(float(fraction), 9), zr)
        if key not in cache:
            zs = np.linspace(*zr, 9)
            step = max(px, 20.0)  # the radius barely depends on pixel size; bound the work
            n = int(np.ceil(8000.0 / step)) | 1
            half = n * step / 2
            imgs = self.images(np.full(9, half), np.full(9, half), zs, (n, n), step)
            c = pixel_centres(n, step) - half
            r = np.hypot(c[None, :], c[:, None]).ravel()
            cache[key] = energy_radius(imgs, r, fraction) + px
        return cache[key]


class ShiftedPSF(PSFBase):
    """A model moved in x, y, z: ``shifted(x, y, z) = base(x + dx, y + dy, z + dz)``.

    Puts a model in another coordinate frame, e.g. a pupil fitted to a bead stack into the
    frame of the calibration (lateral origin at the spline's centre, z = 0 at the scan's
    reference slice). Derivatives are the base model's.

    Parameters
    ----------
    base : PSFBase
        The model to move.
    dx, dy, dz : float
        Offsets (nm).
    z_range : (float, float), optional
        Valid range in the new frame; default the base's range moved by ``-dz``.
    """

    def __init__(
        self,
        base: PSFBase,
        dx: float = 0.0,
        dy: float = 0.0,
        dz: float = 0.0,
        *,
        z_range: tuple[float, float] | None = None,
    ) -> None:
        super().__init__()
        self.base = base
        self.offset = (float(dx), float(dy), float(dz))
        lo, hi = base.z_range
        zr = (lo - self.offset[2], hi - self.offset[2]) if z_range is None else z_range
        zr = (max(float(zr[0]), lo - self.offset[2]), min(float(zr[1]), hi - self.offset[2]))
        if not zr[0] < zr[1]:
            raise ValueError(f"z_range {z_range} does not overlap the base model's range")
        self._z_range = zr
        self.name = getattr(base, "name", "psf")

    def __repr__(self) -> str:
        return f"ShiftedPSF({self.base!r}, offset={self.offset}, z_range={self.z_range})"

    def _images(self, x, y, z, shape, pixel_size, origin, derivatives):
        dx, dy, dz = self.offset
        return self.base._images(x + dx, y + dy, z + dz, shape, pixel_size, origin, derivatives)
