"""Localization tables: the canonical in-memory table and its file formats.

The table is a :class:`pandas.DataFrame` with the columns :data:`LOCS_COLUMNS`, in native
sparseloc conventions (design.md section 3): lengths in nm, brightness in photons, background in
photons per pixel, 0-based frames, ``x`` along columns and ``y`` along rows with the origin at
the outer corner of pixel (0, 0).

Formats, each written atomically (temporary file in the destination folder, then a rename):

``parquet``
    Every column at full precision; analysis metadata as JSON under the Parquet schema metadata
    key ``b"sparseloc"``. Lossless.
``thunderstorm``
    ThunderSTORM CSV: the quoted header ThunderSTORM itself writes, 1-based ``id`` and
    ``frame``, nm and photons. Native coordinates need no shift: ThunderSTORM places the centre
    of pixel ``i`` at ``i + 0.5`` pixels. sparseloc's extra columns follow the standard ones;
    every cell is numeric (ThunderSTORM's importer parses every cell as a number), so ``flag``
    is written as an integer code (:data:`FLAG_CODES`). Lossless for float64 values and for the
    flags in :data:`FLAG_CODES`.
``picasso``
    Picasso HDF5: dataset ``/locs`` (structured array, Picasso's field names and dtypes), ``x``
    and ``y`` in camera pixels with the centre of the first pixel at 0, ``z`` and ``lpz`` in nm,
    plus the YAML sidecar whose first document holds ``Width``, ``Height``, ``Frames`` and
    ``Pixelsize``. Values are float32.
``smlm``
    SMLM-challenge CSV ``Ground-truth,frame,xnano,ynano,znano,intensity`` with 1-based
    ``Ground-truth`` (row id) and ``frame``; only positions and photons survive.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import math
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from .. import __version__
from .atomic import atomic_path

__all__ = [
    "FLAG_CODES",
    "FORMATS",
    "LOCS_COLUMNS",
    "PICASSO_DTYPE",
    "SMLM_COLUMNS",
    "THUNDERSTORM_COLUMNS",
    "THUNDERSTORM_EXTRA_COLUMNS",
    "check_locs",
    "complete_locs",
    "empty_locs",
    "read_parquet",
    "read_picasso_hdf5",
    "read_smlm_csv",
    "read_table",
    "read_thunderstorm_csv",
    "write_parquet",
    "write_picasso_hdf5",
    "write_smlm_csv",
    "write_table",
    "write_thunderstorm_csv",
]

log = logging.getLogger(__name__)

#: Columns of every localization table, in this order.
LOCS_COLUMNS: tuple[str, ...] = (
    "frame",
    "x_nm",
    "y_nm",
    "z_nm",
    "photons",
    "background",
    "sigma_x_nm",
    "sigma_y_nm",
    "sigma_z_nm",
    "sigma_photons",
    "gof",
    "flag",
    "window_id",
)
_INT_COLUMNS = ("frame", "window_id")
_FLOAT_COLUMNS = tuple(c for c in LOCS_COLUMNS if c not in (*_INT_COLUMNS, "flag"))
#: Columns a partial table must have before :func:`complete_locs` fills in the rest.
_CORE_COLUMNS = ("frame", "x_nm", "y_nm")
_DEFAULTS: dict[str, Any] = {
    "z_nm": 0.0,
    "photons": np.nan,
    "background": np.nan,
    "sigma_x_nm": np.nan,
    "sigma_y_nm": np.nan,
    "sigma_z_nm": np.nan,
    "sigma_photons": np.nan,
    "gof": np.nan,
    "flag": "ok",
    "window_id": -1,
}

#: Integer codes of the flags in numeric-only formats (ThunderSTORM CSV, Picasso HDF5).
FLAG_CODES: dict[str, int] = {
    "ok": 0,
    "outside": 1,
    "z_edge": 2,
    "not_converged": 3,
    "diverged": 4,
}
_FLAG_OTHER = "other"
_FLAG_OTHER_CODE = -1

#: Format names accepted by :func:`write_table`.
FORMATS: tuple[str, ...] = ("parquet", "thunderstorm", "picasso", "smlm")
_SUFFIX_FORMATS = {
    ".parquet": "parquet",
    ".pq": "parquet",
    ".csv": "thunderstorm",
    ".hdf5": "picasso",
    ".h5": "picasso",
}

#: The standard ThunderSTORM columns, in the order written (labels as ThunderSTORM writes them).
THUNDERSTORM_COLUMNS: tuple[str, ...] = (
    "id",
    "frame",
    "x [nm]",
    "y [nm]",
    "z [nm]",
    "intensity [photon]",
    "offset [photon]",
    "bkgstd [photon]",
    "uncertainty_xy [nm]",
    "uncertainty_z [nm]",
)
#: sparseloc columns appended after :data:`THUNDERSTORM_COLUMNS` (all numeric).
THUNDERSTORM_EXTRA_COLUMNS: tuple[str, ...] = (
    "sigma_x [nm]",
    "sigma_y [nm]",
    "sigma_photons [photon]",
    "gof",
    "flag",
    "window_id",
)

#: SMLM-challenge CSV header (as in the challenge's ``activations.csv``).
SMLM_COLUMNS: tuple[str, ...] = ("Ground-truth", "frame", "xnano", "ynano", "znano", "intensity")

#: Fields of Picasso's ``/locs`` dataset written by sparseloc (Picasso names and dtypes first,
#: then sparseloc's ``gof``, ``flag`` code and ``window_id``).
PICASSO_DTYPE = np.dtype(
    [
        ("frame", "<u4"),
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("photons", "<f4"),
        ("bg", "<f4"),
        ("lpx", "<f4"),
        ("lpy", "<f4"),
        ("lpz", "<f4"),
        ("photons_unc", "<f4"),
        ("gof", "<f4"),
        ("flag", "<i2"),
        ("window_id", "<i8"),
    ]
)

_PARQUET_KEY = b"sparseloc"
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_PARQUET_MAGIC = b"PAR1"
_LENGTH_UNITS = {"nm": 1.0, "um": 1000.0, "µm": 1000.0}


# --------------------------------------------------------------------------------------------
# the table
# --------------------------------------------------------------------------------------------


def empty_locs() -> pd.DataFrame:
    """Return an empty localization table with the canonical columns and dtypes.

    Returns
    -------
    DataFrame
        Zero rows; ``frame`` and ``window_id`` int64, ``flag`` str, the rest float64.
    """
    data: dict[str, pd.Series] = {}
    for col in LOCS_COLUMNS:
        if col in _INT_COLUMNS:
            data[col] = pd.Series([], dtype=np.int64)
        elif col == "flag":
            data[col] = pd.Series([], dtype=np.float64).astype(str)
        else:
            data[col] = pd.Series([], dtype=np.float64)
    return pd.DataFrame(data)


def check_locs(df: pd.DataFrame, *, what: str = "localization table") -> pd.DataFrame:
    """Validate a localization table and return it with canonical dtypes.

    Parameters
    ----------
    df : DataFrame
        Table with all of :data:`LOCS_COLUMNS`: ``frame`` (0-based), positions ``x_nm, y_nm,
        z_nm`` (nm, native coordinates), ``photons``, ``background`` (photons/pixel),
        uncertainties ``sigma_x_nm, sigma_y_nm, sigma_z_nm`` (nm) and ``sigma_photons``
        (photons), ``gof``, ``flag`` ("ok" or a reason) and ``window_id``.
    what : str
        Name of the table in error messages.

    Returns
    -------
    DataFrame
        A copy with :data:`LOCS_COLUMNS` first (``frame``, ``window_id`` int64; ``flag`` str;
        the rest float64, NaN and infinities allowed) and any other columns after them.

    Raises
    ------
    ValueError
        If ``df`` is not a DataFrame, columns are missing (they are named), frames are not
        non-negative integers, a numeric column holds text, or a flag is missing.
    """
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"the {what} must be a pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in LOCS_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"the {what} is missing the column(s) {', '.join(missing)}")
    out = df.copy()
    for col in _INT_COLUMNS:
        vals = _numeric(out[col], col, what)
        if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
            raise ValueError(f"the {what} column {col!r} must hold integers")
        if col == "frame" and np.any(vals < 0):
            raise ValueError(f"the {what} column 'frame' must be >= 0 (frames are 0-based)")
        out[col] = vals.astype(np.int64)
    for col in _FLOAT_COLUMNS:
        out[col] = _numeric(out[col], col, what)
    if out["flag"].isna().any():
        raise ValueError(f"the {what} column 'flag' has missing values (use 'ok' or a reason)")
    out["flag"] = out["flag"].astype(str)
    rest = [c for c in out.columns if c not in LOCS_COLUMNS]
    return out[list(LOCS_COLUMNS) + rest].reset_index(drop=True)


def complete_locs(df: pd.DataFrame, *, what: str = "localization table") -> pd.DataFrame:
    """Fill the columns a partial table lacks with defaults, then validate it.

    Parameters
    ----------
    df : DataFrame
        Table with at least ``frame``, ``x_nm`` and ``y_nm`` (e.g. a ground-truth table
        ``frame, x_nm, y_nm, z_nm, photons``).
    what : str
        Name of the table in error messages.

    Returns
    -------
    DataFrame
        As from :func:`check_locs`; missing ``z_nm`` is 0 nm (focal plane), ``flag`` is "ok",
        ``window_id`` is -1 and every other missing column is NaN.

    Raises
    ------
    ValueError
        If one of ``frame, x_nm, y_nm`` is missing, or as :func:`check_locs`.
    """
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"the {what} must be a pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in _CORE_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"the {what} is missing the column(s) {', '.join(missing)}")
    out = df.copy()
    for col, value in _DEFAULTS.items():
        if col not in out.columns:
            out[col] = value
    return check_locs(out, what=what)


def _numeric(series: pd.Series, col: str, what: str) -> np.ndarray:
    try:
        return pd.to_numeric(series, errors="raise").to_numpy(dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"the {what} column {col!r} must hold numbers") from exc


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _dest(path: str | Path) -> Path:
    dest = Path(path)
    if dest.is_dir():
        raise ValueError(f"the output path {str(dest)!r} is a folder, not a file")
    folder = dest.parent if str(dest.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"the output folder {str(folder)!r} does not exist")
    return dest


def _source(path: str | Path) -> Path:
    src = Path(path)
    if not src.exists():
        raise FileNotFoundError(f"the file {str(src)!r} does not exist")
    if src.is_dir():
        raise IsADirectoryError(f"{str(src)!r} is a folder, not a table file")
    return src


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON-serialisable")


def _plain_metadata(metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    """Metadata as plain JSON types (numpy scalars and arrays, paths, sets converted)."""
    if metadata is None:
        return {}
    if not isinstance(metadata, Mapping):
        raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
    try:
        return json.loads(json.dumps(dict(metadata), default=_json_default, allow_nan=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata must be JSON-serialisable ({exc})") from exc


def _flag_mapping(flags: Iterable[str]) -> dict[str, int]:
    """:data:`FLAG_CODES` extended with codes for any other reasons present."""
    mapping = dict(FLAG_CODES)
    nxt = max(mapping.values()) + 1
    for reason in sorted(set(flags) - set(mapping)):
        mapping[reason] = nxt
        nxt += 1
    return mapping


def _encode_flags(flags: pd.Series, mapping: Mapping[str, int]) -> np.ndarray:
    codes = flags.map(mapping)
    unknown = codes.isna()
    if unknown.any():
        reasons = sorted(set(flags[unknown]))
        log.warning(
            "flag(s) %s have no numeric code in this format; written as %d (%r)",
            ", ".join(reasons),
            _FLAG_OTHER_CODE,
            _FLAG_OTHER,
        )
        codes = codes.fillna(_FLAG_OTHER_CODE)
    return codes.to_numpy(dtype=np.int64)


def _decode_flags(codes: Any, mapping: Mapping[str, int] | None = None) -> list[str]:
    inverse = {int(v): str(k) for k, v in (mapping or FLAG_CODES).items()}
    inverse.setdefault(_FLAG_OTHER_CODE, _FLAG_OTHER)
    out = []
    for c in np.asarray(codes, dtype=np.float64):
        out.append(inverse.get(int(c), _FLAG_OTHER) if np.isfinite(c) else _FLAG_OTHER)
    return out


def _csv_cells(frame: pd.DataFrame) -> pd.DataFrame:
    """Write infinities as Java spells them (``Infinity``), so ThunderSTORM can parse them."""
    out = frame
    for col in frame.columns:
        vals = frame[col]
        if vals.dtype.kind == "f" and np.isinf(vals.to_numpy()).any():
            if out is frame:
                out = frame.copy()
            text = vals.astype(object)
            text[np.isposinf(vals.to_numpy())] = "Infinity"
            text[np.isneginf(vals.to_numpy())] = "-Infinity"
            out[col] = text
    return out


@functools.cache
def _csv_kw() -> dict[str, Any]:
    """``read_csv`` arguments that read floats exactly. pandas < 3 needs the round-trip
    converter; pandas 3 deprecates it as exact by default, but pandas 3.0.6 was seen to read
    some values one unit in the last place off: the default is kept only where it reads back
    500 seeded random doubles exactly."""
    if int(pd.__version__.split(".")[0]) < 3:
        return {"float_precision": "round_trip"}
    rng = np.random.default_rng(0)
    values = np.concatenate(
        [rng.uniform(0.0, 1e4, 200), rng.normal(0.0, 500.0, 200), 10.0 ** rng.uniform(-8, 8, 100)]
    )
    text = "a\n" + "\n".join(repr(float(v)) for v in values) + "\n"
    got = pd.read_csv(io.StringIO(text))["a"].to_numpy()
    return {} if np.array_equal(got, values) else {"float_precision": "round_trip"}


def _read_csv(path: Path) -> pd.DataFrame:
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*float_precision.*")
            df = pd.read_csv(path, skipinitialspace=True, **_csv_kw())
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{str(path)!r} is not a readable CSV table ({exc})") from exc
    df.columns = [str(c).strip().strip("\"'`").strip() for c in df.columns]
    return df


def _frames_from_one_based(values: pd.Series, where: str) -> np.ndarray:
    vals = _numeric(values, "frame", where)
    if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
        raise ValueError(f"{where} column 'frame' must hold integers")
    if np.any(vals < 1):
        raise ValueError(f"{where} column 'frame' must be >= 1 (this format counts from 1)")
    return vals.astype(np.int64) - 1


# --------------------------------------------------------------------------------------------
# Parquet
# --------------------------------------------------------------------------------------------


def write_parquet(df: pd.DataFrame, path: str | Path, *, metadata: Mapping[str, Any]) -> Path:
    """Write a localization table as Parquet, atomically, with its analysis metadata.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`); extra columns are kept.
    path : str or Path
        Destination file; its folder must exist.
    metadata : dict
        Analysis parameters, PSF calibration hash, ``pixel_size`` (nm), ``shape`` (rows,
        cols), ``n_frames``... Stored as JSON under the schema metadata key ``b"sparseloc"``;
        ``sparseloc_version`` is added when absent. Numpy scalars and arrays are converted.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    ValueError
        If the folder does not exist, the table is invalid or the metadata is not
        JSON-serialisable.
    """
    table = check_locs(df)
    meta = _plain_metadata(metadata)
    meta.setdefault("sparseloc_version", __version__)
    dest = _dest(path)
    arrow = pa.Table.from_pandas(table, preserve_index=False)
    schema_meta = dict(arrow.schema.metadata or {})
    schema_meta[_PARQUET_KEY] = json.dumps(meta).encode("utf-8")
    arrow = arrow.replace_schema_metadata(schema_meta)
    with atomic_path(dest) as tmp:
        pq.write_table(arrow, tmp)
    log.info("wrote %d localizations to %s", len(table), dest)
    return dest


def read_parquet(path: str | Path) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Read a localization table written by :func:`write_parquet`.

    Parameters
    ----------
    path : str or Path
        Parquet file.

    Returns
    -------
    df : DataFrame
        Localization table (:func:`check_locs` form).
    metadata : dict
        The JSON metadata stored under ``b"sparseloc"`` (empty if there is none).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a Parquet file or lacks localization columns (they are named).
    """
    src = _source(path)
    try:
        arrow = pq.read_table(src)
    except (pa.ArrowInvalid, OSError) as exc:
        raise ValueError(f"{str(src)!r} is not a readable Parquet file ({exc})") from exc
    raw = (arrow.schema.metadata or {}).get(_PARQUET_KEY)
    meta: dict[str, Any] = json.loads(raw.decode("utf-8")) if raw else {}
    df = check_locs(arrow.to_pandas(), what=src.name)
    return df, meta


# --------------------------------------------------------------------------------------------
# ThunderSTORM CSV
# --------------------------------------------------------------------------------------------


def write_thunderstorm_csv(df: pd.DataFrame, path: str | Path) -> Path:
    """Write a localization table as a ThunderSTORM CSV, atomically.

    The header is ``"id","frame","x [nm]","y [nm]","z [nm]","intensity [photon]",
    "offset [photon]","bkgstd [photon]","uncertainty_xy [nm]","uncertainty_z [nm]"`` followed
    by :data:`THUNDERSTORM_EXTRA_COLUMNS`, every label quoted as ThunderSTORM writes them.
    ``id`` and ``frame`` are 1-based; x, y, z in nm (native coordinates equal ThunderSTORM's:
    it places the centre of pixel ``i`` at ``i + 0.5`` pixels); ``offset`` is the background
    (photons/pixel), ``bkgstd`` its Poisson standard deviation ``sqrt(background)``,
    ``uncertainty_xy = sqrt((sigma_x^2 + sigma_y^2) / 2)`` and ``uncertainty_z = sigma_z``
    (nm). ``flag`` is written as its integer code (:data:`FLAG_CODES`; other reasons as -1,
    read back as "other") because ThunderSTORM parses every cell as a number; NaN and
    infinities are written ``NaN``, ``Infinity``, ``-Infinity`` (Java's spelling). Floats are
    written with full precision.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`); extra columns are not written.
    path : str or Path
        Destination file; its folder must exist.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    ValueError
        If the folder does not exist or the table is invalid.
    """
    t = check_locs(df)
    dest = _dest(path)
    with np.errstate(invalid="ignore"):
        bkgstd = np.sqrt(t["background"].to_numpy())
        unc_xy = np.sqrt((t["sigma_x_nm"].to_numpy() ** 2 + t["sigma_y_nm"].to_numpy() ** 2) / 2)
    cols = list(THUNDERSTORM_COLUMNS) + list(THUNDERSTORM_EXTRA_COLUMNS)
    out = pd.DataFrame(
        {
            "id": np.arange(1, len(t) + 1, dtype=np.int64),
            "frame": t["frame"].to_numpy() + 1,
            "x [nm]": t["x_nm"].to_numpy(),
            "y [nm]": t["y_nm"].to_numpy(),
            "z [nm]": t["z_nm"].to_numpy(),
            "intensity [photon]": t["photons"].to_numpy(),
            "offset [photon]": t["background"].to_numpy(),
            "bkgstd [photon]": bkgstd,
            "uncertainty_xy [nm]": unc_xy,
            "uncertainty_z [nm]": t["sigma_z_nm"].to_numpy(),
            "sigma_x [nm]": t["sigma_x_nm"].to_numpy(),
            "sigma_y [nm]": t["sigma_y_nm"].to_numpy(),
            "sigma_photons [photon]": t["sigma_photons"].to_numpy(),
            "gof": t["gof"].to_numpy(),
            "flag": _encode_flags(t["flag"], FLAG_CODES),
            "window_id": t["window_id"].to_numpy(),
        },
        columns=cols,
    )
    header = ",".join(f'"{c}"' for c in cols) + "\n"
    with atomic_path(dest) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(header)
            _csv_cells(out).to_csv(fh, header=False, index=False, na_rep="NaN", lineterminator="\n")
    log.info("wrote %d localizations to %s (ThunderSTORM CSV)", len(t), dest)
    return dest


def _parse_label(label: str) -> tuple[str, str]:
    """Split a ThunderSTORM column label ``"name [unit]"`` into (name, unit)."""
    start, end = label.rfind("["), label.rfind("]")
    if start < 0 or end < start:
        return label.strip(), ""
    return label[:start].strip(), label[start + 1 : end].strip()


def read_thunderstorm_csv(path: str | Path) -> pd.DataFrame:
    """Read a ThunderSTORM CSV (written by ThunderSTORM or by :func:`write_thunderstorm_csv`).

    Columns are found by name whatever their order; lengths in ``nm`` or ``um`` are converted
    to nm. Files with only the standard columns are accepted: a missing ``z`` is 0 nm,
    ``sigma_x_nm`` and ``sigma_y_nm`` default to ``uncertainty_xy`` (isotropic), the
    background to ``offset`` (else ``bkgstd**2``), ``sigma_z_nm`` to ``uncertainty_z``,
    ``flag`` to "ok", ``window_id`` to -1, and anything else missing to NaN.

    Parameters
    ----------
    path : str or Path
        CSV file whose header has ThunderSTORM labels such as ``"x [nm]"``.

    Returns
    -------
    DataFrame
        Localization table (:func:`check_locs` form) with 0-based frames.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the header lacks ``frame``, ``x`` or ``y``, a length is in pixels (the pixel size
        is unknown here) or photons in ADU, frames are not 1-based integers, or cells are not
        numbers.
    """
    src = _source(path)
    raw = _read_csv(src)
    where = f"the ThunderSTORM table {src.name}"
    cols: dict[str, tuple[str, str]] = {}
    for label in raw.columns:
        name, unit = _parse_label(label)
        cols.setdefault(name, (label, unit))
    missing = [c for c in ("frame", "x", "y") if c not in cols]
    if missing:
        raise ValueError(f"{where} is missing the column(s) {', '.join(missing)}")

    def length(name: str) -> np.ndarray | None:
        if name not in cols:
            return None
        label, unit = cols[name]
        if unit not in _LENGTH_UNITS:
            raise ValueError(f"{where} column {label!r} is in {unit or 'no unit'}; export it in nm")
        return _numeric(raw[label], label, where) * _LENGTH_UNITS[unit]

    def photons(name: str) -> np.ndarray | None:
        if name not in cols:
            return None
        label, unit = cols[name]
        if unit not in ("photon", ""):
            raise ValueError(f"{where} column {label!r} is in {unit}; export it in photons")
        return _numeric(raw[label], label, where)

    def plain(name: str) -> np.ndarray | None:
        return _numeric(raw[cols[name][0]], name, where) if name in cols else None

    n = len(raw)
    nan = np.full(n, np.nan)

    def first(*options: np.ndarray | None, default: np.ndarray = nan) -> np.ndarray:
        return next((o for o in options if o is not None), default)

    unc_xy = length("uncertainty_xy")
    offset, bkgstd = photons("offset"), photons("bkgstd")
    out = pd.DataFrame(
        {
            "frame": _frames_from_one_based(raw[cols["frame"][0]], where),
            "x_nm": length("x"),
            "y_nm": length("y"),
            "z_nm": first(length("z"), default=np.zeros(n)),
            "photons": first(photons("intensity")),
            "background": first(offset, None if bkgstd is None else bkgstd**2),
            "sigma_x_nm": first(length("sigma_x"), unc_xy),
            "sigma_y_nm": first(length("sigma_y"), unc_xy),
            "sigma_z_nm": first(length("uncertainty_z")),
            "sigma_photons": first(photons("sigma_photons")),
            "gof": first(plain("gof")),
        }
    )
    if "flag" in cols:
        flags = raw[cols["flag"][0]]
        if pd.api.types.is_numeric_dtype(flags):
            out["flag"] = _decode_flags(flags.to_numpy())
        else:
            out["flag"] = flags.astype(str).str.strip()
    else:
        out["flag"] = "ok"
    out["window_id"] = first(plain("window_id"), default=np.full(n, -1.0))
    return check_locs(out, what=where)


# --------------------------------------------------------------------------------------------
# Picasso HDF5 + YAML
# --------------------------------------------------------------------------------------------


def _positive_number(value: Any, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if not math.isfinite(out) or out <= 0:
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return out


def _positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _image_shape(shape: Any) -> tuple[int, int]:
    try:
        dims = tuple(shape)
    except TypeError:
        dims = ()
    if len(dims) != 2:
        raise ValueError(f"shape must be (rows, cols) of the camera image, got {shape!r}")
    return _positive_int(dims[0], "shape[0] (rows)"), _positive_int(dims[1], "shape[1] (cols)")


def _from_info(info: list[dict[str, Any]], key: str) -> Any:
    """Look ``key`` up from the last YAML document to the first, as Picasso does."""
    for doc in reversed(info):
        if isinstance(doc, dict) and doc.get(key) is not None:
            return doc[key]
    return None


def write_picasso_hdf5(
    df: pd.DataFrame,
    path: str | Path,
    *,
    pixel_size: float,
    shape: tuple[int, int],
    n_frames: int,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Write a localization table as Picasso HDF5 plus its YAML sidecar, atomically.

    ``/locs`` is a structured array with the fields of :data:`PICASSO_DTYPE`: ``frame``
    (uint32, 0-based), ``x``, ``y`` in camera pixels with the centre of the first pixel at 0
    (``x = x_nm / pixel_size - 0.5``), ``z`` in nm, ``photons``, ``bg`` (photons/pixel),
    ``lpx``, ``lpy`` (localization precision, pixels), ``lpz`` (nm), ``photons_unc``
    (Picasso's name for the photon uncertainty), then sparseloc's ``gof``, ``flag`` (int16
    code; the code table is in the YAML) and ``window_id`` (int64), all float32 unless noted.
    Picasso reads extra fields as extra columns and saves them again; the flag is numeric so
    that Picasso Filter can histogram it and keep ``flag == 0`` ("ok"), which a text field
    would not allow. ``sx`` and ``sy`` (Gaussian PSF widths) are not written: sparseloc fits
    no Gaussian, and Picasso treats them as optional.

    The sidecar ``path.with_suffix(".yaml")`` holds two YAML documents: first ``Width``,
    ``Height``, ``Frames``, ``Pixelsize`` (nm); then ``Generated by`` and a ``sparseloc``
    mapping (``metadata``, the flag codes, the coordinate convention). The same list is also
    embedded as JSON in the ``/metadata`` dataset, as Picasso >= 0.11 does.

    Note that Picasso's loader drops rows with any NaN, with ``x < 0`` or ``y < 0`` (the
    outer half of the first pixel), ``x >= Width`` or ``y >= Height``, or negative ``lpx``,
    ``lpy``, ``lpz`` or ``photons``; :func:`read_picasso_hdf5` keeps every row.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`); extra columns are not written.
    path : str or Path
        Destination ``.hdf5`` file; its folder must exist.
    pixel_size : float
        Camera pixel size (nm).
    shape : tuple of int
        Camera image ``(rows, cols)``: ``Height``, ``Width`` (pixels).
    n_frames : int
        Number of frames in the movie (``Frames``); every ``frame`` must be below it.
    metadata : dict, optional
        Analysis metadata for the second YAML document (JSON-serialisable).

    Returns
    -------
    Path
        The HDF5 path written.

    Raises
    ------
    ValueError
        If the folder does not exist, the table is invalid, ``pixel_size``, ``shape`` or
        ``n_frames`` are not positive, or a frame is ``>= n_frames``.
    """
    t = check_locs(df)
    pixel = _positive_number(pixel_size, "pixel_size")
    rows, cols = _image_shape(shape)
    frames = _positive_int(n_frames, "n_frames")
    if len(t) and int(t["frame"].max()) >= frames:
        raise ValueError(
            f"frame {int(t['frame'].max())} is outside a movie of n_frames={frames} frames"
        )
    meta = _plain_metadata(metadata)
    dest = _dest(path)
    mapping = _flag_mapping(t["flag"])

    locs = np.zeros(len(t), dtype=PICASSO_DTYPE)
    locs["frame"] = t["frame"].to_numpy()
    locs["x"] = t["x_nm"].to_numpy() / pixel - 0.5
    locs["y"] = t["y_nm"].to_numpy() / pixel - 0.5
    locs["z"] = t["z_nm"].to_numpy()
    locs["photons"] = t["photons"].to_numpy()
    locs["bg"] = t["background"].to_numpy()
    locs["lpx"] = t["sigma_x_nm"].to_numpy() / pixel
    locs["lpy"] = t["sigma_y_nm"].to_numpy() / pixel
    locs["lpz"] = t["sigma_z_nm"].to_numpy()
    locs["photons_unc"] = t["sigma_photons"].to_numpy()
    locs["gof"] = t["gof"].to_numpy()
    locs["flag"] = _encode_flags(t["flag"], mapping)
    locs["window_id"] = t["window_id"].to_numpy()

    info: list[dict[str, Any]] = [
        {"Width": cols, "Height": rows, "Frames": frames, "Pixelsize": pixel},
        {
            "Generated by": f"sparseloc {__version__}",
            "sparseloc": {
                "metadata": meta,
                "flag_codes": mapping,
                "coordinates": (
                    "x, y, lpx, lpy in camera pixels with the centre of the first pixel at 0; "
                    "z, lpz in nm; photons, bg (per pixel) in photons; frame 0-based"
                ),
            },
        },
    ]
    yaml_text = yaml.safe_dump_all(info, default_flow_style=False, sort_keys=False)
    with atomic_path(dest) as tmp_h5, atomic_path(dest.with_suffix(".yaml")) as tmp_yaml:
        with h5py.File(tmp_h5, "w") as fh:
            fh.create_dataset("locs", data=locs)
            fh.create_dataset("metadata", data=json.dumps(info))
        tmp_yaml.write_text(yaml_text, encoding="utf-8")
    log.info("wrote %d localizations to %s (Picasso HDF5)", len(t), dest)
    return dest


