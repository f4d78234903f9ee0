"""physics.segment: one control segment of B balls against the BallPlant reference.

The reference is the continuous-time BallPlant (Drake's error-controlled integrator, witness-located
contacts) in a small diagram where a test-only LeafSystem outputs an analytic racket pose and
spatial velocity at the context's time; the same analytic motion is the segments' RacketMotion.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from ace_drake.diagrams import make_simulator
from ace_drake.physics import contact
from ace_drake.physics.flight import POSITION, VELOCITY, make_state, rk4_trajectory
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import GAP_SCREEN_MARGIN, ContactKind, guard_gaps, simulate
from ace_drake.physics.segment import SPEED_MARGIN, _Segment, _speed_bound, propagate_segment, segment_times
from ace_drake.systems.ball_plant import BallPlant

PARAMS = BallPhysicsParams()
R = PARAMS.aero.ball_radius
STANDOFF = contact.blade_standoff(R, PARAMS.racket)  # blade centre to ball centre on the face, m
SEGMENT = 0.032  # s
FACING_PLUS_X = RotationMatrix.MakeYRotation(np.pi / 2).matrix()  # blade normal z_R along +x


@dataclasses.dataclass(frozen=True)
class Swing:
    """An analytic racket: p(t) = p0 + v0 t + a t^2 / 2, R(t) = exp([omega] t) R0 (a constant
    angular velocity omega in world), t the absolute time (s)."""

    p0: tuple = (0.0, 0.0, 0.0)
    v0: tuple = (0.0, 0.0, 0.0)
    a: tuple = (0.0, 0.0, 0.0)
    R0: np.ndarray = dataclasses.field(default_factory=lambda: FACING_PLUS_X)
    omega: tuple = (0.0, 0.0, 0.0)

    @staticmethod
    def hitting(p_ball, t_hit, v0=(0, 0, 0), a=(0, 0, 0), omega=(0, 0, 0), R_hit=FACING_PLUS_X, offset_R=(0, 0, 0)):
        """The swing whose blade, at t_hit, has orientation R_hit and its centre at ``offset_R``
        (in R, m) from the point STANDOFF behind p_ball along its normal (a face touch at t_hit)."""
        omega, R_hit = np.asarray(omega, float), np.asarray(R_hit, float)
        R0 = _rotation(omega[None], np.array([-t_hit]))[0] @ R_hit
        p_hit = np.asarray(p_ball, float) - STANDOFF * R_hit[:, 2] + R_hit @ np.asarray(offset_R, float)
        v0, a = np.asarray(v0, float), np.asarray(a, float)
        p0 = p_hit - v0 * t_hit - 0.5 * a * t_hit**2
        return Swing(tuple(p0), tuple(v0), tuple(a), R0, tuple(omega))

    def at(self, t: np.ndarray):
        """(p (k, 3), R (k, 3, 3), w (k, 3), v (k, 3)) at absolute times t (k,), row by row."""
        t = np.asarray(t, float)[:, None]
        p0, v0, a, omega = (np.broadcast_to(np.asarray(x, float), (t.shape[0], 3)) for x in (self.p0, self.v0, self.a, self.omega))
        rotation = _rotation(omega, t[:, 0])
        R = np.empty((t.shape[0], 3, 3))
        for i in range(3):
            for j in range(3):
                R[:, i, j] = rotation[:, i, 0] * self.R0[0, j] + rotation[:, i, 1] * self.R0[1, j] + rotation[:, i, 2] * self.R0[2, j]
        return p0 + v0 * t + 0.5 * a * t * t, R, omega.copy(), v0 + a * t


def _rotation(omega, t):
    """exp([omega] t) (k, 3, 3) by Rodrigues' formula, for omega (k, 3) rad/s and t (k,) s."""
    rate = np.sqrt(np.sum(omega * omega, axis=-1))
    axis = omega / np.where(rate > 0, rate, 1.0)[:, None]
    angle = rate * t
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    return np.stack(
        [
            np.stack([c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s], -1),
            np.stack([y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s], -1),
            np.stack([z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)], -1),
        ],
        -2,
    )


