"""Batch calibration: the jobs file, failure isolation, resuming after a kill on a real local Ray, Ray addresses."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

import grounder.sim.rollout as sim
from grounder.calibration.batch import ray_init_kwargs, run_batch
from grounder.calibration.batch_jobs import load_jobs
from grounder.calibration.batch_output import read_result
from grounder.core.trajectory import Trajectory, save_trajectories
from grounder.errors import GrounderError
from tests.conftest import claim_held_by_another_process

REPO = Path(__file__).resolve().parents[3]
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"
TINY = {"params": ["cube.friction.sliding"], "generations": 1, "popsize": 2, "local_iterations": 0}


@pytest.fixture(scope="module")
def traj_dir(tmp_path_factory) -> Path:
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    rng = np.random.default_rng(0)
    seeds = []
    for i in range(3):
        qpos = np.array([0, 0, 0.12, 1, 0, 0, 0], dtype=float)
        qvel = np.concatenate([rng.uniform(-1, 1, 2), [-0.5], rng.uniform(-3, 3, 3)])
        seeds.append(
            Trajectory(
                time_s=np.arange(40) / 148.0, qpos=np.tile(qpos, (40, 1)), qvel=np.tile(qvel, (40, 1)), name=f"t{i}"
            )
        )
    return save_trajectories(sim.simulate(model, seeds), tmp_path_factory.mktemp("batch") / "trajs")  # type: ignore[arg-type]


def _write_jobs(path: Path, jobs: list[dict], **extra: object) -> Path:
    import yaml

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({"defaults": TINY, "jobs": jobs, **extra}))
    return path


def test_jobs_file(tmp_path: Path, traj_dir: Path) -> None:
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [{"id": "one", "scene": str(CUBE_XML), "trajectories": str(traj_dir), "settings": {"seed": 3}}],
        matrix={"scenes": [str(CUBE_XML)], "trajectories": [str(traj_dir)], "settings": {"a": {}, "b": {"popsize": 3}}},
    )
    jobs = load_jobs(jobs_file)
    assert [j.id for j in jobs] == ["one", "cube__trajs__a", "cube__trajs__b"]
    assert jobs[0].settings["seed"] == 3 and jobs[0].settings["generations"] == 1
    assert jobs[2].settings["popsize"] == 3

    bad = tmp_path / "bad.yaml"
    _write_jobs(bad, [{"scene": "a.xml", "trajectories": "d", "settings": {"popsze": 3}}])
    with pytest.raises(GrounderError, match="unknown setting"):
        load_jobs(bad)
    _write_jobs(bad, [{"id": "x", "scene": "a.xml", "trajectories": "d"}] * 2)
    with pytest.raises(GrounderError, match="appears twice"):
        load_jobs(bad)
    bad.write_text("jobs: []\n")
    with pytest.raises(GrounderError, match="no job"):
        load_jobs(bad)


def test_home_folder_in_jobs_file_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`scene: ~/scenes/cube.xml` was read as a folder named `~` beside the jobs file: a YAML file is not expanded by
    a shell, so the loader expands ~ as one would. Relative paths stay relative to the file."""
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    jobs_file = _write_jobs(
        tmp_path / "work" / "jobs.yaml", [{"id": "j", "scene": "~/scenes/cube.xml", "trajectories": "data"}]
    )
    (job,) = load_jobs(jobs_file)
    assert job.scene == home / "scenes" / "cube.xml"
    assert job.trajectories == tmp_path / "work" / "data"


def test_failing_job_is_recorded_and_others_finish(tmp_path: Path, traj_dir: Path) -> None:
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [
            {"id": "good", "scene": str(CUBE_XML), "trajectories": str(traj_dir)},
            {"id": "empty", "scene": str(CUBE_XML), "trajectories": str(tmp_path)},
            {
                "id": "bad_param",
                "scene": str(CUBE_XML),
                "trajectories": str(traj_dir),
                "settings": {"params": ["cube.nope"]},
            },
        ],
    )
    out = tmp_path / "out"
    summary = run_batch(load_jobs(jobs_file), out, inline=True)
    assert set(summary.ran) == {"good", "empty", "bad_param"}
    assert set(summary.failed) == {"empty", "bad_param"}
    assert "no .npz" in (read_result(out, "empty") or {})["error"]
    assert "unknown parameter" in (read_result(out, "bad_param") or {})["error"]
    good = read_result(out, "good")
    assert good is not None and good["status"] == "ok" and "cube.friction.sliding" in good["parameters"]
    assert (out / "scenes" / "good" / "scene.xml").is_file()
    rows = json.loads((out / "results.json").read_text())
    assert [r["id"] for r in rows] == ["good", "empty", "bad_param"]
    assert (out / "results.csv").read_text().count("\n") == 4

    again = run_batch(load_jobs(jobs_file), out, inline=True)
    assert again.skipped == ("good",) and set(again.ran) == {"empty", "bad_param"}
    assert read_result(out, "good") == good


