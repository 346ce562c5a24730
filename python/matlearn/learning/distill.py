"""Distillation of the learned RBF correction into a small MLP (method.md section 6).

What the MLP must reproduce. The RBF correction (cpp/correction) has two parts, both functions
of the principal stretches Fh only: an elastic principal-stress change dPh(Fh) and a damping part
dalpha(Fh), the additive change of the element's stiffness-proportional Rayleigh coefficient
alpha_K. The Model (cpp/fem/model.cpp) applies dalpha as (alpha_K + dalpha)_+ times the nominal
(PSD-projected) stiffness-damping stress, which acts on *all* strain rates of the element, shear
rates included. A network with 3 principal-stress outputs cannot express that (it only sees the
diagonal of U^T Fdot V); folding the damping into 3 outputs made the distilled simulations drift
0.6-1.3 % on bar_damping_2. So the MLP has 4 outputs, (dPh, dalpha), 6 -> 6 -> 6 -> 4, and its
dalpha enters the Model through the same clamped path as the RBF's (total alpha_K never negative:
passive by construction).

Inputs are (Fh, Fhdot), 6 as in the paper. By default the Fhdot inputs are masked (their
first-layer weights are zero, exported as zero columns): the RBF being distilled has no rate
dependence besides dalpha, and an MLP stress that depended on Fhdot could add energy (nothing
makes such a learned viscous stress dissipative). `rate_inputs=True` keeps them.

Samples come from many forward simulations with the RBF model: the train recordings' motions
from their initial poses scaled about the rest shape by factors <= 1, i.e. the range of states
the simulations actually visit (larger factors put most samples where the RBF itself
extrapolates, and their spread dominates the normalisation). Frames are subsampled with a
stride; `offset` picks a disjoint set of frames for held-out agreement. Training: batch norm +
ELU, inputs and outputs normalised to zero mean / unit variance, samples shuffled, seeded; for
export the batch norm (and the input mask) is folded into the linear layers and the network runs
in C++ (`_core.correction.MlpCorrection`).

Coincident stretches: a stress correction must give dPh_i = dPh_j where s_i = s_j (an isotropic
function of F), or the stress depends on the arbitrary principal frame there and the force jumps.
The trained network is not isotropic (on the StVK bar ~40 Pa apart at s_1 = s_2, against ~1 Pa
for the RBF it distils), and the time step's Newton cycled: 68 of 300 steps at the factorisation
limit, 637 factorisations against the RBF's 22. MlpCorrection therefore blends the stress outputs
to be equal at coincidence, over a tenth of the training spread of the stretches (23
factorisations, replay unchanged to 1e-4 % of the object size). Tried instead: a training penalty
on the outputs' differences at coincident stretches (weight 1): consistent, but the 6-wide net
then fits worse (held-out relative error 0.12 -> 0.15 on the StVK bar, 0.31 -> 0.43 on
bar_damping_2, and 0.041 -> 0.073 on an isotropic analytic target).
"""
from __future__ import annotations

import time

import numpy as np

from ..replay import initial_state, simulate_recording

TARGETS = ("dP1", "dP2", "dP3", "dalpha")  # target columns: principal stress change (Pa), alpha_K change (s)


def correction_samples(model, rbf_correction, X, V) -> tuple[np.ndarray, np.ndarray]:
    """Inputs (k, 6) = (Fh, Fhdot) and targets (k, 4) = (dPh, dalpha) of the RBF correction over
    frames X, V (F, n, 3) of `model` (one C++ call per frame over all elements)."""
    ins, outs = [], []
    for x, v in zip(X, V):
        Fh, Fhd = (np.ascontiguousarray(a) for a in model.principal_kinematics(x, v)[:2])
        dP, _, _, dal = rbf_correction.evaluate(Fh, Fhd)
        ins.append(np.concatenate([Fh, Fhd], axis=1))
        outs.append(np.concatenate([np.asarray(dP), np.asarray(dal)[:, None]], axis=1))
    return np.concatenate(ins), np.concatenate(outs)


