"""Analytic PSF models: astigmatic elliptical Gaussian and a two-lobe double helix.

Both models are sums of separable Gaussians, so every pixel is integrated exactly with error
functions (no oversampling), an emitter's image sums to one photon over the unbounded plane,
and the derivatives with respect to ``x``, ``y`` and ``z`` are analytic.

Units follow design.md: positions and widths in nm, angles in radians, images in expected
photons per pixel for one photon. ``x`` runs along columns, ``y`` along rows; the window's outer
corner of pixel (0, 0) sits at ``origin``.

Notes
-----
For a 1-D Gaussian of width ``s`` centred at ``mu``, the fraction of light in the pixel
``[e_j, e_j+1]`` is ``G_j = (erf(u_j+1 / (sqrt(2) s)) - erf(u_j / (sqrt(2) s))) / 2`` with
``u = e - mu``. Its derivatives are ``dG_j/dmu = phi(u_j) - phi(u_j+1)`` and
``dG_j/ds = (u_j phi(u_j) - u_j+1 phi(u_j+1)) / s``, ``phi`` being the normal density of width
``s``. The differences are taken between ``erfc`` values on the side of the Gaussian away from
its peak, so the far tails keep full relative precision (the Fisher information divides by
the model, so the tails matter).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import erfc

from .base import PSFBase, parse_pair

__all__ = ["GaussianAstigPSF", "TwoLobeDHPSF"]

_SQRT2 = np.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


def _check_z_range(z_range: tuple[float, float]) -> tuple[float, float]:
    """Return a validated ``(z_min, z_max)`` in nm."""
    lo, hi = parse_pair(z_range, float, f"z_range must be (z_min, z_max) in nm, got {z_range!r}")
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"z_range must be finite (z_min, z_max) with z_min < z_max, got {z_range}")
    return lo, hi


def _check_finite(name: str, value: float) -> float:
    """Return ``value`` as float or raise a ``ValueError`` naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {value!r}") from exc
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _check_positive(name: str, value: float) -> float:
    """Return ``value`` as float or raise a ``ValueError`` unless it is finite and > 0."""
    v = _check_finite(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return v


def _pixel_edges(n: int, pixel_size: float, origin: float) -> NDArray[np.float64]:
    """Edges (nm) of ``n`` pixels of size ``pixel_size`` starting at ``origin``, shape (n+1,)."""
    return origin + np.arange(n + 1, dtype=np.float64) * pixel_size


def _gauss_pixels(
    edges: NDArray[np.float64],
    centre: NDArray[np.float64],
    sigma: NDArray[np.float64],
    derivatives: bool,
) -> tuple[NDArray[np.float64], ...]:
    """Pixel-integrated normalised 1-D Gaussians and their derivatives.

    Parameters
    ----------
    edges : ndarray, shape (n+1,)
        Pixel edges in nm.
    centre, sigma : ndarray, shape (...)
        Gaussian centres and widths in nm (same shape).
    derivatives : bool
        Also return d/dcentre and d/dsigma.

    Returns
    -------
    g : ndarray, shape (..., n)
        Fraction of the Gaussian in each pixel.
    dg_dcentre, dg_dsigma : ndarray, shape (..., n)
        Only with ``derivatives``; per nm.
    """
    s = sigma[..., None]
    u = edges - centre[..., None]  # (..., n+1)
    t = u / (_SQRT2 * s)
    upper = erfc(t)  # 1 - erf(t): accurate where t > 0
    lower = erfc(-t)  # 1 + erf(t): accurate where t < 0
    right = (t[..., :-1] + t[..., 1:]) > 0  # pixel mostly right of the peak
    g = 0.5 * np.where(right, upper[..., :-1] - upper[..., 1:], lower[..., 1:] - lower[..., :-1])
    if not derivatives:
        return (g,)
    phi = np.exp(-(t * t)) * (_INV_SQRT_2PI / s)  # normal density at the edges
    dg_dc = phi[..., :-1] - phi[..., 1:]
    uphi = u * phi
    dg_ds = (uphi[..., :-1] - uphi[..., 1:]) / s
    return g, dg_dc, dg_ds


class _SeparableGaussianPSF(PSFBase):
    """What both analytic models share: images from the window's pixel edges.

    Subclasses implement ``_edge_images(x, y, z, ex, ey, derivatives)`` with ``ex`` (cols+1,)
    and ``ey`` (rows+1,) the pixel edges in nm; it returns what :meth:`PSFBase._images` does.
    """

    def _images(self, x, y, z, shape, pixel_size, origin, derivatives):
        rows, cols = shape
        ex = _pixel_edges(cols, pixel_size, origin[0])
        ey = _pixel_edges(rows, pixel_size, origin[1])
        return self._edge_images(x, y, z, ex, ey, derivatives)

    def _edge_images(
        self,
        x: NDArray[np.float64],
        y: NDArray[np.float64],
        z: NDArray[np.float64],
        ex: NDArray[np.float64],
        ey: NDArray[np.float64],
        derivatives: bool,
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unit-photon images (K, rows, cols) and optionally derivatives (K, 3, rows, cols)."""
        raise NotImplementedError


class GaussianAstigPSF(_SeparableGaussianPSF):
    """Astigmatic elliptical Gaussian with the width curves of Huang et al. (2008).

    The image of an emitter at ``(x, y, z)`` is a normalised 2-D Gaussian with widths

    ``sigma_x(z) = sigma0 * sqrt(1 + t_x**2 + A*t_x**3 + B*t_x**4)``, ``t_x = (z - c) / d``,

    ``sigma_y(z) = sigma0 * sqrt(1 + t_y**2 + A*t_y**3 + B*t_y**4)``, ``t_y = (z + c) / d``,

    integrated exactly over each pixel. With ``A = B = 0`` the widths cross at ``z = 0``;
    ``sigma_x`` is smallest at ``z = c`` and ``sigma_y`` at ``z = -c``.

    Parameters
    ----------
    sigma0 : float
        In-focus width in nm (> 0).
    c : float
        Offset (nm) of the two focal lines from ``z = 0``.
    d : float
        Depth of focus in nm (> 0).
    A, B : float
        Higher-order (cubic, quartic) coefficients of the width curves (dimensionless).
        They must keep both widths real and positive over ``z_range``.
    z_range : (float, float)
        Valid axial range in nm.
    name : str
        Label used in plots and files.

    References
    ----------
    B. Huang, W. Wang, M. Bates, X. Zhuang, "Three-dimensional super-resolution imaging by
    stochastic optical reconstruction microscopy", Science 319, 810-813 (2008).
    """

    def __init__(
        self,
        *,
        sigma0: float = 130.0,
        c: float = 250.0,
        d: float = 400.0,
        A: float = 0.0,
        B: float = 0.0,
        z_range: tuple[float, float] = (-600.0, 600.0),
        name: str = "astig-gauss",
    ) -> None:
        super().__init__()
        self.sigma0 = _check_positive("sigma0", sigma0)
        self.c = _check_finite("c", c)
        self.d = _check_positive("d", d)
        self.A = _check_finite("A", A)
        self.B = _check_finite("B", B)
        self._z_range = _check_z_range(z_range)
        self.name = str(name)
        # The width polynomial must stay positive over the z range (checked densely, with the
        # end points and the extremes of the quartic included through the fine grid).
        zz = np.linspace(*self._z_range, 4001)
        for axis, shift in (("x", -self.c), ("y", self.c)):
            p, _ = self._poly((zz + shift) / self.d)
            if np.min(p) <= 1e-6:
                raise ValueError(
                    f"A={self.A}, B={self.B} make sigma_{axis}(z) zero or imaginary within "
                    f"z_range={self._z_range}; choose A and B (or z_range) so that "
                    f"1 + t^2 + A t^3 + B t^4 > 0"
                )

    def __repr__(self) -> str:
        return (
            f"GaussianAstigPSF(sigma0={self.sigma0}, c={self.c}, d={self.d}, A={self.A}, "
            f"B={self.B}, z_range={self.z_range}, name={self.name!r})"
        )

    def _poly(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``1 + t^2 + A t^3 + B t^4`` and its derivative with respect to ``t``."""
        p = 1.0 + t * t * (1.0 + t * (self.A + self.B * t))
        dp = t * (2.0 + t * (3.0 * self.A + 4.0 * self.B * t))
        return p, dp

    def _width(
        self, z: NDArray[np.float64], shift: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Width (nm) and its z derivative for ``t = (z + shift) / d``."""
        p, dp = self._poly((z + shift) / self.d)
        s = self.sigma0 * np.sqrt(p)
        ds_dz = self.sigma0 * dp / (2.0 * np.sqrt(p) * self.d)
        return s, ds_dz

    def sigma(self, z: NDArray[np.float64] | float) -> tuple[NDArray[np.float64], ...]:
        """Gaussian widths at ``z``.

        Parameters
        ----------
        z : array_like, shape (K,)
            Axial positions in nm.

        Returns
        -------
        sigma_x, sigma_y : ndarray, shape (K,)
            Widths in nm along x (columns) and y (rows).
        """
        zz = np.atleast_1d(np.asarray(z, dtype=np.float64))
        return self._width(zz, -self.c)[0], self._width(zz, self.c)[0]

    def _edge_images(self, x, y, z, ex, ey, derivatives):
        sx, dsx = self._width(z, -self.c)
        sy, dsy = self._width(z, self.c)
        if not derivatives:
            (gx,) = _gauss_pixels(ex, x, sx, False)
            (gy,) = _gauss_pixels(ey, y, sy, False)
            return gy[:, :, None] * gx[:, None, :]
        gx, gx_c, gx_s = _gauss_pixels(ex, x, sx, True)
        gy, gy_c, gy_s = _gauss_pixels(ey, y, sy, True)
        img = gy[:, :, None] * gx[:, None, :]
        der = np.empty((len(x), 3, ey.size - 1, ex.size - 1))
        der[:, 0] = gy[:, :, None] * gx_c[:, None, :]
        der[:, 1] = gy_c[:, :, None] * gx[:, None, :]
        gx_z = gx_s * dsx[:, None]
        gy_z = gy_s * dsy[:, None]
        der[:, 2] = gy_z[:, :, None] * gx[:, None, :] + gy[:, :, None] * gx_z[:, None, :]
        return img, der


class TwoLobeDHPSF(_SeparableGaussianPSF):
    """Analytic double-helix PSF: two rotating isotropic Gaussian lobes.

    Each lobe holds half of the photons and has width ``lobe_sigma``. The lobes sit at
    ``(x, y) +/- (separation / 2) * (cos theta, sin theta)`` with the axis angle

    ``theta(z) = theta0 + (z - z_mid) * rotation / (z_max - z_min)``, ``z_mid = (z_min + z_max)/2``,

    so the axis turns linearly by ``rotation`` radians across ``z_range``. The angle is measured
    from the +x axis (columns) towards +y (rows); the lobes' midpoint is the emitter position.

    Parameters
    ----------
    lobe_sigma : float
        Width of each lobe in nm (> 0).
    separation : float
        Distance between the lobe centres in nm (>= 0).
    rotation : float
        Total turn of the lobe axis across ``z_range`` in radians.
    theta0 : float
        Axis angle at the middle of ``z_range`` in radians.
    z_range : (float, float)
        Valid axial range in nm.
    name : str
        Label used in plots and files.
    """

    def __init__(
        self,
        *,
        lobe_sigma: float = 150.0,
        separation: float = 900.0,
        rotation: float = np.pi,
        theta0: float = 0.0,
        z_range: tuple[float, float] = (-1000.0, 1000.0),
        name: str = "dh-analytic",
    ) -> None:
        super().__init__()
        self.lobe_sigma = _check_positive("lobe_sigma", lobe_sigma)
        self.separation = _check_finite("separation", separation)
        if self.separation < 0:
            raise ValueError(f"separation must be >= 0 nm, got {separation!r}")
        self.rotation = _check_finite("rotation", rotation)
        self.theta0 = _check_finite("theta0", theta0)
        self._z_range = _check_z_range(z_range)
        self.name = str(name)

    def __repr__(self) -> str:
        return (
            f"TwoLobeDHPSF(lobe_sigma={self.lobe_sigma}, separation={self.separation}, "
            f"rotation={self.rotation}, theta0={self.theta0}, z_range={self.z_range}, "
            f"name={self.name!r})"
        )

    @property
    def rotation_rate(self) -> float:
        """``d theta / d z`` in radians per nm."""
        lo, hi = self._z_range
        return self.rotation / (hi - lo)

    def theta(self, z: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Lobe axis angle (radians, from +x towards +y) at ``z`` (nm), shape (K,)."""
        zz = np.atleast_1d(np.asarray(z, dtype=np.float64))
        lo, hi = self._z_range
        return self.theta0 + (zz - 0.5 * (lo + hi)) * self.rotation_rate

    def lobe_centres(
        self,
        x: NDArray[np.float64] | float,
        y: NDArray[np.float64] | float,
        z: NDArray[np.float64] | float,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Centres of the two lobes.

        Parameters
        ----------
        x, y, z : array_like, shape (K,)
            Emitter positions in nm.

        Returns
        -------
        cx, cy : ndarray, shape (K, 2)
            Lobe centres in nm; lobe 0 at ``+separation/2`` along the axis, lobe 1 opposite.
        """
        th = self.theta(z)[:, None]
        half = 0.5 * self.separation * np.array([1.0, -1.0])
        cx = np.atleast_1d(np.asarray(x, dtype=np.float64))[:, None] + half * np.cos(th)
        cy = np.atleast_1d(np.asarray(y, dtype=np.float64))[:, None] + half * np.sin(th)
        return cx, cy

    def _edge_images(self, x, y, z, ex, ey, derivatives):
        cx, cy = self.lobe_centres(x, y, z)  # (K, 2)
        s = np.full_like(cx, self.lobe_sigma)
        # Per lobe: gx (K, 2, cols), gy (K, 2, rows); image = 0.5 * sum_lobes outer(gy, gx).
        if not derivatives:
            (gx,) = _gauss_pixels(ex, cx, s, False)
            (gy,) = _gauss_pixels(ey, cy, s, False)
            return 0.5 * (gy.transpose(0, 2, 1) @ gx)
        gx, gx_c, _ = _gauss_pixels(ex, cx, s, True)
        gy, gy_c, _ = _gauss_pixels(ey, cy, s, True)
        gy_t = gy.transpose(0, 2, 1)  # (K, rows, 2)
        img = 0.5 * (gy_t @ gx)
        der = np.empty((len(x), 3, ey.size - 1, ex.size - 1))
        der[:, 0] = 0.5 * (gy_t @ gx_c)
        der[:, 1] = 0.5 * (gy_c.transpose(0, 2, 1) @ gx)
        # d(centre)/dz per lobe: +/- (separation/2) * (-sin theta, cos theta) * dtheta/dz.
        th = self.theta(z)
        k = 0.5 * self.separation * self.rotation_rate
        sign = np.array([1.0, -1.0])
        dcx = sign * (-k * np.sin(th))[:, None]  # (K, 2)
        dcy = sign * (k * np.cos(th))[:, None]
        der[:, 2] = 0.5 * (
            gy_t @ (gx_c * dcx[:, :, None]) + (gy_c * dcy[:, :, None]).transpose(0, 2, 1) @ gx
        )
        return img, der
