"""Fisher information and Cramer-Rao lower bounds (CRLB) of PSF models.

For an expected image ``mu_k(theta) = sum_e photons_e * psf_e,k + b`` (photons per pixel ``k``)
and independent pixels, the Fisher information is

``F_ij = sum_k (d mu_k / d theta_i)(d mu_k / d theta_j) / v_k``

with the effective variance ``v_k``:

- ``"poisson"``: ``v_k = mu_k`` (an ideal photon-counting camera);
- ``"emccd"``: ``v_k = 2 mu_k``. The excess noise factor of an EMCCD at high gain is
  ``sqrt(2)``, which doubles the variance of the detected photons and halves the Fisher
  information (``F_emccd = F_poisson / 2``), so every CRLB grows by ``sqrt(2)``;
- ``"scmos"``: ``v_k = mu_k + sigma_k^2`` with ``sigma_k^2`` the read-noise variance in
  photons^2 (ADU variance / gain^2). This is the Poisson approximation of Huang et al., Nature
  Methods 10, 653 (2013): ``(D - o)/g + sigma^2/g^2`` is treated as Poisson with mean
  ``mu + sigma^2/g^2``.

Parameters are ordered per emitter ``[x, y, z, photons]`` (nm, nm, nm, photons), emitter by
emitter, followed by one background parameter (photons per pixel, an additive constant over the
window), so ``P = 4 K + 1``. The CRLB of parameter ``i`` is ``sqrt((F^-1)_ii)``, a standard
deviation in the parameter's unit.

Singular information
--------------------
A parameter that carries no information at all (its row of ``F`` is zero, e.g. ``z`` of a
z-independent model, or the position of an emitter with 0 photons) decouples from the rest; its
bound is reported as ``inf`` and the others are computed from the remaining block, which is
exact. Any other singularity (e.g. two emitters at the same place, whose positions cannot be told
apart) raises :class:`numpy.linalg.LinAlgError` with ``singular="raise"`` (the default); with
``singular="pinv"`` the Moore-Penrose pseudo-inverse is used instead, which gives finite but
optimistic numbers for the unidentifiable combinations.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .psf.base import PSFModel, as_emitters, check_pixel_size, check_shape
from .solvers.variance import noise_factor_of

__all__ = [
    "NOISE_MODELS",
    "crlb",
    "crlb_from_fisher",
    "crlb_single",
    "fisher_information",
]

#: Noise models understood by :func:`fisher_information`.
NOISE_MODELS: tuple[str, ...] = ("poisson", "emccd", "scmos")

Noise = Literal["poisson", "emccd", "scmos"]
Singular = Literal["raise", "pinv"]

# Relative eigenvalue threshold of the diagonally scaled (correlation) Fisher matrix below which
# it is called singular.
_RCOND = 1e-12


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------
def _check_noise(noise: str) -> None:
    if noise not in NOISE_MODELS:
        raise ValueError(f"noise must be one of {', '.join(NOISE_MODELS)}; got {noise!r}")


def _variance(
    mu: NDArray[np.float64],
    noise: str,
    read_variance: ArrayLike | None,
) -> NDArray[np.float64]:
    """Effective per-pixel variance ``(..., rows, cols)`` for ``noise``."""
    _check_noise(noise)
    shot = noise_factor_of(noise) * mu
    if noise == "scmos" and read_variance is None:
        raise ValueError("noise='scmos' needs read_variance (photons^2, scalar or per pixel)")
    if read_variance is not None:
        if noise == "poisson":
            raise ValueError("read_variance is only used with noise='scmos' or 'emccd'")
        rv = np.asarray(read_variance, dtype=np.float64)
        if rv.ndim not in (0, 2) or (rv.ndim == 2 and rv.shape != mu.shape[-2:]):
            raise ValueError(
                f"read_variance must be a scalar or a (rows, cols) = {mu.shape[-2:]} map, "
                f"got shape {rv.shape}"
            )
        if not np.all(np.isfinite(rv)) or np.any(rv < 0):
            raise ValueError("read_variance must be finite and >= 0 photons^2")
        var = shot + rv
    else:
        var = shot
    if not np.all(var > 0):
        raise ValueError(
            "the expected signal (model image + background, + read variance for sCMOS) must be "
            "> 0 photons in every pixel; use a background > 0"
        )
    return var


def _background_map(background: ArrayLike, shape: tuple[int, int]) -> NDArray[np.float64]:
    b = np.asarray(background, dtype=np.float64)
    if b.ndim not in (0, 2) or (b.ndim == 2 and b.shape != shape):
        raise ValueError(
            f"background must be a scalar or a (rows, cols) = {shape} map in photons per pixel, "
            f"got shape {b.shape}"
        )
    _check_background_values(b)
    return np.broadcast_to(b, shape)


def _check_background_values(b: NDArray[np.float64]) -> None:
    if not np.all(np.isfinite(b)) or np.any(b < 0):
        raise ValueError("background must be finite and >= 0 photons per pixel")


def _with_background(grads: NDArray[np.float64]) -> NDArray[np.float64]:
    """Gradients ``(B, P, npix)`` followed by the background's (1 in every pixel)."""
    out = np.empty((grads.shape[0], grads.shape[1] + 1, grads.shape[2]))
    out[:, :-1] = grads
    out[:, -1] = 1.0
    return out


