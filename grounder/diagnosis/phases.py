"""The phases of recorded motion (free flight, impact, sliding, rolling, resting; actuated or free motion for
models without free bodies), detected per sample, and the held-out gap broken down by phase."""

from __future__ import annotations

import copy

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.diagnosis.gap import Scores, Windows

CONTACT_MARGIN_M = 0.004
"""Distance under which a recorded body counts as touching (tracking noise keeps resting bodies a few mm off)."""

PHASES = ("free_flight", "impact", "sliding", "rolling", "resting", "actuated", "free_motion")


def detect_phases(model: mujoco.MjModel, traj: Trajectory) -> np.ndarray:
    """Phase name per recorded sample (T,), from the recorded motion and the model's contacts at recorded states.

    Free bodies: ``impact`` (contact begins, or approaches the surface faster than 0.3 m/s), ``sliding`` (contact
    point slips faster than 0.05 m/s), ``rolling`` (in contact, not slipping, turning faster than 1 rad/s),
    ``resting``, ``free_flight`` (no geom within ``CONTACT_MARGIN_M``). Models without free joints: ``actuated``
    (any control non-zero), ``free_motion`` (moving), ``resting``. With several free bodies the most eventful phase
    wins.
    """
    free = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    # MuJoCo reports contacts only within the margin: widen it (on a copy) to see near-contacts of noisy data.
    model = copy.copy(model)
    model.geom_margin[:] = np.maximum(model.geom_margin, CONTACT_MARGIN_M)
    data = mujoco.MjData(model)
    n = traj.num_steps
    if not free:
        out = np.full(n, "resting", dtype=object)
        moving = np.abs(traj.qvel).max(axis=1) > 0.05
        out[moving] = "free_motion"
        if traj.ctrl is not None:
            out[np.abs(traj.ctrl).max(axis=1) > 1e-9] = "actuated"
        return out
    priority = {p: i for i, p in enumerate(("impact", "sliding", "rolling", "free_flight", "resting"))}
    phase = np.full(n, "resting", dtype=object)
    in_contact = np.zeros((n, len(free)), bool)
    info = []
    for t in range(n):
        data.qpos[:] = traj.qpos[t]
        data.qvel[:] = traj.qvel[t]
        mujoco.mj_forward(model, data)
        row = []
        for k, j in enumerate(free):
            body = int(model.jnt_bodyid[j])
            dof = int(model.jnt_dofadr[j])
            v = traj.qvel[t, dof : dof + 3]
            omega_world = data.xmat[body].reshape(3, 3) @ traj.qvel[t, dof + 3 : dof + 6]
            slip, approach = 0.0, 0.0
            for c in data.contact[: data.ncon]:
                if c.dist > CONTACT_MARGIN_M or body not in (model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]):
                    continue
                in_contact[t, k] = True
                normal = c.frame[:3] * (1.0 if model.geom_bodyid[c.geom2] == body else -1.0)
                vp = v + np.cross(omega_world, c.pos - data.xpos[body])
                vn = float(vp @ normal)
                slip = max(slip, float(np.linalg.norm(vp - vn * normal)))
                approach = max(approach, -vn)
            row.append((slip, approach, float(np.linalg.norm(omega_world))))
        info.append(row)
    for t in range(n):
        best = "resting"
        for k in range(len(free)):
            slip, approach, omega = info[t][k]
            if not in_contact[t, k]:
                p = "free_flight"
            elif (t > 0 and not in_contact[max(0, t - 2) : t, k].all()) or approach > 0.3:
                p = "impact"
            elif slip > 0.05:
                p = "sliding"
            elif omega > 1.0:
                p = "rolling"
            else:
                p = "resting"
            if priority[p] < priority[best]:
                best = p
        phase[t] = best
    return phase


def window_labels(windows: Windows, phases: list[np.ndarray]) -> np.ndarray:
    """Phase name of every window slot (W, S)."""
    labels = np.empty(windows.mask.shape, dtype=object)
    for w in range(len(windows.traj_index)):
        labels[w] = phases[windows.traj_index[w]][windows.sample_index[w]]
    return labels


def phase_reductions(
    before: Scores, after: Scores, windows: Windows, labels: np.ndarray
) -> dict[str, dict[str, float]]:
    """Held-out gap per phase before and after an effect, and its reduction there."""
    out = {}
    e0, e1 = before.sq[0].mean(axis=-1), after.sq[0].mean(axis=-1)
    for p in PHASES:
        sel = windows.mask & (labels == p)
        if sel.any():
            g0, g1 = float(np.sqrt(e0[sel].mean())), float(np.sqrt(e1[sel].mean()))
            out[p] = {"before": g0, "after": g1, "reduction": 1.0 - g1 / max(g0, 1e-300)}
    return out
