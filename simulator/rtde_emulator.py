"""A UR controller's RTDE server (protocol version 2), for tests and demonstrations.

It serves what ``rtde_receive.RTDEReceiveInterface`` (ur-rtde) asks of a robot: the
handshake (``V`` protocol version, ``v`` controller version, ``O`` output setup, ``S`` start,
``P`` pause) and then data packages ``U`` on the 500 Hz grid of the robot's clock. The TCP
follows the same simulated track as the live simulated cell (``simulator.live.TrackSegment``
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
"""
from __future__ import annotations

import argparse
import errno
import math
import multiprocessing
import re
import selectors
import signal
import socket
import struct
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from simulator.live import tcp_on_track

__all__ = ["RtdeEmulator", "EmulatorError", "RTDE_PORT", "ROBOT_RATE_HZ", "output_type",
           "main"]

#: The RTDE port of a UR controller; the ur-rtde client cannot use another.
RTDE_PORT = 30004
#: The controller's cycle (e-Series): samples are sent on this grid of the robot clock.
ROBOT_RATE_HZ = 500.0
PROTOCOL_VERSION = 2
#: Reported by ``v``; major > 3 makes ur-rtde default to 500 Hz (an e-Series controller).
CONTROLLER_VERSION = (5, 15, 0, 0)
#: Samples sent at once to a client whose stream fell behind (a stalled server loop); older
#: ones are skipped, as a controller does not queue them either.
MAX_CATCH_UP_SAMPLES = 50
#: A client that lets this much unsent data pile up is not reading: it is dropped.
MAX_OUTBUF_BYTES = 1 << 20
#: Recipes a client may set up (the controller's recipe id is a uint8, 0 meaning failure).
MAX_RECIPES = 255
#: Longest wait for the server process to listen (a spawned interpreter imports numpy and the
#: simulator: a few seconds on a loaded CI machine).
START_TIMEOUT_S = 60.0
#: Longest wait for the server to answer a control message.
CONTROL_TIMEOUT_S = 10.0

_HEADER = struct.Struct(">HB")
_V, _VERSION, _OUTPUTS, _INPUTS, _START, _PAUSE, _DATA, _TEXT = (ord(c) for c in "VvOISPUM")

