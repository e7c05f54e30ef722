"""The measured (spline) PSF against the model its stack was rendered from.

The stacks come from the cheap analytic double helix (``dh-analytic``), rendered with the
emitter at the ROI centre at 20 nm z steps; one test uses the pupil model, sparingly.
"""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.dictionary import Dictionary
from sparseloc.psf import PSFModel, make_psf
from sparseloc.psf.spline import SplinePSF, bspline_weights

PX = 100.0  # nm
ROI = 27  # px: the analytic DH's lobes sit 4.5 px from the centre with a 1.5 px width
Z = np.arange(-600.0, 600.0 + 1e-9, 20.0)  # nm, 61 planes


def render_stack(model, z, shape=(ROI, ROI), centre=None, px=PX):
    """Unit-photon images of one emitter at ``centre`` (row, col; default the ROI centre)."""
    rows, cols = shape
    r, c = ((rows - 1) / 2, (cols - 1) / 2) if centre is None else centre
    n = len(z)
    return model.images(np.full(n, (c + 0.5) * px), np.full(n, (r + 0.5) * px), z, shape, px)


def rel_err(a, b):
    """Largest absolute difference per image, as a fraction of the reference image's peak."""
    return np.abs(a - b).max(axis=(1, 2)) / np.abs(b).max(axis=(1, 2))


@pytest.fixture(scope="module")
def source():
    return make_psf("dh-analytic")


@pytest.fixture(scope="module")
def stack(source):
    return render_stack(source, Z)


@pytest.fixture(scope="module")
def spline(stack):
    return SplinePSF(stack, PX, Z)


def random_emitters(rng, n, window, z_lo=-560.0, z_hi=560.0, spread=150.0):
    """Emitters near the window centre at positions off the stack's pixel and z grid."""
    rows, cols = window
    x = cols * PX / 2 + rng.uniform(-spread, spread, n)
    y = rows * PX / 2 + rng.uniform(-spread, spread, n)
    z = rng.uniform(z_lo, z_hi, n)
    return x, y, z


def test_bspline_weights_partition_unity():
    f = np.linspace(0, 1, 11, endpoint=False)
    w, dw = bspline_weights(f)
    assert np.allclose(w.sum(axis=1), 1.0, atol=1e-14)
    assert np.allclose(dw.sum(axis=1), 0.0, atol=1e-14)
    assert np.allclose(w[0], [1 / 6, 4 / 6, 1 / 6, 0.0])


def test_is_a_psf_model(spline, source):
    assert isinstance(spline, PSFModel)
    assert spline.z_range == (Z[0], Z[-1])
    assert spline.z_step == pytest.approx(20.0)
    assert spline.pixel_size == PX
    assert spline.centre == ((ROI - 1) / 2, (ROI - 1) / 2)
    # every plane of the stored stack sums to one photon
    assert np.allclose(spline.stack.sum(axis=(1, 2)), 1.0)


def test_exact_at_the_stack_samples(spline, stack):
    # Emitter at the ROI centre, z on a node, same window: the interpolant hits the samples.
    n = len(Z)
    imgs = spline.images(np.full(n, ROI * PX / 2), np.full(n, ROI * PX / 2), Z, (ROI, ROI), PX)
    assert np.max(np.abs(imgs - stack / stack.sum(axis=(1, 2), keepdims=True))) < 1e-8


def test_matches_source_model_off_the_nodes(spline, source):
    # Measured: interior max 0.46 % of the peak (lateral interpolation of a pixel-integrated
    # 1.5 px wide lobe; z alone gives 0.07 %); tolerance 1 %.
    rng = np.random.default_rng(0)
    window = (21, 21)
    x, y, z = random_emitters(rng, 100, window)
    err = rel_err(spline.images(x, y, z, window, PX), source.images(x, y, z, window, PX))
    assert err.max() < 0.01, err.max()
    # Over the whole range, end intervals included: the mirror boundary at the first and
    # last plane costs accuracy there (measured 0.92 % at z = -590 nm); tolerance 2 %.
    zz = np.linspace(Z[0], Z[-1], 241)
    c = np.full(zz.size, 21 * PX / 2 + 13.0)
    err = rel_err(spline.images(c, c, zz, window, PX), source.images(c, c, zz, window, PX))
    assert err.max() < 0.02, err.max()


def test_rectangular_stack_window_and_origin(source):
    # Rows and columns of different lengths everywhere: catches a swapped axis.
    stack = render_stack(source, Z, shape=(25, 31))
    sp = SplinePSF(stack, PX, Z)
    rng = np.random.default_rng(1)
    window, origin = (15, 21), (-1234.5, 777.7)
    x, y, z = random_emitters(rng, 40, window)
    x, y = x + origin[0], y + origin[1]
    a = sp.images(x, y, z, window, PX, origin=origin)
    b = source.images(x, y, z, window, PX, origin=origin)
    assert rel_err(a, b).max() < 0.01  # measured 0.45 %
    # Moving the emitters and the window together changes nothing.
    c = sp.images(x - origin[0], y - origin[1], z, window, PX)
    assert np.allclose(a, c, rtol=0, atol=1e-12)


