"""The diagnosis's simulated marker predictions kept on disk while it runs, so a killed diagnosis
resumes (`diagnose(..., resume=True)`, `matlearn diagnose --resume`).

A diagnosis is a deterministic sequence of a few hundred simulations (sensitivities, fits,
held-out gaps); nearly all of them pass through `Problem.predict`, which already memoises its
markers in memory by (scene, recording, solver, model fingerprint). `SimulationStore` keeps the
same results in a folder whose manifest names the code that wrote it (a digest of every source
file of the matlearn package and of the compiled core: a rebuilt or edited matlearn discards an
earlier one's folder), each result under a digest of everything else the simulation depends on:

* the scene's mesh, clamp, time step and gravity (the once-refined scene of the discretisation
  step has its own);
* the recording's times, markers, marker rest positions, drive points and at-rest flag;
* the solver (Newton iterations per step), the start-velocity mode, and the model's fingerprint
  (`Problem.fingerprint`: its forces at a fixed random deformed, moving state and its masses).

A fresh diagnosis only writes (it simulates exactly as without a store). A resumed one re-runs the
same sequence and takes every stored result instead of simulating it, up to where the killed one
stopped. The few simulations outside `predict` (the start-velocity
scan, the `where` step's constrained replay, the history check's segments) run again. The
linearised replay's preconditioner depends on which simulations ran before (its solves are
converged to 1e-10, not bitwise), so a resumed diagnosis matches an uninterrupted one to
round-off, not bit for bit. The folder is removed once diagnosis.json is written.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
from functools import lru_cache
from pathlib import Path

import numpy as np

FOLDER = ".diagnose_cache"
FORMAT = 1


@lru_cache(maxsize=1)
def code_digest() -> str:
    """sha1 of every .py file of the matlearn package (by relative path) and of its compiled core."""
    from .. import _core

    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha1(f"format {FORMAT}".encode())
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    core = getattr(_core, "__file__", None)
    if core and Path(core).is_file():
        h.update(Path(core).read_bytes())
    return h.hexdigest()


def _digest(*parts) -> str:
    h = hashlib.sha1()
    for p in parts:
        if p is None:
            h.update(b"<none>")
        elif isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(repr(p).encode())
        h.update(b"|")
    return h.hexdigest()


def scene_digest(scene) -> str:
    """Digest of what a scene contributes to a simulation beyond the model: mesh, clamp, time step
    and gravity (material and damping enter through the model's fingerprint)."""
    mesh = scene.mesh
    return _digest(np.asarray(mesh.vertices, float), np.asarray(mesh.tets, np.int64),
                   np.asarray(scene.fixed, np.int64), float(scene.time_step),
                   tuple(float(g) for g in scene.gravity))


def recording_digest(rec) -> str:
    return _digest(rec.times, rec.marker_rest, rec.markers, bool(rec.at_rest_initially),
                   rec.drive_rest, rec.drive)


def _code_of(manifest: Path) -> str | None:
    """The code digest a store's manifest names (None: no readable manifest)."""
    try:
        return json.loads(manifest.read_text()).get("code")
    except (OSError, ValueError):
        return None


class SimulationStore:
    """Simulation results (tuples of arrays) by key in `folder` (one .npz file each, written
    atomically: a kill during a write leaves no partial entry)."""

    def __init__(self, folder, resume: bool = False):
        self.folder = Path(folder)
        # only a resumed run reads: a fresh run simulates everything as it always has (a result
        # computed twice within one run is recomputed, round-off and all), and only writes
        self.reading = bool(resume)
        self.hits = 0
        self._hits_lock = threading.Lock()  # get() runs in Problem.parallel's threads
        self._digests = {}  # id(obj) -> (obj, digest): scenes and recordings, hashed once
        manifest = self.folder / "manifest.json"
        if self.folder.exists() and not (resume and _code_of(manifest) == code_digest()):
            shutil.rmtree(self.folder)  # a fresh run, or results of other (or unknown) code
        # (a kill during a write leaves only a hidden .tmp file, never counted or read)
        self.resumed = sum(1 for p in self.folder.glob("*.npz") if not p.name.startswith(".")) \
            if self.folder.exists() else 0
        self.folder.mkdir(parents=True, exist_ok=True)
        manifest.write_text(json.dumps({"format": FORMAT, "code": code_digest()}))

    def _of(self, obj, fn) -> str:
        hit = self._digests.get(id(obj))
        if hit is None or hit[0] is not obj:
            hit = (obj, fn(obj))
            self._digests[id(obj)] = hit
        return hit[1]

    def key(self, scene, rec, *parts) -> str:
        """The key of a simulation of `rec` on `scene`; `parts`: everything else it depends on
        (solver, start mode, model fingerprints, arrays). The code is not part of it: a folder
        written by other code is discarded when the store opens (manifest.json)."""
        return _digest(self._of(scene, scene_digest), self._of(rec, recording_digest), *parts)

    def get(self, key: str):
        """The arrays stored under `key` (a tuple, in the order put), or None."""
        path = self.folder / f"{key}.npz"
        if not self.reading or not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                out = tuple(z[f"arr_{i}"] for i in range(len(z.files)))
        except (OSError, ValueError, KeyError):  # unreadable: simulate again
            return None
        with self._hits_lock:
            self.hits += 1
        return out

    def put(self, key: str, *arrays: np.ndarray) -> None:
        tmp = self.folder / f".{key}.{os.getpid()}.{threading.get_ident()}.tmp.npz"
        np.savez(tmp, *[np.asarray(a) for a in arrays])
        os.replace(tmp, self.folder / f"{key}.npz")

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
