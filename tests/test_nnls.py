"""The pursuit's sparse NNLS against scipy's dense active-set NNLS (the reference), and its
exclusion rule against a comparison with every atom placed."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import nnls

from sparseloc.solvers import nnls as nnls_module
from sparseloc.solvers.nnls import gram_nnls, sparse_nnls


def _atoms(rng, side: int, n: int, width: int = 7) -> sp.csc_matrix:
    """``n`` Gaussian spots of ``width`` px on a ``side`` x ``side`` image, some placed twice,
    as the columns of a sparse matrix (the pursuit's atoms: each overlaps its neighbours)."""
    rr, cc = np.mgrid[0:side, 0:side]
    cols = []
    centres = rng.uniform(0, side, (n, 2))
    centres[-3:] = centres[:3]  # atoms placed twice: a singular Gram matrix without the ridge
    for r0, c0 in centres:
        img = np.exp(-((rr - r0) ** 2 + (cc - c0) ** 2) / (2 * (width / 2.355) ** 2))
        img[img < 1e-3] = 0.0
        cols.append(sp.csc_matrix(img.reshape(-1, 1)))
    return sp.hstack(cols, format="csc")


def _reference(a: sp.csc_matrix, y: np.ndarray) -> np.ndarray:
    """scipy's NNLS on the same ridged Gram system (its Cholesky factor as the matrix)."""
    from scipy.linalg import cholesky, solve_triangular

    g = (a.T @ a).toarray()
    g[np.diag_indices_from(g)] += nnls_module.RIDGE * np.trace(g) / len(g)
    r = cholesky(g, lower=False)
    x, _ = nnls(r, solve_triangular(r, a.T @ y, trans="T", lower=False), maxiter=50 * len(g))
    return x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sparse_nnls_is_the_nnls_optimum(seed):
    rng = np.random.default_rng(seed)
    a = _atoms(rng, 60, 150)
    truth = rng.uniform(0, 1000, a.shape[1]) * (rng.random(a.shape[1]) < 0.6)
    y = a @ truth + rng.normal(0, 20, a.shape[0])  # noise: some amplitudes end at zero
    x = sparse_nnls(a, y)
    ref = _reference(a, y)
    g = sp.csc_matrix(a.T @ a)
    g = sp.csc_matrix(g + nnls_module.RIDGE * g.diagonal().mean() * sp.identity(g.shape[0]))
    assert nnls_module._pivoting(g, a.T @ y) is not None  # not the fallback's answer
    assert np.all(x >= 0)
    assert np.sum(x == 0) >= 5  # the bound is active somewhere, or the test proves little
    # the same objective; the same amplitudes, where twice-placed atoms (whose split only the
    # ridge decides, to about 1e-7) count as their sum
    assert np.linalg.norm(a @ x - y) == pytest.approx(np.linalg.norm(a @ ref - y), rel=1e-12)
    pooled, pooled_ref = x[:-3].copy(), ref[:-3].copy()
    pooled[:3] += x[-3:]
    pooled_ref[:3] += ref[-3:]
    assert np.abs(pooled - pooled_ref).max() <= 1e-8 * ref.max()


def test_optimality_conditions_hold():
    rng = np.random.default_rng(3)
    a = _atoms(rng, 40, 80)
    y = a @ rng.uniform(-200, 1000, a.shape[1])  # negative truths: many amplitudes at zero
    x = sparse_nnls(a, y)
    gs = sp.csc_matrix(a.T @ a)
    gs = sp.csc_matrix(gs + nnls_module.RIDGE * gs.diagonal().mean() * sp.identity(gs.shape[0]))
    assert nnls_module._pivoting(gs, a.T @ y) is not None
    g = (a.T @ a).toarray()
    g[np.diag_indices_from(g)] += nnls_module.RIDGE * np.trace(g) / len(g)
    grad = g @ x - a.T @ y
    scale = np.abs(a.T @ y).max()
    assert np.all(x >= 0)
    assert np.all(np.abs(grad[x > 0]) <= 1e-8 * scale)  # stationary where free
    assert np.all(grad[x == 0] >= -1e-8 * scale)  # no zero amplitude asks to grow


def test_no_atoms_and_a_dark_image():
    assert sparse_nnls(sp.csc_matrix((25, 0)), np.zeros(25)).shape == (0,)
    a = _atoms(np.random.default_rng(4), 20, 10)
    assert np.all(sparse_nnls(a, -np.ones(a.shape[0])) == 0)


def test_the_active_set_method_takes_over_where_pivoting_does_not_settle(monkeypatch):
    rng = np.random.default_rng(5)
    a = _atoms(rng, 40, 60)
    y = a @ rng.uniform(0, 1000, a.shape[1]) + rng.normal(0, 20, a.shape[0])
    monkeypatch.setattr(nnls_module, "MAX_PIVOTS", 0)
    g = sp.csc_matrix(a.T @ a)
    g = sp.csc_matrix(g + nnls_module.RIDGE * g.diagonal().mean() * sp.identity(g.shape[0]))
    x = gram_nnls(g, a.T @ y)
    ref = _reference(a, y)
    assert np.linalg.norm(a @ x - y) == pytest.approx(np.linalg.norm(a @ ref - y), rel=1e-12)


def test_the_pursuits_exclusion_refuses_what_a_comparison_with_every_atom_refuses():
    from sparseloc.solvers.frame_mp import _Exclusion

    rng = np.random.default_rng(6)
    for distance in (2.0, 3.5, 6.3):
        taken, placed = _Exclusion((50, 70), distance), []
        for r, c in rng.integers(0, [50, 70], size=(400, 2)):
            near = any((r - r2) ** 2 + (c - c2) ** 2 < distance**2 for r2, c2 in placed)
            assert taken.near(r, c) == near
            if not near:
                taken.add(r, c)
                placed.append((r, c))
        assert len(placed) > 10
