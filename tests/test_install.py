"""The package as a user installs it: a wheel, not this checkout.

``pip install .`` copies the packages into site-packages, away from the repository and from
``../shared``; whatever the code finds relative to its own files must come with the wheel
(package data) or be given by an option or the environment.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The wheel built from this checkout, unpacked into a folder of its own."""
    root = tmp_path_factory.mktemp("install")
    wheels, target = root / "wheels", root / "site"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--quiet"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels),
                    str(REPO)], check=True, cwd=root, capture_output=True)
    (wheel,) = wheels.glob("flyscan-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", str(target), str(wheel)],
                   check=True, capture_output=True)
    return root, target


def _flyscan(installed, *argv, env=None):
    root, target = installed
    # The installed copy comes first on the path; the checkout's own folder is not on it.
    environment = {**os.environ, "PYTHONPATH": str(target), **(env or {})}
    environment.pop("FLYSCAN_MESHES", None) if env is None else None
    return subprocess.run([sys.executable, "-m", "flyscan", *argv], cwd=root,
                          env=environment, capture_output=True, text=True, timeout=300)


def test_the_installed_package_is_the_one_run(installed):
    root, target = installed
    proc = subprocess.run([sys.executable, "-c", "import simulator.parts as p; print(p.__file__)"],
                          cwd=root, env={**os.environ, "PYTHONPATH": str(target)},
                          capture_output=True, text=True, check=True)
    assert Path(proc.stdout.strip()).is_relative_to(target)


def test_demo_scan_from_the_wheel(installed, tmp_path):
    proc = _flyscan(installed, "scan", "--demo", "--fps", "60", "--no-eval",
                    "--out", str(tmp_path / "o"))
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["points"] > 1000
    # The cell file and the status page ship as package data.
    root, target = installed
    assert (target / "simulator" / "data" / "reference_cell.json").is_file()
    assert (target / "service" / "static" / "index.html").is_file()


def test_reference_meshes_are_found_by_option_or_environment(installed, tmp_path):
    # Without a checkout beside it, the installed package asks where the meshes are.
    proc = _flyscan(installed, "bench", "scan", "--out", str(tmp_path / "b"))
    assert proc.returncode == 2
    assert "--meshes DIR" in proc.stderr and "FLYSCAN_MESHES" in proc.stderr
    assert "Traceback" not in proc.stderr
    proc = _flyscan(installed, "bench", "scan", "--meshes", str(tmp_path),
                    "--out", str(tmp_path / "b"))
    assert proc.returncode == 2 and "holds no manifest.json" in proc.stderr
    # Given a folder (here the example parts `flyscan parts` writes), they load from it.
    examples = tmp_path / "parts"
    assert _flyscan(installed, "parts", str(examples)).returncode == 0
    check = ("from simulator.parts import load_reference_part as f; "
             "p = f('bracket'); print(p.units, len(p.mesh.faces), round(p.extents_t.max(), 3))")
    root, target = installed
    out = subprocess.run([sys.executable, "-c", check], cwd=root, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(target),
                              "FLYSCAN_MESHES": str(examples)}, check=True)
    assert out.stdout.split() == ["inch", "416", "70.0"]  # 2.756 inch long: 70 mm
