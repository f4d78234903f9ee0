"""Tutorial 02: the robot, its delayed joints, and one scripted swing that returns a ball.

Read this file top to bottom like a notebook. It shows

  1. the robot in Meshcat: its eight joints and their limits, where the racket sits at the ready
     pose, and a tour that moves each joint in turn through a good part of its range;
  2. the delayed joint plant (paper eq. (9)): one step of the commanded position, the simulated
     joint between the 1 kHz samples against the analytic step response, and the lag behind a ramp;
  3. reaching a recorded contact point: inverse kinematics that puts the racket on the median ball
     position at which the real robot hit the ball in its matches against elite players;
  4. a scripted swing: an open-loop joint trajectory, planned from the incoming ball's true state,
     that hits the ball at the top of its bounce and returns it to the human's half.

Every simulation is a Drake Diagram run by a Simulator: the swing diagram of ace_drake.diagrams
(the joints drive a kinematics-only MultibodyPlant whose racket is the BallPlant's racket) in parts
1 and 4, and the DelayedJointPlant alone in part 2. Numbers are SI units (m, s, rad). Run it from
the repository root:

    .venv/bin/python tutorials/02_robot.py                # all parts
    .venv/bin/python tutorials/02_robot.py --no-html      # skip the Meshcat files
    .venv/bin/python tutorials/02_robot.py --data PATH --out DIR

It writes robot.png (parts 2 and 4) and, unless --no-html, joint_tour.html, contact_point.html and
scripted_swing.html into --out (default out/tutorials/02). Part 3 needs the recorded match data
(default ../shared/data/ace_match_events_elite.csv beside the repository); without it that part is
skipped. It takes about 20 s.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import TrajectorySource, VectorLogSink
from pydrake.trajectories import PiecewisePolynomial

from ace_drake.analysis.reach import robot_contact_points
from ace_drake.analysis.scripted_swing import INCOMING_BALL, plan_scripted_swing, run_scripted_swing
from ace_drake.control.joint_model import ProcessModel, ramp_tracking_lag, step_response
from ace_drake.diagrams import build_swing_diagram, make_simulator
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.robot.model import RobotModel, load_scenario
from ace_drake.robot.params import JOINT_NAMES
from ace_drake.systems.delayed_joint_plant import DelayedJointPlant

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO_ROOT.parent / "shared/data/ace_match_events_elite.csv"
DEFAULT_OUT = REPO_ROOT / "out/tutorials/02"
TOUR_REACH = 0.8  # each joint heads this fraction of the way from the ready pose to each limit...
TOUR_CLEARANCE = 0.01  # ...reduced until the robot stays this far (m) from itself and the court
TOUR_SPEED = 0.5  # peak commanded speed and acceleration as a fraction of each joint's limits
TOUR_PAUSE = 0.2  # s at rest at the ready pose before and after the tour
STEP_JOINT = "elbow"  # part 2 plots this joint (all joints share the default eq. (9) parameters)
STEP_SIZE = 0.1  # rad (m for the gantry): the commanded step of part 2
STEP_TIME = 0.005  # s; on a 1 kHz sample, so the interface takes the new command at this instant
RACKET_COLOR, BALL_COLOR = "tab:blue", "tab:orange"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="recorded match events CSV (part 3)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="directory for the PNG and HTML files")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML files")
    return parser.parse_args()


def save_html(meshcat, path: Path) -> None:
    """Writes the current Meshcat scene and recording as one self-contained HTML file."""
    path.write_text(meshcat.StaticHtml())
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB; open it in any browser)")


def tour_extreme(model: RobotModel, joint: int, limit: float) -> float:
    """How far joint ``joint`` can move from the ready pose towards ``limit`` with the others held:
    TOUR_REACH of the way, less in steps of 10 % while any pose on the way (checked every 1/20)
    brings robot geometry within TOUR_CLEARANCE of itself or the court."""
    ready = model.ready_pose
    for reach in np.arange(TOUR_REACH, 0.0, -0.1):
        extreme = ready[joint] + reach * (limit - ready[joint])
        poses = np.tile(ready, (21, 1))
        poses[:, joint] = np.linspace(ready[joint], extreme, 21)
        if not any(model.colliding_pairs(q, TOUR_CLEARANCE) for q in poses):
            return float(extreme)
    return float(ready[joint])


def joint_tour_command(model: RobotModel, extremes: np.ndarray) -> PiecewisePolynomial:
    """q*(t) (8 x 1): from the ready pose each joint in turn goes to its lower extreme, across to its
    upper one and back, the others held at the ready pose. Shape-preserving cubics with zero
    velocity at every waypoint (each is a turning point or a rest), so every segment is a cubic
    from rest to rest with peak speed 1.5 d / T and peak acceleration 6 d / T^2 over distance d
    and duration T: the durations keep both within TOUR_SPEED of the joint's limits."""
    ready = model.ready_pose
    times, waypoints = [0.0, TOUR_PAUSE], [ready, ready]
    for joint, (low, high) in enumerate(extremes):
        for target in (low, high, ready[joint]):
            distance = abs(target - waypoints[-1][joint])
            duration = max(
                0.2,
                1.5 * distance / (TOUR_SPEED * model.velocity_limit[joint]),
                np.sqrt(6.0 * distance / (TOUR_SPEED * model.acceleration_limit[joint])),
            )
            waypoint = ready.copy()
            waypoint[joint] = target
            times.append(times[-1] + duration)
            waypoints.append(waypoint)
    times.append(times[-1] + TOUR_PAUSE)
    waypoints.append(ready)
    return PiecewisePolynomial.CubicShapePreserving(times, np.column_stack(waypoints), zero_end_point_derivatives=True)


