"""Drift correction through the whole pipeline: a drifting filament movie, localized, corrected.

``benchmarks/drift.py`` measures the drift estimators on simulated localization tables; this
script renders the camera movie instead. Blinking 3D filaments (double-helix pupil model,
100 nm pixels, 1000-5000 photons, background 10) drift by 200 nm in x and y and 100 nm in z
over the movie along smooth non-linear paths; the movie is localized with the default frame
solver, the drift is estimated by redundant cross-correlation (``rcc_drift``) from the
localizations alone, and the localizations are scored against the undrifted truth before and
after ``apply_drift``.

Usage::

    python benchmarks/drift_movie.py [--frames 600] [--size 64] [--density 0.5] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from sparseloc.drift import apply_drift, plot_drift, rcc_drift
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf
from sparseloc.simulate import filament_scene, simulate


def imposed_drift(frames: np.ndarray, n_frames: int) -> np.ndarray:
    """(N, 3) drift in nm: 200 nm in x and y, 100 nm in z over the movie, zero at frame 0."""
    s = frames / max(n_frames - 1, 1)
    dx = 200.0 * (0.6 * s + 0.4 * s**2)
    dy = -200.0 * np.sin(0.5 * np.pi * s)
    dz = 100.0 * (s - 0.3 * np.sin(2 * np.pi * s) / (2 * np.pi)) / 1.0
    return np.column_stack([dx, dy, dz])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--size", type=int, default=64, help="frame side (px)")
    ap.add_argument("--density", type=float, default=0.5, help="active emitters per um^2")
    ap.add_argument("--segments", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/drift_movie.json"))
    ap.add_argument("--png", type=Path, default=Path("docs/drift_movie.png"))
    args = ap.parse_args(argv)
    px, shape = 100.0, (args.size, args.size)
    fov = (shape[1] * px, shape[0] * px)
    model = make_psf("dh")
    rng = np.random.default_rng(args.seed)
    truth = filament_scene(
        rng, args.frames, fov, z_range=(-500.0, 500.0), density=args.density
    ).reset_index(drop=True)
    d = imposed_drift(truth["frame"].to_numpy(), args.frames)
    drifted = truth.copy()
    drifted[["x_nm", "y_nm", "z_nm"]] += d
    x, y = drifted.x_nm, drifted.y_nm
    inside = (x >= 0) & (x < fov[0]) & (y >= 0) & (y < fov[1])
    drifted, truth = drifted[inside].reset_index(drop=True), truth[inside].reset_index(drop=True)
    t0 = time.perf_counter()
    sim = simulate(
        model,
        scene=drifted,
        n_frames=args.frames,
        shape=shape,
        pixel_size=px,
        background=10.0,
        seed=args.seed,
    )
    t_sim = time.perf_counter() - t0
    frames = sim.movie.astype(np.float64) - sim.camera.offset
    t0 = time.perf_counter()
    res = localize(frames, model, LocalizeParams(pixel_size=px), workers=args.workers)
    t_loc = time.perf_counter() - t0
    locs = res.table
    t0 = time.perf_counter()
    est = rcc_drift(locs, segments=args.segments)
    t_drift = time.perf_counter() - t0
    true_curve = imposed_drift(est.frames, args.frames)
    err = est.drift - true_curve
    err -= err.mean(axis=0)  # drift is defined up to a constant
    drift_rms = np.sqrt(np.mean(err**2, axis=0))
    corrected = apply_drift(locs, est)
    # The estimate is zero at frame 0 like the truth; a constant offset left in it would
    # show up as bias in "after" below.
    before = evaluate(locs, truth)
    after = evaluate(corrected, truth)
    plot_drift(est, args.png, truth=true_curve)
    print(
        f"{args.frames} frames {shape[0]}x{shape[1]} px at {args.density:g}/um^2: "
        f"{len(truth)} emitters, {len(locs)} localizations "
        f"(simulate {t_sim:.0f} s, localize {t_loc:.0f} s, drift {t_drift:.1f} s)"
    )
    span = np.ptp(true_curve, axis=0)
    print(
        f"imposed drift: x {span[0]:.0f} nm, y {span[1]:.0f} nm, z {span[2]:.0f} nm; "
        f"estimate reliable: {est.reliable}"
    )
    for w in est.warnings:
        print(f"  warning: {w}")
    print(f"drift RMS error x/y/z: {drift_rms[0]:.1f} / {drift_rms[1]:.1f} / {drift_rms[2]:.1f} nm")
    print("                 Jaccard  RMSE lat  RMSE ax   bias x   bias y   bias z")
    for label, ev in (("before", before), ("after", after)):
        print(
            f"  {label:14s} {ev.jaccard:7.1f} {ev.rmse_lateral:9.1f} {ev.rmse_axial:8.1f} "
            f"{ev.bias_x:8.1f} {ev.bias_y:8.1f} {ev.bias_z:8.1f}"
        )
    print(f"wrote {args.png}")
    out = {
        "frames": args.frames,
        "shape": list(shape),
        "density": args.density,
        "n_locs": len(locs),
        "drift_rms_error_nm": drift_rms.tolist(),
        "reliable": bool(est.reliable),
        "before": before.as_dict(),
        "after": after.as_dict(),
        "seconds": {"simulate": t_sim, "localize": t_loc, "drift": t_drift},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
