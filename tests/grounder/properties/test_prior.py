"""Learned physical-property embeddings (issue 5).

Acceptance: on held-out shapes and appearances the model's errors are at most 70% of a train-mean baseline's for
ln density and sliding friction, and its 90% intervals cover 80-97% of the truths; `scene.json` of the grounded
sample carries each object's embedding and spread; sampled scene variants differ and load.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import time
from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np
import pytest

import grounder
from grounder.grounding.evaluate import compare_to_truth
from grounder.properties.materials import MATERIALS, PhysicalProperties
from grounder.properties.prior import (
    WEIGHTS_DIR,
    decode_embedding,
    load_property_model,
    sample_scene_variants,
    sample_variant_specs,
)
from grounder.properties.training_data import crop_square, shape_features
from tests.conftest import CliRun, assert_one_line_error, run_cli

MEAN_KEYS = {"density_kg_m3", "friction", "solref", "restitution"}


# ---------------------------------------------------------------- material table and features


def test_material_table_ranges_are_cited_and_ordered() -> None:
    import grounder.properties.materials as table

    for m in MATERIALS:
        for low, high in (m.density_kg_m3, m.sliding, m.contact_radius_m, m.rolling_m, m.restitution, m.timeconst_s):
            assert 0 < low < high, m.name
        assert m.restitution[1] < 1
        assert m.timeconst_s[0] >= 2 * 0.002, "solref timeconst must stay >= 2 x the exported timestep"
        for source in m.sources:
            assert f"[{source}]" in (table.__doc__ or ""), f"{m.name} cites {source}, missing from the docstring"


def test_the_written_solref_bounces_at_the_predicted_restitution() -> None:
    # The drop test of an exported scene's contact, not a formula: what `ground` writes for a predicted restitution
    # must bounce at it (the textbook spring-damper mapping bounced 8-14% higher on samples/tabletop's objects).
    from grounder.sim.restitution import MIN_TIMECONST_STEPS, bounce_spread, restitution_over_phases
    from scene_export._mjcf import ExportOptions, SceneObjectSpec

    spec = mujoco.MjSpec()
    ExportOptions().set_physics(spec.option)
    option = spec.compile().opt
    floor_s = MIN_TIMECONST_STEPS * option.timestep
    for timeconst_s in (0.005, 0.0087, 0.02, 0.045):
        for e in (0.2, 0.4, 0.6, 0.75):
            props = PhysicalProperties(
                material="x", density_kg_m3=1000.0, friction=(0.5, 0.01, 0.001), restitution=e, timeconst_s=timeconst_s
            )
            written_s, dampratio = props.solref
            assert written_s == pytest.approx(max(timeconst_s, floor_s))  # stiffer than 6 steps is softened
            bounces = restitution_over_phases((written_s, dampratio), SceneObjectSpec.solimp, option)
            assert float(np.mean(bounces)) == pytest.approx(e, rel=0.05), (timeconst_s, e)
            assert bounce_spread(bounces) < 0.6, (timeconst_s, e)  # at 3-4 steps it reached 1-1.8
    # More restitution, less damping, at any time constant.
    ratios = [
        PhysicalProperties(
            material="x", density_kg_m3=1.0, friction=(0.5, 0.01, 0.001), restitution=e, timeconst_s=0.02
        ).solref[1]
        for e in (0.1, 0.3, 0.5, 0.7, 0.9)
    ]
    assert ratios == sorted(ratios, reverse=True)


def test_shape_features_of_a_box_and_a_bowl() -> None:
    import trimesh

    box = trimesh.creation.box(extents=[0.12, 0.08, 0.06])
    f = shape_features(box.vertices, box.faces)
    np.testing.assert_allclose(np.exp(f[:4]), [0.12, 0.08, 0.06, 0.12 * 0.08 * 0.06], rtol=1e-6)
    assert f[4] == pytest.approx(1.0, abs=1e-6) and f[5] == pytest.approx(1.0, abs=1e-6)
    assert math.exp(f[7]) == pytest.approx(2 * box.volume / box.area, rel=1e-6)
    # A bowl: its cavity makes it far from convex and thin-walled.
    profile = [(0, 0), (0.03, 0), (0.06, 0.05), (0.055, 0.05), (0.028, 0.005), (0, 0.005)]
    bowl = trimesh.creation.revolve(np.array(profile, dtype=float), sections=48)
    fb = shape_features(bowl.vertices, bowl.faces)
    assert fb[5] < 0.3 and math.exp(fb[7]) < 0.01


def test_crop_pads_outside_the_image_with_grey() -> None:
    image = np.zeros((40, 60, 3), np.uint8)
    crop = crop_square(image, (0.0, 0.0, 20.0), out_px=8)
    assert crop.shape == (8, 8, 3)
    assert (crop[0, 0] == 128).all() and (crop[-1, -1] == 0).all()


# ---------------------------------------------------------------- the shipped model


def test_shipped_weights_are_small_and_carry_their_recipe() -> None:
    size = sum(p.stat().st_size for p in WEIGHTS_DIR.iterdir() if p.is_file())
    assert size <= 5 * 1024 * 1024
    meta = load_property_model().meta
    assert meta["recipe"]["command"] == "image2sim properties train"
    assert meta["recipe"]["test_seed"] not in (
        meta["recipe"]["options"]["train_seed"],
        meta["recipe"]["options"]["val_seed"],
    )
    # `image2sim properties train` with its defaults is the recipe that made the shipped weights.
    from dataclasses import asdict

    from grounder.properties.network import TrainOptions

    assert meta["recipe"]["options"] == asdict(TrainOptions())


def test_decode_embedding_is_smooth_and_physical() -> None:
    model = load_property_model()
    rng = np.random.default_rng(0)
    z = rng.standard_normal(model.net.embed_dim)
    out = decode_embedding(z)
    assert MEAN_KEYS <= set(out) and set(out["spread"]) == MEAN_KEYS
    assert out["density_kg_m3"] > 0 and min(out["friction"]) > 0 and 0 < out["restitution"] < 1
    low, high = out["spread"]["density_kg_m3"]
    assert low < out["density_kg_m3"] < high
    assert sum(out["material_probs"].values()) == pytest.approx(1.0, abs=1e-9)
    # Smooth: central finite differences at two step sizes agree (no kinks or jumps).
    direction = rng.standard_normal(model.net.embed_dim)

    def ln_density(t: float) -> float:
        return math.log(decode_embedding(z + t * direction)["density_kg_m3"])

    slopes = [(ln_density(h) - ln_density(-h)) / (2 * h) for h in (1e-2, 1e-3)]
    assert slopes[0] == pytest.approx(slopes[1], rel=2e-2, abs=1e-3)
    with pytest.raises(grounder.GrounderError):
        decode_embedding(np.zeros(3))


@pytest.fixture(scope="module")
def heldout() -> dict[str, float]:
    """Figures on a reduced held-out set (200 renders of seed 5: shapes, textures, lights and cameras never trained
    on), through `image2sim properties evaluate --json`. The full figures (1000 objects, seed 3) are in
    docs/results/properties.md."""
    proc = run_cli("properties", "evaluate", "--json", "--num-samples", "200", "--seed", "5")
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads(proc.stdout)
    for key in ("density_mae_log", "baseline_density_mae_log", "friction_mae", "baseline_friction_mae", "coverage90"):
        assert key in figures
    return figures


def test_heldout_density_error_and_coverage(heldout: dict[str, float]) -> None:
    assert heldout["density_mae_log"] <= 0.7 * heldout["baseline_density_mae_log"], heldout
    # A fixed bound too, not only one relative to a baseline from the same run: measured 0.580 (2026-11-27)
    assert heldout["density_mae_log"] <= 0.70, heldout
    assert 0.8 <= heldout["coverage90"] <= 0.97, heldout


def test_heldout_friction_error(heldout: dict[str, float]) -> None:
    assert heldout["friction_mae"] <= 0.7 * heldout["baseline_friction_mae"], heldout
    assert heldout["friction_mae"] <= 0.125, heldout  # measured 0.107 (2026-11-27)


def test_cli_bad_input_exits_2(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    proc = cli("properties", "sample", str(tmp_path / "missing"), "-o", str(tmp_path / "out"))
    assert proc.returncode == 2
    assert [line for line in proc.stderr.splitlines() if line.startswith("image2sim: error:")], proc.stderr
    assert not (tmp_path / "out").exists()
    proc = cli("properties", "evaluate", "--seed", "1")
    assert proc.returncode == 2 and "training/calibration seed" in proc.stderr


def test_a_missing_model_folder_says_how_to_make_one_there(tmp_path: Path) -> None:
    """Not plain `image2sim properties train`, which would regenerate the package's own weights instead."""
    from grounder.properties.prior import load_property_model

    with pytest.raises(grounder.GrounderError) as info:
        load_property_model(tmp_path / "mine")
    assert str(info.value).endswith(f"make one there with `image2sim properties train -o {tmp_path / 'mine'}`")


