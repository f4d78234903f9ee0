"""BallPlant: derivatives, witness-located contacts, racket input, seeding, outputs."""

import numpy as np
import pytest
from pydrake.common import RandomGenerator
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialVelocity

from ace_drake.diagrams import StaticRacket, build_ball_diagram, make_simulator
from ace_drake.physics import contact
from ace_drake.physics.flight import flight_acceleration, make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, contact_gap, simulate
from ace_drake.systems.ball_plant import BallPlant

PARAMS = BallPhysicsParams()
R = PARAMS.aero.ball_radius


def run(diagram, state, duration, seed=0):
    ball = diagram.GetSubsystemByName("ball")
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.SetRandomContext(context, RandomGenerator(seed))
    ball_context = ball.GetMyMutableContextFromRoot(context)
    ball.SetBallState(ball_context, state)
    simulator.AdvanceTo(duration)
    return ball.ball_state_port.Eval(ball_context), ball.contact_events_port.Eval(ball_context)


def test_derivatives_are_eq_1():
    dut = BallPlant(PARAMS)
    context = dut.CreateDefaultContext()
    state = make_state([0.1, 0.2, 0.3], [5.0, -1.0, 2.0], [30.0, 200.0, -50.0])
    dut.SetBallState(context, state)
    derivatives = dut.EvalTimeDerivatives(context).CopyToVector()
    np.testing.assert_allclose(derivatives[:3], state[3:6])
    np.testing.assert_allclose(derivatives[3:6], flight_acceleration(state[3:6], state[6:], PARAMS.aero), rtol=1e-14)
    np.testing.assert_array_equal(derivatives[6:], 0.0)
    np.testing.assert_array_equal(dut.ball_state_port.Eval(context), state)
    assert dut.contact_events_port.Eval(context) == ()


def test_witnesses_have_the_sign_of_the_gaps_and_are_exact_near_contact():
    # The witnesses return cheap lower bounds while clearly positive (BallPlant's docstring).
    dut = BallPlant(PARAMS)
    context = dut.CreateDefaultContext()
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])  # normal along +x
    dut.racket_pose_port.FixValue(context, X_WR)
    rng = np.random.default_rng(0)
    positions = np.r_[rng.uniform([-3, -1.5, -1], [3, 1.5, 1], (300, 3)), [[0.5, 0.2, R + 1e-7], [R + 2e-9, 0.1, 0.05], [1.5, 0.0, -0.74]]]
    for p_W in positions:
        state = make_state(p_W, [1.0, 0.0, 0.0])
        dut.SetBallState(context, state)
        for kind in (ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR):
            gap = float(contact_gap(kind, state, PARAMS))
            witness = dut.CalcStaticGap(context, kind)
            assert witness <= gap + 1e-15 and (witness > 0) == (gap > 0)
            if witness <= 1e-9:
                assert witness == gap
    for depth in (0.003, 1e-8, -1e-6):  # in front of the blade's face, 2 cm off its centre
        p_W = X_WR.multiply([0.02, 0.0, 0.5 * PARAMS.racket.blade_thickness + R + depth])
        dut.SetBallState(context, make_state(p_W, [-1.0, 0.0, 0.0]))
        assert dut.CalcRacketGap(context) == pytest.approx(depth, abs=1e-12)
    dut.SetBallState(context, make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0]))  # 0.6 m in front
    assert 0.0 < dut.CalcRacketGap(context) <= 0.6 - R - 0.5 * PARAMS.racket.blade_thickness


def test_drop_test_impact_time_within_a_microsecond():
    # Vertical fall with quadratic drag has the closed form z(t) = z0 - (v_t^2 / g) ln cosh(g t / v_t).
    ratio = PARAMS.aero.air_density / PARAMS.aero.ball_density
    g = (1 - ratio) * PARAMS.aero.gravity
    k_drag = 3 / (8 * R) * PARAMS.aero.drag_coefficient * ratio
    height = 0.305
    t_impact = np.sqrt(g / k_drag) / g * np.arccosh(np.exp(height * k_drag))
    _, events = run(build_ball_diagram(PARAMS), make_state([0.5, 0.3, height + R], [0, 0, 0]), 0.4)
    assert events[0].kind == ContactKind.TABLE
    assert abs(events[0].time - t_impact) < 1e-6
    assert events[0].state_pre[2] == pytest.approx(R, abs=1e-6)


