"""Shared fixtures: small models and the location of the external test material."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from sparseloc.psf import make_psf

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SPARSELOC_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository; tests that need it skip where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"external test material not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def dh_model():
    return make_psf("dh")


@pytest.fixture(scope="session")
def astig_model():
    return make_psf("astig")


@pytest.fixture(params=["cpu", "cuda"])
def torch_device(request) -> str:
    """A PyTorch device for the backend tests: the CPU always, a CUDA GPU where one is present
    (skipped elsewhere); skipped without PyTorch."""
    torch = pytest.importorskip("torch")
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA GPU")
    return request.param


@pytest.fixture(scope="session", autouse=True)
def _spline_cache(tmp_path_factory):
    """Spline tables (:mod:`sparseloc.psf.cache`) of the test run go to a folder of its own,
    shared by the session's tests, never to the user's cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SPARSELOC_CACHE_DIR", str(tmp_path_factory.mktemp("spline-cache")))
        yield
