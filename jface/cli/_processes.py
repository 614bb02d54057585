"""The process options of the commands that spread their work over ``jax.distributed`` processes
(``jface db build``, ``jface wrinkles fit``): one spelling, one validation, one launcher.

``--processes N`` starts N processes on this machine; ``--coordinator HOST:PORT --process-id I
--num-processes N`` joins one process of a run over several hosts; ``--cluster`` joins the
processes of a cluster job (SLURM, Open MPI, TPU pod). Every process runs the same command with
the same arguments and does its share; process 0 reports (docs/distributed.md).
"""

from __future__ import annotations

import argparse
import os

from jface import _distributed


class Elsewhere(dict):
    """The summary of a process that does not report: process 0 of the run prints the
    summary (and writes the page), this process prints nothing, not even with ``--json``."""


def add_process_options(parser: argparse.ArgumentParser, share: str) -> None:
    """Add ``--processes``, ``--coordinator``, ``--process-id``, ``--num-processes``,
    ``--cluster`` and ``--timeout`` to ``parser``; ``share`` says what a process does (e.g.
    "analysing a share of the maps")."""
    parser.add_argument(
        "--processes",
        type=int,
        default=1,
        help=f"processes on this machine, each {share} on its own devices (default %(default)s)",
    )
    parser.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="join a jax.distributed run whose process 0 serves HOST:PORT (with --process-id "
        "and --num-processes) (default: none)",
    )
    parser.add_argument(
        "--process-id",
        type=int,
        help="this process's index in [0, --num-processes) (default: none)",
    )
    parser.add_argument(
        "--num-processes", type=int, help="processes of the distributed run (default: none)"
    )
    parser.add_argument(
        "--cluster",
        action="store_true",
        help="join the processes of this cluster job (SLURM, Open MPI, TPU pod), found by "
        "jax.distributed (default: off)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=60.0,
        help="seconds to reach the coordinator, and to notice a process that stopped "
        "(default %(default)s)",
    )


def spread(args: argparse.Namespace, command: list[str]) -> bool:
    """Check the process options of a parsed command and set up its processes.

    With ``--processes N`` (N > 1), run ``jface COMMAND`` (the command's own arguments, without
    the process options) as N processes on this machine, wait for them and return True: the
    launched processes did the work and their process 0 reported. Otherwise return False, after
    putting XLA's CPU threading in its deterministic mode (results must not depend on thread
    scheduling, whatever the process count; JAX reads the flags when it starts), giving a
    process that runs alone one CPU device per core (:func:`jface._distributed.
    cpu_device_flags`; the work is sharded over them) and joining the
    ``jax.distributed`` run that ``--coordinator``/``--process-id``/``--num-processes`` or
    ``--cluster`` name: this process then does its share.

    Raises:
        ValueError: ``--processes`` below 1 or given with the options of a joined run,
            ``--cluster`` with ``--coordinator``, and what :func:`jface._distributed.
            join_processes` raises.
        ConnectionError: the coordinator cannot be reached within ``--timeout``.
        ChildProcessError: a launched process failed.
    """
    joined = args.coordinator is not None or args.process_id is not None
    if args.processes != 1:
        if args.processes < 1 or joined or args.num_processes is not None or args.cluster:
            raise ValueError(
                f"--processes must be at least 1 and goes without --coordinator, --process-id, "
                f"--num-processes and --cluster; got --processes {args.processes}"
            )
        command = [*command, *(["--json"] if getattr(args, "json", False) else [])]
        _distributed.run_local_processes(command, args.processes, timeout=args.timeout)
        return True
    flags = _distributed.deterministic_cpu_flags(os.environ.get("XLA_FLAGS", ""))
    if joined or args.num_processes is not None or args.cluster:
        if args.cluster and joined:
            raise ValueError("--cluster detects the processes itself; drop --coordinator")
        # how many of the run's processes share a machine is the user's to say (XLA_FLAGS)
        os.environ["XLA_FLAGS"] = flags
        _distributed.join_processes(
            args.coordinator, args.process_id, args.num_processes, timeout=args.timeout
        )
    else:  # the one process: a device per core
        os.environ["XLA_FLAGS"] = _distributed.cpu_device_flags(flags)
    return False
