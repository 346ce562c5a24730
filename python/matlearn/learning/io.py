"""Learned models on disk: `RUN/model.npz` (arrays) + `RUN/model.json` (metadata).

`load_model(RUN)` returns a `_core.correction.*` object ready for `Model.correction` (used by
`matlearn simulate --model RUN`). A run holds the RBF correction and, after distillation, the
MLP; `model.json["use"]` says which one `load_model` returns by default. A run that started
from the baseline fit (learning/start.py) also stores the fitted material and damping the
correction was learned on (`base_material` / `base_damping` in model.json);
`scene_model(scene, RUN)` builds the complete model (used by `matlearn simulate --model RUN`).
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from .. import _core
from .fit import RbfParams

MODEL_NPZ = "model.npz"
MODEL_JSON = "model.json"


def save_model(run_dir, rbf: RbfParams, mlp: dict | None = None, meta: dict | None = None,
               use: str = "rbf") -> Path:
    """Write the model of a run. mlp: dict(layers=[(W, b), ...], in_mean, in_std, out_mean,
    out_std) (BN already folded); use: "rbf" or "mlp"."""
    if use not in ("rbf", "mlp"):
        raise ValueError(f"use must be 'rbf' or 'mlp', got {use!r}")
    if use == "mlp" and mlp is None:
        raise ValueError("use='mlp' needs an mlp")
    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    arrays = rbf.to_arrays()
    if mlp is not None:
        for i, (W, b) in enumerate(mlp["layers"]):
            arrays[f"mlp_W{i}"] = np.asarray(W, float)
            arrays[f"mlp_b{i}"] = np.asarray(b, float)
        for k in ("in_mean", "in_std", "out_mean", "out_std"):
            arrays[f"mlp_{k}"] = np.asarray(mlp[k], float)
    with open(run / MODEL_NPZ, "wb") as f:
        np.savez(f, **arrays)
    info = {"format": "matlearn-model-1", "use": use, "has_mlp": mlp is not None,
            "mlp_layers": len(mlp["layers"]) if mlp is not None else 0, **(meta or {})}
    (run / MODEL_JSON).write_text(json.dumps(info, indent=1))
    return run / MODEL_NPZ


def add_meta(run_dir, **meta) -> None:
    """Add keys to the metadata (model.json) of a saved run."""
    path = Path(run_dir) / MODEL_JSON
    info = json.loads(path.read_text())
    info.update(meta)
    path.write_text(json.dumps(info, indent=1))


def load_rbf(run_dir) -> RbfParams:
    with np.load(Path(run_dir) / MODEL_NPZ) as z:
        return RbfParams.from_arrays(z)


def load_mlp(run_dir) -> dict:
    run = Path(run_dir)
    info = json.loads((run / MODEL_JSON).read_text())
    if not info.get("has_mlp"):
        raise ValueError(f"{run}: this run has no distilled MLP")
    with np.load(run / MODEL_NPZ) as z:
        layers = [(z[f"mlp_W{i}"], z[f"mlp_b{i}"]) for i in range(info["mlp_layers"])]
        return {"layers": layers, **{k: z[f"mlp_{k}"] for k in ("in_mean", "in_std", "out_mean", "out_std")}}


def mlp_correction(mlp: dict):
    return _core.correction.MlpCorrection(
        [(np.asarray(W, float), np.asarray(b, float)) for W, b in mlp["layers"]],
        np.asarray(mlp["in_mean"], float), np.asarray(mlp["in_std"], float),
        np.asarray(mlp["out_mean"], float), np.asarray(mlp["out_std"], float))


def load_model(run_dir, kind: str | None = None):
    """The learned correction of run `run_dir` (a folder written by `matlearn learn`).
    kind: "rbf", "mlp" or None (the run's choice in model.json)."""
    run = Path(run_dir)
    if run.is_file():
        raise ValueError(f"{run} is a file; pass the run folder that `matlearn learn --out` wrote "
                         f"(it holds {MODEL_NPZ} and {MODEL_JSON})")
    if not (run / MODEL_NPZ).exists() or not (run / MODEL_JSON).exists():
        raise FileNotFoundError(f"{run}: not a learned-model folder (no {MODEL_NPZ}/{MODEL_JSON})")
    try:
        info = json.loads((run / MODEL_JSON).read_text())
        use = kind or info.get("use", "rbf")
        if use not in ("rbf", "mlp"):
            where = "kind" if kind else f"{run / MODEL_JSON}: 'use'"
            raise ValueError(f"{where} must be 'rbf' or 'mlp', got {use!r}")
        if use == "rbf":
            return load_rbf(run).correction()
        # the MLP reproduces the RBF's (dPh, dalpha); how the damping acts is the RBF's too
        c = mlp_correction(load_mlp(run))
        c.tangent_damping = load_rbf(run).tangent_damping
        return c
    except (OSError, EOFError, KeyError, json.JSONDecodeError, zipfile.BadZipFile) as err:
        raise ValueError(f"{run}: the learned model cannot be read ({type(err).__name__}: {err}); "
                         f"it is damaged or incomplete (learn again, or --resume the run)") from None


def scene_model(scene, run_dir, kind: str | None = None):
    """The learned model of run `run_dir` on `scene`: the scene's nominal material and damping
    (or the run's `base_material` / `base_damping`, when it started from the baseline fit) plus
    the learned correction. A run started from a stiffness field (start "field") applies its
    per-element modulus on the mesh it was fitted on only; another mesh gets the model named by
    `transfer_model` (a "best" run: the nominal start's when the kept fitted start's stress scale
    is free, else the best homogeneous start's when it kept a field; start.learn_best_start) or,
    without one, the field's volume-weighted log-mean (`base_material_homogeneous`)."""
    from .field import mesh_fingerprint
    from .start import damping_from_dict, material_from_dict

    correction = load_model(run_dir, kind)  # checks the folder and its files
    info = json.loads((Path(run_dir) / MODEL_JSON).read_text())
    mat = material_from_dict(info["base_material"]) if info.get("base_material") else None
    foreign = bool(info.get("base_material_mesh")) and info["base_material_mesh"] != mesh_fingerprint(scene.mesh)
    if foreign and info.get("transfer_model"):
        # a "best" run that kept a field or a free stress scale: another mesh gets the named start's model
        sub = Path(run_dir) / info["transfer_model"]
        sub_info = json.loads((sub / MODEL_JSON).read_text()) if (sub / MODEL_JSON).exists() else {}
        return scene_model(scene, sub, kind if sub_info.get("has_mlp") else None)
    if foreign:
        # a per-element stiffness field (start "field") belongs to the mesh it was fitted on:
        # another mesh gets the field's volume-weighted log-mean modulus
        mat = material_from_dict(info["base_material_homogeneous"])
    elif mat is not None and np.ndim(mat.youngs_modulus) and np.size(mat.youngs_modulus) != scene.mesh.num_tets:
        raise ValueError(f"{run_dir}: the learned model has a per-element Young's modulus for "
                         f"{np.size(mat.youngs_modulus)} tets; this scene's mesh has {scene.mesh.num_tets}")
    damp = damping_from_dict(info["base_damping"]) if info.get("base_damping") else None
    return scene.model(correction, material=mat, damping=damp)
