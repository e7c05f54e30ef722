"""napari reader: a sparseloc table (Parquet, CSV, Picasso HDF5) as a 3D points layer.

Declared in ``napari.yaml`` (the ``napari.manifest`` entry point), so napari offers it for
``*.parquet``, ``*.csv``, ``*.hdf5`` and ``*.h5`` files. napari itself is imported only for
type checking: the functions here return plain layer-data tuples and are tested without it.

Coordinates are in nm in napari's axis order ``(z, y, x)``; each point is coloured by its
depth (``turbo``) and sized by the table's median lateral uncertainty.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover - napari is an optional extra
    from napari.types import LayerDataTuple

__all__ = ["SUFFIXES", "napari_get_reader", "read_points"]

logger = logging.getLogger(__name__)

#: File endings the reader claims (napari asks again with the path; the content decides).
SUFFIXES = (".parquet", ".csv", ".hdf5", ".h5")


def napari_get_reader(path: str | list[str]) -> Callable[..., list[LayerDataTuple]] | None:
    """The reader for ``path`` if it looks like a localization table, else ``None``.

    napari calls this with one path or a list; a list is accepted when every path qualifies.
    """
    paths = [path] if isinstance(path, str | Path) else list(path)
    if not paths or any(Path(p).suffix.lower() not in SUFFIXES for p in paths):
        return None
    return read_points


def read_points(path: str | list[str]) -> list[LayerDataTuple]:
    """One points layer per table: ``(data (N, 3) as z, y, x in nm, kwargs, "points")``.

    Raises
    ------
    ValueError
        If a file is not a localization table (napari shows the message).
    """
    from .io.tables import read_table

    paths = [path] if isinstance(path, str | Path) else list(path)
    layers: list[Any] = []
    for p in paths:
        t = read_table(p)
        z = t["z_nm"].to_numpy(np.float64)
        data = np.column_stack([z, t["y_nm"].to_numpy(float), t["x_nm"].to_numpy(float)])
        sig = np.sqrt(
            0.5 * (t["sigma_x_nm"].to_numpy(float) ** 2 + t["sigma_y_nm"].to_numpy(float) ** 2)
        )
        sig = sig[np.isfinite(sig)]
        # Points two uncertainties across, at least 10 nm (visible when zoomed in).
        size = float(max(10.0, 2.0 * np.median(sig))) if sig.size else 30.0
        features = {
            "frame": t["frame"].to_numpy(np.int64),
            "z_nm": z,
            "photons": t["photons"].to_numpy(float),
            "sigma_x_nm": t["sigma_x_nm"].to_numpy(float),
            "sigma_z_nm": t["sigma_z_nm"].to_numpy(float),
            "flag": t["flag"].astype(str).to_numpy(),
        }
        kwargs = {
            "name": Path(p).stem,
            "features": features,
            "face_color": "z_nm",
            "face_colormap": "turbo",
            "border_width": 0,
            "size": size,
            "ndim": 3,
            "metadata": {"source": str(p), "units": "nm", "axes": ("z", "y", "x")},
        }
        logger.info("%s: %d localizations as a points layer", p, len(t))
        layers.append((data, kwargs, "points"))
    return layers
