"""Film-a-scene on two scenes of the generated family that no tuning used (issue 60).

The scenes are the first two of the tests' seed range (100-199, `samples/make_scene_family.py --small`: 640x480
video, 1-3 objects), rendered here and grounded by the CLI a user runs. Each check is one of the issue's targets;
`benchmarks/scene_family.py` measures the same targets on held-out scenes (seeds 1000+).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from grounder.grounding.evaluate import ObjectScore, SceneScore, score_scene
from scene_export import settle_test
from tests.conftest import PROGRESS_LINE, assert_one_line_error

REPO = Path(__file__).resolve().parents[2]
SEEDS = (100, 101)


@pytest.fixture(scope="module")
def family_scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("family")
    cmd = [sys.executable, str(REPO / "samples" / "make_scene_family.py"), str(out), "--small"]
    subprocess.run([*cmd, "--seed", str(SEEDS[0]), "--count", str(len(SEEDS))], check=True, capture_output=True)
    return out


# Targets not met yet on these two scenes (seed 101's figures as measured 2026-12-08 on an AVX-512 machine, where its
# meshes differ from those of the machines before: the same code, other rounding; its toy figure, toppling there, is
# at rest since the foot rule of `_objects.mesh_object`); each mark goes once the figure passes (strict: a pass then
# fails the run, so the list cannot go stale). The held-out figures are in docs/results/scene_family.md.
NOT_YET: dict[tuple[int, str], str] = {
    (100, "found"): "a single low-texture cup on a half orbit with --known-extent: no sparse point stands on it; "
    "since 2026-12-07 the scene grounds (a provisional scale, then the known extent on the cup's mesh), but the "
    "cup's fused mesh reaches 62% of its height, so the scene is scaled x 1.61 and the cup counts as an extra body",
    (100, "objects"): "nothing found to measure (the cup, above)",
    (101, "chamfer"): "bowl_0: 5.4 mm, its rim torn and ragged (issue 60 item 6); irregular_1, a toy figure: 6.0 mm",
    (101, "normals"): "bowl_0: 0.69, the torn rim; irregular_1: 0.64; plate_2: 0.88",
    (101, "topology"): "bowl_0: Euler number -16 (holes through the wall), plate_2 -6, irregular_1 0; truth 2",
    (101, "extents"): "irregular_1, a toy figure 5 cm wide and 8.7 cm tall: 38% (its 5 cm base disc meshed 3.8 cm)",
}
# Not met on any machine tried, but near enough that another CPU's rounding could meet it: not strict.
BORDERLINE = {
    (101, "centres"): "irregular_1: 8.8 mm (5.2 mm on the machines before) against 5 mm (its base disc meshed narrow)"
}


PER_OBJECT = ("centres", "chamfer", "extents", "normals", "topology", "cavity")  # checks of each found object


def _seeds(check: str) -> list[object]:
    """The seeds as parameters, each marked where `check` is not met yet on it."""
    params = []
    for seed in SEEDS:
        marks = []
        reason = NOT_YET.get((seed, check)) or NOT_YET.get((seed, "scene"))
        if check in PER_OBJECT:
            reason = reason or NOT_YET.get((seed, "objects"))
        if reason and not (check == "traceback"):
            marks.append(pytest.mark.xfail(reason=f"not yet: {reason}", strict=True))
        elif (seed, check) in BORDERLINE:
            marks.append(pytest.mark.xfail(reason=f"not yet, by a hair: {BORDERLINE[seed, check]}", strict=False))
        params.append(pytest.param(seed, marks=marks, id=f"seed{seed}"))
    return params


_RUNS: dict[int, tuple[subprocess.CompletedProcess[str], Path, Path]] = {}


@pytest.fixture
def grounded(
    request: pytest.FixtureRequest, family_scenes: Path
) -> tuple[subprocess.CompletedProcess[str], Path, Path]:
    seed = request.param
    if seed not in _RUNS:
        scene = family_scenes / f"scene_{seed:05d}"
        family = json.loads((scene / "truth" / "family.json").read_text())
        out = family_scenes / f"grounded_{seed}"
        cmd = [sys.executable, "-m", "grounder.cli", "ground", str(scene / family["source"]), "-o", str(out)]
        _RUNS[seed] = (subprocess.run([*cmd, *family["ground_args"]], capture_output=True, text=True), scene, out)
    return _RUNS[seed]


_SCORES: dict[Path, SceneScore] = {}


@pytest.fixture
def score(grounded: tuple[subprocess.CompletedProcess[str], Path, Path]) -> SceneScore:
    run, scene, out = grounded
    if run.returncode != 0:
        pytest.fail(f"ground exited {run.returncode}: {run.stderr.strip().splitlines()[-1:]}")
    if out not in _SCORES:
        _SCORES[out] = score_scene(out, scene / "truth")
    return _SCORES[out]


def _found(score: SceneScore) -> list[ObjectScore]:
    """The found objects, for the per-object checks; none found fails them (a check of nothing proves nothing)."""
    found = [o for o in score.objects if o.found]
    if not found:
        pytest.fail(f"no object found to measure (of {len(score.objects)})")
    return found


@pytest.mark.parametrize("grounded", _seeds("traceback"), indirect=True)
def test_grounds_without_a_traceback(grounded: tuple[subprocess.CompletedProcess[str], Path, Path]) -> None:
    run, _, _ = grounded
    assert "Traceback" not in run.stderr + run.stdout
    assert run.returncode in (0, 2), run.stderr.strip().splitlines()[-1:]
    if run.returncode == 2:  # refused: one line saying why (after the progress bars)
        assert_one_line_error(run)
        others = [line for line in run.stderr.splitlines() if line.strip() and not PROGRESS_LINE.search(line)]
        assert len(others) == 1, run.stderr


@pytest.mark.parametrize("grounded", _seeds("scene"), indirect=True)
def test_grounds_a_scene(grounded: tuple[subprocess.CompletedProcess[str], Path, Path]) -> None:
    run, _, out = grounded
    assert run.returncode == 0, run.stderr.strip().splitlines()[-1:]
    assert (out / "scene.xml").is_file()


@pytest.mark.parametrize("grounded", _seeds("found"), indirect=True)
def test_every_object_found_and_no_extra_body(score: SceneScore) -> None:
    missing = [o.true_name for o in score.objects if not o.found]
    assert not missing, f"not found: {missing}"
    assert not score.extra_bodies, f"extra bodies: {score.extra_bodies}"


@pytest.mark.parametrize("grounded", _seeds("centres"), indirect=True)
def test_centres_within_5mm(score: SceneScore) -> None:
    for o in _found(score):
        assert o.centre_error_m <= 0.005, f"{o.true_name}: centre off by {o.centre_error_m * 1000:.1f} mm"


@pytest.mark.parametrize("grounded", _seeds("chamfer"), indirect=True)
def test_chamfer_within_4mm(score: SceneScore) -> None:
    for o in _found(score):
        assert o.chamfer_m <= 0.004, f"{o.true_name}: Chamfer {o.chamfer_m * 1000:.2f} mm"


@pytest.mark.parametrize("grounded", _seeds("extents"), indirect=True)
def test_extents_within_8_percent(score: SceneScore) -> None:
    for o in _found(score):
        assert o.extent_error <= 0.08, f"{o.true_name}: extents off by {o.extent_error:.1%}"


@pytest.mark.parametrize("grounded", _seeds("normals"), indirect=True)
def test_normals_agree_with_the_truth(score: SceneScore) -> None:
    for o in _found(score):
        assert o.normal_consistency >= 0.9, f"{o.true_name}: normal consistency {o.normal_consistency:.3f}"


@pytest.mark.parametrize("grounded", _seeds("topology"), indirect=True)
def test_topology_of_the_truth(score: SceneScore) -> None:
    for o in _found(score):
        assert o.euler_number == o.true_euler_number, (
            f"{o.true_name}: Euler {o.euler_number}, truth {o.true_euler_number}"
        )


@pytest.mark.parametrize("grounded", _seeds("cavity"), indirect=True)
def test_open_containers_keep_a_ball(score: SceneScore) -> None:
    for o in _found(score):
        if o.open_container:
            assert o.keeps_ball, f"{o.true_name}: a 1.5 cm ball dropped in did not stay in"


@pytest.mark.parametrize("grounded", _seeds("rest"), indirect=True)
def test_scene_at_rest(grounded: tuple[subprocess.CompletedProcess[str], Path, Path], score: SceneScore) -> None:
    _, _, out = grounded
    for name, motion in settle_test(out / "scene.xml", seconds=2.0).items():
        assert motion.displacement_m <= 0.002, f"{name} moved {motion.displacement_m * 1000:.2f} mm"
        assert motion.rotation_deg <= 1.0, f"{name} turned {motion.rotation_deg:.2f} deg"


def test_scoring_frame_leaves_out_misregistered_cameras() -> None:
    """Known-extent scenes are scored in the frame of a rigid fit of the camera centres. Family photo set 1005
    registered 2 of 29 photos 0.45-0.84 m from where they were: the plain fit then put the others 40-130 mm off
    and tilted the frame, and both found objects counted as extra bodies. The fit now leaves such cameras out."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from grounder.grounding.evaluate import robust_rigid_fit

    rng = np.random.default_rng(5)
    angles = rng.uniform(0, 2 * np.pi, 29)
    true = np.c_[0.6 * np.cos(angles), 0.6 * np.sin(angles), rng.uniform(0.2, 0.4, 29)]
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("zyx", [40, 3, -2], degrees=True).as_matrix()
    pose[:3, 3] = [0.1, -0.2, 0.05]
    grounded = (true - pose[:3, 3]) @ pose[:3, :3]  # pose maps grounded onto true
    grounded += rng.normal(0, 0.002, grounded.shape)  # 2 mm registration noise
    grounded[[4, 24]] += [[0.8, 0.2, 0.1], [-0.3, 0.35, 0.0]]  # two photos registered far off
    fitted, kept = robust_rigid_fit(grounded, true)
    assert kept.sum() == 27 and not kept[[4, 24]].any()
    assert np.abs(fitted - pose).max() < 0.01
    residual = np.linalg.norm(grounded[kept] @ fitted[:3, :3].T + fitted[:3, 3] - true[kept], axis=1)
    assert np.median(residual) < 0.004
