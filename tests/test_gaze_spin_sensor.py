"""GazeSpinSensor: variable-rate samples of the true spin at their exact capture times, latency,
the per-contact bias, tracking loss after a racket contact, seeding."""

import dataclasses

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from ace_drake.diagrams import add_ball, make_simulator
from ace_drake.perception.params import SpinSensorParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.systems.gaze_spin_sensor import GazeSpinSensor

PHYSICS = BallPhysicsParams()
# Clears the net and lands once on the robot's half, at about 0.31 s.
BOUNCING = make_state([1.2, 0.1, 0.3], [-7.0, -0.2, 1.0], [30.0, -200.0, 15.0])
EXACT = SpinSensorParams(
    dropout_probability=0.0, magnitude_noise_std=0.0, axis_noise_std=0.0, magnitude_bias_std=0.0, axis_bias_std=0.0,
    history_capacity=1000,
)


def run(duration, params=SpinSensorParams(), seed=0, start=BOUNCING, racket_pose=None, connect_events=True):
    """(the sensor's history, the plant's contact events) after ``duration`` s."""
    builder = DiagramBuilder()
    ball = add_ball(builder, PHYSICS)
    dut = builder.AddNamedSystem("spin_sensor", GazeSpinSensor(params))
    builder.Connect(ball.ball_state_port, dut.ball_state_port)
    if connect_events:
        builder.Connect(ball.contact_events_port, dut.contact_events_port)
    if racket_pose is not None:
        pose = builder.AddNamedSystem("racket_pose_source", ConstantValueSource(AbstractValue.Make(racket_pose)))
        velocity = builder.AddNamedSystem("racket_velocity_source", ConstantValueSource(AbstractValue.Make(SpatialVelocity(np.zeros(6)))))
        builder.Connect(pose.get_output_port(), ball.racket_pose_port)
        builder.Connect(velocity.get_output_port(), ball.racket_velocity_port)
    diagram = builder.Build()
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), start)
    dut.SetSeed(dut.GetMyMutableContextFromRoot(context), seed)
    simulator.Initialize()
    simulator.AdvanceTo(duration)
    history = dut.spin_measurements_port.Eval(dut.GetMyContextFromRoot(context))
    return history, ball.contact_events_port.Eval(ball.GetMyContextFromRoot(context))


def true_spin(capture_times, events, final_spin):
    """The spin at each capture time from the contacts: piecewise constant in flight."""
    spins = np.tile(final_spin, (len(capture_times), 1))
    for event in reversed(events):
        spins[np.asarray(capture_times) < event.time] = event.state_pre[6:9]
    return spins


@pytest.fixture(scope="module")
def exact_run():
    return run(0.4, EXACT)


def test_samples_are_the_true_spin_at_their_capture_times_at_400_to_700_hz(exact_run):
    history, events = exact_run
    assert events[0].kind == ContactKind.TABLE and 0.1 < events[0].time < 0.35
    captures = np.array([m.capture_time for m in history.measurements])  # in release order
    intervals = np.diff(np.sort(captures))
    assert intervals.min() >= 1 / 700 - 1e-12 and intervals.max() <= 1 / 400 + 1e-12
    assert 400 * 0.38 < len(captures) < 700 * 0.4
    assert [m.sequence for m in history.measurements] == list(range(1, len(captures) + 1))
    values = np.array([m.value for m in history.measurements])
    np.testing.assert_allclose(values, true_spin(captures, events, events[-1].state_post[6:9]), rtol=0, atol=1e-9)
    # The bounce changed the spin and both sides of it were measured.
    assert not np.allclose(events[0].state_pre[6:9], events[0].state_post[6:9])
    assert captures.min() < events[0].time < captures.max()


def test_release_is_capture_plus_a_latency_in_range_and_nothing_early(exact_run):
    history, _ = exact_run
    latencies = np.array([m.release_time - m.capture_time for m in history.measurements])
    assert latencies.min() >= EXACT.latency_min and latencies.max() <= EXACT.latency_max
    assert max(m.release_time for m in history.measurements) <= 0.4
    releases = [m.release_time for m in history.measurements]
    assert releases == sorted(releases)  # numbered in release order


def test_bias_is_constant_between_contacts_and_redrawn_at_each():
    params = dataclasses.replace(EXACT, magnitude_bias_std=20.0, axis_bias_std=0.05)
    history, events = run(0.4, params)
    captures = np.array([m.capture_time for m in history.measurements])
    errors = np.array([m.value for m in history.measurements]) - true_spin(captures, events, events[-1].state_post[6:9])
    before, after = captures < events[0].time, captures >= events[0].time
    # Relative to the spin: the same magnitude offset and axis turn on every sample of an interval.
    for interval in (before, after):
        values = np.array([m.value for m in history.measurements])[interval]
        truth = true_spin(captures, events, events[-1].state_post[6:9])[interval]
        magnitude_offsets = np.linalg.norm(values, axis=1) - np.linalg.norm(truth, axis=1)
        np.testing.assert_allclose(magnitude_offsets, magnitude_offsets[0], atol=1e-9)
        assert abs(magnitude_offsets[0]) > 1e-3
    assert not np.isclose(errors[before][0], errors[after][0]).all()


def test_tracking_is_lost_right_after_a_racket_contact():
    # A blade facing +x at x = -1.2 m, in the path of a ball coming down the table's centre line.
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    start = make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0], [0.0, -100.0, 0.0])
    history, events = run(0.25, EXACT, start=start, racket_pose=X_WR)
    racket = next(e for e in events if e.kind == ContactKind.RACKET)
    captures = np.array([m.capture_time for m in history.measurements])
    assert not np.any((captures >= racket.time) & (captures <= racket.time + EXACT.racket_dropout_duration))
    assert np.any(captures < racket.time) and np.any(captures > racket.time + EXACT.racket_dropout_duration)
    # Before the contact the gap between samples is at most 1/400 s: the loss is the contact's.
    before = captures[captures < racket.time]
    assert racket.time - before.max() <= 1 / 400


def test_default_model_drops_about_five_percent():
    history, _ = run(0.4, dataclasses.replace(SpinSensorParams(), history_capacity=1000), connect_events=False)
    rate = len(history.measurements) / (0.4 - SpinSensorParams().latency_max)
    assert 0.85 * 400 < rate < 0.99 * 700


def test_a_seed_gives_the_same_measurements_bit_for_bit():
    first, again, other = (run(0.1, seed=seed)[0] for seed in (7, 7, 8))
    values = lambda h: np.array([np.r_[m.capture_time, m.release_time, m.value, m.covariance.ravel()] for m in h.measurements])
    np.testing.assert_array_equal(values(first), values(again))
    assert values(first).shape != values(other).shape or not np.array_equal(values(first), values(other))
