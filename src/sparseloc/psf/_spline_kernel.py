"""The call of the numba engine's spline kernel (:func:`sparseloc.psf._spline_numba.spline_kernel`):
images and raw derivatives of K emitters from a cubic B-spline table.

:meth:`SplinePSF._images <sparseloc.psf.spline.SplinePSF>` calls it when :mod:`sparseloc.engine`
runs numba; the kernel does the NumPy path's three gathers (z planes, x columns, y rows) in one
compiled loop per emitter, with no temporaries. ``tests/test_engines.py`` checks that the two
agree.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["spline_images"]


def spline_images(
    kern: Any,
    coef: NDArray[np.float64],
    tz: NDArray[np.float64],
    tx: NDArray[np.float64],
    ty: NDArray[np.float64],
    shape: tuple[int, int],
    stride: int,
    derivatives: bool,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Images (and raw derivatives in spline-node units) of K emitters, compiled.

    Parameters
    ----------
    kern : numba dispatcher
        The compiled kernel (:attr:`sparseloc.engine.Kernels.spline`).
    coef : ndarray, shape (Nz + 2, Ny + 1, Nx + 1)
        Spline coefficients with one mirrored plane at each z end and a zero last row and
        column (where out-of-table indices point).
    tz, tx, ty : ndarray, shape (K,)
        Fractional plane index and the positions of pixel (0, 0) in node units.
    shape : (rows, cols)
        Window size (pixels).
    stride : int
        Nodes per pixel (the table's oversampling).
    derivatives : bool
        Also return d/dtx, d/dty, d/dtz (per node unit; the caller scales them).

    Returns
    -------
    out : ndarray, shape (K, rows, cols)
    der : ndarray, shape (K, 3, rows, cols) or None
    """
    rows, cols = shape
    k = tz.shape[0]
    out = np.empty((k, rows, cols))
    der = np.empty((k, 3, rows, cols)) if derivatives else np.empty((0, 3, 1, 1))
    kern(
        np.ascontiguousarray(coef, dtype=np.float64),
        np.ascontiguousarray(tz, dtype=np.float64),
        np.ascontiguousarray(tx, dtype=np.float64),
        np.ascontiguousarray(ty, dtype=np.float64),
        int(rows),
        int(cols),
        int(stride),
        out,
        der,
        bool(derivatives),
    )
    return out, (der if derivatives else None)
