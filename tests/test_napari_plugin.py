"""The napari plugin's readers and widgets, driven on a small simulated movie and bead stack
and checked against the command line: the preview's points are ``localize`` on that frame,
Run writes the CLI's table, cancel writes nothing, bad input is one notification.

Skipped where napari, Qt (with pytest-qt) or magicgui is missing. Where Qt cannot make an
OpenGL context (e.g. ``QT_QPA_PLATFORM=offscreen`` without a GPU or Xvfb) the widgets run
on napari's viewer model, which has no canvas; the test that docks them in a real viewer
is then skipped.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")  # no screen: Qt draws off screen

napari = pytest.importorskip("napari", reason="napari is not installed (the napari extra)")
pytest.importorskip("pytestqt", reason="pytest-qt is not installed")
pytest.importorskip("magicgui", reason="magicgui is not installed")
pytest.importorskip("qtpy.QtWidgets", reason="no Qt bindings")

from cli_checks import run  # noqa: E402
from sparseloc.io.tables import read_parquet  # noqa: E402

PX = 160.0  # movie pixel (nm)
LOCALIZE_ARGS = ["--psf", "dh-analytic", "--pixel-size", "160", "--z-min", "-300", "--z-max", "300"]
WAIT_MS = 60_000


# -- data ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def movie(tmp_path_factory) -> Path:
    """Four frames of 32 x 32 px (160 nm) of the analytic double helix, written by
    ``sparseloc simulate`` (the TIFF records its pixel size)."""
    path = tmp_path_factory.mktemp("movie") / "m.tif"
    res = run(
        "simulate", "-o", path, "--psf", "dh-analytic", "--frames", "4", "--rows", "32",
        "--cols", "32", "--pixel-size", "160", "--density", "0.15", "--photons-min", "3000",
        "--photons-max", "4000", "--z-min", "-300", "--z-max", "300", "--seed", "3",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return path


@pytest.fixture(scope="module")
def beads(tmp_path_factory) -> Path:
    """A bead z-scan: four beads, 39 planes -475..475 nm in 25 nm steps, 76 x 76 px of
    100 nm, offset 100 ADU."""
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    zp = np.arange(-475.0, 475.0 + 1e-9, 25.0)
    pos = np.array([[2000.0, 2050.0], [5530.0, 2010.0], [2020.0, 5480.0], [5490.0, 5520.0]])
    truth = pd.concat(
        [bead_scan_truth(pos[i : i + 1], zp, 20000.0, np.zeros(1)) for i in range(len(pos))],
        ignore_index=True,
    )
    sim = simulate(
        make_psf("dh-analytic"),
        scene=truth,
        n_frames=zp.size,
        shape=(76, 76),
        pixel_size=100.0,
        background=10.0,
        seed=0,
    )
    path = tmp_path_factory.mktemp("beads") / "beads.tif"
    write_tiff(path, sim.movie)
    return path


# -- viewer ------------------------------------------------------------------------------------


def _opengl() -> str:
    """Empty when Qt can make an OpenGL context napari can draw with, else why not."""
    from qtpy.QtGui import QOffscreenSurface, QOpenGLContext

    ctx = QOpenGLContext()
    if not ctx.create():
        return f"Qt cannot create an OpenGL context (platform {os.environ.get('QT_QPA_PLATFORM')})"
    surface = QOffscreenSurface()
    surface.create()
    try:
        if not ctx.makeCurrent(surface):
            return "the OpenGL context cannot be made current"
        from vispy.gloo import gl

        if not gl.glGetParameter(gl.GL_EXTENSIONS):
            return "the OpenGL context reports no extensions"
    finally:
        ctx.doneCurrent()
    return ""


@pytest.fixture
def no_opengl(qapp) -> str:
    return _opengl()


@pytest.fixture
def viewer(request, no_opengl):
    """napari's viewer (``make_napari_viewer``) where OpenGL works, else its viewer model."""
    if not no_opengl:
        return request.getfixturevalue("make_napari_viewer")()
    from napari.components import ViewerModel

    return ViewerModel()


