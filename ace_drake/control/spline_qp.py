"""The segment QP (paper, Methods *Optimization problem formulation*): per joint, a cubic spline
over one 32 ms segment from the current (q, v, a) to the mapped terminal (q_T, v_T), minimising the
integrated squared jerk, within the command limits at the 1 kHz samples.

With knots at the N samples (every h = 1 ms), a C2 cubic spline has piecewise-linear acceleration,
so it is fixed by the knot accelerations a_1 .. a_N (a_0 = the current acceleration):

    v_{k+1} = v_k + h (a_k + a_{k+1}) / 2,   q_{k+1} = q_k + h v_k + h^2 (2 a_k + a_{k+1}) / 6,
    integral of jerk^2 = sum_k (a_{k+1} - a_k)^2 / h,

a QP in N unknowns per joint with box bounds |a_k| <= A (tighter for a_N near the velocity
limit: ``CommandLimits.acceleration_bounds``, so that the reset can start there), two-sided rows |v_k| <= V and
lower <= q_k <= upper (k = 1 .. N-1; acceleration is linear between knots, so its bound holds
everywhere), and two equalities v_N = v_T, q_N = q_T. The terminal acceleration a_N is free: it is
the next segment's a_0. The matrices are built once; a solve changes only the linear cost term
and the bounds. Solved with DAQP (the paper's solver; an exact active-set method), after a
shortcut: the optimum under the two equalities alone (one precomputed KKT inverse for all eight
joints) is the QP's optimum wherever it meets every bound, so only the joints where a bound is
active (about 3 of 8 in rally strokes) reach DAQP; or, for
comparison, through Drake's MathematicalProgram with Clarabel (an interior-point method; OSQP,
first-order, left acceleration-bound violations of 2e-2 at its default tolerances and reported
the problem infeasible at 1e-9 ones, so it is not offered).
"""

from __future__ import annotations

import dataclasses

import daqp
import numpy as np

from ace_drake.control.trajectory import CommandLimits
from ace_drake.robot.trajectory import JointTrajectory

EQUALITY = 5  # DAQP's sense flag for an equality row


@dataclasses.dataclass(frozen=True)
class SegmentSolution:
    """A spline QP's outcome: ``trajectory`` (N + 1 samples from the start) when ``success``;
    otherwise None, with the solver's ``status``. ``worst_violation`` is the largest constraint
    violation of the returned samples (rad or m, per s, per s^2), checked after every solve."""

    success: bool
    trajectory: JointTrajectory | None
    status: str
    worst_violation: float


