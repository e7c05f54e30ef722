"""Bright emitters among ordinary ones: the false localizations their halos made, with the
halo known (:mod:`sparseloc.solvers.halo`) and without it.

Simulates movies with a pupil model (100 nm pixels, 128 x 128 px, 0.5 /um^2 ordinary
emitters of 1,000-5,000 photons, background 10, Poisson camera, each image rendered out to
8 um) and ``--bright`` emitters per frame of ``--photons`` photons at fixed places (z within
half the range), localizes them with that model and the default settings (a spatial
background: too few frames for a temporal one), once as the pipeline runs and once with the
halo step switched off, and prints Jaccard, false and missed emitters, RMSE and time for
each; a movie without the bright emitters is the control. With ``--calibration`` the
first PSF's movies are localized again with that bead calibration (made from a stack
simulated with the same pupil) in place of the pupil model. Writes JSON::

    python benchmarks/halo.py --psfs dh,astig --frames 4 --out /tmp/halo.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

import sparseloc
import sparseloc.pipeline as pipeline_mod
from sparseloc.config import LocalizeParams
from sparseloc.evaluate import evaluate
from sparseloc.io.calibration import load_calibration
from sparseloc.pipeline import localize
from sparseloc.psf import make_psf
from sparseloc.simulate import render_movie
from sparseloc.simulate_scenes import uniform_scene

PX = 100.0
SHAPE = (128, 128)


def movie(model, frames: int, bright: int, photons: float, seed: int):
    """A movie (frames, rows, cols; photons) and its truth."""
    rng = np.random.default_rng(seed)
    fov = (SHAPE[1] * PX, SHAPE[0] * PX)
    truth = uniform_scene(rng, frames, fov, 0.5, model.z_range)
    lo, hi = 1500.0, SHAPE[0] * PX - 1500.0
    place = rng.uniform(lo, hi, (bright, 2))
    z = rng.uniform(*model.z_range, bright) * 0.5
    rows = [
        dict(frame=f, x_nm=place[i, 0], y_nm=place[i, 1], z_nm=z[i], photons=photons)
        for f in range(frames)
        for i in range(bright)
    ]
    if rows:
        truth = pd.concat([truth, pd.DataFrame(rows, columns=truth.columns)], ignore_index=True)
    truth = truth.sort_values("frame", kind="stable").reset_index(drop=True)
    mu = render_movie(model, truth, frames, SHAPE, PX, 10.0, radius_nm=8000.0)
    return rng.poisson(mu).astype(np.float64), truth


def run(model, frames, truth, halo: bool) -> dict:
    """Localize and score, with the halo step as the pipeline has it or switched off."""
    solver = pipeline_mod._FrameSolver
    saved = solver.halo
    if not halo:
        solver.halo = lambda self, fit, background: None
    try:
        t0 = time.perf_counter()
        table = localize(frames, model, LocalizeParams(pixel_size=PX), check=False).table
        seconds = time.perf_counter() - t0
    finally:
        solver.halo = saved
    ev = evaluate(table, truth)
    return dict(
        jaccard=ev.jaccard,
        tp=ev.tp,
        fp=ev.fp,
        fn=ev.fn,
        rmse_lateral=ev.rmse_lateral,
        rmse_axial=ev.rmse_axial,
        seconds=seconds,
    )


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--psfs", default="dh,astig")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--bright", type=int, default=4, help="bright emitters per frame")
    ap.add_argument("--photons", type=float, default=250_000.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--calibration", type=Path, help="a bead calibration of the first PSF")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/halo.json"))
    args = ap.parse_args(argv)
    print(
        f"{args.frames} frames of {SHAPE[0]}x{SHAPE[1]} px of {PX:.0f} nm, 0.5 /um^2 of "
        f"1,000-5,000 photons, background 10; {args.bright} emitters of {args.photons:,.0f} "
        "photons per frame at fixed places; the pupil model simulates and localizes"
    )
    hdr = (
        f"{'psf':>6} {'model':>11} {'movie':>8} {'halo':>5} | {'Jaccard %':>9} {'TP':>5} "
        f"{'FP':>5} {'FN':>5} "
        f"| {'RMSE lat':>8} {'ax nm':>6} | {'s':>6}"
    )
    print(hdr)
    print("-" * len(hdr))
    out: dict = {
        "sparseloc": sparseloc.__version__,
        "machine": platform.platform(),
        "args": {k: str(v) for k, v in vars(args).items()},
        "rows": [],
    }
    for i, name in enumerate(args.psfs.split(",")):
        model = make_psf(name)
        fitted = [("pupil", model)]
        if i == 0 and args.calibration is not None:
            fitted.append(("calibration", load_calibration(args.calibration)))
        for label, bright in (("control", 0), ("bright", args.bright)):
            frames, truth = movie(model, args.frames, bright, args.photons, args.seed)
            for (kind, fit_model), halo in itertools.product(fitted, (False, True)):
                r = run(fit_model, frames, truth, halo)
                r.update(psf=name, model=kind, movie=label, halo=halo)
                out["rows"].append(r)
                print(
                    f"{name:>6} {kind:>11} {label:>8} {'on' if halo else 'off':>5} | "
                    f"{r['jaccard']:9.1f} "
                    f"{r['tp']:5d} {r['fp']:5d} {r['fn']:5d} | {r['rmse_lateral']:8.1f} "
                    f"{r['rmse_axial']:6.1f} | {r['seconds']:6.1f}",
                    flush=True,
                )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
