"""Hub recordings: MCAP round trip, summaries, a SIGKILLed recorder, damaged files, and ``khepri log info``."""
import json
import math
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import pytest
from mcap.reader import make_reader

from hub.recording import (
    CONTROL,
    HUB_DROPS,
    HUB_STATUS,
    MOCAP_POSES,
    ROBOT_TOPIC_KINDS,
    ForeignChannelWarning,
    LogError,
    Recorder,
    read_log,
    robot_topic,
    summarise,
)

REPO = Path(__file__).resolve().parents[1]
# This checkout's code, whichever checkout or worktree runs the tests (an installed `khepri` script runs the
# checkout it was installed from).
KHEPRI = [sys.executable, "-m", "khepri_cli.main"]
ENV = dict(os.environ, PYTHONPATH=str(REPO))
T0 = 1_770_000_000.0   # a fixed hub-clock start, so stamps and durations are exact


def every_topic_records():
    """(topic, payload, stamp) for every topic the hub uses, two robots, in write order."""
    records = [(MOCAP_POSES, {"bodies": {"kh1": [1.0, 2.0, 0.05, 0.0, 0.0, 0.38, 0.92]}, "frame": 7}, T0)]
    for robot in (1, 2):
        for kind in ROBOT_TOPIC_KINDS:
            payload = {"robot": robot, "kind": kind, "nested": {"list": [1, 2.5, None, True], "text": "é ∆"}}
            records.append((robot_topic(robot, kind), payload, T0 + len(records) * 0.01))
    records.append((CONTROL, {"request": "estop", "reply": "ok"}, T0 + 1.0))
    records.append((HUB_STATUS, {"frames_per_s": 120.0, "robots": 2}, T0 + 1.5))
    return records


def write_log(path, records, **options):
    with Recorder(path, **options) as recorder:
        for topic, payload, stamp in records:
            recorder.write(topic, payload, stamp)
    return path


def test_every_topic_round_trips_and_standard_mcap_readers_see_json_with_schemas(tmp_path):
    records = every_topic_records()
    path = write_log(tmp_path / "all.mcap", records, metadata={"lab": "L1", "robots": [1, 2]})

    back = [(r.topic, r.payload, r.stamp_s) for r in read_log(path)]
    assert [(topic, payload) for topic, payload, _ in back] == [(topic, payload) for topic, payload, _ in records]
    assert all(math.isclose(got, want, abs_tol=1e-6) for (_, _, got), (_, _, want) in zip(back, records))
    assert [r.topic for r in read_log(path, topics=[CONTROL, "/robot/2/relay"])] == ["/robot/2/relay", CONTROL]
    assert [r.topic for r in read_log(path, topics=CONTROL)] == [CONTROL]

    # What Foxglove relies on: json messages, a jsonschema object schema on every channel, an index.
    with open(path, "rb") as file:
        index = make_reader(file).get_summary()
    assert {channel.topic for channel in index.channels.values()} == {topic for topic, _, _ in records}
    for channel in index.channels.values():
        schema = index.schemas[channel.schema_id]
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        assert json.loads(schema.data)["type"] == "object"
    frame_schemas = {index.schemas[c.schema_id].name for c in index.channels.values() if c.topic.endswith("/frame")}
    assert frame_schemas == {"khepri.RobotFrame"}


def test_summary_counts_robots_drops_and_metadata(tmp_path):
    path = tmp_path / "counts.mcap"
    with Recorder(path, metadata={"lab": "L1", "seed": 3}) as recorder:
        for i in range(30):
            recorder.write(MOCAP_POSES, {"bodies": {}}, T0 + i / 10)
        for robot in (10, 2):
            for i in range(5):
                recorder.write(robot_topic(robot, "frame"), {"i": i}, T0 + 1 + i / 10)
        recorder.write(robot_topic(2, "telemetry"), {"state": "push"}, T0 + 1.5)
        for i in range(4):
            recorder.count_drop("stale_pose", sender="2", stamp_s=T0 + i / 10)
        recorder.count_drop("oversize", sender=10, stamp_s=T0 + 2.9)
        recorder.count_drop("unknown_sender", stamp_s=T0 + 2)

    summary = summarise(path)
    assert summary.truncated is False and summary.stop_reason == ""
    assert summary.robots == [2, 10]
    counts = {topic: n for topic, n in summary.topic_counts.items() if topic != HUB_DROPS}
    assert counts == {MOCAP_POSES: 30, "/robot/10/frame": 5, "/robot/2/frame": 5, "/robot/2/telemetry": 1}
    assert summary.drops == {"oversize": 1, "stale_pose": 4, "unknown_sender": 1}
    assert summary.drops_by_sender == {"10": 1, "2": 4, "unknown": 1}
    assert summary.start_s == pytest.approx(T0) and summary.duration_s == pytest.approx(2.9, abs=1e-6)
    assert summary.metadata == {"lab": "L1", "seed": 3} and summary.format_version == 1
    # The index (fast) and a record-by-record walk agree on a complete file.
    assert summarise(path, use_index=False) == summary


