"""The racket contact run backwards (physics/racket_inverse.py): the inversion of eqs (7)-(8),
checked by hand and through the forward model, and the return solve."""

import dataclasses

import numpy as np
import pytest
import torch

from ace_drake.analysis.scripted_swing import INCOMING_BALL
from ace_drake.physics import racket_inverse
from ace_drake.physics.contact import racket_impact, racket_restitution
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate
from ace_drake.physics.racket_inverse import contact_frame, invert_racket_contact, solve_return
from ace_drake.physics.racket_residual import RacketResidualMLP, residual_model, save_residual

PARAMS = BallPhysicsParams()
RADIUS = PARAMS.aero.ball_radius
# The scripted swing's incoming ball at the top of its bounce on the robot's half (0.68 s).
APEX_BALL = simulate(INCOMING_BALL, PARAMS, 0.68).final_state[0]


def test_the_inversion_of_a_head_on_hit_is_hand_worked():
    # No spin, straight along x: the normal is x and the normal law of eq. (7) alone sets the speed.
    v_in, v_out = np.array([-5.0, 0.0, 0.0]), np.array([4.0, 0.0, 0.0])
    normal, v_racket = invert_racket_contact(v_in, np.zeros(3), v_out, PARAMS.racket, RADIUS)
    np.testing.assert_allclose(normal, [1.0, 0.0, 0.0], atol=1e-12)
    speed = v_racket[0]
    eps = racket_restitution(-5.0 - speed, PARAMS.racket)
    assert 4.0 - speed == pytest.approx(-eps * (-5.0 - speed), abs=1e-9)  # v_out.n - s = -eps (v_in.n - s)
    # By hand: eps(4.887 m/s) = 0.8901 exp(-0.011418 * 4.887) = 0.8418, s = (4 - 5 eps) / (1 + eps):
    # the ball would come back at 4.2 m/s off a still racket, so the racket gives way a little.
    assert speed == pytest.approx(-0.1135, abs=2e-4)


@pytest.mark.parametrize("brush_speed", [0.0, 2.5])
def test_the_inversion_reproduces_the_outgoing_velocity_through_eqs_7_8(brush_speed):
    rng = np.random.default_rng(3)
    for _ in range(20):
        v_in = np.array([-7.0, 0.0, -1.0]) + rng.normal(size=3) * [2.0, 1.5, 1.5]
        w_in = rng.normal(size=3) * 250.0
        v_out = np.array([6.0, 0.0, 2.0]) + rng.normal(size=3) * [1.5, 1.0, 1.0]
        normal, v_racket = invert_racket_contact(v_in, w_in, v_out, PARAMS.racket, RADIUS, brush_speed)
        v_post, _ = racket_impact(v_in, w_in, v_racket, contact_frame(normal), PARAMS.racket, RADIUS)
        np.testing.assert_allclose(v_post, v_out, atol=1e-9)
        assert np.linalg.norm(normal) == pytest.approx(1.0) and normal[0] > 0.0  # the forehand faces the opponent
        tangential = v_racket - (v_racket @ normal) * normal
        assert np.linalg.norm(tangential) == pytest.approx(brush_speed, abs=1e-9)
        assert tangential[2] >= -1e-12  # brushing upwards


def test_a_solved_return_lands_on_the_target_over_the_net():
    target = np.array([0.8, -0.3])
    shot = solve_return(APEX_BALL, target, 0.55, PARAMS)
    assert shot is not None
    flight = simulate(np.concatenate([APEX_BALL[:3], shot.v_out, shot.w_out]), PARAMS, 2.0, stop_on=(ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR))
    landing = flight.stop_events[0]
    assert landing.kind == ContactKind.TABLE
    assert landing.time == pytest.approx(0.55, abs=2e-3)
    np.testing.assert_allclose(landing.state_pre[:2], target, atol=0.01)
    assert shot.net_clearance > 0.04


def test_a_diverging_return_solve_gives_up_instead_of_raising(monkeypatch):
    # A non-finite iterate (seen in training: a near-singular Jacobian) and a singular Jacobian.
    assert solve_return(APEX_BALL, np.array([0.8, 0.0]), 0.55, PARAMS, v_guess=np.array([np.inf, 0.0, 1.0])) is None
    flat = simulate(np.tile(APEX_BALL, (4, 1)), PARAMS, 0.55, kinds=())  # every perturbed ball lands alike
    monkeypatch.setattr(racket_inverse, "simulate", lambda *args, **kwargs: flat)
    assert solve_return(APEX_BALL, np.array([0.8, 0.0]), 0.55, PARAMS) is None



class _PlantedResidual:
    """A smooth correction (N, 8) -> (N, 6) of the size the fitted network makes (~0.1 m/s, ~10 rad/s)."""

    def __call__(self, features):
        v = features[:, :3]
        return np.c_[0.02 * v[:, 2:3] * np.ones((1, 3)) + 0.01 * v[:, :3], 0.5 * v[:, [1, 0, 2]]]


def test_with_a_residual_the_inversion_is_solved_through_the_full_model():
    rng = np.random.default_rng(5)
    residual = _PlantedResidual()
    for _ in range(10):
        v_in = np.array([-7.0, 0.0, -1.0]) + rng.normal(size=3) * [2.0, 1.5, 1.5]
        w_in = rng.normal(size=3) * 250.0
        v_out = np.array([6.0, 0.0, 2.0]) + rng.normal(size=(4, 3)) * [1.5, 1.0, 1.0]
        closed = invert_racket_contact(v_in, w_in, v_out, PARAMS.racket, RADIUS, 1.0)
        normal, v_racket = invert_racket_contact(v_in, w_in, v_out, PARAMS.racket, RADIUS, 1.0, residual=residual)
        made, _ = racket_impact(v_in, w_in, v_racket, contact_frame(normal), PARAMS.racket, RADIUS, residual=residual)
        np.testing.assert_allclose(made, v_out, atol=1e-8)
        missed, _ = racket_impact(v_in, w_in, closed[1], contact_frame(closed[0]), PARAMS.racket, RADIUS, residual=residual)
        assert np.max(np.abs(missed - v_out)) > 1e-3  # the closed form alone would miss under the residual
        np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0)


def test_solve_return_uses_the_residual_the_params_select(tmp_path):
    network = RacketResidualMLP()
    with torch.no_grad():
        network.net[-1].bias.copy_(torch.tensor([0.3, -0.2, 0.4, 20.0, -15.0, 5.0]))  # a constant correction
    save_residual(network, tmp_path / "residual.pt")
    params = dataclasses.replace(PARAMS, racket=dataclasses.replace(PARAMS.racket, residual=str(tmp_path / "residual.pt")))
    shot = solve_return(APEX_BALL, np.array([1.0, 0.2]), 0.45, params)
    assert shot is not None
    v_out, w_out = racket_impact(APEX_BALL[3:6], APEX_BALL[6:9], shot.racket_velocity, contact_frame(shot.normal), params.racket, RADIUS,
                                 residual=residual_model(params.racket))
    np.testing.assert_allclose(v_out, shot.v_out, atol=1e-7)
    np.testing.assert_allclose(w_out, shot.w_out, atol=1e-5)
    plain = solve_return(APEX_BALL, np.array([1.0, 0.2]), 0.45, PARAMS)
    assert np.linalg.norm(plain.racket_velocity - shot.racket_velocity) > 0.05
