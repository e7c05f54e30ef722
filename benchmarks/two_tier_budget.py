"""Where a sparse movie's time goes in the two tiers, against the time issue 26's target allows.

Localizes the first ``--frames`` frames of a movie that ``smappy_side_by_side.py`` made (its
``--work`` folder: ``PSF/density_D/movie.tif`` and ``PSF/sparseloc_cal.h5``) in one process
with the default settings, timers around the steps of the two-tier solver
(:mod:`sparseloc.solvers.two_tier`), and prints milliseconds per frame for each step beside
the budget: the time per frame and core at which sparseloc would localize at ``--ratio``
times SMAPpy's end-to-end rate (read from that script's JSON, ``--reference``), the rate
being shared by ``--cores`` cores. A step's time counts at its outermost call, so the rows
add up to the total; the compiled fit loop's row is the part of them spent in
:func:`sparseloc.solvers._fit_numba.lm_fit`.

Beside it, a floor: the least a localizer of this design does per frame, on the very frames
and background estimates the run used (recorded during it): the two tiers' own detection (its
z planes, threshold and camera noise) and z starts, then one compiled single-emitter fit per
candidate in its window (:func:`~sparseloc.solvers.mle.fit_emitters`; no neighbours' light,
count selection, z flips, promotion or crowds), kept where it converged with at least 100
photons. Both tables are scored against the movie's truth (3D, 250 nm lateral, 500 nm
axial), so the gap between them says what the two tiers' work buys and costs::

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
import pandas as pd
import tifffile

import sparseloc
import sparseloc.pipeline as pipeline_mod
import sparseloc.solvers.two_tier as tt
from phases import outermost_timers  # this folder is on the path
from sparseloc.config import LocalizeParams
from sparseloc.evaluate import evaluate
from sparseloc.io.calibration import load_calibration
from sparseloc.pipeline import localize, work_model_for
from sparseloc.solvers.emitters import Emitters
from sparseloc.solvers.frame_windows import window_box
from sparseloc.solvers.mle import fit_emitters

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


def _install(acc: collections.Counter, calls: collections.Counter, seen: list) -> list:
    """Wrap each step's function with a timer counted at its outermost call, and record each
    (frame, background) the frame solver is given in ``seen``."""
    wrap, saved = outermost_timers(acc, calls)
    solver = pipeline_mod._FrameSolver
    solve = solver.__call__

    def recording(self, frame, background, start=None):
        seen.append((np.asarray(frame), np.asarray(background)))
        return solve(self, frame, background, start)

    solver.__call__ = recording
    saved.append((solver, "__call__", solve))
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


def floor(seen: list, model, params: LocalizeParams) -> tuple[pd.DataFrame, float]:
    """The floor's table (one fit per candidate, see the module notes) of the recorded
    (frame, background) pairs, and its seconds."""
    solver = pipeline_mod._FrameSolver(model, params, seen[0][0].shape)
    planes = tt.detection_planes(solver.templates)
    threshold = params.min_snr * tt.detection_match(solver.templates, planes)
    cache: dict = {}
    px = params.pixel_size
    rows = []
    t0 = time.perf_counter()
    for k, (f, bg) in enumerate(seen):
        cand = tt.detect_candidates(f, bg, planes, threshold=threshold, cache=cache)
        for s in tt.z_starts(f, bg, cand, solver.templates):
            r0, r1, c0, c1 = window_box(s[None], *f.shape, px, solver.pad)
            fit = fit_emitters(
                f[r0:r1, c0:c1],
                model,
                Emitters.from_array(s[None]),
                pixel_size=px,
                origin=(c0 * px, r0 * px),
                background=float(np.median(bg[r0:r1, c0:c1])),
            )
            e = fit.emitters.as_array().reshape(-1, 4)
            if fit.converged and len(e) and e[0, 3] >= 100.0:
                rows.append((k, *e[0]))
    seconds = time.perf_counter() - t0
    return pd.DataFrame(rows, columns=["frame", "x_nm", "y_nm", "z_nm", "photons"]), seconds


def scored(table: pd.DataFrame, truth: pd.DataFrame | None, seconds: float) -> dict:
    """Localizations per second, and the scores against ``truth`` where there is one."""
    out = {"seconds": seconds, "rows": len(table), "locs_per_s": len(table) / seconds}
    if truth is not None:
        ev = evaluate(table, truth, lateral_tol=250.0, axial_tol=500.0)
        out.update(
            jaccard=ev.jaccard,
            recall=ev.recall,
            precision=ev.precision,
            rmse_lateral_nm=ev.rmse_lateral,
            rmse_axial_nm=ev.rmse_axial,
        )
    return out


def _score_line(name: str, r: dict) -> str:
    line = f"{name:9s} {r['rows']:6d} rows in {r['seconds']:6.2f} s ({r['locs_per_s']:5.0f} /s)"
    if "jaccard" in r:
        line += (
            f", Jaccard {r['jaccard']:.2f} %, recall {r['recall']:.3f}, precision "
            f"{r['precision']:.3f}, RMSE {r['rmse_lateral_nm']:.1f} / {r['rmse_axial_nm']:.1f} nm"
        )
    return line


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
    truth_csv = folder / f"density_{args.density}" / "movie_truth.csv"
    truth = None
    if truth_csv.exists():
        truth = pd.read_csv(truth_csv)
        truth = truth[truth.frame < len(frames)]
    params = LocalizeParams(pixel_size=100.0)
    model = work_model_for(load_calibration(folder / "sparseloc_cal.h5"), params)
    localize(frames[:2], model, params)  # kernels compiled or loaded before the clock starts

    acc: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    seen: list = []
    saved = _install(acc, calls, seen)
    try:
        t0 = time.perf_counter()
        res = localize(frames, model, params)
        total = time.perf_counter() - t0
    finally:
        for owner, name, f in reversed(saved):
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
    full = scored(res.table, truth, total)
    low_table, low_s = floor(seen, model, params)
    low = scored(low_table, truth, low_s)
    print(_score_line("localize", full))
    print(_score_line("floor", low))
    print(f"localize takes {total / low_s:.1f}x the floor's time")
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
        "localize": full,
        "floor": low,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
