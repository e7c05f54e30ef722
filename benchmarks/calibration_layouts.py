"""Bead layouts, pixel sizes and cameras a calibration may meet, end to end from the command line.

Two sweeps, each case as a microscopist runs it (``sparseloc calibrate`` with its defaults on a
simulated bead z-stack, ``sparseloc localize`` with that calibration and the camera's flags,
:func:`sparseloc.evaluate.evaluate` against the truth; 250 nm / 500 nm tolerance):

- ``layouts``: one PSF and pixel size, bead stacks of different layouts on a 25.6 um field
  (a 3 x 3 grid 6 um apart, one bead, two beads 4 um apart, a 4 x 4 grid 3.5 um apart, 30
  beads at random, beads near the frame's edges, a 3 x 3 grid of beads 4,000-60,000 photons),
  all localizing one movie (30 frames, 12.8 um square, 0.3 /um^2, 1,000-5,000 photons,
  background 10) rendered with the PSF itself;
- ``optics``: each PSF at 65, 100 and 160 nm pixels with an ideal camera, an EMCCD and an
  sCMOS camera (bead stack of 9 beads 3.9 um apart, 20,000 photons each unless
  ``--bead-photons``; movie of 40 frames, 12.8 um square, 0.3 /um^2).

Usage::

    python benchmarks/calibration_layouts.py layouts --psf dh --work /tmp/lay
    python benchmarks/calibration_layouts.py optics --psfs astig,dh --work /tmp/opt
    python benchmarks/calibration_layouts.py optics --psfs dh --pixel-sizes 100 \
        --cameras ideal --bead-photons 2000 --work /tmp/dim
    python benchmarks/calibration_layouts.py optics --psfs astig,dh --pixel-sizes 100 \
        --cameras ideal --bead-margin 0 --bead-step 50 --work /tmp/ends

(the last: a scan no deeper than the movie's emitters, whose model must keep its end planes)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

from sparseloc.camera import Camera
from sparseloc.evaluate import evaluate
from sparseloc.io.calibration import read_calibration_info
from sparseloc.psf import make_psf
from sparseloc.simulate import bead_scan_truth, simulate, write_simulation

#: Beads' photons per frame, stack step (nm) and the margin (nm) beyond the PSF's z range.
BEAD_PHOTONS, BEAD_STEP, BEAD_MARGIN = 20000.0, 20.0, 200.0
BACKGROUND, PHOTONS, DENSITY = 10.0, (1000.0, 5000.0), 0.3

#: Cameras as simulated, and the flags that describe them to the command line.
CAMERAS = {
    "ideal": (Camera(kind="ideal", offset=100.0, gain=1.0), ["--offset", "100", "--gain", "1"]),
    "emccd": (
        Camera(kind="emccd", offset=100.0, gain=12.0, em_gain=200.0, qe=0.9, read_noise=50.0),
        "--camera emccd --offset 100 --gain 12 --em-gain 200 --qe 0.9 --read-noise 50".split(),
    ),
    "scmos": (
        Camera(kind="scmos", offset=100.0, gain=0.5, qe=0.8, read_noise=1.5),
        "--camera scmos --offset 100 --gain 0.5 --qe 0.8 --read-noise 1.5".split(),
    ),
}


def layouts(fov: float, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Bead positions (B, 2; nm) and photons (B,) of each layout on a ``fov`` nm square."""

    def grid(k: int, spacing: float) -> np.ndarray:
        g = (np.arange(k) - (k - 1) / 2) * spacing + fov / 2
        return np.array([(x, y) for y in g for x in g]) + rng.uniform(-40, 40, (k * k, 2))

    c = fov / 2
    edges = [[700, 700], [fov - 900, 800], [800, fov - 700], [fov - 700, fov - 900], [c, c]]
    out = {
        "grid 3x3, 6 um": grid(3, 6000.0),
        "one bead": np.array([[c + 17, c - 23]]),
        "two beads, 4 um": np.array([[c - 2000, c], [c + 2000, c + 50]]),
        "grid 4x4, 3.5 um": grid(4, 3500.0),
        "30 at random": rng.uniform(1500, fov - 1500, (30, 2)),
        "near the edges": np.array(edges, dtype=float),
    }
    table = {k: (v, np.full(len(v), BEAD_PHOTONS)) for k, v in out.items()}
    table["grid 3x3, 4k-60k photons"] = (grid(3, 6000.0), rng.uniform(4000, 60000, 9))
    return table


