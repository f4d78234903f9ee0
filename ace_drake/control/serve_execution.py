"""The robot executes the serve (paper, Methods *Serve design*): the toss from the ball cup, then
the strike of ``control.serve``, as joint commands through the rally's control stack.

The paper's serve trajectory is u_toss(t) for t in [0, t_lift] followed by u_strike(t): "t_lift
[is] the time index of the tossing trajectory in which the acceleration of the ball approximates
that of gravity, meaning that the ball has been released from the cup", and the strike connects
the robot's state at t_lift to the racket state the genetic algorithm found. Here:

1. **The toss** (``plan_toss``). The cup seat (frame ``ball_cup``: the ball's centre when it sits
   in the cup, z out of the cup's opening) moves along a straight line through the intended
   release point in the direction of the intended release velocity (vertical by default), its
   orientation fixed with the opening up. ``solve_cup_line`` solves Drake's InverseKinematics for
   seat positions along the line every ``TossParams.line_step`` (each from its neighbour's
   solution, nearest it in the metric sum dq^2 / A_j, with ``clearance`` between all robot and
   court geometry) and interpolates them with a cubic spline q(s). The seat's distance s(t) along
   the line follows ``CupProfile``: from rest, a constant acceleration for
   ``accelerate_segments`` segments up to the release speed, then braking at
   ``brake_acceleration`` (> g, so the cup leaves the ball behind) to rest. The profile's states
   at the 32 ms segment boundaries, (q(s), q'(s) s_dot), are the terminal targets of the segments;
   each becomes an action through the inverse of the eq. (12) mapping and is proposed to the
   control stack exactly as the safety supervisor would take it (``ControlStack.propose``:
   mapping, spline QP, reset, collision check). The commands (1 kHz samples of the accepted
   segments, then the last reset) drive the joints' exact eq. (9) response (``execute_commands``,
   the ``SegmentJointPlant``'s computation), and the release is found on that executed motion
   (``release_time``). The executed release misses the designed one (the QP smooths the profile's
   corner, the joints lag and filter), so the profile's release height and speed are corrected
   by the executed error and the plan made again, ``TossParams.corrections`` times at most.
2. **The strike** (``plan_strike``): from the first segment boundary at or after t_lift (the
   toss's commands before it are kept: they make the release), IK for the strike's whole racket
   pose (``solve_strike_ik``: blade centre, normal and roll, as the genes fixed them), joint
   velocities that move the blade's contact point at the strike's racket velocity with the least
   rotation, each joint within what the drive's cubic Hermite can reach from the boundary's
   state within the feasible set's acceleration (``hit_velocity_bounds``, ``strike_velocities``:
   the speed-limit weighting of ``robot.ik.racket_joint_velocities`` asks the slow gantry for
   the racket's whole forward speed and misses the hit velocity by 1.6-2.9 m/s), then
   ``control.hit_state.HitDriver.drive`` (the returner's step 5) towards that hit state at the
   hit less the joints' lag (``hit_prediction.joint_lag``), segment by segment through the same
   stack, and a follow-through; the whole command sequence (toss then strike) is executed again
   from the toss's start.

The release (``release_time``): the ball rests in the cup while the cup pushes it, i.e. while the
contact force m (a - g_W) . n >= 0 (a the seat's acceleration, g_W = (0, 0, -g), n the opening
axis); it leaves at the first instant the cup's acceleration along its opening falls below
gravity's, a . n < -g n_z. On the executed motion a is the finite difference of the seat's
velocity over each 1 ms command period (the period's mean acceleration, at its midpoint; the
instantaneous acceleration of the eq. (9) joints swings by hundreds of m/s^2 within a period as
each held command sample steps, a ripple a ball in a real cup does not follow), and the crossing
is interpolated linearly between the midpoints. The ball's state at release is the seat's
position (cubic Hermite between the samples) and velocity (linear between them), its spin the
cup's angular velocity.

Departures from the paper: the paper retargets human toss demonstrations to the robot's
kinematics; here the toss is designed (a straight line, a two-phase profile). The release
criterion takes the free ball's acceleration as gravity alone (drag on a ball rising at 2 m/s is
about 0.45 m/s^2, 5% of g: the ball separates a fraction of a millisecond earlier than computed).
The paper's strike is "an MPC in racket space"; here it is the returner's joint-space drive to
the hit state, the strike's pose solved by IK.

Times of a plan are seconds from the toss's start (the robot at rest, its first segment starting);
strike times (``control.serve.Strike.time``) are seconds from the release, so the hit is at
t_lift + strike.time. SI units, world frame of DESIGN.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import SnoptSolver, Solve
from scipy.interpolate import CubicSpline
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from ace_drake.control.hit_prediction import joint_lag
from ace_drake.control.hit_state import HitDriver
from ace_drake.control.joint_model import JointMotion, JointPropagator
from ace_drake.control.serve import Strike, TossState, toss_ball, umpire_toss
from ace_drake.control.stack import ControlStack, Proposal, plan_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.play.scoring import ROBOT
from ace_drake.play.umpire import Court, Toss, Umpire
from ace_drake.robot.model import RobotModel
from ace_drake.robot.params import RobotDynamicsParams
from ace_drake.robot.trajectory import JointTrajectory

GRAVITY = 9.81  # m/s^2, as physics.params.AeroParams.gravity
IK_MAJOR_ITERATIONS = 200  # SNOPT's limit per IK solve along the cup's line (each starts at its neighbour)
VELOCITY_WEIGHT = 1.0e3  # strike_velocities: per m/s of the contact point's velocity error
ANGULAR_WEIGHT = 1.0  # strike_velocities: per rad/s of the racket's angular velocity


# ---------------------------------------------------------------------------------- the cup's line
@dataclasses.dataclass(frozen=True)
class CupLine:
    """Configurations (``q`` (n, 8)) that put the cup seat at ``origin + s direction`` for the
    distances ``distances`` (n,), m, increasing, with the cup's orientation ``R_WC`` (3, 3) fixed;
    ``configuration`` and ``rate`` interpolate them (cubic spline in s)."""

    origin: np.ndarray
    direction: np.ndarray
    distances: np.ndarray
    q: np.ndarray
    R_WC: np.ndarray

    @property
    def spline(self) -> CubicSpline:
        return CubicSpline(self.distances, self.q, axis=0)

    def configuration(self, s) -> np.ndarray:
        """q(s) (..., 8) at distances s (...,), m along the line from the origin."""
        self._check(s)
        return self.spline(np.asarray(s, dtype=float))

    def rate(self, s) -> np.ndarray:
        """dq/ds (..., 8) at distances s (...,): rad or m per m."""
        self._check(s)
        return self.spline(np.asarray(s, dtype=float), 1)

    def _check(self, s) -> None:
        s = np.asarray(s, dtype=float)
        if np.any(s < self.distances[0] - 1e-9) or np.any(s > self.distances[-1] + 1e-9):
            raise ValueError(f"CupLine: distances {s.min():.4f}..{s.max():.4f} m lie outside the solved "
                             f"{self.distances[0]:.4f}..{self.distances[-1]:.4f} m")


def solve_cup_line(
    model: RobotModel,
    origin,
    direction,
    low: float,
    high: float,
    step: float = 0.005,
    clearance: float = 0.03,
    yaws: tuple[float, ...] = (-0.5 * math.pi, 0.5 * math.pi, -0.75 * math.pi, 0.75 * math.pi, math.pi),
    q_nominal: np.ndarray | None = None,
) -> CupLine:
    """The cup seat on the line origin + s direction (m; direction normalised), s from ``low`` to
    ``high`` (m, low <= 0 <= high) every ``step`` (m), the cup's orientation fixed with its
    opening up (its z along world +z) and its x axis (from the seat towards the blade, which lies
    0.10 m along it and 0.06 m below the seat) at the first of ``yaws`` (rad from world +x about
    +z) for which the whole line solves: the cup's pose fixes the racket's, so the yaw decides
    where the blade goes as the cup moves (towards the table, it would meet the table's end).

    Each point: Drake's InverseKinematics with the seat there (within 0.1 mm), the orientation
    (within 1 mrad), joint limits and ``clearance`` (m) between all robot and court geometry,
    nearest a nominal configuration in sum dq^2 / A_j (A_j each joint's acceleration limit: the
    slow gantry moves least): at s = 0 ``q_nominal`` (default the ready pose with the gantry
    placed by ``RobotModel.seed_for``), the others stepping outwards from their neighbour's
    solution. Raises RuntimeError if no yaw solves the whole line."""
    origin = np.asarray(origin, dtype=float)
    direction = np.asarray(direction, dtype=float)
    if origin.shape != (3,) or direction.shape != (3,) or not np.all(np.isfinite(np.r_[origin, direction])) or np.linalg.norm(direction) < 1e-9:
        raise ValueError(f"solve_cup_line: expected an origin (3,) m and a non-zero direction (3,), got {origin}, {direction}")
    if not (low <= 0.0 <= high and step > 0.0):
        raise ValueError(f"solve_cup_line: need low <= 0 <= high and step > 0 (m), got {low}, {high}, {step}")
    direction = direction / np.linalg.norm(direction)
    world, cup = model.plant.world_frame(), model.ball_cup_frame
    weights = np.diag(1.0 / model.acceleration_limit)

    def solve(p_WC, nominal, orientation: RotationMatrix) -> np.ndarray | None:
        ik = InverseKinematics(model.plant, model.plant_context, with_joint_limits=True)
        ik.AddPositionConstraint(cup, np.zeros(3), world, p_WC - 1e-4, p_WC + 1e-4)
        ik.AddOrientationConstraint(world, orientation, cup, RotationMatrix(), 1e-3)
        ik.AddMinimumDistanceLowerBoundConstraint(clearance, clearance + 0.05)
        ik.prog().AddQuadraticErrorCost(weights, nominal, ik.q())
        ik.prog().SetSolverOption(SnoptSolver().solver_id(), "Major iterations limit", IK_MAJOR_ITERATIONS)
        result = Solve(ik.prog(), nominal)
        return result.GetSolution(ik.q()) if result.is_success() else None

    above = np.arange(1, int(math.floor(high / step + 1e-9)) + 1) * step
    below = -np.arange(1, int(math.floor(-low / step + 1e-9)) + 1) * step
    if high > 0.0 and (above.size == 0 or above[-1] < high - 1e-12):
        above = np.r_[above, high]
    if low < 0.0 and (below.size == 0 or below[-1] > low + 1e-12):
        below = np.r_[below, low]
    nominal = model.seed_for(origin) if q_nominal is None else np.asarray(q_nominal, dtype=float)
    failures = []
    for yaw in yaws:
        R_WC = RotationMatrix.MakeZRotation(yaw)
        solved = {0.0: solve(origin, nominal, R_WC)}
        if solved[0.0] is None:
            failures.append(f"yaw {yaw:+.2f} rad: at the release point")
            continue
        for side in (below, above):
            previous = solved[0.0]
            for s in side:
                previous = solve(origin + s * direction, previous, R_WC)
                if previous is None:
                    failures.append(f"yaw {yaw:+.2f} rad: at s = {s:+.3f} m")
                    break
                solved[float(s)] = previous
            if previous is None:
                break
        else:
            distances = np.array(sorted(solved))
            return CupLine(origin, direction, distances, np.array([solved[s] for s in distances]), R_WC.matrix())
    raise RuntimeError(f"solve_cup_line: no cup yaw puts the seat on the line through {np.round(origin, 4)} m with {clearance} m clearance ({'; '.join(failures)})")


# ---------------------------------------------------------------------------------- the profile
@dataclasses.dataclass(frozen=True)
class CupProfile:
    """The cup seat's designed distance s(t) along its line (m from the release point, t in s from
    the toss's start): from rest at ``start`` a constant acceleration v_switch / t_switch until
    t_switch, reaching (s_switch, v_switch), then braking at ``brake`` (m/s^2 > 0) to rest at
    ``top``."""

    t_switch: float
    s_switch: float
    v_switch: float
    brake: float

    def __post_init__(self) -> None:
        if not (self.t_switch > 0.0 and self.v_switch > 0.0 and self.brake > 0.0):
            raise ValueError(f"CupProfile: t_switch, v_switch and brake must be > 0, got {self.t_switch}, {self.v_switch}, {self.brake}")

    @property
    def acceleration(self) -> float:
        """The upward phase's acceleration, m/s^2."""
        return self.v_switch / self.t_switch

    @property
    def start(self) -> float:
        """s at t = 0, m."""
        return self.s_switch - 0.5 * self.v_switch * self.t_switch

    @property
    def t_stop(self) -> float:
        """When the cup comes to rest, s."""
        return self.t_switch + self.v_switch / self.brake

    @property
    def top(self) -> float:
        """s at rest after braking, m."""
        return self.s_switch + 0.5 * self.v_switch**2 / self.brake

    def at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s m, s_dot m/s, s_ddot m/s^2) at times t (...,) s; before 0 at rest at ``start``, after
        ``t_stop`` at rest at ``top``."""
        t = np.asarray(t, dtype=float)
        rising = np.clip(t, 0.0, self.t_switch)
        braking = np.clip(t - self.t_switch, 0.0, self.v_switch / self.brake)
        a_up = self.acceleration
        s = self.start + 0.5 * a_up * rising**2 + self.v_switch * braking - 0.5 * self.brake * braking**2
        s_dot = np.where(t < self.t_switch, a_up * rising, self.v_switch - self.brake * braking)
        s_ddot = np.where((t >= 0.0) & (t < self.t_switch), a_up, np.where((t >= self.t_switch) & (t < self.t_stop), -self.brake, 0.0))
        return s, np.where(t <= 0.0, 0.0, s_dot), s_ddot


# ---------------------------------------------------------------------------------- commanding and executing
@dataclasses.dataclass(frozen=True)
class CommandedMotion:
    """Joint commands made segment by segment through the control stack, as the safety supervisor
    would have executed them.

    plan: the 1 kHz commands from the start (row 0 the start at rest), the accepted segments then
    the last accepted plan's reset. boundaries (K,): the segments' start samples. actions (K, 16):
    the actions proposed (NaN rows where none was). proposals: the stack's Proposal of each (None
    where no action). The supervisor keeps its plan on a refusal, so a refused proposal leaves the
    commands as they were.
    """

    plan: JointTrajectory
    boundaries: np.ndarray
    actions: np.ndarray
    proposals: tuple[Proposal | None, ...]

    @property
    def accepted(self) -> np.ndarray:
        """(K,) booleans: which proposals the stack accepted."""
        return np.array([p is not None and p.safe for p in self.proposals], dtype=bool)

    @property
    def reasons(self) -> list[str]:
        """Why each refused proposal was refused ("" for accepted ones and for no action)."""
        return [p.reason if p is not None and not p.safe else "" for p in self.proposals]


def command_segments(
    stack: ControlStack,
    plan: JointTrajectory,
    first_segment: int,
    choose_action: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray | None],
    segments: int,
) -> CommandedMotion:
    """Commands ``segments`` segments from segment index ``first_segment`` (its start sample
    first_segment N, N the stack's samples per segment) on the committed ``plan`` (1 kHz commands
    from sample 0; after its end it rests at its last sample): at each boundary k the committed
    plan's state (q, v, a) (the segment's start state, as the supervisor hands it to the mapper
    and the QP), ``choose_action(k, q, v, a)``'s action (16,) or None, and the stack's proposal
    (``ControlStack.propose``); an accepted one replaces the commands from the boundary on
    (segment, then its reset)."""
    N = stack.control.segment_samples
    boundaries, actions, proposals = [], [], []
    for k in range(first_segment, first_segment + segments):
        boundary = k * N
        q, v, a = plan_state(plan, boundary)
        action = choose_action(k, q, v, a)
        boundaries.append(boundary)
        if action is None:
            actions.append(np.full(16, np.nan))
            proposals.append(None)
            continue
        proposal = stack.propose(q, v, a, action)
        actions.append(np.asarray(action, dtype=float))
        proposals.append(proposal)
        if proposal.safe:
            plan = _extend(plan, boundary).until(boundary).then(proposal.plan)
    return CommandedMotion(plan, np.array(boundaries, dtype=int), np.array(actions).reshape(-1, 16), tuple(proposals))


def _extend(plan: JointTrajectory, sample: int) -> JointTrajectory:
    """``plan`` at rest at its last sample until ``sample`` if it ends before."""
    extra = sample - plan.samples
    if extra <= 0:
        return plan
    q, v, a = plan.state(-1)
    return JointTrajectory(plan.period, np.vstack([plan.q, np.tile(q, (extra, 1))]), np.vstack([plan.v, np.tile(v, (extra, 1))]),
                           np.vstack([plan.a, np.tile(a, (extra, 1))]))


def execute_commands(dynamics: RobotDynamicsParams, plan: JointTrajectory, settle: int = 20) -> JointMotion:
    """The joints' exact eq. (9) motion under the 1 kHz commands plan.q (the command at sample n is
    plan.q[n]; before sample 0 the joints rest at plan.q[0] with that command held), over the
    plan and ``settle`` samples more at its last command: what the ``SegmentJointPlant`` computes
    tick by tick (joint i is driven by u[n - k_i - 1] on [t_n, t_n + f_i) and by u[n - k_i] from
    there to t_{n+1}, tau_i = k_i T + f_i). Returns the JointMotion of one environment (B = 1)."""
    if abs(plan.period - dynamics.command_period) > 1e-12:
        raise ValueError(f"execute_commands: the plan's period ({plan.period} s) differs from the joints' command period ({dynamics.command_period} s)")
    propagator = JointPropagator(dynamics.joints, dynamics.command_period)
    commands = np.vstack([plan.q, np.tile(plan.q[-1], (settle, 1))])
    periods = commands.shape[0] - 1
    history = int(propagator.whole_periods.max()) + 2
    padded = np.vstack([np.tile(commands[0], (history, 1)), commands])  # padded[history + n] = u[n]
    columns = np.arange(commands.shape[1])
    newer = np.arange(periods)[:, None] - propagator.whole_periods[None, :] + history
    u_new, u_old = padded[newer, columns], padded[newer - 1, columns]
    zeta0 = np.stack([commands[0], np.zeros_like(commands[0])], axis=-1)[None]
    zeta = propagator.propagate_samples(zeta0, u_old[None], u_new[None])
    return JointMotion(propagator, zeta, u_old[None], u_new[None])


@dataclasses.dataclass(frozen=True)
class PlannedStart:
    """An episode that starts part-way along a committed command plan (a serve: the toss's
    commands already running when the ball leaves the cup).

    plan: the 1 kHz commands from rest (row 0; before it the joints rest there with that command
    held, as ``execute_commands`` assumes). start_sample: the plan's row at the episode's time 0.
    hold_samples: episode samples from time 0 during which the plan is kept whatever the policy
    proposes (the safety supervisor decides no new segment before then).
    """

    plan: JointTrajectory
    start_sample: int
    hold_samples: int

    def __post_init__(self) -> None:
        if not 0 <= self.start_sample < self.plan.samples:
            raise ValueError(f"PlannedStart.start_sample must lie in the plan's {self.plan.samples} samples, got {self.start_sample}")
        if self.hold_samples < 0:
            raise ValueError(f"PlannedStart.hold_samples must be >= 0, got {self.hold_samples}")

    def joint_state(self, dynamics: RobotDynamicsParams, episode_sample: int, history: int) -> tuple[np.ndarray, np.ndarray]:
        """The joints executing the plan (``execute_commands``) at episode sample
        ``episode_sample`` (time 0 at ``start_sample``): zeta (8, 2) [q, q_dot] and the
        ``history`` commands before that sample (history, 8), oldest first: the
        ``SegmentJointPlant``'s state there."""
        sample = self.start_sample + int(episode_sample)
        if sample < 0:
            raise ValueError(f"PlannedStart.joint_state: episode sample {episode_sample} lies before the plan's start")
        motion = execute_commands(dynamics, self.plan, settle=max(1, sample - self.plan.samples + 2))
        before = np.clip(np.arange(sample - history, sample), 0, self.plan.samples - 1)
        return motion.zeta[0, sample].copy(), self.plan.q[before].copy()