def _add(viewer, layer_tuples):
    """Add reader output (LayerDataTuples) as napari's ``open`` does; returns the layers."""
    out = []
    for data, kwargs, kind in layer_tuples:
        out.append(getattr(viewer, f"add_{kind}")(data, **kwargs))
    return out


def _movie_layer(viewer, path):
    from sparseloc.napari_plugin.readers import read_movie

    [layer] = _add(viewer, read_movie(str(path)))
    return layer


def _finish(qtbot, task):
    """Wait for a widget's task to end (worker and helper thread)."""
    assert task is not None
    qtbot.waitUntil(lambda: task.finished, timeout=WAIT_MS)
    if task.thread is not None:  # None: cancelled before it started
        task.thread.join(WAIT_MS / 1000)


@pytest.fixture
def errors():
    """The error notifications shown during the test (their messages)."""
    from napari.utils.notifications import NotificationSeverity, notification_manager

    start = len(notification_manager.records)

    def messages() -> list[str]:
        recs = notification_manager.records[start:]
        return [r.message for r in recs if r.severity == NotificationSeverity.ERROR]

    return messages


def _cli_error(res) -> str:
    """The one sentence a refused command printed (without ``error: ``)."""
    assert res.exit_code == 2, res.output
    [line] = [ln for ln in res.stderr.splitlines() if ln.strip()]
    return line.removeprefix("error: ")


def _localize_widget(viewer, layer, out=None):
    from sparseloc.napari_plugin.localize_widget import LocalizeWidget

    w = LocalizeWidget(viewer)
    w.movie.value = layer
    w.psf.value = "dh-analytic"
    w.pixel_size.value = 160.0
    {o.name: o for o in w.optics}["z_min"].value = -300.0
    {o.name: o for o in w.optics}["z_max"].value = 300.0
    if out is not None:
        w.output.value = out
    return w


# -- readers -----------------------------------------------------------------------------------


def test_the_movie_opens_lazily_with_its_files(movie):
    import dask.array as da

    from sparseloc.io.movie import Movie
    from sparseloc.napari_plugin.readers import MOVIE_KEY, get_movie_reader, read_movie

    assert get_movie_reader(str(movie)) is read_movie
    assert get_movie_reader(str(movie.with_suffix(".parquet"))) is None
    [(data, kwargs, kind)] = read_movie(str(movie))
    assert kind == "image" and isinstance(data, da.Array)
    assert data.chunks[0] == (1, 1, 1, 1)  # one frame a chunk, read when shown
    with Movie.open(movie) as mov:
        np.testing.assert_array_equal(np.asarray(data[2]), mov.frames(2, 3)[0])
        assert kwargs["metadata"][MOVIE_KEY] == [str(movie)]
        assert kwargs["metadata"]["pixel_size_nm"] == mov.pixel_size == PX


def test_a_bad_movie_file_is_the_cli_sentence(tmp_path):
    from sparseloc.napari_plugin.readers import read_movie

    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff")
    res = run("localize", bad, "-o", tmp_path / "x.parquet", *LOCALIZE_ARGS)
    with pytest.raises(ValueError) as err:
        read_movie(str(bad))
    from sparseloc.messages import one_sentence

    assert one_sentence(err.value) == _cli_error(res)


def test_the_manifest_declares_the_readers_and_widgets():
    npe2 = pytest.importorskip("npe2")
    import importlib

    import sparseloc

    pm = npe2.PluginManifest.from_file(Path(sparseloc.__file__).with_name("napari.yaml"))
    commands = {c.id: c.python_name for c in pm.contributions.commands}
    for w in pm.contributions.widgets:
        module, name = commands[w.command].split(":")
        assert callable(getattr(importlib.import_module(module), name))
    readers = [r.command for r in pm.contributions.readers]
    # calibrations are tried before tables (both are .h5)
    assert readers.index("sparseloc.get_calibration_reader") < readers.index("sparseloc.get_reader")


# -- localize ----------------------------------------------------------------------------------


