"""What one frame shows: its exact ground truth, the image made from it, and the truth of an
exposure that spans several instants.

:class:`FrameTruth` holds a frame's stripe samples, one-bounce reflections and LED pixels (the
inputs of the image model, ``simulator.imaging.render_image``) with the poses they come from;
:func:`frame_image` applies the image model to it, with noise; :func:`blur_truths` merges the
truths of the instants of one exposure into the truth of a blurred frame.
``simulator.render.PartScene`` computes the truths.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from simulator.cell import Cell
from simulator.imaging import render_image

__all__ = ["FrameTruth", "frame_image", "blur_truths", "BLUR_ROW_STEP_PX"]


@dataclass(frozen=True)
class FrameTruth:
    """Exact ground truth of one rendered frame.

    Attributes
    ----------
    tcp_b : (3,) float64
        True TCP position, {B}, mm.
    part_pose_b : (4, 4) float64
        ^B X_P at this frame.
    stripe_columns : (N,) int32
        Image column of each stripe sample (``simulator.section.column_hits``): one per
        section segment overlapping the column, so a column may hold several.
    stripe_rows : (N,) float64
        Exact sub-pixel row of each stripe sample (before noise).
    stripe_points_b : (N, 3) float64
        The 3-D point of each sample, {B}, mm.
    stripe_gain : (N,) float64
        Relative brightness: the part's surface return (``simulator.surfaces.surface_gain``:
        the cosine of the laser's incidence for the reference surface) times the share of the
        pixel column the sample covers.
    marker_b : (3,) float64
        LED centre, {B}, mm.
    marker_pixels : (3, 2) float64
        LED centre in the direct, left and right views; NaN where hidden or outside its strip.
    reflection_columns, reflection_rows, reflection_gain : (K,) int32, float64, float64
        Where the laser mirrored by a shiny surface lights the part again (one bounce), as
        seen in the direct view: not the stripe (the light is off the sheet), but drawn like it.
    marker_blobs : (M, 4) float64 or None
        The LED blobs as drawn, ``(u, v, gain, sigma_px)``, when they are not simply one blob of
        the image model's size per view in ``marker_pixels``: an LED of finite size, or a blob
        smeared over the exposure.
    stripe_surfaces : (N,) int64
        The plane of the mesh each stripe sample lies on (``PartScene.surface_ids``: coplanar
        faces share one); empty for a blurred frame's truth.
    """

    tcp_b: np.ndarray
    part_pose_b: np.ndarray
    stripe_columns: np.ndarray
    stripe_rows: np.ndarray
    stripe_points_b: np.ndarray
    stripe_gain: np.ndarray
    marker_b: np.ndarray
    marker_pixels: np.ndarray
    reflection_columns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    reflection_rows: np.ndarray = field(default_factory=lambda: np.zeros(0))
    reflection_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))
    marker_blobs: np.ndarray | None = None
    stripe_surfaces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def frame_image(cell: Cell, truth: FrameTruth | None, rng: np.random.Generator,
                image_model=None, background: np.ndarray | None = None) -> np.ndarray:
    """The image model applied to a frame's geometry, with noise from ``rng``.

    Parameters
    ----------
    cell : Cell
        Gives the image size and model.
    truth : FrameTruth or None
        The frame's geometry (stripe, one-bounce reflections, marker); None renders
        background only.
    rng : numpy.random.Generator
    image_model : simulator.imaging.ImageModel, optional
        Instead of the cell's (a camera's exposure and gain applied to it).
    background : (H, W) uint8, optional
        A background frame rendered earlier from the same image model, drawn over
        (``simulator.imaging.render_image``).

    Returns
    -------
    (H, W) uint8
        The frame, DN.
    """
    cam = cell.calibration.camera
    model = cell.image_model if image_model is None else image_model
    if truth is None:
        return render_image(cam.height, cam.width, model, rng) if background is None \
            else background.copy()
    cols, rows, gain = truth.stripe_columns, truth.stripe_rows, truth.stripe_gain
    if len(truth.reflection_columns):
        cols = np.concatenate([cols, truth.reflection_columns])
        rows = np.concatenate([rows, truth.reflection_rows])
        gain = np.concatenate([gain, truth.reflection_gain])
    blobs = truth.marker_blobs
    if blobs is None:
        return render_image(cam.height, cam.width, model, rng, stripe_cols=cols,
                            stripe_rows=rows, stripe_gain=gain, marker_xy=truth.marker_pixels,
                            background=background)
    return render_image(cam.height, cam.width, model, rng, stripe_cols=cols, stripe_rows=rows,
                        stripe_gain=gain, marker_xy=blobs[:, :2], marker_gain=blobs[:, 2],
                        marker_sigma=blobs[:, 3], background=background)


#: A stripe that moves across a column during the exposure is drawn as a smear of samples
#: at most this far apart along it, px (below the stripe's sigma: a band, not separate lines).
BLUR_ROW_STEP_PX = 0.5


def _merged_by_surface(t: FrameTruth, shift: np.ndarray):
    """A frame's stripe samples merged per column and surface (two triangles of one flat face
    meeting inside a column give one sample: their gain-weighted row and point, summed gain):
    (keys, columns, rows, points moved by ``shift``, gains), keys sorted and unique."""
    key = t.stripe_columns.astype(np.int64) << 32 | t.stripe_surfaces
    keys, group = np.unique(key, return_inverse=True)
    group = group.ravel()
    gain = np.bincount(group, t.stripe_gain, len(keys))
    weight = np.maximum(gain, 1e-300)
    rows = np.bincount(group, t.stripe_gain * t.stripe_rows, len(keys)) / weight
    points = np.stack([np.bincount(group, t.stripe_gain * t.stripe_points_b[:, i], len(keys))
                       for i in range(3)], 1) / weight[:, None] + shift
    return keys, (keys >> 32).astype(np.int32), rows, points, gain


def blur_truths(truths: list[FrameTruth]) -> FrameTruth:
    """One FrameTruth for the instants of one exposure (see ``PartScene.render_blurred``).

    The exposure is integrated over the intervals between the instants (trapezoid rule): a
    sample seen at both ends of an interval (the same column and mesh face) is smeared between
    its two rows, in steps of at most ``BLUR_ROW_STEP_PX``, so that a face the sheet sweeps
    during the exposure (one nearly parallel to the sheet) shows the band a real camera would;
    a sample at one end only (the stripe leaving or reaching the column) counts for half the
    interval. Points are moved with the gripper to the middle instant (they keep their place
    in {T}); reflections are drawn at each instant with 1/K of their brightness. The LED is
    strobed (``simulator.imaging.exposed_model``) at the middle of the exposure: it is the
    middle instant's, sharp.
    """
    k = len(truths)
    ref = truths[k // 2]
    if k == 1:
        return ref
    shift = [ref.tcp_b - t.tcp_b for t in truths]  # the gripper's rotation is fixed in a pass
    share = 1.0 / (k - 1)
    merged = [_merged_by_surface(t, d) for t, d in zip(truths, shift)]
    cols, rows, points, gains = [], [], [], []
    for i in range(k - 1):
        (key_a, ca, ra, pa, ga), (key_b, _, rb, pb, gb) = merged[i], merged[i + 1]
        _, ia, ib = np.intersect1d(key_a, key_b, assume_unique=True, return_indices=True)
        steps = np.maximum(1, np.ceil(np.abs(rb[ib] - ra[ia]) / BLUR_ROW_STEP_PX)).astype(np.int64)
        j = np.repeat(np.arange(len(ia)), steps)
        f = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps) + 0.5) / steps[j]
        ja, jb = ia[j], ib[j]
        cols.append(ca[ja])
        rows.append(ra[ja] + f * (rb[jb] - ra[ja]))
        points.append(pa[ja] + f[:, None] * (pb[jb] - pa[ja]))
        gains.append((ga[ja] + f * (gb[jb] - ga[ja])) * share / steps[j])
        for (keys, c, r, p, g), matched in ((merged[i], ia), (merged[i + 1], ib)):
            alone = np.setdiff1d(np.arange(len(keys)), matched)
            cols.append(c[alone])
            rows.append(r[alone])
            points.append(p[alone])
            gains.append(g[alone] * 0.5 * share)
    cat = np.concatenate
    return dataclasses.replace(
        ref,
        stripe_columns=cat(cols).astype(np.int32),
        stripe_rows=cat(rows),
        stripe_points_b=cat(points),
        stripe_gain=cat(gains),
        stripe_surfaces=np.zeros(0, np.int64),
        reflection_columns=cat([t.reflection_columns for t in truths]),
        reflection_rows=cat([t.reflection_rows for t in truths]),
        reflection_gain=cat([t.reflection_gain for t in truths]) / k)

