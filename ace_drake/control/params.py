"""Control configs: the rally control stack (eq. 12 mapping, spline QP, resets, collision
checks), the model-based returner, and the rally diagram that they are built for (``RallyParams``).
"""

from __future__ import annotations

import dataclasses

from ace_drake.config import ConfigError, require_non_negative, require_positive
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.robot.params import JOINT_NAMES


@dataclasses.dataclass(frozen=True)
class ControlParams:
    """The rally control stack (paper, Methods *Feasible action for optimal control* and *Reset
    trajectories*; ``ace_drake/control``). Times in s; fractions are of the hardware limits of
    ``RobotLimits``. The paper gives the 32 ms segment, the 1 kHz sampling and the 5 ms budget;
    the margins are this project's, chosen so that the delayed joints (eq. (9)) that follow the
    commands stay inside the hardware limits (``ace-drake bench safety`` measures it).
    """

    segment_samples: int = 32  # T: one policy step is this many command periods (32 ms at 1 kHz)
    observation_lead: float = 0.005  # the observation is built this long before its segment starts
    # Command limits = hardware limits shrunk by these, so that the servo's lag, overshoot and
    # inter-sample ripple (eq. (9); ~9% velocity ripple at 1 kHz) stay inside the hardware limits.
    position_margin: float = 0.02  # rad or m inside each position limit
    velocity_fraction: float = 0.85
    acceleration_fraction: float = 0.85
    # The feasible set of the action mapping (eq. (12)) is an inner approximation of what the spline
    # QP can reach: reachability assumes this fraction of the command acceleration, and the
    # control-invariant part assumes braking at ``stop_fraction`` of it after ``reaction_time``.
    reach_fraction: float = 0.8
    stop_fraction: float = 0.6
    reaction_time: float = 0.006
    boundary_samples: int = 24  # velocities sampled along each side of a feasible set's polygon
    # Command periods per cubic piece of the segment spline: 1 (a knot at every 1 kHz sample); with
    # longer pieces the spline cannot follow the feasible set's bang-bang bounds (measured: the
    # QP became infeasible within 10 adversarial steps for 2, 4 and 8).
    knot_samples: int = 1
    qp_solver: str = "daqp"  # "daqp", or "clarabel" through Drake's MathematicalProgram
    # Reset and protective-stop trajectories (Ruckig, jerk-limited and time-optimal): the jerk limit
    # is the command acceleration reached from zero in ``jerk_time``.
    jerk_time: float = 0.002
    reset_pose: tuple[float, ...] | None = None  # stationary reset configuration; None: the ready pose
    # Collision checking of segment + reset (robot.collision): swept bounding boxes over the whole
    # plan, then conservative advancement on Drake's distances where they cannot decide; every
    # point of the robot stays at least ``collision_margin`` (m) from the court and itself.
    collision_margin: float = 0.005
    collision_influence: float = 0.3  # distances beyond this (m) are not reported
    # The check's deadline, in exact distance queries (~10-20 us each, ~40 us with the
    # advancement's bookkeeping): a plan not proven clear within it is refused like a collision
    # (fail safe), which bounds the control step's latency. 16 leaves 0.2% of rally plans over it,
    # all of them colliding anyway (ace-drake bench control).
    collision_query_budget: int = 16

    def __post_init__(self) -> None:
        require_positive(self, "segment_samples", "boundary_samples", "knot_samples", "jerk_time", "collision_influence", "collision_query_budget")
        if self.segment_samples % self.knot_samples:
            raise ConfigError(f"segment_samples ({self.segment_samples}) must be a multiple of knot_samples ({self.knot_samples})")
        require_non_negative(self, "observation_lead", "position_margin", "reaction_time", "collision_margin")
        for name in ("velocity_fraction", "acceleration_fraction", "reach_fraction", "stop_fraction"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if not self.stop_fraction < self.reach_fraction:
            raise ConfigError(f"stop_fraction ({self.stop_fraction}) must be < reach_fraction ({self.reach_fraction})")
        if self.qp_solver not in ("daqp", "clarabel"):
            raise ConfigError(f"qp_solver must be daqp or clarabel, got {self.qp_solver!r}")
        if self.reset_pose is not None and len(self.reset_pose) != len(JOINT_NAMES):
            raise ConfigError(f"reset_pose: expected {len(JOINT_NAMES)} values, got {len(self.reset_pose)}")


RETURNER_MEMORY_PARTS = ("bounce", "hit", "follow", "racket", "ik", "fallback")  # ReturnerParams.forget


IK_NOMINALS = ("braking", "segment_start")  # ReturnerParams.ik_nominal


@dataclasses.dataclass(frozen=True)
class ReturnerParams:
    """The model-based returner (``control/returner.py``): where it sends the ball, which hits it
    considers and how it predicts. Lengths in m (world frame of DESIGN.md), times in s, speeds in
    m/s. The paper's robot has no such controller (it is the related work's approach), so every
    value is this project's choice."""

    target_x: float = 0.75  # landing point's x on the opponent's half (0.685: its centre)
    target_y_limit: float = 0.45  # the skill's y_desired is clipped to +-this
    # Flight times from the hit to the landing, tried in order until the racket state is reachable
    # within the joint speed limits and the ball clears the net by ``net_clearance``.
    flight_times: tuple[float, ...] = (0.55, 0.45, 0.65, 0.75, 0.38)
    net_clearance: float = 0.04  # between the ball's bottom and the net cord
    brush_speed: float = 0.0  # racket speed along the blade's upward tangent (> 0: topspin)
    # Added to brush_speed per unit of the skill's w_s (paper, *Rewards*: w_s weighs the landing's
    # topspin), so that the returner follows the spin skill: 2 m/s put the median landing topspin
    # at +198 / -32 / -157 rad/s for w_s = +1 / 0 / -1 on 21 recorded shots, returning 17 / 18 / 19
    # of them (4 m/s: 11 / 18 / 14; docs/experiments/2026-12-02-skill.md). 0: spin ignored.
    skill_brush: float = 2.0
    # The ball centre at the hit: height above the playing surface, and how far behind the table.
    hit_height_min: float = 0.12
    hit_height_max: float = 0.50
    hit_x_min: float = -2.6
    prediction_step: float = 0.032  # RK4 step of the incoming ball's prediction (one segment)
    prediction_horizon: float = 1.2  # how far ahead the incoming ball is predicted
    candidates_tried: int = 3  # hit times planned per call before giving up
    # Distance between all robot and court geometry at the hit configuration (the supervisor checks
    # the motion with a 5 mm margin, and the motion around the hit comes closer than the hit).
    ik_clearance: float = 0.03
    ik_solves_per_call: int = 4  # full IK solves (``solve_hit_ik``) a call may spend; refinements are free
    # Where a full IK solve starts (its nominal configuration and first seed): "braking", the arm's
    # revolute joints where braking uniformly to rest over the D s to the hit's boundary would stop
    # them, q0 + v0 D / 2, and the gantry at q0, so that a moving arm keeps to the solution it is
    # moving towards; "segment_start", q0 itself. None: "braking" without memory (369 of the 411
    # playable recorded shots against 353), "segment_start" with it (376 against 372), the better
    # rule for each (docs/experiments/2026-12-01-returner-memory.md).
    ik_nominal: str | None = None
    # The joints' lag behind the command (eq. (9) ramp-tracking lag plus half a command period of
    # zero-order hold); None: computed from the scenario's joint dynamics.
    joint_lag: float | None = None
    # Whether the returner remembers the ball it is playing between calls (its hit time, the bounce,
    # its last IK solution: ``control/returner.py``). False: every call plans from its observation
    # alone, so that the action is a function of the observation (as a policy's is): the labels a
    # learner imitates (``training.rollout``, DAgger) are then learnable.
    memory: bool = True
    # With memory on, remembered things to forget, for studying what the memory is worth
    # (docs/experiments/2026-12-01-returner-memory.md); any of RETURNER_MEMORY_PARTS: "bounce" (found behind the
    # ball at every call instead), "hit" (the planned hit time is not tried first), "follow" (the
    # follow-through is decided from the preferred hit, not from the plan), "racket" (the plan's
    # flight time and return are not reused), "ik" (the plan's configuration is not refined: full IK
    # afresh), "fallback" (no falling back on the plan being executed).
    forget: tuple[str, ...] = ()

    @property
    def ik_rule(self) -> str:
        """The IK's starting rule in force (``ik_nominal``, None resolved by ``memory``)."""
        if self.ik_nominal is not None:
            return self.ik_nominal
        return "segment_start" if self.memory else "braking"

    def __post_init__(self) -> None:
        object.__setattr__(self, "forget", tuple(self.forget))
        unknown = [part for part in self.forget if part not in RETURNER_MEMORY_PARTS]
        if unknown:
            raise ConfigError(f"forget: unknown memory part(s) {unknown}; choose from {', '.join(RETURNER_MEMORY_PARTS)}")
        if self.ik_nominal is not None and self.ik_nominal not in IK_NOMINALS:
            raise ConfigError(f"ik_nominal must be one of {', '.join(IK_NOMINALS)}, got {self.ik_nominal!r}")
        require_positive(self, "target_x", "net_clearance", "hit_height_max", "prediction_step", "prediction_horizon", "candidates_tried", "ik_solves_per_call")
        require_non_negative(self, "target_y_limit", "hit_height_min", "ik_clearance")
        if not self.flight_times or any(not t > 0.0 for t in self.flight_times):
            raise ConfigError(f"flight_times must be a non-empty list of positive times (s), got {self.flight_times}")
        if not self.hit_height_min < self.hit_height_max:
            raise ConfigError(f"hit_height_min ({self.hit_height_min}) must be < hit_height_max ({self.hit_height_max})")
        if self.joint_lag is not None and not self.joint_lag >= 0.0:
            raise ConfigError(f"joint_lag must be >= 0 s or null, got {self.joint_lag}")


STEPPINGS = ("continuous", "segment")


@dataclasses.dataclass(frozen=True)
class RallyParams:
    """One rally episode's diagram (``diagrams.add_rally``): the ball (``physics``, with the
    paper's post-table perturbations when ``perturb``), the robot (``scenario``: a scenario YAML in
    models/), its perception (``perception``) and control stack (``control``), and the policy's
    observation histories (paper, *States*: the last N positions and spins; the paper does not
    give N, 10 is 50 ms of positions at 200 Hz). ``hit_prediction``: whether the observation's
    ``hit_prediction`` part is computed (``control.hit_prediction``, ~5 ms of CPU per observation,
    every 32 ms; False: zeros there, for controllers that do not read it). ``hit_memory``: that
    part keeps the hit it predicted 32 ms before while it is still a candidate (the model-based
    returner's memory of its hit time; ``ObservationBuilder``), instead of judging from the
    estimate alone (needs ``hit_prediction``). ``time_limit``: s after
    the opponent's hit at which an unresolved episode ends. ``seed``: the default of every seed
    parameter. ``stepping``: "continuous", the reference diagram (B = 1; Drake's integrator with
    witness-located contacts, 1 kHz joint and supervisor updates), or "segment", the batched
    diagram that advances once per 32 ms segment (docs/architecture.md, *Segment stepping*)."""

    physics: BallPhysicsParams = dataclasses.field(default_factory=BallPhysicsParams)
    perturb: bool = True
    scenario: str = "scenario.yaml"
    control: ControlParams = dataclasses.field(default_factory=ControlParams)
    perception: PerceptionParams = dataclasses.field(default_factory=PerceptionParams)
    position_history: int = 10
    spin_history: int = 10
    hit_prediction: bool = True
    hit_memory: bool = False
    time_limit: float = 2.0
    seed: int = 0
    stepping: str = "continuous"

    def __post_init__(self) -> None:
        require_positive(self, "position_history", "spin_history", "time_limit")
        if self.stepping not in STEPPINGS:
            raise ConfigError(f"stepping must be one of {STEPPINGS}, got {self.stepping!r}")
        if self.hit_memory and not self.hit_prediction:
            raise ConfigError("hit_memory keeps the observation's predicted hit: it needs hit_prediction true")

