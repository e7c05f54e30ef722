"""Matching of localizations to ground truth and SMLM-challenge metrics.

The metrics follow the 2016 SMLM challenge (Sage et al., Nature Methods 16, 387-395, 2019):
localizations and ground-truth emitters of the same frame are paired one-to-one when they lie
within a lateral and an axial tolerance; paired localizations are true positives (TP), unpaired
localizations false positives (FP), unpaired emitters false negatives (FN). From these follow
the Jaccard index, recall, precision, the root-mean-square errors and biases of the pairs, and
the efficiency that combines detection and precision.

Units: positions and tolerances in nm, frames 0-based (any integer or float label works: only
equality of frame labels matters).

Matching rule
-------------
Within one frame a localization ``i`` and an emitter ``j`` may be paired only when their lateral
distance ``sqrt(dx^2 + dy^2) <= lateral_tol`` and (3D evaluation only) ``|dz| <= axial_tol``.
Among the allowed pairs the assignment first **maximises the number of pairs** and then
**minimises the sum of their 3D Euclidean distances** ``sqrt(dx^2 + dy^2 + dz^2)`` (the lateral
distance in a 2D evaluation). This is a minimum-cost maximum-cardinality bipartite matching,
solved exactly with the Hungarian algorithm (:func:`scipy.optimize.linear_sum_assignment`) on a
cost matrix in which forbidden pairs carry a penalty larger than any sum of allowed costs.

The problem is decomposed before any Hungarian step: the allowed pairs of all frames are found
at once with a k-d tree, the bipartite graph of allowed pairs is split into connected components,
components with a single allowed pair (the common case at SMLM densities) are matched directly
and vectorised, and only components with competing pairs are passed to the Hungarian algorithm,
each as a small dense problem.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    "ALPHA_AXIAL",
    "ALPHA_LATERAL",
    "Evaluation",
    "efficiency",
    "evaluate",
    "match_localizations",
]

#: Efficiency weight of the lateral RMSE, in percent per nm (SMLM 2016 challenge).
ALPHA_LATERAL: float = 1.0
#: Efficiency weight of the axial RMSE, in percent per nm (SMLM 2016 challenge).
ALPHA_AXIAL: float = 0.5

_REQUIRED = ("frame", "x_nm", "y_nm")

_MATCH_COLUMNS = [
    "frame",
    "loc_row",
    "truth_row",
    "x_loc",
    "y_loc",
    "z_loc",
    "x_truth",
    "y_truth",
    "z_truth",
    "dx",
    "dy",
    "dz",
    "dist_lateral",
    "dist_3d",
]


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------
def _check_table(df: pd.DataFrame, name: str) -> None:
    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"{name} must be a pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in _REQUIRED if c not in df.columns]
    if missing:
        raise ValueError(
            f"{name} is missing required column(s) {', '.join(repr(c) for c in missing)}; "
            f"expected at least {', '.join(_REQUIRED)} (and z_nm for a 3D evaluation)"
        )
    for col in ("x_nm", "y_nm", "z_nm"):
        if col in df.columns:
            vals = np.asarray(df[col], dtype=np.float64)
            if not np.all(np.isfinite(vals)):
                raise ValueError(f"{name}[{col!r}] contains NaN or infinite values")
    if df["frame"].isna().any():
        raise ValueError(f"{name}['frame'] contains missing values")


def _check_tolerances(lateral_tol: float, axial_tol: float) -> tuple[float, float]:
    lat, ax = float(lateral_tol), float(axial_tol)
    if not (np.isfinite(lat) and lat >= 0):
        raise ValueError(f"lateral_tol must be a finite number >= 0 nm, got {lateral_tol!r}")
    if not (ax >= 0) or np.isnan(ax):
        raise ValueError(f"axial_tol must be a number >= 0 nm (inf allowed), got {axial_tol!r}")
    return lat, ax


def _is_3d(locs: pd.DataFrame, truth: pd.DataFrame) -> bool:
    return "z_nm" in locs.columns and "z_nm" in truth.columns


# --------------------------------------------------------------------------------------------
# Matching
# --------------------------------------------------------------------------------------------
def _assign_component(cost: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Maximum-cardinality, minimum-cost matching on a dense cost with ``inf`` = forbidden."""
    allowed = np.isfinite(cost)
    finite = cost[allowed]
    # A penalty larger than the sum of any set of allowed costs makes every extra allowed pair
    # worth more than any saving in distance: cardinality first, then total distance.
    penalty = (min(cost.shape) + 1.0) * (float(finite.max(initial=0.0)) + 1.0)
    work = np.where(allowed, cost, penalty)
    r, c = linear_sum_assignment(work)
    keep = allowed[r, c]
    return r[keep], c[keep]


