"""The command line: real runs end to end, and bad input as one sentence with exit code 2."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from cli_checks import run, runner
from sparseloc.cli import app


def test_simulate_then_evaluate(tmp_path):
    out = tmp_path / "movie.tif"
    res = run(
        "simulate",
        "-o",
        out,
        "--psf",
        "dh-analytic",
        "--frames",
        "3",
        "--rows",
        "32",
        "--cols",
        "32",
        "--density",
        "1.0",
        "--seed",
        "4",
    )
    assert res.exit_code == 0, res.output
    truth = tmp_path / "movie_truth.csv"
    assert out.is_file() and truth.is_file()
    df = pd.read_csv(truth)
    assert list(df.columns[:5]) == ["frame", "x_nm", "y_nm", "z_nm", "photons"]
    # the truth scored against itself is perfect
    res = run("evaluate", truth, truth, "--json", tmp_path / "eval.json")
    assert res.exit_code == 0, res.output
    assert "100" in res.output
    assert (tmp_path / "eval.json").is_file()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["simulate", "-o", "{tmp}/m.tif", "--psf", "helix"], "unknown PSF 'helix'"),
        (["simulate", "-o", "{tmp}/m.tif", "--pixel-size", "-5"], "--pixel-size"),
        (["simulate", "-o", "{tmp}/missing/m.tif"], "does not exist"),
        (["simulate", "-o", "{tmp}/m.png"], ".tif"),
        (["evaluate", "{tmp}/nope.csv", "{tmp}/nope.csv"], "does not exist"),
    ],
)
def test_bad_input_is_one_sentence_and_exit_2(tmp_path, args, message):
    res = run(*[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert "Traceback" not in res.output
    assert not list(tmp_path.glob("*.tif"))  # nothing half-written


def test_mask_file_that_is_not_2d(tmp_path):
    import numpy as np

    mask = tmp_path / "mask.npy"
    np.save(mask, np.zeros((3, 4, 5)))
    res = run("simulate", "-o", tmp_path / "m.tif", "--psf", mask)
    assert res.exit_code == 2
    assert "must be 2-D" in res.output


def test_demo_runs_and_writes_its_outputs(tmp_path):
    from sparseloc.io.tables import read_table

    out = tmp_path / "demo"
    res = run("demo", "-o", out, "--frames", "12")
    assert res.exit_code == 0, res.output
    for name in ("movie.tif", "locs.parquet", "render.png", "frame0.png", "psf.png"):
        assert (out / name).stat().st_size > 1000
    report = (out / "report.txt").read_text()
    assert "Jaccard" in report and "RMSE" in report and "Jaccard" in res.output
    locs = read_table(out / "locs.parquet")
    assert len(locs) > 50 and locs["frame"].max() <= 11


def test_demo_refuses_a_bad_density(tmp_path):
    res = run("demo", "-o", tmp_path / "d", "--density", "0")
    assert res.exit_code == 2
    assert "density" in res.output


def test_entry_point_is_installed():
    res = subprocess.run(
        [sys.executable, "-m", "sparseloc.cli", "--help"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert res.returncode == 0
    assert "simulate" in res.stdout and "evaluate" in res.stdout


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".hdf5"])
def test_evaluate_reads_every_table_format(tmp_path, suffix):
    from sparseloc.io.tables import complete_locs, write_table

    truth = pd.DataFrame(
        {
            "frame": [0, 0, 1],
            "x_nm": [500.0, 1500.0, 800.0],
            "y_nm": [600.0, 700.0, 900.0],
            "z_nm": [-100.0, 50.0, 200.0],
            "photons": [1000.0, 2000.0, 1500.0],
        }
    )
    truth_path = tmp_path / "truth.csv"
    truth.to_csv(truth_path, index=False)
    locs = complete_locs(truth)
    locs["x_nm"] += 10.0
    out = tmp_path / f"locs{suffix}"
    write_table(locs, out, pixel_size=100.0, shape=(32, 32), n_frames=2, metadata={})
    res = run("evaluate", out, truth_path)
    assert res.exit_code == 0, res.output
    assert "100.0" in res.output  # Jaccard


def test_localize_a_small_movie_and_refuse_bad_input(tmp_path):
    movie = tmp_path / "m.tif"
    res = run(
        "simulate",
        "-o",
        movie,
        "--psf",
        "dh-analytic",
        "--frames",
        "2",
        "--rows",
        "32",
        "--cols",
        "32",
        "--pixel-size",
        "160",
        "--density",
        "0.15",
        "--photons-min",
        "3000",
        "--photons-max",
        "4000",
        "--z-min",
        "-300",
        "--z-max",
        "300",
        "--seed",
        "3",
    )
    assert res.exit_code == 0, res.output
    cfg = tmp_path / "run.toml"
    cfg.write_text(
        '[localize]\npsf = "dh-analytic"\npixel_size = 160.0\nz_min = -300.0\nz_max = 300.0\n'
    )
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", out, "--config", cfg)
    assert res.exit_code == 0, res.output
    assert "localizations" in res.output and "frames" in res.output
    assert "1 process" in res.output  # two frames: no pool (see test_default_workers)
    from sparseloc.io.tables import read_parquet

    table, meta = read_parquet(out)
    assert len(table) >= 8 and meta["params"]["pixel_size"] == 160.0
    # the NumPy reference engine through the command line gives the same table
    out_b = tmp_path / "locs_b.parquet"
    res = run("localize", movie, "-o", out_b, "--config", cfg, "--engine", "numpy")
    assert res.exit_code == 0, res.output
    table_b, meta_b = read_parquet(out_b)
    assert meta_b["params"]["engine"] == "numpy" and len(table_b) == len(table)
    assert np.allclose(table_b["x_nm"], table["x_nm"], atol=1e-3)
    assert meta["params"]["relocate"] == 2  # the default, recorded with the table
    out_r = tmp_path / "locs_r.parquet"
    res = run("localize", movie, "-o", out_r, "--config", cfg, "--relocate", "0")
    assert res.exit_code == 0, res.output
    assert read_parquet(out_r)[1]["params"]["relocate"] == 0
    for key, flag in (("second_start", "--no-second-start"), ("regrow", "--no-regrow")):
        assert meta["params"][key] is True  # the default
        res = run("localize", movie, "-o", tmp_path / f"{key}.parquet", "--config", cfg, flag)
        assert res.exit_code == 0, res.output
        assert read_parquet(tmp_path / f"{key}.parquet")[1]["params"][key] is False
        cfg_off = tmp_path / f"{key}.toml"
        cfg_off.write_text(cfg.read_text() + f"{key} = false\n")
        res = run("localize", movie, "-o", tmp_path / f"{key}_t.parquet", "--config", cfg_off)
        assert res.exit_code == 0, res.output
        assert read_parquet(tmp_path / f"{key}_t.parquet")[1]["params"][key] is False
    assert meta["params"]["haze"] is False  # the default
    res = run("localize", movie, "-o", tmp_path / "locs_h.parquet", "--config", cfg, "--haze")
    assert res.exit_code == 0, res.output
    assert read_parquet(tmp_path / "locs_h.parquet")[1]["params"]["haze"] is True
    # bad input: wrong pixel size, offset above the data, missing folder, unknown config key
    for args, msg in [
        (["--config", cfg, "--pixel-size", "100"], "differs from the movie"),
        (["--config", cfg, "--offset", "5000"], "offset"),
        (["--config", cfg, "--n-sample", "1.33"], "apply to pupil models"),
        (["--config", cfg, "--psf", "dh", "--focal-depth", "500"], "needs --n-sample"),
        (["--config", cfg, "--engine", "tpu"], "engine must be one of auto, numpy, numba"),
        (["--config", cfg, "--min-snr", "nan"], "--min-snr must be a number > 0"),
        (["--config", cfg, "--frames", "0:100"], "goes past the movie's 2 frames"),
        (["--config", cfg, "--relocate", "-1"], "relocate"),
    ]:
        res = run("localize", movie, "-o", tmp_path / "x.csv", *args)
        assert res.exit_code == 2 and msg in res.output, res.output
    # a TOML chunk_frames of 0 is refused, not replaced by the default
    cfg0 = tmp_path / "zero.toml"
    cfg0.write_text(cfg.read_text() + "chunk_frames = 0\n")
    res = run("localize", movie, "-o", tmp_path / "z.parquet", "--config", cfg0)
    assert res.exit_code == 2 and "chunk_frames in zero.toml must be >= 1" in res.output, res.output
    res = run("localize", movie, "-o", tmp_path / "no" / "x.csv", "--config", cfg)
    assert res.exit_code == 2 and "does not exist" in res.output
    bad = tmp_path / "bad.toml"
    bad.write_text("pixelsize = 160\n")
    res = run("localize", movie, "-o", tmp_path / "x.csv", "--config", bad)
    assert res.exit_code == 2 and "unknown keys" in res.output
    assert not (tmp_path / "x.csv").exists()


def test_default_workers(monkeypatch):
    # one process per available core, at most AUTO_WORKERS_CAP and one per
    # MIN_FRAMES_PER_WORKER frames, never fewer than one
    from sparseloc import cli, pool

    monkeypatch.setattr(pool, "available_cores", lambda: 6)
    assert cli._auto_workers(1000) == 6
    assert cli._auto_workers(3 * cli.MIN_FRAMES_PER_WORKER) == 3
    assert cli._auto_workers(2) == 1
    monkeypatch.setattr(pool, "available_cores", lambda: 64)
    assert cli._auto_workers(10**6) == cli.AUTO_WORKERS_CAP


def test_available_cores(monkeypatch):
    from sparseloc import pool

    monkeypatch.setattr(pool, "_cpu_quota", lambda: None)
    monkeypatch.setattr(pool.os, "sched_getaffinity", lambda pid: set(range(6)), raising=False)
    assert pool.available_cores() == 6
    monkeypatch.setattr(pool, "_cpu_quota", lambda: 2.5)  # a container limited to 2.5 CPUs
    assert pool.available_cores() == 2
    monkeypatch.setattr(pool, "_cpu_quota", lambda: 0.5)
    assert pool.available_cores() == 1
    # where the platform cannot tell the affinity: the CPU count
    monkeypatch.setattr(pool, "_cpu_quota", lambda: None)
    monkeypatch.delattr(pool.os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(pool.os, "cpu_count", lambda: 3)
    assert pool.available_cores() == 3
    monkeypatch.setattr(pool.os, "cpu_count", lambda: None)
    assert pool.available_cores() == 1


def test_cpu_quota_from_cgroup_files(tmp_path):
    from sparseloc.pool import _cpu_quota

    assert _cpu_quota(tmp_path) is None  # nothing there
    (tmp_path / "cpu.max").write_text("max 100000\n")  # cgroup v2, no limit
    assert _cpu_quota(tmp_path) is None
    (tmp_path / "cpu.max").write_text("200000 100000\n")
    assert _cpu_quota(tmp_path) == 2.0
    (tmp_path / "cpu.max").write_text("garbage\n")
    assert _cpu_quota(tmp_path) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")  # cgroup v1, no limit
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert _cpu_quota(v1) is None
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("150000\n")
    assert _cpu_quota(v1) == 1.5


def test_frame_range_refuses_negative_frames(tmp_path):
    from sparseloc.config import frame_range
    from sparseloc.io.tiff import write_tiff

    assert frame_range("2:", 6) == (2, 6) and frame_range(":4", 6) == (0, 4)
    for bad in ("-1:", "0:-2"):
        with pytest.raises(ValueError, match="0-based frame numbers >= 0"):
            frame_range(bad, 6)
    # as typed on the command line: refused in the terms of frame numbers, not of a range
    movie = write_tiff(tmp_path / "m.tif", np.full((6, 16, 16), 110, np.uint16), pixel_size=100.0)
    out = tmp_path / "l.parquet"
    res = run("localize", movie, "--psf", "astig-gauss", "--frames=-1:", "-o", out)
    assert res.exit_code == 2 and "0-based frame numbers >= 0" in res.stderr, res.output
    assert not out.exists()


def test_help_wraps_the_description_at_the_terminals_width():
    """A command's description is wrapped at the terminal's width, not at its docstring's
    line ends (which left lines of a few words at 80 columns)."""
    res = runner.invoke(app, ["render", "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0
    lines = [ln.strip() for ln in res.output.splitlines()]
    assert any("rows with a non-finite or absurd coordinate are dropped" in ln for ln in lines)


def test_version_and_the_camera_defaults_in_help():
    from sparseloc import __version__
    from sparseloc.options import LOCALIZE_DEFAULTS

    res = run("--version")
    assert res.exit_code == 0 and res.output.strip() == f"sparseloc {__version__}"
    wide = runner.invoke(app, ["localize", "--help"], env={"COLUMNS": "200"})
    text = " ".join(wide.output.split())
    for flag, shown in (("offset", "ADU; default"), ("gain", "e-/ADU; default")):
        assert f"{shown} {LOCALIZE_DEFAULTS[flag]:g}" in text, text
    assert "--psf" in text and "Needed: PSF.h5 from 'calibrate'" in text
    # the solver's and the camera's defaults are shown too, from the same configuration
    from sparseloc.config import LocalizeParams

    assert f"(default {LocalizeParams(pixel_size=100.0).min_snr:g})" in text
    assert "ideal, emccd or scmos (default ideal)" in text
    assert "auto (default: temporal from 50 frames)" in text
    wide = runner.invoke(app, ["calibrate", "--help"], env={"COLUMNS": "200"})
    flat = " ".join(wide.output.split())
    assert "(fraction of the brightest unsaturated bead). [default: 0.2]" in flat
    assert "work: auto (default:" in text


def test_a_shells_alphabetical_file_order_is_refused_not_read(tmp_path):
    """Single-frame files numbered without padding, as a shell expands an unquoted pattern
    (plain_0, plain_1, plain_10, plain_11, plain_2, ...): read in that order the movie's
    frames are shuffled and every table from it wrong, so the command refuses and says to
    quote the pattern; the quoted pattern reads them in their numbers' order."""
    from cli_checks import refused
    from sparseloc.io.movie import Movie
    from sparseloc.io.tiff import write_tiff

    for k in range(12):
        write_tiff(tmp_path / f"plain_{k}.tif", np.full((16, 16), 100 + k, np.uint16))
    shell = sorted(str(p) for p in tmp_path.glob("plain_*.tif"))
    out = tmp_path / "l.parquet"
    res = run("localize", *shell, "--psf", "astig-gauss", "--pixel-size", 100, "-o", out)
    refused(res, "quote the pattern", "'plain_10.tif' before 'plain_2.tif'")
    assert not out.exists()
    with Movie.open(str(tmp_path / "plain_*.tif")) as mov:
        assert mov.frames()[:, 0, 0].tolist() == list(range(100, 112))
    numbered = sorted(shell, key=lambda s: int(s.rsplit("_", 1)[1].split(".")[0]))
    res = run("camera", *numbered, "--frames", "12")
    assert "quote the pattern" not in res.output
