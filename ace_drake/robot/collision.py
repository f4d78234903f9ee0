"""Sound collision checking of sampled joint trajectories: a broad phase over the whole plan at
once, then conservative advancement on Drake's exact distances where it cannot decide.

The safety supervisor checks each 32 ms segment plus its reset trajectory (up to ~1 s at 1 kHz)
for robot self-collision and robot-court collision (table, net and posts, floor) before it
streams them, inside a control step whose p99 budget is 2 ms. ``TrajectoryCollisionChecker.check``
is *sound*: when it reports ``free``, every point of the robot's collision geometry stays at least
``margin`` (m) from the court and from its own other collision geometries at every instant of the
continuous motion, not only at the samples. It may report as not free a motion that only comes
within margin + 0.2 mm (``DISTANCE_ERROR`` + ``PROOF_TOLERANCE``) of something; it never misses a
collision.

The continuous motion. Between samples k and k + 1 (``period`` h apart) each joint follows the
cubic Hermite interpolant of (q_k, v_k) and (q_{k+1}, v_{k+1}) (``interpolate``); this is exact
for piecewise-cubic (constant-jerk) motion with its knots at the samples. On interval k the
Hermite velocity of a joint is a quadratic with Bernstein coefficients v_k,
3 (q_{k+1} - q_k) / h - v_k - v_{k+1}, v_{k+1}, so |qdot| is at most the largest of their
magnitudes, and its acceleration is linear, so |qddot| is at most the larger of its values at the
ends; both bounds also cover motion with linear acceleration between consistent sampled a_k,
a_{k+1} (``joint_speed_bounds``, ``joint_acceleration_bounds``). Each joint therefore strays at
most h^2 / 8 max |qddot| from the chord between its samples, and each point of the robot, by the
same argument, at most its ``robot.bounds`` deviation (~0.3 mm at full speed).

Why three stages, cheapest first. In a rally most pairs stay far apart over the whole plan and a
few come within centimetres for a few milliseconds. Conservative advancement on exact distances
alone (this module's earlier design) spent most of its queries proving the obvious: each step
can only go as far as worst-case speed bounds allow from the nearest of all pairs, and over a
stroke those bounds overestimate the racket's travel several times. The broad phase proves the
obvious for a whole plan in one compiled pass from the robot's actual positions at every sample;
the exact stage then works only on the few (pair, interval) cells left open, with certificates
that prove a grazing stretch in one query or converge onto a crossing in a few.

Pairs. The checked pairs are those of Drake's ``SceneGraphCollisionChecker`` on the robot
diagram: SceneGraph's collision filters (the SDF's ``drake:collision_filter_group``s and the
plant's adjacent-body filters) and bodies welded together (the robot's base and the court) are
left out.

1. Gates, for the pairs whose distance depends on at most two joints (the carriages and the
   court, the racket and the forearm, ...): mapped once, at construction, over the joints'
   limits widened by ``GATE_PAD``; branch and bound with the pair rates (below) as Lipschitz
   constants proves where they cannot come within the margin. An interval whose joint box (the
   chord between its samples widened by the joints' deviation) meets no bad cell of a pair's map
   is clear for that pair. ``certified`` names the pairs proven clear over the whole box. The
   handle, 3 cm from the forearm at the ready pose and touching it below wrist_2 = -1 rad, costs
   nothing unless the wrist gets there.
2. Swept bounding boxes (``robot.bounds.SweptBounds``), for the other pairs of boxes, spheres,
   capsules and cylinders: per block of ``BLOCK_SAMPLES`` intervals, then per interval, the
   distance between the boxes that the two geometries (or the spheres covering one of them)
   sweep, from their poses at the samples padded by their deviation, is a lower bound on the
   pair's distance at every instant of the block or interval. In rally plans this leaves open
   only cells where the geometries really are within a centimetre or so: the forearm, wrist and
   racket over the table top and legs.
3. Conservative advancement on Drake's signed distances (``ComputeSignedDistancePairClosestPoints``
   on the robot diagram owned by the ``SceneGraphCollisionChecker``), for each pair only over the
   intervals the first two stages left open, in time order (below).

Distances. Drake's distances for capsules, cylinders and boxes come from GJK and carry errors of
order 1e-5 m (second differences along smooth motions up to 2e-5 m, measured): they are trusted
to within ``DISTANCE_ERROR`` = 1e-4 m, which every pair's budget gives up.

Speed bounds. A prismatic joint j moves every point downstream of it at |qdot_j|; a revolute
joint j at |qdot_j| times the point's distance from j's axis, at most rho_j(g) for the points of
geometry g over all configurations (``_Kinematics.axis_radius``; the lever arms of stage 2):

- g on j's child body: its distance from the axis is fixed, and rho_j(g) is the exact maximum
  over the shape (boxes: their vertices; spheres and capsules: centres or segment ends plus the
  radius; cylinders: their two rims, sampled, plus a Lipschitz pad);
- g further down: the distance from j's axis of the next joint's origin (fixed on j's child
  body), plus the fixed distances between consecutive joint origins on each body further down (a
  revolute joint's origin lies on its axis and stays put as it turns; a prismatic joint's travels
  between its position limits), plus g's largest distance from its body's inboard joint origin.

``speed_radii`` r_j = max_g rho_j(g) (1 for prismatic joints) bounds every point's speed by
sum_j |qdot_j| r_j. For this robot (ace_robot.sdf): 1, 1, then shoulder_yaw and shoulder_pitch
(the pitch pivot lies on the yaw axis) 0.55 + 0.50 + 0.2954 (blade rim from the wrist:
0.22 + hypot(0.075, 0.007)) = 1.345 m, elbow 0.795, wrist_1 and wrist_2 0.295, wrist_3 0.0757 (the blade about
the handle axis).

Pair rates. Only joints on the kinematic path between a pair's two bodies change its distance (a
joint upstream of both moves them rigidly together), each at most at |qdot_j| rho_j of the
geometry it moves. Exact symmetries drop more: turning a revolute joint does not change the
distance to a sphere, capsule or cylinder lying on its axis on its parent body, or of one lying
on its axis on its child body (the forearm capsule and wrist_1; the handle and wrist_3). A shape
only symmetric to within eps (the SDF's 1.5708 for pi / 2) costs 2 eps of budget. So pair p's
distance falls at most at c_p . |qdot| m/s (``pair_rates``); integrating c_p . bound over the
intervals gives each pair's cumulative swept bound S_p.

Conservative advancement (stage 3). Each open pair has a frontier: every instant before it is
proven clear for that pair (by stages 1-2 or by its own queries). The check queries, at the
earliest frontier, the pairs whose frontier it is, and each query's distance d_p (with its
witness normal n, from B to A) proves the pair clear for as long as one of three certificates
holds, the furthest of which moves the pair's frontier; from a sample it then skips to the next
interval stages 1-2 left open for the pair:

- distance: every instant up to where S_p has grown by d_p - margin - slack_p (strictly inside
  the interval if not even its end is reachable, near something and fast);
- height, for a moving robot geometry A and a static geometry B (the court, the robot's base):
  every point of B lies at or below B's top z_B, so the distance is at least the height of A's
  lowest point above z_B, which falls at most at c^z . |qdot|, c^z the pair rate with each joint
  whose axis is fixed in the world scaled by the fraction of its motion that can be vertical
  (zero for the gantry's carriages and the shoulder's yaw: ``_Heights``); a swing over the table
  moves the racket mostly sideways;
- plane: the pair's distance is at least its gap along any fixed unit n (min over A of n . x
  less max over B of n . x), which closed-form supports give at every sample from the poses the
  broad phase computed; within an interval every point stays within its deviation of its chord,
  so the gap is at least the linear blend of its values at the interval's ends less the two
  geometries' deviations. Along a graze this proves the whole open run in one query; towards a
  crossing it predicts where the margin is met, which converges in a few queries.

A configuration where all three start below ``PROOF_TOLERANCE`` ends the check (this stops the
steps shrinking without end along a motion that grazes the margin); the report names the pairs
due there that are within margin + PROOF_TOLERANCE. Every instant before the earliest frontier is
proven clear for every pair, which is what the report's ``time`` says.

Cost (one core, ``ace-drake bench control``): ~0.15 ms for a rally plan (segment and reset, ~300
samples) that the broad phase clears, which is 85% of them; ~0.3-0.6 ms with a few exact queries
(~10 us each in Drake, ~40 us with the advancement's bookkeeping), for the plans that come within
a centimetre of something or collide.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from pathlib import Path

import numba
import numpy as np
from pydrake.common import Parallelism
from pydrake.geometry import Box, Capsule, Cylinder, Ellipsoid, Sphere
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.planning import RobotDiagramBuilder, SceneGraphCollisionChecker

from ace_drake.config import MODELS_DIR
from ace_drake.robot.bounds import Shape, SweptBounds
from ace_drake.robot.model import joint_vector, add_robot_to_plant, check_joint_order, load_scenario
from ace_drake.robot.params import JOINT_NAMES, RobotScenario
from ace_drake.robot.trajectory import JointTrajectory

PROOF_TOLERANCE = 1e-4  # m: a clearance below margin + DISTANCE_ERROR + this counts as a collision
DISTANCE_ERROR = 1e-4  # m: Drake's signed distances are trusted to within this (module doc)
SYMMETRY_TOLERANCE = 1e-4  # m: geometry this close to symmetric about a joint axis counts as symmetric
BLOCK_SAMPLES = 16  # intervals per block of the swept-box stage (8-32 clear about as much; measured)
GATE_PAD = 0.05  # rad or m: the gating box extends this far beyond each joint's position limits
GATE_MAX_JOINTS = 2  # pairs whose distance depends on more joints are not gated
GATE_MAX_QUERIES = 40000  # distance evaluations per pair when mapping where it may come close
# m: cells whose Lipschitz spread is below this are not split further, for pairs that depend on
# one joint and on two (the map's cells grow as resolution^-(joints - 1) along its boundary).
GATE_RESOLUTION = (0.0002, 0.002)
_RIM_SAMPLES = 720  # points per cylinder rim when bounding its distance from an axis or point


_GATES: dict[tuple, tuple] = {}  # TrajectoryCollisionChecker's gates by model and margin (read-only once built)


@dataclasses.dataclass(frozen=True)
class CollisionReport:
    """The outcome of ``TrajectoryCollisionChecker.check``.

    free: every configuration of the continuous motion is at least ``margin`` clear.
    time: s from the trajectory's start of the first configuration found not provably margin
        clear (closer than margin + DISTANCE_ERROR + PROOF_TOLERANCE; every earlier instant is
        proven clear); None if free. With the query budget spent: how far the motion was proven.
    pairs: "body/geometry - body/geometry" names of the pairs that close there, closest first
        (robot geometry first); empty if free or the query budget was spent.
    queries: exact distance queries the advancement made (Drake signed-distance calls for one
        pair; the broad phase makes none).
    min_distance: the smallest clearance the check established, m, capped at the influence
        distance: the swept-box bounds of the blocks and intervals they cleared, and Drake's
        distances where it queried (pairs cleared by their gates are not measured).
    """

    free: bool
    time: float | None
    pairs: tuple[str, ...]
    queries: int
    min_distance: float


@dataclasses.dataclass(frozen=True)
class _Pair:
    """A checked pair of collision geometries: its name, its distance-rate coefficients c (8,)
    (m per rad or per m of each joint's motion), the budget it loses to inexact symmetry and
    distance error (m), the SceneGraph ids (robot geometry first), the sum of the two
    geometries' lever arms rho (8,) (``_Kinematics.lever_arms``), and for the plane certificate
    each geometry's body, pose in it (3 x 4) and ``Shape`` (half (3,), radius, rounding as (5,)),
    A's then B's (None if either shape has no closed-form support)."""

    name: str
    rate: np.ndarray
    slack: float
    id_A: object
    id_B: object
    arms: np.ndarray
    geometry: tuple | None


class TrajectoryCollisionChecker:
    """Sound collision checking of ``JointTrajectory``s of the robot in ``scenario`` (see the module
    doc). Joint vectors q (8,) are in JOINT_NAMES order, m and rad.

    margin: the clearance (m) every point of the robot must keep from the court and from itself.
    influence: distances beyond this (m) are not reported by ``clearance`` and ``pair_distances``
        nor in reports; must exceed margin.

    Attributes: ``speed_radii`` (8,) r_j (m per rad, 1 for the prismatic joints): every point of
    the robot's collision geometry moves at most sum_j |qdot_j| r_j m/s. ``certified``: names of
    the pairs proven at least margin apart over the whole box [box_lower, box_upper] (8,) (the
    position limits widened by GATE_PAD).
    """

    def __init__(
        self,
        scenario: RobotScenario | None = None,
        margin: float = 0.005,
        influence: float = 0.3,
        models_dir: str | Path = MODELS_DIR,
    ):
        if not (math.isfinite(margin) and margin >= 0.0):
            raise ValueError(f"TrajectoryCollisionChecker: margin must be a finite distance >= 0 (m), got {margin}")
        if not (math.isfinite(influence) and influence > margin + DISTANCE_ERROR + PROOF_TOLERANCE):
            raise ValueError(f"TrajectoryCollisionChecker: influence must be finite and > margin + {DISTANCE_ERROR + PROOF_TOLERANCE} m, got {influence} (margin {margin})")
        self.scenario = scenario or load_scenario()
        self.margin = float(margin)
        self.influence = float(influence)
        builder = RobotDiagramBuilder(time_step=0.0)
        robot = add_robot_to_plant(builder.plant(), self.scenario, models_dir)
        builder.plant().Finalize()
        check_joint_order(builder.plant(), robot)
        self.robot = robot
        # The checker owns the diagram and decides which body pairs are filtered; one thread.
        self.checker = SceneGraphCollisionChecker(
            model=builder.Build(), robot_model_instances=[robot], edge_step_size=0.05, implicit_context_parallelism=Parallelism(1)
        )
        self.plant = self.checker.plant()
        self.inspector = self.checker.model().scene_graph().model_inspector()
        self._kinematics = _Kinematics(self.plant, self.inspector)
        self.speed_radii = self._kinematics.speed_radii()
        self._pairs, self._pair_index = self._build_pairs()
        self._rate_matrix = np.array([pair.rate for pair in self._pairs]).reshape(-1, len(JOINT_NAMES))
        self._full = self.checker.MakeStandaloneModelContext()
        self._heights = self._build_heights()
        # Pairs whose distance depends on at most GATE_MAX_JOINTS joints: where in those joints'
        # box they may come within margin (nowhere: certified clear).
        self.box_lower = self.plant.GetPositionLowerLimits() - GATE_PAD
        self.box_upper = self.plant.GetPositionUpperLimits() + GATE_PAD
        # The maps are a pure function of the model (its scenario and files) and the margin, and
        # take ~1 s to build: built once per process for each.
        models_dir = Path(models_dir)
        gate_key = (repr(self.scenario), *((models_dir / name).read_bytes() for name in (self.scenario.court_model, self.scenario.robot_model)), self.margin)
        if gate_key not in _GATES:
            _GATES[gate_key] = tuple(gate for p in range(len(self._pairs)) if (gate := self._gate(p)) is not None)
        self._gates = list(_GATES[gate_key])
        self.certified = tuple(self._pairs[gate.pair].name for gate in self._gates if not gate.bad)
        self._bounds = SweptBounds(self.plant, self.inspector, [(pair.id_A, pair.id_B) for pair in self._pairs], self._kinematics.lever_arms)
        # For the broad phase: the pairs of each stage when the plan stays inside the gates' box.
        self._box_lower, self._box_upper = self.box_lower.tolist(), self.box_upper.tolist()
        self._gated_pairs = {gate.pair for gate in self._gates}
        self._bad_gates = [gate for gate in self._gates if gate.bad]
        self._bounded = np.flatnonzero(self._bounds.bounded)
        self._bounded_ungated = np.array([p for p in self._bounded if p not in self._gated_pairs], dtype=int)
        self._unbounded = np.flatnonzero(~self._bounds.bounded).tolist()
        self._unbounded_gated = all(p in self._gated_pairs for p in self._unbounded)
        self._upstream = self._kinematics.upstream_matrix()
        self._warm_up()

    def _warm_up(self) -> None:
        """Runs each compiled kernel once on the ready pose, so that loading (or, the first time,
        compiling) it is part of the construction and not of a control step."""
        q = np.tile(np.asarray(self.scenario.ready_pose, dtype=float), (2, 1))
        _, sag, bend = _motion_bounds(q, np.zeros_like(q), np.zeros_like(q), 0.001, self._upstream)
        q_columns = np.ascontiguousarray(q.T)
        _joint_ranges(q_columns, sag)
        self._bounds.open_intervals(q_columns, bend, BLOCK_SAMPLES, self._bounded, math.inf)  # every level
        X_WB = self._bounds.kinematics.pose_rows(q_columns)
        pair = next((pair for pair in self._pairs if pair.geometry is not None), None)
        if pair is not None:
            _plane_reach(X_WB[:, :, :1].copy(), X_WB, pair.geometry, np.array([0.0, 0.0, 1.0]), np.zeros(1), np.ones(1, dtype=bool), 0, 0.0, self.margin)

    # ------------------------------------------------------------------------------ configurations
    def clearance(self, q: np.ndarray) -> float:
        """The smallest signed distance (m) between the robot's collision geometry and the court
        or its own other (non-filtered) geometry at configuration q, capped at ``influence``."""
        distances = self._distances(joint_vector(q, "q"))
        return min(self.influence, min((d for _, d in distances), default=self.influence))

    def check_config(self, q: np.ndarray) -> bool:
        """Whether configuration q is at least ``margin`` clear (``clearance(q) >= margin``)."""
        return self.clearance(q) >= self.margin

    def pair_distances(self, q: np.ndarray) -> list[tuple[str, float]]:
        """The checked geometry pairs within ``influence`` at q, as (name, signed distance m),
        closest first."""
        distances = self._distances(joint_vector(q, "q"))
        return sorted(((self._pairs[p].name, d) for p, d in distances), key=lambda item: item[1])

    def pair_rates(self) -> dict[str, np.ndarray]:
        """Each checked geometry pair's distance-rate coefficients c (8,): its distance changes at
        most at c . |qdot| m/s (see the module doc)."""
        return {pair.name: pair.rate.copy() for pair in self._pairs}

    # ------------------------------------------------------------------------------ trajectories
    def check(self, trajectory: JointTrajectory, max_queries: int | None = None) -> CollisionReport:
        """Whether the continuous motion of ``trajectory`` (the Hermite interpolant of its samples)
        keeps the robot at least ``margin`` clear of the court and itself: gates and swept
        boxes over the whole plan, then conservative advancement on exact distances where they
        leave a pair open (module doc).

        max_queries: a budget of exact queries; once spent, the report is not free, with ``time``
        how far the motion was proven clear and no ``pairs`` (unproven rather than a collision
        found)."""
        if max_queries is not None and max_queries < 1:
            raise ValueError(f"check: max_queries must be >= 1, got {max_queries}")
        q, v, a, period = _trajectory_arrays(trajectory)
        if q.shape[0] == 1:  # one configuration: an interval that does not move
            q, v, a = q[[0, 0]], np.zeros((2, len(JOINT_NAMES))), np.zeros((2, len(JOINT_NAMES)))
        cumulative, sag, bend = _motion_bounds(q, v, a, period, self._upstream)
        pairs, open_intervals, min_distance, X_WB = self._broad_phase(np.ascontiguousarray(q.T), sag, bend)
        if not len(pairs):
            return CollisionReport(True, None, (), 0, min_distance)
        return self._advance(q, v, period, cumulative, bend, X_WB, pairs, open_intervals, math.inf if max_queries is None else max_queries, min_distance)

    # ------------------------------------------------------------------------------ internals
    def _broad_phase(self, q: np.ndarray, sag: np.ndarray, bend: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """Stages 1 and 2 (module doc) for samples q (8, n + 1), the joints' deviations from their
        chords (8, n) and the points' deviation terms bend (8, n), joints by samples (see
        ``check``): the pairs left open (O,), which of their intervals are (O, n) bool, the
        smallest clearance established (m, capped at influence), and the body poses at the
        samples (``KinematicTree.pose_rows``)."""
        n = sag.shape[1]
        # On interval k each joint stays within sag_k of its chord: within [lower_k, upper_k]
        # (8, n) (computed only if a gate needs them), and all of the motion within [low, high].
        low, high = (bound.tolist() for bound in _joint_ranges(q, sag))
        inside = [lo >= box_lo and hi <= box_hi for lo, hi, box_lo, box_hi in zip(low, high, self._box_lower, self._box_upper)]
        pairs, rows = [], []  # the open pairs and their open intervals
        if all(inside):
            gated, gates = self._gated_pairs, self._bad_gates
        else:  # only the gates whose joints stay inside their map decide
            gates = [gate for gate in self._gates if all(inside[j] for j in gate.joints.tolist())]
            gated = {gate.pair for gate in gates}
        lower = upper = None
        for gate in gates:
            if gate.bad and gate.box_touches(low, high):
                if lower is None:
                    lower, upper = np.minimum(q[:, :-1], q[:, 1:]) - sag, np.maximum(q[:, :-1], q[:, 1:]) + sag
                row = gate.touched(lower, upper)
                if row.any():
                    pairs.append(gate.pair)
                    rows.append(row)
        bounded = self._bounded_ungated if gated is self._gated_pairs else np.array([p for p in self._bounded.tolist() if p not in gated], dtype=int)
        swept_open, smallest, X_WB = self._bounds.open_intervals(q, bend, BLOCK_SAMPLES, bounded, self.margin)
        min_distance = min(self.influence, smallest)
        if not pairs and gated is self._gated_pairs and self._unbounded_gated:  # the common case: the swept boxes' pairs only
            if not swept_open.any():  # and all of them cleared
                return bounded[:0], swept_open[:0], min_distance, X_WB
            failing = np.flatnonzero(swept_open.any(axis=1))
            return bounded[failing], swept_open[failing], min_distance, X_WB
        failing = np.flatnonzero(swept_open.any(axis=1))
        pairs += bounded[failing].tolist()
        rows += list(swept_open[failing])
        for p in self._unbounded:  # pairs only the exact stage can check
            if p not in gated:
                pairs.append(p)
                rows.append(np.ones(n, dtype=bool))
        return np.array(pairs, dtype=int), np.array(rows, dtype=bool).reshape(len(pairs), n), min_distance, X_WB

    def _advance(self, q, v, period: float, cumulative: np.ndarray, bend: np.ndarray, X_WB: np.ndarray, pairs: np.ndarray, open_intervals: np.ndarray, budget: float, min_distance: float) -> CollisionReport:
        """Stage 3 (module doc): conservative advancement of each of ``pairs`` over its open
        intervals (O, n), at most ``budget`` exact queries; cumulative (n + 1, 8): each joint's
        cumulative travel bound at each sample; bend (8, n): the points' deviation terms
        (``_motion_bounds``); X_WB: the body poses at the samples (``KinematicTree.pose_rows``)."""
        n = open_intervals.shape[1]
        checked = [self._pairs[p] for p in pairs.tolist()]
        heights, kinematics = self._heights, self._bounds.kinematics
        height_of = [heights.pair_certificate[p] for p in pairs.tolist()]  # -1: none
        swept = (self._rate_matrix[pairs] @ cumulative.T).tolist()  # per pair, S_p at each sample
        swept_height = (heights.rate_matrix[height_of] @ cumulative.T).tolist()  # rows of -1 unused
        deviation = np.array([pair.arms for pair in checked]) @ bend  # (O, n), m
        # next_open[o][k]: the first interval at or after k left open for pair o (n if none).
        index = np.where(open_intervals, np.arange(n), n)
        next_open = np.concatenate([np.minimum.accumulate(index[:, ::-1], axis=1)[:, ::-1], np.full((len(pairs), 1), n)], axis=1).tolist()
        frontier = [float(row[0]) for row in next_open]  # in samples: every earlier instant is proven
        context = self._full
        query_object = context.GetQueryObject()  # a live view: it sees every position update
        distance = query_object.ComputeSignedDistancePairClosestPoints
        queries = 0
        while True:
            u = min(frontier)
            if u >= n:
                return CollisionReport(True, None, (), queries, min_distance)
            k, fraction = int(u), u - int(u)
            config = q[k] if fraction == 0.0 else interpolate(q[k], v[k], q[k + 1], v[k + 1], period, fraction * period)
            self.checker.UpdateContextPositions(context, config)
            due_distances = {}  # the due pairs' distances at this configuration, m
            X_now = None  # the body poses here, when a plane certificate needs them
            due = [o for o, f in enumerate(frontier) if f == u]
            for o in due:
                if queries >= budget:
                    return CollisionReport(False, u * period, (), queries, min_distance)
                pair = checked[o]
                result = distance(pair.id_A, pair.id_B)
                queries += 1
                min_distance = min(min_distance, result.distance)
                due_distances[o] = result.distance
                reach = _reach(swept[o], result.distance - self.margin - pair.slack, k, fraction)
                h = height_of[o]
                if h >= 0:  # the height certificate, if it proves more
                    geometry, top, height_slack = heights.certificate[h]
                    reach = max(reach, _reach(swept_height[o], heights.lowest(query_object, geometry) - top - self.margin - height_slack, k, fraction))
                if pair.geometry is not None and reach < k + 1:  # the witness normal's plane, if it proves more
                    if X_now is None:
                        X_now = np.ascontiguousarray(X_WB[:, :, k : k + 1]) if fraction == 0.0 else kinematics.pose_rows(config[:, None])
                    normal = result.nhat_BA_W if result.id_A == pair.id_A else -result.nhat_BA_W
                    reach = max(reach, _plane_reach(X_now, X_WB, pair.geometry, normal, deviation[o], open_intervals[o], k, fraction, self.margin))
                if reach == -math.inf:
                    return self._collision_report(u * period, [(checked[o], due_distances.get(o)) for o in due], queries, min_distance)
                # Inside an interval the frontier stays; from a sample, it skips what is clear.
                frontier[o] = reach if reach % 1.0 else float(next_open[o][int(reach)])

    def _distances(self, q: np.ndarray) -> list[tuple[int, float]]:
        """(pair, signed distance) of the checked pairs within ``influence`` at q."""
        self.checker.UpdateContextPositions(self._full, q)
        index = self._pair_index
        out = []
        for result in self._full.GetQueryObject().ComputeSignedDistancePairwiseClosestPoints(max_distance=self.influence):
            p = index.get((result.id_A.get_value(), result.id_B.get_value()))
            if p is not None:
                out.append((p, result.distance))
        return out

    def _collision_report(self, time: float, due: list[tuple[_Pair, float | None]], queries: int, min_distance: float) -> CollisionReport:
        """The report of the configuration at ``time`` s, in the query context, not provably margin
        clear for one of the ``due`` pairs (those whose frontier it is, with their distance there
        (m) if queried; every other pair is proven clear there): names those closer than
        margin + PROOF_TOLERANCE (after their slack), closest first."""
        distance = self._full.GetQueryObject().ComputeSignedDistancePairClosestPoints
        close = []
        for pair, d in due:
            if d is None:
                d = distance(pair.id_A, pair.id_B).distance
                min_distance = min(min_distance, d)
            if d - pair.slack < self.margin + PROOF_TOLERANCE:
                close.append((d, pair.name))
        return CollisionReport(False, time, tuple(name for _, name in sorted(close)), queries, min_distance)

    def _build_heights(self) -> "_Heights":
        """The height certificates of the pairs of a moving robot geometry and a static one (see
        ``_Heights``)."""
        kin, plant, inspector = self._kinematics, self.plant, self.inspector
        self.checker.UpdateContextPositions(self._full, np.asarray(self.scenario.ready_pose, dtype=float))
        query_object = self._full.GetQueryObject()
        sines = kin.vertical_sines(self._full.plant_context())
        geometries, tops, rates, slacks, pair_certificate = [], [], [], [], np.full(len(self._pairs), -1, dtype=int)
        for p, pair in enumerate(self._pairs):
            body_B = plant.GetBodyFromFrameId(inspector.GetFrameId(pair.id_B))
            if kin.upstream[int(body_B.index())] or Shape.of(inspector.GetShape(pair.id_A)) is None:
                continue  # both move (no fixed plane between them), or no closed-form lowest point
            points, radius = kin._points(pair.id_B)
            X_WB = query_object.GetPoseInWorld(pair.id_B).GetAsMatrix4() @ np.linalg.inv(inspector.GetPoseInFrame(pair.id_B).GetAsMatrix4())
            top = float(np.max(points @ X_WB[:3, :3].T[:, 2] + X_WB[2, 3])) + radius
            rate, slack = kin.height_rate(pair.id_A, sines)
            pair_certificate[p] = len(geometries)
            geometries.append(pair.id_A)
            tops.append(top)
            rates.append(rate)
            slacks.append(slack)
        return _Heights(inspector, geometries, tops, np.array(rates).reshape(-1, len(JOINT_NAMES)), slacks, pair_certificate)

    def _build_pairs(self) -> tuple[list[_Pair], dict[tuple[int, int], int]]:
        """The geometry pairs the checker tests (SceneGraph candidates not in the checker's filter
        matrix, at least one on the robot), with their distance-rate coefficients."""
        plant, inspector, kin = self.plant, self.inspector, self._kinematics
        pairs: list[_Pair] = []
        index: dict[tuple[int, int], int] = {}
        for id_A, id_B in sorted(inspector.GetCollisionCandidates(), key=lambda ids: (ids[0].get_value(), ids[1].get_value())):
            body_A, body_B = (plant.GetBodyFromFrameId(inspector.GetFrameId(g)) for g in (id_A, id_B))
            if self.checker.IsCollisionFilteredBetween(body_A, body_B):
                continue
            if not (self.checker.IsPartOfRobot(body_A) or self.checker.IsPartOfRobot(body_B)):
                continue
            if not kin.upstream[int(body_A.index())] and kin.upstream[int(body_B.index())]:
                id_A, id_B, body_A, body_B = id_B, id_A, body_B, body_A  # moving geometry first
            rate, slack = kin.pair_rate(id_A, id_B)
            name = f"{body_A.name()}/{inspector.GetName(id_A)} - {body_B.name()}/{inspector.GetName(id_B)}"
            index[(id_A.get_value(), id_B.get_value())] = index[(id_B.get_value(), id_A.get_value())] = len(pairs)
            shapes = [Shape.of(inspector.GetShape(g)) for g in (id_A, id_B)]
            geometry = None
            if None not in shapes:
                geometry = tuple(
                    item for g, body, shape in ((id_A, body_A, shapes[0]), (id_B, body_B, shapes[1]))
                    for item in (int(body.index()), inspector.GetPoseInFrame(g).GetAsMatrix34(), np.array([*shape.half, shape.radius, shape.rounding]))
                )
            pairs.append(_Pair(name, rate, slack, id_A, id_B, kin.lever_arms(id_A) + kin.lever_arms(id_B), geometry))
        return pairs, index

    def _gate(self, p: int) -> _Gate | None:
        """Where in the box pair p may come closer than margin + PROOF_TOLERANCE, by branch and
        bound on the joints its distance depends on (None if more than GATE_MAX_JOINTS, or the
        map takes more than GATE_MAX_QUERIES evaluations). Over a cell with centre c and
        half-widths w the distance lies within sum_j c_j w_j + slack of d(c) (the rate
        coefficients c_j bound its Lipschitz constant; slack covers the joints dropped by
        symmetry, held at the ready pose): cells proven clear are dropped, cells proven or not
        provably clear (at GATE_RESOLUTION) are kept as the gate's bad boxes."""
        pair = self._pairs[p]
        joints = np.flatnonzero(pair.rate)
        if len(joints) > GATE_MAX_JOINTS:
            return None
        if not len(joints):  # a constant distance: certified or never gated
            self.checker.UpdateContextPositions(self._full, np.asarray(self.scenario.ready_pose, dtype=float))
            d = self._full.GetQueryObject().ComputeSignedDistancePairClosestPoints(pair.id_A, pair.id_B).distance
            ok = d >= self.margin + PROOF_TOLERANCE + pair.slack
            return _Gate(p, joints, joints.astype(float), joints.astype(float), np.zeros(()), 0) if ok else None
        rate = pair.rate[joints]
        q = np.clip(np.asarray(self.scenario.ready_pose, dtype=float), self.box_lower, self.box_upper)
        required = self.margin + PROOF_TOLERANCE + pair.slack
        cells = [(self.box_lower[joints], self.box_upper[joints])]
        bad = []
        for _ in range(GATE_MAX_QUERIES):
            if not cells:
                return _Gate.from_boxes(p, joints, self.box_lower[joints], self.box_upper[joints], bad)
            lower, upper = cells.pop()
            centre, half = 0.5 * (lower + upper), 0.5 * (upper - lower)
            q[joints] = centre
            self.checker.UpdateContextPositions(self._full, q)
            d = self._full.GetQueryObject().ComputeSignedDistancePairClosestPoints(pair.id_A, pair.id_B).distance
            spread = float(rate @ half)
            if d - spread >= required:
                continue  # clear everywhere in the cell
            if d + spread < required or spread <= GATE_RESOLUTION[len(joints) - 1]:
                bad.append((lower, upper))  # close everywhere in it, or not worth splitting
                continue
            split = int(np.argmax(rate * half))  # halve the cell along its most uncertain joint
            left_upper, right_lower = upper.copy(), lower.copy()
            left_upper[split] = right_lower[split] = centre[split]
            cells += [(lower, left_upper), (right_lower, upper)]
        return None


