"""The broad phase's geometry: forward kinematics against Drake's, sin and cos, sphere covers that
contain their shapes, swept-box bounds that never exceed Drake's distances (at the samples and
between them), and the deviation bound behind them."""

import numba
import numpy as np
import pytest
from pydrake.geometry import Box, Capsule, Cylinder, Sphere
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.tree import BodyIndex

from ace_drake.control.params import ControlParams
from ace_drake.robot.bounds import Shape, sin_cos, sphere_cover
from ace_drake.robot.collision import DISTANCE_ERROR, TrajectoryCollisionChecker, _motion_bounds

MARGIN = ControlParams().collision_margin
PERIOD = 0.001


@pytest.fixture(scope="module")
def dut():
    return TrajectoryCollisionChecker(margin=MARGIN)


def random_configurations(dut, count, rng, outside=0.3):
    """Configurations uniform over the joint limits widened by ``outside`` (rad or m)."""
    lower, upper = dut.plant.GetPositionLowerLimits() - outside, dut.plant.GetPositionUpperLimits() + outside
    return rng.uniform(lower, upper, (count, 8))


def poses(kinematics, q):
    """X_WB (S, bodies, 3, 4) at configurations q (S, 8)."""
    rows = kinematics.pose_rows(np.ascontiguousarray(q.T))
    return rows.transpose(2, 0, 1).reshape(len(q), -1, 3, 4)


def shape_points(shape, rng, count):
    """Points (count, 3) in a Drake shape's frame: half on its surface, half inside."""
    half = count // 2
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    depth = np.concatenate([np.ones(half), rng.random(count - half) ** (1 / 3)])[:, None]
    if isinstance(shape, Sphere):
        return shape.radius() * direction * depth
    if isinstance(shape, Capsule):
        z = rng.uniform(-0.5, 0.5, (count, 1)) * shape.length()
        return np.column_stack([np.zeros((count, 2)), z]) + shape.radius() * direction * depth
    if isinstance(shape, Cylinder):
        angle = rng.uniform(0, 2 * np.pi, count)
        radius = shape.radius() * np.sqrt(rng.random(count))
        radius[:half] = shape.radius()  # the rim and the side
        z = rng.uniform(-0.5, 0.5, count) * shape.length()
        z[: half // 2] = np.sign(z[: half // 2]) * 0.5 * shape.length()  # the rims
        return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), z])
    assert isinstance(shape, Box)
    half = 0.5 * np.array([shape.width(), shape.depth(), shape.height()])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    return np.vstack([corners, rng.uniform(-1, 1, (count - 8, 3)) * half])


# ---------------------------------------------------------------------------------- kinematics
def test_forward_kinematics_matches_drake(dut):
    plant = dut.plant
    context = plant.CreateDefaultContext()
    rng = np.random.default_rng(0)
    kinematics = dut._bounds.kinematics
    q = random_configurations(dut, 300, rng, outside=3.0)  # well outside the limits too
    X_WB = poses(kinematics, q)
    assert X_WB.shape == (300, plant.num_bodies(), 3, 4)
    worst = 0.0
    for s in range(len(q)):
        plant.SetPositions(context, q[s])
        for b in range(plant.num_bodies()):
            expected = plant.EvalBodyPoseInWorld(context, plant.get_body(BodyIndex(b))).GetAsMatrix34()
            worst = max(worst, float(np.max(np.abs(X_WB[s, b] - expected))))
    assert worst < 1e-9


@numba.njit
def _sin_cos_of(x, out):
    for i in range(x.shape[0]):
        out[i, 0], out[i, 1] = sin_cos(x[i])


def test_sin_cos_matches_libm():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-4, 4, 200_000), rng.uniform(-1e5, 1e5, 200_000), np.arange(-64, 65) * np.pi / 4, [0.0, -0.0, 1e-300]])
    out = np.empty((len(x), 2))
    _sin_cos_of(x, out)
    assert np.max(np.abs(out[:, 0] - np.sin(x))) <= 2.3e-16
    assert np.max(np.abs(out[:, 1] - np.cos(x))) <= 2.3e-16


# ---------------------------------------------------------------------------------- shapes
# Shapes, and how far (m) their covers may reach beyond them: the capsules to the cover's target,
# the racket's thin blade (radius 7.5 cm, 14 mm thick) to 1.5 cm with its 45 spheres.
COVERED = [
    (Sphere(0.045), 1e-12), (Capsule(0.05, 0.55), 0.003), (Capsule(0.02, 0.03), 0.003), (Capsule(0.1, 0.001), 0.003),
    (Cylinder(0.075, 0.014), 0.015), (Cylinder(0.08, 0.2), 0.035), (Cylinder(0.01, 0.3), 0.01),
]


