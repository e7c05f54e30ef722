"""Issue 27, the command line and file side: no data loss (item 15), existing outputs refused
unless --overwrite and Picasso's sx/sy (item 14), one sentence instead of a traceback (item 19),
no partial outputs and resumes that notice a replaced movie (item 20)."""

from __future__ import annotations

import json
import os
import shutil

import h5py
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cli_checks import refused, run
from sparseloc.io.tables import complete_locs, write_table

CONFIG = '[localize]\npsf = "dh-analytic"\npixel_size = 160.0\nz_min = -300.0\nz_max = 300.0\n'


@pytest.fixture(scope="module")
def movie(tmp_path_factory):
    """A 2-frame 32x32 double-helix movie and a config that localizes it."""
    folder = tmp_path_factory.mktemp("movie")
    path = folder / "m.tif"
    res = run(
        "simulate", "-o", path, "--psf", "dh-analytic", "--frames", "2", "--rows", "32",
        "--cols", "32", "--pixel-size", "160", "--density", "0.15", "--photons-min", "3000",
        "--photons-max", "4000", "--z-min", "-300", "--z-max", "300", "--seed", "3",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    cfg = folder / "run.toml"
    cfg.write_text(CONFIG)
    return path, cfg


@pytest.fixture
def table(tmp_path):
    """A 3000-row Parquet table with sparseloc metadata (enough for a drift estimate)."""
    rng = np.random.default_rng(0)
    n = 3000
    t = complete_locs(
        pd.DataFrame(
            {
                "frame": rng.integers(0, 50, n),
                "x_nm": rng.uniform(100, 5000, n),
                "y_nm": rng.uniform(100, 5000, n),
                "z_nm": rng.uniform(-300, 300, n),
            }
        )
    )
    path = tmp_path / "t.parquet"
    write_table(t, path, metadata={"params": {"pixel_size": 100.0}, "shape": [64, 64]})
    return path


def _parquet_with_raw_metadata(df, path, raw: bytes):
    arrow = pa.Table.from_pandas(df, preserve_index=False)
    pq.write_table(arrow.replace_schema_metadata({b"sparseloc": raw}), path)
    return path


# -- item 15: data loss --------------------------------------------------------------------


def test_run_dir_without_a_manifest_is_refused_and_its_parts_kept(movie, tmp_path):
    path, cfg = movie
    run_dir = tmp_path / "other"
    run_dir.mkdir()
    theirs = run_dir / "part-000000000-000000002.parquet"
    theirs.write_bytes(b"someone else's results")
    for extra in ([], ["--overwrite"]):
        res = run(
            "localize", path, "-o", tmp_path / "l.parquet", "--config", cfg, "--run-dir",
            run_dir, *extra,
        )  # fmt: skip
        refused(res, "no sparseloc run manifest")
        assert theirs.read_bytes() == b"someone else's results"
    assert not (tmp_path / "l.parquet").exists()


@pytest.mark.parametrize("line", ['overwrite = "false"', 'refine = "false"'])
def test_toml_text_for_a_flag_is_refused(movie, tmp_path, line):
    path, _ = movie
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG + line + "\n")
    res = run("localize", path, "-o", tmp_path / "l.parquet", "--config", cfg)
    refused(res, "must be true or false")
    assert not (tmp_path / "l.parquet").exists()


def test_localize_output_equal_to_the_movie_is_refused(movie, tmp_path):
    path, cfg = movie
    copy = tmp_path / "m.tif"
    shutil.copy(path, copy)
    before = copy.read_bytes()
    res = run("localize", copy, "-o", copy, "--format", "parquet", "--overwrite", "--config", cfg)
    refused(res, "is the input")
    assert copy.read_bytes() == before


@pytest.mark.parametrize("command", ["filter", "drift"])
def test_table_output_equal_to_the_input_is_refused(table, tmp_path, command):
    before = table.read_bytes()
    extra = ["--force"] if command == "drift" else []
    refused(run(command, table, "-o", table, *extra), "is the input")
    link = tmp_path / "link.parquet"
    link.symlink_to(table)  # the same file by another name, refused even with --overwrite
    refused(run(command, table, "-o", link, "--overwrite", *extra), "is the input")
    assert table.read_bytes() == before


