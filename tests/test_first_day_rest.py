"""Issue 27, the rest: plain --help (item 7), messages in command-line terms (item 8), the
demo's HTML report and honest summary (item 13), accepted nonsense refused (item 18), no
partial outputs, no stray workers and refusals that name their file or option (item 20)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from cli_checks import refused, run, runner
from sparseloc.cli import app
from sparseloc.io.tables import complete_locs, write_table

COMMANDS = (
    "demo",
    "simulate",
    "calibrate",
    "camera",
    "localize",
    "evaluate",
    "filter",
    "drift",
    "render",
    "overlay",
    "report",
)


def _help(*args: str) -> str:
    res = runner.invoke(app, [*args, "--help"], env={"COLUMNS": "200", "TERMINAL_WIDTH": "200"})
    assert res.exit_code == 0, res.output
    return res.output


# ---- item 7: --help ----------------------------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS)
def test_help_has_plain_placeholders(command):
    text = _help(command)
    usage = next(ln for ln in text.splitlines() if "Usage:" in ln)
    assert "{" not in usage and "}" not in usage, usage
    assert "<bool>" not in text
    assert "list[" not in text


def test_main_help_lists_commands_in_workflow_order():
    text = _help()
    panel = text[text.index("Commands") :]
    pos = [re.search(rf"^\W*{c}\s", panel, re.M) for c in COMMANDS]
    assert all(pos), [c for c, p in zip(COMMANDS, pos, strict=True) if p is None]
    starts = [p.start() for p in pos]
    assert starts == sorted(starts), COMMANDS


def test_main_help_shows_whole_sentences():
    """The demo's description is not broken after "and" (a docstring's line break)."""
    line = next(ln for ln in _help().splitlines() if re.search(r"\bdemo\b", ln))
    assert "write the table" in line, line


def test_help_keeps_square_brackets_of_toml_tables():
    assert "[localize]" in _help("localize") and "[camera]" in _help("localize")
    assert "[camera]" in _help("simulate")


# ---- item 8: messages in command-line terms -----------------------------------------------


def test_float_movie_refusal_gives_no_python_advice(tmp_path):
    import tifffile

    tif = tmp_path / "float.tif"
    tifffile.imwrite(tif, np.ones((2, 16, 16), np.float32))
    res = run("localize", tif, "-o", tmp_path / "l.parquet", "--psf", "dh-analytic",
              "--pixel-size", "100")  # fmt: skip
    refused(res, "float.tif")
    assert "=True" not in res.stderr and "allow_float" not in res.stderr


def _table(tmp_path: Path, n: int, frames: int, span: float = 5000.0) -> Path:
    rng = np.random.default_rng(0)
    t = complete_locs(
        pd.DataFrame(
            {
                "frame": rng.integers(0, frames, n),
                "x_nm": rng.uniform(100, span, n),
                "y_nm": rng.uniform(100, span, n),
                "z_nm": rng.uniform(-300, 300, n),
            }
        )
    )
    path = tmp_path / "t.parquet"
    write_table(t, path, metadata={"params": {"pixel_size": 100.0}, "shape": [64, 64]})
    return path


def test_drift_refusals_speak_of_flags_not_arguments(tmp_path):
    few = _table(tmp_path, 40, 50)
    res = run("drift", few, "-o", tmp_path / "d.parquet")
    refused(res)
    assert "min_locs_per_segment" not in res.stderr and "=" not in res.stderr
    (tmp_path / "t.parquet").unlink()
    wide = _table(tmp_path, 3000, 50, span=5e6)
    res = run("drift", wide, "-o", tmp_path / "d.parquet", "--bin-nm", "1")
    refused(res, "--bin-nm")
    assert "bin_nm" not in res.stderr


# ---- item 13: the demo --------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "d"
    res = run("demo", "-o", out, "--frames", "4")
    assert res.exit_code == 0, res.output
    return out, res.output


def test_demo_writes_the_html_report(demo_run):
    out, text = demo_run
    html = out / "report.html"
    assert html.is_file() and "<html" in html.read_text().lower()
    assert "report.html" in text


def test_demo_summary_states_the_scenes_photon_range(demo_run):
    out, text = demo_run
    truth = pd.read_csv(out / "movie_truth.csv")
    assert "photons 1000-5000" not in text
    lo, hi = truth.photons.min(), truth.photons.max()
    assert f"{lo:.0f}" in text and f"{hi:.0f}" in text, text


# ---- item 18: accepted nonsense -----------------------------------------------------------


@pytest.fixture
def pixel_truth(tmp_path):
    truth = tmp_path / "truth.csv"
    pd.DataFrame(
        {
            "frame_0based": [0, 0],
            "x_px": [5.0, 9.0],
            "y_px": [5.0, 7.0],
            "z_um": [0.0, 0.1],
            "photons_sum": [2000.0, 3000.0],
        }
    ).to_csv(truth, index=False)
    locs = complete_locs(
        pd.DataFrame(
            {"frame": [0, 0], "x_nm": [550.0, 950.0], "y_nm": [550.0, 750.0], "z_nm": [0.0, 100.0]}
        )
    )
    path = tmp_path / "l.parquet"
    write_table(locs, path)
    return path, truth


@pytest.mark.parametrize("command", ["evaluate", "report"])
@pytest.mark.parametrize("value", ["0", "-100", "nan"])
def test_pixel_size_zero_with_pixel_truth_is_refused(pixel_truth, tmp_path, command, value):
    locs, truth = pixel_truth
    if command == "report":
        out = tmp_path / "r.html"
        res = run("report", locs, "--truth", truth, "--pixel-size", value, "-o", out)
    else:
        res = run("evaluate", locs, truth, "--pixel-size", value)
    refused(res, "--pixel-size")
    assert not (tmp_path / "r.html").exists()


@pytest.mark.parametrize(
    "size",
    [("--rows", 100000, "--cols", 100000, "--frames", 1000), ("--frames", 100000000)],
)
def test_simulate_beyond_the_free_memory_is_refused(tmp_path, size):
    """Item 19: a movie that cannot be held in memory is refused before any allocation."""
    out = tmp_path / "big.tif"
    res = run("simulate", "-o", out, "--psf", "dh-analytic", *size)
    refused(res, "GiB of memory", "fewer frames")
    assert not out.exists()


def test_simulate_offset_beyond_uint16_is_refused(tmp_path):
    out = tmp_path / "m.tif"
    res = run("simulate", "-o", out, "--psf", "dh-analytic", "--frames", "1", "--offset", "70000")
    refused(res, "--offset", "65535")
    assert not out.exists()


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    folder = tmp_path_factory.mktemp("cal")
    zs = np.arange(-500.0, 501.0, 50.0)
    truth = bead_scan_truth(np.array([[1400.0, 2400.0], [3400.0, 2400.0]]), zs, 20000.0)
    sim = simulate(make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(48, 48))
    tif = write_tiff(folder / "beads.tif", sim.movie, pixel_size=100.0)
    cal = folder / "psf.h5"
    res = run("calibrate", tif, "-o", cal, "--pixel-size", "100", "--z-step", "50")
    assert res.exit_code == 0, res.output
    return cal


def test_calibration_whose_planes_do_not_sum_to_one_is_refused(calibration, tmp_path):
    from sparseloc.io.calibration import load_calibration

    load_calibration(calibration)  # the file as written loads
    bad = tmp_path / "bad.h5"
    bad.write_bytes(calibration.read_bytes())
    with h5py.File(bad, "r+") as f:
        f["spline/stack"][...] = 3.0 * f["spline/stack"][()]
    with pytest.raises(ValueError, match="sum"):
        load_calibration(bad)
    res = run("simulate", "-o", tmp_path / "m.tif", "--psf", bad, "--frames", "1")
    refused(res, "bad.h5", "sum")
    assert not (tmp_path / "m.tif").exists()


# ---- item 20: leftovers, strays, refusals that name their cause ----------------------------


def test_render_leaves_nothing_when_the_volume_write_fails(tmp_path, monkeypatch):
    import sparseloc.render as render

    locs = _table(tmp_path, 500, 5)

    def fail(*args, **kwargs):
        raise ValueError("cannot write the volume")

    monkeypatch.setattr(render, "write_volume_tiff", fail)
    png, vol, frc = tmp_path / "i.png", tmp_path / "v.tif", tmp_path / "frc.png"
    res = run("render", locs, "-o", png, "--volume", vol, "--frc", frc)
    refused(res, "volume")
    assert not png.exists() and not vol.exists() and not frc.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.parquet"]
    assert "wrote" not in res.stdout


_POOL_SCRIPT = """
import os, sys, time
from sparseloc.pool import in_processes

