"""The numba engine of the maximum-likelihood fit, for spline PSF tables (imported only when
:mod:`sparseloc.engine` chooses numba).

A frame's fits run thousands of times on windows of a few hundred pixels, where NumPy's
per-call overhead dominates; here the model, ``-log L``, the Jacobian and the Fisher matrix are
compiled loops, and the Levenberg-Marquardt rule of :mod:`sparseloc.solvers.lm` is compiled
over them. The spline images come from :func:`sparseloc.psf._spline_numba.spline_kernel`.
"""

from __future__ import annotations

import numba
import numpy as np

from ..psf._spline_numba import FASTMATH, spline_kernel
from . import lm

_jit = numba.njit(cache=True, nogil=True, fastmath=FASTMATH)


@_jit
def _solve(a, b, out):  # pragma: no cover - compiled
    """Gaussian elimination with partial pivoting; False if the matrix is singular."""
    n = b.shape[0]
    m = a.copy()
    r = b.copy()
    for i in range(n):
        piv = i
        best = abs(m[i, i])
        for j in range(i + 1, n):
            if abs(m[j, i]) > best:
                best = abs(m[j, i])
                piv = j
        if not (best > 0.0) or not np.isfinite(best):
            return False
        if piv != i:
            for c in range(n):
                t = m[i, c]
                m[i, c] = m[piv, c]
                m[piv, c] = t
            t = r[i]
            r[i] = r[piv]
            r[piv] = t
        for j in range(i + 1, n):
            f = m[j, i] / m[i, i]
            if f != 0.0:
                for c in range(i, n):
                    m[j, c] -= f * m[i, c]
                r[j] -= f * r[i]
    for i in range(n - 1, -1, -1):
        s = r[i]
        for c in range(i + 1, n):
            s -= m[i, c] * out[c]
        out[i] = s / m[i, i]
    for i in range(n):
        if not np.isfinite(out[i]):
            return False
    return True


@_jit
def _node_coords(theta, k, geo, tz, tx, ty):  # pragma: no cover - compiled
    # geo: SplinePSF.node_geometry; the expressions of sparseloc.psf.spline.table_coords
    for i in range(k):
        x = theta[4 * i]
        y = theta[4 * i + 1]
        z = theta[4 * i + 2]
        t = (z - geo[6]) / geo[7]
        if not (t >= 0.0):  # also NaN
            t = 0.0
        if t > geo[8]:
            t = geo[8]
        tz[i] = t
        tx[i] = geo[0] + (geo[4] - x) * geo[2] / geo[3]
        ty[i] = geo[1] + (geo[5] - y) * geo[2] / geo[3]


@_jit
def _model(coef, geo, theta, k, base, bg_basis, nb, img, der, derivs, mu):  # pragma: no cover
    rows, cols = mu.shape
    tz = np.empty(k)
    tx = np.empty(k)
    ty = np.empty(k)
    _node_coords(theta, k, geo, tz, tx, ty)
    stride = int(geo[2])
    spline_kernel(coef, tz, tx, ty, rows, cols, stride, img, der, derivs)
    for r in range(rows):
        for c in range(cols):
            s = base[r, c]
            for j in range(nb):
                s += theta[4 * k + j] * bg_basis[j, r, c]
            for i in range(k):
                s += theta[4 * i + 3] * img[i, r, c]
            mu[r, c] = s


@_jit
def _nll(mu, v, yv, weight):  # pragma: no cover - compiled
    s = 0.0
    rows, cols = mu.shape
    for r in range(rows):
        for c in range(cols):
            m = mu[r, c] + v[r, c]
            if not (m > 0.0) or not np.isfinite(m):
                return np.inf
            s += m - yv[r, c] * np.log(m)
    return weight * s


@_jit
def _censored_nll(mu, v, yv, keep, weight):  # pragma: no cover - compiled
    """The terms of :func:`_nll` at the censored pixels (``keep`` 0), taken out of it where
    there are any (without, the likelihood is the plain loop's, bit for bit)."""
    s = 0.0
    rows, cols = mu.shape
    for r in range(rows):
        for c in range(cols):
            if keep[r, c] == 0.0:
                m = mu[r, c] + v[r, c]
                s += m - yv[r, c] * np.log(m)
    return weight * s


_clamp = _jit(lm.clamp)
_damped_system = _jit(lm.damped_system)


