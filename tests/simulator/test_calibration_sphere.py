"""The simulated calibration sphere is the sphere the calibration assumes: its faceted
surface's mean radius is the stated one (the facets of an icosphere through points of the
sphere lie inside it, by 1.3 um on average at its subdivision, which the light plane's fit
took as a shift of about 1 um)."""
import numpy as np
import trimesh

from simulator.calsession import SPHERE_SUBDIVISIONS, mean_radius, sphere_part


def test_the_sphere_s_surface_lies_at_its_radius_on_average():
    radius = 28.625
    faceted = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=radius)
    points, _ = trimesh.sample.sample_surface(faceted, 200_000, seed=3)
    deficit = radius - np.linalg.norm(points, axis=1).mean()
    assert 1.0e-3 < deficit < 1.6e-3  # the plain icosphere's facets: 1.3 um inside
    assert abs((radius - mean_radius(faceted)) - deficit) < 0.05e-3  # the quadrature agrees
    mesh = sphere_part(radius).mesh
    points, _ = trimesh.sample.sample_surface(mesh, 200_000, seed=4)
    r = np.linalg.norm(points, axis=1)
    assert abs(r.mean() - radius) < 0.05e-3
    assert np.all(np.abs(r - radius) < 2.0e-3)  # within 2 um everywhere
