"""The localize widget: preview the current frame as points, or localize the whole movie (or
a frame range) into a table file, as ``sparseloc localize`` does.

The options are the command line's (:data:`sparseloc.options.LOCALIZE_DEFAULTS`; an empty
field is the command line's default). The run goes through the same calls as the command:
:func:`sparseloc.config.build_job`, :func:`sparseloc.pipeline.localize` on the movie in
photons and :func:`sparseloc.io.localized.write_localized`, so the table is the same.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    LineEdit,
    ProgressBar,
    PushButton,
)

from ..messages import INPUT_ERRORS
from ..options import LOCALIZE_DEFAULTS
from ._form import CameraFields, OptionalNumber, layer_choices
from ._layers import current_frame, movie_of, points_for_table
from ._worker import Task, notify_error, notify_info

__all__ = ["LocalizeWidget", "check_job_frame", "localize_job"]

#: Built-in PSF models offered (``sparseloc.psf.PSF_NAMES``); "file" uses the PSF file field.
PSF_CHOICES = ["dh", "astig", "clear", "dh-analytic", "astig-gauss", "file"]


def localize_job(job: Any, movie: Any, progress: Any) -> Any:
    """Run ``job`` (:func:`sparseloc.config.build_job` of the command line's options on
    ``movie``) in this process, as ``sparseloc localize`` runs it, reporting each frame done
    to ``progress``.

    Returns
    -------
    LocalizeResult
    """
    from ..pipeline import localize

    return localize(
        job.frames(movie),
        job.model,
        job.params,
        start=job.start,
        stop=job.stop,
        progress=progress,
        workers=1,
        read_variance=job.read_variance_map,
    )


def check_job_frame(job: Any, movie: Any, index: int, table: Any) -> Any:
    """The frame check (:func:`sparseloc.pipeline.check_frame`) of frame ``index`` of
    ``job``'s run that gave ``table``: what the localizations leave unexplained."""
    from ..pipeline import check_frame

    frames = job.frames(movie)
    return check_frame(frames, index, table, job.model, job.params, job.read_variance_map)


@contextmanager
def _closing(movie: Any) -> Iterator[Any]:
    """``movie``, closed at the end of the block (the widget reopens it for each run)."""
    try:
        yield movie
    finally:
        movie.close()