def test_off_centre_stack_with_given_centre(source):
    # The bead sat at (row 12.8, col 13.3) of the ROI, not at its centre.
    centre = (12.8, 13.3)
    sp = SplinePSF(render_stack(source, Z, centre=centre), PX, Z, centre=centre)
    rng = np.random.default_rng(2)
    window = (21, 21)
    x, y, z = random_emitters(rng, 40, window)
    err = rel_err(sp.images(x, y, z, window, PX), source.images(x, y, z, window, PX))
    assert err.max() < 0.01  # measured 0.46 %


def test_derivatives_match_central_differences(spline):
    window = (21, 21)
    x = np.array([1050.0 + 31.7, 1050.0 - 44.2, 1050.0 + 3.1])
    y = np.array([1050.0 - 12.3, 1050.0 + 61.9, 1050.0 - 87.0])
    z = np.array([-211.3, 347.7, 9.9])
    img, der = spline.images(x, y, z, window, PX, derivatives=True)
    assert np.allclose(img, spline.images(x, y, z, window, PX), rtol=0, atol=1e-15)
    h = 1e-3  # nm; measured agreement ~1e-10 of the largest derivative
    for i in range(3):
        step = np.zeros((3, 1))
        step[i] = h
        plus = spline.images(x + step[0], y + step[1], z + step[2], window, PX)
        minus = spline.images(x - step[0], y - step[1], z - step[2], window, PX)
        fd = (plus - minus) / (2 * h)
        scale = np.abs(der[:, i]).max()
        assert scale > 0
        assert np.abs(fd - der[:, i]).max() <= 1e-5 * scale, i
    # gradients(): photons times the derivatives, then the unit image
    photons = np.array([1000.0, 250.0, 4000.0])
    g = spline.gradients(x, y, z, photons, window, PX)
    assert g.shape == (3, 4, *window)
    assert np.allclose(g[:, :3], der * photons[:, None, None, None])
    assert np.allclose(g[:, 3], img)


def test_images_sum_to_one_near_the_roi_centre(spline):
    rng = np.random.default_rng(3)
    window = (41, 41)  # holds the whole 27 px ROI for emitters within 2 px of the centre
    x, y, z = random_emitters(rng, 30, window, z_lo=Z[0], z_hi=Z[-1], spread=200.0)
    sums = spline.images(x, y, z, window, PX).sum(axis=(1, 2))
    assert np.allclose(sums, 1.0, atol=1e-3), sums  # measured 0.99997 .. 1.0000
    img = spline.render(x[:3], y[:3], z[:3], [100.0, 200.0, 300.0], window, PX)
    assert img.sum() == pytest.approx(600.0, rel=1e-3)


def test_far_emitter_leaves_the_window_dark(spline):
    # Indices beyond the ROI must point at zero coefficients, not wrap around.
    img = spline.images([-5000.0, 50000.0, 750.0], [750.0, 750.0, -9000.0], [0, 0, 0], (15, 15), PX)
    assert np.all(img == 0.0)


def test_many_emitters_in_chunks_match_one_by_one(spline):
    # More emitters than one chunk of the evaluation (about 1081 for this ROI).
    rng = np.random.default_rng(4)
    x, y, z = random_emitters(rng, 1200, (9, 9), spread=50.0)
    allk = spline.images(x, y, z, (9, 9), PX)
    sub = np.arange(0, 1200, 97)
    one = np.stack([spline.images(x[i], y[i], z[i], (9, 9), PX)[0] for i in sub])
    assert np.array_equal(allk[sub], one)


def test_support_radius_matches_source(spline, source):
    r = spline.support_radius(PX)
    assert r == pytest.approx(source.support_radius(PX, z_range=spline.z_range), abs=PX)
    assert 450.0 < r < ROI * PX / 2


def test_other_pixel_size_is_refused_naming_both(spline):
    for call in (
        lambda: spline.images([500.0], [500.0], [0.0], (11, 11), 110.0),
        lambda: spline.render([500.0], [500.0], [0.0], [1.0], (11, 11), 110.0),
        lambda: spline.gradients([500.0], [500.0], [0.0], [1.0], (11, 11), 110.0),
        lambda: spline.support_radius(110.0),
    ):
        with pytest.raises(ValueError, match=r"calibrated at 100 nm.*110 nm"):
            call()


@pytest.mark.parametrize("z", [Z[-1] + 1.0, Z[0] - 100.0, np.nan])
def test_z_outside_range_is_refused(spline, z):
    with pytest.raises(ValueError, match=r"outside the model's valid range|finite"):
        spline.images([500.0], [500.0], [z], (11, 11), PX)


def _stack(n=8, size=9):
    rng = np.random.default_rng(5)
    return rng.uniform(0.5, 1.0, (n, size, size))


