"""Where a sparse movie's time goes in the two tiers, against the time issue 26's target allows.

Localizes the first ``--frames`` frames of a movie that ``smappy_side_by_side.py`` made (its
``--work`` folder: ``PSF/density_D/movie.tif`` and ``PSF/sparseloc_cal.h5``) in one process
with the default settings, timers around the steps of the two-tier solver
(:mod:`sparseloc.solvers.two_tier`), and prints milliseconds per frame for each step beside
the budget: the time per frame and core at which sparseloc would localize at ``--ratio``
times SMAPpy's end-to-end rate (read from that script's JSON, ``--reference``), the rate
being shared by ``--cores`` cores. A step's time counts at its outermost call, so the rows
add up to the total; the compiled fit loop's row is the part of them spent in
:func:`sparseloc.solvers._fit_numba.lm_fit`::

    python benchmarks/two_tier_budget.py --work /tmp/sm --psf astig \
        --reference benchmarks/results/smappy_side_by_side_astig_1000.json
"""

from __future__ import annotations

import argparse
import collections
import json
import platform
import time
from pathlib import Path

import numpy as np
import tifffile

import sparseloc
import sparseloc.pipeline as pipeline_mod
import sparseloc.solvers.two_tier as tt
from phases import outermost_timers  # this folder is on the path
from sparseloc.config import LocalizeParams
from sparseloc.io.calibration import load_calibration
from sparseloc.pipeline import localize, work_model_for

#: (owner, function, step): the steps timed, at their outermost call.
STEPS = (
    (pipeline_mod, "temporal_backgrounds", "backgrounds"),
    (pipeline_mod, "capped_bumps", "backgrounds"),
    (pipeline_mod, "spatial_background", "backgrounds"),
    (tt, "detect_candidates", "detection"),
    (tt, "z_starts", "z starts"),
    (tt, "_add_units", "unit fits"),
    (tt, "_refit_sweeps", "unit refits"),
    (tt, "_unexplained", "residual detection"),
    (tt, "_units_from_peaks", "residual peaks as units"),
    (tt, "_solve_crowds", "crowds"),
    (pipeline_mod._FrameSolver, "whole", "frames solved whole"),
)
#: The compiled Levenberg-Marquardt loop's row (inside the steps above).
LOOP = "compiled fit loop (within)"


def _install(acc: collections.Counter, calls: collections.Counter) -> list:
    """Wrap each step's function with a timer counted at its outermost call."""
    wrap, saved = outermost_timers(acc, calls)
    for owner, name, label in STEPS:
        wrap(owner, name, label)
    # the compiled fit loop runs inside several steps: timed on its own, not exclusively
    from sparseloc.solvers import _fit_numba

    loop = _fit_numba.lm_fit
    saved.append((_fit_numba, "lm_fit", loop))

    def timed_loop(*a):
        t = time.perf_counter()
        try:
            return loop(*a)
        finally:
            acc[LOOP] += time.perf_counter() - t
            calls[LOOP] += 1

    _fit_numba.lm_fit = timed_loop
    return saved


def smappy_rate(reference: Path, psf: str) -> float:
    """SMAPpy's end-to-end localizations per second in a smappy_side_by_side.py JSON."""
    data = json.loads(reference.read_text())
    for case in data["cases"]:
        if case["psf"] == psf and "locs_per_s_end_to_end" in case.get("smappy", {}):
            return float(case["smappy"]["locs_per_s_end_to_end"])
    raise SystemExit(f"{reference} holds no SMAPpy rate for the {psf} movie")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="smappy_side_by_side.py --work")
    ap.add_argument("--psf", default="astig", help="the movie's PSF folder: astig or dh")
    ap.add_argument("--density", default="0.05")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--reference", type=Path, required=True, help="smappy_side_by_side JSON")
    ap.add_argument("--ratio", type=float, default=0.5, help="target share of SMAPpy's rate")
    ap.add_argument("--cores", type=int, default=2, help="cores SMAPpy's rate was measured on")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/two_tier_budget.json"))
    args = ap.parse_args(argv)

    folder = args.work / args.psf
    movie = tifffile.imread(folder / f"density_{args.density}" / "movie.tif")
    frames = movie[: args.frames].astype(np.float64) - 100.0  # the script's camera: offset 100
    params = LocalizeParams(pixel_size=100.0)
    model = work_model_for(load_calibration(folder / "sparseloc_cal.h5"), params)
    localize(frames[:2], model, params)  # kernels compiled or loaded before the clock starts

    acc: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    saved = _install(acc, calls)
    try:
        t0 = time.perf_counter()
        res = localize(frames, model, params)
        total = time.perf_counter() - t0
    finally:
        for owner, name, f in saved:
            setattr(owner, name, f)

    n, locs = len(frames), len(res.table)
    rate = smappy_rate(args.reference, args.psf)
    budget = 1e3 * (locs / n) / (args.ratio * rate / args.cores)
    print(
        f"{args.psf} {args.density} /um^2: {n} frames, {locs} localizations "
        f"({locs / n:.1f} per frame) in {total:.1f} s, one process ({locs / total:.0f} /s)"
    )
    print(f"{'step':26s} {'ms/frame':>9s} {'share':>6s} {'calls':>6s}")
    print("-" * 50)
    rows = {}
    for label in dict.fromkeys(label for _, _, label in STEPS):
        ms = 1e3 * acc[label] / n
        rows[label] = {"ms_per_frame": ms, "calls": calls[label]}
        print(f"{label:26s} {ms:9.2f} {acc[label] / total:6.1%} {calls[label]:6d}")
    rest = total - sum(v for k, v in acc.items() if k != LOOP)
    rows["rest"] = {"ms_per_frame": 1e3 * rest / n, "calls": None}
    print(f"{'rest':26s} {1e3 * rest / n:9.2f} {rest / total:6.1%}")
    print(f"{'total':26s} {1e3 * total / n:9.2f}")
    loop_ms = 1e3 * acc[LOOP] / n
    rows[LOOP] = {"ms_per_frame": loop_ms, "calls": calls[LOOP]}
    print(f"{LOOP:26s} {loop_ms:9.2f} {acc[LOOP] / total:6.1%} {calls[LOOP]:6d}")
    print(
        f"budget at {args.ratio:g} x SMAPpy's {rate:.0f} localizations/s on {args.cores} cores: "
        f"{budget:.2f} ms per frame and core ({1e3 * total / n / budget:.1f}x over)"
    )
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.platform(),
        "sparseloc": sparseloc.__version__,
        "args": {k: str(v) for k, v in vars(args).items()},
        "frames": n,
        "localizations": locs,
        "total_s": total,
        "steps": rows,
        "smappy_locs_per_s": rate,
        "budget_ms_per_frame": budget,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
