"""Runs rally episodes on one rally Diagram and one Simulator, resetting its Context each time.

DESIGN.md: build one Simulator per environment and reset its Context rather than rebuild diagrams
(Python systems in built diagrams are never freed in Drake 1.51). An episode starts with the ball
just after the opponent's hit (``diagrams.start_rally``) and runs in 32 ms policy periods until
``episode.classify`` decides it or the time limit passes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.systems.framework import Diagram
from pydrake.systems.primitives import VectorLogSink

from ace_drake.contracts import EpisodeResult
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import make_simulator, start_rally
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
