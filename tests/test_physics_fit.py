"""Physics validation and fitting on synthetic pairs whose true coefficients are known."""

import numpy as np
import pytest

from ace_drake.analysis.bench import sample_incoming_balls
from ace_drake.analysis.physics_fit import fit_physics, get_value, with_values
from ace_drake.analysis.physics_validation import predict_pairs, summarize
from ace_drake.match_data import EventPairs
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate

TRUE = with_values(
    BallPhysicsParams(),
    ["aero.drag_coefficient", "aero.magnus_slope", "aero.magnus_offset", "table.friction", "table.restitution_base"],
    [0.42, 0.085, -0.01, 0.3, 0.93],
)


def synthetic_pairs(params, n=120, seed=1):
    """Shots from the human side, propagated to the table plane with ``params``: (start, bounce)."""
    starts = sample_incoming_balls(n, seed)
    trajectory = simulate(starts, params, 2.0, kinds=(ContactKind.NET, ContactKind.TABLE_PLANE),
                          stop_on=(ContactKind.TABLE_PLANE,), record=False)
    keep = [i for i, e in enumerate(trajectory.stop_events) if e is not None and e.state_pre[0] < 0]
    events = [trajectory.stop_events[i] for i in keep]
    return EventPairs(
        players=np.array(["synthetic"] * len(keep)),
        transitions=np.array(["shot_p2->bounce_p1"] * len(keep)),
        durations=np.array([e.time for e in events]),
        start_states=starts[keep],
        end_states=np.stack([np.concatenate([e.state_pre[:3], e.state_post[3:]]) for e in events]),
    )


def test_validation_of_the_true_model_is_exact():
    pairs = synthetic_pairs(TRUE)
    summary = summarize(pairs, predict_pairs(pairs, TRUE))
    assert summary["missed"] == 0
    assert summary["landing_error_m"]["p90"] < 1e-9
    assert summary["time_error_s"]["p90"] < 1e-9
    assert summary["post_bounce_velocity_error_mps"]["p90"] < 1e-9


def test_fit_recovers_planted_coefficients():
    pairs = synthetic_pairs(TRUE)
    start = BallPhysicsParams()
    before = summarize(pairs, predict_pairs(pairs, start))["landing_error_m"]["median"]
    result = fit_physics(pairs, start, max_evaluations=60)
    after = summarize(pairs, predict_pairs(pairs, result.params))["landing_error_m"]["median"]
    assert before > 0.05 and after < 0.005
    for name in ["aero.drag_coefficient", "aero.magnus_slope", "table.friction", "table.restitution_base"]:
        assert get_value(result.params, name) == pytest.approx(get_value(TRUE, name), rel=0.05), name


def test_fit_rejects_unknown_coefficients():
    with pytest.raises(ValueError, match="cannot fit"):
        fit_physics(synthetic_pairs(TRUE, n=5), names=("aero.ball_radius",))
