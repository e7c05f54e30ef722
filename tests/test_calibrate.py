"""Bead calibration end to end on simulated z-scans: registration, rejection, errors, files, CLI.

Bead scans are rendered with the analytic double helix (``dh-analytic``): 100 nm pixels,
20000 photons per bead per frame, background 10 photons, z from -500 to 500 nm in 20 nm steps,
camera offset 100 ADU (the simulator's default camera).
"""

from __future__ import annotations

import warnings

import h5py
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.calibrate import calibrate_beads, read_z_file
from sparseloc.calibrate_output import calibration_summary
from sparseloc.cli import app
from sparseloc.detect import spatial_background
from sparseloc.io.calibration import load_calibration, read_calibration_info, save_calibration
from sparseloc.io.tables import read_parquet
from sparseloc.io.tiff import write_tiff
from sparseloc.io.truth import read_truth_csv
from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.simulate import bead_scan_truth, simulate

PX = 100.0
Z_STEP = 20.0
ZP = np.arange(-500.0, 500.0 + 1e-9, Z_STEP)  # 51 frames
SHAPE = (120, 120)
OFFSET = 100.0  # ADU, the simulator's camera offset
PHOTONS = 20000.0

runner = CliRunner()


def simulate_scan(model, positions, z_offsets=None, photons=PHOTONS, seed=0):
    """uint16 movie of beads at ``positions`` (nm, (B, 2) x then y) scanned through ZP."""
    positions = np.asarray(positions, float).reshape(-1, 2)
    photons = np.broadcast_to(np.asarray(photons, float), (len(positions),))
    offsets = np.zeros(len(positions)) if z_offsets is None else np.asarray(z_offsets, float)
    truth = pd.concat(
        [
            bead_scan_truth(positions[i : i + 1], ZP, photons[i], offsets[i : i + 1])
            for i in range(len(positions))
        ],
        ignore_index=True,
    )
    sim = simulate(
        model,
        scene=truth,
        n_frames=ZP.size,
        shape=SHAPE,
        pixel_size=PX,
        background=10.0,
        seed=seed,
    )
    assert sim.movie.dtype == np.uint16
    return sim.movie


def ncc_planes(a, b):
    """Normalised cross-correlation of two stacks, plane by plane."""
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    return (a * b).sum(axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def centred(model, z, size):
    """Unit-photon images of an emitter at the centre of a ``size`` x ``size`` window."""
    c = np.full(len(z), size * PX / 2)
    return model.images(c, c, z, (size, size), PX)


def match_truth(beads, positions):
    """Index of the true bead nearest to each row of the bead table."""
    d = np.hypot(
        beads["x_nm"].to_numpy()[:, None] - positions[None, :, 0],
        beads["y_nm"].to_numpy()[:, None] - positions[None, :, 1],
    )
    return np.argmin(d, axis=1)


@pytest.fixture(scope="module")
def model():
    return make_psf("dh-analytic")


@pytest.fixture(scope="module")
def scan(model):
    """Nine beads on a 35 px grid, sub-pixel positions, heights spread over +-40 nm."""
    rng = np.random.default_rng(1)
    grid = np.array([25.0, 60.0, 95.0]) * PX
    positions = np.array([(x, y) for y in grid for x in grid]) + rng.uniform(-50, 50, (9, 2))
    offsets = rng.uniform(-40.0, 40.0, 9)
    movie = simulate_scan(model, positions, offsets, seed=1)
    return {"movie": movie, "positions": positions, "offsets": offsets}


@pytest.fixture(scope="module")
def cal(scan):
    return calibrate_beads(scan["movie"], PX, Z_STEP, offset=OFFSET)


# -- a good scan ---------------------------------------------------------------------------


def test_every_bead_is_found_and_used(cal, scan):
    b = cal.beads
    assert len(b) == 9
    assert cal.n_used == 9 and b["used"].all()
    assert (b["reason"] == "").all()
    assert len(set(match_truth(b, scan["positions"]))) == 9  # one row per true bead
    # photons per plane inside the ROI (measured 19956 .. 20070)
    assert np.allclose(b["photons"], PHOTONS, rtol=0.03)
    assert cal.params["n_beads_found"] == 9 and cal.params["n_beads_used"] == 9


def test_bead_heights_are_recovered(cal, scan):
    # data ~ model(z_frame + shift_z): shift_z is the bead's offset minus the beads' mean.
    # Measured up to 0.5 nm (0.8 nm over 8 seeds); tolerance 3 nm.
    b = cal.beads
    j = match_truth(b, scan["positions"])
    fitted = b["shift_z_nm"].to_numpy()
    true = scan["offsets"][j]
    err = (fitted - fitted.mean()) - (true - true.mean())
    assert np.abs(err).max() < 3.0, err
    assert abs(fitted.mean()) < 1e-6  # the scan's z frame is kept


def test_bead_positions_are_recovered(cal, scan):
    # x_nm, y_nm are native coordinates of the emitter (the model's centre included).
    # Measured up to 0.4 nm (1.5 nm over 8 seeds); tolerance 5 nm.
    b = cal.beads
    j = match_truth(b, scan["positions"])
    dx = b["x_nm"].to_numpy() - scan["positions"][j, 0]
    dy = b["y_nm"].to_numpy() - scan["positions"][j, 1]
    assert np.abs(dx).max() < 5.0, dx
    assert np.abs(dy).max() < 5.0, dy


def test_calibrated_model_matches_the_true_one(cal, scan, model):
    psf = cal.psf
    assert isinstance(psf, SplinePSF)
    nz, rows, cols = cal.average.shape
    assert rows == cols and rows % 2 == 1
    assert nz == cal.z.size and np.allclose(np.diff(cal.z), Z_STEP)
    assert psf.z_range == (cal.z[0], cal.z[-1])
    assert -500.0 <= cal.z[0] < -400.0 and 400.0 < cal.z[-1] <= 500.0  # trimmed by |dz| max
    assert np.allclose(cal.average.sum(axis=(1, 2)), 1.0)
    assert cal.content_hash == psf.content_hash
    # The ROI holds the PSF: the true model leaves < 2 % of its light outside (measured 0-0.4 %).
    truth = centred(model, cal.z + scan["offsets"].mean(), rows)
    assert truth.sum(axis=(1, 2)).min() > 0.98
    # Per plane over the ROI, the calibration's z frame is the beads' mean height.
    # Measured min NCC 0.9998 (0.9997 over 8 seeds); tolerance 0.995.
    ncc = ncc_planes(centred(psf, cal.z, rows), truth)
    assert ncc.min() > 0.995, ncc.min()
    # each registered bead against the average (measured min 0.998)
    assert cal.bead_ncc.shape == (9, nz)
    assert cal.bead_ncc.min() > 0.99


def test_bead_stack_moved_along_z_continues_past_its_end_planes():
    # A stack whose light changes linearly from plane to plane, moved by a fraction of a step:
    # its end planes are read beyond the data, along the end slopes, and come out exact.
    from sparseloc.calibrate import _shift_stack

    rng = np.random.default_rng(0)
    base, slope = rng.uniform(5, 10, (7, 7)), rng.uniform(-1, 1, (7, 7))
    k = np.arange(12.0)[:, None, None]
    stack = base + k * slope
    for dz_steps in (0.15, -0.15, 0.4):
        moved = _shift_stack(stack, np.array([0.0, 0.0, dz_steps * Z_STEP]), PX, Z_STEP)
        # data ~ model(z + dz): the model's plane k is the data's plane k - dz / step
        # measured within 1e-4 of a plane's change (the spline's boundary, six planes out)
        err = np.abs(moved - (base + (k - dz_steps) * slope)).max()
        assert err < 1e-3 * np.abs(slope).max(), err


def test_a_model_serves_planes_just_past_its_range_along_its_end_slope(model):
    # A bead a fifth of a step above the beads' mean reaches past the model's last plane: the
    # model continues along its end slope there, as the beads' stacks do, rather than repeat
    # its end plane (measured: 0.6 % of the light off, against 3.6 % for the end plane).
    from sparseloc.calibrate_error import EXTRAPOLATE_STEPS, served_images, served_planes

    step = 50.0
    table = SplinePSF.from_model(model, PX, roi=31, z_step=step, z_range=(-400.0, 400.0))
    planes = np.arange(-400.0, 400.0 + 1e-6, step)
    z = planes + 0.95 * EXTRAPOLATE_STEPS * step
    idx = served_planes(z, table.z_range, planes)
    assert idx.tolist() == list(range(planes.size))  # the last plane too, not one beyond
    assert served_planes(planes + 0.3 * step, table.z_range, planes).size == planes.size - 1
    c = np.full(1, 15.5 * PX)
    past = served_images(table, c, c, z[-1:], (31, 31))
    true = model.images(c, c, z[-1:], (31, 31), PX)
    end = table.images(c, c, np.array([400.0]), (31, 31), PX)
    err, repeated = (np.abs(a - true).sum() / true.sum() for a in (past, end))
    assert err < 0.5 * repeated, (err, repeated)


def test_model_keeps_every_plane_of_beads_at_one_height(model):
    # Beads at one height: their fitted heights differ by the fits' noise, a small fraction of
    # a step, and the model keeps the scan's end planes (each bead's extrapolated that little).
    rng = np.random.default_rng(4)
    grid = np.array([25.0, 60.0, 95.0]) * PX
    positions = np.array([(x, y) for y in grid for x in grid]) + rng.uniform(-50, 50, (9, 2))
    cal = calibrate_beads(simulate_scan(model, positions, seed=4), PX, Z_STEP, offset=OFFSET)
    assert cal.n_used == 9
    spread = cal.params["bead_height_spread_nm"]
    assert 0 < spread < 0.2 * Z_STEP, spread  # measured 0.48 nm
    assert cal.z[0] == ZP[0] and cal.z[-1] == ZP[-1]
    from sparseloc.calibrate_output import calibration_summary

    assert "mean height" not in "\n".join(calibration_summary(cal))  # no plane was dropped
    # the three planes at each end against the true model (measured min NCC 0.9998)
    rows = cal.average.shape[1]
    ends = np.r_[cal.z[:3], cal.z[-3:]]
    ncc = ncc_planes(centred(cal.psf, ends, rows), centred(model, ends, rows))
    assert ncc.min() > 0.995, ncc


def test_calibrated_model_is_centred_on_the_emitter(cal):
    # The model's lateral origin: the centroid of its z-averaged image at the emitter.
    size = 31
    c = size * PX / 2 + 23.0
    n = cal.z.size
    img = cal.psf.images(np.full(n, c), np.full(n, c - 41.0), cal.z, (size, size), PX)
    proj = img.mean(axis=0)
    rows, cols = np.indices(proj.shape)
    cx = ((cols + 0.5) * PX * proj).sum() / proj.sum()
    cy = ((rows + 0.5) * PX * proj).sum() / proj.sum()
    # measured 0.1 nm; a half-pixel slip would be 50 nm
    assert abs(cx - c) < 5.0 and abs(cy - (c - 41.0)) < 5.0, (cx - c, cy - c + 41.0)


def test_z0_slice_and_gain(scan):
    cal = calibrate_beads(scan["movie"], PX, Z_STEP, offset=OFFSET, gain=2.0, z0_slice=0)
    # z = (slice - z0_slice) * z_step: planes now run from 0 (before trimming) upwards
    assert 0.0 <= cal.z[0] < 100.0 and cal.z[-1] > 900.0
    assert np.allclose(np.diff(cal.z), Z_STEP)
    # photons = (ADU - offset) * gain
    assert np.allclose(cal.beads["photons"], 2 * PHOTONS, rtol=0.03)


# -- rejection -----------------------------------------------------------------------------

# (col, row) in pixels: three good beads, one at the edge, a pair 17 px apart (closer than
# the ROI, but their cores do not overlap: both are used, each cleaned of the other's light),
# a bright bead. The ROI is given so that the reasons do not hang on the default ROI
# estimate. A pair much closer (13 px) is found as one bead: see
# test_rejected_outlier_leaves_no_trace.
ROI = 21
REJECT_PX = np.array([(30, 30), (90, 30), (30, 90), (4, 60), (75, 75), (92, 75), (62, 105)])
REJECT_PHOTONS = np.array([PHOTONS] * 6 + [2 * PHOTONS])
EXPECTED = ["", "", "", "edge", "", ""]


@pytest.fixture(scope="module")
def crowded(model):
    positions = REJECT_PX * PX + 37.0
    movie = simulate_scan(model, positions, photons=REJECT_PHOTONS, seed=5)
    return positions, movie


def check_reasons(beads, positions, last):
    j = match_truth(beads, positions)
    assert sorted(j) == list(range(7))
    reasons = dict(zip(j, beads["reason"], strict=True))
    used = dict(zip(j, beads["used"], strict=True))
    for k, want in enumerate([*EXPECTED, last]):
        assert reasons[k] == want, (k, reasons[k])
        assert used[k] == (want == "")


def test_edge_close_and_saturated_beads_are_rejected(crowded):
    positions, movie = crowded
    # Peaks: about 850 ADU for 20000 photons, 1520 ADU for the bright bead.
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, saturation=1300.0, roi_size=ROI)
    assert cal.params["roi_size_px"] == ROI
    check_reasons(cal.beads, positions, "saturated")
    assert cal.n_used == 5
    assert cal.bead_ncc.shape[0] == 5
    assert cal.params["n_beads_with_neighbours"] == 2
    # the pair's neighbour light was removed: each agrees with the model as the others do
    assert np.median(cal.bead_ncc, axis=1).min() > 0.99


