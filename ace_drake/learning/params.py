"""Learning configs: the rally episode's terminal reward (eq. 10).
"""

from __future__ import annotations

import dataclasses

from ace_drake.config import require_non_negative, require_positive


@dataclasses.dataclass(frozen=True)
class RewardParams:
    """A rally episode's terminal reward (paper eq. (10), *Rewards*; ``learning/rewards.py``):

        R_miss                    the robot did not hit the ball,
        R_hit                     it hit the ball but did not return it,
        R_return = return_base + w_p position_reward exp(-|y_land - y_desired| / position_length)
                               + w_s spin_gain omega_y,

    with the skill [y_desired, w_p, w_s] and omega_y the ball's spin about the y axis of its
    travel frame at landing (topspin > 0). The paper gives no numbers: these are this project's.
    """

    miss: float = -1.0  # R_miss, also for an episode timed out before any hit
    # An episode ended because the commanded motion would collide (paper's end condition (4)): the
    # robot did not hit the ball, so R_miss by default; lower it to punish such commands more.
    collision: float = -1.0
    hit: float = 0.0  # R_hit (not returned): between a miss and a return, so touching the ball pays
    return_base: float = 1.0  # every return gets this, whatever the skill
    # The position term's maximum, at y_land = y_desired (hindsight relabelling gives it): equal to
    # the base, so that an aimed return is worth twice an unaimed one.
    position_reward: float = 1.0
    position_length: float = 0.3  # m; a landing 0.3 m off y_desired gets 37 % (the half is 1.525 m wide)
    spin_gain: float = 1.0 / 400.0  # per rad/s: 400 rad/s of topspin (about the robot's p90 spin) gives 1
    invalid: float = 0.0  # the opponent's shot was a fault: there was no play to make

    def __post_init__(self) -> None:
        require_positive(self, "position_length")
        require_non_negative(self, "position_reward", "spin_gain")

