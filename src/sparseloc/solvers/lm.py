"""The Levenberg-Marquardt rule of the maximum-likelihood fit, written once for every engine.

The fit minimises ``-log L`` by Fisher scoring with Levenberg-Marquardt damping: each iteration
solves ``(F + lam diag F) d = -grad`` (the diagonal floored at 1e-12), clamps ``theta + d`` to
the parameters' bounds and takes the step only if ``-log L`` falls; then ``lam`` shrinks by 10
(not below 1e-7), else it grows by 10 and the step is solved again (at most 12 times). The fit
has converged when no step lowers ``-log L`` or when the relative decrease falls below ``tol``.

:func:`make_levenberg_marquardt` turns an engine's four operations into that loop: the NumPy
engine (:mod:`sparseloc.solvers.refine`, any PSF model) runs it as Python, the numba engine
(:mod:`sparseloc.solvers._fit_numba`, spline tables) compiles the same function. The helpers
:func:`damped_system` and :func:`clamp` are likewise shared: plain Python that numba compiles.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = [
    "DAMPING_TRIALS",
    "LAMBDA_FACTOR",
    "LAMBDA_MIN",
    "LAMBDA_START",
    "clamp",
    "damped_system",
    "make_levenberg_marquardt",
]

#: Damping at the first iteration.
LAMBDA_START = 1e-3
#: The damping shrinks by this factor after a step taken, and grows by it after a step refused.
LAMBDA_FACTOR = 10.0
#: Floor of the damping.
LAMBDA_MIN = 1e-7
#: Steps tried per iteration before the fit is declared at a (constrained) optimum.
DAMPING_TRIALS = 12
#: Floor of the Fisher matrix's diagonal in the damping term.
DIAGONAL_FLOOR = 1e-12


def damped_system(fisher: np.ndarray, lam: float, out: np.ndarray) -> None:
    """``out = F + lam diag(max(diag F, 1e-12))`` for Fisher matrix ``F`` (P, P), in place."""
    n = fisher.shape[0]
    for q in range(n):
        for s in range(n):
            out[q, s] = fisher[q, s]
        d = fisher[q, q]
        if d < DIAGONAL_FLOOR:
            d = DIAGONAL_FLOOR
        out[q, q] += lam * d


def clamp(theta: np.ndarray, k: int, lo: np.ndarray, hi: np.ndarray, min_bg: float) -> None:
    """Clamp ``theta = [x0, y0, z0, N0, x1, ..., b0, ...]`` in place: each emitter's x, y, z,
    photons to ``[lo, hi]`` (shape (4,); NaN becomes ``lo``), the background level ``b0`` to at
    least ``min_bg``."""
    for i in range(k):
        for j in range(4):
            t = theta[4 * i + j]
            if not (t >= lo[j]):  # also NaN
                t = lo[j]
            if t > hi[j]:
                t = hi[j]
            theta[4 * i + j] = t
    if not (theta[4 * k] >= min_bg):
        theta[4 * k] = min_bg


def _levenberg_marquardt(state, max_iter, tol):
    """The loop of :func:`make_levenberg_marquardt`; ``evaluate``, ``score``, ``trial`` and
    ``accept`` are globals of each copy that function makes."""
    f = evaluate(state)  # noqa: F821
    lam = LAMBDA_START
    converged = False
    n_iter = 0
    scored = False  # whether the Fisher matrix is that of the current parameters
    for it in range(1, max_iter + 1):
        n_iter = it
        score(state)  # noqa: F821
        scored = True
        improved = False
        f_t = np.inf
        for _ in range(DAMPING_TRIALS):
            f_t = trial(state, lam)  # noqa: F821
            if f_t < f:
                improved = True
                break
            lam *= LAMBDA_FACTOR
        if not improved:
            converged = True  # no step lowers -log L: a (constrained) optimum
            break
        rel = (f - f_t) / max(abs(f), 1.0)
        accept(state)  # noqa: F821
        f = f_t
        lam = max(lam / LAMBDA_FACTOR, LAMBDA_MIN)
        scored = False
        if rel < tol:
            converged = True
            break
    if not scored:
        score(state)  # noqa: F821  (the Fisher matrix at the result gives the standard errors)
    return f, converged, n_iter


def make_levenberg_marquardt(
    evaluate: Callable[[Any], float],
    score: Callable[[Any], None],
    trial: Callable[[Any, float], float],
    accept: Callable[[Any], None],
) -> Callable[[Any, int, float], tuple[float, bool, int]]:
    """The Levenberg-Marquardt loop over one engine's operations on a fit's ``state``.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(state) -> f``: the model, ``-log L`` and the Jacobian at the start.
    score : callable
        ``score(state)``: gradient and Fisher matrix at the current parameters.
    trial : callable
        ``trial(state, lam) -> f_t``: solve the damped system (:func:`damped_system`), clamp
        the step (:func:`clamp`) and return ``-log L`` there; ``inf`` when the system cannot be
        solved or the step is not finite.
    accept : callable
        ``accept(state)``: the trial becomes the current parameters (with its Jacobian).

    Returns
    -------
    callable
        ``loop(state, max_iter, tol) -> (f, converged, n_iter)``; ``state`` then holds the
        result and the Fisher matrix at it.

    Notes
    -----
    The loop is a copy of one function with the four operations as its globals, not a
    closure over them: numba's cache keys a closure by its pickled cells, which differ in
    every process, so a compiled closure was compiled again (seconds) in every process and
    added a new entry to the cache each time.
    """
    namespace = dict(globals())
    namespace.update(evaluate=evaluate, score=score, trial=trial, accept=accept)
    # each engine's copy its own name: numba files a cached function under its name, so two
    # engines' copies would otherwise share (and load) each other's compiled code
    engine = getattr(evaluate, "__module__", "engine").replace(".", "_")
    name = f"levenberg_marquardt_{engine}"
    code = _levenberg_marquardt.__code__.replace(co_name=name, co_qualname=name)
    loop = types.FunctionType(code, namespace, name)
    loop.__doc__ = _levenberg_marquardt.__doc__
    return loop