def make_work():
    def work(i):
        time.sleep(60)
        return os.getpid()
    return work

def main():
    print("parent", os.getpid(), flush=True)
    for r in in_processes(((i,) for i in range(8)), 2, (make_work, (), "numpy")):
        print(r, flush=True)

if __name__ == "__main__":
    main()
"""


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True)
    return [int(p) for p in out.stdout.split()]


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@contextlib.contextmanager
def _pool_run(tmp_path: Path, command: list[str] | None = None):
    """``command`` (default: the pool script) running in its own session, its two workers
    busy: yields (process, worker pids); whatever is left is killed afterwards."""
    if command is None:
        script = tmp_path / "pool_run.py"
        script.write_text(textwrap.dedent(_POOL_SCRIPT))
        command = [sys.executable, str(script)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, start_new_session=True,
    )  # fmt: skip
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(workers) < 2 and time.monotonic() < deadline:
            time.sleep(0.5)
            # the pool's workers: the parent's children that are Python processes
            workers = [p for p in _children(proc.pid) if _alive(p)]
        if len(workers) < 2:
            ended = proc.poll() is not None
            raise AssertionError(f"no two workers: {workers}, " + (
                f"the run ended: {proc.communicate()[1]}" if ended else "the run goes on"
            ))  # fmt: skip
        time.sleep(2.0)  # the workers are inside their (sleeping) items
        yield proc, workers
    finally:
        for p in workers:
            try:
                os.kill(p, signal.SIGKILL)
            except OSError:
                pass
        with contextlib.suppress(OSError):
            os.killpg(proc.pid, signal.SIGKILL)  # anything else the run started
        if proc.poll() is None:
            proc.kill()


def _left_alive(workers: list[int], seconds: float) -> list[int]:
    """The workers still alive after waiting up to ``seconds`` for them to end."""
    deadline = time.monotonic() + seconds
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    return [p for p in workers if _alive(p)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_die_with_a_killed_parent(tmp_path):
    with _pool_run(tmp_path) as (proc, workers):
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        left = _left_alive(workers, 15)
        assert not left, f"workers still alive after their parent was killed: {left}"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_localize_workers_die_with_a_killed_localize(tmp_path):
    """The trial's case itself: ``localize --workers 2`` killed with SIGKILL mid-run."""
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate

    # a dense movie: the workers start within seconds, long before the run could end (and
    # 100 frames stay below the chunked runs' length)
    sim = simulate(make_psf("astig-gauss"), n_frames=100, shape=(64, 64), density=1.0, seed=0)
    movie = write_tiff(tmp_path / "m.tif", sim.movie, pixel_size=100.0)
    out = tmp_path / "l.parquet"
    command = [sys.executable, "-m", "sparseloc.cli", "localize", str(movie), "-o", str(out)]
    flags = ["--psf", "astig-gauss", "--pixel-size", "100", "--workers", "2"]
    with _pool_run(tmp_path, [*command, *flags]) as run_:
        proc, workers = run_
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        left = _left_alive(workers, 15)
        assert not left, f"workers still alive after localize was killed: {left}"
    assert not out.exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_twice_to_the_process_group_ends_the_pool_at_once(tmp_path):
    """The third walk-through: Ctrl-C sent twice to the whole group (or ``timeout -s INT``)
    left the run hanging in the pool's shutdown with both workers alive. The workers now
    leave Ctrl-C to the parent, which ends them without waiting for their items."""
    with _pool_run(tmp_path) as (proc, workers):
        os.killpg(proc.pid, signal.SIGINT)
        time.sleep(0.3)
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(20)  # raises TimeoutExpired where it hangs
        assert not _left_alive(workers, 10)


def test_refusal_of_a_bad_table_names_the_file(tmp_path):
    bad = tmp_path / "broken.parquet"
    bad.write_bytes(b"not a table")
    for command, extra in (
        ("render", ["-o", tmp_path / "i.png"]),
        ("filter", ["-o", tmp_path / "f.parquet"]),
        ("drift", ["-o", tmp_path / "d.parquet"]),
        ("report", ["-o", tmp_path / "r.html"]),
    ):
        refused(run(command, bad, *extra), "broken.parquet")
