"""Issue 27, the camera side: one camera vocabulary on every command, the TOML file and the
Python API (item 6); ``sparseloc camera`` and the pupil's optics on the command line (item 9);
damaged calibration and mask files end in one sentence (item 16); calibrations without negative
voxels (item 17); no unauthenticated local Dask cluster for ``--workers`` (item 21)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import tifffile

from cli_checks import refused, run, runner
from sparseloc.cli import app

CAMERA_FLAGS = ("--camera", "--offset", "--gain", "--em-gain", "--qe", "--read-noise")
MAP_FLAGS = ("--offset-map", "--variance-map", "--gain-map")
ASTIG = Path(__file__).resolve().parents[2] / "shared" / "data" / "storm_analysis_sim" / "astig"


def held(res) -> None:
    """Success, or a refusal in one sentence: never a traceback."""
    if res.exit_code != 0:
        refused(res)


def _help_text(command: str) -> str:
    res = runner.invoke(app, [command, "--help"], env={"COLUMNS": "200", "TERMINAL_WIDTH": "200"})
    assert res.exit_code == 0, res.output
    return re.sub(r"\s+", " ", res.output)


@pytest.fixture(scope="module")
def beads(tmp_path_factory):
    """A small bead z-scan (ADU) from an EMCCD camera, written as a TIFF, and its camera."""
    from sparseloc.camera import Camera
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    cam = Camera(kind="emccd", offset=100.0, gain=10.0, em_gain=50.0, qe=0.9, read_noise=40.0)
    zs = np.arange(-500.0, 501.0, 50.0)
    pos = np.array([[1400.0, 2400.0], [3400.0, 2400.0], [2400.0, 1200.0]])
    truth = bead_scan_truth(pos, zs, 20000.0)
    sim = simulate(
        make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(48, 48), camera=cam
    )
    tif = write_tiff(tmp_path_factory.mktemp("beads") / "beads.tif", sim.movie, pixel_size=100.0)
    return tif, cam, sim.movie


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """A short simulated movie (ADU, ideal camera, offset 100) for ``localize``."""
    out = tmp_path_factory.mktemp("movie") / "movie.tif"
    res = run(
        "simulate", "-o", out, "--psf", "dh-analytic", "--frames", 8, "--rows", 32, "--cols",
        32, "--pixel-size", 160, "--density", 0.15, "--photons-min", 3000, "--photons-max",
        4000, "--z-min", -300, "--z-max", 300, "--seed", 3,
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    return out


LOCALIZE = ["--psf", "dh-analytic", "--pixel-size", 160, "--z-min", -300, "--z-max", 300]


# -- item 6: one camera vocabulary --------------------------------------------------------------


@pytest.mark.parametrize("command", ["calibrate", "localize", "simulate"])
def test_every_command_takes_the_same_camera_flags(command):
    text = _help_text(command)
    for flag in (*CAMERA_FLAGS, *MAP_FLAGS, "--config"):
        assert flag in text, f"{command} lacks {flag}"
    assert "photons per ADU" not in text  # the gain is e-/ADU everywhere
    assert "e-/ADU" in text
    assert "sCMOS)" not in text  # read noise is not sCMOS only: EMCCDs have it too


def test_camera_section_of_the_toml_file(tmp_path):
    from sparseloc.options import read_config

    cfg = tmp_path / "run.toml"
    cfg.write_text(
        '[camera]\nkind = "emccd"\noffset = 90.0\ngain = 12.0\nem_gain = 200.0\nqe = 0.9\n'
        'read_noise = 60.0\n\n[localize]\npsf = "dh-analytic"\npixel_size = 160.0\n'
    )
    opts = read_config(cfg)
    assert opts["camera"] == "emccd" and opts["em_gain"] == 200.0 and opts["read_noise"] == 60.0
    assert opts["offset"] == 90.0 and opts["gain"] == 12.0 and opts["qe"] == 0.9
    assert opts["psf"] == "dh-analytic"
    # one description: the same Camera from the options as from the Python API
    from sparseloc.camera import Camera, camera_from_options

    expected = Camera(kind="emccd", offset=90, gain=12, em_gain=200, qe=0.9, read_noise=60)
    assert camera_from_options(opts) == expected
    # the camera given twice (in [camera] and in [localize]) is refused in one sentence
    cfg.write_text("[camera]\ngain = 2.0\n\n[localize]\ngain = 3.0\n")
    with pytest.raises(ValueError, match="gain"):
        read_config(cfg)
    cfg.write_text("[camera]\ngian = 2.0\n")
    with pytest.raises(ValueError, match="gian"):
        read_config(cfg)


def test_camera_table_takes_the_flags_name_for_the_kind(tmp_path):
    """Item 6: the flag is --camera, so ``camera = "emccd"`` in [camera] is read as ``kind``;
    both together are refused."""
    from sparseloc.options import read_config

    cfg = tmp_path / "run.toml"
    cfg.write_text('[camera]\ncamera = "emccd"\nem_gain = 100.0\n')
    assert read_config(cfg)["camera"] == "emccd"
    cfg.write_text('[camera]\ncamera = "emccd"\nkind = "scmos"\n')
    with pytest.raises(ValueError, match="both kind and camera"):
        read_config(cfg)


def test_calibrate_converts_adu_to_photons_as_localize_does(beads, tmp_path):
    from sparseloc.camera import to_photons
    from sparseloc.io.calibration import read_calibration_info

    tif, cam, adu = beads
    out = tmp_path / "psf.h5"
    res = run(
        "calibrate", tif, "--pixel-size", 100, "--z-step", 50, "--camera", "emccd",
        "--offset", 100, "--gain", 10, "--em-gain", 50, "--qe", 0.9, "--read-noise", 40,
        "-o", out,
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    params = read_calibration_info(out)["params"]
    photons = (adu.astype(float) - params["offset_adu"]) * params["photons_per_adu"]
    np.testing.assert_allclose(photons, to_photons(adu, cam), rtol=1e-12)


def test_calibrate_reads_the_camera_section(beads, tmp_path):
    from sparseloc.io.calibration import read_calibration_info

    tif, _, _ = beads
    cfg = tmp_path / "cam.toml"
    cfg.write_text('[camera]\nkind = "emccd"\noffset = 100.0\ngain = 10.0\nem_gain = 50.0\n')
    out = tmp_path / "psf.h5"
    res = run("calibrate", tif, "--pixel-size", 100, "--z-step", 50, "--config", cfg, "-o", out)
    assert res.exit_code == 0, res.output
    assert read_calibration_info(out)["params"]["photons_per_adu"] == pytest.approx(10.0 / 50.0)


def test_emccd_read_noise_reaches_simulate_and_localize(movie, tmp_path):
    sim = tmp_path / "em.tif"
    args = ["--camera", "emccd", "--em-gain", 100, "--gain", 20, "--read-noise", 50]
    res = run("simulate", "-o", sim, "--psf", "dh-analytic", "--frames", 2, "--rows", 24,
              "--cols", 24, "--pixel-size", 160, *args)  # fmt: skip
    assert res.exit_code == 0, res.output
    cfg = tmp_path / "cam.toml"
    cfg.write_text('[camera]\nkind = "emccd"\nem_gain = 100.0\ngain = 20.0\nread_noise = 50.0\n')
    out = tmp_path / "locs.parquet"
    res = run("localize", sim, "-o", out, *LOCALIZE, "--workers", 1, "--config", cfg)
    assert res.exit_code == 0, res.output
    from sparseloc.io.tables import read_parquet

    _, meta = read_parquet(out)
    assert meta["camera"]["kind"] == "emccd" and meta["camera"]["read_noise"] == 50.0


def test_an_emccd_without_its_em_gain_is_refused(movie, tmp_path):
    """A forgotten --em-gain made every count read as EM-gain times the photons: a run of
    about an hour (minutes per frame of emitters 300 times too bright) before its check said
    so. Now every command refuses it in one sentence; --em-gain 1 describes the conventional
    output."""
    out = tmp_path / "l.parquet"
    res = run("localize", movie, "-o", out, *LOCALIZE, "--camera", "emccd")
    refused(res, "--camera emccd needs --em-gain", "1 for the camera's conventional output")
    assert not out.exists()
    cfg = tmp_path / "cam.toml"
    cfg.write_text('[camera]\nkind = "emccd"\n')
    refused(run("localize", movie, "-o", out, *LOCALIZE, "--config", cfg), "--em-gain")
    res = run("simulate", "-o", tmp_path / "m.tif", "--psf", "dh-analytic", "--frames", 1,
              "--rows", 16, "--cols", 16, "--camera", "emccd")  # fmt: skip
    refused(res, "--em-gain")
    res = run("localize", movie, "-o", out, *LOCALIZE, "--workers", 1, "--camera", "emccd",
              "--em-gain", 1)  # fmt: skip
    assert res.exit_code == 0, res.output


def test_a_movie_that_begins_with_blank_frames_is_localized(movie, tmp_path):
    """Dropped frames (all zeros) or frames taken with the shutter closed (the offset and its
    noise) at the start of a movie say nothing about the offset: it is checked against
    frames spread over the run, with or without --frames past them; an offset above all of
    them is still refused, and a frame range that holds no frame says so."""
    adu = tifffile.imread(movie)
    rng = np.random.default_rng(0)
    dark = np.round(100.0 + rng.normal(0.0, 1.5, adu[:3].shape)).astype(adu.dtype)
    for name, head in (("zero", np.zeros_like(adu[:3])), ("dark", dark)):
        path = tmp_path / f"{name}.tif"
        tifffile.imwrite(path, np.concatenate([head, adu]))
        for frames in ("0:11", "3:11"):
            out = tmp_path / f"{name}_{frames[0]}.parquet"
            res = run("localize", path, "-o", out, *LOCALIZE, "--workers", 1, "--offset", 100,
                      "--frames", frames)  # fmt: skip
            assert res.exit_code == 0, res.output
            assert out.exists()
    out = tmp_path / "high.parquet"
    res = run("localize", tmp_path / "zero.tif", "-o", out, *LOCALIZE, "--offset", 60000)
    refused(res, "--offset", "spread over the run")
    refused(run("localize", movie, "-o", out, *LOCALIZE, "--frames", "5:3"), "holds no frame")
    assert not out.exists()


def test_simulate_reads_the_camera_section(tmp_path):
    cfg = tmp_path / "cam.toml"
    cfg.write_text("[camera]\noffset = 300.0\ngain = 0.5\n")
    out = tmp_path / "m.tif"
    res = run("simulate", "-o", out, "--psf", "dh-analytic", "--frames", 1, "--rows", 16,
              "--cols", 16, "--config", cfg)  # fmt: skip
    assert res.exit_code == 0, res.output
    assert np.median(tifffile.imread(out)) >= 300  # the section's offset, not the default


def test_calibrate_converts_a_bead_stack_with_the_cameras_maps(tmp_path):
    """A hidden-data trial: an sCMOS bead stack whose offset varies from pixel to pixel
    (15 ADU) could not be calibrated with its maps (refused), and without them the model
    error rose from 4 % to 19 %. The maps convert the stack as they convert a movie."""
    from sparseloc.camera import Camera
    from sparseloc.io.calibration import read_calibration_info
    from sparseloc.io.tiff import write_tiff

    rng = np.random.default_rng(3)
    off = 400.0 + 15.0 * rng.standard_normal((64, 64))
    gain = 0.5 * (1.0 + 0.1 * rng.standard_normal((64, 64)))
    var = np.full((64, 64), 4.0)
    cam = Camera(kind="scmos", offset_map=off, gain_map=gain, variance_map=var)
    tif = write_tiff(tmp_path / "beads.tif", _bead_stack(cam), pixel_size=100.0)
    maps = []
    for name, a in (("off", off), ("gain", gain), ("var", var)):
        np.save(tmp_path / f"{name}.npy", a)
        maps.append(tmp_path / f"{name}.npy")
    common = ("--pixel-size", 100, "--z-step", 50, "--camera", "scmos", "--z0-slice", 12)
    res = run("calibrate", tif, *common, "--offset-map", maps[0], "--gain-map", maps[1],
              "--variance-map", maps[2], "-o", tmp_path / "maps.h5")  # fmt: skip
    assert res.exit_code == 0, res.output
    res = run("calibrate", tif, *common, "--offset", 400, "--gain", 0.5, "--read-noise", 1,
              "-o", tmp_path / "flat.h5")  # fmt: skip
    assert res.exit_code == 0, res.output
    with_maps = read_calibration_info(tmp_path / "maps.h5")["params"]["model_error"]
    without = read_calibration_info(tmp_path / "flat.h5")["params"]["model_error"]
    assert with_maps < 0.5 * without
    # the stack's frames must match the maps
    np.save(tmp_path / "small.npy", off[:32, :32])
    res = run("calibrate", tif, *common, "--offset-map", tmp_path / "small.npy",
              "-o", tmp_path / "bad.h5")  # fmt: skip
    refused(res, "32x32", "64x64")
    assert not (tmp_path / "bad.h5").exists()


# -- item 9: the camera and the optics from the command line -----------------------------------


def _scmos_movie(tmp_path, offset=100.0, gain=0.5, read_noise=2.0):
    """ADU frames of a smooth field from 5 to 400 photons per pixel on an sCMOS camera."""
    from sparseloc.camera import Camera, apply_noise

    cam = Camera(kind="scmos", offset=offset, gain=gain, read_noise=read_noise)
    rows, cols = np.mgrid[0:128, 0:128]
    mu = 5.0 + 395.0 * (0.5 + 0.5 * np.sin(cols / 15.0) * np.cos(rows / 21.0))
    adu = apply_noise(np.broadcast_to(mu, (20, 128, 128)), cam, np.random.default_rng(1))
    path = tmp_path / "field.tif"
    tifffile.imwrite(path, adu)
    return path, adu


def _number(text: str, name: str) -> float:
    m = re.search(rf"{name}\D*?(-?\d+(?:\.\d+)?)", text)
    assert m, text
    return float(m.group(1))


def test_camera_command_estimates_gain_and_read_noise(tmp_path):
    path, _ = _scmos_movie(tmp_path)
    res = run("camera", path, "--offset", 100)
    assert res.exit_code == 0, res.output
    assert _number(res.output, "gain") == pytest.approx(0.5, rel=0.1)
    assert _number(res.output, "read noise") == pytest.approx(2.0, rel=0.3)
    res = run("camera", path)  # offset estimated too: a bound, low by read var / slope
    assert res.exit_code == 0, res.output
    assert _number(res.output, "offset") == pytest.approx(100.0 - 4.0**2 / 2.0, abs=5.0)
    assert "frame-to-frame differences" in res.output and "caution" not in res.output
    assert _number(res.output, "gain") == pytest.approx(0.5, rel=0.1)
    refused(run("camera", tmp_path / "none.tif"), "does not exist")


def test_camera_frames_take_localizes_range_or_a_count(tmp_path):
    """The fourth walk-through: --frames was a count here and START:STOP in localize."""
    path, _ = _scmos_movie(tmp_path)
    for frames, n in (("5:15", 10), ("10", 10), (":4", 4), ("500", 20)):
        res = run("camera", path, "--offset", 100, "--frames", frames)
        assert res.exit_code == 0, res.output
        assert f"differences of {n} frame(s)" in res.output, res.output
    refused(run("camera", path, "--frames", "5:5"), "holds no frame")
    refused(run("camera", path, "--frames", "0:50"), "goes past the movie's 20 frames")
    refused(run("camera", path, "--frames", "abc"), "START:STOP or a number")


def test_camera_on_blinking_emitters_says_its_gain_is_not_to_be_trusted(tmp_path):
    """Single-molecule frames change from frame to frame, so the line comes from single-frame
    noise, which the emitters' images inflate: the gain comes out low and the command says
    so; a steady series of the same camera (a bead stack) gives the gain."""
    movie = tmp_path / "m.tif"
    res = run("simulate", "-o", movie, "--psf", "dh-analytic", "--frames", 20, "--rows", 64,
              "--cols", 64, "--pixel-size", 100, "--density", 0.5, "--seed", 2)  # fmt: skip
    assert res.exit_code == 0, res.output
    res = run("camera", movie, "--offset", 100)
    assert res.exit_code == 0, res.output
    assert "single-frame noise" in res.output and "caution:" in res.output
    assert _number(res.output, "gain") < 0.9  # the true gain is 1 e-/ADU
    # the fourth walk-through: the flags line read as advice to copy, caution or not
    assert "localize with (GAIN from the camera's data sheet" in res.output
    # the fifth walk-through: the line to copy carried a gain 2.6x too low
    assert "--gain GAIN" in res.output
    from sparseloc.camera import estimate_camera

    steady = _scmos_movie(tmp_path, gain=1.0)[1]
    est = estimate_camera(steady, offset=100.0)
    assert est.method == "temporal" and not est.caution
    assert est.gain == pytest.approx(1.0, rel=0.05)


def _bead_stack(camera, beads: int = 4, seed: int = 0):
    """ADU frames of a simulated double-helix bead z-stack (50 nm steps, 20,000 photons)."""
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    zs = np.arange(-600.0, 601.0, 50.0)
    pos = [(1000.0 + 1600.0 * (i % 3), 1000.0 + 1600.0 * (i // 3)) for i in range(beads)]
    truth = bead_scan_truth(np.array(pos), zs, photons=20000.0)
    sim = simulate(make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(64, 64),
                   camera=camera, background=20.0, seed=seed)  # fmt: skip
    return sim.movie


@pytest.mark.parametrize(
    ("kind", "gain", "em_gain", "rel"),
    [("scmos", 1.0, 1.0, 0.06), ("scmos", 2.0, 1.0, 0.06), ("emccd", 50.0, 300.0, 0.06)],
)
def test_camera_gain_from_a_bead_stack(kind, gain, em_gain, rel):
    """Item 9: a bead z-stack's light changes from frame to frame; differences of higher order
    cancel that change, and the gain comes out right with its standard error."""
    import sparseloc.camera as camera_module
    from sparseloc.camera import Camera, estimate_camera

    cam = Camera(kind=kind, offset=200.0, gain=gain, em_gain=em_gain, read_noise=1.5)
    est = estimate_camera(_bead_stack(cam), kind=kind, em_gain=em_gain)
    assert est.method == "temporal"
    # an EMCCD's estimate says that its skewed noise biases it
    assert est.caution == ("" if kind == "scmos" else camera_module.EMCCD_CAUTION)
    assert est.gain == pytest.approx(gain, rel=rel)
    assert 0 < est.gain_error < 0.03 * gain
    assert est.offset == pytest.approx(200.0, abs=15.0)


def test_the_camera_command_asks_about_an_emccd_unless_the_camera_is_given(tmp_path):
    """A hidden-data trial followed the camera command's flags for an EMCCD bead stack and
    got half the photons: the line of an EMCCD holds its excess noise, which the command
    cannot tell from the gain unless told the camera."""
    from sparseloc.camera import Camera
    from sparseloc.io.tiff import write_tiff

    cam = Camera(kind="emccd", offset=200.0, gain=50.0, em_gain=300.0, read_noise=1.5)
    tif = write_tiff(tmp_path / "beads.tif", _bead_stack(cam), pixel_size=100.0)
    res = run("camera", tif)
    assert res.exit_code == 0, res.output
    assert "--camera emccd --em-gain G" in res.output
    res = run("camera", tif, "--camera", "emccd", "--em-gain", 300)
    assert res.exit_code == 0, res.output
    assert "an EMCCD?" not in res.output
    # the line's slope is uncertain by a few per cent beyond its standard errors, which moves
    # its intercept, far below the data, by tens of ADU: no "at least", no offset to copy
    assert "offset at least" not in res.output and "not a bound" in res.output
    assert "--offset DARK_LEVEL" in res.output


@pytest.mark.parametrize("kind", ["scmos", "emccd"])
def test_the_transfer_line_is_not_biased_by_binning_on_its_own_noise(kind):
    """The second walk-through: EMCCD gains 7-17 % low with the offset's bound above the true
    offset, and sCMOS read noise 20-30 % high with the offset given, over several bead
    stacks. Each run's bin now comes from the frames around it, so its noise does not select
    the bin; the means over four stacks lie near the truth (ADU rounding adds 1/12 ADU^2 to
    the read variance: 1.61 e- at 2 e-/ADU)."""
    from sparseloc.camera import Camera, estimate_camera

    gain, em_gain = (2.0, 1.0) if kind == "scmos" else (50.0, 300.0)
    gains, bounds, noises = [], [], []
    for seed in range(4):
        cam = Camera(kind=kind, offset=200.0, gain=gain, em_gain=em_gain, read_noise=1.5)
        movie = _bead_stack(cam, seed=seed)
        est = estimate_camera(movie, kind=kind, em_gain=em_gain)
        gains.append(est.gain)
        bounds.append(est.offset)
        noises.append(estimate_camera(movie, kind=kind, em_gain=em_gain, offset=200.0).read_noise)
    assert np.mean(gains) == pytest.approx(gain, rel=0.03)
    assert np.mean(bounds) < 205.0  # a lower bound of the offset, its noise aside
    if kind == "scmos":
        assert np.mean(noises) < 1.75


def test_an_emccd_read_noise_the_line_cannot_resolve_is_not_printed_as_measured(tmp_path):
    """Behind an EM gain of 300, 1.5 e- of read noise is far below what the line resolves;
    the command says so and does not pass a read noise on to localize. An sCMOS stack's read
    noise is measured, with its bound."""
    from sparseloc.camera import Camera
    from sparseloc.io.tiff import write_tiff

    for kind, gain, em_gain in (("emccd", 50.0, 300.0), ("scmos", 1.0, 1.0)):
        cam = Camera(kind=kind, offset=200.0, gain=gain, em_gain=em_gain, read_noise=1.5)
        tif = write_tiff(tmp_path / f"{kind}.tif", _bead_stack(cam, seed=1), pixel_size=100.0)
        args = ["camera", tif, "--offset", 200, "--camera", kind, "--frames", 25]
        res = run(*args, *(["--em-gain", em_gain] if kind == "emccd" else []))
        assert res.exit_code == 0, res.output
        if kind == "emccd":
            assert "read noise not resolved by the line" in res.output
            assert "--read-noise" not in res.output.split("localize with:")[1]
        else:
            assert _number(res.output, "read noise") == pytest.approx(1.53, rel=0.2)
            assert "at two standard errors" in res.output
            assert "--read-noise" in res.output.split("localize with:")[1]


def test_camera_gain_from_flat_frames_at_several_levels_but_not_one():
    """Item 9: flat frames at three light levels (the frames where the level changes left
    out) give the gain; flat frames at one level hold no line, and the estimate says so."""
    from sparseloc.camera import Camera, apply_noise, estimate_camera

    rng = np.random.default_rng(0)
    cam = Camera(kind="scmos", offset=200.0, gain=2.0, read_noise=1.5)
    flat = rng.uniform(0.95, 1.05, (1, 64, 64))  # the illumination's non-uniformity
    levels = np.concatenate([np.full((7, 64, 64), v) for v in (50.0, 100.0, 400.0)]) * flat
    est = estimate_camera(apply_noise(levels, cam, rng))
    assert est.method == "temporal" and not est.caution
    assert est.gain == pytest.approx(2.0, rel=0.03)
    one = estimate_camera(apply_noise(np.full((20, 64, 64), 100.0) * flat, cam, rng))
    assert "one brightness level" in one.caution


def test_photon_transfer_lives_in_the_library_and_the_benchmark_uses_it(tmp_path):
    from sparseloc.camera import estimate_camera, photon_transfer

    _, adu = _scmos_movie(tmp_path)
    slope, _ = photon_transfer(adu)
    assert slope == pytest.approx(2.0, rel=0.1)  # ADU per photon: 1 / 0.5 e-/ADU
    est = estimate_camera(adu, offset=100.0)
    assert est.gain == pytest.approx(0.5, rel=0.1) and est.read_noise == pytest.approx(2, rel=0.3)
    bench = (Path(__file__).resolve().parents[1] / "benchmarks" / "real_data.py").read_text()
    assert "def photon_transfer" not in bench and "photon_transfer" in bench


class _Frames:
    """The smallest movie that :func:`sparseloc.config.build_job` accepts."""

    pixel_size = None

    def __len__(self) -> int:
        return 2

    def frames(self, start: int, stop: int) -> np.ndarray:
        return np.full((stop - start, 16, 16), 200.0)


def test_localize_builds_a_mask_model_with_the_optics_given(tmp_path):
    from sparseloc.config import build_job

    mask = tmp_path / "mask.npy"
    yy, xx = np.mgrid[-20:21, -20:21] / 20.0
    np.save(mask, np.where(np.hypot(xx, yy) <= 1, 2.0 * xx * yy + 0.5, 0.0))
    opts = {"psf": str(mask), "pixel_size": 110.0, "na": 1.3, "wavelength": 600.0}
    opts |= {"mask_radius": 18.0, "blur": 50.0}
    model = build_job(opts, _Frames()).model
    assert (model.na, model.wavelength, model.blur) == (1.3, 600.0, 50.0)
    assert model.mask.radius == 18.0
    with pytest.raises(ValueError, match="mask-radius"):
        build_job({"psf": "dh", "pixel_size": 110.0, "mask_radius": 18.0}, _Frames())
    text = _help_text("localize")
    for flag in ("--na", "--wavelength", "--mask-radius", "--blur"):
        assert flag in text


def test_localize_takes_the_optics_flags(movie, tmp_path):
    res = run("localize", movie, "-o", tmp_path / "x.parquet", *LOCALIZE, "--na", 1.3)
    refused(res, "--na")  # an analytic model has no pupil: the flag would be ignored


# -- item 16: damaged files end in one sentence ------------------------------------------------


def _damaged(data: bytes, rng: np.random.Generator, n: int) -> list[bytes]:
    """``n`` copies of ``data`` with a few random bytes changed, and some cut short."""
    out = []
    for i in range(n):
        b = bytearray(data)
        if i % 5 == 4:
            b = b[: int(rng.integers(1, len(b)))]
        else:
            for at in rng.integers(0, len(b), size=int(rng.integers(1, 4))):
                b[at] = int(rng.integers(0, 256))
        out.append(bytes(b))
    return out


@pytest.fixture(scope="module")
def calibration_file(beads, tmp_path_factory):
    tif, _, _ = beads
    out = tmp_path_factory.mktemp("cal") / "psf.h5"
    res = run("calibrate", tif, "--pixel-size", 100, "--z-step", 50, "--offset", 100, "-o", out)
    assert res.exit_code == 0, res.output
    return out


def test_damaged_calibration_files_are_refused_in_one_sentence(calibration_file, tmp_path):
    from sparseloc.psf import make_psf

    rng = np.random.default_rng(7)
    # Damage in the metadata and structure, where readers fail: the front and the back.
    data = calibration_file.read_bytes()
    head = _damaged(data[:4096], rng, 20)
    variants = [h + data[4096:] for h in head] + _damaged(data, rng, 20)
    for i, blob in enumerate(variants):
        path = tmp_path / f"bad{i}.h5"
        path.write_bytes(blob)
        try:
            make_psf(str(path))
        except ValueError as exc:
            assert path.name in str(exc), exc
    for i in range(0, len(variants), 4):
        path = tmp_path / f"bad{i}.h5"
        held(run("simulate", "-o", tmp_path / f"s{i}.tif", "--psf", path, "--frames", 1,
                 "--rows", 16, "--cols", 16))  # fmt: skip


def test_damaged_calibration_in_localize(calibration_file, movie, tmp_path):
    rng = np.random.default_rng(3)
    data = calibration_file.read_bytes()
    for i, blob in enumerate(_damaged(data[:4096], rng, 6)):
        path = tmp_path / f"bad{i}.h5"
        path.write_bytes(blob + data[4096:])
        held(run("localize", movie, "-o", tmp_path / f"l{i}.parquet", "--psf", path,
                 "--pixel-size", 100, "--workers", 1))  # fmt: skip


def _mask_files(tmp_path: Path) -> list[Path]:
    from scipy.io import savemat

    yy, xx = np.mgrid[-16:17, -16:17] / 16.0
    phase = np.where(np.hypot(xx, yy) <= 1, 3.0 * xx * yy + 0.2, 0.0)
    np.save(tmp_path / "m.npy", phase)
    savemat(tmp_path / "m.mat", {"phase": phase}, do_compression=True)
    tifffile.imwrite(tmp_path / "m.tif", phase.astype(np.float32), compression="zlib")
    return [tmp_path / "m.npy", tmp_path / "m.mat", tmp_path / "m.tif"]


def test_corrupt_masks_are_refused_in_one_sentence(tmp_path):
    from sparseloc.psf.masks import load_mask

    rng = np.random.default_rng(11)
    for good in _mask_files(tmp_path):
        for i, blob in enumerate(_damaged(good.read_bytes(), rng, 40)):
            path = tmp_path / f"bad{i}{good.suffix}"
            path.write_bytes(blob)
            try:
                load_mask(path)
            except ValueError as exc:
                assert path.name in str(exc), exc


def test_corrupt_masks_in_simulate_and_localize(movie, tmp_path):
    rng = np.random.default_rng(5)
    for good in _mask_files(tmp_path):
        for i, blob in enumerate(_damaged(good.read_bytes(), rng, 3)):
            path = tmp_path / f"bad{i}{good.suffix}"
            path.write_bytes(blob)
            held(run("simulate", "-o", tmp_path / "s.tif", "--psf", path, "--frames", 1,
                     "--rows", 16, "--cols", 16, "--overwrite"))  # fmt: skip
    # a mask whose compressed data are damaged: zlib.error inside scipy
    mat = tmp_path / "m.mat"
    blob = bytearray(mat.read_bytes())
    blob[len(blob) // 2 :] = bytes(len(blob) - len(blob) // 2)
    mat.write_bytes(bytes(blob))
    refused(run("localize", movie, "-o", tmp_path / "x.parquet", "--psf", mat,
                "--pixel-size", 160), "m.mat")  # fmt: skip


def _bad_tag(path: Path) -> Path:
    """``path`` (a TIFF) with its SamplesPerPixel tag's count damaged: tifffile logs an error
    and still reads the image."""
    with tifffile.TiffFile(path) as tif:
        at = tif.pages[0].tags[277].offset
    blob = bytearray(path.read_bytes())
    blob[at + 4] = 5
    bad = path.with_name("tag_" + path.name)
    bad.write_bytes(bytes(blob))
    return bad


def test_a_mask_or_map_tiff_tifffile_calls_damaged_is_refused_without_its_log(tmp_path, capfd):
    """Item 20: tifffile logs ``ERROR tifffile`` for a damaged tag and reads on; masks and
    camera maps are read with the movie reader's checks, refused in one sentence."""
    good = tmp_path / "phase.tif"
    tifffile.imwrite(good, np.zeros((64, 64), np.float32))
    bad = _bad_tag(good)
    res = run("simulate", "-o", tmp_path / "s.tif", "--psf", bad, "--frames", 1,
              "--rows", 16, "--cols", 16)  # fmt: skip
    refused(res, bad.name, "corrupt")
    assert "ERROR" not in capfd.readouterr().err
    gmap = tmp_path / "gain.tif"
    tifffile.imwrite(gmap, np.ones((16, 16), np.float32))
    res = run("simulate", "-o", tmp_path / "s.tif", "--camera", "scmos", "--gain-map",
              _bad_tag(gmap), "--frames", 1, "--rows", 16, "--cols", 16)  # fmt: skip
    refused(res, "tag_gain.tif")
    assert "ERROR" not in capfd.readouterr().err


