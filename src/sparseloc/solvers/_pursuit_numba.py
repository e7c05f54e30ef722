"""numba kernel of the frame pursuit's template selection (imported only when used).

:meth:`sparseloc.solvers.frame._Correlator.best` keeps, per pixel, the template whose
normalised correlation is largest. In NumPy that is a product, an ``argmax`` and two
``take_along_axis`` gathers per batch of templates: about as long as the batch's inverse
FFTs. This loop does the same comparisons in the same order in one pass (bit-identical:
``tests/test_frame.py`` checks it against the NumPy path).
"""

from __future__ import annotations

import numba


@numba.njit(cache=True, nogil=True)
def select_best(part, inv_norm, j0, sb, jb, cb):  # pragma: no cover - compiled
    """Fold one batch of correlations into the running best, in place.

    ``part`` and ``inv_norm`` are (n, rows, cols) single precision; the score is their
    product in single precision, as in NumPy. A template replaces the running best only
    when its score is strictly larger, and the templates are visited in order: the first
    of equal scores wins, as with ``argmax``.
    """
    n, rows, cols = part.shape
    for k in range(n):
        for r in range(rows):
            for c in range(cols):
                s = part[k, r, c] * inv_norm[k, r, c]
                if s > sb[r, c]:
                    sb[r, c] = s
                    jb[r, c] = j0 + k
                    cb[r, c] = part[k, r, c]