class SegmentQp:
    """The jerk-minimising spline QP for the eight joints (module docstring), built once.

    ``solve`` is the fast path (DAQP, one small QP per joint); ``solver`` "clarabel" solves the
    same problem as one MathematicalProgram through Drake instead.
    """

    def __init__(self, limits: CommandLimits, samples: int = 32, period: float = 0.001, knot_samples: int = 1, solver: str = "daqp", tolerance: float = 1e-6):
        """limits: the command limits; samples N and period h (s): the segment's 1 kHz samples;
        knot_samples: samples per spline piece (N must be a multiple); solver: "daqp" or
        "clarabel"; tolerance: the largest constraint violation (in the constraints'
        units) accepted from a solver before the solve counts as failed."""
        if samples < 2 or period <= 0 or knot_samples < 1 or samples % knot_samples:
            raise ValueError(f"SegmentQp: need samples >= 2, period > 0 s and samples a multiple of knot_samples, got {samples}, {period}, {knot_samples}")
        if solver not in ("daqp", "clarabel"):
            raise ValueError(f"SegmentQp: solver must be daqp or clarabel, got {solver!r}")
        self.limits, self.samples, self.period, self.solver, self.tolerance = limits, samples, period, solver, tolerance
        N, h = samples, period
        M = samples // knot_samples  # spline pieces
        self.knots = M
        # Sample accelerations from the knots' (linear interpolation), then sample velocities and
        # positions as linear maps of the sample accelerations (the v0, q0 terms apart): exact,
        # since the acceleration is linear between consecutive samples too.
        knot_times = np.arange(M + 1) * knot_samples
        self._interpolation = np.array([np.interp(k, knot_times, np.eye(M + 1)[j]) for k in range(N + 1) for j in range(M + 1)]).reshape(N + 1, M + 1)
        velocity_map = np.zeros((N + 1, N + 1))
        position_map = np.zeros((N + 1, N + 1))
        for k in range(N):
            velocity_map[k + 1] = velocity_map[k]
            velocity_map[k + 1, k] += h / 2
            velocity_map[k + 1, k + 1] += h / 2
            position_map[k + 1] = position_map[k] + h * velocity_map[k]
            position_map[k + 1, k] += h * h / 3
            position_map[k + 1, k + 1] += h * h / 6
        self._velocity_map = velocity_map @ self._interpolation  # (N + 1, M + 1) over the knots
        self._position_map = position_map @ self._interpolation
        self._times = h * np.arange(N + 1)
        difference = np.diff(np.eye(M + 1), axis=0)  # (M, M + 1): a_{j+1} - a_j
        hessian = 2.0 / (knot_samples * h) * difference.T @ difference  # of 0.5 x' H x over [a_0, x]
        # Rows: v_1 .. v_{N-1}, q_1 .. q_{N-1}, then v_N, q_N (the equalities).
        rows = np.concatenate([self._velocity_map[1:N], self._position_map[1:N], self._velocity_map[N:], self._position_map[N:]])
        # DAQP works on a scaled problem: unknowns x = a / A (per joint) and unit-norm rows.
        self._row_norms = np.linalg.norm(rows[:, 1:], axis=1)
        self._rows_start = rows[:, 0]
        self._rows = np.ascontiguousarray(rows[:, 1:] / self._row_norms[:, None])
        self._hessian = np.ascontiguousarray(hessian[1:, 1:])
        self._hessian_cross = hessian[1:, 0]  # times a_0: the linear term
        self._sense = np.zeros(M + rows.shape[0], dtype=np.int32)
        self._sense[-2:] = EQUALITY
        self._bound_scale = np.concatenate([np.ones(M), 1.0 / self._row_norms])
        # The optimum with the two equalities only (KKT of min 0.5 a' H a + f' a, E a = b): when
        # it meets every inequality it is the QP's optimum, and most joints need no active-set
        # solve. solution = [a; multipliers] = kkt_inverse @ [-f; b].
        equality_rows = rows[-2:, 1:]
        kkt = np.block([[hessian[1:, 1:], equality_rows.T], [equality_rows, np.zeros((2, 2))]])
        self._kkt_inverse = np.linalg.inv(kkt)
        self._all_rows = np.ascontiguousarray(rows[:, 1:])  # unscaled, over a_1 .. a_M
        self._daqp = daqp.Model()
        self._daqp.settings = {**self._daqp.settings, "primal_tol": 1e-9}
        self._daqp.setup(self._hessian, np.zeros(M), self._rows, np.ones(self._sense.size), -np.ones(self._sense.size), self._sense)
        self._program = None

    # ------------------------------------------------------------------------------ solving
    def solve(self, q0, v0, a0, q_terminal, v_terminal) -> SegmentSolution:
        """The segment from (q0, v0, a0) to (q_terminal, v_terminal), each (8,), in rad or m,
        per s and per s^2."""
        values = [np.asarray(x, dtype=float) for x in (q0, v0, a0, q_terminal, v_terminal)]
        if not all(x.shape == (8,) and np.all(np.isfinite(x)) for x in values):
            raise ValueError("SegmentQp.solve: q0, v0, a0, q_terminal, v_terminal must each be 8 finite values")
        return self.solve_batch(*(x[None] for x in values)).solution(0)

    def solve_batch(self, q0, v0, a0, q_terminal, v_terminal) -> "SegmentBatch":
        """The segments of B environments at once, from (q0, v0, a0) to (q_terminal,
        v_terminal), each (B, 8) in rad or m, per s and per s^2; row b equals ``solve`` of row b.
        The equality-constrained optimum (one precomputed KKT inverse) is computed for every
        joint of every row at once and checked against every bound; DAQP solves only the joints
        where one binds, in row then joint order (as a loop of ``solve`` would)."""
        q0, v0, a0, q_terminal, v_terminal = (np.asarray(x, dtype=float) for x in (q0, v0, a0, q_terminal, v_terminal))
        shape = q0.shape
        if len(shape) != 2 or shape[1] != 8 or not all(x.shape == shape and np.all(np.isfinite(x)) for x in (q0, v0, a0, q_terminal, v_terminal)):
            raise ValueError(f"SegmentQp.solve_batch: q0, v0, a0, q_terminal, v_terminal must each be (B, 8) finite values, got shapes {[np.shape(x) for x in (q0, v0, a0, q_terminal, v_terminal)]}")
        lower, upper = self._row_bounds(q0, v0, a0, q_terminal, v_terminal)  # (B, 8, M + rows)
        linear = a0[..., None] * self._hessian_cross  # (B, 8, M)
        rows = shape[0]
        if self.solver == "daqp":
            accelerations, status, failed = self._solve_daqp(linear, lower, upper)
        else:
            solved = [self._solve_program(linear[row], lower[row], upper[row]) for row in range(rows)]
            failed = np.array([x is None for x, _ in solved], dtype=bool)
            accelerations = np.stack([np.zeros((8, self.knots)) if x is None else x for x, _ in solved])
            status = [text for _, text in solved]
        return self._checked(q0, v0, a0, accelerations, q_terminal, v_terminal, status, failed)

    def _row_bounds(self, q0, v0, a0, q_terminal, v_terminal):
        """Bounds (B, 8, N + rows) of [x; rows x], the start's contribution moved to the right,
        for starts and targets (B, 8)."""
        N, M, limits = self.samples, self.knots, self.limits
        inner = self._times[1:N]
        start_v = v0[..., None] + a0[..., None] * self._rows_start[: N - 1]
        start_q = q0[..., None] + v0[..., None] * inner + a0[..., None] * self._rows_start[N - 1 : 2 * N - 2]
        end_v = v0 + a0 * self._rows_start[-2]
        end_q = q0 + v0 * self._times[N] + a0 * self._rows_start[-1]
        box = np.repeat(np.broadcast_to(limits.acceleration, q0.shape)[..., None], M, axis=-1)
        low_box = -box
        # The terminal acceleration starts the reset: no more than its jerk-limited ramp to zero
        # can take without passing the velocity limit.
        low_box[..., -1], box[..., -1] = limits.acceleration_bounds(v_terminal)
        speed = np.broadcast_to(limits.velocity[:, None], start_v.shape)
        upper_q, lower_q = (np.broadcast_to(x[:, None], start_q.shape) for x in (limits.upper, limits.lower))
        v_gap, q_gap = (v_terminal - end_v)[..., None], (q_terminal - end_q)[..., None]
        upper = np.concatenate([box, speed - start_v, upper_q - start_q, v_gap, q_gap], axis=-1)
        lower = np.concatenate([low_box, -speed - start_v, lower_q - start_q, v_gap, q_gap], axis=-1)
        return lower, upper

    def _solve_daqp(self, linear, lower, upper):
        """The QP per joint (of rows (B, 8, ...)): the equality-constrained optimum where it
        meets every bound (then it is the QP's optimum), else DAQP on a scaled problem: unknowns
        x = a / A and each row divided by its norm, so row . a <= b becomes (row / |row|) . x <=
        b / (A |row|), and the cost 0.5 a' H a + f' a becomes (up to the factor A^2) 0.5 x' H x +
        (f / A)' x. H and the rows are then the same for every joint: one DAQP workspace, set up
        once, takes new cost vectors and bounds. Returns the accelerations (B, 8, M), each
        row's status and whether it failed (B,) (a row stops at its first joint DAQP fails on)."""
        M = self.knots
        rows = linear.shape[0]
        right = np.concatenate([-linear, upper[..., -2:]], axis=-1).reshape(rows * 8, M + 2)  # [-f; b]
        solution = _product(right, self._kkt_inverse.T)[:, :M]
        values = np.concatenate([solution, _product(solution, self._all_rows[:-2].T)], axis=1)
        slack = self.tolerance * 1e-3
        flat_lower, flat_upper, flat_linear = (x.reshape(rows * 8, -1) for x in (lower, upper, linear))
        inside = np.all((values >= flat_lower[:, :-2] - slack) & (values <= flat_upper[:, :-2] + slack), axis=1)
        status = ["daqp: solved"] * rows
        failed = np.zeros(rows, dtype=bool)
        for index in np.flatnonzero(~inside):
            row, joint = divmod(int(index), 8)
            if failed[row]:
                continue
            A = self.limits.acceleration[joint]
            scale = self._bound_scale / A
            # The sense flags reset the working set: a cold start, so that a joint's solution
            # does not depend on the problems solved before it.
            self._daqp.update(f=flat_linear[index] / A, bupper=flat_upper[index] * scale, blower=flat_lower[index] * scale, sense=self._sense)
            x, _, exitflag, _ = self._daqp.solve()
            if exitflag < 1:
                status[row], failed[row] = f"daqp exit flag {exitflag} on joint {joint}", True
                continue
            solution[index] = A * x
        return solution.reshape(rows, 8, M), status, failed

    def _solve_program(self, linear, lower, upper):
        # Lazy: Drake's solvers serve only the solver='clarabel' reference; control is NumPy + DAQP.
        from pydrake.solvers import ClarabelSolver

        if self._program is None:
            self._build_program()
        program, variables, cost, box, rows = self._program
        N = self.knots
        cost.evaluator().UpdateCoefficients(np.kron(np.eye(8), self._hessian), linear.ravel())
        box.evaluator().set_bounds(lower[:, :N].ravel(), upper[:, :N].ravel())
        rows.evaluator().set_bounds(lower[:, N:].ravel(), upper[:, N:].ravel())
        result = ClarabelSolver().Solve(program)
        if not result.is_success():
            return None, f"{self.solver}: {result.get_solution_result()}"
        return result.GetSolution(variables).reshape(8, N), f"{self.solver}: solved"

    def _build_program(self) -> None:
        """The same QP for all eight joints as one MathematicalProgram (block-diagonal)."""
        from pydrake.solvers import MathematicalProgram  # lazy, as in _solve_program

        N = self.knots
        program = MathematicalProgram()
        variables = program.NewContinuousVariables(8 * N, "a")
        cost = program.AddQuadraticCost(np.kron(np.eye(8), self._hessian), np.zeros(8 * N), variables, is_convex=True)
        box = program.AddBoundingBoxConstraint(np.zeros(8 * N), np.zeros(8 * N), variables)
        rows_per_joint = self._rows.shape[0]
        unscaled = self._rows * self._row_norms[:, None]
        rows = program.AddLinearConstraint(np.kron(np.eye(8), unscaled), np.zeros(8 * rows_per_joint), np.zeros(8 * rows_per_joint), variables)
        self._program = (program, variables, cost, box, rows)

    # ------------------------------------------------------------------------------ checking
    def _checked(self, q0, v0, a0, accelerations, q_terminal, v_terminal, status, failed) -> "SegmentBatch":
        """Samples of the solved splines (B rows), each row accepted only if it meets every
        constraint to within the tolerance (never execute a solver's garbage); rows that
        ``failed`` in the solver keep their status and no samples."""
        rows, M, N = q0.shape[0], self.knots, self.samples
        knots = np.concatenate([a0[..., None], accelerations], axis=-1).reshape(rows * 8, M + 1)
        v = (v0.reshape(-1, 1) + _product(knots, self._velocity_map.T)).reshape(rows, 8, N + 1)
        q = (q0.reshape(-1, 1) + v0.reshape(-1, 1) * self._times + _product(knots, self._position_map.T)).reshape(rows, 8, N + 1)
        a = _product(knots, self._interpolation.T).reshape(rows, 8, N + 1)
        knots = knots.reshape(rows, 8, M + 1)
        limits, tolerance = self.limits, self.tolerance
        worst = np.max(
            np.stack(
                [
                    np.max(np.abs(knots[..., 1:]) - limits.acceleration[:, None], axis=(1, 2)),
                    np.max(np.abs(v) - limits.velocity[:, None], axis=(1, 2)),
                    np.max(np.maximum(q - limits.upper[:, None], limits.lower[:, None] - q), axis=(1, 2)),
                    np.max(np.abs(v[..., -1] - v_terminal), axis=1),
                    np.max(np.abs(q[..., -1] - q_terminal), axis=1),
                ]
            ),
            axis=0,
        )
        worst = np.maximum(worst, 0.0)
        status = list(status)
        success = ~failed & np.isfinite(worst) & (worst <= tolerance)
        worst = np.where(failed, np.inf, worst)
        for row in np.flatnonzero(~failed & ~success):
            status[row] = f"{status[row]}, but a constraint is violated by {worst[row]:.3g}"
        # Samples as (B, N + 1, 8), contiguous per row.
        q, v, a = (np.ascontiguousarray(np.swapaxes(x, 1, 2)) for x in (q, v, a))
        return SegmentBatch(self.period, success, status, worst, q, v, a)


