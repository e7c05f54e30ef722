"""The paper's Figure 2 experiment, repeated over many random trials.

Three emitters at random in a small volume (default 800 x 800 x 600 nm) centred in an 11 x 11
window of 160 nm pixels, 1000-1200 photons each, background 5 photons/pixel, Poisson noise.
Solvers: matching pursuit on the fine dictionary (10 nm / 15 nm, 1.27 million atoms), convex
optimisation on the coarse dictionary (80 nm / 120 nm, 2904 atoms), and the hybrid MP+CO.

``hybrid`` is MP+CO with emitters polished to their best fine-grid atom; ``hybrid-centres``
converts the fine L1 coefficients by weighted centres, as the paper does; ``hybrid+mle`` adds
the continuous maximum-likelihood fit, its count selection and split/merge search (the
solver's default).

For each: the fraction of trials with the right count, the mean 3D error of matched emitters
(Hungarian assignment, no distance gate), the median time per window, and the paper's figures.
Beside them, the Cramer-Rao bound of each trial (three emitters fitted together with the
background): no unbiased method can have a mean 3D error much below the mean of
``sqrt(crlb_x^2 + crlb_y^2 + crlb_z^2)``.
Also: the same figures split by the closest pair's 3D separation, because two emitters closer
than the noise allows to tell apart are counted as one by any method.

Usage::

    python benchmarks/paper_fig2.py [--psf dh|astig] [--trials 200] [--seed 1] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from sparseloc.crlb import crlb
from sparseloc.dictionary import Dictionary
from sparseloc.psf import make_psf
from sparseloc.solvers import matching_pursuit
from sparseloc.solvers.hybrid import convex_solve, hybrid_solve

PAPER = {
    "mp": {"error_nm": "77-118", "time": "tenths of a second"},
    "co": {"error_nm": "44", "time": "an order of magnitude more than MP"},
    "hybrid": {"error_nm": "34", "time": "-"},
    "hybrid-centres": {"error_nm": "34", "time": "-"},
    "hybrid+mle": {"error_nm": "34 (MP+CO)", "time": "-"},
}
SEPARATION_BINS = (0.0, 150.0, 250.0, np.inf)


def make_trial(rng, model, window, pixel, volume, photons, background):
    """One window: true (3, 4) array of x, y, z, photons and the noisy image."""
    centre = np.array([window * pixel / 2, window * pixel / 2, 0.0])
    pos = centre + rng.uniform(-0.5, 0.5, (3, 3)) * np.asarray(volume)
    ph = rng.uniform(*photons, 3)
    mu = model.render(pos[:, 0], pos[:, 1], pos[:, 2], ph, (window, window), pixel) + background
    return rng.poisson(mu).astype(float), np.column_stack([pos, ph])


def match_error(est: np.ndarray, truth: np.ndarray) -> float:
    """Mean 3D distance (nm) of Hungarian-matched pairs; NaN if nothing was found."""
    if len(est) == 0:
        return float("nan")
    d = np.linalg.norm(est[:, None, :3] - truth[None, :, :3], axis=2)
    r, c = linear_sum_assignment(d)
    return float(d[r, c].mean())


def min_separation(truth: np.ndarray) -> float:
    d = np.linalg.norm(truth[:, None, :3] - truth[None, :, :3], axis=2)
    return float(d[np.triu_indices(len(truth), 1)].min())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--psf", default="dh", help="dh or astig (or any make_psf name)")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--window", type=int, default=11)
    ap.add_argument("--pixel", type=float, default=160.0)
    ap.add_argument("--volume", type=float, nargs=3, default=(800.0, 800.0, 600.0))
    ap.add_argument("--photons", type=float, nargs=2, default=(1000.0, 1200.0))
    ap.add_argument("--background", type=float, default=5.0)
    ap.add_argument("--methods", default="mp,co,hybrid-centres,hybrid,hybrid+mle")
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads while solving")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    out = args.out or Path(f"benchmarks/results/paper_fig2_{args.psf}.json")

    model = make_psf(args.psf)
    zr = (-args.volume[2] / 2, args.volume[2] / 2)
    t0 = time.perf_counter()
    coarse = Dictionary(model, args.window, args.pixel, 80.0, 120.0, zr)
    fine = Dictionary(model, args.window, args.pixel, 10.0, 15.0, zr)
    _ = coarse.quantization_error, fine.quantization_error  # computed once, outside the timing
    build = time.perf_counter() - t0
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    solvers = {
        "mp": lambda y: matching_pursuit(y, fine),
        "co": lambda y: convex_solve(y, coarse),
        "hybrid": lambda y: hybrid_solve(y, coarse, fine, refine=False),
        "hybrid+mle": lambda y: hybrid_solve(y, coarse, fine),
        "hybrid-centres": lambda y: hybrid_solve(y, coarse, fine, polish_fine=False, refine=False),
    }
    rng = np.random.default_rng(args.seed)
    trials = [
        make_trial(rng, model, args.window, args.pixel, args.volume, args.photons, args.background)
        for _ in range(args.trials)
    ]
    seps = np.array([min_separation(t) for _, t in trials])
    bound3d = []
    for _, t in trials:
        sd = crlb(
            model,
            t[:, 0],
            t[:, 1],
            t[:, 2],
            t[:, 3],
            args.background,
            (args.window, args.window),
            args.pixel,
            singular="pinv",
        )
        bound3d.append(float(np.mean(np.linalg.norm(sd[:, :3], axis=1))))
    bound3d = np.array(bound3d)
    records: dict[str, list[dict]] = {m: [] for m in methods}
    # One BLAS thread, as the pipeline runs each window: on a shared 2-core machine BLAS's
    # own threads made the hybrid ~6x slower per window (2.7 s against 0.46 s).
    with threadpool_limits(args.threads):
        for m in methods:
            for y, truth in tqdm(trials, desc=m, leave=False):
                t1 = time.perf_counter()
                sol = solvers[m](y)
                dt = time.perf_counter() - t1
                est = sol.emitters.as_array()
                records[m].append(
                    {"count": len(est), "error_nm": match_error(est, truth), "time_s": dt}
                )

    summary = {}
    print(
        f"\nPaper Figure 2 experiment: psf={args.psf}, {args.trials} trials, 3 emitters in "
        f"{args.volume[0]:.0f}x{args.volume[1]:.0f}x{args.volume[2]:.0f} nm, "
        f"{args.photons[0]:.0f}-{args.photons[1]:.0f} photons, background {args.background:g}, "
        f"{args.window}x{args.window} px of {args.pixel:.0f} nm"
    )
    print(
        f"dictionaries: coarse {coarse.size:,} atoms, fine {fine.size:,} atoms "
        f"(built in {build:.1f} s)\n"
    )
    hdr = (
        f"{'method':<15}{'right count':>12}{'mean 3D err':>13}{'err, right count':>18}"
        f"{'median time':>13}   {'paper error':>12}  paper time"
    )
    print(hdr)
    print("-" * len(hdr))
    for m in methods:
        cnt = np.array([r["count"] for r in records[m]])
        err = np.array([r["error_nm"] for r in records[m]])
        tim = np.array([r["time_s"] for r in records[m]])
        right = cnt == 3
        by_sep = []
        for lo, hi in pairwise(SEPARATION_BINS):
            sel = (seps >= lo) & (seps < hi)
            by_sep.append(
                {
                    "min_sep_nm": [lo, None if np.isinf(hi) else hi],
                    "trials": int(sel.sum()),
                    "right_count": float(np.mean(right[sel])) if sel.any() else None,
                    "mean_error_nm": float(np.nanmean(err[sel])) if sel.any() else None,
                }
            )
        summary[m] = {
            "right_count": float(right.mean()),
            "count_histogram": np.bincount(cnt, minlength=6).tolist(),
            "mean_error_nm": float(np.nanmean(err)),
            "mean_error_right_count_nm": float(np.nanmean(err[right])) if right.any() else None,
            "median_time_s": float(np.median(tim)),
            "mean_crlb_3d_nm_right_count": float(
                np.nanmean(np.where(np.isfinite(bound3d), bound3d, np.nan)[right])
            )
            if right.any()
            else None,
            "by_min_separation": by_sep,
            "paper": PAPER.get(m),
        }
        s = summary[m]
        print(
            f"{m:<15}{100 * s['right_count']:>11.1f}%{s['mean_error_nm']:>10.1f} nm"
            f"{s['mean_error_right_count_nm'] or float('nan'):>15.1f} nm"
            f"{1e3 * s['median_time_s']:>10.1f} ms   {PAPER[m]['error_nm']:>9} nm  "
            f"{PAPER[m]['time']}"
        )
    print("\nright count / mean 3D error by the closest pair's 3D separation:")
    print(
        f"{'method':<15}"
        + "".join(
            f"{f'{lo:.0f}-{hi:.0f} nm' if np.isfinite(hi) else f'>= {lo:.0f} nm':>24}"
            for lo, hi in pairwise(SEPARATION_BINS)
        )
    )
    for m in methods:
        cells = []
        for b in summary[m]["by_min_separation"]:
            if b["trials"]:
                cells.append(
                    f"{100 * b['right_count']:5.1f}% {b['mean_error_nm']:6.1f} nm (n={b['trials']})"
                )
            else:
                cells.append("-")
        print(f"{m:<15}" + "".join(f"{c:>24}" for c in cells))
    print("\nmean 3D error vs the Cramer-Rao bound, trials with the right count:")
    for m in methods:
        s = summary[m]
        if s["mean_error_right_count_nm"] is not None:
            print(
                f"{m:<15} error {s['mean_error_right_count_nm']:6.1f} nm, bound "
                f"{s['mean_crlb_3d_nm_right_count']:6.1f} nm, ratio "
                f"{s['mean_error_right_count_nm'] / s['mean_crlb_3d_nm_right_count']:.2f}"
            )
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()}
    meta["out"] = str(out)
    result = {
        "meta": meta,
        "machine": platform.platform(),
        "summary": summary,
        "dictionary_atoms": {"coarse": coarse.size, "fine": fine.size},
        "min_separation_nm": seps.tolist(),
        "records": records,
    }
    out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
