"""Chunked, resumable localization of long movies, in-process or on a Dask cluster.

A run cuts the frame range into chunks of consecutive frames. Each chunk is one task: it
opens the movie itself (movies pickle as their file paths and read lazily), localizes its
frames with :func:`sparseloc.pipeline.localize` (reading the few frames around the chunk that
the temporal background needs) and returns its table part. The driver writes every part as
soon as it arrives, atomically, into a run folder::

    RUN/manifest.json                      what the run is: parameters, movie, chunks
    RUN/part-000000000-000000500.parquet   one per finished chunk (frames 0..499)

and at the end joins the parts, in frame order, into one table identical to a serial
:func:`localize` of the same frames (window ids renumbered over the movie), whatever the
scheduler and the chunk size.

Resuming: a run started again with the same folder and the same analysis skips the chunks
whose parts exist; a part exists only once complete (temporary name, then rename), so a
killed run never leaves a half part. A folder written by a different analysis (parameters,
PSF, movie, camera, frame range or chunk size) is refused unless ``overwrite``. A movie file
is known by its path, size, modification time and a hash of a sample of its content, so one
replaced by another of the same size and time (``cp -p``) is noticed. A folder that holds
files but no sparseloc manifest is refused even with ``overwrite``: its files are not the
run's to delete.

Faults: on a Dask cluster a chunk whose worker dies is re-run elsewhere by the scheduler,
and a chunk that raises is retried (``retries``); a chunk that still fails is reported with
its frame range while the other chunks go on, and the run ends without a joined table.

Schedulers: ``"sync"`` (this process, one chunk after another), ``"threads"`` (a thread
pool in this process), ``"processes"`` (a pool of worker processes of this machine,
:mod:`sparseloc.pool`: what ``localize --workers N`` uses, with no network port that other
local users could reach), a :class:`distributed.Client`, or a scheduler address
(``"tcp://host:8786"``) of a cluster the user runs. :func:`local_cluster` starts a
``LocalCluster`` of worker processes with one thread each, bound to this machine's loopback
address; it has no authentication, so any local user can submit code to it: local runs use
``"processes"`` instead.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from . import __version__
from .camera import Camera, saturation_level, to_photons
from .defects import replace_defects
from .digest import array_digest, psf_hash
from .io.atomic import write_text_atomic
from .io.tables import LOCS_COLUMNS, empty_locs, read_parquet, write_parquet
from .pipeline import (
    LocalizeParams,
    localize,
    run_checks,
    run_metadata,
    work_model_for,
)
from .psf.base import PSFModel

__all__ = [
    "CHUNK_FRAMES",
    "CameraFrames",
    "RunResult",
    "auto_chunk_frames",
    "join_parts",
    "local_cluster",
    "localize_chunked",
    "plan_chunks",
    "resumable_by_default",
]

logger = logging.getLogger(__name__)

#: Default frames per chunk: long enough that the per-task set-up (templates, FFT plans,
#: reading the background context) is a few per cent of the work, short enough that a lost
#: chunk costs little and a 10,000-frame movie still keeps 2-8 workers busy.
CHUNK_FRAMES = 500
#: Chunks per worker process in a run cut automatically: the workers finish together and the
#: progress bar moves, while each chunk's set-up stays a small part of its work.
AUTO_CHUNKS_PER_WORKER = 4
#: The smallest chunk of an automatic cut (frames).
MIN_AUTO_CHUNK = 50
MANIFEST = "manifest.json"
_PART = "part-{:09d}-{:09d}.parquet"
#: Blocks of a movie hashed to identify its content (evenly spaced, each file's first and last
#: included, shared out over a series' files): enough to tell two movies apart without
#: reading a long movie whole.
_SAMPLE_BLOCKS = 64
_SAMPLE_BYTES = 1 << 16


def _changed(old: Any, new: dict, prefix: str = "") -> list[str]:
    """The keys whose values differ between two run descriptions, nested ones named in full
    (``params.min_snr``): what a refused resume names."""
    out = []
    for k in sorted(set(new) | set(old if isinstance(old, dict) else {})):
        a = old.get(k) if isinstance(old, dict) else None
        b = new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _changed(a, b, f"{prefix}{k}.")
        elif json.dumps(a, default=str) != json.dumps(b, default=str):
            out.append(f"{prefix}{k}")
    return out


def _file_sample_digest(path: str | Path, blocks: int = _SAMPLE_BLOCKS) -> str:
    """SHA-256 (16 hex digits) of ``blocks`` evenly spaced 64 KiB blocks of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        last = max(size - _SAMPLE_BYTES, 0)
        for off in sorted({int(v) for v in np.linspace(0, last, max(blocks, 2))}):
            fh.seek(off)
            h.update(fh.read(_SAMPLE_BYTES))
    return h.hexdigest()[:16]


