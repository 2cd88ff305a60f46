"""One job over several processes, on this machine or several: a group coordinated by
``jax.distributed``.

Process 0 hosts ``jax.distributed``'s coordination service at ``HOST:PORT``; every process
connects to it (:func:`start_group`) and the group's key-value store carries what the
processes tell each other: that process 0 is ready, and for every other process a heartbeat and
its end (done, or the error it stopped on). No XLA collective is used (the processes share no
array), so the group works on CPUs as well as GPUs, without ``jax_cpu_collectives_implementation``.
The work itself (which process computes what, where the results go) is the caller's:
:func:`cdra_jax.sweeps.run_sweep` gives the chunks simulated together (``k``-th in table
order) to process ``k mod N`` and reads the others' chunks from the folder they share.

A process that dies or hangs never leaves process 0 waiting forever: ``jax.distributed`` runs in
its recoverable mode (``jax_enable_recoverability``; without it, the coordination service
aborts every process as soon as one stops), and process 0 (:meth:`Group.wait_for_others`)
raises :class:`GroupError` naming the process when a worker reports an error, when a worker it
started itself exits, when a worker's heartbeat stops for :data:`HEARTBEAT_TIMEOUT` seconds, or
when no work was finished for ``timeout`` seconds. Processes that do not all connect within the
timeout end with one ``error:`` line and exit status 1 (:func:`start_group`).

Like :func:`jax.distributed.initialize`, :func:`start_group` must run before JAX starts a
backend (the first computation or ``jax.devices()``).

Cost: the processes other than 0 compile their programs in every run. JAX writes its persistent
compilation cache from process 0 only, and a compiled program's cache key holds its device,
which on process ``k > 0`` has another id than on one process (2048 for process 1 on a CPU), so
their programs are never found in the cache. A group pays off when its chunks take longer than
that compilation (measured in ``benchmarks/README.md``, section *Several processes*).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax

HEARTBEAT_SECONDS = 2.0
"""Interval between two heartbeats of a worker (s)."""
HEARTBEAT_TIMEOUT = 60.0
"""A worker whose heartbeat has not advanced for this long (s) is taken for dead."""
DEFAULT_TIMEOUT = 300.0
"""Seconds to wait for all processes to connect, and for the next finished piece of work."""
_PREFIX = "cdra_jax/group"


class GroupError(OSError):
    """A process of the group stopped, failed or hung (the message names it). An ``OSError``,
    like the other failures of the environment the command line reports in one line."""


def parse_coordinator(address: str, name: str = "coordinator") -> tuple[str, int]:
    """``(host, port)`` of ``HOST:PORT`` (an IPv6 host in brackets, ``[::1]:1234``).

    Raises:
        ValueError: naming ``name``: no colon, an empty host, a port that is not an integer in
            [1, 65535].
    """
    host, sep, port = str(address).strip().rpartition(":")
    ok = bool(sep and host and port.isdigit()) and 1 <= int(port) <= 65535
    if not ok or host.startswith("[") != host.endswith("]"):
        raise ValueError(
            f"{name} must be HOST:PORT (the address of process 0 and a free port on it, e.g. "
            f"node0:12345), got {address!r}"
        )
    return host, int(port)


def check_group(
    num_processes: int,
    process_id: int | None,
    coordinator: str | None,
    names: dict[str, str] | None = None,
) -> None:
    """Refuse an inconsistent group before any work (``ValueError`` naming the argument).

    ``num_processes >= 1``; ``process_id`` in ``[0, num_processes)``; ``coordinator`` is
    ``HOST:PORT``; a ``process_id`` needs a ``coordinator`` (processes started one by one must
    find process 0). ``names`` maps ``num_processes``/``process_id``/``coordinator`` to the
    names the caller's user knows (the CLI's flags).
    """
    label = {"num_processes": "num_processes", "process_id": "process_id"}
    label |= {"coordinator": "coordinator", **(names or {})}
    n, k, c = label["num_processes"], label["process_id"], label["coordinator"]
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1:
        raise ValueError(f"{n} must be an integer >= 1 (1: one process), got {num_processes!r}")
    if process_id is not None:
        if isinstance(process_id, bool) or not isinstance(process_id, int):
            raise ValueError(f"{k} must be an integer, got {process_id!r}")
        if not 0 <= process_id < num_processes:
            raise ValueError(
                f"{k} must be in [0, {num_processes - 1}] ({n} = {num_processes}), got {process_id}"
            )
        if coordinator is None:
            raise ValueError(f"{k} needs {c} (the HOST:PORT of process 0)")
    if coordinator is not None:
        parse_coordinator(coordinator, c)
        if num_processes == 1:
            raise ValueError(f"{c} is for {n} > 1")


def free_port() -> int:
    """A TCP port free on localhost now (the system picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


@dataclass
class Group:
    """This process's place in a started group.

    Attributes:
        process_id: this process, ``0 .. num_processes - 1``; 0 hosts the coordinator.
        num_processes: processes in the group.
        coordinator: ``HOST:PORT`` of process 0.
        client: ``jax.distributed``'s client (its key-value store).
        timeout: seconds to wait for the other processes (:meth:`wait_ready`,
            :meth:`wait_for_others`).
        workers: the worker processes this process started on this machine (process 0 of a
            local group), index ``k - 1`` for process ``k``.
    """

    process_id: int
    num_processes: int
    coordinator: str
    client: Any = field(repr=False)
    timeout: float = DEFAULT_TIMEOUT
    workers: list[subprocess.Popen] = field(default_factory=list, repr=False)
    _stop: threading.Event = field(default_factory=threading.Event, repr=False)

    def _key(self, what: str, k: int | None = None) -> str:
        return f"{_PREFIX}/{what}" if k is None else f"{_PREFIX}/{what}/{k}"

    def _get(self, key: str) -> str | None:
        try:
            return self.client.key_value_try_get(key)
        except jax.errors.JaxRuntimeError:  # NOT_FOUND
            return None

    def announce_ready(self) -> None:
        """Process 0: the shared state the workers need exists now (:meth:`wait_ready`)."""
        self.client.key_value_set(self._key("ready"), "1", allow_overwrite=True)

    def wait_ready(self) -> None:
        """A worker: wait until process 0 calls :meth:`announce_ready` (``GroupError`` after
        :attr:`timeout` s)."""
        timeout = self.timeout
        try:
            self.client.blocking_key_value_get(self._key("ready"), int(timeout * 1000))
        except jax.errors.JaxRuntimeError:
            raise GroupError(
                f"process {self.process_id}: process 0 did not get ready within {timeout:g} s"
            ) from None

    def finish(self, error: str | None = None) -> None:
        """A worker: report its end to process 0, done (``error=None``) or the error text."""
        text = "done" if error is None else f"error: {error}"
        self.client.key_value_set(self._key("end", self.process_id), text, allow_overwrite=True)

    def _beat(self) -> None:
        key, count = self._key("beat", self.process_id), 0
        while not self._stop.wait(HEARTBEAT_SECONDS):
            count += 1
            try:
                self.client.key_value_set(key, str(count), allow_overwrite=True)
            except Exception:  # the coordinator is gone: the main thread will learn it too
                return

    def wait_for_others(
        self,
        progress: Callable[[], int],
        poll: float = 0.5,
    ) -> None:
        """Process 0: wait until every other process has reported done (:meth:`finish`).

        Args:
            progress: a count of the finished pieces of work (e.g. result files on disk); the
                wait goes on as long as it grows at least once every :attr:`timeout` s.
            poll: seconds between two looks.

        Raises:
            GroupError: naming the process: it reported an error, it was started here and
                exited before reporting done, its heartbeat stopped for
                :data:`HEARTBEAT_TIMEOUT` s; or no progress for :attr:`timeout` s (naming the
                processes not done).
        """
        timeout = self.timeout
        pending = set(range(1, self.num_processes))
        beats: dict[int, tuple[str | None, float]] = {k: (None, time.monotonic()) for k in pending}
        last_count, last_change = progress(), time.monotonic()
        while pending:
            for k in sorted(pending):
                exited = None
                if k - 1 < len(self.workers):
                    exited = self.workers[k - 1].poll()  # before the end key: no race
                end = self._get(self._key("end", k))
                if end == "done":
                    pending.discard(k)
                    continue
                if end is not None:
                    raise GroupError(f"process {k} stopped with {end}")
                if exited is not None:
                    raise GroupError(f"process {k} exited (status {exited}) before finishing")
                beat, since = beats[k]
                now_beat = self._get(self._key("beat", k))
                if now_beat != beat:
                    beats[k] = (now_beat, time.monotonic())
                elif time.monotonic() - since > HEARTBEAT_TIMEOUT:
                    raise GroupError(
                        f"process {k} sent no heartbeat for {HEARTBEAT_TIMEOUT:g} s: it died or "
                        "lost its connection"
                    )
            if not pending:
                return
            count = progress()
            if count != last_count:
                last_count, last_change = count, time.monotonic()
            elif time.monotonic() - last_change > timeout:
                raise GroupError(
                    f"no progress for {timeout:g} s; process(es) "
                    + ", ".join(map(str, sorted(pending)))
                    + " not done"
                )
            time.sleep(poll)

    def close(self, ok: bool = True) -> None:
        """Leave the group: stop the heartbeat; on process 0, wait for (``ok``) or stop the
        workers it started; shut ``jax.distributed`` down."""
        self._stop.set()
        for w in self.workers:
            if ok:
                try:
                    w.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    pass
            if w.poll() is None:
                w.terminate()
                try:
                    w.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    w.kill()
                    w.wait()
        jax.distributed.shutdown()


def _exit_unless_connected(
    connected: threading.Event, timeout: float, message: str, workers: list[subprocess.Popen]
) -> None:
    """Watch the connection: one ``error:`` line and exit status 1 (the workers stopped) if a
    worker started here exits first or ``timeout`` s pass (JAX would abort later with a C++
    stack)."""
    end = time.monotonic() + timeout
    while not connected.wait(0.2):
        gone = [(k, w.returncode) for k, w in enumerate(workers, 1) if w.poll() is not None]
        if gone:
            message = f"process {gone[0][0]} exited (status {gone[0][1]}) before connecting"
        elif time.monotonic() < end:
            continue
        print(f"error: {message}", file=sys.stderr, flush=True)
        for w in workers:
            if w.poll() is None:
                w.kill()
        os._exit(1)


def start_group(
    num_processes: int,
    process_id: int | None = None,
    coordinator: str | None = None,
    *,
    worker_command: Callable[[int, str], Sequence[str]] | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> Group:
    """Start or join a group of ``num_processes`` processes (``jax.distributed.initialize``).

    Processes started by hand (one per machine, say) each pass the same ``coordinator``
    (``HOST:PORT`` of process 0) and their own ``process_id``. With neither, this process is
    process 0 of a group on this machine: it picks a free port on localhost and starts
    processes ``1 .. num_processes - 1`` itself, running ``worker_command(k, coordinator)``
    (an argument list, e.g. the same command line with the worker's id).

    Connecting waits until all processes have connected; a process that is still waiting
    after ``timeout`` s prints one ``error:`` line and exits with status 1 (JAX would abort).
    Must run before JAX starts a backend.

    Raises:
        ValueError: an inconsistent group (:func:`check_group`), or a local group without
            ``worker_command``.
        RuntimeError: JAX has already started a backend.
    """
    check_group(num_processes, process_id, coordinator)
    workers: list[subprocess.Popen] = []
    local = coordinator is None  # process 0 of a group on this machine: it starts the others
    if local:
        if worker_command is None:
            raise ValueError(
                "a group on this machine needs worker_command (the command line of process k; "
                "the CLI passes its own); or start every process yourself with coordinator and "
                "process_id"
            )
        coordinator, process_id = f"localhost:{free_port()}", 0
    assert process_id is not None and coordinator is not None
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError("start_group must run before JAX starts a backend (first computation)")
    if local:
        assert worker_command is not None
        for k in range(1, num_processes):
            command = [str(a) for a in worker_command(k, coordinator)]
            # their report would repeat process 0's; their errors (stderr) are shown
            workers.append(
                subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
            )
    jax.config.update("jax_enable_recoverability", True)
    connected = threading.Event()
    who = "process 0" if process_id == 0 else f"process {process_id}"
    threading.Thread(
        target=_exit_unless_connected,
        args=(
            connected,
            timeout,
            f"{who}: the {num_processes} processes did not all connect to the coordinator "
            f"{coordinator} within {timeout:g} s; start processes 0 .. {num_processes - 1} with "
            "the same command and coordinator, each with its own process id",
            workers,
        ),
        daemon=True,
    ).start()
    try:
        jax.distributed.initialize(
            coordinator_address=coordinator,
            num_processes=num_processes,
            process_id=process_id,
            initialization_timeout=int(timeout) + 30,
        )
    except BaseException:
        for w in workers:
            w.kill()
        raise
    finally:
        connected.set()
    from jax._src.distributed import global_state

    group = Group(process_id, num_processes, coordinator, global_state.client, timeout, workers)
    if process_id != 0:
        threading.Thread(target=group._beat, daemon=True).start()
    return group
