"""The processes of a ``jax.distributed`` run, for every command that spreads its work over
processes and hosts (``jface db build``, ``jface wrinkles fit``): joining them (one coordinator,
a clear error within a timeout), starting several on one machine, exchanging agreement, barriers
and failures through the coordinator, and the XLA flags under which CPU results do not depend on
thread scheduling."""

from __future__ import annotations

import contextlib
import itertools
import os
import socket
import subprocess
import sys
import time
from collections.abc import Sequence

import jax

from jface import _checks

_DETERMINISTIC_CPU_FLAGS = "--xla_cpu_multi_thread_eigen=false"
"""XLA flags under which CPU results do not depend on thread scheduling: a multi-threaded FFT
splits its rows over threads as they come free, which changes the last bit of some results from
run to run. Parallelism then comes from devices and processes (whole maps), not threads."""

_runs = itertools.count()  # every process makes the same calls in the same order


class _Run:
    """Exchanges between the processes of one distributed call, through the coordinator's
    key-value store. A process that fails posts its error, and every process waiting for the
    others raises it at once; a process that dies unannounced is found by the heartbeat."""

    def __init__(self):
        # the coordination service's key-value store: JAX has no public handle on it
        from jax._src import distributed

        self.client = distributed.global_state.client
        self.prefix = f"jface/run{next(_runs)}"

    def fail(self, err: BaseException) -> None:
        with contextlib.suppress(Exception):  # the coordinator may be gone already
            message = " ".join(str(err).split()) or type(err).__name__
            self.client.key_value_set(f"{self.prefix}/failed/{jax.process_index()}", message)

    def gather(self, name: str, value: str) -> list[str]:
        """Post this process's ``value``; wait for every process's (process ``i``'s at ``i``)."""
        self.client.key_value_set(f"{self.prefix}/{name}/{jax.process_index()}", value)
        n = jax.process_count()
        while True:
            failed = self.client.key_value_dir_get(f"{self.prefix}/failed/")
            if failed:
                key, message = sorted(failed)[0]
                raise ChildProcessError(f"process {key.rpartition('/')[2]} failed: {message}")
            posted = dict(self.client.key_value_dir_get(f"{self.prefix}/{name}/"))
            if len(posted) == n:
                return [posted[f"{self.prefix}/{name}/{i}"] for i in range(n)]
            time.sleep(0.05)

    def same_on_all(self, what: str, value: str) -> None:
        values = self.gather("agree", value)
        differ = [i for i, v in enumerate(values) if v != values[0]]
        if differ:
            raise ValueError(
                f"process(es) {differ} differ from process 0 in {what}: every process must run "
                "the same command on the same files"
            )


def join_processes(
    coordinator: str | None = None,
    process_id: int | None = None,
    num_processes: int | None = None,
    *,
    timeout: float = 60.0,
) -> None:
    """Start ``jax.distributed`` for this process, before any JAX computation.

    With ``coordinator`` (``"HOST:PORT"``, served by process 0), ``process_id`` and
    ``num_processes`` it joins those processes; with none of them JAX detects the cluster
    (SLURM, Open MPI, TPU pods). Process 0 opens the coordinator; the others first check that
    it can be reached, so a wrong address fails within ``timeout`` with a clear message instead
    of an abort. All processes then check that they were told the same ``num_processes``.

    Raises:
        ValueError: some but not all of the three, a malformed address, ``process_id`` outside
            ``[0, num_processes)``, or processes that disagree on ``num_processes``.
        ConnectionError: the coordinator cannot be reached within ``timeout`` seconds.
    """
    given = [coordinator is not None, process_id is not None, num_processes is not None]
    if any(given) and not all(given):
        raise ValueError(
            "coordinator, process_id and num_processes go together (or none of them, to detect "
            f"the cluster); got coordinator={coordinator!r}, process_id={process_id!r}, "
            f"num_processes={num_processes!r}"
        )
    timeout = _checks.real(timeout, "timeout", low=1.0)
    if coordinator is None:
        try:
            jax.distributed.initialize(initialization_timeout=int(timeout))
        except ValueError as err:  # JAX names its missing argument, not the missing cluster
            raise ValueError(
                f"found no cluster job to join (SLURM, Open MPI, TPU pod): {err}; give the "
                "coordinator, process id and process count instead"
            ) from err
        return
    num_processes = _checks.integer(num_processes, "num_processes", low=1)
    process_id = _checks.integer(process_id, "process_id", low=0, high=num_processes - 1)
    host, _, port = str(coordinator).rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"coordinator must be HOST:PORT (port 1-65535), got {coordinator!r}")
    if process_id != 0:
        _wait_for_coordinator(host.strip("[]"), int(port), timeout)
    jax.distributed.initialize(
        coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=int(timeout),
        heartbeat_timeout_seconds=int(timeout),
        shutdown_timeout_seconds=int(timeout),
    )
    counts = _Run().gather("num_processes", str(num_processes))
    if len(set(counts)) > 1:
        raise ValueError(
            f"the processes were given different process counts: {counts} (process i gave "
            "item i); give every process the same num_processes"
        )


