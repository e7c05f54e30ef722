"""Non-negative matching pursuit (MP) and its orthogonal variant (OMP) over a PSF dictionary.

Stopping rule (in the order checked at every iteration):

1. ``max_emitters`` atoms selected (a cap the user sets from the window size);
2. the residual is consistent with noise: Pearson's statistic
   ``chi2 = sum((y - model)^2 / var)`` with ``var = noise_factor * max(model, 1) +
   (model_error * signal)^2`` is at most ``N + chi2_sigma * sqrt(2 N)`` for N pixels (the model
   explains the window to within ``chi2_sigma`` standard deviations of a chi-square with N
   degrees of freedom). ``model_error`` is the dictionary's relative grid error
   (:attr:`~sparseloc.dictionary.Dictionary.quantization_error`): on a coarse grid an
   emitter between grid points leaves a residual that is not a new emitter;
3. the best next atom would carry fewer than ``min_photons`` photons, or fewer than
   ``min_snr`` times its own standard error (computed with the same variance as above, so an
   atom that only explains the grid mismatch of a brighter neighbour is not a new emitter).

``noise_factor`` is 1 for Poisson (and sCMOS after offset/gain correction) and 2 for EMCCD
(excess noise doubles the variance).

Background: unless given, the constant background is fitted jointly with every atom. MP scores
atoms by their correlation with the mean-removed residual divided by their mean-removed norm
(exactly the least-squares gain of adding the atom *and* re-fitting the constant), and the
background is ``mean(y - atoms)`` after every step. OMP refits atoms and background by
non-negative least squares.
"""

from __future__ import annotations

import logging
from collections.abc import Generator
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls

from ..dictionary import check_window
from .emitters import MIN_LINK_NM, WindowSolution, group_coefficients
from .variance import pixel_variance

log = logging.getLogger(__name__)

#: Photons of the faintest emitter the solvers report (and of the faintest atom a pursuit adds):
#: the default ``min_photons`` of every solver.
MIN_PHOTONS = 200.0

__all__ = [
    "MIN_PHOTONS",
    "AtomDictionary",
    "check_rule",
    "count_groups",
    "estimate_background",
    "grid_steps",
    "matching_pursuit",
    "pearson_chi2",
    "pursuit_steps",
    "refit_amplitudes",
    "rule_defaults",
    "score_scale",
]


class AtomDictionary(Protocol):
    """What MP needs from a dictionary (``Dictionary`` and ``DenseDictionary`` both have it)."""

    shape: tuple[int, int]

    @property
    def size(self) -> int: ...

    @property
    def norms(self) -> NDArray[np.float64]: ...

    def rmatvec(self, image: ArrayLike) -> NDArray[np.float64]: ...

    def atoms(self, index: ArrayLike) -> NDArray[np.float64]: ...

    def positions(self, index: ArrayLike) -> NDArray[np.float64]: ...


def estimate_background(window: ArrayLike, percentile: float = 25.0) -> float:
    """Robust first guess of a window's background (photons/pixel): a low percentile.

    Molecules only add light, so the darker pixels are mostly background.
    """
    return float(max(np.percentile(np.asarray(window, dtype=np.float64), percentile), 0.0))


def pearson_chi2(
    window: NDArray,
    model: NDArray,
    noise_factor: float = 1.0,
    signal: NDArray | None = None,
    model_error: float = 0.0,
) -> float:
    """Pearson's statistic ``sum((y - mu)^2 / var)`` of a fit.

    ``var = noise_factor * max(mu, 1) + (model_error * signal)^2``: Poisson-like noise plus a
    relative model error on the emitters' part of the model (``signal``, photons/pixel).
    """
    var = pixel_variance(model, noise_factor, signal, model_error)
    return float(np.sum((window - model) ** 2 / var))


def grid_steps(dictionary: AtomDictionary) -> tuple[float, float]:
    """The dictionary's grid steps ``(dxy, dz)`` in nm."""
    grid = getattr(dictionary, "grid", None)
    if grid is not None:
        return grid.dxy, grid.dz
    steps = getattr(dictionary, "steps", None)
    if steps is None:
        raise ValueError("the dictionary does not say its grid steps (dxy, dz)")
    return steps


