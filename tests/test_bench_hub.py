"""``khepri bench hub``: its options reach the benchmark, and a short run with agents' telemetry and recording
reports the three figures."""
import json

import pytest

import hub.bench
from khepri_cli.main import build_parser, main
from onboard.config import ConfigError

FIGURES = {"latency_p50_ms": 0.5, "latency_p99_ms": 0.9, "hub_cpu_percent": 7.0, "frames_received": 1200,
           "last_robot_p50_ms": 0.6, "hub_drops": 0, "frames_dropped": 0}


@pytest.fixture
def calls(monkeypatch):
    seen = []

    def fake_bench_hub(robots, rate_hz, seconds, warmup_s=1.0, telemetry_hz=0.0, record=False):
        seen.append({"robots": robots, "rate_hz": rate_hz, "seconds": seconds, "telemetry_hz": telemetry_hz,
                     "record": record})
        return dict(FIGURES)

    monkeypatch.setattr(hub.bench, "bench_hub", fake_bench_hub)
    return seen


def test_telemetry_and_recording_are_off_by_default(calls, capsys):
    assert main(["bench", "hub", "--json"]) == 0
    assert calls == [{"robots": 100, "rate_hz": 120.0, "seconds": 5.0, "telemetry_hz": 0.0, "record": False}]
    assert json.loads(capsys.readouterr().out) == {k: FIGURES[k] for k in
                                                   ("latency_p50_ms", "latency_p99_ms", "hub_cpu_percent")}


def test_telemetry_hz_and_record_reach_the_benchmark(calls, capsys):
    assert main(["bench", "hub", "--robots", "20", "--telemetry-hz", "10", "--record"]) == 0
    assert calls[-1] == {"robots": 20, "rate_hz": 120.0, "seconds": 5.0, "telemetry_hz": 10.0, "record": True}
    out = capsys.readouterr().out
    assert "agents sending telemetry at 10 Hz" in out and "recording to MCAP" in out
    assert main(["bench", "hub", "--record", "--no-record"]) == 0
    assert calls[-1]["record"] is False


@pytest.mark.parametrize("rate", ["-1", "nan", "inf"])
def test_a_bad_telemetry_rate_is_refused(calls, rate):
    args = build_parser().parse_args(["bench", "hub", "--telemetry-hz", rate])
    with pytest.raises(ConfigError, match="--telemetry-hz"):
        args.func(args)
    assert calls == []


def test_the_options_are_in_the_help(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "hub", "--help"])
    help_text = capsys.readouterr().out
    assert "--telemetry-hz" in help_text and "--record" in help_text and "--no-record" in help_text


def test_a_short_run_with_telemetry_and_recording_reports_its_figures():
    result = hub.bench.bench_hub(5, 60.0, 1.0, warmup_s=0.5, telemetry_hz=10.0, record=True)
    assert result["frames_received"] > 0 and result["hub_drops"] == 0
    assert 0 < result["latency_p50_ms"] <= result["latency_p99_ms"]
    assert result["hub_cpu_percent"] > 0


@pytest.mark.parametrize("option, value, problem", [
    ("--rate", "inf", "must be <= 1000 (got inf)"),
    ("--rate", "nan", "must be > 0 (got nan)"),
    ("--rate", "0.01", "must be a whole number of Hz >= 1 (got 0.01)"),    # the mock would run unthrottled
    ("--rate", "1e7", "must be <= 1000 (got 1e+07)"),
    ("--rate", "1.5", "must be a whole number of Hz >= 1 (got 1.5)"),
    ("--robots", "1100", "must be <= 1000 (got 1100)"),     # ZeroMQ runs out of sockets in one process
    ("--seconds", "inf", "must be <= 3600 (got inf)"),
])
def test_bench_options_outside_what_works_are_refused(calls, option, value, problem):
    args = build_parser().parse_args(["bench", "hub", option, value])
    with pytest.raises(ConfigError) as info:
        args.func(args)
    assert (info.value.field, info.value.problem) == (option, problem)
    assert calls == []


def test_a_window_shorter_than_two_mocap_periods_is_refused_rather_than_blamed_on_the_hub(calls):
    """--rate 1 --seconds 0.5 ended in "the hub sent no frames during the benchmark": no pose was due yet."""
    args = build_parser().parse_args(["bench", "hub", "--robots", "2", "--rate", "1", "--seconds", "0.5"])
    with pytest.raises(ConfigError) as info:
        args.func(args)
    assert info.value.field == "--seconds"
    assert info.value.problem.startswith("must be at least 2 s at --rate 1 (got 0.5): 2 motion-capture periods")
    assert calls == []
    assert main(["bench", "hub", "--rate", "120", "--seconds", "0.5", "--json"]) == 0     # 60 periods


def test_a_hub_that_stops_answering_during_the_bench_is_one_line(monkeypatch, capsys):
    from hub.control import ControlError

    def silent_hub(*args, **kwargs):
        raise ControlError("no answer from the hub at tcp://127.0.0.1:5 within 5 s")

    monkeypatch.setattr(hub.bench, "bench_hub", silent_hub)
    assert main(["bench", "hub", "--json"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == "khepri: error: bench hub: no answer from the hub at tcp://127.0.0.1:5 within 5 s\n"


def test_a_killed_bench_cleans_up_its_hub_and_temporary_folder(tmp_path):
    """`kill` (SIGTERM) of `bench hub --record` left /tmp/khepri-bench-hub-* with its log, config and MCAP file
    (Ctrl-C cleaned up); `bench estop` left its agents' logs the same way."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    env = dict(os.environ, TMPDIR=str(tmp_path), PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    bench = subprocess.Popen([sys.executable, "-m", "khepri_cli.main", "bench", "hub", "--robots", "5", "--rate", "50",
                              "--seconds", "60", "--record"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    deadline = time.monotonic() + 30
    # Killed as its hub process starts (it has read its config and said its first line, and is not yet
    # listening): that hub was left running, orphaned.
    def hub_started():
        logs = list(tmp_path.glob("khepri-bench-hub-*/bench.log"))
        return logs and logs[0].stat().st_size > 0

    while not hub_started() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert list(tmp_path.glob("khepri-bench-hub-*")), "the bench never started its hub"
    bench.send_signal(signal.SIGTERM)
    _, err = bench.communicate(timeout=60)
    assert bench.returncode == 130 and "interrupted" in err, err
    assert not list(tmp_path.glob("khepri-bench-hub-*")), list(tmp_path.iterdir())
    # Nor its hub process, killed while the bench waited for it to listen (it was left running, orphaned).
    deadline = time.monotonic() + 10
    while processes_mentioning(str(tmp_path)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not processes_mentioning(str(tmp_path)), processes_mentioning(str(tmp_path))


def processes_mentioning(text: str) -> list:
    """The command lines of this machine's processes that contain ``text`` (from /proc)."""
    from pathlib import Path

    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in words:
            found.append(words)
    return found
