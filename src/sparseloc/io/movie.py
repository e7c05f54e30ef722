"""Lazily read camera movies: TIFF, ImageJ hyperstack and OME-TIFF files, one or several.

A :class:`Movie` is a read-only view of a stack of camera frames, shape ``(frames, rows, cols)``
in ADU, that reads from disk only the frames asked for, so memory stays bounded whatever the
length of the movie. Several files (e.g. a recording split at 4 GB) form one series in the
order given.

Two ways of reading are used, chosen per file when it is opened:

- **contiguous**: uncompressed data stored in one block (what ImageJ, tifffile and most
  acquisition programs write; also ImageJ files over 4 GB that keep only the first IFD). A range
  of frames is one seek and one read, straight into the output array.
- **pages**: anything else (compressed, tiled or scattered pages); one TIFF page per frame,
  decoded by tifffile.

Every problem with an input file ends in a ``ValueError`` of one sentence that names the file:
missing, empty, not a TIFF, truncated or corrupt (detected when opening where the file is too
short for the frames it declares, otherwise when the damaged frame is read), RGB or several
channels, floating-point data where integer camera counts are expected, or frames that differ
in shape or type across the files of a series.

Examples
--------
>>> with Movie.open("data/run_*.tif") as movie:  # doctest: +SKIP
...     for start, chunk in movie.iter_chunks(500):
...         photons = to_photons(chunk, camera)
"""

from __future__ import annotations

import collections
import contextlib
import glob
import logging
import math
import os
import re
import struct
import threading
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from ..camera import Camera, to_photons

__all__ = ["Movie", "check_camera_for_movie", "photon_frames"]

log = logging.getLogger(__name__)

PathLike = str | os.PathLike[str]

#: At most this many files of a series are held open at once (a series may have thousands).
_MAX_OPEN_FILES = 8

_GLOB_CHARS = re.compile(r"[*?\[]")

# What tifffile logs when the page chain or the layout description of a file is damaged (it
# then goes on with fewer pages, or another layout, without raising).
_FATAL_MESSAGE = re.compile(
    r"corrupt|truncat|failed to reshape|circular reference"
    r"|invalid (page offset|offset to (first )?page|value offset)",
    re.IGNORECASE,
)

# Length units of ImageJ and OME metadata, in nm.
_UNITS_NM = {
    "nm": 1.0,
    "nanometer": 1.0,
    "nanometers": 1.0,
    "nanometre": 1.0,
    "µm": 1e3,
    "μm": 1e3,
    "um": 1e3,
    "\\u00b5m": 1e3,
    "micron": 1e3,
    "microns": 1e3,
    "micrometer": 1e3,
    "micrometers": 1e3,
    "micrometre": 1e3,
    "mm": 1e6,
    "millimeter": 1e6,
    "cm": 1e7,
    "centimeter": 1e7,
    "m": 1e9,
    "meter": 1e9,
    "å": 0.1,
    "angstrom": 0.1,
    "pm": 1e-3,
}


def _q(path: Path) -> str:
    return repr(str(path))


def _natural_key(path: str) -> tuple[list[Any], str]:
    """Sort key that orders ``run_2`` before ``run_10``, and ``movie.tif`` before
    ``movie1.tif`` (the name without its suffix first)."""
    stem, suffix = os.path.splitext(path)
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", stem)], suffix


def _collated(name: str) -> str:
    """A locale's collation key, roughly: case and punctuation ignored (how a shell with a
    UTF-8 locale orders an expanded pattern: ``plain_10`` before ``plain_1``)."""
    return re.sub(r"[^0-9a-z]", "", name.lower())


