"""The other half of the JAX sharded plan's checks on four CPU devices (see
test_sharding.run_sharding_checks), and the sharded plan over two processes
(jax.distributed, multihost_check.py)."""

import os
import socket
import subprocess
import sys
from pathlib import Path

from test_sharding import HALF, run_sharding_checks


def test_jax_sharded_plan_on_four_cpu_devices_overflow_inputs_and_errors():
    run_sharding_checks(f"not ({HALF})", 8)


def test_two_processes_of_two_devices_equal_one_device():
    """Multi-host as JAX runs it: two processes (jax.distributed, gloo on the CPU), the plan
    over the four devices of both, each process giving its own rows; each process checks the
    contacts and gradients against its own one-device plan."""
    with socket.socket() as sock:  # a free port for the coordinator
        sock.bind(("localhost", 0))
        port = sock.getsockname()[1]
    script = Path(__file__).parent / "multihost_check.py"
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(pid), str(port)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=dict(os.environ),  # conftest's cheaper XLA optimisation flags included
        )
        for pid in range(2)
    ]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    for pid, (p, out) in enumerate(zip(procs, outs)):
        assert p.returncode == 0, out[-4000:]
        assert f"process {pid}: equal" in out
