"""The README's commands use flags the commands have (issue 27 item 6: its synopsis once
contradicted ``calibrate --help``), and the camera is given the same way to every command
that reads camera data."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import typer.main

from sparseloc.cli import app

README = Path(__file__).resolve().parents[1] / "README.md"


def _options(name: str) -> set[str]:
    cmd = typer.main.get_command(app).commands[name]
    return {o for p in cmd.params for o in (*p.opts, *p.secondary_opts) if o.startswith("-")}


def _readme_commands() -> list[list[str]]:
    """Every ``sparseloc ...`` line in the README's code blocks, continuations joined,
    split as a shell would (comments dropped)."""
    out = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", README.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            for part in line.split("&&"):
                words = shlex.split(part, comments=True)
                if len(words) > 1 and words[0] == "sparseloc":
                    out.append(words)
    return out


def test_the_readme_shows_commands():
    names = {w[1] for w in _readme_commands()}
    assert {"demo", "calibrate", "simulate", "localize", "render", "camera"} <= names


@pytest.mark.parametrize("words", _readme_commands(), ids=lambda w: " ".join(w[:2]))
def test_every_flag_in_the_readme_exists(words):
    known = _options(words[1])
    flags = {w.split("=")[0] for w in words[2:] if w.startswith("--")}
    assert flags <= known, f"{' '.join(words)}: {sorted(flags - known)} not in {words[1]} --help"


CAMERA_FLAGS = {"--camera", "--offset", "--gain", "--em-gain", "--qe", "--read-noise", "--config"}


@pytest.mark.parametrize("name", ["simulate", "calibrate", "localize"])
def test_every_command_that_reads_camera_data_takes_the_same_camera_flags(name):
    assert CAMERA_FLAGS <= _options(name), sorted(CAMERA_FLAGS - _options(name))


def test_the_camera_estimate_takes_the_flags_of_what_it_does_not_estimate():
    """``sparseloc camera`` estimates the gain (and the offset and read noise where they are
    not given): it takes the other camera flags, by the same names."""
    assert {"--camera", "--offset", "--em-gain", "--read-noise"} <= _options("camera")


def test_the_readme_names_the_camera_flags_that_exist():
    text = README.read_text()
    line = next(ln for ln in text.splitlines() if "give every command your camera" in ln)
    named = set(re.findall(r"`(--[a-z-]+)", line))
    assert CAMERA_FLAGS <= named | {"--config"}, sorted(CAMERA_FLAGS - named)
    assert named <= _options("localize"), sorted(named - _options("localize"))


def test_the_readme_says_where_the_spline_tables_are_cached(monkeypatch, tmp_path):
    """Issue 27 item 12: the first fit with a pupil model tabulates it once; the README says
    so and names the folder and the variable that :func:`sparseloc.psf.cache.cache_dir`
    reads."""
    from sparseloc.psf.cache import cache_dir

    text = " ".join(README.read_text().split())
    assert "cached in `~/.cache/sparseloc` (`SPARSELOC_CACHE_DIR`)" in text
    monkeypatch.setenv("SPARSELOC_CACHE_DIR", str(tmp_path))
    assert cache_dir() == tmp_path
    monkeypatch.delenv("SPARSELOC_CACHE_DIR")
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    if __import__("sys").platform.startswith("linux"):
        assert cache_dir() == tmp_path / ".cache" / "sparseloc"


@pytest.mark.slow
def test_the_tetrapod_recipe_runs_as_the_readme_says(shared_data, tmp_path, monkeypatch):
    """Issue 27 item 9: the README's recipe for DeepSTORM3D's real tetrapod frame runs from
    the command line alone (optics and camera as flags) and gives what its comments say."""
    from typer.testing import CliRunner

    block = next(
        b for b in re.findall(r"```bash\n(.*?)```", README.read_text(), re.S) if "Tetrapod" in b
    )
    monkeypatch.chdir(tmp_path)
    outputs = {}
    for line in block.splitlines():
        words = shlex.split(line.replace("$D", str(shared_data / "deepstorm3d")), comments=True)
        if not words or words[0] != "sparseloc":
            continue
        res = CliRunner().invoke(app, words[1:])
        assert res.exit_code == 0, (line, res.output)
        said = re.search(r"#\s*(.*)$", line)
        outputs[words[1] + str(len(outputs))] = (res.output, said.group(1) if said else "")
    for output, comment in outputs.values():
        for number in re.findall(r"(\d[\d.]*) (?:localizations|e-/ADU|e-)", comment):
            assert number in output, (comment, output)
    assert (tmp_path / "tetrapod_overlay.png").is_file()
    assert (tmp_path / "tetrapod_check.png").is_file()