def test_bead_at_the_integer_type_maximum_is_saturated(crowded):
    positions, movie = crowded
    movie = movie.copy()
    col, row = REJECT_PX[6]
    movie[25, row + 2, col + 3] = 65535  # uint16: saturation defaults to 65535
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, roi_size=ROI)
    check_reasons(cal.beads, positions, "saturated")
    # without the clipped pixel the bright bead is fine
    cal = calibrate_beads(crowded[1], PX, Z_STEP, offset=OFFSET, roi_size=ROI)
    check_reasons(cal.beads, positions, "")


# -- errors --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def one_bead(model):
    return simulate_scan(model, [(6037.0, 5963.0)], seed=2)


def _departure(cal, model):
    """The calibrated model's relative departure from the simulator's PSF over its z range,
    each plane scaled to its best match, at the best z offset (the model's z origin is the
    beads' mean height): the model's systematic error and the noise it holds."""
    z = cal.z[3:-3]
    b = centred(model, z, 31)

    def departure(dz):
        a = centred(cal.psf, z - dz, 31)
        scale = np.sum(a * b, axis=(1, 2)) / np.sum(a * a, axis=(1, 2))
        return float(np.sqrt(np.sum((a * scale[:, None, None] - b) ** 2) / np.sum(b**2)))

    return min(departure(dz) for dz in np.arange(-50.0, 50.1, 2.5))


def test_the_model_error_of_an_exact_psf_does_not_grow_with_fewer_beads(model, scan):
    """A model follows part of each bead's own noise; how much depends on the number of beads
    and on the smoothing, so it is measured, not assumed. Beads rendered from the PSF itself
    leave an unsmoothed model no systematic error: two beads and nine read the same small one,
    below the model's whole departure from the PSF (mostly the noise it holds). A plain
    average's ``n / (n - 1)`` read two beads' error as nearly twice their departure. (The
    smoothing along z is off: the beads choose it by their number, and what it flattens is
    a systematic error.)"""
    kw = dict(offset=OFFSET, z_smooth=False)
    two = calibrate_beads(simulate_scan(model, scan["positions"][[0, 8]], seed=1), PX, Z_STEP, **kw)
    nine = calibrate_beads(scan["movie"], PX, Z_STEP, **kw)
    assert two.n_used == 2 and nine.n_used == 9
    errors = [c.params["model_error"] for c in (two, nine)]
    assert abs(errors[0] - errors[1]) < 0.01, errors
    for c in (two, nine):
        assert c.params["model_error"] < 0.5 * _departure(c, model), c.n_used
        assert 0.0 < c.params["model_self_influence"] < 1.0 / c.n_used


def test_the_beads_smooth_their_model_along_z_as_far_as_their_noise_asks(model, scan, cal):
    """Each plane of a bead average carries its own photon noise; the beads choose how far to
    smooth it along z (held-out beads against the others' model), and the model then lies
    much closer to the PSF than the unsmoothed average, closer than a fixed window of a few
    planes brings it."""
    raw = calibrate_beads(scan["movie"], PX, Z_STEP, offset=OFFSET, z_smooth=False)
    assert raw.params["z_smooth_planes"] == 0
    assert cal.params["z_smooth_planes"] > 0
    assert _departure(cal, model) < 2.0 / 3.0 * _departure(raw, model)


def test_one_bead_calibrates_and_says_its_model_error_is_not_cross_checked(scan, one_bead, cal):
    """A z-stack of a single bead is a common calibration: it gives the bead's model, close
    to the many beads' one, with a warning that no other bead measured its error."""
    from sparseloc.calibrate_output import calibration_summary

    one = calibrate_beads(one_bead, PX, Z_STEP, offset=OFFSET)
    assert one.n_used == 1
    assert "one bead" in one.params["bead_warning"]
    assert cal.params["bead_warning"] == ""
    text = "\n".join(calibration_summary(one))
    assert "warning: calibrated from one bead" in text
    assert "model error: not measured" in text
    # the one bead's model renders the many beads' PSF: an emitter at each z, same light
    z = np.linspace(one.z[2], one.z[-3], 7)
    a = one.psf.images([1000.0] * 7, [1000.0] * 7, z, (21, 21), PX)
    b = cal.psf.images([1000.0] * 7, [1000.0] * 7, z, (21, 21), PX)
    diff = np.abs(a - b).sum(axis=(1, 2)) / b.sum(axis=(1, 2))
    assert diff.max() < 0.15, diff


def test_errors(scan, one_bead):
    movie = scan["movie"]
    with pytest.raises(ValueError, match="only one frame"):
        calibrate_beads(movie[:1], PX, Z_STEP, offset=OFFSET)
    for step in (0.0, -20.0, np.nan):
        with pytest.raises(ValueError, match="--z-step must be a positive number"):
            calibrate_beads(movie, PX, step, offset=OFFSET)
    with pytest.raises(ValueError, match="give the stage step with --z-step"):
        calibrate_beads(movie, PX, None, offset=OFFSET)
    with pytest.raises(ValueError, match="NaN"):
        bad = movie.astype(float)
        bad[3, 50, 50] = np.nan
        calibrate_beads(bad, PX, Z_STEP, offset=OFFSET)
    with pytest.raises(ValueError, match="the z file lists 50 frames but the stack has 51"):
        calibrate_beads(movie, PX, z=ZP[:-1], offset=OFFSET)
    with pytest.raises(ValueError, match="must be 3-D"):
        calibrate_beads(movie[0], PX, Z_STEP)
    with pytest.raises(ValueError, match="at least 4 z planes"):
        calibrate_beads(movie[:3], PX, Z_STEP, offset=OFFSET)
    with pytest.raises(ValueError, match="pixel-size"):
        calibrate_beads(movie, -1.0, Z_STEP, offset=OFFSET)
    with pytest.raises(ValueError, match="only 1 usable bead"):
        calibrate_beads(one_bead, PX, Z_STEP, offset=OFFSET, min_beads=2)
    # Pure noise. Seed 0: for about 1 seed in 10 a noise peak 2-3 px from the frame edge
    # passes detection and the message is 'found 1 bead(s) but none is usable (1 edge)'.
    rng = np.random.default_rng(0)
    noise = (rng.poisson(10.0, (ZP.size, *SHAPE)) + OFFSET).astype(np.uint16)
    with pytest.raises(ValueError, match="no beads found"):
        calibrate_beads(noise, PX, Z_STEP, offset=OFFSET)


def test_default_roi_does_not_depend_on_sub_pixel_phase(model):
    # Regression: the only bead whose extent is measured (>= 40 px from the edges) sits on a
    # pixel corner, so no pixel rounds to ring 0 of its radial profile. An empty ring once made
    # the profile NaN, the extent 0 and the ROI 11 px (a truncated, useless model).
    movie = simulate_scan(model, [(6000.0, 6000.0), (3000.0, 3000.0)], seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, min_beads=1)
    assert cal.params["roi_size_px"] >= 15  # 17-23 px for beads at other phases


def test_rejected_outlier_leaves_no_trace(model):
    # A pair 13 px apart is found as one bright 'bead' (the first reference), later rejected.
    positions = np.array([(30, 30), (90, 30), (30, 90), (75, 75), (88, 75)]) * PX + 37.0
    movie = simulate_scan(model, positions, seed=5)
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
    used = cal.beads[cal.beads["used"]]
    assert len(used) == 3
    # the scan's z frame is the used beads' mean height (all at the same height here)
    assert abs(used["shift_z_nm"].mean()) < 5.0


# -- z files -------------------------------------------------------------------------------


def test_read_z_file_storm_analysis_style(tmp_path):
    path = tmp_path / "z.csv"
    order = np.array([3, 0, 2, 1])  # rows need not be in frame order
    z_um = np.array([-0.05, -0.03, -0.01, 0.01])
    valid = np.array([1, 1, 0, 1])
    pd.DataFrame({"frame_0based": order, "valid": valid[order], "z_um": z_um[order]}).to_csv(
        path, index=False
    )
    z, ok = read_z_file(path)
    assert np.allclose(z, [-50.0, -30.0, -10.0, 10.0])
    assert ok.tolist() == [True, True, False, True]
    with pytest.raises(ValueError, match="does not exist"):
        read_z_file(tmp_path / "missing.csv")


