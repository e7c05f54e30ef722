"""Where the frame solver's time goes: wall time per phase on simulated frames.

Localizes ``--frames`` simulated 128 x 128 double-helix frames (pupil model tabulated as the
pipeline does, 100 nm pixels, 1000-5000 photons, background 10) at ``--density`` emitters
per um^2 in one process, with timers around the solver's parts, and prints one table:

- pursuit: the frame pursuit that gives the fits their start;
- detection: the two-tier solver's candidate detections (the default ``auto`` schedule's
  frames solved in tiers);
- L1 deconvolution: the whole-frame solver's second start's deconvolution of crowded crops
  (the fits from its peaks count as fits);
- maximum-likelihood fits: every ``fit_emitters`` call (groups, count-selection trials,
  z flips, relocations), and within it the compiled Levenberg-Marquardt loop;
- candidate search: the FFT correlations of residual windows with the PSF planes (count
  selection's additions and the relocation trials);
- neighbour light: the other emitters' images summed into each window;
- linear response: the skip test of settled groups;
- rest: everything else (grouping, bookkeeping, background, the table).

The timers count a phase only at its outermost call, so the rows add up to the total. Below
the table it prints what bounds the fits' cost: the compiled loop's Levenberg-Marquardt
iterations per fit, time per iteration and per emitter-iteration, the windows' size and
emitter count, and the count selection's addition attempts (how many pass, and the
likelihood ratios of those that do not). Use it to see what a change should target;
compare versions with ``speed_before_after.py`` (timings on shared machines drift:
alternate runs)::

    python benchmarks/phases.py --frames 3 --density 1
    python benchmarks/phases.py --frames 20 --density 0.05
"""

from __future__ import annotations

import argparse
import collections
import json
import platform
import time
from pathlib import Path

import numpy as np

import sparseloc
import sparseloc.pipeline as pipeline_mod
import sparseloc.solvers.frame as frame_mod
import sparseloc.solvers.frame_mp as pursuit_mod
import sparseloc.solvers.frame_windows as windows_mod
import sparseloc.solvers.refine as refine_mod
import sparseloc.solvers.relocate as relocate_mod
import sparseloc.solvers.two_tier as two_tier_mod
from sparseloc.pipeline import localize
from speed_before_after import benchmark_frames  # this folder is on the path

PHASES = (
    "pursuit",
    "detection",
    "L1 deconvolution",
    "maximum-likelihood fits",
    "candidate search",
    "neighbour light",
    "linear response",
)


def outermost_timers(acc: collections.Counter, calls: collections.Counter | None = None):
    """``(wrap, saved)``: ``wrap(owner, name, label)`` replaces ``owner.name`` by a timer that
    adds its seconds to ``acc[label]`` (and one to ``calls[label]``) at the outermost timed
    call only, so the labels' times add up; ``saved`` lists what to restore."""
    depth = [0]
    saved: list = []

    def wrap(owner, name: str, label: str) -> None:
        f = getattr(owner, name)
        saved.append((owner, name, f))

        def timed(*a, **k):
            if depth[0]:
                return f(*a, **k)
            depth[0] += 1
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                acc[label] += time.perf_counter() - t
                if calls is not None:
                    calls[label] += 1
                depth[0] -= 1

        setattr(owner, name, timed)

    return wrap, saved


def _install_timers(acc: collections.Counter, inner: collections.Counter, fits: list) -> list:
    """Wrap the solver's functions with timers; returns what to restore."""
    wrap, saved = outermost_timers(acc)

    wrap(pursuit_mod, "frame_pursuit", "pursuit")
    wrap(two_tier_mod, "detect_candidates", "detection")
    wrap(pipeline_mod, "tiled_l1_starts", "L1 deconvolution")
    for owner in (refine_mod, frame_mod, relocate_mod, two_tier_mod):
        wrap(owner, "fit_emitters", "maximum-likelihood fits")
    for owner in (refine_mod, relocate_mod):
        wrap(owner, "residual_candidates", "candidate search")
    wrap(windows_mod.NeighbourLight, "window", "neighbour light")
    wrap(relocate_mod, "light_pieces", "neighbour light")
    wrap(relocate_mod, "sum_pieces", "neighbour light")
    wrap(frame_mod, "_response", "linear response")

    # the compiled loop runs inside fit_emitters: timed on its own, not exclusively
    try:
        from sparseloc.solvers import _fit_numba
    except ImportError:  # numba missing: the NumPy loop, no separate row
        return saved
    loop = _fit_numba.lm_fit
    saved.append((_fit_numba, "lm_fit", loop))

    def timed_loop(*a):
        t = time.perf_counter()
        out = loop(*a)
        dt = time.perf_counter() - t
        inner["compiled loop"] += dt
        inner["compiled fits"] += 1
        # lm_fit(coef, geo, y, v, keep, base, bg_basis, weight, theta0, k, ...) -> (..., n_iter)
        fits.append((int(out[5]), int(a[2].size), int(a[9]), dt))
        return out

    _fit_numba.lm_fit = timed_loop
    return saved


def _install_addition_log(additions: list) -> list:
    """Record every addition attempt of the count selection: (likelihood ratio, passed)."""
    passes = refine_mod._addition_passes

    def logged(more, ratio, threshold, min_photons):
        ok = passes(more, ratio, threshold, min_photons)
        additions.append((float(ratio), bool(ok), float(threshold)))
        return ok

    refine_mod._addition_passes = logged
    return [(refine_mod, "_addition_passes", passes)]


