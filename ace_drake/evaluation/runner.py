"""Runs rally episodes on one rally Diagram and one Simulator, resetting its Context each time.

DESIGN.md: build one Simulator per environment and reset its Context rather than rebuild diagrams
(Python systems in built diagrams are never freed in Drake 1.51). An episode starts with the ball
just after the opponent's hit (``diagrams.start_rally``) and runs in 32 ms policy periods until
``episode.classify`` decides it or the time limit passes.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
from pydrake.systems.framework import Diagram
from pydrake.systems.primitives import VectorLogSink

from ace_drake.contracts import EpisodeResult
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import make_segment_simulator, make_simulator, start_rally, start_segment_episodes
from ace_drake.play.episode import classify, timed_out


@dataclasses.dataclass(frozen=True)
class Episode:
    """One finished episode: the shot it started from (9), its result, the simulated duration (s),
    the supervisor's counts [segments accepted, refused] and the skill it was played with
    [y_desired (m), w_p, w_s] (paper, *States*)."""

    shot: np.ndarray
    result: EpisodeResult
    duration: float
    segments: tuple[int, int]
    skill: np.ndarray


class RallyRunner:
    """Episodes of a built rally diagram (``diagrams.build_rally_diagram``) in one Simulator."""

    def __init__(self, diagram: Diagram, params: RallyParams):
        """Args: diagram, a rally diagram (any builder over ``diagrams.add_rally``); params, the
        RallyParams it was built with (its time limit ends episodes)."""

        self.diagram = diagram
        self.params = params
        self.simulator = make_simulator(diagram)
        self.context = self.simulator.get_mutable_context()
        self._default_context = diagram.CreateDefaultContext()
        self._default_context.SetAccuracy(self.context.get_accuracy())  # copied on every reset
        self._ball = diagram.GetSubsystemByName("ball")
        self._loggers = [system for system in diagram.GetSystems() if isinstance(system, VectorLogSink)]
        self._supervisor = diagram.GetSubsystemByName("safety_supervisor")
        self._observation = diagram.GetSubsystemByName("observation_builder")
        self._period = self._supervisor.segment_samples * self._supervisor.period

    def reset(self, shot, seed: int = 0, skill=None, q=None, start_time: float = 0.0) -> None:
        """Resets the Context to the diagram's default (loggers emptied) and starts an episode
        from ``shot`` (see ``diagrams.start_rally``, which also tells the policy) at
        ``start_time`` (s; a multiple of the 32 ms policy period, so that a replay can run
        episodes one after another on one time line)."""

        shot = np.asarray(shot, dtype=float)
        if shot.shape != (9,) or not np.all(np.isfinite(shot)):
            raise ValueError(f"RallyRunner: a shot is 9 finite values [p, v, w], got {shot}")
        periods = start_time / self._period
        if start_time < 0.0 or abs(periods - round(periods)) > 1e-9:
            raise ValueError(f"RallyRunner: start_time must be a non-negative multiple of {self._period} s, got {start_time}")
        self.context.SetTimeStateAndParametersFrom(self._default_context)
        self.context.SetTime(start_time)
        for logger in self._loggers:  # logs live in the Context's cache, not its state
            logger.FindMutableLog(self.context).Clear()
        start_rally(self.diagram, self.context, shot, seed=seed, skill=skill, q=q)
        self.simulator.Initialize()

    def result(self, serve: bool = False) -> EpisodeResult:
        """The episode's state from the ball's contacts so far."""
        return classify(self._ball.contact_events_port.Eval(self._ball.GetMyContextFromRoot(self.context)), serve)

    def run(self, shot, seed: int = 0, serve: bool = False, skill=None, q=None, start_time: float = 0.0) -> Episode:
        """Runs one episode to its end (decided, or the time limit) and returns it."""
        self.reset(shot, seed, skill, q, start_time)
        steps = int(np.ceil(self.params.time_limit / self._period))
        result = self.result(serve)
        for step in range(1, steps + 1):
            self.simulator.AdvanceTo(start_time + step * self._period)
            result = self.result(serve)
            if result.done:
                break
        status = self._supervisor.supervisor_state(self._supervisor.GetMyContextFromRoot(self.context))
        duration = self.context.get_time() - start_time
        skill = self._observation.GetSkill(self._observation.GetMyContextFromRoot(self.context))
        return Episode(np.asarray(shot, dtype=float), timed_out(result), duration, (status.accepted, status.rejected), skill)


class SegmentRallyRunner:
    """Many episodes on one segment-stepped rally diagram (``diagrams.build_segment_rally_diagram``,
    B environments): each environment plays shots one after another, a new one starting in the
    tick after its last ended (decided, or ``params.time_limit``), until every shot is played."""

    def __init__(self, diagram: Diagram, params: RallyParams):
        """Args: diagram, a segment-stepped rally diagram with its policy inside; params, the
        RallyParams it was built with."""
        self.diagram = diagram
        self.params = params
        self.simulator = make_segment_simulator(diagram)
        self.context = self.simulator.get_mutable_context()
        self._default_context = diagram.CreateDefaultContext()
        subsystem = diagram.GetSubsystemByName
        self._ball, self._clock = subsystem("ball"), subsystem("episode_clock")
        self._supervisor, self._observation = subsystem("safety_supervisor"), subsystem("observation_builder")
        self.batch = self._clock.batch
        self.timing = self._clock.timing

    def run_many(self, shots, serve, seeds, skills=None, progress: Callable[[int], None] | None = None) -> list[Episode]:
        """Plays every shot (n, 9) once, shot i seeded with ``seeds[i]`` and played with
        ``skills[i]`` ((n, 3); None: the default skill); ``progress(k)`` after each tick that
        ended k episodes. Returns the Episodes in the shots' order."""
        shots = np.asarray(shots, dtype=float).reshape(-1, 9)
        serve = np.asarray(serve, dtype=bool).reshape(-1)
        seeds = np.asarray(seeds).reshape(-1)
        if serve.size != len(shots) or seeds.size != len(shots):
            raise ValueError(f"SegmentRallyRunner.run_many: {len(shots)} shots need as many serve flags and seeds, got {serve.size}, {seeds.size}")
        if skills is not None:
            skills = np.asarray(skills, dtype=float)
            if skills.shape != (len(shots), 3):
                raise ValueError(f"SegmentRallyRunner.run_many: skills must be ({len(shots)}, 3), got {skills.shape}")
        episodes: list[Episode | None] = [None] * len(shots)
        playing = np.full(self.batch, -1)  # the shot each environment plays (-1: none)
        self.context.SetTimeStateAndParametersFrom(self._default_context)
        self.diagram.GetInputPort("light_curtain").FixValue(self.context, np.zeros(self.batch))
        following = iter(range(len(shots)))

        def start(rows):
            chosen = [(row, next(following, None)) for row in rows]
            chosen = [(row, shot) for row, shot in chosen if shot is not None]
            for row, shot in chosen:
                playing[row] = shot
            if chosen:
                rows_, shots_ = np.array([r for r, _ in chosen]), np.array([s for _, s in chosen])
                start_segment_episodes(self.diagram, self.context, rows_, shots[shots_], seeds[shots_], None if skills is None else skills[shots_])
            for row in rows:
                if row not in {r for r, _ in chosen}:
                    playing[row] = -1

        start(list(range(self.batch)))
        self.simulator.Initialize()
        tick = 0
        limit = self.params.time_limit
        while np.any(playing >= 0):
            tick += 1
            self.simulator.AdvanceTo(tick * self.timing.duration)  # whole ticks (see RallyVectorEnv.step)
            ball = self._ball.plant_state(self._ball.GetMyContextFromRoot(self.context))
            times = self.timing.tick_time(self._clock.ticks(self._clock.GetMyContextFromRoot(self.context)))
            ended = []
            for row in np.flatnonzero(playing >= 0):
                index = playing[row]
                result = classify(ball.events[row], bool(serve[index]))
                if result.done or times[row] >= limit - 1e-9:
                    status = self._supervisor.supervisor_states(self._supervisor.GetMyContextFromRoot(self.context))[row]
                    skill = self._observation.skills(self._observation.GetMyContextFromRoot(self.context))[row].copy()
                    episodes[index] = Episode(shots[index], timed_out(result), float(times[row]), (status.accepted, status.rejected), skill)
                    ended.append(row)
            if ended:
                start(ended)
                if progress is not None:
                    progress(len(ended))
        return episodes
