"""Gap diagnosis of multi-object scenes: an effect withheld on one body is found on that body with its value; an
effect named on a contact pair is written into ``diagnosed.xml`` as a ``<pair>``; the folder `image2sim track`
writes is diagnosed with the tracker's smoothing in the noise floor. The full multi-object cases are in
`benchmarks/diagnose.py` (``diagnose-benchmark``)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder import save_trajectories
from grounder.diagnosis.benchmark import same_place
from grounder.diagnosis.cases import MULTI_BODY, CaseSpec, make_case
from grounder.diagnosis.noise import derivative_noise_gain
from grounder.diagnosis.pipeline import DiagnoseOptions, diagnose
from tests.conftest import CliRun, assert_one_line_error


def _spec(name: str) -> CaseSpec:
    return next(c for c in MULTI_BODY if c.name == name)


def test_friction_withheld_on_one_body_is_found_on_that_body() -> None:
    spec = _spec("two_boxes/sliding_friction@box_a")
    case = make_case(spec, num_trajectories=8, seed=3, duration_s=0.8)
    model = mujoco.MjModel.from_xml_string(case.scene_xml)
    diag = diagnose(
        model, case.trajectories, DiagnoseOptions(nthread=2), spec=mujoco.MjSpec.from_string(case.scene_xml)
    )
    top = diag.effects[0]
    pairs = [f"{a}|{b}" for a, b in diag.layout.pairs] if diag.layout else []
    assert top.effect == "sliding_friction"
    assert same_place("box_a", top.target.label, pairs), (top.key, pairs)
    assert top.params["mu"] == pytest.approx(0.25, rel=0.1)
    assert diag.selected[0] == top.key
    # The global variant explains less than the local one: the other box's friction is right.
    global_ = next(e for e in diag.effects if e.key == "sliding_friction")
    assert global_.heldout_reduction < top.heldout_reduction
    # Where: box_a carries the gap, and the selected effect removes most of it there, not on box_b.
    assert diag.gap["by_body"]["box_a"] > 1.5 * diag.gap["by_body"]["box_b"]  # box_b: at the noise
    step = diag.steps[0]["heldout_by_body"]
    assert step["box_a"]["reduction"] > 0.5
    assert abs(step["box_b"]["reduction"]) < 0.05
    assert set(diag.gap["by_pair"]) >= {"box_a|floor", "box_b|floor"}
    # box_b's remaining gap is the recording's noise there: not reported as unexplained.
    assert diag.unexplained_by_body["box_b"]["after"] <= 1.25 * diag.unexplained_by_body["box_b"]["noise_floor"]
    assert "largely unexplained" not in diag.to_json()["finding"]


@pytest.fixture(scope="module")
def stack_case(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("stack")
    case = make_case(_spec("stack/sliding_friction@box_a|box_b"), num_trajectories=6, seed=4, duration_s=0.5)
    scene = root / "scene.xml"
    scene.write_text(case.scene_xml)
    save_trajectories(case.trajectories, root / "trajs")
    return scene, root / "trajs"


def test_cli_writes_a_contact_pair_effect_as_a_pair(
    stack_case: tuple[Path, Path], tmp_path: Path, cli: Callable[..., CliRun]
) -> None:
    scene, trajs = stack_case
    out = tmp_path / "out"
    proc = cli("diagnose", str(scene), str(trajs), "-o", str(out), "--effects", "sliding_friction@box_a|box_b")
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["selected"] == ["sliding_friction@box_a|box_b"]
    assert doc["effects"][0]["target"] == {"kind": "pair", "label": "box_a|box_b", "parties": ["box_a", "box_b"]}
    mu = doc["effects"][0]["params"]["mu"]
    assert mu == pytest.approx(0.2, rel=0.1)
    assert set(doc["layout"]["contact_pairs"]) == {"box_a|box_b", "box_a|floor", "box_c|floor"}
    nominal = mujoco.MjModel.from_xml_path(str(scene))
    diagnosed = mujoco.MjModel.from_xml_path(str(out / "diagnosed.xml"))
    assert diagnosed.npair == 1  # only the changed pair is written
    names = {mujoco.mj_id2name(diagnosed, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in diagnosed.pair_geom1[:1]}
    names |= {mujoco.mj_id2name(diagnosed, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in diagnosed.pair_geom2[:1]}
    assert names == {"box_a", "box_b"}
    assert diagnosed.pair_friction[0, :2] == pytest.approx([mu, mu], rel=1e-5)  # MJCF keeps 6 digits
    assert np.array_equal(diagnosed.geom_friction, nominal.geom_friction)  # every other contact as it was


def _track_folder(root: Path, smoothing_frames: int = 7) -> Path:
    """A folder shaped like `image2sim track`'s output: segment trajectories and track.json."""
    case = make_case(_spec("two_boxes/sliding_friction@box_a"), num_trajectories=6, seed=5, duration_s=0.5)
    folder = root / "tracks"
    save_trajectories(case.trajectories, folder)
    doc = {
        "format": "image2sim.track/1",
        "fps": 100.0,
        "objects": {"box_a": {"tracked_fraction": 0.9}, "box_b": {"tracked_fraction": 1.0}},
        "segments": [{"name": t.name} for t in case.trajectories],
        "options": {"smoothing": {"window_frames": smoothing_frames}},
    }
    (folder / "track.json").write_text(json.dumps(doc))
    (root / "scene.xml").write_text(case.scene_xml)
    return folder


