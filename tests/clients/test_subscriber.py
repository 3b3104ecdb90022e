"""CloudSubscriber against a real PUB socket on loopback, sending messages of the wire contract."""
import json
import time

import numpy as np
import pytest
import zmq
from numpy.testing import assert_array_equal

from clients import CloudSubscriber, Message, MessageError, load_message

# Bounds for the slow joiner: a subscription reaches a loopback publisher in milliseconds.
JOIN_TIMEOUT_S = 5.0
JOIN_POLL_S = 0.01


class Publisher:
    """A PUB socket that numbers its messages like the service does: per topic."""

    def __init__(self):
        self.socket = zmq.Context.instance().socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        port = self.socket.bind_to_random_port("tcp://127.0.0.1")
        self.endpoint = f"tcp://127.0.0.1:{port}"
        self.seqs = {}
        self.topic = "status"

    @property
    def seq(self):
        return self.seqs.get(self.topic, 0)

    @seq.setter
    def seq(self, value):
        self.seqs[self.topic] = value

    def header(self, scan_id="s1", topic=None, **extra):
        self.topic = topic or "status"
        self.seq += 1
        return {"scan_id": scan_id, "seq": self.seq, "frame": "T", "units": "mm",
                "t": time.time(), **extra}

    def send(self, topic, header, payload=None):
        frames = [topic.encode(), json.dumps(header).encode()]
        self.socket.send_multipart(frames if payload is None else frames + [payload])

    def send_array(self, topic, array, scan_id="s1", **extra):
        header = self.header(scan_id, topic, dtype=array.dtype.str, shape=list(array.shape),
                             fields=["x", "y", "z"], **extra)
        self.send(topic, header, np.ascontiguousarray(array).tobytes())
        return header

    def close(self):
        self.socket.close(linger=0)


@pytest.fixture
def pub():
    publisher = Publisher()
    yield publisher
    publisher.close()


def joined(pub, sub):
    """Publish status messages until the subscriber gets one (the slow joiner), then a last
    one: messages keep their order, so when that one arrives no warm-up is left queued."""
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    while True:
        pub.send("status", pub.header(scan_id=None, state="idle"))
        try:
            first = sub.receive(timeout=JOIN_POLL_S)
            break
        except TimeoutError:
            if time.monotonic() > deadline:
                pytest.fail("the subscriber never joined")
    pub.send("status", pub.header(scan_id=None, state="synced"))
    while sub.receive(timeout=JOIN_TIMEOUT_S).header["state"] != "synced":
        pass
    return first


def test_cloud_round_trip(pub, rng):
    xyz = rng.normal(scale=40.0, size=(1000, 3)).astype("<f4")
    with CloudSubscriber(pub.endpoint) as sub:
        first = joined(pub, sub)
        assert first.topic == "status" and first.array is None and first.header["state"] == "idle"
        sent = pub.send_array("cloud", xyz, scan_id="abc")
        msg = sub.receive(timeout=2.0)
    assert isinstance(msg, Message)
    assert (msg.topic, msg.scan_id, msg.seq) == ("cloud", "abc", sent["seq"])
    assert msg.header == sent
    assert msg.array.shape == (1000, 3) and msg.array.dtype == np.float32
    assert_array_equal(msg.array, xyz)
    assert not msg.array.flags.writeable
    assert sub.lost == 0


def test_empty_cloud_and_pose_without_payload(pub):
    with CloudSubscriber(pub.endpoint) as sub:
        joined(pub, sub)
        pub.send_array("edges", np.zeros((0, 3), "<f4"))
        pose = {"matrix": np.eye(4).tolist(), "misplacement": {"translation_mm": [0, 0, 0]}}
        pub.send("pose", pub.header(pose=pose))
        edges, pose_msg = sub.receive(timeout=2.0), sub.receive(timeout=2.0)
    assert edges.topic == "edges" and edges.array.shape == (0, 3)
    assert pose_msg.topic == "pose" and pose_msg.array is None
    assert pose_msg.header["pose"] == pose


def test_seq_gaps_are_counted_as_lost(pub):
    with CloudSubscriber(pub.endpoint) as sub:
        joined(pub, sub)
        pub.seq += 3                                            # three messages never arrive
        pub.send("status", pub.header(state="armed"))
        sub.receive(timeout=2.0)
        assert sub.lost == 3
        pub.send("status", pub.header(state="scanning"))
        sub.receive(timeout=2.0)
        assert sub.lost == 3
        pub.seq = 0                                             # the service restarted
        pub.send("status", pub.header(state="idle"))
        sub.receive(timeout=2.0)
        pub.seq += 1
        pub.send("status", pub.header(state="armed"))
        sub.receive(timeout=2.0)
    assert sub.lost == 4


