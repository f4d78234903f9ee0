"""The contracts that layers above share: the observation a rally controller reads every 32 ms
(``ObservationLayout``), the critic's privileged observation (``PRIVILEGED_PARTS``), and how an
episode ended (``Outcome``, ``EpisodeResult``, ``END_CONDITIONS``). Plain Python and NumPy, at the
bottom of the layers (docs/architecture.md), so that controllers, systems, learners and
applications agree on them without importing each other.

The observation.

Paper, Methods *States*: s_t = [s_ball, s_robot, s_skill]: the last N noisy ball positions and
spins with their time stamps, the robot's joint state (q, v, a) and end-effector state (pose and
twist) at the end of the segment being executed (where the next segment starts, 5 ms after the
observation), and the skill state (y_desired, w_reward = [w_p, w_s]). The vector also carries the
ball estimator's output (state and status), which the paper's actor does not read but classical
controllers (the model-based returner) do, and the preferred hit predicted from that estimate
(``control.hit_prediction``: the memoryless returner's choice of where to meet the ball), which a
learned actor may read in place of learning the ball's flight and bounce itself (this project's
addition; docs/training.md, *The trainer*); a learner picks its features by ``ObservationLayout`` slices, so
every controller shares one observation port.

Layout (all SI units; ages in s, -1 where the history has fewer entries):

    positions   (N_p, 4)  [p_WB (m), age], newest first
    spins       (N_s, 4)  [w_WB (rad/s), age], newest first
    robot_state (24,)     [q, v, a] at the next segment's start (m, rad; /s; /s^2)
    end_effector (13,)    [p_WR (m), quaternion wxyz, v_WR (m/s), w_WR (rad/s)] there
    skill       (3,)      [y_desired (m), w_p, w_s]
    estimate    (9,)      the EKF's [p, v, w] at the observation time (zeros without a track)
    estimate_status (3,)  [valid, spin valid, age of newest measurement used (s)]
    hit_prediction (11,)  [valid, time from the observation to the preferred hit (s), the predicted
                          ball state there: p (m), v (m/s), w (rad/s)] (zeros without one)
"""

from __future__ import annotations

import dataclasses
import enum
from typing import TYPE_CHECKING

import numpy as np

# The best shipped controller, what ``ace-drake rally`` and ``evaluate`` play with by default
# (``evaluation.controllers`` makes it; here so that the CLI's parser names it without loading it).
DEFAULT_CONTROLLER = "returner"

if TYPE_CHECKING:  # a type only: physics sits above the contracts (docs/architecture.md)
    from ace_drake.physics.propagate import ContactEvent

ROBOT_STATE_SIZE = 24
END_EFFECTOR_SIZE = 13
SKILL_SIZE = 3
ESTIMATE_SIZE = 9
ESTIMATE_STATUS_SIZE = 3
HIT_PREDICTION_SIZE = 11  # [valid, time (s), ball state (9)]: control.hit_prediction
HISTORY_COLUMNS = 4  # value (3) + age (1)


