"""The layers (docs/design.md), checked by import-linter's contracts in pyproject.toml: the
command line over the benchmarks over the service over the planner over the simulator over
scanner_core over the clients' wire formats; the core imports no other package, the service
neither the simulator nor the planner, the clients none; no import cycle; no exception."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONTRACTS = 5
PACKAGES = ("flyscan", "scanner_core", "simulator", "planning", "service", "benchmarks", "clients")


def _lint(cwd: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert exe is not None, "import-linter is not installed (pip install -e '.[test]')"
    return subprocess.run([exe, "--no-cache"], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def test_the_contracts_hold():
    done = _lint(ROOT)
    assert done.returncode == 0, done.stdout[-4000:]
    assert f"Contracts: {CONTRACTS} kept, 0 broken." in done.stdout


@pytest.mark.parametrize("module, imported, arrow", [
    ("service/store.py", "simulator.cell", "service.store -> simulator.cell"),
    ("benchmarks/place.py", "flyscan.common", "benchmarks.place -> flyscan.common"),
    ("scanner_core/calibration/plan.py", "clients.placement", "scanner_core.calibration.plan -> clients.placement"),
    ("simulator/cell.py", "service.settings", "simulator.cell -> service.settings"),
], ids=["the service imports the simulator", "a benchmark imports the command line",
        "the core imports the clients", "the simulator imports the service"])
def test_a_lazy_import_across_a_contract_is_caught(tmp_path, module, imported, arrow):
    """The contracts see imports inside functions too: a copy of the tree in which a module
    imports across a contract inside a function breaks it, and names the arrow."""
    copy = tmp_path / "tree"
    for name in PACKAGES:
        shutil.copytree(ROOT / name, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", copy / "pyproject.toml")
    target = copy / module
    target.write_text(target.read_text() + f"\n\ndef _probe():\n    import {imported}\n"
                                           f"    return {imported}\n")
    done = _lint(copy)
    assert done.returncode != 0
    assert arrow in done.stdout
