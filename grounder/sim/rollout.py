"""Open-loop simulation of recorded trajectories with `mujoco.rollout`, and the errors between two trajectories.

Shared by calibration, diagnosis, the residual and tracking: every trajectory is re-simulated from its first
recorded state with its recorded controls, on the model's own timestep, and read back at the recorded times.

Conventions: a trajectory's `ctrl[t]` is held from `time_s[t]` to `time_s[t + 1]` (zero-order hold). The sample
rate may be coarser than the model timestep; sample times are rounded to whole model steps.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from image2sim_common.rotations import quat_angle_rad

FULLPHYSICS = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)


def default_nthread() -> int:
    """Threads for batched rollouts: the CPU cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def step_indices(time_s: np.ndarray, timestep_s: float, name: str | None = None) -> np.ndarray:
    """Model steps from the first sample to each sample, (T,) int64, 0 for the first.

    Args:
        name: The trajectory's name, for the error message.

    Raises:
        GrounderError: two samples fall on the same model step (the data is sampled faster than the model, or two
            samples share a time).
    """
    steps = np.rint((np.asarray(time_s, np.float64) - time_s[0]) / timestep_s).astype(np.int64)
    if len(steps) > 1 and np.any(np.diff(steps) <= 0):
        gaps = np.diff(time_s)
        at = int(np.argmin(gaps))
        which = f"trajectory {name}" if name else "a trajectory"
        fix = (
            "samples must be at least one model step apart: use a shorter timestep in the scene's <option>, or "
            "resample the recording"
            if gaps[at] > 0
            else "remove the repeated sample from the recording"
        )
        raise GrounderError(
            f"{which}: samples {at} and {at + 1} are {gaps[at] * 1e3:.3f} ms apart but the model timestep is "
            f"{timestep_s * 1e3:.3f} ms; {fix}"
        )
    return steps


def initial_state(
    model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, data: mujoco.MjData | None = None
) -> np.ndarray:
    """The full-physics state vector (`mjSTATE_FULLPHYSICS`) with this qpos and qvel, everything else at rest."""
    data = data if data is not None else mujoco.MjData(model)
    mujoco.mj_resetData(model, data)
    data.qpos[:] = qpos
    data.qvel[:] = qvel
    mujoco.mj_forward(model, data)
    state = np.empty(mujoco.mj_stateSize(model, FULLPHYSICS))
    mujoco.mj_getState(model, data, state, FULLPHYSICS)
    return state


def _offsets(model: mujoco.MjModel) -> tuple[int, int]:
    """Where qpos and qvel start in a full-physics state vector (components are stored in mjtState bit order)."""
    qpos_at = mujoco.mj_stateSize(model, int(mujoco.mjtState.mjSTATE_TIME))
    return qpos_at, qpos_at + model.nq


def _controls(traj: Trajectory, steps: np.ndarray, nu: int, nstep: int) -> np.ndarray:
    """Per-model-step controls (nstep, nu) by zero-order hold of the recorded ones."""
    out = np.zeros((nstep, nu))
    if nu == 0 or traj.ctrl is None:
        return out
    # Step k (from k to k+1) uses the last sample at or before k.
    sample_of_step = np.searchsorted(steps, np.arange(nstep), side="right") - 1
    return traj.ctrl[np.clip(sample_of_step, 0, len(traj.ctrl) - 1)]


@dataclass(frozen=True, kw_only=True)
class RolloutBatch:
    """A batch of open-loop rollouts ready for `mujoco.rollout`: one row per (model, trajectory) pair.

    Attributes:
        states0: (B, nstate) full-physics initial states.
        controls: (B, nstep, nu) per-step controls.
        sample_steps: per row, (T_b,) the model step of each recorded sample (0 for the first).
        nstep: steps simulated per row (the longest trajectory's; shorter rows are read only up to their end).
    """

    states0: np.ndarray
    controls: np.ndarray
    sample_steps: tuple[np.ndarray, ...]
    nstep: int


def _rollout_memory_limit() -> int:
    """Bytes of states one rollout batch may hold: half the machine's memory (a bigger batch is a wrong time column,
    not a run that could finish)."""
    try:
        return max(1 << 30, os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2)
    except (AttributeError, ValueError, OSError):  # pragma: no cover - not POSIX
        return 8 << 30


