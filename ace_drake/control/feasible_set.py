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
        return FeasibleSets(*(getattr(self, field.name)[index] for field in dataclasses.fields(self)))

    def boundary_distance(self, direction: np.ndarray) -> np.ndarray:
        """t (..., 8) such that centre + t * direction lies on the polygon's boundary, for
        directions (..., 8, 2) in (q, v) units (broadcast against the sets' batch); inf for a
        zero direction."""
        direction = np.asarray(direction, dtype=float)
        along = np.einsum("...jek,...jk->...je", self.normals, direction)  # n_e . d
        room = self.offsets - np.einsum("...jek,...jk->...je", self.normals, self.centre)  # b_e - n_e . c >= 0
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            candidates = np.where(along > 1e-300, room / along, np.inf)
        return np.min(candidates, axis=-1)

    def contains(self, y: np.ndarray, tolerance: float = 1e-9) -> np.ndarray:
        """Whether terminal states y (..., 8, 2) lie in each joint's polygon, (..., 8) booleans."""
        y = np.asarray(y, dtype=float)
        excess = np.einsum("...jek,...jk->...je", self.normals, y) - self.offsets
        scale = np.abs(self.offsets) + 1.0
        return np.all(excess <= tolerance * scale, axis=-1)


def ramp_time(control: ControlParams, period: float) -> float:
    """How long (s) the worst-case terminal acceleration takes to ramp out: the QP's knot
    interval, or the resets' jerk-limited ramp from the limit to zero if that is longer."""
    return max(control.knot_samples * period, control.jerk_time)


def invariance_pad(towards: np.ndarray, limits: CommandLimits, control: ControlParams, ramp: float) -> np.ndarray:
    """How far (..., 8) inside a position limit a terminal state must stay, given its velocity
    ``towards`` that limit (..., 8; negative: away from it): part 2 of the module docstring.

    Moving towards it: the worst-case terminal acceleration A ramped out over ``ramp`` s
    (``ramp_time``), the reaction time, then braking at A_s. Moving away: the QP came from a turn
    no closer than the limit. Units: rad or m and per second."""
    A = limits.acceleration
    ramped = np.maximum(towards + 0.5 * A * ramp, 0.0)
    stopping = np.maximum(towards, 0.0) * ramp + A * ramp * ramp / 3.0 + ramped * control.reaction_time + ramped**2 / (2.0 * control.stop_fraction * A)
    turning = np.minimum(towards, 0.0) ** 2 / (2.0 * control.reach_fraction * A)
    return np.maximum(stopping, turning)


def invariant_bounds(v: np.ndarray, limits: CommandLimits, control: ControlParams, ramp: float) -> tuple[np.ndarray, np.ndarray]:
    """The control-invariant position bounds (lo, hi) (..., 8) at terminal velocities v (..., 8)
    (``invariance_pad`` towards each limit). Units: rad or m and per second."""
    return limits.lower + invariance_pad(-v, limits, control, ramp), limits.upper - invariance_pad(v, limits, control, ramp)


def _reach_upper(q1, v1, v, A_r, V, duration, ramp):
    """q_max(v): the largest terminal position reachable with terminal velocity v (module
    docstring), less the ramp pad (ramp / 2) (|w - v1| + |w - v|)."""
    peak = np.minimum(0.5 * (A_r * duration + v1 + v), V)
    bang_bang = q1 - (v1**2 + v**2) / (2.0 * A_r) + peak * duration + peak * (v1 + v) / A_r - peak**2 / A_r
    return bang_bang - 0.5 * ramp * np.abs(peak - v)


_SIDES = np.array([1.0, -1.0])[:, None, None, None]  # s: the upper bound (+1) and the lower (-1)


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
    if not np.all(feasible):
        raise InfeasibleStartError(reasons[int(np.argmin(feasible.ravel()))])
    return sets


