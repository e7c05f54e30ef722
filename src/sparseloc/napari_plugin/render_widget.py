"""The render widget: the xy, xz and yz renders of a table (coloured by depth, as ``sparseloc
render`` draws them) as image layers with a scale bar, the FRC resolution reported, and an
optional drift correction (:func:`sparseloc.drift.rcc_drift`) first."""

from __future__ import annotations

from typing import Any

from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    Label,
    ProgressBar,
    PushButton,
    SpinBox,
)

from ._form import OptionalNumber, layer_choices
from ._layers import table_of
from ._worker import Task, notify_error, notify_info

__all__ = ["RenderWidget", "render_table"]


def render_table(
    table: Any,
    *,
    px_nm: float | None = None,
    all_flags: bool = False,
    drift_segments: int | None = None,
) -> dict[str, Any]:
    """What the render widget shows of ``table``: the rows render uses (flag 'ok' unless
    ``all_flags``), drift-corrected first when ``drift_segments`` is given, rendered as
    ``sparseloc render`` renders them, with the FRC message.

    Returns
    -------
    dict
        ``"images"``: {projection: (rgb (rows, cols, 3), extent (h0, h1, v0, v1) nm)},
        ``"px_nm"``, ``"frc"`` (message), ``"drift"`` (message or None), ``"n"`` (rows drawn).

    Raises
    ------
    ValueError
        In one sentence, as the command line says it (e.g. an unreliable drift estimate).
    """
    from ..drift import apply_drift, rcc_drift
    from ..postprocess import select_usable
    from ..render import frc_report, render_projections, to_rgb

    if len(table) == 0:
        raise ValueError("the table holds no localizations")
    table = select_usable(table, all_flags=all_flags).locs
    drift_msg = None
    if drift_segments is not None:
        est = rcc_drift(table, segments=drift_segments, all_flags=all_flags)
        if not est.reliable:
            raise ValueError(
                "the drift estimate is unreliable (see the log); the table was not corrected"
            )
        table = apply_drift(table, est)
        span = est.drift.max(axis=0) - est.drift.min(axis=0)
        drift_msg = (
            f"drift ({est.method}): range x {span[0]:.1f} nm, y {span[1]:.1f} nm, "
            f"z {span[2]:.1f} nm"
        )
    proj = render_projections(table, px_nm=px_nm)
    images = {}
    for name in ("xy", "xz", "yz"):
        r = getattr(proj, name)
        if r is not None:
            images[name] = (to_rgb(r, z_range=proj.z_range), r.extent)
    _, frc_msg = frc_report(table)
    return {
        "images": images,
        "px_nm": proj.px_nm,
        "frc": frc_msg,
        "drift": drift_msg,
        "n": len(table),
    }


def _takes_units(viewer: Any) -> bool:
    import inspect

    return "units" in inspect.signature(viewer.add_image).parameters


class RenderWidget(Container):
    """Render a localization table; see the module docstring.

    Parameters
    ----------
    viewer : napari.viewer.Viewer
        The viewer whose layers the widget reads and adds to.
    """

    def __init__(self, viewer: Any) -> None:
        self.viewer = viewer
        self.table = ComboBox(
            name="table", label="table layer", choices=layer_choices(viewer, "Points")
        )
        self.file = FileEdit(
            name="file", label="or table file", mode="r", filter="*.parquet *.csv *.hdf5 *.h5"
        )
        self.px = OptionalNumber("px", "render pixel (nm)", tooltip="empty: from the table")
        self.all_flags = CheckBox(name="all_flags", text="use flagged fits too", value=False)
        self.drift = CheckBox(name="drift", text="correct drift first (rcc)", value=False)
        self.segments = SpinBox(name="segments", label="drift segments", value=10, min=2)
        self.render_button = PushButton(name="render", text="Render")
        self.progress = ProgressBar(name="progress", value=0, min=0, max=1)
        self.status = Label(name="status", value="")
        super().__init__(
            widgets=[
                self.table,
                self.file,
                self.px.widget,
                self.all_flags,
                self.drift,
                self.segments,
                self.render_button,
                self.progress,
                self.status,
            ],
            scrollable=True,
        )
        self.status.native.setWordWrap(True)
        self.task: Task | None = None
        self.render_button.changed.connect(self.render)
        for ev in (viewer.layers.events.inserted, viewer.layers.events.removed):
            ev.connect(lambda _e=None: self.table.reset_choices())

    def _table(self) -> tuple[Any, str]:
        from pathlib import Path

        from ..io.tables import read_table_and_metadata

        f = self.file.value
        text = "" if f is None else str(f).strip()
        if text not in ("", "."):
            return read_table_and_metadata(text)[0], Path(text).name
        return table_of(self.table.value)

    def render(self, _value: Any = None) -> Task | None:
        """Render in a worker thread and add the three images."""
        from ..messages import INPUT_ERRORS, one_sentence

        try:
            table, name = self._table()
            kwargs = {
                "px_nm": self.px.value,
                "all_flags": bool(self.all_flags.value),
                "drift_segments": int(self.segments.value) if self.drift.value else None,
            }
        except INPUT_ERRORS as exc:
            notify_error(one_sentence(exc))
            return None

        def done(res: dict) -> None:
            self._show(res, name)
            lines = [res["drift"], res["frc"]] if res["drift"] else [res["frc"]]
            self.status.value = "\n".join(lines)
            notify_info(res["frc"])

        self.progress.min = self.progress.max = 0
        self.render_button.enabled = False
        self.task = Task(lambda _p: render_table(table, **kwargs))
        self.task.start(lambda _n: None, done, self._finished)
        return self.task

    def _finished(self) -> None:
        self.progress.min, self.progress.max = 0, 1
        self.render_button.enabled = True

    def _show(self, res: dict, name: str) -> None:
        """The xy image with yz at its right (z to the right) and xz below it (z down), as
        in the render figure's layout, in nm."""
        px = res["px_nm"]
        images = res["images"]
        x0, x1, y0, y1 = images["xy"][1]
        gap = 10 * px
        # The scale bar reads the layers' units (napari >= 0.6; older ones show no unit).
        units = {"units": ("nm", "nm")} if _takes_units(self.viewer) else {}
        for proj, (rgb, ext) in images.items():
            if proj == "yz":  # rows y, columns z
                rgb, origin = rgb.transpose(1, 0, 2), (ext[0], x1 + gap)
            elif proj == "xz":  # rows z, columns x
                origin = (y1 + gap, ext[0])
            else:
                origin = (y0, x0)
            layer = f"{name} {proj}"
            if layer in self.viewer.layers:
                self.viewer.layers.remove(layer)
            self.viewer.add_image(
                rgb,
                name=layer,
                rgb=True,
                scale=(px, px),
                translate=(origin[0] + px / 2, origin[1] + px / 2),
                metadata={"projection": proj, "extent_nm": ext},
                **units,
            )
        self.viewer.scale_bar.visible = True
