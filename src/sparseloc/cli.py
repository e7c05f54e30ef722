"""Command line: a thin layer over library calls (design.md section 7).

Bad input ends with one sentence on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import json
import logging
import re
import sys
import time
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.markup import escape
from typer.core import TyperArgument, TyperCommand, TyperGroup

from .options import LOCALIZE_DEFAULTS as _D
from .units import TOLERANCE_RANGE_NM, check_length_nm, check_pixel_size, check_z_limits

#: ``sparseloc --help`` lists the commands in the order of a day's work, not of definition.
WORKFLOW_ORDER = (
    "demo",
    "simulate",
    "calibrate",
    "camera",
    "localize",
    "evaluate",
    "filter",
    "drift",
    "render",
    "overlay",
    "report",
)


def _one_line(text: str) -> str:
    """The first paragraph of a docstring on one line (rich keeps single line breaks)."""
    return " ".join(text.strip().split("\n\n")[0].split())


def _reflowed(text: str) -> str:
    """A docstring's paragraphs each on one line, so that the help wraps them at the
    terminal's width rather than at the source's line ends (rich keeps single line breaks)."""
    return "\n\n".join(" ".join(p.split()) for p in text.strip().split("\n\n"))


def _plain(param: Any) -> Any:
    """``param`` with a plain help entry: an argument named in capitals (``LOCS``) whose type
    reads ``<path>...`` for several files (not ``<list[Path]>``), no type beside a flag (no
    ``<bool>``), and square brackets in the help (TOML tables such as ``[camera]``) kept as
    text rather than read as rich markup. Done once per parameter."""
    if getattr(param, "_sparseloc_plain", False):
        return param
    param._sparseloc_plain = True
    if param.help:
        param.help = escape(param.help)
    if isinstance(param, TyperArgument):
        param.metavar = param.metavar or param.name.upper()
        if hasattr(param, "display_type"):  # typer >= 0.28 labels types, older ones do not
            label = "<path>..." if param.nargs != 1 else param.display_type(None)
            param.display_type_rich = lambda ctx, label=label: label
    elif getattr(param, "is_flag", False):
        param.metavar = ""  # a flag takes no value
    return param


class _Command(TyperCommand):
    """A command whose help shows plain placeholders (see :func:`_plain`) and the usage
    ``[OPTIONS] LOCS TRUTH`` rather than ``[OPTIONS] {locs} {truth}``; ``running`` is the
    context of the command being run (which flags were given: :func:`_in_cli_terms`)."""

    running: Any = None

    def invoke(self, ctx: Any) -> Any:
        _Command.running = ctx
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            # outputs are written under temporary names and renamed at the end: none is left
            typer.echo(
                f"interrupted (Ctrl-C): {ctx.info_name} stopped and wrote no output", err=True
            )
            raise typer.Exit(130) from None
        except MemoryError as exc:
            _NOTES.clear()
            need = re.search(r"allocate ([\d.]+ \w+)", str(exc))  # NumPy says how much
            asked = f" (one array of {need.group(1)} did not fit)" if need else ""
            typer.echo(
                f"error: {ctx.info_name} ran out of memory{asked}: give it less to hold (fewer "
                "frames, a smaller region, larger render pixels) or run it where more memory "
                "is free",
                err=True,
            )
            raise typer.Exit(1) from None
        finally:
            _Command.running = None

    def get_params(self, ctx: Any) -> list[Any]:
        if self.help and not getattr(self, "_sparseloc_plain", False):
            self._sparseloc_plain = True
            self.help = escape(_reflowed(self.help))
        return [_plain(p) for p in super().get_params(ctx)]

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for p in self.get_params(ctx):
            if isinstance(p, TyperArgument):
                pieces.append(p.metavar + ("..." if p.nargs != 1 else ""))
        return pieces


class _Group(TyperGroup):
    """The top-level command: subcommands in :data:`WORKFLOW_ORDER`, each described by its
    docstring's whole first paragraph on one line."""

    def list_commands(self, ctx: Any) -> list[str]:
        names = super().list_commands(ctx)
        rank = {n: i for i, n in enumerate(WORKFLOW_ORDER)}
        return sorted(names, key=lambda n: rank.get(n, len(rank)))

    def get_params(self, ctx: Any) -> list[Any]:
        return [_plain(p) for p in super().get_params(ctx)]

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        cmd = super().get_command(ctx, cmd_name)
        if cmd is not None and cmd.short_help is None and cmd.help:
            cmd.short_help = _one_line(cmd.help)
        return cmd


app = typer.Typer(
    cls=_Group,
    add_completion=False,
    no_args_is_help=True,
    help="sparseloc: 3D localization of overlapping single molecules by sparse recovery.",
    pretty_exceptions_enable=False,
)

log = logging.getLogger("sparseloc")


class UserError(Exception):
    """A problem with the user's input, reported as one sentence."""


#: Notes of the running command (e.g. how many flagged rows it leaves out), printed on stderr
#: when it ends, and not at all when it ends in a refusal: a refusal is the one line printed.
_NOTES: list[str] = []

#: Option key -> where the running command's TOML file gave it (``gain in [camera] of
#: cam.toml``), so that a refusal of the value names the file's key rather than a flag.
_FROM_CONFIG: dict[str, str] = {}

#: Library argument names that a command line spells otherwise (by default ``name`` is the
#: option ``--name``); several keys: the options that the argument combines.
_ARG_OPTIONS: dict[str, tuple[str, ...]] = {
    "kind": ("camera",),
    "px_nm": ("px",),
    "sigma_xy_max_nm": ("sigma_max",),
    "sigma_z_max_nm": ("sigma_z_max",),
    "max_distance_nm": ("max_distance",),
    "photons": ("photons_min", "photons_max"),
    "z_range": ("z_min", "z_max"),
}


def _note(message: str) -> None:
    """Say ``message`` on stderr as a note once the command has done its work (_NOTES)."""
    _NOTES.append(message)


def _print_notes() -> None:
    for message in _NOTES:
        typer.echo(f"note: {message}", err=True)
    _NOTES.clear()


def _fail(message: str) -> None:
    _NOTES.clear()  # the refusal alone: notes on work it did not finish would mislead
    typer.echo(f"error: {' '.join(message.split())}", err=True)
    raise typer.Exit(code=2)


def _option_term(key: str, ctx: Any) -> str | None:
    """How the user gave option ``key`` to the running command: its flag (``--pixel-size``),
    or the key and file of the TOML config that gave it; None if the command has neither."""
    flag = "--" + key.replace("_", "-")
    params = ctx.command.params if ctx is not None else []
    param = next(
        (p for p in params if p.param_type_name == "option" and (p.name == key or flag in p.opts)),
        None,
    )
    source = None if param is None else ctx.get_parameter_source(param.name)
    on_line = getattr(source, "name", None) in ("COMMANDLINE", "ENVIRONMENT")
    if key in _FROM_CONFIG and not on_line:
        return _FROM_CONFIG[key]
    return flag if param is not None else None


#: A lower-case word (not part of a path or a quoted name) and what follows it: "must", "=",
#: "is", "(" or a number after a library's argument name (see below).
_ARG_NAME = re.compile(
    r"(?<![\w\-'\"./])([a-z][a-z0-9_]*)(?![\w\-'\"./])(\s+must\b|\s*=(?!=)|\s+is\b|\s+\(|\s+-?\d)?"
)


def _in_cli_terms(message: str) -> str:
    """A library's message in the command's terms: Python argument names (``pixel_size must
    ...``, ``photons_min (5000) is larger ...``) as the flags that set them, and a flag the
    library names for a value that the config file gave as that file's key."""
    ctx = _Command.running

    def term(match: re.Match) -> str:
        name, verb = match.group(1), match.group(2) or ""
        if not verb or re.search(r"\b(the|a|an) $", match.string[: match.start()]):
            # "the frame must be a 2D image" speaks of an image, not of --frame; "holds a
            # pixel_size that" of a metadata key
            return match.group(0)
        if "_" not in name and verb.strip() != "must":
            # a plain word names an option only before "must" ("no format='sparseloc-psf'"
            # speaks of a file's attribute, not of --format)
            return match.group(0)
        terms = [_option_term(k, ctx) for k in _ARG_OPTIONS.get(name, (name,))]
        if any(t is None for t in terms):
            return match.group(0)
        return "/".join(t for t in terms if t) + verb

    if ".toml" not in message:  # a config file's refusal speaks of its keys, not of flags
        message = _ARG_NAME.sub(term, message)
    for key, where in _FROM_CONFIG.items():
        flag = "--" + key.replace("_", "-")
        if flag in message and _option_term(key, ctx) == where:
            message = re.sub(rf"{re.escape(flag)}(?![\w-])", where, message)
    return message


def _run(func, *args, **kwargs):
    """Call a library function, turning input errors into one sentence and exit code 2, in
    the command's terms (:func:`_in_cli_terms`)."""
    from .messages import INPUT_ERRORS, one_sentence

    try:
        return func(*args, **kwargs)
    except (*INPUT_ERRORS, UserError) as exc:
        _fail(_in_cli_terms(one_sentence(exc)))


