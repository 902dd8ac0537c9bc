"""The command line: every README example runs (at least --help); bad input gives one line and exit code 2,
leaving nothing half-written and nothing the user had lost."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import CliRun, assert_one_line_error, run_cli

README_COMMANDS = [
    ["reconstruct"],
    ["ground"],
    ["calibrate"],
    ["rollout"],
    ["randomize"],
    ["import-trajectories"],
    ["batch"],
    ["diagnose"],
    ["diagnose-benchmark"],
    ["track"],
    ["properties", "train"],
    ["properties", "evaluate"],
    ["properties", "sample"],
    ["residual", "train"],
]


@pytest.mark.parametrize("args", [[], *README_COMMANDS], ids=lambda a: " ".join(a) or "image2sim")
def test_help(args: list[str], cli: Callable[..., CliRun]) -> None:
    proc = cli(*args, "--help")
    assert proc.returncode == 0 and "Usage" in proc.stdout, proc.stderr


def test_log_messages_go_to_stderr_and_leave_stdout_to_the_results() -> None:
    code = (
        "import logging; from grounder.cli.common import setup_logging; setup_logging(False); "
        "logging.getLogger('grounder.x').warning('SCALE UNKNOWN: pass --aruco-size'); print('MJCF: out/scene.xml')"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "MJCF: out/scene.xml\n"
    assert "SCALE UNKNOWN" in proc.stderr


@pytest.mark.parametrize("page", ["README.md", "docs/cli.md"])
def test_every_readme_command_has_a_help_test(page: str) -> None:
    """README's examples and the full command reference it links to (docs/cli.md)."""
    text = (Path(__file__).resolve().parents[3] / page).read_text()
    used = {tuple(line.split()[1:3]) for line in text.splitlines() if line.startswith("image2sim ")}
    assert used, f"no `image2sim ...` examples found in {page}"
    tested = {tuple(cmd) for cmd in README_COMMANDS} | {("--help",)}
    for words in used:
        assert words[:1] in tested or words[:2] in tested, f"{page} example `image2sim {' '.join(words)}` untested"


def test_console_script_installed() -> None:
    exe = Path(sys.executable).parent / "image2sim"
    if not exe.exists():
        pytest.skip("package not installed as a console script in this environment")
    assert subprocess.run([str(exe), "--help"], capture_output=True, timeout=60).returncode == 0


def test_the_command_line_starts_without_the_grounding_pipeline() -> None:
    """`import grounder` (and so `image2sim --help` or a refused option) loads none of COLMAP, Open3D, trimesh or
    torch; each public name still resolves to what it names, and `__all__` lists every lazy name."""
    code = (
        "import sys, grounder; print(sorted(m for m in ('pycolmap', 'open3d', 'trimesh', 'torch', "
        "'grounder.grounding.pipeline') if m in sys.modules))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", (proc.stdout, proc.stderr[-2000:])
    import grounder
    from grounder.grounding.pipeline import ground

    assert set(grounder._LAZY) <= set(grounder.__all__)
    assert grounder.ground is ground and all(getattr(grounder, name) is not None for name in grounder.__all__)
    with pytest.raises(AttributeError, match="no attribute 'grund'"):
        _ = grounder.grund  # type: ignore[attr-defined]


def _write_images(folder: Path, images: list[np.ndarray], suffix: str = ".png") -> Path:
    folder.mkdir(parents=True)
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"img_{i:03d}{suffix}"), image)
    return folder


def _tabletop_frames(tabletop_dir: Path, indices: list[int]) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(tabletop_dir / "video.mp4"))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    return [frames[i] for i in indices]


