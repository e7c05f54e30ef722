"""The frame solver's fits on each backend: the default compiled per-group loop against the
batched lockstep path (``LocalizeParams.device``) on NumPy and PyTorch.

Localizes the same simulated 128 x 128 double-helix frames (1 emitter/um^2, 1000-5000 photons,
background 10) in one process with each device, the frames of a run in one lockstep block, and
prints seconds, localizations, Jaccard and RMSE per device; writes JSON. On a GPU machine pass
``--devices none,numpy,cuda``.

    python benchmarks/speed_device.py --frames 2 --devices none,numpy,cpu
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, check_device, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.simulate import SimulatedMovie


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--devices", default="none,numpy,cpu")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/speed_device.json"))
    args = ap.parse_args(argv)
    px, n = 100.0, args.frames
    work = work_model_for(make_psf("dh"), LocalizeParams(pixel_size=px))
    movie = SimulatedMovie(work, n, (128, 128), px, density=1.0, seed=args.seed)
    frames = movie.frames(0, n)
    truth = movie.truth_of(np.arange(n))
    localize(frames[:1], work, LocalizeParams(pixel_size=px))  # compile the numba kernels
    print(f"{n} frames of 128x128 px, 1 /um^2, one process; device none = compiled per-group loop")
    rows = []
    for name in args.devices.split(","):
        dev = None if name == "none" else name
        if dev is not None:
            try:
                check_device(dev)
            except ValueError as exc:
                print(f"device {name}: skipped ({exc})")
                continue
        p = LocalizeParams(pixel_size=px, device=dev)
        t0 = time.perf_counter()
        res = localize(frames, work, p, block=n)
        secs = time.perf_counter() - t0
        ev = evaluate(res.table, truth)
        rows.append(
            {
                "device": name,
                "seconds": secs,
                "seconds_per_frame": secs / n,
                "localizations": len(res.table),
                "jaccard": ev.jaccard,
                "rmse_lateral_nm": ev.rmse_lateral,
                "rmse_axial_nm": ev.rmse_axial,
            }
        )
        print(
            f"device {name:7s}: {secs:6.1f} s ({secs / n:.1f} s/frame), {len(res.table)} locs, "
            f"Jaccard {ev.jaccard:.1f} %, RMSE {ev.rmse_lateral:.1f} / {ev.rmse_axial:.1f} nm",
            flush=True,
        )
    out = {"machine": platform.platform(), "frames": n, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
