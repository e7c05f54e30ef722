"""Whole-frame solver: greedy pursuit over the frame, then maximum-likelihood fits by groups.

Fixed windows see only part of the scene: an engineered PSF spreads a molecule's light over
tens of pixels, so a window holds pieces of its neighbours' images that its dictionary cannot
explain, and the solver answers them with ghost emitters at its edges. Here the whole frame is
one model:

1. **Pursuit** (:func:`~sparseloc.solvers.frame_mp.frame_pursuit`): matching pursuit over
   the frame with a dictionary of shifted templates; its emitters start the fits.
2. **Fit** (:func:`frame_fit`): emitters closer than ``group_distance`` form a group; each group
   gets a window around it and a maximum-likelihood fit with count selection
   (:func:`~sparseloc.solvers.refine.fit_with_count_selection`) in which the light of all other
   emitters of the frame is a known offset (:class:`~sparseloc.solvers.frame_windows.
   NeighbourLight`). Groups are visited again and again (Gauss-Seidel), each time with the
   neighbours' latest fitted images, until a sweep leaves every emitter in place (at most 10
   sweeps): each sweep lets a group see its neighbours' corrected light. Emitters near an end
   of the z range are also tried from the other end (z flips).
3. **Relocation** (:func:`~sparseloc.solvers.relocate.relocation_pass`): after the first
   sweeps (at most :data:`RELOCATE_AFTER`, or fewer when they settle), each emitter in turn is
   replaced by the best PSF position of what its neighbours leave unexplained, kept where the
   likelihood rises, because the sweeps only go downhill and the pursuit's greedy starts leave
   emitters in local optima in a crowd. Then the sweeps go on.

The measurements behind these choices are in ``docs/benchmarks/code_notes_frame.md``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..psf.base import PSFModel
from .emitters import Emitters
from .frame_mp import FrameTemplates, frame_pursuit, frame_templates, tiled_pursuit
from .frame_windows import (
    MAX_GROUP,
    NeighbourLight,
    emitter_groups,
    inside,
    lost_flip_near,
    near_window,
    window_box,
    window_data,
)
from .mle import LikelihoodProblem, check_qe, fit_emitters
from .mp import MIN_PHOTONS
from .refine import LR_THRESHOLD, fit_with_count_selection
from .relocate import RELOCATE, RELOCATE_AFTER, relocation_pass
from .variance import cropped_maps

log = logging.getLogger(__name__)

__all__ = [
    "ADD_THRESHOLD",
    "SINGLE_THRESHOLD",
    "FrameFit",
    "FrameTemplates",
    "add_threshold",
    "frame_fit",
    "frame_pursuit",
    "frame_templates",
    "tiled_pursuit",
]


#: Likelihood-ratio threshold of the count selection in a frame. The chi-square argument of
#: :data:`~sparseloc.solvers.refine.LR_THRESHOLD` (18.47) holds for an exact model; here each
#: group's model includes its neighbours' fitted images, and a calibrated PSF is not exact, so
#: structured residuals read as one more emitter; 80 is an empirical value on the
#: photon-counting scale (measurements in ``docs/benchmarks/code_notes_frame.md``).
ADD_THRESHOLD = 80.0

#: Removal threshold of an emitter alone in its group: the chi-square 0.1 % tail
#: (:data:`~sparseloc.solvers.refine.LR_THRESHOLD`, on the likelihood's scale). Its start
#: already passed a significance test over the frame (the pursuit's or the L1
#: deconvolution's), and no overlapping fit
#: lends it misplaced light, so the test is one against the noise (and the model error's
#: allowance); at high background it keeps emitters whose ratio lies between this and
#: :data:`ADD_THRESHOLD` (``docs/benchmarks/single_threshold.txt``).
SINGLE_THRESHOLD = LR_THRESHOLD


def add_threshold(lr_threshold: float | None, qe: float = 1.0) -> float:
    """The count selection's likelihood-ratio threshold in a frame on the likelihood's scale:
    ``lr_threshold`` (default :data:`ADD_THRESHOLD`, on the photon-counting scale) times
    ``qe``."""
    return (ADD_THRESHOLD if lr_threshold is None else float(lr_threshold)) * check_qe(qe)


@dataclass
class FrameFit:
    """The emitters of one frame after :func:`frame_fit`, with per-emitter fit results.

    Attributes
    ----------
    emitters : Emitters
    sigma : ndarray, shape (K, 4)
        CRLB standard errors of x, y, z (nm) and photons.
    background : ndarray, shape (K,)
        Fitted background of each emitter's group (photons/pixel).
    gof : ndarray, shape (K,)
        Deviance per degree of freedom of each emitter's group window.
    flags : ndarray of str, shape (K,)
    group : ndarray of int, shape (K,)
        Group index (one window per group).
    """

    emitters: Emitters
    sigma: NDArray[np.float64]
    background: NDArray[np.float64]
    gof: NDArray[np.float64]
    flags: NDArray[np.str_]
    group: NDArray[np.int64]


def _near_ends(arr: NDArray, z_range: tuple[float, float], fraction: float) -> list[int]:
    """Indices of the emitters (K, 4) within ``fraction`` of the z range from either end."""
    lo, hi = z_range
    return [
        k for k in range(len(arr)) if min(arr[k, 2] - lo, hi - arr[k, 2]) <= fraction * (hi - lo)
    ]


def _flipped(row: NDArray, z_range: tuple[float, float]) -> NDArray:
    """A copy of one emitter (4,) started from the other end of the z range."""
    lo, hi = z_range
    alt = row.copy()
    alt[2] = np.clip(alt[2] - (hi - lo) if alt[2] > (lo + hi) / 2 else alt[2] + (hi - lo), lo, hi)
    return alt


def _try_z_flips(y, model, fit, kw, fraction, failed: list | None = None):
    """Refit from the other end of the z range each emitter near an end; keep what fits best.

    Each trial fits the one emitter with the rest of the group held fixed (cheap); if any
    trial beats the group's likelihood, the group is refitted jointly from the flipped start
    and kept if its likelihood is higher. ``failed`` (x, y, z of emitters whose trial lost)
    is consulted and extended: an emitter near one of them is not tried again (the later
    sweeps of a frame move emitters by a few nm; 1 in 70 trials wins, nearly all in the
    first sweep).
    """
    arr = fit.emitters.as_array().reshape(-1, 4).copy()
    near = _near_ends(arr, model.z_range, fraction)
    if not near:
        return fit
    base = kw.get("offset")
    base = 0.0 if base is None else base
    px, origin = kw["pixel_size"], kw["origin"]
    flipped = False
    for k in near:
        if lost_flip_near(failed, arr[k]):
            continue
        others = np.delete(arr, k, axis=0)
        off = base + (model.render(*others.T, y.shape, px, origin=origin) if len(others) else 0.0)
        alt = _flipped(arr[k], model.z_range)
        one = fit_emitters(
            y,
            model,
            Emitters.from_array(alt[None]),
            **{**kw, "offset": off, "background": float(fit.background[0])},
        )
        if one.log_likelihood > fit.log_likelihood and len(one.emitters) == 1:
            arr[k] = one.emitters.as_array()[0]
            flipped = True
        elif failed is not None:
            failed.append(arr[k, :3].copy())
    if not flipped:
        return fit
    trial = fit_emitters(y, model, Emitters.from_array(arr), **kw)
    if trial.log_likelihood > fit.log_likelihood and len(trial.emitters) == len(arr):
        trial.history = [*fit.history, "z flip"]
        return trial
    return fit


#: Default ``skip_tolerance`` of :func:`frame_fit`: a fit is kept, not redone, while the known
#: light in its window changes by at most this many background standard deviations per pixel.
SKIP_TOLERANCE = 0.1
#: Largest change of the neighbours' light (background standard deviations per pixel) for
#: which the linear response decides whether a group must be refitted (see ``frame_fit``).
SHIFT_CAP = 1.0
#: Default ``shift_tolerance`` of :func:`frame_fit` (nm).
SHIFT_TOLERANCE = 1.0


def _response(model: PSFModel, y: NDArray, fit, kw: dict) -> NDArray[np.float64] | None:
    """Rows x, y, z of ``-F^-1 J' diag(w/mu)`` at a group's fit, shape (3 K, pixels).

    At the optimum the gradient of ``-log L`` is zero; a small change ``d`` of the known
    offset (photons/pixel) moves the optimum by about ``-F^-1 J' (w d / mu)`` (nm): more known
    light on one side pushes the emitters away from it. ``J``, ``F``, the weight ``w`` and
    ``mu`` (with the sCMOS read variance) are the fit's own
    (:class:`~sparseloc.solvers.mle.LikelihoodProblem`). None if ``F`` is singular.
    """
    prob = LikelihoodProblem(
        y,
        model,
        kw["pixel_size"],
        kw["origin"],
        kw.get("noise", "poisson"),
        kw.get("read_variance"),
        kw.get("plane", False),
        1.0,
        kw.get("offset"),
        kw.get("qe", 1.0),
        fit.background_shape,
        censored=kw.get("censored"),
    )
    theta = np.concatenate([fit.emitters.as_array().ravel(), fit.background])
    jac = prob.jacobian(theta)
    wj = prob.weight * jac * prob.keep.ravel() / (fit.model_image + prob.v).ravel()
    try:
        resp = -np.linalg.solve(prob.fisher(jac, fit.model_image), wj)
    except np.linalg.LinAlgError:
        return None
    k = len(fit.emitters)
    return resp[[4 * i + j for i in range(k) for j in range(3)]]


class _Memo(NamedTuple):
    """A group's last fit in :func:`frame_fit`, kept for the next sweep."""

    offset: NDArray  # the neighbours' light it was fitted with (photons/pixel)
    tol: float  # change of that light below which it is reused outright
    emitters: NDArray  # (K, 4) the fit's emitters
    info: list  # per emitter: sigma, background, gof, flag, group
    origin: tuple  # the window's corner (nm)
    response: list  # [function, then the matrix of _response]: computed on first use
    cap: float  # change above which it is refitted whatever the response says


