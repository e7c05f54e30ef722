"""Fast matching pursuit with the dense reference's selections (certified argmax).

:func:`matching_pursuit_batch` runs MP (or OMP) over many windows in lockstep, one batched
search per iteration, with exactly the stopping rule of
:func:`sparseloc.solvers.mp.matching_pursuit`; its selections (atom indices in order and the
stopping decision) are those of that function over the dense float64 matrix of the same
dictionary (:class:`~sparseloc.dictionary.DenseDictionary`), up to floating-point ties.

The search is :class:`~sparseloc.solvers.atom_search.AtomSearch` (branch and bound over
polynomial models of atom clusters: see :mod:`sparseloc.solvers.atom_search`) for a structured
:class:`~sparseloc.dictionary.Dictionary`, else :class:`ReferenceSearch` (every correlation).
The search runs on NumPy by default; ``device="cpu"`` or ``"cuda"`` runs its bulk on PyTorch.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Generator, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..dictionary import Dictionary, check_window
from .atom_search import CLUSTER_SPAN_NM as CLUSTER_SPAN_NM  # re-exported
from .atom_search import AtomSearch
from .emitters import WindowSolution
from .mp import (
    MIN_PHOTONS,
    Answer,
    AtomDictionary,
    Request,
    check_rule,
    count_groups,
    grid_steps,
    pursuit_steps,
    rule_defaults,
    score_scale,
)

log = logging.getLogger(__name__)

__all__ = [
    "AtomSearch",
    "ReferenceSearch",
    "count_groups",
    "get_search",
    "matching_pursuit_batch",
]

_CACHE: weakref.WeakKeyDictionary[Any, dict[tuple, AtomSearch]] = weakref.WeakKeyDictionary()


class ReferenceSearch:
    """The reference argmax: every correlation via ``dictionary.rmatvec``, as ``matching_pursuit``.

    With a :class:`~sparseloc.dictionary.DenseDictionary` this is the dense float64 ``D^T r``
    reference. Same interface as :class:`AtomSearch`.
    """

    def __init__(
        self,
        dictionary: AtomDictionary,
        *,
        fit_background: bool = True,
        min_norm_fraction: float = 0.3,
    ) -> None:
        self.dictionary = dictionary
        self.centered = bool(fit_background)
        self.n_pix = dictionary.shape[0] * dictionary.shape[1]
        norms = np.asarray(dictionary.norms).ravel()
        self.sums = np.asarray(dictionary.sums).ravel() if self.centered else None
        _, self.inv = score_scale(norms, self.sums, self.n_pix, min_norm_fraction)

    def argmax(
        self, residuals: ArrayLike, *, device: str | None = None
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """``numpy.argmax(corr * inv)`` for each residual (B, rows, cols): index, corr, score."""
        r = np.asarray(residuals, dtype=np.float64).reshape(-1, *self.dictionary.shape)
        out = (np.empty(len(r), dtype=np.int64), np.empty(len(r)), np.empty(len(r)))
        for b, rb in enumerate(r):
            corr = np.asarray(self.dictionary.rmatvec(rb)).ravel()
            if self.sums is not None:
                corr = corr - rb.mean() * self.sums
            score = corr * self.inv
            k = int(np.argmax(score))
            out[0][b], out[1][b], out[2][b] = k, corr[k], score[k]
        return out

    best = argmax


def get_search(
    dictionary: AtomDictionary,
    *,
    fit_background: bool = True,
    min_norm_fraction: float = 0.3,
    **kwargs: Any,
) -> AtomSearch | ReferenceSearch:
    """The search for a dictionary: a cached :class:`AtomSearch` for a structured
    :class:`Dictionary`, else a :class:`ReferenceSearch` (dense or any ``rmatvec``).

    ``kwargs`` go to :class:`AtomSearch` (``block``, ``degrees``, ...).
    """
    if not isinstance(dictionary, Dictionary):
        return ReferenceSearch(
            dictionary, fit_background=fit_background, min_norm_fraction=min_norm_fraction
        )
    key = (bool(fit_background), float(min_norm_fraction), tuple(sorted(kwargs.items())))
    per = _CACHE.setdefault(dictionary, {})
    if key not in per:
        per[key] = AtomSearch(
            dictionary,
            fit_background=fit_background,
            min_norm_fraction=min_norm_fraction,
            **kwargs,
        )
    return per[key]


def matching_pursuit_batch(
    windows: ArrayLike,
    dictionary: AtomDictionary,
    *,
    background: float | ArrayLike | None = None,
    orthogonal: bool = False,
    max_emitters: int = 10,
    min_photons: float = MIN_PHOTONS,
    chi2_sigma: float = 2.0,
    noise_factor: float = 1.0,
    model_error: float | None = None,
    min_snr: float = 4.0,
    replace_sweeps: int = 0,
    max_iter: int | None = None,
    min_norm_fraction: float = 0.3,
    link: float = 1.5,
    device: str | None = None,
    search: AtomSearch | ReferenceSearch | None = None,
) -> list[WindowSolution]:
    """Matching pursuit (or OMP) on many windows at once, with the dense reference's selections.

    Same parameters and results as :func:`~sparseloc.solvers.mp.matching_pursuit` applied to
    each window, except that the atoms' norms and sums are computed as a dense float64 matrix
    would give them, so the selected atoms (indices, in order) and the stopping decision are
    those of ``matching_pursuit`` with the dictionary's
    :class:`~sparseloc.dictionary.DenseDictionary` (up to exact floating-point ties). The
    windows advance in lockstep: each iteration searches all pending residuals in one batch
    (:class:`AtomSearch`).

    Parameters
    ----------
    windows : ndarray, shape (n, rows, cols) or (rows, cols)
        Windows in photons (offset and gain removed).
    dictionary : Dictionary or DenseDictionary
        A structured :class:`~sparseloc.dictionary.Dictionary` gets the fast search; any other
        dictionary the reference search (``rmatvec`` of every atom).
    background : float or array of shape (n,), optional
        Known background (photons/pixel), one for all windows or one per window; ``None``:
        fitted jointly.
    orthogonal, max_emitters, min_photons, chi2_sigma, noise_factor, model_error, min_snr, \
