"""The diagnosis report: a self-contained HTML page (figures embedded as base64 PNG) and ParaView
.vtu files of the residual maps."""
from __future__ import annotations

import base64
import html
import io

import numpy as np


# units of the parameters `effects.describe` reports (the rest are dimensionless)
PARAMETER_UNITS = {"alpha_mass": "1/s", "alpha_stiffness": "s", "stress_at_strain_ref_Pa": "Pa"}


def parameters_text(params: dict) -> str:
    """An effect's parameters for a person: 4 significant digits, ranges as [lo, hi], units named
    (diagnosis.json keeps the full values)."""
    def value(v):
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    return ", ".join(f"{k} {value(v)}" + (f" {PARAMETER_UNITS[k]}" if k in PARAMETER_UNITS else "")
                     for k, v in params.items())


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def residual_map_figure(mesh, values, title, region=None):
    """Surface triangles coloured by the value of their tet (matplotlib 3D)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    V = np.asarray(mesh.vertices)
    T = np.asarray(mesh.tets)
    F = np.asarray(mesh.surface_faces)
    # owner tet of each surface face: the tet containing all three vertices
    key = {tuple(sorted(t[list(c)])): e for e, t in enumerate(T)
           for c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))}
    owner = np.array([key.get(tuple(sorted(f)), 0) for f in F])
    val = np.asarray(values, float)[owner]
    fig = plt.figure(figsize=(6.5, 4))
    ax = fig.add_subplot(111, projection="3d")
    norm = plt.Normalize(val.min(), val.max() if val.max() > val.min() else val.min() + 1)
    cmap = plt.get_cmap("magma")
    coll = Poly3DCollection(V[F], facecolors=cmap(norm(val)), edgecolors=(0, 0, 0, 0.15), linewidths=0.2)
    ax.add_collection3d(coll)
    if region is not None and np.any(region):
        C = V[T[region]].mean(axis=1)
        ax.scatter(C[:, 0], C[:, 1], C[:, 2], s=4, c="cyan", label="located region")
        ax.legend(loc="upper left", fontsize=7)
    lo, hi = V.min(0), V.max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_title(title, fontsize=9)
    m = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(m, ax=ax, shrink=0.6)
    return fig


def _bar(labels, values, title, ylabel):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 2.8))
    ax.bar(range(len(values)), values, color="#4a7ab5")
    ax.set_xticks(range(len(values)))
    ax.set_xticklabels(labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    return fig


def write_vtu(path, mesh, cell_data: dict):
    import meshio

    m = meshio.Mesh(np.asarray(mesh.vertices), [("tetra", np.asarray(mesh.tets))],
                    cell_data={k: [np.asarray(v, float)] for k, v in cell_data.items()})
    m.write(str(path))


def _trajectory_figure(problem, model_pairs):
    """Observed vs predicted displacement magnitude of the most moving marker (first test or
    train recording) for the nominal and the corrected model."""
    import matplotlib.pyplot as plt

    rec = (problem.test or problem.train)[0]
    disp = np.linalg.norm(np.nan_to_num(rec.markers - rec.marker_rest[None]), axis=2)
    k = int(np.argmax(disp.max(axis=0)))
    fig, ax = plt.subplots(figsize=(6.5, 2.8))
    obs = rec.markers[:, k] - rec.marker_rest[k]
    comp = int(np.argmax(np.nanmax(np.abs(obs), axis=0)))
    ax.plot(rec.times, 1e3 * obs[:, comp], "k.", ms=2, label="recorded")
    for label, model in model_pairs:
        P = problem.predict(model, rec, fast=False)
        ax.plot(rec.times, 1e3 * (P[:, k, comp] - rec.marker_rest[k, comp]), label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"marker {k} d{'xyz'[comp]} (mm)")
    ax.legend(fontsize=7)
    ax.set_title("held-out marker trajectory" if problem.test else "train marker trajectory", fontsize=9)
    return fig


def mesh_paragraph(result) -> str:
    """What the model's mesh contributes to the gap (result["discretisation"]), as HTML."""
    d = result.get("discretisation")
    if not d:
        return ""
    g, gb = d.get("gap_with_offset"), result["gap_before"]
    text = (f"linear tets are too stiff; this mesh matches its once-refined mesh with E x "
            f"{d['refined_mesh_factor']:.3g}, and the recordings ask for E x {d['stiffness_factor']:.3g} "
            f"(inside the range a finer truth explains, {d['factor_range'][0]:.3g} .. {d['factor_range'][1]:.3g}; "
            f"a uniform stiffness or density change inside it cannot be told apart from the mesh's error).")
    what = gap_label(result.get("held_out", True))
    if g:
        text += (f" With that factor alone, no effect added, the {what} is max {g['max_error_pct']:.2f} %"
                 f" (before {gb['max_error_pct']:.2f} %).")
    gr = d.get("gap_refined_mesh")
    if gr:
        text += (f" The nominal material on the once-refined mesh (each tet split into 8) gives max "
                 f"{gr['max_error_pct']:.2f} %.")
    advice = mesh_advice(result)
    if advice:
        text += " " + advice[0].upper() + advice[1:] + "."
    return f"<p><b>Mesh:</b> {html.escape(text)}</p>"


