"""The whole-frame fit of :func:`~sparseloc.solvers.frame.frame_fit` for many frames at once,
every maximum-likelihood fit done by :func:`~sparseloc.solvers.batch_fit.fit_batch`.

:func:`frame_fit` visits a frame's groups one after another (Gauss-Seidel): each group is fitted
with the current light of the frame's other emitters near its window (within ``reach``) as a
fixed offset. Two groups that cannot reach each other can be fitted at the same time without
changing anything. Here each frame's groups are coloured (greedily, brightest first) so that no
two groups of one colour reach each other, and a sweep processes the colours in turn: all the
groups of one colour, in all the frames, are fitted together in a few batched calls (on NumPy,
or PyTorch on the CPU or a GPU); then their emitters replace the old ones before the next
colour computes its offsets. With the default colouring rule (``"windows"``: a fit may leave
a group's emitters anywhere in its window grown by one pixel, and two groups conflict when that
box comes within ``reach`` of the other's window) a sweep is exactly a sweep of
:func:`frame_fit` with the groups in another order: colour by colour, brightest first within
a colour.

The count selection (:func:`~sparseloc.solvers.refine.fit_with_count_selection`) and the
z flips (:func:`~sparseloc.solvers.frame._try_z_flips`) are the same rules, run for all the
groups of a colour in lockstep: each round gathers every group's next trial fits (the weakest
emitter removed; an emitter added at one of the two best residual peaks; one emitter started
from the other end of the z range) into one batched call.

Measured on dense double-helix frames (128 x 128 pixels, 1 emitter/um^2, the pipeline's
``frame_fit`` settings: pad 12 px, reach 2050 nm): 11-14 colours per sweep with
``"windows"``, about 8 with ``"emitters"`` (an emitter of one group, as the emitters stand
before the colour, within ``reach`` of the other's window). With ``"emitters"`` a fit that
moves or adds an emitter into the reach of another group of its colour is not seen by that
group in this sweep (in a first sweep from the pursuit's starts, 10 of 36 groups). Over 8
such frames: ``frame_fit`` Jaccard 77.0 %, RMSE 34.8 nm lateral / 51.6 nm axial;
``"windows"`` 77.4 %, 31.8 / 43.4 nm; ``"emitters"`` 75.2 %, 32.4 / 46.4 nm.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..psf.spline import SplinePSF
from .batch_fit import fit_batch
from .emitters import Emitters
from .frame import (
    RELOCATE,
    RELOCATE_AFTER,
    FrameFit,
    _box,
    _flipped,
    _groups,
    _lost_flip_near,
    _near,
    _near_ends,
    _relocate,
    _settled,
    add_threshold,
)
from .refine import (
    REMOVE_SKIP_FACTOR,
    SKIP_FACTOR,
    FitResult,
    _addition_passes,
    _residual_candidates,
    likelihood_weight,
)

log = logging.getLogger(__name__)

__all__ = ["frame_fit_batch"]

#: Batched calls pad their windows to a square whose side is a multiple of this (pixels):
#: ``fit_batch`` keeps a padded copy of the spline table per window shape (the last 4), and
#: a few shapes shared by all calls save rebuilding it. On the CPU (NumPy, a dense 128 x 128
#: frame, 10 sweeps): 11-12 s with squares of 8 px steps (10.4 s with 16 px), 18-19 s with
#: each call padded to its largest window only; the same results to 1e-10 nm.
_SHAPE_STEP = 8

#: Count-selection changes per group, as :func:`fit_with_count_selection`'s default.
_MAX_CHANGES = 4


@dataclass
class _Window:
    """One group's window in one sweep.

    Attributes
    ----------
    frame : int
        Index of the frame in the batch.
    r0, r1, c0, c1 : int
        Rows ``r0:r1`` and columns ``c0:c1`` of the frame (pixels).
    origin : (float, float)
        Outer corner (nm, x then y) of the window's pixel (0, 0).
    y : ndarray, shape (r1 - r0, c1 - c0)
        Photons (clipped at zero unless the noise model is sCMOS).
    offset : ndarray, shape (r1 - r0, c1 - c0)
        Light of the frame's other emitters near the window (photons/pixel).
    background : float
        Starting background (photons/pixel): the median of the background map over the window.
    read_variance : float, ndarray of shape (r1 - r0, c1 - c0) or None
        sCMOS read-noise variance (photons^2).
    """

    frame: int
    r0: int
    r1: int
    c0: int
    c1: int
    origin: tuple[float, float]
    y: NDArray[np.float64]
    offset: NDArray[np.float64]
    background: float
    read_variance: float | NDArray[np.float64] | None

    @property
    def shape(self) -> tuple[int, int]:
        return self.r1 - self.r0, self.c1 - self.c0


@dataclass
class _Request:
    """One fit: a window, starting emitters (K, 4), an offset (the window's when None) and a
    starting background (photons/pixel)."""

    window: _Window
    start: NDArray[np.float64]
    offset: NDArray[np.float64] | None
    background: float


class _Fitter:
    """Runs lists of fits through :func:`fit_batch`, one call per list, and counts the calls.

    One call per list, however different its windows: the padding (to the largest emitter
    count and window of the list) cost less than more calls in a trial on the CPU (NumPy, one
    BLAS thread, two sweeps of a dense 128 x 128 frame: 5.6 s in one call per list, 6.4-8.8 s
    with each list split into calls of similar windows); on a GPU fewer calls matter more.
    """

    def __init__(
        self, model: SplinePSF, pixel_size: float, noise: str, device: Any, qe: float = 1.0
    ) -> None:
        self.model = model
        self.px = float(pixel_size)
        self.noise = noise
        self.device = device
        self.qe = qe
        self.calls = 0
        self.windows = 0

    def __call__(self, reqs: list[_Request]) -> list[FitResult]:
        """The fits of ``reqs`` as :class:`FitResult` (``model_image`` cropped to each window's
        real shape), in order."""
        return self._call(reqs) if reqs else []

    def _call(self, reqs: list[_Request]) -> list[FitResult]:
        """One :func:`fit_batch` call for ``reqs``, padded to the largest emitter count and to
        a square holding the largest window (side a multiple of :data:`_SHAPE_STEP`)."""
        nb = len(reqs)
        side = max(max(r.window.shape) for r in reqs)
        side = -(-side // _SHAPE_STEP) * _SHAPE_STEP
        rows = cols = side
        kmax = max(1, max(len(r.start) for r in reqs))
        y = np.zeros((nb, rows, cols))
        mask = np.zeros((nb, rows, cols), dtype=bool)
        off = np.zeros((nb, rows, cols))
        starts = np.full((nb, kmax, 4), np.nan)
        n_em = np.zeros(nb, dtype=np.int64)
        origins = np.zeros((nb, 2))
        bg = np.zeros(nb)
        maps = any(isinstance(r.window.read_variance, np.ndarray) for r in reqs)
        rv = np.zeros((nb, rows, cols)) if maps else None
        for b, req in enumerate(reqs):
            w = req.window
            r, c = w.shape
            y[b, :r, :c] = w.y
            mask[b, :r, :c] = True
            off[b, :r, :c] = w.offset if req.offset is None else req.offset
            k = len(req.start)
            starts[b, :k] = req.start
            n_em[b] = k
            origins[b] = w.origin
            bg[b] = req.background
            if rv is not None:
                rv[b, :r, :c] = w.read_variance
        read_variance = reqs[0].window.read_variance if rv is None else rv
        res = fit_batch(
            y,
            starts,
            n_em,
            self.model,
            pixel_size=self.px,
            origins=origins,
            offsets=off,
            background=bg,
            mask=mask,
            noise=self.noise,
            read_variance=read_variance,
            device=self.device,
            qe=self.qe,
        )
        self.calls += 1
        self.windows += nb
        out = []
        for b, req in enumerate(reqs):
            fit = res.fit_result(b)
            r, c = req.window.shape
            fit.model_image = fit.model_image[:r, :c].copy()
            out.append(fit)
        return out


#: How far (pixels) a fit may move an emitter beyond its window (``fit_batch``'s default
#: ``xy_margin``, as :func:`fit_emitters`).
_XY_MARGIN = 1.0

COLOURINGS = ("windows", "emitters")


def _colours(
    em: NDArray[np.float64],
    groups: list[NDArray[np.intp]],
    boxes: list[tuple[int, int, int, int]],
    px: float,
    reach: float,
    rule: str = "windows",
) -> NDArray[np.int64]:
    """Greedy colouring of the groups (in their order): conflicting groups get different
    colours.

    Two groups conflict (``rule="windows"``) when the box where a fit may leave one's
    emitters (its window grown by the fit's 1-pixel margin) comes within ``reach`` (nm, per
    axis) of the other's window, or (``rule="emitters"``) when one of the emitters of one, as
    they stand, is within ``reach`` of the other's window.
    """
    ng = len(groups)
    if rule == "windows":
        b = np.asarray(boxes, dtype=np.float64).reshape(ng, 4) * px  # r0, r1, c0, c1 in nm
        m = _XY_MARGIN * px
        lo_r, hi_r = b[:, 0] - m, b[:, 1] + m
        lo_c, hi_c = b[:, 2] - m, b[:, 3] + m
        # conflict[i, j]: group i's reachable box meets group j's window grown by reach
        rows = (lo_r[:, None] < b[None, :, 1] + reach) & (hi_r[:, None] > b[None, :, 0] - reach)
        cols = (lo_c[:, None] < b[None, :, 3] + reach) & (hi_c[:, None] > b[None, :, 2] - reach)
        conflict = rows & cols
    elif rule == "emitters":
        member = np.zeros((ng, len(em)))
        for i, g in enumerate(groups):
            member[i, g] = 1.0
        inside = np.stack([_near(em, b, px, reach) for b in boxes], axis=1).astype(np.float64)
        # conflict[i, j]: an emitter of group i lies within reach of group j's window
        conflict = (member @ inside) > 0
    else:
        raise ValueError(f"colouring must be one of {', '.join(COLOURINGS)}; got {rule!r}")
    conflict |= conflict.T
    colour = np.full(ng, -1, dtype=np.int64)
    for i in range(ng):
        used = set(colour[:i][conflict[i, :i]].tolist())
        c = 0
        while c in used:
            c += 1
        colour[i] = c
    return colour


def _count_selection(
    fit: _Fitter,
    windows: list[_Window],
    best: list[FitResult],
    caps: list[int],
    *,
    threshold: float,
    min_photons: float,
    weight: float,
) -> list[FitResult]:
    """The loop of :func:`fit_with_count_selection` for many windows in lockstep.

    ``best`` holds each window's fit of its starting emitters. Each round gives every window
    that is still changing one removal trial (one batched call for all) or, where it had none
    or kept its emitters, up to two addition trials (one batched call for all).
    """
    model, px = fit.model, fit.px
    best = list(best)
    n = len(windows)
    changes = np.zeros(n, dtype=np.int64)
    open_ = np.ones(n, dtype=bool)
    while open_.any():
        for j in np.flatnonzero(open_):
            e = best[j].emitters
            weak = len(e) > 0 and e.photons.min() < min_photons
            if not (changes[j] < _MAX_CHANGES or weak):
                open_[j] = False
        todo = np.flatnonzero(open_)
        if len(todo) == 0:
            break
        # Removal of the weakest emitter, unless its Wald statistic makes it hopeless.
        trials: list[tuple[int, NDArray, int]] = []
        for j in todo:
            arr = best[j].emitters.as_array().reshape(-1, 4)
            if len(arr) == 0:
                continue
            weakest = int(np.argmin(arr[:, 3]))
            wald = (arr[weakest, 3] / best[j].sigma[weakest, 3]) ** 2
            if (
                not np.isfinite(wald)
                or wald < REMOVE_SKIP_FACTOR * threshold
                or arr[weakest, 3] < min_photons
            ):
                trials.append((int(j), arr, weakest))
        fewer = fit(
            [
                _Request(windows[j], np.delete(arr, w, axis=0), None, float(best[j].background[0]))
                for j, arr, w in trials
            ]
        )
        removed = set()
        for (j, arr, w), f in zip(trials, fewer, strict=True):
            ratio = 2.0 * (best[j].log_likelihood - f.log_likelihood)
            if ratio < threshold or arr[w, 3] < min_photons:
                best[j] = f
                changes[j] += 1
                removed.add(j)
        # Addition at the best residual peaks, where the score statistic lets it pass.
        adds: list[tuple[int, NDArray]] = []
        for j in todo:
            if j in removed:
                continue
            b = best[j]
            w = windows[j]
            if len(b.emitters) < caps[j]:
                cands, stat = _residual_candidates(w.y, b.model_image, model, px, w.origin)
            else:
                cands, stat = [], 0.0
            if weight * stat >= threshold / SKIP_FACTOR:
                for cand in cands:
                    adds.append((int(j), np.vstack([b.emitters.as_array().reshape(-1, 4), cand])))
        more_fits = fit(
            [_Request(windows[j], arr, None, float(best[j].background[0])) for j, arr in adds]
        )
        more: dict[int, FitResult] = {}
        for (j, _), f in zip(adds, more_fits, strict=True):
            if j not in more or f.log_likelihood > more[j].log_likelihood:
                more[j] = f
        for j in todo:
            if j in removed:
                continue
            m = more.get(int(j))
            if m is not None:
                ratio = 2.0 * (m.log_likelihood - best[j].log_likelihood)
                if _addition_passes(m, ratio, threshold, min_photons):
                    best[j] = m
                    changes[j] += 1
                    continue
            open_[j] = False
    return best


def _z_flips(
    fit: _Fitter,
    windows: list[_Window],
    best: list[FitResult],
    fraction: float,
    failed: list[list[NDArray]],
) -> list[FitResult]:
    """The rule of :func:`~sparseloc.solvers.frame._try_z_flips` for many windows at once.

    Each emitter within ``fraction`` of the z range from either end is refitted alone from the
    other end, the rest of its group held fixed with the emitters as the earlier trials left
    them; windows where a trial beat the group's likelihood are refitted jointly. ``failed[j]``
    is window ``j``'s frame's list of positions (x, y, z in nm) where a trial lost: emitters
    near one are not tried, and losing trials extend it. The trials of a window are run
    speculatively together: when one is accepted, the later ones (which held the old emitter
    fixed) are run again in the next round. Each window's trials are decided in its own
    order; the windows of one colour are too far apart to share a failed position.
    """
    model, px = fit.model, fit.px
    n = len(windows)
    arrs = [b.emitters.as_array().reshape(-1, 4).copy() for b in best]
    near = [_near_ends(a, model.z_range, fraction) for a in arrs]
    pos = [0] * n
    flipped = [False] * n
    while True:
        trials: dict[tuple[int, int], int] = {}
        reqs: list[_Request] = []
        for j in range(n):
            w = windows[j]
            arr = arrs[j]
            for k in near[j][pos[j] :]:
                if _lost_flip_near(failed[j], arr[k]):
                    continue
                others = np.delete(arr, k, axis=0)
                off = w.offset
                if len(others):
                    off = off + model.render(*others.T, w.shape, px, origin=w.origin)
                alt = _flipped(arr[k], model.z_range)
                trials[(j, k)] = len(reqs)
                reqs.append(_Request(w, alt[None], off, float(best[j].background[0])))
        if not reqs:
            break
        ones = fit(reqs)
        for j in range(n):
            for k in near[j][pos[j] :]:
                pos[j] += 1
                # decided in order, as _try_z_flips: a loss just recorded may exclude k
                if _lost_flip_near(failed[j], arrs[j][k]):
                    continue
                one = ones[trials[(j, k)]]
                if one.log_likelihood > best[j].log_likelihood and len(one.emitters) == 1:
                    arrs[j][k] = one.emitters.as_array()[0]
                    flipped[j] = True
                    break  # the later trials held the old emitter: run them again
                failed[j].append(arrs[j][k, :3].copy())
    joint = [j for j in range(n) if flipped[j]]
    refits = fit([_Request(windows[j], arrs[j], None, windows[j].background) for j in joint])
    out = list(best)
    for j, t in zip(joint, refits, strict=True):
        if t.log_likelihood > best[j].log_likelihood and len(t.emitters) == len(arrs[j]):
            t.history = [*best[j].history, "z flip"]
            out[j] = t
    return out


def _per_frame(value: Any, n: int, name: str) -> list[Any]:
    """A scalar for every frame, or one value per frame."""
    if isinstance(value, (int, float, np.number)) or (
        isinstance(value, np.ndarray) and value.ndim == 0
    ):
        return [float(value)] * n
    if isinstance(value, np.ndarray) and value.ndim == 2:
        return [value] * n
    vals = list(value)
    if len(vals) != n:
        raise ValueError(f"{name} has {len(vals)} entries for {n} frames")
    return vals


def frame_fit_batch(
    frames: Sequence[ArrayLike],
    model: SplinePSF,
    emitters: Sequence[Emitters],
    *,
    pixel_size: float,
    background: Sequence[ArrayLike | float] | float,
    group_distance: float,
    pad: int,
    reach: float,
    sweeps: int = 10,
    count_selection: bool = True,
    threshold: float | None = None,
    min_photons: float = 200.0,
    max_emitters: int = 10,
    z_flip: float = 0.15,
    max_group: int = 8,
    device: Any = None,
    noise: str = "poisson",
    read_variance: float | ArrayLike | None = None,
    colouring: str = "windows",
    qe: float = 1.0,
    relocate: int = RELOCATE,
) -> list[FrameFit]:
    """:func:`~sparseloc.solvers.frame.frame_fit` for many frames in lockstep, with batched fits.

    Every frame is solved as :func:`frame_fit` solves it: the same groups (emitters closer than
    ``group_distance``, split above ``max_group``), windows, offsets, count selection, z flips,
    sweeps and settle test, relocation passes (run frame by frame on the CPU, as
    :func:`frame_fit` runs them), and the same output. Two things differ:

    - Within a sweep the groups are visited colour by colour (see the module notes) instead of
      brightest first. With ``colouring="windows"`` groups of one colour cannot reach each
      other whatever their fits do, so a sweep is exactly a sweep of :func:`frame_fit` in that
      order. With ``colouring="emitters"`` (fewer colours, so fewer batched calls) a fit that
      moves or adds an emitter into the reach of another group of its colour is not seen by
      that group before the next colour, where :func:`frame_fit` would see it at once.
    - :func:`frame_fit`'s memo (``skip_tolerance``: a group left in place is not refitted while
      its neighbours' light barely changes) is not used: every group is refitted every sweep,
      as :func:`frame_fit` with ``skip_tolerance=0`` does.

    A frame stops when its sweeps settle (a sweep leaves every emitter in place) and no
    relocation pass is due or the last one kept none; the others go on.

    Parameters
    ----------
    frames : sequence of ndarray, each shape (rows, cols)
        Frames in photons (their shapes may differ).
    model : SplinePSF
        The PSF (tabulate other models with :meth:`SplinePSF.from_model`).
    emitters : sequence of Emitters
        Starting emitters of each frame (frame coordinates, nm), e.g. from
        :func:`~sparseloc.solvers.frame.frame_pursuit`.
    pixel_size : float
        Pixel size (nm); must be the spline's.
    background : float, ndarray of shape (rows, cols), or a sequence of them
        Background of each frame (photons/pixel), a map or a constant: the start of each
        group's fitted constant (its median over the window). A single float or 2-D map
        serves every frame.
    group_distance : float
        Emitters closer than this (nm, laterally) are fitted together.
    pad : int
        Pixels around a group's emitters in its window.
    reach : float
        Emitters farther than this (nm, per axis) from a window are left out of its offset.
    sweeps : int
        Most passes over the groups of a frame after the start or after a relocation pass
        that kept one (as :func:`frame_fit`).
    count_selection : bool
        Test one emitter fewer and one more in each group by a likelihood ratio.
    threshold : float, optional
        Likelihood-ratio threshold; default :data:`~sparseloc.solvers.frame.ADD_THRESHOLD`
        (on the photon-counting scale, multiplied by ``qe``).
    min_photons : float
        Emitters with fewer photons are removed and never added.
    max_emitters : int
        Most emitters per group (a group may always grow by two).
    z_flip : float
        Fraction of the z range at either end within which emitters are refitted from the
        other end (see :func:`frame_fit`); 0 disables.
    max_group : int
        Larger groups are halved until no part exceeds this.
    device : None, "numpy", "cpu", "cuda", "cuda:N" or torch.device
        Where :func:`fit_batch` runs (NumPy by default).
    noise : {"poisson", "emccd", "scmos"}
        Likelihood.
    read_variance : float or ndarray of shape (rows, cols), optional
        sCMOS read-noise variance (photons^2), the same for every frame; a map is cropped to
        each window.
    colouring : {"windows", "emitters"}
        Rule of the colouring (see the module notes): ``"windows"`` keeps the sweeps exact
        Gauss-Seidel sweeps; ``"emitters"`` needs fewer colours.
    qe : float
        Quantum efficiency in (0, 1] (see :func:`~sparseloc.solvers.refine.fit_emitters`).
    relocate : int
        Most relocation passes per frame, as in :func:`frame_fit`; they run frame by frame on
        the CPU with unbatched fits. 0 disables.

    Returns
    -------
    list of FrameFit
        One per frame: the emitters inside the frame with their CRLB ``sigma`` (K, 4: x, y,
        z in nm, photons), their group's fitted background (photons/pixel) and deviance per
        degree of freedom, flags and group index (the group's rank by brightness in the
        last sweep).

    Raises
    ------
    ValueError
        ``model`` is not a :class:`SplinePSF`, the lists do not match, a frame is not 2-D, an
        unknown colouring, or :func:`fit_batch` refuses its inputs.
    """
    if not isinstance(model, SplinePSF):
        raise ValueError(
            "frame_fit_batch needs a SplinePSF (tabulate other models with "
            f"SplinePSF.from_model); got {type(model).__name__}"
        )
    if colouring not in COLOURINGS:
        raise ValueError(f"colouring must be one of {', '.join(COLOURINGS)}; got {colouring!r}")
    n = len(frames)
    if len(emitters) != n:
        raise ValueError(f"{len(emitters)} sets of starting emitters for {n} frames")
    px = float(pixel_size)
    threshold = add_threshold(threshold, qe)
    weight = likelihood_weight(noise, qe)
    bgs = _per_frame(background, n, "background")
    data: list[NDArray[np.float64]] = []
    bg_maps: list[NDArray[np.float64]] = []
    rv_maps: list[NDArray[np.float64] | None] = []
    rv_scalar = read_variance is not None and np.ndim(read_variance) == 0
    for i in range(n):
        f = np.asarray(frames[i], dtype=np.float64)
        if f.ndim != 2:
            raise ValueError(f"frame {i} must be 2-D, got shape {f.shape}")
        data.append(f)
        bg_maps.append(np.broadcast_to(np.asarray(bgs[i], dtype=np.float64), f.shape))
        if read_variance is None or rv_scalar:
            rv_maps.append(None)
        else:
            rv_maps.append(np.broadcast_to(np.asarray(read_variance, dtype=np.float64), f.shape))
    fit = _Fitter(model, px, noise, device, qe)
    em = [e.as_array().reshape(-1, 4).copy() for e in emitters]
    info: list[list[tuple]] = [[] for _ in range(n)]
    # per frame, where z flips lost (x, y, z in nm): not tried again there (as frame_fit)
    failed_flips: list[list[NDArray]] = [[] for _ in range(n)]
    running = [True] * n
    # per frame, as frame_fit: relocation passes done, sweeps since the last that kept one
    passes = [0] * n
    reloc_after = min(RELOCATE_AFTER, max(sweeps, 1))
    in_round = [0] * n
    failed_moves: list[list[NDArray]] = [[] for _ in range(n)]
    sweep = 0
    while True:
        for i in range(n):
            if running[i] and len(em[i]) == 0:
                running[i] = False
        active = [i for i in range(n) if running[i]]
        if not active:
            break
        plans = {}
        for i in active:
            rows, cols = data[i].shape
            groups = _groups(em[i][:, :2], group_distance, max_group)
            # brightest first, as frame_fit (the colouring is greedy in this order)
            groups.sort(key=lambda g, e=em[i]: -e[g, 3].sum())
            boxes = [_box(em[i][g], rows, cols, px, pad) for g in groups]
            plans[i] = (groups, boxes, _colours(em[i], groups, boxes, px, reach, colouring))
        n_colours = max(int(p[2].max()) + 1 for p in plans.values())
        new_em: dict[int, list[NDArray | None]] = {i: [None] * len(plans[i][0]) for i in active}
        new_info: dict[int, list[list[tuple] | None]] = {
            i: [None] * len(plans[i][0]) for i in active
        }
        done = {i: np.zeros(len(em[i]), bool) for i in active}
        calls0 = fit.calls
        for colour in range(n_colours):
            wins: list[_Window] = []
            starts: list[NDArray] = []
            where: list[tuple[int, int]] = []
            for i in active:
                groups, boxes, colours = plans[i]
                rows, cols = data[i].shape
                for gi in np.flatnonzero(colours == colour):
                    g = groups[gi]
                    r0, r1, c0, c1 = boxes[gi]
                    origin = (c0 * px, r0 * px)
                    shape = (r1 - r0, c1 - c0)
                    # others: groups refitted in this sweep, the rest as they were
                    others = [a for a in new_em[i] if a is not None and len(a)]
                    rest = np.flatnonzero(~done[i])
                    rest = rest[~np.isin(rest, g)]
                    if len(rest):
                        others.append(em[i][rest])
                    offset = np.zeros(shape)
                    if others:
                        o = np.vstack(others)
                        o = o[_near(o, boxes[gi], px, reach)]
                        if len(o):
                            offset = model.render(*o.T, shape, px, origin=origin)
                    y = data[i][r0:r1, c0:c1]
                    if noise != "scmos":
                        # Read noise puts some pixels below zero; the Poisson fit needs >= 0.
                        y = np.maximum(y, 0.0)
                    rv_map = rv_maps[i]
                    if rv_map is not None:
                        rv: float | NDArray | None = np.ascontiguousarray(rv_map[r0:r1, c0:c1])
                    else:
                        rv = None if read_variance is None else float(read_variance)
                    wins.append(
                        _Window(
                            frame=i,
                            r0=r0,
                            r1=r1,
                            c0=c0,
                            c1=c1,
                            origin=origin,
                            y=y,
                            offset=offset,
                            background=float(max(np.median(bg_maps[i][r0:r1, c0:c1]), 1e-3)),
                            read_variance=rv,
                        )
                    )
                    starts.append(em[i][g])
                    where.append((i, int(gi)))
            if not wins:
                continue
            fits = fit(
                [_Request(w, s, None, w.background) for w, s in zip(wins, starts, strict=True)]
            )
            if count_selection:
                caps = [max(max_emitters, len(s) + 2) for s in starts]
                fits = _count_selection(
                    fit,
                    wins,
                    fits,
                    caps,
                    threshold=threshold,
                    min_photons=min_photons,
                    weight=weight,
                )
            if z_flip:
                fits = _z_flips(fit, wins, fits, z_flip, [failed_flips[w.frame] for w in wins])
            for (i, gi), r in zip(where, fits, strict=True):
                arr = r.emitters.as_array().reshape(-1, 4)
                done[i][plans[i][0][gi]] = True
                new_em[i][gi] = arr
                new_info[i][gi] = [
                    (r.sigma[k], float(r.background[0]), r.deviance_per_dof, r.flags[k], gi)
                    for k in range(len(arr))
                ]
        log.debug(
            "frame_fit_batch sweep %d: %d frames, %d colours, %d batched calls",
            sweep,
            len(active),
            n_colours,
            fit.calls - calls0,
        )
        sweep += 1
        for i in active:
            prev = em[i]
            parts = [a for a in new_em[i] if a is not None]
            em[i] = np.vstack(parts) if parts else np.zeros((0, 4))
            info[i] = [t for part in new_info[i] if part is not None for t in part]
            in_round[i] += 1
            settled = _settled(prev, em[i])
            if passes[i] < relocate and len(em[i]) and (settled or in_round[i] >= reloc_after):
                # frame_fit's relocation pass, frame by frame with unbatched fits (its trials
                # are sequential: each sees the relocations before it)
                em[i], moved = _relocate(
                    data[i],
                    model,
                    em[i],
                    np.array([t[1] for t in info[i]], dtype=np.float64),
                    px=px,
                    group_distance=group_distance,
                    pad=pad,
                    reach=reach,
                    min_photons=min_photons,
                    max_group=max_group,
                    failed=failed_moves[i],
                    noise=noise,
                    qe=qe,
                    read_variance=read_variance if rv_maps[i] is None else rv_maps[i],
                )
                passes[i] = passes[i] + 1 if moved else relocate
                if moved:
                    in_round[i] = 0
                    continue
            if settled or in_round[i] >= max(sweeps, 1):
                running[i] = False
    log.debug("frame_fit_batch: %d fits in %d batched calls", fit.windows, fit.calls)
    out = []
    for i in range(n):
        rows, cols = data[i].shape
        e = em[i]
        inside = (e[:, 0] >= 0) & (e[:, 0] < cols * px) & (e[:, 1] >= 0) & (e[:, 1] < rows * px)
        e = e[inside]
        inf = [t for t, k in zip(info[i], inside, strict=True) if k]
        k = len(e)
        out.append(
            FrameFit(
                emitters=Emitters.from_array(e),
                sigma=np.array([t[0] for t in inf]).reshape(k, 4),
                background=np.array([t[1] for t in inf], dtype=np.float64),
                gof=np.array([t[2] for t in inf], dtype=np.float64),
                flags=np.array([t[3] for t in inf], dtype="<U16"),
                group=np.array([t[4] for t in inf], dtype=np.int64),
            )
        )
    return out
