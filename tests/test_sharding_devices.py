"""The other half of the JAX sharded plan's checks on four CPU devices (see
test_sharding.run_sharding_checks), and the sharded plan over two processes
(jax.distributed, multihost_check.py)."""

import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from test_sharding import HALF, run_sharding_checks


def test_jax_sharded_plan_on_four_cpu_devices_overflow_inputs_and_errors():
    run_sharding_checks(f"not ({HALF})", 10)


def test_two_processes_of_two_devices_equal_one_device():
    """Multi-host as JAX runs it: two processes (jax.distributed, gloo on the CPU), the plan
    over the four devices of both, each process giving its own rows; each process checks the
    contacts and gradients against its own one-device plan."""
    with socket.socket() as sock:  # a free port for the coordinator
        sock.bind(("localhost", 0))
        port = sock.getsockname()[1]
    script = Path(__file__).parent / "multihost_check.py"
    logs = [tempfile.TemporaryFile("w+") for _ in range(2)]  # (a pipe could fill and block)
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(pid), str(port)],
            stdout=log,
            stderr=subprocess.STDOUT,
            text=True,
            env=dict(os.environ),  # conftest's cheaper XLA optimisation flags included
        )
        for pid, log in enumerate(logs)
    ]
    # A process that fails leaves the other waiting in a collective: stop both then.
    deadline = time.monotonic() + 300
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        if any(p.poll() not in (None, 0) for p in procs):
            break
        time.sleep(0.2)
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait()
    for pid, (p, log) in enumerate(zip(procs, logs)):
        log.seek(0)
        out = log.read()
        assert p.returncode == 0, out[-4000:]
        assert f"process {pid}: equal" in out
