"""Calibration: parameter names act the same on a model and on its MJCF, known parameters are recovered from
synthetic tosses, the calibrated scene folder is complete, and bad input gives one line and exit code 2."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
from typer.testing import CliRunner

import grounder.sim.rollout as sim
from grounder.calibration.fit import calibrate, split_names
from grounder.calibration.options import CalibrateOptions
from grounder.calibration.parameters import apply_to_model, apply_to_spec, resolve_parameters
from grounder.core.repeats import split_keeping_together
from grounder.core.trajectory import Trajectory, load_trajectories, save_trajectories
from grounder.errors import GrounderError
from reconstruction.errors import InputError

REPO = Path(__file__).resolve().parents[3]
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"
RATE_HZ = 148.0

MULTI_XML = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="box" pos="0 0 0.2">
      <freejoint/>
      <geom name="box_geom" type="box" size="0.05 0.04 0.03" mass="0.5"/>
      <geom name="box_cap" type="sphere" pos="0.05 0 0" size="0.02" mass="0.1"/>
    </body>
    <body name="arm" pos="0.5 0 0.3">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom name="ball" type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
    </body>
  </worldbody>
  <actuator><motor name="motor" joint="hinge" gear="1"/></actuator>
</mujoco>
"""


def test_parameters_set_model_and_spec_identically() -> None:
    spec = mujoco.MjSpec.from_string(MULTI_XML)
    base = spec.compile()
    names = [
        "box.mass",
        "box.com.x",
        "box.friction.sliding",
        "box.friction.rolling",
        "box.solref.timeconst",
        "box.solref.dampratio",
        "box.solimp.width",
        "box.size_scale",
        "geom:ball.friction.torsional",
        "joint:hinge.damping",
        "joint:hinge.armature",
        "actuator:motor.gain",
        "opt.gravity_scale",
        "opt.impratio",
    ]
    params = resolve_parameters(base, names)
    rng = np.random.default_rng(3)
    values = [float(p.from_unit(rng.uniform(0.1, 0.9))) for p in params]
    direct = apply_to_model(base, params, values)
    compiled = apply_to_spec(spec, base, params, values).compile()
    for field in (
        "body_mass",
        "body_inertia",
        "body_ipos",
        "body_invweight0",
        "dof_invweight0",
        "geom_friction",
        "geom_solref",
        "geom_solimp",
        "geom_size",
        "geom_pos",
        "geom_rbound",
        "geom_priority",
        "dof_damping",
        "dof_armature",
        "actuator_gainprm",
    ):
        np.testing.assert_allclose(
            getattr(direct, field), getattr(compiled, field), rtol=1e-6, atol=1e-9, err_msg=field
        )
    np.testing.assert_allclose(direct.geom_aabb, compiled.geom_aabb, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(direct.opt.gravity, compiled.opt.gravity)
    assert direct.opt.impratio == pytest.approx(compiled.opt.impratio)
    box = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_BODY, "box")
    assert direct.body_mass[box] == pytest.approx(values[0])
    # Calibrated contact geoms outrank the floor, so their own friction governs their contacts.
    floor = mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert (
        direct.geom_priority[mujoco.mj_name2id(base, mujoco.mjtObj.mjOBJ_GEOM, "box_geom")]
        > direct.geom_priority[floor]
    )


@pytest.mark.parametrize(
    ("name", "needle"),
    [
        ("box.weight", "unknown parameter"),
        ("crate.mass", "no body 'crate'"),
        ("geom:nope.friction.sliding", "unknown geom"),
        ("joint:hinge.color", "unknown parameter"),
        ("box.friction.sliding=0.5:0.1", "LOW < HIGH"),
        ("box.solref.timeconst=0:0.1", "lower bound must be > 0"),
    ],
)
def test_bad_parameter_names(name: str, needle: str) -> None:
    base = mujoco.MjModel.from_xml_string(MULTI_XML)
    with pytest.raises(GrounderError, match=needle.replace("(", r"\(")):
        resolve_parameters(base, [name])


def test_split_is_reproducible_and_disjoint() -> None:
    names = [str(i) for i in range(20)]
    train, val = split_names(names, 0.3, seed=0)
    assert len(val) == 6 and len(train) == 14
    assert not set(train) & set(val) and set(train) | set(val) == set(names)
    assert (train, val) == split_names(list(reversed(names)), 0.3, seed=0)
    assert split_names(names, 0.3, seed=1) != (train, val)


def test_split_keeps_copies_of_one_motion_together() -> None:
    names = [str(i) for i in range(20)]
    train, val = split_names(names, 0.3, seed=0)
    # one group straddling the split each way, one inside validation, one inside training
    groups = [(train[0], val[0]), (val[1], train[1]), (val[2], val[3]), (train[2], train[3], train[4])]
    train_g, val_g = split_names(names, 0.3, seed=0, together=groups)
    assert set(train_g) | set(val_g) == set(names) and not set(train_g) & set(val_g)
    for group in groups:  # whole, on the side its first member had
        assert set(group) <= set(train_g if group[0] in train else val_g)
    others = set(names) - {n for g in groups for n in g}
    assert set(train_g) & others == set(train) & others and set(val_g) & others == set(val) & others
    assert len(val_g) == len(val)  # here one moved each way


def test_split_keeping_together_keeps_both_sides() -> None:
    # a group that would fill one side gives way so that the other keeps a unit; a single unit is all training
    assert split_keeping_together(["a", "b", "c"], 2, [("a", "b", "c")]) == ([], ["a", "b", "c"])
    assert split_keeping_together(["a", "b", "c"], 2, [("b", "c")]) == (["a"], ["b", "c"])
    assert split_keeping_together(["a", "b", "c"], 1, [("a", "b")]) == (["a", "b"], ["c"])
    assert split_keeping_together(["a", "b", "c"], 1, [("c", "a")]) == (["b"], ["a", "c"])
    assert split_keeping_together([3, 1, 2, 0], 1, [(0, 3)]) == ([2], [3, 1, 0])  # the group follows 0, not 3
    train, val = split_names(["x", "y", "z"], 0.5, 0, together=[("x", "y", "z")])
    assert (train, val) == (["x", "y", "z"], [])


def _true_cube(friction: float, timeconst: float) -> mujoco.MjModel:
    spec = mujoco.MjSpec.from_file(str(CUBE_XML))
    spec.geom("cube").friction[0] = friction
    spec.geom("cube").solref[0] = timeconst
    spec.geom("cube").priority = 1
    return spec.compile()


def _synthetic_tosses(model: mujoco.MjModel, count: int, frames: int, seed: int) -> list[Trajectory]:
    """Tosses simulated by a known model, sampled at 148 Hz: a sliding, tumbling landing each."""
    rng = np.random.default_rng(seed)
    seeds = []
    for i in range(count):
        quat = rng.normal(size=4)
        qpos = np.concatenate([[0.0, 0.0, rng.uniform(0.1, 0.16)], quat / np.linalg.norm(quat)])
        qvel = np.concatenate([rng.uniform(-1.5, 1.5, 2), [rng.uniform(-1.0, 0.0)], rng.uniform(-6, 6, 3)])
        time_s = np.arange(frames) / RATE_HZ
        seeds.append(
            Trajectory(time_s=time_s, qpos=np.tile(qpos, (frames, 1)), qvel=np.tile(qvel, (frames, 1)), name=f"toss{i}")
        )
    return sim.simulate(model, seeds)  # type: ignore[return-value]


