"""``calibrate --distribution``, ``rollout --samples`` and ``randomize`` on a case with a known answer: tosses whose
friction and damping ratio vary from toss to toss with a known mean and spread (`grounder.calibration.known_case`)."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from grounder.calibration.known_case import VARYING, varying_tosses
from grounder.core.trajectory import load_trajectories, save_trajectories

SEED = 7  # the benchmark's known-answer seeds are 101 and up


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The known case calibrated with a small budget and its distribution fitted (the defaults of the fit)."""
    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions

    root = tmp_path_factory.mktemp("distribution")
    case = varying_tosses(30, SEED)
    (root / "cube.xml").write_text(case.xml)
    save_trajectories(case.trajectories, root / "trajs")
    options = CalibrateOptions(
        params=VARYING, validation_fraction=0.0, generations=1, popsize=4, local_iterations=0, distribution=True
    )
    result = calibrate(root / "cube.xml", case.trajectories, options=options, out=root / "cal")
    return {"root": root, "case": case, "result": result}


def test_fitted_distribution_recovers_the_known_mean_and_spread(calibrated: dict) -> None:
    from grounder.calibration.distribution import read_distribution

    case, out = calibrated["case"], calibrated["root"] / "cal"
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    dist = read_distribution(out / "distribution.json", model.nv)
    assert dist.names == VARYING
    drawn = dist.draw_values(dist.parameters(model), 4000, np.random.default_rng(0))
    true_mean, true_std = case.values.mean(axis=0), case.values.std(axis=0)
    np.testing.assert_allclose(drawn.mean(axis=0), true_mean, rtol=0.2)
    np.testing.assert_allclose(drawn.std(axis=0), true_std, rtol=0.2)
    # the recordings were exact: no start noise worth the name (velocities within a few mm/s of a quadratic fit)
    assert np.all(dist.start_noise.pose_std < 1e-3)
    summary = json.loads((out / "distribution.json").read_text())["summary"]
    assert [row["name"] for row in summary] == list(VARYING)
    report = (out / "report.html").read_text()
    assert "Parameter distribution" in report and "50% bands cover" in report


def test_sampled_rollouts_write_the_median_and_the_fan(calibrated: dict, cli, tmp_path: Path) -> None:
    root = calibrated["root"]
    run = cli("rollout", str(root / "cal"), str(root / "trajs"), "-o", str(tmp_path / "roll"), "--samples", "6")
    assert run.returncode == 0, run.stderr
    medians = load_trajectories(tmp_path / "roll")  # the fans beside them are not read as trajectories
    assert len(medians) == 30
    fan = np.load(tmp_path / "roll" / "toss_000.samples.npz")
    assert fan["qpos"].shape == (6, 100, 7) and fan["qvel"].shape == (6, 100, 6) and fan["time"].shape == (100,)
    np.testing.assert_allclose(medians[0].qpos[:, :3], np.median(fan["qpos"][:, :, :3], axis=0))
    assert np.ptp(fan["qpos"][:, -1, 0]) > 1e-3  # the samples differ (friction and bounce drawn per sample)
    again = cli("rollout", str(root / "cal"), str(root / "trajs"), "-o", str(tmp_path / "again"), "--samples", "6")
    assert again.returncode == 0
    np.testing.assert_array_equal(np.load(tmp_path / "again" / "toss_000.samples.npz")["qpos"], fan["qpos"])
    # without a distribution: one line, exit 2, nothing written
    bare = cli("rollout", str(root / "cube.xml"), str(root / "trajs"), "-o", str(tmp_path / "bare"), "--samples", "4")
    assert bare.returncode == 2 and "distribution.json" in bare.stderr and "Traceback" not in bare.stderr
    assert not (tmp_path / "bare").exists()


def test_randomize_draws_variants_from_the_fitted_distribution(calibrated: dict, cli, tmp_path: Path) -> None:
    root = calibrated["root"]
    run = cli("randomize", str(root / "cal"), "-o", str(tmp_path / "dr"), "-n", "40", "--seed", "3")
    assert run.returncode == 0, run.stderr
    record = json.loads((tmp_path / "dr" / "variants.json").read_text())
    frictions = []
    for row in record["variants"]:
        model = mujoco.MjModel.from_xml_path(str(tmp_path / "dr" / row["xml"]))
        cube_geom = int(np.argmax(model.geom_bodyid == 1))
        assert model.geom_friction[cube_geom, 0] == pytest.approx(row["parameters"]["cube.friction.sliding"], rel=1e-5)
        frictions.append(row["parameters"]["cube.friction.sliding"])
    case = calibrated["case"]
    assert np.std(frictions) == pytest.approx(case.values[:, 0].std(), rel=0.35)  # 40 draws: a loose check
    bad = cli("randomize", str(root / "cube.xml"), "-o", str(tmp_path / "none"))
    assert bad.returncode == 2 and "distribution.json" in bad.stderr


def test_a_damaged_distribution_file_is_refused_in_one_line(calibrated: dict, cli, tmp_path: Path) -> None:
    import shutil

    scene = tmp_path / "scene"
    shutil.copytree(calibrated["root"] / "cal", scene)
    data = json.loads((scene / "distribution.json").read_text())
    for damage in (
        lambda d: d.update(cov_unit=[[1.0, 2.0], [2.0, 1.0]]),  # not positive semi-definite
        lambda d: d.update(mean_unit=[0.5]),
        lambda d: d["start_noise"].update(pose_std=[-1.0] * 6),
        lambda d: d.update(format="something else"),
    ):
        broken = json.loads(json.dumps(data))
        damage(broken)
        (scene / "distribution.json").write_text(json.dumps(broken))
        run = cli("randomize", str(scene), "-o", str(tmp_path / "out"))
        assert run.returncode == 2, run.stderr
        assert "distribution.json" in run.stderr and "Traceback" not in run.stderr
        assert not (tmp_path / "out").exists()


def test_distribution_options_are_checked_before_any_work(calibrated: dict, cli, tmp_path: Path) -> None:
    root = calibrated["root"]
    base = ("calibrate", str(root / "cube.xml"), str(root / "trajs"), "-o", str(tmp_path / "out"), "--distribution")
    for extra, needle in (
        (("--params", "cube.friction.sliding", "--distribution-params", "cube.mass"), "cube.mass"),
        (("--distribution-samples", "2"), "--distribution-samples"),
        (("--distribution-centre", "middle"), "--distribution-centre"),
    ):
        run = cli(*base, *extra)
        assert run.returncode == 2 and needle in run.stderr and "Traceback" not in run.stderr, run.stderr
        assert "global search" not in run.stderr  # refused before the calibration ran
        assert not (tmp_path / "out").exists()