def test_a_missing_path_in_the_jobs_file_is_refused_before_any_job(tmp_path: Path, traj_dir: Path) -> None:
    """A scene or trajectory folder that is not there is known before Ray starts: one line, exit 2, no output
    folder, and the good jobs are not run either (fixing the path and running again runs them all once)."""
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [
            {"id": "good", "scene": str(CUBE_XML), "trajectories": str(traj_dir)},
            {"id": "missing_scene", "scene": "nope.xml", "trajectories": str(traj_dir)},
            {"id": "missing_data", "scene": str(CUBE_XML), "trajectories": "no_such_folder"},
        ],
    )
    out = tmp_path / "out"
    with pytest.raises(
        GrounderError, match=r"job missing_scene: scene .*nope.xml is not an existing scene \(and 1 more"
    ):
        run_batch(load_jobs(jobs_file), out, inline=True)
    assert not out.exists()
    _one_error_line(_cli(["batch", str(jobs_file), "-o", str(out)]), "nope.xml", "fix the path in the jobs file")
    assert not out.exists()


def test_ray_address_is_passed_through(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, traj_dir: Path) -> None:
    import ray

    assert ray_init_kwargs("head:6379", None)["address"] == "head:6379"
    local = ray_init_kwargs(None, 1)
    assert local["num_cpus"] == 1 and "address" not in local and local["include_dashboard"] is False

    seen: dict[str, object] = {}

    class Connected(Exception):
        pass

    def fake_init(**kwargs: object) -> None:
        seen.update(kwargs)
        raise Connected

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", fake_init)
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml", [{"id": "a", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}]
    )
    with socket.create_server(("127.0.0.1", 0)) as head:  # something listening, as a head node's GCS port does
        address = f"127.0.0.1:{head.getsockname()[1]}"
        with pytest.raises(Connected):
            run_batch(load_jobs(jobs_file), tmp_path / "out", address=address)
    assert seen["address"] == address
    assert not (tmp_path / "out").exists()  # connecting comes first: a failed join leaves no output folder


@pytest.mark.parametrize(
    ("address", "why"),
    [
        ("garbage", "not a Ray cluster address"),
        ("head:99999", "not a Ray cluster address"),
        ("127.0.0.1:{free}", "nothing answers at 127.0.0.1"),
        ("ray://127.0.0.1:{free}", "ray[client]"),
    ],
)
def test_an_unusable_ray_address_is_one_clear_error_and_leaves_no_output(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, traj_dir: Path, address: str, why: str
) -> None:
    import importlib.util

    import ray

    def must_not_init(**kwargs: object) -> None:
        raise AssertionError(f"ray.init called with {kwargs}")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", must_not_init)
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "grpc" else real_find_spec(name))
    with socket.create_server(("127.0.0.1", 0)) as probe:
        free = probe.getsockname()[1]  # closed again below: nothing listens there
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml", [{"id": "a", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}]
    )
    with pytest.raises(GrounderError, match=re.escape(why)):
        run_batch(load_jobs(jobs_file), tmp_path / "out", address=address.format(free=free))
    assert not (tmp_path / "out").exists()


