"""End to end on the embedded tabletop sample, through the CLI, compared with the true cameras.

Acceptance (issue 2): >= 90% of frames registered; camera centres within 5 mm (median) of the truth and view
directions within 0.5 deg, in the marker frame directly, with no alignment to the truth.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from reconstruction import ScaleSource
from reconstruction._world import fit_support_plane, world_from_extent, world_unknown_scale

OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def reconstruction_dir(grounded_tabletop: Path) -> Path:
    """The reconstruct stage's output folder inside the session's grounded tabletop (`image2sim ground` runs the
    same stage with the same settings as `image2sim reconstruct`; two runs agree within 0.02 mm in the cameras,
    not bit for bit: see docs/results/grounding.md), so the sample is reconstructed once per test run, not twice;
    `reconstruct`'s own command line is run below."""
    return grounded_tabletop / "reconstruction"


def _points_and_cameras(rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) sparse points and (M, 3) camera centres of a COLMAP model, in its own frame."""
    points = np.array([p.xyz for p in rec.points3D.values()])
    return points, np.array([im.projection_center() for im in rec.images.values()])


def test_reconstruct_command_line_writes_a_registered_model(tabletop_dir: Path, tmp_path: Path) -> None:
    """`image2sim reconstruct` end to end on 20 of the sample's frames: exit 0, a summary line, the stage's files,
    every frame registered and the marker's scale."""
    out = tmp_path / "rec"
    cmd = [sys.executable, "-m", "grounder.cli", "reconstruct", str(tabletop_dir / "video.mp4"), "-o", str(out)]
    proc = subprocess.run([*cmd, "--aruco-size", "0.12", "--max-frames", "20"], capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "registered" in proc.stdout
    report = json.loads((out / "reconstruct.json").read_text())
    assert report["frames_registered"] == report["frames_selected"] == 20
    assert report["scale"]["source"] == ScaleSource.ARUCO
    assert {p.name for p in out.iterdir()} >= {"transforms.json", "reconstruct.json", "sparse", "preview.png"}


def test_reconstruct_shows_no_library_chatter(reconstruction_dir: Path) -> None:
    """The vocabulary tree's k-means (faiss inside pycolmap) printed "WARNING clustering 256 points to 32 centroids:
    please provide at least 1248 training points" on every run, the first line a user saw; it is now silenced (the
    grounding's stderr, kept by tests/conftest.py)."""
    stderr = (reconstruction_dir.parent.parent / "stderr.txt").read_text()
    assert "please provide at least" not in stderr
    assert "WARNING clustering" not in stderr


@pytest.fixture(scope="module")
def truth_cameras(tabletop_dir: Path) -> dict:
    return json.loads((tabletop_dir / "truth" / "cameras.json").read_text())


def test_cameras_match_truth_in_marker_frame(reconstruction_dir: Path, truth_cameras: dict) -> None:
    transforms = json.loads((reconstruction_dir / "transforms.json").read_text())
    truth = {f["frame_index"]: np.array(f["world_from_cam"]) for f in truth_cameras["frames"]}
    centre_err_m, view_err_deg = [], []
    for frame in transforms["frames"]:
        estimate = np.array(frame["transform_matrix"]) @ OPENCV_FROM_OPENGL
        true = truth[frame["frame_index"]]
        centre_err_m.append(np.linalg.norm(estimate[:3, 3] - true[:3, 3]))
        view_err_deg.append(np.degrees(np.arccos(np.clip(estimate[:3, 2] @ true[:3, 2], -1, 1))))
    assert np.median(centre_err_m) <= 0.005, f"median centre error {np.median(centre_err_m) * 1000:.2f} mm"
    assert np.median(view_err_deg) <= 0.5, f"median view error {np.median(view_err_deg):.3f} deg"
    assert np.max(centre_err_m) <= 0.02  # no frame is far off either
    k = truth_cameras["intrinsics"]
    assert transforms["fl_x"] == pytest.approx(k["fx"], rel=0.01)
    assert transforms["cx"] == pytest.approx(k["cx"], abs=2.0) and transforms["cy"] == pytest.approx(k["cy"], abs=2.0)


def test_registration_and_frame_selection(reconstruction_dir: Path, truth_cameras: dict) -> None:
    report = json.loads((reconstruction_dir / "reconstruct.json").read_text())
    assert report["registration_rate"] >= 0.9
    assert report["frames_in_source"] == len(truth_cameras["frames"])
    # The sample plants two blurred and two near-duplicate frames; selection must drop exactly those.
    assert sorted(report["dropped_blurred"]) == sorted(truth_cameras["blurred_frames"])
    assert sorted(report["dropped_duplicate"]) == sorted(truth_cameras["duplicate_frames"])
    assert report["scale"]["source"] == "aruco" and report["scale"]["marker_views"] >= 10
    assert report["mean_reprojection_error_px"] < 1.0
    transforms = json.loads((reconstruction_dir / "transforms.json").read_text())
    assert len(transforms["frames"]) == report["frames_registered"]
    for frame in transforms["frames"]:
        assert (reconstruction_dir / frame["file_path"]).is_file()


def test_colmap_model_is_in_world_frame(reconstruction_dir: Path) -> None:
    rec = pycolmap.Reconstruction(reconstruction_dir / "sparse")
    points, cams = _points_and_cameras(rec)
    plane = fit_support_plane(points, cams)
    # Gravity-aligned: the dominant plane is z = 0 with +z towards the cameras (table top at z = 0).
    assert plane.normal[2] > np.cos(np.radians(0.3))
    assert abs(plane.offset) < 0.002
    assert np.all(cams[:, 2] > 0.2)


def test_table_plane_does_not_depend_on_the_ransac_draw(reconstruction_dir: Path) -> None:
    """The plane is refitted until its inliers settle, so RANSAC's seed (and Open3D's threads, which make one seed
    unrepeatable) do not move it: with two refits, seeds 0-3 kept 1433-1449 inliers of the sample's sparse points
    and the known-extent scale moved by 1%; here the inlier sets must agree within 0.5% (a few points of the
    1430 may settle either way; 20-46 did) and the normals within 0.015 deg (0.03-0.11 deg)."""
    rec = pycolmap.Reconstruction(reconstruction_dir / "sparse")
    points, cams = _points_and_cameras(rec)
    planes = [fit_support_plane(points, cams, seed=seed) for seed in range(4)]
    for plane in planes[1:]:
        assert (plane.inliers != planes[0].inliers).sum() <= 0.005 * planes[0].inliers.sum()
        assert np.degrees(np.arccos(min(1.0, float(plane.normal @ planes[0].normal)))) < 0.015


def test_known_extent_and_unknown_scale_on_the_same_model(reconstruction_dir: Path, tabletop_dir: Path) -> None:
    """The model is already metric, so --known-extent with the true largest extent must find scale ~1."""
    objects = json.loads((tabletop_dir / "truth" / "objects.json").read_text())["objects"]
    longest_m = max(max(o["extents_m"]) for o in objects)
    rec = pycolmap.Reconstruction(reconstruction_dir / "sparse")
    points, cams = _points_and_cameras(rec)
    plane = fit_support_plane(points, cams)
    world = world_from_extent(rec, plane, points, cams, longest_m)
    assert world.scale_source == ScaleSource.KNOWN_EXTENT
    assert world.scale == pytest.approx(1.0, rel=0.05)
    rotation = world.world_from_sfm[:3, :3] / world.scale
    assert rotation[2] @ np.array([0, 0, 1.0]) > np.cos(np.radians(0.3))
    unknown = world_unknown_scale(rec, plane, points)
    assert unknown.scale_source == ScaleSource.UNKNOWN and unknown.scale == 1.0

    # The same model moved by a known similarity (scale 0.37, turned 50 deg about a tilted axis, shifted), as SfM
    # could have returned it: the scale found is 1 / 0.37 of the metric model's, up is found again, and the cameras
    # land where the metric model put them. (A function that changed nothing would pass the checks above alone.)
    sfm_from_metric = pycolmap.Sim3d(0.37, pycolmap.Rotation3d(np.radians(50.0) * np.array([0.6, -0.48, 0.64])),
                                     np.array([0.3, -1.2, 2.0]))  # fmt: skip
    moved = pycolmap.Reconstruction(reconstruction_dir / "sparse")
    moved.transform(sfm_from_metric)
    moved_points, moved_cams = _points_and_cameras(moved)
    moved_world = world_from_extent(moved, fit_support_plane(moved_points, moved_cams), moved_points, moved_cams,
                                    longest_m)  # fmt: skip
    assert moved_world.scale == pytest.approx(world.scale / 0.37, rel=0.01)
    up_sfm = (moved_world.world_from_sfm[:3, :3] / moved_world.scale)[2]  # the world's z axis in SfM coordinates
    true_up_sfm = sfm_from_metric.rotation.matrix() @ rotation[2]
    assert np.degrees(np.arccos(np.clip(up_sfm @ true_up_sfm, -1, 1))) < 0.3
    cams_world = (world.world_from_sfm[:3, :3] @ cams.T).T + world.world_from_sfm[:3, 3]
    moved_cams_world = (moved_world.world_from_sfm[:3, :3] @ moved_cams.T).T + moved_world.world_from_sfm[:3, 3]
    assert np.abs(moved_cams_world - cams_world).max() < 5e-3


def test_known_extent_without_points_on_any_object_is_provisional_for_ground_only(reconstruction_dir: Path) -> None:
    """A plain object gives SfM no points (family seed 100: one low-texture cup): `reconstruct` alone refuses, with
    the way out; for `ground` (`extent_on_meshes`) the frame is the same gravity-aligned table frame, at a
    provisional scale that puts the cameras 0.6 m from the table's centre, to be measured on the meshes."""
    from reconstruction._world import NOMINAL_CAMERA_DISTANCE_M
    from reconstruction.errors import WorldFrameError

    rec = pycolmap.Reconstruction(reconstruction_dir / "sparse")
    points, cams = _points_and_cameras(rec)
    plane = fit_support_plane(points, cams)
    table_only = points[plane.inliers]  # the objects' points gone
    plane = fit_support_plane(table_only, cams)
    with pytest.raises(WorldFrameError, match="no cluster of points stands above the table plane"):
        world_from_extent(rec, plane, table_only, cams, 0.2)
    world = world_from_extent(rec, plane, table_only, cams, 0.2, provisional_ok=True)
    assert world.scale_provisional and world.scale_source == ScaleSource.KNOWN_EXTENT
    cams_world = cams @ world.world_from_sfm[:3, :3].T + world.world_from_sfm[:3, 3]
    table_world = table_only @ world.world_from_sfm[:3, :3].T + world.world_from_sfm[:3, 3]
    assert np.abs(table_world[:, 2]).max() < 0.01 and (cams_world[:, 2] > 0.1).all()  # on the table, cameras above
    distance = np.linalg.norm(cams_world - table_world.mean(axis=0), axis=1)
    assert np.median(distance) == pytest.approx(NOMINAL_CAMERA_DISTANCE_M, rel=0.01)
    assert not world_from_extent(
        rec, fit_support_plane(points, cams), points, cams, 0.2, provisional_ok=True
    ).scale_provisional


def test_real_apple_video_with_known_extent(grounded_apple: Path) -> None:
    """Transfer to a real handheld phone video: registration, gravity, and a plausible metric scale (the reconstruct
    stage's output inside the grounded apple scene, `reconstruction/`)."""
    rec_dir = grounded_apple / "reconstruction"
    report = json.loads((rec_dir / "reconstruct.json").read_text())
    assert report["registration_rate"] >= 0.9
    assert report["mean_reprojection_error_px"] < 1.0
    assert report["scale"]["source"] == ScaleSource.KNOWN_EXTENT
    transforms = json.loads((rec_dir / "transforms.json").read_text())
    assert len(transforms["frames"]) == report["frames_registered"]
    cams = np.array([np.array(f["transform_matrix"])[:3, 3] for f in transforms["frames"]])
    # A phone held over a countertop circling an apple: cameras above the table, tens of centimetres away.
    assert np.all(cams[:, 2] > 0.05)
    distance_m = np.median(np.linalg.norm(cams, axis=1))
    assert 0.15 < distance_m < 1.5, distance_m
    assert (rec_dir / "preview.png").is_file()


@pytest.mark.parametrize("kind", ["missing", "no_images", "fifo", "not_video"])
def test_check_source_names_what_is_wrong_before_any_work(tmp_path: Path, kind: str) -> None:
    import os

    from reconstruction._frames import check_source, read_frames
    from reconstruction.errors import InputError

    source = tmp_path / "source"
    expected = {
        "missing": "does not exist",
        "no_images": "holds no images",
        "fifo": "neither a video file nor a folder",
        "not_video": "is not a readable video",
    }[kind]
    if kind == "no_images":
        source.mkdir()
        (source / "notes.txt").write_text("no frames here")
    elif kind == "fifo":
        os.mkfifo(source)
    elif kind == "not_video":
        source.write_text("this is not a video")
    for reader in (check_source, read_frames):
        with pytest.raises(InputError, match=expected):
            reader(source)


def _sample_frames(images: Path, indices: Sequence[int], smaller_from: int | None = None) -> list[str]:
    """Writes frames ``indices`` of the tabletop sample into ``images`` as JPEGs and returns their names; from the
    ``smaller_from``-th on they are shrunk to 480 x 360 (frames of two sizes)."""
    import cv2

    images.mkdir()
    video = cv2.VideoCapture(str(Path(__file__).resolve().parents[2] / "samples" / "tabletop" / "video.mp4"))
    names = []
    for k, index in enumerate(indices):
        video.set(cv2.CAP_PROP_POS_FRAMES, index)
        ok, frame = video.read()
        assert ok
        names.append(f"frame_{index:05d}.jpg")
        small = smaller_from is not None and k >= smaller_from
        cv2.imwrite(str(images / names[-1]), cv2.resize(frame, (480, 360)) if small else frame)
    video.release()
    return names


def test_feature_extraction_shared_among_threads_writes_the_one_thread_database(tmp_path: Path) -> None:
    """COLMAP's SIFT (`SfmOptions.sift` "colmap"): seven frames of the sample, extracted by one pycolmap call, and
    in chunks (merged in order) by one thread (four chunks) and by three (seven): the COLMAP databases are the same
    to the last byte of every table, so neither the speed-up nor the chunks that give progress can change any
    reconstruction. Progress comes as chunks finish."""
    import sqlite3

    from reconstruction._sfm import EXTRACTION_CHUNKS_PER_WORKER, _extract_share, extract_features, sift_first_octave
    from reconstruction._types import SfmOptions

    images = tmp_path / "images"
    names = _sample_frames(images, range(0, 70, 10))
    one_call = tmp_path / "one_call.db"
    _extract_share(one_call, images, names, SfmOptions(), sift_first_octave(images, names, SfmOptions()))
    dumps = [list(sqlite3.connect(one_call).iterdump())]
    for workers in (1, 3):
        database = tmp_path / f"workers{workers}.db"
        seen: list[int] = []
        extract_features(database, images, names, SfmOptions(sift="colmap", extraction_workers=workers), seen.append)
        dumps.append(list(sqlite3.connect(database).iterdump()))
        chunks = min(len(names), workers * EXTRACTION_CHUNKS_PER_WORKER)  # 4 and 7 chunks
        assert seen == sorted(seen) and seen[-1] == len(names) and len(seen) == chunks, seen
    assert sorted(p.name for p in tmp_path.glob("*.db")) == ["one_call.db", "workers1.db", "workers3.db"]
    assert any('INSERT INTO "keypoints"' in line for line in dumps[0])
    assert dumps[0] == dumps[1] == dumps[2]


def test_feature_shares_that_cannot_merge_fall_back_to_one_thread(tmp_path: Path) -> None:
    """COLMAP's SIFT, frames of two sizes (the shares' cameras disagree): the shares are not merged; one thread
    extracts them, and the database is the one thread's."""
    import sqlite3

    from reconstruction._sfm import (
        UnmergeableSharesError,
        _extract_share,
        extract_features,
        merge_feature_databases,
        sift_first_octave,
    )
    from reconstruction._types import SfmOptions

    images = tmp_path / "images"
    names = _sample_frames(images, (0, 10, 20, 30), smaller_from=2)
    for name, share in (("a.db", names[:2]), ("b.db", names[2:])):
        extract_features(tmp_path / name, images, share, SfmOptions(sift="colmap", extraction_workers=1))
    with pytest.raises(UnmergeableSharesError, match="cameras"):
        merge_feature_databases([tmp_path / "a.db", tmp_path / "b.db"], tmp_path / "merged.db")
    one_call = tmp_path / "one_call.db"
    _extract_share(one_call, images, names, SfmOptions(), sift_first_octave(images, names, SfmOptions()))
    dumps = [list(sqlite3.connect(one_call).iterdump())]
    for workers in (1, 2):
        database = tmp_path / f"workers{workers}.db"
        extract_features(database, images, names, SfmOptions(sift="colmap", extraction_workers=workers))
        dumps.append(list(sqlite3.connect(database).iterdump()))
    assert dumps[0] == dumps[1] == dumps[2]
    assert not list(tmp_path.glob("*.share*"))


def test_opencv_sift_writes_the_same_database_on_any_number_of_threads(tmp_path: Path) -> None:
    """OpenCV's SIFT (`SfmOptions.sift` "opencv"): seven frames of the sample extracted by one thread and by three
    give the same database, every table; one camera, every frame, a few hundred keypoints each in COLMAP's pixels,
    RootSIFT descriptors (unit length once divided by 512, up to the rounding); progress frame by frame."""
    import sqlite3

    import pycolmap

    from reconstruction._sfm import extract_features
    from reconstruction._types import SfmOptions

    images = tmp_path / "images"
    names = _sample_frames(images, range(0, 70, 10))
    dumps = []
    for workers in (1, 3):
        database = tmp_path / f"workers{workers}.db"
        seen: list[int] = []
        extract_features(database, images, names, SfmOptions(sift="opencv", extraction_workers=workers), seen.append)
        assert seen == list(range(1, len(names) + 1))
        dumps.append(list(sqlite3.connect(database).iterdump()))
    assert any('INSERT INTO "keypoints"' in line for line in dumps[0])
    assert dumps[0] == dumps[1]
    with contextlib.closing(pycolmap.Database.open(tmp_path / "workers1.db")) as db:
        assert db.num_cameras() == 1 and sorted(i.name for i in db.read_all_images()) == names
        for image in db.read_all_images():
            keypoints = db.read_keypoints(image.image_id)
            descriptors = db.read_descriptors(image.image_id).data.astype(float) / 512
            assert 200 < len(keypoints) <= SfmOptions().max_num_features
            assert keypoints[:, 0].min() >= 0 and keypoints[:, 0].max() <= 640
            assert keypoints[:, 1].min() >= 0 and keypoints[:, 1].max() <= 480
            np.testing.assert_allclose(np.linalg.norm(descriptors, axis=1), 1.0, atol=0.03)


@pytest.mark.parametrize(("size", "max_px", "octave"), [((640, 480), 1024, -1), ((1296, 972), 1024, 0)])
def test_opencv_sift_puts_a_blob_where_colmap_would(
    tmp_path: Path, size: tuple[int, int], max_px: int, octave: int
) -> None:
    """A dark Gaussian blob on a light frame, centred at (301.5, 207.5) in COLMAP's pixels (the centre of pixel
    (301, 207)): a keypoint sits on it within a tenth of a pixel at the frame's size, whether SIFT saw the frame
    doubled (a small frame) or scaled down to `max_image_size_px` and not doubled (a phone frame). (OpenCV's default
    upscaling put it 0.24 px off, down and to the right: hence its precise upscaling.)"""
    import cv2

    from reconstruction._opencv_sift import frame_features
    from reconstruction._types import SfmOptions

    width, height = size
    scale = width / 640
    centre_cv = (301.0 * scale + 0.5 * (scale - 1), 207.0 * scale + 0.5 * (scale - 1))  # pixel (301, 207)'s centre
    grid_y, grid_x = np.mgrid[0:height, 0:width]
    squared = (grid_x - centre_cv[0]) ** 2 + (grid_y - centre_cv[1]) ** 2
    frame = np.round(220 - 180 * np.exp(-squared / (2 * (4 * scale) ** 2))).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "blob.png"), frame)
    points, descriptors = frame_features(tmp_path / "blob.png", SfmOptions(max_image_size_px=max_px), octave)
    assert len(points) >= 1 and descriptors.shape == (len(points), 128) and descriptors.dtype == np.uint8
    expected = np.array([centre_cv[0] + 0.5, centre_cv[1] + 0.5])
    nearest = points[np.argmin(np.linalg.norm(points[:, :2] - expected, axis=1))]
    assert np.linalg.norm(nearest[:2] - expected) < 0.1 * scale, (nearest, expected)


