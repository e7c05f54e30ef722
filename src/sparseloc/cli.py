"""Command line: a thin layer over library calls (design.md section 7).

Bad input ends with one sentence on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="sparseloc: 3D localization of overlapping single molecules by sparse recovery.",
    pretty_exceptions_enable=False,
)

log = logging.getLogger("sparseloc")


class UserError(Exception):
    """A problem with the user's input, reported as one sentence."""


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


def _run(func, *args, **kwargs):
    """Call a library function, turning input errors into one sentence and exit code 2."""
    try:
        return func(*args, **kwargs)
    except (ValueError, UserError, FileNotFoundError, IsADirectoryError, PermissionError) as exc:
        msg = str(exc).strip() or type(exc).__name__
        _fail(msg[0].lower() + msg[1:] if msg else msg)


def _output_path(path: Path) -> Path:
    if not path.parent.exists() and str(path.parent) not in ("", "."):
        _fail(f"the output folder {str(path.parent)!r} does not exist")
    return path


class SceneKind(StrEnum):
    uniform = "uniform"
    clusters = "clusters"
    filaments = "filaments"


class CameraKind(StrEnum):
    ideal = "ideal"
    emccd = "emccd"
    scmos = "scmos"


@app.callback()
def _main(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the demo's outputs.")] = Path(
        "sparseloc_demo"
    ),
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Simulate a dense double-helix scene and write pictures of the models and the scene."""
    from .demo import run_demo

    t0 = time.perf_counter()
    summary = _run(run_demo, out, seed=seed, progress=sys.stderr.isatty())
    typer.echo(summary["text"])
    typer.echo(f"wrote {len(summary['files'])} files to {out} in {time.perf_counter() - t0:.1f} s:")
    for f in summary["files"]:
        typer.echo(f"  {f}")


@app.command()
def simulate(
    output: Annotated[Path, typer.Option("--output", "-o", help="Output movie (.tif).")],
    psf: Annotated[
        str, typer.Option(help="PSF: dh, astig, clear, dh-analytic, astig-gauss, or a mask file.")
    ] = "dh",
    scene: Annotated[SceneKind, typer.Option(help="Scene type.")] = SceneKind.uniform,
    frames: Annotated[int, typer.Option(help="Number of frames.", min=1)] = 10,
    rows: Annotated[int, typer.Option(help="Frame height (pixels).", min=4)] = 64,
    cols: Annotated[int, typer.Option(help="Frame width (pixels).", min=4)] = 64,
    pixel_size: Annotated[float, typer.Option(help="Pixel size in sample space (nm).")] = 100.0,
    density: Annotated[
        float, typer.Option(help="Emitters per um^2 per frame (uniform scene).")
    ] = 1.0,
    photons_min: Annotated[float, typer.Option(help="Lowest photons per emitter.")] = 1000.0,
    photons_max: Annotated[float, typer.Option(help="Highest photons per emitter.")] = 5000.0,
    background: Annotated[float, typer.Option(help="Background (photons/pixel).")] = 10.0,
    z_min: Annotated[
        float | None, typer.Option(help="Lowest z (nm); default: the PSF's range.")
    ] = None,
    z_max: Annotated[
        float | None, typer.Option(help="Highest z (nm); default: the PSF's range.")
    ] = None,
    cluster_size: Annotated[int, typer.Option(help="Emitters per cluster (clusters scene).")] = 3,
    camera: Annotated[CameraKind, typer.Option(help="Camera noise model.")] = CameraKind.ideal,
    offset: Annotated[float, typer.Option(help="Camera offset (ADU).")] = 100.0,
    gain: Annotated[float, typer.Option(help="Conversion gain (e-/ADU).")] = 1.0,
    em_gain: Annotated[float, typer.Option(help="EM gain (EMCCD).")] = 1.0,
    read_noise: Annotated[float, typer.Option(help="Read noise (e- rms, sCMOS).")] = 0.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Simulate a movie with ground truth: writes OUT.tif and OUT_truth.csv."""
    from .camera import Camera
    from .psf import make_psf
    from .simulate import simulate as run_simulation
    from .simulate import write_simulation

    out = _output_path(output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        _fail(f"the output must be a .tif file, got {out.name!r}")
    model = _run(make_psf, psf)
    cam = _run(
        Camera, kind=camera.value, offset=offset, gain=gain, em_gain=em_gain, read_noise=read_noise
    )
    z_range = None
    if z_min is not None or z_max is not None:
        lo, hi = model.z_range
        z_range = (lo if z_min is None else z_min, hi if z_max is None else z_max)
    kwargs = {"k": cluster_size} if scene is SceneKind.clusters else {}
    t0 = time.perf_counter()
    sim = _run(
        run_simulation,
        model,
        scene=scene.value,
        n_frames=frames,
        shape=(rows, cols),
        pixel_size=pixel_size,
        density=density,
        z_range=z_range,
        photons=(photons_min, photons_max),
        background=background,
        camera=cam,
        seed=seed,
        progress=sys.stderr.isatty(),
        **kwargs,
    )
    tif, truth = _run(write_simulation, sim, out)
    typer.echo(
        f"simulated {frames} frames of {rows}x{cols} px with {len(sim.truth)} emitters "
        f"({len(sim.truth) / frames:.1f} per frame) in {time.perf_counter() - t0:.1f} s"
    )
    typer.echo(f"wrote {tif} and {truth}")


@app.command()
def evaluate(
    locs: Annotated[
        Path,
        typer.Argument(
            help="Localizations: Parquet, ThunderSTORM/SMLM/sparseloc CSV or Picasso HDF5."
        ),
    ],
    truth: Annotated[Path, typer.Argument(help="Ground truth CSV written by 'simulate'.")],
    lateral_tol: Annotated[float, typer.Option(help="Lateral match tolerance (nm).")] = 250.0,
    axial_tol: Annotated[float, typer.Option(help="Axial match tolerance (nm).")] = 500.0,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the figures as JSON.")
    ] = None,
) -> None:
    """Match localizations to the truth and print Jaccard, RMSE, bias and efficiency."""
    from .evaluate import evaluate as run_evaluation
    from .io.tables import read_table
    from .io.truth import read_truth_csv

    for p in (locs, truth):
        if not p.is_file():
            _fail(f"{str(p)!r} does not exist or is not a file")
    loc_df = _run(read_table, locs)
    truth_df = _run(read_truth_csv, truth)
    result = _run(run_evaluation, loc_df, truth_df, lateral_tol=lateral_tol, axial_tol=axial_tol)
    typer.echo(result.summary())
    if json_out is not None:
        from .io.atomic import write_text_atomic

        _output_path(json_out)
        write_text_atomic(json_out, json.dumps(result.as_dict(), indent=2))


def main() -> None:
    """Entry point of the ``sparseloc`` command."""
    app()


if __name__ == "__main__":
    main()
