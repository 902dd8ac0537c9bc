"""Many simulations of each recorded trajectory at once: one per (model, start) sample, batched in `mujoco.rollout`.

`rollout_samples` simulates, for each trajectory, K samples, each with its own model (parameters drawn from a
distribution) and its own first state (the recorded one perturbed, `grounder.sim.start_noise`), and returns their
states at the recorded times. Trajectories are grouped by length (a short one is not simulated to the length of the
longest) and each group's K x B rows go through `mujoco.rollout` in as few calls as the memory cap allows.

`median_trajectory` is the per-time-step median of samples: each coordinate's median, with quaternions first put on
one hemisphere (q and -q are one rotation) and the median renormalised.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

import grounder.sim.rollout as sim
from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError


def quaternion_slices(model: mujoco.MjModel) -> list[slice]:
    """Where the model's quaternions (free and ball joints) are in qpos."""
    out = []
    for j in range(model.njnt):
        adr = int(model.jnt_qposadr[j])
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out.append(slice(adr + 3, adr + 7))
        elif model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            out.append(slice(adr, adr + 4))
    return out


def rollout_samples(
    models: Sequence[mujoco.MjModel],
    trajs: Sequence[Trajectory],
    starts: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    nthread: int | None = None,
    max_batch_mb: float = 256.0,
    group_size: int = 16,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Simulates each trajectory K times, sample k with ``models[k]`` from ``starts[b][0][k], starts[b][1][k]``.

    Args:
        models: K models sharing a size signature.
        trajs: B recorded trajectories (their times and controls are used).
        starts: per trajectory, (qpos (K, nq), qvel (K, nv)) first states.
        max_batch_mb: Memory cap of one rollout call's states.

    Returns:
        Per trajectory, (qpos (K, T, nq), qvel (K, T, nv)) at its recorded times.
    """
    if not models:
        raise GrounderError("no models to sample")
    if len(starts) != len(trajs):
        raise GrounderError("one set of starts per trajectory is needed")
    base = models[0]
    k_count = len(models)
    nthread = nthread or sim.default_nthread()
    qpos_at, qvel_at = sim._offsets(base)
    nstate = mujoco.mj_stateSize(base, sim.FULLPHYSICS)
    template = sim.initial_state(base, base.qpos0, np.zeros(base.nv))
    out: list[tuple[np.ndarray, np.ndarray]] = [(np.empty(0), np.empty(0))] * len(trajs)
    order = sorted(range(len(trajs)), key=lambda i: trajs[i].num_steps)
    for g in range(0, len(order), group_size):
        group = order[g : g + group_size]
        batch = sim.prepare(base, [trajs[i] for i in group])
        # every start is the rest state with its qpos and qvel (what `initial_state` gives, without a forward pass
        # per sample: a full-physics state holds no derived quantity)
        states0 = np.tile(template, (k_count, len(group), 1))
        for col, b in enumerate(group):
            qpos, qvel = starts[b]
            if qpos.shape != (k_count, base.nq) or qvel.shape != (k_count, base.nv):
                raise GrounderError(f"starts of {trajs[b].name}: expected shapes ({k_count}, nq), ({k_count}, nv)")
            states0[:, col, qpos_at : qpos_at + base.nq] = qpos
            states0[:, col, qvel_at : qvel_at + base.nv] = qvel
        per_model_bytes = len(group) * (batch.nstep + 1) * nstate * 8 * 2
        chunk = max(1, int(max_batch_mb * 2**20 // max(per_model_bytes, 1)))
        results = [np.empty((k_count, len(trajs[b].time_s), nstate)) for b in group]
        for k0 in range(0, k_count, chunk):
            sub = list(models[k0 : k0 + chunk])
            rows = len(sub) * len(group)
            model_list = [m for m in sub for _ in group]
            s0 = states0[k0 : k0 + len(sub)].reshape(rows, nstate)
            controls = np.tile(batch.controls, (len(sub), 1, 1)) if base.nu else None
            datas = [mujoco.MjData(base) for _ in range(min(nthread, rows))]
            with sim.mujoco_warnings():
                state, _ = mj_rollout.rollout(model_list, datas, s0, controls, nstep=batch.nstep)
            full = np.concatenate([s0[:, None, :], state], axis=1).reshape(len(sub), len(group), batch.nstep + 1, -1)
            for col in range(len(group)):
                results[col][k0 : k0 + len(sub)] = full[:, col, batch.sample_steps[col]]
        for col, b in enumerate(group):
            out[b] = (
                results[col][:, :, qpos_at : qpos_at + base.nq].copy(),
                results[col][:, :, qvel_at : qvel_at + base.nv].copy(),
            )
    return out


def median_trajectory(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-time-step median of samples qpos (K, T, nq), qvel (K, T, nv) (module docstring): (T, nq), (T, nv)."""
    qpos = np.array(qpos, dtype=np.float64, copy=True)
    for sl in quaternion_slices(model):
        quats = qpos[:, :, sl]
        ref = quats[0]  # the first sample at each time: the hemisphere every sample is put on
        flip = np.sum(quats * ref[None], axis=-1) < 0.0
        quats[flip] *= -1.0
        qpos[:, :, sl] = quats
    med_q = np.median(qpos, axis=0)
    for sl in quaternion_slices(model):
        norm = np.linalg.norm(med_q[:, sl], axis=-1, keepdims=True)
        med_q[:, sl] = med_q[:, sl] / np.maximum(norm, 1e-12)
    return med_q, np.median(qvel, axis=0)
