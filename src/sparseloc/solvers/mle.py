"""The multi-emitter maximum-likelihood fit of one window, its uncertainties and flags.

Model: ``mu = sum_k N_k psf(x_k, y_k, z_k) + b`` with a constant background ``b`` or a tilted
plane ``b0 + bx * u + by * v`` (``u``, ``v``: pixel offsets from the window centre divided by
half the window size, so the three background parameters share one scale). Where the caller
knows the background's shape over the window (``background_shape``: the run's background
estimate, :func:`sparseloc.solvers.frame_windows.background_shape`), the data choose between
the constant and that shape divided by its median, scaled by ``b`` (the background at the
window's median level): the shape is kept where it makes the window likelier than the
constant by :data:`SHAPE_MARGIN` and the model error's allowance, so that a haze varying
across a wide window is not light for emitters to take, while a shape that holds the
emitters' own light (an estimate from crowded frames) is not forced on windows whose
background is flat. The shape's fit is only tried where the constant fit's score along the
shape, ``dlog L / dbeta`` at ``beta = 0`` of the background ``b (1 + beta (s - 1))``, exceeds
the margin: the likelihood is concave in the background along that path, so its slope there
bounds what the shape can gain (the emitters' refit adds little; ``docs/benchmarks/haze.txt``).

Likelihoods (``noise``):

- ``"poisson"``: ``-log L = sum(mu - y log mu)``.
- ``"emccd"``: EM multiplication doubles the variance; the data are modelled as
  ``y / 2 ~ Poisson(mu / 2)``, i.e. the Poisson objective divided by 2. The estimate is the
  same as Poisson's, the Fisher information halves (uncertainties grow by sqrt 2).
- ``"scmos"``: per-pixel read noise (Huang et al. 2013): ``y + v ~ Poisson(mu + v)`` with
  ``v`` the read-noise variance in photons^2 (a scalar or a map).

Read noise of any camera (``read_variance``, photons^2: required for sCMOS, optional for
EMCCD) enters the same way, on the likelihood's scale: with the weight ``w`` below, the data
are modelled as ``w (y + v / w') ~ Poisson(w (mu + v / w'))`` with ``v / w' = w v``, which gives
``y`` the variance ``mu / w + v``: ``F mu / qe`` of shot noise (``F`` = 2 behind EM gain, else 1)
plus the read variance.

Censored pixels (``censored``): a pixel at the camera's saturation says only that its light
reached that level, not how far past it; it is left out of the likelihood (its terms carry
the weight 0), so a bright emitter's clipped peak does not flatten its fitted image.

Quantum efficiency (``qe``): a camera counts photoelectrons, ``e ~ Poisson(qe mu)``, and the
frames hold ``e / qe`` photons, whose variance is ``mu / qe``, not ``mu``. The likelihood of
the photoelectrons is ``qe`` times the Poisson objective in photons (times 1/2 for EMCCD), and
the sCMOS read variance ``v`` (photons^2, ``v_e / qe^2``) enters as ``qe v``. The estimate is
unchanged; the Fisher information, the uncertainties, the likelihood ratios of the count
selection and the deviance are those of the detected photoelectrons. ``qe = 1`` (the default)
is the plain photon-counting model.

The fit is Levenberg-Marquardt with Fisher scoring (:mod:`sparseloc.solvers.lm`, one rule for
every engine): the step solves ``(F + lam diag F) d = -grad`` with ``F = sum(w dmu dmu' / mu)``;
a step is taken only if the likelihood improves (then ``lam`` shrinks), else ``lam`` grows. z
is kept inside the model's range, photons and background positive, x and y within
``xy_margin`` pixels of the window. Spline tables fit on the numba engine where it runs
(:mod:`sparseloc.engine`), every other model on NumPy.

Uncertainties: the Cramer-Rao bound at the fitted parameters, ``sqrt(diag(F^-1))`` (x, y, z in
nm, photons), with the background parameters in ``F``. Goodness of fit: the deviance
``2 w sum(y log(y / mu) - (y - mu))`` per degree of freedom, with the likelihood's weight ``w``
(EMCCD, ``qe``), about 1 for a good fit.

Flags (one string per emitter, ``"ok"`` when fine) and the uncertainties written with them come
from one rule, :func:`fit_flags`: ``"z_edge"`` (z within 1 nm of the model's range, where the
true z may lie outside), ``"outside"`` (x or y outside the window), ``"bad_sigma"`` (a Fisher
matrix that is not positive definite, or an uncertainty that is not finite or absurd),
``"not_converged"``, ``"diverged"`` (non-finite or vanishing photons). ``z_edge``,
``bad_sigma`` and ``diverged`` rows have NaN uncertainties.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..dictionary import check_window
from ..engine import kernels
from ..psf.base import PSFModel
from ..psf.spline import SplinePSF
from .emitters import Emitters
from .lm import clamp, damped_system, make_levenberg_marquardt
from .variance import noise_factor_of

log = logging.getLogger(__name__)

__all__ = [
    "NOISE_MODELS",
    "SHAPE_MARGIN",
    "SIGMA_FLOOR_NM",
    "FitResult",
    "LikelihoodProblem",
    "check_qe",
    "fit_emitters",
    "fit_flags",
    "likelihood_weight",
]

NOISE_MODELS = ("poisson", "emccd", "scmos")
_MIN_PHOTONS = 1.0
_MIN_BG = 1e-3
#: Smallest position uncertainty (nm) a fit may report: ten times below the best optical
#: localization precisions (tenths of a nm); a smaller one is a numerical artefact.
SIGMA_FLOOR_NM = 0.01
# Smallest squared Cholesky pivot of the unit-diagonal Fisher matrix that counts as informative.
_FISHER_RCOND = 1e-12
#: How much likelier (log-likelihood) the background estimate's shape must make a window than a
#: constant for the fit to keep it: half the 0.1 % tail of a chi-square with one degree of
#: freedom (10.83), the one direction the shape adds to a constant, at the count selection's
#: false-alarm rate (:data:`~sparseloc.solvers.refine.LR_THRESHOLD`); plus, as there, half the
#: model error's allowance (:func:`~sparseloc.solvers.refine.error_allowance_at`).
SHAPE_MARGIN = 5.41


@dataclass
class FitResult:
    """A maximum-likelihood fit of K emitters and a background in one window.

    Attributes
    ----------
    emitters : Emitters
        Fitted positions (nm) and photons.
    sigma : ndarray, shape (K, 4)
        CRLB standard errors of x, y, z (nm) and photons at the fit.
    background : ndarray, shape (1,) or (3,)
        Background: ``b`` or ``(b0, bx, by)`` (photons/pixel; see the module notes).
    background_sigma : ndarray
        Standard errors of the background parameters.
    background_image : ndarray, shape (rows, cols)
        The fitted background over the window (photons/pixel).
    background_shape : ndarray, shape (rows, cols), or None
        The shape the background scales where the data chose it (see the module notes),
        None for a constant.
    model_image : ndarray, shape (rows, cols)
        Expected photons per pixel at the fit.
    log_likelihood : float
        ``log L`` up to a data-only constant (``-sum(w (mu - y log mu))``).
    deviance_per_dof : float
        Goodness of fit (about 1 for a good fit).
    flags : ndarray of str, shape (K,)
        ``"ok"`` or the reason the emitter is doubtful.
    converged : bool
    n_iter : int
    fisher : ndarray, shape (P, P)
        The Fisher matrix at the fit; ``sigma``, ``background_sigma``, ``flags`` and ``crlb``
        are computed from it (with ``window`` and ``z_range``) when first asked for.
    window : (x0, y0, x1, y1)
        Edges of the fitted window (nm).
    z_range : (float, float)
        The model's z range (nm).
    """

    emitters: Emitters
    background: NDArray[np.float64]
    model_image: NDArray[np.float64]
    log_likelihood: float
    deviance_per_dof: float
    converged: bool
    n_iter: int
    #: The Fisher matrix at the fit (P, P), the window's edges (x0, y0, x1, y1; nm) and the
    #: model's z range (nm): the uncertainties and flags below come from them.
    fisher: NDArray[np.float64] = field(repr=False)
    window: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    z_range: tuple[float, float] = (-np.inf, np.inf)
    history: list[str] = field(default_factory=list)
    background_image: NDArray[np.float64] | None = field(default=None, repr=False)
    #: The background shape the fit scaled (the window's, as given), or None for a constant.
    background_shape: NDArray[np.float64] | None = field(default=None, repr=False)
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    #: The model error's variance of the fit's window, kept when first computed
    #: (:func:`sparseloc.solvers.refine.error_variance`).
    _error: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def n_params(self) -> int:
        return 4 * len(self.emitters) + self.background.size

    # The uncertainties and flags are computed when first asked for: most trial fits of the
    # count selection and the relocations are compared by their likelihood alone.
    @property
    def sigma(self) -> NDArray[np.float64]:
        return self._uncertainties()["sigma"]

    @property
    def flags(self) -> NDArray[np.str_]:
        return self._uncertainties()["flags"]

    @property
    def background_sigma(self) -> NDArray[np.float64]:
        return self._uncertainties()["background_sigma"]

    @property
    def crlb(self) -> NDArray[np.float64]:
        """The Cramer-Rao standard errors (K, 4) before :func:`fit_flags` blanks a flagged
        row's: the count selection's Wald statistic needs them for every emitter."""
        return self._uncertainties()["crlb"]

    def _uncertainties(self) -> dict:
        if not self._derived:
            sd, fisher_ok = _standard_errors(self.fisher)
            em = self.emitters.as_array().reshape(-1, 4)
            k = len(em)
            sigma, flags = fit_flags(
                em,
                sd[: 4 * k].reshape(k, 4),
                z_range=self.z_range,
                window=self.window,
                converged=self.converged,
                fisher_ok=fisher_ok,
            )
            self._derived.update(
                sigma=sigma,
                flags=flags,
                background_sigma=sd[4 * k :],
                crlb=sd[: 4 * k].reshape(k, 4),
            )
        return self._derived


def check_qe(qe: float) -> float:
    """``qe`` as a float in (0, 1]; ValueError naming the value otherwise."""
    try:
        q = float(qe)
    except (TypeError, ValueError):
        raise ValueError(f"qe must be a number in (0, 1]; got {qe!r}") from None
    if not (np.isfinite(q) and 0.0 < q <= 1.0):
        raise ValueError(f"qe must be in (0, 1] (the fraction of photons detected); got {qe!r}")
    return q


def likelihood_weight(noise: str, qe: float = 1.0) -> float:
    """The weight ``w`` of the Poisson objective in photons (see the module notes): ``qe``,
    halved for EMCCD data (excess noise factor 2)."""
    return check_qe(qe) / noise_factor_of(noise)


def check_read_variance(noise: str, read_variance: object) -> None:
    """Refuse a read variance the noise model cannot carry: sCMOS needs one, EMCCD may have
    one (the read noise behind the EM gain), photon counting has none."""
    if noise == "scmos" and read_variance is None:
        raise ValueError("noise='scmos' needs read_variance (photons^2, scalar or map)")
    if noise == "poisson" and read_variance is not None:
        raise ValueError("read_variance is only used with noise='scmos' or 'emccd'")


def censored_weights(censored: ArrayLike | None, shape: tuple[int, int]) -> NDArray[np.float64]:
    """Each pixel's weight in the likelihood (rows, cols): 0 where ``censored`` (bool, a
    window's), else 1."""
    if censored is None:
        return np.ones(shape)
    c = np.broadcast_to(np.asarray(censored, dtype=bool), shape)
    return np.where(c, 0.0, 1.0)


