"""The scan simulator's inputs (``simulator.virtual_setup``): where the light source and the
camera stand at step 0, the two densities, and further viewpoints.

:class:`VirtualSetup` holds and checks them (:class:`SetupError` when they cannot sweep a
part); :func:`reference_setup` places them as the reference cell has them, in {T}.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from scanner_core.geometry import apply_transform, base_to_tcp, reflection_matrix, unit

__all__ = ["SetupError", "VirtualSetup", "reference_setup", "DEFAULT_STEP_MM",
           "DEFAULT_RAYS_PER_LINE", "MAIN_VIEW"]

DEFAULT_STEP_MM = 0.5
DEFAULT_RAYS_PER_LINE = 1000
#: The camera's name among a sweep's viewpoints: the one whose sight keeps a point.
MAIN_VIEW = "camera"


class SetupError(ValueError):
    """The virtual setup cannot sweep this part: a bad density, or a source or camera that
    stands in, or passes through, the part, or a source level with it."""


@dataclass(frozen=True)
class VirtualSetup:
    """The paper's inputs: where the light source and the camera stand, and the densities.

    Attributes
    ----------
    laser : (3,) float64
        Light source position at step 0, mm, in the setup frame.
    camera : (3,) float64
        Camera position (projection centre) at step 0, mm.
    step_mm : float
        Step size (the paper's StRs): how far the setup moves between two lines, mm.
    rays_per_line : int
        Rays in each line's fan (the depth-buffer resolution).
    views : tuple of (str, (3,) float64)
        Further viewpoints at step 0 (the camera reflected in each mirror, say): each point
        records whether it sees them; they do not filter the cloud.
    motion : (3,) float64
        Unit direction the setup moves along, relative to the part (+y of the setup frame).
    fan : (R, 3) float64, optional
        The line's ray directions, unit vectors across the motion (R = `rays_per_line`).
        By default the fan is fitted to the part: aimed at its centre, just covering it. Fix
        it (`with_fan`) to sweep several meshes of one part with the very same rays.
    """

    laser: np.ndarray
    camera: np.ndarray
    step_mm: float = DEFAULT_STEP_MM
    rays_per_line: int = DEFAULT_RAYS_PER_LINE
    views: tuple = ()
    motion: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fan: np.ndarray | None = None

    def __post_init__(self):
        for name in ("laser", "camera", "motion"):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise SetupError(f"`{name}` must be 3 finite coordinates (mm), got "
                                 f"{getattr(self, name)!r}")
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        if not np.isclose(np.linalg.norm(self.motion), 1.0):
            raise SetupError(f"`motion` must be a unit vector, got {self.motion.tolist()}")
        step = float(self.step_mm)
        if not (np.isfinite(step) and step > 0):
            raise SetupError(f"`step_mm` must be a positive length in mm, got {self.step_mm!r}")
        object.__setattr__(self, "step_mm", step)
        rays = self.rays_per_line
        if isinstance(rays, bool) or int(rays) != rays or rays < 2:
            raise SetupError(f"`rays_per_line` must be a whole number >= 2, got {rays!r}")
        object.__setattr__(self, "rays_per_line", int(rays))
        views = []
        for name, position in self.views:
            p = np.array(position, dtype=np.float64)
            if p.shape != (3,) or not np.all(np.isfinite(p)) or name == MAIN_VIEW:
                raise SetupError(f"view {name!r} needs a name other than {MAIN_VIEW!r} and 3 "
                                 f"finite coordinates, got {position!r}")
            p.setflags(write=False)
            views.append((str(name), p))
        object.__setattr__(self, "views", tuple(views))
        if self.fan is not None:
            fan = np.array(self.fan, dtype=np.float64)
            if (fan.shape != (self.rays_per_line, 3) or not np.all(np.isfinite(fan))
                    or not np.allclose(np.linalg.norm(fan, axis=1), 1.0)
                    or np.abs(fan @ self.motion).max() > 1e-9):
                raise SetupError(f"`fan` must be {self.rays_per_line} unit directions across "
                                 f"the motion, got an array of shape {fan.shape}")
            fan.setflags(write=False)
            object.__setattr__(self, "fan", fan)

    def with_fan(self, fan) -> "VirtualSetup":
        """The same setup with the line's rays fixed to `fan` ((R, 3) unit directions)."""
        return replace(self, fan=fan, rays_per_line=len(fan))

    def laser_at(self, step) -> np.ndarray:
        """Light source position at step number(s) `step`: (3,) or (N, 3) float64, mm."""
        return self._moved(self.laser, step)

    def camera_at(self, step) -> np.ndarray:
        """Camera position at step number(s) `step`: (3,) or (N, 3) float64, mm."""
        return self._moved(self.camera, step)

    def _moved(self, position, step) -> np.ndarray:
        return position + np.multiply.outer(np.asarray(step, np.float64),
                                            self.step_mm * self.motion)


def reference_setup(cell, *, step_mm: float = DEFAULT_STEP_MM,
                    rays_per_line: int = DEFAULT_RAYS_PER_LINE, laser=None, camera=None,
                    mirrors: bool = False) -> VirtualSetup:
    """The reference cell's light source and camera in {T}, at the start of its pass.

    Parameters
    ----------
    cell : simulator.cell.Cell
    step_mm, rays_per_line : float, int
        The densities.
    laser, camera : (3,) array_like, optional
        Positions in {T} at step 0 that replace the cell's.
    mirrors : bool
        Add the camera reflected in each of the cell's mirrors as the views ``left`` and
        ``right`` (the mirrors move with the setup).

    Returns
    -------
    VirtualSetup
        In {T}; it moves along +y_T, as the cell does relative to the part when the robot
        passes along +y_B.
    """
    pp = cell.pass_profile
    tcp_b = np.array([0.0, pp.start_y_mm, pp.height_mm])
    rot_b = cell.gripper_rotation_b
    cal = cell.calibration

    def to_t(point_b):
        return base_to_tcp(np.asarray(point_b, np.float64)[None], tcp_b, rot_b)[0]

    laser_t = to_t(cell.laser_origin_b) if laser is None else laser
    camera_t = to_t(cal.camera.origin) if camera is None else np.asarray(camera, np.float64)
    views = []
    if mirrors:
        # A mirror plane n . x = d in {B} is (R^T n) . x = d - n . tcp in {T}.
        for name, mirror in zip(("left", "right"), cal.mirrors):
            n_b, d_b = mirror.plane.normal, mirror.plane.offset
            flip = reflection_matrix(rot_b.T @ n_b, d_b - n_b @ tcp_b)
            views.append((name, apply_transform(flip, camera_t)))
    motion = unit(rot_b.T @ np.array([0.0, -1.0, 0.0]))  # the cell moves back along the pass
    return VirtualSetup(laser=laser_t, camera=camera_t, step_mm=step_mm,
                        rays_per_line=rays_per_line, views=tuple(views), motion=motion)
