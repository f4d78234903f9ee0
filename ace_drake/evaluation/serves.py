"""The robot's serve library (paper, Methods *Serve design*): serves that the robot executes open
loop, each kept because it fails less than 5% of the time, and the rule that picks the next one.

A library serve (``LibraryServe``) is a strike found by the genetic algorithm
(``analysis.serve_search``; ball level, ``control.serve``) made by the robot after the toss
(``control.serve_execution``: ``plan_toss`` once, ``plan_strike`` per serve): its whole 1 kHz
command sequence from rest (toss, strike, follow-through), the executed release t_lift and the
ball's state there. ``LibraryServe.episode_start`` turns it into the first episode of a served
point on the segment-stepped rally diagram (``serve_episode_start``).

``execute_serves`` measures each serve's legality on that diagram: every serve ``repeats`` times,
batched, each repeat with

- execution noise: the released ball's position and velocity drawn around the executed release,
  independent Gaussians per axis (``ExecutionNoise``; 2 mm and 0.02 m/s by default, chosen: the
  paper gives no figure; a ball seated in a cup of a few mm play, and 1% of the 2 m/s toss speed,
  about what the executed toss already misses its design by, 0.12 mm and 0.026 m/s, so the
  defaults are some fifteen times the position error and about the velocity error of the planned
  toss).
  The robot's own motion is not perturbed: the joints execute the commands exactly (eq. (9)),
  so racket errors enter only through where the ball is when the racket arrives;
- the ball model's perturbations of each table bounce (``RallyParams.perturb``), seeded by the
  repeat's episode seed.

Sensor noise plays no part: the serve is open loop (the supervisor holds the serve's plan to its
end and the policy, which never acts here, is the only reader of the sensors), so the perception
is the cheap statistical model. The umpire of the diagram (``SegmentUmpire``) judges each repeat
from the ball's contacts: a good service has no decision once the ball bounced on the receiver's
court (the server's court first); a net touch is a let and counts as a failure, as is any fault.
Each repeat's randomness comes from ``[seed, serve index, repeat]`` alone, so the figures do not
depend on the batch size or the order of play.

Saved as ``serve_library.npz`` (the commands and a JSON header of everything else) with its
sidecar ``serve_library.json`` (``artefacts.write_sidecar``: command, seed, date, the measured
figures, the npz's sha256, and the header for reading). ``load_serve_library`` checks that the
file was made for the scenario's robot (joint names, and a fingerprint of the scenario's fields
and model files: the commands are joint positions of that robot); a library made for another
robot is re-made from its genes by ``analysis.serve_search.replan_serves``, which reads it
unchecked (``scenario=None``).

Selection (``choose_serve``): the paper selects "based on either their dissimilarity from recent
past serves or rally-winning probability estimated from previous experiments" (its Supplementary
Information 1.8.1, not public, gives the details). Here the dissimilarity: each serve's measured
landing (x, y), speed, topspin and sidespin at the receiver's bounce, scaled (``FEATURE_SCALES``),
its distance to the nearest of the recent serves; a serve is drawn with probability proportional
to that distance (never the same serve as a recent one while another exists; uniform when there
is no history). The rally-winning probability needs match statistics that do not exist yet.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ace_drake import artefacts
from ace_drake.config import MODELS_DIR, InputError
from ace_drake.control.params import ControlParams, RallyParams
from ace_drake.control.serve import TossState, simulate_serve, spin_components, strike_from_genes
from ace_drake.control.serve_execution import ServeStart, TossPlan, plan_strike, serve_episode_start
from ace_drake.control.stack import ControlStack
from ace_drake.diagrams import build_segment_rally_diagram, make_segment_simulator, start_segment_episodes
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.play.scoring import HUMAN, ROBOT
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.robot.params import JOINT_NAMES, RobotScenario, scenario_mismatch, scenario_record
from ace_drake.robot.trajectory import JointTrajectory

DEFAULT_LIBRARY = MODELS_DIR / "serve_library.npz"
FORMAT_VERSION = 1
MAX_FAILURE = 0.05  # the paper's bar: a serve joins the library if it fails less than 5% of the time
SERVE_TIME_LIMIT = 2.5  # s of episode time to a decision or a good service (a serve takes < 1.5 s)
# choose_serve's scales of the measured features: landing x, y (m), speed (m/s), topspin,
# sidespin (rad/s) at the receiver's bounce.
FEATURE_SCALES = np.array([0.2, 0.2, 1.0, 50.0, 50.0])


@dataclasses.dataclass(frozen=True)
class ExecutionNoise:
    """The released ball's deviation from the executed release, per repeat (module docstring):
    independent zero-mean Gaussians per axis. position: m. velocity: m/s."""

    position: float = 0.002
    velocity: float = 0.02

    def __post_init__(self) -> None:
        for name in ("position", "velocity"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"ExecutionNoise.{name} must be a finite standard deviation >= 0, got {value!r}")

    def perturb(self, release: TossState, rng: np.random.Generator) -> TossState:
        """``release`` with its position and velocity drawn around it."""
        return TossState(release.position + rng.normal(0.0, self.position, 3), release.velocity + rng.normal(0.0, self.velocity, 3), release.spin)


@dataclasses.dataclass(frozen=True)
class ServeStats:
    """A serve's measured figures over ``repeats`` noisy executions (``execute_serves``).

    good, lets, faults: counts (good + lets + faults = repeats; a repeat that reached no decision
    and no good service within ``SERVE_TIME_LIMIT`` is a fault). reasons: the umpire's reason of
    each let and fault, counted. Of the good services, at the ball's bounce on the receiver's
    court (just before it): landing_mean, landing_std (x, y) m; speed_mean, speed_std m/s;
    topspin_mean, topspin_std, sidespin_mean, sidespin_std rad/s (``control.serve.spin_components``:
    > 0 topspin, < 0 backspin; sidespin about +z). NaN when there is no good service.
    """

    repeats: int
    good: int
    lets: int
    faults: int
    reasons: dict
    landing_mean: np.ndarray
    landing_std: np.ndarray
    speed_mean: float
    speed_std: float
    topspin_mean: float
    topspin_std: float
    sidespin_mean: float
    sidespin_std: float

    @property
    def legal_fraction(self) -> float:
        return self.good / self.repeats

    @property
    def let_fraction(self) -> float:
        return self.lets / self.repeats

    @property
    def fault_fraction(self) -> float:
        return self.faults / self.repeats

    @property
    def failure_fraction(self) -> float:
        """Lets and faults: what the paper's 5% bounds."""
        return 1.0 - self.legal_fraction

    @property
    def features(self) -> np.ndarray:
        """(landing x, landing y, speed, topspin, sidespin): ``choose_serve``'s description."""
        return np.array([*self.landing_mean, self.speed_mean, self.topspin_mean, self.sidespin_mean], dtype=float)

    def as_dict(self) -> dict:
        """Plain JSON data: the counts, the fractions and the figures."""
        return {
            "repeats": self.repeats, "good": self.good, "lets": self.lets, "faults": self.faults,
            "legal_fraction": self.legal_fraction, "let_fraction": self.let_fraction, "fault_fraction": self.fault_fraction,
            "reasons": dict(self.reasons),
            "landing_mean_m": self.landing_mean.tolist(), "landing_std_m": self.landing_std.tolist(),
            "speed_mean_m_s": self.speed_mean, "speed_std_m_s": self.speed_std,
            "topspin_mean_rad_s": self.topspin_mean, "topspin_std_rad_s": self.topspin_std,
            "sidespin_mean_rad_s": self.sidespin_mean, "sidespin_std_rad_s": self.sidespin_std,
        }

    @staticmethod
    def from_dict(data: dict) -> ServeStats:
        def number(key):
            value = data[key]
            return math.nan if value is None else float(value)

        def pair(key):
            return np.array([math.nan if v is None else float(v) for v in data[key]], dtype=float)

        return ServeStats(int(data["repeats"]), int(data["good"]), int(data["lets"]), int(data["faults"]),
                          {str(k): int(v) for k, v in data["reasons"].items()}, pair("landing_mean_m"), pair("landing_std_m"),
                          number("speed_mean_m_s"), number("speed_std_m_s"), number("topspin_mean_rad_s"), number("topspin_std_rad_s"),
                          number("sidespin_mean_rad_s"), number("sidespin_std_rad_s"))


