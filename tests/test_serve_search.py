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
