"""ThunderSTORM CSV localization tables (re-exported by :mod:`sparseloc.io.tables`).

The quoted header ThunderSTORM itself writes, 1-based ``id`` and ``frame``, nm and photons.
Native coordinates need no shift: ThunderSTORM places the centre of pixel ``i`` at ``i + 0.5``
pixels. sparseloc's extra columns follow the standard ones; every cell is numeric
(ThunderSTORM's importer parses every cell as a number), so ``flag`` is written as an integer
code (:data:`~sparseloc.io.table_files.FLAG_CODES`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from .atomic import atomic_path
from .locs import check_locs, numeric_column
from .table_files import (
    FLAG_CODES,
    csv_cells,
    decode_flags,
    dest_path,
    encode_flags,
    frames_from_one_based,
    read_csv_table,
    source_path,
)

__all__ = [
    "THUNDERSTORM_COLUMNS",
    "THUNDERSTORM_EXTRA_COLUMNS",
    "parse_label",
    "read_thunderstorm_csv",
    "write_thunderstorm_csv",
]

# Messages keep the logger of sparseloc.io.tables, where the table formats have always logged.
log = logging.getLogger("sparseloc.io.tables")

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
#: sparseloc columns appended after :data:`THUNDERSTORM_COLUMNS` (all numeric). They hold
#: uncertainties, named as ThunderSTORM names its own: its ``sigma`` is the PSF's width.
THUNDERSTORM_EXTRA_COLUMNS: tuple[str, ...] = (
    "uncertainty_x [nm]",
    "uncertainty_y [nm]",
    "uncertainty_photons [photon]",
    "gof",
    "flag",
    "window_id",
)

_LENGTH_UNITS = {"nm": 1.0, "um": 1000.0, "µm": 1000.0}


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
    dest = dest_path(path)
    out = _thunderstorm_cells(t)
    header = ",".join(f'"{c}"' for c in out.columns) + "\n"
    with atomic_path(dest) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(header)
            csv_cells(out).to_csv(fh, header=False, index=False, na_rep="NaN", lineterminator="\n")
    log.info("wrote %d localizations to %s (ThunderSTORM CSV)", len(t), dest)
    return dest


def _thunderstorm_cells(t: pd.DataFrame) -> pd.DataFrame:
    """The columns written for the checked table ``t``, in ThunderSTORM's units and order."""
    with np.errstate(invalid="ignore"):
        bkgstd = np.sqrt(t["background"].to_numpy())
        unc_xy = np.sqrt((t["sigma_x_nm"].to_numpy() ** 2 + t["sigma_y_nm"].to_numpy() ** 2) / 2)
    cols = list(THUNDERSTORM_COLUMNS) + list(THUNDERSTORM_EXTRA_COLUMNS)
    return pd.DataFrame(
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
            "uncertainty_x [nm]": t["sigma_x_nm"].to_numpy(),
            "uncertainty_y [nm]": t["sigma_y_nm"].to_numpy(),
            "uncertainty_photons [photon]": t["sigma_photons"].to_numpy(),
            "gof": t["gof"].to_numpy(),
            "flag": encode_flags(t["flag"], FLAG_CODES),
            "window_id": t["window_id"].to_numpy(),
        },
        columns=cols,
    )


def parse_label(label: str) -> tuple[str, str]:
    """Split a ThunderSTORM column label ``"name [unit]"`` into (name, unit)."""
    start, end = label.rfind("["), label.rfind("]")
    if start < 0 or end < start:
        return label.strip(), ""
    return label[:start].strip(), label[start + 1 : end].strip()


class _Columns:
    """The columns of a ThunderSTORM table by name, read in sparseloc's units (None if absent)."""

    def __init__(self, raw: pd.DataFrame, where: str) -> None:
        self.raw = raw
        self.where = where
        self.cols: dict[str, tuple[str, str]] = {}
        for label in raw.columns:
            name, unit = parse_label(label)
            self.cols.setdefault(name, (label, unit))
        missing = [c for c in ("frame", "x", "y") if c not in self.cols]
        if missing:
            raise ValueError(f"{where} is missing the column(s) {', '.join(missing)}")

    def length(self, name: str) -> np.ndarray | None:
        """A length column in nm (``nm`` or ``um`` in the file)."""
        if name not in self.cols:
            return None
        label, unit = self.cols[name]
        if unit not in _LENGTH_UNITS:
            raise ValueError(
                f"{self.where} column {label!r} is in {unit or 'no unit'}; export it in nm"
            )
        return numeric_column(self.raw[label], label, self.where) * _LENGTH_UNITS[unit]

    def photons(self, name: str) -> np.ndarray | None:
        """A photon column (``photon`` or no unit in the file)."""
        if name not in self.cols:
            return None
        label, unit = self.cols[name]
        if unit not in ("photon", ""):
            raise ValueError(f"{self.where} column {label!r} is in {unit}; export it in photons")
        return numeric_column(self.raw[label], label, self.where)

    def plain(self, name: str) -> np.ndarray | None:
        """A column without a unit."""
        if name not in self.cols:
            return None
        return numeric_column(self.raw[self.cols[name][0]], name, self.where)

    def flags(self) -> list[str] | pd.Series | str:
        """The flags: decoded from codes, as text, or "ok" for a file without them."""
        if "flag" not in self.cols:
            return "ok"
        flags = self.raw[self.cols["flag"][0]]
        if pd.api.types.is_numeric_dtype(flags):
            return decode_flags(flags.to_numpy())
        return flags.astype(str).str.strip()


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
    src = source_path(path)
    raw = read_csv_table(src)
    where = f"the ThunderSTORM table {src.name}"
    c = _Columns(raw, where)
    n = len(raw)
    nan = np.full(n, np.nan)

    def first(*options: np.ndarray | None, default: np.ndarray = nan) -> np.ndarray:
        return next((o for o in options if o is not None), default)

    unc_xy = c.length("uncertainty_xy")
    offset, bkgstd = c.photons("offset"), c.photons("bkgstd")
    out = pd.DataFrame(
        {
            "frame": frames_from_one_based(raw[c.cols["frame"][0]], where),
            "x_nm": c.length("x"),
            "y_nm": c.length("y"),
            "z_nm": first(c.length("z"), default=np.zeros(n)),
            "photons": first(c.photons("intensity")),
            "background": first(offset, None if bkgstd is None else bkgstd**2),
            # (sigma_x, sigma_y, sigma_photons: what sparseloc's own files named them before)
            "sigma_x_nm": first(c.length("uncertainty_x"), c.length("sigma_x"), unc_xy),
            "sigma_y_nm": first(c.length("uncertainty_y"), c.length("sigma_y"), unc_xy),
            "sigma_z_nm": first(c.length("uncertainty_z")),
            "sigma_photons": first(c.photons("uncertainty_photons"), c.photons("sigma_photons")),
            "gof": first(c.plain("gof")),
        }
    )
    out["flag"] = c.flags()
    out["window_id"] = first(c.plain("window_id"), default=np.full(n, -1.0))
    return check_locs(out, what=where)