def _product(x: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """x @ matrix for x (8 B, k): one (8, k) product per environment (a 3-D matmul), so that a
    row's result does not depend on the batch it is in (one (8 B, k) product rounds differently
    with B, and OpenBLAS runs it on threads that here cost far more than they save)."""
    return np.matmul(x.reshape(-1, 8, x.shape[-1]), matrix).reshape(x.shape[0], matrix.shape[1])


@dataclasses.dataclass(frozen=True)
class SegmentBatch:
    """The outcomes of ``SegmentQp.solve_batch`` for B rows: ``success`` (B,) booleans,
    ``status`` (B strings), ``worst_violation`` (B,) (inf where the solver failed), and the
    samples q, v, a (B, N + 1, 8) (rad or m, per s, per s^2; meaningful only where
    ``success``). ``solution(b)`` is row b as ``SegmentQp.solve`` returns it."""

    period: float
    success: np.ndarray
    status: list[str]
    worst_violation: np.ndarray
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray

    def __len__(self) -> int:
        return self.success.shape[0]

    def solution(self, row: int) -> SegmentSolution:
        """Row ``row`` as a SegmentSolution (its trajectory views this batch's samples)."""
        trajectory = JointTrajectory(self.period, self.q[row], self.v[row], self.a[row]) if self.success[row] else None
        return SegmentSolution(bool(self.success[row]), trajectory, self.status[row], float(self.worst_violation[row]))
