"""The residual's learned spread: trained on tosses through gusty air (random kicks to the velocity every sample
interval, of a known size), it finds that size where the cube flies, nothing where it rests, a gain above 0 on
held-out rollouts, and sampled rollouts spread while plain ones do not."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.core.trajectory import Trajectory
from grounder.residual.free_body import body_features
from grounder.residual.meta import META_FILE
from grounder.residual.simulator import Simulator
from grounder.residual.train import train_residual
from tests.grounder.residual.test_train import HALF_M, PERIOD_STEPS, RATE_HZ, TINY, _cube_xml

KICK_M_S = 0.05  # std of the random velocity change per sample interval, each axis


def _gusty_tosses(count: int, seed: int, num_samples: int = 50) -> list[Trajectory]:
    """Tosses whose linear velocity gets a random kick N(0, KICK_M_S^2) per axis after every sample interval."""
    rng = np.random.default_rng(seed)
    model = mujoco.MjModel.from_xml_string(_cube_xml())
    data = mujoco.MjData(model)
    out = []
    for i in range(count):
        mujoco.mj_resetData(model, data)
        data.qpos[:3] = [0.0, 0.0, rng.uniform(0.8, 1.2)]
        quat = rng.normal(size=4)
        data.qpos[3:] = quat / np.linalg.norm(quat)
        data.qvel[:3] = [rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(1.0, 2.0)]
        data.qvel[3:] = rng.normal(scale=3.0, size=3)
        qpos, qvel = [data.qpos.copy()], [data.qvel.copy()]
        for _ in range(num_samples - 1):
            for _ in range(PERIOD_STEPS):
                mujoco.mj_step(model, data)
            data.qvel[:3] += rng.normal(scale=KICK_M_S, size=3)
            qpos.append(data.qpos.copy())
            qvel.append(data.qvel.copy())
        time_s = np.arange(num_samples) / RATE_HZ
        out.append(Trajectory(time_s=time_s, qpos=np.array(qpos), qvel=np.array(qvel), name=f"gust_{i}"))
    return out


@pytest.fixture(scope="module")
def gusty(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = tmp_path_factory.mktemp("gusty")
    (scene / "scene.xml").write_text(_cube_xml())
    out = scene / "residual_scene"
    train_residual(scene, _gusty_tosses(30, seed=3), out, replace(TINY, spread=True, spread_gains=(0.0, 0.5, 1.0)))
    return out


def test_spread_learns_the_size_of_the_kicks_in_flight(gusty: Path) -> None:
    sim = Simulator(gusty)
    residual = sim.residual
    assert residual is not None and residual.spread is not None
    record = json.loads((gusty / META_FILE).read_text())
    assert record["spread"]["hidden"] == TINY.spread_hidden
    gain = record["training"]["spread"]["gain"]
    assert gain > 0  # the kicks are worth sampling on held-out rollouts
    flights = _gusty_tosses(5, seed=11)
    qpos = np.concatenate([t.qpos for t in flights])
    qvel = np.concatenate([t.qvel for t in flights])
    feats, _ = body_features(qpos, qvel, residual.bodies)
    gate = residual.gate(feats)
    flying = gate[:, 0] > 0.99
    assert flying.sum() > 50
    z = (feats - residual.feat_mean) / residual.feat_std
    sd = residual.spread.std(z, gate) / gain  # the learned spread itself, before the chosen gain
    learned = np.median(sd[flying, 0, 6:9])  # body-frame velocity outputs (m/s)
    assert 0.6 * KICK_M_S < learned < 1.6 * KICK_M_S, learned
    assert np.median(sd[flying, 0, 9:12]) < 0.5 * learned * 10  # angular velocity: no kicks (rad/s, loose)


def test_spread_is_zero_at_rest_and_sampled_rollouts_spread(gusty: Path) -> None:
    sim = Simulator(gusty)
    residual = sim.residual
    assert residual is not None and residual.spread is not None
    rest_q = np.array([[0.0, 0.0, HALF_M, 1.0, 0.0, 0.0, 0.0]])
    feats, _ = body_features(rest_q, np.zeros((1, 6)), residual.bodies)
    z = (feats - residual.feat_mean) / residual.feat_std
    assert np.all(residual.spread.std(z, residual.gate(feats)) == 0.0)
    trajs = _gusty_tosses(2, seed=12)
    starts = [(np.repeat(t.qpos[:1], 6, 0), np.repeat(t.qvel[:1], 6, 0)) for t in trajs]
    fans = sim.sample(trajs, starts, np.random.default_rng(0))
    assert fans[0][0].shape == (6, trajs[0].num_steps, 7)
    assert np.ptp(fans[0][0][:, -1, 0]) > 1e-3  # the samples part ways
    np.testing.assert_array_equal(fans[0][0][:, 0], starts[0][0])
    residual.spread.gain[:] = 0.0  # zero spread: every sample is the mean rollout
    plain = sim.sample(trajs, starts, np.random.default_rng(0))
    np.testing.assert_allclose(plain[0][0][1:], np.repeat(plain[0][0][:1], 5, 0), atol=1e-12)
    mean = sim.rollout(trajs)
    np.testing.assert_allclose(plain[0][0][0], mean[0].qpos, atol=1e-9)


def test_a_damaged_spread_is_refused_in_one_line(gusty: Path, tmp_path: Path) -> None:
    import shutil

    import torch

    from grounder.errors import GrounderError

    folder = tmp_path / "damaged"
    shutil.copytree(gusty, folder)
    weights = torch.load(folder / "residual.pt", weights_only=True)
    weights["spread.bound"] = -weights["spread.bound"]
    torch.save(weights, folder / "residual.pt")
    with pytest.raises(GrounderError, match=r"spread\.bound.*<= 0"):
        Simulator(folder)
    del weights["spread.gain"]
    torch.save(weights, folder / "residual.pt")
    with pytest.raises(GrounderError, match=r'missing tensor "spread\.gain"'):
        Simulator(folder)
