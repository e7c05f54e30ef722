"""Figures. matplotlib is imported inside each function (never at package import) and uses the
non-interactive Agg backend through an explicit Figure, so nothing touches global state."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .psf.base import PSFModel

__all__ = ["plot_crlb", "plot_psf_montage", "plot_scene", "save_figure"]


def save_figure(fig, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` atomically (temporary name, then rename)."""
    from .io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(
            tmp, dpi=dpi, bbox_inches="tight", format=Path(path).suffix.lstrip(".") or "png"
        )
    return Path(path)


def plot_psf_montage(
    models: Sequence[PSFModel],
    pixel_size: float,
    path: str | Path,
    *,
    n_planes: int = 7,
    window: int | None = None,
) -> Path:
    """Montage of each model's image over its z range (one row per model).

    Parameters
    ----------
    models : sequence of PSFModel
        Models to show.
    pixel_size : float
        Pixel size (nm) to render at.
    path : path
        Output PNG.
    n_planes : int
        Number of z planes per model, evenly spread over its z range.
    window : int, optional
        Window size in pixels; default from the largest support radius.
    """
    from matplotlib.figure import Figure

    if window is None:
        radius = max(m.support_radius(pixel_size) for m in models)
        window = min(int(np.ceil(1.2 * radius / pixel_size)) * 2 + 1, 41)
    fig = Figure(figsize=(1.6 * n_planes, 1.8 * len(models)))
    axes = fig.subplots(len(models), n_planes, squeeze=False)
    half = window * pixel_size / 2
    for row, model in zip(axes, models, strict=True):
        zs = np.linspace(*model.z_range, n_planes)
        imgs = model.images(
            np.full(n_planes, half), np.full(n_planes, half), zs, (window, window), pixel_size
        )
        for ax, img, z in zip(row, imgs, zs, strict=True):
            ax.imshow(img, cmap="magma", extent=(0, 2 * half / 1000, 2 * half / 1000, 0))
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"z = {z:.0f} nm", fontsize=8)
        row[0].set_ylabel(getattr(model, "name", type(model).__name__), fontsize=9)
    fig.suptitle(f"PSF models over z ({pixel_size:.0f} nm pixels, {window}x{window} window)")
    return save_figure(fig, path)


def plot_scene(
    frame: NDArray,
    truth: pd.DataFrame,
    pixel_size: float,
    path: str | Path,
    *,
    title: str = "",
    locs: pd.DataFrame | None = None,
) -> Path:
    """One camera frame with the true emitters (and optional localizations) coloured by z."""
    from matplotlib.figure import Figure

    rows, cols = frame.shape
    fig = Figure(figsize=(7.5, 6.5 * rows / cols + 0.5))
    ax = fig.subplots()
    ext = (0, cols * pixel_size / 1000, rows * pixel_size / 1000, 0)
    ax.imshow(frame, cmap="gray", extent=ext)
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    norm = Normalize(float(truth["z_nm"].min()), float(truth["z_nm"].max()) + 1e-9)
    cmap = colormaps["turbo"]
    ax.scatter(
        truth["x_nm"] / 1000,
        truth["y_nm"] / 1000,
        s=36,
        marker="o",
        facecolors="none",
        edgecolors=cmap(norm(truth["z_nm"].to_numpy())),
        linewidths=1.2,
        label="truth",
    )
    sc = ScalarMappable(norm=norm, cmap=cmap)
    cb = fig.colorbar(sc, ax=ax, shrink=0.8)
    cb.set_label("z (nm)")
    ax.set_xlabel("x (um)")
    ax.set_ylabel("y (um)")
    ax.set_title(title or f"{len(truth)} emitters")
    ax.legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def plot_crlb(z: NDArray, bound: NDArray, path: str | Path, *, title: str = "") -> Path:
    """CRLB standard deviations (x, y, z; nm) against z (nm)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.5, 3.8))
    ax = fig.subplots()
    for i, label in enumerate(("x", "y", "z")):
        ax.plot(z, bound[:, i], marker="o", ms=3, label=label)
    ax.set_xlabel("z (nm)")
    ax.set_ylabel("CRLB (nm)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)