def _session_pids(sid: int) -> list[int]:
    """Processes of a session (the run and every Ray process it started, workers included)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == sid:  # state, ppid, pgrp, session
            pids.append(int(stat.parent.name))
    return pids


def _kill_session(sid: int) -> None:
    """SIGKILL every process of the session we started, until none is left: a crash of the whole run."""
    deadline = time.monotonic() + 30
    while (pids := _session_pids(sid)) and time.monotonic() < deadline:
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        time.sleep(0.1)
    assert not _session_pids(sid), "processes of the killed run survived"


# Safety nets only: how long a test waits for an event (a result record, the run's exit) before it gives up. Each
# wait ends as soon as the event happens; the verdict never rests on how fast the machine is.
_EVENT_BOUND_S = 900.0


def _ok_records(out: Path, job_ids: list[str]) -> list[str]:
    return [j for j in job_ids if (read_result(out, j) or {}).get("status") == "ok"]


def _wait_for_a_finished_job(proc: subprocess.Popen, out: Path, job_ids: list[str]) -> list[str]:
    """Waits until some job's result record says ok (the run is midway), or fails if the run ends first."""
    bound = time.monotonic() + _EVENT_BOUND_S
    while not (finished := _ok_records(out, job_ids)):
        if proc.poll() is not None:
            pytest.fail(f"the run ended (exit {proc.returncode}) before any job finished: {proc.communicate()[1]!r}")
        if time.monotonic() > bound:
            pytest.fail(f"no job finished in {_EVENT_BOUND_S:.0f} s (the safety bound of this wait)")
        time.sleep(0.05)
    return finished


def _wait_for_session_end(sid: int) -> None:
    """Waits until no process of the session is left (Ray's services and workers exit after the driver)."""
    bound = time.monotonic() + _EVENT_BOUND_S
    while _session_pids(sid) and time.monotonic() < bound:
        time.sleep(0.1)


def _batch_cmd(jobs_file: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "grounder.cli", "batch", str(jobs_file), "-o", str(out), "--num-cpus", "1"]


# Ray (no auth prompt); CI: no progress bar on a pipe, so stderr holds only the run's messages.
_RUN_ENV = {**os.environ, "RAY_AUTH_MODE": "disabled", "CI": "1"}


def _start_batch(cmd: list[str]) -> subprocess.Popen:
    """The batch in its own session, with SIGINT as a shell gives it (a test runner's worker may ignore SIGINT,
    and an ignored signal stays ignored in a child)."""
    return subprocess.Popen(
        cmd,
        cwd=REPO,
        env=_RUN_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the run's processes in /proc")
def test_ray_run_killed_midway_resumes_without_redoing(tmp_path: Path, traj_dir: Path) -> None:
    """A real local Ray (one CPU, jobs one at a time): SIGKILL the whole run as soon as a job has finished, re-run.

    The kill follows the first result record, not a clock: on a slow or busy machine the wait is only longer."""
    job_ids = [f"job{i}" for i in range(6)]
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [
            {"id": j, "scene": str(CUBE_XML), "trajectories": str(traj_dir), "settings": {"seed": i}}
            for i, j in enumerate(job_ids)
        ],
    )
    out = tmp_path / "out"
    cmd = _batch_cmd(jobs_file, out)
    proc = _start_batch(cmd)
    try:
        _wait_for_a_finished_job(proc, out, job_ids)
    finally:
        # The driver, Ray's services and its workers (in their own process groups, same session).
        _kill_session(proc.pid)
        proc.communicate(timeout=_EVENT_BOUND_S)
    finished_first = _ok_records(out, job_ids)
    assert len(finished_first) < len(job_ids), "the run finished before it could be killed"
    first_records = {j: (out / "results" / f"{j}.json").read_bytes() for j in finished_first}

    rerun = subprocess.run(cmd, cwd=REPO, env=_RUN_ENV, capture_output=True, text=True, timeout=_EVENT_BOUND_S)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert (
        f"{len(finished_first)} already finished, {len(job_ids) - len(finished_first)} run now, 0 failed"
        in rerun.stdout
    )
    for j in job_ids:
        assert (read_result(out, j) or {}).get("status") == "ok", j
        assert (out / "scenes" / j / "scene.xml").is_file()
    for j, raw in first_records.items():
        assert (out / "results" / f"{j}.json").read_bytes() == raw, f"{j} was redone"
    rows = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in rows] == ["ok"] * len(job_ids)
    assert not list((out / "scenes").glob(".*.tmp")) and not list((out / "results").glob(".*.tmp"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the run's processes in /proc")
@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["TERM", "INT"])
def test_a_signal_stops_a_ray_run_with_one_line_and_a_true_table(
    tmp_path: Path, traj_dir: Path, signum: int, code: int
) -> None:
    """SIGTERM (`timeout`, `docker stop`) or Ctrl-C midway through a real local Ray run: exit 128 + signal, one line
    on stderr and no traceback; Ray's processes are gone, and results.csv / results.json say of every job what its
    record on disk says (a job that finished after the signal does not read pending). Re-running resumes."""
    job_ids = [f"job{i}" for i in range(30)]
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [
            {"id": j, "scene": str(CUBE_XML), "trajectories": str(traj_dir), "settings": {"seed": i}}
            for i, j in enumerate(job_ids)
        ],
    )
    out = tmp_path / "out"
    proc = _start_batch(_batch_cmd(jobs_file, out))
    try:
        _wait_for_a_finished_job(proc, out, job_ids)
        proc.send_signal(signum)
        _, stderr = proc.communicate(timeout=_EVENT_BOUND_S)
        _wait_for_session_end(proc.pid)
        assert not _session_pids(proc.pid), "Ray's processes outlived the stopped run"
    finally:
        _kill_session(proc.pid)
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr and "SIGTERM received" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    name = signal.Signals(signum).name
    assert len(lines) == 1 and lines[0].startswith(f"image2sim: batch stopped ({name}) with "), stderr
    finished = _ok_records(out, job_ids)
    assert f"with {len(finished)} of {len(job_ids)} jobs finished" in lines[0]
    assert 0 < len(finished) < len(job_ids)

    def on_disk(job_id: str) -> str:
        record = read_result(out, job_id)
        return "pending" if record is None else record["status"]

    rows = json.loads((out / "results.json").read_text())
    assert [(r["id"], r["status"]) for r in rows] == [(j, on_disk(j)) for j in job_ids]
    with (out / "results.csv").open(newline="") as handle:
        assert [(r["id"], r["status"]) for r in csv.DictReader(handle)] == [(j, on_disk(j)) for j in job_ids]
    assert {on_disk(j) for j in job_ids} == {"ok", "pending"}  # cancelled jobs are not recorded as failed


