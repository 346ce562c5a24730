"""Stiffness tangents (diagnosis/linearised.py, LinearisedReplay.tangent) against finite
differences of the exact computations they replace; region boundary helpers (region.py)."""
import numpy as np
import pytest

from matlearn import replay
from matlearn.diagnosis import fitting, linearised, region
from matlearn.diagnosis.effects import EffectContext, build_model
from matlearn.diagnosis.problem import Problem

from diagnosis_cases import tiny_case


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    scene = tiny_case(tmp_path_factory.mktemp("lin"), "lin", region=(0.3, 0.7), region_scale=0.5, seed=3)
    P = Problem(scene)
    s = P.scene
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    C = np.asarray(s.mesh.vertices)[np.asarray(s.mesh.tets)].mean(axis=1)
    ctx.region = C[:, 0] > 0.04
    D = np.stack([(C[:, 0] < 0.03).astype(float), np.ones(len(C)),
                  np.random.default_rng(0).standard_normal(len(C))], axis=1)
    return P, ctx, D, {"heterogeneity": [-0.5, 0.1]}


def _rel(a, b):
    return np.linalg.norm(a - b, axis=0) / np.linalg.norm(b, axis=0)


def test_replay_tangent_matches_finite_differences_of_the_replay(setup):
    P, ctx, D, params = setup
    s = P.scene
    rec = P.train[0]
    model = build_model(ctx, params)
    emb = P.embedding(rec)
    x0, v0 = replay.initial_state(s, model, rec, emb)
    n = s.mesh.num_vertices
    R = P.replay_runner(model)
    steps = 80
    X, dQ = R.tangent(model, x0, v0, steps, np.zeros((n, 3)), np.zeros((3 * n, 3)), D,
                      np.asarray(emb.vertices, np.int64), emb.bary)
    X_sim, _ = R.simulate(model, x0, v0, steps, np.zeros((n, 3)))
    np.testing.assert_allclose(X, X_sim, atol=1e-12)

    def Q(X):
        return np.einsum("kj,tkjd->tkd", emb.bary, X[:, emb.vertices])

    eps = 1e-4
    for j in range(D.shape[1]):
        Xp, _ = R.simulate(linearised._scaled(ctx, params, eps * D[:, j]), x0, v0, steps, np.zeros((n, 3)))
        Xm, _ = R.simulate(linearised._scaled(ctx, params, -eps * D[:, j]), x0, v0, steps, np.zeros((n, 3)))
        fd = ((Q(Xp) - Q(Xm)) / (2 * eps)).ravel()
        # the dropped state dependence of the step matrix costs O(h): a few % here
        assert np.linalg.norm(dQ[..., j].ravel() - fd) < 0.05 * np.linalg.norm(fd)
    # a wrong sign or a missing force term would be off by O(1)
    assert np.linalg.norm(dQ[..., 1]) > 0


def test_held_pose_tangent_is_exact(setup):
    P, ctx, D, params = setup
    s = P.scene
    rec = P.train[1]
    model = build_model(ctx, params)
    emb = P.embedding(rec)
    dx0 = linearised._held_pose_tangent(P, model, rec, D)
    eps = 1e-3
    for j in range(D.shape[1]):
        xp, _ = replay.initial_state(s, linearised._scaled(ctx, params, eps * D[:, j]), rec, emb)
        xm, _ = replay.initial_state(s, linearised._scaled(ctx, params, -eps * D[:, j]), rec, emb)
        fd = ((xp - xm) / (2 * eps)).ravel()
        assert np.linalg.norm(dx0[:, j] - fd) < 1e-4 * np.linalg.norm(fd)


