"""`ground`: film a tabletop, get a MuJoCo scene folder. Reconstruct -> dense -> objects -> meshes -> hulls -> MJCF."""

from __future__ import annotations

import json
import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from grounder.errors import GrounderError
from image2sim_common.progress import ProgressFn, no_progress
from reconstruction import (
    CylinderFit,
    CylinderSnapOptions,
    ObjectInstance,
    ObjectsOptions,
    ReconstructionResult,
    ReconstructOptions,
    ScaleSource,
    SceneObjects,
    TexturedMesh,
    TextureOptions,
    TextureView,
    bake_table_texture,
    bake_texture_report,
    find_objects,
    reconstruct,
    rescale_written,
    snap_to_upright_cylinder,
    staged_output_dir,
)
from reconstruction.errors import InputError
from scene_export import (
    CameraSpec,
    CollisionOptions,
    SceneObjectSpec,
    TableSpec,
    convex_decomposition,
    export_scene,
    render_view,
    settle_test,
    single_hull,
    write_preview,
)

if TYPE_CHECKING:
    from grounder.properties.prior import ObjectProperties
    from scene_export import CollisionGeometry

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class GroundOptions:
    """Every stage of film-a-scene; each field is one stage's options.

    Attributes:
        default_density_kg_m3: density given to every object when the property model is off.
        default_friction: (sliding, torsional, rolling) friction when the property model is off.
        property_model: predict each object's density, friction and solref with the learned property model
            (`grounder.properties.prior`) from video crops and shape, and store its embedding and spread in scene.json.
        settle_seconds: simulated time of the stability check written to scene.json.
        cylinder_snap: an object whose mesh is nearly an upright cylinder (a can) has its visual mesh snapped onto
            that cylinder after the property model has seen it (`reconstruction._primitives`): the scan's surface
            ripple biased model-based tracking's depth. The collision hulls stay the scanned mesh's; mass and
            inertia come from the snapped mesh. None: off.
    """

    reconstruct: ReconstructOptions = field(default_factory=ReconstructOptions)
    objects: ObjectsOptions = field(default_factory=ObjectsOptions)
    texture: TextureOptions = field(default_factory=TextureOptions)
    collision: CollisionOptions = field(default_factory=CollisionOptions)
    default_density_kg_m3: float = 600.0
    default_friction: tuple[float, float, float] = (0.6, 0.005, 0.0001)
    property_model: bool = True
    settle_seconds: float = 2.0
    cylinder_snap: CylinderSnapOptions | None = field(default_factory=CylinderSnapOptions)

    def __post_init__(self) -> None:  # checked when built, not after a minute of reconstruction
        density, friction = self.default_density_kg_m3, tuple(self.default_friction)
        if not (math.isfinite(density) and density > 0):
            raise GrounderError(f"default_density_kg_m3={density} but expected a finite density > 0 (kg/m^3)")
        if len(friction) != 3 or not all(math.isfinite(f) and f >= 0 for f in friction):
            raise GrounderError(f"default_friction={friction} but expected (sliding, torsional, rolling), finite >= 0")
        if not (math.isfinite(self.settle_seconds) and self.settle_seconds >= 0):
            raise GrounderError(f"settle_seconds={self.settle_seconds} but expected a finite time >= 0 (s)")


@dataclass(frozen=True, kw_only=True)
class GroundResult:
    """What `ground` wrote."""

    out_dir: Path
    scene_xml: Path
    object_names: tuple[str, ...]
    settle: dict[str, tuple[float, float]]  # name -> (displacement_m, rotation_deg) after settle_seconds
    scale_source: str
    warnings: tuple[str, ...]
    stage_seconds: dict[str, float]


def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise GrounderError(f"{path} could not be read back; check the disk and re-run")
    return np.asarray(image)


RESEGMENT_SCALE_CHANGE = 0.1  # a known-extent refinement beyond +-10% segments and meshes again
DOUBTFUL_EXTENT_STEP = 0.1  # a known-extent refinement beyond +-10% needs a mesh it can trust (`_extent_step`)


def _world_meshes(scene: SceneObjects) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each object's (vertices, faces) in the world frame (object frames are axes-parallel: a translation)."""
    return [(o.mesh.vertices_m + o.world_from_object[:3, 3], o.mesh.faces) for o in scene.objects]


