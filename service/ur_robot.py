"""A Universal Robots arm as the scanner's Robot, through ur-rtde's RTDEReceiveInterface.

The robot streams its TCP pose over RTDE (port 30004) at up to 500 Hz; a reader thread keeps
a bounded history of it and :meth:`URRobot.pose_at` interpolates in that history, as the
simulated robot does. The link is watched and re-made without help: a robot switched off,
a cable pulled or a controller restarted shows as ``connected`` False (within ``stale_s``
plus the client's own checks) and recovers by itself when the robot is back.

What ur-rtde (1.6.5) imposes, and how this module copes (see docs/design.md):

* its constructor holds the GIL while it blocks on the network, for ever against a server
  that accepts but does not answer: every (re)connection is preceded by a probe with a plain
  socket and a short timeout, which runs the RTDE handshake up to the first data package;
* after a disconnect its getters keep returning stale values: a sample is new only when its
  timestamp advances, and no new sample for ``stale_s`` means the link is lost;
* each getter returns one variable: a timestamp and a pose are read by separate calls, and a
  new data package may be applied between them; the package itself is applied whole (its
  receive thread holds the state's mutex over all of a package's variables, and every getter
  takes that mutex), so reading the timestamp again after the pose tells a consistent pair
  (see :meth:`URRobot._follow`);
* ``disconnect()`` sleeps 0.5 s (with the GIL released) and the destructor does the same with
  the GIL held: one client object is made per URRobot and re-used through ``reconnect()``,
  which releases the GIL; ``reconnect()`` uses the controller's default rate (500 Hz on an
  e-Series, 125 Hz on a CB3) whatever ``frequency`` asked for.

Units: RTDE gives metres and a rotation vector (radians); positions become mm in
:func:`_sample_from_rtde`, the one place where units change.
"""
from __future__ import annotations

import bisect
import logging
import math
import re
import socket
import struct
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation

from scanner_core.io import rtde
from scanner_core.devices import TcpPose, chord_deviation_mm
from scanner_core.io.rtde import MAX_FREQUENCY_HZ, RTDE_PORT, ur_pose_parts

__all__ = ["URRobot", "parse_robot_url", "probe_rtde", "RtdeProbeError", "RTDE_PORT",
           "RTDE_VARIABLES"]

log = logging.getLogger(__name__)

#: What the reader asks the controller for (ur-rtde's default list has about 58 variables).
RTDE_VARIABLES = ("timestamp", "actual_TCP_pose")
#: Two samples further apart than this are not interpolated between (the link was down).
MAX_GAP_S = 0.1


class RtdeProbeError(ConnectionError):
    """The robot's RTDE server cannot be reached or does not speak RTDE (a short reason)."""


def parse_robot_url(url: str) -> str:
    """The host of a robot URL ``ur://HOST`` or ``ur://HOST:30004``.

    Raises
    ------
    ValueError
        Not a ``ur://`` URL, no host, or a port other than 30004 (ur-rtde's receive interface
        always connects to 30004).
    """
    m = re.fullmatch(r"ur://(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]@]+)(?::(\d*))?/?", str(url).strip())
    if m is None:
        raise ValueError(f"robot {url!r}: expected ur://HOST or ur://HOST:{RTDE_PORT}")
    host, port = m.group(1).strip("[]"), m.group(2)
    if port is not None and (port == "" or int(port) != RTDE_PORT):
        raise ValueError(f"robot {url!r}: ur-rtde always uses port {RTDE_PORT}; give ur://{host}")
    return host


# --------------------------------------------------------------------------------------------
# Probe: is an RTDE server there and streaming?
# --------------------------------------------------------------------------------------------

def _recv_packet(sock: socket.socket, deadline: float) -> tuple[int, bytes]:
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise socket.timeout()
            sock.settimeout(remaining)
            chunk = sock.recv(n - len(data))
            if not chunk:
                raise RtdeProbeError("closed the connection during the RTDE handshake")
            data += chunk
        return data

    size, kind = rtde.HEADER.unpack(exactly(rtde.HEADER.size))
    if size < rtde.HEADER.size:
        raise RtdeProbeError(f"sent a malformed RTDE packet (size {size})")
    return kind, exactly(size - rtde.HEADER.size)


