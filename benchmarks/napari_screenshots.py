"""Screenshots of the napari plugin on the shared data (``viewer.screenshot()``), written to
``docs/napari/``:

- ``localize_dh_dense.png`` (and ``_zoom``): the localize preview on a dense double-helix frame
  of ``storm_analysis_sim/dh`` (1 emitter per um^2), with the PSF calibrated from the folder's
  bead scan by the calibrate widget (100 nm pixels, each frame's z from
  ``beads_zscan_z.csv``, offset 100 ADU: the settings of ``benchmarks/storm_analysis.py``);
- ``localize_tetrapod.png`` (and ``_zoom``): the preview on DeepSTORM3D's real tetrapod frame,
  with README's settings (mask file, NA 1.45, 670 nm, mask radius 48.3, blur 110 nm, water
  at 1.5 um, z -1500..2500 nm, spatial background, sCMOS offset 30 ADU, gain 0.6017 e-/ADU,
  read noise 5.75 e-);
- ``calibrate_smlm2016_dh.png``: the calibrate widget on the SMLM 2016 challenge's DH bead
  stack (100 nm pixels, 10 nm steps, offset 100 ADU), the model beside the stack.

Needs the ``napari`` extra, a display with OpenGL (e.g. ``xvfb-run -a``) and
``../shared/data``. Prints each preview's count of localizations.

    xvfb-run -a -s "-screen 0 1920x1200x24" python benchmarks/napari_screenshots.py
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("SPARSELOC_SHARED_DATA", "../shared/data"))
OUT = Path("docs/napari")


def wait(app, task, timeout_s: float = 1800.0) -> None:
    """Process Qt events until the widget's task has finished."""
    t0 = time.perf_counter()
    while task is not None and not task.finished:
        app.processEvents()
        time.sleep(0.05)
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError("the widget's task did not finish")
    app.processEvents()


def dock(viewer, widget, name: str):
    """Dock ``widget`` at the right, 480 px wide (the canvas keeps most of the window)."""
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QApplication

    widget.dock = viewer.window.add_dock_widget(widget, name=name, area="right")
    QApplication.instance().processEvents()
    viewer.window._qt_window.resizeDocks([widget.dock], [480], Qt.Horizontal)
    return widget.dock


def new_viewer(napari, title: str):
    viewer = napari.Viewer(title=title, show=True)
    viewer.window._qt_window.resize(1900, 1080)
    return viewer


def open_movie(viewer, path: Path):
    from sparseloc.napari_plugin.readers import read_movie

    [(data, kwargs, _)] = read_movie(str(path))
    return viewer.add_image(data, **kwargs)


def shoot(viewer, app, name: str, canvas_only: bool = False) -> Path:
    from napari._qt.dialogs.qt_notification import NapariQtNotification

    for toast in viewer.window._qt_window.findChildren(NapariQtNotification):
        toast.close()  # e.g. napari's PyQt5 deprecation notice over the canvas
    for _ in range(5):
        app.processEvents()
    if not canvas_only:
        viewer.reset_view()  # fit the data to the canvas as the docked widget left it
        app.processEvents()
    path = OUT / name
    viewer.screenshot(str(path), canvas_only=canvas_only, flash=False)
    print(f"wrote {path}")
    return path


def zoom(viewer, layer, centre_rc: tuple[float, float], half_px: float) -> None:
    """Show ``half_px`` pixels around ``centre_rc`` (row, col) of ``layer``."""
    sy, sx = layer.scale[-2:]
    canvas_h = viewer.window._qt_viewer.canvas.size[1]
    camera = getattr(getattr(viewer, "scene", None), "camera", None) or viewer.camera
    camera.center = (centre_rc[0] * sy, centre_rc[1] * sx)
    camera.zoom = canvas_h / (2 * half_px * sy)


def side_by_side(viewer, app, layer, centre_rc, half_px: float, name: str) -> Path:
    """A zoom on ``half_px`` pixels around ``centre_rc`` (row, col): the frame alone (left)
    beside the frame with the points layers over it (right), in one PNG; every other layer
    (the preview's residual) is hidden."""
    import matplotlib.pyplot as plt
    from napari.layers import Points

    zoom(viewer, layer, centre_rc, half_px)
    for ly in viewer.layers:
        if ly is not layer and not isinstance(ly, Points):
            ly.visible = False
    viewer.screenshot(canvas_only=True, flash=False)  # draws the new view once
    others = [ly for ly in viewer.layers if isinstance(ly, Points)]
    shots = []
    for visible in (False, True):
        for ly in others:
            ly.visible = visible
        for _ in range(5):
            app.processEvents()
        shots.append(viewer.screenshot(canvas_only=True, flash=False))
    gap = np.full((shots[0].shape[0], 12, shots[0].shape[2]), 255, dtype=shots[0].dtype)
    path = OUT / name
    plt.imsave(path, np.hstack([shots[0], gap, shots[1]]))
    print(f"wrote {path}")
    return path


def calibrate(app, viewer, stack: Path, pixel: float, **fields):
    """Drive the calibrate widget (docked) on ``stack``; returns the widget."""
    from sparseloc.napari_plugin.calibrate_widget import CalibrateWidget

    layer = open_movie(viewer, stack)
    w = CalibrateWidget(viewer)
    dock(viewer, w, "sparseloc calibrate")
    w.stack.value = layer
    w.pixel_size.value = pixel
    for name, value in fields.items():  # plain fields and optional numbers alike
        getattr(w, name).value = value
    wait(app, w.run())
    print(w.summary.value)
    return w, layer


