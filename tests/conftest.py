"""Shared fixtures: paths to the embedded samples and to the real recordings in ../shared (skipped if absent)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from reconstruction import CameraIntrinsics, ReconstructionResult, RegisteredFrame, ScaleSource, WorldFrame

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


@pytest.fixture(scope="session")
def grounded_apple(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`image2sim ground` on the real apple video with `--known-extent 0.08`, once per session (about 90 s): the
    film-a-scene test reads its scene, the reconstruct test its `reconstruction/` stage output (one run, not two)."""
    out = tmp_path_factory.mktemp("apple") / "scene"
    cmd = [sys.executable, "-m", "grounder.cli", "ground", str(shared_data / "apple_video" / "apple.mp4")]
    proc = subprocess.run([*cmd, "-o", str(out), "--known-extent", "0.08"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.fixture
def reconstruction_of_points() -> Callable[[np.ndarray], ReconstructionResult]:
    """Factory: a minimal ReconstructionResult (one camera at (0, -0.6, 0.4) m) holding the given sparse points."""

    def make(points_world_m: np.ndarray) -> ReconstructionResult:
        cam = np.eye(4)
        cam[:3, 3] = [0, -0.6, 0.4]
        return ReconstructionResult(
            out_dir=Path("."), source=Path("."), num_source_frames=1, selected_frame_indices=(0,),
            dropped_blurred=(), dropped_duplicate=(),
            intrinsics=CameraIntrinsics(width_px=640, height_px=480, fx_px=500, fy_px=500, cx_px=320, cy_px=240),
            frames=(RegisteredFrame(frame_index=0, image_name="a.jpg", world_from_cam=cam),),
            world=WorldFrame(
                world_from_sfm=np.eye(4), scale_source=ScaleSource.ARUCO, scale=1.0, plane_inlier_ratio=1.0
            ),
            points_world_m=points_world_m, points_rgb=np.zeros((len(points_world_m), 3), np.uint8),
            mean_reprojection_error_px=0.3, stage_seconds={},
        )  # fmt: skip

    return make


# Session fixtures that ground a whole video: every test that needs one runs on the worker that grounds it.
_SHARED_GROUNDINGS = ("grounded_apple", "grounded_tabletop")


def xdist_group_of(item: pytest.Item) -> str | None:
    """The pytest-xdist group a test belongs to (`make test` runs `--dist loadgroup`), or None to run anywhere.

    A worker is its own process, so a fixture wider than one test is built once per worker that needs it: tests
    of one grounding share a group (one grounding, not one per worker), and so do the tests of a module with a
    module-scoped fixture (its fixture is built once, and module-level state such as a Ray instance stays in one
    process)."""
    names = getattr(item, "fixturenames", ())
    for name in _SHARED_GROUNDINGS:
        if name in names:
            return name
    info = getattr(item, "_fixtureinfo", None)
    for defs in info.name2fixturedefs.values() if info is not None else ():
        if defs and defs[-1].scope == "module":
            return item.nodeid.split("::", 1)[0]
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        group = xdist_group_of(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
