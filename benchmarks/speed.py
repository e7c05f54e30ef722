"""Speed, side by side (issue "Speed"): every figure is a ratio against a baseline measured in
the same run.

Sections (each can be skipped):

- ``mp``: matching pursuit over the paper's fine dictionary (1.27 M atoms, 11 x 11 px):
  time per window against the dense matrix-vector reference, and whether the selections are
  identical (:mod:`speed_mp`).
- ``co``: convex recovery on the coarse dictionary against CVXPY on the same problem, with
  the objective gap, and MP+CO with refinement per window of 3 emitters (:mod:`speed_co`).
- ``pipeline``: the whole pipeline (default frame solver, 2 worker processes) on simulated
  128 x 128 double-helix movies at 1 emitter/um^2 (1000-5000 photons, background 10): frames
  of several lengths (cost against length), localizations per second with Jaccard and RMSE
  from the same run, the ratio to storm-analysis's published 30-45 localizations/s, and the
  numba engine against the NumPy engine on the same frames.

Usage::

    python benchmarks/speed.py [--sections mp,co,pipeline] [--frames 25,50,100]
                               [--workers 2] [--out benchmarks/results/speed.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.simulate import SimulatedMovie

#: storm-analysis's deconvolution finder on a double-helix frame, CPU (the issue's figure).
STORM_ANALYSIS_LOCS_PER_S = (30.0, 45.0)


def pipeline_section(
    frame_counts: list[int], workers: int, seed: int = 0, one_run: bool = False
) -> dict:
    """Localize the first n frames of one simulated movie for each n of ``frame_counts``:
    one run per n, or with ``one_run`` a single run over the longest, timed when its first n
    frames are done (the table's first n frames are then evaluated)."""
    px = 100.0
    model = make_psf("dh")
    params = LocalizeParams(pixel_size=px)
    t0 = time.perf_counter()
    work = work_model_for(model, params)  # tabulated once, outside the timings
    t_table = time.perf_counter() - t0
    shape = (128, 128)
    n_max = max(frame_counts)
    movie = SimulatedMovie(work, n_max, shape, px, density=1.0, seed=seed)
    frames = movie.frames(0, n_max)
    truth = movie.truth_of(np.arange(n_max))
    print(
        f"pipeline: simulated {n_max} frames of 128x128 px (100 nm), double-helix pupil model "
        f"tabulated in {t_table:.1f} s, 1 emitter/um^2, 1000-5000 photons, background 10; "
        f"frame solver, {workers} worker process(es)",
        flush=True,
    )
    # warm-up: compile (or load) the numba kernels in this process and start nothing else
    localize(frames[:1], work, params)
    rows = []
    hdr = (
        f"{'frames':>7} {'locs':>7} {'seconds':>8} {'s/frame':>8} {'locs/s':>8} | "
        f"{'Jaccard %':>9} {'RMSE lat':>8} {'RMSE ax':>8}"
    )
    print(hdr)
    print("-" * len(hdr))
    runs = []
    if one_run:
        marks: dict[int, float] = {}
        done = [0]

        def tick(k: int) -> None:
            done[0] += k
            if done[0] in frame_counts:
                marks[done[0]] = time.perf_counter() - t0
                print(f"  {done[0]} frames done at {marks[done[0]]:.1f} s", flush=True)

        t0 = time.perf_counter()
        res = localize(frames[:n_max], work, params, workers=workers, progress=tick)
        for n in frame_counts:
            runs.append((n, res.table[res.table["frame"] < n], marks[n]))
    for n in frame_counts:
        if one_run:
            n, table, secs = runs.pop(0)
        else:
            t0 = time.perf_counter()
            table = localize(frames[:n], work, params, workers=workers).table
            secs = time.perf_counter() - t0
        ev = evaluate(table, truth[truth["frame"] < n])
        row = {
            "frames": n,
            "localizations": len(table),
            "seconds": secs,
            "seconds_per_frame": secs / n,
            "locs_per_s": len(table) / secs,
            "jaccard": ev.jaccard,
            "rmse_lateral_nm": ev.rmse_lateral,
            "rmse_axial_nm": ev.rmse_axial,
        }
        rows.append(row)
        print(
            f"{n:7d} {len(table):7d} {secs:8.1f} {secs / n:8.2f} {row['locs_per_s']:8.1f} | "
            f"{ev.jaccard:9.1f} {ev.rmse_lateral:8.1f} {ev.rmse_axial:8.1f}",
            flush=True,
        )
    base = rows[0]["seconds_per_frame"]
    for r in rows:
        r["cost_per_frame_vs_first"] = r["seconds_per_frame"] / base
    print(
        "cost per frame relative to the shortest run: "
        + ", ".join(f"{r['frames']} frames {r['cost_per_frame_vs_first']:.2f}" for r in rows)
    )
    best = rows[-1]["locs_per_s"]
    lo, hi = STORM_ANALYSIS_LOCS_PER_S
    print(
        f"localizations/s on the longest run: {best:.1f}; storm-analysis's published "
        f"{lo:.0f}-{hi:.0f}/s: ratio {best / hi:.2f}-{best / lo:.2f}"
    )
    # the numba engine against the NumPy reference engine, same frames, one process
    n_cmp = min(2, n_max)
    cmp = {}
    for compiled in (True, False):
        engine = "numba" if compiled else "numpy"
        t0 = time.perf_counter()
        res = localize(frames[:n_cmp], work, replace(params, engine=engine))
        cmp[compiled] = (time.perf_counter() - t0, len(res.table))
    ratio = cmp[False][0] / cmp[True][0]
    print(
        f"compiled (numba) against NumPy paths, {n_cmp} frames, 1 process: "
        f"{cmp[True][0]:.1f} s against {cmp[False][0]:.1f} s ({ratio:.2f}x); "
        f"{cmp[True][1]} and {cmp[False][1]} localizations"
    )
    return {
        "rows": rows,
        "workers": workers,
        "one_run": one_run,
        "storm_analysis_locs_per_s": list(STORM_ANALYSIS_LOCS_PER_S),
        "compiled_vs_numpy": {
            "frames": n_cmp,
            "seconds_compiled": cmp[True][0],
            "seconds_numpy": cmp[False][0],
            "ratio": ratio,
            "localizations": [cmp[True][1], cmp[False][1]],
        },
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sections", default="mp,co,pipeline")
    ap.add_argument("--frames", default="25,50,100", help="movie lengths of the pipeline runs")
    ap.add_argument(
        "--one-run",
        action="store_true",
        help="time the pipeline runs as one run over the longest movie, read when its first "
        "n frames are done (instead of one run per length)",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--mp-windows", type=int, default=200)
    ap.add_argument("--co-windows", type=int, default=30)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/speed.json"))
    ap.add_argument(
        "--print-json", type=Path, default=None, help="print the tables of a saved run and stop"
    )
    args = ap.parse_args(argv)
    if args.print_json is not None:
        import speed_co
        import speed_mp

        saved = json.loads(args.print_json.read_text())
        for key, mod in (("mp", speed_mp), ("co", speed_co)):
            if key in saved:
                mod.print_table(saved[key])
        return saved
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    out: dict = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    if "mp" in sections:
        import speed_mp

        print("== matching pursuit, fine dictionary ==", flush=True)
        out["mp"] = speed_mp.run(n_windows=args.mp_windows)
        speed_mp.print_table(out["mp"])
    if "co" in sections:
        import speed_co

        print("== convex recovery against CVXPY; MP+CO with refinement ==", flush=True)
        out["co"] = speed_co.run(n_windows=args.co_windows)
        speed_co.print_table(out["co"])
    if "pipeline" in sections:
        print("== whole pipeline ==", flush=True)
        counts = [int(v) for v in args.frames.split(",")]
        out["pipeline"] = pipeline_section(counts, args.workers, one_run=args.one_run)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=float))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
