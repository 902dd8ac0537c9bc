"""Snapping a scanned mesh onto a primitive it nearly is: an upright cylinder (a can, a jar, a mug's body).

Model-based tracking reads an object's depth from its mesh's apparent size and texture. A fused scan's surface
ripples by about a millimetre (on `samples/tabletop`'s can 1.2 mm RMS on a 35 mm radius), and that ripple biased the
can's tracked depth by 4-9 mm in flight on `samples/toss` (docs/results/interaction.md); with its
side moved onto the fitted cylinder the bias fell to about 1 mm, as with the true mesh. Only vertex positions move:
faces and texture coordinates stay, so the baked texture stays where it was on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from reconstruction._types import TexturedMesh


@dataclass(frozen=True, kw_only=True)
class CylinderSnapOptions:
    """When and how a mesh is snapped onto its upright cylinder.

    Attributes:
        max_ripple_fraction: the side's RMS distance from the fitted cylinder, as a fraction of its radius, above
            which the object is not treated as a cylinder (scan of a can: 0.034; a bowl 0.09; a box 0.16).
        side_margin_m: vertices this far from both the lowest and the highest vertex define the side.
        cap_band_m: vertices within this of the top or bottom are moved onto that flat cap, and vertices within
            this of the radius onto the side.
        min_height_m: objects lower than this are left as they are (too little side to fit).
    """

    max_ripple_fraction: float = 0.05
    side_margin_m: float = 0.01
    cap_band_m: float = 0.004
    min_height_m: float = 0.03

    def __post_init__(self) -> None:
        if not 0.0 < self.max_ripple_fraction < 1.0:
            raise ValueError(f"max_ripple_fraction={self.max_ripple_fraction} but expected a fraction in (0, 1)")
        if not (self.side_margin_m > 0 and self.cap_band_m > 0 and self.min_height_m > 2 * self.side_margin_m):
            raise ValueError(
                f"side_margin_m={self.side_margin_m}, cap_band_m={self.cap_band_m}, min_height_m="
                f"{self.min_height_m} but expected margins > 0 and a height above twice the side margin"
            )


@dataclass(frozen=True, kw_only=True)
class CylinderFit:
    """The upright cylinder a mesh was snapped onto, in the mesh's frame (z up), metres."""

    centre_xy_m: tuple[float, float]
    radius_m: float
    ripple_rms_m: float  # the side's RMS distance from the cylinder before snapping
    bottom_z_m: float
    top_z_m: float
    moved_median_m: float
    moved_max_m: float

    def as_json(self) -> dict[str, object]:
        return {
            "centre_xy_m": list(self.centre_xy_m),
            "radius_m": self.radius_m,
            "ripple_rms_m": self.ripple_rms_m,
            "height_m": self.top_z_m - self.bottom_z_m,
            "vertices_moved_median_m": self.moved_median_m,
            "vertices_moved_max_m": self.moved_max_m,
        }


def snap_to_upright_cylinder(
    mesh: TexturedMesh, options: CylinderSnapOptions | None = None
) -> tuple[TexturedMesh, CylinderFit | None]:
    """The mesh with its side moved radially onto its least-squares upright cylinder (axis along the frame's z) and
    its caps onto flat ends, and the fit; the mesh unchanged and None where it is not within
    `max_ripple_fraction` of such a cylinder (tapered, boxy, lying on its side, too low)."""
    options = options or CylinderSnapOptions()
    vertices = mesh.vertices_m
    z_bottom, z_top = float(vertices[:, 2].min()), float(vertices[:, 2].max())
    if z_top - z_bottom < options.min_height_m:
        return mesh, None
    side = (vertices[:, 2] > z_bottom + options.side_margin_m) & (vertices[:, 2] < z_top - options.side_margin_m)
    if side.sum() < 16:
        return mesh, None
    x, y = vertices[side, 0], vertices[side, 1]
    # Kasa's algebraic circle fit: x^2 + y^2 = 2 cx x + 2 cy y + c, radius^2 = c + cx^2 + cy^2
    design = np.c_[2 * x, 2 * y, np.ones(len(x))]
    cx, cy, c = np.linalg.lstsq(design, x**2 + y**2, rcond=None)[0]
    radius = float(np.sqrt(max(c + cx**2 + cy**2, 0.0)))
    if radius <= 0.0:
        return mesh, None
    ripple = float(np.sqrt(np.mean((np.hypot(x - cx, y - cy) - radius) ** 2)))
    if ripple > options.max_ripple_fraction * radius:
        return mesh, None
    snapped = vertices.copy()
    offset = vertices[:, :2] - [cx, cy]
    distance = np.linalg.norm(offset, axis=1)
    rim = distance > radius - options.cap_band_m
    snapped[rim, :2] = [cx, cy] + offset[rim] * (radius / distance[rim])[:, None]
    snapped[vertices[:, 2] > z_top - options.cap_band_m, 2] = z_top
    snapped[vertices[:, 2] < z_bottom + options.cap_band_m, 2] = z_bottom
    moved = np.linalg.norm(snapped - vertices, axis=1)
    fit = CylinderFit(
        centre_xy_m=(float(cx), float(cy)),
        radius_m=radius,
        ripple_rms_m=ripple,
        bottom_z_m=z_bottom,
        top_z_m=z_top,
        moved_median_m=float(np.median(moved)),
        moved_max_m=float(moved.max()),
    )
    return replace(mesh, vertices_m=snapped), fit
