"""The outer learning loop (method.md section 6): forward simulate with the current correction,
measure the error against the recordings, rebuild the POD basis, solve the space-time problem,
fit a new correction; repeat until neither the forward error nor the control-force magnitude
improves.

Monotone by construction (a trust region on the correction update): a new correction is
accepted only if its forward *train* error is lower than the current one; otherwise the update
is shortened (blended towards the current correction, same RBF centres) by the factors in
`LearnOptions.backtrack`, and when no step lowers the error the loop stops there; with
`LearnOptions.extend` (off by default) a full update that does lower it is extended to the given
multiples while that lowers it further. A candidate
whose total principal tangent (nominal + correction) loses positive definiteness beyond the
fitted stretches -- probed on a motion twice as large as the fitted one (fit.tangent_margin) --
is treated like one that cannot be simulated: a held-out motion larger than the training one
would blow up with it (layered bar of bench/learning_table.py: both test recordings diverged). So the train
error sequence never increases and the last iterate is the best. Why: with sparse observations
(6 % of the surface vertices) the control forces are only loosely determined away from the
markers and a full fit extrapolates; accepted blindly, the error grew from iteration to
iteration (bench/visibility.py, markers_6: train 0.18 -> 0.25 -> 0.40 -> 0.66 %).

Point clouds: recordings that have clouds and no markers are tracked first
(:func:`matlearn.clouds.prepare.track_scene`, cached in `RUN/tracked/`) and learned through
their tracked markers, with the observation weight chosen from the scan noise and the motion
(:func:`matlearn.clouds.prepare.cloud_lambda`) unless `lam` is given.

Every iteration is checkpointed (`RUN/checkpoint/iter_<k>.npz` + `RUN/metrics.json`), so a
killed run continues with `resume=True` from its last finished iteration and gives the same
result (all steps are deterministic for a given seed; the checkpoint stores the fitted
correction and the space-time trajectories at full precision). metrics.json also records a
fingerprint of the code that produced it (:func:`code_fingerprint`) and a resume with other
code is refused: a checkpointed correction re-scored by changed code is a different model
(bench/visibility.json's markers_13 "wrinkle", 0.05295 -> 0.05311 %, was exactly that: a
checkpoint written before the RBF box extension changed from frozen kernels to the C1
extension, re-scored after it).

Decisions (basis, lambda, accepting an update, stopping, which iterate to keep) use the *train*
recordings only; test recordings are scored for the metrics and never fed back.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..clouds.prepare import cloud_lambda, motion_scales, track_scene
from ..clouds.tracking import refresh_markers
from ..embedding import embed_points
from ..parallel import check_cancelled, pmap
from ..recording import load_recording
from ..replay import (SCORE_START, initial_state, interpolate_frames, simulate_recording, simulation_times,
                      steps_covering)
from .fit import (FitFrames, RbfParams, extension_probes, fit_system, project_linear_part,
                  solve_fit, tangent_margin)
from .initial import initial_trajectory
from .options import LearnOptions
from .pod import pod_basis
from .spacetime import build_problem, constrained_vertices, solve_spacetime


_RESULT_MODULES = ("learning", "clouds", "replay.py", "embedding.py", "scene.py", "materials.py",
                   "recording.py", "meshes.py", "release.py")


# options a resumed run may change: more (or fewer) iterations continue the same run
RESUMABLE_OPTIONS = ("iterations",)


def code_fingerprint() -> str:
    """sha1 of what a learning result depends on: the compiled core (`matlearn._core`) and the
    Python modules of the learning path (`_RESULT_MODULES`)."""
    from .. import _core

    pkg = Path(__file__).resolve().parent.parent
    files = [Path(_core.__file__)]
    for name in _RESULT_MODULES:
        q = pkg / name
        files += sorted(q.rglob("*.py")) if q.is_dir() else [q]
    h = hashlib.sha1()
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def robust_initial_state(scene, model, rec, emb, start: str = "held"):
    """replay.initial_state (`start`: "held" or "released"), retried as the held pose, then
    without its marker-misfit refinement when that static solve fails, and last with the
    nominal model's held pose (a learned correction can make the static Newton solve of the
    held pose fail although dynamic steps, regularised by the mass, are fine; the pose is then
    slightly inconsistent with the model, which the error metric sees as a small initial
    transient)."""
    if start != "held":
        try:
            return initial_state(scene, model, rec, emb, start=start)
        except RuntimeError:
            pass
    try:
        return initial_state(scene, model, rec, emb)
    except RuntimeError:
        pass
    try:
        return initial_state(scene, model, rec, emb, refine=0)
    except RuntimeError:
        return initial_state(scene, scene.model(), rec, emb)


class ErrorBoundExceeded(Exception):
    """A forward check stopped early: a marker error exceeded the bound it had to stay under.
    lower_bound: the largest error seen so far (% of size; the full max error is >= it);
    simulated: the fraction of the train recordings' steps that were simulated."""

    def __init__(self, lower_bound: float, simulated: float):
        super().__init__(f"max error >= {lower_bound:.4g} % after {100 * simulated:.0f} % of the steps")
        self.lower_bound, self.simulated = float(lower_bound), float(simulated)


