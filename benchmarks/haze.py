"""Localizations on a haze: a sample's background broader than one emitter's image.

Real samples add a haze (autofluorescence, out-of-focus light) to the camera's floor. Here
movies of 128 x 128 px of 100 nm are simulated with a PSF model (the built-in astigmatic and
double-helix pupil models tabulated as the pipeline does, or a calibration given with
``--calibration NAME=FILE``): 0.1 emitters/um^2 per frame at random, 1000-5000 photons, z over
the model's range, a floor of 10 photons/pixel plus a Gaussian haze (sigma ``--haze-sigma``
um, centred on the frame) whose peak is each of ``--amplitudes`` times the floor, Poisson
noise. Each movie is localized with the default settings (at 50 frames or more the
background is estimated from the frames around each frame), once without and once with
``haze`` (the fits follow the background estimate's shape), and scored with
:func:`sparseloc.evaluate.evaluate` (250 nm lateral, 500 nm axial); a localization farther than
250 nm from every true emitter of its frame is a false one, counted also where the haze
exceeds 30 % of its peak. The movies are rendered with the model the fits use: this measures
what the background does, not a model's error.

Usage::

    python benchmarks/haze.py [--frames 60] [--psfs astig,dh] [--amplitudes 0,1,1.5]
        [--calibration astig=PSF.h5] [--out benchmarks/results/haze.json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from sparseloc.config import LocalizeParams
from sparseloc.evaluate import evaluate
from sparseloc.io.calibration import load_calibration
from sparseloc.pipeline import localize, work_model_for
from sparseloc.psf import make_psf

PX = 100.0
SIZE = 128
FLOOR = 10.0
DENSITY = 0.1  # emitters per um^2 per frame


def haze_image(amplitude: float, sigma_um: float) -> np.ndarray:
    """The haze (photons/pixel): a Gaussian of ``sigma_um`` centred on the frame."""
    r, c = np.mgrid[:SIZE, :SIZE]
    s = sigma_um * 1000.0 / PX
    centre = (SIZE - 1) / 2
    return amplitude * np.exp(-((r - centre) ** 2 + (c - centre) ** 2) / (2 * s * s))


def movie(model, haze: np.ndarray, n_frames: int, seed: int) -> tuple[np.ndarray, pd.DataFrame]:
    """Frames (photons) and their truth."""
    rng = np.random.default_rng(seed)
    lo, hi = model.z_range
    frames, rows = [], []
    for f in range(n_frames):
        n = rng.poisson(DENSITY * (SIZE * PX / 1000.0) ** 2)
        x, y = rng.uniform(5, SIZE - 5, (2, n)) * PX
        z = rng.uniform(lo + 50, hi - 50, n)
        ph = rng.uniform(1000, 5000, n)
        light = model.render(x, y, z, ph, (SIZE, SIZE), PX)
        frames.append(rng.poisson(light + FLOOR + haze).astype(np.float64))
        rows += [
            {"frame": f, "x_nm": a, "y_nm": b, "z_nm": c, "photons": d}
            for a, b, c, d in zip(x, y, z, ph, strict=True)
        ]
    return np.array(frames), pd.DataFrame(rows)


def false_ones(table: pd.DataFrame, truth: pd.DataFrame, haze: np.ndarray) -> tuple[int, int]:
    """Localizations with no true emitter of their frame within 250 nm, and those of them
    where the haze exceeds 30 % of its peak."""
    n_false = on_haze = 0
    peak = float(haze.max())
    for f, g in table.groupby("frame"):
        t = truth[truth["frame"] == f]
        xy = g[["x_nm", "y_nm"]].to_numpy()
        far = np.full(len(xy), np.inf)
        d = cKDTree(t[["x_nm", "y_nm"]].to_numpy()).query(xy)[0] if len(t) else far
        bad = xy[d > 250.0]
        n_false += len(bad)
        if peak > 0 and len(bad):
            r = np.clip((bad[:, 1] / PX).astype(int), 0, SIZE - 1)
            c = np.clip((bad[:, 0] / PX).astype(int), 0, SIZE - 1)
            on_haze += int(np.sum(haze[r, c] > 0.3 * peak))
    return n_false, on_haze


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--psfs", default="astig,dh")
    ap.add_argument("--amplitudes", default="0,1,1.5", help="haze peaks, times the floor")
    ap.add_argument("--haze-sigma", type=float, default=3.0, help="um")
    ap.add_argument("--calibration", action="append", default=[], help="NAME=PSF.h5")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/haze.json"))
    args = ap.parse_args()
    cals = dict(c.split("=", 1) for c in args.calibration)
    params = LocalizeParams(pixel_size=PX)
    rows = []
    head = f"{'psf':>6} {'haze':>5} {'--haze':>6} | {'truth':>6} {'locs':>6} {'Jac %':>6}"
    head += f" {'prec':>6} {'rec':>6}"
    head += f" | {'false':>5} {'on haze':>7} | {'lat':>5} {'ax':>5} nm | {'s':>6}"
    print(head)
    print("-" * len(head))
    for name in args.psfs.split(","):
        base = load_calibration(cals[name]) if name in cals else make_psf(name)
        model = work_model_for(base, params)
        for amp in (float(a) for a in args.amplitudes.split(",")):
            haze = haze_image(amp * FLOOR, args.haze_sigma)
            frames, truth = movie(model, haze, args.frames, args.seed)
            for on in (False, True):
                t0 = time.perf_counter()
                res = localize(frames, model, replace(params, haze=on))
                seconds = time.perf_counter() - t0
                ev = evaluate(res.table, truth, lateral_tol=250.0, axial_tol=500.0)
                n_false, on_haze = false_ones(res.table, truth, haze)
                row = {
                    "psf": name, "haze_peak_over_floor": amp, "haze_option": on,
                    "truth": len(truth), "locs": len(res.table), "jaccard": ev.jaccard,
                    "precision": ev.precision, "recall": ev.recall, "false": n_false,
                    "false_on_haze": on_haze, "rmse_lateral": ev.rmse_lateral,
                    "rmse_axial": ev.rmse_axial, "seconds": seconds,
                }  # fmt: skip
                rows.append(row)
                print(
                    f"{name:>6} {amp:>5.2g} {'on' if on else 'off':>6} | {len(truth):>6} "
                    f"{len(res.table):>6} {ev.jaccard:>6.1f} {ev.precision:>6.3f} "
                    f"{ev.recall:>6.3f} | {n_false:>5} {on_haze:>7} | "
                    f"{ev.rmse_lateral:>5.1f} {ev.rmse_axial:>5.1f}    | {seconds:>6.1f}",
                    flush=True,
                )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps({"frames": args.frames, "rows": rows}, indent=1))
    tmp.replace(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
