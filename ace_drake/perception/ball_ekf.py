"""The ball state estimator: an extended Kalman filter over [p (m), v (m/s), w (rad/s)] in world.

The process model is the project's ball physics: flight (paper eq. (1)) integrated by RK4 and the
table, net and floor impact maps (eqs (2)-(6)), all through ``physics.propagate.simulate``, which
locates contacts inside a step. The authors' filter (notes.md, *Perception*) fixes the initial
variances, the observation variances and the reset rules; the rest is this module's.

Method, in the order a measurement meets it:

- **Jacobians by finite differences.** The prediction propagates the mean and nine perturbed
  copies of it in one batch; the columns of F are the differences. The batch costs about as much
  as the mean alone (the physics is vectorised and its cost is per call), and through a bounce
  the differences carry the contact's saltation (the bounce time moves with the state), which an
  analytic flight Jacobian would need separately. The perturbations are ``finite_difference_step``
  relative (1e-6: truncation and round-off errors near 1e-6 relative; contact times are located
  to 1e-10 s, 1e-4 of the bounce-time shift they cause).
- **Process noise** (continuous white acceleration, a spin random walk, and at a contact the
  paper's post-bounce perturbation as extra velocity and spin variance) is config.
- **Spin is constant in flight** (paper eq. (1)), so a spin measurement is fused into the posterior
  directly, with no prediction (H = [0, 0, I]), whenever no contact lies between its capture time
  and the posterior's: captured before the posterior but after the last contact the track has
  predicted, or after it but sooner than any contact could happen. Otherwise the filter predicts
  to the capture time first, or, for a spin captured before a contact the track has already
  predicted through (the bias re-draws there anyway), ignores it.
- **Bias of the spin sensor as a consider parameter** (Schmidt-Kalman). The gaze-control system's
  accuracy error is the same for every sample between two contacts (paper, *Sensor modelling*):
  averaging many samples does not remove it. The covariance is carried over [x (9), b (3)] with
  spin measurements z = w + b + noise; b itself is never estimated (its gain is zero; the Joseph
  form keeps the covariance right for that suboptimal gain), so the spin's variance cannot fall
  below the bias's. A contact re-draws b; its covariance is shaped by the first spin measurement
  after that, as the sensor's bias is: spin_bias_magnitude_std^2 along the measured axis and
  (|z| spin_bias_axis_std)^2 across it.
- **Late and out-of-order measurements: re-filtering.** Measurements are processed in capture
  time order, spins ``spin_fusion_lag`` s after theirs (their latency varies more than the
  positions'; the spin being constant in flight, fusing one at a slightly later posterior changes
  the result only through the small spin random walk and the linearisation point, and a spin that
  arrives after a position captured a little later then does not make that position's prediction
  run again). The filter keeps every measurement of the last ``history_duration`` s
  with the filter state after it; a measurement that belongs before the newest one processed is
  inserted at its place and the filter runs again from the state just before it. The result is
  identical, bit for bit, to processing everything in that order, whatever the arrival order.
  Older than the history, a measurement is discarded (and counted).
- **Start of a track.** The first ``initial_position_count`` positions within
  ``max_measurement_gap`` are fitted by least squares with the flight acceleration (gravity and
  drag at the fitted velocity) to give position and velocity at the last of them; spin starts at
  zero with ``initial_spin_variance``, then the spins captured meanwhile are fused. A fit whose
  residuals, normalised by the measurements' covariances, exceed the ``initial_fit_confidence``
  chi-square quantile (a bounce inside the window) drops the oldest position.
- **Resets** (notes.md): when the next capture is more than ``max_measurement_gap`` after the
  previous one, when a position is more than ``max_position_jump`` from its prediction, and at a
  racket contact, whose time the caller supplies (the robot knows when it hit; the opponent's hit
  starts an episode): the track restarts from the measurements captured after it. Also when a
  position's normalised innovation squared exceeds ``max_position_innovation``: a contact that
  the prediction got wrong (a net-cord ball decided by millimetres) is not something the filter's
  linearisation can recover from quickly.

**Batches of environments.** The filter's state is arrays (``EkfBatch``, B environments; the
layout is ``perception.ekf_kernels``'), and every step above is a compiled kernel there, run over
all environments at once; only a prediction whose mean could touch the table, net or floor calls
back into ``physics.propagate.simulate`` (or its compiled one-ball twin ``simulate_ball``; all
environments waiting for one are served, then the kernel resumes). ``update_arrays`` /
``update_batch`` / ``estimate_batch`` are the batched API;
``update`` and ``estimate`` are their B = 1 case, and an ``EkfState`` is one row of an EkfBatch.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterable, Sequence

import numpy as np
from scipy import stats

from ace_drake.perception import ekf_kernels as kernels
from ace_drake.perception.ekf_kernels import CONTACT, FREE_HORIZON_MAX, FREE_SPEED_MARGIN, MAX_START_SPINS, POSITION, SPIN  # noqa: F401
from ace_drake.perception.measurements import Measurement
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.flight import flight_constants
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate, simulate_ball

STATE_SIZE = 9
BIAS = slice(9, 12)  # the spin sensor's bias, a consider parameter, in the 12 x 12 covariance
REQUEST_SIZE = 92  # a prediction's batch (10 x 9) and [duration, step] / [present, last contact]
# From this many predictions of one duration and step (10 balls each), one ``simulate`` call costs
# less than ``simulate_ball`` ball by ball (about equal at 50 balls, a third less at 1000).
SIMULATED_TOGETHER = 5


@dataclasses.dataclass(frozen=True)
class Observation:
    """A measurement as the filter processes it, or a racket contact (kind CONTACT).

    capture_time: s. kind: CONTACT, POSITION or SPIN. sequence: the sensor's number (0 for a
    contact). value (3,): m or rad/s; covariance (3, 3): m^2 or (rad/s)^2. lag: s, processed this
    long after its capture time. ``key`` is the processing order: capture time + lag, then
    contact < position < spin, then sequence (the kernels' order, ``ekf_kernels.merge``).
    """

    capture_time: float
    kind: int
    sequence: int
    value: np.ndarray
    covariance: np.ndarray
    lag: float = 0.0
    key: tuple[float, int, int] = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "key", (self.capture_time + self.lag, self.kind, self.sequence))

    @staticmethod
    def of(measurement: Measurement, kind: int, lag: float = 0.0) -> Observation:
        """The observation of a sensor's Measurement (kind POSITION or SPIN)."""
        return Observation(measurement.capture_time, kind, measurement.sequence, measurement.value, measurement.covariance, lag)

    @staticmethod
    def contact(time: float) -> Observation:
        """A racket contact at ``time`` (s)."""
        return Observation(float(time), CONTACT, 0, np.zeros(3), np.zeros((3, 3)))


@dataclasses.dataclass(frozen=True)
class FilterCore:
    """The filter after some observations (read from an EkfBatch; a copy).

    mean (9,) and covariance (12, 12) over [p, v, w, b] at ``time`` (s), or None while a track
    starts. free_until: s, no contact of the mean trajectory before then. segment_start: s, the
    last contact the track has predicted through (-inf: none). last_capture: capture
    time of the last observation used, s. spin_fused: a spin measurement has been fused since the
    track started. bias_shaped: a spin measurement has shaped the bias covariance since the last
    contact. start_positions, start_spins: observations collected to start a track.
    not_before: observations captured earlier are ignored (the last racket contact). resets: how
    many tracks were dropped (gap, jump, racket contact).
    """

    time: float = -math.inf
    mean: np.ndarray | None = None
    covariance: np.ndarray | None = None
    free_until: float = -math.inf
    segment_start: float = -math.inf
    last_capture: float = -math.inf
    spin_fused: bool = False
    bias_shaped: bool = False
    start_positions: tuple[Observation, ...] = ()
    start_spins: tuple[Observation, ...] = ()
    not_before: float = -math.inf
    resets: int = 0

    @property
    def tracking(self) -> bool:
        """Whether a track has started (the mean exists)."""
        return self.mean is not None


@dataclasses.dataclass(frozen=True)
class EkfBatch:
    """The filters of B environments, as arrays (layout: ``perception.ekf_kernels``); immutable
    by convention (every update returns a new one), so that it can live in a Drake Context's
    abstract state.

    obs_f (B, O, 14), obs_i (B, O, 2): observations in processing order. core_f (B, C, 158),
    core_i (B, C, 6 + P + 16): the filter before the history and after each of its steps.
    index (B, 6) int64 and base_key (B, 3): counts and offsets.
    """

    obs_f: np.ndarray
    obs_i: np.ndarray
    core_f: np.ndarray
    core_i: np.ndarray
    index: np.ndarray
    base_key: np.ndarray

    @staticmethod
    def empty(batch: int, initial_position_count: int) -> EkfBatch:
        """B environments with no track and no history."""
        core_f = np.empty((batch, 1, kernels.CORE_F))
        core_i = np.empty((batch, 1, kernels.core_int_size(initial_position_count)), dtype=np.int64)
        for b in range(batch):
            kernels.empty_core(core_f[b, 0], core_i[b, 0])
        base_key = np.zeros((batch, 3))
        base_key[:, 0] = -math.inf
        return EkfBatch(
            np.zeros((batch, 0, kernels.OBS_F)), np.zeros((batch, 0, kernels.OBS_I), dtype=np.int64), core_f, core_i,
            np.zeros((batch, kernels.INDEX_SIZE), dtype=np.int64), base_key,
        )

    @property
    def size(self) -> int:
        """B."""
        return self.index.shape[0]

    def row(self, b: int) -> EkfState:
        """Environment b's filter (a view, no copy)."""
        return EkfState(self, int(b))

    def rows(self) -> tuple[EkfState, ...]:
        """Every environment's filter."""
        return tuple(EkfState(self, b) for b in range(self.size))

    def cleared(self, rows) -> EkfBatch:
        """A copy with the environments ``rows`` (indices) back to no track and no history."""
        rows = np.asarray(rows, dtype=int).reshape(-1)
        index, core_f, core_i, base_key = self.index.copy(), self.core_f.copy(), self.core_i.copy(), self.base_key.copy()
        for b in rows:
            kernels.empty_core(core_f[b, 0], core_i[b, 0])
        index[rows] = 0
        base_key[rows] = (-math.inf, 0.0, 0.0)
        return EkfBatch(self.obs_f, self.obs_i, core_f, core_i, index, base_key)

    @staticmethod
    def stack(states: Sequence[EkfState], initial_position_count: int) -> EkfBatch:
        """One batch of the filters ``states`` (copies of their rows; ``EkfState()`` is empty)."""
        if states and all(s.batch is states[0].batch for s in states) and states[0].batch is not None \
                and states[0].batch.size == len(states) and all(s.row == b for b, s in enumerate(states)):
            return states[0].batch  # already this batch, in order
        parts = [(s.batch, s.row) if s.batch is not None else (EkfBatch.empty(1, initial_position_count), 0) for s in states]
        columns = kernels.core_int_size(initial_position_count)
        for batch, _ in parts:
            if batch.core_i.shape[2] != columns:
                raise ValueError(f"EkfBatch.stack: a state made for {batch.core_i.shape[2] - kernels.I_START - MAX_START_SPINS} start positions, expected {initial_position_count}")
        count = len(parts)
        observations = max([int(batch.index[row, kernels.X_N]) for batch, row in parts] + [0])
        cores = max(int(batch.index[row, kernels.X_CORE0] + batch.index[row, kernels.X_N] - batch.index[row, kernels.X_FIRST]) + 1 for batch, row in parts) if parts else 1
        out = EkfBatch(
            np.zeros((count, observations, kernels.OBS_F)), np.zeros((count, observations, kernels.OBS_I), dtype=np.int64),
            np.zeros((count, cores, kernels.CORE_F)), np.zeros((count, cores, columns), dtype=np.int64),
            np.zeros((count, kernels.INDEX_SIZE), dtype=np.int64), np.zeros((count, 3)),
        )
        for b, (batch, row) in enumerate(parts):
            n = int(batch.index[row, kernels.X_N])
            c = int(batch.index[row, kernels.X_CORE0] + n - batch.index[row, kernels.X_FIRST]) + 1
            out.obs_f[b, :n], out.obs_i[b, :n] = batch.obs_f[row, :n], batch.obs_i[row, :n]
            out.core_f[b, :c], out.core_i[b, :c] = batch.core_f[row, :c], batch.core_i[row, :c]
            out.index[b], out.base_key[b] = batch.index[row], batch.base_key[row]
        return out


@dataclasses.dataclass(frozen=True)
class EkfState:
    """Everything the filter keeps between updates for one environment: row ``row`` of an
    EkfBatch (None: no track and no history); immutable."""

    batch: EkfBatch | None = None
    row: int = 0

    @functools.cached_property
    def latest(self) -> FilterCore:
        """The filter after every observation so far."""
        if self.batch is None:
            return FilterCore()
        index = self.batch.index[self.row]
        return self._core(int(index[kernels.X_CORE0] + index[kernels.X_N] - index[kernels.X_FIRST]))

    @property
    def discarded(self) -> int:
        """Observations that came too late to re-filter."""
        return 0 if self.batch is None else int(self.batch.index[self.row, kernels.X_DISCARDED])

    @property
    def history_length(self) -> int:
        """How many observations the re-filtering history holds."""
        return 0 if self.batch is None else int(self.batch.index[self.row, kernels.X_N] - self.batch.index[self.row, kernels.X_FIRST])

    def _core(self, c: int) -> FilterCore:
        f, i = self.batch.core_f[self.row, c], self.batch.core_i[self.row, c]
        count = i.shape[0] - kernels.I_START - MAX_START_SPINS
        tracking = bool(i[kernels.I_TRACKING])
        return FilterCore(
            time=float(f[kernels.C_TIME]),
            mean=f[kernels.C_MEAN:kernels.C_MEAN + 9].copy() if tracking else None,
            covariance=f[kernels.C_COVARIANCE:].reshape(12, 12).copy() if tracking else None,
            free_until=float(f[kernels.C_FREE]),
            segment_start=float(f[kernels.C_SEGMENT]),
            last_capture=float(f[kernels.C_LAST]),
            spin_fused=bool(i[kernels.I_SPIN_FUSED]),
            bias_shaped=bool(i[kernels.I_BIAS_SHAPED]),
            start_positions=tuple(self._observation(n) for n in i[kernels.I_START:kernels.I_START + i[kernels.I_POSITIONS]]),
            start_spins=tuple(self._observation(n) for n in i[kernels.I_START + count:kernels.I_START + count + i[kernels.I_SPINS]]),
            not_before=float(f[kernels.C_NOT_BEFORE]),
            resets=int(i[kernels.I_RESETS]),
        )

    def _observation(self, number: int) -> Observation:
        k = int(number - self.batch.index[self.row, kernels.X_OFFSET])
        f, i = self.batch.obs_f[self.row, k], self.batch.obs_i[self.row, k]
        capture, key = float(f[kernels.O_CAPTURE]), float(f[kernels.O_KEY])
        observation = Observation(capture, int(i[kernels.O_KIND]), int(i[kernels.O_SEQUENCE]), f[2:5].copy(), f[5:14].reshape(3, 3).copy(), key - capture)
        object.__setattr__(observation, "key", (key, observation.kind, observation.sequence))
        return observation


@dataclasses.dataclass(frozen=True)
class BallEstimate:
    """The filter's estimate at ``time`` (s): mean (9,) [p (m), v (m/s), w (rad/s)], covariance
    (9, 9); spin_valid: a spin measurement is in it; last_capture_time: s, of the newest
    measurement used."""

    time: float
    mean: np.ndarray
    covariance: np.ndarray
    spin_valid: bool
    last_capture_time: float


@dataclasses.dataclass(frozen=True)
class ObservationBatch:
    """New observations of B environments, rows start[b]:start[b + 1] environment b's:
    values (M, 14) [key (s), capture time (s), value (3,), covariance (9,)] and kinds (M, 2)
    [kind, sequence], in the layout of ``perception.ekf_kernels``."""

    values: np.ndarray
    kinds: np.ndarray
    start: np.ndarray


class BallEkf:
    """The extended Kalman filter of this module's docstring. Stateless itself: every method takes
    a state (``EkfState``, or ``EkfBatch`` for B environments) and returns a new one, so one
    instance serves any number of episodes.

    Example::

        ekf = BallEkf()
        state = ekf.update(ekf.initial_state(), positions=new_positions, spins=new_spins)
        estimate = ekf.estimate(state, time=now)  # None until a track has started
        # B environments at once: the same numbers, environment by environment
        batch = ekf.initial_batch(B)
        batch = ekf.update_arrays(batch, ekf.observations(positions_per_env, spins_per_env))
        means, covariances, status = ekf.estimate_batch(batch, times)
    """

    def __init__(self, params: EstimatorParams | None = None, physics: BallPhysicsParams | None = None):
        """Args: params, the filter's settings; physics, the ball model used to predict."""
        self.params = params or EstimatorParams()
        self.physics = physics or BallPhysicsParams()
        p, ph = self.params, self.physics
        # The bias block until a spin measurement shapes it (it has no effect before).
        self._start_covariance = np.diag(
            [p.initial_position_variance] * 3 + [p.initial_velocity_variance] * 3 + [p.initial_spin_variance] * 3 + [0.0] * 3
        )
        self._start_covariance[BIAS, BIAS] = p.spin_bias_magnitude_std**2 * np.eye(3)
        # Fitting p and v to n positions leaves 3 (n - 2) degrees of freedom.
        fit_threshold = float(stats.chi2.ppf(p.initial_fit_confidence, 3 * (p.initial_position_count - 2)))
        config = np.empty(kernels.CONFIG_SIZE)
        config[: kernels.F_FLIGHT] = [
            p.max_measurement_gap, p.max_position_jump, p.max_position_innovation, p.history_duration,
            p.finite_difference_step, p.max_integration_step, p.acceleration_noise_density, p.spin_noise_density,
            p.bounce_velocity_std, p.bounce_spin_std, p.spin_bias_magnitude_std, p.spin_bias_axis_std, fit_threshold,
            math.nan if p.position_observation_variance is None else p.position_observation_variance,
            math.nan if p.spin_observation_variance is None else p.spin_observation_variance,
            ph.aero.ball_radius, ph.table.length, ph.table.width, ph.table.surface_height, ph.net.height, ph.net.overhang,
            p.max_speed, p.max_spin,
        ]
        config[kernels.F_FLIGHT:] = flight_constants(ph.aero)
        self._config = config

    # ------------------------------------------------------------------------------ one environment
    def initial_state(self) -> EkfState:
        """No track and no history."""
        return EkfState()

    def update(
        self,
        state: EkfState,
        positions: Iterable[Measurement] = (),
        spins: Iterable[Measurement] = (),
        racket_contact_times: Iterable[float] = (),
    ) -> EkfState:
        """Fuses new position (m) and spin (rad/s) measurements and racket contacts (s), in any
        order; those captured before the kept history are discarded and counted (see the module
        docstring). Returns the new state (``state`` itself when there is nothing new)."""
        observations = self.observations([tuple(positions)], [tuple(spins)], [tuple(racket_contact_times)])
        if observations.start[-1] == 0:
            return state
        batch = self.update_arrays(EkfBatch.stack([state], self.params.initial_position_count), observations)
        new = batch.row(0)
        if new.history_length == state.history_length and new.discarded > state.discarded:
            new.__dict__["latest"] = state.latest  # all late: the filter is the one before
        return new

    def estimate(self, state: EkfState, time: float) -> BallEstimate | None:
        """The estimate at ``time`` (s), predicted from the latest posterior (not before it), or
        None while no track has started."""
        if state.batch is None:
            return None
        means, covariances, status = self.estimate_batch(EkfBatch.stack([state], self.params.initial_position_count), [time])
        if status[0, 0] == 0.0:
            return None
        return BallEstimate(float(time), means[0], covariances[0], bool(status[0, 1]), float(status[0, 2]))

    def predict(self, mean: np.ndarray, covariance: np.ndarray, duration: float) -> tuple[np.ndarray, np.ndarray, float | None]:
        """The EKF prediction over ``duration`` s of a mean (9,) and covariance (12, 12) over
        [x, b]: RK4 flight and contact maps for the mean, finite-difference Jacobian F, process
        noise; a contact adds the bounce noise and re-draws the spin bias (uncorrelated, to be
        shaped by the next spin measurement). Returns (mean, covariance, the time of the mean's last
        contact in s after the start, or None)."""
        mean = np.array(mean, dtype=float)
        covariance = np.array(covariance, dtype=float)
        if mean.shape != (9,) or covariance.shape != (12, 12):
            raise ValueError(f"BallEkf.predict: mean must be (9,) and covariance (12, 12), got {mean.shape} and {covariance.shape}")
        requests, results = np.zeros((1, REQUEST_SIZE)), np.zeros((1, REQUEST_SIZE))
        out_mean, out_covariance = np.empty(9), np.empty((12, 12))
        for _ in range(2):
            status, last_contact = kernels.predict(mean, covariance, float(duration), self._config, requests[0], results[0], out_mean, out_covariance)
            if status == kernels.OK:
                return out_mean, out_covariance, None if math.isnan(last_contact) else float(last_contact)
            self._simulate_requests(requests, results, [0])
        raise AssertionError("BallEkf.predict: the kernel did not take the simulated prediction")

    # ------------------------------------------------------------------------------ B environments
    def initial_batch(self, batch: int) -> EkfBatch:
        """B environments with no track and no history."""
        return EkfBatch.empty(int(batch), self.params.initial_position_count)

    def observations(
        self,
        positions: Sequence[Sequence[Measurement]],
        spins: Sequence[Sequence[Measurement]],
        racket_contact_times: Sequence[Sequence[float]] | None = None,
    ) -> ObservationBatch:
        """The ObservationBatch of B environments' new positions (m), spins (rad/s) and racket
        contact times (s): one sequence per environment each (None: no contacts)."""
        count = len(positions)
        if len(spins) != count or (racket_contact_times is not None and len(racket_contact_times) != count):
            raise ValueError(f"BallEkf.observations: {count} environments of positions but {len(spins)} of spins"
                             + ("" if racket_contact_times is None else f" and {len(racket_contact_times)} of racket contacts"))

        def arrays(per_environment):
            items = [(b, m) for b in range(count) for m in per_environment[b]]
            return (np.array([b for b, _ in items], dtype=np.int64), np.array([m.sequence for _, m in items], dtype=np.int64),
                    np.array([m.capture_time for _, m in items], dtype=float), np.array([m.value for _, m in items], dtype=float).reshape(-1, 3),
                    np.array([m.covariance for _, m in items], dtype=float).reshape(-1, 3, 3))

        contacts = [()] * count if racket_contact_times is None else racket_contact_times
        return self.observation_arrays(arrays(positions), arrays(spins), contacts)

    def observation_arrays(self, positions, spins, racket_contact_times: Sequence[Sequence[float]]) -> ObservationBatch:
        """``observations`` from arrays: ``positions`` and ``spins`` each (rows (n,) int, sequence
        (n,) int, capture time (n,) s, value (n, 3) m or rad/s, covariance (n, 3, 3)), grouped by
        environment row in ascending order; ``racket_contact_times``: B sequences of times (s).
        Environment b's rows are its positions, then its spins, then its contacts, each in the
        order given (the filter processes them in capture order whatever the order here)."""

        def as_rings(rows, sequence, capture, value, covariance):
            """The entries as rings of one slot each (entry i: slot 0 of ring i)."""
            n = len(rows)
            return (np.asarray(rows, dtype=np.int64), np.arange(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                    np.asarray(sequence, dtype=np.int64).reshape(n, 1), np.asarray(capture, dtype=float).reshape(n, 1),
                    np.asarray(value, dtype=float).reshape(n, 1, 3), np.asarray(covariance, dtype=float).reshape(n, 1, 3, 3))

        return self.observations_of_rings(as_rings(*positions), as_rings(*spins), racket_contact_times)

    def observations_of_rings(self, positions, spins, racket_contact_times: Sequence[Sequence[float]]) -> ObservationBatch:
        """``observation_arrays`` of measurements held in ring arrays (a MeasurementHistoryBatch's,
        read where they are): ``positions`` and ``spins`` each (rows (n,) int, sources (n,) int,
        slots (n,) int, sequence (R, C) int, capture time (R, C) s, value (R, C, 3) m or rad/s,
        covariance (R, C, 3, 3)), entry i environment rows[i]'s measurement in slot slots[i] of
        ring sources[i], grouped by environment row in ascending order
        (``MeasurementHistoryBatch.since_rows`` gives such rows and slots, with sources = rows);
        ``racket_contact_times``: B sequences of times (s). One compiled kernel
        (``ekf_kernels.place_observations``)."""
        counts = np.array([len(times) for times in racket_contact_times], dtype=np.int64)
        times = np.array([float(time) for times in racket_contact_times for time in times], dtype=float)
        values, kinds, start = kernels.place_observations(*positions, *spins, float(self.params.spin_fusion_lag), counts, times)
        return ObservationBatch(values, kinds, start)

    def update_arrays(self, batch: EkfBatch, observations: ObservationBatch) -> EkfBatch:
        """``update`` of every environment: B filters and their new observations (in any order
        within an environment) -> the B filters after them (a new EkfBatch)."""
        if observations.start.shape[0] != batch.size + 1:
            raise ValueError(f"BallEkf.update_arrays: observations for {observations.start.shape[0] - 1} environments, the batch has {batch.size}")
        obs_f, obs_i, core_f, core_i, index, base_key, progress = kernels.merge(
            batch.obs_f, batch.obs_i, batch.core_f, batch.core_i, batch.index, batch.base_key, observations.values, observations.kinds, observations.start
        )
        requests, results = np.zeros((batch.size, REQUEST_SIZE)), np.zeros((batch.size, REQUEST_SIZE))
        blocked = np.zeros(batch.size, dtype=bool)
        while kernels.advance(obs_f, obs_i, core_f, core_i, index, base_key, progress, self._config, self._start_covariance, requests, results, blocked):
            self._simulate_requests(requests, results, np.flatnonzero(blocked))
        return EkfBatch(obs_f, obs_i, core_f, core_i, index, base_key)

    def update_batch(
        self,
        states: Sequence[EkfState],
        positions: Sequence[Sequence[Measurement]],
        spins: Sequence[Sequence[Measurement]],
        racket_contact_times: Sequence[Sequence[float]] | None = None,
    ) -> tuple[EkfState, ...]:
        """``update`` of B environments at once: the same states, environment by environment, as
        B calls of ``update`` (rows of one new EkfBatch)."""
        batch = EkfBatch.stack(list(states), self.params.initial_position_count)
        return self.update_arrays(batch, self.observations(positions, spins, racket_contact_times)).rows()

    def estimate_batch(self, states: EkfBatch | Sequence[EkfState], times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The estimates of B environments at times (B,) s: means (B, 9) [p, v, w],
        covariances (B, 9, 9), status (B, 3) [valid (1 with a track, else 0, and then zeros in
        the mean and covariance), spin valid, capture time of the newest measurement used (s)]."""
        batch = states if isinstance(states, EkfBatch) else EkfBatch.stack(list(states), self.params.initial_position_count)
        size = batch.size
        times = np.asarray(times, dtype=float)
        if times.shape != (size,):
            times = np.broadcast_to(times, (size,)).copy()
        means, covariances, status = np.zeros((size, 9)), np.zeros((size, 9, 9)), np.zeros((size, 3))
        requests, results = np.zeros((size, REQUEST_SIZE)), np.zeros((size, REQUEST_SIZE))
        pending = np.ones(size, dtype=bool)
        while kernels.estimate(batch.core_f, batch.core_i, batch.index, times, self._config, requests, results, pending, means, covariances, status):
            self._simulate_requests(requests, results, np.flatnonzero(pending))
        if status[:, 0].min(initial=0.0) < 0.0:
            b = np.flatnonzero(status[:, 0] < 0.0)[0]
            core = batch.row(b).latest
            raise ValueError(f"BallEkf.estimate: time {times[b]} s is before the posterior's {core.time} s (environment {b})")
        return means, covariances, status

    # ------------------------------------------------------------------------------ contacts
    def _simulate_requests(self, requests: np.ndarray, results: np.ndarray, rows) -> None:
        """Runs the predictions the kernels left in requests[rows] through ``simulate`` (table,
        net and floor contacts located exactly) into results[rows]. Rows asking for the same
        duration and step bit for bit share one ``simulate`` call: its balls are independent (a
        ball's result does not depend on the others'), and a call costs nearly the same for 10
        balls as for 70. Fewer than SIMULATED_TOGETHER rows take ``simulate_ball`` ball by ball
        instead (``simulate``'s compiled loop for one ball, equal to it bit for bit), cheaper for
        few balls."""
        groups: dict[tuple[float, float], list[int]] = {}
        for b in rows:
            groups.setdefault((float(requests[b, 90]), float(requests[b, 91])), []).append(int(b))
        for (duration, step), members in groups.items():
            states = requests[members, :90].reshape(-1, 9)  # 10 states per row, row by row
            if len(members) >= SIMULATED_TOGETHER:
                trajectory = simulate(states, self.physics, duration, dt=step, record=False)
                final_states, events = trajectory.final_state, trajectory.events
            else:
                legs = [simulate_ball(state, self.physics, duration, dt=step) for state in states]
                final_states, events = np.array([leg.final_state[0] for leg in legs]), [leg.events[0] for leg in legs]
            for k, b in enumerate(members):
                results[b, :90] = final_states[10 * k : 10 * (k + 1)].ravel()
                results[b, 90] = 1.0
                mean_events = events[10 * k]  # of the row's first state, the mean
                results[b, 91] = mean_events[-1].time if mean_events else math.nan