def background_basis(
    shape: tuple[int, int], plane: bool, background_shape: ArrayLike | None = None
) -> list[NDArray[np.float64]]:
    """The background's basis images over a window (see the module notes): a constant (or
    ``background_shape`` divided by its median), and with ``plane`` the two tilts ``u`` and
    ``v``."""
    rows, cols = shape
    u = (np.arange(cols) - (cols - 1) / 2) / max(cols / 2, 1)
    v = (np.arange(rows) - (rows - 1) / 2) / max(rows / 2, 1)
    if background_shape is None:
        basis = [np.ones(shape)]
    else:
        level = np.broadcast_to(np.asarray(background_shape, dtype=np.float64), shape)
        basis = [level / max(float(np.median(level)), 1e-6)]
    if plane:
        basis += [np.broadcast_to(u[None, :], shape), np.broadcast_to(v[:, None], shape)]
    return basis


class LikelihoodProblem:
    """The window, the PSF and the noise model: likelihood, gradient and Fisher matrix."""

    def __init__(
        self,
        y,
        model,
        pixel_size,
        origin,
        noise,
        read_variance,
        plane,
        xy_margin,
        offset=None,
        qe=1.0,
        background_shape=None,
        censored=None,
    ):
        if noise not in NOISE_MODELS:
            raise ValueError(f"noise must be one of {', '.join(NOISE_MODELS)}; got {noise!r}")
        self.y = y
        self.model = model
        self.px = float(pixel_size)
        self.origin = (float(origin[0]), float(origin[1]))
        self.shape = y.shape
        self.weight = likelihood_weight(noise, qe)
        check_read_variance(noise, read_variance)
        if read_variance is None:
            self.v = np.zeros(y.shape)
        else:
            # on the likelihood's scale, w * v (see the module notes)
            self.v = self.weight * np.broadcast_to(
                np.asarray(read_variance, dtype=np.float64), y.shape
            )
            if np.any(self.v < 0):
                raise ValueError("read_variance must be >= 0")
        self.yv = y + self.v
        # 1 for each pixel the likelihood counts, 0 for a censored one (each product with it
        # is placed so that, times 1.0, every sum is bit for bit the one without it)
        self.keep = censored_weights(censored, y.shape)
        # Known light that is not fitted (neighbours' emitters fitted elsewhere), photons/pixel.
        self.offset = 0.0 if offset is None else np.broadcast_to(np.asarray(offset, float), y.shape)
        rows, cols = y.shape
        self.plane = plane
        self.n_bg = 3 if plane else 1
        self.bg_basis = background_basis(y.shape, plane, background_shape)
        self.zlo, self.zhi = model.z_range
        m = xy_margin * self.px
        self.xlo = self.origin[0] - m
        self.xhi = self.origin[0] + cols * self.px + m
        self.ylo = self.origin[1] - m
        self.yhi = self.origin[1] + rows * self.px + m
        # data-only constant so that the deviance is available: sum(y log y - y)
        yy = self.yv
        self._sat = float(
            np.sum(self.keep * (np.where(yy > 0, yy * np.log(np.where(yy > 0, yy, 1.0)), 0.0) - yy))
        )

    # theta = [x0, y0, z0, N0, x1, ..., b...]
    def split(self, theta):
        k = (theta.size - self.n_bg) // 4
        em = theta[: 4 * k].reshape(k, 4)
        return em, theta[4 * k :]

    def background(self, b):
        return sum(bi * basis for bi, basis in zip(b, self.bg_basis, strict=True))

    def mu(self, theta):
        em, b = self.split(theta)
        img = self.background(b) + self.offset
        if len(em):
            img = img + self.model.render(
                em[:, 0], em[:, 1], em[:, 2], em[:, 3], self.shape, self.px, origin=self.origin
            )
        return img

    def nll(self, mu):
        """Negative log-likelihood (without the data-only constant); inf if mu <= 0 anywhere."""
        muv = mu + self.v
        if np.any(muv <= 0) or not np.all(np.isfinite(muv)):
            return np.inf
        return float(self.weight * np.sum(self.keep * (muv - self.yv * np.log(muv))))

    def jacobian(self, theta):
        em, _ = self.split(theta)
        k = len(em)
        cols = []
        if k:
            g = self.model.gradients(
                em[:, 0], em[:, 1], em[:, 2], em[:, 3], self.shape, self.px, origin=self.origin
            )
            cols.append(g.reshape(4 * k, -1))
        cols.append(np.stack([basis.ravel() for basis in self.bg_basis]))
        return np.concatenate(cols, axis=0)  # (P, pixels)

    def fisher(self, jac, mu):
        muv = (mu + self.v).ravel()
        return self.weight * ((jac * self.keep.ravel()) / muv) @ jac.T

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Lower and upper bounds of each emitter's x, y, z (nm) and photons."""
        lo = np.array([self.xlo, self.ylo, self.zlo, _MIN_PHOTONS])
        hi = np.array([self.xhi, self.yhi, self.zhi, np.inf])
        return lo, hi

    def deviance(self, mu):
        muv = mu + self.v
        dev = self._sat - float(np.sum(self.keep * (self.yv * np.log(muv) - muv)))
        return 2.0 * self.weight * dev

    @property
    def n_pixels(self) -> int:
        """Pixels the likelihood counts (those not censored)."""
        return int(np.count_nonzero(self.keep))