# -- item 17: calibrations without negative voxels -----------------------------------------------


@pytest.fixture(scope="module")
def astig_calibration(tmp_path_factory):
    """storm-analysis's astigmatic bead scan (every third plane, four beads) calibrated."""
    if not (ASTIG / "beads_zscan.tif").is_file():
        pytest.skip("storm-analysis's astigmatic beads are not in ../shared/data")
    from sparseloc.calibrate import calibrate_beads, read_z_file
    from sparseloc.io.calibration import save_calibration

    stack = tifffile.imread(ASTIG / "beads_zscan.tif")
    z, valid = read_z_file(ASTIG / "beads_zscan_z.csv")
    every = slice(0, None, 3)
    cal = calibrate_beads(stack[every, :100, :100], 100.0, z=z[every], valid=valid[every],
                          offset=100.0)  # fmt: skip
    out = tmp_path_factory.mktemp("astig") / "astig.h5"
    save_calibration(cal, out)
    return cal, out


def test_calibration_of_astigmatic_beads_has_no_negative_voxels(astig_calibration):
    cal, _ = astig_calibration
    assert np.mean(cal.psf.stack < 0) == 0.0
    assert np.all(np.isfinite(cal.psf.stack))


def test_simulate_and_localize_with_the_astigmatic_calibration(astig_calibration, tmp_path):
    _, psf = astig_calibration
    sim = tmp_path / "m.tif"
    res = run("simulate", "-o", sim, "--psf", psf, "--frames", 3, "--rows", 64, "--cols", 64,
              "--pixel-size", 100, "--density", 0.3, "--photons-min", 50000, "--photons-max",
              50000, "--seed", 2)  # fmt: skip
    assert res.exit_code == 0, res.output
    out = tmp_path / "locs.parquet"
    res = run("localize", sim, "-o", out, "--psf", psf, "--workers", 1)
    assert res.exit_code == 0, res.output
    from sparseloc.io.tables import read_parquet

    table, _ = read_parquet(out)
    ok = table[table["flag"] == "ok"] if "flag" in table else table
    assert len(ok) > 0 and np.all(np.isfinite(ok["gof"]))


