"""Where the methods fail: the quick failure-mode benchmark, and the graceful
behaviour pinned at each break: flags and refusals, never silent garbage.

The cases where the pose is confidently wrong today (no flag, an error above target beyond
3 reported sigma) are pinned as strict xfails with what happens, so that a fix shows up.
"""
import dataclasses
import json

import numpy as np
import pytest

from scanner_core.geometry import Mirror
import flyscan as cli
from scanner_core.scanplan import MIN_PROFILES
from benchmarks import pose_limits as pl
from simulator.cell import load_cell, marker_pixels
from simulator.motion import PassMotion
from simulator.session import misplacement_matrix, run_simulated_scan

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: The targets.
POSE_T_UM, POSE_R_MDEG = pl.TARGET_TRANSLATION_UM, pl.TARGET_ROTATION_MDEG
#: The reference pass of the demo block gives about 225 profiles, 10k points, 120 edge points.
MIN_REFERENCE_FRAMES, MIN_REFERENCE_POINTS, MIN_REFERENCE_EDGES = 200, 5000, 50
#: A free turn reported as held at its start keeps it within this, degrees: the case below
#: once came back 12.7 degrees turned; held, it read 0.096 degrees, then 0.105 once a fit that
#: creeps stops (``pose_fine._settled``) where it ran on to ``max_iterations`` before: what
#: is left is the linear take-back of the free motion, not a drift.
FREE_TURN_HELD_DEG = 0.15
#: The reference cell's scan of the holed cylinder lies 2.0 um off the true surface along
#: its normals (mean signed error, ``ground_truth.accuracy.mean_signed_um``): a pose carries
#: that whole, whatever its sigma; a micrometre of margin.
CLOUD_OFFSET_UM = 3.0


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("pose_limits")
    return out, pl.run(out, quick=True)


@pytest.fixture(scope="module")
def cell():
    return load_cell()


@pytest.fixture(scope="module")
def demo():
    return pl.demo_part()


def row(result, factor, level):
    (found,) = [r for r in result["rows"] if r["factor"] == factor and r["level"] == level]
    return found


# --------------------------------------------------------------------------------------------
# The benchmark's quick run
# --------------------------------------------------------------------------------------------

def test_writes_json_and_png_with_one_row_per_level(bench):
    out, result = bench
    written = json.loads((out / "pose_limits.json").read_text())
    assert written == json.loads(json.dumps(result))
    assert (out / "pose_limits.png").read_bytes()[:8] == PNG_MAGIC
    for factor in pl.FACTORS:
        levels = [r["level"] for r in written["rows"] if r["factor"] == factor.name]
        assert levels == list(factor.quick_levels), factor.name
        assert factor.name in written["summary"]["factors"]
    for key in ("cpu_count", "python", "date"):
        assert key in written["machine"]


def test_reference_pass_is_within_target(bench):
    _, result = bench
    ref = row(result, "noise", 3)
    assert ref["frames"] >= MIN_REFERENCE_FRAMES
    assert ref["points"] >= MIN_REFERENCE_POINTS
    assert ref["edges"]["count"] >= MIN_REFERENCE_EDGES
    assert ref["edges"]["outlier_fraction"] <= pl.TARGET_EDGE_OUTLIERS
    pose = ref["pose"]
    assert pose["flags"] == [] and pose["observable"]
    assert pose["translation_um"] <= POSE_T_UM
    assert pose["rotation_mdeg"] <= POSE_R_MDEG
    assert ref["verdict"] in pl.USABLE


def test_every_factor_reaches_its_break_within_the_quick_levels(bench):
    _, result = bench
    for name, summary in result["summary"]["factors"].items():
        brk = summary["pose_break"]
        assert brk is not None, name
        assert brk["verdict"] in pl.VERDICTS
        assert summary["first_flagged_or_refused"] is not None, name
        assert summary["statement"].startswith("the pose breaks at"), summary["statement"]


