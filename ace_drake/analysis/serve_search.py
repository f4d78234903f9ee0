"""The serve's strike found offline by a genetic algorithm (paper, Methods *Serve design*), with
PyGAD, the authors' library, and their settings (notes.md): 9 genes in [0, 1], 100 generations,
6 parents mating, 3 genes of each offspring mutated by up to +-0.2, a stop once the best fitness
has not improved for 40 generations.

The genes, the simulation and the fitness are ``control.serve``'s (``strike_from_genes``,
``simulate_serves``, ``serve_fitness`` with a kind's ``ServeWeights``); each generation's new
solutions are simulated in one batch (PyGAD's ``fitness_batch_size`` is the population).

PyGAD details: the initial population is uniform in [0, 1]. With a continuous ``gene_space`` PyGAD
replaces a mutated gene by a fresh sample of the space, which is not the authors' "+-0.2", so the
space is given instead as the initial range (``init_range_low`` / ``init_range_high``) and PyGAD's
additive random mutation (``mutation_by_replacement=False``, ``random_mutation_min_val=-0.2``,
``random_mutation_max_val=0.2``, ``mutation_num_genes=3``) is followed by a clip of the mutated
offspring to [0, 1] (``on_mutation``); crossover (single point) keeps genes in [0, 1]. Parent
selection (steady state), crossover and elitism (the best solution kept) are PyGAD's defaults,
the population (``population``, default ``POPULATION``) the paper does not give. ``random_seed``
seeds PyGAD's generators, and the simulation is deterministic: the same seed gives the same genes
bit for bit.

``search_serves`` makes the serve library (``evaluation.serves``) from these searches: the robot
plans each legal result after one toss and the segment-stepped diagram executes it with noise; the
serves failing less than 5% of the time (the paper's bar), distinct in their measured landing,
speed and spin, are kept (``ace-drake serves search``). ``replan_serves`` re-makes a saved library
on the current robot from its own genes, which describe the strike at ball level and do not depend
on the robot (``ace-drake serves replan``: after a change of the robot model, hours of GA searches
are not run again). They live here, above the evaluation layer they call.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pygad

from ace_drake.control.serve import (
    SERVE_GENES,
    ServeOutcome,
    Strike,
    TossState,
    evaluate_genes,
    serve_fitness,
    serve_weights,
    simulate_serves,
    strike_from_genes,
)
from ace_drake import artefacts
from ace_drake.config import MODELS_DIR, InputError
from ace_drake.control.params import RallyParams
from ace_drake.control.serve_execution import TossPlan, plan_strike, plan_toss
from ace_drake.control.stack import ControlStack, make_control_stack
from ace_drake.evaluation.serves import (
    FEATURE_SCALES,
    MAX_FAILURE,
    ExecutionNoise,
    LibraryServe,
    ServeLibrary,
    execute_serves,
    passing,
    plan_serve,
    load_serve_library,
    save_serve_library,
    serve_rally_params,
)
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.robot.params import scenario_record

GENERATIONS = 100  # the authors' setting
PARENTS_MATING = 6  # the authors' setting
MUTATION_GENES = 3  # the authors' setting: genes mutated per offspring
MUTATION_STEP = 0.2  # the authors' setting: a mutated gene moves by up to this, either way
SATURATION = 40  # the authors' setting: generations without improvement before stopping
POPULATION = 50  # solutions per generation (chosen: the paper gives none)
EXECUTED_RELEASES = 8  # search_serves(executed=True): releases each strike is scored from (the planned one and 7 perturbed)


@dataclasses.dataclass(frozen=True)
class SearchResult:
    """One serve search.

    kind: the serve kind (``control.serve.SERVE_KINDS``). seed: PyGAD's random seed. genes (9,):
    the best solution, in [0, 1]. strike, outcome: its strike and simulated serve. fitness: its
    fitness. fitness_history: the best fitness after each generation (the initial population's
    first). generations: generations run (fewer than asked when the best saturated).
    """

    kind: str
    seed: int
    genes: np.ndarray
    strike: Strike
    outcome: ServeOutcome
    fitness: float
    fitness_history: np.ndarray
    generations: int

    @property
    def legal(self) -> bool:
        """Whether the best serve is legal (``ServeOutcome.legal``)."""
        return self.outcome.legal


class ExecutedStrikes:
    """The GA's fitness on what the robot makes of each strike (the paper's: its racket-space
    trajectory from the state at t_lift, executed and the serve simulated): each solution's strike
    planned after the planned toss ``toss`` (``plan_strike``: IK, the drive through the control
    stack, the joints' exact response), and the serve of the executed racket state
    (``StrikePlan.executed_strike``) from the executed release simulated and scored
    (``serve_fitness``). A strike the robot cannot make (the planner fails, the stack refuses a
    segment, the racket touches the tossed ball early) scores 0, below every serve it makes.
    With ``releases`` > 1 the serve is also simulated from that many releases perturbed by
    ``noise`` (drawn once from ``seed``: every solution meets the same ones) and scores its mean
    fitness, so that the GA prefers strikes that stay legal under the execution noise the library
    is judged with. About 0.05 s a solution, against 0.002 s at the ball level."""

    def __init__(self, model: RobotModel, stack, toss, physics: BallPhysicsParams, noise: ExecutionNoise | None = None,
                 releases: int = 1, seed: int = 0):
        self.model, self.stack, self.toss, self.physics = model, stack, toss, physics
        rng = np.random.default_rng(seed)
        noise = ExecutionNoise() if noise is None else noise
        self.releases = [toss.release] + [noise.perturb(toss.release, rng) for _ in range(releases - 1)]

    def evaluate(self, genes, weights) -> tuple[np.ndarray, list[ServeOutcome | None]]:
        """Fitness (N,) and outcomes (None where the robot cannot make the strike) of genes (N, 9)."""
        genes = np.atleast_2d(np.asarray(genes, dtype=float))
        strikes, made = [], []
        for index, gene in enumerate(genes):
            try:
                plan = plan_strike(self.model, self.stack, self.toss, strike_from_genes(gene, self.toss.intended, self.physics))
            except (RuntimeError, ValueError):
                continue
            if any(plan.commands.reasons) or not plan.ball_clearance > 0.0:
                continue
            strikes.append(plan.executed_strike)
            made.append(index)
        fitness, outcomes = np.zeros(len(genes)), [None] * len(genes)
        if strikes:
            executed = Strike(np.array([s.time for s in strikes]), np.array([s.p_WR for s in strikes]), np.array([s.R_WR for s in strikes]),
                              np.array([s.v_WR for s in strikes]))
            scores = np.zeros(len(made))
            for k, release in enumerate(self.releases):
                for j, outcome in enumerate(simulate_serves(executed, release, self.physics)):
                    scores[j] += serve_fitness(outcome, weights) / len(self.releases)
                    if k == 0:
                        outcomes[made[j]] = outcome  # the serve from the planned release
            fitness[made] = scores
        return fitness, outcomes


def search_serve(
    kind: str,
    toss: TossState | None = None,
    physics: BallPhysicsParams | None = None,
    seed: int = 0,
    generations: int = GENERATIONS,
    population: int = POPULATION,
    progress: Callable[[str], None] | None = print,
    robot: ExecutedStrikes | None = None,
) -> SearchResult:
    """The best strike of a serve ``kind`` found by PyGAD with the authors' settings (module
    docstring), from the toss ``toss`` (default ``TossState()``) under ``physics`` (default the
    paper's). ``progress`` (None: silent) receives a line per generation: its number, the best
    fitness and whether that serve is legal. ``robot``: score the strikes the robot makes
    (``ExecutedStrikes``) instead of the ball-level ones."""
    weights = serve_weights(kind)
    toss = TossState() if toss is None else toss
    physics = BallPhysicsParams() if physics is None else physics
    if generations < 1:
        raise ValueError(f"search_serve: generations must be >= 1, got {generations}")
    if population <= PARENTS_MATING:
        raise ValueError(f"search_serve: population must exceed the {PARENTS_MATING} parents mating, got {population}")

    def evaluate(genes):
        return evaluate_genes(genes, toss, physics, weights) if robot is None else robot.evaluate(genes, weights)

    def fitness_batch(ga, solutions, indices):
        fitness, _ = evaluate(np.asarray(solutions, dtype=float))
        return fitness.tolist()

    def clip_offspring(ga, offspring):
        np.clip(offspring, 0.0, 1.0, out=offspring)  # PyGAD keeps this array (returns None)

    def report(ga):
        if progress is not None:
            best = float(np.max(ga.last_generation_fitness))
            progress(f"{kind} seed {seed}: generation {ga.generations_completed:3d}  best fitness {best:.4f}  "
                     f"({'legal' if best >= 1.0 else 'illegal'})")

    ga = pygad.GA(
        num_generations=generations,
        num_parents_mating=PARENTS_MATING,
        sol_per_pop=population,
        num_genes=SERVE_GENES,
        fitness_func=fitness_batch,
        fitness_batch_size=population,
        init_range_low=0.0,
        init_range_high=1.0,
        gene_type=float,
        mutation_type="random",
        mutation_num_genes=MUTATION_GENES,
        mutation_by_replacement=False,
        random_mutation_min_val=-MUTATION_STEP,
        random_mutation_max_val=MUTATION_STEP,
        on_mutation=clip_offspring,
        on_generation=report,
        stop_criteria=f"saturate_{SATURATION}",
        random_seed=seed,
        suppress_warnings=True,
    )
    ga.run()
    genes, fitness, _ = ga.best_solution(pop_fitness=ga.last_generation_fitness)
    genes = np.clip(np.asarray(genes, dtype=float), 0.0, 1.0)
    strike = strike_from_genes(genes, toss, physics)
    check, (outcome,) = evaluate(genes[None])
    if outcome is None:  # the robot could make none of the population's strikes
        _, (outcome,) = evaluate_genes(genes[None], toss, physics, weights)
        outcome = dataclasses.replace(outcome, legal=False)
    return SearchResult(kind, seed, genes, strike, outcome, float(check[0]),
                        np.asarray(ga.best_solutions_fitness[:ga.generations_completed + 1], dtype=float), int(ga.generations_completed))


def search_library(
    kinds: Iterable[str],
    seeds: Iterable[int],
    toss: TossState | None = None,
    physics: BallPhysicsParams | None = None,
    generations: int = GENERATIONS,
    population: int = POPULATION,
    min_gene_distance: float = 0.05,
    progress: Callable[[str], None] | None = print,
    robot: ExecutedStrikes | None = None,
) -> list[SearchResult]:
    """A serve library: ``search_serve`` for every kind and seed, keeping the legal results, best
    first within each kind, without any whose genes lie within ``min_gene_distance`` (Euclidean,
    in [0, 1]^9) of a kept one of the same kind; ``robot``: ``search_serve``'s."""
    kinds, seeds = list(kinds), list(seeds)
    for kind in kinds:
        serve_weights(kind)  # a bad name fails before any search
    library: list[SearchResult] = []
    for kind in kinds:
        results = [search_serve(kind, toss, physics, seed, generations, population, progress, robot) for seed in seeds]
        kept: list[SearchResult] = []
        for result in sorted((r for r in results if r.legal), key=lambda r: -r.fitness):
            if all(np.linalg.norm(result.genes - other.genes) >= min_gene_distance for other in kept):
                kept.append(result)
        library += kept
    return library


# ---------------------------------------------------------------------------------- the library
FEATURE_DISTANCE_MIN = 1.0  # search_serves: kept serves differ by at least this (scaled features, evaluation.serves)
_HISTORY_KEYS = ("command", "date", "search", "extends", "replan", "replanned_from")  # what a new library keeps of the sidecar it came from


def search_serves(
    kinds: Iterable[str],
    seeds: Iterable[int],
    repeats: int = 50,
    seed: int = 0,
    generations: int = GENERATIONS,
    population: int = POPULATION,
    toss: TossState | None = None,
    params: RallyParams | None = None,
    noise: ExecutionNoise | None = None,
    max_failure: float = MAX_FAILURE,
    batch: int = 32,
    out=None,
    extend=None,
    progress: Callable[[str], None] | None = print,
    executed: bool = False,
) -> tuple[ServeLibrary, dict]:
    """The serve library (paper, Methods *Serve design*, with the simulation in place of the
    real robot's trials): the GA for every kind and GA seed (``search_library``: the legal best
    serves, distinct in genes within a kind), each made by the robot after one planned toss
    (``evaluation.serves.plan_serve``; those it cannot make are dropped and counted by reason),
    executed ``repeats`` times with noise on the segment-stepped diagram (``execute_serves``,
    ``seed``), and kept if it fails less than ``max_failure`` of the time and its measured
    landing, speed and spin lie at least ``FEATURE_DISTANCE_MIN`` (scaled by
    ``FEATURE_SCALES``) from every better-scoring kept serve. Writes the library to ``out``
    (``save_serve_library``) when given. ``extend``: a saved library whose serves come first and
    stay (as measured then), the new ones distinct from them too, and any new serve of the same
    name (kind and GA seed) skipped. Returns it and a summary (counts at each stage, the planning
    failures' reasons, every candidate's figures). ``executed``: the GA scores the strikes the
    robot makes (``ExecutedStrikes``, the paper's; ~25 x slower), each from ``EXECUTED_RELEASES``
    releases perturbed by ``noise``, instead of the ball-level ones."""
    kinds, seeds = list(kinds), list(seeds)
    if not kinds:
        raise InputError("search_serves: at least one serve kind is needed")
    for kind in kinds:
        try:
            serve_weights(kind)  # a bad name fails before any search
        except ValueError as error:
            raise InputError(f"search_serves: {error}") from None
    if repeats < 1:
        raise InputError(f"search_serves: repeats must be >= 1, got {repeats}")
    if generations < 1:
        raise InputError(f"search_serves: generations must be >= 1, got {generations}")
    if not seeds:
        raise InputError("search_serves: at least one GA seed is needed")
    _check_out("search_serves", out)
    params = serve_rally_params() if params is None else params
    noise = ExecutionNoise() if noise is None else noise
    toss = TossState() if toss is None else toss
    say = progress if progress is not None else (lambda message: None)
    started = time.perf_counter()
    model, stack = _serve_robot(params)
    base = None if extend is None else load_serve_library(extend, model.scenario)  # a bad file fails before the search
    history = {} if extend is None else _history(extend)  # so does a bad sidecar
    if base is not None and (base.repeats, base.seed, base.noise) != (repeats, seed, noise):
        raise InputError(f"search_serves: the library to extend was measured with {base.repeats} repeats, seed {base.seed} and {base.noise}; "
                         f"this search uses {repeats}, {seed} and {noise}")
    (toss_plan,) = _toss_plans(model, stack, [toss], params.physics)
    robot = ExecutedStrikes(model, stack, toss_plan, params.physics, noise, EXECUTED_RELEASES, seed) if executed else None
    results = search_library(kinds, seeds, toss, params.physics, generations, population, progress=None if progress is None else _every(10, say),
                             robot=robot)
    say(f"serves: the GA found {len(results)} distinct legal serves ({len(kinds)} kinds x {len(seeds)} seeds, {time.perf_counter() - started:.0f} s)")
    requests = []
    for result in results:
        name = f"{result.kind}_{result.seed}"
        if base is not None and name in base.names:
            say(f"serves: {name} is in the library already; skipped")
            continue
        requests.append((toss_plan, name, result.kind, result.genes, result.seed, result.fitness))
    candidates, unplanned = _plan_serves(model, stack, requests, params.physics, say)
    say(f"serves: the robot made {len(candidates)} of them; executing each {repeats} times")
    measured = execute_serves(ServeLibrary(tuple(candidates), scenario_record(model.scenario)), repeats, seed, params, noise, batch, say)
    kept: list[LibraryServe] = [] if base is None else list(base.serves)
    for serve in sorted(measured.serves, key=lambda s: (s.stats.failure_fraction, -s.fitness)):
        if serve.stats.failure_fraction >= max_failure:
            continue
        features = np.nan_to_num(serve.stats.features) / FEATURE_SCALES
        if all(np.linalg.norm(features - np.nan_to_num(other.stats.features) / FEATURE_SCALES) >= FEATURE_DISTANCE_MIN for other in kept):
            kept.append(serve)
    kept_names = {serve.name for serve in kept}
    library = measured.subset([serve.name for serve in measured.serves if serve.name in kept_names])
    if base is not None:
        library = ServeLibrary(base.serves + library.serves, library.scenario, repeats, seed, noise)
    _report(measured, kept_names, say)
    summary = {
        "kinds": kinds, "ga_seeds": seeds, "ga_fitness": "executed" if executed else "ball", "generations": generations, "population": population, "repeats": repeats, "seed": seed,
        "max_failure": max_failure, "ga_legal": len(results), "planned": len(candidates), "unplanned_reasons": dict(Counter(unplanned.values())),
        "extended": None if extend is None else str(extend), "passed": len(passing(measured, max_failure)), "kept": len(library), "wall_time_s": time.perf_counter() - started,
        "candidates": {serve.name: serve.stats.as_dict() for serve in measured.serves},
    }
    if out is not None:
        summary_fields = {key: value for key, value in summary.items() if key != "candidates"}
        previous = {"extends": {key: history[key] for key in _HISTORY_KEYS if key in history}} if history else {}
        save_serve_library(library, out, seed=seed, search=summary_fields, candidates=summary["candidates"], **previous)
        say(f"serves: wrote {out} ({len(library)} serves) and its sidecar")
    return library, summary


def replan_serves(
    library,
    repeats: int | None = None,
    seed: int | None = None,
    params: RallyParams | None = None,
    noise: ExecutionNoise | None = None,
    max_failure: float = MAX_FAILURE,
    batch: int = 32,
    out=None,
    progress: Callable[[str], None] | None = print,
) -> tuple[ServeLibrary, dict]:
    """The serve library saved at ``library`` (its .npz or sidecar path) re-made on the current
    robot (``params.scenario``'s, default ``serve_rally_params()``) from its own genes, which
    describe the strike at ball level and do not depend on the robot. The library is read without
    the robot check (``load_serve_library(path, None)``; its commands are not used); each
    serve's genes are planned after its toss on this robot (``plan_serve``; those it cannot make
    are dropped and counted by reason), executed ``repeats`` times with ``noise`` on the
    segment-stepped diagram (``execute_serves``, ``seed``; each None: the library's own, as
    recorded, its noise ``ExecutionNoise()`` when none is), and kept if they fail less than
    ``max_failure`` of the time. The kept serves keep the library's order, names, kinds, genes,
    GA seeds and fitness; no distinctness rule is applied again (the serves were distinct when
    found). The same seed gives the same library. Writes it to ``out`` (``save_serve_library``;
    it may be ``library``) when given, its sidecar recording the summary (``replan``), every
    candidate's figures and ``replanned_from``: the old file's name and sha256 and its sidecar's
    command, date, search and history. Returns the library and a summary (``source``: the file
    read; the settings; ``serves_read``, ``planned`` and ``kept`` counts; the planning failures
    by serve and by reason; every candidate's figures; ``replanned_from``; the wall time in s)."""
    for name, value in (("repeats", repeats), ("batch", batch)):
        if value is not None and value < 1:
            raise InputError(f"replan_serves: {name} must be >= 1, got {value}")
    _check_out("replan_serves", out)
    params = serve_rally_params() if params is None else params
    say = progress if progress is not None else (lambda message: None)
    started = time.perf_counter()
    model, stack = _serve_robot(params)
    old = load_serve_library(library, None)  # a missing or malformed file fails here
    path = Path(library).with_suffix(".npz") if Path(library).suffix == ".json" else Path(library)  # as load_serve_library reads it
    replanned_from = {**artefacts.data_file(path), **{key: value for key, value in _history(path).items() if key in _HISTORY_KEYS}}
    if repeats is None and old.repeats < 1:
        raise InputError(f"replan_serves: {path} was never measured; give the repeats")
    repeats = old.repeats if repeats is None else repeats
    seed = old.seed if seed is None else seed
    noise = (ExecutionNoise() if old.noise is None else old.noise) if noise is None else noise
    robot = scenario_record(model.scenario)
    same = old.scenario.get("fingerprint") == robot["fingerprint"]
    say(f"serves: replanning {len(old)} serves of {path} (made for {'this' if same else 'another'} robot) on the robot of {params.scenario}")
    try:
        plans = _toss_plans(model, stack, [serve.toss for serve in old.serves], params.physics)
    except RuntimeError as error:
        raise InputError(f"replan_serves: the robot of {params.scenario} cannot make the library's toss: {error}") from None
    requests = [(plan, serve.name, serve.kind, serve.genes, serve.seed, serve.fitness) for plan, serve in zip(plans, old.serves)]
    candidates, unplanned = _plan_serves(model, stack, requests, params.physics, say)
    say(f"serves: the robot made {len(candidates)} of the {len(old)}; executing each {repeats} times")
    measured = execute_serves(ServeLibrary(tuple(candidates), robot), repeats, seed, params, noise, batch, say)
    kept = passing(measured, max_failure)
    replanned = measured.subset(kept)
    _report(measured, set(kept), say, before={serve.name: serve.stats for serve in old.serves})
    summary = {
        "source": path.name, "repeats": repeats, "seed": seed, "execution_noise": {"position_m": noise.position, "velocity_m_s": noise.velocity},
        "max_failure": max_failure, "serves_read": len(old), "planned": len(candidates), "unplanned": unplanned,
        "unplanned_reasons": dict(Counter(unplanned.values())), "kept": len(replanned), "wall_time_s": time.perf_counter() - started,
        "candidates": {serve.name: serve.stats.as_dict() for serve in measured.serves}, "replanned_from": replanned_from,
    }
    if out is not None and not len(replanned):
        raise InputError(f"replan_serves: none of the {len(old)} serves passed on this robot; {out} is left as it was "
                         "(search new serves with `ace-drake serves search`)")
    if out is not None:
        fields = {key: value for key, value in summary.items() if key not in ("candidates", "replanned_from")}
        save_serve_library(replanned, out, seed=seed, replan=fields, candidates=summary["candidates"], replanned_from=replanned_from)
        say(f"serves: wrote {out} ({len(replanned)} serves) and its sidecar")
    return replanned, summary


# ---------------------------------------------------------------------------------- shared steps
def _serve_robot(params: RallyParams) -> tuple[RobotModel, ControlStack]:
    """The robot the serves are planned on: the model of ``params.scenario`` (models/) and its
    control stack (``params.control``)."""
    model = RobotModel(load_scenario(MODELS_DIR / params.scenario))
    return model, make_control_stack(model.scenario, params.control)


def _toss_plans(model: RobotModel, stack: ControlStack, tosses: Iterable[TossState], physics: BallPhysicsParams) -> list[TossPlan]:
    """The robot's planned toss (``plan_toss``) of each of ``tosses`` (release states; positions m,
    velocities m/s, spins rad/s), in order, each distinct toss planned once. Raises RuntimeError
    if the robot cannot make one."""
    plans: dict[bytes, TossPlan] = {}
    result = []
    for toss in tosses:
        key = toss.state.tobytes()
        if key not in plans:
            plans[key] = plan_toss(model, stack, toss, physics=physics)
        result.append(plans[key])
    return result


def _plan_serves(model: RobotModel, stack: ControlStack, requests, physics: BallPhysicsParams,
                 say: Callable[[str], None]) -> tuple[list[LibraryServe], dict[str, str]]:
    """Each request (toss plan, name, kind, genes, GA seed, fitness) made by the robot
    (``plan_serve``), in order, and the names of those it cannot make with why (the error's first
    clause), each said."""
    candidates, unplanned = [], {}
    for toss_plan, name, kind, genes, ga_seed, fitness in requests:
        try:
            candidates.append(plan_serve(model, stack, toss_plan, name, kind, genes, ga_seed, fitness, physics))
        except RuntimeError as error:
            unplanned[name] = str(error).split(":")[0]
            say(f"serves: {name}: the robot cannot make it: {error}")
    return candidates, unplanned


def _report(measured: ServeLibrary, kept_names, say: Callable[[str], None], before: dict | None = None) -> None:
    """A line per measured serve: its legal, let and fault fractions (and ``before[name]``'s
    legal fraction, ServeStats or None, when given) and whether it was kept."""
    for serve in measured.serves:
        s = serve.stats
        was = ""
        if before is not None:
            old = before.get(serve.name)
            was = f"  (was legal {old.legal_fraction:6.1%})" if old is not None else "  (was not measured)"
        say(f"serves: {serve.name:<20} legal {s.legal_fraction:6.1%}  lets {s.let_fraction:5.1%}  faults {s.fault_fraction:5.1%}  "
            f"{'kept' if serve.name in kept_names else 'dropped'}{was}")


def _check_out(who: str, out) -> None:
    """Raises InputError unless ``out`` is None or names a .npz file."""
    if out is not None and Path(out).suffix != ".npz":
        raise InputError(f"{who}: the library is written as a .npz file, got {out}")


def _history(library) -> dict:
    """The sidecar of the library file ``library`` (its .npz or sidecar path) as plain JSON data;
    empty when it has none. Raises InputError when it is not JSON."""
    sidecar = artefacts.sidecar_path(library)
    if not sidecar.is_file():
        return {}
    try:
        return json.loads(sidecar.read_text())
    except (OSError, ValueError) as error:
        raise InputError(f"the sidecar {sidecar} of serve library {library} is malformed: {error}") from None


def _every(generations: int, say: Callable[[str], None]) -> Callable[[str], None]:
    """A GA progress callback passing on every ``generations``-th generation's line."""
    def report(line: str) -> None:
        number = int(line.split("generation")[1].split()[0])
        if number % generations == 0:
            say(line)
    return report