def fit_emitters(
    window: ArrayLike,
    model: PSFModel,
    emitters: Emitters,
    *,
    pixel_size: float,
    origin: tuple[float, float] = (0.0, 0.0),
    background: float | None = None,
    plane: bool = False,
    noise: str = "poisson",
    read_variance: float | ArrayLike | None = None,
    max_iter: int = 60,
    tol: float = 1e-6,
    xy_margin: float = 1.0,
    offset: ArrayLike | None = None,
    qe: float = 1.0,
    background_shape: ArrayLike | None = None,
    censored: ArrayLike | None = None,
) -> FitResult:
    """Maximum-likelihood fit of K emitters plus a background in one window.

    Parameters
    ----------
    window : ndarray, shape (rows, cols)
        Window in photons.
    model : PSFModel
        The continuous PSF model (with gradients).
    emitters : Emitters
        Starting positions (nm) and photons, e.g. a sparse solution.
    pixel_size : float
        Pixel size (nm).
    origin : (float, float)
        Position (nm) of the window's outer corner.
    background : float, optional
        Starting background (photons/pixel); estimated from the window when ``None``.
    plane : bool
        Fit a tilted-plane background instead of a constant.
    noise : {"poisson", "emccd", "scmos"}
        Likelihood (see the module notes).
    read_variance : float or ndarray, optional
        sCMOS read-noise variance (photons^2), scalar or (rows, cols).
    max_iter : int
        Levenberg-Marquardt iterations.
    tol : float
        Stop when the relative decrease of ``-log L`` is below this.
    xy_margin : float
        How far (pixels) an emitter may leave the window.
    offset : float or ndarray, shape (rows, cols), optional
        Known expected light (photons/pixel) added to the model and not fitted, such as the
        images of neighbouring emitters fitted in other windows.
    qe : float
        Quantum efficiency in (0, 1]: the frames hold photoelectrons divided by it, so their
        variance is ``mu / qe`` (see the module notes); 1 for photon-counting data.
    background_shape : ndarray, shape (rows, cols), optional
        The background's shape over the window (photons/pixel; its scale does not matter):
        the fitted background scales it where the data choose it over a constant (see the
        module notes; :attr:`FitResult.background_shape` says which). Default: a constant.
    censored : ndarray of bool, shape (rows, cols), optional
        Pixels at the camera's saturation, left out of the likelihood (see the module notes).

    Returns
    -------
    FitResult
    """
    y = check_window(window)
    if y.ndim != 2:
        raise ValueError("fit_emitters takes one window (rows, cols)")
    if np.any(y < -1e-9) and read_variance is None:
        raise ValueError("the window has negative photon counts; convert ADU to photons first")
    args = (y, model, pixel_size, origin, noise, read_variance, plane, xy_margin, offset, qe)
    flat = LikelihoodProblem(*args, censored=censored)
    fit = _fit(flat, emitters, background, max_iter, tol)
    if background_shape is None:
        return fit
    score = _shape_score(flat, fit, background_shape)
    if score <= SHAPE_MARGIN:
        return fit
    # the count selection's allowance for the model's error, on the log-likelihood's scale
    from .refine import error_allowance_at  # refine imports this module

    kw = dict(pixel_size=pixel_size, origin=origin, noise=noise, qe=qe, read_variance=read_variance)
    kw["censored"] = censored
    bar = SHAPE_MARGIN + 0.5 * error_allowance_at(fit, model, kw)
    if score <= bar:
        return fit
    hazy_prob = LikelihoodProblem(*args, background_shape, censored=censored)
    hazy = _fit(hazy_prob, emitters, background, max_iter, tol)
    if hazy.log_likelihood > fit.log_likelihood + bar:
        hazy.background_shape = np.broadcast_to(background_shape, y.shape)
        return hazy
    return fit


