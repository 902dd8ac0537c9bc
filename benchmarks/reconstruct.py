"""Reconstruct stage on the embedded tabletop sample: per-stage wall time and accuracy against the true cameras.

Run: `.venv/bin/python benchmarks/reconstruct.py [--sample samples/tabletop] [--threads N]`
Targets (issue 2): reconstruct <= 25 s on 2 CPU cores; >= 90% registered; camera centres within 5 mm (median) and
view directions within 0.5 deg of the truth, in the marker frame directly.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from reconstruction import ReconstructOptions, reconstruct

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sample", type=Path, default=REPO / "samples" / "tabletop")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads for COLMAP's matching and mapping (default: the tool's, SfmOptions.num_threads)",
    )
    args = parser.parse_args()
    options = ReconstructOptions(aruco_size_m=0.12)
    if args.threads is not None:
        options = replace(options, sfm=replace(options.sfm, num_threads=args.threads))
    with tempfile.TemporaryDirectory() as tmp:
        tick = time.perf_counter()
        result = reconstruct(args.sample / "video.mp4", Path(tmp) / "rec", options)
        wall_s = time.perf_counter() - tick
    truth = json.loads((args.sample / "truth" / "cameras.json").read_text())
    true_pose = {f["frame_index"]: np.array(f["world_from_cam"]) for f in truth["frames"]}
    centre_mm = np.array(
        [1000 * np.linalg.norm(f.world_from_cam[:3, 3] - true_pose[f.frame_index][:3, 3]) for f in result.frames]
    )
    view_deg = np.array(
        [
            np.degrees(np.arccos(np.clip(f.world_from_cam[:3, 2] @ true_pose[f.frame_index][:3, 2], -1, 1)))
            for f in result.frames
        ]
    )
    print(f"machine: {os.cpu_count()} CPU cores, COLMAP threads {options.sfm.num_threads}")
    print("stage seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in result.stage_seconds.items()))
    print(f"reconstruct wall time: {wall_s:.1f} s (target <= 25 s)")
    print(
        f"frames: {result.num_source_frames} in video, {len(result.selected_frame_indices)} selected "
        f"(dropped blurred {list(result.dropped_blurred)}, near-duplicate {list(result.dropped_duplicate)}), "
        f"{len(result.frames)} registered = {result.registration_rate:.1%} (target >= 90%)"
    )
    reprojection_px = result.mean_reprojection_error_px
    print(f"mean reprojection error: {reprojection_px:.2f} px; marker seen in {result.world.marker_views} frames")
    print(f"camera centre error: median {np.median(centre_mm):.2f} mm, max {centre_mm.max():.2f} mm (target <= 5 mm)")
    print(f"view direction error: median {np.median(view_deg):.3f} deg, max {view_deg.max():.3f} deg (target <= 0.5)")
    fx_true = truth["intrinsics"]["fx"]
    print(f"focal length: {result.intrinsics.fx_px:.2f} px (true {fx_true:.2f} px)")


if __name__ == "__main__":
    main()
