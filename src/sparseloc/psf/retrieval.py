"""Phase retrieval: fit the pupil phase of a :class:`~.pupil.PupilPSF` to a measured bead stack.

The model of plane ``i`` of a bead stack recorded at stage positions ``z_i`` is

``mu_i = N_i * PSF(x0, y0, z_i + z0; phase) + b_i``

where ``PSF`` is the scalar pupil model of :mod:`.pupil` (exact pixel integration), the pupil
phase is ``base_mask + 2 pi sum_j a_j Z_j`` with Noll-normalised Zernike polynomials ``Z_j``
(coefficients ``a_j`` in waves RMS), and ``N_i`` (photons) and ``b_i`` (photons per pixel) are
per-plane scales and backgrounds.

Fitted parameters
-----------------
- Nonlinear: the Zernike coefficients of every ``(n, m)`` with ``2 <= n <= max_order`` except
  defocus ``(2, 0)`` (piston and tilts, ``n < 2``, are never fitted), and the emitter position
  ``x0, y0, z0``. Piston has no effect on the image, tilts are degenerate with ``x0, y0`` and
  defocus is nearly degenerate with ``z0`` (at high NA the defocus phase ``kz z`` also holds
  higher radial orders, which the fitted ``z0`` accounts for).
- Linear: ``N_i`` and ``b_i``, eliminated in closed form at every evaluation (variable
  projection) with the Kaufman approximation of the projected Jacobian.

Derivatives are analytic: with the field ``E = F^-1[P]`` and the intensity ``I = |E|^2``,
``dI/da_j = 2 Re(conj(E) F^-1[i 2 pi Z_j P])``, ``dI/dz0 = 2 Re(conj(E) F^-1[i kz P])``, and the
pixel integration is a fixed linear map (``Re(G_y I G_x^T)``) whose row/column factors carry the
x0/y0 dependence.

Ambiguities
-----------
For a pure-phase pupil, the images of the phase ``psi(k) = -phi(-k)`` at defocus ``z`` equal
those of ``phi`` at ``-z``. Because the stage positions are given and ``z0`` is only an offset,
a stack whose ``z`` axis follows the model's convention (positive ``z`` as in
:class:`~.pupil.PupilPSF`) has no such ambiguity; a stack whose ``z`` axis is reversed is fitted
by ``psi`` instead: coefficients with even ``m`` change sign, those with odd ``m`` do not
(for a double-helix base mask, whose handedness is fixed, such a stack gives a poor fit:
check ``residual_rms`` and reverse ``z`` if needed).

Starting point
--------------
The fit is local. It starts from ``initial`` (default zero) on top of ``base_mask``; a short
multi-start on a coarse model (11 planes, 32 pupil samples) first tries primary astigmatism
``(2, +-2)`` offsets of 0 and +-0.15 waves (the even term whose sign a fit from zero can get
wrong in a strongly aberrated stack) and keeps the best. Stacks with aberrations near
0.3 waves RMS in total can still end in a wrong minimum; for such stacks pass a better
``initial``.

Threads
-------
While :func:`fit_pupil` runs, BLAS is limited to one thread (threadpoolctl): the fit's matrix
products are many and mid-sized, which multithreaded BLAS on a busy machine handles slowly
(FFTs still use all cores).

Example
-------
>>> res = fit_pupil(stack, z, 100.0, na=1.45, wavelength=670.0)  # doctest: +SKIP
>>> res.coefficients[(2, 2)], res.z0, res.residual_rms  # doctest: +SKIP
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import scipy.fft as sfft
from numpy.typing import ArrayLike, NDArray

from .base import check_pixel_size, pixel_centres
from .masks import Mask, ZernikeMask, combine, zernike
from .pupil import PupilPSF

__all__ = ["RetrievalResult", "fit_pupil", "zernike_terms"]

logger = logging.getLogger(__name__)

_CHUNK = 4  # planes per block when building the Jacobian (bounds memory to ~40 MB)
# Coarse multi-start: pupil grid, planes used, iterations, and primary-astigmatism starts (waves).
_COARSE_SAMPLES = 32
_COARSE_PLANES = 11
_COARSE_ITER = 15
_ASTIG_STARTS = ((0.0, 0.0), (0.15, 0.0), (-0.15, 0.0), (0.0, 0.15), (0.0, -0.15))


@dataclass
class RetrievalResult:
    """Outcome of :func:`fit_pupil`.

    Attributes
    ----------
    psf : PupilPSF
        The fitted model, ``mask = base_mask + ZernikeMask(coefficients)``, with the caller's
        ``z_range`` and the ``pupil_samples`` used in the fit. ``psf.images(x0, y0, z + z0, ...)``
        times ``photons`` plus ``background`` reproduces the fitted stack.
    coefficients : dict of (int, int) -> float
        Fitted Zernike coefficients ``(n, m) -> waves RMS`` (Noll normalisation, ``m < 0`` the
        sine terms), relative to ``base_mask``.
    x0, y0 : float
        Fitted lateral bead position (nm) in the ROI frame (outer corner of pixel (0, 0) at 0,
        x along columns, y along rows).
    z0 : float
        Fitted axial offset (nm): plane ``i`` shows the bead at defocus ``z[i] + z0``.
    photons : ndarray, shape (Nz,)
        Per-plane scale (photons, or the stack's units), the total over the unbounded plane.
    background : ndarray, shape (Nz,)
        Per-plane background (stack units per pixel).
    residual_rms : float
        Relative residual ``||data - model|| / ||data||`` (unweighted, over the whole stack).
    n_iterations : int
        Levenberg-Marquardt iterations of the full-resolution fit over all passes (the coarse
        multi-start that precedes it is not counted).
    converged : bool
        Whether the last pass met its tolerance before ``max_iter``.
    """

    psf: PupilPSF
    coefficients: dict[tuple[int, int], float]
    x0: float
    y0: float
    z0: float
    photons: NDArray[np.float64]
    background: NDArray[np.float64]
    residual_rms: float
    n_iterations: int
    converged: bool


def zernike_terms(max_order: int) -> list[tuple[int, int]]:
    """The ``(n, m)`` fitted by :func:`fit_pupil`: ``2 <= n <= max_order``, without ``(2, 0)``.

    Ordered by ``n`` then ``m``.
    """
    return [
        (n, m)
        for n in range(2, int(max_order) + 1)
        for m in range(-n, n + 1, 2)
        if (n, m) != (2, 0)
    ]


class _StackModel:
    """Unit-photon images of one emitter on a fixed window with a variable extra pupil phase.

    Uses the pupil grid of a :class:`PupilPSF` (built with ``base_mask``); all images follow the
    same exact pixel integration as :meth:`PupilPSF.images`.
    """

    def __init__(
        self,
        psf: PupilPSF,
        terms: list[tuple[int, int]],
        shape: tuple[int, int],
        pixel_size: float,
    ) -> None:
        self.psf = psf
        self.terms = terms
        m = psf._m
        _, inside, rho, phi = psf.pupil_coordinates()
        # 2 pi Z_j on the pupil grid (zero outside, where the pupil vanishes anyway).
        self.basis = (
            np.stack(
                [np.where(inside, 2 * np.pi * zernike(n, mm, rho, phi), 0.0) for n, mm in terms]
            )
            if terms
            else np.zeros((0, m, m))
        )
        self.pupil0 = psf._pupil0
        self.kz = psf._kz
        # Parseval: sum |ifft2(P)|^2 = sum |P|^2 / M^2 for any phase, so the norm is constant.
        norm = float(np.sum(np.abs(self.pupil0) ** 2)) / m**2
        self.rows, self.cols = shape
        self.a = pixel_size
        self.k = psf._k
        # fft2 restricted to the kept OTF bins, as a matrix: F[p, s] = exp(-2 pi i idx_p s / M).
        self.F = np.exp(-2j * np.pi * np.outer(psf._otf_idx, np.arange(m)) / m)
        self.scale = (pixel_size / psf.field_size) ** 2 / norm
        self.m = m

    # -- building blocks ---------------------------------------------------------------------
    def factors(self, x0: float, y0: float):
        """Row/column factors ``G`` (n, M) and their derivatives with respect to x0/y0."""
        ex = self.psf.shift_factors(pixel_centres(self.cols, self.a) - x0, self.a)
        ey = self.psf.shift_factors(pixel_centres(self.rows, self.a) - y0, self.a)
        gx, gy = ex @ self.F, ey @ self.F
        dgx, dgy = (ex * (-1j * self.k)) @ self.F, (ey * (-1j * self.k)) @ self.F
        return gx, gy, dgx, dgy

    def pixels(self, inten: NDArray, gx: NDArray, gy: NDArray) -> NDArray[np.float64]:
        """``Re(G_y I G_x^T) * scale`` for real ``I`` of shape (..., M, M) -> (..., rows, cols).

        Written as two large matrix products (not a batch of small ones, which multithreaded
        BLAS handles poorly).
        """
        lead = inten.shape[:-2]
        m, rows, cols = self.m, self.rows, self.cols
        n = int(np.prod(lead, dtype=np.int64))
        gxc = np.concatenate([gx.real, gx.imag], axis=0)  # (2C, M)
        t = inten.reshape(n * m, m) @ gxc.T  # (n*M, 2C): [I Gx.re^T, I Gx.im^T]
        t = t.reshape(n, m, 2, cols).transpose(2, 1, 0, 3).reshape(2 * m, n * cols)
        gyc = np.concatenate([gy.real, -gy.imag], axis=1)  # (R, 2M)
        out = (gyc @ t).reshape(rows, n, cols).transpose(1, 0, 2)
        return (out * self.scale).reshape(*lead, rows, cols)

    def pupils(self, coef: NDArray[np.float64], zdef: NDArray[np.float64]) -> NDArray:
        """Pupils ``P_i`` (Nz, M, M) with the extra phase and each plane's defocus ``zdef`` (nm)."""
        extra = np.tensordot(coef, self.basis, axes=(0, 0)) if coef.size else 0.0
        p = self.pupil0 * np.exp(1j * extra)
        return p[None] * np.exp(1j * self.kz[None] * zdef[:, None, None])

    def images(self, coef, x0, y0, zdef) -> NDArray[np.float64]:
        """Unit-photon images (Nz, rows, cols)."""
        gx, gy, _, _ = self.factors(x0, y0)
        e = sfft.ifft2(self.pupils(coef, zdef), axes=(-2, -1), workers=-1)
        return self.pixels((e * e.conj()).real, gx, gy)

    def jacobian(self, coef, x0, y0, zdef) -> tuple[NDArray, NDArray]:
        """Images (Nz, R, C) and derivatives (Nz, R, C, nt + 3) w.r.t. (coef..., x0, y0, z0).

        The derivatives with respect to the pupil phase are computed in single precision (they
        only steer the optimiser; the images and residuals stay in double precision).
        """
        gx, gy, dgx, dgy = self.factors(x0, y0)
        gx32, gy32 = gx.astype(np.complex64), gy.astype(np.complex64)
        nt = self.basis.shape[0]
        nz = zdef.size
        img = np.empty((nz, self.rows, self.cols))
        der = np.empty((nz, self.rows, self.cols, nt + 3))
        gen = np.concatenate([self.basis, self.kz[None]], axis=0).astype(np.float32)
        for s in range(0, nz, _CHUNK):
            sl = slice(s, min(s + _CHUNK, nz))
            p = self.pupils(coef, zdef[sl])  # (c, M, M)
            e = sfft.ifft2(p, axes=(-2, -1), workers=-1)
            inten = (e * e.conj()).real
            img[sl] = self.pixels(inten, gx, gy)
            der[sl, :, :, nt] = self.pixels(inten, dgx, gy)
            der[sl, :, :, nt + 1] = self.pixels(inten, gx, dgy)
            p32 = (1j * p).astype(np.complex64)
            de = sfft.ifft2(p32[:, None] * gen[None], axes=(-2, -1), workers=-1)
            dinten = 2.0 * (e.conj().astype(np.complex64)[:, None] * de).real  # (c, nt+1, M, M)
            dpix = self.pixels(dinten, gx32, gy32)  # (c, nt + 1, R, C)
            der[sl, :, :, :nt] = np.moveaxis(dpix[:, :nt], 1, -1)
            der[sl, :, :, nt + 2] = dpix[:, nt]
        return img, der


def _linear(f: NDArray, sw: NDArray, d: NDArray):
    """Per-plane weighted least squares of ``d ~ N f + b``.

    Parameters
    ----------
    f : ndarray, shape (..., planes, npix)
        Unit-photon images.
    sw, d : ndarray, shape (planes, npix)
        Square roots of the weights, and the data.

    Returns
    -------
    lin : ndarray, shape (..., planes, 2)
        Photons ``N`` and background ``b`` per plane.
    q : ndarray, shape (..., planes, npix, 2)
        Orthonormal basis of the weighted linear model (for the projected Jacobian).
    res : ndarray, shape (..., planes, npix)
        Weighted residuals ``sw * (d - N f - b)``.
    """
    basis = np.stack([f, np.ones_like(f)], axis=-1) * sw[..., None]
    q, r = np.linalg.qr(basis)
    swd = sw * d
    qt = np.einsum("...nik,...ni->...nk", q, swd)
    lin = np.linalg.solve(r, qt[..., None])[..., 0]
    res = swd - np.einsum("...nik,...nk->...ni", q, qt)
    return lin, q, res


_STEP = 100.0  # nm per unit of the internal position parameters


def _solve(
    model: _StackModel,
    zs: NDArray,
    d: NDArray,
    sw: NDArray,
    coef: NDArray,
    pos: tuple[float, float, float],
    max_iter: int,
) -> tuple[NDArray, tuple[float, float, float], float, int, bool]:
    """Levenberg-Marquardt fit of ``(coef, x0, y0, z0)`` with photons/background projected out.

    ``d`` and ``sw`` have shape (planes, npix). Returns the coefficients, the position (nm), the
    final cost ``||sw (d - mu)||^2 / 2``, the number of iterations and the convergence flag.
    """
    nt = coef.size
    nz = zs.size
    xi, yi, zi = pos

    def unpack(theta: NDArray):
        return (
            theta[:nt],
            xi + _STEP * theta[nt],
            yi + _STEP * theta[nt + 1],
            zi + _STEP * theta[nt + 2],
        )

    def fun(theta: NDArray) -> NDArray:
        c, x0, y0, z0 = unpack(theta)
        f = model.images(c, x0, y0, zs + z0).reshape(nz, -1)
        return _linear(f, sw, d)[2].ravel()

    def jac(theta: NDArray) -> NDArray:
        # Kaufman's approximation: derivatives of mu projected off the (photons, background) span.
        c, x0, y0, z0 = unpack(theta)
        img, der = model.jacobian(c, x0, y0, zs + z0)
        lin, q, _ = _linear(img.reshape(nz, -1), sw, d)
        dw = der.reshape(nz, -1, nt + 3) * (lin[:, 0, None, None] * sw[..., None])
        dw[..., nt:] *= _STEP
        proj = dw - np.einsum("nik,nkj->nij", q, np.einsum("nik,nij->nkj", q, dw))
        return -proj.reshape(-1, nt + 3)

    theta0 = np.concatenate([coef, np.zeros(3)])
    theta, cost, iters, converged = _levenberg_marquardt(fun, jac, theta0, max_iter)
    c, x0, y0, z0 = unpack(theta)
    return c, (float(x0), float(y0), float(z0)), cost, iters, converged


def _scan_z0(model: _StackModel, coef, xi, yi, zs, d, sw) -> float:
    """``z0`` (nm) on a 50 nm grid over +-min(600 nm, half the stack's span) minimising the cost."""
    half = min(600.0, float(np.ptp(zs)) / 2)
    zgrid = np.linspace(-half, half, 2 * int(np.ceil(half / 50.0)) + 1)
    nz = zs.size
    zdef = (zs[None, :] + zgrid[:, None]).ravel()
    f = model.images(coef, xi, yi, zdef).reshape(zgrid.size, nz, -1)
    cost = np.sum(_linear(f, sw, d)[2] ** 2, axis=(-2, -1))
    return float(zgrid[int(np.argmin(cost))])


def _levenberg_marquardt(
    fun: Callable[[NDArray], NDArray],
    jac: Callable[[NDArray], NDArray],
    theta: NDArray[np.float64],
    max_iter: int,
    tol: float = 1e-6,
) -> tuple[NDArray[np.float64], float, int, bool]:
    """Minimise ``||fun(theta)||^2 / 2`` by Levenberg-Marquardt with Marquardt's scaling.

    Converged when a step moves the parameters by less than ``sqrt(tol)`` of their standard
    errors (``delta^T J^T J delta / s^2 < tol`` with ``s^2`` the residual variance), or when the
    cost no longer decreases measurably. Returns ``(theta, cost, iterations, converged)``.
    """
    r = fun(theta)
    cost = 0.5 * float(r @ r)
    lam = 1e-3
    n_par = theta.size
    dof = max(r.size - n_par, 1)
    for it in range(1, max_iter + 1):
        j = jac(theta)
        a = j.T @ j
        g = j.T @ r
        diag = np.maximum(np.diag(a), 1e-12 * max(float(np.max(np.diag(a))), 1e-300))
        s2 = max(2.0 * cost / dof, 1e-300)
        while True:
            try:
                delta = -np.linalg.solve(a + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            r_new = fun(theta + delta)
            cost_new = 0.5 * float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            lam *= 4.0
            if lam > 1e12:
                logger.warning("Levenberg-Marquardt could not decrease the cost; stopping")
                return theta, cost, it, False
        small_step = float(delta @ a @ delta) / s2 < tol
        flat = cost - cost_new <= 1e-12 * cost
        theta, r, cost = theta + delta, r_new, cost_new
        lam = max(lam / 3.0, 1e-9)
        if small_step or flat:
            return theta, cost, it, True
    return theta, cost, max_iter, False


def _validate(stack: ArrayLike, z: ArrayLike, pixel_size: float):
    data = np.asarray(stack, dtype=np.float64)
    if data.ndim != 3:
        raise ValueError(f"stack must be 3-D (Nz, rows, cols), got shape {data.shape}")
    nz, rows, cols = data.shape
    if nz < 3:
        raise ValueError(f"stack must hold at least 3 planes to fit the pupil, got {nz}")
    if rows < 3 or cols < 3:
        raise ValueError(f"each plane must be at least 3 x 3 pixels, got {rows} x {cols}")
    if not np.all(np.isfinite(data)):
        raise ValueError("stack must be finite (no NaN or inf)")
    zs = np.asarray(z, dtype=np.float64)
    if zs.ndim != 1 or zs.size != nz:
        raise ValueError(
            f"z must be 1-D with one stage position per plane ({nz}), got shape {zs.shape}"
        )
    if not np.all(np.isfinite(zs)):
        raise ValueError("z must be finite (no NaN or inf)")
    if np.ptp(zs) <= 0:
        raise ValueError("z must hold at least two different stage positions")
    px = check_pixel_size(pixel_size)
    if not np.any(data > 0):
        raise ValueError("stack holds no signal (no positive pixel)")
    return data, zs, px


def _single_threaded_blas(func):
    """Run ``func`` with BLAS limited to one thread (threadpoolctl)."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return func(*args, **kwargs)

    return wrapper


@_single_threaded_blas
def fit_pupil(
    stack: ArrayLike,
    z: ArrayLike,
    pixel_size: float,
    *,
    na: float,
    wavelength: float,
    n_immersion: float = 1.518,
    base_mask: Mask | None = None,
    max_order: int = 6,
    initial: Mapping[tuple[int, int], float] | None = None,
    z_range: tuple[float, float] | None = None,
    weights: Literal["poisson", "uniform"] = "poisson",
    max_iter: int = 50,
    pupil_samples: int = 64,
) -> RetrievalResult:
    """Fit Zernike aberrations (on top of ``base_mask``) and the bead position to a bead stack.

    Parameters
    ----------
    stack : array_like, shape (Nz, R, C)
        Averaged bead images in photons (or any linear units), one bead near the ROI centre.
    z : array_like, shape (Nz,)
        Stage positions of the planes in nm (``z = 0`` near focus), in the model's convention:
        plane ``i`` is modelled at defocus ``z[i] + z0``.
    pixel_size : float
        Pixel size in nm (sample space).
    na, wavelength, n_immersion : float
        Numerical aperture, emission wavelength (nm) and refractive index of the immersion
        medium.
    base_mask : callable, optional
        Known phase mask ``phase(rho, phi)`` in radians (e.g. :class:`~.masks.DoubleHelixMask`);
        the fitted Zernike phase is added to it. ``None``: clear pupil.
    max_order : int
        Highest radial order ``n`` fitted (>= 2). The fitted terms are :func:`zernike_terms`.
    initial : mapping (n, m) -> float, optional
        Starting coefficients (waves RMS) for some of the fitted terms; the others start at 0.
    z_range : (float, float), optional
        Axial range (nm) of the returned model; default the stack's defocus range
        ``(min(z) + z0, max(z) + z0)``.
    weights : {"poisson", "uniform"}
        ``"poisson"``: weighted least squares with weights ``1 / max(data, floor)`` and then a
        refinement pass with ``1 / max(model, floor)`` (``floor`` = 1e-3 of the stack's maximum);
        ``"uniform"``: ordinary least squares.
    max_iter : int
        Maximum Levenberg-Marquardt iterations per pass of the full-resolution fit.
    pupil_samples : int
        Pupil samples across the diameter (sets the model's period, see :class:`PupilPSF`).

    Returns
    -------
    RetrievalResult
        The fitted model, coefficients, position, per-plane photons/background and diagnostics.

    Raises
    ------
    ValueError
        For a stack that is not 3-D, has fewer than 3 planes or non-finite values, a ``z`` of
        the wrong length, a non-positive pixel size, unknown ``weights``, ``max_order < 2``, or
        ``initial`` keys that are not fitted terms.

    Notes
    -----
    The fit is local: see the module notes on the multi-start that precedes it and on the sign
    of ``z``. The weights are scale-free: a normalised stack gives the same fit as in photons.
    """
    data, zs, px = _validate(stack, z, pixel_size)
    terms = _check_options(max_order, weights, max_iter, z_range)
    coef0 = _initial_coefficients(initial, terms, max_order)
    optics = _Optics(na, wavelength, n_immersion)
    model, coarse = _stack_models(optics, base_mask, pupil_samples, terms, data.shape[1:], px)
    beads = _Beads(zs, data.reshape(len(zs), -1), weights, 1e-3 * float(data.max()))
    sw = beads.root_weights(beads.d)
    coef, pos = _multi_start(coarse, beads, sw, coef0, _centroid(data, px))
    fit = _refine(model, beads, sw, coef, pos, int(max_iter))
    return _result(model, beads, fit, optics, base_mask, pupil_samples, z_range)


def _check_options(
    max_order: int, weights: str, max_iter: int, z_range: tuple[float, float] | None
) -> list[tuple[int, int]]:
    """Check :func:`fit_pupil`'s options; return the fitted Zernike terms."""
    if int(max_order) != max_order or max_order < 2:
        raise ValueError(f"max_order must be an integer >= 2, got {max_order!r}")
    if weights not in ("poisson", "uniform"):
        raise ValueError(f"weights must be 'poisson' or 'uniform', got {weights!r}")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter!r}")
    if z_range is not None and not float(z_range[0]) < float(z_range[1]):
        raise ValueError(f"z_range must be (z_min, z_max) with z_min < z_max, got {z_range}")
    return zernike_terms(int(max_order))


def _initial_coefficients(
    initial: Mapping[tuple[int, int], float] | None, terms: list[tuple[int, int]], max_order: int
) -> NDArray[np.float64]:
    """Starting coefficients (waves RMS) of ``terms``: ``initial`` where given, else 0."""
    coef0 = np.zeros(len(terms))
    if initial:
        for key, val in initial.items():
            key = (int(key[0]), int(key[1]))
            if key not in terms:
                raise ValueError(
                    f"initial term {key} is not fitted; fitted terms (n, m) are "
                    f"2 <= n <= {max_order} without (2, 0)"
                )
            coef0[terms.index(key)] = float(val)
    return coef0


@dataclass(frozen=True)
class _Optics:
    """What every :class:`PupilPSF` of one fit shares."""

    na: float
    wavelength: float
    n_immersion: float

    def psf(self, mask: Mask | None, pupil_samples: int, **kwargs) -> PupilPSF:
        return PupilPSF(
            mask,
            na=self.na,
            wavelength=self.wavelength,
            n_immersion=self.n_immersion,
            pupil_samples=pupil_samples,
            **kwargs,
        )


def _stack_models(
    optics: _Optics,
    base_mask: Mask | None,
    pupil_samples: int,
    terms: list[tuple[int, int]],
    shape: tuple[int, int],
    px: float,
) -> tuple[_StackModel, _StackModel]:
    """The full model and the coarse one of the multi-start (the full one when the coarse
    grid's period is too short for the ROI)."""
    rows, cols = shape
    psf0 = optics.psf(base_mask, pupil_samples)
    if max(rows, cols) * px >= psf0.field_size / 2:
        raise ValueError(
            f"the ROI ({rows} x {cols} pixels of {px} nm) must be smaller than half the model "
            f"period ({psf0.field_size:.0f} nm); increase pupil_samples"
        )
    model = _StackModel(psf0, terms, (rows, cols), px)
    coarse = model
    if pupil_samples > _COARSE_SAMPLES:
        small = optics.psf(base_mask, _COARSE_SAMPLES)
        if max(rows, cols) * px < small.field_size / 2:
            coarse = _StackModel(small, terms, (rows, cols), px)
    return model, coarse


def _centroid(data: NDArray[np.float64], px: float) -> tuple[float, float]:
    """Initial lateral position (nm): centroid of the background-subtracted sum of the planes."""
    nz, rows, cols = data.shape
    border = np.concatenate(
        [data[:, 0].ravel(), data[:, -1].ravel(), data[:, :, 0].ravel(), data[:, :, -1].ravel()]
    )
    tot = np.clip(data.sum(axis=0) - nz * float(np.median(border)), 0.0, None)
    if tot.sum() > 0:
        xi = float((tot.sum(axis=0) * pixel_centres(cols, px)).sum() / tot.sum())
        yi = float((tot.sum(axis=1) * pixel_centres(rows, px)).sum() / tot.sum())
    else:
        xi, yi = cols * px / 2, rows * px / 2
    return xi, yi


@dataclass(frozen=True)
class _Beads:
    """The stack being fitted: stage positions ``zs`` (Nz,), data ``d`` (Nz, npix), the
    weighting (``"poisson"`` or ``"uniform"``) and the floor of the Poisson weights."""

    zs: NDArray[np.float64]
    d: NDArray[np.float64]
    weights: str
    floor: float

    def root_weights(self, values: NDArray) -> NDArray:
        """Square roots of the weights for expected values ``values`` (Nz, npix)."""
        if self.weights == "uniform":
            return np.ones_like(self.d)
        return 1.0 / np.sqrt(np.maximum(values, self.floor))


def _multi_start(
    coarse: _StackModel,
    beads: _Beads,
    sw: NDArray,
    coef0: NDArray[np.float64],
    xy: tuple[float, float],
) -> tuple[NDArray[np.float64], tuple[float, float, float]]:
    """The best of short fits on the coarse model (fewer planes, coarser pupil grid) started
    from ``coef0`` plus each primary-astigmatism offset of :data:`_ASTIG_STARTS`.

    The primary astigmatism is the dominant even aberration of most systems, and its sign is
    what a local fit started at zero can get wrong for strongly aberrated stacks; it is tried
    both ways along both axes. Returns the coefficients and the position (nm).
    """
    xi, yi = xy
    zs, d, terms = beads.zs, beads.d, coarse.terms
    nz = zs.size
    sub = np.unique(np.round(np.linspace(0, nz - 1, min(nz, _COARSE_PLANES))).astype(int))
    i_c, i_s = terms.index((2, 2)), terms.index((2, -2))
    best: tuple[float, NDArray, tuple[float, float, float]] | None = None
    for a_c, a_s in _ASTIG_STARTS:
        start = coef0.copy()
        start[i_c] += a_c
        start[i_s] += a_s
        zi = _scan_z0(coarse, start, xi, yi, zs[sub], d[sub], sw[sub])
        c, pos, cost, _, _ = _solve(
            coarse, zs[sub], d[sub], sw[sub], start, (xi, yi, zi), _COARSE_ITER
        )
        logger.debug("coarse start astig (%+.2f, %+.2f): cost %.6g", a_c, a_s, cost)
        if best is None or cost < best[0]:
            best = (cost, c, pos)
    assert best is not None
    return best[1], best[2]


class _Fit(NamedTuple):
    """End of the full-resolution fit: coefficients, position (nm), the square roots of the
    last weights, Levenberg-Marquardt iterations over all passes and convergence."""

    coef: NDArray[np.float64]
    pos: tuple[float, float, float]
    sw: NDArray[np.float64]
    n_iter: int
    converged: bool


def _refine(
    model: _StackModel,
    beads: _Beads,
    sw: NDArray,
    coef: NDArray[np.float64],
    pos: tuple[float, float, float],
    max_iter: int,
) -> _Fit:
    """The full-resolution fit: one pass, and with Poisson weights a second one with the
    weights of the first pass's model."""
    zs, d = beads.zs, beads.d
    nz = zs.size
    passes = 2 if beads.weights == "poisson" else 1
    converged = False
    n_iter = 0
    for ipass in range(passes):
        if ipass > 0:
            f = model.images(coef, pos[0], pos[1], zs + pos[2]).reshape(nz, -1)
            lin = _linear(f, sw, d)[0]
            sw = beads.root_weights(f * lin[:, :1] + lin[:, 1:])
        coef, pos, cost, iters, converged = _solve(model, zs, d, sw, coef, pos, max_iter)
        n_iter += iters
        logger.info(
            "fit_pupil pass %d: cost %.6g after %d iterations (converged: %s)",
            ipass + 1,
            cost,
            iters,
            converged,
        )
    return _Fit(coef, pos, sw, n_iter, converged)


def _result(
    model: _StackModel,
    beads: _Beads,
    fit: _Fit,
    optics: _Optics,
    base_mask: Mask | None,
    pupil_samples: int,
    z_range: tuple[float, float] | None,
) -> RetrievalResult:
    """The fitted model and the per-plane photons and background of the fit."""
    zs, d = beads.zs, beads.d
    x0, y0, z0 = fit.pos
    f = model.images(fit.coef, x0, y0, zs + z0).reshape(zs.size, -1)
    lin = _linear(f, fit.sw, d)[0]
    mu = f * lin[:, :1] + lin[:, 1:]
    residual_rms = float(np.linalg.norm(d - mu) / np.linalg.norm(d))
    coefficients = {t: float(c) for t, c in zip(model.terms, fit.coef, strict=True)}
    zmask = ZernikeMask(dict(coefficients))
    mask = zmask if base_mask is None else combine([base_mask, zmask])
    zr = (
        (float(zs.min() + z0), float(zs.max() + z0))
        if z_range is None
        else (float(z_range[0]), float(z_range[1]))
    )
    psf = optics.psf(mask, pupil_samples, z_range=zr, name="retrieved")
    return RetrievalResult(
        psf=psf,
        coefficients=coefficients,
        x0=x0,
        y0=y0,
        z0=z0,
        photons=lin[:, 0].copy(),
        background=lin[:, 1].copy(),
        residual_rms=residual_rms,
        n_iterations=fit.n_iter,
        converged=fit.converged,
    )
