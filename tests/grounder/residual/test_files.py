"""A residual scene folder is untrusted input: a corrupt or hostile ``residual.json`` / ``residual.pt``, or a
``scene.xml`` edited since training, ends in one error line naming the file and the fix (exit code 2 from the CLI),
never a traceback, torch's advice to load unsafely, a crash deep inside MuJoCo or a silently wrong simulation.

The folders are written directly (a tiny untrained network, 2 coverage centres), not trained: these tests are
about loading. One test trains, as little as possible, to check that retraining on an edited scene still works.
"""

from __future__ import annotations

import json
import pickle
import shutil
import warnings
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from grounder.cli import app
from grounder.core.trajectory import Trajectory, save_trajectories
from grounder.errors import GrounderError
from grounder.residual.files import file_sha256, scene_files_sha256
from grounder.residual.free_body import NumpyResidual, free_bodies
from grounder.residual.meta import META_FILE, WEIGHTS_FILE, GateOptions, ResidualMeta
from grounder.residual.options import ResidualOptions
from grounder.residual.simulator import Simulator
from grounder.residual.torch_model import residual_model
from grounder.residual.train import train_residual
from grounder.sim.rollout import simulate

RATE_HZ = 100.0
PERIOD_STEPS = 4
HIDDEN = 4
CENTRES = 2
CUBE_XML = f"""<mujoco>
  <option timestep="{1.0 / RATE_HZ / PERIOD_STEPS}"/>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" friction="0.3 0.005 0.0001"/>
    <body name="cube" pos="0 0 0.3">
      <freejoint/>
      <geom type="box" size="0.05 0.05 0.05" mass="0.4" friction="0.3 0.005 0.0001"/>
    </body>
  </worldbody>
</mujoco>
"""


def _write_residual(folder: Path, xml: str = CUBE_XML, files: dict[str, str] | None = None) -> Path:
    """A valid residual scene folder (scene.xml, the ``files`` it loads, residual.json, residual.pt) with an
    untrained tiny network."""
    folder.mkdir(parents=True)
    (folder / "scene.xml").write_text(xml)
    for name, text in (files or {}).items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    model = mujoco.MjModel.from_xml_path(str(folder / "scene.xml"))
    gate = GateOptions(coverage_centres=CENTRES)
    meta = ResidualMeta(
        period_steps=PERIOD_STEPS,
        timestep_s=float(model.opt.timestep),
        bodies=("cube",),
        hidden=HIDDEN,
        layers=1,
        gate=gate,
        scene_xml_sha256=file_sha256(folder / "scene.xml"),
        training={},
        scene_files_sha256=scene_files_sha256(folder / "scene.xml"),
    )
    torch.manual_seed(0)
    radius_m = np.array([b.radius_m for b in free_bodies(model)])
    net = residual_model(meta, radius_m=radius_m)
    torch.save({k: v.detach().clone() for k, v in net.state_dict().items()}, folder / WEIGHTS_FILE)
    (folder / META_FILE).write_text(json.dumps(meta.to_json(), indent=2) + "\n")
    return folder


def _edit_meta(edit: Callable[[dict[str, Any]], None]) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        raw = json.loads((folder / META_FILE).read_text())
        edit(raw)
        (folder / META_FILE).write_text(json.dumps(raw))  # NaN and Infinity as Python's json writes them

    return apply


def _set_meta(key: str, value: Any) -> Callable[[Path], None]:
    def edit(raw: dict[str, Any]) -> None:
        if key.startswith("gate."):
            raw["gate"][key.removeprefix("gate.")] = value
        elif value is _DELETE:
            del raw[key]
        else:
            raw[key] = value

    return _edit_meta(edit)


_DELETE = object()


def _edit_state(edit: Callable[[dict[str, Any]], Any]) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        state = torch.load(folder / WEIGHTS_FILE, weights_only=True)
        result = edit(state)
        torch.save(state if result is None else result, folder / WEIGHTS_FILE)

    return apply


def _set_tensor(name: str, make: Callable[[torch.Tensor], torch.Tensor]) -> Callable[[Path], None]:
    def edit(state: dict[str, torch.Tensor]) -> None:
        state[name] = make(state[name])

    return _edit_state(edit)


def _with_value(value: float, at: tuple[int, ...]) -> Callable[[torch.Tensor], torch.Tensor]:
    def make(tensor: torch.Tensor) -> torch.Tensor:
        tensor = tensor.clone()
        tensor[at] = value
        return tensor

    return make


