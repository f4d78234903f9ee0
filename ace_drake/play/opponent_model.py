"""A simulated human opponent that plays back, fitted to the recorded matches.

The data (``human_responses``). In a match-data file (``match_data``) every ball the robot sent
to the human appears as the robot's shot (``shot_p1``) followed by a bounce on the human's half
(``bounce_p2``), with only net touches in between and, for the robot's serve (the rally's first
event), a bounce on the robot's half (one serve of the elite file has none recorded; it counts).
The recorded state just after that bounce is the *incoming* ball. What followed is the human's *response*:

- a return: the next event is the human's shot (``shot_p2``); its recorded post-hit state
  [p, v, w] (9,) and the time from the bounce to the hit (the hit delay, s) are kept, and whether
  that return then bounced on the robot's half (``bounce_p1``, possibly after a net touch) or not
  (it went out or into the net: the rally's recording ends);
- a miss: the rally ends after the bounce, or the ball bounces on the human's half again.

Any other next event (none occur in the elite file) leaves the ball out. The human's serves are the
first events of the rallies the human served (a ``shot_p2`` first). In
../shared/data/ace_match_events_elite.csv there are 536 incoming balls (121 of them the robot's
serves, 14 via the net), 522 returns (393 of which bounced on the robot's half) and 14 misses; the
elite players return 97.4% of what reaches them.

The model (``OpponentModel``).

- Return probability: a k-nearest-neighbour estimate over the standardised incoming-ball features
  FEATURES (the bounce point x, y; the velocity after the bounce; topspin w_y and sidespin w_z),
  each divided by its standard deviation over the fit data. Of the k nearest recorded incoming
  balls, r were returned; the estimate is smoothed toward the fit data's overall return rate
  p0 = (returns + 1) / (incoming + 2) (Laplace's rule) with ``prior_weight`` m pseudo-balls:
  p = (r + m p0) / (k + m).
- Reaction limit: a ball whose speed after the bounce exceeds the fastest the fitted players ever
  returned (``max_return_speed``, strictly above) is never returned: p = 0. Nothing extrapolates
  the human's reach beyond what was recorded.
- Returns: given that the human returns, the post-hit state is a recorded return of one of the k
  nearest *returned* incoming balls, chosen uniformly, plus independent Gaussian jitter per
  component (``OpponentParams``: 2 cm, 0.15 m/s, 10 rad/s; about the perception noise of the
  recording, so that repeated draws are not bit-identical replays). The post-hit position is where
  *that* human hit *that* ball; it is kept as recorded (a match runner moves the ball to the
  human's hit point), and the neighbour's hit delay comes with it, so that ``ball_at_hit`` gives
  where the actual incoming ball is at that time.
- Serves: a recorded serve of the fitted players, chosen uniformly, with the same jitter.

Recorded returns include the human's errors (about a quarter of them did not land on the robot's
half), so a sampled return may go out: the human's error rate comes with the data.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import spatial, stats

from ace_drake.config import InputError
from ace_drake.match_data import MatchDataError, MatchEvent, load_match_events
from ace_drake.physics.flight import SPIN, VELOCITY
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind, simulate

# Incoming-ball features of the kNN, as columns of the (9,) state after the bounce: where the ball
# bounced (x depth, y placement), its velocity, its topspin (w_y: a ball travelling towards +x with
# topspin turns about +y) and sidespin (w_z).
FEATURES = ("x", "y", "v_x", "v_y", "v_z", "w_y", "w_z")
FEATURE_COLUMNS = np.array([0, 1, 3, 4, 5, 7, 8])
LANDING_FLIGHT_DURATION = 2.0  # s simulated for a return to reach its first table or floor contact
WILSON_Z = 1.959963984540054  # two-sided 95% normal quantile


class OpponentModelError(InputError):
    """An opponent model cannot be fitted or used as asked; the message says what is missing."""


@dataclasses.dataclass(frozen=True)
class OpponentParams:
    """Hyper-parameters of ``OpponentModel``.

    k: neighbours of the kNN estimates (20: about a fifth of one player's ~100 recorded incoming
        balls; with ~3 misses per player a small k would give estimates of 0 or 1 from noise).
    prior_weight: m, pseudo-balls at the overall return rate added to the k neighbours.
    position_jitter (m), velocity_jitter (m/s), spin_jitter (rad/s): standard deviations of the
        Gaussian noise added to each component of a sampled return or serve.
    """

    k: int = 20
    prior_weight: float = 5.0
    position_jitter: float = 0.02
    velocity_jitter: float = 0.15
    spin_jitter: float = 10.0

    def __post_init__(self):
        if self.k < 1:
            raise OpponentModelError(f"OpponentParams.k must be >= 1, got {self.k}")
        for name in ("prior_weight", "position_jitter", "velocity_jitter", "spin_jitter"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise OpponentModelError(f"OpponentParams.{name} must be a finite number >= 0, got {value}")

    @property
    def jitter(self) -> np.ndarray:
        """(9,) standard deviations of the noise on [p (m), v (m/s), w (rad/s)]."""
        return np.repeat([self.position_jitter, self.velocity_jitter, self.spin_jitter], 3)


@dataclasses.dataclass(frozen=True)
class HumanResponses:
    """The human's responses to the balls the robot sent, and the human's serves (module docstring).

    N incoming balls: players (N,) ``player_id``; incoming (N, 9) the recorded state just after the
    bounce on the human's half, [p (m), v (m/s), w (rad/s)]; returned (N,) bool; returns (N, 9) the
    human's recorded post-hit state (NaN where missed); hit_delays (N,) s from the bounce to the
    hit (NaN where missed); return_landed (N,) the return bounced on the robot's half next;
    return_landings (N, 3) where that bounce was recorded, x, y (m), and how long after the hit
    (s) (NaN where it did not land); robot_serve (N,) the incoming ball is the robot's serve; via_net (N,) it touched the net.
    M serves: serves (M, 9) post-hit states, serve_players (M,).
    """

    players: np.ndarray
    incoming: np.ndarray
    returned: np.ndarray
    returns: np.ndarray
    hit_delays: np.ndarray
    return_landed: np.ndarray
    return_landings: np.ndarray
    robot_serve: np.ndarray
    via_net: np.ndarray
    serves: np.ndarray
    serve_players: np.ndarray

    def __len__(self) -> int:
        return len(self.players)

    @property
    def return_rate(self) -> float:
        """The fraction of incoming balls returned (NaN without any)."""
        return float(self.returned.mean()) if len(self) else math.nan

    def of_players(self, players: Sequence[str]) -> "HumanResponses":
        """The incoming balls and serves of the named players only."""
        rows, serve_rows = np.isin(self.players, list(players)), np.isin(self.serve_players, list(players))
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return HumanResponses(**{
            name: value[serve_rows if name.startswith("serve") else rows] for name, value in fields.items()
        })


def require_players(events: Sequence[MatchEvent], players: Sequence[str], source: str = "match data") -> None:
    """Raises MatchDataError naming the recorded players if any of ``players`` has no events."""
    known = sorted({event.player for event in events})
    absent = sorted(set(players) - set(known))
    if absent:
        raise MatchDataError(f"{source}: no events of player(s) {absent}; the recorded players are {known}")


def human_responses(events: Sequence[MatchEvent], players: Sequence[str] = ()) -> HumanResponses:
    """The incoming balls, the human's responses and serves in ``events`` (file order, rallies
    contiguous, as ``load_match_events`` returns them), of ``players`` only (empty: all); raises
    MatchDataError for a player the events do not contain. The rules are the module docstring's."""
    require_players(events, players)
    rows, serves, serve_players = [], [], []
    for rally in split_rallies(events):
        player = rally[0].player
        if players and player not in players:
            continue
        if rally[0].type == "shot_p2" and np.all(np.isfinite(rally[0].state)):
            serves.append(rally[0].state)
            serve_players.append(player)
        robot_shot = None  # index of the robot's last shot, while its ball is on its way to the human
        for i, event in enumerate(rally):
            if event.kind == "shot":
                robot_shot = i if event.side == "p1" else None
                continue
            if robot_shot is None or event.type != "bounce_p2":
                continue
            start, robot_shot = robot_shot, None  # the first bounce on the human's half ends the search
            between = [e.type for e in rally[start + 1:i]]
            serve = start == 0
            allowed = {"net", "bounce_p1"} if serve else {"net"}
            if set(between) - allowed or between.count("bounce_p1") > 1 or not np.all(np.isfinite(event.state)):
                continue
            response = rally[i + 1] if i + 1 < len(rally) else None
            if response is not None and response.type == "shot_p2" and np.all(np.isfinite(response.state)):
                after = rally[i + 2:i + 4]
                kinds = [e.type for e in after]
                landed = bool(kinds) and (kinds[0] == "bounce_p1" or kinds[:2] == ["net", "bounce_p1"])
                landing = np.full(3, np.nan)
                if landed:
                    bounce = after[kinds.index("bounce_p1")]
                    landing = np.array([bounce.state[0], bounce.state[1], bounce.time - response.time])
                rows.append((player, event.state, True, response.state, response.time - event.time, landed, landing, serve, "net" in between))
            elif response is None or response.type == "bounce_p2":
                rows.append((player, event.state, False, np.full(9, np.nan), math.nan, False, np.full(3, np.nan), serve, "net" in between))
    columns = list(zip(*rows)) if rows else [[]] * 9
    return HumanResponses(
        players=np.array(columns[0], dtype=object).astype(str),
        incoming=np.array(columns[1], dtype=float).reshape(-1, 9),
        returned=np.array(columns[2], dtype=bool),
        returns=np.array(columns[3], dtype=float).reshape(-1, 9),
        hit_delays=np.array(columns[4], dtype=float),
        return_landed=np.array(columns[5], dtype=bool),
        return_landings=np.array(columns[6], dtype=float).reshape(-1, 3),
        robot_serve=np.array(columns[7], dtype=bool),
        via_net=np.array(columns[8], dtype=bool),
        serves=np.array(serves, dtype=float).reshape(-1, 9),
        serve_players=np.array(serve_players, dtype=object).astype(str),
    )