def test_invalid_frame_of_the_z_file_is_left_out(tmp_path, scan, model):
    movie = scan["movie"].copy()
    movie[25] = 65535  # a ruined frame: saturates every bead if it were used
    z_um = ZP / 1000.0
    z_um[25] = z_um[24]  # and a repeated z: refused if it were used
    valid = np.ones(ZP.size, int)
    valid[25] = 0
    path = tmp_path / "scan_z.csv"
    rows = np.random.default_rng(0).permutation(ZP.size)
    pd.DataFrame({"frame_0based": rows, "valid": valid[rows], "z_um": z_um[rows]}).to_csv(
        path, index=False
    )
    z, ok = read_z_file(path)
    assert ok.sum() == ZP.size - 1 and not ok[25]
    cal = calibrate_beads(movie, PX, z=z, valid=ok, offset=OFFSET)
    assert cal.n_used == 9
    with pytest.raises(ValueError, match="with each frame's z given"):
        calibrate_beads(movie, PX, z=z, valid=ok, offset=OFFSET, z0_slice=3)
    assert np.allclose(np.diff(cal.z), Z_STEP)  # the 40 nm gap was resampled onto 20 nm
    truth = centred(model, cal.z + scan["offsets"].mean(), cal.average.shape[1])
    assert ncc_planes(centred(cal.psf, cal.z, cal.average.shape[1]), truth).min() > 0.99


# -- calibration files ---------------------------------------------------------------------


def test_save_load_round_trip(tmp_path, cal):
    path = save_calibration(cal, tmp_path / "psf.h5")
    assert path.is_file()
    loaded = load_calibration(path)
    assert isinstance(loaded, SplinePSF)
    assert loaded.content_hash == cal.content_hash
    assert loaded.pixel_size == PX and loaded.z_range == cal.psf.z_range
    assert loaded.centre == pytest.approx(cal.psf.centre)
    rng = np.random.default_rng(8)
    x = 1050.0 + rng.uniform(-100, 100, 20)
    y = 1050.0 + rng.uniform(-100, 100, 20)
    z = rng.uniform(*cal.psf.z_range, 20)
    assert np.array_equal(
        loaded.images(x, y, z, (21, 21), PX), cal.psf.images(x, y, z, (21, 21), PX)
    )
    info = read_calibration_info(path)
    assert info["format"] == "sparseloc-psf" and info["model"] == "spline"
    assert info["pixel_size_nm"] == PX
    assert info["z_min_nm"] == cal.z[0] and info["z_max_nm"] == cal.z[-1]
    assert info["z_step_nm"] == pytest.approx(Z_STEP)
    assert info["content_hash"] == cal.content_hash
    assert info["n_beads_used"] == 9 and info["has_pupil"] is False
    assert info["params"]["roi_size_px"] == cal.params["roi_size_px"]
    with h5py.File(path, "r") as f:
        assert list(f["beads/reason"].asstr()[()]) == [""] * 9
    # make_psf takes the file
    via = make_psf(str(path))
    assert isinstance(via, SplinePSF) and via.content_hash == cal.content_hash
    # asking for a model the file does not hold
    with pytest.raises(ValueError, match="no fitted pupil"):
        load_calibration(path, model="pupil")
    with pytest.raises(ValueError, match="no pupil was fitted"):
        save_calibration(cal, tmp_path / "p.h5", model="pupil")


def test_bad_calibration_files(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(ValueError, match="not a sparseloc PSF calibration"):
        load_calibration(other)
    with pytest.raises(ValueError, match="not a sparseloc PSF calibration"):
        make_psf(str(other))
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(ValueError, match="not a readable HDF5"):
        load_calibration(text)
    with pytest.raises(ValueError, match="does not exist"):
        load_calibration(tmp_path / "missing.h5")
    with pytest.raises(ValueError, match="does not exist"):
        read_calibration_info(tmp_path / "missing.h5")


# -- command line --------------------------------------------------------------------------


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_cli_calibrate_writes_model_and_figure(tmp_path, scan):
    tif = write_tiff(tmp_path / "beads.tif", scan["movie"], pixel_size=PX)
    out = tmp_path / "cal.h5"
    res = invoke(
        "calibrate", tif, "--pixel-size", PX, "--z-step", Z_STEP, "--offset", OFFSET, "-o", out
    )
    assert res.exit_code == 0, res.output
    assert out.is_file() and out.with_suffix(".png").is_file()
    assert "9 of 9 beads used" in res.stdout
    psf = make_psf(str(out))
    assert isinstance(psf, SplinePSF) and psf.pixel_size == PX
    info = read_calibration_info(out)
    assert info["params"]["source"] == "beads.tif"
    assert psf.content_hash in res.stdout
    # a table localized with that file records the hash calibrate printed (one definition)
    movie = write_tiff(tmp_path / "movie.tif", scan["movie"][25:26, 20:60, 20:60], pixel_size=PX)
    locs = tmp_path / "locs.parquet"
    res = invoke("localize", movie, "--psf", out, "--offset", OFFSET, "-o", locs)
    assert res.exit_code == 0, res.output
    assert read_parquet(locs)[1]["psf_hash"] == psf.content_hash


def test_cli_calibrate_needs_a_z_step_or_file(tmp_path, scan):
    tif = write_tiff(tmp_path / "beads.tif", scan["movie"][:5], pixel_size=PX)
    out = tmp_path / "cal.h5"
    res = invoke("calibrate", tif, "--pixel-size", PX, "-o", out)
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    assert "--z-step" in lines[0] and "--z-file" in lines[0]
    assert "Traceback" not in res.output
    assert not out.exists() and not out.with_suffix(".png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["beads.tif"]


def test_cli_calibrate_refuses_a_z0_slice_beside_a_z_file(tmp_path, scan):
    # each frame's z is given by the file: a slice at z = 0 would contradict it
    tif = write_tiff(tmp_path / "beads.tif", scan["movie"][:6], pixel_size=PX)
    zf = tmp_path / "z.csv"
    pd.DataFrame({"frame_0based": range(6), "z_um": np.arange(6) * 0.02}).to_csv(zf, index=False)
    out = tmp_path / "cal.h5"
    res = invoke("calibrate", tif, "--pixel-size", PX, "--z-file", zf, "--z0-slice", 3, "-o", out)
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    assert "--z0-slice" in lines[0] and "--z-file" in lines[0], lines[0]
    assert not out.exists()


def test_cli_calibrate_reports_a_bad_z_file(tmp_path, scan):
    tif = write_tiff(tmp_path / "beads.tif", scan["movie"][:6], pixel_size=PX)
    zf = tmp_path / "z.csv"
    pd.DataFrame({"frame_0based": range(5), "z_um": np.arange(5) * 0.02}).to_csv(zf, index=False)
    out = tmp_path / "cal.h5"
    res = invoke("calibrate", tif, "--pixel-size", PX, "--z-file", zf, "-o", out)
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    assert "5 frames" in lines[0] and "6" in lines[0]
    assert not out.exists()


def test_cli_localize_refuses_another_pixel_size(tmp_path, cal, scan):
    path = save_calibration(cal, tmp_path / "cal.h5")
    movie = write_tiff(tmp_path / "movie.tif", scan["movie"][:2])
    out = tmp_path / "locs.csv"
    res = invoke("localize", movie, "--psf", path, "--pixel-size", 160, "-o", out)
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr
    assert "100 nm" in lines[0] and "160 nm" in lines[0]
    assert not out.exists()


# -- truth files and background ------------------------------------------------------------


def test_read_truth_csv_storm_analysis_style(tmp_path):
    path = tmp_path / "truth.csv"
    pd.DataFrame(
        {
            "frame_0based": [0, 0, 3],
            "x_px": [0.0, 10.25, 63.5],
            "y_px": [0.0, 5.5, -0.5],
            "z_um": [0.1, -0.25, 0.0],
            "photons_sum": [1000.0, 2500.0, 400.0],
        }
    ).to_csv(path, index=False)
    df = read_truth_csv(path, pixel_size=160.0)
    assert list(df.columns[:5]) == ["frame", "x_nm", "y_nm", "z_nm", "photons"]
    assert df["frame"].tolist() == [0, 0, 3]
    # 0.0 is the centre of the first pixel: x_nm = (x_px + 0.5) * pixel_size
    assert np.allclose(df["x_nm"], [80.0, 1720.0, 10240.0])
    assert np.allclose(df["y_nm"], [80.0, 960.0, 0.0])
    assert np.allclose(df["z_nm"], [100.0, -250.0, 0.0])
    assert np.allclose(df["photons"], [1000.0, 2500.0, 400.0])
    with pytest.raises(ValueError, match="pixel size"):
        read_truth_csv(path)


def test_spatial_background_of_a_flat_frame_with_spots():
    rng = np.random.default_rng(0)
    rows, cols = np.indices((128, 128))
    lam = np.full((128, 128), 20.0)
    for r, c in [(20, 30), (64, 64), (100, 40), (40, 100), (110, 110)]:
        lam += 3000.0 * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / 4.5) / (2 * np.pi * 2.25)
    frame = rng.poisson(lam).astype(float)
    bg = spatial_background(frame)
    assert bg.shape == frame.shape
    rel = np.abs(bg / 20.0 - 1.0)
    # measured: 99.4 % of pixels within 5 %, worst 6 %, median 20.1
    assert np.mean(rel < 0.05) > 0.9
    assert rel.max() < 0.15
    assert np.median(bg) == pytest.approx(20.0, rel=0.02)


def test_shifted_psf_moves_the_model():
    from sparseloc.psf.base import ShiftedPSF

    base = make_psf("dh-analytic")
    moved = ShiftedPSF(base, 30.0, -20.0, 50.0)
    lo, hi = base.z_range
    assert moved.z_range == (lo - 50.0, hi - 50.0)
    a, da = moved.images(700.0, 800.0, 0.0, (15, 15), PX, derivatives=True)
    b, db = base.images(730.0, 780.0, 50.0, (15, 15), PX, derivatives=True)
    np.testing.assert_allclose(a, b)
    np.testing.assert_allclose(da, db)


def test_pupil_fit_saved_in_the_calibration_frame(tmp_path):
    from sparseloc.psf import AstigmatismMask, PupilPSF

    truth = PupilPSF(
        AstigmatismMask(0.15), na=1.4, wavelength=600.0, n_immersion=1.5, z_range=(-700.0, 700.0)
    )
    planes = np.arange(-500.0, 500.0 + 1e-6, 50.0)
    pos = np.array([(2500.0, 2500.0), (6500.0, 2500.0), (2500.0, 6500.0)]) + 33.0
    sim = simulate(
        truth,
        scene=bead_scan_truth(pos, planes, 20000.0),
        n_frames=planes.size,
        shape=(90, 90),
        pixel_size=PX,
        background=10.0,
        seed=2,
    )
    cal = calibrate_beads(
        sim.movie,
        PX,
        50.0,
        offset=100.0,
        fit_pupil=True,
        pupil_options={"na": 1.4, "wavelength": 600.0, "n_immersion": 1.5, "max_order": 4},
    )
    assert abs(cal.pupil.coefficients[(2, 2)] - 0.15 / np.sqrt(6)) < 0.02
    path = save_calibration(cal, tmp_path / "cal.h5", model="pupil")
    pupil = load_calibration(path)
    spline = load_calibration(path, model="spline")
    c = (spline.centre[1] + 0.5) * PX, (spline.centre[0] + 0.5) * PX
    nr = spline.stack.shape[1]
    for z in (-300.0, 0.0, 300.0):
        a = pupil.images(*c, z, (nr, nr), PX)[0]
        b = spline.images(*c, z, (nr, nr), PX)[0]
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.97
    # the summary names the model the file serves, as the tables that use it record it
    recorded = read_calibration_info(path)["content_hash"]
    assert recorded == pupil.content_hash != spline.content_hash
    assert f"hash {recorded}" in calibration_summary(cal, None, recorded)[0]
    # each model carries its own error on the beads into the solvers, the pupil's through
    # the spline table the pipeline renders it with
    from sparseloc.config import LocalizeParams
    from sparseloc.pipeline import work_model_for
    from sparseloc.solvers.variance import model_error_of

    # the pupil is the simulator's own, so its error on the beads is noise: measured 0-0.2 %
    # (read as attributes: model_error_of reads a missing one as 0)
    own = cal.pupil.model_error
    assert 0 <= own < 0.01 and own != pytest.approx(cal.params["model_error"], rel=1e-3)
    assert model_error_of(spline) == pytest.approx(cal.params["model_error"])
    assert pupil.model_error == pytest.approx(own) and pupil.error_table is not None
    narrowed = LocalizeParams(pixel_size=PX, z_range=(-300.0, 300.0))
    for work in (
        work_model_for(pupil, LocalizeParams(pixel_size=PX)),
        work_model_for(pupil, narrowed),
    ):
        assert work is not pupil and work.model_error == pytest.approx(own)
        assert work.error_table is pupil.error_table
    # a file written before the pupil's own error was measured: the spline's figure serves
    import h5py

    with h5py.File(path, "r+") as f:
        del f["pupil"].attrs["model_error"]
        del f["pupil/error_table"]
    older = load_calibration(path)
    assert model_error_of(older) == pytest.approx(cal.params["model_error"])
    assert older.error_table is None
    pupil_line = next(x for x in calibration_summary(cal) if "pupil fit" in x)
    assert f"the beads depart from it by {100 * own:.1f} %" in pupil_line


def test_cli_calibrate_refuses_a_pixel_size_that_contradicts_the_file(tmp_path, scan):
    tif = write_tiff(tmp_path / "beads.tif", scan["movie"][:6], pixel_size=PX)
    out = tmp_path / "cal.h5"
    res = invoke("calibrate", tif, "--pixel-size", 2 * PX, "--z-step", 20, "-o", out)
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "metadata" in lines[0], res.stderr
    assert f"{2 * PX:g}" in lines[0] and f"{PX:g}" in lines[0]
    assert not out.exists()


def test_all_beads_saturated_says_what_to_do():
    rng = np.random.default_rng(0)
    movie = rng.poisson(20.0, (8, 60, 60)).astype(np.uint16) + 100
    movie[:, 28:33, 28:33] = 65535
    with pytest.raises(ValueError, match=r"saturated.*lower the laser power"):
        calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, roi_size=15)


