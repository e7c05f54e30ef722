"""Compiled Levenberg-Marquardt loop of :func:`sparseloc.solvers.refine.fit_emitters` for
spline PSFs (numba; imported only when used).

The Python loop spends most of its time in per-iteration overhead on small arrays (a frame's
fits call it thousands of times on windows of a few hundred pixels); this is the same
algorithm, step for step (same damping rule, same clamps, same acceptance test), with the
spline images computed by :func:`sparseloc.psf._spline_numba.spline_kernel`.
"""

from __future__ import annotations

import numba
import numpy as np

from ..psf._spline_numba import _FAST, spline_kernel


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _clamp(theta, k, lo, hi, min_bg):  # pragma: no cover - compiled
    for i in range(k):
        for j in range(4):
            t = theta[4 * i + j]
            if not (t >= lo[j]):  # also NaN
                t = lo[j]
            if t > hi[j]:
                t = hi[j]
            theta[4 * i + j] = t
    if not (theta[4 * k] >= min_bg):
        theta[4 * k] = min_bg


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def _scoring(mu, v, y_v, weight, jac, inv_mu, g_pix, wj, grad, fisher):  # pragma: no cover
    """Gradient of the weighted negative log-likelihood and the Fisher matrix, in place."""
    cols = mu.shape[1]
    npar, npix = jac.shape
    for p in range(npix):
        r = p // cols
        c = p - r * cols
        muv = mu[r, c] + v[r, c]
        inv_mu[p] = 1.0 / muv
        g_pix[p] = 1.0 - y_v[r, c] / muv
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


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def lm_fit(
    coef, geo, y_v, v, base, bg_basis, weight, theta0, k, lo, hi, min_bg, max_iter, tol
):  # pragma: no cover - compiled
    """LM with Fisher scoring; returns theta, mu, f, Fisher matrix, converged, n_iter."""
    rows, cols = y_v.shape
    npix = rows * cols
    nb = bg_basis.shape[0]
    npar = theta0.shape[0]
    img = np.empty((max(k, 1), rows, cols))
    der = np.empty((max(k, 1), 3, rows, cols))
    # The trial steps are rendered with their derivatives into a second pair of buffers: an
    # accepted step (most are) then needs no second rendering, the buffers are swapped.
    img_t = np.empty((max(k, 1), rows, cols))
    der_t = np.empty((max(k, 1), 3, rows, cols))
    inv_mu = np.empty(npix)
    g_pix = np.empty(npix)
    theta = theta0.copy()
    mu = np.empty((rows, cols))
    _model(coef, geo, theta, k, base, bg_basis, nb, img, der, True, mu)
    f = _nll(mu, v, y_v, weight)
    jac = np.empty((npar, npix))
    _jacobian(theta, k, img, der, geo, bg_basis, nb, jac)
    lam = 1e-3
    converged = False
    n_iter = 0
    grad = np.empty(npar)
    fisher = np.empty((npar, npar))
    a = np.empty((npar, npar))
    step = np.empty(npar)
    trial = np.empty(npar)
    mu_t = np.empty((rows, cols))
    wj = np.empty((npar, npix))
    f_t = np.inf
    scored = False  # whether fisher is that of the current theta
    for it in range(1, max_iter + 1):
        n_iter = it
        _scoring(mu, v, y_v, weight, jac, inv_mu, g_pix, wj, grad, fisher)
        scored = True
        improved = False
        for _ in range(12):
            for q in range(npar):
                for s in range(npar):
                    a[q, s] = fisher[q, s]
                d = fisher[q, q]
                if d < 1e-12:
                    d = 1e-12
                a[q, q] += lam * d
            ok = _solve(a, -grad, step)
            if not ok:
                lam *= 10.0
                continue
            for q in range(npar):
                trial[q] = theta[q] + step[q]
            _clamp(trial, k, lo, hi, min_bg)
            _model(coef, geo, trial, k, base, bg_basis, nb, img_t, der_t, True, mu_t)
            f_t = _nll(mu_t, v, y_v, weight)
            if f_t < f:
                improved = True
                break
            lam *= 10.0
        if not improved:
            converged = True
            break
        rel = (f - f_t) / max(abs(f), 1.0)
        theta[:] = trial
        mu[:, :] = mu_t
        f = f_t
        lam = max(lam / 10.0, 1e-7)
        img, img_t = img_t, img
        der, der_t = der_t, der
        _jacobian(theta, k, img, der, geo, bg_basis, nb, jac)
        scored = False
        if rel < tol:
            converged = True
            break
    # the Fisher matrix at the result (its inverse gives the reported standard errors)
    if not scored:
        _scoring(mu, v, y_v, weight, jac, inv_mu, g_pix, wj, grad, fisher)
    return theta, mu, f, fisher, converged, n_iter