@_jit
def _jacobian(theta, k, img, der, geo, bg_basis, nb, jac):  # pragma: no cover - compiled
    rows = img.shape[1]
    cols = img.shape[2]
    sxy = -geo[2] / geo[3]
    sz = 1.0 / geo[7]
    for i in range(k):
        n = theta[4 * i + 3]
        for r in range(rows):
            for c in range(cols):
                p = r * cols + c
                jac[4 * i, p] = der[i, 0, r, c] * sxy * n
                jac[4 * i + 1, p] = der[i, 1, r, c] * sxy * n
                jac[4 * i + 2, p] = der[i, 2, r, c] * sz * n
                jac[4 * i + 3, p] = img[i, r, c]
    for j in range(nb):
        for r in range(rows):
            for c in range(cols):
                jac[4 * k + j, r * cols + c] = bg_basis[j, r, c]


@_jit
def _scoring(mu, v, y_v, keep, weight, jac, inv_mu, g_pix, wj, grad, fisher):  # pragma: no cover
    """Gradient of the weighted negative log-likelihood and the Fisher matrix, in place
    (``keep``: each pixel's weight, 0 where censored)."""
    cols = mu.shape[1]
    npar, npix = jac.shape
    for p in range(npix):
        r = p // cols
        c = p - r * cols
        muv = mu[r, c] + v[r, c]
        inv_mu[p] = 1.0 / muv if keep[r, c] != 0.0 else 0.0
        g_pix[p] = 1.0 - y_v[r, c] / muv if keep[r, c] != 0.0 else 0.0
    # parameter-major loops: contiguous rows of jac (vectorised)
    for q in range(npar):
        acc = 0.0
        for p in range(npix):
            acc += jac[q, p] * g_pix[p]
            wj[q, p] = jac[q, p] * inv_mu[p]
        grad[q] = weight * acc
    # The Fisher matrix's upper triangle in 2 x 4 blocks of (q, s): each pixel's two wj and
    # four jac values feed eight sums held in registers, instead of one product per load
    # (-44 % scoring time for 8 emitters on 35 x 35 pixels). Indices past the end are
    # clamped: an edge block recomputes some entries, with the same values.
    for q in range(0, npar, 2):
        q1 = min(q + 1, npar - 1)
        for s in range(q, npar, 4):
            s1 = min(s + 1, npar - 1)
            s2 = min(s + 2, npar - 1)
            s3 = min(s + 3, npar - 1)
            a0 = a1 = a2 = a3 = b0 = b1 = b2 = b3 = 0.0
            for p in range(npix):
                w0 = wj[q, p]
                w1 = wj[q1, p]
                j0 = jac[s, p]
                j1 = jac[s1, p]
                j2 = jac[s2, p]
                j3 = jac[s3, p]
                a0 += w0 * j0
                a1 += w0 * j1
                a2 += w0 * j2
                a3 += w0 * j3
                b0 += w1 * j0
                b1 += w1 * j1
                b2 += w1 * j2
                b3 += w1 * j3
            fisher[q, s] = weight * a0
            fisher[q, s1] = weight * a1
            fisher[q, s2] = weight * a2
            fisher[q, s3] = weight * a3
            fisher[q1, s] = weight * b0
            fisher[q1, s1] = weight * b1
            fisher[q1, s2] = weight * b2
            fisher[q1, s3] = weight * b3
    # the blocks also wrote some entries below the diagonal: copy the upper triangle down
    for q in range(npar):
        for s in range(q + 1, npar):
            fisher[s, q] = fisher[q, s]


# The fit's state is one tuple (built by lm_fit), by index: 0 coef, 1 geo, 2 y_v, 3 v, 4 base,
# 5 bg_basis, 6 weight, 7 k, 8 lo, 9 hi, 10 min_bg, 11 theta, 12 trial, 13 img, 14 der, 15 cur,
# 16 mu, 17 mu_t, 18 jac, 19 grad, 20 fisher, 21 a, 22 step, 23 inv_mu, 24 g_pix, 25 wj,
# 26 keep (each pixel's weight in the likelihood, 0 where censored), 27 whether any is. The
# images and derivatives are double-buffered (``cur[0]`` is the current one): trial steps are
# rendered with their derivatives, so an accepted step (most are) is not rendered again.


@_jit
def _evaluate(s):  # pragma: no cover - compiled
    coef, geo, y_v, v, base, bg_basis, weight, k = s[:8]
    theta, img, der, cur, mu, jac = s[11], s[13], s[14], s[15], s[16], s[18]
    nb = bg_basis.shape[0]
    c = cur[0]
    _model(coef, geo, theta, k, base, bg_basis, nb, img[c], der[c], True, mu)
    f = _nll(mu, v, y_v, weight)
    if s[27]:
        f -= _censored_nll(mu, v, y_v, s[26], weight)
    _jacobian(theta, k, img[c], der[c], geo, bg_basis, nb, jac)
    return f


