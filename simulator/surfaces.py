"""How a part's surface returns the laser: a diffuse albedo, a specular lobe, one bounce.

The reference image model's stripe (200 DN at gain 1) is a matte white surface lit head-on.
Real parts differ: a dark anodised part returns a tenth of that, machined metal
returns little diffusely but glints many times over full scale where the laser's mirror
direction meets the camera, and a shiny concave part throws part of the laser onto another of
its own surfaces, which shows as a second stripe. Per stripe sample, the brightness relative to
the reference (``FrameTruth.stripe_gain``) is

``albedo * |cos i| + specular * exp(-theta^2 / (2 lobe^2))``

with ``i`` the laser's incidence and ``theta`` the angle between the laser's mirror direction
and the direction to the camera (a Gaussian lobe, the small-angle form of the Torrance-Sparrow
/ Beckmann microfacet lobe [1]_); and a fraction ``mirror`` of the laser goes on along the mirror
direction, lighting the first surface it meets (one bounce; further bounces carry ``mirror``
squared and less).

References
----------
.. [1] K. E. Torrance and E. M. Sparrow, "Theory for off-specular reflection from roughened
   surfaces", J. Opt. Soc. Am. 57(9), pp. 1105-1114, 1967.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from scanner_core.geometry import angle_between

__all__ = ["Surface", "SURFACES", "surface_gain", "mirror_directions", "with_surface"]


@dataclass(frozen=True)
class Surface:
    """A part's reflectance, relative to the reference model's matte white.

    Attributes
    ----------
    albedo : float
        Diffuse share: the stripe's brightness lit head-on, x the reference's.
    specular : float
        Peak of the specular lobe toward the camera, x the reference's stripe (may exceed full
        scale many times over).
    lobe_deg : float
        Width (sigma) of the lobe, degrees: the surface's roughness.
    mirror : float
        Share of the laser's power reflected on along the mirror direction (one bounce).
    """

    albedo: float = 1.0
    specular: float = 0.0
    lobe_deg: float = 10.0
    mirror: float = 0.0

    def __post_init__(self):
        for name in ("albedo", "specular", "mirror"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"surface `{name}` must be >= 0, got {value!r}")
        if not (np.isfinite(self.lobe_deg) and self.lobe_deg > 0):
            raise ValueError(f"surface `lobe_deg` must be > 0, got {self.lobe_deg!r}")
        if self.mirror > 1:
            raise ValueError(f"surface `mirror` is a share of the laser's power, got {self.mirror}")


#: Presets. Plausible numbers, not measurements of one material:
#: - matte: sand-cast or bead-blasted metal, a near-Lambertian grey (80 % of white);
#: - dark: black anodised aluminium, ~8 % diffuse reflectance, a weak broad sheen;
#: - shiny: machined (turned or milled) aluminium: little diffuse return from the tool marks,
#:   a narrow lobe 8 times full brightness, and most of the laser mirrored onward.
SURFACES = {
    "default": Surface(),
    "matte": Surface(albedo=0.8),
    "dark": Surface(albedo=0.08, specular=0.3, lobe_deg=15.0, mirror=0.02),
    "shiny": Surface(albedo=0.25, specular=8.0, lobe_deg=5.0, mirror=0.6),
}


def mirror_directions(incoming, normals) -> np.ndarray:
    """Mirror directions ``d - 2 (d . n) n`` of unit rays ``incoming`` (N, 3) on surfaces of
    unit ``normals`` (N, 3) (either orientation): (N, 3), unit."""
    d = np.asarray(incoming, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    return d - 2.0 * np.einsum("ij,ij->i", d, n)[:, None] * n


def surface_gain(surface: Surface, incoming, normals, to_camera) -> np.ndarray:
    """Brightness of the stripe at each sample relative to the reference model's stripe.

    Parameters
    ----------
    surface : Surface
    incoming : (N, 3) float64
        Unit directions from the laser to the samples.
    normals : (N, 3) float64
        Unit surface normals there (either orientation).
    to_camera : (N, 3) float64
        Unit directions from the samples to the camera.

    Returns
    -------
    (N,) float64
        ``albedo |cos i| + specular exp(-theta^2 / (2 lobe^2))``.
    """
    n = np.asarray(normals, dtype=np.float64)
    d = np.asarray(incoming, dtype=np.float64)
    gain = surface.albedo * np.abs(np.einsum("ij,ij->i", d, n))
    if surface.specular > 0:
        theta = angle_between(mirror_directions(d, n), to_camera)
        gain = gain + surface.specular * np.exp(-0.5 * (theta / np.radians(surface.lobe_deg)) ** 2)
    return gain


def with_surface(part, surface):
    """The part with another surface: a ``Surface`` or the name of one of ``SURFACES``."""
    if isinstance(surface, str):
        try:
            surface = SURFACES[surface]
        except KeyError:
            raise ValueError(f"unknown surface {surface!r}; one of {sorted(SURFACES)}") from None
    if not isinstance(surface, Surface):
        raise TypeError(f"`surface` must be a Surface or a preset name, got {type(surface).__name__}")
    new = dataclasses.replace(part, surface=surface)
    for cached in ("mesh", "bounds", "intersector", "surface_model", "edge_model"):
        if cached in part.__dict__:  # same geometry: keep what was built (the Embree scene)
            new.__dict__[cached] = part.__dict__[cached]
    return new
