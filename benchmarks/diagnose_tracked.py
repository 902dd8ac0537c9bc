"""Gap diagnosis from tracked video, end to end: scene-family tabletops grounded, filmed being thrown with one effect
withheld on one object, tracked, and diagnosed, all by the commands a user runs.

Run: `MUJOCO_GL=osmesa .venv/bin/python benchmarks/diagnose_tracked.py [--seed 3000 --count 3] [--work DIR]
[--json FILE]`

Per scene (`samples/make_scene_family.py --small`, seeds from 3000: a range no test or tuning uses; a seed is taken
when its table has the ArUco marker `track` places the camera by, it has two or more objects and none is drawn
low-texture (the tracker finds objects by their texture), else skipped):
1. `image2sim ground SOURCE -o scene ARGS` (the family's ground arguments);
2. `samples/make_family_clip.py`: the objects thrown `THROWS` times in front of a static camera, reality being the
   grounded scene's physics on the true geometry except one object's sliding friction, scaled by 0.55-0.7 or 1.4-1.7;
3. `image2sim track clip/video.mp4 --scene scene -o tracks --scan-features` (the clip is filmed with the scan's
   camera, so the tracker also learns each object's look from the scan's frames);
4. `image2sim diagnose scene tracks -o diagnosis`.
5. the control: `image2sim diagnose` of the clip's true throws (no tracking) against the clip's true scene with the
   withheld value put back (no scan error): whether the clip makes the effect identifiable at all.
Scored: the withheld effect and its object (or that object's only contact pair) named; the fitted value against the
clip's; the held-out gap reduction above the noise floor; the share left unexplained per body; wall time per stage.
Stages already done in `--work` are reused (delete a folder to redo it: the stages made from it are redone too).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
FIRST_SEED = 3000
IMAGE2SIM = str(Path(sys.executable).parent / "image2sim")


def _run(cmd: list[str], log: Path) -> float:
    """Runs one stage (stdout and stderr to `log`); returns its wall time; raises with the log's tail on failure."""
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, "MUJOCO_GL": "osmesa"})
    if proc.returncode != 0:
        tail = log.read_text().replace("\r", "\n").strip().splitlines()[-3:]
        raise RuntimeError(f"{Path(cmd[0]).name} {cmd[1]} exited {proc.returncode}: {' / '.join(tail)}")
    return time.perf_counter() - start


def _render_family(family: Path, seed: int) -> None:
    """Renders family scene `seed` (`make_scene_family.py --small`) into `family`."""
    family.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(REPO / "samples" / "make_scene_family.py"), str(family), "--seed", str(seed), "--small"]
    _run(cmd, family / f"render_{seed}.log")


def one_scene(seed: int, work: Path) -> dict[str, Any] | None:
    """Grounds, films, tracks and diagnoses scene `seed`; None when the scene does not qualify."""
    family = work / "family"
    scene_dir = family / f"scene_{seed:05d}"
    if not scene_dir.exists():
        _render_family(family, seed)
    record = json.loads((scene_dir / "truth" / "family.json").read_text())
    low_texture = [o for o in record["objects"] if "low texture" in o]
    if record["scale_by"] != "marker" or len(record["objects"]) < 2 or low_texture:
        why = f"{record['scale_by']}, {len(record['objects'])} object(s), {len(low_texture)} low-texture"
        print(f"seed {seed}: skipped ({why})", flush=True)
        return None
    case = work / f"case_{seed:05d}"
    case.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    grounded, clip, control = case / "scene", case / "clip", case / "control"
    tracks, diag = case / "tracks", case / "diagnosis"
    # Each stage's output is reused when present; a stage that runs again voids every stage made from it.
    after = {
        grounded: [clip, control, tracks, diag],
        clip: [control, tracks, diag],
        tracks: [diag],
        control: [],
        diag: [],
    }

    def stage(name: str, folder: Path, done: str, cmd: list[str]) -> None:
        if (folder / done).is_file():
            return
        for stale in [folder, *after[folder]]:
            shutil.rmtree(stale, ignore_errors=True)
        seconds[name] = _run(cmd, case / f"{name}.log")

    source = scene_dir / record["source"]
    result: dict[str, Any] = {"seed": seed, "objects": record["objects"], "named": False, "seconds": seconds}
    stage(
        "ground", grounded, "scene.xml", [IMAGE2SIM, "ground", str(source), "-o", str(grounded), *record["ground_args"]]
    )
    clip_cmd = [sys.executable, str(REPO / "samples" / "make_family_clip.py"), str(scene_dir), "--scene", str(grounded)]
    stage("clip", clip, "video.mp4", [*clip_cmd, "-o", str(clip), "--seed", str(seed)])
    withheld = json.loads((clip / "truth" / "withheld.json").read_text())
    result["withheld"] = withheld_text(withheld)
    result["unmatched_grounded"] = withheld.get("unmatched_grounded", [])
    try:  # the control: the clip's true throws against its true scene with the withheld value put back
        nominal = clip / "truth" / "nominal.xml"
        if not (control / "diagnosis.json").is_file():  # only for a control still to run
            write_nominal(clip / "truth" / "scene.xml", withheld, nominal)
        stage(
            "control",
            control,
            "diagnosis.json",
            [IMAGE2SIM, "diagnose", str(nominal), str(clip / "truth" / "throws"), "-o", str(control)],
        )
        truth_named = {**withheld, "grounded_body": withheld["truth_object"]}
        control_doc = json.loads((control / "diagnosis.json").read_text())
        control_result = score(seed, record, truth_named, {"objects": {}}, control_doc, {})
        keys = ("selected", "named", "fitted", "fitted_error", "reduction_above_noise")
        result["control"] = {k: control_result[k] for k in keys}
        result["control"]["heldout_reduction"] = control_doc["heldout"]["reduction"]
    except RuntimeError as exc:
        result["control"] = {"error": str(exc), "named": False}
    try:
        track_cmd = [IMAGE2SIM, "track", str(clip / "video.mp4"), "--scene", str(grounded), "-o", str(tracks)]
        stage("track", tracks, "track.json", [*track_cmd, "--scan-features"])
        stage("diagnose", diag, "diagnosis.json", [IMAGE2SIM, "diagnose", str(grounded), str(tracks), "-o", str(diag)])
    except RuntimeError as exc:  # a stage that fails is a result too: which one, and why
        track_doc = json.loads((tracks / "track.json").read_text()) if (tracks / "track.json").is_file() else {}
        fractions = {k: v["tracked_fraction"] for k, v in track_doc.get("objects", {}).items()}
        return {**result, "error": str(exc), "tracked_fraction": fractions}
    track_doc = json.loads((tracks / "track.json").read_text())
    scored = score(seed, record, withheld, track_doc, json.loads((diag / "diagnosis.json").read_text()), seconds)
    return {**result, **scored}


