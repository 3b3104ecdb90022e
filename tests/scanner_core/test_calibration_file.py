"""The versioned calibration file: versions, distortion, provenance, image size."""
import json

import numpy as np
import pytest

from scanner_core.geometry.calibration import (CALIBRATION_VERSION, Calibration, CalibrationError,
                                               load_calibration, save_calibration)
from simulator.cell import load_cell
from simulator.effects import realistic_cell


def test_round_trip_keeps_distortion_clock_and_provenance(tmp_path):
    cal = realistic_cell(load_cell(), seed=1).calibration
    from dataclasses import replace
    cal = replace(cal, clock_offset_s=0.0123, provenance={"cell": "test", "observations": 3})
    save_calibration(tmp_path / "c.json", cal)
    back = load_calibration(tmp_path / "c.json")
    assert back.camera.distortion == cal.camera.distortion and back.camera.distorted
    assert back.clock_offset_s == 0.0123
    assert back.provenance == {"cell": "test", "observations": 3}
    assert json.loads((tmp_path / "c.json").read_text())["version"] == CALIBRATION_VERSION


def test_a_version_1_file_reads_as_an_ideal_lens():
    data = load_cell().calibration.to_dict()
    for key in ("version", "clock_offset_s", "provenance"):
        data.pop(key)
    data["camera"].pop("distortion")
    cal = Calibration.from_dict(data)
    assert not cal.camera.distorted and cal.clock_offset_s == 0.0


@pytest.mark.parametrize("version", [3, 0, "2", True])
def test_another_version_is_refused(version):
    data = load_cell().calibration.to_dict() | {"version": version}
    with pytest.raises(CalibrationError, match="version"):
        Calibration.from_dict(data)


@pytest.mark.parametrize("field, value, name", [
    ("distortion", None, "camera.distortion"), ("distortion", [0.1, 0.2], "camera.distortion"),
    ("distortion", ["a", 0, 0, 0, 0], "camera.distortion")])
def test_a_bad_distortion_is_named(field, value, name):
    data = load_cell().calibration.to_dict()
    if value is None:
        data["camera"].pop(field)
    else:
        data["camera"][field] = value
    with pytest.raises(CalibrationError, match=name.replace(".", r"\.")):
        Calibration.from_dict(data)


def test_a_mistyped_clock_offset_is_named():
    data = load_cell().calibration.to_dict() | {"clock_offset_s": "soon"}
    with pytest.raises(CalibrationError, match="clock_offset_s"):
        Calibration.from_dict(data)


def test_another_image_size_is_refused():
    cal = load_cell().calibration
    cal.check_image_size(1920, 1200)
    with pytest.raises(CalibrationError, match="1920 x 1200 images, the camera gives 1280 x 1024"):
        cal.check_image_size(1280, 1024)


@pytest.mark.parametrize("seed", [None, 3, 17, 41, 88])
def test_every_cell_s_own_calibration_is_one_a_cell_can_have(seed):
    from dataclasses import replace

    from scanner_core.geometry.calibration import check_cell_geometry, check_marker_track
    from simulator.calsession import plan_geometry
    from simulator.cell import load_cell
    from simulator.effects import realistic_cell

    cell = load_cell(perturb_seed=seed)
    if seed is not None:
        cell = realistic_cell(cell, seed=seed)
    check_cell_geometry(cell.calibration)
    check_marker_track(cell.calibration, plan_geometry(cell))
    # the same cell's camera turned 17 degrees about its axis and moved 60 mm: its
    # views no longer meet the pass's LED
    cam = cell.calibration.camera
    turn = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0],
                     [0.0, 0.0, 1.0]])
    moved = replace(cell.calibration, camera=replace(cam, rotation=turn @ cam.rotation,
                                                     origin=cam.origin + [60.0, 0.0, 0.0]))
    with pytest.raises(CalibrationError, match="triangulated"):
        check_cell_geometry(moved)
        check_marker_track(moved, plan_geometry(cell))
