"""Named physical parameters of a MuJoCo scene, applied identically to a compiled `MjModel` and to its `MjSpec`.

Naming scheme (the names `image2sim calibrate --params` accepts), one parameter per name:

==============================================  =====================================================  =========
name                                            what it sets                                           unit
==============================================  =====================================================  =========
``BODY.mass``                                   body mass; the body's inertia is scaled with it        kg
``BODY.com.x`` / ``.y`` / ``.z``                centre of mass in the body frame                       m
``BODY.friction.sliding|torsional|rolling``     friction of every collision geom of the body           -, m, m
``BODY.solref.timeconst`` / ``.dampratio``      contact softness of those geoms (solref, standard)     s, -
``BODY.solimp.dmin|dmax|width|midpoint|power``  contact impedance of those geoms (solimp)              -, -, m
``BODY.condim``                                 contact dimensionality, a choice among 3, 4, 6         -
``BODY.size_scale``                             scale of the body's primitive collision geoms (size    -
                                                and offset), not its mass or inertia: compensates a
                                                length bias in the measured geometry
``geom:NAME.<friction|solref|solimp|...>``      as above, for one named geom                           as above
``joint:NAME.damping|frictionloss|armature``    per degree of freedom of the joint; by default         SI
                                                searched in log space, scaled to the joint (below)
``joint:NAME.stiffness``                        joint spring stiffness                                 SI
``actuator:NAME.gain``                          ``gainprm[0]``                                         SI
``actuator:NAME.kp`` / ``.kv``                  position gain (``gainprm[0] = kp``, ``biasprm[1] =     SI
                                                -kp``) / velocity gain (``biasprm[2] = -kv``)
``opt.gravity_scale``                           multiplies the gravity vector: compensates a timing    -
                                                or length-scale bias of the measurement (a 2% slow
                                                clock reads g as 0.96 g), not a physical claim
``opt.impratio``                                frictional-to-normal impedance ratio (elliptic cones)  -
``opt.cone``                                    friction cone, a choice: 0 pyramidal, 1 elliptic       -
==============================================  =====================================================  =========

``BODY`` is a body name as in the MJCF (``box``, ``cube``). Contact parameters (friction, solref, solimp) of a body
or geom that is calibrated take effect in every contact of that geom: the geom's ``priority`` is raised above
all others, so MuJoCo uses its values instead of mixing them with the other geom's (by default the larger
friction and a solmix-weighted solref would be used). The uncalibrated model keeps the scene's own mixing.

A parameter specification string is ``NAME`` (default bounds) or ``NAME=LOW:HIGH`` (explicit bounds). Choices
(``condim``, ``opt.cone``) take no bounds: the global search picks one, the local refinement keeps it.
Default bounds of joint damping, friction loss and armature scale with the joint (``_joint_bounds``): four decades
below the joint inertia / 50 ms, 5 x the joint inertia and half the weight torque of the moving bodies. Explicit
bounds from 0 (``joint:hinge.damping=0:0.5``) are searched linearly.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from grounder.errors import GrounderError

_FRICTION = {"sliding": 0, "torsional": 1, "rolling": 2}
_SOLREF = {"timeconst": 0, "dampratio": 1}
_SOLIMP = {"dmin": 0, "dmax": 1, "width": 2, "midpoint": 3, "power": 4}
_COM = {"x": 0, "y": 1, "z": 2}
_JOINT_DOF_FIELDS = {"damping": "dof_damping", "frictionloss": "dof_frictionloss", "armature": "dof_armature"}
_PRIMITIVES = frozenset(
    int(t)
    for t in (
        mujoco.mjtGeom.mjGEOM_SPHERE,
        mujoco.mjtGeom.mjGEOM_CAPSULE,
        mujoco.mjtGeom.mjGEOM_ELLIPSOID,
        mujoco.mjtGeom.mjGEOM_CYLINDER,
        mujoco.mjtGeom.mjGEOM_BOX,
    )
)

ModelSetter = Callable[[mujoco.MjModel, float], None]
SpecSetter = Callable[[mujoco.MjSpec, float], None]


@dataclass(frozen=True, kw_only=True, eq=False)
class Parameter:
    """One calibrated quantity: where it lives, its scene value and its search bounds.

    Attributes:
        name: The parameter name (module docstring).
        nominal: The value in the scene as given.
        lower, upper: Search bounds, ``lower < upper``.
        log_scale: Search in log space (positive quantities spanning decades).
        unit: Unit for reports.
        contact_geoms: Geom ids whose priority is raised when this parameter is calibrated.
        needs_set_const: Changing it changes derived constants (masses, inertias) that `mj_setConst` refreshes.
    """

    name: str
    nominal: float
    lower: float
    upper: float
    log_scale: bool
    unit: str
    contact_geoms: tuple[int, ...] = ()
    needs_set_const: bool = False
    choices: tuple[float, ...] = ()
    set_model: ModelSetter
    set_spec: SpecSetter

    @property
    def discrete(self) -> bool:
        """A choice among ``choices`` (condim, cone): searched globally, held fixed by the local refinement."""
        return bool(self.choices)

    def to_unit(self, value: np.ndarray | float) -> np.ndarray:
        """Physical value(s) -> search coordinate in [0, 1]."""
        v = np.asarray(value, dtype=np.float64)
        if self.choices:
            n = len(self.choices)
            index = np.argmin(np.abs(np.subtract.outer(v, np.asarray(self.choices))), axis=-1)
            return (index + 0.5) / n
        if self.log_scale:
            # values below the floor (a nominal 0) map below 0, which the search clips to the floor
            v = np.maximum(v, self.lower * 1e-3)
            return (np.log(v) - math.log(self.lower)) / (math.log(self.upper) - math.log(self.lower))
        return (v - self.lower) / (self.upper - self.lower)

    def from_unit(self, u: np.ndarray | float) -> np.ndarray:
        """Search coordinate(s) in [0, 1] -> physical value(s)."""
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        if self.choices:
            # Equal slices of the unit interval, one per choice: a piecewise-constant coordinate for the search.
            index = np.minimum((u * len(self.choices)).astype(np.int64), len(self.choices) - 1)
            return np.asarray(self.choices, dtype=np.float64)[index]
        if self.log_scale:
            return np.exp(math.log(self.lower) + u * (math.log(self.upper) - math.log(self.lower)))
        return self.lower + u * (self.upper - self.lower)


def _name(model: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(model, obj, i) or ""


def _names(model: mujoco.MjModel, obj: mujoco.mjtObj, count: int) -> list[str]:
    return [n for n in (_name(model, obj, i) for i in range(count)) if n]


def collision_geoms(model: mujoco.MjModel, body_id: int) -> list[int]:
    """Geoms of a body that take part in collisions (contype or conaffinity non-zero)."""
    return [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] == body_id and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]


def body_size_m(model: mujoco.MjModel, body_id: int) -> float:
    """Largest extent of a body's collision geoms' bounding boxes, in the body frame, metres (0.1048 for the cube)."""
    corners = []
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    for g in collision_geoms(model, body_id) or [g for g in range(model.ngeom) if model.geom_bodyid[g] == body_id]:
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, model.geom_quat[g])
        local = center + signs * half
        corners.append(model.geom_pos[g] + local @ rot.reshape(3, 3).T)
    if not corners:
        return 0.1
    pts = np.concatenate(corners)
    return float(np.max(pts.max(0) - pts.min(0)))


def _geom_targets(model: mujoco.MjModel, owner: str) -> tuple[list[int], str]:
    """Geom ids addressed by ``BODY`` or ``geom:NAME``, and a label for messages."""
    if owner.startswith("geom:"):
        gname = owner[5:]
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, gname)
        if gid < 0:
            known = _names(model, mujoco.mjtObj.mjOBJ_GEOM, model.ngeom)
            raise GrounderError(f"unknown geom {gname!r} in parameter; named geoms: {known}")
        return [gid], f"geom {gname!r}"
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, owner)
    if bid <= 0:
        raise GrounderError(
            f"unknown body {owner!r} in parameter; bodies: {_names(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody)[1:]}"
        )
    geoms = collision_geoms(model, bid)
    if not geoms:
        raise GrounderError(f"body {owner!r} has no collision geoms, so it has no contact parameters")
    return geoms, f"body {owner!r}"


def _contact_parameter(model: mujoco.MjModel, name: str, owner: str, field: str, sub: str) -> Parameter:
    geoms, label = _geom_targets(model, owner)
    timestep = float(model.opt.timestep)
    if field == "friction":
        if sub not in _FRICTION:
            raise GrounderError(f"unknown parameter {name!r}: friction components are {list(_FRICTION)}")
        k = _FRICTION[sub]
        arr_name = "geom_friction"
        bounds, log, unit = {0: ((0.02, 1.5), True, "-"), 1: ((0.0, 0.05), False, "m"), 2: ((0.0, 0.01), False, "m")}[k]
    elif field == "solref":
        if sub not in _SOLREF:
            raise GrounderError(f"unknown parameter {name!r}: solref components are {list(_SOLREF)}")
        k = _SOLREF[sub]
        arr_name = "geom_solref"
        if k == 0:
            bounds, log, unit = (max(2.0 * timestep, 1e-3), 0.1), True, "s"
        else:
            bounds, log, unit = (0.1, 3.0), True, "-"
    elif field == "solimp":
        if sub not in _SOLIMP:
            raise GrounderError(f"unknown parameter {name!r}: solimp components are {list(_SOLIMP)}")
        k = _SOLIMP[sub]
        arr_name = "geom_solimp"
        bounds, log, unit = [
            ((0.5, 0.99), False, "-"),
            ((0.8, 0.9999), False, "-"),
            ((1e-4, 0.05), True, "m"),
            ((0.1, 0.9), False, "-"),
            ((1.0, 6.0), False, "-"),
        ][k]
    else:
        raise AssertionError(field)
    values = getattr(model, arr_name)[geoms, k]
    if field == "solref" and np.any(values <= 0):
        raise GrounderError(
            f"{label} uses direct (negative) solref; {name} needs the standard timeconst/dampratio form"
        )
    nominal = float(values[0])
    geom_ids = tuple(geoms)

    def set_model(m: mujoco.MjModel, v: float) -> None:
        getattr(m, arr_name)[list(geom_ids), k] = v

    spec_field = field

    def set_spec(s: mujoco.MjSpec, v: float) -> None:
        for g in geom_ids:
            getattr(s.geoms[g], spec_field)[k] = v

    return Parameter(
        name=name,
        nominal=nominal,
        lower=bounds[0],
        upper=bounds[1],
        log_scale=log,
        unit=unit,
        contact_geoms=geom_ids,
        set_model=set_model,
        set_spec=set_spec,
    )


def _size_scale_parameter(model: mujoco.MjModel, name: str, owner: str) -> Parameter:
    geoms, label = _geom_targets(model, owner)
    for g in geoms:
        if int(model.geom_type[g]) not in _PRIMITIVES:
            raise GrounderError(
                f"{name}: {label} has a {mujoco.mjtGeom(model.geom_type[g]).name} collision geom; size_scale "
                "supports primitive geoms (box, sphere, capsule, cylinder, ellipsoid) only"
            )
    geom_ids = tuple(geoms)
    size0 = model.geom_size[list(geom_ids)].copy()
    pos0 = model.geom_pos[list(geom_ids)].copy()
    rbound0 = model.geom_rbound[list(geom_ids)].copy()
    aabb0 = model.geom_aabb[list(geom_ids)].copy()

    def set_model(m: mujoco.MjModel, v: float) -> None:
        idx = list(geom_ids)
        m.geom_size[idx] = size0 * v
        m.geom_pos[idx] = pos0 * v
        m.geom_rbound[idx] = rbound0 * v
        m.geom_aabb[idx] = aabb0 * v

    def set_spec(s: mujoco.MjSpec, v: float) -> None:
        for i, g in enumerate(geom_ids):
            s.geoms[g].size = size0[i] * v
            s.geoms[g].pos = pos0[i] * v

    return Parameter(
        name=name,
        nominal=1.0,
        lower=0.9,
        upper=1.1,
        log_scale=False,
        unit="-",
        set_model=set_model,
        set_spec=set_spec,
    )


def _inertial_to_spec(s: mujoco.MjSpec, m0: mujoco.MjModel, bid: int, mass: float, ipos: np.ndarray) -> None:
    body = s.bodies[bid]
    body.explicitinertial = True
    body.mass = mass
    body.ipos = ipos
    body.iquat = m0.body_iquat[bid].copy()
    body.inertia = m0.body_inertia[bid] * (mass / m0.body_mass[bid])
    body.fullinertia = np.full(6, np.nan)


def _body_parameter(model: mujoco.MjModel, name: str, owner: str, rest: list[str]) -> Parameter:
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, owner)
    if bid <= 0:
        raise GrounderError(
            f"unknown parameter {name!r}: no body {owner!r}; bodies: "
            f"{_names(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody)[1:]}"
        )
    mass0 = float(model.body_mass[bid])
    inertia0 = model.body_inertia[bid].copy()
    ipos0 = model.body_ipos[bid].copy()
    # Mass and centre of mass may both be calibrated: the spec setter reads back what the model setter wrote.
    if rest == ["mass"]:
        if mass0 <= 0:
            raise GrounderError(f"{name}: body {owner!r} has no mass to scale")

        def set_model(m: mujoco.MjModel, v: float) -> None:
            m.body_mass[bid] = v
            m.body_inertia[bid] = inertia0 * (v / mass0)

        def set_spec(s: mujoco.MjSpec, v: float) -> None:
            body = s.bodies[bid]
            ipos = np.asarray(body.ipos) if body.explicitinertial else ipos0
            m0 = _nominal_model_for(s, model)
            _inertial_to_spec(s, m0, bid, v, ipos)

        return Parameter(
            name=name,
            nominal=mass0,
            lower=0.5 * mass0,
            upper=2.0 * mass0,
            log_scale=True,
            unit="kg",
            needs_set_const=True,
            set_model=set_model,
            set_spec=set_spec,
        )
    if len(rest) == 2 and rest[0] == "com" and rest[1] in _COM:
        k = _COM[rest[1]]
        half = 0.25 * body_size_m(model, bid)

        def set_model_com(m: mujoco.MjModel, v: float) -> None:
            m.body_ipos[bid, k] = v

        def set_spec_com(s: mujoco.MjSpec, v: float) -> None:
            body = s.bodies[bid]
            m0 = _nominal_model_for(s, model)
            ipos = np.asarray(body.ipos, dtype=np.float64).copy() if body.explicitinertial else ipos0.copy()
            mass = float(body.mass) if body.explicitinertial else mass0
            ipos[k] = v
            _inertial_to_spec(s, m0, bid, mass, ipos)

        return Parameter(
            name=name,
            nominal=float(ipos0[k]),
            lower=float(ipos0[k]) - half,
            upper=float(ipos0[k]) + half,
            log_scale=False,
            unit="m",
            needs_set_const=True,
            set_model=set_model_com,
            set_spec=set_spec_com,
        )
    if len(rest) == 2 and rest[0] in ("friction", "solref", "solimp"):
        return _contact_parameter(model, name, owner, rest[0], rest[1])
    if rest == ["size_scale"]:
        return _size_scale_parameter(model, name, owner)
    if rest == ["condim"]:
        return _condim_parameter(model, name, owner)
    raise GrounderError(
        f"unknown parameter {name!r}; body parameters are mass, com.x|y|z, friction.sliding|torsional|rolling, "
        "solref.timeconst|dampratio, solimp.dmin|dmax|width|midpoint|power, size_scale, condim"
    )


def _condim_parameter(model: mujoco.MjModel, name: str, owner: str) -> Parameter:
    geoms, _ = _geom_targets(model, owner)
    geom_ids = tuple(geoms)

    def set_model(m: mujoco.MjModel, v: float) -> None:
        m.geom_condim[list(geom_ids)] = round(v)

    def set_spec(s: mujoco.MjSpec, v: float) -> None:
        for g in geom_ids:
            s.geoms[g].condim = round(v)

    return Parameter(
        name=name,
        nominal=float(model.geom_condim[geom_ids[0]]),
        lower=3.0,
        upper=6.0,
        log_scale=False,
        unit="-",
        contact_geoms=geom_ids,
        choices=(3.0, 4.0, 6.0),
        set_model=set_model,
        set_spec=set_spec,
    )


# The spec setters of mass and centre of mass need the nominal principal axes; they are the compiled model's.
_NOMINAL: dict[int, mujoco.MjModel] = {}


def _nominal_model_for(s: mujoco.MjSpec, model: mujoco.MjModel) -> mujoco.MjModel:
    return _NOMINAL.get(id(s), model)


JOINT_SEARCH_DECADES = 4.0


def _joint_bounds(model: mujoco.MjModel, field: str, dofs: list[int], nominal: float) -> tuple[float, float, bool]:
    """Search bounds of a joint parameter, scaled to the joint's own inertia and the model's torques.

    Damping, friction loss and armature span decades and are often far below 1 in SI units (a 0.5 kg, 30 cm
    pendulum has 0.015 kg m^2), so they are searched in log space over ``JOINT_SEARCH_DECADES`` decades below a
    physical ceiling (the diagnosis' scales): damping up to the joint inertia / 50 ms, armature up to 5 x the joint
    inertia, friction loss up to half the weight torque of the moving bodies; the ceiling is at least 10 x the
    nominal value. The floor stands for zero. Stiffness keeps a linear range from 0.
    """
    from grounder.diagnosis.effects import dof_inertia_diag, torque_scale

    if field == "stiffness":
        return 0.0, max(10.0 * nominal, 1.0), False
    inertia = max(float(np.max(dof_inertia_diag(model)[dofs])), 1e-9)
    ceiling = {"damping": inertia / 0.05, "armature": 5.0 * inertia, "frictionloss": 0.5 * torque_scale(model)}[field]
    upper = max(ceiling, 10.0 * nominal)
    return upper * 10.0**-JOINT_SEARCH_DECADES, upper, True


def _joint_parameter(model: mujoco.MjModel, name: str, jname: str, rest: list[str]) -> Parameter:
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname)
    if jid < 0:
        raise GrounderError(
            f"unknown parameter {name!r}: no joint {jname!r}; joints: "
            f"{_names(model, mujoco.mjtObj.mjOBJ_JOINT, model.njnt)}"
        )
    if len(rest) != 1 or rest[0] not in (*_JOINT_DOF_FIELDS, "stiffness"):
        raise GrounderError(f"unknown parameter {name!r}; joint parameters are {[*_JOINT_DOF_FIELDS, 'stiffness']}")
    field = rest[0]
    ndof = {0: 6, 1: 3, 2: 1, 3: 1}[int(model.jnt_type[jid])]
    dofs = list(range(int(model.jnt_dofadr[jid]), int(model.jnt_dofadr[jid]) + ndof))
    if field == "stiffness":
        nominal = float(model.jnt_stiffness[jid])

        def set_model(m: mujoco.MjModel, v: float) -> None:
            m.jnt_stiffness[jid] = v

        def set_spec(s: mujoco.MjSpec, v: float) -> None:
            s.joints[jid].stiffness[0] = v

        unit = "N m/rad"
    else:
        arr = _JOINT_DOF_FIELDS[field]
        nominal = float(getattr(model, arr)[dofs[0]])

        def set_model(m: mujoco.MjModel, v: float) -> None:
            getattr(m, arr)[dofs] = v

        def set_spec(s: mujoco.MjSpec, v: float) -> None:
            attr = getattr(s.joints[jid], field)
            if isinstance(attr, np.ndarray):
                attr[0] = v
            else:
                setattr(s.joints[jid], field, v)

        unit = {"damping": "N m s/rad", "frictionloss": "N m", "armature": "kg m^2"}[field]
    lower, upper, log = _joint_bounds(model, field, dofs, nominal)
    return Parameter(
        name=name,
        nominal=nominal,
        lower=lower,
        upper=upper,
        log_scale=log,
        unit=unit,
        needs_set_const=field == "armature",
        set_model=set_model,
        set_spec=set_spec,
    )


def _actuator_parameter(model: mujoco.MjModel, name: str, aname: str, rest: list[str]) -> Parameter:
    aid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, aname)
    if aid < 0:
        raise GrounderError(
            f"unknown parameter {name!r}: no actuator {aname!r}; actuators: "
            f"{_names(model, mujoco.mjtObj.mjOBJ_ACTUATOR, model.nu)}"
        )
    if rest not in (["gain"], ["kp"], ["kv"]):
        raise GrounderError(f"unknown parameter {name!r}; actuator parameters are gain, kp, kv")
    what = rest[0]
    nominal = float(model.actuator_gainprm[aid, 0]) if what != "kv" else float(-model.actuator_biasprm[aid, 2])

    def set_model(m: mujoco.MjModel, v: float) -> None:
        if what in ("gain", "kp"):
            m.actuator_gainprm[aid, 0] = v
        if what == "kp":
            m.actuator_biasprm[aid, 1] = -v
        if what == "kv":
            m.actuator_biasprm[aid, 2] = -v

    def set_spec(s: mujoco.MjSpec, v: float) -> None:
        act = s.actuators[aid]
        if what in ("gain", "kp"):
            act.gainprm[0] = v
        if what == "kp":
            act.biasprm[1] = -v
        if what == "kv":
            act.biasprm[2] = -v

    lower, upper, log = (0.25 * nominal, 4.0 * nominal, True) if nominal > 0 else (0.0, 1.0, False)
    return Parameter(
        name=name,
        nominal=nominal,
        lower=lower,
        upper=upper,
        log_scale=log,
        unit="SI",
        set_model=set_model,
        set_spec=set_spec,
    )


def _option_parameter(model: mujoco.MjModel, name: str, rest: list[str]) -> Parameter:
    if rest == ["gravity_scale"]:
        gravity0 = model.opt.gravity.copy()

        def set_model(m: mujoco.MjModel, v: float) -> None:
            m.opt.gravity[:] = gravity0 * v

        def set_spec(s: mujoco.MjSpec, v: float) -> None:
            s.option.gravity = gravity0 * v

        return Parameter(
            name=name,
            nominal=1.0,
            lower=0.9,
            upper=1.1,
            log_scale=False,
            unit="-",
            set_model=set_model,
            set_spec=set_spec,
        )
    if rest == ["impratio"]:

        def set_model_imp(m: mujoco.MjModel, v: float) -> None:
            m.opt.impratio = v

        def set_spec_imp(s: mujoco.MjSpec, v: float) -> None:
            s.option.impratio = v

        return Parameter(
            name=name,
            nominal=float(model.opt.impratio),
            lower=1.0,
            upper=20.0,
            log_scale=True,
            unit="-",
            set_model=set_model_imp,
            set_spec=set_spec_imp,
        )
    if rest == ["cone"]:

        def set_model_cone(m: mujoco.MjModel, v: float) -> None:
            m.opt.cone = round(v)

        def set_spec_cone(s: mujoco.MjSpec, v: float) -> None:
            s.option.cone = mujoco.mjtCone(round(v))

        return Parameter(
            name=name,
            nominal=float(model.opt.cone),
            lower=0.0,
            upper=1.0,
            log_scale=False,
            unit="0 pyramidal, 1 elliptic",
            choices=(float(mujoco.mjtCone.mjCONE_PYRAMIDAL), float(mujoco.mjtCone.mjCONE_ELLIPTIC)),
            set_model=set_model_cone,
            set_spec=set_spec_cone,
        )
    raise GrounderError(f"unknown parameter {name!r}; option parameters are opt.gravity_scale, opt.impratio, opt.cone")


_SPEC_RE = re.compile(r"^\s*(?P<name>[^=\s]+)\s*(?:=\s*(?P<lo>[^:]+):(?P<hi>.+))?\s*$")


def resolve_parameter(model: mujoco.MjModel, text: str) -> Parameter:
    """A parameter from its specification string ``NAME`` or ``NAME=LOW:HIGH`` (module docstring).

    Raises:
        GrounderError: the name does not follow the scheme, names a body/geom/joint/actuator the model does not
            have, or the bounds are not numbers with ``LOW < HIGH``.
    """
    match = _SPEC_RE.match(text)
    if match is None:
        raise GrounderError(f"cannot read parameter {text!r}; write NAME or NAME=LOW:HIGH, e.g. box.mass=0.2:0.6")
    name = match["name"]
    if "." not in name:
        raise GrounderError(f"unknown parameter {name!r}; names look like box.mass, box.friction.sliding, opt.impratio")
    owner, *rest = name.split(".")
    if name.startswith("geom:"):
        owner, rest = name.split(".", 1)[0], name.split(".", 1)[1].split(".")
        if len(rest) == 2 and rest[0] in ("friction", "solref", "solimp"):
            param = _contact_parameter(model, name, owner, rest[0], rest[1])
        elif rest == ["size_scale"]:
            param = _size_scale_parameter(model, name, owner)
        else:
            raise GrounderError(
                f"unknown parameter {name!r}; geom parameters are friction.*, solref.*, solimp.*, size_scale"
            )
    elif owner.startswith("joint:"):
        param = _joint_parameter(model, name, owner[6:], rest)
    elif owner.startswith("actuator:"):
        param = _actuator_parameter(model, name, owner[9:], rest)
    elif owner == "opt":
        param = _option_parameter(model, name, rest)
    else:
        param = _body_parameter(model, name, owner, rest)
    if match["lo"] is not None:
        if param.discrete:
            raise GrounderError(f"{name} is a choice among {list(param.choices)}; it takes no bounds")
        try:
            lower, upper = float(match["lo"]), float(match["hi"])
        except ValueError:
            raise GrounderError(f"bounds of {name!r} must be numbers, got {match['lo']!r}:{match['hi']!r}") from None
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise GrounderError(f"bounds of {name!r} must be finite with LOW < HIGH, got {lower}:{upper}")
        log = param.log_scale
        if log and lower <= 0:
            if not owner.startswith("joint:"):
                raise GrounderError(f"{name} is searched in log space; its lower bound must be > 0, got {lower}")
            log = False  # a joint parameter given a range from 0 is searched linearly over it
        param = Parameter(**{**param.__dict__, "lower": lower, "upper": upper, "log_scale": log})
    return param


def default_parameter_names(model: mujoco.MjModel) -> list[str]:
    """Sensible parameters for a scene, by kind.

    - Each free-floating body with collision geoms (tossed or pushed objects): sliding/torsional/rolling friction,
      solref time constant/damping ratio and condim, and the friction cone; contact is what decides where such
      an object ends up (on the real cube tosses, condim 6 with an elliptic cone alone halves the error).
    - Each hinge or slide joint (articulated scenes): damping, frictionloss, armature.
    - Each actuator: gain.
    """
    names: list[str] = []
    for j in range(model.njnt):
        jtype = int(model.jnt_type[j])
        if jtype == mujoco.mjtJoint.mjJNT_FREE:
            bid = int(model.jnt_bodyid[j])
            bname = _name(model, mujoco.mjtObj.mjOBJ_BODY, bid)
            if bname and collision_geoms(model, bid):
                names += [
                    f"{bname}.friction.sliding",
                    f"{bname}.friction.torsional",
                    f"{bname}.friction.rolling",
                    f"{bname}.solref.timeconst",
                    f"{bname}.solref.dampratio",
                    f"{bname}.condim",
                ]
        elif jtype in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            jname = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            if jname:
                names += [f"joint:{jname}.damping", f"joint:{jname}.frictionloss", f"joint:{jname}.armature"]
    for a in range(model.nu):
        aname = _name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
        if aname:
            names.append(f"actuator:{aname}.gain")
    if any(n.endswith(".condim") for n in names):
        names.append("opt.cone")  # torsional and rolling friction behave differently in the two cones
    return names


def resolve_parameters(model: mujoco.MjModel, texts: Sequence[str] | None) -> list[Parameter]:
    """Parameters from specification strings, or the scene's defaults when ``texts`` is None or empty.

    Raises:
        GrounderError: a name is unknown or repeated, or the scene offers no default parameter.
    """
    texts = list(texts) if texts else default_parameter_names(model)
    if not texts:
        raise GrounderError(
            "the scene has no free body with collision geoms, named hinge/slide joint or actuator to calibrate; "
            "name the parameters with --params"
        )
    params = [resolve_parameter(model, t) for t in texts]
    seen: set[str] = set()
    for p in params:
        if p.name in seen:
            raise GrounderError(f"parameter {p.name!r} is given twice")
        seen.add(p.name)
    return params


def contact_priority(model: mujoco.MjModel) -> int:
    """The priority given to calibrated contact geoms: above every geom in the scene."""
    return int(model.geom_priority.max(initial=0)) + 1


def apply_to_model(
    base: mujoco.MjModel,
    params: Sequence[Parameter],
    values: Sequence[float] | np.ndarray,
    *,
    data: mujoco.MjData | None = None,
) -> mujoco.MjModel:
    """A copy of ``base`` with the parameter values set (and calibrated contact geoms given top priority)."""
    import copy

    model = copy.copy(base)
    priority = contact_priority(base)
    for p, v in zip(params, values, strict=True):
        p.set_model(model, float(v))
        if p.contact_geoms:
            model.geom_priority[list(p.contact_geoms)] = priority
    if any(p.needs_set_const for p in params):
        mujoco.mj_setConst(model, data if data is not None else mujoco.MjData(model))
    return model


def apply_to_spec(
    spec: mujoco.MjSpec, base: mujoco.MjModel, params: Sequence[Parameter], values: Sequence[float] | np.ndarray
) -> mujoco.MjSpec:
    """Sets the parameter values in ``spec`` (in place; compiled from the same MJCF as ``base``) and returns it."""
    if len(spec.geoms) != base.ngeom or len(spec.bodies) != base.nbody or len(spec.joints) != base.njnt:
        raise GrounderError("the scene's MjSpec does not match its compiled model (geoms, bodies or joints differ)")
    _NOMINAL[id(spec)] = base
    try:
        priority = contact_priority(base)
        for p, v in zip(params, values, strict=True):
            p.set_spec(spec, float(v))
            for g in p.contact_geoms:
                spec.geoms[g].priority = priority
    finally:
        _NOMINAL.pop(id(spec), None)
    return spec
