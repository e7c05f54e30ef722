"""From sparse coefficients to emitters, and the result type every window solver returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

__all__ = ["Emitters", "WindowSolution", "group_by_boxes", "group_coefficients"]

#: Atoms closer than this (nm; x/y, z) always belong to one emitter, whatever the grid step:
#: two molecules this close cannot be told apart from one image anyway.
MIN_LINK_NM = (50.0, 100.0)


@dataclass(frozen=True)
class Emitters:
    """K emitters: positions (nm) and photons, arrays of shape (K,)."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    z: NDArray[np.float64]
    photons: NDArray[np.float64]

    @classmethod
    def empty(cls) -> Emitters:
        e = np.zeros(0)
        return cls(e, e.copy(), e.copy(), e.copy())

    @classmethod
    def from_array(cls, arr: ArrayLike) -> Emitters:
        """From an array of shape (K, 4): x, y, z, photons."""
        a = np.asarray(arr, dtype=np.float64).reshape(-1, 4)
        return cls(a[:, 0].copy(), a[:, 1].copy(), a[:, 2].copy(), a[:, 3].copy())

    def __len__(self) -> int:
        return int(self.x.size)

    def as_array(self) -> NDArray[np.float64]:
        """(K, 4) array of x, y, z (nm) and photons."""
        return np.stack([self.x, self.y, self.z, self.photons], axis=-1)

    def to_frame(self) -> pd.DataFrame:
        """DataFrame with columns x_nm, y_nm, z_nm, photons."""
        return pd.DataFrame(
            {"x_nm": self.x, "y_nm": self.y, "z_nm": self.z, "photons": self.photons}
        )


@dataclass
class WindowSolution:
    """What a window solver found.

    Attributes
    ----------
    emitters : Emitters
        The emitters (positions in nm, photons).
    background : float
        Background in photons per pixel.
    model_image : ndarray, shape (rows, cols)
        Reconstruction: the selected atoms times their coefficients plus the background.
    method : str
        ``"mp"``, ``"omp"``, ``"co"`` or ``"hybrid"``.
    details : dict
        Method-specific extras (atom indices and coefficients, stop reason, boxes, ...).
    sigma : ndarray, shape (K, 4), optional
        Standard errors of x, y, z (nm) and photons (after a maximum-likelihood fit).
    flags : ndarray of str, shape (K,), optional
        ``"ok"`` or why an emitter is doubtful (after a fit).
    gof : float, optional
        Goodness of fit of the window (deviance per degree of freedom; about 1 is good).
    """

    emitters: Emitters
    background: float
    model_image: NDArray[np.float64]
    method: str
    details: dict[str, Any] = field(default_factory=dict)
    sigma: NDArray[np.float64] | None = None
    flags: NDArray[np.str_] | None = None
    gof: float | None = None


