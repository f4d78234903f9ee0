"""Reinforcement learning: the rally environment, its observation and rewards, the learner (SAC
with the auxiliary decoder loss and an optional cloning term, event tables, hindsight relabelling,
mirroring; the hit-state action's torch kinematics and cloning loss, ``hit_state``), the rollout
workers (``rollout``, ``workers``: Ray) and the training run (``trainer``: ``ace-drake train``).

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
from ace_drake.learning.mirror import JointMirror, Mirror
from ace_drake.learning.networks import Actor, DeterministicPolicy, TwinCritic
from ace_drake.learning.replay import EVENTS, EpisodeSummary, EventReplay, EventThresholds, ReplayConfig, episode_events, relabel_episode
from ace_drake.learning.sac import SacConfig, SacLearner, soft_target
from ace_drake.learning.rewards import position_term, return_reward, spin_term, terminal_reward, travel_frame_spin

__all__ = [
    "EVENTS",
    "Actor",
    "DeterministicPolicy",
    "EpisodeSummary",
    "EventReplay",
    "EventThresholds",
    "JointMirror",
    "Mirror",
    "ReplayConfig",
    "SacConfig",
    "SacLearner",
    "TwinCritic",
    "episode_events",
    "relabel_episode",
    "soft_target",
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