def test_log_info_names_the_bodies_a_motion_capture_log_places(tmp_path):
    """A motion-capture-only log said `robots: none`: which ids a replay of it would feed took a script."""
    from hub.log_text import format_summary

    path = tmp_path / "mocap.mcap"
    with Recorder(path) as recorder:
        recorder.write(MOCAP_POSES, {"bodies": {"11": [0, 0, 0, 0, 0, 0, 1]}, "clock_s": None}, T0)
        recorder.write(MOCAP_POSES, {"bodies": {"10": [0, 0, 0, 0, 0, 0, 1]}, "clock_s": None}, T0 + 1)
    summary = summarise(path)
    assert summary.robots == [] and summary.posed_robots == [10, 11]
    assert summarise(path, use_index=False) == summary
    text = format_summary(summary)
    assert "robots:    none\nposed:     2 (10, 11) in the first and last /mocap/poses records\n" in text, text


def test_a_sil_log_says_how_much_it_simulated_beside_its_wall_clock_duration(tmp_path):
    """log info on a sil log showed 10 s (the wall clock) for a 30 s simulated run, and nothing else."""
    from hub.log_text import format_summary

    path = tmp_path / "sil.mcap"
    with Recorder(path, chunk_size=2048) as recorder:       # many chunks: the index path reads only the ends
        for step in range(300):
            recorder.write(MOCAP_POSES, {"bodies": {"0": [0.1 * step, 0, 0, 0, 0, 0, 1]}, "clock_s": step / 10},
                           T0 + step / 30)
    summary = summarise(path)
    assert (summary.sim_start_s, summary.sim_end_s) == (0.0, 29.9)
    assert summarise(path, use_index=False) == summary
    assert "duration:  9.967 s\nsimulated: 29.900 s (clock_s 0.000 to 29.900 s in /mocap/poses)" \
        in format_summary(summary)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:6000])
    recovered = summarise(cut)
    assert recovered.truncated and recovered.sim_start_s == 0.0 and 0.0 < recovered.sim_end_s < 29.9

    lab = write_log(tmp_path / "lab.mcap", [(MOCAP_POSES, {"bodies": {}, "clock_s": None}, T0 + i) for i in range(3)])
    assert summarise(lab).sim_start_s is None and "simulated:" not in format_summary(summarise(lab))


def test_bad_payloads_raise_naming_the_topic_and_leave_the_file_intact(tmp_path):
    path = tmp_path / "bad.mcap"
    with Recorder(path) as recorder:
        recorder.write("/robot/1/frame", {"i": 0}, T0)
        for payload in ({"when": object()}, {"x": float("nan")}, ["not", "a", "dict"]):
            with pytest.raises(LogError, match="/robot/1/telemetry"):
                recorder.write("/robot/1/telemetry", payload, T0)
        for stamp in (-5.0, time.monotonic() % 1e6, float("nan"), "now"):   # a monotonic clock would scramble the log
            with pytest.raises(LogError, match="/robot/1/frame: stamp_s must be wall-clock"):
                recorder.write("/robot/1/frame", {"i": 1}, stamp)
        with pytest.raises(LogError, match="topic"):
            recorder.write("no-slash", {"i": 1}, T0)
        recorder.write("/robot/1/frame", {"i": 2}, T0 + 1)
    assert [r.payload for r in read_log(path)] == [{"i": 0}, {"i": 2}]
    with open(path, "rb") as file:   # the mcap library's own reader agrees the file is whole
        assert len(list(make_reader(file).iter_messages())) == 2


def test_recorder_lifecycle_and_bad_arguments(tmp_path):
    recorder = Recorder(tmp_path / "life.mcap")
    recorder.write(CONTROL, {"request": "status"})
    recorder.close()
    recorder.close()   # idempotent
    with pytest.raises(LogError, match="closed"):
        recorder.write(CONTROL, {"request": "status"})
    assert summarise(tmp_path / "life.mcap").topic_counts == {CONTROL: 1}
    with pytest.raises(LogError, match="no-such-folder"):
        Recorder(tmp_path / "no-such-folder" / "x.mcap")
    with pytest.raises(LogError, match="metadata.when"):
        Recorder(tmp_path / "meta.mcap", metadata={"when": object()})
    if Path("/dev/full").exists():   # a disk that is full: the error names the file instead of a traceback
        with pytest.raises(LogError, match="/dev/full: cannot write the log"):
            Recorder("/dev/full")


def test_an_idle_recorder_still_flushes_within_its_period(tmp_path):
    """The timer thread closes the chunk even when nothing else is written (a hub idle, then killed)."""
    path = tmp_path / "idle.mcap"
    with Recorder(path, flush_period_s=0.2) as recorder:
        recorder.write(MOCAP_POSES, {"bodies": {}}, T0)
        recorder.count_drop("stale_pose", sender="1")
        deadline = time.monotonic() + 10.0
        seen = []
        while not seen and time.monotonic() < deadline:
            time.sleep(0.05)
            seen = [r.topic for r in read_log(path)]
        assert seen == [MOCAP_POSES, HUB_DROPS]
        assert summarise(path).truncated is True   # still open: no footer yet


