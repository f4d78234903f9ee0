"""The compiled steps of the ball EKF (``perception.ball_ekf``), over B environments at once.

``BallEkf`` (its module docstring has the method) keeps each environment's filter in arrays
(``EkfBatch``) and runs these numba kernels on them; ``BallEkf.update`` is the B = 1 case of
``BallEkf.update_arrays``, so there is one definition of the filter. Environments are independent:
an environment's numbers do not depend on the others in the batch.

Layout of the arrays (the leading axis is the environment, b):

- observations, in processing order: ``obs_f`` (B, O, OBS_F) [key time (s: capture time + lag),
  capture time (s), value (3,), covariance (9,) row-major], ``obs_i`` (B, O, 2) [kind, sequence].
  Observations [0, first) are older than the re-filtering history, kept only while a core's
  start buffers still refer to them; [first, n_obs) are the history's steps.
- cores (the filter after a step, ``FilterCore``): ``core_f`` (B, C, CORE_F) [time, free_until,
  segment_start, last_capture, not_before (s), mean (9,), covariance (144,) over [p, v, w, b]],
  ``core_i`` (B, C, 6 + P + MAX_START_SPINS) [tracking, spin_fused, bias_shaped, resets, the number
  of start positions and of start spins, the start positions' and spins' absolute observation
  numbers]. Core ``core0`` is the base (before step ``first``); core core0 + k + 1 is after step
  first + k.
- ``index`` (B, INDEX_SIZE) int64: [n_obs, first, core0, absolute number of observation 0,
  discarded, the first observation still needed]; ``base_key`` (B, 3): the key of the last
  observation pruned into the base.

A prediction whose mean could touch the table, net or floor needs ``physics.propagate.simulate``
(contacts located exactly), which is Python: the kernel then stops that environment and leaves a
request (the 10 states of the finite-difference batch, the duration and step); the caller runs
``simulate`` for every stopped environment and calls the kernel again, which resumes at the same
step with the result. Everything else (flight by ``physics.flight``'s compiled RK4 step, the
Jacobian, the Kalman updates, the start fits, the resets, re-filtering and pruning) is here.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ace_drake.physics.contact import floor_gap_one, net_gap_one, table_gap_one
from ace_drake.physics.flight import FLIGHT_CONSTANT_COUNT, ball_acceleration, rk4_rows

CONTACT, POSITION, SPIN = 0, 1, 2  # observation kinds, also their order among equal keys
MAX_START_SPINS = 16  # spins kept while a track starts
# Over at most FREE_HORIZON_MAX the ball's speed grows by less than FREE_SPEED_MARGIN: its
# acceleration stays under 250 m/s^2 (drag 140 m/s^2 and Magnus under 70 m/s^2 at 30 m/s, and g),
# so it cannot touch anything sooner than gap / (|v| + margin).
FREE_HORIZON_MAX = 0.02  # s
FREE_SPEED_MARGIN = 5.0  # m/s

# observation columns
O_KEY, O_CAPTURE, O_VALUE, O_COVARIANCE = 0, 1, 2, 5
OBS_F = 14
O_KIND, O_SEQUENCE = 0, 1
OBS_I = 2
# core columns
C_TIME, C_FREE, C_SEGMENT, C_LAST, C_NOT_BEFORE, C_MEAN, C_COVARIANCE = 0, 1, 2, 3, 4, 5, 14
CORE_F = 14 + 144
I_TRACKING, I_SPIN_FUSED, I_BIAS_SHAPED, I_RESETS, I_POSITIONS, I_SPINS, I_START = 0, 1, 2, 3, 4, 5, 6
# index columns
X_N, X_FIRST, X_CORE0, X_OFFSET, X_DISCARDED, X_KEEP = 0, 1, 2, 3, 4, 5
INDEX_SIZE = 6
# configuration (``config_arrays``)
(F_GAP, F_JUMP, F_INNOVATION, F_HISTORY, F_FD_STEP, F_MAX_STEP, F_Q_A, F_Q_W, F_BOUNCE_V, F_BOUNCE_W,
 F_BIAS_MAGNITUDE, F_BIAS_AXIS, F_FIT_THRESHOLD, F_POSITION_VARIANCE, F_SPIN_VARIANCE, F_RADIUS,
 F_TABLE_LENGTH, F_TABLE_WIDTH, F_SURFACE_HEIGHT, F_NET_HEIGHT, F_NET_OVERHANG, F_MAX_SPEED, F_MAX_SPIN, F_FLIGHT) = range(24)
CONFIG_SIZE = F_FLIGHT + FLIGHT_CONSTANT_COUNT  # then physics.flight.flight_constants
OK, BLOCKED = 0, 1
NAN = math.nan


def core_int_size(initial_position_count: int) -> int:
    """Columns of ``core_i`` for ``initial_position_count`` start positions."""
    return I_START + initial_position_count + MAX_START_SPINS


# ------------------------------------------------------------------------------ small maths
@numba.njit(cache=True)
def _solve3(a, rhs, out):
    """out (3, m) = a^-1 rhs for a (3, 3): Gaussian elimination with partial pivoting."""
    m = rhs.shape[1]
    lu = a.copy()
    x = rhs.copy()
    for k in range(3):
        pivot = k
        for r in range(k + 1, 3):
            if abs(lu[r, k]) > abs(lu[pivot, k]):
                pivot = r
        if pivot != k:
            for c in range(3):
                lu[k, c], lu[pivot, c] = lu[pivot, c], lu[k, c]
            for c in range(m):
                x[k, c], x[pivot, c] = x[pivot, c], x[k, c]
        for r in range(k + 1, 3):
            factor = lu[r, k] / lu[k, k]
            for c in range(k + 1, 3):
                lu[r, c] -= factor * lu[k, c]
            for c in range(m):
                x[r, c] -= factor * x[k, c]
    for k in range(2, -1, -1):
        for c in range(m):
            s = x[k, c]
            for j in range(k + 1, 3):
                s -= lu[k, j] * out[j, c]
            out[k, c] = s / lu[k, k]


@numba.njit(cache=True)
def _quadratic3(a, v):
    """v^T a^-1 v for a (3, 3), v (3,)."""
    rhs = np.empty((3, 1))
    rhs[:, 0] = v
    out = np.empty((3, 1))
    _solve3(a, rhs, out)
    return v[0] * out[0, 0] + v[1] * out[1, 0] + v[2] * out[2, 0]


@numba.njit(cache=True)
def _norm3(x, y, z):
    return math.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True)
def contact_gaps(x, y, z, cfg):
    """The table, net and floor guards (m) of a ball centre: ``physics.contact``'s one-ball kernels
    with the EKF's packed constants ``cfg``."""
    radius = cfg[F_RADIUS]
    table = table_gap_one(x, y, z, cfg[F_TABLE_LENGTH], cfg[F_TABLE_WIDTH], radius)
    net = net_gap_one(x, y, z, cfg[F_TABLE_WIDTH], cfg[F_NET_OVERHANG], cfg[F_NET_HEIGHT], radius)
    floor = floor_gap_one(z, cfg[F_SURFACE_HEIGHT], radius)
    return table, net, floor


