"""Unit checks of the diagnosis building blocks (no full diagnosis run)."""
import numpy as np
import pytest

from matlearn import meshes
from matlearn.diagnosis import fitting, where
from matlearn.diagnosis.effects import EffectContext, build_model, clamp_layer
from matlearn.diagnosis.problem import Problem
from matlearn.meshes import refine_tets
from matlearn.scene import Scene, vertices_in_box
from matlearn.materials import Damping, Material


def _ctx(**kw):
    mesh = meshes.bar(0.1, 0.02, 0.02, (4, 1, 1))
    fixed = np.flatnonzero(np.asarray(mesh.vertices)[:, 0] < 1e-9)
    return EffectContext(mesh, Material("corotated", 1e5, 0.3, 1000.0), Damping(0.0, 0.0), fixed, **kw)


def _deformed(mesh, seed=0, amp=0.003):
    rng = np.random.default_rng(seed)
    return np.asarray(mesh.vertices) + amp * rng.standard_normal((mesh.num_vertices, 3))


def test_refine_tets_conserves_volume_and_is_conforming():
    V, T = meshes.grid_tets((2, 1, 1), (0.2, 0.1, 0.1))
    Vn, Tn = refine_tets(V, T)
    assert Tn.shape == (8 * len(T), 4)
    vol = lambda V, T: np.linalg.det(V[T[:, 1:]] - V[T[:, :1]]) / 6  # noqa: E731
    assert np.all(vol(Vn, Tn) > 0)
    np.testing.assert_allclose(vol(Vn, Tn).sum(), 0.2 * 0.1 * 0.1, rtol=1e-12)
    # conforming: every interior face is shared by exactly two tets, boundary area is the box's
    faces = np.sort(Tn[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2
    m = meshes.TetMesh(Vn, Tn)
    F = np.asarray(m.surface_faces)
    area = 0.5 * np.linalg.norm(np.cross(Vn[F[:, 1]] - Vn[F[:, 0]], Vn[F[:, 2]] - Vn[F[:, 0]]), axis=1)
    np.testing.assert_allclose(area.sum(), 2 * (0.2 * 0.1 * 2 + 0.1 * 0.1), rtol=1e-12)


def test_refined_scene_clamps_the_box_not_only_the_coarse_clamp():
    # a box ending between two coarse vertex layers: the refined mesh has midpoints inside it
    # whose edges leave it; they are clamped (the body is held wherever the box is), so the
    # refined reference is held as firmly as a finer recorded body
    mesh = meshes.bar(0.1, 0.02, 0.02, (4, 1, 1))
    box = [[-1.0, -1.0, -1.0], [0.04, 1.0, 1.0]]
    mat = Material("corotated", 1e5, 0.3, 1000.0)

    def refined(fixed_box):
        P = Problem.__new__(Problem)
        P.scene = Scene(mesh, mat, Damping(0.0, 0.0), vertices_in_box(mesh.vertices, box),
                        fixed_box=fixed_box)
        return P.refined_scene()

    boxed, listed = refined(box), refined(None)
    V = np.asarray(boxed.mesh.vertices)
    assert np.array_equal(boxed.fixed, vertices_in_box(V, box))
    assert np.array_equal(np.asarray(listed.mesh.vertices), V)
    # the vertex-list rule: midpoints of clamped edges only (x <= 0.025 here)
    assert np.array_equal(listed.fixed, np.flatnonzero(V[:, 0] <= 0.025 + 1e-12))
    assert set(listed.fixed) < set(boxed.fixed)
    assert np.isclose(V[boxed.fixed, 0].max(), 0.0375)
    assert boxed.fixed_box == box and listed.fixed_box is None


def test_stiffness_and_region_families_scale_elastic_forces_exactly():
    ctx = _ctx()
    x = _deformed(ctx.mesh)
    v = np.zeros_like(x)
    f0 = np.asarray(build_model(ctx, {}).forces(x, v))
    f1 = np.asarray(build_model(ctx, {"stiffness_scale": [np.log(1.7)]}).forces(x, v))
    np.testing.assert_allclose(f1, 1.7 * f0, rtol=1e-10, atol=1e-12)
    # a region scale acts on the region's element forces only: linear in the scale
    ctx.region = np.zeros(ctx.mesh.num_tets, bool)
    ctx.region[:5] = True
    fa = np.asarray(build_model(ctx, {"heterogeneity": [np.log(2.0), 0.0]}).forces(x, v))
    fb = np.asarray(build_model(ctx, {"heterogeneity": [np.log(3.0), 0.0]}).forces(x, v))
    np.testing.assert_allclose(fb - f0, 2.0 * (fa - f0), rtol=1e-9, atol=1e-12)
    # region and rest scaled alike = a uniform scale
    fu = np.asarray(build_model(ctx, {"heterogeneity": [np.log(1.7), np.log(1.7)]}).forces(x, v))
    np.testing.assert_allclose(fu, f1, rtol=1e-10, atol=1e-12)
    # the clamp layer = elements touching a clamped vertex
    assert np.array_equal(ctx.clamp_layer, clamp_layer(ctx.mesh, ctx.fixed))
    assert 0 < ctx.clamp_layer.sum() < ctx.mesh.num_tets


@pytest.mark.parametrize("name,side", [("tension_nonlinearity", 1.0), ("compression_nonlinearity", -1.0)])
def test_one_sided_nonlinearity_acts_on_its_side_only(name, side):
    ctx = _ctx(d_ref=0.02)
    model = build_model(ctx, {name: [1.5, -0.7]})
    corr = model.correction
    S = np.array([[1.03, 0.99, 1.0], [0.97, 1.01, 1.02], [1.0, 1.0, 1.0]])
    dP = np.asarray(corr.evaluate(S, np.zeros_like(S))[0])
    active = side * (S - 1) > 0
    assert np.all(dP[~active] == 0)
    assert np.all(np.abs(dP[active]) > 0)
    # the value follows E0 d_ref sum c_k (d/d_ref)^(k+2) with the strain's sign
    d = np.abs(S - 1) / 0.02
    want = side * 1e5 * 0.02 * (1.5 * d**2 - 0.7 * d**3) * active
    np.testing.assert_allclose(dP, want, rtol=1e-12, atol=1e-9)


def test_one_sided_nonlinearity_jacobian_matches_finite_differences():
    ctx = _ctx(d_ref=0.02)
    corr = build_model(ctx, {"tension_nonlinearity": [2.0, 1.0], "compression_nonlinearity": [1.0, -3.0]}).correction
    rng = np.random.default_rng(3)
    S = 1 + 0.04 * rng.standard_normal((6, 3))
    out = corr.evaluate(S, np.zeros_like(S))
    J = np.asarray(out[1])
    eps = 1e-7
    for j in range(3):
        Sp, Sm = S.copy(), S.copy()
        Sp[:, j] += eps
        Sm[:, j] -= eps
        fd = (np.asarray(corr.evaluate(Sp, 0 * S)[0]) - np.asarray(corr.evaluate(Sm, 0 * S)[0])) / (2 * eps)
        np.testing.assert_allclose(J[:, :, j], fd, rtol=1e-5, atol=1e-3)


def test_damping_families_map_to_rayleigh_coefficients():
    ctx = _ctx(omega=20.0, d_ref=0.05)
    x = np.asarray(ctx.mesh.vertices).copy()
    v = _deformed(ctx.mesh, 1, 0.01) - x
    f_el = np.asarray(build_model(ctx, {}).forces(x, v))
    assert np.allclose(f_el, 0)  # undamped nominal at rest: no force
    m = build_model(ctx, {"rayleigh_damping": [1.0, 2.0]})
    aM, aK = 0.1 * 20.0, 2.0 * 0.1 / 20.0
    M = np.asarray(m.vertex_mass)[:, None]
    K = m.stiffness(x, 0 * v)
    want = -aM * M * v - (K @ v.ravel()).reshape(-1, 3) * aK
    np.testing.assert_allclose(np.asarray(m.forces(x, v)), want, rtol=1e-8, atol=1e-12)


def test_linear_fit_recovers_known_parameters():
    rng = np.random.default_rng(0)
    J = rng.standard_normal((200, 3))
    th = np.array([0.3, -1.2, 0.5])
    r0 = -J @ th
    est, rss = fitting.linear_fit(J, r0)
    np.testing.assert_allclose(est, th, rtol=1e-5)
    assert rss < 1e-8


def test_locate_region_picks_the_deviating_patches():
    rng = np.random.default_rng(1)
    Jp = rng.standard_normal((300, 8))
    truth = np.zeros(8)
    truth[[2, 5]] = -0.8
    sel, th = fitting.locate_region(Jp, -Jp @ truth)
    assert set(np.flatnonzero(sel)) == {2, 5}
    # a uniform offset of the whole body on top does not move the located region
    sel, th = fitting.locate_region(Jp, -Jp @ (truth + 0.3))
    assert set(np.flatnonzero(sel)) == {2, 5}
    # columns not allowed never join the region
    sel, th = fitting.locate_region(Jp, -Jp @ truth, np.arange(8) != 5)
    assert not sel[5]


def test_score_prefers_fewer_parameters_at_equal_fit_and_ignores_gains_below_floor():
    a = fitting.score(1.0, 1, 500, 0.1)
    b = fitting.score(1.0, 2, 500, 0.1)
    assert a < b
    # halving an rss already far below the floor barely changes the score
    assert abs(fitting.score(1e-4, 1, 500, 1.0) - fitting.score(5e-5, 1, 500, 1.0)) < 0.1


def test_regime_split_of_a_tension_only_residual():
    rng = np.random.default_rng(2)
    F, m = 20, 30
    Fh = 1 + 0.05 * rng.standard_normal((F, m, 3))
    Fhd = rng.standard_normal((F, m, 3))
    dp = np.where(Fh > 1, 1e3 * (Fh - 1) ** 2, 0.0)  # elastic, tension side only
    field = where.ResidualField(np.arange(F) * 0.01, np.zeros((F, 4, 3)), dp, Fh, Fhd,
                                np.zeros((F, 4, 3)), np.ones(m))
    r = where.regime_split(field)
    assert r["tension"] == pytest.approx(1.0)
    assert r["elastic"] > 0.8
    np.testing.assert_allclose(r["tension"] + r["compression"], 1.0)
    np.testing.assert_allclose(r["elastic"] + r["dissipative"], 1.0)
    # a purely rate-proportional residual is dissipative
    field.dp = 50.0 * Fhd
    r = where.regime_split(field)
    assert r["dissipative"] > 0.99


def test_strain_dependent_damping_nests_rayleigh_and_adds_an_amplitude_dependence():
    ctx = _ctx(omega=20.0, d_ref=0.05)
    x = _deformed(ctx.mesh, 3, 0.002)
    v = _deformed(ctx.mesh, 4, 0.01) - np.asarray(ctx.mesh.vertices)
    ray = np.asarray(build_model(ctx, {"rayleigh_damping": [0.7, 1.3]}).forces(x, v))
    sdd = np.asarray(build_model(ctx, {"strain_dependent_damping": [0.7, 1.3, 0.0, 0.0]}).forces(x, v))
    np.testing.assert_allclose(sdd, ray, rtol=1e-12, atol=1e-15)
    # a positive slope raises alpha_K where the largest stretch exceeds 1: more damping force
    m = build_model(ctx, {"strain_dependent_damping": [0.7, 1.3, 2.0, 0.0]})
    el = build_model(ctx, {})
    f_el = np.asarray(el.forces(x, 0 * v))
    d_ray = (ray - f_el).ravel() @ v.ravel()
    d_sdd = (np.asarray(m.forces(x, v)) - f_el).ravel() @ v.ravel()
    assert d_sdd < d_ray < 0


def test_locate_region_chooses_the_split_by_the_two_stiffness_fit():
    rng = np.random.default_rng(4)
    Jp = rng.standard_normal((400, 12)) * np.linspace(3.0, 0.3, 12)  # weakly loaded patches last
    truth = np.zeros(12)
    truth[[8, 9, 10]] = 0.9  # a stiffer region among weakly loaded patches
    sel, _ = fitting.locate_region(Jp, -Jp @ truth)
    assert set(np.flatnonzero(sel)) == {8, 9, 10}


def test_a_marker_off_the_surface_keeps_its_rest_offset():
    from types import SimpleNamespace

    from matlearn.embedding import embed_points

    mesh = meshes.bar(0.1, 0.02, 0.02, (4, 1, 1))
    V = np.asarray(mesh.vertices)
    rest = np.array([[0.05, 0.0115, 0.0], [0.08, 0.0, -0.0112], [0.03, 0.002, 0.001]])  # 2 outside, 1 inside
    emb = embed_points(mesh, rest)
    T = 4
    shift = np.array([0.0, 0.002, 0.0])  # the body translated: markers move with it
    obs = np.broadcast_to(rest + shift, (T, 3, 3)).copy()
    rec = SimpleNamespace(marker_rest=rest, markers=obs, seen=np.ones((T, 3), bool))
    problem = SimpleNamespace(scene=SimpleNamespace(mesh=mesh), object_size=0.1, train=[rec],
                              embedding=lambda r: emb,
                              predict=lambda m, r, fast=True: np.broadcast_to(emb.apply(V + shift), (T, 3, 3)))
    off = fitting.rest_offset(problem, rec)
    np.testing.assert_allclose(off[2], 0, atol=1e-12)  # inside: no offset
    np.testing.assert_allclose(off[0], [0, 0.0015, 0], atol=1e-12)
    np.testing.assert_allclose(off[1], [0, 0, -0.0012], atol=1e-12)
    r = fitting.marker_residual(problem, None)
    np.testing.assert_allclose(r, 0, atol=1e-12)


def test_debias_removes_the_discretisation_discrepancy_with_a_bounded_profiled_weight():
    """fitting.debias: r + w b, w the least-squares weight of this residual clipped to the
    plausible range; recordings without a measured discrepancy are left alone."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    recs = [SimpleNamespace(), SimpleNamespace()]
    b = [rng.standard_normal(30), rng.standard_normal(18)]
    prob = SimpleNamespace(disc_bias={id(r): x for r, x in zip(recs, b)}, disc_weight_range=(0.55, 4 / 3))
    B = np.concatenate(b)
    effect = rng.standard_normal(48)
    effect -= (effect @ B) / (B @ B) * B  # an effect orthogonal to the discrepancy
    for w_true in (0.6, 1.0, 1.3):  # inside the range: removed exactly, the effect kept
        np.testing.assert_allclose(fitting.debias(prob, effect - w_true * B, recs), effect, atol=1e-12)
    # beyond the range the weight stops at its bound: the rest is not hidden
    np.testing.assert_allclose(fitting.debias(prob, effect - 3.0 * B, recs), effect - (3.0 - 4 / 3) * B,
                               atol=1e-12)
    np.testing.assert_allclose(fitting.debias(prob, effect + B, recs), effect + 1.55 * B, atol=1e-12)
    # one recording alone uses its own part; an unknown (held-out) recording is unchanged
    r1 = rng.standard_normal(18)
    w = np.clip(-(r1 @ b[1]) / (b[1] @ b[1]), 0.55, 4 / 3)
    np.testing.assert_allclose(fitting.debias(prob, r1, recs[1:]), r1 + w * b[1], atol=1e-12)
    other = SimpleNamespace()
    np.testing.assert_array_equal(fitting.debias(prob, r1, [other]), r1)



def test_the_discretisation_offset_is_found_when_local_steps_from_zero_stall(tmp_path, monkeypatch):
    """discretisation.discretisation measures the coarse mesh's stiffness offset against the
    once-refined mesh. When the local fit from zero stalls (its steps rejected, as on a 288-tet
    plate with a hole whose refined mesh matches a 0.45x stiffness), the grid of softer offsets
    still finds it: about the same offset and a range and removed discrepancy at least as good as
    an unstalled fit's."""
    from diagnosis_cases import tiny_case

    from matlearn.diagnosis import discretisation as disc
    from matlearn.diagnosis.problem import Problem

    path = tiny_case(tmp_path, "bar", E_scale=1.0, cells=(5, 1, 1))

    def run():
        P = Problem(path)
        sc = P.scene
        ctx = EffectContext(sc.mesh, sc.material, sc.damping, sc.fixed)
        new, floors, theta, (b, _), _ = disc.discretisation(P, ctx, lambda m: None)
        return theta, new.offset_reference, new.offset_range, float(b @ b)

    theta, ref, rng_, bb = run()
    assert ref < -0.05  # a coarse bar 1 tet across is clearly too stiff
    real_refine = fitting.refine

    def stalled(problem, ctx, names, theta0, *a, **kw):
        if names == ["stiffness_scale"] and not theta0 and kw.get("target") is not None:
            fit = real_refine(problem, ctx, names, theta0, *a, **dict(kw, iterations=0))
            assert fit.params["stiffness_scale"][0] == 0.0
            return fit
        return real_refine(problem, ctx, names, theta0, *a, **kw)

    monkeypatch.setattr(fitting, "refine", stalled)
    theta2, ref2, rng2, bb2 = run()
    # found again (the grid's start can even reach a closer match than the steps from zero)
    assert ref2 == pytest.approx(ref, abs=0.1) and ref2 < -0.05
    assert rng2[1] - rng2[0] > 0.25 * abs(ref2)  # not collapsed to a point
    assert bb2 <= 1.05 * bb


def test_damping_coordinates_follow_the_damping_families_and_their_clamps():
    """effects.damping_coordinates: where a model's damping lies from the nominal one, in the
    units of the families' parameters (DAMPING_STEPS), the clamp of a coefficient at 0 included."""
    from matlearn.diagnosis.effects import DAMPING_STEPS, damping_coordinates, damping_of

    ctx = _ctx(omega=20.0, d_ref=0.05)
    ctx.damping = Damping(0.5, 0.004)
    np.testing.assert_allclose(damping_coordinates(ctx, {}), 0.0)
    np.testing.assert_allclose(damping_coordinates(ctx, {"stiffness_scale": [0.3]}), 0.0)
    np.testing.assert_allclose(damping_coordinates(ctx, {"rayleigh_damping": [0.5, -0.3]}), [0.5, -0.3])
    # the strain-dependent family moves alpha_M and alpha_K by its first two parameters; its
    # alpha_K polynomial is not a coordinate
    np.testing.assert_allclose(damping_coordinates(ctx, {"strain_dependent_damping": [0.2, 0.1, 1.0, -0.5]}),
                               [0.2, 0.1], atol=1e-12)
    np.testing.assert_allclose(damping_coordinates(ctx, {"strain_dependent_damping": [0.0, 0.0, 1.0, -0.5]}),
                               [0.0, 0.0], atol=1e-12)
    both = {"rayleigh_damping": [0.5, 0.0], "strain_dependent_damping": [0.2, 0.1, 1.0, 0.0]}
    np.testing.assert_allclose(damping_coordinates(ctx, both), [0.7, 0.1], atol=1e-12)
    # alpha_M = 0.5 - 5 * 0.1 * 20 clamps at 0: the coordinate is the clamped move, -0.25
    np.testing.assert_allclose(damping_coordinates(ctx, {"rayleigh_damping": [-5.0, 0.0]}), [-0.25, 0])
    for k, step in enumerate(DAMPING_STEPS):
        np.testing.assert_allclose(damping_coordinates(ctx, step), np.eye(2)[k], atol=1e-12)
    # the polynomial terms still reach the model's damping (damping_of)
    kp = damping_of(ctx, {"strain_dependent_damping": [0.0, 0.0, 1.0, -0.5]}).stiffness_poly
    np.testing.assert_allclose(kp, [0.1 / 20.0 / 0.05, -0.5 * 0.1 / 20.0 / 0.05 ** 2])
    # damping_of is the damping build_model uses: the forces agree
    x = np.asarray(ctx.mesh.vertices).copy()
    v = _deformed(ctx.mesh, 2, 0.01) - x
    p = {"rayleigh_damping": [0.7, 0.4]}
    m_ref = build_model(ctx, p)
    d = damping_of(ctx, p)
    m_dmp = build_model(EffectContext(ctx.mesh, ctx.material, d, ctx.fixed, omega=20.0, d_ref=0.05), {})
    np.testing.assert_allclose(np.asarray(m_ref.forces(x, v)), np.asarray(m_dmp.forces(x, v)), rtol=1e-12)


def test_geometric_units_of_a_decaying_change():
    """fitting.geometric: a change whose every further unit is `ratio` times the last: 1 at one
    unit, 1 + q at two, the plain count at q = 1, and its slope at 0 is -ln q / (1 - q)."""
    q = np.array([0.5, 1.0])
    np.testing.assert_allclose(fitting.geometric(np.array([1.0, 1.0]), q), [1.0, 1.0])
    np.testing.assert_allclose(fitting.geometric(np.array([2.0, 2.0]), q), [1.5, 2.0])
    np.testing.assert_allclose(fitting.geometric(np.array([3.0, -1.5]), q), [1.75, -1.5])
    np.testing.assert_allclose(fitting.geometric(np.array([-1.0, 0.0]), q), [-2.0, 0.0])  # one unit less: -1/q
    h = 1e-6
    slope = (fitting.geometric(np.array([h, h]), q) - fitting.geometric(np.array([-h, -h]), q)) / (2 * h)
    np.testing.assert_allclose(slope, [-np.log(0.5) / 0.5, 1.0], rtol=1e-6)
    np.testing.assert_allclose(fitting.geometric_slope(q), slope, rtol=1e-6)
    np.testing.assert_allclose(fitting.geometric(np.array([0.7]), None), [0.7])


def test_debias_removes_the_discrepancy_at_the_models_own_damping():
    """fitting.discrepancy / debias with damping coordinates: b0 + B d is removed (the weight
    profiled as before); without coordinates b0 alone."""
    from types import SimpleNamespace

    rng = np.random.default_rng(5)
    recs = [SimpleNamespace(), SimpleNamespace()]
    b = [rng.standard_normal(24), rng.standard_normal(12)]
    B = [rng.standard_normal((24, 2)), rng.standard_normal((12, 2))]
    prob = SimpleNamespace(disc_bias={id(r): x for r, x in zip(recs, b)}, disc_bias_ratio=None,
                           disc_bias_damping={id(r): x for r, x in zip(recs, B)}, disc_weight_range=(0.55, 4 / 3))
    d = np.array([0.8, -0.2])
    bd = np.concatenate(b) + np.concatenate(B) @ d
    np.testing.assert_allclose(fitting.discrepancy(prob, recs, d), bd)
    np.testing.assert_allclose(fitting.discrepancy(prob, recs), np.concatenate(b))
    # with a ratio of successive unit changes: b0 + B g(d)
    prob.disc_bias_ratio = np.array([0.5, 1.0])
    np.testing.assert_allclose(fitting.discrepancy(prob, recs, np.array([2.0, -0.2])),
                               np.concatenate(b) + np.concatenate(B) @ np.array([1.5, -0.2]))
    prob.disc_bias_ratio = None
    effect = rng.standard_normal(36)
    effect -= (effect @ bd) / (bd @ bd) * bd
    np.testing.assert_allclose(fitting.debias(prob, effect - 0.9 * bd, recs, d), effect, atol=1e-12)
    # the nominal discrepancy does not remove it
    assert np.linalg.norm(fitting.debias(prob, effect - 0.9 * bd, recs) - effect) > 0.1


def test_the_discretisation_discrepancy_follows_the_damping(tmp_path):
    """discretisation.discretisation measures how the refined-minus-coarse discrepancy changes
    per unit of each damping coordinate. More mass damping damps the mesh's error with the motion
    (|b| shrinks), and the measured secant predicts the discrepancy re-measured at half a unit
    better than the nominal one does."""
    from diagnosis_cases import tiny_case

    from matlearn.diagnosis import discretisation as disc

    path = tiny_case(tmp_path, "bar", E_scale=1.0, cells=(5, 1, 1))
    P = Problem(path)
    sc = P.scene
    ctx = EffectContext(sc.mesh, sc.material, sc.damping, sc.fixed, omega=60.0)
    _, _, _, (b_off, _), _ = disc.discretisation(P, ctx, lambda m: None)
    assert not P.disc_bias_damping and P.disc_bias_ratio is None  # off by default
    new, _, _, (b0, _), _ = disc.discretisation(P, ctx, lambda m: None, follow_damping=True)
    np.testing.assert_allclose(b0, b_off)  # the nominal discrepancy itself is unchanged
    B = np.concatenate([P.disc_bias_damping[id(r)] for r in P.train])
    assert B.shape == (len(b0), 2)
    assert np.linalg.norm(b0 + B[:, 0]) < 0.97 * np.linalg.norm(b0)  # (part of b is the static pose)
    # re-measure b at half a unit of alpha_M, as discretisation does
    offset = {"stiffness_scale": [new.offset_reference]}
    fine = disc._refined_problem(P)
    np.testing.assert_allclose(disc._measure(P, fine, ctx, offset, {}), b0, atol=1e-12)
    b_half = disc._measure(P, fine, ctx, offset, {"rayleigh_damping": [0.5, 0.0]})
    g = fitting.geometric(np.array([0.5, 0.0]), P.disc_bias_ratio)
    assert 0.2 <= P.disc_bias_ratio[0] <= 1.0 and g[1] == 0.0
    assert np.linalg.norm(b_half - (b0 + g[0] * B[:, 0])) < 0.5 * np.linalg.norm(b_half - b0)
    # and fitting.discrepancy is that model
    d = np.array([0.5, 0.0])
    np.testing.assert_allclose(fitting.discrepancy(P, P.train, d), b0 + g[0] * B[:, 0], atol=1e-12)


def test_cli_diagnose_passes_follow_damping(tmp_path, monkeypatch):
    """`matlearn diagnose --follow-damping` turns the option on; without it the default applies."""
    import matlearn.diagnosis as diag
    from diagnosis_cases import tiny_case

    from matlearn.cli import main

    path = tiny_case(tmp_path, "bar", cells=(3, 1, 1))
    seen = []

    def fake(scene, out, **kw):
        seen.append(kw.get("follow_damping"))
        return {"verdict": [], "gap_before": {"max_error_pct": 1.0}}

    monkeypatch.setattr(diag, "diagnose", fake)
    assert main(["diagnose", str(path), "--out", str(tmp_path / "a"), "--no-report", "--follow-damping"]) in (0, None)
    assert main(["diagnose", str(path), "--out", str(tmp_path / "b"), "--no-report"]) in (0, None)
    assert seen == [True, None]
