"""The targets the benchmarks hold the scanner to, where more than one benchmark scores them.

A benchmark's own targets (a stripe's time against a copy of the frame, the simulator's rays per
second, ...) stay beside the figure they judge; these are the ones several benchmarks share, so
that a target read in ``bench pose`` is the one ``bench pose`` limits and ``bench edges`` check.
"""
from __future__ import annotations

__all__ = ["TARGET_TRANSLATION_UM", "TARGET_ROTATION_MDEG", "SIGMA_BOUND",
           "TARGET_EDGE_RMS_UM", "TARGET_EDGE_OUTLIERS", "EDGE_OUTLIER_MM"]

#: The part's pose: the error of the {T} origin, um, and of the turn, mdeg.
TARGET_TRANSLATION_UM = 20.0
TARGET_ROTATION_MDEG = 20.0
#: An unflagged error beyond this many reported sigma is not bounded by the reported std.
SIGMA_BOUND = 3.0

#: The edge cloud against the CAD's sharp edges, in (x_T, y_T): an RMS within
#: TARGET_EDGE_RMS_UM and at most TARGET_EDGE_OUTLIERS of the points farther than
#: EDGE_OUTLIER_MM from every edge (``simulator.evaluate.edge_accuracy``'s outliers).
TARGET_EDGE_RMS_UM = 30.0
TARGET_EDGE_OUTLIERS = 0.05
EDGE_OUTLIER_MM = 0.5
