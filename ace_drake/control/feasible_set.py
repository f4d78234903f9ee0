"""Per-joint feasible sets of terminal (position, velocity) 32 ms ahead (paper, Methods *Feasible
action for optimal control*).

For joint i starting a segment of duration T at (q0, v0, a0), the feasible set F_i is the set of
terminal states (q_T, v_T) that

1. the spline QP can reach: an inner approximation of the reachable set of a double integrator
   under |a| <= A_r = reach_fraction * A, |v| <= V (A, V the command limits), starting from the
   state after the QP's first knot interval h, over which the acceleration ramps from a0 to zero:
   (q1, v1) = (q0 + v0 h + a0 h^2 / 3, v0 + a0 h / 2) over T' = T - h;
2. lie in a control-invariant set: from (q_T, v_T), with any terminal acceleration |a_T| <= A
   towards the limit ramped away over max(h, jerk_time) (the resets ramp at the jerk limit
   J = A / jerk_time; ``control.reset.stop_pad`` derives the pad), a stop at
   A_s = stop_fraction * A after a reaction time tau ends inside [lower, upper], and a state moving away from a limit is one the QP can have
   reached without crossing it (q_T <= upper - v_T^2 / (2 A_r) for v_T < 0, mirrored).

Both sets are convex, so F_i is convex: each is {(q, v): v in [v_a, v_b], lo(v) <= q <= hi(v)}
with lo convex and hi concave. The reachable bounds are the bang-bang motions: with peak velocity
w (``_reach_upper``),

    q_max(v) = g(min(w*, V)), g(w) = q1 - (v1^2 + v^2) / (2 A_r) + w T' + w (v1 + v) / A_r - w^2 / A_r,
    w* = (A_r T' + v1 + v) / 2   (accelerate at +A_r to w, cruise, decelerate at -A_r to v),

less a ramp pad (h / 2) |w* - v|, and q_min(v) mirrors it. The pad is the spline's: its
acceleration is linear between knots h apart, so the final switch of the bang-bang profile (to
-A_r, or +A_r) becomes a ramp that starts up to h early and costs up to h |w - v| / 2 of position;
the slack A_r < A makes up for the other switches, but not for a short final braking (measured
on 300 random, edge and cruising starts: 55 of 10,896 corner targets were out of the QP's reach
without the pad, none with it; ``test_every_corner_of_the_feasible_set_is_reachable`` checks
every corner). Every
state the mapping produces lies in F, and F of that state again
contains states (braking at A_r > A_s reduces the stopping "energy" q + v tau + v^2 / (2 A_s)
faster than the worst-case ramp adds to it), which is the recursive feasibility the spline QP
relies on; ``tests/test_spline_qp.py`` checks it on thousands of states and actions.

F_i is represented by a convex polygon with vertices on its boundary (``boundary_samples``
velocities between v_a and v_b, at each the ends lo(v) and hi(v)): an inner approximation, since a
chord of a convex set lies inside it. Its centre is the midpoint of the velocity range and, at that
velocity, of the position range. Everything is vectorised over the eight joints.
"""

from __future__ import annotations

import dataclasses
import functools

import numba
import numpy as np

from ace_drake.control.params import ControlParams
from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.params import JOINT_NAMES


class InfeasibleStartError(ValueError):
    """The start state lies outside the control-invariant set: no terminal state is feasible."""