def match_localizations(
    locs: pd.DataFrame,
    truth: pd.DataFrame,
    *,
    lateral_tol: float = 250.0,
    axial_tol: float = 500.0,
) -> pd.DataFrame:
    """Pair localizations with ground-truth emitters, one-to-one, frame by frame.

    See the module docstring for the matching rule: pairs must satisfy
    ``lateral distance <= lateral_tol`` and ``|dz| <= axial_tol`` (both inclusive); the
    assignment maximises the number of pairs, then minimises the sum of 3D distances.

    Parameters
    ----------
    locs : DataFrame, N rows
        Localizations with columns ``frame``, ``x_nm``, ``y_nm`` and optionally ``z_nm`` (nm).
        Without ``z_nm`` (in either table) the evaluation is 2D: ``axial_tol`` is ignored and the
        z columns of the result are NaN.
    truth : DataFrame, M rows
        Ground-truth emitters with the same columns.
    lateral_tol : float
        Largest lateral distance (nm) of a pair.
    axial_tol : float
        Largest axial distance ``|z_loc - z_truth|`` (nm) of a pair; ``inf`` disables it.

    Returns
    -------
    DataFrame, one row per matched pair, sorted by frame then ``truth_row``
        ``frame``; ``loc_row`` and ``truth_row`` (0-based positional indices into ``locs`` and
        ``truth``); ``x_loc, y_loc, z_loc, x_truth, y_truth, z_truth`` (nm); errors
        ``dx, dy, dz`` = loc - truth (nm); ``dist_lateral`` and ``dist_3d`` (nm; ``dist_3d``
        equals ``dist_lateral`` in 2D).

    Raises
    ------
    ValueError
        A required column is missing (the message names it), coordinates are not finite, or a
        tolerance is negative.
    """
    _check_table(locs, "locs")
    _check_table(truth, "truth")
    lat_tol, ax_tol = _check_tolerances(lateral_tol, axial_tol)
    three_d = _is_3d(locs, truth)
    n_l, n_t = len(locs), len(truth)
    empty = pd.DataFrame({c: pd.Series(dtype=np.float64) for c in _MATCH_COLUMNS})
    empty = empty.astype(
        {"frame": truth["frame"].dtype, "loc_row": np.int64, "truth_row": np.int64}
    )
    if n_l == 0 or n_t == 0:
        return empty
    # Integer frame codes shared by both tables.
    codes, _ = pd.factorize(pd.concat([locs["frame"], truth["frame"]], ignore_index=True))
    loc = _points(locs, codes[:n_l], three_d)
    tru = _points(truth, codes[n_l:], three_d)
    li, ti, cost = _allowed_pairs(loc, tru, lat_tol, ax_tol, three_d)
    if len(li) == 0:
        return empty
    ml, mt = _assign(li, ti, cost, n_l, n_t)
    return _pairs_table(truth["frame"].to_numpy(), loc, tru, ml, mt, three_d)


@dataclass(frozen=True)
class _Points:
    """One table's rows as arrays: positions ``xyz`` (n, 3) in nm (z NaN in a 2D evaluation)
    and the frame code of each row."""

    xyz: NDArray[np.float64]
    code: NDArray[np.intp]

    def tree(self, spacing: float) -> cKDTree:
        """k-d tree of x, y and the frame code times ``spacing``."""
        return cKDTree(
            np.column_stack(
                [self.xyz[:, 0], self.xyz[:, 1], self.code.astype(np.float64) * spacing]
            )
        )


def _points(df: pd.DataFrame, code: NDArray[np.intp], three_d: bool) -> _Points:
    z = df["z_nm"].to_numpy(np.float64) if three_d else np.full(len(df), np.nan)
    x, y = df["x_nm"].to_numpy(np.float64), df["y_nm"].to_numpy(np.float64)
    return _Points(np.column_stack([x, y, z]), code)


