"""Lazy movie reading (sparseloc.io.movie) and sCMOS camera maps from files."""

from __future__ import annotations

import os
import pickle
import re
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import tifffile

from sparseloc.camera import Camera, to_photons
from sparseloc.io.movie import Movie, check_camera_for_movie, photon_frames
from sparseloc.io.tiff import read_tiff, write_tiff

SHAPE = (12, 9, 11)  # frames, rows, cols: all different, so a swapped axis shows


@pytest.fixture(scope="module")
def data() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, 60000, size=SHAPE, dtype=np.uint16)


def _write_pages(path: Path, data: np.ndarray) -> None:
    """One page at a time, not contiguous: each page becomes its own tifffile series."""
    with tifffile.TiffWriter(path) as tw:
        for frame in data:
            tw.write(frame, contiguous=False)


WRITERS = {
    "imagej": lambda p, d: write_tiff(p, d, pixel_size=100.0),
    "plain": lambda p, d: tifffile.imwrite(p, d),
    "ome": lambda p, d: tifffile.imwrite(p, d, ome=True, metadata={"axes": "TYX"}),
    "ome_default_axes": lambda p, d: tifffile.imwrite(p, d, ome=True),
    "zlib": lambda p, d: tifffile.imwrite(p, d, compression="zlib"),
    "tiled": lambda p, d: tifffile.imwrite(p, d, tile=(16, 16)),
    "pages": _write_pages,
    "imagej_one_ifd": lambda p, d: tifffile.imwrite(
        p, d, imagej=True, metadata={"axes": "TYX"}, truncate=True
    ),
    "big_endian": lambda p, d: tifffile.imwrite(p, d, byteorder=">"),
}


@pytest.fixture(params=sorted(WRITERS))
def movie_file(request, tmp_path, data) -> Path:
    path = tmp_path / f"{request.param}.tif"
    WRITERS[request.param](path, data)
    return path


def _message(exc_info: pytest.ExceptionInfo[ValueError]) -> str:
    return str(exc_info.value)


# -- reading ---------------------------------------------------------------------------------
def test_lazy_reads_equal_full_read(movie_file, data):
    with Movie.open(movie_file) as m:
        assert m.n_frames == len(m) == SHAPE[0]
        assert m.shape == SHAPE[1:]
        assert m.dtype == np.uint16 and m.dtype.isnative
        assert m.paths == (movie_file,)
        full = m.frames()
        assert full.shape == SHAPE and full.dtype == np.uint16
        np.testing.assert_array_equal(full, data)
        for i in range(m.n_frames):
            np.testing.assert_array_equal(m[i], data[i])
        np.testing.assert_array_equal(m[3:7], data[3:7])
        np.testing.assert_array_equal(m.frames(5, 9), data[5:9])
        np.testing.assert_array_equal(m[-1], data[-1])
        np.testing.assert_array_equal(m[-3:], data[-3:])
        np.testing.assert_array_equal(m[8:100], data[8:])
        assert m[7:3].shape == (0, *SHAPE[1:])
        assert m.frames(4, 4).shape == (0, *SHAPE[1:])
        np.testing.assert_array_equal(np.stack(list(m)), data)


def test_matches_read_tiff_and_out_array_is_independent(tmp_path, data):
    path = write_tiff(tmp_path / "w.tif", data)
    with Movie.open(str(path)) as m:
        a = m[2:4]
        a[...] = 0  # the caller owns the array; the movie is unchanged
        np.testing.assert_array_equal(m.frames(), read_tiff(path))


def test_single_2d_image_is_one_frame(tmp_path, data):
    path = tmp_path / "one.tif"
    tifffile.imwrite(path, data[0])
    with Movie.open(path) as m:
        assert m.n_frames == 1 and m.shape == SHAPE[1:]
        np.testing.assert_array_equal(m[0], data[0])
        assert m.frames().shape == (1, *SHAPE[1:])
    assert "1 frame of" in repr(m)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint32])
def test_other_integer_types(tmp_path, dtype):
    d = np.arange(3 * 4 * 5).reshape(3, 4, 5).astype(dtype)
    tifffile.imwrite(tmp_path / "i.tif", d, photometric="minisblack")
    with Movie.open(tmp_path / "i.tif") as m:
        assert m.dtype == dtype
        np.testing.assert_array_equal(m.frames(), d)


