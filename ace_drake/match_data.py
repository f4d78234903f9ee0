"""Recorded match events (the format of ../shared/data/ace_match_events_elite.csv).

Each row is a ball state just after an event (shot, bounce or net) estimated by the real robot's
perception; consecutive events of a rally give the (start, next event) pairs that validate and
identify the ball model.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ace_drake.config import InputError

REQUIRED_COLUMNS = ("player_id", "rally_id", "type", "timestamp", "ball_pos", "ball_vel_out", "ball_spin_out")


class MatchDataError(InputError):
    """The match-data file is missing or malformed; the message names the file, row and column."""


@dataclasses.dataclass(frozen=True)
class MatchEvent:
    """One recorded event: who, which rally, what (``shot``/``bounce``/``net`` by ``p1``/``p2``),
    when (s), and the ball state just after it, (9,) = [p (m), v (m/s), w (rad/s)]; velocity and
    spin are NaN where the recording has none."""

    player: str
    rally: str
    kind: str
    side: str
    time: float
    state: np.ndarray

    @property
    def type(self) -> str:
        """The CSV's ``type`` column, e.g. ``shot_p2``."""
        return f"{self.kind}_{self.side}" if self.side else self.kind


@dataclasses.dataclass(frozen=True)
class EventPairs:
    """N consecutive (start, end) event pairs, as arrays.

    players (N,), transitions (N,) like ``shot_p2->bounce_p1``, durations (N,) s, start_states and
    end_states (N, 9): the recorded post-event states.
    """

    players: np.ndarray
    transitions: np.ndarray
    durations: np.ndarray
    start_states: np.ndarray
    end_states: np.ndarray

    def __len__(self) -> int:
        return len(self.players)

    def subset(self, mask: np.ndarray) -> "EventPairs":
        """The pairs where ``mask`` is true."""
        return EventPairs(*(getattr(self, f.name)[mask] for f in dataclasses.fields(self)))


def load_match_events(path: str | Path) -> list[MatchEvent]:
    """Reads a match-data CSV into events, in file order; raises MatchDataError on bad input."""
    path = Path(path)
    if not path.is_file():
        raise MatchDataError(f"match data file not found: {path}")
    events = []
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in REQUIRED_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise MatchDataError(f"{path}: missing column(s) {missing}; expected {list(REQUIRED_COLUMNS)}")
        for line, row in enumerate(reader, start=2):
            absent = [c for c in REQUIRED_COLUMNS if row.get(c) is None]  # a short row: DictReader fills None
            if absent:
                raise MatchDataError(f"{path}, line {line}: no value in column(s) {absent} (the row has "
                                     f"{sum(v is not None for v in row.values())} fields; expected {len(reader.fieldnames)})")
            try:
                kind, _, side = row["type"].partition("_")
                if kind not in ("shot", "bounce", "net"):
                    raise ValueError(f"unknown event type {row['type']!r}")
                position = _parse_vector(row["ball_pos"])
                if not np.all(np.isfinite(position)):
                    raise ValueError(f"non-finite ball_pos {row['ball_pos']!r}")
                # Velocity and spin may be unknown (NaN), as after some net events.
                state = np.concatenate([position, _parse_vector(row["ball_vel_out"]), _parse_vector(row["ball_spin_out"])])
                time = float(row["timestamp"])
            except (ValueError, KeyError) as error:
                raise MatchDataError(f"{path}, line {line}: {error}") from None
            rally = row["rally_id"].rsplit("/", 1)[0]
            events.append(MatchEvent(row["player_id"], rally, kind, side, time, state))
    if not events:
        raise MatchDataError(f"{path}: no events")
    return events


def event_pairs(
    events: Sequence[MatchEvent],
    start_kinds: Iterable[str] = ("shot", "bounce"),
    end_kinds: Iterable[str] = ("bounce",),
) -> EventPairs:
    """Consecutive events of one rally whose first is in ``start_kinds`` and second in ``end_kinds``.

    The default (shot or bounce, then bounce) gives the flight-and-landing pairs of physics
    validation; a pair with a net event between its ends is not consecutive and is left out.
    """
    start_kinds, end_kinds = set(start_kinds), set(end_kinds)
    rows = []
    for first, second in zip(events[:-1], events[1:]):
        if first.rally != second.rally or first.player != second.player:
            continue
        if (
            first.kind in start_kinds
            and second.kind in end_kinds
            and second.time > first.time
            and np.all(np.isfinite(first.state))
        ):
            rows.append((first, second))
    if not rows:
        return EventPairs(*(np.empty((0,) + s) for s in [(), (), (), (9,), (9,)]))
    return EventPairs(
        players=np.array([a.player for a, _ in rows]),
        transitions=np.array([f"{a.type}->{b.type}" for a, b in rows]),
        durations=np.array([b.time - a.time for a, b in rows]),
        start_states=np.stack([a.state for a, _ in rows]),
        end_states=np.stack([b.state for _, b in rows]),
    )


def _parse_vector(text: str) -> np.ndarray:
    values = text.strip().strip("[]").split()
    if len(values) != 3:
        raise ValueError(f"expected a 3-vector like '[ x y z ]', got {text!r}")
    vector = np.array([float(v) for v in values])
    if np.any(np.isinf(vector)):
        raise ValueError(f"infinite value in {text!r}")
    return vector
