"""Snapping a scanned mesh onto the upright cylinder it nearly is (`reconstruction._primitives`), against meshes with
a known answer: a rippled can comes back on its true cylinder; boxes, tapered bowls and lying cans are left alone."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from reconstruction._primitives import CylinderSnapOptions, snap_to_upright_cylinder
from reconstruction._types import TexturedMesh

RADIUS_M, HEIGHT_M = 0.035, 0.11


def _textured(mesh: trimesh.Trimesh) -> TexturedMesh:
    vertices = np.asarray(mesh.vertices, float)
    uv = (vertices[:, :2] - vertices[:, :2].min(axis=0)) / np.ptp(vertices[:, :2], axis=0)
    return TexturedMesh(
        vertices_m=vertices, faces=np.asarray(mesh.faces, np.int64), uv=uv, texture_rgb=np.zeros((4, 4, 3), np.uint8)
    )


def _solid_of_revolution(profile_rz: list[tuple[float, float]]) -> trimesh.Trimesh:
    """A watertight solid from a (radius, z) profile that starts and ends on the axis, with rings every 2 mm."""
    dense = [profile_rz[0]]
    for (r0, z0), (r1, z1) in itertools.pairwise(profile_rz):
        steps = max(1, int(np.hypot(r1 - r0, z1 - z0) / 0.002))
        dense += [(r0 + (r1 - r0) * t, z0 + (z1 - z0) * t) for t in np.linspace(0, 1, steps + 1)[1:]]
    return trimesh.creation.revolve(np.array(dense), sections=96)


def _can_profile(height_m: float = HEIGHT_M) -> list[tuple[float, float]]:
    return [(0.0, -height_m / 2), (RADIUS_M, -height_m / 2), (RADIUS_M, height_m / 2), (0.0, height_m / 2)]


def _rippled_can(ripple_m: float) -> tuple[TexturedMesh, np.ndarray]:
    """A 35 mm x 110 mm can whose side ripples by `ripple_m` (amplitude, 5 waves round and 3 up), centred off the
    frame's axis by (2, -1) mm like a scan's bounding-box centre; and which vertices are on its side."""
    can = _solid_of_revolution(_can_profile())
    v = np.asarray(can.vertices, float)
    angle = np.arctan2(v[:, 1], v[:, 0])
    r = np.hypot(v[:, 0], v[:, 1])
    on_side = r > RADIUS_M - 1e-6
    wave = ripple_m * np.sin(5 * angle) * np.cos(3 * np.pi * v[:, 2] / HEIGHT_M)
    scale = np.where(on_side, (RADIUS_M + wave) / np.maximum(r, 1e-12), 1.0)
    v[:, :2] *= scale[:, None]
    v[:, :2] += [0.002, -0.001]
    return _textured(trimesh.Trimesh(v, can.faces, process=False)), on_side


def test_a_rippled_can_is_snapped_onto_its_cylinder_and_keeps_its_faces_and_texture() -> None:
    mesh, on_side = _rippled_can(0.0015)
    snapped, fit = snap_to_upright_cylinder(mesh)
    assert fit is not None
    assert fit.radius_m == pytest.approx(RADIUS_M, abs=2e-4)
    assert fit.centre_xy_m == pytest.approx((0.002, -0.001), abs=2e-4)
    assert 0.0005 < fit.ripple_rms_m < 0.0012  # a 1.5 mm amplitude wave: ~0.75 mm RMS
    radial = np.hypot(*(snapped.vertices_m[on_side, :2] - fit.centre_xy_m).T)
    assert np.abs(radial - fit.radius_m).max() < 1e-12  # every side vertex on the cylinder
    assert snapped.vertices_m[:, 2].max() == pytest.approx(HEIGHT_M / 2) and fit.top_z_m - fit.bottom_z_m == (
        pytest.approx(HEIGHT_M)
    )
    top = mesh.vertices_m[:, 2] > HEIGHT_M / 2 - 1e-9
    assert np.all(snapped.vertices_m[top, 2] == fit.top_z_m)  # caps flat
    np.testing.assert_array_equal(snapped.faces, mesh.faces)
    assert snapped.uv is mesh.uv and snapped.texture_rgb is mesh.texture_rgb
    assert fit.moved_max_m <= CylinderSnapOptions().cap_band_m + 1e-9  # cap vertices near the rim go onto it
    assert abs(trimesh.Trimesh(snapped.vertices_m, snapped.faces).volume / (np.pi * RADIUS_M**2 * HEIGHT_M) - 1) < 0.01


@pytest.mark.parametrize(
    "shape",
    ["box", "bowl", "lying_can", "low_disc", "too_rippled_can"],
)
def test_what_is_not_an_upright_cylinder_is_left_alone(shape: str) -> None:
    if shape == "box":
        mesh = _textured(trimesh.creation.box(extents=(0.12, 0.08, 0.06)))
    elif shape == "bowl":  # tapered: 75 mm radius at the rim, 40 mm at the foot, 55 mm high
        mesh = _textured(_solid_of_revolution([(0.0, 0.0), (0.04, 0.0), (0.075, 0.055), (0.0, 0.055)]))
    elif shape == "lying_can":
        can = _solid_of_revolution(_can_profile())
        can.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        mesh = _textured(can)
    elif shape == "low_disc":
        mesh = _textured(_solid_of_revolution(_can_profile(0.02)))
    else:
        mesh, _ = _rippled_can(0.004)  # ~2.8 mm RMS: 8% of the radius
    snapped, fit = snap_to_upright_cylinder(mesh)
    assert fit is None and snapped is mesh


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="max_ripple_fraction"):
        CylinderSnapOptions(max_ripple_fraction=0.0)
    with pytest.raises(ValueError, match="min_height_m"):
        CylinderSnapOptions(min_height_m=0.01)
