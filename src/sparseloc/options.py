"""The options of ``sparseloc localize`` (also the keys of a TOML file's ``[localize]`` table)
and of the camera (every command's camera flags, a TOML file's ``[camera]`` table): their
defaults and types, checked once. Kept free of heavy imports, so that the command line
can show the defaults in ``--help`` without loading the solvers; :mod:`sparseloc.config`
turns the options into a run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = [
    "CAMERA_DEFAULTS",
    "LOCALIZE_DEFAULTS",
    "check_options",
    "read_camera_config",
    "read_config",
]

#: The camera's options, the same on every command (``calibrate``, ``localize``,
#: ``simulate``) and in a TOML file's ``[camera]`` table (where ``kind`` stands for
#: ``camera``): the noise model, offset (ADU), gain (e-/ADU), EM gain, quantum efficiency,
#: read noise (e- rms) and the sCMOS map files. :func:`sparseloc.camera.camera_from_options`
#: turns them into a :class:`~sparseloc.camera.Camera`.
CAMERA_DEFAULTS: dict[str, Any] = {
    "camera": "ideal",
    "offset": 100.0,
    "gain": 1.0,
    # none for an EMCCD (camera_from_options refuses it: forgotten, every count reads as that
    # many times the photons); 1 for the other cameras
    "em_gain": None,
    "qe": 1.0,
    "read_noise": 0.0,
    "offset_map": None,
    "variance_map": None,
    "gain_map": None,
}
#: Keys of a ``[camera]`` table that differ from the option's name.
_CAMERA_TABLE_KEYS = {"kind": "camera"}


#: The options of ``sparseloc localize`` (and keys of a TOML file's ``[localize]`` table) with
#: their defaults; ``None`` means "derived" (from the PSF, the movie or the machine).
LOCALIZE_DEFAULTS: dict[str, Any] = {
    # no default: a built-in model is hardly ever the microscope's, and with a wrong PSF a
    # run is long and its table void (config.build_model refuses a missing one)
    "psf": None,
    "pixel_size": None,
    **CAMERA_DEFAULTS,
    "method": "frame",
    "window": None,
    "margin": None,
    "z_min": None,
    "z_max": None,
    "min_snr": 5.0,
    "background": "auto",
    "refine": True,
    "second_start": True,
    "regrow": True,
    "haze": False,
    "frames": None,
    "format": None,
    "workers": None,  # one per available core (see sparseloc.cli)
    "engine": "auto",
    "n_sample": None,
    "focal_depth": None,
    # Optics of pupil models (None: the model's own, NA 1.45 and 670 nm for mask files).
    "na": None,
    "wavelength": None,
    "mask_radius": None,
    "blur": None,
    "run_dir": None,
    "chunk_frames": None,
    "scheduler": None,
    "overwrite": False,
    "relocate": None,  # LocalizeParams's default
    "frame_schedule": None,  # LocalizeParams's default
    "saturation": None,  # the movie's clipping level, else its integer type's maximum (ADU)
}

_NUMBERS = ("pixel_size", "offset", "gain", "em_gain", "qe", "z_min", "z_max", "min_snr")
_NUMBERS += ("n_sample", "focal_depth", "read_noise", "na", "wavelength", "mask_radius", "blur")
_NUMBERS += ("saturation",)
_WHOLE = ("window", "margin", "workers", "chunk_frames", "relocate")
_FLAGS = ("refine", "second_start", "regrow", "haze", "overwrite")
_TEXT = ("psf", "camera", "method", "background", "frames", "format", "engine", "scheduler")
_TEXT += ("frame_schedule",)
_PATHS = ("offset_map", "variance_map", "gain_map", "run_dir")
#: Whole-number options with a lower bound that no later check enforces (``workers = 0``
#: would otherwise fall back to the default silently).
_MINIMUM = {"workers": 1}
#: Whole numbers beyond this overflow the C integers they end up in (a traceback otherwise).
_WHOLE_MAX = 2**31 - 1


def check_options(options: dict[str, Any], source: str = "the options") -> dict[str, Any]:
    """``options`` with unknown keys and wrongly typed values refused in one sentence
    (ValueError naming ``source``); ``None`` stands for the default."""
    unknown = sorted(set(options) - set(LOCALIZE_DEFAULTS))
    if unknown:
        raise ValueError(
            f"unknown keys in {source}: {', '.join(unknown)}; allowed: "
            f"{', '.join(sorted(LOCALIZE_DEFAULTS))}"
        )
    kinds = [(_NUMBERS, "a number"), (_WHOLE, "a whole number"), (_FLAGS, "true or false")]
    kinds += [(_TEXT, "a text"), (_PATHS, "a path")]
    for key, value in options.items():
        if value is None:
            continue
        kind = next(kind for names, kind in kinds if key in names)
        ok = {
            "a number": isinstance(value, int | float) and not isinstance(value, bool),
            "a whole number": isinstance(value, int) and not isinstance(value, bool),
            "true or false": isinstance(value, bool),
            "a text": isinstance(value, str),
            "a path": isinstance(value, str | Path),
        }[kind]
        if not ok:
            raise ValueError(f"{key} in {source} must be {kind}; got {value!r}")
        if kind == "a whole number":
            if key in _MINIMUM and value < _MINIMUM[key]:
                raise ValueError(f"{key} must be >= {_MINIMUM[key]} in {source}, got {value}")
            if abs(value) > _WHOLE_MAX:
                raise ValueError(f"{key} in {source} is too large: {value}")
    return options


def _read_toml(path: str | Path) -> tuple[Path, dict[str, Any]]:
    """The parsed TOML file ``path``; ValueError in one sentence naming it otherwise."""
    import tomllib

    src = Path(path)
    if not src.is_file():
        raise ValueError(f"the config file {str(src)!r} does not exist")
    try:
        cfg = tomllib.loads(src.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError) as exc:
        raise ValueError(f"cannot read the config file {str(src)!r}: {exc}") from exc
    return src, cfg


def _table(cfg: dict[str, Any], name: str, src: Path) -> dict[str, Any]:
    """The table ``name`` of a parsed TOML file (empty when absent), ``-`` in keys read as
    ``_``."""
    table = cfg.get(name, {})
    if not isinstance(table, dict):
        raise ValueError(
            f"{name} in {src.name} must be a table ([{name}] and its keys below it); got {table!r}"
        )
    return {str(k).replace("-", "_"): v for k, v in table.items()}


def _camera_table(cfg: dict[str, Any], src: Path) -> dict[str, Any]:
    """The ``[camera]`` table of a parsed TOML file as camera options, checked."""
    table = _table(cfg, "camera", src)
    where = f"[camera] of {src.name}"
    # the noise model's kind is ``kind`` in this table and ``camera`` as a flag (--camera)
    # and in [localize]: either name is read here
    known = {*CAMERA_DEFAULTS, *_CAMERA_TABLE_KEYS}
    unknown = sorted(set(table) - known)
    both = [k for k, v in _CAMERA_TABLE_KEYS.items() if k in table and v in table]
    if both:
        raise ValueError(
            f"{where} gives both {both[0]} and {_CAMERA_TABLE_KEYS[both[0]]}; keep one"
        )
    if unknown:
        raise ValueError(
            f"unknown keys in {where}: {', '.join(unknown)}; allowed: {', '.join(sorted(known))}"
        )
    return check_options({_CAMERA_TABLE_KEYS.get(k, k): v for k, v in table.items()}, where)


def read_camera_config(path: str | Path) -> dict[str, Any]:
    """The camera options (:data:`CAMERA_DEFAULTS` keys) of a TOML file's ``[camera]`` table.

    Parameters
    ----------
    path : str or Path
        TOML file; its other tables are not read.

    Returns
    -------
    dict
        Option name -> value (``kind`` returned as ``camera``).

    Raises
    ------
    ValueError
        If the file does not exist or is not UTF-8 TOML, or a key is unknown or wrongly typed
        (one sentence naming the file).
    """
    src, cfg = _read_toml(path)
    return _camera_table(cfg, src)


def read_config(path: str | Path) -> dict[str, Any]:
    """The options of a TOML file: its ``[localize]`` table (or its top level when it has
    neither a ``[localize]`` nor a ``[camera]`` table) and its ``[camera]`` table, with ``-``
    in keys read as ``_``, checked by :func:`check_options`.

    The camera keys may stand in ``[camera]`` (as every command reads them) or, as before, in
    ``[localize]``; one given in both is refused.

    Parameters
    ----------
    path : str or Path
        TOML file.

    Returns
    -------
    dict
        Option name -> value.

    Raises
    ------
    ValueError
        If the file does not exist, is not UTF-8 TOML, its ``localize`` or ``camera`` entry is
        not a table, or an option is unknown, wrongly typed or given twice (one sentence
        naming the file).
    """
    src, cfg = _read_toml(path)
    if "localize" in cfg or "camera" in cfg:
        table = _table(cfg, "localize", src)
    else:
        table = {str(k).replace("-", "_"): v for k, v in cfg.items()}
    options = check_options(table, src.name)
    camera = _camera_table(cfg, src)
    twice = sorted(set(camera) & set(options))
    if twice:
        raise ValueError(
            f"{', '.join(twice)} given in both [camera] and [localize] of {src.name}; "
            "keep the camera in [camera]"
        )
    return {**options, **camera}