def test_rendering_clamps_a_splines_tiny_negative_values():
    from sparseloc.camera import Camera, apply_noise

    mu = np.full((1, 8, 8), 5.0)
    mu[0, 0, 0] = -1e-9  # a cubic spline's undershoot beside a clipped voxel
    adu = apply_noise(mu, Camera(), np.random.default_rng(0))
    assert adu.shape == mu.shape
    with pytest.raises(ValueError, match=">= 0"):
        apply_noise(np.full((1, 8, 8), -5.0), Camera(), np.random.default_rng(0))


# -- item 21: local runs without an open Dask cluster ----------------------------------------


def test_chunked_local_run_uses_a_process_pool_not_an_open_cluster(movie, tmp_path, monkeypatch):
    import sparseloc.distributed as dist

    def no_cluster(*args, **kwargs):
        raise AssertionError("a local run must not start a Dask cluster")

    monkeypatch.setattr(dist, "local_cluster", no_cluster)
    try:
        import distributed

        monkeypatch.setattr(distributed, "LocalCluster", no_cluster)
    except ImportError:
        pass
    out = tmp_path / "locs.parquet"
    res = run("localize", movie, "-o", out, *LOCALIZE, "--chunk-frames", 2, "--workers", 2)
    assert res.exit_code == 0, (res.output, res.exception)
    ref = tmp_path / "ref.parquet"
    res = run("localize", movie, "-o", ref, *LOCALIZE, "--workers", 1)
    assert res.exit_code == 0, res.output
    from sparseloc.io.tables import read_parquet

    a, b = read_parquet(out)[0], read_parquet(ref)[0]
    cols = ["frame", "x_nm", "y_nm", "z_nm", "photons"]
    pd.testing.assert_frame_equal(a[cols].reset_index(drop=True), b[cols].reset_index(drop=True))


