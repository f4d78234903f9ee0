"""Matches under ITTF rules: the robot (a rally controller and its serves) against a simulated human
opponent, on the segment-stepped rally diagram, judged by its umpire.

Each environment of the diagram plays one match. A point is a chain of episodes in one environment:

- **the service**: the robot's (a ``RobotServes`` start: the robot part-way along the serve's
  commands, the ball just released from the cup; the umpire judges the toss) or the human's (a
  recorded serve of the opponent, ``OpponentModel.sample_serve``, the robot at rest at its reset
  pose);
- **the human's strokes**: when the ball has bounced correctly on the human's court (the
  umpire's ``bounced`` with the human to play), the opponent model decides from the ball just after
  that bounce whether the human returns it (``return_probability``); a returned ball is struck
  ``hit_delay`` after the bounce (the recorded neighbour's, rounded up to the next 32 ms tick:
  the episode of the robot's reply starts there, ``lead`` into that tick), at the place the ball
  has reached then (``ball_at_hit``), leaving with the recorded return's spin and the velocity
  that lands it where the recorded return was seen to land, after the same flight time
  (``retarget_returns``; a recorded return that did not land keeps its velocity). The
  new episode starts with the robot as it is (``start_segment_episodes(..., continuing=True)``:
  its joints and committed plan go on) and the policy told that an episode starts, as in training.
  A ball the human misses flies on, and the umpire gives the point when it touches the floor or
  the human's court again;
- **the robot's strokes**: the controller's, through the full control stack; the ball's contacts,
  the robot's racket included, come from the diagram's BallPlant.

The umpire (``systems.segment.umpire``; ``play.umpire`` for the Laws) decides the point; a let is
replayed by the same server; an episode that runs ``EPISODE_LIMIT`` without a decision (a ball that
never comes down) loses the point for the player to play. The score is ``play.scoring.Match``'s.

Departures: the robot starts every point at rest (its serve's start, or its reset pose), where a
real robot walks there between points; the human's stroke timing is quantised to the 32 ms ticks
(at most 32 ms later than the recorded neighbour's); a recorded return that missed the table
misses from where our ball is, with its recorded velocity.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.contracts import DEFAULT_CONTROLLER
from ace_drake.control.params import RallyParams
from ace_drake.control.serve_execution import ServeStart
from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.evaluation.controllers import diagram_params_for, hit_state_controller, make_controller, rally_params
from ace_drake.evaluation.match_track import MatchTrack, TrackPoint
from ace_drake.evaluation.serves import DEFAULT_LIBRARY, ExecutionNoise, ServeLibrary, choose_serve, load_serve_library
from ace_drake.match_data import load_match_events
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.play.opponent_model import OpponentModel, ball_at_hit, require_players, retarget_returns
from ace_drake.play.scoring import HUMAN, ROBOT, Match, MatchRules, opponent
from ace_drake.play.umpire import PointDecision
from ace_drake.robot.model import load_scenario

EPISODE_LIMIT = 3.0  # s of one episode without a decision before the point goes against the player to play
PAUSE = 0.6  # s between two points in the replay's time line
TRACK_STEP = 4  # command samples (ms) between the replay's frames


class RobotServes(Protocol):
    """The robot's serves: ``start(rng, recent)`` picks one (``recent``: names of the robot's
    last serves, newest last) and returns its name and its episode start with execution noise
    drawn from ``rng``."""

    def start(self, rng: np.random.Generator, recent: Sequence[str]) -> tuple[str, ServeStart]: ...


class LibraryServes:
    """The robot's serves from a serve library (``evaluation.serves``): each point's serve chosen
    by dissimilarity to the recent ones (``choose_serve``), its release perturbed by the
    execution noise the library was measured with."""

    def __init__(self, library: ServeLibrary, physics: BallPhysicsParams, noise: ExecutionNoise | None = None):
        if len(library) == 0:
            raise ConfigError("the serve library is empty: the robot has nothing to serve")
        self.library, self.physics = library, physics
        self.noise = noise if noise is not None else (library.noise or ExecutionNoise())

    def start(self, rng: np.random.Generator, recent: Sequence[str]) -> tuple[str, ServeStart]:
        serve = choose_serve(self.library, recent, rng)
        return serve.name, serve.episode_start(self.physics, self.noise.perturb(serve.release, rng))


@dataclasses.dataclass(frozen=True)
class PointResult:
    """One point of a match: the game (from 1) and its score (robot, human) before the point, who
    served, which serve (robot) or None, the winner (None: a let, replayed), the umpire's reason
    and law, the racket strikes (the service included), and the point's duration (s)."""

    game: int
    score: tuple[int, int]
    server: str
    serve: str | None
    winner: str | None
    reason: str
    law: str
    shots: int
    duration: float

    @property
    def let(self) -> bool:
        return self.winner is None

    @property
    def ace(self) -> bool:
        """A service the receiver never touched that won the point."""
        return self.winner == self.server and self.shots == 1

    def strikes_by(self, player: str) -> int:
        """How many times ``player`` struck the ball in the point (the service included)."""
        first = self.shots - self.shots // 2  # the server strikes first, then they alternate
        return first if player == self.server else self.shots // 2

    @property
    def last_striker(self) -> str | None:
        """Who struck the ball last (None: nobody did)."""
        if self.shots == 0:
            return None
        return self.server if self.shots % 2 == 1 else opponent(self.server)

    @property
    def return_error(self) -> str | None:
        """The player whose return (a stroke after the service) lost the point by going out, into
        the net or onto their own court; None otherwise."""
        if self.let or self.shots < 2 or self.winner == self.last_striker:
            return None
        return self.last_striker

    @property
    def service_fault(self) -> bool:
        """The server lost the point before the receiver struck: the service failed."""
        return self.winner is not None and self.winner != self.server and self.shots <= 1


