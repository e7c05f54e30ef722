"""SMAPpy and sparseloc side by side on the same simulated movies (issue 26).

For each PSF (the built-in astigmatic and double-helix pupil models) one bead z-stack is
simulated (3 x 3 beads, 20,000 photons, background 10, 20 nm steps over the PSF's z range and
200 nm beyond it each way) and calibrated by each program's own calibration command
(``sparseloc calibrate``; ``smappy-calibrate``; where that finds no isolated bead, as on the
double-helix stack, SMAPpy's calibration runs again through its API with a wider
bead-detection filter, and the output says so). Movies of 128 x 128 px of 100 nm are simulated
at each density (uniform scene, 1000-5000 photons, background 10 photons/pixel, z over the PSF's
range, ideal camera: Poisson, offset 100 ADU, 1 e-/ADU) and localized by each program's
command-line fit (``sparseloc localize``; ``smappy-fit``) with the camera given as simulated and
everything else at its defaults. Both tables are scored against the truth with
:func:`sparseloc.evaluate.evaluate` (3D, 250 nm lateral and 500 nm axial tolerance).

SMAPpy (PyPI ``smappy-smlm``, needs Python >= 3.12) runs in its own virtual environment, by
default ``benchmarks/.smappy-venv``, created when missing; where it does not install the
SMAPpy half is skipped with a message and the sparseloc half still runs. Each command runs in a
subprocess through a small driver that times the command's own entry point after its imports
("fit s") and the parent times the whole subprocess ("end-to-end s"). One warm-up run on the
first two frames of the first movie of each PSF (untimed) goes before the timed runs of both.

Conventions applied to SMAPpy's table before scoring (both from its documentation and code):
positions in its table are ``pixel * pixel size`` with 0 at the centre of the first pixel, the
truth's origin is the outer corner of that pixel, so half a pixel is added to x and y; its
calibration reads a bead stack's frames as increasing objective positions and reports
``emitter z = -(frame - z0) * dz``, while the simulated stack's frame k holds the beads at
emitter z = z_first + k * dz (the truth's z grows with the frame), so its z is negated.
Frames are 0-based in both.

Usage::

    python benchmarks/smappy_side_by_side.py [--frames 1000] [--psfs astig,dh]
        [--densities 0.05,0.5] [--workers 2] [--sparseloc-args "..."]
        [--smappy-python PATH] [--work DIR] [--size 128]
        [--out benchmarks/results/smappy_side_by_side.json]
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tifffile

from sparseloc.evaluate import evaluate
from sparseloc.psf import make_psf
from sparseloc.simulate import bead_scan_truth, simulate, write_simulation

HERE = Path(__file__).resolve().parent
DEFAULT_VENV = HERE / ".smappy-venv"
SMAPPY_SPEC = "smappy-smlm==0.5.5"

PX = 100.0  # nm per pixel
SHAPE = (128, 128)
PHOTONS = (1000.0, 5000.0)
BACKGROUND = 10.0  # photons per pixel
OFFSET, GAIN = 100.0, 1.0  # the simulated camera: ADU offset, e-/ADU
BEAD_PHOTONS = 20000.0
BEAD_STEP = 20.0  # nm
BEAD_MARGIN = 200.0  # nm of stack beyond the PSF's z range, each way
BEAD_GRID_PX = (24.0, 64.0, 104.0)
LATERAL_TOL, AXIAL_TOL = 250.0, 500.0
WARMUP_FRAMES = 2
SMAPPY_FALLBACK_DETECTION_SIGMA = 4.0  # px; its default is 2

#: Run a console-script entry point ("module:function") with the given argv, timing its imports
#: and the call separately; writes the times as JSON. Run with either program's Python.
DRIVER = """\
import importlib, json, sys, time
out, target, prog = sys.argv[1], sys.argv[2], sys.argv[3]
t0 = time.perf_counter()
module, func = target.split(":")
entry = getattr(importlib.import_module(module), func)
t1 = time.perf_counter()
sys.argv = [prog] + sys.argv[4:]
code = 0
try:
    entry()
except SystemExit as exc:
    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
t2 = time.perf_counter()
with open(out, "w") as f:
    json.dump({"import_s": t1 - t0, "run_s": t2 - t1, "exit": code}, f)