def test_the_last_level_of_each_factor_is_refused_or_flagged(bench):
    _, result = bench
    for factor in pl.FACTORS:
        last = row(result, factor.name, factor.quick_levels[-1])
        assert last["verdict"] in ("refused", "flagged"), (factor.name, last["verdict"])


# --------------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------------

def test_extreme_noise_refuses_or_flags_the_pose(bench):
    _, result = bench
    worst = row(result, "noise", 25)
    # The marker drowns: the pass hardly triggers (the stripe's floors follow the noise, so
    # what frames are placed keep their stripe), and what pose is made of it says not to act
    # on it (measured: 343 points against 10k, flagged).
    assert worst["points"] < 0.1 * row(result, "noise", 3)["points"]
    assert worst["verdict"] in ("refused", "flagged"), worst["pose"]


def test_noisy_pose_is_flagged_or_bounded_by_its_sigma(bench):
    """Once pinned as failing: at 15 DN read noise (5x the reference) the pose came back
    unflagged with ty off by 22 um at 3.8 reported sigma (before the pixel-area stripe model
    kept the drop-out edges, and before motions seen by too few profiles counted as free)."""
    _, result = bench
    noisy = row(result, "noise", 15)
    assert noisy["verdict"] in pl.GRACEFUL, noisy["pose"]


# --------------------------------------------------------------------------------------------
# Pass speed: fewer profiles per mm
# --------------------------------------------------------------------------------------------

def test_cli_refuses_a_pass_with_too_few_profiles(tmp_path, capsys, bench):
    _, result = bench
    fast = row(result, "speed", 2500)
    assert fast["profiles_on_part"] < MIN_PROFILES
    assert "raise --fps" in fast["cli_refusal"]
    out = tmp_path / "scan"
    status = cli.main(["scan", "--demo", "--speed", "2500", "--out", str(out)])
    assert status == 2
    assert "too few" in capsys.readouterr().err
    assert not out.exists()


def test_too_few_profiles_are_refused_or_flagged_without_the_cli(cell, demo):
    """Only the command line refuses a pass with too few profiles; the library and the service
    flag the pose ("sparse"). Once pinned as failing: at 1500 mm/s (9.3 mm apart, 4.3 profiles
    on the block) the pose came back unflagged with ty off by 40 um at 10 reported sigma."""
    trial = pl.TRIALS[0]
    sparse = pl.run_level("speed", 1500, demo, cell, misplacement=trial["misplacement"],
                          seed=trial["seed"], evaluate=False)
    assert sparse["cli_refusal"] is not None
    assert sparse["pose_verdict"] in pl.GRACEFUL, sparse["pose"]


def test_sparse_profiles_the_cli_accepts_give_an_honest_pose(bench):
    _, result = bench
    sparse = row(result, "speed", 1000)
    assert sparse["cli_refusal"] is None
    assert sparse["frames"] > 0
    assert sparse["verdict"] in pl.GRACEFUL, sparse["pose"]


def test_sparse_profiles_never_give_a_confidently_wrong_pose(cell, demo):
    """Once pinned as failing: at 700 mm/s (4.3 mm between profiles, 9 profiles on the 40 mm
    block: the command line accepts it) the demo block misplaced by (-2.5, 2, -0.5) mm and
    -4 deg about z_T, camera seed 1, came back unflagged with ty off by 0.93 mm at 7.0
    reported sigma: the fit settled about a millimetre off along the pass."""
    trial = pl.TRIALS[1]
    sparse = pl.run_level("speed", 700, demo, cell, misplacement=trial["misplacement"],
                          seed=trial["seed"], evaluate=False)
    assert sparse["verdict"] in pl.GRACEFUL, sparse["pose"]


# --------------------------------------------------------------------------------------------
# Saturation
# --------------------------------------------------------------------------------------------

