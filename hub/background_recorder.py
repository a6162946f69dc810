"""Recording off the hub's real-time loop: the loop only queues, a writer thread encodes and writes the log."""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any, Callable, Deque, Optional, Set, Tuple

from .log_format import UnrecordableMessage

UNRECORDABLE = "unrecordable message"    # /hub/drops reason of a message the log could not hold (its topic: sender)
# A disk that stalls (a network share, a dying card) holds the writer thread while the loop keeps queuing: about
# 3000 messages a second for 100 robots at 120 Hz, a few kB each. Past this many waiting, new ones are left out
# (counted, said once) rather than fill the lab PC's memory; and closing waits this long for the writer.
MAX_QUEUED = 50_000
CLOSE_WAIT_S = 10.0

if TYPE_CHECKING:      # hub.recording offers this class too, so it cannot be imported from here at run time
    from .recording import Recorder


class BackgroundRecorder:
    """A :class:`Recorder` written by a thread of its own, so that a hub's real-time loop only queues.

    ``write``, ``write_later`` and ``count_drop`` take the stamp (now, unless given) and append to a queue;
    nothing is encoded in the caller's thread. The writer thread encodes and writes everything in call order
    when :meth:`kick` wakes it (the hub kicks once its downlink frames are out) and at least every
    ``idle_s``. An error in the writer (e.g. a full disk) is raised by the next call, as the Recorder itself
    would have; or, with ``on_failure``, handed to that once, after which every call does nothing (a lab
    run goes on without its log rather than end). A message the log cannot hold (not JSON-able) is left out
    and counted under ``/hub/drops`` as ``unrecordable message`` (its topic as the sender), and ``on_skip`` is
    told once per topic: the file is intact, so recording goes on. ``close`` writes what is queued and closes
    the file.

    Why a thread: encoding a 100-robot lab's frames as JSON takes about 1 ms per motion-capture frame. Done
    by the hub's loop thread, that CPU time makes the kernel treat the thread as busy, so every ZeroMQ send
    that wakes ZeroMQ's I/O thread then preempts it: the frames of the next burst went out about four times
    slower (docs/lab.md, "Hub latency").
    """

    def __init__(self, recorder: Recorder, idle_s: float = 0.05,
                 on_failure: Optional[Callable[[BaseException], None]] = None,
                 on_skip: Optional[Callable[[BaseException], None]] = None,
                 on_behind: Optional[Callable[[int], None]] = None,
                 max_queued: int = MAX_QUEUED, close_wait_s: float = CLOSE_WAIT_S):
        self.recorder = recorder
        self.on_behind = on_behind              # told once, with the queue's length, when messages are left out
        self.max_queued, self.close_wait_s = max_queued, close_wait_s
        self.left_out = 0                       # messages not queued: the writer had fallen that far behind
        self.path = recorder.path
        self.on_failure = on_failure
        self.on_skip = on_skip                  # told once per topic of a message left out (from the writer thread)
        self._skipped_topics: Set[str] = set()
        self.failure: Optional[str] = None      # why recording stopped (with on_failure), else None
        self._queue: Deque[Tuple[Any, ...]] = deque()
        self._kick = threading.Event()
        self._idle_s = idle_s
        self._stopping = False
        self._error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._run, name="khepri-recorder-writer", daemon=True)
        self._thread.start()

    def write(self, topic: str, payload: dict, stamp_s: Optional[float] = None) -> None:
        if self._check():
            return
        self._append((topic, payload, None, time.time() if stamp_s is None else stamp_s))

    def write_later(self, topic: str, build: Callable[..., dict], args: Tuple[Any, ...],
                    stamp_s: Optional[float] = None) -> None:
        """Record ``build(*args)``, called in the writer thread: the arguments must not change afterwards."""
        if self._check():
            return
        self._append((topic, build, args, time.time() if stamp_s is None else stamp_s))

    def count_drop(self, reason: str, sender: Optional[str] = None, stamp_s: Optional[float] = None) -> None:
        if self._check():
            return
        self._append((None, reason, sender, time.time() if stamp_s is None else stamp_s))

    def _append(self, item: Tuple[Any, ...]) -> None:
        if len(self._queue) >= self.max_queued:
            self.left_out += 1
            if self.left_out == 1 and self.on_behind is not None:
                self.on_behind(len(self._queue))
            return
        self._queue.append(item)

    def kick(self) -> None:
        """Write what is queued now (from the writer thread)."""
        if self._queue:
            self._kick.set()

    def flush(self) -> None:
        """Write what is queued, then flush the file (waits for the writer thread)."""
        self._drain_wait()
        if not self._check():
            self.recorder.flush()

    def close(self) -> None:
        """Write what is queued, close the file and stop the writer thread. Safe to call twice."""
        self._stopping = True
        self._kick.set()
        if self._thread is not threading.current_thread():
            self._thread.join(self.close_wait_s)
            if self._thread.is_alive():       # a stalled disk: closing the file would wait on it too
                self._stalled()
                return
        try:
            self.recorder.close()
        except Exception as err:
            if self.on_failure is None:
                self._check()             # the writer's own error, if it had one, says more
                raise
            if self.failure is None and self._error is None:
                self._error = err         # reported below, once
        self._check()

    def _stalled(self) -> None:
        error = RuntimeError(f"the log's writer has not finished within {self.close_wait_s:g} s (a stalled disk?): "
                             f"{self.path} may lack its last {len(self._queue)} messages and its end; "
                             "`khepri log info` reads what it holds")
        if self.on_failure is None:
            raise error
        if self.failure is None:
            self.failure = str(error)
            self.on_failure(error)

    def __enter__(self) -> BackgroundRecorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _check(self) -> bool:
        """Raise the writer's error, or with ``on_failure`` report it once; True once recording has failed."""
        if self._error is not None:
            error, self._error = self._error, None
            if self.on_failure is None:
                raise error
            self.failure = str(error)
            self._queue.clear()
            self.on_failure(error)
        return self.failure is not None

    def _skip(self, topic: str, err: UnrecordableMessage, stamp: float) -> None:
        """Count a message the log cannot hold under /hub/drops, and say so once per topic."""
        try:
            self.recorder.count_drop(UNRECORDABLE, topic, stamp)
        except Exception as failure:             # the file itself failed meanwhile
            self._error = failure
            return
        if topic not in self._skipped_topics:
            self._skipped_topics.add(topic)
            if self.on_skip is not None:
                self.on_skip(err)

    def _drain_wait(self) -> None:
        while self._queue and self._thread.is_alive():
            self._kick.set()
            time.sleep(0.001)

    def _run(self) -> None:
        while True:
            self._kick.wait(self._idle_s)
            self._kick.clear()
            stopping = self._stopping
            while self._queue:
                topic, first, second, stamp = self._queue.popleft()
                if self._error is not None or self.failure is not None:
                    continue                      # reported once; the rest cannot be written either
                try:
                    if topic is None:
                        self.recorder.count_drop(first, second, stamp)
                    elif second is None:
                        self.recorder.write(topic, first, stamp)
                    else:
                        self.recorder.write(topic, first(*second), stamp)
                except UnrecordableMessage as err:   # this message only: the log is intact, so recording goes on
                    self._skip(topic, err, stamp)
                except Exception as err:          # handed to the hub's thread by its next call
                    self._error = err
            if stopping:
                return
