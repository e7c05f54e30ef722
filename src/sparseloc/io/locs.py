"""The canonical localization table: its columns, dtypes and validation.

The table is a :class:`pandas.DataFrame` with the columns :data:`LOCS_COLUMNS`, in native
sparseloc conventions (design.md section 3): lengths in nm, brightness in photons, background in
photons per pixel, 0-based frames, ``x`` along columns and ``y`` along rows with the origin at
the outer corner of pixel (0, 0). :mod:`sparseloc.io.tables` re-exports everything here.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

__all__ = ["LOCS_COLUMNS", "check_locs", "complete_locs", "empty_locs", "numeric_column"]

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
    _check_columns(df, LOCS_COLUMNS, what)
    out = df.copy()
    for col in _INT_COLUMNS:
        vals = numeric_column(out[col], col, what)
        if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
            raise ValueError(f"the {what} column {col!r} must hold integers")
        if col == "frame" and np.any(vals < 0):
            raise ValueError(f"the {what} column 'frame' must be >= 0 (frames are 0-based)")
        out[col] = vals.astype(np.int64)
    for col in _FLOAT_COLUMNS:
        out[col] = numeric_column(out[col], col, what)
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
    _check_columns(df, _CORE_COLUMNS, what)
    out = df.copy()
    for col, value in _DEFAULTS.items():
        if col not in out.columns:
            out[col] = value
    return check_locs(out, what=what)


def _check_columns(df: pd.DataFrame, columns: tuple[str, ...], what: str) -> None:
    """Raise unless ``df`` is a DataFrame holding every one of ``columns``."""
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"the {what} must be a pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"the {what} is missing the column(s) {', '.join(missing)}")


def numeric_column(series: pd.Series, col: str, what: str) -> np.ndarray:
    """``series`` as float64 numbers; ``ValueError`` naming ``col`` of the ``what`` if not."""
    try:
        return pd.to_numeric(series, errors="raise").to_numpy(dtype=np.float64)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"the {what} column {col!r} must hold numbers") from exc