sys.exit(code)
"""

#: SMAPpy's HDF5 table to CSV (frame, x_nm, y_nm, z_nm, photons), with SMAPpy's own reader.
SMAPPY_TO_CSV = """\
import sys
import numpy as np
from smappy.io.hdf5 import load_localizations
locs = load_localizations(sys.argv[1])
cols = ["frame", "x_nm", "y_nm", "z_nm", "photons"]
data = np.column_stack([np.asarray(locs[c], dtype=float) for c in cols]) if len(locs) else \
    np.zeros((0, 5))
np.savetxt(sys.argv[2], data, delimiter=",", header=",".join(cols), comments="", fmt="%.6g")
"""


#: SMAPpy's calibration through its API, as ``smappy-calibrate PATH --out OUT --dz DZ`` does it
#: (same defaults: bead box 27 px, z smoothing 20 nm) but with the bead-detection sigma given.
SMAPPY_CAL_API = """\
import argparse


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("path")
    ap.add_argument("--out")
    ap.add_argument("--dz", type=float)
    ap.add_argument("--detection-sigma", type=float)
    a = ap.parse_args()
    from smappy.calibrate import CalibrationSettings, calibrate
    settings = CalibrationSettings(dz_nm=a.dz, detection_sigma_px=a.detection_sigma)
    result = calibrate([a.path], settings, progress=print)
    result.save(a.out)
    print(f"Saved {a.out}: {result.accepted.sum()} accepted beads")
"""


# --------------------------------------------------------------------------------------------
# SMAPpy's environment
# --------------------------------------------------------------------------------------------
def _python_version(exe: str) -> tuple[int, int] | None:
    try:
        out = subprocess.run(
            [exe, "-c", "import sys; print(sys.version_info[0], sys.version_info[1])"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    major, minor = out.stdout.split()
    return int(major), int(minor)


def find_base_python(given: str | None) -> str | None:
    """A Python >= 3.12 to make SMAPpy's venv with (smappy-smlm 0.5.x requires it)."""
    if given:
        return given
    candidates = [sys.executable]
    for name in ("python3.14", "python3.13", "python3.12", "python3"):
        found = shutil.which(name)
        if found:
            candidates.append(found)
    candidates += sorted(glob.glob(os.path.expanduser("~/.pyenv/versions/3.1[2-9]*/bin/python3")))
    for exe in candidates:
        v = _python_version(exe)
        if v is not None and v >= (3, 12):
            return exe
    return None


def smappy_version(python: str) -> str | None:
    out = subprocess.run(
        [
            python,
            "-c",
            "import importlib.metadata as m, smappy; print(m.version('smappy-smlm'))",
        ],
        capture_output=True,
        text=True,
        env=_smappy_env(),
    )
    return out.stdout.strip() if out.returncode == 0 else None


def ensure_smappy(args: argparse.Namespace) -> tuple[str | None, str]:
    """(python, version) of a working SMAPpy, or (None, why not)."""
    if args.no_smappy:
        return None, "--no-smappy given"
    python = Path(args.smappy_python) if args.smappy_python else DEFAULT_VENV / "bin" / "python"
    if python.exists():
        version = smappy_version(str(python))
        if version:
            return str(python), version
        if args.smappy_python:
            return None, f"{python} cannot import smappy"
    elif args.smappy_python:
        return None, f"{python} does not exist"
    venv = python.parent.parent
    base = find_base_python(args.base_python)
    if base is None:
        return None, "no Python >= 3.12 found to make its venv (give --base-python)"
    print(f"making SMAPpy's venv {venv} with {base} and installing {args.smappy_spec} ...")
    try:
        subprocess.run([base, "-m", "venv", str(venv)], check=True, capture_output=True)
        pip = subprocess.run(
            [str(python), "-m", "pip", "install", "--quiet", args.smappy_spec],
            capture_output=True,
            text=True,
        )
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"could not make the venv ({exc})"
    if pip.returncode != 0:
        lines = [ln for ln in (pip.stderr or pip.stdout).splitlines() if ln.strip()]
        return None, f"pip install {args.smappy_spec} failed: {lines[-1] if lines else '?'}"
    version = smappy_version(str(python))
    if not version:
        return None, "installed, but smappy does not import"
    return str(python), version


def _smappy_env() -> dict:
    env = dict(os.environ)
    env.setdefault("QT_QPA_PLATFORM", "offscreen")  # no window is opened; Qt must not need one
    env.setdefault("MPLBACKEND", "Agg")
    return env


