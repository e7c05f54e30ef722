"""The frame check (sparseloc.frame_residual): a localization on empty background has no
support, a PSF image without a localization is found in the residual, a right one is neither."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.frame_residual import frame_residual, residual_figure
from sparseloc.pipeline import LocalizeParams, run_templates
from sparseloc.psf import make_psf
from sparseloc.solvers.two_tier import detection_planes

PX = 100.0
BG = 10.0


def _check(frame, background, model, em, px, **kw):
    """The check with the run's detection planes for these settings, as check_frame passes."""
    planes = detection_planes(run_templates(model, LocalizeParams(pixel_size=px)))
    return frame_residual(frame, background, model, em, px, templates=planes, **kw)


@pytest.fixture(scope="module")
def scene():
    model = make_psf("astig")
    a = np.array([1500.0, 1500.0, 0.0, 3000.0])
    b = np.array([4200.0, 3400.0, 200.0, 3000.0])
    shape = (56, 64)
    light = model.render(*np.vstack([a, b]).T, shape, PX)
    frame = np.random.default_rng(3).poisson(BG + light).astype(float)
    return model, frame, a, b


def test_marker_on_background_has_no_support_and_missed_image_is_found(scene):
    model, frame, a, b = scene
    fake = np.array([4800.0, 1200.0, 0.0, 2000.0])  # nothing there
    check = _check(frame, BG, model, np.vstack([a, fake]), PX)
    assert check.support[0] > 1000.0
    assert check.support[1] < 0.0
    near = lambda p, xy: np.hypot(p[:, 1] - xy[0] / PX, p[:, 0] - xy[1] / PX) < 3  # noqa: E731
    found = near(check.unexplained, b[:2])
    assert found.any() and not near(check.unexplained, a[:2]).any()
    # a bright missed image is far above the count selection's bar, and the summary says so
    assert check.unexplained_snr[found].max() > np.sqrt(80.0)
    assert np.all(check.unexplained_snr > 4.5)  # the detection's own threshold, 5
    assert "1 below the count selection's bar of 80" in check.summary(80.0, 5.0)


def test_right_localizations_leave_a_noise_residual(scene, tmp_path):
    model, frame, a, b = scene
    em = np.vstack([a, b])
    check = _check(frame, BG, model, em, PX)
    assert np.all(check.support > 1000.0)
    assert len(check.unexplained) == 0
    assert abs(float(np.std(check.residual)) - 1.0) < 0.1
    out = residual_figure(check, PX, tmp_path / "check.png")
    assert out.is_file() and out.stat().st_size > 0
    assert not list(tmp_path.glob(".*tmp*"))


def test_window_backgrounds_replace_the_estimate_in_their_boxes(scene):
    model, frame, a, b = scene
    em = np.vstack([a, b])
    # an estimate that holds the emitters' light twice, as a spatial estimate over a dense
    # cell can: the fits' own constants put the background back where they were fitted
    high = np.full(frame.shape, BG + 3.0)
    low = _check(frame, high, model, em, PX)
    fitted = _check(frame, high, model, em, PX, window_background=[BG, BG])
    assert np.all(fitted.support > low.support)
    assert np.isclose(fitted.model_image[15, 15] - model.render(*em.T, frame.shape, PX)[15, 15],
                      BG, rtol=0.05)  # fmt: skip
    with pytest.raises(ValueError, match="one value per localization"):
        _check(frame, high, model, em, PX, window_background=[BG])


