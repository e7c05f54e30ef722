"""Issue 27 item 20, redone: refusals that name their file or option (the flag, or the key and
file of a TOML config) and the true cause, one line each; no warning printed beside a
refusal, and none from a library's internals on a correct run."""

from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from cli_checks import refused, run
from sparseloc.io.tables import complete_locs, write_table
from sparseloc.io.tiff import write_tiff


def _locs(n: int, frames: int, *, flagged: int = 0, seed: int = 0) -> pd.DataFrame:
    """``n`` localizations spread over ``frames`` frames, the first ``flagged`` rows not 'ok'."""
    rng = np.random.default_rng(seed)
    t = complete_locs(
        pd.DataFrame(
            {
                "frame": np.sort(rng.integers(0, frames, n)),
                "x_nm": rng.uniform(100, 3000, n),
                "y_nm": rng.uniform(100, 3000, n),
                "z_nm": rng.uniform(-300, 300, n),
                "photons": rng.uniform(500, 5000, n),
                "sigma_x_nm": np.full(n, 10.0),
                "sigma_y_nm": np.full(n, 10.0),
                "sigma_z_nm": np.full(n, 20.0),
            }
        )
    )
    t.loc[t.index[:flagged], "flag"] = "z_edge"
    return t


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Small inputs, good and bad: a 32x32 movie of 4 frames, its truth, a table with flagged
    rows, a bead stack, maps, TOML files and damaged files."""
    d = tmp_path_factory.mktemp("audit")
    rng = np.random.default_rng(1)
    f: dict[str, Path] = {}
    f["movie"] = write_tiff(
        d / "movie.tif", rng.poisson(120, (4, 32, 32)).astype(np.uint16), pixel_size=100.0
    )
    f["other_movie"] = write_tiff(
        d / "other.tif", rng.poisson(120, (4, 16, 16)).astype(np.uint16), pixel_size=100.0
    )
    f["beads"] = write_tiff(
        d / "beads.tif", rng.poisson(120, (5, 32, 32)).astype(np.uint16), pixel_size=100.0
    )
    locs = _locs(60, 4, flagged=20)
    f["locs"] = d / "locs.parquet"
    write_table(locs, f["locs"], metadata={"params": {"pixel_size": 100.0}, "shape": [32, 32]})
    f["truth"] = d / "truth.csv"
    locs[["frame", "x_nm", "y_nm", "z_nm", "photons"]].to_csv(f["truth"], index=False)
    f["nocols_parquet"] = d / "nocols.parquet"
    pd.DataFrame({"a": [1.0], "b": [2.0]}).to_parquet(f["nocols_parquet"])
    f["xy_only"] = d / "xy_only.csv"
    pd.DataFrame({"x_nm": [1.0], "y_nm": [2.0]}).to_csv(f["xy_only"], index=False)
    f["map16"] = d / "map16.npy"
    np.save(f["map16"], np.full((16, 16), 100.0))
    f["bad_csv_map"] = d / "badmap.csv"
    f["bad_csv_map"].write_text("a,b\n1,2\n")
    f["bad_npy"] = d / "bad.npy"
    f["bad_npy"].write_bytes(b"garbage, not an array")
    f["other_h5"] = d / "other.h5"
    with h5py.File(f["other_h5"], "w") as h5:
        h5["x"] = np.arange(3)
    f["a_file"] = d / "a_file"
    f["a_file"].write_text("not a folder")
    tomls = {
        "cam_neg": "[camera]\ngain = -1\n",
        "loc_nan": "[localize]\nmin_snr = nan\n",
        "loc_window": "[localize]\nwindow = 0\n",
    }
    for name, text in tomls.items():
        f[name] = d / f"{name}.toml"
        f[name].write_text(text)
    return f


SIM = ("simulate", "--frames", "1", "--rows", "32", "--cols", "32", "--psf", "dh-analytic")
LOC = ("--psf", "dh-analytic", "--pixel-size", "100", "--frames", "0:1")

# (case id, command line with {name} for a file of the fixture and {out} for an output path,
#  words the one sentence must hold, words it must not hold)
CASES = [
    # simulate: the scene's options, named as flags (were pixel_size, z_range, ...)
    (
        "sim-pixel-size",
        [*SIM, "-o", "{out}.tif", "--pixel-size", "0"],
        ["--pixel-size"],
        ["pixel_size"],
    ),
    ("sim-density", [*SIM, "-o", "{out}.tif", "--density", "nan"], ["--density"], []),
    (
        "sim-photons",
        [*SIM, "-o", "{out}.tif", "--photons-min", "5000", "--photons-max", "100"],
        ["--photons-min", "--photons-max"],
        ["lo <= hi"],
    ),
    ("sim-background", [*SIM, "-o", "{out}.tif", "--background", "-1"], ["--background"], []),
    (
        "sim-z",
        [*SIM, "-o", "{out}.tif", "--z-min", "500", "--z-max", "-500"],
        ["--z-min", "--z-max"],
        ["z_range"],
    ),
    (
        "sim-cluster-size",
        [*SIM, "-o", "{out}.tif", "--scene", "clusters", "--cluster-size", "0"],
        ["--cluster-size"],
        [],
    ),
    ("sim-gain", [*SIM, "-o", "{out}.tif", "--gain", "-1"], ["--gain"], []),
    ("sim-qe", [*SIM, "-o", "{out}.tif", "--qe", "2"], ["--qe"], []),
    ("sim-camera", [*SIM, "-o", "{out}.tif", "--camera", "ccd"], ["--camera"], ["kind"]),
    # a TOML value is named as the file's key; a flag that overrides it, as the flag
    (
        "sim-toml-gain",
        [*SIM, "-o", "{out}.tif", "--config", "{cam_neg}"],
        ["gain in [camera] of cam_neg.toml"],
        [],
    ),
    (
        "sim-flag-over-toml",
        [*SIM, "-o", "{out}.tif", "--config", "{cam_neg}", "--gain", "-2"],
        ["--gain", "-2"],
        ["cam_neg.toml"],
    ),
    # sCMOS maps: were a TypeError traceback (the map and the scalar offset both passed)
    (
        "sim-map-unreadable",
        [*SIM, "-o", "{out}.tif", "--camera", "scmos", "--offset-map", "{bad_csv_map}"],
        ["badmap.csv"],
        [],
    ),
    (
        "sim-map-shape",
        [*SIM, "-o", "{out}.tif", "--camera", "scmos", "--offset-map", "{map16}"],
        ["--offset-map", "--rows"],
        [],
    ),
    # a damaged .npy mask: was NumPy's advice to pass allow_pickle=
    (
        "sim-bad-npy",
        ["simulate", "-o", "{out}.tif", "--frames", "1", "--psf", "{bad_npy}"],
        ["bad.npy", "not a NumPy array"],
        ["allow_pickle", "pickle"],
    ),
    (
        "sim-map-bad-npy",
        [*SIM, "-o", "{out}.tif", "--camera", "scmos", "--gain-map", "{bad_npy}"],
        ["gain map file", "bad.npy", "not a NumPy array"],
        ["allow_pickle"],
    ),
    # camera: accepted NaN and negative values, spoke of kind=
    ("camera-offset-nan", ["camera", "{movie}", "--offset", "nan"], ["--offset"], []),
    (
        "camera-offset-above-data",
        ["camera", "{movie}", "--offset", "60000"],
        ["--offset", "movie.tif", "median"],
        [],
    ),
    (
        "camera-read-noise",
        ["camera", "{movie}", "--read-noise", "-1"],
        ["--read-noise"],
        ["read_noise"],
    ),
    ("camera-kind", ["camera", "{movie}", "--camera", "ccd"], ["--camera"], ["kind"]),
    # evaluate: the note on flagged rows was printed before the refusal
    (
        "eval-lateral-tol",
        ["evaluate", "{locs}", "{truth}", "--lateral-tol", "-1"],
        ["--lateral-tol"],
        ["lateral_tol", "note"],
    ),
    (
        "eval-axial-tol",
        ["evaluate", "{locs}", "{truth}", "--axial-tol", "nan"],
        ["--axial-tol"],
        ["axial_tol"],
    ),
    # a table given for the truth: pandas' message ran over two lines
    ("eval-swapped", ["evaluate", "{truth}", "{locs}"], ["locs.parquet"], []),
    # render: px_nm; NaN read as "must be below"; a NaN voxel blamed on px_nm
    ("render-px", ["render", "{locs}", "-o", "{out}.png", "--px", "nan"], ["--px"], ["px_nm"]),
    (
        "render-voxel",
        ["render", "{locs}", "-o", "{out}.png", "--volume", "{out}.tif", "--voxel", "nan", "50"],
        ["--voxel"],
        ["px_nm"],
    ),
    (
        "render-z-min",
        ["render", "{locs}", "-o", "{out}.png", "--z-min", "nan"],
        ["--z-min", "number"],
        ["below"],
    ),
    (
        "render-no-columns",
        ["render", "{nocols_parquet}", "-o", "{out}.png"],
        ["table 'nocols.parquet'"],
        ["the nocols"],
    ),
    (
        "render-csv-no-frame",
        ["render", "{xy_only}", "-o", "{out}.png"],
        ["table 'xy_only.csv'", "frame"],
        ["the the"],
    ),
    # filter: Python argument names
    (
        "filter-photons",
        ["filter", "{locs}", "-o", "{out}.parquet", "--photons-min", "5000", "--photons-max", "10"],
        ["--photons-min", "--photons-max"],
        ["photons_min"],
    ),
    (
        "filter-sigma",
        ["filter", "{locs}", "-o", "{out}.parquet", "--sigma-max", "-1"],
        ["--sigma-max"],
        ["sigma_xy_max_nm"],
    ),
    (
        "filter-distance",
        ["filter", "{locs}", "-o", "{out}.parquet", "--merge", "--max-distance", "-1"],
        ["--max-distance"],
        ["max_distance_nm"],
    ),
    (
        "filter-z",
        ["filter", "{locs}", "-o", "{out}.parquet", "--z-min", "300", "--z-max", "-300"],
        ["--z-min", "--z-max"],
        ["z_range"],
    ),
    # drift: the note before the refusal; the number of segments not named as --segments
    ("drift-segments", ["drift", "{locs}", "-o", "{out}.parquet"], ["--segments"], ["note"]),
    (
        "drift-bin",
        ["drift", "{locs}", "-o", "{out}.parquet", "--segments", "3", "--bin-nm", "nan"],
        ["--bin-nm"],
        ["bin_nm"],
    ),
    # overlay: a movie of another size, neither file named
    (
        "overlay-movie",
        ["overlay", "{other_movie}", "{locs}", "-o", "{out}.png"],
        ["other.tif", "locs.parquet"],
        [],
    ),
    # calibrate: wrong causes (metadata disagreement, no beads, saturated beads)
    (
        "cal-pixel-size",
        ["calibrate", "{beads}", "-o", "{out}.h5", "--z-step", "50", "--pixel-size", "0"],
        ["--pixel-size", "positive"],
        ["disagrees"],
    ),
    (
        "cal-threshold",
        [
            "calibrate",
            "{beads}",
            "-o",
            "{out}.h5",
            "--z-step",
            "50",
            "--pixel-size",
            "100",
            "--threshold",
            "2",
        ],
        ["--threshold", "(0, 1]"],
        ["no beads"],
    ),
    (
        "cal-figure",
        [
            "calibrate",
            "{beads}",
            "-o",
            "{out}.h5",
            "--z-step",
            "50",
            "--pixel-size",
            "100",
            "--figure",
            "{out}.txt",
        ],
        ["--figure", ".png"],
        ["supported formats"],
    ),
    (
        "cal-saturation",
        [
            "calibrate",
            "{beads}",
            "-o",
            "{out}.h5",
            "--z-step",
            "50",
            "--pixel-size",
            "100",
            "--saturation",
            "-1",
        ],
        ["--saturation"],
        ["saturated"],
    ),
    # localize: flags and TOML keys
    (
        "loc-min-snr",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--min-snr", "nan"],
        ["--min-snr"],
        ["min_snr"],
    ),
    (
        "loc-toml-min-snr",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--config", "{loc_nan}"],
        ["min_snr in loc_nan.toml"],
        [],
    ),
    (
        "loc-toml-window",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--config", "{loc_window}"],
        ["window in loc_window.toml"],
        [],
    ),
    (
        "loc-window",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--window", "0"],
        ["--window"],
        [],
    ),
    (
        "loc-frame-schedule",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--frame-schedule", "xyz"],
        ["--frame-schedule"],
        ["frame_schedule"],
    ),
    (
        "loc-map",
        [
            "localize",
            "{movie}",
            *LOC,
            "-o",
            "{out}.parquet",
            "--camera",
            "scmos",
            "--offset-map",
            "{bad_csv_map}",
        ],
        ["badmap.csv"],
        [],
    ),
    (
        "loc-na",
        [
            "localize",
            "{movie}",
            "--psf",
            "dh",
            "--pixel-size",
            "100",
            "-o",
            "{out}.parquet",
            "--na",
            "2",
        ],
        ["--na", "1.518"],
        ["n_immersion"],
    ),
    (
        "loc-na-calibration",
        [
            "localize",
            "{movie}",
            "--psf",
            "astig-gauss",
            "--pixel-size",
            "100",
            "-o",
            "{out}.parquet",
            "--na",
            "1.2",
        ],
        ["--na applies"],
        [],
    ),
    (
        "loc-run-dir",
        ["localize", "{movie}", *LOC, "-o", "{out}.parquet", "--run-dir", "{a_file}"],
        ["--run-dir", "a_file"],
        [],
    ),
]


@pytest.mark.parametrize(
    ("args", "words", "absent"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_refusal_names_its_flag_file_and_cause(files, tmp_path, args, words, absent):
    names = {k: str(v) for k, v in files.items()}
    res = run(*(a.format(out=tmp_path / "out", **names) for a in args))
    refused(res, *words)
    for w in absent:
        assert w not in res.stderr, res.stderr


def test_no_note_before_a_refusal_but_after_a_success(files, tmp_path):
    """The note on flagged rows left out belongs to a run that did its work."""
    res = run("render", files["locs"], "-o", tmp_path / "i.png", "--px", "-1")
    refused(res, "--px")
    res = run("evaluate", files["locs"], files["truth"])
    assert res.exit_code == 0, res.output
    assert "note: excluded 20 flagged localizations" in res.stderr


@pytest.fixture(scope="module")
def drifting(tmp_path_factory) -> Path:
    """200 frames of scattered localizations: no structure to correlate, an unreliable drift."""
    path = tmp_path_factory.mktemp("drift") / "t.parquet"
    write_table(
        _locs(2500, 200, seed=3),
        path,
        metadata={"params": {"pixel_size": 100.0}, "shape": [32, 32]},
    )
    return path


def _drift_logs(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("sparseloc.drift")]


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_unreliable_drift_is_refused_in_one_sentence_with_its_reasons(drifting, tmp_path, caplog):
    plot = tmp_path / "drift.png"
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        res = run(
            "drift", drifting, "-o", tmp_path / "d.parquet", "--segments", "4", "--plot", plot
        )
    refused(res, "unreliable", "--force")
    assert "see the warnings above" not in res.stderr
    assert not _drift_logs(caplog), caplog.messages  # the reasons are in the sentence
    # nothing written: a plot left behind would block the rerun the refusal suggests
    assert not (tmp_path / "d.parquet").exists() and not plot.exists()


def test_forced_drift_says_its_warnings_once(drifting, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        res = run("drift", drifting, "-o", tmp_path / "d.parquet", "--segments", "4", "--force")
    assert res.exit_code == 0, res.output
    assert "warning: " in res.stderr
    assert not _drift_logs(caplog), caplog.messages


def test_report_states_an_unreliable_drift_without_logging_it(drifting, tmp_path, caplog):
    """The report (and the demo, which writes one) said the drift's warnings twice: in the
    report and as log lines on the terminal of a correct run."""
    out = tmp_path / "r.html"
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        res = run("report", drifting, "-o", out)
    assert res.exit_code == 0, res.output
    assert "Unreliable" in out.read_text()
    assert not _warnings(caplog)  # nor the FRC's, which the report states too


def test_render_states_an_undetermined_frc_once(drifting, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        res = run("render", drifting, "-o", tmp_path / "i.png")
    assert res.exit_code == 0, res.output
    assert "FRC resolution: not determined" in res.stdout
    assert not _warnings(caplog)


def test_a_fit_flagged_bad_sigma_is_written_without_a_warning(tmp_path, caplog):
    """``bad_sigma``, a flag of sparseloc's own fits, had no ThunderSTORM code: every CSV
    export of a correct run warned that it was written as 'other' (and read back so)."""
    from sparseloc.io.tables import read_table

    t = _locs(3, 2)
    t["flag"] = ["ok", "bad_sigma", "z_edge"]
    path = tmp_path / "t.csv"
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        write_table(t, path)
    assert not _warnings(caplog)
    assert list(read_table(path)["flag"]) == ["ok", "bad_sigma", "z_edge"]


@pytest.mark.parametrize("command", ["render", "report", "drift", "filter"])
def test_no_warning_before_a_refusal_of_the_same_cause(tmp_path, caplog, command):
    """A table whose every row has an absurd coordinate: one refusal, not a warning that the
    rows were dropped followed by a refusal that none is usable."""
    t = _locs(3, 3)
    t["x_nm"] = [np.inf, 1e300, np.nan]
    path = tmp_path / "t.parquet"
    write_table(t, path, metadata={"params": {"pixel_size": 100.0}, "shape": [32, 32]})
    ext = {"render": ".png", "report": ".html"}.get(command, ".parquet")
    with caplog.at_level(logging.WARNING, logger="sparseloc"):
        res = run(command, path, "-o", tmp_path / f"out{ext}")
    refused(res, "none of the 3 localizations is usable")
    assert not _warnings(caplog), caplog.messages


def test_a_file_attribute_is_not_read_as_a_flag(files, tmp_path):
    """A guard of the translation of argument names into flags (passes before the fix too):
    ``format='sparseloc-psf'``, an attribute the file lacks, is not ``--format``."""
    res = run(
        "localize", files["movie"], "--psf", files["other_h5"], "--pixel-size", "100",
        "-o", tmp_path / "l.parquet",
    )  # fmt: skip
    refused(res, "other.h5", "format='sparseloc-psf'")
    assert "--format" not in res.stderr
