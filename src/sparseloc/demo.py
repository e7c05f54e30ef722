"""The ``sparseloc demo`` job: real work on simulated data, no input needed.

At this stage of the project it simulates a dense double-helix scene with ground truth, draws
the PSF models and the scene, and computes the Cramer-Rao bound of the model over z. Later
stages extend it to localize, evaluate and render.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["run_demo"]


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
    n_frames: int = 5,
    shape: tuple[int, int] = (64, 64),
    pixel_size: float = 100.0,
    density: float = 1.0,
    progress: bool = False,
) -> dict[str, Any]:
    """Simulate a dense double-helix scene and write pictures of the models and the scene.

    Parameters
    ----------
    out_dir : path
        Output folder (created if missing; its parent must exist).
    seed : int
        Random seed of the simulation.
    n_frames, shape, pixel_size, density
        Movie length, frame shape (pixels), pixel size (nm) and emitters per um^2.
    progress : bool
        Show progress bars.

    Returns
    -------
    dict
        ``files``: paths written; ``text``: a short report of what was computed; and the
        figures behind it.
    """
    from .camera import to_photons
    from .crlb import crlb_single
    from .plotting import plot_crlb, plot_psf_montage, plot_scene
    from .psf import make_psf
    from .simulate import simulate, write_simulation

    out = Path(out_dir)
    if not out.parent.exists():
        raise ValueError(f"the folder {str(out.parent)!r} does not exist")
    out.mkdir(exist_ok=True)
    files: list[Path] = []

    dh = make_psf("dh")
    models = [dh, make_psf("astig"), make_psf("dh-analytic"), make_psf("astig-gauss")]
    files.append(plot_psf_montage(models, pixel_size, out / "psf_models.png", n_planes=9))

    log.info("simulating %d frames of %dx%d px at %.1f emitters/um^2", n_frames, *shape, density)
    sim = simulate(
        dh,
        scene="uniform",
        n_frames=n_frames,
        shape=shape,
        pixel_size=pixel_size,
        density=density,
        photons=(1000.0, 5000.0),
        background=10.0,
        seed=seed,
        progress=progress,
    )
    files.extend(write_simulation(sim, out / "dense_dh_scene.tif"))
    frame0 = to_photons(sim.movie[0], sim.camera)
    truth0 = sim.truth[sim.truth["frame"] == 0]
    files.append(
        plot_scene(
            frame0,
            truth0,
            pixel_size,
            out / "dense_dh_scene.png",
            title=f"frame 0: {len(truth0)} double-helix emitters, truth coloured by z",
        )
    )

    zs = np.linspace(*dh.z_range, 21)
    bound = crlb_single(dh, zs, photons=2000.0, background=10.0, pixel_size=pixel_size)
    files.append(
        plot_crlb(
            zs,
            bound,
            out / "crlb_dh.png",
            title="CRLB, double helix, 2000 photons, 10 photons/px background",
        )
    )

    # Conservatively, two images overlap when their centres are closer than the radius that
    # holds half of an image's photons (about 1.3 um for this double helix).
    solve_text = _demo_solve(dh, out, seed, files)

    overlap = _overlap_fraction(sim.truth, dh.support_radius(pixel_size, fraction=0.5))
    per_frame = len(sim.truth) / n_frames
    i0 = int(np.argmin(np.abs(zs)))
    text = "\n".join(
        [
            f"simulated {n_frames} frames of {shape[0]}x{shape[1]} px "
            f"({pixel_size:.0f} nm pixels), double-helix pupil model, {density:.1f} emitters/um^2",
            f"  emitters: {len(sim.truth)} ({per_frame:.1f} per frame); "
            f"{100 * overlap:.0f} % have a neighbour whose image overlaps theirs",
            f"  photons per emitter: median {sim.truth['photons'].median():.0f}; "
            f"background 10 photons/px",
            f"  CRLB at z = 0, 2000 photons: x {bound[i0, 0]:.1f} nm, y {bound[i0, 1]:.1f} nm, "
            f"z {bound[i0, 2]:.1f} nm; worst over z (x, y, z): "
            f"{bound[:, :3].max(axis=0).round(1).tolist()} nm",
            solve_text,
        ]
    )
    return {
        "files": [str(f) for f in files],
        "text": text,
        "n_emitters": len(sim.truth),
        "overlap_fraction": overlap,
        "crlb": bound.tolist(),
    }


def _demo_solve(model, out: Path, seed: int, files: list) -> str:
    """The paper's Figure 2 case: three overlapping emitters in one 11x11 window, MP+CO+MLE."""
    from scipy.optimize import linear_sum_assignment

    from .dictionary import Dictionary
    from .plotting import plot_solve
    from .solvers import hybrid_solve

    rng = np.random.default_rng(seed)
    w, px, zr = 11, 160.0, (-300.0, 300.0)
    centre = np.array([w * px / 2, w * px / 2, 0.0])
    truth = centre + rng.uniform(-0.5, 0.5, (3, 3)) * np.array([800.0, 800.0, 600.0])
    photons = rng.uniform(1000.0, 1200.0, 3)
    mu = model.render(truth[:, 0], truth[:, 1], truth[:, 2], photons, (w, w), px) + 5.0
    window = rng.poisson(mu).astype(float)
    coarse = Dictionary(model, w, px, 80.0, 120.0, zr)
    fine = Dictionary(model, w, px, 10.0, 15.0, zr)
    sol = hybrid_solve(window, coarse, fine)
    files.append(
        plot_solve(
            window,
            sol,
            out / "hybrid_solve.png",
            pixel_size=px,
            truth=np.column_stack([truth, photons]),
            title="MP+CO+MLE on three overlapping double-helix emitters",
        )
    )
    est = sol.emitters.as_array()
    if len(est):
        d = np.linalg.norm(est[:, None, :3] - truth[None], axis=2)
        r, c = linear_sum_assignment(d)
        err = f"mean 3D error {d[r, c].mean():.0f} nm"
    else:
        err = "nothing found"
    return (
        f"  MP+CO+MLE on one 11x11 window with 3 overlapping emitters ({fine.size:,}-atom fine "
        f"dictionary): found {len(est)}, {err}"
    )
