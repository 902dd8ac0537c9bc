"""The joint-space residual (articulated scenes): learns a withheld joint damping and an actuator's weak gain from
recorded motion, never moves a mechanism at rest, stays bounded, agrees across numpy / torch / ONNX, and steps the
same one at a time, in a batch and in a rollout with controls."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.core.trajectory import Trajectory
from grounder.diagnosis.benchmark import select_cases
from grounder.diagnosis.cases import make_case
from grounder.errors import GrounderError
from grounder.residual.joint import NumpyJointResidual, joint_features, joint_space, joint_targets
from grounder.residual.meta import META_FILE, ONNX_FILE, WEIGHTS_FILE
from grounder.residual.options import ResidualOptions
from grounder.residual.simulator import Simulator
from grounder.residual.train import rollout_score, train_residual
from tests._gate_checks import nearest_centre_dist, onnx_gate, smoothstep

SMALL = ResidualOptions(steps=800, hidden=32, seed=0)


def _case(name: str, count: int, seed: int) -> tuple[str, list[Trajectory]]:
    case = make_case(select_cases([name])[0], count, seed=seed)
    return case.scene_xml, case.trajectories


@pytest.fixture(scope="module")
def pendulum_case() -> tuple[str, list[Trajectory]]:
    """The damped pendulum's scene (without the damping) and the recordings the residual is trained on."""
    return _case("pendulum/joint_damping", 24, seed=0)


@pytest.fixture(scope="module")
def pendulum(
    pendulum_case: tuple[str, list[Trajectory]], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, Path]:
    """(nominal scene without damping, residual trained on the damped pendulum's recordings)."""
    xml, trajs = pendulum_case
    nominal = tmp_path_factory.mktemp("pendulum")
    (nominal / "scene.xml").write_text(xml)
    out = tmp_path_factory.mktemp("trained") / "residual"
    train_residual(nominal, trajs, out, SMALL)
    return nominal, out


def test_targets_invert_apply_across_the_angle_wrap() -> None:
    xml, _ = _case("arm/actuator_gain", 1, seed=0)
    model = mujoco.MjModel.from_xml_string(xml)
    space = joint_space(model)
    rng = np.random.default_rng(0)
    q_sim, v_sim = rng.uniform(-3.1, 3.1, (50, 2)), rng.normal(size=(50, 2))
    q_true = q_sim + rng.normal(scale=0.05, size=(50, 2))
    q_true[:5] += 2 * np.pi  # the same angle a turn later: a small correction, not a turn
    v_true = v_sim + rng.normal(scale=0.1, size=(50, 2))
    target = joint_targets(q_sim, v_sim, q_true, v_true, space)
    assert np.abs(target[:, 0, :2]).max() < 0.3
    from grounder.residual.joint import apply_joint_correction

    q, v = apply_joint_correction(q_sim, v_sim, target, space)
    np.testing.assert_allclose(np.angle(np.exp(1j * (q - q_true))), 0.0, atol=1e-12)
    np.testing.assert_allclose(v, v_true, atol=1e-12)


def test_learns_a_withheld_damping(pendulum: tuple[Path, Path]) -> None:
    nominal, trained = pendulum
    _, held_out = _case("pendulum/joint_damping", 8, seed=1)
    plain = Simulator(nominal)
    hybrid = Simulator(trained)
    before = rollout_score(plain.model, plain.rollout(held_out), held_out)
    after = rollout_score(hybrid.model, hybrid.rollout(held_out), held_out)
    assert before > 0.08  # rad: the undamped pendulum swings on
    assert after < 0.15 * before, (before, after)
    meta = json.loads((trained / META_FILE).read_text())
    assert meta["space"] == "joint" and meta["bodies"] == ["hinge"]
    assert meta["features"] == ["sin_hinge", "cos_hinge", "vel_hinge"]
    assert meta["training"]["selected_gain"] > 0


