"""Play configs: the opponent's incoming-shot distribution.
"""

from __future__ import annotations

import dataclasses
import math

from ace_drake.config import ConfigError, require_probability


@dataclasses.dataclass(frozen=True)
class ShotParams:
    """The opponent's incoming-shot distribution (``play/shots.py``; paper, Methods *Initial state
    training distribution*): Gaussian KDEs of post-hit ball states fitted to ``source``,
    "synthetic" (the built-in synthetic set, drawn with ``seed``) or the path of a match-data CSV
    (the human's shots), of the ``players`` named there only (``player_id`` values; empty: all);
    serves are drawn with probability ``serve_fraction`` (paper: 3:7 serves to returns);
    ``bandwidth``: the KDE bandwidth factor (dimensionless), null for Scott's rule."""

    source: str = "synthetic"
    serve_fraction: float = 0.3
    bandwidth: float | None = None
    seed: int = 0
    players: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.source.strip():
            raise ConfigError("source must be 'synthetic' or the path of a match-data CSV, got an empty string")
        require_probability(self, "serve_fraction", allow_one=True)
        if self.bandwidth is not None and not (math.isfinite(self.bandwidth) and self.bandwidth > 0):
            raise ConfigError(f"bandwidth must be > 0 or null (Scott's rule), got {self.bandwidth}")
        if self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")
        if self.players and self.source == "synthetic":
            raise ConfigError("players selects shots of a match-data CSV; the synthetic source has none")