def test_preview_is_localize_on_the_current_frame(qtbot, viewer, movie, tmp_path):
    layer = _movie_layer(viewer, movie)
    viewer.dims.set_point(0, 1)  # frame 1
    w = _localize_widget(viewer, layer)
    _finish(qtbot, w.preview())
    points = viewer.layers[f"{layer.name} frame 1"]
    ref = tmp_path / "frame1.parquet"
    res = run("localize", movie, "-o", ref, *LOCALIZE_ARGS, "--frames", "1:2", "--workers", "1")
    assert res.exit_code == 0, res.output
    table, _ = read_parquet(ref)
    assert len(table) >= 2 and len(points.data) == len(table)
    feats = points.features
    pd.testing.assert_frame_equal(
        feats[table.columns].reset_index(drop=True).astype(table.dtypes),
        table.reset_index(drop=True),
    )
    # one point at each localization's pixel position (frame, row, col), coloured by z
    np.testing.assert_allclose(points.data[:, 0], 1)
    np.testing.assert_allclose(points.data[:, 1], table.y_nm / PX - 0.5)
    np.testing.assert_allclose(points.data[:, 2], table.x_nm / PX - 0.5)
    for col in ("photons", "sigma_x_nm", "sigma_y_nm", "sigma_z_nm"):
        assert col in feats
    assert points.face_colormap.name == "turbo"
    # the frame check beside the points, hidden: the library's check of that frame
    from sparseloc.config import build_job
    from sparseloc.io.movie import Movie
    from sparseloc.napari_plugin.localize_widget import check_job_frame

    resid = viewer.layers[f"{layer.name} frame 1 residual"]
    assert not resid.visible and resid.data.shape == layer.data.shape[-2:]
    with Movie.open(movie) as mov:
        job = build_job({**w.given_options(), "frames": "1:2"}, mov)
        check = check_job_frame(job, mov, 1, table)
    np.testing.assert_allclose(resid.data, check.residual)


def test_previews_of_one_movie_look_for_defective_pixels_once(qtbot, viewer, movie, monkeypatch):
    """The search reads up to 50 frames of the movie; a preview per click would pay it each
    time. A change of camera settings searches again."""
    import sparseloc.config as config

    calls = []
    real = config.find_defects
    monkeypatch.setattr(config, "find_defects", lambda *a: calls.append(1) or real(*a))
    layer = _movie_layer(viewer, movie)
    w = _localize_widget(viewer, layer)
    for frame in (0, 1):
        viewer.dims.set_point(0, frame)
        _finish(qtbot, w.preview())
    assert len(calls) == 1
    w.cam.offset.value = 99.0
    _finish(qtbot, w.preview())
    assert len(calls) == 2


def test_previews_keep_the_clipping_level_they_found(qtbot, viewer, movie, tmp_path, monkeypatch):
    """The first preview finds a clipped movie's level with its defective pixels; the next
    previews reuse both, so every preview leaves out the same pixels as the command line."""
    import tifffile

    import sparseloc.config as config
    from sparseloc.io.tiff import write_tiff

    raw = tifffile.imread(movie)
    top = int(np.percentile(raw, 99.5))
    clipped = write_tiff(tmp_path / "clip.tif", np.minimum(raw, top).astype(np.uint16),
                         pixel_size=160.0)  # fmt: skip
    levels = []
    real = config.build_job
    monkeypatch.setattr(
        config, "build_job", lambda *a: levels.append((job := real(*a)).params.saturation) or job
    )
    w = _localize_widget(viewer, _movie_layer(viewer, clipped))
    for frame in (0, 1):
        viewer.dims.set_point(0, frame)
        _finish(qtbot, w.preview())
    assert levels == [top - 100.0] * 2  # the offset of LOCALIZE_ARGS' camera: 100 ADU


