"""ekf_kernels: the compiled twins of the physics that the EKF's kernels use equal the physics."""

import numpy as np

from ace_drake.perception import ekf_kernels
from ace_drake.perception.ball_ekf import BallEkf
from ace_drake.physics import contact
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate

PHYSICS = BallPhysicsParams()


def test_contact_gaps_are_the_physics_gaps():
    config = BallEkf(physics=PHYSICS)._config
    points = np.random.default_rng(0).uniform([-2.0, -1.2, -0.9], [2.0, 1.2, 0.6], size=(2000, 3))
    points[:20, 0] = 0.0  # on the net's plane
    points[20:40, 2] = 0.02  # on the table
    radius = PHYSICS.aero.ball_radius
    expected = np.column_stack([
        contact.table_gap(points, PHYSICS.table, radius),
        contact.net_gap(points, PHYSICS.table, PHYSICS.net, radius),
        contact.floor_gap(points, PHYSICS.table, radius),
    ])
    actual = np.array([ekf_kernels.contact_gaps(*p, config) for p in points])
    np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(np.sign(actual), np.sign(expected))


def test_flight_without_contact_is_simulate_or_refuses():
    config = BallEkf(physics=PHYSICS)._config
    rng = np.random.default_rng(1)
    free = make_state([1.0, 0.2, 0.3], [-9.0, 0.5, 1.0], [40.0, -300.0, 20.0]) + rng.normal(0, 1e-3, size=(10, 9))
    batch = free.copy()
    assert ekf_kernels._flight_without_contact(batch, 0.013, 0.013 / 3, config)
    np.testing.assert_array_equal(batch, simulate(free, PHYSICS, 0.013, dt=0.013 / 3, record=False).final_state)
    bouncing = make_state([-0.8, 0.1, 0.05], [-5.0, 0.3, -3.0], [0.0, 200.0, 50.0]) + np.zeros((10, 1))
    batch = bouncing.copy()
    assert not ekf_kernels._flight_without_contact(batch, 0.03, 0.005, config)
    np.testing.assert_array_equal(batch, bouncing)