@pytest.fixture(scope="module")
def synthetic() -> tuple[list[Trajectory], dict[str, float]]:
    truth = {"cube.friction.sliding": 0.45, "cube.solref.timeconst": 0.008}
    model = _true_cube(truth["cube.friction.sliding"], truth["cube.solref.timeconst"])
    return _synthetic_tosses(model, count=10, frames=60, seed=0), truth


def test_calibration_recovers_known_parameters(synthetic, tmp_path: Path) -> None:
    trajs, truth = synthetic
    options = CalibrateOptions(
        params=tuple(truth), popsize=5, generations=6, local_iterations=6, validation_fraction=0.3, nthread=2
    )
    out = tmp_path / "calibrated"
    result = calibrate(CUBE_XML, trajs, options=options, out=out)

    for name, true_value in truth.items():
        assert result.values[name] == pytest.approx(true_value, rel=0.05), (name, result.values)
        # The interval holds the value and the truth, and says something (measured: x0.73-1.37 of the value).
        lo, hi = result.intervals[name]
        assert lo < result.values[name] < hi and lo < true_value < hi and hi / lo < 4, (name, lo, hi)
    before, after = result.before["validation"], result.after["validation"]
    assert before.position_pct.mean() > 5.0  # the nominal cube (friction 0.18, timeconst 0.02) is visibly wrong
    # Contact makes the loss rough: 1-2% parameter error still leaves ~1% of the cube width.
    assert after.position_pct.mean() < min(2.5, 0.1 * before.position_pct.mean()), after.position_pct
    assert set(result.validation_names) | set(result.train_names) == {t.name for t in trajs}
    assert len(result.validation_names) == 3

    # The written scene is the calibrated model, with its report and record.
    reloaded = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    cube_geom = mujoco.mj_name2id(reloaded, mujoco.mjtObj.mjOBJ_GEOM, "cube")
    assert reloaded.geom_friction[cube_geom, 0] == pytest.approx(truth["cube.friction.sliding"], rel=0.05)
    np.testing.assert_allclose(reloaded.geom_solref, result.model.geom_solref, rtol=1e-5)
    record = json.loads((out / "calibration.json").read_text())
    assert set(record["parameters"]) == set(truth)
    assert record["split"]["validation"] == list(result.validation_names)
    assert record["errors"]["after"]["validation"]["position_pct_of_size"]["mean"] == pytest.approx(
        after.position_pct.mean()
    )
    report = (out / "report.html").read_text()
    assert report.count("data:image/png;base64,") >= 3 and "cube.friction.sliding" in report


def test_global_search_on_a_subset_then_refinement_on_all(synthetic) -> None:
    """The global search scores candidates on a seeded subset of the training tosses, the refinement on all of them:
    the known parameters are still recovered, and the record names the subset."""
    trajs, truth = synthetic
    options = CalibrateOptions(
        params=tuple(truth),
        popsize=5,
        generations=6,
        local_iterations=6,
        validation_fraction=0.3,
        nthread=2,
        global_search_trajectories=3,
    )
    result = calibrate(CUBE_XML, trajs, options=options)
    subset = result.extra["global_search_trajectories"]
    assert len(subset) == 3 and set(subset) < set(result.train_names), subset
    for name, true_value in truth.items():
        assert result.values[name] == pytest.approx(true_value, rel=0.05), (name, result.values)
    # Fewer rollouts than the whole training split throughout: 6 generations x 10 candidates x 4 tosses fewer.
    whole = calibrate(CUBE_XML, trajs, options=replace(options, global_search_trajectories=None))
    assert "global_search_trajectories" not in whole.extra
    assert result.evaluations < whole.evaluations - 6 * 10 * 4, (result.evaluations, whole.evaluations)


def test_a_copy_of_a_toss_is_named_and_kept_with_it(
    synthetic, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """One toss stored again, turned 90 deg about the vertical and moved: found, named in one warning line, kept on
    the side of the split its original is on, and listed in calibration.json and the report."""
    trajs, _ = synthetic
    src = trajs[0]
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    qpos, qvel = src.qpos.copy(), src.qvel.copy()
    qpos[:, :3] = src.qpos[:, :3] @ turn.T + np.array([0.3, -0.2, 0.0])
    qpos[:, 3:] = [_quat_mul(np.array([np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)]), q) for q in src.qpos[:, 3:]]
    qvel[:, :3] = src.qvel[:, :3] @ turn.T  # world-frame linear velocity turns; the body-frame rate does not
    copy = Trajectory(time_s=src.time_s, qpos=qpos, qvel=qvel, name="toss_copy")
    options = CalibrateOptions(params=("cube.friction.sliding",), generations=0, local_iterations=0, nthread=1)
    out = tmp_path / "calibrated"
    with caplog.at_level(logging.WARNING, logger="grounder.calibration.fit"):
        result = calibrate(CUBE_XML, [*trajs, copy], options=options, out=out)
    lines = [r.getMessage() for r in caplog.records if "record the same motion" in r.getMessage()]
    assert len(lines) == 1 and "toss0=toss_copy" in lines[0], lines
    side = result.validation_names if "toss0" in result.validation_names else result.train_names
    assert "toss_copy" in side
    assert json.loads((out / "calibration.json").read_text())["repeated_trajectories"] == [["toss0", "toss_copy"]]
    assert "toss0=toss_copy" in (out / "report.html").read_text()


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def test_joint_defaults_recover_a_small_damping(tmp_path: Path) -> None:
    """A 0.5 kg, 30 cm pendulum with damping 0.01 N m s/rad: 1% of the old fixed [0, 1] range, which the default
    search never reached (it settled on friction loss 0.046 instead, 20 x the true model's loss)."""
    from grounder.diagnosis.benchmark import select_cases
    from grounder.diagnosis.cases import make_case

    case = make_case(select_cases(["pendulum/joint_damping"])[0], 16, seed=0)
    scene = tmp_path / "pendulum.xml"
    scene.write_text(case.scene_xml)
    result = calibrate(scene, case.trajectories, options=CalibrateOptions(generations=8, local_iterations=4, nthread=2))
    assert set(result.values) == {"joint:hinge.damping", "joint:hinge.frictionloss", "joint:hinge.armature"}
    assert result.values["joint:hinge.damping"] == pytest.approx(0.01, rel=0.1), result.values
    assert result.values["joint:hinge.frictionloss"] < 0.004, result.values  # 10% of the damping torque at 1 rad/s
    assert result.after["validation"].loss.mean() < 0.1 * result.before["validation"].loss.mean()
    explicit = resolve_parameters(mujoco.MjModel.from_xml_path(str(scene)), ["joint:hinge.damping=0:0.5"])[0]
    assert (explicit.lower, explicit.upper, explicit.log_scale) == (0.0, 0.5, False)