def test_properties_help(cli: Callable[..., CliRun]) -> None:
    proc = cli("properties", "--help", timeout=60)
    assert proc.returncode == 0, proc.stderr
    for command in ("train", "evaluate", "sample"):
        assert command in proc.stdout
    from grounder.properties.network import TrainOptions

    proc = cli("properties", "train", "--help", timeout=60)
    assert proc.returncode == 0, proc.stderr
    text = " ".join(proc.stdout.replace("│", " ").split())  # rich wraps the help in a box
    defaults = TrainOptions()
    assert f"Rendered training objects (default {defaults.num_train})." in text, text
    assert f"Training epochs (default {defaults.epochs})." in text, text


# ---------------------------------------------------------------- integration with `ground`


@pytest.fixture(scope="module")
def grounded(grounded_tabletop: Path) -> Path:
    return grounded_tabletop  # the session's one grounded tabletop (tests/conftest.py)


def test_scene_json_carries_embedding_mean_and_spread(grounded: Path, tabletop_dir: Path) -> None:
    manifest = json.loads((grounded / "scene.json").read_text())
    truth = {o["name"]: o for o in json.loads((tabletop_dir / "truth" / "objects.json").read_text())["objects"]}
    matched = {e.name: e.true_name for e in compare_to_truth(grounded, tabletop_dir / "truth")}
    model = load_property_model()
    assert len(manifest["objects"]) == 3
    inside, right_material, friction_err, density_pairs = [], [], [], []
    for name, entry in manifest["objects"].items():
        props = entry["properties"]
        assert len(props["embedding"]) == len(props["embedding_std"]) == model.net.embed_dim
        assert min(props["embedding_std"]) > 0
        assert set(props["mean"]) == MEAN_KEYS and set(props["spread"]) == MEAN_KEYS
        assert props["model_version"] == model.version and props["views"] >= 2
        assert sum(props["material_probs"].values()) == pytest.approx(1.0, abs=1e-6)
        # The MJCF uses the decoded mean: mass = mesh volume x density, friction and solref on the hulls.
        mean = props["mean"]
        assert entry["density_kg_m3"] == pytest.approx(mean["density_kg_m3"], rel=1e-9)
        assert entry["mass_kg"] == pytest.approx(entry["volume_m3"] * mean["density_kg_m3"], rel=1e-6)
        np.testing.assert_allclose(entry["friction"], mean["friction"], rtol=1e-9)
        np.testing.assert_allclose(entry["solref"], mean["solref"], rtol=1e-9)
        decoded = decode_embedding(np.array(props["embedding"]))
        assert decoded["density_kg_m3"] == pytest.approx(mean["density_kg_m3"], rel=1e-6)
        low, high = props["spread"]["density_kg_m3"]
        assert low < mean["density_kg_m3"] < high
        true = truth[matched[name]]
        top = max(props["material_probs"], key=props["material_probs"].get)
        print(
            f"{matched[name]}: density {mean['density_kg_m3']:.0f} [{low:.0f}, {high:.0f}] kg/m^3 (true "
            f"{true['density_kg_m3']:.0f}), sliding {mean['friction'][0]:.2f} (true {true['friction'][0]:.2f}), "
            f"material {top} (true {true['material']})"
        )
        inside.append(low <= true["density_kg_m3"] <= high)
        right_material.append(top == true["material"])
        friction_err.append(abs(mean["friction"][0] - true["friction"][0]))
        density_pairs.append((true["density_kg_m3"], mean["density_kg_m3"]))
    # Against the truth (docs/results/properties.md: the can, metal at 900 kg/m^3, is read as cardboard at 193, outside
    # its interval; the box and bowl are right). Two of three inside their 90% intervals and classed right, sliding
    # friction within 0.1 on average (measured 0.07), and the densities in the true order (box < can < bowl).
    assert sum(inside) >= 2 and sum(right_material) >= 2, (inside, right_material)
    assert np.mean(friction_err) < 0.1, friction_err
    by_truth = sorted(density_pairs)
    assert all(a[1] < b[1] for a, b in itertools.pairwise(by_truth)), by_truth
    model_xml = mujoco.MjModel.from_xml_path(str(grounded / "scene.xml"))
    assert model_xml.nbody == 1 + len(manifest["objects"])


