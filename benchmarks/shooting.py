"""Contact values by multiple shooting over each object's whole tracked run (`grounder.interaction.shooting`),
against the rendered values and the windowed calibration of the same run.

    .venv/bin/python benchmarks/shooting.py --run OUT --clip CLIP [--bodies object_0,object_2] [--grid]

OUT: a `benchmarks/track.py --calibrate --out OUT` run (its `grounded/` scene, `interaction/tracks/` and
`interaction.json`); CLIP: the clip it tracked (with its `truth/`), e.g. `samples/toss` or `out/tossB` from
`samples/make_toss.py --heldout`. By default searches sliding friction, damping ratio and time constant, the node
states fitted at each point (`fit_contact`), and prints each value, its range and whether it is resolved; `--grid`
instead prints each object's cost table over sliding friction x damping ratio with the time constant at the prior
(`contact_profile`), the best point and the range within `ShootingOptions.resolution_cost`. Counts friction and
damping ratio within 20% of the rendered ones; an unresolved value is not counted as either. 1-10 min per object on
2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import mujoco

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from track import contact_values, truth_offsets  # noqa: E402

from grounder.calibration.parameters import Parameter, collision_geoms, resolve_parameters  # noqa: E402
from grounder.interaction.options import InteractionOptions  # noqa: E402
from grounder.interaction.per_object import single_body_scene  # noqa: E402
from grounder.interaction.shooting import ShootingOptions, contact_profile, fit_contact, moving_runs  # noqa: E402
from grounder.interaction.tracks import camera_poses_of, view_point_of  # noqa: E402
from grounder.sim.restitution import body_restitution, simulated_restitution  # noqa: E402
from grounder.tracking.output import load_object_trajectories  # noqa: E402

FIELDS = ("friction.sliding", "solref.dampratio")
JOINT_FIELDS = (*FIELDS, "solref.timeconst")


def contact_setter(friction: Parameter, damping: Parameter) -> Callable[[mujoco.MjModel, float, float], None]:
    """`contact_profile`'s setter of (sliding friction, damping ratio) through the calibration's parameters."""

    def set_contact(model: mujoco.MjModel, mu: float, zeta: float) -> None:
        friction.set_model(model, mu)
        damping.set_model(model, zeta)

    return set_contact


def resolved(best: float, span: tuple[float, float], grid: tuple[float, ...]) -> bool:
    """A value is resolved unless its range covers the grid or reaches 20% past the best point on both sides."""
    if span == (grid[0], grid[-1]):
        return False
    return not (span[0] < best / 1.2 and span[1] > best * 1.2)


def tally(counts: list[int], resolved_value: bool, error_pct: float) -> None:
    """Counts one value as within 20% (index 0), wrong (1) or unresolved (2)."""
    counts[2 if not resolved_value else 0 if abs(error_pct) <= 20 else 1] += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a benchmarks/track.py --calibrate --out folder")
    parser.add_argument("--clip", type=Path, required=True, help="the clip it tracked (with truth/)")
    parser.add_argument("--bodies", default="", help="comma-separated object names (default: all)")
    parser.add_argument("--grid", action="store_true", help="the cost table over a grid (time constant at the prior)")
    parser.add_argument("--node-frames", type=int, default=None, help="ShootingOptions.node_frames (default: its)")
    parser.add_argument(
        "--cross-fit", type=int, default=None, help="ShootingOptions.cross_fit_points (default: its, 0: off)"
    )
    parser.add_argument("--save", type=Path, default=None, help="write each object's points and costs here (JSON)")
    args = parser.parse_args()
    scene, tracks = args.run / "grounded", args.run / "interaction" / "tracks"
    for needed in (scene / "scene.xml", tracks / "track.json", args.clip / "truth" / "scene.xml"):
        if not needed.is_file():
            parser.error(f"{needed} not found; --run takes a `benchmarks/track.py --calibrate --out` folder and "
                         "--clip the clip it tracked")  # fmt: skip
    objects = list(json.loads((scene / "scene.json").read_text())["objects"])
    bodies = args.bodies.split(",") if args.bodies else objects
    if unknown := sorted(set(bodies) - set(objects)):
        parser.error(f"--bodies {unknown}: not objects of {scene} ({objects})")
    track_json = json.loads((tracks / "track.json").read_text())
    fps = float(track_json["fps"])
    view = view_point_of(camera_poses_of(track_json["world_from_cam"]))
    object_tracks = load_object_trajectories(tracks / "track.json", InteractionOptions().track.smoothing)
    rendered = contact_values(args.clip / "truth" / "scene.xml", args.clip)
    offsets = truth_offsets(scene)
    report = args.run / "interaction.json"
    windowed = json.loads(report.read_text())["calibration"]["parameters"] if report.is_file() else {}
    settings = {"node_frames": args.node_frames, "cross_fit_points": args.cross_fit}
    options = ShootingOptions(**{k: v for k, v in settings.items() if v is not None})
    counts = {"shooting": [0, 0, 0], "windows": [0, 0, 0]}  # within 20%, wrong, unresolved
    # Friction and restitution (the bounce the contact produces, `grounder.sim.restitution`), the two values.
    bounce_counts = {"shooting": [0, 0, 0], "windows": [0, 0, 0]}
    saved: dict[str, object] = {}
    # The windows' written contacts: calibrated values, or the prior where one is kept.
    windows_model = mujoco.MjModel.from_xml_path(str(args.run / "scene.xml"))
    for body in bodies:
        true_values = rendered[offsets[body][0]]
        runs = moving_runs(object_tracks[body], fps, options)
        if not runs:
            print(f"{body}: no moving run")
            continue
        with single_body_scene(scene / "scene.xml", body) as sub_xml:
            model = mujoco.MjModel.from_xml_path(str(sub_xml))
            e_true = simulated_restitution(
                (true_values["solref.timeconst"], true_values["solref.dampratio"]),
                model.geom_solimp[collision_geoms(model, model.body(body).id)[0]],
                model.opt,
            )
            tick = time.perf_counter()
            if args.grid:
                setter = contact_setter(*resolve_parameters(model, [f"{body}.{f}" for f in FIELDS]))
                profile = contact_profile(model, setter, runs, options, view_point_m=view)
            else:
                contact = resolve_parameters(model, [f"{body}.{f}" for f in JOINT_FIELDS])
                joint = fit_contact(model, contact, runs, options, view_point_m=view)
        seconds = time.perf_counter() - tick
        if args.grid:
            print(f"\n{body} ({offsets[body][0]}), {profile.nodes} nodes, {seconds:.0f} s; cost, rows damping ratio "
                  f"{profile.damping_grid}, columns friction {profile.friction_grid}:")  # fmt: skip
            for row in profile.cost:
                print("   " + " ".join(f"{v:8.1f}" for v in row))
            fits = [
                ("friction.sliding", profile.friction, profile.friction_range,
                 resolved(profile.friction, profile.friction_range, profile.friction_grid)),
                ("solref.dampratio", profile.damping_ratio, profile.damping_range,
                 resolved(profile.damping_ratio, profile.damping_range, profile.damping_grid)),
            ]  # fmt: skip
        else:
            print(f"\n{body} ({offsets[body][0]}), {joint.nodes} nodes, {seconds:.0f} s, best cost "
                  f"{joint.cost:.1f} of {len(joint.evaluations)} points; those within "
                  f"{options.resolution_cost:g} of it:")  # fmt: skip
            for point, cost in joint.evaluations:
                if cost - joint.cost <= options.resolution_cost:
                    print(f"   {' '.join(f'{v:.4g}' for v in point)}: {cost:.1f}")
            fits = [
                (name.split(".", 1)[1], value, span, ok)
                for name, value, span, ok in zip(joint.names, joint.values, joint.ranges, joint.resolved, strict=True)
            ]
        for field, best, span, ok in fits:
            true = true_values[field]
            error_pct = 100.0 * (best / true - 1.0)
            if field in FIELDS:
                tally(counts["shooting"], ok, error_pct)
            record = windowed.get(f"{body}.{field}", {})
            window_text = "not in the run's report"
            if record:
                window_pct = 100.0 * (record["value"] / true - 1.0)
                window_ok = bool(record.get("constrained"))
                if field in FIELDS:
                    tally(counts["windows"], window_ok, window_pct)
                window_text = f"{window_pct:+.0f}%" if window_ok else "unresolved"
            print(f"  {field}: rendered {true:.4g}; shooting {best:.4g} ({error_pct:+.0f}%, range {span[0]:.4g}.."
                  f"{span[1]:.4g}{'' if ok else ', unresolved'}); windows {window_text}")  # fmt: skip
            if field == "friction.sliding":
                tally(bounce_counts["shooting"], ok, error_pct)
                if record:
                    tally(bounce_counts["windows"], window_ok, window_pct)
        if not args.grid and joint.restitution is not None:
            bounce = joint.restitution
            e_pct = 100.0 * (bounce.value / e_true - 1.0)
            tally(bounce_counts["shooting"], bounce.resolved, e_pct)
            window_text = "not in the run's report"
            damping = windowed.get(f"{body}.solref.dampratio")
            if damping:
                e_win = body_restitution(windows_model, body)
                window_pct = 100.0 * (e_win / e_true - 1.0)
                tally(bounce_counts["windows"], bool(damping.get("constrained")), window_pct)
                window_text = f"{e_win:.3f} ({window_pct:+.0f}%)" + (
                    "" if damping.get("constrained") else ", unresolved"
                )
            print(f"  restitution at 1 m/s: rendered {e_true:.3f}; shooting {bounce.value:.3f} ({e_pct:+.0f}%, range "
                  f"{bounce.range[0]:.3f}..{bounce.range[1]:.3f}{'' if bounce.resolved else ', unresolved'}); "
                  f"windows {window_text}")  # fmt: skip
        if not args.grid:
            saved[body] = {
                "names": list(joint.names),
                "cost": joint.cost,
                "points": [{"values": list(v), "cost": c} for v, c in joint.evaluations],
            }
            if args.save:
                args.save.write_text(json.dumps(saved, indent=1) + "\n")
    print(f"\n{args.run} on {args.clip}: friction and damping ratio within 20% of the rendered values")
    for method, (right, wrong, unresolved) in counts.items():
        print(f"  {method}: {right} of {right + wrong} resolved values, {unresolved} unresolved")
    if not args.grid:
        print(f"{args.run} on {args.clip}: friction and restitution (1 m/s) within 20% of the rendered values")
        for method, (right, wrong, unresolved) in bounce_counts.items():
            print(f"  {method}: {right} of {right + wrong} resolved values, {unresolved} unresolved")


if __name__ == "__main__":
    main()
