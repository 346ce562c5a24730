"""Convergence and error-histogram plots of a learning run (PNG, matplotlib Agg)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_convergence(metrics: list, path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metrics = [m for m in metrics if m.get("train")]
    its = [m["iteration"] for m in metrics]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for role, style in (("train", "-o"), ("test", "-s")):
        if metrics[0].get(role):
            ax[0].semilogy(its, [m[role]["max_error_pct"] for m in metrics], style, label=f"{role} max")
            ax[0].semilogy(its, [m[role]["rms_error_pct"] for m in metrics], style, alpha=0.5,
                           label=f"{role} rms")
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("marker error (% of object size)")
    ax[0].legend()
    ax[0].set_title("forward-simulation error")
    cf = [(m["iteration"], m["control_force_rms"]) for m in metrics if "control_force_rms" in m]
    if cf:
        ax[1].semilogy(*zip(*cf), "-o")
    ax[1].set_xlabel("iteration")
    ax[1].set_ylabel("control force rms (N, reduced)")
    ax[1].set_title("control-force magnitude")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_error_histograms(samples: dict, path, role: str = "test") -> Path:
    """One histogram of per-sample marker errors per iteration (role 'test', else 'train')."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def per_iter(r):
        out = {}
        for key, arr in samples.items():
            _, k, name = key.split("_", 2)
            if name.startswith(r):
                out.setdefault(int(k), []).append(np.asarray(arr))
        return {k: np.concatenate(v) for k, v in sorted(out.items())}

    data = per_iter(role) or per_iter("train")
    n = max(len(data), 1)
    cols = min(4, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    hi = max((v.max() for v in data.values()), default=1.0)
    bins = np.linspace(0, hi, 40)
    for ax, (k, v) in zip(axes.ravel(), data.items()):
        ax.hist(v, bins=bins, color="C0")
        ax.set_title(f"iteration {k}: max {v.max():.2f}%", fontsize=9)
        ax.set_xlabel("error (% size)", fontsize=8)
    for ax in axes.ravel()[len(data):]:
        ax.axis("off")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