def _request(sock: socket.socket, kind: int, payload: bytes, deadline: float) -> bytes:
    """Send one RTDE request and return the payload of its answer (text messages skipped)."""
    sock.sendall(rtde.packet(kind, payload))
    while True:
        got, body = _recv_packet(sock, deadline)
        if got == kind:
            return body
        if got not in (rtde.TEXT_MESSAGE, rtde.DATA_PACKAGE):
            raise RtdeProbeError(f"answered {chr(kind)!r} with packet type {got}")


def probe_rtde(host: str, *, port: int = RTDE_PORT, timeout_s: float = 1.0,
               frequency: float = MAX_FREQUENCY_HZ) -> None:
    """Check with a plain socket that ``host`` serves RTDE and streams data.

    Runs the handshake ur-rtde runs (protocol version 2, an output setup of ``timestamp``,
    start) and waits for the first data package, all within ``timeout_s``; then closes.

    Raises
    ------
    RtdeProbeError
        With a short reason: refused, timed out, not RTDE, no data.
    """
    deadline = time.monotonic() + timeout_s
    where = f"{host}:{port}"
    stage = f"connecting to {where}"
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            stage = f"waiting for {where} to answer the RTDE handshake"
            version = struct.pack(">H", rtde.PROTOCOL_VERSION)
            if _request(sock, rtde.REQUEST_PROTOCOL_VERSION, version, deadline)[:1] != b"\x01":
                raise RtdeProbeError(f"refused RTDE protocol version {rtde.PROTOCOL_VERSION}")
            answer = _request(sock, rtde.SETUP_OUTPUTS,
                              rtde.output_setup(frequency, ["timestamp"]), deadline)
            if answer[:1] in (b"", b"\x00"):
                raise RtdeProbeError("refused the output setup "
                                     f"({answer[1:].decode(errors='replace')})")
            if _request(sock, rtde.START, b"", deadline)[:1] != b"\x01":
                raise RtdeProbeError("refused to start the data stream")
            stage = f"waiting for data from {where}"
            while _recv_packet(sock, deadline)[0] != rtde.DATA_PACKAGE:
                pass
    except RtdeProbeError as exc:
        raise RtdeProbeError(f"{where} {exc}") from None
    except ConnectionRefusedError:
        raise RtdeProbeError(f"nothing listens on {where} (connection refused)") from None
    except socket.timeout:
        raise RtdeProbeError(f"timed out after {timeout_s:g} s {stage}") from None
    except OSError as exc:
        raise RtdeProbeError(f"{stage}: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------------------------
# The robot
# --------------------------------------------------------------------------------------------

def _sample_from_rtde(pose) -> tuple[np.ndarray, np.ndarray]:
    """RTDE ``actual_TCP_pose`` -> ((3,) position in {B}, mm; (3,) rotation vector, rad)."""
    try:
        return ur_pose_parts(pose)
    except ValueError:
        raise ValueError(f"bad actual_TCP_pose {pose!r}") from None


def _default_client_factory(host: str, frequency: float, variables):
    import rtde_receive  # only when a real robot is used

    return rtde_receive.RTDEReceiveInterface(host, frequency, list(variables))


class URRobot:
    """A UR robot's TCP pose over RTDE (``scanner_core.devices.Robot``).

    Constructing does no I/O; :meth:`connect` starts a reader thread that connects, follows
    the stream and reconnects whenever the link is lost, and never raises for a missing robot
    (``connected`` and :meth:`status` tell).

    Parameters
    ----------
    host : str
        The robot's address (see :func:`parse_robot_url`).
    frequency : float
        Rate asked of the controller, Hz (at most 500 on an e-Series).
    history_s : float
        How far back ``pose_at`` reaches, s of the robot clock.
    stale_s : float
        No new sample for this long means the link is lost, s.
    probe_timeout_s : float
        Longest wait for the robot during a (re)connection attempt, s.
    backoff_s, max_backoff_s : float
        Delay after a failed attempt, doubling up to ``max_backoff_s``, s.
    first_sample_s : float
        How long :meth:`connect` waits for the first sample before returning anyway, s.
    client_factory : callable, optional
        ``(host, frequency, variables) -> client`` with ur-rtde's interface; for tests.

    Notes
    -----
    ``TcpPose.t`` is the controller's ``timestamp`` (s since it started), positions are mm in
    the robot base {B}, rotations are of {T} in {B}. After a link loss the history stays
    queryable (its samples remain true); after :meth:`disconnect` it raises RuntimeError.
    """

    def __init__(self, host: str, *, frequency: float = MAX_FREQUENCY_HZ, history_s: float = 10.0,
                 stale_s: float = 0.5, probe_timeout_s: float = 1.0, backoff_s: float = 0.25,
                 max_backoff_s: float = 2.0, first_sample_s: float = 1.0,
                 client_factory=None):
        if not host or not isinstance(host, str):
            raise ValueError(f"`host` must be a non-empty string, got {host!r}")
        for name, value in (("frequency", frequency), ("history_s", history_s),
                            ("stale_s", stale_s), ("probe_timeout_s", probe_timeout_s),
                            ("backoff_s", backoff_s), ("max_backoff_s", max_backoff_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"`{name}` must be finite and > 0, got {value}")
        if frequency > MAX_FREQUENCY_HZ:
            raise ValueError(f"`frequency` must be <= {MAX_FREQUENCY_HZ:g} Hz, got {frequency}")
        self.host = host
        self.frequency = float(frequency)
        self.history_s = float(history_s)
        self.stale_s = float(stale_s)
        self.probe_timeout_s = float(probe_timeout_s)
        self.backoff_s, self.max_backoff_s = float(backoff_s), float(max(max_backoff_s, backoff_s))
        self.first_sample_s = float(first_sample_s)
        self._factory = client_factory or _default_client_factory
        self._lock = threading.Lock()
        self._have_sample = threading.Condition(self._lock)
        self._times: list[float] = []  # robot clock, s, increasing
        self._positions: list[np.ndarray] = []  # (3,) mm in {B}
        self._rotvecs: list[np.ndarray] = []  # (3,) rad
        self._last_sample_mono: float | None = None
        self._link_up = False
        self._active = False  # between connect() and disconnect()
        self._samples = 0
        self._links = 0
        self._clock_resets = 0
        self._last_error: str | None = None
        self._thread: threading.Thread | None = None
        self._stop: threading.Event | None = None
        self._spare_client = None  # handed from one reader thread to the next

    # -- Robot protocol ------------------------------------------------------------------------
    def connect(self) -> None:
        """Start following the robot; waits up to ``first_sample_s`` for a first sample."""
        with self._lock:
            if self._active:
                return
            self._active = True
            self._clear_history()
        stop = threading.Event()
        thread = threading.Thread(target=self._run, args=(stop,), daemon=True,
                                  name=f"ur-rtde-{self.host}")
        self._stop, self._thread = stop, thread
        thread.start()
        deadline = time.monotonic() + self.first_sample_s
        with self._have_sample:
            while not self._times and time.monotonic() < deadline:
                self._have_sample.wait(max(deadline - time.monotonic(), 0.0))

    def disconnect(self) -> None:
        """Stop following the robot (takes about 0.5 s: ur-rtde's disconnect)."""
        stop, thread = self._stop, self._thread
        with self._lock:
            self._active = False
            self._link_up = False
        if stop is None:
            return
        stop.set()
        # A reconnection in progress may take the client's 2.5 s timeout, plus its 0.5 s
        # disconnect; beyond that the thread is abandoned (it owns its client).
        thread.join(5.0)
        if thread.is_alive():
            log.warning("the ur-rtde reader of %s did not stop", self.host)
        self._stop = self._thread = None

    @property
    def connected(self) -> bool:
        """The link is up and samples are flowing."""
        return self._link_up

    def latest(self) -> TcpPose:
        """Newest sample; RuntimeError when not connected or none has arrived."""
        with self._lock:
            self._check_active()
            if not self._times:
                raise RuntimeError(f"no pose has arrived from the robot at {self.host}")
            t, pos, rv = self._times[-1], self._positions[-1], self._rotvecs[-1]
        return TcpPose(t, pos.copy(), Rotation.from_rotvec(rv).as_matrix())

    def pose_at(self, t: float) -> TcpPose:
        """Pose at robot time ``t``, s: position linearly interpolated between the samples
        around it (``TcpPose.interpolation_mm`` how far the path may bow from that chord),
        rotation along the shortest arc between theirs.

        Raises
        ------
        LookupError
            ``t`` lies outside the history (older than ``history_s`` before the newest sample,
            newer than it, or in a gap of the stream longer than ``MAX_GAP_S``).
        RuntimeError
            Not connected (``connect`` not called, or ``disconnect`` called).
        """
        t = float(t)
        with self._lock:
            self._check_active()
            times = self._times
            if not times or not (times[-1] - self.history_s <= t <= times[-1]) or t < times[0]:
                raise LookupError(f"t = {t:.4f} s is outside the robot's history")
            i = bisect.bisect_left(times, t)
            if times[i] == t:
                return TcpPose(t, self._positions[i].copy(),
                               Rotation.from_rotvec(self._rotvecs[i]).as_matrix())
            t0, t1 = times[i - 1], times[i]
            if t1 - t0 > MAX_GAP_S:
                raise LookupError(f"t = {t:.4f} s falls in a {t1 - t0:.3f} s gap of the "
                                  "robot's stream")
            p0, p1 = self._positions[i - 1], self._positions[i]
            r0, r1 = self._rotvecs[i - 1], self._rotvecs[i]
            # samples a loaded reader missed leave a chord the path may bow away from
            deviation = chord_deviation_mm(
                (times[i - 2], self._positions[i - 2]) if i >= 2 else None, (t0, p0), (t1, p1),
                (times[i + 1], self._positions[i + 1]) if i + 1 < len(times) else None)
        w = (t - t0) / (t1 - t0)
        position = (1.0 - w) * p0 + w * p1
        a = Rotation.from_rotvec(r0)
        if np.array_equal(r0, r1):
            rotation = a.as_matrix()
        else:
            step = (a.inv() * Rotation.from_rotvec(r1)).as_rotvec()
            rotation = (a * Rotation.from_rotvec(w * step)).as_matrix()
        return TcpPose(t, position, rotation, deviation)

    # -- diagnostics -------------------------------------------------------------------------------
    def status(self) -> dict:
        """host, connected, samples (kept since made), reconnects (links made after the
        first), last_sample_age_s (None before the first), last_error (short text or None),
        clock_resets (the controller's clock went back: it restarted)."""
        with self._lock:
            age = (None if self._last_sample_mono is None
                   else time.monotonic() - self._last_sample_mono)
            return {"host": self.host, "connected": self._link_up, "samples": self._samples,
                    "reconnects": max(self._links - 1, 0), "last_sample_age_s": age,
                    "last_error": self._last_error, "clock_resets": self._clock_resets}

    def history(self) -> tuple[np.ndarray, np.ndarray]:
        """The samples kept: (N,) robot times, s, and (N, 3) positions in {B}, mm."""
        with self._lock:
            return np.array(self._times), np.array(self._positions).reshape(-1, 3)

    def _clear_history(self) -> None:
        self._times.clear()
        self._positions.clear()
        self._rotvecs.clear()

    def _check_active(self) -> None:
        if not self._active:
            raise RuntimeError(f"the robot at {self.host} is not connected (call connect)")

    # -- the reader thread ---------------------------------------------------------------------
    def _run(self, stop: threading.Event) -> None:
        with self._lock:
            client, self._spare_client = self._spare_client, None
        backoff = self.backoff_s
        try:
            while not stop.is_set():
                try:
                    client = self._open(client)
                except Exception as exc:  # whatever the client raises, the thread goes on
                    self._fail(exc)
                    stop.wait(backoff)
                    backoff = min(2.0 * backoff, self.max_backoff_s)
                    continue
                backoff = self.backoff_s
                reason = self._follow(client, stop)
                with self._lock:
                    self._link_up = False
                if reason is not None:
                    self._fail(reason)
                # Releases the GIL for its 0.5 s sleep; the object is kept for reconnect().
                self._quietly(client.disconnect)
        finally:
            with self._lock:
                self._link_up = False
                self._spare_client = client

    def _open(self, client):
        """Probe, then make or re-make the ur-rtde client; returns it streaming."""
        probe_rtde(self.host, timeout_s=self.probe_timeout_s, frequency=self.frequency)
        if client is None:
            client = self._factory(self.host, self.frequency, RTDE_VARIABLES)
        elif not client.reconnect():
            raise ConnectionError(f"{self.host}:{RTDE_PORT} sent no data after reconnecting")
        if not client.isConnected():
            # ur-rtde's constructor gives up after 2.5 s without data; keep the object.
            raise ConnectionError(f"{self.host}:{RTDE_PORT} sent no data after connecting")
        return client

    def _follow(self, client, stop: threading.Event) -> str | None:
        """Read samples until the link is lost (returns why) or ``stop`` (returns None)."""
        period = 0.5 / self.frequency  # twice the rate: each sample is seen
        last_new = time.monotonic()
        fresh = True
        while not stop.is_set():
            try:
                if not client.isConnected():
                    return "the robot closed the connection"
                t_a = client.getTimestamp()
                pose = client.getActualTCPPose()
                t_b = client.getTimestamp()
                now = time.monotonic()
                # Equal timestamps around the pose: all three are of one data package, so the
                # pair is never torn. This rests on ur-rtde applying a package whole: in 1.6.5
                # RTDE::receiveData holds RobotState's update_state_mutex_ from the package's
                # first variable to its last, and getStateData (behind every getter) locks the
                # same mutex; timestamps strictly increase within a link. A reader therefore
                # never sees a new timestamp beside the previous package's pose, and a package
                # applied between two of these calls changes t_b: the read is dropped, the next
                # poll gets the package whole. (A check on the values instead, "a pose equal to
                # the previous one while moving is stale", would drop true samples: a robot that
                # stops, or the emulator's track that halts at full speed, repeats its pose.)
                if t_a == t_b and self._keep(t_a, pose, now, fresh):
                    if fresh:
                        fresh = False
                        self._link_made()
                    last_new = now
                elif now - last_new > self.stale_s:
                    return f"no new sample for {self.stale_s:g} s"
            except Exception as exc:  # the getters raise RuntimeError; keep the thread alive
                return f"reading the robot failed: {exc}"
            stop.wait(period)
        return None

    def _keep(self, t: float, pose, now: float, fresh: bool) -> bool:
        position, rotvec = _sample_from_rtde(pose)
        t = float(t)
        with self._have_sample:
            times = self._times
            if times and t <= times[-1]:
                if not (fresh and t < times[-1]):
                    return False
                # The first sample of a new link is older than the history: the controller
                # restarted and its clock with it; the old samples are on another clock.
                self._clock_resets += 1
                self._clear_history()
            times.append(t)
            self._positions.append(position)
            self._rotvecs.append(rotvec)
            self._samples += 1
            self._last_sample_mono = now
            if len(times) % 256 == 0:
                cut = bisect.bisect_left(times, t - self.history_s - MAX_GAP_S)
                del times[:cut], self._positions[:cut], self._rotvecs[:cut]
            self._have_sample.notify_all()
        return True

    def _link_made(self) -> None:
        with self._lock:
            self._links += 1
            self._link_up = True
            self._last_error = None
            links = self._links
        log.info("robot %s: %s", self.host, "connected" if links == 1 else "reconnected")

    def _fail(self, exc) -> None:
        text = str(exc) or type(exc).__name__
        with self._lock:
            repeated = text == self._last_error
            self._last_error = text
        if not repeated:
            log.warning("robot %s: %s", self.host, text)

    @staticmethod
    def _quietly(call) -> None:
        try:
            call()
        except Exception as exc:  # a client already torn down: nothing left to close
            log.debug("ur-rtde disconnect: %s", exc)
