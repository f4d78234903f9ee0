"""Ball physics: eq. (1), eqs (2)-(8), net and floor maps, against hand-worked numbers."""


import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ace_drake.config import ConfigError, from_dict
from ace_drake.physics import contact
from ace_drake.physics.flight import (
    flight_acceleration,
    magnus_coefficient,
    make_state,
    one_ball_flight_acceleration,
    rk4_step,
    rk4_step_numpy,
    rk4_trajectory,
)
from ace_drake.physics.params import AeroParams, BallPhysicsParams
from ace_drake.physics.propagate import (
    DEFAULT_KINDS,
    ContactKind,
    apply_impact,
    contact_gap,
    contact_gap_lower_bound,
    first_contact_time,
    locate_root,
    simulate,
    simulate_ball,
)

PARAMS = BallPhysicsParams()
AERO = PARAMS.aero
R = AERO.ball_radius
DENSITY_RATIO = AERO.air_density / AERO.ball_density  # 1.204 / 81.2
MIRROR_Y = np.diag([1.0, -1.0, 1.0])
# Every combination of drag and Magnus models (AeroParams.drag_model, magnus_model).
AERO_MODELS = [
    AeroParams(drag_model=drag, magnus_model=magnus) for drag in ("constant", "spin_ratio") for magnus in ("ratio", "refined")
]


def mirror_state(state):
    """Mirror across the XZ plane: positions and velocities flip y, spin (a pseudo-vector) flips x, z."""
    state = np.array(state, dtype=float)
    state[..., 1] *= -1
    state[..., 4] *= -1
    state[..., 6] *= -1
    state[..., 8] *= -1
    return state


# ---------------------------------------------------------------------------------- eq. (1)


def test_ball_mass_from_density():
    assert AERO.ball_mass == pytest.approx(81.2 * 4 / 3 * np.pi * 0.02**3)
    assert AERO.ball_mass == pytest.approx(2.721e-3, rel=1e-3)


def test_flight_acceleration_hand_worked_drag_only():
    # v = (10, 0, 0), no spin: drag = 3/(8 r) c_d (rho_a/rho_b) |v| v = 18.75 * 0.55 * 0.014828 * 100.
    a = flight_acceleration(np.array([10.0, 0, 0]), np.zeros(3), AERO)
    drag = 3 / (8 * 0.02) * 0.55 * (1.204 / 81.2) * 10 * 10
    assert a[0] == pytest.approx(-drag, rel=1e-12)
    assert a[0] == pytest.approx(-15.2907, rel=1e-4)
    assert a[1] == 0.0
    assert a[2] == pytest.approx(-(1 - 1.204 / 81.2) * 9.81, rel=1e-12)


def test_flight_acceleration_hand_worked_magnus():
    # Topspin for a ball moving +x is w_y > 0; the Magnus force then points down (-z).
    v = np.array([10.0, 0, 0])
    w = np.array([0, 200.0, 0])
    c_m = 0.1 * 10 / (0.02 * 200) - 0.001  # 0.249
    a = flight_acceleration(v, w, AERO)
    a_no_spin = flight_acceleration(v, np.zeros(3), AERO)
    magnus_z = -c_m * DENSITY_RATIO * (10 * 200)  # -(c_M rho ratio) (v x w)_z, (v x w) = (0, 0, 2000)
    assert a[2] - a_no_spin[2] == pytest.approx(magnus_z, rel=1e-12)
    assert magnus_z == pytest.approx(-7.3841, rel=1e-4)
    np.testing.assert_allclose(a[:2], a_no_spin[:2], rtol=0, atol=1e-12)


