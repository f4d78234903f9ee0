"""BallEstimator in the smallest diagram: BallPlant -> statistical position sensor + gaze spin
sensor -> estimator. Accuracy, the outputs before a track, seeding, a racket contact, and that the
system is the BallEkf fed with the sensors' measurements."""

import dataclasses

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from ace_drake.diagrams import add_ball, make_simulator
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.params import EstimatorParams, PositionSensorParams, SpinSensorParams
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.systems.ball_estimator import BallEstimator
from ace_drake.systems.gaze_spin_sensor import GazeSpinSensor
from ace_drake.systems.statistical_position_sensor import StatisticalPositionSensor

PHYSICS = BallPhysicsParams()
SHOT = make_state([1.2, 0.1, 0.3], [-7.0, -0.2, 1.0], [30.0, -200.0, 15.0])  # lands at about 0.31 s
POSITION = dataclasses.replace(PositionSensorParams(), history_capacity=500)
SPIN = dataclasses.replace(SpinSensorParams(), history_capacity=1000)


class Rig:
    """The diagram and a simulator, with a racket standing at ``racket_pose`` if given."""

    def __init__(self, racket_pose=None, connect_events=True, params=None, spin=SPIN):
        builder = DiagramBuilder()
        self.ball = add_ball(builder, PHYSICS)
        self.positions = builder.AddNamedSystem("position_sensor", StatisticalPositionSensor(POSITION))
        self.spins = builder.AddNamedSystem("spin_sensor", GazeSpinSensor(spin))
        self.dut = builder.AddNamedSystem("ball_estimator", BallEstimator(params))
        builder.Connect(self.ball.ball_state_port, self.positions.ball_state_port)
        builder.Connect(self.ball.ball_state_port, self.spins.ball_state_port)
        builder.Connect(self.ball.contact_events_port, self.spins.contact_events_port)
        builder.Connect(self.positions.position_measurements_port, self.dut.position_measurements_port)
        builder.Connect(self.spins.spin_measurements_port, self.dut.spin_measurements_port)
        if connect_events:
            builder.Connect(self.ball.contact_events_port, self.dut.contact_events_port)
        if racket_pose is not None:
            pose = builder.AddNamedSystem("racket_pose_source", ConstantValueSource(AbstractValue.Make(racket_pose)))
            velocity = builder.AddNamedSystem("racket_velocity_source", ConstantValueSource(AbstractValue.Make(SpatialVelocity(np.zeros(6)))))
            builder.Connect(pose.get_output_port(), self.ball.racket_pose_port)
            builder.Connect(velocity.get_output_port(), self.ball.racket_velocity_port)
        self.diagram = builder.Build()
        self.simulator = make_simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()

    def start(self, state=SHOT, seed=0):
        """A new episode at time 0 from ``state``, both sensors seeded with ``seed``."""
        self.context.SetTime(0.0)
        self.ball.SetBallState(self.ball.GetMyMutableContextFromRoot(self.context), state)
        self.positions.SetSeed(self.positions.GetMyMutableContextFromRoot(self.context), seed)
        self.spins.SetSeed(self.spins.GetMyMutableContextFromRoot(self.context), seed)
        self.simulator.Initialize()

    def outputs(self):
        context = self.dut.GetMyContextFromRoot(self.context)
        return (
            self.dut.ball_state_estimate_port.Eval(context),
            self.dut.ball_covariance_port.Eval(context).reshape(9, 9),
            self.dut.estimate_status_port.Eval(context),
        )

    def truth(self):
        return self.ball.ball_state_port.Eval(self.ball.GetMyContextFromRoot(self.context))

    def at(self, time):
        self.simulator.AdvanceTo(time)
        return self.outputs()


@pytest.fixture(scope="module")
def rig():
    return Rig()


def test_no_estimate_before_three_positions_have_arrived(rig):
    rig.start()
    estimate, covariance, status = rig.at(0.015)  # the first positions arrive after about 10 ms
    np.testing.assert_array_equal(estimate, 0.0)
    np.testing.assert_array_equal(covariance, 0.0)
    np.testing.assert_array_equal(status, [0.0, 0.0, -1.0])


def test_each_measurement_is_used_from_its_release_on(rig):
    # No polling wait: at any time the filter holds exactly what the sensors have released.
    rig.start(seed=4)
    context = rig.dut.GetMyContextFromRoot(rig.context)
    for now in np.arange(1, 240) * 0.5e-3 + 1.3e-4:  # off the sensors' and the update's instants
        rig.simulator.AdvanceTo(now)
        state = rig.dut.estimator_state(context)
        for port, read in ((rig.dut.position_measurements_port, state.last_position_sequence), (rig.dut.spin_measurements_port, state.last_spin_sequence)):
            released = [m.sequence for m in port.Eval(context).measurements if m.release_time <= now]
            assert read == (released[-1] if released else 0)
    assert state.last_position_sequence > 10 and state.last_spin_sequence > 30