CHILD = textwrap.dedent("""
    import sys, time
    from hub.recording import Recorder
    recorder = Recorder(sys.argv[1])   # default flush_period_s = 1.0
    i = 0
    while True:
        recorder.write("/robot/1/telemetry", {"i": i}, time.time())
        i += 1
        time.sleep(0.005)
""")


def test_a_sigkilled_recorder_loses_at_most_about_a_second(tmp_path):
    path = tmp_path / "killed.mcap"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], cwd=REPO)
    try:
        # While the child writes, everything older than about a second must already be readable.
        deadline = time.monotonic() + 20.0
        stamps, worst_lag = [], 0.0
        while time.monotonic() < deadline and (len(stamps) < 2 or stamps[-1] - stamps[0] < 3.0):
            time.sleep(0.1)
            stamps = [r.stamp_s for r in read_log(path)] if path.exists() and path.stat().st_size else []
            if stamps:
                worst_lag = max(worst_lag, time.time() - stamps[-1])
        assert child.poll() is None, "the recording child died on its own"
        assert len(stamps) >= 2 and stamps[-1] - stamps[0] >= 3.0, "no data reached the file within 20 s"
        assert worst_lag < 1.5, f"the readable log lagged the writer by {worst_lag:.2f} s"
        killed_at = time.time()
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()

    records = list(read_log(path))
    assert [r.payload["i"] for r in records] == list(range(len(records)))   # a gapless prefix
    assert killed_at - records[-1].stamp_s < 1.5
    summary = summarise(path)
    assert summary.truncated and "no footer" in summary.stop_reason
    assert summary.message_count == len(records) and summary.end_s == pytest.approx(records[-1].stamp_s)


def several_chunk_log(tmp_path):
    path = tmp_path / "chunks.mcap"
    with Recorder(path) as recorder:
        for i in range(60):
            recorder.write(robot_topic(i % 3, "frame"), {"i": i}, T0 + i / 10)
            if i % 10 == 9:
                recorder.flush()   # one chunk per ten messages
    return path, [r.payload["i"] for r in read_log(path)]


def test_a_log_cut_anywhere_reads_as_a_prefix(tmp_path):
    path, everything = several_chunk_log(tmp_path)
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    recovered_counts = set()
    for cut in range(8, len(data), 23):
        cut_path.write_bytes(data[:cut])
        got = [r.payload["i"] for r in read_log(cut_path)]
        assert got == everything[:len(got)], f"cut at {cut}"
        summary = summarise(cut_path)
        assert summary.truncated and summary.message_count == len(got), f"cut at {cut}"
        assert summary.readable_bytes <= cut
        recovered_counts.add(len(got))
    assert {0, 10, 30, 60} <= recovered_counts   # whole chunks come back, and all of them once the data ends


@pytest.mark.parametrize("cut", range(1, 8))
def test_a_log_cut_inside_its_magic_bytes_reads_as_truncated_not_as_another_format(tmp_path, cut):
    """A log cut in its first 8 bytes was 'not an MCAP file', while one cut at byte 30 was TRUNCATED."""
    path = write_log(tmp_path / "whole.mcap", every_topic_records())
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(path.read_bytes()[:cut])
    assert list(read_log(cut_path)) == []
    summary = summarise(cut_path)
    assert summary.truncated and summary.message_count == 0 and summary.readable_bytes == 0
    assert summary.stop_reason == f"the file ends inside the MCAP magic bytes at byte {cut} (it was cut short " \
                                  "as it began)"
    # A hub's log cut before its metadata is not another tool's: it said "not written by a khepri hub?".
    assert "format:    no khepri.log record in what was recovered\n" in run_khepri(cut_path).stdout
    cut_path.write_bytes(b"\x89MCAP1")             # not a prefix of the magic: another file
    with pytest.raises(LogError, match="not an MCAP file"):
        summarise(cut_path)


def damage(path, offset, count=10):
    data = bytearray(path.read_bytes())
    for k in range(offset, offset + count):
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))


def chunk_starts(path):
    with open(path, "rb") as file:
        return [c.chunk_start_offset for c in make_reader(file).get_summary().chunk_indexes]


def test_a_damaged_chunk_is_skipped_and_said_and_the_rest_is_read(tmp_path):
    """A bit flipped on disk cost every record after it: a replay stopped there, silently."""
    path, everything = several_chunk_log(tmp_path)
    damage(path, chunk_starts(path)[1] + 80)    # inside the compressed records: the chunk's CRC no longer matches
    got = [r.payload["i"] for r in read_log(path)]
    assert got == everything[:10] + everything[20:]
    checked = summarise(path, use_index=False)
    assert not checked.truncated and checked.message_count == 50
    assert len(checked.damaged_records) == 1 and checked.damaged_records[0].startswith("chunk at byte")
    assert summarise(path).message_count == 60      # the index counts what was written (log info --check reads all)


def test_a_damaged_record_length_is_walked_past_with_the_index(tmp_path):
    path, everything = several_chunk_log(tmp_path)
    starts = chunk_starts(path)
    damage(path, starts[2] + 1, 8)              # the chunk's length field: it now runs past the end of the file
    got = [r.payload["i"] for r in read_log(path)]
    assert got == everything[:20] + everything[30:]
    checked = summarise(path, use_index=False)
    assert checked.message_count == 50 and checked.damaged_records == [f"bytes {starts[2]}-{starts[3]} (a record's "
                                                                       "length or opcode is damaged)"]


