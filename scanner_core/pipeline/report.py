"""``report.json``: what a scan says about itself, as the CLI and the service both write it."""
from __future__ import annotations

import math

from scanner_core.edges.kinds import kind_counts
from scanner_core.types import Scan

#: The stages of ``Scan.timings_ms`` that are processing (not waiting for frames or workers).
PROCESSING_STAGES = ("marker", "profiles", "scan", "assemble")


def _finite(x):
    """JSON has no NaN: non-finite numbers become None."""
    return x if x is None or math.isfinite(x) else None


def scan_report(scan: Scan, cross_check: dict | None = None, **extra) -> dict:
    """The report of one scan (the contract's fields, then what the pass adds).

    ``edge_kinds`` counts the edge points per ``scanner_core.edges.EdgeKind``: in the edge
    cloud (``dropout``, ``step``) and set aside (``occluded``, ``grazing``, ``turned_away``,
    ``off_model``: ``Scan.edges_aside``); ``edge_points`` is the edge cloud's size.

    Parameters
    ----------
    scan : Scan
    cross_check : dict, optional
        ``scanner_core.pipeline.crosscheck.cross_check`` of the pass.
    **extra
        Further entries (``ground_truth`` of a simulated scan, the service's latency).
    """
    processing_ms = sum(v for k, v in scan.timings_ms.items() if k in PROCESSING_STAGES)
    return {
        "frames": scan.frames,
        "frames_dropped": scan.frames_dropped,
        "frames_unplaced": scan.frames_unplaced,
        "frames_held_rotation": scan.frames_held_rotation,
        "frames_without_rotation": scan.frames_without_rotation,
        "queue_overflows": scan.queue_overflows,
        "end_reason": scan.end_reason,
        "interrupted": scan.interrupted,
        "marker_residual_px": _finite(scan.marker_residual_px),
        "points": int(len(scan.cloud)),
        "points_partly_lit": int(scan.points_partly_lit),
        "edge_points": int(len(scan.edges)),
        "edges_occluded": int(scan.edges_occluded),
        "edges_grazing": int(scan.edges_grazing),
        "edge_kinds": kind_counts(scan),
        "timings_ms": {**scan.timings_ms, "processing": round(processing_ms, 3)},
        "pose": None,
        "cross_check": cross_check if cross_check is not None else {"samples": 0},
        **extra,
    }
