"""Triangulator: the ball's position from each released camera frame (paper, Methods *Ball
triangulation*), as the position measurements the estimator and the policy read."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem

from ace_drake.perception.cameras import Camera, DetectionFrame
from ace_drake.perception.measurements import Measurement, MeasurementHistory
from ace_drake.perception.params import CameraParams
from ace_drake.perception.triangulation import triangulate


@dataclasses.dataclass(frozen=True)
class _TriangulatorState:
    """The measurements released so far (newest last) and the last camera frame absorbed."""

    history: MeasurementHistory
    last_frame_sequence: int

    def __deepcopy__(self, memo) -> _TriangulatorState:
        return self  # immutable: spare Drake's deep copy of abstract state at every update


class Triangulator(LeafSystem):
    """Triangulates each newly released camera frame (multi-view DLT, Gauss-Newton on the
    reprojection error, outlier rejection; ``perception/triangulation.py``).

    Input ports:
        detections (abstract DetectionFrame): from the ApsCameraArray; its cameras must be this
            system's, in the same order.
    Output ports:
        position_measurements (abstract MeasurementHistory): the last ``history_capacity``
            positions p_WB (m) with covariances (m^2), capture and release times (s, the frame's)
            and sequence numbers 1, 2, ... in release order. A frame that does not triangulate
            (fewer than ``params.min_views`` consistent views) adds nothing. The output includes
            the frame on the input port as soon as it is released.
    State:
        abstract: the history and the sequence number of the last frame absorbed into it.
    Events:
        periodic unrestricted update at the camera array's triggers (``params.trigger_rate``,
        200 Hz, offset 0): absorbs the output (history plus the input frame's position) into the
        state, so each frame is triangulated once. An update reads the inputs from before its
        instant, so it absorbs the frame released during the period that ends there (the array
        releases one per period); until then the output adds that frame itself, so it shows every
        frame from its release on. Absorbing at the triggers, where the array's state changes
        anyway, rather than at the releases keeps the output's cache from triangulating a frame
        twice; an update with no new frame says so (EventStatus.DidNothing).
    """

    def __init__(self, cameras: Sequence[Camera], params: CameraParams | None = None, history_capacity: int = 32):
        """Args: cameras, the calibrated array (as given to the ApsCameraArray); params, the
        array's too (its trigger rate times the absorbing updates), with the pixel noise (px, the
        covariance's scale), the outlier threshold (px) and the minimum views; history_capacity,
        measurements kept on the output."""
        super().__init__()
        if not cameras:
            raise ValueError("Triangulator: needs at least one camera")
        if history_capacity < 1:
            raise ValueError(f"Triangulator: history_capacity must be >= 1, got {history_capacity}")
        self.cameras = tuple(cameras)
        self.camera_names = tuple(camera.name for camera in self.cameras)
        self.params = params or CameraParams()
        initial = _TriangulatorState(MeasurementHistory(capacity=history_capacity), 0)
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(initial))
        self.detections_port = self.DeclareAbstractInputPort("detections", AbstractValue.Make(DetectionFrame()))
        self.position_measurements_port = self.DeclareAbstractOutputPort(
            "position_measurements",
            lambda: AbstractValue.Make(initial.history),
            self.CalcPositionMeasurements,
            prerequisites_of_calc={self.abstract_state_ticket(self._state_index), self.detections_port.ticket()},
        )
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / self.params.trigger_rate, 0.0, self.AbsorbFrame)

    # ------------------------------------------------------------------------------ outputs
    def CalcPositionMeasurements(self, context, output):
        output.set_value(self._current(context).history)

    # ------------------------------------------------------------------------------ update
    def AbsorbFrame(self, context, state):
        """Stores the output's history (with the input frame's position) as the state."""
        stored = context.get_abstract_state(self._state_index).get_value()
        frame = self.detections_port.Eval(context)
        if frame.sequence <= stored.last_frame_sequence:
            return EventStatus.DidNothing()  # the Simulator skips writing the state back
        history = self.position_measurements_port.Eval(context)  # cached: triangulated once
        state.get_mutable_abstract_state(self._state_index).set_value(_TriangulatorState(history, frame.sequence))
        return EventStatus.Succeeded()

    # ------------------------------------------------------------------------------ helpers
    def _current(self, context) -> _TriangulatorState:
        """The stored state plus the input frame when it is new."""
        stored = context.get_abstract_state(self._state_index).get_value()
        frame = self.detections_port.Eval(context)
        if frame.sequence <= stored.last_frame_sequence:
            return stored
        if frame.camera_names != self.camera_names:
            raise ValueError(
                f"Triangulator: the detections come from cameras {frame.camera_names}, but this triangulator "
                f"was built for {self.camera_names}"
            )
        result = triangulate(
            self.cameras, frame.pixels, self.params.pixel_noise_sigma, self.params.outlier_threshold_px, self.params.min_views
        )
        history = stored.history
        if result is not None:
            measurement = Measurement(history.last_sequence + 1, frame.capture_time, frame.release_time, result.position, result.covariance)
            history = history.appended(measurement)
        return _TriangulatorState(history, frame.sequence)
