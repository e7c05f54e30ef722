"""Localization tables: the canonical in-memory table and its file formats.

The table is a :class:`pandas.DataFrame` with the columns :data:`LOCS_COLUMNS`, in native
sparseloc conventions (design.md section 3): lengths in nm, brightness in photons, background in
photons per pixel, 0-based frames, ``x`` along columns and ``y`` along rows with the origin at
the outer corner of pixel (0, 0). The table itself is defined in :mod:`sparseloc.io.locs`, the
ThunderSTORM and Picasso formats in :mod:`sparseloc.io.thunderstorm` and
:mod:`sparseloc.io.picasso`; their public names are re-exported here.

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

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from .. import __version__
from .atomic import atomic_path
from .locs import LOCS_COLUMNS, check_locs, complete_locs, empty_locs, numeric_column
from .picasso import PICASSO_DTYPE, read_picasso_hdf5, write_picasso_hdf5
from .table_files import (
    FLAG_CODES,
    csv_cells,
    dest_path,
    frames_from_one_based,
    plain_metadata,
    read_csv_table,
    source_path,
)
from .thunderstorm import (
    THUNDERSTORM_COLUMNS,
    THUNDERSTORM_EXTRA_COLUMNS,
    parse_label,
    read_thunderstorm_csv,
    write_thunderstorm_csv,
)

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
    "read_table_and_metadata",
    "read_thunderstorm_csv",
    "write_parquet",
    "write_picasso_hdf5",
    "write_smlm_csv",
    "write_table",
    "write_thunderstorm_csv",
]

log = logging.getLogger(__name__)

#: Format names accepted by :func:`write_table`.
FORMATS: tuple[str, ...] = ("parquet", "thunderstorm", "picasso", "smlm")
_SUFFIX_FORMATS = {
    ".parquet": "parquet",
    ".pq": "parquet",
    ".csv": "thunderstorm",
    ".hdf5": "picasso",
    ".h5": "picasso",
}

#: SMLM-challenge CSV header (as in the challenge's ``activations.csv``).
SMLM_COLUMNS: tuple[str, ...] = ("Ground-truth", "frame", "xnano", "ynano", "znano", "intensity")

_PARQUET_KEY = b"sparseloc"
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_PARQUET_MAGIC = b"PAR1"


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
    meta = plain_metadata(metadata)
    meta.setdefault("sparseloc_version", __version__)
    dest = dest_path(path)
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
    src = source_path(path)
    try:
        arrow = pq.read_table(src)
    except (pa.ArrowInvalid, OSError) as exc:
        raise ValueError(f"{str(src)!r} is not a readable Parquet file ({exc})") from exc
    raw = (arrow.schema.metadata or {}).get(_PARQUET_KEY)
    meta = _checked_metadata(raw, src.name) if raw else {}
    df = check_locs(arrow.to_pandas(), what=f"table {src.name!r}")
    return df, meta


def _is_number(value: Any, *, whole: bool = False) -> bool:
    kinds = (int, np.integer) if whole else (int, float, np.integer, np.floating)
    return isinstance(value, kinds) and not isinstance(value, bool) and np.isfinite(value)


def _checked_metadata(raw: bytes, name: str) -> dict[str, Any]:
    """The sparseloc metadata of a Parquet file, with the entries that commands compute with
    (``params.pixel_size``, ``shape``, ``frames``, ``n_frames``) checked, so that a damaged or
    foreign file is refused in one sentence instead of failing later."""
    where = f"the sparseloc metadata of {name}"
    try:
        meta = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{where} is not JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise ValueError(f"{where} is a JSON {type(meta).__name__}, not an object")
    params = meta.get("params")
    if params is not None and not isinstance(params, dict):
        raise ValueError(f"{where} holds params that are not an object: {params!r}")
    pixel = (params or {}).get("pixel_size")
    if pixel is not None and not (_is_number(pixel) and pixel > 0):
        raise ValueError(f"{where} holds a pixel_size that is not a number > 0: {pixel!r}")
    for key in ("shape", "frames"):
        value = meta.get(key)
        if value is None:
            continue
        if not (
            isinstance(value, list)
            and len(value) >= 2
            and all(_is_number(v, whole=True) and v >= 0 for v in value)
        ):
            raise ValueError(
                f"{where} holds a {key} that is not a list of whole numbers: {value!r}"
            )
    n_frames = meta.get("n_frames")
    if n_frames is not None and not (_is_number(n_frames, whole=True) and n_frames > 0):
        raise ValueError(f"{where} holds an n_frames that is not a whole number > 0")
    return meta


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
    dest = dest_path(path)
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
        csv_cells(out).to_csv(tmp, index=False, na_rep="NaN", lineterminator="\n")
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
    src = source_path(path)
    raw = read_csv_table(src)
    where = f"the SMLM-challenge table {src.name}"
    missing = [c for c in ("frame", "xnano", "ynano") if c not in raw.columns]
    if missing:
        raise ValueError(f"{where} is missing the column(s) {', '.join(missing)}")
    out = pd.DataFrame(
        {
            "frame": frames_from_one_based(raw["frame"], where),
            "x_nm": numeric_column(raw["xnano"], "xnano", where),
            "y_nm": numeric_column(raw["ynano"], "ynano", where),
        }
    )
    if "znano" in raw.columns:
        out["z_nm"] = numeric_column(raw["znano"], "znano", where)
    if "intensity" in raw.columns:
        out["photons"] = numeric_column(raw["intensity"], "intensity", where)
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
    fmt = format_for(path, format)
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


#: The file each format writes, by the suffixes that name it.
_FORMAT_FILES = {"parquet": "Parquet", "thunderstorm": "CSV", "smlm": "CSV", "picasso": "HDF5"}


def format_for(path: str | Path, format: str | None) -> str:
    """The table format of ``path``: ``format`` where given (refused where the file's suffix
    names another kind of file), else its suffix's."""
    suffix = Path(path).suffix.lower()
    if format is not None:
        fmt = str(format).lower()
        if fmt not in FORMATS:
            raise ValueError(f"unknown table format {format!r} (choose from {', '.join(FORMATS)})")
        implied = _SUFFIX_FORMATS.get(suffix)
        if implied is not None and _FORMAT_FILES[implied] != _FORMAT_FILES[fmt]:
            raise ValueError(
                f"--format {fmt} writes a {_FORMAT_FILES[fmt]} file, but {Path(path).name!r} "
                f"is named as a {_FORMAT_FILES[implied]} file: change the suffix or the format"
            )
        return fmt
    if suffix not in _SUFFIX_FORMATS:
        raise ValueError(
            f"cannot tell the table format from the suffix {suffix or '(none)'!r}; use "
            f".parquet, .csv, .hdf5 or .h5, or name the format ({', '.join(FORMATS)})"
        )
    return _SUFFIX_FORMATS[suffix]