class SwingSource(LeafSystem):
    """Test-only: the Swing's racket_pose (RigidTransform) and racket_spatial_velocity
    (SpatialVelocity) at the context's time, for BallPlant's racket inputs."""

    def __init__(self, swing: Swing):
        super().__init__()
        self._swing = swing
        self.pose_port = self.DeclareAbstractOutputPort("racket_pose", lambda: AbstractValue.Make(RigidTransform()), self.CalcPose)
        self.velocity_port = self.DeclareAbstractOutputPort(
            "racket_spatial_velocity", lambda: AbstractValue.Make(SpatialVelocity()), self.CalcVelocity
        )

    def CalcPose(self, context, output):
        p, R, _, _ = self._swing.at(np.array([context.get_time()]))
        output.set_value(RigidTransform(RotationMatrix(R[0]), p[0]))

    def CalcVelocity(self, context, output):
        _, _, w, v = self._swing.at(np.array([context.get_time()]))
        output.set_value(SpatialVelocity(w[0], v[0]))


class SwingMotion:
    """The RacketMotion of one segment for environments with swings[i] and segment starts t0[i]."""

    def __init__(self, swings, t0, duration=SEGMENT):
        self.swings, self.t0 = list(swings), np.asarray(t0, float)
        self.times = segment_times(duration)
        samples = [self._state(np.full(self.times.size, i), self.times) for i in range(len(self.swings))]
        self.p_WR, self.R_WR, self.w_WR, self.v_WR = (np.stack([s[n] for s in samples]) for n in range(4))

    def _state(self, env, tau):
        out = [np.empty((env.size, 3)), np.empty((env.size, 3, 3)), np.empty((env.size, 3)), np.empty((env.size, 3))]
        for i in np.unique(env):
            rows = env == i
            for slot, value in zip(out, self.swings[i].at(self.t0[i] + tau[rows])):
                slot[rows] = value
        return tuple(out)

    def state_at(self, env, tau):
        return self._state(np.asarray(env), np.asarray(tau, float))


def run_reference(state, swing, duration, perturb=False, seed=0, residual=None):
    """BallPlant in the smallest diagram: (final state (9,), contact events)."""
    builder = DiagramBuilder()
    ball = builder.AddNamedSystem("ball", BallPlant(PARAMS, perturb=perturb, seed=seed, racket_residual=residual))
    if swing is not None:
        source = builder.AddNamedSystem("racket", SwingSource(swing))
        builder.Connect(source.pose_port, ball.racket_pose_port)
        builder.Connect(source.velocity_port, ball.racket_velocity_port)
    diagram = builder.Build()
    simulator = make_simulator(diagram)
    ball_context = ball.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    ball.SetBallState(ball_context, state)
    simulator.AdvanceTo(duration)
    return ball.ball_state_port.Eval(ball_context).copy(), list(ball.contact_events_port.Eval(ball_context))


def run_segments(states, swings, duration, seeds=None, active=None, residual=None):
    """Consecutive segments of B balls from t = 0: (final (B, 9), events per ball, samples)."""
    states = np.array(states, float, ndmin=2)
    n_balls = states.shape[0]
    events = [[] for _ in range(n_balls)]
    samples = []
    for s in range(int(round(duration / SEGMENT))):
        t0 = np.full(n_balls, s * SEGMENT)
        racket = None if swings is None else SwingMotion(swings, t0)
        flight = propagate_segment(
            states, t0, SEGMENT, PARAMS, racket, active=active, perturb_seeds=seeds,
            event_counts=np.array([len(e) for e in events]), residual=residual,
        )
        for i in range(n_balls):
            events[i] += flight.events[i]
        states = flight.final
        samples.append(flight.samples)
    return states, events, samples


def assert_matches_reference(state, swing, duration, perturb=False, seed=0):
    """Same contacts as BallPlant: kinds, times within 1e-6 s, positions within 1 mm, post-contact
    velocities and spins close; the final states within 1 mm. Returns the segments' events."""
    final_ref, events_ref = run_reference(state, swing, duration, perturb, seed)
    final, events, _ = run_segments(state, None if swing is None else [swing], duration, seeds=np.array([seed]) if perturb else None)
    events = events[0]
    assert [e.kind for e in events] == [e.kind for e in events_ref]
    for event, reference in zip(events, events_ref):
        assert abs(event.time - reference.time) < 1e-6
        np.testing.assert_allclose(event.state_pre[:3], reference.state_pre[:3], atol=1e-3)
        np.testing.assert_allclose(event.state_post[3:6], reference.state_post[3:6], atol=1e-3)
        np.testing.assert_allclose(event.state_post[6:], reference.state_post[6:], atol=0.05)
    np.testing.assert_allclose(final[0, :3], final_ref[:3], atol=1e-3)
    np.testing.assert_allclose(final[0, 3:], final_ref[3:], atol=2e-3)
    return events