@pytest.mark.parametrize("chunk", [1, 4, 5, 12, 100])
def test_chunks_cover_every_frame_once(tmp_path, data, chunk):
    write_tiff(tmp_path / "c.tif", data)
    with Movie.open(tmp_path / "c.tif") as m:
        chunks = list(m.iter_chunks(chunk))
    starts = [s for s, _ in chunks]
    assert starts == list(range(0, SHAPE[0], chunk))
    assert all(len(c) <= chunk for _, c in chunks)
    np.testing.assert_array_equal(np.concatenate([c for _, c in chunks]), data)


def test_chunks_of_a_range(tmp_path, data):
    write_tiff(tmp_path / "c.tif", data)
    with Movie.open(tmp_path / "c.tif") as m:
        chunks = list(m.iter_chunks(4, start=3, stop=10))
    assert [s for s, _ in chunks] == [3, 7]
    np.testing.assert_array_equal(np.concatenate([c for _, c in chunks]), data[3:10])


# -- several files -----------------------------------------------------------------------------
@pytest.fixture
def series_files(tmp_path, data) -> list[Path]:
    """run_1, run_2, run_10 (natural order) with 5, 1 and 6 frames."""
    parts = [data[:5], data[5:6], data[6:]]
    paths = [tmp_path / f"run_{k}.tif" for k in (1, 2, 10)]
    write_tiff(paths[0], parts[0], pixel_size=100.0)
    tifffile.imwrite(paths[1], parts[1][0])  # a 2-D image in the middle
    tifffile.imwrite(paths[2], parts[2], compression="zlib")  # another layout
    return paths


def test_multi_file_series_in_order(series_files, data):
    with Movie.open(series_files) as m:
        assert m.n_frames == SHAPE[0] and m.paths == tuple(series_files)
        np.testing.assert_array_equal(m.frames(), data)
        np.testing.assert_array_equal(m.frames(3, 9), data[3:9])  # across all three files
        for i in range(m.n_frames):
            np.testing.assert_array_equal(m[i], data[i])
        chunks = list(m.iter_chunks(4))
        np.testing.assert_array_equal(np.concatenate([c for _, c in chunks]), data)
    with Movie.open(series_files[::-1]) as m:  # the order given is the order of the series
        np.testing.assert_array_equal(m.frames(), np.concatenate([data[6:], data[5:6], data[:5]]))


def test_glob_pattern_sorts_naturally(series_files, data, tmp_path):
    with Movie.open(str(tmp_path / "run_*.tif")) as m:
        assert m.paths == tuple(series_files)  # run_2 before run_10
        np.testing.assert_array_equal(m.frames(), data)
        assert m.pixel_size == pytest.approx(100.0)  # from the only file that records one


def test_many_files_keep_few_open(tmp_path, data):
    paths = []
    for i, frame in enumerate(data):
        paths.append(tmp_path / f"f{i:02d}.tif")
        tifffile.imwrite(paths[-1], frame)
    with Movie.open(paths) as m:
        assert len(m._readers) <= 8
        np.testing.assert_array_equal(m.frames(), data)
        np.testing.assert_array_equal(m[0], data[0])  # reopened after being closed
        assert len(m._readers) <= 8


def test_file_changed_after_open(tmp_path, data):
    paths = [tmp_path / f"f{i:02d}.tif" for i in range(10)]
    for p, frame in zip(paths, data, strict=False):
        tifffile.imwrite(p, frame)
    with Movie.open(paths) as m:
        tifffile.imwrite(paths[9], data[:3], photometric="minisblack")  # rewritten
        with pytest.raises(ValueError, match=r"f09\.tif.* changed since it was opened"):
            m[9]