def feasible_sets_batch(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> tuple[FeasibleSets, np.ndarray, list[str]]:
    """``feasible_sets`` for starts (..., 8) that reports an empty set per start instead of
    raising: (sets, feasible (...) booleans, reasons), reasons a flat list (one per start, in C
    order) of "" or the message InfeasibleStartError would carry. Where a start is infeasible its
    sets are finite but meaningless."""
    q0, v0, a0 = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (q0, v0, a0)))
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
        for row in np.flatnonzero(~np.all(feasible, axis=-1)):
            empty = [name for name, ok in zip(JOINT_NAMES, feasible[row]) if not ok]
            reasons[row] = f"no feasible terminal state for joint(s) {empty} from q={flat[0][row]}, v={flat[1][row]}, a={flat[2][row]}"
        feasible = np.all(feasible, axis=-1)
        for array in (*(getattr(sets, field.name) for field in dataclasses.fields(sets)), feasible):
            array.flags.writeable = False
        _LAST_SETS[:] = [key, (sets, feasible, tuple(reasons))]
    shaped = FeasibleSets(*(getattr(sets, field.name).reshape(batch + getattr(sets, field.name).shape[1:]) for field in dataclasses.fields(sets)))
    return shaped, feasible.reshape(batch), list(reasons)


_LAST_SETS: list = [None, None]  # feasible_sets_batch's last (key, result)


