"""CURVE on by default: only listed robot and operator keys get in, and a robot key cannot claim another id."""
import os
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from hub.config import parse_config
from hub.control import ControlError, request
from hub.harness import HubThread, spawn_agent, stop_processes
from hub.keyfiles import add_keys, init_keys, load_keyring, operator_client_keys
from hub.security import HubAuthenticator
from onboard.agent.link import load_robot_keys
from onboard.config import ConfigError
from onboard.protocol import encode


@pytest.fixture
def keys(tmp_path):
    folder = tmp_path / "keys"
    init_keys(folder, [0, 1], ["alice"])
    return folder


@pytest.fixture
def secure_hub(keys, make_scenario):
    scenario = make_scenario(robots={"count": 2}, arena={"walls": [-2.0, -2.0, 2.0, 2.0]})
    config = parse_config({"source": {"type": "sim"}, "security": {"keys": str(keys)},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    with HubThread(config, scenario=scenario, operator_keys=operator_client_keys(keys)) as hub:
        yield hub


def test_ctl_without_keys_at_an_encrypted_hub_is_told_to_give_them_and_where_they_are(secure_hub, keys):
    """ctl's silence had one message with every question; the connection's events now say which."""
    port = secure_hub.endpoints["control"].rsplit(":", 1)[1]
    said = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "estop", "--port", port],
                          capture_output=True, text=True, cwd=keys.parent, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert said.returncode == 1 and "E-STOP NOT DELIVERED" in said.stderr, said.stderr
    # libzmq reports the refused handshake as a mechanism mismatch or with no detail, by timing: both say it.
    assert "give --keys, a folder holding hub.key and operators/<name>.key_secret" in said.stderr, said.stderr
    assert said.stderr.rstrip().endswith("This folder has operator keys in keys/: try again with --keys keys.")
    # The connection got through: the address family (a hub on ::1 only) is not the cause, and is not said.
    assert "::1" not in said.stderr, said.stderr
    assert secure_hub.status()["mode"] != "estop"


def test_ctl_with_its_keys_at_the_robots_port_is_asked_about_the_port(secure_hub, keys):
    """The robots port refuses every operator key, and ctl sent the operator off to check the key folder."""
    port = secure_hub.endpoints["robots"].rsplit(":", 1)[1]
    said = subprocess.run([sys.executable, "-m", "khepri_cli.main", "ctl", "status", "--port", port, "--keys",
                           str(keys), "--timeout", "2"], capture_output=True, text=True, cwd=keys.parent, timeout=60,
                          env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert said.returncode == 1, said.stderr
    assert "the hub refused this operator key: is that the hub's control port, the one it printed after " \
           "`listening control`, and not its robots port (which takes robot keys only)?" in said.stderr, said.stderr


def test_keys_init_makes_private_secrets_and_refuses_to_overwrite(keys):
    secrets = (keys / "hub.key_secret", keys / "robots" / "robot-1.key_secret", keys / "operators" / "alice.key_secret")
    for path in secrets:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert (keys / "robots" / "robot-0.key").read_text().count("secret-key") == 0
    with pytest.raises(ConfigError, match="already exists"):
        init_keys(keys, [0], ["alice"])


@pytest.mark.parametrize("lone", ["hub.key_secret", "robots/robot-1.key_secret", "operators/alice.key_secret",
                                  "operators/alice.key"])
def test_keys_init_refuses_a_lone_key_file_of_its_own_too(tmp_path, keys, lone):
    """init refused an existing hub.key or robot key, but wrote over a hub.key_secret left without its hub.key."""
    folder = tmp_path / "half"
    (folder / lone).parent.mkdir(parents=True, exist_ok=True)
    (folder / lone).write_bytes((keys / lone).read_bytes())
    with pytest.raises(ConfigError) as refused:
        init_keys(folder, [0, 1], ["alice"])
    assert str(refused.value) == f"FOLDER: {folder / lone} already exists (use --force to replace keys)"
    assert (folder / lone).read_bytes() == (keys / lone).read_bytes()
    assert [p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()] == [lone]


def test_keys_init_force_leaves_only_the_new_keys_for_the_hub_to_accept(keys):
    old_robot_1 = (keys / "robots" / "robot-1.key").read_bytes()
    init_keys(keys, [1, 2], ["bob"], force=True)                    # rotate: robot 0 and alice are gone
    ring = load_keyring(keys)
    assert sorted(ring.robots.values()) == [1, 2] and sorted(ring.operators.values()) == ["bob"]
    assert (keys / "robots" / "robot-1.key").read_bytes() != old_robot_1
    assert sorted(p.name for p in (keys / "robots").iterdir()) == [
        "robot-1.key", "robot-1.key_secret", "robot-2.key", "robot-2.key_secret"]


def test_the_hub_refuses_to_start_without_keys_unless_insecure(tmp_path, make_scenario):
    config = parse_config({"source": {"type": "sim"}, "security": {"keys": str(tmp_path / "none")}})
    with pytest.raises(ConfigError, match="keys init"):
        HubThread(config, scenario=make_scenario()).__enter__()


def test_lab_robots_without_a_key_are_said_at_start(keys, make_scenario):
    """Keys made for robots 0 and 1, a lab of three: robot 2 could never connect, and the hub said nothing."""
    config = parse_config({"source": {"type": "sim"}, "security": {"keys": str(keys)},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    scenario = make_scenario(robots={"count": 3}, arena={"walls": [-2.0, -2.0, 2.0, 2.0]})
    with HubThread(config, scenario=scenario) as hub:
        said = [line for line in hub.lines if "no key" in line]
    assert said == [f"hub: robot 2 of this lab has no key in {keys / 'robots'}, so cannot connect (add its key "
                    f"with `khepri keys add {keys} --robots 2,`, which leaves the other keys as they are, or take "
                    f"it off the scenario (or list robots))"]      # robots: not in this config, so not "off robots"


def test_a_hub_without_operator_keys_says_how_to_add_one(tmp_path, make_scenario):
    folder = tmp_path / "keys"
    init_keys(folder, [0, 1], [])
    for secret in (folder / "operators").glob("*"):
        secret.unlink()
    config = parse_config({"source": {"type": "sim"}, "security": {"keys": str(folder)},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    with HubThread(config, scenario=make_scenario(robots={"count": 2}), operator_keys=None) as hub:
        said = [line for line in hub.lines if "operator key" in line]
    assert said == [f"hub: no operator key in {folder / 'operators'}: `khepri ctl` cannot reach this hub (add one "
                    f"with `khepri keys add {folder} --operator NAME`; the hub accepts it without a restart)"], \
        hub.lines


def test_a_hub_started_right_after_another_in_one_process_gets_the_zap_endpoint(keys):
    """ZeroMQ releases a closed socket's inproc endpoint in its own thread: a secure hub started just after
    another one in the same process (the tests do, one after the other) failed with `Address already in use
    (addr='inproc://zeromq.zap.01')` in a fresh-clone run."""
    ring = load_keyring(keys)
    for _ in range(50):
        authenticator = HubAuthenticator(zmq.Context.instance(), ring, log=lambda line: None)
        authenticator.start()
        authenticator.stop()


@pytest.mark.parametrize("kind", ["missing", "file"])
def test_a_key_folder_that_is_missing_or_a_file_is_said_as_such_by_hub_agent_and_ctl(tmp_path, kind):
    """A missing folder read as "missing nokeys/robots/robot-0.key_secret" or "no operator key in
    nokeys/operators"; a file given for it was told to run `khepri keys init <the file>`."""
    folder = tmp_path / "keys"
    if kind == "file":
        folder.write_text("not a folder")
    said = f"{folder} is a file: give the key folder" if kind == "file" else f"no such folder: {folder} (a key"
    for load, field in ((load_keyring, "security.keys"), (operator_client_keys, "--keys"),
                        (lambda path: load_robot_keys(path, 0), "--keys")):
        with pytest.raises(ConfigError) as info:
            load(folder)
        assert info.value.field == field and info.value.problem.startswith(said), info.value


def test_keys_add_gives_new_robots_keys_and_leaves_every_other_key_as_it_was(keys):
    """What the hub's hint for robots without keys says to run. It used to say `keys init --force`, which
    made a new hub key, new keys for the robots that had them, and removed the operators not named again."""
    before = {path: path.read_bytes() for path in keys.rglob("*.key*")}
    add_keys(keys, [2, 3], ["bob"])
    assert all(path.read_bytes() == data for path, data in before.items())
    ring = load_keyring(keys)
    assert sorted(ring.robots.values()) == [0, 1, 2, 3] and sorted(ring.operators.values()) == ["alice", "bob"]
    assert stat.S_IMODE((keys / "robots" / "robot-3.key_secret").stat().st_mode) == 0o600
    with pytest.raises(ConfigError, match=r"robot 1 already has a key .*robot-1\.key"):
        add_keys(keys, [1, 4], [])
    assert not (keys / "robots" / "robot-4.key").exists()       # refused before anything was made
    with pytest.raises(ConfigError, match="keys init"):
        add_keys(keys.parent / "elsewhere", [5], [])


def test_ctl_with_several_operator_keys_lists_them(keys):
    """'several operator keys in keys/operators: name one' left the operator to go and look which."""
    add_keys(keys, [], ["bob"])
    with pytest.raises(ConfigError) as several:
        operator_client_keys(keys)
    assert str(several.value) == f"--operator: several operator keys in {keys / 'operators'}: alice.key_secret, " \
                                 "bob.key_secret; name one, e.g. --operator alice"
    with pytest.raises(ConfigError) as unknown:
        operator_client_keys(keys, "carol")
    assert str(unknown.value).endswith("(it holds alice.key_secret, bob.key_secret)")
    assert operator_client_keys(keys, "bob")["public"] != operator_client_keys(keys, "alice")["public"]


def test_two_key_files_with_the_same_key_are_refused_naming_both(keys):
    """robot-1.key copied to robot-9.key: the later file silently won, so robot 1 was refused as robot 9 and
    the hub said that robot 1 had no key."""
    (keys / "robots" / "robot-9.key").write_bytes((keys / "robots" / "robot-1.key").read_bytes())
    with pytest.raises(ConfigError, match=r"robot-1\.key and .*robot-9\.key hold the same key"):
        load_keyring(keys)


def client(endpoint, keypair=None):
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    if keypair is not None:
        sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = keypair
    sock.connect(endpoint)
    return sock


def hammer(sock, messages, listen_s=0.5):
    """Send, then collect whatever comes back."""
    for message in messages:
        try:
            sock.send(encode(message), zmq.NOBLOCK)
        except zmq.Again:
            pass       # no connection came up (the handshake failed): nothing to send to
    got = []
    deadline = time.monotonic() + listen_s
    while time.monotonic() < deadline:
        if sock.poll(50):
            got.append(sock.recv())
    return got


HELLO_1 = {"type": "hello", "id": 1, "driver": "SimDriver"}
ESTOP = {"type": "request", "cmd": "estop", "nonce": 1}


def test_secret_keys_readable_by_others_are_warned_about_by_hub_agent_and_ctl(keys, make_scenario, tmp_path, capsys):
    """A secret key copied with the wrong mode (a world-readable hub key on a shared lab PC) let anyone pose
    as the hub, and nothing said so; ssh refuses such keys. Private keys (keys init's 0600) get no warning."""
    config = parse_config({"source": {"type": "sim"}, "security": {"keys": str(keys)},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    scenario = make_scenario(robots={"count": 2}, arena={"walls": [-2.0, -2.0, 2.0, 2.0]})
    operator = operator_client_keys(keys)
    assert "warning" not in capsys.readouterr().err
    with HubThread(config, scenario=scenario) as hub:
        assert not [line for line in hub.lines if "can be read by other users" in line]

    for name in ("hub.key_secret", "robots/robot-0.key_secret", "operators/alice.key_secret"):
        (keys / name).chmod(0o644)
    with HubThread(config, scenario=scenario, operator_keys=operator) as hub:
        agent = spawn_agent(hub.endpoints["robots"], 0, tmp_path / "agent.log", keys=keys)
        try:
            hub.wait_until(lambda s: s["robots"][0]["connected"])      # a warning, not a refusal
        finally:
            stop_processes([agent])
        warned = [line for line in hub.lines if "can be read by other users" in line]
    secret = keys / "hub.key_secret"
    assert warned == [f"hub: warning: the secret key {secret} can be read by other users (mode 0644): anyone who "
                      f"reads it can pose as its owner; run `chmod 600 {secret}`"]
    robot_secret = keys / "robots" / "robot-0.key_secret"
    assert (f"agent 0: warning: the secret key {robot_secret} can be read by other users (mode 0644)"
            in (tmp_path / "agent.log").read_text())
    operator_client_keys(keys)
    assert "khepri ctl: warning: the secret key " + str(keys / "operators" / "alice.key_secret") in \
        capsys.readouterr().err


def test_a_listed_robot_key_connects_and_runs(secure_hub, keys, tmp_path):
    agent = spawn_agent(secure_hub.endpoints["robots"], 0, tmp_path / "agent.log", keys=keys)
    try:
        status = secure_hub.wait_until(lambda s: s["robots"][0]["connected"])
        assert status["secure"] is True and not status["robots"][1]["connected"]
    finally:
        assert stop_processes([agent]) == [0]


def test_no_key_and_unlisted_keys_get_nothing_and_command_nothing(secure_hub, keys):
    server = load_robot_keys(keys, 0)["server"]
    stranger = zmq.curve_keypair()
    alice = operator_client_keys(keys)
    intruders = {
        "no key": client(secure_hub.endpoints["robots"]),
        "unlisted key": client(secure_hub.endpoints["robots"], (*stranger, server)),
        "operator key on the robot socket": client(secure_hub.endpoints["robots"],
                                                   (alice["public"], alice["secret"], server)),
    }
    controllers = {
        "no key": client(secure_hub.endpoints["control"]),
        "unlisted key": client(secure_hub.endpoints["control"], (*stranger, server)),
        "robot key on the control socket": client(secure_hub.endpoints["control"],
                                                  tuple(load_robot_keys(keys, 1)[k] for k in ("public", "secret",
                                                                                             "server"))),
    }
    secure_hub.request("start")
    for name, sock in intruders.items():
        assert hammer(sock, [HELLO_1] * 20) == [], name
    for name, sock in controllers.items():
        assert hammer(sock, [ESTOP] * 5) == [], name
    status = secure_hub.status()
    assert status["mode"] == "run", "an unauthenticated client commanded the hub"
    assert not status["robots"][1]["connected"]
    for sock in (*intruders.values(), *controllers.values()):
        sock.close(0)


def test_a_robot_key_cannot_claim_another_robots_id(secure_hub, keys):
    robot0 = load_robot_keys(keys, 0)
    sock = client(secure_hub.endpoints["robots"], (robot0["public"], robot0["secret"], robot0["server"]))
    assert hammer(sock, [HELLO_1] * 3) == []
    status = secure_hub.status()
    assert status["drops"].get("id mismatch", 0) >= 3
    assert not status["robots"][1]["connected"] and not status["robots"][0]["connected"]
    assert any("claimed to be robot 1" in line and "robot:0" in line for line in secure_hub.lines)
    sock.close(0)


def test_ctl_needs_an_operator_key(secure_hub):
    with pytest.raises(ControlError, match="no answer"):
        request(secure_hub.endpoints["control"], "status", keys=None, timeout_s=0.5)


def test_a_refused_key_is_logged_once_with_the_peers_address(secure_hub, keys):
    """A key mix-up shows in the hub's log, naming where it came from, without a line per retry."""
    server = load_robot_keys(keys, 0)["server"]
    alice = operator_client_keys(keys)
    strangers = [client(secure_hub.endpoints["robots"], (*zmq.curve_keypair(), server)),
                 client(secure_hub.endpoints["robots"], (alice["public"], alice["secret"], server)),
                 client(secure_hub.endpoints["control"], (*zmq.curve_keypair(), server))]
    for sock in strangers:
        hammer(sock, [HELLO_1] * 3, listen_s=1.5)       # ZeroMQ retries the handshake meanwhile
    refused = [line for line in secure_hub.lines if "refused" in line]
    assert refused == [f"hub: refused a robot key from 127.0.0.1: not in {keys / 'robots'} (a key made for another "
                       "hub or lab, or for the other socket?)",
                       f"hub: refused an operator key from 127.0.0.1: not in {keys / 'operators'} (a key made for "
                       "another hub or lab, or for the other socket?)"], secure_hub.lines
    for sock in strangers:
        sock.close(0)


def robot_client(hub, keys, rid):
    pair = load_robot_keys(keys, rid)
    return client(hub.endpoints["robots"], (pair["public"], pair["secret"], pair["server"]))


def test_the_hub_follows_its_key_folder_while_it_runs(secure_hub, keys):
    """As sshd follows authorized_keys: a key deleted from the folder is refused from the next connection, and a
    key added is accepted, without restarting the hub (which used to be needed for both)."""
    from hub.key_reload import CHECK_EVERY_S

    (keys / "robots" / "robot-1.key").unlink()
    (keys / "operators" / "alice.key").unlink()
    add_keys(keys, [], ["bob"])
    time.sleep(CHECK_EVERY_S)
    with pytest.raises(ControlError):
        request(secure_hub.endpoints["control"], "status", keys=operator_client_keys(keys, "alice"), timeout_s=1.0)
    bob = operator_client_keys(keys, "bob")
    assert request(secure_hub.endpoints["control"], "status", keys=bob)["status"]["robots"]
    revoked = robot_client(secure_hub, keys, 1)
    assert hammer(revoked, [HELLO_1] * 3, listen_s=1.0) == []
    revoked.close(0)
    assert not request(secure_hub.endpoints["control"], "status", keys=bob)["status"]["robots"][1]["connected"]
    assert f"hub: accepting the keys of operator bob (added to {keys})" in secure_hub.lines
    assert any(line.startswith(f"hub: no longer accepting the keys of robot 1, operator alice (gone from {keys})")
               for line in secure_hub.lines), secure_hub.lines
    add_keys(keys, [1], [])             # robot 1 given a new pair: it connects again
    time.sleep(CHECK_EVERY_S)
    again = robot_client(secure_hub, keys, 1)
    assert hammer(again, [HELLO_1], listen_s=1.0), "robot 1's new key got no frame"
    again.close(0)


def test_a_key_folder_that_cannot_be_read_keeps_the_keys_the_hub_had_and_says_why_once(secure_hub, keys):
    from hub.key_reload import CHECK_EVERY_S

    alice = operator_client_keys(keys, "alice")
    (keys / "operators" / "copy.key").write_bytes((keys / "operators" / "alice.key").read_bytes())
    for _ in range(3):
        time.sleep(CHECK_EVERY_S)
        assert request(secure_hub.endpoints["control"], "status", keys=alice)["status"]["robots"]
    said = [line for line in secure_hub.lines if "the key folder changed" in line]
    copies = f"{keys / 'operators' / 'alice.key'} and {keys / 'operators' / 'copy.key'}"
    assert said == [f"hub: the key folder changed, but cannot be read (security.keys: {copies} hold the same key: "
                    "each robot and operator needs its own pair (delete the copy)): the hub goes on accepting the "
                    "keys it had; it tries again at the next connection"], secure_hub.lines


class Clock:
    """A hand-turned clock for KeyReload: each reading half a minute on, so that every refresh looks."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        self.now += 30.0
        return self.now


def key_reload(keys):
    from hub.key_reload import KeyReload

    lines = []
    ring = load_keyring(keys)
    return ring, KeyReload(ring, lines.append, clock=Clock()), lines


def test_a_stray_key_file_does_not_hold_up_a_revocation(keys):
    """A folder that cannot be read as a whole kept every key it had, a deleted one too, and said so only once."""
    ring, reload, lines = key_reload(keys)
    (keys / "operators" / "notes.key").write_text("not a key")
    reload.refresh()
    assert sorted(ring.robots.values()) == [0, 1] and len(lines) == 1 and "notes.key" in lines[0]
    (keys / "robots" / "robot-1.key").unlink()
    reload.refresh()
    assert sorted(ring.robots.values()) == [0]
    assert lines[1].endswith("the hub goes on accepting the keys it had, but those of robot 1, whose files are "
                             "gone; it tries again at the next connection"), lines
    (keys / "operators" / "notes.key").unlink()
    add_keys(keys, [1], [])
    reload.refresh()
    assert sorted(ring.robots.values()) == [0, 1] and reload.problem is None
    assert lines[2:] == [f"hub: accepting the keys of robot 1 (added to {keys})"], lines


def test_a_key_file_renamed_to_another_robot_is_said_to_speak_for_it(keys):
    ring, reload, lines = key_reload(keys)
    (keys / "robots" / "robot-1.key").rename(keys / "robots" / "robot-5.key")
    reload.refresh()
    assert sorted(ring.robots.values()) == [0, 5]
    assert lines == [f"hub: accepting the keys of robot 5 (the key robot 1 had) (added to {keys})",
                     f"hub: no longer accepting the keys of robot 1 (gone from {keys}); a connection open already "
                     "goes on until it closes (`khepri ctl estop` stops every robot at once)"], lines


def test_a_robot_given_a_new_pair_is_said_once_as_such(keys):
    ring, reload, lines = key_reload(keys)
    old = next(key for key, rid in ring.robots.items() if rid == 0)
    for name in ("robot-0.key", "robot-0.key_secret"):
        (keys / "robots" / name).unlink()
    add_keys(keys, [0], [])
    reload.refresh()
    assert sorted(ring.robots.values()) == [0, 1] and old not in ring.robots
    assert lines == [f"hub: new keys for robot 0 in {keys}: their old keys are refused"], lines


def test_a_key_changed_while_the_hub_started_is_read_at_the_first_connection(keys):
    """The keys are loaded before the hub connects to its motion capture (seconds, at times), and the folder's
    files were first looked at after that: a key added in between was missed until another file changed."""
    ring, reload, lines = key_reload(keys)
    add_keys(keys, [7], [])             # between loading the ring and the first handshake
    reload.refresh()
    assert sorted(ring.robots.values()) == [0, 1, 7], lines


def test_a_robot_key_file_with_the_wrong_name_is_said_so_when_refused(secure_hub, keys):
    (keys / "robots" / "robot_7.key").write_bytes((keys / "robots" / "robot-1.key").read_bytes())
    (keys / "robots" / "robot-1.key").unlink()
    pair = load_robot_keys(keys, 1)
    sock = client(secure_hub.endpoints["robots"], (pair["public"], pair["secret"], pair["server"]))
    hammer(sock, [HELLO_1], listen_s=1.0)
    sock.close(0)
    refused = [line for line in secure_hub.lines if "refused a robot key" in line]
    assert refused and refused[-1].endswith(f"{keys / 'robots' / 'robot_7.key'} holds it, but a robot's key file "
                                            "must be named robot-<id>.key (the name gives the robot's id)"), \
        secure_hub.lines


HANDSHAKE = "to the robot socket in the CURVE handshake: "
UNENCRYPTED = ("it is not encrypted: a robot's agent started without --keys?; nothing was answered (said at most "
               "every 10 s per address)")


def handshake_lines(hub, reason):
    return [line for line in hub.lines if HANDSHAKE in line and reason in line]


def wait_for_line(hub, reason, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not handshake_lines(hub, reason) and time.monotonic() < deadline:
        time.sleep(0.05)
    return handshake_lines(hub, reason)


def test_an_agent_without_keys_is_logged_by_the_hub(secure_hub, tmp_path):
    """ZeroMQ drops it in the CURVE handshake, before any key check or message: the hub's log said nothing, and
    the operator could not tell why the robot never connected. Said once per address and reason."""
    agent = spawn_agent(secure_hub.endpoints["robots"], 0, tmp_path / "agent.log")       # no --keys
    try:
        said = wait_for_line(secure_hub, "not encrypted")
        time.sleep(2.5)                          # the agent reopens its socket after 2 s without a frame, and retries
        assert not secure_hub.status()["robots"][0]["connected"]
    finally:
        stop_processes([agent])
    said = handshake_lines(secure_hub, "not encrypted")
    # From its address (or, on loopback, from a peer that failed before its address was read), then quiet.
    assert 1 <= len(said) <= 2 and all(line.endswith(UNENCRYPTED) for line in said), secure_hub.lines


def test_ctl_without_keys_is_logged_by_the_hub_once_however_often_it_is_run(secure_hub):
    for _ in range(3):
        with pytest.raises(ControlError, match="no answer"):
            request(secure_hub.endpoints["control"], "status", keys=None, timeout_s=0.5)
    deadline = time.monotonic() + 10.0
    while not [line for line in secure_hub.lines if "to the control socket" in line]:
        assert time.monotonic() < deadline, secure_hub.lines
        time.sleep(0.05)
    said = [line for line in secure_hub.lines if "to the control socket" in line]
    assert 1 <= len(said) <= 2, said            # one line (two when the first peer is gone before its address)
    assert "to the control socket in the CURVE handshake: it is not encrypted: an operator's `khepri ctl` without " \
           "--keys?; nothing was answered (said at most every 10 s per address)" in said[0], said


def test_an_unencrypted_peer_is_named_by_its_address_and_gets_no_message(secure_hub):
    """A ZMTP peer offering the NULL mechanism (what an agent without --keys speaks), its greeting sent a moment
    after connecting: the hub names its address, and sends it nothing but its own greeting."""
    host, port = secure_hub.endpoints["robots"].rsplit("/", 1)[1].rsplit(":", 1)
    greeting = b"\xff" + bytes(8) + b"\x7f" + bytes([3, 0]) + b"NULL".ljust(20, b"\0") + bytes(32)
    with socket.create_connection((host, int(port))) as peer:
        time.sleep(0.3)
        peer.sendall(greeting)
        peer.settimeout(5.0)
        got = b""
        while chunk := peer.recv(4096):
            got += chunk
    assert len(got) <= 64 and got[:1] == b"\xff"        # the hub's greeting, then it closed: no message
    assert wait_for_line(secure_hub, "not encrypted") == [
        f"hub: dropped a connection from 127.0.0.1 {HANDSHAKE}{UNENCRYPTED}"], secure_hub.lines


def test_another_hubs_key_is_logged_once_however_often_the_agent_retries(secure_hub, keys):
    """Robot 0's own key pair with a hub.key from another `keys init`: its hello cannot be decrypted."""
    robot0 = load_robot_keys(keys, 0)
    other_hub = zmq.curve_keypair()[0]
    socks = [client(secure_hub.endpoints["robots"], (robot0["public"], robot0["secret"], other_hub))
             for _ in range(5)]
    try:
        for sock in socks:
            assert hammer(sock, [HELLO_1] * 3, listen_s=0.5) == []      # ZeroMQ retries the handshake meanwhile
    finally:
        for sock in socks:
            sock.close(0)
    said = wait_for_line(secure_hub, "cannot be decrypted")
    assert 1 <= len(said) <= 2, secure_hub.lines      # dozens of failed handshakes: one line (two on a race)
    assert f"its hello cannot be decrypted with this hub's key: the agent's --keys holds a hub.key that is not " \
           f"{keys / 'hub.key'}" in said[0]
    assert not secure_hub.status()["robots"][0]["connected"]


CLOSE_WHILE_PEERS_COME_AND_GO = """
import sys, zmq
from hub.security import HandshakeWatch
ctx = zmq.Context.instance()
for _ in range(40):
    sock = ctx.socket(zmq.ROUTER)
    sock.bind("tcp://127.0.0.1:*")
    watch = HandshakeWatch(ctx, sock, "robots", None, log=lambda text: None)
    peers = [ctx.socket(zmq.DEALER) for _ in range(5)]
    for peer in peers:
        peer.linger = 0
        peer.connect(sock.getsockopt_string(zmq.LAST_ENDPOINT))
    for peer in peers:
        peer.close(0)             # their disconnections reach the monitor as it is turned off
    watch.close()
    assert watch.monitor_stopped, "the reader stopped before the monitor did"
    sock.close(0)
print("closed", flush=True)
"""


def test_a_handshake_watch_closes_while_peers_come_and_go():
    """The hub froze for good on its way out: its handshake watch stopped the monitor's reader first, an agent
    disconnected just then, and libzmq's I/O thread waited for ever to hand that event to the reader while
    holding a lock that disable_monitor() then waited for, holding Python's GIL. The monitor is now turned off
    while the reader still reads, and the reader ends on the monitor's own last event."""
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    run = subprocess.run([sys.executable, "-c", CLOSE_WHILE_PEERS_COME_AND_GO], env=env, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0 and run.stdout == "closed\n", run.stderr


def test_a_waiting_agent_names_the_key_mix_up_that_keeps_the_hub_silent(secure_hub, keys, first_waiting_line):
    """The agent asked every question it could (hub running? port? robot in the lab? key listed?) whatever
    the cause; ZeroMQ's handshake events tell which one it is."""
    from onboard.agent.link import HubLink

    endpoint = secure_hub.endpoints["robots"]
    robot0 = load_robot_keys(keys, 0)
    stranger_public, stranger_secret = zmq.curve_keypair()
    said = {
        "no keys": first_waiting_line(HubLink(0, endpoint)),
        "unlisted": first_waiting_line(HubLink(0, endpoint, keys={"public": stranger_public, "secret": stranger_secret,
                                                                  "server": robot0["server"]})),
        "another hub's key": first_waiting_line(HubLink(0, endpoint, keys=dict(robot0, server=stranger_public))),
    }
    assert said["no keys"].endswith("still trying: the hub is encrypted: start the agent with --keys, a folder "
                                    "holding hub.key and robots/robot-0.key_secret"), said
    assert "still trying: the hub refused robot 0's key: does the hub's key folder hold robots/robot-0.key" \
        in said["unlisted"], said
    # libzmq names the cryptographic error, or, now and then, gives no detail in time: then both causes are asked
    another = said["another hub's key"]
    assert "still trying: the hub dropped the encrypted handshake: the hub.key in --keys is not this hub's key" \
        in another or "is the hub.key in --keys this hub's key" in another, said


@pytest.mark.parametrize("event, value, said", [
    (zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL, 0, "the hub dropped the encrypted handshake (no detail given): is the "
                                              "hub.key in --keys this hub's key"),
    (zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL, zmq.PROTOCOL_ERROR_ZMTP_CRYPTOGRAPHIC,
     "the hub dropped the encrypted handshake: the hub.key in --keys is not this hub's key"),
    (zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL, zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH,
     "the hub is not encrypted (it runs --insecure): start the agent without --keys")])
def test_a_keyed_agent_asks_about_an_insecure_hub_too_when_libzmq_gives_no_detail(event, value, said):
    """An agent with --keys at an --insecure hub was told, now and then, that its hub.key was another hub's:
    libzmq had not yet named the mechanism mismatch."""
    from onboard.agent.connection import ConnectionWatch

    context = zmq.Context.instance()
    sock = context.socket(zmq.DEALER)
    watch = ConnectionWatch(context, sock)
    try:
        watch._note(event, value)
        cause = watch.likely_cause(0, "tcp://127.0.0.1:9", keyed=True)
        assert cause.startswith(said), cause
        if event == zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL:
            assert "not --insecure" in cause
    finally:
        watch.close()
        sock.close(0)


def test_a_waiting_agent_whose_hub_stopped_says_the_hub_closed_the_connection(make_scenario, first_waiting_line):
    """An agent connected to a hub that was then killed said `connected to the hub ..., but it sends robot 0
    nothing: is robot 0 in the hub's lab, and is no other agent connected as robot 0?` until its next socket:
    an operator went looking for a second agent."""
    from onboard.agent.link import HubLink

    config = parse_config({"source": {"type": "sim"}, "security": {"insecure": True},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    with HubThread(config, scenario=make_scenario(robots={"count": 2})) as hub:
        endpoint = hub.endpoints["robots"]
        link = HubLink(9, endpoint)
        deadline = time.monotonic() + 5.0
        while not link.watch.handshake_ok and time.monotonic() < deadline:
            link.watch.read()
            time.sleep(0.02)
        assert link.watch.handshake_ok                 # the connection was up while the hub ran
    said = first_waiting_line(link)
    assert f"still trying: the hub at {endpoint} closed the connection" in said and "did the hub stop" in said, said


def test_a_waiting_agent_says_the_hub_is_not_encrypted_or_does_not_know_the_robot(make_scenario, keys,
                                                                                    first_waiting_line):
    from onboard.agent.link import HubLink

    config = parse_config({"source": {"type": "sim"}, "security": {"insecure": True},
                           "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0}})
    with HubThread(config, scenario=make_scenario(robots={"count": 2})) as hub:
        endpoint = hub.endpoints["robots"]
        keyed = first_waiting_line(HubLink(0, endpoint, keys=load_robot_keys(keys, 0)))
        stranger = first_waiting_line(HubLink(9, endpoint))
    assert keyed.endswith("still trying: the hub is not encrypted (it runs --insecure): start the agent without "
                          "--keys"), keyed
    assert f"still trying: connected to the hub at {endpoint}, but it sends robot 9 nothing: is robot 9 in the " \
           "hub's lab, and is no other agent connected as robot 9?" in stranger, stranger


def test_a_hub_key_copied_from_another_folder_is_refused_naming_both_files(keys, tmp_path):
    """The hub started with another folder's hub.key beside its secret; every agent and ctl given that hub.key
    was refused, and each was told its hub.key was not this hub's (it was this folder's own hub.key)."""
    other = tmp_path / "other"
    init_keys(other, [0], ["bob"])
    (keys / "hub.key").write_bytes((other / "hub.key").read_bytes())
    with pytest.raises(ConfigError) as info:
        load_keyring(keys)
    assert info.value.field == "security.keys" and info.value.problem.startswith(
        f"{keys / 'hub.key'} is not the public key of {keys / 'hub.key_secret'} (copied from another key folder?)")


def test_operator_names_that_would_not_come_back_through_ctl_are_refused(tmp_path):
    """`--operator -dash` was made, and ctl's hint `--operator -dash` then failed; `.` made `...key`; a name
    too long for its .key_secret failed half way through `keys init --force`, after the old keys were gone."""
    for name, problem in [("-dash", "must start with a letter, a digit or '_'"), (".", "must start with"),
                          ("q" * 248, "at most 64 characters (got 248)")]:
        with pytest.raises(ConfigError) as info:
            init_keys(tmp_path / "k", [0], [name])
        assert info.value.field == "--operator" and problem in info.value.problem, info.value
        assert not (tmp_path / "k").exists()


def test_a_key_this_user_may_not_read_is_said_so_naming_the_field(keys, monkeypatch):
    """A hub run as a service account on root's 0700 key folder said `Permission denied: k/hub.key_secret` with no
    field, and an unreadable secret was called `not a key file`."""
    import zmq.auth

    def refuse(path):
        raise PermissionError(13, "Permission denied", path)

    monkeypatch.setattr(zmq.auth, "load_certificate", refuse)
    with pytest.raises(ConfigError) as info:
        load_keyring(keys)
    assert info.value.field == "security.keys"
    assert info.value.problem == (f"{keys / 'hub.key_secret'}: this user may not read it (permission denied): run "
                                  "as the user that made the keys, or give this one read access")
    with pytest.raises(ConfigError) as info:
        operator_client_keys(keys)
    assert info.value.field == "--keys" and "alice.key_secret: this user may not read it" in info.value.problem


def test_keys_made_under_an_open_umask_are_not_writable_by_others_and_a_writable_folder_is_warned(tmp_path):
    """Under umask 000 `keys init` made 0777 folders and 0666 public keys: anyone on the lab PC could add or
    swap a key the hub accepts at its next start, and nothing said so."""
    from hub.keyfiles import writable_by_others

    previous = os.umask(0)
    try:
        init_keys(tmp_path / "k", [0, 1], ["alice"])
    finally:
        os.umask(previous)
    folder = tmp_path / "k"
    for path in [folder, folder / "robots", folder / "operators", *folder.rglob("*.key")]:
        assert not stat.S_IMODE(path.stat().st_mode) & 0o022, (path, oct(path.stat().st_mode))
    for path in folder.rglob("*.key_secret"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert writable_by_others(folder) is None
    (folder / "operators").chmod(0o777)
    assert writable_by_others(folder).startswith(f"{folder / 'operators'} can be written by other users (mode "
                                                 "0777): anyone who can write there can add or swap a key")
