"""Chunked runs: same table on every scheduler, resuming after SIGKILL, lost workers, bad chunks."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pandas as pd
import pytest
import tifffile

from sparseloc.distributed import CameraFrames, localize_chunked, plan_chunks
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate

distributed = pytest.importorskip("distributed")

PX = 100.0


@pytest.fixture(scope="module")
def model():
    return make_psf("dh-analytic")


@pytest.fixture(scope="module")
def movie(model):
    sim = simulate(
        model,
        scene="uniform",
        n_frames=16,
        shape=(32, 32),
        pixel_size=PX,
        density=0.4,
        photons=(2000.0, 5000.0),
        background=10.0,
        seed=2,
    )
    return sim.movie.astype(float) - sim.camera.offset


@pytest.fixture(scope="module")
def params():
    # The analytic model renders fast without a spline table.
    return LocalizeParams(pixel_size=PX, tabulate=False)


@pytest.fixture(scope="module")
def reference(movie, model, params):
    return localize(movie, model, params).table


@pytest.fixture(scope="module")
def client():
    from sparseloc.distributed import local_cluster

    c = local_cluster(2)
    yield c
    c.close()
    c.cluster.close()


def test_plan_chunks():
    assert plan_chunks(0, 10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert plan_chunks(3, 5, 10) == [(3, 5)]
    with pytest.raises(ValueError, match="chunk_frames"):
        plan_chunks(0, 10, 0)


@pytest.mark.parametrize(("scheduler", "chunk"), [("sync", 5), ("threads", 3), ("sync", 16)])
def test_same_table_in_process(movie, model, params, reference, tmp_path, scheduler, chunk):
    res = localize_chunked(
        movie, model, params, tmp_path / "run", chunk_frames=chunk, scheduler=scheduler
    )
    assert res.complete and not res.failed
    assert len(reference) > 20
    pd.testing.assert_frame_equal(res.table, reference)
    assert len(list((tmp_path / "run").glob("part-*.parquet"))) == len(res.chunks)


def test_same_table_on_a_local_cluster(movie, model, params, reference, tmp_path, client):
    res = localize_chunked(movie, model, params, tmp_path / "run", chunk_frames=4, scheduler=client)
    assert res.complete
    pd.testing.assert_frame_equal(res.table, reference)


def test_a_worker_killed_mid_run(movie, model, params, reference, tmp_path, client):
    pids = client.run(os.getpid)
    out: dict = {}

    def run():
        out["res"] = localize_chunked(
            movie, model, params, tmp_path / "run", chunk_frames=2, scheduler=client
        )

    th = threading.Thread(target=run)
    th.start()
    # Kill one worker process while chunks are being solved.
    deadline = time.time() + 60
    while time.time() < deadline and not any(client.processing().values()):
        time.sleep(0.05)
    busy = [w for w, tasks in client.processing().items() if tasks]
    assert busy, "no task started"
    os.kill(pids[busy[0]], signal.SIGKILL)
    th.join(timeout=300)
    res = out["res"]
    assert res.complete, res.summary()
    pd.testing.assert_frame_equal(res.table, reference)
    parts = sorted(p.name for p in (tmp_path / "run").glob("part-*.parquet"))
    assert len(parts) == len(res.chunks) == len(set(parts)) == 8
    # the nanny restarted the worker: the cluster has its two workers again
    client.wait_for_workers(2, timeout=60)


class _CorruptFrames(CameraFrames):
    """Frames whose frame 9 cannot be read (like a corrupt page in a TIFF)."""

    def frames(self, start, stop):
        if start <= 9 < stop:
            raise OSError("frame 9: corrupt TIFF page")
        return super().frames(start, stop)


def test_a_chunk_that_keeps_failing_is_reported(movie, model, tmp_path, client):
    # A one-frame background window: each chunk reads only its own frames.
    import cloudpickle

    # The workers cannot import this test module: send the class by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    p = LocalizeParams(pixel_size=PX, tabulate=False, background_frames=1)
    src = _CorruptFrames(movie)
    for sched in ("sync", client):
        d = tmp_path / ("sync" if sched == "sync" else "cluster")
        res = localize_chunked(src, model, p, d, chunk_frames=4, scheduler=sched, retries=1)
        assert not res.complete and res.table is None
        assert list(res.failed) == [(8, 12)] and res.missing == [(8, 12)]
        assert "frames 8-11 failed" in res.summary() and "corrupt" in res.summary()
        assert len(list(d.glob("part-*.parquet"))) == 3
    # bad values (NaN) are bad data: reported at once, with localize's own message
    nan = movie.copy()
    nan[13, 5, 5] = np.nan
    res = localize_chunked(nan, model, p, tmp_path / "nan", chunk_frames=4, scheduler=client)
    assert list(res.failed) == [(12, 16)] and "NaN" in res.failed[(12, 16)]
    assert len(res.missing) == 1


def test_a_different_analysis_is_refused(movie, model, params, tmp_path):
    localize_chunked(movie, model, params, tmp_path / "run", chunk_frames=8)
    other = LocalizeParams(pixel_size=PX, tabulate=False, min_snr=6.0)
    with pytest.raises(ValueError, match=r"different analysis \(changed: params.min_snr\)"):
        localize_chunked(movie, model, other, tmp_path / "run", chunk_frames=8)
    with pytest.raises(ValueError, match="chunk_frames"):
        localize_chunked(movie, model, params, tmp_path / "run", chunk_frames=4)
    res = localize_chunked(movie, model, other, tmp_path / "run", chunk_frames=8, overwrite=True)
    assert res.complete and not res.done_before


# --- the command line, killed with SIGKILL and started again ------------------------------


def _cli(args, **kw):
    return subprocess.Popen(
        [sys.executable, "-m", "sparseloc.cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def test_sigkill_then_rerun_gives_the_uninterrupted_table(movie, tmp_path):
    from sparseloc.io.tables import read_parquet

    tif = tmp_path / "m.tif"
    tifffile.imwrite(tif, np.clip(movie + 100, 0, 65535).astype(np.uint16))
    base = ["localize", tif, "--psf", "dh-analytic", "--pixel-size", "100", "--offset", "100"]
    full = _cli([*base, "-o", tmp_path / "full.parquet", "--chunk-frames", "2"])
    assert full.wait(timeout=600) == 0, full.stderr.read()
    out = tmp_path / "k.parquet"
    run = ["-o", out, "--chunk-frames", "2", "--run-dir", tmp_path / "k"]
    proc = _cli([*base, *run])
    deadline = time.time() + 300
    while time.time() < deadline and len(list((tmp_path / "k").glob("part-*.parquet"))) < 2:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    n_before = len(list((tmp_path / "k").glob("part-*.parquet")))
    assert 2 <= n_before < 8 and not out.exists()
    again = _cli([*base, *run])
    stdout, stderr = again.communicate(timeout=600)
    assert again.returncode == 0, stderr
    assert f"({n_before} from an earlier run)" in stdout
    a, b = read_parquet(tmp_path / "full.parquet")[0], read_parquet(out)[0]
    pd.testing.assert_frame_equal(a, b)
    assert not a.duplicated(["frame", "x_nm", "y_nm"]).any()
    # different parameters in the same run folder: refused with one sentence, exit code 2
    refused = _cli([*base, "-o", tmp_path / "k2.parquet", *run[2:], "--min-snr", "6"])
    _, stderr = refused.communicate(timeout=300)
    assert refused.returncode == 2 and "different analysis" in stderr
    assert "Traceback" not in stderr


def test_a_simulated_movie_is_the_same_however_it_is_read(model):
    from sparseloc.simulate import SimulatedMovie

    m = SimulatedMovie(model, 30, (24, 24), PX, density=0.6, seed=4)
    whole = m.frames(5, 11)
    parts = np.concatenate([m.frames(5, 7), m.frames(7, 8), m.frames(8, 11)])
    np.testing.assert_array_equal(whole, parts)
    truth = m.truth(5, 11)
    assert set(truth.frame) <= set(range(5, 11)) and len(truth) > 5
    pd.testing.assert_frame_equal(
        m.truth_of([7, 8]), truth[truth.frame.isin([7, 8])].reset_index(drop=True)
    )
    # the emitters are in the frames: a brighter frame holds more light than its background
    assert whole.mean() > 10.0
    with pytest.raises(ValueError, match="outside"):
        m.frames(25, 31)


def test_a_simulated_movie_resumes_and_another_seed_is_refused(model, params, tmp_path):
    # The run key of a movie made on demand is its parameters (not an object's address).
    from sparseloc.simulate import SimulatedMovie

    m = SimulatedMovie(model, 8, (32, 32), PX, density=0.4, seed=4)
    first = localize_chunked(m, model, params, tmp_path / "run", chunk_frames=4, stop=4)
    assert first.chunks == [(0, 4)] and first.complete
    again = localize_chunked(
        SimulatedMovie(model, 8, (32, 32), PX, density=0.4, seed=4),
        model,
        params,
        tmp_path / "run",
        chunk_frames=4,
        stop=4,
    )
    assert again.done_before == [(0, 4)]
    pd.testing.assert_frame_equal(again.table, first.table)
    other = SimulatedMovie(model, 8, (32, 32), PX, density=0.4, seed=5)
    with pytest.raises(ValueError, match="different analysis"):
        localize_chunked(other, model, params, tmp_path / "run", chunk_frames=4, stop=4)


def test_a_frame_source_without_identity_is_refused(model, params, movie, tmp_path):
    class Frames:
        def __len__(self):
            return len(movie)

        def frames(self, start, stop):
            return movie[start:stop]

    with pytest.raises(ValueError, match="identity"):
        localize_chunked(Frames(), model, params, tmp_path / "run", chunk_frames=8)


def test_a_run_that_cannot_start_leaves_no_folder_it_made(
    movie, model, params, tmp_path, monkeypatch
):
    """An unreachable scheduler (here: the chunks' runner refusing at once) removes the run
    folder the run created; a folder that was there before is kept."""
    import sparseloc.distributed as dist

    def unreachable(*args, **kwargs):
        raise ValueError("cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'")

    monkeypatch.setattr(dist, "_run_chunks", unreachable)
    new = tmp_path / "new"
    with pytest.raises(ValueError, match="cannot reach"):
        localize_chunked(movie, model, params, new, chunk_frames=4)
    assert not new.exists()
    kept = tmp_path / "kept"  # a folder given that exists already stays
    kept.mkdir()
    with pytest.raises(ValueError, match="cannot reach"):
        localize_chunked(movie, model, params, kept, chunk_frames=4)
    assert kept.is_dir()


def test_a_z_range_beyond_the_model_is_refused_before_the_run_folder(movie, model, tmp_path):
    """The run's z range narrows the spline table the fits use; one beyond the model's range
    is refused before the run folder and its manifest are written."""
    from sparseloc.psf.spline import SplinePSF

    table = SplinePSF.from_model(model, PX, roi=21, z_step=20.0)
    params = LocalizeParams(pixel_size=PX, z_range=(-5000.0, 0.0))
    run = tmp_path / "run"
    with pytest.raises(ValueError, match="within the PSF model's"):
        localize_chunked(movie, table, params, run, chunk_frames=8)
    assert not run.exists()
