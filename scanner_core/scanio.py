"""Save a scan as the contract's files: ``cloud.ply``, ``edges.ply`` and ``report.json``.

The clouds are binary little-endian PLY, float32 x, y, z in mm in {T}, with per-vertex
``frame_id`` and ``quality``. Every file is written atomically and the report last, so a
directory with a ``report.json`` holds a complete scan.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scanner_core.fileio import save_json_atomic
from scanner_core.ply import write_ply
from scanner_core.types import Scan


def save_scan(out_dir, scan: Scan, report: dict) -> dict[str, Path]:
    """Write a scan's files into ``out_dir`` (created if missing). Returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"cloud": out / "cloud.ply", "edges": out / "edges.ply", "report": out / "report.json"}
    comments = ("flyscan scan", "frame T", "units mm")
    write_ply(paths["cloud"], scan.cloud,
              fields={"frame_id": scan.frame_ids.astype(np.int32),
                      "quality": scan.quality.astype(np.float32)}, comments=comments)
    write_ply(paths["edges"], scan.edges, comments=comments)
    save_json_atomic(paths["report"], report)
    return paths