def test_calibrate_output_or_figure_equal_to_the_stack_is_refused(tmp_path):
    from sparseloc.io.tiff import write_tiff
    from sparseloc.psf import make_psf
    from sparseloc.simulate import bead_scan_truth, simulate

    zs = np.arange(-500.0, 501.0, 50.0)
    truth = bead_scan_truth(np.array([[1400.0, 2400.0], [3400.0, 2400.0]]), zs, 20000.0)
    sim = simulate(make_psf("dh-analytic"), scene=truth, n_frames=zs.size, shape=(48, 48))
    tif = write_tiff(tmp_path / "beads.tif", sim.movie, pixel_size=100.0)
    stack = tmp_path / "beads.h5"  # a TIFF by content: the suffix does not protect it
    shutil.copy(tif, stack)
    before = tif.read_bytes()
    args = ["--pixel-size", 100, "--z-step", 50, "--offset", 100]
    refused(run("calibrate", stack, *args, "-o", stack), "is the input")
    refused(run("calibrate", tif, *args, "-o", tmp_path / "c.h5", "--figure", tif), "input")
    assert stack.read_bytes() == before and tif.read_bytes() == before
    assert not (tmp_path / "c.h5").exists()


def test_picasso_output_keeps_an_unrelated_yaml(table, tmp_path):
    from sparseloc.io.tables import read_table

    foreign = tmp_path / "out.yaml"
    foreign.write_text("somebody: else\n")
    res = run("filter", table, "-o", tmp_path / "out.hdf5")
    refused(res, "out.yaml", "exists")
    res = run("filter", table, "-o", tmp_path / "out.hdf5", "--overwrite")
    refused(res, "out.yaml")  # --overwrite replaces the table's own files, not others'
    assert foreign.read_text() == "somebody: else\n"
    assert not (tmp_path / "out.hdf5").exists()
    with pytest.raises(ValueError, match="without the table"):
        write_table(
            read_table(table), tmp_path / "out.hdf5", pixel_size=100.0, shape=(64, 64),
            n_frames=50,
        )  # fmt: skip
    assert foreign.read_text() == "somebody: else\n"


# -- item 14: Picasso sx/sy, existing outputs ----------------------------------------------


def test_picasso_export_has_the_psf_width(movie, tmp_path):
    path, cfg = movie
    out = tmp_path / "l.hdf5"
    res = run("localize", path, "-o", out, "--config", cfg)
    assert res.exit_code == 0, res.output
    with h5py.File(out) as fh:
        locs = fh["locs"][()]
    assert {"sx", "sy"} <= set(locs.dtype.names) and len(locs)
    assert list(locs.dtype.names[:7]) == ["frame", "x", "y", "z", "photons", "sx", "sy"]
    # the analytic double helix at 160 nm pixels: lobes about 1-3 px apart
    assert np.all((locs["sx"] > 0.5) & (locs["sx"] < 4)) and np.all(np.isfinite(locs["sy"]))
    # the width table travels in the Parquet metadata to later Picasso exports
    pq_out = tmp_path / "l.parquet"
    assert run("localize", path, "-o", pq_out, "--config", cfg).exit_code == 0
    res = run("filter", pq_out, "-o", tmp_path / "f.hdf5", "--all-flags")
    assert res.exit_code == 0, res.output
    with h5py.File(tmp_path / "f.hdf5") as fh:
        again = fh["locs"][()]
    assert np.allclose(np.sort(again["sx"]), np.sort(locs["sx"]))


def test_psf_width_of_a_gaussian_model_is_its_sigma():
    from sparseloc.io.picasso import psf_width_table
    from sparseloc.psf import make_psf

    model = make_psf("astig-gauss")
    t = psf_width_table(model, 100.0, n_planes=5)  # z -600, -300, 0, 300, 600
    z = np.asarray(t["z_nm"])
    sigma_x = model.sigma0 * np.sqrt(1 + ((z - model.c) / model.d) ** 2)
    sigma_y = model.sigma0 * np.sqrt(1 + ((z + model.c) / model.d) ** 2)
    narrow = (sigma_x < 200) & (sigma_y < 200)  # wider ones overflow the 15 px window
    assert np.allclose(np.asarray(t["sx_nm"])[narrow], sigma_x[narrow], rtol=0.03)
    assert np.allclose(np.asarray(t["sy_nm"])[narrow], sigma_y[narrow], rtol=0.03)


def _existing(tmp_path, name):
    p = tmp_path / name
    p.write_text("keep")
    return p


