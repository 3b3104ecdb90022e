"""The trigger state machine, one observation at a time."""
import pytest

from scanner_core.pipeline.trigger import EndReason, Trigger, TriggerError, TriggerParams, TriggerState

FPS = 100.0


def feed_all(trigger, presence, start_id=0):
    """Feed frames (id, t = id / FPS) with the given presence; collect what was emitted."""
    emitted, ended = [], None
    for k, present in enumerate(presence):
        fid = start_id + k
        step = trigger.feed(fid, fid / FPS, present, fid)
        emitted += step.emit
        if step.ended:
            ended = (step.ended, fid)
            break
    return emitted, ended


def test_idle_ignores_frames():
    trigger = Trigger()
    emitted, ended = feed_all(trigger, [True] * 5)
    assert emitted == [] and ended is None and trigger.state is TriggerState.IDLE


def test_pass_spans_the_marker_and_keeps_short_gaps():
    trigger = Trigger(TriggerParams(gap_frames=3))
    trigger.arm()
    presence = [False] * 4 + [True] * 5 + [False] * 2 + [True] * 3 + [False] * 5
    emitted, ended = feed_all(trigger, presence)
    assert emitted == list(range(4, 14))  # the 2-frame gap kept, the lead-out not
    assert ended == (EndReason.MARKER_GONE, 16)
    assert trigger.state is TriggerState.PROCESSING
    assert (trigger.first_frame, trigger.last_frame) == (4, 13)
    trigger.finish()
    assert trigger.state is TriggerState.IDLE


def test_a_marker_that_never_leaves_ends_at_the_maximum_length():
    trigger = Trigger(TriggerParams(max_pass_s=0.5))
    trigger.arm()
    emitted, ended = feed_all(trigger, [True] * 1000)
    assert ended[0] is EndReason.TOO_LONG
    assert len(emitted) == int(0.5 * FPS) + 1


def test_armed_trigger_times_out():
    trigger = Trigger(TriggerParams(arm_timeout_s=0.2))
    trigger.arm()
    emitted, ended = feed_all(trigger, [False] * 100)
    assert emitted == [] and ended == (EndReason.TIMEOUT, 20)
    assert trigger.state is TriggerState.IDLE


@pytest.mark.parametrize("during", ["armed", "scanning"])
def test_camera_stop_ends_the_pass(during):
    trigger = Trigger()
    trigger.arm()
    feed_all(trigger, [True] * 3 if during == "scanning" else [False] * 3)
    step = trigger.camera_stopped()
    assert step.ended is EndReason.CAMERA_STOPPED
    assert trigger.state is (TriggerState.PROCESSING if during == "scanning" else TriggerState.IDLE)


def test_cannot_arm_during_a_pass_and_reset_recovers():
    trigger = Trigger()
    trigger.arm()
    feed_all(trigger, [True] * 3)
    with pytest.raises(TriggerError, match="scanning"):
        trigger.arm()
    assert trigger.reset().ended is EndReason.RESET
    trigger.fault("camera lost")
    assert trigger.state is TriggerState.FAULT and trigger.fault_reason == "camera lost"
    with pytest.raises(TriggerError):
        trigger.arm()
    trigger.reset()
    trigger.arm()
    assert trigger.state is TriggerState.ARMED


def test_bad_params_are_refused():
    with pytest.raises(ValueError, match="gap_frames"):
        TriggerParams(gap_frames=0)
    with pytest.raises(ValueError, match="max_pass_s"):
        TriggerParams(max_pass_s=0)
