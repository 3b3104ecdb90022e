"""Scans on disk: each one appears whole or not at all, and outlives the process.

A scan is a folder ``scans/<scan_id>/`` with ``cloud.ply``, ``edges.ply`` and ``report.json``
(the files ``flyscan scan`` writes) plus ``info.json`` (what the REST API serves). It is
written into a hidden ``.tmp-<scan_id>`` folder and renamed into place in one step, so a
process killed mid-write leaves only a temporary folder, which the next start removes. The
oldest scans beyond ``retention`` are deleted.

The store keeps an index of the scans' infos in memory, read from disk once at ``open`` and
kept by ``save``, ``update_info`` and ``delete``: ``list`` and ``info`` serve it without
reading a file (re-parsing every ``info.json`` on each ``GET /scans`` took the camera's time).
"""
from __future__ import annotations

import copy
import json
import os
import re
import shutil
import threading
from pathlib import Path

from scanner_core.fileio import save_json_atomic
from scanner_core.io.scanfiles import save_scan
from scanner_core.types import Scan

#: Scan ids the store accepts: they become folder names.
SCAN_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
TMP_PREFIX = ".tmp-"


class ScanStore:
    """The scans folder. Thread-safe."""

    def __init__(self, root, retention: int = 200):
        self.root = Path(root) / "scans"
        self.retention = int(retention)
        self._lock = threading.Lock()
        self._index: dict[str, dict] | None = None  # scan_id -> info; None until opened

    def open(self) -> None:
        """Create the folder, remove what a killed write left behind, index the scans."""
        self.root.mkdir(parents=True, exist_ok=True)
        for leftover in self.root.glob(f"{TMP_PREFIX}*"):
            shutil.rmtree(leftover, ignore_errors=True)
        index = dict(self._read_all())
        with self._lock:
            self._index = index

    def _read_all(self) -> list[tuple[str, dict]]:
        """(folder name, info) of every scan folder, read from disk."""
        infos = []
        for folder in self.root.iterdir():
            if folder.name.startswith(TMP_PREFIX) or not folder.is_dir():
                continue
            try:
                info = json.loads((folder / "info.json").read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                continue  # not a scan folder
            if isinstance(info, dict):
                infos.append((folder.name, info))
        return infos

    def path(self, scan_id: str) -> Path:
        if not SCAN_ID.match(scan_id):
            raise KeyError(scan_id)
        return self.root / scan_id

    def save(self, scan_id: str, info: dict, scan: Scan | None = None, report: dict | None = None) -> Path:
        """Write a finished scan (or a failed one: ``scan`` None) atomically."""
        final = self.path(scan_id)
        tmp = self.root / f"{TMP_PREFIX}{scan_id}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            if scan is not None:
                save_scan(tmp, scan, report if report is not None else {})
            elif report is not None:
                save_json_atomic(tmp / "report.json", report)
            save_json_atomic(tmp / "info.json", info)
            _fsync_dir(tmp)
            with self._lock:
                if final.exists():
                    shutil.rmtree(final)
                os.replace(tmp, final)
                _fsync_dir(self.root)
                if self._index is not None:
                    self._index[scan_id] = json.loads(json.dumps(info))
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self._enforce_retention()
        return final

    def update_info(self, scan_id: str, info: dict) -> None:
        """Replace a stored scan's info (atomically); KeyError when there is no such scan."""
        folder = self.path(scan_id)
        if not (folder / "info.json").is_file():
            raise KeyError(scan_id)
        save_json_atomic(folder / "info.json", info)
        with self._lock:
            if self._index is not None:
                self._index[scan_id] = json.loads(json.dumps(info))

    def info(self, scan_id: str) -> dict:
        """The stored info of a scan (from the index once opened); KeyError when there is none."""
        path = self.path(scan_id)
        with self._lock:
            if self._index is not None:
                return copy.deepcopy(self._index[scan_id])
        try:
            return json.loads((path / "info.json").read_text())
        except FileNotFoundError:
            raise KeyError(scan_id) from None

    def file(self, scan_id: str, name: str) -> Path:
        path = self.path(scan_id) / name
        if not path.is_file():
            raise KeyError(f"{scan_id}/{name}")
        return path

    def list(self) -> list[dict]:
        """Infos of the stored scans, newest first: from the index once opened (shallow copies),
        from the disk before."""
        with self._lock:
            index = self._index
            infos = [dict(i) for i in index.values()] if index is not None else None
        if infos is None:
            infos = [info for _, info in self._read_all()]
        return sorted(infos, key=lambda i: i.get("created", 0.0), reverse=True)

    def delete(self, scan_id: str) -> None:
        path = self.path(scan_id)
        with self._lock:
            if not path.is_dir():
                raise KeyError(scan_id)
            try:
                shutil.rmtree(path)
            finally:
                if self._index is not None and not (path / "info.json").is_file():
                    self._index.pop(scan_id, None)

    def _enforce_retention(self) -> None:
        infos = self.list()
        for old in infos[self.retention:]:
            try:
                self.delete(old["scan_id"])
            except KeyError:
                pass


def free_bytes(path) -> int:
    """Bytes free to this process on the file system of `path` (an existing folder)."""
    stat = os.statvfs(path)
    return stat.f_bavail * stat.f_frsize


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
