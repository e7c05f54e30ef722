"""The napari reader works without napari: layer tuples from every table format."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sparseloc.io.tables import complete_locs, write_table
from sparseloc.napari_reader import napari_get_reader, read_points


@pytest.fixture
def table():
    rng = np.random.default_rng(0)
    n = 50
    return complete_locs(
        pd.DataFrame(
            {
                "frame": np.repeat(np.arange(5), 10),
                "x_nm": rng.uniform(0, 5000, n),
                "y_nm": rng.uniform(0, 4000, n),
                "z_nm": rng.uniform(-500, 500, n),
                "photons": rng.uniform(1000, 3000, n),
                "sigma_x_nm": np.full(n, 12.0),
                "sigma_y_nm": np.full(n, 14.0),
                "sigma_z_nm": np.full(n, 30.0),
            }
        )
    )


@pytest.mark.parametrize("suffix", [".parquet", ".csv", ".hdf5"])
def test_every_format_opens_as_a_3d_points_layer(tmp_path, table, suffix):
    path = tmp_path / f"locs{suffix}"
    kwargs = {"metadata": {}} if suffix == ".parquet" else {}
    if suffix == ".hdf5":
        kwargs = {"pixel_size": 100.0, "shape": (40, 50), "n_frames": 5}
    write_table(table, path, **kwargs)
    reader = napari_get_reader(str(path))
    assert reader is read_points
    [(data, kw, kind)] = reader(str(path))
    assert kind == "points" and kw["ndim"] == 3
    assert data.shape == (len(table), 3)
    order = np.lexsort((data[:, 2], data[:, 1]))
    ref = table.sort_values(["y_nm", "x_nm"])
    # napari's axis order is (z, y, x), in nm
    np.testing.assert_allclose(data[order, 2], ref.x_nm, atol=0.01)
    np.testing.assert_allclose(data[order, 1], ref.y_nm, atol=0.01)
    np.testing.assert_allclose(data[order, 0], ref.z_nm, atol=0.01)
    assert kw["face_color"] == "z_nm" and kw["face_colormap"] == "turbo"
    assert len(kw["features"]["z_nm"]) == len(table)
    # points two uncertainties across: rms of 12 and 14 nm
    assert kw["size"] == pytest.approx(2 * np.sqrt((12.0**2 + 14.0**2) / 2), rel=0.01)


def test_other_files_are_not_claimed(tmp_path):
    assert napari_get_reader(str(tmp_path / "movie.tif")) is None
    assert napari_get_reader([str(tmp_path / "a.parquet"), str(tmp_path / "b.tif")]) is None
    assert napari_get_reader([str(tmp_path / "a.parquet"), str(tmp_path / "b.csv")]) is read_points


def test_a_csv_that_is_not_a_table_is_a_clear_error(tmp_path):
    bad = tmp_path / "notes.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError):
        read_points(str(bad))


def test_the_manifest_points_at_the_reader():
    import sparseloc

    manifest = Path(sparseloc.__file__).with_name("napari.yaml")
    spec = yaml.safe_load(manifest.read_text())
    assert spec["name"] == "sparseloc"
    commands = {c["id"]: c["python_name"] for c in spec["contributions"]["commands"]}
    # the table reader (the plugin's other readers: movies and calibrations)
    readers = spec["contributions"]["readers"]
    [reader] = [r for r in readers if r["command"] == "sparseloc.get_reader"]
    module, func = commands[reader["command"]].split(":")
    assert getattr(importlib.import_module(module), func) is napari_get_reader
    assert "*.parquet" in reader["filename_patterns"]
    pyproject = Path(__file__).parents[1] / "pyproject.toml"
    assert 'sparseloc = "sparseloc:napari.yaml"' in pyproject.read_text()


def test_the_manifest_validates_with_npe2_where_installed():
    npe2 = pytest.importorskip("npe2")
    import sparseloc

    pm = npe2.PluginManifest.from_file(Path(sparseloc.__file__).with_name("napari.yaml"))
    assert pm.name == "sparseloc"