@numba.njit(cache=True)
def contact_free_horizon(mean, cfg):
    """How long (s, at most FREE_HORIZON_MAX) the ball at ``mean`` (9,) surely touches nothing:
    ``physics.propagate.contact_gap_lower_bound`` first, then the exact gaps (``contact_gaps``)."""
    x, y, z = mean[0], mean[1], mean[2]
    radius = cfg[F_RADIUS]
    clear = min(z - radius, abs(x) - radius, z + cfg[F_SURFACE_HEIGHT] - radius)
    speed = math.sqrt(((0.0 + mean[3] * mean[3]) + mean[4] * mean[4]) + mean[5] * mean[5])
    if clear > FREE_HORIZON_MAX * (speed + FREE_SPEED_MARGIN) * (1.0 + 1e-9):
        return FREE_HORIZON_MAX
    table, net, floor = contact_gaps(x, y, z, cfg)
    gap = min(table, net, floor)
    if gap <= 0.0:
        return 0.0
    return min(FREE_HORIZON_MAX, gap / (_norm3(mean[3], mean[4], mean[5]) + FREE_SPEED_MARGIN))


@numba.njit(cache=True)
def _noise(obs_f_row, variance, out):
    """The observation's covariance (3, 3), or variance I when the variance is configured."""
    if math.isnan(variance):
        for r in range(3):
            for c in range(3):
                out[r, c] = obs_f_row[O_COVARIANCE + 3 * r + c]
    else:
        for r in range(3):
            for c in range(3):
                out[r, c] = variance if r == c else 0.0


@numba.njit(cache=True)
def _bias_covariance(spin, cfg, out):
    """The spin sensor's bias covariance (3, 3) around a measured spin (3,), (rad/s)^2: magnitude
    along its axis, |w| times the axis std across it (as ``spin_precision_covariance``)."""
    rate = _norm3(spin[0], spin[1], spin[2])
    magnitude_variance = cfg[F_BIAS_MAGNITUDE] ** 2
    if rate < 1e-9:
        for r in range(3):
            for c in range(3):
                out[r, c] = magnitude_variance if r == c else 0.0
        return
    across = (rate * cfg[F_BIAS_AXIS]) ** 2
    for r in range(3):
        for c in range(3):
            along = spin[r] * spin[c] / rate**2
            out[r, c] = magnitude_variance * along + across * ((1.0 if r == c else 0.0) - along)


# ------------------------------------------------------------------------------ prediction
@numba.njit(cache=True)
def _flight_without_contact(batch, duration, dt, cfg):
    """``physics.propagate.simulate(batch, duration, dt)`` in place when none of the rows of batch
    (M, 9) crosses a table, net or floor guard: the same steps (h = min(dt, duration - t)) by the
    same compiled RK4 step, so the same numbers. Returns False, batch unchanged, as soon as a
    guard of some row goes from positive to non-positive (a contact, which ``simulate`` locates)."""
    rows = batch.shape[0]
    gaps = np.empty((rows, 3))
    for r in range(rows):
        gaps[r, 0], gaps[r, 1], gaps[r, 2] = contact_gaps(batch[r, 0], batch[r, 1], batch[r, 2], cfg)
    n_steps = int(math.ceil(duration / dt - 1e-9))
    t = 0.0
    x = batch.copy()
    x1 = np.empty_like(x)
    h_rows = np.empty(rows)
    flight = cfg[F_FLIGHT:]
    for _ in range(n_steps):
        h = min(dt, duration - t)
        if h > 0.0:
            h_rows[:] = h
            rk4_rows(x, h_rows, flight[0], flight[1], flight[2], flight[3], flight[4], flight[5], flight[6], flight[7], flight[8],
                     flight[9], flight[10], x1)
            for r in range(rows):
                table, net, floor = contact_gaps(x1[r, 0], x1[r, 1], x1[r, 2], cfg)
                if (gaps[r, 0] > 0.0 and table <= 0.0) or (gaps[r, 1] > 0.0 and net <= 0.0) or (gaps[r, 2] > 0.0 and floor <= 0.0):
                    return False
                gaps[r, 0], gaps[r, 1], gaps[r, 2] = table, net, floor
            x, x1 = x1, x
        t += h
    batch[:, :] = x
    return True


