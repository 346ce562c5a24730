"""Cloud correspondences (matlearn.clouds.correspondence, cpp/observation): Gaussian weights and
their gradients, the observation residual r_k = sum_n p_kn (c_n - s_k) / sigma^2 and its
Jacobian (weights fixed and full) against central finite differences, the embedded Jacobian on
mesh vertices, and point-to-surface matches."""
import numpy as np
import pytest

from matlearn import _core, meshes
from matlearn.clouds.correspondence import CloudObservation, correspond, match_surface, surface_samples

ob = _core.observation


def _problem(seed=0, K=12, N=60, sigma=0.01):
    rng = np.random.default_rng(seed)
    S = rng.uniform(-0.02, 0.02, (K, 3))
    C = S[rng.integers(0, K, N)] + rng.normal(0, 0.8 * sigma, (N, 3))
    c = correspond(S, C, sigma, cutoff=3.0)
    return S, C, c.pair_point, c.pair_cloud, sigma, c.threshold


def _away_from_cutoff(S, C, pk, pn, sigma, cutoff=3.0, margin=0.05):
    """FD steps must not cross the truncation radius: drop pairs near it."""
    d = np.linalg.norm(C[pn] - S[pk], axis=1) / sigma
    keep = np.abs(d - cutoff) > margin
    return pk[keep], pn[keep]


