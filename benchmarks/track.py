"""Tracking accuracy on `samples/toss`: the grounded scene of `samples/tabletop` tracked through the toss clip.

Run: `.venv/bin/python benchmarks/track.py [--frames N] [--scene out/track_bench/scene] [--occluded] [--calibrate]`

1. Grounds `samples/tabletop/video.mp4` (cached in `out/track_bench/scene`; ~50 s on 2 cores).
2. Tracks every grounded object through `samples/toss/video.mp4` (or `samples/toss_occluded/video.mp4`).
3. Compares with the truth. The grounded body frame is not the truth body frame (the grounded mesh's bounding-box
   centre and axes differ from the true mesh's), so each grounded object is related to its true object once, at the
   scan's rest pose: `offset = inv(world_from_truth_body) @ world_from_grounded_body`, both in the tabletop scan
   (truth: `samples/tabletop/truth/objects.json`; grounded: `scene.json`). A tracked grounded pose P then implies
   the true body pose `P @ inv(offset)`, which is compared with `samples/toss/truth/trajectory.npz`. Objects are
   matched to the truth by their scan positions.

Prints, per object, the tracked fraction and the median / 90th-percentile / max position and rotation errors over
the tracked frames, the RMS position error along the camera ray over the frames where the object moves (the
coordinate tracking measures worst, where calibration reads it), plus the velocity errors of the written
trajectories. `--lk-window-px` and `--max-iterations` set the tracker's `TrackOptions` of the same names.

With `--calibrate`, runs part 2 instead: `grounder.interaction.pipeline.ground_with_interaction` (reusing the cached
grounded scene), and prints per object and parameter (sliding friction; contact damping ratio, `solref[1]`, MuJoCo's
restitution knob: the ratio the clip was rendered with, lower bounces more; contact time constant, `solref[0]`) the
rendered value, the calibrated value, its interval, whether the clip constrains it, and the relative error (target:
within 20%), then how well the scene matches the clip before and after. With `--truth`, the same screen +
calibration runs on the TRUE trajectory against the TRUE scene (no tracking, no grounded mesh): what the clip can
tell at best. With `--calibrate --true-motion --scene S`, the same per-object calibration runs on the TRUE trajectory
carried into scene S's grounded body frames: what the grounded shapes allow when tracking is perfect.

"Rendered value" is compared like with like: the toss scene gives each object geom priority over the table, so
each object-table contact uses exactly the object's friction and solref (`objects.json`, `table_contact`), and the
clip is rendered with the physics settings of every exported scene (timestep, integrator, cone); calibration also
gives the calibrated geoms priority. Restitution is printed both as MuJoCo's damping ratio (what the clip was
rendered with) and as the coefficient of restitution e the contact produces, time constant and damping ratio
together, for a 1 m/s normal impact (`grounder.sim.restitution`); the counts are given both for friction and damping
ratio and for friction and restitution (the issue's two values; restitution counted as resolved where the damping
ratio is).

`--calibration impacts|windows|shooting` picks the calibration (default: the tool's, impacts); with impacts,
`--impacts-compare flight|frames` sets `ImpactOptions.compare`, `--impacts-rotation on|off` sets
`ImpactOptions.compare_rotation`, `--impacts-stability N` sets `ImpactOptions.stability_copies`, `--impacts-drift
MM,S` sets `ImpactOptions.drift_sigma_m` (in mm) and `drift_time_s`, `--impacts-only`
leaves what the landings do not resolve at the prior (no windows), and the per-object impacts, chi-square, noise and
restitution range are printed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from grounder.tracking.options import TrackOptions  # noqa: E402
from grounder.tracking.pipeline import track  # noqa: E402
from image2sim_common.rotations import (  # noqa: E402
    matrix_from_quat,
    quat_angle_rad,
    quat_from_matrix,
)


def pose(pos: list[float] | np.ndarray, quat_wxyz: list[float] | np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = pos
    out[:3, :3] = matrix_from_quat(np.asarray(quat_wxyz, float))
    return out


def ground_scene(scene: Path, scan: str = "tabletop") -> None:
    if (scene / "scene.xml").is_file():
        return
    from grounder import GroundOptions, ground
    from reconstruction import ReconstructOptions

    tick = time.perf_counter()
    ground(ROOT / f"samples/{scan}/video.mp4", scene, GroundOptions(reconstruct=ReconstructOptions(aruco_size_m=0.12)))
    print(f"grounded the tabletop scan in {time.perf_counter() - tick:.1f} s -> {scene}")


def print_camera_error(clip_dir: Path, world_from_cam: np.ndarray, static: bool) -> None:
    """Camera poses found from the table's marker against the true ones, where the clip's truth has them per frame
    (`samples/toss_moving`): median and max camera-centre error (mm) and view-direction error (deg)."""
    truth = json.loads((clip_dir / "truth/camera.json").read_text())
    if "world_from_cam_per_frame" not in truth:
        return
    true_poses = np.array(truth["world_from_cam_per_frame"])
    found = np.broadcast_to(world_from_cam, true_poses.shape) if static else np.asarray(world_from_cam)
    seen = np.isfinite(found).all(axis=(1, 2))
    centre_mm = 1000 * np.linalg.norm(found[seen, :3, 3] - true_poses[seen, :3, 3], axis=1)
    cosine = np.clip(np.sum(found[seen, :3, 2] * true_poses[seen, :3, 2], axis=1), -1.0, 1.0)
    view_deg = np.degrees(np.arccos(cosine))
    print(
        f"camera ({'one static pose' if static else 'a pose per frame'}, found in {int(seen.sum())}/{len(seen)} "
        f"frames): centre error median {np.median(centre_mm):.2f} mm, max {centre_mm.max():.2f}; view direction "
        f"error median {np.median(view_deg):.3f} deg, max {view_deg.max():.3f}"
    )


def truth_offsets(scene: Path) -> dict[str, tuple[str, np.ndarray]]:
    """Grounded object name -> (true object name, offset = truth_body_from_grounded_body at the scan)."""
    grounded = json.loads((scene / "scene.json").read_text())["objects"]
    truth = {o["name"]: o for o in json.loads((ROOT / "samples/tabletop/truth/objects.json").read_text())["objects"]}
    out = {}
    for name, g in grounded.items():
        true_name = min(truth, key=lambda t: np.linalg.norm(np.subtract(truth[t]["pos_m"], g["pos_m"])))
        t = truth[true_name]
        t_pose = pose(t["pos_m"], t["quat_wxyz"]) if "quat_wxyz" in t else None
        if t_pose is None:
            yaw = np.deg2rad(t["yaw_deg"])
            t_pose = pose(t["pos_m"], [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])
        out[name] = (true_name, np.linalg.inv(t_pose) @ pose(g["pos_m"], g["quat_wxyz"]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scene",
        type=Path,
        default=None,
        help="grounded scene (default out/track_bench/scene, with --markers out/track_bench_markers/scene)",
    )
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument(
        "--clip",
        type=Path,
        default=None,
        help="a toss clip folder laid out like samples/toss (e.g. `samples/make_toss.py --fps 60 --out DIR`)",
    )
    parser.add_argument("--occluded", action="store_true", help="track samples/toss_occluded instead")
    parser.add_argument(
        "--moving", action="store_true", help="track samples/toss_moving instead (the toss filmed by a moving camera)"
    )
    parser.add_argument(
        "--markers",
        action="store_true",
        help="scan samples/tabletop_markers and track samples/toss_markers (ArUco markers on the box and the can)",
    )
    parser.add_argument(
        "--marker-use", choices=("pose", "rotation"), default="pose", help="with --markers: TrackOptions.marker_use"
    )
    parser.add_argument("--ignore-markers", action="store_true", help="with --markers: track the clip without them")
    parser.add_argument(
        "--scan-features",
        action="store_true",
        help="feature models also from the scan's frames (TrackOptions.scan_features)",
    )
    parser.add_argument(
        "--place-from-clip",
        action="store_true",
        help="with --markers: ignore the scan's marker places; place each marker from the clip's model-based track",
    )
    parser.add_argument(
        "--lk-window-px", type=int, default=None, help="TrackOptions.lk_window_px (default: the tool's)"
    )
    parser.add_argument(
        "--max-iterations", type=int, default=None, help="TrackOptions.max_iterations (default: the tool's)"
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the trajectories (scene with --calibrate)")
    parser.add_argument("--calibrate", action="store_true", help="ground + track + calibrate (part 2)")
    parser.add_argument(
        "--tracks", type=Path, default=None, help="with --calibrate: calibrate these saved tracks (no re-tracking)"
    )
    parser.add_argument("--truth", action="store_true", help="screen + calibrate on the true trajectory and scene")
    parser.add_argument(
        "--segments",
        action="store_true",
        help="with --calibrate: windows from the segments (every object tracked), not each object's own runs",
    )
    parser.add_argument(
        "--window", type=float, default=None, help="with --calibrate: window length, s (default: the tool's)"
    )
    parser.add_argument(
        "--window-stride", type=float, default=None, help="with --calibrate: window start-to-start, s (default: tool's)"
    )
    parser.add_argument(
        "--true-motion",
        action="store_true",
        help="with --calibrate: calibrate the grounded scene on the true trajectory (no tracking)",
    )
    parser.add_argument(
        "--smooth-poses",
        action="store_true",
        help="with --calibrate --tracks: windows start from the smoothing fit's poses (SmoothingOptions.smooth_poses)",
    )
    parser.add_argument(
        "--generations", type=int, default=None, help="with --calibrate: differential evolution (default: the tool's)"
    )
    parser.add_argument(
        "--popsize", type=int, default=None, help="with --calibrate: population per parameter (default: the tool's)"
    )
    parser.add_argument(
        "--seed", type=int, default=None, help="with --calibrate: seed of the global search (default: the tool's, 0)"
    )
    parser.add_argument(
        "--start-rounds", type=int, default=None, help="with --calibrate: start refits (default: InteractionOptions')"
    )
    parser.add_argument(
        "--calibration",
        choices=("windows", "shooting", "impacts"),
        default=None,
        help="with --calibrate: InteractionOptions.calibration (default: the tool's, impacts)",
    )
    parser.add_argument(
        "--impacts-compare",
        choices=("flight", "frames"),
        default=None,
        help="with --calibration impacts: ImpactOptions.compare (default: the tool's)",
    )
    parser.add_argument(
        "--impacts-rotation",
        choices=("on", "off"),
        default=None,
        help="with --calibration impacts: ImpactOptions.compare_rotation (default: the tool's)",
    )
    parser.add_argument(
        "--impacts-stability",
        type=int,
        default=None,
        help="with --calibration impacts: ImpactOptions.stability_copies (0: off; default: the tool's)",
    )
    parser.add_argument(
        "--impacts-drift",
        type=lambda text: tuple(float(v) for v in text.split(",")),
        default=None,
        metavar="MM,S",
        help="with --calibration impacts: ImpactOptions.drift_sigma_m in mm and drift_time_s (default: the tool's)",
    )
    parser.add_argument(
        "--impacts-only",
        action="store_true",
        help="with --calibration impacts: leave what the impacts do not resolve at the prior (no windows)",
    )
    parser.add_argument(
        "--along-view-weight",
        type=float,
        default=None,
        help="with --calibrate: weight of the position error along the camera ray (default: InteractionOptions')",
    )
    args = parser.parse_args()
    clip_dir = args.clip or ROOT / (
        "samples/toss_occluded"
        if args.occluded
        else "samples/toss_moving"
        if args.moving
        else "samples/toss_markers"
        if args.markers
        else "samples/toss"
    )
    if args.truth:
        truth_benchmark(clip_dir, args)
        return
    if args.scene is None:
        args.scene = ROOT / ("out/track_bench_markers/scene" if args.markers else "out/track_bench/scene")
    ground_scene(args.scene, "tabletop_markers" if args.markers else "tabletop")
    if args.calibrate and args.true_motion:
        true_motion_benchmark(clip_dir, args.scene, args)
        return
    if args.calibrate and args.tracks is not None:
        tracks_benchmark(clip_dir, args.scene, args.tracks, args)
        return
    if args.calibrate:
        calibrate_benchmark(clip_dir, args.scene, args.out or ROOT / "out/interaction_bench", args)
        return
    offsets = truth_offsets(args.scene)
    truth_meta = json.loads((clip_dir / "truth/objects.json").read_text())
    truth_qpos = np.load(clip_dir / "truth/trajectory.npz")["qpos"]
    truth_qvel = np.load(clip_dir / "truth/trajectory.npz")["qvel"]
    adr = {o["name"]: (o["qpos_adr"], o["dof_adr"]) for o in truth_meta["objects"]}

    tick = time.perf_counter()
    result = track(
        clip_dir / "video.mp4",
        args.scene,
        args.out,
        TrackOptions(
            aruco_size_m=0.12,
            max_frames=args.frames,
            scan_features=args.scan_features,
            **track_option_fields(args, clip_dir),
        ),
        overwrite=True,
    )
    print(f"tracked {len(result.time_s)} frames in {time.perf_counter() - tick:.1f} s ({result.seconds})")
    print(f"segments: {list(result.segments)}")
    print_camera_error(clip_dir, result.world_from_cam, result.static_camera)
    for record in result.object_markers:
        print(f"object marker: {record}")
    all_pos: list[float] = []
    all_rot: list[float] = []
    along_moving: list[float] = []  # position error along the camera ray where the object moves faster than 5 cm/s
    cams = np.broadcast_to(result.world_from_cam, (len(result.valid), 4, 4))
    for i, name in enumerate(result.object_names):
        true_name, offset = offsets[name]
        qa, da = adr[true_name]
        pos_err, rot_err, tilt_err = [], [], []
        for f in np.nonzero(result.valid[:, i])[0]:
            implied = result.world_from_objects[f, i] @ np.linalg.inv(offset)
            error_m = implied[:3, 3] - truth_qpos[f, qa : qa + 3]
            pos_err.append(np.linalg.norm(error_m))
            rot_err.append(quat_angle_rad(quat_from_matrix(implied[:3, :3]), truth_qpos[f, qa + 3 : qa + 7]))
            # the part of it that tilts the object's up axis (a bowl's or a can's symmetry axis), not the turn about it
            true_up = matrix_from_quat(truth_qpos[f, qa + 3 : qa + 7])[:, 2]
            tilt_err.append(np.arccos(np.clip(implied[:3, 2] @ true_up, -1.0, 1.0)))
            if np.linalg.norm(truth_qvel[f, da : da + 3]) > 0.05:
                ray = implied[:3, 3] - cams[f, :3, 3]
                along_moving.append(float(error_m @ ray / np.linalg.norm(ray)))
        if not pos_err:
            print(f"{name} ({true_name}): never tracked")
            continue
        pe, re = np.array(pos_err) * 1e3, np.rad2deg(rot_err)
        all_pos.extend(pe)
        all_rot.extend(re)
        lost = [int(f) for f in np.nonzero(~result.valid[:, i])[0]]
        print(
            f"{name} ({true_name}): tracked {result.valid[:, i].sum()}/{len(result.valid)} frames; position error "
            f"median {np.median(pe):.2f} mm, p90 {np.percentile(pe, 90):.2f}, max {pe.max():.2f}; rotation error "
            f"median {np.median(re):.2f} deg, p90 {np.percentile(re, 90):.2f}, max {re.max():.2f} (of which tilt of "
            f"its up axis median {np.median(np.rad2deg(tilt_err)):.2f} deg); lost frames {lost}"
        )
    print(
        f"ALL: median position error {np.median(all_pos):.2f} mm (target <= 5), median rotation error "
        f"{np.median(all_rot):.2f} deg (target <= 3)"
    )
    if along_moving:
        print(
            f"ALL: position error along the camera ray where an object moves (> 5 cm/s, {len(along_moving)} poses): "
            f"RMS {1e3 * np.sqrt(np.mean(np.square(along_moving))):.2f} mm"
        )
    # Velocities of the written trajectories (the grounded body origin is not the true one: the linear velocity of a
    # point offset by r differs by omega x r, so compare at the implied true body origin).
    for traj, (first, last) in zip(result.trajectories, result.segments, strict=True):
        for i, name in enumerate(result.object_names):
            true_name, offset = offsets[name]
            qa, da = adr[true_name]
            rows = slice(first, last + 1)
            lin = traj.qvel[:, 6 * i : 6 * i + 3]
            ang_body = traj.qvel[:, 6 * i + 3 : 6 * i + 6]
            rot = np.stack([matrix_from_quat(q) for q in traj.qpos[:, 7 * i + 3 : 7 * i + 7]])
            ang_world = np.einsum("tij,tj->ti", rot, ang_body)
            r_world = np.einsum("tij,j->ti", rot, np.linalg.inv(offset)[:3, 3])
            lin_true_origin = lin + np.cross(ang_world, r_world)
            err = np.linalg.norm(lin_true_origin - truth_qvel[rows, da : da + 3], axis=1)
            print(f"  {traj.name} {name}: linear velocity error median {np.median(err):.3f} m/s, max {err.max():.3f}")


def track_option_fields(args: argparse.Namespace, clip_dir: Path) -> dict[str, Any]:
    """TrackOptions fields from the command line: the tracker settings given, and the object markers (--markers; by
    default those `ground` measured in the scan)."""
    fields: dict[str, Any] = {
        name: getattr(args, name) for name in ("lk_window_px", "max_iterations") if getattr(args, name) is not None
    }
    if not args.markers:
        return fields
    if args.ignore_markers:
        return {**fields, "scene_markers": False}
    fields["marker_use"] = args.marker_use
    if args.place_from_clip:
        from grounder.tracking.markers import load_object_markers

        fields["scene_markers"] = False
        fields["object_markers"] = load_object_markers(clip_dir / "truth/markers_unplaced.json")
    return fields


def calibrate_benchmark(clip_dir: Path, scene: Path, out: Path, args: argparse.Namespace) -> None:
    from grounder.interaction.pipeline import ground_with_interaction

    offsets = truth_offsets(scene)
    tick = time.perf_counter()
    result = ground_with_interaction(
        ROOT / f"samples/{'tabletop_markers' if args.markers else 'tabletop'}/video.mp4",
        clip_dir / "video.mp4",
        out,
        _options(
            args,
            track=TrackOptions(
                aruco_size_m=0.12, scan_features=args.scan_features, **track_option_fields(args, clip_dir)
            ),
        ),
        grounded_scene=scene,
        overwrite=True,
    )
    print(f"ground_with_interaction: {time.perf_counter() - tick:.1f} s; {result.report['stage_seconds']}")
    print(f"segments: {result.report['tracking']['segments']}; windows: {result.report['windows']}")
    calibration = result.report["calibration"]
    print(f"calibration: {calibration['status']}")
    print_screens(calibration.get("parameters", {}))
    print_parameter_table(calibration.get("parameters", {}), clip_dir, {b: offsets[b][0] for b in offsets})
    print_window_match(calibration)
    print_impacts(calibration)
    options = _options(args)
    if options.own_runs:
        print_start_errors(scene, clip_dir, out / "interaction/tracks/track.json", options)
    print("match with the whole segments (open loop from the first tracked state; hinges on that state):")
    for body, before in result.report["match_before"].items():
        after = result.report.get("match_after", {}).get(body, {})
        print(
            f"  {body}: mean position error {before['mean_position_error_mm']} -> "
            f"{after.get('mean_position_error_mm', '-')} mm"
        )


def _seen(record: dict) -> str:
    if record.get("constrained", True):
        return "yes"
    if "unresolved_fit" in record:
        return f"no: prior kept (fit {record['unresolved_fit']:.3f} unresolved there)"
    return "no: prior kept"


def print_impacts(calibration: dict) -> None:
    """Per object, with `--calibration impacts`: the impacts fitted, the fit's chi-square and the restitution range."""
    for body, info in calibration.get("per_object", {}).items():
        if "impacts" not in info:
            continue
        fit, bounce = info["impacts"], info["restitution"]
        print(
            f"  {body}: {len(fit['names'])} impact(s) {fit['names']}; chi-square {fit['chi2']:.1f} for {fit['dof']} "
            f"residuals (per impact {fit['chi2_per_impact']}, noise across/along the ray {fit['noise_mm']} mm), "
            f"threshold {fit['threshold']:.1f}; best {fit['best']}; "
            f"restitution {bounce['value']:.3f} in {bounce['range'][0]:.3f}..{bounce['range'][1]:.3f} "
            f"({'resolved' if bounce['resolved'] else 'unresolved'})"
        )


