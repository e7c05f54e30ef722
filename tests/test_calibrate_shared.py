"""Calibration on outside material (``../shared/data``): a real retrieved double-helix mask and
storm-analysis's simulated bead scans and frames. Skipped where the data are absent."""

from __future__ import annotations

import numpy as np
import pytest

from sparseloc.calibrate import calibrate_beads, calibrate_file
from sparseloc.psf import make_psf
from sparseloc.simulate import bead_scan_truth, simulate


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.ravel() - a.mean()
    b = b.ravel() - b.mean()
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def test_calibration_reproduces_retrieved_dh_mask(shared_data):
    """A bead scan simulated through the real retrieved mask calibrates back to its PSF."""
    model = make_psf(
        shared_data / "dhpsfu_masks" / "Microscope1_mask_wasmask.mat",
        na=1.15,
        wavelength=670.0,
        n_immersion=1.33,
        z_range=(-1600.0, 1600.0),
    )
    px = 108.6
    planes = np.arange(-1400.0, 1400.0 + 1e-6, 50.0)
    rng = np.random.default_rng(3)
    grid = np.array([(x, y) for x in (3000.0, 7500.0) for y in (3000.0, 7500.0)])
    pos = grid + rng.uniform(-50, 50, grid.shape)
    sim = simulate(
        model,
        scene=bead_scan_truth(pos, planes, 20000.0),
        n_frames=planes.size,
        shape=(100, 100),
        pixel_size=px,
        background=10.0,
        seed=3,
    )
    cal = calibrate_beads(sim.movie, px, 50.0, offset=100.0)
    assert cal.n_used == 4
    spline = cal.psf
    nr = spline.stack.shape[1]
    assert nr >= 25  # the ROI follows the PSF's extent, even with beads near the frame edge
    # The measured model's lateral origin is the centroid of its z-averaged image (a
    # convention); for this asymmetric PSF it sits ~40 nm from the emitter. Compare the two
    # models at the same emitter, using the beads' reported positions against the truth.
    b = cal.beads
    near = np.argmin(
        np.hypot(
            b["x_nm"].to_numpy()[:, None] - pos[:, 0], b["y_nm"].to_numpy()[:, None] - pos[:, 1]
        ),
        axis=1,
    )
    dx = float(np.mean(b["x_nm"].to_numpy() - pos[near, 0]))
    dy = float(np.mean(b["y_nm"].to_numpy() - pos[near, 1]))
    assert abs(dx) < 100 and abs(dy) < 100
    x0 = (spline.centre[1] + 0.5) * px
    y0 = (spline.centre[0] + 0.5) * px
    z = cal.z
    truth = model.images(np.full(z.size, x0 - dx), np.full(z.size, y0 - dy), z, (nr, nr), px)
    got = spline.images(np.full(z.size, x0), np.full(z.size, y0), z, (nr, nr), px)
    ncc = np.array([_ncc(a, b) for a, b in zip(got, truth, strict=True)])
    assert ncc.min() > 0.98, ncc.min()


@pytest.mark.parametrize("kind", ["dh", "astig"])
def test_storm_analysis_bead_scans_calibrate(shared_data, kind):
    """storm-analysis's bead scans: all 18 beads found and used, z from the CSV."""
    folder = shared_data / "storm_analysis_sim" / kind
    cal = calibrate_file(
        folder / "beads_zscan.tif",
        100.0,
        z_file=folder / "beads_zscan_z.csv",
        offset=100.0,
    )
    assert cal.n_used == 18
    assert cal.z[0] < -700 and cal.z[-1] > 700
    # Beads match the positions storm-analysis placed (centre of the first pixel = 0 there).
    import pandas as pd

    ref = pd.read_csv(folder / "beads_zscan_positions.csv")
    rx, ry = (ref["x_px"].to_numpy() + 0.5) * 100.0, (ref["y_px"].to_numpy() + 0.5) * 100.0
    d = np.hypot(
        cal.beads["x_nm"].to_numpy()[:, None] - rx, cal.beads["y_nm"].to_numpy()[:, None] - ry
    )
    assert np.all(d.min(axis=1) < 20.0), d.min(axis=1)
    # Every bead agrees with the average as well as its noise allows (the same PSF everywhere
    # in these scans): no bead stands out from the others.
    per_bead = cal.bead_ncc.mean(axis=1)
    assert per_bead.min() > np.median(per_bead) - 0.03
    assert cal.bead_ncc.min() > 0.75