def ball_at(state, t):
    """The ball (9,) at time t of its free flight (table, net, floor) from ``state``."""
    trajectory = simulate(state, PARAMS, t, dt=1e-4, record=False)
    return trajectory.final_state[0], trajectory.events[0]


SERVE = make_state([1.2, 0.05, 0.25], [-6.0, 0.1, 0.6], [0.0, 80.0, 20.0])  # bounces on the robot's side
DRIVE = make_state([-0.6, 0.0, 0.2], [-6.0, 0.0, 0.0], [0.0, -100.0, 0.0])  # straight at the blade


def swing_into(state, t_hit, **kwargs):
    p_ball = ball_at(state, t_hit)[0][:3]
    return Swing.hitting(p_ball, t_hit, **kwargs)


SHOTS = {  # name: (ball at t = 0, racket); over 17 segments (0.544 s)
    "still_face": (DRIVE, Swing(p0=(-1.2, 0.0, 0.2))),
    # stopped after 7 segments (0.224 s), before the racket, coming on at 3 m/s, reaches the net
    "constant_velocity": (DRIVE, Swing(p0=(-1.5, 0.0, 0.2), v0=(3.0, 0.0, 0.0))),
    "swing_after_bounce": (SERVE, swing_into(SERVE, 0.44, v0=(4.0, 0.5, 1.5), a=(20.0, 0.0, -5.0), omega=(2.0, 1.0, 12.0), offset_R=(0.02, -0.01, 0.004))),
    "edge": (DRIVE, Swing(p0=(-1.5, PARAMS.racket.blade_radius + 0.5 * R, 0.16), v0=(3.0, 0.0, 0.0), omega=(0.0, 0.0, 3.0))),
    "miss": (DRIVE, Swing(p0=(-1.2, PARAMS.racket.blade_radius + R + 0.005, 0.16), omega=(0.0, 0.0, 0.5))),
    "net": (make_state([1.0, 0.1, 0.1], [-7.0, 0.0, 0.4], [0.0, 50.0, 0.0]), Swing(p0=(-1.4, 0.0, 0.2))),
}


@pytest.mark.parametrize("name", SHOTS)
def test_contacts_match_ball_plant(name):
    state, swing = SHOTS[name]
    events = assert_matches_reference(state, swing, 0.224 if name == "constant_velocity" else 0.544)
    kinds = [e.kind for e in events]
    if name in ("still_face", "constant_velocity", "edge", "swing_after_bounce"):
        assert ContactKind.RACKET in kinds
    if name == "swing_after_bounce":
        assert kinds[:2] == [ContactKind.TABLE, ContactKind.RACKET]
    if name == "miss":
        assert ContactKind.RACKET not in kinds
    if name == "net":
        assert kinds[0] == ContactKind.NET


def test_edge_shot_touches_the_rim():
    state, swing = SHOTS["edge"]
    event = next(e for e in run_segments(state, [swing], 0.192)[1][0] if e.kind == ContactKind.RACKET)
    p, R_WR, _, _ = swing.at(np.array([event.time]))
    p_RB = contact.ball_in_racket_frame(event.state_pre[:3], p[0], R_WR[0])
    p_RC = contact.closest_blade_point(p_RB, PARAMS.racket)
    assert np.hypot(p_RC[0], p_RC[1]) == pytest.approx(PARAMS.racket.blade_radius)  # on the rim
    normal = (p_RB - p_RC) / np.linalg.norm(p_RB - p_RC)
    assert abs(normal[2]) < 0.95  # tilted off the blade's normal: not a face contact
    assert np.linalg.norm(p_RB - p_RC) == pytest.approx(R, abs=1e-9)


