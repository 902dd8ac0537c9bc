"""Withheld-effect cases for checking the diagnosis: true system = nominal model + hidden effect(s) + sensor noise.

Scenarios (nominal models built inline, 2 ms timestep, recorded at 100 Hz):

- ``slide_box``: a 0.1 m box pushed along a plane (sliding, then resting);
- ``toss_box``: the box tossed from 0.3-0.5 m with spin (free flight, impact, tumbling, sliding, resting);
- ``roll_ball``: a ball launched rolling (rolling, resting);
- ``spin_ball``: a ball spun about the vertical in place (turning contact, resting);
- ``toss_light_ball``: a light 10 cm ball thrown through the air (free flight, impact);
- ``pendulum``: a hinged rod released from random angles;
- ``arm``: a two-link arm in a vertical plane driven by two motors with random multi-sine controls.

Multi-object scenarios (issue 64: effects on one body, on one contact pair, or on all):

- ``two_boxes``: two boxes pushed apart along the plane (sliding, then resting);
- ``stack``: a small box sliding on top of a larger one that slides on the plane, and a third box sliding alone
  (contact pairs box_a|floor, box_a|box_b, box_c|floor);
- ``three_boxes``: three boxes tossed side by side in their own lanes;
- ``collide``: a box pushed into a second, resting one (the momentum exchange shows their mass ratio);
- ``two_balls``: two light balls thrown through the air in their own lanes.

Hidden effects are library effects with known values, acting everywhere or, with ``target``, on one body
(``box_a``) or one contact pair (``box_a|box_b``), plus effects outside the library: ``periodic_push`` (a
horizontal force oscillating at 3 Hz, e.g. a vibrating table; on the body ``target`` names, else the first) acts
only on the true system.
Sensor noise: positions 0.5 mm, orientations 0.3 deg, joint angles 2 mrad; linear velocities 1 cm/s, angular
velocities 0.05 rad/s (Gaussian, seeded).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.diagnosis.effects import LIBRARY, AppliedEffect, apply_effects, parse_target
from grounder.diagnosis.targets import Layout, moving_body_names, possible_pairs, prepared_spec
from grounder.errors import GrounderError

TIMESTEP_S = 0.002
SAMPLE_DT_S = 0.01
DURATION_S = 1.0

_PLANE = '<geom name="floor" type="plane" size="5 5 0.1" friction="{mu} 0.005 0.0001" condim="{condim}"/>'


def _free_scene(body_geom: str, mu: float = 0.5, condim: int = 3, extra_option: str = "") -> str:
    return f"""<mujoco model="case">
  <option timestep="{TIMESTEP_S}" {extra_option}/>
  <worldbody>
    {_PLANE.format(mu=mu, condim=condim)}
    <body name="object" pos="0 0 0.5"><freejoint name="object"/>{body_geom}</body>
  </worldbody>
</mujoco>"""


def _boxes(*boxes: tuple[str, float, float]) -> str:
    """Free boxes (name, half size m, mass kg), placed by the initial state."""
    return "".join(
        f'<body name="{n}" pos="0 0 0.5"><freejoint name="{n}"/><geom name="{n}" type="box" size="{h} {h} {h}" '
        f'mass="{m}" friction="0.5 0.005 0.0001"/></body>'
        for n, h, m in boxes
    )


def _multi_scene(bodies: str, mu: float = 0.5) -> str:
    return f"""<mujoco model="case">
  <option timestep="{TIMESTEP_S}"/>
  <worldbody>
    {_PLANE.format(mu=mu, condim=3)}
    {bodies}
  </worldbody>
