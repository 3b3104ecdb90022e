"""One pass, from frames to a scan: the one streaming core the CLI, the service and the
benchmarks drive.

Per frame: the LED marker in the three views, found once (:class:`MarkerTracker` searches near
where the previous frames put it) and shared by the trigger's presence test and the frame's
processing; then (:func:`process_frame`) the stripe per column of the direct view and its
triangulation (pixel ray x light plane). Per pass: :class:`PassAccumulator` places each
profile in {T} as it arrives, in any order, by the marker-derived gripper position and the
gripper's orientation from the robot (``Robot.pose_at`` at the frame's time plus the
camera-to-robot clock offset; paper section II: no assumption of constant speed or straight
motion), and yields a scan sorted by frame id.

:func:`run_pass` is the single-threaded driver (``flyscan scan``, the benchmarks); the service
runs the same pieces with the marker and trigger on its acquisition thread and
:func:`process_frame` + :meth:`PassAccumulator.add` on worker threads.

The parts live in modules of their own: one frame's measurement (the marker, the stripe, the
profile, the warm-up, and the settings, :class:`PipelineParams`) in
``scanner_core.pipeline.frame``; the pass's accumulation (placing profiles in {T}, the better
exposed of each pair, the partly lit points, the edge points stitched into the scan) in
``scanner_core.pipeline.accumulate``; the drivers (:func:`camera_frames`,
:func:`measure_frame`, :func:`feed_frame`, :func:`run_pass`) in
``scanner_core.pipeline.drive``. This module gathers their public names.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

from scanner_core.pipeline.accumulate import (MAX_POSE_AGE_S, PREVIOUS_PROFILE_FRAMES,
                                              PassAccumulator, PlacedProfile)
from scanner_core.pipeline.drive import camera_frames, feed_frame, measure_frame, run_pass
from scanner_core.pipeline.frame import (MASK_ROW_FACTOR, MarkerTracker, PipelineParams,
                                         frame_stripe, marker_in_view, observe_marker,
                                         process_frame, warm_up)

__all__ = ["PipelineParams", "observe_marker", "MarkerTracker", "marker_in_view",
           "frame_stripe", "process_frame", "warm_up", "PlacedProfile", "PassAccumulator",
           "camera_frames", "measure_frame", "feed_frame", "run_pass", "MAX_POSE_AGE_S",
           "MASK_ROW_FACTOR", "PREVIOUS_PROFILE_FRAMES"]