def _write_bytes(data: bytes, name: str = META_FILE) -> Callable[[Path], None]:
    def apply(folder: Path) -> None:
        (folder / name).write_bytes(data)

    return apply


def _repeat_key(key: str, value: Any) -> Callable[[Path], None]:
    """residual.json with ``key`` written a second time, first in the object (the trained one stays later)."""

    def apply(folder: Path) -> None:
        text = (folder / META_FILE).read_text()
        assert text.startswith("{") and f'"{key}"' in text
        (folder / META_FILE).write_text("{" + json.dumps(key) + ": " + json.dumps(value) + ", " + text[1:])

    return apply


class _NotWeights:
    """Pickled with protocol 4 it is what torch warns about (pickle protocol) and then refuses (not allowlisted);
    its reduction is harmless even if it ever ran."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (Fraction, (1, 3))


PICKLE_PROTOCOL_4 = pickle.dumps(_NotWeights(), protocol=4)

J, W = META_FILE, WEIGHTS_FILE
# (what is wrong, how the folder is broken, the file the error line names, what else it must say)
BROKEN: list[tuple[str, Callable[[Path], None], str, str]] = [
    # residual.json: not JSON text, not an object
    ("json-not-utf8", _write_bytes(b'{"format": "\xff\xfe"}'), J, "not UTF-8 text"),
    ("json-list", _write_bytes(b"[1, 2, 3]"), J, "expected a JSON object, got a JSON array"),
    ("json-truncated", _write_bytes(b'{"format": "image2'), J, "not valid JSON"),
    ("json-deep", _write_bytes(b"[" * 100_000), J, "nested too deeply"),
    # a key given twice was last-wins without a word (the first of two period_steps is what training wrote)
    ("json-repeated-key", _repeat_key("period_steps", 7), J, 'key "period_steps" appears twice in one object'),
    ("json-repeated-gate-key", _repeat_key("gate", {}), J, 'key "gate" appears twice'),
    # residual.json: fields the Simulator and the residual use as they are
    ("period-zero", _set_meta("period_steps", 0), J, "period_steps is 0, expected an integer in [1, "),
    ("period-huge", _set_meta("period_steps", 10**9), J, "period_steps is 1000000000"),
    ("period-negative", _set_meta("period_steps", -3), J, "period_steps is -3"),
    ("period-fractional", _set_meta("period_steps", 4.7), J, "period_steps is 4.7"),
    ("period-bool", _set_meta("period_steps", True), J, "period_steps is true"),
    ("period-string", _set_meta("period_steps", "4"), J, 'period_steps is "4"'),
    ("timestep-nan", _set_meta("timestep_s", float("nan")), J, "timestep_s is NaN"),
    ("hidden-string", _set_meta("hidden", "abc"), J, 'hidden is "abc"'),
    ("hidden-missing", _set_meta("hidden", _DELETE), J, "hidden is missing"),
    ("layers-zero", _set_meta("layers", 0), J, "layers is 0, expected an integer >= 1"),
    ("bodies-string", _set_meta("bodies", "cube"), J, 'bodies is "cube", expected a non-empty list'),
    ("features-number", _set_meta("features", 3), J, "features is 3, expected a list of names"),
    ("training-list", _set_meta("training", [1]), J, "training is a JSON array, expected an object"),
    ("gate-null", _set_meta("gate", None), J, "gate is null, expected an object"),
    ("gate-centres-negative", _set_meta("gate.coverage_centres", -5), J, "gate.coverage_centres is -5"),
    ("gate-centres-float", _set_meta("gate.coverage_centres", 2.5), J, "gate.coverage_centres is 2.5"),
    ("gate-energy-negative", _set_meta("gate.energy_restore_fraction", -1e9), J, "energy_restore_fraction is"),
    ("gate-energy-above-one", _set_meta("gate.energy_restore_fraction", 1.5), J, "expected a number in [0, 1]"),
    ("gate-margin-nan", _set_meta("gate.range_margin", float("nan")), J, "gate.range_margin is NaN"),
    ("gate-quantile-inf", _set_meta("gate.coverage_quantile", float("inf")), J, "coverage_quantile is Infinity"),
    ("gate-rest-nan", _set_meta("gate.rest_speed_m_s", [float("nan"), 0.05]), J, "rest_speed_m_s is [NaN, 0.05]"),
    ("gate-rest-equal", _set_meta("gate.rest_speed_m_s", [0.05, 0.05]), J, "with on > off"),
    ("gate-rest-number", _set_meta("gate.rest_speed_m_s", 5), J, "gate.rest_speed_m_s is 5"),
    ("gate-air-huge-int", _set_meta("gate.air_clearance_m", [0, 10**400]), J, "gate.air_clearance_m is"),
    ("sha-missing", _set_meta("scene_xml_sha256", _DELETE), J, "scene_xml_sha256 is missing"),
    ("sha-not-hex", _set_meta("scene_xml_sha256", "x" * 64), J, "scene_xml_sha256 is"),
    ("files-sha-list", _set_meta("scene_files_sha256", ["a" * 64]), J, 'scene_files_sha256 is ["'),
    ("files-sha-not-hex", _set_meta("scene_files_sha256", {"m.obj": "x"}), J, 'scene_files_sha256 is {"m.obj"'),
    # residual.json and residual.pt disagree
    ("hidden-not-the-weights", _set_meta("hidden", 8), W, "'nets.0.0.weight' has shape (4, 11), expected (8, 11)"),
    ("layers-not-the-weights", _set_meta("layers", 3), W, 'missing tensor "nets.0.4.weight"'),
    ("centres-not-the-weights", _set_meta("gate.coverage_centres", 3), W, "'centres' has shape (1, 2, 11)"),
    # residual.pt: every tensor dense, real floating point, of the expected shape, finite
    ("pt-shape", _set_tensor("feat_mean", lambda t: torch.zeros(1, 10, dtype=t.dtype)), W, "'feat_mean' has shape"),
    ("pt-flat", _edit_state(lambda s: {k: v.flatten() for k, v in s.items()}), W, "'feat_mean' has shape (11,)"),
    ("pt-sparse", _set_tensor("feat_mean", lambda t: t.to_sparse()), W, "'feat_mean' is a sparse tensor"),
    ("pt-complex", _set_tensor("feat_mean", lambda t: t.to(torch.complex128)), W, "'feat_mean' is a complex tensor"),
    ("pt-integer", _set_tensor("out_gain", lambda t: t.to(torch.int64)), W, "'out_gain' has dtype torch.int64"),
    ("pt-nan-weight", _set_tensor("nets.0.0.weight", _with_value(float("nan"), (0, 0))), W, "NaN or infinite"),
    ("pt-inf-bound", _set_tensor("out_bound", _with_value(float("inf"), (0, 3))), W, "'out_bound' holds NaN"),
    ("pt-zero-std", _set_tensor("feat_std", _with_value(0.0, (0, 2))), W, "'feat_std' holds values <= 0"),
    ("pt-negative-gain", _set_tensor("out_gain", lambda t: -t), W, "negative output gain"),
    ("pt-missing", _edit_state(lambda s: {k: s[k] for k in s if k != "centres"}), W, 'missing tensor "centres"'),
    ("pt-extra", _edit_state(lambda s: s.update(extra=torch.ones(1))), W, 'unexpected tensor "extra"'),
    ("pt-list", _edit_state(lambda s: list(s.values())), W, "expected a state_dict"),
    ("pt-not-tensor", _edit_state(lambda s: s.update(out_gain=[1.0])), W, "'out_gain' is a list, not a tensor"),
    # residual.pt that torch cannot load safely: not torch's text (several lines, suggests weights_only=False)
    ("pt-garbage", _write_bytes(b"not a tensor file" * 10, W), W, "not a valid weights file"),
    ("pt-empty", _write_bytes(b"", W), W, "not a valid weights file (EOFError)"),
    ("pt-pickle-protocol", _write_bytes(PICKLE_PROTOCOL_4, W), W, "not a valid weights file (UnpicklingError)"),
]


@pytest.fixture(scope="module")
def valid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_residual(tmp_path_factory.mktemp("valid") / "res")


@pytest.fixture(scope="module")
def trajs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two short drops of the cube, in the project's trajectory format."""
    time_s = np.arange(6) / RATE_HZ
    qpos = np.tile([0.0, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0], (6, 1))
    out = [Trajectory(time_s=time_s, qpos=qpos, qvel=np.zeros((6, 6)), name=f"drop{i}") for i in range(2)]
    return save_trajectories(out, tmp_path_factory.mktemp("trajs") / "t")


