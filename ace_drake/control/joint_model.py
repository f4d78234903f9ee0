"""The joints' delayed LTI model (paper eq. (9)): construction, exact discretisation, simulation.

Each joint is d/dt zeta = A zeta + b u(t - tau_d), q = c zeta with zeta = [q, q_dot], driven by
the desired position u = q* held constant between the samples of the 1 kHz interface. Sampling
such a system exactly with a delay that is not a whole number of periods (tau_d = k T + f) gives

    zeta[n+1] = Phi zeta[n] + Gamma0 u[n-k] + Gamma1 u[n-k-1],
    Phi = e^{A T}, Gamma0 = int_0^{T-f} e^{A s} ds b, Gamma1 = e^{A (T-f)} int_0^{f} e^{A s} ds b,

which this module evaluates with matrix exponentials and runs through ``scipy.signal.lfilter``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, ss2tf

from ace_drake.config import JointDynamicsParams


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


def discretize(joint: JointDynamicsParams, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Exact zero-order-hold sampling with a fractional delay: (Phi, Gamma0, Gamma1, k); see the
    module docstring. ``period`` is T in seconds."""
    if period <= 0:
        raise ValueError(f"discretize: period must be > 0 s, got {period}")
    A, b, _ = state_matrices(joint)
    k = int(np.floor(joint.delay / period + 1e-12))
    f = joint.delay - k * period

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
