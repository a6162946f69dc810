"""Where a study's runs execute: a local process pool or a Dask cluster, behind one small interface.

``executor.results(runs, out_root)`` takes run specs and yields each run's result as it finishes, in
completion order. A run whose worker raised or died comes back as a failed result, never as an exception,
so one bad run cannot stop a study.
"""
from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional

from onboard.config import ConfigError

from .dask_address import check_dask_address, connect_to_scheduler
from .grid import RunSpec
from .text import counted
from .worker import execute_run, failed_result

RunFunction = Callable[[RunSpec, str], Dict[str, Any]]
WORKER_DIED = "the worker process died while running this run (killed, out of memory or a crash in native code)"


@dataclass
class ExecutorChoice:
    kind: str                      # "local" or "dask"
    address: Optional[str] = None  # a Dask scheduler; None = start a LocalCluster


def parse_executor(text: str) -> ExecutorChoice:
    """``local``, ``dask`` (a LocalCluster on this machine) or ``dask:ADDRESS`` (an existing scheduler)."""
    kind, separator, address = text.partition(":")
    if kind == "local" and not address:
        return ExecutorChoice("local")
    if kind == "dask":
        if separator and not address.strip():
            raise ConfigError("--executor", "dask: needs a scheduler address, e.g. dask:tcp://10.0.0.5:8786")
        if address.strip():
            check_dask_address(address.strip())
        return ExecutorChoice("dask", address.strip() or None)
    raise ConfigError("--executor", f"must be local, dask or dask:ADDRESS (got {text!r})")


def default_workers() -> int:
    return os.cpu_count() or 1


def worker_count(workers: Optional[int] = None) -> int:
    """``--workers``, or the number of cores when not given; ConfigError below 1."""
    workers = default_workers() if workers is None else workers
    if workers < 1:
        raise ConfigError("--workers", f"must be >= 1 (got {workers})")
    return workers


def make_executor(choice: ExecutorChoice, workers: Optional[int] = None, run_function: RunFunction = execute_run):
    workers = worker_count(workers)
    if choice.kind == "dask":
        return DaskExecutor(choice.address, workers, run_function)
    return LocalExecutor(workers, run_function)


class LocalExecutor:
    """A process pool over this machine's cores (fresh interpreters: 'spawn', safe next to threads)."""

    def __init__(self, workers: int, run_function: RunFunction = execute_run):
        self.workers = workers
        self.run_function = run_function
        self.context = multiprocessing.get_context("spawn")

    def describe(self) -> str:
        return f"local process pool, {counted(self.workers, 'worker')}"

    def prepare(self) -> None:
        """Nothing to reach before the study starts."""

    def results(self, runs: Iterable[RunSpec], out_root: str) -> Iterator[Dict[str, Any]]:
        queue = deque(runs)
        pool = self._new_pool()
        in_flight: Dict[Future, RunSpec] = {}
        completed = False
        try:
            while queue or in_flight:
                # Only as many runs in flight as workers: if the pool breaks, the suspects are few.
                while queue and len(in_flight) < self.workers:
                    spec = queue[0]
                    try:
                        future = pool.submit(self.run_function, spec, out_root)
                    except BrokenProcessPool:
                        # A worker died between two completions: its future is failing in flight; the
                        # run not yet submitted waits for the next pool.
                        if not in_flight:
                            pool = self._replace(pool)
                            continue
                        break
                    queue.popleft()
                    in_flight[future] = spec
                done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
                suspects = []
                for future in done:
                    spec = in_flight.pop(future)
                    outcome = self._outcome(future, spec)
                    if outcome is None:
                        suspects.append(spec)
                    else:
                        yield outcome
                if suspects:
                    # A worker died and took the pool down: every run still in flight is a suspect too.
                    suspects += in_flight.values()
                    in_flight.clear()
                    pool.shutdown(wait=True, cancel_futures=True)
                    yield from self._isolate(suspects, out_root)
                    pool = self._new_pool()
            completed = True
        finally:
            if completed:
                pool.shutdown(wait=True)
            else:
                stop_workers(pool)

    def _new_pool(self, workers: Optional[int] = None) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(workers or self.workers, mp_context=self.context,
                                   initializer=exit_with_parent, initargs=(os.getpid(),))

    def _replace(self, pool: ProcessPoolExecutor) -> ProcessPoolExecutor:
        pool.shutdown(wait=True, cancel_futures=True)
        return self._new_pool()

    def _outcome(self, future: Future, spec: RunSpec) -> Optional[Dict[str, Any]]:
        """The run's result; a failed result if it raised; None if the pool broke under it."""
        try:
            return future.result()
        except BrokenProcessPool:
            return None
        except Exception as exc:
            return failed_result(spec, f"{type(exc).__name__}: {exc}")

    def _isolate(self, suspects: List[RunSpec], out_root: str) -> Iterator[Dict[str, Any]]:
        """Run each suspect alone in its own one-worker pool: the one that kills its worker again is
        recorded as failed, the innocent ones that shared the broken pool simply complete."""
        for spec in suspects:
            with self._new_pool(1) as solo:
                outcome = self._outcome(solo.submit(self.run_function, spec, out_root), spec)
            yield outcome if outcome is not None else failed_result(spec, WORKER_DIED)


