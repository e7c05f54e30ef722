"""Localization tables: round trips through every format, exact headers, conventions, errors."""

from __future__ import annotations

import csv

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml

from sparseloc.io import write_truth_csv
from sparseloc.io.tables import (
    FLAG_CODES,
    LOCS_COLUMNS,
    check_locs,
    complete_locs,
    empty_locs,
    read_parquet,
    read_picasso_hdf5,
    read_smlm_csv,
    read_table,
    read_thunderstorm_csv,
    write_parquet,
    write_picasso_hdf5,
    write_smlm_csv,
    write_table,
    write_thunderstorm_csv,
)

PIXEL = 100.0
SHAPE = (48, 64)  # rows, cols
N_FRAMES = 20
FLOATS = [c for c in LOCS_COLUMNS if c not in ("frame", "flag", "window_id")]
TS_HEADER = (
    '"id","frame","x [nm]","y [nm]","z [nm]","intensity [photon]","offset [photon]",'
    '"bkgstd [photon]","uncertainty_xy [nm]","uncertainty_z [nm]"'
)


def _locs(n: int = 40, seed: int = 0) -> pd.DataFrame:
    """Random table inside the image, every x, y past the first half pixel (Picasso keeps it)."""
    rng = np.random.default_rng(seed)
    return pd.DataFrame(
        {
            "frame": np.sort(rng.integers(0, N_FRAMES, n)),
            "x_nm": rng.uniform(PIXEL / 2, SHAPE[1] * PIXEL - PIXEL, n),
            "y_nm": rng.uniform(PIXEL / 2, SHAPE[0] * PIXEL - PIXEL, n),
            "z_nm": rng.uniform(-1000, 1000, n),
            "photons": rng.uniform(500, 8000, n),
            "background": rng.uniform(1, 30, n),
            "sigma_x_nm": rng.uniform(3, 30, n),
            "sigma_y_nm": rng.uniform(3, 30, n),
            "sigma_z_nm": rng.uniform(10, 60, n),
            "sigma_photons": rng.uniform(20, 200, n),
            "gof": rng.uniform(0, 3, n),
            "flag": rng.choice(list(FLAG_CODES), n),
            "window_id": rng.integers(0, 1000, n),
        }
    )


def _assert_same(back: pd.DataFrame, ref: pd.DataFrame, *, rtol: float = 0.0) -> None:
    assert list(back.columns[: len(LOCS_COLUMNS)]) == list(LOCS_COLUMNS)
    assert len(back) == len(ref)
    assert back["frame"].dtype == np.int64
    np.testing.assert_array_equal(back["frame"], ref["frame"])
    np.testing.assert_array_equal(back["window_id"], ref["window_id"])
    assert back["flag"].tolist() == list(ref["flag"])
    for col in FLOATS:
        if rtol == 0.0:
            np.testing.assert_array_equal(back[col].to_numpy(), ref[col].to_numpy(), err_msg=col)
        else:
            np.testing.assert_allclose(back[col], ref[col], rtol=rtol, err_msg=col)


