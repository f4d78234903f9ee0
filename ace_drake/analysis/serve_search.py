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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import numpy as np
import pygad

from ace_drake.control.serve import (
    SERVE_GENES,
    ServeOutcome,
    Strike,
    TossState,
    evaluate_genes,
    serve_weights,
    strike_from_genes,
)
from ace_drake.physics.params import BallPhysicsParams

GENERATIONS = 100  # the authors' setting
PARENTS_MATING = 6  # the authors' setting
MUTATION_GENES = 3  # the authors' setting: genes mutated per offspring
MUTATION_STEP = 0.2  # the authors' setting: a mutated gene moves by up to this, either way
SATURATION = 40  # the authors' setting: generations without improvement before stopping
POPULATION = 50  # solutions per generation (chosen: the paper gives none)


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


def search_serve(
    kind: str,
    toss: TossState | None = None,
    physics: BallPhysicsParams | None = None,
    seed: int = 0,
    generations: int = GENERATIONS,
    population: int = POPULATION,
    progress: Callable[[str], None] | None = print,
) -> SearchResult:
    """The best strike of a serve ``kind`` found by PyGAD with the authors' settings (module
    docstring), from the toss ``toss`` (default ``TossState()``) under ``physics`` (default the
    paper's). ``progress`` (None: silent) receives a line per generation: its number, the best
    fitness and whether that serve is legal."""
    weights = serve_weights(kind)
    toss = TossState() if toss is None else toss
    physics = BallPhysicsParams() if physics is None else physics
    if generations < 1:
        raise ValueError(f"search_serve: generations must be >= 1, got {generations}")
    if population <= PARENTS_MATING:
        raise ValueError(f"search_serve: population must exceed the {PARENTS_MATING} parents mating, got {population}")

    def fitness_batch(ga, solutions, indices):
        fitness, _ = evaluate_genes(np.asarray(solutions, dtype=float), toss, physics, weights)
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
    check, (outcome,) = evaluate_genes(genes[None], toss, physics, weights)
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
) -> list[SearchResult]:
    """A serve library: ``search_serve`` for every kind and seed, keeping the legal results, best
    first within each kind, without any whose genes lie within ``min_gene_distance`` (Euclidean,
    in [0, 1]^9) of a kept one of the same kind."""
    kinds, seeds = list(kinds), list(seeds)
    for kind in kinds:
        serve_weights(kind)  # a bad name fails before any search
    library: list[SearchResult] = []
    for kind in kinds:
        results = [search_serve(kind, toss, physics, seed, generations, population, progress) for seed in seeds]
        kept: list[SearchResult] = []
        for result in sorted((r for r in results if r.legal), key=lambda r: -r.fitness):
            if all(np.linalg.norm(result.genes - other.genes) >= min_gene_distance for other in kept):
                kept.append(result)
        library += kept
    return library
