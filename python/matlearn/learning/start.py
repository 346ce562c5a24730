"""Where the learning starts: the scene's nominal model, or parameters fitted first.

"baseline" start: E, nu and alpha_K of the nominal law (or, with `laws`, of each listed law,
the lowest train rms kept: bench/learning_table.py passes STANDARD_LAWS, the co-rotated, the
neo-Hookean and the St. Venant-Kirchhoff law, so a recording that another standard law explains
better starts the learner from that law and its correction is learned on top of it; the
difference of two of these laws is itself a stress correction of the principal stretches, so
this only moves the learner's starting point, and a law the recordings do not support is not
chosen) are fitted to the train recordings
(baseline.fit_parameters, the Wang-2015-style identification, with alpha_M held at the
nominal value) and replace the nominal ones. A change of E and nu of the co-rotated law is
exactly a linear correction in the principal stretches and a change of alpha_K is a constant
dalpha, so this start is a point of the learner's own model space; alpha_M is held because the
learner has no mass-damping term and could never undo a fitted one (measured: bar_damping_1
started from the 4-parameter fit, alpha_M = 0.5 1/s, stalled at 0.035 % train, 0.08/0.10 %
held-out, against 0.02/0.08 % from the nominal). Iteration 0 of the loop is then the fitted
model, and as the loop keeps the iterate with the lowest train error, the learned model's
train error never ends above the fit's.

The fitted parameters are cached in `RUN/start.json` (a resumed run does not fit again) and are
stored with the learned model (io.save_model meta `base_material` / `base_damping`), so
`matlearn simulate SCENE --model RUN` rebuilds nominal-with-fitted-parameters + correction.
The start's damping has no strain polynomials (mass_poly / stiffness_poly of the nominal are
dropped, as in the baseline).

"field" start (:func:`field_start`): the baseline fit, then every element (or spatial patch) its
own Young's modulus fitted on top of it to the train recordings (learning/field.py): for
objects whose stiffness varies in space (laminates, inclusions, a truth meshed finer than the
model), which a correction of the principal stretches, the same in every element, cannot
represent.

"best" start (:func:`learn_best_start`): the loop is run from all three starts (RUN/start_nominal,
RUN/start_baseline, RUN/start_field, the field built on the baseline start's fit) and the learned
model with the lowest *train* max error is kept (ties: the fewest parameters, PREFERENCE); the
test recordings are never consulted. The field is a candidate since session 29, when its fit
became cheap (tangent Jacobians, learning/field.py): a field fit always lowers the *start's*
train error, but not the *learned* model's: on the damping bars the loop from the field ends at
2-3x the train error of the loop from the baseline (the field absorbs part of the damping
misfit), and that start is not chosen; on the laminates and the neo-Hookean turtle it ends lower
and is (docs/results.md, "Session 29"). Why several starts: none dominates. From the
fitted start the remaining error is a small nonlinearity, and with sparse markers the space-time
control forces identify it poorly: on the StVK "dragon" (6 % markers) they correlate only 0.67
with the true force difference at the same trajectory, and every fitted update raises the train
error from 0.25 % to 0.79-0.94 % (a fit of the true force difference reaches 0.15 % in one
step), so the loop creeps on by shortened steps and ends at 0.19 % train; from the nominal start
the 20 % modulus error dominates the control forces and the loop reaches 0.13 % train
(bench/results/learning_table_nominal_start.json); with the StVK law among the fitted laws
(`laws`, STANDARD_LAWS) that nonlinearity is in the start. bench/results/learning_table.json
(session 30) keeps the nominal start on the tension sphere and the first damping bar, the fitted
start on the compression sphere and the second damping bar, and the field on the turtle, the
StVK bar and both layered bars.
RUN/best_start.json records every start's train error and the choice.

The model other objects get (`transfer_model`, io.scene_model): the kept one, except that a
kept field names the best homogeneous start's model (:func:`transfer_start`), and a kept fitted
start whose train recordings do not determine the stress scale (learning/identify.py) names the
nominal start's: where the data are silent the user's nominal modulus is the better guess
(the compression sphere, driven by a keyframed cap: its fitted start, E = 4.6e4 Pa against the
truth's 1e5 and the nominal 1.2e5, transfers to a post under gravity at 0.96 / 1.19 %, the
nominal start's model at 0.23 / 0.72, the nominal model itself at 0.26 / 0.96).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..materials import Damping, Material
from .baseline import fit_parameters

START_JSON = "start.json"
BEST_JSON = "best_start.json"
FIELD_CHECKPOINT = "field_checkpoint.json"  # the field fit after each of its iterations (resume)
STARTS = ("nominal", "baseline", "field")  # the starts one loop runs from; "best" compares them all
PREFERENCE = ("baseline", "nominal", "field")  # on equal learned train errors: the fewest parameters
MODES = STARTS + ("best",)
# learned train errors this close (relative) count as equal when choosing a kept field's
# transfer model (transfer_start)
TRANSFER_TIE = 0.05
# the standard hyperelastic laws a start may fit (`laws`; matlearn learn --laws all)
STANDARD_LAWS = ("corotated", "neo_hookean", "stvk")


def spec_dict(spec) -> dict:
    """A Material or Damping (dataclasses) as JSON values: per-tet arrays as lists."""
    return {k: np.asarray(v, float).tolist() if isinstance(v, np.ndarray) else v
            for k, v in dataclasses.asdict(spec).items()}


def _number(v):
    """A JSON scalar or per-tet list back as float or array."""
    return np.asarray(v, float) if np.ndim(v) else float(v)


def material_from_dict(d: dict) -> Material:
    return Material(d["model"], _number(d["youngs_modulus"]), _number(d["poisson_ratio"]),
                    _number(d["density"]), [tuple(e) for e in d.get("edits", [])])


def damping_from_dict(d: dict) -> Damping:
    return Damping(float(d["alpha_mass"]), float(d["alpha_stiffness"]), list(d.get("mass_poly", [])),
                   list(d.get("stiffness_poly", [])))


def with_parameters(scene, material: Material, damping: Damping):
    """A copy of `scene` whose nominal material and damping are the given ones."""
    return dataclasses.replace(scene, material=material, damping=damping)


def _warm_for(warm, law: str):
    """The warm start for `law`: warm is None, one fit_parameters result (used for its own law)
    or a dict law -> result."""
    if warm is None:
        return None
    if "material" in warm:
        return warm if warm["material"].model == law else None
    return warm.get(law)


def _cached_start(run_dir, start: str) -> dict | None:
    """The start info RUN/start.json holds for `start` (None: no run folder, no file, or another
    start's)."""
    cache = Path(run_dir) / START_JSON if run_dir is not None else None
    if cache is None or not cache.exists():
        return None
    doc = json.loads(cache.read_text())
    return doc if doc.get("start") == start else None


def _cache_start(run_dir, info: dict) -> None:
    """Write the start info to RUN/start.json (a resumed run reads it instead of fitting again)."""
    if run_dir is not None:
        cache = Path(run_dir) / START_JSON
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_text(json.dumps(info, indent=1))


def baseline_start(scene, run_dir=None, warm: dict | None = None, max_evaluations: int = 20, log=None,
                   laws: tuple | None = None):
    """(scene with fitted E, nu, alpha_K as nominal, start info dict) (module docstring).

    The fit (alpha_M held at the nominal value) is read from RUN/start.json when a previous run
    of this scene wrote it; warm: a baseline.fit_parameters result (or a dict law -> result) to
    start the fit from (e.g. the 4-parameter baseline); laws: the laws fitted (default: the
    scene's own law, co-rotated if it is none of STANDARD_LAWS); with several, the
    fit with the lowest train rms is the start, so the learner starts from the law that explains
    the recordings best (its correction is then learned on top of that law)."""
    doc = _cached_start(run_dir, "baseline")
    if doc is not None:
        fit = {"material": material_from_dict(doc["material"]), "damping": damping_from_dict(doc["damping"]),
               "evaluations": doc.get("evaluations"), "train_rms_pct": doc.get("train_rms_pct")}
    else:
        own = scene.material.model if scene.material.model in STANDARD_LAWS else "corotated"
        fits = {law: fit_parameters(scene, law, max_evaluations=max_evaluations,
                                    alpha_mass=float(scene.damping.alpha_mass), start=_warm_for(warm, law))
                for law in (laws or (own,))}
        if len(fits) > 1:
            fit = fits[min(fits, key=lambda k: fits[k]["train_rms_pct"])]
            fit["train_rms_pct_by_law"] = {k: f["train_rms_pct"] for k, f in fits.items()}
        else:
            fit = next(iter(fits.values()))
    info = {"start": "baseline", "material": spec_dict(fit["material"]),
            "damping": spec_dict(fit["damping"]), "evaluations": fit.get("evaluations"),
            "train_rms_pct": fit.get("train_rms_pct"), "train_rms_pct_by_law": fit.get("train_rms_pct_by_law")}
    _cache_start(run_dir, info)
    if log:
        log(f"learning starts from the baseline fit: {fit['material'].model} E={np.mean(fit['material'].youngs_modulus):.4g} Pa "
            f"nu={np.mean(fit['material'].poisson_ratio):.3f} alpha_M={fit['damping'].alpha_mass:.3g} "
            f"alpha_K={fit['damping'].alpha_stiffness:.3g}")
    return with_parameters(scene, fit["material"], fit["damping"]), info


def field_start(scene, run_dir=None, warm: dict | None = None, max_evaluations: int = 20, log=None,
                laws: tuple | None = None, smooth: float = 0.3, iterations: int = 20,
                max_patches: int = 128, baseline: dict | None = None):
    """(scene with the baseline fit and a per-element stiffness field as nominal, start info):
    :func:`baseline_start` (not cached on its own), then learning.field.fit_stiffness_field on
    top of it (smooth, iterations, max_patches: its arguments). Cached in RUN/start.json like
    the baseline start; the info also holds the field's volume-weighted log-mean material
    (`material_homogeneous`), what the learned model uses on another mesh (io.scene_model).
    The field fit writes RUN/field_checkpoint.json after each of its iterations; a killed run
    resumes the fit from there (the same path as an uninterrupted one). baseline: the info of a
    baseline start already fitted to this scene (the "best" mode's), built on instead of fitting
    it again."""
    from .field import fit_stiffness_field, homogeneous, mesh_fingerprint

    info = _cached_start(run_dir, "field")
    if info is None:
        if baseline is not None and baseline.get("start") == "baseline":
            binfo = baseline
            bscene = with_parameters(scene, material_from_dict(binfo["material"]), damping_from_dict(binfo["damping"]))
        else:
            bscene, binfo = baseline_start(scene, None, warm=warm, max_evaluations=max_evaluations, log=log,
                                           laws=laws)
        ckpt = Path(run_dir) / FIELD_CHECKPOINT if run_dir is not None else None
        mat, finfo = fit_stiffness_field(bscene, bscene.material, bscene.damping, smooth=smooth,
                                         iterations=iterations, max_patches=max_patches, log=log,
                                         checkpoint=ckpt)
        info = {**binfo, "start": "field", "material": spec_dict(mat),
                "material_homogeneous": spec_dict(homogeneous(mat, scene.mesh.rest_volumes)),
                "material_mesh": mesh_fingerprint(scene.mesh),
                "baseline_material": binfo["material"], "field": finfo}
        _cache_start(run_dir, info)
    return with_parameters(scene, material_from_dict(info["material"]), damping_from_dict(info["damping"])), info


def model_meta(info: dict) -> dict:
    """The start's part of a learned model's model.json (io.save_model meta): the fitted base
    material and damping when the start fitted them, and for a stiffness field its mesh's sha1 and
    volume-weighted log-mean material, what another mesh gets (io.scene_model)."""
    if "material" not in info:
        return {}
    meta = {"base_material": info["material"], "base_damping": info["damping"]}
    if "material_homogeneous" in info:
        meta["base_material_homogeneous"] = info["material_homogeneous"]
    if "material_mesh" in info:  # a field, or a "best" run naming a transfer model: the mesh it is for
        meta["base_material_mesh"] = info["material_mesh"]
    if info.get("transfer_start"):  # "best" kept a field or a free stress scale: the model for other meshes
        meta["transfer_model"] = start_folder(info["transfer_start"])
    return meta


def start_folder(name: str) -> str:
    """The folder (in a "best" run's RUN) where start `name` learns and saves its model."""
    return f"start_{name}"


def zero_params():
    """The RbfParams of no correction (a loop that accepted no update)."""
    from .fit import RbfParams

    return RbfParams(np.ones((1, 3)), np.zeros((1, 3)))


def start_scene(scene, start: str, run_dir=None, warm: dict | None = None, max_evaluations: int = 20,
                log=None, laws: tuple | None = None):
    """The scene the loop learns on for `start` ("nominal", "baseline" or "field"; laws: those
    the baseline start fits, :func:`baseline_start`, :func:`field_start`) and the start info."""
    if start not in STARTS:
        raise ValueError(f"start must be one of {STARTS}, got {start!r}")
    if start == "nominal":
        return scene, {"start": "nominal"}
    if start == "field":
        return field_start(scene, run_dir, warm=warm, max_evaluations=max_evaluations, log=log, laws=laws)
    return baseline_start(scene, run_dir, warm=warm, max_evaluations=max_evaluations, log=log, laws=laws)


def learn_best_start(scene, run_dir, options=None, warm: dict | None = None, max_evaluations: int = 20,
                     resume: bool = False, log=None, learn_fn=None, laws: tuple | None = None):
    """Learn from every start of STARTS and keep the one with the lowest learned *train* max error
    (module docstring; ties: PREFERENCE). Each start runs in RUN/start_<name> (resumable on its own). Returns (the scene
    learned on, start info, learn result, run folder of the kept start); the info has
    start="best", chosen, train_max_error_pct per start, the kept start's fitted material and
    damping when it is the baseline or the field, stress_scale (identify.check_learned of the
    kept model), transfer_start (the start whose model in RUN/start_<name> other meshes get: the
    nominal one when the kept fitted start's stress scale is not determined, else the best start
    without a field when the field is kept), and each start's test
    errors for the record (test_per_recording_max_pct; not used). Every start's learned model
    is saved in its folder (io.save_model, no MLP)."""
    if learn_fn is None:
        from .loop import learn as learn_fn
    run_dir = Path(run_dir)
    runs = {}
    for name in STARTS:
        sub = run_dir / start_folder(name)
        if log:
            log(f"start '{name}' (best-start mode, {sub})")
        if name == "field":  # on top of the baseline start's fit, not fitted again
            sc, info = field_start(scene, sub, warm=warm, max_evaluations=max_evaluations, log=log, laws=laws,
                                   baseline=runs["baseline"][1] if "baseline" in runs else None)
        else:
            sc, info = start_scene(scene, name, sub, warm=warm, max_evaluations=max_evaluations, log=log,
                                   laws=laws)
        res = learn_fn(sc, sub, options, resume=resume, log=log)
        runs[name] = (sc, info, res, sub)
    train = {n: float(r[2]["final"]["train"]["max_error_pct"]) for n, r in runs.items()}
    # lowest train error; on a tie the start with the fewest parameters (PREFERENCE: the baseline,
    # whose train error never ends above its fit's, then the nominal, then the field)
    chosen = min(STARTS, key=lambda n: (train[n], PREFERENCE.index(n)))
    sc, info, res, sub = runs[chosen]
    # reported only (which start a test would have preferred); never an input of the choice
    test = {n: (r[2]["final"]["test"] or {}).get("per_recording_max_pct") for n, r in runs.items()}
    out = {**info, "start": "best", "chosen": chosen, "train_max_error_pct": train,
           "test_per_recording_max_pct": test}
    # every start's learned model is saved in its own folder (loadable with io.scene_model); a
    # field belongs to its mesh, so a kept field names the best *homogeneous* start's model as
    # the one another mesh gets (io.scene_model: the learned material, not the object's field)
    from .io import save_model

    for name, (_, i, r, d) in runs.items():
        save_model(d, r["params"] if r["params"] is not None else zero_params(), None,
                   meta={"start": name, **model_meta(i)})
    # does the kept model's stress scale follow from the train recordings? (identify.py)
    from .identify import check_learned
    from .field import mesh_fingerprint

    # on the scene the loop learned on: cloud-only recordings replaced by their tracked markers
    check = check_learned(res["scene"], res["params"])  # reported by the caller (the CLI warns)
    out["stress_scale"] = check
    transfer = None
    if not check["determined"] and chosen != "nominal":
        transfer = "nominal"  # the scale the data leave free: the user's nominal one
    elif chosen == "field":
        transfer = transfer_start(train)
    if transfer is not None:
        out["transfer_start"] = transfer
        out.setdefault("material_mesh", mesh_fingerprint(scene.mesh))
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / BEST_JSON).write_text(json.dumps({"chosen": chosen, "run": sub.name, "transfer": transfer,
                                                 "train_max_error_pct": train}, indent=1))
    if log:
        log(f"best start: {chosen} (learned train max {train[chosen]:.4g} % vs "
            + ", ".join(f"{n} {v:.4g} %" for n, v in train.items() if n != chosen) + ")")
    return sc, out, res, sub


