"""The restitution a MuJoCo contact produces (`grounder.sim.restitution`), against closed forms."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from grounder.errors import GrounderError
from grounder.sim.restitution import body_restitution, simulated_restitution

SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)


def clipped_spring_dashpot_restitution(dampratio: float) -> float:
    """e of a linear spring-dashpot whose force is clipped at zero (it lets go when the force vanishes, before the
    spring is back at rest; Schwager and Poeschel, Phys. Rev. E 75, 051304, 2007), for damping ratio < 1/sqrt(2)."""
    omega = math.sqrt(1.0 - dampratio**2)  # in units of the undamped frequency
    contact_time = (math.pi - math.atan(2.0 * dampratio * omega / (omega**2 - dampratio**2))) / omega
    return math.exp(-dampratio * contact_time)


def _options(xml_option: str) -> mujoco.MjOption:
    return mujoco.MjModel.from_xml_string(f"<mujoco><option {xml_option}/></mujoco>").opt


@pytest.mark.parametrize("dampratio", [0.1, 0.2, 0.4, 0.65])
def test_a_long_time_constant_bounces_as_a_spring_dashpot_that_cannot_pull(dampratio: float) -> None:
    # 40 steps per time constant and no gravity: the closed form, and not the textbook exp(-pi d / sqrt(1 - d^2)),
    # which it exceeds by 2% at d 0.1 and by 43% at d 0.4.
    option = _options('timestep="0.0005" gravity="0 0 0" integrator="implicitfast"')
    e = simulated_restitution((0.02, dampratio), SOLIMP, option, impact_speed_m_s=1.0)
    assert e == pytest.approx(clipped_spring_dashpot_restitution(dampratio), rel=0.01)
    textbook = math.exp(-math.pi * dampratio / math.sqrt(1.0 - dampratio**2))
    if dampratio >= 0.2:
        assert e > 1.05 * textbook


def test_at_a_few_time_steps_the_time_constant_trades_with_the_damping_ratio() -> None:
    # The scene's 2 ms step: (0.0087 s, 0.218), a calibrated point of the can of samples/toss, bounces within 15% of
    # the rendered (0.02 s, 0.15), though its damping ratio is 45% higher; at 0.02 s that ratio bounces 20% lower.
    option = _options('timestep="0.002" integrator="implicitfast" cone="elliptic"')
    rendered = simulated_restitution((0.02, 0.15), SOLIMP, option)
    assert simulated_restitution((0.0087, 0.218), SOLIMP, option) == pytest.approx(rendered, rel=0.15)
    assert simulated_restitution((0.02, 0.218), SOLIMP, option) < 0.85 * rendered
    # More damping bounces less at any time constant.
    for timeconst in (0.0087, 0.02, 0.04):
        bounces = [simulated_restitution((timeconst, d), SOLIMP, option) for d in (0.1, 0.2, 0.3, 0.5)]
        assert bounces == sorted(bounces, reverse=True)


def test_body_restitution_reads_the_bodys_colliding_geom() -> None:
    xml = """<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="1 1 .1"/>
      <body name="box"><freejoint/><geom type="box" size=".02 .02 .02" contype="0" conaffinity="0" solref="0.02 1"/>
        <geom type="box" size=".02 .02 .02" solref="0.03 0.25" solimp="0.9 0.95 0.001 0.5 2"/></body>
      <body name="ghost"><freejoint/><geom type="sphere" size=".01" contype="0" conaffinity="0"/></body>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    assert body_restitution(model, "box") == pytest.approx(simulated_restitution((0.03, 0.25), SOLIMP, model.opt))
    with pytest.raises(GrounderError, match="no colliding geom"):
        body_restitution(model, "ghost")
    with pytest.raises(GrounderError, match="no body named"):
        body_restitution(model, "bowl")


@pytest.mark.parametrize(
    ("solref", "solimp", "speed", "match"),
    [
        ((-1000.0, -10.0), SOLIMP, 1.0, "standard form"),
        ((0.02, float("nan")), SOLIMP, 1.0, "standard form"),
        ((0.02, 0.2), (0.95, 0.9, 0.001, 0.5, 2.0), 1.0, "dmin <= dmax"),
        ((0.02, 0.2), SOLIMP, 0.0, "positive speed"),
    ],
)
def test_bad_contact_values_are_refused(solref: tuple, solimp: tuple, speed: float, match: str) -> None:
    with pytest.raises(GrounderError, match=match):
        simulated_restitution(solref, solimp, None, speed)


BALL_XML = """<mujoco><option timestep="0.002" integrator="implicitfast" cone="elliptic"/><worldbody>
  <geom type="plane" size="1 1 .1"/>
  <body name="ball" pos="0 0 .1"><freejoint/>
    <geom type="sphere" size=".02" priority="1" solref="0.02 0.2" solimp="0.9 0.95 0.001 0.5 2"/></body>
</worldbody></mujoco>"""


def test_the_shooting_search_resolves_the_bounce_where_the_solref_pair_trades() -> None:
    """Points of a (time constant x damping ratio) lattice whose cost is that of their bounce's error (a clip that
    shows bounces): many pairs tie, so the damping ratio is spread past 20%, but the restitution is resolved and
    its range lies within 20% of the truth's; with only the near points evaluated it is not resolved."""
    from grounder.calibration.parameters import resolve_parameters
    from grounder.interaction.shooting import ShootingOptions, _restitution_fit

    model = mujoco.MjModel.from_xml_string(BALL_XML)
    contact = resolve_parameters(model, ["ball.solref.timeconst", "ball.solref.dampratio"])
    truth = body_restitution(model, "ball")
    points = []
    for timeconst in (0.006, 0.008, 0.01, 0.014, 0.02, 0.028, 0.04):
        for dampratio in (0.1, 0.13, 0.16, 0.2, 0.25, 0.3, 0.4):
            contact[0].set_model(model, timeconst)
            contact[1].set_model(model, dampratio)
            cost = 300.0 * math.log(body_restitution(model, "ball") / truth) ** 2  # 6 at 15% off
            points.append((np.array([timeconst, dampratio]), cost))
    options = ShootingOptions()
    fit = _restitution_fit(model, contact, points, np.array([0.02, 0.2]), 0.0, options)
    assert fit is not None and fit.resolved and fit.value == pytest.approx(truth)
    assert truth / 1.2 < fit.range[0] <= fit.range[1] < truth * 1.2
    near_dampratios = [values[1] for values, cost in points if cost <= options.resolution_cost]
    assert min(near_dampratios) < 0.2 / 1.2 or max(near_dampratios) > 0.2 * 1.2  # the pair trades
    assert model.geom_solref[1].tolist() == pytest.approx([0.02, 0.2])  # left at the best point
    near_only = [(values, cost) for values, cost in points if cost <= options.resolution_cost]
    assert not _restitution_fit(model, contact, near_only, np.array([0.02, 0.2]), 0.0, options).resolved
    friction = resolve_parameters(model, ["ball.friction.sliding"])
    assert _restitution_fit(model, friction, [(np.array([0.5]), 0.0)], np.array([0.5]), 0.0, options) is None
