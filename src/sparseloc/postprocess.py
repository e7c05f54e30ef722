"""Post-processing of localization tables: the rows every consumer uses, quality filters and
merging of blinks.

Which rows a consumer uses (:func:`select_usable`)
--------------------------------------------------
One rule, used by ``render``, ``report``, ``filter`` (and ``filter --merge``), ``drift``,
``evaluate`` and ``overlay``:

* Rows whose ``flag`` is not ``"ok"`` (a fit at the edge of the z range, with impossible
  uncertainties, outside its window, diverged or not converged) are **excluded by default**;
  ``all_flags=True`` (``--all-flags`` on the command line) includes them. A table without a
  ``flag`` column is all "ok".
* Rows whose ``x_nm`` or ``y_nm`` is not finite, or whose ``x_nm``, ``y_nm`` or ``z_nm`` lies
  beyond :data:`MAX_COORDINATE_NM` (0.1 m, beyond any microscope's field), or whose ``z_nm`` is
  infinite, are **always dropped, with a warning** that counts them: no image or array can be
  sized by them. A NaN ``z_nm`` (a 2D localization) is kept.

Filtering (:func:`filter_locs`)
-------------------------------
Each criterion that is given keeps the rows inside its limits (limits inclusive):

``flag``
    ``flag`` is one of ``flags`` (default only "ok"; ``flags=None`` keeps every flag).
``photons``
    ``photons_min <= photons <= photons_max`` (photons).
``sigma_xy``
    lateral uncertainty ``sqrt((sigma_x_nm^2 + sigma_y_nm^2) / 2) <= sigma_xy_max_nm`` (nm), the
    quadratic mean of the two lateral CRLB standard errors (ThunderSTORM's ``uncertainty_xy``).
``sigma_z``
    ``sigma_z_nm <= sigma_z_max_nm`` (nm).
``gof``
    ``gof <= gof_max`` (deviance per degree of freedom; about 1 for a good fit).
``z``
    ``z_range[0] <= z_nm <= z_range[1]`` (nm).

A row with NaN in a column an active criterion reads fails that criterion. Criteria are applied
in the order above and each removed row is counted once, against the first criterion it fails
(:attr:`FilterResult.removed`, whose counts add up to the rows removed); how many rows fail each
criterion on its own is in :attr:`FilterResult.failed`.

Merging of blinks (:func:`merge_blinks`)
----------------------------------------
A fluorophore that stays on for several frames gives one localization per frame. The rows are
linked into tracks frame by frame, in increasing frame order: a localization in frame ``f`` may
continue a track whose last localization is in frames ``f - 1 - max_gap .. f - 1`` (at most
``max_gap`` dark frames in between) when their lateral distance is at most ``max_distance_nm``
and their axial distance at most ``max_distance_nm / z_scale`` (z is less precise than x, y;
``z_scale=0`` ignores z). Among the allowed (track, localization) pairs of a frame, the
assignment is one-to-one and greedy nearest-first: pairs are taken in increasing order of the
scaled 3D distance ``sqrt(dx^2 + dy^2 + (z_scale * dz)^2)``, skipping pairs whose track or
localization is already taken. Localizations left over start new tracks. A track is compared by
its *last* localization, so a slowly drifting fluorophore stays one track.

Defaults, from the table's own uncertainties (``sigma_xy = sqrt((sigma_x_nm^2 +
sigma_y_nm^2) / 2)``, medians over the rows where a value is finite and positive):

* ``max_distance_nm = 4 * sqrt(2) * median(sigma_xy)``, at least 20 nm; 50 nm when the table
  has no uncertainties (:func:`default_merge_distance`). Two localizations of one fluorophore
  differ by ``sqrt(2) * sigma`` per axis, so this is a 4-sigma gate on their separation, wide
  enough that noise rarely splits a track.
* ``z_scale = median(sigma_xy) / median(sigma_z_nm)``, so the axial gate is as many axial
  sigmas as the lateral gate is lateral ones; 0.5 without axial uncertainties
  (:func:`default_z_scale`).

Each track becomes one row:

* ``x_nm, y_nm, z_nm``: inverse-variance weighted mean (weights ``1 / sigma^2`` of that axis),
  with ``sigma = 1 / sqrt(sum(1 / sigma_i^2))``. When a track has a missing, zero or non-finite
  sigma on an axis, that axis is the plain mean with ``sigma = sqrt(sum(sigma_i^2)) / n`` (NaN
  when any ``sigma_i`` is unknown).
* ``photons``: sum; ``sigma_photons``: ``sqrt(sum(sigma_photons_i^2))``; ``background`` and
  ``gof``: mean; NaN in any member makes the result NaN.
* ``frame``: first frame; ``window_id``: that of the first row; ``flag``: "ok" when every member
  is "ok", else the first non-ok flag in frame order.
* added columns ``n_frames`` (number of localizations merged) and ``last_frame`` (last frame
  of the track).

Rows with a non-finite position are not linked; each is its own track. Extra columns of the
input (beyond the standard ones) are dropped. Two localizations of the same frame are never
merged.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from numbers import Integral, Real

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from .io.tables import LOCS_COLUMNS, check_locs, complete_locs

__all__ = [
    "FILTER_CRITERIA",
    "MAX_COORDINATE_NM",
    "MERGE_COLUMNS",
    "FilterResult",
    "Usable",
    "default_merge_distance",
    "default_z_scale",
    "excluded_note",
    "filter_locs",
    "flagged_rows",
    "link_blinks",
    "merge_blinks",
    "select_usable",
    "usable_locs",
]

logger = logging.getLogger(__name__)

#: Names of the filter criteria, in the order they are applied.
FILTER_CRITERIA: tuple[str, ...] = ("flag", "photons", "sigma_xy", "sigma_z", "gof", "z")
#: Columns of a merged table: the standard ones, then these.
MERGE_COLUMNS: tuple[str, ...] = (*LOCS_COLUMNS, "n_frames", "last_frame")

_MIN_DEFAULT_DISTANCE_NM = 20.0
_FALLBACK_DISTANCE_NM = 50.0
_GATE_SIGMAS = 4.0
_FALLBACK_Z_SCALE = 0.5
#: Largest |coordinate| (nm) a usable row may have: 0.1 m, far beyond any microscope's field.
MAX_COORDINATE_NM: float = 1e8
# Below this many (track, localization) pairs in a frame a dense distance matrix is cheaper than
# building two k-d trees.
_BRUTE_FORCE_PAIRS = 4096


# --------------------------------------------------------------------------------------------
# the rows every consumer uses
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Usable:
    """Outcome of :func:`select_usable`.

    Attributes
    ----------
    locs : DataFrame
        The rows used, in input order, index reset; columns as given.
    n_input : int
        Rows of the input table.
    n_flagged : int
        Rows excluded because their flag is not "ok" (0 with ``all_flags``).
    n_bad_position : int
        Rows dropped for a non-finite or absurd coordinate.
    """

    locs: pd.DataFrame
    n_input: int
    n_flagged: int
    n_bad_position: int

    def note(self) -> str:
        """One line saying how many flagged rows were excluded, or ``""`` when none was (the
        rows dropped for their coordinates are reported by a logged warning instead)."""
        return excluded_note(self.n_flagged)


def excluded_note(n_flagged: int) -> str:
    """The line that says ``n_flagged`` flagged rows were excluded (``""`` for none)."""
    if not n_flagged:
        return ""
    return f"excluded {n_flagged:,} flagged localizations (--all-flags includes them)"


def select_usable(locs: pd.DataFrame, *, all_flags: bool = False) -> Usable:
    """The rows a consumer uses, by the rule of the module docstring.

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``x_nm`` and ``y_nm`` (nm); ``z_nm`` (nm) and ``flag``
        are read when present. Not modified.
    all_flags : bool
        Include rows whose flag is not "ok".

    Returns
    -------
    Usable
        The rows used and the counts of those left out. Rows dropped for their coordinates are
        also reported by a logged warning.

    Raises
    ------
    ValueError
        If ``locs`` is not a table with ``x_nm`` and ``y_nm``, or no row is left.
    """
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(f"expected a localization table (DataFrame), got {type(locs).__name__}")
    missing = [c for c in ("x_nm", "y_nm") if c not in locs.columns]
    if missing:
        raise ValueError(f"the localization table has no column(s) {', '.join(missing)}")
    n = len(locs)
    flagged = flagged_rows(locs, all_flags=all_flags)
    with np.errstate(invalid="ignore"):
        x, y = _column(locs, "x_nm"), _column(locs, "y_nm")
        good = np.isfinite(x) & np.isfinite(y)
        good &= (np.abs(x) <= MAX_COORDINATE_NM) & (np.abs(y) <= MAX_COORDINATE_NM)
        if "z_nm" in locs.columns:
            z = _column(locs, "z_nm")
            good &= np.isnan(z) | (np.abs(z) <= MAX_COORDINATE_NM)
    bad_position = ~good & ~flagged
    keep = good & ~flagged
    if n and not keep.any():
        why = "flag 'ok' and " if not all_flags and "flag" in locs.columns else ""
        hint = " (--all-flags includes flagged rows)" if flagged.any() else ""
        raise ValueError(
            f"none of the {n:,} localizations is usable ({why}finite coordinates within "
            f"{MAX_COORDINATE_NM:g} nm){hint}"
        )
    # Warned only when rows remain: with none, the refusal above says it (a warning before
    # it would print the same cause twice).
    if bad_position.any():
        logger.warning(
            "dropped %d localizations with a non-finite coordinate or one beyond %g nm",
            int(bad_position.sum()),
            MAX_COORDINATE_NM,
        )
    out = locs.loc[keep].reset_index(drop=True)
    return Usable(out, n, int(flagged.sum()), int(bad_position.sum()))


def flagged_rows(locs: pd.DataFrame, *, all_flags: bool = False) -> np.ndarray:
    """The flag part of the rule: which rows of ``locs`` are excluded for their flag.

    Parameters
    ----------
    locs : DataFrame
        Localization table; ``flag`` is read when present (absent: every row "ok").
    all_flags : bool
        Exclude no row.

    Returns
    -------
    ndarray of bool, shape (len(locs),)
        True where the flag is not "ok" (all False with ``all_flags``).
    """
    if all_flags or "flag" not in locs.columns:
        return np.zeros(len(locs), dtype=bool)
    return locs["flag"].astype(str).to_numpy() != "ok"


def usable_locs(locs: pd.DataFrame, *, all_flags: bool = False) -> pd.DataFrame:
    """The rows of ``locs`` a consumer uses (:func:`select_usable`), as a table."""
    return select_usable(locs, all_flags=all_flags).locs


# --------------------------------------------------------------------------------------------
# filtering
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FilterResult:
    """Outcome of :func:`filter_locs`.

    Attributes
    ----------
    locs : DataFrame
        The rows kept, in input order, index reset; standard columns and dtypes
        (:func:`~sparseloc.io.tables.check_locs`), extra columns kept after them.
    removed : dict of str to int
        For each active criterion (in :data:`FILTER_CRITERIA` order), the rows removed by it:
        each removed row counts once, against the first criterion it fails. The counts add up
        to ``n_input - n_kept``.
    failed : dict of str to int
        For each active criterion, the rows failing it on its own (rows may count in several).
    n_input : int
        Rows of the input table.
    """

    locs: pd.DataFrame
    removed: dict[str, int] = field(default_factory=dict)
    failed: dict[str, int] = field(default_factory=dict)
    n_input: int = 0

    @property
    def n_kept(self) -> int:
        """Rows kept."""
        return len(self.locs)

    @property
    def n_removed(self) -> int:
        """Rows removed."""
        return self.n_input - self.n_kept

    def summary(self) -> str:
        """One line such as ``kept 850 of 1000 localizations; removed 120 by photons, ...``."""
        head = f"kept {self.n_kept} of {self.n_input} localizations"
        if not self.removed:
            return head + " (no criterion active)"
        parts = ", ".join(f"{n} by {name}" for name, n in self.removed.items())
        return f"{head}; removed {parts}"


def filter_locs(
    locs: pd.DataFrame,
    *,
    photons_min: float | None = None,
    photons_max: float | None = None,
    sigma_xy_max_nm: float | None = None,
    sigma_z_max_nm: float | None = None,
    gof_max: float | None = None,
    z_range: tuple[float, float] | None = None,
    flags: Iterable[str] | str | None = ("ok",),
) -> FilterResult:
    """Keep the localizations that pass quality criteria and count what each one removes.

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``frame, x_nm, y_nm`` and the columns of the active
        criteria (a missing ``flag`` column means every row is "ok"); other missing standard
        columns are filled as by :func:`~sparseloc.io.tables.complete_locs`. Not modified.
    photons_min, photons_max : float, optional
        Inclusive limits on ``photons`` (photons).
    sigma_xy_max_nm : float, optional
        Largest lateral uncertainty ``sqrt((sigma_x_nm^2 + sigma_y_nm^2) / 2)`` kept (nm).
    sigma_z_max_nm : float, optional
        Largest ``sigma_z_nm`` kept (nm).
    gof_max : float, optional
        Largest ``gof`` kept (deviance per degree of freedom).
    z_range : (float, float), optional
        Inclusive ``(z_min, z_max)`` on ``z_nm`` (nm).
    flags : iterable of str or str, optional
        Flags kept (default only "ok"); ``None`` keeps every flag.

    Returns
    -------
    FilterResult
        The rows kept and the counts of rows removed per criterion.

    Raises
    ------
    ValueError
        If a limit is not a finite number, a range is reversed, a sigma or gof limit is not
        positive, ``flags`` is empty, or a column an active criterion needs is missing.
    """
    if not isinstance(locs, pd.DataFrame):
        raise ValueError(f"locs must be a pandas DataFrame, got {type(locs).__name__}")
    limits = _filter_limits(
        photons_min, photons_max, sigma_xy_max_nm, sigma_z_max_nm, gof_max, z_range
    )
    keep_flags: set[str] | None = None
    if flags is not None:
        keep_flags = {flags} if isinstance(flags, str) else {str(f) for f in flags}
        if not keep_flags:
            raise ValueError("flags is empty, which would remove every row; use None to keep all")
    _check_filter_columns(locs, limits)
    t = complete_locs(locs)
    masks = _criterion_masks(t, limits, keep_flags)
    alive = np.ones(len(t), dtype=bool)
    removed: dict[str, int] = {}
    failed: dict[str, int] = {}
    for name in FILTER_CRITERIA:
        if name not in masks:
            continue
        ok = masks[name]
        failed[name] = int(np.count_nonzero(~ok))
        removed[name] = int(np.count_nonzero(alive & ~ok))
        alive &= ok
    out = FilterResult(
        locs=t.loc[alive].reset_index(drop=True), removed=removed, failed=failed, n_input=len(t)
    )
    logger.info("filter_locs: %s", out.summary())
    return out


@dataclass(frozen=True)
class _Limits:
    """The checked numeric limits of :func:`filter_locs` (None: criterion not active)."""

    photons_min: float | None
    photons_max: float | None
    sigma_xy_max_nm: float | None
    sigma_z_max_nm: float | None
    gof_max: float | None
    z_range: tuple[float, float] | None

    @property
    def photons(self) -> bool:
        return self.photons_min is not None or self.photons_max is not None


def _filter_limits(
    photons_min: float | None,
    photons_max: float | None,
    sigma_xy_max_nm: float | None,
    sigma_z_max_nm: float | None,
    gof_max: float | None,
    z_range: tuple[float, float] | None,
) -> _Limits:
    """The limits of :func:`filter_locs`, checked; ``ValueError`` naming a bad one."""
    photons_min = _opt_number(photons_min, "photons_min")
    photons_max = _opt_number(photons_max, "photons_max")
    sigma_xy_max_nm = _opt_number(sigma_xy_max_nm, "sigma_xy_max_nm", positive=True)
    sigma_z_max_nm = _opt_number(sigma_z_max_nm, "sigma_z_max_nm", positive=True)
    gof_max = _opt_number(gof_max, "gof_max", positive=True)
    if photons_min is not None and photons_max is not None and photons_min > photons_max:
        raise ValueError(
            f"photons_min ({photons_min:g}) is larger than photons_max ({photons_max:g})"
        )
    z = None
    if z_range is not None:
        try:
            z_lo, z_hi = z_range
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"z_range must be a pair (z_min, z_max) in nm, got {z_range!r}"
            ) from exc
        z_lo = _opt_number(z_lo, "z_range[0]")
        z_hi = _opt_number(z_hi, "z_range[1]")
        if z_lo > z_hi:  # type: ignore[operator]
            raise ValueError(f"z_range is reversed: z_min {z_lo:g} nm > z_max {z_hi:g} nm")
        z = (z_lo, z_hi)
    return _Limits(photons_min, photons_max, sigma_xy_max_nm, sigma_z_max_nm, gof_max, z)


def _check_filter_columns(locs: pd.DataFrame, limits: _Limits) -> None:
    """Raise if ``locs`` lacks a column an active criterion reads.

    complete_locs would fill such a column with NaN and the criterion would then silently
    remove every row. A missing flag column is the exception: it means every row is "ok".
    """
    needed: list[str] = []
    if limits.photons:
        needed.append("photons")
    if limits.sigma_xy_max_nm is not None:
        needed += ["sigma_x_nm", "sigma_y_nm"]
    if limits.sigma_z_max_nm is not None:
        needed.append("sigma_z_nm")
    if limits.gof_max is not None:
        needed.append("gof")
    if limits.z_range is not None:
        needed.append("z_nm")
    missing = [c for c in needed if c not in locs.columns]
    if missing:
        raise ValueError(
            f"the localization table has no column(s) {', '.join(missing)}, which the "
            "requested filter criteria need"
        )


def _criterion_masks(
    t: pd.DataFrame, limits: _Limits, keep_flags: set[str] | None
) -> dict[str, np.ndarray]:
    """The rows of the complete table ``t`` that pass each active criterion."""
    # NaN compares False, so a row with NaN fails every bound it is tested against.
    masks: dict[str, np.ndarray] = {}
    if keep_flags is not None:
        masks["flag"] = t["flag"].isin(keep_flags).to_numpy()
    if limits.photons:
        masks["photons"] = _within(t["photons"].to_numpy(), limits.photons_min, limits.photons_max)
    if limits.sigma_xy_max_nm is not None:
        masks["sigma_xy"] = _within(_lateral_sigma(t), None, limits.sigma_xy_max_nm)
    if limits.sigma_z_max_nm is not None:
        masks["sigma_z"] = _within(t["sigma_z_nm"].to_numpy(), None, limits.sigma_z_max_nm)
    if limits.gof_max is not None:
        masks["gof"] = _within(t["gof"].to_numpy(), None, limits.gof_max)
    if limits.z_range is not None:
        masks["z"] = _within(t["z_nm"].to_numpy(), *limits.z_range)
    return masks


def _within(values: np.ndarray, lo: float | None, hi: float | None) -> np.ndarray:
    ok = ~np.isnan(values)
    if lo is not None:
        ok &= values >= lo
    if hi is not None:
        ok &= values <= hi
    return ok


def _opt_number(value: object, name: str, *, positive: bool = False) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, Real) or not np.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and float(value) <= 0:
        raise ValueError(f"{name} must be > 0, got {float(value):g}")
    return float(value)


# --------------------------------------------------------------------------------------------
# merging of blinks
# --------------------------------------------------------------------------------------------


def default_merge_distance(locs: pd.DataFrame) -> float:
    """Default linking distance of :func:`merge_blinks` (nm).

    Two localizations of one fluorophore differ by noise of standard deviation ``sqrt(2)``
    times their lateral uncertainty ``sigma_xy = sqrt((sigma_x_nm^2 + sigma_y_nm^2) / 2)``; the
    default allows four such standard deviations so that a track is rarely split by noise
    (a 3-sigma gate splits about 1 link in 10 per axis).

    Parameters
    ----------
    locs : DataFrame
        Localization table; reads ``sigma_x_nm`` and ``sigma_y_nm`` (nm) when present.

    Returns
    -------
    float
        ``4 * sqrt(2) * median(sigma_xy)`` over the rows where ``sigma_xy`` is finite and
        positive, at least 20 nm; 50 nm when there is no such row.
    """
    sxy = _finite_positive(_lateral_sigma(locs))
    if sxy.size == 0:
        return _FALLBACK_DISTANCE_NM
    return max(_GATE_SIGMAS * np.sqrt(2.0) * float(np.median(sxy)), _MIN_DEFAULT_DISTANCE_NM)


def default_z_scale(locs: pd.DataFrame) -> float:
    """Default weight of z against x, y in :func:`merge_blinks`.

    Parameters
    ----------
    locs : DataFrame
        Localization table; reads ``sigma_x_nm``, ``sigma_y_nm`` and ``sigma_z_nm`` (nm).

    Returns
    -------
    float
        ``median(sigma_xy) / median(sigma_z_nm)`` over the rows where each is finite and
        positive, so that the axial limit ``max_distance_nm / z_scale`` is as many axial
        standard deviations as the lateral limit is lateral ones; 0.5 when either is unknown.
    """
    sxy = _finite_positive(_lateral_sigma(locs))
    sz = _finite_positive(_column(locs, "sigma_z_nm"))
    if sxy.size == 0 or sz.size == 0:
        return _FALLBACK_Z_SCALE
    return float(np.median(sxy) / np.median(sz))


def _column(locs: pd.DataFrame, name: str) -> np.ndarray:
    if name not in locs.columns:
        return np.full(len(locs), np.nan)
    return pd.to_numeric(locs[name], errors="coerce").to_numpy(dtype=np.float64)


def _lateral_sigma(locs: pd.DataFrame) -> np.ndarray:
    sx, sy = _column(locs, "sigma_x_nm"), _column(locs, "sigma_y_nm")
    with np.errstate(invalid="ignore", over="ignore"):
        return np.sqrt((sx**2 + sy**2) / 2)


def _finite_positive(values: np.ndarray) -> np.ndarray:
    return values[np.isfinite(values) & (values > 0)]


def link_blinks(
    locs: pd.DataFrame,
    *,
    max_distance_nm: float | None = None,
    max_gap: int = 1,
    z_scale: float | None = None,
) -> np.ndarray:
    """Link the localizations of one fluorophore in consecutive frames into tracks.

    The rules are those of the module docstring (greedy nearest-first, one-to-one per frame).

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``frame, x_nm, y_nm`` (``z_nm`` is 0 nm if absent).
    max_distance_nm : float, optional
        Largest lateral distance (nm) between a localization and the last one of the track it
        continues; the axial limit is ``max_distance_nm / z_scale``. Default
        :func:`default_merge_distance`.
    max_gap : int
        Most dark frames allowed inside a track (0: only consecutive frames).
    z_scale : float, optional
        Weight of z against x, y (>= 0; 0 ignores z). Default :func:`default_z_scale`.

    Returns
    -------
    ndarray of int64
        Track label of each row, in input row order; labels are 0, 1, ... in order of the
        tracks' first frames.

    Raises
    ------
    ValueError
        If ``max_distance_nm`` is not a positive finite number, ``max_gap`` not an integer
        >= 0, ``z_scale`` not a finite number >= 0, or the table is invalid (e.g. lacks
        ``frame``, ``x_nm`` or ``y_nm``).
    """
    t = complete_locs(locs)
    dist, gap, zs = _merge_params(t, max_distance_nm, max_gap, z_scale)
    return _link(t, dist, gap, zs)


def merge_blinks(
    locs: pd.DataFrame,
    *,
    max_distance_nm: float | None = None,
    max_gap: int = 1,
    z_scale: float | None = None,
) -> pd.DataFrame:
    """Replace each fluorophore's run of per-frame localizations by one localization.

    Links with :func:`link_blinks` and combines each track as described in the module
    docstring (inverse-variance weighted position, summed photons, ...).

    Parameters
    ----------
    locs : DataFrame
        Localization table with at least ``frame, x_nm, y_nm``; missing standard columns are
        filled as by :func:`~sparseloc.io.tables.complete_locs` (no sigmas: plain means and the
        50 nm default distance). Not modified.
    max_distance_nm : float, optional
        Largest lateral distance (nm) to the last localization of a track; axially
        ``max_distance_nm / z_scale``. Default :func:`default_merge_distance`:
        ``4 * sqrt(2)`` x the median lateral uncertainty, at least 20 nm, 50 nm without
        uncertainties.
    max_gap : int
        Most dark frames allowed inside a track (default 1).
    z_scale : float, optional
        Weight of z against x, y in the distance (>= 0; 0 ignores z). Default
        :func:`default_z_scale`: median lateral over median axial uncertainty, 0.5 without
        uncertainties (z may then differ twice as much as x, y).

    Returns
    -------
    DataFrame
        One row per track, columns :data:`MERGE_COLUMNS` (standard columns and dtypes, then
        ``n_frames`` and ``last_frame``, int64), sorted by ``frame`` then ``x_nm``.

    Raises
    ------
    ValueError
        As :func:`link_blinks`.
    """
    t = complete_locs(locs)
    dist, gap, zs = _merge_params(t, max_distance_nm, max_gap, z_scale)
    n = len(t)
    if n == 0:
        return _merged_frame({c: np.empty(0) for c in MERGE_COLUMNS}, np.empty(0, dtype=str))
    labels = _link(t, dist, gap, zs)
    merged = _merged_frame(*_combine_tracks(t, labels))
    logger.info(
        "merge_blinks: %d localizations -> %d (max distance %.1f nm, max gap %d, z scale %g)",
        n,
        len(merged),
        dist,
        gap,
        zs,
    )
    return merged


def _combine_tracks(
    t: pd.DataFrame, labels: np.ndarray
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The columns of the merged table, one row per track label (rules in the module
    docstring), and the flag of each track."""
    n = len(t)
    frame = t["frame"].to_numpy()
    # Rows grouped by track, each track's rows in frame order: reduceat then works per track.
    order = np.lexsort((frame, labels))
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], n] - 1
    count = np.diff(np.r_[starts, n]).astype(np.float64)

    def col(name: str) -> np.ndarray:
        return t[name].to_numpy(dtype=np.float64)[order]

    def total(values: np.ndarray) -> np.ndarray:
        return np.add.reduceat(values, starts)

    out: dict[str, np.ndarray] = {"frame": frame[order][starts]}
    for axis in ("x", "y", "z"):
        pos, sig = col(f"{axis}_nm"), col(f"sigma_{axis}_nm")
        good = np.isfinite(sig) & (sig > 0)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            w = np.where(good, 1.0 / np.where(good, sig, 1.0) ** 2, 0.0)
            weighted = total(good.astype(np.float64)) == count
            sw = total(w)
            mean_w = total(w * np.where(good, pos, 0.0)) / sw
            sig_w = 1.0 / np.sqrt(sw)
            mean_p = total(pos) / count
            sig_p = np.sqrt(total(sig**2)) / count
        out[f"{axis}_nm"] = np.where(weighted, mean_w, mean_p)
        out[f"sigma_{axis}_nm"] = np.where(weighted, sig_w, sig_p)
    with np.errstate(invalid="ignore", over="ignore"):
        out["photons"] = total(col("photons"))
        out["sigma_photons"] = np.sqrt(total(col("sigma_photons") ** 2))
        out["background"] = total(col("background")) / count
        out["gof"] = total(col("gof")) / count
    out["window_id"] = t["window_id"].to_numpy()[order][starts]
    out["n_frames"] = count
    out["last_frame"] = frame[order][ends]
    return out, _first_non_ok(t["flag"].to_numpy(dtype=object)[order], starts)


