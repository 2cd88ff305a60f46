"""Run a Python script in a subprocess that sees two (forced) XLA:CPU host devices."""

from __future__ import annotations

import subprocess
import sys

from _subprocess import ROOT, checkout_env


def run_on_two_cpu_devices(script: str, timeout: float | None = None, forced: bool = True) -> None:
    """Run ``script`` in a fresh Python with the checkout on ``PYTHONPATH``; fail the test with
    the end of its stderr when it exits non-zero. ``forced``: with
    ``--xla_force_host_platform_device_count=2`` (the flag must be set before JAX starts, hence
    the subprocess); otherwise the script sets up its devices itself (``use_cpu_devices``).
    ``PJRT_NPROC`` is removed from the environment: each script decides the pool size."""
    env = checkout_env("PJRT_NPROC", "NPROC")
    if forced:
        env["XLA_FLAGS"] = (
            env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
        ).strip()
    proc = subprocess.run(
        [sys.executable, "-c", script],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
