"""Tutorial 07: a match under ITTF rules, played one game point by point.

Read this file top to bottom like a notebook. Tutorial 05 returned single shots from a launcher;
here the robot plays a game against a simulated human built from the recorded matches, and an
umpire judges every point (``ace_drake/play/``, docs/play.md). It shows

  1. the umpire on hand-built contacts: a good service, a let, an edge ball, a double bounce
     (``play.umpire.judge_rally``: the ITTF Laws 2.6-2.10 as the simulation sees them);
  2. the pieces of a match: the score (``play.scoring.Match``), the opponent model of one
     recorded player (``play.opponent_model.OpponentModel``: will the human return this ball,
     and how), and the robot's serve library (``evaluation.serves``: serves found by a genetic
     algorithm, each with its measured legality);
  3. one game, point by point, on the segment-stepped rally diagram (``evaluation.match``:
     the robot serves through its control stack, returns with the model-based returner, the
     human returns from its fitted model, the diagram's umpire decides), printed as it goes;
  4. the game's figures (how points ended, rally lengths) as a plot, and its Meshcat replay with
     every point listed and clickable.

Parts 2-4 need the recorded match data (../shared/data/ace_match_events_elite.csv, beside the
repository); without it they are skipped. Numbers are SI units (m, s, rad). Run it from the
repository root:

    .venv/bin/python tutorials/07_match.py                # all parts
    .venv/bin/python tutorials/07_match.py --no-html      # skip the Meshcat file
    .venv/bin/python tutorials/07_match.py --out DIR

It writes match.png and, unless --no-html, match.html into --out (default out/tutorials/07).
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from ace_drake.analysis.match_replay import write_match_replay
from ace_drake.contracts import DEFAULT_CONTROLLER
from ace_drake.evaluation.controllers import make_controller, rally_params
from ace_drake.evaluation.match import LibraryServes, MatchRunner
from ace_drake.evaluation.serves import DEFAULT_LIBRARY, load_serve_library
from ace_drake.physics.propagate import ContactKind
from ace_drake.play.opponent_model import OpponentModel
from ace_drake.play.scoring import HUMAN, ROBOT, MatchRules
from ace_drake.play.umpire import RallyEvent, Toss, judge_rally
from ace_drake.robot.model import load_scenario

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT.parent / "shared" / "data" / "ace_match_events_elite.csv"
OPPONENT = "Elite C"  # the recorded player the simulated human is fitted to
SEED = 3  # the game's seed: the sensors' noise, the ball's perturbations, the human's choices


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "tutorials" / "07")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML file")
    return parser.parse_args()


def contact(kind: ContactKind, time: float, x: float, y: float, z: float = 0.02, v_z: float = -2.0, striker=None) -> RallyEvent:
    """A hand-built contact: the ball's centre at (x, y, z) m at ``time`` s, falling at v_z m/s."""
    return RallyEvent(kind, time, np.array([x, y, z]), np.array([3.0, 0.0, v_z]), striker)


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ 1. the umpire
    # The robot plays from x < 0. Its toss rises 0.2 m from behind its end line; it strikes the
    # falling ball, which must touch its own court, then the human's.
    toss = Toss(0.0, np.array([-1.55, -0.3, 0.1]), np.array([0.0, 0.0, 2.0]), 0.20)
    strike = contact(ContactKind.RACKET, 0.45, -1.5, -0.3, z=0.12, striker=ROBOT)
    rallies = {
        "a good service, the human misses": [strike, contact(ContactKind.TABLE, 0.6, -0.9, -0.2), contact(ContactKind.TABLE, 0.9, 0.5, 0.0),
                                             contact(ContactKind.FLOOR, 1.4, 2.0, 0.1, z=0.02)],
        "a service touching the net: a let": [strike, contact(ContactKind.TABLE, 0.6, -0.9, -0.2), contact(ContactKind.NET, 0.75, 0.0, 0.0, z=0.16),
                                              contact(ContactKind.TABLE, 0.9, 0.5, 0.0)],
        "an edge ball (the top edge is court)": [strike, contact(ContactKind.TABLE, 0.6, -0.9, -0.2), contact(ContactKind.TABLE, 0.9, 1.385, 0.0),
                                                 contact(ContactKind.RACKET, 1.1, 1.6, 0.0, z=0.2, striker=HUMAN),
                                                 contact(ContactKind.TABLE, 1.4, -0.6, 0.1), contact(ContactKind.TABLE, 1.8, -1.0, 0.1)],
        "the service lands on the human's court first": [strike, contact(ContactKind.TABLE, 0.6, 0.3, 0.0)],
    }
    print("1. the umpire on hand-built rallies (the robot serves):")
    for name, events in rallies.items():
        decision = judge_rally(ROBOT, events, toss)
        outcome = "let" if decision.let else f"point to the {decision.winner}"
        print(f"   {name:<46} -> {outcome}: {decision.reason} (Law {decision.law}, {decision.shots} strikes)")

    if not DATA.is_file():
        print(f"\nskipping parts 2-4: the recorded match data is not at {DATA}")
        return

    # ------------------------------------------------------------------ 2. the pieces
    opponent = OpponentModel.from_match_data(DATA, [OPPONENT])
    print(f"\n2. the opponent: {OPPONENT}'s model, fitted on {len(opponent.data)} balls the robot sent to this player "
          f"({opponent.data.return_rate:.1%} returned) and {len(opponent.data.serves)} of the player's serves")
    incoming = opponent.data.incoming[:3]
    for ball, probability in zip(incoming, opponent.return_probability(incoming)):
        print(f"   a ball bouncing at x = {ball[0]:.2f} m, leaving the table at {np.linalg.norm(ball[3:6]):.1f} m/s: returned with p = {probability:.2f}")
    params = rally_params(None, "cameras", SEED, "segment")
    library = load_serve_library(DEFAULT_LIBRARY, load_scenario())
    print(f"   the robot's serve library: {len(library)} serves ({DEFAULT_LIBRARY.name}), each executed {library.repeats} times with noise:")
    for serve in library.serves:
        print(f"     {serve.name:<22} legal {serve.stats.legal_fraction:.0%}, second bounce at x = {serve.stats.landing_mean[0]:+.2f} m, "
              f"{serve.stats.speed_mean:.1f} m/s, topspin {serve.stats.topspin_mean:+.0f}, sidespin {serve.stats.sidespin_mean:+.0f} rad/s")

    # ------------------------------------------------------------------ 3. one game
    rules = MatchRules(best_of=1)  # one game to 11
    print(f"\n3. one game to {rules.points_to_win} against {OPPONENT}, the robot's controller '{DEFAULT_CONTROLLER}', nine cameras, seed {SEED}:")
    runner = MatchRunner(make_controller(DEFAULT_CONTROLLER, params), params, batch=1)
    (result,), track = runner.play(opponent, LibraryServes(library, params.physics), 1, rules, SEED, OPPONENT, record=0,
                                   progress=lambda line: print("   " + line.split(": ", 1)[1]))
    summary = result.summary()
    robot, human = result.games[0]
    print(f"   the {result.winner} won the game {robot}-{human}; rally length {summary['rally_length_mean']:.1f} +- "
          f"{summary['rally_length_std']:.1f} strikes (the paper's matches: 5.0 +- 3.0), robot aces {summary['aces']}, "
          f"service faults {summary['service_faults']}, lets {summary['lets']}")

    # ------------------------------------------------------------------ 4. figures and replay
    decided = [p for p in result.points if not p.let]
    endings = Counter(f"{p.winner}: {p.reason}" for p in decided)
    figure, (lengths, reasons) = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw={"width_ratios": [1, 2]})
    lengths.hist([p.shots for p in decided], bins=np.arange(0.5, max(p.shots for p in decided) + 1.5), color="tab:blue")
    lengths.set(xlabel="strikes in the point (the service included)", ylabel="points", title="rally length")
    labels, counts = zip(*endings.most_common())
    reasons.barh(range(len(labels)), counts, color=["tab:green" if label.startswith("robot") else "tab:red" for label in labels])
    reasons.set_yticks(range(len(labels)), labels, fontsize=8)
    reasons.invert_yaxis()
    reasons.set(xlabel="points", title="how the points ended (green: the robot's)")
    figure.tight_layout()
    png = args.out / "match.png"
    figure.savefig(png, dpi=110)
    print(f"\n4. figures: {png}")
    if not args.no_html:
        html = write_match_replay(track, args.out / "match.html")
        print(f"   the replay, every point listed on the right (click one to jump there): {html}")


if __name__ == "__main__":
    main()
