"""Running a library call in a napari thread worker with progress, cancel and one-sentence
errors.

The call runs in a helper thread of its own, so that the worker's generator can yield its
progress counts (shown by the widget in the main thread) while it works, and so that a cancel
takes effect at the call's next progress report (:class:`Cancelled` raised there).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from ..messages import INPUT_ERRORS, one_sentence

__all__ = ["Cancelled", "Failed", "Task", "notify_error", "notify_info"]

#: How often (s) a worker without progress reports looks whether it was cancelled.
POLL_S = 0.1


class Cancelled(Exception):
    """Raised in the helper thread at the first progress report after a cancel."""


@dataclass(frozen=True)
class Failed:
    """What a task returns for bad input: the sentence to show (no traceback)."""

    message: str


def notify_error(message: str) -> None:
    """Show ``message`` as a napari error notification (no traceback)."""
    from napari.utils.notifications import show_error

    show_error(message)


def notify_info(message: str) -> None:
    """Show ``message`` as a napari information notification."""
    from napari.utils.notifications import show_info

    show_info(message)


class Task:
    """One library call run off the main thread, with progress and cancel.

    Parameters
    ----------
    call : callable
        ``call(progress)`` does the work; ``progress(n)`` reports ``n`` more units done and
        raises :class:`Cancelled` once :meth:`cancel` was called.
    """

    def __init__(self, call: Callable[[Callable[[int], None]], Any]) -> None:
        self._call = call
        self._cancel = threading.Event()
        self.worker: Any = None
        #: The helper thread running the call (once started).
        self.thread: threading.Thread | None = None
        #: Whether the worker has finished (set in the main thread).
        self.finished = False

    @property
    def cancelled(self) -> bool:
        """Whether :meth:`cancel` was called."""
        return self._cancel.is_set()

    def cancel(self) -> None:
        """Stop at the call's next progress report; its result is dropped."""
        self._cancel.set()
        if self.worker is not None:
            self.worker.quit()

    def _finished(self) -> None:
        self.finished = True

    def _progress(self, n: int = 1) -> None:
        if self._cancel.is_set():
            raise Cancelled
        self._queue.put(("progress", n))

    def _run(self) -> Generator[int, None, Any]:
        """The worker's generator: yields progress counts, returns the call's result, a
        :class:`Failed` for bad input, or None when cancelled."""
        self._queue: queue.Queue = queue.Queue()
        out: dict[str, Any] = {}

        def target() -> None:
            try:
                out["value"] = self._call(self._progress)
            except BaseException as exc:  # handed to the worker thread below
                out["error"] = exc
            finally:
                self._queue.put(("done", 0))

        self.thread = threading.Thread(target=target, daemon=True, name="sparseloc-task")
        self.thread.start()
        while True:
            try:
                kind, n = self._queue.get(timeout=POLL_S)
            except queue.Empty:
                yield 0  # lets the worker notice a quit
                continue
            if kind == "done":
                break
            yield n
        err = out.get("error")
        if isinstance(err, Cancelled) or self._cancel.is_set():
            return None
        if isinstance(err, INPUT_ERRORS):
            return Failed(one_sentence(err))
        if err is not None:
            raise err
        return out["value"]

    def start(
        self,
        on_progress: Callable[[int], None],
        on_done: Callable[[Any], None],
        on_finished: Callable[[], None] | None = None,
    ) -> Any:
        """Start the worker and return it (a napari ``GeneratorWorker``).

        ``on_progress(n)`` runs for each report, ``on_done(result)`` when the call succeeded
        (not after a cancel); bad input is shown as an error notification instead.
        ``on_finished()`` runs at the end whatever happened. All run in the main thread.
        """
        from napari.qt.threading import create_worker

        def returned(value: Any) -> None:
            if self.cancelled or value is None:
                return
            if isinstance(value, Failed):
                notify_error(value.message)
            else:
                on_done(value)

        worker = create_worker(self._run, _start_thread=False)
        worker.yielded.connect(on_progress)
        worker.returned.connect(returned)
        worker.finished.connect(self._finished)
        if on_finished is not None:
            worker.finished.connect(on_finished)
        self.worker = worker
        worker.start()
        return worker