@dataclasses.dataclass(frozen=True)
class FeasibleSets:
    """The eight joints' feasible sets of terminal (q, v) (``feasible_sets``), for one start or a
    batch of starts (leading dimensions ``...``).

    centre (..., 8, 2): (q, v) centres; scale (..., 8, 2): half-widths of each polygon's bounding
    box (the shape function f of eq. (12) scales by them); vertices (..., 8, 2K, 2): polygon
    vertices, counter-clockwise in the (q, v) plane; normals (..., 8, 2K, 2) and offsets
    (..., 8, 2K): the polygon as half-planes normal . y <= offset (degenerate edges have a zero
    normal and are ignored).
    """

    centre: np.ndarray
    scale: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """The leading dimensions (() for one start)."""
        return self.centre.shape[:-2]

    def __getitem__(self, index) -> "FeasibleSets":
        """The sets of the starts ``index`` selects along the leading dimensions."""
        if not self.batch_shape:
            raise IndexError("FeasibleSets: the sets of one start have no batch dimension to index")
        return FeasibleSets(*(getattr(self, name)[index] for name in _FIELDS))

    def joint_arrays(self, batch: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The sets broadcast to the leading dimensions ``batch`` and flattened over them and the
        joints, for the compiled loops: centre, scale (S, 2), normals (S, 2K, 2), offsets (S, 2K),
        C-contiguous (views when the batch is the sets' own)."""
        arrays = []
        for name in ("centre", "scale", "normals", "offsets"):
            x = getattr(self, name)
            core = x.shape[x.ndim - _CORE_NDIM[name] :]  # (8, ...)
            if x.shape[: x.ndim - len(core)] != batch:
                x = np.broadcast_to(x, batch + core)
            arrays.append(np.ascontiguousarray(x).reshape((-1,) + core[1:]))
        return tuple(arrays)

    def boundary_distance(self, direction: np.ndarray) -> np.ndarray:
        """t (..., 8) such that centre + t * direction lies on the polygon's boundary, for
        directions (..., 8, 2) in (q, v) units (broadcast against the sets' batch); inf for a
        zero direction. One compiled loop (``_boundary_distance``)."""
        direction = np.asarray(direction, dtype=float)
        batch = self.batch_shape if direction.shape == self.centre.shape else np.broadcast_shapes(direction.shape[:-2], self.batch_shape)
        centre, _, normals, offsets = self.joint_arrays(batch)
        out = np.empty(batch + self.centre.shape[-2:-1])
        direction = np.ascontiguousarray(np.broadcast_to(direction, out.shape + (2,))).reshape(-1, 2)
        _boundary_distance(normals, offsets, centre, direction, out.reshape(-1))
        return out

    def contains(self, y: np.ndarray, tolerance: float = 1e-9) -> np.ndarray:
        """Whether terminal states y (..., 8, 2) lie in each joint's polygon, (..., 8) booleans."""
        y = np.asarray(y, dtype=float)
        excess = np.einsum("...jek,...jk->...je", self.normals, y) - self.offsets
        scale = np.abs(self.offsets) + 1.0
        return np.all(excess <= tolerance * scale, axis=-1)


_FIELDS = tuple(field.name for field in dataclasses.fields(FeasibleSets))


_CORE_NDIM = {"centre": 2, "scale": 2, "vertices": 3, "normals": 3, "offsets": 2}  # each field's dimensions after the batch


@numba.njit(cache=True)
def _boundary_distance(normals, offsets, centre, direction, out):
    """``FeasibleSets.boundary_distance`` of S polygons: normals (S, E, 2), offsets (S, E), centre
    and direction (S, 2), into out (S,)."""
    for s in range(normals.shape[0]):
        out[s] = edge_distance(normals[s], offsets[s], centre[s, 0], centre[s, 1], direction[s, 0], direction[s, 1])


@numba.njit(cache=True)
def edge_distance(normals, offsets, c0, c1, d0, d1):
    """t such that (c0, c1) + t (d0, d1) lies on the boundary of the polygon normals (E, 2) . y <=
    offsets (E,): over the edges e with n_e . d > 1e-300, the smallest (b_e - n_e . c) / (n_e . d)
    (NaN if any is NaN, as NumPy's min); inf if there are none (a zero direction). The one
    definition, which the action mapping's kernels call too."""
    smallest = np.inf
    for e in range(normals.shape[0]):
        along = normals[e, 0] * d0 + normals[e, 1] * d1
        room = offsets[e] - (normals[e, 0] * c0 + normals[e, 1] * c1)
        candidate = room / along if along > 1e-300 else np.inf
        if candidate != candidate:
            return candidate
        smallest = min(smallest, candidate)
    return smallest


def ramp_time(control: ControlParams, period: float) -> float:
    """How long (s) the worst-case terminal acceleration takes to ramp out: the QP's knot
    interval, or the resets' jerk-limited ramp from the limit to zero if that is longer."""
    return max(control.knot_samples * period, control.jerk_time)


def invariance_pad(towards: np.ndarray, limits: CommandLimits, control: ControlParams, ramp: float) -> np.ndarray:
    """How far (..., 8) inside a position limit a terminal state must stay, given its velocity
    ``towards`` that limit (..., 8; negative: away from it): part 2 of the module docstring.

    Moving towards it: the worst-case terminal acceleration A ramped out over ``ramp`` s
    (``ramp_time``), the reaction time, then braking at A_s. Moving away: the QP came from a turn
    no closer than the limit. NaN where ``towards`` is NaN. Units: rad or m and per second."""
    return _pad(np.asarray(towards, dtype=float), limits.acceleration, float(ramp), float(control.reaction_time),
                float(control.stop_fraction), float(control.reach_fraction))


@numba.vectorize(["float64(float64, float64, float64, float64, float64, float64)"], cache=True)
def _pad(towards, A, ramp, reaction_time, stop_fraction, reach_fraction):
    """``invariance_pad`` of one joint (acceleration limit A): the one definition, which the
    feasible sets' kernel calls too."""
    if np.isnan(towards):
        return np.nan
    ramped = max(towards + 0.5 * A * ramp, 0.0)
    stopping = max(towards, 0.0) * ramp + A * ramp * ramp / 3.0 + ramped * reaction_time + ramped * ramped / (2.0 * stop_fraction * A)
    away = min(towards, 0.0)
    turning = away * away / (2.0 * reach_fraction * A)
    return max(stopping, turning)


def invariant_bounds(v: np.ndarray, limits: CommandLimits, control: ControlParams, ramp: float) -> tuple[np.ndarray, np.ndarray]:
    """The control-invariant position bounds (lo, hi) (..., 8) at terminal velocities v (..., 8)
    (``invariance_pad`` towards each limit). Units: rad or m and per second."""
    return limits.lower + invariance_pad(-v, limits, control, ramp), limits.upper - invariance_pad(v, limits, control, ramp)


@numba.njit(cache=True)
def _reach_upper(q1, v1, v, A_r, V, duration, ramp):
    """q_max(v) of one joint: the largest terminal position reachable with terminal velocity v
    (module docstring) from (q1, v1) over ``duration`` s at |a| <= A_r, |v| <= V, less the ramp
    pad (ramp / 2) |w - v|."""
    peak = min(0.5 * (A_r * duration + v1 + v), V)
    bang_bang = q1 - (v1 * v1 + v * v) / (2.0 * A_r) + peak * duration + peak * (v1 + v) / A_r - peak * peak / A_r
    return bang_bang - 0.5 * ramp * abs(peak - v)


def feasible_sets(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> FeasibleSets:
    """The feasible sets of the eight joints for a segment starting at (q0, v0, a0) (..., 8) each
    (rad or m, per s, per s^2; leading dimensions are a batch of starts), sampled every
    ``period`` s (the command period), with the QP's knots every ``control.knot_samples``
    samples.

    The velocity range [v_a, v_b] is found on a grid of ``VELOCITY_GRID`` velocities across the
    reachable range (to 1/(VELOCITY_GRID - 1) of it, from the inside). Raises InfeasibleStartError
    naming the joints whose set is empty (a start outside the control-invariant set, e.g. moving
    fast at a position limit); for a batch, that of its first such start (``feasible_sets_batch``
    reports each start instead)."""
    sets, feasible, reasons = feasible_sets_batch(q0, v0, a0, limits, control, period)
    if not feasible.all():
        raise InfeasibleStartError(reasons[int(np.argmin(feasible.ravel()))])
    return sets


def feasible_sets_batch(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> tuple[FeasibleSets, np.ndarray, list[str]]:
    """``feasible_sets`` for starts (..., 8) that reports an empty set per start instead of
    raising: (sets, feasible (...) booleans, reasons), reasons a flat list (one per start, in C
    order) of "" or the message InfeasibleStartError would carry. Where a start is infeasible its
    sets are finite but meaningless. The arrays returned are read-only."""
    q0, v0, a0 = (np.asarray(x, dtype=float) for x in (q0, v0, a0))
    if not q0.shape == v0.shape == a0.shape:
        q0, v0, a0 = np.broadcast_arrays(q0, v0, a0)
    if q0.shape[-1:] != (len(JOINT_NAMES),):
        raise ValueError(f"feasible_sets: q0, v0, a0 must have {len(JOINT_NAMES)} joints in the last dimension, got shape {q0.shape}")
    batch = q0.shape[:-1]
    flat = [x.reshape(-1, len(JOINT_NAMES)) for x in (q0, v0, a0)]
    # A segment's start state is mapped twice per tick (the policy's ``action_towards`` and the
    # ActionMapper): the last call's sets are kept, keyed on the exact inputs, and shared read-only.
    key = (flat[0].shape, *(x.tobytes() for x in flat), limits.lower.tobytes(), limits.upper.tobytes(), limits.velocity.tobytes(),
           limits.acceleration.tobytes(), control, period)
    if _LAST_SETS[0] == key:
        sets, feasible, reasons = _LAST_SETS[1]
    else:
        sets, feasible = _feasible_sets(*flat, limits, control, period)
        reasons = [""] * feasible.shape[0]
        if not feasible.all():
            for row in np.flatnonzero(~feasible.all(axis=-1)):
                empty = [name for name, ok in zip(JOINT_NAMES, feasible[row]) if not ok]
                reasons[row] = f"no feasible terminal state for joint(s) {empty} from q={flat[0][row]}, v={flat[1][row]}, a={flat[2][row]}"
        feasible = feasible.all(axis=-1)
        for array in (*(getattr(sets, name) for name in _FIELDS), feasible):
            array.flags.writeable = False
        _LAST_SETS[:] = [key, (sets, feasible, tuple(reasons))]
    if len(batch) != 1:  # the sets are computed for a flat batch of starts
        sets = FeasibleSets(*(getattr(sets, name).reshape(batch + getattr(sets, name).shape[1:]) for name in _FIELDS))
        feasible = feasible.reshape(batch)
    return sets, feasible, list(reasons)


_LAST_SETS: list = [None, None]  # feasible_sets_batch's last (key, result)


def _feasible_sets(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> tuple[FeasibleSets, np.ndarray]:
    """The sets (batch B) for starts (B, 8) each, and which joints' sets are non-empty (B, 8):
    one compiled call (``_polygons``)."""
    fractions = _polygon_fractions(control.boundary_samples)
    B, J = q0.shape
    K = fractions.size - 1
    centre, scale = np.empty((B, J, 2)), np.empty((B, J, 2))
    vertices, normals, offsets = np.empty((B, J, 2 * K, 2)), np.empty((B, J, 2 * K, 2)), np.empty((B, J, 2 * K))
    feasible = np.empty((B, J), dtype=np.bool_)
    _polygons(np.ascontiguousarray(q0), np.ascontiguousarray(v0), np.ascontiguousarray(a0), limits.lower, limits.upper, limits.velocity,
              limits.acceleration, float(control.reach_fraction), float(control.knot_samples * period),
              float(control.segment_samples * period - control.knot_samples * period), float(ramp_time(control, period)),
              float(control.reaction_time), float(control.stop_fraction), _GRID, fractions, centre, scale, vertices, normals, offsets, feasible)
    return FeasibleSets(centre=centre, scale=scale, vertices=vertices, normals=normals, offsets=offsets), feasible


@numba.njit(cache=True)
def _side_bounds(q1, v1, excess_upper, excess_lower, v, lower, upper, V, A, reach_fraction, h, rest, ramp, reaction_time, stop_fraction):
    """The bounds (lo, hi) of one joint's set at terminal velocity v: on each side the tighter of
    reachability (``_reach_upper``) and invariance (``_pad``), the lower side mirrored (s = -1:
    q -> -q, v -> -v).

    (q1, v1) is the start after the first knot interval (module docstring, part 1). Where the
    ramp of a0 to zero over it would carry the velocity past its limit (by e = ``excess_*``), the
    spline must instead turn its acceleration round within the interval to meet the bound at the
    sample, and recover after it: it reaches about e h less far on that side (measured: 1.7e-6 m
    for e = 1.7e-3 m/s); that side's start is moved back by 2 e h."""
    bounds = np.empty(2)
    for side in range(2):
        s = 1.0 if side == 0 else -1.0
        x = s * v
        reach = _reach_upper(s * q1 - 2.0 * h * (excess_upper if side == 0 else excess_lower), s * v1, x, reach_fraction * A, V, rest, h)
        limit = upper if side == 0 else -lower
        bounds[side] = s * min(reach, limit - _pad(x, A, ramp, reaction_time, stop_fraction, reach_fraction))
    return bounds[1], bounds[0]


@numba.njit(cache=True)
def _polygons(q0, v0, a0, lower, upper, V, A, reach_fraction, h, rest, ramp, reaction_time, stop_fraction, grid, fractions,
              centre, scale, vertices, normals, offsets, feasible):
    """The feasible sets start by start (B) and joint by joint (8): writes the FeasibleSets'
    fields (B, 8, ...) and whether each set is non-empty (B, 8).

    The velocity range [v_a, v_b] is where the (concave) width hi - lo is >= 0 on the ``grid``
    (fractions of the reachable range: the ramp pad closes its two ends, and a position limit may
    cut it further); the polygon's vertices are at ``fractions`` of [v_a, v_b], the last of them
    the centre's velocity. A joint whose start is not finite has an empty set with NaN fields."""
    B, J = q0.shape
    K = fractions.size - 1
    lo, hi, v = np.empty(K + 1), np.empty(K + 1), np.empty(K + 1)
    for b in range(B):
        for j in range(J):
            if not (np.isfinite(q0[b, j]) and np.isfinite(v0[b, j]) and np.isfinite(a0[b, j])):
                feasible[b, j] = False
                centre[b, j], scale[b, j], vertices[b, j], normals[b, j], offsets[b, j] = np.nan, np.nan, np.nan, np.nan, np.nan
                continue
            A_j, V_j = A[j], V[j]
            A_r = reach_fraction * A_j
            q1 = q0[b, j] + v0[b, j] * h + a0[b, j] * h * h / 3.0
            ramped_v = v0[b, j] + 0.5 * a0[b, j] * h
            v1 = min(max(ramped_v, -V_j), V_j)
            excess_upper = max(ramped_v - V_j, 0.0)
            excess_lower = max(-ramped_v - V_j, 0.0)
            low, high = max(-V_j, v1 - A_r * rest), min(V_j, v1 + A_r * rest)
            # The first and the last grid velocity with hi >= lo: scanned inwards from each end,
            # stopping at the first found (the set usually spans most of the grid).
            first, last = -1, -1
            for g in range(grid.size):
                l, u = _side_bounds(q1, v1, excess_upper, excess_lower, low + grid[g] * (high - low), lower[j], upper[j], V_j, A_j,
                                    reach_fraction, h, rest, ramp, reaction_time, stop_fraction)
                if u >= l:
                    first = g
                    break
            if first >= 0:
                for g in range(grid.size - 1, first - 1, -1):
                    l, u = _side_bounds(q1, v1, excess_upper, excess_lower, low + grid[g] * (high - low), lower[j], upper[j], V_j, A_j,
                                        reach_fraction, h, rest, ramp, reaction_time, stop_fraction)
                    if u >= l:
                        last = g
                        break
            feasible[b, j] = first >= 0
            if first < 0:  # an empty set: finite but meaningless polygons over the whole range
                first, last = 0, grid.size - 1
            v_low, v_high = low + grid[first] * (high - low), low + grid[last] * (high - low)
            for k in range(K + 1):
                v[k] = v_low + fractions[k] * (v_high - v_low)
                lo[k], hi[k] = _side_bounds(q1, v1, excess_upper, excess_lower, v[k], lower[j], upper[j], V_j, A_j,
                                            reach_fraction, h, rest, ramp, reaction_time, stop_fraction)
                hi[k] = max(hi[k], lo[k])  # round-off at the ends
            centre[b, j, 0], centre[b, j, 1] = 0.5 * (lo[K] + hi[K]), v[K]
            # Counter-clockwise in (q, v): up the right side (hi) with increasing v, down the left (lo).
            for k in range(K):
                vertices[b, j, k, 0], vertices[b, j, k, 1] = hi[k], v[k]
                vertices[b, j, 2 * K - 1 - k, 0], vertices[b, j, 2 * K - 1 - k, 1] = lo[k], v[k]
            for e in range(2 * K):
                following = (e + 1) % (2 * K)
                normals[b, j, e, 0] = vertices[b, j, following, 1] - vertices[b, j, e, 1]  # outward for counter-clockwise
                normals[b, j, e, 1] = -(vertices[b, j, following, 0] - vertices[b, j, e, 0])
                offsets[b, j, e] = normals[b, j, e, 0] * vertices[b, j, e, 0] + normals[b, j, e, 1] * vertices[b, j, e, 1]
            top, bottom = hi[0], lo[0]
            for k in range(1, K):
                top, bottom = max(top, hi[k]), min(bottom, lo[k])
            scale[b, j, 0] = max(0.5 * (top - bottom), 1e-12)
            scale[b, j, 1] = max(0.5 * (v_high - v_low), 1e-12)


@functools.lru_cache(maxsize=8)
def _polygon_fractions(samples: int) -> np.ndarray:
    """(samples + 1,): 0 .. 1 in ``samples`` steps, then 0.5 (the centre's row)."""
    fractions = np.linspace(0.0, 1.0, samples + 1)
    fractions[:-1] = np.linspace(0.0, 1.0, samples)
    fractions[-1] = 0.5
    return fractions


VELOCITY_GRID = 129
_GRID = np.linspace(0.0, 1.0, VELOCITY_GRID)


def in_invariant_set(q, v, limits: CommandLimits, control: ControlParams, period: float, tolerance: float = 0.0) -> np.ndarray:
    """Whether joint states (q, v) (..., 8) lie in the control-invariant part of the feasible
    sets (part 2 of the module docstring), with any acceleration within the command limits:
    the states the mapping produces, and from which ``feasible_sets`` is never empty.
    ``tolerance``: how far outside (rad or m, and per s) still counts as inside."""
    lo, hi = invariant_bounds(np.asarray(v, dtype=float), limits, control, ramp_time(control, period))
    q = np.asarray(q, dtype=float)
    return (lo - tolerance <= q) & (q <= hi + tolerance) & (np.abs(v) <= limits.velocity + tolerance)