def group_coefficients(
    positions: ArrayLike,
    coef: ArrayLike,
    steps: tuple[float, float],
    *,
    link: float = 1.5,
    min_photons: float = 0.0,
) -> Emitters:
    """Group neighbouring non-zero atoms into emitters (one emitter per group).

    Two atoms are neighbours when ``|dx|, |dy| <= link * dxy`` and ``|dz| <= link * dz``, or
    closer than :data:`MIN_LINK_NM`; groups are the connected components of that relation. An
    emitter's photons are the sum of its group's coefficients and its position their
    coefficient-weighted centre.

    Parameters
    ----------
    positions : ndarray, shape (k, 3)
        Atom positions (x, y, z) in nm.
    coef : ndarray, shape (k,)
        Coefficients in photons (zeros are ignored).
    steps : (dxy, dz)
        Grid steps (nm) of the dictionary the atoms come from.
    link : float
        Neighbour distance in grid steps.
    min_photons : float
        Drop emitters with fewer photons.

    Returns
    -------
    Emitters
        Sorted by decreasing photons.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(coef, dtype=np.float64).ravel()
    keep = c > 0
    pos, c = pos[keep], c[keep]
    if c.size == 0:
        return Emitters.empty()
    lxy = max(link * steps[0], MIN_LINK_NM[0])
    lz = max(link * steps[1], MIN_LINK_NM[1])
    n_groups, labels = _linked_groups(pos, lxy + 1e-9, lz + 1e-9)
    photons = np.bincount(labels, weights=c, minlength=n_groups)
    centre = _weighted_sums(labels, c, pos, n_groups) / photons[:, None]
    order = np.argsort(-photons)
    order = order[photons[order] >= min_photons]
    return Emitters(centre[order, 0], centre[order, 1], centre[order, 2], photons[order])


def group_by_boxes(
    positions: ArrayLike,
    coef: ArrayLike,
    centres: ArrayLike,
    half_width: tuple[float, float, float],
    *,
    min_photons: float = 0.0,
    merge_nm: tuple[float, float] = MIN_LINK_NM,
) -> Emitters:
    """One emitter per box: each non-zero atom joins the box centre nearest to it.

    Used by the hybrid solver, whose fine atoms all lie in boxes around the coarse estimates.
    Distances are measured in box half-widths, so a box's atoms stay with it even where
    boxes overlap. Emitters that end up closer than ``merge_nm`` (x/y, z) are merged.

    Parameters
    ----------
    positions : ndarray, shape (k, 3)
        Atom positions (nm).
    coef : ndarray, shape (k,)
        Coefficients (photons).
    centres : ndarray, shape (m, 3)
        Box centres (nm).
    half_width : (hx, hy, hz)
        Box half-widths (nm).
    min_photons : float
        Drop emitters with fewer photons.
    merge_nm : (float, float)
        Lateral and axial distance under which two emitters are one.
    """
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(coef, dtype=np.float64).ravel()
    cen = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    keep = c > 0
    pos, c = pos[keep], c[keep]
    if c.size == 0 or cen.size == 0:
        return Emitters.empty()
    scale = np.asarray(half_width, dtype=np.float64)
    d = np.linalg.norm((pos[:, None, :] - cen[None, :, :]) / scale, axis=2)
    label = np.argmin(d, axis=1)
    m = cen.shape[0]
    photons = np.bincount(label, weights=c, minlength=m)
    used = photons > 0
    centre = _weighted_sums(label, c, pos, m)[used] / photons[used, None]
    merged = group_coefficients(centre, photons[used], (0.0, 0.0), link=0.0)
    if merge_nm != MIN_LINK_NM:
        n, lab = _linked_groups(centre, merge_nm[0], merge_nm[1])
        ph = np.bincount(lab, weights=photons[used], minlength=n)
        ctr = _weighted_sums(lab, photons[used], centre, n) / ph[:, None]
        merged = Emitters(ctr[:, 0], ctr[:, 1], ctr[:, 2], ph)
    order = np.argsort(-merged.photons)
    order = order[merged.photons[order] >= min_photons]
    return Emitters(merged.x[order], merged.y[order], merged.z[order], merged.photons[order])


def _linked_groups(pos: NDArray[np.float64], lxy: float, lz: float) -> tuple[int, NDArray]:
    """Connected components of points (k, 3) linked when ``|dx|, |dy| <= lxy``, ``|dz| <= lz``.

    Returns the number of groups and each point's group label.
    """
    d = np.abs(pos[:, None, :] - pos[None, :, :])
    adj = (d[..., 0] <= lxy) & (d[..., 1] <= lxy) & (d[..., 2] <= lz)
    return connected_components(coo_matrix(adj), directed=False)


def _weighted_sums(
    labels: NDArray, weights: NDArray[np.float64], pos: NDArray[np.float64], n: int
) -> NDArray[np.float64]:
    """Per-group sums of ``weights * pos`` (x, y, z), shape (n, 3)."""
    return np.stack(
        [np.bincount(labels, weights=weights * pos[:, i], minlength=n) for i in range(3)], axis=1
    )
