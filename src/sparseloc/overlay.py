"""Localizations drawn over one camera frame: the check that each PSF image got one marker.

The frame is shown in grey (contrast from its 0.5th to 99.8th percentile), x to the right and
y down in µm, the outer corner of pixel (0, 0) at the origin (the tables' native coordinates).
Localizations of that frame flagged ``"ok"`` are hollow circles coloured by z with the colour
map of :func:`sparseloc.render.plot_projections` (:data:`sparseloc.render.DEPTH_CMAP`), with a
colour bar in nm; flagged ones (any other flag) are grey crosses. A white scale bar sits at the
bottom left. Rows with a non-finite or absurd coordinate are dropped with a warning
(:func:`sparseloc.postprocess.select_usable`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

__all__ = ["check_table_movie", "frame_locs", "overlay_figure", "overlay_rows", "plot_overlay"]

log = logging.getLogger(__name__)

#: Colour of the markers of flagged localizations.
FLAGGED_COLOR = "0.6"
#: Resolution (dpi) of the PNG that :func:`plot_overlay` writes by default.
OVERLAY_DPI = 120


def check_table_movie(
    metadata: object, movie_shape: tuple[int, int], table_name: str, movie_name: str
) -> str:
    """ValueError where a table's recorded frame shape is not the movie's; else a note (or
    "") where the table records a movie of another file name.

    Parameters
    ----------
    metadata : dict or None
        The table's metadata (``shape``: frame rows and columns; ``movie``: the file name(s)).
    movie_shape : (int, int)
        The movie's frame shape (rows, cols).
    table_name, movie_name : str
        The files' names, for the messages ("" for a table without one).
    """
    meta = metadata if isinstance(metadata, dict) else {}
    table = f"the table {table_name!r}" if table_name else "the table"
    shape = meta.get("shape")
    if isinstance(shape, list | tuple) and tuple(shape) != tuple(movie_shape):
        raise ValueError(
            f"{table} was made from frames of {tuple(shape)} pixels, but "
            f"those of the movie {movie_name!r} are {tuple(movie_shape)}: is it the right movie?"
        )
    recorded = meta.get("movie")
    names = [Path(str(p)).name for p in (recorded if isinstance(recorded, list) else [recorded])]
    names = [n for n in names if n and n != "None"]
    if names and Path(movie_name).name not in names:
        return (
            f"{table} records the movie {', '.join(names)}, not "
            f"{Path(movie_name).name!r}: is it the right movie?"
        )
    return ""


def frame_locs(locs: pd.DataFrame, frame_index: int) -> pd.DataFrame:
    """The rows of ``locs`` in frame ``frame_index`` (0-based) with usable coordinates, every
    flag kept.

    Parameters
    ----------
    locs : DataFrame
        Localization table with ``frame``, ``x_nm``, ``y_nm`` (nm).
    frame_index : int
        Frame (0-based).

    Returns
    -------
    DataFrame
        The frame's rows, possibly none.
    """
    from .postprocess import select_usable

    if "frame" not in locs.columns:
        raise ValueError("the localization table has no column 'frame'")
    rows = locs.loc[pd.to_numeric(locs["frame"], errors="coerce") == int(frame_index)]
    if len(rows) == 0:
        return rows.reset_index(drop=True)
    return select_usable(rows, all_flags=True).locs


def overlay_figure(
    image: ArrayLike,
    locs: pd.DataFrame,
    *,
    frame_index: int,
    pixel_size: float,
    z_range: tuple[float, float] | None = None,
    title: str | None = None,
    region: tuple[int, int, int, int] | None = None,
):
    """The overlay of the localizations of one frame on that frame (module docstring).

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        The camera frame (ADU or photons; only its contrast matters).
    locs : DataFrame
        Localization table (nm); the rows of ``frame_index`` are drawn.
    frame_index : int
        Frame number (0-based) of ``image``.
    pixel_size : float
        Camera pixel size (nm).
    z_range : (float, float), optional
        Depths (nm) at the ends of the colour map; default the 0.5..99.5th percentile of the
        table's z (all frames, so that colours agree between frames), as in ``render``.
    title : str, optional
        Figure title; default names the frame and counts the markers.
    region : (x0, x1, y0, y1), optional
        Pixel columns ``x0:x1`` and rows ``y0:y1`` of the frame to draw (a zoom); the
        figure is sized so that a frame pixel spans at least two of a PNG's at 120 dpi.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from .plotting import _scale_bar
    from .render import DEPTH_CMAP, _projection_z_range

    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) == 0:
        raise ValueError(f"the frame must be a 2D image, got shape {img.shape}")
    px = float(pixel_size)
    if not (np.isfinite(px) and px > 0):
        raise ValueError(f"the pixel size must be a positive number of nm, got {pixel_size!r}")
    rows = overlay_rows(locs, frame_index, px, img.shape, region)
    c0, r0 = 0, 0
    if region is not None:
        c0, c1, r0, r1 = _checked_region(region, img.shape)
        img = img[r0:r1, c0:c1]
    ok = (rows["flag"].astype(str) == "ok").to_numpy() if "flag" in rows else np.ones(len(rows))
    ok = ok.astype(bool)
    z_all = locs["z_nm"].to_numpy(float) if "z_nm" in locs else np.zeros(0)
    has_z = bool(np.isfinite(z_all).any()) and float(np.nanmax(z_all) - np.nanmin(z_all)) > 0
    zr = _projection_z_range(locs, z_range, has_z) if has_z or z_range is not None else None

    h, w = img.shape
    # µm: left, right, bottom, top
    ext = (c0 * px / 1000.0, (c0 + w) * px / 1000.0, (r0 + h) * px / 1000.0, r0 * px / 1000.0)
    width = max(7.2, 2.0 * w / OVERLAY_DPI + 1.6)  # two PNG pixels per frame pixel, and a bar
    fig = Figure(figsize=(width, (width - 1.2) * h / max(w, 1) + 0.6), layout="constrained")
    ax = fig.add_subplot()
    finite = img[np.isfinite(img)]
    lo, hi = np.percentile(finite, [0.5, 99.8]) if finite.size else (0.0, 1.0)
    ax.imshow(img, cmap="gray", vmin=lo, vmax=hi if hi > lo else lo + 1, extent=ext)
    x = rows["x_nm"].to_numpy(float) / 1000.0
    y = rows["y_nm"].to_numpy(float) / 1000.0
    cmap = colormaps[DEPTH_CMAP]
    norm = Normalize(*(zr if zr is not None else (0.0, 1.0)))
    size = max(20.0, min(120.0, 3000.0 / max(w, h)))
    if ok.any():
        z = rows["z_nm"].to_numpy(float)[ok] if "z_nm" in rows else np.zeros(int(ok.sum()))
        colors = cmap(norm(np.nan_to_num(z, nan=norm.vmin))) if zr is not None else "cyan"
        ax.scatter(
            x[ok],
            y[ok],
            s=size,
            facecolors="none",
            edgecolors=colors,
            linewidths=1.4,
            label=f"ok ({int(ok.sum())})",
        )
    if (~ok).any():
        ax.scatter(
            x[~ok],
            y[~ok],
            s=size,
            marker="x",
            color=FLAGGED_COLOR,
            linewidths=1.2,
            label=f"flagged ({int((~ok).sum())})",
        )
    if len(rows):
        # a dark box: the light grey cross of a flagged fit was invisible on a white one
        ax.legend(
            loc="upper right", fontsize=8, facecolor="0.15", labelcolor="white", framealpha=0.8
        )
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel("x (µm)")
    ax.set_ylabel("y (µm)")
    _scale_bar(ax, ext, "white")
    if zr is not None:
        cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.85)
        cb.set_label("z (nm)")
    if title is None:
        title = f"frame {int(frame_index)}: {len(rows)} localizations"
    ax.set_title(title, fontsize=10)
    return fig


