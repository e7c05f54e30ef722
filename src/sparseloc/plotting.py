"""Figures. matplotlib is imported inside each function (never at package import) and uses the
non-interactive Agg backend through an explicit Figure, so nothing touches global state."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from .psf.base import PSFModel

if TYPE_CHECKING:
    from .solvers.emitters import Emitters, WindowSolution

__all__ = [
    "plot_calibration",
    "plot_crlb",
    "plot_psf_montage",
    "plot_scene",
    "plot_solve",
    "save_figure",
]


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
    if locs is not None and len(locs):
        ax.scatter(
            locs["x_nm"] / 1000,
            locs["y_nm"] / 1000,
            s=40,
            marker="+",
            c=cmap(norm(locs["z_nm"].to_numpy())),
            linewidths=1.2,
            label="localizations",
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


_METHOD_LABELS = {"mp": "MP", "omp": "OMP", "co": "CO", "hybrid": "MP+CO"}


def _scale_bar(ax, extent_um: tuple[float, float, float, float], color: str) -> None:
    """A horizontal scale bar bottom left: the longest of 1, 2 or 5 times a power of ten um
    within a fifth of the image's width (at least 0.1 um)."""
    x0, x1, y_bottom, y_top = extent_um
    width, height = x1 - x0, y_bottom - y_top
    nice = [m * 10.0**k for k in range(-1, 4) for m in (1.0, 2.0, 5.0)]
    length = max([v for v in nice if v <= width / 5] or [0.1])
    xs = x0 + 0.06 * width
    ys = y_bottom - 0.07 * height
    from matplotlib import patheffects

    edge = "black" if color == "white" else "white"
    ax.plot(
        [xs, xs + length],
        [ys, ys],
        color=color,
        lw=3,
        solid_capstyle="butt",
        path_effects=[patheffects.withStroke(linewidth=5, foreground=edge)],
    )
    ax.text(
        xs + length / 2,
        ys - 0.025 * height,
        f"{length:g} µm",
        color=color,
        ha="center",
        va="bottom",
        fontsize=9,
        path_effects=[patheffects.withStroke(linewidth=2, foreground=edge)],
    )


def _photon_summary(label: str, photons: NDArray | None, count: int) -> str:
    if photons is None:
        return f"{label}: {count}"
    ph = np.sort(np.asarray(photons, dtype=float))[::-1]
    shown = ", ".join(f"{p:.0f}" for p in ph[:6]) + (", ..." if ph.size > 6 else "")
    total = f"  (sum {ph.sum():.0f})" if ph.size > 1 else ""
    return f"{label}: {count}" + (f"\n  photons {shown}{total}" if ph.size else "")


