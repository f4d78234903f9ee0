"""The robot's serve at the ball level: the toss, the strike found by a genetic algorithm, the
serve's flight judged by the umpire, and its fitness (paper, Methods *Serve design*).

The paper's serve has three parts: a near-vertical toss from the cup on the end effector (Law
2.6.2: the ball rises at least 16 cm), a strike of the falling ball whose racket state is found
offline by a genetic algorithm (``analysis.serve_search``, PyGAD with the authors' settings), and
a library of the serves that pass on the real robot. This module is the first two at the ball
level: the toss is a ball released from a state (``TossState``), the strike is the racket's state
at the hit (``Strike``: pose and velocity), the contact is the paper's racket model (eqs (7)-(8),
``physics.contact.racket_contact``, with the residual correction that ``physics.racket``
selects) and the flight is the project's propagator (``physics.propagate.simulate``: eq. (1),
the table eqs (2)-(6), net and floor). The robot executes the toss and the strike in
``control.serve_execution``, and ``evaluation.serves`` keeps the serves that it executes reliably
(the library).

Everything is in the world frame of DESIGN.md (origin at the centre of the playing surface, x
towards the human, z up; the robot serves from x < 0), SI units, radians. Times are seconds since
the toss's release. Every function that simulates takes a batch of strikes: a whole GA population
is one call of ``simulate``.

The gene mapping (``strike_from_genes``; nine genes in [0, 1], each mapped linearly onto its
range, ``GENE_RANGES``):

1. strike time, from ``STRIKE_AFTER_APEX`` = 20 ms after the toss's apex (the ball then falls at
   about 0.2 m/s: Law 2.6.3, struck while falling) to the time the ball's centre has fallen to
   ``STRIKE_HEIGHT_MIN`` = 0.04 m above the playing surface (Law 2.6.4: above the surface and
   behind the end line until struck; the toss is 0.18 m behind it);
2. the blade normal's elevation above the horizontal, -60 to +70 degrees (closed face for topspin,
   open face for backspin);
3. its azimuth from +x towards +y, -30 to +30 degrees: with 2, n = (cos e cos a, cos e sin a,
   sin e) points the ball towards the receiver;
4. the racket's speed along the normal, 1 to 8 m/s;
5. the brushing speed along the blade's upward tangent u (world z projected onto the blade),
   -6 to +6 m/s: > 0 brushes up (topspin), < 0 down (backspin);
6. the brushing speed along the blade's side tangent u x n (+y for a normal along +x),
   -6 to +6 m/s: sidespin (> 0 gives spin about -u, clockwise seen from above);
7-8. the contact point on the blade in the racket frame's x and y (R: x from the handle to the
   blade's tip, z the forehand normal), -0.05 to +0.05 m each (the corners lie 0.071 m from the
   centre, inside the blade's 0.075 m radius);
9. the blade's roll about its normal, -pi to pi: the angle from u to the racket frame's x (0:
   the tip up, the handle down).

Genes 1-6 fix the ball's path; 7-9 complete the racket's pose (the position and orientation the
robot must reach: the contact point and the normal give five of its six degrees of freedom, the
roll the sixth). With the paper's isotropic model and a racket that translates they do not change
the ball, but they are the residual correction's inputs (the contact offset and the contact
frame's in-plane axes) and they decide whether the robot can make the strike, which the later
stages judge. The fastest racket is sqrt(8^2 + 6^2 + 6^2) = 11.7 m/s, within the robot's serve
speeds (notes.md: up to about 20 m/s in rallies).

Legality (``ServeOutcome.legal``): the umpire (``play.umpire.judge_rally``, with the toss) has
given no decision once the ball has touched the server's court and then the receiver's court,
which it has done within the horizon; a net touch (a let) is not legal for the library.

The fitness (``serve_fitness``):

- an illegal serve scores in (0, 0.1), graded by how far it got: a stage s (0: the racket missed
  the ball, or the toss or strike broke Law 2.6; 1: struck, but the first contact is not the
  server's court; 2: the server's court first, but then not the receiver's court; 3: a let) and a
  distance g >= 0 to the next stage (0: the ball's approach speed missing for an impact, m/s; 1:
  the distance of the point where the ball first comes down to the table's height from the
  server's court, m; 2: the distance of the second such point from the receiver's court plus the
  ball's shortfall below the net cord, m; 3: the shortfall, m), as
  0.1 (s + 0.05 + 0.9 exp(-g / g_s)) / 4 with g_s = 1 m/s, 0.5 m, 0.5 m, 0.02 m. Every later
  stage scores above every earlier one, and within a stage a serve nearer the next scores more;
- a legal serve scores 1 + sum_j w_j f_j, each term f_j in [0, 1] (``ServeWeights``): the ball's
  speed at its second bounce (fast: |v| / 15 m/s; slow: 1 - that), its spin there relative to its
  horizontal direction of travel d (topspin w.(z x d), backspin the opposite, sidespin |w_z|,
  each over 300 rad/s), its placement (1 - the bounce's distance from a target point / 1 m), the
  net clearance c of the ball's bottom over the cord (low, with a margin m = 3 cm for the real
  robot's execution errors: c / m below the margin, 1 - (c - m) / 0.3 m above it; without the
  margin the search skims the cord by a millimetre) and whether the ball would bounce twice on the
  receiver's court (a "short" serve, the receiver must play it over the table). Every term is
  clipped to [0, 1].
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ace_drake.physics.contact import blade_standoff, racket_contact
from ace_drake.physics.flight import POSITION, SPIN, VELOCITY, rk4_step
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind, simulate
from ace_drake.physics.racket_inverse import contact_frame
from ace_drake.physics.racket_residual import residual_model
from ace_drake.play.scoring import HUMAN, ROBOT
from ace_drake.play.umpire import Court, PointDecision, RallyEvent, Toss, Umpire

SERVE_GENES = 9
STRIKE_AFTER_APEX = 0.02  # s, the earliest strike after the toss's apex (the ball is falling)
STRIKE_HEIGHT_MIN = 0.04  # m, the lowest ball centre above the playing surface at the strike
# The ranges that genes 2-9 map onto, linearly from gene 0 to gene 1 (gene 1, the strike time,
# maps onto the toss's strike window, ``strike_window``).
GENE_RANGES = {
    "elevation": (math.radians(-60.0), math.radians(70.0)),  # rad, blade normal above horizontal
    "azimuth": (math.radians(-30.0), math.radians(30.0)),  # rad, from +x towards +y
    "normal_speed": (1.0, 8.0),  # m/s, racket velocity along the normal
    "brush_up": (-6.0, 6.0),  # m/s, along the blade's upward tangent u (+: topspin)
    "brush_side": (-6.0, 6.0),  # m/s, along u x n (sidespin)
    "contact_x": (-0.05, 0.05),  # m, contact point in R's x (handle to tip)
    "contact_y": (-0.05, 0.05),  # m, contact point in R's y
    "roll": (-math.pi, math.pi),  # rad, from u to R's x about the normal
}
GENE_NAMES = ("strike_time", *GENE_RANGES)
HORIZON = 2.0  # s of flight after the strike
DT = 1e-3  # s, the propagator's step

# Fitness of illegal serves: stages and the distance scale of each (module docstring).
ILLEGAL_STAGES = 4
STAGE_MISS, STAGE_OWN_COURT, STAGE_OTHER_COURT, STAGE_LET, STAGE_LEGAL = range(5)
STAGE_GAP_SCALES = (1.0, 0.5, 0.5, 0.02)  # m/s, m, m, m
ILLEGAL_FITNESS_MAX = 0.1


@dataclasses.dataclass(frozen=True)
class TossState:
    """The ball as it leaves the cup (Law 2.6.2).

    position (3,): m; default 0.18 m behind the robot's end line (x = -1.37 m), 0.3 m to the
    robot's right of the centre line, 0.10 m above the playing surface. velocity (3,): m/s;
    default 2.0 m/s straight up (the ball rises about 0.20 m). spin (3,): rad/s; default none.
    """

    position: np.ndarray = dataclasses.field(default_factory=lambda: np.array([-1.55, -0.3, 0.10]))
    velocity: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 2.0]))
    spin: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        for name in ("position", "velocity", "spin"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"TossState.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if self.velocity[2] <= 0.0:
            raise ValueError(f"TossState.velocity must rise (v_z > 0 m/s), got {self.velocity}")

    @property
    def state(self) -> np.ndarray:
        """The ball's state [p, v, w] (9,) at the release."""
        return np.concatenate([self.position, self.velocity, self.spin])