@pytest.mark.parametrize(
    "noise, qe, rv", [("poisson", 1.0, None), ("scmos", 0.7, 9.0), ("emccd", 0.9, 4.0)]
)
def test_support_is_the_fits_likelihood_ratio_for_each_camera(scene, noise, qe, rv):
    """The support is 2 delta log L of the fits' own likelihood (mle.LikelihoodProblem: the
    weight qe / F, the read variance on its scale) with and without each localization."""
    from sparseloc.solvers.mle import LikelihoodProblem

    model, frame, a, b = scene
    em = np.vstack([a, b])
    check = _check(frame, BG, model, em, PX, noise=noise, qe=qe,
                           read_variance=0.0 if rv is None else rv)  # fmt: skip
    prob = LikelihoodProblem(frame, model, PX, (0.0, 0.0), noise, rv, False, 2.0, qe=qe)
    kw = dict(noise=noise, qe=qe, read_variance=0.0 if rv is None else rv)
    for k in range(len(em)):
        without = _check(frame, BG, model, np.delete(em, k, axis=0), PX, **kw)
        expected = 2.0 * (prob.nll(without.model_image) - prob.nll(check.model_image))
        assert check.support[k] == pytest.approx(expected, rel=1e-9)
    # the residual is in the likelihood's noise units: mu / w + v
    w = qe / (2.0 if noise == "emccd" else 1.0)
    var = check.model_image / w + (0.0 if rv is None else rv)
    np.testing.assert_allclose(check.residual, (frame - check.model_image) / np.sqrt(var))


def test_localize_check_writes_the_picture_and_refuses_a_bad_suffix(tmp_path):
    from cli_checks import run

    movie = tmp_path / "m.tif"
    sim = ("--psf", "astig", "--frames", "2", "--rows", "32", "--cols", "32",
           "--pixel-size", "100", "--density", "0.3", "--photons-min", "3000",
           "--photons-max", "4000", "--seed", "3")  # fmt: skip
    assert run("simulate", "-o", movie, *sim).exit_code == 0
    out, png = tmp_path / "locs.parquet", tmp_path / "check.png"
    args = ("localize", movie, "-o", out, "--psf", "astig", "--pixel-size", "100")
    res = run(*args, "--check", png)
    assert res.exit_code == 0, res.output
    assert "check of frame 0:" in res.output and "below the count selection's bar" in res.output
    assert png.is_file() and png.stat().st_size > 0
    bad = run(*args, "--overwrite", "--check", tmp_path / "check.txt")
    assert bad.exit_code == 2 and "the check's picture must be" in bad.output


def test_check_frame_leaves_out_unusable_rows_and_names_a_missing_column(scene):
    import pandas as pd

    from sparseloc.pipeline import LocalizeParams, addition_bar, check_frame
    from sparseloc.solvers.frame import ADD_THRESHOLD
    from sparseloc.solvers.refine import LR_THRESHOLD

    model, frame, a, b = scene
    rows = np.vstack([a, b, [np.nan, 1000.0, 0.0, 2000.0], [2000.0, 2000.0, 0.0, np.nan]])
    table = pd.DataFrame(rows, columns=["x_nm", "y_nm", "z_nm", "photons"]).assign(frame=0)
    params = LocalizeParams(pixel_size=PX)
    check = check_frame(frame[None], 0, table, model, params)
    assert len(check.support) == 2 and np.all(np.isfinite(check.support))
    with pytest.raises(ValueError, match="no photons column"):
        check_frame(frame[None], 0, table.drop(columns="photons"), model, params)
    assert addition_bar(params) == ADD_THRESHOLD
    assert addition_bar(LocalizeParams(pixel_size=PX, method="mp")) == LR_THRESHOLD


def test_each_support_takes_its_own_windows_background(scene):
    """Two windows fitted with different constants: each localization's support is the
    ratio over its box with its own constant, as in its fit, not the boxes' mean."""
    model, frame, a, b = scene
    near = b.copy()
    near[:2] = a[:2] + 600.0  # boxes overlap
    em = np.vstack([a, near])
    own = np.array([BG - 1.0, BG + 3.0])
    both = _check(frame, BG, model, em, PX, window_background=own)
    for k in range(2):
        alone = _check(frame, own[k], model, em, PX)
        assert both.support[k] == pytest.approx(alone.support[k], rel=1e-9)
