"""Pupil phase masks: double helix, astigmatism, Zernike aberrations, and masks read from files.

A mask is any callable ``phase(rho, phi) -> radians`` over normalised pupil coordinates
(``rho`` in [0, 1] at the pupil edge, ``phi`` the azimuth, counter-clockwise from the x axis).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.special import eval_genlaguerre

__all__ = [
    "MASK_SUFFIXES",
    "ArrayMask",
    "AstigmatismMask",
    "DoubleHelixMask",
    "Mask",
    "SumMask",
    "ZernikeMask",
    "load_mask",
    "zernike",
]

#: File types :func:`load_mask` reads.
MASK_SUFFIXES: tuple[str, ...] = (".mat", ".npy", ".tif", ".tiff", ".csv")

Mask = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]

# Laguerre-Gauss modes (p, l) of the rotating double-helix PSF (Pavani & Piestun 2008).
DH_MODES: tuple[tuple[int, int], ...] = ((0, 1), (1, 3), (2, 5), (3, 7), (4, 9))


@dataclass(frozen=True)
class DoubleHelixMask:
    """Phase of a superposition of Laguerre-Gauss modes: ``arg(sum_j LG_{p_j, l_j})``.

    Parameters
    ----------
    waist : float
        Gaussian waist as a fraction of the pupil radius. Smaller waists rotate faster
        with defocus.
    modes : sequence of (p, l)
        Radial and azimuthal indices; the default is the classic DH set.
    """

    waist: float = 0.3
    modes: tuple[tuple[int, int], ...] = DH_MODES

    def __post_init__(self) -> None:
        if not (0 < self.waist < 10):
            raise ValueError(f"waist must be in (0, 10) pupil radii, got {self.waist}")

    def __call__(self, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray[np.float64]:
        w = self.waist
        s = 2.0 * rho**2 / w**2
        total = np.zeros(np.broadcast(rho, phi).shape, dtype=np.complex128)
        for p, l in self.modes:
            norm = math.sqrt(math.factorial(p) / math.factorial(p + l))
            total += (
                norm
                * (np.sqrt(2.0) * rho / w) ** abs(l)
                * eval_genlaguerre(p, abs(l), s)
                * np.exp(-(rho**2) / w**2)
                * np.exp(1j * l * phi)
            )
        return np.angle(total)


@dataclass(frozen=True)
class AstigmatismMask:
    """Astigmatism ``2*pi*a*rho^2*cos(2*phi)`` with ``a`` in waves (Zernike Z(2, 2) shape)."""

    waves: float = 0.15

    def __call__(self, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray[np.float64]:
        return 2.0 * np.pi * self.waves * rho**2 * np.cos(2.0 * phi)


def zernike(n: int, m: int, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray:
    """Zernike polynomial ``Z_n^m`` (Noll normalisation: RMS 1 over the unit disc).

    ``m >= 0`` gives the cosine term, ``m < 0`` the sine term.
    """
    if n < 0 or abs(m) > n or (n - abs(m)) % 2:
        raise ValueError(f"invalid Zernike indices n={n}, m={m}")
    ma = abs(m)
    radial = np.zeros_like(np.asarray(rho, dtype=np.float64))
    for k in range((n - ma) // 2 + 1):
        c = (
            (-1) ** k
            * math.factorial(n - k)
            / (
                math.factorial(k)
                * math.factorial((n + ma) // 2 - k)
                * math.factorial((n - ma) // 2 - k)
            )
        )
        radial = radial + c * rho ** (n - 2 * k)
    norm = math.sqrt(2 * (n + 1)) if m != 0 else math.sqrt(n + 1)
    ang = np.cos(ma * phi) if m >= 0 else np.sin(ma * phi)
    return norm * radial * ang


@dataclass(frozen=True)
class ZernikeMask:
    """Sum of Noll-normalised Zernike terms; ``coefficients`` maps ``(n, m)`` to waves RMS."""

    coefficients: Mapping[tuple[int, int], float] = field(default_factory=dict)

    def __call__(self, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.zeros(np.broadcast(rho, phi).shape)
        for (n, m), a in self.coefficients.items():
            out += 2.0 * np.pi * a * zernike(n, m, rho, phi)
        return out


@dataclass(frozen=True)
class SumMask:
    """The sum of several masks' phases (e.g. a double helix plus aberrations)."""

    masks: tuple[Mask, ...]

    def __call__(self, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray[np.float64]:
        out = np.zeros(np.broadcast(rho, phi).shape)
        for m in self.masks:
            out = out + m(rho, phi)
        return out


class ArrayMask:
    """A phase mask sampled on a square array (radians), as retrieved or designed elsewhere.

    The pupil disc inside the array is given by ``centre`` (row, col, in array pixels) and
    ``radius`` (array pixels); by default both come from the support of the non-zero values
    (retrieved masks store zeros outside the pupil). The phase is interpolated as
    ``exp(i*phase)`` (bilinear) so that wrapped and unwrapped masks give the same result.

    Parameters
    ----------
    phase : ndarray, shape (N, M)
        Phase in radians.
    centre : (float, float), optional
        Pupil centre (row, col) in array pixels.
    radius : float, optional
        Pupil radius in array pixels.
    flip : bool
        Mirror the mask in x (some set-ups image the mask mirrored).
    """

    def __init__(
        self,
        phase: NDArray[np.float64],
        centre: tuple[float, float] | None = None,
        radius: float | None = None,
        *,
        flip: bool = False,
    ) -> None:
        arr = np.asarray(phase)
        if arr.ndim != 2:
            raise ValueError(f"a phase mask must be a 2-D array, got {arr.ndim} dimension(s)")
        if np.iscomplexobj(arr):
            arr = np.angle(arr)
        arr = arr.astype(np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError("the phase mask contains NaN or inf values")
        support = arr != 0
        if centre is None or radius is None:
            if support.sum() < 10:
                # No zero padding to read the pupil from: assume the disc fills the array.
                support = np.ones_like(support)
            rr, cc = np.nonzero(support)
            if centre is None:
                centre = (float(rr.mean()), float(cc.mean()))
            if radius is None:
                radius = float(np.sqrt(support.sum() / np.pi))
        if radius <= 0:
            raise ValueError(f"radius must be > 0 array pixels, got {radius}")
        self.phase = arr
        self.centre = (float(centre[0]), float(centre[1]))
        self.radius = float(radius)
        self.flip = flip
        self._field = np.exp(1j * arr)

    def __call__(self, rho: NDArray[np.float64], phi: NDArray[np.float64]) -> NDArray[np.float64]:
        from scipy.ndimage import map_coordinates

        kx = rho * np.cos(phi)
        ky = rho * np.sin(phi)
        if self.flip:
            kx = -kx
        rows = self.centre[0] + ky * self.radius
        cols = self.centre[1] + kx * self.radius
        coords = np.stack([np.ravel(rows), np.ravel(cols)])
        re = map_coordinates(self._field.real, coords, order=1, mode="nearest")
        im = map_coordinates(self._field.imag, coords, order=1, mode="nearest")
        return np.angle(re + 1j * im).reshape(np.shape(rows))


def load_mask(
    path: str | Path,
    key: str | None = None,
    *,
    centre: tuple[float, float] | None = None,
    radius: float | None = None,
    flip: bool = False,
) -> ArrayMask:
    """Read a pupil phase mask (radians) from a ``.mat``, ``.npy``, ``.tif`` or ``.csv`` file.

    For MATLAB files ``key`` names the variable; without it the file must hold exactly one
    2-D numeric array. Never unpickles.

    Raises
    ------
    ValueError
        In one sentence naming the file, for a missing, unknown, damaged or unusable file
        (the readers' own errors, such as ``OSError`` or ``zlib.error``, included).
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"mask file {str(p)!r} does not exist")
    try:
        arr = _read_mask_array(p, key)
        arr = np.squeeze(np.asarray(arr))
        if arr.ndim != 2:
            hint = (
                "; a stack of images is a bead z-scan: calibrate it with sparseloc calibrate "
                "and give the .h5 it writes"
                if arr.ndim == 3
                else ""
            )
            raise ValueError(f"the mask in {p.name} must be 2-D, got shape {arr.shape}{hint}")
        if arr.dtype.kind not in "biufc":
            raise ValueError(f"the mask in {p.name} holds {arr.dtype} values, not numbers")
        if arr.dtype.kind in "biu":
            # phases are real numbers; whole numbers are a camera's counts or an SLM's levels
            raise ValueError(
                f"the mask in {p.name} holds whole numbers ({arr.dtype}, {arr.min()}-"
                f"{arr.max()}), not phases in radians: a camera frame is a movie, not a mask, "
                "and an SLM's grey levels need converting to radians first"
            )
        return ArrayMask(arr, centre, radius, flip=flip)
    except ValueError as exc:
        if str(exc).startswith("the mask in"):
            raise
        name = "" if p.name in str(exc) else f" {str(p)!r}"
        raise ValueError(f"cannot use the mask file{name}: {exc}") from exc
    except Exception as exc:
        # A damaged file makes the readers raise almost anything (OSError, zlib.error,
        # struct.error, MemoryError for a corrupt size field ...): all mean "not readable".
        raise ValueError(
            f"the mask file {str(p)!r} is damaged or not a mask ({type(exc).__name__}: {exc})"
        ) from exc


def _read_mask_array(p: Path, key: str | None) -> NDArray:
    """The array stored in the mask file ``p`` (see :func:`load_mask`)."""
    suffix = p.suffix.lower()
    if suffix == ".mat":
        from scipy.io import loadmat

        data = loadmat(p)
        arrays = {
            k: v
            for k, v in data.items()
            if not k.startswith("__") and isinstance(v, np.ndarray) and v.dtype.kind in "fiuc"
        }
        if key is not None:
            if key not in arrays:
                raise ValueError(
                    f"variable {key!r} is not a numeric array in {p.name}; "
                    f"choose one of {sorted(arrays)}"
                )
            return arrays[key]
        two_d = {k: v for k, v in arrays.items() if v.ndim == 2 and min(v.shape) > 4}
        if len(two_d) != 1:
            raise ValueError(
                f"{p.name} holds {len(two_d)} 2-D arrays ({sorted(two_d)}); name one with key="
            )
        return next(iter(two_d.values()))
    if suffix == ".npy":
        from ..io.npy import load_array

        return load_array(p)
    if suffix in (".tif", ".tiff"):
        from ..io.tiff import read_tiff  # the movie reader's checks for damaged files

        return read_tiff(p)
    if suffix in (".csv", ".txt"):
        with open(p, encoding="utf-8", errors="replace") as fh:
            first = fh.readline()
        if any(c.isalpha() and c not in "eE" for c in first):
            raise ValueError(
                f"the mask in {p.name} has a header row ({first.strip()[:40]}...): a phase mask is "
                "a plain array of numbers; a table of localizations or truth goes elsewhere"
            )
        return np.loadtxt(p, delimiter="," if suffix == ".csv" else None)
    raise ValueError(f"unknown mask file type {suffix!r}; use .mat, .npy, .tif or .csv")


def combine(masks: Sequence[Mask]) -> Mask:
    """One mask from several (their phases add)."""
    return masks[0] if len(masks) == 1 else SumMask(tuple(masks))
