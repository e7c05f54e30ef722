"""Shared helpers of the command-line tests: run a command, check a refusal."""

from __future__ import annotations

from typer.testing import CliRunner

from sparseloc.cli import app

runner = CliRunner()


def run(*args):
    """Invoke ``sparseloc ARGS`` (each argument as text) and return the result."""
    return runner.invoke(app, [str(a) for a in args])


def refused(res, *words: str) -> None:
    """Exit code 2 and exactly one sentence on stderr, naming ``words``; no traceback."""
    assert res.exit_code == 2, (res.output, res.exception)
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert "Traceback" not in res.output
    for w in words:
        assert w in lines[0], lines[0]