# -- pixel size --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        ("ome_um", 107.0),
        ("ome_nm", 65.0),
        ("imagej_writer", 160.0),
        ("imagej_micron", 130.0),
        ("plain", None),
    ],
)
def test_pixel_size_from_metadata(tmp_path, data, kind, expected):
    path = tmp_path / f"{kind}.tif"
    if kind == "ome_um":
        meta = {"axes": "TYX", "PhysicalSizeX": 0.107, "PhysicalSizeY": 0.107}
        tifffile.imwrite(path, data, ome=True, metadata=meta)
    elif kind == "ome_nm":
        meta = {"axes": "TYX", "PhysicalSizeX": 65.0, "PhysicalSizeXUnit": "nm"}
        tifffile.imwrite(path, data, ome=True, metadata=meta)
    elif kind == "imagej_writer":
        write_tiff(path, data, pixel_size=160.0)
    elif kind == "imagej_micron":
        tifffile.imwrite(
            path,
            data,
            imagej=True,
            metadata={"axes": "TYX", "unit": "micron"},
            resolution=(1 / 0.13, 1 / 0.13),
        )
    else:
        tifffile.imwrite(path, data)
    with Movie.open(path) as m:
        if expected is None:
            assert m.pixel_size is None
        else:
            assert m.pixel_size == pytest.approx(expected, rel=1e-6)


def test_pixel_sizes_that_disagree(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data[:4], pixel_size=100.0)
    write_tiff(tmp_path / "b.tif", data[4:], pixel_size=110.0)
    with pytest.raises(ValueError, match=r"pixel size of '.*b\.tif' \(110 nm\) differs"):
        Movie.open([tmp_path / "a.tif", tmp_path / "b.tif"])


# -- memory ------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", ["contiguous", "zlib"])
def test_memory_stays_flat(tmp_path, layout):
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 4000, size=(2000, 64, 64), dtype=np.uint16)
    path = tmp_path / "long.tif"
    if layout == "contiguous":
        write_tiff(path, frames)
    else:
        tifffile.imwrite(path, frames, compression="zlib", compressionargs={"level": 1})
    expected = frames[:, 10, 20].astype(np.int64)
    del frames
    file_size = path.stat().st_size
    assert file_size > 8_000_000
    tracemalloc.start()
    try:
        with Movie.open(path) as m:
            after_open = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            got = np.array([m[i][10, 20] for i in range(m.n_frames)], dtype=np.int64)
            frame_by_frame = tracemalloc.get_traced_memory()[1] - after_open
            tracemalloc.reset_peak()
            for _, chunk in m.iter_chunks(50):
                assert chunk.shape == (50, 64, 64)
            by_chunks = tracemalloc.get_traced_memory()[1] - after_open
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(got, expected)
    frame_bytes, chunk_bytes = 64 * 64 * 2, 50 * 64 * 64 * 2
    # flat: reading all 2000 frames costs a few frames (a few chunks), not the file
    assert frame_by_frame < 16 * frame_bytes, frame_by_frame
    assert by_chunks < 3 * chunk_bytes, by_chunks
    assert peak < file_size / 5, f"peak {peak} bytes while reading a {file_size}-byte file"


# -- bad input ---------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match=r"'.*nope\.tif' does not exist"):
        Movie.open(tmp_path / "nope.tif")


def test_missing_file_in_a_series(series_files, tmp_path):
    with pytest.raises(ValueError, match=r"gone\.tif' does not exist"):
        Movie.open([*series_files, tmp_path / "gone.tif"])


def test_glob_that_matches_nothing(tmp_path):
    with pytest.raises(ValueError, match="matches no files"):
        Movie.open(str(tmp_path / "run_*.tif"))


def test_no_files_and_wrong_types(tmp_path):
    with pytest.raises(ValueError, match="no movie files given"):
        Movie.open([])
    with pytest.raises(ValueError, match="must be str or Path"):
        Movie.open([3])


def test_folder(tmp_path):
    with pytest.raises(ValueError, match="is a folder"):
        Movie.open(tmp_path)


def test_empty_file(tmp_path):
    (tmp_path / "empty.tif").write_bytes(b"")
    with pytest.raises(ValueError, match=r"'.*empty\.tif' is empty \(0 bytes\)"):
        Movie.open(tmp_path / "empty.tif")


def test_not_a_tiff(tmp_path):
    (tmp_path / "notes.tif").write_text("frame,x,y\n1,2,3\n")
    with pytest.raises(ValueError, match=r"'.*notes\.tif' is not a TIFF file"):
        Movie.open(tmp_path / "notes.tif")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs file permissions")
def test_unreadable_file(tmp_path, data):
    path = tmp_path / "locked.tif"
    write_tiff(path, data)
    path.chmod(0)
    try:
        with pytest.raises(ValueError, match=r"locked\.tif' cannot be read"):
            Movie.open(path)
    finally:
        path.chmod(0o644)


def _read_all(path: Path) -> None:
    with Movie.open(path) as m:
        for i in range(m.n_frames):
            m[i]