def _feasible_sets(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> tuple[FeasibleSets, np.ndarray]:
    """The sets (batch B) for starts (B, 8) each, and which joints' sets are non-empty (B, 8):
    one compiled call (``_polygons``), bit for bit ``_feasible_sets_numpy``."""
    if not (np.isfinite(q0).all() and np.isfinite(v0).all() and np.isfinite(a0).all()):
        return _feasible_sets_numpy(q0, v0, a0, limits, control, period)  # NaN propagates as NumPy's minimum and maximum do
    fractions = _polygon_fractions(control.boundary_samples)[:, 0, 0]
    B, J = q0.shape
    K = fractions.size - 1
    centre, scale = np.empty((B, J, 2)), np.empty((B, J, 2))
    vertices, normals, offsets = np.empty((B, J, 2 * K, 2)), np.empty((B, J, 2 * K, 2)), np.empty((B, J, 2 * K))
    feasible = np.empty((B, J), dtype=np.bool_)
    _polygons(np.ascontiguousarray(q0), np.ascontiguousarray(v0), np.ascontiguousarray(a0), limits.lower, limits.upper, limits.velocity,
              limits.acceleration, float(control.reach_fraction), float(control.knot_samples * period),
              float(control.segment_samples * period - control.knot_samples * period), float(ramp_time(control, period)),
              float(control.reaction_time), float(control.stop_fraction), _GRID[:, 0, 0], fractions, centre, scale, vertices, normals, offsets, feasible)
    return FeasibleSets(centre=centre, scale=scale, vertices=vertices, normals=normals, offsets=offsets), feasible


def _assembled(lo: np.ndarray, hi: np.ndarray, v: np.ndarray, v_low: np.ndarray, v_high: np.ndarray) -> FeasibleSets:
    """The FeasibleSets of the polygons' sides lo, hi (K + 1, B, 8) at velocities v (K + 1, B, 8)
    (the last row: the centre's), with velocity range [v_low, v_high] (B, 8)."""
    hi = np.maximum(hi, lo)  # round-off at the ends
    centre = np.stack([0.5 * (lo[-1] + hi[-1]), v[-1]], axis=-1)  # (B, 8, 2)
    lo, hi, v = (np.moveaxis(x[:-1], 0, -1) for x in (lo, hi, v))  # (B, 8, K)
    # Counter-clockwise in (q, v): up the right side (hi) with increasing v, down the left (lo).
    vertices = np.concatenate([np.stack([hi, v], axis=-1), np.stack([lo, v], axis=-1)[..., ::-1, :]], axis=-2)  # (B, 8, 2K, 2)
    edges = np.roll(vertices, -1, axis=-2) - vertices
    normals = np.stack([edges[..., 1], -edges[..., 0]], axis=-1)  # outward for counter-clockwise
    offsets = np.einsum("...ek,...ek->...e", normals, vertices)
    scale = np.stack([0.5 * (hi.max(axis=-1) - lo.min(axis=-1)), 0.5 * (v_high - v_low)], axis=-1)
    return FeasibleSets(centre=centre, scale=np.maximum(scale, 1e-12), vertices=vertices, normals=normals, offsets=offsets)


@numba.njit(cache=True)
def _side_bounds(q1, v1, excess_upper, excess_lower, v, lower, upper, V, A, reach_fraction, h, rest, ramp, reaction_time, stop_fraction):
    """``_feasible_sets_numpy``'s ``bounds`` of one joint at velocity v: (lo, hi), the same
    operations in the same order (s = +1: the upper side; s = -1: the lower, mirrored)."""
    A_r = reach_fraction * A
    bounds = np.empty(2)
    for side in range(2):
        s = 1.0 if side == 0 else -1.0
        signed_q1 = s * q1 - 2.0 * h * (excess_upper if side == 0 else excess_lower)
        signed_v1 = s * v1
        x = s * v
        # _reach_upper(signed_q1, signed_v1, x, A_r, V, rest, h)
        peak = min(0.5 * (A_r * rest + signed_v1 + x), V)
        bang_bang = signed_q1 - (signed_v1 * signed_v1 + x * x) / (2.0 * A_r) + peak * rest + peak * (signed_v1 + x) / A_r - peak * peak / A_r
        reach = bang_bang - 0.5 * h * abs(peak - x)
        # invariance_pad(x, ...)
        ramped = max(x + 0.5 * A * ramp, 0.0)
        stopping = max(x, 0.0) * ramp + A * ramp * ramp / 3.0 + ramped * reaction_time + ramped * ramped / (2.0 * stop_fraction * A)
        away = min(x, 0.0)
        turning = away * away / (2.0 * reach_fraction * A)
        limit = upper if side == 0 else -lower
        bounds[side] = s * min(reach, limit - max(stopping, turning))
    return bounds[1], bounds[0]


@numba.njit(cache=True)
def _polygons(q0, v0, a0, lower, upper, V, A, reach_fraction, h, rest, ramp, reaction_time, stop_fraction, grid, fractions,
              centre, scale, vertices, normals, offsets, feasible):
    """``_feasible_sets_numpy`` start by start and joint by joint, on the whole velocity grid
    (which ``_open_range`` reproduces): writes the FeasibleSets' fields and whether each set is
    non-empty (B, 8)."""
    B, J = q0.shape
    K = fractions.size - 1
    lo, hi, v = np.empty(K + 1), np.empty(K + 1), np.empty(K + 1)
    for b in range(B):
        for j in range(J):
            A_j, V_j = A[j], V[j]
            A_r = reach_fraction * A_j
            q1 = q0[b, j] + v0[b, j] * h + a0[b, j] * h * h / 3.0
            ramped_v = v0[b, j] + 0.5 * a0[b, j] * h
            v1 = min(max(ramped_v, -V_j), V_j)
            excess_upper = max(ramped_v - V_j, 0.0)
            excess_lower = max(-ramped_v - V_j, 0.0)
            low, high = max(-V_j, v1 - A_r * rest), min(V_j, v1 + A_r * rest)
            first, last = -1, -1
            for g in range(grid.size):
                l, u = _side_bounds(q1, v1, excess_upper, excess_lower, low + grid[g] * (high - low), lower[j], upper[j], V_j, A_j,
                                    reach_fraction, h, rest, ramp, reaction_time, stop_fraction)
                if u >= l:
                    if first < 0:
                        first = g
                    last = g
            feasible[b, j] = first >= 0
            if first < 0:  # argmax of all False: the first grid point, and the last
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


def _feasible_sets_numpy(q0, v0, a0, limits: CommandLimits, control: ControlParams, period: float) -> tuple[FeasibleSets, np.ndarray]:
    """``_feasible_sets`` in NumPy array operations: the reference of its compiled kernel."""
    A, V = limits.acceleration, limits.velocity
    A_r = control.reach_fraction * A
    h = control.knot_samples * period
    rest = control.segment_samples * period - h
    # The start after the first knot interval's ramp of a0 to zero (module docstring, part 1).
    q1 = q0 + v0 * h + a0 * h * h / 3.0
    v1 = np.clip(v0 + 0.5 * a0 * h, -V, V)
    # Where that ramp would carry the velocity past its limit (by e), the spline must instead
    # turn its acceleration round within the interval to meet the bound at the sample, and
    # recover after it: it reaches about e * h less far on that side (measured: 1.7e-6 m for
    # e = 1.7e-3 m/s); the bound on that side is padded by 2 e h.
    excess = np.maximum(_SIDES * (v0 + 0.5 * a0 * h) - V, 0.0)  # (2, 1, B, 8)
    signed_q1, signed_v1 = _SIDES * q1 - 2.0 * h * excess, _SIDES * v1
    signed_limit = np.empty((2, 1, 1, q0.shape[-1]))  # upper, -lower
    signed_limit[0, 0, 0], signed_limit[1, 0, 0] = limits.upper, -limits.lower
    ramp = ramp_time(control, period)

    def bounds(v: np.ndarray, rows=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (K, b, 8) at velocities v (K, b, 8) of the starts ``rows``: both sides at
        once, the lower one mirrored (s = -1: q -> -q, v -> -v), each the tighter of
        reachability and invariance."""
        x = _SIDES * v  # (2, K, b, 8)
        reach = _reach_upper(signed_q1[:, :, rows], signed_v1[:, :, rows], x, A_r, V, rest, h)
        side = _SIDES * np.minimum(reach, signed_limit - invariance_pad(x, limits, control, ramp))
        return side[1], side[0]

    # The velocity range [v_a, v_b] of F: where the (concave) width hi - lo is >= 0, within the
    # reachable range, found on a grid (the ramp pad closes the reachable range's two ends, and a
    # position limit may cut it further).
    v_low, v_high = np.maximum(-V, v1 - A_r * rest), np.minimum(V, v1 + A_r * rest)
    first, last, feasible = _open_range(bounds, v_low, v_high, h)
    v_low, v_high = _grid_velocity(first, v_low, v_high), _grid_velocity(last, v_low, v_high)
    # Polygon vertices at K velocities from v_a to v_b, and the centre's velocity as one more row.
    v = v_low + _polygon_fractions(control.boundary_samples) * (v_high - v_low)  # (K + 1, B, 8)
    lo, hi = bounds(v)
    return _assembled(lo, hi, v, v_low, v_high), feasible


def _grid_velocity(index: np.ndarray, v_low: np.ndarray, v_high: np.ndarray) -> np.ndarray:
    """The velocities (B, 8) of grid points ``index`` (B, 8), as the grid computes them."""
    return v_low + _GRID[index, 0, 0] * (v_high - v_low)


def _open_range(bounds, v_low: np.ndarray, v_high: np.ndarray, knot_interval: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first and last grid indices (B, 8) where hi >= lo (``bounds``) on the grid of
    ``VELOCITY_GRID`` velocities from v_low to v_high (B, 8), and whether there is one (B, 8):
    exactly what evaluating the whole grid gives, from about a quarter of its points.

    The width w = hi - lo is concave up to two convex kinks, where the ramp pads
    (knot_interval / 2) |w* - v| of hi and lo meet the velocity limit, each raising w's slope by
    knot_interval / 4 (``_reach_upper``). So on the coarse grid of every ``_COARSE``-th point,
    if every |w| exceeds tol = 2 knot_interval dv (dv: the grid step) and the open points are
    contiguous, every fine point between two open ones is open (w stays above tol -
    knot_interval dv) and every fine point beyond the first closed one on either side is closed
    (the slope there keeps the sign it has across the transition); only the fine points next to
    the two transitions need evaluating, by the same arithmetic as on the whole grid. Joints of a
    start where that does not hold (a narrow or empty set) get the whole grid, and so do batches
    of fewer than ``_COARSE_ROWS`` starts (one evaluation of the grid costs less there than two of
    fewer points: NumPy's per-call overhead dominates)."""
    stride, rows = _COARSE, v_low.shape[0]
    if rows < _COARSE_ROWS:
        grid = v_low + _GRID * (v_high - v_low)
        lo, hi = bounds(grid)
        open_ = hi >= lo
        return np.argmax(open_, axis=0), open_.shape[0] - 1 - np.argmax(open_[::-1], axis=0), np.any(open_, axis=0)
    coarse = np.arange(0, VELOCITY_GRID, stride)
    lo, hi = bounds(v_low + _GRID[coarse] * (v_high - v_low))
    width = hi - lo  # (C, B, 8); open where >= 0, as hi >= lo
    open_ = width >= 0.0
    tolerance = 2.0 * knot_interval * (v_high - v_low) / (VELOCITY_GRID - 1) * (1.0 + 1e-6) + 1e-9
    first_coarse = np.argmax(open_, axis=0)
    last_coarse = open_.shape[0] - 1 - np.argmax(open_[::-1], axis=0)
    span = np.arange(open_.shape[0])[:, None, None]
    contiguous = np.all(open_ == ((span >= first_coarse) & (span <= last_coarse)), axis=0)
    decided = np.any(open_, axis=0) & contiguous & np.all(np.abs(width) > tolerance, axis=0)
    # The fine points before the first open coarse point and after the last (clipped to the grid:
    # an end of the grid that is open is its own transition).
    offsets = np.arange(1, stride)
    before = coarse[first_coarse] - stride + offsets[:, None, None]  # (stride - 1, B, 8)
    after = coarse[last_coarse] + offsets[:, None, None]
    fine = np.clip(np.concatenate([before, after]), 0, VELOCITY_GRID - 1)
    lo, hi = bounds(_grid_velocity(fine, v_low, v_high))
    fine_open = (hi >= lo) & (np.concatenate([before, after]) == fine)
    before_open, after_open = fine_open[: stride - 1], fine_open[stride - 1 :]
    first = np.where(np.any(before_open, axis=0), before[0] + np.argmax(before_open, axis=0), coarse[first_coarse])
    last = np.where(np.any(after_open, axis=0), after[-1] - np.argmax(after_open[::-1], axis=0), coarse[last_coarse])
    feasible = np.ones(first.shape, dtype=bool)
    undecided = np.flatnonzero(~np.all(decided, axis=-1))
    if undecided.size:  # the whole grid, for the starts with a joint not decided above
        grid = v_low[undecided] + _GRID * (v_high[undecided] - v_low[undecided])
        lo, hi = bounds(grid, undecided)
        open_ = hi >= lo
        feasible[undecided] = np.any(open_, axis=0)
        first[undecided] = np.argmax(open_, axis=0)
        last[undecided] = open_.shape[0] - 1 - np.argmax(open_[::-1], axis=0)
    return first, last, feasible


@functools.lru_cache(maxsize=8)
def _polygon_fractions(samples: int) -> np.ndarray:
    """(samples + 1, 1, 1): 0 .. 1 in ``samples`` steps, then 0.5 (the centre's row)."""
    fractions = np.linspace(0.0, 1.0, samples + 1)
    fractions[:-1] = np.linspace(0.0, 1.0, samples)
    fractions[-1] = 0.5
    return fractions[:, None, None]


VELOCITY_GRID = 129
_COARSE = 8  # _open_range's coarse grid: every 8th velocity (VELOCITY_GRID - 1 a multiple)
_COARSE_ROWS = 4  # and the smallest batch it is used for
_GRID = np.linspace(0.0, 1.0, VELOCITY_GRID)[:, None, None]


def in_invariant_set(q, v, limits: CommandLimits, control: ControlParams, period: float, tolerance: float = 0.0) -> np.ndarray:
    """Whether joint states (q, v) (..., 8) lie in the control-invariant part of the feasible
    sets (part 2 of the module docstring), with any acceleration within the command limits:
    the states the mapping produces, and from which ``feasible_sets`` is never empty.
    ``tolerance``: how far outside (rad or m, and per s) still counts as inside."""
    lo, hi = invariant_bounds(np.asarray(v, dtype=float), limits, control, ramp_time(control, period))
    q = np.asarray(q, dtype=float)
    return (lo - tolerance <= q) & (q <= hi + tolerance) & (np.abs(v) <= limits.velocity + tolerance)
