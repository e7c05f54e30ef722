"""What the localization-table file formats share: path checks, JSON metadata, the numeric
flag codes and exact CSV cells."""

from __future__ import annotations

import functools
import io
import json
import logging
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .locs import numeric_column

__all__ = [
    "FLAG_CODES",
    "csv_cells",
    "decode_flags",
    "dest_path",
    "encode_flags",
    "flag_mapping",
    "frames_from_one_based",
    "plain_metadata",
    "read_csv_table",
    "source_path",
]

# The warnings of the table formats have always been logged under sparseloc.io.tables.
log = logging.getLogger("sparseloc.io.tables")

#: Integer codes of the flags in numeric-only formats (ThunderSTORM CSV, Picasso HDF5).
FLAG_CODES: dict[str, int] = {
    "ok": 0,
    "outside": 1,
    "z_edge": 2,
    "not_converged": 3,
    "diverged": 4,
    # The fits' flag of a singular Fisher matrix (sparseloc.solvers.mle): without a code every
    # ThunderSTORM export of a correct run warned that it was written as "other".
    "bad_sigma": 5,
}
_FLAG_OTHER = "other"
_FLAG_OTHER_CODE = -1


def dest_path(path: str | Path) -> Path:
    """``path`` as a file to write: ``ValueError`` if it is a folder or its folder is missing."""
    dest = Path(path)
    if dest.is_dir():
        raise ValueError(f"the output path {str(dest)!r} is a folder, not a file")
    folder = dest.parent if str(dest.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"the output folder {str(folder)!r} does not exist")
    return dest


def source_path(path: str | Path) -> Path:
    """``path`` as a table file to read: ``FileNotFoundError`` or ``IsADirectoryError`` if not."""
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


def plain_metadata(metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    """Metadata as plain JSON types (numpy scalars and arrays, paths, sets converted)."""
    if metadata is None:
        return {}
    if not isinstance(metadata, Mapping):
        raise ValueError(f"metadata must be a dict, got {type(metadata).__name__}")
    try:
        return json.loads(json.dumps(dict(metadata), default=_json_default, allow_nan=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"metadata must be JSON-serialisable ({exc})") from exc


def flag_mapping(flags: Iterable[str]) -> dict[str, int]:
    """:data:`FLAG_CODES` extended with codes for any other reasons present."""
    mapping = dict(FLAG_CODES)
    nxt = max(mapping.values()) + 1
    for reason in sorted(set(flags) - set(mapping)):
        mapping[reason] = nxt
        nxt += 1
    return mapping


def encode_flags(flags: pd.Series, mapping: Mapping[str, int]) -> np.ndarray:
    """Integer code of each flag; reasons ``mapping`` lacks become -1 ("other"), with a warning."""
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


def decode_flags(codes: Any, mapping: Mapping[str, int] | None = None) -> list[str]:
    """The flag of each code (by ``mapping``, default :data:`FLAG_CODES`); unknown: "other"."""
    inverse = {int(v): str(k) for k, v in (mapping or FLAG_CODES).items()}
    inverse.setdefault(_FLAG_OTHER_CODE, _FLAG_OTHER)
    out = []
    for c in np.asarray(codes, dtype=np.float64):
        out.append(inverse.get(int(c), _FLAG_OTHER) if np.isfinite(c) else _FLAG_OTHER)
    return out


def csv_cells(frame: pd.DataFrame) -> pd.DataFrame:
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
    converter; pandas 3 deprecates it as exact by default, yet some pandas 3 releases read a
    few values one unit in the last place off, so the default is kept only where it reads back
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


def read_csv_table(path: Path) -> pd.DataFrame:
    """A CSV table with exact floats and its column labels stripped of spaces and quotes."""
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*float_precision.*")
            df = pd.read_csv(path, skipinitialspace=True, **_csv_kw())
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise ValueError(f"{str(path)!r} is not a readable CSV table ({exc})") from exc
    df.columns = [str(c).strip().strip("\"'`").strip() for c in df.columns]
    return df


def frames_from_one_based(values: pd.Series, where: str) -> np.ndarray:
    """0-based frames from a column that counts from 1; ``ValueError`` naming ``where`` if not."""
    vals = numeric_column(values, "frame", where)
    if not np.all(np.isfinite(vals)) or np.any(vals != np.round(vals)):
        raise ValueError(f"{where} column 'frame' must hold integers")
    if np.any(vals < 1):
        raise ValueError(f"{where} column 'frame' must be >= 1 (this format counts from 1)")
    return vals.astype(np.int64) - 1
