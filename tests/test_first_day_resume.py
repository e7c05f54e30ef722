"""Issue 27, item 11: long runs are resumable without being asked.

A run longer than one chunk goes to a run folder beside its output (``OUT.parts``); a rerun
after an interruption continues from the finished chunks, and the folder goes once the table
is written. The chunk limit is lowered here so that a 6-frame movie counts as long.
"""

from __future__ import annotations

import pandas as pd
import pytest

import sparseloc.distributed as distributed
from cli_checks import run
from sparseloc.distributed import auto_chunk_frames, plan_chunks
from sparseloc.io.tables import read_table

ARGS = ["--psf", "dh-analytic", "--pixel-size", "160", "--z-min", "-300", "--z-max", "300"]


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    """Spline tables of these tests go to a folder of their own, not the user's cache."""
    monkeypatch.setenv("SPARSELOC_CACHE_DIR", str(tmp_path / "cache"))


@pytest.fixture
def movie(tmp_path):
    """A six-frame double-helix movie (ideal camera, offset 100 ADU, gain 1)."""
    path = tmp_path / "m.tif"
    res = run(
        "simulate", "-o", path, "--psf", "dh-analytic", "--frames", "6", "--rows", "32",
        "--cols", "32", "--pixel-size", "160", "--density", "0.3", "--photons-min", "2000",
        "--photons-max", "5000", "--z-min", "-300", "--z-max", "300", "--seed", "5",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return path


@pytest.fixture
def short_chunks(monkeypatch):
    """Runs of more than 2 frames count as long; automatic chunks may be 1 frame."""
    monkeypatch.setattr(distributed, "CHUNK_FRAMES", 2)
    monkeypatch.setattr(distributed, "MIN_AUTO_CHUNK", 1)


def _table(path) -> pd.DataFrame:
    return read_table(path).drop(columns=["window_id"]).reset_index(drop=True)


def test_automatic_chunks_are_equal_and_shared_out_over_the_workers(monkeypatch):
    monkeypatch.setattr(distributed, "MIN_AUTO_CHUNK", 50)
    assert auto_chunk_frames(600, 2) == 75  # 8 chunks: 4 per worker
    assert auto_chunk_frames(10_000, 2) == 500  # never more than CHUNK_FRAMES
    assert auto_chunk_frames(120, 8) == 60  # never less than MIN_AUTO_CHUNK
    for n, w in [(501, 1), (777, 3), (20_001, 8)]:
        chunks = plan_chunks(0, n, auto_chunk_frames(n, w))
        sizes = {b - a for a, b in chunks}
        assert max(sizes) - min(sizes) <= max(sizes) // 2 + 1 and max(sizes) <= 500


def test_a_long_run_leaves_the_unchunked_table_and_no_run_folder(tmp_path, movie, short_chunks):
    plain = tmp_path / "plain.parquet"
    res = run("localize", movie, "-o", plain, *ARGS, "--workers", "1", "--chunk-frames", "6")
    assert res.exit_code == 0, res.output
    # chunked on request but with no --run-dir: the folder was not asked for (walk-through 3)
    assert not (tmp_path / "plain.parquet.parts").exists()
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", out, *ARGS, "--workers", "1")
    assert res.exit_code == 0, res.output
    assert "3 of 3 chunks done" in res.output  # 6 frames: 3 chunks for 1 worker
    assert not (tmp_path / "locs.parquet.parts").exists()
    pd.testing.assert_frame_equal(_table(out), _table(plain))


def test_an_interrupted_long_run_continues_when_run_again(
    tmp_path, movie, short_chunks, monkeypatch
):
    calls = {"n": 0}
    solve = distributed._solve_chunk

    def interrupted_after_two(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 2:
            raise KeyboardInterrupt
        return solve(*args, **kwargs)

    monkeypatch.setattr(distributed, "_solve_chunk", interrupted_after_two)
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", out, *ARGS, "--workers", "1")
    assert res.exit_code == 130, res.output
    assert "same command run again continues" in res.output and not out.exists()
    parts = sorted((tmp_path / "locs.parquet.parts").glob("part-*.parquet"))
    assert len(parts) == 2

    monkeypatch.setattr(distributed, "_solve_chunk", solve)
    res = run("localize", movie, "-o", out, *ARGS, "--workers", "1")
    assert res.exit_code == 0, res.output
    assert "(2 from an earlier run)" in res.output, res.output
    plain = tmp_path / "plain.parquet"
    res = run("localize", movie, "-o", plain, *ARGS, "--workers", "1", "--chunk-frames", "6")
    assert res.exit_code == 0, res.output
    pd.testing.assert_frame_equal(_table(out), _table(plain))
    assert not (tmp_path / "locs.parquet.parts").exists()


def test_a_rerun_with_other_workers_keeps_the_runs_chunks(tmp_path, movie, short_chunks):
    """The automatic chunk size depends on the workers; a rerun adopts the run folder's."""
    run_dir = tmp_path / "locs.parquet.parts"
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", tmp_path / "x.parquet", *ARGS, "--run-dir", run_dir,
              "--chunk-frames", "3", "--workers", "1")  # fmt: skip
    assert res.exit_code == 0, res.output
    res = run("localize", movie, "-o", out, *ARGS, "--workers", "2")
    assert res.exit_code == 0, res.output
    assert "2 of 2 chunks done (2 from an earlier run)" in res.output, res.output


def test_a_short_run_is_not_chunked(tmp_path, movie):
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", out, *ARGS, "--workers", "1")
    assert res.exit_code == 0, res.output
    assert "chunks" not in res.output and out.exists()
