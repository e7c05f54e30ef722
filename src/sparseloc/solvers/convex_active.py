"""The Lawson-Hanson active-set machinery of :mod:`sparseloc.solvers.convex`.

:class:`Problem` holds ``B = [A, 1]`` (or ``A`` with a fixed background subtracted from ``y``)
and the products the solver needs; :func:`active_set` solves the penalised non-negative
least-squares problem ``min 0.5 ||B z - y||^2 + c'z, z >= 0`` exactly on it (see the notes of
:mod:`sparseloc.solvers.convex`), and :class:`WorkingSet` restricts a problem to a growing set
of its atoms.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dposv as _posv

# The active-set steps log as part of the convex solver.
log = logging.getLogger("sparseloc.solvers.convex")

__all__ = [
    "GRAM_CACHE_MAX",
    "ActiveSetState",
    "Problem",
    "WorkingSet",
    "active_set",
    "face_inverse",
    "kkt_violation",
]

#: Cache the full Gram matrix ``B' B`` when there are at most this many atoms.
GRAM_CACHE_MAX = 512
# Relative eigenvalue threshold below which a face's Gram matrix is treated as singular.
_SINGULAR_RTOL = 1e-12
# Cholesky is trusted when min(diag L) / max(diag L) exceeds this (condition number <~ 1e14).
_CHOL_DIAG_RATIO = 1e-7


# -- the problem -----------------------------------------------------------------------------
class Problem:
    """``B = [A, 1]`` (or ``A`` with a fixed background subtracted from ``y``), ``z = [x, b]``.

    ``B`` is held as one C-ordered matrix (a copy of ``A`` with the column of ones appended
    when the background is estimated) unless ``copy=False``: the working set's parent problem
    only needs products with ``A``.
    """

    def __init__(
        self,
        A: NDArray,
        y: NDArray,
        background: float | None,
        *,
        cache_gram: bool = True,
        copy: bool = True,
        B: NDArray | None = None,
        Bty: NDArray | None = None,
        bty_max: float = 0.0,
    ) -> None:
        self.A = A
        self.m, self.n = A.shape
        self.has_bg = background is None
        self.b_fixed = 0.0 if background is None else float(background)
        self.y_raw = y
        self.y = y - self.b_fixed if self.b_fixed else y
        self.N = self.n + int(self.has_bg)
        self.B: NDArray | None = B
        if B is None and not self.has_bg:
            self.B = A
        elif B is None and copy:
            self.B = np.empty((self.m, self.N))
            self.B[:, : self.n] = A
            self.B[:, self.n] = 1.0
        self.Bty = self.rmatvec(self.y) if Bty is None else Bty
        # the tolerances' scale: a sub-problem inherits its parent's, so both certify alike
        self._bty_max = max(float(np.max(np.abs(self.Bty))), bty_max)
        self._gram = None
        if cache_gram and self.N <= GRAM_CACHE_MAX:
            C = self.cols(np.arange(self.N))
            self._gram = C.T @ C

    def matvec(self, z: NDArray) -> NDArray:
        """``B z`` (only the non-zero columns are used when ``z`` is sparse)."""
        if self.B is not None:
            nz = np.flatnonzero(z)
            return self.B[:, nz] @ z[nz] if nz.size < self.N // 4 else self.B @ z
        x = z[: self.n]
        nz = np.flatnonzero(x)
        out = self.A[:, nz] @ x[nz] if nz.size < self.n // 4 else self.A @ x
        return out + z[self.n]

    def rmatvec(self, r: NDArray) -> NDArray:
        """``B' r`` for ``r`` of shape (m,) or (m, k)."""
        if r.ndim == 2:  # column by column: narrow matrix products are slow in BLAS
            return np.stack([self.rmatvec(r[:, i]) for i in range(r.shape[1])], axis=1)
        if self.B is not None:
            return r @ self.B  # row-vector GEMV on the C-ordered matrix
        out = np.empty(self.N)
        out[: self.n] = r @ self.A
        out[self.n] = r.sum()
        return out

    def cols(self, idx: NDArray | Sequence[int]) -> NDArray:
        if self.B is not None:
            return self.B[:, idx]
        idx = np.asarray(idx, dtype=np.intp)
        out = np.empty((self.m, idx.size))
        atom = idx < self.n
        out[:, atom] = self.A[:, idx[atom]]
        out[:, ~atom] = 1.0
        return out

    def gram(self, idx: NDArray | Sequence[int]) -> NDArray:
        if self._gram is not None:
            idx = np.asarray(idx, dtype=np.intp)
            return self._gram[np.ix_(idx, idx)]
        C = self.cols(idx)
        return C.T @ C

    def neg_gradient(self, z: NDArray, P: Sequence[int], q_all: NDArray, c: NDArray) -> NDArray:
        """``-(B'(Bz - y) + c)`` for ``z`` supported on ``P``."""
        if self._gram is not None:
            idx = np.asarray(P, dtype=np.intp)
            return q_all - self._gram[:, idx] @ z[idx]
        r = self.y - self.cols(P) @ z[P] if P else self.y
        return self.rmatvec(r) - c

    def penalty(self, lam: float | NDArray) -> NDArray:
        """``c`` of shape (N,): the penalty on every atom, 0 on the background."""
        c = np.zeros(self.N)
        c[: self.n] = lam
        return c

    def split(self, z: NDArray) -> tuple[NDArray, float]:
        x = z[: self.n].copy()
        b = float(z[self.n]) if self.has_bg else self.b_fixed
        return x, b

    def residual(self, z: NDArray) -> NDArray:
        return self.y - self.matvec(z)

    def scale(self, c: NDArray) -> float:
        """Magnitude of the gradient's terms (for absolute tolerances)."""
        s = max(self._bty_max, float(np.max(np.abs(c))) if c.size else 0.0)
        return s if s > 0 else 1.0