def _allowed_pairs(
    loc: _Points, tru: _Points, lat_tol: float, ax_tol: float, three_d: bool
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Every (localization, emitter) pair of the same frame within the tolerances, and its
    distance (3D, or lateral in a 2D evaluation)."""
    # All laterally allowed pairs of all frames at once: the frame code times a spacing larger
    # than the tolerance is a third coordinate, so pairs never cross frames.
    spacing = 2.0 * lat_tol + 1.0
    tree_l, tree_t = loc.tree(spacing), tru.tree(spacing)
    # Slightly generous search radius; the exact inclusive test is applied below.
    radius = lat_tol * (1.0 + 1e-9) + 1e-9
    sdm = tree_l.sparse_distance_matrix(tree_t, max_distance=radius, output_type="ndarray")
    li = sdm["i"].astype(np.intp)
    ti = sdm["j"].astype(np.intp)
    # Recompute exactly (and enforce the inclusive tolerances on the recomputed values).
    same = loc.code[li] == tru.code[ti]
    li, ti = li[same], ti[same]
    dx = loc.xyz[li, 0] - tru.xyz[ti, 0]
    dy = loc.xyz[li, 1] - tru.xyz[ti, 1]
    dlat = np.hypot(dx, dy)
    ok = dlat <= lat_tol
    if three_d:
        dz = loc.xyz[li, 2] - tru.xyz[ti, 2]
        ok &= np.abs(dz) <= ax_tol
        cost = np.sqrt(dlat**2 + dz**2)
    else:
        cost = dlat
    return li[ok], ti[ok], cost[ok]


def _assign(
    li: NDArray[np.intp], ti: NDArray[np.intp], cost: NDArray[np.float64], n_l: int, n_t: int
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The matched localization and emitter rows among the allowed pairs: directly in the
    components of the pair graph with one pair, by the Hungarian algorithm in the others."""
    # Connected components of the bipartite graph (locs are nodes 0..n_l-1, truth n_l..).
    n_nodes = n_l + n_t
    graph = coo_matrix((np.ones(len(li)), (li, n_l + ti)), shape=(n_nodes, n_nodes))
    _, labels = connected_components(graph, directed=False)
    comp = labels[li]
    edges_per_comp = np.bincount(comp, minlength=labels.max() + 1)
    single = edges_per_comp[comp] == 1

    sel_l = [li[single]]
    sel_t = [ti[single]]
    multi = np.flatnonzero(~single)
    if len(multi):
        order = multi[np.argsort(comp[multi], kind="stable")]
        bounds = np.flatnonzero(np.diff(comp[order])) + 1
        for grp in np.split(order, bounds):
            ul, inv_l = np.unique(li[grp], return_inverse=True)
            ut, inv_t = np.unique(ti[grp], return_inverse=True)
            dense = np.full((len(ul), len(ut)), np.inf)
            dense[inv_l, inv_t] = cost[grp]
            r, c = _assign_component(dense)
            sel_l.append(ul[r])
            sel_t.append(ut[c])
    return np.concatenate(sel_l), np.concatenate(sel_t)


def _pairs_table(
    truth_frame: NDArray,
    loc: _Points,
    tru: _Points,
    ml: NDArray[np.intp],
    mt: NDArray[np.intp],
    three_d: bool,
) -> pd.DataFrame:
    """The matched pairs with their errors, sorted by frame then ``truth_row``."""
    out = pd.DataFrame(
        {
            "frame": truth_frame[mt],
            "loc_row": ml.astype(np.int64),
            "truth_row": mt.astype(np.int64),
            "x_loc": loc.xyz[ml, 0],
            "y_loc": loc.xyz[ml, 1],
            "z_loc": loc.xyz[ml, 2],
            "x_truth": tru.xyz[mt, 0],
            "y_truth": tru.xyz[mt, 1],
            "z_truth": tru.xyz[mt, 2],
        }
    )
    out["dx"] = out["x_loc"] - out["x_truth"]
    out["dy"] = out["y_loc"] - out["y_truth"]
    out["dz"] = out["z_loc"] - out["z_truth"]
    out["dist_lateral"] = np.hypot(out["dx"], out["dy"])
    out["dist_3d"] = (
        np.sqrt(out["dist_lateral"] ** 2 + out["dz"] ** 2) if three_d else out["dist_lateral"]
    )
    sort_key = tru.code[mt]
    out = out.iloc[np.lexsort((mt, sort_key))].reset_index(drop=True)
    return out[_MATCH_COLUMNS]


# --------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------
def efficiency(jaccard_percent: float, rmse_nm: float, alpha: float) -> float:
    """SMLM-challenge efficiency ``E = 100 - sqrt((100 - JAC)^2 + alpha^2 RMSE^2)``.

    Parameters
    ----------
    jaccard_percent : float
        Jaccard index in percent (0-100).
    rmse_nm : float
        Root-mean-square error in nm (lateral or axial).
    alpha : float
        Weight in percent per nm: :data:`ALPHA_LATERAL` (1) or :data:`ALPHA_AXIAL` (0.5).

    Returns
    -------
    float
        Efficiency in percent; 100 is perfect; not clipped (it can be negative). NaN when an
        input is NaN.
    """
    jac, rmse, a = float(jaccard_percent), float(rmse_nm), float(alpha)
    if math.isnan(jac) or math.isnan(rmse) or math.isnan(a):
        return math.nan
    return 100.0 - math.sqrt((100.0 - jac) ** 2 + (a * rmse) ** 2)


def _ratio(num: float, den: float) -> float:
    return num / den if den > 0 else math.nan


def _rms(v: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(v**2))) if len(v) else math.nan


