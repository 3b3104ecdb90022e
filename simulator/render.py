"""Frame rendering: what the camera sees of the part in the sheet, and of the LED marker.

For one gripper pose the part is cut by the light plane (exact mesh section), the section is
split at the boundaries of the direct view's pixel columns, and every piece that the laser
reaches and the camera sees (Embree ray casts at its middle) becomes a stripe sample at its
exact sub-pixel row, as bright as the share of the pixel it covers (the pixel integrates over
its area: a stripe ending inside a column lights it in part). The LED marker is projected
into the direct view and, through each mirror, into the mirror views, unless the part hides
it. ``simulator.imaging`` turns the samples into pixels. The ground truth of every frame
comes back with it.

The mesh stays put in {P}; the sheet, camera and laser are moved into {P} instead (the
paper's section III: moving the virtual setup is cheaper than moving the CAD model).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from scanner_core.geometry import apply_transform
from simulator.cell import Cell
from simulator.imaging import render_image
from simulator.parts import Part
from simulator.raycast import Intersector
from simulator.surfaces import mirror_directions, surface_gain

#: A bounced ray starts this far along its way, clear of the surface it leaves (mm).
BOUNCE_OFFSET_MM = 1e-3


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
        Image column of each stripe sample (:func:`column_hits`): one per section segment
        overlapping the column, so a column may hold several.
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


class PartScene:
    """A part in the cell, ready to render: the mesh, its intersector and cached normals."""

    def __init__(self, part: Part, cell: Cell):
        self.part = part
        self.cell = cell

    @cached_property
    def intersector(self) -> Intersector:
        return self.part.intersector

    @cached_property
    def surface_ids(self) -> np.ndarray:
        """(F,) int64: one id per flat face of the mesh (trimesh's facets: adjacent coplanar
        triangles), each other triangle its own: a stripe sweeping across a flat face made of
        several triangles stays on one surface."""
        mesh = self.part.mesh
        ids = np.arange(len(mesh.faces), dtype=np.int64)
        for k, facet in enumerate(mesh.facets):
            ids[facet] = len(mesh.faces) + k
        return ids

    @cached_property
    def _vertices(self) -> np.ndarray:
        return self.part.vertices

    @cached_property
    def _faces(self) -> np.ndarray:
        return self.part.faces

    @cached_property
    def _face_normals(self) -> np.ndarray:
        return np.asarray(self.part.mesh.face_normals, dtype=np.float64)

    def part_pose(self, tcp_b: np.ndarray, grasp: np.ndarray) -> np.ndarray:
        """^B X_P for a TCP position and a true grasp ^T X_P."""
        pose_t = np.eye(4)
        pose_t[:3, :3] = self.cell.gripper_rotation_b
        pose_t[:3, 3] = tcp_b
        return pose_t @ grasp

    def section(self, pose_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The part cut by the light plane: segments (K, 2, 3) in {P} and their faces (K,)."""
        r, t = pose_b[:3, :3], pose_b[:3, 3]
        plane = self.cell.light_plane_b
        normal_p = r.T @ plane.normal
        offset_p = plane.offset - plane.normal @ t
        return slice_mesh(self._vertices, self._faces, normal_p, offset_p)

    def render(self, tcp_b, grasp: np.ndarray, rng: np.random.Generator, *, with_marker=True,
               image_model=None):
        """Render one frame: :meth:`geometry`, then the image model (the cell's, or
        ``image_model``: the camera's exposure applied, ``simulator.imaging.exposed_model``).

        Returns
        -------
        image : (H, W) uint8
        truth : FrameTruth
        """
        truth = self.geometry(tcp_b, grasp, with_marker=with_marker)
        return frame_image(self.cell, truth, rng, image_model), truth

    def geometry(self, tcp_b, grasp: np.ndarray, *, with_marker=True) -> FrameTruth:
        """What one frame shows, without the image model: its stripe samples and marker
        pixels (the inputs of ``render_image``) as the frame's FrameTruth."""
        cal = self.cell.calibration
        cam = cal.camera
        tcp_b = np.asarray(tcp_b, dtype=np.float64)
        pose = self.part_pose(tcp_b, grasp)
        segments, faces = self.section(pose)
        cols, rows, points_p, seg_index, coverage = column_hits(segments, pose, cam,
                                                                cal.direct_columns)
        points_b = apply_transform(pose, points_p)
        keep = (rows >= 0) & (rows <= cam.height - 1) & self._in_fan(points_b)
        cols, rows, points_p, points_b = cols[keep], rows[keep], points_p[keep], points_b[keep]
        faces, coverage = faces[seg_index[keep]], coverage[keep]
        inv = np.linalg.inv(pose)
        laser_p = apply_transform(inv, self.cell.laser_origin_b)
        camera_p = apply_transform(inv, cam.origin)
        lit = self.intersector.visible(laser_p, points_p)
        seen = self.intersector.visible(camera_p, points_p)
        keep = lit & seen
        cols, rows, points_p, points_b = cols[keep], rows[keep], points_p[keep], points_b[keep]
        incidence = points_p - laser_p
        incidence /= np.linalg.norm(incidence, axis=1, keepdims=True)
        faces = faces[keep]
        normals = self._face_normals[faces]
        coverage = coverage[keep]
        surface = self.part.surface
        if surface.specular > 0:
            to_camera = camera_p - points_p
            to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
            gain = surface_gain(surface, incidence, normals, to_camera)
        else:
            gain = surface.albedo * np.abs(np.einsum("ij,ij->i", incidence, normals))
        gain = gain * coverage  # the pixel integrates over the part the sample covers
        marker_b = tcp_b + self.cell.gripper_rotation_b @ cal.marker_offset_t
        marker_px = self.marker_pixels(marker_b, inv) if with_marker else np.full((3, 2), np.nan)
        blobs = None
        if self.cell.effects.led_radius_mm > 0:
            blobs = np.column_stack([marker_px, np.ones(len(marker_px)),
                                     self.marker_sigmas(marker_b)])
        truth = FrameTruth(tcp_b, pose, cols.astype(np.int32), rows, points_b, gain, marker_b,
                           marker_px, marker_blobs=blobs, stripe_surfaces=self.surface_ids[faces])
        if surface.mirror > 0 and len(points_p):
            truth = dataclasses.replace(truth, **self._bounce(points_p, incidence, normals,
                                                              coverage, pose, camera_p))
        return truth

    def render_blurred(self, tcp_b, grasp: np.ndarray, rng: np.random.Generator, *,
                       image_model=None):
        """A frame whose exposure spans several instants (``tcp_b``: (K, 3), one TCP position
        per instant): every instant's stripe and LED drawn at 1/K of its brightness. The
        truth is the middle instant's, with every sample's point moved with the gripper to it
        (the part's points stay where they are in {T})."""
        tcp_b = np.asarray(tcp_b, dtype=np.float64).reshape(-1, 3)
        truth = blur_truths([self.geometry(p, grasp) for p in tcp_b])
        return frame_image(self.cell, truth, rng, image_model), truth

    def marker_sigmas(self, marker_b: np.ndarray) -> np.ndarray:
        """(3,) px: the LED's blob size in each view (half its apparent radius: the sigma of a
        Gaussian of the same spread as a uniform disc is its radius over 2)."""
        cal = self.cell.calibration
        cam = cal.camera
        apparent = [marker_b] + [apply_transform(m.reflection, marker_b) for m in cal.mirrors]
        distance = np.linalg.norm(np.array(apparent) - cam.origin, axis=1)
        return 0.5 * cam.fx * self.cell.effects.led_radius_mm / distance

    def _bounce(self, points_p, incidence, normals, coverage, pose_b, camera_p) -> dict:
        """One bounce: the laser mirrored at each lit sample goes on to the first surface it
        meets, which returns ``mirror x albedo x |cos|`` of it diffusely; the samples the direct
        view sees of those spots (``FrameTruth.reflection_*``)."""
        surface = self.part.surface
        cal = self.cell.calibration
        cam = cal.camera
        onward = mirror_directions(incidence, normals)
        start = points_p + BOUNCE_OFFSET_MM * onward
        distance, face = self.intersector.first_hit(start, onward)
        hit = np.isfinite(distance) & (face >= 0)
        spots = start[hit] + distance[hit, None] * onward[hit]
        cosine = np.abs(np.einsum("ij,ij->i", onward[hit], self._face_normals[face[hit]]))
        gain = surface.mirror * surface.albedo * cosine * coverage[hit]
        seen = self.intersector.visible(np.broadcast_to(camera_p, spots.shape), spots)
        spots, gain = spots[seen], gain[seen]
        pixels = cam.project(apply_transform(pose_b, spots))
        c0, c1 = cal.direct_columns
        cols = np.rint(pixels[:, 0])
        inside = ((cols >= c0) & (cols < c1) & (pixels[:, 1] >= 0)
                  & (pixels[:, 1] <= cam.height - 1) & (gain > 0))
        return {"reflection_columns": cols[inside].astype(np.int32),
                "reflection_rows": pixels[inside, 1], "reflection_gain": gain[inside]}

    def _in_fan(self, points_b: np.ndarray) -> np.ndarray:
        """Inside the laser's fan (its axis points from the source at the sheet's centre)."""
        laser = self.cell.laser_origin_b
        axis = -laser / np.linalg.norm(laser)
        rays = points_b - laser
        cos = rays @ axis / np.linalg.norm(rays, axis=1)
        return cos >= np.cos(np.radians(self.cell.laser_fan_half_angle_deg))

    def marker_pixels(self, marker_b: np.ndarray, inv_pose: np.ndarray) -> np.ndarray:
        """LED pixels in the three views, NaN where the part hides it or it leaves its strip."""
        cal = self.cell.calibration
        cam = cal.camera
        out = np.full((3, 2), np.nan)
        # Each view's light path (camera -> LED, or camera -> mirror -> LED) as legs that
        # the part must not block.
        views = [(marker_b, [(cam.origin, marker_b)], cal.direct_columns)]
        for mirror in cal.mirrors:
            image = apply_transform(mirror.reflection, marker_b)
            hit = mirror.plane.intersect(cam.origin, image - cam.origin)[0]
            views.append((image, [(cam.origin, hit), (hit, marker_b)], mirror.columns))
        for k, (apparent, legs, (c0, c1)) in enumerate(views):
            px = cam.project(apparent)[0]
            if not (np.all(np.isfinite(px)) and c0 <= px[0] <= c1 - 1
                    and 0 <= px[1] <= cam.height - 1):
                continue
            starts = apply_transform(inv_pose, np.array([leg[0] for leg in legs]))
            ends = apply_transform(inv_pose, np.array([leg[1] for leg in legs]))
            if np.all(self.intersector.visible(starts, ends)):
                out[k] = px
        return out


