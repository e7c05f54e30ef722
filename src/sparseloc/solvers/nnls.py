"""Non-negative least squares over sparse atoms: ``min ||A x - y||^2`` subject to ``x >= 0``.

The frame solver's pursuit refits the amplitudes of every atom it placed after each cycle. Its
atoms are templates centred on pixels of the frame, so each overlaps only its neighbours and
the Gram matrix ``A'A`` is sparse. Lawson and Hanson's active-set method (scipy's ``nnls``)
adds one atom per step on a dense factor: its cost grows with the cube of the atoms, which a
dense frame counts in thousands (docs/benchmarks/pursuit_nnls.txt). Block principal pivoting
(Kim & Park, SIAM J. Sci. Comput. 33, 3261 (2011)) exchanges every atom on the wrong side of
the optimality conditions at once and solves each passive set with a sparse factorization: a
few steps, each far below the dense method's cost. Both return the unique optimum when
``A'A`` is positive definite, which the small ridge below ensures.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import nnls
from scipy.sparse import csc_matrix, identity
from scipy.sparse.linalg import splu

__all__ = ["RIDGE", "active_set_nnls", "gram_nnls", "sparse_nnls"]

#: Ridge added to the Gram matrix's diagonal, relative to its mean diagonal: two atoms with
#: the same image (a template placed twice) would otherwise make it singular.
RIDGE = 1e-9
#: Steps of block principal pivoting before the exact but slower active-set method takes over
#: (it converges in a few steps on the pursuit's problems; the bound only guards against
#: cycling on a degenerate one).
MAX_PIVOTS = 100


def sparse_nnls(a: csc_matrix, y: NDArray) -> NDArray[np.float64]:
    """The amplitudes ``x >= 0`` (K,) that minimise ``||a x - y||^2``.

    Parameters
    ----------
    a : sparse matrix, shape (pixels, K)
        The atoms' images, one column each.
    y : ndarray, shape (pixels,)
        The image they explain.
    """
    g = csc_matrix(a.T @ a)
    b = np.asarray(a.T @ y, dtype=np.float64).ravel()
    k = g.shape[0]
    if k == 0:
        return np.zeros(0)
    g = csc_matrix(g + RIDGE * max(float(g.diagonal().sum()) / k, 1e-30) * identity(k))
    return gram_nnls(g, b)


def gram_nnls(g: csc_matrix, b: NDArray) -> NDArray[np.float64]:
    """``argmin_{x >= 0} x'gx/2 - b'x`` for a sparse positive definite ``g`` (K, K) and ``b``
    (K,): block principal pivoting, or the active-set method where it does not settle."""
    x = _pivoting(g, b)
    return x if x is not None else active_set_nnls(g.toarray(), b)


def active_set_nnls(g: NDArray, b: NDArray) -> NDArray[np.float64]:
    """The same optimum for a dense positive definite ``g`` (K, K) by Lawson and Hanson's
    active-set method (scipy's ``nnls``) on its Cholesky factor: exact, cubic in K."""
    from scipy.linalg import cholesky, solve_triangular

    r = cholesky(g, lower=False)
    x, _ = nnls(r, solve_triangular(r, b, trans="T", lower=False), maxiter=50 * len(b))
    return x


def _pivoting(g: csc_matrix, b: NDArray) -> NDArray[np.float64] | None:
    """Kim & Park's block principal pivoting: the passive set's equations solved exactly, every
    variable that breaks the optimality conditions (a negative amplitude, or a zero one whose
    gradient asks to grow) exchanged, down to one at a time after three exchanges that did not
    lower their count. None if it has not settled after :data:`MAX_PIVOTS` steps."""
    k = len(b)
    free = b > 0
    # gradients this small are rounding: an atom whose growth they ask for gains nothing
    tol = 1e-10 * max(float(np.abs(b).max()), 1e-300)
    best, backup = k + 1, 3
    for _ in range(MAX_PIVOTS):
        x = np.zeros(k)
        idx = np.flatnonzero(free)
        if idx.size:
            x[idx] = splu(csc_matrix(g[idx][:, idx]), permc_spec="MMD_AT_PLUS_A").solve(b[idx])
        grad = g @ x - b
        wrong = (free & (x < 0)) | (~free & (grad < -tol))
        n_wrong = int(wrong.sum())
        if n_wrong == 0:
            return x
        if n_wrong < best:
            best, backup = n_wrong, 3
            free ^= wrong
        elif backup > 0:
            backup -= 1
            free ^= wrong
        else:
            i = int(np.flatnonzero(wrong).max())
            free[i] = not free[i]
    return None
