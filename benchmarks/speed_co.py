"""Speed of the convex stage (CO) against CVXPY, and of the hybrid MP+CO per window.

Windows as in the paper's Figure 2 (``benchmarks/paper_fig2.py``): the double-helix pupil model,
11 x 11 windows of 160 nm pixels, three emitters at random in 800 x 800 x 600 nm around the
window centre, 1000-1200 photons each, background 5 photons/pixel, Poisson noise.

CO: the problem :func:`~sparseloc.solvers.hybrid.convex_solve` solves on the coarse dictionary
(80 nm / 120 nm, 2904 atoms): ``min sum(x)  s.t.  ||y - A x - b||_2 <= eps, x >= 0, b >= 0``
with the background ``b`` estimated and ``eps = noise_epsilon(y)`` (``sqrt(sum(max(y, 1)))``).
sparseloc's :func:`~sparseloc.solvers.convex.solve_constrained` against the same problem stated
in CVXPY with each solver in ``CVX_SOLVERS`` (CLARABEL, interior point, at its default
tolerances; SCS, first order, at 1e-5, the loosest setting that keeps the objective within
1e-4). Timings, per window, medians over the windows:

- ``ours``: ``solve_constrained`` (input checks included), timed window by window between the
  CVXPY solves of the same window (so under the same load; CVXPY's solves evict the dictionary
  from the caches, which makes this slower than ``ours_ms_back_to_back``, the same solves one
  after the other);
- ``solve``: CVXPY's ``Problem.solve`` on a problem built once with ``y`` and ``eps`` as
  parameters (the canonicalisation is cached; what is left is CVXPY's parameter update, the
  solver's set-up and its solve);
- ``solver``: the solver's own time (``solver_stats.solve_time``);
- ``build``: building and canonicalising a fresh problem (what a script that states the problem
  anew for each window pays on top of ``solve``).

The ratio of the acceptance ("CO: at least 100x faster than CVXPY at objective gap <= 1e-4") is
``solve / ours`` for the fastest CVXPY solver whose gap stays within 1e-4; the ratios against the
solver-only time and against build + solve are reported beside it. Gap: ``|f_ours - f_cvx| /
|f_cvx|`` with ``f = sum(x)``.

Hybrid: :func:`~sparseloc.solvers.hybrid.hybrid_solve` with its defaults (MP on the coarse
dictionary, CO on the fine one, 10 nm / 15 nm, restricted to boxes, point-source polish and the
maximum-likelihood refinement with count selection), per window, with the time spent in each
stage.

BLAS runs on one thread throughout (``threadpoolctl``), as in ``sparseloc.pipeline``: on a
shared two-core machine a multi-threaded BLAS makes these small products many times slower.

Usage::

    python benchmarks/speed_co.py [--windows 30] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

import sparseloc.solvers.hybrid as hybrid_mod
from sparseloc.dictionary import Dictionary
from sparseloc.psf import make_psf
from sparseloc.solvers.convex import noise_epsilon, solve_constrained
from sparseloc.solvers.hybrid import convex_solve, hybrid_solve

OUT = Path(__file__).resolve().parent / "results" / "speed_co.json"
PSF = "dh"
WINDOW = 11
PIXEL = 160.0
VOLUME = (800.0, 800.0, 600.0)
PHOTONS = (1000.0, 1200.0)
BACKGROUND = 5.0
COARSE_STEPS = (80.0, 120.0)
FINE_STEPS = (10.0, 15.0)
#: CVXPY solvers and their options (SCS: the loosest accuracy whose gap stays within 1e-4).
CVX_SOLVERS: dict[str, dict[str, Any]] = {
    "CLARABEL": {},
    "SCS": {"eps_abs": 1e-5, "eps_rel": 1e-5, "max_iters": 200_000},
}
#: Acceptance: ours at least this many times faster, at most this relative objective gap.
TARGET_RATIO = 100.0
TARGET_GAP = 1e-4
#: Fresh-problem build times are measured on this many windows (they barely vary).
N_BUILD = 3


def simulate_window(rng: np.random.Generator, model) -> tuple[np.ndarray, np.ndarray]:
    """One paper-Figure-2 window: the noisy image and the truth (3, 4) of x, y, z, photons."""
    centre = np.array([WINDOW * PIXEL / 2, WINDOW * PIXEL / 2, 0.0])
    pos = centre + rng.uniform(-0.5, 0.5, (3, 3)) * np.asarray(VOLUME)
    ph = rng.uniform(*PHOTONS, 3)
    mu = model.render(pos[:, 0], pos[:, 1], pos[:, 2], ph, (WINDOW, WINDOW), PIXEL) + BACKGROUND
    return rng.poisson(mu).astype(float), np.column_stack([pos, ph])


def _cvx_problem(A: np.ndarray):
    """``min sum(x) s.t. ||y - A x - b|| <= eps, x, b >= 0`` with ``y``, ``eps`` parameters."""
    import cvxpy as cp

    m, n = A.shape
    x = cp.Variable(n, nonneg=True)
    b = cp.Variable(nonneg=True)
    y = cp.Parameter(m)
    eps = cp.Parameter(nonneg=True)
    prob = cp.Problem(cp.Minimize(cp.sum(x)), [cp.norm(y - A @ x - b, 2) <= eps])
    return prob, y, eps


def _cvx_build_time(A: np.ndarray, y: np.ndarray, eps: float, solver: str) -> float:
    """Seconds to state and canonicalise a fresh problem for one window (no parameters)."""
    import cvxpy as cp

    t0 = time.perf_counter()
    x = cp.Variable(A.shape[1], nonneg=True)
    b = cp.Variable(nonneg=True)
    prob = cp.Problem(cp.Minimize(cp.sum(x)), [cp.norm(y - A @ x - b, 2) <= eps])
    prob.get_problem_data(solver)
    return time.perf_counter() - t0


@contextlib.contextmanager
def _stage_timer(fine: Dictionary) -> Iterator[tuple[dict[str, float], dict[str, int]]]:
    """Seconds in, and calls of, the hybrid's stages: wraps the functions ``hybrid_solve`` looks
    up in its module (restored on exit) and the fine dictionary's ``restrict``."""
    totals = {"mp": 0.0, "fine_restrict": 0.0, "co": 0.0, "polish": 0.0, "refine": 0.0}
    calls = {key: 0 for key in totals}

    def wrap(fn: Callable, key: str) -> Callable:
        def timed(*args, **kwargs):
            calls[key] += 1
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[key] += time.perf_counter() - t0

        return timed

    names = {
        "matching_pursuit": "mp",
        "solve_constrained": "co",
        "polish": "polish",
        "refine_solution": "refine",
    }
    saved = {name: getattr(hybrid_mod, name) for name in names}
    for name, key in names.items():
        setattr(hybrid_mod, name, wrap(saved[name], key))
    fine.restrict = wrap(fine.restrict, "fine_restrict")  # instance attribute, removed below
    try:
        yield totals, calls
    finally:
        for name, fn in saved.items():
            setattr(hybrid_mod, name, fn)
        del fine.restrict