def _fisher_batch(grads: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
    """``F[b] = G[b] diag(1/var[b]) G[b]^T`` for grads ``(B, P, npix)``, var ``(B, npix)``."""
    w = grads / var[:, None, :]
    f = np.einsum("bpk,bqk->bpq", w, grads)
    return 0.5 * (f + np.swapaxes(f, -1, -2))


def crlb_from_fisher(fisher: ArrayLike, *, singular: Singular = "raise") -> NDArray[np.float64]:
    """Square roots of the diagonal of the inverse Fisher matrix.

    Parameters
    ----------
    fisher : array_like, shape (P, P) or (B, P, P)
        Symmetric positive semi-definite Fisher information matrices (units: 1/unit_i/unit_j).
    singular : {"raise", "pinv"}
        What to do when the informative block is singular (see the module docstring).
        Parameters with no information at all always get ``inf``.

    Returns
    -------
    ndarray, shape (P,) or (B, P)
        Standard deviations ``sqrt((F^-1)_ii)`` in the parameters' units.

    Raises
    ------
    numpy.linalg.LinAlgError
        With ``singular="raise"`` when the informative block is singular.
    ValueError
        For an unknown ``singular`` or a matrix that is not square.
    """
    if singular not in ("raise", "pinv"):
        raise ValueError(f"singular must be 'raise' or 'pinv', got {singular!r}")
    f = np.asarray(fisher, dtype=np.float64)
    single = f.ndim == 2
    if single:
        f = f[None]
    if f.ndim != 3 or f.shape[-1] != f.shape[-2]:
        raise ValueError(f"fisher must have shape (P, P) or (B, P, P), got {np.shape(fisher)}")
    out = np.full(f.shape[:2], np.inf)
    for b, fb in enumerate(f):
        d = np.diag(fb).copy()
        scale = np.max(np.abs(d), initial=0.0)
        info = d > scale * 1e-300 if scale > 0 else np.zeros_like(d, dtype=bool)
        idx = np.flatnonzero(info)
        if len(idx) == 0:
            continue
        sub = fb[np.ix_(idx, idx)]
        s = 1.0 / np.sqrt(d[idx])
        corr = sub * s[:, None] * s[None, :]  # unit diagonal: removes the units' scale
        evals, evecs = np.linalg.eigh(corr)
        lo, hi = evals[0], evals[-1]
        if lo <= _RCOND * hi:
            if singular == "raise":
                raise np.linalg.LinAlgError(
                    "the Fisher information matrix is singular: some parameter combination "
                    f"cannot be estimated (smallest/largest eigenvalue of the scaled matrix "
                    f"{lo:.3g}/{hi:.3g}); e.g. emitters that coincide. Pass singular='pinv' "
                    "for a pseudo-inverse"
                )
            keep = evals > _RCOND * hi
            inv_corr = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
        else:
            inv_corr = (evecs / evals) @ evecs.T
        var = np.diag(inv_corr) * s**2
        out[b, idx] = np.sqrt(np.maximum(var, 0.0))
    return out[0] if single else out


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------
def fisher_information(
    model: PSFModel,
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    photons: ArrayLike,
    background: ArrayLike,
    shape: tuple[int, int],
    pixel_size: float,
    *,
    noise: Noise = "poisson",
    origin: tuple[float, float] = (0.0, 0.0),
    read_variance: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Fisher information matrix of K emitters and a constant background in one window.

    Parameters
    ----------
    model : PSFModel
        Any model with ``render`` and ``gradients`` (see :mod:`sparseloc.psf.base`).
    x, y, z : array_like, shape (K,)
        Emitter positions in nm (window coordinates, see ``origin``).
    photons : array_like, shape (K,)
        Emitter brightness in photons.
    background : float or ndarray (rows, cols)
        Background in photons per pixel. A map is allowed; the fitted background parameter is an
        additive constant on top of it (its derivative is 1 in every pixel).
    shape : (rows, cols)
        Window shape in pixels.
    pixel_size : float
        Pixel size in nm.
    noise : {"poisson", "emccd", "scmos"}
        Noise model (see the module docstring).
    origin : (float, float)
        Position (nm), x then y, of the window's outer corner of pixel (0, 0).
    read_variance : float or ndarray (rows, cols), optional
        sCMOS read-noise variance in photons^2; required for, and only allowed with, "scmos".

    Returns
    -------
    ndarray, shape (4K + 1, 4K + 1)
        Symmetric Fisher information; parameters ``[x_0, y_0, z_0, N_0, x_1, ..., b]``, in
        units of 1/(unit_i unit_j) (nm^-2 for positions, photons^-2 for brightness).

    Raises
    ------
    ValueError
        Unknown ``noise`` (the message lists the allowed values), a missing or misplaced
        ``read_variance``, a negative background, or a pixel whose expected variance is not
        positive (e.g. zero background with an ideal camera).
    """
    xs, ys, zs, ns = as_emitters(x, y, z, model.z_range, photons)
    shp = check_shape(shape)
    px = check_pixel_size(pixel_size)
    _check_noise(noise)
    bg = _background_map(background, shp)
    mu = model.render(xs, ys, zs, ns, shp, px, origin=origin) + bg
    var = _variance(mu, noise, read_variance)
    g = np.asarray(model.gradients(xs, ys, zs, ns, shp, px, origin=origin), dtype=np.float64)
    npix = shp[0] * shp[1]
    grads = _with_background(g.reshape(1, 4 * len(xs), npix))
    return _fisher_batch(grads, var.reshape(1, npix))[0]


def crlb(
    model: PSFModel,
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    photons: ArrayLike,
    background: ArrayLike,
    shape: tuple[int, int],
    pixel_size: float,
    *,
    noise: Noise = "poisson",
    origin: tuple[float, float] = (0.0, 0.0),
    read_variance: ArrayLike | None = None,
    return_background: bool = False,
    singular: Singular = "raise",
) -> NDArray[np.float64] | tuple[NDArray[np.float64], float]:
    """Cramer-Rao lower bounds of K emitters fitted jointly with a constant background.

    Parameters
    ----------
    model, x, y, z, photons, background, shape, pixel_size, noise, origin, read_variance
        As in :func:`fisher_information`.
    return_background : bool
        Also return the bound of the background parameter.
    singular : {"raise", "pinv"}
        Handling of a singular Fisher matrix (see the module docstring); parameters without
        any information get ``inf``.

    Returns
    -------
    bounds : ndarray, shape (K, 4)
        Standard deviations of x, y, z (nm) and photons (photons) per emitter.
    background_bound : float
        Only with ``return_background``: standard deviation of the background (photons/pixel).

    Raises
    ------
    numpy.linalg.LinAlgError
        With ``singular="raise"`` when some parameter combination is not identifiable.
    """
    f = fisher_information(
        model,
        x,
        y,
        z,
        photons,
        background,
        shape,
        pixel_size,
        noise=noise,
        origin=origin,
        read_variance=read_variance,
    )
    sd = crlb_from_fisher(f, singular=singular)
    bounds = sd[:-1].reshape(-1, 4)
    if return_background:
        return bounds, float(sd[-1])
    return bounds


def crlb_single(
    model: PSFModel,
    z: ArrayLike,
    photons: ArrayLike,
    background: ArrayLike,
    pixel_size: float,
    window: int | tuple[int, int] | None = None,
    *,
    noise: Noise = "poisson",
    read_variance: ArrayLike | None = None,
    singular: Singular = "raise",
) -> NDArray[np.float64]:
    """CRLB of one emitter at the centre of a window, for each z in an array.

    Each z is an independent single-emitter problem (emitter + constant background).

    Parameters
    ----------
    model : PSFModel
        The PSF model.
    z : array_like, shape (Z,)
        Axial positions in nm.
    photons : float or array_like (Z,)
        Emitter brightness in photons.
    background : float or array_like (Z,)
        Background in photons per pixel.
    pixel_size : float
        Pixel size in nm.
    window : int or (rows, cols), optional
        Window in pixels. Default: the smallest odd square ``2 * ceil(R / pixel_size) + 1``
        holding the disc of radius ``R = model.support_radius(pixel_size)``.
    noise, read_variance, singular
        As in :func:`crlb` (``read_variance`` a scalar or a (rows, cols) map).

    Returns
    -------
    ndarray, shape (Z, 4)
        Standard deviations of x, y, z (nm) and photons (photons) for each z.

    Notes
    -----
    The emitter sits at the window's centre, ``(cols * pixel_size / 2, rows * pixel_size / 2)``
    nm, which for an odd window is the centre of the middle pixel.
    """
    px = check_pixel_size(pixel_size)
    zs = np.atleast_1d(np.asarray(z, dtype=np.float64))
    if zs.ndim != 1:
        raise ValueError(f"z must be a scalar or a 1-D array, got shape {zs.shape}")
    if window is None:
        half = int(np.ceil(model.support_radius(px) / px))
        shp = (2 * half + 1, 2 * half + 1)
    elif np.ndim(window) == 0:
        shp = check_shape((int(window), int(window)))  # type: ignore[arg-type]
    else:
        shp = check_shape(window)  # type: ignore[arg-type]
    _check_noise(noise)
    try:
        ns, bs = np.broadcast_arrays(
            np.asarray(photons, dtype=np.float64), np.asarray(background, dtype=np.float64), zs
        )[:2]
    except ValueError as exc:
        raise ValueError("photons and background must be scalars or have the length of z") from exc
    _check_background_values(bs)
    nz = len(zs)
    cx, cy = shp[1] * px / 2.0, shp[0] * px / 2.0
    g = np.asarray(
        model.gradients(np.full(nz, cx), np.full(nz, cy), zs, ns, shp, px), dtype=np.float64
    )
    npix = shp[0] * shp[1]
    # g[:, 3] is d mu / d photons = the unit-photon image, so mu = N * g[:, 3] + b.
    mu = ns[:, None, None] * g[:, 3] + bs[:, None, None]
    var = _variance(mu, noise, read_variance).reshape(nz, npix)
    f = _fisher_batch(_with_background(g.reshape(nz, 4, npix)), var)
    return crlb_from_fisher(f, singular=singular)[:, :4]
