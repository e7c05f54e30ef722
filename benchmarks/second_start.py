"""The frame solver with and without one of its extra starts, side by side on the same data in
one run: Jaccard, recall, precision, RMSE and time. ``--option second_start`` (default): the L1
deconvolution's start (``LocalizeParams.second_start``); ``--option regrow``: crowded groups
grown again from one emitter (``LocalizeParams.regrow``).

Data: pupil double-helix movies of 128 x 128 px (100 nm pixels, 1000-5000 photons, background
10, Poisson) at several densities, and storm-analysis's double-helix frames at 0.5 and 1 /um^2
(``../shared/data``, calibrated from its bead z-scan) when present. One process.

Usage::

    python benchmarks/second_start.py [--option second_start|regrow]
                                      [--schedule whole-frame|auto] [--data ../shared/data]
                                      [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import tifffile

from sparseloc.calibrate import calibrate_file
from sparseloc.evaluate import evaluate
from sparseloc.io.truth import read_truth_csv
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate

PX = 100.0
#: The boolean options of ``LocalizeParams`` this script compares.
OPTIONS = ("second_start", "regrow")
#: (emitters/um^2, frames) of the simulated movies.
SIMULATED = ((0.05, 40), (0.5, 5), (1.0, 5), (2.0, 3))
SA_FRAMES = {
    "SA DH 0.5/um2": "dh_random_density0.005px2",
    "SA DH 1/um2": "dh_random_density0.01px2",
}


def cases(data: Path):
    """(label, frames in photons, model, truth)."""
    model = make_psf("dh")
    for i, (density, n) in enumerate(SIMULATED):
        sim = simulate(
            model,
            scene="uniform",
            n_frames=n,
            shape=(128, 128),
            pixel_size=PX,
            density=density,
            photons=(1000.0, 5000.0),
            background=10.0,
            seed=20 + i,
        )
        frames = sim.movie.astype(np.float64) - sim.camera.offset
        yield f"pupil DH {density:g}/um2, {n} frames", frames, model, sim.truth
    folder = data / "storm_analysis_sim" / "dh"
    if not folder.is_dir():
        return
    cal = calibrate_file(
        folder / "beads_zscan.tif", PX, z_file=folder / "beads_zscan_z.csv", offset=100.0
    )
    for label, name in SA_FRAMES.items():
        frame = tifffile.imread(folder / f"{name}.tif").astype(np.float64) - 100.0
        truth = read_truth_csv(folder / f"{name}_groundtruth.csv", pixel_size=PX)
        yield label, frame.reshape(-1, *frame.shape[-2:]), cal.psf, truth


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/second_start.json"))
    ap.add_argument("--option", choices=OPTIONS, default="second_start")
    # the extra starts belong to the whole-frame solver: the auto schedule runs them only on
    # frames and crowd crops it solves whole
    ap.add_argument("--schedule", choices=("whole-frame", "auto"), default="whole-frame")
    args = ap.parse_args(argv)
    print(f"{args.option} off, then on; frame schedule {args.schedule}")
    hdr = (
        f"{'data':>30} {'truth':>6} | {'off: Jac':>8} {'rec':>5} {'prec':>5} {'lat':>5} {'ax':>5} "
        f"{'s':>6} | {'on: Jac':>8} {'rec':>5} {'prec':>5} {'lat':>5} {'ax':>5} {'s':>6} | "
        f"{'time x':>6}"
    )
    print(hdr)
    print("-" * len(hdr))
    rows = []
    background = "spatial" if args.schedule == "whole-frame" else "auto"
    base = LocalizeParams(pixel_size=PX, background=background, frame_schedule=args.schedule)
    for label, frames, model, truth in cases(args.data):
        row = {"data": label}
        for key, on in (("off", False), ("on", True)):
            t0 = time.perf_counter()
            res = localize(frames, model, replace(base, **{args.option: on}), check=False)
            ev = evaluate(res.table, truth)
            row[key] = {
                "jaccard": ev.jaccard,
                "recall": ev.recall,
                "precision": ev.precision,
                "rmse_lateral_nm": ev.rmse_lateral,
                "rmse_axial_nm": ev.rmse_axial,
                "seconds": time.perf_counter() - t0,
            }
            row["n_truth"] = ev.n_truth
        print(
            f"{label:>30} {row['n_truth']:6d} | {_cells(row['off'])} | {_cells(row['on'])} | "
            f"{row['on']['seconds'] / row['off']['seconds']:6.2f}",
            flush=True,
        )
        rows.append(row)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"option": args.option, "rows": rows}, indent=2))
    print(f"wrote {args.out}")
    return {"rows": rows}


def _cells(r: dict) -> str:
    return (
        f"{r['jaccard']:8.1f} {r['recall']:5.3f} {r['precision']:5.3f} "
        f"{r['rmse_lateral_nm']:5.1f} {r['rmse_axial_nm']:5.1f} {r['seconds']:6.1f}"
    )


if __name__ == "__main__":
    main()
