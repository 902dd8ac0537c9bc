"""How accurate must the calibration windows' start states be? Calibrate each object of a tracked clip on its own
tracked windows (the tool's windows, paths and settings), with every window's first state replaced by the TRUE
state at that frame plus seeded random errors of a given size, and count the resolved friction and damping-ratio
values within 20% of the rendered ones.

Error size: `--scales` times the whole-start probe's sizes (`InteractionOptions.start_position_error_m`, 1.5 mm;
`start_rotation_error_deg`, 1 deg; `start_speed_error_m_s`, 0.03 m/s; `start_spin_error_rad_s`, 0.1 rad/s; each a
standard deviation per axis), about what tracking gets wrong at a window start on `samples/toss`. Scale 0 is the
true start with the tracked path after it (one draw).

    .venv/bin/python benchmarks/start_accuracy.py --run OUT --clip CLIP [--scales 0,0.25,0.5,1] [--draws 2]

OUT: a `benchmarks/track.py --calibrate --out OUT` run (its `grounded/` scene and `interaction/tracks/`); CLIP: the
clip it tracked (with its `truth/`), e.g. `samples/toss` or `out/tossB` from `samples/make_toss.py --heldout`.
A few seconds per object and draw.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from track import contact_values, true_motion_in_grounded_frames, truth_offsets  # noqa: E402

from grounder.core.trajectory import Trajectory  # noqa: E402
from grounder.interaction.options import InteractionOptions  # noqa: E402
from grounder.interaction.per_object import _single_body_trajectory, single_body_scene  # noqa: E402
from grounder.interaction.tracks import camera_poses_of, view_point_of  # noqa: E402
from grounder.interaction.windows import calibrate_constrained, object_windows  # noqa: E402
from grounder.tracking.output import load_object_trajectories  # noqa: E402

FIELDS = ("friction.sliding", "solref.dampratio")  # the target's values; the time constant is fitted beside them


def with_start(model: mujoco.MjModel, window: Trajectory, true_qpos: np.ndarray, true_qvel: np.ndarray,
               error: np.ndarray) -> Trajectory:  # fmt: skip
    """`window` with its first state the true one moved by `error` (position 3, rotation vector 3, velocity 6)."""
    qpos, qvel = window.qpos.astype(np.float64, copy=True), window.qvel.astype(np.float64, copy=True)
    start = true_qpos.astype(np.float64, copy=True)
    mujoco.mj_integratePos(model, start, error[:6], 1.0)
    qpos[0], qvel[0] = start, true_qvel + error[6:]
    return Trajectory(time_s=window.time_s, qpos=qpos, qvel=qvel, ctrl=window.ctrl, name=window.name)


def _scales(text: str) -> list[float]:
    try:
        scales = [float(s) for s in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated numbers >= 0, e.g. 0,0.25,1") from None
    if any(not s >= 0 for s in scales):
        raise argparse.ArgumentTypeError(f"{text!r}: error sizes must be >= 0")
    return scales


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a benchmarks/track.py --calibrate --out folder")
    parser.add_argument("--clip", type=Path, required=True, help="the clip it tracked (with truth/)")
    parser.add_argument(
        "--scales", type=_scales, default="0,0.25,0.5,1", help="error sizes, times the whole-start probe's"
    )
    parser.add_argument("--draws", type=int, default=2, help="seeded draws per size above 0")
    args = parser.parse_args()
    if args.draws < 1:
        parser.error(f"--draws {args.draws}: expected 1 or more")
    scene, tracks = args.run / "grounded", args.run / "interaction" / "tracks"
    for needed in (scene / "scene.xml", tracks / "track.json", args.clip / "truth" / "scene.xml"):
        if not needed.is_file():
            parser.error(f"{needed} not found; --run takes a `benchmarks/track.py --calibrate --out` folder and "
                         "--clip the clip it tracked")  # fmt: skip
    options = InteractionOptions()
    track_json = json.loads((tracks / "track.json").read_text())
    fps = float(track_json["fps"])
    view = view_point_of(camera_poses_of(track_json["world_from_cam"]))
    object_tracks = load_object_trajectories(tracks / "track.json", options.track.smoothing)
    truth = true_motion_in_grounded_frames(scene, args.clip)
    model = mujoco.MjModel.from_xml_path(str(scene / "scene.xml"))
    rendered = contact_values(args.clip / "truth" / "scene.xml", args.clip)
    offsets = truth_offsets(scene)
    sigma = np.array(
        [options.start_position_error_m] * 3
        + [np.radians(options.start_rotation_error_deg)] * 3
        + [options.start_speed_error_m_s] * 3
        + [options.start_spin_error_rad_s] * 3
    )
    scales: list[float] = args.scales
    counts = {s: [0, 0, 0] for s in scales}  # within 20%, wrong, unresolved
    for body in json.loads((scene / "scene.json").read_text())["objects"]:
        true_body = _single_body_trajectory(model, truth, body)
        fit = object_windows(list(object_tracks[body]), options)
        true_values = rendered[offsets[body][0]]
        params = [f"{body}.{name}" for name in (*FIELDS, "solref.timeconst")]
        with single_body_scene(scene / "scene.xml", body) as sub_xml:
            sub_model = mujoco.MjModel.from_xml_path(str(sub_xml))
            for scale in scales:
                for draw in range(args.draws if scale > 0 else 1):
                    rng = np.random.default_rng([draw, 7])
                    starts = []
                    for w in fit:
                        frame = round(float(w.time_s[0]) * fps)
                        error = rng.normal(size=12) * sigma * scale
                        starts.append(with_start(sub_model, w, true_body.qpos[frame], true_body.qvel[frame], error))
                    tick = time.perf_counter()
                    entry = calibrate_constrained(sub_xml, starts, params, options, view_point_m=view)
                    out = []
                    for field in FIELDS:
                        record = entry["parameters"][f"{body}.{field}"]
                        if not record.get("constrained"):
                            counts[scale][2] += 1
                            out.append(f"{field} unresolved")
                            continue
                        error_pct = 100.0 * (record["value"] / true_values[field] - 1.0)
                        counts[scale][0 if abs(error_pct) <= 20.0 else 1] += 1
                        out.append(f"{field} {error_pct:+.0f}%")
                    print(
                        f"{body} ({offsets[body][0]}), {len(fit)} windows, scale {scale:g}, draw {draw}: "
                        f"{', '.join(out)} ({time.perf_counter() - tick:.0f} s)",
                        flush=True,
                    )
    print(f"\n{args.run} on {args.clip}: resolved values within 20% of the rendered ones")
    for scale, (right, wrong, unresolved) in counts.items():
        print(f"  start errors x{scale:g}: {right} of {right + wrong} within 20%, {unresolved} unresolved")


if __name__ == "__main__":
    main()