class WorkingSet:
    """A growing set of a problem's atoms and its sub-problem (atoms in the order added).

    The sub-problem's matrix ``[A_W, 1]`` lives in a buffer with spare columns, so adding
    atoms copies only the new columns (the background column moves to the end).
    """

    def __init__(self, prob: Problem, atoms: NDArray) -> None:
        self.prob = prob
        self.atoms = np.empty(0, dtype=np.intp)
        self.pos = np.full(prob.n, -1, dtype=np.intp)  # atom -> its index in the sub-problem
        self._buf = np.empty((prob.m, 0))
        self.add(atoms)

    @property
    def size(self) -> int:
        return self.atoms.size

    def add(self, new: NDArray) -> None:
        """Append the atoms ``new`` (not yet in the set)."""
        prob = self.prob
        k, a = self.atoms.size, new.size
        need = k + a + int(prob.has_bg)
        if need > self._buf.shape[1]:
            buf = np.empty((prob.m, max(need, 2 * self._buf.shape[1])))
            buf[:, :k] = self._buf[:, :k]
            self._buf = buf
        self._buf[:, k : k + a] = prob.A[:, new]
        if prob.has_bg:
            self._buf[:, k + a] = 1.0
        self.pos[new] = np.arange(k, k + a)
        self.atoms = np.concatenate([self.atoms, new])

    def problem(self) -> Problem:
        """The problem restricted to the set (same ``y``, background and tolerance scale)."""
        prob, k = self.prob, self.atoms.size
        B = self._buf[:, : k + int(prob.has_bg)]
        Bty = np.concatenate([prob.Bty[self.atoms], prob.Bty[prob.n :]])
        bg = None if prob.has_bg else prob.b_fixed
        return Problem(
            B[:, :k], prob.y_raw, bg, cache_gram=False, B=B, Bty=Bty, bty_max=prob._bty_max
        )

    def to_sub(self, P: Sequence[int]) -> list[int]:
        """Indices ``P`` of the full ``z`` (background at ``n``) that lie in the set, as
        indices of the sub-problem's ``z`` (background at ``size``)."""
        n = self.prob.n
        out = []
        for p in P:
            if p == n:
                out.append(self.atoms.size)
            elif self.pos[p] >= 0:
                out.append(int(self.pos[p]))
        return out

    def to_full(self, z_sub: NDArray) -> NDArray:
        """The sub-problem's ``z`` as the full problem's."""
        prob, k = self.prob, self.atoms.size
        z = np.zeros(prob.N)
        z[self.atoms] = z_sub[:k]
        if prob.has_bg:
            z[prob.n] = z_sub[k]
        return z

    def to_full_index(self, idx: Sequence[int]) -> list[int]:
        """Indices of the sub-problem's ``z`` as indices of the full one."""
        k, n = self.atoms.size, self.prob.n
        return [int(self.atoms[i]) if i < k else n for i in idx]