def test_magnus_coefficient_cap_and_zero_spin_limit():
    assert magnus_coefficient(10.0, 200.0, AERO) == pytest.approx(0.249)
    assert magnus_coefficient(10.0, 1.0, AERO) == 1.0  # capped
    assert magnus_coefficient(10.0, 0.0, AERO) == 1.0  # the defined limit
    # The Magnus acceleration vanishes linearly as |w| -> 0.
    v = np.array([8.0, 1.0, 2.0])
    base = flight_acceleration(v, np.zeros(3), AERO)
    for scale in [1e-2, 1e-4, 1e-6]:
        w = scale * np.array([3.0, -40.0, 5.0])
        delta = np.linalg.norm(flight_acceleration(v, w, AERO) - base)
        assert delta == pytest.approx(DENSITY_RATIO * np.linalg.norm(np.cross(v, w)), rel=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-40, 40), min_size=3, max_size=3),
    st.one_of(st.just([0.0, 0.0, 0.0]), st.lists(st.floats(-1000, 1000), min_size=3, max_size=3)),
)
def test_one_ball_acceleration_is_the_batched_one_bit_for_bit(v, w):
    for aero in AERO_MODELS:
        one = one_ball_flight_acceleration(tuple(v), tuple(w), aero)
        np.testing.assert_array_equal(one, flight_acceleration(np.array(v), np.array(w), aero))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.lists(st.floats(-40, 40), min_size=3, max_size=3),
    st.one_of(st.just([0.0, 0.0, 0.0]), st.lists(st.floats(-1000, 1000), min_size=3, max_size=3)),
    st.floats(-0.05, 0.05),
)
def test_compiled_rk4_step_is_the_numpy_step_bit_for_bit(p, v, w, dt):
    state = make_state(p, v, w)
    for aero in AERO_MODELS:
        np.testing.assert_array_equal(rk4_step(state, dt, aero), rk4_step_numpy(state, dt, aero))


def test_compiled_rk4_step_keeps_shapes_and_per_ball_steps():
    rng = np.random.default_rng(3)
    states = np.concatenate([rng.normal(0, 1, (4, 5, 3)), rng.normal(0, 8, (4, 5, 3)), rng.normal(0, 300, (4, 5, 3))], axis=-1)
    steps = rng.uniform(-0.02, 0.02, (4, 5))
    for aero in AERO_MODELS:
        np.testing.assert_array_equal(rk4_step(states, steps, aero), rk4_step_numpy(states, steps, aero))
    np.testing.assert_array_equal(rk4_step(states[:, 0], steps[:1, 0], AERO), rk4_step_numpy(states[:, 0], steps[:1, 0], AERO))
    assert rk4_step(states[0, 0], 1e-3, AERO).shape == (9,)
    with pytest.raises(ValueError, match=r"\(\.\.\., 9\)"):
        rk4_step(np.zeros(8), 1e-3, AERO)


@pytest.mark.parametrize("aero", AERO_MODELS)
def test_rk4_trajectory_is_repeated_rk4_steps_bit_for_bit(aero):
    rng = np.random.default_rng(4)
    states = np.concatenate([rng.normal(0, 1, (6, 3)), rng.normal(0, 8, (6, 3)), rng.normal(0, 300, (6, 3))], axis=-1)
    steps = np.r_[np.full(5, 1e-3), 3e-4]
    trajectory = rk4_trajectory(states, steps, aero)
    assert trajectory.shape == (6, 7, 9)
    x = states
    np.testing.assert_array_equal(trajectory[:, 0], states)
    for k, h in enumerate(steps):
        x = rk4_step(x, h, aero)
        np.testing.assert_array_equal(trajectory[:, k + 1], x)
    with pytest.raises(ValueError, match="rk4_trajectory"):
        rk4_trajectory(states[0], steps, AERO)


@settings(max_examples=300, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.5, 1.5), st.floats(-1.0, 1.0))
def test_gap_lower_bounds_are_below_the_gaps(x, y, z):
    state = make_state([x, y, z], [0.0, 0.0, 0.0])
    for kind in (ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR, ContactKind.TABLE_PLANE):
        bound = contact_gap_lower_bound(kind, (x, y, z), PARAMS)
        assert bound <= float(contact_gap(kind, state, PARAMS)) + 1e-15
    assert contact_gap_lower_bound(ContactKind.FLOOR, (x, y, z), PARAMS) == float(contact_gap(ContactKind.FLOOR, state, PARAMS))


