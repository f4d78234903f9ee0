"""B balls through one control segment, every contact located exactly, the racket moving.

The segment-stepped rally (issue 29; DESIGN.md) advances time once per 32 ms control segment; this
is the ball's part of it. ``propagate_segment`` flies B balls over the segment's 1 kHz steps with
the RK4 of ``physics.propagate`` and locates, to 1e-10 s, every table, net and floor contact (as
``propagate.simulate``, with its helpers) and every contact with a racket whose pose changes within
the segment (a ``RacketMotion``: the racket's state at the step times, and exactly at any time in
between). It applies the impact maps of ``physics.contact`` at the contact times, so its contacts
are those of the continuous-time ``systems.ball_plant.BallPlant`` (Drake's error-controlled
integrator, witness-located contacts), which is its reference (tests/test_segment.py).

How the racket is found without evaluating it at every step:

1. Fly every ball over the whole segment (the fast pass), then flag the steps that may hold a
   contact: a static guard that goes from positive to non-positive between two steps, or a step
   the racket screen cannot clear. The screen: the ball's centre and the blade's centre move
   apart or together at most at V = (a bound on the ball's speed over the step) + (a bound on the
   racket's, from its velocity samples and RACKET_ACCELERATION_BOUND), so over a step of h their
   distance stays above (d_0 + d_1 - V h) / 2; while that exceeds the blade's half-diagonal plus
   the ball's radius (``contact.blade_half_diagonal``), the ball cannot touch the blade.
2. Each row's flagged steps are redone one at a time, exactly: static crossings by Illinois on the
   RK4 solution (``propagate.first_contact_time``); the racket by the exact gap
   (``contact.racket_gap``; ball on the RK4 dense solution within the step, racket by
   ``RacketMotion.state_at``) sampled so finely that the ball's centre moves at most
   SUBSAMPLE_TRAVEL (2 mm) relative to the blade between samples, and Illinois on the first bracket
   where the gap goes from positive to non-positive (``propagate.locate_root``). A 1.4 cm blade is
   5.4 cm thick for the ball's centre, so nothing tunnels through it at any relative speed (the
   BallPlant's 1 ms step cap stops tunnelling up to 50 m/s); a touch shallower than about 1 mm
   that starts and ends between two samples can be missed, as between the reference's steps.
3. The earliest contact is applied (a separating racket touch, a graze, and a crossing of the
   table's guard from below are no contact: the state is unchanged), the step continues from it,
   and where a contact changed a row's state, the row's fast pass is redone from that step on.

Post-table perturbations follow the BallPlant's rule: a table contact draws from
``np.random.default_rng([seed, number of this episode's events before it])``. Each row's result
is the same bit for bit whatever the other rows are (row independence), as long as the
``RacketMotion`` evaluates each row independently.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Protocol

import numba
import numpy as np

from ace_drake.physics import contact
from ace_drake.physics.contact import ResidualModel
from ace_drake.physics.flight import POSITION, VELOCITY, flight_constants, rk4_one, rk4_step
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import (
    DEFAULT_KINDS,
    GAP_SCREEN_MARGIN,
    MAX_EVENTS_PER_STEP,
    ContactEvent,
    ContactKind,
    apply_impact,
    contact_constants,
    contact_gap_one,
    first_contact_time,
    guard_gaps,
    is_contact,
    locate_root,
)

# m/s^2 and rad/s^2: bounds on the racket's accelerations between two samples, for the screen
# (a fast robot swing peaks near 100 m/s^2; a bound too low could let a contact be missed).
RACKET_ACCELERATION_BOUND = 2000.0
RACKET_ANGULAR_ACCELERATION_BOUND = 20000.0
SPEED_MARGIN = 0.5  # m/s added to the speed bounds (the RK4 dense solution's rate, round-off)
SUBSAMPLE_TRAVEL = 2e-3  # m, the relative travel between the exact racket-gap samples of a step
MAX_SUBSAMPLES = 512  # per step: 1 km/s of relative speed at 1 ms steps
RACKET = len(DEFAULT_KINDS)  # the racket's index after the static kinds'
_KIND_VALUES = np.array(DEFAULT_KINDS, dtype=np.int64)  # the static kinds as the compiled fast pass takes them


class RacketMotion(Protocol):
    """The racket over one segment, for B environments (R: origin at the blade centre, z along the
    blade normal; DESIGN.md).

    times (n+1,): s after the segment's start, the step times (0, dt, ..., duration).
    p_WR (B, n+1, 3): the blade centre at the step times, m, world.
    R_WR (B, n+1, 3, 3): the racket's orientation at the step times.
    w_WR, v_WR (B, n+1, 3): its spatial velocity at the step times, rad/s and m/s of R's origin.
    state_at(env (k,) int, tau (k,) s in [0, duration]) -> (p (k, 3), R (k, 3, 3), w (k, 3),
        v (k, 3)): the exact state of environment env[i] at tau[i], equal to the samples at the
        step times; each row computed independently of the others.
    """

    times: np.ndarray
    p_WR: np.ndarray
    R_WR: np.ndarray
    w_WR: np.ndarray
    v_WR: np.ndarray

    def state_at(self, env: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...


@dataclasses.dataclass
class SegmentFlight:
    """Result of ``propagate_segment`` for B balls.

    times (n+1,): s after the segment's start; samples (B, n+1, 9): the ball states at those times
    (contacts applied at their exact times before); final (B, 9) = samples[:, -1]; events[i]: ball
    i's contacts in this segment, in order, with absolute times (start_times[i] + tau, s).
    """

    times: np.ndarray
    samples: np.ndarray
    final: np.ndarray
    events: list[list[ContactEvent]]


def segment_times(duration: float, dt: float = 1e-3) -> np.ndarray:
    """The step times (n+1,) of a segment of ``duration`` s in steps of ``dt`` s: 0, dt, ...,
    duration (a last, shorter step when duration is not a multiple of dt)."""
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"segment_times: dt must be a positive number of seconds, got {dt}")
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"segment_times: duration must be a positive number of seconds, got {duration}")
    n_steps = int(np.ceil(duration / dt - 1e-9))
    times = np.minimum(np.arange(n_steps + 1) * dt, duration)
    times[-1] = duration
    return times


def propagate_segment(
    states: np.ndarray,
    start_times: np.ndarray,
    duration: float,
    params: BallPhysicsParams,
    racket: RacketMotion | None = None,
    active: np.ndarray | None = None,
    dt: float = 1e-3,
    perturb_seeds: np.ndarray | None = None,
    event_counts: np.ndarray | None = None,
    residual: ResidualModel | None = None,
) -> SegmentFlight:
    """Flies B balls over one segment with every table, net, floor and racket contact located
    exactly and applied (module docstring).

    Args:
        states: (B, 9) [p (m), v (m/s), w (rad/s)] at the segment's start, world.
        start_times: (B,) s, each environment's time at the segment's start (event times).
        duration: the segment's length, s (32 ms in the rally); dt: the step, s.
        racket: the racket's motion over the segment (``RacketMotion``, times = the step times), or
            None: no racket.
        active: (B,) bool, default all; an inactive row passes through unchanged, with no events
            (its state may be anything, NaN included).
        perturb_seeds: (B,) int, the episodes' seeds of the post-table perturbations, or None: no
            perturbations. event_counts: (B,) int, each episode's number of events before this
            segment (the perturbations' stream), default 0.
        residual: an optional racket contact correction (``contact.racket_impact``).
    """
    states = np.array(states, dtype=float)
    if states.ndim != 2 or states.shape[1] != 9:
        raise ValueError(f"propagate_segment: states must be (B, 9), got {states.shape}")
    n_balls = states.shape[0]
    active = np.ones(n_balls, dtype=bool) if active is None else np.asarray(active)
    if active.shape != (n_balls,) or active.dtype != bool:
        raise ValueError(f"propagate_segment: active must be a bool array ({n_balls},), got {active.dtype} {active.shape}")
    if not np.isfinite(states[active]).all():  # array methods: np.all's dispatch costs more than the test here
        raise ValueError("propagate_segment: states of active rows contain NaN or inf")
    start_times = np.asarray(start_times, dtype=float)
    if start_times.shape != (n_balls,) or not np.isfinite(start_times).all():
        raise ValueError(f"propagate_segment: start_times must be ({n_balls},) finite seconds, got shape {start_times.shape}")
    times, steps = _time_grid(float(duration), float(dt))
    perturb_seeds = None if perturb_seeds is None else _integers("perturb_seeds", perturb_seeds, n_balls)
    event_counts = np.zeros(n_balls, dtype=int) if event_counts is None else _integers("event_counts", event_counts, n_balls)
    if (event_counts < 0).any():
        raise ValueError(f"propagate_segment: event_counts must be >= 0, got {event_counts}")
    if racket is not None:
        _check_racket(racket, times, n_balls)
    run = _Segment(states, start_times, times, steps, params, racket, perturb_seeds, event_counts, residual)
    run.propagate(np.flatnonzero(active))
    return SegmentFlight(times=times, samples=run.samples, final=run.samples[:, -1].copy(), events=run.events)


@functools.lru_cache(maxsize=8)
def _time_grid(duration: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``segment_times`` and ``_steps`` of a segment, read only: computed once per (duration, dt)
    (every tick of a rally asks for the same)."""
    times = segment_times(duration, dt)
    steps = _steps(times)
    times.flags.writeable = steps.flags.writeable = False
    return times, steps


def _physics_constants(params: BallPhysicsParams) -> tuple[np.ndarray, tuple[float, ...], float]:
    """The fast pass's constants of ``params``: ``propagate.contact_constants``,
    ``flight_constants`` and the racket screen's reach (``contact.blade_half_diagonal`` plus the
    ball's radius, m). Kept for the last params object seen (frozen, so the same object has the
    same values; a rally passes the same one every tick)."""
    if _LAST_CONSTANTS[0] is not params:
        reach = contact.blade_half_diagonal(params.racket) + params.aero.ball_radius
        _LAST_CONSTANTS[:] = [params, (contact_constants(params), flight_constants(params.aero), reach)]
    return _LAST_CONSTANTS[1]


_LAST_CONSTANTS: list = [None, None]  # [params, its constants] (``_physics_constants``)


def _integers(name: str, values, n_balls: int) -> np.ndarray:
    values = np.asarray(values)
    if values.shape != (n_balls,) or values.dtype.kind not in "iu":  # signed or unsigned integers
        raise ValueError(f"propagate_segment: {name} must be an integer array ({n_balls},), got {values.dtype} {values.shape}")
    return values.astype(np.int64)


def _check_racket(racket: RacketMotion, times: np.ndarray, n_balls: int) -> None:
    racket_times = np.asarray(racket.times, dtype=float)
    if racket_times.shape != times.shape or not np.abs(racket_times - times).max() <= 1e-12:
        raise ValueError(f"propagate_segment: racket.times must be the step times {times.shape} (0, dt, ..., duration), got {racket_times.shape}")
    expected = {"p_WR": (3,), "R_WR": (3, 3), "w_WR": (3,), "v_WR": (3,)}
    values = [np.asarray(getattr(racket, name)) for name in expected]
    for name, tail, value in zip(expected, expected.values(), values):
        if value.shape != (n_balls, times.size) + tail:
            raise ValueError(f"propagate_segment: racket.{name} must be finite {(n_balls, times.size) + tail}, got {value.shape}")
    if not _all_finite(*values):
        bad = next(name for name, value in zip(expected, values) if not np.all(np.isfinite(value)))
        raise ValueError(f"propagate_segment: racket.{bad} must be finite {values[list(expected).index(bad)].shape}, got NaN or inf")


class _Segment:
    """One call's working state: samples (B, n+1, 9) filled by the fast pass and corrected by the
    exact steps, the events, the racket's per-step speed bounds."""

    def __init__(self, states, start_times, times, steps, params, racket, perturb_seeds, event_counts, residual):
        self.params, self.racket, self.residual = params, racket, residual
        self.times, self.steps = times, steps
        self.start_times, self.perturb_seeds, self.event_counts = start_times, perturb_seeds, event_counts
        self.kinds = DEFAULT_KINDS
        self.radius = params.aero.ball_radius
        gap_constants, flight, self.reach = _physics_constants(params)  # reach: the screen's sphere, m
        self.constants = gap_constants, flight  # the fast pass's
        n_balls, n_steps = states.shape[0], self.steps.size
        self.samples = np.repeat(states[:, None, :], n_steps + 1, axis=1)
        self.events: list[list[ContactEvent]] = [[] for _ in range(n_balls)]
        self.p_WR, self.racket_speed = _NO_RACKET_POSITIONS, _NO_RACKET_SPEEDS  # the fast pass's placeholders without a racket
        if racket is not None:
            p, R, w, v = (np.asarray(a, dtype=float) for a in (racket.p_WR, racket.R_WR, racket.w_WR, racket.v_WR))
            self.p_WR, self.R_WR, self.w_WR, self.v_WR = p, R, w, v
            self.racket_speed = np.empty((n_balls, n_steps))  # m/s
            _speed_bound_rows(v, RACKET_ACCELERATION_BOUND * steps, self.racket_speed)
            self._racket_turn = None  # rad/s, computed when first needed (``racket_turn``)

    # ------------------------------------------------------------------ the passes
    def propagate(self, rows: np.ndarray) -> None:
        """Fast pass for ``rows``, then their flagged steps exactly, in order (module docstring)."""
        n_steps = self.steps.size
        flags = np.zeros((self.samples.shape[0], n_steps), dtype=bool)
        if not self._fast_pass(rows, np.zeros(rows.size, dtype=np.int64), flags):
            return  # nothing flagged: most segments
        cursor = np.full(self.samples.shape[0], n_steps)
        cursor[rows] = 0
        step_index = np.arange(n_steps)
        while True:
            pending = flags & (step_index[None, :] >= cursor[:, None])
            todo = np.flatnonzero(pending.any(axis=1))
            if todo.size == 0:
                return
            k = pending[todo].argmax(axis=1)
            x_end, changed = self._exact_step(todo, k)
            cursor[todo] = k + 1
            redo, k_redo = todo[changed], k[changed] + 1
            if redo.size:
                self.samples[redo, k_redo] = x_end[changed]
                self._fast_pass(redo, k_redo, flags)

    def _fast_pass(self, rows: np.ndarray, first: np.ndarray, flags: np.ndarray) -> bool:
        """RK4 from sample first[i] to the segment's end for each of ``rows``, no contacts, and
        flags[rows] (len(rows), n) the steps that may hold a contact (a static guard crossing, or
        a step the racket screen cannot clear); whether any is flagged. The flight, the guards and
        the racket's distance screen in one compiled call (``_fly_and_flag``); the steps that
        screen cannot clear get the exact gaps at their ends (here, in NumPy) with the gap's rate."""
        near = np.zeros(flags.shape, dtype=bool)
        speed = np.empty(flags.shape)
        gap_constants, flight = self.constants
        flagged, screened = _fly_and_flag(self.samples, rows, first, self.steps, _KIND_VALUES, gap_constants, self.racket is not None,
                                          self.p_WR, self.racket_speed, self.reach, flags, near, speed, *flight)
        if screened:  # the same bound on the exact gaps at the ends, with the gap's rate
            env, k = np.nonzero(near)
            x = self.samples
            g0 = contact.racket_gap(x[env, k, POSITION], self.p_WR[env, k], self.R_WR[env, k], self.params.racket, self.radius)
            g1 = contact.racket_gap(x[env, k + 1, POSITION], self.p_WR[env, k + 1], self.R_WR[env, k + 1], self.params.racket, self.radius)
            exact = 0.5 * (g0 + g1 - self._gap_rate(speed[env, k], env, k) * self.steps[k]) <= GAP_SCREEN_MARGIN
            flags[env[exact], k[exact]] = True
            flagged = flagged or exact.any()
        return bool(flagged)

    @property
    def racket_turn(self) -> np.ndarray:
        """(B, n) rad/s: a bound on the racket's angular speed over each step (``_speed_bound`` of
        its angular velocity samples, with RACKET_ANGULAR_ACCELERATION_BOUND); needed only near the
        blade, so computed on first use."""
        if self._racket_turn is None:
            self._racket_turn = np.empty(self.racket_speed.shape)
            _speed_bound_rows(self.w_WR, RACKET_ANGULAR_ACCELERATION_BOUND * self.steps, self._racket_turn)
        return self._racket_turn

    def _gap_rate(self, speed, env, k):
        """A bound (m/s) on the racket gap's rate over step k of environments env, given the bound
        ``speed`` on the ball's speed plus the blade centre's: the blade's points move at most
        |w| times the half-diagonal faster than its centre."""
        return speed + self.racket_turn[env, k] * (self.reach - self.radius)

    # ------------------------------------------------------------------ one exact step
    def _exact_step(self, rows: np.ndarray, k: np.ndarray):
        """Step k[i] of each of ``rows`` with its contacts located and applied. Returns the states
        at the step's end (len(rows), 9) and whether a contact was located (the state differs from
        the fast pass's)."""
        params = self.params
        t0, h = self.times[k], self.steps[k]
        x = self.samples[rows, k].copy()
        gaps = guard_gaps(x, self.kinds, params)
        remaining, elapsed = h.copy(), np.zeros(rows.size)
        changed = np.zeros(rows.size, dtype=bool)
        for _ in range(MAX_EVENTS_PER_STEP):
            live = np.flatnonzero(remaining > 0.0)
            if live.size == 0:
                break
            x0, h0 = x[live], remaining[live]
            x1 = rk4_step(x0, h0, params.aero)
            gaps1 = guard_gaps(x1, self.kinds, params)
            crossing = (gaps[live] > 0.0) & (gaps1 <= 0.0)
            tau = np.full(live.size, np.inf)
            kind_index = np.zeros(live.size, dtype=int)
            static = np.flatnonzero(crossing.any(axis=-1))
            if static.size:
                tau[static], kind_index[static] = first_contact_time(x0[static], h0[static], crossing[static], self.kinds, params)
            if self.racket is not None:
                tau_racket = self._racket_crossing(rows[live], k[live], x0, x1, h0, t0[live] + elapsed[live], elapsed[live] == 0.0)
                earlier = tau_racket < tau
                tau[earlier], kind_index[earlier] = tau_racket[earlier], RACKET
            free = np.isinf(tau)
            x[live[free]], gaps[live[free]] = x1[free], gaps1[free]
            remaining[live[free]] = 0.0
            hit = np.flatnonzero(~free)
            if hit.size == 0:
                break
            x_pre = rk4_step(x0[hit], tau[hit], params.aero)
            touched = live[hit]
            elapsed[touched] += tau[hit]
            remaining[touched] -= tau[hit]
            changed[touched] = True
            on_racket = kind_index[hit] == RACKET
            if on_racket.any():
                at = touched[on_racket]
                x[at] = self._apply_racket_contacts(rows[at], t0[at] + elapsed[at], x_pre[on_racket])
            for j in np.flatnonzero(~on_racket):
                i = touched[j]
                x[i] = self._apply_static_contact(rows[i], kind_index[hit[j]], t0[i] + elapsed[i], x_pre[j])
            gaps[touched] = guard_gaps(x[touched], self.kinds, params)
        unfinished = np.flatnonzero(remaining > 0.0)  # more than MAX_EVENTS_PER_STEP contacts: fly on
        if unfinished.size:
            x[unfinished] = rk4_step(x[unfinished], remaining[unfinished], params.aero)
        return x, changed

    def _racket_crossing(self, envs, k, x0, x1, h0, t_start, at_sample):
        """The first time (s after t_start; inf if none) within (0, h0] at which each ball's racket
        gap goes from positive to non-positive. x0, x1 (m, 9): the ball at t_start and t_start +
        h0; at_sample: t_start is the sample time times[k]. The gap at t_start is needed only where
        the screens leave the step open, so it is computed only there (each row's gap is the same
        whatever rows it is computed with)."""
        params = self.params
        p_R0, R_R0 = self.p_WR[envs, k].copy(), self.R_WR[envs, k].copy()
        moved = np.flatnonzero(~at_sample)
        if moved.size:
            p_R0[moved], R_R0[moved] = self.racket.state_at(envs[moved], t_start[moved])[:2]
        ball_speed = _speed_bound(np.stack([x0[:, VELOCITY], x1[:, VELOCITY]], axis=1), 0.0)[:, 0]
        speed = ball_speed + self.racket_speed[envs, k]
        d0, d1 = _distances(x0[:, POSITION], p_R0), _distances(x1[:, POSITION], self.p_WR[envs, k + 1])
        tau = np.full(envs.size, np.inf)
        c = np.flatnonzero(0.5 * (d0 + d1 - speed * h0) - self.reach <= GAP_SCREEN_MARGIN)
        if c.size == 0:
            return tau
        # The exact gaps at the ends and the gap's rate: most steps near the blade end here.
        g0 = contact.racket_gap(x0[c, POSITION], p_R0[c], R_R0[c], params.racket, self.radius)
        g1 = contact.racket_gap(x1[c, POSITION], self.p_WR[envs[c], k[c] + 1], self.R_WR[envs[c], k[c] + 1], params.racket, self.radius)
        gap_rate = self._gap_rate(speed[c], envs[c], k[c])
        close = 0.5 * (g0 + g1 - gap_rate * h0[c]) <= GAP_SCREEN_MARGIN
        c, gap_rate, clear0 = c[close], gap_rate[close], g0[close] > 0.0  # clear0: the gap is positive at t_start
        if c.size == 0:
            return tau
        count = np.clip(np.ceil(gap_rate * h0[c] / SUBSAMPLE_TRAVEL), 1, MAX_SUBSAMPLES).astype(int)
        owner = np.repeat(np.arange(c.size), count)
        first = np.cumsum(count) - count
        j = np.arange(owner.size) - first[owner] + 1  # 1 .. count
        last = j == count[owner]
        s = np.where(last, h0[c][owner], h0[c][owner] * j / count[owner])
        balls = rk4_step(x0[c][owner], s, params.aero)
        p_R, R_R = self.p_WR[envs[c], k[c] + 1][owner], self.R_WR[envs[c], k[c] + 1][owner]
        inner = np.flatnonzero(~last)
        if inner.size:
            p_R[inner], R_R[inner] = self.racket.state_at(envs[c][owner[inner]], t_start[c][owner[inner]] + s[inner])[:2]
        positive = contact.racket_gap(balls[:, POSITION], p_R, R_R, params.racket, self.radius) > 0.0
        before = np.where(j == 1, clear0[owner], np.roll(positive, 1))
        crossing = np.flatnonzero(before & ~positive)
        if crossing.size == 0:
            return tau
        found, index = np.unique(owner[crossing], return_index=True)  # each owner's first crossing
        index = crossing[index]
        lower = np.where(j[index] == 1, 0.0, s[index - 1])
        rows = c[found]
        envs_found, start_found = envs[rows], t_start[rows]

        def gap(states, time):
            p, R, _, _ = self.racket.state_at(envs_found, start_found + time)
            return contact.racket_gap(states[:, POSITION], p, R, params.racket, self.radius)

        tau[rows] = locate_root(x0[rows], s[index], gap, params, lower=lower)
        return tau

    def _apply_racket_contacts(self, envs: np.ndarray, tau: np.ndarray, pre: np.ndarray) -> np.ndarray:
        """The states (m, 9) after racket contacts of environments envs (m,) at tau (m,) s after
        the segment's start, from pre (m, 9), recording the impacts; a graze leaves the state.

        ``contact.racket_contact`` on all rows at once gives each row's result bit for bit
        (tests/test_segment.py); a residual model need not (a batched network's sums may depend on
        the batch), so with one the rows go one by one."""
        params = self.params
        p, R, w, v = self.racket.state_at(envs, tau)
        if self.residual is None:
            post, impact = contact.racket_contact(pre, p, R, w, v, params.racket, self.radius)
        else:
            rows = [contact.racket_contact(pre[i], p[i], R[i], w[i], v[i], params.racket, self.radius, residual=self.residual) for i in range(envs.size)]
            post, impact = np.array([row[0] for row in rows]).reshape(-1, 9), np.array([bool(row[1]) for row in rows])
        for i in np.flatnonzero(impact):
            self.events[envs[i]].append(ContactEvent(ContactKind.RACKET, float(self.start_times[envs[i]] + tau[i]), pre[i].copy(), post[i].copy()))
        return post

    def _apply_static_contact(self, env: int, kind_index: int, tau: float, pre: np.ndarray) -> np.ndarray:
        """The state (9,) after environment env's contact of kind kinds[kind_index] at tau s after
        the segment's start, recording the event; unchanged for a crossing that is no contact."""
        params = self.params
        kind = self.kinds[kind_index]
        if not is_contact(kind, pre, params):
            return pre
        rng = None
        if self.perturb_seeds is not None and kind == ContactKind.TABLE:  # the BallPlant's rule
            rng = np.random.default_rng([int(self.perturb_seeds[env]), int(self.event_counts[env]) + len(self.events[env])])
        post = apply_impact(kind, pre, params, rng)
        self.events[env].append(ContactEvent(kind, float(self.start_times[env] + tau), pre.copy(), post.copy()))
        return post


def _steps(times: np.ndarray) -> np.ndarray:
    """The step lengths (n,) s of ``segment_times``: dt itself (as ``propagate.simulate`` steps),
    except a shorter last step."""
    steps = np.full(times.size - 1, times[1] - times[0])
    if times.size > 2 and abs((times[-1] - times[-2]) - steps[0]) > 1e-9 * steps[0]:
        steps[-1] = times[-1] - times[-2]
    return steps


def _speed_bound(velocity: np.ndarray, change: np.ndarray | float) -> np.ndarray:
    """A bound (..., n) on the speed between consecutive samples of ``velocity`` (..., n+1, 3):
    ``_speed_bound_one`` of each pair, plus ``change`` (n,) or a float (an acceleration bound
    times the step)."""
    velocity = np.ascontiguousarray(velocity, dtype=float)
    n = velocity.shape[-2] - 1
    change = np.ascontiguousarray(np.broadcast_to(np.asarray(change, dtype=float), (n,)))
    out = np.empty(velocity.shape[:-2] + (n,))
    _speed_bound_rows(velocity.reshape(-1, n + 1, 3), change, out.reshape(-1, n))
    return out


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| (m,) for points a, b (m, 3) (``_length``)."""
    a, b = np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(b, dtype=float)
    out = np.empty(a.shape[0])
    _distance_rows(a, b, out)
    return out


_NO_RACKET_POSITIONS, _NO_RACKET_SPEEDS = np.zeros((0, 1, 3)), np.zeros((0, 1))  # the fast pass's racket arrays without one


@numba.njit(cache=True)
def _length(x, y, z):
    """|(x, y, z)|."""
    return math.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True)
def _speed_bound_one(v0x, v0y, v0z, v1x, v1y, v1z, change):
    """A bound on the speed between two velocity samples v0, v1 (m/s, or rad/s): the larger end
    speed plus the change between the ends, plus ``change`` (an acceleration bound times the
    step) and SPEED_MARGIN."""
    s0, s1 = _length(v0x, v0y, v0z), _length(v1x, v1y, v1z)
    larger = s0 if s0 >= s1 or math.isnan(s0) else s1  # np.maximum's (a NaN wins)
    return larger + _length(v1x - v0x, v1y - v0y, v1z - v0z) + change + SPEED_MARGIN


@numba.njit(cache=True)
def _speed_bound_rows(velocity, change, out):
    """``_speed_bound`` of velocity (M, n+1, 3) with change (n,) into out (M, n)."""
    for i in range(velocity.shape[0]):
        v = velocity[i]
        for k in range(out.shape[1]):
            out[i, k] = _speed_bound_one(v[k, 0], v[k, 1], v[k, 2], v[k + 1, 0], v[k + 1, 1], v[k + 1, 2], change[k])


@numba.njit(cache=True)
def _all_finite(p_WR, R_WR, w_WR, v_WR):
    """Whether every value of a racket's sample arrays is finite."""
    return np.all(np.isfinite(p_WR)) and np.all(np.isfinite(R_WR)) and np.all(np.isfinite(w_WR)) and np.all(np.isfinite(v_WR))


@numba.njit(cache=True)
def _distance_rows(a, b, out):
    """``_distances`` into out (m,)."""
    for i in range(a.shape[0]):
        out[i] = _length(a[i, 0] - b[i, 0], a[i, 1] - b[i, 1], a[i, 2] - b[i, 2])


@numba.njit(cache=True)
def _fly_and_flag(samples, rows, first, steps, kinds, c, with_racket, p_WR, racket_speed, reach, flags, near, speed,
                  drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale, magnus_scale):
    """``_Segment._fast_pass``' compiled part, in place: for each of ``rows``, samples[row] (n+1, 9)
    from sample first[i] on by RK4 steps (``rk4_trajectory``'s), then flags[row] (n,) the steps
    where a guard of ``kinds`` (ContactKind values; ``propagate.contact_gap_one``, c its constants) goes
    from positive to non-positive, and, with_racket, near[row] the steps the racket's distance
    screen cannot clear: the ball's centre and the blade's (p_WR (B, n+1, 3)) move apart or
    together at most at ``speed`` (the ball's speed bound plus racket_speed (B, n), stored in
    speed[row]), so over a step of h their distance stays above (d_0 + d_1 - speed h) / 2; near
    when that is not above ``reach`` + GAP_SCREEN_MARGIN. Returns (any step flagged, the number
    of near steps)."""
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    positive, positive_next = np.empty(kinds.size, dtype=np.bool_), np.empty(kinds.size, dtype=np.bool_)
    flagged, screened = False, 0
    for i in range(rows.size):
        x = samples[rows[i]]
        for k in range(first[i], steps.size):
            rk4_one(x[k], steps[k], drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                    drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x[k + 1])
        for j in range(kinds.size):
            positive[j] = contact_gap_one(kinds[j], x[0], c) > 0.0
        for k in range(steps.size):
            crossing = False
            for j in range(kinds.size):
                positive_next[j] = contact_gap_one(kinds[j], x[k + 1], c) > 0.0
                crossing = crossing or (positive[j] and not positive_next[j])
            positive[:] = positive_next
            flags[rows[i], k] = crossing
            flagged = flagged or crossing
            if with_racket:
                p0, p1 = p_WR[rows[i], k], p_WR[rows[i], k + 1]
                bound = _speed_bound_one(x[k, 3], x[k, 4], x[k, 5], x[k + 1, 3], x[k + 1, 4], x[k + 1, 5], 0.0) + racket_speed[rows[i], k]
                d0 = _length(x[k, 0] - p0[0], x[k, 1] - p0[1], x[k, 2] - p0[2])
                d1 = _length(x[k + 1, 0] - p1[0], x[k + 1, 1] - p1[1], x[k + 1, 2] - p1[2])
                speed[rows[i], k] = bound
                if 0.5 * (d0 + d1 - bound * steps[k]) - reach <= GAP_SCREEN_MARGIN:
                    near[rows[i], k] = True
                    screened += 1
    return flagged, screened