def bead_stack(psf: str, pos, photons, shape, px: float, camera: Camera, path: Path) -> None:
    """Write the bead z-stack of beads ``pos`` (B, 2; nm) of ``photons`` (B,) to ``path``."""
    lo, hi = make_psf(psf).z_range
    wide = make_psf(psf, z_range=(lo - BEAD_MARGIN, hi + BEAD_MARGIN))
    planes = np.arange(lo - BEAD_MARGIN, hi + BEAD_MARGIN + 1e-6, BEAD_STEP)
    scene = bead_scan_truth(pos, planes, BEAD_PHOTONS)
    scene["photons"] = np.tile(np.asarray(photons, float), planes.size)
    sim = simulate(wide, scene=scene, n_frames=planes.size, shape=shape, pixel_size=px,
                   background=BACKGROUND, camera=camera, seed=1)  # fmt: skip
    tifffile.imwrite(path, sim.movie)


def movie(psf: str, frames: int, n: int, px: float, camera: Camera, path: Path) -> Path:
    """Simulate the movie to localize; returns its path (the truth beside it)."""
    sim = simulate(make_psf(psf), scene="uniform", n_frames=frames, shape=(n, n), pixel_size=px,
                   density=DENSITY, photons=PHOTONS, background=BACKGROUND, camera=camera,
                   seed=2)  # fmt: skip
    return write_simulation(sim, path)[0]


def run(argv: list[str], log: Path) -> tuple[int, str]:
    """``sparseloc ARGV`` in a subprocess; its exit code and its last line."""
    p = subprocess.run(["sparseloc", *argv], capture_output=True, text=True)
    text = p.stdout + p.stderr
    log.write_text(text)
    lines = [ln for ln in text.splitlines() if ln.strip() and "Warning" not in ln]
    return p.returncode, lines[-1] if lines else ""


def case(beads: Path, mv: Path, px: float, flags: list[str], folder: Path) -> dict:
    """Calibrate from ``beads``, localize ``mv`` with it, score: one row."""
    cal = folder / "cal.h5"
    px_flag = ["--pixel-size", f"{px:g}", *flags, "--overwrite"]
    rc, last = run(
        ["calibrate", str(beads), "-o", str(cal), "--z-step", f"{BEAD_STEP:g}", *px_flag],
        folder / "cal.log",
    )
    row: dict = {"calibrate": "ok" if rc == 0 else last.removeprefix("error: ")[:90]}
    if rc != 0:
        return row
    info = read_calibration_info(cal)
    row["beads used"] = f"{info['params']['n_beads_used']} of {info['params']['n_beads_found']}"
    row["model error %"] = round(100 * float(info["model_error"]), 1)
    out = folder / "locs.parquet"
    t0 = time.perf_counter()
    rc, last = run(
        ["localize", str(mv), "-o", str(out), "--psf", str(cal), "--workers", "1", *px_flag],
        folder / "loc.log",
    )
    if rc != 0:
        row["localize"] = last[:90]
        return row
    ev = evaluate(pd.read_parquet(out), pd.read_csv(mv.with_name(mv.stem + "_truth.csv")))
    check = [ln for ln in (folder / "loc.log").read_text().splitlines() if "model check" in ln]
    row.update(
        jaccard=round(ev.jaccard, 1),
        recall=round(ev.recall, 3),
        precision=round(ev.precision, 3),
        rmse_lat=round(ev.rmse_lateral, 1),
        rmse_ax=round(ev.rmse_axial, 1),
        bias_x=round(ev.bias_x, 1),
        bias_y=round(ev.bias_y, 1),
        model_check=check[0].split(",")[0].removeprefix("model check: ") if check else "",
        localize_s=round(time.perf_counter() - t0, 1),
    )
    return row


