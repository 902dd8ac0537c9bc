"""A picture of a reconstruction: sparse points and cameras seen from above and from the side, in the world frame.

Drawn with OpenCV so the package needs no plotting library.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from image2sim_common.outdir import write_image
from reconstruction._types import ReconstructionResult
from reconstruction.errors import InputError

PANEL_PX = 480


def _panel(
    points: np.ndarray, colours_bgr: np.ndarray, cams: np.ndarray, looks: np.ndarray, axes: tuple[int, int], title: str
) -> np.ndarray:
    image = np.full((PANEL_PX, PANEL_PX, 3), 250, np.uint8)
    # Points may hold far strays (trim them); every camera stays in the picture.
    lo = np.minimum(np.percentile(points[:, axes], 1, axis=0), cams[:, axes].min(axis=0))
    hi = np.maximum(np.percentile(points[:, axes], 99, axis=0), cams[:, axes].max(axis=0))
    centre, half = (lo + hi) / 2, 0.55 * float(np.max(hi - lo))

    def px(xy: np.ndarray) -> np.ndarray:
        uv = (xy - centre) / half * (PANEL_PX / 2) + PANEL_PX / 2
        return np.stack([uv[..., 0], PANEL_PX - uv[..., 1]], axis=-1).round().astype(np.int32)

    for (u, v), colour in zip(px(points[:, axes]), colours_bgr, strict=True):
        if 0 <= u < PANEL_PX and 0 <= v < PANEL_PX:
            image[v, u] = colour
    unit = 0.1 * half
    origin = px(np.zeros(2))
    for k, colour in ((0, (0, 0, 220)), (1, (0, 160, 0)), (2, (220, 0, 0))):  # world x red, y green, z blue
        if k in axes:
            tip = np.zeros(2)
            tip[axes.index(k)] = unit
            cv2.arrowedLine(image, tuple(origin), tuple(px(tip)), colour, 2, tipLength=0.2)
    for cam, look in zip(cams, looks, strict=True):
        a, b = px(cam[list(axes)]), px(cam[list(axes)] + 0.6 * unit * look[list(axes)])
        cv2.line(image, tuple(a), tuple(b), (40, 40, 40), 1, cv2.LINE_AA)
        cv2.circle(image, tuple(a), 3, (30, 30, 200), -1, cv2.LINE_AA)
    cv2.putText(image, title, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return image


def write_preview(path: Path, result: ReconstructionResult) -> None:
    """Top view (x right, y up) and side view (x right, z up) of points and cameras; units as the world frame."""
    points = result.points_world_m
    colours = result.points_rgb[:, ::-1]
    cams = np.array([f.centre_world_m for f in result.frames])
    looks = np.array([f.world_from_cam[:3, 2] for f in result.frames])
    unit = "m" if str(result.world.scale_source) != "unknown" else "(scale unknown)"
    top = _panel(points, colours, cams, looks, (0, 1), f"top view (x, y) {unit}; red dots = cameras")
    side = _panel(points, colours, cams, looks, (0, 2), f"side view (x, z); table top z = 0; {len(cams)} cameras")
    write_image(path, np.hstack([top, side]), error=InputError)