def test_localize_chunked_in_processes(tmp_path):
    from sparseloc.distributed import localize_chunked
    from sparseloc.pipeline import LocalizeParams, localize
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate

    model = make_psf("dh-analytic")
    sim = simulate(model, n_frames=6, shape=(24, 24), pixel_size=100.0, density=0.4, seed=2)
    frames = sim.movie.astype(float) - sim.camera.offset
    params = LocalizeParams(pixel_size=100.0, tabulate=False)
    res = localize_chunked(frames, model, params, tmp_path / "run", chunk_frames=2,
                           scheduler="processes", workers=2)  # fmt: skip
    ref = localize(frames, model, params).table
    cols = ["frame", "x_nm", "y_nm", "z_nm", "photons"]
    pd.testing.assert_frame_equal(
        res.table[cols].reset_index(drop=True), ref[cols].reset_index(drop=True)
    )


def test_camera_command_never_suggests_a_negative_offset(tmp_path, monkeypatch):
    # With read noise dominating, the line's offset bound can fall below zero: the command
    # says the offset is not placed and leaves it out of the suggested flags.
    import sparseloc.camera as camera_module

    path = tmp_path / "m.tif"
    rng = np.random.default_rng(0)
    tifffile.imwrite(path, rng.poisson(200.0, (6, 32, 32)).astype(np.uint16))
    fake = camera_module.CameraEstimate(-25.0, 0.6, 0.0, False, 1.7, 42.0, method="temporal")
    monkeypatch.setattr(camera_module, "estimate_camera", lambda *a, **k: fake)
    res = run("camera", path)
    assert res.exit_code == 0, res.output
    assert "offset not placed" in res.output
    assert "--offset -25" not in res.output and "--gain 0.6" in res.output