def test_a_damaged_summary_is_not_trusted(tmp_path):
    """One flipped bit in the statistics record made log info print half a million messages, as complete."""
    path, _ = several_chunk_log(tmp_path)
    data = path.read_bytes()
    footer = len(data) - 8 - 29                 # magic 8 bytes; footer record: opcode, length, 2 offsets, CRC
    summary_start = int.from_bytes(data[footer + 9:footer + 17], "little")
    statistics = data.index(bytes([0x0B]), summary_start)      # the statistics record: opcode 0x0B
    # The first channel's message count: after message_count, the schema, channel, attachment, metadata and
    # chunk counts, the start and end times, the map's length and the channel id: 8+2+4+4+4+4+8+8+4+2 bytes.
    damage(path, statistics + 9 + 48 + 2, 1)    # its third byte: +/- 0xFF0000 messages
    summary = summarise(path)
    assert summary.message_count == 60 and summary.topic_counts == summarise(path, use_index=False).topic_counts


def test_log_info_on_a_damaged_drops_chunk_says_so_instead_of_a_traceback(tmp_path):
    """log info reads the drops from the index's chunks: a damaged one raised zstd's error, uncaught."""
    path = tmp_path / "drops.mcap"
    with Recorder(path) as recorder:
        recorder.write("/hub/status", {"i": 0}, T0)
        recorder.flush()
        for k in range(50):
            recorder.count_drop("bad message", f"peer {k}", T0 + 1)
        recorder.write("/hub/status", {"i": 1}, T0 + 1)
        recorder.flush()
        recorder.write("/hub/status", {"i": 2}, T0 + 2)
    damage(path, chunk_starts(path)[1] + 80)
    result = run_khepri(path)
    assert result.returncode == 0 and result.stderr == ""
    assert "status:    complete; DAMAGED, skipped 1: chunk at byte" in result.stdout
    assert "/hub/status" in result.stdout and "Traceback" not in result.stdout
    checked = run_khepri(path, "--check")          # a script can tell from the exit code (it was 0)
    assert checked.returncode == 1 and "DAMAGED, skipped 1" in checked.stdout
    sound = tmp_path / "sound.mcap"
    with Recorder(sound) as recorder:
        recorder.write("/hub/status", {"i": 0}, T0)
    assert run_khepri(sound, "--check").returncode == 0


def test_log_info_takes_several_files_and_goes_on_past_one_it_cannot_read(tmp_path):
    """`khepri log info logs/*.mcap` was refused (`unrecognized arguments`)."""
    first = write_log(tmp_path / "a.mcap", every_topic_records(), metadata={"lab": "A"})
    second = write_log(tmp_path / "b.mcap", every_topic_records(), metadata={"lab": "B"})
    (tmp_path / "empty.mcap").write_bytes(b"")
    said = run_khepri(first, tmp_path / "empty.mcap", second)
    assert said.returncode == 2 and said.stdout.count("status:    complete") == 2
    assert said.stdout.index('lab = "A"') < said.stdout.index('lab = "B"')
    assert said.stderr.strip() == f"khepri: error: {tmp_path / 'empty.mcap'}: empty file (0 bytes): not even the " \
        "MCAP magic bytes a hub writes as it opens a log"
    both = json.loads(run_khepri(first, second, "--json").stdout)
    assert [summary["metadata"] for summary in both] == [{"lab": "A"}, {"lab": "B"}]
    assert run_khepri(first, second, "--check").returncode == 0


def test_a_damaged_metadata_record_costs_only_itself(tmp_path):
    """Read from the index, one damaged metadata record lost them all: the khepri.log record with them, so a hub's
    log was said to be no hub's (and the damage was not placed). The records are walked instead."""
    path = write_log(tmp_path / "meta.mcap", every_topic_records(), metadata={"lab": "L1"})
    data = path.read_bytes()
    damage(path, data.index(b"L1"), 2)          # the user metadata's value: no longer UTF-8
    summary = summarise(path)
    assert summary.format_version == 1 and summary.message_count == summarise(path, use_index=False).message_count
    assert len(summary.damaged_records) == 1 and summary.damaged_records[0].startswith("metadata record at byte ")


@pytest.mark.parametrize("content, problem", [(b"", r"empty file \(0 bytes\): not even the MCAP magic bytes"),
                                              (b"this is not a log\n" * 20, "not an MCAP"), (None, "no such file")])
def test_unreadable_files_give_one_clear_error(tmp_path, content, problem):
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(LogError, match=problem) as caught:
        summarise(path)
    assert str(path) in str(caught.value)
    with pytest.raises(LogError, match=problem):
        read_log(path)   # raised at the call, before iteration


def run_khepri(*args):
    return subprocess.run([*KHEPRI, "log", "info", *map(str, args)], capture_output=True, text=True, timeout=60,
                          env=ENV)


