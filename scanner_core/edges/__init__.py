"""Edge points along one profile: drop-outs evaluated by size, discontinuities by range.

Paper section II: "edges can be defined as discontinuities or drop-outs in the intensity of
the line. Drop-outs are evaluated by size, and discontinuities are evaluated by range in order
to certify whether the discontinuity represents a step in the part surface or an edge on the
part [...] The edge is defined as half the relative step height."

One profile is one frame's per-column stripe measurement (``scanner_core.stripe.extractor.extract``)
over the direct view. Its valid columns are triangulated into the light plane, where each
point gets two in-plane coordinates (mm, in {C} units):

- ``a``, along the stripe: the camera's x axis (image columns) projected into the sheet;
- ``d``, the *range*: in the sheet, perpendicular to ``a``, growing away from the camera.
  In the reference cell ``d`` runs along z_B = -z_T: the depth of the part's underside.

Along the profile (columns in order):

- **Drop-outs.** Runs of columns without a stripe are gaps. A gap with fewer than
  ``min_gap_px`` dark columns is noise (a speck, a dark column of speckle) and is bridged: the
  columns on either side stay neighbours. A larger gap bounded by stripe on one or both sides
  is a drop-out: the part's outline, a hole's rim, a shadow. Each bounding side gets one edge
  point where the stripe's peak intensity falls to half way between its level on that side
  and the level in the gap ("half the relative step", interpolated between columns); where
  the end is sharp (no column but the last lit in part), the last column's lit share of the
  side's level over the background places it within that column instead, which the half
  step, interpolated, misses by up to 0.08 px between the column's sides and middle. Its
  row is extrapolated from that side's rows, then triangulated. When the two sides of a gap
  lie at different ranges (by more than the step threshold and ``FAR_SIDE_SIGMAS`` standard
  errors of their lines extrapolated to the gap's middle), the far side is the boundary of a
  shadow or of an occlusion cast by the near side's edge, not an edge of the part: only the
  near side gives an edge point (``EdgeParams.keep_far_side``). A side's level is taken at the
  top of its falling flank, short of where its rows turn (a dimmer chamfer next to the gap
  keeps its own level); a side under ``min_contrast`` times its gap's level ends in the noise
  and gives no edge point.
- **Steps.** Between neighbouring valid columns (bridged gaps included) a jump in range,
  after removing the local slope of the surface, larger than the step threshold
  (``max(min_step_mm, noise_factor * point-to-point scatter)``) marks a step; a run of up to
  ``max_ramp_px`` such jumps of one sign is one step seen over a few columns (an inclined
  wall, a chamfer). Lines fitted to each side give the relative step height ``h`` at the
  step; the edge point lies at half of it. Where the step is resolved (its half-height level
  falls between two adjacent columns that hold less than half of it) the point is
  interpolated there; otherwise (a jump within one column, or across a bridged gap) the wall
  stands at the near side's boundary: where the near side's stripe falls to half its level, as
  a drop-out's (a pixel column holding the wall is lit in part by the near surface, in
  proportion to the share of the pixel it covers; a column holding both sides' stripes is
  taken as half lit by each when rejected as a double, and as lit by the near side at
  ``DOUBLE_SHARE`` of its peak when measured on one of two peaks, ``StripeResult.n_peaks``),
  and the point is that boundary on the near surface
  moved by ``h / 2`` along ``d``: walls are taken to run along the range axis (vertical walls
  in the reference cell), so in {T} the point projects onto the wall's top and bottom edges.
  A step with a side cut short by another edge must be ``SHORT_SIDE_STEP_FACTOR`` times the
  threshold high (a chamfer's slope at the rim of a larger step is no step of its own).
- **Surfaces curving away.** A side whose rows turn steadily up to its end, past their
  crest (``scanner_core.edges.kernel._curls``), ends where the stripe is lost on a surface
  rounding off, not at an edge: neither a drop-out nor a step is placed there.

Drop-outs at the boundary of an occlusion by a feature outside the sheet look, in one profile,
like a rim: :func:`occluded_dropouts` finds them in the scan. A chamfer narrower than two
columns at an outline lights the stripe's last column or two at a level of its own, which one
profile cannot tell from where the outline lies in its last column: each drop-out reports its
stripe's end (``EdgePoints.stripe_end``), and :func:`chamfered_dropouts` fits the chamfer
along the edge's profiles and places their points at the outline.

Speed: one numba kernel over the profile: 0.05-0.1 ms per 1920-column frame with 1000 valid
columns, about 0.15 ms in a pass with the frame cold in the cache (2 cores, see
``tests/scanner_core/test_edges.py``). The first call loads the compiled kernel (10-20 ms; a
few seconds when it compiles): warm it up before a pass.

The parts live in modules of their own: one profile's detection in ``scanner_core.edges.profile``
(`find_edges` and its types) over its compiled kernel, ``scanner_core.edges.kernel`` (where the
constants of the method are); the scan-level filters in ``scanner_core.edges.filters``; the
edge kinds a scan sets aside in ``scanner_core.edges.kinds``. This module gathers the public
names.

References
----------
.. [1] "Fast visual part inspection for bin picking", section II.
"""
from __future__ import annotations

from scanner_core.edges.filters import (CHAIN_DEG, CHAIN_FRAMES, CHAIN_MIN_MM, CHAIN_SPACINGS,
                                        CHAMFER_MAX_LEVEL, CHAMFER_MIN_GAIN, CHAMFER_MIN_POINTS,
                                        GRAZING_DEG, LONE_PROFILE_REACH, chamfered_dropouts,
                                        grazing_edges, occluded_dropouts)
from scanner_core.edges.kernel import (BEND_NOISE_FACTOR, CURL_MAX_TURNS, CURL_MIN_TURNS,
                                       CURL_NOISE_FACTOR, CURL_PX, CURL_SHARE, DOUBLE_SHARE,
                                       END_FACE_FROM, END_FACE_PX, FAR_SIDE_SIGMAS, FLANK_RISE,
                                       LEVEL_PX, MAD_TO_SIGMA, MIN_NOISE_SAMPLES,
                                       RESOLVED_STEP_FRACTION, ROW_BEND_PX,
                                       SHORT_SIDE_STEP_FACTOR)
from scanner_core.edges.profile import (MIN_COLUMN_COMPONENT, EdgeKind, EdgeParams, EdgePoints,
                                        find_edges, profile_axes)

__all__ = ["EdgeKind", "EdgeParams", "EdgePoints", "find_edges", "occluded_dropouts",
           "grazing_edges", "chamfered_dropouts", "profile_axes",
           # the method's constants, importable from here as before
           "RESOLVED_STEP_FRACTION", "FLANK_RISE", "LEVEL_PX", "ROW_BEND_PX",
           "BEND_NOISE_FACTOR", "SHORT_SIDE_STEP_FACTOR", "CURL_PX", "CURL_SHARE",
           "CURL_NOISE_FACTOR", "CURL_MAX_TURNS", "CURL_MIN_TURNS", "FAR_SIDE_SIGMAS",
           "END_FACE_FROM", "END_FACE_PX", "DOUBLE_SHARE", "MAD_TO_SIGMA",
           "MIN_COLUMN_COMPONENT", "MIN_NOISE_SAMPLES", "CHAMFER_MAX_LEVEL",
           "CHAMFER_MIN_POINTS", "CHAMFER_MIN_GAIN", "CHAIN_FRAMES", "CHAIN_DEG",
           "CHAIN_SPACINGS", "CHAIN_MIN_MM", "GRAZING_DEG", "LONE_PROFILE_REACH"]
