"""Impact maps: table (paper eqs (2)-(6)), racket (eqs (7)-(8)), net and floor; contact geometry.

Each map takes pre-contact velocity and spin (..., 3) in the world frame and returns the
post-contact pair; contacts are instantaneous, position does not change. Batched throughout.

The table, net and floor gaps and maps are each defined once, as a compiled (numba) kernel of one
ball (``table_gap_one``, ``table_impact_one``, ...; scalars in, scalars out); the batched functions
apply that kernel row by row, and compiled one-ball callers (``propagate.simulate_ball``) call it
directly, so every propagator uses the same operations.
"""

from __future__ import annotations

import math
from typing import Callable

import numba
import numpy as np

from ace_drake.physics.params import FloorParams, NetParams, RacketParams, TableParams

# (features (N, 8), -> corrections (N, 6)) in the contact frame; see racket_residual.py.
ResidualModel = Callable[[np.ndarray], np.ndarray]


# ------------------------------------------------------------------------------ one ball, compiled
# Velocities in m/s, spins in rad/s, positions and lengths in m, world frame; the params' fields are
# passed as floats.


@numba.njit(cache=True, error_model="numpy")
def table_restitution_one(v_z, restitution_base, restitution_slope):
    """eps_table = 0.98 - 0.02 |v_z^-| (paper, below eq. (6); v_z^- < 0 at impact)."""
    return restitution_base - restitution_slope * abs(v_z)


@numba.njit(cache=True, error_model="numpy")
def table_alpha_one(vx, vy, vz, wx, wy, wz, friction, restitution_base, restitution_slope, rolling_alpha, radius):
    """alpha of eq. (4) and the sliding flag of eq. (5) for one ball, v (m/s) and w (rad/s) just
    before the table contact; ``table_alpha`` explains the switch."""
    eps = table_restitution_one(vz, restitution_base, restitution_slope)
    slip = math.hypot(vx - radius * wy, vy + radius * wx)  # |v_T|, paper eq. (6)
    normal_impulse = friction * (1.0 + eps) * abs(vz)
    alpha_sliding = normal_impulse / slip if slip > 0.0 else np.inf
    v_s = 1.0 - alpha_sliding / rolling_alpha  # paper eq. (5)
    sliding = v_s > 0.0
    alpha = alpha_sliding if sliding else rolling_alpha  # paper eq. (4)
    return alpha, sliding


@numba.njit(cache=True, error_model="numpy")
def table_impact_one(vx, vy, vz, wx, wy, wz, friction, restitution_base, restitution_slope, rolling_alpha, radius):
    """Post-bounce (v+ (3 floats, m/s), w+ (3 floats, rad/s)) of one ball off the table, paper eqs
    (2)-(3), from v (m/s) and w (rad/s) just before contact (v_z < 0) and the ball's radius, m."""
    alpha, _ = table_alpha_one(vx, vy, vz, wx, wy, wz, friction, restitution_base, restitution_slope, rolling_alpha, radius)
    eps = table_restitution_one(vz, restitution_base, restitution_slope)
    # paper eq. (2): v+ = C_vv v- + C_vw w-
    v_post = ((1.0 - alpha) * vx + alpha * radius * wy, (1.0 - alpha) * vy - alpha * radius * wx, -eps * vz)
    # paper eq. (3): w+ = C_wv v- + C_ww w-
    spin_gain = 1.5 * alpha / radius
    w_post = (-spin_gain * vy + (1.0 - 1.5 * alpha) * wx, spin_gain * vx + (1.0 - 1.5 * alpha) * wy, wz)
    return v_post, w_post


@numba.njit(cache=True, error_model="numpy")
def table_gap_one(x, y, z, length, width, radius):
    """``table_gap`` of one ball centre (x, y, z), m: max(z - r, the signed horizontal distance to
    the table's rectangle)."""
    dx = abs(x) - 0.5 * length
    dy = abs(y) - 0.5 * width
    signed_distance = math.hypot(max(dx, 0.0), max(dy, 0.0)) + min(max(dx, dy), 0.0)
    return max(z - radius, signed_distance)


@numba.njit(cache=True, error_model="numpy")
def net_closest_point_one(y, z, width, overhang, height):
    """(y, z) of ``net_closest_point`` for one ball centre (its x is 0), m."""
    half_span = 0.5 * width + overhang
    return min(max(y, -half_span), half_span), min(max(z, 0.0), height)


