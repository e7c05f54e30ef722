"""Point-source refinement of sparse solutions on a dictionary's grid.

A sparse solution (MP or L1) turns into emitters by grouping its atoms (weighted centres). Two
steps then make those emitters a *point-source* model: one atom per emitter.

- :func:`polish`: each emitter in turn moves to the atom near it that best explains what the
  other emitters and the background leave (largest least-squares gain), then all photons and
  the background are refitted by non-negative least squares; a few sweeps. This is a discrete
  least-squares fit on the grid (on the paper's fine grid, 10 nm / 15 nm).
- :func:`prune`: drop, one at a time, the emitter whose photons are least significant while it
  carries fewer than ``min_snr`` standard errors, where the variance counts the noise and the
  dictionary's grid error (as in the matching-pursuit stopping rule).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import nnls

from ..dictionary import Dictionary
from .emitters import Emitters
from .variance import pixel_variance

__all__ = ["PointModel", "nearest_atoms", "polish", "prune"]


class PointModel:
    """One grid atom per emitter plus a constant background, fitted by NNLS.

    Attributes
    ----------
    index : ndarray of int, shape (K,)
        Flat atom indices.
    photons : ndarray, shape (K,)
        Fitted photons.
    background : float
        Background (photons/pixel).
    """

    def __init__(
        self, y: NDArray, dictionary: Dictionary, index: NDArray, background: float | None
    ) -> None:
        self.y = y
        self.dictionary = dictionary
        self.fixed_bg = background is not None
        self.index = np.asarray(index, dtype=np.int64)
        self.ids = np.arange(self.index.size)  # which input emitter each atom stands for
        self.atoms = dictionary.atoms(self.index) if self.index.size else np.zeros((0, *y.shape))
        self.background = float(background) if background is not None else float(y.mean())
        self.photons = np.zeros(self.index.size)
        self.refit()

    def refit(self) -> None:
        y = self.y.ravel()
        if self.index.size == 0:
            if not self.fixed_bg:
                self.background = float(max(y.mean(), 0.0))
            return
        a = self._matrix()
        if self.fixed_bg:
            self.photons, _ = nnls(a, y - self.background)
        else:
            x, _ = nnls(np.column_stack([a, np.ones(y.size)]), y)
            self.photons, self.background = x[:-1], float(x[-1])

    def _matrix(self) -> NDArray:
        """The atoms as the columns of a (pixels, K) matrix."""
        return self.atoms.reshape(self.index.size, -1).T

    @property
    def signal(self) -> NDArray:
        """Emitters' image (photons/pixel) without background."""
        return np.tensordot(self.photons, self.atoms, axes=(0, 0))

    def emitters(self) -> Emitters:
        pos = self.dictionary.positions(self.index) if self.index.size else np.zeros((0, 3))
        order = np.argsort(-self.photons)
        keep = order[self.photons[order] > 0]
        return Emitters(pos[keep, 0], pos[keep, 1], pos[keep, 2], self.photons[keep].copy())

    def remove(self, j: int) -> None:
        keep = np.arange(self.index.size) != j
        self.index, self.atoms = self.index[keep], self.atoms[keep]
        self.photons, self.ids = self.photons[keep], self.ids[keep]
        self.refit()

    def standard_errors(self, noise_factor: float, model_error: float) -> NDArray:
        """Standard error of each emitter's photons (weighted least squares, fixed positions)."""
        if self.index.size == 0:
            return np.zeros(0)
        sig = self.signal
        var = pixel_variance(sig + self.background, noise_factor, sig, model_error)
        a = self._matrix()
        if not self.fixed_bg:
            a = np.column_stack([a, np.ones(a.shape[0])])
        fisher = a.T @ (a / var.ravel()[:, None])
        cov = np.linalg.pinv(fisher)
        return np.sqrt(np.maximum(np.diag(cov)[: self.index.size], 0.0))


def nearest_atoms(dictionary: Dictionary, emitters: Emitters) -> NDArray:
    """Flat index of the grid atom nearest to each emitter."""
    return dictionary.nearest_index(emitters.x, emitters.y, emitters.z)


def polish(
    y: NDArray,
    dictionary: Dictionary,
    emitters: Emitters,
    background: float | None = None,
    *,
    reach_nm: tuple[float, float] = (40.0, 60.0),
    sweeps: int = 4,
) -> PointModel:
    """Refine emitters to the best single atom each (see the module notes).

    Parameters
    ----------
    y : ndarray, shape (rows, cols)
        Window (photons).
    dictionary : Dictionary
        Grid to refine on (typically the fine one).
    emitters : Emitters
        Starting emitters.
    background : float, optional
        Known background; fitted when ``None``.
    reach_nm : (lateral, axial)
        How far (nm) an emitter may move in one sweep.
    sweeps : int
        Maximum sweeps (stops early when no emitter moves).
    """
    model = PointModel(y, dictionary, nearest_atoms(dictionary, emitters), background)
    g = dictionary.grid
    reach = (max(1, round(reach_nm[0] / g.dxy)), max(1, round(reach_nm[1] / g.dz)))
    for _ in range(sweeps):
        moved = False
        for j in range(model.index.size):
            best = _best_atom(y, dictionary, model, j, reach)
            if best != model.index[j]:
                model.index[j] = best
                model.atoms[j] = dictionary.atoms([best])[0]
                moved = True
            model.refit()
        if not moved:
            break
    return model


def _best_atom(
    y: NDArray, dictionary: Dictionary, model: PointModel, j: int, reach: tuple[int, int]
) -> int:
    """The atom within ``reach`` grid steps of emitter ``j`` (not held by another emitter)
    that best explains what the other emitters and the background leave: the largest
    least-squares gain."""
    others = np.arange(model.index.size) != j
    r = y - model.background - np.tensordot(model.photons[others], model.atoms[others], axes=(0, 0))
    cand = dictionary.neighbourhood(int(model.index[j]), reach)
    cand = cand[~np.isin(cand, model.index[others])]
    atoms = dictionary.atoms(cand).reshape(cand.size, -1)
    rv = r.ravel()
    if not model.fixed_bg:  # the constant is refitted too: work with centred vectors
        atoms_c = atoms - atoms.mean(axis=1, keepdims=True)
        rv = rv - rv.mean()
    else:
        atoms_c = atoms
    corr = atoms_c @ rv
    nrm2 = np.einsum("ij,ij->i", atoms_c, atoms_c)
    gain = np.where(corr > 0, corr**2 / np.maximum(nrm2, 1e-30), 0.0)
    return int(cand[np.argmax(gain)])


def prune(
    model: PointModel,
    *,
    min_snr: float = 4.0,
    min_photons: float = 0.0,
    noise_factor: float = 1.0,
    model_error: float = 0.0,
) -> PointModel:
    """Drop insignificant emitters one at a time (weakest first), refitting after each."""
    while model.index.size:
        se = model.standard_errors(noise_factor, model_error)
        snr = model.photons / np.maximum(se, 1e-12)
        j = int(np.argmin(snr))
        if snr[j] >= min_snr and model.photons[j] >= min_photons:
            break
        model.remove(j)
    return model