@dataclasses.dataclass(frozen=True)
class MatchResult:
    """A finished match: the opponent's name, the rules, the games' scores (robot, human), the
    winner, and every point played (lets included)."""

    opponent: str
    rules: MatchRules
    games: tuple[tuple[int, int], ...]
    winner: str
    points: tuple[PointResult, ...]

    def summary(self) -> dict:
        """The ``match.*`` figures (robot's view): points played (lets excluded) and won, games'
        scores, rally length (strikes per point) mean and standard deviation, the robot's aces
        and service faults, and the human's; each player's returns (strokes after the service)
        and how many of them lost the point (``PointResult.return_error``)."""
        decided = [p for p in self.points if not p.let]
        lengths = np.array([p.shots for p in decided], dtype=float)
        robot_serves = [p for p in decided if p.server == ROBOT]
        human_serves = [p for p in decided if p.server == HUMAN]
        return {
            "opponent": self.opponent,
            "winner": self.winner,
            "points_played": len(decided),
            "points_won": sum(p.winner == ROBOT for p in decided),
            "games": [list(g) for g in self.games],
            "games_won": sum(r > h for r, h in self.games),
            "rally_length_mean": float(lengths.mean()) if lengths.size else 0.0,
            "rally_length_std": float(lengths.std()) if lengths.size else 0.0,
            "aces": sum(p.ace for p in robot_serves),
            "service_faults": sum(p.service_fault for p in robot_serves),
            "lets": sum(p.let for p in self.points),
            "human_aces": sum(p.ace for p in human_serves),
            "human_service_faults": sum(p.service_fault for p in human_serves),
            "points_served": len(robot_serves),
            "human_points_served": len(human_serves),
            "points_won_serving": sum(p.winner == ROBOT for p in robot_serves),
            "points_won_receiving": sum(p.winner == ROBOT for p in human_serves),
            **{f"{player}_returns": sum(p.strikes_by(player) - (p.server == player) for p in decided) for player in (ROBOT, HUMAN)},
            **{f"{player}_return_errors": sum(p.return_error == player for p in decided) for player in (ROBOT, HUMAN)},
        }


@dataclasses.dataclass(frozen=True)
class _HumanStroke:
    """The human's answer to a ball on the human's court: missed, or struck when the episode clock
    reaches ``tick`` with the ball in state ``before`` and leaving in state ``after`` (9,) each."""

    missed: bool
    tick: int = 0
    before: np.ndarray | None = None
    after: np.ndarray | None = None


