"""Bright emitters on a camera that saturates: the fits with and without the clipped pixels.

A camera clips each pixel at its largest count: a 12-bit camera written to 16-bit files at
4095 ADU, any camera at its type's largest value (65535), which an EMCCD at a high EM gain
reaches with a few thousand photons per pixel. Movies of 96 x 96 px of 100 nm are simulated
with the built-in astigmatic and double-helix pupil models (0.3 emitters/um^2 per frame,
``--photons`` photons, 10,000-100,000 by default: fiducial beads, quantum dots, a bright
dye at high power; background 20 photons/px, z over the model's range) on two cameras:
an ideal one (offset 100 ADU, 1 e-/ADU) whose frames are then clipped at ``--clip`` ADU, and
an EMCCD (EM gain 300, 12 e-/ADU, offset 100 ADU) that saturates at 65535 ADU by itself.
Each movie is localized by ``sparseloc localize`` with the camera's flags, once with the
defaults (the pixels at the movie's clipping level, or at its type's largest value, are
left out of the fits) and once with ``--saturation 1e12`` (no pixel taken as saturated: the
clipped values at face value), and the ideal camera's movie once more unclipped; each table
is scored with :func:`sparseloc.evaluate.evaluate` (250 nm lateral, 500 nm axial).

Usage::

    python benchmarks/saturation.py [--frames 20] [--psfs astig,dh] [--work DIR]
        [--out benchmarks/results/saturation.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from sparseloc.camera import Camera
from sparseloc.evaluate import evaluate
from sparseloc.io.tables import read_table
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate, write_simulation

PX = 100.0
CAMERAS = {
    "ideal": (Camera(kind="ideal", offset=100.0, gain=1.0), ["--offset", "100", "--gain", "1"]),
    "emccd": (
        Camera(kind="emccd", offset=100.0, gain=12.0, em_gain=300.0),
        "--camera emccd --offset 100 --gain 12 --em-gain 300".split(),
    ),
}


def localize(movie: Path, out: Path, psf: str, flags: list[str]) -> tuple[float, str]:
    """``sparseloc localize`` on ``movie``; its seconds and its notes (stderr)."""
    t = time.perf_counter()
    cmd = ["sparseloc", "localize", str(movie), "-o", str(out), "--psf", psf, *flags]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed: {p.stderr.strip()}")
    return time.perf_counter() - t, p.stderr


def case(psf: str, cam_name: str, args, work: Path) -> list[dict]:
    """The rows of one PSF on one camera."""
    cam, flags = CAMERAS[cam_name]
    sim = simulate(make_psf(psf), n_frames=args.frames, shape=(96, 96), pixel_size=PX,
                   density=0.3, photons=tuple(args.photons), background=20.0, camera=cam,
                   seed=3)  # fmt: skip
    movies = {}
    if cam_name == "ideal":
        raw = sim.movie
        movies["unclipped"] = (write_simulation(sim, work / f"{psf}_{cam_name}_raw.tif")[0], raw)
        sim.movie = np.minimum(sim.movie, args.clip).astype(np.uint16)
    path = write_simulation(sim, work / f"{psf}_{cam_name}.tif")[0]
    movies["saturated, left out"] = (path, sim.movie)
    movies["saturated, at face value"] = (path, sim.movie)
    rows = []
    for name, (mv, frames) in movies.items():
        top = int(frames.max())
        clipped = int(np.count_nonzero(frames >= top))
        extra = ["--saturation", "1e12"] if name.endswith("face value") else []
        out = work / f"{psf}_{cam_name}_{name.replace(' ', '_').replace(',', '')}.parquet"
        seconds, _ = localize(mv, out, psf, [*flags, "--workers", "1", "--overwrite", *extra])
        ev = evaluate(read_table(out), sim.truth)
        rows.append(dict(psf=psf, camera=cam_name, movie=name, top_adu=top, pixels_at_top=clipped,
                         jaccard=ev.jaccard, recall=ev.recall, precision=ev.precision,
                         rmse_lateral=ev.rmse_lateral, rmse_axial=ev.rmse_axial,
                         seconds=seconds))  # fmt: skip
        r = rows[-1]
        print(f"{psf:6s} {cam_name:6s} {name:26s} {top:6d} {clipped:6d} | {r['jaccard']:5.1f} "
              f"{r['recall']:.3f} {r['precision']:.3f} | {r['rmse_lateral']:5.1f} "
              f"{r['rmse_axial']:5.1f} | {seconds:5.1f}", flush=True)  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--psfs", default="astig,dh")
    ap.add_argument("--cameras", default="ideal,emccd")
    ap.add_argument("--photons", type=float, nargs=2, default=(10000.0, 100000.0))
    ap.add_argument("--clip", type=int, default=4095, help="the ideal camera's clip (ADU)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/saturation.json"))
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="saturation_"))
    work.mkdir(parents=True, exist_ok=True)
    print(f"{args.frames} frames of 96 x 96 px, 0.3 /um^2, {args.photons[0]:g}-"
          f"{args.photons[1]:g} photons, background 20; work folder {work}")  # fmt: skip
    print(f"{'PSF':6s} {'camera':6s} {'movie':26s} {'top':>6s} {'at top':>6s} | {'Jac %':>5s} "
          f"{'rec':>5s} {'prec':>5s} | {'lat':>5s} {'ax':>5s} | {'s':>5s}")  # fmt: skip
    rows = []
    for psf in args.psfs.split(","):
        for cam in args.cameras.split(","):
            rows += case(psf, cam, args, work)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