@dataclasses.dataclass(frozen=True)
class ServeStart:
    """A served point's first episode (``serve_episode_start``): the robot part-way along the
    serve's commands (``planned``), the ball (9,) [p, v, w] just released at the episode's time 0,
    and the umpire's Toss in episode time (its release at or just before 0)."""

    planned: PlannedStart
    ball: np.ndarray
    toss: Toss


def serve_episode_start(commands: JointTrajectory, t_lift: float, release: TossState, physics: BallPhysicsParams) -> ServeStart:
    """The episode of a serve whose ``commands`` (1 kHz, from rest; toss then strike) release the
    ball at ``t_lift`` (s from their start) in the state ``release``: time 0 is the first command
    sample at or after the release, the ball there in free flight from it (``toss_ball``), the
    plan held to its end (the strike and follow-through are committed; the policy takes over
    after)."""
    period = commands.period
    start = int(math.ceil(t_lift / period - 1e-9))
    lag = start * period - t_lift
    ball = toss_ball(release, physics, lag)
    toss = umpire_toss(release, physics)
    toss = Toss(-lag, toss.release_position, toss.release_velocity, toss.apex_height)
    return ServeStart(PlannedStart(commands, start, commands.samples - start), ball, toss)


def mean_joint_state(motion: JointMotion, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The executed joints (environment 0 of ``motion``) at time t (s from its first sample):
    positions (8,) linear between the samples, velocities (8,) the periods' means (position
    differences) linear between the periods' midpoints, accelerations (8,) the second differences
    linear between the samples (the mean motion of ``CupMotion``; rad or m, per s, per s^2)."""
    q = motion.zeta[0, :, :, 0]
    period = motion.propagator.period
    times = np.arange(q.shape[0]) * period
    v = np.diff(q, axis=0) / period
    a = np.diff(v, axis=0) / period
    mid = times[:-1] + 0.5 * period
    interpolate = lambda x, y: np.array([np.interp(t, x, column) for column in y.T])
    return interpolate(times, q), interpolate(mid, v), interpolate(times[1:-1], a)


# ---------------------------------------------------------------------------------- the cup's motion and the release
@dataclasses.dataclass(frozen=True)
class CupMotion:
    """The cup seat's motion at the 1 kHz samples of an executed joint motion, and its mean motion
    over each command period (module docstring: the samples' own velocities sit at the trough of
    the eq. (9) joints' inter-sample ripple, 8% below the mean at 2 m/s).

    times (n,): s. position (n, 3): m. rotation (n, 3, 3): the cup's orientation R_WC (z: the
    opening). ``velocity`` (n - 1, 3) m/s and ``angular_velocity`` (n - 1, 3) rad/s: the means
    over each period, at ``midpoints`` (n - 1,); ``acceleration`` (n - 2, 3) m/s^2: the mean over
    [t_k - T/2, t_k + T/2] (the second difference of the positions), at times[1:-1].
    """

    times: np.ndarray
    position: np.ndarray
    rotation: np.ndarray

    @property
    def axis(self) -> np.ndarray:
        """The opening's direction (n, 3) at the samples."""
        return self.rotation[:, :, 2]

    @property
    def midpoints(self) -> np.ndarray:
        return 0.5 * (self.times[1:] + self.times[:-1])

    @property
    def velocity(self) -> np.ndarray:
        """The mean velocity over each period, m/s (n - 1, 3)."""
        return np.diff(self.position, axis=0) / np.diff(self.times)[:, None]

    @property
    def angular_velocity(self) -> np.ndarray:
        """The mean angular velocity over each period, rad/s (n - 1, 3), in world: the rotation
        vector of R_k+1 R_k^T over the period."""
        relative = Rotation.from_matrix(self.rotation[1:] @ np.swapaxes(self.rotation[:-1], 1, 2))
        return relative.as_rotvec() / np.diff(self.times)[:, None]

    @property
    def acceleration(self) -> np.ndarray:
        """The mean acceleration about each inner sample, m/s^2 (n - 2, 3)."""
        return np.diff(self.velocity, axis=0) / np.diff(self.midpoints)[:, None]

    def state_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position m, velocity m/s, angular velocity rad/s) at time t (s), each linear in time
        (the position between the samples, the mean velocities between the midpoints)."""
        position = np.array([np.interp(t, self.times, self.position[:, i]) for i in range(3)])
        velocity = np.array([np.interp(t, self.midpoints, self.velocity[:, i]) for i in range(3)])
        spin = np.array([np.interp(t, self.midpoints, w) for w in self.angular_velocity.T])
        return position, velocity, spin

    def release(self, gravity: float = GRAVITY) -> float | None:
        """t_lift (``release_time``) of this motion's mean accelerations, s; None if never."""
        return release_time(self.times[1:-1], self.acceleration, self.axis[1:-1], gravity)