@numba.njit(cache=True, error_model="numpy")
def net_gap_one(x, y, z, width, overhang, height, radius):
    """``net_gap`` of one ball centre (x, y, z), m."""
    y_net, z_net = net_closest_point_one(y, z, width, overhang, height)
    dy, dz = y - y_net, z - z_net
    return math.sqrt(x * x + dy * dy + dz * dz) - radius


@numba.njit(cache=True, error_model="numpy")
def net_impact_one(x, y, z, vx, vy, vz, width, overhang, height, restitution, tangential_retention):
    """Post-contact v+ (3 floats, m/s) of one ball at (x, y, z) m with v (m/s) against the net
    (``net_impact``; spin is unchanged)."""
    y_net, z_net = net_closest_point_one(y, z, width, overhang, height)
    dy, dz = y - y_net, z - z_net
    length = max(math.sqrt(x * x + dy * dy + dz * dz), 1e-12)
    nx, ny, nz = x / length, dy / length, dz / length
    v_normal = vx * nx + vy * ny + vz * nz
    if not v_normal < 0.0:  # separating: unchanged
        return vx, vy, vz
    return (tangential_retention * (vx - v_normal * nx) - restitution * v_normal * nx,
            tangential_retention * (vy - v_normal * ny) - restitution * v_normal * ny,
            tangential_retention * (vz - v_normal * nz) - restitution * v_normal * nz)


@numba.njit(cache=True, error_model="numpy")
def floor_gap_one(z, surface_height, radius):
    """``floor_gap`` of one ball centre at height z, m."""
    return z + surface_height - radius


@numba.njit(cache=True, error_model="numpy")
def floor_impact_one(vx, vy, vz, wx, wy, wz, restitution, tangential_retention):
    """Post-bounce (v+ (3 floats, m/s), w+ (3 floats, rad/s)) of one ball off the floor: v_z
    reversed with ``restitution``, the rest scaled by ``tangential_retention``."""
    return ((vx * tangential_retention, vy * tangential_retention, -restitution * vz),
            (wx * tangential_retention, wy * tangential_retention, wz * tangential_retention))


# ------------------------------------------------------------------------------ batched
# The kernels above applied to every row of (..., 3) arrays (the row loops are at the module's end).


def _rows(a, name: str):
    """(a as float rows (M, 3), the batch shape (...)) of a (..., 3) array."""
    a = np.asarray(a, dtype=float)
    if a.shape[-1:] != (3,):
        raise ValueError(f"{name}: expected an array (..., 3), got shape {a.shape}")
    return a.reshape(-1, 3), a.shape[:-1]


def _matching_rows(name: str, *arrays):
    """``_rows`` of arrays of one shape (..., 3), and that batch shape."""
    rows = [_rows(a, name) for a in arrays]
    if any(batch != rows[0][1] for _, batch in rows):
        raise ValueError(f"{name}: arrays of different shapes {[np.shape(a) for a in arrays]}")
    return [r for r, _ in rows], rows[0][1]


def table_restitution(v_z: np.ndarray, table: TableParams) -> np.ndarray:
    """eps_table (any shape, like v_z in m/s): ``table_restitution_one`` (paper, below eq. (6))."""
    v_z = np.asarray(v_z, dtype=float)
    eps = np.empty(v_z.size)
    _table_restitution_rows(v_z.reshape(-1), table.restitution_base, table.restitution_slope, eps)
    return eps.reshape(v_z.shape)[()]


def table_alpha(v_W: np.ndarray, w_W: np.ndarray, table: TableParams, radius: float):
    """The friction coefficient alpha of eq. (4) and the sliding flag v_s > 0 of eq. (5).

    v_T = [v_x - r w_y, v_y + r w_x] is the contact point's slip velocity (eq. (6)). The contact
    slides while mu (1 + eps) |v_z| / |v_T| < 2/5; eq. (5) writes this v_s = 1 - 5/2 mu (1 + eps)
    |v_z| / |v_T| > 0, and 5/2 is 1 / rolling_alpha so that the switch stays continuous if the
    rolling value is changed. A ball with no slip (|v_T| = 0) rolls. Args: v_W (..., 3) m/s, w_W
    (..., 3) rad/s, radius r (m). Returns (alpha (...), sliding (...) bool).
    """
    (v, w), batch = _matching_rows("table_alpha", v_W, w_W)
    alpha, sliding = np.empty(v.shape[0]), np.empty(v.shape[0], dtype=bool)
    _table_alpha_rows(v, w, table.friction, table.restitution_base, table.restitution_slope, table.rolling_alpha, radius,
                      alpha, sliding)
    return alpha.reshape(batch), sliding.reshape(batch)[()]


