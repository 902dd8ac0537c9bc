"""Shared fixtures: paths to the embedded samples and to the real recordings in ../shared (skipped if absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "osmesa")

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def tabletop_dir() -> Path:
    path = SAMPLES / "tabletop"
    if not (path / "video.mp4").exists():
        pytest.skip("samples/tabletop is missing: run `make samples`")
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real recordings not available ({SHARED_DATA} is absent on this machine)")
    return SHARED_DATA
