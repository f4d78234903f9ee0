"""Reach coverage and swing speed (ace-drake bench reach)."""

import numpy as np
import pytest

from ace_drake.analysis.reach import HIT_HEIGHT, fastest_swing, reach_coverage, robot_contact_points, swing_through
from ace_drake.robot.model import RobotModel

HEADER = "player_id,rally_id,type,timestamp,ball_pos,ball_vel_out,ball_spin_out\n"


@pytest.fixture(scope="module")
def model():
    return RobotModel()


def test_contact_points_are_the_robot_shots(tmp_path):
    path = tmp_path / "events.csv"
    path.write_text(
        HEADER
        + 'A,/g/r/e1,shot_p2,1.0,[1.5 0.1 0.2],[-6 0 1],[0 0 0]\n'
        + 'A,/g/r/e2,shot_p1,1.5,[-1.8 0.3 0.25],[6 0 1],[0 0 0]\n'
        + 'A,/g/r/e3,bounce_p1,1.7,[0.5 0.1 0.02],[6 0 -1],[0 0 0]\n'
    )
    np.testing.assert_allclose(robot_contact_points(str(path)), [[-1.8, 0.3, 0.25]])
    path.write_text(HEADER + 'A,/g/r/e1,shot_p2,1.0,[1.5 0.1 0.2],[-6 0 1],[0 0 0]\n')
    with pytest.raises(ValueError, match="no robot contact points"):
        robot_contact_points(str(path))


def test_coverage_counts_reached_and_missed_points(model):
    points = np.array([[-1.8, 0.0, 0.25], [-2.5, -0.8, 0.15], [-0.8, 0.6, 0.3], [1.0, 0.0, 0.2]])
    coverage = reach_coverage(model, points)
    assert coverage["points"] == 4 and coverage["reached"] == 3
    assert coverage["fraction_reached"] == pytest.approx(0.75)
    assert coverage["missed_points"] == [[1.0, 0.0, 0.2]]


def test_a_swing_stays_within_the_limits_and_its_speed_is_the_jacobian_product(model):
    swing = swing_through(model, model.ready_pose)
    assert np.all(np.abs(swing.v_hit) <= model.velocity_limit + 1e-12)
    assert np.all(swing.q_start >= model.lower - 1e-12) and np.all(swing.q_start <= model.upper + 1e-12)
    # Braking after the hit fits too: q_hit + v^2 / (2 a) in the direction of motion.
    q_stop = swing.q_hit + np.sign(swing.v_hit) * swing.v_hit**2 / (2 * model.acceleration_limit)
    assert np.all(q_stop >= model.lower - 1e-12) and np.all(q_stop <= model.upper + 1e-12)
    assert swing.speed == pytest.approx(model.racket_jacobian(model.ready_pose)[3] @ swing.v_hit)
    assert swing.speed > 0


def test_the_robot_can_swing_at_20_m_per_s_at_hitting_height(model):
    swing = fastest_swing(model, seed=0, maxiter=10)
    assert swing.speed >= 20.0  # paper, *Robot hardware*
    height = model.racket_pose(swing.q_hit).translation()[2]
    assert HIT_HEIGHT[0] <= height <= HIT_HEIGHT[1]
    assert swing.normal_angle <= np.radians(45.0)
    assert model.colliding_pairs(swing.q_hit) == [] and model.colliding_pairs(swing.q_start) == []
