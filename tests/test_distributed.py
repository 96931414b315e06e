"""Several JAX processes (diffgcl.distributed): settings, the local launcher, and a sweep in 2
processes × 1 device against the same sweep in 1 process × 2 devices (float64, exact), with a
process killed mid-run.

The runs go through tests/multiprocess_sweep.py (the stand-in env of test_rgcl.py), and the host's
staged simulation of an MJX model in every process through tests/multiprocess_staged.py. On CPU,
JAX's persistent compilation cache is written by process 0 only and its keys differ between
processes, so process 1 compiles the tiny program afresh in every run (≈ 20–60 s here).
"""

from __future__ import annotations

import os
import pickle
import re
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from diffgcl.distributed import (
    EXECUTABLES_DIR,
    ProcessSettings,
    launch_local,
    process_settings,
    without_options,
)

DRIVER = str(Path(__file__).with_name("multiprocess_sweep.py"))
HEARTBEAT_TIMEOUT_S = 20  # the driver's


# ---- settings -----------------------------------------------------------------------------------


def test_settings_from_options_environment_and_launchers():
    assert process_settings(environ={}) is None
    assert process_settings(num_processes=1, environ={}) is None
    s = process_settings("10.0.0.1:1234", 4, 3, environ={})
    assert s == ProcessSettings("10.0.0.1:1234", 4, 3, "options")
    env = {"JAX_COORDINATOR_ADDRESS": "head:99", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}
    assert process_settings(environ=env) == ProcessSettings("head:99", 2, 1, "environment")
    # Options win over the environment, field by field.
    assert process_settings(process_id=0, environ=env) == ProcessSettings(
        "head:99", 2, 0, "environment"
    )
    slurm = {
        "SLURM_JOB_ID": "77",
        "SLURM_NTASKS": "8",
        "SLURM_PROCID": "5",
        "SLURM_STEP_NODELIST": "node[01-04]",
        "SLURM_LOCALID": "1",
    }
    # The coordinator comes from JAX's own SLURM detection (first node of the step).
    assert process_settings(environ=slurm) == ProcessSettings(None, 8, 5, "SLURM")
    assert process_settings(environ=dict(slurm, SLURM_NTASKS="1")) is None  # one task
    k8s = {
        "JOB_COMPLETION_INDEX": "2",
        "JAX_NUM_PROCESSES": "3",
        "JAX_COORDINATOR_ADDRESS": "j-0.s:5",
    }
    assert process_settings(environ=k8s) == ProcessSettings(
        "j-0.s:5", 3, 2, "Kubernetes indexed job"
    )
    assert process_settings(environ={"JOB_COMPLETION_INDEX": "2"}) is None  # a lone indexed job


@pytest.mark.parametrize(
    "kwargs, environ, message",
    [
        ({"num_processes": 2}, {}, "--num-processes=2 but no process id"),
        ({"process_id": 1}, {}, "--process-id given without --num-processes"),
        ({"num_processes": 2, "process_id": 2}, {}, "--process-id=2 is out of range for 2"),
        ({"num_processes": 2, "process_id": 1}, {}, "no coordinator address"),
        ({"coordinator_address": "nohost", "num_processes": 2, "process_id": 1}, {}, "HOST:PORT"),
        ({}, {"JAX_NUM_PROCESSES": "two", "JAX_PROCESS_ID": "0"}, "JAX_NUM_PROCESSES='two' is"),
        ({}, {"JAX_NUM_PROCESSES": "0"}, "JAX_NUM_PROCESSES=0: the number of processes"),
        ({}, {"SLURM_NTASKS": "2", "SLURM_PROCID": "0"}, "SLURM_NTASKS=2 but no coordinator"),
    ],
)
def test_bad_settings_are_one_line_errors(kwargs, environ, message):
    with pytest.raises(ValueError, match=re.escape(message)) as err:
        process_settings(**kwargs, environ=environ)
    assert "\n" not in str(err.value)


def test_launcher_options_are_removed_from_the_children_command():
    argv = ["sweep", "--local-processes", "2", "--devices=1", "--seeds", "4", "--devices", "3"]
    assert without_options(argv, ("--local-processes", "--devices")) == ["sweep", "--seeds", "4"]


def test_cli_rejects_incomplete_settings_in_one_line(monkeypatch):
    from diffgcl.cli import main

    with pytest.raises(SystemExit, match="no process id"):
        main(["sweep", "--num-processes", "2", "--seeds", "2"])
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    monkeypatch.setenv("JAX_PROCESS_ID", "5")
    with pytest.raises(SystemExit, match=re.escape("JAX_PROCESS_ID=5 is out of range")):
        main(["train", "--seeds", "2"])
    with pytest.raises(SystemExit, match="NAME=V1,V2"):
        main(["sweep", "--param", "nope=1"])


