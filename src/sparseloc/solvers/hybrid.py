"""Convex recovery of a window (CO) and the paper's hybrid MP+CO.

Hybrid (Barsic et al. 2014, Fig. 2c-d): matching pursuit on a *coarse* dictionary gives the
count and rough positions; convex L1 recovery then runs on the *fine* dictionary restricted to
boxes around those positions (at least one coarse step each way), which keeps the fine problem
two orders of magnitude smaller than the full fine dictionary.

Stage 1 deliberately errs towards too many emitters (OMP, which refits jointly): a spurious
box costs a little time and the L1 stage gives it no photons, whereas a missed emitter has no
box for the fine stage to find it in.

The stages of :func:`hybrid_solve`:

1. Matching pursuit (OMP with replacement) on the coarse dictionary: count and rough
   positions.
2. Convex L1 recovery on the fine dictionary restricted to boxes of ``box_steps`` coarse
   steps each way around the MP positions; one emitter per box (weighted centre).
3. Point-source check: each emitter becomes its best single fine atom (:func:`polish`);
   while that model leaves more than noise, MP looks for one more emitter in its residual
   and step 2 runs again with a box around it; the larger model is kept if chi2 drops
   by more than ``add_delta_chi2`` (at most ``max_rounds`` solves).
4. Boxes re-centred on the estimates and step 2 repeated (``recentre`` times) when an
   estimate moved: MP's coarse position can be more than one coarse step off.
5. Insignificant emitters dropped (:func:`prune`, ``min_snr``).
6. With ``refine`` (default): maximum-likelihood fit of the emitters with the continuous
   PSF model, off the grid, and (``count_selection``) the likelihood-ratio test of one
   emitter fewer or more (:mod:`sparseloc.solvers.refine`), then (``search``) split,
   merge and exchange moves out of its local optimum
   (:func:`~sparseloc.solvers.refine.split_merge_search`).

With ``polish_fine`` the emitters are those of the point-source model (positions on the
fine grid); without it, the weighted centres of step 2 (the paper's conversion).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from ..dictionary import DenseDictionary, Dictionary, check_window
from .convex import noise_epsilon, solve_constrained
from .emitters import Emitters, WindowSolution, group_by_boxes, group_coefficients
from .mp import MIN_PHOTONS, matching_pursuit, pearson_chi2
from .polish import PointModel, nearest_atoms, polish, prune
from .refine import refine_solution
from .variance import noise_factor_of

log = logging.getLogger(__name__)

__all__ = ["convex_solve", "hybrid_solve"]


def _as_dense(dictionary: Dictionary | DenseDictionary) -> DenseDictionary:
    if isinstance(dictionary, DenseDictionary):
        return dictionary
    return dictionary.restrict(np.ones(dictionary.coef_shape, dtype=bool))


def _select(emitters: Emitters, ids: np.ndarray) -> Emitters:
    """The emitters ``ids`` (a point model's survivors), in their original order."""
    keep = np.sort(ids)
    return Emitters(emitters.x[keep], emitters.y[keep], emitters.z[keep], emitters.photons[keep])


def convex_solve(
    window: ArrayLike,
    dictionary: Dictionary | DenseDictionary,
    *,
    background: float | None = None,
    eps: float | None = None,
    eps_factor: float = 1.0,
    min_photons: float = MIN_PHOTONS,
    min_snr: float = 4.0,
    link: float = 1.5,
) -> WindowSolution:
    """Non-negative L1 recovery of one window (the paper's CO, constrained form).

    Solves ``min sum(x)  s.t.  ||y - D x - b||_2 <= eps, x >= 0, b >= 0`` and groups the
    non-zero coefficients into emitters.

    Parameters
    ----------
    window : ndarray, shape (rows, cols)
        Window in photons.
    dictionary : Dictionary or DenseDictionary
        Atoms (a structured dictionary is made dense: keep it small, e.g. the coarse one).
    background : float, optional
        Known background (photons/pixel); estimated when ``None``.
    eps : float, optional
        Residual bound (photons); default ``eps_factor * noise_epsilon(window)``, the expected
        norm of Poisson noise.
    min_photons : float
        Drop emitters with fewer photons.
    min_snr : float
        With a structured dictionary, drop emitters whose photons are less significant than
        this many standard errors (noise plus the grid's quantisation error); 0 disables.
    link : float
        Grouping distance in grid steps.
    """
    y = check_window(window, dictionary.shape)
    dense = _as_dense(dictionary)
    e = noise_epsilon(y, factor=eps_factor) if eps is None else float(eps)
    res = solve_constrained(dense.matrix, y.ravel(), e, background=background)
    steps = dense.steps if dense.steps is not None else (1.0, 1.0)
    emitters = group_coefficients(
        dense.atom_positions, res.coef, steps, link=link, min_photons=min_photons
    )
    if min_snr > 0 and isinstance(dictionary, Dictionary) and len(emitters):
        # Significance test of each emitter as a point source on this grid (the L1 solution
        # adds small groups to reach the noise level); report the survivors' weighted centres.
        point = PointModel(y, dictionary, nearest_atoms(dictionary, emitters), background)
        point = prune(
            point,
            min_snr=min_snr,
            min_photons=min_photons,
            model_error=dictionary.quantization_error,
        )
        emitters = _select(emitters, point.ids)
    model = dense.matvec(res.coef) + res.background
    support = res.support
    return WindowSolution(
        emitters=emitters,
        background=res.background,
        model_image=model,
        method="co",
        details={
            "index": support if dense.index is None else dense.index[support],
            "coef": res.coef[support],
            "positions": dense.atom_positions[support],
            "eps": e,
            "lam": res.lam,
            "converged": res.converged,
            "feasible": res.feasible,
            "n_atoms": dense.size,
        },
    )


def hybrid_solve(
    window: ArrayLike,
    coarse: Dictionary | DenseDictionary,
    fine: Dictionary,
    *,
    background: float | None = None,
    box_steps: float = 1.0,
    eps_factor: float = 1.0,
    min_photons: float = MIN_PHOTONS,
    min_snr: float = 4.0,
    max_emitters: int = 10,
    mp_chi2_sigma: float = 1.0,
    mp_min_photons: float | None = None,
    mp_min_snr: float = 3.0,
    mp_replace_sweeps: int = 2,
    chi2_sigma: float = 2.0,
    noise_factor: float = 1.0,
    max_rounds: int = 3,
    recentre: int = 1,
    add_delta_chi2: float = 18.5,
    polish_fine: bool = True,
    refine: bool = True,
    count_selection: bool = True,
    search: bool = True,
    noise: str = "poisson",
    read_variance: float | np.ndarray | None = None,
    plane: bool = False,
    link: float = 1.5,
    qe: float = 1.0,
) -> WindowSolution:
    """The hybrid MP+CO solver, with a continuous maximum-likelihood fit as its last stage.

    Its six stages (coarse MP, L1 in fine boxes, point-source rounds, re-centring, pruning,
    refinement) are listed in the module notes.

    Parameters
    ----------
    window : ndarray, shape (rows, cols)
        Window in photons.
    coarse : Dictionary or DenseDictionary
        Coarse dictionary for matching pursuit (the paper: 80 nm / 120 nm).
    fine : Dictionary
        Fine dictionary (the paper: 10 nm / 15 nm) covering the same window; only the atoms
        inside the boxes are used.
    background : float, optional
        Known background (photons/pixel). When ``None`` the MP stage estimates it (jointly
        with the atoms) and it is then held fixed: the L1 objective does not penalise the
        background, so left free it soaks up the emitters' light.
    box_steps : float
        Box half-width around each MP emitter in coarse grid steps (x, y and z).
    eps_factor : float
        Scale of the residual bound of the convex stage (see :func:`convex_solve`).
    min_photons, min_snr : float
        Smallest emitter kept, in photons and in standard errors of its photons.
    max_emitters : int
        Cap on the count.
    mp_chi2_sigma, mp_min_photons, mp_min_snr, mp_replace_sweeps
        Stopping rule and replacement sweeps of the MP stage (see ``matching_pursuit``); looser
        than the final rule so that no emitter is missed.
    chi2_sigma, noise_factor : float
        Noise test of the point-source model (as in ``matching_pursuit``, with the fine
        dictionary's grid error).
    max_rounds : int
        Cap on convex solves that try one more emitter.
    add_delta_chi2 : float
        A further emitter is kept only if it lowers Pearson's chi2 of the point-source model
        by more than this (default 18.5: the 0.1 % tail of a chi-square with 4 degrees of
        freedom, the new emitter's x, y, z and photons).
    recentre : int
        Cap on re-solves with boxes re-centred on the estimates.
    polish_fine : bool
        Report the point-source (polished) emitters rather than the L1 weighted centres.
    refine, count_selection, search : bool
        Run the maximum-likelihood stage, its count selection, and the split/merge search.
    noise, read_variance, plane, qe
        Likelihood and background model of the maximum-likelihood stage (see
        :func:`~sparseloc.solvers.mle.fit_emitters`). ``noise="emccd"`` also sets the
        sparse stages' ``noise_factor`` to 2 when it is left at 1.
    link : float
        Grouping distance in grid steps.

    Returns
    -------
    WindowSolution
        ``details``: ``mp`` (the MP stage's solution), ``box_centres`` (k, 3) nm,
        ``box_half_width`` (hx, hy, hz) nm, ``co`` (the last convex stage's details),
        ``centres_emitters`` (the weighted-centre emitters), ``rounds``, ``chi2``.
    """
    y = check_window(window, fine.shape)
    if y.ndim != 2:
        raise ValueError("hybrid_solve takes one window (rows, cols)")
    if noise_factor == 1.0:
        noise_factor = noise_factor_of(noise)
    if tuple(coarse.shape) != tuple(fine.shape):
        raise ValueError(f"coarse {coarse.shape} and fine {fine.shape} windows differ")
    mp = matching_pursuit(
        y,
        coarse,
        background=background,
        orthogonal=True,
        max_emitters=max_emitters,
        min_photons=min_photons / 2 if mp_min_photons is None else mp_min_photons,
        chi2_sigma=mp_chi2_sigma,
        min_snr=mp_min_snr,
        replace_sweeps=mp_replace_sweeps,
        link=link,
        noise_factor=noise_factor,
    )
    if len(mp.emitters) == 0:
        return _no_emitters(mp)
    half = _box_half_width(coarse, box_steps)
    stage = _FineStage(y, fine, half, background, eps_factor, link, noise_factor)
    chi2_limit = y.size + chi2_sigma * np.sqrt(2.0 * y.size)
    fit, b_fit, rounds = _add_emitters(
        stage, coarse, mp, chi2_limit, max_rounds, max_emitters, add_delta_chi2
    )
    fit = _recentre(stage, fit, b_fit, recentre, polish_fine)
    point = prune(
        fit.point,
        min_snr=min_snr,
        min_photons=min_photons,
        noise_factor=noise_factor,
        model_error=stage.fine_error,
    )
    sol = _sparse_solution(mp, stage, fit, point, polish_fine, rounds, chi2_limit)
    if refine and len(sol.emitters):
        sol = _refine(
            y,
            sol,
            fine,
            [fit.em, mp.emitters],
            count_selection=count_selection,
            search=search,
            noise=noise,
            read_variance=read_variance,
            plane=plane,
            qe=qe,
            max_emitters=max_emitters,
        )
    return sol


def _no_emitters(mp: WindowSolution) -> WindowSolution:
    """The hybrid's answer when the MP stage finds nothing: MP's background and model."""
    return WindowSolution(
        Emitters.empty(),
        mp.background,
        mp.model_image,
        "hybrid",
        {"mp": mp, "box_centres": np.zeros((0, 3))},
    )


def _box_half_width(
    coarse: Dictionary | DenseDictionary, box_steps: float
) -> tuple[float, float, float]:
    """Half-widths (x, y, z) nm of the fine boxes: ``box_steps`` coarse grid steps."""
    cs = coarse.grid if isinstance(coarse, Dictionary) else None
    dxy_c, dz_c = (cs.dxy, cs.dz) if cs is not None else coarse.steps
    return (box_steps * dxy_c, box_steps * dxy_c, box_steps * dz_c)


@dataclass
class _FineStage:
    """What every solve of the fine stage shares: the window, the fine dictionary, the box
    half-widths (nm), the known background (or ``None``) and the convex and chi2 settings."""

    y: np.ndarray
    fine: Dictionary
    half: tuple[float, float, float]
    background: float | None
    eps_factor: float
    link: float
    noise_factor: float
    fine_error: float = field(init=False)

    def __post_init__(self) -> None:
        self.fine_error = self.fine.quantization_error


class _BoxFit(NamedTuple):
    """One solve of the fine stage: boxes around ``centres`` (k, 3) nm, the convex solution,
    its one emitter per box, their point-source model, its chi2 and the fine atoms used."""

    centres: np.ndarray
    co: WindowSolution
    em: Emitters
    point: PointModel
    chi2: float
    n_sub: int


def _solve_boxes(stage: _FineStage, centres: np.ndarray, b_fit: float) -> _BoxFit:
    """Stages 2 and 3 once: L1 on the fine atoms inside the boxes, then the point sources."""
    y, fine = stage.y, stage.fine
    sub = fine.restrict(fine.box_mask(centres, stage.half))
    co = convex_solve(
        y, sub, background=b_fit, eps_factor=stage.eps_factor, min_photons=0.0, link=stage.link
    )
    em = group_by_boxes(
        co.details["positions"], co.details["coef"], centres, stage.half, min_photons=0.0
    )
    # the point-source model refits the background (unless it is known): it has one atom
    # per emitter, so the L1 bias does not apply
    point = polish(y, fine, em, stage.background)
    chi2 = pearson_chi2(
        y, point.signal + point.background, stage.noise_factor, point.signal, stage.fine_error
    )
    return _BoxFit(centres, co, em, point, chi2, sub.size)


def _add_emitters(
    stage: _FineStage,
    coarse: Dictionary | DenseDictionary,
    mp: WindowSolution,
    chi2_limit: float,
    max_rounds: int,
    max_emitters: int,
    add_delta_chi2: float,
) -> tuple[_BoxFit, float, int]:
    """Solve the boxes around the MP emitters, then try one more emitter while the model
    leaves more than noise. Returns the kept fit, the background held fixed, the solves."""
    b_fit = mp.background if stage.background is None else float(stage.background)
    fit = _solve_boxes(stage, mp.emitters.as_array()[:, :3], b_fit)
    if stage.background is None:
        b_fit = fit.point.background
    rounds = 1
    while fit.chi2 > chi2_limit and rounds < max_rounds and len(fit.centres) < max_emitters:
        # Try one more emitter where the residual correlates best with an atom, and keep the
        # larger model only if it lowers chi2 by more than ``add_delta_chi2`` (a
        # likelihood-ratio-like test: 4 more parameters). No size threshold on the candidate:
        # when two emitters were merged, the residual of the third is partly negative and its
        # best atom looks small.
        point = fit.point
        cand = _best_residual_atom(stage.y - point.signal - point.background, coarse)
        if cand is None:
            break
        trial = _solve_boxes(stage, np.vstack([point.emitters().as_array()[:, :3], cand]), b_fit)
        rounds += 1
        if fit.chi2 - trial.chi2 <= add_delta_chi2:
            break
        fit = trial
        if stage.background is None:
            b_fit = fit.point.background
    return fit, b_fit, rounds


def _recentre(
    stage: _FineStage, fit: _BoxFit, b_fit: float, recentre: int, polish_fine: bool
) -> _BoxFit:
    """Stage 4: solve again with the boxes on the estimates while one moved by a quarter of
    a box or more (at most ``recentre`` times)."""
    for _ in range(recentre):
        new = (fit.point.emitters() if polish_fine else fit.em).as_array()[:, :3]
        if len(new) == 0 or _max_shift(new, fit.centres, stage.half) < 0.25:
            break
        fit = _solve_boxes(stage, new, b_fit)
    return fit


def _sparse_solution(
    mp: WindowSolution,
    stage: _FineStage,
    fit: _BoxFit,
    point: PointModel,
    polish_fine: bool,
    rounds: int,
    chi2_limit: float,
) -> WindowSolution:
    """The sparse stages' solution: the pruned point sources (``polish_fine``) or the
    weighted centres of their boxes."""
    if polish_fine:
        emitters = point.emitters()
        model_image = point.signal + point.background
        b_out = point.background
    else:
        emitters = _select(fit.em, point.ids)
        model_image, b_out = fit.co.model_image, fit.co.background
    log.debug(
        "hybrid: MP %d -> %d rounds -> %d fine atoms -> %d emitters",
        len(mp.emitters),
        rounds,
        fit.n_sub,
        len(emitters),
    )
    details = {
        "mp": mp,
        "box_centres": fit.centres,
        "box_half_width": stage.half,
        "co": fit.co.details,
        "centres_emitters": fit.em,
        "n_fine_atoms": fit.n_sub,
        "rounds": rounds,
        "chi2": fit.chi2,
        "chi2_limit": chi2_limit,
    }
    return WindowSolution(emitters, b_out, model_image, "hybrid", details)


def _refine(
    y: np.ndarray,
    sol: WindowSolution,
    fine: Dictionary,
    others: list[Emitters],
    **kwargs: Any,
) -> WindowSolution:
    """Stage 6: maximum-likelihood refinement with the continuous PSF model; ``kwargs`` go
    to :func:`~sparseloc.solvers.refine.refine_solution`."""
    # other estimates of the same emitters (L1 weighted centres, MP) as extra starting
    # points: the likelihood of overlapping PSFs has local optima
    alts = [e for e in others if len(e) == len(sol.emitters)]
    return refine_solution(
        y,
        sol,
        fine.model,
        pixel_size=fine.pixel_size,
        origin=fine.origin,
        extra_starts=alts,
        **kwargs,
    )


def _best_residual_atom(resid: np.ndarray, coarse: Dictionary | DenseDictionary):
    """Position (x, y, z) of the coarse atom best correlated with a residual (None if none)."""
    corr = np.asarray(coarse.rmatvec(resid)).ravel()
    norms = np.asarray(coarse.norms).ravel()
    ok = norms >= 0.3 * norms.max()
    score = np.where(ok, corr / np.where(ok, norms, 1.0), -np.inf)
    k = int(np.argmax(score))
    if not np.isfinite(score[k]) or score[k] <= 0:
        return None
    return coarse.positions([k])[0]


def _max_shift(new: np.ndarray, old: np.ndarray, half: tuple[float, float, float]) -> float:
    """Largest move (in box half-widths) from each new centre to the nearest old one."""
    d = np.abs(new[:, None, :] - old[None, :, :]) / np.asarray(half)
    return float(d.max(axis=2).min(axis=1).max())
