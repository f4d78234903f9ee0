"""End to end: the robot's delayed joints swing a scripted trajectory and return a ball over the net."""

import numpy as np
import pytest

from ace_drake.analysis.scripted_swing import INCOMING_BALL, plan_scripted_swing, run_scripted_swing
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.robot.model import RobotModel


@pytest.fixture(scope="module")
def swing_run():
    model = RobotModel()
    params = BallPhysicsParams()
    swing = plan_scripted_swing(model, INCOMING_BALL, params)
    events, logs = run_scripted_swing(swing, INCOMING_BALL, model.scenario, params)
    return model, swing, events, logs


def test_a_scripted_swing_returns_the_ball_over_the_net(swing_run):
    _, swing, events, _ = swing_run
    kinds = [event.kind for event in events]
    assert kinds[:3] == [ContactKind.TABLE, ContactKind.RACKET, ContactKind.TABLE]
    assert events[0].state_pre[0] < 0  # bounced on the robot's half
    landing = events[2].state_pre
    assert 0.0 < landing[0] < 1.37 and abs(landing[1]) < 0.7625  # on the opponent's half
    assert ContactKind.NET not in kinds[:3]
    assert np.hypot(*(landing[:2] - swing.racket.predicted_landing)) < 0.15
    assert events[1].time == pytest.approx(swing.racket.time, abs=3e-3)


def test_the_delayed_joints_track_the_plan_at_the_hit(swing_run):
    model, swing, events, logs = swing_run
    times, joints = logs["joint_time"], logs["joints"]
    at_hit = np.argmin(np.abs(times - swing.racket.time))
    assert times[at_hit] == pytest.approx(swing.racket.time, abs=1e-6)
    np.testing.assert_allclose(model.racket_pose(joints[at_hit, :8]).translation(), swing.racket.position, atol=3e-3)
    # Velocity over the two command periods around the hit: the joint velocity itself ripples by
    # several percent within each period (every 1 kHz step of the command kicks the stiff servo).
    mean_velocity = (joints[at_hit + 1, :8] - joints[at_hit - 1, :8]) / (times[at_hit + 1] - times[at_hit - 1])
    np.testing.assert_allclose(mean_velocity, swing.v_hit, atol=0.02 * np.max(np.abs(swing.v_hit)))


def test_the_motion_stays_within_the_joint_limits(swing_run):
    model, _, _, logs = swing_run
    q, v = logs["joints"][:, :8], logs["joints"][:, 8:]
    assert np.all(q >= model.lower - 1e-3) and np.all(q <= model.upper + 1e-3)
    assert np.all(np.abs(v) <= model.velocity_limit * 1.02)
