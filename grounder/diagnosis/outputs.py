"""A diagnosis written out: ``diagnosis.json``, ``report.html`` and ``diagnosed.xml`` (the nominal MJCF with the
selected effects that MJCF can express written into it)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.diagnosis.effects import AppliedEffect, apply_effects
from grounder.diagnosis.report import render_report
from grounder.diagnosis.result import Diagnosis
from grounder.errors import GrounderError
from reconstruction import staged_output_dir


def diagnosed_spec_xml(
    scene_xml: Path, model: mujoco.MjModel, applied: list[AppliedEffect], prepared: mujoco.MjModel | None = None
) -> str:
    """The nominal MJCF with the MJCF-expressible selected effects written into it (via MjSpec): per-geom values
    (with a raised priority where one body's values must win), a ``<pair>`` for each contact pair whose values the
    effects changed, per-body masses and centres of mass, and the fluid model.

    Args:
        prepared: the model the diagnosis worked on when it gave contact pairs their own parameters
            (`grounder.diagnosis.targets.prepare`); default ``model``.
    """
    base = prepared if prepared is not None else model
    spec = mujoco.MjSpec.from_file(str(scene_xml))
    diag, _ = apply_effects(base, [a for a in applied if a.effect.in_mjcf])
    compiled = spec.compile()
    if compiled.ngeom != base.ngeom or compiled.nbody != base.nbody:
        raise GrounderError("the scene XML does not compile to the diagnosed model; cannot write the MJCF")
    spec.option.density = float(diag.opt.density)
    spec.option.viscosity = float(diag.opt.viscosity)
    geoms = {int(g.id): g for g in spec.geoms}
    for i in range(base.ngeom):
        g = geoms.get(i)
        if g is None:
            continue
        g.friction = diag.geom_friction[i].copy()
        g.solref = diag.geom_solref[i].copy()
        g.condim = int(diag.geom_condim[i])
        g.priority = int(diag.geom_priority[i])
        if diag.geom_fluid[i, 0] > 0 and (diag.opt.density > 0 or diag.opt.viscosity > 0):
            # Air drag on one body: the ellipsoid model there, zero coefficients on the others (MuJoCo's compiler
            # then adds their added mass, negligible in air).
            g.fluid_ellipsoid = 1.0
            g.fluid_coefs = diag.geom_fluid[i, 1:6].copy()
    _changed_pairs(spec, geoms, base, diag)
    for j, joint in enumerate(spec.joints):
        dof = int(model.jnt_dofadr[j])
        damping = np.atleast_1d(np.array(joint.damping, dtype=float))  # MuJoCo 4: polynomial coefficients
        damping[0] = float(diag.dof_damping[dof])
        joint.damping = damping if damping.shape[0] > 1 else float(damping[0])
        joint.frictionloss = float(diag.dof_frictionloss[dof])
        joint.armature = float(diag.dof_armature[dof])
    bodies = list(spec.bodies)
    for b in range(1, model.nbody):
        if np.allclose(diag.body_mass[b], model.body_mass[b]) and np.allclose(diag.body_ipos[b], model.body_ipos[b]):
            continue
        body = bodies[b]
        body.explicitinertial = True
        body.mass = float(diag.body_mass[b])
        body.ipos = diag.body_ipos[b].copy()
        body.iquat = diag.body_iquat[b].copy()
        body.inertia = diag.body_inertia[b].copy()
        body.fullinertia = np.full(6, np.nan)
    for a, act in enumerate(spec.actuators):
        act.gainprm[0] = float(diag.actuator_gainprm[a, 0])
    return spec.to_xml()


def _changed_pairs(spec: mujoco.MjSpec, geoms: dict[int, Any], base: mujoco.MjModel, diag: mujoco.MjModel) -> None:
    """A ``<pair>`` for each explicit pair of the diagnosed model whose values the effects changed."""
    for p in range(base.npair):
        same = (
            np.allclose(diag.pair_friction[p], base.pair_friction[p])
            and np.allclose(diag.pair_solref[p], base.pair_solref[p])
            and diag.pair_dim[p] == base.pair_dim[p]
        )
        if same:
            continue
        names = []
        for g in (int(base.pair_geom1[p]), int(base.pair_geom2[p])):
            if not geoms[g].name:
                geoms[g].name = f"diag_geom{g}"
            names.append(geoms[g].name)
        spec.add_pair(
            geomname1=names[0],
            geomname2=names[1],
            condim=int(diag.pair_dim[p]),
            friction=diag.pair_friction[p].copy(),
            solref=diag.pair_solref[p].copy(),
            solimp=diag.pair_solimp[p].copy(),
            margin=float(diag.pair_margin[p]),
            gap=float(diag.pair_gap[p]),
        )


def write_outputs(
    diag: Diagnosis, scene_xml: Path, model: mujoco.MjModel, out_dir: Path, *, overwrite: bool = False
) -> Path:
    """Writes ``diagnosis.json``, ``report.html`` and ``diagnosed.xml`` into ``out_dir`` (built aside, then moved)."""
    out_dir = Path(out_dir)
    with staged_output_dir(out_dir, overwrite=overwrite, error=GrounderError, inputs=(scene_xml,)) as staging:
        content = diag.to_json()
        content["mjcf"] = {
            "file": "diagnosed.xml",
            "expressed": [a.effect.name for a in diag.applied if a.effect.in_mjcf],
            "not_expressible": {a.effect.name: a.values for a in diag.applied if not a.effect.in_mjcf},
        }
        (staging / "diagnosis.json").write_text(json.dumps(content, indent=2, default=_json_default))
        (staging / "diagnosed.xml").write_text(diagnosed_spec_xml(scene_xml, model, diag.applied, diag.model))
        (staging / "report.html").write_text(render_report(diag))
    return out_dir


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if hasattr(obj, "__dataclass_fields__"):
        return asdict(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
