"""A grounded scene with one object's visual mesh snapped onto its least-squares upright cylinder: measures whether
a scan's surface ripple is what biases model-based tracking's depth (README, "A calibrated scene from video alone").

The visual mesh is what `image2sim track` matches against the frames. A scanned can's side ripples by about 1 mm
RMS, and tracking reads depth from the mesh's apparent size and texture, so the can came out 4-9 mm nearer than
true in flight. This writes a copy of the scene in which the named object's visual mesh has its side vertices moved
radially onto the cylinder fitted to them (a least-squares circle in the body's x-y plane, the body's z as axis) and
its cap vertices onto the flat top and bottom. Texture coordinates, faces, the collision hulls, mass and inertia are
left as they are, so only what tracking sees changes.

Run: `.venv/bin/python benchmarks/cylinder_snap.py --scene out/det/scene --object object_2 --out
out/det/scene_cylvis`, then track and calibrate against the copy (`benchmarks/track.py --scene out/det/scene_cylvis
...`). Refuses (exit 2) an object whose side is not within 5% of its radius of a cylinder (RMS).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

SIDE_MARGIN_M = 0.01  # vertices this far from both caps define the side's circle
CAP_BAND_M = 0.004  # vertices this close to a cap (or to the side's radius) are moved onto it
MAX_RIPPLE_FRACTION = 0.05  # of the radius: above this the object is not a cylinder


def upright_cylinder(vertices_m: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """Centre x, y, radius, side ripple RMS (m), bottom and top z of the least-squares upright cylinder."""
    z_bottom, z_top = float(vertices_m[:, 2].min()), float(vertices_m[:, 2].max())
    side = (vertices_m[:, 2] > z_bottom + SIDE_MARGIN_M) & (vertices_m[:, 2] < z_top - SIDE_MARGIN_M)
    x, y = vertices_m[side, 0], vertices_m[side, 1]
    design = np.c_[2 * x, 2 * y, np.ones(len(x))]
    cx, cy, c = np.linalg.lstsq(design, x**2 + y**2, rcond=None)[0]
    radius = float(np.sqrt(c + cx**2 + cy**2))
    ripple = float(np.sqrt(np.mean((np.hypot(x - cx, y - cy) - radius) ** 2)))
    return float(cx), float(cy), radius, ripple, z_bottom, z_top


def snapped(vertices_m: np.ndarray) -> tuple[np.ndarray, str]:
    """The vertices moved onto their upright cylinder, and a line describing the fit."""
    cx, cy, radius, ripple, z_bottom, z_top = upright_cylinder(vertices_m)
    about = (
        f"cylinder radius {1000 * radius:.2f} mm, side ripple {1000 * ripple:.2f} mm RMS, "
        f"height {1000 * (z_top - z_bottom):.1f} mm"
    )
    if ripple > MAX_RIPPLE_FRACTION * radius:
        raise ValueError(f"not a cylinder ({about}); pick an object whose side is round")
    out = vertices_m.copy()
    offset = vertices_m[:, :2] - [cx, cy]
    r = np.linalg.norm(offset, axis=1)
    rim = r > radius - CAP_BAND_M
    out[rim, :2] = [cx, cy] + offset[rim] * (radius / r[rim])[:, None]
    out[vertices_m[:, 2] > z_top - CAP_BAND_M, 2] = z_top
    out[vertices_m[:, 2] < z_bottom + CAP_BAND_M, 2] = z_bottom
    moved_mm = 1000 * np.linalg.norm(out - vertices_m, axis=1)
    return out, f"{about}; vertices moved median {np.median(moved_mm):.2f} mm, max {moved_mm.max():.2f} mm"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="grounded scene folder")
    parser.add_argument("--object", required=True, help="grounded body whose visual mesh is snapped (e.g. object_2)")
    parser.add_argument("--out", type=Path, required=True, help="new scene folder (must not exist)")
    args = parser.parse_args()
    mesh = args.scene / "assets" / f"{args.object}_visual.obj"
    if not mesh.is_file():
        sys.exit(f"cylinder_snap: error: {mesh} not found; pass a grounded scene folder and one of its objects")
    if args.out.exists():
        sys.exit(f"cylinder_snap: error: {args.out} exists; pass a new folder")
    lines = mesh.read_text().split("\n")
    rows = [i for i, line in enumerate(lines) if line.startswith("v ")]
    vertices = np.array([[float(v) for v in lines[i].split()[1:4]] for i in rows])
    try:
        moved, about = snapped(vertices)
    except ValueError as error:
        print(f"cylinder_snap: error: {args.object}: {error}", file=sys.stderr)
        sys.exit(2)
    shutil.copytree(args.scene, args.out)
    for row, vertex in zip(rows, moved, strict=True):
        extra = lines[row].split()[4:]  # vertex colours, if any
        lines[row] = " ".join(["v", *(f"{v:.7f}" for v in vertex), *extra])
    (args.out / "assets" / f"{args.object}_visual.obj").write_text("\n".join(lines))
    print(f"{args.object}: {about}; written {args.out}")


if __name__ == "__main__":
    main()