@dataclasses.dataclass(frozen=True)
class LibraryServe:
    """One serve of the library.

    name: unique in its library (e.g. "long_topspin_3": kind and GA seed). kind: the GA's serve
    kind (``control.serve.SERVE_KINDS``). genes (9,): the strike's genes in [0, 1]. toss: the
    toss the GA assumed (TossState, the planned toss's intent). commands: the whole 1 kHz
    JointTrajectory from rest (toss, strike, follow-through) as the supervisor executes it.
    t_lift: the executed release, s from the commands' start. release: the ball's executed state
    there (TossState). seed: the GA's seed. fitness: its ball-level fitness (``serve_fitness``).
    stats: the measured ``ServeStats`` (None until ``execute_serves``).
    """

    name: str
    kind: str
    genes: np.ndarray
    toss: TossState
    commands: JointTrajectory
    t_lift: float
    release: TossState
    seed: int
    fitness: float
    stats: ServeStats | None = None

    def episode_start(self, physics: BallPhysicsParams, release: TossState | None = None) -> ServeStart:
        """The served point's first episode (``serve_episode_start``), the ball released in
        ``release`` (default the executed release; a perturbed one for a noisy repeat)."""
        return serve_episode_start(self.commands, self.t_lift, self.release if release is None else release, physics)


