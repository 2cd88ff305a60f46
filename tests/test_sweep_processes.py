"""``cdra-jax sweep --processes N``: the chunks shared out over a ``jax.distributed`` group.

The sweeps run as ``cdra-jax`` subprocesses (a group must start before JAX does, which the test
process has already started): one small cell (m = 5, the paper solver, 16 trials in chunks of 4,
10 held-out states), so that each process compiles one program (or loads it from the test run's
compilation cache).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _subprocess import checkout_env

from cdra_jax import cli
from cdra_jax.distributed import Group, GroupError, free_port, parse_coordinator

SWEEP = [
    "sweep",
    "--noise-pos",
    "0.08",
    "--noise-rot",
    "0.001",
    "--poses",
    "5",
    "--solvers",
    "paper",
    "--trials",
    "16",
    "--chunk",
    "4",
    "--verify",
    "10",
    "--no-progress",
    "--timeout",
    "120",
]


def _start(out: Path, *extra: str) -> subprocess.Popen:
    env = checkout_env("PJRT_NPROC", "NPROC", "JAX_NUM_CPU_DEVICES")
    argv = [sys.executable, "-m", "cdra_jax.cli", *SWEEP, "--out", str(out), *extra]
    return subprocess.Popen(
        argv, env=env, cwd=out.parent, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def _finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, out, err


def _sweep(out: Path, *extra: str) -> str:
    code, stdout, stderr = _finish(_start(out, *extra))
    assert code == 0, stderr[-3000:]
    return stdout


def _rows(path: Path) -> list[str]:
    """The table without its comment lines (the run's seconds, process count)."""
    return [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]


@pytest.fixture(scope="module")
def one_process(tmp_path_factory) -> list[str]:
    out = tmp_path_factory.mktemp("one") / "t.csv"
    _sweep(out)
    return _rows(out)


def test_two_local_processes_give_the_one_process_table(tmp_path, one_process):
    out = tmp_path / "t.csv"
    stdout = _sweep(out, "--processes", "2")
    assert _rows(out) == one_process  # bit for bit: every float is written exactly (repr)
    assert len(one_process) == 1 + 16
    assert "# processes: 2" in out.read_text()
    assert "process 1" not in stdout  # the worker's report is not repeated
    assert not (tmp_path / ".t.csv.chunks").exists()


@pytest.mark.slow
def test_processes_started_by_hand_give_the_same_table(tmp_path, one_process):
    out = tmp_path / "t.csv"
    group = ["--processes", "2", "--coordinator", f"localhost:{free_port()}"]
    worker = _start(out, *group, "--process-id", "1")
    stdout = _sweep(out, *group, "--process-id", "0")
    code, worker_out, stderr = _finish(worker)
    assert code == 0, stderr[-3000:]
    assert worker_out.strip() == "sweep: process 1 of 2 wrote its chunks"
    assert "16 trials" in stdout
    assert _rows(out) == one_process


def _child(proc: subprocess.Popen) -> int:
    """The first child process of ``proc`` (the worker it started), waiting for it."""
    path = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    for _ in range(1200):
        kids = path.read_text().split() if path.exists() else []
        if kids:
            return int(kids[0])
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        time.sleep(0.05)
    raise AssertionError("no worker process started")


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc")
def test_a_dead_worker_is_named_and_the_sweep_resumes(tmp_path, one_process):
    out = tmp_path / "t.csv"
    chunks = tmp_path / ".t.csv.chunks"
    proc = _start(out, "--processes", "2")
    worker = _child(proc)
    while not (chunks / "settings.json").exists():  # both connected: the sweep has begun
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        time.sleep(0.05)
    os.kill(worker, signal.SIGKILL)
    code, _, stderr = _finish(proc)
    assert code == cli.EXIT_ERROR, stderr[-3000:]
    error = [ln for ln in stderr.splitlines() if ln.startswith("error: ")]
    assert len(error) == 1, stderr[-3000:]
    # chunk g goes to process g mod 2: process 1's are rows 4-7 and 12-15
    for text in ("process 1 exited (status -9)", "2 chunk(s) missing", "rows 4-7 of process 1"):
        assert text in error[0], error
    assert "rows 12-15 of process 1" in error[0] and "rows 0-3" not in error[0], error
    assert not out.exists()
    kept = {p.name: p.stat().st_mtime_ns for p in chunks.glob("*.npz")}
    assert sorted(kept) == ["cell0000-start0000000000.npz", "cell0000-start0000000008.npz"]

    stdout = _sweep(out, "--processes", "2")
    assert _rows(out) == one_process
    assert "16 trials" in stdout


def test_argument_errors_before_any_work(tmp_path, capsys):
    out = str(tmp_path / "t.csv")
    cases = [
        (["--processes", "0"], "--processes must be an integer in [1, 1024], got 0"),
        (["--processes", "2", "--coordinator", "node0"], "--coordinator must be HOST:PORT"),
        (["--processes", "2", "--coordinator", "node0:0"], "got 'node0:0'"),
        (["--processes", "2", "--coordinator", ":80"], "--coordinator must be HOST:PORT"),
        (
            ["--processes", "2", "--coordinator", "node0:1234", "--process-id", "2"],
            "--process-id must be in [0, 1] (--processes = 2), got 2",
        ),
        (["--processes", "2", "--process-id", "1"], "--process-id needs --coordinator"),
        (["--coordinator", "node0:1234"], "--coordinator is for --processes > 1"),
        (["--processes", "2", "--timeout", "0"], "--timeout must be a number in [1, 1e+06]"),
    ]
    for extra, expected in cases:
        assert cli.main([*SWEEP[:-2], "--out", out, *extra]) == cli.EXIT_ERROR, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
        assert expected in err[0], (extra, err)
    assert list(tmp_path.iterdir()) == []


def test_library_errors():
    from cdra_jax.sweeps import run_sweep
    from cdra_jax.workflows import sweep

    with pytest.raises(ValueError, match="needs checkpoint"):
        sweep(None, [0.08], [1e-3], [5], trials=1, processes=2)
    with pytest.raises(ValueError, match="a group on this machine needs worker_command"):
        from cdra_jax.distributed import start_group

        start_group(2)
    group = Group(1, 2, "localhost:1", client=None)
    with pytest.raises(ValueError, match="several processes needs checkpoint"):
        run_sweep(None, [(0.08, 1e-3)], [5], trials=1, group=group)  # type: ignore[arg-type]
    assert parse_coordinator("[::1]:1234") == ("[::1]", 1234)
    assert 0 < free_port() < 65536


class _Store:
    """A stand-in for jax.distributed's key-value store."""

    def __init__(self, values=None):
        self.values = dict(values or {})

    def key_value_try_get(self, key):
        import jax

        if key not in self.values:
            raise jax.errors.JaxRuntimeError(f"NOT_FOUND: {key}")
        return self.values[key]


def test_process_0_names_a_failed_silent_or_stalled_process(monkeypatch):
    import cdra_jax.distributed as dist

    failed = Group(0, 3, "h:1", _Store({"cdra_jax/group/end/1": "done"}), timeout=5)
    failed.client.values["cdra_jax/group/end/2"] = "error: checkpoint x: other arguments"
    with pytest.raises(GroupError, match="process 2 stopped with error: checkpoint x"):
        failed.wait_for_others(lambda: 0, poll=0.01)

    monkeypatch.setattr(dist, "HEARTBEAT_TIMEOUT", 0.2)
    silent = Group(0, 2, "h:1", _Store(), timeout=5)
    with pytest.raises(GroupError, match="process 1 sent no heartbeat for 0.2 s"):
        silent.wait_for_others(lambda: 0, poll=0.01)

    class Beating(_Store):  # alive (the heartbeat advances at every look), never done
        def key_value_try_get(self, key):
            if "/beat/" in key:
                self.values[key] = str(int(self.values.get(key, 0)) + 1)
            return super().key_value_try_get(key)

    stalled = Group(0, 2, "h:1", Beating(), timeout=0.3)
    t0 = time.monotonic()
    with pytest.raises(GroupError, match=r"no progress for 0.3 s; process\(es\) 1 not done"):
        stalled.wait_for_others(lambda: 0, poll=0.01)
    assert time.monotonic() - t0 < 5

    done = Group(0, 2, "h:1", _Store({"cdra_jax/group/end/1": "done"}), timeout=0.3)
    done.wait_for_others(lambda: 0, poll=0.01)  # returns


def test_a_process_that_never_connects_ends_the_wait(tmp_path):
    port = free_port()
    proc = _start(
        tmp_path / "t.csv",
        *("--processes", "2", "--process-id", "0", "--coordinator", f"localhost:{port}"),
        *("--timeout", "2"),
    )
    code, _, stderr = _finish(proc)
    assert code == cli.EXIT_ERROR, stderr[-3000:]
    assert "error: process 0: the 2 processes did not all connect" in stderr, stderr[-3000:]


def test_a_group_on_this_machine_shares_its_cores():
    from cdra_jax.cli.sweep import TRIALS_PER_EXTRA_DEVICE, default_cpu_devices
    from cdra_jax.parallel import schedulable_cores

    cores = schedulable_cores()
    assert default_cpu_devices(10**12, 2) == max(1, cores // 2)
    assert default_cpu_devices(10**12, 4 * cores) == 1
    assert default_cpu_devices(TRIALS_PER_EXTRA_DEVICE - 1, 1) == 1
