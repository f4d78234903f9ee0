"""RallyEnv: a rally episode as a gymnasium environment over the training diagram.

Paper, Methods *Reinforcement learning framework*. An episode starts with the ball in free flight
towards the robot, just after the opponent's hit, and ends when one of the paper's four
conditions holds (``END_CONDITIONS``):

1. ``out_of_play``: the ball is out of play or the shot was not legal: the episode classifier
   (``play.episode.classify``) decides MISSED (a second bounce on the robot's half, the floor) or
   INVALID (the shot's fault); ``time_limit``: the episode reached ``RallyParams.time_limit``
   (s after the opponent's hit) undecided (``episode.timed_out``: MISSED, or NOT_RETURNED after a
   hit).
2. ``hit``: the robot hit the ball. From then on the environment requests no more segments (the
   robot finishes its plan: the last segment's reset) and simulates on, within the same step,
   until the return is decided (its first table or floor contact, or ``post_hit_time_limit``), since
   the reward needs the landing.
3. ``passed``: the ball passed the racket: after its bounce on the robot's half, the ball's centre
   is behind every point of the blade (x below the blade centre's by the blade's radius and half
   thickness plus the ball's radius plus ``pass_margin``) and moving away from the table
   (v_x < 0). A racket contact can then only push the ball further from the table, unless the
   racket overtook the ball and came round behind it, which no stroke does. (Before its bounce the
   ball may pass a racket held over the table: the robot must let it bounce anyway.)
4. ``collision``: the safety supervisor refused the segment of the last action because segment +
   reset would collide ("collision predicted"). Other refusals (an infeasible start, the collision
   check running over its query budget) keep the robot on its last checked plan, as on the real
   robot, and the episode goes on.

Ended by (3) or (4), the episode's result is MISSED (with the reason), since its ball is still in
play. The reward is terminal (paper eq. (10); ``learning.rewards.terminal_reward``), 0 on every
other step. Time: ``reset`` starts the episode at t = 0 and advances to the first observation,
t = T - 5 ms = 27 ms (T = 32 ms, paper Extended Data Fig. 1); each ``step`` fixes the action on the
diagram's ``action_request`` input and advances T, so the PolicyController's event at the current
time reads it for the segment starting 5 ms later, and the next observation is built 5 ms before
the next segment. Drake stops ``AdvanceTo(t)`` with the events at t still pending, so the
observation returned at t is exactly what the controller's event at t sees.

Observation (the actor's): the ``ObservationLayout`` vector of the diagram's ``observation_builder``
(ball position and spin histories with ages, the robot state where the next segment starts, the
skill, and the estimator's output), as float32. ``info["privileged"]`` (the critic's, asymmetric
actor-critic; ``PRIVILEGED_PARTS``): the true ball state from the BallPlant [p (m), v (m/s),
w (rad/s)] (9), the joints' true state [q, v] (16), and the skill [y_desired, w_p, w_s] (3), as
float32. The true joint state is not the whole robot state: what a new segment does depends on
the committed plan, which the actor's ``robot_state`` part carries (the plan's [q, v, a] where the
next segment starts); a critic should read that part of the observation too.

Components that change sign under the mirror y -> -y (issue 7's symmetric augmentation) can be
read off the layouts' names: y of every position, velocity and y_desired; x and z of every spin
(a pseudovector); the gantry_y, shoulder_yaw and wrist joints' sense depends on the robot model.
This module does not mirror anything.

Initial states (paper, *Initial state training distribution*), drawn by ``reset`` from the env's
``np_random``, in this order:

- the shot: from the incoming-shot distribution (``play.shots``, serves : returns = 3 : 7),
  drawn ``shot_batch`` at a time (each draw is checked by simulation; batches are 10x cheaper
  per shot) and used in order; ``reset(seed=...)`` discards the batch;
- the skill (``SkillSampling``): y_desired uniform across the opponent's half, w_p and w_s from
  mixtures biased towards sparse (0) and boundary (0, 1; -1, 1) values;
- the robot: with probability ``dynamic_start_fraction`` a dynamic start, else a static one
  (``StartSampling``). Static: the arm in the reset pose, the two prismatic (gantry) joints uniform
  within their command limits, redrawn until the robot is clear of the court and itself. Dynamic:
  a state part-way along a reset plan: a random joint state (q uniform within the command limits,
  v uniform up to the velocity limit or a fifth of it, a within the bounds a reset can start from)
  inside the control-invariant set, the stack's reset from it to the reset pose (collision
  checked), and a sample uniform along that plan. The paper stores reset plans from previous
  training episodes instead; drawing them afresh keeps every episode a function of its seed.
- the diagram's seed (sensor noise and the ball's post-bounce perturbations).

One diagram and one Simulator per environment; each reset returns the Context to the diagram's
default (``RallyRunner``'s pattern). The same seed gives the same episode, bit for bit.
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np

from ace_drake.config import ConfigError
from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.control.action_mapping import ACTION_SIZE, inverse_map_action
from ace_drake.control.feasible_set import InfeasibleStartError, feasible_sets
from ace_drake.control.params import RallyParams
from ace_drake.control.stack import random_invariant_state
from ace_drake.diagrams import build_training_diagram, make_simulator, start_rally
from ace_drake.learning.params import RewardParams
from ace_drake.learning.rewards import terminal_reward
from ace_drake.perception.params import PerceptionParams
from ace_drake.play.episode import classify, timed_out
from ace_drake.play.params import ShotParams
from ace_drake.play.shots import make_distribution
from ace_drake.robot.params import JOINT_NAMES

PRISMATIC_JOINTS = [JOINT_NAMES.index("gantry_x"), JOINT_NAMES.index("gantry_y")]
COLLISION_REASON = "collision predicted"  # the supervisor's reason for a refused, colliding plan
# The MISSED result's reason for the end conditions that stop an episode whose ball is in play.
UNHIT_REASONS = {"passed": "not hit: the ball passed the racket", "collision": "not hit: the commanded motion would collide"}


def training_rally_params() -> RallyParams:
    """The training diagram's default: the statistical position sensor (the cheap sensor path)."""
    return RallyParams(perception=PerceptionParams(positions="statistical"))