# -- face solves -----------------------------------------------------------------------------
def _cholesky_solve(G: NDArray, rhs: NDArray) -> NDArray | None:
    """``G^-1 rhs`` by Cholesky (LAPACK ``posv``), or None when ``G`` is not safely definite."""
    L, s, info = _posv(G, rhs, lower=1)
    if info != 0:
        return None
    dg = np.diagonal(L)
    if not dg.min() > _CHOL_DIAG_RATIO * dg.max():
        return None
    return s


def _face_solve(G: NDArray, q: NDArray) -> tuple[NDArray | None, NDArray | None]:
    """Minimise ``0.5 z'Gz - q'z`` without constraints.

    Returns ``(s, None)`` with a minimiser (the minimum-norm one if ``G`` is singular but ``q``
    lies in its range) or ``(None, d)`` with a direction ``G d = 0, q'd > 0`` along which the
    objective decreases without bound.
    """
    s = _cholesky_solve(G, q)
    if s is not None and np.isfinite(s).all():
        return s, None
    vals, vecs = np.linalg.eigh(G)
    keep = vals > _SINGULAR_RTOL * max(float(vals[-1]), 1e-300) * G.shape[0]
    proj = vecs.T @ q
    null = ~keep
    qn = proj[null]
    qnorm = float(np.linalg.norm(q))
    if qn.size and float(np.linalg.norm(qn)) > 1e-9 * max(qnorm, 1e-300):
        return None, vecs[:, null] @ qn
    return vecs[:, keep] @ (proj[keep] / vals[keep]), None


def face_inverse(G: NDArray, rhs: NDArray) -> NDArray:
    """``G^+ rhs`` (Cholesky, or eigen-decomposition when ``G`` is singular)."""
    s = _cholesky_solve(G, rhs)
    if s is not None:
        return s
    vals, vecs = np.linalg.eigh(G)
    keep = vals > _SINGULAR_RTOL * max(float(vals[-1]), 1e-300) * G.shape[0]
    return vecs[:, keep] @ ((vecs[:, keep].T @ rhs) / vals[keep].reshape(-1, *[1] * (rhs.ndim - 1)))


# -- the active-set solver -------------------------------------------------------------------
@dataclass
class ActiveSetState:
    """End of :func:`active_set`: the solution ``z`` (N,), its passive set, the face solves
    used and whether the KKT conditions hold to the tolerance."""

    z: NDArray
    passive: list[int]
    n_iter: int
    converged: bool


def active_set(
    prob: Problem,
    c: NDArray,
    init: Sequence[int],
    tol_abs: float,
    max_iter: int,
) -> ActiveSetState:
    """Lawson-Hanson for ``min 0.5||Bz - y||^2 + c'z, z >= 0`` from the passive set ``init``.

    Each outer iteration adds the atom with the largest negative gradient (above ``tol_abs``)
    to the passive set ``P``; ``max_iter`` bounds the face solves in all.
    """
    q_all = prob.Bty - c
    z, P, it = _warm_start(prob, q_all, init)
    excluded: set[int] = set()
    converged = False
    while True:
        w = prob.neg_gradient(z, P, q_all, c)
        w[P] = -np.inf
        if excluded:
            w[list(excluded)] = -np.inf
        j = int(np.argmax(w))
        if not w[j] > tol_abs:
            converged = True
            break
        if it >= max_iter:
            break
        P.append(j)
        P, it, first, progressed = _enter(prob, z, P, q_all, it, max_iter)
        if first and not progressed and P and P[-1] == j:
            P.pop()
            excluded.add(j)
            log.debug("active set: atom %d rejected by its face solve", j)
        elif progressed:
            excluded.clear()
        if it >= max_iter:
            break
    off = np.ones(prob.N, bool)
    off[P] = False
    z[off] = 0.0
    return ActiveSetState(z=z, passive=P, n_iter=it, converged=converged)