def _output_path(path: Path) -> Path:
    if not path.parent.exists() and str(path.parent) not in ("", "."):
        _fail(f"the output folder {str(path.parent)!r} does not exist")
    return path


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file (through links and relative paths too)."""
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except OSError:
        return False


def _new_output(
    path: Path,
    *,
    overwrite: bool,
    inputs: Any = (),
    companions: Any = (),
) -> Path:
    """``path`` as a file the command will write, checked before any work: its folder exists,
    neither it nor its ``companions`` (files written with it, e.g. a Picasso table's YAML) is
    one of the ``inputs``, and none of them exists unless ``overwrite``."""
    out = _output_path(path)
    for f in (out, *companions):
        for inp in inputs:
            if inp is not None and _same_file(f, Path(inp)):
                _fail(f"the output {str(f)!r} is the input {str(inp)!r}; choose another name")
        if f.is_dir():
            _fail(f"the output {str(f)!r} is a folder, not a file")
        if f.exists() and not overwrite:
            _fail(f"{str(f)!r} exists; pass --overwrite to replace it")
    return out


def _table_companions(path: Path, fmt: str | None) -> list[Path]:
    """The files written beside a table: a Picasso HDF5 table's YAML sidecar."""
    from .io.tables import format_for

    if path.is_dir():
        _fail(f"the output {str(path)!r} is a folder, not a file")

    return [path.with_suffix(".yaml")] if _run(format_for, path, fmt) == "picasso" else []


_OVERWRITE_HELP = "Replace existing output files."


class SceneKind(StrEnum):
    uniform = "uniform"
    clusters = "clusters"
    filaments = "filaments"


# The camera's flags, the same on every command (calibrate, localize, simulate, camera) and
# the keys of a TOML file's [camera] table; None: the table's value, else CAMERA_DEFAULTS.
_CameraFlag = Annotated[
    str | None,
    typer.Option(
        "--camera", help=f"Camera noise model: ideal, emccd or scmos (default {_D['camera']})."
    ),
]
_OffsetFlag = Annotated[
    float | None, typer.Option("--offset", help=f"Camera offset (ADU; default {_D['offset']:g}).")
]
_GainFlag = Annotated[
    float | None, typer.Option("--gain", help=f"Conversion gain (e-/ADU; default {_D['gain']:g}).")
]
_EmGainFlag = Annotated[
    float | None,
    typer.Option("--em-gain", help="EM gain of an EMCCD: needed with --camera emccd."),
]
_QeFlag = Annotated[
    float | None,
    typer.Option("--qe", help=f"Quantum efficiency, detected fraction (default {_D['qe']:g})."),
]
_ReadNoiseFlag = Annotated[
    float | None,
    typer.Option(
        "--read-noise",
        help="Read noise (e- rms; EMCCD at the output, sCMOS every pixel; default "
        f"{_D['read_noise']:g}).",
    ),
]
_OffsetMapFlag = Annotated[
    Path | None, typer.Option("--offset-map", help="sCMOS offset map (ADU): .tif, .npy or .csv.")
]
_VarianceMapFlag = Annotated[
    Path | None, typer.Option("--variance-map", help="sCMOS read-noise variance map (ADU^2).")
]
_GainMapFlag = Annotated[Path | None, typer.Option("--gain-map", help="sCMOS gain map (e-/ADU).")]


def _camera_options(config: Path | None, given: dict[str, Any]) -> dict[str, Any]:
    """The camera options of a command: its flags, else the [camera] table of ``config``,
    else the defaults (:data:`sparseloc.options.CAMERA_DEFAULTS`)."""
    from .options import CAMERA_DEFAULTS, read_camera_config

    table = {} if config is None else _run(read_camera_config, config)
    _config_gave(table, f"[camera] of {config.name}" if config is not None else "")
    opts = {**CAMERA_DEFAULTS, **table}
    opts.update({k: v for k, v in given.items() if v is not None})
    return opts


def _config_gave(options: dict[str, Any], where: str) -> None:
    """Record that the config file (``where``) gave ``options``, for refusals of their values."""
    for key in options:
        _FROM_CONFIG[key] = f"{'kind' if key == 'camera' else key} in {where}"


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"sparseloc {__version__}")
        raise typer.Exit()


class _Plain(logging.Formatter):
    """Log records as the commands' own lines read: ``warning: ...`` (INFO messages bare);
    ``--verbose`` keeps each record's level and logger."""

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        return msg if record.levelno <= logging.INFO else f"{record.levelname.lower()}: {msg}"


@app.callback()
def _main(
    ctx: typer.Context,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Print the version."
        ),
    ] = False,
) -> None:
    handler = logging.StreamHandler()
    handler.setFormatter(
        logging.Formatter("%(levelname)s %(name)s: %(message)s") if verbose else _Plain()
    )
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler])
    _NOTES.clear()
    _FROM_CONFIG.clear()
    ctx.call_on_close(_print_notes)


@app.command(cls=_Command)
def demo(
    out: Annotated[
        Path, typer.Option("--output", "--out", "-o", help="Folder for the demo's outputs.")
    ] = Path("sparseloc_demo"),
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    frames: Annotated[int, typer.Option(help="Movie length.", min=1)] = 200,
    density: Annotated[float, typer.Option(help="Active emitters per um^2.")] = 0.5,
    overwrite: Annotated[bool, typer.Option(help="Replace an earlier demo's files.")] = False,
) -> None:
    """Simulate a dense 3D double-helix movie, localize it, score it against the truth and
    write the table, a rendered image and a report."""
    from .demo import run_demo

    if not density > 0:
        _fail(f"--density must be > 0, got {density}")
    t0 = time.perf_counter()
    # what it is doing, stage by stage, and the first run's minute of tabulating the model
    with _info_from("sparseloc.demo"), _info_from("sparseloc.psf.spline"):
        summary = _run(
            run_demo,
            out,
            seed=seed,
            n_frames=frames,
            density=density,
            progress=True,
            overwrite=overwrite,
        )
    typer.echo(summary["text"])
    typer.echo(f"wrote {len(summary['files'])} files to {out} in {time.perf_counter() - t0:.1f} s:")
    for f in summary["files"]:
        typer.echo(f"  {f}")


