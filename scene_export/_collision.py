"""Collision geometry: a convex hull for (nearly) convex meshes, a CoACD decomposition for concave ones.

MuJoCo collides mesh geoms through their convex hulls, so a concave object (a bowl, a mug) needs several convex
pieces to keep its cavity. CoACD gives them; its defaults are tuned here for speed on a laptop CPU, and results are
cached on disk because a decomposition costs seconds while a scene is exported many times during calibration.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from image2sim_common.outdir import atomic_file
from scene_export._mesh import as_mesh_arrays, mesh_sha256, solid_trimesh
from scene_export.errors import DecompositionError, InvalidSceneSpecError

log = logging.getLogger(__name__)

_CACHE_FORMAT = 2  # bump when the cached content or its meaning changes (2: pieces clipped to the mesh's hull)


def default_cache_dir() -> Path:
    """`$IMAGE2SIM_CACHE/coacd` when that variable is set, else `~/.cache/image2sim/coacd`."""
    root = os.environ.get("IMAGE2SIM_CACHE")
    return Path(root) / "coacd" if root else Path.home() / ".cache" / "image2sim" / "coacd"


@dataclass(frozen=True, kw_only=True)
class CoacdOptions:
    """Keyword arguments of `coacd.run_coacd`, passed as `coacd.run_coacd(mesh, **asdict(options))`.

    The defaults are tuned for tabletop objects (a few centimetres to decimetres across, ~1-5k faces). Measured by
    `benchmarks/collision.py` on 2 CPU cores: the sample bowl's true mesh in 2.6 s and a generated 4000-face mug in
    10.6 s, each 16 hulls of <= 64 vertices that keep the cavity (a dropped ball stays inside). Reconstructed
    meshes are rougher and slower: the grounded sample bowl takes about 10 s (17 s at threshold 0.05). What changed
    and why:
    - `threshold` 0.05 -> 0.08: reconstructed bowls took 16-27 s at 0.05; at 0.08 the cavity is still kept and the
      hulls fill 1.65x the true bowl's volume instead of 1.49x (the mug: 1.57x either way).
    - `resolution` 2000 -> 1000: fewer surface samples for the concavity metric, evaluated for every candidate cut.
    - `mcts_nodes` 20 -> 15, `mcts_iterations` 150 -> 60, `mcts_max_depth` 3 -> 2: a shallower, narrower search for
      cutting planes; revolved and extruded shapes are cut well by the first two levels.
    - `preprocess_resolution` 50 -> 30: "auto" skips the voxel remeshing for manifold meshes (ours are checked
      watertight); a non-manifold mesh is remeshed on a 30^3 grid, ~5x fewer voxels (with it, the bowl takes +10 s).
    - `max_convex_hull` -1 -> 16 and `max_ch_vertex` 256 -> 64 with `decimate` on: MuJoCo's collision cost grows
      with hull count and size; CoACD merges the least costly pairs to meet the count.

    Attributes:
        threshold: concavity threshold (fraction of the bounding-box diagonal); lower = more, finer hulls.
        max_convex_hull: most hulls CoACD returns (-1 = no limit); capped by `CollisionOptions.max_hulls`.
        preprocess_mode: "auto" | "on" | "off" manifold preprocessing.
        preprocess_resolution: voxel resolution of the manifold preprocessing.
        resolution: surface samples for the concavity metric.
        mcts_nodes: children per Monte Carlo tree search node.
        mcts_iterations: Monte Carlo tree search iterations.
        mcts_max_depth: Monte Carlo tree search depth.
        pca: align cutting planes with principal axes.
        merge: merge hulls afterwards when that does not break `threshold` (and to meet `max_convex_hull`).
        decimate: limit each hull to `max_ch_vertex` vertices.
        max_ch_vertex: most vertices per hull when `decimate`; capped by `CollisionOptions.max_hull_vertices`.
        extrude: extrude neighbouring hulls along their shared faces.
        extrude_margin: extrusion distance when `extrude`.
        apx_mode: "ch" (convex hulls) or "box" approximation of parts.
        seed: random seed (fixed: the same mesh gives the same hulls).
        real_metric: use the real (not normalised) concavity metric.
    """

    threshold: float = 0.08
    max_convex_hull: int = 16
    preprocess_mode: str = "auto"
    preprocess_resolution: int = 30
    resolution: int = 1000
    mcts_nodes: int = 15
    mcts_iterations: int = 60
    mcts_max_depth: int = 2
    pca: bool = False
    merge: bool = True
    decimate: bool = True
    max_ch_vertex: int = 64
    extrude: bool = False
    extrude_margin: float = 0.01
    apx_mode: str = "ch"
    seed: int = 0
    real_metric: bool = False

    def __post_init__(self) -> None:
        if self.preprocess_mode not in ("auto", "on", "off"):
            raise InvalidSceneSpecError(f"{self.preprocess_mode=} but expected 'auto', 'on' or 'off'")
        if self.apx_mode not in ("ch", "box"):
            raise InvalidSceneSpecError(f"{self.apx_mode=} but expected 'ch' or 'box'")
        if not 0.0 < self.threshold < 1.0:
            raise InvalidSceneSpecError(f"{self.threshold=} but expected a concavity in (0, 1), e.g. 0.05")


@dataclass(frozen=True, kw_only=True)
class CollisionOptions:
    """How an object's collision geometry is made; doubles as the CLI section.

    Attributes:
        max_hulls: most convex hulls per object (MuJoCo tests every hull pair in contact, so fewer is faster).
        max_hull_vertices: most vertices per hull of a decomposed (concave) object.
        single_hull_vertices: most vertices of the one hull of a nearly convex object. It alone carries the
            object's whole outline, so it gets more: at 64, the grounded can of `samples/tabletop` kept 10 vertices
            of its bottom ring, bevelled in two places, and a flat rim landing on the table picks its contact points
            among them; calibrated on the clip's true motion its friction came out +93%. At 256 it came out -1%
            (`benchmarks/track.py --calibrate --true-motion`).
        convex_volume_ratio: a mesh with volume / convex-hull volume at or above this is treated as convex and
            gets its single convex hull without running CoACD (a box is 1.0, the sample bowl 0.2).
        coacd: CoACD settings for the concave ones.
        cache_dir: where decompositions are cached (None: no cache). Default `$IMAGE2SIM_CACHE/coacd`, else
            `~/.cache/image2sim/coacd`.
    """

    max_hulls: int = 16
    max_hull_vertices: int = 64
    single_hull_vertices: int = 256
    convex_volume_ratio: float = 0.9
    coacd: CoacdOptions = field(default_factory=CoacdOptions)
    cache_dir: Path | None = field(default_factory=default_cache_dir)

    def __post_init__(self) -> None:
        if self.max_hulls < 1:
            raise InvalidSceneSpecError(f"{self.max_hulls=} but expected at least 1")
        if min(self.max_hull_vertices, self.single_hull_vertices) < 4:
            raise InvalidSceneSpecError(
                f"{self.max_hull_vertices=}, {self.single_hull_vertices=} but a 3D hull needs at least 4 vertices"
            )
        if not 0.0 < self.convex_volume_ratio <= 1.0:
            raise InvalidSceneSpecError(f"{self.convex_volume_ratio=} but expected a ratio in (0, 1]")


@dataclass(frozen=True, kw_only=True)
class CollisionGeometry:
    """Convex pieces whose union approximates a solid, in the frame of the mesh they came from.

    Attributes:
        hulls: each (K, 3) float64 vertices of one convex hull, metres, K >= 4.
        method: "convex_hull" (one hull, CoACD skipped), "coacd" (decomposed now) or "cache" (decomposed earlier).
        seconds: wall time of `convex_decomposition` for this mesh.
        mesh_sha256: hash of the input vertex and face arrays (provenance, cache key).
    """

    hulls: tuple[np.ndarray, ...]
    method: str
    seconds: float
    mesh_sha256: str

    def __post_init__(self) -> None:
        if not self.hulls:
            raise InvalidSceneSpecError("CollisionGeometry has no hulls; build it with convex_decomposition()")
        for i, hull in enumerate(self.hulls):
            if hull.ndim != 2 or hull.shape[1] != 3 or len(hull) < 4 or not np.isfinite(hull).all():
                raise InvalidSceneSpecError(f"hull {i}: shape {hull.shape} but expected finite (K >= 4, 3) vertices")
        if self.method not in ("convex_hull", "coacd", "cache"):
            raise InvalidSceneSpecError(f"{self.method=} but expected 'convex_hull', 'coacd' or 'cache'")


def convex_decomposition(
    vertices_m: np.ndarray, faces: np.ndarray, options: CollisionOptions | None = None
) -> CollisionGeometry:
    """Convex pieces for a watertight mesh: its convex hull if nearly convex, else a (cached) CoACD decomposition.

    Args:
        vertices_m: (V, 3) float64 vertex positions, metres.
        faces: (F, 3) int vertex indices of a closed triangle mesh.
        options: decomposition settings; defaults to `CollisionOptions()`.

    Returns:
        At most `options.max_hulls` hulls of at most `options.max_hull_vertices` vertices each (a nearly convex
        mesh: one hull of at most `options.single_hull_vertices`), same frame as the input.

    Raises:
        InvalidMeshError: the mesh is empty, has NaN/inf, is not watertight or has zero volume.
        DecompositionError: CoACD is missing, fails, or returns nothing usable.
    """
    start = time.perf_counter()
    options = options or CollisionOptions()
    vertices, faces_arr = as_mesh_arrays(vertices_m, faces, what="mesh for collision geometry")
    mesh = solid_trimesh(vertices, faces_arr, what="mesh for collision geometry")
    sha = mesh_sha256(vertices, faces_arr)
    hull_volume = float(mesh.convex_hull.volume)
    if mesh.volume / hull_volume >= options.convex_volume_ratio:
        hulls = _finish_hulls([mesh.vertices], options, max_vertices=options.single_hull_vertices)
        return CollisionGeometry(
            hulls=hulls, method="convex_hull", seconds=time.perf_counter() - start, mesh_sha256=sha
        )

    cache_path = None
    if options.cache_dir is not None:
        cache_path = Path(options.cache_dir) / f"{_cache_key(sha, options)}.npz"
        cached = _load_cache(cache_path)
        if cached is not None:
            return CollisionGeometry(hulls=cached, method="cache", seconds=time.perf_counter() - start, mesh_sha256=sha)

    parts = _run_coacd(mesh.vertices, mesh.faces, options)
    # CoACD remeshes its input first, so its pieces can stick out of the mesh by up to a voxel (0.7 mm below the
    # flat base of an object seen here): a scene placed by its mesh then starts in the table and pops off it.
    # Every piece of the mesh lies inside the mesh's convex hull, so clip each to that.
    hull_planes = ConvexHull(mesh.vertices).equations
    parts = [clipped for clipped in (_clip_to_halfspaces(p, hull_planes) for p in parts) if clipped is not None]
    hulls = _finish_hulls(parts, options)
    if cache_path is not None:
        _save_cache(cache_path, hulls)
    return CollisionGeometry(hulls=hulls, method="coacd", seconds=time.perf_counter() - start, mesh_sha256=sha)


def _effective_coacd_kwargs(options: CollisionOptions) -> dict[str, object]:
    """`asdict(options.coacd)` with the hull count and size capped by the collision limits."""
    kwargs = asdict(options.coacd)
    count = kwargs["max_convex_hull"]
    kwargs["max_convex_hull"] = options.max_hulls if count < 1 else min(count, options.max_hulls)
    kwargs["max_ch_vertex"] = min(kwargs["max_ch_vertex"], options.max_hull_vertices)
    return kwargs


def _run_coacd(vertices: np.ndarray, faces: np.ndarray, options: CollisionOptions) -> list[np.ndarray]:
    try:
        import coacd
    except ImportError as exc:
        raise DecompositionError(
            f"coacd is needed to decompose concave meshes but is not installed ({exc}); `pip install coacd`"
        ) from exc
    coacd.set_log_level("error")
    kwargs = _effective_coacd_kwargs(options)
    try:
        parts = coacd.run_coacd(coacd.Mesh(vertices, faces.astype(np.int32)), **kwargs)
    except Exception as exc:
        raise DecompositionError(
            f"CoACD failed on a mesh with {len(vertices)} vertices, {len(faces)} faces ({type(exc).__name__}: "
            f"{exc}); try CoacdOptions(preprocess_mode='on') or a simplified mesh"
        ) from exc
    if not parts:
        raise DecompositionError(
            f"CoACD returned no hulls for a mesh with {len(vertices)} vertices; try CoacdOptions(preprocess_mode='on')"
        )
    return [np.asarray(part_vertices, dtype=np.float64) for part_vertices, _ in parts]


def _hull_vertices(points: np.ndarray) -> np.ndarray | None:
    """The vertices of the convex hull of `points`, or None when they span no volume (flat or too few)."""
    if len(points) < 4:
        return None
    try:
        hull = ConvexHull(points)
    except QhullError:
        return None
    if hull.volume <= 1e-15:
        return None
    return np.ascontiguousarray(points[hull.vertices], dtype=np.float64)


def _clip_to_halfspaces(points: np.ndarray, planes: np.ndarray) -> np.ndarray | None:
    """Vertices of conv(points) ∩ {x: planes[:, :3] @ x + planes[:, 3] <= 0}, or None when that has no volume.

    Args:
        points: (K, 3) points whose convex hull is clipped.
        planes: (P, 4) outward half-space equations (scipy's `ConvexHull.equations`).
    """
    hull_vertices = _hull_vertices(points)
    if hull_vertices is None:
        return None
    if np.all(hull_vertices @ planes[:, :3].T + planes[:, 3] <= 1e-12):
        return hull_vertices  # already inside: the common case
    halfspaces = np.concatenate([ConvexHull(hull_vertices).equations, planes])
    # An interior point: the centre of the largest ball inside every half-space (Chebyshev centre, a small LP).
    norms = np.linalg.norm(halfspaces[:, :3], axis=1, keepdims=True)
    result = linprog(
        c=[0.0, 0.0, 0.0, -1.0],
        A_ub=np.hstack([halfspaces[:, :3], norms]),
        b_ub=-halfspaces[:, 3],
        bounds=[(None, None)] * 3 + [(0.0, None)],
        method="highs",
    )
    if not result.success or result.x[3] <= 1e-7:  # empty or thinner than 0.2 micrometres
        return None
    try:
        clipped = HalfspaceIntersection(halfspaces, result.x[:3]).intersections
    except QhullError:
        return None
    return _hull_vertices(clipped)


def _farthest_point_subset(points: np.ndarray, count: int) -> np.ndarray:
    """`count` of `points`, each the farthest from those already chosen, starting from the farthest from the mean.

    On hull vertices this keeps the extreme points, so the reduced hull is an inner approximation that loses the
    least volume for a greedy choice; it is deterministic (no random seed).
    """
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    while len(chosen) < count:
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return points[np.sort(chosen)]


def _limit_vertices(hull: np.ndarray, max_vertices: int) -> np.ndarray:
    while len(hull) > max_vertices:
        reduced = _hull_vertices(_farthest_point_subset(hull, max_vertices))
        if reduced is None:  # cannot happen for a 3D hull's extreme points, but never loop forever
            return hull[:max_vertices]
        hull = reduced
    return hull


def _merge_cheapest(hulls: list[np.ndarray], max_hulls: int) -> list[np.ndarray]:
    """Merges the pair whose joint hull adds the least volume until at most `max_hulls` remain."""
    volumes = [ConvexHull(h).volume for h in hulls]

    def merge_cost(i: int, j: int) -> tuple[float, np.ndarray | None]:
        joint = _hull_vertices(np.concatenate([hulls[i], hulls[j]]))
        return (np.inf, None) if joint is None else (ConvexHull(joint).volume - volumes[i] - volumes[j], joint)

    costs = {(i, j): merge_cost(i, j) for i in range(len(hulls)) for j in range(i + 1, len(hulls))}
    alive = set(range(len(hulls)))
    while len(alive) > max_hulls:
        (i, j), (_, joint) = min(
            ((pair, value) for pair, value in costs.items() if pair[0] in alive and pair[1] in alive),
            key=lambda item: item[1][0],
        )
        assert joint is not None
        alive.discard(j)
        hulls[i], volumes[i] = joint, ConvexHull(joint).volume
        for k in alive - {i}:
            costs[(min(i, k), max(i, k))] = merge_cost(min(i, k), max(i, k))
    return [hulls[i] for i in sorted(alive)]


def single_hull(vertices_m: np.ndarray, options: CollisionOptions | None = None) -> CollisionGeometry:
    """The convex hull of the points alone, as collision geometry: the fallback for a mesh whose decomposition failed
    (coarser: a cavity is filled), so one object's failure does not lose the scene.

    Raises:
        DecompositionError: the points are flat (no hull with volume).
    """
    start = time.perf_counter()
    options = options or CollisionOptions()
    vertices = np.asarray(vertices_m, np.float64).reshape(-1, 3)
    hulls = _finish_hulls([vertices], options, max_vertices=options.single_hull_vertices)
    sha = hashlib.sha256(np.ascontiguousarray(vertices).tobytes()).hexdigest()
    return CollisionGeometry(hulls=hulls, method="convex_hull", seconds=time.perf_counter() - start, mesh_sha256=sha)


def _finish_hulls(
    parts: list[np.ndarray], options: CollisionOptions, *, max_vertices: int | None = None
) -> tuple[np.ndarray, ...]:
    """Hull vertices only, degenerate pieces dropped, count and vertex limits enforced (`max_vertices`, default
    `options.max_hull_vertices`)."""
    hulls = [h for h in (_hull_vertices(p) for p in parts) if h is not None]
    if not hulls:
        raise DecompositionError(
            "every convex piece of the decomposition is flat; the mesh may be a thin sheet: give it thickness"
        )
    if len(hulls) > options.max_hulls:
        hulls = _merge_cheapest(hulls, options.max_hulls)
    limit = options.max_hull_vertices if max_vertices is None else max_vertices
    return tuple(_limit_vertices(h, limit) for h in hulls)


def _cache_key(sha: str, options: CollisionOptions) -> str:
    try:
        from importlib.metadata import version

        coacd_version = version("coacd")
    except Exception:
        coacd_version = "unknown"
    payload = {
        "format": _CACHE_FORMAT,
        "mesh_sha256": sha,
        "coacd": _effective_coacd_kwargs(options),
        "coacd_version": coacd_version,
        "max_hulls": options.max_hulls,
        "max_hull_vertices": options.max_hull_vertices,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def _load_cache(path: Path) -> tuple[np.ndarray, ...] | None:
    """The cached hulls, or None when absent or unreadable (a corrupt entry is recomputed, not trusted)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            count = int(data["count"])
            hulls = tuple(np.asarray(data[f"hull_{i}"], dtype=np.float64) for i in range(count))
        if count < 1 or any(h.ndim != 2 or h.shape[1] != 3 or len(h) < 4 for h in hulls):
            raise ValueError("malformed hull arrays")
    except Exception as exc:
        log.warning("ignoring unreadable CoACD cache entry %s (%s); recomputing", path, exc)
        return None
    return hulls


def _save_cache(path: Path, hulls: tuple[np.ndarray, ...]) -> None:
    """Writes atomically (temporary file + rename), so readers never see half a file; failures only warn."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(path) as handle:
            arrays: dict[str, Any] = {"count": np.array(len(hulls))}
            arrays.update({f"hull_{i}": hull for i, hull in enumerate(hulls)})
            np.savez(handle, allow_pickle=False, **arrays)
    except OSError as exc:
        log.warning("could not write CoACD cache entry %s (%s); continuing without caching", path, exc)