def split_rallies(events: Sequence[MatchEvent]) -> list[list[MatchEvent]]:
    """The events grouped into rallies: runs of consecutive events of one player and rally id."""
    rallies: list[list[MatchEvent]] = []
    for event in events:
        if rallies and (rallies[-1][0].player, rallies[-1][0].rally) == (event.player, event.rally):
            rallies[-1].append(event)
        else:
            rallies.append([event])
    return rallies


def incoming_features(incoming: np.ndarray) -> np.ndarray:
    """(..., 7) FEATURES of (..., 9) incoming-ball states, unscaled (m, m/s, rad/s)."""
    return np.asarray(incoming, dtype=float)[..., FEATURE_COLUMNS]


@dataclasses.dataclass(frozen=True)
class ReturnSample:
    """The human's responses to N incoming balls: returned (N,) bool; states (N, 9) post-hit
    [p (m), v (m/s), w (rad/s)] (NaN where not returned); hit_delays (N,) s from the bounce to the
    recorded hit of the chosen neighbour (NaN where not returned)."""

    returned: np.ndarray
    states: np.ndarray
    hit_delays: np.ndarray


class OpponentModel:
    """The human opponent fitted to recorded responses (module docstring).

    Attributes:
        data: the ``HumanResponses`` fitted to.
        params: the ``OpponentParams``.
        players: the fitted players, sorted.
        overall_return_rate: p0 = (returns + 1) / (incoming + 2), the prior of the kNN estimate.
        max_return_speed: m/s, the fastest incoming ball (speed after the bounce) ever returned;
            faster balls are never returned (reaction limit).
        feature_scale (7,): the FEATURES' standard deviations over the fit data.
    """

    def __init__(self, data: HumanResponses, params: OpponentParams | None = None):
        self.data = data
        self.params = params or OpponentParams()
        self.players = tuple(sorted(set(data.players) | set(data.serve_players)))
        if not data.returned.any():
            raise OpponentModelError(f"no recorded returns of player(s) {list(self.players)} to fit an opponent model to")
        n_incoming, n_returned = len(data), int(data.returned.sum())
        self.overall_return_rate = (n_returned + 1) / (n_incoming + 2)
        self.max_return_speed = float(np.linalg.norm(data.incoming[data.returned][:, VELOCITY], axis=-1).max())
        features = incoming_features(data.incoming)
        scale = features.std(axis=0)
        self.feature_scale = np.where(scale > 0.0, scale, 1.0)
        self._all_tree = spatial.cKDTree(features / self.feature_scale)
        self._returned_rows = np.flatnonzero(data.returned)
        self._returned_tree = spatial.cKDTree(features[self._returned_rows] / self.feature_scale)

    @classmethod
    def fit(cls, events: Sequence[MatchEvent], players: Sequence[str] = (), params: OpponentParams | None = None) -> "OpponentModel":
        """The model of ``players`` (empty: all) fitted to recorded ``events``; raises
        MatchDataError (an InputError) naming the recorded players for an unknown one."""
        return cls(human_responses(events, players), params)

    @classmethod
    def from_match_data(cls, path: str | Path, players: Sequence[str] = (), params: OpponentParams | None = None) -> "OpponentModel":
        """The model of ``players`` (empty: all) fitted to the match-data CSV at ``path``."""
        events = load_match_events(path)
        require_players(events, players, str(path))
        return cls.fit(events, players, params)

    def return_probability(self, incoming: np.ndarray) -> np.ndarray:
        """(N,) probability that the human returns each of the (N, 9) incoming balls (state after
        the bounce on the human's half): the smoothed kNN estimate, 0 beyond the reaction limit."""
        incoming = self._check_incoming(incoming)
        k = min(self.params.k, len(self.data))
        _, neighbours = self._all_tree.query(incoming_features(incoming) / self.feature_scale, k=k)
        returned_among_k = self.data.returned[np.reshape(neighbours, (len(incoming), k))].sum(axis=1)
        m = self.params.prior_weight
        probability = (returned_among_k + m * self.overall_return_rate) / (k + m)
        return np.where(self.within_reach(incoming), probability, 0.0)

    def within_reach(self, incoming: np.ndarray) -> np.ndarray:
        """(N,) bool: the incoming ball is no faster than ``max_return_speed`` (reaction limit)."""
        speed = np.linalg.norm(np.asarray(incoming, dtype=float).reshape(-1, 9)[:, VELOCITY], axis=-1)
        return speed <= self.max_return_speed

    def draw_returns(self, incoming: np.ndarray, rng: np.random.Generator, landings: bool = False):
        """Post-hit states (N, 9) and hit delays (N,) s for the (N, 9) incoming balls *given that
        the human returns them*: each a recorded return of one of the k nearest returned incoming
        balls, chosen uniformly, plus the jitter; with ``landings``, also where and when each
        chosen return was recorded landing (N, 3) (``HumanResponses.return_landings``)."""
        incoming = self._check_incoming(incoming)
        k = min(self.params.k, len(self._returned_rows))
        _, neighbours = self._returned_tree.query(incoming_features(incoming) / self.feature_scale, k=k)
        neighbours = np.reshape(neighbours, (len(incoming), k))
        chosen = self._returned_rows[neighbours[np.arange(len(incoming)), rng.integers(k, size=len(incoming))]]
        states = self.data.returns[chosen] + self.params.jitter * rng.standard_normal((len(incoming), 9))
        if landings:
            return states, self.data.hit_delays[chosen], self.data.return_landings[chosen]
        return states, self.data.hit_delays[chosen]

    def sample_returns(self, incoming: np.ndarray, rng: np.random.Generator) -> ReturnSample:
        """The human's responses to (N, 9) incoming balls: each returned with ``return_probability``,
        the return then drawn as in ``draw_returns``. The same ``rng`` state gives the same sample."""
        incoming = self._check_incoming(incoming)
        returned = rng.random(len(incoming)) < self.return_probability(incoming)
        states, hit_delays = self.draw_returns(incoming, rng)
        states[~returned] = np.nan
        hit_delays = np.where(returned, hit_delays, np.nan)
        return ReturnSample(returned, states, hit_delays)

    def sample_return(self, incoming: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
        """The human's post-hit state (9,) [p (m), v (m/s), w (rad/s)] for one incoming ball (9,),
        or None when the human misses it (probability 1 - ``return_probability``)."""
        sample = self.sample_returns(np.reshape(incoming, (1, 9)), rng)
        return sample.states[0] if sample.returned[0] else None

    def sample_serve(self, rng: np.random.Generator) -> np.ndarray:
        """A recorded serve (9,) of the fitted players, chosen uniformly, with the jitter."""
        if len(self.data.serves) == 0:
            raise OpponentModelError(f"player(s) {list(self.players)} served no recorded rally: no serves to sample")
        serve = self.data.serves[rng.integers(len(self.data.serves))]
        return serve + self.params.jitter * rng.standard_normal(9)

    def _check_incoming(self, incoming: np.ndarray) -> np.ndarray:
        incoming = np.asarray(incoming, dtype=float)
        if incoming.shape[-1:] != (9,) or incoming.ndim > 2:
            raise ValueError(f"incoming balls must be (9,) or (N, 9) states, got shape {incoming.shape}")
        incoming = incoming.reshape(-1, 9)
        if not np.all(np.isfinite(incoming)):
            raise ValueError("incoming balls contain NaN or inf")
        return incoming


def profiles(path: str | Path, params: OpponentParams | None = None) -> dict[str, OpponentModel]:
    """One ``OpponentModel`` per player recorded in the match-data CSV at ``path``."""
    events = load_match_events(path)
    return {player: OpponentModel.fit(events, (player,), params) for player in sorted({e.player for e in events})}


def ball_at_hit(incoming: np.ndarray, hit_delays: np.ndarray, physics: BallPhysicsParams | None = None, dt: float = 1e-3) -> np.ndarray:
    """(N, 9) states of the (N, 9) incoming balls ``hit_delays`` (N,) s after their bounce, flown
    with the ball model (``simulate``, deterministic, table, net and floor contacts), linearly
    interpolated between its ``dt`` steps: where the human meets each ball when hitting it as late
    as the recorded neighbour did."""
    incoming = np.asarray(incoming, dtype=float).reshape(-1, 9)
    hit_delays = np.broadcast_to(np.asarray(hit_delays, dtype=float), (len(incoming),))
    if not np.all(np.isfinite(hit_delays) & (hit_delays >= 0.0)):
        raise ValueError(f"hit_delays must be finite and >= 0 s, got {hit_delays}")
    if len(incoming) == 0 or hit_delays.max() == 0.0:
        return incoming.copy()
    trajectory = simulate(incoming, physics or BallPhysicsParams(), float(hit_delays.max()), dt=dt)
    times, states = trajectory.times, trajectory.states
    after = np.clip(np.searchsorted(times, hit_delays), 1, len(times) - 1)
    before = after - 1
    span = times[after] - times[before]
    weight = np.where(span > 0.0, (hit_delays - times[before]) / np.where(span > 0.0, span, 1.0), 0.0)[:, None]
    rows = np.arange(len(incoming))
    return (1.0 - weight) * states[before, rows] + weight * states[after, rows]


# ------------------------------------------------------------------------------ held-out check


def wilson_interval(successes: int, trials: int, z: float = WILSON_Z) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion (95% for the default z)."""
    if trials == 0:
        return (0.0, 1.0)
    rate = successes / trials
    denominator = 1.0 + z**2 / trials
    centre = (rate + z**2 / (2 * trials)) / denominator
    half_width = z * math.sqrt(rate * (1.0 - rate) / trials + z**2 / (4 * trials**2)) / denominator
    return (max(0.0, centre - half_width), min(1.0, centre + half_width))


def landing_points(returns: np.ndarray, physics: BallPhysicsParams | None = None) -> np.ndarray:
    """(N, 2) x, y (m) where each (N, 9) post-hit state first touches the table if that is on the
    robot's half (x < 0) before any floor contact (net touches allowed), else NaN."""
    returns = np.asarray(returns, dtype=float).reshape(-1, 9)
    landing = np.full((len(returns), 2), np.nan)
    if len(returns) == 0:
        return landing
    trajectory = simulate(returns, physics or BallPhysicsParams(), LANDING_FLIGHT_DURATION,
                          stop_on=(ContactKind.TABLE, ContactKind.FLOOR), record=False)
    for i, event in enumerate(trajectory.stop_events):
        if event is not None and event.kind == ContactKind.TABLE and event.state_pre[0] < 0.0:
            landing[i] = event.state_pre[:2]
    return landing


def first_landings(states: np.ndarray, physics: BallPhysicsParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) x, y (m) and (N,) times (s) of each (N, 9) ball's first table contact if that is on
    the robot's half (x < 0) before any floor contact (net touches allowed); NaN otherwise."""
    states = np.asarray(states, dtype=float).reshape(-1, 9)
    points, times = np.full((len(states), 2), np.nan), np.full(len(states), np.nan)
    if len(states) == 0:
        return points, times
    trajectory = simulate(states, physics or BallPhysicsParams(), LANDING_FLIGHT_DURATION,
                          stop_on=(ContactKind.TABLE, ContactKind.FLOOR), record=False)
    for i, event in enumerate(trajectory.stop_events):
        if event is not None and event.kind == ContactKind.TABLE and event.state_pre[0] < 0.0:
            points[i], times[i] = event.state_pre[:2], event.time
    return points, times


def free_flight_positions(states: np.ndarray, times: np.ndarray, physics: BallPhysicsParams, dt: float = 1e-3) -> np.ndarray:
    """(N, 3) positions (m) of the (N, 9) balls at ``times`` (N,) s in free flight (eq. (1), no
    contacts): ``simulate``'s RK4 grid, cubic Hermite between its samples."""
    states = np.asarray(states, dtype=float).reshape(-1, 9)
    trajectory = simulate(states, physics, float(np.max(times)) + dt, dt=dt, kinds=())
    grid, samples = trajectory.times, trajectory.states
    k = np.clip(np.searchsorted(grid, times, side="right") - 1, 0, len(grid) - 2)
    rows = np.arange(len(states))
    h = grid[k + 1] - grid[k]
    u = ((times - grid[k]) / h)[:, None]
    p0, p1 = samples[k, rows, :3], samples[k + 1, rows, :3]
    v0, v1 = samples[k, rows, 3:6] * h[:, None], samples[k + 1, rows, 3:6] * h[:, None]
    return ((2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * v0 + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * v1)


def retarget_returns(returns: np.ndarray, positions: np.ndarray, physics: BallPhysicsParams | None = None,
                     landings: np.ndarray | None = None, iterations: int = 8, tolerance: float = 1e-3) -> np.ndarray:
    """The (N, 9) post-hit states ``returns`` struck from ``positions`` (N, 3) m instead of their
    own: a return that lands on the robot's half, at ``landings`` (N, 3) [x (m), y (m), time
    after the hit (s)] (default: where the ball model lands it, ``first_landings``), gets the
    velocity whose free flight (``free_flight_positions``) has the ball's centre one radius above
    that point at that time (Newton's method on the three velocity components from the drag-free
    answer, the Jacobian by finite differences; stops within ``tolerance`` m), its spin kept. One
    without a landing (NaN), or whose solve does not converge, keeps its velocity. The human's
    placement and pace stay the recorded ones wherever the match's ball meets the racket (the net
    and the table's edges still stop what they stop)."""
    physics = physics or BallPhysicsParams()
    returns = np.asarray(returns, dtype=float).reshape(-1, 9)
    out = returns.copy()
    out[:, :3] = np.asarray(positions, dtype=float).reshape(-1, 3)
    if landings is None:
        target_points, target_times = first_landings(returns, physics)
    else:
        landings = np.asarray(landings, dtype=float).reshape(-1, 3)
        target_points, target_times = landings[:, :2], landings[:, 2]
    solve = np.flatnonzero(np.isfinite(target_times) & (target_times > 0.0))
    if solve.size == 0:
        return out
    target = np.column_stack([target_points[solve], np.full(solve.size, physics.aero.ball_radius)])
    flight = target_times[solve]
    states = out[solve].copy()
    states[:, 3:6] = (target - states[:, :3]) / flight[:, None] + 0.5 * physics.aero.gravity * flight[:, None] * np.array([0.0, 0.0, 1.0])
    step = 1e-3  # m/s, the finite differences' step
    converged = np.zeros(solve.size, dtype=bool)
    for _ in range(iterations):
        probes = np.repeat(states[:, None, :], 4, axis=1)
        probes[:, 1:, 3:6] += step * np.eye(3)
        reached = free_flight_positions(probes.reshape(-1, 9), np.repeat(flight, 4), physics).reshape(-1, 4, 3)
        residual = reached[:, 0] - target
        converged = np.all(np.abs(residual) < tolerance, axis=1)
        if converged.all():
            break
        jacobian = np.transpose(reached[:, 1:] - reached[:, :1], (0, 2, 1)) / step  # d position / d v
        states[~converged, 3:6] -= np.linalg.solve(jacobian[~converged], residual[~converged][..., None])[..., 0]
    out[solve[converged]] = states[converged]
    return out


def compare_samples(recorded: np.ndarray, sampled: np.ndarray) -> dict:
    """Median, interquartile range and the two-sample Kolmogorov-Smirnov statistic of two
    samples of one quantity (NaNs left out)."""
    recorded, sampled = recorded[np.isfinite(recorded)], sampled[np.isfinite(sampled)]

    def summary(values):
        q1, median, q3 = np.percentile(values, [25, 50, 75]) if len(values) else (math.nan,) * 3
        return float(median), float(q3 - q1)

    (recorded_median, recorded_iqr), (sampled_median, sampled_iqr) = summary(recorded), summary(sampled)
    ks = stats.ks_2samp(recorded, sampled) if len(recorded) and len(sampled) else None
    return {
        "recorded_median": recorded_median, "sampled_median": sampled_median,
        "recorded_iqr": recorded_iqr, "sampled_iqr": sampled_iqr,
        "ks_statistic": float(ks.statistic) if ks else math.nan, "ks_pvalue": float(ks.pvalue) if ks else math.nan,
    }


def heldout_check(
    path: str | Path,
    fit_players: Sequence[str],
    test_players: Sequence[str],
    rng: np.random.Generator,
    params: OpponentParams | None = None,
    physics: BallPhysicsParams | None = None,
) -> dict:
    """The model fitted on ``fit_players`` against the recorded responses of ``test_players``.

    Returns figures, judging nothing: ``return_rate`` with the test players' actual rate, its 95%
    Wilson interval and the model's mean predicted probability over their incoming balls; and
    ``returns``, for every test ball the human returned, one return drawn by the model for it
    (``draw_returns``) against the recorded one: speed (m/s) and spin magnitude (rad/s) each as
    ``compare_samples``, and where the returns land on the robot's half under ``physics``
    (``landing_points``: the fraction that lands, and x, y of those that do).
    """
    events = load_match_events(path)
    require_players(events, list(fit_players) + list(test_players), str(path))
    model = OpponentModel.fit(events, fit_players, params)
    test = human_responses(events, test_players)
    n_returned = int(test.returned.sum())
    interval = wilson_interval(n_returned, len(test))
    predicted = float(model.return_probability(test.incoming).mean()) if len(test) else math.nan
    recorded_returns = test.returns[test.returned]
    sampled_returns, _ = model.draw_returns(test.incoming[test.returned], rng)
    recorded_landing, sampled_landing = landing_points(recorded_returns, physics), landing_points(sampled_returns, physics)

    def magnitude(states, part):
        return np.linalg.norm(states[:, part], axis=-1)

    def landed_fraction(landing):
        return float(np.isfinite(landing[:, 0]).mean()) if len(landing) else math.nan
    return {
        "fit_players": sorted(fit_players),
        "test_players": sorted(test_players),
        "n_fit_incoming": len(model.data),
        "n_test_incoming": len(test),
        "n_test_returned": n_returned,
        "return_rate": {
            "actual": test.return_rate,
            "wilson_95": interval,
            "predicted_mean": predicted,
            "predicted_within_interval": bool(interval[0] <= predicted <= interval[1]),
            "fit_overall": model.overall_return_rate,
        },
        "returns": {
            "speed": compare_samples(magnitude(recorded_returns, VELOCITY), magnitude(sampled_returns, VELOCITY)),
            "spin": compare_samples(magnitude(recorded_returns, SPIN), magnitude(sampled_returns, SPIN)),
            "hit_x": compare_samples(recorded_returns[:, 0], sampled_returns[:, 0]),
            "landed_fraction": {"recorded": landed_fraction(recorded_landing), "sampled": landed_fraction(sampled_landing)},
            "landing_x": compare_samples(recorded_landing[:, 0], sampled_landing[:, 0]),
            "landing_y": compare_samples(recorded_landing[:, 1], sampled_landing[:, 1]),
        },
    }