def test_localize_windows_follow_a_calibrated_psf(cal):
    from sparseloc.config import window_for as _window_for

    px = cal.psf.pixel_size
    window, margin = _window_for(cal.psf, px, None, None)
    assert margin * px >= cal.psf.support_radius(px, 0.9)
    assert window == max(11, 2 * margin + 9)
    assert _window_for(cal.psf, px, 15, 4) == (15, 4)  # the user's choice wins
    assert _window_for(make_psf("dh-analytic"), px, None, None) == (11, 3)


def test_saved_table_keeps_oversampling_and_z_range(tmp_path, cal):
    import dataclasses

    table = SplinePSF.from_model(
        make_psf("astig-gauss"), PX, roi=15, z_step=20.0, oversample=2, z_range=(-300.0, 300.0)
    )
    table = SplinePSF(
        table.stack,
        PX,
        table.z,
        centre=table.centre,
        z_range=(-200.0, 200.0),
        normalise=False,
        oversample=2,
    )
    path = save_calibration(dataclasses.replace(cal, psf=table), tmp_path / "t.h5")
    back = load_calibration(path)
    assert back.oversample == 2 and back.z_range == (-200.0, 200.0)
    args = (700.0, 760.0, 50.0, (15, 15), PX)
    np.testing.assert_array_equal(back.images(*args), table.images(*args))
    assert back.content_hash == table.content_hash


def test_non_finite_z_for_a_valid_frame_is_refused(tmp_path, scan):
    z = np.arange(scan["movie"].shape[0], dtype=float) * Z_STEP
    z[3] = np.nan
    with pytest.raises(ValueError, match="non-finite z"):
        calibrate_beads(scan["movie"], PX, z=z, offset=OFFSET)
    path = tmp_path / "z.csv"
    path.write_text("\n".join(["1,0.0", "1,0.02", "1,0.04"]))
    with pytest.raises(ValueError, match="no header"):
        read_z_file(path)


# -- known bead positions (--beads) ----------------------------------------------------------

#: The light of the test PSF sits this far (nm, x and y) from its emitter, as in measured PSFs.
LIGHT_OFFSET = (30.0, -40.0)


@pytest.fixture(scope="module")
def offset_scan(model):
    """Four beads imaged through a PSF whose light is displaced from the emitter."""
    from sparseloc.psf.base import ShiftedPSF

    shifted = ShiftedPSF(model, *LIGHT_OFFSET)
    positions = np.array([[3000.0, 3000.0], [8000.0, 3050.0], [3020.0, 8000.0], [8010.0, 8040.0]])
    return {"movie": simulate_scan(shifted, positions, seed=4), "positions": positions}


def test_known_bead_positions_put_the_model_origin_on_the_emitter(offset_scan):
    movie, truth = offset_scan["movie"], offset_scan["positions"]
    plain = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
    assert plain.params["lateral_origin"] == "centroid"
    j = match_truth(plain.beads, truth)
    dxy = plain.beads[["x_nm", "y_nm"]].to_numpy() - truth[j]
    assert np.allclose(dxy.mean(axis=0), LIGHT_OFFSET, atol=5.0)  # the centroid's offset
    # each plane's light centroid from the origin: about 0 (a symmetric PSF) without the
    # positions, the PSF's displacement with them
    wander = plain.params["centroid_over_z_nm"]
    assert max(map(abs, wander["x"] + wander["y"])) < 6.0, wander
    known = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, beads=truth)
    assert known.params["lateral_origin"] == "beads" and known.params["n_beads_known"] == 4
    assert np.allclose(known.params["centroid_offset_nm"], LIGHT_OFFSET, atol=3.0)
    wander = known.params["centroid_over_z_nm"]
    assert np.allclose(wander["x"], LIGHT_OFFSET[0], atol=8.0), wander
    assert np.allclose(wander["y"], LIGHT_OFFSET[1], atol=8.0), wander
    j = match_truth(known.beads, truth)
    assert np.abs(known.beads[["x_nm", "y_nm"]].to_numpy() - truth[j]).max() < 3.0
    # an emitter rendered by the model has its light where the bead's light was
    size, c = 31, 31 * PX / 2
    img = known.psf.images(
        np.full(known.z.size, c), np.full(known.z.size, c), known.z, (size, size), PX
    )
    proj = img.mean(axis=0)
    rows, cols = np.indices(proj.shape)
    cx = ((cols + 0.5) * PX * proj).sum() / proj.sum() - c
    cy = ((rows + 0.5) * PX * proj).sum() / proj.sum() - c
    assert abs(cx - LIGHT_OFFSET[0]) < 5.0 and abs(cy - LIGHT_OFFSET[1]) < 5.0, (cx, cy)


def test_bead_position_files(tmp_path, offset_scan):
    from sparseloc.calibrate import read_bead_positions

    truth = offset_scan["positions"]
    nm = tmp_path / "beads_nm.csv"
    pd.DataFrame({"x_nm": np.repeat(truth[:, 0], 3), "y_nm": np.repeat(truth[:, 1], 3)}).to_csv(
        nm, index=False
    )
    assert np.allclose(read_bead_positions(nm, PX), np.unique(truth, axis=0))  # one per bead
    pxf = tmp_path / "beads_px.csv"
    pd.DataFrame({"x_px": truth[:, 0] / PX - 0.5, "y_px": truth[:, 1] / PX - 0.5}).to_csv(
        pxf, index=False
    )
    assert np.allclose(read_bead_positions(pxf, PX), np.unique(truth, axis=0))
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"x": [1.0], "y": [2.0]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="needs columns x_nm, y_nm"):
        read_bead_positions(bad, PX)
    far = truth.copy()
    far[1] += 450.0  # 4.5 px from every bead
    with pytest.raises(ValueError, match="more than 2 px from every bead found"):
        calibrate_beads(offset_scan["movie"], PX, Z_STEP, offset=OFFSET, beads=far)
    dark = np.vstack([truth, [[600.0, 11400.0]]])  # a corner without a bead
    with pytest.raises(ValueError, match=r"\(600, 11400\) nm .* more than 2 px"):
        calibrate_beads(offset_scan["movie"], PX, Z_STEP, offset=OFFSET, beads=dark)


def test_a_bead_listed_twice_or_outside_the_stack_is_no_refusal(offset_scan):
    """A bead file may list a bead twice, or beads of a larger field than the stack holds:
    the twin is one bead, the position outside is left out."""
    truth = offset_scan["positions"]
    listed = np.vstack([truth, truth[:1], [[30000.0, 5000.0]]])
    cal = calibrate_beads(offset_scan["movie"], PX, Z_STEP, offset=OFFSET, beads=listed)
    assert cal.params["lateral_origin"] == "beads" and cal.params["n_beads_known"] == 4
    assert np.allclose(cal.params["centroid_offset_nm"], LIGHT_OFFSET, atol=3.0)


def test_the_match_tolerance_follows_the_beads_scatter():
    """A listed position may lie 2 px from its bead found, or farther where the beads found
    scatter more about their positions (an engineered PSF's light cut by the detection's
    disc): the 99 % distance of that scatter. One position far off among close ones does not
    widen it."""
    from sparseloc.calibrate import _match_tolerance

    def tol(dist):  # each position alone near its own bead found
        d = np.full((len(dist), len(dist)), 100.0)
        d[np.diag_indices_from(d)] = dist
        return _match_tolerance(d, np.ones(len(dist), int), merge=9.0)

    assert tol([0.1, 0.2, 0.1, 4.5]) == 2.0
    assert tol([1.2, 1.4, 1.5, 1.0, 2.1, 0.7]) == pytest.approx(3.03 / 1.177 * 1.3)
    assert tol([0.1, 12.0, 12.0]) == 2.0  # beyond the merge radius: not the scatter


def test_listed_beads_the_detection_merges_are_beads(model):
    """Two beads 1 um apart are found as one bead between them (the detection's merge
    radius), 5 px from either listed position: matching the positions to the beads found
    would refuse a correct file. With the positions known, each listed bead is a bead where
    its light lies, and the merged detection between them is none."""
    from sparseloc.psf.base import ShiftedPSF

    shifted = ShiftedPSF(model, *LIGHT_OFFSET)
    pair = np.array([[5000.0, 6000.0], [6000.0, 6000.0]])
    positions = np.vstack([[[2500.0, 2500.0], [9000.0, 2550.0], [2520.0, 9500.0]], pair])
    movie = simulate_scan(shifted, positions, seed=6)
    plain = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
    midpoint = pair.mean(axis=0) + LIGHT_OFFSET
    xy = plain.beads[["x_nm", "y_nm"]].to_numpy()
    assert np.hypot(*(xy - midpoint).T).min() < 200.0  # the detection merges the pair
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET, beads=positions)
    xy = cal.beads[["x_nm", "y_nm"]].to_numpy()
    for bead in pair + LIGHT_OFFSET:
        assert np.hypot(*(xy - bead).T).min() < 100.0, (bead, xy)
    assert np.hypot(*(xy - midpoint).T).min() > 300.0
    assert cal.params["lateral_origin"] == "beads"
    assert np.allclose(cal.params["centroid_offset_nm"], LIGHT_OFFSET, atol=10.0)