@pytest.mark.parametrize("cut", [32, 0.05, 0.3, 0.7])
def test_truncated_file(movie_file, tmp_path, cut):
    raw = movie_file.read_bytes()
    n_cut = cut if isinstance(cut, int) else int(len(raw) * cut)
    bad = tmp_path / f"cut_{movie_file.name}"
    bad.write_bytes(raw[:-n_cut])
    with pytest.raises(ValueError) as exc:
        _read_all(bad)
    msg = _message(exc)
    assert str(bad) in msg and re.search("truncated or corrupt", msg), msg
    assert "\n" not in msg


def test_truncated_file_never_gives_wrong_frames(movie_file, tmp_path, data):
    """Cut anywhere: an error naming the file, or (only when the bytes cut off are unused
    padding at the very end) exactly the original frames."""
    raw = movie_file.read_bytes()
    bad = tmp_path / "cut.tif"
    for n_cut in sorted({*range(1, 40), *range(40, len(raw), 23)}):
        bad.write_bytes(raw[:-n_cut])
        try:
            with Movie.open(bad) as m:
                frames = m.frames()
        except ValueError as exc:
            assert str(bad) in str(exc) and "truncated or corrupt" in str(exc), (n_cut, exc)
        else:
            assert n_cut <= 16, f"cutting {n_cut} bytes went unnoticed"
            np.testing.assert_array_equal(frames, data)


def test_truncated_file_is_caught_when_the_frame_is_read(tmp_path, data):
    """A compressed frame whose data is damaged in place: found when that frame is read."""
    path = tmp_path / "z.tif"
    tifffile.imwrite(path, data, compression="zlib")
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[5]
        offset, count = page.dataoffsets[0], page.databytecounts[0]
    raw = bytearray(path.read_bytes())
    raw[offset : offset + count] = b"\x00" * count
    path.write_bytes(bytes(raw))
    with Movie.open(path) as m:
        np.testing.assert_array_equal(m[4], data[4])
        with pytest.raises(ValueError, match=r"z\.tif' is truncated or corrupt: frame 5 cannot"):
            m[5]
        np.testing.assert_array_equal(m[6], data[6])


def test_rgb(tmp_path):
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((4, 6, 7, 3), np.uint8), photometric="rgb")
    with pytest.raises(ValueError, match=r"rgb\.tif' holds RGB or multi-sample pixels"):
        Movie.open(tmp_path / "rgb.tif")


def test_several_frame_axes(tmp_path):
    stack = np.zeros((3, 2, 6, 7), np.uint16)
    tifffile.imwrite(tmp_path / "h.tif", stack, imagej=True, metadata={"axes": "TCYX"})
    with pytest.raises(ValueError, match=r"several frame axes \(T=3, C=2.*split the channels"):
        Movie.open(tmp_path / "h.tif")


def test_float_data(tmp_path, data):
    path = tmp_path / "f.tif"
    tifffile.imwrite(path, data.astype(np.float32))
    with pytest.raises(ValueError, match=r"f\.tif' holds floating-point data \(float32\)"):
        Movie.open(path)
    with Movie.open(path, allow_float=True) as m:
        assert m.dtype == np.float32
        np.testing.assert_array_equal(m.frames(), data.astype(np.float32))


def test_complex_data(tmp_path):
    tifffile.imwrite(tmp_path / "c.tif", np.zeros((2, 4, 5), np.complex64))
    with pytest.raises(ValueError, match="expected integer camera counts"):
        Movie.open(tmp_path / "c.tif", allow_float=True)


def test_series_with_different_frame_shapes(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data)
    write_tiff(tmp_path / "b.tif", data[:, :8, :])
    with pytest.raises(ValueError, match=r"frames of '.*b\.tif' are 8 x 11 pixels but those of"):
        Movie.open([tmp_path / "a.tif", tmp_path / "b.tif"])


def test_series_with_different_dtypes(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data)
    tifffile.imwrite(tmp_path / "b.tif", data.astype(np.int32))
    with pytest.raises(ValueError, match=r"b\.tif' holds int32 data but .* holds uint16"):
        Movie.open([tmp_path / "a.tif", tmp_path / "b.tif"])


