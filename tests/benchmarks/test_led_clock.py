"""benchmarks.led_clock on one realistic cell: on a calibration pass whose speed only ramps up,
the drifting robot clock reads as a clock error and the LED's offset takes the other side;
on one whose speed goes up and down again (the calibration's) it does not."""
import json

import numpy as np

from benchmarks.led_clock import run


def test_a_pass_symmetric_in_speed_keeps_the_clocks_drift_out_of_the_led(tmp_path):
    # the bench's session (200 LED and 40 sphere positions): with half of them the peak's
    # own scatter (9-10 um along the pass) is half the ramp's bias
    result = run(tmp_path, seeds=[1], positions=(200, 40), progress=lambda _: None)
    written = json.loads((tmp_path / "led_clock.json").read_text())
    assert (tmp_path / "led_clock.png").stat().st_size > 10_000
    rows = {r["speed_shape"]: r for r in written["rows"]}
    assert set(rows) == {"ramp", "peak"}
    along = int(np.argmax(np.abs(rows["ramp"]["pass_direction_t"])))
    assert abs(rows["ramp"]["pass_direction_t"][along]) > 0.99  # the pass runs along one axis
    for row in rows.values():  # on the true clock, within a few um on every axis
        assert max(abs(v) for v in row["led_error_um"]["true_clock"]) < 5.0, row
    ramp = rows["ramp"]["led_error_um"]["fitted"][along]
    peak = rows["peak"]["led_error_um"]["fitted"][along]
    # cell 1 (31.6 ppm): 18.7 um on the ramp, 3.8 on the peak
    assert abs(ramp) > 10.0 and abs(peak) < 0.5 * abs(ramp), (ramp, peak)
    # on the ramp, the clock error times the pass's speed is about that LED error
    shift_um = rows["ramp"]["clock_error_ms"]["fitted"] * rows["ramp"]["speed_mm_s"]["median"]
    assert abs(abs(shift_um) - abs(ramp)) < 0.5 * abs(shift_um), (shift_um, ramp)
    assert result["summary"]["peak"]["max_z"] < 3.0