def exit_with_parent(parent_pid: int, period_s: float = 0.5) -> None:
    """Pool worker initializer: the worker ends when the driver is gone. A driver killed outright (SIGKILL, the
    out-of-memory killer) cannot stop its workers, and a pool's worker never sees its queue close (it holds
    both ends of it): it finished its run and then waited, orphaned, for ever. Its run is run again on
    resume, as after Ctrl-C."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(period_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """Interrupted (Ctrl-C): end the runs in flight now rather than wait minutes for them. They left no
    result.json, so a resume runs them again."""
    terminate = getattr(pool, "terminate_workers", None)   # public from Python 3.14
    if terminate is not None:
        terminate()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def dask_setup(worker: Any) -> None:
    """Run by each worker process of our LocalCluster as it starts (this module is its Dask ``preload``).

    Ctrl-C in a terminal reaches every process of the foreground group, so the LocalCluster's workers too: each
    printed a traceback of its event loop's KeyboardInterrupt beside the driver's one line. The driver stops
    them (closing the cluster) and keeps the results so far; they need not hear the Ctrl-C themselves."""
    if threading.current_thread() is threading.main_thread():      # signal.signal works only there
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A worker whose heartbeat fell between the scheduler closing and its own close logged an ERROR with two
    # tracebacks: seen after Ctrl-C, and possible at any end of a study. Losing the scheduler mid-study is
    # said by the driver (_check_connected), so this line only ever repeats what the driver knows.
    logging.getLogger("distributed.worker").addFilter(_not_a_heartbeat_to_a_closed_scheduler)


def _not_a_heartbeat_to_a_closed_scheduler(record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith("Failed to communicate with scheduler during heartbeat")


def _not_the_clients_own_word_on_a_lost_scheduler(record: logging.LogRecord) -> bool:
    """The client, having lost its scheduler, logged "Failed to reconnect to scheduler after 30.00 seconds" and
    then two tracebacks of CancelledError from its own close. The driver says it in one line that names the
    scheduler and how to resume (DaskExecutor._check_connected)."""
    if record.getMessage().startswith("Failed to reconnect to scheduler"):
        return False
    return not (record.exc_info and isinstance(record.exc_info[1], asyncio.CancelledError))


class DaskExecutor:
    """Dask distributed: a LocalCluster of ``workers`` single-threaded processes, or an existing scheduler.

    Workers of an existing scheduler need khepri installed (the same version) in their environment.
    """

    def __init__(self, address: Optional[str], workers: int, run_function: RunFunction = execute_run):
        self.address = address
        self.workers = workers
        self.run_function = run_function
        self.client = None          # connected by prepare(), before the study writes anything

    def describe(self) -> str:
        if self.address:
            return f"Dask scheduler at {self.address}"
        return f"Dask LocalCluster, {counted(self.workers, 'worker')}"

    def prepare(self) -> None:
        """Reach the scheduler now: an address that cannot be used is an error before the study folder is
        made or its command recorded."""
        if self.address is not None and self.client is None:
            self.client = connect_to_scheduler(self.address)   # a ConfigError naming the address

    def results(self, runs: Iterable[RunSpec], out_root: str) -> Iterator[Dict[str, Any]]:
        from distributed import as_completed

        client, cluster = self._start()
        futures: Dict[Any, RunSpec] = {}
        client_log = logging.getLogger("distributed.client")
        client_log.addFilter(_not_the_clients_own_word_on_a_lost_scheduler)
        try:
            futures = {self._submit(client, spec, out_root): spec for spec in runs}
            suspects = []
            for future in as_completed(futures):
                self._check_connected(client, future)
                if self._ran_to_an_end(future):
                    yield self._outcome(future, futures[future])
                else:
                    suspects.append(futures[future])
            yield from self._isolate(client, suspects, out_root)
        finally:
            for future in futures:
                future.cancel()
            client.close()
            client_log.removeFilter(_not_the_clients_own_word_on_a_lost_scheduler)
            if cluster is not None:
                cluster.close()

    def _start(self):
        """The client, and the LocalCluster it talks to (None with a scheduler's address)."""
        from distributed import Client, LocalCluster

        if self.address is not None:
            self.prepare()
            client, self.client = self.client, None
            return client, None
        # One thread per worker: the simulator is pure Python, threads would only contend for the GIL.
        # The preload makes its workers ignore Ctrl-C (see dask_setup). Without a dashboard the scheduler still
        # serves a few HTTP routes, on port 8787 unless told otherwise: beside a Dask scheduler or another study
        # that port is taken, and Dask printed "UserWarning: Port 8787 is already in use. Perhaps you already have
        # a cluster running?" in the middle of the study. Any free loopback port will do.
        cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR, preload=[__name__],
                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
        try:
            return Client(cluster, timeout="30s"), cluster
        except OSError as err:
            cluster.close()
            raise ConfigError("--executor", f"cannot connect to the Dask LocalCluster: {err}") from None

    def _submit(self, client, spec: RunSpec, out_root: str):
        return client.submit(self.run_function, spec, out_root, pure=False,
                             key=f"khepri-run-{spec.cell}-seed-{spec.seed}-{os.urandom(4).hex()}")

    def _check_connected(self, client, future) -> None:
        """A task cancelled because the client lost its scheduler did not fail: its run is left without a result
        (a resume runs it) rather than recorded as failed for good; and a worker still running it may yet write
        its real result. The study cannot go on without a scheduler: say so."""
        if future.status in ("cancelled", "lost") and client.status != "running":
            where = f"the Dask scheduler at {self.address}" if self.address else "the Dask LocalCluster's scheduler"
            raise ConfigError("--executor", f"lost the connection to {where}: the runs not finished have no "
                                            f"result; run the same command again to resume them")

    @staticmethod
    def _ran_to_an_end(future) -> bool:
        """Finished, or failed with the run's own exception; not a task that died with its worker (KilledWorker:
        Dask counts every task a dying worker held, so runs queued behind the culprit too) or was lost."""
        from distributed.scheduler import KilledWorker

        if future.status == "finished":
            return True
        return future.status == "error" and not isinstance(future.exception(), KilledWorker)

    def _isolate(self, client, suspects: List[RunSpec], out_root: str) -> Iterator[Dict[str, Any]]:
        """Run each suspect alone, as LocalExecutor._isolate does: the one that kills its worker again is
        recorded as failed, the innocent ones that shared a dying worker simply complete."""
        from distributed import wait as wait_for

        for spec in suspects:
            future = self._submit(client, spec, out_root)
            try:
                wait_for([future])
                self._check_connected(client, future)
                yield self._outcome(future, spec)
            finally:
                future.cancel()

    @staticmethod
    def _outcome(future, spec: RunSpec) -> Dict[str, Any]:
        from distributed.scheduler import KilledWorker

        if future.status == "finished":
            return future.result()
        exc = future.exception() if future.status == "error" else None
        if isinstance(exc, KilledWorker):
            # Run alone, Dask retried the task on other workers; each of them died with it.
            return failed_result(spec, f"{WORKER_DIED} (Dask: {exc})")
        if exc is not None:
            return failed_result(spec, f"{type(exc).__name__}: {exc}")
        return failed_result(spec, f"the Dask task ended as {future.status!r}")