def _rollout(scene: Path, trajs: Path, out: Path, *options: str) -> Any:
    return CliRunner().invoke(app, ["rollout", str(scene), str(trajs), "-o", str(out), *options])


def _assert_one_line(result: Any, *needles: str) -> str:
    """Exit code 2, stderr exactly one ``image2sim: error:`` line (no warning, no traceback) holding ``needles``."""
    assert result.exit_code == 2, (result.exit_code, result.output[-2000:], result.exception)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("image2sim: error: "), result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert "weights_only" not in lines[0] and "Traceback" not in result.output
    return lines[0]


def test_a_valid_folder_loads_and_rolls_out(valid: Path, trajs: Path, tmp_path: Path) -> None:
    sim = Simulator(valid)
    assert isinstance(sim.residual, NumpyResidual) and sim.period_steps == PERIOD_STEPS
    result = _rollout(valid, trajs, tmp_path / "out")
    assert result.exit_code == 0 and "MuJoCo + residual" in result.output, result.output


def test_unstable_rollout_with_the_residual_is_refused(valid: Path, tmp_path: Path) -> None:
    """With the residual on, a rollout MuJoCo stops as unstable (a cube slammed into the floor at 1e9 m/s: the
    contact's acceleration passes MuJoCo's 1e10 limit) is refused like plain MuJoCo's: one line, exit 2, nothing
    written, rather than corrected period after period from a repeated state."""
    time_s = np.arange(6) / RATE_HZ
    qpos = np.tile([0.0, 0.0, 0.05, 1.0, 0.0, 0.0, 0.0], (6, 1))
    qvel = np.zeros((6, 6))
    qvel[0, 2] = -1e9
    bad = save_trajectories([Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name="slam")], tmp_path / "t")
    line = _assert_one_line(_rollout(valid, bad, tmp_path / "out"), "trajectory slam: the simulation became unstable")
    assert "QACC at DOF 2" in line and not (tmp_path / "out").exists()


