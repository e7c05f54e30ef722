"""Fast matching pursuit: the certified argmax and MP selections equal the dense reference's."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.dictionary import DenseDictionary, Dictionary
from sparseloc.solvers import group_coefficients, matching_pursuit, matching_pursuit_batch
from sparseloc.solvers.fast_mp import AtomSearch, ReferenceSearch, count_groups, get_search

PX, W = 160.0, 9


@pytest.fixture(scope="module")
def small(dh_model):
    """57,024 atoms: 20 nm / 30 nm grid, 11 planes, 9 x 9 px window."""
    return Dictionary(dh_model, W, PX, 20.0, 30.0, (-150.0, 150.0))


@pytest.fixture(scope="module")
def dense(small):
    return DenseDictionary(
        small.dense(),
        small.positions(np.arange(small.size)),
        small.shape,
        steps=(small.grid.dxy, small.grid.dz),
    )


@pytest.fixture(scope="module")
def search(small):
    return get_search(small)


def fig2_windows(model, n, seed, window=W, pixel=PX, volume=(500.0, 500.0, 300.0)):
    """Windows like the paper's Figure 2: three emitters of 1000-1200 photons, background 5."""
    rng = np.random.default_rng(seed)
    centre = np.array([window * pixel / 2, window * pixel / 2, 0.0])
    out = []
    for _ in range(n):
        pos = centre + rng.uniform(-0.5, 0.5, (3, 3)) * np.asarray(volume)
        ph = rng.uniform(1000.0, 1200.0, 3)
        mu = model.render(pos[:, 0], pos[:, 1], pos[:, 2], ph, (window, window), pixel) + 5.0
        out.append(rng.poisson(mu).astype(float))
    return np.stack(out)


