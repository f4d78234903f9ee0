"""Fixed-step RK4 propagation of many balls with contact-event location.

``simulate`` integrates a batch of balls with the flight model, locates every table, net and floor
contact inside a step to 1e-10 s (Illinois root finding on the RK4 solution itself) and applies the
impact map there. It is the one propagator used by validation, fitting, prediction and the demos;
the ``BallPlant`` LeafSystem uses the same maps under Drake's integrator and witness functions.
``simulate_ball`` is ``simulate`` of one unperturbed ball compiled (numba), equal to it bit for bit:
for callers that propagate one ball many times per simulated second (the hit prediction, the
training environments' return flights and shot validation: one compiled call per ball is ~4 x
faster than NumPy over a batch of ~100 at 1 ms steps). Both
apply the contact gaps and impact maps of ``contact``, whose one-ball kernels are their only
definition (``simulate`` through the batched functions, ``simulate_ball`` directly).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Iterable, Sequence

import numba
import numpy as np

from ace_drake.physics import contact
from ace_drake.physics.flight import POSITION, SPIN, VELOCITY, flight_constants, rk4_one, rk4_step
from ace_drake.physics.params import BallPhysicsParams

EVENT_TIME_TOLERANCE = 1e-10  # s, width of the final bracket around a contact time
MAX_EVENTS_PER_STEP = 8
GAP_SCREEN_MARGIN = 1e-9  # m, above the lower bounds' round-off (``contact_gap_lower_bound``)


class ContactKind(enum.IntEnum):
    """What the ball touched. TABLE_PLANE is the table's surface extended to infinity (validation)."""

    TABLE = 1
    NET = 2
    FLOOR = 3
    RACKET = 4
    TABLE_PLANE = 5


DEFAULT_KINDS = (ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR)


@dataclasses.dataclass(frozen=True)
class ContactEvent:
    """One contact: its kind, time (s) and the (9,) ball states just before and after it."""

    kind: ContactKind
    time: float
    state_pre: np.ndarray
    state_post: np.ndarray


@dataclasses.dataclass
class Trajectory:
    """Result of ``simulate`` for N balls.

    times (T,) s; states (T, N, 9), the states at the fixed steps (empty if not recorded);
    final_state (N, 9); events[i], ball i's contacts in order; stop_events[i], the contact that
    stopped ball i (a kind in ``stop_on``) or None.
    """

    times: np.ndarray
    states: np.ndarray
    final_state: np.ndarray
    events: list[list[ContactEvent]]
    stop_events: list[ContactEvent | None]


def contact_gap(kind: ContactKind, state: np.ndarray, params: BallPhysicsParams) -> np.ndarray:
    """Guard function of one contact kind, metres: positive in free flight, <= 0 in contact."""
    p_W = state[..., POSITION]
    radius = params.aero.ball_radius
    if kind == ContactKind.TABLE:
        return contact.table_gap(p_W, params.table, radius)
    if kind == ContactKind.TABLE_PLANE:
        return p_W[..., 2] - radius
    if kind == ContactKind.NET:
        return contact.net_gap(p_W, params.table, params.net, radius)
    if kind == ContactKind.FLOOR:
        return contact.floor_gap(p_W, params.table, radius)
    raise ValueError(f"contact_gap: no static guard for {kind!r} (racket contact lives in BallPlant)")


def contact_gap_lower_bound(kind: ContactKind, p_W, params: BallPhysicsParams):
    """A lower bound on ``contact_gap`` in a few float operations, m: for callers that need only
    the gap's sign while the ball is clear, such as the BallPlant's witness functions and
    ``simulate``'s steps (thousands of calls per simulated second). ``p_W``: one ball centre as 3
    floats (a float is returned; the cheapest form for one ball) or centres (..., 3) (an array).

    Table: the height above the playing surface's plane less r (the guard is max(z - r, d)); net:
    the distance from the net's plane x = 0 less r; floor: the floor's gap itself. Exact up to
    round-off (a few 1e-16 m): use it with a margin above that.
    """
    if isinstance(p_W, np.ndarray):
        x, z = p_W[..., 0], p_W[..., 2]
    else:
        x, _, z = p_W
    radius = params.aero.ball_radius
    if kind in (ContactKind.TABLE, ContactKind.TABLE_PLANE):
        return z - radius
    if kind == ContactKind.NET:
        return abs(x) - radius
    if kind == ContactKind.FLOOR:
        return z + params.table.surface_height - radius
    raise ValueError(f"contact_gap_lower_bound: no static guard for {kind!r} (racket contact lives in BallPlant)")


