"""The outer learning loop (method.md section 6): forward simulate with the current correction,
measure the error against the recordings, rebuild the POD basis, solve the space-time problem,
fit a new correction; repeat until neither the forward error nor the control-force magnitude
improves.

Every iteration is checkpointed (`RUN/checkpoint/iter_<k>.npz` + `RUN/metrics.json`), so a
killed run continues with `resume=True` from its last finished iteration and gives the same
result (all steps are deterministic for a given seed; the checkpoint stores the fitted
correction and the space-time trajectories at full precision).

Decisions (basis, stopping, which iterate to keep) use the *train* recordings only; test
recordings are scored for the metrics and never fed back.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..embedding import embed_points
from ..replay import initial_state, interpolate_frames, simulate_recording
from .fit import FitFrames, RbfParams, fit_correction
from .initial import initial_trajectory
from .pod import pod_basis
from .spacetime import build_problem, constrained_vertices, solve_spacetime


@dataclass
class LearnOptions:
    """iterations: max outer iterations; lam: dimensionless observation weight; modes: POD
    modes r; centers: RBF centres; damping: learn the strain-dependent alpha_K change;
    gn_iterations: Gauss-Newton steps per space-time solve; pod_window: fraction of each
    trajectory used for the basis; fit_frames: max frames per recording in the fit; ridges:
    relative Tikhonov weights tried per iteration (the best train error wins); patience: iterations without improvement before stopping;
    seed: k-means seed; backtrack: a new correction whose train error exceeds this factor times
    the best so far is halved towards the previous one (at most twice)."""

    iterations: int = 8
    lam: float = 1.0
    modes: int = 20
    centers: int = 24
    damping: bool = True
    gn_iterations: int = 6
    pod_window: float = 1.0
    fit_frames: int = 150
    ridges: tuple = (1e-6, 1e-4, 1e-2)
    patience: int = 2
    seed: int = 0
    backtrack: float = 1.5

    def __post_init__(self):
        if self.iterations < 1 or self.modes < 1 or self.centers < 1:
            raise ValueError("iterations, modes and centers must be >= 1")
        if not self.lam > 0:
            raise ValueError(f"lambda must be > 0, got {self.lam}")


def robust_initial_state(scene, model, rec, emb):
    """replay.initial_state, retried without its marker-misfit refinement when that static
    solve fails, and last with the nominal model's held pose (a learned correction can make
    the static Newton solve of the held pose fail although dynamic steps, regularised by the
    mass, are fine; the pose is then slightly inconsistent with the model, which the error
    metric sees as a small initial transient)."""
    try:
        return initial_state(scene, model, rec, emb)
    except RuntimeError:
        pass
    try:
        return initial_state(scene, model, rec, emb, refine=0)
    except RuntimeError:
        return initial_state(scene, scene.model(), rec, emb)


def _errors(scene, model, recs, embs):
    """Per-recording marker errors (arrays of seen-sample errors, % of size) and simulations."""
    out, sims = [], []
    size = scene.object_size
    for rec, emb in zip(recs, embs):
        sim = simulate_recording(scene, model, rec, state=robust_initial_state(scene, model, rec, emb))
        P = interpolate_frames(sim[0], emb.apply(sim[1]), rec.times)
        seen = rec.seen
        out.append(100.0 * np.linalg.norm(P - rec.markers, axis=2)[seen] / size)
        sims.append(sim)
    return out, sims


def _summary(errs):
    if not errs:
        return None
    allv = np.concatenate(errs)
    return {"max_error_pct": float(allv.max()), "rms_error_pct": float(np.sqrt(np.mean(allv**2))),
            "per_recording_max_pct": [float(e.max()) for e in errs]}


def _blend(a: RbfParams | None, b: RbfParams, t: float) -> RbfParams:
    """(1 - t) a + t b for corrections on the same centres (a None: the zero correction)."""
    if a is None:
        a = RbfParams(b.centers, np.zeros_like(b.weights), np.zeros((3, 3)), np.zeros(3),
                      np.zeros_like(b.alpha_weights), 0.0, b.epsilon)
    mix = lambda x, y: (1 - t) * np.asarray(x) + t * np.asarray(y)  # noqa: E731
    return RbfParams(b.centers, mix(a.weights, b.weights), mix(a.linear, b.linear), mix(a.bias, b.bias),
                     mix(a.alpha_weights, b.alpha_weights), float(mix(a.alpha_bias, b.alpha_bias)),
                     b.epsilon)


class Learner:
    """Runs the loop for one scene into `run_dir`; see the module docstring."""

    def __init__(self, scene, run_dir, options: LearnOptions | None = None, log=print):
        self.scene = scene
        self.run = Path(run_dir)
        self.opt = options or LearnOptions()
        self.log = log or (lambda *a: None)
        self.train = scene.recordings_with_role("train")
        self.test = scene.recordings_with_role("test")
        self.train = [r for r in self.train if r.num_markers > 0]
        if not self.train:
            raise ValueError("the scene has no 'train' recording with markers to learn from")
        self.test = [r for r in self.test if r.num_markers > 0]
        mesh = scene.mesh
        self.emb_train = [embed_points(mesh, r.marker_rest) for r in self.train]
        self.emb_test = [embed_points(mesh, r.marker_rest) for r in self.test]
        self.nominal = scene.model()
        self.metrics: list[dict] = []
        self.hist: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ checkpoints
    def _ckpt(self, k):
        return self.run / "checkpoint" / f"iter_{k:03d}.npz"

    def _save_checkpoint(self, k, params, st_X):
        d = self.run / "checkpoint"
        d.mkdir(parents=True, exist_ok=True)
        arrays = {f"st_X{i}": X for i, X in enumerate(st_X)}
        if params is not None:
            arrays.update(params.to_arrays())
        tmp = self._ckpt(k).with_suffix(".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        tmp.replace(self._ckpt(k))
        self._write_metrics()

    def _write_metrics(self):
        self.run.mkdir(parents=True, exist_ok=True)
        doc = {"options": asdict(self.opt), "iterations": self.metrics}
        tmp = self.run / "metrics.json.tmp"
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(self.run / "metrics.json")
        with open(self.run / "error_samples.npz", "wb") as f:
            np.savez(f, **self.hist)

    def _load_resume(self):
        """(next iteration, params, st_X) from the last finished checkpoint, or None."""
        mfile = self.run / "metrics.json"
        if not mfile.exists():
            return None
        doc = json.loads(mfile.read_text())
        its = [m for m in doc["iterations"] if "fit" in m and self._ckpt(m["iteration"]).exists()]
        if not its:
            return None
        k = its[-1]["iteration"]
        self.metrics = [m for m in doc["iterations"] if m["iteration"] <= k]
        if (self.run / "error_samples.npz").exists():
            with np.load(self.run / "error_samples.npz") as z:
                self.hist = {key: z[key] for key in z.files if int(key.split("_")[1]) <= k}
        with np.load(self._ckpt(k)) as z:
            params = RbfParams.from_arrays(z) if "rbf_centers" in z.files else None
            st_X = [z[f"st_X{i}"] for i in range(len(self.train))]
        return k + 1, params, st_X

    # ------------------------------------------------------------------ one iteration
    def _spacetime(self, model, sims, st_X, k):
        """Space-time for every train recording; returns (fit frames, new st_X, info)."""
        frames, new_X, info = [], [], []
        V = np.asarray(self.scene.mesh.vertices, float)
        for i, (rec, emb, sim) in enumerate(zip(self.train, self.emb_train, sims)):
            t0 = time.time()
            if st_X is None:
                _, X0, _ = initial_trajectory(self.scene, model, rec, emb)
            else:
                X0 = st_X[i]
            cons, _, _ = constrained_vertices(self.scene, rec)
            setup_base = V  # POD on displacements from rest; driven rows are zeroed anyway
            phi = pod_basis([sim[1], X0], setup_base, cons, self.opt.modes, self.opt.pod_window)
            setup = build_problem(self.scene, model, rec, phi, self.opt.lam, emb)
            out = solve_spacetime(setup, X0, iterations=self.opt.gn_iterations)
            fc = out["control_forces"]
            red = fc.reshape(len(fc), -1) @ phi
            stride = max(1, int(np.ceil(len(fc) / self.opt.fit_frames)))
            frames.append(FitFrames(out["X"][2::stride], out["V"][2::stride], fc[::stride], phi))
            new_X.append(out["X"])
            info.append({"cost": out["report"]["cost"], "cg_iterations": out["report"]["cg_iterations"],
                         "control_force_rms": float(np.sqrt(np.mean(red**2))), "modes": int(phi.shape[1]),
                         "frames": int(len(out["X"])), "wall_s": time.time() - t0})
        return frames, new_X, info

    def run_loop(self, resume: bool = False) -> dict:
        opt = self.opt
        start, params, st_X = 0, None, None
        if resume:
            state = self._load_resume()
            if state is not None:
                start, params, st_X = state
                self.log(f"resuming at iteration {start}")
        best = {"train": np.inf, "cf": np.inf, "stale": 0}
        for m in self.metrics:  # replay the stopping state of resumed iterations
            if m.get("train"):
                self._update_best(best, m)
        prev_params = None
        if start > 1:
            with np.load(self._ckpt(start - 2)) as z:
                prev_params = RbfParams.from_arrays(z)
        k = start
        while True:
            t0 = time.time()
            evaluated = None
            step = 1.0
            for attempt in range(4 if params is not None else 1):
                model = self.scene.model(params.correction() if params is not None else None)
                try:
                    tr_err, sims = _errors(self.scene, model, self.train, self.emb_train)
                    worse = max(e.max() for e in tr_err) > opt.backtrack * best["train"]
                    if params is not None and worse and attempt < 2:
                        # Much worse than the best iterate: the fit overshot; step back.
                        self.log(f"iteration {k}: train error {max(e.max() for e in tr_err):.3f}% "
                                 f"> {opt.backtrack} x best; halving the update")
                        step *= 0.5
                        params = _blend(prev_params, params, 0.5)
                        continue
                    te_err, _ = _errors(self.scene, model, self.test, self.emb_test)
                    evaluated = True
                    break
                except RuntimeError as err:
                    if params is None:
                        raise
                    # The new correction cannot be simulated (divergence): step back towards
                    # the previous correction (same centres, so parameters blend linearly).
                    self.log(f"iteration {k}: forward simulation failed ({err}); halving the update")
                    evaluated = str(err)
                    step *= 0.5
                    params = _blend(prev_params, params, 0.5)
            if evaluated is not True:
                self.metrics.append({"iteration": k, "failed": evaluated, "train": None, "test": None})
                self._write_metrics()
                break
            if step < 1.0:  # the blended correction is this iteration's result
                self._save_checkpoint(k - 1, params, st_X)
            m = {"iteration": k, "train": _summary(tr_err), "test": _summary(te_err),
                 "has_correction": params is not None, "update_step": step}
            for i, e in enumerate(tr_err):
                self.hist[f"it_{k}_train{i}"] = e
            for i, e in enumerate(te_err):
                self.hist[f"it_{k}_test{i}"] = e
            self.log(f"iteration {k}: train max {m['train']['max_error_pct']:.3f}%"
                     + (f", test max {m['test']['max_error_pct']:.3f}%" if m["test"] else ""))
            stop = k >= opt.iterations or (k > 0 and best["stale"] >= opt.patience)
            if stop:
                m["wall_s"] = time.time() - t0
                self.metrics.append(m)
                self._write_metrics()
                break
            frames, st_X, st_info = self._spacetime(model, sims, st_X, k)
            m["spacetime"] = st_info
            m["control_force_rms"] = float(np.sqrt(np.mean([s["control_force_rms"] ** 2 for s in st_info])))
            prev_params = params
            centers = (params.centers, params.epsilon) if params is not None else None
            params, finfo = self._fit(frames, model if params is not None else None, centers, k)
            m["fit"] = finfo
            m["wall_s"] = time.time() - t0
            self.log(f"  control forces {m['control_force_rms']:.3e} N (reduced rms), fit residual "
                     f"{finfo['residual_ratio']:.3f} (ridge {finfo['ridge']:g}), {m['wall_s']:.1f} s")
            self.metrics.append(m)
            self._update_best(best, m)
            self._save_checkpoint(k, params, st_X)
            k += 1
        return self.finish()

    def _fit(self, frames, current_model, centers, k):
        """Fit one correction per ridge weight in options.ridges (same centres) and keep the one
        whose forward simulation best matches the *train* recordings (model selection on
        training data only)."""
        opt = self.opt
        cands = []
        for ridge in opt.ridges:
            p, info = fit_correction(self.nominal, frames, opt.centers, current_model=current_model,
                                     damping=opt.damping, ridge=ridge, seed=opt.seed + k,
                                     centers=centers)
            centers = (p.centers, p.epsilon)
            info["ridge"] = ridge
            if len(opt.ridges) == 1:
                return p, info
            try:
                err = max(e.max() for e in _errors(self.scene, self.scene.model(p.correction()),
                                                   self.train, self.emb_train)[0])
            except RuntimeError:
                err = np.inf
            info["train_max_error_pct"] = float(err)
            cands.append((err, len(cands), p, info))
        err, _, p, info = min(cands, key=lambda c: (c[0], c[1]))
        info["ridge_candidates"] = [{"ridge": c[3]["ridge"], "train_max_error_pct": c[0]} for c in cands]
        return p, info

    @staticmethod
    def _update_best(best, m):
        improved = False
        tr = m["train"]["max_error_pct"]
        if tr < 0.99 * best["train"]:
            best["train"], improved = tr, True
        cf = m.get("control_force_rms")
        if cf is not None and cf < 0.99 * best["cf"]:
            best["cf"], improved = cf, True
        best["stale"] = 0 if improved else best["stale"] + 1

    def finish(self) -> dict:
        """Pick the evaluated iterate with the lowest train error; return the summary."""
        best = min((m for m in self.metrics if m.get("train")), key=lambda m: m["train"]["max_error_pct"])
        k = best["iteration"]
        params = None
        if k > 0:
            with np.load(self._ckpt(k - 1)) as z:
                params = RbfParams.from_arrays(z)
        return {"best_iteration": k, "params": params, "metrics": self.metrics,
                "nominal": self.metrics[0], "final": best}


def learn(scene, run_dir, options: LearnOptions | None = None, resume: bool = False, log=print) -> dict:
    """Run the learning loop; returns dict(best_iteration, params (RbfParams or None when the
    nominal model was best), metrics, nominal, final)."""
    return Learner(scene, run_dir, options, log).run_loop(resume)
