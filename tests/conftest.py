"""Shared fixtures: paths to the embedded samples and to the real recordings in ../shared (skipped if absent)."""

from __future__ import annotations

import os
import subprocess
import sys
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


@pytest.fixture(scope="session")
def grounded_tabletop(tabletop_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`image2sim ground` on the tabletop sample, run once per test session through the CLI (about a minute)."""
    out = tmp_path_factory.mktemp("ground") / "scene"
    cmd = [sys.executable, "-m", "grounder.cli", "ground", str(tabletop_dir / "video.mp4"), "-o", str(out)]
    proc = subprocess.run([*cmd, "--aruco-size", "0.12"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"MJCF: {out / 'scene.xml'}" in proc.stdout
    return out
