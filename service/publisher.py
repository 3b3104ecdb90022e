"""The ZeroMQ publisher: clouds, edges, poses and status, never blocking acquisition.

One thread owns the PUB socket (ZeroMQ sockets are not thread-safe); other threads hand it
messages through a bounded queue and never wait. A message is ``[topic, header]`` or
``[topic, header, payload]``: the header UTF-8 JSON (``scan_id``, ``seq``, ``frame`` "T",
``units`` "mm", ``t`` unix seconds and, with a payload, ``dtype``, ``shape``, ``fields``), the
payload the raw C-order array.

Nothing waits for a subscriber. Every message is numbered (``seq``, one more per message on its
topic) when it is handed over, so every loss shows as a gap to the subscriber that suffered it:
a message the queue cannot take (counted here in ``dropped``), or one that ZeroMQ drops for a
subscriber more than its high-water mark behind (a PUB socket drops per subscriber and tells the
sender nothing, so only that subscriber can count it: ``clients.CloudSubscriber.lost``). The
others keep receiving everything.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time

import numpy as np
import zmq

log = logging.getLogger("flyscan.publisher")

TOPICS = ("cloud", "edges", "pose", "status")
#: Messages waiting for the socket's thread, at most.
QUEUE_MESSAGES = 64


def encode_message(topic: str, header: dict, array: np.ndarray | None = None) -> list[bytes]:
    """The multipart frames of one message (``seq`` and ``t`` must already be in ``header``)."""
    if topic not in TOPICS:
        raise ValueError(f"topic must be one of {TOPICS}, got {topic!r}")
    header = {"frame": "T", "units": "mm", **header}
    if array is None:
        return [topic.encode(), json.dumps(header, allow_nan=False).encode()]
    array = np.ascontiguousarray(array, dtype="<f4")
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"payload must be (N, 3), got {array.shape}")
    header |= {"dtype": "<f4", "shape": list(array.shape), "fields": ["x", "y", "z"]}
    return [topic.encode(), json.dumps(header, allow_nan=False).encode(), array.view(np.uint8).reshape(-1)]


class Publisher:
    """The PUB socket and its thread. ``start``/``stop`` are explicit; constructing binds nothing."""

    def __init__(self, endpoint: str, *, hwm: int = 100, context: zmq.Context | None = None):
        self.endpoint = endpoint
        self.hwm = int(hwm)
        self._context = context or zmq.Context.instance()
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_MESSAGES)
        self._seq: dict[str, int] = {}
        self._seq_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.sent = 0
        self.dropped = 0
        self.last_sent_monotonic: dict[str, float] = {}
        self.bound_endpoint: str | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="zmq-publisher", daemon=True)
        self._thread.start()
        self._ready.wait(5.0)
        if self._error is not None:
            raise RuntimeError(f"cannot bind the ZeroMQ publisher to {self.endpoint}: {self._error}")

    def stop(self) -> None:
        if self._thread is not None:
            try:
                self._queue.put(None, timeout=5.0)
            except queue.Full:
                log.error("the publisher's queue stayed full: its thread is stuck")
            self._thread.join(5.0)
            self._thread = None

    def publish(self, topic: str, header: dict, array: np.ndarray | None = None,
                on_sent=None) -> bool:
        """Queue one message; False (and counted) when the queue is full. ``on_sent`` is called
        on the socket's thread with the monotonic time the message left."""
        with self._seq_lock:  # numbered here, so a message the queue refuses is a gap too
            self._seq[topic] = seq = self._seq.get(topic, 0) + 1
        try:
            self._queue.put_nowait((topic, {**header, "seq": seq}, array, on_sent))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def _run(self) -> None:
        try:
            socket = self._context.socket(zmq.PUB)
            socket.setsockopt(zmq.SNDHWM, self.hwm)
            socket.setsockopt(zmq.LINGER, 0)
            socket.bind(self.endpoint)
            self.bound_endpoint = socket.getsockopt_string(zmq.LAST_ENDPOINT)
        except zmq.ZMQError as exc:
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            while True:
                item = self._queue.get()
                if item is None:
                    return
                topic, header, array, on_sent = item
                try:
                    frames = encode_message(topic, {**header, "t": time.time()}, array)
                except (TypeError, ValueError) as exc:  # a caller's bug: counted, logged, survived
                    log.error("message on %r not sent: %s", topic, exc)
                    self.dropped += 1
                    continue
                try:
                    socket.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
                    self.sent += 1
                except zmq.Again:
                    self.dropped += 1
                now = time.monotonic()
                self.last_sent_monotonic[topic] = now
                if on_sent is not None:
                    try:
                        on_sent(topic, now)
                    except Exception:  # the caller's bookkeeping must not end publishing
                        log.exception("on_sent callback for %r failed", topic)
        finally:
            socket.close(linger=0)
