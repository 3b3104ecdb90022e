"""Prometheus metrics of the service, in a registry of its own (no global state)."""
from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

STATES = ("idle", "armed", "scanning", "processing", "fault")


class Metrics:
    """Counters the finisher updates, gauges refreshed from the status at each scrape."""

    def __init__(self):
        self.registry = CollectorRegistry()
        r = self.registry
        self.scans = Counter("flyscan_scans", "Scans finished, by state", ["state"], registry=r)
        self.points = Histogram("flyscan_scan_points", "Points per finished scan", registry=r,
                                buckets=(100, 1e3, 1e4, 3e4, 1e5, 3e5, 1e6))
        self.latency = Histogram("flyscan_cloud_latency_seconds",
                                 "From the last frame of a pass to its cloud on ZeroMQ", registry=r,
                                 buckets=(0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.2, 0.5, 1.0))
        self.state = Gauge("flyscan_state", "1 for the run state the service is in", ["state"], registry=r)
        self.frames = Gauge("flyscan_camera_frames", "Frames received from the camera", registry=r)
        self.dropped = Gauge("flyscan_camera_frames_dropped", "Gaps in the camera's frame ids", registry=r)
        self.overflows = Gauge("flyscan_queue_overflows", "Frames lost to a full processing queue", registry=r)
        self.fps = Gauge("flyscan_camera_fps", "Camera frame rate", registry=r)
        self.zmq_sent = Gauge("flyscan_zmq_sent", "ZeroMQ messages sent", registry=r)
        self.zmq_dropped = Gauge("flyscan_zmq_dropped", "ZeroMQ messages the publisher's queue refused (a subscriber's own losses show as seq gaps)", registry=r)
        self.robot = Gauge("flyscan_robot_connected", "1 when the robot is connected", registry=r)
        self.renders = Gauge("flyscan_picture_renders",
                             "Pictures drawn and encoded (the other requests were served cached)",
                             ["picture"], registry=r)
        self.pictures_refused = Gauge("flyscan_picture_refused",
                                      "Preview requests refused (503): too many waiting for a render",
                                      registry=r)

    def scan_finished(self, info: dict) -> None:
        self.scans.labels(state=info["state"]).inc()
        if info.get("points"):
            self.points.observe(info["points"])
        latency = (info.get("latency_ms") or {}).get("last_frame_to_zmq")
        if latency is not None:
            self.latency.observe(latency / 1e3)

    def pictures(self, frame_renders: int, preview_renders: int, refused: int) -> None:
        self.renders.labels(picture="frame").set(frame_renders)
        self.renders.labels(picture="preview").set(preview_renders)
        self.pictures_refused.set(refused)

    def render(self, status: dict) -> bytes:
        for state in STATES:
            self.state.labels(state=state).set(1.0 if status["state"] == state else 0.0)
        self.frames.set(status["camera"]["frames"])
        self.dropped.set(status["frames_dropped"])
        self.overflows.set(status["queue"]["overflows"])
        self.fps.set(status["fps"])
        self.zmq_sent.set(status["zmq"]["sent"])
        self.zmq_dropped.set(status["zmq"]["dropped"])
        self.robot.set(1.0 if status["robot"]["connected"] else 0.0)
        return generate_latest(self.registry)
