"""Batch calibration jobs (scenes x datasets x settings) on Ray, resumable.

A jobs file (YAML; relative paths are relative to the file, ``~`` is the home folder)::

    defaults:                      # optional: CalibrateOptions fields applied to every job
      generations: 10
      max_train_trajectories: 40
    jobs:                          # explicit jobs
      - id: cube_default           # optional; default: <scene stem>__<dataset name>__<settings name>
        scene: ../samples/cube_toss/cube.xml
        trajectories: cube_npz/    # a trajectory folder (.npz files) ...
        format: dair-pll-cube      # ... or, with format, a folder an importer reads (image2sim import-trajectories)
        settings: {params: [cube.friction.sliding, cube.solref.timeconst]}
    matrix:                        # optional: every scene x every dataset x every named setting
      scenes: [a/scene_dir, b.xml]
      trajectories: [data1/, {path: ../shared/data/cube_toss, format: dair-pll-cube}]
      settings: {fast: {generations: 2}, full: {}}

Output folder (new, empty, or the output of an earlier batch run, which its ``batch.json`` marks)::

    batch.json          the marker, written before any job runs: ``{"format": "image2sim-batch/1", ...}``. A folder
                        that is not empty and has no marker is refused, since a run replaces what it finds there
    results/<id>.json   one per finished job, written atomically (temporary file, then os.replace): the job's
                        status (ok or failed with the error), parameters, errors before/after, seconds, and
                        ``inputs``: sha256 fingerprints of what it read (:func:`job_inputs`)
    scenes/<id>/        the calibrated scene folder of a successful job (written atomically by calibrate)
    results.csv, results.json   the table of all jobs of the file, rewritten after each finished job and on the way
                        out (also after SIGINT or SIGTERM); a record whose inputs are not the job's now reads pending

A job counts as finished when its ``results/<id>.json`` says ``ok`` and its recorded inputs are the job's inputs now:
the same settings (canonical JSON), scene files (the MJCF and every file it names; for a scene folder also its other
top-level files) and trajectory files (names and contents). A re-run (after a crash or Ctrl-C) skips it and runs the
rest; a job whose settings, scene or trajectories changed runs again, with a warning that names what changed, and so
does one whose record has no fingerprint (written by an older image2sim). Failed jobs are run again, and so are jobs
whose record is unreadable or invalid (with a warning). A failing job is recorded and does not stop the others.
SIGINT or SIGTERM stops a Ray run within a second: the jobs still running are cancelled, Ray is shut down, the
table is rewritten from the records, and the signal is then handed to the handler the caller had before. A scene or
trajectory folder that is not there is refused before any job runs (not with ``address``: on a cluster the paths
need only exist on its nodes, and an input not visible here is left out of the comparison of inputs). Jobs
run as Ray tasks (one CPU each) on a local Ray started for the run, or on an existing cluster given by
``address``: the head node's ``host:port`` (its GCS port, 6379 by default), ``auto`` (the cluster ``ray start``
made on this machine) or ``ray://host:10001`` (the Ray client, which needs ``pip install 'ray[client]'``); the
cluster's nodes need image2sim installed and the paths visible.
A cluster that cannot be reached is reported before the output folder is created.

This module runs the jobs (`run_batch`, `run_job`); the jobs file is read in `grounder.calibration.batch_jobs`, the
output folder's fingerprints, records and table are in `grounder.calibration.batch_output`.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import signal
import socket
import threading
import time
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from grounder.calibration.batch_jobs import Job, check_job_paths, options_from_settings
from grounder.calibration.batch_output import (
    MARKER,
    RESULTS_DIR,
    SCENES_DIR,
    _is_marker,
    _load_result,
    _prepare_output,
    _write_json_atomic,
    check_batch_output,
    job_inputs,
    result_path,
    stale_reason,
    write_table,
)
from grounder.errors import GrounderError
from image2sim_common.progress import ProgressFn

log = logging.getLogger(__name__)

_WAIT_SLICE_S = 0.5  # how long one ray.wait may block: a SIGINT or SIGTERM is acted on within this
_CANCEL_WAIT_S = 60.0  # at most this long for the workers of cancelled jobs to go (a cluster's may answer slowly)


def run_job(job_json: Mapping[str, Any], out_dir: str) -> dict[str, Any]:
    """Runs one job and writes its result record atomically; never raises (a failure is recorded).

    Runs inside a Ray worker (or inline). Returns the record.
    """
    job = Job.from_json(job_json)
    out = Path(out_dir)
    scene_out = out / SCENES_DIR / job.id
    tick = time.time()
    record: dict[str, Any] = {"id": job.id, "job": job.to_json(), "started_unix": tick, "pid": os.getpid()}
    try:
        record["inputs"] = job_inputs(job)  # before reading them: what this run read, barring an edit meanwhile
        from grounder.calibration.fit import calibrate
        from grounder.core.importers import import_trajectories
        from grounder.core.trajectory import load_trajectories

        options = options_from_settings({"nthread": 1, **job.settings})
        if job.format:
            trajs = import_trajectories(job.format, job.trajectories)
        else:
            trajs = load_trajectories(job.trajectories)
        if scene_out.exists():
            shutil.rmtree(scene_out)  # a scene written before a crash whose result record was not
        result = calibrate(job.scene, trajs, options=options, out=scene_out)
        summary = result.to_json()
        record.update(
            status="ok",
            error=None,
            parameters={p.name: p.value for p in result.parameters},
            intervals={p.name: [p.interval_low, p.interval_high] for p in result.parameters},
            errors={
                when: {
                    split: {
                        "position_pct": float(s.position_pct.mean()),
                        "rotation_deg": float(s.rotation_deg.mean()),
                        "count": len(s.names),
                    }
                    for split, s in side.items()
                }
                for when, side in (("before", result.before), ("after", result.after))
            },
            steps_per_second=summary["steps_per_second"],
            scene_out=str(scene_out),
        )
    except GrounderError as exc:
        record.update(status="failed", error=str(exc))
    except Exception as exc:  # a job's crash must not stop the batch: record it with its traceback
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
    record["seconds"] = time.time() - tick
    _write_json_atomic(result_path(out, job.id), record)
    return record


@dataclass(frozen=True, kw_only=True)
class BatchSummary:
    """What a batch run did.

    Attributes:
        total: Jobs in the file.
        skipped: Jobs already finished before this run.
        ran: Jobs run now.
        failed: Ids of jobs that failed (now or before, and still not ok).
        rows: The results table.
        seconds: Wall time.
    """

    total: int
    skipped: tuple[str, ...]
    ran: tuple[str, ...]
    failed: tuple[str, ...]
    rows: tuple[dict[str, Any], ...]
    seconds: float


def ray_init_kwargs(address: str | None, num_cpus: int | None) -> dict[str, Any]:
    """Arguments of ``ray.init``: connect to ``address`` when given, else start a small local Ray."""
    if address:
        return {"address": address, "log_to_driver": False}
    return {
        "num_cpus": num_cpus or max(1, (os.cpu_count() or 2) - 1),
        "include_dashboard": False,
        "log_to_driver": False,
        "configure_logging": False,
    }


_HOST_PORT = re.compile(r"^(?:ray://)?(?P<host>\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.-]+):(?P<port>[0-9]{1,5})$")


def check_ray_address(address: str, *, timeout_s: float = 10.0) -> None:
    """Refuses a cluster address that cannot work, before Ray is asked (Ray itself may hang or print a traceback).

    Args:
        address: ``auto``, ``host:port`` or ``ray://host:port``.
        timeout_s: How long to wait for the TCP connection to ``host:port``.

    Raises:
        GrounderError: Not one of those forms; ``ray://`` without the Ray client installed; nothing listening.
    """
    if address == "auto":
        return
    match = _HOST_PORT.match(address)
    if match is None or not 0 < int(match["port"]) < 65536:
        raise GrounderError(
            f"--address {address!r} is not a Ray cluster address; give the head node's host:port (e.g. head:6379), "
            "auto, or leave --address out for a local Ray"
        )
    if address.startswith("ray://"):
        import importlib.util

        if importlib.util.find_spec("grpc") is None:
            raise GrounderError(
                f"--address {address}: ray:// addresses need the Ray client, which is not installed; run "
                "`.venv/bin/pip install 'ray[client]'`, or give the head node's GCS address (host:6379)"
            )
    host, port = match["host"].strip("[]"), int(match["port"])
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise GrounderError(
            f"--address {address}: nothing answers at {host}:{port} ({exc.strerror or exc}); check that the Ray head "
            "node runs (`ray start --head`) and the host and port, or leave --address out for a local Ray"
        ) from exc


def connect_ray(address: str | None, num_cpus: int | None) -> None:
    """``ray.init`` for a batch run (:func:`ray_init_kwargs`); a cluster that cannot be joined is a user error."""
    import ray

    if address:
        check_ray_address(address)
    try:
        ray.init(**ray_init_kwargs(address, num_cpus))
    except (ConnectionError, ValueError, RuntimeError, TimeoutError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise GrounderError(
            f"cannot start or join {where} ({first}); check --address, or run with --inline to go without Ray"
        ) from exc


def run_batch(
    jobs: Sequence[Job],
    out_dir: Path,
    *,
    address: str | None = None,
    num_cpus: int | None = None,
    inline: bool = False,
    progress: ProgressFn | None = None,
) -> BatchSummary:
    """Runs the jobs not yet finished in ``out_dir`` on Ray (or ``inline``, one after another, without Ray).

    A job is finished when its record says ok and was made from the job's inputs as they are now (module docstring);
    a finished job whose inputs changed is run again, with a warning naming what changed.

    SIGINT and SIGTERM (on the main thread): inline, the handlers in place raise as usual, in the job that runs. On
    Ray they are only noted while the jobs run (`_StopSignals`), and the run stops at once: the jobs not yet done are
    cancelled and waited for, Ray is shut down, the table is rewritten from the records, and then the signal is
    handed to the handler the caller had before ``ray.init`` replaced SIGTERM's (the CLI's raises; Python's default
    for SIGINT raises KeyboardInterrupt; SIG_DFL ends the process as the signal would have).

    Args:
        jobs: From :func:`load_jobs`.
        out_dir: Output folder (module docstring): created if missing; an earlier batch output is reused to resume.
        address: A Ray cluster address; None starts a local Ray for this run.
        num_cpus: CPUs of the local Ray (one job per CPU); ignored with ``address``.
        inline: Run in this process without Ray (debugging, tiny batches).
        progress: ``progress(stage, done, total)``.

    Returns:
        The summary; failed jobs are listed, not raised.

    Raises:
        GrounderError: ``out_dir`` is refused by :func:`check_batch_output`, a pending job's scene or trajectory
            folder is missing (checked without ``address``), or Ray cannot be started or the cluster at ``address``
            joined (all before the output folder is created or any job runs).
    """
    tick = time.time()
    out_dir = Path(out_dir)
    check_batch_output(out_dir)
    memo: dict[tuple[object, ...], str] = {}
    inputs = {job.id: job_inputs(job, seen_here=address is None, memo=memo) for job in jobs}
    skipped: list[str] = []
    for job in jobs:
        record, problem = _load_result(out_dir, job.id)
        if problem:  # e.g. edited by hand or truncated by a full disk: the job's result cannot be trusted
            log.warning("%s: %s; running the job again", result_path(out_dir, job.id), problem)
        elif record is not None and record.get("status") == "ok":
            why = stale_reason(record, inputs[job.id])
            if why:
                log.warning("job %s: %s, re-running", job.id, why)
            elif (out_dir / SCENES_DIR / job.id).is_dir():
                skipped.append(job.id)
    pending = [j for j in jobs if j.id not in set(skipped)]
    if address is None:  # on a cluster the paths need only exist on its nodes
        check_job_paths(pending)
    ran: list[str] = []
    rows: list[dict[str, Any]] = []
    stop = _StopSignals()
    on_ray = bool(pending) and not inline
    started_here = False
    try:
        if on_ray:
            import ray

            started_here = not ray.is_initialized()
            try:
                if started_here:
                    connect_ray(address, num_cpus)  # before the output exists: a bad address leaves nothing behind
                stop.defer()  # after ray.init, which puts its own SIGTERM handler in place of the caller's
            except SystemExit:  # SIGTERM while ray.init ran: its handler calls sys.exit
                stop.received.append(signal.SIGTERM)
        if not stop.received:
            _prepare_output(out_dir, jobs)
            _run_pending(jobs, pending, skipped, out_dir, inputs, ran, inline=inline, progress=progress, stop=stop)
    finally:
        try:  # a signal meanwhile is still only noted: the table is written whatever comes
            if started_here:
                import ray

                ray.shutdown()
            if _is_marker(out_dir / MARKER):  # true once no worker is left to write a record (also after a signal)
                rows = write_table(out_dir, jobs, inputs)
        finally:
            if on_ray:
                stop.restore()
    stop.hand_over()
    failed = tuple(r["id"] for r in rows if r["status"] == "failed")
    return BatchSummary(
        total=len(jobs),
        skipped=tuple(skipped),
        ran=tuple(ran),
        failed=failed,
        rows=tuple(rows),
        seconds=time.time() - tick,
    )


class _StopSignals:
    """SIGINT and SIGTERM noted, not raised, while Ray runs the jobs; then handed to the handlers they replaced.

    Why not let a handler raise: ``ray.init`` replaces the SIGTERM handler with its own, and while ``ray.wait``
    blocks in Ray's core worker a signal meets Ray's C++ handler (which prints a stack trace and exits 1, the exit
    code of a failed job) or, for an exception of our own, is held until the task ends and then surfaces as a
    SystemError. A handler that only notes the signal works whatever Ray does: the loop waits in short slices and
    stops at the next one, and the exception is raised once Ray is shut down and the table is true.

    Only on the main thread (Python runs handlers there), and not for a signal the caller ignores (SIG_IGN).
    """

    _SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.received: list[int] = []
        on_main = threading.current_thread() is threading.main_thread()
        self._before: dict[int, Any] = {s: signal.getsignal(s) for s in self._SIGNALS} if on_main else {}

    def __bool__(self) -> bool:
        return bool(self.received)

    def defer(self) -> None:
        for signum, before in self._before.items():
            if before is not signal.SIG_IGN:
                signal.signal(signum, lambda s, _frame: self.received.append(s))

    def restore(self) -> None:
        """Puts the caller's handlers back (Ray's SIGTERM handler stays after ``ray.shutdown`` otherwise)."""
        for signum, before in self._before.items():
            signal.signal(signum, before if before is not None else signal.SIG_DFL)  # None: not set from Python

    def hand_over(self) -> None:
        """Delivers the first signal received to the caller's handler, which raises (or, SIG_DFL, ends the process)."""
        if not self.received:
            return
        signum = self.received[0]
        before = self._before.get(signum, signal.SIG_DFL)
        if callable(before):
            before(signum, None)
        elif before is not signal.SIG_IGN:
            signal.raise_signal(signum)