# Steps per chunk of a bounded forward check: 1/CHECK_CHUNKS of the recording, at least 10.
CHECK_CHUNKS = 25


def _simulate_bounded(scene, model, rec, emb, bound, done_steps, total_steps, state):
    """simulate_recording in chunks (the trajectory is bitwise the one of a single call);
    raises ErrorBoundExceeded as soon as a marker error at a recording time already simulated
    exceeds `bound` (% of size): the score is a max over samples, so the rest of the simulation
    cannot bring it back under the bound."""
    sim_t = simulation_times(scene, rec)
    steps = len(sim_t) - 1
    size, seen = scene.object_size, rec.seen
    Ys, t_done = [], [-np.inf]

    def check(s, X):
        # an earlier recording (on the other thread) exceeded the bound, or the caller was
        # interrupted: this result is not used (never a rejection: Cancelled passes every handler)
        check_cancelled()
        Ys.append(emb.apply(X))
        t_now = sim_t[s] if s < steps else np.inf
        sel = (rec.times > t_done[0]) & (rec.times <= t_now)
        if sel.any():
            Y = np.concatenate(Ys)
            P = interpolate_frames(sim_t[:len(Y)], Y, rec.times[sel])
            e = np.linalg.norm(P - rec.markers[sel], axis=2)[seen[sel]]
            worst = 100.0 * e.max() / size if e.size else 0.0
            if worst > bound:
                raise ErrorBoundExceeded(worst, (done_steps + s) / total_steps)
        t_done[0] = t_now

    return simulate_recording(scene, model, rec, state=state,
                              chunk=max(10, int(np.ceil(steps / CHECK_CHUNKS))), after_chunk=check)


def _errors(scene, model, recs, embs, bound=np.inf, start="held", states=None):
    """Per-recording marker errors (arrays of seen-sample errors, % of size) and simulations.
    With a finite `bound` (% of size) the simulations run in chunks and stop with
    ErrorBoundExceeded as soon as an error exceeds it (what the candidate checks of the loop
    need: a candidate that cannot beat the bound is rejected without simulating the rest).
    start: the initial-state estimator (robust_initial_state); states: given initial states
    (x0, v0) per recording instead (None: estimated with `model`)."""
    size = scene.object_size
    steps = [len(simulation_times(scene, r)) - 1 for r in recs]
    total = sum(steps)

    def one(i):  # the recordings run on the cores (matlearn.parallel.pmap)
        rec, emb = recs[i], embs[i]
        state = states[i] if states is not None else robust_initial_state(scene, model, rec, emb, start)
        if np.isfinite(bound):
            # the steps before this recording's: a serial check reaches it only when every earlier
            # recording was simulated whole, so its ErrorBoundExceeded is the serial one
            sim = _simulate_bounded(scene, model, rec, emb, bound, sum(steps[:i]), total, state)
        else:
            sim = simulate_recording(scene, model, rec, state=state)
        P = interpolate_frames(sim[0], emb.apply(sim[1]), rec.times)
        return 100.0 * np.linalg.norm(P - rec.markers, axis=2)[rec.seen] / size, sim

    res = pmap(one, range(len(recs)))
    return [r[0] for r in res], [r[1] for r in res]


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
                      np.zeros_like(b.alpha_weights), 0.0, b.epsilon, b.clamp, b.tangent_damping)
    mix = lambda x, y: (1 - t) * np.asarray(x) + t * np.asarray(y)  # noqa: E731
    return RbfParams(b.centers, mix(a.weights, b.weights), mix(a.linear, b.linear), mix(a.bias, b.bias),
                     mix(a.alpha_weights, b.alpha_weights), float(mix(a.alpha_bias, b.alpha_bias)),
                     b.epsilon, b.clamp, b.tangent_damping)