def test_output_folder_must_be_new(synthetic, tmp_path: Path) -> None:
    trajs, _ = synthetic
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep.txt").write_text("mine")
    with pytest.raises(GrounderError, match="not empty"):
        calibrate(CUBE_XML, trajs, options=CalibrateOptions(generations=0, local_iterations=0), out=tmp_path / "taken")
    assert (tmp_path / "taken" / "keep.txt").read_text() == "mine"


def test_output_folder_filled_while_calibrating_keeps_the_result(
    synthetic, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A second run, or the user, writing into the output folder while calibrate works: that was an OSError
    traceback at the end. Now one error naming where the complete result is; the other writer's file is kept."""
    import grounder.calibration.report as report

    trajs, _ = synthetic
    out = tmp_path / "out"
    real_write_report = report.write_report

    def write_report_meanwhile(*args: object, **kwargs: object) -> None:
        real_write_report(*args, **kwargs)  # type: ignore[arg-type]
        out.mkdir()
        (out / "other.txt").write_text("written meanwhile")

    monkeypatch.setattr(report, "write_report", write_report_meanwhile)
    with pytest.raises(
        GrounderError, match=r"appeared while this run worked; it was left as it is.* kept, complete, in"
    ):
        calibrate(CUBE_XML, trajs[:2], options=CalibrateOptions(generations=0, local_iterations=0), out=out)
    assert (out / "other.txt").read_text() == "written meanwhile"
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("out.image2sim-")]
    assert len(kept) == 1 and (kept[0] / "scene.xml").is_file() and (kept[0] / "calibration.json").is_file()


def test_embedding_mode_needs_an_embedding(synthetic) -> None:
    trajs, _ = synthetic
    with pytest.raises(GrounderError, match="scene has no property embedding"):
        calibrate(CUBE_XML, trajs, options=CalibrateOptions(mode="embedding"))


@pytest.mark.parametrize(
    ("objects", "needle"),
    [
        ([1, 2], "'objects' is not a mapping"),
        ({"cube": {"properties": {"embedding": ["a", "b"]}}}, "non-numeric embedding"),
        ({"cube": {"density_kg_m3": "heavy", "properties": {"embedding": [0.0, 0.0]}}}, "non-numeric embedding"),
        ({"cube": {"properties": {"embedding": [0.0, float("nan")]}}}, r"properties\.embedding must be finite"),
        ({"cube": {"properties": {"embedding": [0.0, 0.0, 0.0]}}}, "does not fit this property model"),
        (
            {"cube": {"properties": {"embedding": [0.0, 0.0], "embedding_std": [0.5]}}},
            "malformed embedding / embedding_std",
        ),
        # Each of these decoded to NaN or overflowed in the search (NumPy warnings, then "z.shape=(16,) but expected
        # (16,) finite numbers", naming neither the file nor the field).
        (
            {"cube": {"properties": {"embedding": [0.0, 0.0], "embedding_std": [float("inf"), 0.2]}}},
            r"properties\.embedding_std must be finite numbers in \(0, 10\], got \[Infinity, 0\.2\]",
        ),
        (
            {"cube": {"properties": {"embedding": [1e300, 0.0], "embedding_std": [0.2, 0.2]}}},
            r"properties\.embedding must be finite numbers within \+-30, got \[1e\+300, 0\.0\]",
        ),
        (
            {"cube": {"properties": {"embedding": [0.0, 0.0], "embedding_std": [1e300, 0.2]}}},
            r"properties\.embedding_std must be finite numbers in \(0, 10\]",
        ),
        ({"cube": {"properties": {"embedding": [10**400, 0.0]}}}, "non-numeric embedding"),
        # the mass is rescaled by decoded / stored density: 1e-300 wrote mass="4.9e+302"
        (
            {"cube": {"density_kg_m3": 1e-300, "properties": {"embedding": [0.0, 0.0]}}},
            r"density_kg_m3 1e-300 is outside 0\.1-100000 kg/m\^3",
        ),
        (
            {"cube": {"density_kg_m3": 1e308, "properties": {"embedding": [0.0, 0.0]}}},
            r"density_kg_m3 1e\+308 is outside",
        ),
    ],
    ids=[
        "objects-list",
        "text-embedding",
        "text-density",
        "nan",
        "wrong-size",
        "std-shape",
        "infinite-std",
        "huge-embedding",
        "huge-std",
        "integer-overflow",
        "tiny-density",
        "huge-density",
    ],
)
def test_embedding_mode_malformed_scene_json_is_one_error(objects: object, needle: str, tmp_path: Path) -> None:
    """scene.json comes with the scene: each of these was a traceback (TypeError, AttributeError, ValueError) or an
    error naming neither the file nor the way out."""
    from grounder.calibration.embedding import embedding_space

    def decoder(z: np.ndarray) -> dict:  # a property model of embedding size 2
        if z.shape != (2,):
            raise GrounderError(f"z.shape={z.shape} but expected (2,)")
        return {"density_kg_m3": 500.0, "friction": [0.3, 0.005, 1e-4], "solref": [0.02, 1.0]}

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    (scene / "scene.json").write_text(json.dumps({"objects": objects}))
    with pytest.raises(GrounderError, match=rf"scene\.json.*{needle}.*re-run `image2sim ground`"):
        embedding_space(scene, mujoco.MjModel.from_xml_path(str(CUBE_XML)), decoder)


