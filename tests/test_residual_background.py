"""A frame's spatial background estimated again without the light of the emitters fitted in it."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import sparseloc.pipeline as pipeline
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf

PX = 100.0
BACKGROUND = 20.0


@pytest.fixture(scope="module")
def crowded():
    """One 48 x 48 px frame of 24 double helices (1,500-6,000 photons) over a flat background:
    their images cover most of every 16 px block the spatial estimate takes its darker
    pixels from."""
    model = make_psf("dh-analytic")
    lo, hi = model.z_range
    rng = np.random.default_rng(0)
    n, size = 24, 48
    x = rng.uniform(300, size * PX - 300, n)
    y = rng.uniform(300, size * PX - 300, n)
    z = rng.uniform(0.8 * lo, 0.8 * hi, n)
    photons = rng.uniform(1500, 6000, n)
    mu = model.render(x, y, z, photons, (size, size), PX) + BACKGROUND
    frame = rng.poisson(mu).astype(float)
    truth = pd.DataFrame(dict(frame=0, x_nm=x, y_nm=y, z_nm=z, photons=photons))
    return model, frame, truth


def _spy_fits(monkeypatch) -> list[float]:
    """The median background of every frame fit the pipeline runs, in order."""
    seen: list[float] = []
    real = pipeline.frame_fit

    def spy(frame, model, emitters, background=None, **kw):
        seen.append(float(np.median(background)))
        return real(frame, model, emitters, background=background, **kw)

    monkeypatch.setattr(pipeline, "frame_fit", spy)
    return seen


def test_a_crowded_frame_is_refitted_over_the_background_its_emitters_hid(crowded, monkeypatch):
    model, frame, truth = crowded
    seen = _spy_fits(monkeypatch)
    res = localize(frame[None], model, LocalizeParams(pixel_size=PX), check=False)
    # the frame's own estimate holds the emitters' light; without it the estimate is the
    # background, and the emitters it hid are found
    assert seen[0] > BACKGROUND + 4.0
    assert abs(seen[-1] - BACKGROUND) < 1.5
    ev = evaluate(res.table, truth)
    assert ev.recall >= 0.8  # 0.75 with the first estimate alone


def test_temporal_backgrounds_are_not_estimated_again(crowded, monkeypatch):
    model, frame, _ = crowded
    movie = np.stack([frame, np.full(frame.shape, BACKGROUND), np.full(frame.shape, BACKGROUND)])
    called = []
    monkeypatch.setattr(
        pipeline._FrameSolver, "residual_background", lambda *a, **k: called.append(1)
    )
    p = LocalizeParams(pixel_size=PX, background="temporal")
    localize(movie, model, p, check=False, stop=1)
    assert not called
    assert pipeline._temporal(LocalizeParams(pixel_size=PX), p.min_temporal_frames)
    assert not pipeline._temporal(LocalizeParams(pixel_size=PX), p.min_temporal_frames - 1)


def test_given_starts_are_refitted_without_a_search(crowded, monkeypatch):
    model, frame, truth = crowded
    seen = _spy_fits(monkeypatch)
    searched = []
    real_start = pipeline._FrameSolver.start

    def start(self, *a, **k):
        searched.append(1)
        return real_start(self, *a, **k)

    monkeypatch.setattr(pipeline._FrameSolver, "start", start)
    res = localize(frame[None], model, LocalizeParams(pixel_size=PX), check=False, starts=truth)
    # the fits from the given emitters, then the same refit over the background without
    # their light: the ceiling a run's fits are measured against keeps the run's rule
    assert len(seen) == 2 and abs(seen[-1] - BACKGROUND) < 1.5
    assert not searched
    assert len(res.table) >= 0.9 * len(truth)
