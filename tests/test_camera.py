"""Camera and image geometry (DECK.md §2)."""

import jax.numpy as jnp
import numpy as np
import pytest

from rtjax.camera import basis, image_height, primary_rays


@pytest.mark.parametrize(
    "width, ha, va, height",
    [(400, 40, 30, 294), (1, 40, 30, 1), (11, 30, 30, 11), (7, 90, 1, 1), (100, 60, 90, 173)],
)
def test_image_height(width, ha, va, height):
    assert image_height(width, ha, va) == height
    expected = np.floor(width * np.tan(np.radians(va) / 2) / np.tan(np.radians(ha) / 2) + 0.5)
    assert height == max(1, int(expected))


def test_basis_z_up():
    w, u, v = basis(jnp.array([0.0, -10.0, 0.0]), jnp.zeros(3))
    np.testing.assert_allclose(w, [0, 1, 0], atol=1e-7)
    np.testing.assert_allclose(u, [1, 0, 0], atol=1e-7)  # w × ẑ
    np.testing.assert_allclose(v, [0, 0, 1], atol=1e-7)  # screen up is world up


def test_basis_looking_straight_down_uses_y():
    w, u, v = basis(jnp.array([0.0, 0.0, 10.0]), jnp.zeros(3))
    np.testing.assert_allclose(w, [0, 0, -1], atol=1e-7)
    np.testing.assert_allclose(u, np.cross([0, 0, -1], [0, 1, 0]), atol=1e-7)
    np.testing.assert_allclose(v, np.cross(u, w), atol=1e-7)


def test_primary_rays_corners_and_order():
    """Row 0 is the top; pixel (i, j) samples ((i+½)/W·2−1, 1−(j+½)/H·2) of the half extents."""
    eye, refp = jnp.array([0.0, -10.0, 0.0]), jnp.zeros(3)
    width, height = 4, 2
    o, d = primary_rays(eye, refp, jnp.array([90.0, 45.0]), width, height, jnp.array([0.5, 0.5]))
    assert o.shape == d.shape == (3, 8)
    d = np.asarray(d).T.reshape(height, width, 3)
    th, tv = np.tan(np.radians(45)), np.tan(np.radians(22.5))
    for j in range(height):
        for i in range(width):
            x = (i + 0.5) / width * 2 - 1
            y = 1 - (j + 0.5) / height * 2
            expect = np.array([x * th, 1.0, y * tv])
            np.testing.assert_allclose(d[j, i], expect / np.linalg.norm(expect), atol=1e-6)
    assert d[0, 0, 2] > 0 > d[1, 0, 2]  # top row looks up
    assert d[0, 0, 0] < 0 < d[0, -1, 0]  # left column looks left
