"""Bad input as one sentence: the rule the command line and the napari widgets share.

A library function refuses bad input by raising one of :data:`INPUT_ERRORS` whose message is
one sentence saying what to fix; the front ends show that sentence, never a traceback.
"""

from __future__ import annotations

__all__ = ["INPUT_ERRORS", "one_sentence"]

#: Exceptions that report a problem with the user's input (not a bug).
INPUT_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,
    FileNotFoundError,
    IsADirectoryError,
    PermissionError,
)


def one_sentence(exc: BaseException) -> str:
    """The message of ``exc`` as shown to the user: stripped, starting in lower case (it
    follows ``error: `` on the command line), the exception's type name when it has none."""
    msg = str(exc).strip() or type(exc).__name__
    return msg[0].lower() + msg[1:]
