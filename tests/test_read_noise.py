"""sCMOS read noise through the pipeline, and the pupil model's blur."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.cli import app
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import PupilPSF, make_psf
from sparseloc.simulate import simulate
from sparseloc.solvers.frame import frame_pursuit, frame_templates

PX = 100.0


# --- blur ----------------------------------------------------------------------------------


def _moments(img):
    r, c = np.indices(img.shape)
    s = img.sum()
    mr, mc = (img * r).sum() / s, (img * c).sum() / s
    return s, ((r - mr) ** 2 * img).sum() / s, ((c - mc) ** 2 * img).sum() / s


def test_blur_adds_its_variance_and_keeps_the_photons():
    sharp = PupilPSF(None, z_range=(-500.0, 500.0))
    blurred = PupilPSF(None, z_range=(-500.0, 500.0), blur=150.0)
    x = y = 40.5 * PX
    a = sharp.images([x], [y], [0.0], (81, 81), PX)[0]
    b = blurred.images([x], [y], [0.0], (81, 81), PX)[0]
    sa, vra, vca = _moments(a)
    sb, vrb, vcb = _moments(b)
    assert sb == pytest.approx(sa, rel=1e-3)
    # variances add under convolution: 1.5 px blur adds 2.25 px^2 in each axis
    assert vrb - vra == pytest.approx(2.25, rel=0.05)
    assert vcb - vca == pytest.approx(2.25, rel=0.05)
    assert b.max() < a.max()


def test_blur_derivatives_match_finite_differences():
    m = PupilPSF(make_psf("dh").mask, z_range=(-500.0, 500.0), blur=100.0)
    x, y, z = 10.3 * PX, 9.8 * PX, 120.0
    _, d = m.images([x], [y], [z], (21, 21), PX, derivatives=True)
    h = 0.5
    up = m.images([x], [y], [z + h], (21, 21), PX)[0]
    dn = m.images([x], [y], [z - h], (21, 21), PX)[0]
    np.testing.assert_allclose(d[0, 2], (up - dn) / (2 * h), atol=1e-7)


def test_negative_blur_is_refused():
    with pytest.raises(ValueError, match="blur"):
        PupilPSF(None, blur=-1.0)


# --- read noise in the pursuit and the pipeline --------------------------------------------


@pytest.fixture(scope="module")
def analytic():
    return make_psf("dh-analytic")


def test_read_noise_raises_the_detection_bar(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=120.0)
    mu = analytic.render([2400.0], [2400.0], [0.0], [700.0], (48, 48), PX) + 5.0
    frame = np.random.default_rng(2).poisson(mu).astype(float)
    quiet = frame_pursuit(frame, 5.0, t)
    noisy = frame_pursuit(frame, 5.0, t, read_variance=400.0)
    assert len(quiet) >= 1
    assert len(noisy) == 0
    # a constant map is the scalar
    mapped = frame_pursuit(frame, 5.0, t, read_variance=np.full(frame.shape, 400.0))
    assert len(mapped) == len(noisy)


@pytest.fixture(scope="module")
def movie(analytic):
    sim = simulate(
        analytic,
        scene="uniform",
        n_frames=2,
        shape=(40, 40),
        pixel_size=PX,
        density=0.4,
        photons=(2000.0, 5000.0),
        background=10.0,
        seed=4,
    )
    return sim.movie.astype(float) - sim.camera.offset


def test_constant_read_variance_map_equals_the_scalar(analytic, movie):
    scalar = LocalizeParams(pixel_size=PX, noise="scmos", read_variance=4.0)
    a = localize(movie, analytic, scalar)
    b = localize(movie, analytic, scalar, read_variance=np.full(movie.shape[1:], 4.0))
    assert len(a.table) > 3
    pd.testing.assert_frame_equal(a.table, b.table)
    assert "read_variance_map_sha256" in b.metadata
    # the read noise changes the likelihood: the same emitters' uncertainties grow (compared
    # emitter by emitter: the two runs need not find the same faint extras)
    c = localize(movie, analytic, LocalizeParams(pixel_size=PX))
    ratios = []
    for row in a.table.itertuples():
        same = c.table[c.table.frame == row.frame]
        d = np.hypot(same.x_nm - row.x_nm, same.y_nm - row.y_nm)
        if len(d) and d.min() < 30.0:
            ratios.append(row.sigma_x_nm / same.sigma_x_nm.iloc[int(np.argmin(d.to_numpy()))])
    assert len(ratios) >= 10
    # rows flagged z_edge carry NaN uncertainties
    assert np.nanmedian(ratios) > 1.0  # 1.044 over 20 pairs when written; 1.0 if ignored


@pytest.mark.parametrize("method", ["mp", "hybrid"])
def test_windowed_solvers_take_a_read_variance_map(analytic, movie, method):
    """The windowed solvers crop a map to each window: a constant map is the scalar, and a
    map that is noisy on the left half keeps only the right half's localizations (those of the
    quiet run there)."""
    kw = dict(pixel_size=PX, method=method, noise="scmos")
    scalar = localize(movie, analytic, LocalizeParams(**kw, read_variance=4.0))
    mapped = localize(
        movie, analytic, LocalizeParams(**kw), read_variance=np.full(movie.shape[1:], 4.0)
    )
    assert len(scalar.table) > 3
    pd.testing.assert_frame_equal(scalar.table, mapped.table)
    half = np.full(movie.shape[1:], 4.0)
    half[:, :20] = 1e4
    noisy = localize(movie, analytic, LocalizeParams(**kw), read_variance=half).table
    # Beyond 32 px neither a window owning an emitter (11 px, 3 px margin) nor the detection
    # template (23 px) reaches the noisy half.
    far = 32 * PX
    assert (scalar.table.x_nm > far).sum() >= 1
    assert len(noisy) and (noisy.x_nm > 20 * PX).all()
    np.testing.assert_allclose(
        np.sort(noisy.x_nm[noisy.x_nm > far]), np.sort(scalar.table.x_nm[scalar.table.x_nm > far])
    )


@pytest.mark.parametrize(
    ("kwargs", "rv", "message"),
    [
        ({"noise": "scmos"}, np.ones((5, 5)), "read-variance map is"),
        ({}, np.ones((40, 40)), "sCMOS likelihood"),
        ({"noise": "scmos"}, -np.ones((40, 40)), ">= 0"),
    ],
)
def test_bad_read_variance_maps_are_refused(analytic, movie, kwargs, rv, message):
    with pytest.raises(ValueError, match=message):
        localize(movie, analytic, LocalizeParams(pixel_size=PX, **kwargs), read_variance=rv)


def test_bad_noise_parameters_are_refused():
    with pytest.raises(ValueError, match="noise must be"):
        LocalizeParams(pixel_size=PX, noise="gaussian")
    with pytest.raises(ValueError, match="read_variance"):
        LocalizeParams(pixel_size=PX, read_variance=-1.0)


# --- command line --------------------------------------------------------------------------


def test_localize_cli_takes_scmos_read_noise_and_maps(tmp_path):
    import tifffile

    runner = CliRunner()
    movie = tmp_path / "m.tif"
    res = runner.invoke(
        app,
        [
            "simulate", "-o", str(movie), "--psf", "dh-analytic", "--frames", "1",
            "--rows", "32", "--cols", "32", "--pixel-size", "100", "--density", "0.3",
            "--photons-min", "3000", "--photons-max", "4000", "--camera", "scmos",
            "--read-noise", "1.5", "--seed", "1",
        ],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    base = ["localize", str(movie), "--psf", "dh-analytic", "--pixel-size", "100"]
    out = tmp_path / "a.parquet"
    res = runner.invoke(app, [*base, "-o", str(out), "--camera", "scmos", "--read-noise", "1.5"])
    assert res.exit_code == 0, res.output
    from sparseloc.io.tables import read_parquet

    table, meta = read_parquet(out)
    assert len(table) >= 1
    assert meta["params"]["noise"] == "scmos"
    assert meta["params"]["read_variance"] == pytest.approx(2.25)
    var = tmp_path / "var.tif"
    tifffile.imwrite(var, np.full((32, 32), 2.25, np.float32))
    out2 = tmp_path / "b.parquet"
    res = runner.invoke(
        app, [*base, "-o", str(out2), "--camera", "scmos", "--variance-map", str(var)]
    )
    assert res.exit_code == 0, res.output
    # a uniform map is passed as the scalar it is
    assert read_parquet(out2)[1]["params"]["read_variance"] == pytest.approx(2.25)
    small = tmp_path / "small.tif"
    tifffile.imwrite(small, np.ones((8, 8), np.float32))
    for args, msg in [
        (["--variance-map", str(var)], "need --camera scmos"),
        (["--camera", "scmos", "--variance-map", str(small)], "camera maps are 8x8"),
    ]:
        res = runner.invoke(app, [*base, "-o", str(tmp_path / "x.csv"), *args])
        assert res.exit_code == 2 and msg in res.output, res.output
    assert not (tmp_path / "x.csv").exists()


def test_a_read_variance_map_is_placed_by_rows_and_columns_and_tiles(analytic):
    t = frame_templates(analytic, PX, dxy=50.0, dz=120.0)
    shape = (64, 96)
    mu = analytic.render([1500.0, 8000.0], [3200.0, 3200.0], [0.0, 0.0], [700.0] * 2, shape, PX)
    frame = np.random.default_rng(3).poisson(mu + 5.0).astype(float)
    rv = np.zeros(shape)
    rv[:, :48] = 1000.0  # noisy left half (x < 4800 nm): its emitter is not significant there
    from sparseloc.solvers.frame import tiled_pursuit

    whole = tiled_pursuit(frame, 5.0, t, read_variance=rv)
    tiled = tiled_pursuit(frame, 5.0, t, read_variance=rv, max_pixels=1000, core=32)
    for found in (whole, tiled):
        assert len(found) >= 1
        assert np.all(found.x > 4800.0)  # only the right-hand emitter
    assert len(tiled_pursuit(frame, 5.0, t)) >= 2  # both, without the read noise


def test_read_variance_needs_a_camera_with_read_noise():
    with pytest.raises(ValueError, match="applies to noise='scmos' or 'emccd'"):
        LocalizeParams(pixel_size=PX, read_variance=2.0)


def test_cli_converts_the_variance_map_with_gain_and_qe(tmp_path):
    import tifffile

    movie = tmp_path / "m.tif"
    rng = np.random.default_rng(0)
    tifffile.imwrite(movie, (100 + rng.poisson(20.0, (2, 32, 32))).astype(np.uint16))
    var = tmp_path / "var.tif"
    tifffile.imwrite(var, np.full((32, 32), 16.0, np.float32))
    out = tmp_path / "a.parquet"
    res = CliRunner().invoke(
        app,
        [
            "localize", str(movie), "-o", str(out), "--psf", "dh-analytic",
            "--pixel-size", "100", "--camera", "scmos", "--variance-map", str(var),
            "--gain", "0.5", "--qe", "0.8",
        ],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    from sparseloc.io.tables import read_parquet

    # 16 ADU^2 x (0.5 e-/ADU)^2 / 0.8^2 = 6.25 photons^2
    params = read_parquet(out)[1]["params"]
    assert params["read_variance"] == pytest.approx(6.25)
    assert params["qe"] == 0.8  # the likelihood's quantum efficiency is the camera's


# --- EMCCD read noise ----------------------------------------------------------------------


def test_emccd_read_noise_enters_the_fit_as_its_variance(analytic):
    """An EMCCD's read noise behind its gain adds its variance to the doubled shot noise: the
    fit's uncertainties are the Cramer-Rao bounds of ``2 mu + v``, and its deviance of data
    with that noise is about 1 per degree of freedom (it is not without the read noise)."""
    from sparseloc.crlb import crlb
    from sparseloc.solvers.emitters import Emitters
    from sparseloc.solvers.mle import fit_emitters

    rv, bg, shape = 40.0, 5.0, (21, 21)
    mu = analytic.render([1050.0], [1050.0], [100.0], [3000.0], shape, PX) + bg
    rng = np.random.default_rng(4)
    gofs, plain = [], []
    for _ in range(30):
        y = rng.normal(mu, np.sqrt(2 * mu + rv))
        start = Emitters.from_array([[1040.0, 1060.0, 80.0, 2500.0]])
        kw = dict(pixel_size=PX, noise="emccd", background=bg)
        fit = fit_emitters(y, analytic, start, read_variance=rv, **kw)
        gofs.append(fit.deviance_per_dof)
        plain.append(fit_emitters(np.maximum(y, 0), analytic, start, **kw).deviance_per_dof)
    bound = crlb(analytic, 1050.0, 1050.0, 100.0, 3000.0, bg, shape, PX, noise="emccd",
                 read_variance=rv)  # fmt: skip
    np.testing.assert_allclose(fit.sigma[0, :3], bound[0, :3], rtol=0.25)
    assert 0.8 < np.median(gofs) < 1.25
    assert np.median(plain) > 1.4  # the read variance is a third of a bright pixel's


def test_the_emccd_camera_gives_the_likelihood_its_read_noise():
    from sparseloc.camera import Camera
    from sparseloc.config import noise_model, read_variance_photons

    em = Camera(kind="emccd", em_gain=10.0, read_noise=50.0, qe=0.9)
    assert noise_model(em) == "emccd"
    assert float(read_variance_photons(em, (4, 4))) == pytest.approx((50.0 / (10.0 * 0.9)) ** 2)
    p = LocalizeParams(pixel_size=PX, noise="emccd", read_variance=30.0)
    from sparseloc.pipeline import _noise_kwargs

    assert _noise_kwargs(p)["read_variance"] == 30.0
    # without EM gain the shot noise is not doubled; the read noise remains
    assert noise_model(Camera(kind="emccd", em_gain=1.0, read_noise=8.0)) == "scmos"
    assert noise_model(Camera(kind="emccd", em_gain=1.0)) == "poisson"


def test_emccd_read_noise_given_on_the_command_line_passes_the_model_check(tmp_path):
    """An EMCCD at low EM gain with read noise: its localization fits the data (median goodness
    of fit about 1) only when the read noise is in the likelihood."""
    from sparseloc.io.tables import read_parquet

    cam = ["--camera", "emccd", "--em-gain", "2", "--gain", "1", "--read-noise", "14"]
    geo = ["--psf", "dh-analytic", "--pixel-size", "160", "--z-min", "-300", "--z-max", "300"]
    movie, out = tmp_path / "em.tif", tmp_path / "locs.parquet"
    runner = CliRunner()
    scene = ["--frames", "3", "--rows", "48", "--cols", "48", "--density", "0.3"]
    scene += ["--photons-min", "2000", "--photons-max", "5000", "--seed", "3"]
    res = runner.invoke(app, ["simulate", "-o", str(movie), *geo, *cam, *scene])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["localize", str(movie), "-o", str(out), *geo, *cam, "--workers", "1"])
    assert res.exit_code == 0, res.output
    check = read_parquet(out)[1]["model_check"]
    assert check["verdict"] == "ok", check
    assert 0.85 < check["median_gof"] < 1.2


def test_a_crop_of_the_read_variance_is_the_maps_pixels_or_the_number():
    from sparseloc.solvers.variance import read_variance_crop

    rv = np.arange(20.0).reshape(4, 5)
    crop = read_variance_crop(rv, (4, 5), (1, 3, 2, 5))
    np.testing.assert_array_equal(crop, [[7.0, 8.0, 9.0], [12.0, 13.0, 14.0]])
    # a row of the map broadcast over the frame's rows; open ends as slices have them
    row = read_variance_crop(np.arange(5.0), (4, 5), (None, 2, 3, None))
    np.testing.assert_array_equal(row, [[3.0, 4.0], [3.0, 4.0]])
    assert read_variance_crop(2.5, (4, 5), (1, 3, 2, 5)) == 2.5
    assert read_variance_crop(None, (4, 5), (1, 3, 2, 5)) is None