@pytest.mark.parametrize(
    ("make_args", "name"),
    [
        (lambda t, tab, m, c: ["simulate", "-o", t / "x.tif", "--frames", "1"], "x.tif"),
        (lambda t, tab, m, c: ["simulate", "-o", t / "x.tif", "--frames", "1"], "x_truth.csv"),
        (lambda t, tab, m, c: ["localize", m, "-o", t / "x.csv", "--config", c], "x.csv"),
        (lambda t, tab, m, c: ["localize", m, "-o", t / "x.h5", "--config", c], "x.yaml"),
        (
            lambda t, tab, m, c: ["calibrate", m, "--pixel-size", 160, "--z-step", 50, "-o",
                                  t / "x.h5"],
            "x.h5",
        ),
        (
            lambda t, tab, m, c: ["calibrate", m, "--pixel-size", 160, "--z-step", 50, "-o",
                                  t / "x.h5"],
            "x.png",
        ),
        (lambda t, tab, m, c: ["evaluate", tab, m, "--json", t / "x.json"], "x.json"),
        (lambda t, tab, m, c: ["render", tab, "-o", t / "x.png"], "x.png"),
        (lambda t, tab, m, c: ["render", tab, "-o", t / "y.png", "--frc", t / "x.png"], "x.png"),
        (lambda t, tab, m, c: ["drift", tab, "-o", t / "x.parquet", "--force"], "x.parquet"),
        (lambda t, tab, m, c: ["drift", tab, "-o", t / "y.csv", "--plot", t / "x.png"], "x.png"),
        (lambda t, tab, m, c: ["filter", tab, "-o", t / "x.csv"], "x.csv"),
        (lambda t, tab, m, c: ["report", tab, "-o", t / "x.html"], "x.html"),
    ],
    ids=["simulate", "simulate-truth", "localize", "localize-yaml", "calibrate",
         "calibrate-figure", "evaluate-json", "render", "render-frc", "drift", "drift-plot",
         "filter", "report"],
)  # fmt: skip
def test_existing_outputs_are_refused_unless_overwrite(movie, table, tmp_path, make_args, name):
    path, cfg = movie
    kept = _existing(tmp_path, name)
    res = run(*make_args(tmp_path, table, path, cfg))
    refused(res, name, "exists", "--overwrite")
    assert kept.read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["t.parquet", name])


def test_overwrite_replaces_an_output(table, tmp_path):
    out = _existing(tmp_path, "x.csv")
    res = run("filter", table, "-o", out, "--overwrite")
    assert res.exit_code == 0, res.output
    assert out.read_text() != "keep"


def test_demo_refuses_a_folder_of_an_earlier_demo(tmp_path):
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "locs.parquet").write_text("keep")
    refused(run("demo", "-o", folder, "--frames", "2"), "earlier demo", "--overwrite")
    assert (folder / "locs.parquet").read_text() == "keep"


# -- item 19: one sentence instead of a traceback ------------------------------------------


@pytest.mark.parametrize(
    ("line", "words"),
    [
        ('offset = "100"', ["offset", "a number"]),
        ("workers = 1.5", ["workers", "a whole number"]),
        ("workers = 0", ["workers must be >= 1"]),
        ("workers = 100000000000000000", ["workers", "too large"]),
    ],
)
def test_wrongly_typed_toml_values(movie, tmp_path, line, words):
    path, _ = movie
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG + line + "\n")
    refused(run("localize", path, "-o", tmp_path / "l.parquet", "--config", cfg), *words)
    assert not (tmp_path / "l.parquet").exists()


def test_a_localize_entry_that_is_not_a_table(movie, tmp_path):
    path, _ = movie
    cfg = tmp_path / "c.toml"
    cfg.write_text("localize = 3\n")
    refused(run("localize", path, "-o", tmp_path / "l.parquet", "--config", cfg), "a table")


@pytest.mark.parametrize(
    ("raw", "words"),
    [
        (b"[1, 2]", ["not an object"]),
        (b'{"params": {"pixel_size": "abc"}, "shape": [64, 64]}', ["pixel_size"]),
        (b'{"params": {"pixel_size": "100"}, "shape": [64, 64]}', ["pixel_size"]),
        (b'{"shape": "64x64"}', ["shape"]),
        (b"{not json", ["not JSON"]),
    ],
)
@pytest.mark.parametrize("command", ["filter", "drift", "report"])
def test_parquet_metadata_of_the_wrong_kind(table, tmp_path, raw, words, command):
    from sparseloc.io.tables import read_table

    bad = _parquet_with_raw_metadata(read_table(table), tmp_path / "bad.parquet", raw)
    out = tmp_path / ("o.html" if command == "report" else "o.hdf5")
    extra = ["--force"] if command == "drift" else []
    refused(run(command, bad, "-o", out, *extra), "bad.parquet", *words)
    assert not out.exists()


