"""Comparing a grounded scene with a ground truth (for synthetic samples and benchmarks)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from grounder.errors import GrounderError

if TYPE_CHECKING:
    import trimesh


@dataclass(frozen=True, kw_only=True)
class ObjectError:
    """How far one grounded object is from the true object it was matched to (world frame, metres)."""

    name: str
    true_name: str
    centre_error_m: float  # bounding-box centres
    chamfer_m: float  # mean of both directed mean surface distances
    extents_m: tuple[float, float, float]
    true_extents_m: tuple[float, float, float]
    volume_ratio: float  # grounded / true

    @property
    def extent_error(self) -> float:
        """Largest relative error over the three world-axis extents."""
        return float(np.max(np.abs(np.array(self.extents_m) / np.array(self.true_extents_m) - 1)))


def _true_meshes(truth_dir: Path) -> dict[str, trimesh.Trimesh]:
    import trimesh

    objects = json.loads((truth_dir / "objects.json").read_text())["objects"]
    out: dict[str, trimesh.Trimesh] = {}
    for obj in objects:
        mesh = trimesh.load_mesh(truth_dir / obj["mesh"])
        w, x, y, z = obj["quat_wxyz"]
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        pose[:3, 3] = obj["pos_m"]
        mesh.apply_transform(pose)
        out[obj["name"]] = mesh
    return out


def _grounded_meshes(scene_dir: Path) -> dict[str, trimesh.Trimesh]:
    import trimesh

    manifest = json.loads((scene_dir / "scene.json").read_text())
    out: dict[str, trimesh.Trimesh] = {}
    for name, obj in manifest["objects"].items():
        mesh = trimesh.load_mesh(scene_dir / obj["visual_mesh"], process=False)
        w, x, y, z = obj["quat_wxyz"]
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
        pose[:3, 3] = obj["pos_m"]
        mesh.apply_transform(pose)
        out[name] = mesh
    return out


def compare_to_truth(scene_dir: Path, truth_dir: Path, *, samples: int = 30000, seed: int = 0) -> list[ObjectError]:
    """Matches each grounded object to the nearest true object (by centre) and measures the errors.

    Args:
        scene_dir: a folder written by `ground` (scene.json + assets).
        truth_dir: a sample's truth folder (objects.json + meshes).

    Raises:
        GrounderError: two grounded objects match the same true object.
    """
    truth = _true_meshes(truth_dir)
    grounded = _grounded_meshes(scene_dir)
    rng = np.random.default_rng(seed)
    errors, used = [], set()
    for name, mesh in grounded.items():
        centre = mesh.bounds.mean(axis=0)
        true_name = min(truth, key=lambda n: np.linalg.norm(truth[n].bounds.mean(axis=0) - centre))
        if true_name in used:
            raise GrounderError(f"{name} and another grounded object both match true object {true_name}")
        used.add(true_name)
        true_mesh = truth[true_name]
        a = _sample(mesh, samples, rng)
        b = _sample(true_mesh, samples, rng)
        (d_ab, _), (d_ba, _) = _nearest_both_ways(a, b)
        errors.append(
            ObjectError(
                name=name,
                true_name=true_name,
                centre_error_m=float(np.linalg.norm(centre - true_mesh.bounds.mean(axis=0))),
                chamfer_m=float((d_ab.mean() + d_ba.mean()) / 2),
                extents_m=_triple(mesh.extents),
                true_extents_m=_triple(true_mesh.extents),
                volume_ratio=float(mesh.volume / true_mesh.volume),
            )
        )
    return errors


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


def _sample(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> np.ndarray:
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    return np.asarray(points)


# ---------------------------------------------------------------- scoring a scene of the family (issue 60)


@dataclass(frozen=True, kw_only=True)
class ObjectScore:
    """One true object of a family scene against the grounded body matched to it (truth world frame, metres).

    Unfound objects carry only their names and class; every figure is None for them."""

    true_name: str
    object_class: str
    variant: str
    name: str | None  # the grounded body, None when not found
    centre_error_m: float | None = None  # bounding-box centres
    chamfer_m: float | None = None  # mean of both directed mean surface distances
    extent_error: float | None = None  # worst relative error over the three world-axis extents
    normal_consistency: float | None = None  # mean |cos| between normals at nearest points, both directions
    volume_ratio: float | None = None  # grounded / true
    euler_number: int | None = None  # of the grounded visual mesh, vertices merged by position
    true_euler_number: int | None = None
    open_container: bool = False
    keeps_ball: bool | None = None  # open containers: a 1.5 cm ball dropped in is still inside after 2 s
    mesh_quality: str | None = None  # scene.json's "mesh.quality" ("fallback" when meshing failed)

    @property
    def found(self) -> bool:
        return self.name is not None


@dataclass(frozen=True, kw_only=True)
class SceneScore:
    """A grounded family scene against its truth: per true object, the grounded bodies matched to none, and how
    the grounded world frame was put onto the truth's."""

    objects: tuple[ObjectScore, ...]
    extra_bodies: tuple[str, ...]
    alignment: str  # "marker frame" or "rigid fit of camera centres"
    scale_ratio: float  # grounded / true camera spread: the scale error (1.0 for a perfect scale)


