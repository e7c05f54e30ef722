"""Tests of the analytic PSF models (astigmatic Gaussian, two-lobe double helix)."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.psf import PSFModel
from sparseloc.psf.analytic import GaussianAstigPSF, TwoLobeDHPSF

PIXEL = 100.0  # nm


def _models():
    return [GaussianAstigPSF(), TwoLobeDHPSF()]


MODEL_IDS = ["astig", "dh"]


def _moments(img: np.ndarray, pixel: float) -> tuple[float, float, float, float, float]:
    """Centroid (x, y) and central second moments (xx, yy, xy) in nm of one image."""
    rows, cols = img.shape
    xc = (np.arange(cols) + 0.5) * pixel
    yc = (np.arange(rows) + 0.5) * pixel
    tot = img.sum()
    mx = (img.sum(axis=0) @ xc) / tot
    my = (img.sum(axis=1) @ yc) / tot
    dx = xc[None, :] - mx
    dy = yc[:, None] - my
    mxx = (img * dx**2).sum() / tot
    myy = (img * dy**2).sum() / tot
    mxy = (img * dx * dy).sum() / tot
    return mx, my, mxx, myy, mxy


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_is_psf_model(model):
    assert isinstance(model, PSFModel)
    lo, hi = model.z_range
    assert lo < hi
    assert isinstance(model.name, str)


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_derivatives_match_finite_differences(model):
    shape = (15, 17)
    lo, hi = model.z_range
    h = 1e-3  # nm
    x = np.array([823.4, 911.7])
    y = np.array([731.9, 688.2])
    for zf in (0.1, 0.37, 0.5, 0.81):
        z0 = lo + zf * (hi - lo)
        z = np.array([z0, z0 - 0.05 * (hi - lo)])
        img, der = model.images(x, y, z, shape, PIXEL, derivatives=True)
        assert img.shape == (2, *shape)
        assert der.shape == (2, 3, *shape)
        np.testing.assert_allclose(img, model.images(x, y, z, shape, PIXEL), rtol=0, atol=0)
        for i in range(3):
            step = np.zeros((3, 2))
            step[i] = h
            plus = model.images(x + step[0], y + step[1], z + step[2], shape, PIXEL)
            minus = model.images(x - step[0], y - step[1], z - step[2], shape, PIXEL)
            fd = (plus - minus) / (2 * h)
            an = der[:, i]
            assert np.max(np.abs(an)) > 0
            assert np.max(np.abs(an - fd)) <= 1e-4 * np.max(np.abs(an)), (i, z0)


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_gradients_scale_and_photon_column(model):
    shape = (12, 12)
    x = np.array([512.0, 633.3])
    y = np.array([604.1, 555.5])
    z = np.array([0.0, 200.0])
    photons = np.array([1000.0, 2500.0])
    img, der = model.images(x, y, z, shape, PIXEL, derivatives=True)
    grad = model.gradients(x, y, z, photons, shape, PIXEL)
    assert grad.shape == (2, 4, *shape)
    np.testing.assert_allclose(grad[:, 3], img, rtol=0, atol=0)
    np.testing.assert_allclose(grad[:, :3], der * photons[:, None, None, None], rtol=1e-14)
    rendered = model.render(x, y, z, photons, shape, PIXEL)
    np.testing.assert_allclose(rendered, np.tensordot(photons, img, axes=(0, 0)), rtol=1e-14)


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_unit_sum_over_large_window(model):
    n = 101
    centre = n * PIXEL / 2
    zs = np.linspace(*model.z_range, 5)
    imgs = model.images(np.full(5, centre), np.full(5, centre + 13.0), zs, (n, n), PIXEL)
    np.testing.assert_allclose(imgs.sum(axis=(1, 2)), 1.0, atol=1e-3)
    assert np.all(imgs >= 0)


def test_astig_widths_from_image_moments():
    model = GaussianAstigPSF()
    px = 20.0
    n = 200  # 4 um window: > 6 sigma either side at |z| <= 400 nm
    centre = n * px / 2
    zs = np.array([-400.0, 0.0, 400.0])
    imgs = model.images(np.full(3, centre), np.full(3, centre), zs, (n, n), px)
    widths = []
    for img in imgs:
        mx, my, mxx, myy, mxy = _moments(img, px)
        assert abs(mx - centre) < 1e-6 and abs(my - centre) < 1e-6
        assert abs(mxy) < 1e-6 * mxx
        # Sheppard's correction for pixel integration.
        widths.append((np.sqrt(mxx - px**2 / 12), np.sqrt(myy - px**2 / 12)))
    (sxm, sym), (sx0, sy0), (sxp, syp) = widths
    assert abs(sx0 - sy0) <= 0.01 * sx0
    assert (sxp - syp) * (sxm - sym) < 0
    assert abs(sxp - syp) > 0.2 * sx0 and abs(sxm - sym) > 0.2 * sx0
    # The measured widths agree with the width curves.
    fx, fy = model.sigma(zs)
    np.testing.assert_allclose([w[0] for w in widths], fx, rtol=1e-3)
    np.testing.assert_allclose([w[1] for w in widths], fy, rtol=1e-3)


def test_dh_lobe_axis_turns_and_midpoint_stays():
    model = TwoLobeDHPSF()
    px = 50.0
    n = 80  # 4 um window
    centre = n * px / 2
    zs = np.linspace(*model.z_range, 41)
    imgs = model.images(np.full(41, centre), np.full(41, centre), zs, (n, n), px)
    angles = []
    for img in imgs:
        mx, my, mxx, myy, mxy = _moments(img, px)
        assert np.hypot(mx - centre, my - centre) < 20.0
        angles.append(0.5 * np.arctan2(2 * mxy, mxx - myy))
    # The axis is defined modulo pi: unwrap the doubled angle.
    theta = 0.5 * np.unwrap(2 * np.asarray(angles))
    steps = np.diff(theta)
    assert np.all(steps > 0) or np.all(steps < 0)
    assert abs(theta[-1] - theta[0]) >= np.deg2rad(150)
    # The measured axis follows theta(z) (modulo pi).
    diff = np.angle(np.exp(2j * (theta - model.theta(zs)))) / 2
    assert np.max(np.abs(diff)) < np.deg2rad(1.0)


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_exact_shift_invariance(model):
    shape = (14, 16)
    x = np.array([700.3, 811.1])
    y = np.array([650.7, 733.9])
    z = np.array([-150.0, 275.0])
    photons = np.array([1.0, 2.0])
    d = 37.25
    a = model.render(x + d, y + d, z, photons, shape, PIXEL, origin=(0.0, 0.0))
    b = model.render(x, y, z, photons, shape, PIXEL, origin=(-d, -d))
    assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(a))
    ga = model.gradients(x + d, y + d, z, photons, shape, PIXEL)
    gb = model.gradients(x, y, z, photons, shape, PIXEL, origin=(-d, -d))
    assert np.max(np.abs(ga - gb)) <= 1e-10 * np.max(np.abs(ga))


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_pixel_integration_is_additive(model):
    rows, cols = 12, 14
    x = np.array([633.3, 801.2])
    y = np.array([577.7, 612.4])
    z = np.array([100.0, -320.0])
    origin = (-25.0, 40.0)
    coarse, dcoarse = model.images(x, y, z, (rows, cols), PIXEL, origin=origin, derivatives=True)
    fine, dfine = model.images(
        x, y, z, (3 * rows, 3 * cols), PIXEL / 3, origin=origin, derivatives=True
    )
    binned = fine.reshape(2, rows, 3, cols, 3).sum(axis=(2, 4))
    assert np.max(np.abs(binned - coarse)) <= 1e-10 * np.max(coarse)
    dbinned = dfine.reshape(2, 3, rows, 3, cols, 3).sum(axis=(3, 5))
    assert np.max(np.abs(dbinned - dcoarse)) <= 1e-10 * np.max(np.abs(dcoarse))


def test_far_tail_keeps_relative_precision():
    # Far from the peak the pixel value must stay positive and match the Gaussian tail.
    model = GaussianAstigPSF()
    img = model.images(50.0, 50.0, 250.0, (1, 40), PIXEL)  # sigma_x = sigma0 at z = c
    assert np.all(img > 0)
    ratio = img[0, 1:] / img[0, :-1]
    assert np.all(np.diff(ratio) < 0)  # log-concave all the way out


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_bad_inputs_raise(model):
    lo, hi = model.z_range
    with pytest.raises(ValueError, match="pixel_size"):
        model.images(500.0, 500.0, 0.0, (10, 10), 0.0)
    with pytest.raises(ValueError, match="pixel_size"):
        model.images(500.0, 500.0, 0.0, (10, 10), -100.0)
    with pytest.raises(ValueError, match="outside"):
        model.images(500.0, 500.0, hi + 1.0, (10, 10), PIXEL)
    with pytest.raises(ValueError, match="outside"):
        model.render(500.0, 500.0, lo - 1.0, 100.0, (10, 10), PIXEL)
    with pytest.raises(ValueError, match="photons"):
        model.render(500.0, 500.0, 0.0, -1.0, (10, 10), PIXEL)
    with pytest.raises(ValueError, match="photons"):
        model.gradients(500.0, 500.0, 0.0, -1.0, (10, 10), PIXEL)
    with pytest.raises(ValueError, match="shape"):
        model.images(500.0, 500.0, 0.0, (0, 10), PIXEL)


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [
        ({"sigma0": 0.0}, "sigma0"),
        ({"sigma0": -5.0}, "sigma0"),
        ({"sigma0": np.nan}, "sigma0"),
        ({"d": 0.0}, "d must"),
        ({"c": np.inf}, "c must"),
        ({"A": np.nan}, "A must"),
        ({"B": -1.0}, "sigma_"),  # 1 + t^2 - t^4 goes negative within the z range
        ({"z_range": (600.0, -600.0)}, "z_range"),
        ({"z_range": (0.0, 0.0)}, "z_range"),
        ({"z_range": (0.0,)}, "z_range"),
    ],
)
def test_astig_bad_constructor(kwargs, word):
    with pytest.raises(ValueError, match=word):
        GaussianAstigPSF(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "word"),
    [
        ({"lobe_sigma": 0.0}, "lobe_sigma"),
        ({"lobe_sigma": -1.0}, "lobe_sigma"),
        ({"separation": -10.0}, "separation"),
        ({"separation": np.inf}, "separation"),
        ({"rotation": np.nan}, "rotation"),
        ({"theta0": np.inf}, "theta0"),
        ({"z_range": (1000.0, -1000.0)}, "z_range"),
        ({"z_range": (-np.inf, 0.0)}, "z_range"),
    ],
)
def test_dh_bad_constructor(kwargs, word):
    with pytest.raises(ValueError, match=word):
        TwoLobeDHPSF(**kwargs)


def test_astig_custom_coefficients_are_used():
    model = GaussianAstigPSF(sigma0=100.0, c=200.0, d=300.0, A=0.1, B=0.02)
    sx, sy = model.sigma(np.array([200.0, -200.0]))
    np.testing.assert_allclose([sx[0], sy[1]], 100.0)
    t = 400.0 / 300.0
    np.testing.assert_allclose(sy[0], 100.0 * np.sqrt(1 + t**2 + 0.1 * t**3 + 0.02 * t**4))


def test_dh_vectorised_matches_single():
    model = TwoLobeDHPSF(rotation=-0.8 * np.pi, theta0=0.3)
    x = np.array([400.0, 1210.5, 888.8])
    y = np.array([900.0, 420.2, 777.7])
    z = np.array([-900.0, 10.0, 640.0])
    img, der = model.images(x, y, z, (20, 22), PIXEL, derivatives=True)
    for k in range(3):
        i1, d1 = model.images(x[k], y[k], z[k], (20, 22), PIXEL, derivatives=True)
        np.testing.assert_array_equal(i1[0], img[k])
        np.testing.assert_array_equal(d1[0], der[k])


@pytest.mark.parametrize("model", _models(), ids=MODEL_IDS)
def test_support_radius_is_reasonable(model):
    r = model.support_radius(PIXEL)
    assert 200.0 < r < 2000.0
