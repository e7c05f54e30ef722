"""The background estimates know the camera's noise: read noise and EMCCD excess noise widen
the spread below the mean, and a correction for shot noise alone leaves the background low."""

import numpy as np
import pytest

from sparseloc.config import LocalizeParams
from sparseloc.detect import spatial_background, temporal_background, temporal_backgrounds
from sparseloc.pipeline import _frames_and_backgrounds
from sparseloc.psf.analytic import GaussianAstigPSF

READ_SD = 5.75  # photons (e- at QE 1): an sCMOS camera's read noise


def _scmos(rng, lam: float, shape) -> np.ndarray:
    return rng.poisson(lam, shape) + rng.normal(0.0, READ_SD, shape)


@pytest.mark.parametrize("lam", [3.0, 10.0, 50.0])
def test_a_spatial_background_with_read_noise_is_unbiased(lam):
    frame = _scmos(np.random.default_rng(1), lam, (256, 256))
    got = spatial_background(frame, read_variance=READ_SD**2)
    assert abs(got.mean() - lam) < 0.03 * lam + 0.1
    # a read-variance map is averaged over each block: the same number for a flat map
    as_map = spatial_background(frame, read_variance=np.full(frame.shape, READ_SD**2))
    assert np.allclose(as_map, got)


def test_shot_noise_alone_would_leave_the_background_low():
    frame = _scmos(np.random.default_rng(2), 10.0, (256, 256))
    assert spatial_background(frame).mean() < 8.0
    assert spatial_background(frame, read_variance=READ_SD**2).mean() > 9.7


def test_a_temporal_background_with_emccd_noise_is_nearly_unbiased():
    rng = np.random.default_rng(3)
    n = rng.poisson(50.0, (60, 32, 32))
    frames = rng.gamma(np.maximum(n, 1e-9), 1.0) * (n > 0)  # electrons / EM gain
    poisson = temporal_background(frames).mean()
    emccd = temporal_background(frames, noise_factor=2.0).mean()
    assert poisson < 48.8
    assert abs(emccd - 50.0) < 0.6
    both = temporal_backgrounds(frames, np.array([30]), 30, noise_factor=2.0)[0]
    assert np.allclose(both, temporal_background(frames, noise_factor=2.0))


@pytest.mark.parametrize("background", ["spatial", "temporal"])
def test_the_pipeline_gives_the_estimates_the_cameras_noise(background):
    rng = np.random.default_rng(4)
    movie = _scmos(rng, 10.0, (8, 48, 48))
    p = LocalizeParams(
        pixel_size=100.0, noise="scmos", read_variance=READ_SD**2, background=background
    )
    model = GaussianAstigPSF()
    bgs = [b for _, _, b in _frames_and_backgrounds(lambda a, b: movie[a:b], 8, 0, 8, 4, p, model)]
    assert abs(np.mean(bgs) - 10.0) < 0.5