def _first_non_ok(flag_all: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per track (rows from each of ``starts``): "ok", or its first flag that is not "ok"."""
    n = len(flag_all)
    bad_pos = np.where(flag_all != "ok", np.arange(n), n)
    first_bad = np.minimum.reduceat(bad_pos, starts)
    return np.where(first_bad < n, flag_all[np.minimum(first_bad, n - 1)], "ok")


def _merged_frame(cols: dict[str, np.ndarray], flags: np.ndarray) -> pd.DataFrame:
    data = {c: cols[c] for c in MERGE_COLUMNS if c != "flag"}
    df = pd.DataFrame(data)
    df["flag"] = pd.Series(flags, dtype=object).astype(str)
    df = check_locs(df, what="merged table")
    df["n_frames"] = df["n_frames"].astype(np.int64)
    df["last_frame"] = df["last_frame"].astype(np.int64)
    df = df[list(MERGE_COLUMNS)]
    order = np.lexsort((df["x_nm"].to_numpy(), df["frame"].to_numpy()))
    return df.iloc[order].reset_index(drop=True)


def _merge_params(
    t: pd.DataFrame, max_distance_nm: float | None, max_gap: int, z_scale: float | None
) -> tuple[float, int, float]:
    if max_distance_nm is None:
        dist = default_merge_distance(t)
        logger.debug("merge distance %.1f nm (default rule)", dist)
    else:
        dist = _opt_number(max_distance_nm, "max_distance_nm", positive=True)  # type: ignore[assignment]
    if isinstance(max_gap, bool) or not isinstance(max_gap, Integral) or max_gap < 0:
        raise ValueError(f"max_gap must be an integer >= 0 (dark frames), got {max_gap!r}")
    if z_scale is None:
        zs = default_z_scale(t)
        logger.debug("z scale %.3g (default rule)", zs)
    else:
        zs = _opt_number(z_scale, "z_scale")  # type: ignore[assignment]
        if zs < 0:  # type: ignore[operator]
            raise ValueError(f"z_scale must be >= 0 (0 ignores z), got {z_scale!r}")
    return float(dist), int(max_gap), float(zs)  # type: ignore[arg-type]


def _link(t: pd.DataFrame, dist: float, max_gap: int, z_scale: float) -> np.ndarray:
    """Track label per row of ``t`` (a :func:`complete_locs` table); see the module rules."""
    n = len(t)
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    frame = t["frame"].to_numpy()
    pos = np.column_stack(
        [t["x_nm"].to_numpy(), t["y_nm"].to_numpy(), z_scale * t["z_nm"].to_numpy()]
    )
    finite = np.isfinite(pos).all(axis=1)
    rows = np.flatnonzero(finite)
    rows = rows[np.argsort(frame[rows], kind="stable")]
    fr = frame[rows]
    # One cut per change of frame; no rows, no frames (not one empty frame).
    cut = np.flatnonzero(np.r_[True, fr[1:] != fr[:-1], True]) if rows.size else np.zeros(1, int)
    d2 = dist * dist
    # The cylinder |lateral| <= d, |scaled dz| <= d lies inside the sphere of radius d * sqrt(2).
    radius = dist * np.sqrt(2.0) * (1 + 1e-12)

    # Active tracks: label, last frame, last (scaled) position.
    act_id = np.empty(0, dtype=np.int64)
    act_last = np.empty(0, dtype=np.int64)
    act_pos = np.empty((0, 3))
    next_id = 0
    for k in range(len(cut) - 1):
        idx = rows[cut[k] : cut[k + 1]]
        f = int(fr[cut[k]])
        keep = act_last >= f - 1 - max_gap
        if not keep.all():
            act_id, act_last, act_pos = act_id[keep], act_last[keep], act_pos[keep]
        pts = pos[idx]
        n_t, n_p = len(act_id), len(idx)
        matched_p = np.zeros(n_p, dtype=bool)
        if n_t and n_p:
            ti, pj = _candidate_pairs(act_pos, pts, d2, dist, radius)
            if ti.size:
                at, ap = _greedy_one_to_one(ti, pj, act_pos, pts, n_t, n_p)
                labels[idx[ap]] = act_id[at]
                act_last[at] = f
                act_pos[at] = pts[ap]
                matched_p[ap] = True
        new = np.flatnonzero(~matched_p)
        if new.size:
            ids = np.arange(next_id, next_id + new.size, dtype=np.int64)
            next_id += new.size
            labels[idx[new]] = ids
            act_id = np.concatenate([act_id, ids])
            act_last = np.concatenate([act_last, np.full(new.size, f, dtype=np.int64)])
            act_pos = np.concatenate([act_pos, pts[new]])
    # Rows without a finite position are tracks of their own, numbered in frame order after
    # the linked ones (labels only need to be unique).
    lone = np.flatnonzero(~finite)
    if lone.size:
        lone = lone[np.argsort(frame[lone], kind="stable")]
        labels[lone] = np.arange(next_id, next_id + lone.size)
        logger.debug("%d localizations with a non-finite position left unmerged", lone.size)
    # Renumber in order of first frame so that labels are stable and readable.
    first = np.full(labels.max() + 1, np.iinfo(np.int64).max, dtype=np.int64)
    np.minimum.at(first, labels, frame)
    rank = np.empty_like(first)
    rank[np.lexsort((np.arange(first.size), first))] = np.arange(first.size)
    return rank[labels]


def _candidate_pairs(
    tracks: np.ndarray, pts: np.ndarray, d2: float, dist: float, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """(track, point) index pairs with lateral distance <= dist and scaled |dz| <= dist."""
    if len(tracks) * len(pts) <= _BRUTE_FORCE_PAIRS:
        diff = tracks[:, None, :] - pts[None, :, :]
        lat2 = diff[..., 0] ** 2 + diff[..., 1] ** 2
        ti, pj = np.nonzero((lat2 <= d2) & (np.abs(diff[..., 2]) <= dist))
        return ti, pj
    pairs = cKDTree(tracks).sparse_distance_matrix(cKDTree(pts), radius, output_type="ndarray")
    ti = pairs["i"].astype(np.intp)
    pj = pairs["j"].astype(np.intp)
    diff = tracks[ti] - pts[pj]
    ok = (diff[:, 0] ** 2 + diff[:, 1] ** 2 <= d2) & (np.abs(diff[:, 2]) <= dist)
    return ti[ok], pj[ok]


def _greedy_one_to_one(
    ti: np.ndarray, pj: np.ndarray, tracks: np.ndarray, pts: np.ndarray, n_t: int, n_p: int
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy nearest-first one-to-one assignment of candidate pairs, vectorized.

    Same result as walking the pairs in increasing distance and taking every pair whose track
    and point are both free: in each round, a pair that is the nearest remaining pair of both its
    track and its point is one the walk would take, so all such pairs are taken at once and the
    pairs touching them dropped. Ties are broken by track, then point index.
    """
    diff = tracks[ti] - pts[pj]
    d = np.einsum("ij,ij->i", diff, diff)
    order = np.lexsort((pj, ti, d))
    ti, pj = ti[order], pj[order]
    take_t: list[np.ndarray] = []
    take_p: list[np.ndarray] = []
    used_t = np.zeros(n_t, dtype=bool)
    used_p = np.zeros(n_p, dtype=bool)
    while ti.size:
        # np.unique's return_index gives the first (nearest) pair of each track / point.
        best = np.zeros(ti.size, dtype=bool)
        best[np.unique(ti, return_index=True)[1]] = True
        best_p = np.zeros(ti.size, dtype=bool)
        best_p[np.unique(pj, return_index=True)[1]] = True
        best &= best_p
        at, ap = ti[best], pj[best]
        take_t.append(at)
        take_p.append(ap)
        used_t[at] = True
        used_p[ap] = True
        free = ~used_t[ti] & ~used_p[pj]
        ti, pj = ti[free], pj[free]
    return np.concatenate(take_t), np.concatenate(take_p)
