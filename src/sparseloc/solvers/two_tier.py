"""Two tiers of the frame solver: single fits where emitters are alone, the frame solver where
they crowd.

Most of a movie's emitters have no neighbour whose image overlaps theirs; the frame solver's
pursuit, count-selection trials and relocations buy nothing there. A frame is solved in
tiers:

1. **Detection**: the frame is correlated with the PSF's images at a few z planes
   (:func:`detection_planes`); local maxima above ``min_snr`` times the camera model's noise,
   times the planes' worst match to the pursuit's templates (:func:`detection_match`, so the
   detection misses nothing the pursuit would find), are candidates
   (:func:`~sparseloc.detect.detect_candidates`), strongest first.
2. **Units**: each candidate where the frame, less the light of the units fitted before it,
   still holds a detection (:func:`~sparseloc.detect.snr_at`; the others are parts of
   images already explained) is fitted as one emitter in its window with that light known,
   started at the z plane whose image explains most of its light (:func:`z_starts`), with
   the frame solver's z flips; the frame solver's removal test
   (:func:`~sparseloc.solvers.refine.weakest_removed`) drops a unit too weak to keep. Units
   whose windows see another unit's light are then
   refitted in turn with their neighbours' latest light (at most :data:`REFIT_SWEEPS`
   sweeps, skipped where the frame solver's rule says the fit would stay: that light
   changed by little, or its linear response moves the emitter by less than a nm).
3. **Unexplained light**: the frame less the units' light is searched again (the detection
   test, its variance with the units' shot noise and the model's error). A peak there
   farther than a crowd distance from every unit (:func:`_alone`) is an emitter the
   detection could not separate from a brighter neighbour's correlation, or noise: it is
   tried as a unit, kept only above the count selection's addition threshold (as the frame
   solver's additions are), and the units that see it are refitted. Where a unit near the
   new ones is then doubtful (below), the round is undone and the crowds solve that light,
   as they solve the peaks the addition test drops. At most :data:`UNIT_ROUNDS` rounds.
4. **Promotion**: a unit goes to the crowds when its fit is flagged, when its window's
   chi-square lies :data:`PROMOTE_MISFIT` standard deviations above expectation
   (:func:`misfit`, with the variance rule of :mod:`~sparseloc.solvers.variance`), when it
   lies within a core radius of another unit (:func:`crowd_distance`: the frame solver fits
   those together), or when the frame less the units' light holds a significant peak near
   it (the detection test again, its variance with the units' shot noise and the model's
   error). The peaks step 3 leaves elsewhere are crowds too.
5. **Crowds**: the frame solver (fits with count selection, z flips, relocations) with the
   kept units' light known: a pair starts from its own starts, a larger crowd from the
   frame solver's pursuit on a crop around it (:func:`crowd_boxes`). Units that see the
   crowds' light are refitted with it.

Under the ``auto`` schedule (``whole_when_crowded``) a frame is solved whole instead, by the
frame solver's pursuit, fits and extra starts, where after the promotion the crowds hold
more starts than the kept units hold emitters in a frame dense enough that most emitters'
images would overlap another's (:func:`overlapping`): two tiers only pay where most
emitters are alone, and the whole-frame solver finds more where many images overlap. A
crowd of more than :data:`SMALL_CROWD` starts, or one the crowds' fits grow beyond that, is
solved by the whole-frame solver (``whole``: pursuit, fits and extra starts) on a crop
around it with the kept units' light known: how much of a frame that solver sees follows
the crowd, not the frame's size.

The fits, the z flips and the crowds' count selection are the frame solver's own
(:func:`~sparseloc.solvers.mle.fit_emitters`, :func:`~sparseloc.solvers.frame.frame_fit`).
Measurements: ``docs/benchmarks/two_tier.txt``, ``docs/benchmarks/auto_schedule.txt``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ..detect import detect_candidates, snr_at
from ..psf.base import PSFModel
from .emitters import Emitters
from .frame import (
    SHIFT_CAP,
    SHIFT_TOLERANCE,
    SINGLE_THRESHOLD,
    SKIP_TOLERANCE,
    FrameFit,
    _Memo,
    _response,
    _try_z_flips,
    _unmoved,
    add_threshold,
    frame_fit,
)
from .frame_compose import shifted, subset
from .frame_mp import FrameTemplates
from .frame_windows import NeighbourLight, inside, window_box, window_data, window_kwargs
from .mle import fit_emitters
from .mp import MIN_PHOTONS
from .refine import error_variance, weakest_removed
from .variance import PIXEL_MAPS, cropped_maps, misfit, model_error_of, read_variance_crop

log = logging.getLogger(__name__)

__all__ = [
    "PROMOTE_MISFIT",
    "TierCounts",
    "crowd_boxes",
    "crowd_distance",
    "crowded",
    "detection_match",
    "detection_planes",
    "misfit",
    "overlapping",
    "solve_two_tier",
    "z_starts",
]


#: A single is promoted to the crowds when its window's chi-square lies more than this many
#: standard deviations above its expectation. A false promotion costs only time (the crowd
#: solver then fits it), a missed one costs an emitter: the bar is low (1-3 % of single fits
#: of isolated simulated emitters pass it, see docs/benchmarks/two_tier.txt).
PROMOTE_MISFIT = 2.0


#: Most sweeps over the units that see other units' light, each refitting them in turn with
#: their neighbours' latest light; fewer when a sweep leaves every unit in place.
REFIT_SWEEPS = 2


#: Rounds of unexplained peaks tried as units before the rest go to the crowds.
UNIT_ROUNDS = 2

#: An unexplained peak within this many pixels of one tried as a unit in an earlier round
#: is the same peak (the units' refits move it by a pixel at most): it is not tried again.
TRIED_DISTANCE = 1.5


def _settled(before: NDArray, after: NDArray, xy_tol: float = 2.0, z_tol: float = 5.0) -> bool:
    """Whether a refit left a unit's emitter in place (nm tolerances, as the frame solver's)."""
    if np.shape(after) != np.shape(before):
        return False
    d = np.abs(np.asarray(after) - np.asarray(before))
    return bool(np.all(d[:, :2] < xy_tol) and np.all(d[:, 2] < z_tol))


@dataclass
class TierCounts:
    """How many candidates each tier handled (summed over frames by the caller)."""

    singles: int = 0
    promoted: int = 0
    crowded: int = 0
    frames_with_crowds: int = 0
    frames_whole: int = 0


def crowd_distance(templates: FrameTemplates) -> float:
    """Candidates closer than this (pixels) form a cluster: the radius holding half the light
    of the broadest plane, the distance within which the frame solver fits emitters
    together (their images overlap enough to trade light)."""
    return max(2.0, templates.core_radius)


def _centred(templates: FrameTemplates) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The templates of the phase nearest the pixel centre: images (Z, T, T) and z (Z,)."""
    j = int(np.argmin(np.hypot(templates.dx, templates.dy)))
    sel = np.flatnonzero((templates.dx == templates.dx[j]) & (templates.dy == templates.dy[j]))
    return templates.images[sel], templates.z[sel]


