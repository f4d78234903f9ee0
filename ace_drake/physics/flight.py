"""Ball flight: drag, Magnus and gravity (paper eq. (1)), and the RK4 step.

A ball state is a (..., 9) array [p_W (m), v_W (m/s), w_W (rad/s)] in the world frame of
DESIGN.md; spin is constant in flight (paper, Methods *Ball aerodynamics*). Every function is
batched over the leading dimensions, except ``one_ball_flight_acceleration``, the scalar twin of
``flight_acceleration`` for per-ball callers. ``rk4_step`` is compiled (numba) and equal bit for bit
to the same step written with ``state_derivative`` in NumPy (``rk4_step_numpy``, its reference).

The drag and Magnus coefficients of eq. (1) each come from a model selected in ``AeroParams``
(``drag_model``, ``magnus_model``): the printed paper's (the defaults) or the ones in the authors'
published physics code, in the model set they label as the paper's (``drag_coefficient``,
``magnus_coefficient``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ace_drake.physics.params import AeroParams

POSITION = slice(0, 3)
VELOCITY = slice(3, 6)
SPIN = slice(6, 9)

# The "spin_ratio" drag model (``drag_coefficient``): c_d against the spin ratio S = |w| r / |v| on
# four reference curves, one per speed; each curve has 6 breakpoints S_0..S_5 and values there.
DRAG_REFERENCE_SPEEDS = np.array([2.5, 7.5, 12.5, 17.5])  # m/s
DRAG_SPIN_RATIOS = np.array([
    [0.0, 0.3, 0.7, 0.95, 1.5, 2.0],
    [0.0, 0.4, 0.75, 1.1, 1.3, 2.0],
    [0.0, 0.4, 0.62, 0.95, 1.3, 2.0],
    [0.0, 0.4, 0.5, 0.84, 1.2, 2.0],
])
DRAG_CURVES = np.array([
    [0.55, 0.55, 0.55, 0.55, 0.55, 0.55],
    [0.49, 0.49, 0.55, 0.48, 0.53, 0.53],
    [0.47, 0.47, 0.53, 0.41, 0.48, 0.48],
    [0.47, 0.47, 0.51, 0.37, 0.45, 0.45],
])
DRAG_TABLE_NOMINAL = 0.55  # the c_d that the table is relative to: it is scaled by drag_coefficient / 0.55

# The "refined" Magnus model (``magnus_coefficient``): c_M = m1 |w| + c1 up to |w| = w_break,
# a |w|^2 + b |w| + c above, each parameter given at six reference speeds (|w| in rad/s).
MAGNUS_REFERENCE_SPEEDS = np.array([2.0, 3.5, 7.5, 10.5, 13.5, 17.0])  # m/s
MAGNUS_M1 = np.array([0.0, -0.0011, -0.000775, -0.000658, -0.00056, -0.000448])  # s/rad
MAGNUS_C1 = np.array([0.08, 0.31, 0.366, 0.375, 0.383, 0.371])
MAGNUS_BREAK = np.array([150.0, 200.0, 350.0, 440.0, 550.0, 650.0])  # w_break, rad/s
MAGNUS_A = np.array([-1.852e-7, -1.667e-7, -2.0e-7, -2.604e-7, -3.571e-7, -1.0e-7])  # s^2/rad^2
MAGNUS_B = np.array([-1.296e-4, -3.333e-5, 1.7e-4, 3.646e-4, 5.357e-4, 2.3e-4])  # s/rad
MAGNUS_C = np.array([0.09833, 0.1, 0.05875, -0.0225, -0.08929, -0.0375])

# The model selectors as the compiled kernels take them (floats, like the other constants).
CONSTANT_DRAG, SPIN_RATIO_DRAG = 0.0, 1.0
RATIO_MAGNUS, REFINED_MAGNUS = 0.0, 1.0
FLIGHT_CONSTANT_COUNT = 11  # len(flight_constants(aero))


def drag_coefficient(speed: np.ndarray, spin_rate: np.ndarray, aero: AeroParams) -> np.ndarray:
    """c_d of eq. (1) for ``aero.drag_model``. Args: speed |v| (m/s), spin_rate |w| (rad/s), any
    matching shapes. Returns c_d (dimensionless).

    "constant": c_d = ``aero.drag_coefficient`` (the printed paper's 0.55).

    "spin_ratio": c_d from the spin ratio S = |w| r / |v| and the speed, as in the authors'
    published physics code (the model set they label as the paper's; tables DRAG_SPIN_RATIOS and
    DRAG_CURVES at DRAG_REFERENCE_SPEEDS). At |v| <= 2.5 m/s c_d = 0.55 (so also at |v| = 0, where
    S is undefined). Above, the two reference curves around |v| are blended, breakpoints and values
    alike, (1 - alpha) lower + alpha upper with alpha = (|v| - v_lower) / 5 m/s, and the blended
    curve is read at S: its first value up to S_1, its last from S_4 on, linear in between. S = 0
    without spin. We depart from the authors above 17.5 m/s: they extrapolate the blend (c_d falls
    to 0.27 at 30 m/s), we hold the 17.5 m/s curve (alpha <= 1), so c_d stays in [0.37, 0.55].
    The table is multiplied by ``aero.drag_coefficient / 0.55`` (1 by default), so that fitting
    ``drag_coefficient`` (``physics-fit``) still scales the drag.
    """
    if aero.drag_model == "constant":
        return np.full(np.broadcast(speed, spin_rate).shape, aero.drag_coefficient)
    return spin_ratio_drag_table(speed, spin_rate, aero.ball_radius) * (aero.drag_coefficient / DRAG_TABLE_NOMINAL)


def spin_ratio_drag_table(speed: np.ndarray, spin_rate: np.ndarray, radius: float) -> np.ndarray:
    """The "spin_ratio" table's c_d (``drag_coefficient``, before its scale), batched; the same
    operations in the same order as the compiled ``_spin_ratio_drag_table``."""
    speed, spin_rate = np.broadcast_arrays(np.asarray(speed, dtype=float), np.asarray(spin_rate, dtype=float))
    speeds = DRAG_REFERENCE_SPEEDS
    fast = speed > speeds[0]
    safe_speed = np.where(fast, speed, speeds[0])  # slow balls read the 2.5 m/s curve, then take 0.55
    spin_ratio = spin_rate * radius / safe_speed
    lower = (safe_speed > speeds[1]).astype(np.int64) + (safe_speed > speeds[2])
    # alpha <= 1: above 17.5 m/s the 17.5 m/s curve (we depart from the authors, who extrapolate).
    alpha = np.minimum((safe_speed - speeds[lower]) / (speeds[lower + 1] - speeds[lower]), 1.0)[..., None]
    breaks = (1.0 - alpha) * DRAG_SPIN_RATIOS[lower] + alpha * DRAG_SPIN_RATIOS[lower + 1]
    values = (1.0 - alpha) * DRAG_CURVES[lower] + alpha * DRAG_CURVES[lower + 1]
    # Only S in (S_1, S_4) reads a segment; clipping keeps the others finite (they take an end).
    inside = np.clip(spin_ratio, breaks[..., 1], breaks[..., 4])
    segment = (1 + (inside > breaks[..., 2]).astype(np.int64) + (inside > breaks[..., 3]))[..., None]
    s_lo = np.take_along_axis(breaks, segment, -1)[..., 0]
    s_hi = np.take_along_axis(breaks, segment + 1, -1)[..., 0]
    c_lo = np.take_along_axis(values, segment, -1)[..., 0]
    c_hi = np.take_along_axis(values, segment + 1, -1)[..., 0]
    read = c_lo + (inside - s_lo) / (s_hi - s_lo) * (c_hi - c_lo)
    read = np.where(spin_ratio <= breaks[..., 1], values[..., 0], np.where(spin_ratio >= breaks[..., 4], values[..., 5], read))
    return np.where(fast, read, DRAG_CURVES[0, 0])


def magnus_coefficient(speed: np.ndarray, spin_rate: np.ndarray, aero: AeroParams) -> np.ndarray:
    """c_M of eq. (1) for ``aero.magnus_model``. Args: speed |v| (m/s), spin_rate |w| (rad/s), any
    matching shapes. Returns c_M (dimensionless).

    "ratio": c_M = min(0.1 |v| / (r |w|) - 0.001, 1) (paper, below eq. (1); cap from the authors'
    code; ``magnus_slope``, ``magnus_offset``, ``magnus_cap``). The printed c_M is singular as
    |w| -> 0. With the cap, c_M = cap for all small spin rates, so the Magnus acceleration
    c_M (rho_air / rho_ball)(v x w) goes to zero linearly in |w|: the limit at |w| = 0 is defined
    as c_M = cap and the trajectory is continuous in w.

    "refined": as in the authors' published physics code (the model set they label as the
    paper's): with w = |w| in rad/s, c_M = m1 w + c1 for w <= w_break, a w^2 + b w + c above,
    then max(c_M, 0); the six parameters (MAGNUS_M1 .. MAGNUS_C) are given at
    MAGNUS_REFERENCE_SPEEDS and interpolated linearly in |v|. Outside 2-17 m/s the end values hold;
    we depart from the authors below 2 m/s, where they extrapolate a, b, c linearly. The result is
    multiplied by ``aero.magnus_scale`` (1 by default; it does not act on "ratio"), the knob a fit
    scales this model with. Finite at w = 0, where v x w = 0 leaves no Magnus force.
    """
    speed = np.asarray(speed, dtype=float)
    spin_rate = np.asarray(spin_rate, dtype=float)
    if aero.magnus_model == "refined":
        return refined_magnus_table(speed, spin_rate) * aero.magnus_scale
    spinning = spin_rate > 0.0
    safe_rate = np.where(spinning, spin_rate, 1.0)
    c_m = aero.magnus_slope * speed / (aero.ball_radius * safe_rate) + aero.magnus_offset
    return np.where(spinning, np.minimum(c_m, aero.magnus_cap), aero.magnus_cap)


def refined_magnus_table(speed: np.ndarray, spin_rate: np.ndarray) -> np.ndarray:
    """The "refined" c_M (``magnus_coefficient``, before its scale), batched; the same operations
    in the same order as the compiled ``_refined_magnus_table``."""
    speed, spin_rate = np.broadcast_arrays(np.asarray(speed, dtype=float), np.asarray(spin_rate, dtype=float))
    speeds = MAGNUS_REFERENCE_SPEEDS
    lower = np.zeros(speed.shape, dtype=np.int64)
    for k in range(1, speeds.size - 1):
        lower += speed > speeds[k]
    # 0 <= t <= 1: the end values outside 2-17 m/s (below 2 m/s we depart from the authors, who
    # extrapolate a, b, c).
    t = np.minimum(np.maximum((speed - speeds[lower]) / (speeds[lower + 1] - speeds[lower]), 0.0), 1.0)

    def at_speed(parameter):
        return (1.0 - t) * parameter[lower] + t * parameter[lower + 1]

    m1, c1, w_break = at_speed(MAGNUS_M1), at_speed(MAGNUS_C1), at_speed(MAGNUS_BREAK)
    a, b, c = at_speed(MAGNUS_A), at_speed(MAGNUS_B), at_speed(MAGNUS_C)
    c_m = np.where(spin_rate <= w_break, m1 * spin_rate + c1, a * (spin_rate * spin_rate) + b * spin_rate + c)
    return np.where(c_m < 0.0, 0.0, c_m)


def flight_acceleration(v_W: np.ndarray, w_W: np.ndarray, aero: AeroParams) -> np.ndarray:
    """dv/dt of a ball in flight, m/s^2: paper eq. (1) divided by the ball's mass.

    a = -(3 / (8 r)) c_d (rho_a / rho_b) |v| v - c_M (rho_a / rho_b) (v x w) + (1 - rho_a / rho_b) g,
    the buoyancy factor on g as in the authors' code (``aero.buoyancy``); c_d and c_M from the
    selected models (``drag_coefficient``, ``magnus_coefficient``). Args: v_W, w_W (..., 3).
    """
    v_W = np.asarray(v_W, dtype=float)
    w_W = np.asarray(w_W, dtype=float)
    density_ratio = aero.air_density / aero.ball_density
    vx, vy, vz = v_W[..., 0], v_W[..., 1], v_W[..., 2]
    wx, wy, wz = w_W[..., 0], w_W[..., 1], w_W[..., 2]
    speed = np.sqrt(vx * vx + vy * vy + vz * vz)  # explicit: np.linalg.norm/np.cross dominate small batches
    spin_rate = np.sqrt(wx * wx + wy * wy + wz * wz)
    drag_gain = -(3.0 / (8.0 * aero.ball_radius)) * drag_coefficient(speed, spin_rate, aero) * density_ratio * speed
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
    order: (drag scale -(3 / 8r) c_d rho_a / rho_b (1/m) of the "constant" drag model,
    rho_a / rho_b, the Magnus slope, r (m), offset and cap of the "ratio" Magnus model, the weight
    term (1 - rho_a / rho_b) |g| (m/s^2), the drag model (CONSTANT_DRAG or SPIN_RATIO_DRAG), the
    Magnus model (RATIO_MAGNUS or REFINED_MAGNUS), the "spin_ratio" table's scale
    c_d / 0.55 and the "refined" table's scale); FLIGHT_CONSTANT_COUNT floats."""
    density_ratio = aero.air_density / aero.ball_density
    drag_scale = -(3.0 / (8.0 * aero.ball_radius)) * aero.drag_coefficient * density_ratio
    weight = ((1.0 - density_ratio) if aero.buoyancy else 1.0) * aero.gravity
    drag_model = SPIN_RATIO_DRAG if aero.drag_model == "spin_ratio" else CONSTANT_DRAG
    magnus_model = REFINED_MAGNUS if aero.magnus_model == "refined" else RATIO_MAGNUS
    return (drag_scale, density_ratio, aero.magnus_slope, aero.ball_radius, aero.magnus_offset, aero.magnus_cap, weight,
            drag_model, magnus_model, aero.drag_coefficient / DRAG_TABLE_NOMINAL, aero.magnus_scale)


@numba.njit(cache=True)
def _spin_ratio_drag_table(speed, spin_rate, radius):
    """``spin_ratio_drag_table`` of one ball."""
    speeds = DRAG_REFERENCE_SPEEDS
    if not speed > speeds[0]:
        return DRAG_CURVES[0, 0]
    spin_ratio = spin_rate * radius / speed
    lower = 0
    if speed > speeds[1]:
        lower = 1
    if speed > speeds[2]:
        lower = 2
    alpha = min((speed - speeds[lower]) / (speeds[lower + 1] - speeds[lower]), 1.0)  # held above 17.5 m/s (a departure)
    if spin_ratio <= _blend(DRAG_SPIN_RATIOS, lower, alpha, 1):
        return _blend(DRAG_CURVES, lower, alpha, 0)
    if spin_ratio >= _blend(DRAG_SPIN_RATIOS, lower, alpha, 4):
        return _blend(DRAG_CURVES, lower, alpha, 5)
    segment = 1
    if spin_ratio > _blend(DRAG_SPIN_RATIOS, lower, alpha, 2):
        segment = 2
    if spin_ratio > _blend(DRAG_SPIN_RATIOS, lower, alpha, 3):
        segment = 3
    s_lo, s_hi = _blend(DRAG_SPIN_RATIOS, lower, alpha, segment), _blend(DRAG_SPIN_RATIOS, lower, alpha, segment + 1)
    c_lo, c_hi = _blend(DRAG_CURVES, lower, alpha, segment), _blend(DRAG_CURVES, lower, alpha, segment + 1)
    return c_lo + (spin_ratio - s_lo) / (s_hi - s_lo) * (c_hi - c_lo)


@numba.njit(cache=True)
def _blend(table, lower, alpha, k):
    """Column k of the curve (1 - alpha) table[lower] + alpha table[lower + 1]."""
    return (1.0 - alpha) * table[lower, k] + alpha * table[lower + 1, k]


@numba.njit(cache=True)
def _refined_magnus_table(speed, spin_rate):
    """``refined_magnus_table`` of one ball."""
    speeds = MAGNUS_REFERENCE_SPEEDS
    lower = 0
    for k in range(1, speeds.size - 1):
        if speed > speeds[k]:
            lower += 1
    t = min(max((speed - speeds[lower]) / (speeds[lower + 1] - speeds[lower]), 0.0), 1.0)  # end values held (a departure)
    if spin_rate <= (1.0 - t) * MAGNUS_BREAK[lower] + t * MAGNUS_BREAK[lower + 1]:
        m1 = (1.0 - t) * MAGNUS_M1[lower] + t * MAGNUS_M1[lower + 1]
        c1 = (1.0 - t) * MAGNUS_C1[lower] + t * MAGNUS_C1[lower + 1]
        c_m = m1 * spin_rate + c1
    else:
        a = (1.0 - t) * MAGNUS_A[lower] + t * MAGNUS_A[lower + 1]
        b = (1.0 - t) * MAGNUS_B[lower] + t * MAGNUS_B[lower + 1]
        c = (1.0 - t) * MAGNUS_C[lower] + t * MAGNUS_C[lower + 1]
        c_m = a * (spin_rate * spin_rate) + b * spin_rate + c
    if c_m < 0.0:
        c_m = 0.0
    return c_m


@numba.njit(cache=True, inline="always")
def ball_acceleration(vx, vy, vz, wx, wy, wz, drag_scale, density_ratio, slope, radius, offset, cap, weight,
                      drag_model, magnus_model, drag_table_scale, magnus_scale):
    """Eq. (1) divided by the mass for one ball (m/s^2, 3 floats), in ``flight_acceleration``'s
    order of operations, with the models of ``flight_constants``.

    Inlined where it is called with only the default models' arithmetic and one test; the other
    models are a call (``_modelled_gains``): the tables' code inlined would slow the default RK4
    step by about a quarter."""
    speed = math.sqrt(vx * vx + vy * vy + vz * vz)
    spin_rate = math.sqrt(wx * wx + wy * wy + wz * wz)
    if drag_model == CONSTANT_DRAG and magnus_model == RATIO_MAGNUS:
        drag_gain = drag_scale * speed
        magnus = _ratio_magnus(speed, spin_rate, slope, radius, offset, cap)
    else:
        drag_gain, magnus = _modelled_gains(speed, spin_rate, drag_scale, density_ratio, slope, radius, offset, cap,
                                            drag_model, magnus_model, drag_table_scale, magnus_scale)
    magnus_gain = -magnus * density_ratio
    return (
        drag_gain * vx + magnus_gain * (vy * wz - vz * wy),
        drag_gain * vy + magnus_gain * (vz * wx - vx * wz),
        drag_gain * vz + magnus_gain * (vx * wy - vy * wx) - weight,
    )


@numba.njit(cache=True, inline="always")
def _ratio_magnus(speed, spin_rate, slope, radius, offset, cap):
    """The "ratio" c_M of one ball, its cap, and its limit at zero spin (``magnus_coefficient``)."""
    magnus = cap
    if spin_rate > 0.0:
        magnus = min(slope * speed / (radius * spin_rate) + offset, cap)
    return magnus


@numba.njit(cache=True)
def _modelled_gains(speed, spin_rate, drag_scale, density_ratio, slope, radius, offset, cap, drag_model, magnus_model,
                    drag_table_scale, magnus_scale):
    """``ball_acceleration``'s drag gain -(3 / 8r) c_d (rho_a / rho_b) |v| (1/s) and c_M for any
    models."""
    if drag_model == CONSTANT_DRAG:
        drag_gain = drag_scale * speed
    else:
        c_d = _spin_ratio_drag_table(speed, spin_rate, radius) * drag_table_scale
        drag_gain = -(3.0 / (8.0 * radius)) * c_d * density_ratio * speed
    if magnus_model == RATIO_MAGNUS:
        magnus = _ratio_magnus(speed, spin_rate, slope, radius, offset, cap)
    else:
        magnus = _refined_magnus_table(speed, spin_rate) * magnus_scale
    return drag_gain, magnus


@numba.njit(cache=True, inline="always")
def _derivative(x, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, k):
    """``state_derivative`` of one ball x (9,) into k (9,)."""
    k[0], k[1], k[2] = x[3], x[4], x[5]
    k[3], k[4], k[5] = ball_acceleration(x[3], x[4], x[5], x[6], x[7], x[8], drag_scale, density_ratio, slope, radius, offset, cap,
                                         weight, drag_model, magnus_model, drag_table_scale, magnus_scale)
    k[6], k[7], k[8] = 0.0, 0.0, 0.0


@numba.njit(cache=True)
def rk4_one(x, h, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
            magnus_scale, k1, k2, k3, k4, trial, out):
    """One RK4 step of one ball x (9,) by h into out (9,), with scratch k1..k4, trial (9,); the
    flight constants are ``flight_constants``'."""
    half = 0.5 * h
    _derivative(x, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, k1)
    for j in range(9):
        trial[j] = x[j] + half * k1[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, k2)
    for j in range(9):
        trial[j] = x[j] + half * k2[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, k3)
    for j in range(9):
        trial[j] = x[j] + h * k3[j]
    _derivative(trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
                magnus_scale, k4)
    sixth = h / 6.0
    for j in range(9):
        out[j] = x[j] + sixth * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])


@numba.njit(cache=True)
def rk4_rows(states, steps, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
             drag_table_scale, magnus_scale, out):
    """``rk4_step`` of every row of states (M, 9) by its step (M,) into out (M, 9)."""
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for i in range(states.shape[0]):
        rk4_one(states[i], steps[i], drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, out[i])


@numba.njit(cache=True)
def _rk4_trajectory_rows(states, steps, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                         drag_table_scale, magnus_scale, out):
    """``rk4_trajectory`` of states (M, 9) over steps (n,) into out (M, n+1, 9)."""
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for i in range(states.shape[0]):
        out[i, 0] = states[i]
        for k in range(steps.shape[0]):
            rk4_one(out[i, k], steps[k], drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                    drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, out[i, k + 1])


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