@dataclasses.dataclass
class _Row:
    """One environment's match in progress (the runner's bookkeeping, outside the Context)."""

    index: int
    match: Match
    rng: np.random.Generator
    point_index: int = 0
    shot_index: int = 0
    points: list = dataclasses.field(default_factory=list)
    recent_serves: list = dataclasses.field(default_factory=list)
    serve: str | None = None
    point_ticks: int = 0  # ticks the point has run
    episode_offset: float = 0.0  # point time of the current episode's time 0, s
    stroke: _HumanStroke | None = None  # the human's answer to the ball in play, once decided
    done: bool = False


def episode_seed(seed: int, match: int, point: int, shot: int) -> int:
    """The seed of one episode of a match (its stochastic systems, ``start_segment_episodes``)."""
    return int(np.random.SeedSequence([int(seed), int(match), int(point), int(shot)]).generate_state(1, np.uint32)[0])


class MatchRunner:
    """Plays matches on one segment-stepped rally diagram, one match per environment (module
    docstring)."""

    def __init__(self, controllers, params: RallyParams, batch: int):
        """Args: controllers, one rally controller (``evaluation.controllers``), or ``batch`` of them
        when it remembers its episode (a ``reset()``); params, the rally diagram's (stepping
        "segment"); batch, matches played at once."""
        controllers = list(controllers) if isinstance(controllers, (list, tuple)) else [controllers]
        controllers = [hit_state_controller(c, params) for c in controllers]
        self.params = diagram_params_for(controllers[0], params)
        self.diagram = build_segment_rally_diagram(self.params, controllers if len(controllers) > 1 else controllers[0], batch)
        self.simulator = make_segment_simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self._default_context = self.diagram.CreateDefaultContext()
        get = self.diagram.GetSubsystemByName
        self.ball, self.clock, self.umpire, self.joints = get("ball"), get("episode_clock"), get("umpire"), get("joint_plant")
        self.batch = int(batch)
        self.timing = self.clock.timing

    def _context(self, system):
        return system.GetMyMutableContextFromRoot(self.context)

    def play(self, opponent_model: OpponentModel, serves: RobotServes, count: int, rules: MatchRules | None = None, seed: int = 0,
             opponent_name: str = "", first_server: str | None = None, record: int | None = None,
             progress: Callable[[str], None] | None = None) -> tuple[list[MatchResult], MatchTrack | None]:
        """Plays ``count`` matches (at most ``batch`` at a time) against ``opponent_model`` with the
        robot's ``serves``; match i is seeded by (seed, i) and its first server drawn from that
        (or ``first_server``). ``record``: the match whose replay track to return (None: none).
        ``progress(line)`` after every point of every match. Returns the matches in order and
        the track."""
        rules = MatchRules() if rules is None else rules
        if count < 1:
            raise ValueError(f"MatchRunner.play: count must be >= 1, got {count}")
        results: list[MatchResult | None] = [None] * count
        queue = iter(range(count))
        rows: list[_Row | None] = [None] * self.batch
        self.context.SetTimeStateAndParametersFrom(self._default_context)
        self.diagram.GetInputPort("light_curtain").FixValue(self.context, np.zeros(self.batch))
        track = _TrackRecorder(self.timing) if record is not None else None

        def next_match(row: int) -> None:
            index = next(queue, None)
            if index is None:
                rows[row] = None
                return
            rng = np.random.default_rng([int(seed), index])
            server = first_server or (ROBOT if rng.random() < 0.5 else HUMAN)
            rows[row] = _Row(index, Match(rules, server), rng)
            self._start_point(rows[row], row, opponent_model, serves, seed)

        for row in range(self.batch):
            next_match(row)
        self.simulator.Initialize()
        tick = 0

        def recording_row() -> int | None:
            return next((r for r, state in enumerate(rows) if state is not None and state.index == record), None)

        if track is not None and recording_row() is not None:
            track.mark(self.context.get_time(), rows[recording_row()])
        while any(state is not None for state in rows):
            if track is not None and (row := recording_row()) is not None:
                track.add(self.context.get_time(), self.ball, self.joints, self.context, row)
            tick += 1
            self.simulator.AdvanceTo(tick * self.timing.duration)  # whole ticks: a sum of durations drifts past a tick
            umpires = self.umpire.umpires_port.Eval(self._context(self.umpire))
            ticks = self.clock.ticks(self._context(self.clock))
            for row, state in enumerate(rows):
                if state is None:
                    continue
                state.point_ticks += 1
                ended = self._step_row(state, row, umpires[row], int(ticks[row]), opponent_model, seed)
                if ended is None:
                    continue
                point = self._finish_point(state, umpires[row], *ended)
                if track is not None and state.index == record:
                    track.label(_describe(point))
                if progress is not None:
                    progress(f"match {state.index + 1}: point {len(state.points)}: {_describe(point)}; {state.match.score}")
                if state.match.finished:
                    results[state.index] = MatchResult(opponent_name, rules, tuple(state.match.games), state.match.winner, tuple(state.points))
                    self.umpire.ClosePoints(self._context(self.umpire), [row])
                    next_match(row)
                    if rows[row] is not None and track is not None and rows[row].index == record:
                        track.mark(self.context.get_time(), rows[row])
                else:
                    self._start_point(state, row, opponent_model, serves, seed)
                    if track is not None and state.index == record:
                        track.mark(self.context.get_time(), state)
        return results, (None if track is None else track.finish())

    # ------------------------------------------------------------------------------ points
    def _start_point(self, state: _Row, row: int, opponent_model: OpponentModel, serves: RobotServes, seed: int) -> None:
        state.shot_index, state.stroke, state.serve = 0, None, None
        state.point_ticks, state.episode_offset = 0, 0.0
        server = state.match.server
        episode = episode_seed(seed, state.index, state.point_index, 0)
        umpire_context = self._context(self.umpire)
        if server == ROBOT:
            name, start = serves.start(state.rng, state.recent_serves)
            state.serve = name
            state.recent_serves.append(name)
            start_segment_episodes(self.diagram, self.context, [row], start.ball[None], [episode], planned=[start.planned])
            self.umpire.StartPoints(umpire_context, [row], [ROBOT], [start.toss])
        else:
            ball = opponent_model.sample_serve(state.rng)
            start_segment_episodes(self.diagram, self.context, [row], ball[None], [episode])
            self.umpire.StartPoints(umpire_context, [row], [HUMAN], None)
            # The human's toss is not simulated: the strike's velocity before is unknown, and the
            # umpire judges it only with a Toss.
            self.umpire.HumanStrikes(umpire_context, [row], [0.0], [np.concatenate([ball[:3], np.zeros(3)])])

    def _step_row(self, state: _Row, row: int, umpire, ticks: int, opponent_model: OpponentModel, seed: int):
        """After a tick: the point's decision (decision, None), a time-limit end (None, reason), or
        None while it goes on (the human's stroke is decided or made here)."""
        if umpire.decision is not None:
            return umpire.decision, None
        stroke = state.stroke
        if stroke is not None and not stroke.missed and ticks >= stroke.tick:
            state.stroke = None
            state.shot_index += 1
            hit_time = state.episode_offset + ticks * self.timing.duration
            state.episode_offset = hit_time
            episode = episode_seed(seed, state.index, state.point_index, state.shot_index)
            start_segment_episodes(self.diagram, self.context, [row], stroke.after[None], [episode], continuing=True)
            self.umpire.HumanStrikes(self._context(self.umpire), [row], [hit_time], [stroke.before])
            return None
        if stroke is None and umpire.bounced and umpire.to_play == HUMAN:
            state.stroke = self._human_response(state, row, ticks, opponent_model)
            if not state.stroke.missed and ticks >= state.stroke.tick:  # a stroke due now
                return self._step_row(state, row, umpire, ticks, opponent_model, seed)
            return None
        episode_time = float(self.timing.tick_time(ticks))
        if episode_time >= EPISODE_LIMIT:
            return None, f"time limit: the {umpire.to_play} did not play the ball within {EPISODE_LIMIT} s"
        return None

    def _human_response(self, state: _Row, row: int, ticks: int, opponent_model: OpponentModel) -> _HumanStroke:
        """The human's answer to the ball that just bounced on the human's court."""
        events = self.ball.plant_state(self._context(self.ball)).events[row]
        bounce = next(e for e in reversed(events) if ContactKind(e.kind) == ContactKind.TABLE)
        incoming = np.asarray(bounce.state_post, dtype=float)
        if state.rng.random() >= opponent_model.return_probability(incoming)[0]:
            return _HumanStroke(missed=True)
        states, delays, landings = opponent_model.draw_returns(incoming, state.rng, landings=True)
        period = self.timing.duration
        tick = max(int(math.ceil((bounce.time + float(delays[0])) / period - 1e-9)), ticks)
        before = ball_at_hit(incoming, np.array([tick * period - bounce.time]), self.params.physics)[0]
        after = retarget_returns(states[0], before[:3], self.params.physics, landings)[0]
        return _HumanStroke(False, tick, before, after)

    def _finish_point(self, state: _Row, umpire, decision: PointDecision | None, reason: str | None) -> PointResult:
        """Records the point (the umpire's ``decision``, or a time-limit end with ``reason``
        against the player to play) and awards it."""
        server = state.match.server
        game, score = state.match.game, state.match.points
        if decision is None:
            winner, shots, law, text = opponent(umpire.to_play), umpire.shots, "", reason
        else:
            winner, shots, law, text = decision.winner, decision.shots, decision.law, decision.reason
        point = PointResult(game, score, server, state.serve, winner, text, law, shots, state.point_ticks * self.timing.duration)
        state.points.append(point)
        state.point_index += 1
        if winner is not None:
            state.match.award(winner)
        return point