def test_rk4_converges_at_fourth_order():
    start = make_state([0, 0, 0.3], [10.0, 2.0, 3.0], [50.0, -300.0, 100.0])

    def integrate(dt):
        state = start.copy()
        for _ in range(int(round(0.4 / dt))):
            state = rk4_step(state, dt, AERO)
        return state

    fine = integrate(1e-4)
    error_coarse = np.linalg.norm(integrate(8e-3) - fine)
    error_half = np.linalg.norm(integrate(4e-3) - fine)
    assert 12.0 < error_coarse / error_half < 20.0  # 2^4 = 16


# ---------------------------------------------------------------------------------- eqs (2)-(6)


def test_table_restitution_is_lower_for_faster_impacts():
    assert contact.table_restitution(np.array(-2.0), PARAMS.table) == pytest.approx(0.94)
    assert contact.table_restitution(np.array(-5.0), PARAMS.table) == pytest.approx(0.88)


def test_table_impact_sliding_hand_worked():
    # v- = (4, 1, -3), w- = (10, -50, 5): v_T = (4 + 1, 1 + 0.2) = (5, 1.2), |v_T| = 5.1420
    v = np.array([4.0, 1.0, -3.0])
    w = np.array([10.0, -50.0, 5.0])
    eps = 0.98 - 0.02 * 3
    alpha = 0.25 * (1 + eps) * 3 / np.hypot(5.0, 1.2)
    assert alpha < 0.4  # sliding: v_s = 1 - 2.5 alpha > 0
    v_post, w_post = contact.table_impact(v, w, PARAMS.table, R)
    expected_v = [(1 - alpha) * 4 + alpha * R * -50, (1 - alpha) * 1 - alpha * R * 10, eps * 3]
    expected_w = [
        -1.5 * alpha / R * 1 + (1 - 1.5 * alpha) * 10,
        1.5 * alpha / R * 4 + (1 - 1.5 * alpha) * -50,
        5.0,
    ]
    np.testing.assert_allclose(v_post, expected_v, rtol=1e-12)
    np.testing.assert_allclose(w_post, expected_w, rtol=1e-12)
    np.testing.assert_allclose(v_post, [2.59976, 0.66394, 2.76], rtol=1e-5)


def test_table_impact_rolling_leaves_no_slip():
    # A slow tangential slip against a fast impact rolls: alpha = 2/5, contact point velocity -> 0.
    v = np.array([0.3, -0.2, -4.0])
    w = np.array([5.0, 10.0, 0.0])
    alpha, sliding = contact.table_alpha(v, w, PARAMS.table, R)
    assert not sliding and alpha == pytest.approx(0.4)
    v_post, w_post = contact.table_impact(v, w, PARAMS.table, R)
    slip_after = [v_post[0] - R * w_post[1], v_post[1] + R * w_post[0]]
    np.testing.assert_allclose(slip_after, [0.0, 0.0], atol=1e-12)


def test_table_alpha_switch_is_continuous():
    # At the switch v_s = 0 the sliding alpha equals the rolling one.
    v_z = -3.0
    eps = 0.98 - 0.02 * 3
    slip_at_switch = 0.25 * (1 + eps) * 3 / 0.4
    for slip in [slip_at_switch * (1 - 1e-9), slip_at_switch * (1 + 1e-9)]:
        alpha, _ = contact.table_alpha(np.array([slip, 0, v_z]), np.zeros(3), PARAMS.table, R)
        assert alpha == pytest.approx(0.4, rel=1e-8)