def gap_label(held_out: bool) -> str:
    """What gap_before measures: the test recordings, or the train ones when there is none."""
    return "held-out gap" if held_out else "gap on the train recordings (no test recording)"


def mesh_advice(result) -> str | None:
    """What to do about the mesh when the verdict is empty and the mesh alone accounts for most
    of the gap (None otherwise): refine it where the once-refined mesh halves the gap; where only
    the stiffness factor does (the refined mesh does not), the gap is a uniform stiffness or
    density change that this mesh's error cannot be told from."""
    d, gb = result.get("discretisation") or {}, result["gap_before"]["max_error_pct"]
    if result["verdict"] or not gb:
        return None
    g, gr = d.get("gap_with_offset"), d.get("gap_refined_mesh")
    if gr and gr["max_error_pct"] < 0.5 * gb:
        return "most of the gap is the mesh's discretisation: refine the mesh"
    if g and g["max_error_pct"] < 0.5 * gb:
        if gr:
            return (f"E x {d['stiffness_factor']:.3g} on this mesh removes most of the gap but the once-refined "
                    "mesh does not: a uniform stiffness or density change of the material that this mesh's "
                    "discretisation error cannot tell from its own; diagnosing on a finer mesh can")
        return f"most of the gap is the mesh's discretisation: refine the mesh (or scale E by {d['stiffness_factor']:.3g} on it)"
    return None


def decay_paragraph(result) -> str:
    """The recordings' modal decay against the nominal damping law (result["decay"]), as HTML."""
    d = result.get("decay")
    if not d or d.get("ratio") is None:
        return ""
    per = "; ".join(f"{r['decay_rate']:.3g} 1/s at {r['angular_frequency']:.3g} rad/s (nominal law "
                    f"{r['nominal_decay_rate']:.3g})" for r in d["recordings"] if r)
    text = (f"the recorded oscillations decay x{d['ratio']:.2f} as fast as the nominal damping (with the "
            f"integrator's numerical decay) predicts at their frequencies ({d['z']:.1f} standard errors): {per}. ")
    if d["change"]:
        text += (f"The damping is {d['change']} than modelled; coefficients reproducing the decays: alpha_M "
                 f"{d['alpha_mass']:.4g} 1/s, alpha_K {d['alpha_stiffness']:.4g} s ({d['coefficients']}).")
    else:
        text += f"Inside {d['band'][0]:g} .. {d['band'][1]:g}: no damping change is concluded from the decays."
    return f"<p><b>Decay:</b> {html.escape(text)}</p>"


