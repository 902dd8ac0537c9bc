"""The learned residual: trained on tiny synthetic tosses with a withheld effect (air drag), checked for what it
must guarantee (rest stays rest, bounded, fades outside training states), agreement of its numpy / torch / ONNX
forms, batched stepping, and the CLI."""

from __future__ import annotations

import itertools
import json
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from typer.testing import CliRunner

from grounder.core.trajectory import Trajectory, save_trajectories
from grounder.errors import GrounderError
from grounder.residual.free_body import NumpyResidual, apply_correction, body_features, correction_targets, free_bodies
from grounder.residual.meta import FEATURE_NAMES, META_FILE, ONNX_FILE, WEIGHTS_FILE
from grounder.residual.options import ResidualOptions
from grounder.residual.simulator import Simulator, has_residual
from grounder.residual.train import _selection_split, train_residual
from grounder.sim.rollout import simulate
from image2sim_common.rotations import quat_angle_rad, quat_to_rotvec, rotvec_to_quat
from tests._gate_checks import nearest_centre_dist, onnx_gate, smoothstep

HALF_M = 0.05
RATE_HZ = 100.0
PERIOD_STEPS = 4  # model timestep 2.5 ms


def _cube_xml(fluid_density: float = 0.0) -> str:
    # The "real" world differs from the nominal model by air drag (MuJoCo's inertia-box fluid model): a withheld
    # effect the residual has to learn.
    return f"""<mujoco>
  <option timestep="{1.0 / RATE_HZ / PERIOD_STEPS}" gravity="0 0 -9.81" density="{fluid_density}"
          integrator="implicitfast" cone="pyramidal"/>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" friction="0.3 0.005 0.0001"/>
    <body name="cube" pos="0 0 0.3">
      <freejoint/>
      <inertial pos="0 0 0" mass="0.4" diaginertia="7e-4 7e-4 7e-4"/>
      <geom type="box" size="{HALF_M} {HALF_M} {HALF_M}" friction="0.3 0.005 0.0001"/>
    </body>
  </worldbody>
</mujoco>"""


def _tosses(count: int, seed: int, fluid_density: float, num_samples: int = 60) -> list[Trajectory]:
    """Tosses recorded at RATE_HZ in the world with drag: from 0.4-0.8 m high, 1.5-3 m/s sideways, spinning."""
    rng = np.random.default_rng(seed)
    model = mujoco.MjModel.from_xml_string(_cube_xml(fluid_density))
    qpos0 = np.zeros((count, 7))
    qpos0[:, 2] = rng.uniform(0.4, 0.8, count)
    quat = rng.normal(size=(count, 4))
    qpos0[:, 3:] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    qvel0 = np.zeros((count, 6))
    heading = rng.uniform(0, 2 * np.pi, count)
    speed = rng.uniform(1.5, 3.0, count)
    qvel0[:, 0], qvel0[:, 1] = speed * np.cos(heading), speed * np.sin(heading)
    qvel0[:, 2] = rng.uniform(0.0, 1.5, count)
    qvel0[:, 3:] = rng.normal(scale=4.0, size=(count, 3))
    time_s = np.arange(num_samples) / RATE_HZ
    seeds = [
        Trajectory(time_s=time_s, qpos=np.repeat(q[None], num_samples, 0), qvel=np.repeat(v[None], num_samples, 0))
        for q, v in zip(qpos0, qvel0, strict=True)
    ]
    sims = simulate(model, seeds)
    assert isinstance(sims, list)
    return [
        Trajectory(time_s=s.time_s, qpos=s.qpos, qvel=s.qvel, name=f"toss_{seed}_{i}")  # type: ignore[union-attr]
        for i, s in enumerate(sims)
    ]


def _mean_errors(preds: list[Trajectory], real: list[Trajectory]) -> tuple[float, float]:
    pos = [np.mean(np.linalg.norm(p.qpos[:, :3] - r.qpos[:, :3], axis=1)) for p, r in zip(preds, real, strict=True)]
    rot = [np.degrees(np.mean(quat_angle_rad(p.qpos[:, 3:], r.qpos[:, 3:]))) for p, r in zip(preds, real, strict=True)]
    return float(np.mean(pos)), float(np.mean(rot))


DRAG_DENSITY = 40.0  # kg/m^3: exaggerated so that a short toss shows it clearly
TINY = ResidualOptions(
    steps=600, dagger_rounds=0, dagger_horizon=10, dagger_stride=3, hidden=32, smooth_window=0, seed=0, spread=False
)  # the learned spread: tests/grounder/residual/test_spread.py


