"""What became of the agent's connection to the hub, for the line it prints while no frame arrives.

A silent hub has many causes: nothing listening at the address, a firewall, an encrypted hub and an agent
without keys (or the reverse), a key the hub does not list, another lab's hub key, or a hub that accepts the
connection but does not know this robot. ZeroMQ tells them apart in its socket monitor's events; this reads
them, without a thread, when the agent is about to say it is still waiting, and names the likeliest cause.
"""
from __future__ import annotations

import itertools
from typing import Optional

import zmq
from zmq.utils.monitor import parse_monitor_message

_ADDRESSES = itertools.count()     # inproc names must be unique per context; id() values are reused

EVENTS = (zmq.EVENT_CONNECTED | zmq.EVENT_CONNECT_DELAYED | zmq.EVENT_CONNECT_RETRIED | zmq.EVENT_DISCONNECTED
          | zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
          | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH)
_HANDSHAKE_FAILED = {zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL: "no detail",
                     zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL: "protocol",
                     zmq.EVENT_HANDSHAKE_FAILED_AUTH: "auth"}
# What a silent peer's events point to (ConnectionWatch.kind).
KEY_REFUSED = "key refused"                   # the peer's authenticator refused our CURVE key
MECHANISM_MISMATCH = "mechanism mismatch"     # one side encrypted, the other not
HANDSHAKE_DROPPED = "handshake dropped"       # the handshake failed otherwise (a wrong server key, ...)
CONNECTED_SILENT = "connected, silent"        # the connection is up, and nothing comes over it
CLOSED = "closed"                             # a connection that was up has been closed
CLOSED_AND_REFUSED = "closed, refused"        # ... and nothing accepts a new one
REFUSED = "refused"                           # never connected: refused or unreachable
NO_ANSWER = "no answer"                       # never connected, and no refusal either (a firewall, a wrong host)
MAX_EVENTS_READ = 1000       # per call: a socket retrying every 0.1 s makes a few dozen between two reads


