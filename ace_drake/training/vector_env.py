"""RallyVectorEnv: B rally episodes stepped together on one segment-stepped diagram.

The rally episode of ``training.env`` (its initial-state distribution, its four end conditions
and its terminal reward, paper eq. (10)) for B environments at once, as a
``gymnasium.vector.VectorEnv`` over ``diagrams.build_segment_rally_diagram``: one Simulator, one
Context, B environments in every port. Each ``step`` ticks the diagram once (32 ms of every
environment's episode).

Episodes end independently and restart in the next step (gymnasium's ``NEXT_STEP`` autoreset:
the step after an environment's terminal step starts its next episode, ignoring that step's
action, and returns its first observation with reward 0). Environment i's episode k is a
function of (seed, i + first_index, k) alone: its skill, robot start and the seed of its
stochastic systems are drawn from ``numpy.random.default_rng([seed, index, k, 1])``, and its
shot is the k-th of that environment's own stream of shots (drawn in batches of ``shot_batch``
from ``default_rng([seed, index, 0])``), so a batch gives, environment by environment, the
episodes of single-environment runs with the same seeds.

After a hit the episode ends in the same step, as in ``RallyEnv``: the return is decided by
flying the ball on (``physics.propagate.simulate_ball``, the same flight and impact maps) to its first
table or floor contact or ``post_hit_time_limit``. (The diagram would also let the robot touch the
ball again on the way; a double hit after a return is not looked for.)
"""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from ace_drake.contracts import EpisodeResult, Outcome
from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.learning.rewards import terminal_reward
from ace_drake.physics.propagate import ContactKind, simulate_ball
from ace_drake.play.episode import classify, timed_out
from ace_drake.play.shots import make_distribution
from ace_drake.training.env import UNHIT_REASONS, RallyEnvParams, draw_robot_start, end_condition, hold_action, pass_distance

SHOT_STREAM = 0  # the third key of an environment's shot stream; episode k's own draws use [seed, index, k, 1]


@dataclasses.dataclass
class _Episode:
    """One environment's running episode (the simulation itself lives in the Context)."""

    shot: np.ndarray
    serve: bool
    skill: np.ndarray
    start: str
    result: EpisodeResult
    refused: int = 0
    end: str = ""
    reward: float = 0.0


