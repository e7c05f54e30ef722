"""Defective camera pixels (hot, stuck): found from the data and replaced by their neighbours,
in calibrate and in localize."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import tifffile

from cli_checks import run
from sparseloc.defects import defective_pixels, replace_defects, sharpest_ratio
from sparseloc.psf import make_psf
from sparseloc.simulate import bead_scan_truth, simulate

OFFSET = 100.0


def _stuck(movie: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``movie`` (ADU) with ``n`` pixels stuck 300-3000 ADU above the offset in every frame,
    two of them on the frame's edge; and their mask."""
    rng = np.random.default_rng(seed)
    rows, cols = movie.shape[1:]
    mask = np.zeros((rows, cols), bool)
    mask[rng.integers(2, rows - 2, n - 2), rng.integers(2, cols - 2, n - 2)] = True
    mask[rows - 1, cols // 3] = mask[cols // 2, 0] = True
    out = movie.copy()
    out[:, mask] = (OFFSET + rng.uniform(300.0, 3000.0, mask.sum())).astype(movie.dtype)
    return out, mask


def test_the_sharpest_image_an_objective_forms_bounds_a_pixel_against_its_neighbour():
    ratios = [sharpest_ratio(p) for p in (65.0, 100.0, 160.0, 267.0)]
    assert ratios == sorted(ratios) and ratios[0] > 2.0
    assert 4.0 < sharpest_ratio(100.0) < 5.0 and 11.0 < sharpest_ratio(160.0) < 14.0


@pytest.mark.parametrize("px", [65.0, 80.0])
def test_a_sharp_fiducial_on_fine_pixels_is_light(px):
    """On 65-80 nm pixels a bright emitter in every frame, centred on a pixel, comes close to
    the bound: its rise is measured from the darkest neighbour, a corner that holds light
    too, so the bound counts that corner's light (``c / s + 1``)."""
    model = make_psf("astig", na=1.49, wavelength=520.0, waves=0.0)
    c = 16.5 * px  # a pixel's centre
    scene = pd.DataFrame({"frame": np.arange(20), "x_nm": c, "y_nm": c, "z_nm": 0.0,
                          "photons": 1e5})  # fmt: skip
    sim = simulate(model, scene=scene, n_frames=20, shape=(33, 33), pixel_size=px,
                   background=10.0, seed=2)  # fmt: skip
    assert not defective_pixels(sim.movie.astype(float) - OFFSET, px).any()


def test_stuck_pixels_are_found_and_bright_emitters_in_every_frame_are_not():
    """Fiducial-like emitters of 50,000 photons in focus in every frame (their median is
    their image, sharpest at 160 nm pixels) are light; stuck pixels, also on the frame's
    edge, are not."""
    px = 160.0
    scene = pd.concat(
        [
            pd.DataFrame({"frame": np.arange(10), "x_nm": x, "y_nm": y, "z_nm": 0.0,
                          "photons": 50000.0})
            for x, y in [(2000.0, 2000.0), (5040.0, 3120.0), (7000.0, 6080.0)]
        ],
        ignore_index=True,
    )  # fmt: skip
    sim = simulate(make_psf("astig"), scene=scene, n_frames=10, shape=(64, 64), pixel_size=px,
                   background=10.0, seed=1)  # fmt: skip
    clean = sim.movie.astype(float) - OFFSET
    assert not defective_pixels(clean, px).any()
    stuck, mask = _stuck(sim.movie, 12)
    found = defective_pixels(stuck.astype(float) - OFFSET, px)
    np.testing.assert_array_equal(found, mask)
    fixed = replace_defects(stuck.astype(float) - OFFSET, found)
    assert np.abs(fixed[:, mask] - clean[:, mask]).max() < 30.0
    np.testing.assert_array_equal(fixed[:, ~mask], clean[:, ~mask])


@pytest.fixture(scope="module")
def bead_stack():
    """Nine double-helix beads scanned through focus (ADU), 100 nm pixels."""
    zs = np.arange(-500.0, 501.0, 50.0)
    grid = [2500.0, 6000.0, 9500.0]
    beads = np.array([(x, y) for y in grid for x in grid]) + 23.0
    sim = simulate(make_psf("dh-analytic"), scene=bead_scan_truth(beads, zs, 20000.0),
                   n_frames=zs.size, shape=(120, 120), pixel_size=100.0, background=10.0,
                   seed=2)  # fmt: skip
    return sim.movie


def test_calibration_of_a_stack_with_stuck_pixels(bead_stack, tmp_path):
    """0.1 % of the pixels stuck: left in, they make the beads disagree with their average
    (or read as a bead); they are replaced by their neighbours and said so."""
    from sparseloc.calibrate import calibrate_beads

    stuck, mask = _stuck(bead_stack, 14, seed=3)
    # one stuck at the camera's maximum inside a bead's ROI: no bead's saturation
    stuck[:, 25, 31] = np.iinfo(stuck.dtype).max
    mask[25, 31] = True
    clean = calibrate_beads(bead_stack, 100.0, 50.0, offset=OFFSET)
    cal = calibrate_beads(stuck, 100.0, 50.0, offset=OFFSET)
    assert cal.params["defective_pixels"] == mask.sum() and clean.params["defective_pixels"] == 0
    assert cal.n_used == clean.n_used == 9
    assert cal.params["model_error"] < clean.params["model_error"] + 0.02
    path = tmp_path / "beads.tif"
    tifffile.imwrite(path, stuck)
    res = run("calibrate", path, "-o", tmp_path / "psf.h5", "--pixel-size", 100, "--z-step",
              50, "--offset", OFFSET)  # fmt: skip
    assert res.exit_code == 0, res.output
    assert f"{mask.sum()} defective (hot or stuck) pixel(s) replaced" in res.output


def test_localize_replaces_stuck_pixels(tmp_path):
    """Stuck pixels in a movie read as emitters in every frame (false localizations, slow
    fits); replaced, the run scores as on the clean movie and the table lists them."""
    from sparseloc.evaluate import evaluate
    from sparseloc.io.tables import read_parquet

    sim = simulate(make_psf("dh-analytic"), n_frames=6, shape=(64, 64), pixel_size=100.0,
                   density=0.3, seed=4)  # fmt: skip
    stuck, mask = _stuck(sim.movie, 10, seed=5)
    scores = {}
    for name, movie in (("clean", sim.movie), ("stuck", stuck)):
        path = tmp_path / f"{name}.tif"
        tifffile.imwrite(path, movie)
        out = tmp_path / f"{name}.parquet"
        res = run("localize", path, "-o", out, "--psf", "dh-analytic", "--pixel-size", 100,
                  "--offset", OFFSET, "--workers", 1)  # fmt: skip
        assert res.exit_code == 0, res.output
        assert (f"{mask.sum()} defective" in res.output) == (name == "stuck")
        table, meta = read_parquet(out)
        listed = sorted(map(tuple, meta["defective_pixels"]))
        assert listed == (sorted(map(tuple, np.argwhere(mask).tolist())) if name == "stuck" else [])
        scores[name] = evaluate(table, sim.truth).jaccard
    assert scores["stuck"] > scores["clean"] - 3.0, scores
