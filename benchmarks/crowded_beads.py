"""A crowded bead slide calibrates as well as a sparse one (issue "Trust on data...").

The optics: the pupil double helix (NA 1.45, 670 nm) on 160 nm pixels, tabulated once. Two
bead z-scans of it (20,000 photons per bead and plane, background 10, 20 nm steps, -1..+1 um):

- ``crowded``: 4 beads on a square 3.5 um apart (the double helix is 3-5 um wide);
- ``separate``: 9 beads 9.6 um apart.

Each is calibrated with default settings (``calibrate_beads``), and the two models localize the
same simulated frames (64 x 64 px, uniform emitters at 0.5 and 1 /um^2, 1,000-5,000 photons,
background 10, drawn with the true model). The table gives the beads used, the ROI and the light
it holds, the model error, and Jaccard / RMSE with each model, and the true model for reference.

Usage::

    python benchmarks/crowded_beads.py [--frames 6] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from sparseloc.calibrate import calibrate_beads
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.simulate import bead_scan_truth, simulate

PX = 160.0
Z_STEP = 20.0


def bead_scan(model, positions: np.ndarray, shape: tuple[int, int], seed: int) -> np.ndarray:
    """A uint16 z-scan (offset 100 ADU) of beads at ``positions`` (nm, x then y)."""
    zp = np.arange(-1000.0, 1000.0 + 1e-6, Z_STEP)
    scene = bead_scan_truth(positions, zp, 20000.0)
    sim = simulate(
        model,
        scene=scene,
        n_frames=zp.size,
        shape=shape,
        pixel_size=PX,
        background=10.0,
        seed=seed,
    )
    return sim.movie


def calibrations(model) -> dict:
    """The crowded and the separate calibration of ``model``'s optics."""
    centre = np.array([40.0, 40.0]) * PX
    offsets = [np.array([dx, dy]) for dx in (-1750.0, 1750.0) for dy in (-1750.0, 1750.0)]
    crowded = np.array([centre + d for d in offsets])
    separate = np.array([(x, y) for x in (30.0, 90.0, 150.0) for y in (30.0, 90.0, 150.0)]) * PX
    out = {}
    for name, pos, shape in (("crowded", crowded, (80, 80)), ("separate", separate, (180, 180))):
        cal = calibrate_beads(bead_scan(model, pos, shape, seed=1), PX, Z_STEP, offset=100.0)
        out[name] = cal
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/crowded_beads.json"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    truth_model = SplinePSF.from_model(make_psf("dh"), PX, roi=41, z_step=10.0)
    cals = calibrations(truth_model)
    rows = []
    print(
        f"{'calibration':>11} | beads | ROI px | light held | model err | density | "
        f"Jaccard | RMSE lat / ax nm"
    )
    for density in (0.5, 1.0):
        sim = simulate(
            truth_model,
            scene="uniform",
            n_frames=args.frames,
            shape=(64, 64),
            pixel_size=PX,
            density=density,
            photons=(1000.0, 5000.0),
            background=10.0,
            z_range=(-800.0, 800.0),
            seed=7,
        )
        frames = sim.movie.astype(np.float64) - sim.camera.offset
        for name in ("crowded", "separate", "true"):
            model = truth_model if name == "true" else cals[name].psf
            res = localize(frames, model, LocalizeParams(pixel_size=PX))
            ev = evaluate(res.table, sim.truth)
            cal = cals.get(name)
            row = {
                "calibration": name,
                "density": density,
                "jaccard": ev.jaccard,
                "rmse_lateral": ev.rmse_lateral,
                "rmse_axial": ev.rmse_axial,
                "beads_used": None if cal is None else f"{cal.n_used}/{len(cal.beads)}",
                "roi_px": None if cal is None else cal.params["roi_size_px"],
                "light_held": None if cal is None else cal.params["roi_energy_fraction"],
                "model_error": None if cal is None else cal.params["model_error"],
            }
            rows.append(row)
            held = "" if cal is None else f"{100 * row['light_held'][0]:.1f} %"
            err = "" if cal is None else f"{100 * row['model_error']:.1f} %"
            print(
                f"{name:>11} | {row['beads_used'] or '':>5} | {row['roi_px'] or '':>6} | "
                f"{held:>10} | {err:>9} | {density:7.1f} | {ev.jaccard:7.1f} | "
                f"{ev.rmse_lateral:.1f} / {ev.rmse_axial:.1f}",
                flush=True,
            )
    print(f"total {time.perf_counter() - t0:.0f} s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows}, indent=2, default=float))
    print(f"wrote {args.out}")
    return {"rows": rows}


if __name__ == "__main__":
    main()
