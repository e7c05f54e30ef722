"""Certified argmax of normalised correlations over a structured dictionary (:class:`AtomSearch`).

Every MP iteration needs the atom with the largest normalised correlation with the residual,
``argmax_i corr_i * inv_i`` over all atoms (1,270,016 for the paper's fine dictionary). The
dense reference computes all of them (``D^T r``, 154 million multiply-adds per iteration);
:class:`AtomSearch` finds the same atom by branch and bound:

1. *Clusters.* The atoms are cut into blocks of ``bz x by x bx`` neighbouring grid points
   (z, y, x): (4, 8, 8), 80 x 80 x 60 nm, on the fine grid. Inside a block the normalised
   atom ``a_i`` is a smooth function of its offset ``u_i`` in ``[-1, 1]^3``; a quadratic
   polynomial ``a_i ~ sum_m u_i^m G_m`` fits it to about 1 % of its norm and a cubic one to
   about 0.1 %; ``R`` is the largest misfit of a member (measured, with the float32 models).
2. *Bounds.* With ``g_m = <G_m, r>`` (one float32 matrix product for all clusters and a whole
   batch of residuals) a member's score is ``sum_m u_i^m g_m`` to within ``R ||r||`` (plus
   rounding allowances). The quadratic's maximum over the box, bounded per axis exactly and
   the cross terms by ``|g|``, bounds every member of a cluster from above.
3. *Search.* The clusters with the largest bounds get their members bounded with the cubic
   model, and the best-bounded members are scored exactly, in float64, by the reference
   formula (ties: lowest index, as ``numpy.argmax``). The best of them is proven to be the
   argmax when every atom left out (the other clusters, the other members) has an upper bound
   below its exact score; where that fails the window gets a wider round, then an unbounded
   search of the same bounds: the answer is always the reference's.

Small batches (a single window) bound parent clusters (2 x 1 x 1 clusters) first and only the
clusters of the most promising parents, reading a few MB instead of the whole cluster matrix.

The search runs on NumPy by default; ``device="cpu"`` or ``"cuda"`` runs its bulk (the matrix
product, the bounds and the candidate selection) on PyTorch (imported only then).
:mod:`sparseloc.solvers.fast_mp` drives it, one batched search per MP iteration.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from itertools import product
from typing import Any, NamedTuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike, NDArray

from ..dictionary import Dictionary
from .mp import score_scale

log = logging.getLogger(__name__)

__all__ = ["CLUSTER_SPAN_NM", "AtomSearch", "score_scale"]

#: Physical size (nm) of a cluster: lateral, axial. Chosen for sub-100 nm grids, where a cubic
#: fits a block's atoms to a few thousandths of their norm.
CLUSTER_SPAN_NM = (80.0, 60.0)
#: Relative rounding allowance of a float32 dot product per dimension (a generous gamma_n).
_F32_EPS = 2.0**-22
#: Absolute allowance (relative to ||r||) for float64 rounding between the bound and the exact
#: reference formula.
_F64_EPS = 1e-9


def _monomials(block: tuple[int, int, int], degree: int) -> NDArray[np.int64]:
    """Exponents (n_mono, 3) of a cluster polynomial in (u_z, u_y, u_x), the constant first.

    Powers stop below each block length (two points cannot tell ``u^2`` from a constant).
    """
    exps = [
        e for e in product(*(range(min(degree, b - 1) + 1) for b in block)) if 0 < sum(e) <= degree
    ]
    return np.array([(0, 0, 0), *exps], dtype=np.int64).reshape(-1, 3)


def _bound_terms(exps: NDArray[np.int64]) -> tuple[NDArray[np.int64], ...]:
    """Monomials of a model by how its bound treats them on the box ``[-1, 1]^3``.

    Returns ``odd`` (bounded by ``|g|``), ``even`` (by ``max(g, 0)``), and the pairs
    ``lin[j]``, ``sq[j]`` (``u_k``, ``u_k^2`` of one axis, maximised exactly together).
    """
    rows = [tuple(e) for e in exps.tolist()]
    lin, sq = [], []
    for k in range(3):
        one = tuple(1 if j == k else 0 for j in range(3))
        two = tuple(2 if j == k else 0 for j in range(3))
        if one in rows and two in rows:
            lin.append(rows.index(one))
            sq.append(rows.index(two))
    paired = set(lin) | set(sq)
    rest = [i for i, e in enumerate(rows) if sum(e) > 0 and i not in paired]
    even = [i for i in rest if all(p % 2 == 0 for p in rows[i])]
    odd = [i for i in rest if i not in even]
    return tuple(np.array(v, dtype=np.int64) for v in (odd, even, lin, sq))


def _design(block: tuple[int, int, int], exps: NDArray[np.int64]) -> NDArray[np.float64]:
    """Monomials at the block's members, (bz*by*bx, n_mono); members in C order (z, y, x)."""
    axes = [np.linspace(-1.0, 1.0, b) if b > 1 else np.zeros(1) for b in block]
    u = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.prod(u[:, None, :] ** exps[None, :, :], axis=-1)


class _Layout(NamedTuple):
    """How the grid of ``shape`` (nz, ny, nx) is cut, per axis (z, y, x): ``block`` grid
    points per cluster, ``n_blocks`` clusters (padded to whole parents), ``parent`` clusters
    per parent, ``n_parents`` parents, ``parent_block`` grid points per parent."""

    shape: tuple[int, int, int]
    block: tuple[int, ...]
    n_blocks: tuple[int, ...]
    parent: tuple[int, ...]
    n_parents: tuple[int, ...]
    parent_block: tuple[int, ...]


