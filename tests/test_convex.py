"""Exact convex recovery (``sparseloc.solvers.convex``): CVXPY agreement, KKT, edge cases.

Support comparison with CVXPY. An interior-point solution is never exactly sparse: its entries
off the support are about ``mu / g_i`` (barrier parameter over the reduced gradient), ~1e-9 of
the largest coefficient for ordinary zeros but up to ~3e-6 of it for the near-degenerate zeros
these strongly correlated atoms produce (reduced gradient ~1e-4 lam). Conversely, along nearly
flat directions of the objective (differences of neighbouring atoms) the two solvers may share
a few hundredths of a photon differently (seen: 0.0015 vs 0.036 photons, objective equal to
1e-10). So one threshold would be arbitrary; the fair statements, both tested, are:

- above 1e-4 of the largest coefficient (~0.1-0.3 photons) the supports are identical;
- every exact zero of the active-set solution is below 1e-5 of the largest in CVXPY's.

The exact zeros are further certified by the KKT conditions, checked directly.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import scipy.optimize as sopt

from sparseloc.dictionary import DenseDictionary, Dictionary
from sparseloc.solvers.convex import (
    ConvexResult,
    noise_epsilon,
    solve_constrained,
    solve_penalized,
)

BACKGROUND = 5.0
SUPPORT_RTOL = 1e-4
ZERO_RTOL = 1e-5
N_RANDOM = 20


@pytest.fixture(scope="module")
def dictionary(dh_model) -> Dictionary:
    # 7 x 7 px window, 80 nm / 150 nm steps, z in [-300, 300] nm: 5 x 14 x 14 = 980 atoms
    return Dictionary(dh_model, 7, 160.0, 80.0, 150.0, (-300, 300))


@pytest.fixture(scope="module")
def A(dictionary) -> np.ndarray:
    return dictionary.dense()


def _window(A: np.ndarray, seed: int, *, noise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """1-3 emitters of 1000-3000 photons on dictionary atoms, background 5, Poisson noise."""
    rng = np.random.default_rng(seed)
    n = A.shape[1]
    k = int(rng.integers(1, 4))
    x = np.zeros(n)
    x[rng.choice(n, k, replace=False)] = rng.uniform(1000, 3000, k)
    mu = A @ x + BACKGROUND
    y = rng.poisson(mu).astype(float) if noise else mu
    return y, x


def _design(A: np.ndarray, background: float | None) -> np.ndarray:
    return np.hstack([A, np.ones((A.shape[0], 1))]) if background is None else A


def _nnls_residual(A: np.ndarray, y: np.ndarray, background: float | None) -> float:
    B = _design(A, background)
    target = y if background is None else y - background
    return float(sopt.nnls(B, target, maxiter=50 * B.shape[1])[1])


def _assert_kkt(A, y, res: ConvexResult, lam, background, rtol=1e-7):
    """Gradient of 0.5||r||^2 + lam.x: == 0 on the support, >= 0 on the zeros (b likewise)."""
    r = y - A @ res.coef - res.background
    g = -(A.T @ r) + lam
    scale = max(np.max(np.abs(A.T @ y)), np.max(np.abs(lam)), float(np.sum(y)))
    tol = rtol * scale
    on = res.coef > 0
    assert np.all(res.coef >= 0)
    assert np.max(np.abs(g[on]), initial=0.0) <= tol
    assert np.min(g[~on], initial=0.0) >= -tol
    if background is None:
        gb = -float(r.sum())
        assert res.background >= 0
        if res.background > 0:
            assert abs(gb) <= tol
        else:
            assert gb >= -tol


def _cvx_solve(A, y, background, *, lam=None, eps=None):
    cp = pytest.importorskip("cvxpy")
    n = A.shape[1]
    x = cp.Variable(n, nonneg=True)
    b = cp.Variable(nonneg=True) if background is None else background
    r = y - A @ x - b
    if eps is None:
        prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(r) + cp.sum(cp.multiply(lam, x))))
    else:
        prob = cp.Problem(cp.Minimize(cp.sum(x)), [cp.norm(r, 2) <= eps])
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9)
    assert prob.status == "optimal", prob.status
    bv = float(b.value) if background is None else background
    return np.asarray(x.value), bv, float(prob.value)


def _assert_same_support(ours: np.ndarray, theirs: np.ndarray) -> None:
    thr = SUPPORT_RTOL * theirs.max()
    np.testing.assert_array_equal(np.flatnonzero(ours > thr), np.flatnonzero(theirs > thr))
    assert np.all(theirs[ours == 0] < ZERO_RTOL * theirs.max())


# -- agreement with CVXPY ------------------------------------------------------------------------
@pytest.mark.parametrize("background", [None, BACKGROUND], ids=["estimated-bg", "fixed-bg"])
@pytest.mark.parametrize("seed", range(N_RANDOM))
def test_penalized_matches_cvxpy(A, seed, background):
    y, _ = _window(A, seed)
    rng = np.random.default_rng(1000 + seed)
    b0 = y.mean() if background is None else background
    lam = float(np.max(A.T @ (y - b0))) * rng.uniform(0.01, 0.3)
    res = solve_penalized(A, y, lam, background=background)
    assert res.converged
    x_cvx, b_cvx, obj_cvx = _cvx_solve(A, y, background, lam=lam)
    assert res.objective == pytest.approx(obj_cvx, rel=1e-4)
    assert res.objective <= obj_cvx * (1 + 1e-9)  # exact: never worse than the interior point
    _assert_same_support(res.coef, x_cvx)
    np.testing.assert_allclose(res.coef, x_cvx, atol=1e-3 * x_cvx.max())
    assert res.background == pytest.approx(b_cvx, rel=1e-4, abs=1e-4)
    _assert_kkt(A, y, res, lam, background)
    r = y - A @ res.coef - res.background
    assert res.residual_norm == pytest.approx(np.linalg.norm(r), rel=1e-12)


@pytest.mark.parametrize("background", [None, BACKGROUND], ids=["estimated-bg", "fixed-bg"])
@pytest.mark.parametrize("seed", range(N_RANDOM))
def test_constrained_matches_cvxpy(A, seed, background):
    y, _ = _window(A, seed)
    # the Poisson-noise bound, raised where it is below the NNLS residual (fixed background, a
    # few % of windows): those are infeasible and tested separately
    eps = max(noise_epsilon(y), 1.05 * _nnls_residual(A, y, background))
    res = solve_constrained(A, y, eps, background=background)
    assert res.converged and res.feasible
    assert np.any(res.coef > 0)
    assert res.residual_norm == pytest.approx(eps, rel=1e-6)  # the constraint is active
    x_cvx, b_cvx, obj_cvx = _cvx_solve(A, y, background, eps=eps)
    assert res.objective == pytest.approx(obj_cvx, rel=1e-4)
    assert res.objective == pytest.approx(res.coef.sum(), rel=1e-12)
    _assert_same_support(res.coef, x_cvx)
    np.testing.assert_allclose(res.coef, x_cvx, atol=1e-3 * x_cvx.max())
    assert res.background == pytest.approx(b_cvx, rel=1e-4, abs=1e-4)
    # the constrained solution is the penalised one at the lam found (KKT there)
    _assert_kkt(A, y, res, res.lam, background)
    pen = solve_penalized(A, y, res.lam, background=background)
    np.testing.assert_allclose(pen.coef, res.coef, atol=1e-6 * res.coef.max())


def test_per_atom_penalty_and_weights_match_cvxpy(A):
    y, _ = _window(A, 123)
    rng = np.random.default_rng(5)
    lam = float(np.max(A.T @ (y - y.mean()))) * 0.05 * rng.uniform(0.5, 2.0, A.shape[1])
    res = solve_penalized(A, y, lam)
    x_cvx, _, obj_cvx = _cvx_solve(A, y, None, lam=lam)
    assert res.objective == pytest.approx(obj_cvx, rel=1e-6)
    _assert_same_support(res.coef, x_cvx)
    _assert_kkt(A, y, res, lam, None)
    assert isinstance(res.lam, np.ndarray) and res.lam.shape == (A.shape[1],)
    # constrained with weights: min sum(w x) == sum(x') over the column-rescaled dictionary A/w
    w = rng.uniform(0.5, 2.0, A.shape[1])
    eps = noise_epsilon(y)
    res_w = solve_constrained(A, y, eps, weights=w)
    res_s = solve_constrained(A / w, y, eps)
    assert res_w.objective == pytest.approx(res_s.objective, rel=1e-8)
    np.testing.assert_allclose(res_w.coef * w, res_s.coef, atol=1e-6 * res_s.coef.max())
    _assert_kkt(A, y, res_w, res_w.lam * w, None)


def test_degenerate_dictionary(A):
    """Duplicated and scaled columns make faces singular; the optimum is still exact."""
    y, x_true = _window(A, 7)
    idx = np.flatnonzero(x_true)
    A2 = np.hstack([A, A[:, idx], 2.0 * A[:, idx], 0.5 * (A[:, [0]] + A[:, [1]])])
    lam = float(np.max(A2.T @ (y - y.mean()))) * 0.05
    x0 = np.zeros(A2.shape[1])
    x0[idx] = 1.0
    x0[A.shape[1] :] = 1.0  # warm start on a singular face
    for start in (None, x0):
        res = solve_penalized(A2, y, lam, x0=start)
        assert res.converged
        _assert_kkt(A2, y, res, lam, None)
        _, _, obj_cvx = _cvx_solve(A2, y, None, lam=lam)
        assert res.objective == pytest.approx(obj_cvx, rel=1e-6)
    res = solve_constrained(A2, y, noise_epsilon(y))
    assert res.converged
    assert res.residual_norm == pytest.approx(noise_epsilon(y), rel=1e-6)
    _assert_kkt(A2, y, res, res.lam, None)


# -- properties of the active-set solver ---------------------------------------------------------
def test_nnls_limit_matches_scipy(A):
    for background in (None, BACKGROUND):
        y, _ = _window(A, 11)
        res = solve_penalized(A, y, 0.0, background=background)
        assert res.converged
        assert res.residual_norm == pytest.approx(_nnls_residual(A, y, background), rel=1e-8)
        _assert_kkt(A, y, res, 0.0, background)


def test_large_penalty_gives_background_only(A):
    y, _ = _window(A, 3)
    lam_max = float(np.max(A.T @ (y - y.mean())))
    res = solve_penalized(A, y, lam_max * 1.001)
    assert res.support.size == 0
    assert res.background == pytest.approx(y.mean(), rel=1e-12)
    assert res.objective == pytest.approx(0.5 * np.sum((y - y.mean()) ** 2), rel=1e-12)
    res = solve_penalized(A, y, lam_max * 0.99)
    assert res.support.size > 0


def test_residual_non_decreasing_in_lam(A):
    y, _ = _window(A, 21)
    lam_max = float(np.max(A.T @ (y - y.mean())))
    norms, prev = [], None
    for lam in lam_max * np.geomspace(1e-4, 1.0, 25):
        prev = solve_penalized(A, y, lam, x0=None if prev is None else prev.coef)
        assert prev.converged
        norms.append(prev.residual_norm)
    assert np.all(np.diff(norms) >= -1e-9 * norms[-1])


def test_warm_start_same_answer_fewer_iterations(A):
    y, _ = _window(A, 5)
    lam = float(np.max(A.T @ (y - y.mean()))) * 0.05
    cold = solve_penalized(A, y, lam)
    warm = solve_penalized(A, y, lam * 1.01, x0=cold.coef)
    ref = solve_penalized(A, y, lam * 1.01)
    np.testing.assert_allclose(warm.coef, ref.coef, atol=1e-8 * ref.coef.max())
    assert warm.n_iter < ref.n_iter


def test_accepts_dense_dictionary_and_window(dictionary, A):
    y, _ = _window(A, 2)
    mask = np.zeros(dictionary.coef_shape, dtype=bool)
    mask[:, 2:12, 2:12] = True
    sub = dictionary.restrict(mask)
    assert isinstance(sub, DenseDictionary)
    eps = noise_epsilon(y)
    a = solve_constrained(sub, y.reshape(dictionary.shape), eps)
    b = solve_constrained(sub.matrix, y, eps)
    np.testing.assert_array_equal(a.coef, b.coef)
    assert a.coef.shape == (sub.size,)


# -- edge cases ----------------------------------------------------------------------------------
def test_background_alone_fits(A):
    y, _ = _window(A, 4)
    eps = float(np.linalg.norm(y - y.mean())) * 1.01
    res = solve_constrained(A, y, eps)
    assert res.support.size == 0 and res.converged and res.feasible
    assert res.background == pytest.approx(y.mean())
    assert res.objective == 0.0
    assert solve_penalized(A, y, res.lam).support.size == 0  # lam is large enough for x = 0
    fixed = solve_constrained(A, y, 1e9, background=2.0)
    assert fixed.support.size == 0 and fixed.background == 2.0
    assert fixed.residual_norm == pytest.approx(np.linalg.norm(y - 2.0))


def test_infeasible(A, caplog):
    y, _ = _window(A, 9)
    r_nnls = _nnls_residual(A, y, BACKGROUND)
    eps = 0.5 * r_nnls
    with caplog.at_level(logging.INFO, logger="sparseloc.solvers.convex"):
        res = solve_constrained(A, y, eps, background=BACKGROUND)
    assert not res.feasible
    assert "infeasible" in caplog.text
    assert res.residual_norm == pytest.approx(r_nnls, rel=1e-8)
    assert res.lam == 0.0
    _assert_kkt(A, y, res, 0.0, BACKGROUND)
    with pytest.raises(ValueError, match=r"infeasible.*eps"):
        solve_constrained(A, y, eps, background=BACKGROUND, on_infeasible="raise")


def test_zero_window(A):
    m = A.shape[0]
    for eps in (0.0, 1.0):
        res = solve_constrained(A, np.zeros(m), eps)
        assert res.support.size == 0 and res.background == 0.0 and res.feasible
        assert res.residual_norm == 0.0 and res.objective == 0.0
    pen = solve_penalized(A, np.zeros(m), 1.0)
    assert pen.support.size == 0 and pen.background == 0.0 and pen.objective == 0.0
    # a fixed background above an empty window cannot be fitted with x >= 0
    res = solve_constrained(A, np.zeros(m), 1.0, background=2.0)
    assert not res.feasible and res.support.size == 0
    assert res.residual_norm == pytest.approx(2.0 * np.sqrt(m))
    with pytest.raises(ValueError, match="infeasible"):
        solve_constrained(A, np.zeros(m), 1.0, background=2.0, on_infeasible="raise")


def test_noise_free_exact_fit(A):
    y, x_true = _window(A, 13, noise=False)
    res = solve_constrained(A, y, 0.0, background=BACKGROUND)
    assert res.feasible
    assert res.residual_norm <= 1e-6
    assert res.objective <= x_true.sum() * (1 + 1e-8)  # the truth is feasible
    tiny = solve_constrained(A, y, 1e-3)
    assert tiny.converged and tiny.residual_norm == pytest.approx(1e-3, rel=1e-6)
    assert tiny.objective <= x_true.sum() * (1 + 1e-6)


def test_noise_epsilon():
    assert noise_epsilon(np.full((3, 3), 4.0)) == pytest.approx(6.0)
    assert noise_epsilon(np.zeros(16)) == pytest.approx(4.0)  # floored at 1 photon per pixel
    assert noise_epsilon(np.full(9, 4.0), factor=2.0) == pytest.approx(12.0)
    with pytest.raises(ValueError, match="factor"):
        noise_epsilon(np.ones(4), factor=-1.0)
    with pytest.raises(ValueError, match="y"):
        noise_epsilon([1.0, np.nan])


# -- input validation ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"A": np.ones(5)}, "A must"),
        ({"A": np.full((4, 3), np.nan)}, "A contains"),
        ({"y": np.ones(5)}, "y has 5"),
        ({"y": np.array([1.0, np.nan, 1.0, 1.0])}, "y contains"),
        ({"background": np.nan}, "background"),
        ({"tol": 0.0}, "tol"),
        ({"max_iter": 0}, "max_iter"),
    ],
)
def test_bad_common_input(kwargs, match):
    base = {"A": np.abs(np.random.default_rng(0).normal(size=(4, 3))), "y": np.ones(4)}
    args = {**base, **kwargs}
    A, y = args.pop("A"), args.pop("y")
    with pytest.raises(ValueError, match=match):
        solve_penalized(A, y, 1.0, **args)
    with pytest.raises(ValueError, match=match):
        solve_constrained(A, y, 1.0, **args)


def test_bad_specific_input():
    A = np.abs(np.random.default_rng(0).normal(size=(4, 3)))
    y = np.ones(4)
    for lam in (-1.0, np.inf, np.ones(2), -np.ones(3), "a"):
        with pytest.raises(ValueError, match="lam"):
            solve_penalized(A, y, lam)
    with pytest.raises(ValueError, match="x0"):
        solve_penalized(A, y, 1.0, x0=np.ones(2))
    for eps in (-1.0, np.nan, None):
        with pytest.raises(ValueError, match="eps"):
            solve_constrained(A, y, eps)
    for w in (np.ones(2), np.zeros(3), np.array([1.0, np.inf, 1.0])):
        with pytest.raises(ValueError, match="weights"):
            solve_constrained(A, y, 1.0, weights=w)
    with pytest.raises(ValueError, match="on_infeasible"):
        solve_constrained(A, y, 1.0, on_infeasible="ignore")


# -- working set ---------------------------------------------------------------------------------
@pytest.fixture
def tiny_working_set(monkeypatch):
    """A working set that starts with 4 atoms and grows by 2: many rounds, infeasible ones too."""
    import sparseloc.solvers.convex as convex

    monkeypatch.setattr(convex, "WORKING_SET_SIZE", 4)
    monkeypatch.setattr(convex, "WORKING_SET_GROW", 2)


def _assert_same_result(ws: ConvexResult, full: ConvexResult) -> None:
    assert ws.feasible == full.feasible and ws.converged == full.converged
    assert ws.objective == pytest.approx(full.objective, rel=1e-9, abs=1e-9)
    assert ws.residual_norm == pytest.approx(full.residual_norm, rel=1e-9)
    assert ws.background == pytest.approx(full.background, rel=1e-9, abs=1e-9)
    assert ws.lam == pytest.approx(full.lam, rel=1e-6, abs=1e-12)
    scale = max(float(full.coef.max()), 1.0)
    np.testing.assert_allclose(ws.coef, full.coef, atol=1e-6 * scale)
    # nothing the solution needs is screened out: every atom of the full solution is in it
    assert set(np.flatnonzero(full.coef > 1e-6 * scale)) <= set(ws.support.tolist())


@pytest.mark.parametrize("background", [None, BACKGROUND], ids=["estimated-bg", "fixed-bg"])
@pytest.mark.parametrize("seed", range(10))
def test_working_set_same_as_full(A, seed, background, tiny_working_set):
    y, _ = _window(A, seed)
    eps = noise_epsilon(y)  # with a fixed background some of these windows are infeasible
    full = solve_constrained(A, y, eps, background=background, working_set=False)
    ws = solve_constrained(A, y, eps, background=background, working_set=True)
    _assert_same_result(ws, full)
    _assert_kkt(A, y, ws, ws.lam, background)  # over every atom, not only the working set


@pytest.mark.parametrize("seed", range(3))
def test_working_set_matches_cvxpy(A, seed, tiny_working_set):
    y, _ = _window(A, 100 + seed)
    eps = max(noise_epsilon(y), 1.05 * _nnls_residual(A, y, None))
    res = solve_constrained(A, y, eps, working_set=True)
    assert res.converged and res.feasible
    x_cvx, b_cvx, obj_cvx = _cvx_solve(A, y, None, eps=eps)
    assert res.objective == pytest.approx(obj_cvx, rel=1e-4)
    _assert_same_support(res.coef, x_cvx)
    assert res.background == pytest.approx(b_cvx, rel=1e-4, abs=1e-4)


def test_working_set_edge_cases(A, tiny_working_set):
    y, _ = _window(A, 9)
    # infeasible (fixed background, eps below the NNLS residual): the same NNLS fit
    eps = 0.5 * _nnls_residual(A, y, BACKGROUND)
    full = solve_constrained(A, y, eps, background=BACKGROUND, working_set=False)
    ws = solve_constrained(A, y, eps, background=BACKGROUND, working_set=True)
    assert not ws.feasible
    _assert_same_result(ws, full)
    _assert_kkt(A, y, ws, 0.0, BACKGROUND)
    # the background alone fits
    eps = float(np.linalg.norm(y - y.mean())) * 1.01
    assert solve_constrained(A, y, eps, working_set=True).support.size == 0
    # weights
    w = np.random.default_rng(3).uniform(0.5, 2.0, A.shape[1])
    eps = noise_epsilon(y)
    full = solve_constrained(A, y, eps, weights=w, working_set=False)
    ws = solve_constrained(A, y, eps, weights=w, working_set=True)
    _assert_same_result(ws, full)
    _assert_kkt(A, y, ws, ws.lam * w, None)
    # a dictionary with one atom (the working set is the whole of it at once)
    j = int(np.argmax(A.T @ (y - y.mean())))
    one = A[:, [j]]
    _assert_same_result(
        solve_constrained(one, y, eps, working_set=True),
        solve_constrained(one, y, eps, working_set=False),
    )


def test_working_set_by_default_on_large_dictionaries(dh_model):
    """Above ``WORKING_SET_MIN_ATOMS`` the default path is the working set; same answer."""
    import sparseloc.solvers.convex as convex

    big = Dictionary(dh_model, 7, 160.0, 40.0, 150.0, (-300, 300)).dense()  # 3920 atoms
    assert big.shape[1] > convex.WORKING_SET_MIN_ATOMS
    for seed in range(3):
        y, _ = _window(big, 200 + seed)
        eps = noise_epsilon(y)
        auto = solve_constrained(big, y, eps)
        _assert_same_result(auto, solve_constrained(big, y, eps, working_set=False))
        _assert_kkt(big, y, auto, auto.lam, None)


def test_matrix_check_fast_path():
    """Huge finite entries (their sum overflows) pass; NaN and inf anywhere are refused."""
    from sparseloc.solvers.convex import _check_matrix

    huge = np.full((4, 3), 1e308)
    assert _check_matrix(huge) is not None  # no ValueError though the sum is inf
    y = np.ones(4)
    for bad in (np.inf, -np.inf, np.nan):
        A = np.ones((4, 3))
        A[2, 1] = bad
        with pytest.raises(ValueError, match="A contains"):
            solve_constrained(A, y, 1.0)
