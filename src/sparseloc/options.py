"""The options of ``sparseloc localize`` (also the keys of a TOML file's ``[localize]`` table):
their defaults and types, checked once. Kept free of heavy imports, so that the command line
can show the defaults in ``--help`` without loading the solvers; :mod:`sparseloc.config`
turns the options into a run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

__all__ = ["LOCALIZE_DEFAULTS", "check_options", "read_config"]


#: The options of ``sparseloc localize`` (and keys of a TOML file's ``[localize]`` table) with
#: their defaults; ``None`` means "derived" (from the PSF, the movie or the machine).
LOCALIZE_DEFAULTS: dict[str, Any] = {
    "psf": "dh",
    "pixel_size": None,
    "offset": 100.0,
    "gain": 1.0,
    "em_gain": 1.0,
    "qe": 1.0,
    "camera": "ideal",
    "method": "frame",
    "window": None,
    "margin": None,
    "z_min": None,
    "z_max": None,
    "min_snr": 5.0,
    "background": "auto",
    "refine": True,
    "frames": None,
    "format": None,
    "workers": None,  # one per available core (see sparseloc.cli)
    "engine": "auto",
    "n_sample": None,
    "focal_depth": None,
    "read_noise": 0.0,
    "offset_map": None,
    "variance_map": None,
    "gain_map": None,
    "run_dir": None,
    "chunk_frames": None,
    "scheduler": None,
    "overwrite": False,
    "relocate": None,  # LocalizeParams's default
}

_NUMBERS = ("pixel_size", "offset", "gain", "em_gain", "qe", "z_min", "z_max", "min_snr")
_NUMBERS += ("n_sample", "focal_depth", "read_noise")
_WHOLE = ("window", "margin", "workers", "chunk_frames", "relocate")
_FLAGS = ("refine", "overwrite")
_TEXT = ("psf", "camera", "method", "background", "frames", "format", "engine", "scheduler")
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


def read_config(path: str | Path) -> dict[str, Any]:
    """The options of a TOML file: its ``[localize]`` table (or its top level when it has
    none), with ``-`` in keys read as ``_``, checked by :func:`check_options`.

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
        If the file does not exist, is not UTF-8 TOML, its ``localize`` entry is not a table,
        or an option is unknown or wrongly typed (one sentence naming the file).
    """
    import tomllib

    src = Path(path)
    if not src.is_file():
        raise ValueError(f"the config file {str(src)!r} does not exist")
    try:
        cfg = tomllib.loads(src.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError) as exc:
        raise ValueError(f"cannot read the config file {str(src)!r}: {exc}") from exc
    table = cfg.get("localize", cfg)
    if not isinstance(table, dict):
        raise ValueError(
            f"localize in {src.name} must be a table ([localize] and its keys below it); "
            f"got {table!r}"
        )
    return check_options({str(k).replace("-", "_"): v for k, v in table.items()}, src.name)