def _reran(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.getMessage().endswith(", re-running")]


def test_a_job_whose_inputs_changed_runs_again(
    tmp_path: Path, traj_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Resuming trusts a job's result only while its settings, scene files and trajectory files are the ones it was
    made from: an edit makes the job run again with one line naming what changed, and until then the table does not
    show the old result beside the new inputs. An unchanged job is still skipped."""
    import shutil

    from grounder.calibration.batch_output import write_table
    from grounder.core.trajectory import load_trajectory, save_trajectory

    scene = tmp_path / "scene" / "cube.xml"
    scene.parent.mkdir()
    shutil.copy(CUBE_XML, scene)
    data_a, data_b = shutil.copytree(traj_dir, tmp_path / "a"), shutil.copytree(traj_dir, tmp_path / "b")
    jobs_file = tmp_path / "jobs.yaml"

    def jobs(seed_a: int = 0) -> list:
        return load_jobs(
            _write_jobs(
                jobs_file,
                [
                    {"id": "a", "scene": str(scene), "trajectories": str(data_a), "settings": {"seed": seed_a}},
                    {"id": "b", "scene": str(CUBE_XML), "trajectories": str(data_b)},
                ],
            )
        )

    def run(seed_a: int = 0) -> tuple[tuple[str, ...], list[str]]:
        caplog.clear()
        with caplog.at_level("WARNING", logger="grounder.calibration.batch"):
            summary = run_batch(jobs(seed_a), out, inline=True)
        assert set(summary.ran) | set(summary.skipped) == {"a", "b"} and not summary.failed
        return summary.ran, _reran(caplog)

    out = tmp_path / "out"
    assert run() == (("a", "b"), [])
    assert run() == ((), [])  # nothing changed: both finished
    first_a = read_result(out, "a")

    # Settings: the table shows job a pending (its record is of the old settings) until it has run again.
    rows = write_table(out, jobs(seed_a=5))
    assert [(r["id"], r["status"]) for r in rows] == [("a", "pending"), ("b", "ok")]
    assert run(seed_a=5) == (("a",), ["job a: settings changed, re-running"])
    assert (read_result(out, "a") or {})["job"]["settings"]["seed"] == 5
    assert run(seed_a=5) == ((), [])

    # A trajectory file edited in place (same name, other contents): job b runs again, a does not.
    t0 = load_trajectory(data_b / "t0.npz")
    save_trajectory(replace(t0, qpos=t0.qpos + np.array([0.001, 0, 0, 0, 0, 0, 0])), data_b / "t0.npz")
    assert run(seed_a=5) == (("b",), ["job b: trajectories changed, re-running"])
    # A file added to the folder counts too.
    save_trajectory(replace(t0, name="t9"), data_b / "t9.npz")
    assert run(seed_a=5) == (("b",), ["job b: trajectories changed, re-running"])

    # The scene file edited: job a runs again.
    scene.write_text(scene.read_text().replace("<mujoco", "<!-- edited -->\n<mujoco", 1))
    assert run(seed_a=5) == (("a",), ["job a: scene changed, re-running"])
    assert run(seed_a=5) == ((), [])

    # A record of an older image2sim, without fingerprints: the job runs again, saying why.
    record_file = out / "results" / "b.json"
    record = json.loads(record_file.read_text())
    record_file.write_text(json.dumps({k: v for k, v in record.items() if k != "inputs"}))
    assert run(seed_a=5) == (
        ("b",),
        ["job b: its result has no fingerprint of its inputs (recorded by an older image2sim), re-running"],
    )
    assert first_a is not None and (read_result(out, "a") or {})["inputs"] != first_a["inputs"]


def test_scene_fingerprint_covers_the_files_it_names(tmp_path: Path) -> None:
    """A scene is its MJCF and what it loads (a mesh here), and for a scene folder also its manifest; a batch output
    written inside a trajectory folder is not one of the folder's trajectories."""
    from grounder.calibration.batch_output import scene_sha256, trajectories_sha256

    folder = tmp_path / "scene"
    (folder / "assets").mkdir(parents=True)
    (folder / "assets" / "tet.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    (folder / "scene.xml").write_text(
        '<mujoco><asset><mesh name="tet" file="assets/tet.obj"/></asset>'
        '<worldbody><body><freejoint/><geom type="mesh" mesh="tet"/></body></worldbody></mujoco>'
    )
    (folder / "scene.json").write_text("{}")
    digests = [scene_sha256(folder), scene_sha256(folder / "scene.xml")]
    (folder / "assets" / "tet.obj").write_text(
        "v 0 0 0\nv 2 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    assert scene_sha256(folder) != digests[0] and scene_sha256(folder / "scene.xml") != digests[1]
    digests = [scene_sha256(folder), scene_sha256(folder / "scene.xml")]
    (folder / "scene.json").write_text('{"edited": true}')
    assert scene_sha256(folder) != digests[0]  # the folder's manifest is read (embedding mode)
    assert scene_sha256(folder / "scene.xml") == digests[1]  # the MJCF alone does not read it

    data = tmp_path / "data"
    (data / "tosses").mkdir(parents=True)
    (data / "tosses" / "0.pt").write_bytes(b"x")
    before = {fmt: trajectories_sha256(data, fmt) for fmt in (None, "dair-pll-cube")}
    (data / "out").mkdir()
    (data / "out" / "batch.json").write_text("{}")
    (data / "out" / "results.csv").write_text("id\n")
    assert {fmt: trajectories_sha256(data, fmt) for fmt in (None, "dair-pll-cube")} == before
    (data / "tosses" / "0.pt").write_bytes(b"y")  # what the importer reads
    assert trajectories_sha256(data, "dair-pll-cube") != before["dair-pll-cube"]


def test_cli_batch_inline_reports_failures(tmp_path: Path, traj_dir: Path) -> None:
    from typer.testing import CliRunner

    from grounder.cli import app

    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml",
        [
            {"id": "good", "scene": str(CUBE_XML), "trajectories": str(traj_dir)},
            {"id": "empty", "scene": str(CUBE_XML), "trajectories": str(tmp_path)},
        ],
    )
    result = CliRunner().invoke(app, ["batch", str(jobs_file), "--inline"])
    assert result.exit_code == 1, result.output
    assert "job empty failed" in result.output and "1 failed" in result.output
    assert (tmp_path / "jobs_results" / "results.csv").is_file()
    bad = tmp_path / "bad.yaml"
    bad.write_text("jobs: [{scene: a.xml}]\n")
    result = CliRunner().invoke(app, ["batch", str(bad)])
    assert result.exit_code == 2 and "needs 'scene' and 'trajectories'" in result.output, result.output


def _cli(args: list[str]):
    from typer.testing import CliRunner

    from grounder.cli import app

    return CliRunner().invoke(app, args)


def _one_error_line(result, *needles: str) -> None:
    """Exit 2 with one `image2sim: error:` line naming `needles`, and no traceback."""
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit), result.exception
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("image2sim: error:"), result.output
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_output_folder_batch_did_not_write_is_refused(tmp_path: Path, traj_dir: Path) -> None:
    """A non-empty folder without batch's marker, a file or a symlink as -o: one line, exit 2, nothing touched."""
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml", [{"id": "job", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}]
    )
    user = tmp_path / "user"
    (user / "scenes" / "job").mkdir(parents=True)
    (user / "scenes" / "job" / "important.txt").write_text("keep me")
    (user / "results.csv").write_text("my table")
    (user / "scenes" / ".notes.tmp").write_text("mine too")
    before = {p: p.read_bytes() for p in user.rglob("*") if p.is_file()}
    _one_error_line(_cli(["batch", str(jobs_file), "--inline", "-o", str(user)]), str(user), "batch.json")
    assert {p: p.read_bytes() for p in user.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in user.rglob("*")) == [".notes.tmp", "important.txt", "job", "results.csv", "scenes"]

    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _one_error_line(_cli(["batch", str(jobs_file), "--inline", "-o", str(a_file)]), str(a_file), "is a file")
    assert a_file.read_text() == "x"

    empty = tmp_path / "empty"
    empty.mkdir()
    link = tmp_path / "link"
    link.symlink_to(empty, target_is_directory=True)
    _one_error_line(_cli(["batch", str(jobs_file), "--inline", "-o", str(link)]), str(link), "symbolic link")
    assert not any(empty.iterdir())

    with pytest.raises(GrounderError, match=r"batch\.json"):  # the library refuses too, before any job
        run_batch(load_jobs(jobs_file), user, inline=True)
    assert not (user / "results").exists()