@pytest.mark.parametrize(("breaks", "file", "needle"), [c[1:] for c in BROKEN], ids=[c[0] for c in BROKEN])
def test_broken_residual_is_one_line_exit_2(
    breaks: Callable[[Path], None], file: str, needle: str, valid: Path, trajs: Path, tmp_path: Path
) -> None:
    """The auditor's repro, `image2sim rollout SCENE_WITH_RESIDUAL TRAJ_DIR -o OUT`, for each way a folder breaks:
    rejected when the scene is loaded, before any simulation, naming the file that is wrong and the fix."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    breaks(folder)
    with pytest.raises(GrounderError) as caught:
        Simulator(folder)
    assert "\n" not in str(caught.value)
    line = _assert_one_line(_rollout(folder, trajs, tmp_path / "out"), f"{folder / file}: ", needle)
    assert line.endswith("retrain with `image2sim residual train`"), line
    assert not (tmp_path / "out").exists()


def test_pickle_protocol_file_prints_no_torch_warning(valid: Path, tmp_path: Path) -> None:
    """torch warns (two lines) about a pickle protocol other than its own before refusing the file."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    (folder / WEIGHTS_FILE).write_bytes(PICKLE_PROTOCOL_4)
    with warnings.catch_warnings(record=True) as caught, pytest.raises(GrounderError, match="not a valid weights"):
        warnings.simplefilter("always")
        Simulator(folder)
    assert not [w for w in caught if "pickle protocol" in str(w.message)], [str(w.message) for w in caught]


def test_property_weights_that_do_not_load_are_one_line(tmp_path: Path) -> None:
    """The property model's weights: torch's text (over lines, recommending weights_only=False) is not passed on."""
    from grounder.properties.model_files import WEIGHTS_DIR, PropertyModelError
    from grounder.properties.network import META_FILE as PROPERTY_META
    from grounder.properties.network import WEIGHTS_FILE as PROPERTY_WEIGHTS
    from grounder.properties.prior import load_property_model

    for content in (PICKLE_PROTOCOL_4, b"not a weights file"):
        weights = tmp_path / f"weights_{len(content)}"
        weights.mkdir()
        shutil.copy2(WEIGHTS_DIR / PROPERTY_META, weights / PROPERTY_META)
        (weights / PROPERTY_WEIGHTS).write_bytes(content)
        with warnings.catch_warnings(record=True) as caught, pytest.raises(PropertyModelError) as error:
            warnings.simplefilter("always")
            load_property_model(weights)
        message = str(error.value)
        assert "\n" not in message and "weights_only" not in message, message
        assert message.startswith(f"{weights / PROPERTY_WEIGHTS}: not a valid weights file"), message
        assert f"`image2sim properties train -o {weights} --overwrite`" in message
        assert not [w for w in caught if "pickle protocol" in str(w.message)]