def test_stiffness_jacobian_matches_finite_differences_of_the_residual(setup):
    P, ctx, D, params = setup
    r, J = linearised.stiffness_jacobian(P, ctx, params, D)
    np.testing.assert_allclose(r, fitting.residual_of(P, ctx, params), atol=1e-10)
    eps = 1e-3
    Jf = np.zeros_like(J)
    for j in range(D.shape[1]):
        rp = fitting.marker_residual(P, linearised._scaled(ctx, params, eps * D[:, j]))
        rm = fitting.marker_residual(P, linearised._scaled(ctx, params, -eps * D[:, j]))
        Jf[:, j] = (rp - rm) / (2 * eps)
    assert np.all(_rel(J, Jf) < 0.15), _rel(J, Jf)
    # the finite-difference fallback (used for recordings with drive points) agrees too
    P.reuse_factor = False
    try:
        _, J_fd = linearised.stiffness_jacobian(P, ctx, params, D[:, :1], fd_step=1e-3)
    finally:
        P.reuse_factor = True
    assert _rel(J_fd, Jf[:, :1])[0] < 0.02


def test_a_fit_without_contrast_is_restarted(setup):
    """The zero-parameter heterogeneity fit (region scale = rest scale = 1) is not kept: the
    tangent step of the two scales, checked by simulation, lowers the residual."""
    P, ctx, D, params = setup
    r0 = fitting.residual_of(P, ctx, {"heterogeneity": [0.0, 0.0]})
    zero = fitting.Fit("heterogeneity", {"heterogeneity": np.zeros(2)}, float(r0 @ r0), 3)
    calls = []

    def refit(p):
        calls.append(p)
        return fitting.refine(P, ctx, ["heterogeneity"], p, iterations=1)

    fit = region.restart_scales(P, ctx, zero, refit)
    t = fit.params["heterogeneity"]
    assert calls and fit.rss < 0.8 * zero.rss
    assert abs(t[0] - t[1]) > 0.05
    np.testing.assert_allclose(fitting.residual_of(P, ctx, fit.params) @ fitting.residual_of(P, ctx, fit.params),
                               fit.rss, rtol=1e-8)


def test_greedy_moves_take_only_helpful_columns():
    rng = np.random.default_rng(6)
    r = rng.standard_normal(100)
    good = -0.3 * r
    D = np.column_stack([good, rng.standard_normal(100), good + 0.01 * rng.standard_normal(100)])
    chosen = region.greedy_moves(r, D)
    assert 1 not in chosen and chosen[0] in (0, 2)
    # each accepted column lowered the residual
    cur = r.copy()
    for i in chosen:
        assert np.linalg.norm(cur + D[:, i]) < np.linalg.norm(cur)
        cur = cur + D[:, i]


def test_tangent_refuses_models_it_cannot_differentiate(setup):
    from matlearn.diagnosis.effects import build_model as bm

    P, ctx, D, params = setup
    s = P.scene
    n = s.mesh.num_vertices
    # a correction's stress does not scale with the element stiffness
    model = bm(ctx, {"tension_nonlinearity": [1.0, 0.0]})
    R = P.replay_runner(model)
    V = np.asarray(s.mesh.vertices, float)
    emb = P.embedding(P.train[0])
    with pytest.raises(ValueError, match="correction"):
        R.tangent(model, V, 0 * V, 3, np.zeros((n, 3)), np.zeros((3 * n, 1)), D[:, :1],
                  np.asarray(emb.vertices, np.int64), emb.bary)
    with pytest.raises(ValueError, match="directions"):
        R.tangent(build_model(ctx, {}), V, 0 * V, 3, np.zeros((n, 3)), np.zeros((3 * n, 1)),
                  D[:5, :1], np.asarray(emb.vertices, np.int64), emb.bary)


