"""The hub's background recorder: the loop only queues; a thread of its own encodes and writes, in call order."""
import threading
import time

import pytest

from hub.recording import BackgroundRecorder, LogError, Recorder, read_log, summarise

T0 = 1_700_000_000.0


def test_everything_is_written_in_call_order_with_the_callers_stamps(tmp_path):
    path = tmp_path / "run.mcap"
    built_in = []

    def build(i):
        built_in.append(threading.current_thread().name)
        return {"i": i, "built": True}

    with BackgroundRecorder(Recorder(path)) as recorder:
        recorder.write("/robot/1/frame", {"i": 0}, T0)
        recorder.write_later("/robot/1/frame", build, (1,), T0 + 1)
        recorder.count_drop("bad message", "robot 3", T0 + 1.5)
        before = time.time()
        recorder.write("/hub/status", {"now": True})          # stamped now, by the caller
        recorder.kick()
    records = list(read_log(path))
    assert [(r.topic, r.payload) for r in records if r.topic != "/hub/drops"] == [
        ("/robot/1/frame", {"i": 0}), ("/robot/1/frame", {"i": 1, "built": True}), ("/hub/status", {"now": True})]
    assert [r.stamp_s for r in records[:2]] == [T0, T0 + 1]
    assert before <= records[2].stamp_s <= time.time()
    assert built_in == ["khepri-recorder-writer"]
    assert summarise(path).drops == {"bad message": 1}


def test_a_writer_error_is_raised_by_the_next_call(tmp_path):
    inner = Recorder(tmp_path / "run.mcap")
    recorder = BackgroundRecorder(inner)
    inner.close()                                          # from now on every write is refused
    recorder.write("/robot/1/frame", {"i": 0}, T0)
    recorder.kick()
    deadline = time.monotonic() + 5.0
    with pytest.raises(LogError, match="closed"):
        while time.monotonic() < deadline:
            recorder.write("/robot/1/frame", {"i": 1}, T0)
            time.sleep(0.01)
    recorder.close()
