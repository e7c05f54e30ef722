"""Lone emitters at high background: what the localizer keeps against what the bound allows.

Issue "Trust on data nobody here tuned on", item 3: emitters of 1,000-3,000 photons on 100
photons/px should be found at the rate their Cramer-Rao bound allows. Each frame of a movie
rendered from the SMLM 2016 challenge's measured bead stack (``challenge_render``: its EMCCD,
background 100 photons/px) holds one emitter near the centre of 64 x 64 px, z uniform in
-600..600 nm, all of the same brightness; the movie is localized from a calibration of the same
stack (with the beads' known positions), once started from the truth (what the fits and the
count selection keep) and once from scratch. Printed per PSF and brightness: the recall of
both, and the median lateral and axial bound of the emitters (alone, the challenge's camera).

    python benchmarks/sensitivity.py [--data ../shared/data] [--frames 60]
        [--photons 1000,1500,2000,3000] [--psfs dh,as]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

from challenge_render import BeadPSF, render_movie
from outside import CHALLENGE_CAMERA, PX
from sparseloc.calibrate import calibrate_file, read_bead_positions
from sparseloc.config import build_job
from sparseloc.crlb import crlb_single
from sparseloc.distributed import CameraFrames
from sparseloc.evaluate import evaluate
from sparseloc.io.calibration import save_calibration
from sparseloc.io.movie import Movie
from sparseloc.pipeline import localize

BACKGROUND = 100.0  #: photons/px, as challenge_render


def lone_emitters(n: int, photons: float, seed: int = 0) -> pd.DataFrame:
    """One emitter per frame (challenge columns, 1-based frames) near the centre of 64 px."""
    rng = np.random.default_rng(seed)
    return pd.DataFrame(
        {
            "frame": np.arange(1, n + 1),
            "xnano": 3200.0 + rng.uniform(-50.0, 50.0, n),
            "ynano": 3200.0 + rng.uniform(-50.0, 50.0, n),
            "znano": rng.uniform(-600.0, 600.0, n),
            "intensity": np.full(n, float(photons)),
        }
    )


def median_bounds(model, truth: pd.DataFrame) -> tuple[float, float]:
    """Median lateral (root mean of x and y variances) and axial bound (nm) of each emitter
    alone on the challenge's camera (detected photons and background at its QE)."""
    qe = CHALLENGE_CAMERA["qe"]
    sd = crlb_single(
        model,
        truth["z_nm"].to_numpy(float),
        truth["photons"].to_numpy(float) * qe,
        BACKGROUND * qe,
        PX,
        noise="emccd",
        singular="pinv",
    )
    lateral = np.sqrt((sd[:, 0] ** 2 + sd[:, 1] ** 2) / 2.0)
    return float(np.median(lateral)), float(np.median(sd[:, 2]))


def run(data: Path, psfs: list[str], photons: list[float], n: int, work: Path) -> list[dict]:
    folder = data / "smlm2016"
    beads = read_bead_positions(folder / "beads_gt.csv", PX)
    rows = []
    for kind in psfs:
        stack = folder / f"beads_{kind}.tif"
        psf = BeadPSF.from_beads(stack, folder / "beads_gt.csv")
        cal = calibrate_file(stack, PX, 10.0, z0_slice=75, offset=100.0, beads=beads)
        psf_file = save_calibration(cal, work / f"cal_{kind}.h5")
        for nph in photons:
            acts = lone_emitters(n, nph)
            path = work / f"lone_{kind}_{nph:.0f}.tif"
            tifffile.imwrite(path, render_movie(psf, acts, n, seed=1))
            truth = pd.DataFrame(
                {
                    "frame": acts["frame"] - 1,
                    "x_nm": acts["xnano"],
                    "y_nm": acts["ynano"],
                    "z_nm": acts["znano"],
                    "photons": acts["intensity"],
                }
            )
            with Movie.open(path) as movie:
                job = build_job({"psf": str(psf_file), "pixel_size": PX, **CHALLENGE_CAMERA}, movie)
                frames = CameraFrames(movie, job.camera, job.defects)
                t0 = time.perf_counter()
                kept = localize(frames, job.model, job.params, starts=truth, check=False)
                found = localize(frames, job.model, job.params)
                dt = time.perf_counter() - t0
            lat, ax = median_bounds(job.model, truth)
            rows.append(
                dict(
                    psf=kind.upper(),
                    photons=nph,
                    bound_lateral_nm=lat,
                    bound_axial_nm=ax,
                    recall_from_truth=evaluate(kept.table, truth).recall,
                    recall=evaluate(found.table, truth).recall,
                    precision=evaluate(found.table, truth).precision,
                    seconds=dt,
                )
            )
            r = rows[-1]
            print(
                f"{r['psf']:>3} {nph:8.0f} | {lat:8.0f} {ax:8.0f} | {r['recall_from_truth']:10.2f} "
                f"{r['recall']:8.2f} {r['precision']:9.2f}",
                flush=True,
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--photons", default="1000,1500,2000,3000")
    ap.add_argument("--psfs", default="dh,as")
    args = ap.parse_args()
    print(f"one emitter per frame, {args.frames} frames, background {BACKGROUND:g} photons/px")
    print("PSF  photons | bound lat    axial | from truth   recall precision")
    with tempfile.TemporaryDirectory() as tmp:
        run(
            args.data,
            args.psfs.split(","),
            [float(p) for p in args.photons.split(",")],
            args.frames,
            Path(tmp),
        )


if __name__ == "__main__":
    main()