def test_plant_agrees_with_the_propagator():
    start = make_state([-1.2, 0.1, 0.25], [6.0, 0.5, 1.5], [0.0, 200.0, 30.0])
    final, events = run(build_ball_diagram(PARAMS), start, 1.0)
    reference = simulate(start, PARAMS, 1.0, dt=5e-4)
    assert [e.kind for e in events] == [e.kind for e in reference.events[0]]
    for plant_event, pure_event in zip(events, reference.events[0]):
        assert plant_event.time == pytest.approx(pure_event.time, abs=1e-6)
        np.testing.assert_allclose(plant_event.state_post, pure_event.state_post, atol=1e-4)
    np.testing.assert_allclose(final, reference.final_state[0], atol=1e-3)


def test_racket_returns_the_ball_with_eq_7_and_8():
    # Blade at x = -1.2 facing +x (its normal z_R along +x), moving towards the ball at 3 m/s.
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    V_WR = SpatialVelocity(np.zeros(3), np.array([3.0, 0.0, 0.0]))
    diagram = build_ball_diagram(PARAMS, racket=StaticRacket(X_WR, V_WR))
    start = make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0], [0.0, -100.0, 0.0])
    _, events = run(diagram, start, 0.5)
    racket_event = next(e for e in events if e.kind == ContactKind.RACKET)
    # The ball touches the face: centre r + t/2 in front of the blade plane.
    assert racket_event.state_pre[0] == pytest.approx(-1.2 + R + 0.5 * PARAMS.racket.blade_thickness, abs=1e-6)
    R_WC = X_WR.rotation().matrix()
    expected_v, expected_w = contact.racket_impact(
        racket_event.state_pre[3:6], racket_event.state_pre[6:], np.array([3.0, 0, 0]), R_WC, PARAMS.racket, R
    )
    np.testing.assert_allclose(racket_event.state_post[3:6], expected_v, atol=1e-9)
    np.testing.assert_allclose(racket_event.state_post[6:], expected_w, atol=1e-9)
    assert racket_event.state_post[3] > 5.0  # sent back towards the opponent


def test_racket_back_face_uses_the_flipped_normal():
    # Same blade, turned round: its normal points to -x, the ball arrives on its back face.
    X_front = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    X_back = RigidTransform(RotationMatrix.MakeYRotation(-np.pi / 2), [-1.2, 0.0, 0.2])
    start = make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0], [0.0, -100.0, 40.0])
    events_front = run(build_ball_diagram(PARAMS, racket=StaticRacket(X_front)), start, 0.2)[1]
    events_back = run(build_ball_diagram(PARAMS, racket=StaticRacket(X_back)), start, 0.2)[1]
    front = next(e for e in events_front if e.kind == ContactKind.RACKET)
    back = next(e for e in events_back if e.kind == ContactKind.RACKET)
    assert front.time == pytest.approx(back.time, abs=1e-9)
    np.testing.assert_allclose(back.state_post, front.state_post, atol=1e-9)


def test_unconnected_racket_means_no_racket():
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    start = make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0])
    _, with_racket = run(build_ball_diagram(PARAMS, racket=StaticRacket(X_WR)), start, 0.3)
    _, without = run(build_ball_diagram(PARAMS), start, 0.3)
    assert any(e.kind == ContactKind.RACKET for e in with_racket)
    assert not any(e.kind == ContactKind.RACKET for e in without)