def _shape_score(prob: LikelihoodProblem, fit: FitResult, shape: ArrayLike) -> float:
    """``dlog L / dbeta`` at a constant-background fit, along the background
    ``b (1 + beta (s - 1))`` with ``s`` the window's ``shape`` divided by its median: about how
    much likelier the shape can make the window at most (see the module notes)."""
    s = background_basis(prob.shape, False, shape)[0]
    d = fit.background[0] * (s - 1.0)
    g = prob.keep * (prob.yv / (fit.model_image + prob.v) - 1.0)
    return float(prob.weight * np.sum(g * d))


def _fit(
    prob: LikelihoodProblem, emitters: Emitters, background: float | None, max_iter: int, tol: float
) -> FitResult:
    """The fit of :func:`fit_emitters` on one likelihood problem (its background basis)."""
    y = prob.y
    em0 = emitters.as_array()
    if background is None:
        resid = y - prob.mu(np.concatenate([em0.ravel(), np.zeros(prob.n_bg)]))
        background = float(max(np.median(resid), 1.0))
    b0 = np.zeros(prob.n_bg)
    b0[0] = background
    theta = np.concatenate([em0.ravel(), b0])
    if not np.all(np.isfinite(theta)):
        raise ValueError("the starting positions, photons and background must be finite")
    lo, hi = prob.bounds()
    clamp(theta, len(em0), lo, hi, _MIN_BG)
    if isinstance(prob.model, SplinePSF) and kernels() is not None:
        out = _numba_fit(prob, theta, lo, hi, max_iter, tol)
    else:
        out = _numpy_fit(prob, theta, lo, hi, max_iter, tol)
    return _result(prob, *out)


