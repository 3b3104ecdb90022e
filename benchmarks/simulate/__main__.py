"""``python -m benchmarks.simulate OUT_DIR``: the simulator bench, its summary printed."""
import json
import pathlib
import sys

from benchmarks.simulate import run

summary = run(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "out/bench/simulate"))
print(json.dumps(summary["summary"], indent=2))
