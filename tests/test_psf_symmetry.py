"""A PSF that images z and its mirror about focus alike: said by calibrate and localize."""

from __future__ import annotations

import numpy as np
import pytest

from cli_checks import run
from sparseloc.psf import make_psf
from sparseloc.psf.symmetry import mirror_focus, mirror_warning
from sparseloc.simulate import bead_scan_truth, simulate


@pytest.mark.parametrize(("name", "mirrored"), [("clear", True), ("astig", False), ("dh", False),
                                                ("dh-analytic", False)])  # fmt: skip
def test_only_an_unengineered_psf_mirrors_z_about_focus(name, mirrored):
    model = make_psf(name)
    assert (mirror_focus(model, 100.0) is not None) == mirrored
    assert bool(mirror_warning(model, 100.0)) == mirrored


def test_one_side_of_focus_is_no_mirror():
    """With the depths on one side of focus, z is known: nothing to say."""
    model = make_psf("clear")
    assert mirror_focus(model, 100.0) == pytest.approx(0.0, abs=60.0)
    assert mirror_focus(model, 100.0, (0.0, 1000.0)) is None
    assert mirror_focus(model, 100.0, (-1000.0, -50.0)) is None


def test_calibrate_and_localize_say_so(tmp_path):
    """A clear pupil's beads: the calibration's summary warns, and localize notes it unless
    --z-min / --z-max keep one side of focus (a rehearsal found a third of such fits with the
    wrong sign and no word of it)."""
    from sparseloc.io.tiff import write_tiff

    zs = np.arange(-600.0, 601.0, 50.0)
    beads = np.array([(1500.0, 1500.0), (4500.0, 1700.0), (3000.0, 4500.0)]) + 17.0
    sim = simulate(make_psf("clear"), scene=bead_scan_truth(beads, zs, 20000.0),
                   n_frames=zs.size, shape=(64, 64), pixel_size=100.0, seed=1)  # fmt: skip
    stack = write_tiff(tmp_path / "beads.tif", sim.movie, pixel_size=100.0)
    psf = tmp_path / "psf.h5"
    res = run("calibrate", stack, "-o", psf, "--pixel-size", 100, "--z-step", 50)
    assert res.exit_code == 0, res.output
    assert "looks the same above and below its focus" in res.output
    movie = write_tiff(tmp_path / "movie.tif", sim.movie[:2], pixel_size=100.0)
    for extra, said in (([], True), (["--z-min", 0], False)):
        out = tmp_path / f"locs{len(extra)}.parquet"
        res = run("localize", movie, "-o", out, "--psf", psf, "--workers", 1, *extra)
        assert res.exit_code == 0, res.output
        assert ("above and below its focus" in res.output) == said
