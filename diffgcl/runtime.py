"""Process-wide JAX settings shared by the CLI, the experiments and the tests.

Each distinct jitted program that differentiates through ``mjx.step`` costs 13–24 s to compile on
a 2-core CPU; JAX's persistent compilation cache brings a later process down to well under a
second, so every entry point turns it on (:func:`prepare_process`).

Tracing a training program builds millions of short-lived Python objects (jaxpr variables and
equations, once per ``vmap``/``jacfwd`` pass over ``mjx.step``); with Python's default thresholds
the cyclic garbage collector runs every 700 allocations and walks them all again.
:func:`relax_garbage_collection` raises the thresholds: tracing the USV ``--fast`` run's programs
took 9.3 s instead of 12.1 s, the whole warm run 21 s instead of 28 s
(``experiments/bench_tracing.py``).

XLA's CPU compiler emits each fused kernel with its MLIR fusion emitters by default; its older
LLVM IR emitters compile the same programs in about two thirds of the time, and the programs
run as fast (``docs/compile.md``: the arm's 32-seed rGCL batch compiled in 23 s instead of 36 s,
ran in 6.5 s against 6.7 s). :func:`prepare_process` selects them
(:data:`FAST_COMPILE_FLAGS`) unless ``XLA_FLAGS`` already says otherwise.

XLA's backend (LLVM) optimisation level is 1 instead of XLA's 3 (:data:`COMPILE_LEVEL_FLAGS`):
the USV's ``--fast`` run compiled in 39.5 s instead of 61 s but ran 13 % longer after compiling
(26.0 s against 23.1 s); the arm's rGCL batches compiled 26–32 % faster and ran as fast
(``docs/compile.md``). For a run of hours, ``XLA_FLAGS=--xla_backend_optimization_level=3``
restores XLA's level. For programs that run for well under a second (the test suite's),
``DIFFGCL_QUICK_COMPILE=1`` lowers it to 0 (:data:`QUICK_COMPILE_FLAGS`): the arm's 8-seed rGCL
batch compiled in 25 s instead of 36 s but ran in 4.4 s instead of 1.4 s, and the test suite
took 15 min instead of 23. A training run of minutes loses more than it gains there.

jaxlib 0.10.2's XLA:CPU hands some fusions to its YNNPACK library by default; one of its transpose
kernels crashes the process (SIGSEGV in ``slinky::fuse_contiguous_dims``, under
``YnnFusionThunk``) in the USV's staged hull rollouts. :data:`CRASH_WORKAROUND_FLAGS` turns
those fusions off (XLA's own kernels run instead, measured no slower to compile or run); importing
:mod:`diffgcl` sets them when JAX has not started yet, and so does :func:`prepare_process`.
"""

from __future__ import annotations

import gc
import os
from pathlib import Path

import jax


def cache_root() -> Path:
    """Root of diffgcl's on-disk caches: ``$DIFFGCL_CACHE`` or ``~/.cache/diffgcl``."""
    return Path(os.environ.get("DIFFGCL_CACHE", Path.home() / ".cache" / "diffgcl"))


HOST_DEVICE_FLAG = "--xla_force_host_platform_device_count"
FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
COMPILE_LEVEL_FLAGS = ("--xla_backend_optimization_level=1",)
QUICK_COMPILE_FLAGS = ("--xla_backend_optimization_level=0",)
QUICK_COMPILE_ENV = "DIFFGCL_QUICK_COMPILE"
CRASH_WORKAROUND_FLAGS = ("--xla_cpu_experimental_ynn_fusion_type=",)  # no YNNPACK fusions
SERIAL_CODEGEN_FLAGS = ("--xla_cpu_parallel_codegen_split_count=1",)


def _backends_started() -> bool:
    try:  # private API: if it moves, assume JAX has not started
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return False


def add_xla_flags(flags) -> bool:
    """Append ``--name=value`` flags to ``XLA_FLAGS`` before JAX's backends start; a flag whose
    name ``XLA_FLAGS`` already sets is left as the user set it. Returns whether they were added
    (False once JAX has started: XLA reads its flags once)."""
    if _backends_started():
        return False
    current = os.environ.get("XLA_FLAGS", "")
    names = {f.split("=")[0] for f in current.split()}
    extra = [f for f in flags if f.split("=")[0] not in names]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([current, *extra]).strip()
    return True


