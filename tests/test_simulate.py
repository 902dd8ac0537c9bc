"""Batched re-simulation of trajectories against closed-form answers."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from grounder import Trajectory
from grounder._simulate import free_body_errors, quat_angle_rad, simulate, step_indices
from grounder.errors import GrounderError

FALLING_CUBE = """
<mujoco><option timestep="0.0005"/>
  <worldbody><body name="cube"><freejoint/><geom type="box" size=".05 .05 .05" mass="1"/></body></worldbody>
</mujoco>"""

SLIDER = """
<mujoco><option timestep="0.001" gravity="0 0 0"/>
  <worldbody><body name="cart"><joint name="x" type="slide" axis="1 0 0"/><geom type="sphere" size=".05" mass="2"/>
  </body></worldbody>
  <actuator><motor joint="x" gear="1"/></actuator>
</mujoco>"""


def _ballistic(time_s: np.ndarray, z0: float, vz0: float) -> Trajectory:
    qpos = np.zeros((len(time_s), 7))
    qpos[:, 2] = z0 + vz0 * time_s - 0.5 * 9.81 * time_s**2
    qpos[:, 3] = 1.0
    qvel = np.zeros((len(time_s), 6))
    qvel[:, 2] = vz0 - 9.81 * time_s
    return Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name="toss")


def test_free_flight_matches_the_parabola_at_data_times() -> None:
    model = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    time_s = np.arange(50) / 100.0  # 100 Hz data, 0.5 ms model steps
    real = _ballistic(time_s, z0=2.0, vz0=1.0)
    predicted = simulate(model, [real])[0]
    assert isinstance(predicted, Trajectory)
    pos_err, rot_err = free_body_errors(model, predicted, real)["cube"]
    # Semi-implicit Euler lags the parabola by 0.5 g dt t: 1.2 mm at 0.49 s.
    assert pos_err.max() < 1.5e-3
    assert pos_err.max() > 0.0
    assert rot_err.max() < 1e-9


def test_controls_are_held_between_samples() -> None:
    model = mujoco.MjModel.from_xml_string(SLIDER)
    time_s = np.arange(11) * 0.01
    ctrl = np.where(time_s < 0.05, 4.0, 0.0)[:, None]  # 2 m/s^2 for 50 ms, then coast
    real = Trajectory(time_s=time_s, qpos=np.zeros((11, 1)), qvel=np.zeros((11, 1)), ctrl=ctrl, name="push")
    predicted = simulate(model, [real])[0]
    assert isinstance(predicted, Trajectory)
    np.testing.assert_allclose(predicted.qvel[-1, 0], 2.0 * 0.05, rtol=1e-6)
    np.testing.assert_allclose(predicted.qpos[5, 0], 0.5 * 2.0 * 0.05**2, rtol=0.05)


def test_many_models_times_many_trajectories() -> None:
    base = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    heavy_gravity = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    heavy_gravity.opt.gravity[2] = -20.0
    time_s = np.arange(20) / 50.0
    trajs = [_ballistic(time_s, 1.0, 0.0), _ballistic(time_s, 3.0, 2.0)]
    out = simulate([base, heavy_gravity], trajs)
    assert len(out) == 2 and all(len(row) == 2 for row in out)
    first = out[0][1]
    second = out[1][1]
    assert isinstance(first, Trajectory) and isinstance(second, Trajectory)
    drop_base = trajs[1].qpos[0, 2] - first.qpos[-1, 2]
    drop_heavy = trajs[1].qpos[0, 2] - second.qpos[-1, 2]
    t = time_s[-1]
    assert drop_heavy - drop_base == pytest.approx(0.5 * (20.0 - 9.81) * t**2, rel=0.02)


def test_quaternion_double_cover_is_the_same_rotation() -> None:
    q = np.array([0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    assert quat_angle_rad(q, -q) == pytest.approx(0.0, abs=1e-6)
    about_z = np.array([np.cos(0.25), 0.0, 0.0, np.sin(0.25)])  # 0.5 rad about z
    assert quat_angle_rad(np.array([1.0, 0, 0, 0]), about_z) == pytest.approx(0.5, abs=1e-9)


def test_data_faster_than_the_model_is_refused() -> None:
    with pytest.raises(GrounderError, match="timestep"):
        step_indices(np.array([0.0, 0.0001, 0.0002]), 0.001)


def test_a_time_column_too_long_to_simulate_is_refused_before_allocating() -> None:
    """A trajectory whose times span 1e9 s (milliseconds written as seconds, or a hostile file) used to reach
    `mujoco.rollout` and fail allocating 121 TB; it is now one error naming the trajectory and its span."""
    model = mujoco.MjModel.from_xml_string(FALLING_CUBE)
    qpos = np.array([[0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0]] * 2)  # at rest: a fall over 1e9 s passes MuJoCo's limit
    traj = Trajectory(time_s=np.array([0.0, 1e9]), qpos=qpos, qvel=np.zeros((2, 6)), name="toss")
    with pytest.raises(
        GrounderError, match=r"trajectory 'toss' spans 1e\+09 s, 2000000000000 model steps.*time column"
    ):
        simulate(model, [traj])
