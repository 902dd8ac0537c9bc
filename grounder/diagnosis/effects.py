"""The library of candidate effects for gap diagnosis: each a parametrised change of a MuJoCo model or of the
simulation loop (controls, measurement).

An effect has a few named parameters, each searched in a box (log or linear), and knows the values that reproduce
the nominal model. Applying several effects composes them in order. Three kinds:

- ``recalibration``: a parameter the nominal model already has, re-fitted (``sliding_friction`` when the model has
  friction): a win means "this existing value is miscalibrated", not "something is missing";
- ``new_effect``: physics the nominal model leaves out or sets to zero (``air_drag``, ``actuator_delay``, ...);
- ``measurement``: a bias of the tracking, not of the physics (``length_scale``: recorded positions are ``s`` times
  the true ones; ``time_scale``: recorded seconds are ``1/k`` of true seconds).

The names in :data:`EFFECT_NAMES` are the interface (CLI ``--effects`` and ``diagnosis.json``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from grounder.diagnosis.targets import (
    ALL,
    Target,
    body_id,
    contact_geoms,
    moving_bodies,
    pair_rows,
    target_geoms,
)
from grounder.errors import GrounderError

# Plain ints: numpy ints compare equal to mjtJoint members but `in` on a tuple of them fails.
_FREE = int(mujoco.mjtJoint.mjJNT_FREE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)
_SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)


@dataclass(frozen=True, kw_only=True)
class Param:
    """One searched parameter: box ``[lo, hi]`` searched in log space when ``log`` (``lo > 0``), else linearly."""

    name: str
    lo: float
    hi: float
    log: bool = True

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        u = np.clip(u, 0.0, 1.0)
        if self.log:
            return np.exp(np.log(self.lo) + u * (np.log(self.hi) - np.log(self.lo)))
        return self.lo + u * (self.hi - self.lo)

    def to_unit(self, value: float) -> float:
        if self.log:
            value = max(value, self.lo)
            return float(np.clip((np.log(value) - np.log(self.lo)) / (np.log(self.hi) - np.log(self.lo)), 0, 1))
        return float(np.clip((value - self.lo) / (self.hi - self.lo), 0, 1))


@dataclass(frozen=True, kw_only=True)
class Transforms:
    """What a set of effects does outside the MjModel: to controls, to initial states and to predictions."""

    delay_s: float = 0.0
    length_scale: float = 1.0  # recorded positions = length_scale x true positions
    time_scale: float = 1.0  # true seconds per recorded second
    velocity_lag_s: float = 0.0  # recorded velocities describe the motion this long before the recorded positions


@dataclass(frozen=True, kw_only=True)
class Effect:
    """A parametrised change. ``apply`` edits a copy of the model (and may return loop transforms)."""

    name: str
    description: str
    params_of: Callable[[mujoco.MjModel], tuple[Param, ...]]
    nominal_of: Callable[[mujoco.MjModel], dict[str, float]]
    apply: Callable[[mujoco.MjModel, dict[str, float], dict[str, float]], None]  # (model, values, transforms)
    applicable: Callable[[mujoco.MjModel], bool]
    kind_of: Callable[[mujoco.MjModel], str] = field(default=lambda m: "new_effect")
    in_mjcf: bool = True
    target: Target = ALL
    scopes: tuple[str, ...] = ()  # "body", "pair": where a localised variant can act
    localize: Callable[[Target], Effect] | None = field(default=None, repr=False)

    @property
    def key(self) -> str:
        """The effect's name, with ``@`` and its body or contact pair when localised (``sliding_friction@box_a``)."""
        return self.target.key(self.name)

    def at(self, target: Target) -> Effect:
        """This effect acting on ``target`` only.

        Raises:
            GrounderError: the effect cannot be localised there.
        """
        if target.kind == "all":
            return LIBRARY[self.name]
        if self.localize is None or target.kind not in self.scopes:
            raise GrounderError(f"effect '{self.name}' cannot act on one {target.kind} ('{target.label}')")
        return self.localize(target)


