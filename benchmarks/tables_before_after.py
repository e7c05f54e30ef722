"""Localization tables of fixed inputs, saved by one version of the code and compared with
another's: a refactoring must leave them unchanged.

Inputs: the density benchmark's movies (``density.py``'s simulation: double-helix pupil model,
64 x 64 px of 100 nm, 20 frames at 0.5, 1 and 2 emitters/um^2, seeds 0, 1, 2) and storm-analysis's
double-helix frames in ``../shared/data/storm_analysis_sim/dh`` (calibrated from its bead scan),
all with the default frame solver and one process (each checkout's default schedule: ``auto``
from commit ef7f001 on, ``whole-frame`` before it; compare checkouts on one side of that change).

Usage::

    git worktree add /tmp/before <commit>
    PYTHONPATH=/tmp/before/src python benchmarks/tables_before_after.py save /tmp/tables_before
    python benchmarks/tables_before_after.py save /tmp/tables_after
    python benchmarks/tables_before_after.py compare /tmp/tables_before /tmp/tables_after

``compare`` prints, per input, the row counts and the largest position (nm) and photon
differences of rows matched in order, and exits 1 when any table differs by more than 1e-6 nm.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

DENSITIES = (0.5, 1.0, 2.0)
STORM_FRAMES = ("dh_fista_diag_test01", "dh_random_density0.005px2", "dh_random_density0.01px2")
COLUMNS = ("frame", "x_nm", "y_nm", "z_nm", "photons")


def save(out: Path, data: Path, frames: int) -> None:
    import sparseloc
    from sparseloc.calibrate import calibrate_file
    from sparseloc.pipeline import LocalizeParams, localize
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate

    out.mkdir(parents=True, exist_ok=True)
    px = 100.0
    params = LocalizeParams(pixel_size=px)
    model = make_psf("dh")
    times = {"code": sparseloc.__file__}
    for i, density in enumerate(DENSITIES):
        sim = simulate(
            model,
            scene="uniform",
            n_frames=frames,
            shape=(64, 64),
            pixel_size=px,
            density=density,
            photons=(1000.0, 5000.0),
            background=10.0,
            seed=i,
        )
        movie = sim.movie.astype(np.float64) - sim.camera.offset
        t = time.perf_counter()
        res = localize(movie, model, params, workers=1)
        times[f"density_{density}"] = time.perf_counter() - t
        res.table.to_parquet(out / f"density_{density}.parquet")
        print(f"density {density}: {len(res.table)} rows, {times[f'density_{density}']:.1f} s")
    cal = calibrate_file(
        data / "beads_zscan.tif", px, z_file=data / "beads_zscan_z.csv", offset=100.0
    )
    for name in STORM_FRAMES:
        frame = tifffile.imread(data / f"{name}.tif").astype(np.float64) - 100.0
        frame = frame.reshape(-1, *frame.shape[-2:])
        t = time.perf_counter()
        res = localize(frame, cal.psf, params, workers=1)
        times[name] = time.perf_counter() - t
        res.table.to_parquet(out / f"{name}.parquet")
        print(f"{name}: {len(res.table)} rows, {times[name]:.1f} s")
    (out / "times.json").write_text(json.dumps(times, indent=2))


def compare(before: Path, after: Path) -> int:
    worst = 0.0
    t0 = json.loads((before / "times.json").read_text())
    t1 = json.loads((after / "times.json").read_text())
    print(
        f"{'input':>28} {'rows':>11} | {'max |d pos| nm':>14} {'max |d N|':>10} | "
        f"{'t after/before':>14}"
    )
    for path in sorted(before.glob("*.parquet")):
        a = pd.read_parquet(path)
        b = pd.read_parquet(after / path.name)
        key = path.stem
        rows = f"{len(a)}/{len(b)}"
        if len(a) != len(b):
            print(f"{key:>28} {rows:>11} | row counts differ")
            worst = np.inf
            continue
        a = a.sort_values(list(COLUMNS)).reset_index(drop=True)
        b = b.sort_values(list(COLUMNS)).reset_index(drop=True)
        if not np.array_equal(a["frame"].to_numpy(), b["frame"].to_numpy()):
            print(f"{key:>28} {rows:>11} | frames differ")
            worst = np.inf
            continue
        dpos = np.abs(
            a[["x_nm", "y_nm", "z_nm"]].to_numpy() - b[["x_nm", "y_nm", "z_nm"]].to_numpy()
        )
        dn = np.abs(a["photons"].to_numpy() - b["photons"].to_numpy())
        mpos = float(np.nanmax(dpos)) if dpos.size else 0.0
        mn = float(np.nanmax(dn)) if dn.size else 0.0
        worst = max(worst, mpos)
        ratio = t1[key] / t0[key]
        print(f"{key:>28} {rows:>11} | {mpos:14.2e} {mn:10.2e} | {ratio:14.3f}")
    total = sum(v for k, v in t1.items() if k != "code") / sum(
        v for k, v in t0.items() if k != "code"
    )
    print(f"total time after / before: {total:.3f}")
    ok = worst <= 1e-6
    print("tables equal (positions within 1e-6 nm)" if ok else "TABLES DIFFER")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("save")
    s.add_argument("out", type=Path)
    s.add_argument("--data", type=Path, default=Path("../shared/data/storm_analysis_sim/dh"))
    s.add_argument("--frames", type=int, default=20)
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "save":
        save(args.out, args.data, args.frames)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
