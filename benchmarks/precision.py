"""Precision of the maximum-likelihood stage against the Cramer-Rao bound.

(a) Isolated emitters over the model's z range at 1000, 2000 and 5000 photons and backgrounds 5
    and 20 photons/pixel, double-helix and astigmatic pupil models: RMSE / sqrt(CRLB) in x, y
    and z (errors pooled over z after dividing each by its own bound), bias, and the fraction of
    errors within +-1 reported standard error (0.68 if the reported errors are honest). Fits
    start from the truth perturbed as a sparse solution would be (~ N(0, 30 nm) laterally,
    N(0, 50 nm) axially, photons x U(0.8, 1.2)).
(b) The paper's Figure 2 case (see paper_fig2.py): MP+CO alone, with the maximum-likelihood
    stage without and with its split/merge search, and two fits started from the true emitters
    (with the count selection: what its rule allows once the search is perfect; with the count
    held at 3: the error floor), on the same trials: right-count fraction and mean 3D error.
(c) Pairs of emitters at lateral separations of 100-800 nm, at the same z and 300 nm apart in z:
    detection rate (both found, each within 100 nm) and mean 3D error, hybrid + MLE.

Usage::

    python benchmarks/precision.py [--parts a,b,c] [--reps 25] [--trials 200] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_fig2 import SEPARATION_BINS, make_trial, match_error, min_separation
from sparseloc.crlb import crlb
from sparseloc.dictionary import Dictionary
from sparseloc.psf import make_psf
from sparseloc.solvers import Emitters, hybrid_solve
from sparseloc.solvers.refine import _fewer_starts, fit_emitters, fit_with_count_selection


def part_a(args) -> dict:
    rng = np.random.default_rng(args.seed)
    px, w = 100.0, args.window_a
    out = {}
    print(
        f"\n(a) isolated emitters, {w}x{w} px of {px:.0f} nm, {args.planes} z planes x "
        f"{args.reps} repeats per cell; ratios are RMSE / sqrt(CRLB)"
    )
    hdr = (
        f"{'model':<7}{'photons':>8}{'bg':>4} | {'x':>5}{'y':>6}{'z':>6} | "
        f"{'bias x':>7}{'bias y':>7}{'bias z':>7} nm | {'within 1 sd x, y, z':>20} | "
        f"{'flagged':>7}{'ms/fit':>7}"
    )
    print(hdr)
    print("-" * len(hdr))
    for name in ("dh", "astig"):
        model = make_psf(name)
        lo, hi = model.z_range
        zs = np.linspace(lo + 0.05 * (hi - lo), hi - 0.05 * (hi - lo), args.planes)
        for photons in (1000.0, 2000.0, 5000.0):
            for bg in (5.0, 20.0):
                errs, sds, bounds, times, flagged = [], [], [], [], 0
                for z in zs:
                    bound = None
                    for _ in range(args.reps):
                        x = w * px / 2 + rng.uniform(-px / 2, px / 2)
                        y = w * px / 2 + rng.uniform(-px / 2, px / 2)
                        if bound is None:
                            bound = crlb(model, x, y, z, photons, bg, (w, w), px)[0, :3]
                        mu = model.render(x, y, z, photons, (w, w), px) + bg
                        img = rng.poisson(mu).astype(float)
                        start = Emitters.from_array(
                            [
                                [
                                    x + rng.normal(0, 30),
                                    y + rng.normal(0, 30),
                                    np.clip(z + rng.normal(0, 50), lo, hi),
                                    photons * rng.uniform(0.8, 1.2),
                                ]
                            ]
                        )
                        t0 = time.perf_counter()
                        fit = fit_emitters(img, model, start, pixel_size=px)
                        times.append(time.perf_counter() - t0)
                        if fit.flags[0] != "ok":
                            flagged += 1
                        errs.append(fit.emitters.as_array()[0, :3] - [x, y, z])
                        sds.append(fit.sigma[0, :3])
                        bounds.append(bound)
                e, s, b = np.array(errs), np.array(sds), np.array(bounds)
                ratio = np.sqrt(np.mean((e / b) ** 2, axis=0))
                bias = e.mean(axis=0)
                bias_se = e.std(axis=0) / np.sqrt(len(e))
                within = np.mean(np.abs(e) <= s, axis=0)
                key = f"{name}/{photons:.0f}/{bg:.0f}"
                out[key] = {
                    "rmse_over_sqrt_crlb": ratio.tolist(),
                    "bias_nm": bias.tolist(),
                    "bias_se_nm": bias_se.tolist(),
                    "within_1sd": within.tolist(),
                    "rmse_nm": np.sqrt(np.mean(e**2, axis=0)).tolist(),
                    "mean_crlb_nm": np.sqrt(np.mean(b**2, axis=0)).tolist(),
                    "n": len(e),
                    "flagged": flagged,
                    "median_ms_per_fit": 1e3 * float(np.median(times)),
                }
                print(
                    f"{name:<7}{photons:>8.0f}{bg:>4.0f} | {ratio[0]:5.2f}{ratio[1]:6.2f}"
                    f"{ratio[2]:6.2f} | {bias[0]:7.1f}{bias[1]:7.1f}{bias[2]:7.1f}    | "
                    f"{within[0]:6.2f}{within[1]:6.2f}{within[2]:6.2f}   | "
                    f"{flagged:>7d}{1e3 * np.median(times):>7.0f}"
                )
    return out


def part_b(args) -> dict:
    model = make_psf(args.psf_b)
    w, px, zr = 11, 160.0, (-300.0, 300.0)
    coarse = Dictionary(model, w, px, 80.0, 120.0, zr)
    fine = Dictionary(model, w, px, 10.0, 15.0, zr)
    rng = np.random.default_rng(args.seed)
    trials = [
        make_trial(rng, model, w, px, (800.0, 800.0, 600.0), (1000.0, 1200.0), 5.0)
        for _ in range(args.trials)
    ]
    kw = dict(pixel_size=px, origin=fine.origin)

    def mle(sol):
        return sol.emitters, sol.details["fit"].log_likelihood

    def direct(fit):
        return fit.emitters, fit.log_likelihood

    # The last two rows start from the true emitters (which no solver knows): the count
    # selection's count and error there are what its rule allows once the search is perfect;
    # the fit with the count held at 3 is the error floor of an unbiased fit.
    solvers = {
        "MP+CO": lambda y, t: (hybrid_solve(y, coarse, fine, refine=False).emitters, None),
        "MP+CO+MLE, no search": lambda y, t: mle(hybrid_solve(y, coarse, fine, search=False)),
        "MP+CO+MLE": lambda y, t: mle(hybrid_solve(y, coarse, fine)),
        "truth start + count sel.": lambda y, t: direct(
            fit_with_count_selection(y, model, Emitters.from_array(t), **kw)
        ),
        "truth start, K = 3": lambda y, t: direct(
            fit_emitters(y, model, Emitters.from_array(t), **kw)
        ),
    }
    seps = np.array([min_separation(t) for _, t in trials])
    rows: dict = {}
    # the likeliest fit of each count met in any row, per trial: the evidence for 3 over 2
    best_by_count = [dict() for _ in trials]
    for label, solve in solvers.items():
        counts, errors, times = [], [], []
        for n, (y, truth) in enumerate(tqdm(trials, desc=label, leave=False)):
            t0 = time.perf_counter()
            em, loglik = solve(y, truth)
            times.append(time.perf_counter() - t0)
            est = em.as_array()
            counts.append(len(est))
            errors.append(match_error(est, truth))
            if loglik is not None:
                best = best_by_count[n]
                best[len(est)] = max(best.get(len(est), -np.inf), loglik)
        c, e = np.array(counts), np.array(errors)
        rows[label] = {
            "right_count": float(np.mean(c == 3)),
            "count_histogram": np.bincount(c, minlength=6).tolist(),
            "mean_error_nm": float(np.nanmean(e)),
            "mean_error_right_count_nm": float(np.nanmean(e[c == 3])),
            "median_time_s": float(np.median(times)),
            "right_count_by_min_separation": {
                f"{lo:.0f}-{hi:.0f}": float(np.mean(c[sel] == 3)) if sel.any() else float("nan")
                for lo, hi in pairwise(SEPARATION_BINS)
                for sel in [(seps >= lo) & (seps < hi)]
            },
            "per_trial": {"count": c.tolist(), "error_nm": e.tolist()},
        }
    # Two-emitter models from the truth: each pair merged (photon-weighted centre, summed
    # photons) or each emitter dropped, fitted; with the rows' fits, the likeliest of each count
    ratios = []
    for (y, truth), best in zip(
        tqdm(trials, desc="two-emitter fits", leave=False), best_by_count, strict=True
    ):
        for start in _fewer_starts(truth):
            best[2] = max(
                best.get(2, -np.inf),
                fit_emitters(y, model, Emitters.from_array(start), **kw).log_likelihood,
            )
        ratios.append(2.0 * (best[3] - best[2]))
    ratios = np.array(ratios)
    res = {
        "rows": rows,
        "ratio_best3_vs_best2": ratios.tolist(),
        "min_separation_nm": seps.tolist(),
    }
    print(
        f"\n(b) paper Figure 2 case ({args.psf_b}), {args.trials} trials (3 emitters, "
        f"800x800x600 nm, 1000-1200 photons, background 5, 11x11 px of 160 nm)"
    )
    bins = [f"{lo:.0f}-{hi:.0f}" for lo, hi in pairwise(SEPARATION_BINS)]
    n_bin = [int(np.sum((seps >= lo) & (seps < hi))) for lo, hi in pairwise(SEPARATION_BINS)]
    print(
        f"{'':<26}{'right count':>12}{'mean 3D err':>13}{'err, right count':>18}"
        f"{'median time':>13}   right count by closest pair (nm): "
        + ", ".join(f"{b} (n={n})" for b, n in zip(bins, n_bin, strict=True))
    )
    for label, r in rows.items():
        by = r["right_count_by_min_separation"]
        print(
            f"{label:<26}{100 * r['right_count']:>11.1f}%{r['mean_error_nm']:>10.1f} nm"
            f"{r['mean_error_right_count_nm']:>15.1f} nm{1e3 * r['median_time_s']:>10.0f} ms   "
            + "  ".join(f"{100 * by[b]:5.1f}%" for b in bins)
        )
    print("paper (MP+CO): 34 nm")
    print(
        "likelihood ratio of the likeliest 3-emitter fit over the likeliest 2-emitter fit found "
        "(all rows' fits and 6 two-emitter fits from the truth): "
        + ", ".join(f"above {t} in {100 * np.mean(ratios > t):.1f}%" for t in (18.47, 9.49))
        + " of trials"
    )
    return res


def part_c(args) -> dict:
    model = make_psf("dh")
    w, px, zr = 13, 160.0, (-300.0, 300.0)
    coarse = Dictionary(model, w, px, 80.0, 120.0, zr)
    fine = Dictionary(model, w, px, 10.0, 15.0, zr)
    rng = np.random.default_rng(args.seed + 1)
    seps = [100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 800.0]
    res = {}
    print(
        f"\n(c) pairs, 2000 photons each, background 10, {w}x{w} px of {px:.0f} nm, "
        f"{args.pair_reps} repeats; detection = both found within 100 nm laterally"
    )
    print(
        f"{'separation':>10} | {'same z: detected':>17}{'error':>9} | "
        f"{'dz = 300 nm: detected':>22}{'error':>9}"
    )
    for sep in seps:
        row = {}
        for label, dz in (("same_z", 0.0), ("dz300", 300.0)):
            det, errs = [], []
            for _ in range(args.pair_reps):
                c = np.array([w * px / 2, w * px / 2]) + rng.uniform(-40, 40, 2)
                ang = rng.uniform(0, np.pi)
                d = np.array([np.cos(ang), np.sin(ang)]) * sep / 2
                truth = np.array([[*(c + d), dz / 2, 2000.0], [*(c - d), -dz / 2, 2000.0]])
                mu = (
                    model.render(truth[:, 0], truth[:, 1], truth[:, 2], truth[:, 3], (w, w), px)
                    + 10.0
                )
                y = rng.poisson(mu).astype(float)
                est = hybrid_solve(y, coarse, fine).emitters.as_array()
                ok = False
                if len(est) >= 2:
                    lat = np.linalg.norm(est[:, None, :2] - truth[None, :, :2], axis=2)
                    ok = bool(np.all(lat.min(axis=0) < 100.0)) and len(est) == 2
                det.append(ok)
                errs.append(match_error(est, truth))
            row[label] = {"detected": float(np.mean(det)), "mean_error_nm": float(np.nanmean(errs))}
        res[f"{sep:.0f}"] = row
        print(
            f"{sep:>8.0f} nm | {100 * row['same_z']['detected']:>15.0f}% "
            f"{row['same_z']['mean_error_nm']:>6.1f} nm | "
            f"{100 * row['dz300']['detected']:>20.0f}% {row['dz300']['mean_error_nm']:>6.1f} nm"
        )
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="a,b,c")
    ap.add_argument("--reps", type=int, default=25, help="(a) repeats per z plane")
    ap.add_argument("--planes", type=int, default=9, help="(a) z planes")
    ap.add_argument("--window-a", type=int, default=21, help="(a) window (pixels of 100 nm)")
    ap.add_argument("--trials", type=int, default=200, help="(b) trials")
    ap.add_argument("--psf-b", default="dh", help="(b) PSF model (dh, astig, ...)")
    ap.add_argument("--pair-reps", type=int, default=20, help="(c) repeats per separation")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/precision.json"))
    args = ap.parse_args(argv)
    parts = {p.strip() for p in args.parts.split(",")}
    result = {"meta": {k: str(v) for k, v in vars(args).items()}, "machine": platform.platform()}
    if "a" in parts:
        result["a_isolated"] = part_a(args)
    if "b" in parts:
        result["b_fig2"] = part_b(args)
    if "c" in parts:
        result["c_pairs"] = part_c(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
