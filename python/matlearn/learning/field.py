"""A per-element stiffness field fitted before learning (the "field" start, learning/start.py).

The learned correction is one function of the principal stretches (and rates) for every
element, so it cannot represent an object whose stiffness varies in space: a laminate, an
infilled print, a body with an inclusion, or any truth meshed finer than the model whose coarse
elements hold different fractions of a stiff phase. The field start gives every element (or,
on larger meshes, every spatial patch) its own Young's modulus on top of the fitted baseline:

    E_e = E_baseline exp(q_p(e)),    p(e) the patch of element e (one per element up to
                                     `max_patches`, else k-means patches of the tet centroids,
                                     volume-weighted)

q is fitted to the train recordings' markers by Levenberg-Marquardt Gauss-Newton with a
smoothness penalty on the log-stiffness jumps between face-adjacent patches,

    |r(q)|^2 + smooth * n * rms0^2 * mean_{(a,b) adjacent} (q_a - q_b)^2,

r the marker residual (% of the object size, n samples), rms0 its RMS at the baseline: at
smooth = 1 a mean jump of 1 in log E (2.7x) between neighbours costs as much as the baseline's
whole misfit. The field only replaces the start's Young's modulus; nu, density and damping stay
the baseline's, and the learner then learns its correction on top.

The Jacobian d r / d q comes from forward-mode tangents of the linearised replay
(diagnosis.linearised.stiffness_jacobian, the diagnosis's patch-map machinery): one pass
carries all patch directions through the recording, sharing each step's factorisation, instead
of one full simulation per patch; every step is accepted only when the residual of a full
simulation (`marker_residual_pct`, the objective) drops, so an approximate Jacobian can slow the
fit but not mislead it. Measured against the finite-difference fit (`jacobian="fd"`, scipy
least_squares, one simulation per patch and iteration; session 29, docs/results.md): the layered
bar (96 patches) 14 s instead of ~150 s, train rms 0.0050 vs 0.0051 %, field-start held-out
0.090 / 0.065 vs 0.087 / 0.068 %; the two-half bar (48) 4.4 s, 0.0069 vs 0.0076 %, 0.148 / 0.126 vs
0.165 / 0.133 %; the StVK bar (128 k-means patches) 5.3 s, 0.0246 vs 0.0219 %, 0.240 / 0.326 vs
0.242 / 0.337 %. Each accepted iteration is checkpointed (`checkpoint`), so a killed fit resumes.

The smoothness weight, measured with the finite-difference fit (session 28) on the layered bar
of the learning table (E = 1e5 / 1e7 in fine layers, model coarsened by 2; docs/results.md):
the homogeneous baseline scores 0.74 / 0.12 % held-out, the field 0.34 / 0.08 % (smooth 0.1),
0.36 / 0.08 % (1), 0.55 / 0.08 % (10).

A field belongs to the object it was fitted on: on another mesh (transfer) the learned model
uses the field's volume-weighted log-mean modulus (`homogeneous`).
"""
from __future__ import annotations

import hashlib

import numpy as np
from scipy.optimize import least_squares

from ..embedding import embed_points
from ..materials import Material
from .baseline import marker_residual_pct

MAX_LOG_STEP = 3.0  # bound on |q| (a factor e^3 = 20 either way from the baseline)