@dataclasses.dataclass(frozen=True)
class ServeLibrary:
    """Serves (their names unique) for one robot: ``scenario`` is ``scenario_record`` of the
    RobotScenario they were planned for; ``repeats``, ``seed`` and ``noise`` describe how their
    stats were measured (0, 0, None before)."""

    serves: tuple[LibraryServe, ...]
    scenario: dict
    repeats: int = 0
    seed: int = 0
    noise: ExecutionNoise | None = None

    def __post_init__(self) -> None:
        names = [serve.name for serve in self.serves]
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise InputError(f"ServeLibrary: serve names must be unique, got {', '.join(duplicates)} more than once")
        object.__setattr__(self, "serves", tuple(self.serves))

    def __len__(self) -> int:
        return len(self.serves)

    def __getitem__(self, name: str) -> LibraryServe:
        for serve in self.serves:
            if serve.name == name:
                return serve
        raise KeyError(f"no serve named {name!r}; the library has {', '.join(s.name for s in self.serves)}")

    @property
    def names(self) -> list[str]:
        return [serve.name for serve in self.serves]

    def with_stats(self, stats: Sequence[ServeStats], repeats: int, seed: int, noise: ExecutionNoise) -> ServeLibrary:
        """The library with each serve's measured stats (in its order)."""
        if len(stats) != len(self.serves):
            raise ValueError(f"ServeLibrary.with_stats: {len(self.serves)} serves but {len(stats)} stats")
        serves = tuple(dataclasses.replace(serve, stats=s) for serve, s in zip(self.serves, stats))
        return ServeLibrary(serves, self.scenario, repeats, seed, noise)

    def subset(self, names: Sequence[str]) -> ServeLibrary:
        """The serves named ``names``, in that order."""
        return dataclasses.replace(self, serves=tuple(self[name] for name in names))


# ---------------------------------------------------------------------------------- the robot
def plan_serve(model: RobotModel, stack: ControlStack, toss: TossPlan, name: str, kind: str, genes, seed: int = 0, fitness: float = math.nan,
               physics: BallPhysicsParams | None = None) -> LibraryServe:
    """The serve of ``genes`` made by the robot after the planned toss ``toss`` (``plan_strike``
    of the strike the genes give from ``toss.intended``). Raises RuntimeError saying why the
    robot cannot make it: the planner's own errors (IK, a hit before the strike's first segment),
    a segment the control stack refused, a racket that touches the tossed ball before the hit,
    or an executed racket state (``StrikePlan.executed_strike``, from the executed release) whose
    serve is not legal at the ball level (``simulate_serve``): the drive cannot reach every
    strike the GA finds (too early after the release to reach the speed, too low or too far),
    and the ball-level GA does not know it."""
    physics = toss.physics if physics is None else physics
    genes = np.asarray(genes, dtype=float)
    plan = plan_strike(model, stack, toss, strike_from_genes(genes, toss.intended, physics))
    refused = [reason for reason in plan.commands.reasons if reason]
    if refused:
        raise RuntimeError(f"the control stack refused a strike segment: {refused[0]}")
    if not plan.ball_clearance > 0.0:
        raise RuntimeError("the racket touches the tossed ball before the hit")
    executed = simulate_serve(plan.executed_strike, toss.release, physics)
    if not executed.legal:
        raise RuntimeError(f"the executed strike's serve is not legal at the ball level: {executed.reason} "
                           f"(racket off by {1e3 * np.linalg.norm(plan.position_error):.1f} mm, {math.degrees(plan.normal_error):.2f} deg, "
                           f"{np.linalg.norm(plan.mean_velocity_error):.2f} m/s)")
    return LibraryServe(name, kind, genes.copy(), toss.intended, plan.commands.plan, float(toss.t_lift), toss.release, int(seed), float(fitness))


