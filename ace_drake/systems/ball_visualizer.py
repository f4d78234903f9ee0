"""BallVisualizer: draws the table, net and ball with a trail in Meshcat."""

from __future__ import annotations

import numpy as np
from pydrake.geometry import Box, Meshcat, Rgba, Sphere
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ace_drake.physics.params import BallPhysicsParams

TABLE_COLOR = Rgba(0.05, 0.2, 0.45, 1.0)
LINE_COLOR = Rgba(0.95, 0.95, 0.95, 1.0)
NET_COLOR = Rgba(0.92, 0.92, 0.92, 0.85)
BALL_COLOR = Rgba(1.0, 0.55, 0.0, 1.0)
TRAIL_COLOR = Rgba(1.0, 0.75, 0.3, 0.6)


def set_court_view(meshcat: Meshcat) -> None:
    """Hides Meshcat's grid and axes (the grid would cut through the scene at the playing surface)
    and places the camera behind and beside the robot's end of the table."""
    meshcat.SetProperty("/Grid", "visible", False)
    meshcat.SetProperty("/Axes", "visible", False)
    meshcat.SetCameraPose(np.array([-3.6, -2.2, 1.0]), np.array([0.0, 0.0, 0.0]))


def draw_table(meshcat: Meshcat, params: BallPhysicsParams, prefix: str = "/table") -> None:
    """Adds the table top, its white lines, the net, four legs and the floor to ``meshcat`` and sets
    the court view (``set_court_view``). For diagrams without the robot's SceneGraph, which draws
    its own court (models/table.sdf).

    The playing surface is at z = 0 (DESIGN.md frame); all sizes come from ``params``.
    """
    table, net = params.table, params.net
    set_court_view(meshcat)
    top_thickness = 0.03
    meshcat.SetObject(f"{prefix}/top", Box(table.length, table.width, top_thickness), TABLE_COLOR)
    meshcat.SetTransform(f"{prefix}/top", RigidTransform([0, 0, -0.5 * top_thickness]))
    line_width = 0.02
    lines = {
        "side_left": (Box(table.length, line_width, 0.001), [0, 0.5 * (table.width - line_width), 0]),
        "side_right": (Box(table.length, line_width, 0.001), [0, -0.5 * (table.width - line_width), 0]),
        "end_robot": (Box(line_width, table.width, 0.001), [-0.5 * (table.length - line_width), 0, 0]),
        "end_human": (Box(line_width, table.width, 0.001), [0.5 * (table.length - line_width), 0, 0]),
        "centre": (Box(table.length, 0.003, 0.001), [0, 0, 0]),
    }
    for name, (shape, position) in lines.items():
        meshcat.SetObject(f"{prefix}/lines/{name}", shape, LINE_COLOR)
        meshcat.SetTransform(f"{prefix}/lines/{name}", RigidTransform(position))
    span = table.width + 2 * net.overhang
    meshcat.SetObject(f"{prefix}/net", Box(0.01, span, net.height), NET_COLOR)
    meshcat.SetTransform(f"{prefix}/net", RigidTransform([0, 0, 0.5 * net.height]))
    leg_height = table.surface_height - top_thickness
    for i, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        path = f"{prefix}/legs/{i}"
        meshcat.SetObject(path, Box(0.05, 0.05, leg_height), Rgba(0.2, 0.2, 0.2, 1))
        x = sx * (0.5 * table.length - 0.2)
        y = sy * (0.5 * table.width - 0.15)
        meshcat.SetTransform(path, RigidTransform([x, y, -top_thickness - 0.5 * leg_height]))
    meshcat.SetObject(f"{prefix}/floor", Box(8.0, 6.0, 0.01), Rgba(0.55, 0.35, 0.25, 1))
    meshcat.SetTransform(f"{prefix}/floor", RigidTransform([0, 0, -table.surface_height - 0.005]))


class BallVisualizer(LeafSystem):
    """Publishes the ball and a trail of its recent positions to Meshcat.

    Input ports:
        ball_state (9,): [p (m), v (m/s), w (rad/s)]; only the position is drawn.
    State:
        discrete (3 * trail_length,): the trail, newest position first, m.
    Events:
        initialization and periodic (``publish_period``, default 0.01 s) discrete updates that
        shift the trail, followed by a publish that draws ball and trail. The trail is drawn as
        small spheres moved to past positions, so it survives in a Meshcat recording (an
        animation holds transforms, not geometry updates).
    """

    def __init__(
        self,
        meshcat: Meshcat,
        params: BallPhysicsParams | None = None,
        publish_period: float = 0.01,
        trail_length: int = 40,
        prefix: str = "/ball",
        draw_scene: bool = True,
    ):
        super().__init__()
        if publish_period <= 0:
            raise ValueError(f"BallVisualizer: publish_period must be > 0 s, got {publish_period}")
        if trail_length < 1:
            raise ValueError(f"BallVisualizer: trail_length must be >= 1, got {trail_length}")
        self._meshcat = meshcat
        self._prefix = prefix
        self._trail_length = trail_length
        self.params = params or BallPhysicsParams()
        self.ball_state_port = self.DeclareVectorInputPort("ball_state", 9)
        self._trail_index = self.DeclareDiscreteState(3 * trail_length)
        self.DeclareInitializationDiscreteUpdateEvent(self.FillTrail)
        self.DeclarePeriodicDiscreteUpdateEvent(publish_period, 0.0, self.ShiftTrail)
        self.DeclarePeriodicPublishEvent(publish_period, 0.0, self.Publish)
        radius = self.params.aero.ball_radius
        meshcat.SetObject(f"{prefix}/ball", Sphere(radius), BALL_COLOR)
        self._trail_paths = [f"{prefix}/trail/{i}" for i in range(trail_length)]
        for i, path in enumerate(self._trail_paths):
            meshcat.SetObject(path, Sphere(0.35 * radius * (1 - 0.6 * i / trail_length)), TRAIL_COLOR)
        if draw_scene:
            draw_table(meshcat, self.params)

    def FillTrail(self, context, discrete_state):
        """At initialization the whole trail sits at the ball."""
        position = self.ball_state_port.Eval(context)[:3]
        discrete_state.set_value(self._trail_index, np.tile(position, self._trail_length))

    def ShiftTrail(self, context, discrete_state):
        """Prepends the current position, dropping the oldest."""
        trail = context.get_discrete_state(self._trail_index).get_value()
        position = self.ball_state_port.Eval(context)[:3]
        discrete_state.set_value(self._trail_index, np.concatenate([position, trail[:-3]]))

    def Publish(self, context):
        """Moves the ball and the trail's spheres; timestamps go into any active recording."""
        time = context.get_time()
        position = self.ball_state_port.Eval(context)[:3]
        self._meshcat.SetTransform(f"{self._prefix}/ball", RigidTransform(position), time)
        trail = context.get_discrete_state(self._trail_index).get_value().reshape(-1, 3)
        for path, past in zip(self._trail_paths, trail):
            self._meshcat.SetTransform(path, RigidTransform(past), time)