def _picasso_info(src: Path, fh: h5py.File) -> list[dict[str, Any]]:
    sidecar = src.with_suffix(".yaml")
    if sidecar.is_file():
        try:
            docs = list(yaml.safe_load_all(sidecar.read_text(encoding="utf-8")))
        except yaml.YAMLError as exc:
            raise ValueError(f"the Picasso metadata {sidecar.name!r} is not plain YAML") from exc
        return [d for d in docs if isinstance(d, dict)]
    if "metadata" in fh:
        raw = fh["metadata"][()]
        if isinstance(raw, bytes):
            raw = raw.decode("utf-8")
        try:
            return [d for d in json.loads(raw) if isinstance(d, dict)]
        except (ValueError, TypeError) as exc:
            raise ValueError(f"the metadata embedded in {src.name!r} is not JSON") from exc
    raise ValueError(f"found neither {sidecar.name!r} nor metadata embedded in {src.name!r}")


def read_picasso_hdf5(path: str | Path) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """Read a Picasso HDF5 localization file (Picasso's own or :func:`write_picasso_hdf5`'s).

    Parameters
    ----------
    path : str or Path
        HDF5 file with a structured ``/locs`` dataset, beside its ``.yaml`` sidecar (or with
        the metadata embedded in ``/metadata``).

    Returns
    -------
    df : DataFrame
        Localization table (:func:`check_locs` form) in native coordinates:
        ``x_nm = (x + 0.5) * Pixelsize``, ``sigma_x_nm = lpx * Pixelsize``... A missing ``z``
        is 0 nm; missing ``lpz``, ``photons_unc``, ``gof`` are NaN; a missing ``flag`` is
        "ok" and ``window_id`` -1.
    info : list of dict
        The YAML documents (Picasso's metadata list).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not HDF5, has no structured ``/locs``, or its metadata lacks ``Pixelsize``.
    """
    src = _source(path)
    try:
        fh = h5py.File(src, "r")
    except OSError as exc:
        raise ValueError(f"{str(src)!r} is not a readable HDF5 file ({exc})") from exc
    with fh:
        ds = fh.get("locs")
        if not isinstance(ds, h5py.Dataset) or ds.dtype.names is None:
            raise ValueError(f"{str(src)!r} has no Picasso '/locs' table")
        locs = ds[()]
        info = _picasso_info(src, fh)
    names = set(locs.dtype.names)
    missing = [f for f in ("frame", "x", "y") if f not in names]
    if missing:
        raise ValueError(f"the Picasso table {src.name} lacks the field(s) {', '.join(missing)}")
    pixel_raw = _from_info(info, "Pixelsize")
    if pixel_raw is None:
        raise ValueError(f"the metadata of {src.name} has no Pixelsize (nm)")
    pixel = _positive_number(pixel_raw, "Pixelsize")
    n = len(locs)

    def field(name: str, scale: float = 1.0, default: float = np.nan) -> np.ndarray:
        if name in names:
            return locs[name].astype(np.float64) * scale
        return np.full(n, default)

    out = pd.DataFrame(
        {
            "frame": locs["frame"].astype(np.int64),
            "x_nm": (locs["x"].astype(np.float64) + 0.5) * pixel,
            "y_nm": (locs["y"].astype(np.float64) + 0.5) * pixel,
            "z_nm": field("z", default=0.0),
            "photons": field("photons"),
            "background": field("bg"),
            "sigma_x_nm": field("lpx", pixel),
            "sigma_y_nm": field("lpy", pixel),
            "sigma_z_nm": field("lpz"),
            "sigma_photons": field("photons_unc"),
            "gof": field("gof"),
        }
    )
    if "flag" in names:
        own = _from_info(info, "sparseloc")
        mapping = own.get("flag_codes") if isinstance(own, dict) else None
        out["flag"] = _decode_flags(locs["flag"], mapping)
    else:
        out["flag"] = "ok"
    out["window_id"] = field("window_id", default=-1.0)
    return check_locs(out, what=f"the Picasso table {src.name}"), info