# ---------------------------------------------------------------------------------- measuring
def serve_rally_params(physics: BallPhysicsParams | None = None, perturb: bool = True, scenario: str = "scenario.yaml",
                       control: ControlParams | None = None) -> RallyParams:
    """The segment-stepped diagram's params for serves: statistical positions (the sensors do not
    matter, module docstring), no hit prediction (the policy never acts), the ball's post-table
    perturbations when ``perturb``."""
    return RallyParams(physics=BallPhysicsParams() if physics is None else physics, perturb=perturb, scenario=scenario,
                       control=ControlParams() if control is None else control, perception=PerceptionParams(positions="statistical"),
                       hit_prediction=False, stepping="segment")


def repeat_draw(seed: int, serve_index: int, repeat: int) -> tuple[np.random.Generator, int]:
    """The generator of a repeat's execution noise and its episode seed (module docstring)."""
    rng = np.random.default_rng([int(seed), int(serve_index), int(repeat)])
    return rng, int(rng.integers(0, 2**31 - 1))


@dataclasses.dataclass(frozen=True)
class ServeRun:
    """One executed repeat: ``outcome`` "good", "let" or "fault", the umpire's ``reason``, and
    for a good service the ball's state (9,) just before its bounce on the receiver's court."""

    outcome: str
    reason: str
    bounce: np.ndarray | None


def run_serves(starts: Sequence[tuple[ServeStart, int]], params: RallyParams, batch: int = 32,
               progress: Callable[[int], None] | None = None) -> list[ServeRun]:
    """Plays each (episode start, episode seed) once on one segment-stepped rally diagram of
    ``batch`` environments (a policy that never acts), a new one starting in an environment in
    the tick after its last was judged, and returns each ``ServeRun`` in order. ``progress(k)``
    after each tick that ended k."""
    if batch < 1:
        raise InputError(f"run_serves: batch must be >= 1, got {batch}")
    if params.stepping != "segment":
        raise InputError(f"run_serves: needs the segment-stepped diagram (params.stepping 'segment'), got {params.stepping!r}")
    batch = min(batch, max(1, len(starts)))
    diagram = build_segment_rally_diagram(params, lambda observation: None, batch)
    simulator = make_segment_simulator(diagram)
    context = simulator.get_mutable_context()
    diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(batch))
    umpire, ball, clock = (diagram.GetSubsystemByName(name) for name in ("umpire", "ball", "episode_clock"))
    ticks_limit = int(math.ceil(SERVE_TIME_LIMIT / clock.timing.duration))
    runs: list[ServeRun | None] = [None] * len(starts)
    playing = np.full(batch, -1)
    ticks = np.zeros(batch, dtype=int)
    queue = iter(range(len(starts)))

    def start(rows) -> None:
        chosen = [(row, index) for row in rows if (index := next(queue, None)) is not None]
        for row in rows:
            playing[row] = -1
        if not chosen:
            return
        rows_ = np.array([row for row, _ in chosen])
        for row, index in chosen:
            playing[row], ticks[row] = index, 0
        serve_starts = [starts[index][0] for _, index in chosen]
        start_segment_episodes(diagram, context, rows_, np.array([s.ball for s in serve_starts]), np.array([starts[index][1] for _, index in chosen]),
                               planned=[s.planned for s in serve_starts])
        umpire.StartPoints(umpire.GetMyMutableContextFromRoot(context), rows_, [ROBOT] * len(rows_), [s.toss for s in serve_starts])

    start(list(range(batch)))
    simulator.Initialize()
    tick = 0
    while np.any(playing >= 0):
        tick += 1
        simulator.AdvanceTo(tick * clock.timing.duration)
        ticks += 1
        umpires = umpire.umpires_port.Eval(umpire.GetMyContextFromRoot(context))
        events = ball.plant_state(ball.GetMyContextFromRoot(context)).events
        ended = []
        for row in np.flatnonzero(playing >= 0):
            judge = umpires[row]
            run = None
            if judge.decision is not None:
                run = ServeRun("let" if judge.decision.let else "fault", judge.decision.reason, None)
            elif judge.bounced and judge.to_play == HUMAN:
                bounce = next(e.state_pre for e in events[row] if ContactKind(e.kind) == ContactKind.TABLE and e.state_pre[0] > 0.0)
                run = ServeRun("good", "good service", np.array(bounce, dtype=float))
            elif ticks[row] >= ticks_limit:
                run = ServeRun("fault", f"no good service or decision within {SERVE_TIME_LIMIT} s", None)
            if run is not None:
                runs[playing[row]] = run
                ended.append(row)
        if ended:
            umpire.ClosePoints(umpire.GetMyMutableContextFromRoot(context), ended)
            start(ended)
            if progress is not None:
                progress(len(ended))
    return runs