def _bake_table(scene: SceneObjects, views: list[TextureView], warnings: list[str]) -> np.ndarray | None:
    """The table top's texture as filmed, objects masked out as occluders; None (plain colour) if it fails, with
    a warning: a table without its picture must not cost the scene."""
    try:
        return bake_table_texture(views, scene.table_half_extents, _world_meshes(scene))
    except Exception as exc:
        warnings.append(f"table: texture not baked ({type(exc).__name__}: {exc}); the top is a plain colour")
        return None


def _extent_factor(scene: SceneObjects, known_extent_m: float) -> tuple[float, str]:
    """The scale factor that gives the largest object its known longest extent. "Largest" is the object with the
    longest extent, as `--known-extent` says and as the sparse estimate chose it (`world_from_extent`): by volume,
    a bowl outranks a wider plate, and the plate's length given to the bowl scaled a whole scene by 1.18.

    An object meshed from its silhouettes, or as the convex hull of its points (mesh quality "fallback"), counts
    by its height only: such a hull may join two objects side by side (tuning seed 5: a plate and a mug as one
    22 cm wide hull took the bottle's 22.4 cm and the scene came out x 1.31), but joining does not make it taller;
    and a plain bottle only the silhouettes found is still the longest object (tuning seed 8: its 21 cm given to a
    10 cm can scaled the scene x 2.06)."""

    def length(obj: ObjectInstance) -> float:
        height = float(np.ptp(obj.mesh.vertices_m[:, 2]))
        if obj.mesh_quality in ("silhouette", "fallback"):
            return height  # a hull (of silhouettes, or of fused points) may join objects side by side
        if obj.at_region_edge:
            return height  # the region's sides are upright: they cut what stands on the table short across, not up
        # A box-like footprint (filling 90% of its smallest rectangle) is measured along its own sides, not the
        # world axes: a box turned 45 deg is a diagonal wider on the axes (tuning seed 15: a 10.8 cm carton measured
        # 12.8 cm, and the scene came out x 0.84). A round one has no sides to turn: the world axes, as before.
        footprint = np.asarray(obj.mesh.vertices_m[:, :2], np.float32)
        (_, _), (side_a, side_b), _ = cv2.minAreaRect(footprint)
        filled = float(cv2.contourArea(cv2.convexHull(footprint))) / max(float(side_a * side_b), 1e-12)
        if filled >= 0.9:
            return max(height, float(side_a), float(side_b))
        return float(np.ptp(obj.mesh.vertices_m, axis=0).max())

    largest = max(scene.objects, key=length)
    return known_extent_m / length(largest), largest.name


def _length_on_mesh(obj: ObjectInstance) -> float:
    """The longest extent a mesh could give its object: along any axis, footprint included."""
    return float(np.ptp(obj.mesh.vertices_m, axis=0).max())


def _extent_step(
    scene: SceneObjects, known_extent_m: float, prior: float = 1.0, trust_any: bool = False
) -> tuple[float, str, str | None]:
    """The known extent's correction of the current scale (`_extent_factor`), its object, and why it was declined.

    `scene` is at `prior` x the sparse points' scale (a second segmentation's). A correction that leaves the scale
    more than `DOUBTFUL_EXTENT_STEP` off the sparse estimate is taken only from a mesh that can be measured: not the
    convex hull of fused points that enclosed no solid (mesh quality "fallback"), and with no doubtful mesh (such a
    hull, a visual hull, or a mesh cut by a side of the fused region) that might be the longer object (any extent of
    it, footprint included, longer than the chosen length; a cut mesh's extent is what is left of it, a lower bound;
    held-out 1081: two bowls only their silhouettes found, counted by their 5 cm height, let an 8.9 cm L-block take
    their 17.6 cm and scale the scene x 1.97 where the sparse points had it within 14%). Otherwise the
    step is declined (factor 1) and the reason returned. `trust_any`: there is no sparse estimate (a provisional
    scale), whatever the meshes say is taken.

    A visual hull ("silhouette") and a mesh cut by the region's side count by their height, as in `_extent_factor`:
    tuning seed 53's plain bottle, a silhouette hull, corrected a sparse estimate 1.49 x too large to 0.97 (a thin
    can's fallback hull beside it was 5% shorter); held-out 1067's bottle, cut across by the region's side, corrected
    x 1.29 a sparse estimate that two bowls merged into one cluster had made x 0.79 (6 of 6 objects found, was 1).
    Declined: held-out 1031 (a low-texture cup measured short took the length of a handled mug meshed as a fallback
    hull: x 1.41) and 1033 (a 23 cm phantom sheet, a fallback hull: x 0.64); the sparse estimate was within 8% in
    both. (Tuning seed 50's bottle, once declined here as cut by the side, x 1.36, lacks its neck in the sparse points
    and in the fused surface alike: x 1.43 either way on the AVX-512 machine.)"""
    factor, name = _extent_factor(scene, known_extent_m)
    if trust_any or abs(np.log(prior * factor)) <= np.log(1 + DOUBTFUL_EXTENT_STEP):
        return factor, name, None

    def doubt(obj: ObjectInstance) -> str | None:
        if obj.mesh_quality == "fallback":
            return "the convex hull of its points"
        if obj.mesh_quality == "silhouette":
            return "a visual hull"  # its footprint is no measure, but may be a longer object's
        return "cut by the region's side" if obj.at_region_edge else None

    chosen = next(o for o in scene.objects if o.name == name)
    if chosen.mesh_quality == "fallback":  # a cut mesh counts by its height, which the region's sides leave whole
        return 1.0, name, f"its longest object {name} is the convex hull of its points"
    for other in scene.objects:
        why = doubt(other)
        if other.name != name and why is not None and _length_on_mesh(other) > known_extent_m / factor:
            return 1.0, name, f"{other.name} ({why}) may be longer than {name}"
    return factor, name, None