def plot_solve(
    window: NDArray,
    solution: WindowSolution,
    path: str | Path,
    *,
    pixel_size: float,
    origin: tuple[float, float] = (0.0, 0.0),
    truth: NDArray | None = None,
    mp_emitters: Emitters | None = None,
    title: str = "",
) -> Path:
    """One window's solve, laid out like the paper's Figs 2-3.

    Top row: the window, the reconstruction (``solution.model_image``) and the residual (window
    minus reconstruction, diverging colours centred at 0), in µm with colour bars and a 1 µm
    scale bar. Bottom row: positions (nm) in x-y and x-z with the true positions, the matching
    pursuit positions, the final positions and the refined dictionary's boxes (hybrid only),
    the window's extent as a frame, and a panel with the legend and each set's count and
    photons.

    Parameters
    ----------
    window : ndarray, shape (rows, cols)
        The window in photons.
    solution : WindowSolution
        Any window solver's result (MP, CO or hybrid; boxes are drawn when
        ``details`` holds ``box_centres`` and ``box_half_width``).
    path : path
        Output PNG.
    pixel_size : float
        Pixel size (nm).
    origin : (float, float)
        Position (nm) of the window's outer corner of pixel (0, 0), x then y.
    truth : ndarray, shape (K, 3) or (K, 4), optional
        True x, y, z (nm) and optionally photons.
    mp_emitters : Emitters, optional
        Matching pursuit's emitters; default ``solution.details["mp"].emitters`` if present.
    title : str
        Figure title; default the method and the count.
    """
    from matplotlib.figure import Figure

    img = np.asarray(window, dtype=np.float64)
    model = np.asarray(solution.model_image, dtype=np.float64).reshape(img.shape)
    rows, cols = img.shape
    px = float(pixel_size)
    ox, oy = float(origin[0]), float(origin[1])
    bounds = (ox, ox + cols * px, oy, oy + rows * px)

    details = solution.details or {}
    if mp_emitters is None and details.get("mp") is not None:
        mp_emitters = details["mp"].emitters
    final = solution.emitters
    method = _METHOD_LABELS.get(solution.method, solution.method or "estimate")
    tru = None
    if truth is not None:
        tru = np.asarray(truth, dtype=np.float64)
        tru = tru.reshape(-1, tru.shape[-1] if tru.ndim > 1 else 3)
    centres = np.asarray(details.get("box_centres", np.zeros((0, 3))), dtype=float)
    centres = centres.reshape(-1, 3)
    half = details.get("box_half_width")
    if half is None:
        centres = centres[:0]

    fig = Figure(figsize=(14.0, 9.0), layout="constrained")
    axes = fig.subplots(2, 3, gridspec_kw={"height_ratios": [1.0, 1.0]})
    resid = _solve_images(fig, axes[0], img, model, method, bounds)
    ax_xy, ax_xz, ax_info = axes[1]
    sets = _position_sets(tru, mp_emitters, solution.method, method, final)
    _position_panels(ax_xy, ax_xz, sets, bounds, centres, half)
    chi2 = float(np.sum(resid**2 / np.maximum(model, 1e-9)))
    lines = _summary_lines(tru, mp_emitters, method, final, solution.background)
    lines.append(f"Pearson χ²/pixel {chi2 / img.size:.2f}")
    _legend_and_summary(ax_info, ax_xy, len(centres) > 0, lines)
    count = f"{len(final)} emitter" + ("" if len(final) == 1 else "s")
    fig.suptitle(title or f"{method}: {count} in a {rows}x{cols} window ({px:g} nm pixels)")
    return save_figure(fig, path)


_TRUTH_STYLE = {
    "marker": "o",
    "s": 70,
    "facecolors": "none",
    "edgecolors": "black",
    "linewidths": 1.4,
}
_MP_STYLE = {
    "marker": "s",
    "s": 55,
    "facecolors": "none",
    "edgecolors": "tab:orange",
    "linewidths": 1.6,
}
_FINAL_STYLE = {"marker": "x", "s": 60, "color": "tab:blue", "linewidths": 2.0}
_BOX_STYLE = {
    "fill": False,
    "edgecolor": "tab:blue",
    "linewidth": 1.0,
    "alpha": 0.7,
    "linestyle": "-",
}
_FRAME_STYLE = {"color": "0.45", "linestyle": "--", "linewidth": 1.0}


def _solve_images(fig, axes, img: NDArray, model: NDArray, method: str, bounds) -> NDArray:
    """The window, the reconstruction and their residual (returned) on the axes row ``axes``;
    ``bounds`` are the window's edges ``x_lo, x_hi, y_lo, y_hi`` (nm)."""
    x_lo, x_hi, y_lo, y_hi = bounds
    ext_um = (x_lo / 1000, x_hi / 1000, y_hi / 1000, y_lo / 1000)
    vmin, vmax = float(min(img.min(), model.min())), float(max(img.max(), model.max()))
    resid = img - model
    rmax = float(np.abs(resid).max()) or 1.0
    panels = (
        (img, "window (photons)", "magma", vmin, vmax, "white"),
        (model, f"reconstruction ({method})", "magma", vmin, vmax, "white"),
        (resid, "residual (window - reconstruction)", "RdBu_r", -rmax, rmax, "black"),
    )
    for ax, (data, name, cmap, lo, hi, bar) in zip(axes, panels, strict=True):
        im = ax.imshow(data, cmap=cmap, vmin=lo, vmax=hi, extent=ext_um, interpolation="nearest")
        cb = fig.colorbar(im, ax=ax, shrink=0.85)
        cb.set_label("photons / pixel", fontsize=8)
        cb.ax.tick_params(labelsize=7)
        _scale_bar(ax, ext_um, bar)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
        ax.tick_params(labelsize=8)
    return resid


