"""analysis.serve_search: PyGAD with the authors' settings finds legal serves, reproducibly."""

import numpy as np
import pytest

from ace_drake.analysis.serve_search import search_library, search_serve
from ace_drake.control.serve import SERVE_GENES, serve_fitness, serve_weights

# Small searches: a few seconds each (the authors' 100 generations are `search_serve`'s default).
SHORT = {"generations": 8, "population": 16}


def test_a_short_search_finds_a_legal_serve():
    lines = []
    result = search_serve("long_topspin", seed=1, progress=lines.append, **SHORT)
    assert result.legal, result.outcome.reason
    assert result.fitness >= 1.0
    assert result.fitness == serve_fitness(result.outcome, serve_weights("long_topspin"))
    assert result.genes.shape == (SERVE_GENES,) and np.all((result.genes >= 0.0) & (result.genes <= 1.0))
    assert result.generations == SHORT["generations"]
    assert len(result.fitness_history) == result.generations + 1  # the initial population's first
    assert np.all(np.diff(result.fitness_history) >= 0.0)  # elitism: the best is kept
    assert result.fitness_history[-1] == result.fitness
    assert len(lines) == result.generations
    assert "generation   8" in lines[-1] and "(legal)" in lines[-1]


def test_the_same_seed_gives_the_same_serve_bit_for_bit():
    first = search_serve("short_backspin", seed=7, progress=None, generations=4, population=12)
    second = search_serve("short_backspin", seed=7, progress=None, generations=4, population=12)
    np.testing.assert_array_equal(first.genes, second.genes)
    np.testing.assert_array_equal(first.fitness_history, second.fitness_history)
    other = search_serve("short_backspin", seed=8, progress=None, generations=4, population=12)
    assert not np.array_equal(first.genes, other.genes)


def test_a_bad_kind_names_the_kinds():
    with pytest.raises(ValueError, match="unknown serve kind 'lob'.*short_backspin, long_topspin, long_sidespin, fast_long"):
        search_serve("lob", progress=None)
    with pytest.raises(ValueError, match="unknown serve kind"):
        search_library(["long_topspin", "lob"], [0], progress=None)


def test_the_library_keeps_legal_distinct_serves():
    library = search_library(["long_topspin"], [1, 1], progress=None, **SHORT)
    assert len(library) == 1  # the same seed twice: one serve
    assert library[0].legal and library[0].kind == "long_topspin"


def test_the_ga_can_score_the_strikes_the_robot_makes():
    """``ExecutedStrikes``: a solution's fitness is that of the serve of the racket state the
    robot executes (``plan_strike`` after the planned toss), from the executed release; a short
    search on it is reproducible and its best serve is the executed one."""
    from ace_drake.analysis.serve_search import ExecutedStrikes
    from ace_drake.control.params import ControlParams
    from ace_drake.control.serve import TossState, simulate_serve, strike_from_genes
    from ace_drake.control.serve_execution import plan_strike, plan_toss
    from ace_drake.control.stack import make_control_stack
    from ace_drake.physics.params import BallPhysicsParams
    from ace_drake.robot.model import RobotModel

    model, physics = RobotModel(), BallPhysicsParams()
    stack = make_control_stack(model.scenario, ControlParams())
    toss = plan_toss(model, stack)
    robot = ExecutedStrikes(model, stack, toss, physics)
    genes = np.array([[0.3484, 0.4033, 0.0354, 0.1761, 0.4367, 0.8722, 0.3, 0.2475, 0.7888]])
    weights = serve_weights("short_backspin")
    fitness, (outcome,) = robot.evaluate(genes, weights)
    plan = plan_strike(model, stack, toss, strike_from_genes(genes[0], TossState(), physics))
    expected = simulate_serve(plan.executed_strike, toss.release, physics)
    assert fitness[0] == serve_fitness(expected, weights) and outcome.legal == expected.legal
    runs = [search_serve("long_backspin", seed=3, progress=None, generations=2, population=8, robot=robot) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].genes, runs[1].genes)
    again, (best,) = robot.evaluate(runs[0].genes[None], serve_weights("long_backspin"))
    assert runs[0].fitness == again[0] and runs[0].outcome.legal == best.legal
