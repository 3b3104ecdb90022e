"""Camera, light plane and mirror geometry: the paper's Eq. (1)-(3) and triangulation.

The parts live in modules of their own: the model (vectors and rigid transforms, the pinhole
camera with its lens, planes, mirrors, {B} -> {T}) and its conventions (pixels, {C}, Eq. (1)-(3),
planes) in ``scanner_core.geometry.model``; what is measured with it (the stripe on the light
plane, the marker from the direct and mirror views, with its compiled kernel) in
``scanner_core.geometry.triangulation``. This module gathers their public names.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

from scanner_core.geometry.model import (NO_DISTORTION, PARALLEL_COS, UNDISTORT_ITERATIONS,
                                         UNDISTORT_TOL, Mirror, PinholeCamera, Plane,
                                         angle_between, apply_transform, base_to_tcp,
                                         check_rigid, distort_normalized, planes_moved,
                                         reflection_matrix, undistort_normalized, unit)
from scanner_core.geometry.triangulation import (MAX_RAY_CONDITION, MarkerViews, marker_views,
                                                 reproject_marker, triangulate_marker, triangulate_rays,
                                                 triangulate_stripe)

__all__ = ["PARALLEL_COS", "UNDISTORT_ITERATIONS", "UNDISTORT_TOL", "MAX_RAY_CONDITION",
           "NO_DISTORTION", "unit", "angle_between", "reflection_matrix", "check_rigid",
           "apply_transform", "planes_moved", "base_to_tcp", "distort_normalized",
           "undistort_normalized",
           "PinholeCamera", "Plane", "Mirror", "triangulate_stripe", "triangulate_rays",
           "MarkerViews", "marker_views", "triangulate_marker", "reproject_marker"]