class CameraFrames:
    """Frames of a movie in photons, converted on demand (picklable when the movie is).

    Parameters
    ----------
    movie : Movie or ndarray, shape (n, rows, cols)
        Camera counts (a :class:`sparseloc.io.movie.Movie` reads lazily).
    camera : Camera, optional
        Conversion to photons; ``None`` when the frames already are photons.
    defects : ndarray of bool, shape (rows, cols), optional
        Defective pixels, each replaced in every frame by the median of its neighbours
        (:func:`sparseloc.defects.replace_defects`).
    saturation : float, optional
        ADU at which the camera saturates: a pixel at it is lifted to the level in photons
        that every saturated pixel reaches (:func:`sparseloc.camera.saturation_level`, where
        sCMOS maps give the pixels different levels), so that the run's one level
        (:attr:`~sparseloc.config.LocalizeParams.saturation`) finds each such pixel, and no
        other.
    """

    def __init__(
        self,
        movie: Any,
        camera: Camera | None = None,
        defects: NDArray[np.bool_] | None = None,
        saturation: float | None = None,
    ) -> None:
        self.movie, self.camera, self.defects = movie, camera, defects
        self.saturation = saturation

    def __len__(self) -> int:
        return len(self.movie)

    @property
    def shape(self) -> tuple[int, int]:
        s = self.movie.shape
        return (int(s[-2]), int(s[-1]))

    def frames(self, start: int, stop: int) -> NDArray[np.float64]:
        if hasattr(self.movie, "frames"):
            raw = self.movie.frames(start, stop)
        else:
            raw = np.asarray(self.movie[start:stop])
        if self.camera is None:
            photons = np.asarray(raw, dtype=np.float64)
        else:
            photons = to_photons(raw, self.camera)
            if self.saturation is not None:
                at = np.asarray(raw) >= self.saturation
                if at.any():
                    level = saturation_level(self.saturation, self.camera, self.shape)
                    photons = np.where(at, np.maximum(photons, level), photons)
        if self.defects is not None:
            photons = replace_defects(photons, self.defects)
        return photons

    def identity(self) -> dict:
        """What identifies the data for resuming: the source's own ``identity()``, its files
        (size, modification time, digest of a sample of the content) or a digest of an
        in-memory array."""
        paths = getattr(self.movie, "paths", None)
        own = getattr(self.movie, "identity", None)
        if callable(own):  # e.g. a SimulatedMovie: its generating parameters
            ident: dict[str, Any] = dict(own())
        elif paths:
            files = []
            blocks = _SAMPLE_BLOCKS // len(paths)
            for p in paths:
                st = os.stat(p)
                digest = _file_sample_digest(p, blocks)
                files.append([str(Path(p).resolve()), st.st_size, int(st.st_mtime), digest])
            ident = {"files": files}
        elif hasattr(self.movie, "frames"):
            raise ValueError(
                f"cannot tell whether a {type(self.movie).__name__} is the same data when a run "
                "resumes: give it file paths (.paths) or an identity() method"
            )
        else:
            ident = {"sha256": array_digest(np.asarray(self.movie))}
        ident["camera"] = self.camera.to_dict() if self.camera is not None else None
        if self.defects is not None:
            ident["defects"] = array_digest(np.packbits(self.defects))
        if self.saturation is not None:
            ident["saturation"] = float(self.saturation)
        return ident