@app.command(cls=_Command)
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
        float, typer.Option(help="Emitters per um^2 per frame (uniform and filament scenes).")
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
    camera: _CameraFlag = None,
    offset: _OffsetFlag = None,
    gain: _GainFlag = None,
    em_gain: _EmGainFlag = None,
    qe: _QeFlag = None,
    read_noise: _ReadNoiseFlag = None,
    offset_map: _OffsetMapFlag = None,
    variance_map: _VarianceMapFlag = None,
    gain_map: _GainMapFlag = None,
    config: Annotated[
        Path | None, typer.Option(help="TOML file whose [camera] table describes the camera.")
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Simulate a movie with ground truth: writes OUT.tif and OUT_truth.csv."""
    from .camera import camera_from_options
    from .config import psf_option
    from .simulate import simulate as run_simulation
    from .simulate import truth_path_for, write_simulation

    out = _output_path(output)
    if out.suffix.lower() not in (".tif", ".tiff"):
        _fail(f"the output must be a .tif file, got {out.name!r}")
    _check_scene_options(
        pixel_size, density, photons_min, photons_max, background, z_min, z_max, cluster_size
    )
    out = _new_output(
        out,
        overwrite=overwrite,
        inputs=[Path(psf), config, offset_map, variance_map, gain_map],
        companions=[truth_path_for(out)],
    )
    model = _run(psf_option, psf)
    cam_opts = _camera_options(
        config,
        {
            "camera": camera,
            "offset": offset,
            "gain": gain,
            "em_gain": em_gain,
            "qe": qe,
            "read_noise": read_noise,
            "offset_map": offset_map,
            "variance_map": variance_map,
            "gain_map": gain_map,
        },
    )
    cam = _run(camera_from_options, cam_opts)
    if cam.map_shape is not None and tuple(cam.map_shape) != (rows, cols):
        _fail(
            f"the camera maps (--offset-map, --variance-map, --gain-map) are "
            f"{cam.map_shape[0]}x{cam.map_shape[1]} pixels but the frames are {rows}x{cols} "
            "(--rows, --cols)"
        )
    # The movie is uint16: an offset beyond it would saturate every pixel.
    omap = getattr(cam, "offset_map", None)
    top = float(cam.offset if omap is None else np.max(omap))
    if top > np.iinfo(np.uint16).max:
        flag = "--offset" if omap is None else "--offset-map"
        _fail(
            f"{flag} {top:g} ADU is beyond what a 16-bit movie holds (0-65535 ADU); "
            "give the camera's offset in ADU"
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
        f"simulated {frames} frame{'s' if frames != 1 else ''} of {rows}x{cols} px with "
        f"{len(sim.truth)} emitters "
        f"({len(sim.truth) / frames:.1f} per frame) in {time.perf_counter() - t0:.1f} s"
    )
    typer.echo(f"wrote {tif} and {truth}")


def _check_scene_options(
    pixel_size: float,
    density: float,
    photons_min: float,
    photons_max: float,
    background: float,
    z_min: float | None,
    z_max: float | None,
    cluster_size: int,
) -> None:
    """Refuse ``simulate``'s scene options that describe no scene, naming the flag."""
    _run(check_pixel_size, pixel_size)
    if not (np.isfinite(density) and density >= 0):
        _fail(f"--density must be a number >= 0 (emitters per um^2), got {density:g}")
    for flag, value in (("--photons-min", photons_min), ("--photons-max", photons_max)):
        if not (np.isfinite(value) and value >= 0):
            _fail(f"{flag} must be a number >= 0, got {value:g}")
    if photons_min > photons_max:
        _fail(f"--photons-min {photons_min:g} is above --photons-max {photons_max:g}")
    if not (np.isfinite(background) and background >= 0):
        _fail(f"--background must be a number >= 0 (photons per pixel), got {background:g}")
    for flag, value in (("--z-min", z_min), ("--z-max", z_max)):
        if value is not None and not np.isfinite(value):
            _fail(f"{flag} must be a number of nm, got {value:g}")
    _run(check_z_limits, z_min, z_max)
    if cluster_size < 1:
        _fail(f"--cluster-size must be at least 1, got {cluster_size}")


#: ``localize --workers`` by default: one process per available core, at most this many (each
#: holds about 300 MB: ``docs/benchmarks/memory_10k.txt``) ...
AUTO_WORKERS_CAP = 8
#: ... and at most one per this many frames (a pool's start-up is not worth it for fewer).
MIN_FRAMES_PER_WORKER = 8


def _auto_workers(n_frames: int) -> int:
    """The default number of worker processes for ``n_frames`` frames (see above)."""
    from .pool import available_cores

    return max(1, min(available_cores(), AUTO_WORKERS_CAP, n_frames // MIN_FRAMES_PER_WORKER))


def _load_config(path: Path | None) -> dict:
    from .options import read_config

    cfg = {} if path is None else _run(read_config, path)
    _config_gave(cfg, path.name if path is not None else "")
    return cfg


@app.command(cls=_Command)
def localize(
    movie: Annotated[list[Path], typer.Argument(help="Movie: TIFF/OME-TIFF file(s) in order.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="LOCS.parquet | .csv | .hdf5")],
    psf: Annotated[
        str | None,
        typer.Option(
            help="Needed: PSF.h5 from 'calibrate', a phase-mask file, or a built-in pupil "
            "model (dh, astig, clear) for simulated data."
        ),
    ] = None,
    pixel_size: Annotated[
        float | None, typer.Option(help="Pixel size in sample space (nm).")
    ] = None,
    camera: _CameraFlag = None,
    offset: _OffsetFlag = None,
    gain: _GainFlag = None,
    em_gain: _EmGainFlag = None,
    qe: _QeFlag = None,
    read_noise: _ReadNoiseFlag = None,
    offset_map: _OffsetMapFlag = None,
    variance_map: _VarianceMapFlag = None,
    gain_map: _GainMapFlag = None,
    na: Annotated[
        float | None,
        typer.Option(help="Numerical aperture of a pupil model (default 1.45)."),
    ] = None,
    wavelength: Annotated[
        float | None,
        typer.Option(help="Emission wavelength of a pupil model (nm; default 670)."),
    ] = None,
    mask_radius: Annotated[
        float | None,
        typer.Option(
            help="Radius of the objective's pupil (NA disc) in a mask file's pixels "
            "(default: the disc of the mask's non-zero values)."
        ),
    ] = None,
    blur: Annotated[
        float | None,
        typer.Option(help="Gaussian blur sigma of a pupil model (nm; default 0)."),
    ] = None,
    method: Annotated[str | None, typer.Option(help="frame (default), hybrid, mp or co.")] = None,
    window: Annotated[
        int | None, typer.Option(help="Window size (px); default from a calibrated PSF, or 11.")
    ] = None,
    margin: Annotated[
        int | None, typer.Option(help="Window margin outside its core (px); default likewise.")
    ] = None,
    z_min: Annotated[
        float | None,
        typer.Option(
            help="Lowest z (nm) searched and fitted, within the model's range (sets a pupil "
            "model's range); give the sample's depth plus about 100 nm where it is thinner "
            "than the bead scan."
        ),
    ] = None,
    z_max: Annotated[
        float | None,
        typer.Option(
            help="Highest z (nm) searched and fitted, within the model's range (sets a pupil "
            "model's range); give the sample's depth plus about 100 nm where it is thinner "
            "than the bead scan."
        ),
    ] = None,
    min_snr: Annotated[
        float | None,
        typer.Option(
            help="Detection significance of a new emitter, in noise standard errors "
            f"(default {_D['min_snr']:g})."
        ),
    ] = None,
    refine: Annotated[
        bool | None,
        typer.Option(
            "--refine/--no-refine",
            help="Maximum-likelihood stage (default on; off: the pursuit's positions only).",
        ),
    ] = None,
    frame_schedule: Annotated[
        str | None,
        typer.Option(
            help="How the frame solver spends its work: auto (default: emitters alone fitted "
            "singly, the full solver on small crowds and the whole-frame solver on a crop "
            "around a large one; a frame whose crowds hold more emitters than its singles where "
            "most images overlap solved whole; 2.1-2.3x faster on sparse movies), "
            "whole-frame, or two-tier (never whole).",
        ),
    ] = None,
    second_start: Annotated[
        bool | None,
        typer.Option(
            "--second-start/--no-second-start",
            help="Also fit each frame from its L1 deconvolution's peaks and keep the likelier "
            "fit per region (default on; off: about 2x faster on crowded frames).",
        ),
    ] = None,
    regrow: Annotated[
        bool | None,
        typer.Option(
            "--regrow/--no-regrow",
            help="Also solve each group of overlapping images again from one emitter, adding "
            "one at a time, and keep the likelier arrangement per region (default on; off: "
            "about 1.1x faster on crowded frames).",
        ),
    ] = None,
    haze: Annotated[
        bool | None,
        typer.Option(
            "--haze/--no-haze",
            help="The sample has a haze (autofluorescence, out-of-focus light) broader than one "
            "PSF image: each window's fit follows the background estimate's shape where the "
            "data prefer it to a constant, so the haze gives no false localizations "
            "(default off).",
        ),
    ] = None,
    saturation: Annotated[
        float | None,
        typer.Option(
            help="ADU at which the camera saturates: pixels at it are left out of the fits "
            "(default: the level the movie looks clipped at, else its integer type's largest "
            "value).",
        ),
    ] = None,
    relocate: Annotated[
        int | None,
        typer.Option(
            help="Relocation passes of the frame solver (default 2; 0: about 1.4x faster, "
            "fewer emitters found in crowds).",
            min=0,
        ),
    ] = None,
    background: Annotated[
        str | None,
        typer.Option(
            help="auto (default: temporal from 50 frames), temporal (blinking movies) or "
            "spatial (snapshots, emitters always on)."
        ),
    ] = None,
    frames: Annotated[
        str | None, typer.Option(help="Frame range START:STOP (0-based, STOP excluded).")
    ] = None,
    fmt: Annotated[
        str | None, typer.Option("--format", help="parquet, thunderstorm, picasso, smlm.")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Processes solving frames (default: one per available core, at most "
            f"{AUTO_WORKERS_CAP} and one per {MIN_FRAMES_PER_WORKER} frames; 1 with the "
            "chunked options).",
            min=1,
        ),
    ] = None,
    engine: Annotated[
        str | None,
        typer.Option(
            help="auto (compiled numba kernels where numba works, else NumPy), numba or numpy "
            f"(the plain reference); the same tables to rounding (default {_D['engine']})."
        ),
    ] = None,
    n_sample: Annotated[
        float | None,
        typer.Option(help="Sample refractive index (pupil models; e.g. 1.33 for water)."),
    ] = None,
    focal_depth: Annotated[
        float | None,
        typer.Option(help="Nominal focal plane above the coverslip (nm; with --n-sample)."),
    ] = None,
    run_dir: Annotated[
        Path | None,
        typer.Option(
            help="Chunked, resumable run: parts + manifest here (default OUT.parts, removed "
            "once OUT is written when the run was chunked only for its length)."
        ),
    ] = None,
    chunk_frames: Annotated[
        int | None,
        typer.Option(
            help="Frames per chunk of a chunked run (default 500; a run chunked for its "
            "length: equal chunks, 4 per worker, or those of the run it continues).",
            min=1,
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Chunked run on: sync, threads, processes (--workers of them), or a Dask "
            "scheduler address."
        ),
    ] = None,
    overwrite: Annotated[
        bool | None,
        typer.Option(
            help="Replace an existing output table; start a chunked run over in a used run folder."
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML file: a [localize] table of these options and a [camera] table."),
    ] = None,
    check: Annotated[
        Path | None,
        typer.Option(
            help="Also check the run's first frame: write its picture here (.png, .pdf or "
            ".svg: the frame with its localizations, their model image and the residual) "
            "and print each localization's support and the light they leave unexplained.",
        ),
    ] = None,
) -> None:
    """Localize a movie and write the localization table.

    With --run-dir, --chunk-frames or --scheduler, and on every run of more than 500 frames,
    the movie is cut into chunks of frames run as tasks (in this process, in threads, in
    --workers local processes, or on the Dask scheduler given); each finished chunk is saved
    in the run folder, so the same command started again after an interruption runs only the
    missing chunks. A run chunked only for its length removes its folder once OUT is
    written."""
    from .config import LOCALIZE_DEFAULTS, build_job
    from .distributed import resumable_by_default
    from .psf.symmetry import mirror_warning

    given = {
        "psf": psf,
        "pixel_size": pixel_size,
        "offset": offset,
        "gain": gain,
        "em_gain": em_gain,
        "qe": qe,
        "camera": camera,
        "method": method,
        "window": window,
        "margin": margin,
        "z_min": z_min,
        "z_max": z_max,
        "min_snr": min_snr,
        "refine": refine,
        "second_start": second_start,
        "regrow": regrow,
        "haze": haze,
        "saturation": saturation,
        "relocate": relocate,
        "frame_schedule": frame_schedule,
        "background": background,
        "frames": frames,
        "format": fmt,
        "workers": workers,
        "engine": engine,
        "n_sample": n_sample,
        "focal_depth": focal_depth,
        "na": na,
        "wavelength": wavelength,
        "mask_radius": mask_radius,
        "blur": blur,
        "read_noise": read_noise,
        "offset_map": offset_map,
        "variance_map": variance_map,
        "gain_map": gain_map,
        "run_dir": run_dir,
        "chunk_frames": chunk_frames,
        "scheduler": scheduler,
        "overwrite": overwrite,
    }
    cfg = _load_config(config)
    opts = {**LOCALIZE_DEFAULTS, **cfg}
    opts.update({k: v for k, v in given.items() if v is not None})
    mov = _open_movie(movie, "the movie goes first, the calibration after --psf")
    with mov, _info_from("sparseloc.psf.spline"):
        inputs = [*mov.paths, config, *([Path(str(opts["psf"]))] if opts["psf"] else [])]
        inputs += [opts[k] for k in ("offset_map", "variance_map", "gain_map")]
        out = _new_output(
            output,
            overwrite=bool(opts["overwrite"]),
            inputs=inputs,
            companions=_table_companions(output, opts["format"]),
        )
        if check is not None:
            _check_suffix(check, _FIGURE_SUFFIXES, "the check's picture")
            check = _new_output(check, overwrite=bool(opts["overwrite"]), inputs=[*inputs, out])
        job = _run(build_job, opts, mov)
        mirror = mirror_warning(job.model, job.params.pixel_size, job.params.z_range)
        if mirror:
            typer.echo(f"note: {mirror}", err=True)
        if job.defects is not None:
            typer.echo(
                f"note: {int(job.defects.sum())} defective (hot or stuck) pixel(s) stand above "
                "their neighbours in every frame as no light could; each is replaced by the "
                "median of its neighbours",
                err=True,
            )
        if job.clipped is not None:
            top, ties = job.clipped
            typer.echo(
                f"note: {ties} pixel values of the movie sit at exactly {top:g} ADU, its "
                "largest, as where a camera clips (a 12-bit camera at 4095). "
                + (
                    "The fits leave such pixels out (--saturation sets the level), so the "
                    "brightest emitters are localized from their unclipped pixels, less "
                    "precisely"
                    if job.params.method == "frame"
                    else f"--method {job.params.method} takes them at face value, and the "
                    "brightest emitters' flat peaks misplace their fits, in z most"
                )
                + "; lower the gain, EM gain or exposure where this is not what you expect",
                err=True,
            )
        wide = _wide_window_note(job.params)
        if wide:  # said before the work: it is the work that takes long
            typer.echo(f"note: {wide}", err=True)
        asked = any(opts[k] is not None for k in ("run_dir", "chunk_frames", "scheduler"))
        table = None
        if asked or resumable_by_default(job.stop - job.start):
            _localize_chunked(opts, out, mov, job, auto=not asked)
        else:
            workers = opts["workers"] or _auto_workers(job.stop - job.start)
            res = _localize_in_processes(mov, job, workers)
            _write_localized(res, out, opts, mov, job)
            typer.echo(f"{res.summary()}, {workers} process{'es' if workers > 1 else ''}")
            _run_notes(res.metadata)
            typer.echo(f"wrote {out}")
            table = res.table
        if check is not None:
            _frame_check(check, out, table, mov, job)


def _frame_check(path: Path, table_path: Path, table, mov, job) -> None:
    """``localize --check``: the frame check of the run's first frame
    (:func:`sparseloc.pipeline.check_frame`) on the run's table (``table``, else the file
    written), printed and drawn. The table is written already: a failure says so."""
    from .frame_residual import residual_figure
    from .messages import INPUT_ERRORS, one_sentence
    from .pipeline import addition_bar, check_frame

    if table is None:
        table, _ = _read_locs(table_path)
    p = job.params
    try:
        frames = job.frames(mov)
        res = check_frame(frames, job.start, table, job.model, p, job.read_variance_map)
        typer.echo(f"check of frame {job.start}: {res.summary(addition_bar(p), p.min_snr)}")
        title = f"frame {job.start}: localizations, their model and the residual"
        residual_figure(res, p.pixel_size, path, z_range=p.z_range or job.model.z_range,
                        title=title)  # fmt: skip
    except INPUT_ERRORS as exc:
        _fail(f"wrote {table_path}, but the check failed: {_in_cli_terms(one_sentence(exc))}")
    typer.echo(f"wrote {path}")


@contextmanager
def _info_from(name: str):
    """Show the INFO messages of logger ``name`` (e.g. the minute-long tabulation of a pupil
    model) during the block, whatever ``--verbose`` says."""
    logger = logging.getLogger(name)
    level = logger.level
    if logger.getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.setLevel(level)


def _run_notes(meta: dict) -> None:
    """The run summary's model check and notes (:func:`sparseloc.pipeline.run_checks`)."""
    from .model_check import ModelCheck

    check = meta.get("model_check")
    if check:
        typer.echo(ModelCheck(**check).summary())
    bright = meta.get("beyond_roi")
    if bright:
        n, half = bright["count"], bright["roi_half_nm"] / 1000.0
        typer.echo(
            f"note: {n} localization{'' if n == 1 else 's'} so bright that "
            f"{'its' if n == 1 else 'their'} light beyond the calibration's ROI ({half:.1f} um "
            "from the emitter), which its model does not hold, would stand above the noise: "
            "false localizations can ring such emitters there; a pupil calibration "
            "(calibrate --fit-pupil --model pupil) models that light"
        )
    ends = meta.get("at_z_ends")
    if ends:
        typer.echo(_z_ends_note(ends))


def _z_ends_note(ends: dict) -> str:
    """The note of localizations stopped at the ends of the fits' z range: widen the run's
    range where it narrowed the model's, else the model's range is short of the sample."""
    n, (lo, hi) = ends["count"], (ends["z_min_nm"], ends["z_max_nm"])
    mlo, mhi = ends.get("model_z_min_nm", lo), ends.get("model_z_max_nm", hi)
    one = n == 1
    head = (
        f"note: {n} localization{'' if one else 's'} ({100 * ends['fraction']:.0f} %) stopped "
        f"at an end of the z range ({lo:.0f} to {hi:.0f} nm) and {'is' if one else 'are'} "
        "flagged z_edge: emitters beyond it, whose z is not known (render, drift and evaluate "
        "leave them out); "
    )
    if mlo < lo - 0.5 or mhi > hi + 0.5:
        return head + f"widen --z-min / --z-max (the model covers {mlo:.0f} to {mhi:.0f} nm)"
    return head + "a model over a deeper range (a bead scan deeper than the sample) finds them"


def _table_not_truth(locs: Path, truth: Path) -> tuple[Any, Any]:
    """The table and metadata of ``locs``; where it is not a table but reads as a ground
    truth, a ValueError saying the arguments are swapped."""
    from .io.tables import read_table_and_metadata
    from .io.truth import read_truth_csv

    try:
        return read_table_and_metadata(locs)
    except ValueError as exc:
        try:
            read_truth_csv(locs, pixel_size=100.0)  # any size: whether it reads as a truth
        except Exception:
            raise exc from None
        raise ValueError(
            f"{locs.name} reads as a ground truth, not a localization table: the table goes "
            f"first, the truth second (sparseloc evaluate LOCS {truth.name})"
        ) from None


def _read_truth(truth: Path, pixel_size: float | None, meta: Any) -> tuple[Any, list[str]]:
    """The truth table and what to say of its pixel size: truth in pixels is of the movie the
    table was localized from, so its pixel size is the table's unless given (evaluate and
    report --truth)."""
    from .config import pixel_sizes_differ
    from .io.tables import recorded_pixel_size
    from .io.truth import read_truth_csv, truth_gives_pixels

    table_px = recorded_pixel_size(meta)
    truth_df = _run(
        read_truth_csv,
        truth,
        pixel_size=table_px if pixel_size is None else pixel_size,
        require_photons=False,  # matching needs positions only
    )
    in_px = truth_gives_pixels(truth)
    said = []
    if in_px and pixel_size is None:
        typer.echo(f"truth in pixels, at the table's pixel size of {table_px:g} nm")
    elif pixel_size is not None and not in_px:
        _note(f"--pixel-size is not used: {truth.name} gives positions in nm")
    elif (
        pixel_size is not None and table_px is not None and pixel_sizes_differ(pixel_size, table_px)
    ):
        said.append(
            f"--pixel-size {pixel_size:g} nm differs from the table's {table_px:g} nm: truth "
            "in pixels of the movie the table was localized from takes its pixel size"
        )
    return truth_df, said


def _wide_window_note(params) -> str:
    """A note before a window method's run on windows wider than the paper's 11 px (sized
    to hold a measured PSF's light): its dictionary and convex problems grow with the
    window's area, so such runs take minutes per frame."""
    from .config import LocalizeParams

    paper = LocalizeParams.__dataclass_fields__["window"].default
    if params.method == "frame" or params.window <= paper:
        return ""
    return (
        f"--method {params.method} solves windows of {params.window} px (sized to hold this "
        f"PSF's light; the paper's are {paper} px): expect minutes per frame; the default "
        "--method frame solves whole frames in seconds"
    )


def _localize_in_processes(mov, job, workers: int):
    """The unchunked path of ``localize``: one process or a pool, with a progress bar (or
    progress lines in a log file). Ctrl-C ends it with one sentence and exit code 130."""
    from .distributed import CHUNK_FRAMES
    from .pipeline import localize as run_localize
    from .progress import Progress

    with Progress(job.stop - job.start) as bar:
        try:
            return _run(
                run_localize,
                job.frames(mov),
                job.model,
                job.params,
                start=job.start,
                stop=job.stop,
                progress=bar.update,
                workers=workers,
                read_variance=job.read_variance_map,
            )
        except KeyboardInterrupt:
            typer.echo(
                f"interrupted (Ctrl-C) after {bar.done} of {bar.total} frames: no output was "
                "written, as the table is written when every frame is done (runs of more "
                f"than {CHUNK_FRAMES} frames, or with --run-dir, keep finished chunks for a "
                "rerun)",
                err=True,
            )
            raise typer.Exit(code=130) from None


def _localize_chunked(opts, out, mov, job, auto: bool = False) -> None:
    """The chunked path of ``localize``: run, save parts, join, or report what is missing.

    ``auto``: chunked because the movie is long, not because the user asked (the workers
    then default to the cores). The run folder beside the output (no ``--run-dir``) is
    removed once the table is written."""
    from .distributed import localize_chunked
    from .progress import Progress

    run_dir = Path(opts["run_dir"]) if opts["run_dir"] else out.with_name(out.name + ".parts")
    sched = opts["scheduler"]
    workers = int(opts["workers"] or (_auto_workers(job.stop - job.start) if auto else 1))
    if sched is None:
        # Local worker processes, not a local Dask cluster: that one would take code from any
        # local client, unauthenticated. A Dask cluster runs only at an address given.
        sched = "processes" if workers > 1 else "sync"
    bar = Progress(job.stop - job.start)
    try:
        with bar:
            res = _run(
                localize_chunked,
                job.frames(mov),
                job.model,
                job.params,
                run_dir,
                start=job.start,
                stop=job.stop,
                chunk_frames=None if opts["chunk_frames"] is None else int(opts["chunk_frames"]),
                scheduler=sched,
                threads=max(workers, 2),
                workers=workers,
                overwrite=bool(opts["overwrite"]),
                read_variance=job.read_variance_map,
                progress=bar.update,
            )
    except KeyboardInterrupt:
        typer.echo(
            f"interrupted (Ctrl-C) after {bar.done} of {bar.total} frames: {out} was not "
            f"written; the finished chunks are kept in {run_dir}, and the same command run "
            "again continues from them",
            err=True,
        )
        raise typer.Exit(code=130) from None
    typer.echo(res.summary())
    if not res.complete:
        typer.echo(
            f"error: {len(res.missing)} chunk(s) missing; {out} not written. Run the same "
            f"command again to retry them (finished chunks are kept in {run_dir}).",
            err=True,
        )
        raise typer.Exit(code=1)
    _write_localized(res, out, opts, mov, job)
    if opts["run_dir"] is None:  # a folder the user did not ask for (docs/long_movies.md)
        _remove_run_dir(run_dir)
    _run_notes(res.metadata)
    typer.echo(f"wrote {out}")


def _remove_run_dir(run_dir: Path) -> None:
    """Remove an automatic run folder once its table is written (a failure only warns)."""
    import shutil

    try:
        shutil.rmtree(run_dir)
    except OSError as exc:
        log.warning("could not remove the run folder %s: %s", run_dir, exc)


def _write_localized(res, out: Path, opts: dict, mov, job) -> None:
    """Write ``localize``'s table with the analysis, movie and camera as metadata."""
    from .io.localized import write_localized

    _run(write_localized, res, out, format=opts["format"], movie=mov, job=job)


@app.command(cls=_Command)
def calibrate(
    stack: Annotated[
        Path, typer.Argument(metavar="BEADS.tif", help="Bead z-scan: a multi-frame TIFF.")
    ],
    output: Annotated[Path, typer.Option("--output", "-o", help="Calibration file (.h5).")],
    pixel_size: Annotated[float, typer.Option(help="Pixel size in sample space (nm).")],
    z_step: Annotated[
        float | None,
        typer.Option(
            help="Stage step between frames (nm); with --z-file, the step of the planes the "
            "frames are resampled to (default: the file's median step)."
        ),
    ] = None,
    z_file: Annotated[
        Path | None,
        typer.Option(help="CSV of each frame's z (z_um or z_nm column, optional valid)."),
    ] = None,
    z0_slice: Annotated[
        float | None, typer.Option(help="Slice at z = 0 (default: the middle one).")
    ] = None,
    camera: _CameraFlag = None,
    offset: _OffsetFlag = None,
    gain: _GainFlag = None,
    em_gain: _EmGainFlag = None,
    qe: _QeFlag = None,
    read_noise: _ReadNoiseFlag = None,
    offset_map: _OffsetMapFlag = None,
    variance_map: _VarianceMapFlag = None,
    gain_map: _GainMapFlag = None,
    config: Annotated[
        Path | None, typer.Option(help="TOML file whose [camera] table describes the camera.")
    ] = None,
    roi_size: Annotated[
        int | None, typer.Option(help="ROI side (px); default from the PSF's extent.")
    ] = None,
    threshold: Annotated[
        float,
        typer.Option(help="Bead detection threshold (fraction of the brightest unsaturated bead)."),
    ] = 0.2,
    saturation: Annotated[
        float | None, typer.Option(help="Saturation level (ADU); default the type's maximum.")
    ] = None,
    fit_pupil: Annotated[
        bool, typer.Option("--fit-pupil/--no-fit-pupil", help="Also fit the pupil phase.")
    ] = False,
    na: Annotated[float, typer.Option(help="Numerical aperture (pupil fit).")] = 1.45,
    wavelength: Annotated[float, typer.Option(help="Emission wavelength (nm, pupil fit).")] = 670.0,
    n_immersion: Annotated[float, typer.Option(help="Immersion index (pupil fit).")] = 1.518,
    mask: Annotated[
        str | None,
        typer.Option(help="Base mask for the pupil fit: dh or a mask file (default none)."),
    ] = None,
    model: Annotated[
        str, typer.Option(help="Model the file serves by default: spline or pupil.")
    ] = "spline",
    figure: Annotated[
        Path | None, typer.Option(help="Diagnostic PNG (default: beside the output).")
    ] = None,
    beads: Annotated[
        Path | None,
        typer.Option(
            help="CSV of the beads' known positions: x_nm, y_nm (origin at the outer corner of "
            "pixel (0, 0)) or x_px, y_px (0 at the first pixel's centre). The model's origin "
            "is then the emitter, not the centroid of its light."
        ),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Build a PSF model from a bead z-stack and write it to an HDF5 calibration file.

    The stack is converted to photons as localize converts a movie: (ADU - offset) x gain
    (e-/ADU) / EM gain / QE."""
    from .calibrate import calibrate_file, read_bead_positions
    from .calibrate_output import calibration_path, calibration_summary, write_calibration
    from .calibrate_scan import scan_conversion
    from .camera import camera_from_options
    from .io.calibration import read_calibration_info

    out = _run(calibration_path, _output_path(output))
    if z_step is None and z_file is None:
        _fail("give the stage step with --z-step NM, or each frame's z with --z-file")
    _run(check_pixel_size, pixel_size)
    if not (np.isfinite(threshold) and 0 < threshold <= 1):
        _fail(f"--threshold must be a fraction of the brightest bead, in (0, 1], got {threshold:g}")
    if saturation is not None and not (np.isfinite(saturation) and saturation > 0):
        _fail(f"--saturation must be a positive number of ADU, got {saturation:g}")
    if model not in ("spline", "pupil"):
        _fail(f"--model must be spline or pupil, got {model!r}")
    if model == "pupil" and not fit_pupil:
        _fail("--model pupil needs --fit-pupil")
    fig_path = _output_path(figure) if figure else out.with_suffix(".png")
    cam_opts = _camera_options(
        config,
        {
            "camera": camera,
            "offset": offset,
            "gain": gain,
            "em_gain": em_gain,
            "qe": qe,
            "read_noise": read_noise,
            "offset_map": offset_map,
            "variance_map": variance_map,
            "gain_map": gain_map,
        },
    )
    adu_offset, photons_per_adu = _run(scan_conversion, cam_opts)
    scan_camera = _run(camera_from_options, cam_opts)
    inputs = [stack, z_file, beads, Path(mask) if mask else None, config]
    out = _new_output(out, overwrite=overwrite, inputs=inputs)
    fig_path = _new_output(fig_path, overwrite=overwrite, inputs=[*inputs, out])
    if figure is not None:  # checked before the calibration's work, not by matplotlib after it
        _check_suffix(figure, _FIGURE_SUFFIXES, "--figure")
    pupil_options = None
    if fit_pupil:
        base = None
        if mask:
            from .psf import make_psf

            base = _run(make_psf, mask, na=na, wavelength=wavelength, n_immersion=n_immersion)
            base = getattr(base, "mask", None)
        pupil_options = {
            "na": na,
            "wavelength": wavelength,
            "n_immersion": n_immersion,
            "base_mask": base,
        }
    known = None if beads is None else _run(read_bead_positions, beads, pixel_size)
    t0 = time.perf_counter()
    cal = _run(
        calibrate_file,
        stack,
        pixel_size,
        z_step,
        z_file=z_file,
        z0_slice=z0_slice,
        offset=adu_offset,
        gain=photons_per_adu,
        roi_size=roi_size,
        threshold=threshold,
        saturation=saturation,
        fit_pupil=fit_pupil,
        pupil_options=pupil_options,
        beads=known,
        camera=scan_camera,
    )
    _run(write_calibration, cal, out, fig_path, model=model)
    recorded = read_calibration_info(out)["content_hash"]
    for line in calibration_summary(cal, time.perf_counter() - t0, recorded):
        typer.echo(line)
    typer.echo(f"wrote {out} and {fig_path}")


def _plus_minus(error: float, spec: str) -> str:
    """`` +- error`` formatted with ``spec``, or "" for an unknown (NaN) error."""
    return f" +- {error:{spec}}" if np.isfinite(error) else ""


def _suggested_camera(given: str | None, est: Any) -> str:
    """The ``--camera`` to suggest: the one given, else an sCMOS where the line measured a read
    noise and localize's default (no read noise) where it did not."""
    if given is not None:
        return given
    if est.offset_given and est.read_noise_resolved:
        return "scmos"
    return _D["camera"]


def _camera_frames(frames: str, n: int) -> tuple[int, int]:
    """``camera --frames``: a range as localize's (START:STOP), or a count N from the first
    frame (at most the movie's ``n``)."""
    from .config import frame_range

    if ":" in str(frames):
        start, stop = frame_range(frames, n)
    else:
        try:
            count = int(frames)
        except ValueError:
            raise ValueError(
                f"--frames takes START:STOP or a number of frames, got {frames!r}"
            ) from None
        if count < 1:
            raise ValueError(f"--frames takes at least 1 frame, got {frames!r}")
        start, stop = 0, min(count, n)
    if stop <= start:
        raise ValueError(f"--frames {frames} holds no frame")
    return start, stop


@app.command(name="camera", cls=_Command)
def camera_cmd(
    movie: Annotated[
        list[Path], typer.Argument(help="Movie of raw camera counts (ADU): TIFF/OME-TIFF file(s).")
    ],
    offset: Annotated[
        float | None,
        typer.Option(help="The camera's offset (ADU), where known: the read noise is measured."),
    ] = None,
    read_noise: Annotated[
        float | None,
        typer.Option(help="The read noise (e- rms), where known and the offset is not."),
    ] = None,
    camera: _CameraFlag = None,
    em_gain: _EmGainFlag = None,
    frames: Annotated[
        str,
        typer.Option(
            help="Frames read: START:STOP (0-based, STOP excluded, as in localize), or N for "
            "the first N."
        ),
    ] = "20",
) -> None:
    """Estimate the camera's offset, gain (e-/ADU) and read noise from the movie's
    mean-variance (photon transfer) relation, for localize's camera flags."""
    from .camera import estimate_camera

    kind = camera or "scmos"
    for flag, value in (("--offset", offset), ("--read-noise", read_noise)):
        if value is not None and not (np.isfinite(value) and value >= 0):
            _fail(f"{flag} must be a number >= 0, got {value:g}")
    mov = _open_movie(movie, "give the camera's movie or bead stack (TIFF)")
    with mov:
        start, stop = _run(_camera_frames, frames, len(mov))
        adu = _run(mov.frames, start, stop)
    median = float(np.median(adu))
    if offset is not None and offset >= median:
        _fail(
            f"--offset {offset:g} ADU is not below the median pixel value of {movie[0].name!r} "
            f"({median:g} ADU): the offset is the dark level, below every signal"
        )
    est = _run(
        estimate_camera,
        adu,
        offset=offset,
        read_noise=read_noise,
        kind=kind,
        em_gain=1.0 if em_gain is None else em_gain,
    )
    # Without the offset the line gives only a lower bound of it (read noise taken as given);
    # a bound below zero places nothing, and no offset is suggested.
    placed = est.offset_given or est.offset >= 0
    rough = est.method != "temporal"  # single frames: the emitters' images bias the line
    if est.offset_given:
        typer.echo(f"offset {est.offset:.1f} ADU (given)")
    elif placed and not est.offset_is_bound:
        # the bound holds for the line of a steady series without a caution
        placed = False
        why = (
            " from single frames, not a bound (their line is biased as the gain is"
            if rough
            else ", not a bound (the line's slope is uncertain beyond its standard errors, and "
            "the offset far below the data moves with it"
        )
        typer.echo(
            f"offset about {est.offset:.1f} ADU{why}: see the caution); give --offset (the "
            "median of a dark frame)"
        )
    elif placed:
        typer.echo(
            f"offset at least {est.offset:.1f}{_plus_minus(est.offset_error, '.1f')} ADU (with a "
            f"read noise of {est.read_noise:g} e-; more read noise puts it higher): give "
            "--offset to measure the read noise"
        )
    else:
        typer.echo(
            f"offset not placed: the line's bound ({est.offset:.1f} ADU) is below zero, as the "
            "read noise dominates; give --offset (the median of a dark frame)"
        )
    typer.echo(f"gain {est.gain:.4g}{_plus_minus(est.gain_error, '.2g')} e-/ADU")
    resolved = est.read_noise_resolved
    if est.offset_given and not resolved:
        bound = est.read_noise_bound
        below = f": below about {bound:.3g} e- rms (two standard errors)" if bound > 0 else ""
        typer.echo(f"read noise not resolved by the line{below}; take the camera's data sheet")
    elif est.offset_given:
        upto = (
            f" (up to {est.read_noise_bound:.3g} at two standard errors)"
            if np.isfinite(est.read_noise_bound)
            else ""
        )
        typer.echo(f"read noise {est.read_noise:.3g} e- rms{upto}")
    source = "frame-to-frame differences" if est.method == "temporal" else "single-frame noise"
    typer.echo(
        f"  from the line variance = {est.slope:.4g} x mean {est.intercept:+.4g} (ADU^2) of the "
        f"{source} of {adu.shape[0]} frame(s)"
    )
    if est.caution:
        typer.echo(f"caution: {est.caution}")
    # an offset the line could not place is still needed: localize's default (100 ADU) is
    # not this camera's
    suggested = _suggested_camera(camera, est)
    if camera is None and not est.offset_given:
        typer.echo(
            "read noise not measured without --offset: for a camera with read noise (an sCMOS) "
            "add --camera scmos --read-noise R (e- rms, from its data sheet)"
        )
    if camera is None:
        # the line's slope of an EMCCD is 2 x EM gain / gain: read as a camera without EM
        # gain, its photons would be half the true ones
        typer.echo(
            "an EMCCD? run again with --camera emccd --em-gain G: its excess noise doubles the "
            "variance per photon, and the gain above would then count half the photons"
        )
    flags = f"--camera {suggested} " if suggested != _D["camera"] else ""
    flags += "--offset " + (f"{est.offset:.1f}" if placed else "DARK_LEVEL")
    # a line of flags reads as advice to copy: single frames' noise biases the gain low by a
    # factor of 2 or more (the emitters' images), so that line leaves the gain to the user
    flags += " --gain GAIN" if rough else f" --gain {est.gain:.4g}"
    if kind == "emccd" and em_gain is not None:
        flags += f" --em-gain {em_gain:g}"
    if resolved and suggested != "ideal":
        flags += f" --read-noise {est.read_noise:.3g}"
    lead = (
        "localize with (GAIN from the camera's data sheet or a steady series: see the caution)"
        if rough
        else "localize with"
    )
    typer.echo(f"{lead}: {flags}")


@app.command(cls=_Command)
def evaluate(
    locs: Annotated[
        Path,
        typer.Argument(
            help="Localizations: Parquet, ThunderSTORM/SMLM/sparseloc CSV or Picasso HDF5."
        ),
    ],
    truth: Annotated[
        Path,
        typer.Argument(
            help="Ground truth CSV: simulate's, storm-analysis's (x_px/y_px/z_um) or the SMLM "
            "challenge's (xnano/ynano/znano, 1-based frames)."
        ),
    ],
    pixel_size: Annotated[
        float | None,
        typer.Option(help="Pixel size (nm) for truth given in pixels; default: the table's."),
    ] = None,
    lateral_tol: Annotated[float, typer.Option(help="Lateral match tolerance (nm).")] = 250.0,
    axial_tol: Annotated[float, typer.Option(help="Axial match tolerance (nm).")] = 500.0,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the figures as JSON.")
    ] = None,
    all_flags: Annotated[bool, typer.Option(help=_ALL_FLAGS_HELP)] = False,
    frames: Annotated[
        str | None,
        typer.Option(
            help="Score frames START:STOP only, of the table and the truth (0-based, STOP "
            "excluded; default: the table's recorded range of the truth, else all)."
        ),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Match localizations to the truth and print Jaccard, RMSE, bias and efficiency."""
    from .config import frame_range
    from .evaluate import evaluate as run_evaluation
    from .evaluate import result_cautions, rows_in_frames, scoring_cautions

    for p in (locs, truth):
        if not p.is_file():
            _fail(f"{str(p)!r} does not exist or is not a file")
    for flag, value in (("--lateral-tol", lateral_tol), ("--axial-tol", axial_tol)):
        _run(check_length_nm, value, flag, TOLERANCE_RANGE_NM)
    if json_out is not None:
        _new_output(json_out, overwrite=overwrite, inputs=[locs, truth])
    loc_df, meta = _run(_table_not_truth, locs, truth)
    if pixel_size is not None:
        _run(check_pixel_size, pixel_size)
    truth_df, cautions = _read_truth(truth, pixel_size, meta)
    recorded = meta.get("frames") if isinstance(meta, dict) else None
    if frames is not None:
        n = max(int(df["frame"].max()) + 1 if len(df) else 0 for df in (truth_df, loc_df))
        start, stop = _run(frame_range, frames, max(n, _frames_stop(frames)))
        if start >= n:
            _fail(f"--frames {frames} lies past the table's and the truth's frames (0:{n})")
        truth_df = _run(rows_in_frames, truth_df, (start, stop))
        loc_df = _run(rows_in_frames, loc_df, (start, stop)).reset_index(drop=True)
        typer.echo(f"scored frames {start}:{stop} of the table and the truth")
    elif recorded is not None:
        truth_df = _run(rows_in_frames, truth_df, recorded)
        typer.echo(
            f"scored against the truth of frames {recorded[0]}:{recorded[1]}, the table's range"
        )
    from .postprocess import excluded_note, flagged_rows

    note = excluded_note(int(_run(flagged_rows, loc_df, all_flags=all_flags).sum()))
    if note:  # above the figures it qualifies, where a note at the end is missed
        typer.echo(f"note: {note}", err=True)
    cautions += _run(scoring_cautions, loc_df, truth_df, lateral_tol)
    result = _run(
        run_evaluation,
        loc_df,
        truth_df,
        lateral_tol=lateral_tol,
        axial_tol=axial_tol,
        all_flags=all_flags,
    )
    if not cautions:
        cautions += result_cautions(result)
    # above the figures, which they qualify
    for caution in cautions:
        typer.echo(f"caution: {caution}")
    typer.echo(result.summary())
    if json_out is not None:
        from .io.atomic import write_text_atomic

        _run(write_text_atomic, json_out, json.dumps(result.as_dict(), indent=2))


def _frames_stop(frames: str) -> int:
    """The STOP of ``START:STOP`` where it is a number (0 otherwise): ``evaluate --frames`` may
    name frames past the truth's last emitter."""
    stop = str(frames).partition(":")[2]
    return int(stop) if stop.isdigit() else 0


_FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def _check_suffix(path: Path, allowed: tuple[str, ...], what: str) -> None:
    if path.suffix.lower() not in allowed:
        _fail(f"{what} must be a {' or '.join(allowed)} file, got {path.name!r}")


def _table_output(path: Path, *, overwrite: bool, inputs: Any) -> Path:
    """An output table path whose folder exists and whose suffix names a format, checked by
    :func:`_new_output` with its companions."""
    return _new_output(
        path, overwrite=overwrite, inputs=inputs, companions=_table_companions(path, None)
    )


def _differing(first: str, second: str) -> str:
    """The text "'A' before 'B'" for two paths: their names where those differ, else in
    full."""
    a, b = Path(first), Path(second)
    if a.name == b.name:
        a, b = first, second
    else:
        a, b = a.name, b.name
    return f"{str(a)!r} before {str(b)!r}"


def _open_movie(paths: list[Path], hint: str) -> Any:
    """The movie of ``paths`` (one file or a series), refusing an HDF5 file (a calibration or
    a Picasso table given where the movie belongs) in one sentence with ``hint``."""
    from .io.movie import Movie, out_of_number_order

    backwards = out_of_number_order(paths)
    if backwards:
        _fail(
            f"the {len(paths)} movie files come in alphabetical order, which puts "
            f"{_differing(*backwards)} (a shell's "
            "expansion of an unquoted pattern): quote the pattern (e.g. 'frame_*.tif') so "
            "that sparseloc orders them by their numbers, or name them with padded numbers"
        )

    for path in paths:
        try:
            with open(path, "rb") as fh:
                head = fh.read(8)
        except OSError:
            continue  # Movie.open says what is wrong with it
        if head.startswith(b"\x89HDF"):
            _fail(
                f"{path.name!r} is an HDF5 file (a calibration or a Picasso table?), not a "
                f"movie: {hint}"
            )
    return _run(Movie.open, [str(p) for p in paths] if len(paths) > 1 else str(paths[0]))


def _read_locs(path: Path) -> tuple[Any, dict]:
    """A localization table and its metadata (:func:`~sparseloc.io.tables.read_table_and_metadata`:
    a sparseloc Parquet table's, or a Picasso table's sidecar)."""
    from .io.tables import read_table_and_metadata

    if not path.is_file():
        _fail(f"{str(path)!r} does not exist or is not a file")
    return _run(read_table_and_metadata, path)


_ALL_FLAGS_HELP = "Use flagged fits too (default: only rows flagged 'ok')."


def _usable(table, all_flags: bool):
    """The rows a command uses (:func:`sparseloc.postprocess.select_usable`: flag 'ok' unless
    ``all_flags``, finite coordinates), saying on stderr how many flagged rows were left out."""
    from .postprocess import select_usable

    sel = _run(select_usable, table, all_flags=all_flags)
    if sel.note():
        _note(sel.note())
    return sel.locs


def _write_locs(table, out: Path, meta: dict) -> None:
    """Write a processed table in the format of ``out``'s suffix, with the metadata."""
    from .io.tables import write_table

    kwargs: dict[str, Any] = {"metadata": meta, **_picasso_kwargs(out, meta)}
    if "shape" in kwargs:
        kwargs["n_frames"] = int(table["frame"].max()) + 1 if len(table) else 1
    _run(write_table, table, out, **kwargs)


def _picasso_kwargs(out: Path, meta: dict) -> dict[str, Any]:
    """The pixel size and frame shape a Picasso HDF5 output ``out`` needs, from the input's
    metadata; a refusal where the input has none (checked before the work, again when
    writing). ``{}`` for other outputs."""
    if out.suffix.lower() not in (".hdf5", ".h5"):
        return {}
    params = meta.get("params", {}) if isinstance(meta.get("params"), dict) else {}
    shape = meta.get("shape")
    if not params.get("pixel_size") or not shape:
        _fail(
            "a Picasso HDF5 output needs the pixel size and frame shape, which the input does "
            "not carry (a sparseloc Parquet or Picasso table does); write .parquet or .csv "
            "instead"
        )
    return {"pixel_size": float(params["pixel_size"]), "shape": tuple(shape)}


@app.command(cls=_Command)
def render(
    locs: Annotated[Path, typer.Argument(help="Localization table (any supported format).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Image (.png).")],
    px: Annotated[
        float | None, typer.Option(help="Render pixel (nm); default: from the uncertainties.")
    ] = None,
    z_min: Annotated[float | None, typer.Option(help="Colour scale start (nm).")] = None,
    z_max: Annotated[float | None, typer.Option(help="Colour scale end (nm).")] = None,
    volume: Annotated[
        Path | None, typer.Option(help="Also write a 3D rendering as a TIFF stack (ImageJ).")
    ] = None,
    voxel: Annotated[
        tuple[float, float], typer.Option(help="Volume voxel: lateral and axial size (nm).")
    ] = (20.0, 50.0),
    frc_plot: Annotated[
        Path | None, typer.Option("--frc", help="Also write the FRC curve (.png).")
    ] = None,
    all_flags: Annotated[bool, typer.Option(help=_ALL_FLAGS_HELP)] = False,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Render localizations: xy coloured by depth, with xz and yz; FRC resolution.

    Rows flagged other than 'ok' are left out unless --all-flags; rows with a non-finite or
    absurd coordinate are dropped with a warning; rows without uncertainties are drawn 15 nm
    wide (37.5 nm in z)."""
    from .render import frc_report, plot_frc, plot_projections, render_volume, write_volume_tiff

    _check_suffix(output, (".png",), "the image")
    out = _new_output(output, overwrite=overwrite, inputs=[locs])
    if frc_plot is not None:
        _check_suffix(frc_plot, _FIGURE_SUFFIXES, "--frc")
        _new_output(frc_plot, overwrite=overwrite, inputs=[locs, out])
    if volume is not None:
        _check_suffix(volume, (".tif", ".tiff"), "--volume")
        _new_output(volume, overwrite=overwrite, inputs=[locs, out, frc_plot])
    if not (np.all(np.isfinite(voxel)) and min(voxel) > 0):
        _fail(f"--voxel sizes must be > 0 nm, got {voxel[0]:g} and {voxel[1]:g}")
    if px is not None:
        _run(check_length_nm, px, "--px", TOLERANCE_RANGE_NM)
    for flag, value in (("--z-min", z_min), ("--z-max", z_max)):
        if value is not None and not np.isfinite(value):
            _fail(f"{flag} must be a number of nm, got {value:g}")
    _run(check_z_limits, z_min, z_max)
    table, _ = _read_locs(locs)
    if len(table) == 0:
        _fail(f"{locs.name} holds no localizations")
    table = _usable(table, all_flags)
    zr = None
    if z_min is not None or z_max is not None:
        zr = (
            float(table.z_nm.min()) if z_min is None else z_min,
            float(table.z_nm.max()) if z_max is None else z_max,
        )
        if not zr[0] < zr[1]:
            _fail(f"--z-min {zr[0]:g} must be below --z-max {zr[1]:g}")
    # Everything that can fail is computed before anything is written.
    vol = vmeta = None
    if volume is not None:
        vol, vmeta = _run(render_volume, table, px_nm=voxel[0], pz_nm=voxel[1], z_range=zr)
    res, frc_msg = frc_report(table)
    # Every file is written under a temporary name and renamed only when all are written,
    # so a failure (e.g. of the volume) leaves none of them behind.
    from contextlib import ExitStack

    from .io.atomic import atomic_path

    with ExitStack() as stack:
        wanted = (out, frc_plot if res is not None else None, volume)
        tmp = {p: _run(stack.enter_context, atomic_path(p)) for p in wanted if p is not None}
        _run(plot_projections, table, tmp[out], px_nm=px, z_range=zr, title=locs.name)
        if frc_plot is not None and res is not None:
            _run(plot_frc, res, tmp[frc_plot])
        if volume is not None:
            _run(write_volume_tiff, tmp[volume], vol, voxel[0], voxel[1], vmeta["z0_nm"])
    typer.echo(f"wrote {out}")
    typer.echo(frc_msg)
    if frc_plot is not None and res is not None:
        typer.echo(f"wrote {frc_plot}")
    elif frc_plot is not None:
        _note(f"--frc {frc_plot.name} was not written: there is no FRC curve to draw")
    if volume is not None:
        typer.echo(f"wrote {volume} ({vol.shape[0]} planes of {vol.shape[1]}x{vol.shape[2]})")


@app.command(cls=_Command)
def drift(
    locs: Annotated[Path, typer.Argument(help="Localization table (any supported format).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Corrected table.")],
    method: Annotated[str, typer.Option(help="rcc or fiducial.")] = "rcc",
    segments: Annotated[int, typer.Option(help="Time segments (rcc).", min=2)] = 10,
    plot: Annotated[Path | None, typer.Option(help="Drift curve (.png).")] = None,
    bin_nm: Annotated[float, typer.Option(help="Histogram bin (nm; rcc).")] = 20.0,
    no_z: Annotated[bool, typer.Option("--no-z", help="Estimate x and y only (rcc).")] = False,
    force: Annotated[
        bool, typer.Option(help="Apply an estimate flagged unreliable anyway.")
    ] = False,
    all_flags: Annotated[
        bool, typer.Option(help="Estimate from flagged fits too (all rows are corrected).")
    ] = False,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Estimate the drift (x, y, z) and write the table with it removed."""
    from .drift import (
        apply_drift,
        fiducial_drift,
        lateral_only,
        no_drift_caution,
        plot_drift,
        rcc_drift,
    )

    out = _table_output(output, overwrite=overwrite, inputs=[locs])
    if plot is not None:
        _check_suffix(plot, _FIGURE_SUFFIXES, "--plot")
        _new_output(plot, overwrite=overwrite, inputs=[locs, out])
    if method not in ("rcc", "fiducial"):
        _fail(f"--method must be rcc or fiducial, got {method!r}")
    if not (np.isfinite(bin_nm) and bin_nm > 0):
        _fail(f"--bin-nm must be > 0, got {bin_nm:g}")
    table, meta = _read_locs(locs)
    _picasso_kwargs(out, meta)  # an impossible output is refused before the work
    _usable(table, all_flags)  # says how many flagged rows the estimate leaves out
    if method == "rcc":
        # Its warnings are said below: in the refusal of an unreliable estimate, else after it.
        est = _run(
            rcc_drift,
            table,
            segments=segments,
            bin_nm=bin_nm,
            estimate_z=not no_z,
            all_flags=all_flags,
            log_warnings=False,
        )
    else:
        est = _run(fiducial_drift, table, all_flags=all_flags, log_warnings=False)
    xy = None if force else lateral_only(est)
    if xy is not None:
        # x and y are sound, z is not: correct what is sound rather than nothing
        why = xy.details["z_dropped"][0].removeprefix("z: ")
        _note(f"z drift not corrected ({why}); x and y were (--force applies z too)")
        est = xy
    if not est.reliable and not force:
        # a refused run writes nothing, its plot neither (a rerun would find it in the way)
        why = "; ".join(est.warnings) or "its checks failed"
        _fail(
            f"the drift estimate is unreliable ({why}); nothing was written; --force applies "
            "it anyway (with --plot to see it)"
        )
    if plot is not None:
        _run(plot_drift, est, plot)
        typer.echo(f"wrote {plot}")
    for w in est.warnings:
        typer.echo(f"warning: {w}", err=True)
    typer.echo(f"drift ({est.method}): range {est.range_text()}")
    caution = no_drift_caution(est)
    if caution:
        typer.echo(f"caution: {caution}; it was applied (compare with --plot)")
    corrected = apply_drift(table, est)
    meta = {**meta, "drift": {"method": est.method, "reliable": bool(est.reliable)}}
    if est.method == "rcc":  # how a report estimates the residual drift the same way
        meta["drift"]["segments"] = int(est.details.get("segments", segments))
        meta["drift"]["z_corrected"] = bool(est.details.get("z_estimated", True))
    if caution:
        meta["drift"]["caution"] = caution
    _write_locs(corrected, out, meta)
    typer.echo(f"wrote {out}")


@app.command(name="filter", cls=_Command)
def filter_cmd(
    locs: Annotated[Path, typer.Argument(help="Localization table (any supported format).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Filtered table.")],
    photons_min: Annotated[float | None, typer.Option(help="Fewest photons.")] = None,
    photons_max: Annotated[float | None, typer.Option(help="Most photons.")] = None,
    sigma_max: Annotated[float | None, typer.Option(help="Max lateral sigma (nm).")] = None,
    sigma_z_max: Annotated[float | None, typer.Option(help="Max axial sigma (nm).")] = None,
    gof_max: Annotated[float | None, typer.Option(help="Largest deviance per dof.")] = None,
    z_min: Annotated[float | None, typer.Option(help="Lowest z (nm).")] = None,
    z_max: Annotated[float | None, typer.Option(help="Highest z (nm).")] = None,
    all_flags: Annotated[
        bool, typer.Option(help="Keep flagged fits too (default: only 'ok').")
    ] = False,
    merge: Annotated[
        bool, typer.Option(help="Merge a molecule's localizations in consecutive frames.")
    ] = False,
    max_distance: Annotated[
        float | None,
        typer.Option(help="Merge distance (nm); default 4 sqrt(2) x the median sigma, >= 20 nm."),
    ] = None,
    max_gap: Annotated[int, typer.Option(help="Dark frames a merged track may skip.")] = 1,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Filter localizations by photons, uncertainty, fit quality and z; merge blinks."""
    from .postprocess import filter_locs, merge_blinks

    out = _table_output(output, overwrite=overwrite, inputs=[locs])
    if merge and out.suffix.lower() not in (".parquet", ".pq"):
        _note("only Parquet keeps the merged rows' n_frames and last_frame columns")
    table, meta = _read_locs(locs)
    _picasso_kwargs(out, meta)  # an impossible output is refused before the work
    if len(table):
        # The coordinate part of the rule (select_usable); filter_locs counts the flags itself.
        table = _usable(table, True)
    _run(check_z_limits, z_min, z_max)
    for flag, value in (("--sigma-max", sigma_max), ("--sigma-z-max", sigma_z_max)):
        if value is not None:
            _run(check_length_nm, value, flag, TOLERANCE_RANGE_NM)
    zr = None
    if z_min is not None or z_max is not None:
        zr = (-np.inf if z_min is None else z_min, np.inf if z_max is None else z_max)
    res = _run(
        filter_locs,
        table,
        photons_min=photons_min,
        photons_max=photons_max,
        sigma_xy_max_nm=sigma_max,
        sigma_z_max_nm=sigma_z_max,
        gof_max=gof_max,
        z_range=zr,
        flags=None if all_flags else ("ok",),
    )
    kept = res.locs
    removed = ", ".join(f"{k} {v:,}" for k, v in res.removed.items() if v) or "none"
    typer.echo(f"kept {len(kept):,} of {len(table):,} localizations (removed: {removed})")
    if merge:
        n0 = len(kept)
        kept = _run(merge_blinks, kept, max_distance_nm=max_distance, max_gap=max_gap)
        typer.echo(f"merged {n0:,} localizations into {len(kept):,}")
    _write_locs(kept, out, {**meta, "filter": {"merge": merge}})
    typer.echo(f"wrote {out}")


@app.command(cls=_Command)
def report(
    locs: Annotated[Path, typer.Argument(help="Localization table (any supported format).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Report (.html).")] = Path(
        "report.html"
    ),
    truth: Annotated[
        Path | None, typer.Option(help="Ground truth CSV: adds the evaluation.")
    ] = None,
    pixel_size: Annotated[
        float | None,
        typer.Option(
            help="Camera pixel size (nm): for truth given in pixels and for the --movie "
            "overlay (default: the table's or the movie's)."
        ),
    ] = None,
    movie: Annotated[
        Path | None,
        typer.Option(help="The movie the table was made from: adds an overlay of one frame."),
    ] = None,
    all_flags: Annotated[bool, typer.Option(help=_ALL_FLAGS_HELP)] = False,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Write a one-page HTML quality report (histograms, drift, image, FRC, evaluation)."""
    from .report import write_report

    out = _new_output(output, overwrite=overwrite, inputs=[locs, truth, movie])
    if pixel_size is not None:
        _run(check_pixel_size, pixel_size)
    if movie is not None and not movie.is_file():
        _fail(f"{str(movie)!r} does not exist or is not a file")
    table, meta = _read_locs(locs)
    truth_df = None
    if truth is not None:
        if not truth.is_file():
            _fail(f"{str(truth)!r} does not exist or is not a file")
        truth_df, said = _read_truth(truth, pixel_size, meta)
        for line in said:
            typer.echo(f"caution: {line}")
    _run(
        write_report,
        table,
        out,
        truth=truth_df,
        metadata=meta,
        title=f"sparseloc: {locs.name}",
        all_flags=all_flags,
        movie=movie,
        pixel_size=pixel_size,
    )
    typer.echo(f"wrote {out}")


@app.command(cls=_Command)
def overlay(
    movie: Annotated[Path, typer.Argument(help="Camera movie (TIFF / OME-TIFF).")],
    locs: Annotated[Path, typer.Argument(help="Localization table (any supported format).")],
    frame: Annotated[int, typer.Option(help="Frame to draw (0-based).")] = 0,
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Picture (.png, .pdf or .svg).")
    ] = Path("overlay.png"),
    pixel_size: Annotated[
        float | None,
        typer.Option(help="Camera pixel size (nm); default: the table's, else the movie's."),
    ] = None,
    region: Annotated[
        str | None,
        typer.Option(
            help="Zoom: pixel columns and rows X0:X1,Y0:Y1 of the frame (default: all of it)."
        ),
    ] = None,
    overwrite: Annotated[bool, typer.Option(help=_OVERWRITE_HELP)] = False,
) -> None:
    """Draw one frame with its localizations: circles coloured by z, flagged fits as grey x."""
    from .overlay import check_table_movie, overlay_rows, plot_overlay
    from .report import _overlay_pixel_size

    out = _new_output(output, overwrite=overwrite, inputs=[movie, locs])
    _check_suffix(out, _FIGURE_SUFFIXES, "the picture")
    if pixel_size is not None:
        _run(check_pixel_size, pixel_size)
    if not movie.is_file():
        _fail(f"{str(movie)!r} does not exist or is not a file")
    if locs.suffix.lower() in (".tif", ".tiff") and movie.suffix.lower() not in (".tif", ".tiff"):
        _fail(
            f"{locs.name!r} looks like the movie and {movie.name!r} like the localizations: the "
            "movie goes first (sparseloc overlay MOVIE LOCS)"
        )
    table, meta = _read_locs(locs)
    mov = _open_movie([movie], "the movie goes first, the table second")
    with mov:
        if not 0 <= frame < mov.n_frames:
            _fail(
                f"--frame {frame} is outside the movie {movie.name!r}, whose frames are "
                f"0 to {mov.n_frames - 1}"
            )
        note = _run(check_table_movie, meta, mov.shape, locs.name, movie.name)
        if note:
            _note(note)
        px = _run(_overlay_pixel_size, pixel_size, meta, mov.pixel_size)
        image = _run(mov.__getitem__, frame)
    box = _region(region) if region is not None else None
    _run(plot_overlay, image, table, frame_index=frame, pixel_size=px, path=out, region=box)
    n = len(overlay_rows(table, frame, px, np.shape(image), box))  # the ones drawn
    typer.echo(f"wrote {out} (frame {frame}, {n} localizations)")


def _region(text: str) -> tuple[int, int, int, int]:
    """``X0:X1,Y0:Y1`` (pixels) as (x0, x1, y0, y1); refused in one sentence otherwise."""
    try:
        xs, ys = str(text).split(",")
        x0, x1 = (int(v) for v in xs.split(":"))
        y0, y1 = (int(v) for v in ys.split(":"))
    except ValueError:
        _fail(f"--region must look like X0:X1,Y0:Y1 (pixels), got {text!r}")
    return x0, x1, y0, y1


def main() -> None:
    """Entry point of the ``sparseloc`` command."""
    app()


if __name__ == "__main__":
    main()
