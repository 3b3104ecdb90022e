"""The stripe extractor on real photographs of a laser line crossing a planar target.

Public sets of photographs, each scored against its own target: the target's pose in every
photograph (its corners or dots found by OpenCV, ``solvePnP`` with the set's camera) puts the
target's plane in the camera, so the stripe on it must be a straight line in the undistorted
image and, over a set's photographs, its points must lie on one light plane. Per photograph
the laser's signal is its colour excess (``scanner_core.stripe.extractor.stripe_signal``, the same for
both methods); flyscan's ``extract`` as the pipeline calls it on a colour frame (its defaults
and ``shoulders``) is scored beside a naive peak finder (per
column, the argmax and a 3-point parabola, where the argmax reaches ``BASELINE_DN`` of excess).

Per set: the profiles on the target (columns where the line crosses it), the share of them each
method measures, the RMS about the line (px, undistorted) and about the light plane (um, where
the set gives the target's size), the share more than 1 px off the line (each method's own line: a straight line is what the
geometry asks, whatever either method's offset from the other), the share of rows
within 0.02 px of a whole pixel (4 % unbiased), and the profiles the baseline gets right (within
0.5 px) that flyscan gets wrong.

The photographs are not in this repository (their repositories state no licence): clone each
repository named in ``SETS`` into one folder and give it to ``flyscan bench real DIR``.
Beside them the bench reports the failures the photographs showed, synthesised with their
truth (``benchmarks.synthesised_photos``, ``real_synthesised.png``).
"""
from __future__ import annotations

import glob
import math
import pathlib
import re
import sys
from dataclasses import dataclass

import cv2
import numpy as np

from benchmarks.naive_peaks import BASELINE_DN, baseline_rows, naive_signal
from benchmarks.results import write_json
from benchmarks.synthesised_photos import SEEDS, run_cases
from scanner_core.stripe.extractor import (EXCESS_OFFSET_DN, estimate_noise, extract,
                                           stripe_signal)
from simulator.line_photos import PRESENT_SNR

__all__ = ["PhotoSet", "SETS", "score_set", "run"]

#: A row is within chance of a whole pixel when its fraction is under this (4 % unbiased).
WHOLE_PIXEL_PX = 0.02
#: Off the line by more than this a profile is an outlier; by more than GROSS_PX it is not on
#: the line at all (a reflection, the target's edge) and stays out of the RMS.
OUTLIER_PX = 1.0
GROSS_PX = 3.0
#: The baseline "gets a profile right" within this of the line.
RIGHT_PX = 0.5
#: Columns whose line point lies closer than this to the target's outline are not counted.
OUTLINE_MARGIN_PX = 4.0
#: A profile on the target shows the stripe (a person sees it) where the naive signal's
#: largest value within VISIBLE_NEAR_PX of the line stands VISIBLE_SIGMAS of the frame's noise
#: over the column's medians VISIBLE_RING_PX away from the line, on each side (an
#: overexposed line's excess is hollow across its white core and its red halo spreads a
#: dozen rows: the core's maximum is read that wide, the sides beyond the halo).
#: VISIBLE_SIGMAS is the synthesised photographs' own (``simulator.line_photos.PRESENT_SNR``:
#: the extractor's floor is 5 sigma, a peak at 10 stands clear of the noise); the shares
#: measured at each of VISIBLE_CURVE are reported too.
VISIBLE_SIGMAS = PRESENT_SNR
VISIBLE_CURVE = (5.0, 10.0, 20.0)
VISIBLE_NEAR_PX = 8
VISIBLE_RING_PX = (15, 45)
#: The methods scored: flyscan's pipeline, the naive peak finder on the photograph's colour
#: excess (the issue's baseline), and the naive peak finder on flyscan's signal (what the
#: signal alone is worth).
METHODS = ("flyscan", "baseline", "baseline_on_flyscan_signal")