def test_missing_source(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    """Through the real interpreter and through the in-process runner the other tests use: the same one line."""
    args = ("reconstruct", str(tmp_path / "nope.mp4"), "-o", str(tmp_path / "out"))
    real, here = run_cli(*args), cli(*args)
    assert (here.returncode, here.stdout, here.stderr) == (real.returncode, real.stdout, real.stderr) == (
        2, "", f"image2sim: error: {tmp_path / 'nope.mp4'} does not exist; pass a video file or a folder of images\n"
    )  # fmt: skip
    assert not (tmp_path / "out").exists()


def test_the_in_process_runner_sees_what_a_console_would(
    tmp_path: Path, cli: Callable[..., CliRun], monkeypatch: pytest.MonkeyPatch
) -> None:
    """What C libraries write straight to file descriptor 2 and what the command logs as a warning both reach the
    runner's stderr, so `alone=True` still fails on stray output: here a check that writes both before refusing."""
    import logging
    import os

    import reconstruction._reconstruct as stage
    from reconstruction.errors import InputError

    def noisy_check(source: Path) -> None:
        os.write(2, b"decoder chatter\n")
        logging.getLogger("reconstruction").warning("a warning on the way")
        raise InputError(f"{source} is refused; pass another")

    monkeypatch.setattr(stage._frames, "check_source", noisy_check)
    proc = cli("reconstruct", str(tmp_path / "clip.mp4"), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "is refused")
    assert "decoder chatter" in proc.stderr and "WARNING a warning on the way" in proc.stderr
    with pytest.raises(AssertionError):
        assert_one_line_error(proc, "is refused", alone=True)


def test_unreadable_video(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    fake = tmp_path / "clip.mp4"
    fake.write_text("this is not a video")
    proc = cli("reconstruct", str(fake), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "clip.mp4", alone=True)
    assert not (tmp_path / "out").exists()


def _cut_short(path: Path) -> None:
    """Keeps the first half of a file's bytes: a copy or download that stopped half-way."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_truncated_image_in_a_folder_is_refused(
    tmp_path: Path, tabletop_dir: Path, suffix: str, cli: Callable[..., CliRun]
) -> None:
    """A JPEG cut short decoded with its lower rows grey and only libjpeg's "Premature end of JPEG file" on the
    console; it went on into structure from motion. Now it is named as the frames are read, before any other work."""
    from reconstruction._frames import read_frames

    folder = _write_images(tmp_path / "imgs", _tabletop_frames(tabletop_dir, [5, 10, 15, 20]), suffix)
    assert len(read_frames(folder)) == 4  # the control: the whole images are read
    _cut_short(folder / f"img_002{suffix}")
    proc = cli("reconstruct", str(folder), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, f"img_002{suffix} is truncated or damaged")
    assert not (tmp_path / "out").exists()


def test_truncated_video_is_refused(tmp_path: Path, tabletop_dir: Path, cli: Callable[..., CliRun]) -> None:
    """A video cut short whose container still states its length (here an AVI: its header gives 30 frames) decoded
    the first half and went on as if that were the film. Now the break is named with how many frames decoded."""
    clip = tmp_path / "orbit.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for frame in _tabletop_frames(tabletop_dir, list(range(0, 60, 2))):
        writer.write(cv2.resize(frame, (320, 240)))
    writer.release()
    from reconstruction._frames import read_frames_counted

    assert read_frames_counted(clip)[1] == 30  # the control: the whole file decodes to every frame it states
    _cut_short(clip)
    proc = cli("reconstruct", str(clip), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "orbit.avi stops decoding after", "of the 30 frames it states")
    assert not (tmp_path / "out").exists()


def test_too_few_frames(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    rng = np.random.default_rng(0)
    folder = _write_images(tmp_path / "imgs", [rng.integers(0, 255, (120, 160, 3), np.uint8) for _ in range(2)])
    proc = cli("reconstruct", str(folder), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "2 frame(s)", "at least 3")


def test_featureless_frames(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    folder = _write_images(tmp_path / "imgs", [np.full((120, 160, 3), 128, np.uint8) for _ in range(6)])
    proc = cli("reconstruct", str(folder), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "featureless")
    assert not (tmp_path / "out").exists()


def test_unmatchable_frames_fail_registration(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    rng = np.random.default_rng(1)
    noise = [cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3), np.uint8), (0, 0), 1.5) for _ in range(6)]
    folder = _write_images(tmp_path / "imgs", noise)
    proc = cli("reconstruct", str(folder), "-o", str(tmp_path / "out"))
    assert_one_line_error(proc, "structure from motion")
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.partial")]


def test_marker_size_given_but_no_marker(tmp_path: Path, tabletop_dir: Path, cli: Callable[..., CliRun]) -> None:
    frames = _tabletop_frames(tabletop_dir, [5, 10, 15, 20])
    for frame in frames:  # paint the marker out
        detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
        corners, ids, _ = detector.detectMarkers(frame)
        if ids is not None:
            for quad in corners:
                centre = quad[0].mean(axis=0)
                big = (quad[0] - centre) * 1.6 + centre
                cv2.fillPoly(frame, [big.astype(np.int32)], (60, 110, 170))
    folder = _write_images(tmp_path / "imgs", frames)
    proc = cli("reconstruct", str(folder), "-o", str(tmp_path / "out"), "--aruco-size", "0.12", timeout=60)
    assert_one_line_error(proc, "no ArUco marker", "--known-extent")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--aruco-size", "0.12", "--known-extent", "0.1"], "not both"),
        (["--aruco-size", "120"], "metres"),
        (["--max-frames", "1"], "--max-frames"),
    ],
)
def test_bad_options(
    tmp_path: Path, tabletop_dir: Path, flags: list[str], needle: str, cli: Callable[..., CliRun]
) -> None:
    proc = cli("reconstruct", str(tabletop_dir / "video.mp4"), "-o", str(tmp_path / "out"), *flags)
    assert_one_line_error(proc, needle)


def test_existing_output_is_kept(tmp_path: Path, tabletop_dir: Path, cli: Callable[..., CliRun]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("mine")
    proc = cli("reconstruct", str(tabletop_dir / "video.mp4"), "-o", str(out))
    assert_one_line_error(proc, "--overwrite")
    assert (out / "precious.txt").read_text() == "mine"


def test_failed_overwrite_keeps_previous_output(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "reconstruct.json").write_text("{}")
    folder = _write_images(tmp_path / "imgs", [np.full((120, 160, 3), 128, np.uint8) for _ in range(6)])
    proc = cli("reconstruct", str(folder), "-o", str(out), "--overwrite")
    assert_one_line_error(proc, "featureless")
    assert (out / "reconstruct.json").read_text() == "{}"


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["ground", "--bogus"], "No such option: --bogus"),
        (["ground", "x.mp4", "-o", "out/x", "--aruco-size", "abc"], "'--aruco-size'"),
        (["ground", "x.mp4"], "Missing option '-o'"),
        (["nosuch"], "No such command 'nosuch'"),
    ],
)
def test_usage_errors_are_one_line(args: list[str], needle: str, cli: Callable[..., CliRun]) -> None:
    """Option parsing errors get the same one line as any bad input, not click's boxed usage message."""
    proc = cli(*args, timeout=60)
    assert_one_line_error(proc, needle, "--help", alone=True)


@pytest.mark.parametrize("command", ["reconstruct", "ground"])
def test_output_over_the_source_is_refused(
    tmp_path: Path, tabletop_dir: Path, command: str, cli: Callable[..., CliRun]
) -> None:
    """-o naming the image folder, or a folder that holds it, would replace the user's images even with --overwrite."""
    folder = _write_images(tmp_path / "shoot" / "imgs", _tabletop_frames(tabletop_dir, [5, 10, 15, 20]))
    (tmp_path / "shoot" / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    for out in (folder, folder.parent):
        proc = cli(command, str(folder), "-o", str(out), "--overwrite", "--aruco-size", "0.12", timeout=60)
        assert_one_line_error(proc, "choose an output folder outside", alone=True)
        assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
        assert (tmp_path / "shoot" / "notes.txt").read_text() == "mine"


def test_unreadable_interaction_clip_fails_before_grounding(
    tmp_path: Path, tabletop_dir: Path, cli: Callable[..., CliRun]
) -> None:
    clip = tmp_path / "toss.mp4"
    clip.write_text("this is not a video")
    proc = cli(
        "ground", str(tabletop_dir / "video.mp4"), "--interaction", str(clip), "-o", str(tmp_path / "out"), timeout=60
    )
    assert_one_line_error(proc, "toss.mp4", "not a readable video", alone=True)
    assert not (tmp_path / "out").exists()
    # A clip that opens but is too short to track (3 frames) failed only after the grounding (71 s).
    short = tmp_path / "short"
    short.mkdir()
    for i in range(3):
        cv2.imwrite(str(short / f"{i}.png"), np.full((48, 64, 3), 40 * i, np.uint8))
    proc = cli(
        "ground", str(tabletop_dir / "video.mp4"), "--interaction", str(short), "-o", str(tmp_path / "out"),
        "--aruco-size", "0.12", timeout=60,
    )  # fmt: skip
    assert_one_line_error(proc, "3 frames; tracking needs at least 5", alone=True)
    assert not (tmp_path / "out").exists()


def test_properties_train_keeps_a_non_empty_output(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    out = tmp_path / "weights"
    out.mkdir()
    (out / "property_net.json").write_text("mine")
    proc = cli("properties", "train", "-o", str(out), "--num-train", "100", "--epochs", "1", timeout=60)
    assert_one_line_error(proc, "not empty", "--overwrite", alone=True)
    assert (out / "property_net.json").read_text() == "mine"


def test_diagnose_benchmark_checks_its_json_path_first(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    mine = tmp_path / "results.json"
    mine.write_text("mine")
    proc = cli("diagnose-benchmark", "--json", str(mine), timeout=60)
    assert_one_line_error(proc, "already exists", alone=True)
    assert mine.read_text() == "mine"
    proc = cli("diagnose-benchmark", "--json", str(tmp_path / "nowhere" / "r.json"), timeout=60)
    assert_one_line_error(proc, "does not exist", alone=True)
    proc = cli("diagnose-benchmark", "--trajectories", "0", timeout=60)  # named as the flag it is, not --holdout
    assert_one_line_error(proc, "--trajectories 0 must be between 8 and 1000", alone=True)
    (tmp_path / "a_file").write_text("mine")
    proc = cli("diagnose-benchmark", "--json", str(tmp_path / "a_file" / "r.json"), timeout=60)
    assert_one_line_error(proc, "is a file, not a folder", alone=True)
    # a folder no one can write to (here: /proc, refused even to root) is found before the benchmark's minutes
    proc = cli("diagnose-benchmark", "--json", "/proc/image2sim_results.json", timeout=60)
    assert_one_line_error(proc, "cannot write in /proc", alone=True)
    proc = cli("diagnose-benchmark", "--cases", ",", timeout=60)  # names nothing: not read as "every case"
    assert_one_line_error(proc, "--cases ',' names nothing", alone=True)


def test_a_refused_read_or_write_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cli: Callable[..., CliRun]
) -> None:
    """An OSError no command foresaw (permissions, a full disk) still ends as one line naming the path, exit 2."""
    import grounder.core.importers

    def refused(fmt: str, src_dir: Path) -> list[object]:
        raise PermissionError(13, "Permission denied", str(src_dir / "0.pt"))

    monkeypatch.setattr(grounder.core.importers, "import_trajectories", refused)
    src, out = tmp_path / "tosses", tmp_path / "out"
    src.mkdir()
    proc = cli("import-trajectories", str(src), "-o", str(out), "--format", "dair-pll-cube")
    assert_one_line_error(proc, "refused to read or write", str(src / "0.pt"), "Permission denied", alone=True)
    assert not out.exists()


def test_fail_joins_a_message_over_several_lines(capsys: pytest.CaptureFixture[str]) -> None:
    import typer

    from grounder.cli.common import fail

    with pytest.raises(typer.Exit) as caught:
        fail("what was wrong\n  (a library's own text over lines)\nwhat to do")
    assert caught.value.exit_code == 2
    assert capsys.readouterr().err == "image2sim: error: what was wrong (a library's own text over lines) what to do\n"


def test_value_checks_name_each_value_that_is_wrong(capsys: pytest.CaptureFixture[str]) -> None:
    import typer

    from grounder.cli.common import require

    require(("--density", 600.0, True, "> 0"))  # all fine: nothing printed, no exit
    with pytest.raises(typer.Exit):
        require(
            ("--density", 0.0, False, "> 0"), ("--face-budget", 4000, True, ">= 100"), ("--max-hulls", 0, False, ">= 1")
        )
    assert capsys.readouterr().err == "image2sim: error: --density 0.0 must be > 0; --max-hulls 0 must be >= 1\n"


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["diagnose", "s.xml", "t", "-o", "o", "--threads", "100000"], "--threads 100000 must be between 1 and 256"),
        (["diagnose", "s.xml", "t", "-o", "o", "--seed", "-1"], "--seed -1 must be >= 0"),
        (["diagnose", "s.xml", "t", "-o", "o", "--horizon", "nan"], "--horizon nan must be > 0 and finite"),
        (["diagnose-benchmark", "--threads", "2000"], "--threads 2000 must be between 1 and 256"),
        (["diagnose-benchmark", "--seed", "-1"], "--seed -1 must be >= 0"),
        (["properties", "evaluate", "--seed", "-1"], "--seed -1 must be >= 0"),
        (["properties", "sample", "s", "-o", "o", "-n", "100000"], "-n 100000 must be between 1 and 10000"),
        (["ground", "v.mp4", "-o", "o", "--density", "inf"], "--density inf must be between 1 and 25000 (kg/m^3)"),
        (["ground", "v.mp4", "-o", "o", "--density", "1e300"], "--density 1e+300 must be between 1 and 25000"),
        (["ground", "v.mp4", "-o", "o", "--face-budget", "10000000"], "--face-budget 10000000 must be between 100"),
        (
            ["residual", "train", "s", "t", "-o", "o", "--hidden", "100000"],
            "--hidden 100000 must be between 1 and 4096",
        ),
        (["residual", "train", "s", "t", "-o", "o", "--steps", "10" * 10], "must be between 1 and 1000000"),
        (["residual", "train", "s", "t", "-o", "o", "--seed", "-1"], "--seed -1 must be between 0 and 4294967295"),
        (["batch", "j.yaml", "--num-cpus", "10" * 10], "must be between 1 and 256"),
        (["calibrate", "s.xml", "t", "-o", "o", "--seed", "4294967296"], "seed must be an integer in [0, 4294967295]"),
        (["calibrate", "s.xml", "t", "-o", "o", "--popsize", "10" * 10], "popsize must be an integer in [1, 1000]"),
        (["calibrate", "s.xml", "t", "-o", "o", "--rotation-weight", "1e300"], "--rotation-weight must be a number in"),
        (["reconstruct", "samples/tabletop/video.mp4", "-o", "o", "--seed", "-1"], "--seed is -1 but must be between"),
        (["ground", "samples/tabletop/video.mp4", "-o", "o", "--seed", "2147483648"], "--seed is 2147483648 but"),
        (["properties", "train", "-o", "/proc/image2sim_test/w", "--num-train", "100"], "cannot create the output"),
    ],
)
def test_values_that_cannot_work_are_refused_before_any_work(
    args: list[str], needle: str, cli: Callable[..., CliRun]
) -> None:
    """Each of these was accepted: --threads 2000 grew to 15 GB and ignored SIGTERM, --seed -1 was numpy's
    traceback, --horizon nan reported 'every nan s', --density inf failed after a minute of grounding naming
    another value, an uncreatable -o failed only after training. Later (an audit of every numeric option): seeds
    out of COLMAP's, numpy's or torch's range were tracebacks after the first stage, a huge --popsize, --hidden or
    --num-cpus one from SciPy, torch or Ray, a huge --steps ran without end, and --density 1e300 or
    --rotation-weight 1e300 exited 0 with a meaningless scene or fit."""
    proc = cli(*args, timeout=60)
    assert_one_line_error(proc, needle, alone=True)


def test_sigterm_unwinds_the_output_stage_like_ctrl_c(tmp_path: Path) -> None:
    """SIGTERM (`timeout`, `docker stop`, a cancelled CI job) killed the process through pycolmap's glog handler: a
    35-line stack dump and the hidden staging folder left behind, one per interrupted run. Now the command stops
    as for Ctrl-C: one line, exit 143, nothing half-written, during the long C++ stages too."""
    import signal
    import time

    out = tmp_path / "out"
    video = Path(__file__).resolve().parents[3] / "samples" / "tabletop" / "video.mp4"
    proc = subprocess.Popen(
        [sys.executable, "-m", "grounder.cli", "reconstruct", str(video), "-o", str(out), "--aruco-size", "0.1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not list((tmp_path).glob(".i2s-*.partial/images/*.jpg")) and time.monotonic() < deadline:
        time.sleep(0.2)  # the staging folder is being filled: the work has begun
    time.sleep(2.0)  # into feature extraction (COLMAP's C++)
    proc.send_signal(signal.SIGTERM)
    _stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, (proc.returncode, stderr[-2000:])
    assert "*** SIGTERM received" not in stderr and "Traceback" not in stderr, stderr[-2000:]
    assert stderr.rstrip().endswith("image2sim: stopped (SIGTERM); nothing half-written was left"), stderr[-2000:]
    assert list(tmp_path.iterdir()) == [], list(tmp_path.iterdir())


def test_input_refused_at_the_first_stage_leaves_no_progress_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cli: Callable[..., CliRun]
) -> None:
    """An image found unreadable once `reconstruct` has begun reading frames: the stage's empty progress bar is
    taken down, so the error is the only line on stderr (outside CI too, where the bars are drawn)."""
    monkeypatch.delenv("CI", raising=False)
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "0001.png").write_text("not a png")
    proc = cli("reconstruct", str(frames), "-o", str(tmp_path / "rec"), "--aruco-size", "0.1")
    assert_one_line_error(proc, "0001.png is not a readable image", alone=True)
    assert not (tmp_path / "rec").exists()


def test_progress_shows_an_eta_while_a_stage_of_many_steps_runs() -> None:
    """The ETA column: rich's estimate while a stage of several steps runs, nothing before its first step, for a
    one-step stage, or once the stage is done."""
    from rich.progress import Progress

    from grounder.cli.common import eta_column

    clock = [0.0]
    progress = Progress(get_time=lambda: clock[0])
    column = eta_column()
    frames = progress.add_task("extracting SIFT features", total=66)
    single = progress.add_task("world frame", total=1)
    assert str(column.render(progress.tasks[frames])) == ""  # no step done: no estimate
    for step in range(1, 23):  # a step every half second
        clock[0] = 0.5 * step
        progress.update(frames, completed=step)
    assert str(column.render(progress.tasks[frames])) == "ETA 0:22"  # 44 steps left at 2 a second
    progress.update(single, completed=0)
    assert str(column.render(progress.tasks[single])) == ""
    progress.update(frames, completed=66)
    assert str(column.render(progress.tasks[frames])) == ""