@pytest.mark.parametrize("shape, reach", COVERED)
def test_sphere_covers_contain_their_shapes(shape, reach):
    rng = np.random.default_rng(2)
    centres, radii = sphere_cover(shape)
    points = shape_points(shape, rng, 20_000)
    inside = np.linalg.norm(points[:, None, :] - centres[None], axis=2) <= radii[None] + 1e-12
    assert inside.any(axis=1).all()
    # And not loose: no sphere reaches further than ``reach`` beyond the shape.
    direction = rng.normal(size=(200, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    surfaces = (centres[:, None] + radii[:, None, None] * direction[None]).reshape(-1, 3)
    assert np.max(Shape.of(shape).distance(surfaces)) <= reach


@pytest.mark.parametrize("shape", [Box(0.3, 0.1, 0.05), Sphere(0.045), Capsule(0.05, 0.55), Cylinder(0.075, 0.014)])
def test_shape_support_lowest_point_and_distance(shape):
    rng = np.random.default_rng(3)
    extent = Shape.of(shape)
    points = shape_points(shape, rng, 20_000)
    directions = rng.normal(size=(50, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    sampled = np.max(points @ directions.T, axis=0)
    support = extent.support(directions)
    assert np.all(sampled <= support + 1e-12) and np.all(support - sampled < 0.02)  # and about tight
    X_WG = RigidTransform(RollPitchYaw(rng.uniform(-3, 3, 3)), rng.normal(size=3)).GetAsMatrix34()
    assert extent.lowest(X_WG) <= np.min(points @ X_WG[:, :3].T + X_WG[:, 3], axis=0)[2] + 1e-12
    outside = rng.normal(size=(200, 3)) * 0.3
    nearest = np.min(np.linalg.norm(outside[:, None] - points[None], axis=2), axis=1)
    assert np.all(extent.distance(outside) <= nearest + 1e-12)


# ---------------------------------------------------------------------------------- swept bounds
def exact_distances(dut, q):
    """Drake's signed distance of every checked pair at configuration q."""
    dut.checker.UpdateContextPositions(dut._full, q)
    query = dut._full.GetQueryObject()
    return np.array([query.ComputeSignedDistancePairClosestPoints(pair.id_A, pair.id_B).distance for pair in dut._pairs])


def cleared(dut, q, v, a, pair, threshold):
    """Which intervals of the samples q, v, a (n + 1, 8) the swept bounds prove at least
    ``threshold`` clear for ``pair`` (n,) bool."""
    _, _, bend = _motion_bounds(q, v, a, PERIOD, dut._upstream)
    open_intervals, _, _ = dut._bounds.open_intervals(np.ascontiguousarray(q.T), bend, 4, np.array([pair]), threshold)
    return ~open_intervals[0]


def test_bounds_at_a_configuration_never_exceed_drake_distances(dut):
    # Every bound, at every level (boxes, spheres over a block, per interval), is at most the
    # pair's distance when that is >= 0 and at most 0 when they overlap: asked to prove the pair
    # clear by a hair more than Drake's distance, the broad phase must refuse.
    rng = np.random.default_rng(4)
    bounded = np.flatnonzero(dut._bounds.bounded)
    still = np.zeros((2, 8))
    checked = 0
    for q in random_configurations(dut, 400, rng):
        distances = exact_distances(dut, q)
        samples = np.array([q, q])
        for p in bounded.tolist():
            threshold = max(distances[p], 0.0) + DISTANCE_ERROR
            assert not cleared(dut, samples, still, still, p, threshold)[0], (dut._pairs[p].name, distances[p])
            checked += 1
    assert checked > 5000


def hermite_dense(q0, v0, q1, v1, count):
    """Configurations (count + 1, 8) along the cubic Hermite interpolant over one period."""
    s = np.linspace(0, 1, count + 1)[:, None]
    h = PERIOD
    return (2 * s**3 - 3 * s**2 + 1) * q0 + (s**3 - 2 * s**2 + s) * h * v0 + (3 * s**2 - 2 * s**3) * q1 + (s**3 - s**2) * h * v1


def test_bounds_over_an_interval_never_exceed_the_distance_between_its_samples(dut):
    # Fast intervals (joint speeds up to the limits, accelerations up to twice theirs): a pair is
    # never proven clear by more than Drake's smallest distance on a dense grid of the interval.
    rng = np.random.default_rng(5)
    bounded = np.flatnonzero(dut._bounds.bounded)
    speed, acceleration = dut.plant.GetVelocityUpperLimits(), dut.plant.GetAccelerationUpperLimits()
    checked = 0
    for q0 in random_configurations(dut, 60, rng, outside=0.0):
        v0, v1 = rng.uniform(-speed, speed), rng.uniform(-speed, speed)
        a0 = rng.uniform(-2 * acceleration, 2 * acceleration)
        q1 = q0 + PERIOD * v0 + 0.5 * PERIOD**2 * a0
        dense = np.array([exact_distances(dut, q) for q in hermite_dense(q0, v0, q1, v1, 20)])
        q, v, a = np.array([q0, q1]), np.array([v0, v1]), np.array([a0, a0])
        for p in bounded.tolist():
            threshold = max(dense[:, p].min(), 0.0) + DISTANCE_ERROR
            assert not cleared(dut, q, v, a, p, threshold)[0], dut._pairs[p].name
            checked += 1
    assert checked > 1000


def test_no_point_strays_further_from_its_chord_than_its_deviation(dut):
    # The deviation bound of robot.bounds: h^2 / 8 sum_j rho_j (A_j + V_j (V_j + 4 U_j)), checked
    # on points of every moving geometry along fast Hermite intervals.
    rng = np.random.default_rng(6)
    plant, inspector = dut.plant, dut.inspector
    kinematics = dut._bounds.kinematics
    speed, acceleration = plant.GetVelocityUpperLimits(), plant.GetAccelerationUpperLimits()
    geometries = dut._kinematics.robot_geometries()
    worst = 0.0
    for q0 in random_configurations(dut, 100, rng, outside=0.0):
        v0, v1 = rng.uniform(-speed, speed), rng.uniform(-speed, speed)
        q1 = q0 + PERIOD * 0.5 * (v0 + v1) + rng.uniform(-1, 1, 8) * acceleration * PERIOD**2 / 8
        q, v = np.array([q0, q1]), np.array([v0, v1])
        _, _, bend = _motion_bounds(q, v, np.zeros_like(q), PERIOD, dut._upstream)
        X_WB = poses(kinematics, hermite_dense(q0, v0, q1, v1, 40))  # (41, bodies, 3, 4)
        for g in geometries:
            body = int(plant.GetBodyFromFrameId(inspector.GetFrameId(g)).index())
            X_BG = inspector.GetPoseInFrame(g).GetAsMatrix34()
            points = shape_points(inspector.GetShape(g), rng, 30) @ X_BG[:, :3].T + X_BG[:, 3]
            path = np.einsum("sij,pj->spi", X_WB[:, body, :, :3], points) + X_WB[:, body, None, :, 3]  # (41, points, 3)
            s = np.linspace(0, 1, 41)[:, None, None]
            chord = (1 - s) * path[:1] + s * path[-1:]
            deviation = float(np.max(np.linalg.norm(path - chord, axis=2)))
            bound = float(bend[:, 0] @ dut._kinematics.lever_arms(g))
            assert deviation <= bound * (1 + 1e-6) + 1e-12
            worst = max(worst, deviation / bound)
    assert worst > 0.05  # and the bound is not absurdly loose


def test_block_hulls_and_geometry_boxes_equal_their_references(dut):
    """The kernels' fast paths bit for bit: the block hulls against NumPy's min and max over each
    block's samples (ties of +0 and -0, infinities), the boxed side's boxes without its poses
    against those with them."""
    from ace_drake.robot.bounds import _block_hulls, _geometry_boxes

    rng = np.random.default_rng(8)
    bounds = dut._bounds
    for n, block in ((1, 16), (5, 4), (40, 16), (301, 16), (33, 1)):
        q = random_configurations(dut, n + 1, rng, outside=0.0).T.copy()
        bend = rng.uniform(0, 1e-4, (8, n))
        X = bounds.kinematics.pose_rows(q)
        for geometries in (bounds._covered, bounds._boxed):
            used = rng.random(len(geometries[0])) < 0.8
            kept = _geometry_boxes(X, bend, geometries, used, True)
            scratch = _geometry_boxes(X, bend, geometries, used, False)
            assert scratch[0].shape == (1, 12, n + 1)
            for g in np.flatnonzero(used):
                assert np.array_equal(kept[1][g], scratch[1][g]) and np.array_equal(kept[2][g], scratch[2][g])
            box, deviation = kept[1].copy(), kept[2]
            box[~used] = 0.0
            box[used, :, :, :2] = np.where(rng.random((used.sum(), 2, 3, 2)) < 0.5, 0.0, -0.0)
            if n > 3:
                box[used, 1, 0, 3] = np.inf
            hull, most = _block_hulls(box, deviation, used, block)
            for b in range(hull.shape[0]):
                first, last = b * block, min((b + 1) * block, n)
                for g in np.flatnonzero(used):
                    assert np.array_equal(hull[b, g, 0], box[g, 0, :, first : last + 1].min(axis=1))
                    assert np.array_equal(hull[b, g, 1], box[g, 1, :, first : last + 1].max(axis=1))
                    assert most[b, g] == deviation[g, first:last].max(initial=0.0)


def test_sphere_covers_are_computed_once_and_handed_out_as_copies():
    from ace_drake.robot.bounds import _sphere_cover

    for shape in (Sphere(0.03), Capsule(0.02, 0.3), Cylinder(0.075, 0.007)):
        centres, radii = sphere_cover(shape)
        expected = _sphere_cover(shape, 0.003, 48)
        assert np.array_equal(centres, expected[0]) and np.array_equal(radii, expected[1])
        centres[:] = 1.0
        radii[:] = 0.0
        again = sphere_cover(shape)
        assert np.array_equal(again[0], expected[0]) and np.array_equal(again[1], expected[1])
        other = sphere_cover(shape, excess=0.01, max_spheres=8)
        assert np.array_equal(other[0], _sphere_cover(shape, 0.01, 8)[0])
    with pytest.raises(ValueError, match="unsupported shape"):
        sphere_cover(Box(1.0, 1.0, 1.0))