def test_embedding_mode_recovers_a_known_embedding(synthetic, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a stand-in decoder (z -> friction, timeconst), the posterior embedding explains the synthetic tosses."""
    import grounder.calibration.embedding as emb

    def decoder(z: np.ndarray) -> dict:
        return {
            "density_kg_m3": 500.0,
            "friction": [0.3 * np.exp(z[0]), 0.005, 1e-4],
            "solref": [0.02 * np.exp(z[1]), 1.0],
        }

    monkeypatch.setattr(emb, "embedding_decoder", lambda: decoder)
    trajs, truth = synthetic
    z_true = np.log([truth["cube.friction.sliding"] / 0.3, truth["cube.solref.timeconst"] / 0.02])
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    entry = {"density_kg_m3": 500.0, "properties": {"embedding": [0.0, 0.0], "embedding_std": [0.6, 0.6]}}
    (scene / "scene.json").write_text(json.dumps({"objects": {"cube": entry}}))
    options = CalibrateOptions(mode="embedding", popsize=5, generations=6, local_iterations=4, nthread=2)
    result = calibrate(scene, trajs, options=options, out=tmp_path / "out")
    posterior = np.array(result.extra["embedding"]["cube"]["posterior_embedding"])
    assert posterior[0] == pytest.approx(z_true[0], abs=0.08)  # friction is well determined by sliding tosses
    assert result.values["cube.friction.sliding"] == pytest.approx(truth["cube.friction.sliding"], rel=0.08)
    # The time constant much less so (the search budget leaves it ~30% off): its posterior interval holds the truth.
    lo, hi = result.intervals["cube.solref.timeconst"]
    assert lo <= truth["cube.solref.timeconst"] <= hi and hi / lo < 4
    assert result.values["cube.mass"] == pytest.approx(0.37)  # the decoded density equals the scene's
    lo, hi = result.intervals["cube.friction.sliding"]
    assert lo <= result.values["cube.friction.sliding"] <= hi
    assert result.after["validation"].position_pct.mean() < 0.1 * result.before["validation"].position_pct.mean()
    record = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert record["mode"] == "embedding" and "posterior_embedding_std" in record["embedding"]["cube"]


def test_embedding_mode_distribution_narrows_the_prior(
    synthetic, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--distribution`` in embedding mode: the population starts as the property model's prior N(0, I) and the
    fit narrows it where the tosses say something; the file's decoded Gaussian drives ``randomize``."""
    import grounder.calibration.embedding as emb
    from grounder.calibration.distribution import read_distribution
    from grounder.calibration.randomize import write_randomized_variants

    def decoder(z: np.ndarray) -> dict:
        return {"density_kg_m3": 500.0, "friction": [0.3 * np.exp(z[0]), 0.005, 1e-4], "solref": [0.02, 1.0]}

    monkeypatch.setattr(emb, "embedding_decoder", lambda: decoder)
    trajs, truth = synthetic
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    entry = {"density_kg_m3": 500.0, "properties": {"embedding": [0.0, 0.0], "embedding_std": [0.6, 0.6]}}
    (scene / "scene.json").write_text(json.dumps({"objects": {"cube": entry}}))
    options = CalibrateOptions(
        mode="embedding",
        popsize=4,
        generations=2,
        local_iterations=2,
        distribution=True,
        distribution_samples=24,
        distribution_iterations=2,
    )
    calibrate(scene, trajs[:8], options=options, out=tmp_path / "out")
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "out" / "scene.xml"))
    dist = read_distribution(tmp_path / "out" / "distribution.json", model.nv)
    assert dist.mode == "embedding" and dist.embedding is not None
    cov = np.array(dist.embedding["cov"])
    assert cov[0, 0] < 0.25  # friction's coordinate, which the sliding tosses pin down: far narrower than the prior
    params = dist.parameters(model)
    drawn = dist.draw_values(params, 2000, np.random.default_rng(0))
    sliding = next(i for i, p in enumerate(params) if p.name == "cube.friction.sliding")
    assert np.median(drawn[:, sliding]) == pytest.approx(truth["cube.friction.sliding"], rel=0.15)
    paths = write_randomized_variants(tmp_path / "out", tmp_path / "dr", 3, seed=1)
    assert len(paths) == 3 and all(mujoco.MjModel.from_xml_path(str(p)).nbody == model.nbody for p in paths)


def test_scene_folder_with_assets(tmp_path: Path, synthetic) -> None:
    """A scene folder is copied with its other files; the calibrated MJCF keeps relative asset paths."""
    trajs, _ = synthetic
    scene = tmp_path / "scene"
    (scene / "assets").mkdir(parents=True)
    (scene / "assets" / "note.txt").write_text("asset")
    (scene / "assets" / "report.html").write_text("an asset that shares a name with calibrate's own report")
    (scene / "scene.json").write_text("{}")
    (scene / "residual.json").write_text("{}")  # trained against the uncalibrated model: not carried over
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    result = calibrate(
        scene,
        trajs[:4],
        options=CalibrateOptions(params=("cube.friction.sliding",), generations=1, popsize=2, local_iterations=0),
        out=tmp_path / "out",
    )
    assert (tmp_path / "out" / "assets" / "note.txt").read_text() == "asset"
    assert (tmp_path / "out" / "assets" / "report.html").read_text().startswith("an asset")  # only top-level skips
    manifest = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert set(manifest["calibration"]["parameters"]) == {"cube.friction.sliding"}
    assert not (tmp_path / "out" / "residual.json").exists()
    assert result.out_dir == tmp_path / "out"


# ------------------------------------------------------------------------------------------------ CLI


def _cli(*args: str):
    from grounder.cli import app

    return CliRunner().invoke(app, list(args))


def _assert_exit_2(result, needle: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("image2sim: error:")]
    assert len(lines) == 1 and needle in lines[0], result.output
    assert "Traceback" not in result.output


@pytest.fixture(scope="module")
def traj_dir(synthetic, tmp_path_factory) -> Path:
    trajs, _ = synthetic
    return save_trajectories(trajs[:3], tmp_path_factory.mktemp("data") / "trajs")


def test_cli_unknown_parameter(traj_dir: Path, tmp_path: Path) -> None:
    _assert_exit_2(
        _cli("calibrate", str(CUBE_XML), str(traj_dir), "-o", str(tmp_path / "o"), "--params", "cube.colour"),
        "unknown parameter 'cube.colour'",
    )
    assert not (tmp_path / "o").exists()


def test_cli_trajectory_does_not_match_model(traj_dir: Path, tmp_path: Path) -> None:
    xml = tmp_path / "two.xml"
    xml.write_text(MULTI_XML)
    _assert_exit_2(_cli("calibrate", str(xml), str(traj_dir), "-o", str(tmp_path / "o")), "does not fit the model")


