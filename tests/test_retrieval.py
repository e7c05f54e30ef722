"""Phase retrieval: recover injected Zernike aberrations and the bead position from bead stacks."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.psf import DoubleHelixMask, PupilPSF, ZernikeMask
from sparseloc.psf.masks import combine
from sparseloc.psf.retrieval import _StackModel, fit_pupil, zernike_terms

NA, WAVELENGTH, N_IMM = 1.45, 670.0, 1.518
PX, ROI = 100.0, (21, 21)
X_TRUE, Y_TRUE, Z_TRUE = 1050.0 + 23.0, 1050.0 - 37.0, 35.0  # sub-pixel offsets from the centre
PHOTONS, BACKGROUND = 20000.0, 10.0
Z_STAGE = np.linspace(-600.0, 600.0, 31)


def simulate(truth, base=None, seed=7):
    """Poisson bead stack (31, 21, 21) of a pupil with Zernike ``truth`` on top of ``base``."""
    zmask = ZernikeMask(truth)
    mask = zmask if base is None else combine([base, zmask])
    # The default (finer) pupil sampling of PupilPSF, unlike the fit's 64 samples.
    sim = PupilPSF(mask, na=NA, wavelength=WAVELENGTH, n_immersion=N_IMM)
    n = Z_STAGE.size
    img = sim.images(np.full(n, X_TRUE), np.full(n, Y_TRUE), Z_STAGE + Z_TRUE, ROI, PX)
    rng = np.random.default_rng(seed)
    return rng.poisson(PHOTONS * img + BACKGROUND).astype(np.float64)


def fit(stack, z, **kw):
    return fit_pupil(stack, z, PX, na=NA, wavelength=WAVELENGTH, n_immersion=N_IMM, **kw)


def assert_recovered(res, truth, tol=0.02, order=6):
    assert set(res.coefficients) == set(zernike_terms(order))
    for key, value in res.coefficients.items():
        assert abs(value - truth.get(key, 0.0)) < tol, (key, value, truth.get(key, 0.0))


def test_terms_exclude_piston_tilt_defocus():
    terms = zernike_terms(6)
    assert len(terms) == 24
    assert (2, 0) not in terms and all(n >= 2 for n, _ in terms)
    assert zernike_terms(2) == [(2, -2), (2, 2)]


def test_forward_model_and_derivatives_match_pupil_psf():
    terms = zernike_terms(4)
    coef = np.random.default_rng(0).normal(0.0, 0.05, len(terms))
    base = DoubleHelixMask(0.33)
    model = _StackModel(PupilPSF(base, pupil_samples=48), terms, (15, 17), PX)
    ref = PupilPSF(
        combine([base, ZernikeMask(dict(zip(terms, coef, strict=True)))]), pupil_samples=48
    )
    z = np.array([-400.0, 0.0, 250.0])
    x0, y0 = 820.0, 760.0
    img = model.images(coef, x0, y0, z)
    expected = ref.images(np.full(3, x0), np.full(3, y0), z, (15, 17), PX)
    np.testing.assert_allclose(img, expected, rtol=0, atol=1e-12 * expected.max())
    img2, der = model.jacobian(coef, x0, y0, z)
    np.testing.assert_allclose(img2, img, rtol=0, atol=1e-15)
    h = 1e-5
    for j in (0, 3, len(terms) - 1):
        dc = np.zeros_like(coef)
        dc[j] = h
        fd = (model.images(coef + dc, x0, y0, z) - model.images(coef - dc, x0, y0, z)) / (2 * h)
        np.testing.assert_allclose(der[..., j], fd, rtol=0, atol=1e-4 * np.abs(fd).max())
    hx = 1e-3
    fd = (model.images(coef, x0 + hx, y0, z) - model.images(coef, x0 - hx, y0, z)) / (2 * hx)
    np.testing.assert_allclose(der[..., len(terms)], fd, rtol=0, atol=1e-5 * np.abs(fd).max())
    fd = (model.images(coef, x0, y0, z + hx) - model.images(coef, x0, y0, z - hx)) / (2 * hx)
    np.testing.assert_allclose(der[..., len(terms) + 2], fd, rtol=0, atol=1e-4 * np.abs(fd).max())


@pytest.fixture(scope="module")
def astig_fit():
    truth = {(2, 2): 0.1, (3, 1): 0.06, (4, 0): 0.05}
    stack = simulate(truth)
    return truth, stack, fit(stack, Z_STAGE, base_mask=None)


def test_astigmatic_stack_recovers_aberrations_and_position(astig_fit):
    truth, stack, res = astig_fit
    assert res.converged
    assert_recovered(res, truth)
    assert abs(res.x0 - X_TRUE) < 10.0
    assert abs(res.y0 - Y_TRUE) < 10.0
    assert abs(res.z0 - Z_TRUE) < 20.0
    np.testing.assert_allclose(res.photons, PHOTONS, rtol=0.05)
    np.testing.assert_allclose(res.background, BACKGROUND, atol=2.0)
    # The residual is at the shot-noise level: ||sqrt(mu)|| / ||data||.
    noise = np.sqrt(stack.sum()) / np.linalg.norm(stack)
    assert res.residual_rms < 1.1 * noise


def test_fitted_psf_reproduces_the_stack(astig_fit):
    _, stack, res = astig_fit
    n = Z_STAGE.size
    psf = res.psf
    assert isinstance(psf, PupilPSF)
    assert psf.z_range == pytest.approx((Z_STAGE.min() + res.z0, Z_STAGE.max() + res.z0))
    img = psf.images(np.full(n, res.x0), np.full(n, res.y0), Z_STAGE + res.z0, ROI, PX)
    model = img * res.photons[:, None, None] + res.background[:, None, None]
    rel = np.linalg.norm(stack - model) / np.linalg.norm(stack)
    assert rel == pytest.approx(res.residual_rms, rel=1e-6)


def test_double_helix_stack_recovers_aberrations():
    base = DoubleHelixMask(0.33)
    truth = {(3, 1): 0.1, (4, 0): 0.1}
    stack = simulate(truth, base=base, seed=11)
    res = fit(stack, Z_STAGE, base_mask=base, z_range=(-800.0, 800.0))
    assert res.converged
    assert_recovered(res, truth)
    assert abs(res.x0 - X_TRUE) < 10.0
    assert abs(res.y0 - Y_TRUE) < 10.0
    assert abs(res.z0 - Z_TRUE) < 20.0
    assert res.psf.z_range == (-800.0, 800.0)


def test_reversed_z_axis_gives_the_mirrored_pupil():
    """The documented ambiguity: a stack with z reversed fits -phi(-k) (even m flip sign)."""
    truth = {(2, 2): 0.1, (3, 1): 0.06, (4, 0): 0.05}
    res = fit(simulate(truth), -Z_STAGE)
    mirrored = {(n, m): (-a if m % 2 == 0 else a) for (n, m), a in truth.items()}
    assert_recovered(res, mirrored)
    assert abs(res.z0 + Z_TRUE) < 20.0


@pytest.mark.slow
def test_strong_aberrations_are_recovered():
    rng = np.random.default_rng(3)
    truth = {k: float(rng.normal(0.0, 0.035)) for k in zernike_terms(6)}
    truth[(2, 2)] = 0.15
    res = fit(simulate(truth, seed=0), Z_STAGE)
    assert_recovered(res, truth, tol=0.01)


@pytest.mark.parametrize(
    ("stack", "z", "pixel_size", "match"),
    [
        (np.ones((5, 9)), np.arange(5.0), 100.0, "3-D"),
        (np.ones((2, 9, 9)), np.arange(2.0), 100.0, "at least 3 planes"),
        (np.ones((5, 9, 9)), np.arange(4.0), 100.0, "one stage position per plane"),
        (np.ones((5, 9, 9)), np.arange(5.0), 0.0, "pixel_size"),
        (np.ones((5, 9, 9)), np.arange(5.0), -100.0, "pixel_size"),
        (np.full((5, 9, 9), np.nan), np.arange(5.0), 100.0, "finite"),
        (np.ones((5, 9, 9)), np.array([0.0, 1.0, np.nan, 3.0, 4.0]), 100.0, "finite"),
        (np.ones((5, 9, 9)), np.zeros(5), 100.0, "different stage positions"),
        (np.zeros((5, 9, 9)), np.arange(5.0), 100.0, "no signal"),
    ],
)
def test_bad_input_raises(stack, z, pixel_size, match):
    with pytest.raises(ValueError, match=match):
        fit_pupil(stack, z, pixel_size, na=NA, wavelength=WAVELENGTH)


def test_bad_options_raise():
    stack, z = np.ones((5, 9, 9)), np.arange(5.0) * 100.0
    kw = {"na": NA, "wavelength": WAVELENGTH}
    with pytest.raises(ValueError, match="weights"):
        fit_pupil(stack, z, PX, weights="gaussian", **kw)
    with pytest.raises(ValueError, match="max_order"):
        fit_pupil(stack, z, PX, max_order=1, **kw)
    with pytest.raises(ValueError, match="not fitted"):
        fit_pupil(stack, z, PX, initial={(2, 0): 0.1}, **kw)
    with pytest.raises(ValueError, match="z_range"):
        fit_pupil(stack, z, PX, z_range=(100.0, -100.0), **kw)
    with pytest.raises(ValueError, match="na"):
        fit_pupil(stack, z, PX, na=1.6, wavelength=WAVELENGTH)
    with pytest.raises(ValueError, match="ROI"):
        fit_pupil(np.ones((5, 90, 90)), z, PX, pupil_samples=16, **kw)


def test_normalised_stack_uniform_weights_and_initial():
    """Weights are scale-free; a low-order fit from a given start works on normalised data."""
    truth = {(2, 2): 0.1, (3, 1): 0.06}
    stack = simulate(truth, seed=3)
    keep = slice(None, None, 3)  # 11 planes
    z = Z_STAGE[keep]
    norm = stack[keep] / stack.max()
    kw = {"max_order": 4, "initial": {(2, 2): 0.05}}
    res = fit(norm, z, weights="uniform", **kw)
    assert_recovered(res, truth, order=4)
    assert abs(res.z0 - Z_TRUE) < 20.0
    np.testing.assert_allclose(res.photons, PHOTONS / stack.max(), rtol=0.05)
    scaled = fit(stack[keep], z, weights="poisson", **kw)
    again = fit(norm, z, weights="poisson", **kw)
    for key, value in scaled.coefficients.items():
        assert again.coefficients[key] == pytest.approx(value, abs=1e-4)