</mujoco>"""


SCENES: dict[str, str] = {
    "slide_box": _free_scene(
        '<geom name="box" type="box" size="0.05 0.05 0.05" mass="0.5" friction="0.5 0.005 0.0001"/>'
    ),
    "toss_box": _free_scene(
        '<geom name="box" type="box" size="0.05 0.05 0.05" mass="0.5" friction="0.5 0.005 0.0001"/>'
    ),
    "roll_ball": _free_scene(
        '<geom name="ball" type="sphere" size="0.04" mass="0.2" friction="0.8 0.005 0.0002" condim="6"/>',
        mu=0.8,
        condim=6,
    ),
    "spin_ball": _free_scene(
        '<geom name="ball" type="sphere" size="0.04" mass="0.2" friction="0.6 0.005 0.0001"/>', mu=0.6
    ),
    "toss_light_ball": _free_scene(
        '<geom name="ball" type="sphere" size="0.05" mass="0.06" friction="0.5 0.005 0.0001"/>'
    ),
    "pendulum": f"""<mujoco model="pendulum">
  <option timestep="{TIMESTEP_S}"/>
  <worldbody>
    <body name="rod" pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02" mass="0.5" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>""",
    "arm": f"""<mujoco model="arm">
  <option timestep="{TIMESTEP_S}"/>
  <worldbody>
    <body name="upper" pos="0 0 1"><joint name="shoulder" type="hinge" axis="0 1 0" damping="0.01"/>
      <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="0.6" contype="0" conaffinity="0"/>
      <body name="fore" pos="0.25 0 0"><joint name="elbow" type="hinge" axis="0 1 0" damping="0.01"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" mass="0.3" contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder" gear="1" ctrlrange="-3 3" ctrllimited="true"/>
    <motor name="elbow" joint="elbow" gear="1" ctrlrange="-1.5 1.5" ctrllimited="true"/>
  </actuator>
</mujoco>""",
    "two_boxes": _multi_scene(_boxes(("box_a", 0.05, 0.5), ("box_b", 0.04, 0.3))),
    "stack": _multi_scene(_boxes(("box_a", 0.08, 1.0), ("box_b", 0.03, 0.2), ("box_c", 0.04, 0.3))),
    "three_boxes": _multi_scene(_boxes(("box_a", 0.05, 0.5), ("box_b", 0.04, 0.3), ("box_c", 0.045, 0.4))),
    "collide": _multi_scene(_boxes(("box_a", 0.05, 0.5), ("box_b", 0.04, 0.4))),
    "two_balls": _multi_scene(
        "".join(
            f'<body name="{n}" pos="0 0 0.5"><freejoint name="{n}"/><geom name="{n}" type="sphere" size="0.05" '
            'mass="0.06" friction="0.5 0.005 0.0001"/></body>'
            for n in ("ball_a", "ball_b")
        )
    ),
}
MULTI_BODY_SCENARIOS = ("two_boxes", "stack", "three_boxes", "collide", "two_balls")


@dataclass(frozen=True, kw_only=True)
class HiddenEffect:
    """An effect acting on the true system: a library effect with values, or one outside the library."""

    name: str
    values: dict[str, float]
    in_library: bool = True
    target: str = ""  # "" = everywhere; a body ("box_a") or a contact pair ("box_a|box_b")


@dataclass(frozen=True, kw_only=True)
class CaseSpec:
    name: str
    scenario: str
    hidden: tuple[HiddenEffect, ...]


@dataclass(frozen=True, kw_only=True)
class Case:
    """A generated case: the nominal scene (MJCF text) and the recorded (noisy) trajectories of the true system."""

    spec: CaseSpec
    scene_xml: str
    trajectories: list[Trajectory]

    @property
    def in_library(self) -> bool:
        return all(h.in_library for h in self.spec.hidden)


def _h(name: str, target: str = "", **values: float) -> HiddenEffect:
    return HiddenEffect(name=name, values=values, in_library=name in LIBRARY, target=target)