def test_ittf_drop_test_bounces_to_about_23_cm():
    drop_height = 0.305
    trajectory = simulate(make_state([0.3, 0.2, drop_height + R], [0, 0, 0]), PARAMS, 1.0, dt=5e-4)
    first = trajectory.events[0][0]
    assert first.kind == ContactKind.TABLE
    after = trajectory.states[trajectory.times > first.time + 1e-9, 0, 2]
    apex = after[: int(0.4 / 5e-4)].max() - R
    assert 0.22 < apex < 0.25, apex  # ITTF: 230 mm from 305 mm (23 to 25 cm accepted)


def test_drop_impact_time_matches_analytic_solution_with_drag():
    # Vertical fall with quadratic drag: z(t) = z0 - (v_t^2 / g) ln cosh(g t / v_t).
    g = (1 - DENSITY_RATIO) * AERO.gravity
    k_drag = 3 / (8 * R) * AERO.drag_coefficient * DENSITY_RATIO
    v_terminal = np.sqrt(g / k_drag)
    for height in [0.1, 0.305, 1.0]:
        t_impact = v_terminal / g * np.arccosh(np.exp(height * k_drag))
        trajectory = simulate(make_state([0.5, 0.3, height + R], [0, 0, 0]), PARAMS, 2.0)
        assert abs(trajectory.events[0][0].time - t_impact) < 1e-6


def test_terminal_velocity():
    g = (1 - DENSITY_RATIO) * AERO.gravity
    k_drag = 3 / (8 * R) * AERO.drag_coefficient * DENSITY_RATIO
    a = flight_acceleration(np.array([0, 0, -np.sqrt(g / k_drag)]), np.zeros(3), AERO)
    np.testing.assert_allclose(a, 0.0, atol=1e-12)
    assert np.sqrt(g / k_drag) == pytest.approx(7.95, abs=0.01)  # the model's terminal speed, m/s


# ---------------------------------------------------------------------------------- eqs (7)-(8)


def test_racket_impact_at_rest_with_identity_frame_matches_matrices():
    v = np.array([1.0, -2.0, -6.0])
    w = np.array([30.0, 80.0, -20.0])
    racket = PARAMS.racket
    v_post, w_post = contact.racket_impact(v, w, np.zeros(3), np.eye(3), racket, R)
    k = racket.tangential_k
    eps = racket.restitution_gamma1 * np.exp(racket.restitution_gamma2 * 6.0)
    C_vv = np.diag([1 - k, 1 - k, -eps])
    C_vw = np.array([[0, k * R, 0], [-k * R, 0, 0], [0, 0, 0]])
    C_wv = np.array([[0, -1.5 * k / R, 0], [1.5 * k / R, 0, 0], [0, 0, 0]])
    C_ww = np.diag([1 - 1.5 * k, 1 - 1.5 * k, 1])
    np.testing.assert_allclose(v_post, C_vv @ v + C_vw @ w, rtol=1e-12)
    np.testing.assert_allclose(w_post, C_wv @ v + C_ww @ w, rtol=1e-12)


def test_racket_restitution_defaults_match_notes():
    assert contact.racket_restitution(np.array(1.0), PARAMS.racket) == pytest.approx(0.88, abs=0.002)
    assert contact.racket_restitution(np.array(15.0), PARAMS.racket) == pytest.approx(0.75, abs=0.002)