def _run_pending(
    jobs: Sequence[Job],
    pending: Sequence[Job],
    skipped: Sequence[str],
    out_dir: Path,
    inputs: Mapping[str, Mapping[str, Any]],
    ran: list[str],
    *,
    inline: bool,
    progress: ProgressFn | None,
    stop: _StopSignals,
) -> None:
    """:func:`run_batch` once Ray (if used) is up and the output exists: runs ``pending`` (appended to ``ran`` as
    they end) and rewrites the table after each; on a signal (``stop``), cancels the jobs not done and waits for them.
    """
    report: ProgressFn = progress or (lambda _s, _d, _t: None)
    # Leftovers of a run that was killed while writing: temporary files and folders (never results).
    for leftover in [*(out_dir / RESULTS_DIR).glob(".*.tmp"), *(out_dir / SCENES_DIR).glob(".*.tmp")]:
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            leftover.unlink(missing_ok=True)
    total = len(jobs)
    done = len(skipped)
    stage = "batch jobs"
    report(stage, done, total)
    if skipped:
        log.info("skipping %d finished job(s)", len(skipped))
    write_table(out_dir, jobs, inputs)
    if pending and inline:
        for job in pending:
            record = run_job(job.to_json(), str(out_dir))
            ran.append(job.id)
            done += 1
            _log_record(record)
            write_table(out_dir, jobs, inputs)
            report(stage, done, total)
    elif pending:
        import ray

        remote = ray.remote(num_cpus=1, max_retries=0)(run_job)
        refs = {remote.remote(job.to_json(), str(out_dir)): job for job in pending}
        waiting = list(refs)
        while waiting and not stop:
            ready, waiting = ray.wait(waiting, num_returns=1, timeout=_WAIT_SLICE_S)
            for ref in ready:
                job = refs[ref]
                try:
                    record = ray.get(ref)
                except Exception as exc:  # the worker died (killed, out of memory): record it here
                    record = {
                        "id": job.id,
                        "job": job.to_json(),
                        "inputs": dict(inputs[job.id]),
                        "status": "failed",
                        "error": f"worker failed: {type(exc).__name__}: {exc}".splitlines()[0],
                    }
                    _write_json_atomic(result_path(out_dir, job.id), record)
                ran.append(job.id)
                done += 1
                _log_record(record)
                write_table(out_dir, jobs, inputs)
                report(stage, done, total)
        if waiting:  # stopped: no job may write its record after the table is rewritten on the way out
            for ref in waiting:
                ray.cancel(ref, force=True)  # a running job's worker is killed; a queued one never starts
            ray.wait(waiting, num_returns=len(waiting), timeout=_CANCEL_WAIT_S)
            log.info("stopped: %d job(s) cancelled", len(waiting))


def _log_record(record: Mapping[str, Any]) -> None:
    if record.get("status") == "ok":
        log.info("job %s finished in %.1f s", record.get("id"), float(record.get("seconds", 0.0)))
    else:
        log.warning("job %s failed: %s", record.get("id"), record.get("error"))