def _mean(v: NDArray[np.float64]) -> float:
    return float(np.mean(v)) if len(v) else math.nan


@dataclass(frozen=True)
class Evaluation:
    """SMLM-challenge metrics of one localization table against ground truth.

    Attributes
    ----------
    n_truth, n_locs : int
        Numbers of ground-truth emitters and of localizations.
    tp, fp, fn : int
        True positives (pairs), false positives (unpaired locs), false negatives (unpaired
        emitters).
    jaccard : float
        ``100 * TP / (TP + FP + FN)``, percent (NaN when both tables are empty).
    recall, precision : float
        ``TP / n_truth`` and ``TP / n_locs``, fractions (NaN when the denominator is 0).
    rmse_lateral : float
        ``sqrt(mean(dx^2 + dy^2))`` over pairs, nm.
    rmse_axial : float
        ``sqrt(mean(dz^2))`` over pairs, nm (NaN in 2D).
    rmse_x, rmse_y, rmse_z : float
        Per-axis RMSE over pairs, nm.
    bias_x, bias_y, bias_z : float
        ``mean(loc - truth)`` over pairs, nm.
    efficiency_lateral, efficiency_axial, efficiency_3d : float
        :func:`efficiency` with alpha 1 /nm (lateral), 0.5 /nm (axial) and their mean (NaN in
        2D for the axial and 3D values), percent.
    lateral_tol, axial_tol : float
        Tolerances used, nm.
    three_d : bool
        Whether z was evaluated.
    """

    n_truth: int
    n_locs: int
    tp: int
    fp: int
    fn: int
    jaccard: float
    recall: float
    precision: float
    rmse_lateral: float
    rmse_axial: float
    rmse_x: float
    rmse_y: float
    rmse_z: float
    bias_x: float
    bias_y: float
    bias_z: float
    efficiency_lateral: float
    efficiency_axial: float
    efficiency_3d: float
    lateral_tol: float = 250.0
    axial_tol: float = 500.0
    three_d: bool = True

    def as_dict(self) -> dict[str, float | int | bool]:
        """All fields as a plain ``dict`` (JSON-serialisable; NaN stays NaN)."""
        return asdict(self)

    def summary(self) -> str:
        """A small human-readable table of the metrics."""
        rows: Sequence[tuple[str, str]] = [
            ("ground truth", f"{self.n_truth:d}"),
            ("localizations", f"{self.n_locs:d}"),
            ("TP / FP / FN", f"{self.tp:d} / {self.fp:d} / {self.fn:d}"),
            ("Jaccard (%)", f"{self.jaccard:.2f}"),
            ("recall", f"{self.recall:.4f}"),
            ("precision", f"{self.precision:.4f}"),
            ("RMSE lateral (nm)", f"{self.rmse_lateral:.2f}"),
            ("RMSE axial (nm)", f"{self.rmse_axial:.2f}"),
            ("RMSE x / y / z (nm)", f"{self.rmse_x:.2f} / {self.rmse_y:.2f} / {self.rmse_z:.2f}"),
            (
                "bias x / y / z (nm)",
                f"{self.bias_x:+.2f} / {self.bias_y:+.2f} / {self.bias_z:+.2f}",
            ),
            ("efficiency lateral (%)", f"{self.efficiency_lateral:.2f}"),
            ("efficiency axial (%)", f"{self.efficiency_axial:.2f}"),
            ("efficiency 3D (%)", f"{self.efficiency_3d:.2f}"),
        ]
        mode = "3D" if self.three_d else "2D"
        head = f"Evaluation ({mode}; tolerance lateral {self.lateral_tol:g} nm" + (
            f", axial {self.axial_tol:g} nm)" if self.three_d else ")"
        )
        width = max(len(k) for k, _ in rows)
        lines = [head, "-" * len(head)]
        lines += [f"{k:<{width}}  {v}" for k, v in rows]
        return "\n".join(lines)


