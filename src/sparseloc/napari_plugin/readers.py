"""napari readers: a camera movie (lazily, through :class:`sparseloc.io.movie.Movie`) and a
PSF calibration file (the model's z-stack and the beads used).

Localization tables keep their reader in :mod:`sparseloc.napari_reader`. A calibration
reader is listed before it in ``napari.yaml`` and declines ``.h5`` files that are not
calibrations, which then open as Picasso tables.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "MOVIE_SUFFIXES",
    "get_calibration_reader",
    "get_movie_reader",
    "lazy_frames",
    "model_layer",
    "read_calibration",
    "read_movie",
]

logger = logging.getLogger(__name__)

MOVIE_SUFFIXES = (".tif", ".tiff")
CALIBRATION_SUFFIXES = (".h5", ".hdf5")
#: Metadata key of a movie layer: the files it was read from (what the widgets reopen).
MOVIE_KEY = "sparseloc_movie"


def _paths(path: str | list[str]) -> list[str]:
    return [str(path)] if isinstance(path, str | Path) else [str(p) for p in path]


def get_movie_reader(path: str | list[str]) -> Callable[..., list[Any]] | None:
    """:func:`read_movie` for TIFF files (a list: the files of one movie in order)."""
    paths = _paths(path)
    if paths and all(Path(p).suffix.lower() in MOVIE_SUFFIXES for p in paths):
        return read_movie
    return None


def lazy_frames(movie: Any) -> Any:
    """The frames of ``movie`` as a dask array, shape (frames, rows, cols), one frame a chunk,
    read only when napari shows them (reads go one at a time: the movie is not thread-safe).
    """
    import dask.array as da

    lock = threading.Lock()
    n = len(movie)
    rows, cols = movie.shape

    def load(block_info: dict | None = None) -> np.ndarray:
        i = block_info[None]["chunk-location"][0]
        with lock:
            return np.asarray(movie.frames(i, i + 1))

    return da.map_blocks(
        load,
        chunks=((1,) * n, (rows,), (cols,)),
        dtype=movie.dtype,
        meta=np.empty((0, 0, 0), dtype=movie.dtype),
    )


def read_movie(path: str | list[str]) -> list[Any]:
    """One image layer: the movie's frames (ADU), lazily; the files in its metadata.

    Raises
    ------
    ValueError
        In one sentence, for a file the command line would refuse.
    """
    from ..io.movie import Movie

    paths = _paths(path)
    movie = Movie.open(paths if len(paths) > 1 else paths[0])
    first = np.asarray(movie.frames(0, 1), dtype=np.float64)
    lo, hi = np.percentile(first, [0.5, 99.9])
    kwargs = {
        "name": Path(paths[0]).stem,
        "contrast_limits": (float(lo), float(max(hi, lo + 1))),
        "colormap": "gray",
        "metadata": {MOVIE_KEY: paths, "pixel_size_nm": movie.pixel_size},
    }
    logger.info("%s: %d frames of %s px, read lazily", paths[0], len(movie), movie.shape)
    return [(lazy_frames(movie), kwargs, "image")]


def get_calibration_reader(path: str | list[str]) -> Callable[..., list[Any]] | None:
    """:func:`read_calibration` for one sparseloc calibration file, else None."""
    paths = _paths(path)
    if len(paths) != 1 or Path(paths[0]).suffix.lower() not in CALIBRATION_SUFFIXES:
        return None
    from ..io.calibration import read_calibration_info

    try:
        read_calibration_info(paths[0])
    except ValueError:  # not a calibration (e.g. a Picasso table): another reader's file
        return None
    return read_calibration


def model_layer(
    psf: Any, name: str, source: str | None = None, pixel: float | None = None
) -> tuple[Any, dict]:
    """Image layer data of a spline PSF model: its z-stack (unit photons per plane) with z in
    nm, so that the z slider reads nm, and y, x in nm too, or in units of ``pixel`` per
    camera pixel (to lie on the scale of a bead stack layer)."""
    step = (psf.pixel_size if pixel is None else pixel) / getattr(psf, "oversample", 1)
    z = np.asarray(psf.z, dtype=float)
    kwargs = {
        "name": name,
        "scale": (float(np.median(np.diff(z))) if z.size > 1 else 1.0, step, step),
        "translate": (float(z[0]), 0.0, 0.0),
        "colormap": "magma",
        "metadata": {"source": source, "units": "nm", "axes": ("z", "y", "x")},
    }
    return np.asarray(psf.stack, dtype=np.float32), kwargs


def read_calibration(path: str | list[str]) -> list[Any]:
    """Two layers: the spline model's z-stack (unit photons per plane; z, y, x in nm, so the
    z slider reads nm) and the beads used (points at their x, y in the bead stack, nm)."""
    from ..io.calibration import load_calibration, read_calibration_beads

    p = _paths(path)[0]
    psf = load_calibration(p, model="spline")
    name = Path(p).stem
    image = (*model_layer(psf, f"{name} model", p), "image")
    beads = read_calibration_beads(p)
    used = beads[beads["used"].astype(bool)] if len(beads) else beads
    points = (
        np.column_stack([used["y_nm"].to_numpy(float), used["x_nm"].to_numpy(float)]),
        {
            "name": f"{name} beads used",
            "features": {c: used[c].to_numpy() for c in used.columns if c != "reason"},
            "size": 4 * psf.pixel_size,
            "symbol": "ring",
            "face_color": "lime",
            "metadata": {"source": p, "units": "nm", "axes": ("y", "x")},
        },
        "points",
    )
    return [image, points]
