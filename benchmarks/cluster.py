"""A long movie on a Dask LocalCluster: per-worker peak memory, and scaling from 1 to 2 workers.

The movie is made frame by frame inside the tasks (:class:`sparseloc.simulate.SimulatedMovie`:
uniform emitters, double-helix pupil model, 100 nm pixels, 1000-5000 photons, background 10),
so nothing is stored and each worker reads only its chunk. The script

1. localizes the first ``--scaling-frames`` frames with a 1-worker and then a 2-worker
   LocalCluster (same chunks) and prints the speed ratio;
2. localizes all ``--frames`` frames on a ``--workers`` LocalCluster into a run folder, and
   prints the time, the localizations, each worker's peak resident memory (``ru_maxrss``)
   and the driver's, and the accuracy against the truth (Jaccard, RMSE) on a sample of frames.

Usage::

    python benchmarks/cluster.py [--frames 20000] [--size 128] [--density 0.05] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from sparseloc.distributed import local_cluster, localize_chunked
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, work_model_for
from sparseloc.psf import make_psf
from sparseloc.simulate import SimulatedMovie


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def _timed_run(movie, model, params, run_dir, workers, chunk, stop=None):
    """Run on a fresh LocalCluster; sample every worker's resident memory every 2 s (a
    worker's ru_maxrss would include what it inherited from this process)."""
    client = local_cluster(workers)
    peaks: dict[str, float] = {}
    trace: list[tuple[float, dict]] = []
    done = threading.Event()

    def sample():
        t0 = time.perf_counter()
        while not done.is_set():
            try:
                now = client.run(_rss_mb)
            except Exception:  # a worker restarting: try again
                now = {}
            for k, v in now.items():
                peaks[k] = max(peaks.get(k, 0.0), v)
            trace.append((time.perf_counter() - t0, now))
            done.wait(2.0)

    th = threading.Thread(target=sample, daemon=True)
    try:
        th.start()
        t0 = time.perf_counter()
        res = localize_chunked(
            movie, model, params, run_dir, stop=stop, chunk_frames=chunk, scheduler=client
        )
        secs = time.perf_counter() - t0
    finally:
        done.set()
        th.join()
        client.close()
        client.cluster.close()
    return res, secs, peaks, trace


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--density", type=float, default=0.05, help="emitters per um^2 per frame")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-frames", type=int, default=500)
    ap.add_argument("--scaling-frames", type=int, default=400)
    ap.add_argument("--eval-frames", type=int, default=2000, help="frames scored (a sample)")
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/cluster.json"))
    args = ap.parse_args(argv)
    px = 100.0
    model = make_psf("dh")
    params = LocalizeParams(pixel_size=px)
    # Tabulate once here; the tasks receive the table (and SimulatedMovie renders with it).
    work = work_model_for(model, params)
    shape = (args.size, args.size)
    movie = SimulatedMovie(work, args.frames, shape, px, density=args.density, seed=7)
    tmp = Path(tempfile.mkdtemp(prefix="sparseloc-cluster-"))
    out: dict = {"frames": args.frames, "shape": list(shape), "density": args.density}
    try:
        # 1. scaling, on the same chunks
        n = min(args.scaling_frames, args.frames)
        chunk = max(1, n // 8)
        secs = {}
        for w in (1, 2):
            _, secs[w], _, _ = _timed_run(movie, work, params, tmp / f"s{w}", w, chunk, stop=n)
            print(f"scaling: {n} frames on {w} worker(s): {secs[w]:.1f} s", flush=True)
        out["scaling"] = {"frames": n, "seconds_1": secs[1], "seconds_2": secs[2]}
        print(f"speed-up 1 -> 2 workers: {secs[1] / secs[2]:.2f}x", flush=True)
        # 2. the long run
        run_dir = args.run_dir or tmp / "long"
        res, t_long, peaks, trace = _timed_run(
            movie, work, params, run_dir, args.workers, args.chunk_frames
        )
        # Memory over the run: the first and the last quarter of the samples.
        q = max(1, len(trace) // 4)
        early = max((max(s.values(), default=0.0) for _, s in trace[:q]), default=0.0)
        late = max((max(s.values(), default=0.0) for _, s in trace[-q:]), default=0.0)
        table = res.table
        print(
            f"{args.frames} frames {shape[0]}x{shape[1]} px on {args.workers} workers, chunks "
            f"of {args.chunk_frames}: {len(table):,} localizations in {t_long / 60:.1f} min "
            f"({args.frames / t_long:.1f} frames/s, {len(table) / t_long:.1f} localizations/s)"
        )
        for addr, mb in sorted(peaks.items()):
            print(f"  worker {addr}: peak resident memory {mb:.0f} MB (sampled every 2 s)")
        print(
            f"  largest worker memory in the first / last quarter of the run: {early:.0f} / "
            f"{late:.0f} MB"
        )
        print(f"  driver: peak resident memory {_peak_rss_mb():.0f} MB")
        # accuracy on a sample of frames spread over the movie
        rng = np.random.default_rng(0)
        sample = np.sort(rng.choice(args.frames, min(args.eval_frames, args.frames), False))
        truth = movie.truth_of(sample)
        ev = evaluate(table[table.frame.isin(sample)], truth)
        print(
            f"  accuracy on {len(sample)} sampled frames: Jaccard {ev.jaccard:.1f} %, RMSE "
            f"lateral {ev.rmse_lateral:.1f} nm, axial {ev.rmse_axial:.1f} nm"
        )
        out.update(
            {
                "seconds": t_long,
                "n_locs": len(table),
                "worker_peak_rss_mb": peaks,
                "worker_rss_first_last_quarter_mb": [early, late],
                "driver_peak_rss_mb": _peak_rss_mb(),
                "jaccard": ev.jaccard,
                "rmse_lateral": ev.rmse_lateral,
                "rmse_axial": ev.rmse_axial,
            }
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=str))
    return out


if __name__ == "__main__":
    main()