def _median_ms(values: list[float]) -> float:
    return float(1e3 * np.median(values)) if values else float("nan")


def run(n_windows: int = 30, seed: int = 0) -> dict:
    """Time CO (sparseloc vs CVXPY) and the hybrid per window on paper-Figure-2 windows.

    Parameters
    ----------
    n_windows : int
        Windows simulated (each solved once by every method).
    seed : int
        Seed of the simulation.

    Returns
    -------
    dict
        ``meta``; ``co``: ``ours_ms`` (median per window; ``ours_ms_back_to_back`` the same
        solves one after the other), ``convex_solve_ms`` (the whole CO method on a window: the
        coarse dictionary made dense, the solve, grouping, pruning), per CVXPY solver ``solve_ms``,
        ``solver_ms``, ``build_ms``, the ratios ``ratio_solve``, ``ratio_solver_only``,
        ``ratio_build_and_solve``, ``gap_median``, ``gap_max``, ``statuses``; ``best_solver``,
        ``ratio``, ``gap_max``, ``meets_target``; ``hybrid``: ``ms`` (median per window),
        ``stage_ms`` (median per window of each stage), ``co_calls_per_window``,
        ``co_ms_per_solve`` (mean time of one fine-box CO solve), ``counts`` (emitters found).
    """
    import cvxpy as cp

    if n_windows < 1:
        raise ValueError(f"n_windows must be >= 1, got {n_windows}")
    with threadpool_limits(limits=1):
        model = make_psf(PSF)
        zr = (-VOLUME[2] / 2, VOLUME[2] / 2)
        coarse = Dictionary(model, WINDOW, PIXEL, *COARSE_STEPS, zr)
        fine = Dictionary(model, WINDOW, PIXEL, *FINE_STEPS, zr)
        _ = coarse.quantization_error, fine.quantization_error  # cached, outside the timing
        A = coarse.dense()
        rng = np.random.default_rng(seed)
        windows = [simulate_window(rng, model) for _ in range(n_windows)]

        # -- CO on the coarse dictionary: sparseloc vs CVXPY ---------------------------------
        problems = {name: _cvx_problem(A) for name in CVX_SOLVERS}
        y0 = windows[0][0].ravel()
        solve_constrained(A, y0, noise_epsilon(y0))  # warm-up (imports, first calls)
        for name, (prob, yp, ep) in problems.items():  # compile once, outside the timing
            yp.value, ep.value = y0, noise_epsilon(y0)
            prob.solve(solver=name, **CVX_SOLVERS[name])
        ours_t: list[float] = []
        ours_resid: list[float] = []
        co_window_t: list[float] = []
        cvx: dict[str, dict[str, list]] = {
            name: {"solve": [], "solver": [], "build": [], "gap": [], "status": []}
            for name in CVX_SOLVERS
        }
        for i, (img, _truth) in enumerate(windows):
            y = img.ravel()
            eps = noise_epsilon(y)
            t0 = time.perf_counter()
            res = solve_constrained(A, y, eps)
            ours_t.append(time.perf_counter() - t0)
            ours_resid.append((res.residual_norm - eps) / eps)
            t0 = time.perf_counter()
            convex_solve(img, coarse)
            co_window_t.append(time.perf_counter() - t0)
            for name, (prob, yp, ep) in problems.items():
                yp.value, ep.value = y, eps
                t0 = time.perf_counter()
                prob.solve(solver=name, **CVX_SOLVERS[name])
                rec = cvx[name]
                rec["solve"].append(time.perf_counter() - t0)
                rec["solver"].append(prob.solver_stats.solve_time or float("nan"))
                rec["status"].append(prob.status)
                f = float(prob.value)
                rec["gap"].append(abs(res.objective - f) / abs(f) if f else float("nan"))
                if i < N_BUILD:
                    rec["build"].append(_cvx_build_time(A, y, eps, name))
        ours_ms = _median_ms(ours_t)
        # the same solves back to back (caches warm, as when a run solves window after window)
        b2b = []
        for img, _truth in windows:
            y = img.ravel()
            eps = noise_epsilon(y)
            t0 = time.perf_counter()
            solve_constrained(A, y, eps)
            b2b.append(time.perf_counter() - t0)
        co: dict[str, Any] = {
            "ours_ms": ours_ms,
            "ours_ms_back_to_back": _median_ms(b2b),
            "ours_ms_windows": [1e3 * t for t in ours_t],
            "ours_max_rel_residual_minus_eps": float(np.max(ours_resid)),
            "convex_solve_ms": _median_ms(co_window_t),
            "cvxpy": {},
        }
        for name, rec in cvx.items():
            solve_ms, solver_ms, build_ms = (
                _median_ms(rec[k]) for k in ("solve", "solver", "build")
            )
            gaps = np.asarray(rec["gap"], dtype=float)
            co["cvxpy"][name] = {
                "options": CVX_SOLVERS[name],
                "solve_ms": solve_ms,
                "solver_ms": solver_ms,
                "build_ms": build_ms,
                "ratio_solve": solve_ms / ours_ms,
                "ratio_solver_only": solver_ms / ours_ms,
                "ratio_build_and_solve": (build_ms + solve_ms) / ours_ms,
                "gap_median": float(np.nanmedian(gaps)),
                "gap_max": float(np.nanmax(gaps)),
                "statuses": {s: rec["status"].count(s) for s in sorted(set(rec["status"]))},
                "solve_ms_windows": [1e3 * t for t in rec["solve"]],
                "gap_windows": gaps.tolist(),
            }
        ok = {k: v for k, v in co["cvxpy"].items() if v["gap_max"] <= TARGET_GAP}
        pool = ok or co["cvxpy"]
        best = min(pool, key=lambda k: pool[k]["solve_ms"])
        co["best_solver"] = best
        co["ratio"] = co["cvxpy"][best]["ratio_solve"]
        co["gap_max"] = max(v["gap_max"] for v in co["cvxpy"].values())
        co["meets_target"] = bool(ok) and co["ratio"] >= TARGET_RATIO

        # -- the hybrid MP+CO with refinement ------------------------------------------------
        hybrid_solve(windows[0][0], coarse, fine)  # warm-up
        hyb_t: list[float] = []
        stages: dict[str, list[float]] = {}
        counts: list[int] = []
        co_calls = 0
        for img, _truth in windows:
            with _stage_timer(fine) as (totals, calls):
                t0 = time.perf_counter()
                sol = hybrid_solve(img, coarse, fine)
                hyb_t.append(time.perf_counter() - t0)
            co_calls += calls["co"]
            for key, v in totals.items():
                stages.setdefault(key, []).append(v)
            counts.append(len(sol.emitters))
        hybrid = {
            "ms": _median_ms(hyb_t),
            "ms_windows": [1e3 * t for t in hyb_t],
            "stage_ms": {k: _median_ms(v) for k, v in stages.items()},
            "co_calls_per_window": co_calls / n_windows,
            "co_ms_per_solve": 1e3 * float(np.sum(stages["co"])) / max(co_calls, 1),
            "counts": {str(k): counts.count(k) for k in sorted(set(counts))},
        }
    meta = {
        "psf": PSF,
        "window_px": WINDOW,
        "pixel_nm": PIXEL,
        "volume_nm": list(VOLUME),
        "photons": list(PHOTONS),
        "background": BACKGROUND,
        "n_windows": n_windows,
        "seed": seed,
        "coarse_atoms": coarse.size,
        "fine_atoms": fine.size,
        "blas_threads": 1,
        "cvxpy": cp.__version__,
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "target": {"ratio": TARGET_RATIO, "gap": TARGET_GAP},
    }
    return {"meta": meta, "co": co, "hybrid": hybrid}


