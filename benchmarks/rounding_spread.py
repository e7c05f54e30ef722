"""How far one dense frame's score moves under rounding: storm-analysis's 1 /um^2 double-helix
frame localized with the frame scaled by ``1 + k * 1e-12``.

The frame solver makes discrete choices (which emitters to add, remove, relocate; which of a
region's arrangements is likeliest); where two choices are nearly equally likely, a change in
the last bits of the data decides. A change of the code that moves the score by less than
this spread is not measured by one run of this frame. Prints each run's Jaccard, recall,
precision and RMSE and their spread; writes ``benchmarks/results/rounding_spread.json``.
``--crop 100,150`` localizes the crop of the slow test
``tests/test_calibrate_shared.py::test_storm_analysis_dh_random_density_1_per_um2`` (its
rows and columns from the top left, scored against the truth inside it) with k = 0 .. runs - 1::

    python benchmarks/rounding_spread.py [--data ../shared/data] [--runs 7] [--crop ROWS,COLS]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import tifffile

from sparseloc.calibrate import calibrate_file
from sparseloc.evaluate import evaluate
from sparseloc.io.truth import read_truth_csv
from sparseloc.pipeline import LocalizeParams, localize

PX = 100.0
FRAME = "dh_random_density0.01px2"


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--runs", type=int, default=7, help="k = -(runs // 2) .. runs // 2")
    ap.add_argument("--crop", default=None, help="ROWS,COLS: the slow test's crop of the frame")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rounding_spread.json"))
    args = ap.parse_args(argv)
    folder = args.data / "storm_analysis_sim" / "dh"
    cal = calibrate_file(
        folder / "beads_zscan.tif", PX, z_file=folder / "beads_zscan_z.csv", offset=100.0
    )
    frame = tifffile.imread(folder / f"{FRAME}.tif").astype(np.float64) - 100.0
    frame = frame.reshape(-1, *frame.shape[-2:])
    truth = read_truth_csv(folder / f"{FRAME}_groundtruth.csv", pixel_size=PX)
    params = LocalizeParams(pixel_size=PX)
    ks = range(-(args.runs // 2), args.runs // 2 + 1)
    if args.crop:
        n_rows, n_cols = (int(v) for v in args.crop.split(","))
        frame = frame[:, :n_rows, :n_cols]
        truth = truth[(truth["x_nm"] < n_cols * PX) & (truth["y_nm"] < n_rows * PX)]
        params = LocalizeParams(pixel_size=PX, window=21, margin=6)  # as the test
        ks = range(args.runs)
    keys = ("jaccard", "recall", "precision", "rmse_lateral", "rmse_axial")
    rows = []
    print(
        f"{'scale - 1':>10s} {'Jaccard %':>9s} {'recall':>7s} {'precision':>9s}"
        f" {'RMSE lat / ax nm':>17s}"
    )
    for k in ks:
        eps = k * 1e-12
        res = localize(frame * (1.0 + eps), cal.psf, params)
        ev = evaluate(res.table, truth)
        rows.append({"eps": eps, **{key: float(getattr(ev, key)) for key in keys}})
        print(
            f"{eps:10.0e} {ev.jaccard:9.2f} {ev.recall:7.3f} {ev.precision:9.3f}"
            f" {ev.rmse_lateral:8.1f} {ev.rmse_axial:8.1f}",
            flush=True,
        )
    for key in keys:
        v = np.array([r[key] for r in rows])
        print(
            f"{key:>12s} mean {v.mean():.3f}, SD {v.std(ddof=1):.3f},"
            f" range {v.min():.3f}-{v.max():.3f}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
