"""Real experimental frame: DeepSTORM3D's tetrapod STORM frame through ``localize``.

No ground truth exists: the script prints the count, the fitted z and photon ranges and the
goodness of fit, and writes the frame with the localizations on it (colour = z) to a PNG so a
microscopist can judge whether each PSF image got one localization and empty background none.

Optics from the data's README (DeepSTORM3D, Nehme et al. 2020): printed tetrapod mask, NA 1.45,
670 nm, 110 nm pixels; the frames were saved after minimum subtraction (offset 0 here). The
experiment (DeepSTORM3D's demo-2 settings) imaged emitters 0-4 um deep in water (n 1.33) with
the nominal focal plane 1.5 um deep: the model includes that index mismatch, and z (relative
to the nominal focal plane) is searched over -1500..2500 nm.

Two more optical facts come from that work's settings, not from fitting this frame:

- The mask file stores the phase only inside the disc of angles that reach the camera from a
  water sample (sin theta <= n_water / n_oil), a disc of about 44.7 mask pixels. The objective's
  NA disc is larger: the back focal plane spans ``2 f NA / sqrt(M^2 - NA^2)`` = 2.90 mm on an
  SLM of 30 um pixels (f = 100 mm, M = 100), a radius of 48.3 mask pixels. Reading the support
  as the NA disc would shrink the mask's features by 1.45 / 1.33 (about 9 %).
- The counts are not photons. Their simulations of these data add a baseline of 20-40 counts
  and read noise of 8-12 counts rms; the frame itself shows variance growing with the mean
  (a photon-transfer line, measured below by :func:`sparseloc.camera.photon_transfer` from
  pixel second differences in 6x6 blocks, as ``sparseloc camera`` does: the slope is counts
  per photon, the intercept the read variance less slope x baseline).
  The frame is analysed as sCMOS data with that gain, the middle baseline (30 counts), and
  the read variance the line then implies.
- Their image model blurs every emitter with a Gaussian of about 1 camera pixel (110 nm) to
  match experimental images; the pupil model here takes the same ``blur``.

Usage::

    python benchmarks/real_data.py [--data DIR] [--png docs/real_tetrapod.png] [--baseline 30]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import tifffile

from sparseloc.camera import photon_transfer
from sparseloc.frame_residual import residual_figure
from sparseloc.pipeline import LocalizeParams, addition_bar, check_frame, localize
from sparseloc.psf import make_psf

# DeepSTORM3D demo-2 optics: f_4f 100 mm, magnification 100, SLM pixel 30 um, NA 1.45.
_BFP_RADIUS_PX = 100e3 * 1.45 / np.sqrt(100.0**2 - 1.45**2) / 30.0


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/deepstorm3d"))
    ap.add_argument("--png", type=Path, default=Path("docs/real_tetrapod.png"))
    ap.add_argument(
        "--residual-png",
        type=Path,
        default=Path("docs/real_tetrapod_residual.png"),
        help="frame, model and residual side by side",
    )
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/real_data.json"))
    ap.add_argument("--blur", type=float, default=110.0, help="PSF blur sigma (nm)")
    ap.add_argument(
        "--baseline", type=float, default=30.0, help="camera baseline (counts; 20-40 likely)"
    )
    args = ap.parse_args(argv)
    px = 110.0
    model = make_psf(
        args.data / "Mat_Files_mask_tetrapod_printed.mat",
        na=1.45,
        wavelength=670.0,
        z_range=(-1500.0, 2500.0),
        n_sample=1.33,
        focal_depth=1500.0,
        radius=_BFP_RADIUS_PX,
        blur=args.blur,
    )
    frame = tifffile.imread(args.data / "Experimental_Data_Tetrapod_demo2_1.tif").astype(float)
    frame = frame.reshape(-1, *frame.shape[-2:])
    slope, intercept = photon_transfer(frame[0])
    baseline = args.baseline
    read_var_adu = intercept + slope * baseline
    print(
        f"photon transfer: variance = {slope:.2f} x mean {intercept:+.1f} (counts); baseline "
        f"{baseline:g} -> {slope:.2f} counts/photon, read noise {np.sqrt(read_var_adu):.1f} counts"
    )
    photons = (frame - baseline) / slope
    params = LocalizeParams(
        pixel_size=px,
        background="spatial",
        noise="scmos",
        read_variance=read_var_adu / slope**2,
    )
    t0 = time.perf_counter()
    res = localize(photons, model, params)
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
    check = _check(photons, t, model, params, args.residual_png)
    out = {
        "n_localizations": len(t),
        **check,
        "seconds": secs,
        "z_median_nm": float(t.z_nm.median()),
        "gof_median": float(t.gof.median()),
        "flags": {k: int(v) for k, v in t.flag.value_counts().items()},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    return out


def _check(photons, t, model, params, png: Path) -> dict:
    """The frame check of the run (:func:`sparseloc.pipeline.check_frame`): prints the
    localizations' support and the light they leave, writes the picture."""
    res = check_frame(photons, 0, t, model, params)
    s = np.sort(res.support)
    bar = addition_bar(params)
    print(f"frame check: {res.summary(bar, params.min_snr)}")
    residual_figure(
        res, params.pixel_size, png, z_range=model.z_range,
        title="DeepSTORM3D tetrapod frame: localizations, their model and the residual",
    )  # fmt: skip
    print(f"wrote {png}")
    return {
        "support_median": float(np.median(s)) if len(s) else None,
        "support_below_bar": int(np.sum(s < bar)),
        "unexplained_peaks": len(res.unexplained),
    }


if __name__ == "__main__":
    main()
