"""What ``calibrate`` reports and writes: the summary lines of a calibration and its file
with the diagnostic figure. Shared by the command line and the napari widget."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .calibrate_zsmooth import smoothing_nm

__all__ = ["calibration_path", "calibration_summary", "write_calibration"]


def calibration_path(path: str | Path) -> Path:
    """``path`` as a calibration file name: ValueError in one sentence unless it ends in .h5
    or .hdf5."""
    out = Path(path)
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the calibration file must end in .h5 or .hdf5, got {out.name!r}")
    return out


def calibration_summary(
    cal: Any, seconds: float | None = None, content_hash: str | None = None
) -> list[str]:
    """The key numbers of a calibration, one line each: beads used, planes (and the smoothing
    along z the beads chose), ROI, hash (and the time taken), the model error, the model's
    origin, the known bead positions' offset, a camera gain the stack contradicts, the
    rejected beads by reason and the pupil fit.

    Parameters
    ----------
    cal : Calibration
        From :func:`sparseloc.calibrate.calibrate_beads` or ``calibrate_file``.
    seconds : float, optional
        Time the calibration took (s), added to the first line.
    content_hash : str, optional
        The hash the written file records (a pupil model's where the file serves the
        pupil); default the spline model's.

    Returns
    -------
    list of str
    """
    nz, nr, nc = cal.average.shape
    took = "" if seconds is None else f"; {seconds:.1f} s"
    error = (
        f"  model error: the beads depart from the model by {100 * cal.params['model_error']:.1f} %"
        " of their signal per pixel (rms beyond noise; the count selection allows for it)"
    )
    if cal.params.get("bead_warning"):
        error = "  model error: not measured (one bead; see the warning below)"
    side = cal.model_cut
    cut = (
        ""
        if side is None
        else f", model {side} x {side} px (the light beyond lies below its noise)"
    )
    window = cal.params.get("z_smooth_planes", 0)
    span = smoothing_nm(window, cal.params["z_step_nm"])
    smoothed = f" smoothed over {span:.0f} nm" if window else ""
    lines = [
        f"{cal.n_used} of {len(cal.beads)} beads used; {nz} planes z "
        f"{cal.z[0]:.0f}..{cal.z[-1]:.0f} nm{smoothed}, ROI {nr} x {nc} px{cut}; "
        f"hash {content_hash or cal.content_hash}{took}",
        error,
    ]
    wander = cal.params["centroid_over_z_nm"]
    lines.append(
        f"  model origin: {cal.params['lateral_origin']}; each plane's light centroid lies "
        f"{wander['x'][0]:+.0f}..{wander['x'][1]:+.0f} nm in x and "
        f"{wander['y'][0]:+.0f}..{wander['y'][1]:+.0f} nm in y from it"
    )
    if cal.params.get("n_beads_known"):
        dx, dy = cal.params["centroid_offset_nm"]
        lines.append(
            f"  origin on {cal.params['n_beads_known']} known bead position(s): the light's "
            f"centroid lies {dx:+.1f}, {dy:+.1f} nm (x, y) from the emitter "
            f"(rms over beads {cal.params['bead_position_rms_nm']:.1f} nm)"
        )
    scan = cal.params.get("scan_z_range_nm")
    spread = cal.params.get("bead_height_spread_nm", 0.0)
    if scan is not None and (cal.z[0] > scan[0] + 1e-6 or cal.z[-1] < scan[-1] - 1e-6):
        lines.append(
            f"  the beads lie up to {spread:.0f} nm above or below "
            "their mean height (a tilted or uneven slide): the model keeps the planes every "
            "bead's data covers to within a fifth of a step, "
            f"z {cal.z[0]:.0f}..{cal.z[-1]:.0f} nm of the scan's {scan[0]:.0f}..{scan[-1]:.0f}"
        )
    trend, level = cal.params.get("background_trend", 0.0), cal.params.get("background", 0.0)
    if trend > 0:
        lines.append(
            f"  the background changes by {trend:.1f} photons/px across the field (median "
            f"{level:.1f}): its smooth trend was subtracted from each plane"
        )
    if cal.params.get("clipped_values"):
        top = cal.params["clipped_adu"]
        lines.append(
            f"  warning: {cal.params['clipped_values']} pixel values sit at exactly {top:g} ADU, "
            "the stack's largest: a camera that clips there flattens the beads' brightest "
            f"pixels in the model; give --saturation {top:g} to leave such beads out, or "
            "image the beads dimmer"
        )
    if cal.params.get("defective_pixels"):
        lines.append(
            f"  {cal.params['defective_pixels']} defective (hot or stuck) pixel(s) replaced by "
            "the median of their neighbours"
        )
    if cal.params.get("bead_warning"):
        lines.append(f"  warning: {cal.params['bead_warning']}")
    if cal.params.get("mirror_warning"):
        lines.append(f"  warning: {cal.params['mirror_warning']}")
    if cal.params.get("cluster_warning"):
        lines.append(f"  warning: {cal.params['cluster_warning']}")
    if cal.params.get("phase_warning"):
        lines.append(f"  warning: {cal.params['phase_warning']}")
    if cal.params.get("camera_warning"):
        lines.append(f"  warning: {cal.params['camera_warning']}")
    rejected = cal.beads[~cal.beads["used"]]
    for reason, n in rejected["reason"].value_counts().items():
        lines.append(f"  rejected {n}: {reason}")
    if cal.pupil is not None:
        terms = ", ".join(
            f"Z({n},{m}) {a:+.3f}"
            for (n, m), a in sorted(cal.pupil.coefficients.items())
            if abs(a) >= 0.01
        )
        terms = terms or "no term above 0.01 waves"
        own = getattr(cal.pupil, "model_error", None)
        error = "" if own is None else f"; the beads depart from it by {100 * own:.1f} %"
        lines.append(f"  pupil fit: residual {cal.pupil.residual_rms:.3f}{error}; {terms}")
    return lines


def write_calibration(
    cal: Any, out: str | Path, figure: str | Path, *, model: str = "spline"
) -> tuple[Path, Path]:
    """Write the calibration file and its diagnostic figure (PNG), or neither: the file is
    removed again when the figure fails.

    Parameters
    ----------
    cal : Calibration
        The calibration.
    out : str or Path
        Calibration file (.h5), written atomically.
    figure : str or Path
        Diagnostic figure (.png).
    model : {"spline", "pupil"}
        The model the file serves by default.

    Returns
    -------
    (Path, Path)
        The calibration file and the figure.
    """
    from .io.calibration import save_calibration
    from .plotting import plot_calibration

    out = save_calibration(cal, out, model=model)
    try:
        plot_calibration(cal, figure)
    except BaseException:
        out.unlink(missing_ok=True)  # no calibration without its figure
        raise
    return out, Path(figure)