def test_calibrate_cli_with_bead_positions(tmp_path, offset_scan):
    stack = tmp_path / "beads.tif"
    write_tiff(stack, offset_scan["movie"], pixel_size=PX)
    good = tmp_path / "beads.csv"
    t = offset_scan["positions"]
    pd.DataFrame({"x_nm": t[:, 0], "y_nm": t[:, 1]}).to_csv(good, index=False)
    base = ["calibrate", str(stack), "--pixel-size", "100", "--z-step", "20", "--offset", "100"]
    out = tmp_path / "psf.h5"
    res = runner.invoke(app, [*base, "-o", str(out), "--beads", str(good)])
    assert res.exit_code == 0, res.output
    assert "origin on 4 known bead position(s)" in res.output
    assert "model origin: beads; each plane's light centroid lies" in res.output
    assert read_calibration_info(out)["params"]["lateral_origin"] == "beads"
    bad = tmp_path / "bad.csv"
    pd.DataFrame({"x_nm": [50.0]}).to_csv(bad, index=False)
    out2 = tmp_path / "psf2.h5"
    res = runner.invoke(app, [*base, "-o", str(out2), "--beads", str(bad)])
    assert res.exit_code == 2 and "needs columns x_nm, y_nm" in res.output, res.output
    assert not out2.exists()


def test_tables_record_the_hash_that_calibrate_prints(tmp_path, cal, scan):
    # One hash definition: a table made with a calibration file records the file's hash.
    from sparseloc.pipeline import LocalizeParams, localize

    path = save_calibration(cal, tmp_path / "psf.h5")
    model = make_psf(str(path))
    frame = scan["movie"][25:26, 20:60, 20:60].astype(float) - OFFSET
    res = localize(frame, model, LocalizeParams(pixel_size=PX, method="frame"))
    assert (
        res.metadata["psf_hash"] == cal.content_hash == read_calibration_info(path)["content_hash"]
    )


# -- the model error -------------------------------------------------------------------------


def test_model_error_is_measured_and_saved(tmp_path, cal):
    # nine beads of one PSF: what is left beyond the Poisson noise is small
    e = cal.params["model_error"]
    assert 0.0 <= e < 0.03
    assert len(cal.params["model_error_z"]) == cal.z.size
    loaded = load_calibration(save_calibration(cal, tmp_path / "psf.h5"))
    assert loaded.model_error == pytest.approx(e)


def test_a_pair_seen_as_one_bead_is_the_only_outlier_in_a_crowded_field(model):
    """Two beads 700 nm apart are found as one (the detection merges the lobes of a double
    helix). An outlier test on whole ROIs drops the pair's neighbour too (its ROI holds the
    pair's light), and on a random bead slide the neighbours' light hides the pairs. Each
    bead's own model error on the voxels the average keeps singles out the pair alone, and
    the reason says what it is (its image repeats at the pair's offset)."""
    rng = np.random.default_rng(1)
    grid = np.array([18.0, 43.0, 68.0, 93.0]) * PX  # 2.5 um apart: every ROI sees neighbours
    pos = np.array([(x, y) for y in grid for x in grid]) + rng.uniform(-50, 50, (16, 2))
    movie = simulate_scan(model, np.vstack([pos, pos[5] + [700.0, 0.0]]), seed=3)
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
    assert (cal.beads["reason"] == "outlier").sum() == 0
    outliers = cal.beads[cal.beads["reason"] == "two beads found as one"]
    assert len(outliers) == 1
    found = outliers[["x_nm", "y_nm"]].to_numpy()[0]
    assert min(np.hypot(*(found - pos[5])), np.hypot(*(found - pos[5] - [700.0, 0.0]))) < 300.0
    assert cal.n_used == 15
    # the pair is gone and the 15 beads' cleaned ROIs hold no repeated image
    assert cal.params["cluster_warning"] == ""


def test_a_cluster_found_as_one_bead_is_named(model, cal, one_bead):
    """Beads closer than the detection can part are found as one bead, and alone they make
    a model of the cluster: the calibration says so (the image repeats at the beads' fixed
    offset in every plane), where a single bead and a field of separate beads say nothing."""
    from sparseloc.calibrate_output import calibration_summary

    grid = [(6000.0 + dx, 6000.0 + dy) for dx in (-400.0, 400.0) for dy in (-400.0, 400.0)]
    cluster = calibrate_beads(simulate_scan(model, grid, seed=4), PX, Z_STEP, offset=OFFSET)
    assert cluster.n_used == 1
    said = cluster.params["cluster_warning"]
    assert "the bead used holds one image" in said and "repeated 800 nm away" in said, said
    assert "warning: the bead used holds one image" in "\n".join(calibration_summary(cluster))
    assert cal.params["cluster_warning"] == ""
    single = calibrate_beads(one_bead, PX, Z_STEP, offset=OFFSET)
    assert single.params["cluster_warning"] == ""


def test_the_summary_says_why_beads_at_several_heights_narrow_the_z_range(cal, one_bead):
    """Beads at several heights (a tilted slide) leave the model shorter than the scan at
    each end, and emitters there are flagged z_edge: the summary says why."""
    from sparseloc.calibrate_output import calibration_summary

    said = "\n".join(calibration_summary(cal))
    assert cal.z[0] > ZP[0] and cal.z[-1] < ZP[-1]
    spread = cal.params["bead_height_spread_nm"]
    assert 20.0 < spread < 60.0  # the fixture's beads lie within +-40 nm
    assert f"up to {spread:.0f} nm above or below their mean height" in said
    assert f"of the scan's {ZP[0]:.0f}..{ZP[-1]:.0f}" in said
    single = calibrate_beads(one_bead, PX, Z_STEP, offset=OFFSET)
    assert "mean height" not in "\n".join(calibration_summary(single))


def test_repeated_light_sees_fixed_offsets_not_moving_lobes():
    """Two lobes turning with z (one double helix) repeat at no fixed offset; the same image
    twice, 7 px apart (two equal beads), repeats at half the central peak; a spot that
    stretches with z (astigmatism) has no side peak at all."""
    from sparseloc.calibrate_crowd import REPEATED_LIGHT, repeated_light

    yy, xx = np.mgrid[:31, :31] - 15.0
    angles = np.linspace(0.0, np.pi, 41)

    def lobes(a, cx=0.0):
        dx, dy = 4.0 * np.cos(a), 4.0 * np.sin(a)
        g = lambda x0, y0: np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / 4.0)  # noqa: E731
        return g(cx + dx, dy) + g(cx - dx, -dy)

    one = np.stack([lobes(a) for a in angles])
    two = np.stack([lobes(a, -3.5) + lobes(a, 3.5) for a in angles])
    stretch = np.stack(
        [np.exp(-(xx**2) / (2 * (1.5 + t) ** 2) - yy**2 / (2 * (3.5 - t) ** 2)) for t in
         np.linspace(0.0, 2.0, 41)]
    )  # fmt: skip
    share_one, _ = repeated_light(one)
    share_two, lag_two = repeated_light(two)
    assert share_one < REPEATED_LIGHT < share_two
    assert abs(share_two - 0.5) < 0.05 and abs(lag_two - 7.0) < 0.5
    assert repeated_light(stretch)[0] < 0.05


def test_dim_beads_on_a_crowded_slide_are_all_used(model):
    """Nine beads of 2,000 photons, 3 um apart, the first row and column 1.8 um from the
    frame's edges. Past half the spacing the ROI's light profile reads a ring's light from
    the few pixels nearer this bead than its neighbours; with dim beads that reading is the
    noise, the ROI grew past the spacing, and the beads near the edge were left out."""
    grid = np.array([1800.0, 4800.0, 7800.0])
    pos = np.array([(x, y) for y in grid for x in grid])
    pos = pos + np.random.default_rng(1).uniform(-50, 50, pos.shape)
    movie = simulate_scan(model, pos, photons=2000.0, seed=1)
    cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
    assert cal.n_used == 9
    assert cal.params["bead_roi_size_px"] <= 31  # within the spacing (30 px) and a pixel


def test_beads_near_the_edge_of_a_dark_slide_are_used_in_a_smaller_roi():
    """Six bright beads on a background of 1 photon/px, five of them 1.4 um from the frame's
    edges. With so little noise the light profile of an astigmatic pupil model reaches far:
    an ROI of 99 % of the light would not fit around the beads near the edge and leave one
    bead. The ROI shrinks, down to the radius holding 97 %, until they fit."""
    from sparseloc.calibrate_crowd import ROI_ENERGY_LEAST

    edge, far = 1400.0, SHAPE[0] * PX - 1400.0
    pos = [(edge, edge), (6000.0, edge), (far, edge), (edge, 6000.0), (6000.0, 6000.0),
           (far, far)]  # fmt: skip
    truth = bead_scan_truth(pos, ZP, PHOTONS)
    sim = simulate(
        make_psf("astig"), scene=truth, n_frames=ZP.size, shape=SHAPE, pixel_size=PX,
        background=1.0, seed=1,
    )  # fmt: skip
    cal = calibrate_beads(sim.movie, PX, Z_STEP, offset=OFFSET)
    assert cal.n_used == 6, cal.beads
    assert cal.params["roi_energy_fraction"][0] >= ROI_ENERGY_LEAST
    assert cal.params["model_error"] < 0.1


def test_dim_beads_far_apart_get_the_model_of_their_light_not_of_their_noise(model):
    """Four beads 6 um apart, 30 px from the frame's edges. Dim beads' light beyond the
    lobes is below a model's pixel noise, and the light profile's noise, summed ring by ring,
    takes the ROI out to the room the field leaves: the model ends where the light does, no
    larger than bright beads' of the same optics."""
    pos = np.array([(x, y) for y in (3000.0, 9000.0) for x in (3000.0, 9000.0)])
    pos = pos + np.random.default_rng(2).uniform(-50, 50, pos.shape)
    rois, cals = {}, {}
    for photons in (2000.0, 20000.0):
        movie = simulate_scan(model, pos, photons=photons, seed=1)
        cals[photons] = cal = calibrate_beads(movie, PX, Z_STEP, offset=OFFSET)
        assert cal.n_used == 4
        rois[photons] = cal.params["roi_size_px"]
    assert rois[2000.0] <= rois[20000.0], rois
    # the figure's model panels (the model at the emitter in the average's frame) lie on the
    # average, though the cut model is smaller than it
    from sparseloc.calibrate_output import calibration_summary
    from sparseloc.plotting import _calibration_model

    dim = cals[2000.0]
    assert dim.psf.stack.shape[1] < dim.average.shape[1]
    assert f"model {rois[2000.0]} x {rois[2000.0]} px" in calibration_summary(dim)[0]
    idx = np.arange(0, dim.z.size, 5)
    middle = (dim.average.shape[1] - 1) / 2
    for img in (_calibration_model(dim, idx)[1], dim.average[idx]):
        img = np.clip(img, 0.0, None)
        rows, cols = np.indices(img.shape[1:])
        r = (img * rows).sum(axis=(1, 2)) / img.sum(axis=(1, 2))
        c = (img * cols).sum(axis=(1, 2)) / img.sum(axis=(1, 2))
        assert np.abs(r - middle).max() < 1.5 and np.abs(c - middle).max() < 1.5


