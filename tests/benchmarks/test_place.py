"""bench place, quick: the closed loop on the demo block in the calibrated realistic cell, its
figures against the truth; the placed error and the z-scores on hand-computed cases."""
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks.place import TAUGHT_PLACE, as_pose_result, placed_error, run
from benchmarks.pose.trials import score
from scanner_core.pose.registration import PoseParams


def _rigid(rotvec_deg=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    m[:3, 3] = t
    return m


NOMINAL = _rigid((0.0, 0.0, 90.0), (5.0, -3.0, 40.0))  # ^T X_P,nom


def test_placed_error_of_a_translated_pose():
    # The pose reads the part 10 um off along x_T: the corrected place moves it back by 10 um
    # everywhere, no turn.
    truth = _rigid((1.0, -2.0, 3.0), (2.0, 1.0, -1.0)) @ NOMINAL
    pose = _rigid(t=(0.010, 0.0, 0.0)) @ truth
    err = placed_error(TAUGHT_PLACE, pose, NOMINAL, truth, (7.0, 8.0, 9.0))
    assert err["at_point_um"] == pytest.approx(10.0, abs=1e-6)
    assert err["at_origin_um"] == pytest.approx(10.0, abs=1e-6)
    assert err["angle_mdeg"] == pytest.approx(0.0, abs=1e-6)


def test_placed_error_of_a_turned_pose():
    # The pose turned by 0.05 degrees about z_T at the TCP: a point a from the z_T axis in {T}
    # lands 2 a sin(theta / 2) off; the {P} origin (at (5, -3, 40) in {T}) likewise.
    theta = 0.05
    truth = NOMINAL
    pose = _rigid((0.0, 0.0, theta)) @ truth
    p = np.linalg.inv(NOMINAL) @ np.array([30.0, 0.0, 12.0, 1.0])  # (30, 0, 12) in {T}
    err = placed_error(TAUGHT_PLACE, pose, NOMINAL, truth, p[:3])
    chord = 2.0 * np.sin(np.radians(theta) / 2.0) * 1e3
    assert err["at_point_um"] == pytest.approx(30.0 * chord, rel=1e-9)
    assert err["at_origin_um"] == pytest.approx(np.hypot(5.0, 3.0) * chord, rel=1e-9)
    assert err["angle_mdeg"] == pytest.approx(theta * 1e3, rel=1e-9)


def test_z_scores_of_a_pose_entry():
    # A pose entry 6 um off along x_T and 3 mdeg about y_T, sigmas 2 um and 1 mdeg: z = 3 and
    # 3; a free axis (no sigma) has no z.
    truth = NOMINAL
    pose = _rigid((0.0, 0.003, 0.0), (0.006, 0.0, 0.0)) @ truth
    entry = {"matrix": pose.tolist(), "time_ms": 1.0, "coarse": False, "iterations": 3,
             "flags": [], "observable": False, "free_axes": [{"label": "along z_T"}],
             "inlier_fraction": 1.0, "rms_mm": 0.001,
             "std": {"tx_mm": 0.002, "ty_mm": 0.001, "tz_mm": None, "rx_deg": 0.001,
                     "ry_deg": 0.001, "rz_deg": 0.001}}
    z = score(as_pose_result(entry), truth)["z"]
    assert z[0] == pytest.approx(3.0, rel=1e-6)
    assert z[1] == pytest.approx(0.0, abs=1e-6)
    assert not np.isfinite(z[2])
    assert z[4] == pytest.approx(3.0, rel=1e-6)
    assert z[3] == pytest.approx(0.0, abs=1e-6) and z[5] == pytest.approx(0.0, abs=1e-6)


def _row(std, *, reasons=(), free=(), error=(1.0, -2.0, 0.5, 3.0, -1.0, 2.0)):
    return {"scanned": True, "std_um_mdeg": list(std), "act_reasons": list(reasons),
            "free_axes": list(free), "translation_um": list(error[:3]),
            "rotation_mdeg": list(error[3:]), "act": False}


def test_act_at_another_tolerance():
    from benchmarks.place import act_at

    row = _row([10.0, 20.0, 5.0, 10.0, 12.0, 30.0],
               reasons=["rz: 3 sigma 0.09 degrees, beyond the act tolerance 0.05 degrees"])
    assert not act_at(row, 0.05, 0.05)          # 3 sigma of ty 60 um, of rz 90 mdeg
    assert act_at(row, 0.1, 0.1) and act_at(row, 0.2, 0.2)
    # a reason the tolerance does not change, a free axis, a rival: never acted on
    assert not act_at(_row([1.0] * 6, reasons=["partial scan: 80 % of the part"]), 0.2, 0.2)
    assert not act_at(_row([1.0] * 6, free=["along y_T"]), 0.2, 0.2)
    assert not act_at(_row([1.0] * 6, reasons=["ambiguous: 1 other minimum beyond"]), 0.2, 0.2)


def test_availability_counts_the_right_picks_acted_on():
    from benchmarks.place import availability

    right = dict(_row([5.0] * 6, error=(10.0, -20.0, 5.0, 10.0, -15.0, 30.0)), act=True)
    refused = _row([50.0] * 6, error=(1.0,) * 6,
                   reasons=["tx: 3 sigma 0.15 mm, beyond the act tolerance 0.1 mm"])
    wrong = dict(_row([5.0] * 6, error=(40.0,) + (0.0,) * 5), act=True)  # beyond a third
    free = dict(_row([5.0] * 6, error=(0.0,) * 6, free=["about z_T"]))
    out = availability([right, refused, wrong, free], (0.1, 0.1))
    assert out["right"] == 2 and out["acted_on"] == 1 and out["share"] == 0.5
    assert out["refused_for"] == {"3 sigma beyond the act tolerance": 1}


def test_quick_bench_place(tmp_path):
    result = run(tmp_path, quick=True, picks=3, progress=lambda line: None)
    assert (tmp_path / "place.png").stat().st_size > 10_000
    on_disk = json.loads((tmp_path / "place.json").read_text())
    assert on_disk["summary"] == json.loads(json.dumps(result["summary"]))
    assert set(result["summary"]["targets"]) == {
        "placed_p99_um", "placed_p99_mdeg", "acted_outside_tolerance", "z_rms_lowest",
        "z_rms_highest", "beyond_3_sigma_share", "availability"}
    picks = result["picks"]
    assert len(picks) == 3 and all(p["scanned"] for p in picks)
    assert all(p["cell"] == 1 and set(p["std_terms"]) >= {"profiles", "marker", "light_plane"}
               for p in picks)
    summary = result["summary"]
    # the errors' RMS in sigmas, recomputed from the picks
    z = np.array([p["z"] for p in picks], dtype=float)
    for i, axis in enumerate(("tx", "ty", "tz", "rx", "ry", "rz")):
        assert summary["sigma_calibration"]["z_rms"][axis] == pytest.approx(
            np.sqrt(np.nanmean(z[:, i] ** 2)), rel=1e-4)
    levels = summary["against_tolerance"]
    assert [lv["tolerance"]["mm"] for lv in levels] == [0.05, 0.1, 0.2]
    # a wider tolerance never acts on fewer picks
    assert levels[0]["acted_on"] <= levels[1]["acted_on"] <= levels[2]["acted_on"]
    assert levels[1]["acted_on"] == sum(p["act"] for p in picks)
    block = result["per_part"]["block"]
    for key in ("act_rate", "placed_um", "placed_mdeg", "max_abs_z_acted",
                "max_abs_z_observable", "act_by_level", "act_blocked_by", "pose_ms"):
        assert key in block, key
    params = PoseParams()
    acted = [p for p in picks if p["act"]]
    assert acted, "the demo block's picks are acted on"
    for p in acted:
        # Against the truth: the placed part within the act tolerance, and its turn that of
        # the pose's error (the correction conjugates it).
        assert p["placed"]["at_point_um"] <= params.act_tolerance_mm * 1e3
        assert p["placed"]["at_origin_um"] <= params.act_tolerance_mm * 1e3
        assert p["placed"]["angle_mdeg"] <= params.act_tolerance_deg * 1e3
        assert p["placed"]["angle_mdeg"] == pytest.approx(p["rotation_angle_mdeg"], abs=1e-3)
        assert not p["outside_tolerance"]
        assert p["pose_ms"] > 0 and p["timings_ms"]["pose"] >= p["pose_ms"] * 0.9
    assert result["summary"]["targets"]["acted_outside_tolerance"]["met"]
    assert block["acted_on"] == len(acted)
    assert block["placed_um"]["max"] == pytest.approx(
        max(p["placed"]["at_point_um"] for p in acted), abs=1e-5)