def prepare(model: mujoco.MjModel, trajs: Sequence[Trajectory]) -> RolloutBatch:
    """Initial states, per-step controls and sample steps of trajectories, for any model of this size signature."""
    if not trajs:
        raise GrounderError("no trajectories to simulate")
    data = mujoco.MjData(model)
    steps = [step_indices(t.time_s, model.opt.timestep, t.name) for t in trajs]
    nstep = max(1, max(int(s[-1]) for s in steps))
    state_bytes = len(trajs) * (nstep + 1) * mujoco.mj_stateSize(model, FULLPHYSICS) * 8
    if state_bytes > _rollout_memory_limit():
        longest = max(range(len(trajs)), key=lambda i: int(steps[i][-1]))
        span_s = float(trajs[longest].time_s[-1] - trajs[longest].time_s[0])
        raise GrounderError(
            f"trajectory {trajs[longest].name!r} spans {span_s:.4g} s, {nstep} model steps of "
            f"{model.opt.timestep:.4g} s: rolling out the {len(trajs)} trajectories would hold "
            f"{state_bytes / 1e9:.3g} GB of states, more than half this machine's memory; check its time column "
            "(seconds), or split it into shorter trajectories"
        )
    states0 = np.stack([initial_state(model, t.qpos[0], t.qvel[0], data) for t in trajs])
    controls = np.stack([_controls(t, s, model.nu, nstep) for t, s in zip(trajs, steps, strict=True)])
    return RolloutBatch(states0=states0, controls=controls, sample_steps=tuple(steps), nstep=nstep)


def rollout_states(models: Sequence[mujoco.MjModel], batch: RolloutBatch, *, nthread: int | None = None) -> np.ndarray:
    """Simulates len(models) x len(batch rows) rollouts; returns states (M, B, nstep + 1, nstate), row 0 initial.

    All models must share a size signature (same structure, different parameters), as `mujoco.rollout` requires.
    """
    nthread = nthread or default_nthread()
    m_count, b_count = len(models), len(batch.states0)
    model_list = [m for m in models for _ in range(b_count)]
    states0 = np.tile(batch.states0, (m_count, 1))
    controls = np.tile(batch.controls, (m_count, 1, 1)) if models[0].nu else None
    datas = [mujoco.MjData(models[0]) for _ in range(min(nthread, len(model_list)))]
    state, _ = mj_rollout.rollout(model_list, datas, states0, controls, nstep=batch.nstep)
    full = np.concatenate([states0[:, None, :], state], axis=1)
    return full.reshape(m_count, b_count, batch.nstep + 1, -1)


@contextlib.contextmanager
def mujoco_warnings(collect: bool = True) -> Iterator[list[str]]:
    """Collects the warnings MuJoCo would print (``mju_warning``: an unstable simulation, say) into a list while
    the block runs, instead of letting them reach stdout; the previous handler is restored after. With ``collect``
    false it leaves MuJoCo's handler alone and the list stays empty."""
    messages: list[str] = []
    if not collect:
        yield messages
        return
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(messages.append)
    try:
        yield messages
    finally:
        mujoco.set_mju_user_warning(previous)


def check_stable(
    states: np.ndarray, trajs: Sequence[Trajectory], model: mujoco.MjModel, warnings: Sequence[str] = ()
) -> None:
    """Refuses rollouts that MuJoCo stopped as unstable.

    When a step meets a NaN, infinite or huge (> 1e10) position, velocity or acceleration, MuJoCo warns and
    `mujoco.rollout` repeats the last state to the end, so the state's time stops advancing: the prediction from
    there on is not a simulation.

    Args:
        states: (B, nstep + 1, nstate) full-physics states of one model's rollouts (time first), row 0 initial.
        trajs: the B trajectories they re-simulate, for their names.
        warnings: MuJoCo's messages collected meanwhile (`mujoco_warnings`), the first quoted in the error.

    Raises:
        GrounderError: naming the first trajectory that became unstable and when.
    """
    stalled = np.diff(states[..., 0], axis=-1) <= 0.0  # (B, nstep)
    if not stalled.any():
        return
    b = int(np.argmax(stalled.any(axis=1)))
    after_s = float(np.argmax(stalled[b])) * model.opt.timestep
    said = f" (MuJoCo: {warnings[0].split('. ')[0].rstrip('.')})" if warnings else ""  # not its "Time = ..."
    raise GrounderError(
        f"trajectory {trajs[b].name}: the simulation became unstable {after_s:.4g} s after its start{said}; check "
        f"its first state and controls, which the scene cannot simulate, or lower the scene's timestep "
        f"({model.opt.timestep:.4g} s)"
    )


