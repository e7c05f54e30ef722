"""The temporal background's bump cap (``detect.capped_bumps``), with and without, side by side.

A temporal percentile takes in a molecule that stays on for a third of its window or more;
the cap removes such bumps, and must leave a structured background alone. Simulates movies
of blinking filaments (the project's simulator, 64 x 64 px of 100 nm, 60 frames, about 0.3
active emitters /um^2, 1,000-5,000 photons) for each case:

- on-times: short (``p_off`` 0.5, a molecule is on for 2 frames on average) or long
  (``p_off`` 0.05, 20 frames: longer than half the 21-frame background window);
- background: flat (20 photons/px), or structured: 20 photons/px plus six smooth blobs of
  1-2 um adding 15-40 photons/px each (a cell's autofluorescence);

and localizes each with default settings (temporal background) with the cap and with the
cap switched off. Prints Jaccard, recall, precision and RMSE; writes
``benchmarks/results/background_bumps.json``::

    python benchmarks/background_bumps.py [--psf astig dh] [--frames 60]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from unittest import mock

import numpy as np

from sparseloc import pipeline
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate

PX = 100.0
SHAPE = (64, 64)
BACKGROUND = 20.0


def structured_background(seed: int = 7) -> np.ndarray:
    """20 photons/px plus six smooth blobs (standard deviation 1-2 um, 15-40 photons/px)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]]
    bg = np.full(SHAPE, BACKGROUND)
    for _ in range(6):
        r, c = rng.uniform(0, SHAPE[0]), rng.uniform(0, SHAPE[1])
        s = rng.uniform(10.0, 20.0)
        bg += rng.uniform(15.0, 40.0) * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * s * s))
    return bg


def run_case(psf: str, model, work, p_off: float, background, frames: int, seed: int) -> dict:
    sim = simulate(
        model,
        scene="filament",
        n_frames=frames,
        shape=SHAPE,
        pixel_size=PX,
        density=0.3,
        photons=(1000.0, 5000.0),
        background=background,
        seed=seed,
        z_range=(-500.0, 500.0),
        p_off=p_off,
        n_filaments=4,
    )
    movie = sim.movie.astype(float) - sim.camera.offset
    params = LocalizeParams(pixel_size=PX, z_range=(-500.0, 500.0), background="temporal")
    row = {"psf": psf, "p_off": p_off, "truth": len(sim.truth)}
    for label, cap in (("cap", pipeline.capped_bumps), ("no cap", lambda b, w: b)):
        with mock.patch.object(pipeline, "capped_bumps", cap):
            res = localize(movie, work, params, check=False)
        ev = evaluate(res.table, sim.truth)
        row[label] = {
            "jaccard": ev.jaccard,
            "recall": ev.recall,
            "precision": ev.precision,
            "rmse_lateral": ev.rmse_lateral,
            "rmse_axial": ev.rmse_axial,
        }
    return row


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", nargs="+", default=["astig", "dh"])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/background_bumps.json"))
    args = ap.parse_args(argv)
    rows = []
    print(
        f"{'PSF':6s} {'on-times':9s} {'background':10s} {'truth':>5s} | "
        f"{'cap: Jac %':>10s} {'rec':>5s} {'prec':>5s} {'lat':>5s} {'ax':>5s} | "
        f"{'no cap: Jac %':>13s} {'rec':>5s} {'prec':>5s} {'lat':>5s} {'ax':>5s}"
    )
    for psf in args.psf:
        model = make_psf(psf)
        work = work_model_for(model, LocalizeParams(pixel_size=PX))
        for bg_label, bg in (("flat", BACKGROUND), ("structured", structured_background())):
            for p_off, on_label in ((0.5, "short"), (0.05, "long")):
                row = run_case(psf, model, work, p_off, bg, args.frames, seed=11)
                row["background"] = bg_label
                rows.append(row)
                a, b = row["cap"], row["no cap"]
                print(
                    f"{psf:6s} {on_label:9s} {bg_label:10s} {row['truth']:5d} | "
                    f"{a['jaccard']:10.1f} {a['recall']:5.3f} {a['precision']:5.3f} "
                    f"{a['rmse_lateral']:5.1f} {a['rmse_axial']:5.1f} | "
                    f"{b['jaccard']:13.1f} {b['recall']:5.3f} {b['precision']:5.3f} "
                    f"{b['rmse_lateral']:5.1f} {b['rmse_axial']:5.1f}",
                    flush=True,
                )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2, default=float))
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
