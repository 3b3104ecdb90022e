"""A UR controller's RTDE server (protocol version 2), for tests and demonstrations.

It serves what ``rtde_receive.RTDEReceiveInterface`` (ur-rtde) asks of a robot: the
handshake (``V`` protocol version, ``v`` controller version, ``O`` output setup, ``S`` start,
``P`` pause) and then data packages ``U`` on the 500 Hz grid of the robot's clock. The TCP
follows the same simulated track as the live simulated cell (``simulator.track.TrackSegment``
and ``tcp_on_track``), so what a client reads can be checked against ground truth.

The ur-rtde bindings hold the GIL while their constructor blocks on the network, so the server
must not run in a thread of the process that constructs the client: :class:`RtdeEmulator`
runs it in its own process (multiprocessing, "spawn") and steers it over a pipe.

Clocks: the camera clock is ``time.monotonic() - epoch`` (CLOCK_MONOTONIC is system-wide on
Linux, so parent and server agree on it); the robot clock is the camera clock plus
``clock_offset_s``. Sample ``k`` is the robot's state at robot time ``k / 500`` s and is sent
when that time has come.

Run ``python -m simulator.rtde_emulator --help`` for a stand-alone server.

Packets (all big-endian): a 3-byte header, uint16 size (header included) and uint8 type, then
the payload. A client that sends a malformed packet is disconnected; the server goes on.

The parts: the protocol's constants and packets in ``scanner_core.io.rtde`` (shared with the real
client, ``service.ur_robot``), the robot the server reports in ``simulator.rtde_robot``, the
server in ``simulator.rtde_server``. This module holds the handle that runs the server in its
own process (:class:`RtdeEmulator`) and the stand-alone command (:func:`main`).
"""
from __future__ import annotations

import argparse
import math
import multiprocessing
import socket
import sys
import threading
import time

import numpy as np

from scanner_core.io.rtde import PROTOCOL_VERSION, RTDE_PORT, output_type
from simulator.rtde_robot import ROBOT_RATE_HZ
from simulator.rtde_server import (CONTROLLER_VERSION, MAX_CATCH_UP_SAMPLES, MAX_OUTBUF_BYTES,
                                   MAX_RECIPES, _serve)

__all__ = ["RtdeEmulator", "EmulatorError", "RTDE_PORT", "ROBOT_RATE_HZ", "output_type",
           "main", "free_loopback_host", "PROTOCOL_VERSION", "CONTROLLER_VERSION",
           "MAX_CATCH_UP_SAMPLES", "MAX_OUTBUF_BYTES", "MAX_RECIPES", "START_TIMEOUT_S",
           "CONTROL_TIMEOUT_S"]

#: Longest wait for the server process to listen (a spawned interpreter imports numpy and the
#: simulator: a few seconds on a loaded CI machine).
START_TIMEOUT_S = 60.0
#: Longest wait for the server to answer a control message.
CONTROL_TIMEOUT_S = 10.0


def free_loopback_host(first: int = 2, count: int = 60, port: int = RTDE_PORT) -> str:
    """A loopback address (127.0.0.FIRST, ...) whose ``port`` is free: ur-rtde's port is fixed,
    so emulators side by side need addresses of their own."""
    for n in range(first, first + count):
        host = f"127.0.0.{n}"
        with socket.socket() as probe:
            try:
                probe.bind((host, port))
                return host
            except OSError:
                continue
    raise RuntimeError(f"no loopback address 127.0.0.{first}..{first + count - 1} has port "
                       f"{port} free")


class EmulatorError(RuntimeError):
    """The emulator could not start, or did not answer a control message."""


# --------------------------------------------------------------------------------------------
# The handle (parent process)
# --------------------------------------------------------------------------------------------

