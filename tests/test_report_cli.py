"""The quality report, and the render / drift / filter / report commands."""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.cli import app
from sparseloc.io.tables import complete_locs, write_table
from sparseloc.report import build_report, write_report
from sparseloc.simulate import filament_scene


@pytest.fixture(scope="module")
def scene():
    """Blinking filaments over 400 frames: truth, and localizations = truth + noise."""
    rng = np.random.default_rng(3)
    truth = filament_scene(rng, 400, (6400.0, 6400.0), n_filaments=3, z_range=(-400.0, 400.0))
    n = len(truth)
    locs = truth[["frame", "x_nm", "y_nm", "z_nm", "photons"]].copy()
    locs["x_nm"] += rng.normal(0, 12, n)
    locs["y_nm"] += rng.normal(0, 12, n)
    locs["z_nm"] += rng.normal(0, 30, n)
    locs["sigma_x_nm"] = 12.0
    locs["sigma_y_nm"] = 12.0
    locs["sigma_z_nm"] = 30.0
    locs["gof"] = rng.normal(1.0, 0.05, n)
    return complete_locs(locs), truth


class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.open: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        if tag not in ("img", "meta", "br"):
            self.open.append(tag)

    def handle_endtag(self, tag):
        assert self.open and self.open[-1] == tag, f"</{tag}> closes <{self.open[-1:]}>"
        self.open.pop()


def test_report_has_every_section(scene):
    locs, truth = scene
    assert len(locs) > 2000  # the drift section runs
    page = build_report(locs, truth=truth, metadata={"psf": "dh"})
    parser = _Collect()
    parser.feed(page)
    assert parser.open == []  # every element closed
    for heading in (
        "Summary",
        "Distributions",
        "Localizations per frame",
        "Drift",
        "Rendered image",
        "Against the ground truth",
        "Metadata",
    ):
        assert f"<h2>{heading}" in page
    expected = int(re.search(r'data-figures-expected="(\d+)"', page).group(1))
    assert expected == parser.tags.count("img") == 5
    assert "FRC resolution" in page
    assert "Jaccard" in page


def test_report_without_truth_or_enough_frames(scene):
    locs, _ = scene
    few = locs[locs.frame < 2]
    page = build_report(few)
    assert "Against the ground truth" not in page
    assert "Not estimated" in page
    # the fifth walk-through: a corrected table too short for the report's own estimate was
    # "Not estimated" under metadata saying it was corrected; the report now uses the drift
    # command's rule (50 frames of this scene: estimated, as `sparseloc drift` does) and says
    # what was done
    assert "Not estimated" not in build_report(locs[locs.frame < 50])
    done = build_report(few, metadata={"drift": {"method": "rcc", "reliable": True}})
    assert "already drift-corrected" in done and "residual drift is not estimated" in done
    with pytest.raises(ValueError, match="empty"):
        build_report(locs.iloc[:0])


def test_report_refuses_a_bad_path(scene, tmp_path):
    locs, _ = scene
    with pytest.raises(ValueError, match=r"\.html"):
        write_report(locs, tmp_path / "r.pdf")
    with pytest.raises(ValueError, match="does not exist"):
        write_report(locs, tmp_path / "no" / "r.html")