def _reach(swept: list[float], budget: float, k: int, fraction: float) -> float:
    """How far (in samples) a distance budget (m) proven at sample k + fraction carries along the
    cumulative swept bound ``swept`` (n + 1 values): strictly inside interval k if the budget runs
    out there, else the furthest sample reached; -inf if the budget is below PROOF_TOLERANCE."""
    if not budget >= PROOF_TOLERANCE:  # (NaN included)
        return -math.inf
    interval = swept[k + 1] - swept[k]
    ahead = (1.0 - fraction) * interval
    if ahead > budget:
        return k + fraction + budget / interval  # budget / the pair's rate bound, in samples
    return float(bisect.bisect_right(swept, swept[k + 1] + budget - ahead) - 1)


@numba.njit(cache=True)
def _plane_reach(X_now, X_WB, geometry, normal, deviation, open_intervals, k, fraction, margin):
    """How far (in samples) the plane certificate proves a pair at least ``margin`` (m) clear from
    sample k + fraction (module doc): its gap along the unit ``normal`` (from B to A) at the
    frontier (body poses X_now (num_bodies, 12, 1)) and at the following samples (X_WB), blended
    linearly across each interval less the interval's ``deviation`` (m), over the pair's run of
    open intervals; up to where the blend meets the margin, or to the end of the run. -inf if it
    starts below PROOF_TOLERANCE. geometry: ``_Pair.geometry``."""
    n = open_intervals.shape[0]
    unit = normal / math.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)
    if not (math.isfinite(unit[0]) and math.isfinite(unit[1]) and math.isfinite(unit[2])):
        return -np.inf  # no witness normal (touching)
    previous = _plane_gap(X_now, 0, geometry, unit) - margin
    scale = (1.0 - fraction) ** 2  # the first interval is only the rest of interval k
    start = k + fraction
    i = k
    while i < n and (i == k or open_intervals[i]):
        at_start = previous - scale * deviation[i]
        if at_start < PROOF_TOLERANCE:
            return -np.inf if i == k else float(i)
        following = _plane_gap(X_WB, i + 1, geometry, unit) - margin
        at_end = following - scale * deviation[i]
        if at_end < 0.0:
            return start + (i + 1 - start) * at_start / (at_start - at_end)
        previous, scale, start, i = following, 1.0, float(i + 1), i + 1
    return float(i)