def set_cpu_devices(n: int | None = None) -> bool:
    """Split the host CPU into ``n`` XLA devices (default: one per core, ``os.cpu_count()``).

    Works only before JAX's backends start (the first computation or ``jax.devices()``); leaves a
    device count already given in ``XLA_FLAGS`` alone. Returns whether the setting took effect.
    Accelerators are unaffected: the flag only splits the host platform.
    """
    started = _backends_started()
    flags = os.environ.get("XLA_FLAGS", "")
    if HOST_DEVICE_FLAG in flags or started:
        return False
    n = (os.cpu_count() or 1) if n is None else n
    os.environ["XLA_FLAGS"] = f"{flags} {HOST_DEVICE_FLAG}={n}".strip()
    return True


def add_devices_option(parser) -> None:
    """``--devices N`` on an argparse parser (see :func:`apply_devices_option`)."""
    parser.add_argument(
        "--devices",
        type=int,
        default=None,
        help="XLA CPU devices the seed batch is sharded over (default: one per core)",
    )


def apply_devices_option(args) -> None:
    """:func:`set_cpu_devices` with ``args.devices``; an explicit count that cannot take effect
    (``XLA_FLAGS`` sets one, or JAX has started) is an error rather than silently ignored."""
    if not set_cpu_devices(args.devices) and args.devices is not None:
        raise SystemExit("--devices: XLA_FLAGS already sets the device count, or JAX started")


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache (idempotent); returns its directory."""
    directory = Path(path) if path is not None else cache_root() / "jax"
    directory.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return directory


GC_THRESHOLDS = (100_000, 50, 100)  # Python's default: (700, 10, 10)


def relax_garbage_collection() -> None:
    """Raise the cyclic garbage collector's thresholds to :data:`GC_THRESHOLDS` (process-wide;
    reference counting still frees what is not in a cycle at once). Only entry points call this
    (:func:`prepare_process`): a library does not change its host's collector."""
    gc.set_threshold(*GC_THRESHOLDS)


def prepare_process(cache_dir: str | os.PathLike | None = None, *, processes: int = 1) -> Path:
    """What every entry point (CLI, experiments, tests) sets before it traces anything: JAX's
    persistent compilation cache (:func:`enable_compilation_cache`, returns its directory),
    :func:`relax_garbage_collection`, :data:`CRASH_WORKAROUND_FLAGS` and XLA's faster-compiling
    CPU emitters (:data:`FAST_COMPILE_FLAGS`) and optimisation level (:data:`COMPILE_LEVEL_FLAGS`,
    or :data:`QUICK_COMPILE_FLAGS` where ``$DIFFGCL_QUICK_COMPILE`` is 1; only before JAX's first
    computation). The environment variable, unlike flags a caller sets in ``XLA_FLAGS``,
    reaches every process an entry point starts, whatever ``XLA_FLAGS`` that process is given.

    ``processes``: how many processes of this run compile at the same time on this machine
    (this one and those it starts, which inherit its ``XLA_FLAGS``). With at least one per core,
    XLA codegens each program as one module (:data:`SERIAL_CODEGEN_FLAGS`) instead of splitting
    it for the cores that the other processes occupy: the USV's ``--fast`` run, two processes on
    two cores, took 78 s on average instead of 82 (5 and 6 runs, 73.5–85.1 s against 79.5–83.2
    s); one process alone compiles faster split (the arm's 32-seed batch 12.4–13.0 s split,
    15.8–16.2 s not). The test suite's two workers at the quick level gain nothing (8 min 4 s
    against 8 min 2 s), so ``tests/conftest.py`` leaves it."""
    quick = os.environ.get(QUICK_COMPILE_ENV, "0") == "1"
    add_xla_flags(CRASH_WORKAROUND_FLAGS)
    add_xla_flags(FAST_COMPILE_FLAGS + (QUICK_COMPILE_FLAGS if quick else COMPILE_LEVEL_FLAGS))
    if processes >= (os.cpu_count() or 1):
        add_xla_flags(SERIAL_CODEGEN_FLAGS)
    relax_garbage_collection()
    return enable_compilation_cache(cache_dir)


COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


class CompileClock:
    """Seconds JAX spent tracing, lowering and compiling while the ``with`` block ran (from
    JAX's monitoring events; a compile served by the persistent cache counts its retrieval):
    ``with CompileClock() as clock: ...; clock.seconds``."""

    def __init__(self):
        self.seconds = 0.0
        self._active = False

    def _listen(self, event: str, duration: float, **_) -> None:
        if self._active and event in COMPILE_EVENTS:
            self.seconds += duration

    def __enter__(self) -> CompileClock:
        self._active = True
        jax.monitoring.register_event_duration_secs_listener(self._listen)
        return self

    def __exit__(self, *exc) -> None:
        self._active = False
        try:  # not public API; without it the silenced listener stays registered
            from jax._src import monitoring

            monitoring.unregister_event_duration_listener(self._listen)
        except (ImportError, AttributeError, AssertionError, ValueError):
            pass
