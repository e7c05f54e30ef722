"""The structured dictionary against a dense reference rendered atom by atom."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from sparseloc.dictionary import DenseDictionary, Dictionary, dictionary_memory
from sparseloc.psf import make_psf


@pytest.fixture(scope="module")
def small(dh_model):
    return Dictionary(
        dh_model, 7, 160.0, 40.0, 100.0, (-300.0, 300.0), margin=1, origin=(30.0, -50.0)
    )


@pytest.fixture(scope="module")
def reference(dh_model, small):
    idx = np.arange(small.size)
    return DenseDictionary.from_model(
        dh_model, small.positions(idx), small.shape, 160.0, origin=small.origin
    )


def test_dense_path_matches_direct_rendering(small, reference):
    assert small.size == 7 * 4 * 9 * 4 * 9  # 7 planes, (7 + 2) px * 4 phases per axis
    dense = small.dense()
    assert np.max(np.abs(dense - reference.matrix)) <= 1e-6 * reference.matrix.max()
    assert np.allclose(small.norms.ravel(), reference.norms, rtol=1e-6)


def test_operators_match_dense_reference(small, reference):
    rng = np.random.default_rng(0)
    img = rng.normal(size=small.shape)
    coef = rng.normal(size=small.coef_shape)
    a = small.rmatvec(img).ravel()
    b = reference.matrix.T @ img.ravel()
    assert np.max(np.abs(a - b)) <= 1e-6 * np.max(np.abs(b))
    a = small.matvec(coef).ravel()
    b = reference.matrix @ coef.ravel()
    assert np.max(np.abs(a - b)) <= 1e-6 * np.max(np.abs(b))
    # batched correlation equals one window at a time
    batch = small.rmatvec(np.stack([img, 2 * img]))
    assert np.allclose(batch[1], 2 * small.rmatvec(img))


def test_dot_test_proves_the_adjoint(small):
    rng = np.random.default_rng(1)
    for _ in range(5):
        img = rng.normal(size=small.shape)
        coef = rng.normal(size=small.coef_shape)
        lhs = float(np.sum(small.matvec(coef) * img))
        rhs = float(np.sum(small.rmatvec(img) * coef))
        assert abs(lhs - rhs) <= 1e-10 * max(abs(lhs), 1.0)


def test_grid_positions_follow_conventions(small):
    # atom 0 sits half a grid step inside the corner of the margin
    x, y, z = small.positions([0])[0]
    assert (x, y, z) == pytest.approx((30.0 - 160.0 + 20.0, -50.0 - 160.0 + 20.0, -300.0))
    # an atom's image peaks where the model says it should
    k = np.ravel_multi_index((3, 16, 12), small.coef_shape)
    pos = small.positions([k])[0]
    direct = small.model.images(*pos, small.shape, 160.0, origin=small.origin)[0]
    assert np.allclose(small.atoms([k])[0], direct, atol=1e-12)


def test_restriction_to_boxes(small):
    centres = np.array([[300.0, 300.0, 0.0]])
    mask = small.box_mask(centres, (80.0, 80.0, 100.0))
    sub = small.restrict(mask)
    pos = sub.atom_positions
    assert sub.size == mask.sum() > 0
    assert np.all(np.abs(pos[:, 0] - 300) <= 80) and np.all(np.abs(pos[:, 2]) <= 100)
    img = np.random.default_rng(2).normal(size=small.shape)
    assert np.allclose(sub.rmatvec(img), small.rmatvec(img).ravel()[sub.index])


def test_paper_fine_dictionary_fits_in_2gb(dh_model):
    tracemalloc.start()
    d = Dictionary(dh_model, 11, 160.0, 10.0, 15.0, (-300.0, 300.0))
    corr = d.rmatvec(np.ones((11, 11)))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert d.size == 1_270_016
    assert corr.shape == (41, 176, 176)
    assert peak < 2 * 1024**3
    assert dictionary_memory(11, 160.0, 10.0, 15.0, (-300.0, 300.0)) < 2 * 1024**3


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dxy": 30.0}, "whole number"),
        ({"dz": 0.0}, "dz must be > 0"),
        ({"z_range": (-3000.0, 0.0)}, "outside the model's valid range"),
        ({"shape": 3}, "smaller than the PSF"),
        ({"max_memory": 10_000}, "needs .* GB, more than max_memory"),
    ],
)
def test_bad_dictionary_arguments(dh_model, kwargs, match):
    args = {"shape": 7, "pixel_size": 160.0, "dxy": 80.0, "dz": 150.0, "z_range": (-300, 300)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Dictionary(dh_model, **args)


def test_bad_windows(small):
    with pytest.raises(ValueError, match="2-D image"):
        small.rmatvec(np.zeros(49))
    with pytest.raises(ValueError, match="expects"):
        small.rmatvec(np.zeros((9, 9)))
    bad = np.zeros(small.shape)
    bad[2, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        small.rmatvec(bad)


def test_works_with_analytic_models():
    model = make_psf("astig-gauss")
    d = Dictionary(model, 9, 100.0, 50.0, 100.0, (-300.0, 300.0))
    ref = DenseDictionary.from_model(model, d.positions(np.arange(d.size)), d.shape, 100.0)
    assert np.max(np.abs(d.dense() - ref.matrix)) <= 1e-9