def toss_ball(toss: TossState, physics: BallPhysicsParams, t) -> np.ndarray:
    """The tossed ball's states (..., 9) at times t (..., s since the release; t >= 0) of its free
    flight (eq. (1), no contacts): ``simulate``'s RK4 grid of ``DT`` to the step before each t,
    then one RK4 step to t. Each time's state is the same in any batch."""
    t = np.asarray(t, dtype=float)
    if np.any(t < 0.0) or not np.all(np.isfinite(t)):
        raise ValueError(f"toss_ball: times must be finite and >= 0 s, got {t}")
    flat = t.reshape(-1)
    duration = float(flat.max(initial=0.0))
    grid = simulate(toss.state, physics, duration + DT, dt=DT, kinds=())
    index = np.minimum(np.floor(flat / DT).astype(int), len(grid.times) - 1)
    start = grid.states[index, 0]
    step = flat - grid.times[index]
    states = start.copy()
    moving = step > 0.0
    if np.any(moving):
        states[moving] = rk4_step(start[moving], step[moving], physics.aero)
    return states.reshape(t.shape + (9,))


def toss_apex(toss: TossState, physics: BallPhysicsParams) -> tuple[float, float]:
    """(t_apex s, z_apex m): when and how high the tossed ball peaks (v_z = 0, linear in time
    between the grid's samples)."""
    rise = toss.velocity[2] / physics.aero.gravity
    grid = simulate(toss.state, physics, 2.0 * rise + 0.1, dt=DT, kinds=())
    v_z = grid.states[:, 0, 5]
    k = int(np.flatnonzero(v_z <= 0.0)[0])
    t_apex = grid.times[k - 1] + DT * v_z[k - 1] / (v_z[k - 1] - v_z[k])
    return float(t_apex), float(toss_ball(toss, physics, t_apex)[2])


