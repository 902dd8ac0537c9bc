"""Calibration one object at a time, for objects that never touch each other (`separable_bodies`): each object in a
scene of its own with the table (`single_body_scene`), calibrated by the method `InteractionOptions.calibration`
names (`calibrate_per_body`: its impacts, `grounder.interaction.impacts`, then windows for what they leave; windows,
`grounder.interaction.windows`; or multiple shooting, `shoot_body`), and the values found written into the whole
scene (`write_values` where no whole-scene trajectory can evaluate them).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.errors import GrounderError
from grounder.interaction.impacts import impacts_body
from grounder.interaction.options import InteractionOptions
from grounder.interaction.record import fit_status, fitted_record, prior_record
from grounder.interaction.report import window_match
from grounder.interaction.shooting import ShootingOptions, fit_contact, moving_runs
from grounder.interaction.windows import calibrate_constrained, object_windows, view_settings
from grounder.sim.restitution import REFERENCE_IMPACT_SPEED_M_S
from image2sim_common.progress import ProgressFn


def separable_bodies(scene_xml: Path, trajs: Sequence[Trajectory], clearance_m: float = 0.005) -> bool:
    """Whether the scene's free bodies stay at least `clearance_m` apart in every sample of `trajs` (collision
    geometry), so that each moves as if alone with the table and can be calibrated on its own."""
    import mujoco

    from grounder.sim.rollout import free_joints

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    bodies = [model.body(fj.body).id for fj in free_joints(model)]
    geoms = {
        b: [
            g
            for g in range(model.ngeom)
            if model.geom_bodyid[g] == b and (model.geom_contype[g] or model.geom_conaffinity[g])
        ]
        for b in bodies
    }
    pairs = [(g1, g2) for i, b1 in enumerate(bodies) for b2 in bodies[i + 1 :] for g1 in geoms[b1] for g2 in geoms[b2]]
    if not pairs:
        return True
    data = mujoco.MjData(model)
    for traj in trajs:
        for qpos in traj.qpos:
            data.qpos[:] = qpos
            mujoco.mj_kinematics(model, data)
            for g1, g2 in pairs:
                if mujoco.mj_geomDistance(model, data, g1, g2, clearance_m, None) < clearance_m:
                    return False
    return True


def calibrate_per_body(
    scene_xml: Path,
    segments: Sequence[Trajectory],
    params: Sequence[str],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    object_tracks: Mapping[str, Sequence[Trajectory]] | None = None,
    out: Path | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], list[str]]:
    """Screens and calibrates each object's parameters in a scene of its own (the object and the table).

    For objects that never touch each other (`separable_bodies`): each object's tracked motion is cut into windows
    that start only where its state is well measured (`reliable_starts`), and its parameters are screened and fitted
    on those, alone (a few dimensions, with no other object's tracking errors in the loss). The values found are
    then written into the whole scene (`out`), evaluated on the whole tracked segments. `view_point_m`: as in
    `calibrate_constrained`. `object_tracks`: per object, single-body trajectories of its own tracked frames
    (`grounder.tracking.output.object_trajectories`) to cut its windows from, instead of its columns of `segments`
    (the frames in which every object is tracked).

    Returns:
        The report's `calibration` entry (as `calibrate_constrained`'s, with `windows` per object) and the names of
        all windows used.
    """
    import mujoco

    from grounder.calibration.fit import calibrate
    from grounder.calibration.options import CalibrateOptions
    from grounder.calibration.parameters import resolve_parameters
    from grounder.sim.rollout import free_joints

    model = mujoco.MjModel.from_xml_path(str(scene_xml))

    bodies = [fj.body for fj in free_joints(model)]
    by_body: dict[str, list[str]] = {}
    for name in params:
        body = name.split(".", 1)[0]
        if body not in bodies:
            raise GrounderError(f"{name}: per-object calibration needs parameters of the scene's objects {bodies}")
        by_body.setdefault(body, []).append(name)
    entry: dict[str, Any] = {"parameters": {}, "per_object": {}}
    used: list[str] = []
    values: dict[str, float] = {}
    for body, body_params in by_body.items():
        with single_body_scene(scene_xml, body) as sub_xml:
            body_trajs = (
                list(object_tracks[body])
                if object_tracks is not None
                else [_single_body_trajectory(model, t, body) for t in segments]
            )
            match: dict[str, Any] = {}
            if options.calibration == "shooting":
                sub, fit = shoot_body(
                    sub_xml, body_trajs, body_params, options.shooting, view_point_m=view_point_m, progress=progress
                )
                fit_names = [t.name for t in fit]
            elif options.calibration == "impacts":
                sub, fit_names = impacts_body(
                    sub_xml, body_trajs, body_params, options.impacts, view_point_m=view_point_m, progress=progress
                )
                if options.impacts.windows_for_unresolved:
                    fit = _windows_for_unresolved(
                        sub_xml, body_trajs, body_params, sub, options, view_point_m=view_point_m, progress=progress
                    )
                    fit_names += [t.name for t in fit]
                    if fit:
                        match = window_match(sub_xml, fit, body_params, sub["parameters"])
            else:
                fit = object_windows(body_trajs, options)
                fit_names = [t.name for t in fit]
                sub = {"status": "skipped: no well-measured window shows motion", "parameters": {}}
                if fit:
                    sub = calibrate_constrained(
                        sub_xml, fit, body_params, options, view_point_m=view_point_m, progress=progress
                    )
                    match = window_match(sub_xml, fit, body_params, sub["parameters"])
            used += [f"{body}:{name}" for name in fit_names]
        entry["per_object"][body] = {
            "status": sub["status"],
            "windows": fit_names,
            "start_refinement": sub.get("start_refinement", []),
            "window_match": match,
        }
        if "shooting" in sub:
            entry["per_object"][body]["shooting"] = sub["shooting"]
        if "impacts" in sub:
            entry["per_object"][body]["impacts"] = sub["impacts"]
        if "restitution" in sub:
            entry["per_object"][body]["restitution"] = sub["restitution"]
        for name in body_params:
            record = sub["parameters"].get(name, {})
            entry["parameters"][name] = record
            if record.get("constrained"):
                values[name] = record["value"]
    resolved = {p.name: p for p in resolve_parameters(model, list(params))}
    for name, record in entry["parameters"].items():
        if "value" not in record:  # skipped body: the prior, unconstrained
            record.update(prior_record(resolved[name]))
    unconstrained = [n for n, r in entry["parameters"].items() if not r.get("constrained")]
    if not values:
        entry["status"] = "skipped: the clip constrains none of the parameters (prior kept)"
        return entry, used
    if not segments:
        if out is not None:
            write_values(scene_xml, values, out)
        entry["status"] = (
            "calibrated per object; no segment has every object tracked at once, so the values were not evaluated "
            "on the whole scene"
            + (f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else "")
        )
        return entry, used
    result = calibrate(
        scene_xml.parent if scene_xml.name == "scene.xml" else scene_xml,
        list(segments),
        options=CalibrateOptions(
            params=tuple(values),
            initial=values,
            generations=0,
            local_iterations=0,
            validation_fraction=0.0,
            rotation_weight=options.rotation_weight,
            **view_settings(options, view_point_m),
        ),
        out=out,
        progress=progress,
    )
    entry["status"] = "calibrated per object" + (
        f"; unconstrained by the clip, prior kept: {unconstrained}" if unconstrained else ""
    )
    entry.update(
        train=list(result.train_names),
        validation=[],
        before={k: v.as_dict() for k, v in result.before.items()},
        after={k: v.as_dict() for k, v in result.after.items()},
    )
    return entry, used


def _windows_for_unresolved(
    sub_xml: Path,
    body_trajs: Sequence[Trajectory],
    params: Sequence[str],
    sub: dict[str, Any],
    options: InteractionOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> list[Trajectory]:
    """With `calibration` "impacts": the values the impacts left unresolved are screened and calibrated on the
    object's windows (as `calibration` "windows" does), in its scene with the impacts' resolved values written in;
    their records in `sub` are replaced (marked `"method": "windows"`) and `sub["status"]` says so. A windowed value
    flagged as resting on the start states' accuracy (`start_sensitive`, `start_error_ranges`) keeps the prior
    (its fit is `unresolved_fit`): on five clips of scan D the windows' values for the can were all wrong by 20-34%
    and all flagged. A bounce the impacts resolved keeps its time constant and damping ratio together. Returns the
    windows (none where nothing was left or no window shows motion)."""
    import mujoco

    from grounder.calibration.parameters import apply_to_spec, resolve_parameters

    records = sub["parameters"]
    fixed = {name: r["value"] for name, r in records.items() if r.get("constrained")}
    rest = [name for name in params if not records.get(name, {}).get("constrained")]
    if not rest:
        return []
    fit = object_windows(body_trajs, options)
    if not fit:
        return []
    base = mujoco.MjModel.from_xml_path(str(sub_xml))
    scene = sub_xml
    if fixed:
        spec = mujoco.MjSpec.from_file(str(sub_xml))
        resolved = resolve_parameters(base, list(fixed))
        apply_to_spec(spec, base, resolved, [fixed[p.name] for p in resolved])
        scene = sub_xml.with_name(f"{sub_xml.stem}_impacts.xml")  # in `single_body_scene`'s private folder
        scene.write_text(spec.to_xml())
    windowed = calibrate_constrained(scene, fit, rest, options, view_point_m=view_point_m, progress=progress)
    parameters = {p.name: p for p in resolve_parameters(base, rest)}
    for name in rest:
        record = dict(windowed["parameters"][name])
        if record.get("constrained") and record.get("start_sensitive"):
            # A windowed value that moves past the screen's step under tracking-sized start errors is not taken
            # here: the impacts, which do not rest on the starts, could not resolve it either.
            record = {**prior_record(parameters[name]), "unresolved_fit": record["value"], "start_sensitive": True}
        if "unresolved_fit" in records.get(name, {}):
            record["impacts_unresolved_fit"] = records[name]["unresolved_fit"]
        record["method"] = "windows"
        records[name] = record
    calibrated = [n for n in rest if records[n].get("constrained")]
    sub["status"] += f"; on {len(fit)} window(s), the values the impacts left: {windowed['status']}" + (
        f" (calibrated there: {calibrated})" if calibrated else ""
    )
    return fit


def shoot_body(
    scene_xml: Path,
    body_trajs: Sequence[Trajectory],
    params: Sequence[str],
    options: ShootingOptions,
    *,
    view_point_m: Sequence[float] | None = None,
    progress: ProgressFn | None = None,
) -> tuple[dict[str, Any], list[Trajectory]]:
    """Calibrates one object's contact values in its own scene by multiple shooting over its tracked runs
    (`InteractionOptions.calibration` "shooting").

    Returns the object's calibration entry (as `calibrate_constrained`'s: `status`, per parameter `nominal`,
    `value`, `interval`, `bounds`, `unit`, `constrained`, and `indistinguishable`: the values within
    `options.resolution_cost` of the best cost; an unresolved value keeps the prior and its best point is
    `unresolved_fit`; `shooting`: nodes, runs, cost and the points searched) and the runs used.
    """
    import mujoco

    from grounder.calibration.parameters import resolve_parameters

    runs = []
    if body_trajs:
        fps = 1.0 / float(np.median(np.concatenate([np.diff(t.time_s) for t in body_trajs])))
        runs = moving_runs(body_trajs, fps, options)
    if not runs:
        return {"status": "skipped: no tracked run shows motion", "parameters": {}}, []
    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    contact = resolve_parameters(model, list(params))
    result = fit_contact(model, contact, runs, options, view_point_m=view_point_m, progress=progress)
    records = {
        parameter.name: fitted_record(parameter, value, span, ok)
        for parameter, value, span, ok in zip(contact, result.values, result.ranges, result.resolved, strict=True)
    }
    bounce = result.restitution
    restitution: dict[str, Any] = {}
    if bounce is not None:
        restitution = {
            "value": bounce.value,
            "range": list(bounce.range),
            "resolved": bounce.resolved,
            "impact_speed_m_s": REFERENCE_IMPACT_SPEED_M_S,
        }
        if bounce.resolved:
            # The bounce pins the pair (time constant, damping ratio), not each value: where one of them is not
            # resolved by itself, keeping its prior beside the other's fit would bounce differently from the fit.
            for parameter, value in zip(contact, result.values, strict=True):
                record = records[parameter.name]
                if ".solref." in parameter.name and not record["constrained"]:
                    record.pop("unresolved_fit", None)
                    record.update(value=value, interval=record["indistinguishable"], constrained=True)
                    record["set_with_restitution"] = True
    status = fit_status(
        f"multiple shooting ({result.nodes} nodes over {len(runs)} run(s), cost {result.cost:.1f}, "
        f"{len(result.evaluations)} points searched)",
        records,
    )
    shooting = {
        "nodes": result.nodes,
        "runs": [t.name for t in runs],
        "cost": round(result.cost, 3),
        "evaluations": [{"values": list(v), "cost": round(c, 3)} for v, c in result.evaluations],
    }
    entry = {"status": status, "parameters": records, "shooting": shooting}
    if restitution:
        entry["restitution"] = restitution
    return entry, runs


def _single_body_trajectory(model: Any, traj: Trajectory, body: str) -> Trajectory:
    """The columns of one free body of a trajectory of a scene with free bodies only."""
    from grounder.sim.rollout import free_joints

    joint = next(fj for fj in free_joints(model) if fj.body == body)
    dof = int(model.jnt_dofadr[model.body(body).jntadr[0]])
    return Trajectory(
        time_s=traj.time_s,
        qpos=traj.qpos[:, joint.pos.start : joint.pos.start + 7],
        qvel=traj.qvel[:, dof : dof + 6],
        name=traj.name,
    )


@contextmanager
def single_body_scene(scene_xml: Path, body: str) -> Iterator[Path]:
    """The scene with only `body` of its free bodies (and the table), as an MJCF file in a private temporary folder
    that is removed afterwards.

    A private folder with a copy of the scene's mesh and texture files: written beside scene.xml under a fixed name,
    two calibrations of one scene at once (batch jobs, two terminals) deleted each other's file mid-run, and a
    read-only scene folder could not be calibrated at all. A copy rather than absolute asset paths, because a scene
    may not name files outside its folder (`grounder.sim.scene_files.scene_files`).
    """
    import mujoco

    from grounder.sim.scene_files import copy_scene_files

    single = mujoco.MjSpec.from_file(str(scene_xml))
    for other in list(single.worldbody.bodies):  # a free joint can only sit on a child of the world
        if other.name != body and any(j.type == mujoco.mjtJoint.mjJNT_FREE for j in other.joints):
            single.delete(other)
    tmp = Path(tempfile.mkdtemp(prefix="image2sim_calibrate_"))
    try:
        copy_scene_files(scene_xml, tmp)
        sub_xml = tmp / f"{body}.xml"
        sub_xml.write_text(single.to_xml())
        yield sub_xml
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_values(scene_xml: Path, values: Mapping[str, float], out: Path) -> Path:
    """Writes `out/scene.xml` (with the scene folder's files): the scene with the given parameter values, and their
    record in its `scene.json`. For when the values were fitted per object and no whole-scene trajectory exists to
    evaluate them on (`calibrate` writes the scene otherwise)."""
    import mujoco

    from grounder.calibration.parameters import apply_to_spec, resolve_parameters
    from grounder.calibration.scene_output import NOT_COPIED
    from grounder.sim.scene_files import copy_scene_files

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    spec = mujoco.MjSpec.from_file(str(scene_xml))
    resolved = resolve_parameters(base, list(values))
    apply_to_spec(spec, base, resolved, [values[p.name] for p in resolved])
    out.mkdir(parents=True)
    copy_scene_files(scene_xml.parent, out, skip=NOT_COPIED)
    (out / "scene.xml").write_text(spec.to_xml())
    reloaded = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    if reloaded.nq != base.nq or reloaded.nv != base.nv:
        raise GrounderError("the written scene.xml does not match the scene's joints")
    manifest = out / "scene.json"
    if manifest.is_file():
        data = json.loads(manifest.read_text())
        data["calibration"] = {
            "mode": "per object, no whole-scene evaluation",
            "parameters": dict(values),
            "note": "scene.xml holds the calibrated values; per-object entries above are from before calibration",
        }
        manifest.write_text(json.dumps(data, indent=1) + "\n")
    return out / "scene.xml"