def print_table(result: dict) -> None:
    """Print the result of :func:`run` as a table."""
    co, hyb, meta = result["co"], result["hybrid"], result["meta"]
    print(
        f"\nCO on the coarse dictionary ({meta['coarse_atoms']} atoms), {meta['n_windows']} "
        f"windows, BLAS threads {meta['blas_threads']}, median ms per window"
    )
    hdr = (
        f"{'solver':<10}{'ours':>9}{'CVXPY solve':>13}{'solver only':>13}{'build':>9}"
        f"{'ratio':>9}{'ratio(solver)':>15}{'ratio(build+solve)':>20}{'gap median':>12}"
        f"{'gap max':>10}"
    )
    print(hdr)
    print("-" * len(hdr))
    for name, c in co["cvxpy"].items():
        print(
            f"{name:<10}{co['ours_ms']:>9.2f}{c['solve_ms']:>13.1f}{c['solver_ms']:>13.1f}"
            f"{c['build_ms']:>9.1f}{c['ratio_solve']:>8.0f}x{c['ratio_solver_only']:>14.0f}x"
            f"{c['ratio_build_and_solve']:>19.0f}x{c['gap_median']:>12.1e}{c['gap_max']:>10.1e}"
        )
    print(
        f"acceptance (>= {meta['target']['ratio']:.0f}x at gap <= {meta['target']['gap']:g}): "
        f"{co['ratio']:.0f}x against {co['best_solver']}, gap max {co['gap_max']:.1e} -> "
        f"{'met' if co['meets_target'] else 'NOT met'}"
    )
    print(
        f"ours back to back (warm caches): {co['ours_ms_back_to_back']:.2f} ms per window; "
        f"convex_solve(window, coarse) end to end: {co['convex_solve_ms']:.1f} ms per window"
    )
    print(
        f"\nhybrid_solve (MP coarse + CO fine + ML refinement): {hyb['ms']:.0f} ms per window "
        f"(median); {hyb['co_calls_per_window']:.1f} CO solves per window on the fine boxes, "
        f"{hyb['co_ms_per_solve']:.1f} ms each; stages (median ms per window):"
    )
    print("  " + ", ".join(f"{k} {v:.0f}" for k, v in hyb["stage_ms"].items()))
    print(f"  emitters found: {hyb['counts']}")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table and write ``benchmarks/results/speed_co.json``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    result = run(args.windows, args.seed)
    print_table(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