# ---------------------------------------------------------------------------------------------------------- helpers
def _has_free(model: mujoco.MjModel) -> bool:
    return bool(np.any(model.jnt_type == _FREE))


def _has_contacts(model: mujoco.MjModel) -> bool:
    geoms = contact_geoms(model)
    return bool(len(geoms)) and _has_free(model)


def joint_dofs(model: mujoco.MjModel) -> np.ndarray:
    """Dofs of hinge and slide joints (the ones joint damping, friction and armature act on)."""
    out = [int(model.jnt_dofadr[j]) for j in range(model.njnt) if int(model.jnt_type[j]) in (_HINGE, _SLIDE)]
    return np.array(out, dtype=np.int64)


def dof_inertia_diag(model: mujoco.MjModel) -> np.ndarray:
    """(nv,) diagonal of the joint-space inertia at qpos0 (kg m^2 for hinges, kg for slides)."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return np.diag(full).copy()


def _dof_inertia(model: mujoco.MjModel) -> np.ndarray:
    """Diagonal of the joint-space inertia at qpos0 for the hinge/slide dofs."""
    return dof_inertia_diag(model)[joint_dofs(model)]


def torque_scale(model: mujoco.MjModel) -> float:
    """A typical joint torque: total moving mass x g x model extent (N m)."""
    mass = float(sum(model.body_mass[b] for b in moving_bodies(model)))
    return max(mass * 9.81 * float(model.stat.extent), 1e-6)


def leaf_body(model: mujoco.MjModel) -> int:
    """The last moving body in tree order (the distal link of an arm, or the object itself)."""
    bodies = moving_bodies(model)
    if not bodies:
        raise GrounderError("the model has no moving body; diagnosis needs at least one joint")
    return bodies[-1]


def _body_size_m(model: mujoco.MjModel, body: int) -> float:
    geoms = np.flatnonzero(model.geom_bodyid == body)
    if len(geoms) == 0:
        return 0.1
    return float(max(model.geom_rbound[g] for g in geoms))


def _mean(values: np.ndarray, default: float = 0.0) -> float:
    return float(np.mean(values)) if len(values) else default


# ---------------------------------------------------------------------------------------------------------- effects
# Geom friction columns (sliding, torsional, rolling) -> columns of an explicit pair's 5 friction coefficients.
_PAIR_FRICTION_COLUMNS = {0: [0, 1], 1: [2], 2: [3, 4]}


def _raise_priority(model: mujoco.MjModel, geoms: np.ndarray) -> None:
    """Lets a body's own contact values win over its partners' (MuJoCo takes the higher-priority geom's values)."""
    others = np.setdiff1d(np.arange(model.ngeom), geoms)
    top = int(model.geom_priority[others].max()) if len(others) else 0
    if len(geoms) and int(model.geom_priority[geoms].min()) <= top:
        model.geom_priority[geoms] = top + 1


def _where(target: Target) -> str:
    if target.kind == "all":
        return "every colliding geom"
    if target.kind == "body":
        return f"body '{target.label}' (its geoms and its contact pairs)"
    return f"the contact pair {target.parties[0]} / {target.parties[1]}"


def _friction_effect(name: str, column: int, lo: float, hi: float, what: str, target: Target = ALL) -> Effect:
    def params(model: mujoco.MjModel) -> tuple[Param, ...]:
        return (Param(name="mu", lo=lo, hi=hi),)

    def nominal(model: mujoco.MjModel) -> dict[str, float]:
        rows = pair_rows(model, target)
        if target.kind != "all" and len(rows):
            return {"mu": float(np.max(model.pair_friction[rows][:, _PAIR_FRICTION_COLUMNS[column]]))}
        geoms = target_geoms(model, target) if target.kind != "pair" else contact_geoms(model)
        # MuJoCo takes the larger coefficient of the two geoms in contact.
        return {"mu": float(np.max(model.geom_friction[geoms, column])) if len(geoms) else 0.0}

    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        geoms = target_geoms(model, target)
        model.geom_friction[geoms, column] = values["mu"]
        rows = pair_rows(model, target)
        for c in _PAIR_FRICTION_COLUMNS[column]:
            model.pair_friction[rows, c] = values["mu"]
        if target.kind == "body":
            _raise_priority(model, geoms)
        if column > 0:
            # Torsional friction needs condim >= 4 and rolling friction condim 6.
            need = 4 if column == 1 else 6
            model.geom_condim[geoms] = np.maximum(model.geom_condim[geoms], need)
            model.pair_dim[rows] = np.maximum(model.pair_dim[rows], need)

    def kind(model: mujoco.MjModel) -> str:
        geoms = contact_geoms(model)
        condim_ok = bool(len(geoms)) and int(np.max(model.geom_condim[geoms])) >= (3 if column == 0 else 2 + 2 * column)
        return "recalibration" if nominal(model)["mu"] > lo and condim_ok else "new_effect"

    return Effect(
        name=name,
        description=f"{what} coefficient of {_where(target)}",
        params_of=params,
        nominal_of=nominal,
        apply=apply,
        applicable=_has_contacts,
        kind_of=kind,
        target=target,
        scopes=("body", "pair"),
        localize=lambda t: _friction_effect(name, column, lo, hi, what, t),
    )


def _solref_effect(name: str, column: int, target: Target = ALL) -> Effect:
    def params(model: mujoco.MjModel) -> tuple[Param, ...]:
        if column == 0:
            return (Param(name="timeconst_s", lo=2.0 * model.opt.timestep, hi=0.1),)
        return (Param(name="dampratio", lo=0.05, hi=2.0),)

    key = "timeconst_s" if column == 0 else "dampratio"

    def nominal(model: mujoco.MjModel) -> dict[str, float]:
        rows = pair_rows(model, target)
        if target.kind != "all" and len(rows):
            return {key: _mean(model.pair_solref[rows, column])}
        geoms = target_geoms(model, target) if target.kind != "pair" else contact_geoms(model)
        return {key: _mean(model.geom_solref[geoms, column], 0.02 if column == 0 else 1.0)}

    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        geoms = target_geoms(model, target)
        rows = pair_rows(model, target)
        model.geom_solref[geoms, column] = values[key]
        model.pair_solref[rows, column] = values[key]
        if target.kind == "body":
            _raise_priority(model, geoms)
        if column == 0:
            # Stiffness alone: the default contact stiffness also depends on solimp; keep it.
            model.geom_solref[geoms, 1] = np.maximum(model.geom_solref[geoms, 1], 1e-3)
            model.pair_solref[rows, 1] = np.maximum(model.pair_solref[rows, 1], 1e-3)

    what = (
        "contact time constant (solref[0]; larger = softer)"
        if column == 0
        else "contact damping ratio (solref[1]; smaller = bouncier)"
    )
    return Effect(
        name=name,
        description=what if target.kind == "all" else f"{what} of {_where(target)}",
        params_of=params,
        nominal_of=nominal,
        apply=apply,
        applicable=_has_contacts,
        kind_of=lambda m: "recalibration",
        target=target,
        scopes=("body", "pair"),
        localize=lambda t: _solref_effect(name, column, t),
    )


def _dof_effect(name: str, attr: str, what: str) -> Effect:
    def params(model: mujoco.MjModel) -> tuple[Param, ...]:
        inertia = _dof_inertia(model)
        tau = torque_scale(model)
        if attr == "dof_damping":
            hi = max(float(np.max(inertia)) / 0.05, 1e-6)  # time constants down to 50 ms
        elif attr == "dof_frictionloss":
            hi = 0.5 * tau
        else:
            hi = 5.0 * max(float(np.max(inertia)), 1e-9)
        return (Param(name="value", lo=hi * 1e-4, hi=hi),)

    def nominal(model: mujoco.MjModel) -> dict[str, float]:
        return {"value": _mean(getattr(model, attr)[joint_dofs(model)])}

    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        getattr(model, attr)[joint_dofs(model)] = values["value"]

    def kind(model: mujoco.MjModel) -> str:
        return "recalibration" if nominal(model)["value"] > 0 else "new_effect"

    return Effect(
        name=name,
        description=f"{what} of every hinge and slide joint (one shared value)",
        params_of=params,
        nominal_of=nominal,
        apply=apply,
        applicable=lambda m: len(joint_dofs(m)) > 0,
        kind_of=kind,
    )


def _air_drag(target: Target = ALL) -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        # MuJoCo's fluid model: quadratic drag proportional to the medium density (inertia-box model, or the
        # ellipsoid model per geom where the diagnosis prepared the scene for drag per body).
        model.opt.density = values["density_kg_m3"]
        if target.kind == "body":
            # The other bodies keep the ellipsoid model (the inertia-box one would drag them too) with every
            # coefficient, drag, lift and added mass, at zero: no fluid force on them.
            body = body_id(model, target.parties[0])
            others = np.flatnonzero((model.geom_bodyid != body) & (model.geom_fluid[:, 0] > 0))
            model.geom_fluid[others, 1:] = 0.0

    def applicable(model: mujoco.MjModel) -> bool:
        if target.kind == "body":
            body = body_id(model, target.parties[0])
            # Per body needs the ellipsoid model on the body's geoms; the diagnosis prepares it when the medium is
            # still (density and viscosity zero).
            ellipsoid = bool(np.any(model.geom_fluid[model.geom_bodyid == body, 0] > 0))
            still = model.opt.density == 0 and model.opt.viscosity == 0
            return body > 0 and (ellipsoid or still)
        return len(moving_bodies(model)) > 0

    return Effect(
        name="air_drag",
        description="quadratic aerodynamic drag (MuJoCo fluid model, medium density)"
        + ("" if target.kind == "all" else f" on body '{target.label}' only"),
        params_of=lambda m: (Param(name="density_kg_m3", lo=0.05, hi=500.0),),
        nominal_of=lambda m: {"density_kg_m3": float(m.opt.density)},
        apply=apply,
        applicable=applicable,
        kind_of=lambda m: "recalibration" if m.opt.density > 0 else "new_effect",
        target=target,
        scopes=("body",),
        localize=_air_drag,
    )


def _actuator_delay() -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], transforms: dict[str, float]) -> None:
        transforms["delay_s"] = transforms.get("delay_s", 0.0) + values["delay_s"]

    return Effect(
        name="actuator_delay",
        description="controls act this many seconds after they are recorded",
        params_of=lambda m: (Param(name="delay_s", lo=0.0, hi=0.1, log=False),),
        nominal_of=lambda m: {"delay_s": 0.0},
        apply=apply,
        applicable=lambda m: m.nu > 0,
        in_mjcf=False,
    )


