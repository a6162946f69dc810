"""`khepri sim run` and `khepri bench` from the command line: outputs land where --out says, and bad options
are refused before any simulated second is spent."""
import json
import math
import os
import signal
import time

import pytest

from khepri_cli.main import PatientInterrupts, main


def test_sim_run_writes_its_outputs_into_out(tmp_path, capsys):
    out = tmp_path / "runs" / "lab6"            # parents are made
    assert main(["sim", "run", "lab-6", "--time-limit", "3", "--no-plot", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["scenario"] == "lab-6" and result["sim_time_s"] == pytest.approx(3.0)
    assert (out / "trajectory.npz").is_file()
    printed = capsys.readouterr().out
    assert "lab-6 seed 1: 6 robots" in printed
    # 3 s is too short to cage: the robots stopped at the time limit, and the evaluator says what is missing,
    # and that the robots were still bidding for the seed's place, not stuck
    assert "  not completed: cage did not close; by its 3 s time limit the robots were still bidding" in printed
    assert result["failures"] == ["cage did not close", "by its 3 s time limit the robots were still bidding for the "
                                  "first place in the cage (params.allocation_time_s, 7 s): give it a longer time "
                                  "limit (time_limit_s, --time-limit)"]



def test_a_run_that_completes_despite_a_fault_is_not_called_not_completed(tmp_path, capsys):
    """The scenario's own faults were listed among the failures, so a delivered box read 'not completed'."""
    scenario = tmp_path / "fault.yaml"
    scenario.write_text("behaviour: transport\nseed: 2\nrobots: {count: 6, spawn: {x: [-1.2, -0.6], y: [-1.2, -0.6]}}\n"
                        "object: {shape: box, size: [0.285, 0.435], mass: 0.3}\n"
                        "path: [[0, 0.3, 0], [0, 0.6, 0], [0, 0.9, 0]]\narena: {walls: [-2, -2, 2, 2]}\n"
                        "time_limit_s: 300\nfaults: [{robot: 4, at_s: 40}]\n")
    assert main(["sim", "run", str(scenario), "--no-plot", "--out", str(tmp_path / "run")]) == 0
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    printed = capsys.readouterr().out
    assert result["completed"] and result["failures"] == [], result["failures"]
    assert result["faults_fired"] == ["robot 4 failed at 40 s"]
    assert "not completed" not in printed and "  faults: robot 4 failed at 40 s" in printed


def test_an_agent_restart_is_simulated_by_sim_run_and_refused_by_sil_by_its_field(tmp_path, capsys):
    scenario = tmp_path / "restart.yaml"
    scenario.write_text("behaviour: aggregate\nrobots: {count: 3}\ntime_limit_s: 2\n"
                        "faults: [{robot: 1, at_s: 0.5, restart_after_s: 0.5}]\n")
    assert main(["sim", "run", str(scenario), "--no-plot", "--out", str(tmp_path / "run")]) == 0
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert result["stop_reason"] == "time limit"
    # SIL's agents are processes of their own: the world cannot restart them, and a run without it would mislead.
    assert main(["sil", str(scenario), "--no-plot", "--no-record", "--out", str(tmp_path / "sil")]) == 2
    assert "khepri: error: faults[0].restart_after_s: agent restarts are simulated by `khepri sim run`" \
        in capsys.readouterr().err


def test_each_waypoint_passed_outside_tolerance_is_named_with_how_far_off():
    from sim_backend.transport_metrics import TransportEvaluator

    waypoints = [{"index": 0, "position_error_m": 0.05, "orientation_error_rad": 0.01,
                  "centroid_estimation_error_m": 0.02},
                 {"index": 1, "position_error_m": 0.30, "orientation_error_rad": 0.2,
                  "centroid_estimation_error_m": 0.29}]
    lines = TransportEvaluator._outside_tolerance(waypoints, 0.1, 0.1)
    assert lines == ["waypoint 2 was passed with the object 0.30 m from it (tolerance 0.10 m) and 11.5° off its "
                     "yaw (tolerance 5.73°); the swarm's centroid estimate was 0.29 m off"]
    assert TransportEvaluator._outside_tolerance(waypoints, 0.1, math.inf)[0].endswith("0.29 m off")
    # With the yaw off, how far the swarm's own yaw estimate was off too: why nobody corrected the turn.
    waypoints[1]["yaw_estimation_error_rad"] = math.radians(10.0)
    assert TransportEvaluator._outside_tolerance(waypoints, 0.1, 0.1)[0].endswith(
        "; the swarm's centroid estimate was 0.29 m off and its yaw estimate 10.0° off")
    assert TransportEvaluator._outside_tolerance(waypoints, 0.1, math.inf)[0].endswith("0.29 m off")


def test_an_error_just_over_its_tolerance_is_printed_with_the_decimals_that_show_it():
    """0.104 m against 0.100 m read "0.10 m from it (tolerance 0.10 m)": as if it were within."""
    from sim_backend.transport_metrics import TransportEvaluator

    waypoints = [{"index": 0, "position_error_m": 0.104, "orientation_error_rad": math.radians(5.74),
                  "centroid_estimation_error_m": None}]
    lines = TransportEvaluator._outside_tolerance(waypoints, 0.1, 0.1)      # 0.1 rad: 5.73°
    assert lines == ["waypoint 1 was passed with the object 0.104 m from it (tolerance 0.100 m) and 5.74° off its "
                     "yaw (tolerance 5.73°)"]


def test_an_out_folder_that_cannot_be_made_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    from sim_backend.runner import Simulation

    def must_not_run(self, *args, **kwargs):
        raise AssertionError("the run started although its outputs could not be written")

    monkeypatch.setattr(Simulation, "run", must_not_run)
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    assert main(["sim", "run", "lab-6", "--out", str(blocker / "run")]) == 2
    assert f"--out: cannot create the folder {blocker / 'run'}" in capsys.readouterr().err


@pytest.mark.parametrize("bench, options, message", [
    ("hub", ["--robots", "0"], "--robots: must be >= 1 (got 0)"),
    ("hub", ["--rate", "0"], "--rate: must be > 0 (got 0)"),
    ("hub", ["--seconds", "-1"], "--seconds: must be > 0 (got -1)"),
    ("sim", ["--seconds", "nan"], "--seconds: must be a finite number of seconds > 0 (got nan)"),
    ("sim", ["--seconds", "inf"], "--seconds: must be a finite number of seconds > 0 (got inf)"),
    ("sim", ["--seconds", "0"], "--seconds: must be a finite number of seconds > 0 (got 0)"),
    ("sim", ["--robots", "5,,6"], "--robots: give positive robot counts, e.g. 25,50,100 (got '5,,6')"),
    ("sim", ["--robots", "3", "--behaviour", "dance"], "--behaviour: unknown behaviour 'dance' (known: "),
    ("sim", ["--robots", "6000"], "--robots: 6000 robots do not fit where paper-100-straight starts its robots"),
])
def test_bench_names_the_bad_option(capsys, bench, options, message):
    assert main(["bench", bench, *options]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("command", [["study", "paper", "--reps", "1", "--scenarios", "irregular-cloud"],
                                     ["sil", "lab-6"]])
def test_study_and_sil_refuse_an_out_folder_they_cannot_make(tmp_path, capsys, command):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    assert main([*command, "--out", str(blocker / "out")]) == 2
    assert f"--out: cannot create the folder {blocker / 'out'}" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["sim", "run", "lab-6"], ["sil", "lab-6"]])
def test_an_out_folder_name_too_long_is_said_as_the_out_folder(tmp_path, capsys, command):
    """A scenario named with 300 letters (its default --out) or a --out that long said `khepri: error: File name
    too long: out/xxx...`, naming no option: Path.exists() raised before mkdir's error was caught."""
    out = tmp_path / ("x" * 300)
    assert main([*command, "--out", str(out)]) == 2
    assert capsys.readouterr().err == f"khepri: error: --out: cannot create the folder {out}: File name too long\n"


def test_sil_refuses_an_out_folder_whose_agents_is_a_file_before_it_starts(tmp_path, capsys):
    """It said `khepri: error: File exists: OUT/agents`, without --out, once the hub had started."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "agents").write_text("not a folder")
    assert main(["sil", "lab-6", "--out", str(out)]) == 2
    assert capsys.readouterr().err == (f"khepri: error: --out: {out / 'agents'} is a file, not a folder "
                                       "(sil writes the agents' logs into it)\n")
    assert not (out / "hub.log").exists()              # refused before the hub began


@pytest.mark.parametrize("command,blocked", [(["sil", "lab-6"], "hub.log"), (["sil", "lab-6"], "hub.mcap"),
                                             (["sim", "run", "lab-6"], "result.json")])
def test_a_folder_where_a_run_writes_a_file_is_refused_before_it_starts(tmp_path, capsys, command, blocked):
    """It said `khepri: error: Is a directory: OUT/hub.log`, without --out (and `sim run` only after the run)."""
    out = tmp_path / "out"
    (out / blocked).mkdir(parents=True)
    assert main([*command, "--out", str(out)]) == 2
    assert capsys.readouterr().err == (f"khepri: error: --out: {out / blocked} is a folder, where the run writes "
                                       f"its {blocked} (move it or choose another --out)\n")


@pytest.mark.parametrize("folder, problem", [
    ("/proc/khepri-keys", "cannot create the folder /proc/khepri-keys: No such file or directory"),
    ("{tmp}/a-file/keys", "cannot create the folder {tmp}/a-file/keys: Not a directory"),
    ("{tmp}/a-file", "{tmp}/a-file is a file, not a folder"),
])
def test_keys_init_names_the_folder_it_cannot_write(tmp_path, capsys, folder, problem):
    """`khepri keys init /proc/x` said `No such file or directory: /proc/x`, naming no argument."""
    (tmp_path / "a-file").write_text("not a folder")
    assert main(["keys", "init", folder.format(tmp=tmp_path)]) == 2
    assert capsys.readouterr().err == f"khepri: error: FOLDER: {problem.format(tmp=tmp_path)}\n"


def test_any_os_error_on_a_path_is_one_line_but_one_without_a_path_keeps_its_traceback(tmp_path, capsys,
                                                                                        monkeypatch):
    """hub --record, a keys folder's subfolder and the like: the file system's refusal, without a traceback."""
    import khepri_cli.keys_commands as lab

    too_long = str(tmp_path / ("k" * 300))

    def fail_on_a_path(args):
        raise OSError(36, "File name too long", too_long)   # a plain OSError, not one of its subclasses

    monkeypatch.setattr(lab, "cmd_keys_init", fail_on_a_path)
    assert main(["keys", "init", str(tmp_path / "keys")]) == 2
    err = capsys.readouterr().err
    assert err == f"khepri: error: File name too long: {too_long}\n"
    monkeypatch.setenv("KHEPRI_DEBUG", "1")           # developers get the traceback back
    with pytest.raises(OSError):
        main(["keys", "init", str(tmp_path / "keys")])
    monkeypatch.delenv("KHEPRI_DEBUG")

    def fail(args):
        raise OSError(5, "Input/output error")        # no path to blame: a bug to report, with its traceback

    monkeypatch.setattr(lab, "cmd_keys_init", fail)
    with pytest.raises(OSError):
        main(["keys", "init", str(tmp_path / "keys")])


def test_a_video_that_cannot_be_written_is_refused_before_the_run(tmp_path, capsys):
    (tmp_path / "a-folder.gif").mkdir()
    out = tmp_path / "run"
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", str(tmp_path / "a-folder.gif")]) == 2
    assert f"--video: {tmp_path / 'a-folder.gif'} is a folder" in capsys.readouterr().err
    assert not (out / "result.json").exists()                 # refused up front: nothing was simulated
    (tmp_path / "videos").mkdir()                             # a folder without a suffix: not "type ''"
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", str(tmp_path / "videos")]) == 2
    assert f"--video: {tmp_path / 'videos'} is a folder; give a file name" in capsys.readouterr().err
    slashed = f"{tmp_path / 'clips' / 'run.gif'}/"        # a folder not made yet: was written as the file run.gif
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", slashed, "--time-limit", "1"]) == 2
    assert f"khepri: error: --video: {slashed} names a folder; give a file name ending in .gif or .mp4" in \
        capsys.readouterr().err
    assert not (tmp_path / "clips").exists() and not (out / "result.json").exists()
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", ""]) == 2   # was " is a folder"
    assert "khepri: error: --video: names no file (got an empty string); give a file name ending in .gif or .mp4" \
        in capsys.readouterr().err
    readonly = "/sys/khepri-run.gif"                           # sysfs: read-only, even for root
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", readonly]) == 2
    assert f"--video: cannot write {readonly}" in capsys.readouterr().err
    good = tmp_path / "ok.gif"
    assert main(["sim", "run", "lab-6", "--no-plot", "--out", str(out), "--video", str(good), "--time-limit", "1"]) == 0
    assert good.stat().st_size > 0


@pytest.mark.parametrize("command", [["sim", "run", "lab-6"], ["study", "paper", "--reps", "1"], ["sil", "lab-6"]])
def test_an_empty_out_is_refused_not_taken_as_the_current_folder(command, capsys):
    with pytest.raises(SystemExit) as stopped:           # argparse: exit code 2 and the usage line
        main([*command, "--out", ""])
    assert stopped.value.code == 2
    assert "argument --out: must name a folder (got an empty string)" in capsys.readouterr().err


def test_a_run_without_a_plot_removes_an_earlier_runs_plot_from_its_folder(tmp_path):
    out = tmp_path / "run"
    assert main(["sim", "run", "lab-6", "--time-limit", "1", "--out", str(out)]) == 0
    assert (out / "trajectory.png").is_file()
    assert main(["sim", "run", "lab-6", "--time-limit", "1", "--no-plot", "--out", str(out)]) == 0
    assert not (out / "trajectory.png").exists()          # it would describe the earlier run, not this one


# --- Ctrl-C ------------------------------------------------------------------------------------------------

def test_a_second_ctrl_c_does_not_cut_the_first_ones_cleanup_short(capsys):
    """The first Ctrl-C stops the command through its finally blocks (runs, workers, agents); a second one,
    pressed while those run, used to raise in the middle of them and print a traceback."""
    cleaned = []
    with PatientInterrupts(exiting=False):
        with pytest.raises(KeyboardInterrupt):
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1.0)                        # the signal is handled before this ends
            finally:
                os.kill(os.getpid(), signal.SIGINT)    # pressed again during the cleanup
                time.sleep(0.05)
                cleaned.append(True)
    assert cleaned == [True]
    assert "khepri: stopping; press Ctrl-C again to quit at once" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler     # the test process gets it back


def test_sim_show_fills_in_the_behaviours_parameters_and_runs_as_the_scenario_does(tmp_path, capsys):
    """'every default filled in' left params: {} for the behaviour's 46 parameters."""
    import numpy as np
    import yaml

    assert main(["sim", "show", "lab-6"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["params"]["inter_robot_distance_m"] == 0.45 and "path" not in shown["params"]
    (tmp_path / "shown.yaml").write_text(yaml.safe_dump(shown))
    for name, scenario in (("shown", str(tmp_path / "shown.yaml")), ("built-in", "lab-6")):
        assert main(["sim", "run", scenario, "--time-limit", "5", "--no-plot", "--out", str(tmp_path / name)]) == 0
    runs = [np.load(tmp_path / name / "trajectory.npz")["robot_pose"] for name in ("shown", "built-in")]
    assert np.array_equal(*runs)


def test_sim_show_of_a_faithful_scenario_loads_again(tmp_path, capsys):
    """The faithful profile sets attach_timeout_s to inf, which show printed as .inf, and the file shown was
    refused: `params.attach_timeout_s: must be a finite number (got inf)`."""
    import yaml

    from onboard.behaviour import build_params, get_behaviour
    from sim_backend.runner import mission_params
    from sim_backend.scenario import load_scenario

    def params(path):
        loaded = load_scenario(str(path))
        return build_params(get_behaviour("transport"), mission_params(get_behaviour("transport"), loaded))

    scenario = tmp_path / "faithful.yaml"
    scenario.write_text("behaviour: transport\nobject: {shape: box, size: [0.3, 0.3]}\npath: [[0, 0.3, 0]]\n"
                        "params: {profile: faithful}\n")
    assert main(["sim", "show", str(scenario)]) == 0
    (tmp_path / "shown.yaml").write_text(capsys.readouterr().out)
    assert params(tmp_path / "shown.yaml") == params(scenario)
    assert "attach_timeout_s" not in yaml.safe_load((tmp_path / "shown.yaml").read_text())["params"]


def test_sim_show_quotes_a_name_that_would_read_back_as_a_number(tmp_path, capsys):
    """`name: '1e3'` was shown bare, as YAML 1.1 would not take it for a number; khepri's loader reads YAML 1.2
    numbers, so the file shown was refused: `name: must be a string (got 1000.0)`."""
    for name in ("1e3", "0o10", "-.5", "0x1F"):
        scenario = tmp_path / "odd.yaml"
        scenario.write_text(f"name: '{name}'\nbehaviour: aggregate\n")
        assert main(["sim", "show", str(scenario)]) == 0
        (tmp_path / "shown.yaml").write_text(capsys.readouterr().out)
        assert main(["sim", "show", str(tmp_path / "shown.yaml")]) == 0, capsys.readouterr().err
        assert f"name: '{name}'" in capsys.readouterr().out


def test_sim_show_warns_as_sim_run_does_before_a_doomed_run(tmp_path, capsys):
    """A scenario could be checked with `sim show` and pass, then `sim run` warned that the box sat too close to
    a wall for the robots to get round it."""
    import yaml

    assert main(["sim", "show", "lab-6"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["arena"]["walls"] == [-2.0, -2.0, 2.0, 2.0]
    shown["object"]["position"] = [0.0, -1.75]              # 0.25 m from the wall at y = -2
    shown["path"] = [[0.0, 0.0, 0.0]]
    (tmp_path / "near-wall.yaml").write_text(yaml.safe_dump(shown))
    assert main(["sim", "show", str(tmp_path / "near-wall.yaml")]) == 0
    captured = capsys.readouterr()
    assert "khepri: warning: object.position: the object starts 0.03 m from an arena wall" in captured.err
    assert yaml.safe_load(captured.out)["object"]["position"] == [0.0, -1.75]     # stdout stays pure YAML


@pytest.mark.parametrize("seed, message", [("abc", "must be a whole number >= 0 (got 'abc')"),
                                           ("1.5", "must be a whole number >= 0 (got '1.5')"),
                                           ("-1", "must be >= 0 (got -1)"),
                                           # 300 digits were "--out: ... File name too long"; 5000 int() refused
                                           ("9" * 300, "must be <= 9223372036854775807 (got an integer of 300 "
                                                       "digits)"),
                                           ("9" * 5000, "must be <= 9223372036854775807 (got an integer of 5000 "
                                                        "digits)"),
                                           (str(2 ** 63), "must be <= 9223372036854775807 (got "
                                                          "9223372036854775808)")])
def test_a_bad_seed_is_named_in_plain_words(capsys, seed, message):
    """One line, as every other bad input (README): argparse's own error printed the whole usage first."""
    for command in (["sim", "run"], ["sil"]):
        assert main([*command, "lab-6", "--seed", seed]) == 2
        assert capsys.readouterr().err.strip() == f"khepri: error: --seed: {message}"


def test_time_limit_on_the_command_line_is_what_the_fault_warning_goes_by(tmp_path, capsys):
    """The scenario says 60 s, --time-limit 75: the fault at 70 s fires, yet `sim run` warned that robot 1
    "never fails", and with --time-limit 50 it said nothing though the fault then never fires."""
    scenario = tmp_path / "late-fault.yaml"
    scenario.write_text("robots: {count: 4}\nobject: {shape: box, size: [0.4, 0.4]}\npath: [[1.0, 0, 0]]\n"
                        "time_limit_s: 60\nfaults: [{robot: 1, at_s: 70}]\n")
    assert main(["sim", "run", str(scenario), "--time-limit", "75", "--no-plot", "--out", str(tmp_path / "a")]) == 0
    said = capsys.readouterr()
    assert "never fails" not in said.err and "robot 1 failed at 70 s" in said.out
    assert main(["sim", "run", str(scenario), "--time-limit", "50", "--no-plot", "--out", str(tmp_path / "b")]) == 0
    assert "70 s is not before the time limit (50 s): robot 1 never fails" in capsys.readouterr().err


def test_plain_khepri_prints_its_commands_and_version_says_the_version(capsys):
    """`khepri` alone said "the following arguments are required: COMMAND"; there was no --version."""
    assert main([]) == 2
    out = capsys.readouterr().out
    assert out.startswith("usage: khepri") and "sim" in out and "study" in out
    with pytest.raises(SystemExit) as exited:
        main(["--version"])
    assert exited.value.code == 0 and capsys.readouterr().out.startswith("khepri 0.")


def test_a_surplus_argument_is_said_with_the_commands_own_usage(capsys):
    """`khepri sim run lab-6 extra` printed the top-level usage (`khepri [-h] [--import MODULE] COMMAND ...`)."""
    with pytest.raises(SystemExit) as exited:
        main(["sim", "run", "lab-6", "extra"])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and err.startswith("usage: khepri sim run ")
    assert err.rstrip().endswith("khepri sim run: error: unrecognized arguments: extra")


def test_a_run_under_a_second_says_its_wall_time_in_digits_that_count():
    """It said `8.0 s simulated in 0.0 s (212.53x real time)`."""
    from khepri_cli.sim_commands import summary_line

    result = {"scenario": "s", "seed": 1, "robots": 7, "sim_time_s": 8.0, "wall_time_s": 0.0376,
              "real_time_factor": 212.53, "stop_reason": "time limit"}
    assert "8.0 s simulated in 0.038 s (212.53x real time)" in summary_line(result)
    assert "in 1.2 s" in summary_line({**result, "wall_time_s": 1.234})


def test_result_json_writes_nan_and_infinity_as_null(tmp_path):
    """A physics blow-up or an evaluator's NaN wrote a bare NaN into result.json, which strict JSON readers
    refuse; sim run, sil and a study write the file with the same function."""
    import numpy as np

    from sim_backend.metrics import result_text
    from sim_backend.study.worker import write_result

    result = {"seed": 1, "stop_reason": "time_limit", "final_position_error_m": float("nan"),
              "waypoints": [{"error": np.float64(np.inf)}], "samples": np.array([1.0, -np.inf])}

    def strict(text):
        return json.loads(text, parse_constant=lambda name: pytest.fail(f"result.json holds {name}"))

    assert strict(result_text(result)) == {"seed": 1, "stop_reason": "time_limit", "final_position_error_m": None,
                                           "waypoints": [{"error": None}], "samples": [1.0, None]}
    assert strict(write_result(result, tmp_path / "run").read_text())["final_position_error_m"] is None
