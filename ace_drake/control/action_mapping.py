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

import numpy as np

from ace_drake.control.feasible_set import FeasibleSets
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


def _as_joint_pairs(action: np.ndarray) -> np.ndarray:
    """(..., 16) actions as (..., 8, 2) per-joint (position, velocity) components."""
    action = np.asarray(action, dtype=float)
    if action.shape[-1:] != (ACTION_SIZE,):
        raise ValueError(f"action: expected {ACTION_SIZE} values per action (2 x 8), got shape {action.shape}")
    return np.swapaxes(action.reshape(*action.shape[:-1], 2, len(JOINT_NAMES)), -1, -2)


def map_action(action: np.ndarray, sets: FeasibleSets) -> tuple[np.ndarray, np.ndarray]:
    """Terminal joint positions and velocities (q_T, v_T), each (..., 8) in rad or m and per s,
    for actions (..., 16) in [-1, 1] (paper eq. (12)). Values outside [-1, 1] or not finite raise
    ValueError: a policy's output is squashed into the box, so anything else is a bug upstream."""
    delta = _as_joint_pairs(action)
    if not np.all(np.isfinite(delta)) or np.any(np.abs(delta) > 1.0 + 1e-12):
        raise ValueError(f"map_action: actions must be finite and in [-1, 1], got {np.asarray(action)}")
    size = np.max(np.abs(delta), axis=-1)  # ||delta||_inf = 1 / alpha
    shaped = delta * sets.scale  # f(delta)
    beta = sets.boundary_distance(shaped)
    step = np.where(size > 0.0, size * np.where(np.isfinite(beta), beta, 0.0), 0.0)  # beta / alpha
    y = sets.centre + step[..., None] * shaped
    return y[..., 0], y[..., 1]


def inverse_map_action(q_terminal: np.ndarray, v_terminal: np.ndarray, sets: FeasibleSets) -> np.ndarray:
    """The action (..., 16) that ``map_action`` sends to (q_T, v_T) (..., 8). A terminal state
    outside the feasible set gives components beyond [-1, 1]: clip them to get the action of the
    boundary point on the same ray."""
    y = np.stack([np.asarray(q_terminal, dtype=float), np.asarray(v_terminal, dtype=float)], axis=-1)
    offset = y - sets.centre
    to_boundary = sets.boundary_distance(offset)  # the boundary is at centre + t offset
    unscaled = offset / sets.scale  # f^-1(y - y_bar)
    largest = np.max(np.abs(unscaled), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where((largest > 0.0)[..., None], unscaled / (largest * to_boundary)[..., None], 0.0)
    pairs = np.swapaxes(delta, -1, -2)
    return pairs.reshape(*pairs.shape[:-2], ACTION_SIZE)