#: Output variables of the UR RTDE guide and their types (what the client decodes with its own
#: table, so these must be right); registers are matched by ``_REGISTER``.
_OUTPUT_TYPES = {
    "timestamp": "DOUBLE",
    **{name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "actual_current_window", "actual_current_as_torque")},
    **{name: "DOUBLE" for name in (
        "actual_execution_time", "speed_scaling", "target_speed_fraction", "actual_momentum",
        "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "euromap67_24V_voltage",
        "euromap67_24V_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "tcp_force_scalar", "payload")},
    **{name: "VECTOR3D" for name in (
        "actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog")},
    **{name: "INT32" for name in ("robot_mode", "safety_mode", "safety_status",
                                  "tool_output_voltage")},
    **{name: "UINT32" for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "euromap67_input_bits", "euromap67_output_bits", "tool_mode", "tool_analog_input_types",
        "output_bit_registers0_to_31", "output_bit_registers32_to_63",
        "input_bit_registers0_to_31", "input_bit_registers32_to_63", "script_control_line")},
    **{name: "UINT64" for name in ("actual_digital_input_bits", "actual_digital_output_bits")},
    "joint_mode": "VECTOR6INT32",
    "tool_output_mode": "UINT8",
    "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8",
}
_REGISTER = re.compile(r"(?:output|input)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}
_REGISTER_RANGES = {"int": range(48), "double": range(48), "bit": range(64, 128)}
_TYPE_FORMATS = {"DOUBLE": "d", "VECTOR3D": "3d", "VECTOR6D": "6d", "INT32": "i", "UINT32": "I",
                 "UINT64": "Q", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I", "BOOL": "?",
                 "UINT8": "B"}
#: Constant values of an idle, healthy robot (others are zero): RUNNING, NORMAL, PLAYING.
_CONSTANTS = {"robot_mode": (7,), "safety_mode": (1,), "safety_status": (1,),
              "runtime_state": (2,), "speed_scaling": (1.0,), "target_speed_fraction": (1.0,),
              "actual_main_voltage": (48.0,), "actual_robot_voltage": (48.0,)}


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


def output_type(name: str) -> str | None:
    """The RTDE type of output variable ``name`` (``"VECTOR6D"``, ...), None if unknown."""
    if name in _OUTPUT_TYPES:
        return _OUTPUT_TYPES[name]
    m = _REGISTER.match(name)
    if m is not None and int(m.group(2)) in _REGISTER_RANGES[m.group(1)]:
        return _REGISTER_TYPES[m.group(1)]
    return None


class EmulatorError(RuntimeError):
    """The emulator could not start, or did not answer a control message."""


class _Malformed(ValueError):
    """A client sent a packet the protocol does not allow."""


# --------------------------------------------------------------------------------------------
# The robot's state (server side)
# --------------------------------------------------------------------------------------------

@dataclass
class _Track:
    """What the emulated robot does: its clocks and the TCP's track in {B}."""

    epoch: float
    clock_offset_s: float = 0.0
    rotvec: tuple = (0.0, 0.0, 0.0)
    idle_tcp_b: np.ndarray = field(default_factory=lambda: np.zeros(3))
    segments: list = field(default_factory=list)
    bias_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def robot_now(self) -> float:
        """Robot clock now, s."""
        return time.monotonic() - self.epoch + self.clock_offset_s

    def monotonic_of(self, t_robot: float) -> float:
        """``time.monotonic()`` at which the robot clock reads ``t_robot``."""
        return t_robot - self.clock_offset_s + self.epoch

    def tcp_b_mm(self, t_robot: float) -> np.ndarray:
        """(3,) float64: TCP in {B}, mm, at robot time ``t_robot`` (bias included)."""
        return tcp_on_track(self.segments, self.idle_tcp_b,
                            t_robot - self.clock_offset_s) + self.bias_mm

    def prune(self, keep_s: float = 60.0) -> None:
        """Forget segments replaced by a later one more than ``keep_s`` ago."""
        t_cam = self.robot_now() - self.clock_offset_s
        while len(self.segments) > 1 and self.segments[1].robot_start_t < t_cam - keep_s:
            self.segments.pop(0)


class _Sample:
    """The values of sample ``k``, computed on first use (shared by every client)."""

    def __init__(self, track: _Track, k: int):
        self.track, self.t = track, k / ROBOT_RATE_HZ
        self._cache: dict = {}

    def _pose(self, t: float) -> tuple:
        tcp_m = self.track.tcp_b_mm(t) / 1000.0  # RTDE speaks metres
        return (*(float(x) for x in tcp_m), *self.track.rotvec)

    def value(self, name: str) -> tuple:
        if name in self._cache:
            return self._cache[name]
        if name == "timestamp":
            v = (self.t,)
        elif name in ("actual_TCP_pose", "target_TCP_pose"):
            v = self._pose(self.t)
        elif name in ("actual_TCP_speed", "target_TCP_speed"):
            dt = 0.5e-3  # a central difference: the track is smooth at this scale
            a, b = self._pose(self.t - dt), self._pose(self.t + dt)
            v = (*((y - x) / (2 * dt) for x, y in zip(a[:3], b[:3])), 0.0, 0.0, 0.0)
        else:
            v = _CONSTANTS.get(name) or _zeros(output_type(name))
        self._cache[name] = v
        return v


def _zeros(rtde_type: str) -> tuple:
    fmt = _TYPE_FORMATS[rtde_type]
    n = int(fmt[:-1]) if len(fmt) > 1 else 1
    zero = False if fmt == "?" else (0.0 if fmt[-1] == "d" else 0)
    return (zero,) * n


# --------------------------------------------------------------------------------------------
# Clients
# --------------------------------------------------------------------------------------------

@dataclass
class _Recipe:
    recipe_id: int
    names: tuple
    packer: struct.Struct
    decimation: int  # send every ``decimation``-th sample of the 500 Hz grid


class _Client:
    def __init__(self, sock: socket.socket, peer):
        self.sock, self.peer = sock, peer
        self.inbuf, self.outbuf = bytearray(), bytearray()
        self.version_ok = False
        self.recipes: dict[int, _Recipe] = {}
        self.started = False
        self.next_k = 0


# --------------------------------------------------------------------------------------------
# The server (runs in the emulator's process)
# --------------------------------------------------------------------------------------------

class _Server:
    """One-threaded RTDE server: a selector over the listener, the clients and the control
    pipe, woken for each sample due."""

    def __init__(self, host: str, port: int, control):
        self.host, self.port = host, port
        self.control = control
        self.sel = selectors.DefaultSelector()
        self.listener: socket.socket | None = None
        self.clients: dict[socket.socket, _Client] = {}
        self.track = _Track(epoch=time.monotonic())
        self.dropped_until: float | None = None  # monotonic; inf: until restore
        self.stalled_until: float | None = None  # likewise, for a stream that stops
        self.running = True
        self.counts = {"connections": 0, "malformed": 0, "samples_sent": 0, "dropped_slow": 0}

    # -- listening ------------------------------------------------------------------------------
    def listen(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            # Lets a restored server bind again while old connections sit in TIME_WAIT; on
            # Linux it does not allow two listeners on one address.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host, self.port))
            sock.listen(16)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self.port = sock.getsockname()[1]  # the real one when asked for port 0
        self.listener = sock
        self.sel.register(sock, selectors.EVENT_READ, "listen")

    def _close_listener(self) -> None:
        if self.listener is not None:
            self.sel.unregister(self.listener)
            self.listener.close()
            self.listener = None

    def _accept(self) -> None:
        try:
            sock, peer = self.listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, peer)
        self.clients[sock] = client
        self.sel.register(sock, selectors.EVENT_READ, client)
        self.counts["connections"] += 1

    def _close(self, client: _Client) -> None:
        if self.clients.pop(client.sock, None) is None:
            return
        self.sel.unregister(client.sock)
        client.sock.close()

    # -- the loop ---------------------------------------------------------------------------------
    def run(self) -> None:
        while self.running:
            now = time.monotonic()
            if self.dropped_until is not None and now >= self.dropped_until:
                self._restore()
            timeout = 0.1
            due = self._next_due()
            if due is not None:
                timeout = min(timeout, max(due - now, 0.0))
            for until in (self.dropped_until, self.stalled_until):
                if until is not None and math.isfinite(until):
                    timeout = min(timeout, max(until - now, 0.0))
            for key, mask in self.sel.select(timeout):
                if key.data == "listen":
                    if self.listener is not None:
                        self._accept()
                elif key.data == "control":
                    self._control()
                elif key.fileobj in self.clients:
                    client = key.data
                    if mask & selectors.EVENT_WRITE:
                        self._flush(client)
                    if mask & selectors.EVENT_READ and client.sock in self.clients:
                        self._read(client)
            self._stream()

    def close(self) -> None:
        for client in list(self.clients.values()):
            self._close(client)
        self._close_listener()
        self.sel.close()

    # -- control ---------------------------------------------------------------------------------
    def _control(self) -> None:
        try:
            message = self.control.recv()
        except (EOFError, OSError):  # the parent is gone: so are we
            self.running = False
            return
        command, args = message[0], message[1:]
        try:
            result = getattr(self, f"_cmd_{command}")(*args)
            reply = ("ok", result)
        except Exception as exc:  # reported to the parent, the server goes on
            reply = ("error", f"{type(exc).__name__}: {exc}")
        try:
            self.control.send(reply)
        except (BrokenPipeError, OSError):
            self.running = False

    def _cmd_set_track(self, epoch, clock_offset_s, rotvec, idle_tcp_b):
        self.track.epoch, self.track.clock_offset_s = float(epoch), float(clock_offset_s)
        self.track.rotvec = tuple(float(x) for x in rotvec)
        self.track.idle_tcp_b = np.array(idle_tcp_b, dtype=np.float64)
        self.track.segments.clear()
        # The clock may have jumped: streams go on from its present.
        k_now = math.floor(self.track.robot_now() * ROBOT_RATE_HZ)
        for client in self.clients.values():
            client.next_k = k_now + 1

    def _cmd_add_segment(self, segment):
        segments = self.track.segments
        if segments and segment.robot_start_t < segments[-1].robot_start_t:
            raise ValueError("segments must be added in time order")
        segments.append(segment)
        self.track.prune()

    def _cmd_set_bias(self, bias_mm):
        self.track.bias_mm = np.array(bias_mm, dtype=np.float64)

    def _cmd_drop(self, seconds):
        for client in list(self.clients.values()):
            self._close(client)
        self._close_listener()
        self.dropped_until = math.inf if seconds is None else time.monotonic() + float(seconds)

    def _cmd_stall(self, seconds):
        self.stalled_until = math.inf if seconds is None else time.monotonic() + float(seconds)

    def _cmd_restore(self):
        self._restore()
        self._resume()

    def _cmd_stats(self):
        return {**self.counts, "clients": len(self.clients),
                "streaming": sum(c.started for c in self.clients.values()),
                "stalled": self.stalled_until is not None,
                "listening": self.listener is not None, "port": self.port}

    def _cmd_stop(self):
        self.running = False

    def _resume(self) -> None:
        """End a stall: streams go on from the present (the samples missed are lost, as a
        controller does not queue them)."""
        if self.stalled_until is None:
            return
        self.stalled_until = None
        k_now = math.floor(self.track.robot_now() * ROBOT_RATE_HZ)
        for client in self.clients.values():
            client.next_k = k_now + 1

    def _restore(self) -> None:
        if self.listener is None:
            try:
                self.listen()
            except OSError as exc:  # someone took the address meanwhile: try again soon
                print(f"rtde emulator: cannot listen again on {self.host}:{self.port}: {exc}",
                      file=sys.stderr)
                self.dropped_until = time.monotonic() + 1.0
                return
        self.dropped_until = None

    # -- client I/O ------------------------------------------------------------------------------
    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(client)
            return
        if not data:
            self._close(client)
            return
        client.inbuf += data
        try:
            while len(client.inbuf) >= _HEADER.size:
                size, kind = _HEADER.unpack_from(client.inbuf)
                if size < _HEADER.size:
                    raise _Malformed(f"packet size {size} < 3")
                if len(client.inbuf) < size:
                    break
                payload = bytes(client.inbuf[_HEADER.size:size])
                del client.inbuf[:size]
                self._handle(client, kind, payload)
        except _Malformed as exc:
            self.counts["malformed"] += 1
            print(f"rtde emulator: {client.peer}: {exc}; closing it", file=sys.stderr)
            self._close(client)

    def _send(self, client: _Client, kind: int, payload: bytes) -> None:
        client.outbuf += _HEADER.pack(_HEADER.size + len(payload), kind) + payload

    def _flush(self, client: _Client) -> None:
        if client.sock not in self.clients:
            return
        try:
            sent = client.sock.send(client.outbuf) if client.outbuf else 0
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError:  # reset by the peer, broken pipe
            self._close(client)
            return
        del client.outbuf[:sent]
        if len(client.outbuf) > MAX_OUTBUF_BYTES:
            self.counts["dropped_slow"] += 1
            self._close(client)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbuf else 0)
        if self.sel.get_key(client.sock).events != events:
            self.sel.modify(client.sock, events, client)

    def _handle(self, client: _Client, kind: int, payload: bytes) -> None:
        if kind == _V:
            if len(payload) != 2:
                raise _Malformed(f"protocol version request of {len(payload)} bytes")
            (version,) = struct.unpack(">H", payload)
            client.version_ok = version == PROTOCOL_VERSION
            self._send(client, _V, struct.pack(">B", client.version_ok))
        elif kind == _VERSION:
            self._send(client, _VERSION, struct.pack(">4I", *CONTROLLER_VERSION))
        elif kind == _OUTPUTS:
            self._setup_outputs(client, payload)
        elif kind == _INPUTS:
            # No input registers here: a receive-only robot.
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            self._send(client, _INPUTS, b"\x00" + ",".join(["NOT_FOUND"] * len(names)).encode())
        elif kind == _START:
            client.started = client.version_ok and bool(client.recipes)
            if client.started:
                client.next_k = math.floor(self.track.robot_now() * ROBOT_RATE_HZ) + 1
            self._send(client, _START, struct.pack(">B", client.started))
        elif kind == _PAUSE:
            client.started = False
            self._send(client, _PAUSE, b"\x01")
        elif kind in (_DATA, _TEXT):
            pass  # input data (no inputs are set up) and text messages: nothing to do
        else:
            raise _Malformed(f"unknown packet type {kind}")
        self._flush(client)

    def _setup_outputs(self, client: _Client, payload: bytes) -> None:
        if not client.version_ok:
            raise _Malformed("output setup before protocol version 2 was agreed")
        if len(payload) < 8:
            raise _Malformed(f"output setup of {len(payload)} bytes")
        (frequency,) = struct.unpack_from(">d", payload)
        try:
            names = [n.strip() for n in payload[8:].decode("ascii").split(",") if n.strip()]
        except UnicodeDecodeError as exc:
            raise _Malformed("output names are not ASCII") from exc
        types = [output_type(n) or "NOT_FOUND" for n in names]
        ok = (names and "NOT_FOUND" not in types and 0.0 < frequency <= ROBOT_RATE_HZ
              and len(client.recipes) < MAX_RECIPES)
        recipe_id = 0
        if ok:
            recipe_id = len(client.recipes) + 1
            fmt = ">B" + "".join(_TYPE_FORMATS[t] for t in types)
            client.recipes[recipe_id] = _Recipe(recipe_id, tuple(names), struct.Struct(fmt),
                                                max(1, round(ROBOT_RATE_HZ / frequency)))
        self._send(client, _OUTPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode())

    # -- streaming -------------------------------------------------------------------------------
    def _next_due(self) -> float | None:
        if self.stalled_until is not None:
            return None  # the loop wakes at ``stalled_until`` anyway
        ks = [c.next_k for c in self.clients.values() if c.started]
        return self.track.monotonic_of(min(ks) / ROBOT_RATE_HZ) if ks else None

    def _stream(self) -> None:
        if self.stalled_until is not None:
            if time.monotonic() < self.stalled_until:
                return
            self._resume()
        streaming = [c for c in self.clients.values() if c.started]
        if not streaming:
            return
        k_now = math.floor(self.track.robot_now() * ROBOT_RATE_HZ)
        samples: dict[int, _Sample] = {}
        for client in streaming:
            if client.next_k > k_now:
                continue
            for k in range(max(client.next_k, k_now - MAX_CATCH_UP_SAMPLES + 1), k_now + 1):
                for recipe in client.recipes.values():
                    if k % recipe.decimation:
                        continue
                    sample = samples.get(k) or samples.setdefault(k, _Sample(self.track, k))
                    values = [v for name in recipe.names for v in sample.value(name)]
                    self._send(client, _DATA, recipe.packer.pack(recipe.recipe_id, *values))
                    self.counts["samples_sent"] += 1
            client.next_k = k_now + 1
            self._flush(client)