@_jit
def _score(s):  # pragma: no cover - compiled
    y_v, v, weight = s[2], s[3], s[6]
    mu, jac, grad, fisher, inv_mu, g_pix, wj = s[16], s[18], s[19], s[20], s[23], s[24], s[25]
    _scoring(mu, v, y_v, s[26], weight, jac, inv_mu, g_pix, wj, grad, fisher)


@_jit
def _trial(s, lam):  # pragma: no cover - compiled
    coef, geo, y_v, v, base, bg_basis, weight, k, lo, hi, min_bg, theta, trial = s[:13]
    img, der, cur, mu_t = s[13], s[14], s[15], s[17]
    grad, fisher, a, step = s[19], s[20], s[21], s[22]
    _damped_system(fisher, lam, a)
    if not _solve(a, -grad, step):
        return np.inf
    for q in range(theta.shape[0]):
        trial[q] = theta[q] + step[q]
    _clamp(trial, k, lo, hi, min_bg)
    t = 1 - cur[0]
    _model(coef, geo, trial, k, base, bg_basis, bg_basis.shape[0], img[t], der[t], True, mu_t)
    f = _nll(mu_t, v, y_v, weight)
    if s[27]:
        f -= _censored_nll(mu_t, v, y_v, s[26], weight)
    return f


@_jit
def _accept(s):  # pragma: no cover - compiled
    geo, bg_basis, k, theta, trial = s[1], s[5], s[7], s[11], s[12]
    img, der, cur, mu, mu_t, jac = s[13], s[14], s[15], s[16], s[17], s[18]
    theta[:] = trial
    mu[:, :] = mu_t
    cur[0] = 1 - cur[0]
    c = cur[0]
    _jacobian(theta, k, img[c], der[c], geo, bg_basis, bg_basis.shape[0], jac)


_levenberg_marquardt = _jit(lm.make_levenberg_marquardt(_evaluate, _score, _trial, _accept))


def lm_fit(coef, geo, y_v, v, keep, base, bg_basis, weight, theta0, k, lo, hi, min_bg, max_iter,
           tol):  # fmt: skip
    """The Levenberg-Marquardt fit of ``k`` emitters on a spline table (arrays as float64,
    C-contiguous; ``geo``: :meth:`SplinePSF.node_geometry`; ``keep``: each pixel's weight in
    the likelihood, 0 where censored); returns theta, mu, f, the Fisher matrix at theta,
    converged, n_iter."""
    rows, cols = y_v.shape
    npar = theta0.shape[0]
    kk = max(k, 1)
    state = (
        coef, geo, y_v, v, base, bg_basis, float(weight), int(k), lo, hi, float(min_bg),
        theta0.copy(), np.empty(npar),
        np.empty((2, kk, rows, cols)), np.empty((2, kk, 3, rows, cols)), np.zeros(1, np.int64),
        np.empty((rows, cols)), np.empty((rows, cols)), np.empty((npar, rows * cols)),
        np.empty(npar), np.empty((npar, npar)), np.empty((npar, npar)), np.empty(npar),
        np.empty(rows * cols), np.empty(rows * cols), np.empty((npar, rows * cols)),
        np.ascontiguousarray(keep, dtype=np.float64), bool(np.any(keep == 0.0)),
    )  # fmt: skip
    f, converged, n_iter = _levenberg_marquardt(state, int(max_iter), float(tol))
    return state[11], state[16], f, state[20], converged, n_iter


def warm_up():
    """Run :func:`lm_fit` once on a tiny problem (compiling it or loading it from numba's
    cache); returns it."""
    coef = np.zeros((6, 6, 6))
    geo = np.array([2.0, 2.0, 1.0, 100.0, 50.0, 50.0, 0.0, 10.0, 2.0])
    lm_fit(
        coef,
        geo,
        np.full((2, 2), 5.0),
        np.zeros((2, 2)),
        np.ones((2, 2)),
        np.zeros((2, 2)),
        np.ones((1, 2, 2)),
        1.0,
        np.array([100.0, 100.0, 10.0, 100.0, 5.0]),
        1,
        np.array([0.0, 0.0, 0.0, 1.0]),
        np.array([200.0, 200.0, 20.0, np.inf]),
        1e-3,
        2,
        1e-6,
    )
    return lm_fit
