"""Relocation passes of the frame solver (:func:`relocation_pass`).

The sweeps of :func:`~sparseloc.solvers.frame.frame_fit` only go downhill, and in a crowd the
pursuit's greedy starts leave emitters in local optima (one emitter's image paired with part of
a neighbour's, a missed emitter explained by a wrong one nearby). A pass takes each emitter in
turn out, refits its neighbours without it and fits the best PSF position of what they leave
unexplained in its place; the move is kept if the likelihood rises.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..psf.base import PSFModel
from .emitters import Emitters
from .frame_windows import (
    MAX_GROUP,
    light_pieces,
    lost_flip_near,
    sum_pieces,
    window_box,
    window_data,
    window_kwargs,
)
from .mle import fit_emitters
from .refine import residual_candidates

__all__ = [
    "RELOCATE",
    "RELOCATE_AFTER",
    "RELOCATE_MIN_DZ",
    "RELOCATE_MIN_SHIFT",
    "RelocationTrial",
    "relocation_pass",
]


#: Relocation passes of :func:`~sparseloc.solvers.frame.frame_fit`, each followed by sweeps:
#: a second pass still finds some emitters, a third little more.
RELOCATE = 2
#: A relocation pass follows at most this many sweeps (fewer when they settle): it moves some
#: emitters far, and the sweeps after it settle them all.
RELOCATE_AFTER = 2
#: A relocation is tried only when the best candidate lies at least this far (pixels,
#: laterally) from the emitter it would replace, or ...
RELOCATE_MIN_SHIFT = 1.5
#: ... at least this fraction of the z range away axially: nearer candidates are the emitter
#: itself, and replacing it by them gains nothing.
RELOCATE_MIN_DZ = 0.15


class RelocationTrial(NamedTuple):
    """One relocation found by :func:`relocation_trial`: emitter ``i`` of the frame replaced
    by ``candidate`` (x, y, z in nm, photons) in the window ``box`` (r0, r1, c0, c1 in
    pixels) of its neighbourhood ``group`` (indices, ``i`` last), whose fits start from
    ``background`` and hold ``offset`` (the other emitters' light) fixed, both in
    photons/pixel."""

    i: int
    group: NDArray[np.intp]
    box: tuple[int, int, int, int]
    offset: NDArray[np.float64]
    background: float
    candidate: NDArray[np.float64]


def relocation_trial(
    f: NDArray,
    model: PSFModel,
    em: NDArray,
    i: int,
    bg: NDArray,
    *,
    px: float,
    group_distance: float,
    pad: int,
    max_group: int,
    fit_kwargs: dict,
    frame_light: NDArray,
    pieces: list,
) -> RelocationTrial | None:
    """The relocation of emitter ``i`` worth a fit, or None.

    Its neighbourhood (the emitters within ``group_distance`` of it, laterally, at most
    ``max_group`` with it: the nearest) gets the window of a group, with the light of the
    frame's other emitters as the offset: ``frame_light`` (the sum of ``pieces``,
    :func:`light_pieces` of all the frame's emitters in their order, over the frame) less
    the neighbourhood's own, summed from its ``pieces``. The neighbours are
    fitted there without emitter ``i``, so that they take what of its light they can
    explain, and the residual is searched for the best PSF position
    (:func:`~sparseloc.solvers.refine.residual_candidates`). If that is emitter ``i`` itself
    (closer than :data:`RELOCATE_MIN_SHIFT` pixels and :data:`RELOCATE_MIN_DZ` of the z
    range), there is nothing to try. (Without that refit, the residual of the current model
    less emitter ``i`` gives the emitter itself nearly always.)
    """
    rows, cols = f.shape
    d = np.hypot(em[:, 0] - em[i, 0], em[:, 1] - em[i, 1])
    near_i = np.flatnonzero((d < group_distance) & (np.arange(len(em)) != i))
    near_i = near_i[np.argsort(d[near_i], kind="stable")][: max(max_group, 1) - 1]
    group = np.concatenate([near_i, [i]]).astype(np.intp)
    box = window_box(em[group], rows, cols, px, pad)
    r0, r1, c0, c1 = box
    origin = (c0 * px, r0 * px)
    own = sum_pieces([pieces[j] for j in group], box)
    offset = np.maximum(frame_light[r0:r1, c0:c1] - own, 0.0)  # rounding below zero
    background = float(np.mean(bg[group]))
    y = window_data(f, box, fit_kwargs)
    if len(group) > 1:
        kw = window_kwargs(f, box, px, offset, background, fit_kwargs)
        mu = fit_emitters(y, model, Emitters.from_array(em[group[:-1]]), **kw).model_image
    else:
        mu = offset + background
    cands, _ = residual_candidates(y, mu, model, px, origin, n_best=1, score=False)
    if not cands:
        return None
    c = np.asarray(cands[0], dtype=np.float64)
    lo, hi = model.z_range
    if np.hypot(c[0] - em[i, 0], c[1] - em[i, 1]) < RELOCATE_MIN_SHIFT * px and abs(
        c[2] - em[i, 2]
    ) < RELOCATE_MIN_DZ * (hi - lo):
        return None
    return RelocationTrial(i, group, box, offset, background, c)


def relocation_fit(
    f: NDArray,
    model: PSFModel,
    em: NDArray,
    t: RelocationTrial,
    px: float,
    min_photons: float,
    fit_kwargs: dict,
) -> tuple[NDArray[np.float64], float] | None:
    """The two fits of a relocation (:func:`relocation_pass`): its neighbourhood from the current
    emitters and with emitter ``t.i`` replaced by the candidate. The replacement's emitters
    (K, 4; the group's order) and background (photons/pixel) if its log-likelihood is
    higher and no emitter is below ``min_photons`` or diverged, else None."""
    y = window_data(f, t.box, fit_kwargs)
    kw = window_kwargs(f, t.box, px, t.offset, t.background, fit_kwargs)
    base = fit_emitters(y, model, Emitters.from_array(em[t.group]), **kw)
    kw["background"] = float(base.background[0])
    start = np.vstack([em[t.group[:-1]], t.candidate[None]])
    trial = fit_emitters(y, model, Emitters.from_array(start), **kw)
    new = trial.emitters.as_array().reshape(-1, 4)
    if (
        trial.log_likelihood > base.log_likelihood
        and np.all(trial.flags != "diverged")
        and new[:, 3].min() >= min_photons
    ):
        return new, float(trial.background[0])
    return None


def relocation_pass(
    f: NDArray,
    model: PSFModel,
    em: NDArray,
    bg: NDArray,
    *,
    px: float,
    group_distance: float,
    pad: int,
    reach: float,
    min_photons: float,
    max_group: int = MAX_GROUP,
    failed: list | None = None,
    fixed_light: NDArray | None = None,
    **fit_kwargs,
) -> tuple[NDArray[np.float64], int]:
    """One relocation pass over a frame's emitters: each in turn is removed and the best PSF
    position of what its neighbours leave unexplained is fitted instead; kept if the
    likelihood rises.

    The sweeps of :func:`frame_fit` only move emitters downhill from where they are. In a
    crowd the pursuit's greedy starts can pair one emitter's image with part of a
    neighbour's, or explain a missed emitter by a nearby wrong one, and no downhill path
    leads out: started from the true emitters, the same sweeps reached a log-likelihood
    higher by about 900 per dense frame (see the module notes). A relocation jumps between
    those optima: the emitter's neighbourhood is fitted jointly twice, from the current
    emitters and with emitter ``i`` replaced by the candidate of :func:`relocation_trial`;
    the replacement is kept if its log-likelihood is higher, with the same count and no
    emitter below ``min_photons`` or diverged.

    Parameters
    ----------
    f : ndarray, shape (rows, cols)
        The frame (photons).
    model : PSFModel
        The continuous PSF model.
    em : ndarray, shape (K, 4)
        The frame's emitters (x, y, z in nm, photons), e.g. after :func:`frame_fit`'s sweeps.
    bg : ndarray, shape (K,)
        Each emitter's fitted background (photons/pixel).
    px, group_distance, pad, reach
        As in :func:`frame_fit`.
    min_photons : float
        No emitter of a kept relocation may have fewer photons.
    max_group : int
        Most emitters of a neighbourhood (the nearest; as :func:`frame_fit`'s groups).
    failed : list, optional
        Positions (x, y, z in nm) where a relocation had nothing to try or lost, consulted
        and extended: an emitter near one of them (:data:`FLIP_MEMORY_NM`) is not tried
        again; a kept relocation forgets those less than ``group_distance`` (per axis) from
        its window.
    fixed_light : ndarray, shape (rows, cols), optional
        Known light (photons/pixel) of emitters not in ``em``, part of every offset.
    **fit_kwargs
        ``noise``, ``read_variance`` (a map is cropped to each window), ``plane``, ``qe``.

    Returns
    -------
    em : ndarray, shape (K, 4)
        The emitters after the pass (a copy; same order).
    moved : int
        How many relocations were kept.
    """
    em = np.array(em, dtype=np.float64).reshape(-1, 4)
    bg = np.array(bg, dtype=np.float64)
    moved = 0
    # Each emitter's light piece is rendered once per pass (and again when it moves), and
    # their sum over the frame kept up to date: a trial's offset is a crop of that sum less
    # its neighbourhood's own pieces, instead of a render of every other emitter within
    # reach (on dense frames that render was a tenth of the solver's time).
    full = (0, f.shape[0], 0, f.shape[1])
    pieces = light_pieces(model, em, f.shape, px, (0.0, 0.0), reach)
    light = sum_pieces(pieces, full)
    if fixed_light is not None:
        light = light + fixed_light
    for i in range(len(em)):
        if lost_flip_near(failed, em[i]):
            continue
        t = relocation_trial(
            f,
            model,
            em,
            i,
            bg,
            px=px,
            group_distance=group_distance,
            pad=pad,
            max_group=max_group,
            fit_kwargs=fit_kwargs,
            frame_light=light,
            pieces=pieces,
        )
        kept = None
        if t is not None:
            kept = relocation_fit(f, model, em, t, px, min_photons, fit_kwargs)
        if t is None or kept is None:
            if failed is not None:
                failed.append(em[i, :3].copy())
            continue
        # fit_emitters keeps the count and order of its starting emitters: the group's rows
        light -= sum_pieces([pieces[j] for j in t.group], full)
        em[t.group], bg[t.group] = kept
        new = light_pieces(model, em[t.group], f.shape, px, (0.0, 0.0), reach)
        for j, piece in zip(t.group, new, strict=True):
            pieces[j] = piece
        light += sum_pieces(new, full)
        moved += 1
        if failed:
            # the neighbourhood changed: what lost near it may win now
            r0, r1, c0, c1 = t.box
            fa = np.asarray(failed)
            keep = ~(
                (fa[:, 0] > c0 * px - group_distance)
                & (fa[:, 0] < c1 * px + group_distance)
                & (fa[:, 1] > r0 * px - group_distance)
                & (fa[:, 1] < r1 * px + group_distance)
            )
            failed[:] = [a for a, k in zip(failed, keep, strict=True) if k]
    return em, moved