class _NumpyFit:
    """The NumPy engine's state of one fit (any PSF model): the operations of
    :func:`~sparseloc.solvers.lm.make_levenberg_marquardt` are the functions below."""

    def __init__(self, prob: LikelihoodProblem, theta: NDArray, lo: NDArray, hi: NDArray) -> None:
        self.prob, self.theta, self.lo, self.hi = prob, theta, lo, hi
        self.k = (theta.size - prob.n_bg) // 4
        self.a = np.empty((theta.size, theta.size))


def _numpy_evaluate(s: _NumpyFit) -> float:
    s.mu = s.prob.mu(s.theta)
    s.jac = s.prob.jacobian(s.theta)
    return s.prob.nll(s.mu)


def _numpy_score(s: _NumpyFit) -> None:
    prob = s.prob
    muv = (s.mu + prob.v).ravel()
    s.grad = prob.weight * s.jac @ (prob.keep.ravel() * (1.0 - prob.yv.ravel() / muv))
    s.fisher = prob.fisher(s.jac, s.mu)


def _numpy_trial(s: _NumpyFit, lam: float) -> float:
    damped_system(s.fisher, lam, s.a)
    try:
        step = np.linalg.solve(s.a, -s.grad)
    except np.linalg.LinAlgError:
        return np.inf
    if not np.all(np.isfinite(step)):
        return np.inf
    s.trial = s.theta + step
    clamp(s.trial, s.k, s.lo, s.hi, _MIN_BG)
    s.mu_t = s.prob.mu(s.trial)
    return s.prob.nll(s.mu_t)


