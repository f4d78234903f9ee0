"""The episode seed of a stochastic system, drawn by Drake's random context.

DESIGN.md: seeds reach systems through ``SetRandomContext``, never through a hand-kept list. A
Python LeafSystem cannot take part in ``SetRandomContext`` by itself: pydrake 1.51 binds no
override of ``SetRandomState`` / ``SetRandomParameters`` for Python systems (an override is never
called), so its state and parameters are only ever reset to their defaults. Drake's idiom that a
Python system can use is the *random input port*: the system declares an input labelled random
(``declare_seed_port``: ``random_seed``, one uniform sample), the diagram builder connects a
``RandomSource`` to every unconnected random port (``diagrams.add_random_sources``, over Drake's
``AddRandomInputs``), and ``diagram.SetRandomContext(context, RandomGenerator(seed))`` gives every
RandomSource a fresh seed of its own from that one generator. A new stochastic system that declares
the port is seeded with no edit elsewhere, and no two systems share a stream.

The system reads the port whenever it draws (``episode_seed``) and seeds NumPy's generator with
the sample's 64 bits and its own stream numbers, as before; nothing random is kept on ``self`` or
as a generator object in the Context, so copying or resetting a Context reproduces the draws.

The sources hold their sample for ``SEED_HOLD_PERIOD``: a RandomSource re-samples at a periodic
event with offset 0, so an episode that starts at time 0 reads the sample drawn by
``SetRandomContext`` in its initialization events and its events at t = 0, and the source's next
sample (taken at t = 0 by the Simulator, from the source's own generator in the Context) after
that. Both are functions of the seed, so a seed still fixes the rollout bit for bit.

Unconnected (a system on its own, or in a diagram built without ``add_random_sources``), the port
has no value and the system uses its ``seed`` parameter instead.
"""

from __future__ import annotations

import numpy as np
from pydrake.common import RandomDistribution

SEED_PORT_NAME = "random_seed"
# s; the RandomSources' sampling interval: far longer than any episode, so each holds one sample.
SEED_HOLD_PERIOD = 1.0e6


def declare_seed_port(system):
    """Declares ``system``'s random input port ``random_seed`` (1,): a uniform sample on [0, 1)
    that Drake's random context draws (module docstring). Returns the port."""
    return system.DeclareVectorInputPort(SEED_PORT_NAME, 1, RandomDistribution.kUniform)


def episode_seed(port, context, default: int) -> int:
    """The seed of ``port``'s system in ``context``: the 64 bits of the port's sample when it has
    a value (a RandomSource), else ``default`` (the system's seed parameter)."""
    if not port.HasValue(context):
        return int(default)
    return int(np.float64(port.Eval(context)[0]).view(np.uint64))