def foreign_log(path, channels, metadata=None):
    """An MCAP file another tool wrote, with the mcap library: ``{topic: (message encoding, schema encoding,
    [message bytes])}``, one message of each channel after another; ``metadata`` as the hub's metadata record
    (its values JSON text)."""
    from mcap.writer import Writer

    from hub.log_format import USER_METADATA

    with open(path, "wb") as file:
        writer = Writer(file)
        writer.start(profile="ros2", library="another-tool")
        ids = {}
        for topic, (encoding, schema_encoding, _) in channels.items():
            schema_data = b"{}" if encoding == "json" else b"\x0a\x00"
            schema = writer.register_schema(f"{topic}.Type", schema_encoding, schema_data)
            ids[topic] = writer.register_channel(topic, encoding, schema)
        sequence = 0
        for k in range(max(len(messages) for _, _, messages in channels.values())):
            for topic, (_, _, messages) in channels.items():
                if k < len(messages):
                    stamp = int((T0 + 0.01 * sequence) * 1e9)
                    writer.add_message(ids[topic], log_time=stamp, data=messages[k], publish_time=stamp,
                                       sequence=sequence)
                    sequence += 1
        if metadata is not None:
            writer.add_metadata(USER_METADATA, metadata)
        writer.finish()
    return path


def test_a_foreign_channel_is_skipped_by_read_log_and_listed_by_log_info(tmp_path):
    """read_log raised `/camera: message 0 is not a JSON object` on a file with another tool's protobuf channel,
    which `log info --check` called sound (exit 0). Now read_log skips such channels, saying so once each, and
    log info counts what read_log yields and lists the foreign channels apart."""
    poses = [json.dumps({"bodies": {"1": [0.1 * k, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}}).encode() for k in range(3)]
    path = foreign_log(tmp_path / "merged.mcap", {
        MOCAP_POSES: ("json", "jsonschema", poses),
        "/camera": ("protobuf", "protobuf", [b"\x08\x96\x01"] * 4),
        "/tf": ("ros2msg", "ros2msg", [b"\x00\x01\x00\x00"] * 2)})
    with pytest.warns(ForeignChannelWarning) as said:
        records = list(read_log(path))
    assert [r.payload for r in records] == [json.loads(p) for p in poses]
    assert sorted(str(w.message) for w in said) == [       # once per channel, not once per message
        f"{path}: /camera: message encoding 'protobuf', not JSON: its messages are skipped (a channel another tool "
        "wrote; `khepri log info` lists such channels)",
        f"{path}: /tf: message encoding 'ros2msg', not JSON: its messages are skipped (a channel another tool "
        "wrote; `khepri log info` lists such channels)"]
    foreign = {"/camera": {"encoding": "protobuf", "messages": 4}, "/tf": {"encoding": "ros2msg", "messages": 2}}
    for summary in (summarise(path), summarise(path, use_index=False)):
        assert summary.topic_counts == {MOCAP_POSES: 3} and summary.message_count == len(records)
        assert summary.foreign_topics == foreign and summary.damaged_records == []
    checked = run_khepri(path, "--check")
    assert checked.returncode == 0 and checked.stderr == ""
    assert "foreign:   2 channel(s) not JSON, skipped by read_log and the replay:" in checked.stdout
    assert "/camera           4  (protobuf)" in checked.stdout and "messages:  3\n" in checked.stdout
    assert json.loads(run_khepri(path, "--json").stdout)["foreign_topics"] == foreign


def test_a_log_of_only_foreign_channels_reads_as_empty_not_as_an_error(tmp_path):
    path = foreign_log(tmp_path / "ros.mcap", {"/scan": ("ros2msg", "ros2msg", [b"\x00\x01\x00\x00"] * 3)})
    with pytest.warns(ForeignChannelWarning, match="/scan: message encoding 'ros2msg'"):
        assert list(read_log(path)) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert list(read_log(path, topics=[MOCAP_POSES])) == []     # a channel not asked for is not said
    info = run_khepri(path, "--check")
    assert info.returncode == 0 and info.stderr == ""
    assert "messages:  0\nforeign:   1 channel(s) not JSON" in info.stdout and "/scan  " in info.stdout


def test_log_info_check_finds_the_json_messages_read_log_refuses(tmp_path):
    """A JSON channel with messages that are not JSON objects (another tool's arrays, numbers): read_log stops at
    the first with a LogError, while `log info --check` called the file sound (exit 0)."""
    path = foreign_log(tmp_path / "arrays.mcap", {MOCAP_POSES: ("json", "jsonschema", [b'{"bodies": {}}'] * 2),
                                                  "/foo": ("json", "jsonschema", [b"[1, 2]", b"7", b'{"a": 1}'])})
    with pytest.raises(LogError, match="/foo: message 1 is not a JSON object"):
        list(read_log(path))
    checked = run_khepri(path, "--check")
    assert checked.returncode == 1 and checked.stderr == ""
    assert ("status:    complete; read_log STOPS with an error at /foo: message 1 is not a JSON object, and 1 more "
            "on that topic\n") in checked.stdout
    summary = summarise(path, check_payloads=True)
    assert summary.refused_messages == ["/foo: message 1 is not a JSON object, and 1 more on that topic"]
    assert summarise(path).refused_messages == []              # not decoded without --check: nothing said
    sound = write_log(tmp_path / "sound.mcap", every_topic_records())
    assert run_khepri(sound, "--check").returncode == 0


DEEP_JSON = b"[" * 100_000 + b"]" * 100_000     # valid JSON, but past Python's recursion limit: RecursionError


def test_json_nested_past_pythons_recursion_limit_is_unreadable_json_not_a_traceback(tmp_path):
    """json.loads raises RecursionError, not ValueError, for it: `log info` (a last pose record's clock, a drops
    record, the metadata) and `--check` ended in a traceback, and read_log raised it instead of a LogError."""
    poses = [json.dumps({"bodies": {"1": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, "clock_s": 0.5}).encode()] * 2
    path = foreign_log(tmp_path / "deep.mcap", {MOCAP_POSES: ("json", "jsonschema", poses + [DEEP_JSON]),
                                                HUB_DROPS: ("json", "jsonschema", [DEEP_JSON])},
                       metadata={"lab": '"L1"', "deep": DEEP_JSON.decode()})
    with pytest.raises(LogError, match="/hub/drops: message 1 is not a JSON object"):
        list(read_log(path))
    summary = summarise(path)
    assert summary.metadata == {"lab": "L1", "deep": DEEP_JSON.decode()}   # kept as the text, as any non-JSON
    assert (summary.sim_start_s, summary.sim_end_s, summary.drops) == (None, None, {})
    assert summarise(path, check_payloads=True).refused_messages == [
        "/hub/drops: message 1 is not a JSON object", "/mocap/poses: message 3 is not a JSON object"]
    for options in ([], ["--json"], ["--check"]):
        info = run_khepri(path, *options)
        assert info.returncode == (1 if options == ["--check"] else 0) and info.stderr == "", info.stderr[-300:]
    assert "status:    complete; read_log STOPS with an error at /hub/drops: message 1 is not a JSON object ..." \
        in info.stdout


def nested_list(depth):
    """A list ``depth`` levels deep, built without recursion."""
    value = []
    for _ in range(depth - 1):
        value = [value]
    return value


def test_log_info_json_prints_metadata_nested_hundreds_deep_in_full(tmp_path):
    """A metadata value 600 lists deep (valid JSON, which the reader parses) ended `log info --json` in a
    RecursionError traceback: LogSummary.to_dict used dataclasses.asdict, which copies every value recursively,
    two frames per level. Now the summary is printed whole, that value included."""
    deep = {"a": nested_list(600)}
    path = write_log(tmp_path / "deep.mcap", every_topic_records(), metadata={"lab": "L1", "deep": deep})
    summary = summarise(path)
    assert summary.metadata == {"lab": "L1", "deep": deep} and summary.to_dict()["metadata"]["deep"] == deep
    for options in (["--json"], ["--json", "--check"], []):
        info = run_khepri(path, *options)
        assert info.returncode == 0 and info.stderr == "", info.stderr[-300:]
    parsed = json.loads(run_khepri(path, "--json").stdout)
    assert parsed == json.loads(json.dumps(summary.to_dict())) and parsed["metadata"]["deep"] == deep


def test_log_info_json_stays_json_when_another_tools_metadata_holds_nan_or_infinity(tmp_path):
    """Python's json reads NaN, Infinity and 1e999 (as inf) in a metadata value, and printed them back: the
    --json output then held NaN and Infinity, which strict JSON readers refuse. Such a value is kept as text."""
    from mcap.writer import Writer

    path = tmp_path / "other.mcap"
    with open(path, "wb") as file:
        writer = Writer(file)
        writer.start()
        writer.add_metadata("khepri.metadata", {"a": "NaN", "b": "1e400", "c": '{"x": -Infinity}', "d": "2.5"})
        writer.finish()
    assert summarise(path).metadata == {"a": "NaN", "b": "1e400", "c": '{"x": -Infinity}', "d": 2.5}
    info = run_khepri(path, "--json")
    assert info.returncode == 0, info.stderr

    def refuse(name):
        raise AssertionError(f"{name} in log info --json")
    assert json.loads(info.stdout, parse_constant=refuse)["metadata"]["b"] == "1e400"


@pytest.mark.parametrize("as_json", [True, False])
def test_log_info_replaces_a_metadata_value_too_deep_to_print_by_a_note_naming_it(tmp_path, monkeypatch, capsys,
                                                                                 as_json):
    """A value json can parse but not print back (nearly as deep as Python's recursion limit allows; on Python
    3.12 the C encoder's limit is lower than its parser's): one error line naming the field, exit 1, and the
    summary printed with a note in that value's place and everything else kept, not a traceback."""
    import dataclasses

    import hub.log_summary
    from hub.log_text import UNPRINTABLE_NOTE
    from khepri_cli.main import main

    path = write_log(tmp_path / "cli.mcap", every_topic_records(), metadata={"lab": "L1"})
    sound = summarise(path)
    deep = dataclasses.replace(sound, metadata={"lab": "L1", "deep": nested_list(100_000)})
    monkeypatch.setattr(hub.log_summary, "summarise", lambda *args, **kwargs: deep)
    capsys.readouterr()
    assert main(["log", "info", str(path), *(["--json"] if as_json else [])]) == 1
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.startswith("khepri: error: metadata.deep: nested too deeply to print"), err
    if as_json:
        expected = dict(json.loads(json.dumps(sound.to_dict())), metadata={"lab": "L1", "deep": UNPRINTABLE_NOTE})
        assert json.loads(out) == expected
    else:
        assert f'metadata:  lab = "L1"\nmetadata:  deep = "{UNPRINTABLE_NOTE}"' in out and "status:    complete" in out


def test_cli_log_info_prints_the_summary_and_json(tmp_path):
    path = write_log(tmp_path / "cli.mcap", every_topic_records(), metadata={"lab": "L1"})
    text = run_khepri(path)
    assert text.returncode == 0, text.stderr
    assert "status:    complete" in text.stdout and "robots:    2 (1, 2)" in text.stdout
    assert "/robot/*/frame (2 robots)" in text.stdout and "duration:  1.500 s" in text.stdout
    assert "\nformat:    khepri-log 1\n" in text.stdout
    listed = run_khepri(path, "--all-topics")
    assert "/robot/2/command" in listed.stdout

    as_json = run_khepri(path, "--json")
    assert as_json.returncode == 0, as_json.stderr
    parsed = json.loads(as_json.stdout)
    assert parsed == json.loads(json.dumps(summarise(path).to_dict()))
    assert parsed["topic_counts"][MOCAP_POSES] == 1 and parsed["metadata"] == {"lab": "L1"}
    assert parsed["truncated"] is False and parsed["cut_short"] is False     # said true of every good log

    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(path.read_bytes()[:-200])
    cut = run_khepri(truncated)
    assert cut.returncode == 0 and "TRUNCATED, recovered up to" in cut.stdout
    stub = tmp_path / "stub.mcap"                      # the magic and a torn first record: nothing to recover
    stub.write_bytes(path.read_bytes()[:10])
    assert "TRUNCATED, no message recovered (8 of 10 bytes)" in run_khepri(stub).stdout
    # Written to its end (the closing magic is there), then damaged: it was said TRUNCATED, as for a killed hub.
    data = bytearray(path.read_bytes())
    data[-200:-100] = bytes(b ^ 0xFF for b in data[-200:-100])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    said = run_khepri(damaged, "--check")
    assert said.returncode == 1 and "status:    DAMAGED, recovered up to" in said.stdout, said.stdout
    assert "it was written to its end and damaged since, not cut short" in said.stdout
    assert json.loads(run_khepri(damaged, "--json").stdout)["cut_short"] is False
    assert json.loads(run_khepri(truncated, "--json").stdout)["cut_short"] is True


def test_a_log_in_a_newer_format_is_said_by_log_info_and_the_replay(tmp_path):
    """recording.md says readers should check the format version; neither log info's text nor the replay did,
    so a log whose topics might mean other things by now was read as if it were this version's."""
    from hub.replay_source import ReplaySource

    poses = [(MOCAP_POSES, {"bodies": {"0": [0.1 * k, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, "clock_s": None}, T0 + k)
             for k in range(3)]
    path = foreign_log_with_format(tmp_path / "v99.mcap", "99", poses)
    assert ("format:    khepri-log 99, newer than the log format 1 this khepri reads: a topic or field may mean "
            "something else in it") in run_khepri(path).stdout
    said = []
    replay = ReplaySource(str(path), log=said.append)
    assert said == [f"hub: warning: {path} is in log format 99, newer than the log format 1 this khepri reads: a "
                    "topic or field may mean something else in it (read it with the khepri that wrote it)"]
    assert replay.pending is not None       # played all the same
    assert "format:    no khepri.log record (not written by a khepri hub?)" in run_khepri(
        foreign_log_with_format(tmp_path / "none.mcap", None, poses)).stdout


@pytest.mark.parametrize("version", ["\u00b2", "9" * 5000, "-1"])
def test_a_log_version_that_is_no_whole_number_is_said_unreadable(tmp_path, version):
    """`version: "²"` passed str.isdigit and a 5000-digit one int()'s bound: log info and the replay ended in
    ValueError tracebacks."""
    from hub.log_format import format_version
    from hub.replay_source import ReplaySource

    assert format_version({"khepri.log": {"version": version}}) is None
    poses = [(MOCAP_POSES, {"bodies": {"0": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, "clock_s": None}, T0)]
    path = foreign_log_with_format(tmp_path / "odd.mcap", version, poses)
    said = run_khepri(path)
    assert said.returncode == 0 and "Traceback" not in said.stderr
    # The file has a khepri.log record: it was said to have none, "(not written by a khepri hub?)".
    shown = repr(version) if len(version) < 60 else "'" + "9" * 59 + "..."
    assert f"format:    khepri-log of an unreadable version, {shown} (not a whole number)\n" in said.stdout
    assert json.loads(run_khepri(path, "--json").stdout)["format_version_text"] == version
    assert ReplaySource(str(path), log=lambda line: None).pending is not None


def test_a_body_named_with_a_superscript_or_5000_digits_is_no_robot(tmp_path):
    poses = [(MOCAP_POSES, {"bodies": {name: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}, "clock_s": None}, T0 + k)
             for k, name in enumerate(["\u00b2", "9" * 5000, "3"])]
    said = run_khepri(foreign_log_with_format(tmp_path / "odd.mcap", "1", poses))
    assert said.returncode == 0 and "Traceback" not in said.stderr, said.stderr[-500:]


def foreign_log_with_format(path, version, records):
    """A log another writer made: a khepri.log record of ``version`` (None: none), then JSON ``records``."""
    from mcap.writer import Writer

    with open(path, "wb") as file:
        writer = Writer(file)
        writer.start()
        if version is not None:
            writer.add_metadata("khepri.log", {"format": "khepri-log", "version": version})
        channels = {}
        for topic, payload, stamp in records:
            if topic not in channels:
                schema = writer.register_schema(name="x", encoding="jsonschema", data=b"{}")
                channels[topic] = writer.register_channel(topic=topic, message_encoding="json", schema_id=schema)
            writer.add_message(channel_id=channels[topic], log_time=int(stamp * 1e9), publish_time=int(stamp * 1e9),
                               data=json.dumps(payload).encode())
        writer.finish()
    return path


def test_cli_log_info_bad_files_exit_2_with_one_line(tmp_path):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(os.urandom(256))
    for path in (garbage, tmp_path / "missing.mcap"):
        result = run_khepri(path)
        assert result.returncode == 2 and result.stdout == ""
        assert result.stderr.count("\n") == 1 and str(path) in result.stderr and "Traceback" not in result.stderr


def test_topics_are_listed_with_their_robot_numbers_in_order(tmp_path):
    path = tmp_path / "order.mcap"
    with Recorder(path) as recorder:
        for rid in (10, 2, 1):
            recorder.write(robot_topic(rid, "frame"), {"i": rid}, T0 + rid)
    assert list(summarise(path).topic_counts) == ["/robot/1/frame", "/robot/2/frame", "/robot/10/frame"]


def test_a_run_record_that_names_nobody_is_told_without_by_none(tmp_path):
    """Another tool's (or an older hub's) /hub/run records without `by` gave `started 20:00:00 by None`."""
    from hub.log_text import format_summary

    runs = [("/hub/run", {"run_id": "r1", "behaviour": "transport", "event": "started"}, T0),
            ("/hub/run", {"run_id": "r1", "event": "ended", "cause": "stop", "by": ""}, T0 + 5),
            ("/hub/run", {"run_id": "r2", "event": "started", "by": "operator at 10.0.0.2"}, T0 + 6)]
    text = format_summary(summarise(write_log(tmp_path / "runs.mcap", runs)))
    assert "None" not in text and " by ;" not in text and " by :" not in text, text
    assert re.search(r"r1 \(transport\): started \d\d:\d\d:\d\d; stopped \d\d:\d\d:\d\d", text), text
    assert re.search(r"r2 \(\?\): started \d\d:\d\d:\d\d by operator at 10\.0\.0\.2;", text), text


def test_a_huge_or_unnamed_metadata_value_is_shown_short_and_whole_in_json(tmp_path):
    """Another tool's metadata: a 1 MB value printed a 1 MB line, and an empty key printed `metadata:   = 1`."""
    from hub.log_text import format_summary

    path = write_log(tmp_path / "meta.mcap", [(HUB_STATUS, {"frames_per_s": 1.0}, T0)],
                     metadata={"notes": "x" * 1_000_000, "": 1})
    lines = format_summary(summarise(path)).splitlines()
    notes = next(line for line in lines if line.startswith("metadata:  notes = "))
    assert len(notes) < 400 and notes.endswith("... (1,000,002 characters; all of it with --json)")
    assert "metadata:  (empty key) = 1" in lines
    shown = subprocess.run([*KHEPRI, "log", "info", str(path), "--json"], capture_output=True, text=True, env=ENV)
    assert json.loads(shown.stdout)["metadata"]["notes"] == "x" * 1_000_000


def test_bytes_after_a_logs_end_are_said_and_fail_the_check(tmp_path):
    """`cat a.mcap b.mcap > both.mcap` summarised as `complete`, exit 0 under --check: the second log, 500 kB of
    a run, was dropped without a word. In a --json list an unreadable file kept no place, so the next file's
    summary stood where a script expected it."""
    first = write_log(tmp_path / "a.mcap", every_topic_records())
    second = write_log(tmp_path / "b.mcap", every_topic_records())
    joined = tmp_path / "both.mcap"
    joined.write_bytes(first.read_bytes() + second.read_bytes())
    summary = summarise(joined)
    assert not summary.truncated and summary.readable_bytes == first.stat().st_size
    (said,) = summary.damaged_records
    assert said.startswith(f"{second.stat().st_size} bytes after the log's end at byte {first.stat().st_size}")
    assert run_khepri(joined, "--check").returncode == 1
    (tmp_path / "empty.mcap").write_bytes(b"")
    listed = json.loads(run_khepri(first, tmp_path / "empty.mcap", second, "--json").stdout)
    assert [entry["path"] for entry in listed] == [str(first), str(tmp_path / "empty.mcap"), str(second)]
    assert listed[1]["error"].startswith(f"{tmp_path / 'empty.mcap'}: empty file")