@numba.njit(cache=True)
def _plane_gap(X_WB, s, geometry, normal):
    """The gap (m) between a pair's geometries along the unit ``normal`` (from B to A) at sample s
    of the body poses X_WB (num_bodies, 12, S): min over A of n . x less max over B of n . x, from
    their poses and closed-form supports (``robot.bounds.Shape.support``)."""
    body_A, X_BG_A, shape_A, body_B, X_BG_B, shape_B = geometry
    return _support_gap(X_WB, s, body_A, X_BG_A, shape_A, normal, 1.0) + _support_gap(X_WB, s, body_B, X_BG_B, shape_B, normal, -1.0)


@numba.njit(cache=True)
def _support_gap(X_WB, s, body, X_BG, shape, normal, sign):
    """sign n . p_WG less the shape's support along n: for sign 1 the smallest n . x over the
    geometry, for sign -1 minus the largest (shapes are symmetric about G's origin)."""
    # n in the body's frame, then in G's.
    m0 = X_WB[body, 0, s] * normal[0] + X_WB[body, 4, s] * normal[1] + X_WB[body, 8, s] * normal[2]
    m1 = X_WB[body, 1, s] * normal[0] + X_WB[body, 5, s] * normal[1] + X_WB[body, 9, s] * normal[2]
    m2 = X_WB[body, 2, s] * normal[0] + X_WB[body, 6, s] * normal[1] + X_WB[body, 10, s] * normal[2]
    u0 = abs(X_BG[0, 0] * m0 + X_BG[1, 0] * m1 + X_BG[2, 0] * m2)
    u1 = abs(X_BG[0, 1] * m0 + X_BG[1, 1] * m1 + X_BG[2, 1] * m2)
    u2 = abs(X_BG[0, 2] * m0 + X_BG[1, 2] * m1 + X_BG[2, 2] * m2)
    support = u0 * shape[0] + u1 * shape[1] + u2 * shape[2] + shape[3] * math.sqrt(max(0.0, 1.0 - u2 * u2)) + shape[4]
    # n . p_WG, with p_WG = p_WB + R_WB p_BG.
    along = normal[0] * X_WB[body, 3, s] + normal[1] * X_WB[body, 7, s] + normal[2] * X_WB[body, 11, s]
    along += m0 * X_BG[0, 3] + m1 * X_BG[1, 3] + m2 * X_BG[2, 3]
    return sign * along - support