def table_impact(v_W: np.ndarray, w_W: np.ndarray, table: TableParams, radius: float):
    """Post-bounce velocity and spin off the table, paper eqs (2)-(3) with the printed matrices
    (``table_impact_one``).

    Args: v_W, w_W (..., 3) just before contact (v_z < 0); radius r (m). Returns (v+, w+).
    """
    (v, w), batch = _matching_rows("table_impact", v_W, w_W)
    v_post, w_post = np.empty(v.shape), np.empty(v.shape)
    _table_impact_rows(v, w, table.friction, table.restitution_base, table.restitution_slope, table.rolling_alpha, radius,
                       v_post, w_post)
    return v_post.reshape(batch + (3,)), w_post.reshape(batch + (3,))


def blade_standoff(radius: float, racket: RacketParams) -> float:
    """The blade centre's distance (m) behind a ball of ``radius`` m touching the blade, along
    the blade's normal: the radius plus half the blade's thickness."""
    return radius + 0.5 * racket.blade_thickness


def racket_restitution(v_normal: np.ndarray, racket: RacketParams) -> np.ndarray:
    """eps_racket(|v_z^-|), v_normal in m/s: gamma1 exp(gamma2 |v_z^-|) (paper, below eq. (8)),
    or with ``racket.restitution_law`` "linear" a + b |v_z^-| (the authors' later law, notes.md)."""
    if racket.restitution_law == "linear":
        return racket.restitution_a + racket.restitution_b * np.abs(v_normal)
    return racket.restitution_gamma1 * np.exp(racket.restitution_gamma2 * np.abs(v_normal))


def _racket_contact_frame(v_W, w_W, v_WRc, R_WC):
    """(v_rel_C, w_C): ball velocity relative to the racket (m/s) and spin (rad/s), both in C."""
    R_CW = np.swapaxes(R_WC, -1, -2)
    v_rel_C = np.einsum("...ij,...j->...i", R_CW, np.asarray(v_W, dtype=float) - v_WRc)
    w_C = np.einsum("...ij,...j->...i", R_CW, np.asarray(w_W, dtype=float))
    return v_rel_C, w_C


def _stack_racket_features(v_rel_C, w_C, contact_offset):
    """[v_rel_C, w_C, offset] (..., 8); a missing contact offset is the blade's centre (0, 0)."""
    batch = v_rel_C.shape[:-1]
    offset = np.zeros(batch + (2,)) if contact_offset is None else contact_offset
    return np.concatenate([v_rel_C, w_C, np.broadcast_to(offset, batch + (2,))], -1)


def racket_contact_features(v_W, w_W, v_WRc, R_WC, contact_offset=None) -> np.ndarray:
    """The racket residual's input (..., 8), exactly as ``racket_impact`` builds it.

    [v_rel_C (3, m/s), w_C (3, rad/s), contact offset in C's x-y (2, m)], where v_rel_C =
    R_WC^T (v_W - v_WRc) and w_C = R_WC^T w_W; shapes and frames as in ``racket_impact``.
    """
    return _stack_racket_features(*_racket_contact_frame(v_W, w_W, v_WRc, R_WC), contact_offset)


