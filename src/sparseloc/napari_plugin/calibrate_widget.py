"""The calibrate widget: a PSF model from a bead z-stack layer, as ``sparseloc calibrate``
builds it (:func:`sparseloc.calibrate.calibrate_file` for a layer read from a file, else
:func:`~sparseloc.calibrate.calibrate_beads` on its array), shown as an image stack with the
beads used (green) and rejected (red) over the stack; Save writes the calibration file and
its diagnostic figure.

The bar shows that the calibration is busy (it has no count of work to show); Cancel stops it
at its next step (at most one bead's registration later, through the library call's
``progress``) and drops its result: nothing is shown or saved.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from magicgui.widgets import (
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    ProgressBar,
    PushButton,
)

from ._form import CameraFields, OptionalNumber, layer_choices
from ._layers import movie_files, movie_of
from ._worker import Task, notify_error, notify_info
from .readers import model_layer

__all__ = ["CalibrateWidget", "calibrate_layer"]


def calibrate_layer(
    layer: Any,
    pixel_size: float,
    z_step: float | None,
    z_file: str | None,
    camera: dict[str, Any],
    *,
    beads: str | None = None,
    **kwargs: Any,
) -> Any:
    """Calibrate from an image layer as ``sparseloc calibrate`` does from its file.

    Parameters
    ----------
    layer : napari Image layer
        The bead z-stack (ADU), one frame per z.
    pixel_size : float
        Pixel size in sample space (nm).
    z_step : float or None
        Stage step between frames (nm).
    z_file : str or None
        CSV of each frame's z (see :func:`sparseloc.calibrate.read_z_file`).
    camera : dict
        The camera options (:data:`sparseloc.options.CAMERA_DEFAULTS` keys).
    beads : str, optional
        CSV of the beads' known positions.
    **kwargs
        ``z0_slice``, ``roi_size``, ``threshold``, ``progress`` of
        :func:`sparseloc.calibrate.calibrate_beads`.

    Returns
    -------
    Calibration
    """
    from ..calibrate import calibrate_beads, calibrate_file, read_bead_positions, read_z_file
    from ..calibrate_scan import scan_conversion
    from ..camera import camera_from_options

    offset, photons_per_adu = scan_conversion(camera)
    known = None if beads is None else read_bead_positions(beads, pixel_size)
    scan_camera = camera_from_options(camera)
    kwargs.update(offset=offset, gain=photons_per_adu, beads=known, camera=scan_camera)
    files = movie_files(layer) if layer is not None else []
    if len(files) == 1:
        return calibrate_file(files[0], pixel_size, z_step, z_file=z_file, **kwargs)
    movie = movie_of(layer, "bead stack")
    if z_file is not None:
        z, valid = read_z_file(z_file)
        kwargs.update(z=z, valid=valid)
    return calibrate_beads(movie.frames(), pixel_size, z_step, name=layer.name, **kwargs)


def _put_stack_in_nm(
    layer: Any, z_step: float | None, z_file: str | None, z0_slice: float | None
) -> None:
    """Place the bead stack's frames at their z (nm) as the calibration placed them, so that
    the z slider moves the stack and the model together: ``z = (frame - z0_slice) * z_step``
    (z0 the middle frame by default), or a straight line through a z file's values."""
    from ..calibrate import read_z_file

    n = layer.data.shape[0] if layer.ndim >= 3 else 1
    if n < 2:
        return
    if z_file is not None:
        z, _valid = read_z_file(z_file)
        if len(z) != n:
            return
        step, z_first = np.polyfit(np.arange(n), np.asarray(z, float), 1)
    elif z_step is not None:
        z0 = (n - 1) / 2.0 if z0_slice is None else float(z0_slice)
        step, z_first = float(z_step), -z0 * float(z_step)
    else:
        return
    layer.scale = (float(step), *layer.scale[1:])
    layer.translate = (float(z_first), *layer.translate[1:])


def _optional_path(edit: FileEdit) -> str | None:
    value = edit.value
    text = "" if value is None else str(value).strip()
    return None if text in ("", ".") else text


