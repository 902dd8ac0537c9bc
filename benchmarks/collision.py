"""Collision geometry on the sample objects and a generated mug: CoACD time, hull count and size, volume, cavity.

Run: `.venv/bin/python benchmarks/collision.py [--coacd-defaults] [--samples 200000]`
Targets (film-a-scene issue, part 4): a concave object decomposes in <= 15 s on 2 CPU cores with <= 16 hulls of
<= 64 vertices and keeps its cavity (a 1.5 cm ball dropped into it stays inside); convex objects skip CoACD.
Caching is off here so every figure is a fresh decomposition.

Columns: `method` (convex_hull | coacd), `seconds` (wall time of `convex_decomposition`), `hulls`, `max verts`
(most vertices in one hull), `union/mesh` (Monte Carlo volume of the union of hulls over the mesh volume; 1.00 is
exact, above 1 the hulls fill space the object does not), `covered` (fraction of the mesh's volume inside the
hulls), `ball stays` (a 1.5 cm-radius ball dropped on the cavity's axis is still inside it after 1.5 s).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from reconstruction._types import TexturedMesh
from scene_export import (
    CoacdOptions,
    CollisionGeometry,
    CollisionOptions,
    SceneObjectSpec,
    TableSpec,
    convex_decomposition,
    export_scene,
)

REPO = Path(__file__).resolve().parents[1]
BALL_RADIUS_M = 0.015


@dataclass(frozen=True, kw_only=True)
class Cavity:
    """Where a dropped ball should end up, in the object frame: the cavity's axis, radius and rim height."""

    axis_xy_m: tuple[float, float]
    radius_m: float
    rim_z_m: float


def mug_mesh() -> tuple[trimesh.Trimesh, Cavity]:
    """A watertight mug (8 cm across, 9 cm tall, 5 mm wall, a ring handle), centred on its bounding box.

    Built as an occupancy grid (0.5 mm) closed by marching cubes, so no mesh-boolean engine is needed, then
    decimated to 4000 faces like a grounded object.
    """
    from skimage.measure import marching_cubes

    outer_r, height, wall, bottom = 0.04, 0.09, 0.005, 0.006
    major, minor = 0.026, 0.006  # handle ring in the x-z plane, centred on the outer wall at mid height
    step = 0.0005
    xs = np.arange(-outer_r - 2 * step, outer_r + major + minor + 2 * step, step)
    ys = np.arange(-outer_r - 2 * step, outer_r + 2 * step, step)
    zs = np.arange(-2 * step, height + 2 * step, step)
    x, y, z = np.meshgrid(xs, ys, zs, indexing="ij")
    r = np.hypot(x, y)
    cup = (r <= outer_r) & (z >= 0) & (z <= height) & ~((r <= outer_r - wall) & (z >= bottom))
    ring = np.hypot(np.hypot(x - outer_r, z - height / 2) - major, y) <= minor
    solid = (cup | ring).astype(np.float32)
    verts, faces, _, _ = marching_cubes(np.pad(solid, 1), level=0.5, spacing=(step, step, step))
    verts += np.array([xs[0], ys[0], zs[0]]) - step
    import open3d as o3d

    dense = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(faces[:, ::-1]))
    simple = dense.simplify_quadric_decimation(target_number_of_triangles=4000)  # a scanned object's face budget
    mug = trimesh.Trimesh(np.asarray(simple.vertices), np.asarray(simple.triangles), process=True)
    if mug.volume < 0:
        mug.invert()
    offset = -mug.bounds.mean(axis=0)
    mug.apply_translation(offset)
    return mug, Cavity(
        axis_xy_m=(float(offset[0]), float(offset[1])), radius_m=outer_r - wall, rim_z_m=height + float(offset[2])
    )


def sample_objects() -> list[tuple[str, trimesh.Trimesh, Cavity | None]]:
    assets = REPO / "samples" / "tabletop" / "truth" / "assets"
    out: list[tuple[str, trimesh.Trimesh, Cavity | None]] = []
    for name in ("bowl", "box", "can"):
        mesh = trimesh.load_mesh(assets / f"{name}.obj")
        cavity = Cavity(axis_xy_m=(0.0, 0.0), radius_m=0.075, rim_z_m=mesh.bounds[1, 2]) if name == "bowl" else None
        out.append((name, mesh, cavity))
    mug, cavity = mug_mesh()
    out.append(("mug", mug, cavity))
    return out