def _numpy_accept(s: _NumpyFit) -> None:
    s.theta, s.mu = s.trial, s.mu_t
    s.jac = s.prob.jacobian(s.theta)


_numpy_levenberg_marquardt = make_levenberg_marquardt(
    _numpy_evaluate, _numpy_score, _numpy_trial, _numpy_accept
)


def _numpy_fit(prob: LikelihoodProblem, theta, lo, hi, max_iter: int, tol: float):
    """The fit on the NumPy engine: theta, mu, -log L, Fisher matrix, converged, n_iter."""
    s = _NumpyFit(prob, theta, lo, hi)
    f, converged, n_iter = _numpy_levenberg_marquardt(s, max_iter, tol)
    return s.theta, s.mu, f, s.fisher, converged, n_iter


def _numba_fit(prob: LikelihoodProblem, theta, lo, hi, max_iter: int, tol: float):
    """The fit on the numba engine (spline tables): the same loop, compiled."""
    from ._fit_numba import lm_fit

    m = prob.model
    m._check_pixel(prob.px)
    # a writable copy: a read-only array (a broadcast offset) is another signature to compile
    base = np.array(np.broadcast_to(prob.offset, prob.shape), dtype=np.float64, order="C")
    theta, mu, f, fisher, converged, n_iter = lm_fit(
        m._coef,
        m.node_geometry(prob.origin, prob.px),
        np.ascontiguousarray(prob.yv, dtype=np.float64),
        np.ascontiguousarray(prob.v, dtype=np.float64),
        prob.keep,
        base,
        np.ascontiguousarray(np.stack(prob.bg_basis), dtype=np.float64),
        float(prob.weight),
        np.ascontiguousarray(theta, dtype=np.float64),
        (theta.size - prob.n_bg) // 4,
        lo,
        hi,
        _MIN_BG,
        int(max_iter),
        float(tol),
    )
    return theta, mu, float(f), fisher, bool(converged), int(n_iter)