# --------------------------------------------------------------------------------------------
# Running commands
# --------------------------------------------------------------------------------------------
def run_timed(
    python: str, target: str, prog: str, argv: list[str], work: Path, log: Path, env=None
) -> dict:
    """Run ``prog argv`` (entry point ``target``) with ``python`` through the driver; times."""
    driver = work / "driver.py"
    if not driver.exists():
        driver.write_text(DRIVER)
    times = work / "times.json"
    times.unlink(missing_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        proc = subprocess.run(
            [python, str(driver), str(times), target, prog, *argv],
            stdout=f,
            stderr=subprocess.STDOUT,
            env=env,
        )
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not times.exists():
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-15:])
        raise RuntimeError(f"{prog} failed (exit {proc.returncode}); log {log}:\n{tail}")
    out = json.loads(times.read_text())
    out["wall_s"] = wall
    return out


def camera_flags_sparseloc() -> list[str]:
    return ["--pixel-size", f"{PX:g}", "--offset", f"{OFFSET:g}", "--gain", f"{GAIN:g}"]


def camera_flags_smappy() -> list[str]:
    return [
        "--pixelsize",
        f"{PX / 1000:g}",
        "--offset",
        f"{OFFSET:g}",
        "--conversion",
        f"{GAIN:g}",
        "--no-em",
    ]


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------
def make_bead_stack(psf: str, folder: Path, seed: int) -> dict:
    """Simulate the bead z-stack of ``psf`` and write it as ``beads.tif`` (uint16 ADU)."""
    lo, hi = make_psf(psf).z_range
    wide = make_psf(psf, z_range=(lo - BEAD_MARGIN, hi + BEAD_MARGIN))
    planes = np.arange(lo - BEAD_MARGIN, hi + BEAD_MARGIN + 1e-6, BEAD_STEP)
    rng = np.random.default_rng([seed, 1])
    grid = np.array([(x, y) for y in BEAD_GRID_PX for x in BEAD_GRID_PX]) * PX + PX / 2
    pos = grid + rng.uniform(-PX / 2, PX / 2, grid.shape)
    sim = simulate(
        wide,
        scene=bead_scan_truth(pos, planes, BEAD_PHOTONS),
        n_frames=planes.size,
        shape=SHAPE,
        pixel_size=PX,
        background=BACKGROUND,
        seed=seed,
    )
    path = folder / "beads.tif"
    tifffile.imwrite(path, sim.movie)
    return {
        "path": path,
        "planes": planes.size,
        "z_nm": [float(planes[0]), float(planes[-1])],
        "beads": len(pos),
    }


def make_movie(
    psf: str, density: float, frames: int, folder: Path, seed: int, shape: tuple = SHAPE
) -> Path:
    sim = simulate(
        make_psf(psf),
        scene="uniform",
        n_frames=frames,
        shape=shape,
        pixel_size=PX,
        density=density,
        photons=PHOTONS,
        background=BACKGROUND,
        seed=seed,
    )
    path, _ = write_simulation(sim, folder / "movie.tif")
    return path


def read_truth(movie: Path) -> pd.DataFrame:
    return pd.read_csv(movie.with_name(movie.stem + "_truth.csv"))


# --------------------------------------------------------------------------------------------
# The two programs
# --------------------------------------------------------------------------------------------
def sparseloc_calibrate(beads: Path, folder: Path) -> tuple[Path, dict]:
    cal = folder / "sparseloc_cal.h5"
    argv = [
        "calibrate",
        str(beads),
        "-o",
        str(cal),
        "--z-step",
        f"{BEAD_STEP:g}",
        *camera_flags_sparseloc(),
        "--overwrite",
    ]
    t = run_timed(
        sys.executable, "sparseloc.cli:main", "sparseloc", argv, folder, folder / "sl_cal.log"
    )
    return cal, t


def sparseloc_localize(
    movie: Path, cal: Path, folder: Path, workers: int, extra: list[str], frames: str | None
) -> tuple[pd.DataFrame, dict, list[str]]:
    out = folder / "sparseloc_locs.parquet"
    argv = [
        "localize",
        str(movie),
        "-o",
        str(out),
        "--psf",
        str(cal),
        *camera_flags_sparseloc(),
        "--workers",
        str(workers),
        "--overwrite",
        *(["--frames", frames] if frames else []),
        *extra,
    ]
    t = run_timed(
        sys.executable, "sparseloc.cli:main", "sparseloc", argv, folder, folder / "sl_loc.log"
    )
    return pd.read_parquet(out), t, ["sparseloc", *argv]