def test_run_writes_the_cli_table_and_cancel_writes_nothing(
    qtbot, viewer, movie, tmp_path, monkeypatch
):
    layer = _movie_layer(viewer, movie)
    out = tmp_path / "widget.parquet"
    w = _localize_widget(viewer, layer, out)
    _finish(qtbot, w.run())
    assert out.exists() and w.progress.value == 4
    ref = tmp_path / "cli.parquet"
    res = run("localize", movie, "-o", ref, *LOCALIZE_ARGS)
    assert res.exit_code == 0, res.output
    (mine, meta), (theirs, meta_cli) = read_parquet(out), read_parquet(ref)
    pd.testing.assert_frame_equal(mine, theirs)
    assert meta["params"] == meta_cli["params"] and meta["movie"] == meta_cli["movie"]
    assert meta["psf_hash"] == meta_cli["psf_hash"]
    assert out.stem in viewer.layers  # the table, shown over the movie
    w.cam.gain.value = 0.6017  # numbers are kept as typed (a spin box would round them)
    assert w.given_options()["gain"] == 0.6017
    w.cam.gain.value = 1.0
    # cancelled straight away, and after its first frame: no table, no temporary file
    out2 = tmp_path / "cancelled.parquet"
    w.output.value = out2
    task = w.run()
    w.cancel()
    _finish(qtbot, task)
    from sparseloc.napari_plugin import localize_widget

    frames_done = []
    original = localize_widget.localize_job

    def cancel_after_one_frame(job, movie, progress):
        def report(n=1):
            frames_done.append(n)
            w.cancel()  # the Cancel button, pressed once the first frame is done
            progress(n)

        return original(job, movie, report)

    monkeypatch.setattr(localize_widget, "localize_job", cancel_after_one_frame)
    _finish(qtbot, w.run())
    assert frames_done == [1]
    assert not out2.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cli.parquet", "widget.parquet"]


def test_bad_localize_input_is_one_notification(qtbot, viewer, movie, tmp_path, errors):
    layer = _movie_layer(viewer, movie)
    w = _localize_widget(viewer, None, tmp_path / "x.parquet")
    assert w.run() is None and w.preview() is None
    assert errors() == ["choose the movie layer (open a TIFF movie in napari first)"] * 2
    # a pixel size the movie's metadata contradicts: the CLI's sentence
    w.movie.value = layer
    w.pixel_size.value = 100.0
    res = run("localize", movie, "-o", tmp_path / "x.parquet", *LOCALIZE_ARGS[:2],
              "--pixel-size", "100")  # fmt: skip
    assert w.run() is None
    assert errors()[-1] == _cli_error(res)
    assert not any(tmp_path.iterdir())


# -- calibrate ---------------------------------------------------------------------------------


def test_calibrate_shows_the_model_and_saves_the_cli_file(qtbot, viewer, beads, movie, tmp_path,
                                                          errors):  # fmt: skip
    from sparseloc.io.calibration import read_calibration_info
    from sparseloc.napari_plugin.calibrate_widget import CalibrateWidget
    from sparseloc.napari_plugin.readers import get_calibration_reader, read_calibration

    layer = _movie_layer(viewer, beads)
    w = CalibrateWidget(viewer)
    w.stack.value = layer
    w.pixel_size.value = 100.0
    w.z_step.value = 25.0
    _finish(qtbot, w.run())
    assert w.calibration is not None and w.calibration.n_used == 4
    model = viewer.layers[f"{layer.name} PSF model"]
    assert model.data.shape == w.calibration.psf.stack.shape
    assert model.scale[0] == pytest.approx(25.0)  # the z slider in nm
    assert len(viewer.layers[f"{layer.name} beads"].data) == 4
    assert w.summary.value.startswith("4 of 4 beads used; ")
    out = tmp_path / "psf.h5"
    w.output.value = out
    assert w.save() == out and out.with_suffix(".png").exists()
    ref = tmp_path / "cli.h5"
    res = run("calibrate", beads, "-o", ref, "--pixel-size", "100", "--z-step", "25")
    assert res.exit_code == 0, res.output
    assert read_calibration_info(out)["content_hash"] == read_calibration_info(ref)["content_hash"]
    # the summary's lines are the CLI's (but for the time taken)
    cli_lines = res.output.splitlines()[1:-1]
    assert w.summary.value.splitlines()[1:] == cli_lines
    # the file opens as the model's stack and the beads used
    assert get_calibration_reader(str(out)) is read_calibration
    image, points = _add(viewer, read_calibration(str(out)))
    assert image.data.shape == model.data.shape and len(points.data) == 4
    # a pixel size that contradicts the calibration: the CLI's sentence, nothing written
    lw = _localize_widget(viewer, _movie_layer(viewer, movie), tmp_path / "locs.parquet")
    lw.psf.value = "file"
    lw.psf_file.value = out
    res = run("localize", movie, "-o", tmp_path / "locs.parquet", "--psf", out,
              "--pixel-size", "160")  # fmt: skip
    task = lw.run()
    if task is not None:  # refused by the run (in its worker), not before it
        _finish(qtbot, task)
    assert errors()[-1] == _cli_error(res), errors()
    assert not (tmp_path / "locs.parquet").exists()


