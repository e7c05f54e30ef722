"""Drift correction accuracy: RCC and fiducials on a simulated filament movie with known drift.

Simulates blinking fluorophores on 3D filaments (``filament_scene``; localizations = truth +
Gaussian noise, 15 nm lateral and 40 nm axial by default), imposes a smooth non-linear drift of
200 nm in x and y and 100 nm in z over the movie, and estimates it with ``rcc_drift`` (on the
filament localizations) and ``fiducial_drift`` (the same plus a few fiducial beads present in
95 % of the frames). Prints, per method, the RMS error of the estimated drift per axis (after
removing the constant offset: drift is defined up to a constant), the localization RMSE of the
filament localizations against the truth before and after correction, and the time; writes
JSON and the RCC drift plot.

Usage::

    python benchmarks/drift.py [--frames 10000] [--fov 12800] [--filaments 6] [--fiducials 3]
                               [--noise-lat 15] [--noise-ax 40] [--segments 10] [--bin 20]
                               [--seed 0] [--out FILE] [--png FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sparseloc.drift import apply_drift, fiducial_drift, plot_drift, rcc_drift
from sparseloc.simulate import filament_scene


def true_drift(frames: np.ndarray, n_frames: int) -> np.ndarray:
    """Smooth non-linear drift (nm), zero at frame 0: 200 nm in x and y, 100 nm in z."""
    u = np.asarray(frames, dtype=float) / max(n_frames - 1, 1)
    dx = 200 * (u**1.5 + 0.1 * np.sin(3 * np.pi * u))
    dy = -200 * u + 40 * np.sin(2 * np.pi * u)
    dz = 50 * (1 - np.cos(np.pi * u))
    return np.stack([dx, dy, dz], axis=1)


def trio(v: list[float]) -> str:
    return "/".join(f"{a:.1f}" for a in v)


def rms(a: np.ndarray) -> list[float]:
    return np.sqrt(np.mean(a**2, axis=0)).tolist()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--fov", type=float, default=12800.0, help="field of view side (nm)")
    ap.add_argument("--filaments", type=int, default=6)
    ap.add_argument("--fiducials", type=int, default=3)
    ap.add_argument("--noise-lat", type=float, default=15.0, help="lateral noise sigma (nm)")
    ap.add_argument("--noise-ax", type=float, default=40.0, help="axial noise sigma (nm)")
    ap.add_argument("--segments", type=int, default=10)
    ap.add_argument("--bin", type=float, default=20.0, help="RCC xy bin (nm)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/drift.json"))
    ap.add_argument("--png", type=Path, default=Path("docs/drift.png"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    n = args.frames
    noise = np.array([args.noise_lat, args.noise_lat, args.noise_ax])

    t0 = time.perf_counter()
    truth = filament_scene(rng, n, (args.fov, args.fov), n_filaments=args.filaments)
    truth = truth[["frame", "x_nm", "y_nm", "z_nm"]].reset_index(drop=True)
    beads = []
    for _ in range(args.fiducials):
        x, y = rng.uniform(0.1 * args.fov, 0.9 * args.fov, 2)
        present = np.nonzero(rng.random(n) < 0.95)[0]
        z = rng.uniform(-300, 300)
        beads.append(pd.DataFrame({"frame": present, "x_nm": x, "y_nm": y, "z_nm": z}))

    def observe(table: pd.DataFrame) -> pd.DataFrame:
        pos = table[["x_nm", "y_nm", "z_nm"]].to_numpy()
        pos = pos + true_drift(table["frame"].to_numpy(), n) + rng.normal(0, noise, pos.shape)
        out = pd.DataFrame(pos, columns=["x_nm", "y_nm", "z_nm"])
        out.insert(0, "frame", table["frame"].to_numpy())
        return out

    locs = observe(truth)
    with_beads = pd.concat([locs, *(observe(b) for b in beads)], ignore_index=True)
    with_beads = with_beads.sort_values("frame", kind="stable").reset_index(drop=True)
    sim_s = time.perf_counter() - t0
    print(
        f"{n} frames, {args.fov / 1000:.1f} x {args.fov / 1000:.1f} um, {args.filaments} "
        f"filaments: {len(locs)} localizations ({len(locs) / n:.1f} per frame), noise "
        f"{args.noise_lat:g} nm lateral / {args.noise_ax:g} nm axial; drift 200/200/100 nm "
        f"(x/y/z); {args.fiducials} fiducials in 95 % of frames (fiducial run only); "
        f"simulated in {sim_s:.1f} s"
    )

    xyz = ["x_nm", "y_nm", "z_nm"]
    ref = truth[xyz].to_numpy()
    err_before = rms(locs[xyz].to_numpy() - ref)
    rows = []
    results = {}
    for name, fn, table in (
        ("rcc", lambda t: rcc_drift(t, segments=args.segments, bin_nm=args.bin), locs),
        ("fiducial", fiducial_drift, with_beads),
    ):
        if name == "fiducial" and args.fiducials == 0:
            continue
        t1 = time.perf_counter()
        res = fn(table)
        secs = time.perf_counter() - t1
        results[name] = res
        truth_curve = true_drift(res.frames, n)
        diff = res.drift - truth_curve
        drift_err = rms(diff - diff.mean(axis=0))
        err_after = rms(apply_drift(locs, res)[xyz].to_numpy() - ref)
        rows.append(
            {
                "method": name,
                "drift_rms_error_nm": drift_err,
                "drift_max_error_nm": np.max(np.abs(diff - diff.mean(axis=0)), axis=0).tolist(),
                "loc_rmse_before_nm": err_before,
                "loc_rmse_after_nm": err_after,
                "seconds": secs,
                "reliable": res.reliable,
                "warnings": res.warnings,
                "details": res.details,
            }
        )

    hdr = (
        f"{'method':>8} | {'drift RMS err x/y/z (nm)':>24} | {'loc RMSE before x/y/z':>21} | "
        f"{'loc RMSE after x/y/z':>21} | {'time s':>6} | reliable"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(
            f"{r['method']:>8} | {trio(r['drift_rms_error_nm']):>24} | "
            f"{trio(r['loc_rmse_before_nm']):>21} | {trio(r['loc_rmse_after_nm']):>21} | "
            f"{r['seconds']:6.1f} | {r['reliable']}"
        )
        for w in r["warnings"]:
            print(f"{'':>8}   warning: {w}")
    print(f"localization noise (the floor): {trio(noise.tolist())} nm")

    if "rcc" in results:
        res = results["rcc"]
        plot_drift(res, args.png, truth=true_drift(res.frames, n))
        print(f"wrote {args.png}")
    out = {
        "params": vars(args) | {"out": str(args.out), "png": str(args.png)},
        "n_localizations": len(locs),
        "rows": rows,
        "machine": platform.platform(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=_json_default))
    print(f"wrote {args.out}")
    return out


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"object of type {type(obj).__name__} is not JSON-serialisable")


if __name__ == "__main__":
    main()
