"""Issue 27's flag rule seen from each command line: every consumer of a table leaves rows
flagged other than 'ok' out and says so, ``--all-flags`` takes them in, rows with impossible
uncertainties cannot blow up a report, and the README states the rule as the code applies it."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from sparseloc.cli import app
from sparseloc.io.tables import complete_locs, read_parquet, write_table

runner = CliRunner()
FLAGGED = 100
README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.fixture(scope="module")
def table(tmp_path_factory) -> tuple[Path, Path]:
    """A ring of 3,000 localizations over 200 frames (enough for a drift estimate), the first
    100 flagged z_edge with lateral sigmas of 2e9 nm, as the trial's table had; and a truth."""
    rng = np.random.default_rng(0)
    n = 3000
    th = rng.uniform(0, 2 * np.pi, n)
    t = complete_locs(
        pd.DataFrame(
            {
                "frame": rng.integers(0, 200, n),
                "x_nm": 2000 + 800 * np.cos(th) + rng.normal(0, 10, n),
                "y_nm": 2000 + 800 * np.sin(th) + rng.normal(0, 10, n),
                "z_nm": rng.uniform(-300, 300, n),
                "photons": 2000.0,
                "sigma_x_nm": 10.0,
                "sigma_y_nm": 10.0,
                "sigma_z_nm": 30.0,
                "gof": 1.0,
            }
        )
    )
    t.loc[: FLAGGED - 1, "flag"] = "z_edge"
    t.loc[: FLAGGED - 1, ["sigma_x_nm", "sigma_y_nm"]] = 2e9
    folder = tmp_path_factory.mktemp("rule")
    src, truth = folder / "l.parquet", folder / "truth.csv"
    write_table(t, src)
    t[["frame", "x_nm", "y_nm", "z_nm", "photons"]].to_csv(truth, index=False)
    return src, truth


NOTE = f"excluded {FLAGGED} flagged localizations (--all-flags includes them)"


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


def test_report_leaves_flagged_rows_out_and_draws_their_huge_sigmas_when_asked(table, tmp_path):
    src, _ = table
    out = tmp_path / "r.html"
    res = runner.invoke(app, ["report", str(src), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert f"excluded {FLAGGED} flagged" in out.read_text()
    # with them: the rows of sigma 2e9 nm are drawn within the image, not as 2e9 nm spots
    res = runner.invoke(app, ["report", str(src), "-o", str(out), "--all-flags", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert f"excluded {FLAGGED} flagged" not in out.read_text()


def test_the_readme_states_the_rule_for_every_consumer():
    row = next(line for line in README.read_text().splitlines() if line.startswith("| `flag`"))
    for word in ("render", "report", "drift", "filter", "evaluate", "--all-flags", "NaN sigmas"):
        assert word in row, word
    # every command the row names takes the flag
    for command in re.findall(r"`(render|report|drift|filter|evaluate)`", row):
        res = runner.invoke(app, [command, "--help"], env={"COLUMNS": "200"})
        assert "--all-flags" in res.output, command
