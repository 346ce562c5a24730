"""Distillation of the learned RBF correction into a small MLP (method.md section 6).

Samples come from many forward simulations with the RBF model: the train recordings' motions
from their initial poses scaled about the rest shape by factors <= 1, i.e. the range of states
the simulations actually visit (larger factors put most samples where the RBF itself
extrapolates, and their spread dominates the normalisation). Frames are subsampled with a
stride; `offset` picks a disjoint set of frames for held-out agreement. The target is the total principal-stress correction: the elastic RBF part
plus the damping part expressed as a principal stress, dalpha_eff * (dPh_nom/dFh) Fhdot, where
dalpha_eff is the change of the clamped alpha_K. The MLP is 6 -> 6 -> 6 -> 3 with batch norm +
ELU, inputs and outputs normalised to zero mean / unit variance, samples shuffled, seeded; for
export the batch norm is folded into the preceding linear layers and the network runs in C++
(`_core.correction.MlpCorrection`).
"""
from __future__ import annotations

import time

import numpy as np

from .. import _core
from ..replay import initial_state, simulate_recording


def correction_samples(nominal_model, rbf_model, X, V, material) -> tuple[np.ndarray, np.ndarray]:
    """Inputs (k, 6) = (Fh, Fhdot) and targets (k, 3) over frames X, V (F, n, 3); material =
    (law name, mu (m,), lambda (m,), edits) of the nominal model."""
    ins, outs = [], []
    mat = nominal_model
    for x, v in zip(X, V):  # per frame, each a C++ call over all elements
        Fh, Fhd, Ph_tot, aK = rbf_model.principal_kinematics(x, v)
        _, _, Ph_nom, aK_nom = mat.principal_kinematics(x, v)
        Fh, Fhd = np.asarray(Fh), np.asarray(Fhd)
        dP = np.asarray(Ph_tot) - np.asarray(Ph_nom)
        dalpha = np.asarray(aK) - np.asarray(aK_nom)
        # Damping stress per unit alpha_K in the principal frame: diag(dPh/dFh) * Fhdot.
        dPn = _fd_diag(material, Fh, 1e-6)
        ins.append(np.concatenate([Fh, Fhd], axis=1))
        outs.append(dP + dalpha[:, None] * dPn * Fhd)
    return np.concatenate(ins), np.concatenate(outs)


def _fd_diag(material, Fh, h):
    """Diagonal of dPh_nominal/dFh per element (m, 3) by central differences of the C++
    principal stress (vectorised over elements)."""
    name, mu, lam, edits = material
    out = np.empty_like(Fh)
    for i in range(3):
        e = np.zeros(3)
        e[i] = h
        Pp = np.asarray(_core.fem.principal_stress(name, Fh + e, mu, lam, edits))
        Pm = np.asarray(_core.fem.principal_stress(name, Fh - e, mu, lam, edits))
        out[:, i] = (Pp[:, i] - Pm[:, i]) / (2 * h)
    return out


def simulation_samples(scene, rbf_correction, recordings, scales=(0.5, 0.75, 1.0),
                       max_samples: int = 30000, seed: int = 0, stride: int = 5, offset: int = 0):
    """Run the RBF model through every recording's motion from its initial pose scaled about
    the rest shape by each factor; collect (inputs, targets) on frames offset, offset + stride,
    ... (a different offset gives held-out frames of the same simulations)."""
    nominal = scene.model()
    rbf_model = scene.model(rbf_correction)
    mu, lam = scene.material.lame(scene.mesh.num_tets)
    material = (scene.material.model, mu, lam, [tuple(map(float, e)) for e in scene.material.edits])
    V0 = np.asarray(scene.mesh.vertices, float)
    ins, outs = [], []
    for rec in recordings:
        x0, v0 = initial_state(scene, rbf_model, rec)
        for s in scales:
            xs = V0 + s * (np.asarray(x0) - V0)
            try:
                _, X, Vel = simulate_recording(scene, rbf_model, rec, state=(xs, v0))
            except RuntimeError:
                continue  # a scaled pose the model cannot hold: skip it
            a, b = correction_samples(nominal, rbf_model, X[offset::stride], Vel[offset::stride], material)
            ins.append(a)
            outs.append(b)
    if not ins:
        raise RuntimeError("distill: no simulation produced samples")
    X, Y = np.concatenate(ins), np.concatenate(outs)
    rng = np.random.default_rng(seed)
    if len(X) > max_samples:
        keep = rng.choice(len(X), max_samples, replace=False)
        X, Y = X[keep], Y[keep]
    return X, Y


