"""ZeroMQ subscriber for what the flyscan service publishes: clouds, edge clouds, poses, status.

    from clients import CloudSubscriber

    with CloudSubscriber("tcp://127.0.0.1:5556", topics=("cloud", "pose")) as sub:
        while True:
            msg = sub.receive(timeout=5.0)        # TimeoutError when nothing came in time
            if msg.topic == "cloud":
                xyz = msg.array                   # (N, 3) float32, mm in {T}, read-only
                print(msg.scan_id, xyz.shape, "lost so far:", sub.lost)

The wire format (docs/service.md, ZeroMQ): every message is multipart, ``[topic, header]`` or
``[topic, header, payload]``; the header is UTF-8 JSON with at least ``scan_id``, ``seq``,
``frame`` ("T"), ``units`` ("mm"), ``t`` (unix seconds), and with a payload ``dtype`` ("<f4"),
``shape`` ([N, 3]) and ``fields`` (["x", "y", "z"]); the payload is the raw C-order array.
:func:`load_message` checks all of it and builds the array with ``np.frombuffer``: nothing from
the network is evaluated or unpickled, and only plain numeric dtypes are accepted.

Things a subscriber must know:

- Slow joiner. A SUB socket receives nothing until its subscription has reached the publisher,
  some milliseconds after ``connect``: the messages published in that moment are missed, and
  nobody can tell. Connect early (before arming the scan you want) and keep the subscriber open;
  a subscriber opened after the scan was published never sees it (fetch it over REST).
- Lost messages. The publisher never blocks: when this subscriber falls behind by more than its
  high-water mark, the publisher drops messages for it. ``seq`` goes up by one per message the
  publisher sends on a topic, so gaps are counted per topic in :attr:`CloudSubscriber.lost`,
  whichever topics are subscribed to. Messages missed before the first one received (slow joiner) are not counted; a
  ``seq`` that goes back (the service restarted) starts the count afresh.
- One thread owns a socket: use a subscriber from the thread that opened it.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

import numpy as np
import zmq

__all__ = ["CloudSubscriber", "Message", "MessageError", "load_message", "TOPICS"]

TOPICS = ("cloud", "edges", "pose", "status")
_REQUIRED_KEYS = ("scan_id", "seq", "frame", "units", "t")
# Receive queue per subscriber, in messages (ZeroMQ's default is 1000): a cloud a message,
# so this is plenty; beyond it the publisher drops messages and `lost` counts them.
_DEFAULT_RCVHWM = 1000


class MessageError(ValueError):
    """A message does not follow the wire format (it is refused, never half-read)."""


@dataclass(frozen=True)
class Message:
    """One published message.

    Attributes
    ----------
    topic : str
        "cloud", "edges", "pose" or "status".
    header : dict
        The JSON header (``scan_id``, ``seq``, ``frame``, ``units``, ``t``, and per topic more:
        ``pose`` for pose, ``state`` for status, ``dtype``/``shape``/``fields`` with a payload).
    array : ndarray or None
        The payload as an array of the header's dtype and shape (clouds: (N, 3) float32, mm in
        {T}), read-only (``array.copy()`` to modify it); None for a message without payload.
    """

    topic: str
    header: dict
    array: np.ndarray | None = None

    @property
    def scan_id(self) -> str | None:
        return self.header.get("scan_id")

    @property
    def seq(self) -> int:
        return self.header["seq"]


def load_message(frames: list[bytes]) -> Message:
    """Decode one multipart message ``[topic, header]`` or ``[topic, header, payload]``.

    Raises
    ------
    MessageError
        Wrong number of frames, a header that is not a JSON object with the required keys,
        a dtype that is not a plain numeric one, a shape that is not a list of non-negative
        integers, or a payload whose size does not match dtype and shape.
    """
    if len(frames) not in (2, 3):
        raise MessageError(f"a message has 2 or 3 frames (topic, header[, payload]), "
                           f"got {len(frames)}")
    topic = _decode_topic(frames[0])
    header = _decode_header(frames[1], topic)
    has_payload = len(frames) == 3
    if not has_payload:
        if "dtype" in header or "shape" in header:
            raise MessageError(f"{topic} message {header['seq']}: the header has dtype/shape "
                               "but the message has no payload")
        return Message(topic, header, None)
    payload = memoryview(frames[2]).cast("B")
    dtype = _payload_dtype(header, topic)
    shape = _payload_shape(header, topic)
    expected = math.prod(shape) * dtype.itemsize
    if payload.nbytes != expected:
        raise MessageError(f"{topic} message {header['seq']}: payload is {payload.nbytes} bytes, "
                           f"but dtype {header['dtype']!r} and shape {list(shape)} need "
                           f"{expected}")
    fields = header.get("fields")
    if fields is not None and (not isinstance(fields, list) or len(shape) != 2
                               or len(fields) != shape[1]):
        raise MessageError(f"{topic} message {header['seq']}: fields {fields!r} do not match "
                           f"shape {list(shape)} (one field per column)")
    array = np.frombuffer(payload, dtype=dtype).reshape(shape)
    return Message(topic, header, array)


class CloudSubscriber:
    """A SUB socket on the service's publisher, decoding and checking every message.

    Parameters
    ----------
    endpoint : str
        The publisher's address, ``tcp://HOST:PORT``.
    topics : iterable of str
        Topics to receive, among "cloud", "edges", "pose", "status".
    rcvhwm : int
        Messages queued for this subscriber before the publisher drops (see :attr:`lost`).
    context : zmq.Context, optional
        Defaults to the process's shared ``zmq.Context.instance()``.

    Constructing does no I/O: :meth:`connect` (or ``with``) opens the socket, :meth:`close`
    closes it. See the module docstring for the slow joiner and lost messages.

    Attributes
    ----------
    lost : int
        Messages the publisher sent but this subscriber did not get, from gaps in ``seq``.
    received : int
        Messages received (of every topic subscribed to).
    """

    def __init__(self, endpoint: str = "tcp://127.0.0.1:5556", topics=TOPICS, *,
                 rcvhwm: int = _DEFAULT_RCVHWM, context: zmq.Context | None = None):
        if isinstance(topics, str):
            topics = (topics,)
        topics = tuple(topics)
        unknown = sorted(set(topics) - set(TOPICS))
        if unknown or not topics:
            raise ValueError(f"`topics` must be among {TOPICS}, got {topics}")
        self.endpoint = endpoint
        self.topics = topics
        self.rcvhwm = rcvhwm
        self.lost = 0
        self.received = 0
        self._context = context
        self._socket: zmq.Socket | None = None
        self._last_seq: dict[bytes, int] = {}

    def connect(self) -> CloudSubscriber:
        """Open the SUB socket, subscribe and connect (the publisher may start later)."""
        if self._socket is not None:
            return self
        context = self._context or zmq.Context.instance()
        socket = context.socket(zmq.SUB)
        try:
            socket.setsockopt(zmq.LINGER, 0)
            socket.setsockopt(zmq.RCVHWM, self.rcvhwm)
            for topic in self.topics:
                socket.setsockopt(zmq.SUBSCRIBE, topic.encode())
            socket.connect(self.endpoint)
        except zmq.ZMQError as exc:
            socket.close(linger=0)
            raise ConnectionError(f"cannot connect a subscriber to {self.endpoint!r}: {exc}") \
                from None
        self._socket = socket
        return self

    def close(self) -> None:
        """Close the socket (pending messages are dropped)."""
        if self._socket is not None:
            self._socket.close(linger=0)
            self._socket = None

    def __enter__(self) -> CloudSubscriber:
        return self.connect()

    def __exit__(self, *exc_info) -> None:
        self.close()

    def receive(self, timeout: float | None = None) -> Message:
        """The next message of a subscribed topic.

        Parameters
        ----------
        timeout : float, optional
            Seconds to wait; None waits for ever (Ctrl-C interrupts), 0 only takes what is
            already queued.

        Raises
        ------
        TimeoutError
            No message within `timeout`.
        MessageError
            The message broke the wire format; it is dropped (its ``seq`` still counts), and
            the next call goes on with the next message.
        """
        if self._socket is None:
            raise RuntimeError("the subscriber is not connected: use `with CloudSubscriber(...)` "
                               "or call connect() first")
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        while True:
            if deadline is not None:
                remaining_ms = max(0, math.ceil((deadline - time.monotonic()) * 1000))
                if not self._socket.poll(remaining_ms, zmq.POLLIN):
                    raise TimeoutError(f"no message from {self.endpoint} within {timeout:g} s "
                                       f"(topics {', '.join(self.topics)})")
            frames = self._socket.recv_multipart(copy=True)
            # Subscriptions match prefixes: a topic "cloudy" would pass the "cloud" filter.
            exact = frames[0].decode("utf-8", "replace") in self.topics
            if exact:
                self.received += 1
            self._count_seq(frames)
            if exact:
                return load_message(frames)

    def _count_seq(self, frames: list[bytes]) -> None:
        """Follow ``seq`` before the message is checked, so a refused message is not 'lost'."""
        try:
            seq = json.loads(frames[1])["seq"]
        except (IndexError, ValueError, KeyError, TypeError):
            return
        if not isinstance(seq, int) or isinstance(seq, bool):
            return
        last = self._last_seq.get(frames[0])
        if last is not None and seq > last:
            self.lost += seq - last - 1
        self._last_seq[frames[0]] = seq


def _decode_topic(frame: bytes) -> str:
    try:
        topic = bytes(frame).decode("ascii")
    except UnicodeDecodeError:
        raise MessageError(f"topic {bytes(frame)[:32]!r} is not ASCII") from None
    if topic not in TOPICS:
        raise MessageError(f"unknown topic {topic!r}; known: {TOPICS}")
    return topic


def _decode_header(frame: bytes, topic: str) -> dict:
    try:
        header = json.loads(bytes(frame).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MessageError(f"{topic} message: the header is not UTF-8 JSON ({exc})") from None
    if not isinstance(header, dict):
        raise MessageError(f"{topic} message: the header is a JSON {type(header).__name__}, "
                           "not an object")
    missing = [key for key in _REQUIRED_KEYS if key not in header]
    if missing:
        raise MessageError(f"{topic} message: the header lacks {missing}")
    if not isinstance(header["seq"], int) or isinstance(header["seq"], bool):
        raise MessageError(f"{topic} message: seq {header['seq']!r} is not an integer")
    return header


def _payload_dtype(header: dict, topic: str) -> np.dtype:
    spec = header.get("dtype")
    # Only plain numeric scalars: no object dtype (pickles), no structured or sub-array dtypes.
    try:
        dtype = np.dtype(spec) if isinstance(spec, str) else None
    except (TypeError, ValueError):
        dtype = None
    if dtype is None or dtype.kind not in "iuf" or dtype.fields is not None \
            or dtype.subdtype is not None:
        raise MessageError(f"{topic} message {header['seq']}: dtype {spec!r} is not a plain "
                           "numeric dtype such as '<f4'")
    return dtype


def _payload_shape(header: dict, topic: str) -> tuple[int, ...]:
    shape = header.get("shape")
    if not isinstance(shape, list) or not all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
        raise MessageError(f"{topic} message {header['seq']}: shape {shape!r} is not a list of "
                           "non-negative integers")
    return tuple(shape)
