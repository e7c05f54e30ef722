"""TIFF and truth-CSV readers and writers: round trips, atomic writes, clear errors."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from sparseloc.io import (
    read_tiff,
    read_tiff_metadata,
    read_truth_csv,
    write_tiff,
    write_truth_csv,
)
from sparseloc.psf import PupilPSF
from sparseloc.simulate import simulate, write_simulation


def _truth(n: int = 20, with_id: bool = True) -> pd.DataFrame:
    rng = np.random.default_rng(0)
    df = pd.DataFrame(
        {
            "frame": np.sort(rng.integers(0, 5, n)),
            "x_nm": rng.uniform(0, 6400, n),
            "y_nm": rng.uniform(0, 6400, n),
            "z_nm": rng.uniform(-1000, 1000, n),
            "photons": rng.uniform(1000, 5000, n),
        }
    )
    if with_id:
        df["emitter_id"] = rng.integers(0, 7, n)
    return df


def test_tiff_round_trip(tmp_path):
    movie = np.random.default_rng(1).integers(0, 65536, size=(4, 9, 7), dtype=np.uint16)
    path = write_tiff(tmp_path / "m.tif", movie, pixel_size=107.5, metadata={"seed": 3})
    back = read_tiff(path)
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, movie)
    meta = read_tiff_metadata(path)
    assert meta["shape"] == (4, 9, 7)
    assert meta["pixel_size"] == pytest.approx(107.5)
    assert meta["seed"] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["m.tif"]  # no temporary files left


def test_tiff_single_frame_and_integer_input(tmp_path):
    img = np.arange(12, dtype=np.int32).reshape(3, 4)
    write_tiff(tmp_path / "one.tif", img)
    back = read_tiff(tmp_path / "one.tif")
    assert back.shape == (1, 3, 4) and back.dtype == np.uint16
    np.testing.assert_array_equal(back[0], img)
    assert read_tiff_metadata(tmp_path / "one.tif")["pixel_size"] is None


def test_tiff_errors(tmp_path):
    movie = np.zeros((2, 3, 3), np.uint16)
    with pytest.raises(ValueError, match="does not exist"):
        write_tiff(tmp_path / "missing" / "m.tif", movie)
    with pytest.raises(ValueError, match="dtype"):
        write_tiff(tmp_path / "f.tif", movie.astype(np.float32))
    with pytest.raises(ValueError, match="uint16"):
        write_tiff(tmp_path / "f.tif", np.full((2, 2), 70000))
    with pytest.raises(ValueError, match="frames, rows, cols"):
        write_tiff(tmp_path / "f.tif", np.zeros((2, 2, 2, 2), np.uint16))
    with pytest.raises(ValueError, match="pixel_size"):
        write_tiff(tmp_path / "f.tif", movie, pixel_size=-1.0)
    assert list(tmp_path.iterdir()) == []  # nothing half-written
    with pytest.raises(ValueError, match="does not exist"):
        read_tiff(tmp_path / "nope.tif")
    (tmp_path / "bad.tif").write_bytes(b"not a tiff at all")
    with pytest.raises(ValueError, match="not a TIFF file"):
        read_tiff(tmp_path / "bad.tif")


def test_truth_csv_round_trip(tmp_path):
    df = _truth()
    path = write_truth_csv(tmp_path / "t.csv", df)
    header = path.read_text().splitlines()[0]
    assert header == "frame,x_nm,y_nm,z_nm,photons,emitter_id"
    back = read_truth_csv(path)
    pd.testing.assert_frame_equal(back, df)
    # without emitter_id, and extra columns are not written
    df2 = _truth(with_id=False).assign(extra=1.0)
    write_truth_csv(tmp_path / "t2.csv", df2)
    assert (tmp_path / "t2.csv").read_text().splitlines()[0] == "frame,x_nm,y_nm,z_nm,photons"
    pd.testing.assert_frame_equal(read_truth_csv(tmp_path / "t2.csv"), df2.drop(columns="extra"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv", "t2.csv"]


def test_truth_csv_errors(tmp_path):
    with pytest.raises(ValueError, match="z_nm, photons"):
        write_truth_csv(tmp_path / "t.csv", _truth().drop(columns=["z_nm", "photons"]))
    with pytest.raises(ValueError, match="does not exist"):
        write_truth_csv(tmp_path / "no" / "t.csv", _truth())
    (tmp_path / "bad.csv").write_text("frame,x_nm,y_nm\n0,1,2\n")
    with pytest.raises(ValueError, match="z_nm, photons"):
        read_truth_csv(tmp_path / "bad.csv")
    (tmp_path / "nan.csv").write_text("frame,x_nm,y_nm,z_nm,photons\n0,1,2,,4\n")
    with pytest.raises(ValueError, match="z_nm"):
        read_truth_csv(tmp_path / "nan.csv")
    (tmp_path / "neg.csv").write_text("frame,x_nm,y_nm,z_nm,photons\n-1,1,2,3,4\n")
    with pytest.raises(ValueError, match="frame"):
        read_truth_csv(tmp_path / "neg.csv")
    with pytest.raises(FileNotFoundError):
        read_truth_csv(tmp_path / "missing.csv")
    # localization tables may lack photons
    (tmp_path / "locs.csv").write_text("frame,x_nm,y_nm,z_nm\n0,1,2,3\n")
    assert len(read_truth_csv(tmp_path / "locs.csv", require_photons=False)) == 1


def test_write_simulation(tmp_path):
    sim = simulate(PupilPSF(), n_frames=2, shape=(16, 16), seed=3)
    tif, truth = write_simulation(sim, tmp_path / "OUT.tif")
    assert tif == tmp_path / "OUT.tif" and truth == tmp_path / "OUT_truth.csv"
    np.testing.assert_array_equal(read_tiff(tif), sim.movie)
    assert read_tiff_metadata(tif)["pixel_size"] == pytest.approx(100.0)
    pd.testing.assert_frame_equal(read_truth_csv(truth), sim.truth)
    with pytest.raises(ValueError, match=r"\.tif"):
        write_simulation(sim, tmp_path / "OUT.png")