def serve_stats(runs: Sequence[ServeRun]) -> ServeStats:
    """The ``ServeStats`` of one serve's repeats."""
    outcomes = Counter(run.outcome for run in runs)
    reasons = Counter(run.reason for run in runs if run.outcome != "good")
    bounces = np.array([run.bounce for run in runs if run.outcome == "good"]).reshape(-1, 9)
    speed = np.linalg.norm(bounces[:, 3:6], axis=1)
    spin = spin_components(bounces)

    def mean_std(values):
        return (float(np.mean(values, axis=0)), float(np.std(values, axis=0))) if len(values) else (math.nan, math.nan)

    landing_mean = bounces[:, :2].mean(axis=0) if len(bounces) else np.full(2, math.nan)
    landing_std = bounces[:, :2].std(axis=0) if len(bounces) else np.full(2, math.nan)
    return ServeStats(len(runs), outcomes["good"], outcomes["let"], outcomes["fault"], dict(sorted(reasons.items())),
                      landing_mean, landing_std, *mean_std(speed), *mean_std(spin[:, 0]), *mean_std(spin[:, 1]))


def execute_serves(library: ServeLibrary, repeats: int = 50, seed: int = 0, params: RallyParams | None = None,
                   noise: ExecutionNoise | None = None, batch: int = 32, progress: Callable[[str], None] | None = None) -> ServeLibrary:
    """Every serve of ``library`` executed ``repeats`` times on the segment-stepped rally diagram
    (module docstring: execution noise ``noise``, default ``ExecutionNoise()``; the ball's
    perturbations per ``params``, default ``serve_rally_params()``), ``batch`` at once; returns
    the library with each serve's ``ServeStats``. Deterministic for a seed, whatever ``batch``.
    ``progress`` (None: silent) receives a line now and then."""
    if repeats < 1:
        raise InputError(f"execute_serves: repeats must be >= 1, got {repeats}")
    params = serve_rally_params() if params is None else params
    noise = ExecutionNoise() if noise is None else noise
    starts, owner = [], []
    for index, serve in enumerate(library.serves):
        for repeat in range(repeats):
            rng, episode_seed = repeat_draw(seed, index, repeat)
            starts.append((serve.episode_start(params.physics, noise.perturb(serve.release, rng)), episode_seed))
            owner.append(index)
    done = 0
    step = max(1, len(starts) // 10)

    def count(ended: int) -> None:
        nonlocal done
        before, done = done, done + ended
        if progress is not None and (done // step > before // step or done == len(starts)):
            progress(f"serves: executed {done}/{len(starts)} ({len(library)} serves x {repeats} repeats)")

    runs = run_serves(starts, params, batch, count)
    stats = [serve_stats([run for run, o in zip(runs, owner) if o == index]) for index in range(len(library))]
    return library.with_stats(stats, repeats, seed, noise)


def passing(library: ServeLibrary, max_failure: float = MAX_FAILURE) -> list[str]:
    """Names of the serves measured to fail (let or fault) less than ``max_failure`` of the time."""
    return [s.name for s in library.serves if s.stats is not None and s.stats.failure_fraction < max_failure]


# ---------------------------------------------------------------------------------- choosing
def choose_serve(library: ServeLibrary, recent_names: Sequence[str], rng: np.random.Generator, recent: int = 3) -> LibraryServe:
    """The next serve (module docstring): drawn with probability proportional to its scaled
    feature distance to the nearest of the last ``recent`` of ``recent_names`` (oldest first;
    names not in the library are ignored); uniform without history or when every serve was
    served recently."""
    if len(library) == 0:
        raise InputError("choose_serve: the serve library is empty")
    known = [name for name in recent_names if any(s.name == name for s in library.serves)][-recent:] if recent > 0 else []
    if not known:
        return library.serves[int(rng.integers(len(library)))]
    features = np.array([_features(serve) for serve in library.serves]) / FEATURE_SCALES
    past = np.array([_features(library[name]) for name in known]) / FEATURE_SCALES
    distance = np.nan_to_num(np.linalg.norm(features[:, None, :] - past[None, :, :], axis=-1).min(axis=1))
    distance[[serve.name in known for serve in library.serves]] = 0.0
    if not distance.sum() > 0.0:
        return library.serves[int(rng.integers(len(library)))]
    return library.serves[int(rng.choice(len(library), p=distance / distance.sum()))]


def _features(serve: LibraryServe) -> np.ndarray:
    if serve.stats is None:
        raise InputError(f"choose_serve: serve {serve.name!r} has no measured stats (run execute_serves)")
    return np.nan_to_num(serve.stats.features)


# ---------------------------------------------------------------------------------- files
def _toss_dict(toss: TossState) -> dict:
    return {"position_m": toss.position.tolist(), "velocity_m_s": toss.velocity.tolist(), "spin_rad_s": toss.spin.tolist()}


def _toss_from(data: dict) -> TossState:
    return TossState(np.array(data["position_m"], dtype=float), np.array(data["velocity_m_s"], dtype=float), np.array(data["spin_rad_s"], dtype=float))


def library_header(library: ServeLibrary) -> dict:
    """Everything of ``library`` but the commands, as plain JSON data."""
    serves = []
    for serve in library.serves:
        serves.append({
            "name": serve.name, "kind": serve.kind, "genes": serve.genes.tolist(), "seed": serve.seed, "fitness": serve.fitness,
            "toss": _toss_dict(serve.toss), "t_lift_s": serve.t_lift, "release": _toss_dict(serve.release),
            "command_period_s": serve.commands.period, "command_samples": serve.commands.samples,
            "stats": None if serve.stats is None else serve.stats.as_dict(),
        })
    noise = None if library.noise is None else {"position_m": library.noise.position, "velocity_m_s": library.noise.velocity}
    return {"format": "ace_drake serve library", "version": FORMAT_VERSION, "scenario": library.scenario,
            "repeats": library.repeats, "seed": library.seed, "execution_noise": noise, "serves": serves}


def save_serve_library(library: ServeLibrary, path=DEFAULT_LIBRARY, seed: int | None = None, **fields) -> dict:
    """Writes ``library`` to ``path`` (.npz: each serve's commands q, v, a and the JSON header;
    through a temporary file renamed into place, so that no half-written library is left) and
    then its sidecar (``artefacts.write_sidecar``: provenance, ``seed``, the per-serve figures,
    the header and ``fields``). Returns the sidecar."""
    path = Path(path)
    if path.suffix != ".npz":
        raise InputError(f"a serve library is written as a .npz file, got {path}")
    header = library_header(library)
    arrays = {"header": np.array(json.dumps(header))}
    for index, serve in enumerate(library.serves):
        arrays[f"q_{index}"], arrays[f"v_{index}"], arrays[f"a_{index}"] = serve.commands.q, serve.commands.v, serve.commands.a
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".npz")
    os.close(handle)
    try:
        np.savez_compressed(temporary, **arrays)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # mkstemp's file is private; a library is not
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)
    figures = {serve.name: None if serve.stats is None else serve.stats.as_dict() for serve in library.serves}
    return artefacts.write_sidecar(path, seed=seed, figures=figures, header=header, **fields)