def _layout(
    d: Dictionary, block: tuple[int, int, int] | None, parent: tuple[int, int, int]
) -> _Layout:
    """Clusters of ``block`` grid points (default about :data:`CLUSTER_SPAN_NM`) and parents
    of ``parent`` clusters, both cut to the grid's size."""
    nz, ny, nx = d.coef_shape
    if block is None:
        lat = max(1, round(CLUSTER_SPAN_NM[0] / d.grid.dxy))
        axial = max(1, round(CLUSTER_SPAN_NM[1] / d.grid.dz))
        block = (axial, lat, lat)
    if min(block) < 1 or min(parent) < 1:
        raise ValueError(f"block and parent sizes must be >= 1, got {block}, {parent}")
    shape = (nz, ny, nx)
    blk = tuple(min(int(b), n) for b, n in zip(block, shape, strict=True))
    nb = tuple(-(-n // b) for n, b in zip(shape, blk, strict=True))
    fac = tuple(min(int(f), k) for f, k in zip(parent, nb, strict=True))
    npar = tuple(-(-k // f) for k, f in zip(nb, fac, strict=True))
    nb = tuple(p * f for p, f in zip(npar, fac, strict=True))  # whole parents
    pblk = tuple(b * f for b, f in zip(blk, fac, strict=True))
    return _Layout(shape, blk, nb, fac, npar, pblk)


class _Row(NamedTuple):
    """One row (kz, ky) of parents: its normalised atoms (pz, py, X, n_pix) and their flat
    indices (pz, py, X), -1 where there is no eligible atom."""

    kz: int
    ky: int
    atoms: NDArray[np.float64]
    ids: NDArray[np.int64]


def _family(lay: _Layout) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The parent of each cluster (n_clusters,) and the clusters of each parent
    (n_parents, clusters per parent)."""
    fac, npar = lay.parent, lay.n_parents
    cz, cy, cx = np.unravel_index(np.arange(int(np.prod(lay.n_blocks))), lay.n_blocks)
    parent_of = np.ravel_multi_index((cz // fac[0], cy // fac[1], cx // fac[2]), npar)
    children = np.argsort(parent_of, kind="stable").reshape(int(np.prod(npar)), -1)
    return parent_of, children


def _model_norm(g32: NDArray[np.float32]) -> NDArray[np.float64]:
    """Sum over monomials of the norms of a cluster's models, g32 (n_mono, n, n_pix)."""
    return np.linalg.norm(g32.astype(np.float64), axis=-1).sum(axis=0)


@dataclass
class _ClusterTables:
    """The cluster and parent models while they are fitted, row of parents by row."""

    coarse: NDArray[np.float32]  # (n_mono_a, n_clusters, n_pix), monomial-major: one GEMM
    fine: NDArray[np.float32]  # (n_clusters, n_mono_b, n_pix), cluster-major: gathered
    radius: NDArray[np.float64]  # (2, n_clusters): largest misfit, coarse and fine models
    gnorm: NDArray[np.float64]  # (2, n_clusters): summed model norms
    member: NDArray[np.int64]  # (n_clusters, m): atom ids, -1 where none
    parent_coarse: NDArray[np.float32]  # (n_mono_p, n_parents, n_pix)
    parent_radius: NDArray[np.float64]
    parent_gnorm: NDArray[np.float64]

    @classmethod
    def empty(cls, lay: _Layout, n_pix: int, n_mono: tuple[int, int, int]) -> _ClusterTables:
        ma, mb, mp = n_mono
        m = int(np.prod(lay.block))
        n_cl, n_par = int(np.prod(lay.n_blocks)), int(np.prod(lay.n_parents))
        return cls(
            coarse=np.zeros((ma, n_cl, n_pix), dtype=np.float32),
            fine=np.zeros((n_cl, mb, n_pix), dtype=np.float32),
            radius=np.zeros((2, n_cl)),
            gnorm=np.zeros((2, n_cl)),
            member=np.full((n_cl, m), -1, dtype=np.int64),
            parent_coarse=np.zeros((mp, n_par, n_pix), dtype=np.float32),
            parent_radius=np.zeros(n_par),
            parent_gnorm=np.zeros(n_par),
        )

    def fit_parents(self, lay: _Layout, row: _Row, design: NDArray[np.float64]) -> None:
        """Models of the parents of a row."""
        vecs, vid = _cut(row.atoms, row.ids, lay.parent_block)
        g32, rad = _fit_clusters(vecs, vid >= 0, design)
        npar = lay.n_parents
        prow = (row.kz * npar[1] + row.ky) * npar[2] + np.arange(npar[2])
        self.parent_coarse[:, prow] = g32
        self.parent_radius[prow] = rad
        self.parent_gnorm[prow] = _model_norm(g32)

    def fit_children(
        self, lay: _Layout, row: _Row, designs: tuple[NDArray[np.float64], ...]
    ) -> None:
        """Both models of the clusters of a row's parents, cut in (z, y, x) block order."""
        fac, nb = lay.parent, lay.n_blocks
        vecs, vid = _cut(row.atoms, row.ids, lay.block)
        bz_, by_, bx_ = np.unravel_index(np.arange(vid.shape[0]), (fac[0], fac[1], nb[2]))
        rows = np.ravel_multi_index((row.kz * fac[0] + bz_, row.ky * fac[1] + by_, bx_), nb)
        self.member[rows] = vid
        for level, design in enumerate(designs):
            g32, self.radius[level, rows] = _fit_clusters(vecs, vid >= 0, design)
            self.gnorm[level, rows] = _model_norm(g32)
            if level == 0:
                self.coarse[:, rows] = g32
            else:
                self.fine[rows] = g32.transpose(1, 0, 2)


class AtomSearch:
    """Exact argmax of normalised correlations over all atoms of a :class:`Dictionary`.

    Scores follow :func:`~sparseloc.solvers.mp.matching_pursuit`: with the background fitted
    (``fit_background=True``) ``corr_i = <atom_i, r> - mean(r) * sum(atom_i)`` and
    ``inv_i = 1 / ||atom_i - mean(atom_i)||``, else ``corr_i = <atom_i, r>`` and
    ``inv_i = 1 / ||atom_i||``; atoms with a norm below ``min_norm_fraction`` of the largest
    have ``inv_i = 0`` (never selected). Norms and sums are computed as the dense reference
    does (pixel by pixel, in float64).

    Parameters
    ----------
    dictionary : Dictionary
        The structured dictionary (templates of shape (nz, s, s, CR, CC)).
    fit_background : bool
        Mean-removed scores (the background is fitted jointly) or plain ones (known
        background).
    min_norm_fraction : float
        Eligibility threshold on the atom norm, as in ``matching_pursuit``.
    block : (bz, by, bx), optional
        Cluster size in grid points (z, y, x); default about :data:`CLUSTER_SPAN_NM`
        (80 nm laterally, 60 nm axially): (4, 8, 8) on the paper's fine 10 nm / 15 nm grid.
    degrees : (int, int)
        Degrees of the two polynomial models of a cluster: the cheap one bounds every cluster,
        the accurate one scores the members of the most promising clusters.
    candidates : (int, int)
        Clusters, then atoms, examined per residual before the fallback search.
    chunk : int
        Residuals searched at once (memory about ``chunk * n_clusters * 60`` bytes).
    parent : (int, int, int)
        Clusters per parent cluster (z, y, x). Batches of at most ``small_batch`` residuals
        bound the parents first (a matrix ``prod(parent)`` times smaller) and the clusters of
        only the ``expand`` best parents (the others inherit their parent's bound): a single
        window reads a few MB instead of the whole cluster matrix.
    small_batch, expand : int
        See ``parent``.

    Notes
    -----
    Memory: the models take ``(n_clusters * (n_mono_a + n_mono_b) + n_parents * n_mono_a) *
    rows * cols * 4`` bytes, plus an int64 member table with one entry per grid point and the
    atoms' norms: about 140 MB for the fine dictionary (:meth:`memory`). Construction reads
    every atom twice (about 5 s for its 1.27 million atoms).
    """

    def __init__(
        self,
        dictionary: Dictionary,
        *,
        fit_background: bool = True,
        min_norm_fraction: float = 0.3,
        block: tuple[int, int, int] | None = None,
        degrees: tuple[int, int] = (2, 3),
        candidates: tuple[int, int] = (32, 64),
        chunk: int = 64,
        parent: tuple[int, int, int] = (2, 1, 1),
        small_batch: int = 8,
        expand: int = 32,
    ) -> None:
        if not isinstance(dictionary, Dictionary):
            raise TypeError("AtomSearch needs a structured Dictionary (use ReferenceSearch)")
        # the geometry only: no reference to the dictionary (the cache is keyed on it weakly)
        self.shape = dictionary.shape
        self.coef_shape = dictionary.coef_shape
        self.size = dictionary.size
        self._s, self._n_shift = dictionary.s, dictionary.n_shift
        self.centered = bool(fit_background)
        self.min_norm_fraction = float(min_norm_fraction)
        self.n_pix = dictionary.shape[0] * dictionary.shape[1]
        self.candidates = (max(int(candidates[0]), 1), max(int(candidates[1]), 1))
        self.chunk = max(int(chunk), 1)
        self.small_batch = int(small_batch)
        self.expand = max(int(expand), 1)
        rows, cols = dictionary.shape
        # windows[iz, py, px, oy, ox] is the atom at phase (py, px), shift o = last - q
        self._win = sliding_window_view(dictionary.templates, (rows, cols), axis=(-2, -1))
        self._torch: dict[str, dict[str, Any]] = {}
        self._stats = {"searches": 0, "fallback": 0}
        self._prepare_norms()
        self._prepare_clusters(dictionary, block, degrees, parent)

    # -- construction ----------------------------------------------------------------------------
    def _plane(self, iz: int) -> NDArray[np.float64]:
        """All atoms of z plane ``iz`` as (ny*nx, n_pix), rows in flat index order."""
        ay, ax = self._n_shift
        w = self._win[iz][:, :, ::-1, ::-1]  # (py, px, qy, qx, rows, cols)
        w = w.transpose(2, 0, 3, 1, 4, 5)  # (qy, py, qx, px, rows, cols)
        return np.ascontiguousarray(w).reshape(ay * self._s * ax * self._s, self.n_pix)

    def _normalised(self, iz: int) -> NDArray[np.float64]:
        """Normalised (centred) atoms of a plane; ineligible atoms are zero."""
        a = self._plane(iz)
        sl = slice(iz * a.shape[0], (iz + 1) * a.shape[0])
        if self.centered:
            a = a - (self.sums[sl] / self.n_pix)[:, None]
        return a * self.inv[sl, None]

    def _prepare_norms(self) -> None:
        nz = self.coef_shape[0]
        norms, sums = [], []
        for iz in range(nz):
            # (n_pix, atoms) C order, reduced over axis 0: the dense reference's order
            at = np.ascontiguousarray(self._plane(iz).T)
            norms.append(np.sqrt(np.add.reduce(at * at, axis=0)))
            sums.append(at.sum(axis=0))
        self.norms = np.concatenate(norms)
        self.sums = np.concatenate(sums)
        self.eligible, self.inv = score_scale(
            self.norms, self.sums if self.centered else None, self.n_pix, self.min_norm_fraction
        )

    def _prepare_clusters(
        self,
        d: Dictionary,
        block: tuple[int, int, int] | None,
        degrees: tuple[int, int],
        parent: tuple[int, int, int],
    ) -> None:
        """Cut the grid into clusters and parents and fit their polynomial models."""
        lay = _layout(d, block, parent)
        self.block, self.parent = lay.block, lay.parent
        exps_a = _monomials(lay.block, int(degrees[0]))
        exps_b = _monomials(lay.block, int(degrees[1]))
        exps_p = _monomials(lay.parent_block, int(degrees[0]))
        self._bound_terms = _bound_terms(exps_a)
        self._parent_terms = _bound_terms(exps_p)
        self.design_a = _design(lay.block, exps_a)  # (m, n_mono_a)
        self.design_b = _design(lay.block, exps_b)  # (m, n_mono_b)
        design_p = _design(lay.parent_block, exps_p)
        n_mono = (exps_a.shape[0], exps_b.shape[0], exps_p.shape[0])
        tables = _ClusterTables.empty(lay, self.n_pix, n_mono)
        self.parent_of, self.children = _family(lay)
        py = lay.parent_block[1]
        for kz in range(lay.n_parents[0]):
            slab, ids = self._slab(lay, kz)
            for ky in range(lay.n_parents[1]):
                rows = slice(ky * py, (ky + 1) * py)
                row = _Row(kz, ky, slab[:, rows], ids[:, rows])
                tables.fit_parents(lay, row, design_p)
                tables.fit_children(lay, row, (self.design_a, self.design_b))
        self._keep_clusters(lay, tables)
        self._log_clusters(lay, degrees)

    def _slab(self, lay: _Layout, kz: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """One slab of parents: the normalised atoms (pz, Y, X, n_pix) of its planes and their
        flat indices (-1: no atom, or an ineligible one), zero-padded to whole parents."""
        nz, ny, nx = lay.shape
        pz, py, px = lay.parent_block
        n_pix = self.n_pix
        slab = np.zeros((pz, lay.n_parents[1] * py, lay.n_parents[2] * px, n_pix))
        ids = np.full(slab.shape[:3], -1, dtype=np.int64)
        for j, iz in enumerate(range(kz * pz, min((kz + 1) * pz, nz))):
            flat = np.arange(iz * ny * nx, (iz + 1) * ny * nx, dtype=np.int64).reshape(ny, nx)
            slab[j, :ny, :nx] = self._normalised(iz).reshape(ny, nx, n_pix)
            ids[j, :ny, :nx] = np.where(self.eligible[flat], flat, -1)
        return slab, ids

    def _keep_clusters(self, lay: _Layout, t: _ClusterTables) -> None:
        """Store the fitted models; clusters past the last z plane (there only to make whole
        parents) hold no atom and are dropped."""
        nb, n_pix = lay.n_blocks, self.n_pix
        n_cl = -(-lay.shape[0] // lay.block[0]) * nb[1] * nb[2]
        ma = t.coarse.shape[0]
        mp, n_par = t.parent_coarse.shape[:2]
        self.coarse = np.ascontiguousarray(t.coarse[:, :n_cl]).reshape(ma * n_cl, n_pix)
        self.fine = np.ascontiguousarray(t.fine[:n_cl])
        self.radius = t.radius[:, :n_cl]
        self.gnorm = t.gnorm[:, :n_cl]
        self.member = np.ascontiguousarray(t.member[:n_cl])
        self.parent_of = self.parent_of[:n_cl]
        self.children = np.where(self.children < n_cl, self.children, -1)
        self.parent_coarse = t.parent_coarse.reshape(mp * n_par, n_pix)
        self.parent_radius = t.parent_radius
        self.parent_gnorm = t.parent_gnorm
        self._absent = np.where(self.member >= 0, 0.0, -np.inf).astype(np.float32)
        self._design_b32 = self.design_b.astype(np.float32)

    def _log_clusters(self, lay: _Layout, degrees: tuple[int, int]) -> None:
        radius, prad = self.radius, self.parent_radius
        has = self.member.max(axis=1) >= 0
        log.info(
            "AtomSearch: %d atoms in %d clusters of %s (%d parents of %s); misfit (median, "
            "largest) %.2g, %.2g (degree %d), %.2g, %.2g (degree %d), parents %.2g, %.2g",
            self.size,
            self.n_clusters,
            self.block,
            int(np.prod(lay.n_parents)),
            lay.parent_block,
            float(np.median(radius[0, has])),
            float(radius[0].max()),
            degrees[0],
            float(np.median(radius[1, has])),
            float(radius[1].max()),
            degrees[1],
            float(np.median(prad)),
            float(prad.max()),
        )

    # -- properties --------------------------------------------------------------------------------
    @property
    def n_clusters(self) -> int:
        return int(self.member.shape[0])

    @property
    def fallback_fraction(self) -> float:
        """Fraction of the searches so far that the first round could not prove (they went
        on to a wider round, rarely to the unbounded search)."""
        n = self._stats["searches"]
        return self._stats["fallback"] / n if n else 0.0

    def memory(self) -> int:
        """Bytes held by the search structure (not counting the dictionary)."""
        arrays = (self.coarse, self.fine, self.parent_coarse, self.member, self._absent)
        return int(sum(a.nbytes for a in arrays) + 3 * self.norms.nbytes)

    # -- exact scores ------------------------------------------------------------------------------
    def atoms(self, index: NDArray[np.int64]) -> NDArray[np.float64]:
        """Raw atoms (..., n_pix) of flat indices of any shape (values of ``Dictionary.atoms``)."""
        s = self._s
        iz, iy, ix = np.unravel_index(index, self.coef_shape)
        ay, ax = self._n_shift
        a = self._win[iz, iy % s, ix % s, ay - 1 - iy // s, ax - 1 - ix // s]
        return a.reshape(*np.shape(index), self.n_pix)

    def exact(
        self, resid: NDArray[np.float64], index: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Reference ``corr`` and ``score`` of atoms ``index`` (B, K) for residuals (B, n_pix)."""
        a = self.atoms(index)
        corr = np.einsum("bkn,bn->bk", a, resid)
        if self.centered:
            corr = corr - resid.mean(axis=1)[:, None] * self.sums[index]
        return corr, corr * self.inv[index]

    def dense_scores(self, resid: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``corr`` and ``score`` of every atom (n_atoms,) for one residual: slow, for checks."""
        r = np.asarray(resid, dtype=np.float64).reshape(self.n_pix)
        step = self.coef_shape[1] * self.coef_shape[2]
        corr = np.empty(self.size)
        for iz in range(self.coef_shape[0]):
            corr[iz * step : (iz + 1) * step] = self._plane(iz) @ r
        if self.centered:
            corr = corr - r.mean() * self.sums
        return corr, corr * self.inv

    # -- the search (NumPy) ------------------------------------------------------------------------
    def _eps(self) -> float:
        """Relative float32 rounding allowance of a model's value (dot products and sum)."""
        return (self.n_pix + self.design_b.shape[1] + 8) * _F32_EPS

    def _slack(self, level: int, n_rc: NDArray, n_all: NDArray, clusters=None) -> NDArray:
        """Allowance (B, n) of a model: misfit, float32 rounding, float64 rounding."""
        eps = self._eps()
        rad, gn = self.radius[level], self.gnorm[level]
        if clusters is None:
            return (rad + eps * gn)[None, :] * n_rc[:, None] + _F64_EPS * n_all[:, None]
        return (rad[clusters] + eps * gn[clusters]) * n_rc[:, None] + _F64_EPS * n_all[:, None]

    def _coarse_bounds(self, r: NDArray, rc: NDArray) -> NDArray[np.float32]:
        """Upper bound (B, n_clusters) of every cluster's best score (float32, rigorous)."""
        if r.shape[0] <= self.small_batch and self.children.shape[1] > 1:
            return self._coarse_bounds_parents(r, rc)
        n_cl = self.n_clusters
        r32 = rc.astype(np.float32)
        # NumPy runs a 1-row product as a slow GEMM; the transposed one is a fast GEMV
        g = (self.coarse @ r32.T).T if r.shape[0] <= 2 else r32 @ self.coarse.T
        ub = _poly_bound(g.reshape(r.shape[0], -1, n_cl), self._bound_terms)
        slack = self._slack(0, np.linalg.norm(rc, axis=1), np.linalg.norm(r, axis=1))
        return ub + slack.astype(np.float32)

    def _coarse_bounds_parents(self, r: NDArray, rc: NDArray) -> NDArray[np.float32]:
        """As :meth:`_coarse_bounds` through the parents: clusters of the ``expand``
        best-bounded parents get their own bound, the others their parent's."""
        bsz, n_cl = r.shape[0], self.n_clusters
        n_par = self.children.shape[0]
        n_rc, n_all = np.linalg.norm(rc, axis=1), np.linalg.norm(r, axis=1)
        r32 = rc.astype(np.float32)
        gp = (self.parent_coarse @ r32.T).T.reshape(bsz, -1, n_par)
        eps = self._eps()
        slack_p = (self.parent_radius + eps * self.parent_gnorm)[None, :] * n_rc[:, None]
        ubp = _poly_bound(gp, self._parent_terms) + (slack_p + _F64_EPS * n_all[:, None]).astype(
            np.float32
        )
        ub = ubp[:, self.parent_of]
        top, _ = _top(ubp, self.expand)
        ch = self.children[top].reshape(bsz, -1)
        valid = ch >= 0
        ch = np.where(valid, ch, 0)
        ma = self.design_a.shape[1]
        rows = (np.arange(ma)[None, None, :] * n_cl + ch[..., None]).reshape(bsz, -1)
        g = (self.coarse[rows] @ r32[:, :, None]).reshape(bsz, -1, ma).transpose(0, 2, 1)
        ubc = _poly_bound(g, self._bound_terms)
        ubc += self._slack(0, n_rc, n_all, ch).astype(np.float32)
        ubc[~valid] = np.inf
        np.minimum.at(ub, (np.arange(bsz)[:, None], ch), ubc)
        return ub

    def _member_upper(
        self, rc: NDArray, n_rc: NDArray, n_all: NDArray, clusters: NDArray[np.int64]
    ) -> NDArray[np.float32]:
        """Upper bounds (B, K*m) of the members' scores of clusters (B, K) (-inf: no atom).

        float32 throughout: the allowance covers the rounding of the dot products and of the
        sum over monomials (|u^m| <= 1)."""
        bsz, k = clusters.shape
        mods = self.fine[clusters].reshape(bsz, -1, self.n_pix)  # (B, K*n_mono, n_pix)
        g = (mods @ rc.astype(np.float32)[:, :, None]).reshape(bsz, k, -1)
        hi = g @ self._design_b32.T  # (B, K, m)
        allow = self._slack(1, n_rc, n_all, clusters).astype(np.float32)[..., None]
        hi += allow + self._absent[clusters]
        return hi.reshape(bsz, -1)

    def _member_ids(self, clusters: NDArray[np.int64], pick: NDArray[np.int64]) -> NDArray:
        """Atom ids of positions ``pick`` (B, K') in the member lists of ``clusters`` (B, K)."""
        m = self.member.shape[1]
        cl = np.take_along_axis(clusters, pick // m, axis=1)
        return self.member[cl, pick % m]

    def _search_numpy(self, r: NDArray, rc: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        n_rc, n_all = np.linalg.norm(rc, axis=1), np.linalg.norm(r, axis=1)
        ub = self._coarse_bounds(r, rc)
        first = self._round(r, rc, n_rc, n_all, ub, *self.candidates)
        return self._resolve(r, rc, n_rc, n_all, lambda rows: ub[rows], *first)

    def _round(self, r, rc, n_rc, n_all, ub, ka: int, kc: int):
        """Bound the members of the ``ka`` best-bounded clusters, score the ``kc`` best of them
        exactly. Returns index, corr, score and whether the best is proven (all (B,))."""
        top, rest = _top(ub, ka)
        hi = self._member_upper(rc, n_rc, n_all, top)
        pick, rest_hi = _top(hi, kc)
        cand = self._member_ids(top, pick)
        cand = np.where(np.isfinite(np.take_along_axis(hi, pick, axis=1)), cand, -1)
        index, corr, score = self._exact_best(r, cand)
        # proven: every atom left out is bounded below the best candidate's exact score
        ok = np.maximum(rest, rest_hi) < score
        return index, corr, score, ok

    def _resolve(self, r, rc, n_rc, n_all, ub_rows, index, corr, score, ok):
        """Settle the unproven residuals: a round with 8x the clusters, then no budget."""
        bad = np.flatnonzero(~ok)
        self._stats["searches"] += r.shape[0]
        self._stats["fallback"] += int(bad.size)
        if bad.size:
            ka, kc = self.candidates
            ub = np.asarray(ub_rows(bad))
            i2, c2, s2, ok2 = self._round(
                r[bad], rc[bad], n_rc[bad], n_all[bad], ub, 8 * ka, 4 * kc
            )
            index[bad], corr[bad], score[bad] = i2, c2, s2
            for j in np.flatnonzero(~ok2):
                b = bad[j]
                index[b], corr[b], score[b] = self._unbounded(
                    r[b], rc[b], n_rc[b], n_all[b], ub[j], float(s2[j])
                )
        return index, corr, score

    def _unbounded(self, r, rc, n_rc, n_all, ub, level) -> tuple[int, float, float]:
        """One residual, no candidate budget: every cluster whose bound ``ub`` (n_clusters,)
        reaches ``level`` (the exact score of some atom, or -inf)."""
        clusters = np.flatnonzero(ub >= level)
        cand = []
        for start in range(0, clusters.size, 1024):
            part = clusters[None, start : start + 1024]
            hi = self._member_upper(rc[None], n_rc[None], n_all[None], part)[0]
            sel = np.flatnonzero(hi >= level)
            cand.append(self._member_ids(part, sel[None])[0])
        cand = np.unique(np.concatenate(cand)) if cand else np.zeros(0, dtype=np.int64)
        cand = cand[cand >= 0]
        if cand.size == 0:
            return -1, 0.0, -np.inf
        cc, sc = self.exact(r[None], cand[None])
        j = int(np.argmax(sc[0]))  # candidates sorted: the lowest index wins ties
        return int(cand[j]), float(cc[0, j]), float(sc[0, j])

    def _exact_best(self, r, cand) -> tuple[NDArray, NDArray, NDArray]:
        """Best of the candidates (B, K) (-1: none) by their exact scores; ties: lowest index."""
        bsz = r.shape[0]
        valid = cand >= 0
        corr, score = self.exact(r, np.where(valid, cand, 0))
        score = np.where(valid, score, -np.inf)
        best = score.max(axis=1)
        big = np.iinfo(np.int64).max
        index = np.where((score == best[:, None]) & valid, cand, big).min(axis=1)
        pos = np.argmax((cand == index[:, None]) & valid, axis=1)
        corr = corr[np.arange(bsz), pos]
        index = np.where(np.isfinite(best), index, -1)
        return index, corr, best

    def best(
        self, residuals: ArrayLike, *, device: str | None = None
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """The best eligible atom for each residual.

        Parameters
        ----------
        residuals : ndarray, shape (B, rows, cols) or (B, rows*cols)
            Residual windows in photons.
        device : str, optional
            ``None``: NumPy; ``"cpu"``, ``"cuda"``, ...: the bulk of the search on PyTorch.

        Returns
        -------
        index : ndarray of int64, shape (B,)
            Flat atom index of the largest ``score`` among eligible atoms (-1 if none).
        corr : ndarray, shape (B,)
            Its correlation in photons: ``<atom, r>``, minus ``mean(r) * sum(atom)`` when the
            background is fitted.
        score : ndarray, shape (B,)
            Its score ``corr * inv`` (photons per unit norm).

        Notes
        -----
        When the best eligible score is <= 0, ``numpy.argmax`` over all atoms (the reference)
        may pick an ineligible atom of score 0 instead; :meth:`argmax` follows it exactly.
        """
        r = np.asarray(residuals, dtype=np.float64).reshape(-1, self.n_pix)
        out = (np.empty(r.shape[0], dtype=np.int64), np.empty(r.shape[0]), np.empty(r.shape[0]))
        size = -(-r.shape[0] // max(-(-r.shape[0] // self.chunk), 1))  # even chunks
        for start in range(0, r.shape[0], max(size, 1)):
            sl = slice(start, start + size)
            rb = r[sl]
            rc = rb - rb.mean(axis=1, keepdims=True) if self.centered else rb
            if device is None:
                res = self._search_numpy(rb, rc)
            else:
                res = self._search_torch(rb, rc, device)
            for o, v in zip(out, res, strict=True):
                o[sl] = v
        return out

    def argmax(
        self, residuals: ArrayLike, *, device: str | None = None
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Exactly ``numpy.argmax(corr * inv)`` over all atoms, with its ``corr`` and score.

        As :meth:`best`, but where no eligible atom scores above 0 the answer is the
        reference's (the first atom of the largest score, ineligible ones scoring 0); that
        case scores every atom (slow, rare).
        """
        index, corr, score = self.best(residuals, device=device)
        r = np.asarray(residuals, dtype=np.float64).reshape(-1, self.n_pix)
        for b in np.flatnonzero(~(score > 0)):
            c, s = self.dense_scores(r[b])
            k = int(np.argmax(s))
            index[b], corr[b], score[b] = k, c[k], s[k]
        return index, corr, score

    # -- the search (PyTorch) ----------------------------------------------------------------------
    def _torch_state(self, device: str) -> dict[str, Any]:
        if device not in self._torch:
            from ..engine import torch_device

            torch, dev = torch_device(device)
            # float64 on accelerators: no TF32 shortcuts, and the rounding allowance holds
            dt = torch.float32 if dev.type == "cpu" else torch.float64
            self._torch[device] = {
                "torch": torch,
                "device": dev,
                "dtype": dt,
                "coarse": torch.as_tensor(self.coarse, device=dev, dtype=dt),
                "fine": torch.as_tensor(self.fine, device=dev, dtype=dt),
                "radius": torch.as_tensor(self.radius, device=dev),
                "gnorm": torch.as_tensor(self.gnorm, device=dev),
                "member": torch.as_tensor(self.member, device=dev),
                "absent": torch.as_tensor(self._absent, device=dev, dtype=dt),
                "design_b": torch.as_tensor(self.design_b, device=dev, dtype=dt),
            }
        return self._torch[device]

    def _search_torch(self, r: NDArray, rc: NDArray, device: str):
        """As :meth:`_search_numpy`, the bounds and the candidate choice on PyTorch."""
        st = self._torch_state(device)
        torch = st["torch"]
        dev, dt = st["device"], st["dtype"]
        bsz, n_cl = r.shape[0], self.n_clusters
        m = self.member.shape[1]
        unit = _F32_EPS if dt == torch.float32 else 2.0**-50
        eps = (self.n_pix + self.design_b.shape[1] + 8) * unit
        with _f32_highest(torch):
            rct = torch.as_tensor(rc, device=dev)
            n_rc = torch.linalg.vector_norm(rct, dim=1)[:, None]
            n_all = torch.as_tensor(np.linalg.norm(r, axis=1), device=dev)[:, None]
            rlow = rct.to(dt)
            g = (st["coarse"] @ rlow.T).T.reshape(bsz, -1, n_cl)
            odd, even, lin, sq = (torch.as_tensor(t, device=dev) for t in self._bound_terms)
            ub = g[:, 0] + g[:, odd].abs().sum(dim=1) + g[:, even].clamp(min=0.0).sum(dim=1)
            if lin.numel():
                b, a = g[:, lin], g[:, sq]
                edge = b.abs() + a
                inner = edge + a < 0
                quad = b * b / torch.where(inner, -4.0 * a, torch.ones_like(a))
                ub = ub + torch.where(inner, quad, edge).sum(dim=1)
            allow_a = (st["radius"][0] + eps * st["gnorm"][0]) * n_rc + _F64_EPS * n_all
            ub = ub + allow_a.to(dt)
            ka = min(self.candidates[0], n_cl)
            vals, top = torch.topk(ub, min(ka + 1, n_cl), dim=1)
            rest = vals[:, ka] if ka < n_cl else torch.full_like(vals[:, 0], -math.inf)
            top = top[:, :ka]
            mods = st["fine"].index_select(0, top.reshape(-1)).reshape(bsz, -1, self.n_pix)
            gb = (mods @ rlow[:, :, None]).reshape(bsz, ka, -1)
            allow_b = (st["radius"][1][top] + eps * st["gnorm"][1][top]) * n_rc + (_F64_EPS * n_all)
            hi = gb @ st["design_b"].T + allow_b.to(dt)[..., None] + st["absent"][top]
            hi = hi.reshape(bsz, -1)
            n = hi.shape[1]
            kc = min(self.candidates[1], n)
            hv, pick = torch.topk(hi, min(kc + 1, n), dim=1)
            rest_hi = hv[:, kc] if kc < n else torch.full_like(hv[:, 0], -math.inf)
            pick = pick[:, :kc]
            cl = torch.gather(top, 1, torch.div(pick, m, rounding_mode="floor"))
            cand = st["member"][cl, pick % m]
            cand = torch.where(torch.isfinite(hv[:, :kc]), cand, -1)
            rest = torch.maximum(rest, rest_hi).double().cpu().numpy()
            index, corr, score = self._exact_best(r, cand.cpu().numpy())
            ok = rest < score
            return self._resolve(
                r,
                rc,
                n_rc[:, 0].cpu().numpy(),
                n_all[:, 0].cpu().numpy(),
                lambda rows: ub[torch.as_tensor(rows, device=dev)].double().cpu().numpy(),
                index,
                corr,
                score,
                ok,
            )


def _fit_clusters(
    vecs: NDArray[np.float64], valid: NDArray[np.bool_], design: NDArray[np.float64]
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Least-squares polynomial models of clusters and their largest misfits.

    Parameters
    ----------
    vecs : ndarray, shape (m, n_clusters, n_pix)
        Normalised atoms, member-major.
    valid : ndarray of bool, shape (n_clusters, m)
        Which members exist (eligible atoms inside the grid).
    design : ndarray, shape (m, n_mono)
        Monomials at the members.

    Returns
    -------
    models : ndarray of float32, shape (n_mono, n_clusters, n_pix)
    radius : ndarray, shape (n_clusters,)
        ``max_i ||a_i - sum_m u_i^m G_m||`` over valid members, with the float32 models.
    """
    m, n_cl, n_pix = vecs.shape
    n_mono = design.shape[1]
    fit = (np.linalg.pinv(design) @ vecs.reshape(m, n_cl * n_pix)).reshape(n_mono, n_cl, n_pix)
    for c in np.flatnonzero(~valid.all(axis=1)):
        rows = valid[c]
        if rows.any():
            fit[:, c] = np.linalg.lstsq(design[rows], vecs[rows, c], rcond=None)[0]
        else:
            fit[:, c] = 0.0
    g32 = fit.astype(np.float32)
    model = (design @ g32.astype(np.float64).reshape(n_mono, n_cl * n_pix)).reshape(m, n_cl, n_pix)
    rem = vecs - model
    dist = np.sqrt(np.einsum("mcp,mcp->cm", rem, rem))
    return g32, np.where(valid, dist, 0.0).max(axis=1)


def _cut(
    vecs: NDArray[np.float64], ids: NDArray[np.int64], block: tuple[int, ...]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Blocks of a (Z, Y, X, n_pix) array: (m, n_blocks, n_pix) vectors and (n_blocks, m) ids,
    blocks and members both in C order (z, y, x)."""
    z, y, x, n_pix = vecs.shape
    bz, by, bx = block
    shp = (z // bz, bz, y // by, by, x // bx, bx)
    v = vecs.reshape(*shp, n_pix).transpose(1, 3, 5, 0, 2, 4, 6)
    v = np.ascontiguousarray(v).reshape(bz * by * bx, -1, n_pix)
    i = ids.reshape(shp).transpose(0, 2, 4, 1, 3, 5).reshape(-1, bz * by * bx)
    return v, i


def _poly_bound(g: NDArray, terms: tuple[NDArray[np.int64], ...]) -> NDArray:
    """Upper bound (B, n) over ``u`` in ``[-1, 1]^3`` of ``sum_m g[:, m] u^m``, g (B, n_mono, n).

    Constant + ``|g|`` of odd monomials + ``max(g, 0)`` of even ones, except that each axis'
    ``b u + a u^2`` is maximised exactly (``b^2 / (-4a)`` inside, else ``|b| + a``).
    """
    odd, even, lin, sq = terms
    ub = g[:, 0] + np.abs(g[:, odd]).sum(axis=1) + np.maximum(g[:, even], 0.0).sum(axis=1)
    if lin.size:
        b, a = g[:, lin], g[:, sq]
        edge = np.abs(b) + a
        inner = edge + a < 0  # a < 0 and |b| < -2a: the maximum is inside
        ub += np.where(inner, b * b / np.where(inner, -4.0 * a, 1.0), edge).sum(axis=1)
    return ub


def _top(values: NDArray, k: int) -> tuple[NDArray[np.int64], NDArray]:
    """Indices (B, k) of the k largest values of each row, and the (k+1)-th largest (B,)."""
    bsz, n = values.shape
    if k >= n:
        return np.broadcast_to(np.arange(n), (bsz, n)), np.full(bsz, -np.inf)
    part = np.argpartition(values, n - k - 1, axis=1)
    rest = np.take_along_axis(values, part[:, n - k - 1 : n - k], axis=1)[:, 0]
    return part[:, n - k :], rest.astype(np.float64)


class _f32_highest:
    """Context: full float32 matrix products in PyTorch (no TF32 / bf16 shortcuts)."""

    def __init__(self, torch: Any) -> None:
        self.torch = torch

    def __enter__(self) -> None:
        self.old = self.torch.get_float32_matmul_precision()
        self.torch.set_float32_matmul_precision("highest")

    def __exit__(self, *exc: object) -> None:
        self.torch.set_float32_matmul_precision(self.old)
