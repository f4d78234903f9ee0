"""The joints' delayed LTI model (paper eq. (9)): construction, exact discretisation, simulation.

Each joint is d/dt zeta = A zeta + b u(t - tau_d), q = c zeta with zeta = [q, q_dot], driven by
the desired position u = q* held constant between the samples of the 1 kHz interface. Sampling
such a system exactly with a delay that is not a whole number of periods (tau_d = k T + f) gives

    zeta[n+1] = Phi zeta[n] + Gamma0 u[n-k] + Gamma1 u[n-k-1],
    Phi = e^{A T}, Gamma0 = int_0^{T-f} e^{A s} ds b, Gamma1 = e^{A (T-f)} int_0^{f} e^{A s} ds b,

which this module evaluates with matrix exponentials and runs through ``scipy.signal.lfilter``.
``JointPropagator`` gives the exact state between samples as well, for the 1 kHz joint plant.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numba
import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, ss2tf

from ace_drake.robot.params import JointDynamicsParams


@dataclasses.dataclass(frozen=True)
class ProcessModel:
    """A second-order process model with input delay: K w^2 / (s^2 + 2 zeta w s + w^2) e^{-tau s}.

    gain K (dimensionless), natural_frequency w (rad/s), damping_ratio zeta, delay tau (s).
    """

    gain: float
    natural_frequency: float
    damping_ratio: float
    delay: float

    def to_state_space(self) -> JointDynamicsParams:
        """The eq. (9) form with q_aux = q_dot: A = [[0, 1], [-w^2, -2 zeta w]], b = [0, K w^2]."""
        w = self.natural_frequency
        return JointDynamicsParams(
            a=(0.0, 1.0, -w * w, -2.0 * self.damping_ratio * w),
            b=(0.0, self.gain * w * w),
            delay=self.delay,
        )

    @staticmethod
    def from_state_space(joint: JointDynamicsParams) -> "ProcessModel":
        """The inverse of ``to_state_space``."""
        w = float(np.sqrt(-joint.a[2]))
        return ProcessModel(gain=joint.b[1] / (w * w), natural_frequency=w, damping_ratio=-joint.a[3] / (2 * w), delay=joint.delay)


def state_matrices(joint: JointDynamicsParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (2, 2), b (2,), c (2,) of paper eq. (9)."""
    return np.reshape(joint.a, (2, 2)), np.asarray(joint.b, dtype=float), np.array([1.0, 0.0])


def ramp_tracking_lag(joint: JointDynamicsParams) -> float:
    """How far behind a constant-velocity command the joint settles, in seconds (unit gain):
    the input delay plus the LTI part's lag -a22 / (-a21) = 2 zeta / w."""
    return joint.delay + joint.a[3] / joint.a[2]


def split_delay(delay: float, period: float) -> tuple[int, float]:
    """tau_d = k T + f: the whole periods k >= 0 and the fraction 0 <= f < T (s) of a delay.

    A delay within 1e-12 periods below a whole number of periods counts as that whole number, so
    that 3 ms at 1 kHz is k = 3, f = 0 despite rounding."""
    k = int(np.floor(delay / period + 1e-12))
    return k, max(delay - k * period, 0.0)


