"""Matching pursuit: recovery, the stopping rule and grouping."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.dictionary import Dictionary
from sparseloc.solvers import group_coefficients, matching_pursuit

PX, W = 160.0, 11


@pytest.fixture(scope="module")
def coarse(dh_model):
    return Dictionary(dh_model, W, PX, 80.0, 120.0, (-300.0, 300.0))


@pytest.fixture(scope="module")
def medium(dh_model):
    return Dictionary(dh_model, W, PX, 20.0, 30.0, (-300.0, 300.0))


def window(model, pos, photons, background=5.0, seed=0):
    pos = np.atleast_2d(pos)
    mu = model.render(pos[:, 0], pos[:, 1], pos[:, 2], photons, (W, W), PX) + background
    return np.random.default_rng(seed).poisson(mu).astype(float)


@pytest.mark.parametrize("orthogonal", [False, True])
def test_single_emitter_on_grid_is_found(dh_model, medium, orthogonal):
    k = np.ravel_multi_index((12, 44, 40), medium.coef_shape)
    pos = medium.positions([k])[0]
    y = window(dh_model, pos, 3000.0, seed=1)
    sol = matching_pursuit(y, medium, orthogonal=orthogonal)
    assert len(sol.emitters) == 1
    est = sol.emitters.as_array()[0]
    assert np.hypot(est[0] - pos[0], est[1] - pos[1]) < 25.0
    assert abs(est[2] - pos[2]) < 45.0
    assert abs(est[3] - 3000.0) < 300.0
    assert abs(sol.background - 5.0) < 1.0
    assert sol.details["stop"] in ("noise", "min_photons")


def test_noise_only_window_gives_nothing(coarse):
    y = np.random.default_rng(3).poisson(8.0, (W, W)).astype(float)
    sol = matching_pursuit(y, coarse)
    assert len(sol.emitters) == 0
    assert abs(sol.background - 8.0) < 1.5


def test_two_separated_emitters(dh_model, coarse):
    pos = np.array([[500.0, 600.0, -150.0], [1250.0, 1150.0, 200.0]])
    y = window(dh_model, pos, [2500.0, 2500.0], seed=4)
    sol = matching_pursuit(y, coarse, orthogonal=True)
    est = sol.emitters.as_array()
    # both are found near the truth, and they are the two brightest estimates (a coarse grid
    # may add a dim atom for the mismatch; the hybrid's convex stage removes it)
    for p in pos:
        d = np.linalg.norm(est[:2, :3] - p, axis=1).min()
        assert d < np.linalg.norm([80.0, 80.0, 120.0])  # one coarse grid step
    assert np.all(est[2:, 3] < 0.5 * est[:2, 3].min())


def test_max_emitters_caps_the_count(dh_model, coarse):
    pos = np.array([[400.0, 500.0, 0.0], [1300.0, 1200.0, 100.0], [500.0, 1300.0, -200.0]])
    y = window(dh_model, pos, [3000.0] * 3, seed=5)
    sol = matching_pursuit(y, coarse, orthogonal=True, max_emitters=1)
    assert len(sol.emitters) == 1
    assert sol.details["stop"] == "max_emitters"


def test_known_background_is_used(dh_model, coarse):
    y = window(dh_model, [880.0, 880.0, 0.0], 2000.0, background=20.0, seed=6)
    sol = matching_pursuit(y, coarse, background=20.0)
    assert sol.background == 20.0
    brightest = sol.emitters.as_array()[0]
    assert np.hypot(brightest[0] - 880.0, brightest[1] - 880.0) < 80.0
    assert abs(brightest[3] - 2000.0) < 200.0


def test_grouping_merges_neighbours_only():
    pos = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 15], [500, 0, 0], [510, 0, 15.0]])
    coef = np.array([100, 300, 100, 50, 150.0])
    em = group_coefficients(pos, coef, (10.0, 15.0))
    assert len(em) == 2
    assert em.photons.tolist() == [500.0, 200.0]
    assert em.x[0] == pytest.approx((0 * 100 + 10 * 300 + 10 * 100) / 500)
    assert em.z[1] == pytest.approx(15 * 150 / 200)
    assert len(group_coefficients(pos, coef, (10.0, 15.0), min_photons=300)) == 1


def test_bad_input(coarse):
    with pytest.raises(ValueError, match="2-D image"):
        matching_pursuit(np.zeros(121), coarse)
    with pytest.raises(ValueError, match="max_emitters"):
        matching_pursuit(np.zeros((W, W)), coarse, max_emitters=0)