def racket_impact(
    v_W: np.ndarray,
    w_W: np.ndarray,
    v_WRc: np.ndarray,
    R_WC: np.ndarray,
    racket: RacketParams,
    radius: float,
    contact_offset: np.ndarray | None = None,
    residual: ResidualModel | None = None,
):
    """Post-contact velocity and spin off the racket, paper eqs (7)-(8).

    The linear model acts on the velocity relative to the racket, expressed in the contact frame C
    (z along the blade normal, pointing from the blade towards the ball). Note on notation: the
    paper's R maps world to racket (it writes R^T C R); here R_WC maps C to world, so
    v_C = R_WC^T v_W. Eq. (8) as printed multiplies the absolute v^-; the spin change is driven by
    the contact's slip, so like eq. (7) it uses the relative velocity here (identical for a racket
    at rest, as the table of eq. (3) is).

    Args:
        v_W, w_W: (..., 3) ball velocity (m/s) and spin (rad/s) before contact.
        v_WRc: (..., 3) velocity of the racket's material point at the contact, m/s.
        R_WC: (..., 3, 3) orientation of the contact frame in world.
        contact_offset: (..., 2) contact point on the blade in C's x-y, m (residual input only).
        residual: optional correction model; its output (..., 6) is added to [v+, w+] in C.
    Returns (v+, w+) in world, (..., 3) each.
    """
    v_rel_C, w_C = _racket_contact_frame(v_W, w_W, v_WRc, R_WC)
    k = racket.tangential_k
    eps = racket_restitution(v_rel_C[..., 2], racket)
    vx, vy, vz = v_rel_C[..., 0], v_rel_C[..., 1], v_rel_C[..., 2]
    wx, wy, wz = w_C[..., 0], w_C[..., 1], w_C[..., 2]
    # paper eq. (7), in C: C_vv (v- - v_racket) + C_vw w-
    v_post_C = np.stack(
        [(1.0 - k) * vx + k * radius * wy, (1.0 - k) * vy - k * radius * wx, -eps * vz], axis=-1
    )
    # paper eq. (8), in C: C_wv v_rel + C_ww w-
    spin_gain = 1.5 * k / radius
    w_post_C = np.stack(
        [-spin_gain * vy + (1.0 - 1.5 * k) * wx, spin_gain * vx + (1.0 - 1.5 * k) * wy, wz], axis=-1
    )
    if residual is not None:
        flat = _stack_racket_features(v_rel_C, w_C, contact_offset).reshape(-1, 8)
        correction = np.asarray(residual(flat), dtype=float).reshape(v_rel_C.shape[:-1] + (6,))
        v_post_C = v_post_C + correction[..., :3]
        w_post_C = w_post_C + correction[..., 3:]
    v_post = np.einsum("...ij,...j->...i", R_WC, v_post_C) + v_WRc
    w_post = np.einsum("...ij,...j->...i", R_WC, w_post_C)
    return v_post, w_post


def table_gap(p_W: np.ndarray, table: TableParams, radius: float) -> np.ndarray:
    """Continuous guard for the playing surface, m (...): <= 0 exactly when the ball touches it.

    max(z - r, d), with d the signed horizontal distance of the ball centre p_W (..., 3) to the
    table's rectangle (negative over the table), so a ball passing beside the table never triggers
    it (``table_gap_one``).
    """
    p, batch = _rows(p_W, "table_gap")
    gap = np.empty(p.shape[0])
    _table_gap_rows(p, table.length, table.width, radius, gap)
    return gap.reshape(batch)[()]


def net_closest_point(p_W: np.ndarray, table: TableParams, net: NetParams) -> np.ndarray:
    """Closest point (..., 3) to p_W (..., 3) on the net, a thin rectangle x = 0,
    |y| <= W/2 + overhang, 0 <= z <= h, m (``net_closest_point_one``)."""
    p, batch = _rows(p_W, "net_closest_point")
    closest = np.empty(p.shape)
    _net_closest_point_rows(p, table.width, net.overhang, net.height, closest)
    return closest.reshape(batch + (3,))


def net_gap(p_W: np.ndarray, table: TableParams, net: NetParams, radius: float) -> np.ndarray:
    """Distance (...) from the ball's surface to the net (face, top cord or side edge), m, for ball
    centres p_W (..., 3) (``net_gap_one``)."""
    p, batch = _rows(p_W, "net_gap")
    gap = np.empty(p.shape[0])
    _net_gap_rows(p, table.width, net.overhang, net.height, radius, gap)
    return gap.reshape(batch)[()]


def net_impact(p_W, v_W, w_W, table: TableParams, net: NetParams):
    """Post-contact velocity and spin against the net (``net_impact_one``).

    The contact normal runs from the closest net point to the ball centre: along x on the face,
    tilted over the top cord, so a ball clipping the cord high keeps its forward speed and goes over
    (a net-cord ball, paper Fig. 4). Normal velocity is reversed with ``net.restitution``, tangential
    velocity scaled by ``net.tangential_retention``; spin is unchanged; a separating ball is
    unchanged. Args: p_W (m), v_W (m/s), w_W (rad/s), (..., 3) each. Returns (v+, w+).
    """
    (p, v, w), batch = _matching_rows("net_impact", p_W, v_W, w_W)
    v_post = np.empty(v.shape)
    _net_impact_rows(p, v, table.width, net.overhang, net.height, net.restitution, net.tangential_retention, v_post)
    return v_post.reshape(batch + (3,)), w.reshape(batch + (3,)).copy()