class CalibrateWidget(Container):
    """Calibrate a PSF model from the chosen bead-stack layer; see the module docstring.

    Parameters
    ----------
    viewer : napari.viewer.Viewer
        The viewer whose layers the widget reads and adds to.
    """

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer
        self.stack = ComboBox(
            name="stack", label="bead stack layer", choices=layer_choices(viewer, "Image")
        )
        self.pixel_size = FloatSpinBox(
            name="pixel_size", label="pixel size (nm)", value=100.0, min=1.0, max=10000.0
        )
        self.z_step = OptionalNumber("z_step", "z step (nm)")
        self.z_file = FileEdit(name="z_file", label="z file (CSV)", mode="r", filter="*.csv")
        self.z0_slice = OptionalNumber("z0_slice", "slice at z = 0", tooltip="empty: the middle")
        self.cam = CameraFields()
        self.beads = FileEdit(name="beads", label="bead positions (CSV)", mode="r", filter="*.csv")
        self.threshold = FloatSpinBox(
            name="threshold", label="detection threshold", value=0.2, min=0.01, max=1.0
        )
        self.roi_size = OptionalNumber("roi_size", "ROI (px)", whole=True)
        self.run_button = PushButton(name="run", text="Run")
        self.cancel_button = PushButton(name="cancel", text="Cancel", enabled=False)
        self.progress = ProgressBar(name="progress", value=0, min=0, max=1)
        self.summary = Label(name="summary", value="")
        self.output = FileEdit(name="output", label="calibration", mode="w", filter="*.h5")
        self.save_button = PushButton(name="save", text="Save", enabled=False)
        super().__init__(
            widgets=[
                self.stack,
                self.pixel_size,
                self.z_step.widget,
                self.z_file,
                self.z0_slice.widget,
                *self.cam.widgets,
                self.beads,
                self.threshold,
                self.roi_size.widget,
                self.run_button,
                self.cancel_button,
                self.progress,
                self.summary,
                self.output,
                self.save_button,
            ],
            scrollable=True,
        )
        self.summary.native.setWordWrap(True)
        self.task: Task | None = None
        self.calibration: Any = None
        self.run_button.changed.connect(self.run)
        self.cancel_button.changed.connect(self.cancel)
        self.save_button.changed.connect(self.save)
        for ev in (viewer.layers.events.inserted, viewer.layers.events.removed):
            ev.connect(lambda _e=None: self.stack.reset_choices())

    def run(self, _value: Any = None) -> Task | None:
        """Calibrate in a worker thread; show the model, the beads and the key numbers."""
        from ..calibrate_output import calibration_summary
        from ..messages import one_sentence

        layer = self.stack.value
        try:
            if layer is None:
                raise ValueError("choose the bead stack layer (open the bead z-stack TIFF first)")
            args = (
                layer,
                float(self.pixel_size.value),
                self.z_step.value,
                _optional_path(self.z_file),
                self.cam.options(),
            )
            kwargs = {
                "beads": _optional_path(self.beads),
                "z0_slice": self.z0_slice.value,
                "roi_size": self.roi_size.value,
                "threshold": float(self.threshold.value),
            }
        except ValueError as exc:
            notify_error(one_sentence(exc))
            return None

        def call(_progress: Any) -> Any:
            t0 = time.perf_counter()
            cal = calibrate_layer(*args, progress=lambda: _progress(0), **kwargs)
            return cal, time.perf_counter() - t0

        def done(value: Any) -> None:
            cal, seconds = value
            self.calibration = cal
            self.summary.value = "\n".join(calibration_summary(cal, seconds))
            self.save_button.enabled = True
            _put_stack_in_nm(layer, args[2], args[3], kwargs["z0_slice"])
            self._show(cal, layer)

        self.calibration = None
        self.save_button.enabled = False
        self.progress.min = self.progress.max = 0  # busy
        self.summary.value = "calibrating..."
        self.run_button.enabled, self.cancel_button.enabled = False, True
        self.task = Task(call)
        self.task.start(lambda _n: None, done, self._finished)
        return self.task

    def cancel(self, _value: Any = None) -> None:
        """Drop the running calibration's result."""
        if self.task is not None:
            self.task.cancel()
            self.summary.value = "cancelled"

    def save(self, _value: Any = None) -> Path | None:
        """Write the calibration file and its diagnostic figure (PNG beside it)."""
        from ..calibrate_output import calibration_path, write_calibration
        from ..messages import INPUT_ERRORS, one_sentence

        try:
            if self.calibration is None:
                raise ValueError("run the calibration first")
            out = _optional_path(self.output)
            if out is None:
                raise ValueError("choose the calibration file to write (.h5)")
            path = calibration_path(out)
            write_calibration(self.calibration, path, path.with_suffix(".png"))
        except INPUT_ERRORS as exc:
            notify_error(one_sentence(exc))
            return None
        notify_info(f"wrote {path} and {path.with_suffix('.png')}")
        return path

    def _finished(self) -> None:
        self.progress.min, self.progress.max = 0, 1
        self.progress.value = 1 if self.calibration is not None else 0
        self.run_button.enabled, self.cancel_button.enabled = True, False

    def _show(self, cal: Any, layer: Any) -> None:
        """The model as an image stack and the beads as points over the stack layer."""
        name = f"{layer.name} PSF model"
        data, kwargs = model_layer(cal.psf, name, pixel=float(layer.scale[-1]))
        for n in (name, f"{layer.name} beads"):
            if n in self.viewer.layers:
                self.viewer.layers.remove(n)
        self.viewer.add_image(data, **kwargs)
        b = cal.beads
        p = cal.pixel_size
        rc = np.column_stack([b["y_nm"].to_numpy(float) / p - 0.5, b["x_nm"] / p - 0.5])
        self.viewer.add_points(
            rc,
            name=f"{layer.name} beads",
            features=b.reset_index(drop=True),
            symbol="square",
            size=float(cal.average.shape[1]),
            face_color="transparent",
            border_color=["lime" if u else "red" for u in b["used"]],
            border_width=0.05,
            scale=tuple(layer.scale[-2:]),
            translate=tuple(layer.translate[-2:]),
        )