def smappy_calibrate(python: str, beads: Path, folder: Path) -> tuple[Path, dict, str]:
    """``smappy-calibrate BEADS --out CAL --dz STEP`` (its defaults otherwise). Where it finds no
    isolated bead -- a double helix's lobes turn round a ring in the stack's maximum projection,
    which its 2 px detection filter splits into several close peaks -- it is run again through
    its Python API with the bead-detection sigma (an advanced setting of its calibration window)
    at ``SMAPPY_FALLBACK_DETECTION_SIGMA`` px, all else as the command's defaults."""
    cal = folder / "smappy_cal.h5"
    log = folder / "smappy_cal.log"
    argv = [str(beads), "--out", str(cal), "--dz", f"{BEAD_STEP:g}"]
    env = _smappy_env()
    try:
        t = run_timed(
            python, "smappy.cli.calibrate:main", "smappy-calibrate", argv, folder, log, env
        )
        return cal, t, "smappy-calibrate (defaults)"
    except RuntimeError as exc:
        if "no isolated beads found" not in str(exc):
            raise
    print(
        "calibration: smappy-calibrate with its defaults found no isolated bead (ValueError: no "
        "isolated beads found); again through its API, smappy.calibrate.calibrate with "
        f"CalibrationSettings(detection_sigma_px={SMAPPY_FALLBACK_DETECTION_SIGMA:g}), the "
        "command's defaults otherwise",
        flush=True,
    )
    (folder / "smappy_cal_api.py").write_text(SMAPPY_CAL_API)
    argv += ["--detection-sigma", f"{SMAPPY_FALLBACK_DETECTION_SIGMA:g}"]
    t = run_timed(python, "smappy_cal_api:main", "smappy_cal_api", argv, folder, log, env)
    return cal, t, f"API, detection_sigma_px={SMAPPY_FALLBACK_DETECTION_SIGMA:g}"


def smappy_fit(
    python: str, movie: Path, cal: Path, folder: Path, frames: int | None
) -> tuple[pd.DataFrame, dict, list[str]]:
    out = folder / "smappy_locs.h5"
    out.unlink(missing_ok=True)
    argv = [
        str(movie),
        str(out),
        "--cal",
        str(cal),
        *camera_flags_smappy(),
        *(["--frames", str(frames)] if frames else []),
    ]
    t = run_timed(
        python,
        "smappy.cli.fit:main",
        "smappy-fit",
        argv,
        folder,
        folder / "smappy_fit.log",
        env=_smappy_env(),
    )
    csv = folder / "smappy_locs.csv"
    subprocess.run([python, "-c", SMAPPY_TO_CSV, str(out), str(csv)], check=True, env=_smappy_env())
    table = pd.read_csv(csv)
    # SMAPpy's conventions to the truth's (module docstring): pixel-centre origin, z sign.
    table["x_nm"] += PX / 2
    table["y_nm"] += PX / 2
    table["z_nm"] = -table["z_nm"]
    return table, t, ["smappy-fit", *argv]


def calibration_summary(log: Path, program: str) -> str:
    """The line of a calibration log that says how many beads were used."""
    for line in log.read_text(errors="replace").splitlines():
        if program == "sparseloc" and " beads used" in line:
            return line.split(";")[0].strip()
        if program == "smappy" and line.startswith("Saved "):
            return line.split(": ", 1)[-1].strip()
    return "?"


# --------------------------------------------------------------------------------------------
# Scoring and printing
# --------------------------------------------------------------------------------------------
def score(table: pd.DataFrame, truth: pd.DataFrame, timing: dict) -> dict:
    ev = evaluate(table, truth, lateral_tol=LATERAL_TOL, axial_tol=AXIAL_TOL)
    n = ev.n_locs  # rows scored: sparseloc's flagged rows are left out, as every consumer does
    return {
        "rows": len(table),
        "localizations": n,
        "fit_s": timing["run_s"],
        "import_s": timing["import_s"],
        "end_to_end_s": timing["wall_s"],
        "locs_per_s": n / timing["run_s"] if timing["run_s"] > 0 else float("nan"),
        "locs_per_s_end_to_end": n / timing["wall_s"],
        "n_truth": ev.n_truth,
        "jaccard": ev.jaccard,
        "recall": ev.recall,
        "precision": ev.precision,
        "rmse_lateral_nm": ev.rmse_lateral,
        "rmse_axial_nm": ev.rmse_axial,
        "bias_x_nm": ev.bias_x,
        "bias_y_nm": ev.bias_y,
        "bias_z_nm": ev.bias_z,
    }


