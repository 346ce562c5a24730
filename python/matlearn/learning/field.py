"""A per-element stiffness field fitted before learning (the "field" start, learning/start.py).

The learned correction is one function of the principal stretches (and rates) for every
element, so it cannot represent an object whose stiffness varies in space: a laminate, an
infilled print, a body with an inclusion, or any truth meshed finer than the model whose coarse
elements hold different fractions of a stiff phase. The field start gives every element (or,
on larger meshes, every spatial patch) its own Young's modulus on top of the fitted baseline:

    E_e = E_baseline exp(q_p(e)),    p(e) the patch of element e (one per element up to
                                     `max_patches`, else k-means patches of the tet centroids,
                                     volume-weighted)

q is fitted to the train recordings' markers by a trust-region Gauss-Newton fit on full
simulations (scipy.optimize.least_squares, finite-difference Jacobian: one simulation per patch
and iteration), with a smoothness penalty on the log-stiffness jumps between face-adjacent
patches,

    |r(q)|^2 + smooth * n * rms0^2 * mean_{(a,b) adjacent} (q_a - q_b)^2,

r the marker residual (% of the object size, n samples), rms0 its RMS at the baseline: at
smooth = 1 a mean jump of 1 in log E (2.7x) between neighbours costs as much as the baseline's
whole misfit. The field only replaces the start's Young's modulus; nu, density and damping stay
the baseline's, and the learner then learns its correction on top. Measured on the layered bar
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


def fit_stiffness_field(scene, material: Material, damping, smooth: float = 0.3, iterations: int = 8,
                        max_patches: int = 128, seed: int = 0, log=None) -> tuple[Material, dict]:
    """Fit the per-element log-stiffness field on top of `material` (the baseline fit) to the
    scene's train recordings (module docstring). Returns (material with per-tet E, info)."""
    if not smooth >= 0:
        raise ValueError(f"smooth must be >= 0, got {smooth}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
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
        if log and count[0] % (k + 1) == 0:
            log(f"stiffness field: {count[0]} of ~{total} simulations, best train rms {best[0]:.4g} % of the size")
        return r

    r0 = data_residual(np.zeros(k))
    n = len(r0)
    rms0 = float(np.sqrt(np.mean(r0**2)))
    w = np.sqrt(smooth * n / max(len(pairs), 1)) * rms0

    def residual(q):
        return np.concatenate([data_residual(q), w * (q[pairs[:, 0]] - q[pairs[:, 1]])])

    sol = least_squares(residual, np.zeros(k), bounds=(-MAX_LOG_STEP, MAX_LOG_STEP), method="trf",
                        diff_step=1e-3, max_nfev=iterations)
    q = sol.x
    rms1 = float(np.sqrt(np.mean(sol.fun[:n] ** 2)))  # the data rows of the residual at sol.x
    if not rms1 < rms0:  # nothing gained (or a worse field): the homogeneous baseline stays
        q = np.zeros(k)
        rms1 = rms0
    info = {"patches": k, "adjacent_pairs": int(len(pairs)), "smooth": float(smooth),
            "iterations": int(iterations), "simulations": int(count[0]),
            "train_rms_pct_before": rms0, "train_rms_pct": rms1,
            "log_stiffness_range": [float(q.min()), float(q.max())]}
    if log:
        log(f"stiffness field: {k} patches, train rms {rms0:.4g} -> {rms1:.4g} % of the size, "
            f"log E offsets {q.min():+.2f} .. {q.max():+.2f} ({count[0]} simulations)")
    return material_of(q), info