def umpire_toss(toss: TossState, physics: BallPhysicsParams) -> Toss:
    """The umpire's ``Toss`` for ``toss`` (released at t = 0; its rise from the simulated flight)."""
    _, z_apex = toss_apex(toss, physics)
    return Toss(0.0, toss.position, toss.velocity, z_apex - toss.position[2])


def strike_window(toss: TossState, physics: BallPhysicsParams) -> tuple[float, float]:
    """(earliest, latest) strike times, s: ``STRIKE_AFTER_APEX`` after the apex, and when the
    falling ball's centre reaches ``STRIKE_HEIGHT_MIN`` (linear between the grid's samples).
    Raises ValueError if the toss peaks too low to leave a window."""
    t_apex, z_apex = toss_apex(toss, physics)
    if z_apex <= STRIKE_HEIGHT_MIN + 0.01:
        raise ValueError(f"strike_window: the toss peaks at z = {z_apex:.3f} m, not above the lowest strike height {STRIKE_HEIGHT_MIN} m")
    fall = math.sqrt(2.0 * (z_apex - STRIKE_HEIGHT_MIN) / physics.aero.gravity)
    grid = simulate(toss.state, physics, t_apex + 2.0 * fall + 0.1, dt=DT, kinds=())
    z = grid.states[:, 0, 2]
    k = int(np.flatnonzero((grid.times > t_apex) & (z <= STRIKE_HEIGHT_MIN))[0])
    t_low = grid.times[k - 1] + DT * (z[k - 1] - STRIKE_HEIGHT_MIN) / (z[k - 1] - z[k])
    return t_apex + STRIKE_AFTER_APEX, float(t_low)