@dataclasses.dataclass(frozen=True)
class SkillSampling:
    """How ``reset`` draws the skill (paper, *Initial state training distribution*, item 3:
    "biased towards sparse reward weight vectors and boundary values"; its Supplementary 1.4.5 is
    not public, so the mixture is this project's).

    y_desired (m) is uniform across the opponent's half, within ``y_margin`` of the side lines.
    w_p is 0 with probability ``w_p_zero``, 1 with ``w_p_one``, else uniform on [0, 1]; w_s is 0
    with ``w_s_zero``, -1 with ``w_s_minus_one``, +1 with ``w_s_plus_one``, else uniform on
    [-1, 1]. Defaults: half the w_p draws and 60 % of the w_s draws on sparse and boundary values;
    7.5 % of skills are (w_p, w_s) = (0, 0), a plain return.
    """

    y_margin: float = 0.0
    w_p_zero: float = 0.25
    w_p_one: float = 0.25
    w_s_zero: float = 0.3
    w_s_minus_one: float = 0.15
    w_s_plus_one: float = 0.15

    def __post_init__(self) -> None:
        names = ("y_margin", "w_p_zero", "w_p_one", "w_s_zero", "w_s_minus_one", "w_s_plus_one")
        for name in names:
            if not getattr(self, name) >= 0.0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.w_p_zero + self.w_p_one > 1.0:
            raise ConfigError(f"w_p_zero + w_p_one must be <= 1, got {self.w_p_zero + self.w_p_one}")
        if self.w_s_zero + self.w_s_minus_one + self.w_s_plus_one > 1.0:
            raise ConfigError("w_s_zero + w_s_minus_one + w_s_plus_one must be <= 1")

    def sample(self, rng: np.random.Generator, table_width: float) -> np.ndarray:
        """A skill [y_desired (m), w_p, w_s] (3,)."""
        half = 0.5 * table_width - self.y_margin
        if half < 0.0:
            raise ConfigError(f"y_margin ({self.y_margin} m) is wider than half the table ({0.5 * table_width} m)")
        y_desired = rng.uniform(-half, half)
        w_p = _mixture(rng, ((self.w_p_zero, 0.0), (self.w_p_one, 1.0)), (0.0, 1.0))
        w_s = _mixture(rng, ((self.w_s_zero, 0.0), (self.w_s_minus_one, -1.0), (self.w_s_plus_one, 1.0)), (-1.0, 1.0))
        return np.array([y_desired, w_p, w_s])


