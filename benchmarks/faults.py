"""Fault suite: the real `image2sim` commands, as subprocesses, stopped, starved of disk, raced and given odd paths.

Run: `.venv/bin/python benchmarks/faults.py` (full, about 25 min on 2 cores), `--quick` (a subset, a few minutes),
`--only PATTERN` (cases whose name matches the regular expression), `--json PATH` (the rows as JSON), `--keep` (keep
the work folders). The disk cases mount tmpfs file systems and so need root; without it they are skipped.

Each case prints one row: the exit codes wanted and got, the last line on stderr (a failing or stopped run must end
with exactly one `image2sim: ...` line, with no traceback, segfault or native stack dump anywhere in its output), what
is left beside the output folder (hidden `.i2s-*` staging or lock folders, `NAME.image2sim-*` kept results, anything
else new; also files left in the run's TMPDIR and processes of the run still alive 10 s after it ended), and whether
the user's files (everything in the case's folder before the run, and the inputs) are byte-for-byte unchanged.
The last line is `N passed, M failed`; the exit code is 1 when a case failed.

Signals are sent as a user sends them: SIGINT (Ctrl-C) to the command's process group, SIGTERM (`kill`, `timeout`)
and SIGKILL to its process. Progress is drawn only to a terminal, so runs that are stopped at a stage have stderr on a
pseudo-terminal (CI unset) and the signal goes when the stage's name first appears, plus a delay.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import errno
import fcntl
import hashlib
import json
import os
import pty
import re
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import termios
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = REPO / ".venv" / "bin" / "image2sim"
PY = REPO / ".venv" / "bin" / "python"
VIDEO = REPO / "samples" / "tabletop" / "video.mp4"
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"
CUBE_DATA = REPO.parent / "shared" / "data" / "cube_toss"
SCAN = ["--aruco-size", "0.12", "--max-frames", "30"]
# Fast calibration settings: the fit is not what is measured here.
CAL_FAST = ["--max-train", "3", "--generations", "4", "--popsize", "4", "--local-iterations", "4"]
JOB_SETTINGS = {
    "params": ["cube.friction.sliding"],
    "generations": 2,
    "popsize": 4,
    "local_iterations": 2,
    "max_train_trajectories": 3,
}
ODD = os.fsdecode(b"odd_\xff\xfe")  # bytes that are no UTF-8: a name in another encoding
STOPPED_LINE = {
    signal.SIGINT: "image2sim: stopped (Ctrl-C); nothing half-written was left",
    signal.SIGTERM: "image2sim: stopped (SIGTERM); nothing half-written was left",
}
# What crashes print: Python, the C runtime, glog (COLMAP, Ray), abseil's failure handler (Ray's C++ core), click.
CRASH_MARKS = (
    "Traceback (most recent call last)",
    "Segmentation fault",
    "Fatal Python error",
    "core dumped",
    "terminate called",
    "Check failure stack trace",
    "*** SIG",
    "*** Aborted at",
    "PC: @",
    "Stack trace",
    "Aborted!",
)
# Every stage name the commands report (progress lines), searched for in a run's stderr.
STAGES = (
    "reading frames",
    "extracting SIFT features",
    "matching",
    "registering frames",
    "world frame",
    "dense stereo",
    "segmenting objects",
    "meshing objects",
    "baking textures",
    "physical properties",
    "collision hulls",
    "writing MJCF",
    "object markers",
    "global search",
    "local refinement",
    "intervals",
    "validation",
    "writing",
    "batch jobs",
)
_ANSI = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b\][^\x07]*\x07|\x1b[()][0-9A-Za-z]|\x1b[=>78DEHMc]")


def _text(raw: bytes) -> str:
    return _ANSI.sub("", raw.decode("utf-8", "backslashreplace"))


def _lines(raw: bytes) -> list[str]:
    """A stream's lines as a user reads them: escapes removed, each redraw of a progress line a line of its own."""
    return [line.strip() for line in re.split(r"[\r\n]+", _text(raw)) if line.strip()]


# ---------------------------------------------------------------------------------------------------------------------
# Running a command


class Child:
    """One command, its stdout on a pipe and its stderr on a pipe or (tty) a pseudo-terminal, read by a thread."""

    def __init__(self, argv: list[object], env: dict[str, str], *, tty: bool, cwd: Path = REPO) -> None:
        self.argv = [os.fspath(a) if isinstance(a, Path) else str(a) for a in argv]
        self.out = bytearray()
        self.err = bytearray()
        self.seen: dict[str, float] = {}  # stage -> seconds after start when its name first appeared
        self.fired: list[str] = []
        self._lock = threading.Lock()
        master = slave = None
        if tty:
            master, slave = pty.openpty()
            fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, 200, 0, 0))
        self.start = time.monotonic()
        self.proc = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=slave if tty else subprocess.PIPE,
            env=env,
            cwd=cwd,
            start_new_session=True,  # its own process group, as a shell gives a foreground job
        )
        if slave is not None:
            os.close(slave)
        assert self.proc.stdout is not None
        err_fd = master if master is not None else self.proc.stderr.fileno()  # type: ignore[union-attr]
        self._fds = {self.proc.stdout.fileno(): self.out, err_fd: self.err}
        self._master = master
        self.ended_at: float | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        open_fds = dict(self._fds)
        drain_until = None
        while open_fds:
            if self.proc.poll() is not None and drain_until is None:
                drain_until = time.monotonic() + 1.0  # a child's children may hold the streams open
            if drain_until is not None and time.monotonic() > drain_until:
                break
            ready, _, _ = select.select(list(open_fds), [], [], 0.05)
            for fd in ready:
                try:
                    chunk = os.read(fd, 65536)
                except OSError:  # EIO: the pseudo-terminal's other side is closed
                    chunk = b""
                if not chunk:
                    del open_fds[fd]
                    continue
                with self._lock:
                    open_fds[fd].extend(chunk)
                    if open_fds[fd] is self.err:
                        self._note_stages()

    def _note_stages(self) -> None:
        tail = _text(bytes(self.err[-16384:]))
        now = time.monotonic() - self.start
        for stage in STAGES:
            if stage not in self.seen and stage in tail:
                self.seen[stage] = now

    @property
    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def done(self) -> bool:
        if self.proc.poll() is not None and self.ended_at is None:
            self.ended_at = self.elapsed
        return self.proc.poll() is not None

    def signal(self, signum: int, *, group: bool = False) -> None:
        with contextlib.suppress(ProcessLookupError):
            if group:
                os.killpg(self.proc.pid, signum)
            else:
                os.kill(self.proc.pid, signum)
        self.fired.append(f"{signal.Signals(signum).name} at {self.elapsed:.1f} s")

    def finish(self, timeout_s: float) -> Run:
        try:
            self.proc.wait(timeout=max(1.0, timeout_s - self.elapsed))
            timed_out = False
        except subprocess.TimeoutExpired:
            timed_out = True
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self.done()
        self._reader.join(timeout=5)
        if self._master is not None:
            os.close(self._master)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        return Run(
            argv=self.argv,
            rc=self.proc.returncode,
            stdout=_text(bytes(self.out)),
            err_lines=_lines(bytes(self.err)),
            err_text=_text(bytes(self.err)),
            seconds=self.ended_at if self.ended_at is not None else self.elapsed,
            seen=dict(self.seen),
            fired=list(self.fired),
            timed_out=timed_out,
            pid=self.proc.pid,
        )


