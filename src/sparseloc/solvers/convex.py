"""Exact non-negative L1 recovery (the paper's convex optimisation, "CO"), with a background.

With a dense dictionary ``A`` (``m`` pixels x ``n`` atoms; atoms are unit-photon images, so the
coefficients ``x`` are photons) and a window ``y`` (``m`` photons), two equivalent forms:

- *constrained* (the paper's CVX form, basis-pursuit denoising)::

      minimise sum(x)  subject to  ||y - A x - b||_2 <= eps,  x >= 0,  b >= 0

- *penalised* (its Lagrangian form)::

      minimise 0.5 * ||y - A x - b||_2^2 + lam * sum(x)  subject to  x >= 0,  b >= 0

``b`` is one background level (photons/pixel), estimated (``background=None``) or fixed. Since
``x >= 0``, ``||x||_1 = sum(x)`` and both are small QPs / SOCPs.

Method
------
Write ``z = [x, b]``, ``B = [A, 1]`` and ``c = [lam, 0]`` (a fixed background is subtracted
from ``y`` and ``b`` dropped from ``z``). The penalised form is the non-negative least-squares
problem ``min 0.5 ||B z - y||^2 + c.z, z >= 0``, solved *exactly* by a Lawson-Hanson active-set
method extended to the linear term: the passive (non-zero) set grows one atom at a time (the one
with the largest negative gradient) and each face problem ``(B_P' B_P) z_P = B_P' y - c_P`` is
solved by Cholesky on the small passive set (eigen-decomposition when it is singular). Only the
columns of the passive set are ever multiplied together; the gradient over all atoms is one
product ``B' r`` per outer iteration (an ``n x n`` Gram matrix is cached only for small ``n``).

The constrained form is solved through the penalised one. The optimal residual norm is
non-decreasing in ``lam``, and on an interval of ``lam`` where the active set does not change,
the solution is affine, ``z_P(lam) = a - lam g``, and ``||r(lam)||^2`` is a quadratic. Each
penalised solve (warm-started from the previous active set) therefore also gives the exact
interval of ``lam`` on which its active set is optimal and the root of ``||r(lam)|| = eps`` on
that piece; when the root lies in the interval (and the KKT conditions hold there) the answer
is exact. Otherwise the bracket on ``lam`` shrinks past the whole piece and the next ``lam`` is
the piece's root when it falls inside the bracket (a Newton step on the local quadratic) or the
regula-falsi (Illinois) estimate of ``||r(lam)||^2 = eps^2`` from the bracket's ends (the
first bracket is ``[0, lam_max]``, ``x = 0`` at ``lam_max``). Typically 2-5 penalised solves
settle a window.

Working set (the constrained form with more than :data:`WORKING_SET_MIN_ATOMS` atoms, or
``working_set=True``): most of a large dictionary never enters the solution, so the whole
search above runs on a working set ``W`` of atoms (first the :data:`WORKING_SET_SIZE` best
correlated with the background-only residual) and its answer is then checked against the KKT
conditions of the full problem at the same ``lam`` with one product ``B' r``. The atoms outside
``W`` whose gradient violates them by more than the tolerance (the worst
``max(WORKING_SET_GROW, |W| / 2)``) join ``W`` and the search runs again, warm-started from the
last active set and ``lam``; when none violates, the restricted solution *is* the full one, with
the same certificate as without the working set (an unsafe screening rule made exact by the
check: atoms are only ever added, so nothing the solution needs can be discarded). This
replaces one product with the whole dictionary per active-set iteration by one per round, and
the rounds are few. The problem, the active-set solver and the working set's bookkeeping live
in :mod:`sparseloc.solvers.convex_active`.

Edge cases of the constrained form: when the background alone fits (``||y - b_0|| <= eps``)
the answer is ``x = 0`` (``lam`` is then reported as the smallest penalty that gives it); when
even the non-negative least-squares fit (``lam -> 0``) leaves ``||r|| > eps`` the problem is
infeasible: by default (``on_infeasible="nnls"``) that fit is returned with ``feasible=False``
and logged (at info level: restricted dictionaries are often infeasible by design);
``on_infeasible="raise"`` raises ``ValueError`` with the numbers.

Cost: each outer iteration is one product ``B' r`` (``O(m n)``, ``n`` the working set's size
when there is one) plus a Cholesky of the passive set (``O(k^3)``, ``k`` at most a few tens
here); a first-order method (FISTA) on these strongly correlated atoms needs far more such
products to reach the same KKT accuracy, so none is offered. On the paper's coarse dictionary a
window takes a few milliseconds (``benchmarks/speed_co.py``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .convex_active import GRAM_CACHE_MAX as GRAM_CACHE_MAX
from .convex_active import (
    Problem,
    WorkingSet,
    active_set,
    face_inverse,
    kkt_violation,
)

log = logging.getLogger(__name__)

__all__ = [
    "ConvexResult",
    "noise_epsilon",
    "solve_constrained",
    "solve_penalized",
]

#: Solve on a working set of atoms (see the module notes) when there are more atoms than this.
WORKING_SET_MIN_ATOMS = 1024
#: Initial size of the working set.
WORKING_SET_SIZE = 256
#: Most atoms added to the working set per round (the worst KKT violators).
WORKING_SET_GROW = 128
#: Most penalties tried by :func:`solve_constrained` before it gives up.
MAX_LAMBDA_EVALUATIONS = 200


# -- result ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class ConvexResult:
    """Solution of one convex recovery problem.

    Attributes
    ----------
    coef : ndarray, shape (n,)
        Coefficients in photons; exact zeros off the support.
    background : float
        Background in photons/pixel (the fixed value when one was given).
    lam : float or ndarray
        The penalty: as given to the penalised form (scalar, or per-atom array of shape (n,));
        for the constrained form the scalar ``lam`` whose penalised solution solves it
        (multiplying ``weights`` where those were given).
    objective : float
        Objective of the form solved: ``0.5 ||r||^2 + sum(lam * coef)`` (penalised) or
        ``sum(weights * coef)`` (constrained; ``sum(coef)`` by default), photons.
    residual_norm : float
        ``||y - A coef - background||_2`` in photons.
    n_iter : int
        Face (passive-set) solves in all, over every penalty tried.
    converged : bool
        ``True`` when the KKT conditions hold to the tolerance (and, for the constrained form,
        the penalty was found).
    feasible : bool
        ``False`` only for a constrained problem with no feasible point (see
        :func:`solve_constrained`); the least-squares fit is then returned.
    """

    coef: NDArray[np.float64]
    background: float
    lam: float | NDArray[np.float64]
    objective: float
    residual_norm: float
    n_iter: int
    converged: bool
    feasible: bool = True

    @property
    def support(self) -> NDArray[np.intp]:
        """Indices of the non-zero coefficients (ascending)."""
        return np.flatnonzero(self.coef)


# -- validation ------------------------------------------------------------------------------
def _check_matrix(A: ArrayLike) -> NDArray[np.float64]:
    mat = getattr(A, "matrix", A)  # a DenseDictionary works too
    arr = np.asarray(mat, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"A must be a non-empty 2-D matrix (pixels, atoms), got shape {arr.shape}")
    with np.errstate(over="ignore", invalid="ignore"):
        total = float(arr.sum())  # finite unless an entry is not (or the sum overflows)
    if not math.isfinite(total) and not np.all(np.isfinite(arr)):
        raise ValueError("A contains NaN or inf values")
    return arr


def _check_y(y: ArrayLike, m: int) -> NDArray[np.float64]:
    arr = np.asarray(y, dtype=np.float64)
    if arr.size != m:
        raise ValueError(f"y has {arr.size} values (shape {arr.shape}); A has {m} rows (pixels)")
    if not np.all(np.isfinite(arr)):
        raise ValueError("y contains NaN or inf values")
    return arr.reshape(-1)


def _check_system(A: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The dictionary ``A`` (m, n) and the window ``y`` as its m values."""
    Am = _check_matrix(A)
    return Am, _check_y(y, Am.shape[0])


