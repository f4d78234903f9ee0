"""Ball flight: drag, Magnus and gravity (paper eq. (1)), and the RK4 step.

A ball state is a (..., 9) array [p_W (m), v_W (m/s), w_W (rad/s)] in the world frame of
DESIGN.md; spin is constant in flight (paper, Methods *Ball aerodynamics*). Every function is
batched over the leading dimensions, except ``one_ball_flight_acceleration``, the scalar twin of
``flight_acceleration`` for per-ball callers. ``rk4_step`` is compiled (numba) and equal bit for bit
to the same step written with ``state_derivative`` in NumPy (``rk4_step_numpy``, its reference).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ace_drake.physics.params import AeroParams

POSITION = slice(0, 3)
VELOCITY = slice(3, 6)
SPIN = slice(6, 9)


def magnus_coefficient(speed: np.ndarray, spin_rate: np.ndarray, aero: AeroParams) -> np.ndarray:
    """c_M = min(0.1 |v| / (r |w|) - 0.001, 1) (paper, below eq. (1); cap from the authors' code).

    The printed c_M is singular as |w| -> 0. With the cap, c_M = cap for all small spin rates, so the
    Magnus acceleration c_M (rho_air / rho_ball)(v x w) goes to zero linearly in |w|: the limit at
    |w| = 0 is defined as c_M = cap and the trajectory is continuous in w. Args: speed |v| (m/s),
    spin_rate |w| (rad/s), any matching shapes. Returns c_M (dimensionless).
    """
    speed = np.asarray(speed, dtype=float)
    spin_rate = np.asarray(spin_rate, dtype=float)
    spinning = spin_rate > 0.0
    safe_rate = np.where(spinning, spin_rate, 1.0)
    c_m = aero.magnus_slope * speed / (aero.ball_radius * safe_rate) + aero.magnus_offset
    return np.where(spinning, np.minimum(c_m, aero.magnus_cap), aero.magnus_cap)


def flight_acceleration(v_W: np.ndarray, w_W: np.ndarray, aero: AeroParams) -> np.ndarray:
    """dv/dt of a ball in flight, m/s^2: paper eq. (1) divided by the ball's mass.

    a = -(3 / (8 r)) c_d (rho_a / rho_b) |v| v - c_M (rho_a / rho_b) (v x w) + (1 - rho_a / rho_b) g,
    the buoyancy factor on g as in the authors' code (``aero.buoyancy``). Args: v_W, w_W (..., 3).
    """
    v_W = np.asarray(v_W, dtype=float)
    w_W = np.asarray(w_W, dtype=float)
    density_ratio = aero.air_density / aero.ball_density
    vx, vy, vz = v_W[..., 0], v_W[..., 1], v_W[..., 2]
    wx, wy, wz = w_W[..., 0], w_W[..., 1], w_W[..., 2]
    speed = np.sqrt(vx * vx + vy * vy + vz * vz)  # explicit: np.linalg.norm/np.cross dominate small batches
    spin_rate = np.sqrt(wx * wx + wy * wy + wz * wz)
    drag_gain = -(3.0 / (8.0 * aero.ball_radius)) * aero.drag_coefficient * density_ratio * speed
    magnus_gain = -magnus_coefficient(speed, spin_rate, aero) * density_ratio
    gravity_scale = (1.0 - density_ratio) if aero.buoyancy else 1.0
    a_x = drag_gain * vx + magnus_gain * (vy * wz - vz * wy)
    a_y = drag_gain * vy + magnus_gain * (vz * wx - vx * wz)
    a_z = drag_gain * vz + magnus_gain * (vx * wy - vy * wx) - gravity_scale * aero.gravity
    acceleration = np.empty(np.shape(a_x) + (3,))  # filled per axis: np.stack costs more
    acceleration[..., 0], acceleration[..., 1], acceleration[..., 2] = a_x, a_y, a_z
    return acceleration


def one_ball_flight_acceleration(v_W: tuple[float, float, float], w_W: tuple[float, float, float], aero: AeroParams) -> tuple[float, float, float]:
    """``flight_acceleration`` of one ball in Python floats, m/s^2, equal to it bit for bit (the
    same operations in the same order; tests/test_physics.py checks it).

    For callers that evaluate one ball at a time, such as the BallPlant's derivatives (thousands of
    calls per simulated second): NumPy's per-call overhead on 3-vectors makes the batched function
    about six times slower there. The arithmetic is ``ball_acceleration``'s, which the compiled
    ``rk4_step`` shares. Args: v_W (m/s) and w_W (rad/s) as 3 floats each.
    """
    return ball_acceleration(*v_W, *w_W, *flight_constants(aero))


def state_derivative(state: np.ndarray, aero: AeroParams) -> np.ndarray:
    """d/dt [p, v, w] = [v, a(v, w), 0] for (..., 9) ball states."""
    derivative = np.zeros_like(state, dtype=float)
    derivative[..., POSITION] = state[..., VELOCITY]
    derivative[..., VELOCITY] = flight_acceleration(state[..., VELOCITY], state[..., SPIN], aero)
    return derivative


def rk4_step(state: np.ndarray, dt: float | np.ndarray, aero: AeroParams) -> np.ndarray:
    """One classical Runge-Kutta 4 step of the flight model (eq. (1)).

    Args: state (..., 9); dt seconds, a scalar or an array broadcastable to state[..., :1]
    (per-ball steps, used by event location). Returns the state after dt.

    Compiled: the ball-by-ball loop of ``rk4_rows`` does the operations of ``rk4_step_numpy`` in
    the same order (IEEE arithmetic and square roots only, no fused multiply-adds), so the two are
    equal bit for bit (tests/test_physics.py); ~6 us a call for one ball (mostly the call itself)
    against ~150 us for NumPy's, which is how the predictors call it.
    """
    state = np.asarray(state, dtype=float)
    if state.shape[-1:] != (9,):
        raise ValueError(f"rk4_step: state must be (..., 9), got {state.shape}")
    rows = np.ascontiguousarray(state.reshape(-1, 9))
    steps = np.asarray(dt, dtype=float)
    if steps.ndim == 0:
        steps = np.full(rows.shape[0], float(steps))
    else:
        if steps.shape != state.shape[:-1]:
            steps = np.broadcast_to(steps, state.shape[:-1])
        steps = np.ascontiguousarray(steps.reshape(-1))
    out = np.empty_like(rows)
    rk4_rows(rows, steps, *flight_constants(aero), out)
    return out.reshape(state.shape)


def rk4_step_numpy(state: np.ndarray, dt: float | np.ndarray, aero: AeroParams) -> np.ndarray:
    """``rk4_step`` in NumPy on ``state_derivative``: the reference the compiled step equals."""
    dt = np.asarray(dt, dtype=float)
    if dt.ndim > 0:
        dt = dt[..., None]
    k1 = state_derivative(state, aero)
    k2 = state_derivative(state + 0.5 * dt * k1, aero)
    k3 = state_derivative(state + 0.5 * dt * k2, aero)
    k4 = state_derivative(state + dt * k3, aero)
    return state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def flight_constants(aero: AeroParams) -> tuple[float, ...]:
    """The constants of ``ball_acceleration`` for ``aero``, each computed in ``flight_acceleration``'s
    order: (drag scale -(3 / 8r) c_d rho_a / rho_b (1/m), rho_a / rho_b, the Magnus slope, r (m),
    offset and cap, the weight term (1 - rho_a / rho_b) |g| (m/s^2))."""
    density_ratio = aero.air_density / aero.ball_density
    drag_scale = -(3.0 / (8.0 * aero.ball_radius)) * aero.drag_coefficient * density_ratio
    weight = ((1.0 - density_ratio) if aero.buoyancy else 1.0) * aero.gravity
    return drag_scale, density_ratio, aero.magnus_slope, aero.ball_radius, aero.magnus_offset, aero.magnus_cap, weight


@numba.njit(cache=True)
def ball_acceleration(vx, vy, vz, wx, wy, wz, drag_scale, density_ratio, slope, radius, offset, cap, weight):
    """Eq. (1) divided by the mass for one ball (m/s^2, 3 floats), in ``flight_acceleration``'s
    order of operations (the cap of ``magnus_coefficient`` and its limit at zero spin)."""
    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
    spin_rate = math.sqrt(wx * wx + wy * wy + wz * wz)
    drag_gain = drag_scale * speed
    magnus = cap
    if spin_rate > 0.0:
        magnus = min(slope * speed / (radius * spin_rate) + offset, cap)
    magnus_gain = -magnus * density_ratio
    return (
        drag_gain * vx + magnus_gain * (vy * wz - vz * wy),
        drag_gain * vy + magnus_gain * (vz * wx - vx * wz),
        drag_gain * vz + magnus_gain * (vx * wy - vy * wx) - weight,
    )


@numba.njit(cache=True)
def _derivative(x, drag_scale, density_ratio, slope, radius, offset, cap, weight, k):
    """``state_derivative`` of one ball x (9,) into k (9,)."""
    k[0], k[1], k[2] = x[3], x[4], x[5]
    k[3], k[4], k[5] = ball_acceleration(x[3], x[4], x[5], x[6], x[7], x[8], drag_scale, density_ratio, slope, radius, offset, cap, weight)
    k[6], k[7], k[8] = 0.0, 0.0, 0.0


@numba.njit(cache=True)
def rk4_one(x, h, drag_scale, density_ratio, slope, radius, offset, cap, weight, k1, k2, k3, k4, trial, out):
    """One RK4 step of one ball x (9,) by h into out (9,), with scratch k1..k4, trial (9,)."""
    half = 0.5 * h
    _derivative(x, drag_scale, density_ratio, slope, radius, offset, cap, weight, k1)
    for j in range(9):
        trial[j] = x[j] + half * k1[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, k2)
    for j in range(9):
        trial[j] = x[j] + half * k2[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, k3)
    for j in range(9):
        trial[j] = x[j] + h * k3[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, k4)
    sixth = h / 6.0
    for j in range(9):
        out[j] = x[j] + sixth * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])


@numba.njit(cache=True)
def rk4_rows(states, steps, drag_scale, density_ratio, slope, radius, offset, cap, weight, out):
    """``rk4_step`` of every row of states (M, 9) by its step (M,) into out (M, 9)."""
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for i in range(states.shape[0]):
        rk4_one(states[i], steps[i], drag_scale, density_ratio, slope, radius, offset, cap, weight, k1, k2, k3, k4, trial, out[i])


@numba.njit(cache=True)
def _rk4_trajectory_rows(states, steps, drag_scale, density_ratio, slope, radius, offset, cap, weight, out):
    """``rk4_trajectory`` of states (M, 9) over steps (n,) into out (M, n+1, 9)."""
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for i in range(states.shape[0]):
        out[i, 0] = states[i]
        for k in range(steps.shape[0]):
            rk4_one(out[i, k], steps[k], drag_scale, density_ratio, slope, radius, offset, cap, weight, k1, k2, k3, k4, trial, out[i, k + 1])


def rk4_trajectory(state: np.ndarray, steps: np.ndarray, aero: AeroParams) -> np.ndarray:
    """Consecutive RK4 steps of the flight model (eq. (1)), no contacts: the states (M, n+1, 9)
    of balls starting at state (M, 9) after 0, 1, ..., n steps of steps (n,) s; equal bit for bit
    to calling ``rk4_step`` n times (compiled; one call instead of n for the batched segments)."""
    state = np.ascontiguousarray(state, dtype=float)
    steps = np.ascontiguousarray(steps, dtype=float)
    if state.ndim != 2 or state.shape[1] != 9 or steps.ndim != 1:
        raise ValueError(f"rk4_trajectory: state must be (M, 9) and steps (n,), got {state.shape} and {steps.shape}")
    out = np.empty((state.shape[0], steps.size + 1, 9))
    _rk4_trajectory_rows(state, steps, *flight_constants(aero), out)
    return out


def make_state(p_W, v_W, w_W=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Stacks position (m), velocity (m/s) and spin (rad/s), each (..., 3), into (..., 9)."""
    p_W, v_W, w_W = np.broadcast_arrays(
        np.asarray(p_W, dtype=float), np.asarray(v_W, dtype=float), np.asarray(w_W, dtype=float)
    )
    return np.concatenate([p_W, v_W, w_W], axis=-1)