@dataclass(frozen=True)
class PhotoSet:
    """One public set of photographs and what scoring it needs.

    Attributes
    ----------
    name : str
    repository, commit : str
        Where the photographs are: ``https://github.com/{repository}`` at ``commit``; cloned into
        ``DIR/{repository's name}``.
    laser : str
        ``"red"`` or ``"green"``: the signal is that colour's excess.
    along : str
        ``"rows"``: the line runs across the image's columns (a profile per column, as the
        scanner's camera sees it); ``"columns"``: it runs down the rows, the frame is transposed.
    target : str
        ``"chessboard"`` or ``"circles"`` (a symmetric grid of dots).
    pattern : (int, int)
        OpenCV's pattern size (inner corners or dots per row, per column).
    pitch_mm : float or None
        Square side or dot spacing; None where the set does not say (no light-plane figure).
    laser_images : str
        Glob of the photographs with the line, relative to the clone.
    board_images : str or None
        Where each one's target is found without the line, ``{n}`` the photograph's number
        (the same pose, laser off); None: in the photograph itself.
    calibration_images : str or None
        Glob of more views of the target for the camera's calibration (with ``camera`` None).
    camera : tuple or None
        ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` published with the set; None: read from
        ``camera_file``, or calibrated from the set's own views of the target.
    camera_file : str or None
        An OpenCV FileStorage file in the clone with ``cameraMatrix`` and ``distCoeffs``.
    source : str
        Where each fact above comes from.
    signal : str or None
        ``scanner_core.stripe.extractor.stripe_signal``'s ``signal`` for both methods; None: the laser's
        colour excess.
    """

    name: str
    repository: str
    commit: str
    laser: str
    along: str
    target: str
    pattern: tuple[int, int]
    pitch_mm: float | None
    laser_images: str
    board_images: str | None = None
    calibration_images: str | None = None
    camera: tuple | None = None
    camera_file: str | None = None
    source: str = ""
    signal: str | None = None

    @property
    def folder(self) -> str:
        return self.repository.split("/")[1]


SETS = (
    PhotoSet(
        name="green line, printed chessboard, 640 x 480 JPEG",
        repository="hjamal3/Light-Stripe-Calibration",
        commit="64ce9a67b32ad91e1f22ece0712a617656685b81",
        laser="green", along="columns", target="chessboard", pattern=(6, 8), pitch_mm=40.0,
        laser_images="images/*_right.jpg",
        camera=(514.41205, 685.92876, 329.83671, 237.71471, -0.350373, 0.158447, 0.000735,
                -0.000231, 0.0),
        source="calibrate.py: corners_shape (6, 8), length_square 0.04 m, green, vertical, "
               "the camera matrix and distortion"),
    PhotoSet(
        name="red line, orange chessboard, 960 x 540 JPEG",
        repository="fatal-scythe/newStructuredLight",
        commit="72d55fd1a7cc9a4ce5cce66399d789a21d2dd729",
        laser="red", along="rows", target="chessboard", pattern=(9, 9), pitch_mm=None,
        laser_images="calib_original_images/ob*.jpg",
        board_images="calib_original_images/oa{n}.jpg",
        calibration_images="calib_original_images/oa*.jpg",
        source="README: ob{n} with the laser, oa{n} the same pose without; 9 x 9 inner corners "
               "found by detection; the square's size is not given"),
    PhotoSet(
        name="red line, small chessboard, 640 x 480 PNG",
        repository="biorobotics/blaser-calibration-matlab",
        commit="f6fbe947fb8032c4851e4ca7a7b10515d84c969a",
        laser="red", along="rows", target="chessboard", pattern=(9, 6), pitch_mm=5.0,
        laser_images="blaser_data/640_unified/im*.png",
        calibration_images="blaser_data/640_unified/im*.png",
        source="unified_proc.m: boardSize [7, 10] squares, squareSize 0.005 m"),
    PhotoSet(
        name="red line, dot grid, 1920 x 1080 JPEG",
        repository="zhaocongyang/structured_LineLight_calib",
        commit="672d6417f0ee723e0596a8f0ef03bdb3372768a9",
        laser="red", along="rows", target="circles", pattern=(7, 7), pitch_mm=37.5,
        laser_images="light_picture/light*.jpg",
        board_images="calib_picture/calib{n}.jpg",
        camera_file="Parameters.xml",
        source="main.cpp: patternSize (7, 7), patternLength 37.5 mm, circles; Parameters.xml: "
               "the camera"),
)