@pytest.fixture(scope="module")
def dh_calibration(shared_data):
    folder = shared_data / "storm_analysis_sim" / "dh"
    return calibrate_file(
        folder / "beads_zscan.tif", 100.0, z_file=folder / "beads_zscan_z.csv", offset=100.0
    ).psf


def _localize_crop(shared_data, name, model, window, margin, rows=100, cols=150, scale=1.0):
    import tifffile

    from sparseloc.evaluate import evaluate
    from sparseloc.io.truth import read_truth_csv
    from sparseloc.pipeline import LocalizeParams, localize

    folder = shared_data / "storm_analysis_sim" / "dh"
    frame = tifffile.imread(folder / f"{name}.tif").astype(float) - 100.0
    frame = frame.reshape(-1, *frame.shape[-2:])[:, :rows, :cols]
    truth = read_truth_csv(folder / f"{name}_groundtruth.csv", pixel_size=100.0)
    inside = (truth["x_nm"] < cols * 100.0) & (truth["y_nm"] < rows * 100.0)
    params = LocalizeParams(pixel_size=100.0, window=window, margin=margin)
    res = localize(frame * scale, model, params)
    return evaluate(res.table, truth[inside])


def test_storm_analysis_dh_grid_frame(shared_data, dh_calibration):
    """Calibrate from storm-analysis's DH bead scan, localize a third of its grid frame.

    storm-analysis's own FISTA + spline fit on the whole frame: recall 1.00, RMSE x/y/z
    3.4/3.7/5.5 nm. sparseloc (frame solver) measured on this crop: recall 1.00, 3.1/3.75/5.9
    nm (whole frame 3.4/3.8/5.6 nm; the windowed hybrid gave the same). Thresholds leave room
    for noise in 28 emitters, not for a regression to the grid-limited precision (10 nm steps
    would give ~3-5 nm more).
    """
    ev = _localize_crop(shared_data, "dh_fista_diag_test01", dh_calibration, 17, 4)
    assert ev.recall >= 0.95
    assert ev.jaccard >= 85.0
    assert ev.rmse_x < 6.0 and ev.rmse_y < 6.0 and ev.rmse_z < 9.0


@pytest.mark.slow
def test_storm_analysis_dh_random_density(shared_data, dh_calibration):
    """0.5 emitter/um^2 of heavily overlapping double helices (a third of the frame).

    Measured on this crop with the frame solver (final defaults): recall 0.971, Jaccard
    89.5 %, RMSE lateral 23 nm and axial 55 nm, but median errors of 6 nm laterally and 7 nm
    axially: a few overlapping pairs fitted far off carry the RMSE (without the worst
    5 of 68 pairs it is 10 nm laterally). The windowed hybrid solver measured recall 0.87,
    Jaccard 76 %, RMSE 12.6 / 19 nm. The thresholds guard the recall of overlapping emitters
    and the bulk precision.
    """
    ev = _localize_crop(shared_data, "dh_random_density0.005px2", dh_calibration, 21, 6)
    assert ev.recall >= 0.9
    assert ev.jaccard >= 75.0
    assert ev.rmse_lateral < 50.0 and ev.rmse_axial < 90.0


