"""One-page quality report of a localization table: a self-contained HTML file.

The page holds a summary table; histograms of photons, uncertainties, z and fit quality;
localizations per frame; the drift estimated by redundant cross-correlation (when the movie
is long and dense enough); the rendered image (xy with xz and yz) and its FRC resolution;
and, given the ground truth, the evaluation figures and the error against z; given the movie,
the localizations over the frame that holds the most of them (:mod:`sparseloc.overlay`).
Figures are embedded as PNG data URIs, so the file can be mailed or archived on its own.

Rows: the summary's flag counts cover the whole table; everything else uses the rows of
:func:`sparseloc.postprocess.select_usable` (flag "ok" unless ``all_flags``; rows with a
non-finite or absurd coordinate dropped with a warning). Arrays are sized by the rows and the
distinct frames, never by the largest frame number.

A small inline script counts the figures the browser decoded and writes the count on the
``<body>`` (``data-figures-ok``): a headless browser's DOM dump shows at once whether the page
rendered completely.
"""

from __future__ import annotations

import base64
import html
import io
import logging
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .io.atomic import write_text_atomic

__all__ = ["build_report", "write_report"]

logger = logging.getLogger(__name__)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _png_file(path: Path) -> str:
    return base64.b64encode(path.read_bytes()).decode("ascii")


def _hist_figure(t: pd.DataFrame) -> str:
    from matplotlib.figure import Figure

    panels = [
        ("photons", "photons", "photons"),
        ("sigma_x_nm", "sigma x (nm)", "uncertainty x"),
        ("sigma_y_nm", "sigma y (nm)", "uncertainty y"),
        ("sigma_z_nm", "sigma z (nm)", "uncertainty z"),
        ("z_nm", "z (nm)", "depth"),
        ("gof", "deviance / dof", "fit quality"),
    ]
    fig = Figure(figsize=(12, 6), layout="constrained")
    axes = fig.subplots(2, 3).ravel()
    for ax, (col, label, title) in zip(axes, panels, strict=True):
        v = t[col].to_numpy(float) if col in t else np.zeros(0)
        v = v[np.isfinite(v)]
        if v.size:
            hi = np.percentile(v, 99.5)
            lo = min(v.min(), np.percentile(v, 0.5))
            ax.hist(v, bins=60, range=(lo, hi if hi > lo else lo + 1), color="#3b75af")
            ax.axvline(np.median(v), color="k", lw=1, ls="--")
            ax.set_title(f"{title}: median {np.median(v):.3g}", fontsize=10)
        else:
            ax.text(0.5, 0.5, "no values", ha="center", va="center", transform=ax.transAxes)
            ax.set_title(title, fontsize=10)
        ax.set_xlabel(label)
    return _png(fig)


#: Frame ranges up to this many frames (or 4 per distinct frame) are drawn frame by frame.
_DENSE_FRAMES = 100_000