def out_of_number_order(paths: Sequence[PathLike]) -> tuple[str, str] | None:
    """Two of ``paths`` (a series' files in the order given) whose numbers run backwards
    where the order is an alphabetical one (``run_10`` before ``run_2``: a shell's expansion
    of an unquoted pattern over unpadded numbers, by character codes or by a locale's
    collation), the later-numbered first; None where the order is the names' natural order,
    or not alphabetical (a deliberate order)."""
    names = [os.fspath(x) for x in paths]
    if len(names) < 2 or names not in (sorted(names), sorted(names, key=_collated)):
        return None
    natural = sorted(names, key=_natural_key)
    if natural == names:
        return None
    i = next(k for k in range(len(names)) if names[k] != natural[k])
    return names[i], natural[i]


def _expand_paths(paths: PathLike | Sequence[PathLike]) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        text = os.fspath(paths)
        if _GLOB_CHARS.search(text) and not os.path.exists(text):
            found = [p for p in glob.glob(text) if not os.path.isdir(p)]
            if not found:
                raise ValueError(f"the pattern {text!r} matches no files")
            return [Path(p) for p in sorted(found, key=_natural_key)]
        return [Path(text)]
    try:
        items = list(paths)
    except TypeError:
        raise ValueError(
            f"paths must be a file name, a glob pattern or a sequence of file names, "
            f"got {type(paths).__name__}"
        ) from None
    if not items:
        raise ValueError("no movie files given")
    out = []
    for item in items:
        if not isinstance(item, (str, os.PathLike)):
            raise ValueError(f"movie file names must be str or Path, got {type(item).__name__}")
        out.append(Path(item))
    return out


@contextlib.contextmanager
def _tifffile_messages() -> Iterator[list[str]]:
    """Collect (and keep off the console) what tifffile logs; corrupt files make it chatty."""
    messages: list[str] = []

    def _keep(record: logging.LogRecord) -> bool:
        messages.append(record.getMessage())
        return False

    logger = logging.getLogger("tifffile")
    logger.addFilter(_keep)
    try:
        yield messages
    finally:
        logger.removeFilter(_keep)


def _clean(message: str) -> str:
    """A tifffile log message without its ``<tifffile.Class @offset>`` prefix."""
    return re.sub(r"^<[^>]*>\s*", "", message.strip()).splitlines()[0] if message.strip() else ""


def _detail(exc: BaseException, messages: Sequence[str] = ()) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if messages:
        text += f"; tifffile: {_clean(messages[0])}"
    return text


def _corrupt(path: Path, what: str) -> ValueError:
    return ValueError(f"{_q(path)} is truncated or corrupt: {what}")


def _to_nm(value: Any, unit: Any) -> float | None:
    try:
        size = float(value)
    except (TypeError, ValueError):
        return None
    factor = _UNITS_NM.get(str(unit).strip().lower()) if unit is not None else None
    if factor is None or not (math.isfinite(size) and size > 0):
        return None
    return size * factor


def _ome_pixel_size(xml: str) -> float | None:
    try:
        root = ET.fromstring(xml)
    except ET.ParseError:
        return None
    for elem in root.iter():
        if elem.tag == "Pixels" or elem.tag.endswith("}Pixels"):
            value = elem.get("PhysicalSizeX")
            if value is None:
                return None
            return _to_nm(value, elem.get("PhysicalSizeXUnit", "µm"))
    return None


def _imagej_pixel_size(tif: tifffile.TiffFile) -> float | None:
    ij = tif.imagej_metadata or {}
    if "pixel_size_nm" in ij:  # written by sparseloc.io.tiff.write_tiff
        return _to_nm(ij["pixel_size_nm"], "nm")
    unit = ij.get("unit")
    if unit is None:
        return None
    tag = tif.pages[0].tags.get("XResolution")
    if tag is None:
        return None
    num, den = tag.value
    if not num:
        return None
    return _to_nm(den / num, unit)  # XResolution is pixels per unit


@dataclass
class _Source:
    """One file of a movie: where its frames are and how to read them."""

    path: Path
    n_frames: int
    shape: tuple[int, int]
    dtype: np.dtype[Any]
    pixel_size: float | None
    size: int  # file size in bytes when opened
    contiguous_offset: int | None  # byte offset of frame 0 when stored as one block
    file_dtype: np.dtype[Any]  # dtype with the file's byte order
    top_level_pages: bool  # frames are the file's pages, not those of its first series

    @property
    def frame_bytes(self) -> int:
        return self.shape[0] * self.shape[1] * self.file_dtype.itemsize


