"""Merging of blinks: molecules recovered from simulated PALM localizations, and speed.

Simulates localizations (no images) of N molecules at random 3D positions in a square field
(z in -500..500 nm). Each molecule switches on once, at a uniformly random frame, stays on for a
geometric number of frames (mean ``--mean-on``), then either blinks off for exactly one frame
(probability ``--p-blink``) and comes back on for another geometric run, or bleaches; localizations
past the last frame are dropped. Each on-frame gives one localization: the position plus Gaussian
noise of standard deviation ``--sigma-xy`` (x, y) and ``--sigma-z`` (z) at 3000 photons, scaled
by ``sqrt(3000 / photons)`` with photons uniform in 1000..5000; the sigma columns hold the
noise's true standard deviations. ``window_id`` carries the molecule id, so that each merged row
can be scored against its first localization's molecule.

For a sparse (realistic) case and denser ones (same molecules, fewer frames, so more of them
on per frame), merges with ``max_gap`` 0, 1, 2 and the default
distance, and once with the 3-sigma gate ``3 * median(sigma_xy)``, ``z_scale=0.5`` for
comparison; prints molecules, localizations, merged rows, merged/true (acceptance 0.9..1.1),
the share of merged rows mixing molecules, the share of molecules split over several rows, RMSE
against the truth before and after merging, and time. Then times ~1e6 localizations. Writes
JSON.

Usage::

    python benchmarks/merge.py [--molecules 2000] [--frames 2000] [--field-um 10]
                               [--dense-molecules 20000] [--dense-frames 500,150]
                               [--scale-molecules 270000] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd

from sparseloc.postprocess import default_merge_distance, link_blinks, merge_blinks


def simulate_palm(
    rng: np.random.Generator,
    n_mol: int,
    n_frames: int,
    field_nm: float,
    *,
    mean_on: float = 3.0,
    p_blink: float = 0.2,
    sigma_xy: float = 15.0,
    sigma_z: float = 40.0,
) -> tuple[pd.DataFrame, np.ndarray]:
    """Localizations of blinking molecules (frame, x, y, z in nm) and the true positions."""
    truth = np.column_stack(
        [rng.uniform(0, field_nm, (n_mol, 2)), rng.uniform(-500.0, 500.0, n_mol)]
    )
    start = rng.integers(0, n_frames, n_mol)
    # On-periods per molecule: 1 + number of one-frame blinks before bleaching.
    n_per = rng.geometric(1.0 - p_blink, n_mol)
    per_mol = np.repeat(np.arange(n_mol), n_per)
    per_len = rng.geometric(1.0 / mean_on, per_mol.size)
    # Start of each period: the molecule's start plus the earlier periods and their dark frames.
    step = per_len + 1
    first_per = np.cumsum(n_per) - n_per
    cum = np.cumsum(step) - step
    per_start = start[per_mol] + cum - cum[first_per][per_mol]
    mol = np.repeat(per_mol, per_len)
    first_loc = np.cumsum(per_len) - per_len
    frame = np.repeat(per_start, per_len) + np.arange(mol.size) - np.repeat(first_loc, per_len)
    keep = frame < n_frames
    mol, frame = mol[keep], frame[keep]
    photons = rng.uniform(1000.0, 5000.0, mol.size)
    scale = np.sqrt(3000.0 / photons)
    sig = np.column_stack([sigma_xy * scale, sigma_xy * scale, sigma_z * scale])
    xyz = truth[mol] + rng.normal(size=(mol.size, 3)) * sig
    df = pd.DataFrame(
        {
            "frame": frame,
            "x_nm": xyz[:, 0],
            "y_nm": xyz[:, 1],
            "z_nm": xyz[:, 2],
            "photons": photons,
            "background": 10.0,
            "sigma_x_nm": sig[:, 0],
            "sigma_y_nm": sig[:, 1],
            "sigma_z_nm": sig[:, 2],
            "sigma_photons": np.sqrt(photons),
            "gof": 1.0,
            "flag": "ok",
            "window_id": mol,
        }
    )
    return df.sort_values("frame", kind="stable").reset_index(drop=True), truth


def rmse(df: pd.DataFrame, truth: np.ndarray) -> tuple[float, float]:
    """Lateral (per axis) and axial RMSE (nm) of rows against their molecule (window_id)."""
    t = truth[df["window_id"].to_numpy()]
    dx = df["x_nm"].to_numpy() - t[:, 0]
    dy = df["y_nm"].to_numpy() - t[:, 1]
    dz = df["z_nm"].to_numpy() - t[:, 2]
    return float(np.sqrt(np.mean((dx**2 + dy**2) / 2))), float(np.sqrt(np.mean(dz**2)))


def score(
    name: str, locs: pd.DataFrame, truth: np.ndarray, gap: int, dist: float | None, zs: float | None
) -> dict:
    t0 = time.perf_counter()
    merged = merge_blinks(locs, max_distance_nm=dist, max_gap=gap, z_scale=zs)
    secs = time.perf_counter() - t0
    labels = link_blinks(locs, max_distance_nm=dist, max_gap=gap, z_scale=zs)
    mol = locs["window_id"].to_numpy()
    pairs = pd.DataFrame({"track": labels, "mol": mol})
    mixed = pairs.groupby("track")["mol"].nunique().gt(1).mean()
    split = pairs.groupby("mol")["track"].nunique().gt(1).mean()
    n_true = int(np.unique(mol).size)
    raw_xy, raw_z = rmse(locs, truth)
    m_xy, m_z = rmse(merged, truth)
    return {
        "case": name,
        "max_gap": gap,
        "max_distance_nm": default_merge_distance(locs) if dist is None else dist,
        "z_scale": "default" if zs is None else zs,
        "true_molecules": n_true,
        "raw_locs": len(locs),
        "merged_locs": len(merged),
        "ratio": len(merged) / n_true,
        "mixed_tracks_pct": 100 * float(mixed),
        "split_molecules_pct": 100 * float(split),
        "rmse_xy_raw_nm": raw_xy,
        "rmse_xy_merged_nm": m_xy,
        "rmse_z_raw_nm": raw_z,
        "rmse_z_merged_nm": m_z,
        "seconds": secs,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--molecules", type=int, default=2000)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--field-um", type=float, default=10.0)
    ap.add_argument("--dense-molecules", type=int, default=20000)
    ap.add_argument(
        "--dense-frames", default="500,150", help="frames of each dense case (comma-separated)"
    )
    ap.add_argument("--scale-molecules", type=int, default=270000, help="0 skips the timing")
    ap.add_argument("--scale-frames", type=int, default=20000)
    ap.add_argument("--mean-on", type=float, default=3.0)
    ap.add_argument("--p-blink", type=float, default=0.2)
    ap.add_argument("--sigma-xy", type=float, default=15.0)
    ap.add_argument("--sigma-z", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/merge.json"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    field = args.field_um * 1000.0
    kw = dict(
        mean_on=args.mean_on, p_blink=args.p_blink, sigma_xy=args.sigma_xy, sigma_z=args.sigma_z
    )
    area = args.field_um**2
    cases = [("sparse", args.molecules, args.frames)] + [
        (f"dense{i + 1}", args.dense_molecules, int(f))
        for i, f in enumerate(args.dense_frames.split(","))
    ]
    print(
        f"PALM-like localizations in a {args.field_um:g} x {args.field_um:g} um field, z -500..500"
        f" nm; on-runs geometric (mean {args.mean_on:g} frames), one-frame blinks with "
        f"probability {args.p_blink:g}; noise {args.sigma_xy:g} nm lateral, {args.sigma_z:g} nm "
        "axial at 3000 photons (photons 1000..5000)"
    )
    hdr = (
        f"{'case':>6} {'gap':>3} {'dist nm':>7} {'z_scale':>7} | {'true':>6} {'raw':>7} "
        f"{'merged':>7} {'ratio':>6} | {'mixed%':>6} {'split%':>6} | {'xy raw':>6} {'merged':>6} "
        f"{'z raw':>6} {'merged':>6} nm | {'s':>5}"
    )
    out: dict = {"params": vars(args) | {"out": str(args.out)}, "rows": [], "machine": ""}
    out["machine"] = platform.platform()
    for name, n_mol, n_frames in cases:
        locs, truth = simulate_palm(rng, n_mol, n_frames, field, **kw)
        per_frame = len(locs) / n_frames
        print(
            f"\n{name}: {n_mol} molecules ({n_mol / area:.0f}/um^2) over {n_frames} frames, "
            f"{len(locs)} localizations, {per_frame:.1f} per frame ({per_frame / area:.3f}/um^2)"
        )
        print(hdr)
        print("-" * len(hdr))
        med = float(np.median(np.sqrt((locs["sigma_x_nm"] ** 2 + locs["sigma_y_nm"] ** 2) / 2)))
        runs = [(g, None, None) for g in (0, 1, 2)] + [(1, 3.0 * med, 0.5)]
        for gap, dist, zs in runs:
            row = score(name, locs, truth, gap, dist, zs)
            row["molecules_per_um2"] = n_mol / area
            row["locs_per_frame"] = per_frame
            out["rows"].append(row)
            zlabel = "data" if zs is None else f"{zs:g}"
            print(
                f"{name:>6} {gap:3d} {row['max_distance_nm']:7.1f} {zlabel:>7} | "
                f"{row['true_molecules']:6d} {row['raw_locs']:7d} {row['merged_locs']:7d} "
                f"{row['ratio']:6.3f} | {row['mixed_tracks_pct']:6.2f} "
                f"{row['split_molecules_pct']:6.2f} | {row['rmse_xy_raw_nm']:6.1f} "
                f"{row['rmse_xy_merged_nm']:6.1f} {row['rmse_z_raw_nm']:6.1f} "
                f"{row['rmse_z_merged_nm']:6.1f}    | {row['seconds']:5.2f}",
                flush=True,
            )
    if args.scale_molecules > 0:
        # Same molecule density as the sparse case's field scaled up, so linking stays local.
        side = field * np.sqrt(args.scale_molecules / max(args.molecules, 1))
        locs, _ = simulate_palm(rng, args.scale_molecules, args.scale_frames, side, **kw)
        t0 = time.perf_counter()
        merged = merge_blinks(locs, max_gap=1)
        secs = time.perf_counter() - t0
        n_true = int(locs["window_id"].nunique())
        out["timing"] = {
            "molecules": n_true,
            "raw_locs": len(locs),
            "merged_locs": len(merged),
            "frames": args.scale_frames,
            "field_um": side / 1000.0,
            "seconds": secs,
        }
        print(
            f"\ntiming: {len(locs)} localizations ({args.scale_frames} frames, "
            f"{side / 1000:.0f} x {side / 1000:.0f} um) -> {len(merged)} rows "
            f"(ratio {len(merged) / n_true:.3f}) in {secs:.1f} s (max_gap 1)"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
