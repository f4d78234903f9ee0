"""Scoring a table-tennis match between the robot and a human, by the ITTF Laws.

The rules implemented (ITTF Handbook, Laws 2.11-2.13):

- 2.11 A game is won by the first player to score 11 points, unless both score 10, when it is won
  by the first to lead by 2 ("deuce"). ``MatchRules.golden_point`` is an option outside the Laws
  (the paper's matches used it): at 10-10 the next point wins the game.
- 2.12 A match is the best of an odd number of games.
- 2.13.3 The service passes to the receiver after every 2 points, and after every point once both
  players have 10 points, the order of serving staying the same.
- 2.13.5 The player who served first in a game receives first in the next game.
- 2.13.7 The players change ends after each game, and in the last possible game of the match when
  one player first reaches 5 points. Ends have no effect in simulation; the deciding game's change
  is recorded on the point that triggers it (``PointRecord.change_ends``).

``MatchRules`` is immutable. ``Match`` is a mutable state machine: ``award`` records one point and
returns an immutable ``PointRecord``. Scores are pairs ordered (robot, human), whoever serves.
"""

from __future__ import annotations

import dataclasses

from ace_drake.config import ConfigError

ROBOT, HUMAN = "robot", "human"
PLAYERS = (ROBOT, HUMAN)


def opponent(player: str) -> str:
    """The other player."""
    return HUMAN if require_player(player, "player") == ROBOT else ROBOT


def require_player(player: str, what: str) -> str:
    """``player`` if it is one of ``PLAYERS``, else a ValueError naming ``what``."""
    if player not in PLAYERS:
        raise ValueError(f"{what} must be one of {PLAYERS}, got {player!r}")
    return player


def _pair_index(player: str) -> int:
    return PLAYERS.index(player)


@dataclasses.dataclass(frozen=True)
class MatchRules:
    """How games and matches are won (Laws 2.11-2.12).

    points_to_win: points that win a game (11); win_by: the lead needed once both players have
    points_to_win - 1 (2); best_of: games in the longest match, a positive odd integer (3);
    golden_point: at (points_to_win - 1)-all the next point wins the game (not ITTF; False).
    """

    points_to_win: int = 11
    win_by: int = 2
    best_of: int = 3
    golden_point: bool = False

    def __post_init__(self) -> None:
        for name in ("points_to_win", "win_by", "best_of"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"MatchRules.{name} must be a positive integer, got {value!r}")
        if self.best_of % 2 == 0:
            raise ConfigError(f"MatchRules.best_of must be odd (a match is the best of an odd number of games, Law 2.12), got {self.best_of}")

    @property
    def games_to_win(self) -> int:
        """Games that win the match: a majority of ``best_of``."""
        return self.best_of // 2 + 1

    @property
    def deuce_points(self) -> int:
        """The score each player must reach for deuce (10): from there the service alternates every
        point and a game needs a lead of ``win_by`` (or, with golden_point, one more point)."""
        return self.points_to_win - 1

    @property
    def ends_change_points(self) -> int:
        """In the deciding game the ends change when a player first reaches this score (5 of 11)."""
        return self.points_to_win // 2

    def game_won(self, points: int, other_points: int) -> bool:
        """Whether a player with ``points`` against ``other_points`` has won the game."""
        if points < self.points_to_win:
            return False
        return self.golden_point or points - other_points >= self.win_by


@dataclasses.dataclass(frozen=True)
class PointRecord:
    """One awarded point. Scores are (robot, human); games are numbered from 1.

    winner, server: players. game: the game the point was played in. points_before, points_after:
    that game's score before and after the point. games_after: games won after the point.
    game_over, match_over: the point ended the game, the match. change_ends: the point brought
    a player to 5 in the deciding game, when the players change ends (Law 2.13.7).
    """

    winner: str
    server: str
    game: int
    points_before: tuple[int, int]
    points_after: tuple[int, int]
    games_after: tuple[int, int]
    game_over: bool
    match_over: bool
    change_ends: bool