#: Detection planes are kept so that every plane's image correlates at least this well with a
#: kept one: the signal-to-noise lost to a z between the planes is then a few per cent.
PLANE_CORRELATION = 0.9


def detection_planes(templates: FrameTemplates) -> NDArray[np.float64]:
    """The centred templates (P, T, T) the detection correlates with: from the first z plane
    on, each next one whose normalised correlation with the last kept falls below
    :data:`PLANE_CORRELATION` (a fast-changing PSF, such as a double helix, keeps more)."""
    imgs, _ = _centred(templates)
    unit = imgs / np.linalg.norm(imgs.reshape(len(imgs), -1), axis=1)[:, None, None]
    keep = [0]
    for j in range(1, len(unit)):
        if float(np.sum(unit[j] * unit[keep[-1]])) < PLANE_CORRELATION:
            keep.append(j - 1 if j - 1 > keep[-1] else j)
    if keep[-1] != len(unit) - 1:
        keep.append(len(unit) - 1)
    return imgs[sorted(set(keep))]


def detection_match(templates: FrameTemplates, planes: NDArray) -> float:
    """The worst match of the detection planes to the pursuit's templates: the smallest, over
    the templates (every phase and plane), of the best normalised correlation with a
    detection plane at a whole-pixel shift of up to one pixel. A detection threshold of
    ``min_snr`` times this finds every emitter the pursuit's ``min_snr`` would (the
    detection's correlation falls by at most this factor)."""
    d = planes.reshape(len(planes), -1)
    d = d / np.linalg.norm(d, axis=1)[:, None]
    t = (
        templates.images
        / np.linalg.norm(templates.images.reshape(len(templates.images), -1), axis=1)[:, None, None]
    )
    best = np.zeros(len(t))
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            shifted = np.roll(t, (dy, dx), axis=(1, 2)).reshape(len(t), -1)
            best = np.maximum(best, (shifted @ d.T).max(axis=1))
    return float(np.clip(best.min(), 0.0, 1.0))


def z_starts(
    frame: NDArray, background: NDArray, rc: NDArray, templates: FrameTemplates
) -> NDArray[np.float64]:
    """Starting x, y, z (nm) and photons (K, 4) of candidates at pixels ``rc`` (K, 2).

    x and y are the candidate pixel's centre; z is the plane whose centred template explains
    most of the light around the candidate (largest ``<d, t>^2 / <t, t>``, ``d`` the frame
    less the background), and the photons are that plane's least-squares amplitude.
    """
    imgs, zs = _centred(templates)
    if len(rc) == 0:
        return np.zeros((0, 4))
    t = imgs.shape[-1]
    h = t // 2
    d = np.pad(np.asarray(frame, float) - background, h)
    r = rc[:, 0].astype(int)
    c = rc[:, 1].astype(int)
    rows = r[:, None] + np.arange(t)[None, :]
    cols = c[:, None] + np.arange(t)[None, :]
    patches = d[rows[:, :, None], cols[:, None, :]].reshape(len(rc), -1)
    tt = imgs.reshape(len(zs), -1)
    proj = patches @ tt.T  # (K, Z)
    norm = np.einsum("zp,zp->z", tt, tt)
    best = np.argmax(np.where(proj > 0, proj**2 / norm, -np.inf), axis=1)
    px = templates.pixel_size
    photons = np.maximum(proj[np.arange(len(rc)), best] / norm[best], 1.0)
    return np.column_stack([(c + 0.5) * px, (r + 0.5) * px, zs[best], photons])


