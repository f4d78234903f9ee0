"""Tutorial 05: the rally diagram, or the whole robot returning a ball.

Read this file top to bottom like a notebook. Everything of the earlier tutorials joins here in
one Drake Diagram (``ace_drake.diagrams.add_rally``, the wiring of DESIGN.md): the ball
(BallPlant), the robot's perception of it (nine cameras, triangulator, spin sensor, EKF), the
observation the controller reads every 32 ms (paper, Methods *States*), the control stack (eq.
(12) mapping, spline QP, reset, safety supervisor) and the delayed joints (eq. (9)) whose racket
is the ball's racket. It shows

  1. the diagram: its systems and its graph (SVG when Graphviz is installed, else DOT);
  2. one rally: an incoming shot from the match data (or a built-in one) returned by the
     model-based returner (``ace_drake/control/returner.py``), the ball and racket plotted from
     the side and from above, the joints against their limits;
  3. the replay: a self-contained Meshcat HTML file of the rally;
  4. the skill (paper, Methods *States*, *Rewards*): the same shot played with other skills
     [y_desired, w_p, w_s], the returner aiming at y_desired and brushing the ball for topspin
     (w_s > 0) or backspin (w_s < 0);
  5. a batch of rallies: the same wiring, segment-stepped and batched
     (``diagrams.build_segment_rally_diagram``, docs/architecture.md *Segment stepping*): BATCH
     returners play BATCH_SHOTS shots together, each environment taking the next shot when its
     episode ends (``evaluation.runner.SegmentRallyRunner``), as ``ace-drake evaluate`` does.

Numbers are SI units (m, s, rad). Run it from the repository root:

    .venv/bin/python tutorials/05_rally.py                # all parts
    .venv/bin/python tutorials/05_rally.py --no-html      # skip the Meshcat file
    .venv/bin/python tutorials/05_rally.py --out DIR

It writes rally.png, rally_diagram.svg (or .dot) and, unless --no-html, rally.html into --out
(default out/tutorials/05).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import time
from collections import Counter
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from pydrake.geometry import Meshcat

from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_rally_diagram, build_segment_rally_diagram, graphviz_dot
from ace_drake.evaluation.controllers import DEFAULT_CONTROLLER, make_controller
from ace_drake.evaluation.runner import RallyRunner, SegmentRallyRunner
from ace_drake.learning.rewards import travel_frame_spin
from ace_drake.physics.flight import make_state
from ace_drake.play.shots import human_shots
from ace_drake.robot.model import RobotModel
from ace_drake.robot.params import JOINT_NAMES

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT.parent / "shared" / "data" / "ace_match_events_elite.csv"
# A return from the human's side when the match data is absent: 7 m/s with topspin.
BUILT_IN_SHOT = make_state((1.6, 0.2, 0.25), (-7.0, -0.5, 1.3), (0.0, 150.0, 0.0))
SHOT_INDEX = 1  # which human shot of the match data to play
# The seed of every episode here (the sensors' noise, the ball's perturbations): episodes are
# reproducible by seed, and this one shows the returner's usual play (with skill (+0.3, 1, +1) it
# returns human shot 1 for 7 of the seeds 0-7; with seed 0 that return lands long).
SEED = 1
# Part 4's skills [y_desired (m), w_p, w_s]: aimed left with topspin, at the centre line with none,
# aimed right with backspin.
SKILLS = ((0.3, 1.0, 1.0), (0.0, 1.0, 0.0), (-0.3, 1.0, -1.0))


# Part 5: environments in the batch, and the shots they share out.
BATCH = 8
BATCH_SHOTS = 16


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "tutorials" / "05")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML file")
    return parser.parse_args()


def write_graph(diagram, out: Path) -> Path:
    """The diagram's graph as SVG (Graphviz's dot) or, without Graphviz, as DOT text."""
    dot_text = graphviz_dot(diagram)
    if shutil.which("dot") is None:
        path = out / "rally_diagram.dot"
        path.write_text(dot_text)
        print("   (Graphviz's dot is not installed, so the graph is DOT text: apt install graphviz)")
        return path
    path = out / "rally_diagram.svg"
    path.write_bytes(subprocess.run(["dot", "-Tsvg"], input=dot_text.encode(), capture_output=True, check=True).stdout)
    return path


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ 1. the diagram
    params = RallyParams()  # defaults: the nine cameras, the EKF, the paper's ball model with perturbations
    controller = make_controller(DEFAULT_CONTROLLER, params)
    meshcat = None if args.no_html else Meshcat()
    diagram = build_rally_diagram(params, controller, meshcat)
    names = [system.get_name() for system in diagram.GetSystems()]
    print(f"1. the rally diagram has {len(names)} systems:")
    print("   " + ", ".join(names))
    print(f"   its graph: {write_graph(diagram, args.out)}")

    # ------------------------------------------------------------------ 2. one rally
    if DATA.is_file():
        shots, serve = human_shots(DATA)
        shot, is_serve, source = shots[SHOT_INDEX], bool(serve[SHOT_INDEX]), f"human shot {SHOT_INDEX} of {DATA.name}"
    else:
        shot, is_serve, source = BUILT_IN_SHOT, False, "the built-in shot (match data not found)"
    print(f"\n2. {source}: p = {np.round(shot[:3], 2)} m, v = {np.round(shot[3:6], 2)} m/s, w = {np.round(shot[6:], 0)} rad/s")
    runner = RallyRunner(diagram, params)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=60.0, set_visualizations_while_recording=False)
    episode = runner.run(shot, seed=SEED, serve=is_serve)
    result = episode.result
    print(f"   outcome: {result.outcome.value} {result.reason}".rstrip())
    print(f"   segments accepted {episode.segments[0]}, refused {episode.segments[1]}; {episode.duration:.2f} s simulated")
    if result.hit is not None:
        out = result.hit.state_post
        print(f"   hit at t = {result.hit.time:.3f} s, {1000 * result.bounce_to_hit_time:.0f} ms after the bounce; "
              f"the ball leaves at {np.linalg.norm(out[3:6]):.1f} m/s with {np.linalg.norm(out[6:]):.0f} rad/s of spin")
    if result.landing is not None:
        print(f"   the return lands at (x, y) = ({result.landing.state_pre[0]:+.2f}, {result.landing.state_pre[1]:+.2f}) m")

    ball_log = diagram.GetSubsystemByName("ball_logger").FindLog(runner.context)
    joint_log = diagram.GetSubsystemByName("joint_logger").FindLog(runner.context)
    ball = ball_log.data().T
    t_joint, joints = joint_log.sample_times(), joint_log.data().T
    model = RobotModel()
    racket = np.array([model.racket_pose(state[: len(JOINT_NAMES)]).translation() for state in joints])

    figure, axes = plt.subplots(1, 3, figsize=(18, 5))
    ax = axes[0]
    ax.plot(ball[:, 0], ball[:, 2], label="ball")
    ax.plot(racket[:, 0], racket[:, 2], label="racket centre")
    ax.plot([-1.37, 1.37], [0, 0], "k", lw=3)
    ax.plot([0, 0], [0, 0.1525], "k", lw=2)
    ax.set(xlabel="x (m)", ylabel="z (m)", title="2. the rally from the side")
    ax.legend()
    ax = axes[1]
    ax.add_patch(plt.Rectangle((-1.37, -0.7625), 2.74, 1.525, color="tab:green", alpha=0.3))
    ax.plot(ball[:, 0], ball[:, 1], label="ball")
    ax.plot(racket[:, 0], racket[:, 1], label="racket centre")
    ax.set_aspect("equal")
    ax.set(xlabel="x (m)", ylabel="y (m)", title=f"from above: {result.outcome.value}")
    ax.legend()
    ax = axes[2]
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    lower, upper = supervisor.stack.limits.lower, supervisor.stack.limits.upper
    span = upper - lower
    for index, name in enumerate(JOINT_NAMES):
        ax.plot(t_joint, (joints[:, index] - lower[index]) / span[index], label=name)
    ax.axhline(0.0, color="k", ls="--")
    ax.axhline(1.0, color="k", ls="--")
    ax.set(xlabel="t (s)", ylabel="position within the command limits (0 to 1)", title="the joints against their limits")
    ax.legend(fontsize=7)
    figure.tight_layout()
    png = args.out / "rally.png"
    figure.savefig(png, dpi=80)
    print(f"\nwrote {png}")

    # ------------------------------------------------------------------ 3. the replay
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        html = args.out / "rally.html"
        html.write_text(meshcat.StaticHtml())
        print(f"wrote {html}")

    # ------------------------------------------------------------------ 4. the skill
    # A skill is fixed for an episode: the ObservationBuilder holds it as a parameter of the Context
    # (``RallyRunner.run(skill=...)`` sets it), and every controller reads it in its observation.
    # The returner aims its return at y_desired (within +-target_y_limit) and brushes the ball
    # along the blade by skill_brush * w_s: the spin at landing is what the reward's w_s weighs.
    # The incoming spin carries over in part (eqs (7)-(8)), so w_s moves the landing's spin up or
    # down from what a flat stroke gives (for human shot 1: +388, +193 and +67 rad/s).
    print("\n4. the same shot with other skills [y_desired, w_p, w_s]:")
    for skill in SKILLS:
        result = runner.run(shot, seed=SEED, serve=is_serve, skill=skill).result
        landing = "" if result.landing is None else (
            f", lands at y = {result.landing.state_pre[1]:+.2f} m with topspin {travel_frame_spin(result.landing.state_pre):+.0f} rad/s")
        print(f"   skill ({skill[0]:+.1f}, {skill[1]:.0f}, {skill[2]:+.0f}): {result.outcome.value}{landing}")

    # ------------------------------------------------------------------ 5. a batch of rallies
    # The segment-stepped diagram has the same systems under the same names, each carrying B
    # environments; it advances once per 32 ms segment, computing each segment's 1 kHz joint
    # samples, racket poses, ball flight with its contacts and sensor samples vectorised. The
    # model-based returner remembers its episode, so each environment gets its own.
    batch_params = RallyParams(stepping="segment")
    returners = [make_controller(DEFAULT_CONTROLLER, batch_params) for _ in range(BATCH)]
    batch_diagram = build_segment_rally_diagram(batch_params, returners, BATCH)
    if DATA.is_file():
        batch_shots, batch_serve = shots[:BATCH_SHOTS], serve[:BATCH_SHOTS]
    else:
        batch_shots, batch_serve = np.tile(BUILT_IN_SHOT, (BATCH_SHOTS, 1)), np.zeros(BATCH_SHOTS, dtype=bool)
    start = time.perf_counter()
    episodes = SegmentRallyRunner(batch_diagram, batch_params).run_many(batch_shots, batch_serve, seeds=SEED + np.arange(BATCH_SHOTS))
    wall = time.perf_counter() - start
    outcomes = Counter(episode.result.outcome.value for episode in episodes)
    simulated = sum(episode.duration for episode in episodes)
    print(f"\n5. {BATCH_SHOTS} shots, {BATCH} at a time on the segment-stepped diagram: {dict(outcomes)}; "
          f"{simulated:.1f} s of play simulated in {wall:.1f} s ({simulated / wall:.1f} x real time)")


if __name__ == "__main__":
    main()