# ---- the local launcher (no JAX in the children) -------------------------------------------------

CHILD = """
import os, signal, sys, time
i = int(os.environ["JAX_PROCESS_ID"])
print(f"child {i} of {os.environ['JAX_NUM_PROCESSES']} at {os.environ['JAX_COORDINATOR_ADDRESS']}")
print("flags", os.environ["XLA_FLAGS"])
if sys.argv[1] == "kill" and i == 1:
    os.kill(os.getpid(), signal.SIGKILL)
if sys.argv[1] in ("kill", "hang") and i == 0:
    time.sleep(600)
if sys.argv[1] == "status":
    sys.exit(3 if i == 0 else 0)
"""


def test_launcher_starts_processes_and_reports_the_first_to_fail(capfd):
    assert launch_local([sys.executable, "-c", CHILD, "ok"], 3, devices_per_process=2) == 0
    out, err = capfd.readouterr()
    assert re.search(r"^child 0 of 3 at 127\.0\.0\.1:\d+$", out, re.M), out
    assert "--xla_force_host_platform_device_count=2" in out
    assert "[process 2] child 2 of 3" in err and "[process 1] child 1 of 3" in err

    start = time.monotonic()
    assert launch_local([sys.executable, "-c", CHILD, "kill"], 2, grace_s=1.0) == 1
    assert time.monotonic() - start < 30
    last = capfd.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("diffgcl: the 2-process run failed: process 1 ended first")
    assert "(killed by SIGKILL); process 0 stopped by the launcher 1 s later" in last

    # Every process finished and process 0 says e.g. "no seed succeeded": its status, no message.
    assert launch_local([sys.executable, "-c", CHILD, "status"], 2) == 3
    assert "diffgcl:" not in capfd.readouterr().err

    assert launch_local([sys.executable, "-c", CHILD, "hang"], 2, timeout_s=2.0) == 1
    last = capfd.readouterr().err.strip().splitlines()[-1]
    assert "took longer than 2 s; the launcher stopped process(es) [0]" in last


LATE = """
import os, sys, time
import numpy as np
from diffgcl import distributed
distributed.join(distributed.process_settings(), heartbeat_timeout_s=20)
import jax
if jax.process_index() == 1:
    time.sleep(float(sys.argv[1]))  # e.g. a slow start on a busy host
distributed.check_same_everywhere("numbers", np.arange(3))
from diffgcl.sim.sharding import shard_batch
print("gathered", distributed.to_host(shard_batch(np.arange(2.0))).tolist())
"""


@pytest.mark.slow
def test_a_process_that_arrives_late_still_joins(capfd):
    """Gloo gives the processes 30 s to meet at a communicator's first use; the coordination
    service's barrier in front of it has no such limit."""
    assert launch_local([sys.executable, "-c", LATE, "40"], 2, devices_per_process=1) == 0
    assert "gathered [0.0, 1.0]" in capfd.readouterr().out


# ---- the sweep in one process --------------------------------------------------------------------


