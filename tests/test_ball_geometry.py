"""BallGeometry: the ball's sphere in a SceneGraph, perception role only, posed at the ball."""

import numpy as np
import pytest
from pydrake.geometry import Role, SceneGraph
from pydrake.systems.framework import DiagramBuilder

from ace_drake.perception.detection import BALL_RENDER_COLOR
from ace_drake.systems.ball_geometry import BallGeometry


def test_pose_follows_the_ball_and_the_sphere_is_for_cameras_only():
    builder = DiagramBuilder()
    scene_graph = builder.AddNamedSystem("scene_graph", SceneGraph())
    dut = builder.AddNamedSystem("ball_geometry", BallGeometry(scene_graph))
    builder.Connect(dut.geometry_pose_port, scene_graph.get_source_pose_port(dut.source_id))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    dut_context = dut.GetMyMutableContextFromRoot(context)
    dut.ball_state_port.FixValue(dut_context, np.array([0.3, -0.2, 0.5, 4.0, 0.0, 1.0, 0.0, 100.0, 0.0]))
    poses = dut.geometry_pose_port.Eval(dut_context)
    np.testing.assert_array_equal(poses.value(dut.frame_id).translation(), [0.3, -0.2, 0.5])
    inspector = scene_graph.model_inspector()
    (geometry_id,) = inspector.GetGeometries(dut.frame_id)
    assert inspector.GetShape(geometry_id).radius() == pytest.approx(0.02)
    assert inspector.GetPerceptionProperties(geometry_id) is not None
    assert inspector.GetIllustrationProperties(geometry_id) is None  # Meshcat's ball is the BallVisualizer's
    diffuse = inspector.GetPerceptionProperties(geometry_id).GetProperty("phong", "diffuse")
    assert (diffuse.r(), diffuse.g(), diffuse.b(), diffuse.a()) == pytest.approx(BALL_RENDER_COLOR)
    assert scene_graph.model_inspector().NumGeometriesWithRole(Role.kPerception) == 1
