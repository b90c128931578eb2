"""One process of a two-process JAX run (jax.distributed on the CPU, gloo collectives, two
devices a process): the sharded plan over the four devices of both processes, its inputs made
from each process's own rows (`jax.make_array_from_callback`), equals this process's
one-device plan, contacts and gradients. Run by test_sharding.py:

    python tests/multihost_check.py PROCESS_ID PORT
"""

import os
import sys

os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2 " + os.environ.get(
    "XLA_FLAGS", ""
)
import jax  # noqa: E402

jax.config.update("jax_platforms", "cpu")
jax.config.update("jax_cpu_collectives_implementation", "gloo")
jax.config.update("jax_enable_x64", True)
pid, port = int(sys.argv[1]), int(sys.argv[2])
jax.distributed.initialize(f"localhost:{port}", num_processes=2, process_id=pid)

import arraycontact_jax as acj  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.experimental import multihost_utils  # noqa: E402
from jax.sharding import Mesh, NamedSharding  # noqa: E402
from jax.sharding import PartitionSpec as P  # noqa: E402

from arraycontact import scenes  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from sharding_checks import _loss, _same  # noqa: E402

assert jax.process_count() == 2 and jax.device_count() == 4 and jax.local_device_count() == 2
s = scenes.graded_surfaces(2**10, ratio=30.0, seed=6)
mesh = Mesh(np.array(jax.devices()), ("space",))
rows = NamedSharding(mesh, P("space"))


def value_and_grads(p, slave, pts):
    # The plan goes in as an argument (a pytree): JAX does not let a jitted function close
    # over arrays that span other processes' devices.
    def f(p, slave, pts):
        c = acj.detect(p, slave, pts)
        return _loss(c), c

    return jax.jit(jax.value_and_grad(f, argnums=(1, 2), has_aux=True))(p, slave, pts)


def mine(a):  # a global array of which this process gives its own rows
    return jax.make_array_from_callback(a.shape, rows, lambda i: a[i])


(v, c), g = value_and_grads(acj.plan(s.master, s.slave, mesh=mesh), mine(s.slave),
                            mine(s.master.points))  # fmt: skip
c = jax.tree.map(lambda a: np.asarray(multihost_utils.process_allgather(a, tiled=True)), c)
g = [np.asarray(multihost_utils.process_allgather(a, tiled=True)) for a in g]
one = acj.plan(s.master, s.slave)  # this process's first device
(v1, r), g1 = value_and_grads(one, jnp.asarray(s.slave), jnp.asarray(s.master.points))
_same(c, r)
assert np.isclose(float(v), float(v1), rtol=1e-12)
for a, b in zip(g, g1):
    scale = float(np.abs(np.asarray(b)).max())
    assert np.allclose(a, np.asarray(b), rtol=1e-10, atol=1e-10 * scale)
assert int(np.asarray(r.active).sum()) > 0.5 * len(s.slave)
print(f"process {pid}: equal", flush=True)
jax.distributed.shutdown()