def _describe(point: PointResult) -> str:
    if point.let:
        return f"let ({point.reason})"
    return f"{point.winner} won, {point.shots} strikes ({point.reason})"


class _TrackRecorder:
    """Collects one match's replay track: the ball and the joints every ``TRACK_STEP`` ms."""

    def __init__(self, timing):
        self.timing = timing
        self.times, self.ball, self.q, self.points = [], [], [], []
        self.pause = 0.0

    def mark(self, time: float, state: _Row) -> None:
        """A point starts at global ``time``: a pause in the replay, the ball hidden."""
        if self.times:
            self.times.append(self.times[-1] + 0.5 * self.timing.period)
            self.ball.append(np.full(3, np.nan))
            self.q.append(self.q[-1])
            self.pause += PAUSE
        match = state.match
        who = "robot serves" if match.server == ROBOT else "human serves"
        robot, human = match.points
        self.points.append(TrackPoint(time + self.pause, f"Point {len(state.points) + 1}, game {match.game}: {robot}-{human}, {who}"))

    def label(self, outcome: str) -> None:
        """Appends the last point's ``outcome`` to its label."""
        point = self.points[-1]
        self.points[-1] = TrackPoint(point.start_time, f"{point.label} - {outcome}")

    def add(self, time: float, ball, joints, context, row: int) -> None:
        """The next tick's ball and joints of environment ``row`` (evaluated before the tick runs:
        the same values the tick then uses)."""
        flight = ball.ball_flight_port.Eval(ball.GetMyContextFromRoot(context))
        motion = joints.joint_motion_port.Eval(joints.GetMyContextFromRoot(context))
        samples = np.arange(0, self.timing.samples, TRACK_STEP)
        self.times.extend(time + self.pause + samples * self.timing.period)
        self.ball.extend(flight.samples[row, samples, :3])
        self.q.extend(motion.zeta[row, samples, :, 0])

    def finish(self) -> MatchTrack:
        return MatchTrack(np.asarray(self.times), np.asarray(self.ball), np.asarray(self.q), tuple(self.points))