def test_two_beads_that_see_each_other_give_a_model_centred_on_them(model):
    """Two beads 2.5 um apart, each in the other's ROI: a fixed two rounds of removing the
    neighbour's modelled light leave part of it in the model, its origin off the beads; the
    rounds go on until no bead moves."""
    pos = np.array([(4767.0, 5977.0), (7267.0, 6031.0)])
    cal = calibrate_beads(simulate_scan(model, pos, seed=3), PX, Z_STEP, offset=OFFSET)
    assert cal.n_used == 2
    found = cal.beads[["x_nm", "y_nm"]].to_numpy()
    off = np.array([found[np.argmin(np.hypot(*(found - p).T))] - p for p in pos])
    assert np.abs(off).max() < 5.0, off
    assert cal.params["model_error"] < 0.1


@pytest.fixture(scope="module")
def two_psfs():
    """Nine beads of which half have wider lobes than the other half: no one model fits them
    all."""
    positions = np.array([(x, y) for y in (25.0, 60.0, 95.0) for x in (25.0, 60.0, 95.0)]) * PX
    narrow = simulate_scan(make_psf("dh-analytic"), positions[::2], seed=3)
    wide = simulate_scan(make_psf("dh-analytic", lobe_sigma=190.0), positions[1::2], seed=4)
    return (narrow.astype(np.int64) + wide.astype(np.int64) - int(OFFSET)).astype(np.uint16)


@pytest.fixture(scope="module")
def mixed(two_psfs):
    return calibrate_beads(two_psfs, PX, Z_STEP, offset=OFFSET)


def test_model_error_grows_when_the_beads_differ(cal, mixed):
    assert mixed.n_used >= 6
    assert mixed.params["model_error"] > max(0.05, 3 * cal.params["model_error"])


def test_the_model_error_is_kept_pixel_by_pixel_and_saved(tmp_path, cal, mixed):
    """The beads' residual variance about the model, pixel by pixel, is the model's error
    table (rendered like the PSF, per photon squared): never negative, far larger where the
    beads differ, and written to the calibration file."""
    table = cal.psf.error_table
    assert table is not None and np.all(table.stack >= 0)
    assert table.z_range[0] <= -300 and table.z_range[1] >= 300
    loaded = load_calibration(save_calibration(cal, tmp_path / "psf.h5"))
    np.testing.assert_allclose(loaded.error_table.stack, table.stack)
    assert loaded.error_table.centre == pytest.approx(table.centre)

    def error_var(c):  # an emitter of 10,000 photons at z = 0, summed over its window
        return c.psf.error_table.render([1000.0], [1000.0], [0.0], [1e8], (21, 21), PX).sum()

    assert error_var(mixed) > 10 * error_var(cal)


def test_dim_beads_leave_the_error_table_their_error_not_their_noise(model):
    """Beads rendered from the PSF itself leave the model little systematic error. Dim beads'
    excess is mostly noise about zero pixel by pixel, and clipped at zero it would keep its
    positive half everywhere: an allowance for an error the beads do not show, which costs
    the count selection dim emitters. The table holds no more than the error the beads'
    residuals show overall (the model error)."""
    pos = np.array([(x, y) for y in (3000.0, 9000.0) for x in (3000.0, 9000.0)])
    pos = pos + np.random.default_rng(2).uniform(-50, 50, pos.shape)
    cal = calibrate_beads(simulate_scan(model, pos, photons=2000.0, seed=1), PX, Z_STEP,
                          offset=OFFSET)  # fmt: skip
    z = np.array([-400.0, -200.0, 0.0, 200.0, 400.0])
    at = (np.full(z.size, 3000.0), np.full(z.size, 3000.0), z)
    table = cal.psf.error_table
    allowance = 0.0 if table is None else table.render(*at, np.ones(z.size), (41, 41), PX).sum()
    signal = (cal.psf.images(*at, (41, 41), PX) ** 2).sum()
    assert np.sqrt(allowance / signal) < cal.params["model_error"] + 0.02


def test_calibration_too_far_from_its_beads_is_refused(monkeypatch, two_psfs):
    import sparseloc.calibrate as calibrate_module

    # the beads of two PSFs leave the model an error, above a low bar
    monkeypatch.setattr(calibrate_module, "MAX_MODEL_ERROR", 0.01)
    with pytest.raises(ValueError, match=r"depart from their average by \d+ %"):
        calibrate_beads(two_psfs, PX, Z_STEP, offset=OFFSET)


@pytest.mark.parametrize(
    ("scene", "density", "refusal"),
    [
        ("filament", 0.3, "none is usable"),
        ("filament", 1.0, "only 1 usable bead"),
        ("uniform", 1.0, "the beads depart from their average"),
    ],
)
def test_a_single_molecule_movie_is_named_as_not_a_bead_scan(model, scene, density, refusal):
    """The third walk-through: calibrating a blinking movie advised "image more beads in the
    field". Each refusal that such a movie reaches now says the spots change from frame to
    frame, and a bead scan's spots agree from frame to frame."""
    sim = simulate(model, scene=scene, n_frames=30, shape=(64, 64), density=density, seed=3)
    with pytest.raises(ValueError, match=refusal) as info:
        calibrate_beads(sim.movie, PX, Z_STEP, offset=sim.camera.offset)
    assert "is the file a single-molecule movie?" in str(info.value)
    assert "image more beads" not in str(info.value)
    assert "check the z step" not in str(info.value)


