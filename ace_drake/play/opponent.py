"""The simulated opponent.

The rally episodes start from a ``Launcher``: one shot drawn from the incoming-shot distribution
(``play/shots.py``), no reply. The opponent that returns the robot's balls as the recorded players
did is ``play.opponent_model.OpponentModel``; the umpire and the score are ``play.umpire`` and
``play.scoring`` (docs/play.md).
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