def test_cli_empty_directory(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    _assert_exit_2(_cli("calibrate", str(CUBE_XML), str(tmp_path / "empty"), "-o", str(tmp_path / "o")), "no .npz")
    _assert_exit_2(_cli("rollout", str(CUBE_XML), str(tmp_path / "empty"), "-o", str(tmp_path / "p")), "no .npz")


def test_cli_missing_scene(traj_dir: Path, tmp_path: Path) -> None:
    _assert_exit_2(
        _cli("calibrate", str(tmp_path / "nope.xml"), str(traj_dir), "-o", str(tmp_path / "o")), "does not exist"
    )


def test_cli_calibrate_runs(traj_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "cal"
    result = _cli(
        "calibrate", str(CUBE_XML), str(traj_dir), "-o", str(out),
        "--params", "cube.friction.sliding,cube.solref.timeconst", "--generations", "1", "--popsize", "2",
        "--local-iterations", "0",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "cube.friction.sliding" in result.output and (out / "calibration.json").is_file()


def test_cli_rollout_matches_simulate(traj_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "pred"
    result = _cli("rollout", str(CUBE_XML), str(traj_dir), "-o", str(out), "--no-residual")
    assert result.exit_code == 0, result.output
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    real = load_trajectories(traj_dir, model)
    preds = load_trajectories(out, model)
    assert [p.name for p in preds] == [t.name for t in real]
    expected = sim.simulate(model, real)
    for p, e in zip(preds, expected, strict=True):
        np.testing.assert_allclose(p.qpos, e.qpos)  # type: ignore[union-attr]
        np.testing.assert_allclose(p.time_s, e.time_s)  # type: ignore[union-attr]


STIFF_SPRING_XML = """<mujoco><option timestep="0.01"/><worldbody><body>
<joint name="s" type="slide" axis="1 0 0" stiffness="1e6"/><geom type="sphere" size="0.05" mass="1"/>
</body></worldbody></mujoco>"""


def test_rollout_that_mujoco_stops_as_unstable_is_refused(traj_dir: Path, tmp_path: Path) -> None:
    """A spring too stiff for the scene's timestep (dt sqrt(k/m) = 10, explicit in MuJoCo's Euler) grows x100
    per step until MuJoCo stops the rollout and repeats its last state. `image2sim rollout` then names the
    trajectory and when, in one line, exit 2, writes nothing, and MuJoCo's own warning does not reach the output.
    Calibration keeps such a rollout (a candidate that goes unstable only scores badly)."""
    scene = tmp_path / "spring.xml"
    scene.write_text(STIFF_SPRING_XML)
    model = mujoco.MjModel.from_xml_path(str(scene))
    time_s = np.arange(20) / 100.0
    still = Trajectory(time_s=time_s, qpos=np.zeros((20, 1)), qvel=np.zeros((20, 1)), name="still")
    pulled = Trajectory(time_s=time_s, qpos=np.full((20, 1), 0.01), qvel=np.zeros((20, 1)), name="pulled")
    data = save_trajectories([still, pulled], tmp_path / "trajs")
    out = tmp_path / "pred"
    result = _cli("rollout", str(scene), str(data), "-o", str(out))
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("image2sim: error: trajectory pulled: the simulation became unstable 0.04 s after")
    assert "in QACC at DOF 0" in lines[0] and "lower the scene's timestep (0.01 s)" in lines[0], lines[0]
    assert "WARNING" not in result.output and not out.exists()
    with pytest.raises(GrounderError, match="trajectory pulled: the simulation became unstable"):
        sim.simulate(model, [still, pulled], stable=True)
    kept = sim.simulate(model, [still, pulled])  # calibration's call: the stopped rollout repeats its last state
    assert isinstance(kept[1], Trajectory) and np.all(kept[1].qpos[5:] == kept[1].qpos[5])
    cube = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    real = load_trajectories(traj_dir, cube)
    for p, e in zip(sim.simulate(cube, real, stable=True), sim.simulate(cube, real), strict=True):
        np.testing.assert_array_equal(p.qpos, e.qpos)  # type: ignore[union-attr]  # usual rollouts pass unchanged


def test_cli_rollout_refuses_a_state_beyond_what_mujoco_simulates(traj_dir: Path, tmp_path: Path) -> None:
    """A finite but absurd value (1e200 m/s, as a corrupt or hostile file may hold) is refused when the file is
    read, naming the file and the entry, before any simulation (MuJoCo's own limit is 1e10)."""
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    real = load_trajectories(traj_dir, model)
    files = save_trajectories(real, tmp_path / "trajs")
    name = sorted(files.glob("*.npz"))[1]
    with np.load(name) as f:
        arrays = dict(f)
    arrays["qvel"][0, 2] = -1e200
    np.savez(name, **arrays)
    result = _cli("rollout", str(CUBE_XML), str(files), "-o", str(tmp_path / "pred"))
    _assert_exit_2(result, f"{name.name}: 'qvel[0, 2]' is -1e+200, beyond the 1e+10 MuJoCo can simulate")
    assert not (tmp_path / "pred").exists()
    with pytest.raises(GrounderError, match=r"'qvel\[3, 0\]' is 2e\+10"):
        Trajectory(time_s=np.arange(4.0), qpos=np.zeros((4, 1)), qvel=np.array([[0.0], [0], [0], [2e10]]))


def test_cli_rollout_uses_the_residual_when_the_scene_has_one(
    traj_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import grounder.residual.simulator as simulator

    calls: list[str] = []

    class FakeSimulator:
        def __init__(self, scene: Path, *, use_residual: bool = True) -> None:
            calls.append(str(scene))
            self.model = mujoco.MjModel.from_xml_path(str(CUBE_XML))

        def rollout(self, trajs: list[Trajectory], *, stable: bool = False) -> list[Trajectory]:
            return sim.simulate(self.model, trajs, stable=stable)  # type: ignore[return-value]

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    monkeypatch.setattr(simulator, "has_residual", lambda scene_dir: Path(scene_dir) == scene)
    monkeypatch.setattr(simulator, "Simulator", FakeSimulator)
    result = _cli("rollout", str(scene), str(traj_dir), "-o", str(tmp_path / "a"))
    assert result.exit_code == 0 and "MuJoCo + residual" in result.output and calls == [str(scene)], result.output
    result = _cli("rollout", str(scene), str(traj_dir), "-o", str(tmp_path / "b"), "--no-residual")
    assert result.exit_code == 0 and "MuJoCo + residual" not in result.output and len(calls) == 1, result.output


@pytest.mark.parametrize("command", ["calibrate", "rollout", "import-trajectories", "batch"])
def test_cli_help(command: str) -> None:
    result = _cli(command, "--help")
    assert result.exit_code == 0 and "Usage" in result.output, result.output


@pytest.mark.parametrize(
    ("command", "flags"),
    [
        (["rollout"], []),
        (["rollout"], ["--overwrite"]),
        (["diagnose"], ["--overwrite"]),
        (["residual", "train"], ["--overwrite"]),
    ],
)
def test_cli_output_over_the_trajectories_is_refused(
    command: list[str], flags: list[str], traj_dir: Path, tmp_path: Path
) -> None:
    """-o naming the trajectory folder (or a folder above it) would replace the recording: refused, nothing touched."""
    import shutil

    mine = shutil.copytree(traj_dir, tmp_path / "rec" / "trajs")
    before = {p.name: p.read_bytes() for p in mine.iterdir()}
    for out in (mine, mine.parent):
        _assert_exit_2(
            _cli(*command, str(CUBE_XML), str(mine), "-o", str(out), *flags), "choose an output folder outside"
        )
        assert {p.name: p.read_bytes() for p in mine.iterdir()} == before


@pytest.mark.parametrize("command", ["calibrate", "import-trajectories"])
def test_cli_non_empty_output_suggests_no_missing_flag(command: str, traj_dir: Path, tmp_path: Path) -> None:
    """These commands have no --overwrite, so their error must not suggest one."""
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "mine.txt").write_text("mine")
    args = [str(CUBE_XML), str(traj_dir)] if command == "calibrate" else [str(traj_dir)]
    result = _cli(command, *args, "-o", str(tmp_path / "taken"))
    _assert_exit_2(result, "not empty")
    assert "--overwrite" not in result.output
    assert (tmp_path / "taken" / "mine.txt").read_text() == "mine"


# ------------------------------------------------------------------------------------------------ self-contained scenes


def _mesh_cube_xml(mesh_file: str, extra: str = "") -> str:
    """The nominal cube with its box as a mesh read from `mesh_file` (and `extra` MJCF before the world body)."""
    text = CUBE_XML.read_text()
    text = text.replace(
        '<geom name="cube" type="box" size="0.0524 0.0524 0.0524"', '<geom name="cube" type="mesh" mesh="cube_mesh"'
    )
    return text.replace("<worldbody>", f'{extra}<asset><mesh name="cube_mesh" file="{mesh_file}"/></asset><worldbody>')


def _write_cube_obj(path: Path) -> Path:
    import trimesh

    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=[0.1048] * 3).export(path)
    return path


@pytest.mark.parametrize("escape", ["mesh", "absolute mesh", "include", "linked mesh"])
@pytest.mark.parametrize(
    ("command", "flags"),
    [
        (["calibrate"], ["--generations", "0", "--local-iterations", "0"]),
        (["rollout"], []),
        (["residual", "train"], []),
    ],
)
def test_cli_scene_reaching_outside_its_folder_is_refused(
    escape: str, command: list[str], flags: list[str], traj_dir: Path, tmp_path: Path
) -> None:
    """A scene is someone else's file: what it names outside its folder is neither read nor written. Before, a lone
    MJCF naming `../../cube.obj` was loaded, and calibrate copied that mesh to `../../cube.obj` of its output's
    staging folder: over the user's own file of that name, beside the output."""
    work = tmp_path / "work"
    precious = work / "cube.obj"
    precious.parent.mkdir(parents=True)
    precious.write_text("the user's own file\n")
    scene_dir = tmp_path / "downloads" / "a" / "b"
    scene_dir.mkdir(parents=True)
    _write_cube_obj(tmp_path / "downloads" / "cube.obj")
    if escape == "mesh":
        xml = _mesh_cube_xml("../../cube.obj")
    elif escape == "absolute mesh":
        xml = _mesh_cube_xml(str(tmp_path / "downloads" / "cube.obj"))
    elif escape == "include":
        (tmp_path / "downloads" / "a" / "inc.xml").write_text("<mujoco><option timestep='0.001'/></mujoco>")
        xml = CUBE_XML.read_text().replace("<worldbody>", '<include file="../inc.xml"/><worldbody>')
    else:  # a link inside the folder that resolves outside it
        (scene_dir / "assets").symlink_to(tmp_path / "downloads")
        xml = _mesh_cube_xml("assets/cube.obj")
    (scene_dir / "scene.xml").write_text(xml)
    out = work / "x" / "out"
    result = _cli(*command, str(scene_dir / "scene.xml"), str(traj_dir), "-o", str(out), *flags)
    _assert_exit_2(result, "outside the scene's folder")
    assert precious.read_text() == "the user's own file\n"
    assert sorted(p.name for p in work.iterdir()) == ["cube.obj"]


def test_lone_mjcf_output_carries_what_it_loads_and_nothing_else(synthetic, tmp_path: Path) -> None:
    """Calibrating a lone MJCF copies its mesh (at the same relative path) and not the rest of its folder; a scene
    folder's links are copied as links, not as the files they point to; an output inside the scene folder does not
    copy itself into itself."""
    trajs, _ = synthetic
    options = CalibrateOptions(params=("cube.friction.sliding",), generations=0, popsize=2, local_iterations=0)
    lone = tmp_path / "desk"
    _write_cube_obj(lone / "meshes" / "cube.obj")
    (lone / "private.txt").write_text("not part of the scene")
    (lone / "cube_mesh.xml").write_text(_mesh_cube_xml("meshes/cube.obj"))
    calibrate(lone / "cube_mesh.xml", trajs[:2], options=options, out=tmp_path / "from_lone")
    written = sorted(str(p.relative_to(tmp_path / "from_lone")) for p in (tmp_path / "from_lone").rglob("*"))
    assert written == ["calibration.json", "meshes", "meshes/cube.obj", "report.html", "scene.xml"], written
    assert mujoco.MjModel.from_xml_path(str(tmp_path / "from_lone" / "scene.xml")).nmesh == 1

    folder = tmp_path / "scene"
    _write_cube_obj(folder / "assets" / "cube.obj")
    (folder / "scene.xml").write_text(_mesh_cube_xml("assets/cube.obj"))
    (folder / "docs").mkdir()
    (folder / "docs" / "notes.txt").write_text("inside")
    (folder / "notes.txt").symlink_to(Path("docs") / "notes.txt")  # a link out of the folder is refused
    calibrate(folder, trajs[:2], options=options, out=folder / "calibrated")
    out = folder / "calibrated"
    assert (out / "notes.txt").is_symlink() and (out / "assets" / "cube.obj").is_file()
    assert not any(p.name.endswith(".tmp") or p.name == "calibrated" for p in out.rglob("*")), list(out.rglob("*"))


@pytest.mark.parametrize("target", ["full folder", "empty folder", "nothing"])
@pytest.mark.parametrize(
    ("command", "flags"),
    [
        (["calibrate"], ["--generations", "0", "--local-iterations", "0"]),
        (["rollout"], ["--overwrite"]),
        (["import-trajectories"], []),
        (["residual", "train"], ["--overwrite"]),
    ],
)
def test_cli_output_that_is_a_link_is_refused(
    target: str, command: list[str], flags: list[str], traj_dir: Path, tmp_path: Path
) -> None:
    """-o naming a symbolic link: replacing the output would replace the user's link (or write through it into the
    folder it points to, file by file). Before: tracebacks (rmdir or rename on a link), a half-made hidden folder
    beside a dangling link, or the link's folder rewritten. Now one line, exit 2, the link and
    its folder as they were."""
    pointed = tmp_path / "mine"
    if target != "nothing":
        pointed.mkdir()
    if target == "full folder":
        (pointed / "0.npz").write_text("the user's file")
    link = tmp_path / "link"
    link.symlink_to(pointed)
    args = [str(traj_dir)] if command == ["import-trajectories"] else [str(CUBE_XML), str(traj_dir)]
    _assert_exit_2(_cli(*command, *args, "-o", str(link), *flags), "is a symbolic link")
    assert link.is_symlink() and link.readlink() == pointed
    if target == "full folder":
        assert [p.name for p in pointed.iterdir()] == ["0.npz"] and (pointed / "0.npz").read_text() == "the user's file"
    elif target == "empty folder":
        assert not any(pointed.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["link", *(["mine"] if target != "nothing" else [])])


def test_cli_rollout_overwrite_replaces_the_whole_folder(traj_dir: Path, tmp_path: Path) -> None:
    """--overwrite replaces an earlier rollout (its rollout.json marks it) as one, like every command: no stale file
    of the earlier run is left among the new predictions. A folder that is no image2sim output is not replaced: a
    mistyped -o with --overwrite deleted the user's files."""
    out = tmp_path / "pred"
    out.mkdir()
    (out / "mine.txt").write_text("the user's")
    result = _cli("rollout", str(CUBE_XML), str(traj_dir), "-o", str(out), "--overwrite", "--no-residual")
    _assert_exit_2(result, "is not an image2sim output (it holds none of reconstruct.json")
    assert [p.name for p in out.iterdir()] == ["mine.txt"]
    (out / "mine.txt").unlink()
    assert _cli("rollout", str(CUBE_XML), str(traj_dir), "-o", str(out), "--no-residual").exit_code == 0
    record = json.loads((out / "rollout.json").read_text())
    assert record["residual"] is False and record["files"] == sorted(p.name for p in traj_dir.iterdir())
    (out / "stale.npz").write_text("from an earlier run")
    result = _cli("rollout", str(CUBE_XML), str(traj_dir), "-o", str(out), "--overwrite", "--no-residual")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == sorted([*(p.name for p in traj_dir.iterdir()), "rollout.json"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pred"]


@pytest.mark.parametrize(("command", "flags"), [(["rollout"], ["--no-residual"]), (["residual", "train"], [])])
def test_cli_overwrite_of_a_folder_inside_the_scene_is_refused(
    command: list[str], flags: list[str], traj_dir: Path, tmp_path: Path
) -> None:
    """-o scene/assets --overwrite used to replace the scene's meshes with the output (exit 0; the scene then no
    longer loaded). A folder inside an input is replaced only when it is an image2sim output."""
    from reconstruction import check_output_dir

    scene = tmp_path / "scene"
    _write_cube_obj(scene / "assets" / "cube.obj")
    (scene / "scene.xml").write_text(_mesh_cube_xml("assets/cube.obj"))
    before = (scene / "assets" / "cube.obj").read_bytes()
    result = _cli(*command, str(scene), str(traj_dir), "-o", str(scene / "assets"), "--overwrite", *flags)
    _assert_exit_2(result, "lies inside the input")
    assert [p.name for p in (scene / "assets").iterdir()] == ["cube.obj"]
    assert (scene / "assets" / "cube.obj").read_bytes() == before
    # An earlier output of the tool inside the input folder may be replaced.
    (scene / "calibrated").mkdir()
    (scene / "calibrated" / "calibration.json").write_text("{}")
    check_output_dir(scene / "calibrated", overwrite=True, inputs=(scene,), error=InputError)


# ----------------------------------------------------------------------------------------------- options, scene.json


@pytest.mark.parametrize(
    ("settings", "needle"),
    [
        # A NaN weight made every loss NaN, hence 1e6, hence every candidate equal: "success" at the nominal values.
        (
            {"rotation_weight": float("nan")},
            "rotation_weight must be a number in [0, 100] (percent of size per degree), got NaN",
        ),
        ({"rotation_weight": float("inf")}, "rotation_weight must be a number in [0, 100]"),
        ({"rotation_weight": -1.0}, "rotation_weight must be a number in [0, 100]"),
        (
            {"rotation_weight": "1"},
            'rotation_weight must be a number in [0, 100] (percent of size per degree), got "1"',
        ),
        ({"generations": 2.5}, "generations must be an integer >= 0, got 2.5"),
        ({"generations": True}, "generations must be an integer >= 0, got true"),
        ({"popsize": 0}, "popsize must be an integer in [1, 1000], got 0"),
        ({"local_iterations": "3"}, "local_iterations must be an integer >= 0"),
        ({"seed": -1}, "seed must be an integer in [0, 4294967295]"),
        ({"split_seed": 1.0}, "split_seed must be an integer in [0, 4294967295]"),
        ({"nthread": 0}, "nthread must be an integer in [1, 256] or null"),
        ({"nthread": 100_000}, "nthread must be an integer in [1, 256] or null"),  # hung a batch job
        ({"max_train_trajectories": 0}, "max_train_trajectories must be an integer >= 1 or null"),
        # huge values: scipy's seed and popsize overflowed (tracebacks), a weight of 1e300 fitted overflowing costs
        ({"seed": 2**32}, "seed must be an integer in [0, 4294967295], got 4294967296"),
        ({"popsize": 10**20}, "popsize must be an integer in [1, 1000]"),
        ({"rotation_weight": 1e300}, "rotation_weight must be a number in [0, 100] (percent of size per degree)"),
        ({"params": "cube.friction.sliding"}, "params must be a list of parameter names"),
        ({"params": ("cube.friction.sliding", 3)}, "params must be a list of parameter names"),
        ({"validation_fraction": float("nan")}, "validation_fraction must be a number in [0, 1), got NaN"),
        ({"along_view_weight": float("nan")}, "along_view_weight must be a number in (0, 1]"),
        ({"view_point_m": (0.0, float("nan"), 1.0)}, "view_point_m must be 3 finite numbers"),
        ({"view_point_m": (0.0, 1.0)}, "view_point_m must be 3 finite numbers"),
        ({"fd_step": 0.0}, "fd_step must be a number in (0, 1)"),
        ({"interval_level": float("nan")}, "interval_level must be a number in (0, 1)"),
        ({"max_batch_mb": float("nan")}, "max_batch_mb must be a finite number > 0 (MiB), got NaN"),
        ({"max_batch_mb": float("inf")}, "max_batch_mb must be a finite number > 0"),
        ({"robust_scale": float("inf")}, "robust_scale must be a finite number > 0 or null, got Infinity"),
        ({"initial": {"cube.friction.sliding": float("nan")}}, "initial must be a mapping of parameter names"),
        ({"separate_bodies": "no"}, 'separate_bodies must be true or false, got "no"'),
        ({"mode": "fast"}, "mode must be 'raw' or 'embedding', got \"fast\""),
    ],
    ids=lambda v: "-".join(v) if isinstance(v, dict) else "",
)
def test_options_are_checked(settings: dict, needle: str) -> None:
    """Each field of `CalibrateOptions` is checked for type and range: one line naming it, the value and what is
    expected, whether it came from Python or a batch file's settings."""
    from grounder.calibration.batch_jobs import options_from_settings

    with pytest.raises(GrounderError) as caught:
        CalibrateOptions(**settings)
    assert str(caught.value).startswith(f"calibrate option {needle}"), str(caught.value)
    assert "\n" not in str(caught.value)
    if not isinstance(settings.get("params"), str):  # a batch file's text params are comma-separated names
        with pytest.raises(GrounderError, match="calibrate option"):
            options_from_settings({k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()})


def test_valid_options_are_kept() -> None:
    """NumPy numbers and lists are accepted and stored as plain Python values (calibration.json writes them)."""
    default = CalibrateOptions()
    assert (default.rotation_weight, default.generations, default.params, default.nthread) == (0.0, 20, (), None)
    options = CalibrateOptions(
        params=["cube.friction.sliding"],  # type: ignore[arg-type]
        generations=np.int64(3),  # type: ignore[arg-type]
        rotation_weight=np.float64(0.5),
        view_point_m=np.array([0.0, -1.0, 0.5]),  # type: ignore[arg-type]
        initial={"cube.friction.sliding": np.float64(0.3)},
        robust_scale=1,
        nthread=2,
    )
    assert options.params == ("cube.friction.sliding",) and options.generations == 3
    assert options.view_point_m == (0.0, -1.0, 0.5) and type(options.view_point_m[0]) is float
    assert options.initial == {"cube.friction.sliding": 0.3}
    json.dumps({k: (list(v) if isinstance(v, tuple) else v) for k, v in options.__dict__.items() if k != "generations"})


def test_cli_nan_rotation_weight_is_refused(traj_dir: Path, tmp_path: Path) -> None:
    """`--rotation-weight nan` ran a calibration that fitted nothing and exited 0."""
    result = _cli(
        "calibrate", str(CUBE_XML), str(traj_dir), "-o", str(tmp_path / "o"),
        "--params", "cube.friction.sliding", "--rotation-weight", "nan",
        "--generations", "0", "--local-iterations", "0",
    )  # fmt: skip
    _assert_exit_2(result, "--rotation-weight must be a number in [0, 100]")  # the flag, not the Python field
    assert "got NaN" in result.output
    assert not (tmp_path / "o").exists()
    result = _cli(
        "calibrate", str(CUBE_XML), str(traj_dir), "-o", str(tmp_path / "o"), "--max-train", "0",
    )  # fmt: skip
    _assert_exit_2(result, "--max-train must be an integer >= 1, got 0")  # not "max_train_trajectories ... or null"


def test_note_replaces_a_linked_scene_json(tmp_path: Path) -> None:
    """The calibration note replaces the output's scene.json; it used to be written through a copied link, into the
    file the link points at (the user's own, outside the output folder)."""
    from grounder.calibration.scene_output import _note_in_manifest

    outside = tmp_path / "victim.json"
    outside.write_text('{"objects": {}, "note": "the user\'s own file"}')
    before = outside.read_bytes()
    stage = tmp_path / "out"
    stage.mkdir()
    (stage / "scene.json").symlink_to(outside)
    result = SimpleNamespace(mode="raw", values={"cube.friction.sliding": 0.4})
    _note_in_manifest(stage / "scene.json", result)  # type: ignore[arg-type]
    assert outside.read_bytes() == before
    assert not (stage / "scene.json").is_symlink() and (stage / "scene.json").is_file()
    manifest = json.loads((stage / "scene.json").read_text())
    assert manifest["note"] == "the user's own file"
    assert manifest["calibration"]["parameters"] == {"cube.friction.sliding": 0.4}
    assert sorted(p.name for p in stage.iterdir()) == ["scene.json"]  # no temporary file left


def test_calibrate_replaces_a_linked_scene_json(synthetic, tmp_path: Path) -> None:
    """A scene folder whose scene.json is a link (inside the folder): the output's scene.json is a file of its own
    with the note; the link's target, in the scene and in its copy, is left as it was."""
    trajs, _ = synthetic
    scene = tmp_path / "scene"
    (scene / "meta").mkdir(parents=True)
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    (scene / "meta" / "manifest.json").write_text('{"objects": {}}\n')
    (scene / "scene.json").symlink_to(Path("meta") / "manifest.json")
    before = (scene / "meta" / "manifest.json").read_bytes()
    options = CalibrateOptions(params=("cube.friction.sliding",), generations=0, local_iterations=0)
    out = tmp_path / "out"
    calibrate(scene, trajs[:2], options=options, out=out)
    assert (scene / "meta" / "manifest.json").read_bytes() == before
    assert (out / "meta" / "manifest.json").read_bytes() == before
    assert (out / "scene.json").is_file() and not (out / "scene.json").is_symlink()
    assert set(json.loads((out / "scene.json").read_text())["calibration"]["parameters"]) == {"cube.friction.sliding"}


def test_scene_json_linking_out_of_the_folder_is_refused_before_the_work(synthetic, tmp_path: Path) -> None:
    """A scene.json that links to a file of the user's outside the scene folder: calibrate copied the link and then
    wrote its note through it into that file. Now the link is refused before the first step; the file is untouched."""
    trajs, _ = synthetic
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    (tmp_path / "users.json").write_text('{"objects": {}}\n')
    (scene / "scene.json").symlink_to(tmp_path / "users.json")
    steps: list[str] = []
    options = CalibrateOptions(params=("cube.friction.sliding",), generations=0, local_iterations=0)
    with pytest.raises(GrounderError, match=r"scene\.json: a link to .*users\.json, which its copy would follow out"):
        calibrate(scene, trajs[:2], options=options, out=tmp_path / "out", progress=lambda s, _d, _t: steps.append(s))
    assert steps == [] and not (tmp_path / "out").exists()
    assert (tmp_path / "users.json").read_text() == '{"objects": {}}\n'


def test_deeply_nested_scene_json_is_refused_before_the_work(synthetic, tmp_path: Path) -> None:
    """A scene.json nested deeper than Python's JSON parser allows raised RecursionError (a traceback), and only
    once the whole calibration had run; now one error before the first step, in raw and embedding mode."""
    from grounder.calibration.embedding import embedding_space

    trajs, _ = synthetic
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    (scene / "scene.json").write_text("[" * 100_000)
    steps: list[str] = []
    options = CalibrateOptions(params=("cube.friction.sliding",), generations=0, local_iterations=0)
    with pytest.raises(GrounderError, match=r"scene\.json: JSON nested too deeply"):
        calibrate(scene, trajs[:2], options=options, out=tmp_path / "out", progress=lambda s, _d, _t: steps.append(s))
    assert steps == [] and not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]
    with pytest.raises(GrounderError, match=r"nested too deeply.*re-run `image2sim ground`"):
        embedding_space(scene, mujoco.MjModel.from_xml_path(str(CUBE_XML)))
    (scene / "scene.json").write_text("{not json")
    with pytest.raises(GrounderError, match=r"scene\.json: not valid JSON \(Expecting"):
        calibrate(scene, trajs[:2], options=options, out=tmp_path / "out")
    # Python's json keeps the last of a repeated key: which the writer meant cannot be told, so it is refused.
    (scene / "scene.json").write_text('{"objects": {"cube": {"density_kg_m3": 500}}, "objects": {}}')
    with pytest.raises(GrounderError, match=r'scene\.json: key "objects" appears twice in one object; restore it'):
        calibrate(scene, trajs[:2], options=options, out=tmp_path / "out")
    with pytest.raises(GrounderError, match=r'key "objects" appears twice.*re-run `image2sim ground`'):
        embedding_space(scene, mujoco.MjModel.from_xml_path(str(CUBE_XML)))
    assert steps == [] and not (tmp_path / "out").exists()
    calibrate(scene, trajs[:2], options=options)  # no output folder: scene.json is not read


def test_cli_embedding_mode_infinite_std_is_one_line(traj_dir: Path, tmp_path: Path) -> None:
    """An infinite embedding_std printed NumPy warnings, then an error naming neither scene.json nor the field."""
    import warnings

    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "scene.xml").write_text(CUBE_XML.read_text())
    entry = {
        "density_kg_m3": 500.0,
        "properties": {"embedding": [0.1] * 16, "embedding_std": [float("inf")] + [0.2] * 15},
    }
    (scene / "scene.json").write_text(json.dumps({"objects": {"cube": entry}}))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        result = _cli(
            "calibrate", str(scene), str(traj_dir), "-o", str(tmp_path / "o"), "--mode", "embedding",
            "--generations", "1", "--popsize", "1", "--local-iterations", "0",
        )  # fmt: skip
    _assert_exit_2(result, 'scene.json: object "cube": properties.embedding_std must be finite numbers in (0, 10]')
    assert "re-run `image2sim ground`" in result.output and "Warning" not in result.output