@dataclass(frozen=True, kw_only=True)
class _ExtentRefinement:
    """What the known extent did to the scale (`_refine_known_extent`)."""

    scene: SceneObjects  # the segmentation to rescale: the first, or the second (made at the first pass's scale)
    step: float  # rescales `scene` to the final metres
    factor: float  # the final scale over the sparse points' (or the provisional) scale
    note: str  # for the reconstruction record
    warning: str | None  # for the manifest


def _refine_known_extent(
    scene: SceneObjects,
    known_extent_m: float,
    provisional: bool,
    resegment: Callable[[float], SceneObjects],
) -> _ExtentRefinement:
    """The known extent measured on the meshes (`_extent_step`). A correction beyond +-`RESEGMENT_SCALE_CHANGE`
    segments again at the corrected scale (`resegment(factor)`, which returns the new segmentation) and measures
    there; a second measure that is declined returns the scale to the sparse estimate, as a first would have.
    `provisional`: no sparse estimate (no point stood on any object), the meshes' measure is taken whatever it is."""
    factor, largest, declined = _extent_step(scene, known_extent_m, trust_any=provisional)
    step, second_pass = factor, ""
    if abs(np.log(factor)) > np.log(1 + RESEGMENT_SCALE_CHANGE):
        # Segmentation and meshing work in metres (voxels, gaps, margins): at a scale this far off they merged or
        # fattened the objects. Segment and mesh again in the corrected metres, then refine.
        scene = resegment(factor)
        step, second_largest, declined = _extent_step(scene, known_extent_m, prior=factor, trust_any=provisional)
        if declined is None:
            largest, second_pass = second_largest, f" (x {step:.4f} on the second segmentation)"
        else:
            step = 1.0 / factor  # back to the sparse estimate
        factor *= step
    if declined is not None:
        return _ExtentRefinement(
            scene=scene,
            step=step,
            factor=factor,
            note=f"known extent: the meshes' correction was declined ({declined}); the sparse points' scale stands",
            warning=f"scale: --known-extent was measured on the sparse points only ({declined}), coarser than on a "
            "mesh; a marker (--aruco-size) scales a scene exactly",
        )
    warning = None
    if provisional:
        warning = (
            f"scale: no sparse point stood on any object, so --known-extent was measured on the mesh of {largest} "
            "alone; check its size in the preview, or film with a marker (--aruco-size)"
        )
    note = f"known extent refined on the segmented mesh of {largest}: scale x {factor:.4f}{second_pass}"
    return _ExtentRefinement(scene=scene, step=step, factor=factor, note=note, warning=warning)


def _rescale(
    scene: SceneObjects, result: ReconstructionResult, factor: float, note: str
) -> tuple[SceneObjects, ReconstructionResult]:
    """Scales the whole world (objects, cameras, points) about its origin by `factor`, and rewrites the
    reconstruction folder in the same metres (`reconstruction.rescale_written`)."""
    objects = []
    for obj in scene.objects:
        pose = obj.world_from_object.copy()
        pose[:3, 3] *= factor
        objects.append(
            replace(obj, mesh=replace(obj.mesh, vertices_m=obj.mesh.vertices_m * factor), world_from_object=pose)
        )
    half = (scene.table_half_extents[0] * factor, scene.table_half_extents[1] * factor)
    return replace(scene, objects=tuple(objects), table_half_extents=half), rescale_written(result, factor, note)


