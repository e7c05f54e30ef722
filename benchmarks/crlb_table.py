"""CRLB table of the double-helix pupil model versus z.

Prints the Cramer-Rao lower bounds (standard deviations, nm) of x, y and z (and photons) for one
emitter at the centre of a window, fitted together with a constant background, and writes them as
JSON.

Example::

    python benchmarks/crlb_table.py --out benchmarks/results/crlb_table.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from sparseloc.crlb import NOISE_MODELS, crlb_single
from sparseloc.psf import make_psf


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=float, default=1100.0, help="photons per emitter")
    ap.add_argument("--background", type=float, default=5.0, help="photons per pixel")
    ap.add_argument("--pixel-size", type=float, default=160.0, help="nm")
    ap.add_argument("--na", type=float, default=1.45)
    ap.add_argument("--wavelength", type=float, default=670.0, help="nm")
    ap.add_argument(
        "--waist", type=float, default=None, help="DH waist, pupil radii (default: the dh model's)"
    )
    ap.add_argument("--z-min", type=float, default=-600.0, help="nm")
    ap.add_argument("--z-max", type=float, default=600.0, help="nm")
    ap.add_argument("--z-step", type=float, default=100.0, help="nm")
    ap.add_argument(
        "--window",
        type=int,
        default=None,
        help="square window in pixels (default: holds the model's support radius)",
    )
    ap.add_argument("--noise", choices=NOISE_MODELS, default="poisson")
    ap.add_argument("--read-variance", type=float, default=None, help="photons^2 (sCMOS)")
    ap.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/crlb_table.json"), help="JSON path"
    )
    args = ap.parse_args(argv)

    extra = {} if args.waist is None else {"waist": args.waist}
    model = make_psf("dh", na=args.na, wavelength=args.wavelength, **extra)
    z = np.arange(args.z_min, args.z_max + 0.5 * args.z_step, args.z_step)
    if args.window is None:
        radius = model.support_radius(args.pixel_size)
        window = 2 * int(np.ceil(radius / args.pixel_size)) + 1
    else:
        window = args.window
    t0 = time.perf_counter()
    bounds = crlb_single(
        model,
        z,
        args.photons,
        args.background,
        args.pixel_size,
        window=window,
        noise=args.noise,
        read_variance=args.read_variance,
    )
    elapsed = time.perf_counter() - t0

    print(
        f"CRLB of {model!r}, DH waist {model.mask.waist}\n"
        f"{args.photons:g} photons, background {args.background:g} photons/pixel, "
        f"{args.pixel_size:g} nm pixels, {window}x{window} window, noise {args.noise}"
    )
    head = f"{'z (nm)':>8} {'x (nm)':>8} {'y (nm)':>8} {'z (nm)':>8} {'N (ph)':>8}"
    print(head)
    print("-" * len(head))
    for zi, b in zip(z, bounds, strict=True):
        print(f"{zi:8.0f} {b[0]:8.2f} {b[1]:8.2f} {b[2]:8.2f} {b[3]:8.1f}")
    mean = bounds.mean(axis=0)
    print("-" * len(head))
    print(f"{'mean':>8} {mean[0]:8.2f} {mean[1]:8.2f} {mean[2]:8.2f} {mean[3]:8.1f}")
    print(f"({elapsed:.2f} s)")

    result = {
        "model": repr(model),
        "waist": model.mask.waist,
        "photons": args.photons,
        "background_photons_per_pixel": args.background,
        "pixel_size_nm": args.pixel_size,
        "window_px": window,
        "noise": args.noise,
        "read_variance_photons2": args.read_variance,
        "z_nm": z.tolist(),
        "crlb_x_nm": bounds[:, 0].tolist(),
        "crlb_y_nm": bounds[:, 1].tolist(),
        "crlb_z_nm": bounds[:, 2].tolist(),
        "crlb_photons": bounds[:, 3].tolist(),
        "seconds": elapsed,
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