HEADER = (
    f"{'program':<10} {'locs':>6} {'fit s':>7} {'e2e s':>7} {'locs/s':>8} {'e2e/s':>8} | "
    f"{'Jaccard %':>9} {'recall':>6} {'prec':>5} | {'RMSE lat':>8} {'ax nm':>6}"
)


def print_row(name: str, r: dict) -> None:
    print(
        f"{name:<10} {r['localizations']:6d} {r['fit_s']:7.1f} {r['end_to_end_s']:7.1f} "
        f"{r['locs_per_s']:8.1f} {r['locs_per_s_end_to_end']:8.1f} | {r['jaccard']:9.1f} "
        f"{r['recall']:6.3f} {r['precision']:5.3f} | {r['rmse_lateral_nm']:8.1f} "
        f"{r['rmse_axial_nm']:6.1f}",
        flush=True,
    )


# --------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1000, help="frames per movie")
    ap.add_argument("--psfs", default="astig,dh", help="built-in PSFs: astig, dh")
    ap.add_argument("--densities", default="0.05,0.5", help="emitters per um^2")
    ap.add_argument("--workers", type=int, default=2, help="sparseloc localize --workers")
    ap.add_argument(
        "--sparseloc-args", default="", help="extra flags for sparseloc localize (one string)"
    )
    ap.add_argument(
        "--smappy-python",
        default=None,
        help=f"Python of a venv with SMAPpy (default {DEFAULT_VENV}/bin/python, made if missing)",
    )
    ap.add_argument("--base-python", default=None, help="Python >= 3.12 to make that venv with")
    ap.add_argument("--smappy-spec", default=SMAPPY_SPEC, help="what pip installs there")
    ap.add_argument("--no-smappy", action="store_true", help="run the sparseloc half only")
    ap.add_argument("--work", type=Path, default=None, help="folder for movies, calibrations")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--size", type=int, default=SHAPE[0], help="movie frames SIZE x SIZE px (bead stacks stay)"
    )
    ap.add_argument(
        "--out", type=Path, default=HERE / "results" / "smappy_side_by_side.json", help="JSON"
    )
    args = ap.parse_args(argv)
    psfs = [p.strip() for p in args.psfs.split(",") if p.strip()]
    densities = [float(d) for d in args.densities.split(",") if d.strip()]
    extra = shlex.split(args.sparseloc_args)

    smappy_python, smappy_info = ensure_smappy(args)
    if smappy_python is None:
        print(f"SMAPpy skipped: {smappy_info}")
    else:
        print(f"SMAPpy {smappy_info} ({smappy_python})")
    work = args.work or Path(tempfile.mkdtemp(prefix="smappy_side_by_side_"))
    work.mkdir(parents=True, exist_ok=True)
    print(
        f"movies: {args.frames} frames of {args.size}x{args.size} px of {PX:.0f} nm, uniform "
        f"scene, {PHOTONS[0]:.0f}-{PHOTONS[1]:.0f} photons, background {BACKGROUND:g} "
        f"photons/px, ideal camera (Poisson; offset {OFFSET:g} ADU, {GAIN:g} e-/ADU), z over "
        f"the PSF's range; seed {args.seed}\n"
        f"bead stacks: {len(BEAD_GRID_PX) ** 2} beads, {BEAD_PHOTONS:.0f} photons, background "
        f"{BACKGROUND:g}, {BEAD_STEP:g} nm steps over the PSF's range +-{BEAD_MARGIN:.0f} nm\n"
        f"sparseloc: calibrate, then localize --workers {args.workers}"
        + (f" {args.sparseloc_args}" if extra else "")
        + "; SMAPpy: smappy-calibrate --dz, then smappy-fit --cal (threads: its default, one "
        "per core)\nscoring: sparseloc.evaluate.evaluate, 3D, tolerance "
        f"{LATERAL_TOL:.0f} nm lateral, {AXIAL_TOL:.0f} nm axial; 'fit s' is the command's "
        "run after its imports, 'e2e s' the whole process; locs/s = scored localizations / fit s"
        f"\nwork folder: {work}",
        flush=True,
    )
    out: dict = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "smappy": {"python": smappy_python, "version_or_skip_reason": smappy_info},
        "settings": {
            "pixel_nm": PX,
            "shape": [args.size, args.size],
            "photons": list(PHOTONS),
            "background": BACKGROUND,
            "camera_offset_adu": OFFSET,
            "camera_gain_e_per_adu": GAIN,
            "bead_photons": BEAD_PHOTONS,
            "bead_step_nm": BEAD_STEP,
            "lateral_tol_nm": LATERAL_TOL,
            "axial_tol_nm": AXIAL_TOL,
        },
        "cases": [],
    }
    for i, psf in enumerate(psfs):
        folder = work / psf
        folder.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        beads = make_bead_stack(psf, folder, args.seed + 100 * i)
        print(
            f"\n== {psf} == bead stack: {beads['beads']} beads, {beads['planes']} planes, z "
            f"{beads['z_nm'][0]:.0f}..{beads['z_nm'][1]:.0f} nm (simulated in "
            f"{time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        sl_cal, sl_cal_t = sparseloc_calibrate(beads["path"], folder)
        cal_info = {
            "sparseloc": {
                **sl_cal_t,
                "summary": calibration_summary(folder / "sl_cal.log", "sparseloc"),
            }
        }
        print(
            f"calibration: sparseloc {sl_cal_t['run_s']:.1f} s ({sl_cal_t['wall_s']:.1f} s "
            f"end to end): {cal_info['sparseloc']['summary']}",
            flush=True,
        )
        sm_cal = None
        if smappy_python:
            try:
                sm_cal, sm_cal_t, how = smappy_calibrate(smappy_python, beads["path"], folder)
            except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
                why = str(exc).strip().splitlines()[-1]
                print(f"calibration: SMAPpy failed, its half skipped for {psf}: {why}")
                cal_info["smappy"] = {"failed": why}
            else:
                cal_info["smappy"] = {
                    **sm_cal_t,
                    "how": how,
                    "summary": calibration_summary(folder / "smappy_cal.log", "smappy"),
                }
                print(
                    f"calibration: SMAPpy {sm_cal_t['run_s']:.1f} s ({sm_cal_t['wall_s']:.1f} s "
                    f"end to end; {how}): {cal_info['smappy']['summary']}",
                    flush=True,
                )
        run_smappy = sm_cal is not None
        for j, density in enumerate(densities):
            dfolder = folder / f"density_{density:g}"
            dfolder.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            movie = make_movie(
                psf, density, args.frames, dfolder, args.seed + 100 * i + 1 + j,
                (args.size, args.size),
            )  # fmt: skip
            truth = read_truth(movie)
            print(
                f"\n{psf}, {density:g} /um^2: {len(truth)} emitters in {args.frames} frames "
                f"(simulated in {time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
            if j == 0:  # warm-up (compiled-kernel caches, file caches), untimed
                sparseloc_localize(
                    movie, sl_cal, dfolder, args.workers, extra, f"0:{WARMUP_FRAMES}"
                )
                if run_smappy:
                    smappy_fit(smappy_python, movie, sm_cal, dfolder, WARMUP_FRAMES)
            case = {"psf": psf, "density": density, "frames": args.frames}
            case["calibration"] = cal_info
            print(HEADER)
            print("-" * len(HEADER))
            if run_smappy:
                table, t, cmd = smappy_fit(smappy_python, movie, sm_cal, dfolder, None)
                case["smappy"] = score(table, truth, t) | {"command": cmd}
                print_row("SMAPpy", case["smappy"])
            table, t, cmd = sparseloc_localize(movie, sl_cal, dfolder, args.workers, extra, None)
            case["sparseloc"] = score(table, truth, t) | {"command": cmd}
            print_row("sparseloc", case["sparseloc"])
            if run_smappy:
                a, b = case["sparseloc"], case["smappy"]
                case["ratio_locs_per_s"] = a["locs_per_s"] / b["locs_per_s"]
                case["ratio_locs_per_s_end_to_end"] = (
                    a["locs_per_s_end_to_end"] / b["locs_per_s_end_to_end"]
                )
                print(
                    f"ratio sparseloc/SMAPpy, localizations/s: {case['ratio_locs_per_s']:.3f} "
                    f"(fit), {case['ratio_locs_per_s_end_to_end']:.3f} (end to end)",
                    flush=True,
                )
            out["cases"].append(case)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2, default=str))
    print(f"\nwrote {args.out}")
    return out


if __name__ == "__main__":
    main()
