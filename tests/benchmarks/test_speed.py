"""The camera scoring behind `benchmarks/speed.py`: centres matched to the truth by frame index, errors after a
similarity alignment (zero for a model that is the truth moved, turned and scaled; the displacement of a moved
camera otherwise), and errors in the marker frame taken as they are."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from image2sim_common.rotations import quat_to_mat

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from speed import aligned_errors_mm, direct_errors_mm, frame_index, true_centres


def _truth(tmp_path: Path, centres: dict[int, np.ndarray]) -> Path:
    frames = []
    for index, centre in centres.items():
        pose = np.eye(4)
        pose[:3, 3] = centre
        frames.append({"frame_index": index, "world_from_cam": pose.tolist()})
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"frames": frames}))
    return path


def test_centres_are_scored_by_frame_index_after_a_similarity(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    truth = {3 * k: rng.normal(scale=0.3, size=3) for k in range(12)}
    loaded = true_centres(_truth(tmp_path, truth))
    assert set(loaded) == set(truth)
    rot = quat_to_mat(np.array([0.8, 0.2, -0.4, 0.4]) / np.linalg.norm([0.8, 0.2, -0.4, 0.4]))
    # the model: the truth in another frame (turned, scaled by 3, moved), one frame missing, one extra
    found = {k: 3.0 * rot @ c + np.array([1.0, -2.0, 0.5]) for k, c in loaded.items() if k != 0}
    found[99] = np.zeros(3)
    assert np.max(aligned_errors_mm(found, loaded)) == pytest.approx(0.0, abs=1e-6)
    assert len(aligned_errors_mm(found, loaded)) == 11
    # one camera 4 mm off in the model's units (x 3): about 4 mm off after the alignment, the others far less
    moved = dict(found)
    moved[9] = moved[9] + rot @ np.array([0.012, 0.0, 0.0])
    errors = aligned_errors_mm(moved, loaded)
    assert 3.0 < errors.max() < 4.0 and np.median(errors) < 0.5
    # in the marker frame nothing is aligned: the frame change itself is the error
    assert direct_errors_mm(found, loaded).min() > 100.0
    assert direct_errors_mm(loaded, loaded).max() == 0.0


def test_frame_index_comes_from_reconstructs_image_names() -> None:
    assert frame_index("frame_00042.jpg") == 42
    with pytest.raises(ValueError, match="IMG_1234"):
        frame_index("IMG_1234.jpg")