@pytest.mark.parametrize("period, offset", [(None, None), (0.001, 0.0), (0.005, 0.002)])
def test_the_update_timing_changes_no_output(period, offset):
    # Whenever the filter is stored (the default: every 32 ms at 27 ms), the outputs are the filter
    # fed at once with everything released by the context's time, bit for bit: read every 4 ms
    # through a flight with a bounce. (Across timings the outputs agree to ~1e-6 only: the update
    # instants are also the ball integrator's step boundaries, which move the true ball by ~1e-14,
    # and the filter's finite-difference Jacobians magnify that.)
    params = EstimatorParams() if period is None else dataclasses.replace(EstimatorParams(), update_period=period, update_offset=offset)
    rig = Rig(params=params)
    rig.start(seed=6)
    context = rig.dut.GetMyContextFromRoot(rig.context)
    ekf = BallEkf()
    for now in np.arange(1, 100) * 0.004:
        estimate, _, status = rig.at(now)
        released = lambda port: [m for m in port.Eval(context).measurements if m.release_time <= now]
        expected = ekf.estimate(ekf.update(ekf.initial_state(), released(rig.dut.position_measurements_port), released(rig.dut.spin_measurements_port)), now)
        if expected is None:
            assert status[0] == 0.0
        else:
            np.testing.assert_array_equal(estimate, expected.mean)
    assert status[0] == 1.0 and now > 0.35  # tracked past the bounce (at about 0.31 s)


def test_estimate_tracks_the_ball_in_flight_and_after_the_bounce(rig):
    rig.start()
    estimate, covariance, status = rig.at(0.15)
    error = estimate - rig.truth()
    assert np.linalg.norm(error[:3]) < 0.01
    assert np.linalg.norm(error[3:6]) < 0.15
    assert np.linalg.norm(error[6:]) < 60.0  # the spin sensor's bias: ~18 rad/s typical
    assert status[0] == 1.0 and status[1] == 1.0
    assert POSITION.latency_min <= status[2] <= POSITION.latency_max + 0.001
    np.testing.assert_allclose(covariance, covariance.T)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    estimate, _, _ = rig.at(0.37)  # 60 ms after the bounce
    error = estimate - rig.truth()
    assert np.linalg.norm(error[3:6]) < 0.3
    assert rig.dut.estimator_state(rig.dut.GetMyContextFromRoot(rig.context)).filter.latest.resets == 0


def test_a_seed_gives_the_same_estimate_bit_for_bit(rig):
    results = []
    for seed in (3, 3, 4):
        rig.start(seed=seed)
        results.append(rig.at(0.1)[0].copy())
    np.testing.assert_array_equal(results[0], results[1])
    assert not np.array_equal(results[0], results[2])


def test_the_system_is_the_filter_fed_with_the_sensors_measurements(rig):
    rig.start(seed=5)
    rig.simulator.AdvanceTo(0.2005)
    positions = rig.positions.position_measurements_port.Eval(rig.positions.GetMyContextFromRoot(rig.context))
    spins = rig.spins.spin_measurements_port.Eval(rig.spins.GetMyContextFromRoot(rig.context))
    released = lambda history: [m for m in history.measurements if m.release_time <= 0.2005]
    ekf = BallEkf()
    expected = ekf.update(ekf.initial_state(), released(positions), released(spins)).latest
    actual = rig.dut.estimator_state(rig.dut.GetMyContextFromRoot(rig.context)).filter.latest
    np.testing.assert_array_equal(actual.mean, expected.mean)
    np.testing.assert_array_equal(actual.covariance, expected.covariance)


def test_a_racket_contact_restarts_the_track_on_the_returned_ball():
    # A blade at x = -1.2 m facing +x, in the path of a ball coming down the centre line.
    X_WR = RigidTransform(RotationMatrix.MakeYRotation(np.pi / 2), [-1.2, 0.0, 0.2])
    rig = Rig(racket_pose=X_WR)
    rig.start(make_state([-0.2, 0.0, 0.2], [-6.0, 0.0, 0.8], [0.0, -100.0, 0.0]))  # hit at 0.175 s
    _, _, status = rig.at(0.17)
    assert status[0] == 1.0
    events = rig.ball.contact_events_port.Eval(rig.ball.GetMyContextFromRoot(rig.context))
    assert not events
    rig.simulator.AdvanceTo(0.18)
    events = rig.ball.contact_events_port.Eval(rig.ball.GetMyContextFromRoot(rig.context))
    hit = next(e for e in events if e.kind == ContactKind.RACKET)
    _, _, status = rig.at(0.181)
    assert status[0] == 0.0  # dropped at once: what it knew was the incoming ball
    estimate, _, status = rig.at(round(hit.time + 0.06, 3))
    state = rig.dut.estimator_state(rig.dut.GetMyContextFromRoot(rig.context))
    assert state.filter.latest.resets == 1
    assert status[0] == 1.0
    assert estimate[3] > 0  # going back towards the opponent
    assert np.linalg.norm(estimate[3:6] - rig.truth()[3:6]) < 0.5


