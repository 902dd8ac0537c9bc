"""Objects on the table, step two: one watertight mesh per object instance (`reconstruction._segment` finds them).

Meshing: the fused surface is kept where the depth maps measured it (a TSDF also closes off space no camera saw),
the object's surface is voxelised, its footprint on the table is capped (the unseen underside is
assumed flat where the object meets the table: recorded as `closed_bottom`), enclosed space is filled, the unseen
space under each column is filled to the table where the object stands on it and along a slope under an overhang,
space the depth maps see through is carved away (the visible part of an undercut, stereo bumps), and marching
cubes gives a watertight surface, corrected by half a voxel inwards, smoothed and decimated.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from scipy import ndimage

from reconstruction._dense import DenseResult, DepthMap
from reconstruction._segment import ObjectSegment, SegmentationError, footprint_image

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class MeshOptions:
    """Watertight meshing settings.

    Attributes:
        face_budget: decimate each object's mesh to at most this many faces.
        cap_height_voxels: points lower than this outline the footprint closed on the table.
        skirt_height_voxels: layers above the table cleared of protrusions thinner than 5 voxels.
        grid_refinement: inside/outside grid cells per fusion voxel.
        smooth_iterations: Taubin smoothing steps after marching cubes.
        carve_min_views: a voxel of the filled solid is removed when at least this many depth maps see a surface
            behind it (0: no carving).
        carve_margin_voxels: how far behind the voxel (fusion voxels) that surface must be.
        carve_edge_px: depth pixels this close to a depth jump or a hole are not trusted for carving (stereo
            fattens silhouettes).
        carve_jump_fraction: a depth jump is a change over 3 x 3 pixels larger than this fraction of the depth.
        underside: how the unseen space under an overhang (a bowl's flared wall) is closed: "taper" runs a straight
            slope from where the object sits on the table out to the lowest wall the depth maps saw (see
            `_tapered_bottom`); "fill" fills every column down to the table.
        seen_wall_voxels: a column's lowest solid cell counts as a seen wall when a surface point of the object
            lies this close (fusion voxels).
        support_min_views, support_tolerance_voxels: the fused surface counts only where at least this many depth
            maps measured a surface within this distance along their rays (fusion voxels); 0 views: all of it.
            Fewer than 2 leaves the TSDF's curtains under overhangs; 3 already drops real surface that only a few
            oblique views saw (measured on three reconstructions of the tabletop sample: bowl Chamfer -0.15 mm at
            2 views and 1.5 voxels, the box unchanged; at 5 views the bowl falls apart).
        outline_gap_voxels: gaps up to about twice this wide (fusion voxels) in the ring of an object's
            cross-section are closed before its inside counts as inside the outline that trims the layers next to
            the table (a torn bowl wall kept its floor at 3; tuning seed 42).
        min_tip_angle_deg: an object standing on the table is meshed again with a foot under its seen surface
            (`_foot_columns`) when its mesh tips over past its support's edge at a smaller tilt than this
            (`tip_angle_deg`): the object was filmed at rest.
    """

    face_budget: int = 4000
    cap_height_voxels: float = 2.0
    skirt_height_voxels: float = 6.0
    grid_refinement: int = 2
    smooth_iterations: int = 10
    carve_min_views: int = 3
    carve_margin_voxels: float = 3.0
    carve_edge_px: int = 1
    carve_jump_fraction: float = 0.03
    underside: Literal["taper", "fill"] = "taper"
    seen_wall_voxels: float = 1.5
    support_min_views: int = 2
    support_tolerance_voxels: float = 1.5
    outline_gap_voxels: float = 3.0
    min_tip_angle_deg: float = 5.0


@dataclass(frozen=True, kw_only=True)
class WatertightMesh:
    vertices_world: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    closed_bottom: bool
    warnings: tuple[str, ...] = ()


def standing_sheet(points_world: np.ndarray, max_aspect: float, min_height_ratio: float = 2.0) -> bool:
    """Whether points form a sheet standing on edge: the smallest rectangle around their footprint on the table has
    a short side under `max_aspect` x its long side, and they stand over `min_height_ratio` x that short side tall
    (a pen or a box lying flat is no sheet).

    Args:
        points_world: (N, 3) float, metres, world frame (table top z = 0); non-finite rows are ignored.
        max_aspect: short side / long side below which a footprint is sheet-like.
        min_height_ratio: height / short side above which the points stand up.
    """
    import cv2

    points = points_world[np.isfinite(points_world).all(axis=1)]
    if len(points) < 3:
        return False
    (_, _), (side_a, side_b), _ = cv2.minAreaRect(np.asarray(points[:, :2], np.float32))
    short, long = min(side_a, side_b), max(side_a, side_b)
    return bool(short < max_aspect * long and np.ptp(points[:, 2]) > min_height_ratio * short)


def fallback_mesh(segment: ObjectSegment) -> WatertightMesh:
    """A closed surface for an object that `mesh_object` could not mesh: the convex hull of its fused points and of
    their footprint on the table (z = 0), so that it stands where the object stands. Coarser than the real mesh (a
    cavity is filled, a handle bridged) but never lost: one object's failure must not lose the scene.

    Raises:
        SegmentationError: the object has too few points, or they are flat, for any closed surface.
    """
    import trimesh
    from scipy.spatial import ConvexHull

    points = np.asarray(segment.points_world, float)
    points = points[np.isfinite(points).all(axis=1)]
    footprint = points.copy()
    footprint[:, 2] = 0.0
    every = np.vstack([points, footprint])
    # Qhull's triangulated facets, oriented by its outward normals, close by construction; trimesh's `convex_hull`
    # merged near-coincident hull vertices of a few thousand points on a can's wall and left the hull open (a test's
    # can of 6000 points), which lost the object.
    hull = None
    if len(points) >= 4:
        try:
            qhull = ConvexHull(every)
        except Exception:  # Qhull's errors for flat or degenerate input
            qhull = None
        if qhull is not None:
            faces = qhull.simplices.copy()
            tri = every[faces]
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            inward = np.einsum("ij,ij->i", normals, qhull.equations[:, :3]) < 0
            faces[inward] = faces[inward][:, ::-1]
            used, remapped = np.unique(faces, return_inverse=True)
            hull = trimesh.Trimesh(every[used], remapped.reshape(-1, 3), process=False)
    if hull is None or not hull.is_watertight or hull.volume <= 0:
        raise SegmentationError(
            f"an object of {len(points)} fused points could not be closed even as their convex hull; film it from "
            "more sides"
        )
    return WatertightMesh(vertices_world=np.asarray(hull.vertices), faces=np.asarray(hull.faces), closed_bottom=True)


def _oriented_shell(dense: DenseResult, segment: ObjectSegment, cam_centres: np.ndarray) -> np.ndarray:
    """The object's fused faces, flipped if needed so that normals point out, towards the cameras."""
    faces = dense.faces[segment.face_ids]
    tri = dense.vertices_world[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    to_cameras = cam_centres.mean(axis=0) - tri.mean(axis=1)
    if np.sum(np.einsum("ij,ij->i", normals, to_cameras) > 0) < 0.5 * len(faces):
        faces = faces[:, ::-1]
    return faces


def _footprint_cap(points: np.ndarray, voxel: float, cap_height: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated cap on the table (z = 0, normals down) under the object's body.

    The outline comes from the points standing above `cap_height`: the object's own lowest points mix with noisy
    table surface beside it, which made skirts reaching far past the object. The camera never sees where an object
    meets the table: closing it flat there is an assumption, recorded with the object (`closed_bottom`).
    """
    low = points[points[:, 2] >= cap_height][:, :2]
    if len(low) < 10:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    image, origin, cell = footprint_image(low, voxel, dilate_cells=0)
    image = ndimage.binary_erosion(image, iterations=1)
    cells = np.argwhere(image)
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])
    verts = ((cells[:, None, :] + corners[None]) * cell + origin).reshape(-1, 2)
    verts = np.c_[verts, np.zeros(len(verts))]
    base = np.arange(len(cells))[:, None] * 4
    faces = np.concatenate(
        [base + np.array([0, 2, 1]), base + np.array([0, 3, 2])]
    )  # clockwise seen from above: normal -z
    return verts, faces


def mesh_object(
    dense: DenseResult,
    segment: ObjectSegment,
    cam_centres: np.ndarray,
    options: MeshOptions | None = None,
) -> WatertightMesh:
    """Watertight mesh of one object: inside = generalized winding number of its fused shell plus a table cap.

    The fused surface has holes (occlusions, weak texture); the winding number (Jacobson et al. 2013) still
    tells inside from outside across them, where filling voxels or carving would leak.

    An object filmed at rest on the table must rest there in the simulation too. Stereo rarely measures the low
    side of a foot next to the table (a toy figure's base disc, 1 cm tall), and the inside test then stands the
    object on the narrower part above it; when the mesh would tip over at less than ``min_tip_angle_deg`` of tilt,
    every column under the object's seen surface is filled down to the table instead (carved where the depth maps
    see through it, as before), and the steadier mesh is kept, with a warning. (Test seed 101's toy figure stood on
    a 2 x 1 cm foot of its 5 cm base on one CPU and toppled in the settle test.)

    Args:
        dense: fused surface (world frame, table top z = 0).
        segment: the object's part of it.
        cam_centres: (M, 3) registered camera centres (to orient the shell).
        options: settings.

    Raises:
        SegmentationError: nothing closed could be made of the object.
    """
    options = options or MeshOptions()
    mesh = _closed_surface(dense, segment, cam_centres, options, foot=False)
    contact_m = 0.25 * dense.voxel_size
    tilt = tip_angle_deg(mesh.vertices_world, mesh.faces, contact_m)
    if tilt >= options.min_tip_angle_deg or np.min(mesh.vertices_world[:, 2]) > contact_m:
        return mesh  # steady, or not standing on the table (resting on another object)
    try:
        footed = _closed_surface(dense, segment, cam_centres, options, foot=True)
    except SegmentationError:
        return mesh
    footed_tilt = tip_angle_deg(footed.vertices_world, footed.faces, contact_m)
    if footed_tilt <= tilt:
        return mesh
    note = (
        f"its mesh stood on too narrow a foot to rest (tips over at {tilt:.1f} deg): the space under its seen surface "
        f"was filled down to the table (tips over at {footed_tilt:.1f} deg)"
    )
    log.info("an object %s", note)
    return WatertightMesh(
        vertices_world=footed.vertices_world, faces=footed.faces, closed_bottom=footed.closed_bottom, warnings=(note,)
    )


def tip_angle_deg(vertices_world: np.ndarray, faces: np.ndarray, contact_m: float) -> float:
    """How far a closed mesh standing on the table (z = 0) can tilt before it tips over: the angle, seen from its
    centre of mass (uniform density), between straight down and the nearest edge of its support (the convex hull of
    its vertices within `contact_m` of the table). Negative when the centre of mass lies outside the support; -90
    with no support to stand on.

    Args:
        vertices_world: (V, 3) float, metres, world frame (table top z = 0).
        faces: (F, 3) int, a closed surface.
        contact_m: vertices this close to the table touch it.
    """
    import trimesh
    from scipy.spatial import ConvexHull, QhullError

    support = vertices_world[vertices_world[:, 2] <= contact_m, :2]
    if len(support) < 3:
        return -90.0
    try:
        hull = ConvexHull(support)
    except QhullError:  # a line or a point: no area to stand on
        return -90.0
    centre = trimesh.Trimesh(vertices_world, faces, process=False).center_mass
    inside_m = float(np.min(-(hull.equations[:, :2] @ centre[:2] + hull.equations[:, 2])))
    return float(np.degrees(np.arctan2(inside_m, max(float(centre[2]), 1e-9))))


def _closed_surface(
    dense: DenseResult, segment: ObjectSegment, cam_centres: np.ndarray, options: MeshOptions, foot: bool
) -> WatertightMesh:
    """`mesh_object`'s surface; `foot`: every column under the object's seen surface is filled down to the table
    (`_foot_columns`), not only those under its inside-test solid, and none is tapered."""
    import igl
    import trimesh
    from skimage.measure import marching_cubes

    # The inside test runs on a grid finer than the fusion voxels: voxel centres that sit on the surface count as
    # inside, which biases the surface outwards by up to half a grid cell.
    voxel = dense.voxel_size / options.grid_refinement
    shell_faces = _oriented_shell(dense, segment, cam_centres)
    points = segment.points_world
    if options.support_min_views > 0 and dense.depth_maps:
        # A TSDF also has zero crossings where no depth map measured a surface: at the edge of space no camera saw
        # (under a bowl's flare it hangs a curtain from the wall to the table, which the cap then closed off as
        # solid). Keep the fused surface the depth maps back, unless that leaves too little to judge by.
        tolerance_m = options.support_tolerance_voxels * dense.voxel_size
        face_ok = _measured(dense.vertices_world[shell_faces].mean(axis=1), dense.depth_maps, tolerance_m)
        point_ok = _measured(points, dense.depth_maps, tolerance_m)
        face_ok, point_ok = face_ok >= options.support_min_views, point_ok >= options.support_min_views
        if face_ok.mean() >= 0.5 and point_ok.mean() >= 0.5:
            shell_faces, points = shell_faces[face_ok], points[point_ok]
        else:
            log.warning(
                "only %.0f%% of an object's fused surface is backed by %d depth maps: kept all of it",
                100 * min(face_ok.mean(), point_ok.mean()),
                options.support_min_views,
            )
    cap_v, cap_f = _footprint_cap(points, dense.voxel_size, options.cap_height_voxels * dense.voxel_size)
    verts = np.concatenate([dense.vertices_world, cap_v])
    faces = np.concatenate([shell_faces, cap_f + len(dense.vertices_world)])
    pad = 3
    lo_index = np.floor(segment.points_world.min(axis=0) / voxel).astype(int) - pad
    lo_index[2] = -pad
    hi_index = np.ceil(segment.points_world.max(axis=0) / voxel).astype(int) + pad
    shape = tuple(int(n) for n in hi_index - lo_index + 1)
    lo = lo_index * voxel
    centres = lo + np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3) * voxel
    winding = igl.fast_winding_number(
        np.ascontiguousarray(verts, np.float64), np.ascontiguousarray(faces, np.int64), centres
    ).reshape(shape)
    solid = winding > 0.5
    z0 = int(np.ceil(-lo[2] / voxel))  # first voxel layer at or above the table top z = 0
    solid[:, :, :z0] = False
    solid = _largest_piece(solid, "an object's surface encloses no volume; film it from more sides")
    # Objects rest on the table: below what the cameras saw, each column of the footprint is filled down to the
    # table (an apple seen only from above becomes solid to the table instead of floating), or, under an overhang,
    # down to a slope from where the object stands to the lowest wall seen (`_tapered_bottom`). An assumption.
    footprint = np.asarray(solid.any(axis=2))
    first = np.where(footprint, solid.argmax(axis=2), 0)
    if foot:
        low_m = options.cap_height_voxels * dense.voxel_size
        columns, lowest = _foot_columns(points, lo, voxel, footprint.shape, low_m)
        first = np.where(footprint, np.minimum(first, lowest), lowest)
        footprint = footprint | columns
    layers = np.arange(shape[2])[None, None, :]
    bottom = np.full(footprint.shape, z0)
    if options.underside == "taper" and not foot:
        margin_layers = int(np.ceil(options.carve_margin_voxels * dense.voxel_size / voxel))
        reach_m = options.seen_wall_voxels * dense.voxel_size
        seen = _seen_lowest(points, lo, voxel, first, footprint, reach_m)
        bottom = _tapered_bottom(footprint, first, z0, margin_layers, seen)
    extrude = footprint[..., None] & (layers >= bottom[..., None]) & (layers < first[..., None])
    solid |= extrude
    # The fill above is an assumption; where depth maps see the table or the far side of the object through it
    # (under a bowl's flared wall, past a stereo bump), it is wrong: carve it, keep the largest piece.
    if options.carve_min_views > 0 and dense.depth_maps:
        margin = options.carve_margin_voxels * dense.voxel_size
        on_surface, inside = _fused_tests(dense)
        solid &= ~_seen_through(dense.depth_maps, solid, lo, voxel, margin, options, on_surface, inside)
        # Within `margin` of the table no depth map can tell the object from the table behind it: there the object
        # keeps the cross-section it has just above (a flared wall's carved undercut reaches down to the table).
        # That cross-section's ring may be torn (a bowl's low wall, stereo holes); closed across its gaps, the floor
        # inside it stays (tuning seed 42: with the ring's hole unfilled, the bowl lost its floor and became a ring).
        above = min(shape[2] - 1, z0 + int(np.ceil(margin / voxel)))
        gap_cells = round(options.outline_gap_voxels * options.grid_refinement)
        solid[:, :, z0:above] &= _outline(solid, above, 4, gap_cells)[:, :, None]  # 4 layers: one may be broken
        solid = _largest_piece(solid, "the depth maps see through the whole object; film it from more sides")
    # Shadowed table next to an object is poorly matched and leaves thin skirts at its base: open the lowest
    # layers in the table plane, outside the outline of the layers just above them (walls higher up are left alone,
    # however thin, and so is their foot: opened too, a mug's 4 mm wall lost its lowest 1.4 cm and the mug hung
    # above the table, tuning seed 45).
    refine = options.grid_refinement
    top_layer = min(shape[2], z0 + int(np.ceil(options.skirt_height_voxels * refine)))
    base_layers = slice(z0, top_layer)
    opened = ndimage.binary_opening(solid[:, :, base_layers], structure=np.ones((4 * refine + 1, 4 * refine + 1, 1)))
    above_outline = ndimage.binary_dilation(_outline(solid, top_layer, 2 * refine), iterations=refine)
    solid[:, :, base_layers] = opened | (solid[:, :, base_layers] & above_outline[:, :, None])
    closed_bottom = bool(extrude.any() or len(cap_f) > 0)
    field = ndimage.gaussian_filter(solid.astype(np.float32), sigma=0.7 * options.grid_refinement)
    field[:, :, :z0] = 0.0
    field = np.pad(field, 1)  # empty all round, so the surface closes
    mc_verts, mc_faces, _, _ = marching_cubes(field, level=0.5, spacing=(voxel, voxel, voxel))
    mesh = trimesh.Trimesh(mc_verts + lo - voxel, mc_faces[:, ::-1], process=True)
    mesh = _largest_component(mesh)
    if mesh.volume < 0:
        mesh.invert()
    trimesh.smoothing.filter_taubin(mesh, iterations=options.smooth_iterations)
    # Decimation and the base snap are refinements: if either breaks the closed surface on some input, fall back to
    # the surface without it rather than failing the whole scene.
    decimated = _decimate(mesh, options.face_budget)
    candidates = [_snap_base(decimated, dense.voxel_size), decimated, _snap_base(mesh, dense.voxel_size), mesh]
    good = [m for m in candidates if _is_closed(m)]
    if not good:
        # Rare: marching cubes can leave a non-manifold edge where two lobes of the solid touch; repair, then retry.
        candidates = [_repaired(m) for m in candidates]
        good = [m for m in candidates if _is_closed(m)]
        if good:
            log.warning("an object's surface needed repair to close (%d faces)", len(good[0].faces))
    if not good:
        log.warning(
            "could not close an object's surface: %s",
            [(len(m.faces), bool(m.is_watertight), float(m.volume)) for m in candidates],
        )
        raise SegmentationError(
            "could not build a closed mesh for an object (degenerate surface); film it from more sides"
        )
    mesh = good[0]
    return WatertightMesh(
        vertices_world=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces), closed_bottom=closed_bottom
    )


def _foot_columns(
    points_world: np.ndarray, lo: np.ndarray, voxel: float, shape: tuple[int, int], min_height_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) grid columns under the object's seen surface, and the layer of the lowest point seen in each (a large
    value elsewhere): the points `min_height_m` or more above the table (lower ones mix with the table's), their
    columns closed across the gaps between fused points (two cells) and their enclosed holes filled."""
    high = points_world[points_world[:, 2] >= min_height_m]
    lowest = np.full(shape, np.iinfo(np.int32).max // 2, np.int32)
    if len(high) == 0:
        return np.zeros(shape, bool), lowest
    cell = np.round((high - lo) / voxel).astype(int)
    keep = (cell[:, 0] >= 0) & (cell[:, 0] < shape[0]) & (cell[:, 1] >= 0) & (cell[:, 1] < shape[1])
    cell = cell[keep]
    np.minimum.at(lowest, (cell[:, 0], cell[:, 1]), cell[:, 2].astype(np.int32))
    seen = lowest < np.iinfo(np.int32).max // 2
    columns = ndimage.binary_fill_holes(ndimage.binary_closing(seen, iterations=2, border_value=0))
    # A column between seen ones takes the lowest layer seen within two cells of it.
    spread = ndimage.minimum_filter(lowest, size=5, mode="constant", cval=np.iinfo(np.int32).max // 2)
    filled = np.where(seen, lowest, spread)
    columns &= filled < np.iinfo(np.int32).max // 2
    return np.asarray(columns), filled


def _seen_lowest(
    points_world: np.ndarray, lo: np.ndarray, voxel: float, first: np.ndarray, footprint: np.ndarray, reach_m: float
) -> np.ndarray:
    """(X, Y) columns whose lowest solid cell lies on a surface the depth maps saw (an object point within
    `reach_m`), rather than where the inside test bridged a hole in the fused surface."""
    from scipy.spatial import cKDTree

    ij = np.argwhere(footprint)
    centres = lo + np.column_stack([ij, first[ij[:, 0], ij[:, 1]]]) * voxel
    dist, _ = cKDTree(points_world).query(centres, distance_upper_bound=1.01 * reach_m)
    seen = np.zeros_like(footprint)
    seen[ij[:, 0], ij[:, 1]] = dist <= reach_m
    return seen


def _tapered_bottom(
    footprint: np.ndarray, first: np.ndarray, z0: int, margin_layers: int, seen_lowest: np.ndarray
) -> np.ndarray:
    """(X, Y) layer from which each column of the footprint is filled up to its lowest solid cell `first`.

    Where an object reaches the table (its lowest solid cell within `margin_layers` of the table layer `z0`) it
    stands on it: filled to the table. Under an overhang, the space between the table and the lowest wall the
    cameras saw was never seen (a camera above the table cannot look up under a bowl's flare). Filling it all down
    to the table turns a bowl into a bucket; instead the fill runs a straight slope from the edge of where the object
    stands (table height) up to the nearest seen lowest wall: per column, the height of that wall times its distance
    from the standing part over the wall's distance from it. Without a standing part or a seen wall, every column
    is filled down to the table, as before (an apple seen only from above).
    """
    bottom = np.full(footprint.shape, z0)
    standing = footprint & (first <= z0 + margin_layers)
    anchors = footprint & ~standing & seen_lowest
    if not standing.any() or not anchors.any():
        return bottom
    from_standing = ndimage.distance_transform_edt(~standing)
    _, nearest = ndimage.distance_transform_edt(~anchors, return_indices=True)
    ai, aj = nearest[0], nearest[1]
    anchor_height = first[ai, aj] - z0
    anchor_reach = np.maximum(from_standing[ai, aj], 1.0)
    slope_bottom = z0 + np.floor(anchor_height * np.minimum(from_standing / anchor_reach, 1.0)).astype(int)
    return np.where(footprint & ~standing, slope_bottom, z0)


def _outline(solid: np.ndarray, first_layer: int, layers: int, gap_cells: int = 0) -> np.ndarray:
    """(X, Y) outline of a voxel solid over `layers` layers from `first_layer` up, its enclosed holes filled (a
    cup's cavity is inside its outline), once gaps in its ring up to about 2 x `gap_cells` wide are closed."""
    section = solid[:, :, first_layer : first_layer + layers].any(axis=2)
    outline = ndimage.binary_fill_holes(section)
    if gap_cells > 0:
        # Grown by `gap_cells` the ring closes, its inside is filled, and shrunk back it keeps that inside.
        r = gap_cells
        disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r + 0.01
        grown = ndimage.binary_fill_holes(ndimage.binary_dilation(np.pad(section, r + 1), structure=disk))
        outline |= ndimage.binary_erosion(grown, structure=disk)[r + 1 : -r - 1, r + 1 : -r - 1]
    return np.asarray(outline)


def _largest_piece(solid: np.ndarray, empty_message: str) -> np.ndarray:
    """The largest connected piece of a voxel solid, its enclosed holes filled.

    Raises:
        SegmentationError: `empty_message`, when the solid is empty.
    """
    labels, count = ndimage.label(solid)
    if count == 0:
        raise SegmentationError(empty_message)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return np.asarray(ndimage.binary_fill_holes(labels == int(sizes.argmax())))


def _fused_tests(
    dense: DenseResult,
) -> tuple[Callable[[np.ndarray], np.ndarray] | None, Callable[[np.ndarray], np.ndarray] | None]:
    """Tests of world points (N, 3) against the fused TSDF: on its surface (|TSDF| <= half the truncation), and
    clearly inside an object (TSDF <= -0.3, fused from at least 2 depth maps). None without a TSDF."""
    if len(dense.tsdf_voxels) == 0:
        return None, None
    lookup = dense.tsdf_sampler()

    def on_surface(points_world: np.ndarray) -> np.ndarray:
        value, weight = lookup(points_world)
        return (np.abs(value) <= 0.5) & (weight > 0)

    def inside(points_world: np.ndarray) -> np.ndarray:
        value, weight = lookup(points_world)
        return (value <= -0.3) & (weight >= 2)

    return on_surface, inside


def _seen_through(
    depth_maps: tuple[DepthMap, ...],
    solid: np.ndarray,
    lo: np.ndarray,
    voxel: float,
    margin: float,
    options: MeshOptions,
    on_surface: Callable[[np.ndarray], np.ndarray] | None = None,
    inside_fused: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Voxels of `solid` (grid origin `lo`, spacing `voxel`) that enough depth maps see a surface behind.

    Space carving: a depth map that measures a surface more than `margin` behind a voxel, along the ray through
    it, sees through it. Depth next to depth jumps and holes is left out: block matching drags background depth
    across silhouettes, which would eat into objects. With `on_surface`, the surface a depth map measures must also
    be one the fusion of all depth maps agrees on: one view's depth that falls through a plain bowl floor does not
    carve the floor. With `inside_fused`, voxels the fusion holds to be inside an object (a thin wall between two
    seen surfaces) are kept, whatever a few views say.
    """
    index = np.argwhere(solid)
    centres = lo + index * voxel
    votes = np.zeros(len(index), np.int32)
    for depth_map in depth_maps:
        depth = depth_map.depth
        valid = depth > 0
        if options.carve_edge_px > 0:
            near = ndimage.maximum_filter(np.where(valid, depth, 0.0), size=3)
            far = ndimage.minimum_filter(np.where(valid, depth, np.inf), size=3)
            jump = (near - far) > options.carve_jump_fraction * depth
            valid &= ~ndimage.binary_dilation(jump | ~valid, iterations=options.carve_edge_px)
        hit, u, v, z = _pixels(depth_map, centres)
        measured = depth[v, u]
        seen = valid[v, u] & (measured > z[hit] + margin)
        if on_surface is not None and seen.any():
            # The measured point lies on the ray through the voxel, `measured / z` times as far from the camera.
            origin = depth_map.world_from_cam[:3, 3]
            behind = origin + (centres[hit[seen]] - origin) * (measured[seen] / z[hit[seen]])[:, None]
            seen[seen] = on_surface(behind)
        votes[hit[seen]] += 1
    carve = votes >= options.carve_min_views
    if inside_fused is not None and carve.any():
        carve[carve] = ~inside_fused(centres[carve])
    out = np.zeros_like(solid)
    out[tuple(index[carve].T)] = True
    return out


def _measured(points_world: np.ndarray, depth_maps: tuple[DepthMap, ...], tolerance_m: float) -> np.ndarray:
    """(N,) how many depth maps measured a surface within `tolerance_m` (along the ray) of each point."""
    count = np.zeros(len(points_world), np.int32)
    for depth_map in depth_maps:
        hit, u, v, z = _pixels(depth_map, points_world)
        measured = depth_map.depth[v, u]
        near = (measured > 0) & (np.abs(measured - z[hit]) <= tolerance_m)
        count[hit[near]] += 1
    return count


def _pixels(depth_map: DepthMap, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where world points (N, 3) fall in a depth map: the indices of those in front of the camera and inside the
    image, their pixel columns and rows (nearest pixel), and the camera depth z of all N points."""
    cam_from_world = np.linalg.inv(depth_map.world_from_cam)
    cam = points_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[:, 2]
    ahead = z > 1e-6
    u = np.full(len(z), -1)
    v = np.full(len(z), -1)
    u[ahead] = np.round(depth_map.k[0, 0] * cam[ahead, 0] / z[ahead] + depth_map.k[0, 2]).astype(int)
    v[ahead] = np.round(depth_map.k[1, 1] * cam[ahead, 1] / z[ahead] + depth_map.k[1, 2]).astype(int)
    height, width = depth_map.depth.shape
    hit = np.flatnonzero(ahead & (u >= 0) & (u < width) & (v >= 0) & (v < height))
    return hit, u[hit], v[hit], z


def _is_closed(mesh: trimesh.Trimesh) -> bool:
    return bool(mesh.is_watertight) and bool(np.isfinite(mesh.volume)) and float(mesh.volume) > 0


def _repaired(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Drops degenerate and duplicate faces, fills small holes, orients faces outwards, keeps the largest piece."""
    import trimesh

    fixed = mesh.copy()
    fixed.merge_vertices()
    fixed.update_faces(fixed.nondegenerate_faces())
    fixed.update_faces(fixed.unique_faces())
    fixed.remove_unreferenced_vertices()
    trimesh.repair.fill_holes(fixed)
    trimesh.repair.fix_normals(fixed)
    fixed = _largest_component(fixed)
    if fixed.volume < 0:
        fixed.invert()
    return fixed


def _snap_base(mesh: trimesh.Trimesh, voxel_size: float) -> trimesh.Trimesh:
    """The assumed bottom is flat on the table: snap what smoothing rounded off back onto z = 0, so the object
    rests on a plane instead of rocking on a rounded base."""
    import trimesh

    vertices = np.array(mesh.vertices)
    vertices[vertices[:, 2] < voxel_size, 2] = 0.0
    return trimesh.Trimesh(vertices, mesh.faces, process=True)


def _largest_component(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh
    # Closed pieces first (by volume), then open ones by face count: volumes in m^3 are far below any face count.
    # (A flat closed sliver has zero volume: trimesh divides by it for the centre of mass.)
    with np.errstate(invalid="ignore", divide="ignore"):
        return max(parts, key=lambda m: (1, abs(m.volume)) if m.is_watertight else (0, len(m.faces)))


def _decimate(mesh: trimesh.Trimesh, face_budget: int) -> trimesh.Trimesh:
    """Quadric decimation (Open3D keeps closed meshes closed) to the face budget; keeps the input otherwise."""
    import open3d as o3d
    import trimesh

    if len(mesh.faces) <= face_budget:
        return mesh
    o3d_mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces)
    )
    simple = o3d_mesh.simplify_quadric_decimation(target_number_of_triangles=face_budget)
    out = trimesh.Trimesh(np.asarray(simple.vertices), np.asarray(simple.triangles), process=True)
    if out.is_watertight and out.volume > 0:
        return out
    log.warning("decimation broke watertightness; keeping %d faces", len(mesh.faces))
    return mesh
