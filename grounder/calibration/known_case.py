"""A case with a known answer for the distribution fit: cube tosses whose friction and damping ratio (restitution)
vary from toss to toss with a known mean and spread.

The cube (10 cm, 0.4 kg) is tossed onto a plane from 0.3-0.6 m, 1-2.5 m/s sideways, spinning; each toss draws
its sliding friction and its contact damping ratio (which sets the bounce: `grounder.sim.restitution`) from
independent Gaussians, is simulated with MuJoCo and recorded at 100 Hz for 1 s. The cube's contact parameters
govern (its geoms get the top priority, as calibration sets them).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from grounder.calibration.parameters import apply_to_model, resolve_parameters
from grounder.core.trajectory import Trajectory
from grounder.sim.rollout import simulate

RATE_HZ = 100.0
PERIOD_STEPS = 4
HALF_M = 0.05
VARYING = ("cube.friction.sliding", "cube.solref.dampratio")


def cube_xml(friction: float = 0.5, dampratio: float = 0.5) -> str:
    """The scene: a free cube over a plane, timestep a quarter of the sample interval."""
    return f"""<mujoco model="known_case_cube">
  <option timestep="{1.0 / RATE_HZ / PERIOD_STEPS}" gravity="0 0 -9.81" integrator="implicitfast" cone="pyramidal"/>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" friction="0.3 0.005 0.0001"/>
    <body name="cube" pos="0 0 0.3">
      <freejoint/>
      <inertial pos="0 0 0" mass="0.4" diaginertia="7e-4 7e-4 7e-4"/>
      <geom type="box" size="{HALF_M} {HALF_M} {HALF_M}" friction="{friction} 0.005 0.0001"
            solref="0.02 {dampratio}"/>
    </body>
  </worldbody>
</mujoco>"""


@dataclass(frozen=True, kw_only=True, eq=False)
class KnownCase:
    """The scene (at the population mean), the tosses, and the values each toss ran with ((N, 2), `VARYING`)."""

    xml: str
    trajectories: list[Trajectory]
    values: np.ndarray
    mean: np.ndarray
    std: np.ndarray


def varying_tosses(
    count: int,
    seed: int,
    mean: tuple[float, float] = (0.5, 0.5),
    std: tuple[float, float] = (0.1, 0.1),
    num_samples: int = 100,
) -> KnownCase:
    """``count`` tosses, each with its own (sliding friction, damping ratio) ~ N(mean, diag(std^2))."""
    rng = np.random.default_rng(seed)
    xml = cube_xml(*mean)
    base = mujoco.MjModel.from_xml_string(xml)
    params = resolve_parameters(base, list(VARYING))
    values = np.asarray(mean) + np.asarray(std) * rng.normal(size=(count, 2))
    values = np.maximum(values, 0.02)
    trajs = []
    for i in range(count):
        model = apply_to_model(base, params, values[i])
        qpos0 = np.zeros(7)
        qpos0[2] = rng.uniform(0.3, 0.6)
        quat = rng.normal(size=4)
        qpos0[3:] = quat / np.linalg.norm(quat)
        qvel0 = np.zeros(6)
        heading, speed = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(1.0, 2.5)
        qvel0[:2] = speed * np.cos(heading), speed * np.sin(heading)
        qvel0[2] = rng.uniform(0.0, 1.0)
        qvel0[3:] = rng.normal(scale=3.0, size=3)
        time_s = np.arange(num_samples) / RATE_HZ
        seed_traj = Trajectory(
            time_s=time_s, qpos=np.repeat(qpos0[None], num_samples, 0), qvel=np.repeat(qvel0[None], num_samples, 0)
        )
        pred = simulate(model, [seed_traj], stable=True)[0]
        assert isinstance(pred, Trajectory)
        trajs.append(Trajectory(time_s=time_s, qpos=pred.qpos, qvel=pred.qvel, name=f"toss_{i:03d}"))
    return KnownCase(xml=xml, trajectories=trajs, values=values, mean=np.asarray(mean), std=np.asarray(std))
