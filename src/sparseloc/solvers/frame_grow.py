"""A third start for crowded regions: each grown again from one emitter.

The pursuit places its emitters on a fixed grid, one after the other, each on the residual of
the ones before; where two images overlap, the first lands between them and the rest explain
what it leaves, and the fits from there keep the wrong arrangement. The L1 deconvolution's
peaks (the second start) get stuck elsewhere. Here each group of two or more emitters of a
frame's fit is solved once more in its window, with every other emitter's light known: from
the one best PSF position of what that light and the background leave, the count selection
adds one emitter at a time (the best position of the residual) and refits them all jointly
after each addition, so that an emitter placed between two images moves onto one of them
before the next is placed. :func:`~sparseloc.solvers.frame_compose.likelier_per_region` then
keeps, region by region, the likelier arrangement (``docs/benchmarks/regrow.txt``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..psf.base import PSFModel
from .emitters import Emitters
from .frame import SINGLE_THRESHOLD, FrameFit
from .frame_compose import as_frame_fit, joined, subset
from .frame_windows import NeighbourLight, emitter_groups, region_window, window_box
from .mp import MIN_PHOTONS
from .refine import fit_with_count_selection, residual_candidates

__all__ = ["grown_groups"]


def grown_groups(
    frame: NDArray,
    background: NDArray,
    fit: FrameFit,
    model: PSFModel,
    *,
    pixel_size: float,
    group_distance: float,
    pad: int,
    reach: float,
    penalty: float,
    max_emitters: int,
    fit_kwargs: dict,
    fixed_light: NDArray | None = None,
) -> FrameFit | None:
    """``fit`` with each group of two or more of its emitters solved again from one emitter,
    or None where it has no such group (or none yields a start).

    Parameters
    ----------
    frame, background, model, pixel_size, pad, fit_kwargs, fixed_light
        As in :func:`~sparseloc.solvers.frame_compose.likelier_per_region`, which takes the
        same keywords to compose ``fit`` with this function's result.
    fit : FrameFit
        The frame's fit. Its groups are the frame solver's: emitters closer than
        ``group_distance`` (nm, laterally), split into parts of at most
        :data:`~sparseloc.solvers.frame_windows.MAX_GROUP`.
    group_distance : float
        Emitters closer than this (nm, laterally) form a group.
    reach : float
        Emitters farther than this (nm) from a window add no light to it.
    penalty : float
        The count selection's threshold (``2 log L`` per emitter); a lone emitter's removal
        uses :data:`~sparseloc.solvers.frame.SINGLE_THRESHOLD`.
    max_emitters : int
        Most emitters of a grown part, or its count and two more if larger (the frame
        solver's cap).

    Returns
    -------
    FrameFit or None
        Emitters in frame coordinates (some may lie off its pixels: the composition keeps
        only those on them); a grown part's emitters share its window's background and
        goodness of fit.
    """
    arr = fit.emitters.as_array().reshape(-1, 4)
    groups = [g for g in emitter_groups(arr[:, :2], group_distance) if len(g) > 1]
    if not groups:
        return None
    shape = np.shape(frame)
    light = NeighbourLight(model, shape, pixel_size)
    redone = np.zeros(len(arr), bool)
    grown: FrameFit | None = None
    for g in groups:
        box = window_box(arr[g], *shape, pixel_size, pad)
        rest = np.delete(arr, g, axis=0)
        y, kw = region_window(
            frame, background, box, light, rest, pixel_size, fit_kwargs, fixed_light, reach
        )
        known = kw["offset"] + kw["background"]
        first, _ = residual_candidates(
            y, known, model, pixel_size, kw["origin"], n_best=1, score=False
        )
        if not first:
            continue
        part = fit_with_count_selection(
            y,
            model,
            Emitters.from_array(np.asarray(first, dtype=np.float64)),
            lr_threshold=penalty,
            single_threshold=SINGLE_THRESHOLD,
            min_photons=MIN_PHOTONS,
            max_emitters=max(max_emitters, len(g) + 2),
            max_changes=3 * len(g) + 4,
            **kw,
        )
        redone[g] = True
        grown = as_frame_fit(part) if grown is None else joined(grown, as_frame_fit(part))
    if grown is None:
        return None
    return joined(subset(fit, ~redone), grown)
