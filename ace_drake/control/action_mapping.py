"""The action mapping of paper eq. (12): policy actions in [-1, 1]^(2 x 8) onto feasible terminal
joint states 32 ms ahead, and its inverse.

An action is 16 numbers: row 0 of its (2, 8) form is the eight joints' terminal-position
components, row 1 their terminal-velocity components (JOINT_NAMES order). The mapping is applied
per joint, from the square X = [-1, 1]^2 (centre 0) to the joint's feasible set Y = F_i of
``feasible_set`` (centre y_bar); the product of eight bijections is a bijection of the whole
action box onto the product of the feasible sets. With the paper's notation, for x = delta != 0,

    alpha = 1 / ||delta||_inf                  (x_bar + alpha delta on the square's boundary),
    f(delta) = (s_q delta_q, s_v delta_v)       (the shape function: scale by F_i's half-widths),
    beta: y_bar + beta f(delta) on dF_i        (``FeasibleSets.boundary_distance``),
    y = y_bar + (beta / alpha) f(delta),

and y = y_bar for delta = 0. The map is radial in the direction f(delta), so it sends the centre to
the centre, the square's boundary (||delta||_inf = 1) to F_i's boundary, and is inverted by
casting the ray y - y_bar back: ||delta||_inf = |y - y_bar| / |boundary - y_bar| and delta's
direction is f^-1(y - y_bar).
"""

from __future__ import annotations

import numba
import numpy as np

from ace_drake.control.feasible_set import FeasibleSets, edge_distance
from ace_drake.robot.params import JOINT_NAMES

ACTION_SIZE = 2 * len(JOINT_NAMES)


def is_valid_action(action) -> bool:
    """Whether a policy's output ``action`` is an action: 16 finite numbers (values beyond [-1, 1]
    are clipped into the box by whoever executes it). The one test of a policy's output, shared
    by the PolicyController (which counts anything else as an invalid action) and the hit-state
    layer (which passes an actor's invalid output on to it unchanged)."""
    try:
        action = np.asarray(action, dtype=float)
    except (TypeError, ValueError):
        return False
    return action.shape == (ACTION_SIZE,) and bool(np.all(np.isfinite(action)))


def map_action(action: np.ndarray, sets: FeasibleSets) -> tuple[np.ndarray, np.ndarray]:
    """Terminal joint positions and velocities (q_T, v_T), each (..., 8) in rad or m and per s,
    for actions (..., 16) in [-1, 1] (paper eq. (12)). Values outside [-1, 1] or not finite raise
    ValueError: a policy's output is squashed into the box, so anything else is a bug upstream.
    One compiled loop over the joints (``_map_pairs``)."""
    action = np.asarray(action, dtype=float)
    if action.shape[-1:] != (ACTION_SIZE,):
        raise ValueError(f"action: expected {ACTION_SIZE} values per action (2 x 8), got shape {action.shape}")
    batch = action.shape[:-1] if action.shape[:-1] == sets.batch_shape else np.broadcast_shapes(action.shape[:-1], sets.batch_shape)
    centre, scale, normals, offsets = sets.joint_arrays(batch)
    actions = np.ascontiguousarray(np.broadcast_to(action, batch + (ACTION_SIZE,))).reshape(-1, ACTION_SIZE)
    q, v = np.empty(batch + (len(JOINT_NAMES),)), np.empty(batch + (len(JOINT_NAMES),))
    if not _map_pairs(actions, centre, scale, normals, offsets, q.reshape(-1), v.reshape(-1)):
        raise ValueError(f"map_action: actions must be finite and in [-1, 1], got {action}")
    return q, v