replace_sweeps, max_iter, min_norm_fraction, link
        As in :func:`~sparseloc.solvers.mp.matching_pursuit`.
    device : str, optional
        ``None`` (NumPy), or a PyTorch device (``"cpu"``, ``"cuda"``) for the search.
    search : AtomSearch or ReferenceSearch, optional
        A prepared search (default: :func:`get_search`, cached per dictionary).

    Returns
    -------
    list of WindowSolution
        One per window, as ``matching_pursuit`` returns them.
    """
    ys = _as_batch(windows, dictionary)
    check_rule(max_emitters, min_photons, chi2_sigma, noise_factor)
    max_iter, model_error = rule_defaults(dictionary, max_emitters, max_iter, model_error)
    bgs = _backgrounds(background, ys.shape[0])
    search = _checked_search(search, dictionary, background is None, min_norm_fraction)
    steps = grid_steps(dictionary)
    gens = [
        pursuit_steps(
            ys[i],
            dictionary,
            search.inv,
            background=bgs[i],
            orthogonal=orthogonal,
            max_emitters=max_emitters,
            min_photons=min_photons,
            chi2_sigma=chi2_sigma,
            noise_factor=noise_factor,
            model_error=model_error,
            min_snr=min_snr,
            replace_sweeps=replace_sweeps,
            max_iter=max_iter,
            link=link,
            steps=steps,
        )
        for i in range(ys.shape[0])
    ]
    return _lockstep(gens, search, device)


def _as_batch(windows: ArrayLike, dictionary: AtomDictionary) -> NDArray[np.float64]:
    """The windows, checked, as a batch (n, rows, cols)."""
    ys = check_window(windows, dictionary.shape)
    return ys[None] if ys.ndim == 2 else ys


def _backgrounds(background: float | ArrayLike | None, n: int) -> Sequence[float | None]:
    """One known background per window (``None``: fitted)."""
    if background is None:
        return [None] * n
    arr = np.broadcast_to(np.asarray(background, dtype=np.float64), (n,))
    return [float(v) for v in arr]


def _checked_search(
    search: AtomSearch | ReferenceSearch | None,
    dictionary: AtomDictionary,
    fit_bg: bool,
    min_norm_fraction: float,
) -> AtomSearch | ReferenceSearch:
    """The given search, checked against the background mode, or the cached one."""
    if search is None:
        return get_search(dictionary, fit_background=fit_bg, min_norm_fraction=min_norm_fraction)
    if search.centered != fit_bg:
        raise ValueError("the search's background mode does not match `background`")
    return search


def _lockstep(
    gens: list[Generator[Request, Answer, WindowSolution]],
    search: AtomSearch | ReferenceSearch,
    device: str | None,
) -> list[WindowSolution]:
    """Run the windows' pursuits together: each round answers every pending request with
    one batched search (the exact argmax where a strict request's best score is not > 0)."""
    n = len(gens)
    results: list[WindowSolution | None] = [None] * n
    pending: dict[int, Request] = {}
    for i, gen in enumerate(gens):
        _advance(gen, None, i, pending, results)
    while pending:
        ids = list(pending)
        strict = np.array([pending[i][1] for i in ids])
        resid = np.stack([pending[i][0] for i in ids])
        idx, corr, score = search.best(resid, device=device)
        if strict.any():
            sel = np.flatnonzero(strict & ~(score > 0))
            if sel.size:
                i2, c2, s2 = search.argmax(resid[sel], device=device)
                idx[sel], corr[sel], score[sel] = i2, c2, s2
        for j, i in enumerate(ids):
            answer = (int(idx[j]), float(corr[j]), float(score[j]))
            _advance(gens[i], answer, i, pending, results)
    log.debug("MP batch: %d windows", n)
    return [r for r in results if r is not None]


def _advance(
    gen: Generator[Request, Answer, WindowSolution],
    answer: Answer | None,
    i: int,
    pending: dict[int, Request],
    results: list[WindowSolution | None],
) -> None:
    try:
        pending[i] = gen.send(answer) if answer is not None else next(gen)
    except StopIteration as done:
        pending.pop(i, None)
        results[i] = done.value