def face_pairs(tets: np.ndarray) -> np.ndarray:
    """(m, 2) indices of the tet pairs that share a face (each pair once, smaller index first)."""
    tets = np.asarray(tets, np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (#T, 4), got {tets.shape}")
    local = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    faces = np.sort(tets[:, local].reshape(-1, 3), axis=1)
    owner = np.repeat(np.arange(len(tets)), 4)
    order = np.lexsort(faces.T[::-1])
    f, o = faces[order], owner[order]
    same = np.all(f[1:] == f[:-1], axis=1)
    pairs = np.stack([o[:-1][same], o[1:][same]], axis=1)
    return np.sort(pairs, axis=1)


def patches(mesh, max_patches: int, seed: int = 0) -> np.ndarray:
    """Patch label per tet: the tet itself when the mesh has at most `max_patches` tets, else
    k-means (seeded) of the tet centroids into `max_patches` patches (empty ones dropped)."""
    if max_patches < 1:
        raise ValueError(f"max_patches must be >= 1, got {max_patches}")
    nt = int(mesh.num_tets)
    if nt <= max_patches:
        return np.arange(nt)
    from sklearn.cluster import KMeans

    V = np.asarray(mesh.vertices, float)
    centroids = V[np.asarray(mesh.tets)].mean(axis=1)
    labels = KMeans(max_patches, n_init=4, random_state=seed).fit(
        centroids, sample_weight=np.asarray(mesh.rest_volumes)).labels_
    return np.unique(labels, return_inverse=True)[1]


def patch_pairs(tets: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Adjacent patch pairs (patches holding face-adjacent tets), each once."""
    p = labels[face_pairs(tets)]
    p = np.sort(p[p[:, 0] != p[:, 1]], axis=1)
    return np.unique(p, axis=0) if len(p) else np.zeros((0, 2), np.int64)


def mesh_fingerprint(mesh) -> str:
    """sha1 of the mesh's rest vertices and tets: a per-element field applies to this mesh only."""
    h = hashlib.sha1(np.ascontiguousarray(np.asarray(mesh.vertices, np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(mesh.tets, np.int64)).tobytes())
    return h.hexdigest()


def homogeneous(material: Material, volumes) -> Material:
    """`material` with its Young's modulus replaced by the volume-weighted log-mean over the
    tets of `volumes` (a field carried to another mesh)."""
    volumes = np.asarray(volumes, float)
    E = np.broadcast_to(np.asarray(material.youngs_modulus, float), volumes.shape)
    Eh = float(np.exp(np.sum(volumes * np.log(E)) / np.sum(volumes)))
    return Material(material.model, Eh, float(np.mean(material.poisson_ratio)),
                    float(np.mean(material.density)), list(material.edits))


class TangentJacobian:
    """d(train marker residual, % of the size)/d(patch log-stiffness) by forward-mode tangents of
    the linearised replay (diagnosis.linearised.stiffness_jacobian: one pass for all patches,
    sharing each step's factorisation; the held pose differentiated too), in place of one full
    simulation per patch. Rows in the order of `baseline.marker_residual_pct` over the same
    recordings; None from __call__ where the layouts differ (then the caller falls back to
    finite differences). Recordings with drive points are replayed with the driven vertices
    prescribed (their motion is given), tangents too."""

    def __init__(self, scene, damping, labels):
        from ..diagnosis.linearised import patch_directions
        from ..diagnosis.problem import Problem

        self.problem = Problem(scene)
        self.damping = damping
        self.D = patch_directions(labels)
        self.passes = 0

    def __call__(self, material: Material, rows: int) -> np.ndarray | None:
        from ..diagnosis.effects import EffectContext
        from ..diagnosis.linearised import stiffness_jacobian

        sc = self.problem.scene
        ctx = EffectContext(sc.mesh, material, self.damping, sc.fixed)
        _, J = stiffness_jacobian(self.problem, ctx, {}, self.D)
        self.passes += 1
        if J.shape[0] != rows or not np.all(np.isfinite(J)):
            return None
        return 100.0 * J  # object-size units -> % of the size


def _checkpoint_read(path, k: int, fingerprint: str):
    """(q, iteration, Levenberg-Marquardt damping, converged) saved by a previous run of the same
    fit, or None."""
    import json

    if path is None or not path.exists():
        return None
    doc = json.loads(path.read_text())
    if doc.get("fingerprint") != fingerprint or len(doc.get("q", [])) != k:
        return None
    return np.asarray(doc["q"], float), int(doc["iteration"]), float(doc["damping"]), bool(doc["converged"])


def _checkpoint_write(path, q, iteration: int, damping: float, converged: bool, fingerprint: str) -> None:
    import json

    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"fingerprint": fingerprint, "iteration": iteration, "damping": damping,
                                   "converged": converged,
                                   "q": np.asarray(q, float).tolist()}))
        tmp.replace(path)


def fit_stiffness_field(scene, material: Material, damping, smooth: float = 0.3, iterations: int = 20,
                        max_patches: int = 128, seed: int = 0, log=None, jacobian: str = "tangent",
                        checkpoint=None) -> tuple[Material, dict]:
    """Fit the per-element log-stiffness field on top of `material` (the baseline fit) to the
    scene's train recordings (module docstring). Returns (material with per-tet E, info).

    jacobian: "tangent" (default): Levenberg-Marquardt Gauss-Newton whose Jacobian comes from
    forward-mode tangents (:class:`TangentJacobian`, one linearised pass per iteration for all
    patches) and whose every step is accepted only when the *simulated* residual (full Newton,
    `marker_residual_pct`) drops; "fd": scipy least_squares with a finite-difference Jacobian
    (one full simulation per patch and iteration). checkpoint: a JSON file (tangent fit) that
    holds the field after every accepted iteration; a killed fit resumes from it."""
    if not smooth >= 0:
        raise ValueError(f"smooth must be >= 0, got {smooth}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if jacobian not in ("tangent", "fd"):
        raise ValueError(f"jacobian must be 'tangent' or 'fd', got {jacobian!r}")
    recs = [r for r in scene.recordings_with_role("train") if r.num_markers > 0]
    if not recs:
        raise ValueError("stiffness field: the scene has no train recording with markers")
    mesh = scene.mesh
    nt = int(mesh.num_tets)
    E0 = np.broadcast_to(np.asarray(material.youngs_modulus, float), (nt,)).copy()
    labels = patches(mesh, max_patches, seed)
    k = int(labels.max()) + 1
    pairs = patch_pairs(mesh.tets, labels)
    embs = [embed_points(mesh, r.marker_rest) for r in recs]

    def material_of(q):
        return Material(material.model, E0 * np.exp(q[labels]), material.poisson_ratio,
                        material.density, list(material.edits))

    count, best = [0], [np.inf]
    total = (k + 1) * (iterations + 1)  # about: one Jacobian (k simulations) per iteration

    def data_residual(q):
        count[0] += 1
        r = marker_residual_pct(scene, scene.model(material=material_of(q), damping=damping), recs, embs)
        best[0] = min(best[0], float(np.sqrt(np.mean(r**2))))
        if log and jacobian == "fd" and count[0] % (k + 1) == 0:
            log(f"stiffness field: {count[0]} of ~{total} simulations, best train rms {best[0]:.4g} % of the size")
        return r

    r0 = data_residual(np.zeros(k))
    n = len(r0)
    rms0 = float(np.sqrt(np.mean(r0**2)))
    w = np.sqrt(smooth * n / max(len(pairs), 1)) * rms0
    info = {"patches": k, "adjacent_pairs": int(len(pairs)), "smooth": float(smooth),
            "iterations": int(iterations), "jacobian": jacobian}
    if jacobian == "fd":
        def residual(q):
            return np.concatenate([data_residual(q), w * (q[pairs[:, 0]] - q[pairs[:, 1]])])

        sol = least_squares(residual, np.zeros(k), bounds=(-MAX_LOG_STEP, MAX_LOG_STEP), method="trf",
                            diff_step=1e-3, max_nfev=iterations)
        q = sol.x
        rms1 = float(np.sqrt(np.mean(sol.fun[:n] ** 2)))  # the data rows of the residual at sol.x
    else:
        fingerprint = mesh_fingerprint(mesh) + f"|{E0.sum():.17g}|{smooth}|{max_patches}|{seed}"
        q, rms1, lm = _tangent_fit(scene, material_of, damping, labels, pairs, w, data_residual, r0,
                                   iterations, fingerprint, checkpoint, log)
        info.update(lm)
    if not rms1 < rms0:  # nothing gained (or a worse field): the homogeneous baseline stays
        q = np.zeros(k)
        rms1 = rms0
    info.update({"simulations": int(count[0]), "train_rms_pct_before": rms0, "train_rms_pct": rms1,
                 "log_stiffness_range": [float(q.min()), float(q.max())]})
    if log:
        log(f"stiffness field: {k} patches, train rms {rms0:.4g} -> {rms1:.4g} % of the size, "
            f"log E offsets {q.min():+.2f} .. {q.max():+.2f} ({count[0]} simulations)")
    return material_of(q), info


# Levenberg-Marquardt of the tangent fit: damping of diag(H) at the start, its growth on a
# rejected step, the tries per iteration, the largest log-stiffness change per step
LM_DAMPING = 0.05
LM_GROW = 4.0
LM_TRIES = 6
LM_MAX_STEP = 1.0


def _tangent_fit(scene, material_of, damping, labels, pairs, w, data_residual, r0, iterations,
                 fingerprint, checkpoint, log):
    """The tangent Levenberg-Marquardt fit of fit_stiffness_field (its docstring). Returns (q,
    train rms at q, info)."""
    from pathlib import Path

    k = int(labels.max()) + 1
    n = len(r0)
    S = np.zeros((len(pairs), k))  # smoothness rows: q_a - q_b per adjacent pair
    S[np.arange(len(pairs)), pairs[:, 0]] = 1.0
    S[np.arange(len(pairs)), pairs[:, 1]] = -1.0
    jac = TangentJacobian(scene, damping, labels)
    path = Path(checkpoint) if checkpoint is not None else None
    q, r, it0, lam, converged = np.zeros(k), r0, 0, LM_DAMPING, False
    got = _checkpoint_read(path, k, fingerprint)
    if got is not None:  # the state after the last finished iteration: the same path on
        q, it0, lam, converged = got
        r = data_residual(q)
        if log:
            log(f"stiffness field: resumed after iteration {it0} ({path})")

    def cost(q, r):
        s = w * (S @ q)
        return float(r @ r + s @ s)

    cur, fd_passes, done = cost(q, r), 0, it0
    for it in range(it0, iterations if not converged else it0):
        if log:
            log(f"stiffness field: iteration {it + 1} of {iterations}: tangents of {k} patches ...")
        J = jac(material_of(q), n)
        if J is None:  # layouts differ: finite differences of the simulated residual
            J = np.stack([(data_residual(q + 1e-3 * e) - r) / 1e-3 for e in np.eye(k)], axis=1)
            fd_passes += 1
        H = J.T @ J + w * w * (S.T @ S)
        g = J.T @ r + w * w * (S.T @ (S @ q))
        d = np.diag(H).copy() + 1e-12 * max(float(np.mean(np.diag(H))), 1e-300)
        accepted = False
        for _ in range(LM_TRIES):
            step = -np.linalg.solve(H + lam * np.diag(d), g)
            if np.abs(step).max() > LM_MAX_STEP:
                step *= LM_MAX_STEP / np.abs(step).max()
            qn = np.clip(q + step, -MAX_LOG_STEP, MAX_LOG_STEP)
            rn = data_residual(qn)
            cn = cost(qn, rn)
            if cn < cur:
                accepted = True
                break
            lam *= LM_GROW
        if not accepted:
            break
        converged = cur - cn < 1e-3 * cn  # less than 0.1 % of the cost gained: stop
        q, r, cur, lam, done = qn, rn, cn, max(lam / 3.0, 1e-4), it + 1
        _checkpoint_write(path, q, done, lam, converged, fingerprint)
        if log:
            log(f"stiffness field: iteration {done} of {iterations}, train rms "
                f"{np.sqrt(np.mean(r**2)):.4g} % of the size")
        if converged:
            break
    return q, float(np.sqrt(np.mean(r**2))), {"tangent_passes": jac.passes, "fd_passes": fd_passes,
                                              "iterations_done": done}