@numba.njit(cache=True)
def predict(mean, covariance, duration, cfg, request, result, out_mean, out_covariance):
    """The EKF prediction over ``duration`` s of a mean (9,) and covariance (12, 12) over [x, b]
    into out_mean, out_covariance (``BallEkf.predict``). Returns (OK or BLOCKED, the time of the
    mean's last contact in s after the start, NaN for none).

    request (10 * 9 + 2,): where a prediction that needs ``simulate`` (a guard crossing) leaves
    its batch and [duration, step] (BLOCKED); result (10 * 9 + 2,): [final batch, 1 when present,
    last contact time], consumed by the next such prediction."""
    if duration <= 0.0:
        out_mean[:] = mean
        out_covariance[:, :] = covariance
        return OK, NAN
    steps = np.empty(9)
    for j in range(9):
        steps[j] = cfg[F_FD_STEP] * (1.0 + abs(mean[j]))
    batch = np.empty((10, 9))
    for r in range(10):
        batch[r] = mean
    for j in range(9):
        batch[1 + j, j] = mean[j] + steps[j]
    substeps = max(1, math.ceil(duration / cfg[F_MAX_STEP] - 1e-9))
    step = duration / substeps
    last_contact = NAN
    if duration <= contact_free_horizon(mean, cfg):
        step_array = np.full(10, step)
        other = np.empty((10, 9))
        flight = cfg[F_FLIGHT:]
        for _ in range(substeps):
            rk4_rows(batch, step_array, flight[0], flight[1], flight[2], flight[3], flight[4], flight[5], flight[6], flight[7],
                     flight[8], flight[9], flight[10], other)
            batch, other = other, batch
    elif _flight_without_contact(batch, duration, step, cfg):
        pass
    elif result[90] == 1.0:
        for r in range(10):
            for c in range(9):
                batch[r, c] = result[9 * r + c]
        last_contact = result[91]
        result[90] = 0.0
    else:
        for r in range(10):
            for c in range(9):
                request[9 * r + c] = batch[r, c]
        request[90], request[91] = duration, step
        return BLOCKED, NAN
    jacobian = np.empty((9, 9))
    for i in range(9):
        for j in range(9):
            jacobian[i, j] = (batch[1 + j, i] - batch[0, i]) / steps[j]
    # F P F^T over x, F P_xb (as matrix products, summed in index order)
    f_p = np.zeros((9, 12))
    for i in range(9):
        for k in range(9):
            f = jacobian[i, k]
            for j in range(12):
                f_p[i, j] += f * covariance[k, j]
    for i in range(9):
        for j in range(9):
            s = 0.0
            for k in range(9):
                s += f_p[i, k] * jacobian[j, k]
            out_covariance[i, j] = s
    q_a, q_w = cfg[F_Q_A], cfg[F_Q_W]
    for k in range(3):  # process noise: white acceleration and a spin random walk
        out_covariance[k, k] += q_a * duration**3 / 3.0
        out_covariance[k, 3 + k] += q_a * duration**2 / 2.0
        out_covariance[3 + k, k] += q_a * duration**2 / 2.0
        out_covariance[3 + k, 3 + k] += q_a * duration
        out_covariance[6 + k, 6 + k] += q_w * duration
    out_mean[:] = batch[0]
    if not math.isnan(last_contact):
        for k in range(3):
            out_covariance[3 + k, 3 + k] += cfg[F_BOUNCE_V] ** 2
            out_covariance[6 + k, 6 + k] += cfg[F_BOUNCE_W] ** 2
        unshaped = cfg[F_BIAS_MAGNITUDE] ** 2
        for r in range(3):
            for c in range(12):
                out_covariance[9 + r, c] = 0.0
                out_covariance[c, 9 + r] = 0.0
            out_covariance[9 + r, 9 + r] = unshaped
    else:
        for i in range(9):
            for j in range(3):
                out_covariance[i, 9 + j] = f_p[i, 9 + j]
                out_covariance[9 + j, i] = f_p[i, 9 + j]
        for r in range(3):
            for c in range(3):
                out_covariance[9 + r, 9 + c] = covariance[9 + r, 9 + c]
    return OK, last_contact