def _read_rgb(path: pathlib.Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"cannot read {path} as an image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def _find_target(rgb: np.ndarray, ps: PhotoSet):
    """The target's image points (N, 2) float32, or None."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if ps.target == "circles":
        found, pts = cv2.findCirclesGrid(grey, ps.pattern, flags=cv2.CALIB_CB_SYMMETRIC_GRID)
        return pts.reshape(-1, 2) if found else None
    found, pts = cv2.findChessboardCornersSB(
        grey, ps.pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if found:
        return pts.reshape(-1, 2)
    found, pts = cv2.findChessboardCorners(
        grey, ps.pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not found:
        return None
    pts = cv2.cornerSubPix(grey, pts, (5, 5), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    return pts.reshape(-1, 2)


def _object_points(ps: PhotoSet) -> np.ndarray:
    """(N, 3) float32 target points in pitch units (or mm), in OpenCV's order."""
    cols, rows = ps.pattern
    pitch = ps.pitch_mm or 1.0
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float32) * pitch
    return np.hstack([grid, np.zeros((len(grid), 1), np.float32)])


def _camera(ps: PhotoSet, root: pathlib.Path, views):
    """(K (3, 3), dist (5,)) of the set, and how it was obtained."""
    if ps.camera is not None:
        fx, fy, cx, cy, *dist = ps.camera
        return (np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.array(dist, float),
                "published with the set")
    if ps.camera_file is not None:
        fs = cv2.FileStorage(str(root / ps.camera_file), cv2.FILE_STORAGE_READ)
        k, d = fs.getNode("cameraMatrix").mat(), fs.getNode("distCoeffs").mat()
        fs.release()
        return np.asarray(k, float), np.asarray(d, float).ravel(), ps.camera_file
    obj = _object_points(ps)
    found = [(pts, size) for pts, size in views if pts is not None]
    if len(found) < 3:
        raise RuntimeError(f"{ps.name}: the target is found in {len(found)} views, too few "
                           "to calibrate the camera")
    size = found[0][1]
    rms, k, d, _, _ = cv2.calibrateCamera([obj] * len(found), [p for p, _ in found], size,
                                          None, None)
    return k, d.ravel(), f"calibrated from {len(found)} views (RMS {rms:.2f} px)"


def _outline(ps: PhotoSet, rvec, tvec, k, dist) -> np.ndarray:
    """(M, 2) float32 polygon of the target's printed area in the image: the grid grown by one
    pitch on every side (a chessboard's outer squares, a dot grid's margin)."""
    cols, rows = ps.pattern
    pitch = ps.pitch_mm or 1.0
    t = np.linspace(0.0, 1.0, 25)
    x0, x1, y0, y1 = -1.0, float(cols), -1.0, float(rows)
    edges = [np.c_[x0 + (x1 - x0) * t, np.full_like(t, y0)],
             np.c_[np.full_like(t, x1), y0 + (y1 - y0) * t],
             np.c_[x1 - (x1 - x0) * t, np.full_like(t, y1)],
             np.c_[np.full_like(t, x0), y1 - (y1 - y0) * t]]
    pts = np.vstack(edges) * pitch
    pts3 = np.hstack([pts, np.zeros((len(pts), 1))]).astype(np.float64)
    img, _ = cv2.projectPoints(pts3, rvec, tvec, k, dist)
    return img.reshape(-1, 2).astype(np.float32)


def _undistort(px: np.ndarray, k, dist) -> np.ndarray:
    """(N, 2) image points -> (N, 2) normalised undistorted coordinates."""
    if len(px) == 0:
        return np.zeros((0, 2))
    return cv2.undistortPoints(px.reshape(-1, 1, 2).astype(np.float64), k, dist).reshape(-1, 2)


def _fit_line(pts: np.ndarray, trials: int = 400):
    """The line through most of (N, 2) points (undistorted pixels): the pair of points whose
    line holds the most within ``OUTLIER_PX`` (RANSAC, a fixed seed), refined by total least
    squares on those; (centre, unit normal), or None with fewer than 10 points. Both methods'
    points are pooled: whichever measured a profile right, the line is where most agree."""
    if len(pts) < 10:
        return None
    rng = np.random.default_rng(0)
    best, best_count = None, -1
    for _ in range(trials):
        i, j = rng.choice(len(pts), 2, replace=False)
        d = pts[j] - pts[i]
        norm = math.hypot(d[0], d[1])
        if norm < 20.0:
            continue
        normal = np.array([-d[1], d[0]]) / norm
        count = int(np.sum(np.abs((pts - pts[i]) @ normal) <= OUTLIER_PX))
        if count > best_count:
            best, best_count = (pts[i], normal), count
    if best is None:
        return None
    centre, normal = best
    for _ in range(3):
        keep = np.abs((pts - centre) @ normal) <= OUTLIER_PX
        if keep.sum() < 10:
            return None
        centre = pts[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[keep] - centre, full_matrices=False)
        normal = vt[1]
    return centre, normal


