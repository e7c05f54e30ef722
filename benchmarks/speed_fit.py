"""Speed of the maximum-likelihood fit: ``fit_emitters`` window by window against ``fit_batch``.

Windows of 21x21 pixels (100 nm) hold 1-3 double-helix emitters (spline table of the pupil
model, as the pipeline's ``tabulate``) with 1000-5000 photons on a background of 10, Poisson
noise; every fit starts from the truth moved by about 30 nm (x, y), 60 nm (z) and 10 %
(photons). The same windows are fitted by ``fit_emitters`` in a loop, by ``fit_batch`` on
NumPy, on PyTorch's CPU backend and, where available, on CUDA, all in float64 (plus one
float32-rendering run), with one thread for BLAS and torch so that the ratios compare the
code and not the cores. Agreement is measured against the loop.

Usage: ``python benchmarks/speed_fit.py [--windows 500] [--seed 0] [--out FILE]``;
``--scaling 1000,10000,100000 --device cuda`` times ``fit_batch`` alone against the batch size.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from sparseloc.psf import make_psf
from sparseloc.psf.spline import SplinePSF
from sparseloc.solvers import Emitters
from sparseloc.solvers.batch_fit import BatchFitResult, fit_batch
from sparseloc.solvers.refine import fit_emitters

log = logging.getLogger("speed_fit")

PX = 100.0  # nm
W = 21  # px
K_MAX = 3
BACKGROUND = 10.0
OUT = Path(__file__).resolve().parent / "results" / "speed_fit.json"


def make_spline() -> SplinePSF:
    """The pipeline's table of the double-helix pupil model (45 px ROI, 10 nm planes)."""
    return SplinePSF.from_model(make_psf("dh"), PX, roi=45, z_step=10.0)


def make_windows(spline: SplinePSF, n_windows: int, seed: int) -> dict[str, Any]:
    """Simulated windows, truths and starts (see the module notes)."""
    rng = np.random.default_rng(seed)
    ne = rng.integers(1, K_MAX + 1, n_windows)
    origins = np.round(rng.uniform(0, 20000, (n_windows, 2)) / PX) * PX
    truth = np.full((n_windows, K_MAX, 4), np.nan)
    starts = np.full((n_windows, K_MAX, 4), np.nan)
    windows = np.empty((n_windows, W, W))
    zlo, zhi = spline.z_range
    for b in range(n_windows):
        k = ne[b]
        t = np.column_stack(
            [
                origins[b, 0] + rng.uniform(0.3, 0.7, k) * W * PX,
                origins[b, 1] + rng.uniform(0.3, 0.7, k) * W * PX,
                rng.uniform(zlo + 150, zhi - 150, k),
                rng.uniform(1000, 5000, k),
            ]
        )
        mu = spline.render(*t.T, (W, W), PX, origin=tuple(origins[b])) + BACKGROUND
        windows[b] = rng.poisson(mu)
        truth[b, :k] = t
        move = np.column_stack(
            [rng.normal(0, 30, (k, 2)), rng.normal(0, 60, k), rng.normal(0, 0.1, k) * t[:, 3]]
        )
        starts[b, :k] = t + move
    return {"windows": windows, "starts": starts, "n_emitters": ne, "origins": origins}


def loop_fit(spline: SplinePSF, data: dict[str, Any]) -> list:
    """``fit_emitters`` on each window."""
    out = []
    for b in range(len(data["windows"])):
        k = data["n_emitters"][b]
        out.append(
            fit_emitters(
                data["windows"][b],
                spline,
                Emitters.from_array(data["starts"][b, :k]),
                pixel_size=PX,
                origin=tuple(data["origins"][b]),
                background=BACKGROUND,
            )
        )
    return out


def batch_fit(spline: SplinePSF, data: dict[str, Any], **kw) -> BatchFitResult:
    return fit_batch(
        data["windows"],
        data["starts"],
        data["n_emitters"],
        spline,
        pixel_size=PX,
        origins=data["origins"],
        background=BACKGROUND,
        **kw,
    )