class _Heights:
    """Height certificates for the pairs of a moving robot geometry A and a static geometry B
    (the court, the robot's base): every point of B lies at or below B's top z_B, so the pair's
    distance is at least A's lowest point's height z_A minus z_B. z_A falls at most at
    sum_j |qdot_j| c_j sin(theta_j): a joint whose axis is fixed in the world (all joints above it
    prismatic) moves points vertically at sin(theta_j) of its full rate, theta_j its axis's angle
    from vertical (revolute; 0 for the shoulder's yaw) or from horizontal (prismatic; 0 for the
    gantry's carriages); ``_Kinematics.height_rate``. Over a table the robot mostly sweeps
    sideways, and this certificate proves much longer steps than the distance's.

    certificate[h] = (A's geometry id, z_B (m), slack (m)); rate_matrix (H, 8); pair_certificate
    (P,) the certificate of each pair, or -1."""

    def __init__(self, inspector, geometries, tops, rate_matrix, slacks, pair_certificate):
        self.certificate = [(g, top, slack) for g, top, slack in zip(geometries, tops, slacks)]
        self.rate_matrix = rate_matrix
        self.pair_certificate = pair_certificate.tolist()
        self._shapes = {g: (tuple((shape := Shape.of(inspector.GetShape(g))).half.tolist()), shape.radius, shape.rounding) for g in set(geometries)}

    def lowest(self, query_object, geometry) -> float:
        """z (m) of the geometry's lowest point in the query's configuration (``Shape.lowest``,
        in scalars: one pose)."""
        u0, u1, u2, z = query_object.GetPoseInWorld(geometry).GetAsMatrix34()[2].tolist()
        (h0, h1, h2), radius, rounding = self._shapes[geometry]
        u0, u1, u2 = abs(u0), abs(u1), abs(u2)
        return z - (u0 * h0 + u1 * h1 + u2 * h2 + radius * math.sqrt(max(0.0, 1.0 - u2 * u2)) + rounding)


