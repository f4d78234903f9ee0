"""The simulated opponent.

For now the opponent is a ``Launcher``: it starts each rally episode with one shot drawn from the
incoming-shot distribution (``play/shots.py``) and takes no further part. The rules-aware opponent,
which returns the robot's shots and keeps score, comes later (issue 6).
"""

from __future__ import annotations

import numpy as np

from ace_drake.play.shots import RETURN, SERVE, ShotDistribution


class Launcher:
    """Starts each episode with a shot sampled from a ``ShotDistribution``, like a ball launcher.

    A plain Python object, not a LeafSystem: the rally diagram sets the BallPlant's state in the
    Context to the shot at each episode start (``diagrams.start_rally``), so nothing about an
    episode is kept here.
    """

    def __init__(self, distribution: ShotDistribution):
        self.distribution = distribution

    def shot(self, rng: np.random.Generator) -> tuple[np.ndarray, str]:
        """The next shot: its (9,) state just after the opponent's hit, [p (m), v (m/s),
        w (rad/s)], and its kind, ``"serve"`` or ``"return"``. Seeded by ``rng`` alone."""
        sample = self.distribution.draw(rng, 1)
        return sample.states[0], SERVE if sample.serve[0] else RETURN