def _analyse(path: Path, tif: tifffile.TiffFile, allow_float: bool, size: int) -> _Source:
    """Check one opened TIFF file and find its frames."""
    n_pages = len(tif.pages)  # follows the whole chain of IFDs: a cut one makes tifffile log
    all_series = tif.series
    if not n_pages or not all_series:
        raise _corrupt(path, "no image was found in it")
    _check_last_ifd(path, tif, n_pages, size)
    series = all_series[0]
    top_level = False
    if (
        len(all_series) > 1
        and series.ndim == 2
        and len(all_series) == n_pages
        and all(s.shape == series.shape and s.dtype == series.dtype for s in all_series)
    ):
        # One series per page (e.g. pages written one by one with their own description).
        top_level = True
    keyframe = series.keyframe
    n_series = len(all_series) if top_level else 1
    n_frames, rows, cols = _frame_layout(path, series, keyframe, n_series)
    dtype = _camera_dtype(path, series, allow_float)
    file_dtype = dtype.newbyteorder(tif.byteorder)
    pixel_size = _file_pixel_size(tif)
    if tif.is_imagej and not top_level:
        declared = (tif.imagej_metadata or {}).get("images")
        if isinstance(declared, int) and declared > n_frames:
            raise _corrupt(
                path, f"its ImageJ header declares {declared} images but only {n_frames} were found"
            )

    source = _Source(
        path=path,
        n_frames=n_frames,
        shape=(rows, cols),
        dtype=dtype.newbyteorder("="),
        pixel_size=pixel_size,
        size=size,
        contiguous_offset=None,
        file_dtype=file_dtype,
        top_level_pages=top_level,
    )
    if (
        not top_level
        and series.dataoffset is not None
        and keyframe.compression == 1
        and keyframe.bitspersample == 8 * dtype.itemsize
        and keyframe.fillorder == 1
    ):
        source.contiguous_offset = int(series.dataoffset)
        need = source.contiguous_offset + n_frames * source.frame_bytes
        if need > size:
            raise _corrupt(
                path,
                f"its {n_frames} frames of {rows} x {cols} {dtype} need {need} bytes but the "
                f"file has only {size}",
            )
        return source
    pages = tif.pages if top_level else series.pages
    if len(pages) != n_frames:
        raise ValueError(
            f"{_q(path)} cannot be read frame by frame: {n_frames} frames in {len(pages)} pages"
        )
    _check_page(source, pages[n_frames - 1], n_frames - 1)
    return source


def _frame_layout(path: Path, series: Any, keyframe: Any, n_series: int) -> tuple[int, int, int]:
    """Frames, rows and cols of ``n_series`` series like ``series``: one stack of grey
    (rows, cols) frames, else ``ValueError`` saying what the file holds instead."""
    axes, shape = series.axes, tuple(series.shape)
    if keyframe.samplesperpixel > 1 or "S" in axes:
        raise ValueError(
            f"{_q(path)} holds RGB or multi-sample pixels ({keyframe.samplesperpixel} values "
            f"per pixel, shape {shape}, axes {axes}); expected one grey value per pixel"
        )
    if len(shape) < 2 or axes[-2:] != "YX" or keyframe.imagedepth > 1:
        raise ValueError(
            f"{_q(path)} holds images of shape {shape} (axes {axes}); expected (rows, cols) frames"
        )
    lead = dict(zip(axes[:-2], shape[:-2], strict=True))
    several = [f"{a}={n}" for a, n in lead.items() if n > 1]
    if len(several) > 1:
        hint = "; split the channels first" if lead.get("C", 1) > 1 else ""
        raise ValueError(
            f"{_q(path)} has several frame axes ({', '.join(several)}; shape {shape}, axes "
            f"{axes}); expected one stack of (rows, cols) frames{hint}"
        )
    n_frames = math.prod(shape[:-2]) * n_series
    rows, cols = int(shape[-2]), int(shape[-1])
    if n_frames == 0 or rows == 0 or cols == 0:
        raise ValueError(f"{_q(path)} holds no frames (shape {shape})")
    return n_frames, rows, cols


