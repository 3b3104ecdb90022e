"""benchmarks.led_clock on one realistic cell: the calibration's LED offset is off along the
pass by what its clock offset trades against it; on the simulator's true clock it is not."""
import json

import numpy as np

from benchmarks.led_clock import run


def test_the_led_error_along_the_pass_is_the_clocks(tmp_path):
    result = run(tmp_path, seeds=[1], positions=(100, 20), progress=lambda _: None)
    written = json.loads((tmp_path / "led_clock.json").read_text())
    assert (tmp_path / "led_clock.png").stat().st_size > 10_000
    (row,) = written["rows"]
    along = int(np.argmax(np.abs(row["pass_direction_t"])))
    assert abs(row["pass_direction_t"][along]) > 0.99  # the pass runs along one {T} axis
    fitted, on_truth = row["led_error_um"]["fitted"], row["led_error_um"]["true_clock"]
    # on the true clock the LED comes within a few um on every axis (1.5, 0.7, 3.0 with the
    # bench's 200 positions); the fitted one is off along the pass by more
    assert max(abs(v) for v in on_truth) < 5.0, on_truth
    assert abs(fitted[along]) > 3 * abs(on_truth[along]), (fitted, on_truth)
    # the clock error times the pass's speed is about that LED error (one trades against
    # the other): both move the marker along the pass
    shift_um = row["clock_error_ms"]["fitted"] * row["speed_mm_s"]["median"]
    assert abs(abs(shift_um) - abs(fitted[along] - on_truth[along])) < 0.5 * abs(shift_um)
    assert result["rows"][0]["perturb_seed"] == 1