@dataclasses.dataclass(frozen=True)
class Strike:
    """The racket's state at the service strike, for one strike or a batch (leading dims ...).

    time (...,): s since the toss's release. p_WR (..., 3): the blade centre, m. R_WR (..., 3, 3):
    the racket frame's orientation (z the forehand normal, x from the handle to the tip). v_WR
    (..., 3): the racket's velocity, m/s (it translates: no angular velocity at the hit).
    """

    time: np.ndarray
    p_WR: np.ndarray
    R_WR: np.ndarray
    v_WR: np.ndarray

    def __post_init__(self) -> None:
        time = np.asarray(self.time, dtype=float)
        for name, tail in (("time", ()), ("p_WR", (3,)), ("R_WR", (3, 3)), ("v_WR", (3,))):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != time.shape + tail:
                raise ValueError(f"Strike.{name} must have shape {time.shape + tail}, got {value.shape}")
            object.__setattr__(self, name, value)

    @property
    def shape(self) -> tuple[int, ...]:
        """The batch's shape (() for one strike)."""
        return self.time.shape

    @property
    def normal(self) -> np.ndarray:
        """The blade's forehand normal (..., 3)."""
        return self.R_WR[..., :, 2]

    def __getitem__(self, index) -> Strike:
        return Strike(self.time[index], self.p_WR[index], self.R_WR[index], self.v_WR[index])

    def __len__(self) -> int:
        return len(self.time)


def gene_values(genes) -> dict[str, np.ndarray]:
    """The physical values (..., each) of genes 2-9 (..., 9) in [0, 1]: ``GENE_RANGES``' units."""
    genes = _check_genes(genes)
    return {name: low + genes[..., i + 1] * (high - low) for i, (name, (low, high)) in enumerate(GENE_RANGES.items())}


def strike_from_genes(genes, toss: TossState, physics: BallPhysicsParams) -> Strike:
    """The strike (module docstring's gene mapping) of genes (..., 9) in [0, 1]: the racket meets
    the tossed ball at the strike time, the ball touching the forehand face at the contact point."""
    genes = _check_genes(genes)
    t_first, t_last = strike_window(toss, physics)
    time = t_first + genes[..., 0] * (t_last - t_first)
    values = gene_values(genes)
    elevation, azimuth = values["elevation"], values["azimuth"]
    normal = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1)
    R_W0 = contact_frame(normal)  # x: the blade's upward tangent u, y: n x u, z: n
    up, across = R_W0[..., :, 0], R_W0[..., :, 1]
    roll = values["roll"][..., None]
    x_axis = np.cos(roll) * up + np.sin(roll) * across
    R_WR = np.stack([x_axis, np.cross(normal, x_axis), normal], axis=-1)
    v_WR = (values["normal_speed"][..., None] * normal + values["brush_up"][..., None] * up
            - values["brush_side"][..., None] * across)  # u x n = -(n x u)
    p_WB = toss_ball(toss, physics, time)[..., POSITION]
    offset = np.stack([values["contact_x"], values["contact_y"]], axis=-1)
    p_WR = (p_WB - blade_standoff(physics.aero.ball_radius, physics.racket) * normal
            - offset[..., :1] * R_WR[..., :, 0] - offset[..., 1:] * R_WR[..., :, 1])
    return Strike(time, p_WR, R_WR, v_WR)


def _check_genes(genes) -> np.ndarray:
    genes = np.asarray(genes, dtype=float)
    if genes.shape[-1:] != (SERVE_GENES,):
        raise ValueError(f"serve genes must have shape (..., {SERVE_GENES}), got {genes.shape}")
    if not np.all((genes >= 0.0) & (genes <= 1.0)):
        raise ValueError(f"serve genes must lie in [0, 1], got {genes}")
    return genes