def sweep_layouts(args) -> list[dict]:
    px, fov = args.pixel_size, 25600.0
    n = round(fov / px)
    camera, flags = CAMERAS["ideal"]
    mv = movie(args.psf, 30, round(12800 / px), px, camera, args.work / "movie.tif")
    rows = []
    for name, (pos, photons) in layouts(fov, np.random.default_rng(5)).items():
        folder = args.work / name.replace(" ", "_").replace(",", "")
        folder.mkdir(parents=True, exist_ok=True)
        bead_stack(args.psf, pos, photons, (n, n), px, camera, folder / "beads.tif")
        rows.append({"layout": name, "beads": len(pos), **case(folder / "beads.tif", mv, px,
                                                                flags, folder)})  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def sweep_optics(args) -> list[dict]:
    rows = []
    for psf in args.psfs.split(","):
        for px in (float(v) for v in args.pixel_sizes.split(",")):
            n = round(12800 / px)
            g = np.array([2500.0, 6400.0, 10300.0])
            pos = np.array([(x, y) for y in g for x in g])
            pos = pos + np.random.default_rng(1).uniform(-50, 50, pos.shape)
            for cam in args.cameras.split(","):
                camera, flags = CAMERAS[cam]
                folder = args.work / f"{psf}_{int(px)}_{cam}"
                folder.mkdir(parents=True, exist_ok=True)
                bead_stack(psf, pos, np.full(len(pos), args.bead_photons), (n, n), px, camera,
                           folder / "beads.tif")  # fmt: skip
                mv = movie(psf, 40, n, px, camera, folder / "movie.tif")
                row = {"psf": psf, "pixel nm": px, "camera": cam, "bead photons": args.bead_photons}
                rows.append({**row, **case(folder / "beads.tif", mv, px, flags, folder)})
                print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    global BEAD_MARGIN, BEAD_STEP  # the scan's shape, read by bead_stack and case
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sweep", choices=["layouts", "optics"])
    ap.add_argument("--psf", default="dh", help="layouts: the PSF (dh, astig)")
    ap.add_argument("--psfs", default="astig,dh", help="optics: the PSFs")
    ap.add_argument("--pixel-size", type=float, default=100.0, help="layouts: nm")
    ap.add_argument("--pixel-sizes", default="65,100,160", help="optics: nm")
    ap.add_argument("--cameras", default=",".join(CAMERAS), help="optics: " + ", ".join(CAMERAS))
    ap.add_argument(
        "--bead-photons", type=float, default=BEAD_PHOTONS, help="optics: each bead's photons"
    )
    ap.add_argument(
        "--bead-margin", type=float, default=BEAD_MARGIN, help="nm the scan reaches past the PSF's"
    )
    ap.add_argument("--bead-step", type=float, default=BEAD_STEP, help="the scan's step (nm)")
    ap.add_argument("--work", type=Path, required=True, help="folder for stacks and movies")
    ap.add_argument("--out", type=Path, default=None, help="JSON (default: WORK/SWEEP.json)")
    args = ap.parse_args(argv)
    BEAD_MARGIN, BEAD_STEP = args.bead_margin, args.bead_step
    args.work.mkdir(parents=True, exist_ok=True)
    rows = sweep_layouts(args) if args.sweep == "layouts" else sweep_optics(args)
    table = pd.DataFrame(rows)
    with pd.option_context("display.width", 250, "display.max_columns", 30):
        print(table.to_string(index=False))
    out = args.out or args.work / f"{args.sweep}.json"
    out.write_text(json.dumps(rows, indent=2, default=str))
    print(f"wrote {out}")
    return rows


if __name__ == "__main__":
    main()