@pytest.mark.parametrize(
    ("content", "field"),
    [
        pytest.param(b"\x8a\x9f\x00\xff-<d(\x1b\xfe", "UTF-8", id="binary"),
        pytest.param(b"jobs: 5\n", "'jobs'", id="jobs-int"),
        pytest.param(b"matrix: {scenes: 5, trajectories: [d]}\n", "matrix.scenes", id="matrix-scenes-int"),
        pytest.param(
            b"matrix: {scenes: [a.xml], trajectories: [d], settings: [1, 2]}\n",
            "matrix.settings[0]",
            id="matrix-settings-ints",
        ),
        pytest.param(b"matrix: {scenes: [a.xml], trajectories: 7}\n", "matrix.trajectories", id="matrix-data-int"),
        pytest.param(b"jobs: [{scene: [a.xml], trajectories: d}]\n", "jobs[0]: scene", id="scene-list"),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: d, format: nosuch}]\n",
            'jobs[0]: unknown trajectory format "nosuch"',
            id="format-unknown",
        ),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: {path: d, format: 3}}]\n",
            "jobs[0]: unknown trajectory format 3",
            id="format-int",
        ),
        pytest.param(
            b"matrix: {scenes: [a.xml], trajectories: [{path: d, format: nosuch}]}\n",
            "matrix.trajectories[0]: unknown trajectory format",
            id="matrix-format-unknown",
        ),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: d, settings: {mode: bogus}}]\n", "mode must be", id="bad-mode"
        ),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: d, settings: {popsize: 0}}]\n", "job a__d__0: ", id="popsize-0"
        ),
        pytest.param(
            b"defaults: {1: 2, a: 3}\njobs: [{scene: a.xml, trajectories: d}]\n",
            'defaults: unknown setting(s) 1, "a"; known: ',
            id="settings-mixed-key-types",
        ),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: d, x: 1, 2: 3}]\n",
            'jobs[0]: unknown key(s) 2, "x"; expected ',
            id="job-mixed-key-types",
        ),
        pytest.param(
            b'jobs: [{scene: "a\\0b", trajectories: d}]\n',
            'jobs[0]: scene contains a NUL character: "a\\u0000b"',
            id="scene-nul",
        ),
        pytest.param(
            b'matrix: {scenes: [a.xml], trajectories: [{path: "d\\0", format: dair-pll-cube}]}\n',
            "matrix.trajectories[0]: trajectories.path contains a NUL character",
            id="matrix-data-nul",
        ),
        pytest.param(b"jobs: " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply", id="deep-yaml"),
        pytest.param(
            b"jobs: [{scene: a.xml, trajectories: d}]\njobs: [{scene: b.xml, trajectories: d}]\n",
            'line 2: key "jobs" appears twice in one mapping (first on line 1)',
            id="duplicate-top-key",
        ),
        pytest.param(
            b"jobs:\n  - scene: a.xml\n    trajectories: d\n    scene: b.xml\n",
            'line 4: key "scene" appears twice in one mapping (first on line 2)',
            id="duplicate-job-key",
        ),
        pytest.param(
            b"defaults: {seed: 1}\njobs: [{scene: a.xml, trajectories: d, settings: {seed: 1, 'seed': 2}}]\n",
            'line 2: key "seed" appears twice',
            id="duplicate-settings-key",
        ),
    ],
)
def test_jobs_file_of_wrong_types_is_one_line(tmp_path: Path, content: bytes, field: str) -> None:
    jobs_file = tmp_path / "jobs.yaml"
    jobs_file.write_bytes(content)
    with pytest.raises(GrounderError, match=re.escape(field)):
        load_jobs(jobs_file)
    _one_error_line(_cli(["batch", str(jobs_file), "--inline"]), str(jobs_file), field)
    assert not (tmp_path / "jobs_results").exists()