class RtdeEmulator:
    """An RTDE server in its own process, steered from this one.

    Until :meth:`set_track` it serves an idle robot at the origin of {B} with the identity
    rotation, its clock starting at ``start``.

    Parameters
    ----------
    host : str
        Address to listen on; use different loopback addresses (127.0.0.2, ...) to run several
        emulators at once, since the ur-rtde client only uses port 30004.
    port : int
        TCP port; 0 picks a free one (for clients other than ur-rtde).

    Examples
    --------
    >>> with RtdeEmulator("127.0.0.2") as robot:            # doctest: +SKIP
    ...     robot.set_track(epoch, 0.25, rotation_b, idle_tcp_b)
    ...     robot.add_segment(live_pass.segment)
    """

    def __init__(self, host: str = "127.0.0.1", port: int = RTDE_PORT):
        self.host, self.port = host, int(port)
        self._process = None
        self._conn = None
        self._lock = threading.Lock()  # one request and its reply at a time

    # -- life cycle ----------------------------------------------------------------------------
    def start(self, timeout_s: float = START_TIMEOUT_S) -> "RtdeEmulator":
        """Spawn the server process and wait until it listens.

        Raises
        ------
        EmulatorError
            The address is taken, or the process did not start within ``timeout_s``.
        """
        if self._process is not None:
            return self
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_serve, args=(self.host, self.port, child), daemon=True,
                              name=f"rtde-emulator-{self.host}:{self.port}")
        process.start()
        child.close()
        try:
            if not parent.poll(timeout_s):
                raise EmulatorError(f"the RTDE emulator on {self.host}:{self.port} did not start "
                                    f"within {timeout_s} s")
            status, detail = parent.recv()
        except (EOFError, EmulatorError) as exc:
            process.kill()
            process.join()
            parent.close()
            if isinstance(exc, EmulatorError):
                raise
            raise EmulatorError(f"the RTDE emulator process exited (code {process.exitcode})"
                                ) from None
        if status != "listening":
            process.join(5.0)
            parent.close()
            raise EmulatorError(f"RTDE emulator: {detail}")
        self.port = int(detail)
        self._process, self._conn = process, parent
        return self

    def stop(self) -> None:
        """Stop the server process (closing every connection). Idempotent."""
        process, conn = self._process, self._conn
        if process is None:
            return
        try:
            self._call("stop", timeout_s=5.0)
        except EmulatorError:
            pass
        process.join(5.0)
        if process.is_alive():
            process.kill()
            process.join()
        conn.close()
        self._process = self._conn = None

    def __enter__(self) -> "RtdeEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.is_alive()

    # -- control ----------------------------------------------------------------------------------
    def _call(self, command: str, *args, timeout_s: float = CONTROL_TIMEOUT_S):
        if self._conn is None:
            raise EmulatorError("the RTDE emulator is not running")
        with self._lock:
            try:
                self._conn.send((command, *args))
                if not self._conn.poll(timeout_s):
                    raise EmulatorError(f"the RTDE emulator did not answer {command!r}")
                status, result = self._conn.recv()
            except (EOFError, OSError) as exc:
                raise EmulatorError(f"the RTDE emulator process is gone ({exc})") from None
        if status != "ok":
            raise EmulatorError(f"RTDE emulator, {command}: {result}")
        return result

    def set_track(self, epoch_monotonic: float, clock_offset_s: float, rotation_b,
                  idle_tcp_b) -> None:
        """Set the robot's clock and pose; forgets the segments.

        Parameters
        ----------
        epoch_monotonic : float
            ``time.monotonic()`` at camera clock 0 (in this process: the clock is system-wide).
        clock_offset_s : float
            Robot clock = camera clock + offset, s.
        rotation_b : (3, 3) array_like
            Rotation of {T} in {B} (columns are the {T} axes); reported as a rotation vector.
        idle_tcp_b : (3,) array_like
            TCP in {B} before the first segment, mm.
        """
        from scanner_core.io.rtde import matrix_to_ur_pose

        rotation = np.asarray(rotation_b, dtype=np.float64)
        if rotation.shape != (3, 3):
            raise ValueError(f"`rotation_b` must be (3, 3), got {rotation.shape}")
        idle = np.asarray(idle_tcp_b, dtype=np.float64)
        if idle.shape != (3,) or not np.all(np.isfinite(idle)):
            raise ValueError(f"`idle_tcp_b` must be a finite 3-vector, got {idle_tcp_b!r}")
        if not (math.isfinite(epoch_monotonic) and math.isfinite(clock_offset_s)):
            raise ValueError("`epoch_monotonic` and `clock_offset_s` must be finite")
        turn = np.eye(4)
        turn[:3, :3] = rotation
        rotvec = matrix_to_ur_pose(turn)[3:]  # ValueError unless a rotation
        self._call("set_track", float(epoch_monotonic), float(clock_offset_s),
                   tuple(float(x) for x in rotvec), tuple(float(x) for x in idle))

    def add_segment(self, segment) -> None:
        """Append a ``simulator.track.TrackSegment`` (camera clock; in time order)."""
        self._call("add_segment", segment)

    def set_bias(self, bias_mm) -> None:
        """Add ``bias_mm`` ((3,), mm in {B}) to every TCP position reported from now on."""
        bias = np.asarray(bias_mm, dtype=np.float64)
        if bias.shape != (3,) or not np.all(np.isfinite(bias)):
            raise ValueError(f"`bias_mm` must be a finite 3-vector, got {bias_mm!r}")
        self._call("set_bias", tuple(float(x) for x in bias))

    def drop(self, seconds: float | None = None) -> None:
        """Close every connection and refuse new ones (connection refused) for ``seconds``,
        or until :meth:`restore` when None."""
        if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"`seconds` must be finite and >= 0, got {seconds}")
        self._call("drop", None if seconds is None else float(seconds))

    def stall(self, seconds: float | None = None) -> None:
        """Keep every connection open but send no data (a frozen controller, a cable cut
        without a reset) for ``seconds``, or until :meth:`restore` when None. The handshake
        is still answered."""
        if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"`seconds` must be finite and >= 0, got {seconds}")
        self._call("stall", None if seconds is None else float(seconds))

    def restore(self) -> None:
        """Accept connections and stream again after :meth:`drop` or :meth:`stall`."""
        self._call("restore")

    def stats(self) -> dict:
        """Server counters: connections, malformed, samples_sent, dropped_slow, clients,
        streaming, listening, port."""
        return self._call("stats")