def test_indexing_errors(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data)
    with Movie.open(tmp_path / "a.tif") as m:
        with pytest.raises(IndexError):
            m[SHAPE[0]]
        with pytest.raises(ValueError, match="step 1"):
            m[::2]
        with pytest.raises(TypeError):
            m["0"]
        with pytest.raises(ValueError, match="outside the movie of 12 frames"):
            m.frames(3, 13)
        with pytest.raises(ValueError, match="outside the movie"):
            m.frames(-1, 2)
        with pytest.raises(ValueError, match="chunk_frames must be a positive integer"):
            next(m.iter_chunks(0))


def test_close_and_context_manager(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data)
    m = Movie.open(tmp_path / "a.tif")
    np.testing.assert_array_equal(m[0], data[0])
    m.close()
    m.close()  # twice is fine
    assert m.closed
    with pytest.raises(ValueError, match="the movie is closed"):
        m[0]
    with Movie.open(tmp_path / "a.tif") as m2:
        pass
    assert m2.closed and "closed" in repr(m2)


def test_pickle_reopens(tmp_path, data):
    write_tiff(tmp_path / "a.tif", data)
    with Movie.open(tmp_path / "a.tif") as m:
        m2 = pickle.loads(pickle.dumps(m))
    with m2:
        np.testing.assert_array_equal(m2.frames(), data)


def test_concurrent_reads(series_files, data):
    order = np.random.default_rng(3).integers(0, SHAPE[0], size=200)
    with Movie.open(series_files) as m, ThreadPoolExecutor(8) as pool:
        frames = list(pool.map(lambda i: m[int(i)], order))
    for i, frame in zip(order, frames, strict=True):
        np.testing.assert_array_equal(frame, data[i])


# -- camera maps -------------------------------------------------------------------------------
@pytest.fixture
def maps() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    rows, cols = SHAPE[1:]
    return {
        "offset": rng.uniform(90, 110, size=(rows, cols)),
        "variance": rng.uniform(1, 9, size=(rows, cols)),
        "gain": rng.uniform(0.4, 0.6, size=(rows, cols)),
    }


def _save_map(path: Path, array: np.ndarray) -> Path:
    if path.suffix == ".npy":
        np.save(path, array)
    elif path.suffix == ".csv":
        np.savetxt(path, array, delimiter=",", fmt="%.17g")
    else:
        tifffile.imwrite(path, array.astype(np.float32))
    return path


@pytest.mark.parametrize("suffix", [".tif", ".npy", ".csv"])
def test_scmos_maps_from_files(tmp_path, maps, suffix):
    files = {k: _save_map(tmp_path / f"{k}{suffix}", v) for k, v in maps.items()}
    cam = Camera.from_map_files(qe=0.8, **files)
    assert cam.kind == "scmos" and cam.qe == 0.8 and cam.map_shape == SHAPE[1:]
    tol = 1e-6 if suffix == ".tif" else 0  # float32 in the TIFF
    np.testing.assert_allclose(cam.offset_map, maps["offset"], rtol=tol)
    np.testing.assert_allclose(cam.variance_map, maps["variance"], rtol=tol)
    np.testing.assert_allclose(cam.gain_map, maps["gain"], rtol=tol)


def test_some_maps_and_scalars(tmp_path, maps):
    off = _save_map(tmp_path / "off.npy", maps["offset"])
    cam = Camera.from_map_files(offset=str(off), gain=2.0)
    assert cam.gain == 2.0 and cam.gain_map is None and cam.variance_map is None
    np.testing.assert_array_equal(cam.offset_map, maps["offset"])
    cam = Camera.from_map_files(gain=maps["gain"], offset=100)
    assert cam.offset == 100.0
    np.testing.assert_array_equal(cam.gain_map, maps["gain"])


def test_map_stack_of_one_is_accepted(tmp_path, maps):
    path = tmp_path / "off.tif"
    tifffile.imwrite(path, maps["offset"][None].astype(np.float32))
    assert Camera.from_map_files(offset=path).map_shape == SHAPE[1:]


