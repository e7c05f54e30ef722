"""Issue 27's flag rule seen from each command line: every consumer of a table leaves rows
flagged other than 'ok' out and says so, ``--all-flags`` takes them in, rows with impossible
uncertainties cannot blow up a report, and the README states the rule as the code applies it."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.cli import app
from sparseloc.io.tables import read_parquet, write_table

runner = CliRunner()
FLAGGED = 100
README = Path(__file__).resolve().parents[1] / "README.md"


def _ring(seed: int, x_shift_per_frame: float = 0.0, moving: int = 0) -> pd.DataFrame:
    """3,000 localizations on a ring of 800 nm radius over 200 frames, the first ``moving``
    shifted in x by ``x_shift_per_frame`` nm per frame, all flagged 'ok'."""
    from test_first_day_flags import _table

    n = 3000
    t = _table(n, seed)
    rng = np.random.default_rng(seed + 100)
    th = rng.uniform(0, 2 * np.pi, n)
    frame = rng.integers(0, 200, n)
    shift = np.where(np.arange(n) < moving, x_shift_per_frame * frame, 0.0)
    t["frame"] = frame
    t["x_nm"] = 2000 + 800 * np.cos(th) + rng.normal(0, 10, n) + shift
    t["y_nm"] = 2000 + 800 * np.sin(th) + rng.normal(0, 10, n)
    return t


@pytest.fixture(scope="module")
def table(tmp_path_factory) -> tuple[Path, Path]:
    """A ring of 3,000 localizations over 200 frames (enough for a drift estimate), the first
    100 flagged z_edge with lateral sigmas of 2e9 nm, as the trial's table had; and a truth."""
    t = _ring(seed=0)
    t.loc[: FLAGGED - 1, "flag"] = "z_edge"
    t.loc[: FLAGGED - 1, ["sigma_x_nm", "sigma_y_nm"]] = 2e9
    t.loc[: FLAGGED - 1, "sigma_z_nm"] = np.resize([9.7e9, np.nan, 1e-14], FLAGGED)
    folder = tmp_path_factory.mktemp("rule")
    src, truth = folder / "l.parquet", folder / "truth.csv"
    write_table(t, src)
    t[["frame", "x_nm", "y_nm", "z_nm", "photons"]].to_csv(truth, index=False)
    return src, truth


NOTE = f"excluded {FLAGGED} flagged localizations (--all-flags includes them)"
CONSUMERS = ("render", "report", "drift", "filter", "evaluate")


@pytest.mark.parametrize(
    "command",
    [
        ["render", "{src}", "-o", "{out}.png"],
        ["drift", "{src}", "--segments", "4", "--no-z", "-o", "{out}.parquet"],
        ["evaluate", "{src}", "{truth}"],
    ],
    ids=lambda c: c[0],
)
def test_each_command_says_it_left_the_flagged_rows_out(table, tmp_path, command):
    src, truth = table
    args = [a.format(src=src, truth=truth, out=tmp_path / "out") for a in command]
    left_out = runner.invoke(app, args)
    assert left_out.exit_code == 0, left_out.output
    assert NOTE in left_out.stderr
    taken = runner.invoke(app, [*args, "--all-flags", *(["--overwrite"] * (args[0] != "evaluate"))])
    assert taken.exit_code == 0, taken.output
    assert "flagged" not in taken.stderr
    if args[0] == "evaluate":  # what it scored, not only what it said, and said above it
        assert left_out.output.index(NOTE) < left_out.output.index("Jaccard"), left_out.output
        assert re.search(rf"localizations\s+{3000 - FLAGGED}\b", left_out.stdout), left_out.stdout
        assert re.search(r"localizations\s+3000\b", taken.stdout), taken.stdout


def _drift_range_x(res) -> float:
    return float(re.search(r"range x ([0-9.]+) nm", res.stdout).group(1))


def test_drift_estimates_from_the_ok_rows_unless_all_flags(tmp_path):
    """Two thirds of the rows flagged and moving 400 nm in x over the movie, the 'ok' rows
    still: the estimate follows the rows the rule lets in."""
    t = _ring(seed=1, x_shift_per_frame=2.0, moving=2000)
    t.loc[:1999, "flag"] = "z_edge"
    src = tmp_path / "l.parquet"
    write_table(t, src)
    args = ["drift", str(src), "--segments", "4", "--no-z", "-o", str(tmp_path / "d.parquet")]
    still = runner.invoke(app, args)
    assert still.exit_code == 0, still.output
    moved = runner.invoke(app, [*args, "--all-flags", "--overwrite"])
    assert moved.exit_code == 0, moved.output
    ranges = _drift_range_x(still), _drift_range_x(moved)
    assert ranges[0] < 50.0 and ranges[1] > 150.0, ranges


def test_filter_keeps_only_ok_rows_unless_all_flags(table, tmp_path):
    src, _ = table
    out = tmp_path / "f.parquet"
    res = runner.invoke(app, ["filter", str(src), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert f"removed: flag {FLAGGED}" in res.stdout
    kept, _ = read_parquet(out)
    assert len(kept) == 3000 - FLAGGED and (kept["flag"] == "ok").all()
    res = runner.invoke(app, ["filter", str(src), "-o", str(out), "--all-flags", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert len(read_parquet(out)[0]) == 3000


def test_report_leaves_flagged_rows_out(table, tmp_path):
    src, _ = table
    out = tmp_path / "r.html"
    res = runner.invoke(app, ["report", str(src), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert f"excluded {FLAGGED} flagged" in out.read_text()
    res = runner.invoke(app, ["report", str(src), "-o", str(out), "--all-flags", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert f"excluded {FLAGGED} flagged" not in out.read_text()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux limits")
@pytest.mark.parametrize(("command", "suffix"), [("render", ".png"), ("report", ".html")])
def test_impossible_sigmas_fit_in_a_small_memory_limit(table, tmp_path, command, suffix):
    """Item 1: with the flagged rows taken in, their sigmas of 2e9 nm (and 9.7e9, NaN, 1e-14 nm
    along z) are drawn within the image's memory: the command runs with 300 MiB beyond what
    the process holds after a small run of the same command."""
    from test_first_day_flags import run_under_a_limit

    src, _ = table
    out = tmp_path / f"out{suffix}"
    r = run_under_a_limit(
        tmp_path, command, suffix, [command, str(src), "-o", str(out), "--all-flags"]
    )
    assert r.returncode == 0, r.stderr
    assert out.is_file()


def test_the_readme_states_the_rule_for_every_consumer():
    row = next(line for line in README.read_text().splitlines() if line.startswith("| `flag`"))
    for word in (*(f"`{c}`" for c in CONSUMERS), "--all-flags", "NaN sigmas"):
        assert word in row, word
    for command in CONSUMERS:
        res = runner.invoke(app, [command, "--help"], env={"COLUMNS": "200"})
        assert "--all-flags" in res.output, command