def test_sweep_pads_its_last_chunk_and_scores_every_run(demos_file):
    """run_sweep over 2 learning rates × 2 seeds in chunks of 3 (the second padded with a copy of
    the last run) against each run of jit(train) on its own, scored by run_outcome."""
    from test_rgcl import Slider, tiny_config

    from diffgcl.algorithms.rgcl import make_train
    from diffgcl.algorithms.sweep import parse_grid, run_outcome, run_sweep

    env, config = Slider(), tiny_config("v2", iterations=2)
    demos = pickle.loads(Path(demos_file).read_bytes())
    grid = parse_grid(["cost_lr=1e-2,3e-3"])
    result = run_sweep(config, env, demos, [4, 5], grid, chunk=3, keep_states=True)
    n = len(jax.devices())  # another test in this worker may have split the CPU into two
    assert result.chunk == -(-3 // n) * n and result.processes == 1 and len(result.points) == 2
    assert result.outcome.success.shape == (4,) and result.state.iteration.shape == (4,)
    rgcl = make_train(config, env)
    single = jax.jit(rgcl.train)
    score = jax.jit(lambda state, metrics: run_outcome(env, state, metrics))
    for i, (lr, seed) in enumerate([(1e-2, 4), (1e-2, 5), (3e-3, 4), (3e-3, 5)]):
        hp = rgcl.default_hparams().replace(cost_lr=jax.numpy.asarray(lr))
        state, metrics = single(jax.random.PRNGKey(seed), demos, hp)
        np.testing.assert_allclose(result.state.gps.controller.K[i], state.gps.controller.K)
        expected = score(state, metrics)
        for name in ("success", "final_distance", "final_true_cost"):
            got, want = getattr(result.outcome, name)[i], np.asarray(getattr(expected, name))
            np.testing.assert_allclose(got, want, rtol=1e-9, err_msg=name)
    # The score by hand: the final controllers' noise-free rollout, worst condition.
    from diffgcl.algorithms.rgcl import final_rollouts

    X = np.asarray(final_rollouts(env, jax.tree.map(lambda a: a[3], result.state.gps.controller)))
    np.testing.assert_allclose(result.outcome.final_distance[3], np.abs(X[:, -1, :2]).max())
    assert result.outcome.success[3] == bool(np.all(np.abs(X[:, -3:, :2]) < 0.15))
    rows = result.table()
    assert [r["cost_lr"] for r in rows] == [1e-2, 3e-3]
    assert rows[1]["success_rate"] == result.outcome.success[2:].mean()
    summary = result.to_dict()
    assert [r["seed"] for r in summary["runs"]] == [4, 5, 4, 5]


# ---- a sweep over two processes -----------------------------------------------------------------


@pytest.fixture(scope="module")
def demos_file(tmp_path_factory):
    """The stand-in's expert demos (GPS on its known cost), pickled for the driver."""
    from test_rgcl import Slider

    from diffgcl.algorithms.expert import make_demo_set, sample_expert
    from diffgcl.algorithms.gps import GPSConfig, make_gps
    from diffgcl.algorithms.rgcl import demo_batch

    env = Slider()
    gps = make_gps(GPSConfig(iterations=8, init_var=1.0, kl_step=1.0), env, env.expert_cost)
    state, _ = jax.jit(gps.train)(jax.random.PRNGKey(0))
    traj, cond = sample_expert(
        env, state.controller, env.initial_states(), jax.random.PRNGKey(1), 8, smooth_sigma=None
    )
    demos = demo_batch(make_demo_set(env, traj, np.asarray(cond), cost=env.expert_cost), 1)
    path = tmp_path_factory.mktemp("demos") / "demos.pkl"
    path.write_bytes(pickle.dumps(jax.tree.map(np.asarray, demos)))
    return str(path)


def _one_process_two_devices(*args) -> str:
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run(
        [sys.executable, DRIVER, *args], env=env, capture_output=True, text=True, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def _assert_same_npz(one: Path, two: Path, rtol: float = 0.0) -> None:
    """Every array of the two files equal: bitwise (``rtol=0``), or within ``rtol`` times the
    larger of 1 and the array's largest magnitude (an array of rounding noise about zero, such
    as a residual, compares on the absolute scale)."""
    a, b = np.load(one), np.load(two)
    assert a.files == b.files and len(a.files) > 50, (len(a.files), len(b.files))
    for name in a.files:
        if rtol == 0.0 or not np.issubdtype(a[name].dtype, np.floating):
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        else:
            scale = max(1.0, float(np.max(np.abs(b[name]), initial=0.0)))
            np.testing.assert_allclose(a[name], b[name], rtol=0.0, atol=rtol * scale, err_msg=name)


def test_two_processes_give_the_one_process_sweep_exactly(demos_file, tmp_path, capfd):
    """And every process keeps its compiled sweep program: run again with the same cache, each
    loads its own (the files are read, not rewritten) and the outcome is the same."""
    one, two, again = tmp_path / "one.npz", tmp_path / "two.npz", tmp_path / "again.npz"
    out = _one_process_two_devices("sweep", demos_file, str(one))
    assert "chunk 4 devices 2 processes 1" in out
    env = dict(os.environ, DIFFGCL_CACHE=str(tmp_path / "cache"))  # starts empty
    command = [sys.executable, DRIVER, "sweep", demos_file, str(two)]
    rc = launch_local(command, 2, devices_per_process=1, timeout_s=900, env=env)
    out, err = capfd.readouterr()
    assert rc == 0, err[-3000:]
    assert "chunk 4 devices 2 processes 2" in out
    assert "uneven: a batch of 3 does not divide over the 2 devices of 2 processes" in out
    _assert_same_npz(one, two)
    success, distance = np.load(two)["arr_0"], np.load(two)["arr_1"]
    assert success.shape == (6,) and success.dtype == bool
    assert distance.dtype == np.float64 and len(set(distance.tolist())) == 6  # all runs differ

    executables = sorted((tmp_path / "cache" / EXECUTABLES_DIR).glob("*.bin"))
    assert len(executables) == 2, executables  # one sweep program per process
    written = {p: p.stat().st_mtime_ns for p in executables}
    command = [sys.executable, DRIVER, "sweep", demos_file, str(again)]
    rc = launch_local(command, 2, devices_per_process=1, timeout_s=900, env=env)
    out, err = capfd.readouterr()
    assert rc == 0, err[-3000:]
    assert "unreadable" not in out + err and "not cached" not in out + err
    assert {p: p.stat().st_mtime_ns for p in executables} == written
    _assert_same_npz(two, again)


def test_a_killed_process_fails_the_run_in_bounded_time(demos_file, tmp_path, capfd):
    """Process 1 is killed once the run has started: process 0, compiling and running its slice
    of the first chunk, stops by itself within the heartbeat timeout (plus slack) — or at once
    with a one-line error if it reaches the all-gather first — and the launcher's last line says
    what happened."""
    command = [sys.executable, DRIVER, "sweep", demos_file, str(tmp_path / "x.npz")]
    rc = launch_local(command + ["--kill-process", "1"], 2, devices_per_process=1, timeout_s=900)
    err = capfd.readouterr().err
    assert rc == 1
    assert not (tmp_path / "x.npz").exists()
    last = err.strip().splitlines()[-1]
    pattern = r"process 1 ended first \(killed by SIGKILL\); process 0 (.*) (\d+) s later"
    found = re.search(pattern, last)
    assert found, err[-3000:]
    # Waiting for process 1 (the barrier after compiling, or the all-gather), process 0 gets the
    # error from JAX's heartbeat check or the reset connection and leaves with one line (exit
    # code 1); were it inside a computation, JAX would abort it (SIGABRT). Either way it stops by
    # itself, not by the launcher.
    assert found.group(1) in ("exit code 1", "killed by SIGABRT"), last
    assert int(found.group(2)) <= HEARTBEAT_TIMEOUT_S + 20, last
    if found.group(1) == "exit code 1":
        assert re.search(r"^sweep: .* failed, another process of the run has stopped", err, re.M)


def test_staged_simulation_runs_in_every_process(tmp_path, capfd):
    """Host-side staged work (the demos' dynamics that ``diffgcl sweep`` and ``train`` compute
    before the runs, the API's rollouts) in a run of 2 processes: each process computes the whole
    batch on its own device and gets what one process gets. An MJX model: a program whose
    output XLA leaves split over the processes' devices cannot be read back on the host, which
    ended ``diffgcl sweep --local-processes 2`` on the built-in arm."""
    sys.path.insert(0, str(Path(__file__).parent))
    from multiprocess_staged import staged_outputs
    from test_trajopt import SLIDER

    model = tmp_path / "slider.xml"
    model.write_text(SLIDER)
    command = [sys.executable, str(Path(__file__).with_name("multiprocess_staged.py"))]
    rc = launch_local([*command, str(model), str(tmp_path / "out")], 2, timeout_s=600)
    err = capfd.readouterr().err
    assert rc == 0, err[-3000:]
    one = staged_outputs(model)
    for i in range(2):
        got = np.load(tmp_path / f"out_{i}.npz")
        for name, value in one.items():
            np.testing.assert_allclose(got[name], value, rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.slow
def test_two_process_training_resumes_like_one_process(demos_file, tmp_path, capfd):
    """The host runner over 2 processes: crash after 2 of 3 iterations, resume from process 0's
    checkpoint; the state and metrics equal the same crash/resume in one process × 2 devices to
    float64 rounding (1e-12 of each array's largest entry, or absolute below 1). Not bitwise,
    unlike the sweep above: the controllers' gains differed by up to 6e-15 relative, entries
    near zero by 4e-16 (measured; whether the layouts' programs or the resume round differently
    was not traced), where a wrong resume would differ in the leading digits."""
    one, two = tmp_path / "one.npz", tmp_path / "two.npz"
    _one_process_two_devices("train", demos_file, str(one), "--run-dir", str(tmp_path / "r1"))
    command = [sys.executable, DRIVER, "train", demos_file, str(two), "--run-dir"]
    rc = launch_local(command + [str(tmp_path / "r2")], 2, devices_per_process=1, timeout_s=900)
    out, err = capfd.readouterr()
    assert rc == 0, err[-3000:]
    assert "resumed" in out and "resumed" not in err  # process 0 reports it, process 1 is quiet
    assert sorted(p.name for p in (tmp_path / "r2").iterdir()) == ["checkpoint.npz"]
    _assert_same_npz(one, two, rtol=1e-12)
