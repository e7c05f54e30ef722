"""Pipeline accuracy against emitter density (issue 5's acceptance table).

Simulates double-helix movies (pupil model, 100 nm pixels, 1000-5000 photons, background 10,
z in -1000..1000 nm, Poisson camera) at several densities, localizes them with the pipeline
(spline table of the model; the default frame solver, or ``--method hybrid`` for the paper's
windowed MP+CO+MLE) and prints Jaccard, RMSE lateral and axial and efficiency per density;
writes JSON.

Usage::

    python benchmarks/density.py [--densities 0.5,1,2] [--frames 10] [--size 64]
                                 [--method frame|hybrid] [--window 21] [--margin 6]
                                 [--workers 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--densities", default="0.5,1,2", help="emitters per um^2")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--method", default="frame")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--size", type=int, default=64, help="frame side (px)")
    ap.add_argument("--window", type=int, default=21)
    ap.add_argument("--margin", type=int, default=6)
    ap.add_argument("--psf", default="dh")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/density.json"))
    args = ap.parse_args(argv)
    model = make_psf(args.psf)
    px = 100.0
    densities = [float(d) for d in args.densities.split(",")]
    params = LocalizeParams(
        pixel_size=px, method=args.method, window=args.window, margin=args.margin
    )
    print(
        f"{args.psf} pupil model, {args.frames} frames of {args.size}x{args.size} px of "
        f"{px:.0f} nm per density, 1000-5000 photons, background 10, z -1000..1000 nm; "
        f"method {args.method}"
        + (f", windows {args.window} px, margin {args.margin} px" if args.method != "frame" else "")
        + f"; {args.workers} worker process(es)"
    )
    hdr = (
        f"{'density':>8} {'emitters':>8} | {'Jaccard %':>9} {'recall':>7} {'precision':>9} | "
        f"{'RMSE lat':>8} {'RMSE ax':>8} nm | {'eff lat':>7} {'eff ax':>7} % | {'s/frame':>7}"
    )
    print(hdr)
    print("-" * len(hdr))
    out = {
        "params": vars(args) | {"out": str(args.out)},
        "rows": [],
        "machine": platform.platform(),
    }
    for i, d in enumerate(densities):
        sim = simulate(
            model,
            scene="uniform",
            n_frames=args.frames,
            shape=(args.size, args.size),
            pixel_size=px,
            density=d,
            photons=(1000.0, 5000.0),
            background=10.0,
            seed=args.seed + i,
        )
        frames = sim.movie.astype(np.float64) - sim.camera.offset
        t0 = time.perf_counter()
        res = localize(frames, model, params, workers=args.workers)
        secs = time.perf_counter() - t0
        ev = evaluate(res.table, sim.truth)
        row = {
            "density": d,
            "n_truth": ev.n_truth,
            "jaccard": ev.jaccard,
            "recall": ev.recall,
            "precision": ev.precision,
            "rmse_lateral_nm": ev.rmse_lateral,
            "rmse_axial_nm": ev.rmse_axial,
            "efficiency_lateral": ev.efficiency_lateral,
            "efficiency_axial": ev.efficiency_axial,
            "seconds_per_frame": secs / args.frames,
            "windows": res.n_windows,
        }
        out["rows"].append(row)
        print(
            f"{d:8.2f} {ev.n_truth:8d} | {ev.jaccard:9.1f} {ev.recall:7.3f} {ev.precision:9.3f} | "
            f"{ev.rmse_lateral:8.1f} {ev.rmse_axial:8.1f}    | {ev.efficiency_lateral:7.1f} "
            f"{ev.efficiency_axial:7.1f}   | {secs / args.frames:7.1f}",
            flush=True,
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