@dataclass
class Run:
    argv: list[str]
    rc: int
    stdout: str
    err_lines: list[str]
    err_text: str
    seconds: float
    seen: dict[str, float]
    fired: list[str]
    timed_out: bool
    pid: int

    @property
    def last(self) -> str:
        return self.err_lines[-1] if self.err_lines else ""

    @property
    def stage(self) -> str:
        """The last stage the run had reached (by its progress lines), or '-'."""
        return max(self.seen, key=self.seen.__getitem__) if self.seen else "-"


@dataclass
class Trigger:
    """`action(child)` once, `delay` seconds after `when(child)` first holds."""

    when: Callable[[Child], bool]
    action: Callable[[Child], None]
    delay: float = 0.0
    _since: float | None = None
    fired: bool = False


def on_stage(stage: str, action: Callable[[Child], None], delay: float = 0.3) -> Trigger:
    return Trigger(lambda c: stage in c.seen, action, delay)


def at_time(seconds: float, action: Callable[[Child], None]) -> Trigger:
    return Trigger(lambda c: c.elapsed >= seconds, action)


def when_exists(pattern: Callable[[], bool], action: Callable[[Child], None], delay: float = 0.3) -> Trigger:
    return Trigger(lambda c: pattern(), action, delay)


def send(signum: int) -> Callable[[Child], None]:
    return lambda c: c.signal(signum, group=signum == signal.SIGINT)  # Ctrl-C reaches the whole foreground group


