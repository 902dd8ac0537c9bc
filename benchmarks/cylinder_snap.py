"""A grounded scene with one object's visual mesh snapped onto its least-squares upright cylinder: measures whether
a scan's surface ripple is what biases model-based tracking's depth (docs/results/interaction.md).
`ground` does this itself since 2026-11-26 (`GroundOptions.cylinder_snap`, `reconstruction._primitives`, the same
function); this applies it to a scene grounded before.

The visual mesh is what `image2sim track` matches against the frames. A scanned can's side ripples by about 1 mm
RMS, and tracking reads depth from the mesh's apparent size and texture, so the can came out 4-9 mm nearer than
true in flight. This writes a copy of the scene in which the named object's visual mesh has its side vertices moved
radially onto the cylinder fitted to them (a least-squares circle in the body's x-y plane, the body's z as axis) and
its cap vertices onto the flat top and bottom. Texture coordinates, faces, the collision hulls, mass and inertia are
left as they are, so only what tracking sees changes.

Run: `.venv/bin/python benchmarks/cylinder_snap.py --scene out/det/scene --object object_2 --out
out/det/scene_cylvis`, then track and calibrate against the copy (`benchmarks/track.py --scene out/det/scene_cylvis
...`). Refuses (exit 2) an object whose side is not within 5% of its radius of a cylinder (RMS), as `ground` does.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from reconstruction._primitives import snap_to_upright_cylinder  # noqa: E402
from reconstruction._types import TexturedMesh  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", type=Path, required=True, help="grounded scene folder")
    parser.add_argument("--object", required=True, help="grounded body whose visual mesh is snapped (e.g. object_2)")
    parser.add_argument("--out", type=Path, required=True, help="new scene folder (must not exist)")
    args = parser.parse_args()
    obj_path = args.scene / "assets" / f"{args.object}_visual.obj"
    if not obj_path.is_file():
        sys.exit(f"cylinder_snap: error: {obj_path} not found; pass a grounded scene folder and one of its objects")
    if args.out.exists():
        sys.exit(f"cylinder_snap: error: {args.out} exists; pass a new folder")
    lines = obj_path.read_text().split("\n")
    rows = [i for i, line in enumerate(lines) if line.startswith("v ")]
    vertices = np.array([[float(v) for v in lines[i].split()[1:4]] for i in rows])
    snapped, fit = snap_to_upright_cylinder(TexturedMesh(vertices_m=vertices, faces=np.zeros((0, 3), np.int64)))
    if fit is None:
        print(f"cylinder_snap: error: {args.object} is not an upright cylinder; pick a round one", file=sys.stderr)
        sys.exit(2)
    about = (
        f"cylinder radius {1000 * fit.radius_m:.2f} mm, side ripple {1000 * fit.ripple_rms_m:.2f} mm RMS, "
        f"vertices moved median {1000 * fit.moved_median_m:.2f} mm, max {1000 * fit.moved_max_m:.2f} mm"
    )
    shutil.copytree(args.scene, args.out)
    for row, vertex in zip(rows, snapped.vertices_m, strict=True):
        extra = lines[row].split()[4:]  # vertex colours, if any
        lines[row] = " ".join(["v", *(f"{v:.7f}" for v in vertex), *extra])
    (args.out / "assets" / f"{args.object}_visual.obj").write_text("\n".join(lines))
    print(f"{args.object}: {about}; written {args.out}")


if __name__ == "__main__":
    main()
