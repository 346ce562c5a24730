"""Options of the outer learning loop (`matlearn.learning.loop`), with their checks."""
from __future__ import annotations

from dataclasses import dataclass

from ..clouds.tracking import TrackOptions
from ..replay import STARTS


@dataclass
class LearnOptions:
    """iterations: max outer iterations; lam: dimensionless observation weight (None: 1 for
    marker recordings, chosen from the noise for point clouds); modes: POD modes r; centers:
    RBF centres; damping: learn the strain-dependent alpha_K change; gn_iterations:
    Gauss-Newton steps per space-time solve; pod_window: fraction of each trajectory used for
    the basis; fit_frames: max frames per recording in the fit; smoothing: weights of the
    fit's tangent penalty (fit.py: the RBF part's tangent relative to the nominal modulus)
    and ridges: relative numerical Tikhonov weights; extrapolation: (linear, edge) weight
    pairs of the penalties on what the correction does beyond the data (fit.solve_fit: the
    linear part A and the RBF part's slope where it leaves the data; (0, 0), the default: none;
    fit.EXTRAPOLATION_WEIGHTS, which the `learn` CLI and bench/learning_table.py pass, adds a
    penalised family. It is not the library default because of its cost at scale: on the 6k-tet
    bar of bench/learning_scale.py its 4 extra checks in the rejected iteration cost 3.5 forward
    simulations although each stopped after 4 % of the steps: 15.9x the forward simulation in
    all, bench/results/learning_scale.json `extrapolation_variant`); every
    (extrapolation, smoothing, ridge) triple is a candidate per iteration (the best train
    error wins; when none is stable and simulable, up to `escalate` more with 10x, 100x the
    largest smoothing weight are tried before the update is shortened); ridge_search: "all" (fit and
    forward-simulate every candidate) or "first" (in the given order, stop at the first
    whose train error is lower than the current one: one fit + one forward simulation per
    iteration instead of one per candidate, for large cases, bench/learning_scale.py); patience: iterations without
    improvement before stopping; seed: k-means seed; backtrack: shortened update steps tried
    when the full update does not lower the train error, as fractions of the full update (a
    halving ladder by default); track: tracking options for cloud recordings (None: defaults); tangent_stride: frames sharing one nominal tangent evaluation
    in the space-time Jacobian (1: every frame; the per-frame tangents dominate the space-time
    cost of long recordings at 1 ms, bench/learning_scale.py measures the tradeoff);
    refresh_correspondences: for train recordings tracked from point clouds, rounds of
    re-estimating the cloud correspondences at the space-time trajectory
    (:func:`matlearn.clouds.tracking.refresh_markers`) followed by another Gauss-Newton solve
    against the refreshed markers (method.md section 7; 0: the tracker's correspondences
    throughout; on single-view scans of a bar one round ends 2 % further from the true surface,
    tests/python/test_learn_clouds.py); early_stop: a candidate's forward check stops as soon as
    a marker error exceeds the error it must beat (ridge_search "all": the best fully checked
    candidate's, so the choice and every accepted number are those of full checks; "first" and
    shortened steps: the current error, as only an improvement is looked for); the score is a
    max over samples, so the rest cannot bring it back under (a stopped check records the error
    that exceeded, a lower bound, and `stopped_early`); gn_tolerance: a space-time solve stops
    when a Gauss-Newton step lowers the cost by less than this fraction; jacobian_every:
    Gauss-Newton steps per evaluation of the space-time Jacobian blocks (1: every step; k > 1:
    chord steps in between, re-evaluated after a shortened step; spacetime.solve_spacetime);
    retry_rejected: after an update no step of
    which lowers the train error, solve again with the rejected candidate's motion in the basis
    (while `patience` allows; False: stop there. At scale a retry costs a space-time solve and
    up to ~6 forward checks; on the 6k-tet bar of bench/learning_scale.py it gained 0.1 %
    relative train error); start_pose: how the TRAIN recordings' initial poses are estimated
    (replay.initial_state `start`: "held", the default, or "released"); the test recordings
    are always scored with replay.SCORE_START, the protocol every model is scored with;
    symmetric: fit the permutation-equivariant RBF, isotropic by construction (fit.py module
    docstring, "Symmetric fit"; False: the free fit of sessions 1-8, not isotropic);
    tangent_damping: the learned correction's elastic part also enters the stiffness-proportional
    Rayleigh damping, (alpha_K + dalpha) K_psd(nominal + correction) (`_core` Correction
    .tangent_damping; the fit linearises it at the current model). Off by default: on the edited
    spheres of bench/learning_table.py it changed the learned errors by <= 0.05 % (docs/results.md);
    extend: longer steps along an update whose full step lowers the train error, as multiples of
    it (increasing, > 1), each checked by a forward simulation and kept while it lowers the train
    error further (a line search along the update). Off by default (()): with (2, 4) the tension
    sphere of bench/learning_table.py reaches a lower train error in 6 iterations instead of 20
    and the whole table runs in half the time, but the longer steps also amplify what the train
    recordings do not determine: the held-out error rose on the StVK bar, damping bar 1 and the
    demo (docs/results.md, Learning; bench/results/learning_table_extend.json)."""

    iterations: int = 8
    lam: float | None = None
    modes: int = 20
    centers: int = 24
    damping: bool = True
    gn_iterations: int = 6
    pod_window: float = 1.0
    fit_frames: int = 150
    ridges: tuple = (1e-6,)
    ridge_search: str = "all"
    patience: int = 2
    seed: int = 0
    backtrack: tuple = (0.5, 0.25, 0.125)
    track: TrackOptions | None = None
    smoothing: tuple = (1e-3, 1e-2, 1e-1, 1.0)
    extrapolation: tuple = ((0.0, 0.0),)
    escalate: int = 2
    tangent_stride: int = 1
    refresh_correspondences: int = 0
    early_stop: bool = True
    gn_tolerance: float = 2e-3
    jacobian_every: int = 1
    retry_rejected: bool = True
    start_pose: str = "held"
    symmetric: bool = True
    tangent_damping: bool = False
    extend: tuple = ()

    def __post_init__(self):
        if self.iterations < 1 or self.modes < 1 or self.centers < 1:
            raise ValueError("iterations, modes and centers must be >= 1")
        if self.lam is not None and not self.lam > 0:
            raise ValueError(f"lambda must be > 0, got {self.lam}")
        self.backtrack = tuple(float(t) for t in self.backtrack)
        if any(not 0 < t < 1 for t in self.backtrack):
            raise ValueError(f"backtrack steps must lie in (0, 1), got {self.backtrack}")
        self.extend = tuple(float(t) for t in self.extend)
        if any(not t > 1 for t in self.extend) or list(self.extend) != sorted(self.extend):
            raise ValueError(f"extend steps must be increasing and > 1, got {self.extend}")
        if not self.ridges:
            raise ValueError("ridges: at least one ridge weight")
        self.smoothing = tuple(float(t) for t in self.smoothing)
        if not self.smoothing or any(not t >= 0 for t in self.smoothing):
            raise ValueError(f"smoothing: at least one weight, all >= 0, got {self.smoothing}")
        self.extrapolation = tuple((float(a), float(b)) for a, b in self.extrapolation)
        if not self.extrapolation or any(not (a >= 0 and b >= 0) for a, b in self.extrapolation):
            raise ValueError(f"extrapolation: at least one (linear, edge) pair, all >= 0, got {self.extrapolation}")
        if self.tangent_stride < 1:
            raise ValueError(f"tangent_stride must be >= 1, got {self.tangent_stride}")
        if self.refresh_correspondences < 0:
            raise ValueError(f"refresh_correspondences must be >= 0, got {self.refresh_correspondences}")
        if self.start_pose not in STARTS:
            raise ValueError(f"start_pose must be one of {STARTS}, got {self.start_pose!r}")
        if self.jacobian_every < 1:
            raise ValueError(f"jacobian_every must be >= 1, got {self.jacobian_every}")
        if not 0 <= self.gn_tolerance < 1:
            raise ValueError(f"gn_tolerance must lie in [0, 1), got {self.gn_tolerance}")
        if self.ridge_search not in ("all", "first"):
            raise ValueError(f"ridge_search must be 'all' or 'first', got {self.ridge_search!r}")