def _clusters(rc: NDArray, distance: float) -> list[list[int]]:
    """Candidates (K, 2 pixels) linked by distances below ``distance``, each list in the
    candidates' order (strongest first)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(rc)
    if n == 0:
        return []
    pairs = cKDTree(rc).query_pairs(distance, output_type="ndarray")
    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    out: dict[int, list[int]] = {}
    for i, lab in enumerate(labels):
        out.setdefault(int(lab), []).append(i)
    return sorted(out.values(), key=lambda c: c[0])


class _Unit:
    """One tier-1 fit: its window, emitters (K, 4) and the numbers the table needs."""

    __slots__ = ("background", "box", "flags", "gof", "memo", "misfit", "rows", "sigma")

    def __init__(self, box, rows, sigma, background, gof, flags, misfit, memo):
        self.box, self.rows, self.sigma = box, rows, sigma
        self.background, self.gof, self.flags = background, gof, flags
        self.misfit = misfit  # the window's chi-square excess, in its standard deviations
        self.memo = memo  # the known light it was fitted with and the frame solver's skip rule

    def doubtful(self) -> bool:
        """Whether one of its fits is flagged or the window's misfit is significant."""
        bad = any(fl not in ("ok", "not_converged") for fl in self.flags)
        return bad or self.misfit > PROMOTE_MISFIT


class _Tier1:
    """The frame, its noise and the fitting options of one frame's tier-1 fits."""

    def __init__(self, f, bg, model, opts, noise_factor, rv, z_flip, fixed=None):
        self.f, self.bg, self.model, self.opts = f, bg, model, opts
        self.light = NeighbourLight(model, f.shape, opts["pixel_size"], fixed)
        self.px, self.pad = opts["pixel_size"], int(opts["pad"])
        keys = ("noise", "qe", "plane", *PIXEL_MAPS)
        kw = {k: opts[k] for k in keys if k in opts}
        if kw.get("read_variance") is None:
            kw.pop("read_variance", None)
        self.fit_kwargs = kw
        self.noise = (noise_factor, model_error_of(model), rv)
        self.z_flip = z_flip
        self.lr = add_threshold(opts.get("lr_threshold"), kw.get("qe", 1.0))

    def box(self, rows: NDArray) -> tuple[int, int, int, int]:
        return window_box(rows, *self.f.shape, self.px, self.pad)

    def refit(self, unit: _Unit, others) -> _Unit:
        """``unit`` fitted again with the light of emitters ``others`` known; the unit as it
        is while the frame solver's rule (:func:`~sparseloc.solvers.frame._unmoved`: that
        light changed by little, or its linear response moves the emitter by less than
        :data:`~sparseloc.solvers.frame.SHIFT_TOLERANCE`) says the fit would stay."""
        box = self.box(unit.rows)
        offset = _light(self.light, list(others), box)
        origin = (box[2] * self.px, box[0] * self.px)
        if box == unit.box and _unmoved(unit.memo, offset, origin, SHIFT_TOLERANCE):
            return unit
        return self.fit(unit.rows, offset=offset)

    def fit(
        self, start: NDArray, others=(), offset: NDArray | None = None, added: bool = False
    ) -> _Unit:
        """Fit emitters ``start`` (K, 4) in their window with the light of emitters ``others``
        (arrays (M, 4)) known, or ``offset`` (photons/pixel over the window), and the frame
        solver's z flips near the ends of the z range. The fit is kept where the count
        selection's removal test keeps it: with the bar of an emitter alone in its group, or
        with the bar of an addition where ``added`` (a start proposed by the light that
        fitted emitters leave unexplained, as the count selection's additions are)."""
        box = self.box(start)
        if offset is None:
            offset = _light(self.light, list(others), box)
        r0, r1, c0, c1 = box
        f, model = self.f, self.model
        y = window_data(f, box, self.fit_kwargs)
        background = float(max(np.median(self.bg[r0:r1, c0:c1]), 1e-3))
        kw = window_kwargs(f, box, self.px, offset, background, self.fit_kwargs)
        fit = fit_emitters(y, model, Emitters.from_array(start), **kw)
        if self.z_flip:
            fit = _try_z_flips(y, model, fit, kw, self.z_flip, None)
        # the frame solver's count selection would remove an emitter this weak
        single = None if added else SINGLE_THRESHOLD
        fewer = weakest_removed(y, model, fit, kw, self.lr, MIN_PHOTONS, single)
        if fewer is not None:
            fit = fewer
        nf, _, rv = self.noise
        rv = rv[r0:r1, c0:c1] if np.ndim(rv) else rv
        rows = fit.emitters.as_array().reshape(-1, 4)
        bad = misfit(y, fit.model_image, error_variance(fit, model, kw), nf, rv, kw.get("censored"))
        bg = float(fit.background[0])
        sd = np.sqrt(max(kw["background"], 1.0))
        # as the frame solver's memo: the linear response is computed when first needed
        resp = [lambda: _response(model, y, fit, kw)]
        memo = _Memo(offset, SKIP_TOLERANCE * sd, rows, [], kw["origin"], resp, SHIFT_CAP * sd)
        return _Unit(box, rows, fit.sigma, bg, fit.deviance_per_dof, fit.flags, bad, memo)


def _light(light: NeighbourLight, rows: list[NDArray], box) -> NDArray[np.float64]:
    rows = [r for r in rows if len(r)]
    if not rows:
        return light.known(box)
    return light.window(np.vstack(rows), box)


