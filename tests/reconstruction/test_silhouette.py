"""Objects from their silhouettes against the table (`reconstruction/_silhouette.py`), and the checks that drop
phantom pieces of the fused surface (`reconstruction/_scene_objects`): against rendered truth.

The scene is the first of the tests' family seed range (`samples/make_scene_family.py --small --seed 100`): one
plain, low-texture cup on a half orbit, the case stereo gives no surface at all. The hull is run on the truth's
cameras, so the check is of the silhouettes and the hull, not of the structure from motion.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from reconstruction._dense import RegionOfInterest, StereoView
from reconstruction._scene_objects import _resting, _with_silhouettes
from reconstruction._silhouette import SilhouetteOptions, hull_mesh, visual_hull
from reconstruction._types import ObjectInstance, TexturedMesh

REPO = Path(__file__).resolve().parents[2]
SEED = 100
VOXEL_M = 0.0025


@pytest.fixture(scope="module")
def plain_cup(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[StereoView], np.ndarray, dict]:
    out = tmp_path_factory.mktemp("silhouette")
    cmd = [sys.executable, str(REPO / "samples" / "make_scene_family.py"), str(out), "--small", "--seed", str(SEED)]
    subprocess.run(cmd, check=True, capture_output=True)
    truth = out / f"scene_{SEED:05d}" / "truth"
    cameras = json.loads((truth / "cameras.json").read_text())
    video = cv2.VideoCapture(str(truth.parent / "video.mp4"))
    frames = []
    while True:
        ok, frame = video.read()
        if not ok:
            break
        frames.append(frame)
    video.release()
    views = [
        StereoView(image_bgr=frames[f["frame_index"]], world_from_cam=np.array(f["world_from_cam"]))
        for f in cameras["frames"]
    ]
    i = cameras["intrinsics"]
    k = np.array([[i["fx"], 0.0, i["cx"] - 0.5], [0.0, i["fy"], i["cy"] - 0.5], [0.0, 0.0, 1.0]])
    (cup,) = json.loads((truth / "objects.json").read_text())["objects"]
    return views, k, cup


def _roi(cup: dict) -> RegionOfInterest:
    centre = np.array(cup["pos_m"])
    return RegionOfInterest(
        min_world=np.array([centre[0] - 0.15, centre[1] - 0.15, -0.02]),
        max_world=np.array([centre[0] + 0.15, centre[1] + 0.15, 0.25]),
    )


def test_a_plain_cup_is_found_from_its_silhouettes(plain_cup: tuple[list[StereoView], np.ndarray, dict]) -> None:
    """Issue 60: a low-texture cup, which stereo gives no surface (seed 100 ended with exit 2), comes out of the
    visual hull as one piece where it stands: centre within 5 mm on the table, width and height within 15% (a hull
    is never smaller than the object; the cup's top rim is seen against the table in few frames)."""
    views, k, cup = plain_cup
    hull = visual_hull(views, k, _roi(cup), VOXEL_M)
    assert hull is not None
    assert len(hull.pieces) == 1, [len(p.cells) for p in hull.pieces]
    vertices, _ = hull_mesh(hull.pieces[0])
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, extents = (lo + hi) / 2, hi - lo
    assert np.linalg.norm(centre[:2] - np.array(cup["pos_m"])[:2]) < 0.005
    assert lo[2] == pytest.approx(0.0, abs=1e-6)  # it stands on the table
    np.testing.assert_allclose(extents, cup["extents_m"], rtol=0.15)


def test_colour_alone_misses_part_of_the_cup(plain_cup: tuple[list[StereoView], np.ndarray, dict]) -> None:
    """The table's pattern is compared too, and it matters: without it (colour only), the hull of the same cup is
    smaller (parts of a plain object whose colour is near the table's are carved away)."""
    views, k, cup = plain_cup
    both = visual_hull(views, k, _roi(cup), VOXEL_M)
    colour_only = visual_hull(views, k, _roi(cup), VOXEL_M, SilhouetteOptions(zncc_threshold=-1.0))
    assert both is not None and colour_only is not None
    cells = sum(len(p.cells) for p in both.pieces)
    assert cells > sum(len(p.cells) for p in colour_only.pieces)


def _box(centre: tuple[float, float, float], half: float) -> ObjectInstance:
    corners = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    import trimesh

    mesh = trimesh.Trimesh(corners).convex_hull
    pose = np.eye(4)
    pose[:3, 3] = centre
    return ObjectInstance(
        name="object_0",
        mesh=TexturedMesh(vertices_m=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces)),
        world_from_object=pose,
    )