def _actuator_gain() -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        model.actuator_gainprm[:, 0] *= values["scale"]

    return Effect(
        name="actuator_gain",
        description="actuator gain (force per unit control) scaled for every actuator",
        params_of=lambda m: (Param(name="scale", lo=0.25, hi=4.0),),
        nominal_of=lambda m: {"scale": 1.0},
        apply=apply,
        applicable=lambda m: m.nu > 0,
        kind_of=lambda m: "recalibration",
    )


def _bodies_of(model: mujoco.MjModel, target: Target) -> list[int]:
    return moving_bodies(model) if target.kind == "all" else [body_id(model, target.parties[0])]


def _mass(target: Target = ALL) -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        for b in _bodies_of(model, target):
            model.body_mass[b] *= values["scale"]
            model.body_inertia[b] *= values["scale"]

    return Effect(
        name="mass",
        description=(
            "mass (and inertia, same density) of every moving body scaled"
            if target.kind == "all"
            else f"mass (and inertia, same density) of body '{target.label}' scaled"
        ),
        params_of=lambda m: (Param(name="scale", lo=0.25, hi=4.0),),
        nominal_of=lambda m: {"scale": 1.0},
        apply=apply,
        applicable=lambda m: len(moving_bodies(m)) > 0 and all(b > 0 for b in _bodies_of(m, target)),
        kind_of=lambda m: "recalibration",
        target=target,
        scopes=("body",),
        localize=_mass,
    )


