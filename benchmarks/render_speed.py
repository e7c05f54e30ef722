"""Render speed of each PSF model: images per second for a 17x17 window.

Prints a table and writes JSON. Usage: ``python benchmarks/render_speed.py [--out FILE]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from sparseloc.psf import make_psf

MODELS = ["dh", "astig", "clear", "dh-analytic", "astig-gauss"]


def time_model(name: str, batch: int, derivatives: bool, repeats: int, pixel: float) -> float:
    """Median seconds per image over ``repeats`` calls rendering ``batch`` emitters each."""
    model = make_psf(name)
    rng = np.random.default_rng(0)
    x = rng.uniform(1000, 1700, batch)
    y = rng.uniform(1000, 1700, batch)
    z = rng.uniform(*model.z_range, batch)
    model.images(x, y, z, (17, 17), pixel, derivatives=derivatives)  # warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.images(x, y, z, (17, 17), pixel, derivatives=derivatives)
        times.append((time.perf_counter() - t0) / batch)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/render_speed.json"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--pixel", type=float, default=100.0)
    args = ap.parse_args()
    rows = []
    print(f"{'model':<13}{'images/s':>12}{'with gradients/s':>19}")
    for name in MODELS:
        plain = time_model(name, args.batch, False, args.repeats, args.pixel)
        grad = time_model(name, args.batch, True, args.repeats, args.pixel)
        rows.append({"model": name, "images_per_s": 1 / plain, "gradients_per_s": 1 / grad})
        print(f"{name:<13}{1 / plain:>12.0f}{1 / grad:>19.0f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "window": [17, 17],
        "pixel_nm": args.pixel,
        "batch": args.batch,
        "repeats": args.repeats,
        "machine": platform.platform(),
        "processor": platform.processor(),
    }
    args.out.write_text(json.dumps({"meta": meta, "results": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