def test_calibrate_cancel_stops_the_work(qtbot, viewer, beads, monkeypatch):
    """Cancel stops the calibration at its next step (one bead's registration), not only its
    result: the registrations after it are not run."""
    import sparseloc.calibrate as calibrate_module
    from sparseloc.napari_plugin.calibrate_widget import CalibrateWidget

    layer = _movie_layer(viewer, beads)
    w = CalibrateWidget(viewer)
    w.stack.value = layer
    w.pixel_size.value = 100.0
    w.z_step.value = 25.0
    fits = []
    original = calibrate_module._fit_shift

    def cancel_at_the_first_bead(*args, **kwargs):
        fits.append(1)
        w.cancel()  # the Cancel button, pressed during the first registration
        return original(*args, **kwargs)

    monkeypatch.setattr(calibrate_module, "_fit_shift", cancel_at_the_first_bead)
    _finish(qtbot, w.run())
    assert len(fits) == 1  # 4 beads x 3 rounds, and more, without the cancel
    assert w.calibration is None and w.summary.value == "cancelled"


def test_bad_calibrate_input_is_one_notification(qtbot, viewer, tmp_path, errors):
    from sparseloc.io.tiff import write_tiff
    from sparseloc.napari_plugin.calibrate_widget import CalibrateWidget

    w = CalibrateWidget(viewer)
    assert w.run() is None
    assert errors() == ["choose the bead stack layer (open the bead z-stack TIFF first)"]
    # a 2D image where a z-stack is needed
    frame = np.full((40, 40), 110, np.uint16)
    one = tmp_path / "one.tif"
    write_tiff(one, frame)
    res = run("calibrate", one, "-o", tmp_path / "x.h5", "--pixel-size", "100", "--z-step", "25")
    w.stack.reset_choices()
    w.stack.value = viewer.add_image(frame, name="one frame")
    w.z_step.value = 25.0
    _finish(qtbot, w.run())
    assert errors()[-1] == _cli_error(res)
    w.output.value = tmp_path / "x.h5"
    assert w.save() is None and errors()[-1] == "run the calibration first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.tif"]


# -- render ------------------------------------------------------------------------------------


def test_render_adds_the_three_projections_and_the_frc(qtbot, viewer, movie, tmp_path):
    from sparseloc.napari_plugin.render_widget import RenderWidget
    from sparseloc.napari_reader import read_points

    locs = tmp_path / "locs.parquet"
    assert run("localize", movie, "-o", locs, *LOCALIZE_ARGS).exit_code == 0
    res = run("render", locs, "-o", tmp_path / "image.png")
    assert res.exit_code == 0, res.output
    [layer] = _add(viewer, read_points(str(locs)))
    w = RenderWidget(viewer)
    w.table.value = layer
    _finish(qtbot, w.render())
    for proj in ("xy", "xz", "yz"):
        img = viewer.layers[f"{layer.name} {proj}"]
        assert img.rgb and img.data.shape[-1] == 3 and img.data.max() > 0
    frc_line = next(ln for ln in res.output.splitlines() if ln.startswith("FRC"))
    assert w.status.value == frc_line


def test_widgets_dock_in_a_real_viewer(request, no_opengl, movie):
    if no_opengl:
        pytest.skip(f"no OpenGL context for napari's canvas: {no_opengl}")
    from sparseloc.napari_plugin.calibrate_widget import CalibrateWidget
    from sparseloc.napari_plugin.localize_widget import LocalizeWidget
    from sparseloc.napari_plugin.render_widget import RenderWidget

    viewer = request.getfixturevalue("make_napari_viewer")()
    layer = _movie_layer(viewer, movie)
    for cls in (CalibrateWidget, LocalizeWidget, RenderWidget):
        viewer.window.add_dock_widget(cls(viewer), name=cls.__name__)
    assert viewer.screenshot(canvas_only=True).shape[-1] == 4
    assert layer in viewer.layers