def test_a_manifest_holding_a_list(movie, tmp_path):
    path, cfg = movie
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "manifest.json").write_text("[1, 2]")
    res = run(
        "localize", path, "-o", tmp_path / "l.parquet", "--config", cfg, "--run-dir", run_dir,
        "--overwrite",
    )  # fmt: skip
    refused(res, "not a sparseloc run manifest")
    assert json.loads((run_dir / "manifest.json").read_text()) == [1, 2]


def test_evaluate_json_into_a_folder_it_cannot_write(table, tmp_path, monkeypatch):
    import tempfile

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    # A read-only folder, as seen by a user without root (the tests may run as root).
    truth = tmp_path / "truth.csv"
    pd.read_parquet(table)[["frame", "x_nm", "y_nm", "z_nm"]].assign(photons=1000.0).to_csv(
        truth, index=False
    )
    monkeypatch.setattr(tempfile, "mkstemp", denied)
    res = run("evaluate", table, truth, "--json", tmp_path / "e.json")
    refused(res, "cannot write", "e.json", "Permission denied")


def test_demo_into_an_existing_file(tmp_path):
    f = _existing(tmp_path, "demo")
    refused(run("demo", "-o", f, "--frames", "2"), "is a file")
    assert f.read_text() == "keep"


# -- item 20: no partial outputs, resumes that notice a replaced movie ---------------------


def test_a_failed_truth_write_leaves_no_movie(tmp_path, monkeypatch):
    import sparseloc.io.truth
    from sparseloc.psf import make_psf
    from sparseloc.simulate import simulate, write_simulation

    sim = simulate(make_psf("dh-analytic"), n_frames=1, shape=(16, 16), pixel_size=100.0)

    def broken(path, df):
        raise OSError("disk full")

    monkeypatch.setattr(sparseloc.io.truth, "write_truth_csv", broken)
    with pytest.raises(OSError, match="disk full"):
        write_simulation(sim, tmp_path / "m.tif")
    assert list(tmp_path.iterdir()) == []


def test_a_failed_demo_leaves_no_folder(tmp_path, monkeypatch):
    import sparseloc.demo

    def broken(*args, **kwargs):
        raise ValueError("the solver failed")

    monkeypatch.setattr(sparseloc.demo, "_localize", broken)
    with pytest.raises(ValueError, match="the solver failed"):
        sparseloc.demo.run_demo(tmp_path / "d", n_frames=2)
    assert list(tmp_path.iterdir()) == []


def _same_size_and_time(src, dest):
    """Replace ``dest`` by ``src``'s bytes keeping ``dest``'s size and times (as ``cp -p``
    of a movie of the same size would)."""
    st = os.stat(dest)
    data = src.read_bytes()
    assert len(data) == st.st_size
    dest.write_bytes(data)
    os.utime(dest, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_movie_identity_sees_the_content(tmp_path):
    from sparseloc.distributed import CameraFrames
    from sparseloc.io.movie import Movie
    from sparseloc.io.tiff import write_tiff

    rng = np.random.default_rng(0)
    a = write_tiff(tmp_path / "a.tif", rng.integers(0, 500, (4, 16, 16)), pixel_size=100.0)
    b = write_tiff(tmp_path / "b.tif", rng.integers(0, 500, (4, 16, 16)), pixel_size=100.0)
    with Movie.open(str(a)) as mov:
        before = CameraFrames(mov).identity()
    _same_size_and_time(b, a)
    with Movie.open(str(a)) as mov:
        after = CameraFrames(mov).identity()
    assert before != after


def test_a_resume_refuses_a_replaced_movie(tmp_path):
    args = ["--psf", "dh-analytic", "--frames", "4", "--rows", "24", "--cols", "24"]
    args += ["--pixel-size", "160", "--density", "0.1", "--z-min", "-300", "--z-max", "300"]
    m = tmp_path / "m.tif"
    assert run("simulate", "-o", m, *args, "--seed", "1").exit_code == 0
    assert run("simulate", "-o", tmp_path / "n.tif", *args, "--seed", "2").exit_code == 0
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG + "chunk_frames = 2\n")
    out = tmp_path / "l.parquet"
    run_dir = tmp_path / "run"
    res = run("localize", m, "-o", out, "--config", cfg, "--run-dir", run_dir)
    assert res.exit_code == 0, res.output
    out.unlink()
    (run_dir / "part-000000002-000000004.parquet").unlink()  # as if killed before the end
    _same_size_and_time(tmp_path / "n.tif", m)
    res = run("localize", m, "-o", out, "--config", cfg, "--run-dir", run_dir)
    refused(res, "different analysis", "data")
    assert not out.exists()


