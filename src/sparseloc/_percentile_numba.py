"""numba kernel of the temporal background's sliding percentile (imported only when
:mod:`sparseloc.engine` chooses numba)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _lerp(a, b, t):  # pragma: no cover - compiled
    # NumPy's linear interpolation of np.percentile, branch for branch (same rounding)
    d = b - a
    if t >= 0.5:
        return b - d * (1.0 - t)
    return a + d * t


@numba.njit(cache=True, nogil=True)
def sliding_percentiles(chunk, centres, half, q, out):  # pragma: no cover - compiled
    """``out[k]``: the per-pixel percentile ``q`` (0-100, linear) of ``chunk[lo:hi]`` with
    ``lo = max(c - half, 0)``, ``hi = min(c + half + 1, n)`` for ``c = centres[k]``
    (increasing). Each pixel keeps its window sorted as it slides: one value out and one
    in per frame instead of a sort."""
    n, rows, cols = chunk.shape
    m = centres.shape[0]
    win = np.empty(2 * half + 2)
    for r in range(rows):
        for c in range(cols):
            size = 0
            lo = 0
            hi = 0
            for k in range(m):
                a = max(centres[k] - half, 0)
                b = min(centres[k] + half + 1, n)
                if k == 0 or a < lo or a > hi:  # (re)start the window
                    size = 0
                    lo = a
                    hi = a
                while lo < a:  # drop chunk[lo] from the sorted window
                    v = chunk[lo, r, c]
                    i = 0
                    while win[i] != v:
                        i += 1
                    for j in range(i, size - 1):
                        win[j] = win[j + 1]
                    size -= 1
                    lo += 1
                while hi < b:  # insert chunk[hi]
                    v = chunk[hi, r, c]
                    i = size
                    while i > 0 and win[i - 1] > v:
                        win[i] = win[i - 1]
                        i -= 1
                    win[i] = v
                    size += 1
                    hi += 1
                vi = q / 100.0 * (size - 1)
                below = int(np.floor(vi))
                above = min(below + 1, size - 1)
                out[k, r, c] = _lerp(win[below], win[above], vi - below)