def test_racket_impact_is_frame_invariant_and_galilean():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    R_WC = Rotation.random(random_state=4).as_matrix()
    v = rng.normal(0, 5, 3)
    w = rng.normal(0, 200, 3)
    v_racket = rng.normal(0, 3, 3)
    v_post, w_post = contact.racket_impact(v, w, v_racket, R_WC, PARAMS.racket, R)
    # Same contact computed in C by hand.
    v_post_C, w_post_C = contact.racket_impact(R_WC.T @ (v - v_racket), R_WC.T @ w, np.zeros(3), np.eye(3), PARAMS.racket, R)
    np.testing.assert_allclose(v_post, R_WC @ v_post_C + v_racket, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(w_post, R_WC @ w_post_C, rtol=1e-10, atol=1e-10)


def test_racket_impact_batched_equals_loop():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    n = 7
    R_WC = Rotation.random(n, random_state=6).as_matrix()
    v, w, vr = rng.normal(0, 5, (n, 3)), rng.normal(0, 200, (n, 3)), rng.normal(0, 3, (n, 3))
    v_batch, w_batch = contact.racket_impact(v, w, vr, R_WC, PARAMS.racket, R)
    for i in range(n):
        v_i, w_i = contact.racket_impact(v[i], w[i], vr[i], R_WC[i], PARAMS.racket, R)
        np.testing.assert_allclose(v_batch[i], v_i, rtol=1e-12)
        np.testing.assert_allclose(w_batch[i], w_i, rtol=1e-12)


# ---------------------------------------------------------------------------------- net and floor


def test_net_face_hit_stops_the_ball_on_its_side():
    start = make_state([-0.5, 0.0, 0.05], [5.0, 0.0, 0.0])
    trajectory = simulate(start, PARAMS, 0.3, kinds=(ContactKind.NET,), stop_on=())
    (event,) = trajectory.events[0][:1]
    assert event.kind == ContactKind.NET
    assert event.state_pre[0] == pytest.approx(-R, abs=1e-6)
    assert event.state_post[3] == pytest.approx(-0.05 * event.state_pre[3], rel=1e-6)
    assert trajectory.final_state[0, 0] < 0


def test_net_cord_ball_goes_over():
    # The ball's centre passes 19 mm above the cord: the contact normal is mostly vertical.
    height = PARAMS.net.height + 0.019
    start = make_state([-0.05, 0.0, height], [3.0, 0.0, 0.0])
    trajectory = simulate(start, PARAMS, 0.6, kinds=(ContactKind.NET, ContactKind.TABLE))
    kinds = [e.kind for e in trajectory.events[0]]
    assert kinds[0] == ContactKind.NET
    net = trajectory.events[0][0]
    assert net.state_post[3] > 0.5 * net.state_pre[3]  # keeps most of its forward speed
    assert ContactKind.TABLE in kinds
    table = trajectory.events[0][kinds.index(ContactKind.TABLE)]
    assert table.state_pre[0] > 0  # lands on the far side


def test_ball_beside_the_net_passes():
    start = make_state([-0.3, 0.5 * PARAMS.table.width + PARAMS.net.overhang + 0.05, 0.05], [6.0, 0.0, 0.0])
    trajectory = simulate(start, PARAMS, 0.2, kinds=(ContactKind.NET,))
    assert trajectory.events[0] == []


def test_floor_impact():
    v_post, w_post = contact.floor_impact(np.array([1.0, 2.0, -4.0]), np.array([0, 10.0, 0]), PARAMS.floor)
    np.testing.assert_allclose(v_post, [0.8, 1.6, 2.0])
    np.testing.assert_allclose(w_post, [0, 8.0, 0])


def test_ball_off_the_table_falls_to_the_floor():
    start = make_state([1.5, 0.0, 0.2], [2.0, 0.0, 0.0])
    trajectory = simulate(start, PARAMS, 1.0)
    assert trajectory.events[0][0].kind == ContactKind.FLOOR
    assert trajectory.events[0][0].state_pre[2] == pytest.approx(-0.76 + R, abs=1e-6)


# ---------------------------------------------------------------------------------- symmetry, batches


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-1.3, -0.5), st.floats(-0.5, 0.5), st.floats(0.1, 0.4),
    st.floats(4, 15), st.floats(-2, 2), st.floats(-1, 3),
    st.floats(-400, 400), st.floats(-400, 400), st.floats(-400, 400),
)
def test_mirror_symmetry_in_y_is_exact(px, py, pz, vx, vy, vz, wx, wy, wz):
    start = make_state([px, py, pz], [vx, vy, vz], [wx, wy, wz])
    trajectory = simulate(np.stack([start, mirror_state(start)]), PARAMS, 0.8, dt=2e-3)
    np.testing.assert_allclose(trajectory.states[:, 1], mirror_state(trajectory.states[:, 0]), rtol=0, atol=1e-12)
    assert [e.kind for e in trajectory.events[0]] == [e.kind for e in trajectory.events[1]]


