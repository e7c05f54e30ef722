"""Convex recovery of a window (CO) and the paper's hybrid MP+CO.

Hybrid (Barsic et al. 2014, Fig. 2c-d): matching pursuit on a *coarse* dictionary gives the
count and rough positions; convex L1 recovery then runs on the *fine* dictionary restricted to
boxes around those positions (at least one coarse step each way), which keeps the fine problem
two orders of magnitude smaller than the full fine dictionary.

Stage 1 deliberately errs towards too many emitters (OMP, which refits jointly): a spurious
box costs a little time and the L1 stage gives it no photons, whereas a missed emitter has no
box for the fine stage to find it in.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike

from ..dictionary import DenseDictionary, Dictionary, check_window
from .convex import noise_epsilon, solve_constrained
from .emitters import Emitters, WindowSolution, group_by_boxes, group_coefficients
from .mp import estimate_background, matching_pursuit, pearson_chi2

log = logging.getLogger(__name__)

__all__ = ["convex_solve", "hybrid_solve"]


def _as_dense(dictionary: Dictionary | DenseDictionary) -> DenseDictionary:
    if isinstance(dictionary, DenseDictionary):
        return dictionary
    return dictionary.restrict(np.ones(dictionary.coef_shape, dtype=bool))


def convex_solve(
    window: ArrayLike,
    dictionary: Dictionary | DenseDictionary,
    *,
    background: float | None = None,
    eps: float | None = None,
    eps_factor: float = 1.0,
    min_photons: float = 200.0,
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
    min_photons: float = 200.0,
    max_emitters: int = 10,
    mp_chi2_sigma: float = 1.0,
    mp_min_photons: float | None = None,
    mp_min_snr: float = 3.0,
    mp_replace_sweeps: int = 2,
    chi2_sigma: float = 2.0,
    noise_factor: float = 1.0,
    max_rounds: int = 3,
    recentre: int = 1,
    link: float = 1.5,
) -> WindowSolution:
    """The hybrid MP+CO solver.

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
        Known background (photons/pixel); estimated when ``None``.
    box_steps : float
        Box half-width around each MP emitter in coarse grid steps (x, y and z).
    eps_factor : float
        Scale of the residual bound of the convex stage (see :func:`convex_solve`).
    min_photons : float
        Smallest emitter kept.
    max_emitters : int
        Cap on MP's count.
    mp_replace_sweeps : int
        Replacement sweeps of the MP stage (see ``matching_pursuit``).
    chi2_sigma, noise_factor : float
        Noise test of the fine fit (as in ``matching_pursuit``, with the fine dictionary's
        grid error). While the fine fit fails it, MP looks for one more emitter in its residual
        and the convex stage runs again, at most ``max_rounds`` times in all.
    max_rounds : int
        Cap on rounds that add an emitter.
    recentre : int
        Cap on re-solves with boxes re-centred on the convex estimates (stops early once no
        box centre moves by more than a quarter of its half-width).
    mp_chi2_sigma, mp_min_photons, mp_min_snr : float
        Stopping rule of the MP stage (see :func:`~sparseloc.solvers.mp.matching_pursuit`);
        looser than the final rule so that no emitter is missed.
    link : float
        Grouping distance in grid steps.

    Returns
    -------
    WindowSolution
        ``details``: ``mp`` (the MP stage's solution), ``box_centres`` (k, 3) nm,
        ``box_half_width`` (hx, hy, hz) nm, ``co`` details.
    """
    y = check_window(window, fine.shape)
    if tuple(coarse.shape) != tuple(fine.shape):
        raise ValueError(f"coarse {coarse.shape} and fine {fine.shape} windows differ")
    b0 = background if background is not None else estimate_background(y)
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
    )
    if len(mp.emitters) == 0:
        return WindowSolution(
            Emitters.empty(),
            mp.background,
            mp.model_image,
            "hybrid",
            {"mp": mp, "box_centres": np.zeros((0, 3))},
        )
    cs = coarse.grid if isinstance(coarse, Dictionary) else None
    dxy_c, dz_c = (cs.dxy, cs.dz) if cs is not None else coarse.steps
    half = (box_steps * dxy_c, box_steps * dxy_c, box_steps * dz_c)
    centres = mp.emitters.as_array()[:, :3]
    fine_error = fine.quantization_error
    n_pix = y.size
    chi2_limit = n_pix + chi2_sigma * np.sqrt(2.0 * n_pix)
    # The L1 objective does not penalise the background, so left free it soaks up light that
    # belongs to the emitters (photons come out ~20 % low). Unless the caller knows it, fix it
    # at the MP stage's least-squares estimate.
    b_fit = mp.background if background is None else background
    rounds = 0
    while True:
        rounds += 1
        mask = fine.box_mask(centres, half)
        sub = fine.restrict(mask)
        co = convex_solve(
            y, sub, background=b_fit, eps_factor=eps_factor, min_photons=0.0, link=link
        )
        # One emitter per box (the paper's blue boxes), not per connected group of fine atoms:
        # an L1 solution often spreads an off-grid emitter over atoms 50-100 nm apart.
        emitters = group_by_boxes(
            co.details["positions"], co.details["coef"], centres, half, min_photons=min_photons
        )
        # MP's coarse estimate is often more than one coarse step from the emitter, so the
        # convex estimate can sit on its box's wall: re-centre the boxes on the convex
        # estimates and solve again until they stop moving (at most ``recentre`` times).
        for _ in range(recentre):
            new_centres = emitters.as_array()[:, :3]
            if len(new_centres) == 0:
                break
            moved = _max_shift(new_centres, centres, half)
            centres = new_centres
            if moved < 0.25:
                break
            sub = fine.restrict(fine.box_mask(centres, half))
            co = convex_solve(
                y, sub, background=b_fit, eps_factor=eps_factor, min_photons=0.0, link=link
            )
            emitters = group_by_boxes(
                co.details["positions"], co.details["coef"], centres, half, min_photons=min_photons
            )
        # The convex fit always reaches the noise level (its residual norm is eps), so it
        # cannot tell whether an emitter is missing. A model of one point source per emitter
        # can: snap each emitter to its nearest fine atom and refit photons and background.
        signal, b_pt = _point_model(y, fine, emitters, b_fit)
        chi2 = pearson_chi2(y, signal + b_pt, noise_factor, signal, fine_error)
        if chi2 <= chi2_limit or rounds >= max_rounds or len(centres) >= max_emitters:
            break
        # Look for one more emitter in the residual of the point-source model.
        extra = matching_pursuit(
            y - signal,
            coarse,
            background=b_pt,
            orthogonal=True,
            max_emitters=1,
            min_photons=min_photons,
            chi2_sigma=chi2_sigma,
            min_snr=mp_min_snr,
            link=link,
            noise_factor=noise_factor,
        )
        if len(extra.emitters) == 0:
            break
        centres = np.vstack([centres, extra.emitters.as_array()[:1, :3]])
    co.emitters = emitters
    log.debug(
        "hybrid: MP %d emitters, %d rounds -> %d fine atoms -> %d emitters (b0 %.2f)",
        len(mp.emitters),
        rounds,
        sub.size,
        len(co.emitters),
        b0,
    )
    details = {
        "mp": mp,
        "box_centres": centres,
        "box_half_width": half,
        "co": co.details,
        "n_fine_atoms": sub.size,
        "rounds": rounds,
        "chi2": chi2,
        "chi2_limit": chi2_limit,
    }
    return WindowSolution(co.emitters, co.background, co.model_image, "hybrid", details)


def _point_model(
    y: np.ndarray, fine: Dictionary, emitters: Emitters, background: float | None
) -> tuple[np.ndarray, float]:
    """Image of one fine atom per emitter (nearest grid point), photons refitted by NNLS."""
    from scipy.optimize import nnls

    if len(emitters) == 0:
        b = float(np.mean(y)) if background is None else float(background)
        return np.zeros_like(y), b
    g = fine.grid
    ix = np.clip(np.rint((emitters.x - g.x[0]) / g.dxy).astype(int), 0, g.x.size - 1)
    iy = np.clip(np.rint((emitters.y - g.y[0]) / g.dxy).astype(int), 0, g.y.size - 1)
    iz = np.clip(np.rint((emitters.z - g.z[0]) / g.dz).astype(int), 0, g.z.size - 1)
    atoms = fine.atoms(np.ravel_multi_index((iz, iy, ix), fine.coef_shape))
    a = atoms.reshape(len(emitters), -1).T
    if background is None:
        x, _ = nnls(np.column_stack([a, np.ones(y.size)]), y.ravel())
        return (a @ x[:-1]).reshape(y.shape), float(x[-1])
    x, _ = nnls(a, (y - background).ravel())
    return (a @ x).reshape(y.shape), float(background)


def _max_shift(new: np.ndarray, old: np.ndarray, half: tuple[float, float, float]) -> float:
    """Largest move (in box half-widths) from each new centre to the nearest old one."""
    d = np.abs(new[:, None, :] - old[None, :, :]) / np.asarray(half)
    return float(d.max(axis=2).min(axis=1).max())
