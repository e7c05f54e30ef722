"""The smooth trend of a frame's background across the field (detect.background_trend)."""

from __future__ import annotations

import numpy as np

from sparseloc.detect import background_trend


def _frames(level, spots=(), n=20, shape=(96, 96), seed=0):
    """Poisson frames of a background ``level`` (H, W) with Gaussian spots (row, col, photons)."""
    rows, cols = np.indices(shape)
    mean = np.broadcast_to(level, shape).astype(float).copy()
    for r, c, a in spots:
        mean += a * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 3.0**2)) / (2 * np.pi * 9)
    return np.random.default_rng(seed).poisson(mean, (n, *shape)).astype(float)


def test_a_tilt_under_bright_spots_is_found():
    cols = np.arange(96)[None, :] * np.ones((96, 1))
    tilt = 10.0 + 15.0 * cols / 95
    spots = [(24, 24, 2e5), (24, 72, 2e5), (72, 24, 2e5), (72, 72, 2e5)]
    trend = background_trend(_frames(tilt, spots))
    truth = tilt - tilt.mean()
    assert np.abs(trend - truth).max() < 1.0, np.abs(trend - truth).max()


def test_a_flat_background_has_no_trend_whatever_lies_on_it():
    spots = [(20, 15, 3e5), (50, 18, 3e5), (80, 12, 3e5)]  # all on the left
    assert not background_trend(_frames(np.full((96, 96), 10.0), spots)).any()


def test_light_over_the_whole_field_leaves_no_trend_to_read():
    """Beads every 12 px leave fewer than 6 blocks dark: the tilt beneath them is not read
    (a fit through their blocks would read their light as one)."""
    tilt = 10.0 + 15.0 * np.arange(96)[None, :] / 95 * np.ones((96, 1))
    spots = [(r, c, 2e5) for r in range(6, 96, 12) for c in range(6, 96, 12)]
    assert not background_trend(_frames(tilt, spots)).any()


def test_a_read_variance_map_and_a_narrow_frame():
    """An sCMOS read-variance map (photons^2 per pixel) is averaged per block; a frame 24 px
    wide gets 6 blocks across, and its tilt along that side is read."""
    tilt = 10.0 + 12.0 * np.arange(24)[None, :] / 23 * np.ones((96, 1))
    frames = _frames(tilt, shape=(96, 24))
    rv = np.full((96, 24), 2.0)
    trend = background_trend(frames, read_variance=rv)
    truth = tilt - tilt.mean()
    assert np.abs(trend - truth).max() < 1.0, np.abs(trend - truth).max()


def _defocusing(level, spots, n=30, shape=(128, 128), seed=0):
    """Poisson frames of a background ``level`` (H, W) with spots (row, col, photons) that
    widen away from the middle frame, as beads defocus through a scan."""
    rows, cols = np.indices(shape)
    rng = np.random.default_rng(seed)
    out = np.empty((n, *shape))
    for k in range(n):
        s = 1.5 + 4.0 * abs(k - (n - 1) / 2) / ((n - 1) / 2)
        mean = np.broadcast_to(level, shape).astype(float).copy()
        for r, c, a in spots:
            mean += (
                a * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)
            )
        out[k] = rng.poisson(mean)
    return out


_GRID = [(r, c, 2e4) for r in (22, 64, 106) for c in (22, 64, 106)]


def test_an_illumination_profile_no_plane_follows_is_read_from_the_steady_blocks():
    """A Gaussian illumination (5 -> 40 photons/px) leaves too few blocks under any plane;
    the blocks whose light stays through the scan (the beads' changes) carry its shape."""
    rows, cols = np.indices((128, 128))
    light = 5.0 + 35.0 * np.exp(-((rows - 64) ** 2 + (cols - 84) ** 2) / (2 * 60.0**2))
    trend = background_trend(_defocusing(light, _GRID))
    err = trend - (light - light.mean())
    assert np.abs(err).max() < 2.5, np.abs(err).max()
    assert np.sqrt(np.mean(err**2)) < 0.5


def test_defocusing_beads_on_a_flat_background_read_no_profile():
    """Beads every 16 px leave no plane enough unlit blocks; the steady blocks between them
    are flat."""
    spots = [(r, c, 2e4) for r in range(8, 128, 16) for c in range(8, 128, 16)]
    assert not background_trend(_defocusing(np.full((128, 128), 10.0), spots, seed=1)).any()


def test_steady_blocks_on_one_side_of_the_field_draw_no_profile():
    """Beads over the right 60 % of the field leave the steady blocks on its left: a spline
    through them would extrapolate the profile across the beads (worse than none)."""
    rows, cols = np.indices((128, 128))
    light = 5.0 + 35.0 * np.exp(-((rows - 64) ** 2 + (cols - 40) ** 2) / (2 * 40.0**2))
    spots = [(r, c, 2e4) for r in range(8, 128, 16) for c in range(56, 128, 12)]
    assert not background_trend(_defocusing(light, spots)).any()


def test_the_steady_halos_of_a_crowded_flat_scan_are_no_illumination_profile(shared_data):
    """storm-analysis's astigmatic bead scan (18 beads on a flat 10 photons/px): too little
    of it is unlit for a plane, and the beads' halos that stay through the scan make its
    steady blocks differ by 1-2 photons/px, bead by bead, not across the field."""
    import tifffile

    stack = tifffile.imread(shared_data / "storm_analysis_sim" / "astig" / "beads_zscan.tif")
    assert not background_trend(stack.astype(float) - 100.0).any()
