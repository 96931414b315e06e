"""One batch of independent runs over several JAX processes (several machines, or one machine).

One process already splits a seed × hyperparameter batch over its own devices
(:func:`diffgcl.sim.sharding.vmap_over_devices`). JAX's multi-controller runtime runs the same
program in N processes, each owning the devices of its host; after :func:`join` the batch mesh
(:func:`diffgcl.sim.sharding.batch_mesh`) spans the devices of every process, each process
computes its slice of the batch, and :func:`to_host` gathers the results (an all-gather: gloo TCP
collectives on CPUs, NCCL on GPUs). Every process ends with the whole result; process 0
(:func:`is_leader`) writes the run folder.

Settings (:func:`process_settings`), first found wins, field by field:

1. options: ``--coordinator HOST:PORT --num-processes N --process-id I``;
2. ``JAX_COORDINATOR_ADDRESS`` (read by JAX itself), ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``
   (diffgcl's, in JAX's naming);
3. SLURM under ``srun``: ``SLURM_NTASKS`` and ``SLURM_PROCID``; the coordinator is then the first
   host of ``SLURM_STEP_NODELIST`` with a port derived from ``SLURM_JOB_ID`` (JAX's own SLURM
   detection, ``JAX_COORDINATOR_PORT`` overrides the port);
4. a Kubernetes indexed Job (or JobSet): ``JOB_COMPLETION_INDEX`` is the process id; the pod
   spec sets ``JAX_NUM_PROCESSES`` and ``JAX_COORDINATOR_ADDRESS`` (pod 0's stable DNS name).

A count of one, or no settings at all, is a plain one-process run: nothing is started.

Failure: every process sends heartbeats to the coordination service that process 0 hosts. When a
process stops (killed, out of memory, machine lost), the service fails every other process after
``heartbeat_timeout_s`` (measured with 10 s: the survivor aborted 10 s after the kill), so a run
with a dead process fails rather than waiting forever. Before each collective the processes meet
at a :func:`barrier` of that service (gloo alone allows 30 s to meet at a communicator's first
use); a failed barrier or all-gather is a :class:`ProcessLost` with one line, which
:func:`abandon` reports. :func:`launch_local` starts N processes on this machine and turns their
ends into one line.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

ADDRESS_VAR = "JAX_COORDINATOR_ADDRESS"
NUM_PROCESSES_VAR = "JAX_NUM_PROCESSES"
PROCESS_ID_VAR = "JAX_PROCESS_ID"
SLURM_NTASKS, SLURM_PROCID = "SLURM_NTASKS", "SLURM_PROCID"
SLURM_NODELIST, SLURM_JOB_ID = "SLURM_STEP_NODELIST", "SLURM_JOB_ID"
K8S_INDEX = "JOB_COMPLETION_INDEX"

HEARTBEAT_TIMEOUT_S = 60


@dataclass(frozen=True)
class ProcessSettings:
    """Where this process stands in a multi-process run.

    coordinator_address: ``HOST:PORT`` of process 0's coordination service, or None when JAX
    derives it from the cluster launcher (SLURM); source: where the settings came from (for
    messages).
    """

    coordinator_address: str | None
    num_processes: int
    process_id: int
    source: str

    def describe(self) -> str:
        address = self.coordinator_address or "from SLURM_STEP_NODELIST"
        return (
            f"process {self.process_id} of {self.num_processes} ({self.source}), "
            f"coordinator {address}"
        )


def _int_setting(value, name: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r} is not an integer") from None


def _first(*candidates):
    """The first (value, name) whose value is not None, else (None, None)."""
    for value, name in candidates:
        if value is not None:
            return value, name
    return None, None


def process_settings(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    environ: Mapping[str, str] | None = None,
) -> ProcessSettings | None:
    """This process's place in a multi-process run, or None for a one-process run.

    Arguments are the command-line options (None: not given); ``environ`` defaults to
    ``os.environ``. See the module docstring for the order. Raises ValueError with a one-line
    message naming the option or variable when the settings are incomplete or inconsistent.
    """
    env = os.environ if environ is None else environ
    under_slurm = SLURM_PROCID in env
    num, num_name = _first(
        (num_processes, "--num-processes"),
        (env.get(NUM_PROCESSES_VAR), NUM_PROCESSES_VAR),
        (env.get(SLURM_NTASKS) if under_slurm else None, SLURM_NTASKS),
    )
    pid, pid_name = _first(
        (process_id, "--process-id"),
        (env.get(PROCESS_ID_VAR), PROCESS_ID_VAR),
        (env.get(SLURM_PROCID) if num_name == SLURM_NTASKS else None, SLURM_PROCID),
        (env.get(K8S_INDEX) if num is not None else None, K8S_INDEX),
    )
    address, address_name = _first(
        (coordinator_address, "--coordinator"), (env.get(ADDRESS_VAR), ADDRESS_VAR)
    )
    if num is None:
        if pid_name in ("--process-id", PROCESS_ID_VAR):
            raise ValueError(f"{pid_name} given without --num-processes (or {NUM_PROCESSES_VAR})")
        return None
    num = _int_setting(num, num_name)
    if num < 1:
        raise ValueError(f"{num_name}={num}: the number of processes must be at least 1")
    if num == 1:
        return None
    if pid is None:
        raise ValueError(
            f"{num_name}={num} but no process id: give --process-id or set {PROCESS_ID_VAR}"
        )
    pid = _int_setting(pid, pid_name)
    if not 0 <= pid < num:
        raise ValueError(f"{pid_name}={pid} is out of range for {num} processes (0..{num - 1})")
    if address is not None:
        host, _, port = str(address).rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"{address_name}={address!r}: expected HOST:PORT")
    elif not (num_name == SLURM_NTASKS and SLURM_NODELIST in env and SLURM_JOB_ID in env):
        raise ValueError(
            f"{num_name}={num} but no coordinator address: give --coordinator HOST:PORT or set "
            f"{ADDRESS_VAR} (process 0's host and a free port)"
        )
    source = {"--num-processes": "options", SLURM_NTASKS: "SLURM"}.get(num_name, "environment")
    if pid_name == K8S_INDEX:
        source = "Kubernetes indexed job"
    return ProcessSettings(address, num, pid, source)


def join(
    settings: ProcessSettings | None,
    *,
    heartbeat_timeout_s: int = HEARTBEAT_TIMEOUT_S,
    initialization_timeout_s: int = 300,
    shutdown_timeout_s: int = 60,
) -> bool:
    """Connect this process to the others (``jax.distributed.initialize``, CPU collectives
    through gloo); returns False and does nothing for a one-process run (``settings`` None).

    Must run before JAX's first computation. Raises RuntimeError with one line when that is too
    late or when the coordinator cannot be reached within ``initialization_timeout_s``.
    """
    if settings is None:
        return False
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError("the multi-process run must be joined before JAX's first computation")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(
            coordinator_address=settings.coordinator_address,
            num_processes=settings.num_processes,
            process_id=settings.process_id,
            initialization_timeout=initialization_timeout_s,
            heartbeat_timeout_seconds=heartbeat_timeout_s,
            shutdown_timeout_seconds=shutdown_timeout_s,
        )
    except Exception as err:  # JAX raises XlaRuntimeError or ValueError with a multi-line text
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RuntimeError(f"could not join as {settings.describe()}: {first}") from None
    return True


def is_leader() -> bool:
    """Whether this is process 0 (the one that prints and writes run folders)."""
    return jax.process_index() == 0


class ProcessLost(RuntimeError):
    """A collective across the processes failed: another process of the run has stopped."""


def abandon(message: str) -> NoReturn:
    """Print ``message`` and leave at once with status 1, skipping JAX's shutdown, which would
    wait for the lost process and then abort with a C++ stack trace."""
    print(message, file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(1)


def _lost(err: Exception, doing: str) -> ProcessLost:
    first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return ProcessLost(f"{doing} failed, another process of the run has stopped ({first})")


_barriers: dict[str, int] = {}  # how often each barrier was passed (ids must not repeat)


def barrier(name: str, timeout_s: float = 3600.0) -> None:
    """Wait until every process reaches the barrier ``name`` (e.g. until process 0 has written
    the run folder, so that no process shuts down while another still works); free in a
    one-process run. Uses the coordination service, not the devices."""
    if jax.process_count() == 1:
        return
    from jax._src import distributed as jax_distributed  # the client JAX's runtime connected

    client = jax_distributed.global_state.client
    _barriers[name] = _barriers.get(name, 0) + 1
    try:
        client.wait_at_barrier(f"diffgcl:{name}:{_barriers[name]}", int(1000 * timeout_s))
    except jax.errors.JaxRuntimeError as err:
        raise _lost(err, f"waiting for every process ({name})") from None


def _identity(*leaves):
    return leaves


def to_host(tree):
    """NumPy copies of every array of ``tree``, whole: arrays split over the devices of several
    processes are all-gathered first (one jitted program for the whole tree; every process must
    call this at the same point), local arrays are simply copied."""
    leaves, treedef = jax.tree.flatten(tree)
    split = [
        i for i, a in enumerate(leaves) if isinstance(a, jax.Array) and not a.is_fully_addressable
    ]
    if not split:
        return jax.tree.unflatten(treedef, [np.asarray(a) for a in leaves])
    whole = tuple(NamedSharding(leaves[i].sharding.mesh, PartitionSpec()) for i in split)
    barrier("gather")  # see check_same_everywhere
    try:
        gathered = jax.jit(_identity, out_shardings=whole)(*(leaves[i] for i in split))
        for i, a in zip(split, gathered, strict=True):
            leaves[i] = a.addressable_data(0)
        return jax.tree.unflatten(treedef, [np.asarray(a) for a in leaves])
    except jax.errors.JaxRuntimeError as err:
        raise _lost(err, "gathering the results") from None


# ---- compiled programs in every process's persistent cache --------------------------------------

EXECUTABLES_DIR = "executables"  # under diffgcl's cache root, beside JAX's own cache


def _executable_key(lowered) -> str:
    """What a compiled program of this process depends on: the program (StableHLO text), the
    JAX and jaxlib versions, the XLA flags, and this process's place and devices."""
    import jaxlib

    h = hashlib.sha256()
    for part in (
        lowered.as_text(),
        jax.__version__,
        jaxlib.__version__,
        os.environ.get("XLA_FLAGS", ""),
        f"process {jax.process_index()} of {jax.process_count()}",
        repr([(d.id, d.platform, d.device_kind) for d in jax.devices()]),
    ):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


