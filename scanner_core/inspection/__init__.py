"""Inspection: is what the gripper holds the expected part, alone and whole? The cloud against
the model at the registered pose: every point's deviation, and the regions of extra or missing
material, of deformation, or a wrong part.

This is the package's public face; its modules hold the code."""
from __future__ import annotations

from scanner_core.inspection.check import (KINDS, Inspection, InspectionParams, Region,
                                           inspect_scan, point_deviations, point_spacing)

__all__ = ["KINDS", "Inspection", "InspectionParams", "Region", "inspect_scan",
           "point_deviations", "point_spacing"]