def test_scene_edited_since_training_is_refused(valid: Path, trajs: Path, tmp_path: Path) -> None:
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    xml = folder / "scene.xml"
    xml.write_text(CUBE_XML.replace('mass="0.4" friction="0.3', 'mass="0.4" friction="0.9'))  # the audit's edit
    assert xml.read_text() != CUBE_XML
    with pytest.raises(GrounderError, match=r"scene\.xml changed since the residual was trained"):
        Simulator(folder)
    line = _assert_one_line(_rollout(folder, trajs, tmp_path / "out"), str(xml), "sha256", "image2sim residual train")
    assert "restore the scene" in line
    # Without the residual applied there is nothing stale to refuse; plain MuJoCo runs at the residual's period.
    assert Simulator(folder, use_residual=False).period_steps == PERIOD_STEPS
    assert _rollout(folder, trajs, tmp_path / "plain", "--no-residual").exit_code == 0
    xml.write_text(CUBE_XML)  # restored: the residual applies again
    assert Simulator(folder).residual is not None


MESH_CUBE_XML = CUBE_XML.replace('<geom type="box" size="0.05 0.05 0.05"', '<geom type="mesh" mesh="cube"').replace(
    "<worldbody>", '<asset><mesh name="cube" file="assets/cube.obj"/></asset>\n  <worldbody>'
)
CUBE_OBJ = "".join(f"v {x} {y} {z}\n" for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)) + (
    "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6\n"
)


def test_mesh_edited_since_training_is_refused(trajs: Path, tmp_path: Path) -> None:
    """The residual was trained on the scene's meshes too: a mesh changed, removed or added since training is
    refused like an edited scene.xml, naming the file; a residual.json from before the per-file hashes (no
    ``scene_files_sha256``) still loads, checked on scene.xml alone."""
    folder = _write_residual(tmp_path / "res", MESH_CUBE_XML, {"assets/cube.obj": CUBE_OBJ})
    meta = json.loads((folder / META_FILE).read_text())
    assert meta["scene_files_sha256"] == {"assets/cube.obj": file_sha256(folder / "assets/cube.obj")}
    assert Simulator(folder).residual is not None
    mesh = folder / "assets/cube.obj"
    mesh.write_text(CUBE_OBJ.replace("v 0.05 0.05 0.05", "v 0.06 0.05 0.05"))
    with pytest.raises(GrounderError, match=r"assets/cube\.obj changed \(sha256 .*since the residual was trained"):
        Simulator(folder)
    line = _assert_one_line(_rollout(folder, trajs, tmp_path / "out"), "assets/cube.obj changed", "residual train")
    assert "restore the scene" in line and not (tmp_path / "out").exists()
    assert _rollout(folder, trajs, tmp_path / "plain", "--no-residual").exit_code == 0  # not applied: nothing stale
    mesh.write_text(CUBE_OBJ)
    assert Simulator(folder).residual is not None
    # A file the scene loads that training did not see, or one it saw that is gone from the record.
    _set_meta("scene_files_sha256", {**meta["scene_files_sha256"], "assets/old.obj": "0" * 64})(folder)
    with pytest.raises(GrounderError, match=r"assets/old\.obj is gone since the residual was trained"):
        Simulator(folder)
    _set_meta("scene_files_sha256", {})(folder)
    with pytest.raises(GrounderError, match=r"assets/cube\.obj is new since the residual was trained"):
        Simulator(folder)
    _set_meta("scene_files_sha256", _DELETE)(folder)  # written before the field existed
    mesh.write_text(CUBE_OBJ.replace("v 0.05 0.05 0.05", "v 0.06 0.05 0.05"))
    assert Simulator(folder).residual is not None


def _four_tosses(xml: str, count: int = 4) -> list[Trajectory]:
    """Four (or ``count``) short tosses of the cube, simulated in ``xml``."""
    model = mujoco.MjModel.from_xml_string(xml)
    time_s = np.arange(12) / RATE_HZ
    seeds = []
    for i in range(count):
        qpos = np.tile([0.0, 0.0, 0.2 + 0.05 * i, 1.0, 0.0, 0.0, 0.0], (12, 1))
        qvel = np.tile([1.0, 0.5 * i, 0.0, 2.0, -1.0, 0.5], (12, 1))
        seeds.append(Trajectory(time_s=time_s, qpos=qpos, qvel=qvel, name=f"t{i}"))
    recorded = simulate(model, seeds)
    assert isinstance(recorded, list)
    return recorded