def agreement(ref: BatchFitResult | list, res: BatchFitResult) -> dict[str, float]:
    """Largest and median differences of ``res`` from ``ref`` (a loop's FitResults or a
    batch result) over windows: positions (nm), photons, -log L and sigma (relative)."""
    if isinstance(ref, list):
        k = res.theta.shape[1]
        theta = np.full_like(res.theta, np.nan)
        sigma = np.full_like(res.sigma, np.nan)
        for b, r in enumerate(ref):
            theta[b, : len(r.emitters)] = r.emitters.as_array()
            sigma[b, : len(r.emitters)] = r.sigma
        ll = np.array([r.log_likelihood for r in ref])
        n_iter = np.array([r.n_iter for r in ref])
        conv = np.array([r.converged for r in ref])
        assert theta.shape[1] == k
    else:
        theta, sigma, ll = ref.theta, ref.sigma, ref.log_likelihood
        n_iter, conv = ref.n_iter, ref.converged
    real = np.isfinite(theta[..., 0])
    dpos = np.abs(res.theta[..., :3] - theta[..., :3])[real]
    dph = np.abs(res.theta[..., 3] / theta[..., 3] - 1)[real]
    dsig = np.abs(res.sigma / sigma - 1)[real]
    dll = np.abs(res.log_likelihood / ll - 1)
    return {
        "max_position_nm": float(dpos.max()),
        "median_position_nm": float(np.median(dpos)),
        "max_photons_rel": float(dph.max()),
        "max_nll_rel": float(dll.max()),
        "max_sigma_rel": float(np.nanmax(dsig)),
        "windows_over_0.5nm": int(np.sum(np.any(dpos.reshape(-1, 3) > 0.5, axis=1))),
        "same_iterations_fraction": float(np.mean(res.n_iter == n_iter)),
        "same_converged_fraction": float(np.mean(res.converged == conv)),
    }


def _as_batch(fits: list, n_windows: int) -> BatchFitResult:
    """A loop's FitResults in a BatchFitResult (only what :func:`agreement` reads)."""
    theta = np.full((n_windows, K_MAX, 4), np.nan)
    sigma = np.full((n_windows, K_MAX, 4), np.nan)
    for b, r in enumerate(fits):
        theta[b, : len(r.emitters)] = r.emitters.as_array()
        sigma[b, : len(r.emitters)] = r.sigma
    nan = np.full(n_windows, np.nan)
    return BatchFitResult(
        theta=theta,
        sigma=sigma,
        background=nan,
        background_params=nan[:, None],
        background_sigma=nan[:, None],
        log_likelihood=np.array([r.log_likelihood for r in fits]),
        deviance_per_dof=nan,
        flags=np.full((n_windows, K_MAX), "", dtype="<U16"),
        converged=np.array([r.converged for r in fits]),
        n_iter=np.array([r.n_iter for r in fits]),
        n_emitters=np.array([len(r.emitters) for r in fits]),
        model_image=np.zeros((n_windows, 0, 0)),
        device="loop",
        seconds=float("nan"),
    )


def _timed(fn):
    """Wall time of one call and its result."""
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _path_kwargs(name: str) -> dict[str, Any]:
    return {
        "batch_numpy": {},
        "batch_numpy_float32": {"precision": "float32"},
        "batch_torch_cpu": {"device": "cpu"},
        "batch_torch_cuda": {"device": "cuda"},
    }[name]