@numba.njit(cache=True)
def _map_pairs(actions, centre, scale, normals, offsets, q, v):
    """``map_action`` of actions (B, 16) onto the sets of B x 8 joints (``FeasibleSets.joint_arrays``),
    into q and v (B x 8,): per joint, with delta its (position, velocity) components,
    y = y_bar + (beta / alpha) f(delta) (module docstring). False (and the outputs meaningless)
    if an action is not finite or not within [-1, 1] (to 1e-12)."""
    joints = actions.shape[1] // 2
    for b in range(actions.shape[0]):
        for j in range(joints):
            d0, d1 = actions[b, j], actions[b, joints + j]
            if not (abs(d0) <= 1.0 + 1e-12 and abs(d1) <= 1.0 + 1e-12):  # also catches NaN; inf is beyond
                return False
    for b in range(actions.shape[0]):
        for j in range(joints):
            s = b * joints + j
            d0, d1 = actions[b, j], actions[b, joints + j]
            size = max(abs(d0), abs(d1))  # ||delta||_inf = 1 / alpha
            f0, f1 = d0 * scale[s, 0], d1 * scale[s, 1]  # f(delta)
            beta = edge_distance(normals[s], offsets[s], centre[s, 0], centre[s, 1], f0, f1)
            step = size * (beta if np.isfinite(beta) else 0.0) if size > 0.0 else 0.0  # beta / alpha
            q[s] = centre[s, 0] + step * f0
            v[s] = centre[s, 1] + step * f1
    return True


def inverse_map_action(q_terminal: np.ndarray, v_terminal: np.ndarray, sets: FeasibleSets) -> np.ndarray:
    """The action (..., 16) that ``map_action`` sends to (q_T, v_T) (..., 8). A terminal state
    outside the feasible set gives components beyond [-1, 1]: clip them to get the action of the
    boundary point on the same ray. One compiled loop over the joints (``_inverse_pairs``)."""
    q_terminal, v_terminal = np.asarray(q_terminal, dtype=float), np.asarray(v_terminal, dtype=float)
    if q_terminal.shape != v_terminal.shape:
        raise ValueError(f"inverse_map_action: q_terminal and v_terminal must share a shape, got {q_terminal.shape} and {v_terminal.shape}")
    batch = q_terminal.shape[:-1] if q_terminal.shape[:-1] == sets.batch_shape else np.broadcast_shapes(q_terminal.shape[:-1], sets.batch_shape)
    centre, scale, normals, offsets = sets.joint_arrays(batch)
    q, v = (np.ascontiguousarray(np.broadcast_to(x, batch + sets.centre.shape[-2:-1])).reshape(-1) for x in (q_terminal, v_terminal))
    out = np.empty(batch + (ACTION_SIZE,))
    _inverse_pairs(q, v, centre, scale, normals, offsets, out.reshape(-1, ACTION_SIZE))
    return out


@numba.njit(cache=True, error_model="numpy")  # numpy: x / 0 is inf or NaN, not an exception
def _inverse_pairs(q, v, centre, scale, normals, offsets, out):
    """``inverse_map_action`` of terminal states q, v (B x 8,) in the sets of B x 8 joints
    (``FeasibleSets.joint_arrays``), into the actions out (B, 16): the ray from the centre through
    y cast back, ||delta||_inf = |y - y_bar| / |boundary - y_bar| along f^-1(y - y_bar)."""
    joints = out.shape[1] // 2
    for b in range(out.shape[0]):
        for j in range(joints):
            s = b * joints + j
            o0, o1 = q[s] - centre[s, 0], v[s] - centre[s, 1]  # y - y_bar
            to_boundary = edge_distance(normals[s], offsets[s], centre[s, 0], centre[s, 1], o0, o1)  # the boundary is at y_bar + t (y - y_bar)
            u0, u1 = o0 / scale[s, 0], o1 / scale[s, 1]  # f^-1(y - y_bar)
            largest = np.nan if (u0 != u0 or u1 != u1) else max(abs(u0), abs(u1))
            if largest > 0.0:
                out[b, j], out[b, joints + j] = u0 / (largest * to_boundary), u1 / (largest * to_boundary)
            else:
                out[b, j], out[b, joints + j] = 0.0, 0.0