def dh_dense(napari, app, tmp: Path) -> None:
    d = DATA / "storm_analysis_sim" / "dh"
    viewer = new_viewer(napari, "sparseloc: dense double helix")
    cw, _ = calibrate(app, viewer, d / "beads_zscan.tif", 100.0, z_file=d / "beads_zscan_z.csv")
    psf = tmp / "dh_psf.h5"
    cw.output.value = psf
    assert cw.save() == psf
    viewer.close()
    from sparseloc.napari_plugin.localize_widget import LocalizeWidget

    viewer = new_viewer(napari, "sparseloc: dense double helix")
    layer = open_movie(viewer, d / "dh_random_density0.01px2.tif")
    w = LocalizeWidget(viewer)
    dock(viewer, w, "sparseloc localize")
    w.movie.value = layer
    w.psf.value = "file"
    w.psf_file.value = psf
    w.cam.offset.value = 100.0
    wait(app, w.preview())
    print("dense DH frame:", w.status.value)
    viewer.reset_view()
    shoot(viewer, app, "localize_dh_dense.png")
    # Scored against the folder's ground truth, which the zoomed view shows as white crosses.
    from sparseloc.evaluate import evaluate
    from sparseloc.io.truth import read_truth_csv

    points = viewer.layers[f"{layer.name} frame 0"]
    truth = read_truth_csv(d / "dh_random_density0.01px2_groundtruth.csv", pixel_size=100.0)
    print(evaluate(points.metadata["sparseloc_table"], truth).summary())
    rc = np.column_stack([np.zeros(len(truth)), truth.y_nm / 100 - 0.5, truth.x_nm / 100 - 0.5])
    viewer.add_points(rc, name="ground truth", symbol="cross", size=2, face_color="white")
    points.size = 4
    side_by_side(viewer, app, layer, (100, 150), 30, "localize_dh_dense_zoom.png")
    viewer.close()


def tetrapod(napari, app) -> None:
    from sparseloc.napari_plugin.localize_widget import LocalizeWidget

    d = DATA / "deepstorm3d"
    viewer = new_viewer(napari, "sparseloc: tetrapod")
    layer = open_movie(viewer, d / "Experimental_Data_Tetrapod_demo2_1.tif")
    w = LocalizeWidget(viewer)
    dock(viewer, w, "sparseloc localize")
    w.movie.value = layer
    w.psf.value = "file"
    w.psf_file.value = d / "Mat_Files_mask_tetrapod_printed.mat"
    w.pixel_size.value = 110.0
    optics = {o.name: o for o in w.optics}
    for name, value in {
        "na": 1.45,
        "wavelength": 670.0,
        "mask_radius": 48.3,
        "blur": 110.0,
        "n_sample": 1.33,
        "focal_depth": 1500.0,
        "z_min": -1500.0,
        "z_max": 2500.0,
    }.items():
        optics[name].value = value
    w.background.value = "spatial"
    w.cam.camera.value = "scmos"
    w.cam.offset.value = 30.0
    w.cam.gain.value = 0.6017
    w.cam.read_noise.value = 5.75
    wait(app, w.preview())
    print("tetrapod frame:", w.status.value)
    frame = np.asarray(layer.data[0], dtype=float)
    layer.contrast_limits = tuple(np.percentile(frame, [5, 99.8]))
    viewer.reset_view()
    shoot(viewer, app, "localize_tetrapod.png")
    rows, cols = layer.data.shape[-2:]
    viewer.layers[f"{layer.name} frame 0"].size = 6
    half = min(rows, cols) / 4
    side_by_side(viewer, app, layer, (rows / 2, cols / 2), half, "localize_tetrapod_zoom.png")
    viewer.close()


def smlm2016(napari, app) -> None:
    viewer = new_viewer(napari, "sparseloc: calibrate (SMLM 2016 DH beads)")
    _, layer = calibrate(app, viewer, DATA / "smlm2016" / "beads_dh.tif", 100.0, z_step=10.0)
    model = viewer.layers[f"{layer.name} PSF model"]
    viewer.layers.move(viewer.layers.index(model), len(viewer.layers))  # on top
    # The grid puts each run of ``stride`` layers from the bottom in a cell: the stack with
    # its beads in one, the model in the next.
    grid = getattr(getattr(viewer, "canvas", None), "grid", None) or viewer.grid
    grid.stride = 2
    grid.enabled = True
    viewer.dims.set_point(0, 0.0)  # z = 0 nm: the focus of stack and model alike
    viewer.reset_view()
    shoot(viewer, app, "calibrate_smlm2016_dh.png")
    viewer.close()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=["dh", "tetrapod", "smlm2016"], action="append")
    args = ap.parse_args(argv)
    import napari
    from qtpy.QtWidgets import QApplication

    OUT.mkdir(parents=True, exist_ok=True)
    app = QApplication.instance() or napari.qt.get_qapp()
    wanted = args.only or ["dh", "tetrapod", "smlm2016"]
    with tempfile.TemporaryDirectory() as tmp:
        if "dh" in wanted:
            dh_dense(napari, app, Path(tmp))
        if "tetrapod" in wanted:
            tetrapod(napari, app)
        if "smlm2016" in wanted:
            smlm2016(napari, app)


if __name__ == "__main__":
    main()
