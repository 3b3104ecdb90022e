"""Where the calibrated LED offset's error comes from: the clocks of the calibration pass.

``flyscan calibrate`` fits the LED's offset from the TCP, ``m`` (mm in {T}), and one clock
offset ``d`` (robot minus camera, s) to the calibration pass
(``scanner_core.pipeline.crosscheck.estimate_led_and_clock``: ``M_i = p(t_i + d) + R(t_i + d) m``). Along
the pass a clock error moves every marker position by the robot's velocity times it, which an
LED offset along the pass direction also does: only the pass's changes of speed tell them
apart, and a robot clock that drifts along a pass whose speed only grows reads as a constant
clock error. For each realistic cell (``--perturb-seed``, every effect) and each shape of the
calibration pass's speed (``"ramp"``: up all the way, a scan's; ``"peak"``: up to the middle
and down again, the calibration pass's), this bench calibrates as ``flyscan
calibrate --sim`` does, runs the calibration pass again and fits the LED three ways on the
same marker positions:

- **fitted**: the calibration's own (one clock offset for the pass, fitted with the LED);
- **true clock**: the LED alone, with the robot clock of every frame taken from the simulator's
  truth (its offset and its drift: evaluation only);
- **with drift**: the LED, a clock offset and a clock drift (ppm) fitted together.

Each LED error is reported per {T} axis, um, beside the calibration's
``marker_offset_std_mm`` and the pass's direction in {T}.

``python -m benchmarks.led_clock OUT [--seeds 1 2 3]`` writes ``led_clock.json`` and
``led_clock.png``.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.results import pyplot, save_figure, write_json
from scanner_core.calibration.session import calibrate_session
from scanner_core.pipeline.crosscheck import clock_and_offset_rows, robot_rotations, track_at
from scanner_core.pipeline import PipelineParams, camera_frames, run_pass
from simulator.calsession import simulate_session, true_robot_clock
from simulator.cell import load_cell
from simulator.effects import realistic_cell

#: The session's LED and sphere positions (``bench calibrate``'s and ``bench place``'s).
SESSION_POSITIONS = (200, 40)
SEEDS = (1, 2, 3, 4, 5)
#: Gauss-Newton steps of the fit with a drift (it converges in 3-4).
DRIFT_ITERATIONS = 8
#: The calibration pass's speed shapes compared (``simulator.cell.SPEED_SHAPES``).
SHAPES = ("ramp", "peak")


def _led_on_clock(robot, marker_b, robot_times) -> np.ndarray:
    """The LED in {T}, mm, by least squares of ``M_i - p(s_i) = R(s_i) m`` at robot times."""
    p, _, ok = track_at(robot, robot_times)
    rotations = robot_rotations(robot, robot_times[ok])
    m, *_ = np.linalg.lstsq(rotations.reshape(-1, 3), (marker_b[ok] - p[ok]).ravel(),
                            rcond=None)
    return m


def _led_with_drift(robot, marker_b, times, start_s) -> tuple[np.ndarray, float, float]:
    """The LED (mm in {T}), the clock offset at the pass's middle (s) and its drift (ppm),
    fitted together: ``M_i = p(t_i + d0 + d1 (t_i - t_mid)) + R m``, Gauss-Newton."""
    d0, d1, middle = float(start_s), 0.0, float(np.median(times))
    m = np.zeros(3)
    for _ in range(DRIFT_ITERATIONS):
        robot_times = times + d0 + d1 * (times - middle)
        p, velocity, ok = track_at(robot, robot_times)
        rows = clock_and_offset_rows(velocity[ok], robot_rotations(robot, robot_times[ok]))
        drift = (velocity[ok] * (times[ok] - middle)[:, None]).ravel()
        a = np.column_stack([rows[:, :1], drift, rows[:, 1:]])
        step, *_ = np.linalg.lstsq(a, (marker_b[ok] - p[ok]).ravel(), rcond=None)
        d0, d1, m = d0 + step[0], d1 + step[1], step[2:]
    return m, d0, d1 * 1e6


def _row(seed: int, shape: str, positions=SESSION_POSITIONS) -> dict:
    t0 = time.perf_counter()
    cell = realistic_cell(load_cell(perturb_seed=seed), seed=seed)
    session = simulate_session(cell, seed=seed, led_count=positions[0],
                               sphere_count=positions[1], pass_speed_shape=shape)
    calibration, _ = calibrate_session(session, seed=seed)
    true_led = cell.calibration.marker_offset_t
    # The calibration pass again, placed with the design's LED and clock, as the session's is.
    nominal = replace(calibration, marker_offset_t=session.nominal.marker_offset_t,
                      clock_offset_s=session.nominal.clock_offset_s)
    camera, robot = session.pass_devices()
    camera.open()
    robot.connect()
    try:
        scan = run_pass(camera_frames(camera), nominal, robot, PipelineParams())
    finally:
        camera.close()
    times = scan.tcp_times
    marker_b = scan.tcp_positions_b + np.einsum("fij,j->fi", scan.tcp_rotations_b,
                                                nominal.marker_offset_t)
    true_clock = true_robot_clock(cell, times)
    on_truth = _led_on_clock(robot, marker_b, true_clock)
    drifting, d0, drift_ppm = _led_with_drift(robot, marker_b, times, calibration.clock_offset_s)
    _, velocity, ok = track_at(robot, true_clock)
    speed = np.linalg.norm(velocity[ok], axis=1)
    heading_b = np.median(velocity[ok], axis=0)
    heading_t = scan.tcp_rotations_b[0].T @ (heading_b / np.linalg.norm(heading_b))
    middle = float(np.median(times))
    true_middle = float(np.interp(middle, times, true_clock - times))
    um = lambda led: np.round((np.asarray(led) - true_led) * 1e3, 2).tolist()  # noqa: E731
    std = calibration.marker_offset_std_mm
    return {
        "perturb_seed": seed, "speed_shape": shape, "frames": int(len(times)),
        "speed_mm_s": {"min": float(speed.min()), "median": float(np.median(speed)),
                       "max": float(speed.max())},
        "pass_direction_t": np.round(heading_t, 3).tolist(),
        "clock_drift_ppm_true": float(cell.effects.clock_drift_ppm),
        "true_clock_change_over_pass_ms": float((true_clock[-1] - times[-1]
                                                 - true_clock[0] + times[0]) * 1e3),
        "led_error_um": {"fitted": um(calibration.marker_offset_t), "true_clock": um(on_truth),
                         "with_drift": um(drifting)},
        "led_std_um": None if std is None else np.round(np.asarray(std) * 1e3, 2).tolist(),
        "clock_error_ms": {"fitted": (calibration.clock_offset_s - true_middle) * 1e3,
                           "with_drift": (d0 - true_middle) * 1e3},
        "drift_ppm_fitted": drift_ppm,
        "time_s": round(time.perf_counter() - t0, 1),
    }


def run(out_dir, seeds=SEEDS, progress=None, positions=SESSION_POSITIONS, shapes=SHAPES) -> dict:
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    rows = []
    with threadpool_limits(limits=1, user_api="blas"):
        for seed in seeds:
            for shape in shapes:
                row = _row(int(seed), shape, positions)
                rows.append(row)
                e = row["led_error_um"]
                say(f"seed {seed}, {shape}: LED error um (x, y, z in T) fitted {e['fitted']}, "
                    f"true clock {e['true_clock']}, with drift {e['with_drift']}; std "
                    f"{row['led_std_um']}; clock {row['clock_error_ms']['fitted']:+.3f} ms "
                    f"({row['time_s']} s)")
    result = {"seeds": list(seeds), "shapes": list(shapes), "session_positions": list(positions),
              "rows": rows, "summary": _summary(rows)}
    write_json(out / "led_clock.json", result)
    plot(result, out / "led_clock.png")
    return result


def _along_pass(row: dict | None, what: str) -> float:
    """`row`'s figure along the pass (the {T} axis it travels along), um: its LED error
    ``"fitted"``, ``"true_clock"`` or ``"with_drift"``, or its reported ``"sigma"``; NaN
    without a row or a sigma."""
    if row is None:
        return float("nan")
    values = row["led_std_um"] if what == "sigma" else row["led_error_um"][what]
    if values is None:
        return float("nan")
    return float(values[int(np.argmax(np.abs(row["pass_direction_t"])))])


def _summary(rows) -> dict:
    """Per shape, over the cells, along the pass: the fitted LED's RMS and largest error, the
    true-clock LED's largest, and the largest error in units of the reported sigma."""
    out = {}
    for shape in dict.fromkeys(r["speed_shape"] for r in rows):
        mine = [r for r in rows if r["speed_shape"] == shape]
        fitted = np.array([_along_pass(r, "fitted") for r in mine])
        truth = np.array([_along_pass(r, "true_clock") for r in mine])
        sigma = np.array([_along_pass(r, "sigma") for r in mine])
        out[shape] = {"cells": len(mine), "fitted_rms_um": float(np.sqrt(np.mean(fitted**2))),
                      "fitted_max_um": float(np.max(np.abs(fitted))),
                      "true_clock_max_um": float(np.max(np.abs(truth))),
                      "max_z": float(np.nanmax(np.abs(fitted) / sigma))}
    return out