def solve_two_tier(
    frame: NDArray,
    background: NDArray,
    model: PSFModel,
    templates: FrameTemplates,
    *,
    pursuit,
    fit_options: dict,
    min_snr: float,
    noise_factor: float,
    read_variance: float | NDArray = 0.0,
    z_flip: float = 0.15,
    counts: TierCounts | None = None,
    cache: dict | None = None,
    whole_when_crowded: bool = False,
    whole=None,
    fixed_light: NDArray | None = None,
) -> FrameFit | None:
    """Solve one frame in two tiers (see the module notes).

    Parameters
    ----------
    frame, background : ndarray, shape (rows, cols)
        The frame and its background (photons).
    model : PSFModel
        The continuous PSF model.
    templates : FrameTemplates
        The pursuit's templates (their centred phase gives the detection's planes, see
        :func:`detection_planes`, and the z starts).
    pursuit : callable
        ``pursuit(image, background, read_variance) -> Emitters``: the frame solver's start
        on a crop of the frame (read variance a scalar or the crop's map).
    fit_options : dict
        Keywords of :func:`frame_fit` but the frame's own (``pixel_size``, ``pad``, ``reach``,
        ``group_distance``, noise keywords, ...).
    min_snr : float
        Detection threshold (standard deviations), also of the promotion test.
    noise_factor : float
        The camera's variance per expected photon.
    read_variance : float or ndarray
        Read-noise variance (photons^2) per pixel.
    z_flip : float
        As in :func:`frame_fit`.
    counts : TierCounts, optional
        Incremented with this frame's counts.
    cache : dict, optional
        Kept between frames: the detection's planes and their spectra.
    whole_when_crowded : bool
        Return None where the crowds hold more starts than the kept units hold emitters in
        a frame where most images overlap, and, without ``whole``, where a crowd holds more
        than :data:`SMALL_CROWD` starts or its fit more than that many emitters: the caller
        then solves the frame whole (its pursuit and extra starts find more where images
        overlap than the crowds' fits).
    whole : callable, optional
        ``whole(image, background, fixed_light, read_variance, background_shape, censored)
        -> FrameFit``: the whole-frame solver on a crop (with the crop's background shape and
        censored pixels, or None). Where given, a crowd of more than :data:`SMALL_CROWD`
        starts is solved by it on a crop around the crowd, with the kept units' light known,
        instead of sending the frame whole (the frame's size then does not decide how much
        of it the whole-frame solver sees).
    fixed_light : ndarray, shape (rows, cols), optional
        Light known besides the emitters' (photons/pixel): in every window's known light and
        under every detection.

    Returns
    -------
    FrameFit or None
    """
    f = np.asarray(frame, dtype=np.float64)
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    opts = dict(fit_options)
    px, reach = opts["pixel_size"], float(opts["reach"])
    rv = np.broadcast_to(np.asarray(read_variance, dtype=np.float64), f.shape)
    det = dict(noise_factor=noise_factor, threshold=min_snr)
    tier = _Tier1(f, bg, model, opts, noise_factor, rv, z_flip, fixed_light)
    light = tier.light
    seen = bg if fixed_light is None else bg + fixed_light
    crowd = crowd_distance(templates)
    if cache is None:
        cache = {}
    if cache.get("templates") is not templates:
        planes = detection_planes(templates)
        match = detection_match(templates, planes)
        cache.update(templates=templates, planes=planes, match=match, spectra={})
    planes, spectra = cache["planes"], cache["spectra"]
    # candidates as sensitive as the pursuit's; the count selection's removal test decides
    det["threshold"] = min_snr * cache["match"]

    # 1. candidates, strongest first
    cand = detect_candidates(f, seen, planes, read_variance=rv, cache=spectra, **det)
    starts = z_starts(f, seen, cand, templates) if len(cand) else np.zeros((0, 4))

    # 2. units: each candidate that the units before it leave significant is fitted as one
    # emitter with their light known (the others are parts of their images), then each unit
    # once more with all the others' light
    units: list[_Unit] = []

    def rows_of(skip: int | None = None) -> list[NDArray]:
        """The emitters of every unit but ``skip``."""
        return [u.rows for k, u in enumerate(units) if k != skip]

    _add_units(tier, planes, cand, starts, units, det["threshold"])
    _refit_sweeps(tier, units, px, reach)

    # 3. unexplained light: peaks alone are tried as units (see the module notes)
    tried = np.zeros((0, 2))
    for round_ in range(UNIT_ROUNDS + 1):
        units[:] = [u for u in units if len(u.rows)]
        resid, s_light = _unexplained(tier, planes, rows_of(), spectra, det)
        alone = _alone(resid, units, px, crowd, reach / px, tried)
        if round_ == UNIT_ROUNDS or not alone.any():
            break
        new = z_starts(f, bg + s_light, resid[alone], templates)
        n_before = len(units)
        kept = _units_from_peaks(tier, planes, resid[alone], new, units, det["threshold"])
        if not kept or len(units) == n_before:
            break  # the units as before the round: the same residual, those peaks the crowds'
        tried = np.vstack([tried, resid[alone]])

    # 4. promotion: units that one emitter does not explain, units closer than a crowd
    # distance to another (the frame solver fits those together), and significant light
    # that the units leave unexplained go to the crowds
    close = _close_units(units, px, crowd)
    near_resid = _near(units, resid, px, crowd)
    promoted = [k for k, u in enumerate(units) if u.doubtful() or near_resid[k] or close[k]]
    crowd_pts = np.vstack([resid, *(_unit_points([units[k]], px) for k in promoted)])
    kept = [k for k in range(len(units)) if k not in set(promoted)]
    n_kept = sum(len(units[k].rows) for k in kept)
    start = np.vstack([*(units[k].rows for k in promoted), z_starts(f, seen, resid, templates)])
    if whole_when_crowded and crowded(start, n_kept, px, reach, f.shape, large=whole is None):
        return _whole(counts)

    # 5. crowds: the frame solver with the units' light known; then units that see the
    # crowds' light once more with it
    crowd_fit = None
    if len(crowd_pts):
        known = [units[k].rows for k in kept]
        crowd_fit, crowd_em, grown = _solve_crowds(
            f, bg, model, start, known, light, pursuit, opts, crowd, rv, whole
        )
        # the count selection may have grown a small crowd into a large one
        if whole_when_crowded and grown:
            return _whole(counts)
        if len(crowd_em) and kept:
            tree = cKDTree(crowd_em[:, :2])
            for k in kept:
                if any(tree.query_ball_point(r[:2], reach + tier.pad * px) for r in units[k].rows):
                    # the promoted units' emitters are the crowds' now (in crowd_em)
                    others = [units[j].rows for j in kept if j != k]
                    units[k] = tier.refit(units[k], [*others, crowd_em])
    if counts is not None:
        counts.singles += n_kept
        counts.promoted += len(promoted)
        counts.crowded += len(crowd_pts)
        counts.frames_with_crowds += int(len(crowd_pts) > 0)
    return _merge([units[k] for k in kept], crowd_fit, f.shape, px)


