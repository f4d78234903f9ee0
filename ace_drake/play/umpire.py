"""The umpire: who wins a rally, from the ball's contacts in time order (ITTF Laws 2.5-2.10).

A rally is the sequence of the ball's contacts with the table, the net, the floor and the players'
rackets (``RallyEvent``: a ``physics.propagate.ContactEvent`` plus, for a racket, whose it is),
starting at the service. The frame is DESIGN.md's: origin at the centre of the playing surface,
x towards the human, z up; x < 0 is the robot's court, x >= 0 the human's. SI units throughout.

The Laws as they matter in simulation:

- 2.6 Service. 2.6.2: the ball is projected near vertically upwards and rises at least 16 cm,
  then falls without touching anything before being struck; 2.6.3: it is struck while falling,
  touches the server's court first and then, after passing over or around the net assembly,
  the receiver's court; 2.6.4: until struck it is above the playing surface and behind the
  server's end line. The toss (2.6.2 and 2.6.4) is judged only when a ``Toss`` is given: the
  project's serves are often post-hit ball states with no toss simulated.
- 2.7 Return: after bouncing once on the striker's court, the ball is struck so that it passes over
  or around the net assembly and touches the opponent's court, directly or after touching the net
  assembly (a net-cord ball that lands is good).
- 2.9.1.1 Let: a service that touches the net assembly and is otherwise good (or is obstructed by
  the receiver after touching it) is replayed, no point.
- 2.10.1 The point goes to the opponent of the player who: fails to serve (2.10.1.1) or return
  (2.10.1.2) correctly; lets the ball touch anything but the net assembly (a second bounce on their
  court, the floor) after the opponent's shot before striking it (2.10.1.3); plays a ball that
  passes beyond the receiver's end line without touching their court (2.10.1.4) or through the net
  (2.10.1.5); obstructs the ball (2.10.1.6); strikes it twice in succession (2.10.1.7).
- 2.1.2 The playing surface includes its top edges but not its sides (edge balls count).

Simplifications (the simulation cannot see more):

- A strike before the ball has bounced on the striker's court (a volley) loses the point whatever
  the ball's path. In the Laws that is obstruction (2.5.8) only over or travelling towards the
  playing surface; a ball struck beyond the end line while going long would be the striker's point.
- Edge balls: a TABLE contact counts as the playing surface when the ball's centre is not below the
  surface plane (z >= 0) and within one ball radius of the table's rectangle (|x| <= L/2 + r,
  |y| <= W/2 + r, a 1e-6 m round-off allowance added); otherwise it is a side ball and counts as
  touching something other than the court. The project's propagator only makes top-surface
  contacts with the ball's centre over the rectangle, so every one of its TABLE contacts counts.
- Through the net: the propagator's net contact reflects the ball, so a ball cannot pass through
  the net. A NET contact whose ball centre is below the playing surface's plane or more than one
  ball radius from the net assembly (the rectangle x = 0, |y| <= W/2 + overhang, 0 <= z <= net
  height) is judged a ball through or under the net (2.10.1.5).
- The toss: "near vertically" is taken as a release velocity within ``MAX_TOSS_TILT`` = 10 degrees
  of +z (the Laws give no number; a 1.8 m/s toss then drifts at most 0.3 m/s sideways); the rise is
  the toss's own apex height above the release point (``Toss.apex_height``, e.g. from a simulated
  flight; ``Toss.ballistic`` is the drag-free value); "falling" is a negative vertical velocity
  just before the service strike. The ball resting on the palm and "without imparting spin"
  (2.6.1-2.6.2) and visibility (2.6.4-2.6.5) are not judged.
- Anything but the server's racket touching the ball before the service strike is a service fault
  (2.6.2), except a strike by the receiver, judged as a volley.
- A rally whose events run out before a decision is undecided: ``judge_rally`` returns None and the
  caller (a match runner with a time limit) decides; ``Umpire.to_play`` says who must play next.
  Events after the deciding one are ignored.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Iterable

import numpy as np

from ace_drake.physics.flight import POSITION, VELOCITY
from ace_drake.physics.params import BallPhysicsParams, NetParams, TableParams
from ace_drake.physics.propagate import ContactEvent, ContactKind
from ace_drake.play.scoring import HUMAN, ROBOT, opponent, require_player

MIN_TOSS_RISE = 0.16  # m above the release point (Law 2.6.2)
MAX_TOSS_TILT = math.radians(10.0)  # rad, release velocity from vertical ("near vertically", chosen)
POSITION_SLACK = 1e-6  # m, round-off allowance on the court's and net's edges
GRAVITY = 9.81  # m/s^2, for Toss.ballistic
RALLY_KINDS = (ContactKind.TABLE, ContactKind.NET, ContactKind.FLOOR, ContactKind.RACKET)


@dataclasses.dataclass(frozen=True)
class RallyEvent:
    """One contact of the ball in a rally.

    kind: TABLE, NET, FLOOR or RACKET. time: s. position (3,): the ball's centre at the contact, m.
    velocity_pre (3,): the ball's velocity just before it, m/s. striker: for a RACKET, whose racket
    (ROBOT or HUMAN); None for any other kind.
    """

    kind: ContactKind
    time: float
    position: np.ndarray
    velocity_pre: np.ndarray
    striker: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in RALLY_KINDS:
            raise ValueError(f"RallyEvent.kind must be one of {[k.name for k in RALLY_KINDS]}, got {self.kind!r}")
        if self.kind == ContactKind.RACKET:
            require_player(self.striker, "RallyEvent.striker of a RACKET contact")
        elif self.striker is not None:
            raise ValueError(f"RallyEvent.striker must be None for a {self.kind.name} contact, got {self.striker!r}")
        for name in ("position", "velocity_pre"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,):
                raise ValueError(f"RallyEvent.{name} must have shape (3,), got {value.shape}")
            object.__setattr__(self, name, value)

    @classmethod
    def from_contact(cls, event: ContactEvent, striker: str | None = None) -> RallyEvent:
        """The rally event of a propagator or BallPlant contact; ``striker`` for a RACKET."""
        state = np.asarray(event.state_pre, dtype=float)
        return cls(ContactKind(event.kind), float(event.time), state[POSITION], state[VELOCITY], striker)


@dataclasses.dataclass(frozen=True)
class Toss:
    """The service toss (Law 2.6.2).

    release_time: s. release_position (3,): the ball's centre as it leaves the hand, m.
    release_velocity (3,): m/s. apex_height: how far the ball rose above the release point, m.
    """

    release_time: float
    release_position: np.ndarray
    release_velocity: np.ndarray
    apex_height: float

    def __post_init__(self) -> None:
        for name in ("release_position", "release_velocity"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,):
                raise ValueError(f"Toss.{name} must have shape (3,), got {value.shape}")
            object.__setattr__(self, name, value)

    @classmethod
    def ballistic(cls, release_time: float, release_position, release_velocity, gravity: float = GRAVITY) -> Toss:
        """A toss whose apex is the drag-free one, v_z^2 / (2 g) above the release (0 if v_z <= 0)."""
        v_z = float(np.asarray(release_velocity, dtype=float)[2])
        return cls(release_time, release_position, release_velocity, max(v_z, 0.0) ** 2 / (2.0 * gravity))

    @property
    def tilt(self) -> float:
        """Angle of the release velocity from vertical (+z), rad (pi for a ball at rest)."""
        speed = float(np.linalg.norm(self.release_velocity))
        return math.acos(np.clip(self.release_velocity[2] / speed, -1.0, 1.0)) if speed > 0.0 else math.pi


@dataclasses.dataclass(frozen=True)
class Court:
    """The geometry the umpire needs: the table and net (``physics.params``) and the ball's
    radius, m."""

    table: TableParams = dataclasses.field(default_factory=TableParams)
    net: NetParams = dataclasses.field(default_factory=NetParams)
    ball_radius: float = 0.02

    @classmethod
    def from_physics(cls, params: BallPhysicsParams) -> Court:
        return cls(params.table, params.net, params.aero.ball_radius)

    def half(self, position) -> str:
        """Whose half of the table ``position`` is over: x < 0 the robot's, else the human's."""
        return ROBOT if position[0] < 0.0 else HUMAN

    def on_playing_surface(self, position) -> bool:
        """Whether a TABLE contact with the ball's centre at ``position`` touches the playing
        surface or its top edges (module docstring: within one ball radius of the rectangle)."""
        reach = self.ball_radius + POSITION_SLACK
        return bool(
            position[2] >= -POSITION_SLACK
            and abs(position[0]) <= 0.5 * self.table.length + reach
            and abs(position[1]) <= 0.5 * self.table.width + reach
        )

    def behind_end_line(self, position, player: str) -> bool:
        """Whether ``position`` is beyond ``player``'s end line (x < -L/2 for the robot)."""
        sign = -1.0 if player == ROBOT else 1.0
        return sign * position[0] > 0.5 * self.table.length

    def on_net_assembly(self, position) -> bool:
        """Whether a NET contact with the ball's centre at ``position`` touches the net assembly
        from above the playing surface (else the ball went through or under it)."""
        half_span = 0.5 * self.table.width + self.net.overhang
        closest = np.array([0.0, np.clip(position[1], -half_span, half_span), np.clip(position[2], 0.0, self.net.height)])
        distance = float(np.linalg.norm(np.asarray(position, dtype=float) - closest))
        return bool(position[2] >= 0.0 and distance <= self.ball_radius + POSITION_SLACK)


