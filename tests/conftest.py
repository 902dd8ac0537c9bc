"""Shared fixtures: paths to the embedded samples and to the real recordings in ../shared (skipped if absent)."""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from filelock import FileLock

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


def _once_per_run(tmp_path_factory: pytest.TempPathFactory, name: str, cmd: list[str]) -> Path:
    """Runs the `image2sim` command `cmd` + `-o OUT` once per test run and returns OUT (its stdout and stderr are
    kept beside it, in OUT's parent).

    `make test` runs the test files on several pytest-xdist workers (`--dist loadfile`), each its own process with
    its own session fixtures; the folder and its lock lie in the run's shared temporary folder, so the first worker
    that needs it runs the command and the others wait for its result instead of grounding the video again. A
    failed run leaves no `.done` mark: the next worker to ask runs it again and reports its own failure."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the workers' basetemps are siblings under the run's folder
    out, done = root / name / "scene", root / f"{name}.done"
    with FileLock(str(root / f"{name}.lock")):
        if not done.exists():
            shutil.rmtree(out.parent, ignore_errors=True)
            out.parent.mkdir(parents=True)
            proc = run_cli(*cmd, "-o", str(out), timeout=900)
            assert proc.returncode == 0, proc.stderr[-3000:]
            assert f"MJCF: {out / 'scene.xml'}" in proc.stdout
            (out.parent / "stdout.txt").write_text(proc.stdout)
            (out.parent / "stderr.txt").write_text(proc.stderr)
            done.touch()
    return out


@pytest.fixture(scope="session")
def grounded_tabletop(tabletop_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`image2sim ground` on the tabletop sample, run once per test run through the CLI (about a minute)."""
    cmd = ["ground", str(tabletop_dir / "video.mp4"), "--aruco-size", "0.12"]
    return _once_per_run(tmp_path_factory, "grounded_tabletop", cmd)


@pytest.fixture(scope="session")
def grounded_apple(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`image2sim ground` on the real apple video with `--known-extent 0.08`, once per test run (about 90 s): the
    film-a-scene test reads its scene, the reconstruct test its `reconstruction/` stage output (one run, not two)."""
    cmd = ["ground", str(shared_data / "apple_video" / "apple.mp4"), "--known-extent", "0.08"]
    return _once_per_run(tmp_path_factory, "grounded_apple", cmd)


def run_cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """`image2sim ARGS...` through the real interpreter (`python -m grounder.cli`) from the repository root; the
    `cli` fixture below runs commands in-process, which most tests use."""
    return subprocess.run(
        [sys.executable, "-m", "grounder.cli", *args], capture_output=True, text=True, timeout=timeout, cwd=REPO
    )


@dataclass(frozen=True)
class CliRun:
    """What one `image2sim` command did: its exit code and what it wrote (the fields of a CompletedProcess)."""

    returncode: int
    stdout: str
    stderr: str


@contextlib.contextmanager
def claim_held_by_another_process(out_dir: Path) -> Iterator[subprocess.Popen[str]]:
    """A second process holding `out_dir`'s output claim, as a run writing there does; killed with SIGKILL after
    (so its claim is left stale, as a killed run's is)."""
    code = (
        "import sys; from image2sim_common.outdir import claim_output; "
        "claim_output(sys.argv[1], error=ValueError); print('claimed', flush=True); sys.stdin.read()"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(out_dir)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=REPO
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "claimed"
        yield proc
    finally:
        proc.kill()
        proc.wait()


@pytest.fixture(autouse=True)
def _release_output_claims() -> object:
    """In-process runs (the `cli` fixture, library calls) release the output folders they claimed, as a process's
    end does: a test that checked an output and then failed leaves no lock beside it for the next test."""
    yield
    from image2sim_common.outdir import release_output_claims

    release_output_claims()


@pytest.fixture
def cli(
    capfd: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> Callable[..., CliRun]:
    """Runs `image2sim ARGS...` inside this test's process, from the repository root, through the console script's
    own entry point (`grounder.cli.main`: parsing, the one-line errors, the exit code); `timeout` in seconds.

    A subprocess costs 1-3 s of interpreter start and imports per command (2.3 CPU-minutes over `test_cli.py`);
    `test_cli.py` keeps some through the real interpreter (the console script, `python -m grounder.cli`, what a bare
    start imports). Output is captured at the file descriptors, so what C libraries write (decoders, COLMAP) is in
    `stderr` as on a console. The command's logging goes to pytest's handler here (the CLI sets up its own only
    where the root logger has none), so its warnings are appended to `stderr`, a line each. A command still running
    at `timeout` ends the whole test process with every thread's traceback (`faulthandler`): a check that something
    is refused before any work fails there rather than hanging the run."""
    from grounder.cli import main

    monkeypatch.chdir(REPO)

    def run(*args: str, timeout: float = 300) -> CliRun:
        capfd.readouterr()
        caplog.clear()
        faulthandler.dump_traceback_later(timeout, exit=True)
        try:
            main(list(args))
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            faulthandler.cancel_dump_traceback_later()
        out, err = capfd.readouterr()
        logged = "".join(f"{r.levelname} {r.getMessage()}\n" for r in caplog.records if r.levelno >= logging.WARNING)
        return CliRun(code, out, err + logged)

    return run


# A progress line as `stage_progress` draws it: "stage  [bar]  done/total  h:mm:ss" (the bar is blank at 0).
PROGRESS_LINE = re.compile(r"\s\d+/\d+\s+\d+:\d\d:\d\d\s*$")


def assert_one_line_error(proc: CliRun | subprocess.CompletedProcess[str], *needles: str, alone: bool = False) -> None:
    """Exit code 2 and one error line naming `needles`; `alone`: nothing else on stderr either (input rejected before
    any work: no progress line, no decoder chatter)."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-1500:])
    lines = [line for line in proc.stderr.splitlines() if line.startswith("image2sim: error:")]
    assert len(lines) == 1, proc.stderr
    if alone:
        assert [line for line in proc.stderr.splitlines() if line.strip()] == lines, proc.stderr
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


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


# `make test` hands whole files to the workers in collection order (`--dist loadfile --no-loadscope-reorder`): the
# files that take minutes go first, so that the run does not end with one worker busy on one of them, and the files
# that read grounder/grounding/test_pipeline.py's groundings go last, when the groundings are made (a worker waiting on
# one does nothing).
TESTS = Path(__file__).resolve().parent
_FIRST = (
    "grounder/grounding/test_pipeline.py",
    "samples/test_make_scene_family.py",
    "grounder/interaction/test_shooting.py",
    "grounder/tracking/test_pipeline.py",
    "grounder/cli/test_app.py",
    "grounder/interaction/test_impacts.py",
    "grounder/tracking/test_markers.py",
)
_LAST = ("grounder/properties/test_prior.py", "reconstruction/test_reconstruct.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        name = item.path.relative_to(TESTS).as_posix()
        if name in _FIRST:
            return _FIRST.index(name)
        return len(_FIRST) + 1 + _LAST.index(name) if name in _LAST else len(_FIRST)

    items.sort(key=rank)  # stable: the order within a file and among the other files stays
