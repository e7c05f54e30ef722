"""Form fields the widgets share: optional numbers (empty: the command line's default), the
camera's options (the command line's vocabulary and defaults) and layer choices."""

from __future__ import annotations

from typing import Any

from ..options import CAMERA_DEFAULTS

__all__ = ["CameraFields", "OptionalNumber", "layer_choices"]


class OptionalNumber:
    """A text field for a number, kept exactly as typed (a spin box would round it); left
    empty it is ``default`` (None: the command line's default).

    Parameters
    ----------
    name : str
        The option's name (as in :data:`sparseloc.options.LOCALIZE_DEFAULTS`).
    label : str
        What the field shows.
    whole : bool
        A whole number (window sizes, passes) rather than a real one.
    default : float, optional
        The value of an empty field, shown in it at the start.
    """

    def __init__(
        self,
        name: str,
        label: str,
        whole: bool = False,
        tooltip: str = "",
        default: float | None = None,
    ) -> None:
        from magicgui.widgets import LineEdit

        self.name, self.whole, self.default = name, whole, default
        self.widget = LineEdit(name=name, label=label, tooltip=tooltip or None)
        self.value = default

    @property
    def value(self) -> float | int | None:
        """The number typed, ``default`` when empty; ValueError in one sentence otherwise."""
        text = str(self.widget.value).strip()
        if not text:
            return self.default
        try:
            return int(text) if self.whole else float(text)
        except ValueError:
            kind = "a whole number" if self.whole else "a number"
            raise ValueError(f"{self.name} must be {kind}, got {text!r}") from None

    @value.setter
    def value(self, v: float | None) -> None:
        self.widget.value = "" if v is None else f"{v:.12g}"


class CameraFields:
    """The camera's flags as fields: kind, offset (ADU), gain (e-/ADU), EM gain, QE and read
    noise (e- rms), with :data:`sparseloc.options.CAMERA_DEFAULTS`."""

    def __init__(self) -> None:
        from magicgui.widgets import ComboBox

        d = CAMERA_DEFAULTS
        self.camera = ComboBox(
            name="camera", label="camera", choices=["ideal", "emccd", "scmos"], value=d["camera"]
        )
        self.offset = OptionalNumber("offset", "offset (ADU)", default=d["offset"])
        self.gain = OptionalNumber("gain", "gain (e-/ADU)", default=d["gain"])
        self.em_gain = OptionalNumber("em_gain", "EM gain", default=d["em_gain"])
        self.qe = OptionalNumber("qe", "QE", default=d["qe"])
        self.read_noise = OptionalNumber(
            "read_noise", "read noise (e- rms)", default=d["read_noise"]
        )
        self._numbers = [self.offset, self.gain, self.em_gain, self.qe, self.read_noise]

    @property
    def widgets(self) -> list[Any]:
        return [self.camera, *(n.widget for n in self._numbers)]

    def options(self) -> dict[str, Any]:
        """The camera options as the command line passes them (keys of CAMERA_DEFAULTS)."""
        return {"camera": self.camera.value, **{n.name: n.value for n in self._numbers}}


def layer_choices(viewer: Any, kind: str) -> Any:
    """A function listing the viewer's layers of ``kind`` ("Image", "Points") for a ComboBox
    (None first: no layer chosen)."""

    def choices(_widget: Any = None) -> list[Any]:
        found = [(ly.name, ly) for ly in viewer.layers if type(ly).__name__ == kind]
        return [("", None), *found]

    return choices
