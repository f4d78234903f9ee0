"""A rally episode's terminal reward (paper, Methods *Rewards*, eq. (10)), as pure functions.

All reward terms are computed once the episode has ended, from its terminal state: what the
episode's outcome was (``play.episode.classify``) and, for a return, the ball state at landing:

    R = R_miss     if the robot did not hit the ball (missed, passed, timed out, or its
                   command would have collided),
        R_hit      if it hit the ball but did not return it,
        R_return   if it returned it,

    R_return = return_base
             + w_p * position_reward * exp(-|y_land - y_desired| / position_length)
             + w_s * spin_gain * omega_y.

The skill [y_desired (m), w_p in [0, 1], w_s in [-1, 1]] is fixed for the episode (paper, *States*).
y_land is the y of the ball's centre at its first table contact after the hit. omega_y is the
ball's spin about the y axis of its travel frame B at that contact: x_B is the ball's horizontal
direction of travel, z_B the world's up, y_B = z_B x x_B, so omega_y > 0 is topspin (the ball's
top turning towards where it goes) and < 0 backspin, whichever way the ball flies. omega_y is
unchanged by mirroring across the XZ plane, and the position term is too when y_desired is
mirrored with the landing (issue 7's symmetric augmentation). Numbers: ``config.RewardParams``.

Functions take arrays and broadcast over leading batch dimensions (``(..., 9)`` ball states,
``(..., 3)`` skills), so that hindsight relabelling can recompute rewards in batches.
"""

from __future__ import annotations

import numpy as np

from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.learning.params import RewardParams

UP = np.array([0.0, 0.0, 1.0])


def travel_frame_spin(ball_state) -> np.ndarray:
    """omega_y (...,), rad/s: the spin w_WB of ``ball_state`` (..., 9) [p, v, w] about the y axis
    of the ball's travel frame (module docstring); topspin > 0. 0 for a ball with no horizontal
    velocity (its travel frame is undefined)."""
    state = np.asarray(ball_state, dtype=float)
    v_horizontal = state[..., 3:6] * np.array([1.0, 1.0, 0.0])
    speed = np.linalg.norm(v_horizontal, axis=-1, keepdims=True)
    x_B = np.divide(v_horizontal, speed, out=np.zeros_like(v_horizontal), where=speed > 0.0)
    y_B = np.cross(UP, x_B)
    return np.sum(state[..., 6:9] * y_B, axis=-1)


def position_term(y_land, y_desired, params: RewardParams) -> np.ndarray:
    """position_reward * exp(-|y_land - y_desired| / position_length): the position term before
    its weight w_p; its maximum, position_reward, at y_land = y_desired."""
    distance = np.abs(np.asarray(y_land, dtype=float) - np.asarray(y_desired, dtype=float))
    return params.position_reward * np.exp(-distance / params.position_length)


def spin_term(landing_state, params: RewardParams) -> np.ndarray:
    """spin_gain * omega_y at landing: the spin term before its weight w_s (paper: "proportional
    to the angular velocity in the y-axis of the ball frame on landing")."""
    return params.spin_gain * travel_frame_spin(landing_state)


def return_reward(landing_state, skill, params: RewardParams) -> np.ndarray:
    """R_return (...,) for a return that landed in ``landing_state`` (..., 9), the ball just
    before its first table contact after the hit, under ``skill`` (..., 3) [y_desired, w_p, w_s]
    (paper eq. (10) with the module docstring's terms)."""
    landing_state = np.asarray(landing_state, dtype=float)
    skill = np.asarray(skill, dtype=float)
    y_desired, w_p, w_s = skill[..., 0], skill[..., 1], skill[..., 2]
    position = position_term(landing_state[..., 1], y_desired, params)
    return params.return_base + w_p * position + w_s * spin_term(landing_state, params)


def terminal_reward(result: EpisodeResult, skill, params: RewardParams, collided: bool = False) -> float:
    """The reward of an ended episode (paper eq. (10)): from its final ``result`` (an outcome
    other than IN_PLAY; a time-limited episode's ``episode.timed_out`` result) and the episode's
    skill [y_desired (m), w_p, w_s]. ``collided``: the episode ended because a commanded motion
    would have collided (end condition (4)); it scores ``params.collision`` unless the robot had
    already hit the ball (then ``result`` may still be IN_PLAY). Raises ValueError for an
    IN_PLAY result otherwise."""
    if collided and result.hit is None:
        return params.collision
    if result.outcome is Outcome.IN_PLAY:
        raise ValueError("terminal_reward: the episode is still in play; rewards are terminal")
    if result.outcome is Outcome.RETURNED:
        return float(return_reward(result.landing.state_pre, skill, params))
    if result.hit is not None:  # NOT_RETURNED, whether the hit was early, short, long or double
        return params.hit
    if result.outcome is Outcome.INVALID:
        return params.invalid
    return params.miss