@pytest.fixture(scope="module")
def driven(tmp_path_factory):
    """A bar whose free end is driven (keyframed drive points) from a pose held by a side load,
    markers on half the surface: the sphere cases' kind of recording."""
    from matlearn import meshes
    from matlearn.materials import Damping, Material
    from matlearn.synthetic import Motion, make_case

    L = 0.1
    mesh = meshes.bar(L, 0.02, 0.02, cells=(6, 1, 1))
    end = [[L - 0.001, -1, -1], [1, 1, 1]]
    side = [[0.5 * L - 0.009, -1, -1], [0.5 * L + 0.009, 1, 1]]
    drive = {"box": end, "keyframes": [[0.0, [0, 0, 0]], [0.03, [0.004, 0.006, 0]], [0.06, [0, -0.004, 0.003]]]}
    path = make_case(tmp_path_factory.mktemp("drv"), "drv", mesh, Material("corotated", 1.5e5, 0.4, 1000.0),
                     Damping(0.0, 0.004), mesh, Material("corotated", 1e5, 0.4, 1000.0), Damping(0.0, 0.004),
                     [[-1, -1, -1], [1e-4, 1, 1]],
                     [Motion("drive", "train", 0.06, load={"box": side, "force": [0, 0.4, 0]}, drive=drive)],
                     marker_fraction=0.5, seed=1)
    P = Problem(str(path))
    s = P.scene
    assert P.train[0].has_drive and not P.train[0].at_rest_initially
    ctx = EffectContext(s.mesh, s.material, s.damping, s.fixed)
    C = np.asarray(s.mesh.vertices)[np.asarray(s.mesh.tets)].mean(axis=1)
    D = np.stack([(C[:, 0] < 0.04).astype(float), np.ones(len(C))], axis=1)
    return P, ctx, D


def test_linearised_replay_follows_drive_points_like_the_integrator(driven):
    """The driven recording through LinearisedReplay (driven vertices prescribed) is the
    integrator's constrained simulation with one Newton iteration per step, to the PCG tolerance."""
    P, ctx, _ = driven
    s, rec = P.scene, P.train[0]
    model = build_model(ctx, {})
    state = replay.initial_state(s, model, rec, P.embedding(rec))
    ref = replay.simulate_recording(s, model, rec, state=state, max_newton=1)
    sim_t, X, V = P._linearised(model, rec, state)
    np.testing.assert_allclose(sim_t, ref[0])
    assert np.abs(X - ref[1]).max() < 1e-9 * s.object_size
    didx = replay.drive_vertices(s, rec)[0]
    assert len(didx) and np.abs(X[1:, didx] - ref[1][1:, didx]).max() == 0.0  # exactly at the targets
    # the driven vertices move (a clamped replay would leave them at rest)
    assert np.abs(X[-1, didx] - X[0, didx]).max() > 1e-3
    # targets are required, and must have one row per driven vertex
    n = s.mesh.num_vertices
    R = P.replay_runner(model, didx)
    with pytest.raises(ValueError, match="targets"):
        R.simulate(model, X[0], V[0], 3, np.zeros((n, 3)))
    with pytest.raises(ValueError, match="targets"):
        R.simulate(model, X[0], V[0], 3, np.zeros((n, 3)), targets=np.zeros((3, len(didx) + 1, 3)))
    from matlearn import _core
    with pytest.raises(ValueError, match="also fixed"):
        _core.time.LinearisedReplay(model, s.fixed, s.time_step, np.zeros(3), prescribed=s.fixed[:1])


def test_stiffness_jacobian_of_a_driven_recording_by_tangents(driven, monkeypatch):
    """Driven recordings get tangent Jacobians too (no finite differences: every simulation is
    one of the two residuals' or the tangent pass), matching central differences."""
    P, ctx, D = driven
    calls = []
    monkeypatch.setattr(fitting, "marker_residual",
                        lambda *a, **k: calls.append(1) or pytest.fail("finite differences used"))
    r, J = linearised.stiffness_jacobian(P, ctx, {}, D)
    monkeypatch.undo()
    np.testing.assert_allclose(r, fitting.residual_of(P, ctx, {}), atol=1e-10)
    eps = 1e-3
    Jf = np.zeros_like(J)
    for j in range(D.shape[1]):
        rp = fitting.marker_residual(P, linearised._scaled(ctx, {}, eps * D[:, j]))
        rm = fitting.marker_residual(P, linearised._scaled(ctx, {}, -eps * D[:, j]))
        Jf[:, j] = (rp - rm) / (2 * eps)
    assert np.all(np.linalg.norm(Jf, axis=0) > 0)
    assert np.all(_rel(J, Jf) < 0.15), _rel(J, Jf)