def test_a_bead_scans_frames_agree_at_about_one(scan, cal):
    from sparseloc.calibrate import SCAN_AGREEMENT, _frame_agreement, _whole_rois
    from sparseloc.calibrate_scan import read_scan

    data = read_scan(scan["movie"], PX, Z_STEP, None, None, None, OFFSET, 1.0, None)
    centres = scan["positions"][:, ::-1] / PX - 0.5  # (row, col) px
    rois = _whole_rois(data, centres, cal.params["bead_roi_size_px"] // 2)
    assert len(rois) >= 4
    assert _frame_agreement(rois, data.background) > max(SCAN_AGREEMENT, 0.97)


def test_the_figures_model_panels_are_half_a_step_off_every_plane(cal):
    """The fifth walk-through: the last plane's "change over half a step" panel was blank (half
    a step above it was clipped back onto it)."""
    from sparseloc.plotting import _calibration_model

    idx = np.array([0, len(cal.z) // 2, len(cal.z) - 1])
    _, _, zs = _calibration_model(cal, idx)
    assert np.allclose(np.abs(zs - cal.z[idx]), cal.psf.z_step / 2)
    assert np.all(zs >= cal.psf.z_range[0]) and np.all(zs <= cal.psf.z_range[1])


def test_a_double_helix_on_small_pixels_is_one_bead_each():
    """A double helix's ring of lobe positions spans more pixels on 65 nm pixels than on
    100 nm ones: the detection's smoothing at a fixed 3 px found its lobes as beads (each
    pair then too close, or averaged into a model 73 % off its beads)."""
    px = 65.0
    positions = np.array([(2000.0, 2000.0), (6000.0, 2100.0), (2100.0, 6000.0), (6000.0, 6000.0)])
    positions += 13.0
    truth = bead_scan_truth(positions, ZP, PHOTONS)
    sim = simulate(
        make_psf("dh-analytic"), scene=truth, n_frames=ZP.size, shape=(124, 124),
        pixel_size=px, background=10.0, seed=0,
    )  # fmt: skip
    cal = calibrate_beads(sim.movie, px, Z_STEP, offset=OFFSET)
    assert cal.n_used == 4 and len(cal.beads) == 4
    found = cal.beads[["x_nm", "y_nm"]].to_numpy()
    d = np.linalg.norm(found[:, None, :] - positions[None, :, :], axis=2)
    assert d.min(axis=1).max() < px  # each found bead is one of the true ones


def test_the_bead_detections_scale_is_physical_below_100_nm_pixels():
    from sparseloc.calibrate import detection_sigma

    assert detection_sigma(65.0) == pytest.approx(300.0 / 65.0)
    assert detection_sigma(PX) == detection_sigma(160.0) == 3.0  # unchanged from 100 nm up


def test_a_random_crowded_bead_field_keeps_its_neighbours_light_out_of_the_model():
    """22 beads at random on a 16 x 16 um field: most ROIs hold other beads' light, some of
    it from beads at the frame's edge or too close to another to be used. Without modelling
    the edge beads' light and leaving each bead's voxels that disagree with the other beads'
    out of the average and of the error's measurement, the model erred by 38 % of the
    signal (and a count selection allowing for that keeps few dim emitters)."""
    rng = np.random.default_rng(3)
    positions = rng.uniform(300, 15700, (22, 2))
    truth = bead_scan_truth(positions, ZP, PHOTONS)
    sim = simulate(
        make_psf("dh-analytic"), scene=truth, n_frames=ZP.size, shape=(160, 160),
        pixel_size=PX, background=10.0, seed=3,
    )  # fmt: skip
    cal = calibrate_beads(sim.movie, PX, Z_STEP, offset=OFFSET)
    assert cal.n_used >= 6
    assert cal.params["n_beads_with_neighbours"] >= 1
    assert cal.psf.model_error < 0.05


def test_crowded_beads_at_one_height_keep_their_neighbours_light_out_of_the_end_planes():
    """Four beads 3 um apart at one height: their fitted heights differ by a fraction of a
    step, so a neighbour's end plane lies just beyond the model's range. Its light was left
    in the bead's ROI there, and the model's first and last planes erred by 18 and 12 %
    once they were kept (the other planes by at most 3 %)."""
    positions = np.array([(x, y) for x in (4500.0, 7500.0) for y in (4500.0, 7500.0)]) + 27.0
    cal = calibrate_beads(
        simulate_scan(make_psf("dh-analytic"), positions, seed=5), PX, Z_STEP, offset=OFFSET
    )
    assert cal.n_used == 4 and cal.params["n_beads_with_neighbours"] == 4
    assert cal.z[0] == ZP[0] and cal.z[-1] == ZP[-1]
    per_plane = np.asarray(cal.params["model_error_z"])
    ends = per_plane[[0, 1, -2, -1]]
    # measured: ends at most 2.0 %, the rest at most 3.4 %
    assert ends.max() <= max(per_plane[2:-2].max(), 0.02), per_plane


def test_the_robust_average_leaves_out_only_a_crowded_beads_odd_voxels():
    from sparseloc.calibrate import robust_average

    rng = np.random.default_rng(0)
    shape = np.exp(-(np.hypot(*np.mgrid[-5:6, -5:6]) ** 2) / 8.0)[None] * 500.0  # (1, 11, 11)
    stacks = rng.poisson(np.broadcast_to(shape, (6, 1, 11, 11))).astype(float)
    stacks[2] *= 2.0  # a brighter bead weighs more, as in the plain mean
    clean_mean = stacks.mean(axis=0)
    stacks[4, 0, :3, :3] += 400.0  # a neighbour's light in bead 4's corner
    plain = stacks.mean(axis=0)
    suspects = np.array([False, False, False, False, True, False])
    robust = robust_average(stacks, suspects)
    corner = (0, slice(0, 3), slice(0, 3))
    assert np.abs(plain[corner] - clean_mean[corner]).min() > 60.0
    assert np.abs(robust[corner] - clean_mean[corner]).max() < 30.0
    # no suspect: the plain mean
    np.testing.assert_allclose(robust_average(stacks, np.zeros(6, bool)), plain)


def _astig_beads_160nm():
    """Nine astigmatic beads on 160 nm pixels (the pupil model samples coarsely there) and a
    sparse movie of the same optics (ADU, offset ``OFFSET``)."""
    px = 160.0
    astig = make_psf("astig")
    lo, hi = astig.z_range
    planes = np.arange(lo - 200.0, hi + 200.0 + 1e-6, Z_STEP)
    grid = np.array([2500.0, 6400.0, 10300.0])
    beads = np.array([(x, y) for y in grid for x in grid]) + 17.0
    beads += np.random.default_rng(5).uniform(-60.0, 60.0, beads.shape)  # sub-pixel phases
    stack = simulate(
        make_psf("astig", z_range=(lo - 200.0, hi + 200.0)),
        scene=bead_scan_truth(beads, planes, PHOTONS), n_frames=planes.size, shape=(80, 80),
        pixel_size=px, background=10.0, seed=1,
    )  # fmt: skip
    movie = simulate(astig, n_frames=12, shape=(80, 80), pixel_size=px, density=0.3, seed=2)
    return px, stack.movie, movie


def test_a_fine_grid_from_noisy_beads_is_as_sharp_as_their_psf():
    """Noisy beads (EMCCD, 160 nm pixels, 10,000 photons on a background of 30) on the
    half-pixel grid: a clip of its dark nodes' noise at zero in every round raises a floor
    that the beads' fitted backgrounds cannot see, and a model broader than the PSF reads
    photons high and backgrounds low. The grid keeps the pixel model's floor and is clipped
    once, after the z smoothing: its peak and wings are the PSF's."""
    from sparseloc.camera import Camera

    px = 160.0
    optics = dict(na=1.3, wavelength=600.0, waves=0.25, z_range=(-1000.0, 1000.0))
    true = make_psf("astig", **optics)
    planes = np.arange(-800.0, 800.1, 20.0)
    # sub-pixel phases spread over the pixel (see the next test)
    beads = [(2000.0, 2000.0), (5560.0, 2090.0), (2100.0, 5540.0), (5530.0, 5630.0)]
    cam = Camera(kind="emccd", offset=500.0, gain=20.0, em_gain=200.0, qe=0.95, read_noise=50.0)
    stack = simulate(
        true, scene=bead_scan_truth(beads, planes, photons=1e4), n_frames=planes.size,
        shape=(80, 80), pixel_size=px, background=30.0, camera=cam, seed=3,
    )  # fmt: skip
    gain = cam.gain / cam.em_gain / cam.qe
    cal = calibrate_beads(stack.movie, px, z=planes, offset=500.0, gain=gain, camera=cam)
    assert cal.psf.oversample == 2
    side = 19
    ring = np.hypot(*np.mgrid[:side, :side] - side // 2) >= 8
    for z in (0.0, 600.0):
        at = np.array([side / 2 * px]), np.array([side / 2 * px]), np.array([z])
        got, want = (m.images(*at, (side, side), px)[0] for m in (cal.psf, true))
        got, want = got / got.sum(), want / want.sum()
        assert abs(got.max() / want.max() - 1.0) < 0.05, (z, got.max(), want.max())
        assert got[ring].mean() < 2.0 * want[ring].mean(), (z, got[ring].mean(), want[ring].mean())


def test_beads_at_one_sub_pixel_phase_get_the_grid_and_a_warning():
    """Nine beads on a grid of whole pixels (all at one sub-pixel phase) on coarse pixels:
    no bead samples the half-pixel grid's nodes between phases, but its interpolation there
    still fits emitters better than the pixel model does (calibration_pixel_phase.txt), so
    the grid stays, and the calibration warns that its model error says nothing of those
    nodes; the same beads at spread phases get the grid without the warning."""
    from sparseloc.calibrate_oversample import phases_spread

    px = 160.0
    whole = np.array([(x, y) for y in (15.0, 40.0, 65.0) for x in (15.0, 40.0, 65.0)]) * px
    spread = whole + np.random.default_rng(3).uniform(-0.5, 0.5, whole.shape) * px
    assert not phases_spread(whole / px + 0.01 * np.random.default_rng(4).normal(size=(9, 2)))
    assert phases_spread(spread / px)
    cals = {}
    for name, beads in (("whole", whole), ("spread", spread)):
        stack = simulate(
            make_psf("astig"), scene=bead_scan_truth(beads, ZP, PHOTONS), n_frames=ZP.size,
            shape=(80, 80), pixel_size=px, background=10.0, seed=1,
        )  # fmt: skip
        cals[name] = calibrate_beads(stack.movie, px, Z_STEP, offset=OFFSET)
    assert {k: c.psf.oversample for k, c in cals.items()} == {"whole": 2, "spread": 2}
    assert "nearly one sub-pixel position along x and y" in cals["whole"].params["phase_warning"]
    assert cals["spread"].params["phase_warning"] == ""
    summary = "\n".join(calibration_summary(cals["whole"]))
    assert "warning: the 9 beads used sit at nearly one sub-pixel position" in summary


def test_the_model_check_allows_for_the_error_the_calibration_measured(monkeypatch):
    """Astigmatic beads on 160 nm pixels, modelled at the camera's pixels: the calibration
    measures its model error (the bead images are sampled coarsely) and the count selection
    allows for it; the run's model check must allow for it too, or it calls a misfit the
    calibration measured and names a wrong PSF or camera as the likely cause."""
    import sparseloc.calibrate as calibrate_module
    from sparseloc.model_check import check_fit
    from sparseloc.pipeline import LocalizeParams, localize, work_model_for

    px, stack, movie = _astig_beads_160nm()
    monkeypatch.setattr(calibrate_module, "worth_oversampling", lambda n: False)
    cal = calibrate_beads(stack, px, Z_STEP, offset=OFFSET)
    assert cal.psf.model_error > 0.05
    params = LocalizeParams(pixel_size=px)
    res = localize(movie.movie.astype(float) - OFFSET, work_model_for(cal.psf, params), params)
    check = res.metadata["model_check"]
    assert check["verdict"] == "ok"
    # the windows misfit far beyond a correct model's spread, up to the bar of a check that
    # knows no model error, and the check raised its bar by what the calibration measured
    n, k = check["fits"], check["dof"]
    bare = check_fit(np.full(n, check["median_gof"]), np.full(n, k))
    assert check["median_gof"] > 1.0 + 0.8 * (bare.upper - 1.0)
    assert check["upper"] > bare.upper + 0.05


def test_coarse_pixels_are_modelled_on_a_finer_grid(monkeypatch, cal):
    """A hidden-data trial: bead calibrations on 160 nm pixels missed their beads by twice as
    much as on 100 nm and localized far below the optics' own model; beads at one sub-pixel
    phase agreed, at random phases they did not (resampled coarse pixels disagree). Where the
    beads' images hold light next to the pixels' Nyquist frequency, the model is fitted on a
    grid of half a pixel to every bead's samples at their own offsets: it misses its beads by
    less and fits a movie of the same optics better. On 100 nm pixels the pixel model stays."""
    import sparseloc.calibrate as calibrate_module
    from sparseloc.evaluate import evaluate
    from sparseloc.pipeline import LocalizeParams, localize, work_model_for

    px, stack, movie = _astig_beads_160nm()
    fine = calibrate_beads(stack, px, Z_STEP, offset=OFFSET)
    assert fine.psf.oversample == 2 and fine.average.shape[1] * 2 == fine.psf.stack.shape[1]
    with monkeypatch.context() as m:
        m.setattr(calibrate_module, "worth_oversampling", lambda n: False)
        coarse = calibrate_beads(stack, px, Z_STEP, offset=OFFSET)
    assert fine.psf.model_error < 0.5 * coarse.psf.model_error
    params = LocalizeParams(pixel_size=px)
    frames = movie.movie.astype(float) - OFFSET
    runs = [localize(frames, work_model_for(c.psf, params), params) for c in (fine, coarse)]
    gof = [r.metadata["model_check"]["median_gof"] for r in runs]
    assert abs(gof[0] - 1.0) < abs(gof[1] - 1.0)
    jac = [evaluate(r.table, movie.truth).jaccard for r in runs]
    assert jac[0] >= jac[1]
    # the emitter stays where the pixel model puts it: the same origin, finer
    assert fine.psf.pixel_centre == pytest.approx(coarse.psf.pixel_centre, abs=1e-9)
    assert cal.psf.oversample == 1  # nine beads on 100 nm pixels: sampled finely enough


def test_the_model_error_is_measured_beyond_the_cameras_own_noise():
    """An EMCCD doubles the variance of every photon (excess noise): the model error, the
    beads' residual beyond the expected noise, took that noise for the model's error (an
    astigmatic calibration on 65 nm pixels: 14.4 % with the EMCCD against 3.3 % with an
    ideal camera, and the count selection then allowed for the wrong amount)."""
    from sparseloc.camera import Camera

    camera = Camera(kind="emccd", offset=OFFSET, gain=12.0, em_gain=200.0, qe=0.9, read_noise=50.0)
    positions = np.array([(3000.0, 3000.0), (9000.0, 3000.0), (3000.0, 9000.0), (9000.0, 9000.0)])
    sim = simulate(
        make_psf("dh-analytic"), scene=bead_scan_truth(positions + 23.0, ZP, PHOTONS),
        n_frames=ZP.size, shape=SHAPE, pixel_size=PX, background=10.0, camera=camera, seed=4,
    )  # fmt: skip
    kw = dict(offset=OFFSET, gain=camera.photons_per_adu)
    blind = calibrate_beads(sim.movie, PX, Z_STEP, **kw).psf.model_error  # photon counting
    told = calibrate_beads(sim.movie, PX, Z_STEP, camera=camera, **kw).psf.model_error
    assert told < 0.7 * blind


def test_the_calibrations_noise_is_the_cameras():
    from sparseloc.calibrate import photon_noise
    from sparseloc.camera import Camera

    emccd = Camera(kind="emccd", offset=OFFSET, gain=12.0, em_gain=200.0, qe=0.9, read_noise=50.0)
    a, b = photon_noise(emccd)
    assert a == pytest.approx(2.0 / 0.9) and b == pytest.approx((50.0 / (200.0 * 0.9)) ** 2)
    scmos = Camera(kind="scmos", offset=OFFSET, gain=0.5, qe=0.8, read_noise=1.5)
    assert photon_noise(scmos) == pytest.approx((1.0 / 0.8, (1.5 / 0.8) ** 2))
    assert photon_noise(None) == (1.0, 0.0)


def test_the_robust_average_keeps_an_emccds_noise():
    """The robust average's clip took the median absolute deviation of a handful of beads, at
    least the square root of the voxel's light, for a voxel's noise: an EMCCD's skewed noise
    on the frame's background lies far above that floor, so the clip cut voxels of beads that
    hold no other light, and the model error, measured on the kept voxels, missed part of
    the noise it subtracts. The floor is the camera's noise of the voxel, background included."""
    from sparseloc.calibrate import CameraNoise, robust_keep

    rng = np.random.default_rng(0)
    bg, qe, em = 10.0, 0.9, 200.0
    yy, xx = np.mgrid[-10:11, -10:11]
    spot = np.exp(-(xx**2 + yy**2) / 8.0)
    mu = np.broadcast_to(5000.0 * spot / spot.sum(), (9, 20, 21, 21)) + bg
    electrons = rng.poisson(qe * mu)
    photons = rng.gamma(np.maximum(electrons, 1e-9), em) * (electrons > 0) / (em * qe)
    noise = CameraNoise(2.0 / qe, 0.0, np.full(20, bg))
    keep = robust_keep(photons - bg, np.ones(9, bool), noise)
    kept_power = np.sum((photons - mu)[keep] ** 2) / np.sum(noise.a * mu[keep])
    assert keep.mean() > 0.98
    assert kept_power > 0.94


@pytest.mark.parametrize("oversample", [1, 2, 3])
def test_a_model_cut_to_its_light_renders_the_same_light_inside(oversample):
    """The model of dim beads is cut where its light ends: inside the cut it renders what the
    whole model renders (up to the light cut off), and a cut no smaller than the model is none
    (an oversampled model keeps every sample of its pixels' phases)."""
    from sparseloc.calibrate import _cropped

    side, o = 21, oversample
    ax = (np.arange(side * o) - (side * o - 1) / 2) / o
    rr, cc = np.meshgrid(ax, ax, indexing="ij")
    stack = np.stack([np.exp(-(rr**2 + cc**2) / (2 * s**2)) for s in np.linspace(3.0, 4.0, 6)])
    c = (side * o - 1) / 2
    psf = SplinePSF(stack, PX, np.arange(6) * 50.0, centre=(c, c), oversample=o)
    assert _cropped(psf, side // 2) is psf
    cut = _cropped(psf, 6)
    assert cut.stack.shape[1] // o == 13
    args = ([15.5 * PX + 30.0], [15.5 * PX - 20.0], [120.0], (31, 31), PX)
    whole, part = psf.images(*args)[0], cut.images(*args)[0]
    inner = (slice(11, 20), slice(11, 20))
    np.testing.assert_allclose(
        part[inner] / part[inner].sum(), whole[inner] / whole[inner].sum(), atol=1e-4
    )
    assert np.abs(whole[:7]).sum() > 1e-3  # (the whole model has light there; the cut, none)
    assert np.abs(part[:7]).max() < 1e-4 and np.abs(part[:, :7]).max() < 1e-4


def test_a_saturated_bead_does_not_hide_the_usable_ones():
    """The detection keeps maxima above a fraction of the brightest bead; a saturated bead
    (unusable, and far brighter than any other) would set that scale and hide every usable
    bead. Its pixels' neighbourhood does not set it: the dimmer beads are found, the
    saturated one too (for the vetting to reject by name)."""
    from sparseloc.calibrate import find_beads

    rows, cols = np.indices((80, 80))
    spots = [(20, 20, 1e6), (20, 60, 3e4), (60, 20, 3e4), (60, 60, 3e4)]
    img = sum(a * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / 8.0) for r, c, a in spots)
    img = img + np.random.default_rng(0).normal(0.0, 1.0, img.shape)
    assert len(find_beads(img)) == 1
    saturated = np.zeros(img.shape, bool)
    saturated[19:22, 19:22] = True
    found = find_beads(img, saturated=saturated)
    assert len(found) == 4 and np.allclose(found[0], (20, 20), atol=0.5)


def test_the_saturation_mask_must_be_the_frames():
    """A saturation mask of another shape is refused in one sentence; an integer mask works
    as a boolean one."""
    from sparseloc.calibrate import find_beads

    rows, cols = np.indices((40, 40))
    img = 1e6 * np.exp(-((rows - 10) ** 2 + (cols - 10) ** 2) / 8.0)
    img = img + 3e4 * np.exp(-((rows - 30) ** 2 + (cols - 30) ** 2) / 8.0)
    mask = np.zeros((40, 40), np.uint8)
    mask[9:12, 9:12] = 1
    assert len(find_beads(img, saturated=mask)) == 2
    with pytest.raises(ValueError, match="saturation mask"):
        find_beads(img, saturated=np.zeros((30, 30), bool))


def test_a_crowded_field_without_symmetry_keeps_the_model_origin_on_the_emitter():
    """Twelve beads of the pupil double helix (a halo microns wide) at random, at least 2 um
    apart: each ROI holds neighbours' halos on different sides. The light the neighbours'
    model misses (its halo cut by a border background, the rounds stopped once the beads no
    longer moved) stayed in the average and moved its light centroid, the model's origin,
    52 / 60 nm off the emitters; the built-in double helix's light centroid is the emitter."""
    rng = np.random.default_rng(7)
    positions: list[np.ndarray] = []
    for q in rng.uniform(1500, 11300, (40, 2)):
        if all(np.hypot(*(q - b)) > 2000 for b in positions):
            positions.append(q)
    xy = np.array(positions[:16])
    planes = np.arange(-1000.0, 1000.1, 50.0)
    sim = simulate(
        make_psf("dh"), scene=bead_scan_truth(xy, planes, PHOTONS), n_frames=planes.size,
        shape=(128, 128), pixel_size=PX, background=10.0, seed=1,
    )  # fmt: skip
    known = pd.DataFrame({"x_nm": xy[:, 0], "y_nm": xy[:, 1]})
    cal = calibrate_beads(sim.movie, PX, 50.0, offset=OFFSET, beads=known)
    assert cal.params["n_beads_with_neighbours"] >= 4
    assert np.hypot(*cal.params["centroid_offset_nm"]) < 30.0, cal.params["centroid_offset_nm"]
    assert cal.params["model_error"] < 0.05


def _scan_with_background(positions, background, shape=(96, 96), seed=2):
    """A double-helix bead scan (50 nm steps) over ``background`` (photons/px, (H, W))."""
    planes = np.arange(-1000.0, 1000.1, 50.0)
    sim = simulate(
        make_psf("dh"), scene=bead_scan_truth(positions, planes, PHOTONS), n_frames=planes.size,
        shape=shape, pixel_size=PX, background=np.broadcast_to(background, (planes.size, *shape)),
        seed=seed,
    )  # fmt: skip
    known = pd.DataFrame({"x_nm": positions[:, 0], "y_nm": positions[:, 1]})
    return calibrate_beads(sim.movie, PX, 50.0, offset=OFFSET, beads=known)


def test_a_background_tilted_across_the_scan_does_not_move_the_model_origin():
    """Illumination that rises across the field (10 to 25 photons/px) put a ramp in every
    bead's ROI; a single background level per plane left it in the model, whose light
    centroid, the origin without bead positions, sat 25 nm off the emitters (every table
    made with it as far off). The trend is measured and subtracted, and named."""
    xy = np.array([(2400.0, 2400.0), (7200.0, 2400.0), (2400.0, 7200.0), (7200.0, 7200.0)])
    tilt = 10.0 + 15.0 * np.linspace(0.0, 1.0, 96)[None, :] * np.ones((96, 1))
    cal = _scan_with_background(xy, tilt)
    assert np.abs(cal.params["centroid_offset_nm"]).max() < 8.0, cal.params["centroid_offset_nm"]
    assert 12.0 < cal.params["background_trend"] < 18.0, cal.params["background_trend"]
    assert "the background changes by" in "\n".join(calibration_summary(cal))


def test_a_curved_illumination_profile_under_the_scan_is_read_and_subtracted():
    """A Gaussian illumination (5 -> 40 photons/px, sigma 8 um) under 9 beads: no plane
    follows it, and without its trend 2 beads of 9 were used (the bump read as the beads'
    light, an ROI of 47 px) and the model's origin lay 231 nm off the beads."""
    rows, cols = np.indices((128, 128))
    r2 = ((cols + 0.5) * PX - 8400.0) ** 2 + ((rows + 0.5) * PX - 6400.0) ** 2
    light = 5.0 + 35.0 * np.exp(-r2 / (2 * 8000.0**2))
    g = np.linspace(2200.0, 10600.0, 3)
    xy = np.array([(x + 137.0, y - 71.0) for x in g for y in g])
    cal = _scan_with_background(xy, light, shape=(128, 128))
    assert cal.params["n_beads_used"] == 9
    assert np.abs(cal.params["centroid_offset_nm"]).max() < 8.0, cal.params["centroid_offset_nm"]
    assert 15.0 < cal.params["background_trend"] < 25.0, cal.params["background_trend"]


def test_the_halos_of_beads_on_one_side_are_no_tilt_of_the_background():
    """Beads on the left of a flat background light its left side with their halos: read as
    a tilt, subtracting it would put a ramp in every ROI."""
    xy = np.array([(3000.0, 3000.0), (3000.0, 8000.0), (3000.0, 13000.0)])
    cal = _scan_with_background(xy, np.full((160, 160), 10.0), shape=(160, 160))
    assert cal.params["background_trend"] == 0.0
    assert np.abs(cal.params["centroid_offset_nm"]).max() < 8.0, cal.params["centroid_offset_nm"]


def test_a_stack_clipped_below_its_type_maximum_is_named():
    """A 12-bit camera written to 16-bit files clips at 4095, far below the type's maximum
    (the default saturation): 142 pixel values at exactly 4095 in a rehearsal's stack went
    unremarked. The summary names the value and the --saturation that would use it."""
    from sparseloc.camera import clipping

    planes = np.arange(-600.0, 600.1, 50.0)
    xy = np.array([(2400.0, 2400.0), (7200.0, 2400.0), (2400.0, 7200.0), (7200.0, 7200.0)])
    sim = simulate(
        make_psf("astig"), scene=bead_scan_truth(xy, planes, 70000.0), n_frames=planes.size,
        shape=(96, 96), pixel_size=PX, background=10.0, seed=4,
    )  # fmt: skip
    assert clipping(sim.movie, 65535.0) is None  # unclipped: its maximum is one pixel's
    clipped = np.minimum(sim.movie, 4095).astype(np.uint16)
    top, ties = clipping(clipped, 65535.0)
    assert top == 4095 and ties >= 10
    assert clipping(clipped, 4095.0) is None  # the saturation given names those pixels
    cal = calibrate_beads(clipped, PX, 50.0, offset=OFFSET)
    text = "\n".join(calibration_summary(cal))
    assert "sit at exactly 4095 ADU" in text and "--saturation 4095" in text, text
    # a pixel stuck at one value in every plane is a defect, not a clipped camera
    stuck = sim.movie.copy()
    stuck[:, 5, 80] = 65000
    cal = calibrate_beads(stuck, PX, 50.0, offset=OFFSET)
    assert cal.params["defective_pixels"] >= 1 and cal.params["clipped_values"] == 0