def test_an_em_gain_refusal_speaks_of_the_camera_not_of_kind(tmp_path):
    """The second walk-through: ``[camera]`` with an EM gain on an sCMOS named ``kind``, a
    word the user never wrote."""
    movie = tmp_path / "m.tif"
    assert run("simulate", "-o", movie, "--frames", 1, "--rows", 16, "--cols", 16).exit_code == 0
    cfg = tmp_path / "cam.toml"
    cfg.write_text('[camera]\ncamera = "scmos"\nem_gain = 100\n')
    for extra in (["--config", cfg], ["--camera", "scmos", "--em-gain", 100]):
        res = run("localize", movie, "-o", tmp_path / "x.parquet", "--psf", "dh",
                  "--pixel-size", 100, *extra)  # fmt: skip
        assert res.exit_code == 2, res.output
        assert "unless the camera is an emccd (this one is scmos)" in res.output
        assert "kind" not in res.output


def test_an_unreadable_mask_names_the_psf_option(tmp_path):
    """The second walk-through: a damaged TIFF given as ``--psf`` was refused without naming
    the option."""
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"not a tiff at all" * 20)
    movie = tmp_path / "m.tif"
    assert run("simulate", "-o", movie, "--frames", 1, "--rows", 16, "--cols", 16).exit_code == 0
    for args in (
        ["localize", movie, "-o", tmp_path / "x.parquet", "--psf", bad, "--pixel-size", 100],
        ["simulate", "-o", tmp_path / "s.tif", "--psf", bad],
    ):
        res = run(*args)
        assert res.exit_code == 2, res.output
        assert "--psf: cannot use the mask file: " in res.output
        assert "bad.tif' is not a TIFF file" in res.output
    assert not (tmp_path / "x.parquet").exists() and not (tmp_path / "s.tif").exists()