def test_floating_pieces_are_dropped_and_stacked_ones_kept() -> None:
    """A fused piece 10 cm above the table with nothing under it (a phantom behind a bottle on the family's low
    passes) is no object; one standing on another object is."""
    standing = _box((0.0, 0.0, 0.03), 0.03)
    stacked = _box((0.0, 0.0, 0.08), 0.02)  # on top of the first
    floating = _box((0.2, 0.0, 0.12), 0.02)
    kept = _resting([standing, stacked, floating], max_float_m=0.015)
    assert [tuple(o.world_from_object[:3, 3]) for o in kept] == [(0.0, 0.0, 0.03), (0.0, 0.0, 0.08)]
    assert [o.name for o in kept] == ["object_0", "object_1"]


def test_a_wide_phantom_high_over_a_small_object_is_not_resting_on_it() -> None:
    """Held-out 1048 and 1053 (issue 60): wide phantoms of smeared depth 7-12 cm above the table were kept because
    a ball or a mug stood somewhere under them, and fell over in the settle test. Resting on another object means
    lying on its top (within the float tolerance), centred over it; a box on a box is still kept."""
    ball = _box((0.0, 0.0, 0.02), 0.02)  # top at 4 cm
    # 36 x 3.5 x 10 cm, 8.6 cm up, one end over the ball
    corners = np.array([[x, y, z] for x in (-0.02, 0.34) for y in (-0.0175, 0.0175) for z in (0.086, 0.186)])
    import trimesh

    hull = trimesh.Trimesh(corners).convex_hull
    phantom = ObjectInstance(
        name="object_1",
        mesh=TexturedMesh(vertices_m=np.asarray(hull.vertices), faces=np.asarray(hull.faces)),
        world_from_object=np.eye(4),
    )
    on_top = _box((0.0, 0.0, 0.055), 0.015)  # bottom at 4 cm, on the ball's top
    kept = _resting([ball, phantom, on_top], max_float_m=0.018)
    assert [tuple(np.round(o.world_from_object[:3, 3], 3)) for o in kept] == [(0.0, 0.0, 0.02), (0.0, 0.0, 0.055)]


def test_the_hull_adds_what_the_fused_surface_missed_and_keeps_what_it_found(
    plain_cup: tuple[list[StereoView], np.ndarray, dict],
) -> None:
    """The cup the fused surface missed is added, meshed from its silhouettes ("silhouette" quality, a warning
    saying so); a fused object is kept even where the hull carved it (an object the table's colour is carved)."""
    views, k, cup = plain_cup
    x, y, _ = cup["pos_m"]
    fused = _box((x + 0.09, y, 0.02), 0.02)  # on bare table beside the cup: the hull carves it
    kept = _with_silhouettes([fused], views, k, _roi(cup), VOXEL_M, SilhouetteOptions())
    assert len(kept) == 2
    assert kept[0].mesh_quality == "full" and kept[0].world_from_object[0, 3] == pytest.approx(x + 0.09)
    added = kept[1]
    assert added.mesh_quality == "silhouette" and "silhouettes" in added.warnings[0]
    assert np.linalg.norm(added.world_from_object[:2, 3] - np.array([x, y])) < 0.005
    assert [o.name for o in kept] == ["object_0", "object_1"]