def crowded(
    start: NDArray,
    n_kept: int,
    px: float,
    reach: float,
    shape: tuple[int, int] | None = None,
    large: bool = True,
) -> bool:
    """Whether the ``auto`` schedule solves a frame whole: its crowds' starts ``start``
    (K, 4; nm, photons) outnumber the ``n_kept`` emitters of the kept units in a frame
    (``shape``, pixels) whose emitters mostly overlap another's image (:func:`overlapping`),
    or, where ``large``, one crowd (starts linked within ``reach`` nm, half a template's
    width) holds more than :data:`SMALL_CROWD` of them (without ``large`` the caller
    solves such a crowd on a crop of the frame)."""
    many = len(start) > n_kept
    if many and shape is not None:
        many = overlapping(len(start) + n_kept, shape, px, reach) > 0.5
    return many or (large and _large_crowd(start, px, reach))


def overlapping(n: int, shape: tuple[int, int], px: float, reach: float) -> float:
    """The fraction of ``n`` emitters spread at random over a frame that have another within
    ``reach`` (the centre of one inside the other's image): ``1 - exp(-rho pi reach^2)``.

    Parameters
    ----------
    n : int
        Emitters in the frame.
    shape : (int, int)
        The frame's shape (pixels).
    px : float
        Pixel size (nm).
    reach : float
        Half a template's width (nm).

    Returns
    -------
    float
        A fraction in [0, 1).
    """
    area = shape[0] * shape[1] * px * px
    return float(1.0 - np.exp(-max(n - 1, 0) / area * np.pi * reach * reach))


def _whole(counts: TierCounts | None) -> None:
    """The frame is left to the whole-frame solver (counted in ``counts``)."""
    if counts is not None:
        counts.frames_whole += 1
    return None


def _add_units(
    tier: _Tier1, planes, cand: NDArray, starts: NDArray, units: list, threshold, added=False
):
    """Fit each candidate (pixels ``cand`` (K, 2), starts (K, 4)) in turn as one emitter with
    the light of ``units`` known, where the frame less that light still holds a detection
    there (the others are parts of images already explained); append the fits the count
    selection keeps to ``units`` (with the addition's bar where ``added``, see
    :meth:`_Tier1.fit`)."""
    e = tier.noise[1]
    for i in range(len(cand)):
        known = [u.rows for u in units]
        if units and not _significant(tier, planes, cand[i], known, e, threshold):
            continue
        unit = tier.fit(starts[i][None], known, added=added)
        if len(unit.rows):
            units.append(unit)


def _refit_sweeps(tier: _Tier1, units: list, px: float, reach: float) -> None:
    """Refit, in place, the units whose windows see another unit's light, each in turn with
    its neighbours' latest light, for at most :data:`REFIT_SWEEPS` sweeps (fewer when a sweep
    leaves every unit in place)."""
    near = _neighbours_in_reach(units, px, reach)
    for _ in range(REFIT_SWEEPS):
        moved = 0
        for k in near:
            before = units[k].rows
            if len(before):
                units[k] = tier.refit(units[k], [u.rows for j, u in enumerate(units) if j != k])
                moved += not _settled(before, units[k].rows)
        if not moved:
            break