class Learner:
    """Runs the loop for one scene into `run_dir`; see the module docstring."""

    def __init__(self, scene, run_dir, options: LearnOptions | None = None, log=print):
        self.run = Path(run_dir)
        self.opt = options or LearnOptions()
        self.log = log or (lambda *a: None)
        # Cloud-only recordings take the marker path through the tracker (cached in RUN/tracked).
        scene, self.tracking = track_scene(scene, self.run / "tracked", self.opt.track, self.log,
                                           progress=log is not None)
        self.scene = scene
        train = [(p, r) for p, r in zip(scene.recording_paths("train"), scene.recordings_with_role("train"))
                 if r.num_markers > 0]
        self.train = [r for _, r in train]
        # the cloud recording each train recording was tracked from (None: a marker recording)
        tracked_from = {str(Path(v["tracked"]).resolve()): p for p, v in self.tracking.items()}
        self.cloud_sources = [tracked_from.get(str(Path(p).resolve())) for p, _ in train]
        if not self.train:
            raise ValueError("the scene has no 'train' recording with markers or point clouds to learn from")
        for p, r in train:  # the space-time problem needs a motion: at least 2 steps
            if steps_covering(r.duration, scene.time_step) < 2:
                raise ValueError(f"train recording {Path(p).name}: {len(r.times)} frame(s) over {r.duration:g} s, "
                                 f"less than 2 time steps of {scene.time_step:g} s: nothing to learn a motion from")
        self.test = [r for r in scene.recordings_with_role("test") if r.num_markers > 0]
        mesh = scene.mesh
        self.emb_train = [embed_points(mesh, r.marker_rest) for r in self.train]
        self.emb_test = [embed_points(mesh, r.marker_rest) for r in self.test]
        self.nominal = scene.model()
        self.metrics: list[dict] = []
        self.code = code_fingerprint()
        self.hist: dict[str, np.ndarray] = {}
        self.lam: float | None = self.opt.lam if self.opt.lam is not None else (None if self.tracking else 1.0)
        self.lam_info: dict = {"source": "option" if self.opt.lam is not None else "marker default"}
        self._evaluated = None  # (params, train errors, sims, test errors) known for the next iteration
        # start_pose "released": the train recordings' initial states, estimated once per iteration
        # with the current model and shared by its candidates' checks (None: per model, held)
        self._train_states = None
        self._basis_sims = None  # after a rejected update: the candidate's simulations for the basis

    # ------------------------------------------------------------------ checkpoints
    def _ckpt(self, k):
        return self.run / "checkpoint" / f"iter_{k:03d}.npz"

    def _save_checkpoint(self, k, params, st_X, candidate=None):
        d = self.run / "checkpoint"
        d.mkdir(parents=True, exist_ok=True)
        arrays = {f"st_X{i}": X for i, X in enumerate(st_X)}
        if params is not None:
            arrays.update(params.to_arrays())
        if candidate is not None:  # a rejected update whose simulations feed the next basis
            arrays.update(candidate.to_arrays("cand_"))
        tmp = self._ckpt(k).with_suffix(".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        tmp.replace(self._ckpt(k))
        self._write_metrics()

    def _write_metrics(self):
        self.run.mkdir(parents=True, exist_ok=True)
        doc = {"options": asdict(self.opt), "code": self.code, "lambda": self.lam,
               "lambda_choice": self.lam_info, "tracking": self.tracking, "iterations": self.metrics}
        tmp = self.run / "metrics.json.tmp"
        tmp.write_text(json.dumps(doc, indent=1, default=str))
        tmp.replace(self.run / "metrics.json")
        with open(self.run / "error_samples.npz", "wb") as f:
            np.savez(f, **self.hist)

    def _load_resume(self):
        """(next iteration, params, st_X) from the last finished checkpoint, or None."""
        mfile = self.run / "metrics.json"
        if not mfile.exists():
            return None
        doc = json.loads(mfile.read_text())
        if doc.get("code") != self.code:
            raise ValueError(f"{self.run} was written by different code (fingerprint {doc.get('code')}, now "
                             f"{self.code}); resuming would not reproduce an uninterrupted run: start "
                             f"a new run (or delete {mfile})")
        # every option but the iteration cap shapes the iterations already run: resuming with
        # another would mix two runs (and metrics.json would name only the new options)
        now = json.loads(json.dumps(asdict(self.opt), default=str))
        was = doc.get("options", {})
        changed = sorted(k for k in set(now) | set(was) if k not in RESUMABLE_OPTIONS and now.get(k) != was.get(k))
        if changed:
            raise ValueError(f"{self.run} was run with other options ("
                             + ", ".join(f"{k}: {was.get(k)!r} then, {now.get(k)!r} now" for k in changed)
                             + "); resume with the run's options (only the iteration cap may change) or start "
                               "a new run")
        its = [m for m in doc["iterations"] if "fit" in m and self._ckpt(m["iteration"]).exists()]
        if not its:
            return None
        k = its[-1]["iteration"]
        self.metrics = [m for m in doc["iterations"] if m["iteration"] <= k]
        if doc.get("lambda") is not None and self.opt.lam is None:
            self.lam, self.lam_info = float(doc["lambda"]), doc.get("lambda_choice", {})
        if (self.run / "error_samples.npz").exists():
            with np.load(self.run / "error_samples.npz") as z:
                self.hist = {key: z[key] for key in z.files if int(key.split("_")[1]) <= k}
        with np.load(self._ckpt(k)) as z:
            params = RbfParams.from_arrays(z) if "rbf_centers" in z.files else None
            st_X = [z[f"st_X{i}"] for i in range(len(self.train))]
            cand = RbfParams.from_arrays(z, "cand_") if "cand_centers" in z.files else None
        if cand is not None:
            self._basis_sims = self._train_error(cand)[2]
        return k + 1, params, st_X

    # ------------------------------------------------------------------ one iteration
    def _choose_lambda(self, sims):
        """Observation weight for tracked clouds from the nominal model's motion and the noise of
        the tracked markers (matlearn.clouds.prepare.cloud_lambda); the smallest over the
        train recordings."""
        h = self.scene.time_step
        info = {Path(v["tracked"]).resolve(): v for v in self.tracking.values()}
        rows = []
        for path, sim in zip(self.scene.recording_paths("train"), sims):
            v = info.get(Path(path).resolve())
            if v is None:  # a marker recording in a mixed scene
                continue
            cons, _, _ = constrained_vertices(self.scene, load_recording(path))
            free = np.setdiff1d(np.arange(self.scene.mesh.num_vertices), cons)
            ms = motion_scales(sim[1], h, free)
            lam = cloud_lambda(ms["d_rms_m"], ms["omega_s"], v["sigma_obs_m"], v["frame_dt_s"] or h, h)
            rows.append({"recording": str(path), **ms, "sigma_obs_m": v["sigma_obs_m"],
                         "frame_dt_s": v["frame_dt_s"], "lam": lam})
        self.lam = min([r["lam"] for r in rows], default=1.0)
        self.lam_info = {"source": "clouds: Wiener cutoff of the space-time smoother, min over train "
                                   "recordings (matlearn.clouds.prepare.cloud_lambda)", "recordings": rows}
        self.log(f"observation weight lambda = {self.lam:.3g} (from the scanner noise and the motion)")

    def _spacetime(self, model, sims, st_X, k):
        """Space-time for every train recording; returns (fit frames, new st_X, info). The
        recordings' problems are independent and are solved side by side (matlearn.parallel)."""
        V = np.asarray(self.scene.mesh.vertices, float)

        def one(i):
            rec, emb, sim = self.train[i], self.emb_train[i], sims[i]
            t0 = time.time()
            if st_X is None:
                _, X0, _ = initial_trajectory(self.scene, model, rec, emb)
            else:
                X0 = st_X[i]
            cons, _, _ = constrained_vertices(self.scene, rec)
            basis = [sim[1], X0]
            if self._basis_sims is not None:  # after a rejected update: its motion too
                basis.append(self._basis_sims[i][1])
            phi = pod_basis(basis, V, cons, self.opt.modes, self.opt.pod_window)
            setup = build_problem(self.scene, model, rec, phi, self.lam, emb)
            setup.problem.tangent_stride = self.opt.tangent_stride
            out = solve_spacetime(setup, X0, iterations=self.opt.gn_iterations,
                                  tolerance=self.opt.gn_tolerance, jacobian_every=self.opt.jacobian_every)
            rounds = []
            cloud = self.cloud_sources[i] if self.opt.refresh_correspondences else None
            source = load_recording(cloud) if cloud is not None else None
            for _ in range(self.opt.refresh_correspondences if source is not None else 0):
                # Re-estimate the cloud correspondences at the space-time trajectory, solve again.
                refreshed = refresh_markers(self.scene, source, setup.times, out["X"], model, self.opt.track)
                setup = build_problem(self.scene, model, refreshed, phi, self.lam,
                                      embed_points(self.scene.mesh, refreshed.marker_rest))
                setup.problem.tangent_stride = self.opt.tangent_stride
                out = solve_spacetime(setup, out["X"], iterations=self.opt.gn_iterations,
                                      tolerance=self.opt.gn_tolerance,
                                      jacobian_every=self.opt.jacobian_every)
                rounds.append(out["report"]["cost"])
            fc = out["control_forces"]
            red = fc.reshape(len(fc), -1) @ phi
            stride = max(1, int(np.ceil(len(fc) / self.opt.fit_frames)))
            P = interpolate_frames(setup.times, emb.apply(out["X"]), rec.times)
            fit_err = np.linalg.norm(P - rec.markers, axis=2)[rec.seen]
            return (FitFrames(out["X"][2::stride], out["V"][2::stride], fc[::stride], phi), out["X"],
                    {"cost": out["report"]["cost"], "cg_iterations": out["report"]["cg_iterations"],
                     "marker_max_error_pct": float(100.0 * fit_err.max() / self.scene.object_size)
                     if fit_err.size else 0.0,
                     "step_length": out["report"]["step_length"],
                     "control_force_rms": float(np.sqrt(np.mean(red**2))), "modes": int(phi.shape[1]),
                     "frames": int(len(out["X"])), "wall_s": time.time() - t0,
                     "refresh_costs": rounds})

        got = pmap(one, range(len(self.train)))
        return [g[0] for g in got], [g[1] for g in got], [g[2] for g in got]

    def _train_error(self, params, bound=np.inf):
        """(max train error %, errors, sims) of a correction; inf when it cannot be simulated.
        A finite `bound`: the check stops as soon as an error exceeds it and returns the error
        that did (a lower bound of the max, > bound) with errors and sims None."""
        try:
            model = self.scene.model(params.correction() if params is not None else None)
            errs, sims = _errors(self.scene, model, self.train, self.emb_train, bound, self.opt.start_pose,
                                 self._train_states)
            return max(e.max() for e in errs), errs, sims
        except ErrorBoundExceeded as stop:
            self.log(f"  forward check stopped after {100 * stop.simulated:.0f} % of the steps: error "
                     f"{stop.lower_bound:.4f} % > {bound:.4f} %")
            return stop.lower_bound, None, None
        except RuntimeError:
            return np.inf, None, None

    def run_loop(self, resume: bool = False) -> dict:
        opt = self.opt
        start, params, st_X = 0, None, None
        h = self.scene.time_step
        steps = [steps_covering(r.duration, h) for r in self.train + self.test]
        self.log(f"learning on {self.scene.mesh.num_tets} tets from {len(self.train)} train recording(s) "
                 f"({sum(steps[:len(self.train)]):,} time steps of {h:g} s), scored on {len(self.test)} test "
                 f"recording(s) ({sum(steps[len(self.train):]):,} steps)")
        if resume:
            state = self._load_resume()
            if state is not None:
                start, params, st_X = state
                self.log(f"resuming at iteration {start}")
        best = {"train": np.inf, "cf": np.inf, "stale": 0}
        for m in self.metrics:  # replay the stopping state of resumed iterations
            if m.get("train"):
                self._update_best(best, m)
        k = start
        while True:
            t0 = time.time()
            model = self.scene.model(params.correction() if params is not None else None)
            known = self._evaluated is not None and self._evaluated[0] is params
            if known and opt.start_pose == "held":
                tr_err, sims, te_err = self._evaluated[1:]
            else:  # the nominal model, a resumed run's last accepted update, or new start states
                if opt.start_pose != "held":
                    self._train_states = [robust_initial_state(self.scene, model, rec, emb, opt.start_pose)
                                          for rec, emb in zip(self.train, self.emb_train)]
                tr_err, sims = _errors(self.scene, model, self.train, self.emb_train, start=opt.start_pose,
                                       states=self._train_states)
                te_err = self._evaluated[3] if known else None
            if te_err is None:
                try:
                    te_err, _ = _errors(self.scene, model, self.test, self.emb_test, start=SCORE_START)
                except RuntimeError as err:  # scored only; never a decision input
                    te_err = []
                    self.log(f"iteration {k}: a test recording cannot be simulated ({err})")
            m = {"iteration": k, "train": _summary(tr_err), "test": _summary(te_err),
                 "has_correction": params is not None}
            for i, e in enumerate(tr_err):
                self.hist[f"it_{k}_train{i}"] = e
            for i, e in enumerate(te_err):
                self.hist[f"it_{k}_test{i}"] = e
            self.log(f"iteration {k}: train max {m['train']['max_error_pct']:.3f}%"
                     + (f", test max {m['test']['max_error_pct']:.3f}%" if m["test"] else ""))
            if self.metrics and self.metrics[-1]["iteration"] == k:  # resumed past a stop record
                self.metrics.pop()
            if k >= opt.iterations or (k > 0 and best["stale"] >= opt.patience):
                m["stop"] = "iterations" if k >= opt.iterations else "no improvement"
                m["wall_s"] = time.time() - t0
                self.metrics.append(m)
                self._write_metrics()
                break
            if self.lam is None:
                self._choose_lambda(sims)
            m["lam"] = self.lam
            frames, new_X, st_info = self._spacetime(model, sims, st_X, k)
            m["spacetime"] = st_info
            m["control_force_rms"] = float(np.sqrt(np.mean([s["control_force_rms"] ** 2 for s in st_info])))
            current = m["train"]["max_error_pct"]
            new_params, finfo, evaluated = self._update(frames, params, model, current, k)
            self._basis_sims = None
            m["fit"] = finfo
            m["wall_s"] = time.time() - t0
            self.log(f"  control forces {m['control_force_rms']:.3e} N (reduced rms), fit residual "
                     f"{finfo['residual_ratio']:.3f} (ridge {finfo['ridge']:g}), update step "
                     f"{finfo['update_step']:g}, {m['wall_s']:.1f} s")
            self.metrics.append(m)
            self._update_best(best, m)
            if new_params is None:
                # No step of the update lowers the train error. Keep the correction; the next
                # iteration starts the space-time solve from this one's trajectories and adds
                # the rejected candidate's motion to the basis (new information, same model).
                # After `patience` such iterations without improvement the loop has converged.
                m["update"] = "rejected"
                if best["stale"] >= opt.patience or evaluated[1] is None or not opt.retry_rejected:
                    m["stop"] = "no improving update"
                    self._write_metrics()
                    break
                self._basis_sims = evaluated[1]
                self._evaluated = (params, tr_err, sims, te_err)
                self._save_checkpoint(k, params, new_X, candidate=evaluated[0])
                st_X = new_X
            else:
                m["update"] = "accepted"
                params, st_X = new_params, new_X
                self._evaluated = (params, *evaluated, None)
                self._save_checkpoint(k, params, st_X)
            k += 1
        return self.finish()

    def _update(self, frames, params, current_model, current_err, k):
        """The next correction: fit one candidate per (smoothing, ridge) weight pair of the
        options (same centres) and take the one with the lowest forward *train* error (model selection on
        training data only). The update is accepted only if it lowers the train error;
        otherwise it is shortened (blended towards the current correction) by the factors in
        options.backtrack, and when no step lowers the error the loop has converged (returns
        None). Returns (params or None, info, (errors, sims) of the accepted params)."""
        opt = self.opt
        cands = []
        centers = (params.centers, params.epsilon) if params is not None else None
        probes = extension_probes(self.nominal, frames, seed=opt.seed + k)
        mu, lam = float(np.median(self.nominal.mu)), float(np.median(self.nominal.lam))

        def evaluate(q, bound=np.inf):
            """(train error, errors, sims, tangent margin); unstable beyond the data: inf,
            unsimulated; stopped early above `bound`: a lower bound of the error, unsimulated."""
            margin = tangent_margin(q, self.scene.material, mu, lam, probes)
            if margin < 0:
                return np.inf, None, None, margin
            return (*self._train_error(q, bound), margin)

        def check_bound():
            """The error a candidate's check may stop above. "all": the lowest error of the
            candidates simulated to the end (one exceeding it can be neither the best nor, as
            that best is >= the current error unless the search stopped, an improvement: same
            choice, same numbers). "first" looks for the first improvement only: the current
            error (the candidate to shorten is then the lowest, possibly a lower bound)."""
            if not opt.early_stop:
                return np.inf
            if opt.ridge_search == "first":
                return current_err
            return min([c[0] for c in cands if c[6] is not None], default=np.inf)

        # the normal equations do not depend on the weights: assembled once for all candidates
        system = fit_system(self.nominal, frames, opt.centers,
                            current_model=current_model if params is not None else None,
                            damping=opt.damping, seed=opt.seed + k, centers=centers,
                            symmetric=opt.symmetric, tangent_damping=opt.tangent_damping)
        # (ridge, smoothing, (linear, edge) extrapolation penalties), in the order of the options
        pairs = [(r, s, x) for x in opt.extrapolation for s in opt.smoothing for r in opt.ridges]
        planned = len(pairs)
        while pairs:
            ridge, smooth, extra = pairs.pop(0)
            p, info = solve_fit(system, ridge, smooth, *extra) if any(extra) else solve_fit(system, ridge, smooth)
            info["ridge"], info["smooth"], info["extrapolation"] = ridge, smooth, list(extra)
            err, errs, sims, info["tangent_margin"] = evaluate(p, check_bound())
            info["train_max_error_pct"] = float(err)
            info["stopped_early"] = bool(np.isfinite(err) and sims is None)
            cands.append((err, -info["tangent_margin"], len(cands), p, info, errs, sims))
            if opt.ridge_search == "first" and err < current_err:
                break
            escalated = len(cands) - planned
            if not pairs and escalated < opt.escalate and not any(np.isfinite(c[0]) for c in cands):
                # No candidate is stable (or simulable): smooth harder (x10) before shortening.
                pairs = [(opt.ridges[0], 10.0 * max(c[4]["smooth"] for c in cands), max(opt.extrapolation))]
        if not any(np.isfinite(c[0]) for c in cands) and opt.ridge_search == "all":
            # Still none: the global linear part itself destabilises. Project the most stable
            # candidate's linear part so that the total tangent at rest is positive
            # semi-definite (fit.project_linear_part) and try that.
            q0 = min(cands, key=lambda c: (c[1], c[2]))
            p = project_linear_part(q0[3], self.scene.material, mu, lam)
            info = dict(q0[4], projected=True)
            err, errs, sims, info["tangent_margin"] = evaluate(p)
            info["train_max_error_pct"] = float(err)
            cands.append((err, -info["tangent_margin"], len(cands), p, info, errs, sims))
        # Lowest train error; among unsimulable candidates the most stable one (to be shortened).
        cands_best = min(cands, key=lambda c: (c[0], c[1], c[2]))
        err, _, _, p, info, errs, sims = cands_best
        full, full_sims = p, sims  # the full update: every shorter or longer step blends from it
        info["ridge_candidates"] = [{"ridge": c[4]["ridge"], "smooth": c[4]["smooth"],
                                     "extrapolation": c[4]["extrapolation"],
                                     "tangent_margin": c[4]["tangent_margin"],
                                     "train_max_error_pct": float(c[0]),
                                     "stopped_early": c[4].get("stopped_early", False)} for c in cands]
        info["update_step"] = 1.0
        tried = [{"step": 1.0, "train_max_error_pct": float(err)}]

        def check(t, q, bound):
            """Forward check of the update at step t (correction q), recorded in `tried`; only an
            error below `bound` matters, so the check stops once it is exceeded."""
            e, es, ss, margin = evaluate(q, bound if opt.early_stop else np.inf)
            tried.append({"step": t, "train_max_error_pct": float(e), "tangent_margin": margin,
                          "stopped_early": bool(np.isfinite(e) and ss is None)})
            return e, es, ss

        for t in opt.backtrack:
            if err < current_err:
                break
            info["update_step"] = t
            p = _blend(params, full, t)  # a fraction of the full update, not of the last step
            err, errs, sims = check(t, p, current_err)
            self.log(f"  update does not lower the train error ({tried[-2]['train_max_error_pct']:.3f}% >= "
                     f"{current_err:.3f}%); step {t:g}: {err:.3f}%")
        if err < current_err and info["update_step"] == 1.0:
            # The accepted update is a direction too: longer steps along it (a line search,
            # each checked by a forward simulation like any candidate and kept only while it
            # lowers the train error further). Gentle control forces make every update short,
            # so without it the loop creeps (tension sphere: -2 % of the error per iteration).
            for t in opt.extend:
                q = _blend(params, full, t)
                e2, errs2, sims2 = check(t, q, err)  # below err it was simulated to the end
                if not e2 < err:
                    break
                self.log(f"  longer step {t:g}: {e2:.3f}% < {err:.3f}%")
                p, err, errs, sims, info["update_step"] = q, e2, errs2, sims2, t
        info["steps_tried"] = tried
        if not err < current_err:
            info["update_step"] = 0.0
            if full_sims is None and np.isfinite(cands_best[0]) and opt.retry_rejected:
                full_sims = self._train_error(full)[2]  # stopped early: its motion for the next basis
            return None, info, (full, full_sims)
        return p, info, (errs, sims)

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
        best = min((m for m in self.metrics if m.get("train")),
                   key=lambda m: (m["train"]["max_error_pct"], -m["iteration"]))
        k = best["iteration"]
        params = None
        if k > 0:
            with np.load(self._ckpt(k - 1)) as z:
                params = RbfParams.from_arrays(z) if "rbf_centers" in z.files else None
        return {"best_iteration": k, "params": params, "metrics": self.metrics,
                "nominal": self.metrics[0], "final": best, "lambda": self.lam,
                "scene": self.scene, "tracking": self.tracking}


def learn(scene, run_dir, options: LearnOptions | None = None, resume: bool = False, log=print,
          meta: dict | None = None) -> dict:
    """Run the learning loop on `scene` (a Scene or a scene.toml path) and save the kept
    correction as RUN/model.npz + model.json (io.save_model, no MLP; loadable with `matlearn
    simulate SCENE --model RUN` and io.scene_model). meta: what model.json says of the start
    (default {"start": "nominal"}: the scene's own material; a fitted start gives its base
    material, start.learn_from). Returns
    dict(best_iteration, params (RbfParams or None when the nominal model was best), metrics,
    nominal, final, lambda (the observation weight used), scene (the scene learned from: cloud
    recordings replaced by tracked markers), tracking)."""
    from .io import save_model
    from .start import zero_params

    if isinstance(scene, (str, Path)):
        from ..scene import load_scene

        scene = load_scene(scene)
    res = Learner(scene, run_dir, options, log).run_loop(resume)
    info = {"start": "nominal", **(meta or {}), "best_iteration": res["best_iteration"]}
    if scene.path is not None:
        info["scene"] = str(Path(scene.path).resolve())
    save_model(run_dir, res["params"] if res["params"] is not None else zero_params(), None, meta=info)
    return res