def cup_motion(model: RobotModel, times, q) -> CupMotion:
    """The cup seat's ``CupMotion`` at joint positions q (n, 8) at ``times`` (n,) s."""
    times, q = np.asarray(times, dtype=float), np.asarray(q, dtype=float)
    position, rotation = np.empty((times.size, 3)), np.empty((times.size, 3, 3))
    for k in range(times.size):
        model.plant.SetPositions(model.plant_context, q[k])
        X_WC = model.ball_cup_frame.CalcPoseInWorld(model.plant_context)
        position[k], rotation[k] = X_WC.translation(), X_WC.rotation().matrix()
    return CupMotion(times, position, rotation)


def release_time(times, acceleration, axis, gravity: float = GRAVITY) -> float | None:
    """t_lift, s: the first time the cup's acceleration along its opening falls below gravity's,
    (a - g_W) . n < 0 with g_W = (0, 0, -gravity) (the ball's contact force would pull), from
    accelerations (n, 3) m/s^2 and opening axes (n, 3) at ``times`` (n,) s, linear in between
    (module docstring); None if it never does. A first sample already below is the release."""
    times, acceleration, axis = (np.asarray(x, dtype=float) for x in (times, acceleration, axis))
    support = np.einsum("ij,ij->i", acceleration, axis) + gravity * axis[:, 2]  # (a - g_W) . n, m/s^2
    below = np.flatnonzero(support < 0.0)
    if below.size == 0:
        return None
    k = int(below[0])
    if k == 0:
        return float(times[0])
    return float(times[k - 1] + (times[k] - times[k - 1]) * support[k - 1] / (support[k - 1] - support[k]))


