"""The front door's speed, side by side with the tools a user would otherwise run, in one run on one machine.

Run: `MUJOCO_GL=osmesa .venv/bin/python benchmarks/speed.py [--work out/speed] [--json FILE] [--skip-calibrate]`

1. `image2sim reconstruct` against COLMAP's own pipeline with its default options (`pycolmap.extract_features`,
   `match_sequential` for a video or `match_exhaustive` for photos, `incremental_mapping`), each in a process of its
   own as a user runs them, on the same frames (the ones `reconstruct` selected and wrote to its `images/`): wall
   time, and camera centre error against the truth, (a) in the marker frame, COLMAP's model put through the same
   world-frame step as ours (`reconstruction._reconstruct._establish_world`), where the input has a marker, and (b)
   after a similarity alignment of each tool's registered centres to the true ones (Umeyama), on every input. Inputs:
   `samples/tabletop`, the first two videos and the first photo set among scene-family seeds 2000 and up (this
   benchmark's range: no test or tuning uses it; rendered once into `--work`).
2. `image2sim ground samples/tabletop/video.mp4` per stage (`scene.json`'s `stage_seconds_detail`).
3. `image2sim calibrate` on the 280 training cube tosses of `../shared/data/cube_toss` with `benchmarks/cube_toss.py`'s
   parameters and budget, every training toss fitted: wall time, model steps per second, held-out error.

Targets (issue 63): reconstruct <= 0.3x COLMAP's time with camera centres no worse than 1.2x COLMAP's, on each input;
ground on the sample <= 30 s; calibrate on 280 tosses <= 5 min at a held-out error within 0.3 points of 13.4%.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CLI = str(REPO / ".venv" / "bin" / "image2sim")
SHARED = REPO.parent / "shared" / "data" / "cube_toss"
FIRST_SEED = 2000  # this benchmark's scene-family seeds (samples/make_scene_family.py lists the ranges)
ENV = {**os.environ, "MUJOCO_GL": "osmesa"}

# COLMAP with its defaults, as a user runs it, in a fresh process: the times of its three steps, its largest model.
_COLMAP_DEFAULTS = """
import json, sys, time
from pathlib import Path
import pycolmap
images, work, sequential = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3] == "video"
database = work / "database.db"
tick = time.perf_counter()
pycolmap.extract_features(database, images)
features = time.perf_counter()
(pycolmap.match_sequential if sequential else pycolmap.match_exhaustive)(database)
matching = time.perf_counter()
models = pycolmap.incremental_mapping(database, images, work / "sparse")
mapping = time.perf_counter()
best = max(models.items(), key=lambda kv: kv[1].num_reg_images())[0] if models else None
print(json.dumps({"features": features - tick, "matching": matching - features, "mapping": mapping - matching,
                  "model": None if best is None else str(work / "sparse" / str(best))}))
"""


def family_inputs(scenes: Path) -> list[tuple[str, Path, list[str], Path]]:
    """The first two videos and the first photo set among the family's seeds from FIRST_SEED, rendered on demand."""
    picked: list[tuple[str, Path, list[str], Path]] = []
    videos = photos = 0
    for seed in range(FIRST_SEED, FIRST_SEED + 40):
        scene = scenes / f"scene_{seed:05d}"
        if not (scene / "truth" / "family.json").exists():
            cmd = [sys.executable, str(REPO / "samples" / "make_scene_family.py"), str(scenes), "--seed", str(seed)]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env=ENV)
        family = json.loads((scene / "truth" / "family.json").read_text())
        is_photos = family["source"] == "photos"
        if (is_photos and photos < 1) or (not is_photos and videos < 2):
            kind = "photos" if is_photos else "video"
            label = f"family {seed} ({kind}, {family['views']} views, {family['size_px'][0]}x{family['size_px'][1]})"
            picked.append((label, scene / family["source"], family["ground_args"], scene / "truth" / "cameras.json"))
            photos += is_photos
            videos += not is_photos
        if photos >= 1 and videos >= 2:
            return picked
    raise SystemExit(f"fewer than two videos and one photo set among seeds {FIRST_SEED}..{FIRST_SEED + 39}")


def true_centres(cameras_json: Path) -> dict[int, np.ndarray]:
    """Camera centre (world, metres) by frame index: the video frame's, or the photo's place in the sorted folder."""
    frames = json.loads(cameras_json.read_text())["frames"]
    return {int(f["frame_index"]): np.asarray(f["world_from_cam"], float)[:3, 3] for f in frames}


def frame_index(image_name: str) -> int:
    match = re.fullmatch(r"frame_(\d+)\.\w+", image_name)
    if match is None:
        raise ValueError(f"unexpected image name {image_name!r}")
    return int(match.group(1))


def model_centres(model_dir: Path) -> dict[int, np.ndarray]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    return {frame_index(im.name): np.asarray(im.projection_center()) for im in rec.images.values() if im.has_pose}


