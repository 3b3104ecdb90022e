"""The real-surfaces benchmark's pieces, and its cloud target on the demo block."""
import pytest

from benchmarks import surfaces as bench
from simulator.cell import load_cell
from simulator.surfaces import SURFACES

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def rows(block_part):
    cell = load_cell()
    runs = {}
    for preset, mode in (("matte", "fixed"), ("matte", "multiple"), ("shiny", "fixed"),
                         ("shiny", "dynamic"), ("shiny", "multiple")):
        runs[preset, mode] = bench.scan_row(block_part, SURFACES[preset], mode, cell, label=preset)
    return runs


def test_shiny_part_with_exposure_control_meets_the_target(rows):
    """the shiny preset with dynamic or multiple exposure keeps >= 95 % of the matte
    preset's points, RMS within 1.5x. Measured on the block: dynamic 0.97 of the points at
    0.99x the RMS of the matte preset at the fixed exposure; multiple 1.00 and 1.13x against the
    matte preset at multiple exposure (one measurement per column per pair of frames)."""
    dynamic = bench._ratios(rows["shiny", "dynamic"], rows["matte", "fixed"])
    multiple = bench._ratios(rows["shiny", "multiple"], rows["matte", "multiple"])
    assert dynamic["within"], dynamic
    assert multiple["within"], multiple
    # without exposure control the shiny block's dim diffuse return costs accuracy
    fixed = bench._ratios(rows["shiny", "fixed"], rows["matte", "fixed"])
    assert fixed["rms_ratio"] > 2.0


def test_rows_carry_the_truth_figures(rows):
    row = rows["matte", "fixed"]
    assert row["points"] > 5000 and row["rms_um"] < 20.0
    assert row["surface_params"] == {"albedo": 0.8, "specular": 0.0, "lobe_deg": 10.0,
                                     "mirror": 0.0}


def test_breaks_are_the_first_level_off_target():
    def row(mode, albedo, points, rms):
        r = {"exposure": mode, "surface_params": {"albedo": albedo}, "points": points,
             "rms_um": rms}
        r.update(bench._ratios(r, {"points": 1000, "rms_um": 10.0}))
        return r

    rows = [row("fixed", 1.0, 1000, 10.0), row("fixed", 0.5, 990, 12.0), row("fixed", 0.25, 900, 12.0),
            row("dynamic", 1.0, 1000, 10.0), row("dynamic", 0.5, 1000, 16.0),
            row("dynamic", 0.25, 1000, 10.0)]
    breaks = bench._breaks(rows, "albedo", (1.0, 0.5, 0.25))
    assert breaks == {"fixed": 0.25, "dynamic": 0.5}