BENCHMARK: tuple[CaseSpec, ...] = (
    CaseSpec(name="slide_box/sliding_friction", scenario="slide_box", hidden=(_h("sliding_friction", mu=0.25),)),
    CaseSpec(name="spin_ball/torsional_friction", scenario="spin_ball", hidden=(_h("torsional_friction", mu=0.002),)),
    CaseSpec(name="roll_ball/rolling_friction", scenario="roll_ball", hidden=(_h("rolling_friction", mu=0.004),)),
    CaseSpec(name="toss_box/restitution", scenario="toss_box", hidden=(_h("restitution", dampratio=0.15),)),
    CaseSpec(
        name="toss_box/contact_stiffness", scenario="toss_box", hidden=(_h("contact_stiffness", timeconst_s=0.04),)
    ),
    CaseSpec(name="toss_light_ball/air_drag", scenario="toss_light_ball", hidden=(_h("air_drag", density_kg_m3=4.0),)),
    CaseSpec(name="pendulum/joint_damping", scenario="pendulum", hidden=(_h("joint_damping", value=0.01),)),
    CaseSpec(name="pendulum/joint_friction", scenario="pendulum", hidden=(_h("joint_friction", value=0.04),)),
    CaseSpec(name="pendulum/armature", scenario="pendulum", hidden=(_h("armature", value=0.006),)),
    CaseSpec(name="arm/actuator_delay", scenario="arm", hidden=(_h("actuator_delay", delay_s=0.03),)),
    CaseSpec(name="arm/actuator_gain", scenario="arm", hidden=(_h("actuator_gain", scale=0.7),)),
    CaseSpec(name="arm/mass", scenario="arm", hidden=(_h("mass", scale=1.5),)),
    CaseSpec(
        name="roll_ball/com_offset", scenario="roll_ball", hidden=(_h("com_offset", dx_m=0.02, dy_m=0.0, dz_m=0.0),)
    ),
    CaseSpec(name="toss_box/length_scale", scenario="toss_box", hidden=(_h("length_scale", scale=0.97),)),
    CaseSpec(
        name="arm/delay+gain",
        scenario="arm",
        hidden=(_h("actuator_delay", delay_s=0.03), _h("actuator_gain", scale=0.75)),
    ),
    CaseSpec(
        name="slide_box/periodic_push",
        scenario="slide_box",
        hidden=(_h("periodic_push", amplitude_n=2.0, freq_hz=3.0),),
    ),
)
"""The withheld-effect benchmark: 14 single in-library effects, one pair, one effect outside the library."""

MULTI_BODY: tuple[CaseSpec, ...] = (
    CaseSpec(
        name="two_boxes/sliding_friction@box_a",
        scenario="two_boxes",
        hidden=(_h("sliding_friction", target="box_a", mu=0.25),),
    ),
    CaseSpec(name="two_boxes/sliding_friction", scenario="two_boxes", hidden=(_h("sliding_friction", mu=0.3),)),
    CaseSpec(
        name="stack/sliding_friction@box_a|box_b",
        scenario="stack",
        hidden=(_h("sliding_friction", target="box_a|box_b", mu=0.2),),
    ),
    CaseSpec(
        name="three_boxes/restitution@box_c",
        scenario="three_boxes",
        hidden=(_h("restitution", target="box_c", dampratio=0.15),),
    ),
    CaseSpec(name="three_boxes/restitution", scenario="three_boxes", hidden=(_h("restitution", dampratio=0.2),)),
    CaseSpec(name="collide/mass@box_b", scenario="collide", hidden=(_h("mass", target="box_b", scale=2.0),)),
    CaseSpec(
        name="two_balls/air_drag@ball_b",
        scenario="two_balls",
        hidden=(_h("air_drag", target="ball_b", density_kg_m3=4.0),),
    ),
    CaseSpec(name="collide/no_gap", scenario="collide", hidden=()),
    CaseSpec(
        name="two_boxes/periodic_push@box_b",
        scenario="two_boxes",
        hidden=(_h("periodic_push", target="box_b", amplitude_n=1.5, freq_hz=3.0),),
    ),
)
"""Multi-object cases (issue 64): effects on one body, on one contact pair and on all bodies, with two and three
bodies; a case with no gap; one effect outside the library on one body."""
ALL_CASES: tuple[CaseSpec, ...] = BENCHMARK + MULTI_BODY
"""Every case `diagnose-benchmark` runs by default."""