@numba.njit(cache=True)
def _kalman_update(mean, covariance, innovation, spin, noise):
    """Schmidt-Kalman update in place: the gain's bias rows are zero; Joseph form (valid for any
    gain). A position sees p (H = [I 0 0 0]); a spin (spin True) sees w + b (H = [0 0 I I])."""
    covariance_h = np.empty((3, 12))  # (P H^T)^T
    for r in range(12):
        for c in range(3):
            covariance_h[c, r] = covariance[r, 6 + c] + covariance[r, 9 + c] if spin else covariance[r, c]
    innovation_covariance = np.empty((3, 3))  # H P H^T + R
    for r in range(3):
        for c in range(3):
            h_p_h = covariance_h[c, 6 + r] + covariance_h[c, 9 + r] if spin else covariance_h[c, r]
            innovation_covariance[r, c] = h_p_h + noise[r, c]
    gain_t = np.empty((3, 12))  # K^T
    _solve3(innovation_covariance, covariance_h, gain_t)
    gain_t[:, 9:] = 0.0
    for r in range(9):
        mean[r] = mean[r] + (gain_t[0, r] * innovation[0] + gain_t[1, r] * innovation[1] + gain_t[2, r] * innovation[2])
    # (I - K H) P (I - K H)^T + K R K^T with (I - K H) P = P - K (H P)
    reduced = np.empty((12, 12))
    for r in range(12):
        for c in range(12):
            reduced[r, c] = covariance[r, c] - (gain_t[0, r] * covariance_h[0, c] + gain_t[1, r] * covariance_h[1, c] + gain_t[2, r] * covariance_h[2, c])
    reduced_h = np.empty((12, 3))  # ((I - K H) P) H^T
    for r in range(12):
        for c in range(3):
            reduced_h[r, c] = reduced[r, 6 + c] + reduced[r, 9 + c] if spin else reduced[r, c]
    gain_noise = np.empty((12, 3))  # K R
    for r in range(12):
        for c in range(3):
            gain_noise[r, c] = gain_t[0, r] * noise[0, c] + gain_t[1, r] * noise[1, c] + gain_t[2, r] * noise[2, c]
    joseph = np.empty((12, 12))
    for r in range(12):
        for c in range(12):
            joseph[r, c] = reduced[r, c] - (reduced_h[r, 0] * gain_t[0, c] + reduced_h[r, 1] * gain_t[1, c] + reduced_h[r, 2] * gain_t[2, c]) \
                + (gain_noise[r, 0] * gain_t[0, c] + gain_noise[r, 1] * gain_t[1, c] + gain_noise[r, 2] * gain_t[2, c])
    for r in range(12):
        for c in range(12):
            covariance[r, c] = 0.5 * (joseph[r, c] + joseph[c, r])


# ------------------------------------------------------------------------------ cores
@numba.njit(cache=True)
def _load(core_f_row, mean, covariance):
    mean[:] = core_f_row[C_MEAN:C_MEAN + 9]
    for r in range(12):
        for c in range(12):
            covariance[r, c] = core_f_row[C_COVARIANCE + 12 * r + c]


@numba.njit(cache=True)
def _store(core_f_row, mean, covariance):
    core_f_row[C_MEAN:C_MEAN + 9] = mean
    for r in range(12):
        for c in range(12):
            core_f_row[C_COVARIANCE + 12 * r + c] = covariance[r, c]


@numba.njit(cache=True)
def empty_core(core_f_row, core_i_row):
    """The core of no track and no history (``FilterCore()``)."""
    core_f_row[:] = 0.0
    core_f_row[C_TIME] = -math.inf
    core_f_row[C_FREE] = -math.inf
    core_f_row[C_SEGMENT] = -math.inf
    core_f_row[C_LAST] = -math.inf
    core_f_row[C_NOT_BEFORE] = -math.inf
    core_i_row[:] = 0


@numba.njit(cache=True)
def _reset(core_f, core_i, not_before):
    """The track dropped (kept: time, last capture, the reset count): FilterCore._reset."""
    core_f[C_FREE] = -math.inf
    core_f[C_SEGMENT] = -math.inf
    core_f[C_NOT_BEFORE] = not_before
    core_i[I_RESETS] += core_i[I_TRACKING]
    core_i[I_TRACKING] = 0
    core_i[I_SPIN_FUSED] = 0
    core_i[I_BIAS_SHAPED] = 0
    core_i[I_POSITIONS] = 0
    core_i[I_SPINS] = 0


@numba.njit(cache=True)
def _fuse_spin(core_f, core_i, spin_f, spin_time, obs_f, offset, cfg, request, result):
    """A spin measurement (its observation row spin_f) fused into the core in place."""
    if spin_time < core_f[C_SEGMENT]:
        return OK  # captured before a contact the track has predicted through: stale
    bias_shaped, segment_start = core_i[I_BIAS_SHAPED], core_f[C_SEGMENT]
    mean, covariance = np.empty(9), np.empty((12, 12))
    if spin_time <= core_f[C_FREE]:
        # Same flight as the posterior: the spin then is the spin now (paper eq. (1)).
        _load(core_f, mean, covariance)
        posterior_time, free_until = core_f[C_TIME], core_f[C_FREE]
    else:
        prior_mean, prior_covariance = np.empty(9), np.empty((12, 12))
        _load(core_f, prior_mean, prior_covariance)
        status, last_contact = predict(prior_mean, prior_covariance, spin_time - core_f[C_TIME], cfg, request, result, mean, covariance)
        if status == BLOCKED:
            return BLOCKED
        posterior_time, free_until = spin_time, spin_time + contact_free_horizon(mean, cfg)
        if not math.isnan(last_contact):
            bias_shaped, segment_start = 0, core_f[C_TIME] + last_contact
    value = spin_f[O_VALUE:O_VALUE + 3]
    if not bias_shaped:
        # The first spin since the bias was drawn: no cross-covariance yet, shape its block.
        bias = np.empty((3, 3))
        _bias_covariance(value, cfg, bias)
        covariance[9:, 9:] = bias
    noise = np.empty((3, 3))
    _noise(spin_f, cfg[F_SPIN_VARIANCE], noise)
    innovation = np.empty(3)
    for k in range(3):
        innovation[k] = value[k] - mean[6 + k]
    _kalman_update(mean, covariance, innovation, True, noise)
    _store(core_f, mean, covariance)
    core_f[C_TIME] = posterior_time
    core_f[C_FREE] = free_until
    core_f[C_SEGMENT] = segment_start
    core_f[C_LAST] = max(core_f[C_LAST], spin_time)
    core_i[I_SPIN_FUSED] = 1
    core_i[I_BIAS_SHAPED] = 1
    return OK


