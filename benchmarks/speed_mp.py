"""Speed of matching pursuit over the paper's fine dictionary: dense reference vs fast MP.

The paper's fine dictionary (double-helix PSF, 11 x 11 windows of 160 nm pixels, 10 nm / 15 nm
grid over 600 nm: 1,270,016 atoms) and Figure-2 windows (three emitters of 1000-1200 photons
in 800 x 800 x 600 nm, background 5, Poisson noise; as in ``paper_fig2.py``). Timed, per
window, for the whole MP solve (every iteration up to the stopping rule):

- ``dense64``: :func:`~sparseloc.solvers.matching_pursuit` with the dense float64 matrix
  (``D^T r`` by matrix-vector product each iteration): the reference, on a subset of windows;
- ``dense32``: the same with a float32 copy of the matrix (timing only);
- ``fft``: the current default, ``matching_pursuit`` on the structured dictionary (FFT
  correlations), on a few windows;
- ``fast_batched``: :func:`~sparseloc.solvers.matching_pursuit_batch`, all windows in one call;
- ``fast_single``: the same, one window per call;
- ``fast_torch``: batched with ``device="cpu"`` (when PyTorch is installed).

Selections (atom indices in order, stop reason, iteration count) of the fast MP are compared
with the dense float64 reference on the reference subset.

Usage::

    python benchmarks/speed_mp.py [--windows 200] [--seed 0] [--ref-windows 20] [--out FILE]
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

from sparseloc.dictionary import DenseDictionary, Dictionary
from sparseloc.psf import make_psf
from sparseloc.solvers import matching_pursuit, matching_pursuit_batch
from sparseloc.solvers.fast_mp import get_search

log = logging.getLogger(__name__)

WINDOW, PIXEL = 11, 160.0
VOLUME = (800.0, 800.0, 600.0)
PHOTONS = (1000.0, 1200.0)
BACKGROUND = 5.0
OUT = Path(__file__).resolve().parent / "results" / "speed_mp.json"
TARGET_MS = 10.0  # per window, whole MP solve, median


class _Dense(DenseDictionary):
    """DenseDictionary whose ``sums`` are computed once (the property re-sums 1.2 GB per call,
    which is not part of an MP iteration), optionally with a float32 matrix."""

    def __init__(self, matrix, positions, shape, *, steps, dtype=np.float64) -> None:
        if dtype == np.float64:
            super().__init__(matrix, positions, shape, steps=steps)
        else:  # the base class insists on float64; keep a float32 matrix instead
            self.matrix = np.ascontiguousarray(matrix, dtype=dtype)
            self.atom_positions = np.asarray(positions, dtype=np.float64)
            self.shape = tuple(shape)
            self.index = None
            self.steps = steps
            self._norms = np.linalg.norm(self.matrix, axis=0).astype(np.float64)
        self._sums = self.matrix.sum(axis=0).astype(np.float64)

    @property
    def sums(self) -> np.ndarray:
        return self._sums

    def rmatvec(self, image):
        if self.matrix.dtype == np.float64:
            return super().rmatvec(image)
        img = np.asarray(image, dtype=self.matrix.dtype)
        return (img.reshape(-1) @ self.matrix).astype(np.float64)


def simulate(model, n: int, seed: int) -> np.ndarray:
    """Figure-2 windows (n, 11, 11): the simulation of ``paper_fig2.make_trial``."""
    rng = np.random.default_rng(seed)
    centre = np.array([WINDOW * PIXEL / 2, WINDOW * PIXEL / 2, 0.0])
    out = []
    for _ in range(n):
        pos = centre + rng.uniform(-0.5, 0.5, (3, 3)) * np.asarray(VOLUME)
        ph = rng.uniform(*PHOTONS, 3)
        mu = model.render(pos[:, 0], pos[:, 1], pos[:, 2], ph, (WINDOW, WINDOW), PIXEL)
        out.append(rng.poisson(mu + BACKGROUND).astype(float))
    return np.stack(out)


def _timed(fn, *args, **kwargs) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def _same(a, b) -> bool:
    return (
        np.array_equal(a.details["index"], b.details["index"])
        and a.details["stop"] == b.details["stop"]
        and a.details["n_iter"] == b.details["n_iter"]
    )


def run(
    n_windows: int = 200,
    seed: int = 0,
    *,
    ref_windows: int = 20,
    fft_windows: int = 5,
    single_windows: int = 50,
    repeats: int = 3,
    dense32: bool = True,
    torch_path: bool = True,
    torch_device: str = "cpu",
) -> dict:
    """Time dense-reference and fast MP on the paper's fine dictionary.

    Parameters
    ----------
    n_windows : int
        Figure-2 windows simulated; the batched fast MP solves all of them.
    seed : int
        Seed of the simulation.
    ref_windows : int
        Windows solved by the dense references (about 1 s each) and compared.
    fft_windows : int
        Windows solved by the current FFT ``matching_pursuit``.
    single_windows : int
        Windows solved one per call by the fast MP.
    repeats : int
        Repeats of the batched solve (its per-window time is the median over repeats).
    dense32 : bool
        Also time the float32 dense matrix (another 0.6 GB).
    torch_path : bool
        Also time the PyTorch path when PyTorch is installed.
    torch_device : str
        Its device ("cpu", "cuda").

    Returns
    -------
    dict
        ``ms_per_window``: milliseconds per window of each method, the median over windows
        (for ``fast_batched``: a batch's time over its window count, the median of
        ``repeats`` batches); ``speedup``: ratios of those; ``identical_fraction``: fast vs
        dense float64 selections (indices in order, stop reason, iteration count);
        ``setup_s``: one-off set-up times (dictionary, fast search, dense matrix), not in the
        per-window times; the numbers of windows timed, the fast search's fallback fraction,
        and whether the 10 ms target is met.
    """
    model = make_psf("dh")
    zr = (-VOLUME[2] / 2, VOLUME[2] / 2)
    fine, t_dict = _timed(Dictionary, model, WINDOW, PIXEL, 10.0, 15.0, zr)
    qe = fine.quantization_error
    search, t_search = _timed(get_search, fine)
    ys = simulate(model, n_windows, seed)
    n_ref = min(ref_windows, n_windows)
    steps = (fine.grid.dxy, fine.grid.dz)
    ms: dict[str, float | None] = {}
    counts: dict[str, int] = {}

    # fast MP, batched (warm-up once: first-call allocations) and one window per call
    matching_pursuit_batch(ys[: min(8, n_windows)], fine)
    per_win = []
    fast = None
    for _ in range(max(repeats, 1)):
        fast, dt = _timed(matching_pursuit_batch, ys, fine)
        per_win.append(dt / n_windows)
    ms["fast_batched"] = 1e3 * float(np.median(per_win))
    counts["fast_batched"] = n_windows
    n_single = min(single_windows, n_windows)
    single_t = []
    single = []
    for y in ys[:n_single]:
        sol, dt = _timed(matching_pursuit_batch, y[None], fine)
        single.append(sol[0])
        single_t.append(dt)
    ms["fast_single"] = 1e3 * float(np.median(single_t))
    counts["fast_single"] = n_single
    batch_vs_single = all(_same(a, b) for a, b in zip(single, fast, strict=False))

    ms["fast_torch"] = None
    torch_same = None
    if torch_path:
        try:
            import torch  # noqa: F401
        except ImportError:
            log.info("PyTorch is not installed: no torch timing")
        else:
            matching_pursuit_batch(ys[: min(8, n_windows)], fine, device=torch_device)
            tsol, dt = _timed(matching_pursuit_batch, ys, fine, device=torch_device)
            ms["fast_torch"] = 1e3 * dt / n_windows
            counts["fast_torch"] = n_windows
            torch_same = float(np.mean([_same(a, b) for a, b in zip(tsol, fast, strict=True)]))

    # the current default: FFT correlations with every atom
    n_fft = min(fft_windows, n_windows)
    fft_t = [_timed(matching_pursuit, y, fine)[1] for y in ys[:n_fft]]
    ms["fft"] = 1e3 * float(np.median(fft_t)) if fft_t else None
    counts["fft"] = n_fft

    # the dense float64 reference (and its selections)
    t0 = time.perf_counter()
    dense = _Dense(fine.dense(), fine.positions(np.arange(fine.size)), fine.shape, steps=steps)
    t_dense = time.perf_counter() - t0
    ref = []
    ref_t = []
    for y in ys[:n_ref]:
        sol, dt = _timed(matching_pursuit, y, dense, model_error=qe)
        ref.append(sol)
        ref_t.append(dt)
    ms["dense64"] = 1e3 * float(np.median(ref_t)) if ref_t else None
    counts["dense64"] = n_ref
    same = [_same(a, b) for a, b in zip(fast[:n_ref], ref, strict=True)]

    ms["dense32"] = None
    same32 = []
    if dense32 and n_ref:
        d32 = _Dense(dense.matrix, dense.atom_positions, fine.shape, steps=steps, dtype=np.float32)
        del dense
        t32 = []
        for y, r in zip(ys[:n_ref], ref, strict=True):
            sol, dt = _timed(matching_pursuit, y, d32, model_error=qe)
            t32.append(dt)
            same32.append(_same(sol, r))
        ms["dense32"] = 1e3 * float(np.median(t32))
        counts["dense32"] = n_ref
        del d32

    def ratio(a: str, b: str) -> float | None:
        return ms[a] / ms[b] if ms.get(a) and ms.get(b) else None

    stops: dict[str, int] = {}
    for f in fast:
        stops[f.details["stop"]] = stops.get(f.details["stop"], 0) + 1
    return {
        "dictionary_atoms": fine.size,
        "windows": n_windows,
        "seed": seed,
        "ms_per_window": ms,
        "windows_timed": counts,
        "speedup": {
            "dense64_over_fast_batched": ratio("dense64", "fast_batched"),
            "dense64_over_fast_single": ratio("dense64", "fast_single"),
            "dense32_over_fast_batched": ratio("dense32", "fast_batched"),
            "fft_over_fast_batched": ratio("fft", "fast_batched"),
            "fft_over_fast_single": ratio("fft", "fast_single"),
        },
        "identical_fraction": float(np.mean(same)) if same else None,
        "identical_windows": n_ref,
        "dense32_identical_fraction": float(np.mean(same32)) if same32 else None,
        "batched_equals_single": batch_vs_single,
        "torch_equals_numpy_fraction": torch_same,
        "torch_device": torch_device,
        "target_ms": TARGET_MS,
        "meets_target": bool(ms["fast_batched"] <= TARGET_MS),
        "mean_iterations": float(np.mean([f.details["n_iter"] for f in fast])),
        "stops": stops,
        "fallback_fraction": search.fallback_fraction,
        "setup_s": {"dictionary": t_dict, "search": t_search, "dense_matrix": t_dense},
        "search_memory_mb": search.memory() / 1e6,
        "machine": platform.platform(),
        "processor": platform.processor(),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ref-windows", type=int, default=20)
    ap.add_argument("--no-dense32", action="store_true")
    ap.add_argument("--torch-device", default="cpu", help="device of the PyTorch path")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    res = run(
        args.windows,
        args.seed,
        ref_windows=args.ref_windows,
        dense32=not args.no_dense32,
        torch_device=args.torch_device,
    )
    print_table(res)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print(f"\nwrote {args.out}")
    return 0


def print_table(res: dict) -> None:
    """The table of a :func:`run` result."""
    ms = res["ms_per_window"]
    n = res["windows_timed"]
    print(
        f"\nMP on the fine dictionary ({res['dictionary_atoms']:,} atoms), Figure-2 windows; "
        f"set-up: dictionary {res['setup_s']['dictionary']:.1f} s, fast search "
        f"{res['setup_s']['search']:.1f} s ({res['search_memory_mb']:.0f} MB)\n"
    )
    print(f"{'method':<28}{'windows':>8}{'ms / window':>13}{'x fast batched':>16}")
    labels = {
        "dense64": "dense float64 D^T r (ref.)",
        "dense32": "dense float32 D^T r",
        "fft": "FFT (current default)",
        "fast_single": "fast, one window per call",
        "fast_batched": "fast, batched",
        "fast_torch": f"fast, batched, torch {res.get('torch_device', 'cpu')}",
    }
    for key, label in labels.items():
        if ms.get(key) is None:
            continue
        print(f"{label:<28}{n[key]:>8}{ms[key]:>13.2f}{ms[key] / ms['fast_batched']:>16.1f}")
    print(
        f"\nidentical selections (fast vs dense float64): "
        f"{100 * res['identical_fraction']:.1f} % of {res['identical_windows']} windows"
        + (
            f"; dense float32 vs float64: {100 * res['dense32_identical_fraction']:.1f} %"
            if res["dense32_identical_fraction"] is not None
            else ""
        )
    )
    if res["torch_equals_numpy_fraction"] is not None:
        print(f"torch path selections = NumPy's: {100 * res['torch_equals_numpy_fraction']:.1f} %")
    print(
        f"target {res['target_ms']:.0f} ms per window (batched): "
        f"{'met' if res['meets_target'] else 'NOT met'}"
    )
    print(
        f"mean MP iterations {res['mean_iterations']:.2f}; stops {res['stops']}; "
        f"fallback searches {100 * res['fallback_fraction']:.1f} %"
    )


if __name__ == "__main__":
    raise SystemExit(main())
