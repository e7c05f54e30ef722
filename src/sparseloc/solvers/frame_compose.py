"""Two fits of one frame, from two starting points, made into one: the likelier per region.

The frame solver's fits only go uphill from their start, and in a crowd the pursuit's greedy
start can leave them in a wrong arrangement that the true one beats by far in likelihood (the
measurements are in ``docs/benchmarks/second_start.txt``). A second start from the L1
deconvolution (:mod:`sparseloc.solvers.frame_l1`) gets stuck elsewhere. Where the two fits
disagree, each region's two arrangements are refitted in the same window, with the same free
background and the light of every other emitter known, and the one with the larger
likelihood, less the count selection's threshold per emitter, is kept. Regions where only one
fit has emitters are left to that fit's count selection.

Each fit also holds true emitters the other missed, so together they hold more of a crowd
than either (``docs/benchmarks/union_start.txt``). So a region's third arrangement is the
union of its two, settled by the frame solver's count selection (which tests first the
emitter whose brightness the data determine least: one of two that share one image).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..psf.base import PSFModel
from .emitters import Emitters
from .frame import SINGLE_THRESHOLD, FrameFit
from .frame_windows import NeighbourLight, emitter_groups, inside, region_window, window_box
from .mle import FitResult, fit_emitters
from .mp import MIN_PHOTONS
from .refine import fit_with_count_selection

__all__ = [
    "REGION_MAX_ENTRIES",
    "UNION_MAX",
    "as_frame_fit",
    "crowded_boxes",
    "joined",
    "likelier_per_region",
    "same_as",
    "shifted",
    "subset",
]

#: Emitters of the two fits this close (nm, laterally and axially) are the same emitter. The
#: tolerance only saves work: an emitter both fits hold a little apart joins a region whose two
#: arrangements are refitted and compared like any other.
SAME_LATERAL, SAME_AXIAL = 20.0, 40.0
#: A region's union is settled only where it holds at most this many emitters: each of its
#: removals refits them all (seconds at this size), and where crowds percolate across a
#: frame (hundreds of emitters in one region) the region chooses between the two fits alone.
#: A bound on the cost, not a threshold of the result (``docs/benchmarks/union_start.txt``).
UNION_MAX = 64
#: A region is compared at all only where a joint fit of either arrangement has at most this
#: many Jacobian entries (4 per emitter plus one, times the window's pixels): the fit's state
#: holds several arrays of that size (about 130 MB each here). Beyond it (a wrong PSF's
#: hundreds of emitters over a whole frame: gigabytes and tens of minutes) the first fit
#: stays. A bound on the cost, not a threshold of the result.
REGION_MAX_ENTRIES = 2**24


def same_as(a: NDArray, b: NDArray, lateral: float, axial: float) -> NDArray[np.bool_]:
    """(len(a),): whether each emitter of ``a`` (K, 4+) has one of ``b`` within ``lateral`` nm
    laterally and ``axial`` nm axially."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    d = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    dz = np.abs(a[:, None, 2] - b[None, :, 2])
    return ((d <= lateral) & (dz <= axial)).any(axis=1)


def _regions(points: NDArray, distance: float) -> NDArray[np.intp]:
    """Labels of the points (K, 2+) linked by steps of at most ``distance`` (nm): the frame
    solver's grouping (:func:`~sparseloc.solvers.frame_windows.emitter_groups`) unsplit."""
    labels = np.zeros(len(points), dtype=np.intp)
    for k, members in enumerate(emitter_groups(points[:, :2], distance, max(len(points), 1))):
        labels[members] = k
    return labels


def crowded_boxes(
    fit: FrameFit, shape: tuple[int, int], pixel_size: float, margin: int
) -> list[tuple[int, int, int, int]]:
    """The parts of a frame where ``fit`` has groups of more than one emitter: each such
    group's pixels and ``margin`` more each way (r0, r1, c0, c1), overlapping parts merged.
    Where every emitter was fitted alone, a second start has no arrangement to find that the
    first missed (the count selection decided each emitter's presence)."""
    arr = fit.emitters.as_array().reshape(-1, 4)
    groups, counts = np.unique(fit.group, return_counts=True)
    boxes = [
        window_box(arr[fit.group == g], *shape, pixel_size, margin)
        for g, n in zip(groups, counts, strict=True)
        if n > 1
    ]
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    boxes[i] = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def shifted(fit: FrameFit, dx: float, dy: float) -> FrameFit:
    """``fit`` with its emitters moved by ``dx``, ``dy`` (nm): a crop's fit in the frame."""
    arr = fit.emitters.as_array().reshape(-1, 4).copy()
    arr[:, 0] += dx
    arr[:, 1] += dy
    return FrameFit(
        Emitters.from_array(arr), fit.sigma, fit.background, fit.gof, fit.flags, fit.group
    )


def subset(fit: FrameFit, keep: NDArray[np.bool_]) -> FrameFit:
    """The emitters ``keep`` of ``fit``."""
    arr = fit.emitters.as_array().reshape(-1, 4)
    return FrameFit(
        Emitters.from_array(arr[keep]),
        fit.sigma[keep],
        fit.background[keep],
        fit.gof[keep],
        fit.flags[keep],
        fit.group[keep],
    )


def joined(a: FrameFit, b: FrameFit) -> FrameFit:
    """The emitters of ``a`` then ``b``; ``b``'s groups numbered after ``a``'s."""
    g0 = int(a.group.max()) + 1 if len(a.group) else 0
    return FrameFit(
        Emitters.from_array(
            np.vstack([a.emitters.as_array().reshape(-1, 4), b.emitters.as_array().reshape(-1, 4)])
        ),
        np.vstack([a.sigma.reshape(-1, 4), b.sigma.reshape(-1, 4)]),
        np.concatenate([a.background, b.background]),
        np.concatenate([a.gof, b.gof]),
        np.concatenate([a.flags, b.flags]),
        np.concatenate([a.group, b.group + g0]),
    )