DEFAULT_MATCH_DATA = MODELS_DIR.parent.parent / "shared" / "data" / "ace_match_events_elite.csv"  # the recorded matches, beside the project
DEFAULT_OPPONENT = "Elite C"


def point_rows(result: MatchResult) -> list[dict]:
    """One row per point of ``result``: game, score (robot, human) before it, server, serve,
    winner (None: a let), strikes, how it ended (the umpire's reason and law), duration (s)."""
    return [{"game": p.game, "score": list(p.score), "server": p.server, "serve": p.serve, "winner": p.winner, "strikes": p.shots,
             "reason": p.reason, "law": p.law, "duration_s": round(p.duration, 3)} for p in result.points]


def aggregate(results: Sequence[MatchResult]) -> dict:
    """The ``match.*`` figures over several matches: sums of points, games, aces and faults, the
    rally length over all their decided points, and the matches won."""
    summaries = [r.summary() for r in results]
    lengths = np.array([p.shots for r in results for p in r.points if not p.let], dtype=float)
    total = {key: sum(s[key] for s in summaries) for key in ("points_played", "points_won", "games_won", "aces", "service_faults", "lets",
                                                             "points_served", "human_points_served", "human_aces", "human_service_faults", "points_won_serving", "points_won_receiving",
                                                             "robot_returns", "human_returns", "robot_return_errors", "human_return_errors")}
    total.update(matches=len(results), matches_won=sum(r.winner == ROBOT for r in results),
                 games=[game for s in summaries for game in s["games"]],
                 rally_length_mean=float(lengths.mean()) if lengths.size else 0.0,
                 rally_length_std=float(lengths.std()) if lengths.size else 0.0)
    return total