def _initial_state(scenario: str, model: mujoco.MjModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    qpos = model.qpos0.copy()
    qvel = np.zeros(model.nv)
    if scenario in ("slide_box", "spin_ball", "roll_ball"):
        half = {"slide_box": 0.05, "spin_ball": 0.04, "roll_ball": 0.04}[scenario]
        qpos[:3] = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), half - 1e-4]
        yaw = rng.uniform(-np.pi, np.pi)
        qpos[3:7] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
        heading = rng.uniform(-np.pi, np.pi)
        direction = np.array([np.cos(heading), np.sin(heading), 0.0])
        if scenario == "slide_box":
            qvel[:3] = direction * rng.uniform(1.0, 2.5)
            qvel[5] = rng.uniform(-4, 4)
        elif scenario == "spin_ball":
            qvel[:3] = direction * rng.uniform(0.0, 0.3)
            qvel[5] = rng.choice([-1, 1]) * rng.uniform(15, 35)
        else:
            speed = rng.uniform(1.0, 2.0)
            qvel[:3] = direction * speed
            # Rolling without slipping: omega_world = z x v / r, expressed in the body frame (rotated by yaw).
            omega_world = np.cross([0, 0, 1.0], qvel[:3]) / half
            c, s = np.cos(yaw), np.sin(yaw)
            qvel[3:6] = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ omega_world
    elif scenario in ("toss_box", "toss_light_ball"):
        qpos[:3] = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.3, 0.5)]
        q = rng.normal(size=4)
        qpos[3:7] = q / np.linalg.norm(q)
        if scenario == "toss_box":
            qvel[:3] = [rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(-0.5, 1.5)]
            qvel[3:6] = rng.uniform(-8, 8, 3)
        else:
            heading = rng.uniform(-np.pi, np.pi)
            qvel[:3] = [3.5 * np.cos(heading), 3.5 * np.sin(heading), rng.uniform(2.0, 4.0)]
            qvel[3:6] = rng.uniform(-5, 5, 3)
    elif scenario in MULTI_BODY_SCENARIOS:
        _multi_initial_state(scenario, qpos, qvel, rng)
    elif scenario == "pendulum":
        qpos[0] = rng.uniform(-2.2, 2.2)
        qvel[0] = rng.uniform(-2, 2)
    elif scenario == "arm":
        qpos[:] = rng.uniform(-1.0, 1.0, 2)
    else:
        raise GrounderError(f"unknown scenario '{scenario}'")
    return qpos, qvel