def fit_statistics(fits: list, additions: list, n_locs: int) -> dict:
    """What bounds the fits' cost: iterations, window sizes, the addition attempts."""
    out: dict = {}
    if fits:
        it, npix, k, dt = (np.array(v, dtype=np.float64) for v in zip(*fits, strict=True))
        out |= {
            "fits": len(fits),
            "fits_per_localization": len(fits) / max(n_locs, 1),
            "iterations_mean": float(it.mean()),
            "iterations_median": float(np.median(it)),
            "iterations_p90": float(np.percentile(it, 90)),
            "us_per_iteration": 1e6 * float(dt.sum() / it.sum()),
            # a fit of no emitter (background only) counts as one emitter, in both figures
            "us_per_emitter_iteration": 1e6 * float(dt.sum() / (it * np.maximum(k, 1)).sum()),
            "emitter_iterations_per_localization": float(
                (it * np.maximum(k, 1)).sum() / max(n_locs, 1)
            ),
            "window_pixels_mean": float(npix.mean()),
            "emitters_per_fit_mean": float(k.mean()),
        }
    if additions:
        ratio, ok, thr = (np.array(v, dtype=np.float64) for v in zip(*additions, strict=True))
        rej = ok == 0
        out |= {
            "addition_attempts": len(additions),
            "addition_passed": int(ok.sum()),
            "addition_threshold": float(thr[0]),
            "rejected_ratio_quartiles": np.percentile(ratio[rej], [25, 50, 75]).tolist()
            if rej.any()
            else [],
        }
    return out


def _print_statistics(st: dict) -> None:
    if "fits" in st:
        print(
            f"compiled fits: {st['fits']} ({st['fits_per_localization']:.1f} per localization), "
            f"Levenberg-Marquardt iterations per fit mean {st['iterations_mean']:.1f}, "
            f"median {st['iterations_median']:.0f}, 90th percentile {st['iterations_p90']:.0f}"
        )
        print(
            f"  {st['us_per_iteration']:.0f} us per iteration on windows of "
            f"{st['window_pixels_mean']:.0f} px with {st['emitters_per_fit_mean']:.1f} emitters "
            f"(mean): {st['us_per_emitter_iteration']:.0f} us per emitter and iteration, "
            f"{st['emitter_iterations_per_localization']:.0f} emitter-iterations per localization"
        )
    if "addition_attempts" in st:
        q = st["rejected_ratio_quartiles"]
        print(
            f"count selection: {st['addition_attempts']} addition attempts (up to two trial "
            f"fits each), {st['addition_passed']} passed the ratio {st['addition_threshold']:g}"
            + (f"; the others' ratios: quartiles {q[0]:.0f} / {q[1]:.0f} / {q[2]:.0f}" if q else "")
        )


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--density", type=float, default=1.0, help="emitters per um^2")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/phases.json"))
    args = ap.parse_args(argv)

    # the kernels are compiled or loaded there, outside the timings
    frames, work, params, _ = benchmark_frames(args.frames, args.density, args.seed)

    acc: collections.Counter = collections.Counter()
    inner: collections.Counter = collections.Counter()
    fits: list = []
    additions: list = []
    saved = _install_timers(acc, inner, fits) + _install_addition_log(additions)
    try:
        t0 = time.perf_counter()
        res = localize(frames, work, params)
        total = time.perf_counter() - t0
    finally:
        for owner, name, f in reversed(saved):
            setattr(owner, name, f)

    rows = {name: acc[name] for name in PHASES}
    rows["rest"] = total - sum(rows.values())
    print(
        f"{args.frames} frames of 128x128 px at {args.density:g} emitters/um^2 (seed {args.seed}), "
        f"one process: {len(res.table)} localizations in {total:.2f} s "
        f"({len(res.table) / total:.1f}/s)"
    )
    print(f"{'phase':26s} {'seconds':>8s} {'share':>7s}")
    print("-" * 43)
    for name, sec in rows.items():
        print(f"{name:26s} {sec:8.2f} {100 * sec / total:6.1f}%")
        if name == "maximum-likelihood fits" and inner["compiled fits"]:
            print(
                f"{'  of which compiled loop':26s} {inner['compiled loop']:8.2f} "
                f"{100 * inner['compiled loop'] / total:6.1f}%   "
                f"({inner['compiled fits']} fits, "
                f"{1e3 * inner['compiled loop'] / inner['compiled fits']:.2f} ms each in the loop, "
                f"{1e3 * (sec - inner['compiled loop']) / inner['compiled fits']:.2f} ms around it)"
            )
    stats = fit_statistics(fits, additions, len(res.table))
    _print_statistics(stats)
    out = {
        "frames": args.frames,
        "density": args.density,
        "seed": args.seed,
        "seconds": total,
        "localizations": len(res.table),
        "phases_s": rows,
        "compiled_loop_s": inner["compiled loop"],
        "compiled_fits": inner["compiled fits"],
        "fit_statistics": stats,
        "version": sparseloc.__version__,
        "machine": platform.platform(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(out, indent=2))
    tmp.replace(args.out)
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