def test_saturated_stripe_keeps_an_honest_pose(bench):
    """Clipped stripes are measured from their flanks, so a stripe at 4x full scale
    keeps its points and an honest pose (measured: 24.5 um off along tx at 2.9 reported sigma
    on one trial of the full run, within target on the others). The plateaus widen with the
    peak; the width gate follows the frame, so at 200x (50 000 DN) a third of the
    points are still measured (3595 of 10425 on the quick trial) and the pose, 126 um off, says
    so in its sigma; at 800x (945 points, no edge) the pose is flagged, never silently wrong."""
    _, result = bench
    reference = row(result, "saturation", 200)
    bright = row(result, "saturation", 1000)
    assert bright["points"] >= 0.95 * reference["points"]
    assert bright["verdict"] in pl.GRACEFUL, bright["pose"]
    clipped = row(result, "saturation", 200000)
    assert clipped["verdict"] in ("refused", "flagged"), clipped["pose"]
    assert clipped["points"] < 0.2 * reference["points"]


def test_saturated_stripe_gives_no_edge_outliers(bench):
    """Once pinned as failing: at a stripe peak of 240 DN 12 % of the edge points lay beyond
    0.5 mm of any CAD edge (edge RMS 277 um), before steps were placed where the near side's
    stripe falls to half its level."""
    _, result = bench
    bright = row(result, "saturation", 1000)
    assert bright["edges"]["outlier_fraction"] <= pl.TARGET_EDGE_OUTLIERS


# --------------------------------------------------------------------------------------------
# The marker hidden in a mirror
# --------------------------------------------------------------------------------------------

def test_hiding_narrows_the_true_mirror_strip_only(cell, demo):
    half = pl.condition("marker", 0.5, demo, cell)[1]
    assert half.calibration.camera is cell.calibration.camera
    assert half.calibration.mirrors[0] == cell.calibration.mirrors[0]
    c0, c1 = half.calibration.mirrors[1].columns
    assert c0 == cell.calibration.mirrors[1].columns[0]
    assert c1 < cell.calibration.mirrors[1].columns[1]
    # Where the TCP is as the part enters the sheet and as it leaves: hidden, then seen.
    y_t = demo.vertices_t()[:, 1]
    motion = PassMotion(cell.pass_profile)
    times = np.linspace(0.0, motion.duration_s, 4001)
    tcp = motion.tcp_position(times)
    enter, leave = (tcp[np.searchsorted(tcp[:, 1], y)] for y in (y_t.min(), y_t.max()))
    columns = marker_pixels(cell, np.stack([enter, leave]))[:, 2, 0]
    assert not c0 <= columns[0] <= c1 - 1
    assert c0 <= columns[1] <= c1 - 1
    both = pl.condition("marker", 2.0, demo, cell)[1]
    assert [m.columns[0] == m.columns[1] for m in both.calibration.mirrors] == [True, True]


def test_marker_hidden_in_the_right_mirror_still_places_frames(bench):
    _, result = bench
    reference, hidden = row(result, "marker", 0.0), row(result, "marker", 1.0)
    # Frames are placed from the direct view and the left mirror alone.
    assert hidden["frames"] >= 0.9 * reference["frames"]
    assert hidden["points"] >= 0.9 * reference["points"]
    assert hidden["frames_unplaced"] <= 0.05 * hidden["frames"]
    assert hidden["verdict"] in pl.GRACEFUL, hidden["pose"]


def test_marker_hidden_in_the_left_mirror_still_places_frames(cell, demo):
    cal = cell.calibration
    left = cal.mirrors[0]
    truth = dataclasses.replace(cell, calibration=dataclasses.replace(
        cal, mirrors=(Mirror(left.plane, (left.columns[0], left.columns[0])), cal.mirrors[1])))
    trial = pl.TRIALS[0]
    scan, report = run_simulated_scan(demo, truth, calibration=cal,
                                      misplacement=misplacement_matrix(trial["misplacement"]),
                                      seed=trial["seed"], evaluate=False)
    assert report["frames"] >= MIN_REFERENCE_FRAMES
    assert report["frames_unplaced"] <= 0.05 * report["frames"]
    figures = pl.pose_figures(report)
    assert pl.pose_verdict(figures) in pl.GRACEFUL, figures