def test_without_contact_events_the_estimator_still_runs():
    rig = Rig(connect_events=False)
    rig.start()
    estimate, _, status = rig.at(0.1)
    assert status[0] == 1.0
    assert np.linalg.norm(estimate[:3] - rig.truth()[:3]) < 0.01


def test_measurements_lost_between_updates_are_an_error_not_a_silent_gap():
    # Stored every 0.5 s, the filter would need more than the spin sensor's default history (64).
    rig = Rig(params=dataclasses.replace(EstimatorParams(), update_period=0.5, update_offset=0.0), spin=SpinSensorParams())
    rig.start()
    rig.at(0.08)  # about 40 spins released: all still in the history
    with pytest.raises(RuntimeError, match="history_capacity"):
        rig.at(0.2)


def released_streams(count=4, ticks=18, tick=0.032, offset=0.0):
    """Per tick, B sensor histories and contact events as the segment-stepped sensors give them:
    returns through both statistical sensors, released tick by tick (histories of 64), and a
    racket contact at 0.2 s in environment 1. Yields (k tick - offset (s), ...) for k = 1, 2, ...."""
    from ace_drake.perception.ekf_evaluation import simulate_shots
    from ace_drake.perception.measurements import MeasurementHistory
    from ace_drake.perception.sensor_models import release_due
    from ace_drake.physics.propagate import ContactEvent
    from ace_drake.play.shots import RETURN_RANGES, synthetic_candidates, valid_shots

    candidates = synthetic_candidates(np.random.default_rng(4), RETURN_RANGES, 40)
    shots = simulate_shots(candidates[valid_shots(candidates, False)][:count], ticks * tick, seed=4)
    histories = [[MeasurementHistory(capacity=64), MeasurementHistory(capacity=64)] for _ in shots]
    pending = [[shot.positions, shot.spins] for shot in shots]
    racket = ContactEvent(ContactKind.RACKET, 0.2, np.zeros(9), np.zeros(9))
    for k in range(1, ticks + 1):
        now = k * tick - offset
        for row in range(count):
            for kind in range(2):
                histories[row][kind], pending[row][kind] = release_due(histories[row][kind], pending[row][kind], now)
        events = [(racket,) if row == 1 and now >= 0.2 else () for row in range(count)]
        yield now, [h[0] for h in histories], [h[1] for h in histories], events


def test_fusing_a_batch_is_fusing_each_environment():
    from ace_drake.systems.ball_estimator import EstimatorBatchState, EstimatorState, fuse_measurements, fuse_measurements_batch

    ekf = BallEkf()
    batch = EstimatorBatchState.initial(ekf, 4)
    single = [EstimatorState()] * 4
    for now, positions, spins, events in released_streams():
        batch = fuse_measurements_batch(ekf, batch, positions, spins, events, np.full(4, now))
        single = [fuse_measurements(ekf, single[b], positions[b], spins[b], events[b], now) for b in range(4)]
        again = fuse_measurements_batch(ekf, batch, positions, spins, events, np.full(4, now))
        assert again is batch  # nothing new
        for b in range(4):
            row = batch.row(b)
            assert (row.last_position_sequence, row.last_spin_sequence, row.contacts_seen) == (
                single[b].last_position_sequence, single[b].last_spin_sequence, single[b].contacts_seen)
            a, e = row.filter.latest, single[b].filter.latest
            assert (a.tracking, a.resets, a.time) == (e.tracking, e.resets, e.time)
            if e.tracking:
                np.testing.assert_array_equal(a.mean, e.mean)
                np.testing.assert_array_equal(a.covariance, e.covariance)
    assert single[1].filter.latest.resets >= 1 and all(state.filter.latest.tracking for state in single)


def test_fusing_a_batch_refuses_a_history_that_lost_measurements():
    from ace_drake.perception.measurements import MeasurementHistoryBatch
    from ace_drake.systems.ball_estimator import EstimatorBatchState, fuse_measurements_batch

    ekf = BallEkf()
    positions = MeasurementHistoryBatch.empty(2, 4)
    rows = np.array([1] * 6)  # six released in environment 1 since the filter read nothing: 1 and 2 are lost
    times = 0.005 * np.arange(1, 7)
    positions = positions.extended(rows, times, times + 0.01, np.tile([0.0, 0.0, 1.0], (6, 1)), np.tile(np.eye(3) * 1e-6, (6, 1, 1)))
    with pytest.raises(RuntimeError, match="position sensor's history starts at measurement 3, but the filter has read only up to 0"):
        fuse_measurements_batch(ekf, EstimatorBatchState.initial(ekf, 2), positions, MeasurementHistoryBatch.empty(2, 4), [(), ()], np.full(2, 0.05))