def simulate(
    model: mujoco.MjModel | Sequence[mujoco.MjModel],
    trajs: Sequence[Trajectory],
    *,
    nthread: int | None = None,
    stable: bool = False,
) -> list[list[Trajectory]] | list[Trajectory]:
    """Re-simulates each trajectory from its first state with its controls; predictions at the recorded times.

    Args:
        model: one model, or a sequence of models sharing a size signature (e.g. candidate parameter sets).
        trajs: recorded trajectories in the model's joint order.
        stable: raise (`check_stable`) when MuJoCo stops a rollout as unstable, rather than return its repeated
            last state (calibration leaves this off: an unstable candidate only scores badly).

    Returns:
        For one model, one predicted `Trajectory` per input (same name, times and ctrl). For a sequence of models,
        a list per model.
    """
    models = [model] if isinstance(model, mujoco.MjModel) else list(model)
    batch = prepare(models[0], trajs)
    with mujoco_warnings(stable) as warnings:
        states = rollout_states(models, batch, nthread=nthread)
    if stable:
        for m, states_m in zip(models, states, strict=True):
            check_stable(states_m, trajs, m, warnings)
    qpos_at, qvel_at = _offsets(models[0])
    nq, nv = models[0].nq, models[0].nv
    out: list[list[Trajectory]] = []
    for i in range(len(models)):
        preds = []
        for b, traj in enumerate(trajs):
            rows = states[i, b, batch.sample_steps[b]]
            preds.append(
                Trajectory(
                    time_s=traj.time_s.copy(),
                    qpos=rows[:, qpos_at : qpos_at + nq].copy(),
                    qvel=rows[:, qvel_at : qvel_at + nv].copy(),
                    ctrl=None if traj.ctrl is None else traj.ctrl.copy(),
                    name=traj.name,
                )
            )
        out.append(preds)
    return out[0] if isinstance(model, mujoco.MjModel) else out


@dataclass(frozen=True, kw_only=True)
class FreeJointIndex:
    """Where one free joint's position and quaternion (w first) live in qpos."""

    body: str
    pos: slice
    quat: slice


def free_joints(model: mujoco.MjModel) -> list[FreeJointIndex]:
    """The model's free joints, with the name of the body each moves."""
    out = []
    for j in range(model.njnt):
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            adr = int(model.jnt_qposadr[j])
            body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[j])) or f"body{j}"
            out.append(FreeJointIndex(body=body, pos=slice(adr, adr + 3), quat=slice(adr + 3, adr + 7)))
    return out


def along_view_weighted(
    error_m: np.ndarray, position_m: np.ndarray, view_point_m: np.ndarray | None, along_view_weight: float
) -> np.ndarray:
    """Position errors (..., 3) with their component along the viewing ray scaled by `along_view_weight`.

    The ray runs from `view_point_m` (world, metres: the camera centre) to `position_m` (broadcast with
    `error_m`: where the object was observed). A camera measures an object's depth far less precisely than its
    place across the image (`samples/toss`: 4-6 times), so a loss over tracked positions should trust the
    along-ray part less. Returns `error_m` unchanged when `view_point_m` is None or the weight is 1.
    """
    if view_point_m is None or along_view_weight == 1.0:
        return error_m
    ray = np.asarray(position_m, np.float64) - np.asarray(view_point_m, np.float64)
    ray = ray / np.maximum(np.linalg.norm(ray, axis=-1, keepdims=True), 1e-12)
    along = np.sum(error_m * ray, axis=-1, keepdims=True)
    return error_m - (1.0 - along_view_weight) * along * ray


def free_body_errors(
    model: mujoco.MjModel, predicted: Trajectory, real: Trajectory
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per free body, (position error (T,) metres, rotation error (T,) radians) between two trajectories."""
    return {
        fj.body: (
            np.linalg.norm(predicted.qpos[:, fj.pos] - real.qpos[:, fj.pos], axis=1),
            quat_angle_rad(predicted.qpos[:, fj.quat], real.qpos[:, fj.quat]),
        )
        for fj in free_joints(model)
    }