def _method_points(rows, along):
    """Valid profile points (N, 2) in image (x, y) and their profile's column."""
    cols = np.nonzero(np.isfinite(rows))[0]
    r = rows[cols].astype(np.float64)
    if along == "rows":
        return np.c_[cols, r], cols
    return np.c_[r, cols], cols


def score_photo(rgb, ps: PhotoSet, rvec, tvec, k, dist) -> dict | None:
    """Both methods on one photograph against its target: per method the arrays the set's
    figures are made of, or None where the line cannot be fitted."""
    name = ps.signal or f"{ps.laser}_excess"
    signal = stripe_signal(rgb, name)
    naive = naive_signal(rgb, name)
    if ps.along == "columns":
        signal = np.ascontiguousarray(signal.T)
        naive = np.ascontiguousarray(naive.T)
    res = extract(signal, shoulders=True)  # a colour frame's, as the pipeline measures it
    # the peak finder's gate counts from the excess's zero, as on the bare excess
    offset = EXCESS_OFFSET_DN if name.endswith("_excess") else 0.0
    methods = {"flyscan": np.where(res.valid, res.row, np.nan).astype(np.float64),
               "baseline": baseline_rows(naive, BASELINE_DN + offset),
               "baseline_on_flyscan_signal": baseline_rows(signal, BASELINE_DN + offset)}
    outline = _outline(ps, rvec, tvec, k, dist)
    f_k = k[0, 0]  # undistorted distances in pixels of the camera's focal length

    def inside(xy):
        return np.array([cv2.pointPolygonTest(outline, (float(x), float(y)), True)
                         for x, y in xy]) >= OUTLINE_MARGIN_PX

    pts = {}
    for name, rows in methods.items():
        xy, cols = _method_points(rows, ps.along)
        pts[name] = (xy, cols, rows)
    # the line through the points on the target (a profile measured elsewhere in its column,
    # on the floor or a wall, is scored below as off the line)
    union = np.vstack([_undistort(p[0][inside(p[0])], k, dist) if len(p[0]) else np.zeros((0, 2))
                       for m, p in pts.items() if m in ("flyscan", "baseline")]) * f_k
    line = _fit_line(union)
    if line is None:
        return None
    centre, normal = line
    # the profiles on the target: every column where the line (drawn through the undistorted
    # image and distorted back) crosses it, away from its outline
    direction = np.array([-normal[1], normal[0]])
    span = np.linspace(-4000.0, 4000.0, 16001)
    on_line = (centre + span[:, None] * direction) / f_k
    drawn, _ = cv2.projectPoints(np.c_[on_line, np.ones(len(on_line))], np.zeros(3),
                                 np.zeros(3), k, dist)
    drawn = drawn.reshape(-1, 2)
    h, w = rgb.shape[:2]
    axis = 0 if ps.along == "rows" else 1
    n_cols = w if ps.along == "rows" else h
    good = (drawn[:, 0] >= 0) & (drawn[:, 0] < w) & (drawn[:, 1] >= 0) & (drawn[:, 1] < h)
    drawn = drawn[good]
    order = np.argsort(drawn[:, axis])
    drawn = drawn[order]
    cols_all = np.arange(n_cols)
    if len(drawn) < 2:
        return None
    cross = np.interp(cols_all, drawn[:, axis], drawn[:, 1 - axis], left=np.nan, right=np.nan)
    line_xy = (np.c_[cols_all, cross] if ps.along == "rows" else np.c_[cross, cols_all])
    ok = np.isfinite(cross)
    board = np.zeros(n_cols, bool)
    board[ok] = inside(line_xy[ok])
    contrast = np.where(board, _stripe_contrast(naive, cross), np.nan)
    visible = contrast >= VISIBLE_SIGMAS
    curve = {level: contrast >= level for level in VISIBLE_CURVE}
    out = {"profiles_on_target": int(board.sum()), "profiles_visible": int(visible.sum()),
           "profiles_visible_at": {level: int(v.sum()) for level, v in curve.items()}}
    # the target's plane in the camera, for the light plane
    rot, _ = cv2.Rodrigues(rvec)
    plane_n = rot[:, 2]
    plane_d = float(plane_n @ tvec.ravel())
    dist_px = {}
    for name, (xy, cols, rows) in pts.items():
        und = _undistort(xy, k, dist)
        # each method about its own line through its profiles on the target: straightness,
        # whatever either method's offset from the other
        own = _fit_line(und[board[cols]] * f_k) or (centre, normal)
        d = ((und * f_k - own[0]) @ own[1])
        sel = board[cols]
        d, cols_b, und = d[sel], cols[sel], und[sel]
        dist_px[name] = np.full(n_cols, np.nan)
        dist_px[name][cols_b] = d
        rays = np.c_[und, np.ones(len(und))]
        points = rays * (plane_d / (rays @ plane_n))[:, None]
        frac = np.abs(rows[cols_b] - np.round(rows[cols_b]))
        out[name] = {"measured": int(len(d)), "measured_visible": int(visible[cols_b].sum()),
                     "measured_visible_at": {level: int(v[cols_b].sum())
                                             for level, v in curve.items()},
                     "distance_px": d, "points_mm": points,
                     "whole_pixel": frac < WHOLE_PIXEL_PX}
    b, f = dist_px["baseline"], dist_px["flyscan"]
    right = np.abs(b) <= RIGHT_PX
    out["baseline_right"] = int(right.sum())
    out["baseline_right_flyscan_not"] = int((right & ~(np.abs(f) <= RIGHT_PX)).sum())
    return out