def print_window_match(calibration: dict) -> None:
    """Per object: how well its calibration windows match before and after (the report's `window_match`)."""
    print("match with the calibration windows (median over windows of each window's mean error):")
    for body, info in calibration.get("per_object", {}).items():
        match = info.get("window_match") or {}
        if match:
            b, a = match["before"], match["after"]
            print(
                f"  {body}: {match['windows']} windows, position {b['median_position_error_mm']} -> "
                f"{a['median_position_error_mm']} mm, rotation {b['median_rotation_error_deg']} -> "
                f"{a['median_rotation_error_deg']} deg"
            )


def print_start_errors(scene: Path, clip_dir: Path, track_json: Path, options: Any) -> None:
    """Per object, the windows its calibration is cut into (each object's own tracked runs, window starts as
    `grounder.interaction.per_object.calibrate_per_body` chooses them) and how far each tracked start velocity is from
    the truth: the slide after a landing is as long as the start speed squared over the friction, so these errors show
    up in the calibrated values (README, #8)."""
    import mujoco

    from grounder.interaction.per_object import _single_body_trajectory
    from grounder.interaction.windows import reliable_starts, windows
    from grounder.tracking.output import load_object_trajectories

    fps = float(json.loads(track_json.read_text())["fps"])
    model = mujoco.MjModel.from_xml_path(str(scene / "scene.xml"))
    truth = true_motion_in_grounded_frames(scene, clip_dir)
    smoothing = options.track.smoothing
    every = []
    print("window starts, tracked start velocity against the truth:")
    for body, runs in load_object_trajectories(track_json, smoothing).items():
        true_body = _single_body_trajectory(model, truth, body)
        starts = [reliable_starts(run, smoothing) for run in runs]
        cut = windows(runs, options.window_s, options.window_stride_s, options.min_motion_m_s, starts=starts)
        frames = [round(w.time_s[0] * fps) for w in cut]
        errors = [
            1e3 * float(np.linalg.norm(w.qvel[0, :3] - true_body.qvel[f, :3])) for w, f in zip(cut, frames, strict=True)
        ]
        every += errors
        print(f"  {body}: {len(cut)} windows at frames {frames}, speed error {[round(e) for e in errors]} mm/s")
    if every:
        print(f"  all {len(every)}: median {np.median(every):.0f}, p90 {np.percentile(every, 90):.0f} mm/s")