def _warm_start(
    prob: Problem, q_all: NDArray, init: Sequence[int]
) -> tuple[NDArray, list[int], int]:
    """Solve on the initial face and drop its non-positive entries until the solution is
    positive: ``(z, P, face solves)``."""
    z = np.zeros(prob.N)
    P: list[int] = sorted({int(i) for i in init})
    it = 0
    while P:
        it += 1
        s, _ = _face_solve(prob.gram(P), q_all[P])
        if s is None:
            P = []
            break
        if s.min() > 0:
            z[P] = s
            break
        P = [p for p, v in zip(P, s, strict=True) if v > 0]
    return z, P, it


def _enter(
    prob: Problem, z: NDArray, P: list[int], q_all: NDArray, it: int, max_iter: int
) -> tuple[list[int], int, bool, bool]:
    """The inner loop: let the atom just appended to ``P`` enter the passive set.

    Solves on the face and, while its minimiser is not positive, steps to the boundary and drops
    the atoms that reach zero. Updates ``z`` in place; returns ``(P, it, first, progressed)``
    with ``first`` true when the first face solve already refused the new atom (round-off) and
    ``progressed`` when ``z`` changed.
    """
    first = True
    progressed = False
    while it < max_iter:
        it += 1
        idx = np.asarray(P)
        zP = z[idx]
        s, d = _face_solve(prob.gram(idx), q_all[idx])
        if s is not None and s.min() > 0:
            z[idx] = s
            progressed = True
            break
        # the new atom cannot enter (round-off): skip it
        if first and (s[-1] if s is not None else d[-1]) <= 0:
            break
        znew, drop = _step_to_boundary(zP, s, d)
        z[idx] = znew
        progressed = progressed or np.any(znew != zP)
        P = [p for p, dr in zip(P, drop, strict=True) if not dr]
        first = False
    return P, it, first, progressed


def _step_to_boundary(
    zP: NDArray, s: NDArray | None, d: NDArray | None
) -> tuple[NDArray, NDArray[np.bool_]]:
    """From the positive ``zP``, towards the face minimiser ``s`` (or along the unbounded
    direction ``d`` when there is none) up to the first entry that reaches zero.

    Returns the new values (zeros where dropped) and which entries drop.
    """
    if s is not None:
        neg = s <= 0
        ratio = zP[neg] / (zP[neg] - s[neg])
        alpha = float(ratio.min())
        znew = zP + alpha * (s - zP)
    else:  # unbounded face: move along d to the boundary
        neg = d < 0
        if not np.any(neg):
            raise RuntimeError("the penalised problem is unbounded below (negative lam?)")
        ratio = zP[neg] / -d[neg]
        t = float(ratio.min())
        znew = zP + t * d
    drop = np.zeros(zP.size, bool)
    drop[np.flatnonzero(neg)[np.argmin(ratio)]] = True
    drop |= znew <= 0
    znew[drop] = 0.0
    return znew, drop


def kkt_violation(prob: Problem, z: NDArray, c: NDArray) -> float:
    """Largest violation of the KKT conditions (gradient units)."""
    g = prob.rmatvec(prob.matvec(z) - prob.y) + c
    on = z > 0
    v_on = float(np.max(np.abs(g[on]))) if np.any(on) else 0.0
    v_off = float(np.max(-g[~on])) if np.any(~on) else 0.0
    return max(v_on, v_off, 0.0)