# --------------------------------------------------------------------------------------------
# Stand-alone
# --------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m simulator.rtde_emulator",
        description="An emulated UR robot's RTDE server (port 30004 protocol, version 2) for "
                    "trying ur-rtde clients without a robot. By default the robot stands idle "
                    "where the reference cell's pass begins, with the cell's gripper rotation; "
                    "with --pass-every it runs the reference pass again and again.")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on")
    parser.add_argument("--port", type=int, default=RTDE_PORT,
                        help=f"TCP port (default {RTDE_PORT}, the only one ur-rtde uses)")
    parser.add_argument("--pass-every", type=float, default=None, metavar="S",
                        help="start the reference cell's pass every S seconds (at least the "
                             "pass's length); default: an idle robot")
    parser.add_argument("--clock-offset", type=float, default=0.0, metavar="S",
                        help="robot clock minus camera clock, s (the camera clock starts at 0 "
                             "when the emulator starts)")
    args = parser.parse_args(argv)

    from simulator.cell import load_cell
    from simulator.track import TrackSegment, pass_frame_count
    from simulator.motion import PassMotion

    cell = load_cell()
    profile = cell.pass_profile
    pass_s = (pass_frame_count(profile) - 1) / profile.fps
    if args.pass_every is not None and not args.pass_every >= pass_s:
        parser.error(f"--pass-every must be at least the pass's length, {pass_s:.2f} s")
    emulator = RtdeEmulator(args.host, args.port)
    try:
        emulator.start()
    except EmulatorError as exc:
        print(exc, file=sys.stderr)
        return 1
    try:
        epoch = time.monotonic()
        emulator.set_track(epoch, args.clock_offset, cell.gripper_rotation_b,
                           PassMotion(profile).tcp_position(-profile.lead_in_s))
        print(f"RTDE emulator on {args.host}:{emulator.port}"
              + (f", a pass every {args.pass_every} s" if args.pass_every else ", idle"),
              flush=True)
        t_next = 1.0
        while True:
            if args.pass_every is None:
                time.sleep(3600.0)
                continue
            time.sleep(max(t_next - (time.monotonic() - epoch), 0.0))
            emulator.add_segment(TrackSegment(t_next, t_next + profile.lead_in_s,
                                              t_next + pass_s, profile))
            t_next += args.pass_every
    except KeyboardInterrupt:
        return 0
    finally:
        emulator.stop()


if __name__ == "__main__":
    sys.exit(main())
