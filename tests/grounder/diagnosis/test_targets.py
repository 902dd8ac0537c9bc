"""Effects on one body or one contact pair: the prepared model (explicit pairs with MuJoCo's mixed values) simulates as
the nominal one does, and a localised effect changes what it names and nothing else, with the consequence a formula
predicts."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from grounder import Trajectory
from grounder.diagnosis.benchmark import same_place
from grounder.diagnosis.cases import MULTI_BODY, SCENES, make_case
from grounder.diagnosis.effects import LIBRARY, AppliedEffect, apply_effects, parse_target, resolve_effects
from grounder.diagnosis.targets import (
    Layout,
    body_target,
    contacts_at_samples,
    find_layout,
    pair_rows,
    pair_target,
    possible_pairs,
    prepare,
    prepared_spec,
)
from grounder.errors import GrounderError

GRAVITY = 9.81

# Two boxes with different contact values, so that mixing shows: box_a's friction is the larger against the floor,
# the floor's against box_b; the solrefs average (solmix 1 each).
MIXED_XML = """<mujoco><option timestep="0.002"/><worldbody>
<geom name="floor" type="plane" size="5 5 0.1" friction="0.6 0.005 0.0001" solref="0.02 1"/>
<body name="box_a" pos="-0.3 0 0.05"><freejoint/>
  <geom type="box" size="0.05 0.05 0.05" mass="0.5" friction="0.9 0.01 0.0001" solref="0.04 0.5"/></body>
<body name="box_b" pos="0.3 0 0.04"><freejoint/>
  <geom name="gb" type="box" size="0.04 0.04 0.04" mass="0.3" friction="0.3 0.005 0.0001"/></body>