def compile_program(lowered, cache_dir: str | os.PathLike | None = None):
    """``lowered.compile()``, through a persistent cache that every process of a multi-process
    run reads and writes (in a one-process run: ``lowered.compile()``, JAX's own cache).

    JAX writes its persistent compilation cache from process 0 only, and on CPUs a program's key
    there differs between processes (the host topology's fingerprint is part of it), so every
    other process compiled every program afresh in every run: a two-process sweep's second run
    still compiled its 27 s program in process 1. Here each process keeps its executables under
    ``cache_dir`` (default ``<diffgcl cache>/executables``), keyed by the program, the versions,
    the XLA flags and the process's devices, written with
    :func:`jax.experimental.serialize_executable.serialize`. An unreadable entry is compiled
    again and replaced. Load only caches you wrote: a serialized executable is code."""
    if jax.process_count() == 1:
        return lowered.compile()
    from jax.experimental.serialize_executable import deserialize_and_load, serialize

    from diffgcl.runtime import cache_root

    directory = Path(cache_dir) if cache_dir is not None else cache_root() / EXECUTABLES_DIR
    path = directory / f"{_executable_key(lowered)}.bin"
    in_tree = jax.tree.structure(lowered.args_info)
    if path.is_file():
        try:
            return deserialize_and_load(
                path.read_bytes(), in_tree, lowered.out_tree, execution_devices=jax.devices()
            )
        except Exception as err:  # a partial or stale entry: compile and replace it
            print(f"process {jax.process_index()}: {path.name} unreadable ({err}); compiling")
    compiled = lowered.compile()
    try:
        payload, _, _ = serialize(compiled)
        directory.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.part")
        partial.write_bytes(payload)
        partial.replace(path)  # atomic: a reader never sees half a file
    except (ValueError, NotImplementedError, OSError) as err:
        print(f"process {jax.process_index()}: compiled program not cached ({err})")
    return compiled