def floor_gap(p_W: np.ndarray, table: TableParams, radius: float) -> np.ndarray:
    """Height (...) of the ball's bottom above the floor (z = -surface_height), m, for ball centres
    p_W (..., 3) (``floor_gap_one``)."""
    p, batch = _rows(p_W, "floor_gap")
    gap = np.empty(p.shape[0])
    _floor_gap_rows(p, table.surface_height, radius, gap)
    return gap.reshape(batch)[()]


def floor_impact(v_W, w_W, floor: FloorParams):
    """Post-bounce velocity and spin off the floor: v_z reversed with restitution, tangential scaled
    (``floor_impact_one``). Args: v_W (m/s), w_W (rad/s), (..., 3) each. Returns (v+, w+)."""
    (v, w), batch = _matching_rows("floor_impact", v_W, w_W)
    v_post, w_post = np.empty(v.shape), np.empty(v.shape)
    _floor_impact_rows(v, w, floor.restitution, floor.tangential_retention, v_post, w_post)
    return v_post.reshape(batch + (3,)), w_post.reshape(batch + (3,))


def perturb_velocity_and_spin(v_W, w_W, velocity_std: float, spin_std: float, rng: np.random.Generator):
    """Adds independent zero-mean Gaussian noise to each component (paper, *Physics perturbations*)."""
    v_W = np.asarray(v_W, dtype=float)
    w_W = np.asarray(w_W, dtype=float)
    return (
        v_W + velocity_std * rng.standard_normal(v_W.shape),
        w_W + spin_std * rng.standard_normal(w_W.shape),
    )


# ------------------------------------------------------------------------------ racket geometry
# The blade is a disc of radius R_b and thickness t whose frame R has its origin at the blade's
# centre and its z axis along the blade's normal (DESIGN.md). These functions are the one
# definition of the ball-blade geometry, shared by the BallPlant and ``physics.segment``; all are
# batched over leading dimensions. The gap and the contact frame are written component by
# component (no einsum or matmul, whose summation may depend on the batch's shape), so a row's
# gap is the same bit for bit in any batch; ``racket_impact`` is not (the segment propagator
# applies it one contact at a time, with the BallPlant's shapes).


def blade_half_diagonal(racket: RacketParams) -> float:
    """The radius (m) of the smallest sphere about the blade's centre holding the whole blade,
    hypot(R_b, t / 2): every blade point lies within it."""
    return float(np.hypot(racket.blade_radius, 0.5 * racket.blade_thickness))


def _rotate(R, p, transpose: bool):
    """R p (or R^T p) for R (..., 3, 3) and p (..., 3), component by component (no einsum, whose
    summation strategy may depend on the batch's shape)."""
    if transpose:
        columns = [R[..., 0, i] * p[..., 0] + R[..., 1, i] * p[..., 1] + R[..., 2, i] * p[..., 2] for i in range(3)]
    else:
        columns = [R[..., i, 0] * p[..., 0] + R[..., i, 1] * p[..., 1] + R[..., i, 2] * p[..., 2] for i in range(3)]
    out = np.empty(np.broadcast_shapes(R.shape[:-1], p.shape))
    out[..., 0], out[..., 1], out[..., 2] = columns
    return out


def _cross(a, b):
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _norm(a):
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2])


def ball_in_racket_frame(p_WB, p_WR, R_WR) -> np.ndarray:
    """p_RB = R_WR^T (p_WB - p_WR): the ball centre in the racket frame R, m. Args: p_WB (..., 3)
    ball centre, p_WR (..., 3) blade centre, R_WR (..., 3, 3) racket orientation, all in world."""
    p_WB, p_WR, R_WR = (np.asarray(a, dtype=float) for a in (p_WB, p_WR, R_WR))
    return _rotate(R_WR, p_WB - p_WR, transpose=True)


