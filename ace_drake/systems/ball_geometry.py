"""BallGeometry: the ball as a sphere in a SceneGraph, posed from the BallPlant's state, so that
Drake's rendering cameras see it (the ApsCameraArray's rendered mode)."""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    FramePoseVector,
    GeometryFrame,
    GeometryInstance,
    PerceptionProperties,
    RenderLabel,
    Rgba,
    SceneGraph,
    Sphere,
)
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ace_drake.perception.cameras import BALL_RADIUS
from ace_drake.perception.detection import BALL_RENDER_COLOR

BALL_RENDER_LABEL = 1  # the ball's label in label images


class BallGeometry(LeafSystem):
    """Registers the ball's sphere with a SceneGraph (perception role only: Meshcat draws the ball
    through the BallVisualizer) and poses it at the ball's position.

    Input ports:
        ball_state (9,): [p_WB (m), v_WB (m/s), w_WB (rad/s)]; only the position is used (the
            sphere is uniformly coloured, so its orientation is not rendered).
    Output ports:
        geometry_pose (abstract FramePoseVector): X_WB of the ball's frame; connect it to
            ``scene_graph.get_source_pose_port(ball_geometry.source_id)``.
    State, events: none.
    """

    def __init__(self, scene_graph: SceneGraph, radius: float = BALL_RADIUS, color: tuple[float, ...] = BALL_RENDER_COLOR):
        """Args: scene_graph, where to register the sphere (source name ``ball``); radius, m;
        color, RGBA in [0, 1] (the detector's default thresholds expect BALL_RENDER_COLOR)."""
        super().__init__()
        self.source_id = scene_graph.RegisterSource("ball")
        self.frame_id = scene_graph.RegisterFrame(self.source_id, GeometryFrame("ball"))
        geometry = GeometryInstance(RigidTransform(), Sphere(radius), "ball")
        perception = PerceptionProperties()
        perception.AddProperty("phong", "diffuse", Rgba(*color))
        perception.AddProperty("label", "id", RenderLabel(BALL_RENDER_LABEL))
        geometry.set_perception_properties(perception)
        scene_graph.RegisterGeometry(self.source_id, self.frame_id, geometry)
        self.ball_state_port = self.DeclareVectorInputPort("ball_state", 9)
        self.geometry_pose_port = self.DeclareAbstractOutputPort(
            "geometry_pose", lambda: AbstractValue.Make(FramePoseVector()), self.CalcGeometryPose
        )

    def CalcGeometryPose(self, context, output):
        poses = FramePoseVector()
        poses.set_value(self.frame_id, RigidTransform(np.asarray(self.ball_state_port.Eval(context)[:3])))
        output.set_value(poses)
