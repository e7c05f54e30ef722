"""Ground-truth tables as CSV: ``frame,x_nm,y_nm,z_nm,photons`` (+ ``emitter_id``).

Frames are 0-based and coordinates native (design.md): nm from the outer corner of pixel (0, 0),
``x`` along columns, ``y`` along rows.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from .atomic import atomic_path

__all__ = [
    "TRUTH_COLUMNS",
    "check_truth_table",
    "gives_pixels",
    "read_truth_csv",
    "truth_gives_pixels",
    "write_truth_csv",
]

log = logging.getLogger(__name__)

#: Columns of every truth table, in file order; ``emitter_id`` follows when present.
TRUTH_COLUMNS: tuple[str, ...] = ("frame", "x_nm", "y_nm", "z_nm", "photons")
_OPTIONAL = ("emitter_id",)
_FLOAT_COLUMNS = ("x_nm", "y_nm", "z_nm", "photons")
_INT_COLUMNS = ("frame", "emitter_id")


def check_truth_table(
    df: pd.DataFrame, *, require_photons: bool = True, what: str = "truth table"
) -> pd.DataFrame:
    """Validate a truth table and return it with canonical dtypes.

    Parameters
    ----------
    df : DataFrame
        Table with at least ``frame, x_nm, y_nm, z_nm, photons``.
    require_photons : bool
        Whether ``photons`` is required (localization tables may lack it).
    what : str
        Name of the table in error messages.

    Returns
    -------
    DataFrame
        A copy with ``frame`` (and ``emitter_id``) as int64 and coordinates/photons as float64;
        the known columns come first, other columns are kept after them.

    Raises
    ------
    ValueError
        Naming missing columns, non-integer or negative frames, or non-finite values.
    """
    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"{what} must be a pandas DataFrame, got {type(df).__name__}")
    required = [c for c in TRUTH_COLUMNS if require_photons or c != "photons"]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise ValueError(
            f"{what} is missing the column(s) {', '.join(missing)} "
            f"(expected {','.join(TRUTH_COLUMNS)})"
        )
    out = df.copy()
    for col in _INT_COLUMNS:
        if col not in out.columns:
            continue
        vals = pd.to_numeric(out[col], errors="coerce").to_numpy(dtype=np.float64)
        if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
            raise ValueError(f"{what} column {col!r} must hold integers")
        if np.any(vals < 0):
            raise ValueError(f"{what} column {col!r} must be >= 0 (0-based)")
        out[col] = vals.astype(np.int64)
    for col in _FLOAT_COLUMNS:
        if col not in out.columns:
            continue
        vals = pd.to_numeric(out[col], errors="coerce").to_numpy(dtype=np.float64)
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"{what} column {col!r} must hold finite numbers (no NaN or text)")
        out[col] = vals
    known = [c for c in (*TRUTH_COLUMNS, *_OPTIONAL) if c in out.columns]
    rest = [c for c in out.columns if c not in known]
    return out[known + rest]


def write_truth_csv(path: str | Path, df: pd.DataFrame) -> Path:
    """Write a truth table as CSV, atomically.

    Parameters
    ----------
    path : str or Path
        Destination file; its folder must exist.
    df : DataFrame
        Truth table; exactly ``frame,x_nm,y_nm,z_nm,photons`` (+ ``emitter_id`` if present) are
        written, in that order, with full float precision.

    Returns
    -------
    Path
        The path written.
    """
    table = check_truth_table(df)
    cols = list(TRUTH_COLUMNS) + [c for c in _OPTIONAL if c in table.columns]
    with atomic_path(path) as tmp:
        table[cols].to_csv(tmp, index=False, lineterminator="\n")
    log.info("wrote %d truth rows to %s", len(table), path)
    return Path(path)


_BINARY_MAGIC = {
    b"PAR1": "a Parquet",
    b"\x89HDF": "an HDF5",
    b"II*\x00": "a TIFF (a movie?)",
    b"MM\x00*": "a TIFF (a movie?)",
}


#: Columns that only fitted localizations carry (uncertainties, goodness of fit): a truth
#: table with them is a localization table in the truth's place.
_FIT_COLUMNS = frozenset({"sigma_x_nm", "sigma_y_nm", "sigma_z_nm", "gof"})


def _binary_table_kind(path: Path) -> str | None:
    """The kind of a binary file (Parquet, HDF5, TIFF) from its magic bytes, else None."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    return _BINARY_MAGIC.get(head)