def test_weights_match_gaussian_and_truncate():
    S, C, pk, pn, sigma, thr = _problem()
    p = ob.cloud_weights(S, C, pk, pn, sigma, thr)
    d2 = ((C[pn] - S[pk]) ** 2).sum(1)
    ref = np.exp(-0.5 * d2 / sigma**2)
    ref[ref < thr] = 0.0
    np.testing.assert_allclose(p, ref, rtol=1e-13, atol=0)
    # A higher threshold zeroes exactly the weights below it.
    p2 = ob.cloud_weights(S, C, pk, pn, sigma, 0.5)
    np.testing.assert_array_equal(p2 == 0, ref < 0.5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weight_gradients_fd(seed):
    S, C, pk, pn, sigma, thr = _problem(seed)
    pk, pn = _away_from_cutoff(S, C, pk, pn, sigma)
    G = ob.cloud_weight_gradients(S, C, pk, pn, sigma, thr)
    eps = 1e-7
    for d in range(3):
        Sp, Sm = S.copy(), S.copy()
        Sp[:, d] += eps
        Sm[:, d] -= eps
        fd = (ob.cloud_weights(Sp, C, pk, pn, sigma, thr) - ob.cloud_weights(Sm, C, pk, pn, sigma, thr)) / (2 * eps)
        np.testing.assert_allclose(G[:, d], fd, rtol=1e-5, atol=1e-6 * np.abs(G).max())


def test_residual_matches_reference_and_targets():
    S, C, pk, pn, sigma, thr = _problem(3)
    R = ob.cloud_residual(S, C, pk, pn, sigma, thr)
    p = ob.cloud_weights(S, C, pk, pn, sigma, thr)
    ref = np.zeros_like(S)
    np.add.at(ref, pk, p[:, None] * (C[pn] - S[pk]) / sigma**2)
    np.testing.assert_allclose(R, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    mean, W = ob.cloud_targets(S, C, pk, pn, sigma, thr)
    has = W > 0
    np.testing.assert_allclose(R[has], W[has, None] * (mean[has] - S[has]) / sigma**2, rtol=1e-9,
                               atol=1e-9 * np.abs(R).max())
    assert np.all(np.isnan(mean[~has]))


@pytest.mark.parametrize("seed", [0, 4])
def test_residual_jacobian_blocks_fd(seed):
    S, C, pk, pn, sigma, thr = _problem(seed)
    pk, pn = _away_from_cutoff(S, C, pk, pn, sigma)
    J = ob.cloud_residual_blocks(S, C, pk, pn, sigma, thr, True)
    eps = 1e-7
    for d in range(3):
        Sp, Sm = S.copy(), S.copy()
        Sp[:, d] += eps
        Sm[:, d] -= eps
        fd = (ob.cloud_residual(Sp, C, pk, pn, sigma, thr) - ob.cloud_residual(Sm, C, pk, pn, sigma, thr)) / (2 * eps)
        # r_k depends on s_k only: column d of block k is d r_k / d s_k[d].
        np.testing.assert_allclose(J[:, :, d], fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())
    # Weights held fixed: -W_k / sigma^2 I.
    Jf = ob.cloud_residual_blocks(S, C, pk, pn, sigma, thr, False)
    W = np.bincount(pk, ob.cloud_weights(S, C, pk, pn, sigma, thr), minlength=len(S))
    np.testing.assert_allclose(Jf, -(W / sigma**2)[:, None, None] * np.eye(3)[None], rtol=1e-12, atol=0)


def test_embedded_observation_jacobian_fd():
    mesh = meshes.bar(cells=(3, 1, 1))
    samples = surface_samples(mesh, level=1)
    rng = np.random.default_rng(5)
    V = np.asarray(mesh.vertices)
    X = V + 0.002 * rng.standard_normal(V.shape)
    cloud = samples.apply(V) + 0.003 * rng.standard_normal((samples.num_points, 3))
    obs = CloudObservation(samples, cloud, sigma=0.01, lam=2.0)
    c = obs.update(X)
    c.pair_point, c.pair_cloud = _away_from_cutoff(c.S, c.C, c.pair_point, c.pair_cloud, c.sigma)
    assert len(c.pair_point) > samples.num_points
    J = obs.jacobian(X, full=True).toarray()
    eps = 1e-7
    fd = np.zeros_like(J)
    for i in range(X.size):
        Xp, Xm = X.ravel().copy(), X.ravel().copy()
        Xp[i] += eps
        Xm[i] -= eps
        fd[:, i] = (obs.residual(Xp.reshape(-1, 3)) - obs.residual(Xm.reshape(-1, 3))) / (2 * eps)
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())


def test_bad_input_raises():
    S, C, pk, pn, sigma, thr = _problem()
    with pytest.raises(ValueError, match="same length"):
        ob.cloud_residual(S, C, pk[:-1], pn, sigma, thr)
    with pytest.raises(ValueError, match="sigma"):
        ob.cloud_weights(S, C, pk, pn, 0.0, thr)
    bad = pk.copy()
    bad[0] = len(S)
    with pytest.raises(ValueError, match="out of range"):
        ob.cloud_weights(S, C, bad, pn, sigma, thr)
    with pytest.raises(ValueError, match="shape"):
        ob.cloud_weights(S[:, :2], C, pk, pn, sigma, thr)


def test_match_surface_offsets_along_normal():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    rng = np.random.default_rng(0)
    bary = rng.dirichlet([2, 2, 2], 20)
    onface = bary @ V[[0, 2, 1]]  # points inside the z = 0 face
    h = rng.uniform(-0.01, -0.001, 20)  # just outside (below) that face
    cloud = onface + h[:, None] * np.array([0, 0, 1.0])
    m = match_surface(V, F, cloud, sigma=0.01, cutoff=3.0)
    np.testing.assert_allclose(m.offset, np.c_[np.zeros((20, 2)), h], atol=1e-6)
    np.testing.assert_allclose(m.weight, np.exp(-0.5 * (h / 0.01) ** 2), rtol=1e-4)
    np.testing.assert_allclose(np.einsum("nj,njd->nd", m.bary, V[m.tri]), onface, atol=1e-6)
    far = match_surface(V, F, np.array([[0.3, 0.3, -0.5]]), sigma=0.01, cutoff=3.0)
    assert far.weight[0] == 0.0  # an outlier beyond the cutoff has no weight


def test_find_pairs_matches_brute_force():
    from matlearn.clouds.correspondence import find_pairs

    rng = np.random.default_rng(7)
    S, C = rng.uniform(0, 1, (40, 3)), rng.uniform(0, 1, (70, 3))
    pk, pn = find_pairs(S, C, 0.2)
    D = np.linalg.norm(S[:, None] - C[None], axis=2)
    ref = set(zip(*np.nonzero(D <= 0.2)))
    assert set(zip(pk.tolist(), pn.tolist())) == {(int(a), int(b)) for a, b in ref}