def _digest(value) -> np.ndarray:
    """A 128-bit digest of a pytree of arrays, or of anything JSON can write."""
    h = hashlib.sha256()
    leaves = jax.tree.leaves(value)
    if leaves and all(isinstance(a, (np.ndarray, jax.Array, np.generic)) for a in leaves):
        for a in leaves:
            a = np.ascontiguousarray(np.asarray(a))
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    else:
        h.update(json.dumps(value, sort_keys=True, default=str).encode())
    return np.frombuffer(h.digest()[:16], np.uint32).copy()


def check_same_everywhere(
    what: str, value, hint: str = "start every process with the same options and data"
) -> None:
    """Raise ValueError when ``value`` (arrays, or JSON-able settings) differs between the
    processes of a multi-process run: every process must start with the same options and data
    (a demo folder that differs between machines would silently mix two experiments). A
    collective: every process calls it at the same point; free in a one-process run."""
    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    # Arrive together: gloo gives the processes 30 s to meet at a communicator's first use
    # (measured: "Gloo context initialization failed: DEADLINE_EXCEEDED ... 29.99s" when one
    # process built its env that much later on a busy host); the barrier has no such limit.
    barrier(f"compare {what}")
    try:
        digests = np.asarray(multihost_utils.process_allgather(_digest(value)))
    except jax.errors.JaxRuntimeError as err:
        raise _lost(err, f"comparing the {what}") from None
    differ = [p for p in range(digests.shape[0]) if not np.array_equal(digests[p], digests[0])]
    if differ:
        raise ValueError(
            f"{what} differ between processes: process(es) {differ} do not match process 0 ({hint})"
        )