# --------------------------------------------------------------------------------------------
# SMLM-challenge CSV
# --------------------------------------------------------------------------------------------


def write_smlm_csv(df: pd.DataFrame, path: str | Path) -> Path:
    """Write a localization table as an SMLM-challenge CSV, atomically.

    Header ``Ground-truth,frame,xnano,ynano,znano,intensity`` as in the challenge's
    ``activations.csv``: a 1-based row id, the 1-based frame, x, y, z (nm, native
    coordinates) and photons, full float precision. Other columns are not written.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`).
    path : str or Path
        Destination file; its folder must exist.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    ValueError
        If the folder does not exist or the table is invalid.
    """
    t = check_locs(df)
    dest = _dest(path)
    out = pd.DataFrame(
        {
            "Ground-truth": np.arange(1, len(t) + 1, dtype=np.int64),
            "frame": t["frame"].to_numpy() + 1,
            "xnano": t["x_nm"].to_numpy(),
            "ynano": t["y_nm"].to_numpy(),
            "znano": t["z_nm"].to_numpy(),
            "intensity": t["photons"].to_numpy(),
        },
        columns=list(SMLM_COLUMNS),
    )
    with atomic_path(dest) as tmp:
        _csv_cells(out).to_csv(tmp, index=False, na_rep="NaN", lineterminator="\n")
    log.info("wrote %d localizations to %s (SMLM-challenge CSV)", len(t), dest)
    return dest