def rows_in_frames(table: pd.DataFrame, frames: Sequence[int] | None) -> pd.DataFrame:
    """The rows of ``table`` (a truth or a localization table, with ``frame``) in the frame
    range ``(start, stop)`` (0-based, stop excluded): the range a table was localized over (its
    metadata's ``frames``) or the one ``evaluate --frames`` scores; all rows when ``frames`` is
    None."""
    if frames is None:
        return table
    try:
        start, stop = (int(v) for v in frames)
    except (TypeError, ValueError):
        raise ValueError(f"the table's frame range {frames!r} is not (start, stop)") from None
    f = table["frame"].to_numpy()
    return table[(f >= start) & (f < stop)]


def _near_counts(
    locs: pd.DataFrame, truth: pd.DataFrame, shifts: Sequence[int], tol: float
) -> list[int]:
    """For each frame shift, how many localizations lie within ``tol`` nm (laterally) of a
    truth emitter of their frame, the truth's frames moved by that shift."""
    lxy = locs[["x_nm", "y_nm"]].to_numpy(float)
    txy = truth[["x_nm", "y_nm"]].to_numpy(float)
    ok_l, ok_t = np.isfinite(lxy).all(axis=1), np.isfinite(txy).all(axis=1)
    lf = locs["frame"].to_numpy(float)[ok_l]
    tf = truth["frame"].to_numpy(float)[ok_t]
    # frames as a third axis, far enough apart that only same-frame pairs lie within tol
    sep = 4.0 * tol
    query = np.column_stack([lxy[ok_l], lf * sep])
    out = []
    for shift in shifts:
        tree = cKDTree(np.column_stack([txy[ok_t], (tf + shift) * sep]))
        d, _ = tree.query(query, distance_upper_bound=tol)
        out.append(int(np.isfinite(d).sum()))
    return out


def frame_offset_caution(locs: pd.DataFrame, truth: pd.DataFrame, tol: float) -> str | None:
    """A sentence where the truth's frames seem one off the table's (a 1-based truth file read
    as 0-based, or the reverse): more localizations lie near a truth emitter with the truth
    moved by one frame than as given, by more than three standard deviations of the counts'
    Poisson noise. None otherwise."""
    if len(locs) == 0 or len(truth) == 0:
        return None
    same, earlier, later = _near_counts(locs, truth, (0, -1, 1), tol)
    best, shift = max((earlier, -1), (later, 1))
    if best - same > 3.0 * math.sqrt(best + same):
        return (
            f"{best} localizations lie near a truth emitter with the truth's frames moved by "
            f"{shift:+d} against {same} as given: are the truth's frames "
            f"{'1-based' if shift == -1 else 'numbered from -1'}? sparseloc reads 0-based "
            "frames (the SMLM challenge's and ThunderSTORM's files are recognised)"
        )
    return None


def scoring_cautions(
    locs: pd.DataFrame, truth: pd.DataFrame, lateral_tol: float = 250.0
) -> list[str]:
    """What makes a per-frame score of ``locs`` against ``truth`` misleading, one sentence
    each: a table merged over frames (``filter --merge``), truth that holds none of the
    table's frames or only some of them, or truth whose frames seem one off the table's
    (:func:`frame_offset_caution`, within ``lateral_tol`` nm)."""
    out = []
    if "n_frames" in locs.columns and np.nanmax(locs["n_frames"].to_numpy(), initial=1) > 1:
        out.append(
            "the table was merged over frames (filter --merge): a row stands for several "
            "frames but matches the truth of its first only, so the rest count as missed; "
            "score the table before merging"
        )
    lf, tf = locs["frame"].to_numpy(), truth["frame"].to_numpy()
    if len(lf) and len(tf):
        covered = np.isin(np.unique(lf), np.unique(tf)).mean()
        if covered < 0.5:
            out.append(
                f"the truth holds frames {int(tf.min())}-{int(tf.max())} but the table's rows "
                f"lie in frames {int(lf.min())}-{int(lf.max())} ({covered:.0%} of the table's "
                "frames have truth): is it the truth of this movie?"
            )
        else:
            beyond = np.unique(tf[(tf < lf.min()) | (tf > lf.max())])
            if beyond.size > np.unique(tf).size // 2:
                out.append(
                    f"the table's rows lie in frames {int(lf.min())}-{int(lf.max())} but the "
                    f"truth holds frames {int(tf.min())}-{int(tf.max())}, whose emitters "
                    "elsewhere count as missed: a table of part of the movie (localize "
                    "--frames) is scored with evaluate --frames START:STOP"
                )
    offset = frame_offset_caution(locs, truth, lateral_tol)
    if offset:
        out.append(offset)
    return out


