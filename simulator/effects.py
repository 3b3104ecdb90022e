"""What a real cell does that the ideal simulated one does not (the "realistic cell").

Each effect has a setting and a plausible default for a real cell; the reference cell has them
all off, ``realistic_cell`` turns on some or all of them. The scanner is told none of it: it
learns what it can from data (``flyscan calibrate``) and the evaluation alone reads the truth.

- ``lens``: radial and tangential distortion of a 16 mm machine-vision lens (about 10 px at
  the corners of the 1920 x 1200 sensor). Goes into the true camera.
- ``exposure``: the part moves during the exposure (0.2 mm at 200 mm/s and 1 ms): each frame
  integrates ``BLUR_SAMPLES`` instants across it (``simulator.render.blur_truths``), the
  frame's time stamp at its start; the LED, strobed at the exposure's middle, stays sharp.
- ``clocks``: the robot's clock runs ahead of the camera's by an offset and drifts.
- ``robot``: the robot reports its TCP with a little noise, and its orientation a little off
  (a real arm's kinematics are calibrated to a few thousandths of a degree at best).
- ``led``: the LED has a radius: its blob is as large as the LED looks from that view (the
  mirror views look from farther away), not a fixed 2.5 px; and in a perturbed cell it sits
  off the drawing by a few tenths of a millimetre (``LED_MOUNT_MM``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

EFFECTS = ("lens", "exposure", "clocks", "robot", "led")
#: How far the LED sits from where the drawing puts it, one sigma per axis, mm (perturbed cells).
LED_MOUNT_MM = 0.3
#: Instants a blurred frame averages over its exposure.
BLUR_SAMPLES = 5
#: A real 16 mm lens on a 2/3" sensor: k1, k2, p1, p2, k3 (OpenCV's order).
REAL_LENS_DISTORTION = (-0.08, 0.12, 2.0e-4, -1.0e-4, 0.0)


@dataclass(frozen=True)
class CellEffects:
    """The effects of a real cell, each off by default.

    Attributes
    ----------
    exposure_blur : bool
        Frames integrate the motion over their exposure.
    clock_offset_s : float
        The robot's clock minus the camera's at the start of the pass, s.
    clock_drift_ppm : float
        How much faster the robot's clock runs, parts per million.
    tcp_noise_mm : float
        Standard deviation of the robot's reported TCP position, per axis and sample, mm.
    tcp_rotation_error_deg : float
        Angle between the reported and the true orientation of the tool, degrees (about a
        fixed axis, ``tcp_rotation_axis``).
    tcp_rotation_axis : (3,) tuple of float
    led_radius_mm : float
        Radius of the LED; 0 keeps the image model's fixed blob.
    seed : int
        Seeds the robot's reporting noise.
    """

    exposure_blur: bool = False
    clock_offset_s: float = 0.0
    clock_drift_ppm: float = 0.0
    tcp_noise_mm: float = 0.0
    tcp_rotation_error_deg: float = 0.0
    tcp_rotation_axis: tuple = (0.6, 0.0, 0.8)
    led_radius_mm: float = 0.0
    seed: int = 0

    @property
    def robot_rotation_error(self) -> np.ndarray:
        """(3, 3): reported rotation = this @ true rotation."""
        from scipy.spatial.transform import Rotation

        axis = np.asarray(self.tcp_rotation_axis, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        return Rotation.from_rotvec(np.radians(self.tcp_rotation_error_deg) * axis).as_matrix()

    def robot_time(self, t_camera):
        """The robot's clock at camera time(s) ``t_camera``, s."""
        if isinstance(t_camera, float):  # the robot's per-frame lookups: no numpy on scalars
            return self.clock_offset_s + (1.0 + 1e-6 * self.clock_drift_ppm) * t_camera
        return self.clock_offset_s + (1.0 + 1e-6 * self.clock_drift_ppm) * np.asarray(t_camera)

    def camera_time(self, t_robot):
        """The inverse of :meth:`robot_time`."""
        if isinstance(t_robot, float):  # the robot's per-frame lookups: no numpy on scalars
            return (t_robot - self.clock_offset_s) / (1.0 + 1e-6 * self.clock_drift_ppm)
        return (np.asarray(t_robot) - self.clock_offset_s) / (1.0 + 1e-6 * self.clock_drift_ppm)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["tcp_rotation_axis"] = list(self.tcp_rotation_axis)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "CellEffects":
        data = dict(data)
        if "tcp_rotation_axis" in data:
            data["tcp_rotation_axis"] = tuple(data["tcp_rotation_axis"])
        return cls(**data)


#: The defaults of a real cell, effect by effect (lens distortion lives in the camera).
REAL_CELL = CellEffects(exposure_blur=True, clock_offset_s=0.0125, clock_drift_ppm=30.0,
                        tcp_noise_mm=0.005, tcp_rotation_error_deg=0.002, led_radius_mm=1.5)


def parse_effects(text: str | None) -> tuple[str, ...]:
    """``"all"``, ``"none"`` or a comma-separated subset of EFFECTS; ValueError naming the
    unknown ones."""
    if text is None or text.strip() in ("", "none"):
        return ()
    if text.strip() == "all":
        return EFFECTS
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown cell effect(s) {unknown}: choose from {', '.join(EFFECTS)}, "
                         f"'all' or 'none'")
    return names


def realistic_cell(cell, effects=EFFECTS, *, seed: int | None = None):
    """``cell`` with the chosen effects of a real cell switched on at their defaults.

    With ``seed`` (``--perturb-seed``), the effects' sizes move too: the lens's coefficients by
    10 %, the clock offset by 5 ms, the drift by 20 ppm, the orientation error's axis.
    """
    unknown = [n for n in effects if n not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown cell effect(s) {unknown}: choose from {', '.join(EFFECTS)}")
    on = set(effects)
    real = REAL_CELL
    lens = REAL_LENS_DISTORTION
    if seed is not None:
        rng = np.random.default_rng([0xEFFEC7, seed])
        lens = tuple(float(v) for v in np.asarray(lens) * (1.0 + 0.1 * rng.standard_normal(5)))
        axis = rng.standard_normal(3)
        real = replace(real, clock_offset_s=real.clock_offset_s + 0.005 * rng.standard_normal(),
                       clock_drift_ppm=real.clock_drift_ppm + 20.0 * rng.standard_normal(),
                       tcp_rotation_axis=tuple(float(v) for v in axis / np.linalg.norm(axis)),
                       seed=int(seed))
    off = CellEffects()
    effects_now = CellEffects(
        exposure_blur=real.exposure_blur if "exposure" in on else off.exposure_blur,
        clock_offset_s=real.clock_offset_s if "clocks" in on else 0.0,
        clock_drift_ppm=real.clock_drift_ppm if "clocks" in on else 0.0,
        tcp_noise_mm=real.tcp_noise_mm if "robot" in on else 0.0,
        tcp_rotation_error_deg=real.tcp_rotation_error_deg if "robot" in on else 0.0,
        tcp_rotation_axis=real.tcp_rotation_axis,
        led_radius_mm=real.led_radius_mm if "led" in on else 0.0,
        seed=real.seed)
    cal = cell.calibration
    camera = replace(cal.camera, distortion=lens if "lens" in on else cal.camera.distortion)
    marker = cal.marker_offset_t
    if seed is not None and "led" in on:
        # The LED as mounted, off the drawing by a few tenths of a millimetre.
        marker = marker + LED_MOUNT_MM * np.random.default_rng([0x1ED, seed]).standard_normal(3)
    return replace(cell, calibration=replace(cal, camera=camera, marker_offset_t=marker),
                   effects=effects_now)