def _stripe_contrast(signal: np.ndarray, cross: np.ndarray) -> np.ndarray:
    """(W,) float: how far the stripe stands out at rows ``cross`` (W,) float (NaN: off the
    photograph) of ``signal`` (H, W) uint8, in the frame's noise sigmas (``estimate_noise``):
    the largest value within ``VISIBLE_NEAR_PX`` of the line over the higher of the column's
    medians ``VISIBLE_RING_PX`` away on either side (a texture's edge under the line is no
    stripe); NaN where a side runs off the photograph."""
    h, w = signal.shape
    noise = estimate_noise(signal)[1]
    near_lo, near_hi = VISIBLE_RING_PX
    out = np.full(w, np.nan)
    for c in np.flatnonzero(np.isfinite(cross)):
        r = int(round(float(cross[c])))
        core = signal[max(r - VISIBLE_NEAR_PX, 0):min(r + VISIBLE_NEAR_PX + 1, h), c]
        above = signal[max(r - near_hi, 0):max(r - near_lo + 1, 0), c]
        below = signal[min(r + near_lo, h):min(r + near_hi + 1, h), c]
        if len(core) and len(above) and len(below):
            side = max(float(np.median(above)), float(np.median(below)))
            out[c] = (float(core.max()) - side) / noise
    return out


