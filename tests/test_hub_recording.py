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


def test_a_string_with_a_lone_surrogate_is_recorded_escaped_and_reads_back_the_same(tmp_path):
    """A file name read with surrogateescape has no UTF-8 form: writing it stopped the whole recording."""
    path = tmp_path / "run.mcap"
    name = b"log-\xff.txt".decode("utf-8", "surrogateescape")
    with BackgroundRecorder(Recorder(path)) as recorder:
        recorder.write("/robot/1/telemetry", {"file": name, "é": "ok"}, T0)
        recorder.write("/robot/1/telemetry", {"file": "after"}, T0 + 1)
    assert [r.payload for r in read_log(path)] == [{"file": name, "é": "ok"}, {"file": "after"}]
    assert summarise(path, check_payloads=True).refused_messages == []


def test_a_message_the_log_cannot_hold_is_left_out_and_counted_and_recording_goes_on(tmp_path):
    """One unwritable telemetry ended the recording for the rest of the run (RECORDING STOPPED), though the file
    was intact; now it is left out, counted under /hub/drops, and said once per topic."""
    path = tmp_path / "run.mcap"
    skipped, failed = [], []
    with BackgroundRecorder(Recorder(path), on_failure=failed.append, on_skip=skipped.append) as recorder:
        recorder.write("/robot/1/frame", {"i": 0}, T0)
        for k in range(3):
            recorder.write("/robot/1/telemetry", {"y": float("inf"), "k": k}, T0 + 1 + k)
        recorder.write_later("/robot/2/telemetry", lambda: {"seen": {1, 2}}, (), T0 + 4)
        recorder.write("/robot/1/frame", {"i": 1}, T0 + 5)
    assert failed == [] and recorder.failure is None
    assert [str(err) for err in skipped] == [
        "/robot/1/telemetry: payload is not JSON-able: Out of range float values are not JSON compliant",
        "/robot/2/telemetry: payload is not JSON-able: Object of type set is not JSON serializable"]
    assert [(r.topic, r.payload) for r in read_log(path) if r.topic != "/hub/drops"] == [
        ("/robot/1/frame", {"i": 0}), ("/robot/1/frame", {"i": 1})]
    summary = summarise(path)
    assert summary.drops == {"unrecordable message": 4}
    assert summary.drops_by_sender == {"/robot/1/telemetry": 3, "/robot/2/telemetry": 1}


def test_a_console_line_with_a_lone_surrogate_is_printed_escaped_and_the_console_stays(tmp_path):
    """say() took the UnicodeEncodeError (a ValueError) for a closed console, and silenced it for good."""
    import io

    from onboard.console import say

    raw = io.BytesIO()
    stream = io.TextIOWrapper(raw, encoding="utf-8", errors="strict")
    say("robot 3: state bad\ud800name", stream)
    say("next line", stream)
    assert raw.getvalue().decode() == "robot 3: state bad\\ud800name\nnext line\n"


def test_a_console_line_its_encoding_cannot_hold_is_escaped_in_that_encoding():
    """On an ASCII console (a C locale) the escaped line must be ASCII too, or the retry fails again."""
    import io

    from onboard.console import say

    raw = io.BytesIO()
    stream = io.TextIOWrapper(raw, encoding="ascii", errors="strict", write_through=True)
    say("état \ud800", stream)
    assert raw.getvalue() == b"\\xe9tat \\ud800\n"


class StalledDisk(Recorder):
    """A real log whose writes hang until ``resume`` is set: a network share that stopped answering."""

    def __init__(self, path):
        super().__init__(path)
        self.resume = threading.Event()

    def write(self, topic, payload, stamp_s=None):
        self.resume.wait()
        super().write(topic, payload, stamp_s)


def test_a_stalled_disk_neither_fills_memory_nor_hangs_the_hubs_way_out(tmp_path):
    """The queue grew without bound while the writer waited on the disk, and close() waited for ever."""
    disk = StalledDisk(tmp_path / "run.mcap")
    behind, failures = [], []
    recorder = BackgroundRecorder(disk, on_failure=failures.append, on_behind=behind.append, max_queued=100,
                                  close_wait_s=0.5)
    for i in range(250):
        recorder.write("/robot/1/frame", {"i": i}, T0 + i)
    recorder.kick()
    assert recorder.left_out >= 149 and behind and behind[0] >= 99     # said once, when the first was left out
    assert len(behind) == 1
    started = time.monotonic()
    recorder.close()
    assert time.monotonic() - started < 2.0
    assert len(failures) == 1 and "has not finished within 0.5 s (a stalled disk?)" in str(failures[0])
    assert recorder.failure == str(failures[0])
    disk.resume.set()                 # the share answers again: the write under way ends, and nothing after it
    deadline = time.monotonic() + 5.0
    while recorder._thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    disk.flush()
    assert [r.payload["i"] for r in read_log(tmp_path / "run.mcap") if r.topic == "/robot/1/frame"] == [0]
