"""numba kernel of the frame pursuit's template selection (imported only when used).

:meth:`sparseloc.solvers.frame_mp.Correlator.best` keeps, per pixel, the template whose
normalised correlation is largest. In NumPy that is a product, an ``argmax`` and two
``take_along_axis`` gathers per batch of templates: about as long as the batch's inverse
FFTs. This loop does the same comparisons in the same order in one pass (bit-identical:
``tests/test_frame.py`` checks it against the NumPy path).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def select_best(full, h, inv_norm, j0, sb, jb, cb):  # pragma: no cover - compiled
    """Fold one batch of correlations into the running best, in place.

    ``full`` (n, >= h + rows, >= h + cols) holds the batch's circular correlations, whose
    pixels ``[h : h + rows, h : h + cols]`` are the frame's; ``inv_norm`` is (n, rows, cols).
    Both are single precision and the score is their product in single precision, as in
    NumPy. The running best ``sb`` (score), ``jb`` (template, int32) and ``cb``
    (correlation) are single precision too: they only ever hold single-precision values,
    and half the bytes make the loop faster.
    A template replaces the running best only when its score is strictly larger, and the
    templates are visited in order: the first of equal scores wins, as with ``argmax``.
    """
    n = full.shape[0]
    rows, cols = sb.shape
    for k in range(n):
        jj = np.int32(j0 + k)
        for r in range(rows):
            fr = full[k, h + r]
            ir = inv_norm[k, r]
            sbr = sb[r]
            jbr = jb[r]
            cbr = cb[r]
            for c in range(cols):
                p = fr[h + c]
                s = p * ir[c]
                b = sbr[c]
                better = s > b
                sbr[c] = s if better else b
                jbr[c] = jj if better else jbr[c]
                cbr[c] = p if better else cbr[c]