def test_a_solid_piece_beside_a_fused_object_is_kept_and_a_thin_cone_beside_it_is_not(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Held-out 1006 (issue 60): two bottles the silhouettes found 1 cm from a fused book were dropped by the rule
    that took every hull piece within 4 voxels of a fused object for a part of it. That rule was made for the real
    apple's red glow on the table, which the hull leaves as a thin cone (4.5% of its box of cells). Beside a fused
    object, a solid piece is a neighbour and kept; a thin one is the colour the object casts, and dropped."""
    from reconstruction import _silhouette

    cell = 2 * VOXEL_M
    book = _box((0.0, 0.0, 0.02), 0.02)  # x, y in [-2, 2] cm
    solid = _silhouette.HullObject(  # a 4 x 4 x 15 cm column 7.5 mm from the book: inside the 4-voxel gap
        cells=np.argwhere(np.ones((8, 8, 30), bool)), origin_world=np.array([0.03, -0.0175, 0.5 * cell]), cell_m=cell
    )
    cone = _silhouette.HullObject(  # a slanted sheet, one cell thick, on the book's other side
        cells=np.array([(i, j, 19 - i) for i in range(20) for j in range(8)]),
        origin_world=np.array([-0.03 - 19 * cell, -0.0175, 0.5 * cell]),
        cell_m=cell,
    )
    assert solid.fill == 1.0 and cone.fill == pytest.approx(0.05)
    hull = _silhouette.VisualHull(pieces=(solid, cone))
    monkeypatch.setattr(_silhouette, "visual_hull", lambda *args, **kwargs: hull)
    region = RegionOfInterest(min_world=np.array([-0.2, -0.2, -0.02]), max_world=np.array([0.2, 0.2, 0.25]))
    kept = _with_silhouettes([book], [], np.eye(3), region, VOXEL_M, SilhouetteOptions())
    assert [o.mesh_quality for o in kept] == ["full", "silhouette"]
    assert kept[1].world_from_object[0, 3] > 0.03  # the column, not the cone


def test_a_fused_fragment_of_a_plain_cup_gives_way_to_its_hull(
    plain_cup: tuple[list[StereoView], np.ndarray, dict],
) -> None:
    """Held-out 1043 (issue 60): stereo fused a 2.9 x 1.8 x 1.5 cm crumb at the foot of a plain cup 8.7 x 8.7 x 10 cm;
    its footprint met the cup's hull piece, which was then taken for a part of it, and the cup was never meshed.
    A fused object that small inside the one solid hull piece it meets is a fragment: the hull replaces it (one
    object, "silhouette" quality, a warning that says why). A fused object the cup's size there is kept as fused."""
    views, k, cup = plain_cup
    x, y, _ = cup["pos_m"]
    half = np.array(cup["extents_m"]) / 2
    crumb = _box((x + 0.6 * half[0], y, 0.008), 0.008)
    kept = _with_silhouettes([crumb], views, k, _roi(cup), VOXEL_M, SilhouetteOptions())
    assert len(kept) == 1
    (cup_object,) = kept
    assert cup_object.mesh_quality == "silhouette" and "fragment" in cup_object.warnings[0]
    assert np.linalg.norm(cup_object.world_from_object[:2, 3] - np.array([x, y])) < 0.005
    assert np.ptp(cup_object.mesh.vertices_m[:, 2]) == pytest.approx(cup["extents_m"][2], rel=0.15)

    whole = _box((x, y, half[2]), float(half.min()))  # the cup's width, fused (a cube as wide as the cup)
    kept = _with_silhouettes([whole], views, k, _roi(cup), VOXEL_M, SilhouetteOptions())
    assert [o.mesh_quality for o in kept] == ["full"]


def test_early_carving_decides_every_cell_as_counting_every_frame() -> None:
    """`_label_counts` with `carve_fraction` stops looking at a cell once it is carved whatever the frames left see;
    kept and carved must come out as with all frames counted, on random labels from cameras around a grid."""
    from image2sim_common.rotations import look_at_world_from_cam
    from reconstruction._silhouette import _label_counts

    rng = np.random.default_rng(3)
    k = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    views, labels = [], []
    for angle in np.linspace(0, 2 * np.pi, 40, endpoint=False):
        eye = np.array([0.5 * np.cos(angle), 0.5 * np.sin(angle), 0.4])
        views.append(
            StereoView(
                image_bgr=np.zeros((120, 160, 3), np.uint8), world_from_cam=look_at_world_from_cam(eye, np.zeros(3))
            )
        )
        # Mostly table (1), a patch of object (2) in the middle, a few unlabelled pixels (0), some noise.
        label = np.ones((120, 160), np.uint8)
        label[45:75, 60:100] = 2
        noisy = rng.random(label.shape) < 0.05
        label[noisy] = rng.integers(0, 3, size=int(noisy.sum()))
        labels.append(label)
    axis = np.linspace(-0.15, 0.15, 25)
    centres = np.stack(np.meshgrid(axis, axis, np.linspace(0.0, 0.2, 12), indexing="ij"), axis=-1).reshape(-1, 3)
    f, min_fg = 0.1, 6
    bg, fg = _label_counts(centres, labels, views, k)
    bg_early, fg_early = _label_counts(centres, labels, views, k, carve_fraction=f)

    def kept(b: np.ndarray, o: np.ndarray) -> np.ndarray:
        return (o >= min_fg) & (b <= f * np.maximum(b + o, 1))

    def carved(b: np.ndarray, o: np.ndarray) -> np.ndarray:
        return b > f * np.maximum(b + o, 1)

    assert 0 < kept(bg, fg).sum() < len(centres) // 2  # both outcomes occur
    assert (bg_early < bg).sum() > len(centres) // 2  # most cells were left early
    np.testing.assert_array_equal(kept(bg_early, fg_early), kept(bg, fg))
    np.testing.assert_array_equal(carved(bg_early, fg_early), carved(bg, fg))
