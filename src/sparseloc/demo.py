"""The ``sparseloc demo`` job: the main job on simulated data, no input needed.

It simulates a blinking 3D double-helix filament movie at high density (every emitter's image
overlaps its neighbours'), localizes it with the default pipeline, scores the result against
the simulation's ground truth, and writes the table, a rendered image beside the truth, the
first frame with both marked, a short text report and the HTML report.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["DEMO_FILES", "run_demo"]

#: The files the demo writes into its folder.
DEMO_FILES = (
    "movie.tif",
    "movie_truth.csv",
    "locs.parquet",
    "render.png",
    "frame0.png",
    "psf.png",
    "report.txt",
    "report.html",
)


def _overlap_fraction(truth, radius_nm: float) -> float:
    """Fraction of emitters with another emitter of the same frame within ``radius_nm``."""
    from scipy.spatial import cKDTree

    n_close = 0
    for _, df in truth.groupby("frame"):
        if len(df) < 2:
            continue
        tree = cKDTree(df[["x_nm", "y_nm"]].to_numpy())
        d, _ = tree.query(df[["x_nm", "y_nm"]].to_numpy(), k=2)
        n_close += int(np.sum(d[:, 1] < radius_nm))
    return n_close / max(len(truth), 1)


def run_demo(
    out_dir: str | Path,
    *,
    seed: int = 0,
    n_frames: int = 200,
    shape: tuple[int, int] = (64, 64),
    pixel_size: float = 100.0,
    density: float = 0.5,
    z_range: tuple[float, float] = (-600.0, 600.0),
    progress: bool = False,
    workers: int | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Simulate, localize, evaluate and render a dense double-helix filament movie.

    Parameters
    ----------
    out_dir : path
        Output folder (created if missing; its parent must exist).
    seed : int
        Random seed of the simulation.
    n_frames, shape, pixel_size : int, (int, int), float
        Movie length, frame shape (pixels) and pixel size (nm).
    density : float
        Mean active emitters per um^2 per frame.
    z_range : (float, float)
        Axial range of the filaments (nm).
    progress : bool
        Show progress bars.
    workers : int, optional
        Processes solving frames; default the machine's cores, at most 2 (the demo's frames
        are small, more processes gain little).
    overwrite : bool
        Replace the files of an earlier demo in ``out_dir`` instead of refusing.

    Returns
    -------
    dict
        ``files`` (paths written), ``text`` (the report), ``evaluation`` (the
        :class:`~sparseloc.evaluate.Evaluation` as a dict), ``seconds`` (per step) and the
        counts behind the report.

    Raises
    ------
    ValueError
        If ``out_dir`` is a file, its parent folder is missing, or it holds an earlier demo's
        files and ``overwrite`` is false. Nothing is written then, nor when a step fails: the
        files are made in a temporary folder beside ``out_dir`` and moved in at the end.
    """
    from .evaluate import evaluate
    from .psf import make_psf
    from .simulate import write_simulation

    setup = _Setup(n_frames, shape, pixel_size, density, z_range)
    out = _output_folder(out_dir, overwrite)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    files: list[Path] = []
    seconds: dict[str, float] = {}
    try:
        t0 = time.perf_counter()
        dh = make_psf("dh")
        sim = _simulate(dh, setup, seed, progress)
        files.extend(write_simulation(sim, work / "movie.tif"))
        seconds["simulate"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        frames = sim.movie.astype(np.float64) - sim.camera.offset  # ideal camera: gain 1
        res = _localize(frames, dh, pixel_size, n_frames, progress, workers)
        seconds["localize"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        log.info("scoring, rendering and writing the report")
        ev = evaluate(res.table, sim.truth)
        files.extend(_write_results(work, out, res, sim, frames, dh, setup))
        stats = _truth_stats(sim.truth, dh, pixel_size)
        seconds["evaluate and write"] = time.perf_counter() - t0

        text = "\n".join(_report_lines(setup, sim, res, ev, stats, seconds))
        files.append(_write_report(work, text))
        files.append(_write_html_report(work, res, sim, pixel_size))
        out.mkdir(exist_ok=True)
        for f in files:
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {
        "files": [str(out / f.name) for f in files],
        "text": text,
        "evaluation": asdict(ev),
        "seconds": seconds,
        "n_emitters": len(sim.truth),
        "n_localizations": len(res.table),
        "overlap_fraction": stats["overlap"],
    }


class _Setup(NamedTuple):
    """The simulated movie: frames, frame shape (px), pixel size (nm), emitters per um^2
    per frame, axial range of the filaments (nm)."""

    n_frames: int
    shape: tuple[int, int]
    pixel_size: float
    density: float
    z_range: tuple[float, float]


def _output_folder(out_dir: str | Path, overwrite: bool) -> Path:
    """The output folder, checked: its parent exists, it is not a file, and it holds no
    earlier demo's files unless ``overwrite`` (it is created at the end)."""
    out = Path(out_dir)
    if not out.parent.is_dir():
        raise ValueError(f"the folder {str(out.parent)!r} does not exist")
    if out.exists() and not out.is_dir():
        raise ValueError(f"{str(out)!r} is a file; the demo writes a folder of files")
    old = [name for name in DEMO_FILES if (out / name).exists()]
    if old and not overwrite:
        raise ValueError(
            f"{str(out)!r} holds the files of an earlier demo ({', '.join(old)}); pass "
            "--overwrite to replace them or choose another folder"
        )
    return out


def _simulate(dh: Any, setup: _Setup, seed: int, progress: bool) -> Any:
    """The demo's movie: blinking filaments whose brightness varies about 1000-5000 photons
    (the filament scene's own spread), background 10 photons/px."""
    from .simulate import simulate

    log.info(
        "simulating %d frames of %dx%d px at %.2f emitters/um^2",
        setup.n_frames,
        *setup.shape,
        setup.density,
    )
    return simulate(
        dh,
        scene="filament",
        n_frames=setup.n_frames,
        shape=setup.shape,
        pixel_size=setup.pixel_size,
        density=setup.density,
        z_range=setup.z_range,
        photons=(1000.0, 5000.0),
        background=10.0,
        seed=seed,
        progress=progress,
    )


def _localize(
    frames: np.ndarray,
    dh: Any,
    pixel_size: float,
    n_frames: int,
    progress: bool,
    workers: int | None,
) -> Any:
    """The default pipeline on the frames (photons), with progress if asked (a bar on a
    terminal, else lines: :class:`sparseloc.progress.Progress`); default ``workers`` the
    machine's cores, at most 2."""
    from .pipeline import LocalizeParams, localize

    if workers is None:
        from .pool import available_cores

        workers = min(2, available_cores())

    params = LocalizeParams(pixel_size=pixel_size)
    log.info("localizing %d frames on %d process(es)", n_frames, workers)
    if not progress:
        return localize(frames, dh, params, workers=workers)
    from .progress import Progress

    with Progress(n_frames) as bar:
        return localize(frames, dh, params, progress=bar.update, workers=workers)


def _write_results(
    out: Path, final: Path, res: Any, sim: Any, frames: np.ndarray, dh: Any, setup: _Setup
) -> list[Path]:
    """The table, the rendering beside the truth, frame 0 with both marked, the PSF montage,
    written into ``out``; the table's metadata names the movie in the ``final`` folder."""
    from .io.tables import write_table
    from .plotting import plot_psf_montage, plot_scene
    from .render import plot_projections

    n_frames, pixel_size, density = setup.n_frames, setup.pixel_size, setup.density
    meta = {**res.metadata, "movie": str(final / "movie.tif"), "camera": sim.camera.to_dict()}
    files = [
        write_table(
            res.table,
            out / "locs.parquet",
            pixel_size=pixel_size,
            shape=setup.shape,
            n_frames=n_frames,
            metadata=meta,
        ),
        plot_projections(
            res.table,
            out / "render.png",
            truth=sim.truth,
            z_range=setup.z_range,
            title=f"double-helix filaments, {n_frames} frames at {density:g} emitters/um^2",
        ),
    ]
    f0 = res.table[res.table["frame"] == 0]
    truth0 = sim.truth[sim.truth["frame"] == 0]
    files.append(
        plot_scene(
            frames[0],
            truth0,
            pixel_size,
            out / "frame0.png",
            locs=f0,
            title=f"frame 0: {len(truth0)} emitters (circles), {len(f0)} localizations (+)",
        )
    )
    files.append(plot_psf_montage([dh], pixel_size, out / "psf.png", n_planes=9))
    return files


def _truth_stats(truth: Any, dh: Any, pixel_size: float) -> dict[str, Any]:
    """The CRLB (x, y, z nm) of an isolated emitter at z = 0 with 2000 photons, and the
    fraction of emitters with a neighbour within the radius holding half of a PSF's light."""
    from .crlb import crlb_single

    zc = np.array([0.0])
    bound = crlb_single(dh, zc, photons=2000.0, background=10.0, pixel_size=pixel_size)[0]
    overlap = _overlap_fraction(truth, dh.support_radius(pixel_size, fraction=0.5))
    return {"crlb": bound, "overlap": overlap}


def _report_lines(
    setup: _Setup, sim: Any, res: Any, ev: Any, stats: dict[str, Any], seconds: dict[str, float]
) -> list[str]:
    """The text report, a line per fact."""
    n_frames, shape, pixel_size, density, z_range = setup
    per_frame = len(sim.truth) / n_frames
    bound, overlap = stats["crlb"], stats["overlap"]
    ph = sim.truth["photons"]  # the scene's own brightness, not the nominal 1000-5000
    return [
        "sparseloc demo",
        f"movie: {n_frames} frames of {shape[0]}x{shape[1]} px ({pixel_size:.0f} nm), "
        f"double-helix pupil model, blinking filaments at z {z_range[0]:.0f}..{z_range[1]:.0f}"
        " nm",
        f"  {len(sim.truth)} emitters ({per_frame:.1f} per frame, {density:g} per um^2); "
        f"{100 * overlap:.0f} % have a neighbour within the radius holding half of a PSF's light",
        f"  photons {ph.min():.0f}-{ph.max():.0f} (5-95 % {ph.quantile(0.05):.0f}-"
        f"{ph.quantile(0.95):.0f}, median {ph.median():.0f}), background 10 photons/px, "
        "Poisson noise",
        f"localize: {res.summary()}",
        f"evaluate (pairs within 250 nm laterally and 500 nm axially): Jaccard "
        f"{ev.jaccard:.1f} %, recall {ev.recall:.3f}, precision {ev.precision:.3f}",
        f"  RMSE lateral {ev.rmse_lateral:.1f} nm, axial {ev.rmse_axial:.1f} nm "
        f"(x {ev.rmse_x:.1f}, y {ev.rmse_y:.1f}); efficiency lateral "
        f"{ev.efficiency_lateral:.1f} %, axial {ev.efficiency_axial:.1f} %",
        f"  CRLB of an isolated emitter at z = 0, 2000 photons: x {bound[0]:.1f} nm, "
        f"y {bound[1]:.1f} nm, z {bound[2]:.1f} nm",
        "time: " + ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items()),
    ]


def _write_report(out: Path, text: str) -> Path:
    """``report.txt`` in ``out``, written atomically."""
    from .io.atomic import atomic_path

    path = out / "report.txt"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text + "\n", encoding="utf-8")
    return path


def _write_html_report(out: Path, res: Any, sim: Any, pixel_size: float) -> Path:
    """``report.html`` in ``out``: the one-page report of ``sparseloc report`` with the
    evaluation against the truth and an overlay of frame 0 (``movie.tif`` in ``out``)."""
    from .report import write_report

    return write_report(
        res.table,
        out / "report.html",
        truth=sim.truth,
        metadata=res.metadata,
        title="sparseloc demo",
        movie=out / "movie.tif",
        pixel_size=pixel_size,
    )