def transfer_start(train: dict) -> str:
    """The start whose model another mesh gets when the field is kept: of the homogeneous starts
    whose learned train max error is within TRANSFER_TIE (relative) of the lowest, the first in
    PREFERENCE, i.e. the fitted law over the nominal one. On another shape what carries over is
    the material, and where both explain the source equally well the one whose law was fitted to
    it needs the smaller correction, which has less to extrapolate. (StVK bar: learned train
    0.1590 % from the nominal start, 0.1596 % from the fitted StVK law; on the capsule their models
    score 2.04 / 1.05 and 0.27 / 0.22 %, docs/results.md, "Session 30".)"""
    homogeneous = [n for n in STARTS if n != "field"]
    best = min(train[n] for n in homogeneous)
    near = [n for n in homogeneous if train[n] <= (1.0 + TRANSFER_TIE) * best]
    return min(near, key=PREFERENCE.index)


def chosen_run(run_dir) -> Path:
    """The run folder holding the kept model: RUN/start_<chosen> for a best-of-both run
    (RUN/best_start.json), else RUN itself."""
    run_dir = Path(run_dir)
    f = run_dir / BEST_JSON
    return run_dir / json.loads(f.read_text())["run"] if f.exists() else run_dir


def learn_from(scene, start: str, run_dir, options=None, warm: dict | None = None, max_evaluations: int = 20,
               resume: bool = False, log=None, laws: tuple | None = None):
    """Learn from the start `start` (one of MODES: "nominal", "baseline", "field" (the baseline
    fit with a per-element stiffness field, :func:`field_start`), or "best" for the first two,
    :func:`learn_best_start`; laws: those the baseline start fits). Returns (the scene learned on, start info, learn result, run folder
    of the kept model); the info's stress_scale is identify.check_learned of the kept model."""
    if start == "best":
        return learn_best_start(scene, run_dir, options, warm=warm, max_evaluations=max_evaluations,
                                resume=resume, log=log, laws=laws)
    from .identify import check_learned
    from .loop import learn

    sc, info = start_scene(scene, start, run_dir, warm=warm, max_evaluations=max_evaluations, log=log, laws=laws)
    # the correction belongs to the start's material: saved with it
    res = learn(sc, run_dir, options, resume=resume, log=log, meta={"start": start, **model_meta(info)})
    # on the scene the loop learned on (cloud-only recordings replaced by their tracked markers)
    return sc, {**info, "stress_scale": check_learned(res["scene"], res["params"])}, res, Path(run_dir)