def _tiny_options() -> ResidualOptions:
    return ResidualOptions(
        steps=2, batch_size=8, hidden=HIDDEN, layers=1, gains=(0.0, 1.0), gate=GateOptions(coverage_centres=CENTRES)
    )


def test_retraining_on_an_edited_residual_scene_works(valid: Path, tmp_path: Path) -> None:
    """What the refusal says to do: `residual train` on the edited folder (its old residual is not applied while
    training), and the new residual loads with the edited scene.xml."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    edited = CUBE_XML.replace('mass="0.4" friction="0.3', 'mass="0.4" friction="0.6')
    (folder / "scene.xml").write_text(edited)
    result = train_residual(folder, _four_tosses(edited), tmp_path / "retrained", _tiny_options())
    out = result.out
    written = json.loads((out / META_FILE).read_text())
    assert written["scene_xml_sha256"] == file_sha256(folder / "scene.xml")
    assert written["scene_files_sha256"] == {}  # a scene of primitives loads no files
    assert Simulator(out).residual is not None
    assert result.gain == 1.0 and result.gain_scores == {}  # four trajectories: none held out, the gain unchecked


@pytest.mark.parametrize("case", ["pt-garbage", "pt-nan-weight", "hidden-not-the-weights"])
def test_retraining_on_a_broken_residual_works(
    case: str, valid: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The refusal of a broken residual says "retrain with `image2sim residual train`": that command must not be
    refused for the very residual it is to replace (it is not applied while training)."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    breaks = next(c[1] for c in BROKEN if c[0] == case)
    breaks(folder)
    with pytest.raises(GrounderError):
        Simulator(folder)
    out = train_residual(folder, _four_tosses(CUBE_XML), tmp_path / "retrained", _tiny_options()).out
    assert Simulator(out).residual is not None
    # With trajectories held out for the gain check too, the scene is loaded once: the broken residual is named
    # in one warning, not one per stage of training.
    caplog.clear()
    train_residual(folder, _four_tosses(CUBE_XML, 6), tmp_path / "retrained6", _tiny_options())
    warned = [r for r in caplog.records if "not using the residual" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in caplog.records]


@pytest.mark.parametrize("kept", [META_FILE, WEIGHTS_FILE])
def test_half_a_residual_is_refused_not_ignored(kept: str, valid: Path, trajs: Path, tmp_path: Path) -> None:
    """A folder with residual.pt but no residual.json (or the other way round) would roll out as plain MuJoCo while
    the user believes the residual is on: refused, one line naming both files; --no-residual still runs."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    missing = WEIGHTS_FILE if kept == META_FILE else META_FILE
    (folder / missing).unlink()
    with pytest.raises(GrounderError, match=f"has no {missing} beside it"):
        Simulator(folder)
    _assert_one_line(_rollout(folder, trajs, tmp_path / "out"), str(folder / kept), missing, "--no-residual")
    assert not (tmp_path / "out").exists()
    plain = _rollout(folder, trajs, tmp_path / "plain", "--no-residual")
    assert plain.exit_code == 0, plain.output


def test_an_unchecked_gain_is_said_so(valid: Path, tmp_path: Path) -> None:
    """Fewer than 5 trajectories leave none to choose the output gain on: the command says it is unchecked rather
    than "chosen on held-out rollouts"."""
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    tosses = save_trajectories(_four_tosses(CUBE_XML), tmp_path / "tosses")
    args = ["residual", "train", str(folder), str(tosses), "-o", str(tmp_path / "out"), "--steps", "2"]
    result = CliRunner().invoke(app, [*args, "--hidden", str(HIDDEN), "--rounds", "1"])
    assert result.exit_code == 0, result.output
    assert "output gain 1, NOT checked on held-out rollouts" in result.stdout
    assert "chosen on held-out" not in result.stdout


def test_a_free_body_residual_in_a_jointed_scene_names_its_file(valid: Path, tmp_path: Path) -> None:
    folder = tmp_path / "res"
    shutil.copytree(valid, folder)
    hinge = '<mujoco><worldbody><body><joint type="hinge"/><geom size="0.1" mass="1"/></body></worldbody></mujoco>'
    (folder / "scene.xml").write_text(hinge)
    with pytest.raises(GrounderError) as caught:
        Simulator(folder)
    line = str(caught.value)
    assert line.startswith(f"{folder / META_FILE}: a residual of free bodies") and "--no-residual" in line, line