def random_residuals(d, n, seed):
    """Noise, atoms with noise, negative and mean-shifted residuals."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, d.size, (n, 2))
    atoms = d.atoms(k.ravel()).reshape(n, 2, -1)
    amp = rng.uniform(0.0, 1500.0, (n, 2, 1))
    r = (amp * atoms).sum(axis=1) + rng.normal(0.0, 3.0, (n, atoms.shape[-1]))
    r[: n // 8] *= -1.0
    r[n // 8 : n // 4] += rng.uniform(-20.0, 20.0, (n // 4 - n // 8, 1))
    return r.reshape(n, *d.shape)


def same_selection(a, b):
    return (
        np.array_equal(a.details["index"], b.details["index"])
        and a.details["stop"] == b.details["stop"]
        and a.details["n_iter"] == b.details["n_iter"]
    )


def test_atoms_norms_and_sums_are_the_dense_ones(small, dense, search):
    k = np.array([0, 17, 4321, 30000, small.size - 1])
    np.testing.assert_array_equal(search.atoms(k), small.atoms(k).reshape(k.size, -1))
    ref = ReferenceSearch(dense)
    np.testing.assert_array_equal(search.sums, ref.sums)
    np.testing.assert_array_equal(search.inv, ref.inv)


@pytest.mark.parametrize("fit_background", [True, False])
def test_best_atom_is_the_dense_argmax(small, dense, fit_background):
    s = get_search(small, fit_background=fit_background)
    ref = ReferenceSearch(dense, fit_background=fit_background)
    r = random_residuals(small, 150, seed=1 if fit_background else 2)
    idx, corr, score = s.argmax(r)
    ri, rcorr, rscore = ref.argmax(r)
    np.testing.assert_array_equal(idx, ri)
    np.testing.assert_allclose(score, rscore, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(corr, rcorr, rtol=1e-12, atol=1e-9)


def test_fallback_search_is_still_exact(small, dense):
    """A candidate budget of one cluster and one atom proves almost nothing: the wider round
    and the unbounded search must give the same answers."""
    s = AtomSearch(small, candidates=(1, 1))
    r = random_residuals(small, 60, seed=3)
    idx, _, score = s.best(r)
    ri, _, rscore = ReferenceSearch(dense).argmax(r)
    positive = rscore > 0
    np.testing.assert_allclose(score[positive], rscore[positive], rtol=1e-12)
    assert s.fallback_fraction > 0.5
    np.testing.assert_array_equal(idx[positive], ri[positive])


def test_one_residual_at_a_time_through_the_parents(small, dense):
    """Small batches bound parent clusters first; with and without a candidate budget."""
    r = random_residuals(small, 24, seed=12)
    ri, _, rscore = ReferenceSearch(dense).argmax(r)
    for s in (get_search(small), AtomSearch(small, candidates=(1, 1))):
        assert s.small_batch >= 1
        idx = np.array([s.best(r[i : i + 1])[0][0] for i in range(len(r))])
        np.testing.assert_array_equal(idx[rscore > 0], ri[rscore > 0])


def test_bounds_hold_for_every_atom(small, search):
    """The cluster bound is above every member's exact score; so is each member's bound."""
    r = random_residuals(small, 4, seed=4).reshape(4, -1)
    rc = r - r.mean(axis=1, keepdims=True)
    ub = search._coarse_bounds(r, rc)
    ub_parents = search._coarse_bounds_parents(r, rc)
    n_rc, n_all = np.linalg.norm(rc, axis=1), np.linalg.norm(r, axis=1)
    clusters = np.broadcast_to(np.arange(search.n_clusters), (4, search.n_clusters))
    hi = search._member_upper(rc, n_rc, n_all, clusters).reshape(4, search.n_clusters, -1)
    for b in range(4):
        _, score = search.dense_scores(r[b])
        member = search.member
        exact = np.where(member >= 0, score[np.maximum(member, 0)], -np.inf)
        assert np.all(exact <= hi[b])
        assert np.all(exact.max(axis=1) <= ub[b])
        assert np.all(exact.max(axis=1) <= ub_parents[b])


def test_mp_batch_selects_what_the_dense_reference_selects(dh_model, small, dense):
    ys = fig2_windows(dh_model, 40, seed=5)
    qe = small.quantization_error
    fast = matching_pursuit_batch(ys, small)
    for y, f in zip(ys, fast, strict=True):
        ref = matching_pursuit(y, dense, model_error=qe)
        assert same_selection(f, ref)
        np.testing.assert_allclose(f.details["coef"], ref.details["coef"], rtol=1e-9)
        assert f.background == pytest.approx(ref.background, rel=1e-9, abs=1e-9)
        assert len(f.emitters) == len(ref.emitters)
    stops = {f.details["stop"] for f in fast}
    assert stops - {"max_iter"}, stops


def test_mp_batch_with_known_background_and_omp(dh_model, small, dense):
    ys = fig2_windows(dh_model, 12, seed=6)
    qe = small.quantization_error
    fixed = matching_pursuit_batch(ys[:6], small, background=5.0)
    omp = matching_pursuit_batch(ys[6:], small, orthogonal=True, replace_sweeps=1)
    for y, f in zip(ys[:6], fixed, strict=True):
        assert same_selection(f, matching_pursuit(y, dense, background=5.0, model_error=qe))
    for y, f in zip(ys[6:], omp, strict=True):
        ref = matching_pursuit(y, dense, orthogonal=True, replace_sweeps=1, model_error=qe)
        assert same_selection(f, ref)
        assert f.method == "omp"


def test_single_window_batch_and_reference_search(dh_model, small, dense):
    y = fig2_windows(dh_model, 1, seed=7)[0]
    a = matching_pursuit_batch(y, small)[0]
    b = matching_pursuit_batch(y[None], small)[0]
    c = matching_pursuit_batch(y, dense, model_error=small.quantization_error)[0]
    assert same_selection(a, b)
    assert same_selection(a, c)
    np.testing.assert_allclose(a.model_image, c.model_image, rtol=1e-9, atol=1e-9)


def test_search_is_cached_per_dictionary_and_mode(small, search):
    assert get_search(small) is search
    assert get_search(small, fit_background=False) is not search


def test_count_groups_is_the_number_of_emitters():
    rng = np.random.default_rng(8)
    for _ in range(50):
        n = int(rng.integers(0, 8))
        pos = rng.uniform(0.0, 300.0, (n, 3))
        coef = rng.choice([0.0, 100.0, 500.0], n)
        steps = (10.0, 15.0)
        assert count_groups(pos, coef, steps, link=1.5) == len(
            group_coefficients(pos, coef, steps, link=1.5)
        )


def test_bad_input(small):
    with pytest.raises(ValueError, match="expects"):
        matching_pursuit_batch(np.zeros((2, 5, 5)), small)
    with pytest.raises(TypeError):
        AtomSearch(object())  # type: ignore[arg-type]


def test_torch_path_matches_numpy(dh_model, small, search, torch_device):
    r = random_residuals(small, 80, seed=9)
    a = search.best(r)
    b = search.best(r, device=torch_device)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[2], b[2], rtol=1e-12)
    ys = fig2_windows(dh_model, 10, seed=10)
    for f, g in zip(
        matching_pursuit_batch(ys, small),
        matching_pursuit_batch(ys, small, device=torch_device),
        strict=True,
    ):
        assert same_selection(f, g)


@pytest.mark.slow
def test_paper_fine_dictionary_matches_dense_reference(dh_model):
    """The paper's fine dictionary (1,270,016 atoms, 1.2 GB dense): 12 Figure-2 windows."""
    fine = Dictionary(dh_model, 11, PX, 10.0, 15.0, (-300.0, 300.0))
    dense = DenseDictionary(
        fine.dense(),
        fine.positions(np.arange(fine.size)),
        fine.shape,
        steps=(fine.grid.dxy, fine.grid.dz),
    )
    ys = fig2_windows(dh_model, 12, seed=11, window=11, volume=(800.0, 800.0, 600.0))
    fast = matching_pursuit_batch(ys, fine)
    for y, f in zip(ys, fast, strict=True):
        assert same_selection(f, matching_pursuit(y, dense, model_error=fine.quantization_error))
