"""The incoming-shot distribution: kernel density estimates of the opponent's post-hit ball states.

Paper, Methods *Initial state training distribution*, item 1: an episode's initial ball state is
drawn from a kernel density estimate (KDE) fitted either to a synthetic set (uniformly sampled
ball states that were checked for validity) or to human shots; there is one KDE for serves and
one for returns, and serves and returns are drawn 3:7.

A shot is a (9,) ball state just after the opponent's hit, [p_W (m), v_W (m/s), w_W (rad/s)] in
the world frame of DESIGN.md (origin at the centre of the table's playing surface, x towards the
human, z up; the robot plays from x < 0). Each KDE is ``scipy.stats.gaussian_kde`` over all nine
values (its kernel covariance is the data's covariance times the bandwidth factor squared, so the
mixed units need no scaling).

Every drawn state is simulated with the project's ball model (``physics.propagate.simulate_ball``,
deterministic, no racket) and kept only if it is a shot the robot has to play: it starts in free
flight on the human's side (x > 0), and the episode classifier (``play.episode.classify``, the
ITTF rules the rally umpire applies) finds its bounce on the robot's half: a return's first table
contact is on the robot's half (x < 0), a serve bounces on the server's half (x > 0) and then on
the robot's, each before any floor contact (touching the net on the way is allowed, as in the
episode). A ball whose centre misses the table's rectangle makes no table contact at all, so a
shot that would land beyond an end or side line is rejected by the same check. Rejected draws are
replaced by new ones.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import stats

from ace_drake.config import InputError
from ace_drake.match_data import MatchDataError, load_match_events
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import DEFAULT_KINDS, ContactEvent, ContactKind, contact_gap, simulate_ball
from ace_drake.play.episode import classify
from ace_drake.play.params import ShotParams

SERVE, RETURN = "serve", "return"
SERVE_FRACTION = 0.3  # serves : returns = 3 : 7 (paper, *Initial state training distribution*)
FLIGHT_DURATION = 2.0  # s simulated to a shot's next bounce: a shot that takes longer is not one to play
# Draws stop with an error once this many have been simulated and fewer than MIN_ACCEPTANCE of
# them were valid: the distribution puts almost no mass on playable shots.
MIN_ACCEPTANCE = 0.05
MIN_DRAWS_BEFORE_GIVING_UP = 500
# The first batch of draws assumes this acceptance (the built-in and human KDEs accept about 63%),
# so that one simulation per kind usually suffices; later batches use the rate seen so far.
FIRST_BATCH_ACCEPTANCE = 0.6
SYNTHETIC_CANDIDATES = 2000  # uniform draws per kind for the synthetic set, before the validity check


class ShotDistributionError(InputError):
    """A shot distribution cannot be fitted or sampled; the message says which kind and why."""


@dataclasses.dataclass(frozen=True)
class ShotSample:
    """Shots drawn from a ``ShotDistribution``.

    states (n, 9): [p (m), v (m/s), w (rad/s)] just after the hit, every one valid; serve (n,):
    True for a serve, False for a return; acceptance_rate: the fraction of the KDE draws simulated
    for this sample that were valid (1 when n = 0).
    """

    states: np.ndarray
    serve: np.ndarray
    acceptance_rate: float


def valid_shots(states: np.ndarray, serve: bool, physics: BallPhysicsParams | None = None) -> np.ndarray:
    """Which of the (N, 9) post-hit states are valid shots of one kind (the module docstring's
    rules), by simulating them with ``physics`` (default: the paper's model) at the propagator's
    default 1 ms step. Returns (N,) bool."""
    physics = physics or BallPhysicsParams()
    states = np.asarray(states, dtype=float).reshape(-1, 9)
    starts_in_flight = np.all(np.isfinite(states), axis=1) & (states[:, 0] > 0.0)
    for kind in DEFAULT_KINDS:
        starts_in_flight &= contact_gap(kind, np.nan_to_num(states), physics) > 0.0
    valid = np.zeros(len(states), dtype=bool)
    rows = np.flatnonzero(starts_in_flight)
    if rows.size == 0:
        return valid
    events = _contacts_to_next_bounce(states[rows], physics)
    if serve:
        # A serve is decided at its second table contact: follow the balls that bounced on the
        # server's half on to their next one.
        again = [
            i for i, contacts in enumerate(events)
            if contacts and contacts[-1].kind == ContactKind.TABLE and contacts[-1].state_pre[0] > 0.0
        ]
        if again:
            after_bounce = np.array([events[i][-1].state_post for i in again])
            for i, contacts in zip(again, _contacts_to_next_bounce(after_bounce, physics)):
                events[i] = events[i] + contacts
    valid[rows] = [classify(contacts, serve=serve).bounce is not None for contacts in events]
    return valid


def _contacts_to_next_bounce(states: np.ndarray, physics: BallPhysicsParams) -> list[list[ContactEvent]]:
    """Each (N, 9) ball's contacts up to its first table or floor contact (net touches on the way),
    within FLIGHT_DURATION (s); stopping there keeps the simulation short."""
    # Ball by ball with the compiled propagator: ``simulate``'s contacts bit for bit, ~4 x faster
    # than its NumPy loop over the batch (drawing shots took ~28% of a rollout worker's time).
    stop_on = (ContactKind.TABLE, ContactKind.FLOOR)
    return [simulate_ball(state, physics, FLIGHT_DURATION, stop_on=stop_on).events[0] for state in states]


class ShotDistribution:
    """Serves and returns from two Gaussian KDEs, mixed ``serve_fraction`` : 1 - ``serve_fraction``,
    every draw checked for validity by simulation and redrawn if invalid (module docstring).

    Attributes:
        serves (n_s, 9), returns (n_r, 9): the states the KDEs were fitted to, [p (m), v (m/s),
            w (rad/s)].
        serve_fraction: probability that a shot is a serve (paper: 0.3).
        bandwidth: the KDEs' bandwidth factor; None is Scott's rule, n^(-1/(d+4)) with d = 9.
        physics: the ball model that judges validity.
    """

    def __init__(
        self,
        serves: np.ndarray,
        returns: np.ndarray,
        serve_fraction: float = SERVE_FRACTION,
        bandwidth: float | None = None,
        physics: BallPhysicsParams | None = None,
    ):
        if not 0.0 <= serve_fraction <= 1.0:
            raise ShotDistributionError(f"serve_fraction must be in [0, 1], got {serve_fraction}")
        self.serves = np.asarray(serves, dtype=float).reshape(-1, 9)
        self.returns = np.asarray(returns, dtype=float).reshape(-1, 9)
        self.serve_fraction = serve_fraction
        self.bandwidth = bandwidth
        self.physics = physics or BallPhysicsParams()
        self._kdes = {}
        for kind, states, probability in ((SERVE, self.serves, serve_fraction), (RETURN, self.returns, 1.0 - serve_fraction)):
            if probability == 0.0:
                continue
            if len(states) <= 9 or not np.all(np.isfinite(states)):
                raise ShotDistributionError(f"a KDE of {kind}s needs more than 9 finite (9,) states, got {len(states)}")
            try:
                self._kdes[kind] = stats.gaussian_kde(states.T, bw_method=bandwidth)
            except np.linalg.LinAlgError:
                raise ShotDistributionError(f"the {kind} states are degenerate (singular covariance)") from None

    def draw(self, rng: np.random.Generator, n: int) -> ShotSample:
        """n valid shots: each a serve with probability ``serve_fraction``, else a return, drawn
        from that kind's KDE until valid. The same ``rng`` state gives the same sample, bit for
        bit. Raises ShotDistributionError when a kind's draws are almost never valid."""
        if n < 0:
            raise ValueError(f"ShotDistribution.draw: n must be >= 0, got {n}")
        serve = rng.random(n) < self.serve_fraction
        states = np.empty((n, 9))
        n_valid, drawn = 0, 0
        for kind, rows in ((SERVE, serve), (RETURN, ~serve)):
            if rows.any():
                states[rows], kind_valid, kind_drawn = self._draw_valid(kind, rng, int(rows.sum()))
                n_valid, drawn = n_valid + kind_valid, drawn + kind_drawn
        return ShotSample(states, serve, n_valid / drawn if drawn else 1.0)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """The (n, 9) states of ``draw(rng, n)``: [p (m), v (m/s), w (rad/s)] after the hit."""
        return self.draw(rng, n).states

    def _draw_valid(self, kind: str, rng: np.random.Generator, count: int) -> tuple[np.ndarray, int, int]:
        """``count`` valid states of one kind, and how many of the draws simulated to find them
        were valid (at least ``count``: the last batch may overshoot) and drawn in all."""
        kept, n_valid, drawn = [], 0, 0
        while n_valid < count:
            rate = n_valid / drawn if drawn else FIRST_BATCH_ACCEPTANCE
            if drawn >= MIN_DRAWS_BEFORE_GIVING_UP and rate < MIN_ACCEPTANCE:
                raise ShotDistributionError(
                    f"only {n_valid} of {drawn} {kind}s drawn from the KDE are valid shots "
                    f"(< {MIN_ACCEPTANCE:.0%}): the data hardly contains shots that bounce on the robot's half"
                )
            # Enough draws for the rest at the rate seen so far, with a margin against bad luck.
            batch = math.ceil(1.1 * (count - n_valid) / max(rate, MIN_ACCEPTANCE)) + 8
            candidates = self._kdes[kind].resample(batch, seed=rng).T
            valid = valid_shots(candidates, kind == SERVE, self.physics)
            kept.append(candidates[valid])
            n_valid += int(valid.sum())
            drawn += batch
        return np.concatenate(kept)[:count], n_valid, drawn


# ------------------------------------------------------------------------------ synthetic set


@dataclasses.dataclass(frozen=True)
class ShotRanges:
    """Uniform ranges, (low, high), of one kind of synthetic shot.

    The hit point is (x, y, z), m. The ball leaves it at ``speed`` (m/s) and ``elevation`` above
    the horizontal (deg), heading horizontally towards an aim point (aim_x, aim_y) (m) on the
    robot's half. Spin (rad/s) is given in the ball's travel frame: ``topspin`` about the horizontal
    axis across the flight (negative values are backspin), ``sidespin`` about z, ``corkscrew`` about
    the heading.
    """

    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]
    speed: tuple[float, float]
    elevation: tuple[float, float]
    aim_x: tuple[float, float] = (-1.3, -0.2)
    aim_y: tuple[float, float] = (-0.7, 0.7)
    topspin: tuple[float, float] = (-300.0, 600.0)
    sidespin: tuple[float, float] = (-300.0, 300.0)
    corkscrew: tuple[float, float] = (-100.0, 100.0)


