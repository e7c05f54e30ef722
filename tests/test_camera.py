"""Camera noise models: moments of to_photons(apply_noise(mu)) and parameter validation."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.camera import Camera, apply_noise, noise_variance, to_photons


def test_ideal_camera_is_poisson():
    rng = np.random.default_rng(0)
    mu = np.full((200, 32, 32), 20.0)
    cam = Camera(offset=100.0, gain=1.0)
    adu = apply_noise(mu, cam, rng)
    assert adu.dtype == np.uint16 and adu.shape == mu.shape
    ph = to_photons(adu, cam)
    assert ph.dtype == np.float64
    assert abs(ph.mean() / 20.0 - 1) < 0.01
    assert abs(ph.var() / 20.0 - 1) < 0.03
    np.testing.assert_allclose(noise_variance(mu, cam), 20.0)


def test_qe_and_gain_convert_back_to_photons():
    rng = np.random.default_rng(1)
    mu = np.full((100, 32, 32), 200.0)
    cam = Camera(offset=400.0, gain=0.5, qe=0.8)
    ph = to_photons(apply_noise(mu, cam, rng), cam)
    assert abs(ph.mean() / 200.0 - 1) < 0.01
    # detected electrons are Poisson(qe mu): the variance in photons is mu / qe
    assert abs(ph.var() / (200.0 / 0.8) - 1) < 0.04
    np.testing.assert_allclose(noise_variance(mu, cam), 250.0)


@pytest.mark.parametrize("mu_value", [5.0, 50.0])
def test_emccd_excess_noise_factor_two(mu_value):
    rng = np.random.default_rng(2)
    mu = np.full((400, 32, 32), mu_value)
    cam = Camera(kind="emccd", offset=100.0, gain=10.0, em_gain=100.0, read_noise=20.0)
    ph = to_photons(apply_noise(mu, cam, rng), cam)
    assert abs(ph.mean() / mu_value - 1) < 0.01
    var = ph.var()
    assert abs(var / (2 * mu_value) - 1) < 0.03  # read noise adds only (20/100)^2 = 0.04
    np.testing.assert_allclose(noise_variance(mu, cam), 2 * mu_value + 0.04)
    assert abs(var / noise_variance(mu_value, cam) - 1) < 0.03


def test_scmos_per_pixel_read_noise_gain_and_offset():
    rng = np.random.default_rng(3)
    shape = (8, 8)
    var_map = np.linspace(1.0, 60.0, 64).reshape(shape)  # ADU^2, strongly varying
    gain_map = np.linspace(0.5, 2.0, 64).reshape(shape)[::-1]  # e-/ADU
    offset_map = np.linspace(90.0, 120.0, 64).reshape(shape).T
    cam = Camera(kind="scmos", offset_map=offset_map, variance_map=var_map, gain_map=gain_map)
    mu = np.full((6000, *shape), 10.0)
    ph = to_photons(apply_noise(mu, cam, rng), cam)
    expected_var = noise_variance(mu[0], cam)
    np.testing.assert_allclose(expected_var, 10.0 + var_map * gain_map**2)
    np.testing.assert_allclose(ph.mean(axis=0), 10.0, atol=0.7)
    ratio = ph.var(axis=0) / expected_var
    assert abs(ratio.mean() - 1) < 0.02
    assert np.all(np.abs(ratio - 1) < 0.15)


def test_scmos_scalar_read_noise():
    rng = np.random.default_rng(4)
    cam = Camera(kind="scmos", read_noise=3.0, gain=2.0)
    mu = np.full((300, 32, 32), 15.0)
    ph = to_photons(apply_noise(mu, cam, rng), cam)
    # + rounding to whole ADU: gain^2 / 12 e-^2
    assert abs(ph.var() / (15.0 + 9.0 + 4.0 / 12) - 1) < 0.03
    np.testing.assert_allclose(noise_variance(mu, cam), 24.0)


def test_apply_noise_is_reproducible_and_clipped():
    mu = np.random.default_rng(5).uniform(0, 100, size=(3, 16, 16))
    cam = Camera()
    a = apply_noise(mu, cam, np.random.default_rng(7))
    b = apply_noise(mu, cam, np.random.default_rng(7))
    assert np.array_equal(a, b)
    big = apply_noise(np.full((4, 4), 1e6), cam, np.random.default_rng(0))
    assert big.dtype == np.uint16 and np.all(big == 65535)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"kind": "ccd"}, "kind"),
        ({"gain": 0.0}, "gain"),
        ({"gain": float("nan")}, "gain"),
        ({"offset": -1.0}, "offset"),
        ({"qe": 1.5}, "qe"),
        ({"qe": 0.0}, "qe"),
        ({"kind": "emccd", "em_gain": 0.5}, "em_gain"),
        ({"kind": "ideal", "em_gain": 100.0}, "em_gain"),
        ({"kind": "ideal", "read_noise": 1.0}, "read_noise"),
        ({"kind": "scmos", "read_noise": -1.0}, "read_noise"),
        ({"kind": "emccd", "gain_map": np.ones((4, 4))}, "gain_map"),
        ({"kind": "scmos", "variance_map": -np.ones((4, 4))}, "variance_map"),
        ({"kind": "scmos", "gain_map": np.zeros((4, 4))}, "gain_map"),
        ({"kind": "scmos", "offset_map": np.ones(4)}, "offset_map"),
        ({"kind": "scmos", "offset_map": np.ones((4, 4)), "gain_map": np.ones((4, 5))}, "shape"),
        ({"kind": "scmos", "read_noise": 1.0, "variance_map": np.ones((4, 4))}, "variance_map"),
    ],
)
def test_camera_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        Camera(**kwargs)


def test_kind_error_lists_allowed_values():
    with pytest.raises(ValueError, match=r"ideal.*emccd.*scmos"):
        Camera(kind="CMOS")


def test_scmos_maps_must_match_image():
    cam = Camera(kind="scmos", variance_map=np.ones((4, 4)))
    with pytest.raises(ValueError, match="does not match"):
        apply_noise(np.ones((2, 5, 4)), cam, np.random.default_rng(0))
    with pytest.raises(ValueError, match="does not match"):
        to_photons(np.ones((5, 4)), cam)


def test_camera_is_frozen_and_compares_maps():
    a = Camera(kind="scmos", variance_map=np.ones((2, 2)))
    b = Camera(kind="scmos", variance_map=np.ones((2, 2)))
    c = Camera(kind="scmos", variance_map=2 * np.ones((2, 2)))
    assert a == b and hash(a) == hash(b)
    assert a != c
    with pytest.raises(AttributeError):
        a.gain = 2.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        a.variance_map[0, 0] = 5.0  # read-only copy


def test_apply_noise_rejects_bad_input():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=">= 0"):
        apply_noise(-np.ones((4, 4)), Camera(), rng)
    with pytest.raises(ValueError, match="finite"):
        apply_noise(np.full((4, 4), np.nan), Camera(), rng)
    with pytest.raises(ValueError, match="rows, cols"):
        apply_noise(np.ones(4), Camera(), rng)
