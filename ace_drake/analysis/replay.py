"""Replay one recorded rally through the BallPlant diagram and compare its bounces with the data.

Neither racket is modelled here, so every recorded shot (the robot's or the human's) is replayed as
a reset of the ball's state to the recorded post-shot state; between shots the ball flies and
bounces under the ball model alone (flight eq. (1), table eqs (2)-(6), net and floor). Time runs
continuously through one Simulator, from 0 at the rally's first event, so the simulated table
contacts can be set against the recorded bounces: how far the model lands from where the real ball
landed after each shot.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import numpy as np
from pydrake.geometry import Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform

from ace_drake.diagrams import build_ball_diagram, make_simulator
from ace_drake.match_data import MatchEvent
from ace_drake.physics.flight import POSITION
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind

TAIL_DURATION = 0.5  # s simulated after the rally's last recorded event
LOG_PERIOD = 0.005  # s between logged ball states
RECORDING_FPS = 50.0  # frames per second of the Meshcat recording (keeps long rallies' HTML small)
RECORDED_BOUNCE_RADIUS = 0.012  # m, the markers of recorded bounces in Meshcat
RECORDED_BOUNCE_COLOR = Rgba(0.1, 0.85, 0.3, 1.0)


class RallyKey(NamedTuple):
    """Names one rally: the opponent (``Elite A``) and the rally id (``/game_0/rally_3``).

    Rally ids restart for every opponent, so both are needed.
    """

    player: str
    rally: str


@dataclasses.dataclass(frozen=True)
class BounceComparison:
    """A recorded bounce and the simulated table contact nearest to it in time.

    simulated is None (and distance and time_error NaN) when the simulation had no table contact.
    distance: between the recorded and simulated ball centres at the bounce, m.
    time_error: simulated minus recorded bounce time, s.
    """

    recorded: MatchEvent
    simulated: ContactEvent | None
    distance: float
    time_error: float


@dataclasses.dataclass
class RallyReplay:
    """A recorded rally replayed through the BallPlant; all times in s from the rally's first event.

    key: which rally; start_time: its first event's recorded timestamp, s (the replay's 0).
    times (T,) s and states (T, 9) [p (m), v (m/s), w (rad/s)]: the simulated ball, sampled every
    LOG_PERIOD s; the state jumps between the samples around each recorded shot (the reset).
    contact_events: the simulated table, net and floor contacts, in time order.
    recorded: the recorded events replayed (those with a full state), in time order.
    bounces: one comparison per recorded bounce.
    """

    key: RallyKey
    start_time: float
    times: np.ndarray
    states: np.ndarray
    contact_events: tuple[ContactEvent, ...]
    recorded: tuple[MatchEvent, ...]
    bounces: tuple[BounceComparison, ...]

    @property
    def bounce_distances(self) -> np.ndarray:
        """(B,) distance between each recorded bounce and its simulated table contact, m."""
        return np.array([b.distance for b in self.bounces])


def rally_keys(events: Sequence[MatchEvent]) -> list[RallyKey]:
    """Every rally in ``events``, in order of first appearance."""
    return list(dict.fromkeys(RallyKey(e.player, e.rally) for e in events))


def select_rally(events: Sequence[MatchEvent], rally: str, player: str | None = None) -> list[MatchEvent]:
    """The events of rally id ``rally`` (e.g. ``/game_0/rally_3``), sorted by time.

    ``player`` (e.g. ``Elite A``) is needed when more than one opponent has a rally with that id.
    Raises ValueError for an unknown rally or an ambiguous one.
    """
    matching = [e for e in events if e.rally == rally and (player is None or e.player == player)]
    if not matching:
        who = f" against {player!r}" if player is not None else ""
        known = sorted({e.rally for e in events if player is None or e.player == player})
        shown = ", ".join(known[:5]) + (", ..." if len(known) > 5 else "")
        raise ValueError(f"select_rally: no rally {rally!r}{who} in the events; known ids: {shown or 'none'}")
    players = sorted({e.player for e in matching})
    if len(players) > 1:
        raise ValueError(f"select_rally: rally {rally!r} exists for players {players}; pass player= to choose one")
    return sorted(matching, key=lambda e: e.time)


def longest_rallies(events: Sequence[MatchEvent], n: int = 1, player: str | None = None) -> list[RallyKey]:
    """The ``n`` rallies with the most shots (of ``player`` only, if given), longest first.

    Ties keep the order of the events.
    """
    if n < 1:
        raise ValueError(f"longest_rallies: n must be >= 1, got {n}")
    shots: dict[RallyKey, int] = {}
    for event in events:
        if player is None or event.player == player:
            key = RallyKey(event.player, event.rally)
            shots[key] = shots.get(key, 0) + (event.kind == "shot")
    if not shots:
        raise ValueError(f"longest_rallies: no events for player {player!r}")
    return sorted(shots, key=lambda key: -shots[key])[:n]


def replay_rally(
    events: Sequence[MatchEvent],
    params: BallPhysicsParams | None = None,
    meshcat: Meshcat | None = None,
    *,
    rally: str | None = None,
    player: str | None = None,
    tail: float = TAIL_DURATION,
) -> RallyReplay:
    """Replays one recorded rally through a ball diagram, resetting the ball at every recorded shot.

    Args:
        events: recorded events; either one rally's events, or many with ``rally`` (and, where the
            id is ambiguous, ``player``) choosing one (see ``select_rally``).
        params: the ball model (the paper's by default).
        meshcat: if given, the replay is recorded and published (``meshcat.StaticHtml()`` gives a
            self-contained file), with the recorded bounces drawn as green markers under
            ``/recorded``.
        tail: seconds simulated after the last recorded event.

    The ball starts at the first event's recorded post-event state (normally the serve) and is set
    to the recorded post-shot state at each later shot. Events with NaN velocity or spin (some net
    events) are left out. Raises ValueError for an unknown or ambiguous rally, or events from more
    than one rally without ``rally``. Each call builds one diagram, which Drake 1.51 never frees:
    fine for a few rallies per process, not for thousands.
    """
    if rally is not None:
        events = select_rally(events, rally, player)
    elif player is not None:
        raise ValueError(f"replay_rally: player={player!r} given without rally=; pass the rally id too")
    else:
        keys = rally_keys(events)
        if len(keys) != 1:
            raise ValueError(f"replay_rally: events hold {len(keys)} rallies; pass rally= (and player=) to choose one")
        events = sorted(events, key=lambda e: e.time)
    if tail < 0:
        raise ValueError(f"replay_rally: tail must be >= 0 s, got {tail}")
    usable = [e for e in events if np.all(np.isfinite(e.state))]
    if not usable:
        raise ValueError(f"replay_rally: rally {events[0].rally!r} has no event with a full ball state")
    start_time = usable[0].time
    recorded = tuple(dataclasses.replace(e, time=e.time - start_time) for e in usable)
    resets = [recorded[0]] + [e for e in recorded[1:] if e.kind == "shot"]
    end_time = recorded[-1].time + tail

    params = params or BallPhysicsParams()
    diagram = build_ball_diagram(params, meshcat=meshcat, log_period=LOG_PERIOD)
    ball = diagram.GetSubsystemByName("ball")
    logger = diagram.GetSubsystemByName("ball_logger")
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    ball_context = ball.GetMyMutableContextFromRoot(context)
    log = logger.GetMutableLog(logger.GetMyContextFromRoot(context))
    log.Clear()
    if meshcat is not None:
        _draw_recorded_bounces(meshcat, recorded)
        meshcat.StartRecording(frames_per_second=RECORDING_FPS, set_visualizations_while_recording=False)
    contact_events: list[ContactEvent] = []
    context.SetTime(0.0)
    for index, shot in enumerate(resets):
        segment_end = resets[index + 1].time if index + 1 < len(resets) else end_time
        # SetBallState clears the contact events, so collect each segment's before the next reset.
        ball.SetBallState(ball_context, shot.state)
        simulator.Initialize()
        simulator.AdvanceTo(segment_end)
        contact_events.extend(ball.contact_events_port.Eval(ball_context))
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()

    return RallyReplay(
        key=RallyKey(usable[0].player, usable[0].rally),
        start_time=start_time,
        times=log.sample_times().copy(),
        states=log.data().T.copy(),
        contact_events=tuple(contact_events),
        recorded=recorded,
        bounces=compare_bounces(recorded, contact_events),
    )


def compare_bounces(recorded: Sequence[MatchEvent], simulated: Sequence[ContactEvent]) -> tuple[BounceComparison, ...]:
    """For each recorded bounce, the simulated table contact nearest in time (same time origin)."""
    table_contacts = [e for e in simulated if e.kind == ContactKind.TABLE]
    contact_times = np.array([e.time for e in table_contacts])
    comparisons = []
    for event in recorded:
        if event.kind != "bounce":
            continue
        if not table_contacts:
            comparisons.append(BounceComparison(event, None, float("nan"), float("nan")))
            continue
        nearest = table_contacts[int(np.argmin(np.abs(contact_times - event.time)))]
        distance = float(np.linalg.norm(nearest.state_pre[POSITION] - event.state[POSITION]))
        comparisons.append(BounceComparison(event, nearest, distance, nearest.time - event.time))
    return tuple(comparisons)


def _draw_recorded_bounces(meshcat: Meshcat, recorded: Sequence[MatchEvent]) -> None:
    """Static markers at the recorded bounce positions, under ``/recorded`` (replacing any old ones)."""
    meshcat.Delete("/recorded")
    bounces = [e for e in recorded if e.kind == "bounce"]
    for index, event in enumerate(bounces):
        path = f"/recorded/bounce_{index}"
        meshcat.SetObject(path, Sphere(RECORDED_BOUNCE_RADIUS), RECORDED_BOUNCE_COLOR)
        meshcat.SetTransform(path, RigidTransform(event.state[POSITION]))