def _standard_errors(fisher: NDArray) -> tuple[NDArray, bool]:
    """``sqrt(diag(F^-1))`` and whether any of it could be computed.

    ``F`` is scaled to unit diagonal before the Cholesky test, so that parameters of different
    units (nm, photons) do not decide it. Where it fails, the parameters the data do not
    constrain (no information, or the largest part of a combination without any) get NaN, and
    the others the standard errors of ``F`` restricted to them (those parameters held at their
    fitted values): one emitter at the end of the model's z range, or two that share one
    image, does not void the uncertainties of the other emitters of its window.
    """
    f = np.asarray(fisher, dtype=np.float64)
    d = np.diag(f)
    out = np.full(len(d), np.nan)
    if f.size == 0 or not np.all(np.isfinite(f)):
        return out, False
    keep = d > 0
    while keep.any():
        idx = np.flatnonzero(keep)
        s = np.sqrt(d[idx])
        corr = f[np.ix_(idx, idx)] / np.outer(s, s)
        if _positive_definite(corr):
            inv = np.linalg.inv(corr)
            with np.errstate(invalid="ignore"):
                out[idx] = np.sqrt(np.diag(inv)) / s
            return out, True
        # the parameters that carry the least-constrained combinations (two emitters that
        # share one image: both emitters' parameters) are left out together
        w, v = np.linalg.eigh(corr)
        null = w < _FISHER_RCOND
        null[0] = True
        weight = np.abs(v[:, null]).max(axis=1)
        keep[idx[weight >= 0.5 * weight.max()]] = False
    return out, False


def _positive_definite(corr: NDArray) -> bool:
    """Whether a unit-diagonal matrix passes the Cholesky test with no pivot near zero (a
    near-zero pivot means a combination of parameters the data do not constrain)."""
    try:
        chol = np.linalg.cholesky(corr)
    except np.linalg.LinAlgError:
        return False
    return bool(np.min(np.diag(chol)) ** 2 >= _FISHER_RCOND)