def plot(result: dict, path) -> None:
    """The LED's error along the pass per cell: fitted on a pass whose speed ramps up, fitted
    on one whose speed peaks at its middle (with its reported sigma), and on the true clock."""
    plt = pyplot()
    rows = result["rows"]
    seeds = list(dict.fromkeys(r["perturb_seed"] for r in rows))
    by = {(r["perturb_seed"], r["speed_shape"]): r for r in rows}
    x = np.arange(len(seeds))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    bars = [("ramp", "fitted", "pass speed ramping up (before)"),
            ("peak", "fitted", "pass speed up then down (now)"),
            ("peak", "true_clock", "on the true clock")]
    for k, (shape, key, label) in enumerate(bars):
        ax.bar(x + (k - 1) * 0.27, [_along_pass(by.get((seed, shape)), key) for seed in seeds],
               0.27, label=label)
    sigmas = [_along_pass(by.get((seed, "peak")), "sigma") for seed in seeds]
    ax.errorbar(x, np.zeros(len(seeds)), yerr=sigmas, fmt="none", ecolor="k", capsize=4,
                label="reported sigma (now)")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.set_xticks(x, [f"cell {seed}" for seed in seeds])
    ax.set_ylabel("LED offset error along the pass (um)")
    ax.set_title("the calibrated LED offset: a drifting clock against the pass's speed")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.led_clock",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("out", type=pathlib.Path)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    parser.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES))
    args = parser.parse_args(argv)
    run(args.out, args.seeds, shapes=tuple(args.shapes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
