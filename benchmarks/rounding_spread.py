"""How far one dense frame's score moves under rounding: storm-analysis's 1 /um^2 double-helix
frame localized with the frame scaled by ``1 + k * 1e-12``.

The frame solver makes discrete choices (which emitters to add, remove, relocate; which of a
region's arrangements is likeliest); where two choices are nearly equally likely, a change in
the last bits of the data decides. A change of the code that moves the score by less than
this spread is not measured by one run of this frame. Prints each run's Jaccard, recall and
precision and their spread; writes ``benchmarks/results/rounding_spread.json``::

    python benchmarks/rounding_spread.py [--data ../shared/data] [--runs 7]
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
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/rounding_spread.json"))
    args = ap.parse_args(argv)
    folder = args.data / "storm_analysis_sim" / "dh"
    cal = calibrate_file(
        folder / "beads_zscan.tif", PX, z_file=folder / "beads_zscan_z.csv", offset=100.0
    )
    frame = tifffile.imread(folder / f"{FRAME}.tif").astype(np.float64) - 100.0
    frame = frame.reshape(-1, *frame.shape[-2:])
    truth = read_truth_csv(folder / f"{FRAME}_groundtruth.csv", pixel_size=PX)
    rows = []
    print(f"{'scale - 1':>10s} {'Jaccard %':>9s} {'recall':>7s} {'precision':>9s}")
    for k in range(-(args.runs // 2), args.runs // 2 + 1):
        eps = k * 1e-12
        res = localize(frame * (1.0 + eps), cal.psf, LocalizeParams(pixel_size=PX))
        ev = evaluate(res.table, truth)
        rows.append(
            {"eps": eps, "jaccard": ev.jaccard, "recall": ev.recall, "precision": ev.precision}
        )
        print(f"{eps:10.0e} {ev.jaccard:9.2f} {ev.recall:7.3f} {ev.precision:9.3f}", flush=True)
    j = np.array([r["jaccard"] for r in rows])
    print(f"Jaccard mean {j.mean():.2f}, SD {j.std(ddof=1):.2f}, range {j.min():.2f}-{j.max():.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {args.out}")
    return rows


if __name__ == "__main__":
    main()