def test_camera_suggests_scmos_only_for_a_measured_read_noise(tmp_path):
    """The third walk-through: ``sparseloc camera beads.tif`` on a camera without read noise
    suggested ``--camera scmos``. Without --camera the suggestion follows the measurement."""
    from sparseloc.camera import Camera
    from sparseloc.io.tiff import write_tiff

    def suggestion(read_noise, *args):
        cam = Camera(kind="scmos" if read_noise else "ideal", offset=200.0, gain=1.0,
                     read_noise=read_noise)  # fmt: skip
        tif = write_tiff(tmp_path / f"b{read_noise}.tif", _bead_stack(cam, seed=2),
                         pixel_size=100.0)  # fmt: skip
        res = run("camera", tif, "--frames", 25, *args)
        assert res.exit_code == 0, res.output
        return res.output, res.output.split("localize with:")[1]

    out, flags = suggestion(0.0)  # no offset: the read noise is not measured
    assert "--camera" not in flags and "read noise not measured without --offset" in out
    out, flags = suggestion(0.0, "--offset", 200)
    assert "--camera" not in flags and "--read-noise" not in flags
    out, flags = suggestion(3.0, "--offset", 200)
    assert "--camera scmos" in flags and "--read-noise" in flags
    out, flags = suggestion(0.0, "--offset", 200, "--camera", "scmos")
    assert "--camera scmos" in flags


