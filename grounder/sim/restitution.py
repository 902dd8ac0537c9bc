"""The coefficient of restitution a MuJoCo contact actually produces.

MuJoCo has no restitution parameter. A contact's bounce follows from its `solref` (time constant, damping ratio
d), its `solimp`, and the scene's physics settings (time step, integrator, gravity). Two mappings from d alone miss it:
- The textbook one of a linear spring-damper, e = exp(-pi d / sqrt(1 - d^2)), lets the contact pull the object
  back. MuJoCo's contact force never pulls, so the object lets go earlier and bounces higher: e is that of a
  spring-dashpot whose force is clipped at zero (Schwager and Poeschel, Phys. Rev. E 2007): d 0.2 gives 0.572 where
  the textbook says 0.527, d 0.4 0.364 against 0.254 (measured here within 0.5% at a long time constant, without
  gravity: `tests/grounder/sim/test_restitution.py`).
- Neither holds where the time constant is a few time steps: the bounce then depends on where within a step the
  impact falls. At the scene step of 2 ms, a time constant of 0.0087 s and d 0.2175 bounce at 0.39 to 0.78 over the
  phases of a 1 m/s impact (0.56 on average), and (time constant, damping ratio) pairs trade: (0.0087 s, 0.218) and
  (0.02 s, 0.15) bounce at 0.57 and 0.64. A clip, which shows bounces, pins e, not the damping ratio alone.

`simulated_restitution` measures e the way a drop test would: a small sphere with the contact's `solref` and
`solimp` hits a plane at a given normal speed in a scene with the given physics settings (gravity included); e is
its upward speed the step after the contact lets go, over the impact speed, averaged over `_PHASES` impact phases
within a time step. Friction plays no part in a normal impact (condim 1 to 6 give the same e); mass and size do not
either, as a standard `solref` scales stiffness and damping by the contact's effective mass.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import mujoco
import numpy as np

from grounder.calibration.parameters import collision_geoms
from grounder.errors import GrounderError

REFERENCE_IMPACT_SPEED_M_S = 1.0  # about the landing speed of an object dropped from 5 cm
_SPHERE_RADIUS_M = 0.01
_SPHERE_MASS_KG = 0.05
_PHASES = 8  # impact phases within a time step, averaged
_MAX_CONTACT_S = 1.0  # a contact that holds this long is taken as no bounce (e = 0)
# Physics settings copied from the scene, so that the drop runs as a contact of that scene would.
_OPTION_FIELDS = (
    "timestep",
    "integrator",
    "cone",
    "impratio",
    "gravity",
    "solver",
    "iterations",
    "tolerance",
    "ls_iterations",
    "ls_tolerance",
    "noslip_iterations",
    "noslip_tolerance",
    "disableflags",
    "enableflags",
    "o_solref",
    "o_solimp",
)


def simulated_restitution(
    solref: Sequence[float],
    solimp: Sequence[float],
    option: Any | None = None,
    impact_speed_m_s: float = REFERENCE_IMPACT_SPEED_M_S,
) -> float:
    """Coefficient of restitution of a normal impact on a contact with this `solref` and `solimp` (module docstring):
    the mean of `restitution_over_phases`."""
    return float(np.mean(restitution_over_phases(solref, solimp, option, impact_speed_m_s)))


def bounce_spread(ratios: np.ndarray) -> float:
    """How much a contact's bounce depends on where within a time step the impact falls: (highest - lowest) over the
    mean of `restitution_over_phases`. About 0.2 at a time constant of 10 steps (0.02 s at 2 ms) and damping ratio
    0.15-0.3; 0.6-1.4 at 3-4 steps, where single phases bounce at e > 1 (a contact too stiff for the step)."""
    mean = float(np.mean(ratios))
    return float((np.max(ratios) - np.min(ratios)) / mean) if mean > 0 else 0.0


def restitution_over_phases(
    solref: Sequence[float],
    solimp: Sequence[float],
    option: Any | None = None,
    impact_speed_m_s: float = REFERENCE_IMPACT_SPEED_M_S,
) -> np.ndarray:
    """Per impact phase within a time step (`_PHASES` of them), the coefficient of restitution of a normal impact
    on a contact with this `solref` and `solimp` (module docstring).

    Args:
        solref: (time constant s, damping ratio), MuJoCo's standard form.
        solimp: (dmin, dmax, width m, midpoint, power).
        option: the physics settings to drop under (an `MjModel.opt`, or None for MuJoCo's defaults).
        impact_speed_m_s: normal speed at first touch.

    Returns:
        Rebound speed over impact speed, per phase; 0 where the sphere never leaves the plane. Can exceed 1 where a
        contact too stiff for the time step gains energy.

    Raises:
        GrounderError: a direct (negative) or non-finite solref, a bad solimp, or a speed that is not positive.
    """
    solref_v = np.asarray(solref, float)
    solimp_v = np.asarray(solimp, float)
    if solref_v.shape != (2,) or not np.all(np.isfinite(solref_v)) or np.any(solref_v <= 0):
        raise GrounderError(
            f"solref={list(solref)} but restitution needs the standard form (time constant s > 0, damping ratio > 0)"
        )
    if solimp_v.shape != (5,) or not (0 < solimp_v[0] <= solimp_v[1] < 1 and solimp_v[2] > 0):
        raise GrounderError(
            f"solimp={list(solimp)} but expected (dmin, dmax, width, midpoint, power), 0 < dmin <= dmax < 1"
        )
    if not (np.isfinite(impact_speed_m_s) and impact_speed_m_s > 0):
        raise GrounderError(f"impact_speed_m_s={impact_speed_m_s} but expected a positive speed, e.g. 1.0")

    spec = mujoco.MjSpec()
    if option is not None:
        for field in _OPTION_FIELDS:
            setattr(
                spec.option,
                field,
                np.array(getattr(option, field)) if field.startswith(("o_", "grav")) else getattr(option, field),
            )
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1.0, 1.0, 0.1], condim=1)
    body = spec.worldbody.add_body()
    body.add_freejoint()
    body.add_geom(
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[_SPHERE_RADIUS_M, 0, 0],
        mass=_SPHERE_MASS_KG,
        condim=1,
        priority=1,  # the sphere's solref and solimp govern the contact, unmixed with the plane's
        solref=solref_v.tolist(),
        solimp=solimp_v.tolist(),
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    ratios = []
    for phase in np.arange(_PHASES) / _PHASES:
        mujoco.mj_resetData(model, data)
        # First touch `phase` of a step after a step starts: impacts in a clip fall anywhere within a step.
        data.qpos[2] = _SPHERE_RADIUS_M + phase * impact_speed_m_s * model.opt.timestep
        data.qvel[2] = -impact_speed_m_s
        ratios.append(_rebound_speed_m_s(model, data) / impact_speed_m_s)
    return np.array(ratios)


def _rebound_speed_m_s(model: Any, data: Any) -> float:
    """Upward speed of the sphere the step after its contact lets go; 0 if it never does."""
    touched = False
    for _ in range(int(np.ceil(_MAX_CONTACT_S / model.opt.timestep))):
        mujoco.mj_step(model, data)
        if data.ncon:
            touched = True
        elif touched and data.qvel[2] > 0:
            return float(data.qvel[2])
    return 0.0


def body_restitution(model: Any, body: str, impact_speed_m_s: float = REFERENCE_IMPACT_SPEED_M_S) -> float:
    """`simulated_restitution` of a body's contacts in `model` (`body_restitution_over_phases`' mean)."""
    return float(np.mean(body_restitution_over_phases(model, body, impact_speed_m_s)))


def body_restitution_over_phases(
    model: Any, body: str, impact_speed_m_s: float = REFERENCE_IMPACT_SPEED_M_S
) -> np.ndarray:
    """`restitution_over_phases` of a body's contacts in `model`: the `solref` and `solimp` of its first colliding
    geom (a grounded object's hulls share them, and outrank the table's by priority) under the model's settings.

    Raises:
        GrounderError: no such body, or it has no colliding geom.
    """
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        raise GrounderError(f"no body named {body!r} in the model; pass one of the scene's object names")
    geoms = collision_geoms(model, body_id)
    if not geoms:
        raise GrounderError(f"body {body!r} has no colliding geom, so no contact to take a restitution from")
    g = geoms[0]
    return restitution_over_phases(model.geom_solref[g], model.geom_solimp[g], model.opt, impact_speed_m_s)


# ---------------------------------------------------------------- the solref to write for a wanted bounce

# The stiffest contact written for a predicted restitution, in time steps. Below 6 steps the bounce turns on where
# within a step an impact falls: at 2 ms, bounces of e 0.2-0.8 vary by (highest - lowest) / mean 0.39-0.45 over
# the impact phases at 0.012 s and by 0.46-0.79 at 0.01 s, where e 0.8 is out of reach (damping ratios just below
# the one for 0.7 bounce at e > 1). Material time constants (hard plastics, ceramic, metal: 0.005-0.01 s) are
# stiffer than that; a 2 ms step cannot resolve them, so they are softened to this floor.
MIN_TIMECONST_STEPS = 6.0
# The bounce table `contact_solref` inverts: damping ratios and time constants (from the floor up) it drop-tests.
_TABLE_DAMPRATIOS = np.geomspace(0.01, 3.0, 36)
_TABLE_TIMECONST_ROWS = 8
_TABLE_MAX_TIMECONST_S = 0.2


def contact_solref(
    restitution: float, timeconst_s: float, export: Any | None = None, solimp: Sequence[float] | None = None
) -> tuple[float, float]:
    """The `solref` (time constant s, damping ratio) to write for a contact that should bounce at `restitution`
    (`simulated_restitution` at `REFERENCE_IMPACT_SPEED_M_S`) in a scene exported with `export`'s physics settings.

    The time constant is `timeconst_s`, raised to `MIN_TIMECONST_STEPS` time steps where it is stiffer; the damping
    ratio is read off a table of drop tests at that time constant (interpolated in log damping ratio and log time
    constant; a smooth enough function of both for numerical derivatives). The textbook exp(-pi d / sqrt(1 - d^2))
    would miss: MuJoCo's contacts cannot pull, and at a few steps per time constant the step matters (module
    docstring). A restitution beyond what the table's damping ratios (0.01-3) give gets the nearest end, and a time
    constant past the table's last row (0.2 s) that row's damping ratio. Measured against the drop test at the
    default settings: within 4% for e 0.2-0.95 at time constants 0.012-0.06 s (e 0.05-0.1: up to 28% low at 0.02 s).
    At the floor, bounces above 0.75 still vary with the impact's phase by more than half (`bounce_spread`).

    Args:
        restitution: the wanted coefficient of restitution, in [0, 1] (0 and 1 get the table's ends).
        timeconst_s: the wanted contact time constant, > 0.
        export: a `scene_export.ExportOptions` (None: its defaults, the scenes `image2sim ground` writes).
        solimp: the contact's solimp (None: `scene_export.SceneObjectSpec`'s default).

    Raises:
        GrounderError: a restitution outside [0, 1] or a time constant that is not positive.
    """
    from scene_export import ExportOptions, SceneObjectSpec

    if not (np.isfinite(restitution) and 0.0 <= restitution <= 1.0):
        raise GrounderError(f"restitution={restitution} but expected a coefficient in [0, 1], e.g. 0.5")
    if not (np.isfinite(timeconst_s) and timeconst_s > 0.0):
        raise GrounderError(f"timeconst_s={timeconst_s} but expected a positive contact time constant, e.g. 0.02")
    export = export if export is not None else ExportOptions()
    solimp_t = tuple(float(v) for v in (solimp if solimp is not None else SceneObjectSpec.solimp))
    timeconsts_s, bounce_rows = _bounce_table(export, solimp_t)
    timeconst_s = float(max(timeconst_s, timeconsts_s[0]))
    # Where the time constant falls between the table's rows (log spaced), and each row's damping ratio for the bounce.
    u = float(np.interp(np.log(timeconst_s), np.log(timeconsts_s), np.arange(len(timeconsts_s))))
    i = min(int(u), len(timeconsts_s) - 2)
    w = u - i
    log_d = [float(np.interp(-restitution, -bounces, np.log(_TABLE_DAMPRATIOS))) for bounces in bounce_rows[i : i + 2]]
    return timeconst_s, float(np.exp((1.0 - w) * log_d[0] + w * log_d[1]))


@functools.lru_cache(maxsize=8)
def _bounce_table(export: Any, solimp: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Time constants (T,) from the floor to `_TABLE_MAX_TIMECONST_S`, and per time constant the mean bounce at each
    of `_TABLE_DAMPRATIOS` (T, D), made non-increasing and strictly decreasing (by 1e-9 per entry) in the damping
    ratio so that it inverts (about 300 drop tests, 1-2 s, once per settings)."""
    spec = mujoco.MjSpec()
    export.set_physics(spec.option)
    option = spec.compile().opt
    timeconsts_s = np.geomspace(MIN_TIMECONST_STEPS * option.timestep, _TABLE_MAX_TIMECONST_S, _TABLE_TIMECONST_ROWS)
    rows = []
    for timeconst in timeconsts_s:
        bounces = [simulated_restitution((timeconst, d), solimp, option) for d in _TABLE_DAMPRATIOS]
        rows.append(np.minimum.accumulate(bounces) - 1e-9 * np.arange(len(bounces)))
    return timeconsts_s, np.array(rows)
