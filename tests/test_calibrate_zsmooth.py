"""The model's smoothing along z is chosen by the beads (sparseloc.calibrate_zsmooth)."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.calibrate_zsmooth import (
    WINDOWS,
    choose_window,
    clean_average,
    fallback_window,
    model_stack,
)
from sparseloc.psf import make_psf

PX = 100.0
R = 31


def _truth(name: str, step: float) -> np.ndarray:
    """The PSF ``name`` on R x R pixels of PX nm, one plane per ``step`` nm over +-600 nm,
    each plane normalised."""
    psf = make_psf(name)
    z = np.arange(-600.0, 600.0 + 1e-6, step)
    c = R * PX / 2
    img = psf.images(np.full(z.size, c), np.full(z.size, c), z, (R, R), PX)
    return img / img.sum(axis=(1, 2), keepdims=True)


def _beads(truth: np.ndarray, n: int, photons: float, background: float, seed: int):
    """``n`` beads of ``truth`` with Poisson noise, photons less the background."""
    rng = np.random.default_rng(seed)
    return rng.poisson(photons * truth + background, (n, *truth.shape)) - background


def _departure(model: np.ndarray, truth: np.ndarray, photons: float) -> float:
    """Chi-square per voxel of a bright emitter's image from ``model`` against its image from
    the noise-free ``truth`` made a model the same way (background 10 photons/px)."""
    ref = clean_average(truth)
    return float(np.mean((photons * (model - ref)) ** 2 / (photons * ref + 10.0)))


def _model(beads: np.ndarray, window: int) -> np.ndarray:
    return model_stack(beads.mean(axis=0), window)


def _choose(beads: np.ndarray, background: float) -> int:
    keep = np.ones(beads.shape, dtype=bool)
    share = np.ones((beads.shape[0], 1, 1, 1))
    return choose_window(beads, keep, share, lambda fit: np.maximum(fit + background, 1.0)).window


@pytest.mark.parametrize(
    ("name", "step", "photons", "n"),
    [
        ("astig", 10.0, 3000.0, 4),  # dim beads, fine steps: much noise to smooth away
        ("astig", 10.0, 300000.0, 9),  # bright beads: little
        ("dh-analytic", 20.0, 20000.0, 6),
    ],
)
def test_the_beads_choose_a_window_near_the_best_one(name, step, photons, n):
    """Held-out beads pick a window whose model lies about as close to the true PSF as the
    best candidate's, and closer than the fixed ~80 nm window's where that one is not best:
    the window follows the beads' noise, not a constant."""
    truth = _truth(name, step)
    beads = _beads(truth, n, photons, 10.0, seed=1)
    chosen = _choose(beads, 10.0)
    candidates = [w for w in (0, *WINDOWS) if w <= truth.shape[0]]
    far = {w: _departure(_model(beads, w), truth, photons) for w in candidates}
    best = min(far.values())
    assert far[chosen] <= 1.1 * best, (chosen, far)
    fixed = fallback_window(step, truth.shape[0])
    if far[fixed] > 1.2 * best:
        assert far[chosen] < far[fixed], (chosen, fixed, far)


def test_dimmer_beads_are_smoothed_over_more_planes():
    """The noise a model must be rid of grows as the beads dim, the flattening a window costs
    does not: dimmer beads choose a wider window."""
    truth = _truth("astig", 10.0)
    dim = _choose(_beads(truth, 4, 3000.0, 10.0, seed=2), 10.0)
    bright = _choose(_beads(truth, 4, 300000.0, 10.0, seed=2), 10.0)
    assert dim > bright, (dim, bright)


def test_one_bead_cannot_choose():
    truth = _truth("astig", 10.0)
    with pytest.raises(ValueError, match="two beads"):
        _choose(_beads(truth, 1, 3000.0, 10.0, seed=3), 10.0)