def test_calibrate_warns_where_the_stacks_noise_contradicts_the_gain(tmp_path):
    """The third walk-through: ``calibrate --gain 10`` for a 1 e-/ADU camera gave a model error
    of 16.3 % (7.2 % with the right gain) and no word; ``sparseloc camera`` on the same stack
    measured 0.996. The stack's own noise now checks the gain."""
    from sparseloc.camera import Camera
    from sparseloc.io.tiff import write_tiff

    cam = Camera(kind="scmos", offset=200.0, gain=1.0, read_noise=1.5)
    tif = write_tiff(tmp_path / "beads.tif", _bead_stack(cam, seed=3), pixel_size=100.0)
    for gain, warned in ((10.0, True), (1.0, False), (1.2, False)):
        out = tmp_path / f"psf{gain:g}.h5"
        res = run("calibrate", tif, "-o", out, "--pixel-size", 100, "--z-step", 50,
                  "--offset", 200, "--gain", gain)  # fmt: skip
        assert res.exit_code == 0, res.output
        assert ("the stack's noise says the camera's gain is" in res.output) is warned, res.output
        assert out.exists()


def test_calibrate_warns_where_the_stacks_noise_says_the_offset_is_missing(tmp_path):
    """The fifth walk-through: ``calibrate --offset 0`` (the offset forgotten) stored a model
    error of 0.0 % (7.2 % with the right offset) and said nothing."""
    from sparseloc.camera import Camera, offset_mismatch
    from sparseloc.io.tiff import write_tiff

    cam = Camera(kind="scmos", offset=200.0, gain=1.0, read_noise=1.5)
    stack = _bead_stack(cam, seed=4)
    tif = write_tiff(tmp_path / "beads.tif", stack, pixel_size=100.0)
    for offset, warned in ((0, True), (190, True), (200, False), (199, False)):
        out = tmp_path / f"psf{offset}.h5"
        res = run("calibrate", tif, "-o", out, "--pixel-size", 100, "--z-step", 50,
                  "--offset", offset)  # fmt: skip
        assert res.exit_code == 0, res.output
        said = "the stack's noise says the camera's offset is at least" in res.output
        assert said is warned, res.output
    # a higher offset than the camera's is not what the line can tell (it bounds from below)
    assert offset_mismatch(stack, Camera(kind="scmos", offset=210.0, gain=1.0)) == ""


def test_a_single_bead_stack_with_the_right_offset_draws_no_offset_warning():
    """A rehearsal's one astigmatic bead (this seed) read "the offset is at least 101.5 ADU,
    not the 100 given" with the right offset: a bead stack is not quite steady, and its
    line's offset is off by more than its standard error; a dark level below a pixel's
    noise at the background changes no fit."""
    from sparseloc.camera import Camera, offset_mismatch
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    planes = np.arange(-800.0, 800.1, 50.0)
    scene = bead_scan_truth(np.array([[4800.0, 4800.0]]), planes, 20000.0)
    model = make_psf("astig", z_range=(-1000, 1000))
    sim = simulate(model, scene=scene, n_frames=planes.size, shape=(96, 96), pixel_size=100.0,
                   background=10.0, seed=3)  # fmt: skip
    assert offset_mismatch(sim.movie, Camera(kind="ideal", offset=100.0, gain=1.0)) == ""
    # a forgotten offset is still named
    assert "at least" in offset_mismatch(sim.movie, Camera(kind="ideal", offset=0.0, gain=1.0))


@pytest.mark.parametrize("oversample", [10**9, 0, -3])
def test_a_calibration_with_an_absurd_oversample_is_refused(calibration_file, tmp_path, oversample):
    """Item 19: a calibration file whose spline claims an absurd oversampling is refused in
    one sentence naming the file, by the library and by the commands, rather than building
    a table of that size (MemoryError) or dividing by it."""
    from sparseloc.psf import make_psf

    path = tmp_path / "odd.h5"
    shutil.copyfile(calibration_file, path)
    with h5py.File(path, "r+") as f:
        f["spline"].attrs["oversample"] = oversample
    with pytest.raises(ValueError, match=r"odd\.h5"):
        make_psf(str(path))
    out = tmp_path / "s.tif"
    refused(run("simulate", "-o", out, "--psf", path, "--frames", 1, "--rows", 16, "--cols", 16),
            "odd.h5")  # fmt: skip
    assert not out.exists()


def test_camera_on_single_frames_calls_its_offset_no_bound(movie):
    """On single-molecule frames the line is biased (see the caution): a new user's movie of
    offset 100 gave "offset at least 105.7 ADU ... localize with --offset 105.7"."""
    res = run("camera", movie)
    assert res.exit_code == 0, res.output
    assert "single-frame noise" in res.output
    assert "offset at least" not in res.output
    assert "from single frames, not a bound" in res.output
    assert "--offset DARK_LEVEL" in res.output