def likelier_per_region(
    frame: NDArray,
    background: NDArray,
    first: FrameFit,
    second: FrameFit,
    model: PSFModel,
    *,
    pixel_size: float,
    group_distance: float,
    pad: int,
    penalty: float,
    fit_kwargs: dict,
    fixed_light: NDArray | None = None,
) -> FrameFit:
    """One fit of the frame from two: ``first``, with each region where ``second`` places its
    emitters differently replaced by ``second``'s, or by the union of the two settled by the
    count selection, where that is likelier.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        The frame (photons).
    background : ndarray, shape (rows, cols)
        Its background (photons/pixel): each window fit's start.
    first, second : FrameFit
        Two fits of the frame.
    model : PSFModel
        The fits' PSF model.
    pixel_size : float
        Pixel size (nm).
    group_distance : float
        Emitters that only one fit has (within :data:`SAME_LATERAL` / :data:`SAME_AXIAL` nm)
        form regions of those closer than this (nm).
    pad : int
        Pixels around a region's emitters in its window.
    penalty : float
        ``2 log L`` an emitter must add to be worth it: the count selection's threshold (also
        the union's, with :data:`~sparseloc.solvers.frame.SINGLE_THRESHOLD` for a lone
        emitter).
    fit_kwargs : dict
        The likelihood's keywords of :func:`~sparseloc.solvers.mle.fit_emitters` (``noise``,
        ``qe``, ``read_variance``).
    fixed_light : ndarray, shape (rows, cols), optional
        Light known beside the two fits' emitters (photons/pixel), as in
        :func:`~sparseloc.solvers.frame.frame_fit`.

    Returns
    -------
    FrameFit
    """
    a = first.emitters.as_array().reshape(-1, 4)
    b = second.emitters.as_array().reshape(-1, 4)
    only_a = np.nonzero(~same_as(a, b, SAME_LATERAL, SAME_AXIAL))[0]
    only_b = np.nonzero(~same_as(b, a, SAME_LATERAL, SAME_AXIAL))[0]
    labels = _regions(np.vstack([a[only_a], b[only_b]]), group_distance)
    la, lb = labels[: len(only_a)], labels[len(only_a) :]
    use_a = np.ones(len(a), bool)
    use_b = np.zeros(len(b), bool)
    unions: list[FrameFit] = []
    light = NeighbourLight(model, np.shape(frame), pixel_size)
    for region in np.unique(labels):
        ea, eb = only_a[la == region], only_b[lb == region]
        if len(ea) == 0 or len(eb) == 0:
            continue
        box = window_box(np.vstack([a[ea], b[eb]]), *np.shape(frame), pixel_size, pad)
        r0, r1, c0, c1 = box
        if (4 * max(len(ea), len(eb)) + 1) * (r1 - r0) * (c1 - c0) > REGION_MAX_ENTRIES:
            continue  # too costly to compare: the first fit stays
        others = use_a.copy()
        others[ea] = False
        kept = [a[others], b[use_b]] + [u.emitters.as_array().reshape(-1, 4) for u in unions]
        y, kw = region_window(
            frame, background, box, light, np.vstack(kept), pixel_size, fit_kwargs, fixed_light
        )
        best, settled = _likeliest(y, model, a[ea], b[eb], kw, penalty)
        if best > 0:
            use_a[ea] = False
        if best == 1:
            use_b[eb] = True
        elif best == 2:
            unions.append(as_frame_fit(settled))
    out = joined(subset(first, use_a), subset(second, use_b))
    for u in unions:
        out = joined(out, u)
    # as the frame solver's fits, only emitters on the frame's (or crop's) pixels
    whole = (0, np.shape(frame)[0], 0, np.shape(frame)[1])
    return subset(out, inside(out.emitters.as_array().reshape(-1, 4), whole, pixel_size))


def _likeliest(
    y: NDArray, model: PSFModel, ea: NDArray, eb: NDArray, kw: dict, penalty: float
) -> tuple[int, FitResult | None]:
    """Which of a region's arrangements is likeliest, less ``penalty`` per emitter: 0 the
    first fit's ``ea`` (K, 4), 1 the second's ``eb``, 2 their union settled by the count
    selection (returned too; None where the union holds more than :data:`UNION_MAX`)."""
    union = np.vstack([ea, eb])
    scores = [
        2.0 * fit_emitters(y, model, Emitters.from_array(part), **kw).log_likelihood
        - penalty * len(part)
        for part in (ea, eb)
    ]
    if len(union) > UNION_MAX:
        return int(np.argmax(scores)), None
    settled = fit_with_count_selection(
        y,
        model,
        Emitters.from_array(union),
        lr_threshold=penalty,
        single_threshold=SINGLE_THRESHOLD,
        min_photons=MIN_PHOTONS,
        max_emitters=len(union) + 2,
        max_changes=len(union),
        **kw,
    )
    scores.append(2.0 * settled.log_likelihood - penalty * len(settled.emitters))
    return int(np.argmax(scores)), settled


def as_frame_fit(fit: FitResult) -> FrameFit:
    """A window fit's emitters as one group of a frame fit."""
    k = len(fit.emitters)
    return FrameFit(
        fit.emitters,
        np.asarray(fit.sigma).reshape(-1, 4),
        np.full(k, float(fit.background[0])),
        np.full(k, fit.deviance_per_dof),
        np.asarray(fit.flags),
        np.zeros(k, dtype=np.intp),
    )