def drive(children: list[tuple[Child, list[Trigger]]], timeout_s: float) -> list[Run]:
    """Runs the triggers of each child until every child has ended; returns their runs."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not all(c.done() for c, _ in children):
        for child, triggers in children:
            if child.done():
                continue
            for trig in triggers:
                if trig.fired:
                    continue
                if trig._since is None and trig.when(child):
                    trig._since = time.monotonic()
                if trig._since is not None and time.monotonic() >= trig._since + trig.delay:
                    trig.fired = True
                    trig.action(child)
        time.sleep(0.02)
    return [child.finish(max(1.0, deadline - time.monotonic())) for child, _ in children]


# ---------------------------------------------------------------------------------------------------------------------
# What a case looks at


def _digest(path: Path) -> str:
    if path.is_symlink():
        return "link:" + os.fsdecode(os.readlink(path))
    if path.is_dir():
        return "dir"
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def snapshot(root: Path, skip: tuple[Path, ...] = ()) -> dict[Path, str]:
    """Every path under `root` (not under `skip`) and its content's hash."""
    found: dict[Path, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        dirnames[:] = [d for d in dirnames if here / d not in skip]
        for name in [*dirnames, *filenames]:
            path = here / name
            with contextlib.suppress(OSError):
                found[path] = _digest(path)
    return found


def top_new(before: dict[Path, str], after: dict[Path, str]) -> list[Path]:
    """Paths in `after` not in `before`, only the topmost of each new subtree."""
    new = sorted(set(after) - set(before))
    tops: list[Path] = []
    for path in new:
        if not any(top in path.parents for top in tops):
            tops.append(path)
    return tops


def shown_name(path: Path) -> str:
    """A file name as its bytes read (a byte that is no UTF-8 as \\xff), a newline as \\n."""
    name = os.fsencode(path.name).decode("utf-8", "backslashreplace").replace("\n", "\\n")
    return name if len(name) <= 60 else f"{name[:8]}...({len(name)} characters)"


def describe(path: Path, out: Path | None) -> str:
    name = shown_name(path)
    if out is not None and path == out:
        return f"{name}/ (output)" if path.is_dir() else f"{name} (output)"
    if out is not None and path in out.parents:
        return f"{name}/ (holds the output)"
    if name.startswith(".i2s-"):
        return f"{name} (staging)" if name.endswith((".partial", ".old", ".probe")) else f"{name} (lock)"
    if ".image2sim-" in name:
        return f"{name}/ (kept result)"
    return f"{name} (new)"


def _leaked(token: str) -> list[str]:
    """Processes whose environment carries `token`: a run's children still alive."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if token.encode() in (entry / "environ").read_bytes():
                found.append(f"{entry.name}:{(entry / 'comm').read_text().strip()}")
        except OSError:
            continue
    return found


@dataclass
class Row:
    case: str
    expect: str = ""
    got: str = ""
    last_line: str = ""
    left: str = ""
    user_files: str = ""
    ok: bool = True
    skipped: bool = False
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def fail(self, why: str) -> None:
        self.ok = False
        self.problems.append(why)


class Ctx:
    """A case's folder `ws` (the user's world: inputs, their files, the outputs) and its harness folder (TMPDIR, the
    CoACD cache), the environment its commands get, and the checks every case makes."""

    def __init__(self, ws: Path, row: Row) -> None:
        self.ws = ws
        self.row = row
        self.harness = ws / ".h"
        self.tmp = self.harness / "t"
        self.tmp.mkdir(parents=True)
        self.token = f"I2S_FAULTS_{os.getpid()}_{ws.name}"
        self.tokens: list[str] = []
        self._n = 0

    def env(self, *, tty: bool) -> dict[str, str]:
        env = dict(os.environ)
        env.update(MUJOCO_GL="osmesa", PYOPENGL_PLATFORM="osmesa", TMPDIR=str(self.tmp), COLUMNS="200")
        self._n += 1
        env["IMAGE2SIM_CACHE"] = str(self.harness / f"cache{self._n}")  # a fresh cache: stage times as on first use
        token = f"{self.token}_{self._n}"
        env["I2S_FAULTS_TOKEN"] = token
        self.tokens.append(token)
        if tty:
            env.pop("CI", None)  # progress is drawn to a terminal whatever CI says; leave it as a user's shell has it
        else:
            env["CI"] = "1"  # no progress on a pipe: stderr holds the lines a user or a CI log would read
        return env

    def start(self, *args: object, tty: bool = False) -> Child:
        return Child([BIN, *args], self.env(tty=tty), tty=tty)

    def run(self, *args: object, tty: bool = False, triggers: tuple[Trigger, ...] = (), timeout_s: float = 600) -> Run:
        return drive([(self.start(*args, tty=tty), list(triggers))], timeout_s)[0]

    def plant(self, folder: Path | None = None) -> None:
        """The user's own files beside where an output goes: a note, a folder with data, a name like a kept result's."""
        folder = folder or self.ws
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "notes.txt").write_text("my notes\n")
        (folder / "data").mkdir(exist_ok=True)
        (folder / "data" / "blob.bin").write_bytes(os.urandom(4096))
        (folder / "old.image2sim-mine").mkdir(exist_ok=True)
        (folder / "old.image2sim-mine" / "x.txt").write_text("not a kept result: the user's folder\n")

    def mark(self) -> dict[Path, str]:
        return snapshot(self.ws, skip=(self.harness,))

    def check_run(self, run: Run, want: set[int], *, line: str | None = None, contains: str | None = None) -> None:
        """The run ended with an exit code in `want` and without a crash; a non-zero one with exactly one
        `image2sim:` line, last on stderr (equal to `line`, or holding `contains`); a zero one with none."""
        row = self.row
        if run.timed_out:
            row.fail(f"timed out after {run.seconds:.0f} s")
        if run.rc not in want:
            crash = run.rc < 0 or run.rc in (134, 139)
            row.fail(f"{'crashed: ' if crash else ''}exit {run.rc}, wanted {'/'.join(map(str, sorted(want)))}")
        for mark in CRASH_MARKS:
            if mark in run.err_text or mark in run.stdout:
                row.fail(f"output holds {mark!r}")
        ours = [ln for ln in run.err_lines if ln.startswith("image2sim:")]
        if run.rc != 0:
            if len(ours) != 1:
                row.fail(f"{len(ours)} 'image2sim:' lines on stderr, wanted 1")
            elif run.last != ours[0]:
                row.fail(f"the 'image2sim:' line is not the last on stderr (last: {self.short(run.last)!r})")
            elif line is not None and ours[0] != line:
                row.fail(f"line is not {line!r}")
            elif contains is not None and contains not in ours[0]:
                row.fail(f"line does not say {contains!r}")
        elif ours:
            row.fail(f"exit 0 but stderr says {self.short(ours[0])!r}")

    def check_beside(self, before: dict[Path, str], *, out: Path | None, allowed: Callable[[Path], bool]) -> None:
        """Records what is new in the case folder (`left`) and whether the user's files are the same (`user_files`).

        `allowed(path)`: a new topmost path the case expects (the output, a kept result); anything else fails."""
        after = self.mark()
        new = top_new(before, after)
        inside_new = [p for p in after if any(t == p or t in p.parents for t in new)]
        changed = [p for p, h in before.items() if after.get(p) != h and p not in inside_new]
        shown = [describe(p, out) for p in new]
        for path in new:
            if not allowed(path):
                self.row.fail(f"left {describe(path, out)}")
        leftovers = [p.name for p in self.tmp.iterdir() if p.name != "ray"] if self.tmp.is_dir() else []
        if leftovers:
            shown.append(f"TMPDIR: {', '.join(sorted(leftovers)[:4])}")
            self.row.fail(f"left in TMPDIR: {', '.join(sorted(leftovers))}")
        self.row.left = ", ".join(self.short(s) for s in shown) or "nothing"
        missing = [p for p in changed if p not in after]
        altered = [p for p in changed if p in after]
        if missing or altered:
            parts = [f"missing {self.rel(p)}" for p in missing[:3]] + [f"changed {self.rel(p)}" for p in altered[:3]]
            self.row.user_files = "; ".join(parts)
            self.row.fail("user files changed: " + self.row.user_files)
        else:
            self.row.user_files = "same"

    def check_processes(self) -> None:
        """No process of this case's runs is left 10 s after they end (Ray's raylet, a worker, COLMAP threads...)."""
        deadline = time.monotonic() + 10
        while True:
            alive = [p for token in self.tokens for p in _leaked(token)]
            if not alive or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        if alive:
            self.row.fail(f"processes still alive: {', '.join(alive[:5])}")
            for pid in (int(p.split(":")[0]) for p in alive):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)

    def rel(self, path: Path) -> str:
        return self.short(os.fsdecode(path.relative_to(self.ws)) if self.ws in path.parents else str(path))

    def short(self, text: str) -> str:
        text = text.replace(str(self.ws), "WS")
        return os.fsencode(text).decode("utf-8", "backslashreplace")

    def result(self, run: Run, *, expect: str, line_of: Run | None = None) -> None:
        self.row.expect = expect
        self.row.got = str(run.rc) if not self.row.got else self.row.got
        self.row.last_line = self.short((line_of or run).last) or "(nothing)"
        if run.fired:
            self.row.notes.append("sent " + ", ".join(run.fired) + f" ({run.stage})")


def stage_at(run: Run) -> str:
    return run.stage


def is_output(path: Path) -> Callable[[Path], bool]:
    return lambda p: p == path


def nothing(_path: Path) -> bool:
    return False


def valid_output(folder: Path, marker: str) -> str | None:
    """Why `folder` is not a whole result (its marker JSON, and for a scene: the MJCF compiles), or None."""
    if not folder.is_dir():
        return f"{folder.name} is not there"
    try:
        json.loads((folder / marker).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return f"{marker} unreadable ({exc})"
    if marker == "scene.json":
        check = subprocess.run(
            [
                PY,
                "-c",
                "import mujoco, sys; mujoco.MjModel.from_xml_path(sys.argv[1])",
                os.fspath(folder / "scene.xml"),
            ],
            capture_output=True,
            text=True,
            env={**os.environ, "MUJOCO_GL": "osmesa"},
        )
        if check.returncode != 0:
            return f"scene.xml does not compile: {check.stderr.strip().splitlines()[-1:]}"
    return None


# ---------------------------------------------------------------------------------------------------------------------
# Inputs shared by the cases (made once per suite, copied into each case's folder)


class Fixtures:
    def __init__(self, root: Path) -> None:
        self.root = root
        self._trajs: Path | None = None
        self._recon: Path | None = None

    def trajs(self) -> Path:
        """~20 real cube tosses, imported with `image2sim import-trajectories --format dair-pll-cube`."""
        if self._trajs is None:
            src = self.root / "cube_src"
            (src / "tosses").mkdir(parents=True)
            tosses = sorted((CUBE_DATA / "tosses").glob("*.pt"), key=lambda p: int(p.stem))[:20]
            if not tosses:
                raise RuntimeError(f"no tosses in {CUBE_DATA / 'tosses'}")
            for toss in tosses:
                shutil.copy2(toss, src / "tosses" / toss.name)
            out = self.root / "trajs"
            done = subprocess.run(
                [BIN, "import-trajectories", src, "-o", out, "--format", "dair-pll-cube"],
                capture_output=True,
                text=True,
            )
            if done.returncode != 0:
                raise RuntimeError(f"import-trajectories failed: {done.stderr.strip()}")
            self._trajs = out
        return self._trajs

    def reconstruction(self) -> Path:
        """An earlier `reconstruct` output (for the cases that replace one)."""
        if self._recon is None:
            out = self.root / "recon"
            done = subprocess.run(
                [BIN, "reconstruct", VIDEO, "-o", out, *SCAN],
                capture_output=True,
                text=True,
                env={**os.environ, "CI": "1", "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"},
            )
            if done.returncode != 0:
                raise RuntimeError(f"reconstruct failed: {done.stderr.strip()}")
            self._recon = out
        return self._recon


FIX: Fixtures


def copy_trajs(ctx: Ctx, name: str = "trajs") -> Path:
    dst = ctx.ws / name
    shutil.copytree(FIX.trajs(), dst)
    return dst


def input_hashes() -> dict[Path, str]:
    return {p: _digest(p) for p in (VIDEO, CUBE_XML)}


# ---------------------------------------------------------------------------------------------------------------------
# Cases


def signal_ground(stage: str, signum: int, delay: float = 0.3) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        out = ctx.ws / "scene"
        ctx.plant()
        before = ctx.mark()
        run = ctx.run("ground", VIDEO, "-o", out, *SCAN, tty=True, triggers=(on_stage(stage, send(signum), delay),))
        ctx.result(run, expect=str(128 + signum))
        if not run.fired:
            ctx.row.fail(f"the run ended (exit {run.rc}) before '{stage}' + {delay} s")
        ctx.check_run(run, {128 + signum}, line=STOPPED_LINE[signal.Signals(signum)])
        ctx.check_beside(before, out=out, allowed=nothing)
        ctx.check_processes()

    return case


def signal_calibrate(stage: str, signum: int) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        trajs = copy_trajs(ctx)
        out = ctx.ws / "calibrated"
        ctx.plant()
        before = ctx.mark()
        run = ctx.run(
            "calibrate", CUBE_XML, trajs, "-o", out, *CAL_FAST, tty=True, triggers=(on_stage(stage, send(signum)),)
        )
        ctx.result(run, expect=str(128 + signum))
        if not run.fired:
            ctx.row.fail(f"the run ended (exit {run.rc}) before '{stage}'")
        ctx.check_run(run, {128 + signum}, line=STOPPED_LINE[signal.Signals(signum)])
        ctx.check_beside(before, out=out, allowed=nothing)
        ctx.check_processes()

    return case


def write_jobs(ctx: Ctx, ids: list[str], trajs: Path, settings: dict[str, dict] | None = None) -> Path:
    import yaml

    jobs = [
        {"id": i, "scene": str(CUBE_XML), "trajectories": str(trajs), "settings": (settings or {}).get(i, {})}
        for i in ids
    ]
    path = ctx.ws / "jobs.yaml"
    path.write_text(yaml.safe_dump({"defaults": JOB_SETTINGS, "jobs": jobs}))
    return path


def check_table(ctx: Ctx, out: Path, ids: list[str], run: Run | None = None) -> None:
    """results.csv and results.json agree with results/<id>.json; a stop line's K is the table's ok count; no
    temporary files in results/; scenes/ holds only the scenes of ok jobs."""
    row = ctx.row
    try:
        with open(out / "results.csv", newline="", encoding="utf-8") as f:
            table = {r["id"]: r["status"] for r in csv.DictReader(f)}
        listed = {r["id"]: r["status"] for r in json.loads((out / "results.json").read_text(encoding="utf-8"))}
    except (OSError, ValueError, KeyError) as exc:
        row.fail(f"no readable table ({exc})")
        return
    if list(table) != ids:
        row.fail(f"results.csv lists {list(table)}, jobs are {ids}")
    if listed != table:
        row.fail("results.json and results.csv disagree")
    for job_id in ids:
        record_path = out / "results" / f"{job_id}.json"
        record = json.loads(record_path.read_text(encoding="utf-8")) if record_path.is_file() else None
        want = record["status"] if record else "pending"
        if table.get(job_id) != want:
            row.fail(f"results.csv says {job_id} {table.get(job_id)}, its record {want}")
    oks = sum(s == "ok" for s in table.values())
    row.notes.append(f"table: {oks} ok of {len(table)}")
    if run is not None:
        m = re.search(r"with (\d+) of (\d+) jobs finished", run.last)
        if m and (int(m.group(1)), int(m.group(2))) != (oks, len(ids)):
            row.fail(f"line says {m.group(1)} of {m.group(2)} finished, the table {oks} of {len(ids)}")
    temporary = [p.name for sub in ("results", "scenes") if (out / sub).is_dir() for p in (out / sub).iterdir()]
    stray = [n for n in temporary if n.startswith(".")]
    if stray:
        ctx.row.left += f"; inside: {', '.join(sorted(stray)[:4])}"
        row.fail(f"left inside the batch output: {', '.join(sorted(stray))}")
    scenes = (
        {p.name for p in (out / "scenes").iterdir() if not p.name.startswith(".")}
        if (out / "scenes").is_dir()
        else set()
    )
    if scenes - {i for i, s in table.items() if s == "ok"}:
        row.fail(f"scenes/ holds {sorted(scenes)} for ok jobs {sorted(i for i, s in table.items() if s == 'ok')}")


BATCH_STOP = re.compile(
    r"^image2sim: batch stopped \((SIGINT|SIGTERM)\) (with \d+ of \d+ jobs finished|before any job)"
)


def signal_batch(moment: str, signum: int, *, resume: bool = False) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        trajs = copy_trajs(ctx)
        ids = ["a", "b", "c"]
        jobs = write_jobs(ctx, ids, trajs)
        out = ctx.ws / "batch_out"
        ctx.plant()
        before = ctx.mark()
        if moment == "first record":
            trig = when_exists(lambda: any((out / "results").glob("*.json")), send(signum))
        elif moment == "ray start":
            trig = when_exists(lambda: (ctx.tmp / "ray").exists(), send(signum), delay=0.5)
        else:
            trig = at_time(float(moment.rstrip("s")), send(signum))
        run = ctx.run("batch", jobs, "-o", out, "--num-cpus", "1", tty=True, triggers=(trig,))
        ctx.result(run, expect=str(128 + signum))
        if not run.fired:
            ctx.row.fail(f"the run ended (exit {run.rc}) before the signal")
        ctx.check_run(run, {128 + signum})
        if run.err_lines and run.rc == 128 + signum:
            if not (BATCH_STOP.match(run.last) or run.last == STOPPED_LINE[signal.Signals(signum)]):
                ctx.row.fail("the line is neither batch's stop line nor the stopped line")
            if moment == "first record" and not BATCH_STOP.match(run.last):
                ctx.row.fail("not batch's stop line")
        # A stop leaves a resumable batch output, or (stopped before it was made) nothing.
        ctx.check_beside(before, out=out, allowed=is_output(out))
        if out.exists():
            check_table(ctx, out, ids, run)
        ctx.check_processes()
        if resume:
            again = ctx.run("batch", jobs, "-o", out, "--num-cpus", "1")
            ctx.row.got = f"{run.rc}, resume {again.rc}"
            ctx.row.expect += ", resume 0"
            ctx.check_run(again, {0})
            finished = re.search(r"(\d+) already finished, (\d+) run now", again.stdout)
            ctx.row.notes.append(f"resume: {finished.group(0) if finished else again.stdout.strip()[-80:]}")
            check_table(ctx, out, ids)
            ctx.check_processes()

    return case


@contextlib.contextmanager
def tmpfs(ctx: Ctx, size: str) -> Iterator[Path | None]:
    """A tmpfs of `size` mounted at WS/disk, unmounted on the way out; None (case skipped) where mount fails."""
    disk = ctx.ws / "disk"
    disk.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", disk], capture_output=True, text=True)
    if done.returncode != 0:
        ctx.row.skipped = True
        ctx.row.notes.append(f"mount failed ({done.stderr.strip() or done.returncode}): skipped")
        yield None
        return
    try:
        yield disk
    finally:
        for _attempt in range(10):
            if subprocess.run(["umount", disk], capture_output=True).returncode == 0:
                break
            time.sleep(0.5)
        else:
            subprocess.run(["umount", "-l", disk], capture_output=True)
            ctx.row.fail("tmpfs busy at the end (lazy unmount)")


def used_bytes(disk: Path) -> int:
    st = os.statvfs(disk)
    return (st.f_blocks - st.f_bfree) * st.f_frsize


def fill(disk: Path, leave: int = 0) -> Path:
    """Fills `disk` up (another program's big file) to within `leave` bytes of full."""
    filler = disk / "filler.bin"
    with open(filler, "ab") as f:
        for chunk in (1 << 20, 1 << 16, 4096):
            while True:
                free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
                if free - chunk < leave:
                    break
                try:
                    f.write(b"\0" * chunk)
                    f.flush()
                except OSError as exc:
                    if exc.errno != errno.ENOSPC:
                        raise
                    break
    return filler


def disk_case(
    command: str, size: str, *, fill_at: str | None = None, prefill: int | None = None, delay: float = 0.0
) -> Callable[[Ctx], None]:
    """`command` with -o on a small tmpfs, full from the start (`prefill`: bytes left free), too small for the run,
    or filled by another program when stage `fill_at` starts. Wants exit 2 and the no-space line, the user's file
    on the disk intact, and the disk as it was before (the filler removed)."""

    def case(ctx: Ctx) -> None:
        with tmpfs(ctx, size) as disk:
            if disk is None:
                return
            (disk / "mine.txt").write_bytes(os.urandom(2048))
            out = disk / "out"
            args: list[object]
            if command in ("calibrate", "rollout"):
                args = [command, CUBE_XML, copy_trajs(ctx), "-o", out]
                args += CAL_FAST if command == "calibrate" else []
            elif command == "import-trajectories":
                FIX.trajs()  # made from the tosses copied to fixtures/cube_src
                args = [command, FIX.root / "cube_src", "-o", out, "--format", "dair-pll-cube"]
            else:
                args = [command, VIDEO, "-o", out, *SCAN]
            ctx.plant()
            before = ctx.mark()
            used_before = used_bytes(disk)
            filler: list[Path] = []
            if prefill is not None:
                filler.append(fill(disk, prefill))
            triggers = ()
            if fill_at is not None:
                triggers = (on_stage(fill_at, lambda c: filler.append(fill(disk)), delay),)
            run = ctx.run(*args, tty=True, triggers=triggers)
            for f in filler:
                f.unlink()
            ctx.result(run, expect="2")
            ctx.row.notes.append(f"failed at: {run.stage}")
            if fill_at is not None and not filler:
                ctx.row.fail(f"the run ended before '{fill_at}'")
            ctx.check_run(run, {2})
            if run.rc == 2 and not ("no space left on the disk" in run.last or "needs about" in run.last):
                ctx.row.fail("the line does not say the disk is full")
            ctx.check_beside(before, out=out, allowed=nothing)
            if used_bytes(disk) != used_before:
                ctx.row.fail(f"the disk holds {used_bytes(disk) - used_before} bytes more than before")
            ctx.check_processes()

    return case


def concurrent(command: str) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        out = ctx.ws / "out"
        ctx.plant()
        before = ctx.mark()
        first = ctx.start(command, VIDEO, "-o", out, *SCAN)
        time.sleep(2.0)
        second = ctx.start(command, VIDEO, "-o", out, *SCAN)
        run1, run2 = drive([(first, []), (second, [])], 900)
        ctx.result(run2, expect="0, 2")
        ctx.row.got = f"{run1.rc}, {run2.rc}"
        ctx.check_run(run1, {0})
        ctx.check_run(run2, {2}, contains=f"another image2sim run (process {run1.pid}) is writing to")
        problem = valid_output(out, "scene.json" if command == "ground" else "reconstruct.json")
        if problem:
            ctx.row.fail(f"first run's result: {problem}")
        ctx.row.notes.append(f"second refused after {run2.seconds:.1f} s")
        ctx.check_beside(before, out=out, allowed=is_output(out))
        ctx.check_processes()

    return case


def appears(command: str, *, overwrite: bool) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        out = ctx.ws / "out"
        ctx.plant()
        before = ctx.mark()

        def someone_writes(_c: Child) -> None:
            out.mkdir()
            (out / "notes.txt").write_text("someone else's notes\n")

        extra = ["--overwrite"] if overwrite else []
        run = ctx.run(command, VIDEO, "-o", out, *SCAN, *extra, triggers=(at_time(3.0, someone_writes),))
        ctx.result(run, expect="2")
        ctx.check_run(run, {2}, contains="the result is kept, complete, in")
        kept = [p for p in out.parent.iterdir() if p.name.startswith("out.image2sim-")]
        if len(kept) != 1:
            ctx.row.fail(f"{len(kept)} kept results beside the output")
        else:
            if ctx.short(str(kept[0])) not in ctx.short(run.last):
                ctx.row.fail("the line does not name the kept folder")
            problem = valid_output(kept[0], "scene.json" if command == "ground" else "reconstruct.json")
            if problem:
                ctx.row.fail(f"kept result: {problem}")
        if sorted(p.name for p in out.iterdir()) != ["notes.txt"] or (out / "notes.txt").read_text() != (
            "someone else's notes\n"
        ):
            ctx.row.fail("the folder that appeared was changed")
        ctx.check_beside(before, out=out, allowed=lambda p: p == out or p in kept)
        ctx.check_processes()

    return case


def killed(command: str, stage: str, *, over_old: bool) -> Callable[[Ctx], None]:
    """SIGKILL at `stage` (with `over_old`: --overwrite over an earlier output, which must stay as it was), then the
    same command on the same -o: exit 0, and nothing the killed run left remains."""

    def case(ctx: Ctx) -> None:
        out = ctx.ws / "out"
        ctx.plant()
        extra: list[str] = []
        if over_old:
            shutil.copytree(FIX.reconstruction(), out)
            extra = ["--overwrite"]
        before = ctx.mark()
        marker = "scene.json" if command == "ground" else "reconstruct.json"
        run = ctx.run(command, VIDEO, "-o", out, *SCAN, *extra, tty=True, triggers=(on_stage(stage, send(9)),))
        if not run.fired:
            ctx.row.fail(f"the run ended (exit {run.rc}) before '{stage}'")
        if run.rc != -9:
            ctx.row.fail(f"killed run exit {run.rc}, wanted -9")
        after_kill = top_new(before, ctx.mark())
        ctx.row.notes.append("after the kill: " + (", ".join(describe(p, out) for p in after_kill) or "nothing"))
        if over_old:
            still = snapshot(out)
            if still != {p: h for p, h in before.items() if out in p.parents}:
                ctx.row.fail("the earlier output changed when the run was killed")
        ctx.check_processes()
        again = ctx.run(command, VIDEO, "-o", out, *SCAN, *extra)
        ctx.result(again, expect="-9, 0")
        ctx.row.got = f"{run.rc}, {again.rc}"
        ctx.check_run(again, {0})
        problem = valid_output(out, marker)
        if problem:
            ctx.row.fail(f"re-run's result: {problem}")
        # The earlier output is replaced on purpose (--overwrite): leave it out of the user's files.
        kept_before = {p: h for p, h in before.items() if not (over_old and (p == out or out in p.parents))}
        ctx.check_beside(kept_before, out=out, allowed=is_output(out))
        ctx.check_processes()

    return case


def sigterm_over_old(ctx: Ctx) -> None:
    """SIGTERM during `reconstruct --overwrite` over an earlier output: that output is left as it was."""
    out = ctx.ws / "out"
    ctx.plant()
    shutil.copytree(FIX.reconstruction(), out)
    before = ctx.mark()
    trig = on_stage("registering frames", send(signal.SIGTERM))
    run = ctx.run("reconstruct", VIDEO, "-o", out, *SCAN, "--overwrite", tty=True, triggers=(trig,))
    ctx.result(run, expect="143")
    if not run.fired:
        ctx.row.fail("the run ended before the signal")
    ctx.check_run(run, {143}, line=STOPPED_LINE[signal.SIGTERM])
    ctx.check_beside(before, out=out, allowed=nothing)
    ctx.check_processes()


def edited_batch(ctx: Ctx) -> None:
    trajs = copy_trajs(ctx)
    ids = ["a", "b"]
    jobs = write_jobs(ctx, ids, trajs, {"a": {"seed": 1}, "b": {"seed": 1}})
    out = ctx.ws / "batch_out"
    ctx.plant()
    first = ctx.run("batch", jobs, "-o", out, "--num-cpus", "1")
    ctx.check_run(first, {0})
    record_a = (out / "results" / "a.json").read_bytes() if (out / "results" / "a.json").is_file() else b""
    jobs = write_jobs(ctx, ids, trajs, {"a": {"seed": 1}, "b": {"seed": 2}})  # the user edits job b
    before = ctx.mark()
    again = ctx.run("batch", jobs, "-o", out, "--num-cpus", "1")
    ctx.result(again, expect="0, 0")
    ctx.row.got = f"{first.rc}, {again.rc}"
    ctx.check_run(again, {0})
    said = " ".join(again.err_text.split())
    if not re.search(r"job b: [^.]*settings[^.]*re-running", said):
        ctx.row.fail("no warning saying job b re-runs because its settings changed")
    if re.search(r"job a: .*re-running", said):
        ctx.row.fail("job a re-ran")
    if "2 jobs: 1 already finished, 1 run now, 0 failed" not in again.stdout:
        ctx.row.fail(f"summary: {again.stdout.strip()[-100:]!r}")
    if (out / "results" / "a.json").read_bytes() != record_a:
        ctx.row.fail("job a's record was rewritten")
    warning = next((ln for ln in again.err_lines if "job b" in ln), "")
    ctx.row.notes.append(f"warning: {warning[:140]}")
    check_table(ctx, out, ids)
    # The batch output is the command's to rewrite; the rest of the folder is the user's.
    ctx.check_beside(
        {p: h for p, h in before.items() if p != out and out not in p.parents}, out=out, allowed=is_output(out)
    )
    ctx.check_processes()


def odd_reconstruct(ctx: Ctx) -> None:
    src = ctx.ws / ODD
    src.mkdir()
    video = src / os.fsdecode(b"v_\xe9.mp4")
    shutil.copy2(VIDEO, video)
    out = ctx.ws / os.fsdecode(b"out_\xff") / os.fsdecode(b"sc\xe8ne")
    ctx.plant()
    before = ctx.mark()
    run = ctx.run("reconstruct", video, "-o", out, *SCAN)
    ctx.result(run, expect="0")
    ctx.check_run(run, {0})
    problem = valid_output(out, "reconstruct.json")
    if problem:
        ctx.row.fail(problem)
    ctx.check_beside(before, out=out, allowed=lambda p: p == out.parent)
    ctx.check_processes()


def odd_scene(command: str) -> Callable[[Ctx], None]:
    def case(ctx: Ctx) -> None:
        scene_dir = ctx.ws / os.fsdecode(b"sc\xe8nes_\xff")
        scene_dir.mkdir()
        scene = scene_dir / os.fsdecode(b"cube_\xfe.xml")
        shutil.copy2(CUBE_XML, scene)
        trajs = copy_trajs(ctx, os.fsdecode(b"traj_\xff"))
        out = ctx.ws / os.fsdecode(b"out_\xff\xfe")
        ctx.plant()
        before = ctx.mark()
        run = ctx.run(command, scene, trajs, "-o", out, *(CAL_FAST if command == "calibrate" else []))
        ctx.result(run, expect="0")
        ctx.check_run(run, {0})
        problem = valid_output(out, "calibration.json" if command == "calibrate" else "rollout.json")
        if problem:
            ctx.row.fail(problem)
        ctx.check_beside(before, out=out, allowed=is_output(out))
        ctx.check_processes()

    return case


def long_name(ctx: Ctx) -> None:
    out = ctx.ws / ("g" * 250)
    ctx.plant()
    before = ctx.mark()
    run = ctx.run("ground", VIDEO, "-o", out, *SCAN)
    ctx.result(run, expect="0")
    ctx.check_run(run, {0})
    problem = valid_output(out, "scene.json")
    if problem:
        ctx.row.fail(problem)
    ctx.check_beside(before, out=out, allowed=is_output(out))
    ctx.check_processes()


def newline_name(ctx: Ctx) -> None:
    out = ctx.ws / "my scan\nof the table"
    ctx.plant()
    before = ctx.mark()
    run = ctx.run("reconstruct", VIDEO, "-o", out, *SCAN)
    ctx.result(run, expect="0")
    ctx.check_run(run, {0})
    problem = valid_output(out, "reconstruct.json")
    if problem:
        ctx.row.fail(problem)
    ctx.check_beside(before, out=out, allowed=is_output(out))
    ctx.check_processes()


# ---------------------------------------------------------------------------------------------------------------------
# The suite

GROUND_STAGES = (  # stage, delay (s): "writing MJCF" lasts under a second
    ("reading frames", 0.3),
    ("extracting SIFT features", 0.3),
    ("matching", 0.3),
    ("registering frames", 0.3),
    ("dense stereo", 0.3),
    ("meshing objects", 0.3),
    ("baking textures", 0.3),
    ("collision hulls", 0.3),
    ("writing MJCF", 0.1),
)
QUICK = {
    "ground SIGINT at extracting SIFT features",
    "ground SIGTERM at dense stereo",
    "calibrate SIGTERM at global search",
    "batch SIGTERM after first record + resume",
    "disk full: ground on 1m tmpfs",
    "disk full: import-trajectories on full tmpfs",
    "concurrent: reconstruct twice on one -o",
    "folder appears at -o: reconstruct",
    "SIGKILL at matching, re-run: reconstruct --overwrite over old output",
    "odd path: reconstruct (non-UTF-8 input and -o)",
    "odd path: rollout (non-UTF-8 scene, trajectories, -o)",
}


def cases() -> list[tuple[str, Callable[[Ctx], None]]]:
    found: list[tuple[str, Callable[[Ctx], None]]] = []
    for stage, delay in GROUND_STAGES:
        for signum in (signal.SIGINT, signal.SIGTERM):
            found.append((f"ground {signum.name} at {stage}", signal_ground(stage, signum, delay)))
    for stage in ("global search", "local refinement"):
        for signum in (signal.SIGINT, signal.SIGTERM):
            found.append((f"calibrate {signum.name} at {stage}", signal_calibrate(stage, signum)))
    found += [
        ("batch SIGINT at 1 s", signal_batch("1s", signal.SIGINT)),
        ("batch SIGTERM during Ray start-up", signal_batch("ray start", signal.SIGTERM)),
        ("batch SIGINT after first record", signal_batch("first record", signal.SIGINT)),
        ("batch SIGTERM after first record + resume", signal_batch("first record", signal.SIGTERM, resume=True)),
        ("disk full: ground on 1m tmpfs", disk_case("ground", "1m")),
        ("disk full: ground on 4m tmpfs", disk_case("ground", "4m")),
        ("disk full: ground on 10m tmpfs", disk_case("ground", "10m")),
        ("disk fills at matching: ground", disk_case("ground", "48m", fill_at="matching", delay=0.5)),
        ("disk fills at registering frames: ground", disk_case("ground", "48m", fill_at="registering frames")),
        ("disk fills at dense stereo: ground", disk_case("ground", "48m", fill_at="dense stereo", delay=0.3)),
        ("disk fills at meshing objects: ground", disk_case("ground", "48m", fill_at="meshing objects", delay=0.3)),
        ("disk fills at writing MJCF: ground", disk_case("ground", "48m", fill_at="writing MJCF")),
        ("disk full: calibrate on full tmpfs", disk_case("calibrate", "2m", prefill=0)),
        ("disk full: import-trajectories on full tmpfs", disk_case("import-trajectories", "2m", prefill=0)),
        ("disk full: import-trajectories, 100 KB free", disk_case("import-trajectories", "2m", prefill=100_000)),
        ("disk full: rollout on full tmpfs", disk_case("rollout", "2m", prefill=0)),
        ("concurrent: ground twice on one -o", concurrent("ground")),
        ("concurrent: reconstruct twice on one -o", concurrent("reconstruct")),
        ("folder appears at -o: reconstruct", appears("reconstruct", overwrite=False)),
        ("folder appears at -o: ground --overwrite", appears("ground", overwrite=True)),
        ("SIGKILL at dense stereo, re-run: ground", killed("ground", "dense stereo", over_old=False)),
        (
            "SIGKILL at matching, re-run: reconstruct --overwrite over old output",
            killed("reconstruct", "matching", over_old=True),
        ),
        ("SIGTERM: reconstruct --overwrite keeps old output", sigterm_over_old),
        ("batch: edited job re-runs, other skipped", edited_batch),
        ("odd path: reconstruct (non-UTF-8 input and -o)", odd_reconstruct),
        ("odd path: rollout (non-UTF-8 scene, trajectories, -o)", odd_scene("rollout")),
        ("odd path: calibrate (non-UTF-8 scene, trajectories, -o)", odd_scene("calibrate")),
        ("odd path: ground -o of 250 characters", long_name),
        ("odd path: reconstruct -o with spaces and a newline", newline_name),
    ]
    return found


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", "\\n")


HEADER = "| case | exit want | exit got | stderr last line | left beside the output | user files | result |"


def format_row(row: Row) -> str:
    verdict = "skip" if row.skipped else ("PASS" if row.ok else "FAIL: " + "; ".join(row.problems))
    if row.notes:
        verdict += " (" + "; ".join(row.notes) + ")"
    cells = [row.case, row.expect, row.got, row.last_line, row.left, row.user_files, verdict]
    return "| " + " | ".join(_cell(c) for c in cells) + " |"


def run_case(root: Path, index: int, name: str, fn: Callable[[Ctx], None]) -> Row:
    row = Row(case=name)
    ws = root / f"c{index:02d}"
    ctx = Ctx(ws, row)
    inputs = input_hashes()
    tick = time.monotonic()
    try:
        fn(ctx)
    except Exception as exc:  # the harness itself failed: the case fails, the suite goes on
        import traceback

        row.fail(f"harness error: {type(exc).__name__}: {exc}")
        traceback.print_exc(file=sys.stderr)
    if input_hashes() != inputs:
        row.fail("the sample inputs changed")
    row.seconds = time.monotonic() - tick
    return row


def main() -> int:
    global FIX
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a subset, a few minutes")
    parser.add_argument("--only", metavar="PATTERN", help="the cases whose name matches this regular expression")
    parser.add_argument("--json", type=Path, metavar="PATH", help="write the rows here as JSON")
    parser.add_argument("--keep", action="store_true", help="keep the work folders (printed at the end)")
    args = parser.parse_args()
    selected = [
        (n, f) for n, f in cases() if (not args.quick or n in QUICK) and (not args.only or re.search(args.only, n))
    ]
    if not selected:
        print("no case matches", file=sys.stderr)
        return 2
    root = Path(tempfile.mkdtemp(prefix="i2sf-", dir="/tmp"))  # short: Ray's socket paths live under TMPDIR
    FIX = Fixtures(root / "fixtures")
    tick = time.monotonic()
    rows: list[Row] = []
    print(f"{len(selected)} cases; {os.cpu_count()} CPU cores", flush=True)
    print(HEADER)
    print("|" + "---|" * 7, flush=True)
    try:
        for index, (name, fn) in enumerate(selected):
            row = run_case(root, index, name, fn)
            rows.append(row)
            print(format_row(row), flush=True)
    finally:
        wall_s = time.monotonic() - tick
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    passed = sum(r.ok and not r.skipped for r in rows)
    failed = sum(not r.ok for r in rows)
    skipped = sum(r.skipped and r.ok for r in rows)
    print(
        f"wall time {wall_s / 60:.1f} min"
        + (f"; {skipped} skipped" if skipped else "")
        + (f"; work folders kept in {root}" if args.keep else "")
    )
    print(f"{passed} passed, {failed} failed")
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "rows": [asdict(r) for r in rows],
                    "passed": passed,
                    "failed": failed,
                    "skipped": skipped,
                    "wall_s": wall_s,
                    "cpus": os.cpu_count(),
                },
                indent=1,
            )
        )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
