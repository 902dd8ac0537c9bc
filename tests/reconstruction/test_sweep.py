"""Multi-view plane sweep (`reconstruction/_sweep.py`), the depth of photo sets: against rendered truth."""

from __future__ import annotations

import cv2
import numpy as np

from reconstruction._sweep import SweepOptions, choose_neighbours, consistent, sweep_depth

SIZE = (480, 360)  # (width, height) px
K = np.array([[420.0, 0.0, 239.5], [0.0, 420.0, 179.5], [0.0, 0.0, 1.0]])
TABLE_HALF_M, BLOCK_HALF_M, BLOCK_TOP_M = 0.3, 0.06, 0.05


def _look_at(azimuth_deg: float, elevation_deg: float, distance_m: float) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = distance_m * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)  # OpenCV axes
    pose[:3, 3] = eye
    return pose


def _texture(seed: int, size: int) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0, 255, (size, size)).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.5)


def _render(world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grey image and true depth of a textured table (z = 0) with a textured square block top (z = 5 cm) on it.

    Only the block's top is drawn (no sides): each surface is a plane, drawn exactly by its homography."""
    cam_from_world = np.linalg.inv(world_from_cam)
    image = np.zeros(SIZE[::-1], np.float32)
    depth = np.zeros(SIZE[::-1], np.float64)
    for half, z, seed in ((TABLE_HALF_M, 0.0, 1), (BLOCK_HALF_M, BLOCK_TOP_M, 2)):
        texture = _texture(seed, round(2 * half / 0.0012))  # texels about as big as pixels (no aliasing)
        px = 2 * half / texture.shape[0]  # metres per texture pixel
        plane_from_texture = np.array([[px, 0, -half], [0, px, -half], [0, 0, 1.0]])
        # A point (x, y, z) of the plane: cam = R[:, :2] (x, y) + (R[:, 2] z + t).
        rotation, translation = cam_from_world[:3, :3], cam_from_world[:3, 3]
        columns = np.stack([rotation[:, 0], rotation[:, 1], rotation[:, 2] * z + translation], axis=1)
        homography = K @ columns @ plane_from_texture
        drawn = cv2.warpPerspective(texture, homography, SIZE, flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.ones_like(texture), homography, SIZE, flags=cv2.INTER_NEAREST) > 0.5
        image[mask] = drawn[mask]
        # True depth: the ray of each pixel meets the plane z.
        cols, rows = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]))
        rays = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(K).T @ world_from_cam[:3, :3].T
        lam = (z - world_from_cam[2, 3]) / rays[..., 2]
        depth[mask] = lam[mask]  # camera z of the point: rays have camera z = 1
    return image, depth


def test_plane_sweep_measures_the_depth_of_stills_20_degrees_apart() -> None:
    """Issue 60: stills 20 deg apart, which rectified two-view stereo cannot pair (the family's photo sets gave
    their objects no depth), get depth from the sweep: most textured pixels, within 0.5% of the truth on the table
    and on the block's top, and nothing through the table."""
    poses = [_look_at(az, 35.0, 0.6) for az in (0.0, 20.0, -20.0, 40.0, -40.0)]
    renders = [_render(p) for p in poses]
    options = SweepOptions()
    neighbours = choose_neighbours(poses, np.zeros(3), options)
    assert set(neighbours[0]) == {1, 2, 3, 4}
    others = [(renders[j][0], poses[j]) for j in neighbours[0]]
    depth, _ = sweep_depth(renders[0][0], poses[0], others, K, (0.3, 1.0), options, height_range=(-0.02, 0.15))
    truth = renders[0][1]
    inner = np.zeros_like(truth, bool)
    inner[20:-20, 20:-20] = True  # away from the window border
    measured = (depth > 0) & (truth > 0) & inner
    assert measured.sum() >= 0.7 * ((truth > 0) & inner).sum()
    error = np.abs(depth[measured] - truth[measured]) / truth[measured]
    assert np.median(error) < 0.005 and np.mean(error > 0.02) < 0.05
    # The block's top (5 cm up, 11 mm nearer than the table behind it) is measured on its own.
    block = measured & _block_mask(poses[0])
    assert block.sum() > 500
    assert np.median(np.abs(depth[block] - truth[block]) / truth[block]) < 0.005
    # Off the table (a black background), nothing is measured beyond the window's reach of the table's edge.
    off_table = cv2.distanceTransform((truth == 0).astype(np.uint8), cv2.DIST_L2, 3) > options.window_px
    assert ((depth > 0) & off_table).sum() < 0.001 * measured.sum()