@dataclass
class RunResult:
    """Outcome of :func:`localize_chunked`.

    Attributes
    ----------
    table : DataFrame or None
        The joined table when every chunk is done, else None.
    chunks : list of (int, int)
        All chunks ``(start, stop)`` (frames, stop exclusive).
    done_before : list of (int, int)
        Chunks already done when the run started (resumed).
    failed : dict
        ``(start, stop) -> error message`` for chunks that failed after their retries.
    seconds : float
        Wall time of this call.
    metadata : dict
        Analysis metadata (as :func:`localize` writes it), for the joined table.
    run_dir : Path
    """

    table: pd.DataFrame | None
    chunks: list[tuple[int, int]]
    done_before: list[tuple[int, int]]
    failed: dict[tuple[int, int], str]
    seconds: float
    metadata: dict
    run_dir: Path
    n_windows: int = 0
    missing: list[tuple[int, int]] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return self.table is not None

    def summary(self) -> str:
        """One paragraph: chunks done, resumed, failed (with their frame ranges)."""
        n = len(self.chunks)
        done = n - len(self.missing)
        parts = [f"{done} of {n} chunks done ({len(self.done_before)} from an earlier run)"]
        if self.table is not None:
            parts.append(f"{len(self.table):,} localizations in {self.seconds:.1f} s")
        for (a, b), msg in sorted(self.failed.items()):
            parts.append(f"frames {a}-{b - 1} failed: {msg}")
        if self.missing and not self.failed:
            parts.append("missing frames " + ", ".join(f"{a}-{b - 1}" for a, b in self.missing))
        return "; ".join(parts)


def plan_chunks(start: int, stop: int, chunk_frames: int) -> list[tuple[int, int]]:
    """Consecutive ``(start, stop)`` frame ranges of at most ``chunk_frames`` frames."""
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    if not 0 <= start < stop:
        raise ValueError(f"frame range {start}:{stop} is empty")
    return [(a, min(a + chunk_frames, stop)) for a in range(start, stop, chunk_frames)]


def resumable_by_default(n_frames: int) -> bool:
    """Whether ``localize`` runs ``n_frames`` frames chunked, in a run folder beside its output,
    without being asked: a run longer than one chunk, whose loss to an interruption costs."""
    return n_frames > CHUNK_FRAMES