class LocalizeWidget(Container):
    """Localize the chosen movie layer; see the module docstring.

    Parameters
    ----------
    viewer : napari.viewer.Viewer
        The viewer whose layers the widget reads and adds to.
    """

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer
        # each movie's defective pixels and clipping level, found once per camera and pixel
        # size (a preview would otherwise read 50 frames on every click)
        self._defects: dict[tuple, Any] = {}
        d = LOCALIZE_DEFAULTS
        self.movie = ComboBox(
            name="movie", label="movie layer", choices=layer_choices(viewer, "Image")
        )
        self.psf = ComboBox(name="psf", label="PSF", choices=PSF_CHOICES, value=d["psf"] or "file")
        self.psf_file = FileEdit(
            name="psf_file", label="PSF file", mode="r", filter="*.h5 *.hdf5 *.mat *.npy *.tif"
        )
        self.pixel_size = OptionalNumber(
            "pixel_size", "pixel size (nm)", tooltip="empty: the calibration's"
        )
        self.cam = CameraFields()
        self.optics = [
            OptionalNumber("na", "NA"),
            OptionalNumber("wavelength", "wavelength (nm)"),
            OptionalNumber("mask_radius", "mask radius (mask px)"),
            OptionalNumber("blur", "blur (nm)"),
            OptionalNumber("n_sample", "sample index"),
            OptionalNumber("focal_depth", "focal depth (nm)"),
            OptionalNumber("z_min", "z min (nm)"),
            OptionalNumber("z_max", "z max (nm)"),
        ]
        self.method = ComboBox(
            name="method", choices=["frame", "hybrid", "mp", "co"], value=d["method"]
        )
        self.min_snr = FloatSpinBox(
            name="min_snr", label="min SNR", value=d["min_snr"], min=0.1, max=1000
        )
        self.background = ComboBox(
            name="background", choices=["auto", "temporal", "spatial"], value=d["background"]
        )
        self.refine = CheckBox(name="refine", text="maximum-likelihood refinement", value=True)
        self.engine = ComboBox(name="engine", choices=["auto", "numba", "numpy"], value="auto")
        self.frames = LineEdit(name="frames", label="frames (START:STOP)")
        self.output = FileEdit(
            name="output", label="table", mode="w", filter="*.parquet *.csv *.hdf5"
        )
        self.preview_button = PushButton(name="preview", text="Preview current frame")
        self.run_button = PushButton(name="run", text="Run")
        self.cancel_button = PushButton(name="cancel", text="Cancel", enabled=False)
        self.progress = ProgressBar(name="progress", value=0, min=0, max=1)
        self.status = Label(name="status", value="")
        super().__init__(
            widgets=[
                self.movie,
                self.psf,
                self.psf_file,
                self.pixel_size.widget,
                *self.cam.widgets,
                *(o.widget for o in self.optics),
                self.method,
                self.min_snr,
                self.background,
                self.refine,
                self.engine,
                self.frames,
                self.output,
                self.preview_button,
                self.run_button,
                self.cancel_button,
                self.progress,
                self.status,
            ],
            scrollable=True,
        )
        self.status.native.setWordWrap(True)
        self.task: Task | None = None
        self.preview_button.changed.connect(self.preview)
        self.run_button.changed.connect(self.run)
        self.cancel_button.changed.connect(self.cancel)
        for ev in (viewer.layers.events.inserted, viewer.layers.events.removed):
            ev.connect(lambda _e=None: self.movie.reset_choices())

    # -- options ------------------------------------------------------------------------------

    def given_options(self) -> dict[str, Any]:
        """The options given, as the command line's ``given`` dict (None: not given).

        Raises
        ------
        ValueError
            For a number field that is not a number, or "file" without a PSF file.
        """
        psf = self.psf.value
        if psf == "file":
            f = self.psf_file.value
            if f is None or not str(f).strip() or Path(f).is_dir():
                raise ValueError("choose the PSF file (a calibration .h5 or a mask file)")
            psf = str(f)
        opts: dict[str, Any] = {"psf": psf, "pixel_size": self.pixel_size.value}
        opts.update(self.cam.options())
        opts.update({o.name: o.value for o in self.optics})
        opts.update(
            method=self.method.value,
            min_snr=float(self.min_snr.value),
            background=self.background.value,
            refine=bool(self.refine.value),
            engine=self.engine.value,
            frames=str(self.frames.value).strip() or None,
        )
        return {k: v for k, v in opts.items() if v is not None}

    def _movie(self) -> Any:
        return movie_of(self.movie.value)

    # -- actions ------------------------------------------------------------------------------

    def preview(self, _value: Any = None) -> Task | None:
        """Localize the frame the viewer shows and draw its localizations as points."""
        from ..config import build_job

        movie = None
        try:
            layer = self.movie.value
            movie = self._movie()
            f = current_frame(self.viewer, layer)
            opts = self.given_options()
            key = (id(layer.data), repr(sorted((k, str(v)) for k, v in opts.items())))
            known = self._defects.get(key, ("find", None))
            job = build_job({**opts, "frames": f"{f}:{f + 1}"}, movie, *known)
            self._defects[key] = (job.defects, job.clipped)
        except INPUT_ERRORS as exc:
            return self._refuse(exc, movie)

        def call(progress: Any) -> Any:
            from ..messages import INPUT_ERRORS, one_sentence

            with _closing(movie):
                res = localize_job(job, movie, progress)
                try:  # the points stand without the check
                    return res, check_job_frame(job, movie, f, res.table)
                except INPUT_ERRORS as exc:
                    return res, one_sentence(exc)

        def done(out: Any) -> None:
            res, check = out
            name = f"{layer.name} frame {f}"
            self._show_points(res.table, job, layer, name)
            said = f"frame {f}: {len(res.table)} localizations in {res.seconds:.1f} s"
            if isinstance(check, str):
                self.status.value = f"{said}; the check failed: {check}"
                return
            self._show_residual(check, layer, f"{name} residual")
            self.status.value = (
                f"{said}; {len(check.unexplained)} peaks of light left (layer '{name} residual')"
            )

        return self._start(call, done, 1)

    def run(self, _value: Any = None) -> Task | None:
        """Localize the frames chosen and write the table (only when every frame is done)."""
        from ..config import build_job
        from ..io.tables import format_for

        movie = None
        try:
            layer = self.movie.value
            movie = self._movie()
            out = self._output(movie)
            format_for(out, None)
            job = build_job(self.given_options(), movie)
        except INPUT_ERRORS as exc:
            return self._refuse(exc, movie)

        def call(progress: Any) -> Any:
            from ..io.localized import write_localized

            with _closing(movie):
                res = localize_job(job, movie, progress)
                # The table is written (atomically) only after the last frame: a cancel,
                # which stops the run at a frame's end, leaves no file.
                write_localized(res, out, format=None, movie=movie, job=job)
            return res

        def done(res: Any) -> None:
            self._show_points(res.table, job, layer, out.stem)
            self.status.value = f"{res.summary()}; wrote {out.name}"
            notify_info(f"wrote {out}")

        return self._start(call, done, job.stop - job.start)

    def cancel(self, _value: Any = None) -> None:
        """Stop the running preview or run at its next frame; nothing is written."""
        if self.task is not None:
            self.task.cancel()
            self.status.value = "cancelled"

    # -- helpers ------------------------------------------------------------------------------

    def _output(self, movie: Any) -> Path:
        """The output table chosen, checked: given, not a folder, not the movie itself."""
        value = self.output.value
        if value is None or not str(value).strip() or str(value) == ".":
            raise ValueError("choose the output table file (.parquet, .csv or .hdf5)")
        out = Path(value)
        if out.is_dir():
            raise ValueError(f"the output {str(out)!r} is a folder, not a file")
        if not out.parent.is_dir():
            raise ValueError(f"the output folder {str(out.parent)!r} does not exist")
        for p in getattr(movie, "paths", ()):
            if out.resolve() == Path(p).resolve():
                raise ValueError(f"the output {str(out)!r} is the input {str(p)!r}")
        return out

    def _refuse(self, exc: BaseException, movie: Any = None) -> None:
        from ..messages import one_sentence

        if movie is not None:
            movie.close()
        notify_error(one_sentence(exc))
        self.status.value = one_sentence(exc)
        return None

    def _start(self, call: Any, done: Any, total: int) -> Task:
        self.progress.max = max(1, total)
        self.progress.value = 0
        self.status.value = "running..."
        self._busy(True)
        task = Task(call)
        self.task = task

        def step(n: int) -> None:
            self.progress.value = min(self.progress.max, self.progress.value + n)

        task.start(step, done, lambda: self._busy(False))
        return task

    def _busy(self, busy: bool) -> None:
        self.preview_button.enabled = not busy
        self.run_button.enabled = not busy
        self.cancel_button.enabled = busy

    def _show_residual(self, check: Any, layer: Any, name: str) -> None:
        """Add (or replace) the preview's residual, ``(frame - model) / noise SD``
        (:mod:`sparseloc.frame_residual`), as an image layer over the frame's pixels; hidden,
        so the frame and its points stay in view."""
        if name in self.viewer.layers:
            self.viewer.layers.remove(name)
        self.viewer.add_image(
            check.residual,
            name=name,
            colormap="RdBu_r",
            contrast_limits=(-5.0, 5.0),
            scale=tuple(layer.scale[-2:]),
            translate=tuple(layer.translate[-2:]),
            visible=False,
        )

    def _show_points(self, table: Any, job: Any, layer: Any, name: str) -> None:
        """Add (or replace) the points layer of ``table`` over ``layer``."""
        data, kwargs = points_for_table(
            table, job.params.pixel_size, layer, job.params.z_range, name
        )
        if name in self.viewer.layers:
            self.viewer.layers.remove(name)
        self.viewer.add_points(data, **kwargs)