def test_map_errors(tmp_path, maps):
    off = _save_map(tmp_path / "off.npy", maps["offset"])
    small = _save_map(tmp_path / "gain.csv", maps["gain"][:5])
    with pytest.raises(ValueError, match=r"differ in shape: offset '.*off\.npy' is 9 x 11.*5 x 11"):
        Camera.from_map_files(offset=off, gain=small)
    with pytest.raises(ValueError, match=r"offset map file '.*missing\.npy' does not exist"):
        Camera.from_map_files(offset=tmp_path / "missing.npy")
    with pytest.raises(ValueError, match=r"unsupported type '\.mat'"):
        Camera.from_map_files(offset=tmp_path / "off.mat")
    line = _save_map(tmp_path / "line.npy", maps["offset"][0])
    with pytest.raises(
        ValueError, match=r"must be one 2-D \(rows, cols\) image, got shape \(11,\)"
    ):
        Camera.from_map_files(offset=line)
    stack = tmp_path / "three.tif"
    tifffile.imwrite(
        stack, np.stack([maps["offset"]] * 3).astype(np.float32), photometric="minisblack"
    )
    with pytest.raises(ValueError, match=r"got shape \(3, 9, 11\)"):
        Camera.from_map_files(offset=stack)
    nan = maps["variance"].copy()
    nan[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"variance map '.*nan\.npy' holds NaN"):
        Camera.from_map_files(variance=_save_map(tmp_path / "nan.npy", nan))
    pickled = tmp_path / "obj.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"offset map file '.*obj\.npy' could not be read"):
        Camera.from_map_files(offset=pickled)
    (tmp_path / "head.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"head\.csv' could not be read"):
        Camera.from_map_files(gain=tmp_path / "head.csv")
    with pytest.raises(ValueError, match="at least one map"):
        Camera.from_map_files(offset=100.0)
    with pytest.raises(ValueError, match="only allowed with kind='scmos'"):
        Camera.from_map_files(kind="emccd", offset=off)
    with pytest.raises(ValueError, match="not offset_map"):
        Camera.from_map_files(offset_map=maps["offset"])


def test_camera_maps_must_fit_the_movie(tmp_path, data, maps):
    write_tiff(tmp_path / "a.tif", data)
    cam = Camera.from_map_files(offset=_save_map(tmp_path / "o.npy", maps["offset"][:, :10]))
    with Movie.open(tmp_path / "a.tif") as m:
        with pytest.raises(ValueError, match=r"camera maps are 9 x 10 pixels but the movie "):
            check_camera_for_movie(cam, m)
        with pytest.raises(ValueError, match="camera maps are 9 x 10"):
            photon_frames(m, cam, 0, 2)
    check_camera_for_movie(cam, (100, 9, 10))
    check_camera_for_movie(Camera(), (9, 10))  # no maps: any shape


def test_photon_frames_apply_maps_per_pixel(tmp_path, data, maps):
    write_tiff(tmp_path / "a.tif", data)
    files = {k: _save_map(tmp_path / f"{k}.npy", v) for k, v in maps.items()}
    cam = Camera.from_map_files(qe=0.9, **files)
    with Movie.open(tmp_path / "a.tif") as m:
        got = photon_frames(m, cam, 2, 6)
        whole = photon_frames(m, cam)
    expected = (data[2:6].astype(np.float64) - maps["offset"]) * maps["gain"] / 0.9
    assert got.dtype == np.float64 and got.shape == (4, *SHAPE[1:])
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    np.testing.assert_allclose(whole, to_photons(data, cam), rtol=1e-12)


def test_file_lists_whose_numbers_run_backwards():
    """A list in an alphabetical order (a shell's, by character codes or by a UTF-8 locale's
    collation, which ignores punctuation) whose names' numbers run another way is named; a
    list in the numbers' order, a name without a number before the numbered ones, and a
    deliberate order are not."""
    from sparseloc.io.movie import out_of_number_order

    codes = [f"plain_{k}.tif" for k in (0, 1, 10, 11, 2, 3)]
    locale = [f"plain_{k}.tif" for k in (0, 10, 11, 1, 2, 3)]
    assert out_of_number_order(codes) == ("plain_10.tif", "plain_2.tif")
    assert out_of_number_order(locale) == ("plain_10.tif", "plain_1.tif")
    assert out_of_number_order([f"plain_{k}.tif" for k in range(12)]) is None
    assert out_of_number_order(["movie.tif", "movie1.tif", "movie2.tif"]) is None
    assert out_of_number_order(["b_2.tif", "a_10.tif"]) is None  # not alphabetical: chosen
    assert out_of_number_order(["run10/movie.tif", "run2/movie.tif"]) == (
        "run10/movie.tif",
        "run2/movie.tif",
    )