def train_mlp(X, Y, epochs: int = 60, batch: int = 1024, lr: float = 1e-2, seed: int = 0,
              hidden: int = 6) -> tuple[dict, dict]:
    """Train 6 -> hidden -> hidden -> 3 (BatchNorm + ELU) on normalised data; returns (exported
    dict with BN folded, info)."""
    import torch

    torch.manual_seed(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 6-wide network gains nothing from threads
    rng = np.random.default_rng(seed)
    in_mean, in_std = X.mean(0), X.std(0) + 1e-12
    out_mean, out_std = Y.mean(0), Y.std(0) + 1e-12
    Xn = torch.tensor((X - in_mean) / in_std, dtype=torch.float64)
    Yn = torch.tensor((Y - out_mean) / out_std, dtype=torch.float64)
    net = torch.nn.Sequential(
        torch.nn.Linear(6, hidden), torch.nn.BatchNorm1d(hidden), torch.nn.ELU(),
        torch.nn.Linear(hidden, hidden), torch.nn.BatchNorm1d(hidden), torch.nn.ELU(),
        torch.nn.Linear(hidden, 3)).double()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    n = len(Xn)
    t0 = time.time()
    for _ in range(epochs):
        net.train()
        perm = torch.tensor(rng.permutation(n))
        for i in range(0, n - 1, batch):
            idx = perm[i:i + batch]
            if len(idx) < 2:
                continue
            opt.zero_grad()
            loss = torch.mean((net(Xn[idx]) - Yn[idx]) ** 2)
            loss.backward()
            opt.step()
        sched.step()
    torch.set_num_threads(threads)
    net.eval()
    with torch.no_grad():
        mse = float(torch.mean((net(Xn) - Yn) ** 2))
    layers = []
    mods = list(net)
    for i in (0, 3):
        lin, bn = mods[i], mods[i + 1]
        g = (bn.weight / torch.sqrt(bn.running_var + bn.eps)).detach().numpy()
        W = lin.weight.detach().numpy() * g[:, None]
        b = (lin.bias.detach().numpy() - bn.running_mean.detach().numpy()) * g + bn.bias.detach().numpy()
        layers.append((W, b))
    layers.append((mods[6].weight.detach().numpy().copy(), mods[6].bias.detach().numpy().copy()))
    exported = {"layers": layers, "in_mean": in_mean, "in_std": in_std, "out_mean": out_mean,
                "out_std": out_std}
    return exported, {"train_mse_normalised": mse, "samples": int(n), "epochs": epochs,
                      "train_s": time.time() - t0}


def compare(rbf_correction, mlp_correction, X, Y, repeats: int = 5) -> dict:
    """NN-vs-RBF agreement on samples (X (k, 6), RBF targets Y (k, 3)): relative L2 error
    ||pred - Y|| / ||Y - mean(Y)||, and the evaluation speed ratio (RBF time / MLP time, same
    inputs, same process, best of `repeats`; omitted when repeats is 0 or rbf_correction None)."""
    Fh, Fhd = np.ascontiguousarray(X[:, :3]), np.ascontiguousarray(X[:, 3:])
    pred = np.asarray(mlp_correction.evaluate(Fh, Fhd)[0])
    err = pred - Y
    rel = float(np.linalg.norm(err) / max(np.linalg.norm(Y - Y.mean(0)), 1e-300))
    out = {"relative_error": rel, "max_abs_error_pa": float(np.abs(err).max()), "samples": int(len(X))}
    if repeats < 1 or rbf_correction is None:
        return out

    def best(fn):
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        return min(ts)

    t_rbf = best(lambda: rbf_correction.evaluate(Fh, Fhd))
    t_mlp = best(lambda: mlp_correction.evaluate(Fh, Fhd))
    out.update({"rbf_eval_s": t_rbf, "mlp_eval_s": t_mlp, "speed_ratio_rbf_over_mlp": t_rbf / t_mlp})
    return out