def ground(
    source: Path,
    out_dir: Path,
    options: GroundOptions | None = None,
    *,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
) -> GroundResult:
    """A MuJoCo scene folder from a video of a tabletop.

    Writes atomically to `out_dir`: `scene.xml`, `assets/`, `scene.json`, `preview.png` (an input frame beside
    MuJoCo's render from the same pose) and `reconstruction/` (cameras, as `image2sim reconstruct` writes them).

    Args:
        source: video file or image folder.
        out_dir: output folder; must be new or empty unless `overwrite`.
        options: settings of every stage.
        overwrite: replace a non-empty `out_dir` once the new scene is complete.
        progress: called as progress(stage, done, total).

    Raises:
        GrounderError, ReconstructionError, SceneExportError: bad input or nothing usable, with what to do.
    """
    options = options or GroundOptions()
    report = progress or no_progress
    warm_up: list[threading.Thread] = []
    stop_warm_up = threading.Event()
    try:
        return _ground_staged(source, out_dir, options, overwrite, report, warm_up, stop_warm_up)
    finally:
        # Never return or raise with the warm-up thread still in native code (an import, MuJoCo): a thread torn
        # down at interpreter exit while in C++ crashed the process after its last line (SIGSEGV, exit 139).
        stop_warm_up.set()
        for thread in warm_up:
            thread.join()


