"""``haze``: the fits' background follows the shape of the background estimate where the data
prefer it to a constant (a haze broader than one emitter's image is background, not
emitters)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sparseloc.config import LocalizeParams
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import _FrameSolver, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.solvers.emitters import Emitters
from sparseloc.solvers.frame_windows import background_shape
from sparseloc.solvers.mle import fit_emitters

PX = 100.0
SHAPE = (64, 64)


@pytest.fixture(scope="module")
def astig():
    """The astigmatic pupil model tabulated as the pipeline does."""
    p = LocalizeParams(pixel_size=PX, background="temporal", haze=True)
    return work_model_for(make_psf("astig"), p), p


def _haze(amplitude: float) -> np.ndarray:
    """A haze 2 um wide (one sigma) centred on the frame, photons/pixel."""
    r, c = np.mgrid[: SHAPE[0], : SHAPE[1]]
    return amplitude * np.exp(-((r - 32.0) ** 2 + (c - 32.0) ** 2) / (2 * 20.0**2))


def test_a_fit_that_scales_the_background_shape_is_not_biased_by_a_haze(astig):
    """One emitter on the flank of a haze: with the haze's shape the fit finds its photons
    and position; a constant background leaves the haze's slope for the emitter to take."""
    work, _ = astig
    rng = np.random.default_rng(0)
    bg = 10.0 + _haze(20.0)[8:40, 8:40]  # the haze's flank over a 32 px window
    truth = np.array([1600.0, 1600.0, 0.0, 2000.0])
    errors = {}
    for shaped in (False, True):
        err = []
        for seed in range(6):
            mu = work.render(*truth[:, None], bg.shape, PX) + bg
            y = np.random.default_rng(seed).poisson(mu).astype(float)
            fit = fit_emitters(
                y, work, Emitters.from_array(truth[None] + rng.normal(0, 30, 4) * [1, 1, 1, 0]),
                pixel_size=PX, background_shape=bg if shaped else None,
            )  # fmt: skip
            err.append(fit.emitters.as_array()[0] - truth)
        errors[shaped] = np.abs(np.mean(err, axis=0))
    assert errors[True][3] < 0.05 * truth[3] and np.all(errors[True][:2] < 15.0)
    assert errors[False][3] > 2 * errors[True][3]
    assert fit.background_shape is not None  # the data chose the shape
    # the fitted background is the haze at the shape's median level
    assert abs(fit.background[0] - np.median(bg)) < 1.0
    assert np.allclose(fit.background_image, fit.background[0] * bg / np.median(bg))


def _movie(work, haze, n_frames=24, seed=1):
    rng = np.random.default_rng(seed)
    frames, rows = [], []
    for f in range(n_frames):
        xy = rng.uniform(600, 5800, (3, 2))
        z = rng.uniform(-400, 400, 3)
        ph = rng.uniform(1500, 3000, 3)
        mu = work.render(xy[:, 0], xy[:, 1], z, ph, SHAPE, PX) + 10.0 + haze
        frames.append(rng.poisson(mu).astype(float))
        rows += [dict(frame=f, x_nm=a, y_nm=b, z_nm=c, photons=d) for a, b, c, d in
                 zip(xy[:, 0], xy[:, 1], z, ph, strict=True)]  # fmt: skip
    import pandas as pd

    return np.array(frames), pd.DataFrame(rows)


def test_a_haze_in_a_movie_gives_no_false_emitters(astig):
    """A haze as bright as the floor under a temporal background estimate: the fits take it
    as background (a window's constant cannot follow its slope, and the count selection
    explained the excess with emitters)."""
    work, p = astig
    frames, truth = _movie(work, _haze(10.0))
    res = localize(frames, work, p)
    ev = evaluate(res.table, truth, lateral_tol=250.0, axial_tol=500.0)
    assert ev.fp <= 1 and ev.recall > 0.95, ev


def test_the_haze_option_gives_the_fits_the_estimates_shape(astig):
    """Off (the default) the fits keep a constant background; on, every fit of the frame
    solver is given the estimate smoothed at the PSF's core radius, to scale where the data
    prefer it."""
    work, p = astig
    bg = 10.0 + _haze(20.0)
    assert _FrameSolver(work, replace(p, haze=False), SHAPE).background_shape(bg) is None
    solver = _FrameSolver(work, p, SHAPE)
    want = background_shape(bg, solver.templates.core_radius)
    assert np.allclose(solver.background_shape(bg), want)
    assert solver.fit_kwargs(shape=want)["background_shape"] is want
    assert not LocalizeParams(pixel_size=PX).haze


def _flank(work, amplitude: float, seed: int):
    """One emitter on a 32 px window of a haze's flank: the data, the truth, the window's
    background (photons/pixel) and a start near the truth."""
    bg = 10.0 + _haze(amplitude)[8:40, 8:40]
    truth = np.array([1600.0, 1600.0, 0.0, 2000.0])
    rng = np.random.default_rng(seed)
    y = rng.poisson(work.render(*truth[:, None], bg.shape, PX) + bg).astype(float)
    start = truth[None] + rng.normal(0, 30, 4) * [1, 1, 1, 0]
    return y, truth, bg, Emitters.from_array(start)


def test_a_shape_the_data_do_not_ask_for_leaves_the_constant(astig):
    """A flat background under a shape with a bump where the emitter is (an estimate from
    crowded frames holds the emitters' own light): the fit keeps the constant, the very fit
    made without the shape, and says so."""
    work, _ = astig
    r, c = np.mgrid[:32, :32]
    bump = 10.0 + 15.0 * np.exp(-((r - 15.5) ** 2 + (c - 15.5) ** 2) / (2 * 3.0**2))
    for seed in range(6):
        y, _, _, start = _flank(work, 0.0, seed)
        flat = fit_emitters(y, work, start, pixel_size=PX)
        fit = fit_emitters(y, work, start, pixel_size=PX, background_shape=bump)
        assert fit.background_shape is None
        assert np.array_equal(fit.emitters.as_array(), flat.emitters.as_array())


def test_the_shape_is_tried_only_where_the_constant_fits_slope_allows_it(astig, monkeypatch):
    """The shape's fit runs only where the constant fit's score along the shape exceeds the
    margin, and the choice is that of fitting both (the likelihood is concave along the
    path from the constant to the shape): flat windows cost one fit, hazy ones two."""
    from sparseloc.solvers import mle

    work, _ = astig
    calls = []
    real = mle._fit
    monkeypatch.setattr(mle, "_fit", lambda prob, *a: calls.append(prob) or real(prob, *a))
    tried = {}
    for amplitude in (0.0, 5.0, 20.0):
        for seed in range(4):
            y, _, bg, start = _flank(work, amplitude, seed)
            calls.clear()
            fit = fit_emitters(y, work, start, pixel_size=PX, background_shape=bg)
            tried[amplitude, seed] = len(calls) == 2
            args = (y, work, PX, (0.0, 0.0), "poisson", None, False, 1.0, None, 1.0)
            flat = real(mle.LikelihoodProblem(*args), start, None, 60, 1e-6)
            hazy = real(mle.LikelihoodProblem(*args, bg), start, None, 60, 1e-6)
            both = hazy.log_likelihood > flat.log_likelihood + mle.SHAPE_MARGIN
            assert (fit.background_shape is not None) == both, (amplitude, seed)
    assert not any(tried[0.0, s] for s in range(4))
    assert all(tried[20.0, s] for s in range(4))
