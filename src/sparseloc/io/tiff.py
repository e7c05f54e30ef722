"""TIFF stacks: uint16 camera movies of shape (frames, rows, cols).

Movies are written as ImageJ hyperstacks (axes ``TYX``, uncompressed, contiguous), which Fiji
opens directly and which can exceed 4 GB. The pixel size is stored in nm as the resolution and
as ``pixel_size_nm`` in the ImageJ description.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from numpy.typing import ArrayLike, NDArray

from .atomic import atomic_path

__all__ = ["read_tiff", "read_tiff_metadata", "write_tiff"]

log = logging.getLogger(__name__)

# Keys tifffile writes itself into an ImageJ description.
_IMAGEJ_RESERVED = {
    "ImageJ",
    "images",
    "channels",
    "slices",
    "frames",
    "hyperstack",
    "mode",
    "loop",
    "unit",
    "spacing",
    "finterval",
    "axes",
    "min",
    "max",
}


def _as_uint16_stack(movie: ArrayLike) -> NDArray[np.uint16]:
    arr = np.asarray(movie)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or 0 in arr.shape:
        raise ValueError(
            f"movie must be a non-empty (frames, rows, cols) stack, got shape {arr.shape}"
        )
    if arr.dtype == np.uint16:
        return arr
    if not (np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_):
        raise ValueError(
            f"movie must hold integer camera counts (uint16), got dtype {arr.dtype}; "
            "round and clip it first (e.g. with sparseloc.camera.apply_noise)"
        )
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi > np.iinfo(np.uint16).max:
        raise ValueError(f"movie values {lo}..{hi} do not fit in uint16 (0..65535)")
    return arr.astype(np.uint16)


def write_tiff(
    path: str | Path,
    movie: ArrayLike,
    *,
    pixel_size: float | None = None,
    metadata: dict[str, Any] | None = None,
) -> Path:
    """Write a uint16 movie as a TIFF stack, atomically.

    Parameters
    ----------
    path : str or Path
        Destination file; its folder must exist.
    movie : array_like, shape (frames, rows, cols) or (rows, cols)
        Camera counts in ADU; integer data within 0..65535 is converted to uint16, floating
        point data is refused.
    pixel_size : float, optional
        Pixel size in nm, stored as the resolution (pixels per nm) and ``pixel_size_nm``.
    metadata : dict, optional
        Extra ``key: value`` pairs (numbers or strings) stored in the ImageJ description.

    Returns
    -------
    Path
        The path written.

    Raises
    ------
    ValueError
        If the folder does not exist, the movie has the wrong shape or dtype, or the pixel
        size is not positive.
    """
    data = _as_uint16_stack(movie)
    meta: dict[str, Any] = {"axes": "TYX"}
    kwargs: dict[str, Any] = {}
    if pixel_size is not None:
        px = float(pixel_size)
        if not (np.isfinite(px) and px > 0):
            raise ValueError(f"pixel_size must be a positive number of nm, got {pixel_size!r}")
        meta["unit"] = "nm"
        meta["pixel_size_nm"] = px
        kwargs["resolution"] = (1.0 / px, 1.0 / px)
    for key, value in (metadata or {}).items():
        key = str(key)
        if key in _IMAGEJ_RESERVED or not key.isidentifier():
            raise ValueError(f"metadata key {key!r} is reserved or not a plain identifier")
        if isinstance(value, (bool, np.bool_)):
            value = str(bool(value)).lower()
        elif isinstance(value, (int, float, np.integer, np.floating)):
            value = value.item() if isinstance(value, np.generic) else value
        else:
            value = str(value)
            if "\n" in value or not value.isascii():
                raise ValueError(f"metadata value of {key!r} must be one line of ASCII text")
        meta[key] = value
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, data, imagej=True, metadata=meta, **kwargs)
    log.info("wrote %s: %d frames of %d x %d px", path, *data.shape)
    return Path(path)


def read_tiff(path: str | Path) -> NDArray[np.generic]:
    """Read a whole TIFF stack into memory (a thin wrapper over :class:`~.movie.Movie`).

    Parameters
    ----------
    path : str or Path
        TIFF or OME-TIFF file.

    Returns
    -------
    movie : ndarray, shape (frames, rows, cols)
        In its stored dtype; a single 2-D image becomes one frame.

    Raises
    ------
    ValueError
        If the file does not exist, is not a readable TIFF, is truncated, or holds more than one
        value per pixel (e.g. RGB).
    """
    from .movie import Movie

    with Movie.open(path, allow_float=True) as movie:
        return movie.frames(0, len(movie))


def read_tiff_metadata(path: str | Path) -> dict[str, Any]:
    """Metadata of a TIFF written by :func:`write_tiff` (or ImageJ).

    Returns
    -------
    dict
        ``shape`` (frames, rows, cols), ``dtype``, ``pixel_size`` (nm, or None when unknown, as
        :class:`~.movie.Movie` reads it) and any other ``key: value`` pairs of the ImageJ
        description.
    """
    from .movie import Movie

    with Movie.open(path, allow_float=True) as movie:
        out = {
            "shape": (len(movie), *movie.shape),
            "dtype": str(movie.dtype),
            "pixel_size": movie.pixel_size,
        }
    with tifffile.TiffFile(path) as tif:
        ij = dict(tif.imagej_metadata or {})
    extras = {k: v for k, v in ij.items() if k not in ("ImageJ", "pixel_size_nm")}
    return {**extras, **out}
