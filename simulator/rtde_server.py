"""The emulated UR controller's RTDE server: one thread, in the emulator's own process.

A selector over the listener, the clients and the control pipe from the parent
(``simulator.rtde_emulator.RtdeEmulator``), woken for each sample due. It answers the
handshake of the protocol (``scanner_core.io.rtde``: ``V`` protocol version, ``v`` controller
version, ``O`` output setup, ``I`` input setup, ``S`` start, ``P`` pause) and then sends data
packages ``U`` on the 500 Hz grid of the robot's clock (``simulator.rtde_robot``). A client
that sends a malformed packet is disconnected; the server goes on. Control messages come over
the pipe as ``(command, *args)`` and are answered ``("ok", result)`` or ``("error", text)``.
"""
from __future__ import annotations

import errno
import math
import selectors
import signal
import socket
import struct
import sys
import time
from dataclasses import dataclass

import numpy as np

from scanner_core.io import rtde as rtde
from simulator.rtde_robot import ROBOT_RATE_HZ, _Sample, _Track

#: Reported by ``v``; major > 3 makes ur-rtde default to 500 Hz (an e-Series controller).
CONTROLLER_VERSION = (5, 15, 0, 0)
#: Samples sent at once to a client whose stream fell behind (a stalled server loop); older
#: ones are skipped, as a controller does not queue them either.
MAX_CATCH_UP_SAMPLES = 50
#: A client that lets this much unsent data pile up is not reading: it is dropped.
MAX_OUTBUF_BYTES = 1 << 20
#: Recipes a client may set up (the controller's recipe id is a uint8, 0 meaning failure).
MAX_RECIPES = 255


class _Malformed(ValueError):
    """A client sent a packet the protocol does not allow."""


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
            while len(client.inbuf) >= rtde.HEADER.size:
                size, kind = rtde.HEADER.unpack_from(client.inbuf)
                if size < rtde.HEADER.size:
                    raise _Malformed(f"packet size {size} < 3")
                if len(client.inbuf) < size:
                    break
                payload = bytes(client.inbuf[rtde.HEADER.size:size])
                del client.inbuf[:size]
                self._handle(client, kind, payload)
        except _Malformed as exc:
            self.counts["malformed"] += 1
            print(f"rtde emulator: {client.peer}: {exc}; closing it", file=sys.stderr)
            self._close(client)

    def _send(self, client: _Client, kind: int, payload: bytes) -> None:
        client.outbuf += rtde.packet(kind, payload)

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
        if kind == rtde.REQUEST_PROTOCOL_VERSION:
            if len(payload) != 2:
                raise _Malformed(f"protocol version request of {len(payload)} bytes")
            (version,) = struct.unpack(">H", payload)
            client.version_ok = version == rtde.PROTOCOL_VERSION
            self._send(client, rtde.REQUEST_PROTOCOL_VERSION,
                       struct.pack(">B", client.version_ok))
        elif kind == rtde.GET_URCONTROL_VERSION:
            self._send(client, rtde.GET_URCONTROL_VERSION,
                       struct.pack(">4I", *CONTROLLER_VERSION))
        elif kind == rtde.SETUP_OUTPUTS:
            self._setup_outputs(client, payload)
        elif kind == rtde.SETUP_INPUTS:
            # No input registers here: a receive-only robot.
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            self._send(client, rtde.SETUP_INPUTS,
                       b"\x00" + ",".join(["NOT_FOUND"] * len(names)).encode())
        elif kind == rtde.START:
            client.started = client.version_ok and bool(client.recipes)
            if client.started:
                client.next_k = math.floor(self.track.robot_now() * ROBOT_RATE_HZ) + 1
            self._send(client, rtde.START, struct.pack(">B", client.started))
        elif kind == rtde.PAUSE:
            client.started = False
            self._send(client, rtde.PAUSE, b"\x01")
        elif kind in (rtde.DATA_PACKAGE, rtde.TEXT_MESSAGE):
            pass  # input data (no inputs are set up) and text messages: nothing to do
        else:
            raise _Malformed(f"unknown packet type {kind}")
        self._flush(client)

    def _setup_outputs(self, client: _Client, payload: bytes) -> None:
        if not client.version_ok:
            raise _Malformed("output setup before protocol version 2 was agreed")
        try:
            frequency, names = rtde.parse_output_setup(payload)
        except ValueError as exc:
            raise _Malformed(str(exc)) from exc
        types = [rtde.output_type(n) or "NOT_FOUND" for n in names]
        ok = (names and "NOT_FOUND" not in types and 0.0 < frequency <= ROBOT_RATE_HZ
              and len(client.recipes) < MAX_RECIPES)
        recipe_id = 0
        if ok:
            recipe_id = len(client.recipes) + 1
            client.recipes[recipe_id] = _Recipe(recipe_id, tuple(names),
                                                rtde.data_package(types),
                                                max(1, round(ROBOT_RATE_HZ / frequency)))
        self._send(client, rtde.SETUP_OUTPUTS,
                   struct.pack(">B", recipe_id) + ",".join(types).encode())

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
                    self._send(client, rtde.DATA_PACKAGE,
                               recipe.packer.pack(recipe.recipe_id, *values))
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