def inside_mesh(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """(N,) bool: which points are inside the closed mesh (Open3D's Embree ray casting; trimesh's is ~30x slower)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor.from_numpy(np.asarray(mesh.faces, np.uint32)),
    )
    return scene.compute_occupancy(o3d.core.Tensor.from_numpy(points.astype(np.float32))).numpy() > 0.5


def volume_ratios(mesh: trimesh.Trimesh, hulls: tuple[np.ndarray, ...], samples: int) -> tuple[float, float]:
    """(union-of-hulls volume / mesh volume, fraction of the mesh volume inside the hulls), by Monte Carlo."""
    rng = np.random.default_rng(0)
    low = np.min([h.min(axis=0) for h in hulls] + [mesh.bounds[0]], axis=0)
    high = np.max([h.max(axis=0) for h in hulls] + [mesh.bounds[1]], axis=0)
    points = rng.uniform(low, high, size=(samples, 3))
    in_union = np.zeros(samples, bool)
    for hull in hulls:
        equations = ConvexHull(hull).equations
        in_union |= (points @ equations[:, :3].T + equations[:, 3] <= 1e-9).all(axis=1)
    in_mesh = inside_mesh(mesh, points)
    box_volume = float(np.prod(high - low))
    union_volume = in_union.mean() * box_volume
    return union_volume / mesh.volume, float((in_union & in_mesh).sum() / max(1, in_mesh.sum()))


def ball_stays(mesh: trimesh.Trimesh, collision: CollisionGeometry, cavity: Cavity, tmp: Path) -> bool:
    """Exports the object alone on the table, drops a ball on the cavity's axis, and checks it is inside at 1.5 s."""
    pose = np.eye(4)
    pose[2, 3] = -mesh.bounds[0, 2]  # resting on the table top (z = 0)
    scene = export_scene(
        [
            SceneObjectSpec(
                name="object",
                visual=TexturedMesh(vertices_m=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces)),
                collision=collision,
                world_from_object=pose,
                density_kg_m3=1500.0,
            )
        ],
        TableSpec(),
        [],
        tmp / "scene",
        overwrite=True,
    )
    spec = mujoco.MjSpec.from_file(str(scene.scene_xml))
    axis = np.array([*cavity.axis_xy_m, 0.0]) + pose[:3, 3]
    ball = spec.worldbody.add_body(name="ball", pos=[axis[0], axis[1], pose[2, 3] + cavity.rim_z_m + 0.04])
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS_M, 0, 0], density=1000.0)
    model = spec.compile()
    data = mujoco.MjData(model)
    for _ in range(round(1.5 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    body = model.body("object").id
    ball_in_object = data.xmat[body].reshape(3, 3).T @ (data.xpos[model.body("ball").id] - data.xpos[body])
    radial = np.linalg.norm(ball_in_object[:2] - np.array(cavity.axis_xy_m))
    return bool(radial < cavity.radius_m and ball_in_object[2] < cavity.rim_z_m)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coacd-defaults", action="store_true", help="also time CoACD with its own defaults")
    parser.add_argument("--samples", type=int, default=200_000, help="Monte Carlo points for the volume ratios")
    args = parser.parse_args()
    tuned = CollisionOptions(cache_dir=None)
    configs = [("tuned", tuned)]
    if args.coacd_defaults:
        # CoACD's own defaults (no hull or vertex limits); our hard limits still apply afterwards.
        plain = CoacdOptions(
            max_convex_hull=-1,
            preprocess_resolution=50,
            resolution=2000,
            mcts_nodes=20,
            mcts_iterations=150,
            mcts_max_depth=3,
            decimate=False,
            max_ch_vertex=256,
        )
        configs.append(("coacd-defaults", replace(tuned, coacd=plain)))
    print(f"machine: {os.cpu_count()} CPU cores; mujoco {mujoco.__version__}, trimesh {trimesh.__version__}")
    print(f"tuned CoacdOptions: {tuned.coacd}")
    header = f"{'object':7} {'config':15} {'method':12} {'seconds':>8} {'hulls':>5} {'max verts':>9} "
    print(header + f"{'union/mesh':>10} {'covered':>8} {'ball stays':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, mesh, cavity in sample_objects():
            ratio = mesh.volume / mesh.convex_hull.volume
            for label, options in configs:
                collision = convex_decomposition(mesh.vertices, mesh.faces, options)
                union, covered = volume_ratios(mesh, collision.hulls, args.samples)
                stays = "n/a" if cavity is None else ("yes" if ball_stays(mesh, collision, cavity, Path(tmp)) else "NO")
                print(
                    f"{name:7} {label:15} {collision.method:12} {collision.seconds:8.2f} {len(collision.hulls):5d} "
                    f"{max(len(h) for h in collision.hulls):9d} {union:10.2f} {covered:8.3f} {stays:>10}"
                    + (f"   (mesh/convex-hull volume {ratio:.2f})" if label == "tuned" else "")
                )


if __name__ == "__main__":
    main()