def is_contact(kind: ContactKind, state: np.ndarray, params: BallPhysicsParams) -> bool:
    """Whether a guard crossing of ``kind`` at (9,) ``state`` is a real contact.

    A ball that enters the table's footprint from the side below the playing surface crosses the
    table guard without touching the top: that is not a table contact (the table's sides are not
    modelled). Every other crossing is a contact.
    """
    return _is_contact_one(int(kind), state[2], params.aero.ball_radius)


@numba.njit(cache=True)
def _is_contact_one(kind, z, radius):
    """``is_contact`` for a ContactKind value ``kind`` and the ball centre's height z, m."""
    return not (kind == 1 and z < radius - 1e-6)


def apply_impact(
    kind: ContactKind,
    state: np.ndarray,
    params: BallPhysicsParams,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Post-contact (..., 9) state for a table, net or floor contact at ``state``.

    With ``rng``, a table contact is followed by the paper's Gaussian perturbations of velocity and
    spin (``params.perturbation``); without it everything is deterministic.
    """
    p_W, v_W, w_W = state[..., POSITION], state[..., VELOCITY], state[..., SPIN]
    if kind in (ContactKind.TABLE, ContactKind.TABLE_PLANE):
        v_post, w_post = contact.table_impact(v_W, w_W, params.table, params.aero.ball_radius)
        if rng is not None:
            v_post, w_post = contact.perturb_velocity_and_spin(
                v_post, w_post, params.perturbation.velocity_std, params.perturbation.spin_std, rng
            )
    elif kind == ContactKind.NET:
        v_post, w_post = contact.net_impact(p_W, v_W, w_W, params.table, params.net)
    elif kind == ContactKind.FLOOR:
        v_post, w_post = contact.floor_impact(v_W, w_W, params.floor)
    else:
        raise ValueError(f"apply_impact: no static impact map for {kind!r}")
    return np.concatenate([p_W, v_post, w_post], axis=-1)


def simulate(
    initial_state: np.ndarray,
    params: BallPhysicsParams,
    duration: float,
    dt: float = 1e-3,
    kinds: Sequence[ContactKind] = DEFAULT_KINDS,
    stop_on: Iterable[ContactKind] = (),
    rng: np.random.Generator | None = None,
    record: bool = True,
) -> Trajectory:
    """Propagates balls for ``duration`` seconds with RK4 steps of ``dt``, handling contacts.

    Args:
        initial_state: (9,) or (N, 9) ball states at t = 0.
        kinds: which contacts exist (default table, net and floor).
        stop_on: kinds at which a ball stops: its final state is the state just before that
            contact, recorded in ``stop_events`` (the post-contact state is computed too).
        rng: enables the post-table perturbations; None is deterministic.
        record: keep the (T, N, 9) states at every step (False saves memory for large batches).
    """
    if dt <= 0 or not np.isfinite(dt):
        raise ValueError(f"simulate: dt must be a positive number of seconds, got {dt}")
    if duration < 0:
        raise ValueError(f"simulate: duration must be >= 0, got {duration}")
    x = np.array(initial_state, dtype=float, ndmin=2)
    if x.shape[-1] != 9 or x.ndim != 2:
        raise ValueError(f"simulate: initial_state must be (9,) or (N, 9), got {np.shape(initial_state)}")
    if not np.all(np.isfinite(x)):
        raise ValueError("simulate: initial_state contains NaN or inf")
    kinds = tuple(ContactKind(k) for k in kinds)
    stop_on = frozenset(ContactKind(k) for k in stop_on)
    n_balls = x.shape[0]
    active = np.ones(n_balls, dtype=bool)
    events: list[list[ContactEvent]] = [[] for _ in range(n_balls)]
    stop_events: list[ContactEvent | None] = [None] * n_balls
    n_steps = int(np.ceil(duration / dt - 1e-9))
    times = [0.0]
    states = [x.copy()] if record else []
    t = 0.0
    # The guards' signs at every ball's current state (``guard_gaps``), carried from step to step (a
    # free step's end is the next step's start), recomputed only where a contact changed the state.
    gaps = guard_gaps(x, kinds, params) if kinds else None
    for _ in range(n_steps):
        h = min(dt, duration - t)
        remaining = np.where(active, h, 0.0)
        elapsed = np.zeros(n_balls)
        for _ in range(MAX_EVENTS_PER_STEP):
            rows = np.flatnonzero(remaining > 0.0)
            if rows.size == 0:
                break
            x0, h0 = x[rows], remaining[rows]
            x1 = rk4_step(x0, h0, params.aero)
            if not kinds:
                x[rows], remaining[rows] = x1, 0.0
                break
            gaps0 = gaps[rows]
            gaps1 = guard_gaps(x1, kinds, params)
            crossing = (gaps0 > 0.0) & (gaps1 <= 0.0)
            free = ~crossing.any(axis=-1)
            x[rows[free]] = x1[free]
            gaps[rows[free]] = gaps1[free]
            remaining[rows[free]] = 0.0
            if free.all():
                break
            hit = ~free
            tau, kind_index = first_contact_time(x0[hit], h0[hit], crossing[hit], kinds, params)
            x_pre = rk4_step(x0[hit], tau, params.aero)
            for j, row in enumerate(rows[hit]):
                kind = kinds[kind_index[j]]
                time = t + elapsed[row] + tau[j]
                if not is_contact(kind, x_pre[j], params):
                    x_post = x_pre[j]
                else:
                    x_post = apply_impact(kind, x_pre[j], params, rng)
                    event = ContactEvent(kind, time, x_pre[j].copy(), x_post.copy())
                    events[row].append(event)
                    if kind in stop_on:
                        stop_events[row] = event
                        active[row] = False
                        x[row] = x_pre[j]
                        remaining[row] = 0.0
                        continue
                x[row] = x_post
                remaining[row] -= tau[j]
                elapsed[row] += tau[j]
            gaps[rows[hit]] = guard_gaps(x[rows[hit]], kinds, params)
        t += h
        times.append(t)
        if record:
            states.append(x.copy())
    return Trajectory(
        times=np.asarray(times),
        states=np.asarray(states) if record else np.empty((0, n_balls, 9)),
        final_state=x,
        events=events,
        stop_events=stop_events,
    )


def guard_gaps(states: np.ndarray, kinds: Sequence[ContactKind], params: BallPhysicsParams) -> np.ndarray:
    """The guards of every kind for (N, 9) states, (N, len(kinds)), m, where callers read
    only their signs: each is ``contact_gap``, or, for a kind every ball is clearly clear of, its
    lower bound (``contact_gap_lower_bound`` above GAP_SCREEN_MARGIN), which has the same sign at a
    fraction of the cost (most steps of a flight)."""
    gaps = np.empty((states.shape[0], len(kinds)))
    for k, kind in enumerate(kinds):
        bound = contact_gap_lower_bound(kind, states[:, POSITION], params)
        gaps[:, k] = bound if (bound > GAP_SCREEN_MARGIN).all() else contact_gap(kind, states, params)
    return gaps


def first_contact_time(x0, h, crossing, kinds, params):
    """Earliest contact time tau (M,) s within each ball's step, and the index (M,) of its kind in
    ``kinds``, for balls x0 (M, 9) with steps h (M,) s whose guards ``crossing`` (M, len(kinds))
    bool go from positive to non-positive over the step: ``locate_root`` on each, ties to the
    earlier kind. Compiled, ball by ball (``_first_contact_rows``: ``_locate_root_one`` is
    ``locate_root``'s iteration operation for operation, and its rows are independent)."""
    x0 = np.ascontiguousarray(x0, dtype=float)
    tau, kind_index = np.empty(x0.shape[0]), np.empty(x0.shape[0], dtype=np.int64)
    _first_contact_rows(x0, np.ascontiguousarray(h, dtype=float), np.ascontiguousarray(crossing, dtype=np.bool_),
                        np.array([int(kind) for kind in kinds], dtype=np.int64), contact_constants(params), *flight_constants(params.aero),
                        tau, kind_index)
    return tau, kind_index


def locate_root(x0, h, gap, params, max_iterations: int = 100, lower=None):
    """A tau in (lower, h] with gap(rk4(x0, tau), tau) <= 0 at the end of the first crossing,
    given gap > 0 at ``lower`` (default 0) and <= 0 at h; for each of the M rows of x0 (M, 9),
    h (M,), lower (M,) (s). ``gap(states (M, 9), tau (M,))`` is the guard, m; tau lets a guard
    depend on time (a moving racket, ``physics.segment``).

    Illinois (modified regula falsi) on the RK4 dense solution: superlinear on smooth guards, and
    it keeps a bracket, so the piecewise guards (table edge, net cord) are safe. Returns the
    bracket's right end (the contact side) once the bracket is narrower than 1e-10 s. Rows are
    independent: a row's result does not depend on the others (a closed bracket stays put).
    """
    if lower is None:
        a = np.zeros_like(h)
        g_a = gap(x0, a)
    else:
        a = np.array(lower, dtype=float)
        g_a = gap(rk4_step(x0, a, params.aero), a)
    b = h.copy()
    g_b = gap(rk4_step(x0, b, params.aero), b)
    last_side = np.zeros_like(h, dtype=int)
    for _ in range(max_iterations):
        open_rows = (b - a) > EVENT_TIME_TOLERANCE
        if not open_rows.any():
            break
        denominator = g_a - g_b
        c = np.where(denominator > 0, b + g_b * (b - a) / np.where(denominator > 0, denominator, 1.0), 0.5 * (a + b))
        # Keep the trial strictly inside the bracket; fall back to bisection at the ends.
        c = np.where((c <= a) | (c >= b), 0.5 * (a + b), c)
        g_c = gap(rk4_step(x0, c, params.aero), c)
        move_a = open_rows & (g_c > 0.0)
        move_b = open_rows & ~(g_c > 0.0)
        g_b = np.where(move_a & (last_side == 1), 0.5 * g_b, g_b)  # Illinois: halve the stale end
        g_a = np.where(move_b & (last_side == -1), 0.5 * g_a, g_a)
        a = np.where(move_a, c, a)
        g_a = np.where(move_a, g_c, g_a)
        b = np.where(move_b, c, b)
        g_b = np.where(move_b, g_c, g_b)
        last_side = np.where(move_a, 1, np.where(move_b, -1, last_side))
        # A trial that lands on the guard within 1e-13 m closes the bracket at once.
        exact = move_b & (g_c > -1e-13)
        a = np.where(exact, np.maximum(a, c - EVENT_TIME_TOLERANCE), a)
    return b


# ------------------------------------------------------------------------------------------------
# One ball, compiled
# ------------------------------------------------------------------------------------------------


def simulate_ball(
    initial_state: np.ndarray,
    params: BallPhysicsParams,
    duration: float,
    dt: float = 1e-3,
    kinds: Sequence[ContactKind] = DEFAULT_KINDS,
    stop_on: Iterable[ContactKind] = (),
) -> Trajectory:
    """``simulate`` of one ball (9,) without perturbations (``rng`` None), recording every step:
    the same Trajectory (N = 1), bit for bit (tests/test_physics.py), from one compiled call
    (``_simulate_ball``: ``simulate``'s loop in the same order, with the same ``contact`` kernels
    for the gaps and impact maps) instead of NumPy calls per step and per root-finding iteration.
    ``kinds``: any of TABLE, TABLE_PLANE, NET and FLOOR."""
    if dt <= 0 or not np.isfinite(dt):
        raise ValueError(f"simulate_ball: dt must be a positive number of seconds, got {dt}")
    if duration < 0:
        raise ValueError(f"simulate_ball: duration must be >= 0, got {duration}")
    x = np.array(initial_state, dtype=float).reshape(-1)
    if x.shape != (9,):
        raise ValueError(f"simulate_ball: initial_state must be 9 finite numbers, got shape {np.shape(initial_state)}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"simulate_ball: initial_state must be 9 finite numbers, got {x.tolist()}")
    kinds = tuple(ContactKind(k) for k in kinds)
    stop_on = frozenset(ContactKind(k) for k in stop_on)
    times, states, event_kinds, event_times, event_pre, event_post, stop = simulate_ball_arrays(
        x, float(duration), float(dt), np.array([int(k) for k in kinds], dtype=np.int64), np.array([k in stop_on for k in kinds], dtype=np.bool_),
        contact_constants(params), *flight_constants(params.aero),
    )
    # copies, as simulate's: a view would keep the compiled loop's whole event buffer alive
    events = [ContactEvent(ContactKind(int(event_kinds[i])), float(event_times[i]), event_pre[i].copy(), event_post[i].copy())
              for i in range(event_kinds.size)]
    return Trajectory(times=times, states=states[:, None, :], final_state=states[-1:].copy(), events=[events],
                      stop_events=[events[stop] if stop >= 0 else None])


@numba.njit(cache=True)
def simulate_ball_arrays(x, duration, dt, kinds, stops, c, *flight):
    """``simulate_ball``'s compiled part, for compiled callers too (``control.hit_prediction``): one
    ball x (9,) (not changed) for ``duration`` s in steps of dt s with the contact ``kinds``
    (ContactKind values), stopping at those with ``stops`` (bool); c: ``contact_constants``,
    flight: ``flight_constants``. Returns (times (n+1,), states (n+1, 9), the contacts' kinds,
    times (s) and states just before and after (count,), the index of the stopping contact or
    -1)."""
    n_steps = int(math.ceil(duration / dt - 1e-9))
    times, states = np.empty(n_steps + 1), np.empty((n_steps + 1, 9))
    capacity = MAX_EVENTS_PER_STEP * n_steps
    event_kinds, event_times = np.empty(capacity, dtype=np.int64), np.empty(capacity)
    event_pre, event_post = np.empty((capacity, 9)), np.empty((capacity, 9))
    count, stop = _simulate_ball(x.copy(), duration, dt, n_steps, kinds, stops, c, *flight, times, states, event_kinds, event_times,
                                 event_pre, event_post)
    return times, states, event_kinds[:count], event_times[:count], event_pre[:count], event_post[:count], stop


# The contact constants as ``_simulate_ball`` takes them (``contact_constants``), by index.
(_RADIUS, _TABLE_LENGTH, _TABLE_WIDTH, _SURFACE_HEIGHT, _FRICTION, _RESTITUTION_BASE, _RESTITUTION_SLOPE, _ROLLING_ALPHA,
 _NET_HEIGHT, _NET_OVERHANG, _NET_RESTITUTION, _NET_RETENTION, _FLOOR_RESTITUTION, _FLOOR_RETENTION) = range(14)


def contact_constants(params: BallPhysicsParams) -> np.ndarray:
    """The params' fields that ``contact``'s one-ball kernels take, as one array (the indices above)."""
    table, net, floor = params.table, params.net, params.floor
    return np.array([params.aero.ball_radius, table.length, table.width, table.surface_height, table.friction,
                     table.restitution_base, table.restitution_slope, table.rolling_alpha, net.height, net.overhang,
                     net.restitution, net.tangential_retention, floor.restitution, floor.tangential_retention])


@numba.njit(cache=True)
def contact_gap_one(kind, x, c):
    """``contact_gap`` of one ball x (9,) for ContactKind ``kind``, m (c: ``contact_constants``)."""
    if kind == 1:  # TABLE
        return contact.table_gap_one(x[0], x[1], x[2], c[_TABLE_LENGTH], c[_TABLE_WIDTH], c[_RADIUS])
    if kind == 2:  # NET
        return contact.net_gap_one(x[0], x[1], x[2], c[_TABLE_WIDTH], c[_NET_OVERHANG], c[_NET_HEIGHT], c[_RADIUS])
    if kind == 3:  # FLOOR
        return contact.floor_gap_one(x[2], c[_SURFACE_HEIGHT], c[_RADIUS])
    return x[2] - c[_RADIUS]  # TABLE_PLANE


@numba.njit(cache=True)
def _impact_one(kind, x, c, out):
    """``apply_impact`` (no perturbation) of one ball x (9,) into out (9,), with ``contact``'s
    kernels: the table's map (TABLE, TABLE_PLANE), the net's or the floor's."""
    for j in range(9):
        out[j] = x[j]
    if kind == 1 or kind == 5:
        (out[3], out[4], out[5]), (out[6], out[7], out[8]) = contact.table_impact_one(
            x[3], x[4], x[5], x[6], x[7], x[8], c[_FRICTION], c[_RESTITUTION_BASE], c[_RESTITUTION_SLOPE], c[_ROLLING_ALPHA],
            c[_RADIUS])
    elif kind == 2:
        out[3], out[4], out[5] = contact.net_impact_one(x[0], x[1], x[2], x[3], x[4], x[5], c[_TABLE_WIDTH], c[_NET_OVERHANG],
                                                        c[_NET_HEIGHT], c[_NET_RESTITUTION], c[_NET_RETENTION])
    else:
        (out[3], out[4], out[5]), (out[6], out[7], out[8]) = contact.floor_impact_one(
            x[3], x[4], x[5], x[6], x[7], x[8], c[_FLOOR_RESTITUTION], c[_FLOOR_RETENTION])


@numba.njit(cache=True)
def _simulate_ball(x, duration, dt, n_steps, kinds, stops, c, drag_scale, density_ratio, slope, radius, offset, cap, weight,
                   drag_model, magnus_model, drag_table_scale, magnus_scale, times, states, event_kinds, event_times,
                   event_pre, event_post):
    """``simulate``'s loop for one ball x (9,) (changed in place) and the contact ``kinds`` (K,),
    ContactKind values in ``simulate``'s order, stopping at those with ``stops`` (K,): the states
    at the n_steps steps into times (n_steps+1,) and states (n_steps+1, 9), the contacts into
    event_kinds, event_times, event_pre, event_post. Returns (the number of contacts, the index of
    the stopping one or -1). The guards are the exact ``contact_gap`` (``simulate`` compares only
    their signs, which its cheaper lower bounds share); the contact times ``locate_root``'s
    Illinois iteration."""
    K = kinds.shape[0]
    k1, k2, k3, k4, trial = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    x1, x_pre, x_post = np.empty(9), np.empty(9), np.empty(9)
    gaps, gaps1 = np.empty(K), np.empty(K)
    for k in range(K):
        gaps[k] = contact_gap_one(kinds[k], x, c)
    active = True
    count, stop = 0, -1
    t = 0.0
    times[0] = 0.0
    states[0] = x
    for step in range(n_steps):
        h = min(dt, duration - t)
        remaining = h if active else 0.0
        elapsed = 0.0
        for _ in range(MAX_EVENTS_PER_STEP):
            if not remaining > 0.0:
                break
            rk4_one(x, remaining, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                    drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x1)
            crossed = False
            for k in range(K):
                gaps1[k] = contact_gap_one(kinds[k], x1, c)
                crossed = crossed or (gaps[k] > 0.0 and gaps1[k] <= 0.0)
            if not crossed:
                x[:] = x1
                gaps[:] = gaps1
                break
            # first_contact_time: the earliest crossing guard's root, ties to the earlier kind.
            tau, first = np.inf, 0
            for k in range(K):
                if gaps[k] > 0.0 and gaps1[k] <= 0.0:
                    tau_k = _locate_root_one(kinds[k], x, remaining, c, drag_scale, density_ratio, slope, radius, offset, cap,
                                             weight, drag_model, magnus_model, drag_table_scale, magnus_scale,
                                             k1, k2, k3, k4, trial, x1)
                    if tau_k < tau:
                        tau, first = tau_k, k
            rk4_one(x, tau, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                    drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x_pre)
            kind = kinds[first]
            if not _is_contact_one(kind, x_pre[2], c[_RADIUS]):  # beside the table, below its top
                x_post[:] = x_pre
            else:
                _impact_one(kind, x_pre, c, x_post)
                event_kinds[count], event_times[count] = kind, t + elapsed + tau
                event_pre[count], event_post[count] = x_pre, x_post
                count += 1
                if stops[first]:
                    stop = count - 1
                    active = False
                    x[:] = x_pre
                    remaining = 0.0
                    for k in range(K):
                        gaps[k] = contact_gap_one(kinds[k], x, c)
                    continue
            x[:] = x_post
            remaining -= tau
            elapsed += tau
            for k in range(K):
                gaps[k] = contact_gap_one(kinds[k], x, c)
        t += h
        times[step + 1] = t
        states[step + 1] = x
    return count, stop


@numba.njit(cache=True)
def _first_contact_rows(x0, h, crossing, kinds, c, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                        drag_table_scale, magnus_scale, tau, kind_index):
    """``first_contact_time`` of balls x0 (M, 9), steps h (M,), crossings (M, K) of the ContactKind
    values ``kinds`` (K,), into tau (M,) and kind_index (M,) (c: ``contact_constants``)."""
    k1, k2, k3, k4, trial, x1 = np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9), np.empty(9)
    for i in range(x0.shape[0]):
        tau[i], kind_index[i] = np.inf, 0
        for k in range(kinds.shape[0]):
            if crossing[i, k]:
                tau_k = _locate_root_one(kinds[k], x0[i], h[i], c, drag_scale, density_ratio, slope, radius, offset, cap, weight,
                                         drag_model, magnus_model, drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x1)
                if tau_k < tau[i]:
                    tau[i], kind_index[i] = tau_k, k


@numba.njit(cache=True)
def _locate_root_one(kind, x0, h, c, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                     drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x1):
    """``locate_root`` (lower 0) of one ball x0 (9,) over a step h, s, for the guard of ContactKind
    ``kind``: the Illinois iteration, operation for operation (x1 (9,) is scratch)."""
    a, g_a = 0.0, contact_gap_one(kind, x0, c)
    b = h
    rk4_one(x0, b, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model, drag_table_scale,
            magnus_scale, k1, k2, k3, k4, trial, x1)
    g_b = contact_gap_one(kind, x1, c)
    last_side = 0
    for _ in range(100):
        if not (b - a) > EVENT_TIME_TOLERANCE:
            break
        denominator = g_a - g_b
        c_trial = b + g_b * (b - a) / denominator if denominator > 0 else 0.5 * (a + b)
        if c_trial <= a or c_trial >= b:
            c_trial = 0.5 * (a + b)
        rk4_one(x0, c_trial, drag_scale, density_ratio, slope, radius, offset, cap, weight, drag_model, magnus_model,
                drag_table_scale, magnus_scale, k1, k2, k3, k4, trial, x1)
        g_c = contact_gap_one(kind, x1, c)
        if g_c > 0.0:
            if last_side == 1:
                g_b = 0.5 * g_b  # Illinois: halve the stale end
            a, g_a, last_side = c_trial, g_c, 1
        else:
            if last_side == -1:
                g_a = 0.5 * g_a
            b, g_b, last_side = c_trial, g_c, -1
            if g_c > -1e-13:  # a trial on the guard within 1e-13 m closes the bracket at once
                a = max(a, c_trial - EVENT_TIME_TOLERANCE)
    return b