def withheld_text(withheld: dict[str, Any]) -> str:
    """``sliding_friction@object_1 (box_0) 0.525 -> 0.318``: the effect, where (grounded and true name), values."""
    return (
        f"{withheld['effect']}@{withheld['grounded_body']} ({withheld['truth_object']}) "
        f"{float(withheld['scene_value']):.3f} -> {float(withheld['clip_value']):.3f}"
    )


def write_nominal(clip_scene: Path, withheld: dict[str, Any], out: Path) -> None:
    """The clip's true scene with the withheld value put back: what the diagnosis would be given with a perfect
    scan (the control: true geometry, true states, nothing tracked)."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(clip_scene))
    geom = spec.geom(f"{withheld['truth_object']}_geom")
    friction = list(geom.friction)
    friction[0] = float(withheld["scene_value"])
    geom.friction = friction
    out.write_text(spec.to_xml())


def score(
    seed: int,
    record: dict[str, Any],
    withheld: dict[str, Any],
    track: dict[str, Any],
    diagnosis: dict[str, Any],
    seconds: dict[str, float],
) -> dict[str, Any]:
    from grounder.diagnosis.benchmark import same_place

    body = str(withheld["grounded_body"])
    pairs = list(diagnosis["layout"]["contact_pairs"])
    selected = list(diagnosis["selected"])
    # The first selected effect (the one that explains most) must be the withheld one, at its object or that
    # object's only contact pair.
    first = next((e for e in diagnosis["effects"] if e["key"] == selected[0]), None) if selected else None
    named = first is not None and first["effect"] == withheld["effect"]
    named = named and first is not None and same_place(body, first["target"]["label"], pairs)
    fitted = float(next(iter(first["params"].values()))) if named and first is not None else None
    clip_value = float(withheld["clip_value"])
    heldout = diagnosis["heldout"]
    return {
        "seed": seed,
        "objects": record["objects"],
        "withheld": withheld_text(withheld),
        "tracked_fraction": {k: v["tracked_fraction"] for k, v in track["objects"].items()},
        "segments": len(track.get("segments", [])),
        "selected": selected,
        "named": named,
        "fitted": fitted,
        "fitted_error": None if fitted is None else abs(fitted - clip_value) / clip_value,
        "reduction_above_noise": heldout["reduction_above_noise"],
        "unexplained_by_body": {k: v["unexplained_fraction"] for k, v in diagnosis["unexplained_by_body"].items()},
        "finding": diagnosis["finding"],
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=FIRST_SEED, help="first seed to try (3000 and up: held out)")
    parser.add_argument("--count", type=int, default=3, help="scenes to diagnose (seeds that qualify)")
    parser.add_argument("--max-seeds", type=int, default=40, help="give up after trying this many seeds")
    parser.add_argument("--work", type=Path, default=REPO / "out" / "diagnose_tracked")
    parser.add_argument("--json", type=Path, help="write the per-scene results here")
    args = parser.parse_args()
    results: list[dict[str, Any]] = []
    for seed in range(args.seed, args.seed + args.max_seeds):
        if len(results) >= args.count:
            break
        try:
            result = one_scene(seed, args.work)
        except RuntimeError as exc:
            result = {"seed": seed, "error": str(exc), "named": False}
        if result is not None and "error" in result:
            print(f"seed {seed}: FAILED {result['error']}; control: {result.get('control')}", flush=True)
        if result is None:
            continue
        results.append(result)
        if "error" not in result:
            print(
                f"seed {seed}: withheld {result['withheld']}; selected {result['selected']}; named {result['named']}; "
                f"fitted {result['fitted']}; held-out reduction above noise {result['reduction_above_noise']:.0%}; "
                f"tracked {result['tracked_fraction']}, {result['segments']} segments; {result['seconds']}; "
                f"control (true scene and states): {result['control']}",
                flush=True,
            )
    named = sum(bool(r["named"]) for r in results)
    print(f"\nnamed the withheld effect and object in {named} of {len(results)} scenes")
    for r in results:
        print(json.dumps(r))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