# ---- a launcher for several processes on this machine ------------------------------------------


def free_port() -> int:
    """A TCP port that is free on this host now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ending(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _forward(stream, prefix: str, out) -> None:
    for line in iter(stream.readline, b""):
        out.write(prefix + line.decode(errors="replace"))
        out.flush()
    stream.close()


def launch_local(
    command: Sequence[str],
    num_processes: int,
    *,
    devices_per_process: int | None = None,
    port: int | None = None,
    grace_s: float = HEARTBEAT_TIMEOUT_S + 30,
    timeout_s: float | None = None,
    env: Mapping[str, str] | None = None,
) -> int:
    """Run ``command`` as ``num_processes`` processes of one multi-process run on this host.

    Each child gets ``JAX_COORDINATOR_ADDRESS=127.0.0.1:PORT``, ``JAX_NUM_PROCESSES`` and its
    ``JAX_PROCESS_ID``, and ``devices_per_process`` XLA CPU devices (default: this host's cores
    shared out, at least one). Process 0's output passes through; the others' is prefixed
    ``[process i]`` on stderr. When a process fails, the others get ``grace_s`` seconds to end
    (the distributed service aborts them after its heartbeat timeout) before the launcher stops
    them; ``timeout_s`` bounds the whole run. Returns process 0's exit status when every other
    process exited with 0 (the command's own status), else 1 after one line on stderr saying
    which process ended first and how.
    """
    if num_processes < 1:
        raise ValueError(f"--local-processes {num_processes}: must be at least 1")
    from diffgcl.runtime import HOST_DEVICE_FLAG

    devices = devices_per_process or max(1, (os.cpu_count() or 1) // num_processes)
    port = free_port() if port is None else port
    base = dict(os.environ if env is None else env)
    flags = [f for f in base.get("XLA_FLAGS", "").split() if not f.startswith(HOST_DEVICE_FLAG)]
    base["XLA_FLAGS"] = " ".join([*flags, f"{HOST_DEVICE_FLAG}={devices}"])
    base.update(
        {ADDRESS_VAR: f"127.0.0.1:{port}", NUM_PROCESSES_VAR: str(num_processes)},
        PYTHONUNBUFFERED="1",
    )
    procs, threads = [], []
    for i in range(num_processes):
        child_env = dict(base, **{PROCESS_ID_VAR: str(i)})
        if i == 0:
            procs.append(subprocess.Popen(list(command), env=child_env))
            continue
        p = subprocess.Popen(
            list(command), env=child_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        t = threading.Thread(target=_forward, args=(p.stdout, f"[process {i}] ", sys.stderr))
        t.daemon = True
        t.start()
        procs.append(p)
        threads.append(t)
    ended: dict[int, tuple[float, int]] = {}  # process -> (time, return code)
    stopped: list[int] = []
    first_failure = None
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        while len(ended) < num_processes:
            now = time.monotonic()
            for i, p in enumerate(procs):
                if i not in ended and p.poll() is not None:
                    ended[i] = (now, p.returncode)
                    if p.returncode != 0 and first_failure is None:
                        first_failure = now
            late = deadline is not None and now > deadline
            if late or (first_failure is not None and now - first_failure > grace_s):
                for i, p in enumerate(procs):
                    if i not in ended:
                        p.kill()
                        ended[i] = (now, p.wait())
                        stopped.append(i)
            time.sleep(0.1)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for t in threads:
            t.join(timeout=5)
    codes = {i: code for i, (_, code) in ended.items()}
    if not stopped and all(codes[i] == 0 for i in codes if i > 0) and codes[0] > 0:
        return codes[0]  # every process finished; process 0's status is the command's
    if first_failure is None:
        if not stopped:
            return 0
        print(
            f"diffgcl: the {num_processes}-process run took longer than {timeout_s:g} s; "
            f"the launcher stopped process(es) {stopped}",
            file=sys.stderr,
        )
        return 1
    first = min((i for i in ended if i not in stopped and ended[i][1] != 0), key=ended.get)
    t0 = ended[first][0]
    others = []
    for i in sorted(ended, key=ended.get):
        if i != first:
            how = "stopped by the launcher" if i in stopped else _ending(ended[i][1])
            dt = ended[i][0] - t0
            others.append(f"process {i} {how} {abs(dt):.0f} s {'later' if dt >= 0 else 'earlier'}")
    print(
        f"diffgcl: the {num_processes}-process run failed: process {first} ended first "
        f"({_ending(ended[first][1])}); " + ", ".join(others),
        file=sys.stderr,
    )
    return 1


# ---- command-line options -----------------------------------------------------------------------

LAUNCHER_OPTIONS = ("--local-processes", "--devices")


def add_process_options(parser) -> None:
    """The multi-process options on an argparse parser (see :func:`launch_or_join`)."""
    group = parser.add_argument_group(
        "several processes", "or the environment a cluster launcher sets (docs/scale_out.md)"
    )
    group.add_argument(
        "--local-processes",
        type=int,
        default=None,
        metavar="N",
        help="start N processes of this command on this host (with --devices each)",
    )
    group.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="process 0's")
    group.add_argument("--num-processes", type=int, default=None, metavar="N")
    group.add_argument("--process-id", type=int, default=None, metavar="I")
    group.add_argument(
        "--heartbeat-timeout",
        type=int,
        default=HEARTBEAT_TIMEOUT_S,
        metavar="S",
        help="seconds after which a silent process stops the run",
    )


def without_options(argv: Sequence[str], names: Sequence[str]) -> list[str]:
    """``argv`` without the options ``names`` and their values (``--x V`` or ``--x=V``)."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in names:
            skip = True
        elif not any(arg.startswith(f"{name}=") for name in names):
            out.append(arg)
    return out


def launch_or_join(
    args, program: Sequence[str], argv: Sequence[str], prepare: Callable[[], object] | None = None
) -> int | None:
    """With ``--local-processes N``: call ``prepare`` here (one-process work the processes need
    done first, e.g. generating cached demos), then run ``program + argv`` (less the launcher's
    options) as N processes on this host and return their exit status (:func:`launch_local`).
    Otherwise join the multi-process run that the options or the environment describe, if any,
    and return None. Bad settings end the program with a one-line message."""
    try:
        if args.local_processes is not None:
            if prepare is not None:
                prepare()
            command = [*program, *without_options(argv, LAUNCHER_OPTIONS)]
            return launch_local(
                command,
                args.local_processes,
                devices_per_process=getattr(args, "devices", None),
                grace_s=args.heartbeat_timeout + 30,
            )
        settings = process_settings(args.coordinator, args.num_processes, args.process_id)
        join(settings, heartbeat_timeout_s=args.heartbeat_timeout)
    except (ValueError, RuntimeError) as err:
        raise SystemExit(f"diffgcl: {err}") from None
    return None