@pytest.mark.parametrize(("frames", "sequential"), [(range(0, 60, 3), True), (range(0, 60, 10), False)])
def test_matching_shared_among_processes_writes_the_one_thread_database(
    tmp_path: Path, frames: range, sequential: bool
) -> None:
    """Twenty frames of the sample matched sequentially with loop detection (the pairing lists some pairs twice),
    and six matched exhaustively, by one thread and in three shares of pairs, each matched in chunks by a worker
    process: the matches and two-view geometries are the same to the last byte, so the speed-up cannot change any
    reconstruction; no share is left behind; progress comes chunk by chunk, up to every pair listed. (The shares
    were matched in threads, and about one run in ten here, and one CI run, gave a pair a keypoint match more or
    less: pycolmap's matching is not safe to run in several threads of one process.)"""
    import sqlite3

    from reconstruction._sfm import extract_features, match_features
    from reconstruction._types import SfmOptions

    images = tmp_path / "images"
    names = _sample_frames(images, frames)
    features = tmp_path / "features.db"
    extract_features(features, images, names, SfmOptions())
    dumps = []
    for workers in (1, 3):
        database = tmp_path / f"workers{workers}.db"
        shutil.copyfile(features, database)
        work = tmp_path / f"work{workers}"
        work.mkdir()
        seen: list[tuple[int, int]] = []
        options = SfmOptions(matching_workers=workers)
        match_features(
            database,
            len(names),
            sequential=sequential,
            options=options,
            work_dir=work,
            progress=lambda done, pairs, seen=seen: seen.append((done, pairs)),
        )
        if workers > 1:  # in chunks, each reported as it finishes; one worker is one COLMAP call
            assert [done for done, _ in seen] == sorted(done for done, _ in seen) and len(seen) > workers, seen
            assert seen[-1][0] == seen[-1][1] > len(names) - 2, seen
        dumps.append([line for line in sqlite3.connect(database).iterdump() if "matches" in line or "two_view" in line])
        assert {p.name for p in work.iterdir()} <= {"vocab_tree.bin"}
    assert sorted(p.name for p in tmp_path.glob("*.db")) == ["features.db", "workers1.db", "workers3.db"]
    verified = [line for line in dumps[0] if line.startswith('INSERT INTO "two_view_geometries"')]
    # exhaustive: every pair; sequential: at least each frame with its next (the sample's frames all overlap)
    assert len(verified) >= (len(names) * (len(names) - 1) // 2 if not sequential else len(names) - 1), len(verified)
    assert dumps[0] == dumps[1]


def test_a_matching_worker_that_fails_is_one_error_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker process that dies (out of memory, a COLMAP check) is a ReconstructionError with its exit status and
    the last of what it printed, not a hang or a silently short table; its log file is removed."""
    from reconstruction import _sfm
    from reconstruction.errors import ReconstructionError

    monkeypatch.setattr(_sfm, "_MATCH_SHARE_CHILD", "import sys; sys.stderr.write('Check failed: x\\n'); sys.exit(3)")
    ticks: list[int] = []
    with pytest.raises(ReconstructionError, match=r"process \(exit status 3, 0 of 1 chunks done\): Check failed: x"):
        _sfm._match_share_in_process(
            tmp_path / "part.db",
            [tmp_path / "pairs0.txt"],
            [7],
            pycolmap.FeatureMatchingOptions(),
            pycolmap.TwoViewGeometryOptions(),
            ticks.append,
        )
    assert ticks == [] and list(tmp_path.iterdir()) == []
    # One that exits cleanly without doing every chunk would leave its share short, merged as if complete.
    monkeypatch.setattr(_sfm, "_MATCH_SHARE_CHILD", "print('first chunk', flush=True)")
    with pytest.raises(ReconstructionError, match=r"exit status 0, 1 of 2 chunks done"):
        _sfm._match_share_in_process(
            tmp_path / "part.db",
            [tmp_path / "pairs0.txt", tmp_path / "pairs1.txt"],
            [7, 5],
            pycolmap.FeatureMatchingOptions(),
            pycolmap.TwoViewGeometryOptions(),
            ticks.append,
        )
    assert ticks == [7] and list(tmp_path.iterdir()) == []


def test_a_stopping_run_ends_its_matching_worker_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """When the run stops (Ctrl-C, SIGTERM, another share failing) the next progress tick raises; the worker process
    is then killed rather than left to match the rest of its share (or to outlive the command)."""
    import os
    import time

    from reconstruction import _sfm

    pid_file = tmp_path / "pid"
    child = f"import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); print('one', flush=True); "
    child += "time.sleep(60)"
    monkeypatch.setattr(_sfm, "_MATCH_SHARE_CHILD", child)

    def tick(_pairs: int) -> None:
        raise KeyboardInterrupt

    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        _sfm._match_share_in_process(
            tmp_path / "part.db",
            [tmp_path / "a.txt", tmp_path / "b.txt"],
            [3, 4],
            pycolmap.FeatureMatchingOptions(),
            pycolmap.TwoViewGeometryOptions(),
            tick,
        )
    assert time.monotonic() - start < 20  # not the child's 60 s
    pid = int(pid_file.read_text())
    with pytest.raises(ProcessLookupError):  # killed and reaped
        os.kill(pid, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pid"]


def test_loop_detection_index_is_the_same_on_every_build_in_one_process(
    reconstruction_dir: Path, tmp_path: Path
) -> None:
    """The vocabulary tree's k-means draws from COLMAP's process-wide generator. Unseeded, a second build in the same
    process (as a second `reconstruct` call would make) came out different, and with it the loops closed and the
    model (4662 against 4665 points). Built twice from the sample's database, with other draws between: identical.
    (Three builds on two threads gave three indexes on a 2-core AMD EPYC: the build runs on one.)"""
    import hashlib

    import pycolmap

    from reconstruction._sfm import build_vocab_tree

    database = reconstruction_dir / "colmap" / "database.db"
    digests = []
    for i in range(2):
        pycolmap.set_random_seed(1234 + i)  # some other COLMAP call left the generator elsewhere
        index = build_vocab_tree(database, tmp_path / f"tree{i}.bin")
        digests.append(hashlib.sha256(index.read_bytes()).hexdigest())
    assert digests[0] == digests[1]
    other_seed = build_vocab_tree(database, tmp_path / "tree_seed1.bin", seed=1)
    assert hashlib.sha256(other_seed.read_bytes()).hexdigest() != digests[0]  # the seed is what fixes it


def test_staged_output_dir_edge_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`-o .` (was: the whole run, then "PosixPath('.') has an empty name"); an output folder gets the user's usual
    permissions (mkdtemp made them owner-only); a failed run removes the parent folders it created; a location
    that cannot be created is one InputError (was a FileNotFoundError traceback)."""
    import os
    import stat

    from reconstruction import staged_output_dir
    from reconstruction.errors import InputError

    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    with staged_output_dir(Path("."), error=InputError) as stage:
        (stage / "result.txt").write_text("done")
    assert (tmp_path / "here" / "result.txt").read_text() == "done"
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "here").stat().st_mode) == 0o777 & ~umask
    with pytest.raises(RuntimeError), staged_output_dir(tmp_path / "new" / "a" / "out", error=InputError):
        raise RuntimeError("the work failed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here"]
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match=r"cannot create the output folder .*: .*file is a file, not a folder"):
        with staged_output_dir(tmp_path / "file" / "o", error=InputError):
            pass