@dataclasses.dataclass(frozen=True)
class PointDecision:
    """How a rally ended.

    winner: who scores (None for a let). reason: a short phrase. let: the rally is replayed
    (Law 2.9). shots: racket strikes in the rally up to the deciding event, the service included.
    law: the ITTF law applied, e.g. "2.10.1.3". event: the deciding contact (None when the toss
    alone decided).
    """

    winner: str | None
    reason: str
    let: bool = False
    shots: int = 0
    law: str = ""
    event: RallyEvent | None = None

    @property
    def loser(self) -> str | None:
        """Who committed the fault (None for a let)."""
        return None if self.winner is None else opponent(self.winner)


class _Phase(enum.Enum):
    TOSS = "toss"  # waiting for the service strike
    SERVICE_OWN_COURT = "service, to the server's court"
    SERVICE_OTHER_COURT = "service, to the receiver's court"
    RETURN = "a return, to the opponent's court"
    BOUNCED = "bounced on the court of the player to play"


class Umpire:
    """Judges one rally event by event (mutable; one instance per rally).

    Args:
        server: who serves (ROBOT or HUMAN).
        toss: the service toss, judged when given (module docstring).
        court: the table, net and ball geometry (default: the project's).

    ``observe(event)`` returns the decision once made (the same one for every later event),
    None while the ball is in play.
    """

    def __init__(self, server: str, toss: Toss | None = None, court: Court | None = None):
        self.server = require_player(server, "Umpire server")
        self.toss = toss
        self.court = Court() if court is None else court
        self.shots = 0
        self.decision: PointDecision | None = None
        self._phase = _Phase.TOSS
        self._striker = None  # who struck last
        self._service_touched_net = False
        self._last_time = -math.inf
        if toss is not None:
            self.decision = self._judge_toss(toss)

    @property
    def to_play(self) -> str | None:
        """Who must strike the ball next (the server before the service); None once decided."""
        if self.decision is not None:
            return None
        return self.server if self._striker is None else opponent(self._striker)

    @property
    def bounced(self) -> bool:
        """The ball has bounced correctly on the court of the player to play (``to_play``), who
        may strike it now; False once decided."""
        return self.decision is None and self._phase == _Phase.BOUNCED

    def observe(self, event: RallyEvent) -> PointDecision | None:
        """Takes the rally's next contact; returns the decision if the rally is over."""
        if event.time < self._last_time:
            raise ValueError(f"Umpire.observe: events must be in time order, got t = {event.time} s after t = {self._last_time} s")
        self._last_time = event.time
        if self.decision is None:
            if event.kind == ContactKind.RACKET:
                self.shots += 1
            self.decision = self._judge(event)
        return self.decision

    # --- the rules ------------------------------------------------------------------------

    def _point(self, winner: str, reason: str, law: str, event: RallyEvent | None) -> PointDecision:
        return PointDecision(winner, reason, False, self.shots, law, event)

    def _judge_toss(self, toss: Toss) -> PointDecision | None:
        receiver = opponent(self.server)
        if toss.tilt > MAX_TOSS_TILT:
            return self._point(receiver, f"toss not near vertical: {math.degrees(toss.tilt):.1f} deg from vertical", "2.6.2", None)
        if toss.apex_height < MIN_TOSS_RISE:
            return self._point(receiver, f"toss rose {toss.apex_height:.3f} m, less than {MIN_TOSS_RISE} m", "2.6.2", None)
        if not (toss.release_position[2] > 0.0 and self.court.behind_end_line(toss.release_position, self.server)):
            return self._point(receiver, "toss released over the table or below its surface", "2.6.4", None)
        return None

    def _judge(self, event: RallyEvent) -> PointDecision | None:
        if self._phase == _Phase.TOSS:
            return self._judge_before_service(event)
        if self._phase in (_Phase.SERVICE_OWN_COURT, _Phase.SERVICE_OTHER_COURT):
            return self._judge_service(event)
        return self._judge_rally(event)

    def _judge_before_service(self, event: RallyEvent) -> PointDecision | None:
        server, receiver = self.server, opponent(self.server)
        if event.kind != ContactKind.RACKET:
            return self._point(receiver, f"the tossed ball touched the {event.kind.name.lower()} before the service", "2.6.2", event)
        if event.striker == receiver:
            return self._point(server, "the receiver struck the ball before the service (volley)", "2.10.1.6", event)
        if self.toss is not None:
            if event.time < self.toss.release_time:
                raise ValueError(f"Umpire: the service strike at t = {event.time} s precedes the toss's release at t = {self.toss.release_time} s")
            if event.velocity_pre[2] >= 0.0:
                return self._point(receiver, "service struck while the ball was rising", "2.6.3", event)
            if not (event.position[2] > 0.0 and self.court.behind_end_line(event.position, server)):
                return self._point(receiver, "service struck over the table or below its surface", "2.6.4", event)
        self._striker = server
        self._phase = _Phase.SERVICE_OWN_COURT
        return None

    def _judge_service(self, event: RallyEvent) -> PointDecision | None:
        server, receiver = self.server, opponent(self.server)
        court = self.court
        own_court_touched = self._phase == _Phase.SERVICE_OTHER_COURT
        if event.kind == ContactKind.RACKET:
            if event.striker == server:
                return self._point(receiver, "the server struck the ball twice", "2.10.1.7", event)
            if self._service_touched_net:
                return PointDecision(None, "service touched the net, then obstructed by the receiver: let", True, self.shots, "2.9.1.1", event)
            return self._point(server, "the receiver struck the service before it bounced (volley)", "2.10.1.6", event)
        if event.kind == ContactKind.FLOOR:
            return self._point(receiver, "service missed the table", "2.6.3", event)
        if event.kind == ContactKind.NET:
            if not own_court_touched:
                return self._point(receiver, "service touched the net before the server's court", "2.6.3", event)
            if not court.on_net_assembly(event.position):
                return self._point(receiver, "service went through or under the net", "2.10.1.5", event)
            self._service_touched_net = True
            return None
        # TABLE
        if not court.on_playing_surface(event.position):
            return self._point(receiver, "service touched the side of the table", "2.6.3", event)
        half = court.half(event.position)
        if not own_court_touched:
            if half != server:
                return self._point(receiver, "service touched the receiver's court first", "2.6.3", event)
            self._phase = _Phase.SERVICE_OTHER_COURT
            return None
        if half == server:
            return self._point(receiver, "service touched the server's court twice", "2.6.3", event)
        if self._service_touched_net:
            return PointDecision(None, "service touched the net, otherwise good: let", True, self.shots, "2.9.1.1", event)
        self._phase = _Phase.BOUNCED  # a good service: the receiver is to play it
        return None

    def _judge_rally(self, event: RallyEvent) -> PointDecision | None:
        striker = self._striker
        to_play = opponent(striker)
        court = self.court
        bounced = self._phase == _Phase.BOUNCED
        if event.kind == ContactKind.RACKET:
            if event.striker == striker:
                return self._point(to_play, f"the {striker} struck the ball twice", "2.10.1.7", event)
            if not bounced:
                return self._point(striker, f"the {to_play} struck the ball before it bounced (volley)", "2.10.1.6", event)
            self._striker, self._phase = to_play, _Phase.RETURN
            return None
        if event.kind == ContactKind.NET:
            if not court.on_net_assembly(event.position):
                if bounced:  # a good return came back under the net untouched: not returned
                    return self._point(striker, f"the {to_play} did not return the ball (it went back under the net)", "2.10.1.2", event)
                return self._point(to_play, f"the {striker}'s shot went through or under the net", "2.10.1.5", event)
            return None  # the net assembly may be touched on a return, and after the bounce
        if not bounced:
            if event.kind == ContactKind.FLOOR:
                if court.half(event.position) == to_play:
                    return self._point(to_play, f"the {striker}'s return went beyond the {to_play}'s court", "2.10.1.4", event)
                return self._point(to_play, f"the {striker}'s return did not reach the {to_play}'s court", "2.7", event)
            if not court.on_playing_surface(event.position):
                return self._point(to_play, f"the {striker}'s return touched the side of the table", "2.7", event)
            if court.half(event.position) == striker:
                return self._point(to_play, f"the {striker}'s return touched the {striker}'s own court", "2.7", event)
            self._phase = _Phase.BOUNCED
            return None
        # The ball has bounced on the court of the player to play, who has not struck it.
        if event.kind == ContactKind.FLOOR:
            return self._point(striker, f"the {to_play} did not return the ball: it reached the floor", "2.10.1.3", event)
        if court.on_playing_surface(event.position) and court.half(event.position) == to_play:
            return self._point(striker, f"the {to_play} did not return the ball: second bounce", "2.10.1.3", event)
        return self._point(striker, f"the {to_play} did not return the ball: it touched the table again", "2.10.1.3", event)


def umpire_after(server: str, events: Iterable[RallyEvent], toss: Toss | None = None, court: Court | None = None) -> Umpire:
    """The Umpire of a rally served by ``server`` after it observed ``events`` (in time order; it
    stops at the decision)."""
    umpire = Umpire(server, toss, court)
    for event in events:
        if umpire.observe(event) is not None:
            break
    return umpire


def judge_rally(server: str, events: Iterable[RallyEvent], toss: Toss | None = None, court: Court | None = None) -> PointDecision | None:
    """The decision on a rally from its contacts in time order (module docstring), or None if the
    events run out while the ball is still in play."""
    return umpire_after(server, events, toss, court).decision