def _camera_dtype(path: Path, series: Any, allow_float: bool) -> np.dtype[Any]:
    """The series' dtype: integer camera counts, or floats when ``allow_float``."""
    dtype = np.dtype(series.dtype)
    if dtype.kind == "f":
        if not allow_float:
            raise ValueError(
                f"{_q(path)} holds floating-point data ({dtype}) where integer camera counts "
                "(ADU) are expected; convert it to the camera's integer counts"
            )
    elif dtype.kind not in "iu":
        raise ValueError(f"{_q(path)} holds {dtype} data; expected integer camera counts (ADU)")
    return dtype


def _file_pixel_size(tif: tifffile.TiffFile) -> float | None:
    """Pixel size (nm) from the OME metadata, else the ImageJ metadata; None when absent."""
    pixel_size = None
    if tif.is_ome and tif.ome_metadata:
        pixel_size = _ome_pixel_size(tif.ome_metadata)
    if pixel_size is None and tif.is_imagej:
        pixel_size = _imagej_pixel_size(tif)
    return pixel_size


def _check_last_ifd(path: Path, tif: tifffile.TiffFile, n_pages: int, size: int) -> None:
    """Raise if the last image file directory (IFD) of the file is cut off."""
    fmt = tif.tiff
    offset = int(tif.pages[n_pages - 1].offset)
    fh = tif.filehandle
    fh.seek(offset)
    raw = fh.read(fmt.tagnosize)
    if len(raw) < fmt.tagnosize:
        raise _corrupt(path, f"its last image directory (IFD {n_pages - 1}) is cut off")
    n_tags = struct.unpack(fmt.tagnoformat, raw)[0]
    end = offset + fmt.tagnosize + n_tags * fmt.tagsize + fmt.offsetsize
    if end > size:
        raise _corrupt(path, f"its last image directory (IFD {n_pages - 1}) is cut off")


def _check_page(source: _Source, page: Any, index: int) -> None:
    """Raise if the data of one page lie beyond the end of the file."""
    if page is None:
        raise _corrupt(source.path, f"frame {index} has no image data")
    offsets, counts = page.dataoffsets, page.databytecounts
    if not offsets or any(o + c > source.size for o, c in zip(offsets, counts, strict=False)):
        raise _corrupt(source.path, f"the data of frame {index} lie beyond the end of the file")