@dataclasses.dataclass(frozen=True)
class ServeOutcome:
    """One simulated serve (``simulate_serve``); times in s since the toss's release.

    strike: the racket state. impact: whether the racket met the ball (else the ball fell on).
    ball_pre, ball_post (9,): the ball just before and after the strike. contacts: the ball's
    table, net and floor contacts after the strike, up to the horizon or the floor. events: the
    umpire's view (the robot's RACKET strike if any, then ``contacts``). service_decision: the
    umpire's decision by the second table contact (None: still in play). decision: its decision on
    all of ``events`` (for a legal serve, how the point ends if the receiver does not play it).
    legal: the module docstring's definition. reason: the umpire's reason when illegal, else
    "good service". second_bounce: the second table contact (the first on the receiver's court
    for a legal serve), or None. third_contact: the contact after it, or None. net_clearance: the
    ball's bottom over the net cord where it first crosses the net's plane towards the receiver,
    m (negative: it touched the net; nan: it never reached it). stage, gap: how far an illegal
    serve got and its distance to the next stage (module docstring; stage 4 and gap 0 if legal).
    """

    strike: Strike
    impact: bool
    ball_pre: np.ndarray
    ball_post: np.ndarray
    contacts: list[ContactEvent]
    events: list[RallyEvent]
    service_decision: PointDecision | None
    decision: PointDecision | None
    legal: bool
    reason: str
    second_bounce: ContactEvent | None
    third_contact: ContactEvent | None
    net_clearance: float
    stage: int
    gap: float

    @property
    def short(self) -> bool:
        """Whether the ball would bounce twice on the receiver's court (its third contact is the
        receiver's table): the receiver must play it over the table."""
        contact = self.third_contact
        return bool(contact is not None and contact.kind == ContactKind.TABLE and contact.state_pre[0] >= 0.0)

    @property
    def bounce_speed(self) -> float:
        """The ball's speed just before its second bounce, m/s (nan without one)."""
        return float(np.linalg.norm(self.second_bounce.state_pre[VELOCITY])) if self.second_bounce else math.nan

    @property
    def bounce_spin(self) -> np.ndarray:
        """(topspin, sidespin) rad/s just before the second bounce (``spin_components``; nan)."""
        return spin_components(self.second_bounce.state_pre) if self.second_bounce else np.full(2, math.nan)

    @property
    def bounce_position(self) -> np.ndarray:
        """(x, y) of the second bounce, m (nan without one)."""
        return self.second_bounce.state_pre[:2].copy() if self.second_bounce else np.full(2, math.nan)


def spin_components(state) -> np.ndarray:
    """(topspin, sidespin) (..., 2) rad/s of ball states (..., 9): the spin about z x d, with d
    the horizontal direction of travel (> 0 topspin, < 0 backspin), and about z (sidespin)."""
    state = np.asarray(state, dtype=float)
    v, w = state[..., VELOCITY], state[..., SPIN]
    horizontal = np.hypot(v[..., 0], v[..., 1])
    d = np.stack([v[..., 0], v[..., 1]], axis=-1) / np.maximum(horizontal, 1e-12)[..., None]
    topspin = w[..., 1] * d[..., 0] - w[..., 0] * d[..., 1]  # w . (z x d), z x d = (-d_y, d_x, 0)
    return np.stack([topspin, w[..., 2]], axis=-1)


def simulate_serves(strikes: Strike, toss: TossState, physics: BallPhysicsParams, horizon: float = HORIZON) -> list[ServeOutcome]:
    """The serves of a batch of strikes (N,), one ``simulate`` call for all: the tossed ball at
    each strike time, the racket contact (eqs (7)-(8), ``racket_contact``: an impact only if the
    ball approaches the blade), then ``horizon`` s of flight with table, net and floor contacts
    (stopping at the floor), judged by the umpire with the toss."""
    if len(strikes.shape) != 1:
        raise ValueError(f"simulate_serves: strikes must be a batch of shape (N,), got {strikes.shape}")
    radius = physics.aero.ball_radius
    ball_pre = toss_ball(toss, physics, strikes.time)
    ball_post, impact = racket_contact(
        ball_pre, strikes.p_WR, strikes.R_WR, np.zeros(3), strikes.v_WR, physics.racket, radius, residual_model(physics.racket),
    )  # paper eqs (7)-(8)
    flight = simulate(ball_post, physics, horizon, dt=DT, stop_on=(ContactKind.FLOOR,))
    toss_for_umpire = umpire_toss(toss, physics)
    court = Court.from_physics(physics)
    outcomes = []
    for i in range(len(strikes)):
        t0 = float(strikes.time[i])
        contacts = [ContactEvent(e.kind, e.time + t0, e.state_pre, e.state_post) for e in flight.events[i]]
        outcomes.append(_judge(strikes[i], bool(impact[i]), ball_pre[i], ball_post[i], contacts,
                               flight.times + t0, flight.states[:, i], toss_for_umpire, court, physics))
    return outcomes


