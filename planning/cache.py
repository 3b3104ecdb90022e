"""The planner's result cache: one file per candidate, named by the content hash of the part
(its mesh file and unit) and the candidate (grasp, turn, preset, the planner's version and
seed), so a rerun, or a run after a worker died, computes only what is missing.

A result is ``KEY.json`` and, when it has a picture's points, ``KEY.npz``; both are written
atomically (a temporary file renamed into place), the JSON last: a result is there once its
JSON is. Failures of the pass itself ("failed" with the reason) are results like the others;
a task that raised is not cached (it may be the machine's, not the part's).
"""
from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from scanner_core.fileio import save_json_atomic, write_bytes_atomic

__all__ = ["PLANNER_VERSION", "candidate_key", "ResultCache"]

#: Changes whenever what a candidate's result holds or how it is computed changes: older
#: results are then computed again.
PLANNER_VERSION = 1
_ARRAYS = ("preview", "preview_edges")


def candidate_key(digest: str, units: str, candidate_key: dict, seed: int) -> str:
    """Hex SHA-256 of a candidate's identity: the mesh file's `digest`, its unit, the
    candidate's `Candidate.key`, the noise seed and `PLANNER_VERSION`."""
    blob = json.dumps({"mesh": digest, "units": units, "candidate": candidate_key,
                       "seed": int(seed), "planner": PLANNER_VERSION}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


class ResultCache:
    """Candidate results on disk under `root` (created on first write)."""

    def __init__(self, root):
        self.root = Path(root)

    def _path(self, key: str, suffix: str) -> Path:
        return self.root / key[:2] / f"{key}{suffix}"

    def get(self, key: str) -> dict | None:
        """The stored result, with its picture's arrays, or None when there is none (or it
        cannot be read: then it is computed again)."""
        path = self._path(key, ".json")
        try:
            result = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            return None
        arrays = self._path(key, ".npz")
        if arrays.is_file():
            try:
                with np.load(arrays) as data:
                    result.update({name: data[name] for name in data.files})
            except (OSError, ValueError):
                return None
        return result

    def put(self, key: str, result: dict) -> None:
        """Store a result (arrays in ``.npz``, the rest in ``.json``)."""
        path = self._path(key, ".json")
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: np.asarray(result[k]) for k in _ARRAYS if k in result}
        if arrays:
            buffer = io.BytesIO()
            np.savez(buffer, **arrays)
            write_bytes_atomic(self._path(key, ".npz"), buffer.getvalue())
        save_json_atomic(path, {k: v for k, v in result.items() if k not in _ARRAYS})
