"""The geometric window: the rows the inspection volume can light, per column."""
import numpy as np
import pytest

from scanner_core.pipeline import PipelineParams, frame_stripe, observe_marker, process_frame
from scanner_core.stripe.extractor import Reason
from scanner_core.types import Frame
from scanner_core.stripe.window import volume_rows, volume_section_b
from simulator.session import simulated_cell

VOLUME = (150.0, 150.0, 100.0)


@pytest.fixture(scope="module")
def pass_frames(cell, block_part):
    sim = simulated_cell(block_part, cell, seed=2)
    sim.camera.open()
    frames = []
    for _ in range(sim.camera.frame_count):
        frame = sim.camera.grab()
        truth = sim.camera.truths[frame.frame_id]
        if len(truth.stripe_columns) > 300:
            frames.append((frame, truth))
    sim.camera.close()
    return frames


def test_section_corners_lie_on_the_sheet_and_in_the_box(cell):
    rotation = cell.gripper_rotation_b
    plane = cell.light_plane_b
    # the TCP 50 mm above the sheet, along its normal: the sheet cuts the box below it
    tcp = plane.offset * plane.normal - 50.0 * plane.normal * np.sign(plane.normal[2] or 1.0)
    corners = volume_section_b(tcp, rotation, VOLUME, 0.0, plane)
    assert len(corners) in (3, 4, 5, 6)
    assert np.abs(corners @ plane.normal - plane.offset).max() < 1e-9
    local = (corners - tcp) @ rotation  # into {T}
    assert np.all(np.abs(local[:, :2]) <= 75.0 + 1e-9)
    assert np.all((local[:, 2] >= -1e-9) & (local[:, 2] <= 100.0 + 1e-9))


def test_every_true_stripe_row_is_inside_and_the_window_is_narrow(cell, pass_frames):
    """Over a pass of the block, all true stripe samples fall inside their frame's window
    (no margin in mm or px needed), while the window spans well under half the rows."""
    inside, total, spans = 0, 0, []
    for _, truth in pass_frames:
        lo, hi = volume_rows(cell.calibration, truth.tcp_b, cell.gripper_rotation_b, VOLUME,
                             margin_mm=0.0, margin_px=0.0)
        c, r = truth.stripe_columns, truth.stripe_rows
        inside += int(((r >= lo[c]) & (r <= hi[c])).sum())
        total += len(r)
        open_ = lo <= hi
        spans.append(np.median(hi[open_] - lo[open_]))
    assert inside == total > 0
    assert np.median(spans) < 0.4 * cell.calibration.camera.height


def test_columns_the_volume_cannot_reach_are_closed(cell):
    plane = cell.light_plane_b
    far = (plane.offset + 1000.0) * plane.normal  # the volume 1 m off the sheet
    lo, hi = volume_rows(cell.calibration, far, cell.gripper_rotation_b, VOLUME)
    assert np.all(lo > hi)


def _frame_with_glare(frame, truth, rows_out, columns):
    """The frame with a line brighter than the stripe (a reflection) at ``rows_out`` in
    ``columns``, and the true stripe erased from the last quarter of them."""
    image = frame.image.astype(np.float64)
    r = np.arange(image.shape[0])[:, None]
    glare = 250.0 * np.exp(-0.5 * ((r - rows_out[None, :]) / 1.5) ** 2)
    erased = columns[3 * len(columns) // 4:]
    image[:, erased] = np.minimum(image[:, erased], 14.0)
    image[:, columns] = np.maximum(image[:, columns], glare)
    return Frame(np.clip(np.round(image), 0, 255).astype(np.uint8), frame.frame_id, frame.t), erased


@pytest.mark.parametrize("policy", ["strongest", "continuity"])
def test_window_rejects_a_reflection_outside_the_volume(cell, pass_frames, policy):
    """A brighter line below the volume's rows (the gripper, a reflection onto the cell) over
    200 stripe columns: without the window the strongest peak takes it; with the robot's
    rotation the window leaves it out, and where the stripe is missing too the column is
    flagged, never guessed."""
    frame, truth = pass_frames[len(pass_frames) // 2]
    cal = cell.calibration
    lo, hi = volume_rows(cal, truth.tcp_b, cell.gripper_rotation_b, VOLUME)
    columns = np.unique(truth.stripe_columns)[50:250]
    rows_out = hi[columns] + 40.0
    glared, erased = _frame_with_glare(frame, truth, rows_out, columns)
    params = PipelineParams(stripe_policy=policy)
    marker = observe_marker(glared.image, cal, params)
    assert marker.valid
    true_row = np.full(cal.camera.width, np.nan)
    true_row[truth.stripe_columns] = truth.stripe_rows
    clean = process_frame(frame, cal, params, marker, cell.gripper_rotation_b)
    kept = np.intersect1d(np.setdiff1d(columns, erased), clean.columns)  # measured when clean
    assert len(kept) > 100

    blind = process_frame(glared, cal, params, marker)
    windowed = process_frame(glared, cal, params, marker, cell.gripper_rotation_b)

    def profile_rows(profile):  # the stripe's rows, back from the triangulated points
        px = cal.camera.project(profile.points_b)
        rows = np.full(cal.camera.width, np.nan)
        rows[profile.columns] = px[:, 1]
        return rows

    blind_rows, window_rows = profile_rows(blind), profile_rows(windowed)
    if policy == "strongest":
        assert np.mean(np.abs(blind_rows[kept] - rows_out[np.isin(columns, kept)]) < 1.0) > 0.9
    # where a column holds several true samples (a step), the clean frame's row is the truth
    on_stripe = np.abs(window_rows[kept] - profile_rows(clean)[kept]) < 0.01
    assert np.nanmax(np.abs(profile_rows(clean)[kept] - true_row[kept])) < 12.0
    assert on_stripe.mean() > 0.98
    assert not np.isin(erased, windowed.columns).any()  # flagged, not guessed


def test_window_reason_is_outside(cell, pass_frames):
    """Where the stripe is erased and only the glare 40 rows beyond the window is left, the
    column holds no stripe: OUTSIDE_WINDOW where the glare lies in rows some column's window
    reaches, NO_PEAK where no window reaches its rows (those are never read)."""
    frame, truth = pass_frames[len(pass_frames) // 2]
    cal = cell.calibration
    lo, hi = volume_rows(cal, truth.tcp_b, cell.gripper_rotation_b, VOLUME)
    columns = np.unique(truth.stripe_columns)[50:250]
    glared, erased = _frame_with_glare(frame, truth, hi[columns] + 40.0, columns)
    params = PipelineParams()
    marker = observe_marker(glared.image, cal, params)
    result, valid, _ = frame_stripe(glared.image, cal, params, marker, cell.gripper_rotation_b)
    read = np.nanmax(np.where(lo <= hi, hi, np.nan)) + 1  # the last row any window reaches
    glare_read = hi[erased] + 40.0 < read - 2.0
    assert np.all(result.reason[erased][glare_read] == Reason.OUTSIDE_WINDOW)
    assert np.all(result.reason[erased][~glare_read] == Reason.NO_PEAK)
    assert not valid[erased].any()