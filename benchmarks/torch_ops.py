"""PyTorch operations per batched fit: a proxy, measurable on any CPU, for the kernel launches
that bound ``fit_batch`` (and the batched frame solver) on a GPU at small batch sizes.

Runs one ``fit_batch`` call on PyTorch's CPU backend over the windows of
``speed_fit.make_windows`` and counts the ATen operations it dispatches, split into views
(no kernel) and the rest (about one kernel launch each on CUDA), with the number of renders.
Prints a table of the most frequent operations and writes JSON.

    python benchmarks/torch_ops.py [--windows 200] [--out benchmarks/results/torch_ops.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: Operations that only make views (no kernel on a GPU).
VIEWS = (
    "unsqueeze", "slice", "select", "view", "expand", "_unsafe_view", "lift_fresh", "alias",
    "as_strided", "squeeze", "aten.t.", "transpose", "permute", "detach",
)  # fmt: skip


def count(n_windows: int, seed: int = 0) -> dict:
    import torch  # noqa: F401  (the counter needs PyTorch)
    from torch.utils._python_dispatch import TorchDispatchMode

    from sparseloc.solvers import batch_fit as bf
    from speed_fit import batch_fit, make_spline, make_windows

    class Counter(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ops: dict[str, int] = {}

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops[str(func)] = self.ops.get(str(func), 0) + 1
            return func(*args, **(kwargs or {}))

    spline = make_spline()
    data = make_windows(spline, n_windows, seed)
    batch_fit(spline, {k: v[:8] for k, v in data.items()}, device="cpu")  # tables, warm-up
    renders = [0]
    render = bf._render

    def counted(*a, **k):
        renders[0] += 1
        return render(*a, **k)

    bf._render = counted
    try:
        with Counter() as c:
            res = batch_fit(spline, data, device="cpu")
    finally:
        bf._render = render
    views = sum(v for k, v in c.ops.items() if any(w in k for w in VIEWS))
    total = sum(c.ops.values())
    return {
        "windows": n_windows,
        "renders": renders[0],
        "mean_iterations": float(res.n_iter.mean()),
        "ops": total,
        "view_ops": views,
        "kernel_ops": total - views,
        "by_name": dict(sorted(c.ops.items(), key=lambda kv: -kv[1])),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--windows", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/torch_ops.json"))
    args = ap.parse_args(argv)
    out = count(args.windows)
    print(
        f"fit_batch of {out['windows']} windows on PyTorch (CPU): {out['ops']} ATen operations, "
        f"{out['kernel_ops']} not views (about one GPU kernel each), {out['renders']} renders, "
        f"mean {out['mean_iterations']:.2f} iterations; per render "
        f"{out['kernel_ops'] / max(out['renders'], 1):.0f} kernel operations"
    )
    for name, n in list(out["by_name"].items())[:15]:
        print(f"{n:>8}  {name}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
