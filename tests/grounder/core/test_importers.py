"""Importing the real cube tosses: column mapping onto the free joint, 148 Hz timing, names, bad input."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from grounder.core.importers import load_dair_pll_cube
from grounder.core.trajectory import load_trajectories
from grounder.errors import GrounderError

REPO = Path(__file__).resolve().parents[3]
CUBE_XML = REPO / "samples" / "cube_toss" / "cube.xml"
SHARED_CUBE = Path(__file__).resolve().parents[4] / "shared" / "data" / "cube_toss"


def _toss(rows: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(rows, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    data = np.concatenate([quat, rng.normal(size=(rows, 9))], axis=1)
    return torch.from_numpy(data)


@pytest.fixture()
def fake_tosses(tmp_path: Path) -> Path:
    tosses = tmp_path / "cube_toss" / "tosses"
    tosses.mkdir(parents=True)
    for n, rows in ((10, 5), (2, 4), (7, 6)):
        torch.save(_toss(rows, n), tosses / f"{n}.pt")
    (tosses / "notes.txt").write_text("ignored")
    return tosses.parent


def test_column_mapping_and_timing(fake_tosses: Path) -> None:
    trajs = load_dair_pll_cube(fake_tosses)
    assert [t.name for t in trajs] == ["2", "7", "10"]  # numeric order, not string order
    raw = torch.load(fake_tosses / "tosses" / "7.pt", weights_only=True).numpy()
    t = trajs[1]
    np.testing.assert_allclose(t.time_s, np.arange(6) / 148.0)
    np.testing.assert_allclose(t.qpos[:, :3], raw[:, 4:7])  # position
    np.testing.assert_allclose(t.qpos[:, 3:], raw[:, 0:4], atol=1e-12)  # quaternion w-first
    np.testing.assert_allclose(t.qvel[:, :3], raw[:, 10:13])  # world linear velocity
    np.testing.assert_allclose(t.qvel[:, 3:], raw[:, 7:10])  # body angular velocity
    # Passing the tosses folder itself gives the same.
    assert [x.name for x in load_dair_pll_cube(fake_tosses / "tosses")] == ["2", "7", "10"]


def test_bad_input(tmp_path: Path) -> None:
    with pytest.raises(GrounderError, match="does not exist"):
        load_dair_pll_cube(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(GrounderError, match="no toss files"):
        load_dair_pll_cube(tmp_path / "empty")
    bad = tmp_path / "bad"
    bad.mkdir()
    torch.save(torch.zeros(5, 12, dtype=torch.float64), bad / "1.pt")
    with pytest.raises(GrounderError, match=r"expected shape \(T >= 2, 13\)"):
        load_dair_pll_cube(bad)
    torch.save(torch.ones(5, 13, dtype=torch.float64), bad / "1.pt")
    with pytest.raises(GrounderError, match="quaternion"):
        load_dair_pll_cube(bad)
    import pickle
    import warnings

    (bad / "1.pt").write_bytes(pickle.dumps([1, 2], protocol=4))  # a plain pickle: torch warns before failing
    with warnings.catch_warnings(record=True) as caught_warnings:
        warnings.simplefilter("always")
        with pytest.raises(GrounderError, match="not a tensor file torch loads safely"):
            load_dair_pll_cube(bad)
    assert not [w for w in caught_warnings if "pickle" in str(w.message)]  # nothing printed ahead of the one line
    (bad / "1.pt").write_text("not a tensor")  # torch's own message runs over lines and suggests an unsafe load
    with pytest.raises(GrounderError, match="not a tensor file torch loads safely") as caught:
        load_dair_pll_cube(bad)
    assert "\n" not in str(caught.value) and "weights_only" not in str(caught.value)


@pytest.mark.filterwarnings("ignore::UserWarning")  # torch: nested and quantized tensors are prototype or deprecated
@pytest.mark.parametrize("kind", ["sparse", "nested", "meta (no data)", "quantized", "complex", "bits16"])
def test_unusual_tensors_are_one_error(kind: str, tmp_path: Path) -> None:
    """Tensors torch loads safely but that are not plain data: before, a traceback from .numpy() (sparse, nested,
    meta, quantized, bits16) or, for complex values, the imaginary part dropped with only a warning and exit 0."""
    good = _toss(5, 0)
    tensor = {
        "sparse": lambda: good.to_sparse(),
        "nested": lambda: torch.nested.nested_tensor([good, good[:3]]),
        "meta (no data)": lambda: good.to("meta"),
        "quantized": lambda: torch.quantize_per_tensor(good.float(), 0.1, 0, torch.qint8),
        "complex": lambda: good.to(torch.complex128) * (1 + 1e-3j),
        "bits16": lambda: torch.zeros(10, 26, dtype=torch.uint8).view(torch.bits16),
    }[kind]()
    (tmp_path / "tosses").mkdir()
    torch.save(tensor, tmp_path / "tosses" / "1.pt")
    with pytest.raises(
        GrounderError,
        match=rf"1\.pt: the toss (is a {re.escape(kind)} tensor, not a dense real one|has dtype torch\.{kind}, which "
        "holds no numbers to read); expected a dense real tensor",
    ):
        load_dair_pll_cube(tmp_path)


def test_cli_import(fake_tosses: Path, tmp_path: Path) -> None:
    out = tmp_path / "npz"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "grounder.cli",
            "import-trajectories",
            "--format",
            "dair-pll-cube",
            str(fake_tosses),
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    trajs = load_trajectories(out, model)
    assert [t.name for t in trajs] == ["2", "7", "10"]
    from typer.testing import CliRunner

    from grounder.cli import app

    result = CliRunner().invoke(app, ["import-trajectories", str(tmp_path / "nothing"), "-o", str(tmp_path / "x")])
    assert result.exit_code == 2 and result.output.count("image2sim: error:") == 1, result.output
    assert "does not exist" in result.output and not (tmp_path / "x").exists()


def test_real_tosses() -> None:
    if not (SHARED_CUBE / "tosses").is_dir():
        pytest.skip(f"real cube tosses not available ({SHARED_CUBE} is absent)")
    trajs = load_dair_pll_cube(SHARED_CUBE)
    assert len(trajs) == 400
    assert all(85 <= t.num_steps <= 139 for t in trajs)
    assert trajs[0].name == "0" and int(trajs[-1].name) > int(trajs[-2].name)
    model = mujoco.MjModel.from_xml_path(str(CUBE_XML))
    # Every sample falls on a model step: 148 Hz is 8 steps of 1/1184 s.
    assert model.opt.timestep * 148 * 8 == pytest.approx(1.0)
    # The README's quirk: the cube rests at about 0.978 of its half-edge.
    rest_z = np.median([t.qpos[-1, 2] for t in trajs])
    assert rest_z == pytest.approx(0.978 * 0.0524, abs=0.0005)
    # The cube in the model has the README's size and mass.
    cube = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "cube")
    assert model.body_mass[cube] == pytest.approx(0.37)
    assert 2 * model.geom_size[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "cube"), 0] == pytest.approx(0.1048)