def _unexplained(
    tier: _Tier1, planes, known: list, spectra: dict, det: dict
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Detections (K, 2 pixels) in the frame less the light of emitters ``known``, its
    variance with their shot noise and the model's error; and that light (rows, cols)."""
    f, bg = tier.f, tier.bg
    _, e, rv = tier.noise
    s_light = _light(tier.light, known, (0, f.shape[0], 0, f.shape[1]))
    var = rv + (e * s_light) ** 2 if e > 0 else rv
    resid = detect_candidates(f, bg + s_light, planes, read_variance=var, cache=spectra, **det)
    return resid, s_light


def _alone(
    pts: NDArray, units: list, px: float, crowd: float, reach: float, tried: NDArray
) -> NDArray:
    """Whether each unexplained peak (K, 2 pixels, strongest first) is tried as a unit: it
    was not tried before (none of ``tried`` within :data:`TRIED_DISTANCE` pixels), it lies
    farther than ``crowd`` pixels from every unit's emitter, and no stronger peak within
    ``reach`` pixels (half a template's width) goes to the crowds (the peaks of a crowd's
    residual, a double helix's lobes among them, are the crowd's)."""
    out = ~np.asarray(_near_points(pts, units, px, crowd), dtype=bool)
    if len(tried) and len(pts):
        out &= cKDTree(tried).query(pts)[0] > TRIED_DISTANCE
    if len(pts) > 1:
        tree = cKDTree(pts)
        for i in range(len(pts)):
            if out[i] and any(j < i and not out[j] for j in tree.query_ball_point(pts[i], reach)):
                out[i] = False
    return out


def _units_from_peaks(tier: _Tier1, planes, pts: NDArray, starts: NDArray, units: list,
                      threshold: float) -> bool:  # fmt: skip
    """Try unexplained peaks (pixels ``pts`` (K, 2), starts (K, 4)) as units, and refit the
    units that see their light; keep the result (True) unless a unit within reach of a new
    one is then doubtful (:meth:`_Unit.doubtful`): one emitter each does not explain that
    light (a wrong fit between two emitters leaves peaks around it), and ``units`` is put
    back as it was (False) for the crowds to solve."""
    before = list(units)
    _add_units(tier, planes, pts, starts, units, threshold, added=True)
    added = units[len(before) :]
    if not added:
        return True  # the addition test dropped every peak; the crowds fit them
    px, reach = tier.px, float(tier.opts["reach"])
    _refit_sweeps(tier, units, px, reach)
    new_xy = [u.rows[:, :2] for u in units[len(before) :] if len(u.rows)]
    if new_xy:
        tree = cKDTree(np.vstack(new_xy))
        for u in units:
            if u.doubtful() and any(tree.query_ball_point(r[:2], reach) for r in u.rows):
                units[:] = before
                return False
    return True


def _near_points(pts: NDArray, units: list, px: float, distance: float) -> list[bool]:
    """Whether each point (K, 2 pixels) lies within ``distance`` (pixels) of a unit's
    emitter."""
    up = _unit_points(units, px)
    if len(pts) == 0 or len(up) == 0:
        return [False] * len(pts)
    return list(cKDTree(up).query(pts)[0] < distance)


def _significant(tier: _Tier1, planes, rc, known: list, e: float, min_snr: float) -> bool:
    """Whether the frame less the light of emitters ``known`` still holds a detection at
    pixel ``rc`` (the detection test, its variance with their shot noise and model error)."""
    f, bg = tier.f, tier.bg
    h = planes.shape[-1] // 2 + 1
    r, c = int(rc[0]), int(rc[1])
    box = (max(r - h, 0), min(r + h + 1, f.shape[0]), max(c - h, 0), min(c + h + 1, f.shape[1]))
    r0, r1, c0, c1 = box
    lit = _light(tier.light, known, box)
    nf, _, rv = tier.noise
    rvw = rv[r0:r1, c0:c1] if np.ndim(rv) else rv
    noise = nf * np.maximum(bg[r0:r1, c0:c1] + lit, 1e-3) + rvw + (e * lit) ** 2
    d = f[r0:r1, c0:c1] - bg[r0:r1, c0:c1] - lit
    return bool(snr_at(d, noise, planes, np.array([[r - r0, c - c0]]))[0] > min_snr)


def _close_units(units: list[_Unit], px: float, distance: float) -> list[bool]:
    """Whether each unit's emitter lies closer than ``distance`` (pixels) to another's."""
    out = [False] * len(units)
    if len(units) > 1:
        pts = _unit_points(units, px)
        for i, j in cKDTree(pts).query_pairs(distance):
            out[i] = out[j] = True
    return out


def _unit_points(units: list[_Unit], px: float) -> NDArray:
    """Pixel (row, col) of every unit's emitters, (K, 2)."""
    rows = [u.rows for u in units if len(u.rows)]
    if not rows:
        return np.zeros((0, 2))
    r = np.vstack(rows)
    return np.column_stack([r[:, 1] / px - 0.5, r[:, 0] / px - 0.5])


def _near(units: list[_Unit], pts: NDArray, px: float, distance: float) -> list[bool]:
    """Whether each unit has an emitter within ``distance`` (pixels) of one of ``pts``."""
    if len(pts) == 0:
        return [False] * len(units)
    tree = cKDTree(pts)
    return [
        bool(len(u.rows)) and bool(np.any(tree.query(_unit_points([u], px))[0] < distance))
        for u in units
    ]


def _others(rows: list[NDArray], i: int) -> list[NDArray]:
    return [r for k, r in enumerate(rows) if k != i]


def _neighbours_in_reach(units: list[_Unit], px: float, reach: float) -> list[int]:
    """Units whose window holds pixels within ``reach`` (nm) of another unit's emitter."""
    if len(units) < 2:
        return []
    xy = np.vstack([u.rows[:, :2] for u in units])
    owner = np.concatenate([np.full(len(u.rows), k) for k, u in enumerate(units)])
    tree = cKDTree(xy)
    out = []
    for k, u in enumerate(units):
        r0, r1, c0, c1 = u.box
        centre = ((c0 + c1) / 2 * px, (r0 + r1) / 2 * px)
        half = 0.5 * max(r1 - r0, c1 - c0) * px
        if np.any(owner[tree.query_ball_point(centre, reach + half)] != k):
            out.append(k)
    return out


#: Crops of the crowds are whole multiples of this many pixels a side (few shapes, so the
#: pursuit's correlators are built once per shape and reused).
CROP_STEP = 32


def crowd_boxes(
    pts: NDArray, margin: int, shape: tuple[int, int], join: int = 0
) -> list[tuple[int, int, int, int]]:
    """Boxes (r0, r1, c0, c1) around groups of crowd points (K, 2 pixels): each point with
    ``margin`` pixels around it; boxes closer than ``join`` pixels are merged (so a crop sees
    the light of the crowd next to it), and each is grown to a multiple of
    :data:`CROP_STEP` pixels a side inside the frame."""
    rows, cols = shape
    boxes = [
        [int(r) - margin, int(r) + margin + 1, int(c) - margin, int(c) + margin + 1] for r, c in pts
    ]
    merged = True
    while merged:
        merged = False
        out: list[list[int]] = []
        for b in boxes:
            for o in out:
                if (
                    b[0] < o[1] + join
                    and o[0] < b[1] + join
                    and b[2] < o[3] + join
                    and o[2] < b[3] + join
                ):
                    o[:] = [min(o[0], b[0]), max(o[1], b[1]), min(o[2], b[2]), max(o[3], b[3])]
                    merged = True
                    break
            else:
                out.append(list(b))
        boxes = out
    return [_snapped(b, rows, cols) for b in boxes]


def _snapped(b, rows: int, cols: int) -> tuple[int, int, int, int]:
    """Box ``b`` grown to a multiple of :data:`CROP_STEP` a side, shifted inside the frame."""
    out = []
    for lo, hi, n in ((b[0], b[1], rows), (b[2], b[3], cols)):
        size = min(int(np.ceil((hi - lo) / CROP_STEP)) * CROP_STEP, n)
        start = int(np.clip((lo + hi) // 2 - size // 2, 0, n - size))
        out += [start, start + size]
    return tuple(out)


#: A crowd of at most this many starts (promoted units and unexplained peaks closer than half
#: a template's width) is fitted from them, the count selection deciding how many stay; a
#: larger one from the pursuit on a crop (docs/benchmarks/two_tier.txt: 3 kept every dense
#: table's Jaccard, 4 cost 0.6 points on double helices at 1 /um^2).
SMALL_CROWD = 3


def _crowd_groups(start: NDArray, px: float, reach: float) -> tuple[NDArray, list[list[int]]]:
    """The crowds' starts (K, 4 nm) as pixels (K, 2) and their clusters: starts closer than
    half a template's width (``reach``, nm) to another."""
    pts = np.column_stack([start[:, 1] / px - 0.5, start[:, 0] / px - 0.5])
    return pts, _clusters(pts, int(np.ceil(reach / px)))


def _large_crowd(start: NDArray, px: float, reach: float) -> bool:
    """Whether a crowd of more than :data:`SMALL_CROWD` starts is among ``start`` (K, 4)."""
    return any(len(g) > SMALL_CROWD for g in _crowd_groups(start, px, reach)[1])


def _solve_crowds(f, bg, model, start, known_rows, light, pursuit, opts, crowd, rv, whole=None):
    """The frame solver on the crowds, with the units' light known: a small crowd
    (:data:`SMALL_CROWD`) from its starts ``start`` (K, 4), a larger one on a crop around it
    (:func:`_pursuit_crop`: the whole-frame solver ``whole`` where given, else the
    pursuit's start and the fits). Returns the FrameFit (frame coordinates), its emitters
    (K, 4) and whether the small crowds' fit grew a crowd of more than :data:`SMALL_CROWD`."""
    px = opts["pixel_size"]
    pts, groups = _crowd_groups(start, px, opts["reach"])
    big = [i for g in groups if len(g) > SMALL_CROWD for i in g]
    small = [i for g in groups if len(g) <= SMALL_CROWD for i in g]
    fits = []
    if big and (pursuit is not None or whole is not None):
        fits += _pursuit_crop(
            f, bg, model, pts[big], known_rows, light, pursuit, opts, crowd, rv, whole
        )
    else:
        small += big
    grown = False
    if small:
        done = [ft.emitters.as_array().reshape(-1, 4) for ft in fits]
        fixed = _light(light, [*known_rows, *done], (0, f.shape[0], 0, f.shape[1]))
        em = Emitters.from_array(start[sorted(small)])
        fit = frame_fit(f, model, em, background=bg, fixed_light=fixed, **opts)
        grown = _large_crowd(fit.emitters.as_array().reshape(-1, 4), px, opts["reach"])
        if grown and whole is not None:
            # a crowd the count selection grew large: its crop solved as a large crowd's
            fits += _regrown(f, bg, model, fit, [*known_rows, *done], light, opts, crowd, rv, whole)
            grown = False
        else:
            fits.append(fit)
    if not fits:
        return None, np.zeros((0, 4)), False
    fit = _concat(fits)
    return fit, fit.emitters.as_array().reshape(-1, 4), grown


def _concat(fits: list[FrameFit]) -> FrameFit:
    """The FrameFits one after the other, their groups numbered on."""
    groups = np.cumsum([0] + [int(ft.group.max()) + 1 if len(ft.group) else 0 for ft in fits])
    return FrameFit(
        emitters=Emitters.from_array(
            np.vstack([ft.emitters.as_array().reshape(-1, 4) for ft in fits])
        ),
        sigma=np.vstack([ft.sigma for ft in fits]),
        background=np.concatenate([ft.background for ft in fits]),
        gof=np.concatenate([ft.gof for ft in fits]),
        flags=np.concatenate([ft.flags for ft in fits]),
        group=np.concatenate([ft.group + g for ft, g in zip(fits, groups, strict=False)]),
    )


def _regrown(f, bg, model, fit, known_rows, light, opts, crowd, rv, whole) -> list[FrameFit]:
    """The small crowds' ``fit`` where it grew a crowd of more than :data:`SMALL_CROWD`:
    that crowd's crops solved by ``whole`` (:func:`_pursuit_crop`), with the light of the
    small crowds' emitters outside them known, and those emitters."""
    px = opts["pixel_size"]
    em = fit.emitters.as_array().reshape(-1, 4)
    pts, groups = _crowd_groups(em, px, opts["reach"])
    large = [i for g in groups if len(g) > SMALL_CROWD for i in g]
    out = np.zeros(len(em), dtype=bool)
    for box in _crop_boxes(pts[large], opts, f.shape):
        out |= inside(em, box, px)
    rest = subset(fit, ~out)
    crops = _pursuit_crop(
        f, bg, model, pts[large], [*known_rows, em[~out]], light, None, opts, crowd, rv, whole
    )
    return [rest, *crops]


def _crop_boxes(pts: NDArray, opts: dict, shape: tuple[int, int]) -> list[tuple]:
    """The crops of :func:`_pursuit_crop` around crowd points ``pts`` (K, 2 pixels)."""
    h = int(np.ceil(opts["reach"] / opts["pixel_size"]))
    return crowd_boxes(pts, h + 1, shape, join=2 * h)


def _pursuit_crop(f, bg, model, pts, known_rows, light, pursuit, opts, crowd, rv, whole=None):
    """The frame solver on crops around crowds (points ``pts``, pixels) with the units' light
    known; FrameFits in frame coordinates.

    Each crop holds its crowd with half a template's width around it, so the pursuit sees
    every image whole, and crowds whose images could reach each other share a crop. Where
    ``whole`` is given it solves each crop (the whole-frame solver: pursuit, fits, second
    start); else the fits start from the pursuit's emitters, those farther than a crowd
    distance and a pad from the crowd's points left out (the units explain them)."""
    px, pad = opts["pixel_size"], int(opts["pad"])
    fits = []
    for r0, r1, c0, c1 in _crop_boxes(pts, opts, f.shape):
        win = (slice(r0, r1), slice(c0, c1))
        fixed = _light(light, known_rows, (r0, r1, c0, c1))
        maps = {k: opts[k] for k in PIXEL_MAPS if k in opts}
        maps = cropped_maps(maps, f.shape, (r0, r1, c0, c1))
        if whole is not None:
            m = {k: maps.get(k) for k in PIXEL_MAPS}
            fit = whole(f[win], bg[win], fixed, m["read_variance"], m["background_shape"],
                        m["censored"])  # fmt: skip
            fits.append(shifted(fit, c0 * px, r0 * px))
            continue
        sub_rv = read_variance_crop(rv, f.shape, (r0, r1, c0, c1))
        start = pursuit(f[win], bg[win] + fixed, sub_rv).as_array().reshape(-1, 4)
        if len(start):
            at = np.column_stack([start[:, 1] / px - 0.5 + r0, start[:, 0] / px - 0.5 + c0])
            d, _ = cKDTree(pts).query(at)
            start = start[d < crowd + pad]
        if len(start) == 0:
            continue
        sub_opts = {**opts, **maps}
        fit = frame_fit(
            f[win], model, Emitters.from_array(start), background=bg[win], fixed_light=fixed,
            **sub_opts,
        )  # fmt: skip
        fits.append(shifted(fit, c0 * px, r0 * px))
    return fits


def _merge(units: list[_Unit], crowd_fit: FrameFit | None, shape, px) -> FrameFit:
    """One FrameFit of the units (one group each) and the crowds' fit, inside the frame."""
    rows, cols = shape
    em = np.vstack([u.rows for u in units]) if units else np.zeros((0, 4))
    parts = FrameFit(
        emitters=Emitters.from_array(em),
        sigma=np.vstack([u.sigma for u in units]) if units else np.zeros((0, 4)),
        background=np.concatenate([np.full(len(u.rows), u.background) for u in units] or [[]]),
        gof=np.concatenate([np.full(len(u.rows), u.gof) for u in units] or [[]]),
        flags=np.concatenate([u.flags for u in units] or [[]]).astype("<U16"),
        group=np.concatenate([np.full(len(u.rows), k) for k, u in enumerate(units)] or [[]]),
    )
    if crowd_fit is not None and len(crowd_fit.emitters):
        n = len(units)
        parts = FrameFit(
            emitters=Emitters.from_array(np.vstack([em, crowd_fit.emitters.as_array()])),
            sigma=np.vstack([parts.sigma, crowd_fit.sigma]),
            background=np.concatenate([parts.background, crowd_fit.background]),
            gof=np.concatenate([parts.gof, crowd_fit.gof]),
            flags=np.concatenate([parts.flags, crowd_fit.flags]),
            group=np.concatenate([parts.group, crowd_fit.group + n]),
        )
    e = parts.emitters.as_array().reshape(-1, 4)
    inside = (e[:, 0] >= 0) & (e[:, 0] < cols * px) & (e[:, 1] >= 0) & (e[:, 1] < rows * px)
    return FrameFit(
        emitters=Emitters.from_array(e[inside]),
        sigma=parts.sigma[inside],
        background=parts.background[inside].astype(np.float64),
        gof=parts.gof[inside].astype(np.float64),
        flags=parts.flags[inside],
        group=parts.group[inside].astype(np.int64),
    )