@dataclasses.dataclass(frozen=True)
class _Gate:
    """Where a pair whose distance depends only on ``joints`` (J,) may come within margin inside
    the checker's box: the bad boxes, rasterised on a grid of ``width`` (J,) cells from
    ``origin`` (J,) and stored as a summed-area table ``counts`` (shape + 1) for box queries.
    ``bad`` counts the bad cells (0: the pair is certified clear)."""

    pair: int
    joints: np.ndarray
    origin: np.ndarray
    width: np.ndarray
    counts: np.ndarray
    bad: int

    def __post_init__(self):
        for array in (self.joints, self.origin, self.width, self.counts):  # shared by the checkers of one model
            array.setflags(write=False)
        # box_touches' per-joint (joint, origin, width, table size) as plain Python numbers, read once
        object.__setattr__(self, "_axes", tuple(zip(self.joints.tolist(), self.origin.tolist(), self.width.tolist(), self.counts.shape)))

    @staticmethod
    def from_boxes(pair: int, joints: np.ndarray, lower: np.ndarray, upper: np.ndarray, boxes: list) -> "_Gate":
        """The gate of the bad ``boxes`` [(lower, upper)] (cells of the bisection of the box
        [lower, upper], so on the grid of the smallest of them)."""
        if not boxes:
            return _Gate(pair, joints, lower, upper - lower, np.zeros((2,) * len(joints), dtype=np.int64), 0)
        width = np.min([hi - lo for lo, hi in boxes], axis=0)
        shape = np.maximum(np.round((upper - lower) / width).astype(int), 1)
        grid = np.zeros(shape, dtype=bool)
        for lo, hi in boxes:
            i0 = np.round((lo - lower) / width).astype(int)
            i1 = np.round((hi - lower) / width).astype(int)
            grid[tuple(slice(a, b) for a, b in zip(i0, i1))] = True
        counts = np.zeros(shape + 1, dtype=np.int64)
        summed = grid.astype(np.int64)
        for axis in range(len(joints)):
            summed = np.cumsum(summed, axis=axis)
        counts[(slice(1, None),) * len(joints)] = summed
        return _Gate(pair, joints, lower, width, counts, int(grid.sum()))

    def touched(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """Which of the boxes [lower, upper] (8, n), inside the gate's box, meet a bad cell (n,)
        bool (closed cells: touching counts)."""
        last = (np.array(self.counts.shape) - 2)[:, None]
        origin, width = self.origin[:, None], self.width[:, None]
        i0 = np.clip(np.floor((lower[self.joints] - origin) / width).astype(int), 0, last)
        i1 = np.clip(np.floor((upper[self.joints] - origin) / width).astype(int), 0, last) + 1
        c = self.counts
        if len(self.joints) == 1:
            inside = c[i1[0]] - c[i0[0]]
        else:
            inside = c[i1[0], i1[1]] - c[i0[0], i1[1]] - c[i1[0], i0[1]] + c[i0[0], i0[1]]
        return inside > 0

    def box_touches(self, lower: list[float], upper: list[float]) -> bool:
        """``touched`` for one box [lower, upper] (8,), in plain Python (fast)."""
        index = []
        for j, origin, width, size in self._axes:
            i0 = min(max(math.floor((lower[j] - origin) / width), 0), size - 2)
            i1 = min(max(math.floor((upper[j] - origin) / width), 0), size - 2) + 1
            index.append((i0, i1))
        c = self.counts
        if len(index) == 1:
            (i0, i1), = index
            return bool(c[i1] - c[i0] > 0)
        (a0, a1), (b0, b1) = index
        return bool(c[a1, b1] - c[a0, b1] - c[a1, b0] + c[a0, b0] > 0)


# ---------------------------------------------------------------------------------- motion
def interpolate(q0: np.ndarray, v0: np.ndarray, q1: np.ndarray, v1: np.ndarray, period: float, t: float) -> np.ndarray:
    """The cubic Hermite interpolant of (q0, v0) at 0 and (q1, v1) at ``period`` (s), at time t."""
    s = t / period
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * q0 + (s3 - 2 * s2 + s) * period * v0 + (3 * s2 - 2 * s3) * q1 + (s3 - s2) * period * v1


@numba.njit(cache=True)
def _speed_bound(q0, q1, v0, v1, a0, a1, period):
    """A bound on |qdot| over an interval (``joint_speed_bounds``)."""
    # max(|v_k|, |v_k+1|) + max(|a_k|, |a_k+1|) * period / 4 is at least the end-point Bernstein terms.
    linear = max(abs(v0), abs(v1)) + max(abs(a0), abs(a1)) * (period / 4.0)
    middle = abs((q1 - q0) * (3.0 / period) - v0 - v1)
    return max(middle, linear)


@numba.njit(cache=True)
def _acceleration_bound(q0, q1, v0, v1, a0, a1, period):
    """A bound on |qddot| over an interval (``joint_acceleration_bounds``)."""
    rise = (q1 - q0) * (6.0 / (period * period))
    start = rise - (4.0 * v0 + 2.0 * v1) / period
    end = (2.0 * v0 + 4.0 * v1) / period - rise
    return max(abs(start), abs(end), abs(a0), abs(a1))


@numba.njit(cache=True)
def joint_speed_bounds(q: np.ndarray, v: np.ndarray, a: np.ndarray, period: float) -> np.ndarray:
    """Per interval and joint (n, 8), a bound on |qdot| over [t_k, t_{k+1}] for the Hermite
    interpolant of the samples (largest Bernstein coefficient of its quadratic velocity), and for
    motion with linear acceleration between the sampled a (max |v| + max |a| * period / 4)."""
    out = np.empty((q.shape[0] - 1, q.shape[1]))
    for k in range(q.shape[0] - 1):
        for j in range(q.shape[1]):
            out[k, j] = _speed_bound(q[k, j], q[k + 1, j], v[k, j], v[k + 1, j], a[k, j], a[k + 1, j], period)
    return out


@numba.njit(cache=True)
def joint_acceleration_bounds(q: np.ndarray, v: np.ndarray, a: np.ndarray, period: float) -> np.ndarray:
    """Per interval and joint (n, 8), a bound on |qddot| over [t_k, t_{k+1}] for the Hermite
    interpolant of the samples (its acceleration is linear in time: the larger of its values at
    the ends), and for motion with linear acceleration between the sampled a."""
    out = np.empty((q.shape[0] - 1, q.shape[1]))
    for k in range(q.shape[0] - 1):
        for j in range(q.shape[1]):
            out[k, j] = _acceleration_bound(q[k, j], q[k + 1, j], v[k, j], v[k + 1, j], a[k, j], a[k + 1, j], period)
    return out


@numba.njit(cache=True)
def _motion_bounds(q, v, a, period, upstream):
    """For samples q, v, a (n + 1, 8): the cumulative travel bound of each joint at each sample
    (n + 1, 8), and per joint and interval, joints by intervals (8, n): how far the joint strays
    from the chord between its samples, h^2 / 8 A, and the deviation terms of the robot's points,
    h^2 / 8 (A + V (V + 4 U)) (module doc of robot.bounds; V, A: ``joint_speed_bounds``,
    ``joint_acceleration_bounds``; U_j: the sum of V over the joints upstream of j, upstream
    (8, 8) [i, j] = 1 if i is)."""
    n, joints = q.shape[0] - 1, q.shape[1]
    cumulative, sag, bend = np.zeros((n + 1, joints)), np.empty((joints, n)), np.empty((joints, n))
    speed = np.empty(joints)
    scale = period * period / 8.0
    for k in range(n):
        for j in range(joints):
            speed[j] = _speed_bound(q[k, j], q[k + 1, j], v[k, j], v[k + 1, j], a[k, j], a[k + 1, j], period)
            cumulative[k + 1, j] = cumulative[k, j] + period * speed[j]
            sag[j, k] = scale * _acceleration_bound(q[k, j], q[k + 1, j], v[k, j], v[k + 1, j], a[k, j], a[k + 1, j], period)
        for j in range(joints):
            above = 0.0
            for i in range(joints):
                above += upstream[i, j] * speed[i]
            bend[j, k] = sag[j, k] + scale * speed[j] * (speed[j] + 4.0 * above)
    return cumulative, sag, bend


@numba.njit(cache=True)
def _joint_ranges(q, sag):
    """The range [low, high] (8,) each of every joint over a motion: the smallest of
    min(q_k, q_k+1) - sag_k and the largest of max(q_k, q_k+1) + sag_k over its intervals k, for
    samples q (8, n + 1) and the joints' deviations from their chords sag (8, n). NaN if any
    term is NaN (as NumPy's min and max reductions)."""
    joints, n = sag.shape
    low, high = np.empty(joints), np.empty(joints)
    for j in range(joints):
        smallest, largest = np.inf, -np.inf
        for k in range(n):
            a, b = q[j, k], q[j, k + 1]
            below = (a if a < b else b) - sag[j, k]  # q is finite (checked): min and max are exact
            above = (b if a < b else a) + sag[j, k]
            if below < smallest or below != below:
                smallest = below if smallest == smallest else smallest
            if above > largest or above != above:
                largest = above if largest == largest else largest
        low[j], high[j] = smallest, largest
    return low, high


def _trajectory_arrays(trajectory: JointTrajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    if not isinstance(trajectory, JointTrajectory):
        raise ValueError(f"check: expected a JointTrajectory, got {type(trajectory).__name__}")
    period = float(trajectory.period)
    if not (math.isfinite(period) and period > 0.0):
        raise ValueError(f"check: trajectory period must be a finite time > 0 (s), got {trajectory.period}")
    arrays = [np.asarray(x, dtype=float) for x in (trajectory.q, trajectory.v, trajectory.a)]
    if not math.isfinite(sum(float(x.sum()) for x in arrays)):  # fast path; finds NaN and inf
        for name, x in zip("qva", arrays):
            if not np.all(np.isfinite(x)):
                rows = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
                raise ValueError(f"check: trajectory {name} has non-finite values at samples {rows[:5].tolist()}")
    return arrays[0], arrays[1], arrays[2], period


# ---------------------------------------------------------------------------------- geometry
class _Kinematics:
    """The plant's kinematic tree and the geometry radii behind the speed bounds (module doc)."""

    def __init__(self, plant, inspector):
        self.plant, self.inspector = plant, inspector
        n_bodies = plant.num_bodies()
        self.inboard = [None] * n_bodies  # the joint whose child is each body
        for joint_index in plant.GetJointIndices():
            joint = plant.get_joint(joint_index)
            kind = joint.type_name()
            if kind not in ("revolute", "prismatic", "weld"):
                raise ValueError(f"robot collision: unsupported joint type {kind!r} ({joint.name()}); expected revolute, prismatic or weld")
            self.inboard[int(joint.child_body().index())] = joint
        # upstream[b]: the moving joints from body b up to the world, nearest first.
        self.upstream = []
        for b in range(n_bodies):
            chain, body = [], b
            while self.inboard[body] is not None:
                joint = self.inboard[body]
                if joint.type_name() != "weld":
                    chain.append(joint)
                body = int(joint.parent_body().index())
            self.upstream.append(chain)
        self.velocity_index = {int(j.index()): j.velocity_start() for b in self.upstream for j in b}

    # -- geometry extremes
    def _points(self, geometry_id) -> tuple[np.ndarray, float]:
        """Points (k, 3) in the body frame and a radius: the geometry lies within ``radius`` of
        their convex hull, and the farthest points of it from any point or line are within the
        returned bound (cylinders: rim samples, radius the Lipschitz pad)."""
        shape = self.inspector.GetShape(geometry_id)
        X_BG: RigidTransform = self.inspector.GetPoseInFrame(geometry_id)
        if isinstance(shape, Box):
            half = 0.5 * np.array([shape.width(), shape.depth(), shape.height()])
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
            return (X_BG.rotation().matrix() @ corners.T).T + X_BG.translation(), 0.0
        if isinstance(shape, Sphere):
            return X_BG.translation()[None, :], shape.radius()
        if isinstance(shape, Capsule):
            ends = np.array([[0, 0, -0.5 * shape.length()], [0, 0, 0.5 * shape.length()]])
            return (X_BG.rotation().matrix() @ ends.T).T + X_BG.translation(), shape.radius()
        if isinstance(shape, Cylinder):
            theta = np.linspace(0.0, 2 * np.pi, _RIM_SAMPLES, endpoint=False)
            r, h = shape.radius(), 0.5 * shape.length()
            rim = np.array([[r * np.cos(t), r * np.sin(t), z] for z in (-h, h) for t in theta])
            # Between rim samples a point is within r * pi / N of one (arc), so pad by that.
            return (X_BG.rotation().matrix() @ rim.T).T + X_BG.translation(), r * np.pi / _RIM_SAMPLES
        if isinstance(shape, Ellipsoid):
            return X_BG.translation()[None, :], max(shape.a(), shape.b(), shape.c())
        raise ValueError(f"robot collision: unsupported collision shape {type(shape).__name__} ({self.inspector.GetName(geometry_id)})")

    def _farthest(self, geometry_id, origin: np.ndarray, axis: np.ndarray | None = None) -> float:
        """An upper bound (m) on the distance of the geometry's points (body frame) from ``origin``,
        or, given a unit ``axis``, from the line through origin along it."""
        points, radius = self._points(geometry_id)
        d = points - origin
        if axis is not None:
            d = d - np.outer(d @ axis, axis)
        return float(np.max(np.linalg.norm(d, axis=1)) + radius)

    def symmetry_error(self, geometry_id, origin: np.ndarray, axis: np.ndarray) -> float:
        """How far (m) the geometry is from being symmetric about the line (body frame): a rigid
        motion moving no point further than this maps it onto a shape of revolution about the
        line; inf if it is not a sphere, capsule or cylinder."""
        shape = self.inspector.GetShape(geometry_id)
        X_BG = self.inspector.GetPoseInFrame(geometry_id)
        offset = X_BG.translation() - origin
        off_axis = float(np.linalg.norm(offset - (offset @ axis) * axis))
        if isinstance(shape, Sphere):
            return off_axis
        if isinstance(shape, (Capsule, Cylinder)):
            z = X_BG.rotation().matrix()[:, 2]
            tilt = math.acos(min(1.0, abs(float(z @ axis))))
            extent = 0.5 * shape.length() + shape.radius()  # farthest point from the centre, at most
            return off_axis + tilt * extent
        return math.inf

    # -- joint frames
    @staticmethod
    def _axis(joint) -> np.ndarray:
        axis = joint.revolute_axis() if joint.type_name() == "revolute" else joint.translation_axis()
        return np.asarray(axis, dtype=float) / np.linalg.norm(axis)

    def _origin_in_child(self, joint) -> np.ndarray:
        """Joint origin (its child frame M's origin) in the child body's frame."""
        return joint.frame_on_child().GetFixedPoseInBodyFrame().translation()

    def _origins_in_parent(self, joint) -> np.ndarray:
        """Where the joint origin can be in the parent body's frame (k, 3): revolute (M's origin
        is F's, on the axis), weld (fixed), prismatic (its travel's two ends; the distance from a
        point or a line is convex along it)."""
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame()
        kind = joint.type_name()
        if kind == "revolute":
            return X_PF.translation()[None, :]
        if kind == "weld":
            return X_PF.multiply(joint.X_FM()).translation()[None, :]
        lower, upper = joint.position_lower_limits()[0], joint.position_upper_limits()[0]
        if not (math.isfinite(lower) and math.isfinite(upper)):
            raise ValueError(f"robot collision: prismatic joint {joint.name()} below a revolute joint needs finite position limits")
        axis = X_PF.rotation().matrix() @ self._axis(joint)
        return np.array([X_PF.translation() + lower * axis, X_PF.translation() + upper * axis])

    def _axis_line_in_child(self, joint) -> tuple[np.ndarray, np.ndarray]:
        X_CM = joint.frame_on_child().GetFixedPoseInBodyFrame()
        return X_CM.translation(), X_CM.rotation().matrix() @ self._axis(joint)

    def _axis_line_in_parent(self, joint) -> tuple[np.ndarray, np.ndarray]:
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame()
        return X_PF.translation(), X_PF.rotation().matrix() @ self._axis(joint)

    # -- radii
    def axis_radius(self, joint, geometry_id) -> float:
        """rho_j(g): a bound (m) on the distance of geometry g's points from revolute joint j's
        axis over all configurations (1 for a prismatic joint); g's body must be downstream of j."""
        if joint.type_name() == "prismatic":
            return 1.0
        body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(geometry_id)).index())
        child = int(joint.child_body().index())
        # The bodies from j's child down to g's body, through their inboard joints.
        path, b = [], body
        while b != child:
            path.append(self.inboard[b])
            if path[-1] is None:
                raise ValueError(f"robot collision: geometry {self.inspector.GetName(geometry_id)} is not downstream of joint {joint.name()}")
            b = int(path[-1].parent_body().index())
        path.reverse()  # joints from j's child body down to g's body
        origin, axis = self._axis_line_in_child(joint)
        if not path:
            return self._farthest(geometry_id, origin, axis)
        # Distance from j's axis of the first joint origin (fixed on j's child body, up to travel).
        first = path[0]
        offsets = self._origins_in_parent(first) - origin
        total = float(np.max(np.linalg.norm(offsets - np.outer(offsets @ axis, axis), axis=1)))
        # Then from each joint's origin to the next one's, on the body between them.
        for inner, outer in zip(path[:-1], path[1:]):
            total += float(np.max(np.linalg.norm(self._origins_in_parent(outer) - self._origin_in_child(inner), axis=1)))
        return total + self._farthest(geometry_id, self._origin_in_child(path[-1]))

    def lever_arms(self, geometry_id) -> np.ndarray:
        """rho (8,): every point of the geometry moves at most at sum_j |qdot_j| rho_j m/s
        (``axis_radius`` for the joints upstream of its body, 0 for the others)."""
        body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(geometry_id)).index())
        arms = np.zeros(len(JOINT_NAMES))
        for joint in self.upstream[body]:
            arms[self.velocity_index[int(joint.index())]] = self.axis_radius(joint, geometry_id)
        return arms

    def upstream_matrix(self) -> np.ndarray:
        """(8, 8): entry [i, j] is 1 if joint i is upstream of joint j (moves j's parent body)."""
        upstream = np.zeros((len(JOINT_NAMES), len(JOINT_NAMES)))
        for joints in self.upstream:
            if joints:  # the body's inboard joint, then the joints above it
                j = self.velocity_index[int(joints[0].index())]
                for joint in joints[1:]:
                    upstream[self.velocity_index[int(joint.index())], j] = 1.0
        return upstream

    def robot_geometries(self) -> list:
        """Collision geometries on bodies moved by a joint."""
        out = []
        for b in range(self.plant.num_bodies()):
            if self.upstream[b]:
                out.extend(self.plant.GetCollisionGeometriesForBody(self.plant.get_body(BodyIndex(b))))
        return out

    def speed_radii(self) -> np.ndarray:
        """r (8,): max over robot geometries downstream of each joint of rho_j (module doc)."""
        r = np.zeros(len(JOINT_NAMES))
        for g in self.robot_geometries():
            body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(g)).index())
            for joint in self.upstream[body]:
                i = self.velocity_index[int(joint.index())]
                r[i] = max(r[i], self.axis_radius(joint, g))
        return r

    def vertical_sines(self, plant_context) -> np.ndarray:
        """(8,) per joint: 1, or for a joint whose axis is fixed in the world (every moving joint
        above it prismatic) the fraction of its motion that can be vertical, sin of the axis's
        angle from vertical (revolute) or |axis_z| (prismatic)."""
        sines = np.ones(len(JOINT_NAMES))
        world = self.plant.world_frame()
        for joint_index in self.plant.GetJointIndices():
            joint = self.plant.get_joint(joint_index)
            if joint.type_name() not in ("revolute", "prismatic"):
                continue
            above = self.upstream[int(joint.parent_body().index())]
            if any(j.type_name() != "prismatic" for j in above):
                continue
            R_WF = self.plant.CalcRelativeTransform(plant_context, world, joint.frame_on_parent()).rotation().matrix()
            axis = R_WF @ self._axis(joint)
            vertical = abs(float(axis[2]))
            sine = math.sqrt(max(0.0, 1.0 - vertical * vertical)) if joint.type_name() == "revolute" else vertical
            sines[self.velocity_index[int(joint.index())]] = min(1.0, sine + 1e-12)
        return sines

    def height_rate(self, geometry_id, sines: np.ndarray) -> tuple[np.ndarray, float]:
        """The rate coefficients c (8,) of the height of the geometry's lowest point (it changes at
        most at c . |qdot| m/s) and its symmetry slack (m): each joint above the geometry at its
        axis radius times its vertical sine, except a revolute joint about whose axis the
        geometry, on its child body, is symmetric (turning it maps the shape onto itself)."""
        body = int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(geometry_id)).index())
        rate = np.zeros(len(JOINT_NAMES))
        eps = 0.0
        for joint in self.upstream[body]:
            i = self.velocity_index[int(joint.index())]
            if joint.type_name() == "revolute" and body == int(joint.child_body().index()):
                error = self.symmetry_error(geometry_id, *self._axis_line_in_child(joint))
                if error <= SYMMETRY_TOLERANCE:
                    eps += error
                    continue
            rate[i] = self.axis_radius(joint, geometry_id) * sines[i]
        return np.where(rate > 0, rate + eps, 0.0), 2.0 * eps

    def pair_rate(self, id_A, id_B) -> tuple[np.ndarray, float]:
        """The distance-rate coefficients c (8,) of a geometry pair and its symmetry slack (m)."""
        bodies = [int(self.plant.GetBodyFromFrameId(self.inspector.GetFrameId(g)).index()) for g in (id_A, id_B)]
        upstream = [{int(j.index()) for j in self.upstream[b]} for b in bodies]
        rate = np.zeros(len(JOINT_NAMES))
        errors = []
        used = set()  # a geometry made symmetric about one axis cannot also be about another
        for side, (g, other_g) in enumerate(((id_A, id_B), (id_B, id_A))):
            for joint in self.upstream[bodies[side]]:
                if int(joint.index()) in upstream[1 - side]:
                    continue  # upstream of both: moves the pair rigidly
                candidates = []
                if joint.type_name() == "revolute":
                    # This joint turns g's side; g symmetric about its axis on its child body, or
                    # other_g on its parent body, makes the pair's distance independent of it.
                    if bodies[side] == int(joint.child_body().index()) and g not in used:
                        candidates.append((self.symmetry_error(g, *self._axis_line_in_child(joint)), g))
                    if bodies[1 - side] == int(joint.parent_body().index()) and other_g not in used:
                        candidates.append((self.symmetry_error(other_g, *self._axis_line_in_parent(joint)), other_g))
                error, geometry = min(candidates, default=(math.inf, None), key=lambda item: item[0])
                if error <= SYMMETRY_TOLERANCE:
                    errors.append(error)
                    used.add(geometry)
                    continue
                rate[self.velocity_index[int(joint.index())]] = self.axis_radius(joint, g)
        eps = sum(errors)
        # Replacing near-symmetric shapes by exact ones moves their points by <= eps: distance
        # budget 2 eps, and radii up to eps larger. And the computed distance may be off by
        # DISTANCE_ERROR.
        return np.where(rate > 0, rate + eps, 0.0), 2.0 * eps + DISTANCE_ERROR
