"""Reinforcement learning: the rally environment, its observation and rewards (issue 7 adds the
learner).

Importing this package does not import Drake's diagram builders; ``RallyEnv`` builds its
training diagram when constructed.
"""

from ace_drake.learning.observation import ObservationLayout
from ace_drake.learning.rally_env import (
    END_CONDITIONS,
    PRIVILEGED_PARTS,
    RallyEnv,
    RallyEnvParams,
    SkillSampling,
    privileged_slice,
)
from ace_drake.learning.rewards import position_term, return_reward, spin_term, terminal_reward, travel_frame_spin

__all__ = [
    "END_CONDITIONS",
    "PRIVILEGED_PARTS",
    "ObservationLayout",
    "RallyEnv",
    "RallyEnvParams",
    "SkillSampling",
    "position_term",
    "privileged_slice",
    "return_reward",
    "spin_term",
    "terminal_reward",
    "travel_frame_spin",
]