# ---------------------------------------------------------------------------------- the toss
@dataclasses.dataclass(frozen=True)
class TossParams:
    """The designed toss (module docstring). Lengths in m, times in s.

    accelerate_segments: segments of constant acceleration from rest to the release speed (5:
    0.16 s; 12.5 m/s^2 for the default 2 m/s). brake_acceleration: the cup's deceleration after
    the release, m/s^2 (> g; 2.5 g leaves the ball 2.3 cm above the seat 10 ms after the release).
    rest_segments: segments held at the cup's rest after braking (the plan ends at rest).
    line_step: IK grid along the line. line_margin: how far the line is solved beyond the motion
    (the corrections move the profile). clearance: between all robot and court geometry at every
    IK point. corrections: re-plans from the executed release error at most. position_tolerance,
    velocity_tolerance: stop correcting once the executed release is within them (m, m/s).
    """

    accelerate_segments: int = 5
    brake_acceleration: float = 2.5 * GRAVITY
    rest_segments: int = 1
    line_step: float = 0.005
    line_margin: float = 0.03
    clearance: float = 0.03
    corrections: int = 4
    position_tolerance: float = 5e-4
    velocity_tolerance: float = 2e-3

    def __post_init__(self) -> None:
        if self.accelerate_segments < 1 or self.rest_segments < 0 or self.corrections < 0:
            raise ValueError(f"TossParams: accelerate_segments >= 1, rest_segments >= 0 and corrections >= 0 expected, got "
                             f"{self.accelerate_segments}, {self.rest_segments}, {self.corrections}")
        if not self.brake_acceleration > GRAVITY:
            raise ValueError(f"TossParams.brake_acceleration must exceed g = {GRAVITY} m/s^2 (the cup must leave the ball), got {self.brake_acceleration}")
        for name in ("line_step", "line_margin", "clearance", "position_tolerance", "velocity_tolerance"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"TossParams.{name} must be > 0, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class TossPlan:
    """A toss made by the robot (``plan_toss``).

    intended: the TossState asked for. line: the cup's line (IK). profile: the designed profile
    after the corrections. commands: the commanded segments (``CommandedMotion``; its plan starts
    at rest at q_start). motion: the executed joint motion (eq. (9)). cup: the cup seat's executed
    motion at the samples. t_lift: the release, s from the toss's start (None: the cup never let
    go). release: the ball's state at t_lift (a TossState; None without a release). q_lift,
    v_lift, a_lift (8,): the executed joints at t_lift (``mean_joint_state``: rad or m, per s,
    per s^2). corrections: re-plans made. physics: the ball physics of the rise.
    """

    intended: TossState
    line: CupLine
    profile: CupProfile
    commands: CommandedMotion
    motion: JointMotion
    cup: CupMotion
    t_lift: float | None
    release: TossState | None
    q_lift: np.ndarray | None
    v_lift: np.ndarray | None
    a_lift: np.ndarray | None
    corrections: int
    physics: BallPhysicsParams

    @property
    def q_start(self) -> np.ndarray:
        """The joints' configuration at rest at the toss's start (8,)."""
        return self.commands.plan.q[0]

    @property
    def position_error(self) -> np.ndarray:
        """Executed minus intended release position (3,), m."""
        return self.release.position - self.intended.position

    @property
    def velocity_error(self) -> np.ndarray:
        """Executed minus intended release velocity (3,), m/s."""
        return self.release.velocity - self.intended.velocity

    @property
    def umpire_toss(self) -> Toss:
        """The umpire's Toss of the executed release (its rise from the simulated flight)."""
        return umpire_toss(self.release, self.physics)

    @property
    def tilt(self) -> float:
        """The executed release velocity's angle from vertical, rad."""
        return self.umpire_toss.tilt

    @property
    def rise(self) -> float:
        """How far the released ball rises above the release point, m."""
        return self.umpire_toss.apex_height

    @property
    def legal(self) -> bool:
        """Whether the umpire accepts the executed toss (Laws 2.6.2, 2.6.4)."""
        return self.release is not None and Umpire(ROBOT, self.umpire_toss, Court.from_physics(self.physics)).decision is None


def plan_toss(
    model: RobotModel,
    stack: ControlStack,
    toss: TossState | None = None,
    params: TossParams | None = None,
    physics: BallPhysicsParams | None = None,
    dynamics: RobotDynamicsParams | None = None,
    line: CupLine | None = None,
) -> TossPlan:
    """The robot's toss releasing the ball in the state ``toss`` (default ``TossState()``), made
    and executed as the module docstring says; ``line``: a solved ``CupLine`` to reuse (through
    the toss's release point, along its velocity, covering the motion). The joints' dynamics
    default to the model's scenario's. Raises RuntimeError if the stack refuses a segment or the
    executed cup never lets go."""
    toss = TossState() if toss is None else toss
    params = TossParams() if params is None else params
    physics = BallPhysicsParams() if physics is None else physics
    dynamics = model.scenario.dynamics if dynamics is None else dynamics
    gravity = physics.aero.gravity
    speed = float(np.linalg.norm(toss.velocity))
    direction = toss.velocity / speed
    T = stack.segment_duration
    t_switch = params.accelerate_segments * T
    travel_up = 0.5 * speed * t_switch
    travel_brake = 0.5 * speed**2 / params.brake_acceleration
    if line is None:
        margin = params.line_margin
        line = solve_cup_line(model, toss.position, direction, -travel_up - margin, travel_brake + margin, params.line_step, params.clearance)
    profile = CupProfile(t_switch, 0.0, speed, params.brake_acceleration)
    for correction in range(params.corrections + 1):
        commands, motion, cup, t_lift, release = _toss_once(model, stack, dynamics, line, profile, params, gravity, toss)
        if release is None:
            raise RuntimeError(f"plan_toss: the executed cup never decelerated faster than gravity (profile {profile})")
        along = float(np.dot(release.position - toss.position, direction))
        speed_error = float(np.dot(release.velocity, direction)) - speed
        if (abs(along) < params.position_tolerance and abs(speed_error) < params.velocity_tolerance) or correction == params.corrections:
            break
        profile = CupProfile(t_switch, profile.s_switch - along, profile.v_switch - speed_error, params.brake_acceleration)
    q_lift, v_lift, a_lift = mean_joint_state(motion, t_lift)
    return TossPlan(toss, line, profile, commands, motion, cup, t_lift, release, q_lift, v_lift, a_lift, correction, physics)


def _toss_once(model, stack, dynamics, line, profile, params, gravity, toss):
    """One plan of the toss for ``profile``: commands, executed motion, cup motion, t_lift and
    the released ball's TossState (None if the cup never lets go)."""
    T, N = stack.segment_duration, stack.control.segment_samples
    segments = int(math.ceil(profile.t_stop / T)) + params.rest_segments
    q_start = line.configuration(profile.start)
    plan = JointTrajectory.stationary(q_start, stack.period)
    driver = HitDriver(stack)

    def choose(k, q, v, a):
        s, s_dot, _ = profile.at((k + 1) * T)
        return driver.action_to(q, v, a, line.configuration(s), line.rate(s) * s_dot)

    commands = command_segments(stack, plan, 0, choose, segments)
    if not commands.accepted.all():
        refused = [f"segment {k}: {reason}" for k, reason in enumerate(commands.reasons) if reason]
        raise RuntimeError(f"plan_toss: the control stack refused {'; '.join(refused)}")
    motion = execute_commands(dynamics, commands.plan)
    states = motion.states[0]
    cup = cup_motion(model, np.arange(states.shape[0]) * motion.propagator.period, states[:, :8])
    t_lift = cup.release(gravity)
    if t_lift is None:
        return commands, motion, cup, None, None
    position, velocity, spin = cup.state_at(t_lift)
    if velocity[2] <= 0.0:
        return commands, motion, cup, t_lift, None
    return commands, motion, cup, t_lift, TossState(position, velocity, spin)


# ---------------------------------------------------------------------------------- the strike
@dataclasses.dataclass(frozen=True)
class StrikeParams:
    """The strike's hit state and its drive (module docstring). Lengths in m, angles in rad.

    clearance: between all robot and court geometry at the hit configuration (the returner's
    ``ik_clearance``). position_tolerance, angle_tolerance: the IK's on the blade centre and the
    racket's orientation (the strike's whole pose, roll included; if that fails, the normal alone
    with the roll free, ``StrikePlan.roll_free``). follow_segments: segments commanded after the
    hit (following through at the joints' velocities) before the stack's reset takes over. lag:
    how far the joints lag their commands, s (None: ``hit_prediction.joint_lag`` of the scenario):
    the hit state is commanded that much before the hit.
    """

    clearance: float = 0.02
    position_tolerance: float = 1e-3
    angle_tolerance: float = math.radians(0.5)
    follow_segments: int = 1
    lag: float | None = None

    def __post_init__(self) -> None:
        if not (self.clearance >= 0.0 and self.position_tolerance > 0.0 and self.angle_tolerance > 0.0 and self.follow_segments >= 0):
            raise ValueError(f"StrikeParams: clearance >= 0, tolerances > 0 and follow_segments >= 0 expected, got {self}")
        if self.lag is not None and not self.lag >= 0.0:
            raise ValueError(f"StrikeParams.lag must be >= 0 s or None, got {self.lag}")


@dataclasses.dataclass(frozen=True)
class RacketState:
    """The racket frame's state: position (3,) m (the blade centre), rotation (3, 3) R_WR (z the
    forehand normal), velocity (3,) m/s and angular_velocity (3,) rad/s, in world."""

    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return self.rotation[:, 2]


def racket_state(model: RobotModel, q, v) -> RacketState:
    """The racket frame's ``RacketState`` at joint positions q (8,) and velocities v (8,)."""
    X_WR = model.racket_pose(q)
    V_WR = model.racket_spatial_velocity(q, v)
    return RacketState(X_WR.translation(), X_WR.rotation().matrix(), V_WR.translational(), V_WR.rotational())


def hit_velocity_bounds(q0, v0, q_hit, duration: float, velocity_limit, acceleration_limit) -> tuple[np.ndarray, np.ndarray]:
    """Per joint, the hit velocities v1 (lower, upper) (8,) of the cubic Hermite from (q0, v0) to
    (q_hit, v1) over ``duration`` s (``control.hit_state.hermite``, the drive's path) whose
    acceleration stays within +-``acceleration_limit`` (it is linear in time: its two ends,
    (6 dq - (4 v0 + 2 v1) D) / D^2 and (-6 dq + (2 v0 + 4 v1) D) / D^2) and |v1| within
    ``velocity_limit``. An empty interval (lower > upper) means q_hit is out of the joint's reach."""
    q0, v0, q_hit = (np.asarray(x, dtype=float) for x in (q0, v0, q_hit))
    D, A, V = float(duration), np.asarray(acceleration_limit, dtype=float), np.asarray(velocity_limit, dtype=float)
    delta = q_hit - q0
    start = ((6.0 * delta - 4.0 * v0 * D - A * D**2) / (2.0 * D), (6.0 * delta - 4.0 * v0 * D + A * D**2) / (2.0 * D))
    end = ((6.0 * delta - 2.0 * v0 * D - A * D**2) / (4.0 * D), (6.0 * delta - 2.0 * v0 * D + A * D**2) / (4.0 * D))
    return np.maximum.reduce([start[0], end[0], -V]), np.minimum.reduce([start[1], end[1], V])


def strike_velocities(model: RobotModel, q, v_WR, contact_offset, lower, upper) -> np.ndarray:
    """Joint velocities (8,) for a strike's racket velocity at q: the blade's point at
    ``contact_offset`` (3,; m, world-aligned, from the blade centre: where the ball touches it)
    moving at v_WR (3,; m/s), the racket turning as little as it can, each joint within its
    bounds (lower, upper) (8,) and near its interval's centre. A bounded least-squares problem
    (SciPy's ``lsq_linear``) in priority order by weight:

        VELOCITY_WEIGHT^2 |J_c v - v_WR|^2 + ANGULAR_WEIGHT^2 |J_w v|^2 + sum_j ((v_j - c_j) / h_j)^2,

    J_c = J_v - [r]x J_w the contact point's translational Jacobian (r = contact_offset), J_w the
    angular one, c and h each interval's centre and half-width (an empty interval counts as its
    centre +- 1e-3). The strike's racket only translates (``control.serve.Strike``): what the
    ball feels is the contact point's velocity, which this meets exactly where the bounds allow,
    leaving the angular velocity to make up for the joints' reach; the returner's
    ``robot.ik.racket_joint_velocities`` instead weights by the speed limits and leaves the
    angular velocity free."""
    jacobian = model.racket_jacobian(q)
    angular, linear = jacobian[:3], jacobian[3:]
    r = np.asarray(contact_offset, dtype=float)
    skew = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    contact = linear - skew @ angular  # v + w x r = v - r x w
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    centre = 0.5 * (lower + upper)
    half = np.maximum(0.5 * (upper - lower), 1e-3)
    low, high = np.minimum(lower, centre - 1e-3), np.maximum(upper, centre + 1e-3)
    rows = np.vstack([VELOCITY_WEIGHT * contact, ANGULAR_WEIGHT * angular, np.diag(1.0 / half)])
    values = np.r_[VELOCITY_WEIGHT * np.asarray(v_WR, dtype=float), np.zeros(3), centre / half]
    return lsq_linear(rows, values, bounds=(low, high), method="bvls").x


def solve_strike_ik(model: RobotModel, strike: Strike, q_nominal, params: StrikeParams | None = None) -> tuple[np.ndarray, bool]:
    """A configuration (8,) for the racket pose of one strike (blade centre ``strike.p_WR`` and
    orientation ``strike.R_WR``, within the params' tolerances, joint limits, ``clearance``),
    nearest ``q_nominal`` in sum dq^2 / A_j, from q_nominal and then ``RobotModel.seed_for``'s
    seeds; if the whole pose fails, the normal alone (``robot.ik.solve_hit_ik``'s constraints).
    Returns (q, roll_free); raises RuntimeError if neither solves."""
    params = StrikeParams() if params is None else params
    if strike.shape != ():
        raise ValueError(f"solve_strike_ik: one strike expected, got a batch {strike.shape}")
    world = model.plant.world_frame()
    weights = np.diag(1.0 / model.acceleration_limit)
    nominal = np.asarray(q_nominal, dtype=float)
    seeds = [nominal] + [model.seed_for(strike.p_WR, roll) for roll in (0.0, 1.5, -1.5)]
    tolerance = np.full(3, params.position_tolerance)
    for roll_free in (False, True):
        for seed in seeds:
            ik = InverseKinematics(model.plant, model.plant_context, with_joint_limits=True)
            ik.AddPositionConstraint(model.racket_frame, np.zeros(3), world, strike.p_WR - tolerance, strike.p_WR + tolerance)
            if roll_free:
                ik.AddAngleBetweenVectorsConstraint(world, strike.normal, model.racket_frame, [0.0, 0.0, 1.0], 0.0, params.angle_tolerance)
            else:
                ik.AddOrientationConstraint(world, RotationMatrix(strike.R_WR), model.racket_frame, RotationMatrix(), params.angle_tolerance)
            ik.AddMinimumDistanceLowerBoundConstraint(params.clearance, params.clearance + 0.05)
            ik.prog().AddQuadraticErrorCost(weights, nominal, ik.q())
            ik.prog().SetSolverOption(SnoptSolver().solver_id(), "Major iterations limit", IK_MAJOR_ITERATIONS)
            result = Solve(ik.prog(), seed)
            if result.is_success():
                return result.GetSolution(ik.q()), roll_free
    raise RuntimeError(f"solve_strike_ik: no configuration reaches the strike's racket pose at {np.round(strike.p_WR, 4)} m with {params.clearance} m clearance")


@dataclasses.dataclass(frozen=True)
class StrikePlan:
    """The toss then the strike, made and executed by the robot (``plan_strike``).

    toss: the TossPlan. strike: the strike asked for (times from the release). t_hit: the hit, s
    from the toss's start (t_lift + strike.time). q_hit, v_hit (8,): the hit state (IK, and the
    joint velocities of the racket's velocity with no angular velocity). roll_free: the IK freed
    the blade's roll (the whole pose failed). first_segment: the strike's first segment (its
    boundary the first at or after t_lift). commands: the whole command sequence (toss then
    strike, as the supervisor executes it). motion: the executed joints. intended: the strike's
    racket state. executed: the executed racket state at t_hit (the joints' exact state there:
    what the ball plant's racket sees). executed_mean: the same with the joints' mean velocities
    over the command period around t_hit (``mean_joint_state``; the exact ones carry the eq. (9)
    ripple).
    ball_clearance: the smallest distance (m) from the tossed ball's surface to the blade between
    20 ms after t_lift and 10 ms before t_hit (> 0: the racket does not touch the ball early).
    """

    toss: TossPlan
    strike: Strike
    t_hit: float
    q_hit: np.ndarray
    v_hit: np.ndarray
    contact_offset: np.ndarray
    roll_free: bool
    first_segment: int
    commands: CommandedMotion
    motion: JointMotion
    intended: RacketState
    executed: RacketState
    executed_mean: RacketState
    ball_clearance: float

    @property
    def position_error(self) -> np.ndarray:
        """Executed minus intended blade centre at t_hit (3,), m."""
        return self.executed.position - self.intended.position

    @property
    def normal_error(self) -> float:
        """The angle between the executed and intended forehand normals at t_hit, rad."""
        return float(math.acos(np.clip(np.dot(self.executed.normal, self.intended.normal), -1.0, 1.0)))

    def contact_velocity(self, state: RacketState) -> np.ndarray:
        """The velocity (3,) m/s of the blade's contact point (``contact_offset``) in ``state``."""
        return state.velocity + np.cross(state.angular_velocity, self.contact_offset)

    @property
    def velocity_error(self) -> np.ndarray:
        """Executed (exact) minus intended velocity of the contact point at t_hit (3,), m/s."""
        return self.contact_velocity(self.executed) - self.strike.v_WR

    @property
    def mean_velocity_error(self) -> np.ndarray:
        """Executed (mean) minus intended velocity of the contact point at t_hit (3,), m/s."""
        return self.contact_velocity(self.executed_mean) - self.strike.v_WR

    @property
    def executed_strike(self) -> Strike:
        """The executed racket at the hit as a translating Strike (times from the release): its
        pose, and the contact point's mean velocity, for ``control.serve.simulate_serve``."""
        return Strike(np.asarray(self.strike.time), self.executed.position, self.executed.rotation, self.contact_velocity(self.executed_mean))


def plan_strike(
    model: RobotModel,
    stack: ControlStack,
    toss: TossPlan,
    strike: Strike,
    params: StrikeParams | None = None,
    dynamics: RobotDynamicsParams | None = None,
) -> StrikePlan:
    """The strike ``strike`` (one; times from the release) made after the toss ``toss`` and
    executed with it (module docstring): from the first segment boundary at or after t_lift, the
    returner's drive (``HitDriver.drive``) towards the hit state (``solve_strike_ik``,
    ``hit_velocity_bounds``, ``strike_velocities``) at t_hit less the joints' lag, then ``follow_segments``
    following through, each proposed to ``stack``; the toss's commands before that boundary are
    kept. Raises RuntimeError if the hit is before that boundary or the IK fails."""
    params = StrikeParams() if params is None else params
    dynamics = model.scenario.dynamics if dynamics is None else dynamics
    if strike.shape != ():
        raise ValueError(f"plan_strike: one strike expected, got a batch {strike.shape}")
    if toss.t_lift is None:
        raise ValueError("plan_strike: the toss released no ball")
    T, N = stack.segment_duration, stack.control.segment_samples
    lag = joint_lag(model.scenario) if params.lag is None else params.lag
    t_hit = toss.t_lift + float(strike.time)
    first = int(math.ceil(toss.t_lift / T - 1e-9))
    if t_hit - lag <= first * T:
        raise RuntimeError(f"plan_strike: the hit at t = {t_hit:.3f} s comes before the strike's first segment at {first * T:.3f} s")
    q_start, v_start, _ = plan_state(toss.commands.plan, first * N)
    q_hit, roll_free = solve_strike_ik(model, strike, q_start, params)
    lower, upper = hit_velocity_bounds(q_start, v_start, q_hit, t_hit - lag - first * T, stack.limits.velocity,
                                       stack.control.reach_fraction * stack.limits.acceleration)
    ball = toss_ball(toss.intended, toss.physics, float(strike.time))[:3]
    contact_offset = ball - toss.physics.aero.ball_radius * strike.normal - strike.p_WR
    v_hit = strike_velocities(model, q_hit, strike.v_WR, contact_offset, lower, upper)
    driver = HitDriver(stack)
    last = int(math.floor((t_hit - lag) / T - 1e-9))  # the segment in which the commanded hit falls

    def choose(k, q, v, a):
        if k <= last:
            return driver.drive(q, v, a, q_hit, v_hit, t_hit - lag - k * T)
        return driver.follow_through(q, v, a)

    commands = command_segments(stack, toss.commands.plan.until(first * N), first, choose, last - first + 1 + params.follow_segments)
    motion = execute_commands(dynamics, commands.plan)
    state = motion.state_at(np.array([0]), np.array([t_hit]))[0]
    executed = racket_state(model, state[:8], state[8:])
    _, v_mean, _ = mean_joint_state(motion, t_hit)
    executed_mean = racket_state(model, state[:8], v_mean)
    intended = RacketState(strike.p_WR, strike.R_WR, strike.v_WR, np.zeros(3))
    clearance = _ball_clearance(model, toss, motion, t_hit)
    return StrikePlan(toss, strike, t_hit, q_hit, v_hit, contact_offset, roll_free, first, commands, motion, intended, executed, executed_mean, clearance)


def blade_distance(X_WR_rotation, X_WR_translation, p_W, radius: float, thickness: float) -> float:
    """The distance (m) from a point p_W (3,) to the blade: a disc of ``radius`` and ``thickness``
    (m) centred on the racket frame's origin, normal to its z (0 inside)."""
    p_R = np.asarray(X_WR_rotation).T @ (np.asarray(p_W) - np.asarray(X_WR_translation))
    radial = math.hypot(p_R[0], p_R[1]) - radius
    axial = abs(p_R[2]) - 0.5 * thickness
    if radial <= 0.0:
        return max(axial, 0.0)
    if axial <= 0.0:
        return radial
    return math.hypot(radial, axial)


def _ball_clearance(model, toss, motion, t_hit, start_after: float = 0.02, stop_before: float = 0.01, step: float = 0.002) -> float:
    """``StrikePlan.ball_clearance``: the tossed ball's surface to the blade (m, smallest)."""
    physics = toss.physics
    times = np.arange(toss.t_lift + start_after, t_hit - stop_before, step)
    if times.size == 0:
        return math.inf
    balls = toss_ball_positions(toss, times)
    states = motion.state_at(np.zeros(times.size, dtype=int), times)
    racket = physics.racket
    distances = []
    for state, ball in zip(states, balls):
        X_WR = model.racket_pose(state[:8])
        distances.append(blade_distance(X_WR.rotation().matrix(), X_WR.translation(), ball, racket.blade_radius, racket.blade_thickness))
    return float(min(distances)) - physics.aero.ball_radius


def toss_ball_positions(toss: TossPlan, times) -> np.ndarray:
    """The released ball's centre (..., 3) at plan times ``times`` (..., s from the toss's start,
    >= t_lift): its free flight from the executed release."""
    return toss_ball(toss.release, toss.physics, np.asarray(times, dtype=float) - toss.t_lift)[..., :3]