def _plane_rms_um(points: np.ndarray) -> float | None:
    """RMS (um) of (N, 3) points (mm) about their plane, trimmed at 5 times a robust sigma."""
    if len(points) < 20:
        return None
    keep = np.ones(len(points), bool)
    for _ in range(4):
        centre = points[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(points[keep] - centre, full_matrices=False)
        d = (points - centre) @ vt[2]
        sigma = 1.4826 * np.median(np.abs(d[keep]))
        keep = np.abs(d) <= max(5.0 * sigma, 1e-9)
    return float(np.sqrt(np.mean(d[keep] ** 2)) * 1000.0)


def _number(path: pathlib.Path) -> str:
    found = re.findall(r"\d+", path.stem)
    return found[-1] if found else ""


def score_set(ps: PhotoSet, root: pathlib.Path, progress=None) -> dict:
    """Both methods over one set's photographs (``root`` is the clone)."""
    paths = sorted(pathlib.Path(p) for p in glob.glob(str(root / ps.laser_images)))
    if not paths:
        raise FileNotFoundError(f"{ps.name}: no {ps.laser_images} under {root} (clone "
                                f"https://github.com/{ps.repository} there)")
    views = []
    per_photo = []
    for path in paths:
        rgb = _read_rgb(path)
        board = (rgb if ps.board_images is None
                 else _read_rgb(root / ps.board_images.format(n=_number(path))))
        pts = _find_target(board, ps)
        per_photo.append((path, rgb, pts))
        views.append((pts, (rgb.shape[1], rgb.shape[0])))
    if ps.camera is None and ps.camera_file is None and ps.calibration_images:
        extra = sorted(set(glob.glob(str(root / ps.calibration_images))) - {str(p) for p in paths})
        for p in extra:
            img = _read_rgb(pathlib.Path(p))
            views.append((_find_target(img, ps), (img.shape[1], img.shape[0])))
    k, dist, camera_from = _camera(ps, root, views)
    obj = _object_points(ps)
    totals = {"photographs": len(paths), "scored": 0, "profiles_on_target": 0,
              "profiles_visible": 0, "baseline_right": 0, "baseline_right_flyscan_not": 0}
    visible_at = dict.fromkeys(VISIBLE_CURVE, 0)
    pooled = {m: {"d": [], "points": [], "whole": [], "visible": 0,
                  "visible_at": dict.fromkeys(VISIBLE_CURVE, 0)} for m in METHODS}
    for i, (path, rgb, pts) in enumerate(per_photo):
        if progress:
            progress(f"{ps.folder}: {path.name} ({i + 1}/{len(per_photo)})")
        if pts is None:
            continue
        ok, rvec, tvec = cv2.solvePnP(obj, pts, k, dist)
        if not ok:
            continue
        s = score_photo(rgb, ps, rvec, tvec, k, dist)
        if s is None:
            continue
        totals["scored"] += 1
        for key in ("profiles_on_target", "profiles_visible", "baseline_right",
                    "baseline_right_flyscan_not"):
            totals[key] += s[key]
        for level in VISIBLE_CURVE:
            visible_at[level] += s["profiles_visible_at"][level]
        for m in pooled:
            pooled[m]["visible"] += s[m]["measured_visible"]
            for level in VISIBLE_CURVE:
                pooled[m]["visible_at"][level] += s[m]["measured_visible_at"][level]
            pooled[m]["d"].append(s[m]["distance_px"])
            pooled[m]["points"].append(s[m]["points_mm"])
            pooled[m]["whole"].append(s[m]["whole_pixel"])
    figures = {}
    for m, p in pooled.items():
        d = np.concatenate(p["d"]) if p["d"] else np.zeros(0)
        pts3 = np.vstack(p["points"]) if p["points"] else np.zeros((0, 3))
        whole = np.concatenate(p["whole"]) if p["whole"] else np.zeros(0, bool)
        near = np.abs(d) <= GROSS_PX
        figures[m] = {
            "measured": int(len(d)),
            "measured_share": len(d) / max(totals["profiles_on_target"], 1),
            "measured_visible_share": p["visible"] / max(totals["profiles_visible"], 1),
            "measured_visible_share_at_sigmas": {
                str(level): p["visible_at"][level] / max(visible_at[level], 1)
                for level in VISIBLE_CURVE},
            "rms_line_px": float(np.sqrt(np.mean(d[near] ** 2))) if near.any() else None,
            "beyond_1px_share": float(np.mean(np.abs(d) > OUTLIER_PX)) if len(d) else None,
            "gross_share": float(np.mean(~near)) if len(d) else None,
            "whole_pixel_share": float(np.mean(whole)) if len(whole) else None,
            "rms_plane_um": (_plane_rms_um(pts3[near]) if ps.pitch_mm else None),
        }
    return {"name": ps.name, "repository": ps.repository, "commit": ps.commit,
            "laser": ps.laser, "camera": camera_from, "source": ps.source, **totals,
            "profiles_visible_at_sigmas": {str(k): v for k, v in visible_at.items()},
            **{m: figures[m] for m in METHODS}}


def _bar_panels(path: pathlib.Path, names: list[str], panels, series, title: str,
                height_in: float) -> None:
    """One horizontal bar per name and series in each of ``panels`` ((key, title, scale); a
    ``whole_pixel`` key gets chance's line, dashed); ``series`` is (label, colour,
    value(index, key))."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(17, height_in))
    y = np.arange(len(names))
    width = 0.8 / len(series)
    for ax, (key, panel_title, scale) in zip(axes, panels):
        for k, (label, colour, value) in enumerate(series):
            ax.barh(y + width * (k - (len(series) - 1) / 2),
                    [(value(i, key) or 0.0) * scale for i in range(len(names))],
                    height=width * 0.95, color=colour, label=label)
        if key.startswith("whole_pixel"):
            ax.axvline(100 * 2 * WHOLE_PIXEL_PX, color="k", lw=0.8, ls="--")
        ax.set_title(panel_title, fontsize=10)
        ax.set_yticks(y)
        ax.set_yticklabels(names if ax is axes[0] else [], fontsize=8)
        ax.invert_yaxis()
    handles, texts = axes[0].get_legend_handles_labels()
    fig.legend(handles, texts, fontsize=9, loc="lower center", ncol=len(series))
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot(sets: list[dict], path: pathlib.Path) -> None:
    labels = {"flyscan": "flyscan (defaults)",
              "baseline": f"argmax + parabola (>= {BASELINE_DN:.0f} DN), the colour excess",
              "baseline_on_flyscan_signal": "argmax + parabola, flyscan's signal"}
    _bar_panels(path, [s["name"].replace(", ", ",\n", 1) for s in sets],
                [("rms_line_px", "RMS about the line, px", 1.0),
                 ("measured_visible_share", "profiles showing the stripe measured, %", 100.0),
                 ("beyond_1px_share", "profiles > 1 px off the line, %", 100.0),
                 ("whole_pixel_share", "rows within 0.02 px of a whole pixel, %", 100.0)],
                [(labels[m], colour, lambda i, key, m=m: sets[i][m][key])
                 for m, colour in zip(METHODS, ("C0", "C7", "C8"))],
                "Real photographs of a laser line on a planar target: flyscan against a naive "
                "peak finder", 4.6)


def _plot_synthesised(cases: dict, path: pathlib.Path) -> None:
    names = list(cases)
    _bar_panels(path, names,
                [("rms", "RMS about the drawn line, px", 1.0),
                 ("measured", "columns holding a stripe measured, %", 100.0),
                 ("beyond_1px", "measured columns > 1 px off, %", 100.0),
                 ("whole_pixel", "rows within 0.02 px of a whole pixel, %", 100.0)],
                [(label, colour, lambda i, key, m=m: cases[names[i]][m][key])
                 for m, colour, label in (("flyscan", "C0", "flyscan (defaults)"),
                                          ("baseline", "C7", "argmax + parabola"))],
                "Synthesised photographs (simulator.line_photos, three frames each): flyscan "
                "against a naive peak finder, scored against the drawn line", 6.4)


def run(out_dir: pathlib.Path, folder: pathlib.Path, *, quick: bool = False) -> dict:
    """Score every set found under ``folder`` and the synthesised cases, and write
    ``real.json``, ``real.png`` and ``real_synthesised.png``."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    folder = pathlib.Path(folder)
    results, missing = [], []
    for ps in SETS:
        root = folder / ps.folder
        if not root.is_dir():
            missing.append(f"https://github.com/{ps.repository} (commit {ps.commit[:10]}) "
                           f"into {root}")
            continue
        results.append(score_set(ps, root, progress=lambda m: print(m, file=sys.stderr)))
    if not results:
        raise FileNotFoundError("none of the sets is under " + str(folder) + ": clone "
                                + "; ".join(missing))
    for line in missing:
        print(f"bench real: not scored (missing): clone {line}", file=sys.stderr)
    summary = {s["name"]: {m: {k: s[m][k] for k in ("measured_share", "measured_visible_share",
                                                     "rms_line_px", "rms_plane_um",
                                                     "beyond_1px_share", "whole_pixel_share")}
                           for m in METHODS}
               for s in results}
    for s in results:
        summary[s["name"]]["baseline_right_flyscan_not"] = s["baseline_right_flyscan_not"]
    synthesised = run_cases(seeds=(0,) if quick else SEEDS,
                            progress=lambda m: print(m, file=sys.stderr))
    summary["synthesised"] = {
        name: {"rms_ratio": c["rms_ratio"],
               "beyond_1px_share": [c["flyscan"]["beyond_1px"], c["baseline"]["beyond_1px"]],
               "measured_share": [c["flyscan"]["measured"], c["baseline"]["measured"]],
               "false_off_line": [c["flyscan"]["false_off_line"],
                                  c["baseline"]["false_off_line"]]}
        for name, c in synthesised.items()}
    result = {"sets": results, "missing": missing, "summary": summary,
              "baseline": f"argmax + 3-point parabola, argmax >= {BASELINE_DN} DN",
              "synthesised": synthesised}
    write_json(out_dir / "real.json", result)
    _plot(results, out_dir / "real.png")
    _plot_synthesised(synthesised, out_dir / "real_synthesised.png")
    return result
