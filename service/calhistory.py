"""The calibration history: every calibration the service was given or fitted, versioned, the
active one marked, and a rollback to the one active before.

``DATA/calibration/history/``: ``vNNNN.json`` (the calibration file, as ``flyscan
calibrate`` writes it), ``vNNNN.report.json`` (the fit's report, when fitted) and ``index.json``
(the versions' entries, the active one and the order they were activated in), each written
atomically. A version is never changed once written; activating one writes the data folder's
``calibration.json`` too (what the service starts with), through ``Service.set_calibration``,
which refuses while a pass is acquired or processed (a pass is never interrupted).
"""
from __future__ import annotations

import datetime as _dt
import json
import threading
from pathlib import Path

from scanner_core.geometry.calibration import Calibration, load_calibration, save_calibration
from scanner_core.fileio import save_json_atomic

__all__ = ["CalibrationHistory", "NoSuchVersion", "NoPreviousVersion", "open_history",
           "keep_and_activate", "activate", "rollback"]


class NoSuchVersion(KeyError):
    """No calibration of that version."""


class NoPreviousVersion(LookupError):
    """A rollback with nothing active before the active version."""


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


class CalibrationHistory:
    """The versions in ``folder``; constructing does no I/O, :meth:`open` reads the index.
    Thread-safe (one lock)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._index = {"versions": [], "active": None, "activations": []}

    # -- files ------------------------------------------------------------------------------
    def _path(self, version: int, suffix: str = ".json") -> Path:
        return self.folder / f"v{version:04d}{suffix}"

    def _save_index(self) -> None:
        save_json_atomic(self.folder / "index.json", self._index)

    def open(self, current: Calibration, source: str) -> None:
        """Read the index; an empty history starts with ``current`` as version 1, active."""
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / "index.json"
        with self._lock:
            if path.is_file():
                self._index = json.loads(path.read_text())
                return
        entry = self.add(current, source=source)
        self.mark_active(entry["version"])

    # -- versions ---------------------------------------------------------------------------
    def add(self, calibration: Calibration, *, source: str, report: dict | None = None,
            figures: dict | None = None) -> dict:
        """Keep a calibration as the next version (not active); its entry."""
        with self._lock:
            version = max((e["version"] for e in self._index["versions"]), default=0) + 1
            save_calibration(self._path(version), calibration)
            if report is not None:
                save_json_atomic(self._path(version, ".report.json"), report)
            entry = {"version": version, "created": _now(), "source": source,
                     "figures": figures or {}, "has_report": report is not None}
            self._index["versions"].append(entry)
            self._save_index()
            return dict(entry)

    def entry(self, version: int) -> dict:
        with self._lock:
            for e in self._index["versions"]:
                if e["version"] == version:
                    return {**e, "active": self._index["active"] == version}
        raise NoSuchVersion(f"no calibration version {version}")

    def calibration(self, version: int) -> Calibration:
        self.entry(version)  # NoSuchVersion first
        return load_calibration(self._path(version))

    def report(self, version: int) -> dict | None:
        path = self._path(version, ".report.json")
        if not self.entry(version)["has_report"] or not path.is_file():
            return None
        return json.loads(path.read_text())

    def residuals_path(self, version: int) -> Path:
        """Where the version's residuals chart is kept (``service.calsessions``)."""
        self.entry(version)
        return self._path(version, ".residuals.png")

    def entries(self) -> list[dict]:
        with self._lock:
            active = self._index["active"]
            return [{**e, "active": e["version"] == active} for e in self._index["versions"]]

    @property
    def active(self) -> int | None:
        with self._lock:
            return self._index["active"]

    def mark_active(self, version: int) -> None:
        """Record that ``version`` is now the service's calibration (the caller set it)."""
        self.entry(version)
        with self._lock:
            if self._index["active"] != version:
                self._index["activations"].append(version)
            self._index["active"] = version
            self._save_index()

    def previous(self) -> int:
        """The version active before the active one (a rollback's target)."""
        with self._lock:
            log = self._index["activations"]
            if len(log) < 2:
                raise NoPreviousVersion("no calibration was active before this one")
            return log[-2]

    def rolled_back(self, version: int) -> None:
        """Record a rollback to ``version`` (:meth:`previous`; the caller set it): the
        activation it undoes leaves the log, so that a second rollback goes one further."""
        with self._lock:
            log = self._index["activations"]
            if len(log) < 2 or log[-2] != version:
                raise NoPreviousVersion(f"version {version} was not active before this one")
            log.pop()
            self._index["active"] = version
            self._save_index()


# -- the service's calibration and its history (``service.daemon.Service``) --------------------

def open_history(service, source: str) -> None:
    """Open the service's history, and keep the calibration it starts with as the active
    version (a new one when it is not the one the history holds active: ``--calibration``)."""
    current = service.engine.calibration
    history = service.calibration_history
    history.open(current, source=source)
    active = history.active
    if active is None or history.calibration(active).to_dict() != current.to_dict():
        history.mark_active(history.add(current, source=source)["version"])


def keep_and_activate(service, calibration: Calibration, source: str = "PUT /calibration") -> dict:
    """A calibration given whole (``PUT /calibration``): the service's, and a new version,
    active. ValueError, EngineBusy, OSError as ``Service.set_calibration``."""
    service.set_calibration(calibration)
    history = service.calibration_history
    entry = history.add(calibration, source=source)
    history.mark_active(entry["version"])
    return history.entry(entry["version"])


def activate(service, version: int) -> dict:
    """Make a version the service's calibration (only ever when asked). NoSuchVersion, and as
    ``Service.set_calibration``: EngineBusy during a pass, which is never interrupted."""
    history = service.calibration_history
    service.set_calibration(history.calibration(version))
    history.mark_active(version)
    return history.entry(version)


def rollback(service) -> dict:
    """Back to the calibration active before the active one, exactly as it was kept
    (NoPreviousVersion when there is none)."""
    history = service.calibration_history
    version = history.previous()
    service.set_calibration(history.calibration(version))
    history.rolled_back(version)
    return history.entry(version)