def read_smlm_csv(path: str | Path) -> pd.DataFrame:
    """Read an SMLM-challenge CSV (``frame, xnano, ynano[, znano][, intensity]``).

    Parameters
    ----------
    path : str or Path
        CSV file; column names are matched after stripping spaces (the challenge's files
        write ``intensity `` with a trailing space), ``Ground-truth`` is ignored.

    Returns
    -------
    DataFrame
        Localization table (:func:`check_locs` form) with 0-based frames; a missing ``znano``
        is 0 nm, a missing ``intensity`` NaN, ``flag`` "ok", ``window_id`` -1, the rest NaN.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If ``frame``, ``xnano`` or ``ynano`` is missing or frames are not 1-based integers.
    """
    src = _source(path)
    raw = _read_csv(src)
    where = f"the SMLM-challenge table {src.name}"
    missing = [c for c in ("frame", "xnano", "ynano") if c not in raw.columns]
    if missing:
        raise ValueError(f"{where} is missing the column(s) {', '.join(missing)}")
    out = pd.DataFrame(
        {
            "frame": _frames_from_one_based(raw["frame"], where),
            "x_nm": _numeric(raw["xnano"], "xnano", where),
            "y_nm": _numeric(raw["ynano"], "ynano", where),
        }
    )
    if "znano" in raw.columns:
        out["z_nm"] = _numeric(raw["znano"], "znano", where)
    if "intensity" in raw.columns:
        out["photons"] = _numeric(raw["intensity"], "intensity", where)
    return complete_locs(out, what=where)


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------


