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
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Iterable, Sequence

import numpy as np
from scipy import stats

from ace_drake.perception.measurements import Measurement
from ace_drake.perception.params import EstimatorParams
from ace_drake.physics.flight import flight_acceleration, rk4_step
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import DEFAULT_KINDS, contact_gap, contact_gap_lower_bound, simulate

STATE_SIZE = 9
BIAS = slice(9, 12)  # the spin sensor's bias, a consider parameter, in the 12 x 12 covariance
CONTACT, POSITION, SPIN = 0, 1, 2  # observation kinds, also their order among equal capture times
# Over at most FREE_HORIZON_MAX the ball's speed grows by less than FREE_SPEED_MARGIN: its
# acceleration stays under 250 m/s^2 (drag 140 m/s^2 and Magnus under 70 m/s^2 at 30 m/s, and g),
# so it cannot touch anything sooner than gap / (|v| + margin).
FREE_HORIZON_MAX = 0.02  # s
FREE_SPEED_MARGIN = 5.0  # m/s
MAX_START_SPINS = 16  # spins kept while a track starts


@dataclasses.dataclass(frozen=True)
class Observation:
    """A measurement as the filter processes it, or a racket contact (kind CONTACT).

    capture_time: s. kind: CONTACT, POSITION or SPIN. sequence: the sensor's number (0 for a
    contact). value (3,): m or rad/s; covariance (3, 3): m^2 or (rad/s)^2. lag: s, processed this
    long after its capture time.
    """

    capture_time: float
    kind: int
    sequence: int
    value: np.ndarray
    covariance: np.ndarray
    lag: float = 0.0
    # Processing order: capture time + lag, then contact < position < spin, then sequence. Stored,
    # not a property: the filter compares keys of its whole history at every update.
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
    """The filter after some observations; immutable.

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

    def __deepcopy__(self, memo):  # immutable: Drake's state copies may share it
        return self


@dataclasses.dataclass(frozen=True)
class EkfState:
    """Everything the filter keeps between updates; immutable, so that it can live in a Drake
    Context's abstract state.

    steps: the observations of the last ``history_duration`` s of capture time, in processing
    order, with ``cores``, the filter after each. base: the filter before the first of them;
    base_key: the key of the last observation pruned into it. discarded: observations that came
    too late to re-filter.
    """

    base: FilterCore = dataclasses.field(default_factory=FilterCore)
    base_key: tuple[float, int, int] = (-math.inf, 0, 0)
    steps: tuple[Observation, ...] = ()
    cores: tuple[FilterCore, ...] = ()
    discarded: int = 0

    @property
    def latest(self) -> FilterCore:
        """The filter after every observation so far."""
        return self.cores[-1] if self.cores else self.base

    def __deepcopy__(self, memo):
        return self


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


class BallEkf:
    """The extended Kalman filter of this module's docstring. Stateless itself: every method takes
    an ``EkfState`` and returns a new one, so one instance serves any number of episodes.

    Example::

        ekf = BallEkf()
        state = ekf.update(ekf.initial_state(), positions=new_positions, spins=new_spins)
        estimate = ekf.estimate(state, time=now)  # None until a track has started
    """

    def __init__(self, params: EstimatorParams | None = None, physics: BallPhysicsParams | None = None):
        """Args: params, the filter's settings; physics, the ball model used to predict."""
        self.params = params or EstimatorParams()
        self.physics = physics or BallPhysicsParams()
        p = self.params
        # The bias block until a spin measurement shapes it (it has no effect before).
        self._unshaped_bias_covariance = p.spin_bias_magnitude_std**2 * np.eye(3)
        self._start_covariance = np.diag(
            [p.initial_position_variance] * 3 + [p.initial_velocity_variance] * 3 + [p.initial_spin_variance] * 3 + [0.0] * 3
        )
        self._start_covariance[BIAS, BIAS] = self._unshaped_bias_covariance
        # Fitting p and v to n positions leaves 3 (n - 2) degrees of freedom.
        self._fit_threshold = float(stats.chi2.ppf(p.initial_fit_confidence, 3 * (p.initial_position_count - 2)))
        # What each measurement sees of [x, b] (the columns of H that are I): p; w + b.
        self._position_h = (slice(0, 3),)
        self._spin_h = (slice(6, 9), BIAS)

    # ------------------------------------------------------------------------------ public
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
        docstring). Returns the new state."""
        new = [Observation.of(m, POSITION) for m in positions]
        new += [Observation.of(m, SPIN, self.params.spin_fusion_lag) for m in spins]
        new += [Observation.contact(t) for t in racket_contact_times]
        if not new:
            return state
        new.sort(key=lambda o: o.key)
        late = sum(1 for o in new if o.key <= state.base_key)
        new = new[late:]
        if not new:
            return dataclasses.replace(state, discarded=state.discarded + late)
        keys = [o.key for o in state.steps]
        start = bisect.bisect_right(keys, new[0].key)
        core = state.cores[start - 1] if start > 0 else state.base
        replay = sorted((*state.steps[start:], *new), key=lambda o: o.key)
        steps, cores = list(state.steps[:start]), list(state.cores[:start])
        for observation in replay:
            core = self._process(core, observation)
            steps.append(observation)
            cores.append(core)
        # Keep history_duration s for measurements that come late.
        horizon = steps[-1].key[0] - self.params.history_duration
        pruned = 0
        while pruned < len(steps) - 1 and steps[pruned].key[0] < horizon:
            pruned += 1
        base, base_key = state.base, state.base_key
        if pruned:
            base, base_key = cores[pruned - 1], steps[pruned - 1].key
        return EkfState(base, base_key, tuple(steps[pruned:]), tuple(cores[pruned:]), state.discarded + late)

    def estimate(self, state: EkfState, time: float) -> BallEstimate | None:
        """The estimate at ``time`` (s), predicted from the latest posterior (not before it), or
        None while no track has started."""
        core = state.latest
        if not core.tracking:
            return None
        if time < core.time:
            raise ValueError(f"BallEkf.estimate: time {time} s is before the posterior's {core.time} s")
        mean, covariance, _ = self.predict(core.mean, core.covariance, time - core.time)
        return BallEstimate(float(time), mean, covariance[:STATE_SIZE, :STATE_SIZE], core.spin_fused, core.last_capture)

    def predict(self, mean: np.ndarray, covariance: np.ndarray, duration: float) -> tuple[np.ndarray, np.ndarray, float | None]:
        """The EKF prediction over ``duration`` s of a mean (9,) and covariance (12, 12) over
        [x, b]: RK4 flight and contact maps for the mean, finite-difference Jacobian F, process
        noise; a contact adds the bounce noise and re-draws the spin bias (uncorrelated, to be
        shaped by the next spin measurement). Returns (mean, covariance, the time of the mean's last
        contact in s after the start, or None)."""
        if duration <= 0.0:
            return mean, covariance, None
        params = self.params
        steps = params.finite_difference_step * (1.0 + np.abs(mean))
        batch = np.vstack([mean, mean + np.diag(steps)])
        substeps = max(1, math.ceil(duration / params.max_integration_step - 1e-9))
        step = duration / substeps
        if duration <= self._contact_free_horizon(mean):
            for _ in range(substeps):
                batch = rk4_step(batch, step, self.physics.aero)
            last_contact = None
        else:
            trajectory = simulate(batch, self.physics, duration, dt=step, record=False)
            batch = trajectory.final_state
            last_contact = trajectory.events[0][-1].time if trajectory.events[0] else None
        jacobian = (batch[1:] - batch[0]).T / steps[None, :]
        predicted = np.empty_like(covariance)
        x_x = jacobian @ covariance[:STATE_SIZE, :STATE_SIZE] @ jacobian.T + self._process_noise(duration)
        predicted[:STATE_SIZE, :STATE_SIZE] = x_x
        if last_contact is not None:
            predicted[3:6, 3:6] += params.bounce_velocity_std**2 * np.eye(3)
            predicted[6:9, 6:9] += params.bounce_spin_std**2 * np.eye(3)
            predicted[:STATE_SIZE, BIAS] = 0.0
            predicted[BIAS, :STATE_SIZE] = 0.0
            predicted[BIAS, BIAS] = self._unshaped_bias_covariance
        else:
            x_b = jacobian @ covariance[:STATE_SIZE, BIAS]
            predicted[:STATE_SIZE, BIAS] = x_b
            predicted[BIAS, :STATE_SIZE] = x_b.T
            predicted[BIAS, BIAS] = covariance[BIAS, BIAS]
        return batch[0], predicted, last_contact

    # ------------------------------------------------------------------------------ steps
    def _process(self, core: FilterCore, observation: Observation) -> FilterCore:
        """The filter after one more observation, in capture order."""
        if observation.kind == CONTACT:
            return self._reset(core, observation.capture_time)
        if observation.capture_time < core.not_before:
            return core
        if core.tracking and observation.capture_time - core.last_capture > self.params.max_measurement_gap:
            core = self._reset(core, core.not_before)
        if not core.tracking:
            return self._collect(core, observation)
        if observation.kind == POSITION:
            return self._fuse_position(core, observation)
        return self._fuse_spin(core, observation)

    def _reset(self, core: FilterCore, not_before: float) -> FilterCore:
        return FilterCore(
            time=core.time,
            last_capture=core.last_capture,
            not_before=not_before,
            resets=core.resets + int(core.tracking),
        )

    def _collect(self, core: FilterCore, observation: Observation) -> FilterCore:
        """Gathers observations to start a track; starts it when enough positions fit."""
        gap = self.params.max_measurement_gap
        time = observation.capture_time
        positions = tuple(o for o in core.start_positions if time - o.capture_time <= gap)
        spins = tuple(o for o in core.start_spins if time - o.capture_time <= gap)
        if observation.kind == SPIN:
            spins = (*spins, observation)[-MAX_START_SPINS:]
            return dataclasses.replace(core, start_positions=positions, start_spins=spins, last_capture=time)
        positions = (*positions, observation)[-self.params.initial_position_count :]
        collecting = dataclasses.replace(core, start_positions=positions, start_spins=spins, last_capture=time)
        if len(positions) < self.params.initial_position_count:
            return collecting
        fitted = self._fit_start(positions)
        if fitted is None:
            return dataclasses.replace(collecting, start_positions=positions[1:])
        mean = np.concatenate([fitted, np.zeros(3)])
        started = FilterCore(
            time=time,
            mean=mean,
            covariance=self._start_covariance.copy(),
            free_until=time + self._contact_free_horizon(mean),
            last_capture=time,
            not_before=core.not_before,
            resets=core.resets,
        )
        # Spin is constant in flight: the spins captured while the track started measure it now.
        for spin in spins:
            started = self._fuse_spin(started, spin)
        return dataclasses.replace(started, last_capture=time)

    def _fit_start(self, positions: Sequence[Observation]) -> np.ndarray | None:
        """[p, v] (6,) at the last position from a least-squares fit of p + v tau + a tau^2 / 2,
        a the flight acceleration without spin at the fitted velocity (two passes); None if the
        normalised residual sum exceeds its chi-square threshold."""
        tau = np.array([o.capture_time for o in positions]) - positions[-1].capture_time
        measured = np.array([o.value for o in positions])
        design = np.column_stack([np.ones_like(tau), tau])
        acceleration = flight_acceleration(np.zeros(3), np.zeros(3), self.physics.aero)
        for _ in range(2):
            target = measured - 0.5 * tau[:, None] ** 2 * acceleration[None, :]
            solution, *_ = np.linalg.lstsq(design, target, rcond=None)
            acceleration = flight_acceleration(solution[1], np.zeros(3), self.physics.aero)
        residual = measured - design @ solution - 0.5 * tau[:, None] ** 2 * acceleration[None, :]
        normalised = sum(r @ np.linalg.solve(self._position_noise(o), r) for r, o in zip(residual, positions))
        if normalised > self._fit_threshold:
            return None
        return np.concatenate([solution[0], solution[1]])

    def _fuse_position(self, core: FilterCore, observation: Observation) -> FilterCore:
        time = observation.capture_time
        mean, covariance, last_contact = self.predict(core.mean, core.covariance, time - core.time)
        innovation = observation.value - mean[:3]
        noise = self._position_noise(observation)
        normalised = innovation @ np.linalg.solve(covariance[:3, :3] + noise, innovation)
        if np.linalg.norm(innovation) > self.params.max_position_jump or normalised > self.params.max_position_innovation:
            return self._collect(self._reset(core, core.not_before), observation)
        mean, covariance = self._kalman_update(mean, covariance, innovation, self._position_h, noise)
        return dataclasses.replace(
            core,
            time=time,
            mean=mean,
            covariance=covariance,
            free_until=time + self._contact_free_horizon(mean),
            segment_start=core.segment_start if last_contact is None else core.time + last_contact,
            last_capture=time,
            bias_shaped=core.bias_shaped and last_contact is None,
        )

    def _fuse_spin(self, core: FilterCore, observation: Observation) -> FilterCore:
        time = observation.capture_time
        if time < core.segment_start:
            return core  # captured before a contact the track has predicted through: stale
        bias_shaped, segment_start = core.bias_shaped, core.segment_start
        if time <= core.free_until:
            # Same flight as the posterior: the spin then is the spin now (paper eq. (1)).
            mean, covariance, posterior_time, free_until = core.mean, core.covariance, core.time, core.free_until
        else:
            mean, covariance, last_contact = self.predict(core.mean, core.covariance, time - core.time)
            posterior_time, free_until = time, time + self._contact_free_horizon(mean)
            if last_contact is not None:
                bias_shaped, segment_start = False, core.time + last_contact
        if not bias_shaped:
            # The first spin since the bias was drawn: no cross-covariance yet, shape its block.
            covariance = covariance.copy()
            covariance[BIAS, BIAS] = self._bias_covariance(observation.value)
        noise = self._spin_noise(observation)
        mean, covariance = self._kalman_update(mean, covariance, observation.value - mean[6:9], self._spin_h, noise)
        return dataclasses.replace(
            core,
            time=posterior_time,
            mean=mean,
            covariance=covariance,
            free_until=free_until,
            segment_start=segment_start,
            last_capture=max(core.last_capture, time),
            spin_fused=True,
            bias_shaped=True,
        )

    # ------------------------------------------------------------------------------ maths
    def _kalman_update(self, mean, covariance, innovation, observed, noise):
        """Schmidt-Kalman update: the gain's bias rows are zero; Joseph form (valid for any gain).

        ``observed``: the slices of [x, b] whose sum the measurement sees (H = [I at each]); the
        products with H are these columns and rows, the same numbers as the matrix products."""
        covariance_h = sum(covariance[:, block] for block in observed)  # P H^T
        innovation_covariance = sum(covariance_h[block] for block in observed) + noise  # H P H^T + R
        gain = np.linalg.solve(innovation_covariance, covariance_h.T).T
        gain[BIAS] = 0.0
        mean = mean + gain[:STATE_SIZE] @ innovation
        reduction = np.eye(12)  # I - K H
        for block in observed:
            reduction[:, block] -= gain
        covariance = reduction @ covariance @ reduction.T + gain @ noise @ gain.T
        return mean, 0.5 * (covariance + covariance.T)

    def _bias_covariance(self, spin: np.ndarray) -> np.ndarray:
        """The spin sensor's bias covariance around a measured spin (3,), (rad/s)^2: magnitude
        along its axis, |w| times the axis std across it (as ``spin_precision_covariance``)."""
        rate = float(np.linalg.norm(spin))
        magnitude_variance = self.params.spin_bias_magnitude_std**2
        if rate < 1e-9:
            return magnitude_variance * np.eye(3)
        along = np.outer(spin, spin) / rate**2
        return magnitude_variance * along + (rate * self.params.spin_bias_axis_std) ** 2 * (np.eye(3) - along)

    def _process_noise(self, duration: float) -> np.ndarray:
        """Q over ``duration`` s: white acceleration (position-velocity block) and spin random walk."""
        q_a, q_w = self.params.acceleration_noise_density, self.params.spin_noise_density
        noise = np.zeros((STATE_SIZE, STATE_SIZE))
        eye = np.eye(3)
        noise[0:3, 0:3] = q_a * duration**3 / 3.0 * eye
        noise[0:3, 3:6] = noise[3:6, 0:3] = q_a * duration**2 / 2.0 * eye
        noise[3:6, 3:6] = q_a * duration * eye
        noise[6:9, 6:9] = q_w * duration * eye
        return noise

    def _contact_free_horizon(self, mean: np.ndarray) -> float:
        """How long (s, at most FREE_HORIZON_MAX) the ball at ``mean`` surely touches nothing."""
        # Far from everything (most of a flight) the cheap lower bounds on the gaps already give
        # the maximum; a relative 1e-9 covers their round-off and that of the speed.
        position, velocity = mean[:3].tolist(), mean[3:6].tolist()
        clear = min(contact_gap_lower_bound(kind, position, self.physics) for kind in DEFAULT_KINDS)
        if clear > FREE_HORIZON_MAX * (math.sqrt(sum(v * v for v in velocity)) + FREE_SPEED_MARGIN) * (1.0 + 1e-9):
            return FREE_HORIZON_MAX
        gap = min(float(contact_gap(kind, mean, self.physics)) for kind in DEFAULT_KINDS)
        if gap <= 0.0:
            return 0.0
        return min(FREE_HORIZON_MAX, gap / (float(np.linalg.norm(mean[3:6])) + FREE_SPEED_MARGIN))

    def _position_noise(self, observation: Observation) -> np.ndarray:
        variance = self.params.position_observation_variance
        return observation.covariance if variance is None else variance * np.eye(3)

    def _spin_noise(self, observation: Observation) -> np.ndarray:
        variance = self.params.spin_observation_variance
        return observation.covariance if variance is None else variance * np.eye(3)
