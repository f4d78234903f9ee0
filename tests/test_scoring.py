"""ITTF scoring (play/scoring.py): games, deuce, golden point, service order, matches."""

import pytest

from ace_drake.play.scoring import HUMAN, ROBOT, Match, MatchRules, opponent


def play(match: Match, winners) -> list:
    return [match.award(winner) for winner in winners]


def to_ten_all(match: Match) -> None:
    """Robot and human take points in turn to 10-10 (robot first)."""
    play(match, [ROBOT, HUMAN] * 10)


def test_a_game_to_11_5():
    dut = Match(MatchRules(best_of=3), first_server=ROBOT)
    records = play(dut, [ROBOT, HUMAN] * 5 + [ROBOT] * 5)
    assert dut.points == (10, 5) and not records[-1].game_over
    assert dut.score == "0-0 (10-5)"
    last = dut.award(ROBOT)
    assert last.points_before == (10, 5) and last.points_after == (11, 5)
    assert last.game_over and not last.match_over and last.games_after == (1, 0)
    assert dut.games == [(11, 5)] and dut.points == (0, 0) and dut.game == 2
    assert dut.score == "1-0 (0-0)"


def test_deuce_needs_a_lead_of_two():
    dut = Match()
    to_ten_all(dut)
    advantage = dut.award(ROBOT)
    assert advantage.points_after == (11, 10) and not advantage.game_over
    assert dut.award(ROBOT).game_over
    assert dut.games == [(12, 10)]


def test_golden_point_at_ten_all():
    dut = Match(MatchRules(golden_point=True))
    to_ten_all(dut)
    record = dut.award(HUMAN)
    assert record.points_after == (10, 11) and record.game_over
    assert dut.games == [(10, 11)]


def test_service_changes_every_two_points_and_every_point_from_ten_all():
    dut = Match(first_server=ROBOT)
    servers = [record.server for record in play(dut, [ROBOT, HUMAN] * 10 + [ROBOT, HUMAN, ROBOT, HUMAN])]
    expected = "RRHH" * 5 + "RHRH"  # 20 points in pairs, then one each from 10-10
    assert "".join(s[0].upper() for s in servers) == expected
    assert dut.points == (12, 12) and dut.server == ROBOT


def test_the_first_server_of_a_game_receives_first_in_the_next():
    dut = Match(MatchRules(best_of=5), first_server=HUMAN)
    assert dut.server == HUMAN
    play(dut, [ROBOT] * 11)
    assert dut.server == ROBOT and dut.receiver == HUMAN
    play(dut, [HUMAN] * 11)
    assert dut.server == HUMAN
    assert [r.server for r in dut.history if r.points_before == (0, 0)] == [HUMAN, ROBOT]


def test_best_of_three_ends_at_two_games():
    dut = Match(MatchRules(best_of=3))
    play(dut, [ROBOT] * 11)
    play(dut, [HUMAN] * 10 + [ROBOT] * 10 + [HUMAN])
    assert dut.score == "1-0 (10-11)" and not dut.finished and dut.winner is None
    assert dut.award(ROBOT).points_after == (11, 11)
    assert not dut.award(ROBOT).match_over
    assert dut.award(ROBOT).match_over
    assert dut.finished and dut.winner == ROBOT
    assert dut.games == [(11, 0), (13, 11)]
    assert dut.score == "2-0 (11-0, 13-11)"
    assert dut.server is None and dut.game == 2


def test_best_of_five_changes_ends_at_five_in_the_deciding_game_only():
    dut = Match(MatchRules(best_of=5))
    for winner in (ROBOT, HUMAN, ROBOT, HUMAN):
        play(dut, [winner] * 11)
    assert not dut.finished and dut.deciding_game and dut.score == "2-2 (0-0)"
    records = play(dut, [HUMAN] * 4 + [ROBOT] * 6)
    assert [r.change_ends for r in records] == [False] * 4 + [False] * 4 + [True, False]  # 4-4 -> 5-4 robot
    assert not any(r.change_ends for r in dut.history[:44])
    play(dut, [ROBOT] * 5)
    assert dut.finished and dut.winner == ROBOT and dut.score == "3-2 (11-0, 0-11, 11-0, 0-11, 11-4)"


def test_awarding_after_the_match_is_an_error():
    dut = Match(MatchRules(best_of=1))
    play(dut, [HUMAN] * 11)
    assert dut.winner == HUMAN
    with pytest.raises(RuntimeError, match="match is over"):
        dut.award(ROBOT)


@pytest.mark.parametrize("best_of", [0, 2, -1])
def test_best_of_must_be_a_positive_odd_integer(best_of):
    with pytest.raises(ValueError, match="best_of"):
        MatchRules(best_of=best_of)


def test_unknown_players_are_errors():
    with pytest.raises(ValueError, match="first_server"):
        Match(first_server="robbot")
    with pytest.raises(ValueError, match="winner"):
        Match().award("umpire")
    assert opponent(ROBOT) == HUMAN and opponent(HUMAN) == ROBOT