def simulation_samples(scene, rbf_correction, recordings, scales=(0.5, 0.75, 1.0),
                       max_samples: int = 30000, seed: int = 0, stride: int = 5, offset: int = 0):
    """Run the RBF model through every recording's motion from its initial pose (held by the RBF
    model, or by the nominal one where the RBF model's static solve fails) scaled about the rest
    shape by each factor; collect (inputs (k, 6), targets (k, 4)) on frames offset,
    offset + stride, ... (a different offset gives held-out frames of the same simulations)."""
    rbf_model = scene.model(rbf_correction)
    V0 = np.asarray(scene.mesh.vertices, float)
    ins, outs = [], []
    for rec in recordings:
        try:
            x0, v0 = initial_state(scene, rbf_model, rec)
        except RuntimeError:  # the RBF model cannot hold the pose: start from the nominal's
            x0, v0 = initial_state(scene, scene.model(), rec)
        for s in scales:
            xs = V0 + s * (np.asarray(x0) - V0)
            try:
                _, X, Vel = simulate_recording(scene, rbf_model, rec, state=(xs, v0))
            except RuntimeError:
                continue  # a scaled pose the model cannot hold: skip it
            a, b = correction_samples(rbf_model, rbf_correction, X[offset::stride], Vel[offset::stride])
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


def make_net(outputs: int = 4, hidden: int = 6, rate_inputs: bool = False):
    """The torch network (float64): input mask (Fhdot columns zero unless rate_inputs), then
    Linear 6->hidden, BatchNorm, ELU, Linear hidden->hidden, BatchNorm, ELU, Linear hidden->outputs."""
    import torch

    class Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.register_buffer("mask", torch.tensor([1.0] * 3 + [1.0 if rate_inputs else 0.0] * 3,
                                                      dtype=torch.float64))
            self.body = torch.nn.Sequential(
                torch.nn.Linear(6, hidden), torch.nn.BatchNorm1d(hidden), torch.nn.ELU(),
                torch.nn.Linear(hidden, hidden), torch.nn.BatchNorm1d(hidden), torch.nn.ELU(),
                torch.nn.Linear(hidden, outputs)).double()

        def forward(self, x):
            return self.body(x * self.mask)

    if outputs not in (3, 4):
        raise ValueError(f"outputs must be 3 (dPh) or 4 (dPh, dalpha), got {outputs}")
    return Net()


def export_net(net, in_mean, in_std, out_mean, out_std) -> dict:
    """dict(layers=[(W, b), ...], in_mean, in_std, out_mean, out_std) for MlpCorrection: the
    input mask and the batch norms (running statistics, eval mode) folded into the linear layers."""
    import torch

    mods = list(net.body)
    mask = net.mask.detach().numpy()
    layers = []
    for k, i in enumerate((0, 3)):
        lin, bn = mods[i], mods[i + 1]
        g = (bn.weight / torch.sqrt(bn.running_var + bn.eps)).detach().numpy()
        W = lin.weight.detach().numpy() * g[:, None]
        if k == 0:
            W = W * mask[None, :]
        b = (lin.bias.detach().numpy() - bn.running_mean.detach().numpy()) * g + bn.bias.detach().numpy()
        layers.append((W.copy(), b.copy()))
    layers.append((mods[6].weight.detach().numpy().copy(), mods[6].bias.detach().numpy().copy()))
    return {"layers": layers, "in_mean": np.asarray(in_mean, float), "in_std": np.asarray(in_std, float),
            "out_mean": np.asarray(out_mean, float), "out_std": np.asarray(out_std, float)}