def _rigid_from_cameras(scene_dir: Path, truth_dir: Path) -> tuple[np.ndarray, float, int]:
    """4x4 truth_from_grounded, the rigid (Kabsch) fit of the grounded camera centres onto the true ones, the
    ratio of their spreads (the grounded scale error), and how many cameras the fit left out. Frames are paired by
    `frame_index`; cameras registered far from where they were (a photo put on the wrong side of the table) are
    left out (`robust_rigid_fit`) so that they do not tilt the frame every object is scored in."""
    transforms = json.loads((scene_dir / "reconstruction" / "transforms.json").read_text())
    truth = json.loads((truth_dir / "cameras.json").read_text())
    true_centres = {f["frame_index"]: np.asarray(f["world_from_cam"])[:3, 3] for f in truth["frames"]}
    pairs = [
        (np.asarray(f["transform_matrix"])[:3, 3], true_centres[f["frame_index"]])
        for f in transforms["frames"]
        if f["frame_index"] in true_centres
    ]
    if len(pairs) < 3:
        raise GrounderError(f"only {len(pairs)} grounded cameras pair with the truth's; cannot align the frames")
    grounded = np.array([p[0] for p in pairs])
    true = np.array([p[1] for p in pairs])
    pose, kept = robust_rigid_fit(grounded, true)
    g, t = grounded[kept], true[kept]
    g0, t0 = g.mean(axis=0), t.mean(axis=0)
    spread = float(np.sqrt(((g - g0) ** 2).sum(axis=1).mean() / ((t - t0) ** 2).sum(axis=1).mean()))
    return pose, spread, int((~kept).sum())


def _kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 rigid transform taking (N, 3) `source` onto `target` in the least-squares sense."""
    s0, t0 = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((target - t0).T @ (source - s0))
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = t0 - rotation @ s0
    return pose


def robust_rigid_fit(source: np.ndarray, target: np.ndarray, rounds: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch fit of `source` onto `target` that leaves out points more than 3x the median residual (and over
    1 mm) off, refitted until the set stops changing; returns the 4x4 transform and the (N,) mask of points kept."""
    kept = np.ones(len(source), bool)
    pose = _kabsch(source, target)
    for _ in range(rounds):
        residual = np.linalg.norm(source @ pose[:3, :3].T + pose[:3, 3] - target, axis=1)
        new = residual <= max(3.0 * float(np.median(residual[kept])), 1e-3)
        if new.sum() < 3 or (new == kept).all():
            break
        kept = new
        pose = _kabsch(source[kept], target[kept])
    return pose, kept


def _samples_with_normals(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    points, faces = trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 31)))
    return np.asarray(points), np.asarray(mesh.face_normals)[faces]


