"""storm-analysis's simulated double-helix frames through the pipeline (issue 5's peer data).

Calibrates a spline PSF from the folder's bead z-scan (``calibrate_file``), localizes the grid
frame and the two random-density frames (0.5 and 1 emitter/um^2) with the default frame solver,
and prints Jaccard, recall, precision and RMSE against the folder's ground truth; writes JSON.
storm-analysis's own result on the grid frame (its README): recall 1.00, RMSE x/y/z
3.4/3.7/5.5 nm.

Usage::

    python benchmarks/storm_analysis.py [--data ../shared/data/storm_analysis_sim/dh]
                                        [--workers 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import tifffile

from sparseloc.calibrate import calibrate_file
from sparseloc.evaluate import evaluate
from sparseloc.io.truth import read_truth_csv
from sparseloc.pipeline import LocalizeParams, localize

FRAMES = {
    "grid": "dh_fista_diag_test01",
    "0.5 /um^2": "dh_random_density0.005px2",
    "1 /um^2": "dh_random_density0.01px2",
}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/storm_analysis_sim/dh"))
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/storm_analysis.json"))
    args = ap.parse_args(argv)
    px = 100.0
    t0 = time.perf_counter()
    cal = calibrate_file(
        args.data / "beads_zscan.tif", px, z_file=args.data / "beads_zscan_z.csv", offset=100.0
    )
    print(f"calibration from the bead scan: {time.perf_counter() - t0:.1f} s")
    hdr = (
        f"{'frame':>10} {'emitters':>8} | {'Jaccard %':>9} {'recall':>6} {'precision':>9} | "
        f"{'RMSE x':>6} {'y':>5} {'z':>5} {'lat':>5} {'ax':>5} nm | {'s':>5}"
    )
    print(hdr)
    print("-" * len(hdr))
    rows = []
    for label, name in FRAMES.items():
        frame = tifffile.imread(args.data / f"{name}.tif").astype(np.float64) - 100.0
        frame = frame.reshape(-1, *frame.shape[-2:])
        truth = read_truth_csv(args.data / f"{name}_groundtruth.csv", pixel_size=px)
        t0 = time.perf_counter()
        res = localize(frame, cal.psf, LocalizeParams(pixel_size=px), workers=args.workers)
        secs = time.perf_counter() - t0
        ev = evaluate(res.table, truth)
        print(
            f"{label:>10} {ev.n_truth:8d} | {ev.jaccard:9.1f} {ev.recall:6.3f} "
            f"{ev.precision:9.3f} | {ev.rmse_x:6.2f} {ev.rmse_y:5.2f} {ev.rmse_z:5.2f} "
            f"{ev.rmse_lateral:5.1f} {ev.rmse_axial:5.1f}    | {secs:5.1f}",
            flush=True,
        )
        rows.append(
            {
                "frame": name,
                "n_truth": ev.n_truth,
                "jaccard": ev.jaccard,
                "recall": ev.recall,
                "precision": ev.precision,
                "rmse_x_nm": ev.rmse_x,
                "rmse_y_nm": ev.rmse_y,
                "rmse_z_nm": ev.rmse_z,
                "rmse_lateral_nm": ev.rmse_lateral,
                "rmse_axial_nm": ev.rmse_axial,
                "seconds": secs,
            }
        )
    out = {"rows": rows, "workers": args.workers}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