def test_perturbed_bounces_match_ball_plant_by_seed():
    state, swing = SHOTS["swing_after_bounce"]
    a = assert_matches_reference(state, swing, 0.544, perturb=True, seed=7)
    b = assert_matches_reference(state, swing, 0.544, perturb=True, seed=8)
    assert not np.allclose(a[0].state_post, b[0].state_post)


def test_a_fast_ball_does_not_tunnel_through_a_blade_swung_at_it():
    # 45 m/s at a blade coming at 5 m/s: 50 m/s relative, 5 cm per 1 ms step.
    state = make_state([-0.3, 0.0, 0.2], [-45.0, 0.0, 0.0])
    swing = Swing.hitting(ball_at(state, 0.0213)[0][:3], 0.0213, v0=(5.0, 0.0, 0.0))
    event = run_segments(state, [swing], 0.032)[1][0][0]
    assert event.kind == ContactKind.RACKET
    final_ref, events_ref = run_reference(state, swing, 0.032)
    assert abs(event.time - events_ref[0].time) < 1e-6


def test_a_fast_ball_grazing_the_rim_is_caught_whatever_its_phase_in_the_step():
    # 45 m/s at a blade coming at 5 m/s, the ball's centre in the blade's plane R_b + 0.9 r off
    # its axis: the stretch where it overlaps the rim is 3.1 cm long, the relative travel per 1 ms
    # step 5 cm, so at a third of these phases both step ends are clear (checked with sub-samples
    # off); the sub-sampled gap finds the contact, at BallPlant's time.
    for phase in np.linspace(0.0, 1e-3, 9):
        state = make_state([-0.3, 0.0, 0.2], [-45.0, 0.0, 0.0])
        p_ball = ball_at(state, 0.0213 + phase)[0][:3]
        swing = Swing.hitting(p_ball, 0.0213 + phase, v0=(5.0, 0.0, 0.0), offset_R=(0.0, -(PARAMS.racket.blade_radius + 0.9 * R), -STANDOFF))
        events = run_segments(state, [swing], 0.032)[1][0]
        assert [e.kind for e in events][:1] == [ContactKind.RACKET]
        if phase == 0.0:
            assert abs(events[0].time - run_reference(state, swing, 0.032)[1][0].time) < 1e-6


def test_a_residual_model_corrects_racket_contacts_as_in_ball_plant():
    def residual(features):
        return 0.02 * features[:, :6]

    state, swing = SHOTS["swing_after_bounce"]
    events = run_segments(state, [swing], 0.448, residual=residual)[1][0]
    _, events_ref = run_reference(state, swing, 0.448, residual=residual)
    plain = run_segments(state, [swing], 0.448)[1][0]
    assert [e.kind for e in events] == [e.kind for e in events_ref] == [ContactKind.TABLE, ContactKind.RACKET]
    np.testing.assert_allclose(events[1].state_post[3:6], events_ref[1].state_post[3:6], atol=1e-3)
    assert not np.allclose(events[1].state_post[3:6], plain[1].state_post[3:6], atol=1e-2)


def test_rows_are_independent_bit_for_bit():
    states = np.stack([SHOTS[name][0] for name in SHOTS])
    swings = [SHOTS[name][1] for name in SHOTS]
    seeds = np.arange(len(swings)) + 3
    final, events, samples = run_segments(states, swings, 0.544, seeds=seeds)
    for i in range(len(swings)):
        final_i, events_i, samples_i = run_segments(states[i : i + 1], swings[i : i + 1], 0.544, seeds=seeds[i : i + 1])
        np.testing.assert_array_equal(final[i], final_i[0])
        for batch, single in zip(samples, samples_i):
            np.testing.assert_array_equal(batch[i], single[0])
        assert [(e.kind, e.time) for e in events[i]] == [(e.kind, e.time) for e in events_i[0]]
        for e, f in zip(events[i], events_i[0]):
            np.testing.assert_array_equal(e.state_post, f.state_post)


