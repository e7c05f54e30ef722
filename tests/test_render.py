"""Rendering (2D, 3D, colour) and the FRC resolution estimate."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import tifffile

from sparseloc import render as R


def _table(**cols) -> pd.DataFrame:
    n = len(np.atleast_1d(cols["x_nm"]))
    data = {"frame": np.arange(n)}
    data.update({k: np.broadcast_to(np.asarray(v, dtype=float), (n,)) for k, v in cols.items()})
    return pd.DataFrame(data)


def _moments(r: R.Rendered) -> tuple[float, float, float, float, float]:
    """Sum, centroid (h, v) and standard deviations (h, v) of an image, in nm."""
    d = r.density.astype(np.float64)
    h0, _, v0, _ = r.extent
    hc = h0 + (np.arange(d.shape[1]) + 0.5) * r.px_nm
    vc = v0 + (np.arange(d.shape[0]) + 0.5) * r.px_nm
    total = d.sum()
    mh = (d.sum(axis=0) * hc).sum() / total
    mv = (d.sum(axis=1) * vc).sum() / total
    sh = math.sqrt((d.sum(axis=0) * (hc - mh) ** 2).sum() / total)
    sv = math.sqrt((d.sum(axis=1) * (vc - mv) ** 2).sum() / total)
    return total, mh, mv, sh, sv


EXT = (0.0, 2000.0, 0.0, 2000.0)


# -- render_gaussian ---------------------------------------------------------------------------


def test_single_spot_sums_to_one_with_its_own_second_moments():
    t = _table(x_nm=1003.0, y_nm=988.0, z_nm=0.0, sigma_x_nm=30.0, sigma_y_nm=60.0)
    r = R.render_gaussian(t, px_nm=5.0, extent=EXT)
    total, mx, my, sx, sy = _moments(r)
    assert r.density.dtype == np.float32 and r.density.shape == (400, 400)
    assert total == pytest.approx(1.0, abs=1e-4)  # counts localizations, not photons
    assert mx == pytest.approx(1003.0, abs=0.5) and my == pytest.approx(988.0, abs=0.5)
    assert sx**2 == pytest.approx(30.0**2, rel=0.03)
    assert sy**2 == pytest.approx(60.0**2, rel=0.03)


def test_imprecise_spot_is_wider_and_dimmer():
    sharp = R.render_gaussian(
        _table(x_nm=1000.0, y_nm=1000.0, sigma_x_nm=30.0, sigma_y_nm=30.0), px_nm=5.0, extent=EXT
    )
    wide = R.render_gaussian(
        _table(x_nm=1000.0, y_nm=1000.0, sigma_x_nm=100.0, sigma_y_nm=100.0), px_nm=5.0, extent=EXT
    )
    assert wide.density.max() < 0.2 * sharp.density.max()  # (30 / 100)^2 = 0.09 in theory
    assert _moments(wide)[3] == pytest.approx(100.0, rel=0.02)
    assert _moments(wide)[0] == pytest.approx(1.0, abs=1e-3)


def test_default_and_minimum_spot_sizes():
    bare = R.render_gaussian(_table(x_nm=1000.0, y_nm=1000.0), px_nm=2.0, extent=EXT)
    assert _moments(bare)[3] == pytest.approx(15.0, rel=0.03)  # default_sigma_nm
    nan = _table(x_nm=1000.0, y_nm=1000.0, sigma_x_nm=np.nan, sigma_y_nm=-1.0)
    assert _moments(R.render_gaussian(nan, px_nm=2.0, extent=EXT, default_sigma_nm=25.0))[
        3:
    ] == pytest.approx((25.0, 25.0), rel=0.03)
    floored = R.render_gaussian(
        _table(x_nm=1000.0, y_nm=1000.0, sigma_x_nm=5.0, sigma_y_nm=5.0),
        px_nm=2.0,
        extent=EXT,
        sigma_min_nm=40.0,
    )
    assert _moments(floored)[3] == pytest.approx(40.0, rel=0.03)


def test_many_widths_keep_mass_centroid_and_variance():
    # 400 localizations at one point with widths spread over 1.2..6 px: the level mixture must
    # give each spot its own variance, so the image's variance is the mean sigma^2.
    rng = np.random.default_rng(3)
    n = 400
    sx = rng.uniform(12.0, 60.0, n)
    sy = rng.uniform(12.0, 60.0, n)
    t = pd.DataFrame(
        {"x_nm": np.full(n, 1001.0), "y_nm": np.full(n, 997.0), "sigma_x_nm": sx, "sigma_y_nm": sy}
    )
    r = R.render_gaussian(t, px_nm=10.0, extent=EXT)
    total, mx, my, sdx, sdy = _moments(r)
    assert total == pytest.approx(n, rel=1e-4)
    assert (mx, my) == pytest.approx((1001.0, 997.0), abs=0.5)
    assert sdx**2 == pytest.approx(np.mean(sx**2), rel=0.03)
    assert sdy**2 == pytest.approx(np.mean(sy**2), rel=0.03)


@pytest.mark.parametrize("lo, hi, tol", [(2.0, 4.0, 0.03), (1.0, 2.0, 0.12)])
def test_filter_and_splat_paths_agree(lo, hi, tol):
    rng = np.random.default_rng(1)
    n = 1500
    pos = rng.uniform(20, 130, (n, 2))
    sig = rng.uniform(lo, hi, (n, 2))
    a = R._accumulate(pos, sig, (150, 150), np.ones((1, n)), method="filter")[0]
    b = R._accumulate(pos, sig, (150, 150), np.ones((1, n)), method="splat")[0]
    assert a.sum() == pytest.approx(n, rel=1e-4) and b.sum() == pytest.approx(n, rel=1e-4)
    assert np.abs(a - b).max() < tol * b.max()


@pytest.mark.parametrize("method", ["filter", "splat"])
def test_both_paths_give_each_spot_its_variance_at_one_pixel_widths(method):
    # At ~1 px the bilinear deposit's own spread (px^2 / 6 on average) matters; the filter
    # path must take it off. Image variance = mean sigma^2 + spread of the positions.
    rng = np.random.default_rng(7)
    n = 3000
    pos = rng.uniform(50, 51, (n, 2))  # every sub-pixel offset, little spread
    sig = np.full((n, 2), 1.0)
    img = R._accumulate(pos, sig, (100, 100), np.ones((1, n)), method=method)[0].astype(float)
    centres = np.arange(100) + 0.5
    for axis in (0, 1):
        prof = img.sum(axis=1 - axis)
        mean = (prof * centres).sum() / n
        var = (prof * (centres - mean) ** 2).sum() / n
        assert mean == pytest.approx(pos[:, axis].mean(), abs=0.01)
        assert var == pytest.approx(1.0 + pos[:, axis].var(), rel=0.01)


def test_localization_lands_on_the_right_pixel_in_every_projection():
    x, y, z = 1234.0, 567.0, -321.0
    t = _table(x_nm=x, y_nm=y, z_nm=z, sigma_x_nm=10.0, sigma_y_nm=10.0, sigma_z_nm=10.0)
    expect = {
        "xy": ((0.0, 2000.0, 0.0, 1000.0), x, y),
        "xz": ((0.0, 2000.0, -800.0, 800.0), x, z),
        "yz": ((0.0, 1000.0, -800.0, 800.0), y, z),
    }
    for proj, (ext, h, v) in expect.items():
        r = R.render_gaussian(t, px_nm=10.0, projection=proj, extent=ext)
        assert r.axes == tuple(proj)
        assert r.extent == ext
        row, col = np.unravel_index(np.argmax(r.density), r.density.shape)
        assert (row, col) == (int((v - ext[2]) // 10), int((h - ext[0]) // 10)), proj


def test_default_extent_is_padded_and_on_the_pixel_grid():
    t = _table(x_nm=[1000.0, 3000.0], y_nm=[500.0, 800.0], sigma_x_nm=20.0, sigma_y_nm=20.0)
    r = R.render_gaussian(t, px_nm=10.0)
    h0, h1, v0, v1 = r.extent
    assert h0 <= 1000 - 4 * 20 and h1 >= 3000 + 4 * 20 and v0 <= 500 - 80 and v1 >= 800 + 80
    assert h0 % 10 == 0 and v0 % 10 == 0
    assert r.density.shape == (round((v1 - v0) / 10), round((h1 - h0) / 10))
    assert r.density.sum() == pytest.approx(2.0, abs=1e-3)


def test_depth_image_gives_each_spot_its_depth():
    t = _table(x_nm=[500.0, 1500.0], y_nm=[1000.0, 1000.0], z_nm=[-300.0, 300.0])
    r = R.render_gaussian(t, px_nm=10.0, extent=EXT)
    assert r.depth is not None and r.depth.shape == r.density.shape
    assert r.depth[100, 50] == pytest.approx(-300.0, abs=0.5)
    assert r.depth[100, 150] == pytest.approx(300.0, abs=0.5)
    assert np.isnan(r.depth[10, 10])  # nothing there
    rgb = R.to_rgb(r, z_range=(-300.0, 300.0))
    assert rgb.shape == (200, 200, 3)
    # turbo: the deep spot is blue-ish, the high one red-ish
    assert rgb[100, 50, 2] > rgb[100, 50, 0] and rgb[100, 150, 0] > rgb[100, 150, 2]
    # side views take their hue from the z of each row, matching the xy colours
    xz = R.render_gaussian(t, px_nm=10.0, projection="xz", extent=(0.0, 2000.0, -505.0, 495.0))
    assert xz.depth is None
    side = R.to_rgb(xz, z_range=(-300.0, 300.0))
    assert side[20, 50, 2] > side[20, 50, 0] and side[80, 150, 0] > side[80, 150, 2]
    hue = [c / c.max() for c in (side[20, 50], rgb[100, 50])]  # brightness scales differ
    np.testing.assert_allclose(hue[0], hue[1], atol=0.05)


def test_two_dimensional_table_has_no_depth_and_no_side_views():
    t = _table(x_nm=[500.0, 1500.0], y_nm=[1000.0, 1000.0])
    r = R.render_gaussian(t, px_nm=10.0, extent=EXT)
    assert r.depth is None
    rgb = R.to_rgb(r)
    assert np.array_equal(rgb[..., 0], rgb[..., 1]) and rgb.max() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="z_nm"):
        R.render_gaussian(t, projection="xz")


def test_brightness_follows_one_shared_scale():
    t = _table(x_nm=[500.0, 1500.0], y_nm=[1000.0, 1000.0], z_nm=[0.0, 0.0])
    r = R.render_gaussian(t, px_nm=10.0, extent=EXT)
    vmax = R.intensity_scale(r, saturate=100.0)
    assert vmax == pytest.approx(float(r.density.max()))
    full = R.to_rgb(r, vmax=vmax, z_range=(-1.0, 1.0))
    half = R.to_rgb(r, vmax=2 * vmax, z_range=(-1.0, 1.0))
    np.testing.assert_allclose(half, full / 2, atol=1e-6)
    gam = R.to_rgb(r, vmax=vmax, z_range=(-1.0, 1.0), gamma=0.5)
    assert gam.sum() > full.sum()


def test_default_scale_saturates_the_densest_pixels():
    # 200 lone spots and one pile of 50: the pile is far above the 99.5th percentile of the
    # non-zero pixels, which sets full brightness.
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.uniform(100, 1900, 200), np.full(50, 1000.0)])
    y = np.concatenate([rng.uniform(100, 1900, 200), np.full(50, 1000.0)])
    r = R.render_gaussian(_table(x_nm=x, y_nm=y), px_nm=10.0, extent=EXT)
    scale = R.intensity_scale(r)
    d = r.density
    assert scale == pytest.approx(np.percentile(d[d > 1e-6 * d.max()], 99.5), rel=1e-6)
    assert scale < 0.2 * d.max()
    rgb = R.to_rgb(r)
    assert rgb[100, 100].max() == pytest.approx(1.0)  # saturated
    assert 0.0 < np.mean(rgb.max(axis=2) >= 0.999) < 0.01  # but only the densest pixels


# -- volume ------------------------------------------------------------------------------------


def test_volume_peak_sum_and_imagej_tiff(tmp_path):
    t = _table(
        x_nm=[510.0, 1530.0],
        y_nm=[730.0, 290.0],
        z_nm=[-220.0, 130.0],
        sigma_x_nm=15.0,
        sigma_y_nm=15.0,
        sigma_z_nm=40.0,
    )
    vol, meta = R.render_volume(
        t.iloc[:1], px_nm=20.0, pz_nm=50.0, extent=(0.0, 2000.0, 0.0, 1000.0), z_range=(-500, 500)
    )
    assert vol.shape == (20, 50, 100) and vol.dtype == np.float32
    assert np.unravel_index(np.argmax(vol), vol.shape) == ((-220 + 500) // 50, 730 // 20, 510 // 20)
    assert vol.sum() == pytest.approx(1.0, abs=1e-3)
    both, meta = R.render_volume(t)
    assert both.sum() == pytest.approx(2.0, abs=2e-3)
    assert meta["z0_nm"] == meta["extent_nm"][4] and meta["z0_nm"] % 50 == 0

    path = R.write_volume_tiff(tmp_path / "vol.tif", both, 20.0, 50.0, meta["z0_nm"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vol.tif"]  # no temporary left
    with tifffile.TiffFile(path) as tif:
        np.testing.assert_array_equal(tif.asarray(), both)
        ij = tif.imagej_metadata
        assert ij["spacing"] == pytest.approx(0.05) and ij["unit"] == "um"
        assert ij["slices"] == both.shape[0]
        num, den = tif.pages[0].tags["XResolution"].value
        assert num / den == pytest.approx(50.0)  # pixels per um at 20 nm
        assert ij["z0_nm"] == pytest.approx(meta["z0_nm"])


# -- FRC ---------------------------------------------------------------------------------------


def _lines(sigma: float, seed: int = 0) -> pd.DataFrame:
    """Molecules on random line segments in a 3 um field, ~8 localizations each, blurred by
    ``sigma`` (nm)."""
    rng = np.random.default_rng(seed)
    mols = []
    for _ in range(12):
        p0 = rng.uniform(0, 3000, 2)
        ang = rng.uniform(0, np.pi)
        s = rng.uniform(0, 1500, 40)
        mols.append(p0 + np.outer(s, [np.cos(ang), np.sin(ang)]))
    mol = np.vstack(mols)
    reps = rng.poisson(8, len(mol))
    xy = np.repeat(mol, reps, axis=0) + rng.normal(0, sigma, (reps.sum(), 2))
    return pd.DataFrame(
        {"frame": rng.integers(0, 2000, len(xy)), "x_nm": xy[:, 0], "y_nm": xy[:, 1]}
    )


def test_frc_resolution_tracks_localization_precision():
    fine = R.frc(_lines(10.0))
    coarse = R.frc(_lines(40.0))
    assert fine.warning == "" and coarse.warning == ""
    assert 15.0 < fine.resolution_nm < 60.0
    assert coarse.resolution_nm > 2.0 * fine.resolution_nm
    assert fine.frequency[-1] == pytest.approx(1 / 10.0, rel=0.01)  # Nyquist at 5 nm bins
    assert fine.curve[0] > 0.8 and fine.threshold == pytest.approx(1 / 7)
    # the resolution sits where the smoothed curve crosses 1/7
    k = np.searchsorted(fine.frequency, 1 / fine.resolution_nm)
    assert fine.curve[k - 1] >= 1 / 7 > fine.curve[k]


def test_frc_curve_matches_a_direct_full_plane_computation():
    rng = np.random.default_rng(9)
    n = 3000
    xy = rng.normal(160.0, 40.0, (n, 2))
    t = pd.DataFrame({"frame": np.arange(n), "x_nm": xy[:, 0], "y_nm": xy[:, 1]})
    res = R.frc(t, px_nm=5.0, split="random", seed=3, extent=(0.0, 320.0, 0.0, 320.0))
    half = np.random.default_rng(3).permutation(n) % 2 == 1
    edges = np.arange(65) * 5.0
    ffts = [
        np.fft.fft2(np.histogram2d(xy[h, 1], xy[h, 0], bins=(edges, edges))[0])
        for h in (~half, half)
    ]
    q = np.hypot(*np.meshgrid(np.fft.fftfreq(64, 5.0), np.fft.fftfreq(64, 5.0)))
    ring = np.rint(q * 64 * 5.0).astype(int)
    num = np.bincount(ring.ravel(), (ffts[0] * np.conj(ffts[1])).real.ravel())
    p1 = np.bincount(ring.ravel(), (np.abs(ffts[0]) ** 2).ravel())
    p2 = np.bincount(ring.ravel(), (np.abs(ffts[1]) ** 2).ravel())
    direct = (num / np.sqrt(p1 * p2))[1:33]
    np.testing.assert_allclose(res.curve_raw, direct, atol=2e-4)
    np.testing.assert_allclose(res.frequency, np.arange(1, 33) / 320.0)


def test_frc_of_structureless_points_only_sees_the_field_outline():
    # Uniform random points: the halves share nothing but the field's outline, so the curve
    # drops from the lowest rings and then stays at zero; the "resolution" is a sizeable
    # fraction of the field, far coarser than for a structure.
    rng = np.random.default_rng(5)
    n = 4000
    u = pd.DataFrame(
        {
            "frame": rng.integers(0, 2000, n),
            "x_nm": rng.uniform(0, 3000, n),
            "y_nm": rng.uniform(0, 3000, n),
        }
    )
    res = R.frc(u)
    assert res.resolution_nm > 100.0
    assert res.resolution_nm > 3 * R.frc(_lines(10.0)).resolution_nm
    assert abs(float(np.mean(res.curve[50:]))) < 0.03


def test_frc_reports_nan_with_a_reason_when_it_cannot_cross():
    res = R.frc(_lines(2.0), px_nm=100.0)  # bins far coarser than the structure's detail
    assert math.isnan(res.resolution_nm)
    assert "never falls below" in res.warning


def test_frc_split_in_frame_blocks():
    t = _lines(10.0)
    res = R.frc(t, n_blocks=4)
    frames = t["frame"].to_numpy()
    odd = ((frames - frames.min()) * 4 // (frames.max() - frames.min() + 1)) % 2 == 1
    assert res.n_halves == (int((~odd).sum()), int(odd.sum()))
    one_frame = t.assign(frame=0)
    with pytest.raises(ValueError, match="too few to split by blocks") as refusal:
        R.frc(one_frame)
    assert "split=" not in str(refusal.value)  # the refusal reaches CLI users: no Python keywords
    rnd = R.frc(one_frame, split="random")
    assert abs(rnd.n_halves[0] - rnd.n_halves[1]) <= 1 and np.isfinite(rnd.resolution_nm)


# -- figures -----------------------------------------------------------------------------------


def test_figures_are_written(tmp_path):
    rng = np.random.default_rng(2)
    n = 3000
    th = rng.uniform(0, 2 * np.pi, n)
    t = pd.DataFrame(
        {
            "frame": rng.integers(0, 500, n),
            "x_nm": 1000 + 300 * np.cos(th) + rng.normal(0, 10, n),
            "y_nm": 1000 + 300 * np.sin(th) + rng.normal(0, 10, n),
            "z_nm": 200 * np.sin(th),
            "sigma_x_nm": 10.0,
            "sigma_y_nm": 10.0,
            "sigma_z_nm": 30.0,
        }
    )
    out = R.plot_projections(t, tmp_path / "p.png", title="ring", truth=t.iloc[:100])
    flat = R.plot_projections(t.drop(columns="z_nm"), tmp_path / "flat.png")
    curve = R.plot_frc(R.frc(t), tmp_path / "frc.png")
    for p in (out, flat, curve):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.png", "frc.png", "p.png"]


def test_automatic_pixel_size():
    t = _table(x_nm=[0.0, 1000.0], y_nm=[0.0, 1000.0], sigma_x_nm=10.0, sigma_y_nm=10.0)
    assert R._auto_px(t, 1000.0) == 5.0  # half the median uncertainty
    assert R._auto_px(t, 50_000.0) == 25.0  # at most ~2000 px across
    assert R._auto_px(t[["x_nm", "y_nm"]], 1000.0) == 10.0  # 15 nm default -> 7.5 -> 10


# -- bad input ---------------------------------------------------------------------------------


def test_bad_input_raises_clear_errors(tmp_path):
    t = _table(x_nm=[100.0, 200.0], y_nm=[100.0, 200.0], z_nm=[0.0, 10.0])
    empty = t.iloc[:0]
    cases = [
        (lambda: R.render_gaussian(empty), "empty"),
        (lambda: R.render_gaussian(t, px_nm=0.0), "px_nm"),
        (lambda: R.render_gaussian(t, px_nm=-5.0), "px_nm"),
        (lambda: R.render_gaussian(t, projection="zz"), "projection"),
        (lambda: R.render_gaussian(t.drop(columns="x_nm")), "x_nm"),
        (lambda: R.render_gaussian(t, extent=(10.0, 0.0, 0.0, 10.0)), "extent"),
        (lambda: R.render_gaussian(t, px_nm=0.1, extent=(0.0, 1e5, 0.0, 1e5)), "cap"),
        (lambda: R.render_gaussian(t.assign(x_nm=np.nan)), "finite"),
        (lambda: R.render_volume(t.drop(columns="z_nm")), "z_nm"),
        (lambda: R.render_volume(t, px_nm=1.0, pz_nm=1.0, z_range=(-1e4, 1e4)), "cap"),
        (lambda: R.frc(t, split="halves"), "split"),
        (lambda: R.frc(t, n_blocks=1), "n_blocks"),
        (lambda: R.frc(empty), "empty"),
        (lambda: R.write_volume_tiff(tmp_path / "v.tif", np.zeros((4, 4)), 20, 50, 0), "shape"),
        (
            lambda: R.write_volume_tiff(tmp_path / "no" / "v.tif", np.zeros((2, 4, 4)), 20, 50),
            "does not exist",
        ),
    ]
    for call, words in cases:
        with pytest.raises(ValueError, match=words):
            call()
    r = R.render_gaussian(t)
    with pytest.raises(ValueError, match="saturate"):
        R.to_rgb(r, saturate=0.0)
    with pytest.raises(ValueError, match="gamma"):
        R.to_rgb(r, gamma=-1.0)
    with pytest.raises(ValueError, match="z_range"):
        R.plot_projections(t, tmp_path / "x.png", z_range=(5.0, 5.0))


def test_a_spot_wider_than_the_image_is_left_out():
    # A doubtful fit's uncertainty (1e7 nm here; 1e9 seen) must not size the kernels (the old
    # code built a 16-million-tap kernel here): the image is the one without that row.
    good = _table(
        x_nm=[800.0, 1200.0], y_nm=[900.0, 1100.0], z_nm=0.0, sigma_x_nm=20.0, sigma_y_nm=20.0
    )
    wide = _table(x_nm=1000.0, y_nm=1000.0, z_nm=0.0, sigma_x_nm=1e7, sigma_y_nm=1e7)
    both = pd.concat([good, wide], ignore_index=True)
    r = R.render_gaussian(both, px_nm=5.0, extent=EXT)
    ref = R.render_gaussian(good, px_nm=5.0, extent=EXT)
    assert np.array_equal(r.density, ref.density)


def test_an_frc_of_too_few_localizations_says_so():
    """The third walk-through: 83 localizations from 5 frames printed "FRC resolution:
    50.1 nm" with no caution. The report repeats the FRC over other splits of the frame
    blocks and cautions where the value depends on the split."""
    lines = _lines(10.0)
    res, msg = R.frc_report(lines)
    assert res is not None and len(res.extra["spread_nm"]) == 4
    assert "other splits of the frame blocks" in msg and "caution" not in msg, msg
    few = lines.sample(90, random_state=0).assign(frame=lambda t: t["frame"] % 5)
    res, msg = R.frc_report(few)
    assert "caution" in msg and "too few to measure the resolution" in msg, msg