class RallyVectorEnv(gymnasium.vector.VectorEnv):
    """B rally episodes (module docstring) as a gymnasium vector environment.

    Actions (B, 16) in [-1, 1] (``control.action_mapping``, eq. (12)); observations (B, n) float32
    (``ObservationLayout``, ``self.layout``); rewards terminal (``learning.rewards``); ``truncated``
    is always False. infos (arrays over the B environments): ``privileged`` (B, 28) float32 (the
    true ball [p, v, w], the joints' true [q, v] and the skill, ``training.env.PRIVILEGED_PARTS``),
    ``time`` (s, each episode's), ``outcome`` and ``end`` (strings), ``serve``, ``skill`` (B, 3),
    ``start``, ``segments`` (B, 2) [accepted, refused], ``episode_index`` (each environment's episode
    index) and ``result`` (the EpisodeResults, objects).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int, params: RallyEnvParams | None = None, distribution=None, first_index: int = 0):
        """Args: num_envs, B; params (default RallyEnvParams(); its rally params are used with
        ``stepping="segment"``); distribution, a ``play.shots.ShotDistribution`` (default: fitted
        from ``params.shots`` at the first reset); first_index, the index of environment 0 in the
        seeding (workers of one run give theirs disjoint ranges)."""
        if num_envs < 1:
            raise ValueError(f"RallyVectorEnv: num_envs must be >= 1, got {num_envs}")
        self.params = params or RallyEnvParams()
        rally = dataclasses.replace(self.params.rally, stepping="segment")
        self.params = dataclasses.replace(self.params, rally=rally)
        self.num_envs = int(num_envs)
        self.first_index = int(first_index)
        self.diagram = build_segment_rally_diagram(rally, None, self.num_envs)
        self.simulator = make_segment_simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self._default_context = self.diagram.CreateDefaultContext()
        subsystem = self.diagram.GetSubsystemByName
        self._ball, self._joints = subsystem("ball"), subsystem("joint_plant")
        self._supervisor, self._observation_builder = subsystem("safety_supervisor"), subsystem("observation_builder")
        self._clock = subsystem("episode_clock")
        self.stack = self._supervisor.stack
        self.layout = self._observation_builder.layout
        self.timing = self._supervisor.timing
        self._kinematics = self.diagram.GetSubsystemByName("planned_kinematics").kinematics
        self._pass_distance = pass_distance(self.params)
        self.single_observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (self.layout.size,), np.float32)
        self.single_action_space = gymnasium.spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._distribution = distribution
        self._seed = 0
        self._shots: list[list] = [[] for _ in range(self.num_envs)]
        self._shot_rngs: list[np.random.Generator] = []
        self._episode_index = np.zeros(self.num_envs, dtype=np.int64)
        self._episodes: list[_Episode | None] = [None] * self.num_envs
        self._restart = np.zeros(self.num_envs, dtype=bool)
        self._tick = 0

    # ------------------------------------------------------------------------------ gymnasium
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Starts episode 0 of every environment (``seed`` None: one drawn from the vector env's
        own generator, ``np_random``) and returns the first observations (B, n) and infos.
        ``options`` is not supported."""
        if options:
            raise ValueError(f"RallyVectorEnv.reset: options are not supported, got {sorted(options)}")
        super().reset(seed=seed)
        self._seed = int(self.np_random.integers(2**31 - 1)) if seed is None else int(seed)
        self._shot_rngs = [np.random.default_rng([self._seed, self.first_index + i, SHOT_STREAM]) for i in range(self.num_envs)]
        self._shots = [[] for _ in range(self.num_envs)]
        self._episode_index[:] = 0
        self.context.SetTimeStateAndParametersFrom(self._default_context)
        self._start(np.arange(self.num_envs))
        self.diagram.GetInputPort("light_curtain").FixValue(self.context, np.zeros(self.num_envs))
        self._request(np.zeros((self.num_envs, ACTION_SIZE)), np.zeros(self.num_envs, dtype=bool))
        self.simulator.Initialize()
        self._tick = 1
        self.simulator.AdvanceTo(self._tick * self.timing.duration)  # every episode's tick 0: to its first observation
        self._restart[:] = False
        return self._observations(), self._infos()

    def step(self, actions):
        """One tick: the running environments act, those that ended last step start their next
        episode (NEXT_STEP autoreset). Returns (observations, rewards, terminated, truncated, infos)."""
        if not self._shot_rngs:
            raise RuntimeError("RallyVectorEnv.step: call reset() first")
        actions = np.asarray(actions, dtype=float)
        if actions.shape != (self.num_envs, ACTION_SIZE):
            raise ValueError(f"RallyVectorEnv.step: actions must have shape ({self.num_envs}, {ACTION_SIZE}), got {actions.shape}")
        restarting = np.flatnonzero(self._restart)
        if restarting.size:
            self._episode_index[restarting] += 1
            self._start(restarting)
        running = ~self._restart
        self._request(actions, running)
        refused_before = np.array([s.rejected for s in self._supervisor_states()])
        # Whole ticks: a time summed step by step can stop an ulp before a tick and shift every action.
        self._tick += 1
        self.simulator.AdvanceTo(self._tick * self.timing.duration)
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        states = self._supervisor_states()
        balls = self._ball_states()
        events = self._events()
        times = self._episode_times()
        racket_x = self._racket_x()
        for row in np.flatnonzero(running):
            episode = self._episodes[row]
            episode.result = classify(events[row], episode.serve)
            episode.end = end_condition(episode.result, states[row].rejected > refused_before[row], states[row].last_reason,
                                        balls[row], racket_x[row], self._pass_distance, times[row], self.params.rally.time_limit)
            if episode.end == "hit":
                episode.result = self._finish_return(events[row], balls[row], times[row], episode)
            elif episode.end == "time_limit":
                episode.result = timed_out(episode.result)
            elif episode.end in UNHIT_REASONS:
                episode.result = dataclasses.replace(episode.result, outcome=Outcome.MISSED, reason=UNHIT_REASONS[episode.end])
            if episode.end:
                episode.reward = terminal_reward(episode.result, episode.skill, self.params.reward, collided=episode.end == "collision")
                rewards[row], terminated[row] = episode.reward, True
        self._restart = terminated.copy()
        return self._observations(), rewards, terminated, np.zeros(self.num_envs, dtype=bool), self._infos()

    # ------------------------------------------------------------------------------ queries
    def results(self) -> list[EpisodeResult | None]:
        """Each environment's running (or just ended) EpisodeResult."""
        return [None if e is None else e.result for e in self._episodes]

    def privileged_observations(self) -> np.ndarray:
        """The critic's observations now (B, 28), float32: true ball, joints' true [q, v], skill."""
        joints = self._joints.joint_state_port.Eval(self._joints.GetMyContextFromRoot(self.context))
        skills = np.array([e.skill for e in self._episodes])
        return np.concatenate([self._ball_states(), joints, skills], axis=1).astype(np.float32)

    def ball_from_blade(self) -> np.ndarray:
        """The true ball centres relative to the blade centres now (B, 3), m (world axes)."""
        joints = self._joints.joint_state_port.Eval(self._joints.GetMyContextFromRoot(self.context))
        n = joints.shape[1] // 2
        return self._ball_states()[:, :3] - self._kinematics.racket_pose(joints[:, :n])[0]

    def hold_actions(self, rows=None) -> np.ndarray:
        """The actions (k, 16) that continue the committed plans of environments ``rows`` (default
        all) through the segment the next step decides (``training.env.hold_action``): what "no new
        segment" does, as an action a demonstrator without one can be labelled with."""
        rows = np.arange(self.num_envs) if rows is None else np.asarray(rows, dtype=int).reshape(-1)
        states = self._supervisor_states()
        boundaries = self.timing.boundary_sample(self._clock.ticks(self._clock.GetMyContextFromRoot(self.context)))
        return np.array([hold_action(self.stack, states[row].plan, int(boundaries[row] - states[row].plan_start)) for row in rows]).reshape(-1, ACTION_SIZE)

    # ------------------------------------------------------------------------------ helpers
    def _start(self, rows: np.ndarray) -> None:
        """Draws and starts the next episode of environments ``rows`` (module docstring)."""
        shots, serves, skills, qs, vs, as_, kinds, seeds = [], [], [], [], [], [], [], []
        width = self.params.rally.physics.table.width
        for row in rows:
            shot, serve = self._next_shot(row)
            rng = np.random.default_rng([self._seed, self.first_index + int(row), int(self._episode_index[row]), 1])
            skill = self.params.skill.sample(rng, width)
            kind = "dynamic" if rng.random() < self.params.dynamic_start_fraction else "static"
            q, v, a, kind = draw_robot_start(self.stack, self.params, rng, kind)
            seeds.append(int(rng.integers(2**31 - 1)))
            shots.append(shot), serves.append(serve), skills.append(skill), kinds.append(kind), qs.append(q)
            vs.append(np.zeros(q.size) if v is None else v)
            as_.append(np.zeros(q.size) if a is None else a)
        start_segment_episodes(self.diagram, self.context, rows, np.array(shots), np.array(seeds), np.array(skills), np.array(qs), np.array(vs), np.array(as_))
        for k, row in enumerate(rows):
            self._episodes[row] = _Episode(shots[k], serves[k], skills[k], kinds[k], classify((), serves[k]))

    def _next_shot(self, row: int):
        """The next shot of environment ``row``'s stream (a new batch when it is used up)."""
        if not self._shots[row]:
            if self._distribution is None:
                self._distribution = make_distribution(self.params.shots, self.params.rally.physics)
            sample = self._distribution.draw(self._shot_rngs[row], self.params.shot_batch)
            self._shots[row] = list(zip(sample.states, (bool(s) for s in sample.serve)))
        return self._shots[row].pop(0)

    def _finish_return(self, events, ball: np.ndarray, time: float, episode: _Episode) -> EpisodeResult:
        """The return decided by flying the ball on from ``ball`` (9,) at episode ``time`` (s) to
        its first table or floor contact, within ``post_hit_time_limit`` of the hit."""
        result = classify(events, episode.serve)
        remaining = result.hit.time + self.params.post_hit_time_limit - time
        if not result.done and remaining > 0.0:
            # One ball, unperturbed: the compiled propagator, ``simulate``'s steps and contacts bit for
            # bit (NumPy per 1 ms step made this ~45% of a rollout worker's time).
            flight = simulate_ball(ball, self.params.rally.physics, remaining, dt=self.timing.period,
                                   stop_on=(ContactKind.TABLE, ContactKind.FLOOR))
            later = tuple(dataclasses.replace(event, time=event.time + time) for event in flight.events[0])
            result = classify(tuple(events) + later, episode.serve)
        return timed_out(result)

    def _request(self, actions: np.ndarray, valid: np.ndarray) -> None:
        request = np.concatenate([actions, valid.astype(float)[:, None]], axis=1)
        self.diagram.GetInputPort("action_request").FixValue(self.context, request)

    def _observations(self) -> np.ndarray:
        builder = self._observation_builder
        return builder.observation_port.Eval(builder.GetMyContextFromRoot(self.context)).astype(np.float32)

    def _supervisor_states(self):
        return self._supervisor.supervisor_states(self._supervisor.GetMyContextFromRoot(self.context))

    def _ball_states(self) -> np.ndarray:
        return self._ball.plant_state(self._ball.GetMyContextFromRoot(self.context)).balls

    def _events(self):
        return self._ball.plant_state(self._ball.GetMyContextFromRoot(self.context)).events

    def _episode_times(self) -> np.ndarray:
        return self.timing.tick_time(self._clock.ticks(self._clock.GetMyContextFromRoot(self.context)))

    def _racket_x(self) -> np.ndarray:
        """The blade centre's x (m) at the tick's start, from the joints' true state."""
        joints = self._joints.joint_state_port.Eval(self._joints.GetMyContextFromRoot(self.context))
        n = joints.shape[1] // 2
        return self._kinematics.racket_pose(joints[:, :n])[0][:, 0]

    def _infos(self) -> dict:
        states = self._supervisor_states()
        episodes = self._episodes
        return {
            "privileged": self.privileged_observations(),
            "time": self._episode_times().astype(float),
            "outcome": np.array([e.result.outcome.value for e in episodes]),
            "end": np.array([e.end for e in episodes]),
            "serve": np.array([e.serve for e in episodes]),
            "skill": np.array([e.skill for e in episodes]),
            "start": np.array([e.start for e in episodes]),
            "segments": np.array([[s.accepted, s.rejected] for s in states]),
            "episode_index": self._episode_index.copy(),
            "result": np.array([e.result for e in episodes], dtype=object),
        }
