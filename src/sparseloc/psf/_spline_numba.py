"""numba kernels of :mod:`sparseloc.psf._spline_kernel` (imported only when used)."""

from __future__ import annotations

import numba
import numpy as np

from .spline import bspline_terms

#: Let LLVM reorder and fuse sums (vector loops) but keep NaN/inf semantics: the
#: likelihood and the solver test for non-finite values.
_FAST = {"reassoc", "contract", "nsz"}


_terms = numba.njit(cache=True, inline="always")(bspline_terms)


@numba.njit(cache=True, inline="always")
def _weights(f, w, dw):
    t = _terms(f)
    for m in range(4):
        w[m] = t[m]
        dw[m] = t[4 + m]


@numba.njit(cache=True, nogil=True, fastmath=_FAST)
def spline_kernel(coef, tz, tx, ty, rows, cols, stride, out, der, derivatives):  # pragma: no cover
    """Images (K, rows, cols) and raw derivatives (K, 3, rows, cols) of K emitters.

    Separable, in the order of the NumPy path: the four z planes are combined once over the
    emitter's footprint of nodes, then the x neighbours per column, then the y neighbours
    per row.
    """
    _, ny1, nx1 = coef.shape
    ny = ny1 - 1
    nx = nx1 - 1
    wz = np.empty(4)
    dwz = np.empty(4)
    wx = np.empty(4)
    dwx = np.empty(4)
    wy = np.empty(4)
    dwy = np.empty(4)
    fy = stride * (rows - 1) + 4  # footprint of nodes along y and x
    fx = stride * (cols - 1) + 4
    pz = np.empty((fy, fx))
    dpz = np.empty((fy, fx))
    a_v = np.empty((fy, cols))
    a_x = np.empty((fy, cols))
    a_z = np.empty((fy, cols))
    for k in range(tz.shape[0]):
        iz = int(np.floor(tz[k]))
        # no bounds checks in compiled code: keep the four planes inside the table
        iz = min(max(iz, 0), coef.shape[0] - 4)
        _weights(tz[k] - iz, wz, dwz)
        i0x = np.floor(tx[k])
        _weights(tx[k] - i0x, wx, dwx)
        i0y = np.floor(ty[k])
        _weights(ty[k] - i0y, wy, dwy)
        bx = int(i0x) - 1
        by = int(i0y) - 1
        for u in range(fy):
            yi = by + u
            inside_y = yi >= 0 and yi < ny
            for t in range(fx):
                xi = bx + t
                if inside_y and xi >= 0 and xi < nx:
                    c0 = coef[iz, yi, xi]
                    c1 = coef[iz + 1, yi, xi]
                    c2 = coef[iz + 2, yi, xi]
                    c3 = coef[iz + 3, yi, xi]
                    pz[u, t] = wz[0] * c0 + wz[1] * c1 + wz[2] * c2 + wz[3] * c3
                    if derivatives:
                        dpz[u, t] = dwz[0] * c0 + dwz[1] * c1 + dwz[2] * c2 + dwz[3] * c3
                else:
                    pz[u, t] = 0.0
                    dpz[u, t] = 0.0
        for u in range(fy):
            for c in range(cols):
                t0 = stride * c
                sv = 0.0
                sx = 0.0
                sz = 0.0
                for m in range(4):
                    sv += wx[m] * pz[u, t0 + m]
                    if derivatives:
                        sx += dwx[m] * pz[u, t0 + m]
                        sz += wx[m] * dpz[u, t0 + m]
                a_v[u, c] = sv
                a_x[u, c] = sx
                a_z[u, c] = sz
        for r in range(rows):
            u0 = stride * r
            for c in range(cols):
                v = 0.0
                gx = 0.0
                gy = 0.0
                gz = 0.0
                for b in range(4):
                    v += wy[b] * a_v[u0 + b, c]
                    if derivatives:
                        gy += dwy[b] * a_v[u0 + b, c]
                        gx += wy[b] * a_x[u0 + b, c]
                        gz += wy[b] * a_z[u0 + b, c]
                out[k, r, c] = v
                if derivatives:
                    der[k, 0, r, c] = gx
                    der[k, 1, r, c] = gy
                    der[k, 2, r, c] = gz
