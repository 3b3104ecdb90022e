"""``flyscan bench real``'s scoring on photographs of its own making: a green laser line across
a chessboard seen from five poses, drawn where the light plane meets the board, so that the
line, the board's plane and the light plane are known; the set named as a cloned repository
would be, the bench's own PhotoSet for it."""

import dataclasses
import json

import cv2
import numpy as np
import pytest

from benchmarks import real_photos, synthesised_photos
from benchmarks.real_photos import PhotoSet, score_set
from flyscan import main

FOCAL_PX, WIDTH, HEIGHT = 900.0, 640, 480
PATTERN, PITCH_MM = (9, 6), 15.0
SET = PhotoSet(name="synthetic green line", repository="tests/synthetic", commit="0" * 40,
               laser="green", along="rows", target="chessboard", pattern=PATTERN,
               pitch_mm=PITCH_MM, laser_images="views/view*.png",
               camera=(FOCAL_PX, FOCAL_PX, WIDTH / 2, HEIGHT / 2, 0.0, 0.0, 0.0, 0.0, 0.0))
# The light plane in the camera: n . X = d (mm), a sheet from above the camera seen nearly
# edge-on, so that the line runs across the columns.
LIGHT_N = np.array([0.0, 1.0, -0.25]) / np.hypot(1.0, 0.25)
LIGHT_D = LIGHT_N @ np.array([0.0, 10.0, 300.0])


def _board_texture(scale):
    """The printed board (well exposed: nothing clips under the line): squares of PITCH_MM, a
    square's margin of white, ``scale`` px/mm;
    (image, the board's origin (its first inner corner) in the texture, px)."""
    squares = (PATTERN[0] + 1, PATTERN[1] + 1)
    side = int(round(PITCH_MM * scale))
    tex = np.full(((squares[1] + 2) * side, (squares[0] + 2) * side), 170, np.uint8)
    for i in range(squares[0]):
        for j in range(squares[1]):
            if (i + j) % 2 == 0:
                tex[(j + 1) * side:(j + 2) * side, (i + 1) * side:(i + 2) * side] = 25
    return tex, 2 * side


def _view(rvec, tvec, rng, fade_from=WIDTH):
    """One RGB photograph: the board under white light, the green line on it (none from
    column ``fade_from`` on: a line that fades out)."""
    k = np.array([[FOCAL_PX, 0, WIDTH / 2], [0, FOCAL_PX, HEIGHT / 2], [0, 0, 1.0]])
    rot, _ = cv2.Rodrigues(rvec)
    scale = 8.0
    tex, origin = _board_texture(scale)
    # texture px -> board mm -> image
    to_mm = np.array([[1 / scale, 0, -origin / scale], [0, 1 / scale, -origin / scale], [0, 0, 1]])
    homography = k @ np.column_stack([rot[:, 0], rot[:, 1], tvec]) @ to_mm
    board = cv2.warpPerspective(tex, homography, (WIDTH, HEIGHT), flags=cv2.INTER_AREA,
                                borderValue=90)
    inside = cv2.warpPerspective(np.ones_like(tex), homography, (WIDTH, HEIGHT)) > 0
    # the line: per column, the row whose ray meets the board where the light plane is
    n_b = rot[:, 2]
    d_b = n_b @ tvec
    v = np.linspace(0, HEIGHT - 1, 8 * HEIGHT)
    line = np.full(WIDTH, np.nan)
    for u in range(WIDTH):
        rays = np.linalg.solve(k, np.vstack([np.full_like(v, u), v, np.ones_like(v)]))
        points = rays * (d_b / (n_b @ rays))
        f = LIGHT_N @ points - LIGHT_D
        cross = np.nonzero(np.diff(np.sign(f)))[0]
        if cross.size:
            i = cross[0]
            line[u] = v[i] - f[i] * (v[i + 1] - v[i]) / (f[i + 1] - f[i])
    rows = np.arange(HEIGHT)[:, None]
    stripe = 70.0 * np.exp(-0.5 * ((rows - line[None, :]) / 1.3) ** 2)
    stripe = np.where(inside & np.isfinite(stripe) & (np.arange(WIDTH) < fade_from), stripe, 0.0)
    grey = board.astype(np.float64)
    rgb = np.stack([grey + 0.10 * stripe, grey + stripe, grey + 0.15 * stripe], axis=-1)
    rgb += rng.normal(0.0, 1.5, rgb.shape)
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)