# Returns: hit behind the human's end line (x = 1.37 m) at table height or a little above, 5-15 m/s,
# flat to a lob, topspin up to 600 rad/s, backspin and sidespin up to 300 rad/s. About a quarter
# of these draws are valid (the rest miss the table or do not clear the net).
RETURN_RANGES = ShotRanges(x=(1.4, 2.2), y=(-0.7, 0.7), z=(0.1, 0.4), speed=(5.0, 15.0), elevation=(0.0, 20.0))
# Serves: hit lower and closer to the end line, slower and downwards so that they bounce on the
# server's half first; mostly backspin and sidespin. About a third are valid.
SERVE_RANGES = ShotRanges(
    x=(1.4, 1.9), y=(-0.7, 0.7), z=(0.05, 0.3), speed=(4.5, 9.0), elevation=(-20.0, -5.0), topspin=(-400.0, 200.0)
)


def synthetic_candidates(rng: np.random.Generator, ranges: ShotRanges, count: int) -> np.ndarray:
    """``count`` post-hit states (count, 9) [p (m), v (m/s), w (rad/s)] drawn uniformly from
    ``ranges``; not yet checked for validity."""
    draw = {f.name: rng.uniform(*getattr(ranges, f.name), size=count) for f in dataclasses.fields(ranges)}
    p_W = np.stack([draw["x"], draw["y"], draw["z"]], axis=-1)
    heading = np.stack([draw["aim_x"] - draw["x"], draw["aim_y"] - draw["y"], np.zeros(count)], axis=-1)
    heading /= np.linalg.norm(heading, axis=-1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    elevation = np.radians(draw["elevation"])[:, None]
    v_W = draw["speed"][:, None] * (np.cos(elevation) * heading + np.sin(elevation) * up)
    # Topspin turns the ball's top towards its heading: spin about up x heading.
    across = np.cross(up, heading)
    w_W = draw["topspin"][:, None] * across + draw["sidespin"][:, None] * up + draw["corkscrew"][:, None] * heading
    return make_state(p_W, v_W, w_W)


def synthetic_distribution(
    seed: int = 0,
    serve_fraction: float = SERVE_FRACTION,
    bandwidth: float | None = None,
    physics: BallPhysicsParams | None = None,
    candidates: int = SYNTHETIC_CANDIDATES,
) -> ShotDistribution:
    """KDEs fitted to the synthetic set: ``candidates`` uniform draws per kind from SERVE_RANGES
    and RETURN_RANGES (seeded by ``seed``), of which only the valid ones enter the fit (paper: "shots
    are uniformly sampled from a range of initial ball states and checked for validity")."""
    rng = np.random.default_rng(seed)
    serves = synthetic_candidates(rng, SERVE_RANGES, candidates)
    returns = synthetic_candidates(rng, RETURN_RANGES, candidates)
    serves = serves[valid_shots(serves, True, physics)]
    returns = returns[valid_shots(returns, False, physics)]
    return ShotDistribution(serves, returns, serve_fraction, bandwidth, physics)


# ------------------------------------------------------------------------------ human shots


def human_shots(path: str | Path, players: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray]:
    """The human's shots (``shot_p2`` events) of a match-data CSV, in file order, of the named
    ``players`` only (``player_id`` values such as "Elite A"; empty: all of them), e.g. to fit a
    distribution on some players and evaluate on the others.

    Returns states (n, 9), [p (m), v (m/s), w (rad/s)] just after the hit, and serve (n,) bool:
    the shot is a serve, the first shot of its rally (rallies are recorded from their first event,
    in order; ``match_data``). Raises MatchDataError for a missing or malformed file or a
    player the file does not contain.
    """
    events = load_match_events(path)
    absent = sorted(set(players) - {event.player for event in events})
    if absent:
        known = sorted({event.player for event in events})
        raise MatchDataError(f"{path}: no events of player(s) {absent}; the file has {known}")
    states, serve = [], []
    rally = None
    for event in events:
        if (event.player, event.rally) != rally:
            rally, shots_so_far = (event.player, event.rally), 0
        if event.kind != "shot":
            continue
        if event.side == "p2" and (not players or event.player in players):
            states.append(event.state)
            serve.append(shots_so_far == 0)
        shots_so_far += 1
    return np.array(states, dtype=float).reshape(-1, 9), np.array(serve, dtype=bool)


def held_out_players(params: ShotParams, path: str | Path) -> tuple[str, ...]:
    """The players of the match-data CSV at ``path`` whose shots a distribution described by
    ``params`` did not see: those not in ``params.players`` when it was fitted to that same file
    with a players selection, else none (sorted ``player_id`` values)."""
    if not params.players or params.source == "synthetic" or Path(params.source).resolve() != Path(path).resolve():
        return ()
    return tuple(sorted({event.player for event in load_match_events(path)} - set(params.players)))


def distribution_from_match_data(
    path: str | Path,
    serve_fraction: float = SERVE_FRACTION,
    bandwidth: float | None = None,
    physics: BallPhysicsParams | None = None,
    players: Sequence[str] = (),
) -> ShotDistribution:
    """KDEs fitted to the human's serves and returns in a match-data CSV (``human_shots``, of
    ``players`` only; empty: all): the paper's human KDE models. Only recorded shots that are
    valid under ``physics`` enter the fit, as for the synthetic set (under the paper's model: 102
    of the 115 serves and 310 of the 522 returns of ../shared/data/ace_match_events_elite.csv)."""
    states, serve = human_shots(path, players)
    serves, returns = states[serve], states[~serve]
    serves = serves[valid_shots(serves, True, physics)]
    returns = returns[valid_shots(returns, False, physics)]
    return ShotDistribution(serves, returns, serve_fraction, bandwidth, physics)


def make_distribution(params: ShotParams, physics: BallPhysicsParams | None = None) -> ShotDistribution:
    """The distribution ``params`` describes: the synthetic set (seeded by ``params.seed``) or
    the human shots of the match-data CSV at ``params.source`` (of ``params.players``); validity judged by ``physics``."""
    if params.source == "synthetic":
        return synthetic_distribution(params.seed, params.serve_fraction, params.bandwidth, physics)
    return distribution_from_match_data(params.source, params.serve_fraction, params.bandwidth, physics, params.players)
