"""The same frames through whichever sparseloc is imported: compare two versions of the code.

Localizes ``N`` simulated 128 x 128 double-helix frames (``DENSITY`` emitters/um^2, default 1;
seed 3) in one process and prints one JSON line (seconds, localizations, Jaccard, RMSE), with
each checkout's default schedule (``auto`` from commit ef7f001 on, ``whole-frame`` before it:
compare checkouts on one side of that change). Run it once with this checkout and once with an
older one first on the path, back to back::

    git worktree add /tmp/old 633c58a
    PYTHONPATH=/tmp/old/src python benchmarks/speed_before_after.py 4
    python benchmarks/speed_before_after.py 4
    python benchmarks/speed_before_after.py 40 0.05   # N DENSITY: a sparse movie
"""

import json
import sys
import time

import numpy as np

import sparseloc
from sparseloc.evaluate import evaluate
from sparseloc.pipeline import LocalizeParams, localize, work_model_for
from sparseloc.psf import make_psf
from sparseloc.simulate import simulate


def benchmark_frames(n: int, density: float, seed: int = 3, psf: str = "dh"):
    """``n`` simulated 128 x 128 frames of the built-in pupil model ``psf`` (photons; tabulated
    as the pipeline does, 100 nm pixels, 1000-5000 photons, background 10) at ``density``
    emitters per um^2: ``(frames, work model, params, simulation)``, the kernels already
    compiled or loaded by one localized frame (also used by ``phases.py``, ``two_tier.py``)."""
    model = make_psf(psf)
    p = LocalizeParams(pixel_size=100.0)
    work = work_model_for(model, p)
    sim = simulate(
        model,
        scene="uniform",
        n_frames=n,
        shape=(128, 128),
        pixel_size=100.0,
        density=density,
        photons=(1000.0, 5000.0),
        background=10.0,
        seed=seed,
    )
    frames = sim.movie.astype(np.float64) - sim.camera.offset
    localize(frames[:1], work, p)
    return frames, work, p, sim


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 4
    density = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
    frames, work, p, sim = benchmark_frames(n, density)
    t = time.perf_counter()
    r = localize(frames, work, p)
    dt = time.perf_counter() - t
    ev = evaluate(r.table, sim.truth)
    print(
        json.dumps(
            {
                "code": sparseloc.__file__,
                "frames": n,
                "density": density,
                "seconds": dt,
                "locs": len(r.table),
                "locs_per_s": len(r.table) / dt,
                "jaccard": ev.jaccard,
                "rmse_lat": ev.rmse_lateral,
                "rmse_ax": ev.rmse_axial,
            }
        )
    )


if __name__ == "__main__":
    main()