def closest_blade_point(p_RB, racket: RacketParams) -> np.ndarray:
    """The blade's point closest to p_RB (..., 3), both in R, m: the point's radial part clipped
    to the disc's radius and its z to the half-thickness."""
    p_RB = np.asarray(p_RB, dtype=float)
    radial = np.hypot(p_RB[..., 0], p_RB[..., 1])
    outside = radial > 0
    scale = np.where(outside, np.minimum(1.0, racket.blade_radius / np.where(outside, radial, 1.0)), 1.0)
    half_thickness = 0.5 * racket.blade_thickness
    closest = np.empty(p_RB.shape)
    closest[..., 0] = p_RB[..., 0] * scale
    closest[..., 1] = p_RB[..., 1] * scale
    closest[..., 2] = np.clip(p_RB[..., 2], -half_thickness, half_thickness)
    return closest


def racket_gap(p_WB, p_WR, R_WR, racket: RacketParams, radius: float) -> np.ndarray:
    """Distance from the ball's surface to the blade, m (..., ): <= 0 exactly in contact.
    Args as ``ball_in_racket_frame``; radius r of the ball, m."""
    p_RB = ball_in_racket_frame(p_WB, p_WR, R_WR)
    return _norm(p_RB - closest_blade_point(p_RB, racket)) - radius


def racket_contact_frame(p_RB, racket: RacketParams):
    """The contact point p_RC (..., 3) and the contact frame's orientation R_RC (..., 3, 3), in R,
    for a ball at p_RB (..., 3) touching the blade.

    C's z axis is the normal from the closest blade point towards the ball centre (the face's
    normal, flipped on the back face, tilted on the rim); its x axis is R's x made orthogonal to
    the normal (R's y when the normal is along R's x)."""
    p_RB = np.asarray(p_RB, dtype=float)
    p_RC = closest_blade_point(p_RB, racket)
    offset = p_RB - p_RC
    normal = offset / np.maximum(_norm(offset), 1e-12)[..., None]
    x_axis = -normal[..., 0:1] * normal
    x_axis[..., 0] += 1.0
    along_x = _norm(x_axis) < 1e-6
    if np.any(along_x):
        y_axis = -normal[..., 1:2] * normal
        y_axis[..., 1] += 1.0
        x_axis = np.where(along_x[..., None], y_axis, x_axis)
    x_axis = x_axis / _norm(x_axis)[..., None]
    R_RC = np.stack([x_axis, _cross(normal, x_axis), normal], axis=-1)
    return p_RC, R_RC


def racket_contact(state, p_WR, R_WR, w_WR, v_WR, racket: RacketParams, radius: float, residual: ResidualModel | None = None):
    """The ball's state after touching the blade, and whether the touch is an impact.

    At the contact point C (``racket_contact_frame``) the racket's material point moves at
    v_WRc = v_WR + w_WR x (p_WC - p_WR). A ball whose velocity relative to it has no component
    into the blade (v - v_WRc) . z_C >= 0 is separating: a graze, the state is unchanged and the
    flag False. Otherwise the post-contact velocity and spin are ``racket_impact``'s (paper eqs
    (7)-(8), with the contact offset in C's x-y as the residual's input).

    Args: state (..., 9) [p, v, w] just before contact; p_WR (..., 3), R_WR (..., 3, 3) the
    racket's pose; w_WR (..., 3) rad/s and v_WR (..., 3) m/s its spatial velocity (of R's origin),
    all in world; residual, an optional correction model. Returns (state_post (..., 9), impact
    (...,) bool).
    """
    state = np.asarray(state, dtype=float)
    batch = state.shape[:-1]
    state = state.reshape(-1, 9)
    p_WR, w_WR, v_WR = (np.broadcast_to(np.asarray(a, dtype=float), batch + (3,)).reshape(-1, 3) for a in (p_WR, w_WR, v_WR))
    R_WR = np.broadcast_to(np.asarray(R_WR, dtype=float), batch + (3, 3)).reshape(-1, 3, 3)
    p_WB, v_WB, w_WB = state[:, 0:3], state[:, 3:6], state[:, 6:9]
    p_RC, R_RC = racket_contact_frame(ball_in_racket_frame(p_WB, p_WR, R_WR), racket)
    R_WC = np.stack([_rotate(R_WR, R_RC[..., j], transpose=False) for j in range(3)], axis=-1)
    p_RoC_W = _rotate(R_WR, p_RC, transpose=False)  # from the blade's centre to C, in world
    v_WRc = v_WR + _cross(w_WR, p_RoC_W)
    v_relative = v_WB - v_WRc
    approach = v_relative[:, 0] * R_WC[:, 0, 2] + v_relative[:, 1] * R_WC[:, 1, 2] + v_relative[:, 2] * R_WC[:, 2, 2]
    impact = approach < 0.0
    post = state.copy()
    if np.any(impact):
        contact_offset = _rotate(R_RC[impact], p_RC[impact], transpose=True)[:, :2]
        v_post, w_post = racket_impact(
            v_WB[impact], w_WB[impact], v_WRc[impact], R_WC[impact], racket, radius,
            contact_offset=contact_offset, residual=residual,
        )  # paper eqs (7)-(8)
        post[impact, 3:6] = v_post
        post[impact, 6:9] = w_post
    return post.reshape(batch + (9,)), impact.reshape(batch)