def test_batched_contact_maps_apply_the_one_ball_kernels_row_by_row():
    # The table, net and floor gaps and maps are defined once, per ball (contact.*_one); the batched
    # functions give each row exactly the kernel's result, whatever the batch's shape.
    rng = np.random.default_rng(3)
    p = rng.uniform([-1.6, -0.9, -0.1], [1.6, 0.9, 0.5], (24, 3))
    v = rng.uniform(-10.0, 10.0, (24, 3))
    w = rng.uniform(-500.0, 500.0, (24, 3))
    table, net, floor = PARAMS.table, PARAMS.net, PARAMS.floor
    for shape in [(24, 3), (4, 6, 3)]:
        ps, vs, ws = (a.reshape(shape) for a in (p, v, w))
        table_post = np.concatenate(contact.table_impact(vs, ws, table, R), -1).reshape(24, 6)
        net_post = contact.net_impact(ps, vs, ws, table, net)[0].reshape(24, 3)
        floor_post = np.concatenate(contact.floor_impact(vs, ws, floor), -1).reshape(24, 6)
        gaps = np.stack([contact.table_gap(ps, table, R), contact.net_gap(ps, table, net, R), contact.floor_gap(ps, table, R)],
                        -1).reshape(24, 3)
        for i in range(24):
            (x, y, z), (vx, vy, vz), (wx, wy, wz) = p[i], v[i], w[i]
            tv, tw = contact.table_impact_one(vx, vy, vz, wx, wy, wz, table.friction, table.restitution_base,
                                              table.restitution_slope, table.rolling_alpha, R)
            assert tuple(table_post[i]) == tv + tw
            assert tuple(net_post[i]) == contact.net_impact_one(x, y, z, vx, vy, vz, table.width, net.overhang, net.height,
                                                                net.restitution, net.tangential_retention)
            fv, fw = contact.floor_impact_one(vx, vy, vz, wx, wy, wz, floor.restitution, floor.tangential_retention)
            assert tuple(floor_post[i]) == fv + fw
            assert tuple(gaps[i]) == (
                contact.table_gap_one(x, y, z, table.length, table.width, R),
                contact.net_gap_one(x, y, z, table.width, net.overhang, net.height, R),
                contact.floor_gap_one(z, table.surface_height, R),
            )


def test_batched_simulation_equals_one_by_one():
    rng = np.random.default_rng(0)
    n = 6
    starts = make_state(
        np.c_[rng.uniform(-1.3, -0.6, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.1, 0.4, n)],
        np.c_[rng.uniform(5, 12, n), rng.uniform(-1, 1, n), rng.uniform(0, 3, n)],
        rng.normal(0, 200, (n, 3)),
    )
    batch = simulate(starts, PARAMS, 1.0, record=False)
    for i in range(n):
        single = simulate(starts[i], PARAMS, 1.0, record=False)
        np.testing.assert_allclose(batch.final_state[i], single.final_state[0], rtol=1e-12, atol=1e-12)
        assert [e.time for e in batch.events[i]] == pytest.approx([e.time for e in single.events[0]], abs=1e-12)


def test_perturbations_are_seeded_and_only_with_rng():
    start = make_state([0.5, 0.1, 0.3], [-3.0, 0.2, 0.0], [0, 100.0, 0])
    plain_a = simulate(start, PARAMS, 0.5).final_state
    plain_b = simulate(start, PARAMS, 0.5).final_state
    np.testing.assert_array_equal(plain_a, plain_b)
    seeded_a = simulate(start, PARAMS, 0.5, rng=np.random.default_rng(7)).final_state
    seeded_b = simulate(start, PARAMS, 0.5, rng=np.random.default_rng(7)).final_state
    np.testing.assert_array_equal(seeded_a, seeded_b)
    assert not np.allclose(seeded_a, plain_a)