@numba.njit(cache=True)
def _fit_start(positions, obs_f, offset, cfg, out):
    """[p, v] (6,) into out at the last of the start positions (absolute observation numbers
    ``positions``) from a least-squares fit of p + v tau + a tau^2 / 2, a the flight acceleration
    without spin at the fitted velocity (two passes); False if the normalised residual sum exceeds
    its chi-square threshold."""
    n = positions.shape[0]
    last = obs_f[positions[n - 1] - offset]
    tau = np.empty(n)
    measured = np.empty((n, 3))
    for k in range(n):
        row = obs_f[positions[k] - offset]
        tau[k] = row[O_CAPTURE] - last[O_CAPTURE]
        measured[k] = row[O_VALUE:O_VALUE + 3]
    design = np.empty((n, 2))
    design[:, 0] = 1.0
    design[:, 1] = tau
    flight = cfg[F_FLIGHT:]
    a = ball_acceleration(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, flight[0], flight[1], flight[2], flight[3], flight[4], flight[5], flight[6],
                          flight[7], flight[8], flight[9], flight[10])
    solution = np.empty((2, 3))
    target = np.empty((n, 3))
    for _ in range(2):
        for k in range(n):
            for c in range(3):
                target[k, c] = measured[k, c] - 0.5 * tau[k] ** 2 * a[c]
        solution = np.linalg.lstsq(design, target, rcond=-1.0)[0]  # rcond as NumPy's None: eps max(n, 2)
        a = ball_acceleration(solution[1, 0], solution[1, 1], solution[1, 2], 0.0, 0.0, 0.0, flight[0], flight[1], flight[2], flight[3],
                              flight[4], flight[5], flight[6], flight[7], flight[8], flight[9], flight[10])
    normalised = 0.0
    noise = np.empty((3, 3))
    residual = np.empty(3)
    for k in range(n):
        for c in range(3):
            residual[c] = measured[k, c] - (solution[0, c] + tau[k] * solution[1, c]) - 0.5 * tau[k] ** 2 * a[c]
        _noise(obs_f[positions[k] - offset], cfg[F_POSITION_VARIANCE], noise)
        normalised += _quadratic3(noise, residual)
    if normalised > cfg[F_FIT_THRESHOLD]:
        return False
    out[:3] = solution[0]
    out[3:] = solution[1]
    return True


@numba.njit(cache=True)
def _collect(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result):
    """Gathers observations to start a track; starts it when enough positions fit (in place)."""
    count = core_i.shape[0] - I_START - MAX_START_SPINS  # initial_position_count
    spin_column = I_START + count
    gap = cfg[F_GAP]
    time = obs_row_f[O_CAPTURE]
    kept = 0
    for k in range(core_i[I_POSITIONS]):
        number = core_i[I_START + k]
        if time - obs_f[number - offset, O_CAPTURE] <= gap:
            core_i[I_START + kept] = number
            kept += 1
    core_i[I_POSITIONS] = kept
    kept = 0
    for k in range(core_i[I_SPINS]):
        number = core_i[spin_column + k]
        if time - obs_f[number - offset, O_CAPTURE] <= gap:
            core_i[spin_column + kept] = number
            kept += 1
    core_i[I_SPINS] = kept
    core_f[C_LAST] = time
    if obs_row_i[O_KIND] == SPIN:
        if kept == MAX_START_SPINS:
            core_i[spin_column:spin_column + MAX_START_SPINS - 1] = core_i[spin_column + 1:spin_column + MAX_START_SPINS].copy()
            kept -= 1
        core_i[spin_column + kept] = obs_number
        core_i[I_SPINS] = kept + 1
        return OK
    positions = core_i[I_POSITIONS]
    if positions == count:
        core_i[I_START:I_START + count - 1] = core_i[I_START + 1:I_START + count].copy()
        positions -= 1
    core_i[I_START + positions] = obs_number
    core_i[I_POSITIONS] = positions + 1
    if positions + 1 < count:
        return OK
    fitted = np.empty(6)
    if not _fit_start(core_i[I_START:I_START + count].copy(), obs_f, offset, cfg, fitted):
        core_i[I_START:I_START + count - 1] = core_i[I_START + 1:I_START + count].copy()
        core_i[I_POSITIONS] = count - 1
        return OK
    mean = np.zeros(9)
    mean[:6] = fitted
    spins = core_i[spin_column:spin_column + core_i[I_SPINS]].copy()
    _store(core_f, mean, start_covariance)
    core_f[C_TIME] = time
    core_f[C_FREE] = time + contact_free_horizon(mean, cfg)
    core_f[C_SEGMENT] = -math.inf
    core_i[I_TRACKING] = 1
    core_i[I_SPIN_FUSED] = 0
    core_i[I_BIAS_SHAPED] = 0
    core_i[I_POSITIONS] = 0
    core_i[I_SPINS] = 0
    # Spin is constant in flight: the spins captured while the track started measure it now.
    for number in spins:
        spin_f = obs_f[number - offset]
        if _fuse_spin(core_f, core_i, spin_f, spin_f[O_CAPTURE], obs_f, offset, cfg, request, result) == BLOCKED:
            return BLOCKED
    core_f[C_LAST] = time
    return OK