def discretize(joint: JointDynamicsParams, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Exact zero-order-hold sampling with a fractional delay: (Phi, Gamma0, Gamma1, k); see the
    module docstring. ``period`` is T in seconds."""
    if period <= 0:
        raise ValueError(f"discretize: period must be > 0 s, got {period}")
    A, b, _ = state_matrices(joint)
    k, f = split_delay(joint.delay, period)

    def hold(duration: float) -> tuple[np.ndarray, np.ndarray]:
        # expm([[A, b], [0, 0]] t) = [[e^{At}, int_0^t e^{As} ds b], [0, 1]]
        augmented = np.zeros((3, 3))
        augmented[:2, :2] = A
        augmented[:2, 2] = b
        exponential = expm(augmented * duration)
        return exponential[:2, :2], exponential[:2, 2]

    phi, _ = hold(period)
    phi_rest, gamma0 = hold(period - f)
    _, integral_f = hold(f)
    gamma1 = phi_rest @ integral_f
    return phi, gamma0, gamma1, k


class JointPropagator:
    """Exact inter-sample solution of paper eq. (9) for a set of joints.

    Within one command period after a sample, joint i's delayed input u_i(t - tau_i) takes two
    values: u_old on [0, f_i) and u_new from f_i on, where tau_i = k_i T + f_i (``split_delay``).
    With the equilibrium zeta_eq(u) = -A^{-1} b u of a constant input, the solution is

        s <= f:  zeta(s) = zeta_eq(u_old) + e^{A s} (zeta_0 - zeta_eq(u_old)),
        s >  f:  zeta(s) = zeta_eq(u_new) + e^{A (s - f)} (zeta(f) - zeta_eq(u_new)),

    which equals Phi(s) zeta_0 + G(s) u with G(s) = int_0^s e^{A sigma} dsigma b, and at s = T
    ``discretize``'s Phi zeta + Gamma1 u_old + Gamma0 u_new. Writing it about the equilibrium keeps
    a joint at rest exactly at rest and needs only e^{A s} of the 2x2 A, which has the closed form
    (m = tr(A) / 2, omega^2 = det(A) - m^2)

        e^{A s} = e^{m s} (c(s) I + S(s) (A - m I)),
        c = cos(omega s), S = sin(omega s) / omega        (underdamped, omega^2 > 0),
        c = cosh(kappa s), S = sinh(kappa s) / kappa      (overdamped, kappa^2 = -omega^2 > 0),
        c = 1, S = s                                      (critical damping),

    with no ill-conditioned eigenvector matrix to fall back from. A must be invertible (the config
    requires it Hurwitz). The joint plant evaluates this at every output between samples (the
    BallPlant's racket witness asks a few times per millisecond), so the loop over joints is
    compiled (numba): about a microsecond a call against tens for the vectorised NumPy form.
    """

    def __init__(self, joints: Sequence[JointDynamicsParams], period: float):
        """joints: the eq. (9) parameters of each joint; period: the command period T, s."""
        if period <= 0:
            raise ValueError(f"JointPropagator: period must be > 0 s, got {period}")
        self.period = float(period)
        split = [split_delay(joint.delay, period) for joint in joints]
        self.whole_periods = np.array([k for k, _ in split], dtype=int)  # k_i
        self.fractional_delays = np.array([f for _, f in split])  # f_i, s
        A = np.array([state_matrices(joint)[0] for joint in joints])
        b = np.array([state_matrices(joint)[1] for joint in joints])
        self._equilibrium_per_input = np.ascontiguousarray(-np.linalg.solve(A, b[..., None])[..., 0])  # -A^{-1} b, (n, 2)
        self._half_trace = 0.5 * (A[:, 0, 0] + A[:, 1, 1])
        self._A_shifted = np.ascontiguousarray(A - self._half_trace[:, None, None] * np.eye(2))
        self._omega_squared = np.linalg.det(A) - self._half_trace**2

    def propagate(self, zeta: np.ndarray, u_old: np.ndarray, u_new: np.ndarray, elapsed: float) -> np.ndarray:
        """zeta (n, 2) = [q, q_dot] per joint ``elapsed`` seconds after a sample where it was ``zeta``.

        u_old, u_new (n,): the delayed input before and after f_i (rad or m). Exact for any elapsed
        time >= 0 over which the input takes only these two values, i.e. up to T after a sample.
        """
        out = np.empty((self.fractional_delays.size, 2))
        _propagate(
            np.ascontiguousarray(zeta, dtype=float), np.ascontiguousarray(u_old, dtype=float), np.ascontiguousarray(u_new, dtype=float),
            float(elapsed), self.fractional_delays, self._equilibrium_per_input, self._half_trace, self._A_shifted, self._omega_squared, out,
        )
        return out

    def propagate_many(self, zeta: np.ndarray, u_old: np.ndarray, u_new: np.ndarray, elapsed: np.ndarray) -> np.ndarray:
        """``propagate`` for k independent cases at once: zeta (k, n, 2), u_old and u_new (k, n),
        elapsed (k,) s, each in [0, T]. Row i equals ``propagate(zeta[i], u_old[i], u_new[i],
        elapsed[i])`` bit for bit (the same compiled loop, row by row)."""
        zeta = np.ascontiguousarray(zeta, dtype=float)
        u_old = np.ascontiguousarray(u_old, dtype=float)
        u_new = np.ascontiguousarray(u_new, dtype=float)
        elapsed = np.ascontiguousarray(np.broadcast_to(np.asarray(elapsed, dtype=float), zeta.shape[:1]))
        n = self.fractional_delays.size
        if zeta.ndim != 3 or zeta.shape[1:] != (n, 2) or u_old.shape != zeta.shape[:2] or u_new.shape != zeta.shape[:2]:
            raise ValueError(f"JointPropagator.propagate_many: expected zeta (k, {n}, 2) and inputs (k, {n}), got {zeta.shape}, {u_old.shape}, {u_new.shape}")
        out = np.empty_like(zeta)
        _propagate_many(zeta, u_old, u_new, elapsed, self.fractional_delays, self._equilibrium_per_input, self._half_trace, self._A_shifted, self._omega_squared, out)
        return out

    def propagate_samples(self, zeta: np.ndarray, u_old: np.ndarray, u_new: np.ndarray) -> np.ndarray:
        """zeta at every sample of m command periods for B joint sets: zeta (B, n, 2) at the first
        sample, u_old and u_new (B, m, n) each period's two delayed inputs; returns (B, m + 1, n, 2),
        row 0 the start. Each period is ``propagate(..., T)`` from the previous sample, so the
        samples equal the 1 kHz DelayedJointPlant's bit for bit."""
        zeta = np.ascontiguousarray(zeta, dtype=float)
        u_old = np.ascontiguousarray(u_old, dtype=float)
        u_new = np.ascontiguousarray(u_new, dtype=float)
        B, m, n = u_old.shape
        if zeta.shape != (B, n, 2) or u_new.shape != (B, m, n):
            raise ValueError(f"JointPropagator.propagate_samples: expected zeta ({B}, {n}, 2) and inputs ({B}, {m}, {n}), got {zeta.shape}, {u_new.shape}")
        out = np.empty((B, m + 1, n, 2))
        _propagate_samples(zeta, u_old, u_new, self.period, self.fractional_delays, self._equilibrium_per_input, self._half_trace, self._A_shifted, self._omega_squared, out)
        return out


@dataclasses.dataclass(frozen=True)
class JointMotion:
    """The joints' exact motion (paper eq. (9)) over m command periods for B environments: zeta
    (B, m + 1, n, 2) at the samples (row 0 the start), and each period's delayed inputs u_old,
    u_new (B, m, n) (``JointPropagator.propagate``'s), at the propagator's period T."""

    propagator: JointPropagator
    zeta: np.ndarray
    u_old: np.ndarray
    u_new: np.ndarray

    @property
    def states(self) -> np.ndarray:
        """[q, v] at the samples, (B, m + 1, 2 n): rad or m, per s."""
        return np.concatenate([self.zeta[..., 0], self.zeta[..., 1]], axis=-1)

    def state_at(self, rows: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """[q, v] (k, 2 n) of environments ``rows`` (k,) at times ``tau`` (k,) s after the first
        sample, each in [0, m T]: exact between the samples."""
        rows = np.asarray(rows, dtype=int)
        tau = np.asarray(tau, dtype=float)
        period = self.propagator.period
        periods = self.u_old.shape[1]
        index = np.clip(np.floor(tau / period).astype(int), 0, periods - 1)
        zeta = self.propagator.propagate_many(self.zeta[rows, index], self.u_old[rows, index], self.u_new[rows, index], tau - index * period)
        return np.concatenate([zeta[..., 0], zeta[..., 1]], axis=-1)


@numba.njit(cache=True)
def _propagate(zeta, u_old, u_new, elapsed, fractional, equilibrium, half_trace, A_shifted, omega_squared, out):
    """``JointPropagator.propagate`` into ``out`` (n, 2), one joint at a time."""
    for i in range(zeta.shape[0]):
        q, q_dot = zeta[i, 0], zeta[i, 1]
        if elapsed > fractional[i]:
            q, q_dot = _hold(i, q, q_dot, u_old[i], fractional[i], equilibrium, half_trace, A_shifted, omega_squared)
            q, q_dot = _hold(i, q, q_dot, u_new[i], elapsed - fractional[i], equilibrium, half_trace, A_shifted, omega_squared)
        else:
            q, q_dot = _hold(i, q, q_dot, u_old[i], elapsed, equilibrium, half_trace, A_shifted, omega_squared)
        out[i, 0] = q
        out[i, 1] = q_dot


@numba.njit(cache=True)
def _propagate_many(zeta, u_old, u_new, elapsed, fractional, equilibrium, half_trace, A_shifted, omega_squared, out):
    """``JointPropagator.propagate_many`` into ``out`` (k, n, 2)."""
    for row in range(zeta.shape[0]):
        _propagate(zeta[row], u_old[row], u_new[row], elapsed[row], fractional, equilibrium, half_trace, A_shifted, omega_squared, out[row])


@numba.njit(cache=True)
def _propagate_samples(zeta, u_old, u_new, period, fractional, equilibrium, half_trace, A_shifted, omega_squared, out):
    """``JointPropagator.propagate_samples`` into ``out`` (B, m + 1, n, 2): ``_propagate`` over
    each period T in turn, with the two holds' coefficients (``_hold_coefficients`` of f_i and
    T - f_i, the same every period) computed once."""
    n = zeta.shape[1]
    first, second = np.empty((n, 3)), np.empty((n, 3))
    for i in range(n):
        first[i, 0], first[i, 1], first[i, 2] = _hold_coefficients(i, fractional[i], half_trace, omega_squared)
        second[i, 0], second[i, 1], second[i, 2] = _hold_coefficients(i, period - fractional[i], half_trace, omega_squared)
    for row in range(zeta.shape[0]):
        out[row, 0] = zeta[row]
        for sample in range(u_old.shape[1]):
            for i in range(n):
                q, q_dot = out[row, sample, i, 0], out[row, sample, i, 1]
                if period > fractional[i]:
                    q, q_dot = _hold_with(i, q, q_dot, u_old[row, sample, i], first[i, 0], first[i, 1], first[i, 2], equilibrium, A_shifted)
                    q, q_dot = _hold_with(i, q, q_dot, u_new[row, sample, i], second[i, 0], second[i, 1], second[i, 2], equilibrium, A_shifted)
                else:
                    q, q_dot = _hold(i, q, q_dot, u_old[row, sample, i], period, equilibrium, half_trace, A_shifted, omega_squared)
                out[row, sample + 1, i, 0] = q
                out[row, sample + 1, i, 1] = q_dot


@numba.njit(cache=True)
def _hold(i, q, q_dot, u, duration, equilibrium, half_trace, A_shifted, omega_squared):
    """Joint i's zeta_eq(u) + e^{A s} (zeta - zeta_eq(u)) after holding u for s = ``duration``."""
    cosine, sine_over_omega, scale = _hold_coefficients(i, duration, half_trace, omega_squared)
    return _hold_with(i, q, q_dot, u, cosine, sine_over_omega, scale, equilibrium, A_shifted)


@numba.njit(cache=True)
def _hold_coefficients(i, duration, half_trace, omega_squared):
    """Joint i's e^{A s} = scale (cosine I + sine_over_omega (A - m I)) for s = ``duration``
    (class docstring): (cosine, sine_over_omega, scale)."""
    w2 = omega_squared[i]
    if w2 > 0.0:
        omega = math.sqrt(w2)
        cosine, sine_over_omega = math.cos(omega * duration), math.sin(omega * duration) / omega
    elif w2 < 0.0:
        kappa = math.sqrt(-w2)
        cosine, sine_over_omega = math.cosh(kappa * duration), math.sinh(kappa * duration) / kappa
    else:
        cosine, sine_over_omega = 1.0, duration
    return cosine, sine_over_omega, math.exp(half_trace[i] * duration)


@numba.njit(cache=True)
def _hold_with(i, q, q_dot, u, cosine, sine_over_omega, scale, equilibrium, A_shifted):
    """``_hold`` given its coefficients (``_hold_coefficients``)."""
    q_eq = equilibrium[i, 0] * u
    q_dot_eq = equilibrium[i, 1] * u
    d0 = q - q_eq
    d1 = q_dot - q_dot_eq
    s0 = A_shifted[i, 0, 0] * d0 + A_shifted[i, 0, 1] * d1
    s1 = A_shifted[i, 1, 0] * d0 + A_shifted[i, 1, 1] * d1
    return q_eq + scale * (cosine * d0 + sine_over_omega * s0), q_dot_eq + scale * (cosine * d1 + sine_over_omega * s1)


def feedforward_command(joints, q: np.ndarray, q_dot: np.ndarray, q_ddot: np.ndarray) -> np.ndarray:
    """The command that makes eq. (9) follow a desired motion exactly: with q_aux = q_dot the
    second row reads q_ddot = a21 q + a22 q_dot + b2 u(t - tau_d), so the command due at t - tau_d
    is u = (q_ddot - a21 q - a22 q_dot) / b2.

    ``joints``: the joints' JointDynamicsParams (n); q, q_dot, q_ddot: (..., n) desired position,
    velocity and acceleration at time t (rad or m, per s, per s^2). Returns u (..., n), the
    command to issue tau_d earlier, i.e. at t - tau_d,i for joint i.
    """
    a21 = np.array([joint.a[2] for joint in joints])
    a22 = np.array([joint.a[3] for joint in joints])
    b2 = np.array([joint.b[1] for joint in joints])
    return (np.asarray(q_ddot) - a21 * np.asarray(q) - a22 * np.asarray(q_dot)) / b2


def simulate_joint(joint: JointDynamicsParams, command: np.ndarray, period: float) -> np.ndarray:
    """Joint positions q[n] at the sample times for the held command u[n] (rad or m).

    The joint starts at rest at command[0], and the command is taken to have been command[0]
    before the log starts. Returns an array shaped like ``command``.
    """
    command = np.asarray(command, dtype=float)
    if command.ndim != 1 or command.size == 0:
        raise ValueError(f"simulate_joint: command must be a non-empty 1-D array, got shape {command.shape}")
    phi, gamma0, gamma1, k = discretize(joint, period)
    # Augmented state [zeta; u[n-k-1]] driven by w[n] = u[n-k]: one 3-state LTI filter.
    A_d = np.zeros((3, 3))
    A_d[:2, :2] = phi
    A_d[:2, 2] = gamma1
    B_d = np.array([gamma0[0], gamma0[1], 1.0])[:, None]
    C_d = np.array([[1.0, 0.0, 0.0]])
    numerator, denominator = ss2tf(A_d, B_d, C_d, np.zeros((1, 1)))
    start = command[0]
    delayed = np.concatenate([np.full(k, start), command[: command.size - k]]) if k else command
    # Work on deviations from the starting rest state so that the filter starts at zero.
    response = lfilter(numerator[0], denominator, delayed - start)
    return response + start * _dc_gain(joint)


def step_response(joint: JointDynamicsParams, times: np.ndarray, step: float = 1.0) -> np.ndarray:
    """Analytic continuous-time q(t) after a step of ``step`` in q* at t = 0, from rest at 0."""
    A, b, c = state_matrices(joint)
    times = np.asarray(times, dtype=float)
    shifted = np.maximum(times - joint.delay, 0.0)
    # zeta(t) = A^{-1} (e^{A t} - I) b step for t >= tau_d
    A_inverse = np.linalg.inv(A)
    return np.array([step * c @ A_inverse @ (expm(A * t) - np.eye(2)) @ b for t in shifted])


def _dc_gain(joint: JointDynamicsParams) -> float:
    A, b, c = state_matrices(joint)
    return float(-c @ np.linalg.solve(A, b))
