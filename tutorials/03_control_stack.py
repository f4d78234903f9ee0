"""Tutorial 03: the rally control stack, from a policy's action to a safe 1 kHz joint command.

Read this file top to bottom like a notebook. Every 32 ms the policy outputs an action in
[-1, 1]^16; the stack turns it into joint commands (paper, Fig. 1c and Methods *Feasible action
for optimal control*, *Reset trajectories*):

    action -> eq. (12): a feasible terminal joint state (q_T, v_T) 32 ms ahead
           -> spline QP: the jerk-minimising segment to it, sampled at 1 kHz, within the limits
           -> reset: from the segment's end to a stationary reset pose (time-optimal, jerk-limited)
           -> supervisor: executes segment + reset only if collision-free, else keeps the
              previous plan (whose reset was checked when it was accepted).

It shows

  1. the feasible set and the mapping: each joint's set of terminal (q, v) in the (q, v) plane, where
     random actions, the action box's boundary and the action 0 land; a joint near its position
     limit, where the control-invariant set cuts into what the QP could reach; the inverse map;
  2. a segment and its reset: one proposal from a moving state with an extreme action, against the
     command limits, and how long each stage took;
  3. the fallback, in Meshcat: a policy that drives the racket into the table; the supervisor
     refuses every segment whose motion it cannot prove clear, and the robot keeps clear;
  4. the light curtain: someone walks onto the robot's side; the protective stop brings every joint
     to rest and no new segment is accepted until the curtain clears.

Parts 3 and 4 run the controlled-robot Diagram of ace_drake.diagrams (policy_controller ->
action_mapper -> spline_qp -> reset_mpc -> safety_supervisor -> the delayed joints of eq. (9)) in a
Simulator; parts 1 and 2 call the same ControlStack directly. Numbers are SI units (m, s, rad).
Run it from the repository root:

    .venv/bin/python tutorials/03_control_stack.py                # all parts
    .venv/bin/python tutorials/03_control_stack.py --no-html      # skip the Meshcat file
    .venv/bin/python tutorials/03_control_stack.py --out DIR

It writes control_stack.png (all parts) and, unless --no-html, fallback.html (part 3) into --out
(default out/tutorials/03). It takes about 10 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import re
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator

from ace_drake.control.action_mapping import inverse_map_action, map_action
from ace_drake.control.feasible_set import feasible_sets, in_invariant_set, invariant_bounds, ramp_time
from ace_drake.control.params import ControlParams
from ace_drake.control.stack import make_control_stack
from ace_drake.diagrams import build_controlled_robot_diagram, start_controlled_robot
from ace_drake.robot.collision import TrajectoryCollisionChecker
from ace_drake.robot.model import load_scenario
from ace_drake.robot.params import JOINT_NAMES

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "out/tutorials/03"
SEED = 3  # numpy Generator seed for the random actions (part 1) and the random policy (part 4)
# Part 1: the start of the segment: the reset pose, each joint moving at this fraction of its
# command velocity limit, alternately forwards and backwards.
START_SPEED = 0.4
SET_JOINTS = ("gantry_x", "shoulder_pitch", "elbow", "wrist_1")  # part 1 plots these joints' sets
RANDOM_ACTIONS = 500
BOUNDARY_ACTIONS = 256  # actions on the boundary of the action square (64 per side)
# Part 1: a joint near its upper position limit, moving towards it (picked so that the cut is large).
NEAR_LIMIT_JOINT = "elbow"
NEAR_LIMIT_GAP = 0.2  # rad short of the command limit
NEAR_LIMIT_SPEED = 0.3  # fraction of the velocity limit, towards the limit
# Part 2: every joint's action is (+1, +1) (as far and as fast forwards as feasible) except these
# joints', which get (-1, -1); the plot shows PLOT_JOINTS.
BACKWARDS_JOINTS = ("shoulder_pitch", "wrist_1")
PLOT_JOINTS = ("gantry_x", "shoulder_pitch")
# Part 3: test_safety_supervisor's target, found with RobotModel.solve_racket_pose_ik: these joint
# values put the blade centre at (-1.1, 0, 0) m, inside the table top.
IN_THE_TABLE = np.array([0.398, -0.112, -0.043, 0.423, 0.333, -0.002, -0.748, 0.04])
FALLBACK_DURATION = 1.5  # s
FALLBACK_JOINT = "gantry_x"  # part 3 plots this joint's command and response
# Part 4: the light curtain is broken over [CURTAIN_BREAK, CURTAIN_CLEAR) s.
CURTAIN_BREAK, CURTAIN_CLEAR, CURTAIN_END = 0.3, 0.6, 0.8
COLORS = {"set": "tab:blue", "random": "tab:gray", "boundary": "tab:orange", "corner": "tab:red", "centre": "black"}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="directory for the PNG and HTML files")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML file")
    return parser.parse_args()


def save_html(meshcat, path: Path) -> None:
    """Writes the current Meshcat scene and recording as one self-contained HTML file."""
    path.write_text(meshcat.StaticHtml())
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB; open it in any browser)")


def unit(joint: int) -> str:
    """The gantry axes are prismatic (m), the arm's six joints revolute (rad)."""
    return "m" if JOINT_NAMES[joint].startswith("gantry") else "rad"