def test_stop_on_returns_state_at_contact():
    start = make_state([-1.0, 0.0, 0.3], [5.0, 0.0, 0.0])
    trajectory = simulate(start, PARAMS, 1.0, kinds=(ContactKind.NET, ContactKind.TABLE), stop_on=(ContactKind.TABLE,))
    stop = trajectory.stop_events[0]
    assert stop.kind == ContactKind.TABLE
    np.testing.assert_allclose(trajectory.final_state[0], stop.state_pre)
    np.testing.assert_allclose(stop.state_post, apply_impact(ContactKind.TABLE, stop.state_pre, PARAMS))


# ---------------------------------------------------------------------------------- config


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="aero.drag_coefficient"):
        from_dict(BallPhysicsParams, {"aero": {"drag_coefficient": "high"}})
    with pytest.raises(ConfigError, match="unknown field"):
        from_dict(BallPhysicsParams, {"aero": {"drag_coeff": 0.5}})
    with pytest.raises(ConfigError, match="ball_radius"):
        from_dict(BallPhysicsParams, {"aero": {"ball_radius": -1.0}})
    fitted = from_dict(BallPhysicsParams, {"table": {"friction": 0.2}})
    assert fitted.table.friction == 0.2 and fitted.aero == AeroParams()


def test_simulate_rejects_bad_input():
    with pytest.raises(ValueError, match="initial_state"):
        simulate(np.zeros(8), PARAMS, 1.0)
    with pytest.raises(ValueError, match="NaN"):
        simulate(np.full(9, np.nan), PARAMS, 1.0)
    with pytest.raises(ValueError, match="dt"):
        simulate(np.zeros(9), PARAMS, 1.0, dt=0.0)
    # the compiled one-ball simulation too: a wrong shape names the shape, a NaN the numbers
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        simulate_ball(np.zeros(8), PARAMS, 1.0)
    with pytest.raises(ValueError, match="got \\[nan"):
        simulate_ball(np.full(9, np.nan), PARAMS, 1.0)
    with pytest.raises(ValueError, match="dt"):
        simulate_ball(np.zeros(9), PARAMS, 1.0, dt=0.0)


def test_compiled_one_ball_simulation_equals_simulate_bit_for_bit():
    # simulate_ball's compiled loop against simulate's (both apply contact's one-ball kernels).
    # Random balls over and around the table with every static kind, stopping or not, and
    # steps from 1 (the command period) to 50 ms: the same steps, contacts (kinds, times, states)
    # and stops.
    rng = np.random.default_rng(11)
    cases = [((ContactKind.TABLE_PLANE, ContactKind.NET, ContactKind.FLOOR), (ContactKind.TABLE_PLANE, ContactKind.FLOOR)),
             ((ContactKind.NET, ContactKind.FLOOR), (ContactKind.FLOOR,)),
             ((ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR), ()),
             ((ContactKind.TABLE,), (ContactKind.TABLE,)),
             (DEFAULT_KINDS, (ContactKind.TABLE, ContactKind.FLOOR))]  # a return's flight (training.vector_env)
    contacts = 0
    for index in range(400):
        kinds, stop_on = cases[index % len(cases)]
        state = np.concatenate([rng.uniform([-1.6, -0.9, -0.05], [1.6, 0.9, 0.6]), rng.uniform([-12.0, -3.0, -4.0], [12.0, 3.0, 4.0]),
                                rng.uniform(-500.0, 500.0, 3)])
        duration, dt = rng.uniform(0.01, 0.6), (0.032, 0.01, 0.001, 0.05)[index % 4]
        expected = simulate(state, PARAMS, duration, dt=dt, kinds=kinds, stop_on=stop_on)
        actual = simulate_ball(state, PARAMS, duration, dt=dt, kinds=kinds, stop_on=stop_on)
        np.testing.assert_array_equal(actual.times, expected.times)
        np.testing.assert_array_equal(actual.states, expected.states)
        np.testing.assert_array_equal(actual.final_state, expected.final_state)
        assert len(actual.events[0]) == len(expected.events[0])
        for mine, theirs in zip(actual.events[0], expected.events[0]):
            assert mine.kind == theirs.kind and mine.time == theirs.time
            np.testing.assert_array_equal(mine.state_pre, theirs.state_pre)
            np.testing.assert_array_equal(mine.state_post, theirs.state_post)
        stopped = expected.stop_events[0]
        assert (actual.stop_events[0] is None) == (stopped is None)
        if stopped is not None:
            assert actual.stop_events[0].time == stopped.time
        contacts += len(expected.events[0])
    assert contacts > 100