def write_table(
    df: pd.DataFrame,
    path: str | Path,
    *,
    format: str | None = None,
    pixel_size: float | None = None,
    shape: tuple[int, int] | None = None,
    n_frames: int | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Write a localization table in the format named, or chosen by the file suffix.

    Parameters
    ----------
    df : DataFrame
        Localization table (:func:`check_locs`).
    path : str or Path
        Destination file; its folder must exist.
    format : {"parquet", "thunderstorm", "picasso", "smlm"}, optional
        Output format; by default from the suffix: ``.parquet``/``.pq`` Parquet, ``.csv``
        ThunderSTORM, ``.hdf5``/``.h5`` Picasso.
    pixel_size : float, optional
        Camera pixel size (nm); required for Picasso.
    shape : tuple of int, optional
        Camera image ``(rows, cols)``; required for Picasso.
    n_frames : int, optional
        Number of movie frames; required for Picasso.
    metadata : dict, optional
        Analysis metadata (Parquet schema metadata, Picasso YAML); ignored by the CSV formats.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    ValueError
        If the format is unknown or cannot be inferred, Picasso's ``pixel_size``, ``shape``
        or ``n_frames`` is missing (they are named), or as the writer raises.
    """
    fmt = _format_for(path, format)
    if fmt == "parquet":
        return write_parquet(df, path, metadata=metadata or {})
    if fmt == "thunderstorm":
        return write_thunderstorm_csv(df, path)
    if fmt == "smlm":
        return write_smlm_csv(df, path)
    needed = {"pixel_size": pixel_size, "shape": shape, "n_frames": n_frames}
    missing = [k for k, v in needed.items() if v is None]
    if missing:
        raise ValueError(f"the Picasso format needs {', '.join(missing)}")
    return write_picasso_hdf5(
        df,
        path,
        pixel_size=pixel_size,  # type: ignore[arg-type]
        shape=shape,  # type: ignore[arg-type]
        n_frames=n_frames,  # type: ignore[arg-type]
        metadata=metadata,
    )


def _format_for(path: str | Path, format: str | None) -> str:
    if format is not None:
        fmt = str(format).lower()
        if fmt not in FORMATS:
            raise ValueError(f"unknown table format {format!r} (choose from {', '.join(FORMATS)})")
        return fmt
    suffix = Path(path).suffix.lower()
    if suffix not in _SUFFIX_FORMATS:
        raise ValueError(
            f"cannot tell the table format from the suffix {suffix or '(none)'!r}; use "
            f".parquet, .csv, .hdf5 or .h5, or name the format ({', '.join(FORMATS)})"
        )
    return _SUFFIX_FORMATS[suffix]


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a localization table, detecting its format from the file's contents.

    Parquet and HDF5 (Picasso ``/locs``) are told by their magic bytes; CSV files by their
    header: ThunderSTORM (labels such as ``x [nm]``), SMLM challenge (``xnano``), or a
    sparseloc CSV with ``frame,x_nm,y_nm`` (e.g. a ground-truth table
    ``frame,x_nm,y_nm,z_nm,photons``; missing columns filled as in :func:`complete_locs`).

    Parameters
    ----------
    path : str or Path
        Table file.

    Returns
    -------
    DataFrame
        Localization table (:func:`check_locs` form).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the format is not recognised or the file is invalid.
    """
    src = _source(path)
    with open(src, "rb") as fh:
        head = fh.read(8)
    if head.startswith(_PARQUET_MAGIC):
        return read_parquet(src)[0]
    if head.startswith(_HDF5_MAGIC):
        return read_picasso_hdf5(src)[0]
    try:
        with open(src, encoding="utf-8") as fh:
            first_line = fh.readline()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{str(src)!r} is not a Parquet, HDF5 or CSV table") from exc
    labels = [c.strip().strip("\"'`").strip() for c in first_line.split(",")]
    names = {_parse_label(c)[0] for c in labels}
    if "xnano" in labels:
        return read_smlm_csv(src)
    if "x_nm" in labels:
        raw = _read_csv(src)
        return complete_locs(raw, what=f"the table {src.name}")
    if {"frame", "x", "y"} <= names:
        return read_thunderstorm_csv(src)
    raise ValueError(
        f"{str(src)!r} is not a recognised localization table (header {first_line.strip()!r})"
    )