def _position_sets(
    tru: NDArray | None, mp_emitters, solver: str, method: str, final
) -> list[tuple[str, NDArray, dict]]:
    """(label, xyz (n, 3) nm, scatter style) of the truth, the MP and the final positions."""
    sets = []
    if tru is not None:
        sets.append(("truth", tru[:, :3], _TRUTH_STYLE))
    if mp_emitters is not None:
        sets.append(("MP", mp_emitters.as_array()[:, :3], _MP_STYLE))
    mp_only = mp_emitters is None and solver in ("mp", "omp")
    sets.append((method, final.as_array()[:, :3], _MP_STYLE if mp_only else _FINAL_STYLE))
    return sets


def _position_panels(ax_xy, ax_xz, sets: list, bounds, centres: NDArray, half) -> None:
    """Positions in x-y and x-z with the refined dictionary's boxes and the window's extent,
    framed to show them all (x-z kept from going flat)."""
    from matplotlib.patches import Rectangle

    x_lo, x_hi, y_lo, y_hi = bounds
    all_pts = np.vstack([p for _, p, _ in sets] + [np.zeros((0, 3))])
    xs = np.concatenate([[x_lo, x_hi], all_pts[:, 0]])
    ys = np.concatenate([[y_lo, y_hi], all_pts[:, 1]])
    zs = all_pts[:, 2]
    if len(centres):
        hx, hy, hz = (float(h) for h in half)
        xs = np.concatenate([xs, centres[:, 0] - hx, centres[:, 0] + hx])
        ys = np.concatenate([ys, centres[:, 1] - hy, centres[:, 1] + hy])
        zs = np.concatenate([zs, centres[:, 2] - hz, centres[:, 2] + hz])
        for cx, cy, cz in centres:
            ax_xy.add_patch(Rectangle((cx - hx, cy - hy), 2 * hx, 2 * hy, **_BOX_STYLE))
            ax_xz.add_patch(Rectangle((cx - hx, cz - hz), 2 * hx, 2 * hz, **_BOX_STYLE))

    ax_xy.add_patch(Rectangle((x_lo, y_lo), x_hi - x_lo, y_hi - y_lo, fill=False, **_FRAME_STYLE))
    ax_xz.axvline(x_lo, **_FRAME_STYLE)
    ax_xz.axvline(x_hi, **_FRAME_STYLE)

    for label, p, style in sets:
        ax_xy.scatter(p[:, 0], p[:, 1], label=label, zorder=3, **style)
        ax_xz.scatter(p[:, 0], p[:, 2], label=label, zorder=3, **style)

    pad_xy = 0.05 * max(xs.max() - xs.min(), ys.max() - ys.min())
    xlim = (xs.min() - pad_xy, xs.max() + pad_xy)
    ax_xy.set_xlim(xlim)
    ax_xy.set_ylim(ys.max() + pad_xy, ys.min() - pad_xy)  # y grows downwards, as in the images
    z_lo, z_hi = (float(zs.min()), float(zs.max())) if zs.size else (0.0, 0.0)
    pad_z = max(0.1 * (z_hi - z_lo), 50.0)
    z_lo, z_hi = z_lo - pad_z, z_hi + pad_z
    grow = max(0.5 * (xlim[1] - xlim[0]) - (z_hi - z_lo), 0.0) / 2  # keep x-z from going flat
    zlim = (z_lo - grow, z_hi + grow)
    ax_xz.set_xlim(xlim)
    ax_xz.set_ylim(zlim)
    for ax, name, ylab in ((ax_xy, "positions x-y", "y (nm)"), (ax_xz, "positions x-z", "z (nm)")):
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (nm)")
        ax.set_ylabel(ylab)
        ax.set_title(name, fontsize=10)
        ax.tick_params(labelsize=8)
        ax.grid(alpha=0.25)