def _check_scalar(value: float, name: str, *, nonneg: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {value!r}") from exc
    if not math.isfinite(v) or (nonneg and v < 0):
        raise ValueError(f"{name} must be finite{' and >= 0' if nonneg else ''}, got {value!r}")
    return v


def _check_lam(lam: float | ArrayLike, n: int) -> float | NDArray[np.float64]:
    try:
        arr = np.asarray(lam, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"lam must be a number or an array of numbers, got {lam!r}") from exc
    if arr.ndim == 0:
        return _check_scalar(float(arr), "lam")
    if arr.shape != (n,):
        raise ValueError(f"lam must be a scalar or an array of shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError("lam must be finite and >= 0")
    return arr.copy()


def _check_weights(weights: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if weights is None:
        return np.ones(n)
    try:
        arr = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"weights must be an array of numbers, got {weights!r}") from exc
    if arr.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError("weights must be finite and > 0")
    return arr


def _check_tol(tol: float) -> float:
    t = _check_scalar(tol, "tol")
    if t <= 0:
        raise ValueError(f"tol must be > 0, got {tol!r}")
    return t


def _check_max_iter(max_iter: int | None, default: int) -> int:
    if max_iter is None:
        return default
    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    return int(max_iter)


# -- penalised form --------------------------------------------------------------------------
def solve_penalized(
    A: ArrayLike,
    y: ArrayLike,
    lam: float | ArrayLike,
    *,
    background: float | None = None,
    x0: ArrayLike | None = None,
    tol: float = 1e-10,
    max_iter: int | None = None,
) -> ConvexResult:
    """Exact solution of ``min 0.5||y - A x - b||^2 + sum(lam * x)``, ``x >= 0``, ``b >= 0``.

    Parameters
    ----------
    A : ndarray, shape (m, n), or DenseDictionary
        Dictionary: unit-photon atom images as columns (m pixels, n atoms).
    y : ndarray, shape (m,) or any shape with m values
        Window in photons (flattened in C order, the dictionary's pixel order).
    lam : float or ndarray, shape (n,)
        Penalty in photons (the units of ``A' y``), scalar or one per atom, ``>= 0``.
        ``lam = 0`` gives the non-negative least-squares fit; ``lam >= max(A' (y - b_0))``
        (``b_0`` the background-only fit) gives ``coef = 0``.
    background : float, optional
        Fixed background in photons/pixel; ``None`` (default) estimates ``b >= 0``.
    x0 : ndarray, shape (n,), optional
        Warm start: the support (``x0 > 0``) is the initial passive set (values are ignored).
    tol : float
        Relative tolerance of the KKT conditions (scaled by ``max |B' y|`` and ``max lam``).
    max_iter : int, optional
        Most face solves; default ``5 * n + 100``.

    Returns
    -------
    ConvexResult
        ``objective = 0.5 ||r||^2 + sum(lam * coef)``; ``lam`` as given.

    Raises
    ------
    ValueError
        On invalid input (the message names the argument).
    """
    Am, yv = _check_system(A, y)
    n = Am.shape[1]
    lam_v = _check_lam(lam, n)
    bg = None if background is None else _check_scalar(background, "background", nonneg=False)
    tol = _check_tol(tol)
    max_it = _check_max_iter(max_iter, 5 * n + 100)
    init: list[int] = []
    if x0 is not None:
        x0a = np.asarray(x0, dtype=np.float64)
        if x0a.shape != (n,) or not np.all(np.isfinite(x0a)):
            raise ValueError(f"x0 must be a finite array of shape ({n},), got shape {x0a.shape}")
        init = list(np.flatnonzero(x0a > 0))
    prob = Problem(Am, yv, bg)
    if prob.has_bg:
        init.append(n)
    c = prob.penalty(lam_v)
    tol_abs = tol * prob.scale(c)
    st = active_set(prob, c, init, tol_abs, max_it)
    return _penalized_result(prob, st.z, c, lam_v, st.n_iter, st.converged, tol_abs)


def _penalized_result(
    prob: Problem,
    z: NDArray,
    c: NDArray,
    lam: float | NDArray,
    n_iter: int,
    converged: bool,
    tol_abs: float,
) -> ConvexResult:
    x, b = prob.split(z)
    rn = float(np.linalg.norm(prob.residual(z)))
    obj = 0.5 * rn**2 + float(c[: prob.n] @ x)
    viol = kkt_violation(prob, z, c)
    ok = converged and viol <= 10 * tol_abs
    if not ok:
        log.warning("penalised solve not converged (KKT violation %.3g, tol %.3g)", viol, tol_abs)
    return ConvexResult(
        coef=x,
        background=b,
        lam=lam,
        objective=obj,
        residual_norm=rn,
        n_iter=n_iter,
        converged=bool(ok),
    )


# -- constrained form ------------------------------------------------------------------------
@dataclass
class _Piece:
    """The penalised path on one active set: ``z_P = a - lam g``, ``r = r0 + lam v``."""

    P: NDArray
    a: NDArray
    g: NDArray
    r0: NDArray
    v: NDArray
    lo: float
    hi: float

    def sq_norm(self, lam: float) -> float:
        """``||r(lam)||^2`` on this piece."""
        r = self.r0 + lam * self.v
        return float(r @ r)

    def root(self, eps: float) -> float | None:
        """``lam >= 0`` with ``||r0 + lam v|| = eps`` (None if there is none)."""
        vv = float(self.v @ self.v)
        rv = float(self.r0 @ self.v)
        rr = float(self.r0 @ self.r0)
        cst = rr - eps * eps
        if vv <= 0:
            return None
        disc = rv * rv - vv * cst
        if disc < 0:
            return None
        sq = math.sqrt(disc)
        # roots (-rv +- sq) / vv; the larger one, computed without cancellation
        t = (-rv + sq) / vv if rv <= 0 else -cst / (rv + sq)
        return t if t >= 0 else None


def _piece(prob: Problem, P: Sequence[int], wts: NDArray, tol_abs: float) -> _Piece:
    """The piece of the path through the active set ``P`` and the ``lam`` where it is optimal."""
    idx = np.asarray(sorted(P), dtype=np.intp)
    if idx.size == 0:
        r0 = prob.y.copy()
        v = np.zeros(prob.m)
        a = g = np.zeros(0)
    else:
        C = prob.cols(idx)
        sol = face_inverse(C.T @ C, np.stack([prob.Bty[idx], wts[idx]], axis=1))
        a, g = sol[:, 0], sol[:, 1]
        r0 = prob.y - C @ a
        v = C @ g
    lo, hi = 0.0, math.inf
    # positivity of the passive entries: a_i - lam g_i > 0
    for ai, gi in zip(a, g, strict=True):
        if gi > 0:
            hi = min(hi, ai / gi)
        elif gi < 0:
            lo = max(lo, ai / gi)
        elif ai <= 0:
            hi = -math.inf
    # gradient on the zeros, to the KKT tolerance: -B_j'r0 + lam (w_j - B_j'v) >= -tol_abs
    bt = prob.rmatvec(np.stack([r0, v], axis=1))
    zero = np.ones(prob.N, bool)
    zero[idx] = False
    p = bt[zero, 0] - tol_abs
    qz = wts[zero] - bt[zero, 1]
    tiny = 1e-14 * np.maximum(np.abs(bt[zero, 1]) + wts[zero], 1e-300)
    pos, neg = qz > tiny, qz < -tiny
    if np.any(pos):
        lo = max(lo, float(np.max(p[pos] / qz[pos])))
    if np.any(neg):
        hi = min(hi, float(np.min(p[neg] / qz[neg])))
    if np.any(~pos & ~neg & (p > 0)):
        hi = -math.inf  # a zero whose gradient stays negative: no valid lam (round-off)
    return _Piece(P=idx, a=a, g=g, r0=r0, v=v, lo=lo, hi=hi)


def noise_epsilon(y: ArrayLike, *, factor: float = 1.0) -> float:
    """Default residual bound: the expected norm of Poisson noise when the model fits.

    ``eps = factor * sqrt(sum(max(y, 1)))``: for Poisson counts ``E||y - mu||^2 = sum(mu)`` and
    ``mu`` is estimated by the data (floored at one photon per pixel).

    Parameters
    ----------
    y : array_like
        Window in photons (any shape).
    factor : float
        Multiplier (``>= 0``).

    Returns
    -------
    float
        ``eps`` in photons.
    """
    f = _check_scalar(factor, "factor")
    arr = np.asarray(y, dtype=np.float64)
    if arr.size == 0 or not np.all(np.isfinite(arr)):
        raise ValueError("y must be a non-empty finite array")
    return f * math.sqrt(float(np.sum(np.maximum(arr, 1.0))))


def solve_constrained(
    A: ArrayLike,
    y: ArrayLike,
    eps: float,
    *,
    background: float | None = None,
    weights: ArrayLike | None = None,
    tol: float = 1e-10,
    max_iter: int | None = None,
    on_infeasible: Literal["nnls", "raise"] = "nnls",
    working_set: bool | None = None,
) -> ConvexResult:
    """Exact solution of ``min sum(x)  s.t.  ||y - A x - b||_2 <= eps, x >= 0, b >= 0``.

    Parameters
    ----------
    A : ndarray, shape (m, n), or DenseDictionary
        Dictionary: unit-photon atom images as columns (m pixels, n atoms).
    y : ndarray, shape (m,) or any shape with m values
        Window in photons.
    eps : float
        Bound on the residual norm in photons (``>= 0``); see :func:`noise_epsilon`.
    background : float, optional
        Fixed background in photons/pixel; ``None`` (default) estimates ``b >= 0``.
    weights : ndarray, shape (n,), optional
        Minimise ``sum(weights * x)`` instead (weights ``> 0``).
    tol : float
        Relative tolerance of the KKT conditions of the penalised solves.
    max_iter : int, optional
        Most face solves per penalised solve; default ``5 * n + 100``.
    on_infeasible : {"nnls", "raise"}
        What to do when even the non-negative least-squares fit has ``||r|| > eps``: return it
        with ``feasible=False`` (and ``lam = 0``), logging it, or raise ``ValueError``.
    working_set : bool, optional
        Solve on a working set of atoms that grows until the KKT conditions hold on every atom
        (see the module notes); same answer, fewer products with the whole dictionary. Default
        (``None``): when there are more than :data:`WORKING_SET_MIN_ATOMS` atoms.

    Returns
    -------
    ConvexResult
        ``objective = sum(weights * coef)``, ``lam`` the penalty at which the penalised form
        has the same solution; ``residual_norm == eps`` (to round-off) whenever
        ``coef != 0``. When the background alone fits (``||y - b_0|| <= eps``) ``coef = 0`` and
        ``background`` is the least-squares level ``max(mean(y), 0)`` (or the fixed one).

    Raises
    ------
    ValueError
        On invalid input, or (``on_infeasible="raise"``) when the problem has no feasible point.
    """
    Am, yv = _check_system(A, y)
    n = Am.shape[1]
    e = _check_scalar(eps, "eps")
    bg = None if background is None else _check_scalar(background, "background", nonneg=False)
    w = _check_weights(weights, n)
    tol = _check_tol(tol)
    max_it = _check_max_iter(max_iter, 5 * n + 100)
    if on_infeasible not in ("nnls", "raise"):
        raise ValueError(f"on_infeasible must be 'nnls' or 'raise', got {on_infeasible!r}")
    use_ws = _use_working_set(working_set, n)
    prob = Problem(Am, yv, bg, cache_gram=not use_ws, copy=not use_ws)
    wts = prob.penalty(w)  # (N,) weights with 0 on the background
    z, P, rn, score = _background_fit(prob, w)
    lam_max = float(np.max(score))
    if rn <= e:
        return _background_result(prob, z, rn, e, lam_max)
    if lam_max <= 0:  # x = 0 is the non-negative least-squares fit and it does not reach eps
        return _infeasible(prob, z, rn, e, wts, 0, on_infeasible)
    r_tol = 1e-9 * max(float(np.linalg.norm(prob.y)), 1.0)  # photons: "||r|| = eps" tolerance
    search = _SearchArgs(e, lam_max, rn, tol, max_it, r_tol)
    if use_ws:
        out = _search_working_set(prob, w, score, P, search)
    else:
        out = _search(prob, wts, P, search)
    return _constrained_result(prob, out, e, wts, on_infeasible)


def _background_fit(
    prob: Problem, w: NDArray
) -> tuple[NDArray, list[int], float, NDArray[np.float64]]:
    """The solution ``x = 0`` (the background alone): ``z``, its passive set, its residual norm
    and each atom's correlation with the residual over its weight (the largest is ``lam_max``,
    the smallest penalty that keeps ``x = 0``)."""
    n = prob.n
    z = np.zeros(prob.N)
    P: list[int] = []
    if prob.has_bg:
        z[n] = max(float(prob.y.mean()), 0.0)
        if z[n] > 0:
            P = [n]
    r = prob.residual(z)
    rn = float(np.linalg.norm(r))
    corr = prob.Bty[:n] if not prob.has_bg else r @ prob.A  # r = y there: B'y is known
    return z, P, rn, corr / w


def _background_result(
    prob: Problem, z: NDArray, rn: float, eps: float, lam_max: float
) -> ConvexResult:
    x, b = prob.split(z)
    log.debug("constrained: the background alone fits (||r|| = %.4g <= eps = %.4g)", rn, eps)
    return ConvexResult(
        coef=x,
        background=b,
        lam=max(lam_max, 0.0),
        objective=0.0,
        residual_norm=rn,
        n_iter=0,
        converged=True,
    )


@dataclass(frozen=True)
class _SearchArgs:
    """What the penalty search needs besides the problem: the bound ``eps``, the smallest
    penalty ``lam_max`` with ``x = 0`` and the residual norm ``rn_max`` there, the relative KKT
    tolerance, the face solves per penalised solve and the tolerance of ``||r|| = eps``."""

    eps: float
    lam_max: float
    rn_max: float
    tol: float
    max_it: int
    r_tol: float


def _search_working_set(
    prob: Problem, w: NDArray, score: NDArray, P: list[int], args: _SearchArgs
) -> _Outcome:
    """:func:`_search` on a working set: the atoms best correlated with the background-only
    residual, grown by the atoms that violate the KKT conditions of the restricted solution
    until none does (see the module notes)."""
    n = prob.n
    wts = prob.penalty(w)
    ws = WorkingSet(prob, _top(score, min(n, WORKING_SET_SIZE)))
    lam0 = None
    total_it = 0
    for n_round in range(1, n + 2):
        sub = ws.problem()
        out = _search(sub, sub.penalty(w[ws.atoms]), ws.to_sub(P), args, lam0)
        total_it += out.n_iter
        z = ws.to_full(out.z)
        P = ws.to_full_index(out.passive)
        if ws.size == n:
            break
        lam = out.lam
        tol_abs = args.tol * prob.scale(lam * wts if lam > 0 else wts * args.lam_max)
        g = prob.rmatvec(prob.residual(z))[:n] - lam * w  # minus the gradient, atoms only
        g[ws.atoms] = -np.inf
        viol = np.flatnonzero(g > tol_abs)
        log.debug(
            "constrained working set round %d: %d atoms, %s at lam=%.6g, %d KKT violations",
            n_round, ws.size, out.kind, lam, viol.size,
        )  # fmt: skip
        if viol.size == 0:
            break
        grow = max(WORKING_SET_GROW, ws.size // 2)
        ws.add(viol if viol.size <= grow else _top(g, grow))
        lam0 = lam if out.kind == "found" and lam > 0 else None
    return _Outcome(out.kind, z, out.lam, P, total_it, out.converged, out.rn)


def _use_working_set(working_set: bool | None, n: int) -> bool:
    if working_set is None:
        return n > WORKING_SET_MIN_ATOMS
    return bool(working_set)


def _top(score: NDArray, k: int) -> NDArray[np.intp]:
    """Indices of the ``k`` largest entries of ``score``, ascending."""
    if k >= score.size:
        return np.arange(score.size)
    return np.sort(np.argpartition(score, score.size - k)[score.size - k :])


@dataclass
class _Outcome:
    """End of the penalty search on one (sub-)problem, in that problem's indices."""

    kind: Literal["found", "infeasible", "not_found"]
    z: NDArray
    lam: float
    passive: list[int]
    n_iter: int
    converged: bool
    rn: float


def _constrained_result(
    prob: Problem, out: _Outcome, eps: float, wts: NDArray, on_infeasible: str
) -> ConvexResult:
    if out.kind == "infeasible":
        return _infeasible(prob, out.z, out.rn, eps, wts, out.n_iter, on_infeasible)
    if out.kind == "not_found":
        log.warning("constrained solve: the penalty was not found (lam %.6g)", out.lam)
    x, b = prob.split(out.z)
    return ConvexResult(
        coef=x,
        background=b,
        lam=float(out.lam),
        objective=float(wts[: prob.n] @ x),
        residual_norm=out.rn,
        n_iter=out.n_iter,
        converged=out.converged,
    )


def _search(
    prob: Problem,
    wts: NDArray,
    P: list[int],
    args: _SearchArgs,
    lam0: float | None = None,
) -> _Outcome:
    """The penalty ``lam`` whose penalised solution has ``||r|| = eps`` (see the module notes).

    ``wts`` are the weights (N,) with 0 on the background, ``P`` the initial passive set and
    ``lam0`` an optional first guess in ``(0, lam_max)``.
    """
    e = args.eps
    br = _Bracket.start(e, args.lam_max, args.rn_max)
    lam = br.first_guess(lam0)
    total_it = 0
    for n_eval in range(1, MAX_LAMBDA_EVALUATIONS + 1):
        c = lam * wts
        tol_abs = args.tol * prob.scale(c if lam > 0 else wts * args.lam_max)
        st = active_set(prob, c, P, tol_abs, args.max_it)
        total_it += st.n_iter
        P = list(st.passive)
        pc = _piece(prob, P, wts, tol_abs)
        rn = float(np.linalg.norm(prob.residual(st.z)))
        root = pc.root(e)
        log.debug(
            "constrained eval %d: lam=%.6g ||r||=%.6g eps=%.6g piece=[%.6g, %.6g] root=%s |P|=%d",
            n_eval, lam, rn, e, pc.lo, pc.hi, root, len(P),
        )  # fmt: skip
        if abs(rn - e) <= args.r_tol:  # this penalised solution already meets the bound
            return _Outcome("found", st.z, float(lam), P, total_it, st.converged, rn)
        rejected = False
        if root is not None:
            slack = 1e-9 * max(root, lam)
            if pc.lo - slack <= root <= pc.hi + slack:
                done = _finish(prob, pc, root, e, wts, tol_abs, args.r_tol)
                if done is not None:
                    z, rn_f, ok = done
                    return _Outcome("found", z, float(root), list(pc.P), total_it, ok, rn_f)
                rejected = True
        if pc.lo <= 0 and root is None and rn > e:
            return _nnls_end(prob, pc, e, args.r_tol, total_it)
        if br.shrink(pc, lam, rn, rejected):
            break
        lam = br.next_guess(root)
    # not found: the closest evaluated solution
    log.debug("constrained search: the penalty was not found (bracket [%.6g, %.6g])", br.lo, br.hi)
    c = br.hi * wts
    st = active_set(prob, c, P, args.tol * prob.scale(c), args.max_it)
    total_it += st.n_iter
    rn = float(np.linalg.norm(prob.residual(st.z)))
    return _Outcome("not_found", st.z, float(br.hi), list(st.passive), total_it, False, rn)


def _nnls_end(prob: Problem, pc: _Piece, eps: float, r_tol: float, total_it: int) -> _Outcome:
    """The ``lam = 0`` end (the NNLS fit) of a piece that is optimal down to ``lam = 0``:
    infeasible unless it fits exactly (``eps = 0``)."""
    z0 = np.zeros(prob.N)
    if pc.P.size:
        z0[pc.P] = np.maximum(pc.a, 0.0)
    r0n = float(np.linalg.norm(prob.residual(z0)))
    kind = "found" if r0n <= eps + r_tol else "infeasible"  # found: eps = 0, exact fit
    return _Outcome(kind, z0, 0.0, list(pc.P), total_it, True, r0n)


@dataclass
class _Bracket:
    """Bracket ``[lo, hi]`` on ``lam`` with ``g = ||r||^2 - eps^2`` at both ends.

    While ``lo = 0``, ``g_lo`` is its lower bound ``-eps^2`` (a zero residual); at ``hi =
    lam_max`` the solution is ``x = 0`` (known). ``side`` is the end that moved last (1: hi,
    -1: lo) for the Illinois rule.
    """

    eps: float
    lam_max: float
    lo: float
    g_lo: float
    hi: float
    g_hi: float
    side: int = 0
    newton_streak: int = 0

    @classmethod
    def start(cls, e: float, lam_max: float, rn_max: float) -> _Bracket:
        return cls(e, lam_max, 0.0, -e * e, lam_max, rn_max * rn_max - e * e)

    def first_guess(self, lam0: float | None) -> float:
        """``lam0`` when it lies in ``(0, lam_max)``, otherwise regula falsi on the bracket."""
        e = self.eps
        lam = self.lam_max * (e * e) / (e * e + self.g_hi)  # regula falsi
        if lam0 is not None and 0 < lam0 < self.lam_max:
            lam = lam0
        return lam

    def shrink(self, pc: _Piece, lam: float, rn: float, rejected: bool) -> bool:
        """Move the end on ``lam``'s side past the whole piece; True when the bracket closed.

        Only to ``lam`` itself if its root failed or the piece, by round-off, does not contain
        ``lam``. Illinois rule: when the same end moves twice, halve the other end's ``g``.
        """
        e = self.eps
        slack = 1e-9 * lam
        rejected = rejected or not (pc.lo - slack <= lam <= pc.hi + slack)
        g = rn * rn - e * e
        if rn > e:
            new = lam if rejected else min(lam, max(pc.lo, self.lo))
            self.hi, self.g_hi = new, (g if new == lam else pc.sq_norm(new) - e * e)
            if self.side == 1:
                self.g_lo *= 0.5
            self.side = 1
        else:
            new = lam if rejected else max(lam, min(pc.hi, self.hi))
            self.lo, self.g_lo = new, (g if new == lam else pc.sq_norm(new) - e * e)
            if self.side == -1:
                self.g_hi *= 0.5
            self.side = -1
        return self.hi <= self.lo * (1 + 1e-15)

    def next_guess(self, root: float | None) -> float:
        """The piece's root (a Newton step) when it lies inside the bracket, at most three
        times in a row; otherwise regula falsi on ``g(lam)``, kept inside the bracket."""
        lo, hi = self.lo, self.hi
        if lo > 0 and root is not None and lo < root < hi and self.newton_streak < 3:
            lam = float(root)
            self.newton_streak += 1
        else:
            t = -self.g_lo / (self.g_hi - self.g_lo) if self.g_hi > self.g_lo else 0.5
            lam = lo + min(max(t, 1e-3), 1 - 1e-3) * (hi - lo)
            self.newton_streak = 0
        if lo == 0 and hi <= 1e-12 * self.lam_max:
            lam = 0.0  # the non-negative least-squares end
        return lam


def _finish(
    prob: Problem,
    pc: _Piece,
    lam: float,
    eps: float,
    wts: NDArray,
    tol_abs: float,
    r_tol: float,
) -> tuple[NDArray, float, bool] | None:
    """The solution at ``lam`` on the piece's active set, if it satisfies the KKT conditions:
    ``(z, ||r||, ||r|| == eps to tolerance)``."""
    z = np.zeros(prob.N)
    if pc.P.size:
        zp = pc.a - lam * pc.g
        z[pc.P] = np.where(zp > 0, zp, 0.0)
    c = lam * wts
    viol = kkt_violation(prob, z, c)
    tol_kkt = 10 * tol_abs + 1e-9 * prob.scale(wts * max(lam, 1e-300))
    if viol > tol_kkt:
        log.debug("piece root lam=%.6g rejected: KKT violation %.3g", lam, viol)
        return None
    rn = float(np.linalg.norm(prob.residual(z)))
    return z, rn, abs(rn - eps) <= max(1e-6 * eps, r_tol)


def _infeasible(
    prob: Problem,
    z: NDArray,
    rn: float,
    eps: float,
    wts: NDArray,
    n_iter: int,
    on_infeasible: str,
) -> ConvexResult:
    msg = (
        f"infeasible: the non-negative least-squares fit leaves ||y - A x - b|| = {rn:.6g} "
        f"photons > eps = {eps:.6g}"
    )
    if on_infeasible == "raise":
        raise ValueError(msg)
    # info, not warning: restricted dictionaries (the hybrid's boxes) are often infeasible by
    # design, and the result says so (feasible=False)
    log.info("%s; returning that fit", msg)
    x, b = prob.split(z)
    return ConvexResult(
        coef=x,
        background=b,
        lam=0.0,
        objective=float(wts[: prob.n] @ x),
        residual_norm=rn,
        n_iter=n_iter,
        converged=True,
        feasible=False,
    )
