"""The held-out gap after each verdict effect (diagnosis.json): an effect whose refit grows the
held-out gap is marked as doing so (fitting.mark_held_out_changes), never left looking like a
shrink."""
from matlearn.diagnosis import fitting


def _gap(mx):
    return {"max_error_pct": mx, "rms_error_pct": mx / 3}


def test_an_effect_that_grows_the_held_out_gap_is_marked():
    effects = [{"name": "stiffness_scale", "gap_after": _gap(5.65)},
               {"name": "support_compliance", "gap_after": _gap(5.46)},
               {"name": "rayleigh_damping", "gap_after": _gap(4.0)}]
    grew = fitting.mark_held_out_changes(effects, ["stiffness_scale"], _gap(5.33))
    assert grew == ["stiffness_scale"]
    assert effects[0]["held_out_worse"] is True
    assert abs(effects[0]["gap_change_pct"] - 0.32) < 1e-9
    # entries outside the verdict are the effect alone, not a step of the verdict: unmarked
    assert "held_out_worse" not in effects[1] and "gap_change_pct" not in effects[1]


def test_each_step_is_compared_with_the_gap_before_it_was_added():
    # the first effect shrinks the gap, the second grows it again (cumulative gaps): only the
    # second is marked, although its gap is still below the nominal one
    effects = [{"name": "rayleigh_damping", "gap_after": _gap(2.0)},
               {"name": "compression_nonlinearity", "gap_after": _gap(2.5)},
               {"name": "history_dependence", "gap_after": _gap(9.0), "outside_library": True}]
    verdict = ["history_dependence", "rayleigh_damping", "compression_nonlinearity"]
    grew = fitting.mark_held_out_changes(effects, verdict, _gap(4.0))
    assert grew == ["compression_nonlinearity"]
    assert effects[0]["gap_change_pct"] == -2.0 and "held_out_worse" not in effects[0]
    assert effects[1]["gap_change_pct"] == 0.5
    assert "gap_change_pct" not in effects[2]  # outside the library: nothing was added
