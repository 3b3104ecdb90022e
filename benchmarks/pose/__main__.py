"""``python -m benchmarks.pose OUT_DIR [--quick]``: the pose bench, its summary printed."""
import json
import pathlib
import sys

from benchmarks.pose import run

args = [a for a in sys.argv[1:] if a != "--quick"]
out = run(pathlib.Path(args[0] if args else "out/bench/pose"), quick="--quick" in sys.argv)
print(json.dumps(out["summary"], indent=2))