def test_an_output_folder_that_cannot_move_is_refused_early_or_keeps_the_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A mount point (a Docker volume, say) cannot be renamed: it was a Device-busy traceback after all the work,
    and the result thrown away. Now it is refused before the work; and a folder that cannot be moved for another
    reason (made immutable, or created meanwhile) is one error that names where the complete result is kept."""
    import os

    from reconstruction import check_output_dir, staged_output_dir
    from reconstruction.errors import InputError

    volume = tmp_path / "volume"
    volume.mkdir()
    real_ismount = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == volume or real_ismount(p))
    with pytest.raises(InputError, match=f"is a mount point.*-o {volume / 'out'}"):
        check_output_dir(volume, error=InputError)
    monkeypatch.setattr(os.path, "ismount", real_ismount)

    users = tmp_path / "users"
    users.mkdir()
    (users / "notes.txt").write_text("mine")
    (users / "reconstruct.json").write_text("{}")  # an earlier output: --overwrite may replace it
    real_rename = Path.rename

    def busy_rename(self: Path, target: str | Path) -> Path:
        if self == users:
            raise OSError(16, "Device or resource busy")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", busy_rename)
    with pytest.raises(InputError, match=r"cannot move the result into .*Device or resource busy.*kept, complete, in"):
        with staged_output_dir(users, overwrite=True, error=InputError) as stage:
            (stage / "result.txt").write_text("done")
    assert (users / "notes.txt").read_text() == "mine"  # the user's folder is as it was
    assert (users / "reconstruct.json").read_text() == "{}"
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("users.image2sim-")]
    assert len(kept) == 1 and (kept[0] / "result.txt").read_text() == "done"


@pytest.mark.parametrize("side_px", [10_000, 20_000])
def test_image_bombs_beyond_pillows_limits_are_one_error(tmp_path: Path, side_px: int) -> None:
    """A PNG header of 20000 x 20000 px (over Pillow's own error limit, 179 Mpx) was a DecompressionBombError
    traceback; one of 10000 x 10000 (over its warning limit, 89 Mpx) printed Pillow's two-line warning before the
    refusal. Both are now the one refusal of a frame over 50 Mpx, and nothing else."""
    import struct
    import warnings
    import zlib

    from reconstruction._frames import read_frames
    from reconstruction.errors import InputError

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    folder = tmp_path / "frames"
    folder.mkdir()
    header = struct.pack(">IIBBBBB", side_px, side_px, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    (folder / "0.png").write_bytes(png)  # a few dozen bytes
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(InputError, match=r"0\.png is (10000x10000 px, more|larger) than the 50 Mpx a frame may"):
            read_frames(folder)
    assert not caught, [str(w.message) for w in caught]


def test_read_frames_bounds_memory_and_refuses_image_bombs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A long video used to be decoded whole before --max-frames applied (4 GB for 20 s of 1080p), and a 0.9 MB PNG
    of 30000 x 30000 px was decoded (10.8 GB). Now the frames kept stay within the byte budget, evenly spread with
    their source indices and the source's count, and an image larger than the pixel limit is refused from its
    header, before decoding."""
    import cv2

    import reconstruction._frames as frames_module
    from reconstruction._frames import read_frames_counted
    from reconstruction.errors import InputError

    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(40):  # named so that string order would differ from the natural order
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 255, (24, 32, 3), np.uint8))
    one_frame = 24 * 32 * 3
    steps: list[tuple[int, int]] = []
    frames, count = read_frames_counted(folder, lambda d, t: steps.append((d, t)), max_bytes=10 * one_frame)
    assert count == 40 and steps[-1] == (40, 40)
    assert [f.index for f in frames] == list(range(0, 40, 4))  # thinned twice: every 4th frame, from the first
    assert [f.name for f in frames] == [f"{i}.png" for i in range(0, 40, 4)]
    np.testing.assert_array_equal(frames[3].image_bgr, cv2.imread(str(folder / "12.png")))
    assert sum(f.image_bgr.nbytes for f in frames) <= 10 * one_frame
    monkeypatch.setattr(frames_module, "MAX_IMAGE_PIXELS", 700)
    with pytest.raises(InputError, match=r"0\.png is 32x24 px, more than"):
        read_frames_counted(folder)