def _project_relative(path) -> str:
    """``path`` relative to the project's root (e.g. ``../shared/data/...``), so that a stored
    summary names no machine's directories."""
    return os.path.relpath(Path(path).resolve(), MODELS_DIR.parent.resolve())


def run_match(controller: str = DEFAULT_CONTROLLER, opponent_name: str = DEFAULT_OPPONENT, data=None, best_of: int = 3,
              golden_point: bool = False, matches: int = 1, sensors: str = "cameras", seed: int = 0, ball_params=None,
              serves=None, batch: int = 8, record: bool = True, progress: Callable[[str], None] = print) -> tuple[dict, MatchTrack | None]:
    """``ace-drake rally``: ``matches`` best-of-``best_of`` matches of the controller named
    ``controller`` (``make_controller``) and the serve library ``serves`` (default the shipped
    one) against the opponent model of the recorded player ``opponent_name`` fitted on the
    match data ``data`` (default the recorded matches beside the project), on the segment-stepped
    rally diagram of ``rally_params`` (``batch`` matches at once). Every input is checked before
    anything is simulated. Returns the summary (``match``: ``aggregate``; ``matches``: each
    match's ``summary``; ``points``: the first match's ``point_rows``) and, with ``record``, the
    first match's replay track."""
    rules = MatchRules(best_of=best_of, golden_point=golden_point)
    if matches < 1 or batch < 1:
        raise ConfigError(f"rally: the number of matches and --batch must be >= 1, got {matches} and {batch}")
    params = rally_params(ball_params, sensors, seed, "segment")
    first = make_controller(controller, params)
    library = load_serve_library(DEFAULT_LIBRARY if serves is None else serves, load_scenario(MODELS_DIR / params.scenario))
    robot_serves = LibraryServes(library, params.physics)
    data = DEFAULT_MATCH_DATA if data is None else data
    if not Path(data).is_file():
        raise ConfigError(f"rally: no match data at {data}: the opponent is fitted on recorded matches (pass --data FILE)")
    events = load_match_events(data)
    require_players(events, [opponent_name], str(data))
    opponent_model = OpponentModel.fit(events, [opponent_name])
    batch = min(batch, matches)
    controllers = [first] + [make_controller(controller, params) for _ in range(batch - 1)] if callable(getattr(first, "reset", None)) else first
    progress(f"rally: {matches} best-of-{best_of} match(es) of '{controller}' against {opponent_name} ({sensors} sensors, seed {seed}, "
             f"{len(library)} serves)")
    runner = MatchRunner(controllers, params, batch)
    results, track = runner.play(opponent_model, robot_serves, matches, rules, seed, opponent_name, record=0 if record else None, progress=progress)
    recorded = opponent_model.data
    return {"controller": controller, "opponent": opponent_name, "best_of": best_of, "golden_point": golden_point, "seed": seed,
            "sensors": sensors, "date": datetime.date.today().isoformat(), "data": _project_relative(data),
            "serves": _project_relative(DEFAULT_LIBRARY if serves is None else serves),
            "opponent_recorded": {"balls_in": len(recorded), "return_rate": recorded.return_rate,
                                  "returns_landed": float(recorded.return_landed[recorded.returned].mean())},
            "match": aggregate(results), "matches": [r.summary() for r in results], "points": point_rows(results[0])}, track