def run(
    n_windows: int = 500, seed: int = 0, spline: SplinePSF | None = None, repeats: int = 2
) -> dict[str, Any]:
    """Time and compare the fits (see the module notes).

    Parameters
    ----------
    n_windows : int
        Windows to fit.
    seed : int
        Random seed of the simulation.
    spline : SplinePSF, optional
        The table (default: :func:`make_spline`, ~10 s to build).
    repeats : int
        Interleaved timing rounds; the best time of each path is kept.

    Returns
    -------
    dict
        ``meta``, ``timings`` (seconds and fits per second per path; ratios to the loop) and
        ``agreement`` (per path, against the loop; torch also against NumPy).
    """
    from threadpoolctl import threadpool_limits

    spline = make_spline() if spline is None else spline
    data = make_windows(spline, n_windows, seed)
    n_fits = int(data["n_emitters"].sum())
    timings: dict[str, dict[str, float]] = {}
    agree: dict[str, dict[str, float]] = {}
    try:
        import torch
    except ImportError:
        torch = None
        log.warning("torch is not installed: the PyTorch paths are skipped")
    paths: dict[str, Any] = {
        "loop_fit_emitters": lambda: loop_fit(spline, data),
        "batch_numpy": lambda: batch_fit(spline, data),
        "batch_numpy_float32": lambda: batch_fit(spline, data, precision="float32"),
    }
    if getattr(spline, "compiled", False):
        # fit_emitters has a compiled (numba) path for splines: time its NumPy path too.
        def numpy_loop():
            spline.compiled = False
            try:
                return loop_fit(spline, data)
            finally:
                spline.compiled = True

        paths["loop_fit_emitters_numpy"] = numpy_loop
    if torch is not None:
        paths["batch_torch_cpu"] = lambda: batch_fit(spline, data, device="cpu")
        if torch.cuda.is_available():
            paths["batch_torch_cuda"] = lambda: batch_fit(spline, data, device="cuda")
    few = {k: v[:8] for k, v in data.items()}
    threads = torch.get_num_threads() if torch is not None else None
    out: dict[str, Any] = {}
    try:
        if torch is not None:
            torch.set_num_threads(1)
        with threadpool_limits(limits=1):
            # warm up (numba caches, tables on each device, torch kernels)
            loop_fit(spline, few)
            for name in paths:
                if name.startswith("batch"):
                    batch_fit(spline, few, **_path_kwargs(name))
            # Interleaved rounds, best of each: the machine's load drifts between paths.
            best = dict.fromkeys(paths, np.inf)
            for _ in range(repeats):
                for name, fn in paths.items():
                    sec, out[name] = _timed(fn)
                    best[name] = min(best[name], sec)
    finally:
        if torch is not None:
            torch.set_num_threads(threads)
    for name, sec in best.items():
        timings[name] = {"seconds": sec}
    loop = out["loop_fit_emitters"]
    if "loop_fit_emitters_numpy" in out:
        agree["loop_numpy_vs_loop"] = agreement(
            loop, _as_batch(out["loop_fit_emitters_numpy"], n_windows)
        )
    results = {k: v for k, v in out.items() if k.startswith("batch")}
    loop_sec = timings["loop_fit_emitters"]["seconds"]
    py_sec = timings.get("loop_fit_emitters_numpy", {}).get("seconds")
    for t in timings.values():
        t["windows_per_s"] = n_windows / t["seconds"]
        t["emitter_fits_per_s"] = n_fits / t["seconds"]
        t["speedup_vs_loop"] = loop_sec / t["seconds"]
        if py_sec is not None:
            t["speedup_vs_numpy_loop"] = py_sec / t["seconds"]
    for name, res in results.items():
        agree[name] = agreement(loop, res)
    for name in ("batch_torch_cpu", "batch_torch_cuda"):
        if name in results:
            agree[f"{name}_vs_numpy"] = agreement(results["batch_numpy"], results[name])
    agree["batch_numpy_float32_vs_float64"] = agreement(
        results["batch_numpy"], results["batch_numpy_float32"]
    )
    meta = {
        "n_windows": n_windows,
        "n_emitters": n_fits,
        "window_px": [W, W],
        "pixel_nm": PX,
        "background": BACKGROUND,
        "seed": seed,
        "spline": repr(spline),
        "threads": 1,
        "repeats": repeats,
        "machine": platform.platform(),
        "processor": platform.processor(),
        "mean_iterations_loop": float(np.mean([r.n_iter for r in loop])),
    }
    return {"meta": meta, "timings": timings, "agreement": agree}