def test_dense_stereo_on_several_threads_fuses_what_one_thread_fuses(
    truth_cameras: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sample's first 24 frames (less its two duplicates) at their true poses, fused one at a time and three ahead
    on other threads: the same depth maps, TSDF and surface to the bit. Once from 8 stereo pairs alone (``min_pairs``
    0), once with the plane sweep's depth maps beside a few pairs (every second frame at half size: the sweep is what a
    photo set gets, and at full size on all 22 frames it took 6 minutes of the test run)."""
    import cv2

    from reconstruction import _dense
    from reconstruction._sweep import SweepOptions
    from reconstruction._types import CameraIntrinsics

    truth = {f["frame_index"]: np.array(f["world_from_cam"]) for f in truth_cameras["frames"]}
    video = cv2.VideoCapture(str(Path(__file__).resolve().parents[2] / "samples" / "tabletop" / "video.mp4"))
    views = []
    for index in range(24):
        ok, frame = video.read()
        assert ok
        if index not in truth_cameras["duplicate_frames"]:
            views.append(_dense.StereoView(image_bgr=frame, world_from_cam=truth[index]))
    video.release()
    i = truth_cameras["intrinsics"]
    intrinsics = CameraIntrinsics(
        width_px=i["width"], height_px=i["height"], fx_px=i["fx"], fy_px=i["fy"], cx_px=i["cx"], cy_px=i["cy"]
    )
    roi = _dense.RegionOfInterest(min_world=np.array([-0.35, -0.3, -0.02]), max_world=np.array([0.35, 0.3, 0.2]))
    stereo_only = _dense.DenseOptions(num_reference_views=8, min_pairs=0)
    with_sweep = _dense.DenseOptions(
        num_reference_views=8, max_image_size_px=320, sweep=SweepOptions(num_planes=48, table_planes=32)
    )
    for options, subset, min_maps in ((stereo_only, views, 6), (with_sweep, views[::2], 13)):
        fused = []
        for cores in (1, 3):
            monkeypatch.setattr(_dense, "usable_cores", lambda cores=cores: cores)
            fused.append(_dense.fuse_views(subset, intrinsics, roi, options))
        one, many = fused
        assert len(one.depth_maps) >= min_maps and len(one.faces) > 1000
        assert one.num_pairs == many.num_pairs and len(one.depth_maps) == len(many.depth_maps)
        for name in ("vertices_world", "faces", "vertex_rgb", "tsdf_voxels", "tsdf_values"):
            np.testing.assert_array_equal(getattr(one, name), getattr(many, name), err_msg=name)
        for a, b in zip(one.depth_maps, many.depth_maps, strict=True):
            np.testing.assert_array_equal(a.depth, b.depth)


def test_an_image_that_cannot_be_written_is_one_error(tmp_path: Path) -> None:
    """cv2.imwrite returns False on a full disk or a missing folder; ignored, reconstruct went on and failed inside
    COLMAP with "No registered database factory succeeded". Now the write itself fails, naming the file."""
    from image2sim_common.outdir import write_image
    from reconstruction.errors import InputError

    image = np.zeros((8, 8, 3), np.uint8)
    write_image(tmp_path / "ok.png", image, error=InputError)
    assert (tmp_path / "ok.png").stat().st_size > 0
    with pytest.raises(InputError, match=r"could not write .*gone[/\\]frame\.jpg \(disk full"):
        write_image(tmp_path / "gone" / "frame.jpg", image, error=InputError)


def test_sift_doubles_only_frames_too_small_for_enough_features(tmp_path: Path) -> None:
    """SIFT's first octave works on the doubled frame below `SfmOptions.upsample_below_px` (after the
    `max_image_size_px` cap) and on the frame itself above it, decided by the smallest frame; the choice reaches
    COLMAP (the doubled octave finds more keypoints on the same frame)."""
    import sqlite3

    import cv2

    from reconstruction._sfm import extract_features, sift_first_octave
    from reconstruction._types import SfmOptions

    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (720, 1296), dtype=np.uint8), (0, 0), 3)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "phone.png"), texture)
    cv2.imwrite(str(images / "small.png"), cv2.resize(texture, (640, 360), interpolation=cv2.INTER_AREA))
    options = SfmOptions()
    assert sift_first_octave(images, ["phone.png"], options) == 0  # 1296 px, SIFT at 1024 px: not doubled
    assert sift_first_octave(images, ["small.png"], options) == -1
    assert sift_first_octave(images, ["phone.png", "small.png"], options) == -1  # the smallest frame decides
    assert sift_first_octave(images, ["phone.png"], SfmOptions(max_image_size_px=800)) == -1  # SIFT's size counts

    counts = []
    for below_px in (1000, 2000):  # the phone frame at its own size, then doubled
        database = tmp_path / f"below{below_px}.db"
        options = SfmOptions(upsample_below_px=below_px, max_num_features=20000)
        extract_features(database, images, ["phone.png"], options)
        with sqlite3.connect(database) as db:
            counts.append(db.execute("SELECT rows FROM keypoints").fetchone()[0])
    assert counts[1] > 1.2 * counts[0], counts


def test_importing_reconstruction_keeps_opencv_png_writing_alive(tmp_path: Path) -> None:
    """pycolmap loaded before cv2 makes OpenCV's first PNG write abort the process (double free in zlib: the two
    carry their own copies). The package loads cv2 first, so the README's API snippet (`from reconstruction
    import ...`, then a grounding that writes PNGs) runs; a user's own earlier `import pycolmap` gets a warning."""
    png = tmp_path / "x.png"
    write = f"import numpy as np, cv2; assert cv2.imwrite({str(png)!r}, np.zeros((48, 64, 3), np.uint8))"
    first = subprocess.run(
        [sys.executable, "-c", f"import reconstruction, pycolmap; {write}"],
        capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    assert png.is_file()
    late = subprocess.run(
        [sys.executable, "-W", "always", "-c", "import pycolmap, reconstruction"],
        capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[2],
    )  # fmt: skip
    assert late.returncode == 0 and "pycolmap was imported before cv2" in late.stderr, late.stderr[-2000:]


def test_atomic_file_is_whole_or_absent(tmp_path: Path) -> None:
    """The one temporary-file-then-rename writer every atomic file write uses (reports, trajectories, batch
    records, the CoACD cache): an error inside leaves the old file as it was and no temporary file behind."""
    from image2sim_common.outdir import atomic_file

    path = tmp_path / "record.json"
    with atomic_file(path, "w") as handle:
        handle.write("first")
    assert path.read_text() == "first"
    with pytest.raises(RuntimeError, match="half way"), atomic_file(path, "w") as handle:
        handle.write("second, cut short")
        raise RuntimeError("half way")
    assert path.read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record.json"]
    with atomic_file(tmp_path / "arrays.npz") as handle:
        np.savez(handle, a=np.arange(3))
    assert np.load(tmp_path / "arrays.npz")["a"].tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="expected 'wb' or 'w'"), atomic_file(path, "a"):
        pass


def test_photos_are_not_dropped_as_blurred_or_duplicate_neighbours(tabletop_dir: Path) -> None:
    """Unordered stills (issue 60): a photo much softer than the ones next to it by name, and two photos of nearly
    the same view, all go to structure from motion; the same frames as a video drop both. Written against the old
    selection, which treated a folder's name order as time and dropped them."""
    import cv2

    from reconstruction import Frame, select_frames
    from reconstruction._types import FrameSelectionOptions

    capture = cv2.VideoCapture(str(tabletop_dir / "video.mp4"))
    images = []
    while len(images) < 12:
        ok, image = capture.read()
        assert ok
        images.append(image)
    capture.release()
    images[6] = cv2.GaussianBlur(images[6], (0, 0), 4.0)  # much softer than its neighbours
    images[9] = images[8].copy()  # the same view twice
    frames = [Frame(index=i, name=f"IMG_{i:04d}.jpg", image_bgr=im) for i, im in enumerate(images)]
    options = FrameSelectionOptions()
    as_video = select_frames(frames, options)
    assert 6 in as_video.blurred and 9 in as_video.duplicate
    as_photos = select_frames(frames, options, ordered=False)
    assert [f.index for f in as_photos.kept] == list(range(12))
    assert as_photos.blurred == () and as_photos.duplicate == ()


def _orbit_views(azimuths_deg: Sequence[float], radius_m: float = 0.6, height_m: float = 0.4) -> list:
    from reconstruction._dense import StereoView

    views = []
    for az in np.deg2rad(azimuths_deg):
        eye = np.array([radius_m * np.cos(az), radius_m * np.sin(az), height_m])
        forward = -eye / np.linalg.norm(eye)
        x = np.cross(forward, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(forward, x)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, y, forward], axis=1)  # OpenCV axes: x right, y down, z forward
        pose[:3, 3] = eye
        views.append(StereoView(image_bgr=np.zeros((4, 4, 3), np.uint8), world_from_cam=pose))
    return views


def test_sparse_stills_get_wide_baseline_stereo_pairs_and_a_video_does_not() -> None:
    """Issue 60: stills 24 deg apart (baseline / distance 0.42) have no partner in the video range (0.08-0.25),
    so the old pairing gave a photo set no depth at all; now they pair in the wide range. A video orbit, 5 deg
    apart, is paired exactly as before."""
    from reconstruction._dense import DenseOptions, choose_pairs

    options = DenseOptions()
    stills = _orbit_views(np.arange(0, 360, 24))
    pairs = choose_pairs(stills, np.zeros(3), options)
    assert len(pairs) >= 10
    narrow = DenseOptions(min_pairs=0)  # the wide range switched off: the old pairing
    assert choose_pairs(stills, np.zeros(3), narrow) == []
    video = _orbit_views(np.arange(0, 360, 5))
    assert choose_pairs(video, np.zeros(3), options) == choose_pairs(video, np.zeros(3), narrow)


def test_photo_folders_get_colmaps_feature_budget() -> None:
    from reconstruction._types import SfmOptions

    photos = SfmOptions().for_photos()
    assert (photos.max_num_features, photos.max_image_size_px) == (8192, 2048)
    assert SfmOptions(max_num_features=10000).for_photos().max_num_features == 10000  # never fewer


def test_an_unreadable_video_is_quiet_after_a_good_one(tmp_path: Path, tabletop_dir: Path) -> None:
    """OpenCV reads FFmpeg's log level once per process, at its first capture: the level set around each of our
    opens did nothing once anything else in the process (a test, a library) had opened a video first, and an
    unreadable clip then printed "moov atom not found" beside the one error line (a CLI test failed or passed by
    the order its worker ran tests in). In a fresh process: a plain OpenCV capture first, then ours."""
    junk = tmp_path / "junk.mp4"
    junk.write_text("this is not a video")
    code = (
        "import cv2; from pathlib import Path; from reconstruction._frames import open_video\n"
        f"cv2.VideoCapture({str(tabletop_dir / 'video.mp4')!r}).release()\n"
        f"assert not open_video(Path({str(junk)!r})).isOpened()\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "moov atom" not in run.stderr, run.stderr


def test_views_that_give_no_depth_are_one_error_not_an_open3d_crash() -> None:
    """Family photo set 1016 (issue 60): 23 stills, one stereo pair found and nothing of it in the box; Open3D then
    refused to extract a surface from the empty grid (RuntimeError: "Input number of keys should > 0", exit 1,
    an internal error). Now it is the stage's error a user can act on."""
    from reconstruction._dense import DenseOptions, RegionOfInterest, fuse_views
    from reconstruction._types import CameraIntrinsics
    from reconstruction.errors import DenseError

    views = _orbit_views([0.0, 90.0, 180.0, 270.0])  # no two close enough to pair
    intrinsics = CameraIntrinsics(width_px=4, height_px=4, fx_px=4.0, fy_px=4.0, cx_px=2.0, cy_px=2.0)
    roi = RegionOfInterest(min_world=np.array([-0.1, -0.1, 0.0]), max_world=np.array([0.1, 0.1, 0.1]))
    with pytest.raises(DenseError, match="no stereo pair"):
        fuse_views(views, intrinsics, roi, DenseOptions())