def _summary_lines(
    tru: NDArray | None, mp_emitters, method: str, final, background: float
) -> list[str]:
    """Count and photons of each set of positions, and the background."""
    lines = []
    if tru is not None:
        lines.append(_photon_summary("truth", tru[:, 3] if tru.shape[1] > 3 else None, len(tru)))
    if mp_emitters is not None:
        lines.append(_photon_summary("MP", mp_emitters.photons, len(mp_emitters)))
    lines.append(_photon_summary(method, final.photons, len(final)))
    lines.append(f"background {background:.2f} photons/pixel")
    return lines


def _legend_and_summary(ax_info, ax_xy, boxes: bool, lines: list[str]) -> None:
    """The legend of the position panels and the summary ``lines`` on the axes ``ax_info``."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ax_info.axis("off")
    handles, labels = ax_xy.get_legend_handles_labels()
    if boxes:
        handles.append(Patch(**_BOX_STYLE))
        labels.append("refined dictionary boxes")
    handles.append(Line2D([], [], **_FRAME_STYLE))
    labels.append("window extent")
    ax_info.legend(
        handles,
        labels,
        loc="upper left",
        fontsize=9,
        frameon=False,
        title="positions",
        title_fontsize=10,
    )
    ax_info.text(
        0.0,
        0.55,
        "\n".join(lines),
        transform=ax_info.transAxes,
        va="top",
        ha="left",
        fontsize=9,
        family="monospace",
        bbox={"boxstyle": "round", "facecolor": "0.96", "edgecolor": "0.7"},
    )


def plot_calibration(cal, path: str | Path, *, n_planes: int = 7) -> Path:
    """Diagnostic figure of a bead calibration (PNG).

    Top: the z-averaged bead field with the beads used (green) and rejected (red, with the
    reason). Then, at ``n_planes`` planes over z: the registered average of the beads, the
    model (the fitted pupil when there is one, else the spline half a step off the nodes),
    and their difference on the same colour scale. Bottom: each bead's normalised
    cross-correlation with the average over z.

    Parameters
    ----------
    cal : Calibration
        From :func:`sparseloc.calibrate.calibrate_beads`.
    path : path
        Output PNG.
    n_planes : int
        Planes shown.
    """
    from matplotlib.figure import Figure

    psf = cal.psf
    z = cal.z
    idx = np.linspace(0, len(z) - 1, n_planes).round().astype(int)
    avg = cal.average[idx]
    nr = avg.shape[1]
    p = cal.pixel_size
    model_name, mod, zs_mod = _calibration_model(cal, idx)
    # With a fitted pupil the third row is the fit's residual; without one it shows how much
    # the PSF changes over half a z step (what the spline interpolates across).
    res_label = "residual" if cal.pupil is not None else "change over\nhalf a step"
    fig = Figure(figsize=(2.0 * n_planes, 12.5))
    grid = fig.add_gridspec(5, n_planes, height_ratios=[2.6, 1, 1, 1, 1.4])
    ax = fig.add_subplot(grid[0, :])
    _bead_field(ax, cal, nr)
    ax.set_title(
        f"{cal.n_used} of {len(cal.beads)} beads used; ROI {nr} px of {p:g} nm"
        f"{'' if cal.model_cut is None else f', model {cal.model_cut} px'}; "
        f"z {z[0]:.0f}..{z[-1]:.0f} nm in {psf.z_step:g} nm steps"
    )
    ax.set_axis_off()
    vmax = float(max(avg.max(), mod.max()))
    res_lim = float(np.abs(avg - mod).max()) or 1.0
    for j in range(idx.size):
        for i, (img, label, kw) in enumerate(
            (
                (avg[j], f"average z={z[idx[j]]:.0f}", {"vmin": 0, "vmax": vmax, "cmap": "magma"}),
                (
                    mod[j],
                    f"{model_name}\nz={zs_mod[j]:.0f}",
                    {"vmin": 0, "vmax": vmax, "cmap": "magma"},
                ),
                (
                    avg[j] - mod[j],
                    res_label,
                    {"vmin": -res_lim, "vmax": res_lim, "cmap": "RdBu_r"},
                ),
            )
        ):
            a = fig.add_subplot(grid[1 + i, j])
            a.imshow(img, origin="upper", **kw)
            a.set_title(label, fontsize=8)
            a.set_axis_off()
    a = fig.add_subplot(grid[4, :])
    if cal.bead_ncc is not None and len(cal.bead_ncc):
        for row in cal.bead_ncc:
            a.plot(z, row, lw=0.8, alpha=0.7)
        a.set_ylim(max(0.0, float(np.nanmin(cal.bead_ncc)) - 0.02), 1.0)
    a.set_xlabel("z (nm)")
    a.set_ylabel("bead vs average NCC")
    title = f"residual scale: +-{res_lim:.2g} of a unit-photon plane"
    err_z = cal.params.get("model_error_z")
    if err_z is not None and len(err_z) == len(z):
        # the model error the solvers allow for, per plane (calibrate_error)
        b = a.twinx()
        b.plot(z, 100 * np.asarray(err_z, float), "k--", lw=1.2)
        b.set_ylabel("model error (% of signal)")
        b.set_ylim(0, max(1.0, 110 * float(np.nanmax(err_z))))
        title += f"; model error {100 * cal.params['model_error']:.1f} % (dashed)"
    a.set_title(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def _calibration_model(cal, idx: NDArray) -> tuple[str, NDArray, NDArray]:
    """The model shown against the average at planes ``idx``: its name, its images and their
    z (nm). The fitted pupil at the planes when there is one, else the spline half a step off
    them (above, or below the last plane)."""
    psf = cal.psf
    z = cal.z
    nr, nc = cal.average.shape[1:]
    p = cal.pixel_size
    cr, cc = cal.emitter_pixel
    x0, y0 = (cc + 0.5) * p, (cr + 0.5) * p
    if cal.pupil is not None:
        mod = cal.pupil.frame_model.images(
            np.full(idx.size, x0), np.full(idx.size, y0), z[idx], (nr, nc), p
        )
        return "pupil fit", mod / mod.sum(axis=(1, 2), keepdims=True), z[idx]
    # half a step above each plane, below the last one (above it lies outside the model)
    up = z[idx] + psf.z_step / 2
    zs_mod = np.where(up <= psf.z_range[1], up, z[idx] - psf.z_step / 2)
    mod = psf.images(np.full(idx.size, x0), np.full(idx.size, y0), zs_mod, (nr, nc), p)
    if cal.model_cut is not None:
        # a model cut to its light holds one photon there: the average's light in its box
        h = cal.model_cut // 2
        box = (
            slice(None),
            slice(round(cr) - h, round(cr) + h + 1),
            slice(round(cc) - h, round(cc) + h + 1),
        )
        mod = (
            mod
            * (cal.average[idx][box].sum(axis=(1, 2)) / mod[box].sum(axis=(1, 2)))[:, None, None]
        )
    return "spline (half step)", mod, zs_mod


def _bead_field(ax, cal, nr: int) -> None:
    """The z-averaged bead field with the ROIs of the beads used (green) and rejected (red,
    with the reason)."""
    from matplotlib.patches import Rectangle

    p = cal.pixel_size
    proj = cal.projection
    ax.imshow(proj, cmap="gray", origin="upper", vmin=0, vmax=np.percentile(proj, 99.9))
    for _, b in cal.beads.iterrows():
        col, row = b["x_nm"] / p - 0.5, b["y_nm"] / p - 0.5
        colour = "lime" if b["used"] else "red"
        half = nr / 2
        ax.add_patch(
            Rectangle((col - half, row - half), nr, nr, fill=False, edgecolor=colour, lw=0.8)
        )
        if not b["used"]:
            ax.text(col, row - half - 1, str(b["reason"]), color="red", fontsize=7, ha="center")