def _unmoved(hit: _Memo, offset: NDArray, origin: tuple, shift_tolerance: float) -> bool:
    """Whether a memo entry's group would stay where it is with this offset."""
    if hit.offset.shape != offset.shape or hit.origin != origin:
        return False
    d = offset - hit.offset
    m = float(np.max(np.abs(d))) if d.size else 0.0
    if m <= hit.tol:
        return True
    if shift_tolerance <= 0 or m > hit.cap:
        return False
    slot = hit.response
    if callable(slot[0]):  # computed once, on first use
        slot[0] = slot[0]()
    resp = slot[0]
    if resp is None:
        return False
    shift = np.abs(resp @ d.ravel()).reshape(-1, 3)
    return bool(
        np.all(shift[:, :2] <= shift_tolerance) and np.all(shift[:, 2] <= 2 * shift_tolerance)
    )


def _settled(prev: NDArray, em: NDArray, xy_tol: float = 2.0, z_tol: float = 5.0) -> bool:
    """Whether a sweep left the emitters where they were (same count; nm tolerances)."""
    if prev.shape != em.shape or len(em) == 0:
        return len(em) == 0 and len(prev) == 0
    from scipy.spatial import cKDTree

    d, j = cKDTree(prev[:, :2]).query(em[:, :2])
    return bool(
        np.all(d < xy_tol)
        and len(np.unique(j)) == len(j)
        and np.all(abs(prev[j, 2] - em[:, 2]) < z_tol)
    )


