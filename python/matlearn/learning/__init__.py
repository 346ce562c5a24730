"""Learning elastic and damping corrections from sparse recordings (method.md sections 4-6).

Public API:
* :func:`learn` / :class:`LearnOptions` — the outer loop (loop.py);
* :func:`save_model` / :func:`load_model` — learned models on disk (io.py);
* :func:`build_problem`, :func:`solve_spacetime` — space-time solve and control forces;
* :func:`fit_correction`, :class:`RbfParams` — RBF fit from control forces;
* :func:`pod_basis`, :func:`initial_trajectory`;
* :func:`transfer_score` — a learned correction on another scene (transfer.py);
* :func:`stress_scale_check` — whether the recordings determine a model's stress scale (identify.py).
"""
from .fit import FitFrames, RbfParams, fit_correction
from .identify import stress_scale_check
from .initial import initial_trajectory
from .io import load_model, save_model
from .loop import LearnOptions, learn
from .pod import pod_basis
from .spacetime import build_problem, observation_weight, solve_spacetime
from .transfer import transfer_score

__all__ = [
    "FitFrames", "RbfParams", "fit_correction", "initial_trajectory", "load_model", "save_model",
    "LearnOptions", "learn", "pod_basis", "build_problem", "observation_weight", "solve_spacetime",
    "transfer_score", "stress_scale_check",
]