def gives_pixels(columns) -> bool:
    """Whether a truth table with these column names gives positions in pixels
    (storm-analysis's ``x_px, y_px``) rather than nm."""
    cols = {str(c).strip() for c in columns}
    return {"x_px", "y_px"} <= cols and "x_nm" not in cols


def truth_gives_pixels(path: str | Path) -> bool:
    """:func:`gives_pixels` of a truth CSV's header (a file :func:`read_truth_csv` read)."""
    return gives_pixels(pd.read_csv(path, nrows=0).columns)


def read_truth_csv(
    path: str | Path, *, require_photons: bool = True, pixel_size: float | None = None
) -> pd.DataFrame:
    """Read and validate a truth table written by :func:`write_truth_csv`.

    Also reads storm-analysis style truth (``frame_0based, x_px, y_px, z_um[, photons_sum]``,
    pixel positions with 0.0 at the centre of the first pixel) when ``pixel_size`` (nm) is
    given: ``x_nm = (x_px + 0.5) * pixel_size``; and the SMLM 2016 challenge's activations
    and tables (``frame`` 1-based, ``xnano, ynano[, znano], intensity`` in nm and photons),
    as ``localize --format smlm`` writes them.

    Parameters
    ----------
    path : str or Path
        CSV file with a header row.
    require_photons : bool
        Whether the ``photons`` column is required.

    Returns
    -------
    DataFrame
        ``frame`` (int64), ``x_nm, y_nm, z_nm, photons`` (float64), ``emitter_id`` (int64) when
        present, then any other columns.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a CSV table or columns are missing (they are named) or invalid.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"the file {str(p)!r} does not exist")
    if p.is_dir():
        raise IsADirectoryError(f"{str(p)!r} is a folder, not a CSV file")
    binary = _binary_table_kind(p)
    if binary is not None:
        hint = (
            "is it a localization table given in the truth's place? (the localizations go "
            "first, the truth second)"
            if "TIFF" not in binary
            else "the truth is the CSV that simulate wrote beside the movie, or the data's own"
        )
        raise ValueError(f"{str(p)!r} is {binary} file, not a CSV truth table: {hint}")
    try:
        df = pd.read_csv(p)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{str(p)!r} is not a readable CSV table ({exc})") from exc
    df.columns = [str(c).strip() for c in df.columns]
    fitted = [c for c in df.columns if c in _FIT_COLUMNS or c.startswith("uncertainty")]
    if fitted:
        raise ValueError(
            f"{p.name} has the columns of fitted localizations ({', '.join(fitted[:3])}), not "
            "of a ground truth: is it the localization table given in the truth's place? (the "
            "localizations go first, the truth second)"
        )
    if gives_pixels(df.columns):
        if pixel_size is None:
            raise ValueError(
                f"{p.name} gives positions in pixels (x_px, y_px); pass the pixel size "
                "(--pixel-size) to convert them to nm"
            )
        conv = pd.DataFrame(
            {
                "frame": df["frame_0based" if "frame_0based" in df else "frame"],
                "x_nm": (df["x_px"] + 0.5) * float(pixel_size),
                "y_nm": (df["y_px"] + 0.5) * float(pixel_size),
                "z_nm": df["z_um"] * 1000.0 if "z_um" in df else df.get("z_nm", 0.0),
            }
        )
        for key in ("photons", "photons_sum"):
            if key in df:
                conv["photons"] = df[key]
                break
        df = conv
    elif {"xnano", "ynano"} <= set(df.columns) and "x_nm" not in df.columns:
        from .tables import read_smlm_csv

        df = read_smlm_csv(p)[["frame", "x_nm", "y_nm", "z_nm", "photons"]]
    return check_truth_table(df, require_photons=require_photons, what=f"{p.name}")