def _wait_for_coordinator(host: str, port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, port), timeout=min(5.0, timeout)):
                return
        except OSError as err:
            if time.monotonic() > deadline:
                raise ConnectionError(
                    f"cannot reach the coordinator {host}:{port} within {timeout:g} s ({err}); "
                    "is process 0 running, and is the port open to this host?"
                ) from None
            time.sleep(0.2)


def run_local_processes(command: Sequence[str], processes: int, *, timeout: float = 60.0) -> None:
    """Run ``jface COMMAND`` as ``processes`` processes of one ``jax.distributed`` run on this
    machine (coordinator on localhost, a free port), and wait for them.

    Each process gets ``--coordinator``, ``--process-id``, ``--num-processes`` and ``--timeout``
    appended, and :func:`deterministic_cpu_flags` in ``XLA_FLAGS``. When one fails, the others
    are stopped (they remove their unfinished files; finished work stays for a rerun).

    Raises:
        ValueError: ``processes`` below 1.
        ChildProcessError: a process failed (its exit status; its own message is on stderr).
        KeyboardInterrupt: interrupted; the processes are stopped first.
    """
    processes = _checks.integer(processes, "processes", low=1)
    with socket.socket() as probe:  # a port free now; the coordinator binds it a moment later
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = dict(os.environ, XLA_FLAGS=deterministic_cpu_flags(os.environ.get("XLA_FLAGS", "")))
    entry = "import sys; from jface.cli import main; sys.exit(main(sys.argv[1:]))"
    children = []
    for i in range(processes):
        flags = ["--coordinator", f"127.0.0.1:{port}", "--process-id", str(i)]
        flags += ["--num-processes", str(processes), "--timeout", f"{timeout:g}"]
        # process 0 reports; the others would repeat its progress and summary
        out = None if i == 0 else subprocess.DEVNULL
        children.append(
            subprocess.Popen([sys.executable, "-c", entry, *command, *flags], env=env, stdout=out)
        )
    try:
        while True:
            codes = [child.poll() for child in children]
            failed = [i for i, code in enumerate(codes) if code not in (None, 0)]
            if failed:
                raise ChildProcessError(
                    f"process {failed[0]} of {processes} failed (exit status "
                    f"{codes[failed[0]]}); the others were stopped. Finished work (chunks, "
                    "patches) is kept: run the command again to resume"
                )
            if all(code == 0 for code in codes):
                return
            time.sleep(0.1)
    finally:
        for child in children:
            if child.poll() is None:
                child.terminate()
        for child in children:
            try:
                child.wait(timeout=30)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def cpu_device_flags(xla_flags: str = "") -> str:
    """``xla_flags`` (``XLA_FLAGS``) with one CPU device per core this process may use, unless
    it sets the count itself: under :func:`deterministic_cpu_flags` one device keeps about 1.8
    of two cores busy, and work sharded over devices uses the rest (a wrinkle fit's swarm: 64
    against 80 ms per agent on two cores). Set it before JAX starts; a GPU's devices are
    unchanged."""
    if "xla_force_host_platform_device_count" in xla_flags:
        return xla_flags
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{xla_flags} --xla_force_host_platform_device_count={max(1, cores or 1)}".strip()


def deterministic_cpu_flags(xla_flags: str = "") -> str:
    """``xla_flags`` (``XLA_FLAGS``) with ``--xla_cpu_multi_thread_eigen=false`` added, unless it
    sets Eigen's threading itself: then CPU results do not depend on thread scheduling (see
    :data:`_DETERMINISTIC_CPU_FLAGS`). Set it before JAX starts."""
    if "xla_cpu_multi_thread_eigen" in xla_flags:
        return xla_flags
    return f"{xla_flags} {_DETERMINISTIC_CPU_FLAGS}".strip()
