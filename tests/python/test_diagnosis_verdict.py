"""Verdict rules on synthetic fits (no simulation): which of several fits the data cannot tell
apart leads, and when a nested family's extra parameters count as evidence."""
import numpy as np

from matlearn.diagnosis import fitting, pipeline, ranking


def _row(name, rss, n_eff=400.0, floor=1e-2, credit=None):
    dof = pipeline._dof(name)
    row = {"name": name, "rss": rss, "score": fitting.score(rss, dof, n_eff, floor), "_fit": object()}
    if credit is not None:
        row["credited"] = fitting.score(rss + credit.get(name, 0.0), dof, n_eff, floor)
    return row


def test_a_tie_is_led_by_the_fit_that_is_best_once_charged_its_discretisation_credit():
    # a located region leaves 1/5 of the uniform scale's residual, but could mimic a large part
    # of the mesh's error (credit 0.09): its gain (0.10) is within CREDIT_FACTOR x its credit, so
    # neither fit beats the other. Charged all it could have mimicked (0.02 + 0.09 = 0.11) it
    # still explains more than the scale (0.12 + 0.001): it leads, confounded with the scale.
    credit = {"stiffness_scale": 1e-3, "density": 1e-3, "heterogeneity": 9e-2}
    tol = {n: 1e-5 for n in credit}
    rows = [_row(n, r, credit=credit) for n, r in
            (("stiffness_scale", 0.12), ("density", 0.12), ("heterogeneity", 0.02))]
    assert not ranking.beats(rows[2], rows[0], credit, tol)
    ranking.confounded(rows, credit, tol, rss0=0.55)
    out = ranking.order(rows, credit, tol)
    assert [r["name"] for r in out] == ["heterogeneity", "stiffness_scale", "density"]
    assert "stiffness_scale" in out[0]["confounded_with"]
    # when the credit could explain the whole gain, the uniform scale leads
    credit["heterogeneity"] = 0.11
    rows = [_row(n, r, credit=credit) for n, r in (("stiffness_scale", 0.12), ("heterogeneity", 0.02))]
    assert ranking.order(rows, credit, tol)[0]["name"] == "stiffness_scale"


def test_a_nested_family_needs_a_leave_one_out_gain_beyond_the_noise():
    # strain-dependent damping (contains Rayleigh damping) fits better than its credit and by the
    # criterion, but its leave-one-recording-out residual is lower only by a noise-sized amount
    rss_noise, n = 3.3e-3, 40000
    tol = {nm: ranking.noise_tolerance(rss_noise, n, pipeline._dof(nm))
           for nm in ("strain_dependent_damping", "rayleigh_damping")}
    credit = {"strain_dependent_damping": 2.6e-5, "rayleigh_damping": 2.1e-5}
    big = _row("strain_dependent_damping", 3.96e-3, n_eff=340, floor=3.4e-3)
    small = _row("rayleigh_damping", 4.22e-3, n_eff=340, floor=3.4e-3)
    big["score"] = small["score"] - 0.3
    assert ranking.beats(big, small, credit, tol)
    loo = {"strain_dependent_damping": 4.8560e-3, "rayleigh_damping": 4.8593e-3}
    best, forced = pipeline._resolve_nested([big, small], lambda name, fit: loo[name], credit, tol,
                                            lambda m: None)
    assert best["name"] == "rayleigh_damping"
    assert forced["_ties"] == [("rayleigh_damping", "strain_dependent_damping")]
    # a clear leave-one-recording-out gain decides for the larger family
    loo["strain_dependent_damping"] = 4.0e-3
    best, _ = pipeline._resolve_nested([big, small], lambda name, fit: loo[name], credit, tol,
                                       lambda m: None)
    assert best["name"] == "strain_dependent_damping"
    assert np.isfinite(best["score"])