@dataclasses.dataclass(frozen=True)
class ObservationLayout:
    """Slices of the observation vector (module docstring) for history lengths N_p and N_s."""

    position_history: int = 10
    spin_history: int = 10

    def __post_init__(self) -> None:
        if self.position_history < 1 or self.spin_history < 1:
            raise ValueError(f"ObservationLayout: history lengths must be >= 1, got {self.position_history}, {self.spin_history}")

    @property
    def _sizes(self) -> dict[str, int]:
        return {
            "positions": self.position_history * HISTORY_COLUMNS,
            "spins": self.spin_history * HISTORY_COLUMNS,
            "robot_state": ROBOT_STATE_SIZE,
            "end_effector": END_EFFECTOR_SIZE,
            "skill": SKILL_SIZE,
            "estimate": ESTIMATE_SIZE,
            "estimate_status": ESTIMATE_STATUS_SIZE,
            "hit_prediction": HIT_PREDICTION_SIZE,
        }

    @property
    def size(self) -> int:
        """Length of the observation vector."""
        return sum(self._sizes.values())

    def slice(self, part: str) -> slice:
        """Where ``part`` (a name of the module docstring's layout) lies in the vector."""
        start = 0
        for name, size in self._sizes.items():
            if name == part:
                return slice(start, start + size)
            start += size
        raise KeyError(f"ObservationLayout: no part {part!r}; parts are {list(self._sizes)}")

    def indices(self, parts) -> np.ndarray:
        """The vector's indices (int array) of the named parts, in the order given: what an actor
        reading those parts selects."""
        return np.concatenate([np.arange(self.size)[self.slice(name)] for name in parts]) if parts else np.zeros(0, dtype=int)

    def part(self, observation: np.ndarray, name: str) -> np.ndarray:
        """The part ``name`` of ``observation``, histories as (N, 4) arrays."""
        values = np.asarray(observation)[self.slice(name)]
        return values.reshape(-1, HISTORY_COLUMNS) if name in ("positions", "spins") else values

    def hit_within(self, observations, window: float):
        """Whether each observation's predicted hit is valid and at most ``window`` s ahead: a
        bool array (...,) for observations (..., size), NumPy or torch alike."""
        prediction = observations[..., self.slice("hit_prediction")]
        return (prediction[..., 0] > 0.5) & (prediction[..., 1] <= window)

    def assemble(self, positions, spins, robot_state, end_effector, skill, estimate, estimate_status, hit_prediction=None) -> np.ndarray:
        """The observation vector from its parts (shapes as in the module docstring);
        ``hit_prediction`` None: zeros (no prediction)."""
        parts = dict(
            positions=positions, spins=spins, robot_state=robot_state, end_effector=end_effector,
            skill=skill, estimate=estimate, estimate_status=estimate_status,
            hit_prediction=np.zeros(HIT_PREDICTION_SIZE) if hit_prediction is None else hit_prediction,
        )
        vectors = []
        for name, size in self._sizes.items():
            vector = np.asarray(parts[name], dtype=float).ravel()
            if vector.size != size:
                raise ValueError(f"ObservationLayout.assemble: {name} has {vector.size} values, expected {size}")
            vectors.append(vector)
        return np.concatenate(vectors)


# ----------------------------------------------------------------------------------------------
# The critic's privileged observation (asymmetric actor-critic; training.env.RallyEnv's info)
# ----------------------------------------------------------------------------------------------

# The critic's privileged observation, in order: part -> size.
PRIVILEGED_PARTS = {"ball_state": 9, "joint_state": 16, "skill": 3}


def privileged_slice(part: str) -> slice:
    """Where ``part`` (a key of PRIVILEGED_PARTS) lies in ``info["privileged"]``."""
    start = 0
    for name, size in PRIVILEGED_PARTS.items():
        if name == part:
            return slice(start, start + size)
        start += size
    raise KeyError(f"privileged_slice: no part {part!r}; parts are {list(PRIVILEGED_PARTS)}")


# ----------------------------------------------------------------------------------------------
# How an episode ended (play.episode classifies; training and evaluation read it)
# ----------------------------------------------------------------------------------------------

# The conditions that end a training episode (training.env.RallyEnv; DESIGN.md *One episode*).
END_CONDITIONS = ("out_of_play", "time_limit", "hit", "passed", "collision")


class Outcome(str, enum.Enum):
    IN_PLAY = "in_play"
    RETURNED = "returned"
    NOT_RETURNED = "not_returned"
    MISSED = "missed"
    INVALID = "invalid"


@dataclasses.dataclass(frozen=True)
class EpisodeResult:
    """How an episode stands: its outcome, why (a short phrase), and the events that decided it:
    the incoming ball's bounce on the robot's half, the robot's hit, and where the return landed
    (the first table contact after the hit), each None until it happens."""

    outcome: Outcome
    reason: str = ""
    bounce: ContactEvent | None = None
    hit: ContactEvent | None = None
    landing: ContactEvent | None = None

    @property
    def done(self) -> bool:
        return self.outcome is not Outcome.IN_PLAY

    @property
    def bounce_to_hit_time(self) -> float | None:
        """Time from the bounce on the robot's half to the hit, s (None without both)."""
        return None if self.bounce is None or self.hit is None else self.hit.time - self.bounce.time