def train_mlp(X, Y, epochs: int = 60, batch: int = 1024, lr: float = 1e-2, seed: int = 0,
              hidden: int = 6, rate_inputs: bool = False) -> tuple[dict, dict]:
    """Train 6 -> hidden -> hidden -> Y.shape[1] (BatchNorm + ELU) on normalised, shuffled
    samples X (k, 6), Y (k, 4) = (dPh, dalpha) (or (k, 3): stress only); returns (exported dict
    with BN folded, info)."""
    import torch

    X, Y = np.asarray(X, float), np.asarray(Y, float)
    if X.ndim != 2 or X.shape[1] != 6 or Y.ndim != 2 or Y.shape[1] not in (3, 4) or len(X) != len(Y):
        raise ValueError(f"train_mlp: need X (k, 6) and Y (k, 3 or 4), got {X.shape} and {Y.shape}")
    torch.manual_seed(seed)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 6-wide network gains nothing from threads
    rng = np.random.default_rng(seed)
    in_mean, in_std = X.mean(0), X.std(0) + 1e-12
    out_mean, out_std = Y.mean(0), Y.std(0) + 1e-12
    Xn = torch.tensor((X - in_mean) / in_std, dtype=torch.float64)
    Yn = torch.tensor((Y - out_mean) / out_std, dtype=torch.float64)
    net = make_net(Y.shape[1], hidden, rate_inputs)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    n = len(Xn)
    t0 = time.time()
    try:
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
        net.eval()
        with torch.no_grad():
            per_out = torch.mean((net(Xn) - Yn) ** 2, dim=0).numpy()
    finally:
        torch.set_num_threads(threads)
    exported = export_net(net, in_mean, in_std, out_mean, out_std)
    return exported, {"train_mse_normalised": float(per_out.mean()),
                      "train_mse_normalised_per_output": [float(v) for v in per_out],
                      "samples": int(n), "epochs": epochs, "hidden": hidden, "outputs": int(Y.shape[1]),
                      "rate_inputs": rate_inputs, "train_s": time.time() - t0}


def _rel(err, ref) -> float:
    return float(np.linalg.norm(err) / max(np.linalg.norm(ref - ref.mean(0)), 1e-300))


def compare(rbf_correction, mlp_correction, X, Y, repeats: int = 15) -> dict:
    """NN-vs-RBF agreement on samples X (k, 6) with RBF targets Y (k, 4) = (dPh, dalpha) (or
    (k, 3)): relative L2 errors ||pred - Y|| / ||Y - mean(Y)|| of the stress columns
    (`relative_error`) and of dalpha (`dalpha_relative_error`), max abs errors, and the evaluation
    speed ratios (RBF time / MLP time, same inputs, same process, interleaved, best of `repeats`;
    omitted when repeats is 0 or rbf_correction None): with Jacobians (`evaluate`, what a tangent
    needs) and values only (`evaluate_values`, what force-only evaluations use)."""
    Fh, Fhd = np.ascontiguousarray(X[:, :3]), np.ascontiguousarray(X[:, 3:])
    r = mlp_correction.evaluate(Fh, Fhd)
    pred = np.asarray(r[0])
    err = pred - Y[:, :3]
    out = {"relative_error": _rel(err, Y[:, :3]), "max_abs_error_pa": float(np.abs(err).max()),
           "samples": int(len(X))}
    if Y.shape[1] == 4:
        e_a = np.asarray(r[3]) - Y[:, 3]
        out.update({"dalpha_relative_error": _rel(e_a, Y[:, 3]), "dalpha_max_abs_error_s": float(np.abs(e_a).max())})
    if repeats < 1 or rbf_correction is None:
        return out

    # Interleaved, best of `repeats` each: on a shared machine the load changes between calls.
    calls = {"rbf_eval_s": lambda: rbf_correction.evaluate(Fh, Fhd),
             "mlp_eval_s": lambda: mlp_correction.evaluate(Fh, Fhd),
             "rbf_values_s": lambda: rbf_correction.evaluate_values(Fh, Fhd),
             "mlp_values_s": lambda: mlp_correction.evaluate_values(Fh, Fhd)}
    best = dict.fromkeys(calls, np.inf)
    for _ in range(repeats):
        for key, call in calls.items():
            t = time.perf_counter()
            call()
            best[key] = min(best[key], time.perf_counter() - t)
    out.update({**best, "speed_ratio_rbf_over_mlp": best["rbf_eval_s"] / best["mlp_eval_s"],
                "values_speed_ratio_rbf_over_mlp": best["rbf_values_s"] / best["mlp_values_s"]})
    return out