def simulate_serve(strike: Strike, toss: TossState, physics: BallPhysicsParams, horizon: float = HORIZON) -> ServeOutcome:
    """The serve of one strike (``simulate_serves`` with a batch of one)."""
    if strike.shape != ():
        raise ValueError(f"simulate_serve: one strike expected, got a batch {strike.shape}; use simulate_serves")
    batch = Strike(strike.time[None], strike.p_WR[None], strike.R_WR[None], strike.v_WR[None])
    return simulate_serves(batch, toss, physics, horizon)[0]


def _judge(strike, impact, ball_pre, ball_post, contacts, times, states, toss, court, physics) -> ServeOutcome:
    """The umpire's decisions, the second bounce and third contact, the net clearance and the
    legality stage of one serve (``simulate_serves``)."""
    events = [RallyEvent(ContactKind.RACKET, float(strike.time), ball_pre[POSITION], ball_pre[VELOCITY], ROBOT)] if impact else []
    events += [RallyEvent.from_contact(c) for c in contacts]
    tables = [i for i, c in enumerate(contacts) if c.kind == ContactKind.TABLE]
    second = contacts[tables[1]] if len(tables) > 1 else None
    third = contacts[tables[1] + 1] if len(tables) > 1 and tables[1] + 1 < len(contacts) else None
    # The service: the umpire's decision by the second table contact; then on to the third.
    umpire = Umpire(ROBOT, toss, court)
    service_end = (tables[1] + 1 + int(impact)) if second is not None else len(events)
    for event in events[:service_end]:
        if umpire.observe(event) is not None:
            break
    service_decision = umpire.decision
    for event in events[service_end:]:
        if umpire.observe(event) is not None:
            break
    # By the second table contact the umpire has faulted anything but the server's court then the
    # receiver's, and called a net touch a let: no decision then is a good service.
    legal = service_decision is None and second is not None
    clearance = _net_clearance(contacts, times, states, physics)
    if legal:
        stage, gap, reason = STAGE_LEGAL, 0.0, "good service"
    else:
        reason = service_decision.reason if service_decision is not None else "the service did not reach the receiver's court within the horizon"
        stage, gap = _illegal_stage(impact, ball_pre, strike, contacts, times, states, service_decision, clearance, court, physics)
    return ServeOutcome(strike, impact, ball_pre, ball_post, contacts, events, service_decision, umpire.decision,
                        legal, reason, second, third, clearance, stage, gap)


def _net_clearance(contacts, times, states, physics) -> float:
    """The ball's bottom over the net cord (m) where it first reaches the net's plane moving
    towards the receiver: at a NET contact z - r - h, else where the sampled flight crosses x = 0
    (linear between samples); nan if neither happens."""
    radius, height = physics.aero.ball_radius, physics.net.height
    x = states[:, 0]
    crossing = np.flatnonzero((x[:-1] < 0.0) & (x[1:] >= 0.0))
    t_cross = times[crossing[0]] if crossing.size else math.inf
    nets = [c for c in contacts if c.kind == ContactKind.NET and c.time <= t_cross + DT]
    if nets:
        return float(nets[0].state_pre[2] - radius - height)
    if not crossing.size:
        return math.nan
    k = crossing[0]
    z = states[k, 2] + (states[k + 1, 2] - states[k, 2]) * (-x[k] / (x[k + 1] - x[k]))
    return float(z - radius - height)


def _landings(contacts, times, states, physics) -> list[np.ndarray]:
    """(x, y) of each time the ball comes down to the table's height (centre one radius above the
    surface plane) after the strike, in order: its TABLE contacts and, off the table, the sampled
    flight's downward crossings of that height (linear between samples)."""
    radius, table = physics.aero.ball_radius, physics.table
    found = [(c.time, c.state_pre[:2].copy()) for c in contacts if c.kind == ContactKind.TABLE]
    z = states[:, 2]
    for k in np.flatnonzero((z[:-1] > radius) & (z[1:] <= radius)):
        point = states[k, :2] + (states[k + 1, :2] - states[k, :2]) * ((z[k] - radius) / (z[k] - z[k + 1]))
        if abs(point[0]) > 0.5 * table.length or abs(point[1]) > 0.5 * table.width:
            found.append((times[k], point))
    return [point for _, point in sorted(found, key=lambda item: item[0])]