def test_corrupt_result_record_is_run_again(tmp_path: Path, traj_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    """An earlier run's record that the table cannot read (hand-edited, truncated) counts as not finished."""
    jobs = load_jobs(
        _write_jobs(tmp_path / "jobs.yaml", [{"id": "job", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}])
    )
    out = tmp_path / "out"
    out.mkdir()  # an empty folder is accepted
    assert run_batch(jobs, out, inline=True).ran == ("job",)
    record_file = out / "results" / "job.json"
    record = json.loads(record_file.read_text())
    record_file.write_text(json.dumps({**record, "seconds": "abc"}))
    with caplog.at_level("WARNING", logger="grounder.calibration.batch"):
        again = run_batch(jobs, out, inline=True)
    assert again.skipped == () and again.ran == ("job",) and again.failed == ()
    assert any("job.json" in r.getMessage() and "'seconds'" in r.getMessage() for r in caplog.records)
    assert isinstance((read_result(out, "job") or {})["seconds"], float)
    record_file.write_text("{not json")
    assert read_result(out, "job") is None
    assert json.loads((out / "batch.json").read_text())["format"] == "image2sim-batch/1"  # the resumable output


def test_merged_settings_are_checked_when_loading(tmp_path: Path) -> None:
    """Defaults + a job's (or a matrix entry's) settings build `CalibrateOptions` at load: the merge is checked."""
    import yaml

    jobs_file = tmp_path / "jobs.yaml"

    def write(data: dict) -> Path:
        jobs_file.write_text(yaml.safe_dump(data))
        return jobs_file

    # Each piece is valid alone; together they are not (separate_bodies is raw mode only).
    write({"defaults": {"separate_bodies": True}, "jobs": [{"id": "one", "scene": "a.xml", "trajectories": "d"}]})
    assert [j.id for j in load_jobs(jobs_file)] == ["one"]
    write(
        {
            "defaults": {"separate_bodies": True},
            "jobs": [
                {"id": "one", "scene": "a.xml", "trajectories": "d"},
                {"id": "two", "scene": "a.xml", "trajectories": "d", "settings": {"mode": "embedding"}},
            ],
        }
    )
    with pytest.raises(GrounderError, match=r"job two: .*separate_bodies applies to raw mode only"):
        load_jobs(jobs_file)
    _one_error_line(_cli(["batch", str(jobs_file), "--inline"]), str(jobs_file), "job two: ", "separate_bodies")
    assert not (tmp_path / "jobs_results").exists()

    # Defaults invalid alone, valid once each job overrides them: the jobs load, with their ids and count.
    write(
        {
            "defaults": {"separate_bodies": True, "mode": "embedding"},
            "jobs": [{"id": "one", "scene": "a.xml", "trajectories": "d", "settings": {"mode": "raw"}}],
            "matrix": {"scenes": ["a.xml"], "trajectories": ["d"], "settings": {"r": {"mode": "raw"}}},
        }
    )
    assert [(j.id, j.settings["mode"]) for j in load_jobs(jobs_file)] == [("one", "raw"), ("a__d__r", "raw")]

    # A matrix entry: the job named is the one whose merged settings fail; a wrong type fails there too.
    matrix = {"scenes": ["a.xml"], "trajectories": ["d"], "settings": {"ok": {}, "bad": {"popsize": 0}}}
    write({"defaults": {"popsize": 2}, "matrix": matrix})
    with pytest.raises(GrounderError, match=r"job a__d__bad: .*popsize"):
        load_jobs(jobs_file)
    write({"defaults": {"popsize": 2}, "matrix": {**matrix, "settings": {"ok": {}, "bad": {"popsize": "x"}}}})
    with pytest.raises(GrounderError, match=r"job a__d__bad: .*popsize"):
        load_jobs(jobs_file)
    _one_error_line(_cli(["batch", str(jobs_file), "--inline"]), str(jobs_file), "job a__d__bad: ", "popsize")
    assert not (tmp_path / "jobs_results").exists()


def test_yaml_merge_keys_are_not_duplicate_keys(tmp_path: Path) -> None:
    """A key that overrides one merged in with ``<<: *anchor`` is YAML's override, not a repeated key."""
    jobs_file = tmp_path / "jobs.yaml"
    jobs_file.write_text(
        "defaults: &base {generations: 1, popsize: 2}\n"
        "jobs:\n"
        "  - {id: one, scene: a.xml, trajectories: d, settings: {<<: *base, popsize: 3}}\n"
        "  - {id: two, scene: a.xml, trajectories: d, settings: *base}\n"
    )
    jobs = load_jobs(jobs_file)
    assert [(j.id, dict(j.settings)) for j in jobs] == [
        ("one", {"generations": 1, "popsize": 3}),
        ("two", {"generations": 1, "popsize": 2}),
    ]


def test_deeply_nested_marker_or_record_is_not_trusted(
    tmp_path: Path, traj_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """JSON nested past the recursion limit in batch.json or results/<id>.json: not a marker, not a record."""
    deep = "[" * 5000 + "]" * 5000
    jobs_file = _write_jobs(
        tmp_path / "jobs.yaml", [{"id": "job", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}]
    )
    jobs = load_jobs(jobs_file)

    marked = tmp_path / "marked"
    marked.mkdir()
    (marked / "batch.json").write_text(deep)
    _one_error_line(_cli(["batch", str(jobs_file), "--inline", "-o", str(marked)]), str(marked), "no valid batch.json")
    with pytest.raises(GrounderError, match=r"no valid batch\.json"):
        run_batch(jobs, marked, inline=True)
    assert sorted(p.name for p in marked.iterdir()) == ["batch.json"]

    out = tmp_path / "out"
    (out / "results").mkdir(parents=True)
    (out / "batch.json").write_text(json.dumps({"format": "image2sim-batch/1"}))
    (out / "results" / "job.json").write_text(deep)
    assert read_result(out, "job") is None
    with caplog.at_level("WARNING", logger="grounder.calibration.batch"):
        summary = run_batch(jobs, out, inline=True)
    assert summary.skipped == () and summary.ran == ("job",) and summary.failed == ()
    assert any("job.json" in r.getMessage() and "nested too deeply" in r.getMessage() for r in caplog.records)
    assert (read_result(out, "job") or {}).get("status") == "ok"


def test_a_folder_or_a_missing_path_as_the_jobs_file_is_one_clear_line(tmp_path: Path) -> None:
    with pytest.raises(GrounderError, match=r"is a folder; pass the jobs file \(YAML\) itself"):
        load_jobs(tmp_path)
    with pytest.raises(GrounderError, match=r"jobs file does not exist; pass the path of a jobs file"):
        load_jobs(tmp_path / "jobs.yaml")


def test_a_second_batch_on_the_same_output_is_refused_while_the_first_runs(tmp_path: Path, traj_dir: Path) -> None:
    """Two batch runs on one results folder would both write its records and table; the second is now refused with
    one line while another process holds the folder's claim, and nothing of the first's is touched."""
    out = tmp_path / "jobs_results"
    job = {"id": "good", "scene": str(CUBE_XML), "trajectories": str(traj_dir)}
    jobs_file = _write_jobs(tmp_path / "jobs.yaml", [job])
    with claim_held_by_another_process(out):
        _one_error_line(_cli(["batch", str(jobs_file), "--inline"]), "another image2sim run", str(out))
        assert not out.exists()
    result = _cli(["batch", str(jobs_file), "--inline"])  # the holder is gone: its claim is stale
    assert result.exit_code == 0, result.output
