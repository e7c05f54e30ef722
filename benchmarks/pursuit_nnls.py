"""The whole-frame pursuit's amplitude refits against frame size: sparse NNLS against dense.

The frame solver's pursuit refits every atom's amplitude after each cycle. It runs on whole
frames up to 512 x 512 px (larger ones in tiles), so a dense frame of that size holds
thousands of atoms. This script simulates one double-helix frame (pupil model, 100 nm pixels,
1000-5000 photons, background 10) per size at one density, runs the pursuit alone twice, with
the library's NNLS (block principal pivoting on the sparse Gram matrix,
``sparseloc.solvers.nnls``) and with scipy's dense active-set NNLS on the same Gram system
(the method used before), and prints the atoms, the time of the NNLS calls and of the pursuit,
and whether both found the same emitters. Writes JSON.

Usage::

    python benchmarks/pursuit_nnls.py [--sizes 128,256,512] [--density 1] [--repeats 3]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from sparseloc.pipeline import LocalizeParams, _FrameSolver
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate
from sparseloc.solvers import frame_mp
from sparseloc.solvers.nnls import RIDGE, active_set_nnls, sparse_nnls


def dense_nnls(a, y):
    """scipy's Lawson-Hanson NNLS on the same ridged Gram system (the method used before)."""
    g = (a.T @ a).toarray()
    g[np.diag_indices_from(g)] += RIDGE * max(float(np.trace(g)) / max(len(g), 1), 1e-30)
    return active_set_nnls(g, a.T @ y)


def run(solver, frame, engine) -> dict:
    """The pursuit on ``frame`` with ``engine`` as the NNLS: emitters, times, atoms per call."""
    calls = []

    def timed(a, y):
        t0 = time.perf_counter()
        x = engine(a, y)
        calls.append((a.shape[1], time.perf_counter() - t0))
        return x

    frame_mp.sparse_nnls = timed
    try:
        t0 = time.perf_counter()
        found = solver.start(frame, np.full(frame.shape, 10.0))
        seconds = time.perf_counter() - t0
    finally:
        frame_mp.sparse_nnls = sparse_nnls
    return {
        "emitters": found.as_array().reshape(-1, 4),
        "seconds": seconds,
        "nnls_seconds": sum(t for _, t in calls),
        "atoms": max((n for n, _ in calls), default=0),
    }


def _median_run(runs: list[dict]) -> dict:
    """The first run's emitters and atoms with the median times over ``runs``."""
    out = dict(runs[0])
    for key in ("seconds", "nnls_seconds"):
        out[key] = float(np.median([r[key] for r in runs]))
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="128,256,512", help="frame sides (px)")
    ap.add_argument("--density", type=float, default=1.0, help="emitters per um^2")
    ap.add_argument("--repeats", type=int, default=3, help="runs per engine (medians)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/pursuit_nnls.json"))
    args = ap.parse_args(argv)
    model = make_psf("dh")
    params = LocalizeParams(pixel_size=100.0)
    print(
        f"dh pupil model, one frame per size at {args.density} /um^2, 1000-5000 photons, "
        f"background 10; the pursuit alone, one process; median of {args.repeats} runs per "
        "engine, alternating which goes first (one run where the dense one takes over 20 s)"
    )
    hdr = (
        f"{'size':>5} {'truth':>6} {'atoms':>6} | {'sparse NNLS s':>13} {'pursuit s':>9} | "
        f"{'dense NNLS s':>12} {'pursuit s':>9} | {'speed-up':>8} same"
    )
    print(hdr)
    print("-" * len(hdr))
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        sim = simulate(
            model,
            scene="uniform",
            n_frames=1,
            shape=(size, size),
            pixel_size=100.0,
            density=args.density,
            photons=(1000.0, 5000.0),
            background=10.0,
            seed=1,
        )
        frame = sim.movie[0].astype(np.float64) - sim.camera.offset
        solver = _FrameSolver(model, params, frame.shape)
        run(solver, frame, sparse_nnls)  # compiles, and builds the frame's correlator
        fasts, slows = [], []
        for r in range(args.repeats):  # alternating which goes first; medians below
            order = [(fasts, sparse_nnls), (slows, dense_nnls)]
            for runs, engine in order[:: 1 if r % 2 == 0 else -1]:
                if engine is dense_nnls and slows and slows[0]["seconds"] > 20.0:
                    continue  # one run of a slow one says enough
                runs.append(run(solver, frame, engine))
        fast, slow = _median_run(fasts), _median_run(slows)
        same = fast["emitters"].shape == slow["emitters"].shape and bool(
            np.allclose(fast["emitters"], slow["emitters"], rtol=0, atol=1e-3)
        )
        row = {
            "size": size,
            "truth": len(sim.truth),
            "atoms": fast["atoms"],
            "sparse_nnls_s": fast["nnls_seconds"],
            "sparse_pursuit_s": fast["seconds"],
            "dense_nnls_s": slow["nnls_seconds"],
            "dense_pursuit_s": slow["seconds"],
            "same_emitters": same,
        }
        rows.append(row)
        ratio = row["dense_pursuit_s"] / row["sparse_pursuit_s"]
        print(
            f"{size:5d} {row['truth']:6d} {row['atoms']:6d} | {row['sparse_nnls_s']:13.2f} "
            f"{row['sparse_pursuit_s']:9.2f} | {row['dense_nnls_s']:12.2f} "
            f"{row['dense_pursuit_s']:9.2f} | {ratio:8.2f} "
            f"{'yes' if same else 'no'}",
            flush=True,
        )
    out = {"params": vars(args) | {"out": str(args.out)}, "rows": rows}
    out["machine"] = platform.platform()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