def _ground_staged(
    source: Path,
    out_dir: Path,
    options: GroundOptions,
    overwrite: bool,
    report: ProgressFn,
    warm_up: list[threading.Thread],
    stop_warm_up: threading.Event,
) -> GroundResult:
    """`ground`'s work; `warm_up` collects the warm-up thread, which stops at its next step once `stop_warm_up`."""
    seconds: dict[str, float] = {}
    # the same time by the steps a user would name (frames ... mapping, world frame, dense, segment, mesh, ...)
    detail: dict[str, float] = {}
    warnings: list[str] = []
    with staged_output_dir(Path(out_dir), overwrite=overwrite, inputs=(source,), error=InputError) as stage:
        tick = time.perf_counter()
        rec = reconstruct(
            source,
            stage / "reconstruction",
            replace(options.reconstruct, extent_on_meshes=True),  # a plain object's known extent: on its mesh
            progress=report,
            on_mapping=lambda: warm_up.append(_start_warm_up(options, stop_warm_up)),
        )
        seconds["reconstruct"] = time.perf_counter() - tick
        detail.update(rec.stage_seconds)
        rec = replace(rec, out_dir=stage / "reconstruction")
        if rec.world.scale_source == ScaleSource.UNKNOWN:
            warnings.append("scale unknown: pass --aruco-size or --known-extent for a metric scene")

        tick = time.perf_counter()
        scene = find_objects(rec, options.objects, progress=report, seconds=detail)
        seconds["dense_segment_mesh"] = time.perf_counter() - tick
        scale_note = None
        if rec.world.scale_source == ScaleSource.KNOWN_EXTENT and options.reconstruct.known_extent_m:
            reconstruction = rec

            def resegment(factor: float) -> SceneObjects:
                nonlocal reconstruction
                note = f"known extent on a first segmentation: scale x {factor:.4f}"
                _, reconstruction = _rescale(scene, reconstruction, factor, note)
                return find_objects(reconstruction, options.objects, progress=report, seconds=detail)

            refined = _refine_known_extent(
                scene, options.reconstruct.known_extent_m, rec.world.scale_provisional, resegment
            )
            scale_note = refined.note
            if refined.warning is not None:
                warnings.append(refined.warning)
            scene, rec = _rescale(refined.scene, reconstruction, refined.step, refined.note)
            rec = replace(rec, world=replace(rec.world, scale_provisional=False))  # measured now
        for obj in scene.objects:
            warnings.extend(f"{obj.name}: {w}" for w in obj.warnings)

        # CoACD runs in C++ without holding the GIL and keeps ~1.4 of 2 cores busy: the meshes are decomposed in the
        # background while textures are baked and properties predicted.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="coacd") as pool:
            hull_jobs = {
                o.name: pool.submit(convex_decomposition, o.mesh.vertices_m, o.mesh.faces, options.collision)
                for o in scene.objects
            }
            try:
                tick = time.perf_counter()
                views = [
                    TextureView(
                        image_bgr=_read_image(rec.out_dir / "images" / f.image_name),
                        world_from_cam=f.world_from_cam,
                        intrinsics=rec.intrinsics,
                    )
                    for f in rec.frames
                ]
                textured, coverage = _bake_textures(scene, views, options, report, warnings)
                table_texture = _bake_table(scene, views, warnings)
                seconds["texture"] = time.perf_counter() - tick

                tick = time.perf_counter()
                for thread in warm_up:
                    thread.join()
                properties = _predict_properties(textured, views, report, warnings) if options.property_model else {}
                seconds["properties"] = time.perf_counter() - tick
                textured, cylinders = _snap_cylinders(textured, options.cylinder_snap)

                tick = time.perf_counter()
                specs = _object_specs(textured, hull_jobs, properties, options, report, warnings)
                seconds["collision"] = time.perf_counter() - tick  # what is left of the decomposition by then
            finally:
                for job in hull_jobs.values():
                    job.cancel()  # after an error: the decompositions not started yet

        tick = time.perf_counter()
        report("writing MJCF", 0, 1)
        preview_frame = rec.frames[0]
        camera = CameraSpec.from_intrinsics("video", preview_frame.world_from_cam, rec.intrinsics)
        table = TableSpec(half_extents_m=scene.table_half_extents, texture_rgb=table_texture)
        provenance = _provenance(rec, scene, textured, coverage, scale_note, options, bool(properties), cylinders)
        exported = export_scene(specs, table, [camera], stage / "export", manifest_extra=provenance)
        for child in exported.out_dir.iterdir():
            shutil.move(str(child), stage / child.name)
        exported.out_dir.rmdir()
        scene_xml = stage / "scene.xml"
        frame_bgr = _read_image(rec.out_dir / "images" / preview_frame.image_name)
        write_preview(stage / "preview.png", frame_bgr, render_view(scene_xml, camera))
        settle = settle_test(scene_xml, seconds=options.settle_seconds)
        manifest_path = stage / "scene.json"
        manifest = json.loads(manifest_path.read_text())
        manifest["settle_test"] = {
            "seconds": options.settle_seconds,
            "objects": {
                n: {"displacement_m": m.displacement_m, "rotation_deg": m.rotation_deg} for n, m in settle.items()
            },
        }
        for input_name, physical in properties.items():
            manifest["objects"][exported.body_names[input_name]]["properties"] = physical.to_json()
        for obj in textured:  # "fallback": meshing failed and the object is the hull of its points (`find_objects`)
            manifest["objects"][exported.body_names[obj.name]]["mesh"] = {
                "quality": obj.mesh_quality,
                "reason": obj.mesh_reason,
            }
        report("object markers", 0, 1)
        manifest["object_markers"] = _scan_object_markers(views, manifest["objects"], options, warnings)
        manifest["warnings"] = warnings
        manifest_path.write_text(json.dumps(manifest, indent=1) + "\n")
        seconds["export"] = time.perf_counter() - tick
        manifest["stage_seconds"] = {k: round(v, 2) for k, v in seconds.items()}
        detail.update((k, seconds[k]) for k in ("texture", "properties", "collision", "export") if k in seconds)
        manifest["stage_seconds_detail"] = {k: round(v, 2) for k, v in detail.items()}
        manifest_path.write_text(json.dumps(manifest, indent=1) + "\n")
    for warning in warnings:
        log.warning(warning)
    if not textured:
        raise GrounderError("no object found")  # unreachable: find_objects raises first
    return GroundResult(
        out_dir=Path(out_dir),
        scene_xml=Path(out_dir) / "scene.xml",
        object_names=tuple(o.name for o in textured),
        settle={n: (m.displacement_m, m.rotation_deg) for n, m in settle.items()},
        scale_source=str(rec.world.scale_source),
        warnings=tuple(warnings),
        stage_seconds=seconds,
    )