def test_cli_diagnoses_a_track_folder_with_the_tracker_smoothing_in_the_noise(
    tmp_path: Path, cli: Callable[..., CliRun]
) -> None:
    folder = _track_folder(tmp_path)
    out = tmp_path / "out"
    proc = cli("diagnose", str(tmp_path / "scene.xml"), str(folder), "-o", str(out), "--effects", "sliding_friction")
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads((out / "diagnosis.json").read_text())
    noise = doc["noise"]
    assert noise["velocity_smoothing_frames"] == 7
    assert noise["velocity_m_s"] >= noise["position_m"] * derivative_noise_gain(7, 0.01) * (1 - 1e-9)
    assert len(doc["split"]["tracked_segments_used"]) == 6


def test_cli_refuses_a_track_json_it_did_not_write(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    folder = _track_folder(tmp_path)
    (folder / "track.json").write_text('{"format": "someone-else/2"}')
    out = tmp_path / "out"
    proc = cli("diagnose", str(tmp_path / "scene.xml"), str(folder), "-o", str(out))
    assert_one_line_error(proc, "not a track.json that image2sim track wrote")
    assert not out.exists()


def test_cli_says_which_object_was_never_tracked_when_track_wrote_no_trajectory(
    tmp_path: Path, cli: Callable[..., CliRun]
) -> None:
    """`image2sim track` writes track.json but no trajectory when no frame has every object tracked (a phantom the
    scan left, an object the tracker never finds): the refusal names the tracked shares, not a missing file."""
    folder = _track_folder(tmp_path)
    for npz in folder.glob("*.npz"):
        npz.unlink()
    doc = json.loads((folder / "track.json").read_text())
    doc["segments"] = []
    doc["objects"]["box_b"]["tracked_fraction"] = 0.0
    (folder / "track.json").write_text(json.dumps(doc))
    out = tmp_path / "out"
    proc = cli("diagnose", str(tmp_path / "scene.xml"), str(folder), "-o", str(out))
    assert_one_line_error(proc, "found no run of frames long enough with every object tracked")
    assert "box_b 0%" in proc.stderr and "box_a 90%" in proc.stderr
    assert not out.exists()


def test_derivative_noise_gain_matches_a_savitzky_golay_fit() -> None:
    """The slope of a 7-frame least-squares fit of white noise (sigma 1) has sigma 1 / (dt sqrt(28))."""
    from scipy.signal import savgol_filter

    rng = np.random.default_rng(0)
    noise = rng.normal(size=200_000)
    slope = savgol_filter(noise, 7, 2, deriv=1, delta=0.01)
    assert np.std(slope[10:-10]) == pytest.approx(derivative_noise_gain(7, 0.01), rel=0.02)


@pytest.mark.parametrize(
    ("effect", "needle"),
    [
        ("sliding_friction@box_b|box_c", "box_b and box_c never touch in the recordings"),
        ("mass@box_a|box_b", "effect 'mass' cannot act on one pair"),
        ("restitution@nobody", "'@nobody' names no moving body"),
    ],
)
def test_cli_refuses_a_place_an_effect_cannot_act_on(
    effect: str, needle: str, stack_case: tuple[Path, Path], tmp_path: Path, cli: Callable[..., CliRun]
) -> None:
    scene, trajs = stack_case
    out = tmp_path / "out"
    proc = cli("diagnose", str(scene), str(trajs), "-o", str(out), "--effects", effect)
    assert_one_line_error(proc, needle)
    assert not out.exists()