def frame_image(cell: Cell, truth: FrameTruth | None, rng: np.random.Generator,
                image_model=None) -> np.ndarray:
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

    Returns
    -------
    (H, W) uint8
        The frame, DN.
    """
    cam = cell.calibration.camera
    model = cell.image_model if image_model is None else image_model
    if truth is None:
        return render_image(cam.height, cam.width, model, rng)
    cols, rows, gain = truth.stripe_columns, truth.stripe_rows, truth.stripe_gain
    if len(truth.reflection_columns):
        cols = np.concatenate([cols, truth.reflection_columns])
        rows = np.concatenate([rows, truth.reflection_rows])
        gain = np.concatenate([gain, truth.reflection_gain])
    blobs = truth.marker_blobs
    if blobs is None:
        return render_image(cam.height, cam.width, model, rng, stripe_cols=cols,
                            stripe_rows=rows, stripe_gain=gain, marker_xy=truth.marker_pixels)
    return render_image(cam.height, cam.width, model, rng, stripe_cols=cols, stripe_rows=rows,
                        stripe_gain=gain, marker_xy=blobs[:, :2], marker_gain=blobs[:, 2],
                        marker_sigma=blobs[:, 3])


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


def slice_mesh(vertices, faces, normal, offset) -> tuple[np.ndarray, np.ndarray]:
    """Cut a triangle mesh with the plane ``normal . x = offset``.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int
    normal : (3,) float64
    offset : float

    Returns
    -------
    segments : (K, 2, 3) float64
        One segment per face that crosses the plane.
    face_index : (K,) int64
    """
    s = vertices @ normal - offset
    sf = s[faces]
    above = sf >= 0.0  # a vertex on the plane counts as above: no face yields a point-segment twice
    crossing = above.any(axis=1) & ~above.all(axis=1)
    index = np.nonzero(crossing)[0]
    if len(index) == 0:
        return np.zeros((0, 2, 3)), index
    v = vertices[faces[index]]
    sv = sf[index]
    av = above[index]
    points = np.empty((len(index), 3, 3))
    cuts = np.empty((len(index), 3), dtype=bool)
    for e, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        cuts[:, e] = av[:, a] != av[:, b]
        with np.errstate(divide="ignore", invalid="ignore"):  # uncut edges are discarded below
            t = sv[:, a] / (sv[:, a] - sv[:, b])
            points[:, e] = v[:, a] + t[:, None] * (v[:, b] - v[:, a])
    # Exactly two edges of a crossing face are cut; take them in edge order.
    order = np.argsort(~cuts, axis=1, kind="stable")[:, :2]
    segments = np.take_along_axis(points, order[:, :, None], axis=1)
    return segments, index


def column_hits(segments_p, pose_b, camera, columns):
    """Where the section segments fall in each image column, weighted by pixel coverage.

    A camera integrates over each pixel's area: pixel column ``c`` covers ``u`` in
    ``[c - 0.5, c + 0.5]``. A segment projecting to ``[u_min, u_max]`` gives one sample to
    every column it overlaps, taken at the middle of the overlap (where that column plane,
    through the camera centre, cuts the segment), with the overlap's share of the pixel as its
    coverage: the last column of a stripe that ends inside it is lit in proportion to the
    part it covers, and two segments meeting inside a column give two partial samples whose
    coverages add up to 1 (for a straight section, their coverage-weighted row is the row at
    the column's centre). Overlaps of zero length (a segment along a line of sight) give no
    sample.

    Parameters
    ----------
    segments_p : (K, 2, 3) float64
        Section segments in {P}, mm.
    pose_b : (4, 4) float64
        ^B X_P.
    camera : PinholeCamera
    columns : (2,) int
        The view's columns, half-open ``[c0, c1)``: coverage is counted within
        ``[c0 - 0.5, c1 - 0.5]``.

    Returns
    -------
    cols : (N,) int64
    rows : (N,) float64
        Exact sub-pixel row at the middle of the overlap.
    points_p : (N, 3) float64
        The 3-D point there, in {P}.
    segment : (N,) int64
        Which segment it came from.
    coverage : (N,) float64
        Share of the pixel column the segment covers, in (0, 1].
    """
    if len(segments_p) == 0:
        return (np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64),
                np.zeros(0))
    if camera.distorted:
        return _column_hits_through_lens(segments_p, pose_b, camera, columns)
    seg_b = apply_transform(pose_b, segments_p.reshape(-1, 3))
    q = camera.to_camera(seg_b).reshape(-1, 2, 3)
    qa, qb = q[:, 0], q[:, 1]
    front = (qa[:, 2] > 0) & (qb[:, 2] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ua = camera.fx * qa[:, 0] / qa[:, 2] + camera.cx
        ub = camera.fx * qb[:, 0] / qb[:, 2] + camera.cx
    umin = np.clip(np.minimum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    umax = np.clip(np.maximum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    # Columns whose pixel [c - 0.5, c + 0.5] overlaps [umin, umax] (a span ending on a pixel
    # boundary does not reach into the next pixel).
    first = np.floor(umin + 0.5)
    last = np.ceil(umax + 0.5) - 1.0
    spans = front & (umax > umin)
    counts = np.where(spans, last - first + 1.0, 0.0).astype(np.int64)
    segment = np.repeat(np.arange(len(q)), counts)
    starts = np.repeat(np.where(spans, first, 0.0).astype(np.int64), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cols = starts + offsets
    lo = np.maximum(umin[segment], cols - 0.5)
    hi = np.minimum(umax[segment], cols + 0.5)
    coverage = hi - lo
    keep = coverage > 0.0
    cols, segment, coverage = cols[keep], segment[keep], coverage[keep]
    u = 0.5 * (lo[keep] + hi[keep])  # the middle of the overlap
    k = (u - camera.cx) / camera.fx
    a, b = qa[segment], qb[segment]
    d = b - a
    t = (k * a[:, 2] - a[:, 0]) / (d[:, 0] - k * d[:, 2])
    t = np.clip(t, 0.0, 1.0)
    x = a + t[:, None] * d
    rows = camera.fy * x[:, 1] / x[:, 2] + camera.cy
    points_p = segments_p[segment, 0] + t[:, None] * (segments_p[segment, 1] - segments_p[segment, 0])
    return cols, rows, points_p, segment, coverage


#: Through a distorting lens, section segments are cut into pieces at most this long in the
#: image (px) and each piece taken as straight there: the lens bends a 100 px stripe by pixels,
#: a 0.5 px piece by less than 1e-4 px.
LENS_PIECE_PX = 0.5


def _column_hits_through_lens(segments_p, pose_b, camera, columns):
    """:func:`column_hits` for a camera whose lens distorts: a pixel column is no longer a
    plane through the camera centre, so the segments are cut into short pieces, each piece's
    ends projected through the lens and the piece taken as straight in the image."""
    seg_b = apply_transform(pose_b, segments_p.reshape(-1, 3)).reshape(-1, 2, 3)
    ideal = camera.without_distortion()
    ends = ideal.project(seg_b.reshape(-1, 3)).reshape(-1, 2, 2)
    span = np.abs(ends[:, 1] - ends[:, 0]).max(axis=1)
    ok = np.isfinite(span)
    pieces = np.where(ok, np.ceil(np.where(ok, span, 0.0) / LENS_PIECE_PX), 0).astype(np.int64)
    pieces = np.maximum(pieces, ok.astype(np.int64))
    segment = np.repeat(np.arange(len(seg_b)), pieces)
    k = np.arange(pieces.sum()) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    t0 = k / pieces[segment]
    t1 = (k + 1) / pieces[segment]
    a, d = segments_p[segment, 0], segments_p[segment, 1] - segments_p[segment, 0]
    pa, pb = a + t0[:, None] * d, a + t1[:, None] * d
    px = camera.project(apply_transform(pose_b, np.concatenate([pa, pb]))).reshape(2, -1, 2)
    ua, va, ub, vb = px[0, :, 0], px[0, :, 1], px[1, :, 0], px[1, :, 1]
    umin = np.clip(np.minimum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    umax = np.clip(np.maximum(ua, ub), columns[0] - 0.5, columns[1] - 0.5)
    first = np.floor(umin + 0.5)
    last = np.ceil(umax + 0.5) - 1.0
    spans = np.isfinite(ua) & np.isfinite(ub) & (umax > umin)
    counts = np.where(spans, last - first + 1.0, 0.0).astype(np.int64)
    piece = np.repeat(np.arange(len(ua)), counts)
    starts = np.repeat(np.where(spans, first, 0.0).astype(np.int64), counts)
    cols = starts + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    lo = np.maximum(umin[piece], cols - 0.5)
    hi = np.minimum(umax[piece], cols + 0.5)
    coverage = hi - lo
    keep = coverage > 0.0
    cols, piece, coverage = cols[keep], piece[keep], coverage[keep]
    u = 0.5 * (lo[keep] + hi[keep])
    t = np.clip((u - ua[piece]) / (ub[piece] - ua[piece]), 0.0, 1.0)
    rows = va[piece] + t * (vb[piece] - va[piece])
    points_p = pa[piece] + t[:, None] * (pb[piece] - pa[piece])
    # One sample per segment and column, as without a lens: the pieces' coverage-weighted mean.
    seg = segment[piece]
    key, first, group = np.unique(seg * (int(columns[1]) + 1) + cols, return_index=True,
                                  return_inverse=True)
    weight = np.bincount(group, coverage)
    rows = np.bincount(group, coverage * rows) / weight
    points_p = np.stack([np.bincount(group, coverage * points_p[:, i]) for i in range(3)], 1)
    return cols[first], rows, points_p / weight[:, None], seg[first], weight
