"""Drift from fiducials: tracks of spots present in most frames (beads), averaged.

Fiducials are found as tracks, so that they are followed even when the drift carries them
further than ``radius_nm``. The movie is cut into windows of ``smooth_frames`` frames (at
least 5), in which the drift is much smaller than ``radius_nm``. In each window, spots are
groups of localizations within ``radius_nm / 2`` (tight, so that a stretch of labelled
structure rarely qualifies) present in at least ``0.75 x min_fraction`` of the window's
frames (lenient: the strict test follows). Spots of windows up to 5 apart and within
``radius_nm / 2`` of each other are linked into tracks (nearest pairs first, one spot per
track and window). Every frame then takes, per track, the localization nearest to the
track's interpolated position, within ``radius_nm``. A track is a fiducial when it has such
a localization in at least ``min_fraction`` of all frames and is point-like: its robust
scatter about its own running median is below ``radius_nm / 5`` per axis (a patch of
blinking molecules scatters over the whole radius); localizations more than 4 scatters
from that running median (a neighbouring molecule in a frame that misses the fiducial) are
dropped. Any spot that passes is fixed to the sample, so at very high duty cycles a small
group of quasi-permanently emitting molecules can serve as a (noisier) fiducial too.

The drift of a frame is the mean over the fiducials present of (position - that fiducial's
median position); frames without any fiducial are interpolated linearly; the curve is then
smoothed by a running median (robust to a wrong match) followed by a running mean (which
removes the median's steps), both over ``smooth_frames`` frames (past the movie's ends the
curve continues at the rate of its last ``smooth_frames`` frames), and referenced to zero
at the first frame. :mod:`sparseloc.drift` re-exports :func:`fiducial_drift`.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.ndimage import median_filter, uniform_filter1d
from scipy.spatial import cKDTree

from .drift_common import DriftResult, positive, read_locs

__all__ = ["fiducial_drift"]

# Messages keep the logger of sparseloc.drift, where fiducial_drift has always logged.
log = logging.getLogger("sparseloc.drift")


def fiducial_drift(
    locs: pd.DataFrame,
    *,
    radius_nm: float = 150.0,
    min_fraction: float = 0.8,
    smooth_frames: int = 25,
    all_flags: bool = False,
    log_warnings: bool = True,
) -> DriftResult:
    """Drift from fiducials: spots present in at least ``min_fraction`` of the frames.

    The method is described in the module docstring: spots found in windows of
    ``smooth_frames`` frames are linked into tracks, the point-like tracks present in enough
    frames are the fiducials, and their mean deviation from their median positions, smoothed
    over ``smooth_frames`` frames, is the drift.

    Parameters
    ----------
    locs : DataFrame
        Table with at least ``frame, x_nm, y_nm`` (``z_nm`` optional; nm). Rows with a flag
        other than "ok" are ignored unless ``all_flags``
        (:func:`sparseloc.postprocess.select_usable`).
    radius_nm : float
        Grouping radius (nm): larger than the localization scatter of a fiducial, smaller than
        the distance between fiducials.
    min_fraction : float
        Fraction of the frames (0..1] a fiducial must be found in.
    smooth_frames : int
        Length of the running filters and of the detection windows (frames).
    all_flags : bool
        Use flagged rows too.
    log_warnings : bool
        Log each of the result's ``warnings`` (False: the caller shows them itself).

    Returns
    -------
    DriftResult
        ``method="fiducial"``, with ``fiducials`` (median positions) and ``raw_drift``.
        ``reliable`` is False when the fiducials disagree with each other by more than
        ``radius_nm / 5`` RMS after smoothing, or fewer than ``min_fraction`` of the frames
        contain any fiducial; a single fiducial only adds a warning.

    Raises
    ------
    ValueError
        For bad parameters or input, or when no fiducial is found (the message lists how many
        frames the best candidates were present in).
    """
    radius_nm, smooth_frames = _check_params(radius_nm, min_fraction, smooth_frames)
    data = read_locs(locs, all_flags=all_flags)
    f0, f1 = int(data.frame.min()), int(data.frame.max())
    fi = data.frame - f0
    order = np.argsort(fi, kind="stable")
    search = _Search(
        fi[order], data.xyz[order], f1 - f0 + 1, radius_nm, min_fraction, smooth_frames
    )
    fid_pos, n_tracks = search.fiducials()
    medians, dev, have, raw, smooth = _combine(fid_pos, smooth_frames)
    ref = smooth[0].copy()  # drift is defined up to a constant: zero at the first frame
    warnings, reliable, spread = _check_fiducials(dev, smooth, have, search)
    for w in warnings if log_warnings else ():
        log.warning("fiducial_drift: %s", w)
    return DriftResult(
        frames=np.arange(f0, f1 + 1),
        drift=smooth - ref,
        method="fiducial",
        reliable=reliable,
        warnings=warnings,
        fiducials=medians,
        raw_drift=raw - ref,
        details={
            "fiducials": len(fid_pos),
            "frames_present": [int(np.isfinite(p[:, 0]).sum()) for p in fid_pos],
            "frames_covered": int(have.sum()),
            "tracks": n_tracks,
            "disagreement_nm": spread,
            "radius_nm": radius_nm,
            "min_fraction": min_fraction,
            "smooth_frames": smooth_frames,
            "z_estimated": data.has_z,
        },
    )


def _check_params(radius_nm: float, min_fraction: float, smooth_frames: int) -> tuple[float, int]:
    """``radius_nm`` and ``smooth_frames`` checked and converted; ``min_fraction`` checked."""
    radius_nm = positive("radius_nm", radius_nm)
    if not (math.isfinite(min_fraction) and 0 < min_fraction <= 1):
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction!r}")
    if int(smooth_frames) != smooth_frames or smooth_frames < 1:
        raise ValueError(f"smooth_frames must be a positive integer, got {smooth_frames!r}")
    return radius_nm, int(smooth_frames)


class _Search:
    """One search for fiducials among localizations ``xyz`` (N, 3; nm) sorted by their frame
    ``fi`` (counted from the table's first frame), over ``n_frames`` frames."""

    def __init__(
        self,
        fi: NDArray,
        xyz: NDArray,
        n_frames: int,
        radius_nm: float,
        min_fraction: float,
        smooth_frames: int,
    ) -> None:
        self.fi, self.xyz, self.xy = fi, xyz, xyz[:, :2]
        self.n_frames = n_frames
        self.radius_nm = radius_nm
        self.min_fraction = min_fraction
        self.smooth_frames = smooth_frames
        self.win_len = min(max(smooth_frames, 5), n_frames)
        self.n_win = -(-n_frames // self.win_len)
        self.need_frames = math.ceil(min_fraction * n_frames)

    def spots(self) -> tuple[NDArray, NDArray, NDArray]:
        """Spots of every window: centres (K, 2) nm, windows (K,) and frames present (K,)."""
        fi, xy, win_len, n_frames = self.fi, self.xy, self.win_len, self.n_frames
        bounds = np.searchsorted(fi, np.arange(self.n_win + 1) * win_len)
        spot_xy, spot_win, spot_n = [], [], []
        for w in range(self.n_win):
            a, b = bounds[w], bounds[w + 1]
            if b - a == 0:
                continue
            frames_in_win = min(win_len, n_frames - w * win_len)
            need = max(2, math.ceil(0.75 * self.min_fraction * frames_in_win))
            for centre, n_present in _window_spots(xy[a:b], fi[a:b], 0.5 * self.radius_nm, need):
                spot_xy.append(centre)
                spot_win.append(w)
                spot_n.append(n_present)
        if not spot_xy:
            raise ValueError(
                f"no fiducial found: no group of localizations within {self.radius_nm:g} nm "
                f"is present in {0.75 * self.min_fraction:.0%} of the frames "
                f"of any {win_len}-frame window ({xy.shape[0]} localizations in {n_frames} frames)"
            )
        return np.asarray(spot_xy), np.asarray(spot_win), np.asarray(spot_n)

    def positions(self, wins: NDArray, centres: NDArray) -> NDArray:
        """Position (F, 3) in every frame of the localization nearest to a track seen in
        windows ``wins`` at ``centres`` (nm), within ``radius_nm``; NaN where there is none."""
        fi, xy = self.fi, self.xy
        all_frames = np.arange(self.n_frames, dtype=np.float64)
        win_centre = (np.arange(self.n_win) + 0.5) * self.win_len - 0.5
        px = np.interp(all_frames, win_centre[wins], centres[:, 0])
        py = np.interp(all_frames, win_centre[wins], centres[:, 1])
        dist = np.hypot(xy[:, 0] - px[fi], xy[:, 1] - py[fi])
        near = np.nonzero(dist <= self.radius_nm)[0]
        near = near[np.lexsort((dist[near], fi[near]))]
        first = near[np.unique(fi[near], return_index=True)[1]]  # nearest one per frame
        pos = np.full((self.n_frames, 3), np.nan)
        pos[fi[first]] = self.xyz[first]
        return pos

    def fiducials(self) -> tuple[list[NDArray], int]:
        """Positions (F, 3) of every track that is a fiducial, and the number of tracks tried."""
        spot_xy, spot_win, spot_n = self.spots()
        tracks = _link_spots(spot_xy, spot_win, 0.5 * self.radius_nm, gap=5)
        min_windows = 0.5 * self.min_fraction * self.n_win
        max_scatter = self.radius_nm / 5
        candidates: list[tuple[int, float]] = []  # (frames present, scatter nm) of each track
        fid_pos: list[NDArray] = []
        for track in tracks:
            wins = spot_win[track]
            if wins.size < min_windows:
                # seen in too few windows to be present in min_fraction of the frames; its
                # spots' frame counts stand in for its presence in the error message
                candidates.append((int(spot_n[track].sum()), math.nan))
                continue
            pos = self.positions(wins, spot_xy[track])
            scatter, outlier = _track_scatter(pos[:, :2], self.smooth_frames)
            pos[outlier] = np.nan  # e.g. a nearby molecule in a frame that misses the fiducial
            present = int(np.isfinite(pos[:, 0]).sum())
            candidates.append((present, scatter))
            if present >= self.need_frames and scatter < max_scatter:
                fid_pos.append(pos)
        if not fid_pos:
            raise self.not_found(candidates, max_scatter)
        return fid_pos, len(candidates)

    def not_found(self, candidates: list[tuple[int, float]], max_scatter: float) -> ValueError:
        """The error when no track qualifies, listing the five best candidates."""
        best = sorted(candidates, reverse=True)[:5]
        listed = (
            ", ".join(
                f"{n} frames" + (f" (scatter {sc:.0f} nm)" if math.isfinite(sc) else "")
                for n, sc in best
            )
            or "none"
        )
        return ValueError(
            f"no fiducial found: a fiducial must be present in >= {self.need_frames} of the "
            f"{self.n_frames} frames ({self.min_fraction:.0%}) with a scatter below "
            f"{max_scatter:.0f} nm (a fifth of the search radius); the best candidates: {listed}"
        )


def _combine(
    fid_pos: list[NDArray], smooth_frames: int
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """Median position (K, 3) of each fiducial, deviations from it (K, F, 3), the frames with
    a fiducial (F,), and the mean deviation per frame (F, 3) raw and smoothed."""
    pos_all = np.stack(fid_pos)  # (K, F, 3); z is 0 for 2D tables
    medians = np.nanmedian(pos_all, axis=1)  # (K, 3)
    dev = pos_all - medians[:, None, :]
    count = np.sum(np.isfinite(dev[..., 0]), axis=0)
    have = count > 0
    raw = np.full((pos_all.shape[1], 3), np.nan)
    raw[have] = np.nansum(dev[:, have], axis=0) / count[have, None]
    smooth = _smooth(_fill_gaps(raw), smooth_frames)
    return medians, dev, have, raw, smooth


def _check_fiducials(
    dev: NDArray, smooth: NDArray, have: NDArray, search: _Search
) -> tuple[list[str], bool, float]:
    """Warnings, reliability and the fiducials' RMS disagreement (nm; NaN for one fiducial)."""
    warnings: list[str] = []
    reliable = True
    n_fid = dev.shape[0]
    spread = math.nan
    if n_fid == 1:
        warnings.append("a single fiducial: its drift cannot be cross-checked against another")
    else:
        # each fiducial's own smoothed lateral track against the combined one
        own = np.stack([_smooth(_fill_gaps(d[:, :2]), search.smooth_frames) for d in dev])
        spread = float(np.sqrt(np.mean((own - smooth[None, :, :2]) ** 2)))
        if spread > search.radius_nm / 5:
            warnings.append(
                f"the {n_fid} fiducials disagree by {spread:.0f} nm RMS (> radius_nm / 5 = "
                f"{search.radius_nm / 5:.0f} nm): some may not be fixed to the sample"
            )
            reliable = False
    covered = int(have.sum())
    if covered < search.need_frames:
        warnings.append(
            f"only {covered} of {search.n_frames} frames contain a fiducial; the rest are "
            "interpolated"
        )
        reliable = False
    return warnings, reliable, spread


def _window_spots(
    xy: NDArray, frame: NDArray, radius: float, need: int
) -> list[tuple[NDArray, int]]:
    """Groups of localizations within ``radius`` present in >= ``need`` frames: (median
    position, frames present) of each, seeded greedily from the most crowded localization."""
    tree = cKDTree(xy)
    counts = tree.query_ball_point(xy, radius, return_length=True)
    used = np.zeros(len(xy), dtype=bool)
    spots = []
    for i in np.argsort(-counts, kind="stable"):
        if counts[i] < need:
            break  # sorted: no later seed has enough neighbours
        if used[i]:
            continue
        nb = np.asarray(tree.query_ball_point(xy[i], radius), dtype=np.int64)
        nb = nb[~used[nb]]
        n_present = np.unique(frame[nb]).size
        if n_present >= need:
            spots.append((np.median(xy[nb], axis=0), n_present))
            used[nb] = True
    return spots


def _link_spots(centre: NDArray, win: NDArray, max_step: float, gap: int) -> list[NDArray]:
    """Tracks through the windows: each spot joins the nearest track (within ``max_step``, last
    seen at most ``gap`` windows earlier; nearest pairs first) or starts a new one. Returns the
    spot indices of every track, one spot per window, in window order."""
    tracks: list[list[int]] = []
    for w in np.unique(win):
        cur = np.nonzero(win == w)[0]
        active = [t for t, members in enumerate(tracks) if w - win[members[-1]] <= gap]
        taken_t: set[int] = set()
        taken_s: set[int] = set()
        if active:
            last = centre[[tracks[t][-1] for t in active]]
            dist = np.hypot(*(last[:, None, :] - centre[cur][None, :, :]).transpose(2, 0, 1))
            for flat in np.argsort(dist, axis=None):
                a, b = np.unravel_index(flat, dist.shape)
                if dist[a, b] > max_step:
                    break  # sorted: every later pair is further apart
                if a in taken_t or b in taken_s:
                    continue
                taken_t.add(a)
                taken_s.add(b)
                tracks[active[a]].append(int(cur[b]))
        tracks.extend([int(cur[b])] for b in range(cur.size) if b not in taken_s)
    return [np.asarray(members, dtype=np.int64) for members in tracks]


def _track_scatter(pos: NDArray, smooth_frames: int) -> tuple[float, NDArray[np.bool_]]:
    """Robust scatter (nm, worst axis) of a track's positions (F, 2) about their running
    median, and which frames lie more than 4 scatters (at least 10 nm) from it."""
    ok = np.isfinite(pos[:, 0])
    outlier = np.zeros(pos.shape[0], dtype=bool)
    if ok.sum() < 3:
        return math.inf, outlier
    p = pos[ok]
    size = min(max(smooth_frames, 3), p.shape[0])
    resid = p - median_filter(p, size=(size, 1), mode="mirror")
    resid -= np.median(resid, axis=0)
    per_axis = 1.4826 * np.median(np.abs(resid), axis=0)
    outlier[ok] = np.any(np.abs(resid) > np.maximum(4 * per_axis, 10.0), axis=1)
    return float(np.max(per_axis)), outlier


def _fill_gaps(values: NDArray) -> NDArray:
    """Rows (frames) of ``values`` (F, D) that are NaN, linearly interpolated from the others
    (held constant beyond the first / last finite row)."""
    ok = np.isfinite(values[:, 0])
    t = np.arange(values.shape[0], dtype=np.float64)
    return np.stack([np.interp(t, t[ok], values[ok, k]) for k in range(values.shape[1])], axis=1)


def _smooth(values: NDArray, size: int) -> NDArray:
    """Running median then running mean over ``size`` frames along axis 0, the series
    continued past each end by its point reflection about the line fitted to its ``size``
    frames there: a drift that goes on at a steady rate keeps it to the last frame (a plain
    mirror would flatten it there by about the rate times ``size / 4``)."""
    n = values.shape[0]
    size = min(size, n)
    if size <= 1:
        return values.copy()
    pad = size
    ext = np.vstack(
        [
            _reflected(values[:size], pad, at_start=True),
            values,
            _reflected(values[n - size :], pad, at_start=False),
        ]
    )
    out = median_filter(ext, size=(size, 1), mode="nearest")
    out = uniform_filter1d(out, size, axis=0, mode="nearest")
    return out[pad : pad + n]


def _reflected(end: NDArray, pad: int, at_start: bool) -> NDArray:
    """``pad`` rows continuing the rows ``end`` (the series' first or last ones) past that
    end: each row reflected through the point of the least-squares line of ``end`` at the
    end's frame."""
    m = end.shape[0]
    t = np.arange(m, dtype=np.float64)
    edge = 0.0 if at_start else m - 1.0
    pivot = np.array([np.polyval(np.polyfit(t, end[:, k], 1), edge) for k in range(end.shape[1])])
    # the frames at distance 1 .. pad from the end, mirrored (repeating the series if short)
    idx = np.arange(1, pad + 1) % (2 * m - 2) if m > 1 else np.zeros(pad, int)
    idx = np.where(idx < m, idx, 2 * m - 2 - idx)
    if at_start:
        return (2 * pivot - end[idx])[::-1]
    return 2 * pivot - end[m - 1 - idx]