def aligned_errors_mm(found: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> np.ndarray:
    """Centre errors after the similarity that best maps the found centres onto the true ones (Umeyama)."""
    from reconstruction._world import umeyama

    keys = sorted(set(found) & set(truth))
    src = np.array([found[k] for k in keys])
    dst = np.array([truth[k] for k in keys])
    scale, rot, trans = umeyama(src, dst)
    moved = scale * src @ rot.T + trans
    return 1000 * np.linalg.norm(moved - dst, axis=1)


def direct_errors_mm(found: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> np.ndarray:
    keys = sorted(set(found) & set(truth))
    return np.array([1000 * np.linalg.norm(found[k] - truth[k]) for k in keys])


def colmap_in_marker_frame(model_dir: Path, images: Path, args: list[str]) -> dict[int, np.ndarray] | None:
    """COLMAP's camera centres put through our world-frame step (marker inputs only), None where it fails."""
    import cv2
    import pycolmap

    from reconstruction import _frames
    from reconstruction._reconstruct import _detect_marker, _establish_world
    from reconstruction._types import ReconstructOptions

    if "--aruco-size" not in args:
        return None
    options = ReconstructOptions(aruco_size_m=float(args[args.index("--aruco-size") + 1]))
    rec = pycolmap.Reconstruction(str(model_dir))
    names = sorted(im.name for im in rec.images.values())
    frames = tuple(
        _frames.Frame(index=frame_index(n), name=n, image_bgr=cv2.imread(str(images / n), cv2.IMREAD_COLOR))
        for n in names
    )
    try:
        world = _establish_world(rec, _detect_marker(frames, names, options), options)
    except Exception as exc:  # a model the marker step cannot use is reported as such, not as an error of ours
        print(f"  COLMAP's model through the marker step: {type(exc).__name__}: {exc}")
        return None
    m = world.world_from_sfm
    return {frame_index(im.name): m[:3, :3] @ im.projection_center() + m[:3, 3] for im in rec.images.values()}


def side_by_side(label: str, source: Path, args: list[str], cameras: Path, work: Path) -> dict[str, object]:
    out = work / "reconstruct"
    cmd = [CLI, "reconstruct", str(source), "-o", str(out), "--overwrite", *args]
    tick = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, env=ENV)
    ours_s = time.perf_counter() - tick
    if run.returncode != 0:
        return {"input": label, "error": (run.stderr.strip().splitlines() or ["?"])[-1]}
    stages = json.loads((out / "reconstruct.json").read_text())["stage_seconds"]
    truth = true_centres(cameras)
    ours = model_centres(out / "sparse")
    images = out / "images"
    with tempfile.TemporaryDirectory(dir=work) as tmp:
        kind = "photos" if source.is_dir() else "video"
        tick = time.perf_counter()
        colmap = subprocess.run(
            [sys.executable, "-c", _COLMAP_DEFAULTS, str(images), tmp, kind], capture_output=True, text=True
        )
        colmap_s = time.perf_counter() - tick
        colmap_stages = json.loads(colmap.stdout.strip().splitlines()[-1])
        model = colmap_stages.pop("model")
        theirs = model_centres(Path(model)) if model else {}
        marker = colmap_in_marker_frame(Path(model), images, args) if model else None
    record: dict[str, object] = {
        "input": label,
        "frames": len(list(images.iterdir())),
        "ours_s": ours_s,
        "ours_stages": stages,
        "ours_registered": len(ours),
        "colmap_s": colmap_s,
        "colmap_stages": colmap_stages,
        "colmap_registered": len(theirs),
        "ratio": ours_s / colmap_s,
        "ours_aligned_mm": float(np.median(aligned_errors_mm(ours, truth))),
        "colmap_aligned_mm": float(np.median(aligned_errors_mm(theirs, truth))) if len(theirs) >= 3 else None,
    }
    if "--aruco-size" in args:
        record["ours_marker_mm"] = float(np.median(direct_errors_mm(ours, truth)))
        record["colmap_marker_mm"] = None if marker is None else float(np.median(direct_errors_mm(marker, truth)))
    return record


def ground_stages(work: Path) -> dict[str, object]:
    out = work / "ground"
    cmd = [CLI, "ground", str(REPO / "samples" / "tabletop" / "video.mp4"), "-o", str(out), "--overwrite"]
    tick = time.perf_counter()
    run = subprocess.run([*cmd, "--aruco-size", "0.12"], capture_output=True, text=True, env=ENV)
    wall_s = time.perf_counter() - tick
    if run.returncode != 0:
        return {"error": (run.stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall_s}
    manifest = json.loads((out / "scene.json").read_text())
    return {"wall_s": wall_s, "stages": manifest["stage_seconds_detail"], "objects": len(manifest["objects"])}


def calibrate_tosses(work: Path) -> dict[str, object]:
    sys.path.insert(0, str(REPO / "benchmarks"))
    from cube_toss import CUBE_XML, DEFAULT_PARAMS

    trajs, out = work / "cube_npz", work / "cube_cal"
    if not trajs.exists():
        subprocess.run(
            [CLI, "import-trajectories", "--format", "dair-pll-cube", str(SHARED), "-o", str(trajs)],
            check=True,
            capture_output=True,
        )
    if out.exists():
        shutil.rmtree(out)
    cmd = [CLI, "calibrate", str(CUBE_XML), str(trajs), "-o", str(out)]
    for name in DEFAULT_PARAMS:
        cmd += ["--params", name]
    cmd += ["--popsize", "5", "--generations", "12", "--local-iterations", "4"]  # cube_toss.py's budget
    tick = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, env=ENV)
    wall_s = time.perf_counter() - tick
    if run.returncode != 0:
        return {"error": (run.stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall_s}
    record = json.loads((out / "calibration.json").read_text())
    validation = record["errors"]["after"]["validation"]
    return {
        "wall_s": wall_s,
        "train": len(record["split"]["train"]),
        "validation": len(record["split"]["validation"]),
        "steps_per_second": record["steps_per_second"],
        "evaluations": record["evaluations"],
        "validation_position_pct": validation["position_pct_of_size"]["mean"],
        "validation_rotation_deg": validation["rotation_deg"]["mean"],
    }


def _fmt(value: object, spec: str = ".2f") -> str:
    return "-" if value is None else format(value, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=REPO / "out" / "speed")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--skip-family", action="store_true", help="the tabletop sample only")
    parser.add_argument("--skip-ground", action="store_true")
    parser.add_argument("--skip-calibrate", action="store_true")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"machine: {os.cpu_count()} CPU cores")

    inputs = [
        (
            "samples/tabletop (video)",
            REPO / "samples" / "tabletop" / "video.mp4",
            ["--aruco-size", "0.12"],
            REPO / "samples" / "tabletop" / "truth" / "cameras.json",
        )
    ]
    if not args.skip_family:
        inputs += family_inputs(args.work / "scenes")
    figures: dict[str, object] = {"reconstruct": []}
    print("\nreconstruct vs COLMAP defaults (same frames; centre error median, mm)")
    print("input | frames | ours s | COLMAP s | ratio (<= 0.3) | registered ours/COLMAP | marker frame ours/COLMAP |")
    print("  aligned ours/COLMAP | ours: features, matching, mapping s | COLMAP: features, matching, mapping s")
    for label, source, ground_args, cameras in inputs:
        r = side_by_side(label, source, ground_args, cameras, args.work)
        figures["reconstruct"].append(r)  # type: ignore[attr-defined]
        if "error" in r:
            print(f"{label} | failed: {r['error']}")
            continue
        s, c = r["ours_stages"], r["colmap_stages"]
        print(
            f"{label} | {r['frames']} | {r['ours_s']:.1f} | {r['colmap_s']:.1f} | {r['ratio']:.2f} | "
            f"{r['ours_registered']}/{r['colmap_registered']} | "
            f"{_fmt(r.get('ours_marker_mm'))}/{_fmt(r.get('colmap_marker_mm'))} | "
            f"{_fmt(r['ours_aligned_mm'])}/{_fmt(r['colmap_aligned_mm'])} | "
            f"{s['features']:.1f}, {s['matching']:.1f}, {s['mapping']:.1f} | "  # type: ignore[index]
            f"{c['features']:.1f}, {c['matching']:.1f}, {c['mapping']:.1f}",  # type: ignore[index]
            flush=True,
        )
    if not args.skip_ground:
        g = ground_stages(args.work)
        figures["ground"] = g
        if "error" in g:
            print(f"\nground on samples/tabletop failed: {g['error']}")
        else:
            stages = ", ".join(f"{k} {v:.1f}" for k, v in g["stages"].items())  # type: ignore[attr-defined]
            print(f"\nground samples/tabletop: {g['wall_s']:.1f} s wall (target <= 30 s), {g['objects']} objects")
            print(f"  by stage (s): {stages}")
    if not args.skip_calibrate:
        if not SHARED.is_dir():
            print(f"\ncalibrate: skipped, the real cube tosses are not at {SHARED}")
        else:
            c = calibrate_tosses(args.work)
            figures["calibrate"] = c
            if "error" in c:
                print(f"\ncalibrate failed: {c['error']}")
            else:
                print(
                    f"\ncalibrate on {c['train']} training tosses: {c['wall_s']:.0f} s wall (target <= 300 s), "
                    f"{c['steps_per_second']:.0f} model steps/s in rollouts, {c['evaluations']} trajectory rollouts; "
                    f"held out ({c['validation']}): {c['validation_position_pct']:.1f}% / "
                    f"{c['validation_rotation_deg']:.1f} deg (target within 0.3 of 13.4%)"
                )
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
