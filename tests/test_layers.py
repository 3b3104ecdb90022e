"""The layers (ARCHITECTURE.md), checked by import-linter's contracts in pyproject.toml:
benchmarks over the service and its command line over the simulator over scanner_core,
clients on their own, the service's real path free of the simulator, no import cycle."""
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONTRACTS = 4


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert exe is not None, "import-linter is not installed (pip install -e '.[test]')"
    return subprocess.run([exe, "--no-cache"], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_the_contracts_hold():
    done = _lint(ROOT)
    assert done.returncode == 0, done.stdout[-4000:]
    assert f"Contracts: {CONTRACTS} kept, 0 broken." in done.stdout


def test_a_lazy_import_of_the_simulator_from_the_service_is_caught(tmp_path):
    """The contract sees imports inside functions too: a copy of the tree in which the
    service's store imports the simulator inside a function breaks it."""
    copy = tmp_path / "tree"
    for name in ("scanner_core", "simulator", "planning", "service", "benchmarks", "clients"):
        shutil.copytree(ROOT / name, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", copy / "pyproject.toml")
    store = copy / "service" / "store.py"
    store.write_text(store.read_text() + "\n\ndef _probe():\n"
                     "    from simulator.cell import load_cell\n    return load_cell\n")
    done = _lint(copy)
    assert done.returncode != 0
    assert "service.store -> simulator.cell" in done.stdout
