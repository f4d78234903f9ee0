"""SegmentBallEstimator: B environments' filters, each the BallEstimator's rule, tick by tick."""

import numpy as np
from pydrake.common.value import AbstractValue

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.systems.ball_estimator import EstimatorState, estimate_outputs, fuse_measurements
from ace_drake.systems.segment.ball_estimator import SegmentBallEstimator
from test_ball_estimator import released_streams


def test_each_environment_is_the_reference_rule_and_episodes_restart():
    timing = SegmentTiming()
    dut = SegmentBallEstimator(EstimatorParams(), BallPhysicsParams(), 4, timing)
    context = dut.CreateDefaultContext()
    ekf = BallEkf()
    single = [EstimatorState()] * 4
    lead = float(timing.seconds(timing.lead))
    for k, (now, positions, spins, events) in enumerate(released_streams(tick=timing.duration, offset=lead), start=1):
        ticks = np.full(4, k, dtype=np.int64)
        tick_now = float(timing.tick_time(ticks)[0])
        assert abs(tick_now - now) < 1e-12  # the estimate is at the system's tick time
        for port, value in ((dut.position_measurements_port, tuple(positions)), (dut.spin_measurements_port, tuple(spins)),
                            (dut.contact_events_port, tuple(events)), (dut.episode_ticks_port, ticks)):
            port.FixValue(context, AbstractValue.Make(value))
        estimates = dut.ball_state_estimate_port.Eval(context)
        status = dut.estimate_status_port.Eval(context)
        single = [fuse_measurements(ekf, single[b], positions[b], spins[b], events[b], tick_now) for b in range(4)]
        for b in range(4):
            expected_estimate, expected_status = estimate_outputs(ekf.estimate(single[b].filter, tick_now))
            np.testing.assert_array_equal(estimates[b], expected_estimate)
            np.testing.assert_array_equal(status[b], expected_status)
        context.get_mutable_abstract_state(0).set_value(dut.estimator_states(context))
    assert np.all(status[:, 0] == 1.0)
    dut.StartEpisodes(context, [2])
    state = context.get_abstract_state(0).get_value()
    assert not state.row(2).filter.latest.tracking and state.row(2).last_position_sequence == 0
    assert state.row(0).filter.latest.tracking