def _com_offset(target: Target = ALL) -> Effect:
    def body_of(model: mujoco.MjModel) -> int:
        return leaf_body(model) if target.kind == "all" else body_id(model, target.parties[0])

    def params(model: mujoco.MjModel) -> tuple[Param, ...]:
        half = 0.5 * _body_size_m(model, body_of(model))
        return tuple(Param(name=f"d{axis}_m", lo=-half, hi=half, log=False) for axis in "xyz")

    def apply(model: mujoco.MjModel, values: dict[str, float], _: dict[str, float]) -> None:
        body = body_of(model)
        model.body_ipos[body] += [values["dx_m"], values["dy_m"], values["dz_m"]]
        # The compiler marks bodies whose inertial frame is their body frame and then skips the offset.
        model.body_sameframe[body] = 0
        model.body_simple[body] = 0
        dofs = slice(int(model.body_dofadr[body]), int(model.body_dofadr[body] + model.body_dofnum[body]))
        model.dof_simplenum[dofs] = 0

    return Effect(
        name="com_offset",
        description=(
            "centre of mass of the distal (last) moving body shifted, in its body frame"
            if target.kind == "all"
            else f"centre of mass of body '{target.label}' shifted, in its body frame"
        ),
        params_of=params,
        nominal_of=lambda m: {"dx_m": 0.0, "dy_m": 0.0, "dz_m": 0.0},
        apply=apply,
        applicable=lambda m: len(moving_bodies(m)) > 0 and body_of(m) > 0,
        kind_of=lambda m: "recalibration",
        target=target,
        scopes=("body",),
        localize=_com_offset,
    )