def test_mechanism_at_rest_stays_at_rest(pendulum: tuple[Path, Path]) -> None:
    _, trained = pendulum
    sim = Simulator(trained)
    assert isinstance(sim.residual, NumpyJointResidual)
    sim.residual.out_gain[:] = 1.0
    qpos, qvel = np.zeros(1), np.zeros(1)  # hanging straight down, still
    feats = joint_features(qpos[None], qvel[None], None, sim.residual.space)
    assert np.all(sim.residual(feats) == 0.0)
    for _ in range(round(2.0 / sim.dt_s)):
        qpos, qvel = sim.step(qpos, qvel)
    assert abs(qpos[0]) < 1e-9 and abs(qvel[0]) < 1e-9


def test_bounded_and_fades_outside_training(pendulum: tuple[Path, Path]) -> None:
    _, trained = pendulum
    residual = Simulator(trained).residual
    assert isinstance(residual, NumpyJointResidual)
    rng = np.random.default_rng(2)
    feats = rng.normal(size=(2000, 1, 3)) * 30.0
    assert np.all(np.abs(residual(feats)) <= residual.out_bound[None] + 1e-12)
    far = np.array([[[0.0, 1.0, 200.0]]])  # 200 rad/s: never seen
    assert residual.gate(far)[0, 0] == 0.0


def _residual_at_gain_1(trained: Path) -> tuple[NumpyJointResidual, dict[str, np.ndarray]]:
    """The trained residual and its ``state_dict`` (as numpy) at output gain 1, so that its correction shows the
    gate whatever gain training chose."""
    import torch

    loaded = Simulator(trained).residual
    assert isinstance(loaded, NumpyJointResidual)
    state = {k: v.numpy().copy() for k, v in torch.load(trained / WEIGHTS_FILE, weights_only=True).items()}
    state["out_gain"] = np.ones_like(state["out_gain"])
    return NumpyJointResidual(state, loaded.meta, loaded.space), state