def square_boundary(per_side: int) -> np.ndarray:
    """(4 per_side, 2) points going round the boundary of [-1, 1]^2 (||x||_inf = 1), corners included."""
    s = np.linspace(-1.0, 1.0, per_side, endpoint=False)
    one = np.ones_like(s)
    return np.concatenate([np.stack([s, -one], 1), np.stack([one, s], 1), np.stack([-s, one], 1), np.stack([-one, -s], 1)])


def joint_actions(pairs: np.ndarray, joint: int) -> np.ndarray:
    """Actions (n, 16) whose joint ``joint`` has (position, velocity) components ``pairs`` (n, 2),
    all other components 0. (The mapping is per joint, so the others do not matter.)"""
    actions = np.zeros((len(pairs), 2, len(JOINT_NAMES)))
    actions[:, 0, joint], actions[:, 1, joint] = pairs[:, 0], pairs[:, 1]
    return actions.reshape(len(pairs), -1)  # row-major (2, 8): positions, then velocities


def boundary_gap(points: np.ndarray, sets, joint: int) -> np.ndarray:
    """How far (n, 2) points in (q, v) units lie past the edge lines of joint ``joint``'s polygon
    (the largest signed distance over its edges): < 0 inside, 0 on the boundary."""
    normals, offsets = sets.normals[joint], sets.offsets[joint]
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 0.0  # degenerate edges have a zero normal
    return np.max((points @ normals[keep].T - offsets[keep]) / lengths[keep], axis=1)


def polygon_area(vertices: np.ndarray) -> float:
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def refusal_cause(reason: str) -> str:
    """A refusal's reason in a few words. A predicted collision's reason (ControlStack.check) is
    the CollisionReport's text, which names the geometry pairs that would close first as
    'body/model::geometry - body/model::geometry': keep the first; otherwise the reason up to its
    first colon (e.g. "collision check over its budget")."""
    if reason.startswith("collision predicted"):
        pairs = re.findall(r"'([^']+ - [^']+)'", reason)
        return f"collision predicted: {pairs[0]}" if pairs else "collision predicted"
    return reason.split(":")[0]


def refusal_group(reason: str) -> str:
    """"court" or "self" for a predicted collision with the court or the robot itself, else "other"."""
    cause = refusal_cause(reason)
    if not cause.startswith("collision predicted: "):
        return "other"
    return "court" if "court::" in cause else "self"