def _block_mask(world_from_cam: np.ndarray) -> np.ndarray:
    cam_from_world = np.linalg.inv(world_from_cam)
    corners = np.array([[x, y, BLOCK_TOP_M] for x, y in ((-1, -1), (1, -1), (1, 1), (-1, 1))], float)
    corners[:, :2] *= BLOCK_HALF_M * 0.8  # inside its edges
    pixels = (corners @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]) @ K.T
    mask = np.zeros(SIZE[::-1], np.uint8)
    cv2.fillConvexPoly(mask, np.round(pixels[:, :2] / pixels[:, 2:]).astype(np.int32), 1)
    return mask > 0


def test_consistency_keeps_agreeing_depths_and_drops_a_lone_one() -> None:
    """A depth two maps agree on survives; one only its own map has (a false match) is dropped."""
    poses = [_look_at(0.0, 35.0, 0.6), _look_at(20.0, 35.0, 0.6)]
    truths = [_render(p)[1].astype(np.float32) for p in poses]
    wrong = truths[0].copy()
    wrong[260:300, 100:140] *= 0.9  # 10% too near: the other map measures the table there
    kept = consistent([wrong, truths[1]], poses, K, SweepOptions())
    assert (kept[0][260:300, 100:140] == 0).all()
    table = kept[0][200:340, 160:320]  # table seen by both, away from the block
    assert (table > 0).mean() > 0.98


def _five_stills() -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    poses = [_look_at(az, 35.0, 0.6) for az in (0.0, 20.0, -20.0, 40.0, -40.0)]
    return poses, [_render(p) for p in poses]


def test_a_blown_out_patch_in_a_neighbour_matches_nothing() -> None:
    """A flat (saturated) neighbour window has zero variance while its covariance keeps float32 rounding: the
    score reached 3.9, beat every true match, and gave those pixels arbitrary depths. Now it scores nothing, and
    depth elsewhere is as good as without the patch."""
    poses, renders = _five_stills()
    others = []
    for j in (1, 2, 3, 4):
        image = renders[j][0].copy()
        if j in (1, 2):
            image[120:240, 160:320] = 255.0  # a highlight clipped to white
        others.append((image, poses[j]))
    options = SweepOptions()
    depth, score = sweep_depth(renders[0][0], poses[0], others, K, (0.3, 1.0), options, height_range=(-0.02, 0.15))
    assert score.max() <= 1.0 + 1e-6
    truth = renders[0][1]
    measured = (depth > 0) & (truth > 0)
    error = np.abs(depth[measured] - truth[measured]) / truth[measured]
    assert measured.sum() > 0.6 * (truth > 0).sum()
    assert np.median(error) < 0.005 and np.mean(error > 0.02) < 0.05


def test_a_crop_measures_what_the_whole_image_does_there_and_nothing_goes_through_the_table() -> None:
    """The sweep runs only inside the region's image box (7x faster on a family photo set): inside the crop it
    gives the whole image's depth (the reference's K shifted by the crop's corner), outside it nothing. No
    measured point lies below the bottom of the height range."""
    poses, renders = _five_stills()
    others = [(renders[j][0], poses[j]) for j in (1, 2, 3, 4)]
    options = SweepOptions()
    args = (renders[0][0], poses[0], others, K, (0.3, 1.0), options)
    whole, _ = sweep_depth(*args, height_range=(-0.02, 0.15))
    crop = (100, 80, 380, 280)
    part, _ = sweep_depth(*args, height_range=(-0.02, 0.15), crop=crop)
    x0, y0, x1, y1 = crop
    assert not part[:y0].any() and not part[y1:].any() and not part[:, :x0].any() and not part[:, x1:].any()
    inner = (slice(y0 + 8, y1 - 8), slice(x0 + 8, x1 - 8))  # away from the crop's edge, where windows differ
    a, b = whole[inner], part[inner]
    assert ((a > 0) == (b > 0)).mean() > 0.99
    both = (a > 0) & (b > 0)
    assert np.abs(a[both] - b[both]).max() < 1e-4
    # World height of every measured point: never below the floor of the range (2 cm under the table).
    vs, us = np.nonzero(whole > 0)
    rays = np.stack([us, vs, np.ones_like(us)], 1).astype(float) @ np.linalg.inv(K).T
    z_world = (rays * whole[vs, us, None]) @ poses[0][2, :3] + poses[0][2, 3]
    assert z_world.min() >= -0.02 - 1e-3