@pytest.mark.parametrize(
    ("stack", "z", "kwargs", "match"),
    [
        (_stack()[0], np.arange(8.0), {}, "planes, rows, cols"),
        (_stack(n=3), np.arange(3.0), {}, "at least 4 planes"),
        (_stack(size=4), np.arange(8.0), {}, "at least 4 planes of 5x5"),
        (np.where(np.arange(9) == 4, np.nan, _stack()), np.arange(8.0), {}, "NaN"),
        (_stack(), np.array([0, 10, 20, 30, 45, 50, 60, 70.0]), {}, "evenly spaced"),
        (_stack(), np.arange(8.0)[::-1], {}, "must increase"),
        (_stack(), np.arange(7.0), {}, "z has 7 values"),
        (_stack() * (np.arange(8) != 2)[:, None, None], np.arange(8.0), {}, "positive total"),
        (_stack(), np.arange(8.0), {"z_range": (-1.0, 5.0)}, "z_range"),
        (_stack(), np.arange(8.0), {"pixel_size": 0.0}, "pixel_size"),
    ],
)
def test_bad_stacks_are_refused(stack, z, kwargs, match):
    kw = {"pixel_size": PX, **kwargs}
    with pytest.raises(ValueError, match=match):
        SplinePSF(stack, kw.pop("pixel_size"), z, **kw)


def test_content_hash(stack):
    a = SplinePSF(stack, PX, Z)
    h = a.content_hash
    assert len(h) == 16 and int(h, 16) >= 0
    assert SplinePSF(stack.copy(), PX, Z.copy()).content_hash == h  # stable
    changed = stack.copy()
    changed[30, 13, 13] *= 1.001
    assert SplinePSF(changed, PX, Z).content_hash != h
    assert SplinePSF(stack, PX, Z + 1.0).content_hash != h
    assert SplinePSF(stack, 101.0, Z).content_hash != h


def test_dictionary_from_spline_passes_the_dot_test(spline):
    d = Dictionary(spline, 15, PX, 50.0, 100.0, (-300.0, 300.0))
    rng = np.random.default_rng(6)
    for _ in range(3):
        img = rng.normal(size=d.shape)
        coef = rng.normal(size=d.coef_shape)
        lhs = float(np.sum(d.matvec(coef) * img))
        rhs = float(np.sum(d.rmatvec(img) * coef))
        assert abs(lhs - rhs) <= 1e-10 * max(abs(lhs), 1.0)
    # its atoms are the spline's images at the grid positions
    idx = np.array([0, 123, d.size // 2, d.size - 1])
    pos = d.positions(idx)
    ref = spline.images(pos[:, 0], pos[:, 1], pos[:, 2], d.shape, PX)
    assert np.allclose(d.atoms(idx).reshape(ref.shape), ref, rtol=0, atol=1e-12)


def test_spline_of_the_pupil_model(dh_model):
    # The sharper pupil double helix (several ms an image): one short stack, a few probes.
    pupil = dh_model
    z = np.arange(-200.0, 200.0 + 1e-9, 20.0)
    sp = SplinePSF(render_stack(pupil, z, shape=(31, 31)), PX, z, normalise=False)
    rng = np.random.default_rng(7)
    window = (21, 21)
    x, y, zz = random_emitters(rng, 12, window, z_lo=-180.0, z_hi=180.0)
    err = rel_err(sp.images(x, y, zz, window, PX), pupil.images(x, y, zz, window, PX))
    # Measured up to 1.6 % of the peak (a ~1 px wide lobe sampled at 100 nm); tolerance 3 %.
    assert err.max() < 0.03, err.max()


@pytest.mark.parametrize(("oversample", "tol"), [(1, 0.05), (2, 0.004), (3, 0.001)])
def test_table_of_a_model_matches_it(oversample, tol):
    """SplinePSF.from_model: interpolation error shrinks with lateral oversampling (measured
    at 160 nm pixels for the analytic double helix: 3.4 %, 0.12 %, 0.02 % of the peak)."""
    model = make_psf("dh-analytic")
    px, w = 160.0, 11
    table = SplinePSF.from_model(
        model, px, roi=2 * w + 3, z_step=10.0, z_range=(-500.0, 500.0), oversample=oversample
    )
    rng = np.random.default_rng(4)
    x, y = rng.uniform(600, 1100, 25), rng.uniform(600, 1100, 25)
    z = rng.uniform(-490, 490, 25)
    a, da = model.images(x, y, z, (w, w), px, derivatives=True)
    b, db = table.images(x, y, z, (w, w), px, derivatives=True)
    assert np.abs(a - b).max() <= tol * a.max()
    if oversample > 1:
        for i in range(3):
            assert np.abs(da[:, i] - db[:, i]).max() <= 10 * tol * np.abs(da[:, i]).max()
    # photon scale is the model's (no per-plane normalisation)
    np.testing.assert_allclose(b.sum(axis=(1, 2)), a.sum(axis=(1, 2)), rtol=0.01)
    assert abs(table.support_radius(px) - model.support_radius(px)) <= px


def test_oversampled_stack_normalises_to_one_photon():
    model = make_psf("dh-analytic")
    table = SplinePSF.from_model(model, 100.0, roi=31, z_step=20.0, oversample=2)
    again = SplinePSF(table.stack, 100.0, table.z, centre=table.centre, oversample=2)
    img = again.images(1550.0, 1550.0, 0.0, (31, 31), 100.0)
    assert abs(img.sum() - 1.0) < 1e-3
