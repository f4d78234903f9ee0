"""Evaluating the ball state estimator on simulated shots: truth, sensor streams, replay, figures.

``simulate_shots`` propagates a batch of balls with the project's physics (post-bounce
perturbations on, as in training) and samples the statistical position and spin sensors along each
trajectory exactly as the Drake sensors do (``perception.sensor_models``); ``replay`` feeds one
shot's measurements to a ``BallEkf`` in release order at the estimator's update rate, as the
``BallEstimator`` system does; ``evaluate`` gathers the errors, the normalised estimation error
squared (NEES) and the CPU time per update. The perception benchmark and the estimator's tests
use these. Pure NumPy, no Drake.
"""

from __future__ import annotations

import dataclasses
import time as wall_clock
from collections.abc import Sequence

import numpy as np

from ace_drake.perception.ball_ekf import BallEkf, BallEstimate, EkfState
from ace_drake.perception.measurements import MeasurementHistory
from ace_drake.perception.params import PositionSensorParams, SpinSensorParams
from ace_drake.perception.sensor_models import (
    PendingMeasurement,
    draw_spin_bias,
    first_spin_capture_time,
    insert_pending,
    racket_tracking_loss,
    release_due,
    sample_position_measurements,
    sample_spin_measurements,
    spin_at_times,
    spin_capture_times,
)
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind, simulate

# Random streams under the seed; one generator per shot and stream.
POSITION_STREAM, SPIN_STREAM, BIAS_STREAM, PERTURBATION_STREAM = 11, 12, 13, 14


@dataclasses.dataclass(frozen=True)
class SimulatedShot:
    """One ball's truth and sensor output.

    times (T,) s, on a grid of step dt from 0; states (T, 9) the true [p, v, w] there; events: its
    contacts; positions, spins: the sampled measurements (capture and release times, values,
    covariances), in release order.
    """

    times: np.ndarray
    states: np.ndarray
    events: tuple[ContactEvent, ...]
    positions: tuple[PendingMeasurement, ...]
    spins: tuple[PendingMeasurement, ...]

    def true_state(self, time: float) -> np.ndarray:
        """The true state (9,) at ``time`` (s), which must lie on the grid."""
        step = self.times[1] - self.times[0]
        index = int(round(time / step))
        if abs(index * step - time) > 1e-9 or not 0 <= index < len(self.times):
            raise ValueError(f"SimulatedShot.true_state: {time} s is not on the {step} s grid of [0, {self.times[-1]}]")
        return self.states[index]


def simulate_shots(
    initial_states: np.ndarray,
    duration: float,
    seed: int = 0,
    physics: BallPhysicsParams | None = None,
    position: PositionSensorParams | None = None,
    spin: SpinSensorParams | None = None,
    dt: float = 1e-3,
    perturb: bool = True,
) -> list[SimulatedShot]:
    """Simulates balls from ``initial_states`` (N, 9) for ``duration`` s and samples both sensors.

    The positions are sampled at the triggers (multiples of ``position.trigger_period``, which must
    be a multiple of ``dt``), the spins at their variable-rate capture times, with the spin just
    before any later contact, an accuracy bias per contact interval and the tracking loss after
    racket contacts. ``perturb``: the paper's post-bounce perturbations in the truth. Shot i draws
    from generators seeded [seed, stream, i].
    """
    physics = physics or BallPhysicsParams()
    position = position or PositionSensorParams()
    spin = spin or SpinSensorParams()
    initial_states = np.array(initial_states, dtype=float, ndmin=2)
    steps_per_trigger = position.trigger_period / dt
    if abs(steps_per_trigger - round(steps_per_trigger)) > 1e-9:
        raise ValueError(f"simulate_shots: the trigger period {position.trigger_period} s is not a multiple of dt = {dt} s")
    rng = np.random.default_rng([seed, PERTURBATION_STREAM]) if perturb else None
    trajectory = simulate(initial_states, physics, duration, dt=dt, rng=rng)
    trigger_indices = np.arange(0, len(trajectory.times), int(round(steps_per_trigger)))
    shots = []
    for index in range(initial_states.shape[0]):
        states = trajectory.states[:, index]
        events = tuple(trajectory.events[index])
        position_rng = np.random.default_rng([seed, POSITION_STREAM, index])
        positions = sample_position_measurements(
            states[trigger_indices, :3], trajectory.times[trigger_indices], position, position_rng
        )
        spin_rng = np.random.default_rng([seed, SPIN_STREAM, index])
        captures, _ = spin_capture_times(first_spin_capture_time(0.0, spin, spin_rng), trajectory.times[-1], spin, spin_rng)
        contact_times = np.array([event.time for event in events])
        spins_before = np.array([event.state_pre[6:9] for event in events]).reshape(-1, 3)
        w_WB, intervals = spin_at_times(captures, states[-1, 6:9], contact_times, spins_before)
        bias_rng = np.random.default_rng([seed, BIAS_STREAM, index])
        biases = [draw_spin_bias(spin, bias_rng) for _ in range(len(events) + 1)]
        racket_times = [event.time for event in events if event.kind == ContactKind.RACKET]
        spins = sample_spin_measurements(
            w_WB,
            captures,
            np.array([biases[i].magnitude for i in intervals]),
            np.array([biases[i].rotation_vector for i in intervals]).reshape(-1, 3),
            racket_tracking_loss(captures, racket_times, spin),
            spin,
            spin_rng,
        )
        shots.append(SimulatedShot(trajectory.times, states, events, insert_pending((), positions), insert_pending((), spins)))
    return shots