def test_inactive_rows_pass_through_unchanged():
    states = np.stack([DRIVE, DRIVE, np.full(9, np.nan)])
    swings = [SHOTS["still_face"][1]] * 3
    active = np.array([True, False, False])
    flight = propagate_segment(states, np.zeros(3), SEGMENT, PARAMS, SwingMotion(swings, np.zeros(3)), active=active)
    assert flight.samples.shape == (3, 33, 9)
    np.testing.assert_array_equal(flight.samples[1], np.broadcast_to(DRIVE, (33, 9)))
    assert np.all(np.isnan(flight.final[2]))
    assert flight.events[1] == [] and flight.events[2] == []
    assert not np.array_equal(flight.final[0], DRIVE)


def test_without_contacts_it_is_the_propagator():
    state = make_state([1.0, 0.0, 0.3], [-4.0, 0.2, 1.0], [0.0, 30.0, 0.0])
    flight = propagate_segment(state[None], np.zeros(1), SEGMENT, PARAMS)
    reference = simulate(state, PARAMS, SEGMENT)
    # Equal steps but the last: simulate's is 0.032 s less the sum of 31 steps, here dt itself.
    np.testing.assert_array_equal(flight.samples[0, :-1], reference.states[:-1, 0])
    np.testing.assert_allclose(flight.samples[0, -1], reference.states[-1, 0], rtol=1e-14, atol=1e-15)
    assert flight.events == [[]]


def test_bad_shapes_raise():
    motion = SwingMotion([SHOTS["still_face"][1]], np.zeros(1))
    with pytest.raises(ValueError, match="states must be"):
        propagate_segment(np.zeros(9), np.zeros(1), SEGMENT, PARAMS)
    with pytest.raises(ValueError, match="start_times"):
        propagate_segment(DRIVE[None], np.zeros(2), SEGMENT, PARAMS)
    with pytest.raises(ValueError, match="active"):
        propagate_segment(DRIVE[None], np.zeros(1), SEGMENT, PARAMS, active=np.ones(1))
    with pytest.raises(ValueError, match="perturb_seeds"):
        propagate_segment(DRIVE[None], np.zeros(1), SEGMENT, PARAMS, perturb_seeds=np.zeros(1))
    with pytest.raises(ValueError, match="NaN"):
        propagate_segment(np.full((1, 9), np.nan), np.zeros(1), SEGMENT, PARAMS)
    with pytest.raises(ValueError, match="duration"):
        propagate_segment(DRIVE[None], np.zeros(1), -1.0, PARAMS)
    with pytest.raises(ValueError, match="racket.times"):
        propagate_segment(DRIVE[None], np.zeros(1), 0.016, PARAMS, motion)
    with pytest.raises(ValueError, match="racket.p_WR"):
        propagate_segment(np.stack([DRIVE, DRIVE]), np.zeros(2), SEGMENT, PARAMS, motion)
    bad = SwingMotion([SHOTS["still_face"][1]], np.zeros(1))
    bad.R_WR = bad.R_WR.copy()
    bad.R_WR[0, 5, 1, 1] = np.nan
    with pytest.raises(ValueError, match="racket.R_WR must be finite"):
        propagate_segment(DRIVE[None], np.zeros(1), SEGMENT, PARAMS, bad)


# ------------------------------------------------------------------------------ the compiled fast pass


def reference_speed_bound(velocity, change):
    """``segment._speed_bound`` in NumPy: the reference of the compiled ``_speed_bound_one``."""
    speed = _norm(velocity)
    return np.maximum(speed[..., :-1], speed[..., 1:]) + _norm(velocity[..., 1:, :] - velocity[..., :-1, :]) + change + SPEED_MARGIN


def _norm(a):
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2])


