"""Physics of the pupil model: shape over z, normalisation, exactness, gradients, masks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from sparseloc.psf import PSFModel, PupilPSF, load_mask, make_psf
from sparseloc.psf.masks import ArrayMask


def lobe_pair(img: np.ndarray, px: float) -> tuple[float, np.ndarray]:
    """Angle (deg, mod 180) of the line through the two brightest lobes, and their midpoint (nm)."""
    sm = ndi.gaussian_filter(img, 1.0)
    peaks = np.argwhere((ndi.maximum_filter(sm, 5) == sm) & (sm > 0.2 * sm.max()))
    order = np.argsort(sm[tuple(peaks.T)])[::-1][:2]
    pts = []
    for r, c in peaks[order]:
        sl = (slice(r - 3, r + 4), slice(c - 3, c + 4))
        w = img[sl]
        rr, cc = np.mgrid[sl]
        pts.append((((cc + 0.5) * w).sum() / w.sum() * px, ((rr + 0.5) * w).sum() / w.sum() * px))
    pts = np.array(pts)
    d = pts[1] - pts[0]
    return float(np.degrees(np.arctan2(d[1], d[0])) % 180.0), pts.mean(axis=0)


def test_models_satisfy_protocol(dh_model, astig_model):
    assert isinstance(dh_model, PSFModel)
    assert isinstance(astig_model, PSFModel)


def test_double_helix_rotates_about_fixed_midpoint(dh_model):
    px, n = 20.0, 161
    zs = np.linspace(*dh_model.z_range, 21)
    x0, y0 = n * px / 2 + 3.0, n * px / 2 - 7.0
    imgs = dh_model.images(np.full(21, x0), np.full(21, y0), zs, (n, n), px)
    res = [lobe_pair(im, px) for im in imgs]
    ang = np.degrees(np.unwrap(np.radians([a for a, _ in res]) * 2) / 2)
    steps = np.diff(ang)
    assert np.all(steps > 0) or np.all(steps < 0), f"lobe axis not monotonic: {ang}"
    assert abs(ang[-1] - ang[0]) >= 150.0
    mids = np.array([m for _, m in res])
    assert np.max(np.hypot(mids[:, 0] - x0, mids[:, 1] - y0)) < 20.0


def test_astigmatic_widths_cross_at_focus(astig_model):
    px, n = 20.0, 121
    zs = np.array([-300.0, 0.0, 300.0])
    imgs = astig_model.images(np.full(3, n * px / 2), np.full(3, n * px / 2), zs, (n, n), px)

    def widths(img):
        c = (np.arange(n) + 0.5) * px
        px_, py_ = img.sum(0), img.sum(1)
        mx, my = (px_ * c).sum() / px_.sum(), (py_ * c).sum() / py_.sum()
        # second moments of the central part (tails of a pupil PSF decay too slowly for raw moments)
        core = img > 0.05 * img.max()
        yy, xx = np.nonzero(core)
        w = img[core]
        sx = np.sqrt((w * ((xx + 0.5) * px - mx) ** 2).sum() / w.sum())
        sy = np.sqrt((w * ((yy + 0.5) * px - my) ** 2).sum() / w.sum())
        return sx, sy

    (sxm, sym), (sx0, sy0), (sxp, syp) = (widths(im) for im in imgs)
    assert abs(sx0 - sy0) / sx0 < 0.01
    assert sxm > 1.3 * sym and syp > 1.3 * sxp


def test_clear_pupil_fwhm_matches_diffraction():
    model = PupilPSF(na=1.4, wavelength=600.0)
    n, px = 101, 10.0
    img = model.images(n * px / 2, n * px / 2, 0.0, (n, n), px)[0]
    row = img[n // 2]
    above = np.nonzero(row > row.max() / 2)[0]
    fwhm = (above[-1] - above[0] + 1) * px
    assert abs(fwhm - 0.51 * 600 / 1.4) / (0.51 * 600 / 1.4) < 0.1


@pytest.mark.parametrize("name", ["dh", "astig", "clear"])
def test_image_sums_to_photons_over_large_window(name):
    # A pupil PSF's tails fall as 1/r^3, so the energy outside radius R falls as 1/R: a 20 um
    # window holds all but ~1 %; 10 um windows hold 97.6 % (dh) to 98.3 % (clear).
    model = make_psf(name)
    n, px = 201, 100.0
    img = model.render(n * px / 2, n * px / 2, 0.0, 1000.0, (n, n), px)
    assert abs(img.sum() - 1000.0) / 1000.0 < 0.02


def test_normalisation_over_one_period_is_exact(dh_model):
    # Over exactly one period of the sampled pupil's field the model integrates to 1 photon.
    n = 64
    px = dh_model.field_size / n
    centre = dh_model.field_size / 2
    img = dh_model.render(centre + 13.0, centre - 41.0, 250.0, 1.0, (n, n), px)
    assert abs(img.sum() - 1.0) < 1e-9


def test_exact_subpixel_shift_invariance(dh_model):
    shape, px = (17, 17), 160.0
    x, y, z = 1300.0, 1350.0, 240.0
    d = (37.3, -61.9)
    shifted = dh_model.render(x + d[0], y + d[1], z, 1.0, shape, px)
    on_shifted_grid = dh_model.render(x, y, z, 1.0, shape, px, origin=(-d[0], -d[1]))
    assert np.max(np.abs(shifted - on_shifted_grid)) <= 1e-6 * shifted.max()
    # a whole-pixel shift equals moving the array
    moved = dh_model.render(x + 2 * px, y - px, z, 1.0, shape, px)
    base = dh_model.render(x, y, z, 1.0, shape, px)
    assert np.allclose(moved[2:-1, 2:-2], base[3:, :-4], rtol=0, atol=1e-9 * base.max())


def test_pixel_integration_is_exact(dh_model):
    # The integral over a pixel equals the sum of the integrals over its 3x3 sub-pixels.
    px, n, s = 160.0, 11, 3
    x, y, z = 870.0, 905.0, -310.0
    coarse = dh_model.render(x, y, z, 1.0, (n, n), px)
    fine = dh_model.render(x, y, z, 1.0, (n * s, n * s), px / s)
    binned = fine.reshape(n, s, n, s).sum(axis=(1, 3))
    assert np.max(np.abs(binned - coarse)) <= 1e-9 * coarse.max()
    # and differs from a point-sampled (not integrated) model by much more than that
    sampled = dh_model.render(x, y, z, 1.0, (n * 15, n * 15), px / 15)[7::15, 7::15] * 225
    assert np.max(np.abs(sampled - coarse)) > 1e-3 * coarse.max()


@pytest.mark.parametrize("name", ["dh", "astig"])
def test_gradients_match_finite_differences(name):
    model = make_psf(name)
    shape, px = (13, 15), 110.0
    x = np.array([700.0, 905.3])
    y = np.array([640.2, 800.9])
    z = np.array([-350.0, 420.0])
    n = np.array([1000.0, 2500.0])
    g = model.gradients(x, y, z, n, shape, px)
    steps = {0: 1e-2, 1: 1e-2, 2: 5e-2}
    for k in range(2):
        for p, h in steps.items():
            plus = [x.copy(), y.copy(), z.copy()]
            minus = [x.copy(), y.copy(), z.copy()]
            plus[p][k] += h
            minus[p][k] -= h
            fd = (model.render(*plus, n, shape, px) - model.render(*minus, n, shape, px)) / (2 * h)
            an = g[k, p]
            assert np.max(np.abs(an - fd)) <= 1e-4 * np.max(np.abs(an)), (k, p)
        assert np.allclose(g[k, 3], model.images(x, y, z, shape, px)[k])


def test_retrieved_dh_mask_loads_and_renders(shared_data):
    model = make_psf(
        shared_data / "dhpsfu_masks" / "Microscope1_mask_wasmask.mat",
        na=1.15,
        wavelength=670.0,
        z_range=(-1500.0, 1500.0),
    )
    px, n = 108.6, 41
    imgs = model.images(
        np.full(5, n * px / 2), np.full(5, n * px / 2), np.linspace(-1500, 1500, 5), (n, n), px
    )
    assert np.all(np.isfinite(imgs))
    assert np.all(imgs.sum(axis=(1, 2)) > 0.5)
    # it is a rotating two-lobe PSF: the lobe axis turns across the range
    angles = [lobe_pair(im, px)[0] for im in imgs]
    assert np.ptp(np.unwrap(np.radians(angles) * 2)) / 2 > np.radians(60)


def test_tetrapod_mask_loads_and_renders(shared_data):
    model = make_psf(
        shared_data / "deepstorm3d" / "Mat_Files_mask_tetrapod_printed.mat",
        na=1.45,
        wavelength=670.0,
        z_range=(-2000.0, 2000.0),
    )
    imgs = model.images([2255.0] * 3, [2255.0] * 3, [-2000.0, 0.0, 2000.0], (41, 41), 110.0)
    assert np.all(np.isfinite(imgs)) and np.all(imgs >= -1e-12)
    # different depths give clearly different images
    a, b = imgs[0] / np.linalg.norm(imgs[0]), imgs[2] / np.linalg.norm(imgs[2])
    assert float((a * b).sum()) < 0.8


def test_array_mask_reproduces_analytic_mask():
    from sparseloc.psf import AstigmatismMask

    n = 129
    c = np.arange(n) - (n - 1) / 2
    xx, yy = np.meshgrid(c / 60.0, c / 60.0)
    rho, phi = np.hypot(xx, yy), np.arctan2(yy, xx)
    analytic = AstigmatismMask(0.2)
    arr = np.where(rho <= 1, analytic(rho, phi), 0.0)
    from_array = PupilPSF(ArrayMask(arr, centre=((n - 1) / 2, (n - 1) / 2), radius=60.0))
    direct = PupilPSF(analytic)
    a = from_array.render(900, 900, 300, 1.0, (15, 15), 120.0)
    b = direct.render(900, 900, 300, 1.0, (15, 15), 120.0)
    assert np.max(np.abs(a - b)) < 0.02 * b.max()


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda m: m.render(0, 0, 0, 1, (5, 5), 0.0), "pixel_size"),
        (lambda m: m.render(0, 0, 0, 1, (5, 5), -3.0), "pixel_size"),
        (lambda m: m.render(0, 0, 5000.0, 1, (5, 5), 100.0), "z = 5000"),
        (lambda m: m.render(0, 0, 0, -1.0, (5, 5), 100.0), "photons"),
        (lambda m: m.render(np.nan, 0, 0, 1.0, (5, 5), 100.0), "x must be finite"),
    ],
)
def test_bad_input_names_the_argument(dh_model, call, match):
    with pytest.raises(ValueError, match=match):
        call(dh_model)


def test_unknown_psf_name_lists_allowed():
    with pytest.raises(ValueError, match=r"unknown PSF 'helix'.*dh, astig"):
        make_psf("helix")


def test_mask_file_must_be_2d(tmp_path):
    path = tmp_path / "mask.npy"
    np.save(path, np.zeros((4, 5, 6)))
    with pytest.raises(ValueError, match="must be 2-D"):
        load_mask(path)
    with pytest.raises(ValueError, match="does not exist"):
        load_mask(tmp_path / "missing.mat")


def test_sample_index_equal_to_immersion_changes_nothing():
    x = np.array([1100.0])
    plain = PupilPSF(None)
    same = PupilPSF(None, n_sample=1.518, focal_depth=1200.0)
    for z in (-600.0, 0.0, 700.0):
        a = plain.images(x, x, [z], (21, 21), 100.0)
        b = same.images(x, x, [z], (21, 21), 100.0)
        assert np.allclose(a, b, rtol=0, atol=1e-12 * a.max())


def test_water_sample_moves_the_focus_towards_the_coverslip():
    """An oil objective focused 2 um into water: the sharpest image lies at a depth of about
    n_water / n_oil of the nominal one (paraxial focal shift 0.88; high angles give less),
    i.e. at z < 0, and its derivative in z still matches finite differences."""
    water = PupilPSF(None, n_sample=1.33, focal_depth=2000.0, z_range=(-2000.0, 1000.0))
    x = np.array([1100.0])
    zs = np.arange(-900.0, 301.0, 50.0)
    peaks = [water.images(x, x, [z], (21, 21), 100.0).max() for z in zs]
    z_best = zs[int(np.argmax(peaks))]
    assert -700.0 <= z_best <= -150.0
    _img, der = water.images(x, x, [-200.0], (21, 21), 100.0, derivatives=True)
    hi = water.images(x, x, [-199.5], (21, 21), 100.0)
    lo = water.images(x, x, [-200.5], (21, 21), 100.0)
    fd = (hi - lo)[0] / 1.0
    assert np.max(np.abs(der[0, 2] - fd)) < 1e-3 * np.max(np.abs(fd))


def test_emitters_below_the_coverslip_are_refused():
    with pytest.raises(ValueError, match="coverslip"):
        PupilPSF(None, n_sample=1.33, focal_depth=500.0, z_range=(-1000.0, 1000.0))
    with pytest.raises(ValueError, match="n_sample"):
        PupilPSF(None, n_sample=0.0)


def test_tabulation_never_renders_below_the_coverslip():
    from sparseloc.psf.spline import SplinePSF

    water = PupilPSF(None, n_sample=1.33, focal_depth=500.0, z_range=(-500.0, 500.0))
    assert water.renders_beyond_range(np.array([-520.0, -490.0])).tolist() == [False, True]
    table = SplinePSF.from_model(water, 100.0, roi=15, z_step=10.0)
    assert table.z.min() == -500.0 and table.z.max() == 530.0  # 3 extra planes above only