@dataclasses.dataclass(frozen=True)
class Replay:
    """The result of ``replay``: estimates at the report times (None without a track), the final
    filter state, CPU seconds spent in ``BallEkf.update`` and how many updates fused something."""

    estimates: dict[float, BallEstimate | None]
    final: EkfState
    update_seconds: float
    updates: int


def replay(
    ekf: BallEkf,
    shot: SimulatedShot,
    report_times: Sequence[float],
    update_period: float = 1e-3,
    duration: float | None = None,
) -> Replay:
    """Feeds ``shot``'s measurements to ``ekf`` as the BallEstimator does: every ``update_period``
    s, the measurements released since the last update, for ``duration`` s (default the whole
    shot); estimates at ``report_times`` (s, on the update grid), taken after that instant's
    update."""
    position_history, spin_history = MeasurementHistory(capacity=256), MeasurementHistory(capacity=256)
    position_pending, spin_pending = shot.positions, shot.spins
    state = ekf.initial_state()
    last_position = last_spin = 0
    report_steps = {int(round(t / update_period)): t for t in report_times}
    estimates: dict[float, BallEstimate | None] = {}
    seconds, updates = 0.0, 0
    end = shot.times[-1] if duration is None else min(duration, shot.times[-1])
    for step in range(int(round(end / update_period)) + 1):
        now = step * update_period
        position_history, position_pending = release_due(position_history, position_pending, now)
        spin_history, spin_pending = release_due(spin_history, spin_pending, now)
        positions, spins = position_history.since(last_position), spin_history.since(last_spin)
        last_position, last_spin = position_history.last_sequence, spin_history.last_sequence
        if positions or spins:
            start = wall_clock.perf_counter()
            state = ekf.update(state, positions, spins)
            seconds += wall_clock.perf_counter() - start
            updates += 1
        if step in report_steps:
            estimates[report_steps[step]] = ekf.estimate(state, now)
    return Replay(estimates, state, seconds, updates)


def evaluate(
    ekf: BallEkf,
    shots: Sequence[SimulatedShot],
    report_times: Sequence[float] = (0.05, 0.15),
    update_period: float = 1e-3,
) -> dict:
    """Estimation errors over ``shots`` at each report time (s after the shot's start; each shot is
    replayed up to the last report time).

    Returns {"report_times": {t: {"valid_fraction", "position_error_mean_m", "velocity_error_mean_m_s",
    "velocity_error_p95_m_s", "spin_error_mean_rad_s", "spin_error_p95_rad_s", "nees_mean" (9-d),
    "nees_position_velocity_mean" (6-d), "nees_spin_mean" (3-d)}}, "update_cpu_seconds_mean",
    "updates", "resets", "discarded"}; errors are Euclidean norms over the shots with a track.
    """
    per_time: dict[float, list] = {t: [] for t in report_times}
    seconds, updates, resets, discarded = 0.0, 0, 0, 0
    for shot in shots:
        result = replay(ekf, shot, report_times, update_period, duration=max(report_times))
        seconds += result.update_seconds
        updates += result.updates
        resets += result.final.latest.resets
        discarded += result.final.discarded
        for t in report_times:
            per_time[t].append((result.estimates[t], shot.true_state(t)))
    figures = {}
    for t, pairs in per_time.items():
        rows = []
        for estimate, truth in pairs:
            if estimate is None:
                continue
            error = estimate.mean - truth
            covariance = estimate.covariance
            rows.append(
                [
                    np.linalg.norm(error[:3]),
                    np.linalg.norm(error[3:6]),
                    np.linalg.norm(error[6:9]),
                    error @ np.linalg.solve(covariance, error),
                    error[:6] @ np.linalg.solve(covariance[:6, :6], error[:6]),
                    error[6:] @ np.linalg.solve(covariance[6:, 6:], error[6:]),
                ]
            )
        rows = np.array(rows).reshape(-1, 6)
        valid = rows.shape[0] > 0
        figures[t] = {
            "valid_fraction": rows.shape[0] / max(len(pairs), 1),
            "position_error_mean_m": float(rows[:, 0].mean()) if valid else float("nan"),
            "velocity_error_mean_m_s": float(rows[:, 1].mean()) if valid else float("nan"),
            "velocity_error_p95_m_s": float(np.percentile(rows[:, 1], 95)) if valid else float("nan"),
            "spin_error_mean_rad_s": float(rows[:, 2].mean()) if valid else float("nan"),
            "spin_error_p95_rad_s": float(np.percentile(rows[:, 2], 95)) if valid else float("nan"),
            "nees_mean": float(rows[:, 3].mean()) if valid else float("nan"),
            "nees_position_velocity_mean": float(rows[:, 4].mean()) if valid else float("nan"),
            "nees_spin_mean": float(rows[:, 5].mean()) if valid else float("nan"),
        }
    return {
        "report_times": figures,
        "update_cpu_seconds_mean": seconds / max(updates, 1),
        "updates": updates,
        "resets": resets,
        "discarded": discarded,
    }
