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

The frame's ground truth, its image and the blur of an exposure are in
``simulator.frame_truth``; the mesh section and its pixel columns in ``simulator.section``.
This module holds the scene that computes a frame's truth (:class:`PartScene`) and gathers the
public names of the three.
"""
from __future__ import annotations

import dataclasses
from functools import cached_property

import numpy as np

from scanner_core.geometry import apply_transform
from simulator.cell import Cell
from simulator.frame_truth import BLUR_ROW_STEP_PX, FrameTruth, blur_truths, frame_image
from simulator.parts import Part
from simulator.raycast import Intersector
from simulator.section import LENS_PIECE_PX, column_hits, slice_mesh
from simulator.surfaces import mirror_directions, surface_gain

__all__ = ["PartScene", "FrameTruth", "frame_image", "blur_truths", "slice_mesh", "column_hits",
           "BOUNCE_OFFSET_MM", "BLUR_ROW_STEP_PX", "LENS_PIECE_PX"]

#: A bounced ray starts this far along its way, clear of the surface it leaves (mm).
BOUNCE_OFFSET_MM = 1e-3


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