def _leftovers(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# ---------------------------------------------------------------------------------- the table


def test_empty_and_check():
    empty = empty_locs()
    assert list(empty.columns) == list(LOCS_COLUMNS)
    assert len(empty) == 0
    assert empty["frame"].dtype == np.int64 and empty["window_id"].dtype == np.int64
    checked = check_locs(_locs(5).assign(extra=1.0))
    assert list(checked.columns) == [*LOCS_COLUMNS, "extra"]
    with pytest.raises(ValueError, match="photons, background"):
        check_locs(_locs(5).drop(columns=["photons", "background"]))
    with pytest.raises(ValueError, match="0-based"):
        check_locs(_locs(5).assign(frame=-1))
    with pytest.raises(ValueError, match="integers"):
        check_locs(_locs(5).assign(frame=0.5))
    with pytest.raises(ValueError, match="'gof' must hold numbers"):
        check_locs(_locs(5).assign(gof="bad"))
    full = complete_locs(pd.DataFrame({"frame": [0, 2], "x_nm": [1.0, 2.0], "y_nm": [3.0, 4.0]}))
    assert full["flag"].tolist() == ["ok", "ok"]
    assert full["window_id"].tolist() == [-1, -1]
    assert full["z_nm"].tolist() == [0.0, 0.0]
    assert full["photons"].isna().all()


# -------------------------------------------------------------------------------------- Parquet


def test_parquet_round_trip_and_metadata(tmp_path):
    df = _locs().assign(flag=lambda d: d["flag"].where(d.index % 7 != 0, "custom reason"))
    meta = {
        "pixel_size": np.float64(107.5),
        "shape": (48, 64),
        "n_frames": np.int64(20),
        "psf_hash": "sha256:abc",
        "params": {"method": "hybrid", "dxy": [10, 15]},
    }
    path = write_parquet(df, tmp_path / "l.parquet", metadata=meta)
    back, meta_back = read_parquet(path)
    _assert_same(back, df)
    assert meta_back["pixel_size"] == 107.5
    assert meta_back["shape"] == [48, 64]
    assert meta_back["n_frames"] == 20
    assert meta_back["params"] == {"method": "hybrid", "dxy": [10, 15]}
    assert meta_back["sparseloc_version"]
    _assert_same(read_table(path), df)
    assert _leftovers(tmp_path) == []


# --------------------------------------------------------------------------------- ThunderSTORM


def test_thunderstorm_round_trip_and_header(tmp_path):
    df = _locs()
    df.loc[3, "sigma_z_nm"] = np.nan
    df.loc[4, "gof"] = np.inf
    path = write_thunderstorm_csv(df, tmp_path / "l.csv")
    raw = path.read_bytes()
    first = raw.split(b"\n", 1)[0]
    assert first.startswith(TS_HEADER.encode() + b",")
    assert (
        first
        == (
            TS_HEADER + ',"uncertainty_x [nm]","uncertainty_y [nm]","uncertainty_photons [photon]",'
            '"gof","flag","window_id"'
        ).encode()
    )
    rows = list(csv.DictReader(path.open(newline="")))
    assert [int(r["id"]) for r in rows] == list(range(1, len(df) + 1))
    assert [int(r["frame"]) for r in rows] == list(df["frame"] + 1)
    assert rows[3]["uncertainty_z [nm]"] == "NaN" and rows[4]["gof"] == "Infinity"
    # every cell parses as a number, as ThunderSTORM's importer requires
    for r in rows:
        [float(v) for v in r.values()]
    r0 = rows[0]
    assert float(r0["offset [photon]"]) == df.loc[0, "background"]
    assert float(r0["bkgstd [photon]"]) == pytest.approx(np.sqrt(df.loc[0, "background"]))
    sx, sy = df.loc[0, "sigma_x_nm"], df.loc[0, "sigma_y_nm"]
    assert float(r0["uncertainty_xy [nm]"]) == pytest.approx(np.sqrt((sx**2 + sy**2) / 2))
    assert int(r0["flag"]) == FLAG_CODES[df.loc[0, "flag"]]

    back = read_thunderstorm_csv(path)
    _assert_same(back, df)
    _assert_same(read_table(path), df)
    assert _leftovers(tmp_path) == []


def test_thunderstorm_standard_columns_only(tmp_path):
    path = tmp_path / "ts.csv"
    path.write_text(
        TS_HEADER + "\n1,1,150.5,250.25,-30,1000,4,2,12,40\n2,3,1000,2000,100,2500,9,3,20,55\n",
        encoding="utf-8",
    )
    back = read_thunderstorm_csv(path)
    assert back["frame"].tolist() == [0, 2]
    assert back["x_nm"].tolist() == [150.5, 1000.0]
    assert back["background"].tolist() == [4.0, 9.0]
    assert back["sigma_x_nm"].tolist() == [12.0, 20.0]
    assert back["sigma_y_nm"].tolist() == [12.0, 20.0]
    assert back["sigma_z_nm"].tolist() == [40.0, 55.0]
    assert back["sigma_photons"].isna().all() and back["gof"].isna().all()
    assert back["flag"].tolist() == ["ok", "ok"]
    assert back["window_id"].tolist() == [-1, -1]
    # micrometres are converted; pixels cannot be without a pixel size
    um = tmp_path / "um.csv"
    um.write_text('"frame","x [um]","y [um]"\n1,1.5,2\n', encoding="utf-8")
    assert read_table(um)["x_nm"].tolist() == [1500.0]
    px = tmp_path / "px.csv"
    px.write_text('"frame","x [px]","y [px]"\n1,1.5,2\n', encoding="utf-8")
    with pytest.raises(ValueError, match="in nm"):
        read_thunderstorm_csv(px)


def test_thunderstorm_unknown_flag_becomes_other(tmp_path):
    df = _locs(4).assign(flag=["ok", "my reason", "diverged", "ok"])
    back = read_thunderstorm_csv(write_thunderstorm_csv(df, tmp_path / "l.csv"))
    assert back["flag"].tolist() == ["ok", "other", "diverged", "ok"]


# --------------------------------------------------------------------------------------- Picasso


def test_picasso_hand_made_conversion(tmp_path):
    df = complete_locs(
        pd.DataFrame(
            {
                "frame": [0, 3],
                "x_nm": [150.0, 50.0],
                "y_nm": [50.0, 1250.0],
                "z_nm": [-200.0, 300.0],
                "photons": [1000.0, 2000.0],
                "background": [5.0, 7.0],
                "sigma_x_nm": [10.0, 20.0],
                "sigma_y_nm": [30.0, 40.0],
                "sigma_z_nm": [25.0, 35.0],
            }
        )
    )
    path = write_picasso_hdf5(df, tmp_path / "l.hdf5", pixel_size=100, shape=(16, 32), n_frames=4)
    with h5py.File(path, "r") as fh:
        locs = fh["locs"][()]
    assert locs.dtype["frame"] == np.uint32
    for name in ("x", "y", "z", "photons", "bg", "lpx", "lpy", "lpz"):
        assert locs.dtype[name] == np.float32
    np.testing.assert_array_equal(locs["frame"], [0, 3])
    np.testing.assert_allclose(locs["x"], [1.0, 0.0])  # x_nm = 150 at 100 nm/px -> 1.0 px
    np.testing.assert_allclose(locs["y"], [0.0, 12.0])
    np.testing.assert_allclose(locs["z"], [-200.0, 300.0])  # nm
    np.testing.assert_allclose(locs["lpx"], [0.1, 0.2])  # px
    np.testing.assert_allclose(locs["lpy"], [0.3, 0.4])
    np.testing.assert_allclose(locs["lpz"], [25.0, 35.0])  # nm
    np.testing.assert_allclose(locs["bg"], [5.0, 7.0])

    docs = list(yaml.safe_load_all(path.with_suffix(".yaml").read_text(encoding="utf-8")))
    assert docs[0] == {"Width": 32, "Height": 16, "Frames": 4, "Pixelsize": 100.0}
    assert docs[1]["sparseloc"]["flag_codes"]["ok"] == 0


def test_picasso_round_trip(tmp_path):
    df = _locs().assign(flag=lambda d: d["flag"].where(d.index % 5 != 0, "custom reason"))
    meta = {"psf_hash": "sha256:abc", "pixel_size": PIXEL}
    path = write_table(
        df, tmp_path / "l.hdf5", pixel_size=PIXEL, shape=SHAPE, n_frames=N_FRAMES, metadata=meta
    )
    back, info = read_picasso_hdf5(path)
    _assert_same(back, df, rtol=1e-6)
    assert list(info[0]) == ["Width", "Height", "Frames", "Pixelsize"]
    assert info[0]["Width"] == SHAPE[1] and info[0]["Height"] == SHAPE[0]
    assert info[1]["sparseloc"]["metadata"] == meta
    # the sidecar is optional: the same metadata is embedded in /metadata
    path.with_suffix(".yaml").unlink()
    _assert_same(read_table(path), df, rtol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.hdf5"]


@pytest.mark.filterwarnings("ignore:The inplace keyword")
def test_picasso_loads_our_file(tmp_path):
    pio = pytest.importorskip("picasso.io")
    df = _locs()
    path = write_picasso_hdf5(
        df, tmp_path / "l.hdf5", pixel_size=PIXEL, shape=SHAPE, n_frames=N_FRAMES
    )
    locs, info = pio.load_locs(str(path))
    assert len(locs) == len(df)  # nothing dropped by Picasso's sanity checks
    np.testing.assert_array_equal(locs["frame"], df["frame"])
    np.testing.assert_allclose(locs["x"], df["x_nm"] / PIXEL - 0.5, rtol=1e-6)
    np.testing.assert_allclose(locs["y"], df["y_nm"] / PIXEL - 0.5, rtol=1e-6)
    np.testing.assert_allclose(locs["z"], df["z_nm"], rtol=1e-6)
    np.testing.assert_allclose(locs["lpx"], df["sigma_x_nm"] / PIXEL, rtol=1e-6)
    np.testing.assert_allclose(locs["photons"], df["photons"], rtol=1e-6)
    assert info[0]["Pixelsize"] == PIXEL
    # Picasso saves it again, and the copy still reads back
    pio.save_locs(str(tmp_path / "again.hdf5"), locs, info)
    _assert_same(read_picasso_hdf5(tmp_path / "again.hdf5")[0], df, rtol=1e-6)


# ---------------------------------------------------------------------------------------- SMLM


def test_smlm_round_trip(tmp_path):
    df = _locs()
    path = write_smlm_csv(df, tmp_path / "l.csv")
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == "Ground-truth,frame,xnano,ynano,znano,intensity"
    assert lines[1].split(",")[:2] == ["1", str(df.loc[0, "frame"] + 1)]
    for back in (read_smlm_csv(path), read_table(path)):
        np.testing.assert_array_equal(back["frame"], df["frame"])
        for col in ("x_nm", "y_nm", "z_nm", "photons"):
            np.testing.assert_array_equal(back[col].to_numpy(), df[col].to_numpy())
        assert (back["flag"] == "ok").all()
        assert back["sigma_x_nm"].isna().all()
    # the challenge's own files: ", " separators and "intensity " with a trailing space
    theirs = tmp_path / "activations.csv"
    theirs.write_text(
        "Ground-truth,frame,xnano,ynano,znano,intensity \n"
        "    1,     1, 4467.775, 3508.066, -352.211, 2319.470 \n",
        encoding="utf-8",
    )
    back = read_table(theirs)
    assert back["frame"].tolist() == [0]
    assert back["x_nm"].tolist() == [4467.775]
    assert back["photons"].tolist() == [2319.47]


# ------------------------------------------------------------------------------------ dispatch


def test_dispatch_and_truth_csv(tmp_path):
    df = _locs(10)
    for name, fmt in [("a.parquet", None), ("b.csv", None), ("c.h5", None), ("d.txt", "smlm")]:
        path = write_table(
            df, tmp_path / name, format=fmt, pixel_size=PIXEL, shape=SHAPE, n_frames=N_FRAMES
        )
        back = read_table(path)
        np.testing.assert_array_equal(back["frame"], df["frame"])
        np.testing.assert_allclose(back["x_nm"], df["x_nm"], rtol=1e-6)
    truth = df[["frame", "x_nm", "y_nm", "z_nm", "photons"]]
    back = read_table(write_truth_csv(tmp_path / "truth.csv", truth))
    np.testing.assert_array_equal(back["x_nm"].to_numpy(), truth["x_nm"].to_numpy())
    assert (back["flag"] == "ok").all() and (back["window_id"] == -1).all()
    assert _leftovers(tmp_path) == []


def test_empty_table_round_trips(tmp_path):
    empty = empty_locs()
    assert len(read_parquet(write_parquet(empty, tmp_path / "e.parquet", metadata={}))[0]) == 0
    assert len(read_thunderstorm_csv(write_thunderstorm_csv(empty, tmp_path / "e.csv"))) == 0
    path = write_picasso_hdf5(empty, tmp_path / "e.hdf5", pixel_size=PIXEL, shape=SHAPE, n_frames=1)
    assert len(read_picasso_hdf5(path)[0]) == 0


# ---------------------------------------------------------------------------------- bad input


def test_bad_input(tmp_path):
    df = _locs(5)
    nowhere = tmp_path / "missing" / "l"
    writers = [
        lambda d, p: write_parquet(d, p.with_suffix(".parquet"), metadata={}),
        lambda d, p: write_thunderstorm_csv(d, p.with_suffix(".csv")),
        lambda d, p: write_smlm_csv(d, p.with_suffix(".csv")),
        lambda d, p: write_picasso_hdf5(
            d, p.with_suffix(".hdf5"), pixel_size=PIXEL, shape=SHAPE, n_frames=N_FRAMES
        ),
    ]
    for write in writers:
        with pytest.raises(ValueError, match="does not exist"):
            write(df, nowhere)
        with pytest.raises(ValueError, match=r"missing the column.*sigma_z_nm"):
            write(df.drop(columns=["sigma_z_nm"]), tmp_path / "x")
    for fmt in ("parquet", "thunderstorm", "smlm", "picasso"):
        with pytest.raises(ValueError, match="missing the column"):
            write_table(
                df.drop(columns=["flag"]),
                tmp_path / "x.out",
                format=fmt,
                pixel_size=PIXEL,
                shape=SHAPE,
                n_frames=N_FRAMES,
            )
    with pytest.raises(ValueError, match="unknown table format 'xml'"):
        write_table(df, tmp_path / "x.xml", format="xml")
    with pytest.raises(ValueError, match="suffix"):
        write_table(df, tmp_path / "x.xml")
    with pytest.raises(ValueError, match="pixel_size, shape, n_frames"):
        write_table(df, tmp_path / "x.hdf5")
    with pytest.raises(ValueError, match="pixel_size"):
        write_picasso_hdf5(df, tmp_path / "x.hdf5", pixel_size=0, shape=SHAPE, n_frames=N_FRAMES)
    with pytest.raises(ValueError, match="n_frames"):
        write_picasso_hdf5(df, tmp_path / "x.hdf5", pixel_size=PIXEL, shape=SHAPE, n_frames=2)
    with pytest.raises(ValueError, match="metadata must be JSON"):
        write_parquet(df, tmp_path / "x.parquet", metadata={"f": object()})
    with pytest.raises(FileNotFoundError):
        read_table(tmp_path / "absent.csv")
    junk = tmp_path / "junk.csv"
    junk.write_text("a,b\n1,2\n", encoding="utf-8")
    with pytest.raises(ValueError, match="not a recognised localization table"):
        read_table(junk)
    bad_frames = tmp_path / "zero.csv"
    bad_frames.write_text('"frame","x [nm]","y [nm]"\n0,1,2\n', encoding="utf-8")
    with pytest.raises(ValueError, match="counts from 1"):
        read_table(bad_frames)
    # nothing half-written, no temporary files
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.csv", "zero.csv"]


def test_thunderstorm_uncertainty_columns_and_older_files(tmp_path):
    # The uncertainties are uncertainty_* columns (ThunderSTORM's sigma is the PSF's width);
    # files written with the older sigma_* names still read back the same.
    df = _locs()
    path = write_thunderstorm_csv(df, tmp_path / "l.csv")
    header = path.read_text().split("\n", 1)[0]
    assert '"uncertainty_x [nm]"' in header and '"sigma_x [nm]"' not in header
    old = tmp_path / "old.csv"
    text = path.read_text()
    for new, was in (("uncertainty_x", "sigma_x"), ("uncertainty_y", "sigma_y")):
        text = text.replace(f'"{new} [nm]"', f'"{was} [nm]"')
    old.write_text(text.replace('"uncertainty_photons [photon]"', '"sigma_photons [photon]"'))
    a, b = read_thunderstorm_csv(path), read_thunderstorm_csv(old)
    for col in ("sigma_x_nm", "sigma_y_nm", "sigma_photons"):
        np.testing.assert_array_equal(a[col].to_numpy(), b[col].to_numpy())
        np.testing.assert_allclose(a[col].to_numpy(), df[col].to_numpy(), rtol=1e-12)


def test_a_format_that_contradicts_the_files_suffix_is_refused():
    """The fourth walk-through: `-o out.csv --format parquet` wrote a Parquet file named .csv."""
    from sparseloc.io.tables import format_for

    assert format_for("t.csv", "smlm") == "smlm" and format_for("t.csv", None) == "thunderstorm"
    assert format_for("t.txt", "parquet") == "parquet"  # a suffix of no format decides nothing
    with pytest.raises(ValueError, match=r"writes a Parquet file, but 't\.csv' is named as a CSV"):
        format_for("t.csv", "parquet")
    with pytest.raises(ValueError, match="writes a HDF5 file"):
        format_for("t.parquet", "picasso")


def test_a_picasso_table_written_by_sparseloc_gives_back_its_metadata(tmp_path):
    """The fourth walk-through: a `--frames 0:10` run written as Picasso HDF5 was scored
    against the whole truth (3.8 % against 82 %): its sidecar held the range, unread."""
    from sparseloc.io.tables import complete_locs, read_table_and_metadata, write_table

    locs = complete_locs(pd.DataFrame({"frame": [0, 3], "x_nm": 500.0, "y_nm": 500.0,
                                       "z_nm": 0.0}))  # fmt: skip
    path = tmp_path / "t.hdf5"
    write_table(locs, path, pixel_size=100.0, shape=(32, 32), n_frames=20,
                metadata={"frames": [0, 10], "shape": [32, 32]})  # fmt: skip
    table, meta = read_table_and_metadata(path)
    assert len(table) == 2 and meta["frames"] == [0, 10] and meta["shape"] == [32, 32]