def contact_values(truth_xml: Path, clip_dir: Path) -> dict[str, dict[str, float]]:
    """True object name -> calibration parameter field (sliding friction, damping ratio, time constant) -> value of
    its contacts with the table, as MuJoCo mixed them when rendering: read from the contacts of the clip's last
    (resting) frame."""
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(truth_xml))
    data = mujoco.MjData(model)
    truth = np.load(clip_dir / "truth/trajectory.npz", allow_pickle=False)
    data.qpos[:] = truth["qpos"][-1]
    mujoco.mj_forward(model, data)
    out: dict[str, dict[str, float]] = {}
    for contact in data.contact[: data.ncon]:
        for g in (int(contact.geom1), int(contact.geom2)):
            body = model.body(int(model.geom_bodyid[g])).name
            if model.geom_bodyid[g] != 0:
                out[body] = {
                    "friction.sliding": float(contact.friction[0]),
                    "solref.dampratio": float(contact.solref[1]),
                    "solref.timeconst": float(contact.solref[0]),
                }
    return out


def print_parameter_table(params: dict, clip_dir: Path, true_names: dict[str, str]) -> None:
    """Per parameter: rendered value, calibrated value, whether the clip constrains it, its resolution range, the
    relative error (restitution also as e), and its best values with the windows' start speeds off by a typical
    tracking error (`grounder.interaction.windows.start_error_ranges`)."""
    import mujoco

    from grounder.calibration.parameters import collision_geoms
    from grounder.sim.restitution import body_restitution, simulated_restitution

    truth_xml = clip_dir / "truth/scene.xml"
    if not truth_xml.exists():  # samples/toss_occluded: the same simulated toss, re-rendered with a card in front
        truth_xml = ROOT / "samples/toss/truth/scene.xml"
    contact = contact_values(truth_xml, clip_dir)
    truth = mujoco.MjModel.from_xml_path(str(truth_xml))
    print(
        "| parameter | object | rendered | calibrated | constrained by the clip | indistinguishable range | "
        "error | as restitution e at 1 m/s: rendered / calibrated / error | best value with start speeds off (flag) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    counts = [0, 0, 0]  # friction and damping ratio: within 20%, wrong, unresolved (prior kept)
    bounce_counts = [0, 0, 0]  # friction and restitution (the damping ratio's status), likewise
    for name, p in params.items():
        body, field = name.split(".", 1)
        true_name = true_names.get(body, body)
        rendered = contact[true_name][field]
        constrained = p.get("constrained", True)
        span = "{:.3f}..{:.3f}".format(*p["indistinguishable"]) if "indistinguishable" in p else "-"
        value = p["value"]
        error = f"{100 * (value - rendered) / rendered:+.0f}%" if constrained else "n/a (prior kept)"
        as_e = "-"
        timeconst = params.get(f"{body}.solref.timeconst")
        if field == "solref.dampratio" and timeconst is not None:
            # The bounce the contact produces (`grounder.sim.restitution`): the calibrated time constant and damping
            # ratio together, in the truth scene's physics settings (those of every exported scene).
            solimp = truth.geom_solimp[collision_geoms(truth, truth.body(true_name).id)[0]]
            e_true = body_restitution(truth, true_name)
            e_cal = simulated_restitution((timeconst["value"], value), solimp, truth.opt)
            as_e = f"{e_true:.3f} / {e_cal:.3f} / " + (
                f"{100 * (e_cal - e_true) / e_true:+.0f}%" if constrained else "n/a"
            )
            bounce_counts[2 if not constrained else 0 if abs(e_cal / e_true - 1.0) <= 0.2 else 1] += 1
        starts = "-"
        if "start_error_range" in p:
            starts = "{:.3f}..{:.3f}".format(*p["start_error_range"]) + (
                " (start-sensitive)" if p.get("start_sensitive") else ""
            )
        print(
            f"| {name} | {true_name} | {rendered:.3f} | {value:.3f} | {_seen(p)} | {span} | {error} | {as_e} | "
            f"{starts} |"
        )
        if field in ("friction.sliding", "solref.dampratio"):
            counts[2 if not constrained else 0 if abs(value / rendered - 1.0) <= 0.2 else 1] += 1
        if field == "friction.sliding":
            bounce_counts[2 if not constrained else 0 if abs(value / rendered - 1.0) <= 0.2 else 1] += 1
    print(
        f"friction and damping ratio: {counts[0]} of {counts[0] + counts[1]} resolved values within 20% of the "
        f"rendered ones, {counts[2]} unresolved (prior kept)"
    )
    print(
        f"friction and restitution (1 m/s): {bounce_counts[0]} of {bounce_counts[0] + bounce_counts[1]} resolved "
        f"values within 20% of the rendered ones, {bounce_counts[2]} unresolved (prior kept)"
    )


def tracks_benchmark(clip_dir: Path, scene: Path, tracks: Path, args: argparse.Namespace) -> None:
    """Screen + calibrate the grounded scene on saved tracks (e.g. `OUT/interaction/tracks` of a `--calibrate` run),
    per object as `ground --interaction` does."""
    from grounder.interaction.options import default_params
    from grounder.interaction.per_object import calibrate_per_body
    from grounder.interaction.tracks import saved_tracks
    from grounder.tracking.smooth import SmoothingOptions

    names = list(json.loads((scene / "scene.json").read_text())["objects"])
    offsets = truth_offsets(scene)
    tick = time.perf_counter()
    options = _options(args, track=TrackOptions(smoothing=SmoothingOptions(smooth_poses=args.smooth_poses)))
    saved = saved_tracks(tracks, options.track)  # what `ground --interaction` calibrates from, too
    entry, _ = calibrate_per_body(
        scene / "scene.xml",
        saved.segments,
        default_params(names),
        options,
        view_point_m=saved.view_point_m,
        object_tracks=saved.object_tracks if options.own_runs else None,
    )
    print(f"screen + calibration on {tracks}: {time.perf_counter() - tick:.1f} s; {entry['status']}")
    print_screens(entry["parameters"])
    print_parameter_table(entry["parameters"], clip_dir, {b: offsets[b][0] for b in offsets})
    print_window_match(entry)
    print_impacts(entry)
    if options.own_runs:
        print_start_errors(scene, clip_dir, tracks / "track.json", options)


def true_motion_in_grounded_frames(scene: Path, clip_dir: Path) -> Any:
    """The clip's true trajectory expressed in the grounded scene's bodies and joint order: each grounded body's pose
    is the true pose times its offset (`truth_offsets`), its linear velocity that of the grounded body origin, its
    angular velocity in the grounded body frame."""
    from grounder.core.trajectory import Trajectory

    offsets = truth_offsets(scene)
    names = list(json.loads((scene / "scene.json").read_text())["objects"])
    adr = {
        o["name"]: (o["qpos_adr"], o["dof_adr"])
        for o in json.loads((clip_dir / "truth/objects.json").read_text())["objects"]
    }
    truth = np.load(clip_dir / "truth/trajectory.npz", allow_pickle=False)
    frames = len(truth["time"])
    qpos, qvel = np.zeros((frames, 7 * len(names))), np.zeros((frames, 6 * len(names)))
    for i, name in enumerate(names):
        true_name, offset = offsets[name]
        qa, da = adr[true_name]
        for f in range(frames):
            world_from_true = pose(truth["qpos"][f, qa : qa + 3], truth["qpos"][f, qa + 3 : qa + 7])
            world_from_grounded = world_from_true @ offset
            qpos[f, 7 * i : 7 * i + 3] = world_from_grounded[:3, 3]
            qpos[f, 7 * i + 3 : 7 * i + 7] = quat_from_matrix(world_from_grounded[:3, :3])
            angular_body = truth["qvel"][f, da + 3 : da + 6]
            lever_world = world_from_true[:3, :3] @ offset[:3, 3]
            qvel[f, 6 * i : 6 * i + 3] = truth["qvel"][f, da : da + 3] + np.cross(
                world_from_true[:3, :3] @ angular_body, lever_world
            )
            qvel[f, 6 * i + 3 : 6 * i + 6] = offset[:3, :3].T @ angular_body
    return Trajectory(time_s=truth["time"], qpos=qpos, qvel=qvel, ctrl=None, name="true_motion")


def true_motion_benchmark(clip_dir: Path, scene: Path, args: argparse.Namespace) -> None:
    """Screen + calibrate the grounded scene on the clip's TRUE motion, per object as `ground --interaction` does:
    what the grounded shapes and masses allow when tracking is perfect (tracking's share of the errors is the
    difference to a `--calibrate` run)."""
    from grounder.interaction.options import default_params
    from grounder.interaction.per_object import calibrate_per_body
    from grounder.interaction.tracks import view_point_of

    names = list(json.loads((scene / "scene.json").read_text())["objects"])
    offsets = truth_offsets(scene)
    world_from_cam = np.array(json.loads((clip_dir / "truth/camera.json").read_text())["world_from_cam"])
    tick = time.perf_counter()
    entry, _ = calibrate_per_body(
        scene / "scene.xml",
        [true_motion_in_grounded_frames(scene, clip_dir)],
        default_params(names),
        _options(args),
        view_point_m=view_point_of(world_from_cam),
    )
    print(f"screen + calibration of {scene} on the true motion: {time.perf_counter() - tick:.1f} s; {entry['status']}")
    print_screens(entry["parameters"])
    print_parameter_table(entry["parameters"], clip_dir, {b: offsets[b][0] for b in offsets})
    print_window_match(entry)
    print_impacts(entry)


def _options(args: argparse.Namespace, **fields: Any) -> Any:
    """The benchmark's `InteractionOptions`: the tool's defaults (what `ground --interaction` runs), except the search
    budget and seed, `--start-rounds` and `--along-view-weight` where given."""
    from grounder.interaction.options import ImpactOptions, InteractionOptions

    budget = {"generations": args.generations, "popsize": args.popsize, "seed": args.seed}
    given = {
        "start_rounds": args.start_rounds,
        "along_view_weight": args.along_view_weight,
        "own_runs": False if args.segments else None,
        "window_stride_s": args.window_stride,
        "window_s": args.window,
        "calibration": args.calibration,
    }
    chosen = {k: v for k, v in given.items() if v is not None}
    settings = {k: v for k, v in budget.items() if v is not None}
    impacts = ImpactOptions()
    if args.impacts_compare is not None:
        impacts = replace(impacts, compare=args.impacts_compare)
    if args.impacts_rotation is not None:
        impacts = replace(impacts, compare_rotation=args.impacts_rotation == "on")
    if args.impacts_stability is not None:
        impacts = replace(impacts, stability_copies=args.impacts_stability)
    if args.impacts_drift is not None:
        drift_mm, drift_s = args.impacts_drift
        impacts = replace(impacts, drift_sigma_m=1e-3 * drift_mm, drift_time_s=drift_s)
    if args.impacts_only:
        impacts = replace(impacts, windows_for_unresolved=False)
    return InteractionOptions(calibrate_settings=settings, impacts=impacts, **chosen, **fields)


def print_screens(params: dict) -> None:
    for name, p in params.items():
        if "screen" not in p:  # not screened (`--calibration shooting`)
            continue
        screen = p["screen"]
        print(
            f"  {name}: grid best {screen.get('grid_best')}, rollout change at -20% {screen.get('change_down_mm_deg')}"
            f" / +20% {screen.get('change_up_mm_deg')} (mm, deg)"
        )


def truth_benchmark(clip_dir: Path, args: argparse.Namespace) -> None:
    """Screen + calibrate on the true trajectory against the true scene (prior: every object at friction 0.45,
    damping ratio 0.4 and time constant 0.01 s, not the rendered values): what the clip can tell at best, without
    tracking or meshing."""
    import shutil
    import tempfile

    import mujoco

    from grounder.core.trajectory import Trajectory
    from grounder.interaction.options import default_params
    from grounder.interaction.per_object import calibrate_per_body

    truth = np.load(clip_dir / "truth/trajectory.npz", allow_pickle=False)
    traj = Trajectory(time_s=truth["time"], qpos=truth["qpos"], qvel=truth["qvel"], ctrl=None, name="truth")
    names = json.loads((clip_dir / "truth/objects.json").read_text())["joint_order"]
    bodies = [n.removesuffix("_free") for n in names]
    with tempfile.TemporaryDirectory() as tmp:
        scene = Path(tmp) / "truth"
        shutil.copytree(clip_dir / "truth", scene)
        spec = mujoco.MjSpec.from_file(str(scene / "scene.xml"))
        for body in bodies:
            geom = spec.geom(f"{body}_geom")
            geom.friction[0] = 0.45
            geom.solref[0] = 0.01
            geom.solref[1] = 0.4
        (scene / "scene.xml").write_text(spec.to_xml())
        tick = time.perf_counter()
        entry, _ = calibrate_per_body(
            scene / "scene.xml",
            [traj],
            default_params(bodies),
            _options(args),
        )
    print(f"truth screen + calibration: {time.perf_counter() - tick:.1f} s; {entry['status']}")
    print_screens(entry["parameters"])
    print_parameter_table(entry["parameters"], clip_dir, {b: b for b in bodies})


if __name__ == "__main__":
    main()