def _serve(host: str, port: int, control) -> None:
    """The emulator process: listen, report, serve until told to stop or orphaned."""
    # Ctrl-C in a terminal reaches the whole process group: the parent decides when the
    # emulator stops (it says so, or its end of the control pipe closes).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    server = _Server(host, port, control)
    try:
        server.listen()
    except OSError as exc:
        taken = exc.errno == errno.EADDRINUSE
        control.send(("error", f"cannot listen on {host}:{port}: "
                      + ("the address is in use (another emulator or server?)" if taken
                         else str(exc))))
        return
    control.send(("listening", server.port))
    server.sel.register(control, selectors.EVENT_READ, "control")
    try:
        server.run()
    except KeyboardInterrupt:  # Ctrl-C in a terminal reaches the whole process group
        pass
    finally:
        server.close()


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
        from scipy.spatial.transform import Rotation

        rotation = np.asarray(rotation_b, dtype=np.float64)
        if rotation.shape != (3, 3):
            raise ValueError(f"`rotation_b` must be (3, 3), got {rotation.shape}")
        idle = np.asarray(idle_tcp_b, dtype=np.float64)
        if idle.shape != (3,) or not np.all(np.isfinite(idle)):
            raise ValueError(f"`idle_tcp_b` must be a finite 3-vector, got {idle_tcp_b!r}")
        if not (math.isfinite(epoch_monotonic) and math.isfinite(clock_offset_s)):
            raise ValueError("`epoch_monotonic` and `clock_offset_s` must be finite")
        rotvec = Rotation.from_matrix(rotation).as_rotvec()
        self._call("set_track", float(epoch_monotonic), float(clock_offset_s),
                   tuple(float(x) for x in rotvec), tuple(float(x) for x in idle))

    def add_segment(self, segment) -> None:
        """Append a ``simulator.live.TrackSegment`` (camera clock; in time order)."""
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
    from simulator.live import TrackSegment, pass_frame_count
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
