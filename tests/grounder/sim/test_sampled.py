"""Sampled rollouts: the start noise measured from recordings, the median of a fan, and the scores of a fan."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from grounder.core.trajectory import Trajectory
from grounder.sim.sample_scores import score_samples, summarise
from grounder.sim.sampled import median_trajectory, rollout_samples
from grounder.sim.start_noise import measure_start_noise, perturbed_starts
from image2sim_common.rotations import quat_angle_rad, quat_mul, rotvec_to_quat

FREE_XML = """<mujoco><option gravity="0 0 -9.81" timestep="0.0025"/><worldbody>
<body name="box"><freejoint/><geom type="box" size="0.05 0.05 0.05" mass="0.3"/></body></worldbody></mujoco>"""
RATE_HZ = 100.0


def _flights(count: int, pos_noise_m: float, vel_noise_m_s: float, seed: int) -> list[Trajectory]:
    """Free flights (parabola, constant spin about z) recorded with Gaussian pose noise on every sample and an
    independent error on the first recorded linear velocity."""
    rng = np.random.default_rng(seed)
    t = np.arange(12) / RATE_HZ
    out = []
    for i in range(count):
        p0, v0, w = rng.normal(size=3) + np.array([0, 0, 1.0]), rng.normal(size=3), rng.normal()
        pos = p0 + v0 * t[:, None] + 0.5 * np.array([0, 0, -9.81]) * t[:, None] ** 2
        pos = pos + rng.normal(scale=pos_noise_m, size=pos.shape)
        quat = np.stack([rotvec_to_quat(np.array([0.0, 0.0, w * s])) for s in t])
        qvel = np.zeros((len(t), 6))
        qvel[:, :3] = v0 + np.array([0, 0, -9.81]) * t[:, None]
        qvel[0, :3] += rng.normal(scale=vel_noise_m_s, size=3)
        qvel[:, 5] = w
        out.append(Trajectory(time_s=t, qpos=np.hstack([pos, quat]), qvel=qvel, name=f"f{i}"))
    return out


def test_start_noise_is_measured_from_the_recordings_themselves() -> None:
    model = mujoco.MjModel.from_xml_string(FREE_XML)
    noise = measure_start_noise(model, _flights(400, pos_noise_m=0.001, vel_noise_m_s=0.1, seed=0))
    assert noise.trajectories == 400
    # the pose noise of every sample, and the error of the first recorded velocity
    np.testing.assert_allclose(noise.pose_std[:3], 0.001, rtol=0.2)
    assert np.all(noise.pose_std[3:] < 1e-6)  # rotations were recorded exactly
    np.testing.assert_allclose(noise.velocity_std[:3], 0.1, rtol=0.25)
    clean = measure_start_noise(model, _flights(20, pos_noise_m=0.0, vel_noise_m_s=0.0, seed=1))
    assert np.all(clean.pose_std < 1e-9) and np.all(clean.velocity_std < 1e-6)
    assert measure_start_noise(model, _flights(2, 0.002, 0.1, seed=2)).trajectories == 0  # too few: none


def test_perturbed_starts_spread_as_measured_and_keep_unit_quaternions() -> None:
    model = mujoco.MjModel.from_xml_string(FREE_XML)
    noise = measure_start_noise(model, _flights(200, pos_noise_m=0.002, vel_noise_m_s=0.1, seed=3))
    traj = _flights(1, 0.0, 0.0, seed=4)[0]
    qpos, qvel = perturbed_starts(model, traj.qpos[0], traj.qvel[0], noise, 4000, np.random.default_rng(0))
    np.testing.assert_allclose(qpos[:, :3].std(axis=0), noise.pose_std[:3], rtol=0.1)
    np.testing.assert_allclose(qvel.std(axis=0)[:3], noise.velocity_std[:3], rtol=0.1)
    np.testing.assert_allclose(np.linalg.norm(qpos[:, 3:], axis=1), 1.0, atol=1e-12)


def test_median_of_a_fan_treats_q_and_minus_q_as_one_rotation() -> None:
    model = mujoco.MjModel.from_xml_string(FREE_XML)
    rng = np.random.default_rng(0)
    centre = rotvec_to_quat(np.array([0.3, -0.2, 1.0]))
    quats = np.stack([quat_mul(centre, rotvec_to_quat(rng.normal(scale=0.05, size=3))) for _ in range(31)])
    quats[::2] *= -1.0  # half the samples written as -q
    qpos = np.zeros((31, 1, 7))
    qpos[:, 0, :3] = rng.normal(size=(31, 3))
    qpos[:, 0, 3:] = quats
    med_q, _ = median_trajectory(model, qpos, np.zeros((31, 1, 6)))
    assert quat_angle_rad(med_q[0, 3:], centre) < 0.05
    np.testing.assert_allclose(med_q[0, :3], np.median(qpos[:, 0, :3], axis=0))


def test_scores_of_a_fan_drawn_like_the_recording_are_calibrated() -> None:
    """Recording and samples drawn from one random process: the bands cover their level; one sample alone scores
    its own distance, and a fan that is too narrow undercovers."""
    model = mujoco.MjModel.from_xml_string(FREE_XML)
    rng = np.random.default_rng(5)
    t_count, k_count = 40, 64
    scores, narrow = [], []

    def walk(count: int, scale: float) -> np.ndarray:
        qpos = np.zeros((count, t_count, 7))
        qpos[:, :, :3] = np.cumsum(rng.normal(scale=scale, size=(count, t_count, 3)), axis=1)
        rv = np.cumsum(rng.normal(scale=0.02, size=(count, t_count, 3)), axis=1)
        qpos[:, :, 3:] = rotvec_to_quat(rv.reshape(-1, 3)).reshape(count, t_count, 4)
        return qpos

    for i in range(40):
        real_q = walk(1, 0.01)[0]
        real = Trajectory(time_s=np.arange(t_count) / RATE_HZ, qpos=real_q, qvel=np.zeros((t_count, 6)), name=f"r{i}")
        scores.append(score_samples(model, real, walk(k_count, 0.01), np.zeros((k_count, t_count, 6))))
        narrow.append(score_samples(model, real, walk(k_count, 0.003), np.zeros((k_count, t_count, 6))))
    s = summarise(scores)
    assert s["coverage90_position"] == pytest.approx(0.9, abs=0.05)
    assert s["coverage50_position"] == pytest.approx(0.5, abs=0.07)
    assert s["coverage90_rotation"] == pytest.approx(0.9, abs=0.05)
    assert summarise(narrow)["coverage90_position"] < 0.7
    assert summarise(narrow)["energy"] > s["energy"]  # a proper score prefers the right spread
    # one simulation: the energy score is its time-averaged distance, every band has width 0
    one = walk(1, 0.01)
    single = score_samples(model, real, np.repeat(one, 2, axis=0), np.zeros((2, t_count, 6)))
    size = 0.1
    dp = np.linalg.norm(one[0, :, :3] - real.qpos[:, :3], axis=1) / size
    da = quat_angle_rad(one[0, :, 3:], real.qpos[:, 3:])
    assert single.energy == pytest.approx(np.mean(np.sqrt(dp**2 + da**2)))
    assert single.band_position_pct[-1] == 0.0
    assert single.best_position_pct == pytest.approx(100 * dp.mean())


def test_sampled_rollouts_match_one_by_one_simulation() -> None:
    """Batched (model, start) samples give what simulating each pair alone gives."""
    from grounder.sim.rollout import simulate

    trajs = _flights(3, 0.0, 0.0, seed=6)
    models = []
    for g in (9.0, 9.81, 10.5):
        m = mujoco.MjModel.from_xml_string(FREE_XML)
        m.opt.gravity[2] = -g
        models.append(m)
    rng = np.random.default_rng(0)
    starts = [
        (t.qpos[[0, 0, 0]] + rng.normal(scale=0.01, size=(3, 7)) * [1, 1, 1, 0, 0, 0, 0], t.qvel[[0, 0, 0]])
        for t in trajs
    ]
    sims = rollout_samples(models, trajs, starts, group_size=2)
    for b, t in enumerate(trajs):
        for k, m in enumerate(models):
            one = Trajectory(time_s=t.time_s, qpos=np.vstack([starts[b][0][k], t.qpos[1:]]), qvel=t.qvel, name="x")
            ref = simulate(m, [one])[0]
            np.testing.assert_allclose(sims[b][0][k], ref.qpos, atol=1e-9)