def _probe(path: Path, allow_float: bool) -> tuple[_Source, tifffile.TiffFile]:
    """Open one file, check it and describe its frames; the open TiffFile is returned too."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise ValueError(f"the movie file {_q(path)} does not exist") from None
    except OSError as exc:
        raise ValueError(f"the movie file {_q(path)} cannot be read ({_detail(exc)})") from exc
    if path.is_dir():
        raise ValueError(f"{_q(path)} is a folder, not a TIFF file")
    if st.st_size == 0:
        raise ValueError(f"the movie file {_q(path)} is empty (0 bytes)")
    with _tifffile_messages() as messages:
        try:
            tif = tifffile.TiffFile(path)
        except PermissionError as exc:
            raise ValueError(f"the movie file {_q(path)} cannot be read ({exc.strerror})") from exc
        except Exception as exc:  # tifffile raises many types for a damaged file
            raise ValueError(
                f"{_q(path)} is not a TIFF file, or is truncated or corrupt "
                f"({_detail(exc, messages)})"
            ) from exc
        try:
            source = _analyse(path, tif, allow_float, st.st_size)
        except Exception as exc:
            tif.close()
            fatal = [m for m in messages if _FATAL_MESSAGE.search(m)]
            if fatal:  # damage explains whatever else looks wrong
                raise _corrupt(path, _clean(fatal[0])) from exc
            if isinstance(exc, ValueError) and str(exc).startswith(_q(path)):  # ours
                raise
            raise _corrupt(path, _detail(exc, messages)) from exc
    fatal = [m for m in messages if _FATAL_MESSAGE.search(m)]
    if fatal:
        tif.close()
        raise _corrupt(path, _clean(fatal[0]))
    for message in messages:
        log.warning("%s: %s", path, _clean(message))
    return source, tif


class _Reader:
    """An open file of a movie: a raw file for contiguous data, else a TiffFile."""

    def __init__(self, source: _Source, tif: tifffile.TiffFile | None = None) -> None:
        self.source = source
        self._raw: IO[bytes] | None = None
        self._tif: tifffile.TiffFile | None = None
        self._pages: Any = None
        try:
            size = source.path.stat().st_size
        except OSError as exc:
            if tif is not None:
                tif.close()
            raise ValueError(
                f"the movie file {_q(source.path)} can no longer be read ({_detail(exc)})"
            ) from exc
        if size != source.size:
            if tif is not None:
                tif.close()
            raise ValueError(
                f"the movie file {_q(source.path)} changed since it was opened "
                f"({source.size} bytes then, {size} now)"
            )
        if source.contiguous_offset is not None:
            if tif is not None:
                tif.close()
            self._raw = open(source.path, "rb")  # closed in close()
            return
        if tif is None:
            with _tifffile_messages() as messages:
                try:
                    tif = tifffile.TiffFile(source.path)
                except Exception as exc:
                    raise _corrupt(source.path, _detail(exc, messages)) from exc
        self._tif = tif
        self._pages = tif.pages if source.top_level_pages else tif.series[0].pages

    def read(self, start: int, stop: int, out: NDArray[Any]) -> None:
        """Read frames ``start:stop`` of this file into ``out`` (``stop - start`` frames)."""
        src = self.source
        if self._raw is not None:
            assert src.contiguous_offset is not None
            self._raw.seek(src.contiguous_offset + start * src.frame_bytes)
            if src.file_dtype == out.dtype:
                buf = memoryview(out).cast("B")
                got = self._raw.readinto(buf)
                if got != len(buf):
                    raise _corrupt(src.path, f"frames {start}..{stop - 1} end early")
            else:
                data = np.fromfile(self._raw, dtype=src.file_dtype, count=out.size)
                if data.size != out.size:
                    raise _corrupt(src.path, f"frames {start}..{stop - 1} end early")
                out[...] = data.reshape(out.shape)
            return
        with _tifffile_messages() as messages:
            for k, index in enumerate(range(start, stop)):
                try:
                    page = self._pages[index]
                    _check_page(src, page, index)
                    frame = page.asarray()
                except ValueError as exc:
                    if str(exc).startswith(_q(src.path)):
                        raise
                    raise _corrupt(
                        src.path, f"frame {index} cannot be read ({_detail(exc, messages)})"
                    ) from exc
                except Exception as exc:
                    raise _corrupt(
                        src.path, f"frame {index} cannot be read ({_detail(exc, messages)})"
                    ) from exc
                if frame.shape != src.shape:
                    raise _corrupt(
                        src.path, f"frame {index} has shape {frame.shape}, not {src.shape}"
                    )
                out[k] = frame

    def close(self) -> None:
        if self._raw is not None:
            self._raw.close()
            self._raw = None
        if self._tif is not None:
            self._tif.close()
            self._tif = None
            self._pages = None


def _reopen(paths: tuple[Path, ...], allow_float: bool) -> Movie:
    return Movie.open(paths, allow_float=allow_float)


class Movie:
    """A camera movie, shape (frames, rows, cols), read lazily from one or more TIFF files.

    Create it with :meth:`Movie.open`. Frames are read from disk only when asked for
    (:meth:`frames`, indexing, :meth:`iter_chunks`), so memory stays bounded whatever the
    length of the movie. Reading is thread-safe (reads are serialised). Close the movie with
    :meth:`close` or use it as a context manager. A movie can be pickled (it reopens its files
    on unpickling), e.g. to send it to Dask workers.

    Attributes
    ----------
    n_frames : int
        Number of frames over all files.
    shape : tuple of int
        Frame shape ``(rows, cols)`` in pixels.
    dtype : numpy.dtype
        Data type of the frames (camera counts, ADU), native byte order.
    pixel_size : float or None
        Pixel size in nm from the OME or ImageJ metadata of the files, or None when absent.
    paths : tuple of Path
        The files of the series, in order.
    """

    def __init__(self, sources: Sequence[_Source], *, allow_float: bool = False) -> None:
        if not sources:
            raise ValueError("a movie needs at least one file")
        self._sources = tuple(sources)
        self._allow_float = allow_float
        self._starts = np.cumsum([0] + [s.n_frames for s in self._sources])
        self._readers: collections.OrderedDict[int, _Reader] = collections.OrderedDict()
        self._lock = threading.RLock()
        self._closed = False

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def open(cls, paths: PathLike | Sequence[PathLike], *, allow_float: bool = False) -> Movie:
        """Open a movie without reading its frames.

        Parameters
        ----------
        paths : str or Path or sequence of them
            One TIFF / ImageJ / OME-TIFF file; a glob pattern such as ``"data/run_*.tif"``
            (expanded in natural order: ``run_2`` before ``run_10``); or several files that
            form one series, in the order given. A single 2-D image is a one-frame movie.
        allow_float : bool
            Accept floating-point data (e.g. movies already in photons). By default only
            integer camera counts are accepted.

        Returns
        -------
        Movie

        Raises
        ------
        ValueError
            If a file is missing, empty, not a readable TIFF, truncated or corrupt, holds RGB
            or multi-channel images or floating-point data (unless ``allow_float``), or if the
            files of a series differ in frame shape, dtype or pixel size.
        """
        files = _expand_paths(paths)
        sources: list[_Source] = []
        tifs: list[tifffile.TiffFile] = []  # the first few files stay open (already parsed)
        try:
            for path in files:
                source, tif = _probe(path, allow_float)
                sources.append(source)
                if len(tifs) < _MAX_OPEN_FILES:
                    tifs.append(tif)
                else:
                    tif.close()
                first = sources[0]
                if source.shape != first.shape:
                    raise ValueError(
                        f"the frames of {_q(path)} are {source.shape[0]} x {source.shape[1]} "
                        f"pixels but those of {_q(first.path)} are "
                        f"{first.shape[0]} x {first.shape[1]}; the files of a series must match"
                    )
                if source.dtype != first.dtype:
                    raise ValueError(
                        f"{_q(path)} holds {source.dtype} data but {_q(first.path)} holds "
                        f"{first.dtype}; the files of a series must match"
                    )
            sizes = [(s.pixel_size, s.path) for s in sources if s.pixel_size is not None]
            for size, path in sizes[1:]:
                if not math.isclose(size, sizes[0][0], rel_tol=1e-6):
                    raise ValueError(
                        f"the pixel size of {_q(path)} ({size:g} nm) differs from that of "
                        f"{_q(sizes[0][1])} ({sizes[0][0]:g} nm)"
                    )
        except BaseException:
            for tif in tifs:
                tif.close()
            raise
        movie = cls(sources, allow_float=allow_float)
        try:
            for index, tif in enumerate(tifs):
                movie._readers[index] = _Reader(sources[index], tif)
        except BaseException:
            for tif in tifs[len(movie._readers) :]:
                tif.close()
            movie.close()
            raise
        return movie

    # -- properties -----------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of frames over all files."""
        return int(self._starts[-1])

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape ``(rows, cols)`` in pixels."""
        return self._sources[0].shape

    @property
    def dtype(self) -> np.dtype[Any]:
        """Data type of the frames, native byte order."""
        return self._sources[0].dtype

    @property
    def pixel_size(self) -> float | None:
        """Pixel size in nm from the file metadata, or None when no file records one."""
        for source in self._sources:
            if source.pixel_size is not None:
                return source.pixel_size
        return None

    @property
    def paths(self) -> tuple[Path, ...]:
        """The files of the series, in order."""
        return tuple(s.path for s in self._sources)

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has been called."""
        return self._closed

    def __len__(self) -> int:
        return self.n_frames

    def __repr__(self) -> str:
        px = "unknown" if self.pixel_size is None else f"{self.pixel_size:g} nm"
        files = "1 file" if len(self._sources) == 1 else f"{len(self._sources)} files"
        state = ", closed" if self._closed else ""
        return (
            f"Movie({files}, {self.n_frames} frame{'' if self.n_frames == 1 else 's'} of "
            f"{self.shape[0]} x {self.shape[1]} {self.dtype}, pixel size {px}{state})"
        )

    # -- reading --------------------------------------------------------------------------
    def _reader(self, index: int) -> _Reader:
        reader = self._readers.get(index)
        if reader is not None:
            self._readers.move_to_end(index)
            return reader
        reader = _Reader(self._sources[index])
        self._readers[index] = reader
        while len(self._readers) > _MAX_OPEN_FILES:
            _, oldest = self._readers.popitem(last=False)
            oldest.close()
        return reader

    def frames(self, start: int = 0, stop: int | None = None) -> NDArray[Any]:
        """Read frames ``start`` to ``stop - 1``.

        Parameters
        ----------
        start : int
            First frame (0-based), ``0 <= start <= n_frames``.
        stop : int, optional
            One past the last frame, ``start <= stop <= n_frames``; default ``n_frames``.

        Returns
        -------
        ndarray, shape (stop - start, rows, cols)
            Camera counts (ADU) in :attr:`dtype`; a new array owned by the caller.

        Raises
        ------
        ValueError
            If the range is outside the movie, the movie is closed, or a file turns out to be
            truncated or corrupt.
        """
        n = self.n_frames
        stop = n if stop is None else stop
        if not all(isinstance(v, (int, np.integer)) for v in (start, stop)):
            raise ValueError(f"start and stop must be integers, got {start!r} and {stop!r}")
        start, stop = int(start), int(stop)
        if not 0 <= start <= stop <= n:
            raise ValueError(
                f"frames {start}..{stop} are outside the movie of {n} frames "
                f"(need 0 <= start <= stop <= {n})"
            )
        out = np.empty((stop - start, *self.shape), dtype=self.dtype)
        if stop == start:
            return out
        with self._lock:
            if self._closed:
                raise ValueError("the movie is closed")
            first = int(np.searchsorted(self._starts, start, side="right")) - 1
            for index in range(first, len(self._sources)):
                file_start = int(self._starts[index])
                lo = max(start, file_start)
                hi = min(stop, int(self._starts[index + 1]))
                if lo >= stop:
                    break
                if hi > lo:
                    self._reader(index).read(
                        lo - file_start, hi - file_start, out[lo - start : hi - start]
                    )
        return out

    def __getitem__(self, key: int | slice) -> NDArray[Any]:
        """``movie[i]`` is frame ``i`` (rows, cols); ``movie[a:b]`` is (frames, rows, cols).

        Negative indices count from the end; slices must have step 1.
        """
        if isinstance(key, (int, np.integer)):
            i = int(key)
            if i < 0:
                i += self.n_frames
            if not 0 <= i < self.n_frames:
                raise IndexError(f"frame {int(key)} is outside the movie of {self.n_frames} frames")
            return self.frames(i, i + 1)[0]
        if isinstance(key, slice):
            if key.step not in (None, 1):
                raise ValueError(f"only slices with step 1 are supported, got step {key.step}")
            start, stop, _ = key.indices(self.n_frames)
            return self.frames(start, max(start, stop))
        raise TypeError(f"a movie is indexed by an int or a slice, got {type(key).__name__}")

    def __iter__(self) -> Iterator[NDArray[Any]]:
        """Frames one at a time, each (rows, cols)."""
        for i in range(self.n_frames):
            yield self[i]

    def iter_chunks(
        self, chunk_frames: int, start: int = 0, stop: int | None = None
    ) -> Iterator[tuple[int, NDArray[Any]]]:
        """Read the movie in consecutive chunks of frames.

        Parameters
        ----------
        chunk_frames : int
            Frames per chunk (>= 1); the last chunk may be shorter.
        start, stop : int, optional
            Range of frames to cover (default: the whole movie).

        Yields
        ------
        first : int
            Index of the chunk's first frame in the movie.
        chunk : ndarray, shape (<= chunk_frames, rows, cols)
            Camera counts (ADU).
        """
        if (
            not isinstance(chunk_frames, (int, np.integer))
            or isinstance(chunk_frames, bool)
            or chunk_frames < 1
        ):
            raise ValueError(f"chunk_frames must be a positive integer, got {chunk_frames!r}")
        stop = self.n_frames if stop is None else stop
        if not 0 <= start <= stop <= self.n_frames:
            raise ValueError(
                f"frames {start}..{stop} are outside the movie of {self.n_frames} frames"
            )
        for first in range(start, stop, int(chunk_frames)):
            yield first, self.frames(first, min(first + int(chunk_frames), stop))

    # -- lifetime -------------------------------------------------------------------------
    def close(self) -> None:
        """Close every open file; further reads raise ``ValueError``. Safe to call twice."""
        with self._lock:
            self._closed = True
            while self._readers:
                _, reader = self._readers.popitem()
                reader.close()

    def __enter__(self) -> Movie:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def __reduce__(self) -> tuple[Any, ...]:
        return (_reopen, (self.paths, self._allow_float))