</worldbody></mujoco>"""


def _slide(model: mujoco.MjModel, speed_m_s: float = 1.5, seconds: float = 1.0) -> np.ndarray:
    """(2, 3) final positions of the two boxes launched apart along x from rest on the floor."""
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    data.qpos[2], data.qpos[9] = 0.05 - 1e-4, 0.04 - 1e-4
    data.qvel[0], data.qvel[6] = -speed_m_s, speed_m_s
    mujoco.mj_step(model, data, nstep=round(seconds / model.opt.timestep))
    return np.array([data.qpos[0:3], data.qpos[7:10]])


def _prepared(xml: str) -> mujoco.MjModel:
    nominal = mujoco.MjModel.from_xml_string(xml)
    layout = Layout(bodies=("box_a", "box_b"), pairs=possible_pairs(nominal))
    return prepared_spec(mujoco.MjSpec.from_string(xml), nominal, layout).compile()


def test_explicit_pairs_carry_mujocos_mixed_values_and_simulate_the_same() -> None:
    nominal = mujoco.MjModel.from_xml_string(MIXED_XML)
    prepared = _prepared(MIXED_XML)
    assert possible_pairs(nominal) == (("box_a", "box_b"), ("box_a", "floor"), ("box_b", "floor"))
    rows = pair_rows(prepared, pair_target("box_a", "floor"))
    assert len(rows) == 1
    assert prepared.pair_friction[rows[0]] == pytest.approx([0.9, 0.9, 0.01, 0.0001, 0.0001])
    assert prepared.pair_solref[rows[0]] == pytest.approx([0.03, 0.75])  # mean of (0.04, 0.5) and (0.02, 1)
    rows_b = pair_rows(prepared, pair_target("box_b", "floor"))
    assert prepared.pair_friction[rows_b[0], 0] == pytest.approx(0.6)
    assert _slide(prepared) == pytest.approx(_slide(nominal), abs=1e-6)


def test_contact_pairs_are_found_at_the_recorded_states() -> None:
    case = make_case(next(c for c in MULTI_BODY if c.scenario == "stack"), num_trajectories=2, duration_s=0.3)
    model = mujoco.MjModel.from_xml_string(case.scene_xml)
    layout = find_layout(model, [contacts_at_samples(model, t) for t in case.trajectories])
    assert set(layout.pairs) == {("box_a", "box_b"), ("box_a", "floor"), ("box_c", "floor")}
    assert layout.localised


def test_sliding_friction_on_one_body_changes_that_body_only() -> None:
    """A box launched at v on a floor of friction mu stops after v^2 / (2 mu g)."""
    prepared = _prepared(MIXED_XML)
    effect = LIBRARY["sliding_friction"].at(body_target("box_b"))
    assert effect.key == "sliding_friction@box_b"
    out, _ = apply_effects(prepared, [AppliedEffect(effect=effect, values={"mu": 0.15})])
    before, after = _slide(prepared), _slide(out)
    assert after[0] == pytest.approx(before[0], abs=1e-9)  # box_a untouched
    travel = after[1, 0] - 0.3
    assert travel == pytest.approx(1.5**2 / (2 * 0.15 * GRAVITY), rel=0.03)
    assert before[1, 0] - 0.3 == pytest.approx(1.5**2 / (2 * 0.6 * GRAVITY), rel=0.03)  # the floor's 0.6 won before
    assert prepared.geom_friction[2, 0] == pytest.approx(0.3)  # nominal model left alone


def test_sliding_friction_on_one_pair_changes_that_pair_only() -> None:
    prepared = _prepared(MIXED_XML)
    effect = LIBRARY["sliding_friction"].at(pair_target("floor", "box_a"))
    assert effect.key == "sliding_friction@box_a|floor"
    assert effect.nominal_of(prepared) == {"mu": pytest.approx(0.9)}
    out, _ = apply_effects(prepared, [AppliedEffect(effect=effect, values={"mu": 0.2})])
    changed = np.flatnonzero(~np.isclose(out.pair_friction[:, 0], prepared.pair_friction[:, 0]))
    assert changed.tolist() == pair_rows(prepared, pair_target("box_a", "floor")).tolist()
    assert np.array_equal(out.geom_friction, prepared.geom_friction)
    after = _slide(out)
    assert -0.3 - after[0, 0] == pytest.approx(1.5**2 / (2 * 0.2 * GRAVITY), rel=0.03)
    assert after[1] == pytest.approx(_slide(prepared)[1], abs=1e-9)


def test_mass_and_com_offset_on_one_body() -> None:
    model = mujoco.MjModel.from_xml_string(SCENES["collide"])
    mass = LIBRARY["mass"].at(body_target("box_b"))
    out, _ = apply_effects(model, [AppliedEffect(effect=mass, values={"scale": 2.0})])
    a, b = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in ("box_a", "box_b"))
    assert out.body_mass[b] == pytest.approx(2 * model.body_mass[b])
    assert out.body_mass[a] == pytest.approx(model.body_mass[a])
    com = LIBRARY["com_offset"].at(body_target("box_a"))
    out, _ = apply_effects(model, [AppliedEffect(effect=com, values={"dx_m": 0.01, "dy_m": 0.0, "dz_m": 0.0})])
    assert out.body_ipos[a] == pytest.approx(model.body_ipos[a] + [0.01, 0, 0])
    assert out.body_ipos[b] == pytest.approx(model.body_ipos[b])


def test_air_drag_on_one_body_leaves_the_other_in_free_fall() -> None:
    xml = SCENES["two_balls"]
    nominal = mujoco.MjModel.from_xml_string(xml)
    layout = Layout(bodies=("ball_a", "ball_b"), pairs=possible_pairs(nominal))
    prepared = prepared_spec(mujoco.MjSpec.from_string(xml), nominal, layout).compile()
    effect = LIBRARY["air_drag"].at(body_target("ball_b"))
    out, _ = apply_effects(prepared, [AppliedEffect(effect=effect, values={"density_kg_m3": 50.0})])
    data = mujoco.MjData(out)
    data.qpos[:] = [0, -0.4, 2, 1, 0, 0, 0, 0, 0.4, 2, 1, 0, 0, 0]
    data.qvel[:] = [3, 0, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0]
    mujoco.mj_step(out, data, nstep=100)  # 0.2 s, in the air
    assert data.qvel[0] == pytest.approx(3.0, abs=1e-9)  # ball_a: no drag
    assert data.qvel[2] == pytest.approx(-GRAVITY * 0.2, rel=1e-3)
    assert data.qvel[6] < 2.9  # ball_b slowed by drag


def test_named_targets_are_checked() -> None:
    model = mujoco.MjModel.from_xml_string(SCENES["stack"])
    assert parse_target(model, "box_a") == body_target("box_a")
    assert parse_target(model, "floor|box_b") == pair_target("box_b", "floor")
    names = [e.key for e in resolve_effects(["sliding_friction@box_a|box_b", "mass@box_c"], model)]
    assert names == ["sliding_friction@box_a|box_b", "mass@box_c"]
    for bad in ("box_z", "box_a|box_a", "floor|nothing", "a|b|c"):
        with pytest.raises(GrounderError):
            parse_target(model, bad)
    with pytest.raises(GrounderError, match="cannot act on one pair"):
        LIBRARY["mass"].at(pair_target("box_a", "box_b"))


def test_prepare_keeps_a_single_body_scene_as_it_is() -> None:
    xml = SCENES["slide_box"]
    model = mujoco.MjModel.from_xml_string(xml)
    case = make_case(next(c for c in MULTI_BODY if c.scenario == "two_boxes"), num_trajectories=1, duration_s=0.2)
    one = Trajectory(
        time_s=case.trajectories[0].time_s,
        qpos=case.trajectories[0].qpos[:, :7],
        qvel=case.trajectories[0].qvel[:, :6],
        name="one",
    )
    prepared, layout = prepare(model, mujoco.MjSpec.from_string(xml), [one], [contacts_at_samples(model, one)])
    assert prepared is model and not layout.explicit and not layout.localised


def test_same_place_counts_a_body_with_one_contact_pair_as_that_pair() -> None:
    pairs = ("box_a|floor", "box_a|box_b", "box_b|floor")
    assert same_place("box_a|box_b", "box_a|box_b", pairs)
    assert not same_place("box_a|box_b", "box_a", pairs)  # box_a also touches the floor
    assert same_place("box_c", "box_c|floor", ("box_c|floor", "box_a|floor"))
    assert not same_place("", "box_a", pairs)