def auto_chunk_frames(n_frames: int, workers: int) -> int:
    """Frames per chunk when the user chose none: equal chunks of at most
    :data:`CHUNK_FRAMES` (and at least :data:`MIN_AUTO_CHUNK`) frames, at least
    :data:`AUTO_CHUNKS_PER_WORKER` per worker and a multiple of ``workers`` in number."""
    workers = max(1, int(workers))
    k = max(-(-n_frames // CHUNK_FRAMES), AUTO_CHUNKS_PER_WORKER * workers)
    k = min(-(-k // workers) * workers, max(1, n_frames // MIN_AUTO_CHUNK))
    return max(1, -(-n_frames // max(k, 1)))


def _chunk_frames_of_run(run_dir: Path) -> int | None:
    """The chunk size of the run recorded in ``run_dir``'s manifest, if it holds one."""
    try:
        run = json.loads((run_dir / MANIFEST).read_text()).get("run", {})
        return int(run["chunk_frames"])
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None


def local_cluster(workers: int, **kwargs: Any):
    """A ``distributed.Client`` on a new ``LocalCluster``: ``workers`` processes, one thread
    each (the solvers run single-threaded BLAS; processes share out the cores)."""
    dask = _distributed()
    # Dask's scheduler and nannies log every start and stop at INFO: keep a user's terminal
    # for sparseloc's own messages unless they asked for detail.
    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        logging.getLogger("distributed").setLevel(logging.WARNING)
    kwargs.setdefault("silence_logs", logging.WARNING)
    kwargs.setdefault("threads_per_worker", 1)
    kwargs.setdefault("processes", True)
    kwargs.setdefault("dashboard_address", None)
    # Loopback only: no other machine can reach it (other local users still can).
    kwargs.setdefault("host", "127.0.0.1")
    cluster = dask.LocalCluster(n_workers=workers, **kwargs)
    return dask.Client(cluster)


def _distributed() -> Any:
    """The ``distributed`` package, or a ValueError that says how to install it."""
    try:
        import distributed
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ValueError(
            "Dask execution needs the 'dask' extra: pip install 'sparseloc[dask]'"
        ) from exc
    return distributed


def _solve_chunk(
    source: CameraFrames,
    work_model: PSFModel,
    params: LocalizeParams,
    start: int,
    stop: int,
    read_variance: NDArray | None,
) -> tuple[pd.DataFrame | None, int | str]:
    """One task: the table part of frames ``start..stop-1`` and its number of windows.

    Bad data (``ValueError``: NaN frames, unreadable values) gives ``(None, message)``
    instead of raising: running it again cannot help, so the cluster does not retry it.
    Other errors (a file system that failed to answer, a worker that died) raise and are
    retried.
    """
    try:
        res = localize(
            source,
            work_model,
            params,
            start=start,
            stop=stop,
            read_variance=read_variance,
            check=False,  # the whole run is checked once, on the joined table
        )
    except ValueError as exc:
        return None, str(exc)
    return res.table, res.n_windows


def _run_key(
    source: CameraFrames,
    model: PSFModel,
    params: LocalizeParams,
    frame_range: tuple[int, int],
    chunk_frames: int,
    read_variance: NDArray | None,
) -> tuple[str, dict]:
    data = source.identity()
    desc = {
        "params": asdict(params),
        "psf_hash": psf_hash(model, params.pixel_size),
        # the movie and the camera apart, so that a refusal names the one that changed
        "data": {k: v for k, v in data.items() if k != "camera"},
        "camera": data.get("camera"),
        "frames": list(frame_range),
        "chunk_frames": int(chunk_frames),
        "read_variance": None if read_variance is None else array_digest(read_variance),
    }
    text = json.dumps(desc, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20], desc


def _prepare_run_dir(run_dir: Path, key: str, desc: dict, chunks, overwrite: bool) -> None:
    if not run_dir.parent.is_dir():
        raise ValueError(f"the folder {str(run_dir.parent)!r} does not exist")
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"the run folder (--run-dir) {str(run_dir)!r} is a file, not a folder")
    man = run_dir / MANIFEST
    # A manifest's temporary file, left by a run killed while writing it, is the run's own.
    others = run_dir.is_dir() and not man.exists()
    if others and any(not p.name.startswith(f".{MANIFEST}.") for p in run_dir.iterdir()):
        raise ValueError(
            f"{str(run_dir)!r} holds files but no sparseloc run manifest; give an empty or "
            "new folder for the run's parts"
        )
    run_dir.mkdir(exist_ok=True)
    if man.exists():
        try:
            old = json.loads(man.read_text())
        except (ValueError, OSError) as exc:
            raise ValueError(f"cannot read {str(man)!r}: {exc}") from exc
        if not (isinstance(old, dict) and "key" in old and isinstance(old.get("run"), dict)):
            raise ValueError(
                f"{str(man)!r} is not a sparseloc run manifest, so the folder is not a "
                "sparseloc run's; give an empty or new folder for the run's parts"
            )
        if old.get("key") != key and not overwrite:
            changed = _changed(old.get("run", {}), desc)
            raise ValueError(
                f"the run folder {str(run_dir)!r} holds results of a different analysis "
                f"(changed: {', '.join(changed) or 'unknown'}); pass --overwrite to start over "
                "or choose another folder"
            )
    if overwrite or not man.exists():
        for p in run_dir.glob("part-*.parquet"):
            p.unlink()
    manifest = {
        "key": key,
        "sparseloc_version": __version__,
        "chunks": [list(c) for c in chunks],
        "run": desc,
    }
    write_text_atomic(man, json.dumps(manifest, indent=1, default=str))


def _part_path(run_dir: Path, chunk: tuple[int, int]) -> Path:
    return run_dir / _PART.format(*chunk)


def _write_part(run_dir: Path, chunk: tuple[int, int], table: pd.DataFrame, n_windows: int):
    write_parquet(
        table,
        _part_path(run_dir, chunk),
        metadata={"chunk": list(chunk), "n_windows": int(n_windows)},
    )


def join_parts(run_dir: str | Path, chunks: Sequence[tuple[int, int]]) -> tuple[pd.DataFrame, int]:
    """Join the parts of ``chunks`` (in order) into one table; window ids become unique over
    the movie, numbered as a serial run numbers them. Returns the table and its windows."""
    run_dir = Path(run_dir)
    tables, offset = [], 0
    for chunk in chunks:
        t, meta = read_parquet(_part_path(run_dir, chunk))
        t = t.copy()
        t["window_id"] = t["window_id"].to_numpy() + offset
        offset += int(meta["n_windows"])
        tables.append(t)
    nonempty = [t for t in tables if len(t)]
    if not nonempty:
        return empty_locs(), offset
    table = pd.concat(nonempty, ignore_index=True)
    return table[list(LOCS_COLUMNS)], offset


def localize_chunked(
    frames: CameraFrames | Any,
    model: PSFModel,
    params: LocalizeParams,
    run_dir: str | Path,
    *,
    start: int = 0,
    stop: int | None = None,
    chunk_frames: int | None = CHUNK_FRAMES,
    scheduler: Any = "sync",
    threads: int = 2,
    workers: int = 2,
    overwrite: bool = False,
    retries: int = 2,
    read_variance: NDArray | None = None,
    progress: Callable[[int], None] | None = None,
) -> RunResult:
    """Localize frames ``start..stop-1`` chunk by chunk into ``run_dir`` (see the module).

    Parameters
    ----------
    frames : CameraFrames, Movie or ndarray, shape (n, rows, cols)
        The movie in photons (wrap camera counts in :class:`CameraFrames`). On a cluster it
        is pickled into every task: a :class:`~sparseloc.io.movie.Movie` travels as its
        paths, which the workers must be able to read.
    model : PSFModel
        PSF model; tabulated once here (``params.tabulate``) and sent to every worker.
    params : LocalizeParams
        Analysis parameters (as for :func:`localize`).
    run_dir : str or Path
        Folder of the run's parts and manifest (created; its parent must exist).
    start, stop : int
        Frame range (stop exclusive; default the whole movie).
    chunk_frames : int or None
        Frames per task; ``None``: those of the run already in ``run_dir`` (so a rerun with
        other ``workers`` continues it), else :func:`auto_chunk_frames`.
    scheduler : "sync", "threads", "processes", distributed.Client or str
        Where the chunks run; a string other than "sync"/"threads"/"processes" is a
        scheduler address.
    threads : int
        Threads for ``scheduler="threads"``.
    workers : int
        Worker processes for ``scheduler="processes"``.
    overwrite : bool
        Discard the parts of a different earlier analysis in ``run_dir`` instead of refusing.
    retries : int
        Extra attempts of a failing chunk on a cluster.
    read_variance : ndarray, optional
        sCMOS read-variance map (photons^2), as for :func:`localize`.
    progress : callable, optional
        Called with the number of frames of every chunk finished.

    Returns
    -------
    RunResult

    Raises
    ------
    ValueError
        Bad parameters, an unusable run folder, or a folder of a different analysis.
    """
    t0 = time.perf_counter()
    source = frames if isinstance(frames, CameraFrames) else CameraFrames(frames)
    n = len(source)
    stop = n if stop is None else min(stop, n)
    run_dir = Path(run_dir)
    if chunk_frames is None:
        pool = workers if scheduler == "processes" else threads if scheduler == "threads" else 1
        chunk_frames = _chunk_frames_of_run(run_dir) or auto_chunk_frames(stop - start, pool)
    chunks = plan_chunks(start, stop, chunk_frames)
    key, desc = _run_key(source, model, params, (start, stop), chunk_frames, read_variance)
    work_model = work_model_for(model, params)  # refuses a bad z range before the folder
    created = not run_dir.exists()
    _prepare_run_dir(run_dir, key, desc, chunks, overwrite)
    done_before, todo = _done_and_todo(run_dir, chunks, chunk_frames, progress)
    writer = _PartWriter(run_dir, progress)
    if todo:
        args = (work_model, params)
        pool = workers if scheduler == "processes" else threads
        try:
            _run_chunks(scheduler, source, args, todo, read_variance, writer, pool, retries)
        except ValueError:
            # a run that could not start (an unreachable scheduler) leaves no folder it made
            if created and not any(run_dir.glob("part-*.parquet")):
                shutil.rmtree(run_dir, ignore_errors=True)
            raise
    meta = _run_metadata(model, params, source, (start, stop), run_dir, chunk_frames)
    res = _collect(run_dir, chunks, done_before, writer.failed, meta, t0)
    if res.table is not None:
        checks = run_checks(res.table, model, work_model, params, source.shape, read_variance)
        res.metadata.update(checks)
    return res


def _done_and_todo(
    run_dir: Path,
    chunks: list[tuple[int, int]],
    chunk_frames: int,
    progress: Callable[[int], None] | None,
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """The chunks whose parts exist (reported to ``progress`` at once) and those to run."""
    done_before = [c for c in chunks if _part_path(run_dir, c).exists()]
    todo = [c for c in chunks if c not in set(done_before)]
    if progress is not None and done_before:
        progress(sum(b - a for a, b in done_before))
    logger.info(
        "%d chunks of up to %d frames; %d done before, %d to run",
        len(chunks),
        chunk_frames,
        len(done_before),
        len(todo),
    )
    return done_before, todo


class _PartWriter:
    """Takes each chunk's result as it arrives: writes its part and reports its frames, or
    records why it failed (``failed``: chunk -> message)."""

    def __init__(self, run_dir: Path, progress: Callable[[int], None] | None) -> None:
        self.run_dir, self.progress = run_dir, progress
        self.failed: dict[tuple[int, int], str] = {}

    def __call__(
        self, chunk: tuple[int, int], table: pd.DataFrame | None, n_windows: int | str
    ) -> None:
        if table is None:  # bad data in the chunk: n_windows is the message
            self.failed[chunk] = str(n_windows)
            logger.warning("frames %d-%d failed: %s", chunk[0], chunk[1] - 1, n_windows)
            return
        _write_part(self.run_dir, chunk, table, n_windows)
        if self.progress is not None:
            self.progress(chunk[1] - chunk[0])

    def take(self, chunk: tuple[int, int], result: Callable[[], tuple]) -> None:
        """The result of ``result()``; an ``OSError`` (a file system that failed to answer)
        fails the chunk."""
        try:
            table, nw = result()
        except OSError as exc:
            self.failed[chunk] = str(exc)
            return
        self(chunk, table, nw)


def _run_chunks(
    scheduler: Any,
    source: CameraFrames,
    args: tuple[PSFModel, LocalizeParams],
    todo: list[tuple[int, int]],
    read_variance: NDArray | None,
    writer: _PartWriter,
    threads: int,
    retries: int,
) -> None:
    """Solve the chunks ``todo`` on ``scheduler``, handing each result to ``writer``;
    ``threads`` is the size of a thread or process pool."""
    if scheduler == "sync":
        for chunk in todo:
            writer.take(chunk, partial(_solve_chunk, source, *args, *chunk, read_variance))
    elif scheduler == "threads":
        with ThreadPoolExecutor(max(1, int(threads))) as pool:
            futs = {
                pool.submit(_solve_chunk, source, *args, *chunk, read_variance): chunk
                for chunk in todo
            }
            for fut in as_completed(futs):
                writer.take(futs[fut], fut.result)
    elif scheduler == "processes":
        _run_in_processes(source, args, todo, read_variance, writer, threads)
    else:
        _run_on_cluster(scheduler, source, args, todo, read_variance, retries, writer)


class _ChunkSolver:
    """A worker process's solver of chunks (:func:`sparseloc.pool.in_processes`): the frame
    source, model and parameters arrive once per process, each task is only its frames.

    Each worker copies the source: a forked worker would otherwise share the parent's open
    movie file, and its reads would move the others' file position; a copied
    :class:`~sparseloc.io.movie.Movie` opens its files anew in the worker.
    """

    def __init__(
        self,
        source: Any,
        work_model: PSFModel,
        params: LocalizeParams,
        read_variance: NDArray | None,
    ) -> None:
        import copy

        self.args = (copy.deepcopy(source), work_model, params)
        self.read_variance = read_variance

    def __call__(self, start: int, stop: int) -> tuple[pd.DataFrame | None, int | str]:
        try:
            return _solve_chunk(*self.args, start, stop, self.read_variance)
        except OSError as exc:  # a file system that failed to answer: this chunk fails
            return None, str(exc)


def _run_in_processes(source, args, todo, read_variance, writer, workers: int) -> None:
    """Solve the chunks ``todo`` in a pool of ``workers`` local processes."""
    from concurrent.futures.process import BrokenProcessPool

    from .pool import in_processes

    init = (_ChunkSolver, (source, *args, read_variance), args[1].engine)
    done: set[tuple[int, int]] = set()
    try:
        for chunk, (table, nw) in zip(todo, in_processes(todo, int(workers), init), strict=False):
            writer(chunk, table, nw)
            done.add(chunk)
    except BrokenProcessPool as exc:  # a worker died (killed, out of memory)
        for chunk in todo:
            if chunk not in done:
                writer.failed[chunk] = f"a worker process died ({exc})"


def _run_metadata(
    model: PSFModel,
    params: LocalizeParams,
    source: CameraFrames,
    frames: tuple[int, int],
    run_dir: Path,
    chunk_frames: int,
) -> dict:
    """The analysis metadata of the joined table."""
    meta = run_metadata(model, params, frames, source.shape)
    return {**meta, "run_dir": str(run_dir), "chunk_frames": int(chunk_frames)}


def _collect(
    run_dir: Path,
    chunks: list[tuple[int, int]],
    done_before: list[tuple[int, int]],
    failed: dict[tuple[int, int], str],
    meta: dict,
    t0: float,
) -> RunResult:
    """The run's result: the joined table when every part exists, else what is missing."""
    missing = [c for c in chunks if not _part_path(run_dir, c).exists()]
    table, n_windows = None, 0
    if not missing:
        table, n_windows = join_parts(run_dir, chunks)
    return RunResult(
        table=table,
        chunks=chunks,
        done_before=done_before,
        failed=failed,
        seconds=time.perf_counter() - t0,
        metadata=meta,
        run_dir=run_dir,
        n_windows=n_windows,
        missing=missing,
    )


def _run_on_cluster(scheduler, source, args, todo, read_variance, retries, writer):
    """Submit every chunk to a Dask cluster and write parts as they complete."""
    dask = _distributed()
    own = not isinstance(scheduler, dask.Client)
    try:
        client = dask.Client(scheduler, timeout="20s") if own else scheduler
    except OSError as exc:
        raise ValueError(f"cannot reach the Dask scheduler at {scheduler!r}: {exc}") from exc
    try:
        # The tabulated model (tens of MB) goes to every worker once, not with every task.
        model_f = client.scatter(args[0], broadcast=True, hash=False)
        # The frame source too: a Movie is only its paths, but a simulated movie or an
        # in-memory array would otherwise travel with every task.
        source_f = client.scatter(source, broadcast=True, hash=False)
        rv_f = None if read_variance is None else client.scatter(read_variance, broadcast=True)
        futs = {}
        for chunk in todo:
            fut = client.submit(
                _solve_chunk,
                source_f,
                model_f,
                args[1],
                *chunk,
                rv_f,
                retries=retries,
                pure=False,
                key=f"sparseloc-chunk-{chunk[0]}-{chunk[1]}-{os.getpid()}-{time.time_ns()}",
            )
            futs[fut] = chunk
        for fut in dask.as_completed(list(futs)):
            chunk = futs[fut]
            try:
                table, nw = fut.result()
            except Exception as exc:
                writer.failed[chunk] = f"{type(exc).__name__}: {exc}"
                logger.warning("frames %d-%d failed: %s", chunk[0], chunk[1] - 1, exc)
                continue
            writer(chunk, table, nw)
            fut.release()
    finally:
        if own:
            client.close()
