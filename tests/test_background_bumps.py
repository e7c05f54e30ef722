"""The temporal background does not take in a molecule that stays on (detect.capped_bumps)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.detect import capped_bumps, temporal_backgrounds
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.psf.base import light_radius

PX = 100.0
BG = 50.0


def _on_movie(model, n: int, on: int, shape=(40, 40), photons=3000.0, seed=0):
    """``n`` frames of a flat background with one emitter (z 0) on in the first ``on``."""
    rng = np.random.default_rng(seed)
    x = y = shape[0] * PX / 2
    mu = model.render([x], [y], [0.0], [photons], shape, PX)
    frames = np.array([rng.poisson(BG + mu * (k < on)) for k in range(n)], dtype=float)
    return frames, mu, (x, y)


def _width(model) -> int:
    return 2 * light_radius(model, PX) + 1


def test_a_molecule_on_in_most_frames_leaves_no_bump_in_the_background():
    model = make_psf("dh-analytic")
    frames, mu, _ = _on_movie(model, 21, 18)
    raw = temporal_backgrounds(frames, np.array([10]), 10)
    lit = mu > 0.02 * mu.max()
    # the percentile takes in most of the molecule's light ...
    assert (raw[0][lit] - BG).sum() > 0.5 * mu[lit].sum()
    # ... the cap leaves little of it
    capped = capped_bumps(raw, _width(model))
    assert (capped[0][lit] - BG).sum() < 0.1 * mu[lit].sum()


def test_the_cap_leaves_a_smooth_background_and_its_noise():
    rng = np.random.default_rng(1)
    rows, cols = np.mgrid[0:96, 0:96]
    width = 15
    # a ramp and a hill four image widths wide: the background's own scales
    smooth = (
        60.0
        + 0.2 * cols
        + 40.0 * np.exp(-((rows - 40) ** 2 + (cols - 60) ** 2) / (2 * (2 * width) ** 2))
    )
    sd = 1.0
    est = smooth + rng.normal(0.0, sd, smooth.shape)
    capped = capped_bumps(est[None], width)[0]
    lowered = est - capped
    # on average the cap lowers the estimate by 0.08 of its standard deviation (the normal
    # tail above one standard deviation); the interpolation between block centres adds a little
    assert lowered.mean() < 0.15 * sd
    assert np.abs(capped - smooth).max() < 5 * sd


def test_a_molecule_that_stays_on_is_found_in_each_frame():
    # on in 18 of 21 frames, 1,000 photons on 50 /px: without the cap 5 of its 18 frames
    model = make_psf("dh-analytic")
    frames, _, (x, y) = _on_movie(model, 21, 18, shape=(32, 32), photons=1000.0)
    truth = {"frame": np.arange(18), "x_nm": x, "y_nm": y, "z_nm": 0.0, "photons": 1000.0}
    params = LocalizeParams(pixel_size=PX, z_range=(-300.0, 300.0), background="temporal")
    res = localize(frames, model, params, check=False)
    ev = evaluate(res.table, pd.DataFrame(truth))
    assert ev.recall >= 0.9 and ev.precision >= 0.9


@pytest.mark.parametrize(
    "maps, block, allowance",
    [
        (np.ones((1, 8, 8)), 0, 1.0),
        (np.ones((1, 8, 8)), 5, -1.0),
        (np.full((1, 8, 8), np.nan), 5, 1.0),
    ],
)
def test_the_cap_refuses_bad_input_in_one_sentence(maps, block, allowance):
    with pytest.raises(ValueError, match=r"block|finite"):
        capped_bumps(maps, block, allowance)
