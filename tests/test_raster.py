"""Mesh rasteriser: exact coverage, analytic Lambertian shading, z-buffer, poses, bad input."""

import numpy as np
import pytest
import trimesh

from jface import raster

SQUARE_V = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def test_square_coverage_is_exact():
    """A 2×2 square in a 4-unit frame of 20 pixels covers exactly the central 10×10 pixels."""
    img = raster.render(
        SQUARE_V, SQUARE_F, 20, center=np.zeros(3), extent=4.0, light=(0, 0, 1), ambient=0.0
    )
    expected = np.zeros((20, 20), np.float32)
    expected[5:15, 5:15] = 1.0
    np.testing.assert_allclose(img, expected, atol=1e-6)
    assert img.dtype == np.float32


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def test_sphere_shading_matches_lambert(sphere):
    v, f = sphere
    size = 64
    light = np.array([0.3, 0.5, 1.0])
    img = raster.render(v, f, size, center=np.zeros(3), extent=2.2, light=light, ambient=0.1)
    centres = (np.arange(size) + 0.5 - size / 2) * 2.2 / size
    x, y = np.meshgrid(centres, -centres)
    r2 = x**2 + y**2
    inside = r2 < 0.85**2
    n = np.stack([x, y, np.sqrt(np.maximum(1 - r2, 0))], axis=-1)
    expected = 0.1 + 0.9 * np.maximum(n @ (light / np.linalg.norm(light)), 0)
    assert np.abs(img[inside] - expected[inside]).max() < 0.02
    assert np.all(img[r2 > 1.02] == 0.0)  # background outside the silhouette


def test_perspective_silhouette(sphere):
    """A unit sphere seen from distance D subtends asin(1/D): the silhouette's pixel area."""
    v, f = sphere
    size, extent, fov = 96, 2.4, 30.0
    img = raster.render(
        v, f, size, camera="perspective", fov=fov, center=np.zeros(3), extent=extent
    )
    distance = 0.5 * extent / np.tan(np.radians(fov) / 2)
    focal = size / extent * distance  # pixels per unit at unit depth
    radius_px = focal * np.tan(np.arcsin(1.0 / distance))
    area = np.sum(img > 0)
    assert abs(area / (np.pi * radius_px**2) - 1) < 0.03
    ortho = raster.render(v, f, size, center=np.zeros(3), extent=extent)
    assert area > np.sum(ortho > 0)  # perspective makes the near sphere look larger


def test_z_buffer_and_order_independence():
    far = SQUARE_V + np.array([0.0, 0, -1])
    near = 0.5 * SQUARE_V + np.array([0.0, 0, 1])
    v = np.concatenate([far, near])
    f = np.concatenate([SQUARE_F, SQUARE_F + 4])
    albedo = np.r_[np.full(4, 0.3), np.full(4, 0.9)]
    kwargs = dict(center=np.zeros(3), extent=4.0, light=(0, 0, 1), ambient=0.0, albedo=albedo)
    img = raster.render(v, f, 20, **kwargs)
    assert np.allclose(img[8:12, 8:12], 0.9) and np.allclose(img[5, 5], 0.3)
    np.testing.assert_array_equal(img, raster.render(v, f[::-1], 20, **kwargs))


def test_pose_equals_rotated_vertices(sphere):
    mesh = trimesh.creation.box(extents=(1.0, 0.6, 0.3))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    c, e = raster.framing(v)
    posed = raster.render(v, f, 48, yaw=30, pitch=-20, roll=10, center=c, extent=e)
    turned = (v - c) @ raster.rotation(30, -20, 10).T + c
    np.testing.assert_allclose(posed, raster.render(turned, f, 48, center=c, extent=e), atol=1e-6)
    profile = raster.render(v, f, 48, yaw=90, center=c, extent=e)
    # Seen from the side, the box's 0.3-deep face spans about 0.3 / e of the width.
    cols = np.flatnonzero(np.any(profile > 0, axis=0))
    assert abs(cols.size - 48 * 0.3 / e) <= 1.5


def test_rasterize_barycentrics_locate_pixel_centres(sphere):
    v, f = sphere
    _, screen = raster.project(v, 40, center=np.zeros(3), extent=2.5)
    frags = raster.rasterize(screen, f, (40, 40))
    hit = frags.face >= 0
    rows, cols = np.nonzero(hit)
    corners = screen[f[frags.face[hit]]][..., :2]  # (m, 3, 2)
    located = np.sum(corners * frags.bary[hit][..., None], axis=1)
    np.testing.assert_allclose(located, np.stack([cols + 0.5, rows + 0.5], axis=1), atol=1e-9)
    assert np.all(np.isinf(frags.depth[~hit])) and np.all(frags.bary[hit] >= -1e-9)


def test_bad_input():
    with pytest.raises(ValueError, match=r"faces index vertices 0\.\.3"):
        raster.render(SQUARE_V, SQUARE_F + 2)
    with pytest.raises(TypeError, match="faces must be an integer array"):
        raster.render(SQUARE_V, SQUARE_F.astype(float))
    with pytest.raises(ValueError, match=r"vertices must have shape \(N, 3\)"):
        raster.render(SQUARE_V[:, :2], SQUARE_F)
    with pytest.raises(ValueError, match="vertices must be finite"):
        raster.render(np.where(SQUARE_V > 0, np.nan, SQUARE_V), SQUARE_F)
    with pytest.raises(ValueError, match="size must be in"):
        raster.render(SQUARE_V, SQUARE_F, (0, 10))
    with pytest.raises(ValueError, match="camera must be one of"):
        raster.render(SQUARE_V, SQUARE_F, camera="fisheye")
    with pytest.raises(ValueError, match="light must be a non-zero"):
        raster.render(SQUARE_V, SQUARE_F, light=(0, 0, 0))
    with pytest.raises(ValueError, match=r"albedo must have shape \(4\)"):
        raster.render(SQUARE_V, SQUARE_F, albedo=np.ones(3))