@numba.njit(cache=True)
def _fuse_position(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result):
    time = obs_row_f[O_CAPTURE]
    prior_mean, prior_covariance = np.empty(9), np.empty((12, 12))
    _load(core_f, prior_mean, prior_covariance)
    mean, covariance = np.empty(9), np.empty((12, 12))
    status, last_contact = predict(prior_mean, prior_covariance, time - core_f[C_TIME], cfg, request, result, mean, covariance)
    if status == BLOCKED:
        return BLOCKED
    innovation = np.empty(3)
    for k in range(3):
        innovation[k] = obs_row_f[O_VALUE + k] - mean[k]
    noise = np.empty((3, 3))
    _noise(obs_row_f, cfg[F_POSITION_VARIANCE], noise)
    normalised = _quadratic3(covariance[:3, :3] + noise, innovation)
    # Written as "not within the bounds" so that a non-finite prediction (a diverged track: an
    # absurd velocity through the quadratic drag overflows RK4 to inf and NaN) restarts it too, as
    # does one faster or spinning faster than any ball (``estimate`` gives none for it).
    if not (_norm3(innovation[0], innovation[1], innovation[2]) <= cfg[F_JUMP] and normalised <= cfg[F_INNOVATION]
            and _plausible(mean, cfg)):
        _reset(core_f, core_i, core_f[C_NOT_BEFORE])
        return _collect(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result)
    _kalman_update(mean, covariance, innovation, False, noise)
    _store(core_f, mean, covariance)
    if not math.isnan(last_contact):
        core_f[C_SEGMENT] = core_f[C_TIME] + last_contact
        core_i[I_BIAS_SHAPED] = 0
    core_f[C_TIME] = time
    core_f[C_FREE] = time + contact_free_horizon(mean, cfg)
    core_f[C_LAST] = time
    return OK


@numba.njit(cache=True)
def _process(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result):
    """The core (a copy of the previous one) after one more observation, in place."""
    time = obs_row_f[O_CAPTURE]
    if obs_row_i[O_KIND] == CONTACT:
        _reset(core_f, core_i, time)
        return OK
    if time < core_f[C_NOT_BEFORE]:
        return OK
    if core_i[I_TRACKING] and time - core_f[C_LAST] > cfg[F_GAP]:
        _reset(core_f, core_i, core_f[C_NOT_BEFORE])
    if not core_i[I_TRACKING]:
        return _collect(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result)
    if obs_row_i[O_KIND] == POSITION:
        return _fuse_position(core_f, core_i, obs_row_f, obs_row_i, obs_number, obs_f, offset, cfg, start_covariance, request, result)
    return _fuse_spin(core_f, core_i, obs_row_f, time, obs_f, offset, cfg, request, result)


# ------------------------------------------------------------------------------ batch kernels
@numba.njit(cache=True)
def _row_counts(rows, count):
    """How many of ``rows`` (n,) name each of ``count`` environments (np.bincount)."""
    counts = np.zeros(count, dtype=np.int64)
    for r in rows:
        counts[r] += 1
    return counts


@numba.njit(cache=True)
def _place_measurements(rows, sources, slots, sequence, capture, value, covariance, kind, lag, counts, offset, start, values, kinds):
    """Writes measurement entries (n,) into the observation rows (``place_observations``): entry i,
    the measurement in slot slots[i] of ring sources[i] of the arrays sequence, capture (R, C),
    value (R, C, 3), covariance (R, C, 3, 3), is environment rows[i]'s, after offset[rows[i]] of
    its rows; the entries are grouped by environment, in ascending order."""
    first = np.cumsum(counts) - counts  # each environment's first entry
    for i in range(rows.shape[0]):
        r, source, slot = rows[i], sources[i], slots[i]
        at = start[r] + offset[r] + i - first[r]
        values[at, O_KEY] = capture[source, slot] + lag
        values[at, O_CAPTURE] = capture[source, slot]
        for k in range(3):
            values[at, O_VALUE + k] = value[source, slot, k]
            for m in range(3):
                values[at, O_COVARIANCE + 3 * k + m] = covariance[source, slot, k, m]
        kinds[at, O_KIND] = kind
        kinds[at, O_SEQUENCE] = sequence[source, slot]


