"""The frame solver's schedules side by side: whole-frame, two-tier and auto (the default).

Simulates 128 x 128 px movies (100 nm pixels, 1000-5000 photons, background 10; the
project's pupil models tabulated as the pipeline does) for each case, localizes each with
each schedule in one process, back to back, and prints localizations per second, their
ratio to whole-frame's, Jaccard and RMSE; writes ``benchmarks/results/two_tier.json``::

    python benchmarks/two_tier.py            # the four cases below
    python benchmarks/two_tier.py --quick    # fewer frames
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from sparseloc.evaluate import evaluate
from sparseloc.pipeline import localize
from speed_before_after import benchmark_frames  # this folder is on the path

SCHEDULES = ("whole-frame", "two-tier", "auto")
CASES = [("astig", 0.05, 100), ("dh", 0.05, 100), ("astig", 0.5, 20), ("dh", 1.0, 8)]


def run_case(psf: str, density: float, n: int, seed: int = 3) -> list[dict]:
    frames, work, p0, sim = benchmark_frames(n, density, seed, psf)
    rows = []
    for schedule in SCHEDULES:
        p = replace(p0, frame_schedule=schedule)
        localize(frames[:1], work, p)  # kernels compiled, templates built
        t = time.perf_counter()
        r = localize(frames, work, p)
        dt = time.perf_counter() - t
        ev = evaluate(r.table, sim.truth)
        rows.append(
            dict(
                psf=psf,
                density=density,
                frames=n,
                schedule=schedule,
                locs=len(r.table),
                seconds=dt,
                locs_per_s=len(r.table) / dt,
                jaccard=ev.jaccard,
                rmse_lateral=ev.rmse_lateral,
                rmse_axial=ev.rmse_axial,
            )
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a quarter of the frames")
    args = ap.parse_args()
    head = (
        f"{'PSF':6s} {'/um^2':>6s} {'frames':>6s} {'schedule':12s} {'locs':>6s} "
        f"{'s':>7s} {'locs/s':>7s} {'ratio':>6s} {'Jaccard':>8s} {'RMSE lat':>9s} {'ax':>6s}"
    )
    print("one process, back to back; ratio = localizations per second / whole-frame's")
    print(head)
    print("-" * len(head))
    out = []
    for psf, density, n in CASES:
        rows = run_case(psf, density, max(4, n // 4) if args.quick else n)
        base = rows[0]["locs_per_s"]
        for r in rows:
            r["ratio"] = r["locs_per_s"] / base
            print(
                f"{r['psf']:6s} {r['density']:6.2f} {r['frames']:6d} {r['schedule']:12s} "
                f"{r['locs']:6d} {r['seconds']:7.1f} {r['locs_per_s']:7.1f} {r['ratio']:6.2f} "
                f"{r['jaccard']:8.1f} {r['rmse_lateral']:9.1f} {r['rmse_axial']:6.1f}",
                flush=True,
            )
        out += rows
    path = Path(__file__).parent / "results" / "two_tier.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