#: Below this recall and this precision together, a score more likely compares the table with
#: another movie's truth (or in the wrong units) than measures the localization.
WRONG_TRUTH_FRACTION: float = 0.5


def result_cautions(result: Evaluation) -> list[str]:
    """What a score itself says is likely wrong with the comparison: fewer than
    :data:`WRONG_TRUTH_FRACTION` of the localizations match and as few of the truth is found
    (another movie's truth, a wrong ``--pixel-size`` for truth in pixels, shifted
    coordinates, or a wrong PSF or camera)."""
    if result.n_locs == 0 or result.n_truth == 0:
        return []
    if result.recall < WRONG_TRUTH_FRACTION and result.precision < WRONG_TRUTH_FRACTION:
        return [
            f"only {result.precision:.0%} of the localizations match the truth and "
            f"{result.recall:.0%} of the truth is found: is it the truth of this movie (and "
            "the right --pixel-size for truth in pixels)? A wrong PSF or camera setting also "
            "scores this low"
        ]
    return []


def evaluate(
    locs: pd.DataFrame,
    truth: pd.DataFrame,
    *,
    lateral_tol: float = 250.0,
    axial_tol: float = 500.0,
    all_flags: bool = False,
) -> Evaluation:
    """Match ``locs`` to ``truth`` (:func:`match_localizations`) and compute challenge metrics.

    Parameters
    ----------
    locs, truth : DataFrame
        Columns ``frame``, ``x_nm``, ``y_nm`` and optionally ``z_nm`` (nm). Without ``z_nm`` in
        either table the evaluation is 2D and the axial metrics are NaN. Rows of ``locs`` whose
        ``flag`` is not "ok" are left out unless ``all_flags``
        (:func:`sparseloc.postprocess.flagged_rows`, the rule every consumer follows); NaN
        coordinates are refused rather than dropped, so that no row is scored silently.
    lateral_tol, axial_tol : float
        Matching tolerances in nm (inclusive).
    all_flags : bool
        Score flagged rows too.

    Returns
    -------
    Evaluation
        Counts, Jaccard (percent), recall and precision (fractions), RMSE and bias (nm),
        efficiencies (percent).
    """
    from .postprocess import flagged_rows

    if isinstance(locs, pd.DataFrame):
        flagged = flagged_rows(locs, all_flags=all_flags)
        if flagged.any():
            locs = locs.loc[~flagged].reset_index(drop=True)
    matches = match_localizations(locs, truth, lateral_tol=lateral_tol, axial_tol=axial_tol)
    three_d = _is_3d(locs, truth)
    n_t, n_l, tp = len(truth), len(locs), len(matches)
    fp, fn = n_l - tp, n_t - tp
    jac = _ratio(100.0 * tp, tp + fp + fn)
    dx = matches["dx"].to_numpy(np.float64)
    dy = matches["dy"].to_numpy(np.float64)
    dz = matches["dz"].to_numpy(np.float64)
    rmse_lat = float(np.sqrt(np.mean(dx**2 + dy**2))) if tp else math.nan
    rmse_ax = _rms(dz) if three_d else math.nan
    e_lat = efficiency(jac, rmse_lat, ALPHA_LATERAL)
    e_ax = efficiency(jac, rmse_ax, ALPHA_AXIAL)
    return Evaluation(
        n_truth=n_t,
        n_locs=n_l,
        tp=tp,
        fp=fp,
        fn=fn,
        jaccard=jac,
        recall=_ratio(tp, n_t),
        precision=_ratio(tp, n_l),
        rmse_lateral=rmse_lat,
        rmse_axial=rmse_ax,
        rmse_x=_rms(dx),
        rmse_y=_rms(dy),
        rmse_z=rmse_ax,
        bias_x=_mean(dx),
        bias_y=_mean(dy),
        bias_z=_mean(dz) if three_d else math.nan,
        efficiency_lateral=e_lat,
        efficiency_axial=e_ax,
        efficiency_3d=0.5 * (e_lat + e_ax),
        lateral_tol=float(lateral_tol),
        axial_tol=float(axial_tol),
        three_d=three_d,
    )