@numba.njit(cache=True)
def place_observations(position_rows, position_sources, position_slots, position_sequence, position_capture, position_value, position_covariance,
                       spin_rows, spin_sources, spin_slots, spin_sequence, spin_capture, spin_value, spin_covariance, spin_lag,
                       contact_counts, contact_times):
    """The new observations of B environments (``BallEkf.observation_arrays``) as (values (M, OBS_F),
    kinds (M, OBS_I), start (B + 1,)): environment b's rows start[b]:start[b + 1] are its
    positions, then its spins (keys capture time + spin_lag, s), then its contact_counts[b] (B,)
    racket contacts, each in the order given. Positions and spins as ``_place_measurements``'
    entries; contact_times (sum of contact_counts,), s, environment by environment."""
    count = contact_counts.shape[0]
    position_counts, spin_counts = _row_counts(position_rows, count), _row_counts(spin_rows, count)
    start = np.zeros(count + 1, dtype=np.int64)
    start[1:] = np.cumsum(position_counts + spin_counts + contact_counts)
    values = np.zeros((start[count], OBS_F))
    kinds = np.zeros((start[count], OBS_I), dtype=np.int64)
    _place_measurements(position_rows, position_sources, position_slots, position_sequence, position_capture, position_value, position_covariance,
                        POSITION, 0.0, position_counts, np.zeros(count, dtype=np.int64), start, values, kinds)
    _place_measurements(spin_rows, spin_sources, spin_slots, spin_sequence, spin_capture, spin_value, spin_covariance,
                        SPIN, spin_lag, spin_counts, position_counts, start, values, kinds)
    at = 0
    for b in range(count):
        for k in range(contact_counts[b]):
            row = start[b] + position_counts[b] + spin_counts[b] + k
            values[row, O_KEY] = contact_times[at]  # kind CONTACT (0), sequence 0
            values[row, O_CAPTURE] = contact_times[at]
            at += 1
    return values, kinds, start


@numba.njit(cache=True)
def _key_less_equal(t0, k0, s0, t1, k1, s1):
    """(t0, k0, s0) <= (t1, k1, s1), lexicographically (Python's tuple order)."""
    if t0 != t1:
        return t0 < t1
    if k0 != k1:
        return k0 < k1
    return s0 <= s1


@numba.njit(cache=True)
def merge(old_obs_f, old_obs_i, old_core_f, old_core_i, old_index, old_base_key, new_f, new_i, new_start):
    """New arrays (obs_f, obs_i, core_f, core_i, index, base_key, progress) of the filters: each
    environment's kept observations and cores copied (from index 0), its new observations (rows
    new_start[b]:new_start[b + 1] of new_f, new_i) inserted at their places in processing order,
    those at or before the base's key counted as discarded. progress[b]: the first step to
    (re)process, or -1 when nothing is to be processed."""
    size = old_index.shape[0]
    capacity_obs, capacity_cores = 1, 0  # the most observations kept and steps of any environment
    for b in range(size):
        new = new_start[b + 1] - new_start[b]
        capacity_obs = max(capacity_obs, old_index[b, X_N] - old_index[b, X_KEEP] + new)
        capacity_cores = max(capacity_cores, old_index[b, X_N] - old_index[b, X_FIRST] + new)
    obs_f, obs_i = np.empty((size, capacity_obs, OBS_F)), np.empty((size, capacity_obs, OBS_I), dtype=np.int64)
    core_f = np.empty((size, capacity_cores + 1, CORE_F))
    core_i = np.empty((size, capacity_cores + 1, old_core_i.shape[2]), dtype=np.int64)
    index, base_key, progress = np.empty((size, INDEX_SIZE), dtype=np.int64), np.empty((size, 3)), np.empty(size, dtype=np.int64)
    for b in range(size):
        n_old, first, core0, offset, discarded, keep = old_index[b]
        base_key[b] = old_base_key[b]
        # the new observations in processing order (stable: as listed among equal keys)
        rows = np.arange(new_start[b], new_start[b + 1])
        for a in range(1, rows.shape[0]):
            r = rows[a]
            j = a - 1
            while j >= 0 and not _key_less_equal(new_f[rows[j], O_KEY], new_i[rows[j], O_KIND], new_i[rows[j], O_SEQUENCE], new_f[r, O_KEY], new_i[r, O_KIND], new_i[r, O_SEQUENCE]):
                rows[j + 1] = rows[j]
                j -= 1
            rows[j + 1] = r
        late = 0
        while late < rows.shape[0] and _key_less_equal(new_f[rows[late], O_KEY], new_i[rows[late], O_KIND], new_i[rows[late], O_SEQUENCE], base_key[b, 0], base_key[b, 1], base_key[b, 2]):
            late += 1
        rows = rows[late:]
        # bisect_right among the history's steps [first, n_old)
        start = n_old
        if rows.shape[0]:
            r = rows[0]
            start = first
            while start < n_old and _key_less_equal(old_obs_f[b, start, O_KEY], old_obs_i[b, start, O_KIND], old_obs_i[b, start, O_SEQUENCE], new_f[r, O_KEY], new_i[r, O_KIND], new_i[r, O_SEQUENCE]):
                start += 1
        obs_f[b, :start - keep] = old_obs_f[b, keep:start]
        obs_i[b, :start - keep] = old_obs_i[b, keep:start]
        # the replay: the steps from start on and the new observations, merged (steps first among equal keys)
        out, i, j = start - keep, start, 0
        while i < n_old or j < rows.shape[0]:
            take_old = j == rows.shape[0] or (i < n_old and _key_less_equal(old_obs_f[b, i, O_KEY], old_obs_i[b, i, O_KIND], old_obs_i[b, i, O_SEQUENCE], new_f[rows[j], O_KEY], new_i[rows[j], O_KIND], new_i[rows[j], O_SEQUENCE]))
            if take_old:
                obs_f[b, out] = old_obs_f[b, i]
                obs_i[b, out] = old_obs_i[b, i]
                i += 1
            else:
                obs_f[b, out] = new_f[rows[j]]
                obs_i[b, out] = new_i[rows[j]]
                j += 1
            out += 1
        cores = (start if rows.shape[0] else n_old) - first + 1
        core_f[b, :cores] = old_core_f[b, core0:core0 + cores]
        core_i[b, :cores] = old_core_i[b, core0:core0 + cores]
        index[b, X_N] = out
        index[b, X_FIRST] = first - keep
        index[b, X_CORE0] = 0
        index[b, X_OFFSET] = offset + keep
        index[b, X_DISCARDED] = discarded + late
        index[b, X_KEEP] = 0
        progress[b] = start - keep if rows.shape[0] else -1
    return obs_f, obs_i, core_f, core_i, index, base_key, progress