POSES = [((0.25, -0.2, 0.02), (-60.0, -30.0, 310.0)), ((-0.2, 0.25, -0.05), (-70.0, -45.0, 330.0)),
         ((0.3, 0.15, 0.1), (-55.0, -40.0, 300.0)), ((-0.15, -0.3, 0.0), (-65.0, -25.0, 320.0)),
         ((0.05, 0.35, -0.08), (-60.0, -50.0, 340.0))]


def _write_set(folder, name, fade_from=WIDTH):
    views = folder / name / "views"
    views.mkdir(parents=True)
    rng = np.random.default_rng(3)
    for i, (r, t) in enumerate(POSES):
        rgb = _view(np.array(r), np.array(t), rng, fade_from)
        assert cv2.imwrite(str(views / f"view{i}.png"), rgb[:, :, ::-1])


@pytest.fixture(scope="module")
def photographs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sets")
    _write_set(folder, "synthetic")
    return folder


def test_the_bench_scores_a_known_line_and_plane(photographs):
    figures = score_set(SET, photographs / "synthetic")
    assert figures["scored"] == 5
    fly, base = figures["flyscan"], figures["baseline"]
    assert fly["measured_share"] >= 0.98
    assert fly["beyond_1px_share"] == 0.0
    # the line is drawn exactly: what is left is the stripe's noise and the board's edges
    assert fly["rms_line_px"] < 0.08
    assert fly["rms_line_px"] < base["rms_line_px"]
    # the same plane in every view, 300 mm away at 900 px: 0.05 px is about 17 um
    assert fly["rms_plane_um"] < 40.0
    assert fly["whole_pixel_share"] < 0.07
    # the line is seen in every profile on the target, and measured in each
    assert figures["profiles_visible"] >= 0.98 * figures["profiles_on_target"]
    assert fly["measured_visible_share"] >= 0.99
    # the naive peak finder on flyscan's own signal: the same line, scored alike
    assert figures["baseline_on_flyscan_signal"]["rms_line_px"] < 2 * base["rms_line_px"]


def test_a_profile_where_no_stripe_shows_is_not_counted_as_visible(tmp_path):
    """The same photographs with the line gone from column 400 on: the profiles there are on
    the target but show nothing, and are not held against either method."""
    _write_set(tmp_path, "synthetic", fade_from=400)
    whole = score_set(SET, tmp_path / "synthetic")
    _write_set(tmp_path / "full", "synthetic")
    full = score_set(SET, tmp_path / "full" / "synthetic")
    assert whole["profiles_on_target"] == full["profiles_on_target"]
    assert whole["profiles_visible"] < 0.8 * full["profiles_visible"]
    assert whole["flyscan"]["measured_visible_share"] >= 0.99
    # and where nothing shows, nothing is measured
    seen = whole["profiles_visible"] / whole["profiles_on_target"]
    assert whole["flyscan"]["measured_share"] <= seen + 0.01


def test_flyscan_bench_real_writes_its_figures_and_names_what_is_missing(photographs, tmp_path,
                                                                         monkeypatch, capsys):
    monkeypatch.setattr(real_photos, "SETS", real_photos.SETS[:1] + (SET,))
    dim = "mono, dim line 15 DN over 1 DN of noise"
    monkeypatch.setattr(synthesised_photos, "CASES", {dim: synthesised_photos.CASES[dim]})
    assert main(["bench", "real", str(photographs), "--out", str(tmp_path), "--quick"]) == 0
    result = json.loads((tmp_path / "real.json").read_text())
    assert [s["name"] for s in result["sets"]] == [SET.name]
    # the synthesised dim line: every column measured, the naive peak finder at 20 DN few
    assert list(result["synthesised"]) == [dim]
    assert result["synthesised"][dim]["flyscan"]["measured"] > 0.99
    assert result["synthesised"][dim]["baseline"]["measured"] < 0.5
    assert (tmp_path / "real_synthesised.png").stat().st_size > 10_000
    assert result["missing"] and "hjamal3/Light-Stripe-Calibration" in result["missing"][0]
    assert (tmp_path / "real.png").stat().st_size > 10_000
    assert "not scored (missing): clone https://github.com/hjamal3" in capsys.readouterr().err
    assert main(["bench", "real", "--out", str(tmp_path)]) == 2
    assert "needs the folder holding clones of https://github.com/" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["bench", "real", str(empty), "--out", str(tmp_path)]) == 2
    assert "none of the sets is under" in capsys.readouterr().err
    assert main(["bench", "stripe", str(empty), "--out", str(tmp_path)]) == 2
    assert "bench stripe takes no folder" in capsys.readouterr().err
    assert main(["bench", "real", str(tmp_path / "nowhere"), "--out", str(tmp_path)]) == 2
    assert "is not a folder" in capsys.readouterr().err