def overlay_rows(
    locs: pd.DataFrame,
    frame_index: int,
    pixel_size: float,
    shape: tuple[int, int],
    region: tuple[int, int, int, int] | None = None,
) -> pd.DataFrame:
    """The rows an overlay of frame ``frame_index`` (of ``shape`` pixels) draws:
    :func:`frame_locs`, inside ``region`` (x0, x1, y0, y1; pixels, clipped to the frame)
    where one is given."""
    rows = frame_locs(locs, frame_index)
    if region is not None:
        c0, c1, r0, r1 = _checked_region(region, shape)
        xs = rows["x_nm"].to_numpy(float) / pixel_size
        ys = rows["y_nm"].to_numpy(float) / pixel_size
        rows = rows[(xs >= c0) & (xs < c1) & (ys >= r0) & (ys < r1)]
    return rows


def _checked_region(region, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``region`` (x0, x1, y0, y1; pixels) as ints within the frame; ValueError if empty."""
    c0, c1, r0, r1 = (int(v) for v in region)
    rows, cols = shape
    c0, c1, r0, r1 = max(c0, 0), min(c1, cols), max(r0, 0), min(r1, rows)
    if not (c0 < c1 and r0 < r1):
        raise ValueError(
            f"the region x {region[0]}:{region[1]}, y {region[2]}:{region[3]} px holds no pixel "
            f"of the {cols} x {rows} px frame"
        )
    return c0, c1, r0, r1


def plot_overlay(
    image: ArrayLike,
    locs: pd.DataFrame,
    *,
    frame_index: int,
    pixel_size: float,
    path: str | Path,
    z_range: tuple[float, float] | None = None,
    title: str | None = None,
    dpi: int = OVERLAY_DPI,
    region: tuple[int, int, int, int] | None = None,
) -> Path:
    """Write :func:`overlay_figure` to ``path`` (PNG, PDF or SVG by its suffix) atomically.

    Parameters
    ----------
    image, locs, frame_index, pixel_size, z_range, title, region
        As :func:`overlay_figure`.
    path : str or Path
        Output file; written under a temporary name, then renamed.
    dpi : int
        Resolution of a PNG.

    Returns
    -------
    Path
    """
    from .plotting import save_figure

    fig = overlay_figure(
        image,
        locs,
        frame_index=frame_index,
        pixel_size=pixel_size,
        z_range=z_range,
        title=title,
        region=region,
    )
    return save_figure(fig, path, dpi=dpi)