def score_scale(
    norms: NDArray[np.float64],
    sums: NDArray[np.float64] | None,
    n_pix: int,
    min_norm_fraction: float,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Which atoms may be selected, and ``inv``, the factor that turns their correlations
    into scores.

    ``inv`` is 1 / the norm of the atom, mean-removed when ``sums`` (the atoms' pixel sums)
    is given (fitted background); 0 for atoms below ``min_norm_fraction`` of the largest
    norm, or of no norm once centred.
    """
    if sums is not None:
        eff = np.sqrt(np.maximum(norms**2 - sums**2 / n_pix, 0.0))
    else:
        eff = norms
    eligible = (norms >= min_norm_fraction * norms.max()) & (eff > 1e-12)
    return eligible, np.where(eligible, 1.0 / np.where(eligible, eff, 1.0), 0.0)


def check_rule(
    max_emitters: int, min_photons: float, chi2_sigma: float, noise_factor: float
) -> None:
    """Refuse a stopping rule that cannot work: no emitters, negative limits or noise."""
    if max_emitters < 1:
        raise ValueError(f"max_emitters must be >= 1, got {max_emitters}")
    if min_photons < 0 or chi2_sigma < 0 or noise_factor <= 0:
        raise ValueError("min_photons and chi2_sigma must be >= 0 and noise_factor > 0")


def rule_defaults(
    dictionary: AtomDictionary, max_emitters: int, max_iter: int | None, model_error: float | None
) -> tuple[int, float]:
    """``max_iter`` (default 4 per emitter) and ``model_error`` (default the dictionary's
    grid error)."""
    max_iter = 4 * max_emitters if max_iter is None else int(max_iter)
    if model_error is None:
        model_error = float(getattr(dictionary, "quantization_error", 0.0))
    return max_iter, model_error


def matching_pursuit(
    window: ArrayLike,
    dictionary: AtomDictionary,
    *,
    background: float | None = None,
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
) -> WindowSolution:
    """Find the emitters in one window by non-negative matching pursuit.

    Parameters
    ----------
    window : ndarray, shape (rows, cols)
        The window in photons (offset and gain already removed).
    dictionary : Dictionary or DenseDictionary
        Atoms: unit-photon PSF images on a 3D grid.
    background : float, optional
        Known background (photons/pixel). ``None``: fitted jointly (see the module notes).
    orthogonal : bool
        OMP: after each selection, refit all kept atoms and the background jointly
        (non-negative least squares).
    max_emitters : int
        Stop after this many distinct emitters.
    min_photons : float
        Stop when the next atom would carry fewer photons; also the smallest emitter kept.
    chi2_sigma : float
        Noise-aware stop: see the module notes.
    noise_factor : float
        Variance per expected photon: 1 (Poisson, sCMOS) or 2 (EMCCD).
    model_error : float, optional
        Relative model error in the noise test; default the dictionary's
        ``quantization_error`` (0 if it has none).
    min_snr : float
        A new atom must carry at least this many standard errors of photons.
    replace_sweeps : int
        After each new atom (OMP only), this many sweeps that take every kept atom out in turn,
        choose the best atom for the residual of the others and refit ("OMP with
        replacement"). Greedy selection puts the first atom between overlapping emitters; the
        sweeps move it back onto one of them.
    max_iter : int, optional
        Hard cap on atom selections (default ``4 * max_emitters``).
    min_norm_fraction : float
        Atoms whose norm is below this fraction of the largest (mostly outside the window) are
        never selected: their normalised correlation is unreliable.
    link : float
        Grouping distance in grid steps (see :func:`group_coefficients`).

    Returns
    -------
    WindowSolution
        ``details`` holds ``index`` and ``coef`` of the selected atoms, ``stop`` (the reason),
        ``chi2``, ``chi2_limit`` and ``n_iter``.
    """
    y = check_window(window, dictionary.shape)
    if y.ndim != 2:
        raise ValueError("matching_pursuit takes one window (rows, cols)")
    check_rule(max_emitters, min_photons, chi2_sigma, noise_factor)
    max_iter, model_error = rule_defaults(dictionary, max_emitters, max_iter, model_error)
    norms = np.asarray(dictionary.norms).ravel()
    sums = None if background is not None else np.asarray(dictionary.sums).ravel()
    _, inv = score_scale(norms, sums, y.size, min_norm_fraction)
    steps = pursuit_steps(
        y,
        dictionary,
        inv,
        background=background,
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
        steps=grid_steps(dictionary),
    )
    try:
        resid, _ = next(steps)
        while True:
            corr = np.asarray(dictionary.rmatvec(resid)).ravel()
            if sums is not None:
                corr = corr - resid.mean() * sums
            score = corr * inv
            k = int(np.argmax(score))
            resid, _ = steps.send((k, float(corr[k]), float(score[k])))
    except StopIteration as done:
        sol = done.value
    log.debug(
        "MP: %d atoms, %d emitters, stop=%s",
        sol.details["index"].size,
        len(sol.emitters),
        sol.details["stop"],
    )
    return sol


def count_groups(
    positions: ArrayLike, coef: ArrayLike, steps: tuple[float, float], *, link: float = 1.5
) -> int:
    """``len(group_coefficients(positions, coef, steps, link=link))``, without the emitters.

    The same neighbour relation (``|dx|, |dy| <= max(link * dxy, MIN_LINK_NM[0])``,
    ``|dz| <= max(link * dz, MIN_LINK_NM[1])``, atoms with ``coef > 0``) and its connected
    components, counted by a plain graph search (no sparse matrices: MP asks after every atom).

    Parameters
    ----------
    positions : ndarray, shape (k, 3)
        Atom positions (x, y, z) in nm.
    coef : ndarray, shape (k,)
        Coefficients in photons.
    steps : (dxy, dz)
        Grid steps in nm.
    link : float
        Neighbour distance in grid steps.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(coef, dtype=np.float64).ravel()
    pos = pos[c > 0]
    n = pos.shape[0]
    if n <= 1:
        return n
    lxy = max(link * steps[0], MIN_LINK_NM[0])
    lz = max(link * steps[1], MIN_LINK_NM[1])
    d = np.abs(pos[:, None, :] - pos[None, :, :])
    adj = (d[..., 0] <= lxy + 1e-9) & (d[..., 1] <= lxy + 1e-9) & (d[..., 2] <= lz + 1e-9)
    seen = np.zeros(n, dtype=bool)
    groups = 0
    for i in range(n):
        if seen[i]:
            continue
        groups += 1
        seen[i] = True
        stack = [i]
        while stack:
            nb = np.flatnonzero(adj[stack.pop()] & ~seen)
            seen[nb] = True
            stack.extend(nb.tolist())
    return groups


Request = tuple[NDArray[np.float64], bool]
Answer = tuple[int, float, float]


def pursuit_steps(
    y: NDArray[np.float64],
    dictionary: AtomDictionary,
    inv: NDArray[np.float64],
    *,
    background: float | None,
    orthogonal: bool,
    max_emitters: int,
    min_photons: float,
    chi2_sigma: float,
    noise_factor: float,
    model_error: float,
    min_snr: float,
    replace_sweeps: int,
    max_iter: int,
    link: float,
    steps: tuple[float, float],
) -> Generator[Request, Answer, WindowSolution]:
    """The pursuit's rule for one window, step by step: it yields each residual whose best atom
    it needs (with ``True`` where the exact ``numpy.argmax`` semantics matter) and is sent
    ``(index, corr, score)`` of that atom; it returns the window's solution.

    :func:`matching_pursuit` answers with the dictionary's correlations,
    :func:`~sparseloc.solvers.fast_mp.matching_pursuit_batch` with a batched search over many
    windows. ``inv`` (one per atom) is the reciprocal of the atom's norm (mean-removed when the
    background is fitted), 0 for atoms never to be chosen; the other parameters are those of
    :func:`matching_pursuit`."""
    fixed_bg = background is not None
    n_pix = y.size
    centred_scores = not fixed_bg
    b = float(background) if fixed_bg else float(max(y.mean(), 0.0))
    chi2_limit = n_pix + chi2_sigma * np.sqrt(2.0 * n_pix)
    index: list[int] = []
    coef: list[float] = []
    atoms: list[NDArray] = []
    fit = np.zeros_like(y)
    stop = "max_iter"
    n_iter = 0
    for n_iter in range(1, max_iter + 1):  # noqa: B007 - n_iter is reported
        chi2 = pearson_chi2(y, fit + b, noise_factor, fit, model_error)
        if chi2 <= chi2_limit:
            stop = "noise"
            break
        resid = y - fit - b
        k, corr_k, score_k = yield resid, False
        if not score_k > 0:
            stop = "no positive correlation"
            break
        amp = corr_k * inv[k] ** 2
        if amp < min_photons:
            stop = "min_photons"
            break
        atom = dictionary.atoms([k])[0]
        var = pixel_variance(fit + b, noise_factor, fit, model_error)
        centred = atom - atom.mean() if centred_scores else atom
        sigma = np.sqrt(np.sum(centred**2 * var)) * inv[k] ** 2
        if amp < min_snr * sigma:
            stop = "min_snr"
            break
        if k in index:
            coef[index.index(k)] += amp
        else:
            index.append(k)
            coef.append(amp)
            atoms.append(atom)
        if orthogonal:
            coef, b = refit_amplitudes(y, atoms, b, fixed_bg)
            for _ in range(replace_sweeps if len(index) > 1 else 0):
                changed = False
                for j in range(len(index)):
                    others = [i for i in range(len(index)) if i != j]
                    part = np.tensordot(
                        np.asarray(coef)[others], np.asarray(atoms)[others], axes=(0, 0)
                    )
                    r = y - part - b
                    kj, _, _ = yield r, True
                    if kj != index[j] and kj not in index:
                        index[j] = kj
                        atoms[j] = dictionary.atoms([kj])[0]
                        changed = True
                coef, b = refit_amplitudes(y, atoms, b, fixed_bg)
                if not changed:
                    break
            fit = np.tensordot(np.asarray(coef), np.asarray(atoms), axes=(0, 0))
        else:
            fit = fit + amp * atom
            if not fixed_bg:
                b = float(max(np.mean(y - fit), 0.0))
        n_emit = count_groups(dictionary.positions(index), coef, steps, link=link)
        if n_emit >= max_emitters:
            stop = "max_emitters"
            break
    idx = np.asarray(index, dtype=np.int64)
    cf = np.asarray(coef, dtype=np.float64)
    keep = cf > 0
    idx, cf = idx[keep], cf[keep]
    emitters = group_coefficients(
        dictionary.positions(idx) if idx.size else np.zeros((0, 3)),
        cf,
        steps,
        link=link,
        min_photons=min_photons,
    )
    model = fit + b
    return WindowSolution(
        emitters=emitters,
        background=b,
        model_image=model,
        method="omp" if orthogonal else "mp",
        details={
            "index": idx,
            "coef": cf,
            "stop": stop,
            "n_iter": n_iter,
            "chi2": pearson_chi2(y, model, noise_factor, fit, model_error),
            "chi2_limit": chi2_limit,
            "model_error": model_error,
        },
    )


def refit_amplitudes(
    y: NDArray, atoms: list[NDArray], b: float, fixed_bg: bool
) -> tuple[list[float], float]:
    """Non-negative least squares of the kept atoms (and the background unless fixed)."""
    a = np.asarray(atoms).reshape(len(atoms), -1).T
    if fixed_bg:
        x, _ = nnls(a, (y - b).ravel())
        return list(x), b
    x, _ = nnls(np.column_stack([a, np.ones(y.size)]), y.ravel())
    return list(x[:-1]), float(x[-1])