@pytest.fixture(scope="module")
def nominal_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = tmp_path_factory.mktemp("nominal")
    (scene / "scene.xml").write_text(_cube_xml())
    return scene


@pytest.fixture(scope="module")
def training_tosses() -> list[Trajectory]:
    return _tosses(24, seed=1, fluid_density=DRAG_DENSITY)


@pytest.fixture(scope="module")
def trained(nominal_scene: Path, training_tosses: list[Trajectory], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("trained") / "residual_scene"
    train_residual(nominal_scene, training_tosses, out, TINY)
    return out


def test_quaternion_helpers_round_trip() -> None:
    rng = np.random.default_rng(0)
    rotvec = rng.normal(size=(50, 3))
    rotvec *= (np.minimum(np.linalg.norm(rotvec, axis=1), 3.0) / np.linalg.norm(rotvec, axis=1))[:, None]
    np.testing.assert_allclose(quat_to_rotvec(rotvec_to_quat(rotvec)), rotvec, atol=1e-12)
    tiny = np.array([[1e-9, -2e-9, 3e-10]])
    np.testing.assert_allclose(quat_to_rotvec(rotvec_to_quat(tiny)), tiny, rtol=1e-9)


def test_targets_invert_apply(nominal_scene: Path) -> None:
    model = mujoco.MjModel.from_xml_path(str(nominal_scene / "scene.xml"))
    bodies = free_bodies(model)
    trajs = _tosses(2, seed=5, fluid_density=0.0, num_samples=20)
    q0, v0 = trajs[0].qpos, trajs[0].qvel
    q1, v1 = trajs[1].qpos, trajs[1].qvel
    feats, rots = body_features(q0, v0, bodies)
    corr = correction_targets(q0, v0, q1, v1, rots, bodies)
    q_back, v_back = apply_correction(q0, v0, corr, rots, bodies)
    np.testing.assert_allclose(q_back[:, :3], q1[:, :3], atol=1e-12)
    assert np.max(quat_angle_rad(q_back[:, 3:], q1[:, 3:])) < 1e-9
    np.testing.assert_allclose(v_back, v1, atol=1e-12)
    # clearance of a cube lying flat at height h is h - half-edge
    flat = np.array([[0.0, 0.0, 0.2, 1.0, 0.0, 0.0, 0.0]])
    feats, _ = body_features(flat, np.zeros((1, 6)), bodies)
    assert feats[0, 0, FEATURE_NAMES.index("clearance_m")] == pytest.approx(0.2 - HALF_M, abs=1e-12)


def test_residual_beats_nominal_on_withheld_drag(nominal_scene: Path, trained: Path) -> None:
    held_out = _tosses(12, seed=2, fluid_density=DRAG_DENSITY)
    nominal = Simulator(nominal_scene).rollout(held_out)
    corrected = Simulator(trained).rollout(held_out)
    pos_nominal, rot_nominal = _mean_errors(nominal, held_out)
    pos_residual, rot_residual = _mean_errors(corrected, held_out)
    assert pos_nominal > 0.02  # the withheld drag matters
    assert pos_residual < 0.6 * pos_nominal, (pos_residual, pos_nominal)
    assert rot_residual < rot_nominal + 2.0


def test_files_and_metadata(trained: Path) -> None:
    assert has_residual(trained)
    assert not has_residual(trained / "missing")
    meta = json.loads((trained / META_FILE).read_text())
    assert meta["period_steps"] == PERIOD_STEPS
    assert meta["bodies"] == ["cube"]
    assert meta["training"]["selected_gain"] > 0  # the drag is worth correcting on held-out rollouts
    assert (trained / "scene.xml").is_file() and (trained / WEIGHTS_FILE).is_file()
    import torch

    state = torch.load(trained / WEIGHTS_FILE, weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in state.values())


def test_object_at_rest_stays_at_rest(trained: Path) -> None:
    sim = Simulator(trained)
    assert sim.residual is not None
    # settle with MuJoCo alone, then 2 s with the residual on
    plain = Simulator(trained, use_residual=False)
    qpos = np.array([0.1, -0.2, HALF_M + 0.002, 1.0, 0.0, 0.0, 0.0])
    qvel = np.zeros(6)
    for _ in range(50):
        qpos, qvel = plain.step(qpos, qvel)
    start = qpos.copy()
    feats, _ = body_features(qpos[None], qvel[None], sim.residual.bodies)
    assert np.all(sim.residual(feats) == 0.0)  # exactly zero at rest
    steps = round(2.0 / sim.dt_s)
    for _ in range(steps):
        qpos, qvel = sim.step(qpos, qvel)
    assert np.linalg.norm(qpos[:3] - start[:3]) < 1e-3
    assert np.degrees(quat_angle_rad(qpos[3:], start[3:])) < 0.1
    # same in a batch, with a little residual speed below the rest threshold
    batch_q = np.repeat(start[None], 8, 0)
    batch_v = np.zeros((8, 6))
    batch_v[:, 0] = np.linspace(0.0, 0.005, 8)
    for _ in range(steps):
        batch_q, batch_v = sim.step_batch(batch_q, batch_v)
    assert np.max(np.linalg.norm(batch_q[:, :3] - start[:3], axis=1)) < 1e-3


def test_bounded_and_fades_outside_training(trained: Path) -> None:
    residual = Simulator(trained).residual
    assert residual is not None
    rng = np.random.default_rng(3)
    feats = rng.normal(size=(2000, 1, len(FEATURE_NAMES))) * 20.0
    corr = residual(feats)
    assert np.all(np.abs(corr) <= residual.out_bound[None] + 1e-12)
    far = np.zeros((1, 1, len(FEATURE_NAMES)))
    far[..., 0], far[..., 1], far[..., 4] = 5.0, 5.05, 1.0  # 5 m up: never seen in training
    far[..., 5] = 30.0
    assert residual.gate(far)[0, 0] == 0.0
    assert np.all(residual(far) == 0.0)
    # inside the training states the gate is on for most of them
    held_out = _tosses(4, seed=7, fluid_density=DRAG_DENSITY)
    q = np.concatenate([t.qpos[:20] for t in held_out])
    v = np.concatenate([t.qvel[:20] for t in held_out])
    feats_in, _ = body_features(q, v, residual.bodies)
    assert np.mean(residual.gate(feats_in) > 0.5) > 0.8


def _residual_at_gain_1(trained: Path, coverage_scale: float = 1.0) -> tuple[NumpyResidual, dict[str, np.ndarray]]:
    """The trained residual and its ``state_dict`` (as numpy) at output gain 1, so that its correction shows the
    gate whatever gain training chose, with its coverage distance scaled by ``coverage_scale``."""
    import torch

    loaded = Simulator(trained).residual
    assert isinstance(loaded, NumpyResidual)
    state = {k: v.numpy().copy() for k, v in torch.load(trained / WEIGHTS_FILE, weights_only=True).items()}
    state["out_gain"] = np.ones_like(state["out_gain"])
    state["coverage_dist"] = state["coverage_dist"] * coverage_scale
    return NumpyResidual(state, loaded.meta, loaded.bodies, loaded.gravity), state


def _gate_of_every_form(
    residual: NumpyResidual, state: dict[str, np.ndarray], onnx_path: Path, qpos0: np.ndarray, qvel0: np.ndarray
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The gate (N,) of states (N, 7), (N, 6) of the cube as each form of the residual (at gain 1) applies it.

    ``numpy``: ``NumpyResidual.gate``; ``fast``: read back from what ``correct_one`` adds to a MuJoCo prediction at
    the origin (the energy cap scales velocities only, so the position it returns is the gate times the raw
    position correction in the world frame); ``torch``: ``ResidualModel.gate``; ``onnx``: the exported graph's
    correction (with the same statistics and gain) over the raw one. Also returns (N,) True where ``correct_one``
    left the prediction exactly as it was.
    """
    import torch

    from grounder.residual.torch_model import residual_model

    feats, rots = body_features(qpos0, qvel0, residual.bodies)
    raw = residual.raw(feats)[:, 0]
    fast, untouched = np.empty(len(qpos0)), np.empty(len(qpos0), dtype=bool)
    origin = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    for i in range(len(qpos0)):
        qpos, qvel = origin.copy(), qvel0[i].copy()
        residual.correct_one(qpos0[i], qvel0[i], qpos, qvel)
        untouched[i] = np.array_equal(qpos, origin) and np.array_equal(qvel, qvel0[i])
        fast[i] = (rots[i, 0].T @ qpos[:3]) @ raw[i, :3] / (raw[i, :3] @ raw[i, :3])
    model = residual_model(residual.meta, radius_m=residual.radius_m)
    model.load_state_dict({k: torch.as_tensor(v) for k, v in state.items() if not k.startswith("spread.")})
    with torch.no_grad():
        gate_torch = model.gate(torch.as_tensor(feats))[:, 0].numpy()
    gate_onnx = onnx_gate(onnx_path, state, feats, raw, swapped=("coverage_dist", "out_gain"))
    gates = {"numpy": residual.gate(feats)[:, 0], "fast": fast, "torch": gate_torch, "onnx": gate_onnx}
    return gates, untouched


@pytest.mark.parametrize(("coverage_scale", "multiples"), [(1.0, (0.5, 1.5)), (0.5, (0.5, 1.5, 2.5))])
def test_gate_fades_with_distance_from_the_training_states(
    trained: Path, training_tosses: list[Trajectory], coverage_scale: float, multiples: tuple[float, ...]
) -> None:
    """A training state in flight, moved (its body-frame velocity and angular velocity) away from the training
    states while every feature stays inside its training range: the gate is 1 up to the coverage distance from the
    nearest k-means centre, fades (1 - smoothstep(distance / coverage_dist - 1)) and is 0 from twice that, in every
    form of the residual; where it is 0 the correction is exactly zero.

    The tiny training set leaves a coverage distance (~3.7 standardised units in 11 features) whose double lies
    outside the training ranges from every state inside them (the farthest in-range point is about 2x away), so the
    distance fade alone cannot be followed to 0 with it: the full path uses the residual with that distance halved.
    """
    residual, state = _residual_at_gain_1(trained, coverage_scale)
    lo, hi = residual.range_lo[0], residual.range_hi[0]
    coverage_dist = float(residual.coverage_dist[0])
    qpos = np.concatenate([t.qpos for t in training_tosses])
    qvel = np.concatenate([t.qvel for t in training_tosses])
    feats, rots = body_features(qpos, qvel, residual.bodies)
    f = feats[:, 0]
    dist = nearest_centre_dist(residual, f) / coverage_dist
    flying = f[:, 0] > residual.meta.gate.air_clearance_m[1]  # in flight the at-rest gate is 1 whatever the speed
    starts = np.flatnonzero(np.all((f >= lo) & (f <= hi), axis=1) & flying & (dist < 0.25))
    # towards a corner (2% inside) of the velocity ranges, the orientation and height kept: inside every range
    corners = lo[5:] + np.array(list(itertools.product((0.02, 0.98), repeat=6))) * (hi - lo)[5:]
    t = np.linspace(0.0, 1.0, 801)[:, None]
    for i in starts:
        targets = np.repeat(f[i][None], len(corners), axis=0)
        targets[:, 5:] = corners
        target = targets[np.argmax(nearest_centre_dist(residual, targets))]
        d = nearest_centre_dist(residual, f[i] + t * (target - f[i])) / coverage_dist
        if d.max() < multiples[-1] + 0.05:
            continue
        end = int(np.argmax(d > multiples[-1] + 0.05)) + 1
        if np.all(np.diff(np.clip(d[:end] - 1.0, 0.0, 1.0)) >= 0.0):  # the distance grows where the gate fades
            break
    else:
        pytest.fail(f"no path from a training state out to {multiples[-1]}x the coverage distance inside the ranges")
    step = target - f[i]
    path_q = np.repeat(qpos[i][None], end, axis=0)
    path_v = qvel[i] + t[:end] * np.concatenate([rots[i, 0] @ step[5:8], step[8:11]])
    path_f = body_features(path_q, path_v, residual.bodies)[0][:, 0]
    np.testing.assert_allclose(path_f, f[i] + t[:end] * step, atol=1e-9)
    assert np.all((path_f >= lo) & (path_f <= hi))
    d = d[:end]
    picks = [int(np.argmin(np.abs(d - m))) for m in multiples]
    np.testing.assert_allclose(d[picks], multiples, atol=0.02)
    gates, untouched = _gate_of_every_form(residual, state, trained / ONNX_FILE, path_q, path_v)
    for form, gate in gates.items():
        np.testing.assert_allclose(gate, 1.0 - smoothstep(d - 1.0), atol=1e-9, err_msg=form)
        assert gate[picks[0]] == pytest.approx(1.0, abs=1e-12), form
        assert 0.05 < gate[picks[1]] < 0.95, form
        assert np.all(np.diff(gate) <= 1e-12), form  # never opens again on the way out
        if len(picks) > 2:
            assert gate[picks[2]] == pytest.approx(0.0, abs=1e-12), form
    if len(picks) > 2:
        far = slice(picks[2], picks[2] + 1)
        assert gates["numpy"][picks[2]] == 0.0
        assert np.all(residual(body_features(path_q[far], path_v[far], residual.bodies)[0]) == 0.0)
        assert untouched[picks[2]] and not untouched[picks[1]]
    assert not untouched[picks[0]]


@pytest.mark.parametrize("side", ["above", "below"])
def test_gate_closes_outside_a_feature_range_near_the_training_states(
    trained: Path, training_tosses: list[Trajectory], side: str
) -> None:
    """One feature (the body-frame x velocity) pushed past its training range, the state staying within the
    coverage distance of a training centre: the gate is 1 just inside, 1 - smoothstep(x) at x margins beyond
    (margin: ``range_margin`` of the range) and 0 past the margin, in every form; there the correction is zero."""
    residual, state = _residual_at_gain_1(trained)
    lo, hi = residual.range_lo[0], residual.range_hi[0]
    k = FEATURE_NAMES.index("vel_body_x_m_s")
    margin = residual.meta.gate.range_margin * (hi[k] - lo[k])
    edge, outward = (hi[k], 1.0) if side == "above" else (lo[k], -1.0)
    beyond = np.array([-0.01, 0.5, 1.05])  # in margins past the edge
    qpos = np.concatenate([t.qpos for t in training_tosses])
    qvel = np.concatenate([t.qvel for t in training_tosses])
    feats, rots = body_features(qpos, qvel, residual.bodies)
    f = feats[:, 0]
    others = np.delete(np.arange(len(FEATURE_NAMES)), k)
    ok = np.all((f[:, others] >= lo[others]) & (f[:, others] <= hi[others]), axis=1)
    ok &= f[:, 0] > residual.meta.gate.air_clearance_m[1]
    pushed = f.copy()
    pushed[:, k] = edge + outward * beyond[-1] * margin
    i = int(np.flatnonzero(ok)[np.argmin(nearest_centre_dist(residual, pushed[ok]))])
    new_k = edge + outward * beyond * margin
    path_q = np.repeat(qpos[i][None], len(beyond), axis=0)
    path_v = np.repeat(qvel[i][None], len(beyond), axis=0)
    path_v[:, :3] += (new_k - f[i, k])[:, None] * rots[i, 0][:, 0]  # along the body's x axis
    path_f = body_features(path_q, path_v, residual.bodies)[0][:, 0]
    np.testing.assert_allclose(path_f[:, k], new_k, atol=1e-9)
    np.testing.assert_allclose(path_f[:, others], np.repeat(f[i, others][None], len(beyond), 0), atol=1e-9)
    # near the training states (no distance fade), so only the range check can close the gate
    assert np.all(nearest_centre_dist(residual, path_f) < residual.coverage_dist[0])
    gates, untouched = _gate_of_every_form(residual, state, trained / ONNX_FILE, path_q, path_v)
    for form, gate in gates.items():
        np.testing.assert_allclose(gate, 1.0 - smoothstep(beyond), atol=1e-6, err_msg=form)
        assert gate[0] == pytest.approx(1.0, abs=1e-12) and gate[-1] == pytest.approx(0.0, abs=1e-12), form
    assert gates["numpy"][-1] == 0.0
    assert np.all(residual(body_features(path_q[2:], path_v[2:], residual.bodies)[0]) == 0.0)
    assert list(untouched) == [False, False, True]


def test_numpy_torch_onnx_agree(trained: Path) -> None:
    import onnx
    import torch
    from onnx.reference import ReferenceEvaluator

    from grounder.residual.torch_model import residual_model

    residual = Simulator(trained).residual
    assert residual is not None
    model = residual_model(residual.meta, radius_m=residual.radius_m)
    weights = torch.load(trained / WEIGHTS_FILE, weights_only=True)
    model.load_state_dict({k: v for k, v in weights.items() if not k.startswith("spread.")})  # the mean's tensors
    held_out = _tosses(2, seed=8, fluid_density=DRAG_DENSITY)
    feats, _ = body_features(
        np.concatenate([t.qpos for t in held_out]), np.concatenate([t.qvel for t in held_out]), residual.bodies
    )
    expected = residual(feats)
    assert np.abs(expected).max() > 0
    with torch.no_grad():
        np.testing.assert_allclose(model(torch.as_tensor(feats)).numpy(), expected, rtol=1e-9, atol=1e-12)
    graph = onnx.load(str(trained / ONNX_FILE))
    onnx.checker.check_model(graph)
    assert [i.name for i in graph.graph.input] == ["features"]
    (out,) = ReferenceEvaluator(graph).run(None, {"features": feats})
    np.testing.assert_allclose(out, expected, rtol=1e-9, atol=1e-12)


def test_batch_of_1024_and_single_agree(trained: Path) -> None:
    sim = Simulator(trained)
    tosses = _tosses(1024, seed=9, fluid_density=DRAG_DENSITY, num_samples=2)
    qpos = np.stack([t.qpos[0] for t in tosses])
    qvel = np.stack([t.qvel[0] for t in tosses])
    for _ in range(5):
        qpos, qvel = sim.step_batch(qpos, qvel)
    assert qpos.shape == (1024, 7) and np.isfinite(qpos).all() and np.isfinite(qvel).all()
    q1, v1 = sim.step_batch(qpos[:3], qvel[:3])
    for i in range(3):
        qs, vs = sim.step(qpos[i], qvel[i])
        np.testing.assert_allclose(qs, q1[i], atol=1e-9)
        np.testing.assert_allclose(vs, v1[i], atol=1e-6)


def test_rollout_contract(nominal_scene: Path, trained: Path) -> None:
    trajs = _tosses(3, seed=4, fluid_density=DRAG_DENSITY, num_samples=30)
    model = mujoco.MjModel.from_xml_path(str(nominal_scene / "scene.xml"))
    expected = simulate(model, trajs)
    got = Simulator(trained, use_residual=False).rollout(trajs)
    for e, g in zip(expected, got, strict=True):
        np.testing.assert_array_equal(e.qpos, g.qpos)  # type: ignore[union-attr]
    preds = Simulator(trained).rollout(trajs)
    for p, t in zip(preds, trajs, strict=True):
        assert p.name == t.name and np.array_equal(p.time_s, t.time_s)
        np.testing.assert_array_equal(p.qpos[0], t.qpos[0])
    # the hybrid rollout is the same as stepping one period at a time
    sim = Simulator(trained)
    qpos, qvel = trajs[0].qpos[0], trajs[0].qvel[0]
    for k in range(1, 10):
        qpos, qvel = sim.step(qpos, qvel)
        np.testing.assert_allclose(qpos, preds[0].qpos[k], atol=1e-7)


def test_training_is_reproducible(nominal_scene: Path, tmp_path: Path) -> None:
    import torch

    trajs = _tosses(6, seed=11, fluid_density=DRAG_DENSITY, num_samples=30)
    options = ResidualOptions(steps=20, dagger_rounds=1, dagger_horizon=5, hidden=16, seed=3)
    train_residual(nominal_scene, trajs, tmp_path / "a", options)
    train_residual(nominal_scene, trajs, tmp_path / "b", options)
    a = torch.load(tmp_path / "a" / WEIGHTS_FILE, weights_only=True)
    b = torch.load(tmp_path / "b" / WEIGHTS_FILE, weights_only=True)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_errors(nominal_scene: Path, trained: Path, tmp_path: Path) -> None:
    with pytest.raises(GrounderError, match=r"scene\.xml"):
        Simulator(tmp_path / "nowhere")
    with pytest.raises(GrounderError, match="not empty"):
        train_residual(nominal_scene, _tosses(2, seed=1, fluid_density=0.0, num_samples=10), trained, TINY)
    meta = json.loads((trained / META_FILE).read_text())
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "scene.xml").write_text(_cube_xml().replace('timestep="0.0025"', 'timestep="0.002"'))
    (broken / WEIGHTS_FILE).write_bytes((trained / WEIGHTS_FILE).read_bytes())
    (broken / META_FILE).write_text(json.dumps(meta))
    with pytest.raises(GrounderError, match="timestep"):
        Simulator(broken)


def test_cli_train(nominal_scene: Path, tmp_path: Path) -> None:
    from grounder.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["residual", "train", "--help"])
    assert result.exit_code == 0 and "residual train" in result.output
    traj_dir = save_trajectories(_tosses(4, seed=12, fluid_density=DRAG_DENSITY, num_samples=20), tmp_path / "trajs")
    out = tmp_path / "out"
    args = ["residual", "train", str(nominal_scene), str(traj_dir), "-o", str(out), "--steps", "20", "--rounds", "0"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert has_residual(out) and (out / ONNX_FILE).is_file()
    report = (out / "report.html").read_text()  # 4 trajectories: none held out, so no gain check to show
    assert "No gain check: too few trajectories" in report and "Gain on held-out" not in report
    result = runner.invoke(app, ["residual", "train", str(tmp_path / "none"), str(traj_dir), "-o", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert "scene.xml" in result.output
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "scene.xml").write_text("<mujoco")  # not even XML: one line naming the file
    result = runner.invoke(app, ["residual", "train", str(broken), str(traj_dir), "-o", str(tmp_path / "y")])
    assert result.exit_code == 2 and "scene.xml: not well-formed XML (" in result.output
    assert len(result.output.strip().splitlines()) == 1 and not (tmp_path / "y").exists()


def test_fast_single_state_path_equals_reference(trained: Path) -> None:
    """``correct_one`` (compiled, skips the network where the gate is 0) is the same function as the vectorised
    ``correct``: in flight, at rest, near and outside the training ranges; where the gate is 0 it leaves MuJoCo's
    state exactly as it was."""
    residual = Simulator(trained).residual
    assert residual is not None
    plain = Simulator(trained, use_residual=False)
    tosses = _tosses(6, seed=11, fluid_density=DRAG_DENSITY)
    q0 = np.concatenate([t.qpos for t in tosses])
    v0 = np.concatenate([t.qvel for t in tosses])
    rng = np.random.default_rng(12)
    # at rest on the floor (slow, and just below the rest threshold), and partly or far outside training
    rest_q = np.tile([0.1, -0.2, HALF_M, 1.0, 0.0, 0.0, 0.0], (8, 1))
    rest_v = np.zeros((8, 6))
    rest_v[:, 0] = np.linspace(0.0, 0.009, 8)
    out_q = q0[rng.choice(len(q0), 40)]
    out_v = v0[rng.choice(len(v0), 40)] * rng.uniform(0.5, 4.0, (40, 1))
    out_q[:10, 2] += rng.uniform(0.5, 5.0, 10)
    q0, v0 = np.concatenate([q0, rest_q, out_q]), np.concatenate([v0, rest_v, out_v])
    q_sim, v_sim = plain.step_batch(q0, v0)
    feats, _ = body_features(q0, v0, residual.bodies)
    gate = residual.gate(feats)[:, 0]
    assert np.sum(gate == 0.0) >= 10 and np.sum((gate > 0.0) & (gate < 1.0)) >= 5 and np.sum(gate == 1.0) >= 100
    q_ref, v_ref = residual.correct(q0, v0, q_sim, v_sim)
    assert np.abs(q_ref - q_sim).max() > 1e-5  # the correction is not trivially zero
    for i in range(len(q0)):
        q, v = q_sim[i].copy(), v_sim[i].copy()
        residual.correct_one(q0[i], v0[i], q, v)
        np.testing.assert_allclose(q, q_ref[i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(v, v_ref[i], rtol=0, atol=1e-10)
        if gate[i] == 0.0:  # exactly as MuJoCo made it
            assert np.array_equal(q, q_sim[i]) and np.array_equal(v, v_sim[i])
    # the output gain, set in place as training's gain check does, applies to the single-state path too
    moved = int(np.argmax(gate))
    gain = residual.out_gain.copy()
    for scale in (0.0, 0.5):
        residual.out_gain[:] = scale * gain
        q, v = q_sim[moved].copy(), v_sim[moved].copy()
        residual.correct_one(q0[moved], v0[moved], q, v)
        q_ref, v_ref = residual.correct(
            q0[moved : moved + 1], v0[moved : moved + 1], q_sim[moved : moved + 1], v_sim[moved : moved + 1]
        )
        np.testing.assert_allclose(q, q_ref[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(v, v_ref[0], rtol=0, atol=1e-10)
        assert np.array_equal(q, q_sim[moved]) == (scale == 0.0)
    residual.out_gain[:] = gain


def test_rollout_errors_known_answer(nominal_scene: Path) -> None:
    """A prediction 6 mm and 30 deg off the recording all along: 6% of the 0.1 m cube and 30 deg, score 0.36."""
    from grounder.residual.report import rollout_errors
    from grounder.residual.train import rollout_score

    model = mujoco.MjModel.from_xml_path(str(nominal_scene / "scene.xml"))
    real = _tosses(2, seed=7, fluid_density=0.0, num_samples=15)
    half = np.radians(30.0) / 2.0
    turn = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])  # 30 deg about z
    preds = []
    for r in real:
        qpos = r.qpos.copy()
        qpos[:, 0] += 0.006
        w, x, y, z = qpos[:, 3:].T
        tw, _, _, tz = turn  # quaternion product q * turn, turn about z
        qpos[:, 3:] = np.stack([w * tw - z * tz, x * tw + y * tz, y * tw - x * tz, w * tz + z * tw], axis=1)
        preds.append(Trajectory(time_s=r.time_s, qpos=qpos, qvel=r.qvel))
    errors = rollout_errors(model, preds, real)
    np.testing.assert_allclose(errors.position_pct, 6.0, rtol=1e-9)
    np.testing.assert_allclose(errors.rotation_deg, 30.0, rtol=1e-6)
    assert rollout_score(model, preds, real) == pytest.approx(0.36, rel=1e-6)
    assert rollout_score(model, real, real) == pytest.approx(0.0, abs=1e-6)


def test_report_shows_the_gain_check_and_the_gate(trained: Path) -> None:
    """report.html: one self-contained file whose gain table is the gain check's own scores, with the chosen gain,
    the held-out rollouts and the gate's share of held-out states."""
    import html
    import re

    from grounder.residual.train import REPORT_FILE

    text = (trained / REPORT_FILE).read_text()
    assert "http://" not in text and "https://" not in text and 'src="data:image/png;base64,' in text
    meta = json.loads((trained / META_FILE).read_text())["training"]
    rows = dict(re.findall(r"<tr><td>([0-9.]+)</td><td>([0-9.]+)</td>", text))
    assert rows, "no gain table"
    assert {float(g): float(s) for g, s in rows.items()} == pytest.approx(
        {float(g): s for g, s in meta["gain_scores"].items()}, abs=6e-5
    )
    assert f"chose gain {meta['selected_gain']:g}" in html.unescape(text)
    shares = re.search(
        r"closed \(no correction\) in ([0-9.]+)%, fully open in ([0-9.]+)%, in between in ([0-9.-]+)%", text
    )
    assert shares is not None
    assert sum(float(v) for v in shares.groups()) == pytest.approx(100.0, abs=0.2)
    assert float(shares.group(2)) > 50.0  # tosses in flight: the gate is open most of the time
    assert text.count("<img") >= 4  # gain curve, held-out scatter, trajectories, gate histogram


def test_output_inside_the_scene_folder(tmp_path: Path) -> None:
    """The output is staged beside itself; inside the scene folder that is inside the folder being copied: the copy
    must not take the staging folder along (a nested copy of itself), nor anything half-written."""
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(_cube_xml())
    (scene / "notes.txt").write_text("mine")
    options = replace(TINY, steps=50)
    out = train_residual(scene, _tosses(6, seed=3, fluid_density=0.0, num_samples=20), scene / "res", options).out
    assert out == scene / "res"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["scene.xml", "notes.txt", WEIGHTS_FILE, META_FILE, ONNX_FILE, "report.html"]
    )
    assert sorted(p.name for p in scene.iterdir()) == ["notes.txt", "res", "scene.xml"]


def test_compiled_path_works_where_no_cache_folder_is_writable(monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only install and user cache: numba finds no folder to cache in (it raises when the function is
    defined); the single-state path is then compiled in the process instead of failing to import."""
    import numba
    from numba.core import caching

    from grounder.residual.kernel import _jit

    def half(x: float) -> float:
        return 0.5 * x

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])
    with pytest.raises(RuntimeError, match="no locator available"):
        numba.njit(cache=True)(half)
    compiled = _jit(half)
    assert compiled(3.0) == 1.5
    assert isinstance(compiled._cache, caching.NullCache)  # compiled here, not cached


def test_gain_check_split_keeps_copies_together() -> None:
    """The trajectories the gain is chosen on and those fitted never share a motion stored twice."""
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body><joint type="slide"/><geom size="0.1"/></body></worldbody></mujoco>'
    )

    def slide(speed: float, name: str) -> Trajectory:
        return Trajectory(time_s=np.arange(3) / 148.0, qpos=np.zeros((3, 1)), qvel=np.full((3, 1), speed), name=name)

    trajs = [slide(i, f"t{i}") for i in range(20)]
    options = ResidualOptions(selection_fraction=0.3, seed=0)
    fit, held = _selection_split(trajs, options, model)
    assert len(held) == 6 and {t.name for t in fit} | {t.name for t in held} == {t.name for t in trajs}
    a, b = int(fit[0].name[1:]), int(held[0].name[1:])
    # b recorded again as a copy of a: the pair follows its first member, the lower index, here a: both fitted
    assert a < b
    copied = [slide(a if i == b else i, f"t{i}") for i in range(20)]
    fit_g, held_g = _selection_split(copied, options, model)
    assert {f"t{a}", f"t{b}"} <= {t.name for t in fit_g} and len(held_g) == 5