def test_picasso_tables_filter_back_to_picasso(table, tmp_path):
    """A new user's `filter h2.hdf5 -o h2f.hdf5 --merge` (a table localize wrote as Picasso
    HDF5) did the work, then refused the output for want of a pixel size the sidecar held."""
    import yaml

    first = tmp_path / "a.hdf5"
    assert run("filter", table, "-o", first).exit_code == 0
    again = run("filter", first, "-o", tmp_path / "b.hdf5", "--merge")
    assert again.exit_code == 0, again.output
    assert (tmp_path / "b.hdf5").is_file()
    # another program's Picasso table: its image description gives the pixel size and shape
    docs = list(yaml.safe_load_all(first.with_suffix(".yaml").read_text()))
    other = tmp_path / "other.hdf5"
    shutil.copyfile(first, other)
    other.with_suffix(".yaml").write_text(yaml.safe_dump(docs[0]))
    assert run("filter", other, "-o", tmp_path / "c.hdf5").exit_code == 0
    # a table without them is refused before the work, not after it
    csv = tmp_path / "t.csv"
    pd.read_parquet(table)[["frame", "x_nm", "y_nm", "z_nm"]].to_csv(csv, index=False)
    res = run("filter", csv, "-o", tmp_path / "d.hdf5")
    refused(res, "pixel size and frame shape")
    assert "kept" not in res.output and not (tmp_path / "d.hdf5").exists()


def test_a_calibration_given_as_the_movie_is_named_as_swapped(movie, tmp_path):
    """`localize PSF.h5 ... --psf movie.tif` said only that PSF.h5 is not a TIFF file."""
    path, _ = movie
    cal = tmp_path / "PSF.h5"
    with h5py.File(cal, "w") as f:
        f["x"] = np.zeros(3)
    out = tmp_path / "l.parquet"
    res = run("localize", cal, "-o", out, "--psf", path, "--pixel-size", "160")
    refused(res, "PSF.h5", "HDF5 file", "the calibration after --psf")
    assert not out.exists()
    table = tmp_path / "t.parquet"
    write_table(
        complete_locs(pd.DataFrame({"frame": [0], "x_nm": [500.0], "y_nm": [500.0]})), table
    )
    res = run("overlay", cal, table, "-o", tmp_path / "o.png", "--pixel-size", "160")
    refused(res, "PSF.h5", "HDF5 file", "the movie goes first")


def test_a_movie_given_as_the_mask_and_evaluates_mistakes_are_refused(movie, tmp_path):
    """A new user's trial: a camera movie given as --psf was read as a phase mask (its counts as
    radians) and the run sat at 0 % for minutes; `evaluate --frames` past both the table and
    the truth printed NaN scores with exit 0; the truth given first was "not a recognised
    localization table", with no word of the order."""
    import tifffile

    path, cfg = movie
    frame = tmp_path / "frame.tif"  # one camera frame: a 2-D image, as a mask is
    tifffile.imwrite(frame, tifffile.imread(path)[0])
    out = tmp_path / "l.parquet"
    res = run("localize", frame, "-o", out, "--psf", frame, "--pixel-size", "160")
    refused(res, "frame.tif", "whole numbers", "not a mask")
    assert not out.exists()
    table = tmp_path / "t.parquet"
    assert run("localize", path, "-o", table, "--config", cfg).exit_code == 0
    truth = path.with_name("m_truth.csv")
    refused(run("evaluate", table, truth, "--frames", "3:9"), "--frames 3:9", "(0:2)")
    assert run("evaluate", table, truth, "--frames", "1:9").exit_code == 0
    # storm-analysis's truth (pixels, frame_0based) given first
    t = pd.read_csv(truth)
    sa = tmp_path / "gt.csv"
    pd.DataFrame(
        {"frame_0based": t["frame"], "x_px": t["x_nm"] / 160.0 - 0.5,
         "y_px": t["y_nm"] / 160.0 - 0.5, "z_um": t["z_nm"] / 1e3, "photons_sum": t["photons"]}
    ).to_csv(sa, index=False)  # fmt: skip
    refused(run("evaluate", sa, table), "gt.csv", "ground truth", "the table goes first")