def frame_fit(
    frame: NDArray,
    model: PSFModel,
    emitters: Emitters,
    *,
    pixel_size: float,
    background: NDArray | float,
    group_distance: float,
    pad: int,
    reach: float,
    sweeps: int = 10,
    count_selection: bool = True,
    lr_threshold: float | None = None,
    min_photons: float = MIN_PHOTONS,
    max_emitters: int = 10,
    z_flip: float = 0.15,
    max_group: int = MAX_GROUP,
    skip_tolerance: float = SKIP_TOLERANCE,
    shift_tolerance: float = SHIFT_TOLERANCE,
    relocate: int = RELOCATE,
    fixed_light: NDArray | None = None,
    **fit_kwargs,
) -> FrameFit:
    """Maximum-likelihood fit of a frame's emitters, group by group.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        One frame in photons.
    model : PSFModel
        The continuous PSF model.
    emitters : Emitters
        Starting emitters (frame coordinates, nm), e.g. from :func:`frame_pursuit`.
    pixel_size : float
        Pixel size (nm).
    background : ndarray or float
        Background map or constant (photons/pixel): the start of each group's fitted constant.
    group_distance : float
        Emitters closer than this (nm, laterally) are fitted together.
    pad : int
        Pixels around a group's emitters in its window.
    reach : float
        Emitters farther than this (nm) from a window are left out of its offset.
    sweeps : int
        Most passes over the groups after the start or after a relocation pass that kept
        one; fewer when a pass leaves every emitter in place. A relocation pass comes after
        at most ``min(sweeps, RELOCATE_AFTER)`` of them (or when they settle).
    count_selection, lr_threshold, min_photons, max_emitters
        Count selection in each group (see :func:`fit_with_count_selection`); the default
        ``lr_threshold`` is :data:`ADD_THRESHOLD`, on the photon-counting scale (multiplied by
        ``qe`` when one is given); an emitter alone in its group is removed below
        :data:`SINGLE_THRESHOLD` (or ``lr_threshold`` if lower). A group may always grow by
        two emitters.
    max_group : int
        Larger groups are halved (across their longer side) until no part exceeds this: a
        dense field would otherwise make one huge fit (memory and time grow with its square).
    z_flip : float
        Emitters fitted within this fraction of the z range from either end are refitted
        from the other end, and the better likelihood is kept: a double helix that turns by
        half a revolution over its range looks alike at both ends, and the fit cannot cross
        from one to the other. 0 disables.
    skip_tolerance : float
        A group that a sweep leaves where it was is not refitted in the next sweep while its
        neighbours' light in its window changes by at most this many times the background's
        Poisson standard deviation per pixel; 0 refits every group every sweep.
    shift_tolerance : float
        Such a group is also not refitted when its neighbours' change, carried through the
        fit's linear response (``-F^-1 J' diag(1/mu)``), would move none of its emitters by
        more than this (nm) laterally or twice this axially, and changes no pixel by more
        than :data:`SHIFT_CAP` standard deviations; 0 turns this test off.
    relocate : int
        Most relocation passes (:func:`relocation_pass`: each emitter in turn replaced by the best
        PSF position of what the others leave unexplained, kept if the likelihood rises),
        each after the sweeps settle or after :data:`RELOCATE_AFTER` of them, and followed
        by sweeps again; the last pass is the first that keeps none. 0 disables.
    fixed_light : ndarray, shape (rows, cols), optional
        Known light (photons/pixel) of emitters fitted elsewhere (the two-tier solver's
        singles), added to every window's offset and not fitted.
    **fit_kwargs
        ``noise``, ``read_variance`` (a map is cropped to each window), ``plane``, ``qe``,
        ``background_shape`` (the frame's, cropped to each window: the shape the fits scale
        for their background, see :func:`~sparseloc.solvers.mle.fit_emitters`; default a
        constant).

    Returns
    -------
    FrameFit
        Emitters inside the frame.
    """
    f = np.asarray(frame, dtype=np.float64)
    px = float(pixel_size)
    rv = fit_kwargs.pop("read_variance", None)
    fixed = None if fixed_light is None else np.broadcast_to(fixed_light, f.shape)
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), f.shape)
    for key in ("background_shape", "censored"):
        if fit_kwargs.get(key) is None:
            fit_kwargs.pop(key, None)
    sweep = _Sweep(
        f,
        model,
        px,
        bg,
        rv,
        dict(
            group_distance=group_distance,
            pad=pad,
            reach=reach,
            count_selection=count_selection,
            lr_threshold=add_threshold(lr_threshold, fit_kwargs.get("qe", 1.0)),
            min_photons=min_photons,
            max_emitters=max_emitters,
            z_flip=z_flip,
            max_group=max_group,
            skip_tolerance=skip_tolerance,
            shift_tolerance=shift_tolerance,
        ),
        fit_kwargs,
        fixed,
    )
    em = emitters.as_array().reshape(-1, 4)
    info: list[tuple] = [(np.full(4, np.nan), np.nan, np.nan, "ok", -1)] * len(em)
    failed_moves: list[NDArray] = []  # where relocations lost (see relocation_pass)
    passes = 0  # relocation passes done
    relocate_after = min(RELOCATE_AFTER, max(sweeps, 1))
    in_round = 0  # sweeps since the start or the last relocation that kept one
    while len(em):
        prev = em
        em, info = sweep(em)
        in_round += 1
        settled = _settled(prev, em)
        if passes < relocate and len(em) and (settled or in_round >= relocate_after):
            # before a relocation the emitters need not have settled exactly: it moves some
            # of them far, and the sweeps after it settle them all
            em, moved = relocation_pass(
                f,
                model,
                em,
                np.array([i[1] for i in info], dtype=np.float64),
                px=px,
                group_distance=group_distance,
                pad=pad,
                reach=reach,
                min_photons=min_photons,
                max_group=max_group,
                failed=failed_moves,
                fixed_light=fixed,
                read_variance=rv,
                **fit_kwargs,
            )
            log.debug("frame_fit: relocation pass %d kept %d of %d", passes, moved, len(em))
            passes = passes + 1 if moved else relocate
            if moved:
                in_round = 0
                continue
        if settled or in_round >= max(sweeps, 1):
            break
    return _inside(em, info, f.shape, px)