def fit_flags(
    emitters: NDArray,
    sigma: NDArray,
    *,
    z_range: tuple[float, float],
    window: tuple[float, float, float, float],
    converged: bool,
    fisher_ok: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.str_]]:
    """The one rule that turns a fit's standard errors into the uncertainties and flags written
    to a localization table.

    A flag other than ``"ok"`` names the first reason, in this order: ``"diverged"``
    (non-finite position or photons at their floor), ``"outside"`` (x or y outside the window),
    ``"z_edge"`` (z within 1 nm of the model's z range, where the true z may lie beyond it),
    ``"bad_sigma"`` (no part of the Fisher matrix could be inverted, or an uncertainty is not
    finite (the data do not constrain one of the emitter's parameters), is larger than the
    window along x or y or than the z range along z, or is below :data:`SIGMA_FLOOR_NM`),
    ``"not_converged"``. Rows flagged ``"diverged"``, ``"z_edge"`` or
    ``"bad_sigma"`` get NaN uncertainties: their Cramer-Rao bound does not describe the error.

    Parameters
    ----------
    emitters : ndarray, shape (K, 4)
        Fitted ``x, y, z`` (nm) and photons.
    sigma : ndarray, shape (K, 4)
        Standard errors of ``x, y, z`` (nm) and photons, ``sqrt(diag(F^-1))``.
    z_range : (float, float)
        The PSF model's z range (nm).
    window : (x0, y0, x1, y1)
        Edges of the fitted window (nm).
    converged : bool
        Whether the fit converged.
    fisher_ok : bool
        Whether any part of the Fisher matrix could be inverted (:func:`_standard_errors`).

    Returns
    -------
    sigma : ndarray, shape (K, 4)
        The uncertainties to write (nm, nm, nm, photons), NaN where the rule voids them.
    flags : ndarray of str, shape (K,)
    """
    em = np.asarray(emitters, dtype=np.float64).reshape(-1, 4)
    sd = np.array(sigma, dtype=np.float64).reshape(-1, 4)
    k = len(em)
    flags = np.full(k, "ok", dtype="<U16")
    if k == 0:
        return sd, flags
    zlo, zhi = (float(v) for v in z_range)
    x0, y0, x1, y1 = (float(v) for v in window)
    with np.errstate(invalid="ignore"):
        upper = np.array([x1 - x0, y1 - y0, zhi - zlo])
        bad_sd = ~np.all(np.isfinite(sd), axis=1) | ~np.all(sd[:, 3:] > 0, axis=1)
        bad_sd |= np.any((sd[:, :3] > upper) | (sd[:, :3] < SIGMA_FLOOR_NM), axis=1)
        bad_sd |= not fisher_ok
        at_edge = (em[:, 2] <= zlo + 1.0) | (em[:, 2] >= zhi - 1.0)
        outside = (em[:, 0] < x0) | (em[:, 0] > x1) | (em[:, 1] < y0) | (em[:, 1] > y1)
        diverged = ~np.all(np.isfinite(em), axis=1) | (em[:, 3] <= _MIN_PHOTONS * 1.01)
    if not converged:
        flags[:] = "not_converged"
    # Later assignments win: the list runs from the weakest reason to the strongest.
    flags[bad_sd] = "bad_sigma"
    flags[at_edge] = "z_edge"
    flags[outside] = "outside"
    flags[diverged] = "diverged"
    sd[bad_sd | at_edge | diverged] = np.nan
    return sd, flags


def _result(prob: LikelihoodProblem, theta, mu, f, fisher, converged, n_iter) -> FitResult:
    """The :class:`FitResult` of a fit that ended at ``theta`` (``fisher``: its Fisher
    matrix, from which the standard errors come; flags by :func:`fit_flags`)."""
    em, b = prob.split(theta)
    rows, cols = prob.shape
    window = (
        prob.origin[0],
        prob.origin[1],
        prob.origin[0] + cols * prob.px,
        prob.origin[1] + rows * prob.px,
    )
    dof = max(prob.n_pixels - theta.size, 1)
    return FitResult(
        emitters=Emitters.from_array(em),
        background=b.copy(),
        model_image=mu,
        log_likelihood=-f,
        deviance_per_dof=prob.deviance(mu) / dof,
        converged=converged,
        n_iter=n_iter,
        fisher=np.asarray(fisher, dtype=np.float64).copy(),
        window=window,
        z_range=(prob.zlo, prob.zhi),
        background_image=prob.background(b),
    )