def load_serve_library(path, scenario: RobotScenario | None) -> ServeLibrary:
    """The library saved at ``path`` (its .npz; a .json path means its sidecar's artefact),
    checked against the robot ``scenario``. Raises InputError naming the file and the problem:
    missing, not a serve library or malformed, or made for another robot. ``scenario=None``
    skips the last check: the library as saved, its ``scenario`` the record of the robot it was
    made for, whose joint positions its commands are; only for reading its genes and figures
    (``analysis.serve_search.replan_serves``), never to execute on another robot."""
    path = Path(path)
    if path.suffix == ".json":
        path = path.with_suffix(".npz")
    if not path.is_file():
        raise InputError(f"serve library {path} does not exist (make one with `ace-drake serves search`)")
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            if header.get("format") != "ace_drake serve library":
                raise ValueError("its header is not a serve library's")
            if header.get("version") != FORMAT_VERSION:
                raise ValueError(f"its format version is {header.get('version')}, this code reads {FORMAT_VERSION}")
            mismatch = None if scenario is None else scenario_mismatch(header["scenario"], scenario_record(scenario))
            if mismatch is not None:
                raise _OtherRobot(mismatch)
            serves = []
            for index, entry in enumerate(header["serves"]):
                commands = JointTrajectory(float(entry["command_period_s"]), data[f"q_{index}"], data[f"v_{index}"], data[f"a_{index}"])
                if commands.samples != int(entry["command_samples"]):
                    raise ValueError(f"serve {entry['name']!r} has {commands.samples} command samples, its header says {entry['command_samples']}")
                genes = np.array(entry["genes"], dtype=float)
                if genes.shape != (9,):
                    raise ValueError(f"serve {entry['name']!r} has {genes.size} genes, not 9")
                stats = None if entry["stats"] is None else ServeStats.from_dict(entry["stats"])
                serves.append(LibraryServe(str(entry["name"]), str(entry["kind"]), genes, _toss_from(entry["toss"]), commands,
                                           float(entry["t_lift_s"]), _toss_from(entry["release"]), int(entry["seed"]),
                                           math.nan if entry["fitness"] is None else float(entry["fitness"]), stats))
            noise = header["execution_noise"]
            noise = None if noise is None else ExecutionNoise(float(noise["position_m"]), float(noise["velocity_m_s"]))
            return ServeLibrary(tuple(serves), header["scenario"], int(header["repeats"]), int(header["seed"]), noise)
    except _OtherRobot as error:
        raise InputError(f"serve library {path} was made for another robot: {error} (re-make it from its genes with `ace-drake serves replan`)") from None
    except InputError:
        raise
    except Exception as error:  # a truncated zip, a missing key, a bad value: the file is malformed
        raise InputError(f"serve library {path} is malformed: {type(error).__name__}: {error}") from None


class _OtherRobot(Exception):
    pass


def evaluate_library(path=DEFAULT_LIBRARY, repeats: int = 50, seed: int = 0, batch: int = 32, scenario: RobotScenario | None = None,
                     progress: Callable[[str], None] | None = None) -> dict:
    """``ace-drake serves evaluate``: the library at ``path`` loaded for ``scenario`` (default
    models/scenario.yaml's robot), every serve executed ``repeats`` times (``execute_serves``,
    ``seed``, the library's recorded execution noise or the default), as plain JSON data: the
    settings and ``serves``, a row per serve with its name, kind and ``ServeStats.as_dict``."""
    library = load_serve_library(path, load_scenario() if scenario is None else scenario)
    noise = ExecutionNoise() if library.noise is None else library.noise
    measured = execute_serves(library, repeats, seed, serve_rally_params(), noise, batch, progress)
    rows = [{"name": serve.name, "kind": serve.kind, **serve.stats.as_dict()} for serve in measured.serves]
    return {"library": str(path), "repeats": repeats, "seed": seed,
            "execution_noise": {"position_m": noise.position, "velocity_m_s": noise.velocity},
            "passing": len(passing(measured)), "max_failure": MAX_FAILURE, "serves": rows}
