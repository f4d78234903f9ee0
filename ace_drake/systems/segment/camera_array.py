"""SegmentCameraArray: the nine frame cameras and the triangulator of B environments."""

from __future__ import annotations

import numpy as np

from ace_drake.control.segment_timing import SegmentTiming
from ace_drake.perception.camera_segment import CameraSegment
from ace_drake.perception.params import PositionSensorParams
from ace_drake.perception.sensor_models import PendingBatch
from ace_drake.systems.segment.position_sensor import SegmentPositionSensor


class SegmentCameraArray(SegmentPositionSensor):
    """The continuous-time ``ApsCameraArray`` (analytic mode) and ``Triangulator`` for B
    environments in one system (paper, Methods *Ball triangulation*;
    ``perception.camera_segment.CameraSegment``): at each 200 Hz trigger inside a tick every
    camera detects the ball or not (pixel noise, dropout, the table's occlusion), the frame is
    triangulated (multi-view DLT, Gauss-Newton, outlier rejection) and released after the
    triangulation latency. The draws of trigger k of an episode come from [seed, k + 1], as the
    reference's. Ports, state and events as the SegmentPositionSensor's (the position path's
    other choice; the wiring is the same).
    """

    def __init__(self, cameras: CameraSegment, history_capacity: int, batch: int, timing: SegmentTiming):
        """Args: cameras, the batched camera array; history_capacity, the measurements the output
        keeps; batch, B; timing, the segment time line."""
        self.cameras = cameras
        super().__init__(PositionSensorParams(history_capacity=history_capacity), batch, timing)

    def _trigger_period(self) -> float:
        return self.cameras.period

    def _sample(self, flight, ticks: np.ndarray, first: np.ndarray, seeds: np.ndarray) -> PendingBatch:
        triggers, valid = self._trigger_grid(first)
        groups: dict[tuple, list[int]] = {}
        for row in range(self.batch):
            groups.setdefault(tuple((triggers[row, valid[row]] - first[row]).tolist()), []).append(row)
        parts = []
        for offsets, rows in groups.items():
            if not offsets:
                continue
            rows = np.array(rows)
            indices = np.asarray(offsets)
            row_triggers = first[rows, None] + indices[None, :]  # episode samples (k, m)
            measured = self.cameras.measure(
                flight.samples[rows][:, indices, :3], self.timing.seconds(row_triggers), seeds[rows].astype(np.uint64), row_triggers // self._trigger + 1
            )
            parts.append((np.repeat(rows, indices.size), measured))
        if not parts:
            return PendingBatch.empty()
        return PendingBatch.from_samples(
            *(np.concatenate(items) for items in zip(*(
                (sample_rows, m.capture_time.reshape(-1), m.release_time.reshape(-1), m.value.reshape(-1, 3), m.covariance.reshape(-1, 3, 3), m.valid.reshape(-1))
                for sample_rows, m in parts
            )))
        )
