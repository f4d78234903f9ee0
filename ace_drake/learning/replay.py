"""Experience replay with the paper's event tables and hindsight relabelling (issue 7).

Paper, Methods *Algorithm*, data augmentation (2) and (3):

- Event tables: transitions of episodes that led to predetermined events are stored in separate
  replay buffers, and each mini-batch is drawn from the tables in fixed shares (stratified
  sampling). The paper names near miss, ball hit, ball returned, high-speed return, high-topspin
  return and high-backspin return; its definitions (Supplementary 1.4.8) are not public, so the
  heuristics below are this project's (``EventThresholds``). Every transition also goes to the
  ``all`` table (the ordinary buffer), and an episode's transitions go to every table whose event
  it ended in (a high-speed return is also a return and a hit):

      all                   every episode
      miss                  the robot did not hit the ball (outcome MISSED without a hit: the
                            ball bounced twice or left, passed the racket, or the command would
                            have collided; paper eq. (10)'s R_miss)
      near_miss             a miss whose ball came within ``near_miss_distance`` of the blade
                            centre (closest approach, measured by the collector)
      hit                   the robot hit the ball (returned or not)
      return                the return landed on the opponent's half (outcome RETURNED)
      high_speed_return     a return leaving the racket faster than ``high_speed`` (m/s)
      high_topspin_return   a return landing with travel-frame spin omega_y >= ``high_topspin``
      high_backspin_return  a return landing with omega_y <= -``high_backspin`` (rad/s)

  omega_y is the reward's (``rewards.travel_frame_spin``: topspin > 0), so events, like rewards,
  are unchanged by the XZ mirror. A batch draws its B rows from the tables with probabilities
  proportional to ``ReplayConfig.table_weights``, renormalised over the non-empty tables (the
  table counts are multinomial), then uniformly within each table.
- Hindsight relabelling (Andrychowicz et al. 2017): a returned episode is stored a second time
  with the skill [y_desired, w_p, w_s] := [y_land, 1, w_s] in every observation's skill part
  (the actor's ``skill`` slice and the privileged ``skill`` slice, now and next), and its
  terminal reward recomputed by ``rewards.return_reward`` with that skill: the landing is then
  exactly on target, so the position term is its maximum ``position_reward``.

- Monte Carlo returns: every stored row also holds its episode's discounted return from that step
  on, G_t = sum_{k>=t} gamma^(k-t) r_k (``discounted_returns``; gamma per policy step, G in reward
  units; the reward is terminal, so G_t = gamma^(n-1-t) r_{n-1} for an episode of n rows),
  computed for each copy after relabelling and augmentation, so a hindsight copy's returns are its
  own. The learner's target may read it (``sac``: ``mc_mix``, ``mc_bound``).

Transitions are dicts of arrays with the keys of ``sac.BATCH_KEYS`` (one row per policy step); a
table's rows add ``mc_return`` (``TABLE_KEYS``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ace_drake.contracts import EpisodeResult, ObservationLayout, Outcome, privileged_slice
from ace_drake.learning.params import RewardParams
from ace_drake.learning.rewards import return_reward, travel_frame_spin
from ace_drake.learning.sac import SacConfig

TRANSITION_KEYS = ("obs", "privileged", "action", "reward", "next_obs", "next_privileged", "done")
# A table row: the transition and its discounted return to the episode's end (module docstring).
TABLE_KEYS = TRANSITION_KEYS + ("mc_return",)
# The value of a column that a loaded table state lacks (a checkpoint written before the column
# was stored): -inf, "no return stored", which leaves the target as it is (sac: mc_mix, mc_bound).
MISSING_COLUMNS = {"mc_return": -np.inf}

# What a replay table's state (NumPy arrays; NumPy scalars in the evaluation figures beside them)
# needs from the unpickler beyond tensors and plain containers: NumPy's array and scalar
# reconstruction and the dtypes the tables and figures use, nothing that runs other code.
NUMPY_SAFE_GLOBALS = [np._core.multiarray._reconstruct, np._core.multiarray.scalar, np.ndarray, np.dtype,
                      *(type(np.dtype(kind)) for kind in (np.float32, np.float64, np.int64, np.bool_))]


def load_weights_only(path):
    """``torch.load(path, weights_only=True)`` (on the CPU) for a file holding tensors, plain
    containers and replay-table states (NUMPY_SAFE_GLOBALS allowed): a training checkpoint, or a
    file of demonstrations; anything else in the file raises ``pickle.UnpicklingError``. (Not
    memory-mapped: a loaded optimiser keeps the file's tensors as its state, and a file changed
    under a mapping kills the process.)"""

    with torch.serialization.safe_globals(NUMPY_SAFE_GLOBALS):
        return torch.load(path, map_location="cpu", weights_only=True)
EVENTS = ("all", "miss", "near_miss", "hit", "return", "high_speed_return", "high_topspin_return", "high_backspin_return")


@dataclasses.dataclass(frozen=True)
class EventThresholds:
    """The event heuristics' numbers (module docstring; the paper's are not public).

    near_miss_distance: m, closest approach of the ball's centre to the blade centre for a miss
    to be near (blade radius 0.075 + ball radius 0.02 + 0.055 m).
    high_speed: m/s, the ball's speed just after the hit (the robot's published returns: median
    7.8, p90 12.3 m/s).
    high_topspin, high_backspin: rad/s, |omega_y| at landing (the robot's published spin: median
    248, p90 408 rad/s; backspin returns spin less, so a lower bar).
    """

    near_miss_distance: float = 0.15
    high_speed: float = 10.0
    high_topspin: float = 250.0
    high_backspin: float = 150.0


@dataclasses.dataclass(frozen=True)
class EpisodeSummary:
    """What the event heuristics read from an ended episode: its ``result`` (outcome, hit and
    landing events) and, for near misses, the closest approach (m) of the ball's centre to the
    blade centre over the episode (None when not measured: then no miss counts as near)."""

    result: EpisodeResult
    closest_approach: float | None = None


def episode_events(summary: EpisodeSummary, thresholds: EventThresholds = EventThresholds()) -> tuple[str, ...]:
    """The EVENTS (module docstring's definitions) an episode ended in, ``all`` first."""
    result = summary.result
    events = ["all"]
    if result.hit is None:
        if result.outcome is Outcome.MISSED:
            events.append("miss")
            if summary.closest_approach is not None and summary.closest_approach <= thresholds.near_miss_distance:
                events.append("near_miss")
        return tuple(events)
    events.append("hit")
    if result.outcome is Outcome.RETURNED:
        events.append("return")
        if np.linalg.norm(result.hit.state_post[3:6]) >= thresholds.high_speed:
            events.append("high_speed_return")
        spin = float(travel_frame_spin(result.landing.state_pre))
        if spin >= thresholds.high_topspin:
            events.append("high_topspin_return")
        if spin <= -thresholds.high_backspin:
            events.append("high_backspin_return")
    return tuple(events)


def _default_weights() -> dict[str, float]:
    # Half of every batch from the ordinary buffer, the rest shared by the events (the paper's
    # shares are not public). A share whose table is empty goes to the others.
    return {"all": 0.5, "miss": 0.05, "near_miss": 0.1, "hit": 0.1, "return": 0.1,
            "high_speed_return": 0.05, "high_topspin_return": 0.05, "high_backspin_return": 0.05}


def _default_capacities() -> dict[str, int]:
    # Transitions per table (not public). A transition of the default layout is ~1.4 kB (float32).
    return {name: (200_000 if name == "all" else 30_000) for name in EVENTS}


@dataclasses.dataclass(frozen=True)
class ReplayConfig:
    """table_weights: each table's share of a batch (renormalised over non-empty tables);
    table_capacities: transitions per table (oldest overwritten first); thresholds: the events'
    heuristics; relabel: store hindsight copies of returned episodes; seed: the sampling stream."""

    table_weights: dict[str, float] = dataclasses.field(default_factory=_default_weights)
    table_capacities: dict[str, int] = dataclasses.field(default_factory=_default_capacities)
    thresholds: EventThresholds = dataclasses.field(default_factory=EventThresholds)
    relabel: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for field in ("table_weights", "table_capacities"):
            unknown = set(getattr(self, field)) - set(EVENTS)
            if unknown:
                raise ValueError(f"ReplayConfig.{field}: unknown event(s) {sorted(unknown)}; events are {EVENTS}")
        if any(not w >= 0.0 for w in self.table_weights.values()) or not sum(self.table_weights.values()) > 0.0:
            raise ValueError(f"ReplayConfig.table_weights must be >= 0 with a positive sum, got {self.table_weights}")
        if any(c < 1 for c in self.table_capacities.values()):
            raise ValueError(f"ReplayConfig.table_capacities must be >= 1, got {self.table_capacities}")


def discounted_returns(reward, gamma: float) -> np.ndarray:
    """G_t = sum_{k>=t} gamma^(k-t) r_k (n,), in reward units, for an episode's rewards (n,) in
    step order and the discount ``gamma`` per policy step: each step's discounted return to the
    episode's end (the Monte Carlo return of the module docstring)."""
    reward = np.asarray(reward, dtype=float)
    out = np.empty_like(reward)
    running = 0.0
    for t in range(len(reward) - 1, -1, -1):
        running = reward[t] + gamma * running
        out[t] = running
    return out


class RingBuffer:
    """Fixed-capacity storage of transitions (float32 arrays allocated at the first insert);
    when full, each new transition overwrites the oldest."""

    def __init__(self, capacity: int, keys: tuple[str, ...] = TRANSITION_KEYS):
        self.capacity = capacity
        self.keys = keys
        self.size = 0
        self._next = 0
        self._data: dict[str, np.ndarray] | None = None

    def add(self, transitions: dict[str, np.ndarray]) -> None:
        count = len(transitions[self.keys[0]])
        if count > self.capacity:  # only the newest fit
            transitions, count = {key: transitions[key][-self.capacity:] for key in self.keys}, self.capacity
        if self._data is None:
            self._data = {key: np.zeros((self.capacity, *np.shape(transitions[key])[1:]), np.float32) for key in self.keys}
        rows = (self._next + np.arange(count)) % self.capacity
        for key in self.keys:
            self._data[key][rows] = transitions[key]
        self._next = int((self._next + count) % self.capacity)
        self.size = min(self.size + count, self.capacity)

    def get(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        return {key: self._data[key][rows] for key in self.keys}

    def oldest_first(self) -> np.ndarray:
        """The stored rows' indices in the order they were added (a full ring's oldest row is at
        its write position)."""
        start = self._next if self.size == self.capacity else 0
        return (start + np.arange(self.size)) % self.capacity

    def state_dict(self) -> dict:
        """The stored rows (only the filled ones, as tensors sharing the table's memory: a
        checkpoint writes them straight to its file, without a copy; they change with the next
        ``add``, so write or copy them first) and the write position."""
        data = None if self._data is None else {key: torch.from_numpy(value[: self.size]) for key, value in self._data.items()}
        return {"capacity": self.capacity, "size": self.size, "next": self._next, "data": data}

    def load_state_dict(self, state: dict) -> None:
        """Restores a ``state_dict``. One saved with another capacity (a later training stage's
        table: ``ReplayConfig.table_capacities``) loads its rows oldest first, the newest
        ``capacity`` of them where they do not all fit, and the next row goes after them."""
        size, written_next, self._data = int(state["size"]), int(state["next"]), None
        if state["data"] is None or state["capacity"] == self.capacity:
            self.size, self._next = size, written_next  # as it lay
            rows = slice(None)
        else:
            start = written_next if size == state["capacity"] else 0
            rows = ((start + np.arange(size)) % state["capacity"])[-self.capacity:]
            self.size = len(rows)
            self._next = self.size % self.capacity
        if state["data"] is not None:
            self._data = {key: np.zeros((self.capacity, *value.shape[1:]), np.float32) for key, value in state["data"].items()}
            for key, value in state["data"].items():  # tensors, or NumPy arrays in older checkpoints
                self._data[key][: self.size] = np.asarray(value)[rows]
            for key in self.keys:  # a scalar column stored since the state was written
                if key not in self._data:
                    if key not in MISSING_COLUMNS:
                        raise KeyError(f"RingBuffer.load_state_dict: the state lacks the column {key!r}")
                    self._data[key] = np.full(self.capacity, MISSING_COLUMNS[key], np.float32)


def relabel_episode(transitions: dict[str, np.ndarray], landing_state: np.ndarray, layout: ObservationLayout,
                    params: RewardParams) -> dict[str, np.ndarray]:
    """The hindsight copy of a returned episode's transitions (module docstring): skill
    [y_land, 1, w_s] everywhere, the terminal rewards recomputed (rewards.return_reward), the
    other rewards unchanged (0: rewards are terminal)."""
    out = {key: np.array(value, dtype=np.float32, copy=True) for key, value in transitions.items()}
    old_skill = np.asarray(transitions["privileged"], dtype=float)[0, privileged_slice("skill")]
    skill = np.array([landing_state[1], 1.0, old_skill[2]])
    for key in ("obs", "next_obs"):
        out[key][:, layout.slice("skill")] = skill
    for key in ("privileged", "next_privileged"):
        out[key][:, privileged_slice("skill")] = skill
    terminal = np.asarray(transitions["done"]) > 0.5
    out["reward"][terminal] = return_reward(landing_state, skill, params)
    return out


class EventReplay:
    """The event tables (module docstring): ``add_episode`` stores an ended episode (and its
    augmented copies) in the tables of its events; ``sample`` draws a mixed batch.

    ``augment``: callables mapping a transitions dict to another (e.g. ``mirror.Mirror.transitions``),
    each applied to the episode and its hindsight copy, whose outputs are stored as well.
    ``gamma``: the discount per policy step of the stored Monte Carlo returns (the learner's
    ``SacConfig.gamma``).
    """

    def __init__(self, config: ReplayConfig | None = None, layout: ObservationLayout | None = None,
                 reward: RewardParams | None = None, augment=(), gamma: float = SacConfig.gamma):
        if not 0.0 <= gamma < 1.0:
            raise ValueError(f"EventReplay: gamma must be in [0, 1), got {gamma}")
        self.gamma = gamma
        self.config = config or ReplayConfig()
        self.layout = layout or ObservationLayout()
        self.reward = reward or RewardParams()
        self.augment = tuple(augment)
        capacities = {**_default_capacities(), **self.config.table_capacities}
        self.tables = {name: RingBuffer(capacities[name], TABLE_KEYS) for name in EVENTS}
        self.weights = np.array([self.config.table_weights.get(name, 0.0) for name in EVENTS])
        self.rng = np.random.default_rng(self.config.seed)
        self.episodes = 0

    def add_episode(self, transitions: dict[str, np.ndarray], summary: EpisodeSummary) -> tuple[str, ...]:
        """Stores an ended episode's transitions (keys TRANSITION_KEYS, rows in step order, the
        last terminal), its hindsight copy if it was returned, and their augmentations, each with
        its own Monte Carlo returns, in the tables of its events (returned)."""
        missing = [key for key in TRANSITION_KEYS if key not in transitions]
        if missing:
            raise KeyError(f"EventReplay.add_episode: transitions lack {missing}")
        events = episode_events(summary, self.config.thresholds)
        copies = [transitions]
        if self.config.relabel and summary.result.outcome is Outcome.RETURNED:
            copies.append(relabel_episode(transitions, summary.result.landing.state_pre, self.layout, self.reward))
        copies += [augment(copy) for augment in self.augment for copy in list(copies)]
        for copy in copies:
            rows = {**copy, "mc_return": discounted_returns(copy["reward"], self.gamma)}
            for name in events:
                self.tables[name].add(rows)
        self.episodes += 1
        return events

    def table_probabilities(self) -> np.ndarray:
        """Each table's probability (EVENTS order) of supplying a batch row now."""
        weights = self.weights * np.array([self.tables[name].size > 0 for name in EVENTS])
        total = weights.sum()
        if total == 0.0:
            raise ValueError("EventReplay.sample: every table with a positive weight is empty")
        return weights / total

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """A batch (keys TABLE_KEYS, plus ``table``: the EVENTS index each row came from)."""
        counts = self.rng.multinomial(batch_size, self.table_probabilities())
        parts, tables = [], []
        for index, (name, count) in enumerate(zip(EVENTS, counts)):
            if count:
                table = self.tables[name]
                parts.append(table.get(self.rng.integers(table.size, size=count)))
                tables.append(np.full(count, index))
        batch = {key: np.concatenate([part[key] for part in parts]) for key in TABLE_KEYS}
        batch["table"] = np.concatenate(tables)
        return batch

    def state_dict(self) -> dict:
        """The tables' contents, the sampling stream and the episode count (for a resumable
        training checkpoint; large: every stored transition)."""
        return {"tables": {name: table.state_dict() for name, table in self.tables.items()},
                "rng": self.rng.bit_generator.state, "episodes": self.episodes}

    def load_state_dict(self, state: dict) -> None:
        for name, table in self.tables.items():
            table.load_state_dict(state["tables"][name])
        self.rng.bit_generator.state = state["rng"]
        self.episodes = int(state["episodes"])

    def __len__(self) -> int:
        return self.tables["all"].size


class DemonstrationBuffer:
    """The demonstrated transitions (observation, the demonstrator's action) that the learner's
    behaviour-cloning term reads (``sac`` docstring), sampled uniformly.

    ``augment``: callables mapping the rows (keys ``KEYS``) to others (e.g.
    ``mirror.Mirror.transitions``), whose outputs are stored as well, as ``EventReplay``'s."""

    KEYS = ("obs", "privileged", "demo_action")

    def __init__(self, capacity: int = 200_000, seed: int = 0, augment=()):
        self.buffer = RingBuffer(capacity, self.KEYS)
        self.rng = np.random.default_rng(seed)
        self.augment = tuple(augment)

    def add(self, transitions: dict[str, np.ndarray]) -> None:
        """Stores an episode's rows (keys ``KEYS``; the rest ignored) that have a label (a
        hit-state label is NaN where the returner planned no hit: ``rollout``), and their
        augmentations."""
        labelled = np.all(np.isfinite(transitions["demo_action"]), axis=-1)
        if labelled.any():
            rows = {key: np.asarray(transitions[key])[labelled] for key in self.KEYS}
            for copy in (rows, *(augment(rows) for augment in self.augment)):
                self.buffer.add({key: copy[key] for key in self.KEYS})

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        if self.buffer.size == 0:
            raise ValueError("DemonstrationBuffer.sample: no demonstrations stored")
        return self.buffer.get(self.rng.integers(self.buffer.size, size=batch_size))

    def state_dict(self) -> dict:
        return {"buffer": self.buffer.state_dict(), "rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        self.buffer.load_state_dict(state["buffer"])
        self.rng.bit_generator.state = state["rng"]

    def __len__(self) -> int:
        return self.buffer.size