def _gate_of_every_form(
    residual: NumpyJointResidual, state: dict[str, np.ndarray], onnx_path: Path, qpos0: np.ndarray, qvel0: np.ndarray
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The gate (N,) of pendulum states (N, 1), (N, 1) as each form of the residual (at gain 1) applies it.

    ``numpy``: ``NumpyJointResidual.gate``; ``fast``: read back from what ``correct_one`` adds to a zero MuJoCo
    prediction (the gated correction itself); ``torch``: ``JointResidualModel.gate``; ``onnx``: the exported graph's
    correction (at gain 1) over the raw one. Also returns (N,) True where ``correct_one`` left the prediction as it was.
    """
    import torch

    from grounder.residual.torch_model import residual_model

    space = residual.space
    feats = joint_features(qpos0, qvel0, None, space)
    raw = residual.raw(feats)[:, 0]
    fast, untouched = np.empty(len(qpos0)), np.empty(len(qpos0), dtype=bool)
    for i in range(len(qpos0)):
        qpos, qvel = np.zeros(qpos0.shape[1]), np.zeros(qvel0.shape[1])
        residual.correct_one(qpos0[i], qvel0[i], qpos, qvel, None)
        untouched[i] = not (np.any(qpos) or np.any(qvel))
        added = np.concatenate([qpos[space.qpos_adr], qvel[space.dof_adr]])
        fast[i] = added @ raw[i] / (raw[i] @ raw[i])
    model = residual_model(residual.meta, space=space)
    model.load_state_dict({k: torch.as_tensor(v) for k, v in state.items()})
    with torch.no_grad():
        gate_torch = model.gate(torch.as_tensor(feats))[:, 0].numpy()
    gate_onnx = onnx_gate(onnx_path, state, feats, raw, swapped=("out_gain",))
    gates = {"numpy": residual.gate(feats)[:, 0], "fast": fast, "torch": gate_torch, "onnx": gate_onnx}
    return gates, untouched


def test_gate_fades_with_distance_from_the_training_states(
    pendulum: tuple[Path, Path], pendulum_case: tuple[str, list[Trajectory]]
) -> None:
    """A training state of the pendulum moved (angle and velocity) to 0.5, 1.5 and 2.5 times the coverage distance
    from the nearest k-means centre, every feature inside its training range and the pendulum moving: the gate is
    1, then 1 - smoothstep(distance / coverage_dist - 1) (strictly between), then 0 and never opens again on the
    way, in every form of the residual; at 0 the correction is exactly zero."""
    _, trained = pendulum
    residual, state = _residual_at_gain_1(trained)
    space = residual.space
    assert space.feature_names == ("sin_hinge", "cos_hinge", "vel_hinge")
    lo, hi = residual.range_lo[0], residual.range_hi[0]
    coverage_dist = float(residual.coverage_dist[0])
    moving = residual.meta.gate.rest_speed_m_s[1]  # faster than this the at-rest gate is 1
    multiples = (0.5, 1.5, 2.5)
    qpos = np.concatenate([t.qpos for t in pendulum_case[1]])
    qvel = np.concatenate([t.qvel for t in pendulum_case[1]])
    f = joint_features(qpos, qvel, None, space)[:, 0]
    dist = nearest_centre_dist(residual, f) / coverage_dist
    starts = np.flatnonzero(np.all((f >= lo) & (f <= hi), axis=1) & (np.abs(qvel[:, 0]) > 10 * moving) & (dist < 0.25))
    # far states: in range, moving, beyond the last multiple; tried nearest first from each start
    angle, vel = (g.ravel() for g in np.meshgrid(np.linspace(-np.pi, np.pi, 361), np.linspace(lo[2], hi[2], 201)))
    grid = joint_features(angle[:, None], vel[:, None], None, space)[:, 0]
    far = np.all((grid >= lo) & (grid <= hi), axis=1) & (np.abs(vel) > 2 * moving)
    far &= nearest_centre_dist(residual, grid) / coverage_dist > multiples[-1] + 0.2
    t = np.linspace(0.0, 1.0, 801)
    for i in starts:
        turn = np.angle(np.exp(1j * (angle[far] - qpos[i, 0])))  # the shorter way round
        order = np.argsort(np.hypot(turn, (vel[far] - qvel[i, 0]) / residual.feat_std[0, 2]))[:5]
        for turn_j, vel_j in zip(turn[order], vel[far][order], strict=True):
            path_q = (qpos[i, 0] + t * turn_j)[:, None]
            path_v = (qvel[i, 0] + t * (vel_j - qvel[i, 0]))[:, None]
            path_f = joint_features(path_q, path_v, None, space)[:, 0]
            d = nearest_centre_dist(residual, path_f) / coverage_dist
            end = int(np.argmax(d > multiples[-1] + 0.05)) + 1
            inside = np.all((path_f[:end] >= lo) & (path_f[:end] <= hi)) and np.all(np.abs(path_v[:end]) >= moving)
            if inside and np.all(np.diff(np.clip(d[:end] - 1.0, 0.0, 1.0)) >= 0.0):
                break
        else:
            continue
        break
    else:
        pytest.fail(f"no path from a training state out to {multiples[-1]}x the coverage distance inside the ranges")
    path_q, path_v, d = path_q[:end], path_v[:end], d[:end]
    picks = [int(np.argmin(np.abs(d - m))) for m in multiples]
    np.testing.assert_allclose(d[picks], multiples, atol=0.02)
    gates, untouched = _gate_of_every_form(residual, state, trained / ONNX_FILE, path_q, path_v)
    for form, gate in gates.items():
        np.testing.assert_allclose(gate, 1.0 - smoothstep(d - 1.0), atol=1e-9, err_msg=form)
        assert gate[picks[0]] == pytest.approx(1.0, abs=1e-12), form
        assert 0.05 < gate[picks[1]] < 0.95, form
        assert gate[picks[2]] == pytest.approx(0.0, abs=1e-12), form
        assert np.all(np.diff(gate) <= 1e-12), form
    assert gates["numpy"][picks[2]] == 0.0
    far_feats = joint_features(path_q[picks[2] :], path_v[picks[2] :], None, space)
    assert np.all(residual(far_feats) == 0.0)
    assert not untouched[picks[0]] and not untouched[picks[1]] and untouched[picks[2]]


@pytest.mark.parametrize("side", ["above", "below"])
def test_gate_closes_outside_a_feature_range_near_the_training_states(
    pendulum: tuple[Path, Path], pendulum_case: tuple[str, list[Trajectory]], side: str
) -> None:
    """The joint velocity pushed past its training range from a training state, staying near the training states
    (the distance fade alone would leave at least half the gate): the gate is open just inside, fades by
    1 - smoothstep(x) at x margins beyond (margin: ``range_margin`` of the range) and is 0 past the margin, in
    every form; there the correction is zero."""
    _, trained = pendulum
    residual, state = _residual_at_gain_1(trained)
    space = residual.space
    lo, hi = residual.range_lo[0], residual.range_hi[0]
    coverage_dist = float(residual.coverage_dist[0])
    k = space.feature_names.index("vel_hinge")
    margin = residual.meta.gate.range_margin * (hi[k] - lo[k])
    edge, outward = (hi[k], 1.0) if side == "above" else (lo[k], -1.0)
    beyond = np.array([-0.01, 0.5, 1.05])  # in margins past the edge
    qpos = np.concatenate([t.qpos for t in pendulum_case[1]])
    qvel = np.concatenate([t.qvel for t in pendulum_case[1]])
    f = joint_features(qpos, qvel, None, space)[:, 0]
    ok = np.all((f[:, :k] >= lo[:k]) & (f[:, :k] <= hi[:k]), axis=1)
    pushed = f.copy()
    pushed[:, k] = edge + outward * beyond[-1] * margin
    i = int(np.flatnonzero(ok)[np.argmin(nearest_centre_dist(residual, pushed[ok]))])
    path_q = np.repeat(qpos[i][None], len(beyond), axis=0)
    path_v = (edge + outward * beyond * margin)[:, None]
    path_f = joint_features(path_q, path_v, None, space)[:, 0]
    near = 1.0 - smoothstep(nearest_centre_dist(residual, path_f) / coverage_dist - 1.0)
    assert np.all(near >= 0.5), near  # near the training states: only the range check can close the gate
    assert np.all(np.abs(path_v) > residual.meta.gate.rest_speed_m_s[1])
    gates, untouched = _gate_of_every_form(residual, state, trained / ONNX_FILE, path_q, path_v)
    for form, gate in gates.items():
        np.testing.assert_allclose(gate, near * (1.0 - smoothstep(beyond)), atol=1e-6, err_msg=form)
        assert gate[0] >= 0.5 and gate[-1] == pytest.approx(0.0, abs=1e-12), form
    assert gates["numpy"][-1] == 0.0
    assert np.all(residual(joint_features(path_q[2:], path_v[2:], None, space)) == 0.0)
    assert list(untouched) == [False, False, True]


def test_numpy_torch_onnx_agree(pendulum: tuple[Path, Path]) -> None:
    import onnx
    import torch
    from onnx.reference import ReferenceEvaluator

    from grounder.residual.torch_model import residual_model

    _, trained = pendulum
    residual = Simulator(trained).residual
    assert isinstance(residual, NumpyJointResidual)
    space = residual.space
    model = residual_model(residual.meta, space=space)
    model.load_state_dict(torch.load(trained / WEIGHTS_FILE, weights_only=True))
    _, held_out = _case("pendulum/joint_damping", 2, seed=3)
    feats = joint_features(
        np.concatenate([t.qpos for t in held_out]), np.concatenate([t.qvel for t in held_out]), None, space
    )
    expected = residual(feats)
    assert np.abs(expected).max() > 0
    with torch.no_grad():
        np.testing.assert_allclose(model(torch.as_tensor(feats)).numpy(), expected, rtol=1e-9, atol=1e-12)
    graph = onnx.load(str(trained / ONNX_FILE))
    (out,) = ReferenceEvaluator(graph).run(None, {"features": feats})
    np.testing.assert_allclose(out, expected, rtol=1e-9, atol=1e-12)


def test_driven_arm_single_batch_and_rollout_agree(tmp_path: Path) -> None:
    """The arm's controls are features: one state at a time, a batch and a rollout must hand them over alike."""
    xml, trajs = _case("arm/actuator_gain", 16, seed=0)
    nominal = tmp_path / "arm"
    nominal.mkdir()
    (nominal / "scene.xml").write_text(xml)
    result = train_residual(nominal, trajs, tmp_path / "residual", ResidualOptions(steps=400, hidden=32, seed=0))
    sim = Simulator(tmp_path / "residual")
    assert isinstance(sim.residual, NumpyJointResidual)
    space = sim.residual.space
    assert space.history == 5  # 50 ms of earlier controls at 100 Hz
    assert sim.residual.meta.feature_names[6:10] == ("ctrl_0", "ctrl_1", "ctrl_0_prev1", "ctrl_1_prev1")
    sim.residual.out_gain[:] = 1.0  # whatever was chosen, exercise the correction
    traj = trajs[0]
    assert traj.ctrl is not None
    ctrl = traj.ctrl

    def earlier(k: int) -> np.ndarray:  # the controls of the periods before period k, the first one held
        return np.stack([ctrl[max(k - j, 0)] for j in range(1, space.history + 1)])

    pred = sim.rollout([traj])[0]
    qpos, qvel = traj.qpos[0].copy(), traj.qvel[0].copy()
    for k in range(1, 20):
        qpos, qvel = sim.step(qpos, qvel, ctrl[k - 1], earlier(k - 1))
        np.testing.assert_allclose(qpos, pred.qpos[k], atol=1e-9)
    starts = range(3, 8)
    history = np.stack([earlier(i) for i in starts])
    q_b, v_b = sim.step_batch(traj.qpos[3:8], traj.qvel[3:8], ctrl[3:8], history)
    for row, i in enumerate(starts):
        q_s, v_s = sim.step(traj.qpos[i], traj.qvel[i], ctrl[i], earlier(i))
        np.testing.assert_allclose(q_s, q_b[row], atol=1e-9)
        np.testing.assert_allclose(v_s, v_b[row], atol=1e-9)
    held_q, held_v = sim.step(traj.qpos[5], traj.qvel[5], ctrl[5])  # no history given: the control held through it
    assert not np.allclose(held_v, v_b[2])  # the history matters
    q_held_b, v_held_b = sim.step_batch(traj.qpos[5:6], traj.qvel[5:6], ctrl[5:6])
    np.testing.assert_allclose(held_q, q_held_b[0], atol=1e-9)
    np.testing.assert_allclose(held_v, v_held_b[0], atol=1e-9)
    assert result.one_step_rms_after[2] < result.one_step_rms_before[2]  # the weak motors are learnt


def test_learns_an_actuator_delay_from_earlier_controls(tmp_path: Path) -> None:
    """A 30 ms motor delay: only the controls of the periods before show it (the present one does not)."""
    xml, trajs = _case("arm/actuator_delay", 24, seed=0)
    _, held_out = _case("arm/actuator_delay", 8, seed=1)
    nominal = tmp_path / "arm"
    nominal.mkdir()
    (nominal / "scene.xml").write_text(xml)
    train_residual(nominal, trajs, tmp_path / "residual", SMALL)
    plain, hybrid = Simulator(nominal), Simulator(tmp_path / "residual")
    before = rollout_score(plain.model, plain.rollout(held_out), held_out)
    after = rollout_score(hybrid.model, hybrid.rollout(held_out), held_out)
    assert after < 0.5 * before, (before, after)


def test_errors(pendulum: tuple[Path, Path], tmp_path: Path) -> None:
    _, trained = pendulum
    arm_xml, arm_trajs = _case("arm/actuator_gain", 6, seed=0)
    (trained_copy := tmp_path / "other").mkdir()
    for f in trained.iterdir():
        (trained_copy / f.name).write_bytes(f.read_bytes())
    (trained_copy / "scene.xml").write_text(arm_xml)
    with pytest.raises(GrounderError, match="retrain it on this scene"):
        Simulator(trained_copy)
    (arm := tmp_path / "arm").mkdir()
    (arm / "scene.xml").write_text(arm_xml)
    with pytest.raises(GrounderError, match="dagger_rounds=0"):
        train_residual(arm, arm_trajs, tmp_path / "out", ResidualOptions(dagger_rounds=1))
    assert not (tmp_path / "out").exists()


def test_cli_trains_and_rolls_out_a_jointed_scene(pendulum: tuple[Path, Path], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from grounder.cli import app
    from grounder.core.trajectory import save_trajectories

    nominal, _ = pendulum
    _, trajs = _case("pendulum/joint_damping", 6, seed=4)
    traj_dir = save_trajectories(trajs, tmp_path / "trajs")
    out = tmp_path / "out"
    runner = CliRunner()
    args = ["residual", "train", str(nominal), str(traj_dir), "-o", str(out), "--steps", "50"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "joint-space residual" in result.output and (out / ONNX_FILE).is_file()
    report = (out / "report.html").read_text()  # 6 trajectories: 1 held out for the gain, its rollouts shown
    assert "joint error (rad or m)" in report and "joint velocity, rad/s or m/s" in report
    assert str(out / "report.html") in result.output.replace("\n", "")
    result = runner.invoke(app, ["rollout", str(out), str(traj_dir), "-o", str(tmp_path / "pred")])
    assert result.exit_code == 0, result.output
    assert len(list((tmp_path / "pred").glob("*.npz"))) == 6


def test_single_state_path_equals_the_vectorised_one(pendulum: tuple[Path, Path]) -> None:
    """``correct_one`` (what ``Simulator.step`` uses; it stops early where the gate is 0) is ``correct``."""
    _, trained = pendulum
    residual = Simulator(trained).residual
    assert isinstance(residual, NumpyJointResidual)
    residual.out_gain[:] = 1.0
    _, trajs = _case("pendulum/joint_damping", 3, seed=5)
    qpos0 = np.concatenate([t.qpos for t in trajs] + [np.zeros((2, 1)), np.full((1, 1), 3.0)])
    qvel0 = np.concatenate([t.qvel for t in trajs] + [np.array([[0.0], [0.005]]), np.full((1, 1), 80.0)])
    rng = np.random.default_rng(6)
    qpos_sim, qvel_sim = qpos0 + rng.normal(scale=0.01, size=qpos0.shape), qvel0 + rng.normal(size=qvel0.shape)
    expected_q, expected_v = residual.correct(qpos0, qvel0, qpos_sim, qvel_sim)
    moved = 0
    for i in range(len(qpos0)):
        q, v = qpos_sim[i].copy(), qvel_sim[i].copy()
        residual.correct_one(qpos0[i], qvel0[i], q, v, None)
        np.testing.assert_allclose(q, expected_q[i], rtol=0, atol=1e-12)
        np.testing.assert_allclose(v, expected_v[i], rtol=0, atol=1e-12)
        moved += bool(np.any(v != qvel_sim[i]))
    assert 0 < moved < len(qpos0)  # some states corrected, the still and the far ones not