def reference_flags(run, rows):
    """The fast pass's flags in NumPy (the reference of the compiled ``_fly_and_flag`` and the
    exact gaps after it): (flags (len(rows), n), the number of steps the distance screen could not
    clear, the number of those the exact gaps cleared)."""
    x = run.samples[rows]
    m, n_points = x.shape[:2]
    positive = guard_gaps(x.reshape(-1, 9), run.kinds, run.params).reshape(m, n_points, -1) > 0.0
    flags = (positive[:, :-1] & ~positive[:, 1:]).any(axis=-1)
    screened = cleared = 0
    if run.racket is not None:
        speed = reference_speed_bound(x[..., VELOCITY], 0.0) + run.racket_speed[rows]
        distance = _norm(x[..., POSITION] - run.p_WR[rows])
        near = 0.5 * (distance[:, :-1] + distance[:, 1:] - speed * run.steps) - run.reach <= GAP_SCREEN_MARGIN
        i, k = np.nonzero(near)
        screened = i.size
        if i.size:
            env = rows[i]
            g0 = contact.racket_gap(x[i, k, POSITION], run.p_WR[env, k], run.R_WR[env, k], run.params.racket, run.radius)
            g1 = contact.racket_gap(x[i, k + 1, POSITION], run.p_WR[env, k + 1], run.R_WR[env, k + 1], run.params.racket, run.radius)
            near[i, k] = 0.5 * (g0 + g1 - run._gap_rate(speed[i, k], env, k) * run.steps[k]) <= GAP_SCREEN_MARGIN
            cleared = screened - near[i, k].sum()
        flags |= near
    return flags, screened, cleared


def test_speed_bounds_are_the_numpy_reference():
    rng = np.random.default_rng(2)
    velocity = rng.normal(0.0, 5.0, (4, 33, 3))
    change = rng.uniform(0.0, 3.0, 32)
    np.testing.assert_array_equal(_speed_bound(velocity, change), reference_speed_bound(velocity, change))
    np.testing.assert_array_equal(_speed_bound(velocity[:, :2], 0.0), reference_speed_bound(velocity[:, :2], 0.0))
    velocity[1, 4, 2] = np.nan  # np.maximum's NaN
    np.testing.assert_array_equal(_speed_bound(velocity, change), reference_speed_bound(velocity, change))


def test_the_compiled_fast_pass_is_the_numpy_reference():
    # Balls over and around the table and the net (guard crossings), with rackets swung through
    # them, beside them (the distance screen fails, the exact gaps clear) and far away; whole
    # rows, and rows flown again from a later sample.
    rng = np.random.default_rng(7)
    count = 60
    states = np.concatenate([rng.uniform([-1.6, -0.9, 0.0], [1.6, 0.9, 0.3], (count, 3)), rng.uniform([-8.0, -2.0, -3.0], [8.0, 2.0, 2.0], (count, 3)),
                             rng.uniform(-300.0, 300.0, (count, 3))], axis=1)
    times, steps = segment_times(SEGMENT), np.full(32, 1e-3)
    flown = rk4_trajectory(states, steps, PARAMS.aero)
    swings = []
    for i in range(count):
        t_hit = rng.uniform(0.0, SEGMENT)
        p_ball = flown[i, int(round(t_hit * 1e3)), :3]
        offset = [(0.0, 0.0, 0.0), (0.12, 0.0, 0.0), (0.0, 0.0, 0.5), (2.0, 0.0, 0.0)][i % 4]
        swings.append(Swing.hitting(p_ball, t_hit, v0=rng.normal(0.0, 3.0, 3), omega=rng.normal(0.0, 10.0, 3), offset_R=offset))
    for racket in (SwingMotion(swings, np.zeros(count)), None):
        run = _Segment(states, np.zeros(count), times, steps, PARAMS, racket, None, np.zeros(count, dtype=np.int64), None)
        rows = np.arange(count)
        flags = np.zeros((count, 32), dtype=bool)
        assert run._fast_pass(rows, np.zeros(count, dtype=np.int64), flags) == flags.any()
        np.testing.assert_array_equal(run.samples, flown)
        expected, screened, cleared = reference_flags(run, rows)
        np.testing.assert_array_equal(flags, expected)
        if racket is not None:
            assert flags.any(axis=1).sum() > count // 4 and screened > 20 and cleared > 5
        else:
            assert flags.any(axis=1).sum() >= 3  # guard crossings alone
        # Some rows again from a later sample, from another state there.
        redo, first = rows[::3], rng.integers(1, 32, rows[::3].size)
        run.samples[redo, first] = states[redo]
        run._fast_pass(redo, first, flags)
        for row, k in zip(redo, first):
            np.testing.assert_array_equal(run.samples[row, k:], rk4_trajectory(states[row : row + 1], steps[k:], PARAMS.aero)[0])
        np.testing.assert_array_equal(flags[redo], reference_flags(run, redo)[0])
