"""Atomic writes: write to a temporary name in the destination folder, then rename.

A crash or a bad input never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "write_text_atomic"]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``.

    Raises ``ValueError`` if the destination folder does not exist or cannot be written in.
    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"the output folder {str(folder)!r} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=dest.suffix, dir=folder)
    except OSError as exc:  # a read-only folder, a full disk: one sentence, not a traceback
        raise ValueError(
            f"cannot write {dest.name!r} in the folder {str(folder)!r}: "
            f"{exc.strerror or exc}".rstrip()
        ) from exc
    os.close(fd)
    # mkstemp creates 0600; give the file the permissions a plain open() would have
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, dest)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