def test_topics_filter_exactly(pub, rng):
    xyz = rng.normal(size=(3, 3)).astype("<f4")
    with CloudSubscriber(pub.endpoint, topics=("cloud", "status")) as sub:
        joined(pub, sub)
        pub.send_array("edges", xyz)                            # not subscribed
        pub.send("cloudy", pub.header())                        # matches the prefix "cloud"
        pub.send_array("cloud", xyz)
        msg = sub.receive(timeout=2.0)
        assert msg.topic == "cloud"
        with pytest.raises(TimeoutError):
            sub.receive(timeout=0.05)
    assert sub.lost == 0                          # seq counts per topic: "edges" is not followed


def test_bad_payload_size_is_refused_and_the_next_message_read(pub):
    with CloudSubscriber(pub.endpoint) as sub:
        joined(pub, sub)
        header = pub.header(dtype="<f4", shape=[10, 3], fields=["x", "y", "z"])
        pub.send("cloud", header, b"\0" * (10 * 3 * 4 - 4))
        with pytest.raises(MessageError, match=r"payload is 116 bytes, but dtype '<f4' and "
                                               r"shape \[10, 3\] need 120"):
            sub.receive(timeout=2.0)
        pub.send_array("cloud", np.ones((2, 3), "<f4"))
        assert sub.receive(timeout=2.0).array.shape == (2, 3)
    assert sub.lost == 0


def test_receive_times_out(pub):
    with CloudSubscriber(pub.endpoint, topics=("pose",)) as sub:
        start = time.monotonic()
        with pytest.raises(TimeoutError, match="no message from .* within 0.1 s"):
            sub.receive(timeout=0.1)
        assert time.monotonic() - start < 1.0
        with pytest.raises(TimeoutError):
            sub.receive(timeout=0)


def test_receive_needs_a_connection():
    sub = CloudSubscriber("tcp://127.0.0.1:1")                  # constructing does no I/O
    with pytest.raises(RuntimeError, match="not connected"):
        sub.receive(timeout=0)
    with pytest.raises(ValueError, match="topics"):
        CloudSubscriber(topics=("clouds",))
    with pytest.raises(ConnectionError, match="cannot connect"):
        CloudSubscriber("not an endpoint").connect()


# -- the decoder on its own -------------------------------------------------------------------
def frames(header=None, payload=None, topic=b"cloud", **changes):
    base = {"scan_id": "s", "seq": 1, "frame": "T", "units": "mm", "t": 0.0}
    if payload is not None:
        base |= {"dtype": "<f4", "shape": [2, 3], "fields": ["x", "y", "z"]}
    base |= changes
    head = json.dumps(base).encode() if header is None else header
    return [topic, head] + ([] if payload is None else [payload])


GOOD_PAYLOAD = np.arange(6, dtype="<f4").tobytes()


def test_load_message_accepts_other_numeric_dtypes():
    msg = load_message(frames(payload=np.arange(6, dtype=">i2").tobytes(), dtype=">i2"))
    assert_array_equal(msg.array, np.arange(6).reshape(2, 3))


@pytest.mark.parametrize("bad, message", [
    ([b"cloud"], "2 or 3 frames"),
    (frames(topic=b"images"), "unknown topic 'images'"),
    (frames(header=b"\x80 not json"), "not UTF-8 JSON"),
    (frames(header=b"[1, 2]"), "JSON list, not an object"),
    (frames(header=b'{"scan_id": "s", "seq": 1}'), r"lacks \['frame', 'units', 't'\]"),
    (frames(seq="7"), "seq '7' is not an integer"),
    (frames(payload=GOOD_PAYLOAD, dtype="O"), "dtype 'O' is not a plain numeric"),
    (frames(payload=GOOD_PAYLOAD, dtype="<f4,<i4"), "not a plain numeric"),
    (frames(payload=GOOD_PAYLOAD, dtype="(3,)<f4"), "not a plain numeric"),
    (frames(payload=GOOD_PAYLOAD, dtype="no such type"), "not a plain numeric"),
    (frames(payload=GOOD_PAYLOAD, dtype=None), "dtype None"),
    (frames(payload=GOOD_PAYLOAD, shape=[2, -3]), "not a list of non-negative integers"),
    (frames(payload=GOOD_PAYLOAD, shape="2,3"), "not a list of non-negative integers"),
    (frames(payload=GOOD_PAYLOAD, fields=["x", "y"]), "one field per column"),
    (frames(dtype="<f4", shape=[2, 3]), "no payload"),
])
def test_load_message_refuses_what_breaks_the_contract(bad, message):
    with pytest.raises(MessageError, match=message):
        load_message(bad)