def _start_warm_up(options: GroundOptions, stop: threading.Event) -> threading.Thread:
    """Loads, in a background thread, what the later stages need and the reconstruction does not: open3d, torch
    with the property model, and the bounce table that turns predicted restitutions into `solref`
    (`grounder.sim.restitution`), about 10 s of one core's work. Started when mapping starts (`reconstruct`'s
    `on_mapping`), which runs on one thread for a reproducible model and leaves the other cores idle; started
    earlier it slowed the reconstruction's multi-threaded stages by as much as it saved. The results are the same,
    the caches being the ones the stages read. A failure is left to the stage that needs the thing, which then meets
    the error itself and reports it. Returns the thread; once `stop` is set it ends after the step it is in (the
    caller joins it: a thread still in C++ at interpreter exit crashes the process).
    """

    def work() -> None:
        try:
            import open3d  # noqa: F401  (dense fusion and meshing)

            if options.property_model and not stop.is_set():
                from grounder.properties.prior import load_property_model
                from grounder.sim.restitution import contact_solref

                load_property_model()
                if not stop.is_set():
                    contact_solref(0.5, 0.02)  # what `_natural` asks for: the default export settings' table
        except Exception as exc:  # reported where it matters, by the stage that needs it
            log.debug("warm-up stopped: %s", exc)

    thread = threading.Thread(target=work, name="ground-warm-up")
    thread.start()
    return thread


def _scan_object_markers(
    views: list[TextureView], objects: dict[str, dict], options: GroundOptions, warnings: list[str]
) -> list[dict[str, object]]:
    """ArUco markers stuck on objects, measured in the scan (`grounder.grounding.scan_markers`), as `scene.json` stores
    them."""
    from grounder.grounding.scan_markers import find_scan_markers
    from image2sim_common.rotations import pose_matrix

    bodies = {
        name: (pose_matrix(record["pos_m"], record["quat_wxyz"]), np.asarray(record["extents_m"], float))
        for name, record in objects.items()
    }
    markers, notes = find_scan_markers(
        views, bodies, options.reconstruct.aruco_dictionary, options.reconstruct.aruco_id
    )
    warnings.extend(notes)
    return [m.to_json() for m in markers]


def _bake_textures(
    scene: SceneObjects, views: list[TextureView], options: GroundOptions, report: ProgressFn, warnings: list[str]
) -> tuple[list[ObjectInstance], dict[str, float]]:
    """Each object's mesh with a colour texture baked from the views (the other objects occlude), and the share of
    its surface the views covered."""
    textured: list[ObjectInstance] = []
    coverage: dict[str, float] = {}
    world_meshes = _world_meshes(scene)
    for i, obj in enumerate(scene.objects):
        report("baking textures", i, len(scene.objects))
        others = [m for j, m in enumerate(world_meshes) if j != i]
        try:
            bake = bake_texture_report(world_meshes[i][0], obj.mesh.faces, views, options.texture, occluders=others)
        except Exception as exc:  # one object's failure must not lose the scene: it stays untextured
            reason = f"texturing failed ({type(exc).__name__}: {' '.join(str(exc).split())}); left untextured"
            textured.append(_fallen_back(obj, reason))
            warnings.append(f"{obj.name}: {reason}")
            coverage[obj.name] = 0.0
            continue
        mesh = bake.mesh
        textured.append(replace(obj, mesh=replace(mesh, vertices_m=mesh.vertices_m - obj.world_from_object[:3, 3])))
        coverage[obj.name] = bake.coverage
    return textured, coverage


def _fallen_back(obj: ObjectInstance, reason: str) -> ObjectInstance:
    """`obj` marked as made another way (`mesh.quality` "fallback" in scene.json), with `reason` among its
    warnings (which `ground` logs, naming the object)."""
    reasons = "; ".join(r for r in (obj.mesh_reason, reason) if r)
    return replace(obj, mesh_quality="fallback", mesh_reason=reasons, warnings=(*obj.warnings, reason))


def _object_specs(
    textured: list[ObjectInstance],
    hull_jobs: dict[str, Future[CollisionGeometry]],
    properties: dict[str, ObjectProperties],
    options: GroundOptions,
    report: ProgressFn,
    warnings: list[str],
) -> list[SceneObjectSpec]:
    """The export spec of each object: its textured mesh, its collision hulls (waited for) and its physics. An
    object whose decomposition failed gets one convex hull, and is marked so in `textured` and `warnings`."""
    specs = []
    for i, obj in enumerate(textured):
        report("collision hulls", i, len(textured))
        physical = properties.get(obj.name)
        try:
            collision = hull_jobs[obj.name].result()
        except Exception as exc:  # one object's failure must not lose the scene: one convex hull instead
            reason = f"convex decomposition failed ({type(exc).__name__}: {' '.join(str(exc).split())}); one hull"
            collision = single_hull(obj.mesh.vertices_m, options.collision)
            textured[i] = obj = _fallen_back(obj, reason)
            warnings.append(f"{obj.name}: {reason}")
        specs.append(
            SceneObjectSpec(
                name=obj.name,
                visual=obj.mesh,
                collision=collision,
                world_from_object=obj.world_from_object,
                density_kg_m3=options.default_density_kg_m3 if physical is None else physical.density_kg_m3,
                friction=options.default_friction if physical is None else physical.friction,
                solref=SceneObjectSpec.solref if physical is None else physical.solref,
            )
        )
    return specs