@pytest.mark.slow
def test_storm_analysis_dh_random_density_1_per_um2(shared_data, dh_calibration):
    """1 emitter/um^2 of double helices (a third of the frame): most images overlap two or
    more others.

    On a frame this dense the count selection's choices move with rounding: the frame scaled
    by 1 + k 1e-12 (k = 0..7) gives Jaccard indices with a standard deviation of 1.3-2.1
    points and precisions of 0.014 (docs/benchmarks/rounding_spread_crop.txt). One run
    cannot guard against a regression, so the test scores the mean of four such runs. Their
    means measured: recall 0.912, precision 0.889, Jaccard 81.9 %, RMSE 50.5 / 69.6 nm (the
    code of an earlier version, 2b1b41f: 0.922, 0.886, 82.4 %, 47.2 / 77.3 nm). The
    thresholds lie about three standard deviations of such a mean below them.
    """
    scores = [
        _localize_crop(
            shared_data, "dh_random_density0.01px2", dh_calibration, 21, 6, scale=1 + k * 1e-12
        )
        for k in range(4)
    ]
    mean = {
        key: float(np.mean([getattr(ev, key) for ev in scores]))
        for key in ("precision", "recall", "jaccard", "rmse_lateral", "rmse_axial")
    }
    assert mean["precision"] >= 0.865, mean
    assert mean["recall"] >= 0.895, mean
    assert mean["jaccard"] >= 79.5, mean
    assert mean["rmse_lateral"] < 56.0 and mean["rmse_axial"] < 88.0, mean


def _false_lobe_fits(table, truth) -> tuple[float, int]:
    """Of a table's localizations: the share that are false and dim beside a true emitter
    (no truth within 100 nm laterally and 300 nm axially, the nearest truth within 1 um and
    brighter: a fit to part of a neighbour's image), and the number of false ones beyond
    the truth's z range by more than 100 nm that no flag marks."""
    from scipy.spatial import cKDTree

    from sparseloc.evaluate import match_localizations

    t = truth[["x_nm", "y_nm", "z_nm", "photons"]].to_numpy()
    loc = table[["x_nm", "y_nm", "z_nm", "photons"]].to_numpy()
    pairs = match_localizations(table, truth, lateral_tol=100.0, axial_tol=300.0)
    true = np.zeros(len(loc), dtype=bool)
    true[pairs["loc_row"].to_numpy()] = True
    d, nearest = cKDTree(t[:, :2]).query(loc[:, :2])
    lobe = ~true & (d < 1000.0) & (loc[:, 3] < t[nearest, 3])
    beyond = ~true & ((loc[:, 2] < t[:, 2].min() - 100.0) | (loc[:, 2] > t[:, 2].max() + 100.0))
    unflagged = beyond & (table["flag"].to_numpy() == "ok")
    return float(lobe.mean()), int(unflagged.sum())


@pytest.mark.slow
def test_few_dim_fits_on_a_neighbours_lobe_at_1_per_um2(shared_data, dh_calibration):
    """storm-analysis's whole DH frame at 1 /um^2 with default settings (issue 27 item 3).

    The first-day trial found 211 of 737 localizations false there, most of them dim fits
    to a neighbour's lobe, 41 % with z beyond the data's range, and the flags removed 41.
    Measured with this test's rules: before the count selection knew the model's error
    (3585ebd's parent) 255 of 739 localizations (34.5 %) were dim false fits beside a
    brighter emitter and 61 false fits beyond the z range carried no flag; now 67 of 606
    (11.1 %) and 9. The thresholds sit between, far from both (a run's rounding
    moves these counts by a few).
    """
    import tifffile

    from sparseloc.io.truth import read_truth_csv
    from sparseloc.pipeline import LocalizeParams, localize

    folder = shared_data / "storm_analysis_sim" / "dh"
    name = "dh_random_density0.01px2"
    frame = tifffile.imread(folder / f"{name}.tif").astype(float) - 100.0
    truth = read_truth_csv(folder / f"{name}_groundtruth.csv", pixel_size=100.0)
    res = localize(frame.reshape(-1, *frame.shape[-2:]), dh_calibration, LocalizeParams(100.0))
    lobe_share, unflagged_beyond = _false_lobe_fits(res.table, truth)
    assert lobe_share < 0.2, lobe_share
    assert unflagged_beyond < 30, unflagged_beyond