class ConnectionWatch:
    """The monitor of one socket, read on demand. Its reading end takes any number of events (a receive
    high-water mark of 0), so libzmq's I/O thread never blocks on it however seldom it is read."""

    def __init__(self, context: zmq.Context, sock: zmq.Socket) -> None:
        self.sock = sock
        address = f"inproc://agent-connection-{next(_ADDRESSES)}"
        sock.monitor(address, EVENTS)
        try:
            self.events = context.socket(zmq.PAIR)
            self.events.linger = 0
            self.events.rcvhwm = 0
            self.events.connect(address)
        except zmq.ZMQError:
            sock.disable_monitor()       # a monitor with no reader could block libzmq's I/O thread
            raise
        self.connected = False         # TCP got through at least once
        self.refused = False           # since the last connection, an attempt failed (refused, unreachable)
        self.handshake_ok = False      # the connection is up: a ZMTP handshake completed (keys accepted, or none)
        self.dropped = False           # a connection that was up has been closed (the hub stopped, or its PC)
        self.handshake_failed: Optional[str] = None     # the last failure: "protocol", "auth", "no detail"
        self.protocol_error: Optional[int] = None       # its ZMTP error, for "protocol"

    def read(self) -> None:
        """Takes the events waiting, and remembers what they say."""
        for _ in range(MAX_EVENTS_READ):
            try:
                frames = self.events.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                event = parse_monitor_message(frames)
            except Exception:   # noqa: BLE001 - a malformed event must not stop an agent; it is skipped
                continue
            self._note(event["event"], event["value"])

    def _note(self, kind: int, value: int) -> None:
        if kind == zmq.EVENT_CONNECTED:
            self.connected, self.refused = True, False
        elif kind == zmq.EVENT_CONNECT_RETRIED:
            self.refused = True
        elif kind == zmq.EVENT_HANDSHAKE_SUCCEEDED:
            self.handshake_ok, self.handshake_failed, self.dropped = True, None, False
        elif kind == zmq.EVENT_DISCONNECTED:
            # What held before (a handshake that went through) is past: a hub killed after it had connected
            # was said as "connected, but it sends robot 0 nothing" until the agent's next socket.
            self.dropped = self.dropped or self.handshake_ok
            self.handshake_ok = False
        elif kind in _HANDSHAKE_FAILED:
            self.handshake_failed = _HANDSHAKE_FAILED[kind]
            self.protocol_error = value if kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL else None

    def kind(self) -> Optional[str]:
        """The likeliest reason the peer is silent, as one of the constants above (``KEY_REFUSED`` ...
        ``NO_ANSWER``), or None when the events do not tell. The agent and ``khepri ctl`` each say it in their
        own words (their flags and hints differ)."""
        self.read()
        if self.handshake_failed is not None:
            if self.handshake_failed == "auth":
                return KEY_REFUSED
            mismatch = self.protocol_error == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH
            if self.handshake_failed == "protocol" and mismatch:
                return MECHANISM_MISMATCH
            return HANDSHAKE_DROPPED
        if self.handshake_ok:
            return CONNECTED_SILENT
        if self.dropped:
            return CLOSED_AND_REFUSED if self.refused else CLOSED
        if self.refused and not self.connected:
            return REFUSED
        if not self.connected:
            return NO_ANSWER
        return None

    def likely_cause(self, robot_id: int, address: str, keyed: bool) -> Optional[str]:
        """What most likely keeps the hub silent, or None when the events do not tell (then the agent asks
        its general questions)."""
        kind = self.kind()
        if kind in (KEY_REFUSED, MECHANISM_MISMATCH, HANDSHAKE_DROPPED):
            return self._handshake_cause(kind, robot_id, keyed)
        if kind == CONNECTED_SILENT:
            # A key is one robot's: another robot's key file speaks for that robot, and the hub drops the claim.
            questions = [f"is robot {robot_id} in the hub's lab", f"is no other agent connected as robot {robot_id}"]
            if keyed:
                questions.append(f"is robots/robot-{robot_id}.key_secret robot {robot_id}'s own key (not another "
                                 "robot's)")
            asked = ", ".join(questions[:-1]) + ", and " + questions[-1]
            return (f"connected to the hub at {address}, but it sends robot {robot_id} nothing: {asked}? The hub's "
                    "console says which")
        if kind in (CLOSED, CLOSED_AND_REFUSED):
            now = " and nothing accepts a new one (refused or unreachable)" if kind == CLOSED_AND_REFUSED else ""
            return (f"the hub at {address} closed the connection{now}: did the hub stop, or its PC? Start it "
                    "again: this agent reconnects by itself")
        if kind == REFUSED:
            return (f"nothing accepts a connection at {address} (refused or unreachable): is the hub running, "
                    "and are --hub and --port the host and robots port it printed when it started?")
        if kind == NO_ANSWER:
            return (f"no answer at {address} yet: is that the hub PC's address, is it on this network, or does "
                    "a firewall drop the connection?")
        return None

    def _handshake_cause(self, kind: str, robot_id: int, keyed: bool) -> str:
        if kind == KEY_REFUSED:
            return (f"the hub refused robot {robot_id}'s key: does the hub's key folder hold "
                    f"robots/robot-{robot_id}.key, the pair of this robot's key_secret?")
        if kind == MECHANISM_MISMATCH:
            if keyed:
                return "the hub is not encrypted (it runs --insecure): start the agent without --keys"
            return ("the hub is encrypted: start the agent with --keys, a folder holding hub.key and "
                    f"robots/robot-{robot_id}.key_secret")
        if keyed and self.protocol_error is None:
            # libzmq does not always give the reason in time: an --insecure hub was said to hold another key.
            return ("the hub dropped the encrypted handshake (no detail given): is the hub.key in --keys this hub's "
                    "key (not another hub's, or an older `khepri keys init`'s), and does the hub run with keys (not "
                    "--insecure, for which the agent runs without --keys)?")
        if keyed:
            return ("the hub dropped the encrypted handshake: the hub.key in --keys is not this hub's key "
                    "(the keys of another hub, or of an older `khepri keys init`?)")
        return f"the hub dropped the connection in its handshake ({self.detail()})"

    def detail(self) -> str:
        if self.protocol_error is not None:
            return f"ZMTP error {self.protocol_error:#x}"
        return "no detail given"

    def close(self) -> None:
        """Before the socket is closed: the monitor is turned off while its reading end is still there (libzmq
        sends it a last event, which must not find the reader gone), then the reader is closed."""
        try:
            self.sock.disable_monitor()
        except zmq.ZMQError:
            pass
        self.events.close(0)


def watch_connection(context: zmq.Context, sock: zmq.Socket) -> Optional[ConnectionWatch]:
    """A watch on ``sock``, or None where the socket cannot be monitored (a libzmq too old for these events):
    the agent then asks its general questions, as before. Watching is help, never a reason not to run."""
    try:
        return ConnectionWatch(context, sock)
    except zmq.ZMQError:
        return None