def _snap_cylinders(
    objects: list[ObjectInstance], options: CylinderSnapOptions | None
) -> tuple[list[ObjectInstance], dict[str, CylinderFit]]:
    """Each object whose mesh is nearly an upright cylinder with its mesh snapped onto it, and the fits by name."""
    if options is None:
        return objects, {}
    snapped, fits = [], {}
    for obj in objects:
        mesh, fit = snap_to_upright_cylinder(obj.mesh, options)
        snapped.append(obj if fit is None else replace(obj, mesh=mesh))
        if fit is not None:
            fits[obj.name] = fit
    return snapped, fits


def _provenance(
    rec: ReconstructionResult,
    scene: SceneObjects,
    objects: list[ObjectInstance],
    coverage: dict[str, float],
    scale_note: str | None,
    options: GroundOptions,
    learned_properties: bool = False,
    cylinders: dict[str, CylinderFit] | None = None,
) -> dict[str, object]:
    import importlib.metadata as md

    fits = cylinders or {}

    def version(pkg: str) -> str:
        try:
            return md.version(pkg)
        except md.PackageNotFoundError:
            return "unknown"

    return {
        "provenance": {
            "source": str(rec.source),
            "scale_source": str(rec.world.scale_source),
            "scale_note": scale_note,
            "frames_in_source": rec.num_source_frames,
            "frames_used": [f.frame_index for f in rec.frames],
            "registration_rate": rec.registration_rate,
            "mean_reprojection_error_px": rec.mean_reprojection_error_px,
            "dense": {"stereo_pairs": scene.num_stereo_pairs, "voxel_size": scene.voxel_size},
            "assumptions": [
                "unseen undersides are closed flat where objects meet the table (closed_bottom)",
                (
                    "density, friction and solref are the learned property model's prior means (see each "
                    "object's properties), not measured"
                )
                if learned_properties
                else f"density {options.default_density_kg_m3} kg/m^3 and friction {list(options.default_friction)} "
                "are defaults, not measured",
            ],
            "versions": {p: version(p) for p in ("image2sim", "pycolmap", "open3d", "coacd", "mujoco", "trimesh")},
        },
        "objects_extra": {
            o.name: {
                "closed_bottom": o.closed_bottom,
                "num_views": o.num_views,
                "texture_coverage": coverage.get(o.name),
                "visual_snapped_to_cylinder": fits[o.name].as_json() if o.name in fits else None,
                "warnings": list(o.warnings),
            }
            for o in objects
        },
    }


def _predict_properties(
    objects: list[ObjectInstance], views: list[TextureView], report: ProgressFn, warnings: list[str]
) -> dict[str, ObjectProperties]:
    """The learned property model's prediction for every object, from crops of the frames and the mesh shape.

    When the model cannot run (no weights, an object never fully in view) the defaults are kept with a warning.
    """
    from grounder.properties.model_files import PropertyModelError
    from grounder.properties.prior import CropView, assign_properties

    report("physical properties", 0, 1)
    crop_views = [
        CropView(image_bgr=v.image_bgr, world_from_cam=v.world_from_cam, camera_matrix=v.intrinsics.matrix)
        for v in views
    ]
    meshes = [(o.name, mesh_in_world(o).vertices_m, o.mesh.faces) for o in objects]
    try:
        result = assign_properties(meshes, crop_views)
    except PropertyModelError as exc:
        warnings.append(f"property model not used, default density and friction kept: {exc}")
        return {}
    report("physical properties", 1, 1)
    return result


def mesh_in_world(obj: ObjectInstance) -> TexturedMesh:
    """The object's mesh moved to the world frame."""
    return replace(obj.mesh, vertices_m=obj.mesh.vertices_m + obj.world_from_object[:3, 3])
