"""Real experimental frame: DeepSTORM3D's tetrapod STORM frame through ``localize``.

No ground truth exists: the script prints the count, the fitted z and photon ranges and the
goodness of fit, and writes the frame with the localizations on it (colour = z) to a PNG so a
microscopist can judge whether each PSF image got one localization and empty background none.

Optics from the data's README (DeepSTORM3D, Nehme et al. 2020): printed tetrapod mask, NA 1.45,
670 nm, 110 nm pixels; the frames were saved after minimum subtraction (offset 0 here). The
experiment (DeepSTORM3D's demo-2 settings) imaged emitters 0-4 um deep in water (n 1.33) with
the nominal focal plane 1.5 um deep: the model includes that index mismatch, and z (relative
to the nominal focal plane) is searched over -1500..2500 nm.

Usage::

    python benchmarks/real_data.py [--data DIR] [--png docs/real_tetrapod.png]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import tifffile

from sparseloc.pipeline import LocalizeParams, localize
from sparseloc.psf import make_psf


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/deepstorm3d"))
    ap.add_argument("--png", type=Path, default=Path("docs/real_tetrapod.png"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/real_data.json"))
    args = ap.parse_args(argv)
    px = 110.0
    model = make_psf(
        args.data / "Mat_Files_mask_tetrapod_printed.mat",
        na=1.45,
        wavelength=670.0,
        z_range=(-1500.0, 2500.0),
        n_sample=1.33,
        focal_depth=1500.0,
    )
    frame = tifffile.imread(args.data / "Experimental_Data_Tetrapod_demo2_1.tif").astype(float)
    frame = frame.reshape(-1, *frame.shape[-2:])
    t0 = time.perf_counter()
    res = localize(frame, model, LocalizeParams(pixel_size=px, background="spatial"))
    secs = time.perf_counter() - t0
    t = res.table
    print(f"tetrapod frame {frame.shape[1]}x{frame.shape[2]} px: {res.summary()}")
    print(
        f"z (nm): median {t.z_nm.median():.0f}, 5-95 % {t.z_nm.quantile(0.05):.0f} to "
        f"{t.z_nm.quantile(0.95):.0f}; photons median {t.photons.median():.0f}; background "
        f"median {t.background.median():.1f}; deviance/dof median {t.gof.median():.2f}; "
        f"flags {t.flag.value_counts().to_dict()}"
    )
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 9), layout="constrained")
    ax = fig.subplots()
    lo, hi = np.percentile(frame[0], [1, 99.7])
    ax.imshow(frame[0], cmap="gray", vmin=lo, vmax=hi)
    sc = ax.scatter(
        t.x_nm / px - 0.5,
        t.y_nm / px - 0.5,
        c=t.z_nm,
        cmap="turbo",
        vmin=model.z_range[0],
        vmax=model.z_range[1],
        s=36,
        marker="+",
        linewidths=1.2,
    )
    fig.colorbar(sc, ax=ax, shrink=0.7).set_label("z (nm)")
    ax.set_title(
        f"DeepSTORM3D tetrapod frame (real data): {len(t)} localizations, pupil model from the "
        "printed mask"
    )
    ax.set_xlabel("x (px, 110 nm)")
    ax.set_ylabel("y (px)")
    args.png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.png, dpi=80)
    print(f"wrote {args.png}")
    out = {
        "n_localizations": len(t),
        "seconds": secs,
        "z_median_nm": float(t.z_nm.median()),
        "gof_median": float(t.gof.median()),
        "flags": {k: int(v) for k, v in t.flag.value_counts().items()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