def test_sampled_variants_differ_and_load(grounded: Path, tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    models = sample_scene_variants(grounded, 4, seed=0)
    assert len(models) == 4
    bodies = [mujoco.mj_name2id(models[0], mujoco.mjtObj.mjOBJ_BODY, n) for n in ("object_0", "object_1")]
    masses = np.array([[m.body_mass[b] for b in bodies] for m in models])
    assert len(np.unique(masses.round(9), axis=0)) == 4
    hull = next(
        g for g in range(models[0].ngeom) if models[0].geom_contype[g] and models[0].geom_bodyid[g] == bodies[0]
    )
    frictions = [m.geom_friction[hull, 0] for m in models]
    assert len(set(np.round(frictions, 9))) == 4
    for m in models:
        data = mujoco.MjData(m)
        mujoco.mj_step(m, data, 50)
        assert np.isfinite(data.qpos).all()
    again = sample_scene_variants(grounded, 4, seed=0)
    np.testing.assert_array_equal([m.body_mass for m in again], [m.body_mass for m in models])
    # The draws follow the distribution scene.json states: per object, about 90% of 200 draws fall inside its 90%
    # interval (binomial sd 0.021), their median ln density is the stored transformed mean, and each drawn model's
    # mass is the mesh volume x the drawn density.
    manifest = json.loads((grounded / "scene.json").read_text())["objects"]
    draws = sample_variant_specs(grounded, 200, seed=1)
    for name, entry in manifest.items():
        density = np.array([drawn[name]["density_kg_m3"] for _, drawn in draws])
        low, high = entry["properties"]["spread"]["density_kg_m3"]
        inside = np.mean((density >= low) & (density <= high))
        assert 0.83 <= inside <= 0.96, (name, inside)
        mean_t, std_t = entry["properties"]["transformed"]["mean"][0], entry["properties"]["transformed"]["std"][0]
        assert abs(np.median(np.log(density)) - mean_t) < 0.3 * std_t, (name, np.median(np.log(density)), mean_t)
        for spec, drawn in draws[:3]:
            assert spec.body(name).mass == pytest.approx(entry["volume_m3"] * drawn[name]["density_kg_m3"], rel=1e-6)
    # The CLI writes them as MJCF next to a record of what was drawn.
    proc = cli("properties", "sample", str(grounded), "-n", "2", "-o", str(tmp_path / "variants"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    record = json.loads((tmp_path / "variants" / "variants.json").read_text())
    assert len(record["variants"]) == 2
    # Self-contained like every scene folder: it still loads when moved away from the scene it was drawn from.
    moved = (tmp_path / "variants").rename(tmp_path / "elsewhere")
    for v in record["variants"]:
        model = mujoco.MjModel.from_xml_path(str(moved / v["xml"]))
        assert model.nbody == len(models[0].body_mass)


# ---------------------------------------------------------------- malformed inputs (audit)


def _tiny_scene(folder: Path, entry: object) -> Path:
    """A scene folder with one free box `object_0` and a scene.json whose `objects.object_0` is `entry`."""
    folder.mkdir()
    (folder / "scene.xml").write_text(
        '<mujoco><worldbody><body name="object_0" pos="0 0 0.1"><freejoint/>'
        '<inertial pos="0 0 0" mass="0.125" diaginertia="2e-4 2e-4 2e-4"/>'
        '<geom type="box" size="0.05 0.05 0.05"/></body></worldbody></mujoco>'
    )
    (folder / "scene.json").write_text(json.dumps({"format": "image2sim.scene/1", "objects": {"object_0": entry}}))
    return folder


def _entry(**changes: object) -> dict[str, object]:
    transformed = {"mean": [7.0, -0.7, -7.0, -9.0, -0.5, -4.0], "std": [0.5, 0.2, 0.5, 0.8, 0.4, 0.3]}
    entry: dict[str, object] = {"density_kg_m3": 1000.0, "properties": {"transformed": transformed}}
    for key, value in changes.items():
        if key in ("mean", "std"):
            transformed[key] = value
        else:
            entry[key] = value
    return entry


@pytest.mark.parametrize(
    ("manifest", "field"),
    [
        ([1, 2], "the top level"),
        ({"objects": [1]}, "objects must"),
        ({"objects": {"object_0": "x"}}, "objects.object_0 must"),
        ({"objects": {"object_0": {"density_kg_m3": 1000.0, "properties": "x"}}}, "objects.object_0.properties must"),
        ({"objects": {"object_0": _entry(std="abc")}}, "objects.object_0.properties.transformed.std"),
        ({"objects": {"object_0": _entry(std=[0.5, 0.2, 0.5, 0.8, 0.4, 0.0])}}, "transformed.std must be positive"),
        ({"objects": {"object_0": _entry(mean=[1000.0] * 6)}}, "objects.object_0.properties.transformed.mean"),
        ({"objects": {"object_0": _entry(mean=[1.0])}}, "objects.object_0.properties.transformed.mean"),
        ({"objects": {"object_0": _entry(mean=[math.nan] * 6)}}, "objects.object_0.properties.transformed.mean"),
        ({"objects": {"object_0": _entry(density_kg_m3=0)}}, "objects.object_0.density_kg_m3"),
        ({"objects": {"object_0": _entry(density_kg_m3="heavy")}}, "objects.object_0.density_kg_m3"),
        ({"objects": {"object_0": _entry(density_kg_m3=math.nan)}}, "objects.object_0.density_kg_m3"),
        ({"objects": {"object_0": {"density_kg_m3": 1000.0}}}, "no object has predicted properties"),
    ],
)
def test_sampling_rejects_a_malformed_scene_json(tmp_path: Path, manifest: object, field: str) -> None:
    scene = _tiny_scene(tmp_path / "scene", _entry())
    assert len(sample_variant_specs(scene, 2, seed=0)) == 2  # the well-formed scene samples
    (scene / "scene.json").write_text(json.dumps(manifest))
    with pytest.raises(grounder.GrounderError) as info:
        sample_variant_specs(scene, 2, seed=0)
    message = str(info.value)
    assert "\n" not in message and str(scene / "scene.json") in message and field in message, message
    assert "image2sim ground" in message, message


def test_sampling_keeps_draws_finite_and_cli_rejects_bad_scene_json(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    # A very wide (but finite) stored spread: every drawn value stays finite and the variants compile.
    wide = _tiny_scene(tmp_path / "wide", _entry(std=[1e6] * 6))
    for spec, drawn in sample_variant_specs(wide, 8, seed=0):
        values = drawn["object_0"]
        assert all(math.isfinite(v) for v in [values["density_kg_m3"], *values["friction"], *values["solref"]])
        assert spec.compile().body_mass[1] == pytest.approx(0.125 * values["density_kg_m3"] / 1000.0, rel=1e-9)
    # Objects without `properties` keep their values, beside one that has them; a scene where none has them would
    # give identical variants, and is refused.
    mixed = _tiny_scene(tmp_path / "mixed", _entry())
    xml = (mixed / "scene.xml").read_text()
    second = xml[xml.index('<body name="object_0"') : xml.index("</worldbody>")].replace("object_0", "object_1")
    (mixed / "scene.xml").write_text(xml.replace("</worldbody>", second + "</worldbody>"))
    manifest = json.loads((mixed / "scene.json").read_text())
    manifest["objects"]["object_1"] = {"density_kg_m3": 1000.0}
    (mixed / "scene.json").write_text(json.dumps(manifest))
    (spec, drawn), *_ = sample_variant_specs(mixed, 1)
    assert set(drawn) == {"object_0"} and spec.body("object_1").mass == pytest.approx(0.125)
    plain = _tiny_scene(tmp_path / "plain", {"density_kg_m3": 1000.0})
    with pytest.raises(grounder.GrounderError, match="no object has predicted properties to draw from"):
        sample_variant_specs(plain, 1)
    # Through the CLI: one line, exit 2, nothing written.
    bad = _tiny_scene(tmp_path / "bad", _entry(density_kg_m3=0))
    proc = cli("properties", "sample", str(bad), "-o", str(tmp_path / "out"), timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.count("\n") == 1 and "objects.object_0.density_kg_m3" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "out").exists()
    # A scene.xml MuJoCo rejects (well-formed XML, an unknown geom type) was a ValueError traceback.
    xml = bad / "scene.xml"
    xml.write_text(xml.read_text().replace('type="box"', 'type="bogus"', 1))
    assert 'type="bogus"' in xml.read_text()
    (bad / "scene.json").write_text(json.dumps({"objects": {"object_0": _entry()}}))
    proc = cli("properties", "sample", str(bad), "-o", str(tmp_path / "out"), timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.count("\n") == 1 and "scene.xml: MuJoCo cannot load it (XML Error" in proc.stderr, proc.stderr


def test_sample_refuses_a_scene_folder_it_cannot_copy_whole(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    """A mesh the MJCF loads but the folder lacks was found only while copying it (a traceback, exit 1); the folder
    itself, a path that is not there and the MJCF passed in its place are each named for what they are."""
    scene = _tiny_scene(tmp_path / "scene", _entry())
    (scene / "assets").mkdir()
    (scene / "assets" / "object_0.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    )
    xml = (scene / "scene.xml").read_text()
    xml = xml.replace("<worldbody>", '<asset><mesh name="m" file="assets/object_0.obj"/></asset><worldbody>')
    (scene / "scene.xml").write_text(
        xml.replace("</body>", '<geom type="mesh" mesh="m" contype="0" conaffinity="0"/></body>')
    )
    out = tmp_path / "out"
    proc = cli("properties", "sample", str(scene), "-n", "1", "-o", str(out), timeout=120)
    assert proc.returncode == 0 and (out / "assets" / "object_0.obj").is_file(), proc.stderr[-2000:]
    (scene / "assets" / "object_0.obj").unlink()
    proc = cli("properties", "sample", str(scene), "-o", str(tmp_path / "out2"), timeout=120)
    assert_one_line_error(proc, "MuJoCo cannot load it", "object_0.obj", alone=True)
    assert not (tmp_path / "out2").exists()
    (scene / "scene.json").unlink()
    proc = cli("properties", "sample", str(scene), "-o", str(tmp_path / "out2"), timeout=120)
    assert_one_line_error(proc, "has no scene.json;", alone=True)
    proc = cli("properties", "sample", str(tmp_path / "nope"), "-o", str(tmp_path / "out2"), timeout=120)
    assert_one_line_error(proc, "nope does not exist", alone=True)
    proc = cli("properties", "sample", str(scene / "scene.xml"), "-o", str(tmp_path / "out2"), timeout=120)
    assert_one_line_error(proc, "scene.xml is a file; pass the scene folder", alone=True)
    assert not (tmp_path / "out2").exists()


def _copied_weights(folder: Path, **changes: object) -> Path:
    """The shipped weights in `folder` with top-level or `normalisation` metadata fields replaced."""
    from grounder.properties.network import META_FILE, WEIGHTS_FILE

    folder.mkdir()
    (folder / WEIGHTS_FILE).write_bytes((WEIGHTS_DIR / WEIGHTS_FILE).read_bytes())
    meta = json.loads((WEIGHTS_DIR / META_FILE).read_text())
    for key, value in changes.items():
        if key in meta["normalisation"]:
            meta["normalisation"][key] = value
        else:
            meta[key] = value
    (folder / META_FILE).write_text(json.dumps(meta))
    return folder


def test_weights_metadata_is_checked_against_the_tensors_before_building(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import grounder.properties.network as _properties_model
    from grounder.properties.model_files import PropertyModelError

    built: list[int] = []
    real_net = _properties_model.PropertyNet

    def spy(embed_dim: int = 16) -> object:
        built.append(embed_dim)
        if embed_dim != 16:  # stands in for the gigabytes the network of this size would take
            raise MemoryError
        return real_net(embed_dim)

    monkeypatch.setattr(_properties_model, "PropertyNet", spy)
    assert load_property_model(_copied_weights(tmp_path / "ok")).net.embed_dim == 16
    with pytest.raises(PropertyModelError) as info:
        load_property_model(_copied_weights(tmp_path / "embed", embed_dim=4_000_000))
    message = str(info.value)
    assert built == [16], built  # the oversized network was never built
    assert "property_net.json" in message and "embed_dim" in message and "image2sim properties train" in message
    assert "\n" not in message, message
    for field, value in (("embed_dim", "16"), ("target_std", [1.0] * 5), ("spread_scale", [1.0] * 5 + [-1.0])):
        with pytest.raises(PropertyModelError, match=field):
            load_property_model(_copied_weights(tmp_path / f"bad_{field}", **{field: value}))


@pytest.mark.parametrize("kind", ["sparse", "meta (no data)", "complex", "integer"])
def test_weights_that_are_not_plain_real_tensors_are_refused(tmp_path: Path, kind: str) -> None:
    """torch loads these safely; before, a sparse or meta tensor failed in the network with a traceback (or an error
    naming no tensor), and complex or integer weights were copied into the network as their real part or as whole
    numbers, with only a warning."""
    import torch

    from grounder.properties.model_files import PropertyModelError
    from grounder.properties.network import WEIGHTS_FILE, load

    weights = _copied_weights(tmp_path / "w")
    state = torch.load(weights / WEIGHTS_FILE, weights_only=True)
    load(weights)  # the control: the shipped tensors load
    key = "z_head.weight"
    state[key] = {
        "sparse": lambda t: t.to_sparse(),
        "meta (no data)": lambda t: t.to("meta"),
        "complex": lambda t: t.to(torch.complex128) * (1 + 1e-3j),
        "integer": lambda t: (t * 1000).to(torch.int64),
    }[kind](state[key])
    torch.save(state, weights / WEIGHTS_FILE)
    expected = "has dtype torch.int64, expected torch.float32" if kind == "integer" else f"is a {kind} tensor"
    for loader in (load, load_property_model):
        with pytest.raises(PropertyModelError, match=rf"tensor {re.escape(key)} {re.escape(expected)}[;,]"):
            loader(weights)


def test_non_finite_normalisation_is_refused_by_evaluate(tmp_path: Path, cli: Callable[..., CliRun]) -> None:
    from grounder.properties.network import load

    weights = _copied_weights(tmp_path / "nan", target_std=[math.nan] * 6)
    with pytest.raises(grounder.GrounderError, match=r"property_net\.json: normalisation\.target_std"):
        load(weights)
    proc = cli("properties", "evaluate", "--weights", str(weights), "--num-samples", "10", timeout=120)
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr[-2000:])
    assert proc.stderr.count("\n") == 1 and "normalisation.target_std" in proc.stderr, proc.stderr
    assert "regenerate with `image2sim properties train" in proc.stderr and "MAE" not in proc.stdout


HUGE = str(10**20)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["train", "--num-train", HUGE, "--epochs", "1"], f"--num-train {HUGE} must be between 100 and 50000"),
        (["train", "--num-train", "50001"], "--num-train 50001 must be between 100 and 50000"),
        (["train", "--num-train", "99"], "--num-train 99 must be between 100 and 50000"),
        (["train", "--num-train", "100", "--epochs", HUGE], f"--epochs {HUGE} must be between 1 and 1000"),
        (["train", "--num-train", "100", "--epochs", "1001"], "--epochs 1001 must be between 1 and 1000"),
        (["evaluate", "--num-samples", HUGE], f"--num-samples {HUGE} must be between 10 and 100000"),
        (["evaluate", "--num-samples", "100001"], "--num-samples 100001 must be between 10 and 100000"),
    ],
)
def test_counts_too_large_to_finish_are_refused_before_any_work(
    args: list[str], needle: str, tmp_path: Path, cli: Callable[..., CliRun]
) -> None:
    """--num-train or --num-samples 1e20 was numpy's 'Maximum allowed dimension exceeded' traceback after loading
    (exit 1), and 1e5 or 1e6 would allocate 4-37 GB of crops up front; --epochs 1e20 trained without end."""
    out = tmp_path / "weights"
    command = ["properties", *args, *(["-o", str(out)] if args[0] == "train" else [])]
    tick = time.perf_counter()
    proc = cli(*command, timeout=60)  # a run that starts working fails by its timeout, not by hanging
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("image2sim: error: "), proc.stderr
    assert needle in lines[0], lines[0]
    assert time.perf_counter() - tick < 30 and not out.exists() and not proc.stdout


def test_train_options_and_dataset_refuse_sizes_that_cannot_finish() -> None:
    """The library checks what the CLI checks: Python callers get one GrounderError, before any allocation."""
    from grounder.properties.network import MAX_EPOCHS, MAX_NUM_TRAIN, TrainOptions, evaluate
    from grounder.properties.training_data import MAX_SAMPLES, generate_dataset

    for kwargs in (
        {"num_train": 10**20},
        {"num_train": MAX_NUM_TRAIN + 1},
        {"num_val": MAX_SAMPLES + 1},
        {"epochs": 10**20},
        {"epochs": MAX_EPOCHS + 1},
        {"epochs": 0},
        {"epochs": 2.5},
        {"batch_size": 0},
        {"learning_rate": math.nan},
        {"torch_seed": -1},
    ):
        name = next(iter(kwargs))
        with pytest.raises(grounder.GrounderError, match=rf"TrainOptions\.{name}=.* but expected"):
            TrainOptions(**kwargs)  # type: ignore[arg-type]
    TrainOptions(num_train=MAX_NUM_TRAIN, epochs=MAX_EPOCHS)  # the bounds themselves are allowed
    for n in (10**20, MAX_SAMPLES + 1, 0, True):
        with pytest.raises(grounder.GrounderError, match=rf"num_samples={n!r} but expected an integer between 1 and"):
            generate_dataset(n, 3)
    with pytest.raises(grounder.GrounderError, match=r"num_samples=100000000000000000000 but expected"):
        evaluate(WEIGHTS_DIR, num_samples=10**20)


def test_saving_weights_that_fails_midway_keeps_the_old_pair(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`save` replaced the weights, then the metadata: a failure between them left new weights beside old metadata.
    Both are now written in full first; a failure writing the metadata leaves the old pair and no temporary file."""
    import grounder.properties.network as _properties_model
    from grounder.properties.network import META_FILE, WEIGHTS_FILE, PropertyNet

    folder = _copied_weights(tmp_path / "weights")
    before = {name: (folder / name).read_bytes() for name in (WEIGHTS_FILE, META_FILE)}

    def full_disk(self: Path, *args: object, **kwargs: object) -> int:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    with pytest.raises(OSError, match="No space left"):
        _properties_model.save(PropertyNet(), {"format": 1}, folder)
    assert {name: (folder / name).read_bytes() for name in (WEIGHTS_FILE, META_FILE)} == before
    assert sorted(p.name for p in folder.iterdir()) == sorted(before)