def _place(
    qpos: np.ndarray,
    qvel: np.ndarray,
    i: int,
    pos: list[float],
    yaw: float,
    vel: list[float] | np.ndarray,
    omega_body: list[float] | np.ndarray,
) -> None:
    """Free body ``i``: world position, yaw about the vertical, world linear velocity, body angular velocity."""
    qpos[7 * i : 7 * i + 7] = [*pos, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    qvel[6 * i : 6 * i + 6] = [*vel, *omega_body]


def _heading(angle: float, speed: float) -> list[float]:
    return [speed * np.cos(angle), speed * np.sin(angle), 0.0]


def _multi_initial_state(scenario: str, qpos: np.ndarray, qvel: np.ndarray, rng: np.random.Generator) -> None:
    u = rng.uniform
    if scenario == "two_boxes":
        # Pushed away from each other: they rarely touch.
        for i, (x, half, away) in enumerate(((-0.25, 0.05, np.pi), (0.25, 0.04, 0.0))):
            _place(qpos, qvel, i, [x + u(-0.05, 0.05), u(-0.1, 0.1), half - 1e-4], u(-np.pi, np.pi),
                   _heading(away + u(-1.0, 1.0), u(1.0, 2.5)), [0, 0, u(-4, 4)])  # fmt: skip
    elif scenario == "stack":
        # box_b rides on box_a and slips on it (its own velocity differs a little); box_c slides alone.
        va = np.array(_heading(u(-np.pi, np.pi), u(0.0, 0.15)))
        slip = np.array(_heading(u(-np.pi, np.pi), u(0.2, 0.45)))
        x, y = u(-0.1, 0.05), u(-0.15, 0.15)
        back = -0.03 * (va + slip) / np.linalg.norm(va + slip)  # room ahead on box_a's top
        _place(qpos, qvel, 0, [x, y, 0.08 - 1e-4], u(-0.3, 0.3), va, [0, 0, 0])
        _place(qpos, qvel, 1, [x + back[0], y + back[1], 0.19 - 2e-4], u(-0.5, 0.5), va + slip, [0, 0, u(-1, 1)])
        _place(qpos, qvel, 2, [0.4 + u(-0.05, 0.05), u(-0.1, 0.1), 0.04 - 1e-4], u(-np.pi, np.pi),
               _heading(u(-1.0, 1.0), u(1.0, 2.0)), [0, 0, u(-4, 4)])  # fmt: skip
    elif scenario == "three_boxes":
        for i, lane in enumerate((-0.45, 0.0, 0.45)):
            q = rng.normal(size=4)
            qpos[7 * i : 7 * i + 7] = [u(-0.1, 0.1), lane + u(-0.05, 0.05), u(0.3, 0.5), *(q / np.linalg.norm(q))]
            qvel[6 * i : 6 * i + 6] = [u(-1.0, 1.0), u(-0.4, 0.4), u(-0.5, 1.5), *u(-8, 8, 3)]
    elif scenario == "collide":
        y = u(-0.1, 0.1)
        _place(qpos, qvel, 0, [-0.22, y, 0.05 - 1e-4], u(-0.2, 0.2), _heading(u(-0.15, 0.15), u(1.8, 2.5)),
               [0, 0, 0])  # fmt: skip
        _place(qpos, qvel, 1, [0.0, y + u(-0.03, 0.03), 0.04 - 1e-4], u(-0.3, 0.3), [0, 0, 0], [0, 0, 0])
    elif scenario == "two_balls":
        for i, lane in enumerate((-0.4, 0.4)):
            heading = u(-0.6, 0.6) + (np.pi if i == 0 else 0.0)
            qpos[7 * i : 7 * i + 7] = [u(-0.1, 0.1), lane, u(0.3, 0.5), 1.0, 0.0, 0.0, 0.0]
            qvel[6 * i : 6 * i + 6] = [3.5 * np.cos(heading), 3.5 * np.sin(heading), u(2.0, 4.0), *u(-5, 5, 3)]


def _controls(scenario: str, model: mujoco.MjModel, times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random multi-sine controls held at the sample rate, within the control ranges."""
    ctrl = np.zeros((len(times), model.nu))
    for a in range(model.nu):
        hi = float(model.actuator_ctrlrange[a, 1])
        freqs = rng.uniform(0.5, 4.0, 3)
        phases = rng.uniform(0, 2 * np.pi, 3)
        amps = rng.uniform(0.2, 0.5, 3) * hi
        ctrl[:, a] = np.clip(
            sum(A * np.sin(2 * np.pi * f * times + p) for A, f, p in zip(amps, freqs, phases, strict=True)), -hi, hi
        )
    return ctrl


def _noisy(
    model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    qpos, qvel = qpos.copy(), qvel.copy()
    for j in range(model.njnt):
        a, d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            qpos[:, a : a + 3] += rng.normal(0, 5e-4, (len(qpos), 3))
            # A small random rotation: q <- q * exp(delta / 2), delta ~ 0.3 deg per axis.
            delta = rng.normal(0, np.deg2rad(0.3), (len(qpos), 3))
            for t in range(len(qpos)):
                dq = np.empty(4)
                mujoco.mju_axisAngle2Quat(dq, delta[t] / max(np.linalg.norm(delta[t]), 1e-12), np.linalg.norm(delta[t]))
                out = np.empty(4)
                mujoco.mju_mulQuat(out, qpos[t, a + 3 : a + 7], dq)
                qpos[t, a + 3 : a + 7] = out / np.linalg.norm(out)
            qvel[:, d : d + 3] += rng.normal(0, 0.01, (len(qvel), 3))
            qvel[:, d + 3 : d + 6] += rng.normal(0, 0.05, (len(qvel), 3))
        else:
            qpos[:, a] += rng.normal(0, 2e-3, len(qpos))
            qvel[:, d] += rng.normal(0, 0.02, len(qvel))
    return qpos, qvel


def make_case(spec: CaseSpec, num_trajectories: int = 16, seed: int = 0, duration_s: float = DURATION_S) -> Case:
    """Simulates the true system of a case and records noisy trajectories (deterministic for a seed)."""
    xml = SCENES[spec.scenario]
    nominal = mujoco.MjModel.from_xml_string(xml)
    base = nominal
    if any(h.target for h in spec.hidden if h.in_library):
        # Contact pairs with their own parameters, every pair that can touch (what the diagnosis prepares).
        layout = Layout(bodies=tuple(moving_body_names(nominal)), pairs=possible_pairs(nominal))
        base = prepared_spec(mujoco.MjSpec.from_string(xml), nominal, layout).compile()
    library = [
        AppliedEffect(effect=LIBRARY[h.name].at(parse_target(base, h.target)) if h.target else LIBRARY[h.name],
                      values=h.values)
        for h in spec.hidden
        if h.in_library
    ]  # fmt: skip
    true_model, transforms = apply_effects(base, library)
    push = next((h for h in spec.hidden if h.name == "periodic_push"), None)
    push_body = (
        1 if push is None or not push.target else int(mujoco.mj_name2id(nominal, mujoco.mjtObj.mjOBJ_BODY, push.target))
    )
    unknown = [h.name for h in spec.hidden if not h.in_library and h.name != "periodic_push"]
    if unknown:
        raise GrounderError(f"unknown hidden effect(s) {unknown}")
    rng = np.random.default_rng(seed)
    data = mujoco.MjData(true_model)
    dt = true_model.opt.timestep  # time_scale would change it; the recorded clock stays TIMESTEP_S-based
    sub = round(SAMPLE_DT_S / TIMESTEP_S)
    n_samples = round(duration_s / SAMPLE_DT_S) + 1
    times = np.arange(n_samples) * SAMPLE_DT_S
    delay_steps = round(transforms.delay_s / TIMESTEP_S)
    trajs = []
    for i in range(num_trajectories):
        qpos0, qvel0 = _initial_state(spec.scenario, nominal, rng)
        ctrl = _controls(spec.scenario, nominal, times, rng) if nominal.nu else None
        push_dir = rng.normal(size=2)
        push_dir /= np.linalg.norm(push_dir)
        mujoco.mj_resetData(true_model, data)
        data.qpos[:] = qpos0
        data.qvel[:] = qvel0
        qpos = np.empty((n_samples, nominal.nq))
        qvel = np.empty((n_samples, nominal.nv))
        for k in range(n_samples):
            mujoco.mj_forward(true_model, data)
            qpos[k], qvel[k] = data.qpos, data.qvel
            if k == n_samples - 1:
                break
            for s in range(sub):
                step = k * sub + s
                if ctrl is not None:
                    src = max(0, step - delay_steps) // sub
                    data.ctrl[:] = ctrl[src]
                if push is not None:
                    f = push.values["amplitude_n"] * np.sin(2 * np.pi * push.values["freq_hz"] * step * dt)
                    data.xfrc_applied[push_body, :2] = f * push_dir
                mujoco.mj_step(true_model, data)
        if transforms.length_scale != 1.0:
            for j in range(nominal.njnt):
                if nominal.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                    a, d = int(nominal.jnt_qposadr[j]), int(nominal.jnt_dofadr[j])
                    qpos[:, a : a + 3] *= transforms.length_scale
                    qvel[:, d : d + 3] *= transforms.length_scale
        qpos, qvel = _noisy(nominal, qpos, qvel, rng)
        trajs.append(Trajectory(time_s=times, qpos=qpos, qvel=qvel, ctrl=ctrl, name=f"traj_{i:02d}"))
    return Case(spec=spec, scene_xml=xml, trajectories=trajs)