@numba.njit(cache=True)
def advance(obs_f, obs_i, core_f, core_i, index, base_key, progress, cfg, start_covariance, requests, results, blocked):
    """Processes every environment's steps from progress[b] on, until done (then prunes the
    history to ``history_duration`` s, progress -1) or until a prediction needs ``simulate``
    (blocked[b] True, its request in requests[b]; call again with the result in results[b]).
    Returns how many environments are blocked."""
    blocked_count = 0
    for b in range(index.shape[0]):
        blocked[b] = False
        if progress[b] < 0:
            continue
        n, first, offset = index[b, X_N], index[b, X_FIRST], index[b, X_OFFSET]
        i = progress[b]
        while i < n:
            c = index[b, X_CORE0] + i - first
            core_f[b, c + 1] = core_f[b, c]
            core_i[b, c + 1] = core_i[b, c]
            status = _process(core_f[b, c + 1], core_i[b, c + 1], obs_f[b, i], obs_i[b, i], offset + i, obs_f[b], offset, cfg, start_covariance, requests[b], results[b])
            if status == BLOCKED:
                break
            i += 1
        progress[b] = i
        if i < n:
            blocked[b] = True
            blocked_count += 1
            continue
        progress[b] = -1
        # Keep history_duration s for measurements that come late.
        horizon = obs_f[b, n - 1, O_KEY] - cfg[F_HISTORY]
        pruned = 0
        while pruned < n - first - 1 and obs_f[b, first + pruned, O_KEY] < horizon:
            pruned += 1
        if pruned:
            last = first + pruned - 1
            base_key[b, 0], base_key[b, 1], base_key[b, 2] = obs_f[b, last, O_KEY], obs_i[b, last, O_KIND], obs_i[b, last, O_SEQUENCE]
            index[b, X_FIRST] = first + pruned
            index[b, X_CORE0] += pruned
        keep = index[b, X_FIRST]
        base = index[b, X_CORE0]
        count = core_i.shape[2] - I_START - MAX_START_SPINS
        for k in range(core_i[b, base, I_POSITIONS]):
            keep = min(keep, core_i[b, base, I_START + k] - offset)
        for k in range(core_i[b, base, I_SPINS]):
            keep = min(keep, core_i[b, base, I_START + count + k] - offset)
        index[b, X_KEEP] = keep
    return blocked_count


@numba.njit(cache=True)
def _plausible(mean, cfg):
    """Whether a ball state (9,) is one a ball can have: speed and spin within ``EstimatorParams``'
    max_speed and max_spin (False for NaN)."""
    return (_norm3(mean[3], mean[4], mean[5]) <= cfg[F_MAX_SPEED]
            and _norm3(mean[6], mean[7], mean[8]) <= cfg[F_MAX_SPIN])


@numba.njit(cache=True)
def estimate(core_f, core_i, index, times, cfg, requests, results, pending, means, covariances, status):
    """Predicts each pending environment's latest posterior to times[b] (s) into means (B, 9),
    covariances (B, 9, 9) and status (B, 3) [valid, spin fused, last capture (s)]; pending[b]
    False when done, True when blocked (a request in requests[b], as in ``advance``). An
    environment without a track, or whose prediction is not finite or faster or spinning faster
    than any ball (``EstimatorParams.max_speed``, ``max_spin``: a diverged track), gets valid 0;
    times[b] before the posterior gives valid -1. Returns how many environments are blocked."""
    blocked_count = 0
    for b in range(index.shape[0]):
        if not pending[b]:
            continue
        c = index[b, X_CORE0] + index[b, X_N] - index[b, X_FIRST]
        pending[b] = False
        if not core_i[b, c, I_TRACKING]:
            status[b, 0] = 0.0
            continue
        if times[b] < core_f[b, c, C_TIME]:
            status[b, 0] = -1.0
            continue
        mean, covariance = np.empty(9), np.empty((12, 12))
        _load(core_f[b, c], mean, covariance)
        predicted_mean, predicted_covariance = np.empty(9), np.empty((12, 12))
        result, _ = predict(mean, covariance, times[b] - core_f[b, c, C_TIME], cfg, requests[b], results[b], predicted_mean, predicted_covariance)
        if result == BLOCKED:
            pending[b] = True
            blocked_count += 1
            continue
        # a diverged track: no estimate (its next position restarts it); its covariance, through the
        # finite-difference Jacobian, overflows before its mean does, and a mean can diverge to
        # absurd finite values first (a velocity of 1e24 m/s was seen in training)
        if not (np.all(np.isfinite(predicted_mean)) and np.all(np.isfinite(predicted_covariance[:9, :9]))
                and _plausible(predicted_mean, cfg)):
            status[b, 0] = 0.0
            continue
        means[b] = predicted_mean
        covariances[b] = predicted_covariance[:9, :9]
        status[b, 0] = 1.0
        status[b, 1] = float(core_i[b, c, I_SPIN_FUSED])
        status[b, 2] = core_f[b, c, C_LAST]
    return blocked_count