def supervisor_counts(supervisor, context) -> tuple[int, int]:
    state = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context))
    return state.accepted, state.rejected


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    scenario = load_scenario()  # models/scenario.yaml: robot and court models, limits, eq. (9)
    control = ControlParams()  # the stack's margins and parameters (ace_drake/config.py)
    # The stack with Drake collision checking of every plan, exactly as the supervisor uses it.
    stack = make_control_stack(scenario, control)
    limits, period, T = stack.limits, stack.period, stack.segment_duration
    rng = np.random.default_rng(SEED)
    # One Meshcat viewer (a local web server); part 3 draws into it and saves an HTML file.
    meshcat = None if args.no_html else Meshcat()

    figure = plt.figure(figsize=(18, 16), layout="constrained")
    rows = figure.add_gridspec(2, 1, height_ratios=[0.85, 2.0])
    set_plots = rows[0].subgridspec(1, len(SET_JOINTS) + 1).subplots()
    lower = rows[1].subgridspec(1, 2, width_ratios=[1.0, 1.15])
    plan_plots = lower[0].subgridspec(3, len(PLOT_JOINTS)).subplots(sharex=True)
    right = lower[1].subgridspec(3, 1)
    fallback_plot = figure.add_subplot(right[0])
    clearance_plot = figure.add_subplot(right[1], sharex=fallback_plot)
    curtain_plot = figure.add_subplot(right[2])

    # ------------------------------------------------------------------------------------------
    # 1. The feasible set and the mapping (eq. (12))
    # ------------------------------------------------------------------------------------------
    # The command limits are the hardware limits shrunk by ControlParams' margins. For a segment
    # starting at (q0, v0, a0), each joint's feasible set F_i is the set of terminal states
    # (q_T, v_T) 32 ms ahead that (1) the spline QP can reach (bang-bang at reach_fraction of the
    # acceleration limit: a lens-shaped set around q0 + v0 T) and (2) lie in a control-invariant
    # set: from there a stop at stop_fraction of the acceleration limit, after a reaction time,
    # stays inside the position limits, so the next segment again has a non-empty set. F_i is
    # convex; feasible_sets represents it by a polygon of 2 x boundary_samples vertices.
    print("== 1. The feasible set and the mapping (eq. (12)) ==")
    print(f"segment T = {1000 * T:.0f} ms sampled every {1000 * period:.0f} ms; command limits:")
    print(f"{'joint':<16}{'unit':<6}{'lower':>7}{'upper':>7}{'velocity':>10}{'accel.':>9}{'jerk':>9}")
    for j, name in enumerate(JOINT_NAMES):
        print(f"{name:<16}{unit(j):<6}{limits.lower[j]:>+7.2f}{limits.upper[j]:>+7.2f}{limits.velocity[j]:>10.2f}"
              f"{limits.acceleration[j]:>9.1f}{limits.jerk[j]:>9.0f}")
    q0 = stack.reset_pose.copy()
    v0 = START_SPEED * limits.velocity * np.resize([1.0, -1.0], len(JOINT_NAMES))
    a0 = np.zeros(len(JOINT_NAMES))
    inside = in_invariant_set(q0, v0, limits, control, period)
    print(f"start: the reset pose, moving at +-{START_SPEED:.0%} of the velocity limits; in the invariant set: {bool(inside.all())}")
    sets = feasible_sets(q0, v0, a0, limits, control, period)

    # An action is (2, 8) row-major: row 0 the joints' position components, row 1 the velocity
    # components. Per joint, eq. (12) maps the square [-1, 1]^2 onto F_i radially: the centre to
    # F_i's centre, each ray from it scaled (through F_i's half-widths) so that the square's
    # boundary lands on F_i's boundary. So a uniform action does not give a uniform terminal state.
    random_actions = rng.uniform(-1.0, 1.0, (RANDOM_ACTIONS, 16))
    q_random, v_random = map_action(random_actions, sets)  # (500, 8) each
    all_inside = sets.contains(np.stack([q_random, v_random], axis=-1)).all()
    print(f"{RANDOM_ACTIONS} uniform random actions: all mapped into the feasible sets: {bool(all_inside)}")
    # Actions with every component +-1: 256 of the 2^16, in which each joint gets all four sign
    # pairs. They land on only 4 points per joint, the images of the square's corners (the mapping
    # is per joint); the square's whole boundary lands on F_i's boundary.
    corner_actions = np.array(list(itertools.product([-1.0, 1.0], repeat=8)))  # 256 x (8 position signs)
    corner_actions = np.concatenate([corner_actions, corner_actions[:, ::-1]], axis=1)  # velocity signs: reversed
    q_corner, v_corner = map_action(corner_actions, sets)
    square = square_boundary(BOUNDARY_ACTIONS // 4)
    print(f"{'joint':<16}{'centre q':>10}{'centre v':>10}{'half-widths (q, v)':>22}"
          f"{'corner images':>15}{'max |gap| of boundary images':>30}")
    for j, name in enumerate(JOINT_NAMES):
        q_edge, v_edge = map_action(joint_actions(square, j), sets)
        gap = np.abs(boundary_gap(np.stack([q_edge[:, j], v_edge[:, j]], 1), sets, j)).max()
        corners = len(np.unique(np.round(np.stack([q_corner[:, j], v_corner[:, j]], 1), 12), axis=0))
        print(f"{name:<16}{sets.centre[j, 0]:>+10.3f}{sets.centre[j, 1]:>+10.3f}"
              f"{f'({sets.scale[j, 0]:.3f}, {sets.scale[j, 1]:.2f})':>22}{corners:>15}{gap:>27.1e} {unit(j)}")
    q_zero, v_zero = map_action(np.zeros(16), sets)
    print(f"action 0 -> the centres: largest difference {np.abs(np.stack([q_zero, v_zero], 1) - sets.centre).max():.1e}")
    # The inverse map casts the ray back: a policy trained elsewhere, or a controller thinking in
    # joint targets (ControlStack.action_towards), gets the action of any terminal state.
    action = random_actions[0]
    round_trip = inverse_map_action(*map_action(action, sets), sets)
    print(f"inverse_map_action(map_action(a)) - a for one random action: largest |difference| {np.abs(round_trip - action).max():.1e}; "
          f"over all {RANDOM_ACTIONS}: {np.abs(inverse_map_action(q_random, v_random, sets) - random_actions).max():.1e}")

    for ax, name in zip(set_plots, SET_JOINTS):
        j = JOINT_NAMES.index(name)
        ax.fill(*sets.vertices[j].T, color=COLORS["set"], alpha=0.2, label="feasible set $F_i$")
        ax.plot(*np.vstack([sets.vertices[j], sets.vertices[j][:1]]).T, color=COLORS["set"], linewidth=1)
        # Images of the concentric squares ||delta||_inf = 0.25, 0.5, 0.75: the mapping's radial grid.
        for size in (0.25, 0.5, 0.75):
            ring = map_action(joint_actions(size * square_boundary(32), j), sets)
            ax.plot(np.append(ring[0][:, j], ring[0][0, j]), np.append(ring[1][:, j], ring[1][0, j]),
                    color=COLORS["set"], linewidth=0.5, alpha=0.6)
        ax.plot(q_random[:, j], v_random[:, j], ".", color=COLORS["random"], markersize=2, label=f"{RANDOM_ACTIONS} random actions")
        q_edge, v_edge = map_action(joint_actions(square, j), sets)
        ax.plot(q_edge[:, j], v_edge[:, j], ".", color=COLORS["boundary"], markersize=3, label=f"{BOUNDARY_ACTIONS} actions on the square's boundary")
        ax.plot(q_corner[:, j], v_corner[:, j], "s", color=COLORS["corner"], markersize=5, label="256 actions of all +-1 (corners)")
        ax.plot(*sets.centre[j], "+", color=COLORS["centre"], markersize=14, markeredgewidth=2, label="centre")
        ax.plot(q_zero[j], v_zero[j], "o", color=COLORS["centre"], markerfacecolor="none", markersize=9, label="action 0")
        ax.set(title=f"(1) {name}: $F_i$ and eq. (12)", xlabel=f"q_T ({unit(j)})", ylabel=f"v_T ({unit(j)}/s)")
    set_plots[0].legend(loc="lower right", fontsize=7)

    # Near a position limit. A joint heading for its limit must keep a stopping distance at the
    # end of the segment: invariant_bounds gives the largest terminal position hi(v_T) from which
    # the stop (reaction time, then braking) still ends inside the limits; it cuts off the part of
    # the reachable set beyond it. The reachable set alone is feasible_sets with the position
    # limits moved far away.
    j = JOINT_NAMES.index(NEAR_LIMIT_JOINT)
    q_near, v_near = q0.copy(), v0.copy()
    q_near[j] = limits.upper[j] - NEAR_LIMIT_GAP
    v_near[j] = NEAR_LIMIT_SPEED * limits.velocity[j]
    near_inside = in_invariant_set(q_near, v_near, limits, control, period)
    near = feasible_sets(q_near, v_near, a0, limits, control, period)
    unlimited = dataclasses.replace(limits, lower=limits.lower - 100.0, upper=limits.upper + 100.0)
    reachable = feasible_sets(q_near, v_near, a0, unlimited, control, period)
    kept = polygon_area(near.vertices[j]) / polygon_area(reachable.vertices[j])
    print(
        f"{NEAR_LIMIT_JOINT} {NEAR_LIMIT_GAP} rad below its upper limit moving towards it at {v_near[j]:.2f} rad/s: "
        f"in the invariant set: {bool(near_inside[j])}; the feasible set keeps {kept:.0%} of the reachable set's area, "
        f"its terminal velocity at most {near.vertices[j][:, 1].max():.2f} rad/s (reachable: {reachable.vertices[j][:, 1].max():.2f})"
    )
    ax = set_plots[-1]
    ax.fill(*reachable.vertices[j].T, color="tab:gray", alpha=0.15, label="reachable by the QP")
    ax.fill(*near.vertices[j].T, color=COLORS["set"], alpha=0.3, label="feasible set (reachable and invariant)")
    velocities = np.linspace(reachable.vertices[j][:, 1].min(), reachable.vertices[j][:, 1].max(), 200)
    v_grid = np.tile(v_near, (len(velocities), 1))
    v_grid[:, j] = velocities
    _, hi = invariant_bounds(v_grid, limits, control, ramp_time(control, period))  # as feasible_sets does
    ax.plot(hi[:, j], velocities, color="tab:purple", label="invariant bound hi(v_T)")
    ax.axvline(limits.upper[j], color="black", linestyle="--", linewidth=1, label="command limit")
    q_near_random, v_near_random = map_action(random_actions, near)
    ax.plot(q_near_random[:, j], v_near_random[:, j], ".", color=COLORS["random"], markersize=2)
    ax.plot(*near.centre[j], "+", color=COLORS["centre"], markersize=14, markeredgewidth=2)
    ax.set(title=f"(1) {NEAR_LIMIT_JOINT} near its upper limit", xlabel="q_T (rad)", ylabel="v_T (rad/s)",
           xlim=(reachable.vertices[j][:, 0].min() - 0.02, limits.upper[j] + 0.02))
    ax.legend(loc="lower left", fontsize=7)

    # ------------------------------------------------------------------------------------------
    # 2. A segment and its reset
    # ------------------------------------------------------------------------------------------
    # ControlStack.propose runs the four stages of one control step: the mapping (above), the spline
    # QP (a cubic spline with a knot every 1 ms minimising the integrated squared jerk, from the
    # current (q, v, a) to exactly (q_T, v_T), within the limits at every sample; DAQP), the reset
    # (Ruckig: time-optimal and jerk-limited, all joints arriving together at the reset pose at
    # rest) and the collision check of segment + reset (conservative advancement on Drake's
    # signed distances: provably clear for the continuous motion, not only at the samples).
    print("\n== 2. A segment and its reset ==")
    extreme = np.ones((2, len(JOINT_NAMES)))
    for name in BACKWARDS_JOINTS:
        extreme[:, JOINT_NAMES.index(name)] = -1.0
    stack.propose(q0, v0, a0, extreme.ravel())  # once to warm up (first calls allocate)
    proposal = stack.propose(q0, v0, a0, extreme.ravel())
    print(f"action: (+1, +1) for every joint but {', '.join(BACKWARDS_JOINTS)} (-1, -1); safe: {proposal.safe} {proposal.reason}")
    timings = ", ".join(f"{stage} {1000 * seconds:.2f}" for stage, seconds in proposal.seconds.items())
    print(f"stage wall times (ms): {timings}; total {1000 * sum(proposal.seconds.values()):.2f} of the 5 ms budget")
    segment, reset, plan = proposal.segment, proposal.reset, proposal.plan
    q_T, v_T = proposal.target
    reached = max(np.abs(segment.q[-1] - q_T).max(), np.abs(segment.v[-1] - v_T).max())
    print(f"segment: {segment.samples} samples; its end is the mapped target to {reached:.1e}; "
          f"terminal acceleration (free in the QP, the next segment's start) up to {np.abs(segment.a[-1] / limits.acceleration).max():.0%} of the limit")
    print(f"reset: {reset.duration:.3f} s to the reset pose, ending at rest (|v| {np.abs(reset.v[-1]).max():.0f}, |a| {np.abs(reset.a[-1]).max():.0f})")
    print(f"limits.violations(segment + reset): {limits.violations(plan)}")
    peak = np.max(np.abs(plan.v) / limits.velocity), np.max(np.abs(plan.a) / limits.acceleration)
    print(f"peak commanded velocity {peak[0]:.0%}, acceleration {peak[1]:.0%} of the command limits")

    times = 1000 * period * np.arange(plan.samples + 1)
    for column, name in enumerate(PLOT_JOINTS):
        j = JOINT_NAMES.index(name)
        u = unit(j)
        for row, (values, label, bound) in enumerate((
            (plan.q, f"q ({u})", (limits.lower[j], limits.upper[j])),
            (plan.v, f"v ({u}/s)", (-limits.velocity[j], limits.velocity[j])),
            (plan.a, f"a ({u}/s$^2$)", (-limits.acceleration[j], limits.acceleration[j])),
        )):
            ax = plan_plots[row, column]
            ax.plot(times[: segment.samples + 1], values[: segment.samples + 1, j], color="tab:blue", linewidth=2, label="segment (spline QP)")
            ax.plot(times[segment.samples:], values[segment.samples:, j], color="tab:green", linewidth=2, label="reset (Ruckig)")
            for value in bound:
                ax.axhline(value, color="black", linestyle="--", linewidth=1)
            ax.axvline(1000 * T, color="tab:red", linewidth=0.8)
            ax.set(ylabel=label)
        plan_plots[0, column].plot(1000 * T, q_T[j], "o", color="tab:red", label="mapped target (q_T, v_T)")
        plan_plots[1, column].plot(1000 * T, v_T[j], "o", color="tab:red")
        plan_plots[0, column].axhline(stack.reset_pose[j], color="tab:green", linestyle=":", linewidth=1, label="reset pose")
        plan_plots[0, column].set_title(f"(2) {name}: segment, then reset")
        plan_plots[2, column].set(xlabel="time (ms)")
    plan_plots[0, 0].plot([], [], color="black", linestyle="--", linewidth=1, label="command limits")
    plan_plots[0, 0].plot([], [], color="tab:red", linewidth=0.8, label="end of the 32 ms segment")
    plan_plots[0, 0].legend(loc="upper right", fontsize=8)

    # ------------------------------------------------------------------------------------------
    # 3. The fallback: a policy that drives into the table
    # ------------------------------------------------------------------------------------------
    # The policy aims every joint at IN_THE_TABLE as fast as the limits allow (action_towards
    # inverts the mapping). Each proposal's segment is feasible and within the limits; what makes
    # it unsafe is where it leads. The supervisor checks segment + reset: if any point of the robot
    # would come within collision_margin of the court or of itself (the racket's handle folds
    # towards the forearm on the way), or if the check cannot prove the motion clear within its
    # deadline of collision_query_budget distance queries (fail safe), it refuses the segment and
    # keeps its plan, the reset of the last accepted segment, which takes the robot back towards
    # the reset pose; from there the policy tries again. The robot never touches the table.
    print("\n== 3. The fallback: a policy driving the racket into the table ==")
    holder = {}

    def into_the_table(observation: np.ndarray) -> np.ndarray:
        q, v, a = np.split(observation, 3)  # the state where its segment starts
        return holder["stack"].action_towards(q, v, a, IN_THE_TABLE)

    diagram = build_controlled_robot_diagram(into_the_table, scenario, control, meshcat)
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    holder["stack"] = supervisor.stack
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    start_controlled_robot(diagram, context)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=30.0, set_visualizations_while_recording=False)
    # Step segment by segment to see each decision (the supervisor decides at each boundary).
    decisions = []  # (boundary time, "accepted" | "refused", the refusal's reason)
    boundaries = np.arange(T, FALLBACK_DURATION + 1e-9, T)
    previous = supervisor_counts(supervisor, context)
    for boundary in boundaries:
        simulator.AdvanceTo(boundary + 0.5 * period)
        counts = supervisor_counts(supervisor, context)
        if counts != previous:
            reason = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context)).last_reason
            decisions.append((boundary, "accepted", "") if counts[0] > previous[0] else (boundary, "refused", reason))
        previous = counts
    simulator.AdvanceTo(FALLBACK_DURATION)
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        save_html(meshcat, args.out / "fallback.html")
        written.append(args.out / "fallback.html")
    state = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context))
    print(f"{FALLBACK_DURATION} s: {state.accepted} segments accepted, {state.rejected} refused")
    # (state.last_reason is cleared by the next accepted segment: the decisions keep every reason.)
    refusals = [(t, reason) for t, kind, reason in decisions if kind == "refused"]
    if refusals:
        print(f"last refusal (t = {refusals[-1][0]:.3f} s): {refusals[-1][1]}")
        print(f"refusals from t = {refusals[0][0]:.3f} s on, by cause (for a collision: the pair predicted to close first):")
        causes = [refusal_cause(reason) for _, reason in refusals]
        for cause in sorted(set(causes)):
            print(f"  {causes.count(cause):>3} x {cause}")
    else:
        print("no segment was refused")
    commands = diagram.GetSubsystemByName("command_logger").FindLog(context)
    joints = diagram.GetSubsystemByName("joint_logger").FindLog(context)
    # The clearance of the simulated joints (eq. (9): they trail the command) every 2 ms: the
    # signed distances of the checked geometry pairs within the checker's influence distance,
    # split into robot-court pairs (table, net, floor) and robot-robot pairs.
    checker = TrajectoryCollisionChecker(scenario, margin=0.0)
    joint_times = joints.sample_times()[::2]
    court_clearance, self_clearance, closest_pair = [], [], []
    for q in joints.data()[:8, ::2].T:
        pairs = checker.pair_distances(q)  # closest first
        court = [(name, d) for name, d in pairs if "court::" in name]
        court_clearance.append(court[0][1] if court else checker.influence)
        closest_pair.append(court[0][0] if court else "")
        self_clearance.append(min([d for name, d in pairs if "court::" not in name], default=checker.influence))
    court_clearance, self_clearance = np.array(court_clearance), np.array(self_clearance)
    closest = int(np.argmin(court_clearance))
    print(f"minimum clearance of the logged joint configurations to the court: {1000 * court_clearance[closest]:.1f} mm "
          f"at t = {joint_times[closest]:.3f} s ({closest_pair[closest]}; collision_margin {1000 * control.collision_margin:.0f} mm); "
          f"to the robot itself: {1000 * self_clearance.min():.1f} mm")

    j = JOINT_NAMES.index(FALLBACK_JOINT)
    fallback_plot.plot(commands.sample_times(), commands.data()[j], color="tab:blue", label="command")
    fallback_plot.plot(joints.sample_times(), joints.data()[j], color="tab:orange", linestyle="--", label="joint (eq. (9))")
    fallback_plot.axhline(IN_THE_TABLE[j], color="tab:red", linestyle=":", label="the policy's goal (racket in the table)")
    height = stack.reset_pose[j] - 0.05
    accepted_times = [t for t, kind, _ in decisions if kind == "accepted"]
    fallback_plot.plot(accepted_times, np.full(len(accepted_times), height), "|", color="tab:green", markersize=8, label="segment accepted")
    for group, color, label in (("court", "tab:red", "refused: robot would near the court"),
                                 ("self", "tab:purple", "refused: robot would near itself"),
                                 ("other", "tab:brown", "refused: not proven clear in time")):
        marks = [t for t, reason in refusals if refusal_group(reason) == group]
        if marks:
            fallback_plot.plot(marks, np.full(len(marks), height), "x", color=color, markersize=8, label=label)
    fallback_plot.set(title=f"(3) The fallback: {FALLBACK_JOINT} under the into-the-table policy", ylabel=f"{FALLBACK_JOINT} ({unit(j)})")
    fallback_plot.legend(loc="center right", fontsize=8)
    fallback_plot.tick_params(labelbottom=False)
    clearance_plot.plot(joint_times, 1000 * court_clearance, color="tab:blue", label="robot to court (table, net, floor)")
    clearance_plot.plot(joint_times, 1000 * self_clearance, color="tab:gray", linewidth=1, label="robot to itself")
    clearance_plot.axhline(1000 * control.collision_margin, color="tab:red", linestyle="--", label="collision_margin")
    clearance_plot.set(title="(3) The logged joints' clearance", xlabel="time (s)", ylabel="clearance (mm)",
                       ylim=(0.0, min(1000 * checker.influence, 1.3e3 * max(self_clearance.max(), court_clearance[closest:].max()))))
    clearance_plot.legend(loc="upper right", fontsize=8)

    # ------------------------------------------------------------------------------------------
    # 4. The light curtain
    # ------------------------------------------------------------------------------------------
    # A random policy (uniform actions) drives the robot. At CURTAIN_BREAK someone breaks the light
    # curtain (the diagram's input port 0): at its next 1 ms update the supervisor replaces its plan
    # with the protective stop, every joint braking on its own as fast as its acceleration and jerk
    # limits allow, and accepts no segment until the curtain clears.
    print("\n== 4. The light curtain ==")
    policy_rng = np.random.default_rng(SEED)
    diagram = build_controlled_robot_diagram(lambda observation: policy_rng.uniform(-1.0, 1.0, 16), scenario, control)
    supervisor = diagram.GetSubsystemByName("safety_supervisor")
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    start_controlled_robot(diagram, context, light_curtain=0.0)
    simulator.AdvanceTo(CURTAIN_BREAK)
    at_break = supervisor_counts(supervisor, context)
    diagram.GetInputPort("light_curtain").FixValue(context, [1.0])
    simulator.AdvanceTo(CURTAIN_CLEAR)
    state = supervisor.supervisor_state(supervisor.GetMyContextFromRoot(context))
    at_clear = state.accepted, state.rejected
    stop_start = state.plan_start * period
    diagram.GetInputPort("light_curtain").FixValue(context, [0.0])
    simulator.AdvanceTo(CURTAIN_END)
    at_end = supervisor_counts(supervisor, context)
    commands = diagram.GetSubsystemByName("command_logger").FindLog(context)
    times = commands.sample_times()
    q_cmd, v_cmd, a_cmd = np.split(commands.data(), 3)
    # The commanded state where the stop began, and the stop ControlStack plans from it.
    k_stop = int(np.argmin(np.abs(times - stop_start)))
    stop, _ = stack.protective_stop(q_cmd[:, k_stop], v_cmd[:, k_stop], a_cmd[:, k_stop])
    broken = (times >= CURTAIN_BREAK) & (times < CURTAIN_CLEAR)
    moving = broken & np.any(v_cmd != 0.0, axis=0)
    at_rest = times[moving].max() + period if moving.any() else CURTAIN_BREAK
    # The joint that took longest to stop: the last nonzero commanded velocity of each joint.
    stop_times = [times[broken & (v_cmd[j] != 0.0)].max(initial=CURTAIN_BREAK) + period for j in range(len(JOINT_NAMES))]
    slowest = int(np.argmax(stop_times))
    print(f"curtain broken at t = {CURTAIN_BREAK:.3f} s; protective stop from t = {stop_start:.3f} s "
          f"({state.last_reason!r}, stopped: {state.stopped})")
    print(f"commanded velocity zero for every joint from t = {at_rest:.3f} s: {1000 * (at_rest - CURTAIN_BREAK):.0f} ms after the break "
          f"(plan_stop from the commanded state: {1000 * stop.duration:.0f} ms); the last to stop, {JOINT_NAMES[slowest]}, was moving at "
          f"{v_cmd[slowest, k_stop]:+.2f} {unit(slowest)}/s ({np.abs(v_cmd[slowest, k_stop]) / limits.velocity[slowest]:.0%} of its limit) "
          f"and accelerating at {a_cmd[slowest, k_stop]:+.1f} {unit(slowest)}/s^2")
    held = times >= at_rest
    held &= times < CURTAIN_CLEAR
    still = bool(np.all(v_cmd[:, held] == 0.0) and np.all(np.ptp(q_cmd[:, held], axis=1) == 0.0))
    print(f"held exactly still (v = 0, q unchanged) from then until the curtain cleared: {still}")
    while_broken = "no new segments while broken" if at_clear == at_break else f"{at_clear[0] - at_break[0]} accepted while broken (a bug)"
    print(f"segments accepted / refused: {at_break[0]} / {at_break[1]} at the break, {at_clear[0]} / {at_clear[1]} when it cleared "
          f"at t = {CURTAIN_CLEAR:.3f} s: {while_broken}; {at_end[0]} / {at_end[1]} at t = {CURTAIN_END:.3f} s")

    for j, name in enumerate(JOINT_NAMES):
        curtain_plot.plot(times, v_cmd[j] / limits.velocity[j], linewidth=1, label=name)
    curtain_plot.axvspan(CURTAIN_BREAK, CURTAIN_CLEAR, color="tab:red", alpha=0.1, label="light curtain broken")
    curtain_plot.axvline(at_rest, color="black", linestyle=":", linewidth=1, label="all at rest")
    curtain_plot.set(title="(4) The light curtain: commanded velocities under a random policy", xlabel="time (s)",
                     ylabel="v / velocity limit", xlim=(0.0, CURTAIN_END), ylim=(-1.05, 1.05))
    curtain_plot.legend(loc="lower left", ncols=5, fontsize=7)

    png = args.out / "control_stack.png"
    figure.savefig(png, dpi=100)
    written.insert(0, png)

    print("\n== Files ==")
    if meshcat is None:
        print("(--no-html: Meshcat file skipped)")
    for path in written:
        print(f"  {path}")


if __name__ == "__main__":
    main()
