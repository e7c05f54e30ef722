"""Scalar pupil-function PSF with any phase mask, exact pixel integration and sub-pixel shifts.

Notes
-----
The field in the image plane is the Fourier transform of the pupil
``P(k) = A(k) exp(i phi_mask(k)) exp(i kz z)`` over the disc ``|k| <= k_max = 2 pi NA / lambda``,
with ``kz = sqrt((2 pi n / lambda)^2 - |k|^2)`` and the aplanatic factor ``A = 1/sqrt(cos theta)``.

The pupil is sampled with spacing ``dk = 2 pi / L``; by Poisson summation the resulting field is
the continuous one periodised with period ``L`` (``field_size``, default about 22 um, far larger
than any window). The intensity ``|E|^2`` is then an exact trigonometric polynomial whose
coefficients, the optical transfer function ``c_m``, come from one FFT of ``|E|^2`` sampled at
the intensity Nyquist rate. From the OTF:

- integrating over a pixel of side ``a`` multiplies ``c_m`` by
  ``a sinc(kx a / 2) * a sinc(ky a / 2)`` (exact, no oversampling);
- the pixel values at arbitrary positions relative to the emitter come from a separable matrix
  DFT ``Re(Ey @ C @ Ex.T)``, so a sub-pixel shift is exact;
- d/dx and d/dy multiply column/row factors by ``-i k``; d/dz comes from the OTF of
  ``2 Re(conj(E) dE/dz)`` with ``dE/dz`` the transform of ``i kz P``.

Normalisation: ``c_0 = 1``, so an emitter's image sums to one photon over one period (the
unbounded plane up to the negligible periodisation).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft
from numpy.typing import NDArray

from ..units import WAVELENGTH_RANGE_NM, check_length_nm
from .base import PSFBase, as_emitters, pixel_centres
from .masks import Mask

__all__ = ["PupilPSF"]


def _check_args(
    na: float,
    wavelength: float,
    n_immersion: float,
    z_range: tuple[float, float],
    pupil_samples: int,
    n_sample: float | None,
    focal_depth: float,
    blur: float,
) -> None:
    """Raise a ``ValueError`` naming the first invalid :class:`PupilPSF` argument."""
    if not (np.isfinite(blur) and blur >= 0):
        raise ValueError(f"blur must be a standard deviation >= 0 nm, got {blur}")
    if not (0 < na < n_immersion):
        raise ValueError(
            f"na must be in (0, {n_immersion:g}), below the immersion's refractive index, got {na}"
        )
    check_length_nm(wavelength, "wavelength", WAVELENGTH_RANGE_NM)
    if pupil_samples < 16:
        raise ValueError(f"pupil_samples must be >= 16, got {pupil_samples}")
    if not z_range[0] < z_range[1]:
        raise ValueError(f"z_range must be (z_min, z_max) with z_min < z_max, got {z_range}")
    if n_sample is not None:
        if not n_sample > 0:
            raise ValueError(f"n_sample must be > 0, got {n_sample}")
        if focal_depth + z_range[0] < -1e-6:
            raise ValueError(
                f"z_range starts {-z_range[0]:g} nm below the focal plane but the focal "
                f"plane is only {focal_depth:g} nm above the coverslip"
            )


class PupilPSF(PSFBase):
    """Scalar pupil model of a widefield microscope with a phase mask.

    Parameters
    ----------
    mask : callable, optional
        ``phase(rho, phi)`` in radians over the normalised pupil (see :mod:`.masks`);
        ``None`` gives the clear (standard) PSF.
    na : float
        Numerical aperture.
    wavelength : float
        Emission wavelength in nm.
    n_immersion : float
        Refractive index of the immersion medium (sets ``kz``).
    z_range : (float, float)
        Valid axial range in nm.
    pupil_samples : int
        Pupil samples across its diameter. Sets the period ``L = pupil_samples * lambda / (2 NA)``.
    aplanatic : bool
        Apply the ``1/sqrt(cos theta)`` apodisation.
    name : str
        Label used in plots and files.
    n_sample : float, optional
        Refractive index of the sample (e.g. 1.33 for water). ``None``: the same as the
        immersion medium (no mismatch). With a mismatch, an emitter at ``z`` sits at depth
        ``focal_depth + z`` above the coverslip and its pupil phase is
        ``kz_sample (focal_depth + z) - kz_immersion focal_depth`` (the usual scalar model of
        index mismatch, without Fresnel coefficients; angles beyond ``n_sample`` are
        evanescent in the sample and fade with depth).
    focal_depth : float
        Nominal focal plane: the stage's focus position above the coverslip (nm), used only
        with ``n_sample``.
    blur : float
        Standard deviation (nm) of a Gaussian that blurs every image, 0 for none: what a
        scalar pupil model leaves out of real images (the emitter's size and dipole
        orientation, residual motion, camera pixel cross-talk). Applied to the OTF, so
        derivatives and sub-pixel shifts stay exact.
    """

    def __init__(
        self,
        mask: Mask | None = None,
        *,
        na: float = 1.45,
        wavelength: float = 670.0,
        n_immersion: float = 1.518,
        z_range: tuple[float, float] = (-1000.0, 1000.0),
        pupil_samples: int = 96,
        aplanatic: bool = True,
        name: str = "pupil",
        n_sample: float | None = None,
        focal_depth: float = 0.0,
        blur: float = 0.0,
    ) -> None:
        super().__init__()
        _check_args(
            na, wavelength, n_immersion, z_range, pupil_samples, n_sample, focal_depth, blur
        )
        self.n_sample = None if n_sample is None else float(n_sample)
        self.focal_depth = float(focal_depth)
        self.mask = mask
        self.na = float(na)
        self.wavelength = float(wavelength)
        self.n_immersion = float(n_immersion)
        self._z_range = (float(z_range[0]), float(z_range[1]))
        self.aplanatic = aplanatic
        self.name = name
        self.pupil_samples = int(pupil_samples)
        self.field_size = self.pupil_samples * self.wavelength / (2 * self.na)  # period L, nm
        self._dk = 2 * np.pi / self.field_size
        # FFT size: the intensity's spectrum spans 2 * pupil_samples bins; leave a small guard.
        self._m = sfft.next_fast_len(2 * self.pupil_samples + 8)
        self._pupil0, self._kz = self._pupil_at_focus()
        # Keep only the OTF's support (|index| <= half) for the matrix DFT.
        half = min(self.pupil_samples + 2, self._m // 2 - 1)
        self._otf_idx = np.arange(-half, half + 1)
        self._k = self._otf_idx * self._dk  # angular spatial frequencies (rad/nm) of kept bins
        self.blur = float(blur)
        # The Gaussian's transfer function on the kept OTF bins (row = ky, col = kx).
        g = np.exp(-0.5 * (self.blur * self._k) ** 2)
        self._blur_tf = g[:, None] * g[None, :]

    def pupil_coordinates(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
        """The pupil grid (M, M) in FFT order: ``|k|`` (rad/nm), the disc ``|k| <= k_max``, and
        the normalised polar coordinates ``rho`` (0 outside the disc) and ``phi`` (radians)."""
        m = self._m
        idx = np.fft.fftfreq(m, d=1.0 / m)  # integer frequency indices in FFT order
        kx, ky = np.meshgrid(idx * self._dk, idx * self._dk)
        k_max = 2 * np.pi * self.na / self.wavelength
        kr = np.hypot(kx, ky)
        inside = kr <= k_max
        rho = np.where(inside, kr / k_max, 0.0)
        phi = np.arctan2(ky, kx)
        return kr, inside, rho, phi

    def _pupil_at_focus(self) -> tuple[NDArray[np.complex128], NDArray]:
        """The pupil ``P(k)`` of an emitter at ``z = 0`` and the ``kz`` (rad/nm) that defocuses it.

        With a sample index, ``kz`` is the sample's (complex beyond its critical angle) and the
        pupil carries the phase of the nominal focal depth.
        """
        kr, inside, rho, phi = self.pupil_coordinates()
        kn = 2 * np.pi * self.n_immersion / self.wavelength
        kz = np.sqrt(np.maximum(kn**2 - kr**2, 0.0))
        amp = np.where(inside, 1.0, 0.0)
        if self.aplanatic:
            amp = amp / np.sqrt(np.maximum(kz / kn, 1e-12))
        phase = np.zeros_like(kr)
        if self.mask is not None:
            phase = np.where(inside, np.asarray(self.mask(rho, phi), dtype=np.float64), 0.0)
        pupil0 = amp * np.exp(1j * phase)
        kz = np.where(inside, kz, 0.0)
        if self.n_sample is None:
            return pupil0, kz
        ks = 2 * np.pi * self.n_sample / self.wavelength
        # Complex beyond the sample's critical angle: exp(i kz_s depth) decays there.
        kzs = np.where(inside, np.sqrt(ks**2 - kr**2 + 0j), 0.0)
        return pupil0 * np.exp(1j * (kzs - kz) * self.focal_depth), kzs

    def __repr__(self) -> str:
        return (
            f"PupilPSF(name={self.name!r}, na={self.na}, wavelength={self.wavelength}, "
            f"n_immersion={self.n_immersion}, z_range={self.z_range}"
            + (
                f", n_sample={self.n_sample}, focal_depth={self.focal_depth}"
                if self.n_sample is not None
                else ""
            )
            + (f", blur={self.blur}" if self.blur else "")
            + ")"
        )

    def renders_beyond_range(self, z: NDArray[np.float64]) -> NDArray[np.bool_]:
        """With a sample index, never below the coverslip (depth ``focal_depth + z < 0``)."""
        z = np.asarray(z, dtype=np.float64)
        if self.n_sample is None:
            return np.ones(z.shape, dtype=bool)
        return self.focal_depth + z >= 0.0

    # -- OTF ------------------------------------------------------------------------------
    def otf(self, z: NDArray[np.float64], derivative: bool = False):
        """OTF coefficients ``c_m`` (K, B, B), centred, with ``c_0 = 1``; optionally d/dz.

        ``B = 2*half+1`` bins at angular frequencies ``self._k`` (rad/nm), row index = ky.
        """
        z = np.atleast_1d(np.asarray(z, dtype=np.float64))
        defocus = np.exp(1j * self._kz[None] * z[:, None, None])
        p = self._pupil0[None] * defocus
        e = sfft.ifft2(p, axes=(-2, -1), workers=-1)
        inten = (e * e.conj()).real
        norm = inten.sum(axis=(-2, -1), keepdims=True)
        c = self._kept_bins(inten / norm)
        if not derivative:
            return c
        de = sfft.ifft2(1j * self._kz[None] * p, axes=(-2, -1), workers=-1)
        dinten = 2.0 * (e.conj() * de).real
        return c, self._kept_bins(dinten / norm)

    def _kept_bins(self, inten: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The kept, centred OTF bins (K, B, B) of intensities (K, M, M), blurred if asked."""
        sel = self._otf_idx % self._m
        c = sfft.fft2(inten, axes=(-2, -1), workers=-1)[:, sel][:, :, sel]
        if self.blur:
            c = c * self._blur_tf
        return c

    def _pixel_offsets(
        self,
        x: NDArray[np.float64],
        y: NDArray[np.float64],
        shape: tuple[int, int],
        a: float,
        origin: tuple[float, float],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel centres minus emitter positions (nm): ``u`` (K, cols) and ``v`` (K, rows)."""
        rows, cols = shape
        u = pixel_centres(cols, a, origin[0])[None, :] - x[:, None]
        v = pixel_centres(rows, a, origin[1])[None, :] - y[:, None]
        return u, v

    def shift_factors(self, d: NDArray[np.float64], pixel_size: float) -> NDArray[np.complex128]:
        """Row or column factors ``exp(i k d) sinc(k a / 2)`` of the matrix DFT, shape
        ``(*d.shape, B)``, for offsets ``d`` (nm) of pixel centres from the emitter.

        The sinc is the transfer function of a pixel of side ``a = pixel_size`` (exact pixel
        integration; ``np.sinc(t) = sin(pi t)/(pi t)``).
        """
        k = self._k
        box = np.sinc(k * pixel_size / (2 * np.pi))
        return np.exp(1j * d[..., None] * k) * box

    def images_on_grid(
        self,
        x: NDArray[np.float64],
        y: NDArray[np.float64],
        z: NDArray[np.float64],
        shape: tuple[int, int],
        pixel_size: float,
        *,
        origin: tuple[float, float] = (0.0, 0.0),
    ) -> NDArray[np.float64]:
        """Unit-photon images of emitters on the grid ``z x y x x``: shape (nz, ny, nx, rows, cols).

        Same values as :meth:`images` at every grid point, but computed by separable products
        that share the OTF of each plane and the row/column factors of each x and y (this is
        what makes building a dictionary of a million atoms take seconds).
        """
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        y = np.atleast_1d(np.asarray(y, dtype=np.float64))
        z = as_emitters(np.zeros_like(np.atleast_1d(z)), 0.0 * np.atleast_1d(z), z, self.z_range)[2]
        shape, a, origin = self._check_window(shape, pixel_size, origin)
        rows, cols = shape
        k = self._k
        u, v = self._pixel_offsets(x, y, shape, a, origin)  # (nx, cols), (ny, rows)
        if np.any(np.abs(u) >= self.field_size / 2) or np.any(np.abs(v) >= self.field_size / 2):
            raise ValueError("the grid window is larger than half the model's field_size")
        ex = self.shift_factors(u, a).reshape(-1, k.size)  # (nx*cols, B)
        ey = self.shift_factors(v, a)  # (ny, rows, B)
        scale = (a / self.field_size) ** 2
        out = np.empty((z.size, y.size, x.size, rows, cols))
        for iz, c in enumerate(self.otf(z)):
            cx = (c @ ex.T).reshape(k.size, x.size, cols)  # (B, nx, cols)
            img = np.einsum("yrb,bxc->yxrc", ey, cx, optimize=True).real
            out[iz] = img * scale
        return out

    def _images(self, x, y, z, shape, pixel_size, origin, derivatives):
        rows, cols = shape
        a = pixel_size
        L = self.field_size
        k = self._k
        u, v = self._pixel_offsets(x, y, shape, a, origin)  # (K, cols), (K, rows)
        ex = self.shift_factors(u, a)  # (K, cols, B)
        ey = self.shift_factors(v, a)  # (K, rows, B)
        scale = (a / L) ** 2
        # Emitters often share planes (dictionaries, simulations at fixed z): one OTF per plane.
        zu, inv = np.unique(z, return_inverse=True)
        if derivatives:
            c, dc = self.otf(zu, derivative=True)
            c, dc = c[inv], dc[inv]
        else:
            c = self.otf(zu)[inv]
        cx = c @ ex.transpose(0, 2, 1)  # (K, B, cols)
        img = (ey @ cx).real * scale
        # Periodisation guard: pixels farther than L/2 from the emitter would see the
        # neighbouring period's copy; the PSF there is ~1e-6 of its peak, so set them to zero.
        valid = (np.abs(v)[:, :, None] < L / 2) & (np.abs(u)[:, None, :] < L / 2)
        if not valid.all():
            img = np.where(valid, img, 0.0)
        if not derivatives:
            return img
        der = np.empty((len(x), 3, rows, cols))
        # d/dx0 of exp(i k (u - x0)) = -i k exp(...)
        der[:, 0] = (ey @ (c @ (ex * (-1j * k)).transpose(0, 2, 1))).real * scale
        der[:, 1] = ((ey * (-1j * k)) @ cx).real * scale
        der[:, 2] = (ey @ (dc @ ex.transpose(0, 2, 1))).real * scale
        if not valid.all():
            der = np.where(valid[:, None], der, 0.0)
        return img, der