def recorded_pixel_size(metadata: Any) -> float | None:
    """The camera pixel size (nm) a table's analysis metadata records (``params``), or None."""
    params = metadata.get("params") if isinstance(metadata, Mapping) else None
    value = params.get("pixel_size") if isinstance(params, Mapping) else None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if np.isfinite(value) and value > 0 else None


def read_table_and_metadata(path: str | Path) -> tuple[pd.DataFrame, dict[str, Any]]:
    """:func:`read_table`, with the analysis metadata of a sparseloc Parquet table or of a
    Picasso table that sparseloc wrote (its sidecar's ``sparseloc`` document); of another
    Picasso table, its pixel size and frame shape (``Pixelsize``, ``Height``, ``Width``);
    ``{}`` for the other formats."""
    src = source_path(path)
    with open(src, "rb") as fh:
        head = fh.read(8)
    if head.startswith(_PARQUET_MAGIC):
        return read_parquet(src)
    table = read_table(src)
    if head.startswith(b"\x89HDF"):
        _, docs = read_picasso_hdf5(src)
        for doc in docs:
            own = doc.get("sparseloc")
            if isinstance(own, dict) and isinstance(own.get("metadata"), dict):
                return table, own["metadata"]
        # another program's Picasso table: its image description
        for doc in docs:
            try:
                px, shape = float(doc["Pixelsize"]), [int(doc["Height"]), int(doc["Width"])]
            except (KeyError, TypeError, ValueError):
                continue
            return table, {"params": {"pixel_size": px}, "shape": shape}
    return table, {}


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
    src = source_path(path)
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
    names = {parse_label(c)[0] for c in labels}
    if "xnano" in labels:
        return read_smlm_csv(src)
    if "x_nm" in labels:
        raw = read_csv_table(src)
        return complete_locs(raw, what=f"table {src.name!r}")
    if {"frame", "x", "y"} <= names:
        return read_thunderstorm_csv(src)
    raise ValueError(
        f"{str(src)!r} is not a recognised localization table (header {first_line.strip()!r})"
    )