def _distance_to_half(point, half: str, physics) -> float:
    """Horizontal distance (m) from ``point`` (x, y) to a player's court (the half-table)."""
    table = physics.table
    x_low, x_high = (-0.5 * table.length, 0.0) if half == ROBOT else (0.0, 0.5 * table.length)
    dx = max(x_low - point[0], 0.0, point[0] - x_high)
    dy = max(abs(point[1]) - 0.5 * table.width, 0.0)
    return float(math.hypot(dx, dy))


def _illegal_stage(impact, ball_pre, strike, contacts, times, states, decision, clearance, court, physics) -> tuple[int, float]:
    """(stage, gap) of an illegal serve (module docstring)."""
    if not impact:
        # The ball's speed towards the blade that an impact needed: (v_ball - v_racket) . n < 0.
        return STAGE_MISS, float(np.dot(ball_pre[VELOCITY] - strike.v_WR, strike.normal))
    if decision is not None and (decision.event is None or decision.event.kind == ContactKind.RACKET):
        return STAGE_MISS, math.inf  # a toss or strike fault (Laws 2.6.2-2.6.4): not graded
    landings = _landings(contacts, times, states, physics)
    first = contacts[0] if contacts else None
    on_own_court = (first is not None and first.kind == ContactKind.TABLE and court.half(first.state_pre[POSITION]) == ROBOT
                    and court.on_playing_surface(first.state_pre[POSITION]))
    if not on_own_court:
        point = landings[0] if landings else states[-1, :2]
        return STAGE_OWN_COURT, _distance_to_half(point, ROBOT, physics)
    if decision is not None and decision.let:
        return STAGE_LET, max(-clearance, 0.0)
    point = landings[1] if len(landings) > 1 else states[-1, :2]
    shortfall = max(-clearance, 0.0) if np.isfinite(clearance) else 0.0
    return STAGE_OTHER_COURT, _distance_to_half(point, HUMAN, physics) + shortfall


@dataclasses.dataclass(frozen=True)
class ServeWeights:
    """The weights w_j >= 0 of a legal serve's fitness terms (module docstring), its target and
    the terms' scales.

    fast, slow: the ball's speed at the second bounce, |v| / speed_scale and 1 - that.
    topspin, backspin, sidespin: its spin there (``spin_components``) over spin_scale.
    placement: 1 - the second bounce's distance from ``target`` (x, y; m) / placement_scale.
    low_net: the net clearance c over ``net_margin`` m below it, 1 - (c - net_margin) /
    clearance_scale above it (low, but not skimming the cord). short: 1 if the ball would bounce
    twice on the receiver's court (``ServeOutcome.short``).
    """

    fast: float = 0.0
    slow: float = 0.0
    topspin: float = 0.0
    backspin: float = 0.0
    sidespin: float = 0.0
    placement: float = 0.0
    target: tuple[float, float] = (1.0, 0.0)  # m, on the receiver's court
    low_net: float = 0.0
    short: float = 0.0
    speed_scale: float = 15.0  # m/s
    spin_scale: float = 300.0  # rad/s
    placement_scale: float = 1.0  # m
    clearance_scale: float = 0.3  # m
    net_margin: float = 0.03  # m, the best net clearance

    def __post_init__(self) -> None:
        for field in ("fast", "slow", "topspin", "backspin", "sidespin", "placement", "low_net", "short"):
            value = getattr(self, field)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"ServeWeights.{field} must be a finite weight >= 0, got {value!r}")
        for field in ("speed_scale", "spin_scale", "placement_scale", "clearance_scale", "net_margin"):
            if not getattr(self, field) > 0.0:
                raise ValueError(f"ServeWeights.{field} must be > 0, got {getattr(self, field)!r}")
        if len(self.target) != 2:
            raise ValueError(f"ServeWeights.target must be (x, y) in m, got {self.target!r}")