def _per_frame_figure(t: pd.DataFrame, n_frames: int) -> str:
    from matplotlib.figure import Figure

    frames, per = np.unique(t["frame"].to_numpy(np.int64), return_counts=True)
    fig = Figure(figsize=(12, 3), layout="constrained")
    ax = fig.subplots()
    if n_frames <= max(_DENSE_FRAMES, 4 * len(frames)):
        counts = np.zeros(n_frames, dtype=np.int64)
        counts[frames] = per
        ax.plot(np.arange(len(counts)), counts, lw=0.6, color="#999999", label="per frame")
        w = max(1, len(counts) // 100)
        if w > 1:
            smooth = np.convolve(counts, np.ones(w) / w, mode="same")
            ax.plot(np.arange(len(counts)), smooth, color="k", lw=1.2, label=f"mean over {w}")
            ax.legend(fontsize=8)
    else:
        # Frame numbers far beyond the rows' count: only the frames that hold rows are drawn,
        # so the arrays stay as small as the table.
        ax.plot(frames, per, ".", ms=3, color="#3b75af", label="frames with localizations")
        ax.legend(fontsize=8)
    ax.set_xlabel("frame")
    ax.set_ylabel("localizations")
    return _png(fig)


def _drift_section(
    t: pd.DataFrame, corrected: Mapping[str, Any] | None = None
) -> tuple[str, str | None]:
    """Text and figure of the drift estimate, or the reason there is none; ``corrected``: the
    table's metadata of a drift correction already applied (``sparseloc drift``), which
    makes the estimate the residual drift."""
    from .drift import no_drift_caution, plot_drift, rcc_drift

    done = ""
    same: dict[str, Any] = {}  # the correction's own segments, and z only where it corrected z
    if isinstance(corrected, Mapping):
        method = html.escape(str(corrected.get("method", "")))
        done = f"This table is already drift-corrected (<code>sparseloc drift</code>, {method}). "
        segments = corrected.get("segments")
        if isinstance(segments, int) and segments >= 2:
            same["segments"] = segments
        if corrected.get("z_corrected") is False:
            same["estimate_z"] = False
    try:
        # Unreliable: the section's text says why; logged too, the warnings would be printed on
        # the terminal of a run that asked only for a report (or the demo), beside its output.
        # Too short a table: the drift command's own rule refuses it, in its words.
        d = rcc_drift(t, log_warnings=False, **same)
    except ValueError as exc:
        what = "Its residual drift is not estimated" if done else "Not estimated"
        return f"{done}{what}: {html.escape(str(exc))}", None
    with tempfile.TemporaryDirectory() as tmp:
        figure = _png_file(plot_drift(d, Path(tmp) / "drift.png"))
    ranges = f"{d.range_text(0)} over the movie"
    if done:
        text = (
            f"{done}Redundant cross-correlation of the corrected table, the residual drift: "
            f"range {ranges} (at the estimate's noise where the correction worked)."
        )
    else:
        text = (
            f"Redundant cross-correlation: drift range {ranges} (not applied here; see "
            "<code>sparseloc drift</code>)."
        )
    if not d.reliable:
        text += " <b>Unreliable:</b> " + html.escape("; ".join(d.warnings))
    # shifts that vary like noise: on a corrected table the correction left no drift; on an
    # uncorrected one there may be none to correct
    caution = no_drift_caution(d)
    if caution:
        text += (
            " The residual shifts vary like noise, not like a drift: the correction left none"
            + ("." if d.details.get("z_estimated") else " in x and y (z not estimated).")
            if done
            else " <b>Caution:</b> " + html.escape(caution) + "."
        )
    return text, figure


def _truth_section(t: pd.DataFrame, truth: pd.DataFrame) -> tuple[str, str]:
    from matplotlib.figure import Figure

    from .evaluate import evaluate, match_localizations, result_cautions, scoring_cautions

    ev = evaluate(t, truth)
    m = match_localizations(t, truth, lateral_tol=ev.lateral_tol, axial_tol=ev.axial_tol)
    cautions = scoring_cautions(t, truth) or result_cautions(ev)
    rows = [("caution", c) for c in cautions] + [
        ("truth / localizations", f"{ev.n_truth:,} / {ev.n_locs:,}"),
        ("true / false positives, false negatives", f"{ev.tp:,} / {ev.fp:,}, {ev.fn:,}"),
        ("Jaccard", f"{ev.jaccard:.1f} %"),
        ("recall / precision", f"{ev.recall:.3f} / {ev.precision:.3f}"),
        ("RMSE lateral / axial", f"{ev.rmse_lateral:.1f} / {ev.rmse_axial:.1f} nm"),
        ("bias x / y / z", f"{ev.bias_x:.1f} / {ev.bias_y:.1f} / {ev.bias_z:.1f} nm"),
        (
            "efficiency lateral / axial",
            f"{ev.efficiency_lateral:.1f} / {ev.efficiency_axial:.1f} %",
        ),
        ("tolerances", f"{ev.lateral_tol:g} nm lateral, {ev.axial_tol:g} nm axial"),
    ]
    fig = Figure(figsize=(12, 3.5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    zt = m["z_truth"].to_numpy(float)
    if len(m) and np.isfinite(zt).all():
        edges = np.linspace(zt.min(), zt.max() + 1e-9, 11)
        idx = np.clip(np.digitize(zt, edges) - 1, 0, 9)
        mid = 0.5 * (edges[1:] + edges[:-1])
        rms = {
            axis: [
                np.sqrt(np.mean(m[f"d{axis}"].to_numpy(float)[idx == i] ** 2))
                if np.any(idx == i)
                else np.nan
                for i in range(10)
            ]
            for axis in "xyz"
        }
        for axis in "xyz":
            ax1.plot(mid, rms[axis], "o-", label=axis)
        ax1.legend(fontsize=8)
        counts = np.bincount(idx, minlength=10)
        ax2.bar(mid, counts, width=np.diff(edges), color="#3b75af", label="matched")
        tz = truth["z_nm"].to_numpy(float) if "z_nm" in truth else np.zeros(len(truth))
        all_counts = np.histogram(tz, bins=edges)[0]
        ax2.step(mid, all_counts, where="mid", color="k", label="truth")
        ax2.legend(fontsize=8)
    ax1.set_xlabel("true z (nm)")
    ax1.set_ylabel("RMS error (nm)")
    ax1.set_title("error against depth", fontsize=10)
    ax2.set_xlabel("true z (nm)")
    ax2.set_title("detections against depth", fontsize=10)
    return _rows_html(rows), _png(fig)


def build_report(
    locs: pd.DataFrame,
    *,
    truth: pd.DataFrame | None = None,
    metadata: Mapping[str, Any] | None = None,
    title: str = "sparseloc report",
    render_px: float | None = None,
    all_flags: bool = False,
    movie: str | Path | None = None,
    pixel_size: float | None = None,
) -> str:
    """The report as an HTML string (see the module docstring).

    Parameters
    ----------
    locs : DataFrame
        Localization table (:data:`sparseloc.io.tables.LOCS_COLUMNS`; nm, photons).
    truth : DataFrame, optional
        Ground truth (``frame, x_nm, y_nm[, z_nm]``): adds the evaluation and error against z.
    metadata : mapping, optional
        Shown as a table (e.g. the analysis parameters stored in a Parquet file).
    title : str
        Page title.
    render_px : float, optional
        Pixel size (nm) of the rendered image; default chosen by
        :func:`sparseloc.render.plot_projections`.
    all_flags : bool
        Use flagged rows too (default: only rows flagged "ok").
    movie : str or Path, optional
        The camera movie the table was made from: adds the overlay of one frame.
    pixel_size : float, optional
        Camera pixel size (nm) for the overlay; default from ``metadata`` (``params``) or the
        movie's own.

    Raises
    ------
    ValueError
        If the table is empty or has no usable row, or the movie cannot be read.
    """
    from .io.tables import complete_locs
    from .postprocess import select_usable

    if len(locs) == 0:
        raise ValueError("the localization table is empty: nothing to report")
    full = complete_locs(locs)
    sel = select_usable(full, all_flags=all_flags)
    t = sel.locs
    n_frames = int(t["frame"].max()) + 1
    sections: list[str] = []
    summary = _summary_rows(t, n_frames, full["flag"])
    if sel.note():
        summary.append(("left out", sel.note()))
    sections.append(_table_html("Summary", summary))
    sections.append(_figure_html("Distributions", _hist_figure(t)))
    sections.append(_figure_html("Localizations per frame", _per_frame_figure(t, n_frames)))
    text, fig = _drift_section(t, (metadata or {}).get("drift"))
    sections.append(_figure_html("Drift", fig, text))
    render_b64, frc_text = _render_section(t, render_px)
    sections.append(_figure_html("Rendered image (colour = z)", render_b64, frc_text))
    if movie is not None:
        heading, fig = _overlay_section(full, movie, pixel_size, metadata)
        sections.append(_figure_html(heading, fig))
    if truth is not None:
        table, fig = _truth_section(t, truth)
        sections.append(_figure_html("Against the ground truth", fig, table))
    if metadata:
        items = [(str(k), _short(v)) for k, v in metadata.items()]
        sections.append(_table_html("Metadata", items))
    body = "\n".join(sections)
    n_fig = body.count("<img ")
    return _PAGE.format(
        title=html.escape(title), body=body, n_figures=n_fig, style=_STYLE, script=_SCRIPT
    )


def _summary_rows(t: pd.DataFrame, n_frames: int, flag: pd.Series) -> list[tuple[str, str]]:
    """Counts, field, z range, median photons, uncertainties and fit quality of the rows used,
    and the flags of the whole table."""
    flags = flag.value_counts().to_dict()
    return [
        ("localizations", f"{len(t):,}"),
        ("frames", f"{n_frames:,} ({len(t) / n_frames:.1f} localizations per frame)"),
        ("field (x, y)", f"{np.ptp(t.x_nm) / 1000:.1f} x {np.ptp(t.y_nm) / 1000:.1f} µm"),
        ("z range", f"{t.z_nm.min():.0f} to {t.z_nm.max():.0f} nm"),
        ("median photons", f"{t.photons.median():.0f}"),
        (
            "median uncertainty x / y / z",
            f"{t.sigma_x_nm.median():.1f} / {t.sigma_y_nm.median():.1f} / "
            f"{t.sigma_z_nm.median():.1f} nm",
        ),
        ("median deviance / dof", f"{t.gof.median():.2f}"),
        ("flags", ", ".join(f"{k}: {v:,}" for k, v in flags.items())),
    ]


def _render_section(t: pd.DataFrame, render_px: float | None) -> tuple[str, str]:
    """The rendered image (base64 PNG) and the text of its FRC resolution."""
    from .render import frc_report, plot_projections

    with tempfile.TemporaryDirectory() as tmp:
        png = plot_projections(t, Path(tmp) / "render.png", px_nm=render_px, title="")
        render_b64 = _png_file(png)
    _, message = frc_report(t)
    frc_text = html.escape(message) + " (1/7 threshold, halves of alternating frame blocks)"
    return render_b64, frc_text


def _overlay_section(
    locs: pd.DataFrame,
    movie: str | Path,
    pixel_size: float | None,
    metadata: Mapping[str, Any] | None,
) -> tuple[str, str]:
    """Heading and figure of the overlay on the movie's frame with the most localizations."""
    from .io.movie import Movie
    from .overlay import check_table_movie, overlay_figure

    with Movie.open(movie) as m:
        check_table_movie(metadata, m.shape, "", Path(movie).name)
        px = _overlay_pixel_size(pixel_size, metadata, m.pixel_size)
        frame = locs["frame"].to_numpy(np.int64)
        inside = frame[(frame >= 0) & (frame < m.n_frames)]
        if inside.size == 0:
            raise ValueError(
                f"no localization lies in the {m.n_frames} frames of the movie {str(movie)!r}"
            )
        values, counts = np.unique(inside, return_counts=True)
        best = int(values[np.argmax(counts)])
        image = m[best]
    fig = overlay_figure(image, locs, frame_index=best, pixel_size=px)
    return f"Localizations over frame {best}", _png(fig)


def _overlay_pixel_size(
    given: float | None, metadata: Mapping[str, Any] | None, movie_px: float | None
) -> float:
    """The camera pixel size (nm): given, else the analysis' (metadata), else the movie's."""
    from .io.tables import recorded_pixel_size

    if given is not None:
        return float(given)
    recorded = recorded_pixel_size(metadata)
    if recorded is not None:
        return recorded
    if movie_px is not None:
        return float(movie_px)
    raise ValueError(
        "the overlay needs the camera pixel size: give it (--pixel-size), as neither the "
        "table's metadata nor the movie records it"
    )


def write_report(
    locs: pd.DataFrame,
    path: str | Path,
    *,
    truth: pd.DataFrame | None = None,
    metadata: Mapping[str, Any] | None = None,
    title: str = "sparseloc report",
    render_px: float | None = None,
    all_flags: bool = False,
    movie: str | Path | None = None,
    pixel_size: float | None = None,
) -> Path:
    """Write :func:`build_report` to ``path`` (``.html``) atomically and return the path;
    parameters as :func:`build_report`."""
    p = Path(path)
    if p.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"the report is an HTML file: give a .html path, not {p.name!r}")
    if not p.parent.is_dir():
        raise ValueError(f"the folder {str(p.parent)!r} does not exist")
    page = build_report(
        locs,
        truth=truth,
        metadata=metadata,
        title=title,
        render_px=render_px,
        all_flags=all_flags,
        movie=movie,
        pixel_size=pixel_size,
    )
    return write_text_atomic(p, page)


def _short(v: Any) -> str:
    s = str(v)
    return s if len(s) <= 300 else s[:297] + "..."


def _rows_html(rows: list[tuple[str, str]]) -> str:
    cells = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f"<table>{cells}</table>"


def _table_html(heading: str, rows: list[tuple[str, str]]) -> str:
    return f"<section><h2>{html.escape(heading)}</h2>{_rows_html(rows)}</section>"


def _figure_html(heading: str, b64: str | None, text: str = "") -> str:
    img = f'<img class="figure" alt="{html.escape(heading)}" src="data:image/png;base64,{b64}">'
    parts = [f"<h2>{html.escape(heading)}</h2>"]
    if text:
        parts.append(f"<div>{text}</div>")
    if b64 is not None:
        parts.append(img)
    return "<section>" + "".join(parts) + "</section>"


_STYLE = """
body { font-family: sans-serif; max-width: 1250px; margin: 1em auto; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; }
th { text-align: left; padding: 2px 12px 2px 0; font-weight: normal; color: #555; }
td { padding: 2px 0; } img.figure { max-width: 100%; }
"""

_SCRIPT = """
window.addEventListener("load", function () {
  var imgs = document.querySelectorAll("img.figure"), ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
  }
  document.body.setAttribute("data-figures-ok", ok + "/" + imgs.length);
});
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>{style}</style>
</head>
<body data-figures-expected="{n_figures}">
<h1>{title}</h1>
{body}
<script>{script}</script>
</body>
</html>
"""
