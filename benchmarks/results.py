"""Writing a benchmark's results: the one JSON writer, the machine it ran on, the charts' canvas.

Every benchmark writes its figures with `write_json`: made JSON-safe (`json_safe`: numpy to
Python, NaN and infinities to null, since JSON has neither), with the machine's description
(`machine_info`) when the figures hold none, written atomically
(``scanner_core.fileio.save_json_atomic``), so a benchmark stopped half-way never leaves half a
file. Its charts are drawn on matplotlib's Agg backend (`pyplot`) and saved by `save_figure`.
"""
from __future__ import annotations

import datetime
import math
import os
import platform

import numpy as np

from scanner_core.fileio import save_json_atomic

__all__ = ["machine_info", "json_safe", "write_json", "pyplot", "save_figure"]


def machine_info() -> dict:
    """What machine a benchmark ran on: recorded beside every figure."""
    import numba

    info = {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def json_safe(value, *, digits: int | None = None):
    """A copy of `value` JSON can hold: numpy scalars and arrays to Python, tuples to lists,
    keys to strings, NaN and infinities to None; floats rounded to `digits` when given."""
    if isinstance(value, dict):
        return {str(k): json_safe(v, digits=digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, digits=digits) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist(), digits=digits)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not math.isfinite(v):
            return None
        return v if digits is None else round(v, digits)
    return value


def write_json(path, result: dict, *, digits: int | None = None) -> dict:
    """Write a benchmark's figures to `path` (JSON, indented, atomically) and return what was
    written: `result` made safe by `json_safe` (floats rounded to `digits` when given), with
    ``machine`` (`machine_info`) added when it holds none."""
    out = json_safe(result, digits=digits)
    if "machine" not in out:
        out["machine"] = machine_info()
    save_json_atomic(path, out)
    return out


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, no display), imported when a chart
    is drawn: the benchmarks import without it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, *, dpi: int = 100, rect=None) -> None:
    """Lay `fig` out (within `rect` of the figure when given), save it to `path` and close it."""
    import matplotlib.pyplot as plt

    if rect is None:
        fig.tight_layout()
    else:
        fig.tight_layout(rect=rect)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
