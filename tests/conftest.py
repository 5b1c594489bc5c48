"""Shared pytest fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def shared_data_dir() -> Path:
    """The shared real-data folder: $ENDOGSIM_SHARED_DATA, else <repo>/../shared/data."""
    env = os.environ.get("ENDOGSIM_SHARED_DATA")
    return Path(env).resolve() if env else (Path(__file__).parents[1] / ".." / "shared" / "data").resolve()


@pytest.fixture
def shared_data() -> Path:
    """Path to the shared real-data folder; skips the test when it is absent."""
    d = shared_data_dir()
    if not d.is_dir():
        pytest.skip(f"shared real data not found at {d}")
    return d
