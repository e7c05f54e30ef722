"""Issue 27: what the repeated new-user trial found (unit slips, misleading causes, a silent
demo, plots of refused runs)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import tifffile

from cli_checks import refused, run
from sparseloc.units import check_pixel_size, check_z_step


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPARSELOC_CACHE_DIR", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def beads(tmp_path_factory):
    """A bead z-scan (ADU, ideal camera, offset 100) without pixel-size metadata."""
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    zs = np.arange(-500.0, 501.0, 50.0)
    truth = bead_scan_truth(np.array([[1600.0, 1600.0], [3200.0, 3200.0]]), zs, 20000.0)
    sim = simulate(make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(48, 48))
    path = tmp_path_factory.mktemp("beads") / "beads.tif"
    tifffile.imwrite(path, sim.movie)
    return path


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    out = tmp_path_factory.mktemp("movie") / "movie.tif"
    res = run("simulate", "-o", out, "--psf", "dh-analytic", "--frames", 2, "--rows", 32,
              "--cols", 32, "--pixel-size", 160, "--seed", 3)  # fmt: skip
    assert res.exit_code == 0, res.output
    return out


def test_lengths_in_micrometres_are_refused_as_such():
    assert check_pixel_size(100) == 100.0 and check_z_step(50) == 50.0
    with pytest.raises(ValueError, match=r"micrometres\? 0.1 um is 100 nm"):
        check_pixel_size(0.1)
    with pytest.raises(ValueError, match=r"--z-step 0.05 nm .* 0.05 um is 50 nm"):
        check_z_step(0.05)
    with pytest.raises(ValueError, match="positive number of nm"):
        check_pixel_size(0)
    with pytest.raises(ValueError, match="several planes over the PSF's depth"):
        check_z_step(1e5)
    # a new user's 5 um step gave "39 planes z -95000..95000 nm" without a word
    with pytest.raises(ValueError, match="--z-step 5000 nm is above 1000 nm"):
        check_z_step(5000)
    assert check_z_step(1000) == 1000.0


def test_calibrate_refuses_a_z_step_or_pixel_size_in_micrometres(beads, tmp_path):
    out = tmp_path / "c.h5"
    refused(run("calibrate", beads, "-o", out, "--pixel-size", 100, "--z-step", 0.05), "--z-step")
    res = run("calibrate", beads, "-o", out, "--pixel-size", 0.1, "--z-step", 50)
    refused(res, "--pixel-size", "micrometres")
    assert not out.exists()


def test_localize_pixel_size_refusals_name_the_cause(movie, tmp_path):
    out = tmp_path / "l.parquet"
    res = run("localize", movie, "-o", out, "--psf", "dh-analytic", "--pixel-size", 0.16)
    refused(res, "--pixel-size", "micrometres")
    res = run("localize", movie, "-o", out, "--psf", "dh-analytic", "--pixel-size", 0)
    refused(res, "--pixel-size must be a positive number")
    assert "metadata" not in res.output
    # a built-in model has no pixel size, and this movie records none
    import tifffile

    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, tifffile.imread(movie))
    res = run("localize", plain, "-o", out, "--psf", "dh")
    refused(res, "--pixel-size", "'dh'", "sparseloc calibrate", "nor does the movie's metadata")
    assert not out.exists()


def test_the_demo_says_what_it_is_doing(tmp_path, caplog):
    """Its stages as log lines (shown whatever --verbose says) and the localization's
    progress, also where stderr is not a terminal (before: silence until the end)."""
    import logging

    with caplog.at_level(logging.INFO, logger="sparseloc.demo"):
        res = run("demo", "-o", tmp_path / "d", "--frames", 2)
    assert res.exit_code == 0, res.output
    said = " ".join(caplog.messages)
    for stage in ("simulating", "localizing 2 frames", "scoring"):
        assert stage in said, said
    assert "localize: 2/2 frames" in res.output


def test_an_output_folder_is_refused_as_a_folder(movie, tmp_path):
    res = run("localize", movie, "-o", tmp_path, "--psf", "dh-analytic", "--pixel-size", 160)
    refused(res, "is a folder, not a file")


def test_a_bead_stack_given_as_psf_points_at_calibrate(beads, movie, tmp_path):
    res = run("localize", movie, "-o", tmp_path / "l.parquet", "--psf", beads, "--pixel-size", 160)
    refused(res, "bead z-scan", "sparseloc calibrate")


def test_camera_suggests_an_offset_even_where_the_line_cannot_place_it(tmp_path):
    from sparseloc.camera import Camera, apply_noise

    cam = Camera(kind="scmos", offset=100.0, gain=0.5, read_noise=20.0)
    rows, cols = np.mgrid[0:64, 0:64]
    mu = 5.0 + 395.0 * (0.5 + 0.5 * np.sin(cols / 15.0) * np.cos(rows / 21.0))
    path = tmp_path / "field.tif"
    tifffile.imwrite(
        path, apply_noise(np.broadcast_to(mu, (10, 64, 64)), cam, np.random.default_rng(1))
    )
    res = run("camera", path)
    assert res.exit_code == 0, res.output
    assert "offset not placed" in res.output and "--offset DARK_LEVEL" in res.output


def test_a_run_folder_refusal_names_a_changed_camera(movie, tmp_path):
    args = ["--psf", "dh-analytic", "--pixel-size", 160, "--run-dir", tmp_path / "run"]
    res = run("localize", movie, "-o", tmp_path / "a.parquet", *args, "--offset", 100)
    assert res.exit_code == 0, res.output
    res = run("localize", movie, "-o", tmp_path / "b.parquet", *args, "--offset", 90)
    # the saturation, in photons, follows the offset
    refused(res, "changed: camera.offset, params.saturation)")


def test_too_little_noise_names_an_offset_set_too_low():
    from sparseloc.model_check import check_fit

    low = check_fit(np.full(50, 0.3), np.full(50, 150.0), background=np.full(50, 10.0))
    assert low.verdict == "too_little_noise" and "offset set too low" in low.message


def test_drift_with_an_unreliable_z_corrects_x_and_y_and_says_so(tmp_path):
    """The README's drift step failed on its own short movie: x and y were sound, z had too
    few correlations, and nothing was written. Now x and y are corrected, z is left alone."""
    import pandas as pd

    rng = np.random.default_rng(0)
    n = 20000
    t, ang = rng.uniform(0, 1, n), rng.integers(0, 6, n) * 0.5  # lines in xy
    frame = rng.integers(0, 500, n)
    table = pd.DataFrame(
        {
            "frame": frame,
            "x_nm": 2000 + 4000 * t * np.cos(ang) + rng.normal(0, 15, n) + 0.02 * frame,
            "y_nm": 2000 + 4000 * t * np.sin(ang) + rng.normal(0, 15, n),
            "z_nm": rng.uniform(-800, 800, n),  # no structure in z: no z correlation
            "photons": 1000.0,
        }
    )
    locs = tmp_path / "locs.csv"
    table.to_csv(locs, index=False)
    out, plot = tmp_path / "dc.parquet", tmp_path / "drift.png"
    res = run("drift", locs, "-o", out, "--segments", 5, "--plot", plot)
    assert res.exit_code == 0, res.output
    assert "z drift not corrected (" in res.output and "x and y were" in res.output
    # item 8: the advice names the command's flags, not the library's arguments
    assert "--force" in res.output and "estimate_z" not in res.output
    from sparseloc.io.tables import read_table

    dc = read_table(out)
    assert np.allclose(np.sort(dc["z_nm"].to_numpy()), np.sort(table["z_nm"].to_numpy()))
    assert plot.exists()
    # the report of the corrected table checks the residual drift as the correction was made
    # (5 segments, x and y): it said "Unreliable: z ... use fewer segments" beside "already
    # drift-corrected"
    html = tmp_path / "r.html"
    assert run("report", out, "-o", html).exit_code == 0
    text = html.read_text()
    assert "already drift-corrected" in text
    assert "Unreliable" not in text and "fewer segments" not in text


@pytest.fixture(scope="module")
def locs_file(tmp_path_factory):
    from sparseloc.io.tables import complete_locs, write_table

    rng = np.random.default_rng(1)
    n = 200
    cols = {"frame": rng.integers(0, 20, n), "x_nm": rng.uniform(0, 3000, n),
            "y_nm": rng.uniform(0, 3000, n), "z_nm": rng.uniform(-400, 400, n),
            "sigma_x_nm": 10.0, "sigma_y_nm": 10.0, "sigma_z_nm": 20.0}  # fmt: skip
    locs = complete_locs(pd.DataFrame(cols))
    path = tmp_path_factory.mktemp("locs") / "locs.parquet"
    write_table(locs, path, pixel_size=100.0)
    truth = path.with_name("truth.csv")
    locs[["frame", "x_nm", "y_nm", "z_nm"]].assign(photons=1000.0).to_csv(truth, index=False)
    return path, truth


@pytest.mark.parametrize(
    ("command", "args", "flag"),
    [
        ("filter", ["--z-min", "-0.5", "--z-max", "0.5"], "--z-min/--z-max"),
        ("filter", ["--sigma-max", "0.03"], "--sigma-max"),
        ("render", ["--px", "0.005"], "--px"),
        ("evaluate", ["--lateral-tol", "0.25"], "--lateral-tol"),
        ("localize", ["--z-min", "-0.8", "--z-max", "0.8"], "--z-min/--z-max"),
        ("localize", ["--wavelength", "0.67"], "--wavelength"),
    ],
)
def test_other_lengths_in_micrometres_are_refused_as_such(
    locs_file, movie, tmp_path, command, args, flag
):
    """The fourth walk-through: micrometres were caught for --pixel-size and --z-step only;
    filter kept 2 of 3,179 rows or wrote an empty table, evaluate scored 0 %, a wavelength in
    um ended in 'the PSF stack contains NaN or inf values'."""
    locs, truth = locs_file
    if command == "filter":
        argv = ["filter", locs, "-o", tmp_path / "f.parquet"]
    elif command == "render":
        argv = ["render", locs, "-o", tmp_path / "r.png"]
    elif command == "evaluate":
        argv = ["evaluate", locs, truth]
    else:
        argv = ["localize", movie, "-o", tmp_path / "l.parquet", "--psf", "dh",
                "--pixel-size", 160]  # fmt: skip
    res = run(*argv, *args)
    refused(res, flag, "micrometres")
    assert not any(tmp_path.iterdir())


def test_report_and_overlay_check_that_the_movie_is_the_tables(movie, tmp_path):
    """The fourth walk-through: `report --movie` drew a 64 x 64 px table over a 332 x 492 px
    movie that `overlay` refused; a table recorded from another movie of the same size was
    drawn without a word."""
    from sparseloc.io.tables import complete_locs, write_table

    locs = complete_locs(pd.DataFrame({"frame": [0, 1], "x_nm": 1000.0, "y_nm": 1000.0,
                                       "z_nm": 0.0}))  # fmt: skip
    other = tmp_path / "other_size.parquet"
    write_table(locs, other, metadata={"shape": [64, 64], "movie": ["big.tif"]})
    for argv in (["report", other, "-o", tmp_path / "r.html", "--movie", movie],
                 ["overlay", movie, other, "-o", tmp_path / "o.png"]):  # fmt: skip
        refused(run(*argv), "is it the right movie")
    assert not (tmp_path / "r.html").exists() and not (tmp_path / "o.png").exists()
    renamed = tmp_path / "same_size.parquet"
    write_table(locs, renamed, metadata={"shape": [32, 32], "movie": ["elsewhere.tif"]})
    res = run("overlay", movie, renamed, "-o", tmp_path / "o.png")
    assert res.exit_code == 0, res.output
    assert "records the movie elsewhere.tif" in res.output


def test_frames_smaller_than_the_window_are_refused_up_front_with_the_fix(beads, tmp_path):
    """The fourth walk-through: a 32 x 32 px movie with a calibration's 43 px window failed
    chunk by chunk (8 warnings, exit 1, 'run the same command again') and left a run folder
    that made the corrected command need --overwrite."""
    psf = tmp_path / "psf.h5"
    res = run("calibrate", beads, "-o", psf, "--pixel-size", 100, "--z-step", 50)
    assert res.exit_code == 0, res.output
    small = tmp_path / "small.tif"
    res = run("simulate", "-o", small, "--psf", "dh-analytic", "--frames", 20, "--rows", 16,
              "--cols", 16, "--pixel-size", 100, "--seed", 1)  # fmt: skip
    assert res.exit_code == 0, res.output
    out = tmp_path / "small.parquet"
    res = run("localize", small, "-o", out, "--psf", psf, "--chunk-frames", 5)
    refused(res, "smaller than one window", "--window 16 or less")
    assert not out.exists() and not (tmp_path / "small.parquet.parts").exists()


def test_ctrl_c_in_any_command_says_so(beads, tmp_path, monkeypatch):
    """The fourth walk-through: Ctrl-C during calibrate printed nothing (localize said what
    happened)."""
    import sparseloc.calibrate as calibrate_module

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate_module, "calibrate_file", interrupted)
    out = tmp_path / "c.h5"
    res = run("calibrate", beads, "-o", out, "--pixel-size", 100, "--z-step", 50)
    assert res.exit_code == 130
    assert "interrupted (Ctrl-C): calibrate stopped and wrote no output" in res.output
    assert not out.exists()