def _nearest_both_ways(a: np.ndarray, b: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """(distances, indices) from each point of `a` to its nearest in `b`, then from `b` to `a`."""
    return cKDTree(b).query(a), cKDTree(a).query(b)


def _surface_agreement(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """Chamfer distance (mean of both directed mean distances) between two (points, normals) samplings, and the
    normal consistency: the mean |cos| of the angle between each sample's normal and its nearest sample's on the
    other surface, both ways (1 = the surfaces face the same way everywhere; 0.64 = random directions)."""
    (d_ab, i_ab), (d_ba, i_ba) = _nearest_both_ways(a[0], b[0])
    cos_ab = np.abs((a[1] * b[1][i_ab]).sum(axis=1))
    cos_ba = np.abs((b[1] * a[1][i_ba]).sum(axis=1))
    return float((d_ab.mean() + d_ba.mean()) / 2), float((cos_ab.mean() + cos_ba.mean()) / 2)


def _cavity_drop_point(mesh: trimesh.Trimesh, cell_m: float = 0.003) -> np.ndarray:
    """The point 1 cm above an open container's rim over the lowest floor inside it (world frame): where a ball
    dropped straight down lands in the cavity. From a height map of surface samples seen from above: per 3 mm
    cell the highest sample; the cavity floor is the cells lowest among those the object covers."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, 60000, seed=0)
    cells = np.floor(points[:, :2] / cell_m).astype(int)
    keys, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    top = np.full(len(keys), -np.inf)
    np.maximum.at(top, inverse.ravel(), points[:, 2])
    covered = counts >= 3
    floor = covered & (top <= top[covered].min() + 0.001)
    centre = (keys[floor].mean(axis=0) + 0.5) * cell_m
    return np.array([centre[0], centre[1], mesh.bounds[1][2] + 0.01])


def ball_stays_in(scene_xml: Path, body: str, drop_m: np.ndarray, radius_m: float = 0.0075) -> bool:
    """Drops a ball of `radius_m` (1.5 cm across, 10 g) from `drop_m` (grounded world frame) into `body` and
    simulates 2 s: True when it ends inside the body's bounding box below its rim, i.e. the cavity held it."""
    import mujoco

    spec = mujoco.MjSpec.from_file(str(scene_xml))
    ball = spec.worldbody.add_body(name="_probe_ball", pos=drop_m.tolist())
    ball.add_freejoint()
    ball.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius_m, 0, 0], mass=0.01, condim=3)
    model = spec.compile()
    data = mujoco.MjData(model)
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    ball_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "_probe_ball")
    mujoco.mj_forward(model, data)
    # The container's world bounding box from its geoms' AABBs at the end (it may be nudged by the ball).
    for _ in range(round(2.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == body_id]
    corners = []
    for g in geoms:
        centre = data.geom_xpos[g] + data.geom_xmat[g].reshape(3, 3) @ model.geom_aabb[g][:3]
        half = np.abs(data.geom_xmat[g].reshape(3, 3)) @ model.geom_aabb[g][3:]
        corners += [centre - half, centre + half]
    lo, hi = np.min(corners, axis=0), np.max(corners, axis=0)
    ball_pos = data.xpos[ball_id]
    return bool(np.all(ball_pos[:2] > lo[:2]) and np.all(ball_pos[:2] < hi[:2]) and ball_pos[2] < hi[2])


def score_scene(scene_dir: Path, truth_dir: Path, *, samples: int = 20000, seed: int = 0) -> SceneScore:
    """Scores a grounded family scene (`samples/make_scene_family.py`) against its truth.

    Marker scenes share the truth's world frame; known-extent scenes are put onto it by a rigid fit of the camera
    centres (never of the objects, which would hide their errors). Each true object is matched to at most one
    grounded body whose centre lies within half the object's largest extent (at least 3 cm), nearest pairs first;
    grounded bodies left over are extra bodies.
    """
    import trimesh
    from scipy.optimize import linear_sum_assignment

    family = json.loads((truth_dir / "family.json").read_text())
    true_records = {o["name"]: o for o in json.loads((truth_dir / "objects.json").read_text())["objects"]}
    truth = _true_meshes(truth_dir)
    grounded = _grounded_meshes(scene_dir)
    manifest = json.loads((scene_dir / "scene.json").read_text())
    if family["scale_by"] == "marker":
        truth_from_grounded, scale_ratio, alignment = np.eye(4), 1.0, "marker frame"
    else:
        truth_from_grounded, scale_ratio, left_out = _rigid_from_cameras(scene_dir, truth_dir)
        alignment = "rigid fit of camera centres" + (f" ({left_out} far-off camera(s) left out)" if left_out else "")
    for mesh in grounded.values():
        mesh.apply_transform(truth_from_grounded)
    true_names, names = list(truth), list(grounded)
    cost = np.full((len(true_names), len(names)), 1e3)
    for i, t in enumerate(true_names):
        gate = max(0.03, 0.5 * float(truth[t].extents.max()))
        for j, g in enumerate(names):
            d = float(np.linalg.norm(truth[t].bounds.mean(axis=0) - grounded[g].bounds.mean(axis=0)))
            if d <= gate:
                cost[i, j] = d
    match: dict[str, str] = {}
    if names:
        for i, j in zip(*linear_sum_assignment(cost), strict=True):
            if cost[i, j] < 1e3:
                match[true_names[i]] = names[j]
    rng = np.random.default_rng(seed)
    scores = []
    for t in true_names:
        record = true_records[t]
        common: dict[str, Any] = {
            "true_name": t,
            "object_class": record.get("class", "?"),
            "variant": record.get("variant", "?"),
            "open_container": bool(record.get("open_container", False)),
            "true_euler_number": record.get("euler_number"),
        }
        if t not in match:
            scores.append(ObjectScore(name=None, **common))
            continue
        g = match[t]
        mesh, true_mesh = grounded[g], truth[t]
        a, b = _samples_with_normals(mesh, samples, rng), _samples_with_normals(true_mesh, samples, rng)
        chamfer, normal_consistency = _surface_agreement(a, b)
        merged = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        merged.merge_vertices(merge_tex=True, merge_norm=True)
        keeps = None
        if common["open_container"]:
            drop_truth = _cavity_drop_point(true_mesh)
            drop_grounded = (np.linalg.inv(truth_from_grounded) @ np.append(drop_truth, 1.0))[:3]
            keeps = ball_stays_in(scene_dir / "scene.xml", g, drop_grounded)
        scores.append(
            ObjectScore(
                name=g,
                centre_error_m=float(np.linalg.norm(mesh.bounds.mean(axis=0) - true_mesh.bounds.mean(axis=0))),
                chamfer_m=chamfer,
                extent_error=float(np.max(np.abs(mesh.extents / true_mesh.extents - 1))),
                normal_consistency=normal_consistency,
                volume_ratio=float(abs(mesh.volume) / true_mesh.volume),
                euler_number=int(merged.euler_number),
                keeps_ball=keeps,
                mesh_quality=(manifest["objects"][g].get("mesh") or {}).get("quality"),
                **common,
            )
        )
    extra = tuple(sorted(set(names) - set(match.values())))
    return SceneScore(objects=tuple(scores), extra_bodies=extra, alignment=alignment, scale_ratio=scale_ratio)
