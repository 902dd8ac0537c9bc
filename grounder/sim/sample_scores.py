"""How well a fan of sampled simulations describes one recorded trajectory: energy score, band coverage and width,
the best of the samples, and the median trajectory's errors.

Each free body's motion is read as (position / body size, rotation); the scores are averaged over free bodies.

- **Energy score** (Gneiting & Raftery 2007; lower is better): ``E d(X, y) - 0.5 E d(X, X')`` over samples X, X' of
  the whole trajectory and the recording y, with ``d`` the time-average of ``sqrt(|dp / size|^2 + angle^2)`` (angle
  in radians). A proper scoring rule: it rewards a fan exactly as wide as the real spread; for a single simulation it
  is that simulation's distance ``d(x, y)``.
- **Coverage** of the central 50% and 90% bands: at each time step after the first, the samples' distances to the
  per-step median (position: metres over size; rotation: angle) give the band (their 50% / 90% quantile); the step
  is covered when the recording's distance to the median is within it. A calibrated fan covers 0.5 and 0.9.
- **Band width**: the time-average of the 90% (and 50%) band, position in percent of size, rotation in degrees.
- **Best of N** (the metric of Acosta, Yang & Posa, RA-L 2022, over the first N samples): the smallest time-average
  position error (percent of size) and, separately, the smallest time-average rotation error (degrees).
- **Median**: the same time-averages for the per-step median trajectory (`grounder.sim.sampled.median_trajectory`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from grounder.calibration.parameters import body_size_m
from grounder.core.trajectory import Trajectory
from grounder.sim.rollout import free_joints
from grounder.sim.sampled import median_trajectory
from image2sim_common.rotations import quat_angle_rad

BANDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)  # the reliability curve's levels; 0.5 and 0.9 reported


@dataclass(frozen=True, kw_only=True)
class SampleScores:
    """One recorded trajectory's scores (module docstring); coverage as covered / counted steps per band."""

    energy: float
    energy_position: float
    energy_rotation: float
    covered_position: tuple[int, ...]
    covered_rotation: tuple[int, ...]
    steps: int
    band_position_pct: tuple[float, ...]
    band_rotation_deg: tuple[float, ...]
    best_position_pct: float
    best_rotation_deg: float
    median_position_pct: float
    median_rotation_deg: float


def _energy(dist_to_real: np.ndarray, dist_pairs: np.ndarray) -> float:
    k = len(dist_to_real)
    pair_mean = dist_pairs.sum() / (k * (k - 1)) if k > 1 else 0.0
    return float(dist_to_real.mean() - 0.5 * pair_mean)


