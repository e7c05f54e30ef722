"""A NumPy ``.npy`` file read as a plain array, never as pickled objects."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ["NOT_AN_ARRAY", "load_array"]

#: The refusal of a file that holds no plain array. NumPy's own message reads a damaged header
#: as pickled data and advises ``allow_pickle=True``: advice for Python code, and unsafe.
NOT_AN_ARRAY = "not a NumPy array file (as numpy.save writes): damaged or of another kind"


def load_array(path: str | Path) -> NDArray:
    """The array in ``path`` (``numpy.load`` with ``allow_pickle=False``).

    Raises
    ------
    ValueError
        :data:`NOT_AN_ARRAY` for a file that holds no plain array (a damaged header, pickled
        objects); OSError and others as ``numpy.load`` raises them.
    """
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise ValueError(NOT_AN_ARRAY) from exc
