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
the tracked frames, plus the velocity errors of the written trajectories.

With `--calibrate`, runs part 2 instead: `grounder._interaction.ground_with_interaction` (reusing the cached grounded
scene), and prints per object the calibrated sliding friction and contact damping ratio (MuJoCo's restitution knob)
beside the values the clip was rendered with (`truth/objects.json`), their relative errors (target: within 20%), and
how well the scene matches the clip before and after.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from grounder._simulate import quat_angle_rad  # noqa: E402
from grounder._track import TrackOptions, track  # noqa: E402
from grounder._track_smooth import matrix_from_quat, quat_from_matrix  # noqa: E402


def pose(pos: list[float] | np.ndarray, quat_wxyz: list[float] | np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = pos
    out[:3, :3] = matrix_from_quat(np.asarray(quat_wxyz, float))
    return out


def ground_scene(scene: Path) -> None:
    if (scene / "scene.xml").is_file():
        return
    from grounder import GroundOptions, ground
    from reconstruction import ReconstructOptions

    tick = time.perf_counter()
    ground(ROOT / "samples/tabletop/video.mp4", scene, GroundOptions(reconstruct=ReconstructOptions(aruco_size_m=0.12)))
    print(f"grounded the tabletop scan in {time.perf_counter() - tick:.1f} s -> {scene}")


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
    parser.add_argument("--scene", type=Path, default=ROOT / "out/track_bench/scene")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--occluded", action="store_true", help="track samples/toss_occluded instead")
    parser.add_argument("--out", type=Path, default=None, help="also write the trajectories (scene with --calibrate)")
    parser.add_argument("--calibrate", action="store_true", help="ground + track + calibrate (part 2)")
    parser.add_argument("--generations", type=int, default=10, help="with --calibrate: differential evolution")
    parser.add_argument("--popsize", type=int, default=6, help="with --calibrate: population per parameter")
    args = parser.parse_args()
    clip_dir = ROOT / ("samples/toss_occluded" if args.occluded else "samples/toss")
    ground_scene(args.scene)
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
        TrackOptions(aruco_size_m=0.12, max_frames=args.frames),
        overwrite=True,
    )
    print(f"tracked {len(result.time_s)} frames in {time.perf_counter() - tick:.1f} s ({result.seconds})")
    print(f"segments: {list(result.segments)}")
    all_pos: list[float] = []
    all_rot: list[float] = []
    for i, name in enumerate(result.object_names):
        true_name, offset = offsets[name]
        qa, _ = adr[true_name]
        pos_err, rot_err = [], []
        for f in np.nonzero(result.valid[:, i])[0]:
            implied = result.world_from_objects[f, i] @ np.linalg.inv(offset)
            pos_err.append(np.linalg.norm(implied[:3, 3] - truth_qpos[f, qa : qa + 3]))
            rot_err.append(quat_angle_rad(quat_from_matrix(implied[:3, :3]), truth_qpos[f, qa + 3 : qa + 7]))
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
            f"median {np.median(re):.2f} deg, p90 {np.percentile(re, 90):.2f}, max {re.max():.2f}; lost frames {lost}"
        )
    print(
        f"ALL: median position error {np.median(all_pos):.2f} mm (target <= 5), median rotation error "
        f"{np.median(all_rot):.2f} deg (target <= 3)"
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


def calibrate_benchmark(clip_dir: Path, scene: Path, out: Path, args: argparse.Namespace) -> None:
    from grounder._interaction import InteractionOptions, ground_with_interaction

    offsets = truth_offsets(scene)
    truth = {o["name"]: o for o in json.loads((clip_dir / "truth/objects.json").read_text())["objects"]}
    tick = time.perf_counter()
    result = ground_with_interaction(
        ROOT / "samples/tabletop/video.mp4",
        clip_dir / "video.mp4",
        out,
        InteractionOptions(
            track=TrackOptions(aruco_size_m=0.12),
            calibrate_settings={"generations": args.generations, "popsize": args.popsize},
        ),
        grounded_scene=scene,
        overwrite=True,
    )
    print(f"ground_with_interaction: {time.perf_counter() - tick:.1f} s; {result.report['stage_seconds']}")
    print(f"segments: {result.report['tracking']['segments']}; windows: {result.report['windows']}")
    calibration = result.report["calibration"]
    print(f"calibration: {calibration['status']}")
    for name, p in calibration.get("parameters", {}).items():
        body, field = name.split(".", 1)
        true_name = offsets[body][0]
        true_value = truth[true_name]["friction"][0] if field == "friction.sliding" else truth[true_name]["solref"][1]
        rel = (p["value"] - true_value) / true_value
        print(
            f"{name} ({true_name}): {p['nominal']:.3f} -> {p['value']:.3f} (interval {p['interval'][0]:.3f}.."
            f"{p['interval'][1]:.3f}); rendered with {true_value:.3f}; error {100 * rel:+.0f}%"
        )
    for split in ("train", "validation"):
        if calibration.get("before", {}).get(split, {}).get("count"):
            before = calibration["before"][split]["position_pct_of_size"]["mean"]
            after = calibration["after"][split]["position_pct_of_size"]["mean"]
            print(f"{split}: position error {before:.1f}% -> {after:.1f}% of object size")
    print("match with the clip (open-loop over the tracked segments):")
    for body, before in result.report["match_before"].items():
        after = result.report.get("match_after", {}).get(body, {})
        print(
            f"  {body}: mean position error {before['mean_position_error_mm']} -> "
            f"{after.get('mean_position_error_mm', '-')} mm"
        )


if __name__ == "__main__":
    main()