def score_samples(
    model: mujoco.MjModel, real: Trajectory, qpos: np.ndarray, qvel: np.ndarray, best_of: int = 16
) -> SampleScores:
    """Scores K sampled simulations qpos (K, T, nq), qvel (K, T, nv) of the recording ``real`` (module docstring)."""
    free = free_joints(model)
    if not free:
        raise ValueError("sample scores need a free body")
    med_q, _ = median_trajectory(model, qpos, qvel)
    k_count, t_count = qpos.shape[0], qpos.shape[1]
    energy = np.zeros(3)
    covered_p = np.zeros(len(BANDS), dtype=int)
    covered_r = np.zeros(len(BANDS), dtype=int)
    band_p = np.zeros(len(BANDS))
    band_r = np.zeros(len(BANDS))
    best_p = np.zeros(min(best_of, k_count))
    best_r = np.zeros(min(best_of, k_count))
    med_p = med_r = 0.0
    for fj in free:
        size = body_size_m(model, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, fj.body))
        pos = qpos[:, :, fj.pos] / size  # (K, T, 3)
        quat = qpos[:, :, fj.quat]
        real_pos = real.qpos[:, fj.pos] / size
        real_quat = real.qpos[:, fj.quat]
        # distances sample -> recording, per step
        dp_real = np.linalg.norm(pos - real_pos[None], axis=2)  # (K, T)
        da_real = quat_angle_rad(quat, np.broadcast_to(real_quat[None], quat.shape))
        # pairwise distances between samples, per step
        dp_pair = np.linalg.norm(pos[:, None] - pos[None, :], axis=3)  # (K, K, T)
        da_pair = quat_angle_rad(
            np.broadcast_to(quat[:, None], (k_count, k_count, t_count, 4)),
            np.broadcast_to(quat[None, :], (k_count, k_count, t_count, 4)),
        )
        energy[0] += _energy(np.sqrt(dp_real**2 + da_real**2).mean(1), np.sqrt(dp_pair**2 + da_pair**2).mean(2))
        energy[1] += _energy(dp_real.mean(1), dp_pair.mean(2))
        energy[2] += _energy(da_real.mean(1), da_pair.mean(2))
        # bands about the per-step median
        med_pos = med_q[:, fj.pos] / size
        med_quat = med_q[:, fj.quat]
        sp = np.linalg.norm(pos - med_pos[None], axis=2)[:, 1:]
        sa = quat_angle_rad(quat, np.broadcast_to(med_quat[None], quat.shape))[:, 1:]
        rp = np.linalg.norm(real_pos - med_pos, axis=1)[1:]
        ra = quat_angle_rad(real_quat, med_quat)[1:]
        for i, level in enumerate(BANDS):
            bp = np.quantile(sp, level, axis=0)
            ba = np.quantile(sa, level, axis=0)
            covered_p[i] += int(np.sum(rp <= bp + 1e-12))
            covered_r[i] += int(np.sum(ra <= ba + 1e-12))
            band_p[i] += 100.0 * float(bp.mean())
            band_r[i] += float(np.degrees(ba.mean()))
        best_p += 100.0 * dp_real[: len(best_p)].mean(1)
        best_r += np.degrees(da_real[: len(best_r)].mean(1))
        med_p += 100.0 * float(np.linalg.norm(med_pos - real_pos, axis=1).mean())
        med_r += float(np.degrees(quat_angle_rad(med_quat, real_quat).mean()))
    n = len(free)
    return SampleScores(
        energy=float(energy[0] / n),
        energy_position=float(energy[1] / n),
        energy_rotation=float(energy[2] / n),
        covered_position=tuple(int(c) for c in covered_p),
        covered_rotation=tuple(int(c) for c in covered_r),
        steps=(t_count - 1) * n,
        band_position_pct=tuple(float(b / n) for b in band_p),
        band_rotation_deg=tuple(float(b / n) for b in band_r),
        best_position_pct=float(best_p.min() / n),
        best_rotation_deg=float(best_r.min() / n),
        median_position_pct=med_p / n,
        median_rotation_deg=med_r / n,
    )


def summarise(scores: Sequence[SampleScores]) -> dict[str, Any]:
    """Means over trajectories (coverage: over all their steps)."""
    steps = sum(s.steps for s in scores)
    out: dict[str, Any] = {
        "energy": float(np.mean([s.energy for s in scores])),
        "energy_position": float(np.mean([s.energy_position for s in scores])),
        "energy_rotation": float(np.mean([s.energy_rotation for s in scores])),
        "best_position_pct": float(np.mean([s.best_position_pct for s in scores])),
        "best_rotation_deg": float(np.mean([s.best_rotation_deg for s in scores])),
        "median_position_pct": float(np.mean([s.median_position_pct for s in scores])),
        "median_rotation_deg": float(np.mean([s.median_rotation_deg for s in scores])),
        "trajectories": len(scores),
    }
    out["reliability_levels"] = list(BANDS)
    out["reliability_position"] = [
        sum(s.covered_position[i] for s in scores) / max(steps, 1) for i in range(len(BANDS))
    ]
    out["reliability_rotation"] = [
        sum(s.covered_rotation[i] for s in scores) / max(steps, 1) for i in range(len(BANDS))
    ]
    for i, level in enumerate(BANDS):
        if level not in (0.5, 0.9):
            continue
        tag = f"{round(level * 100)}"
        out[f"coverage{tag}_position"] = sum(s.covered_position[i] for s in scores) / max(steps, 1)
        out[f"coverage{tag}_rotation"] = sum(s.covered_rotation[i] for s in scores) / max(steps, 1)
        out[f"band{tag}_position_pct"] = float(np.mean([s.band_position_pct[i] for s in scores]))
        out[f"band{tag}_rotation_deg"] = float(np.mean([s.band_rotation_deg[i] for s in scores]))
    return out