def test_ball_beside_the_racket_passes():
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    start = make_state([-0.6, 0.075 + R + 0.005, 0.2], [-6.0, 0.0, 0.0])  # 5 mm outside the blade
    _, events = run(build_ball_diagram(PARAMS, racket=StaticRacket(X_WR)), start, 0.3)
    assert not any(e.kind == ContactKind.RACKET for e in events)


def test_perturbations_are_reproducible_by_seed():
    diagram = build_ball_diagram(PARAMS, perturb=True)
    start = make_state([0.6, 0.1, 0.3], [-4.0, 0.3, 0.0], [0.0, 150.0, 0.0])
    a, _ = run(diagram, start, 0.6, seed=11)
    b, _ = run(diagram, start, 0.6, seed=11)
    c, _ = run(diagram, start, 0.6, seed=12)
    unperturbed, _ = run(build_ball_diagram(PARAMS), start, 0.6)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert not np.allclose(a, unperturbed)


def test_set_ball_state_rejects_bad_input():
    dut = BallPlant(PARAMS)
    context = dut.CreateDefaultContext()
    with pytest.raises(ValueError, match="SetBallState"):
        dut.SetBallState(context, np.zeros(6))
    with pytest.raises(ValueError, match="SetBallState"):
        dut.SetBallState(context, np.full(9, np.nan))


def test_a_fast_ball_does_not_tunnel_through_the_blade():
    # BallPlant's docstring: under make_simulator's settings a 48 m/s ball is caught by the racket
    # witness, not stepped over (at this speed the 1e-6 accuracy already keeps steps near 0.25 ms;
    # the 1 ms cap matters for a moving racket, which a StaticRacket cannot show).
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    start = make_state([-0.2, 0.0, 0.2], [-48.0, 0.0, 0.0])
    _, events = run(build_ball_diagram(PARAMS, racket=StaticRacket(X_WR)), start, 0.05)
    racket_event = next(e for e in events if e.kind == ContactKind.RACKET)
    assert racket_event.state_pre[0] == pytest.approx(-1.2 + R + 0.5 * PARAMS.racket.blade_thickness, abs=1e-6)


def test_racket_witness_bounds_by_the_reach_box_without_reading_the_racket():
    # The blade's centre stays in the box: far from it the witness needs no racket pose (the
    # input is left unset here, and reading it would raise); near it, the witness is as without.
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    box = (np.array([-1.5, -0.3, 0.0]), np.array([-1.0, 0.3, 0.5]))
    dut, reference = BallPlant(PARAMS, racket_reach=box), BallPlant(PARAMS)
    unset, context, reference_context = dut.CreateDefaultContext(), dut.CreateDefaultContext(), reference.CreateDefaultContext()
    dut.racket_pose_port.FixValue(context, X_WR)
    reference.racket_pose_port.FixValue(reference_context, X_WR)
    far = make_state([0.5, 0.0, 0.3], [-6.0, 0.0, 0.0])
    dut.SetBallState(unset, far)
    assert dut.CalcRacketGap(unset) == pytest.approx(1.5 - np.hypot(PARAMS.racket.blade_radius, 0.5 * PARAMS.racket.blade_thickness) - R)
    rng = np.random.default_rng(1)
    for p_W in np.r_[rng.uniform([-2, -1, -0.5], [0.5, 1, 1], (300, 3)), [X_WR.multiply([0.02, 0.0, 0.5 * PARAMS.racket.blade_thickness + R + 1e-8])]]:
        dut.SetBallState(context, make_state(p_W, [-1.0, 0.0, 0.0]))
        reference.SetBallState(reference_context, make_state(p_W, [-1.0, 0.0, 0.0]))
        witness, gap = dut.CalcRacketGap(context), reference.CalcRacketGap(reference_context)
        assert witness <= gap + 1e-15 and (witness > 0) == (gap > 0)
        if gap <= 1e-9:
            assert witness == gap
    with pytest.raises(ValueError, match="racket_reach"):
        BallPlant(PARAMS, racket_reach=(box[1], box[0]))
