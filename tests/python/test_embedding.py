"""Embedding of rest-space points in a tet mesh (barycentric in a tet, or closest surface triangle)."""
import numpy as np
import pytest

from matlearn import meshes
from matlearn.embedding import embed_points

L, W = 0.2, 0.04
LO, HI = np.array([0.0, -W / 2, -W / 2]), np.array([L, W / 2, W / 2])


@pytest.fixture(scope="module")
def bar():
    return meshes.bar(L, W, W, cells=(6, 2, 2))


def test_interior_points_follow_affine_deformation_exactly(bar):
    rng = np.random.default_rng(0)
    P = rng.uniform(LO, HI, size=(200, 3))
    emb = embed_points(bar, P)
    assert emb.inside.all() and np.all(emb.distance == 0)
    assert np.all(emb.bary >= -1e-9)
    np.testing.assert_allclose(emb.bary.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(emb.vertices, bar.tets[emb.tet])
    A = np.array([[1.3, 0.2, -0.1], [0.05, 0.8, 0.3], [-0.2, 0.1, 1.1]])
    c = np.array([0.01, -0.02, 0.5])
    frames = np.stack([bar.vertices @ (s * A).T + c for s in (1.0, 0.5, -0.7)])  # (3, n, 3)
    expect = np.stack([P @ (s * A).T + c for s in (1.0, 0.5, -0.7)])
    np.testing.assert_allclose(emb.apply(frames), expect, atol=1e-12)
    S = emb.matrix(bar.num_vertices)
    assert S.shape == (200, bar.num_vertices)
    np.testing.assert_allclose(S @ frames[1], expect[1], atol=1e-12)
    np.testing.assert_allclose(emb.apply(frames[2]), expect[2], atol=1e-12)


def test_outside_points_attach_to_closest_surface_point(bar):
    rng = np.random.default_rng(1)
    P = rng.uniform(LO - 0.01, HI + 0.01, size=(300, 3))
    P = P[np.any((P < LO) | (P > HI), axis=1)]  # strictly outside the box
    emb = embed_points(bar, P)
    assert not emb.inside.any()
    closest = np.clip(P, LO, HI)  # the box's closest point
    np.testing.assert_allclose(emb.apply(bar.vertices), closest, atol=1e-12)
    np.testing.assert_allclose(emb.distance, np.linalg.norm(P - closest, axis=1), atol=1e-12)
    # Weights live on the 3 vertices of a surface face: one zero, the rest convex.
    assert np.all((emb.bary == 0).sum(axis=1) >= 1) and np.all(emb.bary >= -1e-12)


def test_vertices_embed_to_themselves(bar):
    idx = np.array([0, 5, 17, bar.num_vertices - 1])
    emb = embed_points(bar, bar.vertices[idx])
    np.testing.assert_array_equal(emb.nearest_vertices(), idx)
    np.testing.assert_allclose(emb.apply(bar.vertices), bar.vertices[idx], atol=1e-14)


def test_curved_surface_markers_from_a_finer_surface():
    """Markers on a fine sphere embed in a coarse TetGen sphere within the discretisation gap."""
    import trimesh

    r = 0.05
    coarse = meshes.sphere(r, subdivisions=1)
    fine = trimesh.creation.icosphere(subdivisions=3, radius=r).vertices
    emb = embed_points(coarse, fine)
    attached = emb.apply(coarse.vertices)
    gap = np.linalg.norm(fine - attached, axis=1)
    assert gap.max() < 0.1 * r
    np.testing.assert_allclose(gap[~emb.inside], emb.distance[~emb.inside], atol=1e-12)
    # Points inside the coarse mesh are exactly reproduced.
    np.testing.assert_allclose(attached[emb.inside], fine[emb.inside], atol=1e-12)


def test_bad_points():
    m = meshes.bar(cells=(1, 1, 1))
    with pytest.raises(ValueError, match=r"points: expected shape \(K, 3\)"):
        embed_points(m, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        embed_points(m, np.full((1, 3), np.nan))
    assert embed_points(m, np.zeros((0, 3))).num_points == 0