def write_report(out, problem, ctx, result, shares, field, fits, selected, patch_theta, labels):
    from .effects import build_model

    mesh = problem.mesh
    figs = []
    figs.append(("Residual share per element (control-force work)",
                 _png(residual_map_figure(mesh, shares, "residual share per element"))))
    region = ctx.region if "heterogeneity" in result["verdict"] else None
    figs.append(("Fitted log-stiffness change per spatial patch (simulation sensitivities)",
                 _png(residual_map_figure(mesh, patch_theta[labels], "patch log-stiffness change", region))))
    rg = result["where"]["regime"]
    figs.append(("Regimes", _png(_bar(list(rg), list(rg.values()), "residual by regime", "share"))))
    sb = np.array(result["where"]["frames"]["share_by_time"])
    figs.append(("Residual over time", _png(_bar([f"{t:.2f}" for t in sb[:, 0]], sb[:, 1],
                                                "residual share by time (s)", "share"))))
    eff = result["effects"]
    figs.append(("Effect ranking", _png(_bar([e["name"] for e in eff], [e["explained"] for e in eff],
                                             "fraction of the residual explained (train markers; decay-claimed damping: the decay mismatch)",
                                             "explained"))))
    pairs = [("nominal", problem.scene.model())]
    if selected is not None:
        pairs.append(("with " + " + ".join(selected.params), build_model(ctx, selected.params)))
    figs.append(("Marker trajectories before/after", _png(_trajectory_figure(problem, pairs))))

    write_vtu(out / "residual_map.vtu", mesh, {
        "residual_share": shares,
        "stress_residual_rms": np.sqrt((field.dp**2).sum(axis=2).mean(axis=0)),
        "patch_log_stiffness": patch_theta[labels],
        "patch": labels.astype(float),
        "located_region": (ctx.region if ctx.region is not None else np.zeros(mesh.num_tets)).astype(float),
    })
    rows = "".join(
        f"<tr><td>{html.escape(e['name'])}</td><td>{e['explained']:.3f}"
        f"{' (of the decay mismatch)' if e.get('evidence') == 'decay' else ''}</td><td>{e['score']:.1f}</td>"
        f"<td>{html.escape(parameters_text(e['parameters']))}</td>"
        f"<td>{'' if not e.get('gap_after') else '%.2f / %.2f' % (e['gap_after']['max_error_pct'], e['gap_after']['rms_error_pct'])}"
        f"{' (grows the held-out gap)' if e.get('held_out_worse') else ''}</td>"
        f"<td>{html.escape(', '.join(e.get('confounded_with', [])))}</td></tr>"
        for e in eff)
    gb = result["gap_before"]
    body = f"""<html><head><meta charset="utf-8"><title>matlearn diagnosis</title>
<style>body{{font-family:sans-serif;max-width:900px;margin:auto}}td,th{{padding:2px 8px;border-bottom:1px solid #ddd;font-size:13px}}</style>
</head><body><h1>Sim-to-real gap diagnosis</h1>
<p><b>Verdict:</b> {html.escape(', '.join(result['verdict']) or 'no effect beyond noise and discretisation')}</p>
<p>Held-out gap before: max {gb['max_error_pct']:.2f} %, RMS {gb['rms_error_pct']:.2f} % of the object size
({result['object_size']:.4g} m){'' if result['held_out'] else ' (no test recording: scored on train)'}.
Floor: train rss {result['floor']['rss_train']:.3e} vs noise+discretisation {result['floor']['rss_floor']:.3e}.</p>
{mesh_paragraph(result)}
{decay_paragraph(result)}
<h2>Which effect</h2><table><tr><th>effect</th><th>explained</th><th>score (BIC)</th><th>parameters</th>
<th>gap after (max / RMS %)</th><th>confounded with</th></tr>{rows}</table>
<h2>Where</h2>{''.join(f'<h3>{html.escape(t)}</h3><img src="{src}">' for t, src in figs)}
<p>ParaView: residual_map.vtu (cell data).</p></body></html>"""
    (out / "report.html").write_text(body)
