"""Between napari layers and the library: a movie layer as a movie, the current frame, a
table as a points layer over the frames."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .readers import MOVIE_KEY, MOVIE_SUFFIXES

__all__ = [
    "ArrayMovie",
    "current_frame",
    "movie_files",
    "movie_of",
    "points_for_table",
    "table_of",
]

#: Metadata key of a points layer that holds a localization table (a DataFrame).
TABLE_KEY = "sparseloc_table"


class ArrayMovie:
    """Camera frames held by a layer (an array, not a file) with the movie interface the
    library reads: ``len()``, ``shape`` (rows, cols), ``dtype``, ``frames(start, stop)``,
    ``pixel_size`` (None: unknown) and ``paths`` (none)."""

    pixel_size = None
    paths: tuple[Path, ...] = ()

    def __init__(self, data: Any) -> None:
        self._data = data

    def __len__(self) -> int:
        return int(self._data.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self._data.shape[-2]), int(self._data.shape[-1])

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self._data.dtype)

    def frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Frames ``start:stop`` as an array (frames, rows, cols)."""
        return np.asarray(self._data[start : len(self) if stop is None else stop])

    def close(self) -> None:
        """Nothing to close (the layer keeps its data)."""


def movie_files(layer: Any) -> list[str]:
    """The movie files a layer was read from: ours, or napari's own TIFF reader's."""
    paths = list(layer.metadata.get(MOVIE_KEY) or [])
    if not paths:
        src = getattr(getattr(layer, "source", None), "path", None)
        if src and Path(str(src)).suffix.lower() in MOVIE_SUFFIXES:
            paths = [str(src)]
    return paths


def movie_of(layer: Any, what: str = "movie") -> Any:
    """The movie of an image layer: its files reopened as the command line opens them, else
    its array as an :class:`ArrayMovie` (a 2D image is one frame).

    Raises
    ------
    ValueError
        In one sentence: no layer, an RGB or multiscale layer, or not (rows, cols) frames.
    """
    from ..io.movie import Movie

    if layer is None:
        raise ValueError(f"choose the {what} layer (open a TIFF movie in napari first)")
    files = movie_files(layer)
    if files:
        return Movie.open(files if len(files) > 1 else files[0])
    if getattr(layer, "multiscale", False) or getattr(layer, "rgb", False):
        raise ValueError(
            f"the layer {layer.name!r} holds RGB or multiscale images; expected one grey "
            "value per pixel"
        )
    data = layer.data
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3:
        raise ValueError(
            f"the layer {layer.name!r} holds images of shape {tuple(layer.data.shape)}; "
            "expected (rows, cols) frames"
        )
    return ArrayMovie(data)


def current_frame(viewer: Any, layer: Any) -> int:
    """The frame of ``layer`` the viewer shows (0 for a 2D image)."""
    if layer.ndim < 3:
        return 0
    world = float(viewer.dims.point[-3])
    f = round((world - float(layer.translate[-3])) / float(layer.scale[-3]))
    return int(np.clip(f, 0, layer.data.shape[-3] - 1))


def points_for_table(
    table: pd.DataFrame,
    pixel_size: float,
    image: Any,
    z_range: tuple[float, float],
    name: str,
) -> tuple[np.ndarray, dict[str, Any]]:
    """A points layer over ``image``: one ring per localization at its pixel position
    (frame, row, col; or row, col over a 2D image), coloured by z with render's colour map,
    the table's columns (photons, uncertainties, ...) as its features.

    Parameters
    ----------
    table : DataFrame
        Localization table (nm, native coordinates: pixel (r, c) centred at (c + 0.5) px).
    pixel_size : float
        Camera pixel size (nm).
    image : napari Image layer
        The frames; the points take its scale and translation.
    z_range : (float, float)
        Depths (nm) at the ends of the colour map.
    name : str
        Layer name.

    Returns
    -------
    (ndarray, dict)
        Layer data and keyword arguments for ``viewer.add_points``.
    """
    from ..render import DEPTH_CMAP

    rc = [table["y_nm"].to_numpy(float) / pixel_size - 0.5]
    rc.append(table["x_nm"].to_numpy(float) / pixel_size - 0.5)
    if image.ndim >= 3:
        rc.insert(0, table["frame"].to_numpy(float))
    data = np.column_stack(rc) if len(table) else np.zeros((0, len(rc)))
    features = {c: table[c].to_numpy() for c in table.columns}
    features["flag"] = table["flag"].astype(str).to_numpy()
    kwargs = {
        "name": name,
        "features": pd.DataFrame(features),
        "face_color": "z_nm",
        "face_colormap": DEPTH_CMAP,
        "face_contrast_limits": (float(z_range[0]), float(z_range[1])),
        "symbol": "ring",
        "size": 7,
        "border_width": 0,
        "scale": tuple(image.scale[-len(rc) :]),
        "translate": tuple(image.translate[-len(rc) :]),
        "metadata": {TABLE_KEY: table, "pixel_size_nm": pixel_size},
    }
    return data, kwargs


def table_of(layer: Any) -> tuple[pd.DataFrame, str]:
    """The localization table of a points layer (from a table file or a widget) and its name.

    Raises
    ------
    ValueError
        If no layer is chosen or it holds no table.
    """
    from ..io.tables import read_table_and_metadata

    if layer is None:
        raise ValueError("choose a localization table (a points layer or a table file)")
    table = layer.metadata.get(TABLE_KEY)
    if table is not None:
        return table, layer.name
    src = layer.metadata.get("source")
    if src:
        return read_table_and_metadata(src)[0], layer.name
    raise ValueError(f"the layer {layer.name!r} holds no localization table")