def test_a_stack_of_one_bead_on_a_wide_field_gives_the_gain():
    """A z-stack of one bead on a field of background: one bin of the line spans the bead's
    dim wings to its peak, and a clip set by the bin's pooled variance cuts the peak's noise
    (a gain far too high, and calibrate warning of a wrong --gain). Each difference is
    clipped on the line at its own light."""
    from sparseloc.camera import Camera, camera_mismatch, estimate_camera
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    cam = Camera(kind="scmos", offset=100.0, gain=1.0, read_noise=1.5)
    zs = np.arange(-500.0, 501.0, 20.0)
    truth = bead_scan_truth(np.array([(6037.0, 5963.0)]), zs, photons=20000.0)
    movie = simulate(make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(120, 120),
                     camera=cam, background=10.0, seed=0).movie  # fmt: skip
    est = estimate_camera(movie, kind="scmos")
    assert est.method == "temporal"
    assert est.gain == pytest.approx(1.0, rel=0.25)
    assert camera_mismatch(movie, cam) == ""


def test_localize_names_a_movie_clipped_below_its_type_maximum(tmp_path):
    """A rehearsal's 12-bit movie in 16-bit files (261 pixel values at 4095): the fits took
    the flat peaks at face value (axial RMSE 5.7 -> 19.4 nm) and only the generic misfit
    warning spoke. localize now names the value; an unclipped movie gets no such note. The
    fits leave out pixels at the clipping level (unclipped: at the type's maximum), or at
    the level --saturation gives."""
    from sparseloc.io.tables import read_table_and_metadata
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate

    sim = simulate(make_psf("astig"), n_frames=3, shape=(48, 48), pixel_size=100.0,
                   density=0.5, photons=(20000.0, 40000.0), seed=2)  # fmt: skip
    top = int(np.percentile(sim.movie, 99.8))
    for name, movie, noted in (
        ("clip", np.minimum(sim.movie, top), True),
        ("raw", sim.movie, False),
    ):
        tif = write_tiff(tmp_path / f"{name}.tif", movie.astype(np.uint16), pixel_size=100.0)
        res = run("localize", tif, "-o", tmp_path / f"{name}.parquet", "--psf", "astig",
                  "--offset", 100, "--frames", "0:1", "--workers", 1)  # fmt: skip
        assert res.exit_code == 0, res.output
        said = f"pixel values of the movie sit at exactly {top} ADU" in res.output
        assert said is noted, res.output
        _, meta = read_table_and_metadata(tmp_path / f"{name}.parquet")
        # offset 100 ADU, gain 1 e-/ADU: the level in photons
        assert meta["params"]["saturation"] == (top if noted else 65535) - 100.0
    res = run("localize", tmp_path / "raw.tif", "-o", tmp_path / "given.parquet", "--psf", "astig",
              "--offset", 100, "--frames", "0:1", "--workers", 1,
              "--saturation", 65000)  # fmt: skip
    assert res.exit_code == 0, res.output
    meta = read_table_and_metadata(tmp_path / "given.parquet")[1]
    assert meta["params"]["saturation"] == 64900.0
    for bad, said in ((-5, "must be a positive number"), (top - 1, "lies below frame 0's")):
        res = run("localize", tmp_path / "clip.tif", "-o", tmp_path / "bad.parquet", "--psf",
                  "astig", "--offset", 100, "--saturation", bad)  # fmt: skip
        assert res.exit_code != 0 and said in res.output, res.output
        assert not (tmp_path / "bad.parquet").exists()


def test_saturated_pixels_of_an_scmos_camera_with_maps_are_found_pixel_by_pixel():
    """sCMOS gain and offset maps give each pixel its own saturation in photons; the run
    keeps one level (the largest), the frames' reader lifts each saturated pixel to it, and
    no other pixel reaches it (with the lowest level, 1006 of 1024 unsaturated pixels 300 ADU
    below the clip were taken as saturated: a review's finding)."""
    from sparseloc.camera import Camera, saturation_level
    from sparseloc.distributed import CameraFrames
    from sparseloc.pipeline import censored_pixels

    rng = np.random.default_rng(0)
    shape = (32, 32)
    cam = Camera(kind="scmos", offset=100.0, gain=0.5, read_noise=1.5,
                 offset_map=100.0 + rng.normal(0, 3, shape),
                 gain_map=0.5 + rng.normal(0, 0.02, shape))  # fmt: skip
    raw = np.full((1, *shape), 4095 - 300, dtype=np.uint16)
    hit = rng.random(shape) < 0.05
    raw[0][hit] = 4095
    level = saturation_level(4095, cam, shape)
    photons = CameraFrames(raw, cam, None, 4095.0).frames(0, 1)[0]
    assert np.array_equal(censored_pixels(photons, level), hit)
    # read without the saturation, the level found by the largest map value misses the
    # pixels whose own saturation lies lower
    plain = CameraFrames(raw, cam).frames(0, 1)[0]
    found = censored_pixels(plain, level)
    assert (0 if found is None else found.sum()) <= 1 < hit.sum()


@pytest.mark.parametrize("chunked", [False, True])
def test_the_cli_leaves_out_exactly_the_clipped_pixels_of_an_scmos_camera_with_maps(
    tmp_path, monkeypatch, chunked
):
    """The command line reads the frames through the job (its saturated pixels lifted to the
    run's level), chunked or not: each frame's censored pixels are the clipped ones, though
    the gain and offset maps give each pixel its own level in photons."""
    import tifffile

    import sparseloc.pipeline as pipeline
    from sparseloc.io.tiff import write_tiff

    rng = np.random.default_rng(1)
    shape = (40, 40)
    tifffile.imwrite(tmp_path / "off.tif", (100.0 + rng.normal(0, 3, shape)).astype(np.float32))
    tifffile.imwrite(tmp_path / "gain.tif", (0.5 + rng.normal(0, 0.02, shape)).astype(np.float32))
    raw = rng.poisson(200.0, (2, *shape)).astype(np.uint16) + 3500
    hit = rng.random(raw.shape) < 0.03
    raw[hit] = 4095
    movie = write_tiff(tmp_path / "m.tif", raw, pixel_size=100.0)
    seen = []
    real = pipeline.censored_pixels
    monkeypatch.setattr(
        pipeline, "censored_pixels", lambda f, s: seen.append(real(f, s)) or seen[-1]
    )
    extra = ["--run-dir", tmp_path / "run", "--chunk-frames", 1] if chunked else []
    res = run("localize", movie, "-o", tmp_path / "t.parquet", "--psf", "dh-analytic",
              "--camera", "scmos", "--offset-map", tmp_path / "off.tif", "--gain-map",
              tmp_path / "gain.tif", "--read-noise", 1.5, "--saturation", 4095,
              "--workers", 1, *extra)  # fmt: skip
    assert res.exit_code == 0, res.output
    assert len(seen) == 2 and all(np.array_equal(m, h) for m, h in zip(seen, hit, strict=True))