def test_ball_entering_the_table_footprint_below_the_surface_is_no_table_contact():
    # 1 cm below the playing surface, beside the table, moving under it: no top contact.
    start = make_state([0.5, 0.5 * PARAMS.table.width + 0.1, -0.01], [0.0, -3.0, 0.0])
    trajectory = simulate(start, PARAMS, 0.2, kinds=(ContactKind.TABLE,))
    assert trajectory.events[0] == []
    # The same ball 5 cm above the surface falls onto the table top.
    above = make_state([0.5, 0.5 * PARAMS.table.width + 0.1, 0.05], [0.0, -3.0, 0.0])
    assert simulate(above, PARAMS, 0.3, kinds=(ContactKind.TABLE,)).events[0][0].kind == ContactKind.TABLE


def reference_first_contact_time(x0, h, crossing, kinds, params):
    """``first_contact_time`` on NumPy's ``locate_root``: the reference of the compiled one."""
    tau = np.full(x0.shape[0], np.inf)
    kind_index = np.zeros(x0.shape[0], dtype=int)
    for k, kind in enumerate(kinds):
        rows = np.flatnonzero(crossing[:, k])
        if rows.size == 0:
            continue
        tau_k = locate_root(x0[rows], h[rows], lambda s, _tau, kind=kind: contact_gap(kind, s, params), params)
        better = tau_k < tau[rows]
        tau[rows[better]] = tau_k[better]
        kind_index[rows[better]] = k
    return tau, kind_index


@pytest.mark.parametrize("kinds", [(ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR), (ContactKind.TABLE_PLANE, ContactKind.NET, ContactKind.FLOOR)])
def test_compiled_first_contact_time_is_locate_root_on_each_guard(kinds):
    # Steps of 1 to 40 ms that cross one guard or several (the earliest wins, ties to the earlier kind).
    rng = np.random.default_rng(12)
    state = np.concatenate([rng.uniform([-1.6, -0.9, -0.8], [1.6, 0.9, 0.4], (4000, 3)), rng.uniform([-12.0, -3.0, -6.0], [12.0, 3.0, 3.0], (4000, 3)),
                            rng.uniform(-500.0, 500.0, (4000, 3))], axis=1)
    h = rng.choice([0.001, 0.008, 0.032, 0.04], 4000)
    gaps0 = np.stack([contact_gap(kind, state, PARAMS) for kind in kinds], axis=-1)
    gaps1 = np.stack([contact_gap(kind, rk4_step(state, h, PARAMS.aero), PARAMS) for kind in kinds], axis=-1)
    crossing = (gaps0 > 0.0) & (gaps1 <= 0.0)
    rows = np.flatnonzero(crossing.any(axis=-1))
    assert rows.size > 100 and (crossing[rows].sum(axis=-1) > 1).any()
    tau, kind_index = first_contact_time(state[rows], h[rows], crossing[rows], kinds, PARAMS)
    expected_tau, expected_index = reference_first_contact_time(state[rows], h[rows], crossing[rows], kinds, PARAMS)
    np.testing.assert_array_equal(tau, expected_tau)
    np.testing.assert_array_equal(kind_index, expected_index)
