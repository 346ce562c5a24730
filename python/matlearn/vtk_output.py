"""ParaView output: a time series of `.vtu` files (one per frame, deformed positions) indexed by
a `.pvd` collection, written with meshio."""
from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np


def write_time_series(out_dir, mesh, times, X, point_data: dict | None = None,
                      cell_data: dict | None = None, name: str = "frame") -> Path:
    """Write `out_dir/<name>_<i>.vtu` for each frame and `out_dir/<name>.pvd`; returns the .pvd.

    times (F,), X (F, n, 3) deformed positions. Every frame gets point data `displacement`
    (X - rest). point_data / cell_data values are per frame (F, n, ...) / (F, m, ...) or constant
    over frames (n, ...) / (m, ...)."""
    import meshio

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    times = np.asarray(times, float).ravel()
    X = np.asarray(X, float)
    rest = np.asarray(mesh.vertices, float)
    tets = np.asarray(mesh.tets)
    n, m = len(rest), len(tets)
    F = len(times)
    if X.shape != (F, n, 3):
        raise ValueError(f"X: expected shape ({F}, {n}, 3) from times and mesh, got {X.shape}")

    def frame_value(arr, size, what, f):
        a = np.asarray(arr)
        if a.shape[:2] == (F, size) and not (F == size and a.ndim == 1):
            return a[f]
        if a.shape[0] == size:
            return a
        raise ValueError(f"{what}: expected leading shape ({F}, {size}) or ({size},), got {a.shape}")

    entries = []
    for f in range(F):
        pd = {"displacement": X[f] - rest}
        for k, v in (point_data or {}).items():
            pd[k] = frame_value(v, n, f"point_data[{k!r}]", f)
        cd = {k: [frame_value(v, m, f"cell_data[{k!r}]", f)] for k, v in (cell_data or {}).items()}
        fname = f"{name}_{f:05d}.vtu"
        meshio.write(out / fname, meshio.Mesh(X[f], [("tetra", tets)], point_data=pd, cell_data=cd))
        entries.append(f'    <DataSet timestep="{float(times[f])!r}" group="" part="0" file={quoteattr(fname)}/>')
    pvd = out / f"{name}.pvd"
    pvd.write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n"
    )
    return pvd
