"""What `ground --interaction` reports beside the calibration: how well a scene's open-loop rollouts match the
tracked motion (`clip_match` over whole segments, `window_match` over an object's calibration windows), each
object's coefficient of restitution before and after (`scene_restitution`), and the report as Markdown
(`markdown_report`, `interaction.md`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from grounder.core.trajectory import Trajectory
from grounder.sim.restitution import REFERENCE_IMPACT_SPEED_M_S, body_restitution


def _open_loop_errors(model: Any, trajs: Sequence[Trajectory]) -> list[dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Per trajectory, each free body's per-frame position (m) and rotation (rad) error of the open-loop rollout from
    its first state (`grounder.sim.rollout.free_body_errors`)."""
    from grounder.sim.rollout import free_body_errors, simulate

    if not trajs:
        return []
    predicted = simulate(model, list(trajs))
    out = []
    for pred, real in zip(predicted, trajs, strict=True):
        assert isinstance(pred, Trajectory)
        out.append(free_body_errors(model, pred, real))
    return out


def clip_match(scene_xml: Path, trajs: Sequence[Trajectory]) -> dict[str, dict[str, float]]:
    """Per object, open-loop rollout of each tracked segment from its first state: mean / max position error (mm)
    and mean rotation error (deg) against the tracked poses, over all segments."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene_xml))
    per_body: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for errors in _open_loop_errors(model, trajs):
        for body, (pos, rot) in errors.items():
            per_body.setdefault(body, []).append((pos, rot))
    return {
        body: {
            "mean_position_error_mm": round(1e3 * float(np.mean(np.concatenate([p for p, _ in errs]))), 2),
            "max_position_error_mm": round(1e3 * float(np.max(np.concatenate([p for p, _ in errs]))), 2),
            "mean_rotation_error_deg": round(float(np.rad2deg(np.mean(np.concatenate([r for _, r in errs])))), 2),
        }
        for body, errs in per_body.items()
    }


def window_match(
    scene_xml: Path, fit: Sequence[Trajectory], params: Sequence[str], records: Mapping[str, Mapping[str, Any]]
) -> dict[str, Any]:
    """How well one object's calibration windows match before (prior) and after calibration (`records`' values):
    per window the mean position (mm) and rotation (deg) error of the open-loop rollout from its tracked start; the
    median and mean over the windows. What the calibration fits, so what it can be held to."""
    import mujoco

    from grounder.calibration.parameters import apply_to_model, resolve_parameters

    base = mujoco.MjModel.from_xml_path(str(scene_xml))
    resolved = resolve_parameters(base, list(params))
    out: dict[str, Any] = {"windows": len(fit)}
    for label, values in (
        ("before", [p.nominal for p in resolved]),
        ("after", [float(records.get(p.name, {}).get("value", p.nominal)) for p in resolved]),
    ):
        position_mm, rotation_deg = [], []
        for errors in _open_loop_errors(apply_to_model(base, resolved, values), fit):
            for pos, rot in errors.values():
                position_mm.append(1e3 * float(np.mean(pos)))
                rotation_deg.append(float(np.rad2deg(np.mean(rot))))
        out[label] = {
            "median_position_error_mm": round(float(np.median(position_mm)), 2),
            "mean_position_error_mm": round(float(np.mean(position_mm)), 2),
            "median_rotation_error_deg": round(float(np.median(rotation_deg)), 2),
            "mean_rotation_error_deg": round(float(np.mean(rotation_deg)), 2),
        }
    return out


def scene_restitution(before_xml: Path, after_xml: Path | None, objects: Sequence[str]) -> dict[str, Any]:
    """Per object, the coefficient of restitution of its contacts (`grounder.sim.restitution.body_restitution`, a
    normal impact at `REFERENCE_IMPACT_SPEED_M_S`) in the grounded scene (`before`: the property model's prior)
    and in the calibrated one (`after`; the prior's where not calibrated)."""
    import mujoco

    models = {"before": mujoco.MjModel.from_xml_path(str(before_xml))}
    if after_xml is not None:
        models["after"] = mujoco.MjModel.from_xml_path(str(after_xml))
    out: dict[str, Any] = {"impact_speed_m_s": REFERENCE_IMPACT_SPEED_M_S, "objects": {}}
    for name in objects:
        values = {key: round(body_restitution(model, name), 4) for key, model in models.items()}
        out["objects"][name] = {"before": values["before"], "after": values.get("after", values["before"])}
    return out


def markdown_report(payload: dict[str, Any]) -> str:
    lines = ["# Interaction report", "", f"Scan `{payload['scan']}`, clip `{payload['clip']}`.", "", "## Tracking", ""]
    for name, info in payload["tracking"]["objects"].items():
        lost = info["lost_frames"]
        lost_text = f"lost in frames {lost}" if lost else "never lost"
        lines.append(f"- {name}: tracked in {100 * info['tracked_fraction']:.0f}% of the frames, {lost_text}")
    spans = ", ".join(f"{s['first_frame']}-{s['last_frame']}" for s in payload["tracking"]["segments"])
    lines += ["", f"Segments with every object tracked: {spans}. Calibration sees only tracked frames.", ""]
    lines += ["![tracked outlines and per-frame status](interaction/tracks/overview.png)", ""]
    lines += ["## Calibration", "", f"Status: {payload['calibration']['status']}.", ""]
    params = payload["calibration"].get("parameters", {})
    if params:
        speed = payload.get("start_speed_error_m_s")
        draws = payload.get("start_state_errors", {}).get("draws", 0)
        probe = "start speeds " + ("off" if speed is None else f"+-{speed:g} m/s")
        if draws:
            probe = f"starts off (speeds +-{speed:g} m/s; {draws} random whole-state errors)"
        lines += [
            f"| parameter | before | after | interval | constrained by the clip | best value with {probe} |",
            "|---|---|---|---|---|---|",
        ]
        for name, p in params.items():
            seen = "yes" if p.get("constrained", True) else "no: prior kept"
            if p.get("set_with_restitution"):
                seen = "with the bounce: the restitution is resolved, this value alone is not"
            if "unresolved_fit" in p:
                seen += f" (the fit, {p['unresolved_fit']:.4g}, is not resolved where it landed)"
            starts = "-"
            if "start_error_range" in p:
                starts = "{:.4g} .. {:.4g}".format(*p["start_error_range"])
                if p.get("start_sensitive"):
                    starts += ": **rests on the start states' accuracy**"
            lines.append(
                f"| {name} | {p['nominal']:.4g} | {p['value']:.4g} | {p['interval'][0]:.4g} .. "
                f"{p['interval'][1]:.4g} | {seen} | {starts} |"
            )
        lines.append("")
        if any(p.get("start_sensitive") for p in params.values()):
            fps = payload["tracking"].get("fps")
            rate = "" if fps is None else f" This clip has {fps:g} frames per second."
            lines += [
                "A value that rests on the start states' accuracy moves past the screen's step when the windows'",
                "starts are off by a typical tracking error: treat it as a rough estimate. A clip filmed at",
                f"60 fps or more, or markers on the object, measure the starts better.{rate}",
                "",
            ]
    if payload.get("impacts_figure"):
        lines += [
            f"![each object's fit to the contacts after its free flights]({payload['impacts_figure']})",
            "",
        ]
    for body, info in payload["calibration"].get("per_object", {}).items():
        if "impacts" in info:
            hits = info["impacts"]
            lines.append(
                f"- {body}: {len(hits['names'])} contact(s) after a tracked free flight ({', '.join(hits['names'])}), "
                f"chi-square {hits['chi2']:.1f} for {hits['dof']} residuals, tracking noise across / along the "
                f"viewing ray {hits['noise_mm'][0]:.2f} / {hits['noise_mm'][1]:.2f} mm; best friction "
                f"{hits['best']['friction']:.3g}, restitution {hits['best']['restitution']:.3g}"
                + _copies_text(hits.get("stability_copies", []), hits.get("stability_um", 0.0))
            )
        if "shooting" in info:
            shot = info["shooting"]
            lines.append(
                f"- {body}: multiple shooting over {shot['nodes']} nodes ({len(shot['runs'])} run(s)), best cost "
                f"{shot['cost']:.1f} of {len(shot['evaluations'])} points searched"
            )
        for refit in info.get("start_refinement", []):
            fits = refit["windows"]
            if fits:
                velocity = [f["velocity_change_m_s"] for f in fits]
                position = [f["position_change_mm"] for f in fits]
                lines.append(
                    f"- {body}, start refit {refit['round']}: {len(fits)} windows, start velocity moved by median "
                    f"{np.median(velocity):.3f} m/s (max {max(velocity):.3f}), position by median "
                    f"{np.median(position):.1f} mm (max {max(position):.1f})"
                )
    if payload["calibration"].get("per_object"):
        lines.append("")
    bounce = payload.get("restitution", {})
    if bounce.get("objects"):
        speed = bounce["impact_speed_m_s"]
        lines += [
            f"## Bounce: coefficient of restitution of each object's contacts ({speed:g} m/s normal impact)",
            "",
            "MuJoCo's contact has no restitution parameter; this is the bounce its time constant and damping ratio",
            "produce in this scene (a drop test, `grounder.sim.restitution`).",
            "",
            "| object | before | after | range the clip allows (shooting: within the resolution cost; impacts: "
            "within the chi-square threshold) |",
            "|---|---|---|---|",
        ]
        for name, e in bounce["objects"].items():
            shot = payload["calibration"].get("per_object", {}).get(name, {}).get("restitution")
            span = "-"
            if shot:
                span = "{:.3f} .. {:.3f}".format(*shot["range"]) + ("" if shot["resolved"] else " (not resolved)")
            lines.append(f"| {name} | {e['before']:.3f} | {e['after']:.3f} | {span} |")
        lines.append("")
    lines += ["## Match with the clip", ""]
    per_object = {b: i["window_match"] for b, i in payload["calibration"].get("per_object", {}).items()}
    if any(per_object.values()):
        lines += [
            "Calibration windows (what calibration fits): each rolled out open loop from its tracked start; per",
            "window the mean error over its frames, then the median (and mean) over the object's windows:",
            "",
            "| object | windows | position error before (mm) | after (mm) | rotation error before (deg) | after |",
            "|---|---|---|---|---|---|",
        ]
        for name, m in per_object.items():
            if not m:
                lines.append(f"| {name} | 0 | - | - | - | - |")
                continue
            b, a = m["before"], m["after"]
            lines.append(
                f"| {name} | {m['windows']} | {b['median_position_error_mm']} ({b['mean_position_error_mm']}) | "
                f"{a['median_position_error_mm']} ({a['mean_position_error_mm']}) | "
                f"{b['median_rotation_error_deg']} ({b['mean_rotation_error_deg']}) | "
                f"{a['median_rotation_error_deg']} ({a['mean_rotation_error_deg']}) |"
            )
        lines += [""]
    lines += [
        "Whole tracked segments, open loop from the first tracked state. After the first bounce a tossed object's",
        "motion hinges on that state (often in the air, where tracking is least certain), so this figure can grow",
        "even as the windows above improve:",
        "",
    ]
    lines += ["| object | mean position error before (mm) | after (mm) | mean rotation error before (deg) | after |"]
    lines += ["|---|---|---|---|---|"]
    after = payload.get("match_after", {})
    for name, before in payload["match_before"].items():
        a = after.get(name, {})
        lines.append(
            f"| {name} | {before['mean_position_error_mm']} | {a.get('mean_position_error_mm', '-')} | "
            f"{before['mean_rotation_error_deg']} | {a.get('mean_rotation_error_deg', '-')} |"
        )
    return "\n".join(lines) + "\n"


def _copies_text(copies: Sequence[Mapping[str, Any]], moved_um: float) -> str:
    """The report's words for the impacts' stability copies (`ImpactOptions.stability_copies`): each copy's best
    friction and restitution, "?" where it did not resolve them."""
    if not copies:
        return ""

    def value(copy: Mapping[str, Any], name: str) -> str:
        return f"{copy[name]:.3g}" if copy[f"{name}_resolved"] else "?"

    shown = "; ".join(f"{value(c, 'friction')}, {value(c, 'restitution')}" for c in copies)
    return f"; on copies of the tracks moved by {moved_um:g} um (friction, restitution; ? not resolved): {shown}"