@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs Debian's chromium")
def test_report_opens_in_headless_chromium(scene, tmp_path):
    locs, truth = scene
    path = write_report(locs, tmp_path / "report.html", truth=truth)
    res = subprocess.run(
        [
            "chromium",
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--enable-logging=stderr",
            "--v=0",
            "--virtual-time-budget=10000",
            "--dump-dom",
            path.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr[-2000:]
    # the page's own check: every figure decoded
    m = re.search(r'data-figures-ok="(\d+)/(\d+)"', res.stdout)
    assert m is not None, res.stdout[:500]
    assert m.group(1) == m.group(2) == "5"
    console = [ln for ln in res.stderr.splitlines() if "CONSOLE" in ln]
    assert not [ln for ln in console if "Uncaught" in ln or "rror" in ln], console


# --- commands ------------------------------------------------------------------------------


@pytest.fixture
def table_file(scene, tmp_path):
    locs, truth = scene
    path = tmp_path / "locs.parquet"
    write_table(
        locs, path, metadata={"params": {"pixel_size": 100.0}, "shape": [64, 64], "psf": "dh"}
    )
    tpath = tmp_path / "truth.csv"
    truth[["frame", "x_nm", "y_nm", "z_nm", "photons"]].to_csv(tpath, index=False)
    return path, tpath


def test_render_command(table_file, tmp_path):
    import tifffile

    path, _ = table_file
    out = tmp_path / "img.png"
    vol = tmp_path / "vol.tif"
    res = CliRunner().invoke(
        app,
        [
            "render",
            str(path),
            "-o",
            str(out),
            "--volume",
            str(vol),
            "--frc",
            str(tmp_path / "f.png"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert out.stat().st_size > 10_000 and (tmp_path / "f.png").exists()
    assert "FRC resolution" in res.output
    assert tifffile.imread(vol).ndim == 3
    bad = CliRunner().invoke(app, ["render", str(path), "-o", str(tmp_path / "img.jpg")])
    assert bad.exit_code == 2 and ".png" in bad.output
    missing = CliRunner().invoke(
        app, ["render", str(tmp_path / "x.parquet"), "-o", str(out), "--overwrite"]
    )
    assert missing.exit_code == 2 and "does not exist" in missing.output


def test_filter_and_merge_command(table_file, tmp_path):
    from sparseloc.io.tables import read_parquet

    path, _ = table_file
    out = tmp_path / "f.parquet"
    res = CliRunner().invoke(
        app,
        ["filter", str(path), "-o", str(out), "--photons-min", "1500", "--gof-max", "1.05"],
    )
    assert res.exit_code == 0, res.output
    kept, meta = read_parquet(out)
    assert len(kept) > 0 and kept.photons.min() >= 1500 and kept.gof.max() <= 1.05
    assert meta["psf"] == "dh"  # the input's metadata travels
    out2 = tmp_path / "m.parquet"
    res = CliRunner().invoke(app, ["filter", str(path), "-o", str(out2), "--merge"])
    assert res.exit_code == 0, res.output
    merged, _ = read_parquet(out2)
    assert len(merged) < len(pd.read_parquet(path))
    out3 = tmp_path / "m.hdf5"
    res = CliRunner().invoke(app, ["filter", str(path), "-o", str(out3)])
    assert res.exit_code == 0, res.output  # pixel size and shape come from the metadata


def test_drift_command(table_file, tmp_path):
    path, _ = table_file
    out = tmp_path / "d.parquet"
    res = CliRunner().invoke(
        app,
        ["drift", str(path), "-o", str(out), "--plot", str(tmp_path / "d.png"), "--force"],
    )
    assert res.exit_code == 0, res.output
    assert out.exists() and (tmp_path / "d.png").exists()
    bad = CliRunner().invoke(
        app, ["drift", str(path), "-o", str(out), "--method", "beads", "--overwrite"]
    )
    assert bad.exit_code == 2 and "rcc or fiducial" in bad.output


def test_report_command(table_file, tmp_path):
    path, tpath = table_file
    out = tmp_path / "r.html"
    res = CliRunner().invoke(app, ["report", str(path), "-o", str(out), "--truth", str(tpath)])
    assert res.exit_code == 0, res.output
    page = out.read_text()
    assert "Jaccard" in page and "pixel_size" in page
    bad = CliRunner().invoke(app, ["report", str(path), "-o", str(tmp_path / "r.txt")])
    assert bad.exit_code == 2 and not (tmp_path / "r.txt").exists()


def test_drift_command_corrects_and_refuses_unreliable_estimates(scene, tmp_path):
    from sparseloc.io.tables import read_parquet

    locs, _ = scene
    drifted = locs.copy()
    drifted["x_nm"] += 0.5 * drifted["frame"]  # 200 nm over the 400 frames
    path = tmp_path / "d.parquet"
    write_table(drifted, path, metadata={})
    out = tmp_path / "c.parquet"
    res = CliRunner().invoke(app, ["drift", str(path), "-o", str(out), "--no-z"])
    assert res.exit_code == 0, res.output
    fixed, _ = read_parquet(out)
    late = drifted.frame > 300
    err_before = np.abs(drifted.x_nm[late] - locs.x_nm[late]).mean()
    err_after = np.abs(fixed.x_nm.to_numpy()[late.to_numpy()] - locs.x_nm[late]).mean()
    assert err_before > 150 and err_after < 30
    # a handful of localizations: no estimate, one sentence, no table
    few = tmp_path / "few.parquet"
    write_table(drifted.iloc[::40], few, metadata={})
    out2 = tmp_path / "c2.parquet"
    res = CliRunner().invoke(app, ["drift", str(few), "-o", str(out2)])
    assert res.exit_code == 2 and not out2.exists()
    assert "Traceback" not in res.output


def test_render_short_and_wide_tables(tmp_path):
    rng = np.random.default_rng(1)
    n = 400
    for name, frames, width in (("short", 10, 5000.0), ("wide", 100, 200_000.0)):
        t = complete_locs(
            pd.DataFrame(
                {
                    "frame": rng.integers(0, frames, n),
                    "x_nm": rng.uniform(0, width, n),
                    "y_nm": rng.uniform(0, 5000.0, n),
                    "z_nm": rng.uniform(-300, 300, n),
                }
            )
        )
        path = tmp_path / f"{name}.parquet"
        write_table(t, path, metadata={})
        out = tmp_path / f"{name}.png"
        res = CliRunner().invoke(app, ["render", str(path), "-o", str(out)])
        assert res.exit_code == 0, res.output
        assert out.exists() and "FRC" in res.output


def test_commands_check_their_outputs_before_working(table_file, tmp_path):
    path, _ = table_file
    for args, msg in [
        (["render", str(path), "-o", str(tmp_path / "a.png"), "--frc", str(tmp_path / "f.xyz")],
         "--frc"),
        (["drift", str(path), "-o", str(tmp_path / "d.txt")], "txt"),
        (["filter", str(path), "-o", str(tmp_path / "f.xyz")], "xyz"),
    ]:  # fmt: skip
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and msg in res.output, res.output
    assert not list(tmp_path.glob("a.png")) and not list(tmp_path.glob("d.*"))


def test_the_report_of_a_drift_corrected_table_speaks_of_residual_drift(scene):
    """The third walk-through: the report of a table that ``sparseloc drift`` had corrected
    said "(not applied here; see sparseloc drift)" beside metadata saying it was."""
    locs, _ = scene
    plain = build_report(locs, metadata={"psf": "dh"})
    assert "not applied here" in plain and "already drift-corrected" not in plain
    done = build_report(locs, metadata={"psf": "dh", "drift": {"method": "rcc", "reliable": True}})
    assert "already drift-corrected" in done and "residual drift" in done
    assert "not applied here" not in done
    # the scene does not drift: the report says so, as the drift command does; on a corrected
    # table the same finding says the correction left no drift (not a caution against it)
    assert "like noise" in plain and "Caution:" in plain
    assert "the correction left none" in done and "Caution:" not in done


def test_the_reports_truth_section_cautions_as_evaluate_does(scene):
    """The fourth walk-through's wrong truth file: the report's evaluation gets the caution
    that `evaluate` prints (the same functions)."""
    locs, truth = scene
    right = build_report(locs, truth=truth, metadata={"psf": "dh"})
    assert "is it the truth of this movie" not in right
    moved = truth.assign(x_nm=truth["x_nm"] + 3000.0, y_nm=truth["y_nm"] + 3000.0)
    wrong = build_report(locs, truth=moved, metadata={"psf": "dh"})
    assert "is it the truth of this movie" in wrong


def test_report_truth_in_pixels_takes_the_tables_pixel_size(scene, tmp_path):
    """The review of the fifth walk-through's fix: evaluate took the table's pixel size for
    truth in pixels, report --truth still refused without --pixel-size (one rule now)."""
    from sparseloc.io.tables import write_table

    locs, truth = scene
    path = tmp_path / "locs.parquet"
    write_table(locs, path, metadata={"params": {"pixel_size": 100.0}})
    px = tmp_path / "truth_px.csv"
    pd.DataFrame({"frame_0based": truth["frame"], "x_px": truth["x_nm"] / 100.0 - 0.5,
                  "y_px": truth["y_nm"] / 100.0 - 0.5, "z_um": truth["z_nm"] / 1000.0,
                  "photons_sum": 1000.0}).to_csv(px, index=False)  # fmt: skip
    out = tmp_path / "r.html"
    res = CliRunner().invoke(app, ["report", str(path), "-o", str(out), "--truth", str(px)])
    assert res.exit_code == 0, res.output
    assert "at the table's pixel size of 100 nm" in res.output and "Jaccard" in out.read_text()