def _mixture(rng: np.random.Generator, atoms, interval) -> float:
    """One draw: each atom's value with its probability, else uniform on ``interval``."""
    u = rng.random()
    for probability, value in atoms:
        if u < probability:
            return value
        u -= probability
    return rng.uniform(*interval)


@dataclasses.dataclass(frozen=True)
class RallyEnvParams:
    """Everything a RallyEnv is built from.

    rally: the training diagram (default: statistical position sensor); shots: the incoming-shot
    distribution; reward: eq. (10)'s numbers; skill: the skill sampling; dynamic_start_fraction:
    probability of a dynamic initial robot state (module docstring); static_attempts,
    dynamic_attempts: draws before giving up on a collision-free start (static: then the reset
    pose; dynamic: then a static start); post_hit_time_limit: s after the hit within which the
    return must be decided (a ball still flying then counts as not returned); pass_margin: m,
    end condition (3)'s margin; shot_batch: shots drawn (and validity-checked) at a time.
    """

    rally: RallyParams = dataclasses.field(default_factory=training_rally_params)
    shots: ShotParams = dataclasses.field(default_factory=ShotParams)
    reward: RewardParams = dataclasses.field(default_factory=RewardParams)
    skill: SkillSampling = dataclasses.field(default_factory=SkillSampling)
    dynamic_start_fraction: float = 0.5  # the paper gives no ratio of static to dynamic starts
    static_attempts: int = 20
    dynamic_attempts: int = 200
    # Generous: the robot's returns (published: median 7.8 m/s) cross the 2.74 m table in well under 1 s.
    post_hit_time_limit: float = 1.5
    pass_margin: float = 0.05
    shot_batch: int = 64

    def __post_init__(self) -> None:
        if not 0.0 <= self.dynamic_start_fraction <= 1.0:
            raise ConfigError(f"dynamic_start_fraction must be in [0, 1], got {self.dynamic_start_fraction}")
        for name in ("static_attempts", "dynamic_attempts", "shot_batch"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.post_hit_time_limit > 0.0:
            raise ConfigError(f"post_hit_time_limit must be > 0, got {self.post_hit_time_limit}")
        if not self.pass_margin >= 0.0:
            raise ConfigError(f"pass_margin must be >= 0, got {self.pass_margin}")


def hold_action(stack, plan, start: int) -> np.ndarray:
    """The action (16,) whose segment continues ``plan`` (a ``JointTrajectory``) from its row
    ``start`` (the next segment boundary, in plan samples) through one segment, as near as the
    action mapping reaches: eq. (12) inverted at the plan's state a segment later, clipped onto the
    box. Zeros when that start lies outside the control-invariant set. What "no new segment" does,
    as an action to learn from (``RallyEnv.hold_action``, ``RallyVectorEnv.hold_actions``)."""

    first = int(np.clip(start, 0, plan.samples))
    last = int(np.clip(start + stack.control.segment_samples, 0, plan.samples))
    q0, v0, a0 = plan.state(first)
    q1, v1, _ = plan.state(last)
    try:
        sets = feasible_sets(q0, v0, a0, stack.limits, stack.control, stack.period)
    except InfeasibleStartError:
        return np.zeros(ACTION_SIZE)
    return np.clip(inverse_map_action(q1, v1, sets), -1.0, 1.0)


def draw_robot_start(stack, params: RallyEnvParams, rng: np.random.Generator, start: str):
    """(q, v, a, kind) of a drawn initial robot state (module docstring); v and a are None for a
    static start; ``start`` "static" or "dynamic" (a dynamic start that finds no collision-free
    moving state within ``dynamic_attempts`` stands still instead, kind "static")."""
    if start == "dynamic":
        drawn = _draw_dynamic_state(stack, params, rng)
        if drawn is not None:
            return (*drawn, "dynamic")
        start = "static"  # no collision-free moving start found: stand still instead
    if start != "static":
        raise ValueError(f"RallyEnv.reset: start must be 'static' or 'dynamic', got {start!r}")
    return _draw_static_state(stack, params, rng), None, None, "static"


def _draw_static_state(stack, params: RallyEnvParams, rng: np.random.Generator) -> np.ndarray:
    """The reset pose with the prismatic joints uniform within their command limits, clear of
    the court and itself (the reset pose if ``static_attempts`` draws all collide)."""
    limits = stack.limits
    for _ in range(params.static_attempts):
        q = stack.reset_pose.copy()
        q[PRISMATIC_JOINTS] = rng.uniform(limits.lower[PRISMATIC_JOINTS], limits.upper[PRISMATIC_JOINTS])
        if stack.initial_plan(q)[1]:
            return q
    return stack.reset_pose.copy()


def _draw_dynamic_state(stack, params: RallyEnvParams, rng: np.random.Generator):
    """(q, v, a) part-way along a collision-free reset plan from a random invariant state, or
    None after ``dynamic_attempts`` draws."""
    for _ in range(params.dynamic_attempts):
        q, v, a = random_invariant_state(stack, rng)
        plan, free = stack.initial_plan(q, v, a)
        if not free:
            continue
        state = tuple(np.array(x) for x in plan.state(int(rng.integers(plan.samples))))
        if stack.initial_plan(*state)[1]:  # the supervisor re-plans the reset from there
            return state
    return None


def pass_distance(params: RallyEnvParams) -> float:
    """End condition (3)'s distance (m): the ball is behind every point of the blade by this much."""
    physics = params.rally.physics
    return physics.racket.blade_radius + 0.5 * physics.racket.blade_thickness + physics.aero.ball_radius + params.pass_margin


def end_condition(result: EpisodeResult, refused: bool, last_reason: str, ball: np.ndarray, racket_x: float, distance: float,
                  time: float, time_limit: float) -> str:
    """Which of END_CONDITIONS ended the episode in the last step ("" for none), from its result
    so far, whether the supervisor refused the last segment and why, the true ball state (9,),
    the blade centre's x (m), the pass distance (m), the episode time and the time limit (s)."""
    if result.hit is not None:
        return "hit"
    if refused and last_reason.startswith(COLLISION_REASON):
        return "collision"
    if result.done:
        return "out_of_play"
    if result.bounce is not None and ball[0] < racket_x - distance and ball[3] < 0.0:
        return "passed"
    if time >= time_limit - 1e-9:
        return "time_limit"
    return ""


@dataclasses.dataclass
class _Episode:
    """The running episode's bookkeeping (the simulation itself lives in the Context)."""

    shot: np.ndarray
    serve: bool
    skill: np.ndarray
    start: str  # "static", "dynamic" or "given"
    result: EpisodeResult
    end: str = ""  # one of END_CONDITIONS once ended
    reward: float = 0.0


class RallyEnv(gymnasium.Env):
    """The rally episode (module docstring) as a gymnasium environment.

    Action: (16,) in [-1, 1], the control stack's abstract action (``control.action_mapping``:
    terminal joint positions, then velocities, 32 ms ahead; paper eq. (12)).
    Observation: ``layout.size`` float32 values, ``ObservationLayout`` (``self.layout``).
    Reward: terminal only (``learning.rewards``). ``truncated`` is always False: the time limits end
    episodes with a decided outcome (``episode.timed_out``).
    info: ``privileged`` (28,) float32 (PRIVILEGED_PARTS), ``time`` (s), ``outcome`` (an
    ``Outcome`` value), ``end`` (one of END_CONDITIONS, or "" while running), ``serve``, ``skill``
    (3,), ``start`` ("static", "dynamic" or "given") and ``segments`` (accepted, refused).

    ``reset(options=...)`` may fix parts of the initial state: ``shot`` (9,) [p, v, w] with
    ``serve`` (bool, default False), ``skill`` (3,), the robot's ``q`` (8,) with optional ``v``,
    ``a`` (8,) each (a moving start must be collision-free along its reset), or ``start``
    ("static" or "dynamic") to choose the kind of drawn robot state. The ``result`` attribute holds
    the episode's EpisodeResult (with its contact events).
    """

    metadata = {"render_modes": []}

    def __init__(self, params: RallyEnvParams | None = None, distribution=None):
        """Args: params (default RallyEnvParams()); distribution, a ``play.shots.ShotDistribution``
        to draw shots from (default: ``make_distribution(params.shots)``, fitted at the first reset
        that needs a shot, ~4 s for the synthetic set; share one between environments)."""

        super().__init__()
        self.params = params or RallyEnvParams()
        self.diagram = build_training_diagram(self.params.rally)
        self.simulator = make_simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self._default_context = self.diagram.CreateDefaultContext()
        self._default_context.SetAccuracy(self.context.get_accuracy())  # copied on every reset
        self._ball = self.diagram.GetSubsystemByName("ball")
        self._joints = self.diagram.GetSubsystemByName("joint_plant")
        self._kinematics = self.diagram.GetSubsystemByName("robot_kinematics")
        self._supervisor = self.diagram.GetSubsystemByName("safety_supervisor")
        self._observation_builder = self.diagram.GetSubsystemByName("observation_builder")
        self._action_request = self.diagram.GetInputPort("action_request")
        self.stack = self._supervisor.stack
        self.layout = self._observation_builder.layout
        self.period = self.stack.segment_duration
        self._first_observation = self.period - self.stack.control.observation_lead
        self._pass_distance = pass_distance(self.params)
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (self.layout.size,), np.float32)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)
        self._distribution = distribution
        self._shots: list[tuple[np.ndarray, bool]] = []
        self._episode: _Episode | None = None
        self._steps = 0

    # ------------------------------------------------------------------------------ gymnasium
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._shots.clear()  # the batch came from the previous random stream
        options = dict(options or {})
        unknown = set(options) - {"shot", "serve", "skill", "q", "v", "a", "start"}
        if unknown:
            raise ValueError(f"RallyEnv.reset: unknown option(s) {sorted(unknown)}")
        if "shot" in options:
            shot, serve = np.asarray(options["shot"], dtype=float), bool(options.get("serve", False))
        else:
            shot, serve = self._next_shot()
        if "skill" in options:
            skill = np.asarray(options["skill"], dtype=float)
        else:
            skill = self.params.skill.sample(self.np_random, self.params.rally.physics.table.width)
        if "q" in options:
            start = "given"
            q, v, a = (None if options.get(name) is None else np.asarray(options[name], dtype=float) for name in ("q", "v", "a"))
        else:
            start = options.get("start")
            if start is None:
                start = "dynamic" if self.np_random.random() < self.params.dynamic_start_fraction else "static"
            q, v, a, start = self._draw_robot_state(start)
        diagram_seed = int(self.np_random.integers(2**31 - 1))


        self.context.SetTimeStateAndParametersFrom(self._default_context)
        start_rally(self.diagram, self.context, shot, seed=diagram_seed, skill=skill, q=q)
        if v is not None or a is not None:
            # A moving start: the plan is the reset from (q, v, a); the joints move at v.
            self._supervisor.Initialize(self._supervisor.GetMyMutableContextFromRoot(self.context), q, v, a)
            self._joints.SetJointState(self._joints.GetMyMutableContextFromRoot(self.context), q, v)
        self._request(np.zeros(ACTION_SIZE), valid=False)
        self.simulator.Initialize()
        self._steps = 0
        self.simulator.AdvanceTo(self._first_observation)
        self._episode = _Episode(shot, serve, skill, start, self._classify(serve))
        return self._observation(), self._info()

    def step(self, action):
        episode = self._episode
        if episode is None or episode.end:
            raise RuntimeError("RallyEnv.step: the episode has ended (or never started): call reset()")
        action = np.asarray(action, dtype=float)
        if action.shape != (ACTION_SIZE,):
            raise ValueError(f"RallyEnv.step: the action must have shape ({ACTION_SIZE},), got {action.shape}")
        refused_before = self._supervisor_state().rejected
        self._request(action, valid=True)
        self._advance()
        episode.result = self._classify(episode.serve)
        episode.end = self._end_condition(episode, refused_before)
        if episode.end == "hit":
            self._finish_return(episode)
        elif episode.end == "time_limit":
            episode.result = timed_out(episode.result)
        elif episode.end in UNHIT_REASONS:  # the ball is still in play, but no hit will come
            episode.result = dataclasses.replace(episode.result, outcome=Outcome.MISSED, reason=UNHIT_REASONS[episode.end])
        if episode.end:
            episode.reward = terminal_reward(episode.result, episode.skill, self.params.reward, collided=episode.end == "collision")
        return self._observation(), episode.reward, bool(episode.end), False, self._info()

    # ------------------------------------------------------------------------------ queries
    @property
    def result(self) -> EpisodeResult | None:
        """The running (or ended) episode's EpisodeResult; None before the first reset."""
        return None if self._episode is None else self._episode.result

    def privileged_observation(self) -> np.ndarray:
        """The critic's observation now (PRIVILEGED_PARTS), float32."""
        ball = self._ball.ball_state_port.Eval(self._ball.GetMyContextFromRoot(self.context))
        joints = self._joints.joint_state_port.Eval(self._joints.GetMyContextFromRoot(self.context))
        return np.concatenate([ball, joints, self._episode.skill]).astype(np.float32)

    def ball_from_blade(self) -> np.ndarray:
        """The true ball centre relative to the blade centre now (3,), m (world axes)."""
        ball = self._ball.ball_state_port.Eval(self._ball.GetMyContextFromRoot(self.context))[:3]
        X_WR = self._kinematics.racket_pose_port.Eval(self._kinematics.GetMyContextFromRoot(self.context))
        return ball - X_WR.translation()

    def hold_action(self) -> np.ndarray:
        """The action (16,) that continues the committed plan through the next segment, as near as
        the action mapping reaches (eq. (12) inverted at the plan's state 32 ms after the segment
        start; clipped onto the box): what "no new segment" does, for a controller that has no
        action to give (``learning.demonstrations``). Zeros when the plan's start lies outside the
        control-invariant set."""

        status = self._supervisor_state()
        start = round((self.context.get_time() + self.stack.control.observation_lead) / status.plan.period) - status.plan_start
        return hold_action(self.stack, status.plan, start)

    # ------------------------------------------------------------------------------ helpers
    def _observation(self) -> np.ndarray:
        builder = self._observation_builder
        return builder.observation_port.Eval(builder.GetMyContextFromRoot(self.context)).astype(np.float32)

    def _info(self) -> dict:
        episode = self._episode
        status = self._supervisor_state()
        return {
            "privileged": self.privileged_observation(),
            "time": self.context.get_time(),
            "outcome": episode.result.outcome.value,
            "end": episode.end,
            "serve": episode.serve,
            "skill": episode.skill.copy(),
            "start": episode.start,
            "segments": (status.accepted, status.rejected),
        }

    def _request(self, action: np.ndarray, valid: bool) -> None:
        """Fixes the diagram's action_request input: the action for the controller's next event."""
        self._action_request.FixValue(self.context, np.append(action, 1.0 if valid else 0.0))

    def _classify(self, serve: bool) -> EpisodeResult:
        return classify(self._ball.contact_events_port.Eval(self._ball.GetMyContextFromRoot(self.context)), serve)

    def _supervisor_state(self):
        return self._supervisor.supervisor_state(self._supervisor.GetMyContextFromRoot(self.context))

    def _end_condition(self, episode: _Episode, refused_before: int) -> str:
        """Which of END_CONDITIONS ended the episode in the last step ("" for none)."""
        status = self._supervisor_state()
        ball = self._ball.ball_state_port.Eval(self._ball.GetMyContextFromRoot(self.context))
        X_WR = self._kinematics.racket_pose_port.Eval(self._kinematics.GetMyContextFromRoot(self.context))
        return end_condition(episode.result, status.rejected > refused_before, status.last_reason, ball, X_WR.translation()[0],
                             self._pass_distance, self.context.get_time(), self.params.rally.time_limit)

    def _advance(self) -> None:
        """One period on: to the next observation instant, counted in whole periods (a time summed
        period by period can land an ulp past the controller's event and hand it the old action)."""
        self._steps += 1
        self.simulator.AdvanceTo(self._first_observation + self._steps * self.period)

    def _finish_return(self, episode: _Episode) -> None:
        """After the hit: no more segments; simulate until the return is decided or
        ``post_hit_time_limit`` has passed since the hit."""
        self._request(np.zeros(ACTION_SIZE), valid=False)
        deadline = episode.result.hit.time + self.params.post_hit_time_limit
        while not episode.result.done and self.context.get_time() < deadline:
            self._advance()
            episode.result = self._classify(episode.serve)
        episode.result = timed_out(episode.result)

    def _next_shot(self) -> tuple[np.ndarray, bool]:
        """The next shot of the current batch, drawing a new batch when it is used up."""
        if not self._shots:
            if self._distribution is None:
                self._distribution = make_distribution(self.params.shots, self.params.rally.physics)
            sample = self._distribution.draw(self.np_random, self.params.shot_batch)
            self._shots = list(zip(sample.states, (bool(s) for s in sample.serve)))
        return self._shots.pop(0)

    def _draw_robot_state(self, start: str):
        """(q, v, a, kind) of a drawn initial robot state (``draw_robot_start``)."""
        return draw_robot_start(self.stack, self.params, self.np_random, start)