# The serve kinds: the receiver's court is x in [0, 1.37] m, |y| <= 0.7625 m.
SERVE_KINDS = {
    # Slow, heavy backspin, bouncing twice on the receiver's court. Its target and net margin
    # leave room for execution errors: at (0.35 m, 3 cm), of 45 searches, none of the 9 serves the
    # robot made failed less than 5% of 100 noisy repeats on the diagram (lets, and second
    # bounces on the server's own court); docs/play.md, *Serve library*.
    "short_backspin": ServeWeights(slow=0.5, backspin=1.0, placement=1.0, target=(0.5, 0.0), low_net=0.5, short=0.5, net_margin=0.06),
    # Topspin to the receiver's end line, fairly fast, low over the net.
    "long_topspin": ServeWeights(fast=0.5, topspin=1.0, placement=1.0, target=(1.15, 0.0), low_net=0.5),
    # Sidespin to a deep corner (the receiver's +y side).
    "long_sidespin": ServeWeights(fast=0.3, sidespin=1.0, placement=1.0, target=(1.15, 0.5), low_net=0.5),
    # As fast as possible to the other deep corner, skimming the net.
    "fast_long": ServeWeights(fast=1.5, placement=1.0, target=(1.2, -0.55), low_net=1.0),
    # Heavy backspin, deep to the receiver's backhand side (+y).
    "long_backspin": ServeWeights(fast=0.3, backspin=1.0, placement=1.0, target=(1.1, 0.3), low_net=0.5),
}


def serve_weights(kind: str) -> ServeWeights:
    """The preset weights of a serve kind (``SERVE_KINDS``); ValueError naming the kinds."""
    if kind not in SERVE_KINDS:
        raise ValueError(f"unknown serve kind {kind!r}; the kinds are {', '.join(SERVE_KINDS)}")
    return SERVE_KINDS[kind]


def serve_terms(outcome: ServeOutcome, weights: ServeWeights) -> dict[str, float]:
    """The legal-serve fitness terms f_j in [0, 1] (module docstring) of a legal outcome."""
    if not outcome.legal:
        raise ValueError(f"serve_terms: the serve is not legal ({outcome.reason})")
    speed = outcome.bounce_speed / weights.speed_scale
    topspin, sidespin = outcome.bounce_spin / weights.spin_scale
    distance = float(np.linalg.norm(outcome.bounce_position - np.asarray(weights.target, dtype=float)))
    clearance, margin = outcome.net_clearance, weights.net_margin
    terms = {
        "fast": speed,
        "slow": 1.0 - speed,
        "topspin": topspin,
        "backspin": -topspin,
        "sidespin": abs(sidespin),
        "placement": 1.0 - distance / weights.placement_scale,
        "low_net": clearance / margin if clearance < margin else 1.0 - (clearance - margin) / weights.clearance_scale,
        "short": float(outcome.short),
    }
    return {name: float(np.clip(np.nan_to_num(value), 0.0, 1.0)) for name, value in terms.items()}


def serve_fitness(outcome: ServeOutcome, weights: ServeWeights) -> float:
    """The serve's fitness (module docstring): in (0, 0.1) if illegal, graded by its stage and
    gap; 1 + sum_j w_j f_j if legal."""
    if not outcome.legal:
        scale = STAGE_GAP_SCALES[outcome.stage]
        closeness = math.exp(-max(outcome.gap, 0.0) / scale) if np.isfinite(outcome.gap) else 0.0
        return ILLEGAL_FITNESS_MAX * (outcome.stage + 0.05 + 0.9 * closeness) / ILLEGAL_STAGES
    terms = serve_terms(outcome, weights)
    return 1.0 + sum(getattr(weights, name) * value for name, value in terms.items())


def evaluate_genes(genes, toss: TossState, physics: BallPhysicsParams, weights: ServeWeights) -> tuple[np.ndarray, list[ServeOutcome]]:
    """Fitness (N,) and outcomes of a population of genes (N, 9): one batched simulation."""
    genes = np.atleast_2d(_check_genes(genes))
    outcomes = simulate_serves(strike_from_genes(genes, toss, physics), toss, physics)
    return np.array([serve_fitness(o, weights) for o in outcomes]), outcomes
