"""Provenance of cloud points against the renderer's stripe samples (simulator.evaluate)."""
import numpy as np

from simulator.evaluate import PROVENANCE_TOL_MM, unmatched
from simulator.render import FrameTruth


def _truth(columns, rows, points_b):
    n = len(columns)
    return FrameTruth(tcp_b=np.zeros(3), part_pose_b=np.eye(4),
                      stripe_columns=np.asarray(columns, np.int32),
                      stripe_rows=np.asarray(rows, np.float64),
                      stripe_points_b=np.asarray(points_b, np.float64),
                      stripe_gain=np.ones(n), marker_b=np.zeros(3),
                      marker_pixels=np.full((3, 2), np.nan))


def test_a_blend_of_the_samples_of_one_column_has_a_visible_source():
    """Column 10 holds a sample on a surface and one 1 mm away on a wall: the stripe measured
    there blends them, anywhere between. A point that far between samples of two different
    columns, or off the chord, has no source."""
    truths = {
        0: _truth([10, 10, 11], [500.0, 497.0, 500.0],
                  [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.16, 0.0, 0.0]]),
        1: _truth([10, 11], [500.0, 497.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    }
    off = 2.0 * PROVENANCE_TOL_MM
    cloud = np.array([[0.0, 0.0, 0.5],  # on the chord of column 10, frame 0
                      [0.0, 0.0, 0.93],  # near its end
                      [off, 0.0, 0.5],  # off the chord
                      [0.0, 0.0, 0.5]])  # frame 1: the two samples are in different columns
    frames = np.array([0, 0, 0, 1])
    assert unmatched(cloud, frames, truths, np.eye(3)).tolist() == [False, False, True, True]