# ------------------------------------------------------------------------------ row loops
# The one-ball kernels over the rows (M, 3) of the batched functions' arrays, into their outputs.


@numba.njit(cache=True, error_model="numpy")
def _table_restitution_rows(v_z, restitution_base, restitution_slope, eps):
    for i in range(v_z.shape[0]):
        eps[i] = table_restitution_one(v_z[i], restitution_base, restitution_slope)


@numba.njit(cache=True, error_model="numpy")
def _table_alpha_rows(v, w, friction, restitution_base, restitution_slope, rolling_alpha, radius, alpha, sliding):
    for i in range(v.shape[0]):
        alpha[i], sliding[i] = table_alpha_one(v[i, 0], v[i, 1], v[i, 2], w[i, 0], w[i, 1], w[i, 2], friction, restitution_base,
                                               restitution_slope, rolling_alpha, radius)


@numba.njit(cache=True, error_model="numpy")
def _table_impact_rows(v, w, friction, restitution_base, restitution_slope, rolling_alpha, radius, v_post, w_post):
    for i in range(v.shape[0]):
        (v_post[i, 0], v_post[i, 1], v_post[i, 2]), (w_post[i, 0], w_post[i, 1], w_post[i, 2]) = table_impact_one(
            v[i, 0], v[i, 1], v[i, 2], w[i, 0], w[i, 1], w[i, 2], friction, restitution_base, restitution_slope, rolling_alpha,
            radius)


@numba.njit(cache=True, error_model="numpy")
def _table_gap_rows(p, length, width, radius, gap):
    for i in range(p.shape[0]):
        gap[i] = table_gap_one(p[i, 0], p[i, 1], p[i, 2], length, width, radius)


@numba.njit(cache=True, error_model="numpy")
def _net_closest_point_rows(p, width, overhang, height, closest):
    for i in range(p.shape[0]):
        closest[i, 0] = 0.0
        closest[i, 1], closest[i, 2] = net_closest_point_one(p[i, 1], p[i, 2], width, overhang, height)


@numba.njit(cache=True, error_model="numpy")
def _net_gap_rows(p, width, overhang, height, radius, gap):
    for i in range(p.shape[0]):
        gap[i] = net_gap_one(p[i, 0], p[i, 1], p[i, 2], width, overhang, height, radius)


@numba.njit(cache=True, error_model="numpy")
def _net_impact_rows(p, v, width, overhang, height, restitution, tangential_retention, v_post):
    for i in range(p.shape[0]):
        v_post[i, 0], v_post[i, 1], v_post[i, 2] = net_impact_one(
            p[i, 0], p[i, 1], p[i, 2], v[i, 0], v[i, 1], v[i, 2], width, overhang, height, restitution, tangential_retention)


@numba.njit(cache=True, error_model="numpy")
def _floor_gap_rows(p, surface_height, radius, gap):
    for i in range(p.shape[0]):
        gap[i] = floor_gap_one(p[i, 2], surface_height, radius)


@numba.njit(cache=True, error_model="numpy")
def _floor_impact_rows(v, w, restitution, tangential_retention, v_post, w_post):
    for i in range(v.shape[0]):
        (v_post[i, 0], v_post[i, 1], v_post[i, 2]), (w_post[i, 0], w_post[i, 1], w_post[i, 2]) = floor_impact_one(
            v[i, 0], v[i, 1], v[i, 2], w[i, 0], w[i, 1], w[i, 2], restitution, tangential_retention)
