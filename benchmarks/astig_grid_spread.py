"""How far RMSE / sqrt(CRLB) of one 126-emitter frame spreads when the model is exact.

storm-analysis's astigmatic grid frame (``../shared/data/storm_analysis_sim/astig``) is one
frame of 126 emitters; outside.py scores it as RMSE / sqrt(CRLB) per axis. This script
renders the same emitters (positions, z, photons, background 20) with the model calibrated
from that folder's bead scan, draws Poisson noise many times, localizes each draw with
default settings and prints the ratio per axis per draw, their mean, spread and how often a
draw exceeds 1.1; writes ``benchmarks/results/astig_grid_spread.json``::

    python benchmarks/astig_grid_spread.py [--draws 30] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from sparseloc.calibrate import calibrate_file
from sparseloc.crlb import crlb
from sparseloc.evaluate import evaluate
from sparseloc.io.truth import read_truth_csv
from sparseloc.pipeline import LocalizeParams, localize

PX = 100.0
BACKGROUND = 20.0
SHAPE = (200, 300)


def crlb_rms(model, truth) -> np.ndarray:
    """Root-mean-square sqrt(CRLB) of x, y, z over ``truth`` (each alone in 21 x 21 px)."""
    c = 10.5 * PX
    sd = [
        np.asarray(crlb(model, [c], [c], [t.z_nm], [t.photons], BACKGROUND, (21, 21), PX)).reshape(
            -1
        )[:3]
        for t in truth.itertuples()
    ]
    return np.sqrt(np.mean(np.square(sd), axis=0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/astig_grid_spread.json"))
    args = ap.parse_args()
    folder = args.data / "storm_analysis_sim" / "astig"
    cal = calibrate_file(
        folder / "beads_zscan.tif", PX, z_file=folder / "beads_zscan_z.csv", offset=100.0
    )
    truth = read_truth_csv(folder / "as_spliner_diag_test02_groundtruth.csv", pixel_size=PX)
    truth = truth[truth["frame"] < 1].reset_index(drop=True)
    rms = crlb_rms(cal.psf, truth)
    t = truth
    mu = cal.psf.render(t.x_nm, t.y_nm, t.z_nm, t.photons, SHAPE, PX) + BACKGROUND
    rng = np.random.default_rng(args.seed)
    ratios = []
    print(f"{len(truth)} emitters, sqrt(CRLB) x/y/z {rms[0]:.1f}/{rms[1]:.1f}/{rms[2]:.1f} nm")
    print(f"{'draw':>4s} {'recall':>6s} {'x':>5s} {'y':>5s} {'z':>5s}")
    for i in range(args.draws):
        frame = rng.poisson(mu)[None].astype(np.float64)
        ev = evaluate(localize(frame, cal.psf, LocalizeParams(pixel_size=PX)).table, truth)
        r = [ev.rmse_x / rms[0], ev.rmse_y / rms[1], ev.rmse_z / rms[2]]
        ratios.append(r)
        print(f"{i:4d} {ev.recall:6.3f} {r[0]:5.2f} {r[1]:5.2f} {r[2]:5.2f}", flush=True)
    o = np.array(ratios)
    over = o > 1.1
    print(f"mean {o.mean(0).round(3)}, SD {o.std(0).round(3)}, max {o.max(0).round(2)}")
    print(f"draws above 1.1 per axis: {over.mean(0).round(2)}; any axis: {over.any(1).mean():.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {"crlb_rms_nm": rms.tolist(), "ratios": o.tolist(), "above_1_1": over.mean(0).tolist()}
        )
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
