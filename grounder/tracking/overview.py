"""`overview.png` of a `track` run: what was tracked where, to look at rather than read from `track.json`.

Top: up to eight frames of the clip, evenly spread, each with every tracked object's outline at its tracked pose
(the grounded mesh rendered there), in the object's colour, with the object's name where it is tracked. Bottom: one
row per object over every frame of the clip: green where tracked by the model, blue where measured by a marker on
it, grey where the backward pass extrapolated it, red where lost (hidden, out of view, rejected). A reader sees at a
glance whether the outlines sit on the objects and which frames calibration may use.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from grounder.tracking.render import PinholeCamera, PoseRenderer

OBJECT_COLOURS_BGR = ((0, 200, 255), (255, 120, 0), (80, 220, 80), (200, 80, 255), (0, 80, 255), (255, 255, 0))
STATUS_COLOURS_BGR = {
    "track": (60, 180, 60),
    "detect": (60, 180, 60),
    "marker": (220, 120, 30),
    "track_backwards": (150, 150, 150),
    "lost": (40, 40, 220),
}
_TILES = 8
_ROW_PX = 14


def status_rows(sources: np.ndarray, width_px: int) -> np.ndarray:
    """(N * _ROW_PX, width_px, 3) uint8: one coloured row per object, one column band per frame (`sources` (F, N))."""
    frames, count = sources.shape
    out = np.full((count * _ROW_PX, width_px, 3), 255, np.uint8)
    edges = np.linspace(0, width_px, frames + 1).round().astype(int)
    for i in range(count):
        for f in range(frames):
            colour = STATUS_COLOURS_BGR.get(str(sources[f, i]), STATUS_COLOURS_BGR["lost"])
            out[i * _ROW_PX + 1 : (i + 1) * _ROW_PX - 1, edges[f] : max(edges[f + 1], edges[f] + 1)] = colour
    return out


def track_overview(
    frames_bgr: Sequence[np.ndarray],
    scene_xml: Path,
    camera: PinholeCamera,
    world_from_cam: np.ndarray,
    world_from_objects: np.ndarray,
    valid: np.ndarray,
    sources: np.ndarray,
    names: Sequence[str],
    first_frame: int,
) -> np.ndarray:
    """The overview image (BGR uint8): tiles of outlined frames over the per-object status rows (module docstring).

    Args:
        frames_bgr: the clip's undistorted frames that were tracked.
        world_from_cam: (F, 4, 4) camera poses (NaN where unknown).
        world_from_objects: (F, N, 4, 4) tracked poses; valid: (F, N); sources: (F, N) `FrameScore.source`.
        first_frame: the clip index of frames_bgr[0], for the captions.
    """
    count = len(frames_bgr)
    picks = np.unique(np.linspace(0, count - 1, min(_TILES, count)).round().astype(int))
    tiles = []
    scale = 0.5
    with PoseRenderer(scene_xml, camera) as renderer:
        for f in picks:
            image = frames_bgr[f].copy()
            if np.isfinite(world_from_cam[f]).all():
                renderer.set_camera(world_from_cam[f])
                poses = [world_from_objects[f, i] if valid[f, i] else None for i in range(len(names))]
                view = renderer.render(poses, rgb=False)
                for i, name in enumerate(names):
                    if not valid[f, i]:
                        continue
                    colour = OBJECT_COLOURS_BGR[i % len(OBJECT_COLOURS_BGR)]
                    mask = (view.object_id == i).astype(np.uint8)
                    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                    cv2.drawContours(image, contours, -1, colour, 2)
                    ys, xs = np.nonzero(mask)
                    if len(xs):
                        cv2.putText(image, name, (int(xs.min()), max(12, int(ys.min()) - 4)), 0, 0.5, colour, 1)
            small = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            cv2.putText(small, f"frame {first_frame + int(f)}", (6, 16), 0, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(small)
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.vstack([np.hstack(tiles[k : k + 4]) for k in range(0, len(tiles), 4)])
    width = grid.shape[1]
    label_px = 110
    rows = status_rows(sources, width - label_px)
    labelled = np.full((rows.shape[0], width, 3), 255, np.uint8)
    labelled[:, label_px:] = rows
    for i, name in enumerate(names):
        colour = OBJECT_COLOURS_BGR[i % len(OBJECT_COLOURS_BGR)]
        cv2.putText(labelled, name, (4, (i + 1) * _ROW_PX - 3), 0, 0.4, colour, 1, cv2.LINE_AA)
    legend = np.full((20, width, 3), 255, np.uint8)
    x = 4
    for text, key in (
        ("tracked", "track"),
        ("marker", "marker"),
        ("extrapolated back", "track_backwards"),
        ("lost", "lost"),
    ):
        cv2.rectangle(legend, (x, 5), (x + 12, 15), STATUS_COLOURS_BGR[key], -1)
        cv2.putText(legend, text, (x + 16, 15), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        x += 30 + 8 * len(text)
    caption = f"frames {first_frame}-{first_frame + count - 1}, left to right"
    cv2.putText(legend, caption, (x + 10, 15), 0, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([grid, legend, labelled])