class _Sweep:
    """One frame's Gauss-Seidel sweeps over its groups: the data, the options, the neighbours'
    light, the memo of groups left in place, and the z flips that lost."""

    def __init__(self, f, model, px, bg, rv, opts: dict, fit_kwargs: dict, fixed=None) -> None:
        self.f, self.model, self.px, self.bg, self.rv = f, model, px, bg, rv
        self.fixed = fixed  # light of emitters not fitted here (photons/pixel), or None
        self.o = opts
        self.fit_kwargs = fit_kwargs
        # A group whose emitters are exactly the output of its last fit, and whose neighbours'
        # light changed by less than a small fraction of the noise since then, would be
        # refitted from its own optimum to the same place: its last result is kept (later
        # sweeps move few emitters, so most groups are skipped).
        self.memo: dict[bytes, _Memo] = {}
        self.light = NeighbourLight(model, f.shape, px)
        self.failed_flips: list[NDArray] = []

    def __call__(self, em: NDArray) -> tuple[NDArray, list[tuple]]:
        """One sweep: every group refitted (or kept) with its neighbours' latest light.
        Returns the emitters (K, 4) and their (sigma, background, gof, flag, group)."""
        self.light.keep(em)
        groups = emitter_groups(em[:, :2], self.o["group_distance"], self.o["max_group"])
        # brightest groups first: their light is the largest offset for the others
        groups.sort(key=lambda g: -em[g, 3].sum())
        new_em: list[NDArray] = []
        new_info: list[tuple] = []
        done = np.zeros(len(em), bool)
        # Only this sweep's groups are remembered for the next: an older entry matches only
        # emitters that came back exactly, and the entries (windows, fits) would pile up.
        last, self.memo = self.memo, {}
        for gi, g in enumerate(groups):
            box = window_box(em[g], *self.f.shape, self.px, self.o["pad"])
            offset = self._offset(em, g, done, new_em, box)
            origin = (box[2] * self.px, box[0] * self.px)
            key = np.ascontiguousarray(em[g]).tobytes()
            hit = last.get(key)
            done[g] = True
            if hit is not None and _unmoved(hit, offset, origin, self.o["shift_tolerance"]):
                self.memo[key] = hit
                new_em.append(hit.emitters)
                new_info.extend((*i[:4], gi) for i in hit.info)
                continue
            arr, group_info = self._fit(em[g], gi, box, offset)
            new_em.append(arr)
            new_info.extend(group_info)
        return (np.vstack(new_em) if new_em else np.zeros((0, 4))), new_info

    def _offset(self, em, g, done, new_em, box) -> NDArray[np.float64]:
        """The light (photons/pixel) in window ``box`` of every emitter but group ``g``'s:
        groups already refitted in this sweep (``new_em``), the rest as they were."""
        others = [e for e in new_em if len(e)]
        rest = np.flatnonzero(~done)
        rest = rest[~np.isin(rest, g)]
        if len(rest):
            others.append(em[rest])
        r0, r1, c0, c1 = box
        offset = np.zeros((r1 - r0, c1 - c0))
        if others:
            o = np.vstack(others)
            near = near_window(o, box, self.px, self.o["reach"])
            if near.any():
                offset = self.light.window(o[near], box)
        if self.fixed is not None:
            offset = offset + self.fixed[r0:r1, c0:c1]
        return offset

    def _fit(self, start_em, gi: int, box, offset):
        """Fit one group in its window (count selection, z flips) and remember the result."""
        r0, r1, c0, c1 = box
        model, o = self.model, self.o
        origin = (c0 * self.px, r0 * self.px)
        y = window_data(self.f, box, {"read_variance": self.rv})
        kw = dict(
            pixel_size=self.px,
            origin=origin,
            offset=offset,
            background=float(max(np.median(self.bg[r0:r1, c0:c1]), 1e-3)),
            **self.fit_kwargs,
        )
        if self.rv is not None:
            kw["read_variance"] = self.rv
        kw = cropped_maps(kw, self.f.shape, box)
        start = Emitters.from_array(start_em)
        if o["count_selection"]:
            fit = fit_with_count_selection(
                y,
                model,
                start,
                lr_threshold=o["lr_threshold"],
                single_threshold=SINGLE_THRESHOLD,
                min_photons=o["min_photons"],
                max_emitters=max(o["max_emitters"], len(start_em) + 2),
                **kw,
            )
        else:
            fit = fit_emitters(y, model, start, **kw)
        if o["z_flip"]:
            fit = _try_z_flips(y, model, fit, kw, o["z_flip"], self.failed_flips)
        arr = fit.emitters.as_array().reshape(-1, 4)
        group_info = [
            (fit.sigma[k], float(fit.background[0]), fit.deviance_per_dof, fit.flags[k], gi)
            for k in range(len(arr))
        ]
        if o["skip_tolerance"] > 0 and len(arr):
            sd = np.sqrt(max(kw["background"], 1.0))
            # the linear response is computed when first needed (most entries never are)
            resp = [lambda y=y, fit=fit, kw=kw: _response(model, y, fit, kw)]
            self.memo[np.ascontiguousarray(arr).tobytes()] = _Memo(
                offset, o["skip_tolerance"] * sd, arr, group_info, origin, resp, SHIFT_CAP * sd
            )
        return arr, group_info


def _inside(em: NDArray, info: list[tuple], shape: tuple[int, int], px: float) -> FrameFit:
    """The :class:`FrameFit` of the emitters inside the frame."""
    on = inside(em, (0, shape[0], 0, shape[1]), px)
    em = em[on]
    info = [i for i, k in zip(info, on, strict=True) if k]
    k = len(em)
    return FrameFit(
        emitters=Emitters.from_array(em),
        sigma=np.array([i[0] for i in info]).reshape(k, 4),
        background=np.array([i[1] for i in info], dtype=np.float64),
        gof=np.array([i[2] for i in info], dtype=np.float64),
        flags=np.array([i[3] for i in info], dtype="<U16"),
        group=np.array([i[4] for i in info], dtype=np.int64),
    )