def check_camera_for_movie(camera: Camera, movie_shape: Movie | Sequence[int]) -> None:
    """Check that a camera's sCMOS maps fit the frames of a movie.

    Parameters
    ----------
    camera : Camera
        Camera model; cameras without per-pixel maps fit any movie.
    movie_shape : Movie or sequence of int
        A movie, or its frame shape ``(rows, cols)`` or ``(frames, rows, cols)``.

    Raises
    ------
    ValueError
        If the maps' (rows, cols) differ from the frames'.
    """
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
    shape = movie_shape.shape if isinstance(movie_shape, Movie) else tuple(movie_shape)
    if len(shape) < 2:
        raise ValueError(f"a movie frame shape needs (rows, cols), got {tuple(shape)}")
    frame = (int(shape[-2]), int(shape[-1]))
    maps = camera.map_shape
    if maps is not None and tuple(maps) != frame:
        raise ValueError(
            f"the camera maps are {maps[0]} x {maps[1]} pixels but the movie frames are "
            f"{frame[0]} x {frame[1]}; use maps of the same sensor region"
        )


def photon_frames(
    movie: Movie, camera: Camera, start: int = 0, stop: int | None = None
) -> NDArray[np.float64]:
    """Read frames of a movie and convert them to photons.

    Parameters
    ----------
    movie : Movie
        Camera movie in ADU.
    camera : Camera
        Camera model; sCMOS maps are applied per pixel
        (``photons = (ADU - offset) * gain / em_gain / qe``).
    start, stop : int, optional
        Frames ``start`` to ``stop - 1`` (default: the whole movie).

    Returns
    -------
    ndarray of float64, shape (stop - start, rows, cols)
        Photons per pixel.

    Raises
    ------
    ValueError
        If the camera maps do not fit the movie's frames, or as :meth:`Movie.frames`.
    """
    check_camera_for_movie(camera, movie)
    return to_photons(movie.frames(start, stop), camera)