def test_marker_hidden_in_both_mirrors_refuses(bench):
    _, result = bench
    blind = row(result, "marker", 2.0)
    assert blind["frames"] == 0 and blind["points"] == 0
    assert blind["verdict"] == "refused"


def test_half_scanned_part_is_flagged_or_bounded(cell, demo):
    """The marker hidden in the right mirror throughout and in the left one for the first half
    of the part: the trigger (two views) starts half-way. The pose says so ("partial scan").
    Once pinned as failing: 100 of 225 profiles, and the pose of the half-scanned demo block
    came back unflagged with rz off by 97 mdeg at 3.5 sigma and tx by 20 um at 3.8 sigma."""
    trial = pl.TRIALS[1]
    half = pl.run_level("marker", 1.5, demo, cell, misplacement=trial["misplacement"],
                        seed=trial["seed"], evaluate=False)
    assert half["frames"] > 0
    assert half["verdict"] in pl.GRACEFUL, half["pose"]


# --------------------------------------------------------------------------------------------
# Symmetry
# --------------------------------------------------------------------------------------------

def test_symmetric_part_rejects_a_hole_off_the_part():
    with pytest.raises(ValueError, match="offset_mm"):
        pl.symmetric_part(pl.SYM_RADIUS_MM)


def test_cylinder_turns_freely_about_z_and_is_placed_at_its_axis(bench):
    _, result = bench
    cylinder = row(result, "symmetry", 0.0)
    pose = cylinder["pose"]
    assert pose["free_axes"] == ["about z_T"]
    assert not pose["observable"]
    assert any("not observable" in f for f in pose["flags"])
    assert cylinder["verdict"] == "flagged"
    # Whatever the turn, the axis is where the truth puts it.
    assert pose["free_axis_error_um"] <= POSE_T_UM
    # A hole 12 mm off the axis fixes the turn: no motion is free and the error about z_T is
    # bounded by its sigma; whether that sigma is within the act tolerance (observable, issue
    # 27) is the tolerance's call: the quick bench's scan holds it to 65 mdeg, beyond 0.1/3.
    # Beyond their sigmas, the errors are at most the cloud's own offset: this cell's scan
    # lies 2.0 um off the surface along its normals (its mean signed error, against the
    # truth), which moves z_T whole; its calibration is the truth, and carries no measured
    # uncertainty for a term of the sigma to hold it.
    holed = row(result, "symmetry", 12.0)["pose"]
    assert holed["free_axes"] == [] and abs(holed["sigmas"][5]) <= 3.0
    assert holed["unbounded_rotation_mdeg"] == 0.0
    assert holed["unbounded_translation_um"] <= CLOUD_OFFSET_UM


def test_cylinder_free_turn_is_held_at_its_start(cell):
    """A free turn is held where it started. Once pinned as failing: the cylinder misplaced by
    (1.5, -1, 0.5) mm without a turn came back turned by 12.7 deg about its axis, so the {T}
    origin's tx, ty, reported with a 6 and 5 um std, were off by 0.19 and 0.35 mm."""
    cylinder = pl.symmetric_part(0.0)
    _, report = run_simulated_scan(cylinder, cell,
                                   misplacement=misplacement_matrix([1.5, -1.0, 0.5, 0, 0, 0]),
                                   seed=0, evaluate=False)
    pose = report["pose"]
    assert [a["label"] for a in pose["free_axes"]] == ["about z_T"]
    assert abs(pose["misplacement"]["rotation_deg"][2]) <= FREE_TURN_HELD_DEG
