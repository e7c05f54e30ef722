"""Calibrated spline against the ideal theory on an aberrated double-helix microscope.

A bead z-scan is simulated from a double-helix pupil with added aberrations (0.1 waves RMS of
coma Z(3,1) and of spherical Z(4,0) by default), calibrated with ``calibrate_beads`` into a
cubic-spline model, and isolated emitters simulated from the same aberrated pupil are fitted
(maximum likelihood, Poisson) with three models:

- ``spline``: the calibration (what a user gets from ``sparseloc calibrate``);
- ``ideal``: the unaberrated double-helix pupil (what a user gets from theory alone);
- ``truth``: the aberrated pupil itself (the best possible model; a reference).

For each model: the axial bias at each z and its largest magnitude, and RMSE / sqrt(CRLB) in x,
y, z pooled over z (bounds from the true model). Fits start from the truth perturbed as a
sparse solution would be (N(0, 30 nm) laterally, N(0, 50 nm) axially). Lateral positions are
compared after removing each model's mean lateral offset: the lateral origin of a measured PSF
is a convention (the centroid of its z-averaged image), and coma moves that centroid.

Usage::

    python benchmarks/calibration.py [--coma 0.1] [--spherical 0.1] [--planes 9] [--reps 40]
                                     [--photons 2000] [--background 10] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from sparseloc.calibrate import calibrate_beads
from sparseloc.crlb import crlb
from sparseloc.psf import DoubleHelixMask, PupilPSF, ZernikeMask, make_psf
from sparseloc.psf.masks import combine
from sparseloc.simulate import bead_scan_truth, simulate
from sparseloc.solvers import Emitters
from sparseloc.solvers.refine import fit_emitters


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--coma", type=float, default=0.1, help="Z(3,1) in waves RMS")
    ap.add_argument("--spherical", type=float, default=0.1, help="Z(4,0) in waves RMS")
    ap.add_argument("--planes", type=int, default=9, help="z planes of test emitters")
    ap.add_argument("--reps", type=int, default=40, help="emitters per plane")
    ap.add_argument("--photons", type=float, default=2000.0)
    ap.add_argument("--background", type=float, default=10.0)
    ap.add_argument("--window", type=int, default=17)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/calibration.json"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    px = 100.0
    aberr = ZernikeMask({(3, 1): args.coma, (4, 0): args.spherical})
    truth_model = PupilPSF(
        combine([DoubleHelixMask(0.33), aberr]), z_range=(-1000.0, 1000.0), name="dh+aberr"
    )
    ideal = make_psf("dh")

    # -- bead calibration ------------------------------------------------------------------
    planes = np.arange(-900.0, 900.0 + 1e-6, 20.0)
    grid = np.array([(x, y) for x in (3000.0, 8000.0, 13000.0) for y in (3000.0, 8000.0, 13000.0)])
    pos = grid + rng.uniform(-50, 50, grid.shape)
    offsets = rng.uniform(-30, 30, len(pos))
    offsets -= offsets.mean()  # z = 0 is the beads' mean focus, as calibrate_beads defines it
    t0 = time.perf_counter()
    sim = simulate(
        truth_model,
        scene=bead_scan_truth(pos, planes, 20000.0, offsets),
        n_frames=planes.size,
        shape=(160, 160),
        pixel_size=px,
        background=10.0,
        seed=args.seed,
    )
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    cal = calibrate_beads(sim.movie, px, 20.0, offset=100.0)
    t_cal = time.perf_counter() - t0
    spline = cal.psf
    used = cal.beads[cal.beads["used"]]
    print(
        f"bead scan: {planes.size} planes, {len(pos)} beads, simulated in {t_sim:.0f} s; "
        f"calibrated in {t_cal:.1f} s from {len(used)} beads, ROI {spline.stack.shape[1]} px, "
        f"z {spline.z_range[0]:.0f}..{spline.z_range[1]:.0f} nm"
    )
    fitted = used["shift_z_nm"].to_numpy()
    # Match each used bead to the nearest true position (detection order differs).
    bx, by = used["x_nm"].to_numpy(), used["y_nm"].to_numpy()
    nearest = np.argmin(np.hypot(bx[:, None] - pos[:, 0], by[:, None] - pos[:, 1]), axis=1)
    z_err = (fitted - fitted.mean()) - (offsets[nearest] - offsets[nearest].mean())
    xy_err = np.hypot(bx - pos[nearest, 0], by - pos[nearest, 1])
    print(
        f"bead z offsets recovered to {np.sqrt(np.mean(z_err**2)):.1f} nm RMS; bead positions "
        f"{np.median(xy_err):.1f} nm median off the emitters (coma moves the PSF's centroid)"
    )

    # -- isolated emitters -------------------------------------------------------------------
    w = args.window
    zs = np.linspace(-600.0, 600.0, args.planes)
    models = {"spline": spline, "ideal": ideal, "truth": truth_model}
    errs = {k: [] for k in models}
    zt_all, bounds = [], []
    times = {k: [] for k in models}
    for z in tqdm(zs, desc="planes", leave=False):
        for _ in range(args.reps):
            x = w * px / 2 + rng.uniform(-px / 2, px / 2)
            y = w * px / 2 + rng.uniform(-px / 2, px / 2)
            mu = truth_model.render(x, y, z, args.photons, (w, w), px) + args.background
            img = rng.poisson(mu).astype(float)
            bounds.append(crlb(truth_model, x, y, z, args.photons, args.background, (w, w), px)[0])
            zt_all.append(z)
            start_off = [rng.normal(0, 30), rng.normal(0, 30), rng.normal(0, 50)]
            for name, model in models.items():
                lo, hi = model.z_range
                start = Emitters.from_array(
                    [
                        [
                            x + start_off[0],
                            y + start_off[1],
                            float(np.clip(z + start_off[2], lo, hi)),
                            args.photons,
                        ]
                    ]
                )
                t0 = time.perf_counter()
                fit = fit_emitters(img, model, start, pixel_size=px)
                times[name].append(time.perf_counter() - t0)
                errs[name].append(fit.emitters.as_array()[0, :3] - [x, y, z])
    zt = np.array(zt_all)
    b = np.array(bounds)[:, :3]  # crlb() returns standard deviations (nm)
    print(
        f"\n{len(zt)} emitters from the aberrated pupil (coma {args.coma}, spherical "
        f"{args.spherical} waves), {args.photons:.0f} photons, background {args.background:g}, "
        f"{w}x{w} px of {px:.0f} nm, z {zs[0]:.0f}..{zs[-1]:.0f} nm"
    )
    hdr = (
        f"{'model':<8}| {'max |bias z|':>12} {'mean |bias z|':>13} | "
        f"{'RMSE/sqrt(CRLB) x':>18}{'y':>6}{'z':>6} | {'lateral offset x, y':>20} | ms/fit"
    )
    print(hdr)
    print("-" * len(hdr))
    out = {
        "params": vars(args) | {"out": str(args.out)},
        "calibration": {
            "beads_used": len(used),
            "roi_px": int(spline.stack.shape[1]),
            "z_range_nm": list(spline.z_range),
            "seconds": t_cal,
            "fitted_shift_z_nm": fitted.tolist(),
            "true_offsets_nm": offsets[nearest].tolist(),
            "z_offset_rms_error_nm": float(np.sqrt(np.mean(z_err**2))),
        },
        "models": {},
        "z_nm": zs.tolist(),
        "machine": platform.platform(),
    }
    for name in models:
        e = np.array(errs[name])
        offset_xy = e[:, :2].mean(axis=0)
        e_c = e.copy()
        e_c[:, :2] -= offset_xy
        bias_z = np.array([e[zt == z, 2].mean() for z in zs])
        se_z = np.array([e[zt == z, 2].std() / np.sqrt((zt == z).sum()) for z in zs])
        ratio = np.sqrt(np.mean((e_c / b) ** 2, axis=0))
        out["models"][name] = {
            "bias_z_by_plane_nm": bias_z.tolist(),
            "bias_z_se_nm": se_z.tolist(),
            "max_abs_bias_z_nm": float(np.abs(bias_z).max()),
            "mean_abs_bias_z_nm": float(np.abs(bias_z).mean()),
            "rmse_over_sqrt_crlb": ratio.tolist(),
            "lateral_offset_nm": offset_xy.tolist(),
            "rmse_nm": np.sqrt(np.mean(e_c**2, axis=0)).tolist(),
            "median_ms_per_fit": 1e3 * float(np.median(times[name])),
        }
        print(
            f"{name:<8}| {np.abs(bias_z).max():12.1f} {np.abs(bias_z).mean():13.1f} | "
            f"{ratio[0]:18.2f}{ratio[1]:6.2f}{ratio[2]:6.2f} | "
            f"{offset_xy[0]:9.1f}{offset_xy[1]:9.1f}   | {1e3 * np.median(times[name]):6.1f}"
        )
    print(
        "\naxial bias by plane (nm; standard error about "
        f"{np.mean(out['models']['truth']['bias_z_se_nm']):.1f} nm):"
    )
    print(f"{'z':>7}" + "".join(f"{name:>9}" for name in models))
    for i, z in enumerate(zs):
        print(
            f"{z:7.0f}"
            + "".join(f"{out['models'][n]['bias_z_by_plane_nm'][i]:9.1f}" for n in models)
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"\nwrote {args.out}")
    return out


if __name__ == "__main__":
    main()
