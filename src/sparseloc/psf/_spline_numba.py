"""numba kernels of :mod:`sparseloc.psf._spline_kernel` (imported only when used)."""

from __future__ import annotations

import numba
import numpy as np

from .spline import bspline_terms

#: Let LLVM reorder and fuse sums (vector loops) but keep NaN/inf semantics: the
#: likelihood and the solver test for non-finite values.
FASTMATH = {"reassoc", "contract", "nsz"}


_terms = numba.njit(cache=True, inline="always")(bspline_terms)


@numba.njit(cache=True, inline="always")
def _weights(f, w, dw):
    t = _terms(f)
    for m in range(4):
        w[m] = t[m]
        dw[m] = t[4 + m]


@numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
def spline_kernel(coef, tz, tx, ty, rows, cols, stride, out, der, derivatives):  # pragma: no cover
    """Images (K, rows, cols) and raw derivatives (K, 3, rows, cols) of K emitters.

    Separable, in the order of the NumPy path: the four z planes are combined once over the
    emitter's footprint of nodes (:func:`_z_pass`), then the x neighbours per column
    (:func:`_x_pass`), then the y neighbours per row (:func:`_y_pass`); numba inlines the
    three. The inner loops carry no branches (the footprint's part inside the table is
    found once per row, the derivative switch is outside the loops), so LLVM vectorises
    them, with the same sums in the same order.
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
        # the footprint's columns inside the table: [t_lo, t_hi)
        t_lo = min(max(-bx, 0), fx)
        t_hi = max(min(nx - bx, fx), t_lo)
        _z_pass(coef, iz, wz, dwz, by, bx, fy, ny, t_lo, t_hi, pz, dpz, derivatives)
        _x_pass(pz, dpz, wx, dwx, fy, cols, stride, a_v, a_x, a_z, derivatives)
        _y_pass(a_v, a_x, a_z, wy, dwy, rows, cols, stride, k, out, der, derivatives)


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _z_pass(
    coef, iz, wz, dwz, by, bx, fy, ny, t_lo, t_hi, pz, dpz, derivatives
):  # pragma: no cover
    """``pz`` (fy, fx): planes ``iz..iz+3`` weighted by ``wz`` over the footprint of nodes
    from (by, bx), zero outside the table; ``dpz`` likewise with ``dwz``."""
    w0, w1, w2, w3 = wz[0], wz[1], wz[2], wz[3]
    d0, d1, d2, d3 = dwz[0], dwz[1], dwz[2], dwz[3]
    for u in range(fy):
        yi = by + u
        if yi < 0 or yi >= ny:
            pz[u, :] = 0.0
            dpz[u, :] = 0.0
            continue
        pz[u, :t_lo] = 0.0
        dpz[u, :t_lo] = 0.0
        pz[u, t_hi:] = 0.0
        dpz[u, t_hi:] = 0.0
        q0 = coef[iz, yi]
        q1 = coef[iz + 1, yi]
        q2 = coef[iz + 2, yi]
        q3 = coef[iz + 3, yi]
        if derivatives:
            for t in range(t_lo, t_hi):
                xi = bx + t
                c0 = q0[xi]
                c1 = q1[xi]
                c2 = q2[xi]
                c3 = q3[xi]
                pz[u, t] = w0 * c0 + w1 * c1 + w2 * c2 + w3 * c3
                dpz[u, t] = d0 * c0 + d1 * c1 + d2 * c2 + d3 * c3
        else:
            for t in range(t_lo, t_hi):
                xi = bx + t
                pz[u, t] = w0 * q0[xi] + w1 * q1[xi] + w2 * q2[xi] + w3 * q3[xi]


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _x_pass(pz, dpz, wx, dwx, fy, cols, stride, a_v, a_x, a_z, derivatives):  # pragma: no cover
    """``a_v`` (fy, cols): the four x neighbours of each column of ``pz`` weighted by ``wx``;
    ``a_x`` with ``dwx``, ``a_z`` the same of ``dpz``."""
    x0, x1, x2, x3 = wx[0], wx[1], wx[2], wx[3]
    e0, e1, e2, e3 = dwx[0], dwx[1], dwx[2], dwx[3]
    for u in range(fy):
        if derivatives:
            for c in range(cols):
                t0 = stride * c
                p0 = pz[u, t0]
                p1 = pz[u, t0 + 1]
                p2 = pz[u, t0 + 2]
                p3 = pz[u, t0 + 3]
                a_v[u, c] = x0 * p0 + x1 * p1 + x2 * p2 + x3 * p3
                a_x[u, c] = e0 * p0 + e1 * p1 + e2 * p2 + e3 * p3
                a_z[u, c] = (
                    x0 * dpz[u, t0]
                    + x1 * dpz[u, t0 + 1]
                    + x2 * dpz[u, t0 + 2]
                    + x3 * dpz[u, t0 + 3]
                )
        else:
            for c in range(cols):
                t0 = stride * c
                a_v[u, c] = (
                    x0 * pz[u, t0] + x1 * pz[u, t0 + 1] + x2 * pz[u, t0 + 2] + x3 * pz[u, t0 + 3]
                )


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _y_pass(
    a_v, a_x, a_z, wy, dwy, rows, cols, stride, k, out, der, derivatives
):  # pragma: no cover
    """``out[k]``: the four y neighbours of each row of ``a_v`` weighted by ``wy``; ``der[k]``
    the x, y and z derivatives (``a_x``; ``a_v`` with ``dwy``; ``a_z``)."""
    y0, y1, y2, y3 = wy[0], wy[1], wy[2], wy[3]
    f0, f1, f2, f3 = dwy[0], dwy[1], dwy[2], dwy[3]
    for r in range(rows):
        u0 = stride * r
        if derivatives:
            for c in range(cols):
                v0 = a_v[u0, c]
                v1 = a_v[u0 + 1, c]
                v2 = a_v[u0 + 2, c]
                v3 = a_v[u0 + 3, c]
                out[k, r, c] = y0 * v0 + y1 * v1 + y2 * v2 + y3 * v3
                der[k, 0, r, c] = (
                    y0 * a_x[u0, c]
                    + y1 * a_x[u0 + 1, c]
                    + y2 * a_x[u0 + 2, c]
                    + y3 * a_x[u0 + 3, c]
                )
                der[k, 1, r, c] = f0 * v0 + f1 * v1 + f2 * v2 + f3 * v3
                der[k, 2, r, c] = (
                    y0 * a_z[u0, c]
                    + y1 * a_z[u0 + 1, c]
                    + y2 * a_z[u0 + 2, c]
                    + y3 * a_z[u0 + 3, c]
                )
        else:
            for c in range(cols):
                out[k, r, c] = (
                    y0 * a_v[u0, c]
                    + y1 * a_v[u0 + 1, c]
                    + y2 * a_v[u0 + 2, c]
                    + y3 * a_v[u0 + 3, c]
                )