class Match:
    """A match in progress (mutable): the score, who serves, and the points so far.

    Args:
        rules: how games and the match are won.
        first_server: who serves the first point of the first game (ROBOT or HUMAN).
    """

    def __init__(self, rules: MatchRules | None = None, first_server: str = ROBOT):
        self.rules = MatchRules() if rules is None else rules
        self.first_server = require_player(first_server, "Match first_server")
        self.games: list[tuple[int, int]] = []  # final scores (robot, human) of the finished games
        self.history: list[PointRecord] = []
        self._points = [0, 0]
        self._server = self.first_server

    @property
    def game(self) -> int:
        """The number of the game being played (from 1); after the match, the number of games."""
        return len(self.games) + (0 if self.finished else 1)

    @property
    def points(self) -> tuple[int, int]:
        """The current game's score (robot, human); (0, 0) after the match."""
        return tuple(self._points)

    @property
    def games_won(self) -> tuple[int, int]:
        """Games won (robot, human)."""
        robot = sum(r > h for r, h in self.games)
        return robot, len(self.games) - robot

    @property
    def finished(self) -> bool:
        return max(self.games_won) >= self.rules.games_to_win

    @property
    def winner(self) -> str | None:
        """The match's winner, None until it is finished."""
        if not self.finished:
            return None
        robot, human = self.games_won
        return ROBOT if robot > human else HUMAN

    @property
    def server(self) -> str | None:
        """Who serves the next point (Law 2.13); None after the match."""
        return None if self.finished else self._server

    @property
    def receiver(self) -> str | None:
        """Who receives the next point; None after the match."""
        return None if self.finished else opponent(self._server)

    @property
    def deciding_game(self) -> bool:
        """Whether the game being played is the last possible one of the match."""
        return self.game == self.rules.best_of

    @property
    def score(self) -> str:
        """Games and the current game's points, robot first: "1-0 (7-5)"; after the match, the
        games and every game's score: "2-1 (11-5, 9-11, 11-7)"."""
        robot_games, human_games = self.games_won
        if self.finished:
            return f"{robot_games}-{human_games} (" + ", ".join(f"{r}-{h}" for r, h in self.games) + ")"
        return f"{robot_games}-{human_games} ({self._points[0]}-{self._points[1]})"

    def award(self, winner: str) -> PointRecord:
        """Scores a point for ``winner`` and moves the service on; returns the point's record.

        Raises RuntimeError once the match is finished, ValueError for an unknown player.
        """
        require_player(winner, "Match.award winner")
        if self.finished:
            raise RuntimeError(f"Match.award: the match is over ({self.score}, won by {self.winner}); no more points can be awarded")
        rules = self.rules
        game, server, deciding = self.game, self._server, self.deciding_game
        before = self.points
        self._points[_pair_index(winner)] += 1
        after = self.points
        won = after[_pair_index(winner)]
        lost = after[1 - _pair_index(winner)]
        change_ends = deciding and won == rules.ends_change_points and lost < rules.ends_change_points
        game_over = rules.game_won(won, lost)
        if game_over:
            self.games.append(after)
            self._points = [0, 0]
            # Law 2.13.5: the first server of a game receives first in the next one.
            self._server = self.first_server if len(self.games) % 2 == 0 else opponent(self.first_server)
        else:
            played = won + lost
            both_at_deuce = min(after) >= rules.deuce_points
            # Law 2.13.3: every 2 points, every point from 10-10.
            if both_at_deuce or played % 2 == 0:
                self._server = opponent(self._server)
        record = PointRecord(
            winner=winner, server=server, game=game, points_before=before, points_after=after,
            games_after=self.games_won, game_over=game_over, match_over=self.finished, change_ends=change_ends,
        )
        self.history.append(record)
        return record