def _length_scale() -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], transforms: dict[str, float]) -> None:
        transforms["length_scale"] = transforms.get("length_scale", 1.0) * values["scale"]

    return Effect(
        name="length_scale",
        description="tracking bias: recorded positions are `scale` x the true ones",
        params_of=lambda m: (Param(name="scale", lo=0.9, hi=1.1, log=False),),
        nominal_of=lambda m: {"scale": 1.0},
        apply=apply,
        applicable=_has_free,
        kind_of=lambda m: "measurement",
        in_mjcf=False,
    )


def _time_scale() -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], transforms: dict[str, float]) -> None:
        transforms["time_scale"] = transforms.get("time_scale", 1.0) * values["scale"]
        model.opt.timestep *= values["scale"]

    return Effect(
        name="time_scale",
        description="timing bias: one recorded second lasts `scale` true seconds",
        params_of=lambda m: (Param(name="scale", lo=0.9, hi=1.1, log=False),),
        nominal_of=lambda m: {"scale": 1.0},
        apply=apply,
        applicable=_has_free,
        kind_of=lambda m: "measurement",
        in_mjcf=False,
    )


def _velocity_lag() -> Effect:
    def apply(model: mujoco.MjModel, values: dict[str, float], transforms: dict[str, float]) -> None:
        transforms["velocity_lag_s"] = transforms.get("velocity_lag_s", 0.0) + values["lag_s"]

    return Effect(
        name="velocity_lag",
        description="recording bias: recorded velocities lag the recorded positions (e.g. backward differences)",
        params_of=lambda m: (Param(name="lag_s", lo=-0.01, hi=0.01, log=False),),
        nominal_of=lambda m: {"lag_s": 0.0},
        apply=apply,
        applicable=lambda m: m.nv > 0,
        kind_of=lambda m: "measurement",
        in_mjcf=False,
    )


LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        _air_drag(),
        _friction_effect("sliding_friction", 0, 0.02, 2.0, "sliding friction"),
        _friction_effect("torsional_friction", 1, 1e-5, 0.1, "torsional friction (m)"),
        _friction_effect("rolling_friction", 2, 1e-6, 0.05, "rolling friction (m)"),
        _solref_effect("restitution", 1),
        _solref_effect("contact_stiffness", 0),
        _dof_effect("joint_damping", "dof_damping", "viscous damping (N m s/rad)"),
        _dof_effect("joint_friction", "dof_frictionloss", "Coulomb friction loss (N m)"),
        _dof_effect("armature", "dof_armature", "armature (rotor inertia, kg m^2)"),
        _actuator_delay(),
        _actuator_gain(),
        _mass(),
        _com_offset(),
        _length_scale(),
        _time_scale(),
        _velocity_lag(),
    )
}
EFFECT_NAMES: tuple[str, ...] = tuple(LIBRARY)
"""Every effect name the diagnosis knows, in library order."""


def parse_target(model: mujoco.MjModel, label: str) -> Target:
    """``box_a`` (a body) or ``box_a|floor`` (a contact pair: two bodies, or a body and a static geom).

    Raises:
        GrounderError: a name that is neither a moving body nor, in a pair, a static geom or body.
    """
    from grounder.diagnosis.targets import body_target, moving_body_names, pair_target, party_geoms

    parts = [p.strip() for p in label.split("|")]
    bodies = moving_body_names(model)
    if len(parts) == 1:
        if parts[0] not in bodies:
            raise GrounderError(f"'@{label}' names no moving body; moving bodies: {', '.join(bodies) or 'none'}")
        return body_target(parts[0])
    if len(parts) != 2 or parts[0] == parts[1]:
        raise GrounderError(f"'@{label}' is not a contact pair; write two different names: body_a|floor")
    for part in parts:
        if not len(party_geoms(model, part)):
            raise GrounderError(
                f"'@{label}': '{part}' is not a body or geom that collides; moving bodies: {', '.join(bodies)}"
            )
    if not set(parts) & set(bodies):
        raise GrounderError(f"'@{label}': neither side moves; name at least one moving body")
    return pair_target(parts[0], parts[1])


def resolve_effects(names: list[str] | tuple[str, ...] | None, model: mujoco.MjModel) -> list[Effect]:
    """The named effects (all applicable ones when ``names`` is None); ``name@body`` or ``name@body|other`` acts on
    one body or one contact pair only.

    Raises:
        GrounderError: an unknown name, or a named effect that cannot act on this model.
    """
    if names is None:
        return [e for e in LIBRARY.values() if e.applicable(model)]
    out = []
    for entry in names:
        name, _, where = entry.partition("@")
        if name not in LIBRARY:
            raise GrounderError(f"unknown effect '{name}'; available: {', '.join(EFFECT_NAMES)}")
        effect = LIBRARY[name]
        if where:
            effect = effect.at(parse_target(model, where))
        if not effect.applicable(model):
            raise GrounderError(
                f"effect '{entry}' cannot act on this model (no actuator, joint or contact it applies to); "
                f"leave it out of --effects"
            )
        out.append(effect)
    if not out:
        raise GrounderError("no effect to test; pass at least one name to --effects")
    return out


@dataclass(frozen=True, kw_only=True)
class AppliedEffect:
    """An effect with fitted values."""

    effect: Effect
    values: dict[str, float]


def apply_effects(model: mujoco.MjModel, applied: list[AppliedEffect]) -> tuple[mujoco.MjModel, Transforms]:
    """A copy of ``model`` with the effects applied in order, and the loop transforms they add."""
    out = copy.copy(model)
    transforms: dict[str, float] = {}
    for item in applied:
        item.effect.apply(out, item.values, transforms)
    if applied:
        # Constants derived from masses and inertias (e.g. the inverse weights that set constraint softness).
        mujoco.mj_setConst(out, mujoco.MjData(out))
    return out, Transforms(**transforms)