def scaling(
    sizes: list[int],
    device: str | None,
    seed: int = 0,
    *,
    precision: str = "float64",
    chunk: int | None = None,
    spline: SplinePSF | None = None,
) -> dict:
    """Throughput of ``fit_batch`` against the number of windows fitted in one call.

    Up to 5,000 distinct windows are simulated and repeated to fill the larger batches (the
    iterations each window needs stay those of the distinct set). Each size is timed once
    after a warm-up of 8 windows; the results come back as NumPy arrays, so a GPU's work is
    complete when the clock stops.

    Returns
    -------
    dict
        ``rows``: windows, emitters, seconds, windows/s and emitters/s per size.
    """
    spline = make_spline() if spline is None else spline
    base = make_windows(spline, min(max(sizes), 5000), seed)
    batch_fit(spline, {k: v[:8] for k, v in base.items()}, device=device, precision=precision)
    rows = []
    for n in sizes:
        reps = -(-n // len(base["windows"]))
        data = {k: np.concatenate([v] * reps)[:n] for k, v in base.items()}
        sec, _ = _timed(
            lambda d=data: batch_fit(spline, d, device=device, precision=precision, chunk=chunk)
        )
        ne = int(data["n_emitters"].sum())
        rows.append(
            {
                "windows": n,
                "emitters": ne,
                "seconds": sec,
                "windows_per_s": n / sec,
                "emitters_per_s": ne / sec,
            }
        )
        print(
            f"{n:>9} windows {ne:>9} emitters {sec:9.3f} s {n / sec:>11.0f} windows/s "
            f"{ne / sec:>11.0f} emitters/s",
            flush=True,
        )
    return {
        "device": device or "numpy",
        "precision": precision,
        "chunk": chunk,
        "machine": platform.platform(),
        "rows": rows,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--windows", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument(
        "--scaling",
        default=None,
        help="comma-separated batch sizes: time fit_batch alone against the batch size",
    )
    ap.add_argument("--device", default=None, help="fit_batch's device for --scaling")
    ap.add_argument("--precision", default="float64", help="for --scaling")
    ap.add_argument("--chunk", type=int, default=None, help="for --scaling")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.scaling:
        sizes = [int(v) for v in args.scaling.split(",")]
        out = scaling(sizes, args.device, args.seed, precision=args.precision, chunk=args.chunk)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2))
        print(f"wrote {args.out}")
        return
    out = run(args.windows, args.seed)
    print_table(out)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"\nwrote {args.out}")


def print_table(out: dict) -> None:
    """The timings and agreement table of a :func:`run` result."""
    print(f"{out['meta']['n_windows']} windows, {out['meta']['n_emitters']} emitters, 1 thread")
    print(
        f"{'path':<24}{'seconds':>9}{'windows/s':>11}{'emitters/s':>12}{'vs loop':>9}"
        f"{'vs numpy loop':>15}"
    )
    for name, t in out["timings"].items():
        vs_py = t.get("speedup_vs_numpy_loop", float("nan"))
        print(
            f"{name:<24}{t['seconds']:>9.3f}{t['windows_per_s']:>11.0f}"
            f"{t['emitter_fits_per_s']:>12.0f}{t['speedup_vs_loop']:>8.2f}x{vs_py:>14.2f}x"
        )
    print(
        f"\n{'agreement':<32}{'max pos nm':>11}{'max N rel':>11}{'max nll rel':>12}"
        f"{'max sd rel':>11}{'same iter':>10}"
    )
    for name, a in out["agreement"].items():
        print(
            f"{name:<32}{a['max_position_nm']:>11.2e}{a['max_photons_rel']:>11.2e}"
            f"{a['max_nll_rel']:>12.2e}{a['max_sigma_rel']:>11.2e}"
            f"{a['same_iterations_fraction']:>10.2f}"
        )


if __name__ == "__main__":
    main()