def peak_rates(trajectory: PiecewisePolynomial, order: int) -> np.ndarray:
    """Each joint's largest |d^order q*/dt^order| (8,) over the trajectory, sampled every ms."""
    derivative = trajectory.derivative(order)
    times = np.arange(trajectory.start_time(), trajectory.end_time(), 1e-3)
    return np.max(np.abs([derivative.value(t)[:, 0] for t in times]), axis=0)


def draw_table_side_view(ax, params: BallPhysicsParams) -> None:
    """The playing surface (z = 0) and the net in the x-z plane."""
    half_length = 0.5 * params.table.length
    ax.plot([-half_length, half_length], [0.0, 0.0], color="tab:green", linewidth=4, label="table surface")
    ax.plot([0.0, 0.0], [0.0, params.net.height], color="black", linewidth=2, label="net")


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    params = BallPhysicsParams()  # the paper's ball model, with the authors' published constants
    scenario = load_scenario()  # models/scenario.yaml: robot and court models, limits, eq. (9)
    model = RobotModel(scenario)  # a MultibodyPlant of robot and court for kinematics and collisions
    # One Meshcat viewer (a local web server); parts 1, 3 and 4 draw into it and save HTML files.
    meshcat = None if args.no_html else Meshcat()

    figure = plt.figure(figsize=(13, 9), layout="constrained")
    grid = figure.add_gridspec(2, 2, height_ratios=[1.0, 0.7], width_ratios=[1.0, 1.2])
    step_plot = figure.add_subplot(grid[0, 0])
    time_grid = grid[0, 1].subgridspec(2, 1)
    x_plot = figure.add_subplot(time_grid[0])
    z_plot = figure.add_subplot(time_grid[1], sharex=x_plot)
    side_view = figure.add_subplot(grid[1, :])

    # ------------------------------------------------------------------------------------------
    # 1. The robot in Meshcat
    # ------------------------------------------------------------------------------------------
    # Ace stands behind its end of the table (x < -1.37 m). Two prismatic gantry axes carry a
    # six-joint arm: gantry_x moves the arm towards the table and back, gantry_y across it; the
    # shoulder yaws and pitches, the elbow bends, and three wrist joints turn the racket (wrist_1
    # rolls about the forearm, wrist_2 and wrist_3 each turn at right angles to the axis before).
    # The racket frame R has its origin at the blade centre and its z axis along the forehand
    # normal. The scenario's limits are designed (the paper publishes none).
    print("== 1. The robot: joints, limits and a tour through them ==")
    kinds = [model.plant.GetJointByName(name, model.robot).type_name() for name in JOINT_NAMES]
    units = ["m" if kind == "prismatic" else "rad" for kind in kinds]
    print(f"{'joint':<16}{'type':<11}{'unit':<6}{'lower':>7}{'upper':>7}{'ready':>7}{'speed limit':>14}")
    for joint, name in enumerate(JOINT_NAMES):
        print(
            f"{name:<16}{kinds[joint]:<11}{units[joint]:<6}{model.lower[joint]:>+7.2f}{model.upper[joint]:>+7.2f}"
            f"{model.ready_pose[joint]:>+7.2f}{model.velocity_limit[joint]:>8.1f} {units[joint]}/s"
        )
    X_WR_ready = model.racket_pose(model.ready_pose)
    p_WR_ready, normal_ready = X_WR_ready.translation(), X_WR_ready.rotation().matrix()[:, 2]
    table_end = -0.5 * params.table.length
    print(
        f"ready pose: blade centre at {np.round(p_WR_ready, 2)} m ({table_end - p_WR_ready[0]:.2f} m behind the "
        f"table's end, {p_WR_ready[2]:.2f} m above the playing surface), forehand normal {np.round(normal_ready, 2) + 0.0}"
    )

    # The tour: each joint in turn from the ready pose towards both limits, as far as the robot
    # stays clear of itself and the table (RobotModel.colliding_pairs asks the SceneGraph for the
    # signed distances between all collision geometries): gantry_x stops short because further
    # forward the forearm would reach the table. The swing diagram plays the tour as the joints'
    # command; meanwhile a ball dropped on the human's half bounces in place, out of the racket's reach.
    extremes = np.array([[tour_extreme(model, j, model.lower[j]), tour_extreme(model, j, model.upper[j])] for j in range(8)])
    span = model.upper - model.lower
    print("the tour (with 1 cm clearance everywhere on the way):")
    for joint, name in enumerate(JOINT_NAMES):
        low, high = extremes[joint]
        print(f"  {name:<16}{low:+6.2f} .. {high:+6.2f}   {(high - low) / span[joint]:4.0%} of its range")
    tour = joint_tour_command(model, extremes)
    tour_speed = peak_rates(tour, 1)
    print(
        f"{tour.end_time():.1f} s; peak commanded speed {np.max(tour_speed / model.velocity_limit):.0%} "
        f"and acceleration {np.max(peak_rates(tour, 2) / model.acceleration_limit):.0%} of the limits"
    )

    diagram = build_swing_diagram(tour, scenario, params, meshcat, log_period=0.002)
    context = diagram.CreateDefaultContext()
    ball = diagram.GetSubsystemByName("ball")
    ball.SetBallState(ball.GetMyMutableContextFromRoot(context), make_state((0.8, 0.3, 0.4), (0, 0, 0), (0, 0, 0)))
    joints = diagram.GetSubsystemByName("joint_plant")
    joints.SetJointState(joints.GetMyMutableContextFromRoot(context), model.ready_pose)  # at rest, command = q
    simulator = make_simulator(diagram, context)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=30.0, set_visualizations_while_recording=False)
    simulator.AdvanceTo(tour.end_time())
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        save_html(meshcat, args.out / "joint_tour.html")
        written.append(args.out / "joint_tour.html")
    # How far each joint trailed its command: part 2 explains it.
    joint_log = diagram.GetSubsystemByName("joint_logger").FindLog(context)
    commanded = np.array([tour.value(t)[:, 0] for t in joint_log.sample_times()])
    tour_gap = np.max(np.abs(joint_log.data()[:8].T - commanded), axis=0)
    trailing = int(tour_gap.argmax())
    print(
        f"the joints trailed their command: {JOINT_NAMES[trailing]} the most, by up to "
        f"{1000 * tour_gap[trailing]:.0f} m{units[trailing]} (commanded at up to {tour_speed[trailing]:.1f} {units[trailing]}/s)"
    )

    # ------------------------------------------------------------------------------------------
    # 2. The delayed joint plant: paper eq. (9)
    # ------------------------------------------------------------------------------------------
    # Each joint is a second-order LTI system whose input, the commanded position q*, arrives
    # tau_d late:
    #     d/dt zeta = A zeta + b q*(t - tau_d),   zeta = [q, q_dot],   q = [1 0] zeta     (eq. (9))
    # with A = [[0, 1], [-w^2, -2 zeta w]], b = [0, w^2]. The 1 kHz interface samples q* at
    # t_n = n T and holds it. DelayedJointPlant keeps zeta at the last sample as discrete state and
    # computes the exact solution at whatever time its output is asked for, so a logger every
    # 0.1 ms sees the joint between samples. The analytic step response, shifted to the step, must
    # match it to rounding.
    print("\n== 2. The delayed joint plant (eq. (9)): a step of the command ==")
    joint_params = scenario.dynamics.joints
    process = ProcessModel.from_state_space(joint_params[JOINT_NAMES.index(STEP_JOINT)])
    print(
        f"w = {process.natural_frequency:.0f} rad/s, damping ratio {process.damping_ratio:.2f}, "
        f"delay tau_d = {1000 * process.delay:.1f} ms, sampled every {1000 * scenario.dynamics.command_period:.0f} ms"
    )
    end_time = 0.02
    step_command = PiecewisePolynomial.ZeroOrderHold(
        [0.0, STEP_TIME, end_time], np.column_stack([np.zeros(8), np.full(8, STEP_SIZE), np.full(8, STEP_SIZE)])
    )
    builder = DiagramBuilder()
    source = builder.AddNamedSystem("step_command", TrajectorySource(step_command))
    joint_plant = builder.AddNamedSystem("joint_plant", DelayedJointPlant(scenario.dynamics))
    logger = builder.AddNamedSystem("q_logger", VectorLogSink(8, 1e-4))  # 10x finer than the samples
    builder.Connect(source.get_output_port(), joint_plant.q_command_port)
    builder.Connect(joint_plant.q_port, logger.get_input_port())
    step_diagram = builder.Build()
    step_context = step_diagram.CreateDefaultContext()
    joint_plant.SetJointState(joint_plant.GetMyMutableContextFromRoot(step_context), np.zeros(8))
    Simulator(step_diagram, step_context).AdvanceTo(end_time)
    step_log = logger.FindLog(step_context)
    times, q_simulated = step_log.sample_times(), step_log.data()
    q_analytic = np.array([step_response(joint, times - STEP_TIME, STEP_SIZE) for joint in joint_params])
    plotted = JOINT_NAMES.index(STEP_JOINT)
    at_rest = times[np.flatnonzero(q_simulated[plotted] == 0.0)[-1]]  # the last logged time still at 0
    settled = times[np.flatnonzero(q_simulated[plotted] >= 0.9 * STEP_SIZE)[0]]
    overshoot = q_simulated[plotted].max() / STEP_SIZE - 1.0
    print(
        f"step of {STEP_SIZE} rad at t = {1000 * STEP_TIME:.0f} ms: the {STEP_JOINT} is still at 0 at {1000 * at_rest:.1f} ms, "
        f"reaches 90 % at {1000 * settled:.1f} ms, overshoots by {overshoot:.2%}"
    )
    print(f"largest difference from the analytic response, all joints, {len(times)} times: {np.abs(q_simulated - q_analytic).max():.1e}")
    # Along a ramp q* = v t the joint settles a fixed time behind: the delay plus the LTI lag
    # 2 zeta / w. Holding each 1 kHz sample for a period adds T / 2 on average (the held command
    # is 0 to T old). Together they explain how far part 1's joints trailed their command.
    lag, delay = ramp_tracking_lag(joint_params[trailing]), joint_params[trailing].delay
    period = scenario.dynamics.command_period
    print(
        f"ramp-tracking lag {1000 * lag:.1f} ms = {1000 * delay:.1f} ms delay + "
        f"{1000 * (lag - delay):.1f} ms (2 zeta / w); with the hold's T / 2 = {500 * period:.1f} ms, "
        f"{JOINT_NAMES[trailing]} at {tour_speed[trailing]:.1f} {units[trailing]}/s should trail by "
        f"{1000 * tour_speed[trailing] * (lag + 0.5 * period):.0f} m{units[trailing]} "
        f"(part 1: {1000 * tour_gap[trailing]:.0f} m{units[trailing]})"
    )
    # A swing must therefore be commanded ahead of time: plan_scripted_swing (part 4) issues the
    # exact inverse of eq. (9), tau_d early.

    fine_times = np.linspace(0.0, end_time, 2001)
    step_plot.plot(1000 * fine_times, np.array([step_command.value(t)[plotted, 0] for t in fine_times]),
                   color="tab:gray", label="command q*")
    step_plot.plot(1000 * fine_times, step_response(joint_params[plotted], fine_times - STEP_TIME, STEP_SIZE),
                   color="black", linewidth=1, label="analytic step response")
    step_plot.plot(1000 * times, q_simulated[plotted], ".", color=RACKET_COLOR, markersize=4,
                   label="DelayedJointPlant (every 0.1 ms)")
    step_plot.axvspan(1000 * STEP_TIME, 1000 * (STEP_TIME + process.delay), color="tab:red", alpha=0.15,
                      label=f"delay tau_d = {1000 * process.delay:.0f} ms")
    for sample in np.arange(0.0, end_time + 1e-9, scenario.dynamics.command_period):
        step_plot.axvline(1000 * sample, color="tab:gray", linewidth=0.3, alpha=0.5)
    step_plot.set(
        title=f"(a) Part 2: a step of the {STEP_JOINT}'s command (grid: 1 kHz samples)",
        xlabel="time (ms)",
        ylabel=f"{STEP_JOINT} angle q (rad)",
        xlim=(0.0, 1000 * end_time),
    )
    step_plot.legend(loc="lower right", fontsize=9)

    # ------------------------------------------------------------------------------------------
    # 3. Reaching a recorded contact point
    # ------------------------------------------------------------------------------------------
    # The match data hold the ball's position at each of the real robot's hits. Inverse kinematics
    # (Drake's InverseKinematics, solved by SNOPT/IPOPT from seeds behind the point) finds joint
    # values that put a ball at the median of those positions against the forehand face, the face
    # within 45 degrees of +x, everything 1 cm clear of the court and itself. The racket Jacobian
    # there tells which joints drive a forward swing.
    print("\n== 3. Reaching the median recorded contact point ==")
    if not args.data.is_file():
        print(f"match data not found at {args.data}: skipping part 3 (pass --data PATH to the CSV)")
    else:
        contact_points = robot_contact_points(args.data)
        p_WB = np.median(contact_points, axis=0)  # per coordinate
        print(f"{len(contact_points)} recorded robot hits; median ball position {np.round(p_WB, 3)} m")
        ik = model.solve_racket_ik(p_WB)
        if not ik.success:
            print(f"inverse kinematics failed after {ik.attempts} seeds ({ik.solve_time * 1000:.0f} ms)")
        else:
            X_WR = model.racket_pose(ik.q)
            normal = X_WR.rotation().matrix()[:, 2]
            print(f"solved in {ik.solve_time * 1000:.1f} ms ({ik.attempts} seed{'s' if ik.attempts > 1 else ''}):")
            for name, value, ready in zip(JOINT_NAMES, ik.q, model.ready_pose):
                print(f"  {name:<16}{value:+6.3f}   (ready {ready:+6.2f})")
            print(
                f"blade centre {np.round(X_WR.translation(), 3)} m, {100 * np.linalg.norm(X_WR.translation() - p_WB):.1f} cm "
                f"from the ball centre; normal {np.degrees(np.arccos(normal[0])):.0f} deg from +x"
            )
            # Row 3 of J (6 x 8, [w; v] of the blade centre) is d(racket x)/dq: times each joint's
            # speed limit, how fast that joint alone could drive the racket towards the opponent.
            forward = model.racket_jacobian(ik.q)[3] * model.velocity_limit
            order = np.argsort(-np.abs(forward))[:3]
            print("fastest forward racket speed from one joint at its limit: " + ", ".join(
                f"{JOINT_NAMES[j]} {abs(forward[j]):.1f} m/s" for j in order))
            if meshcat is not None:
                # A snapshot: the swing diagram holding q, the ball on the face. Initialize()
                # publishes once, which draws the robot and the ball.
                meshcat.Delete()
                meshcat.DeleteRecording()
                hold = build_swing_diagram(PiecewisePolynomial(ik.q[:, None]), scenario, params, meshcat)
                hold_context = hold.CreateDefaultContext()
                hold_ball = hold.GetSubsystemByName("ball")
                hold_ball.SetBallState(hold_ball.GetMyMutableContextFromRoot(hold_context), make_state(p_WB, (0, 0, 0), (0, 0, 0)))
                hold_joints = hold.GetSubsystemByName("joint_plant")
                hold_joints.SetJointState(hold_joints.GetMyMutableContextFromRoot(hold_context), ik.q)
                make_simulator(hold, hold_context).Initialize()
                save_html(meshcat, args.out / "contact_point.html")
                written.append(args.out / "contact_point.html")

    # ------------------------------------------------------------------------------------------
    # 4. A scripted swing
    # ------------------------------------------------------------------------------------------
    # plan_scripted_swing predicts the incoming ball, picks the top of its bounce on the robot's half
    # as the hit, solves the racket normal and velocity (the inverted racket contact model, paper
    # eqs (7)-(8); control/returner.py) for a return that lands near (0.8, 0) m, solves the IK for that racket pose, and joins the ready
    # pose, the hit and a stop with a cubic joint trajectory within the limits. Its command is the
    # exact inverse of eq. (9), issued tau_d early. run_scripted_swing then plays that command
    # open-loop in the swing diagram: nothing corrects the swing once it has started.
    print("\n== 4. A scripted swing ==")
    swing = plan_scripted_swing(model, INCOMING_BALL, params)
    plan = swing.racket
    print(
        f"incoming ball from {np.round(INCOMING_BALL[:3], 2)} m at {np.round(INCOMING_BALL[3:6], 1)} m/s, "
        f"topspin {-INCOMING_BALL[7]:.0f} rad/s"
    )
    print(
        f"plan: hit at t = {plan.time:.3f} s at {np.round(plan.position, 3)} m, racket {np.linalg.norm(plan.velocity):.1f} m/s "
        f"along {np.round(plan.normal, 2)}; predicted landing {np.round(plan.predicted_landing, 3)} m"
    )
    if meshcat is not None:
        meshcat.Delete()
        meshcat.DeleteRecording()
    events, logs = run_scripted_swing(swing, INCOMING_BALL, scenario, params, duration=1.6, meshcat=meshcat)
    if meshcat is not None:
        save_html(meshcat, args.out / "scripted_swing.html")
        written.append(args.out / "scripted_swing.html")
    print(f"{'contact':<8}{'t (s)':>8}{'position (m)':>26}")
    for event in events:
        print(f"{event.kind.name:<8}{event.time:>8.3f}{str(np.round(event.state_pre[:3], 3)):>26}")
    hit = next((e for e in events if e.kind == ContactKind.RACKET), None)
    after_hit = [e for e in events if hit is not None and e.time > hit.time]
    landing = after_hit[0] if after_hit else None
    if landing is not None and landing.kind == ContactKind.TABLE and landing.state_pre[0] > 0.0:
        miss = np.linalg.norm(landing.state_pre[:2] - plan.predicted_landing)
        print(
            f"the ball was returned: hit {1000 * (hit.time - plan.time):+.1f} ms from the plan, landed at "
            f"{np.round(landing.state_pre[:2], 3)} m, {100 * miss:.1f} cm from the planned landing"
        )
    else:
        # The plan and the simulation share the ball model, so this means the swing went wrong.
        print("the return failed: no table contact on the human's half right after the racket")

    # (b) and (c): the racket's blade centre from the logged joints, through the same kinematics.
    racket_positions = np.array([model.racket_pose(q).translation() for q in logs["joints"][:, :8]])
    ball_positions = logs["ball"][:, :3]
    for ax, axis, label in ((x_plot, 0, "x, along the table (m)"), (z_plot, 2, "z, height (m)")):
        ax.plot(logs["joint_time"], racket_positions[:, axis], color=RACKET_COLOR, label="racket (blade centre)")
        ax.plot(logs["time"], ball_positions[:, axis], color=BALL_COLOR, label="ball")
        if hit is not None:
            ax.axvline(hit.time, color="tab:red", linestyle="--", linewidth=1, label=f"hit, t = {hit.time:.3f} s")
        ax.set(ylabel=label)
    x_plot.axhline(table_end, color="tab:green", linewidth=0.8, linestyle=":", label="table's end")
    z_plot.axhline(0.0, color="tab:green", linewidth=0.8, linestyle=":", label="playing surface")
    x_plot.set_title("(b) Part 4: the scripted swing over time")
    x_plot.legend(loc="lower right", fontsize=8, ncols=2)
    x_plot.set_ylim(-2.7, 2.4)
    z_plot.legend(loc="upper right", fontsize=8, ncols=3)
    z_plot.set(xlabel="time (s)", xlim=(0.0, logs["time"][-1]), ylim=(-0.15, 0.65))
    x_plot.tick_params(labelbottom=False)

    draw_table_side_view(side_view, params)
    # Incoming and returned ball cross over the same table: draw them apart.
    returned = logs["time"] >= (hit.time if hit is not None else np.inf)
    incoming = ~returned
    incoming[np.argmax(returned)] = True  # share the sample at the hit so the two lines meet
    side_view.plot(ball_positions[incoming, 0], ball_positions[incoming, 2], color=BALL_COLOR, linestyle="--", label="ball, incoming")
    if hit is not None:
        side_view.plot(ball_positions[returned, 0], ball_positions[returned, 2], color=BALL_COLOR, label="ball, returned")
    side_view.plot(racket_positions[:, 0], racket_positions[:, 2], color=RACKET_COLOR, label="racket (blade centre)")
    for event in events:
        marker = "o" if event.kind == ContactKind.TABLE else "*"
        side_view.plot(event.state_pre[0], event.state_pre[2], marker, color="tab:red", markersize=8 if marker == "*" else 6)
    side_view.plot([], [], "o", color="tab:red", label="table contact")
    side_view.plot([], [], "*", color="tab:red", label="racket contact")
    if hit is not None:
        # The blade at the hit, seen edge-on: a segment across the normal, as long as the blade is wide.
        q_at_hit = logs["joints"][np.argmin(np.abs(logs["joint_time"] - hit.time)), :8]
        X_WR_hit = model.racket_pose(q_at_hit)
        normal_hit = X_WR_hit.rotation().matrix()[:, 2]
        across = np.array([-normal_hit[2], normal_hit[0]]) / np.hypot(normal_hit[0], normal_hit[2])
        centre = X_WR_hit.translation()[[0, 2]]
        blade = np.stack([centre - params.racket.blade_radius * across, centre + params.racket.blade_radius * across])
        side_view.plot(*blade.T, color="black", linewidth=3, label="blade at the hit")
    side_view.plot(*plan.predicted_landing[:1], 0.02, "x", color="black", markersize=9, label="planned landing")
    side_view.set(
        title="(c) Part 4: side view of the ball and the racket",
        xlabel="x, along the table (m)",
        ylabel="z, height above the playing surface (m)",
        xlim=(-2.2, 2.2),
        ylim=(-0.15, 0.85),
        aspect="equal",
    )
    side_view.legend(loc="upper center", ncols=4, fontsize=9)

    png = args.out / "robot.png"
    figure.savefig(png, dpi=110)
    written.insert(0, png)

    print("\n== Files ==")
    if meshcat is None:
        print("(--no-html: Meshcat files skipped)")
    for path in written:
        print(f"  {path}")


if __name__ == "__main__":
    main()
