"""Input checks and pixel grids shared by the renderers (:mod:`sparseloc.render`) and the
Fourier ring correlation (:mod:`sparseloc.frc`).

Coordinates follow the localization tables: nm, ``x`` to the right, ``y`` down. An axis's grid
starts at a multiple of the pixel size unless an extent is given.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
from numpy.typing import NDArray

__all__ = [
    "AXIAL_DEFAULT_FACTOR",
    "MAX_PIXELS",
    "PAD_CAP_PX",
    "POSITION_COLUMNS",
    "SIGMA_COLUMNS",
    "TRUNCATE",
    "axis_grid",
    "check_size",
    "check_table",
    "finite_rows",
    "positive_nm",
    "widths",
]

# Messages keep the logger of sparseloc.render, where the renderers have always logged.
log = logging.getLogger("sparseloc.render")

#: Largest image or volume (pixels or voxels) any renderer will allocate.
MAX_PIXELS: int = 200_000_000
#: Spots are cut at this many standard deviations.
TRUNCATE: float = 4.0
#: Widths up to this many pixels always count when an extent is padded (see :func:`axis_grid`).
PAD_CAP_PX: float = 100.0
#: Axial default width as a multiple of the lateral one when a table has no ``sigma_z_nm``.
AXIAL_DEFAULT_FACTOR: float = 2.5

#: Table column of the position along each axis (nm).
POSITION_COLUMNS = {"x": "x_nm", "y": "y_nm", "z": "z_nm"}
#: Table column of the uncertainty along each axis (nm).
SIGMA_COLUMNS = {"x": "sigma_x_nm", "y": "sigma_y_nm", "z": "sigma_z_nm"}


def positive_nm(value: float, name: str) -> float:
    """``value`` as a float; ``ValueError`` naming ``name`` unless it is finite and > 0."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number of nm, got {value!r}")
    return v


def check_table(locs: pd.DataFrame, axes: tuple[str, ...]) -> None:
    """Raise unless ``locs`` is a non-empty table with the position columns of ``axes``."""
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(f"expected a localization table (DataFrame), got {type(locs).__name__}")
    for a in axes:
        if POSITION_COLUMNS[a] not in locs.columns:
            raise ValueError(f"the localization table has no column {POSITION_COLUMNS[a]!r}")
    if len(locs) == 0:
        raise ValueError("the localization table is empty: there is nothing to render")


def finite_rows(locs: pd.DataFrame, axes: tuple[str, ...]) -> tuple[NDArray, NDArray[np.bool_]]:
    """Positions (n, len(axes)) in nm of the rows whose coordinates are all finite."""
    pos = np.column_stack([locs[POSITION_COLUMNS[a]].to_numpy(dtype=np.float64) for a in axes])
    ok = np.all(np.isfinite(pos), axis=1)
    if not ok.all():
        log.info(
            "skipping %d of %d localizations with non-finite coordinates", (~ok).sum(), ok.size
        )
    if not ok.any():
        raise ValueError(f"none of the {ok.size} localizations has finite coordinates")
    return pos[ok], ok


def widths(
    locs: pd.DataFrame,
    axes: tuple[str, ...],
    ok: NDArray[np.bool_],
    default_nm: float,
    floors_nm: tuple[float, ...],
) -> NDArray[np.float64]:
    """Per-localization widths (n, len(axes)) in nm: the table's uncertainties where usable,
    else the default (lateral) or ``AXIAL_DEFAULT_FACTOR`` times it (z), at least the floor."""
    out = np.empty((int(ok.sum()), len(axes)))
    for j, a in enumerate(axes):
        fallback = default_nm * (AXIAL_DEFAULT_FACTOR if a == "z" else 1.0)
        col = SIGMA_COLUMNS[a]
        if col in locs.columns:
            s = locs[col].to_numpy(dtype=np.float64)[ok]
            s = np.where(np.isfinite(s) & (s > 0), s, fallback)
        else:
            s = np.full(out.shape[0], fallback)
        out[:, j] = np.maximum(s, floors_nm[j])
    return out


def axis_grid(
    pos: NDArray, sig: NDArray, step: float, given: tuple[float, float] | None, name: str
) -> tuple[float, int]:
    """Start (nm) and number of pixels along one axis.

    Without ``given`` the data range padded by TRUNCATE (4) 95th-percentile widths, snapped to
    multiples of ``step`` so that images with the same pixel size share a grid; with ``given``
    its start, and its end moved up to a whole number of pixels. Widths larger than the data's
    range (or :data:`PAD_CAP_PX` pixels, if more) are left out of the percentile: such a spot
    spreads over more than the whole image, so the image is sized by the positions, never by
    an absurd uncertainty."""
    if given is None:
        cap = max(float(pos.max() - pos.min()), PAD_CAP_PX * step)
        usable = sig[sig <= cap]
        pad = TRUNCATE * float(np.percentile(usable, 95)) if usable.size else 0.0
        lo = math.floor((float(pos.min()) - pad) / step) * step
        n = max(1, math.ceil((float(pos.max()) + pad - lo) / step))
        return lo, n
    lo, hi = (float(v) for v in given)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"the {name} extent must run from low to high nm, got {lo:g}..{hi:g}")
    return lo, max(1, math.ceil((hi - lo) / step - 1e-9))


def check_size(shape: tuple[int, ...], what: str) -> None:
    """Raise if an image of ``shape`` would exceed :data:`MAX_PIXELS`."""
    total = math.prod(shape)
    if total > MAX_PIXELS:
        dims = " x ".join(str(s) for s in shape)
        raise ValueError(
            f"the {what} would have {dims} = {total:.3g} pixels, over the cap of "
            f"{MAX_PIXELS:.3g}: use larger pixels or a smaller extent"
        )
