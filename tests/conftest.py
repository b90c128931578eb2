import gc
import hashlib
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import arraycontact as ac
from arraycontact.reference import _closest_on_faces

BACKENDS = ["numpy", "jax"]

# JAX run strictly: an implicit broadcast across ranks or an implicit dtype promotion (a silent
# float32 -> float64) in a kernel is a test failure, not a slowdown a user finds.
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

# XLA's cheaper CPU compilation: the suite's time is mostly XLA compiling programs that then run
# for milliseconds. Optimisation level 0 took a quarter off it; the legacy CPU emitters compile
# curved-face programs in half the time of the fusion emitters and run them as fast. The
# benchmarks and users compile with the defaults, and the answers checked do not depend on it.
# XLA aborts the process on a flag it does not know (flags come and go between jaxlib
# versions), so they are tried in a child first. Read when the first backend starts, so after
# `import jax` is early enough; the xdist workers and the suite's child processes inherit them.
_CHEAP_XLA = [
    "--xla_backend_optimization_level=0",
    "--xla_llvm_disable_expensive_passes=true",
    "--xla_cpu_use_fusion_emitters=false",
]


def _cheap_xla_flags():
    flags = os.environ.get("XLA_FLAGS", "")
    if all(f in flags.split() for f in _CHEAP_XLA):
        return
    flags = " ".join([flags, *_CHEAP_XLA]).strip()
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    if subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True).returncode == 0:
        os.environ["XLA_FLAGS"] = flags


_cheap_xla_flags()


def _declare_warp_kernels():
    """Every Warp kernel overload declared before any launch, as the warm-up does
    (tests/warp_warmup.py): a worker's modules are then the ones the warm-up compiled, whatever
    mix of elements and precisions its tests launch (else each new mix compiles a module
    again)."""
    from arraycontact._backends import quiet_warp

    quiet_warp()  # before arraycontact_warp imports Warp
    from arraycontact_warp._real import precision

    for dtype in ("float32", "float64"):
        precision(dtype).declare_all()


_declare_warp_kernels()


def _maps():
    with open("/proc/self/maps") as f:
        return sum(1 for _ in f)


@pytest.fixture(autouse=True, scope="module")
def _release_xla_programs():
    """Each compiled XLA CPU program holds memory maps until its cache entry goes; a process
    past the kernel's vm.max_map_count (65530 by default) crashes in the next compilation (a
    segfault, not an error: README, "Many compilations in one process"). One worker runs half
    the suite, so the programs are released at the end of a test file once the maps pass an
    eighth of the limit (not after every file: later files reuse many of the same programs),
    and the count is checked to stay far from the limit."""
    yield
    if not os.path.exists("/proc/self/maps"):
        jax.clear_caches()
        return
    with open("/proc/sys/vm/max_map_count") as f:
        limit = int(f.read())
    if _maps() > limit // 8:
        jax.clear_caches()
        gc.collect()
    assert _maps() < limit // 4, f"{_maps()} memory maps after the module (limit {limit})"


def pytest_sessionstart(session):
    """Warp's CPU kernels compiled in a child process first (tests/warp_warmup.py), once: by
    pytest-xdist's controller, not by each worker. Not with `-n 0`: one process compiles what
    it uses anyway (on a GPU machine the warm-up would compile every module for the GPU
    first)."""
    if hasattr(session.config, "workerinput") or not getattr(
        session.config.option, "numprocesses", None
    ):
        return
    import subprocess
    import sys
    from pathlib import Path

    here = Path(__file__).parent
    # One process a precision, both at once: their kernels are in modules of their own (a cold
    # kernel cache: 97 -> 50 s on the 2-core machine).
    jobs = [
        subprocess.Popen(
            [sys.executable, str(here / "warp_warmup.py"), dtype],
            cwd=here.parent,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for dtype in ("float32", "float64")
    ]
    for j in jobs:
        err = j.communicate()[1]
        if j.returncode != 0:
            raise RuntimeError("compiling the Warp kernels failed:\n" + err[-4000:])


@pytest.fixture(params=["node tree", "face walk"])
def node_search(request, monkeypatch):
    """Both ways a Warp exact plan finds the closest node, on this device: a node tree and
    kernel of its own (a GPU's way) or the face scan's walk (the CPU's), each precision's."""
    walk = request.param == "face walk"
    set_node_search(monkeypatch, walk)
    return walk


def set_node_search(monkeypatch, walk: bool):
    from arraycontact_warp import _real

    for dtype in ("float32", "float64"):
        monkeypatch.setattr(_real.precision(dtype), "NODES_IN_FACE_SCAN", {0: walk, 1: walk})


@pytest.fixture(params=BACKENDS)
def backend(request):
    return request.param


_REFERENCES = {}


def reference(slave, master):
    """The brute-force reference of (slave, master), computed once per session: the back-end
    parametrisations of a test share it (on curved faces it takes most of a test's time)."""
    slave = np.ascontiguousarray(slave, float)
    key = hashlib.sha1(
        b"".join(
            [
                slave.tobytes(),
                master.points.tobytes(),
                np.ascontiguousarray(master.faces).tobytes(),
                master.element.name.encode(),
            ]
        )
    ).hexdigest()
    if key not in _REFERENCES:
        _REFERENCES[key] = ac.reference.closest_points(slave, master)
    return _REFERENCES[key]


def assert_matches_reference(c, slave, master, ref=None, *, dtype=np.float64):
    """`c` (a Contacts) equals the brute-force reference on (slave, master).

    Same active set (up to slaves whose distance is within the tolerance of d_max), distances
    within 1e-12 relative (float64) or 1e-5 of the longest edge (float32), and a face that the
    reference finds at the minimal distance; in float64 the very face the reference's tie rule
    picks (smallest id among equidistant faces)."""
    slave = np.asarray(slave, float)
    ref = ref if ref is not None else reference(slave, master)
    L = master.longest_edge
    tol = 1e-12 * max(L, 1) if dtype == np.float64 else 1e-5 * L
    border = np.abs(ref.distance - c.d_max) <= tol
    want = ref.distance <= c.d_max
    assert np.array_equal(c.active[~border], want[~border]), (
        f"{(c.active != want)[~border].sum()} slaves differ in activity"
    )
    a = c.active & want
    if not a.any():
        return ref
    err = np.abs(c.distance[a] - ref.distance[a])
    rel = err / np.maximum(ref.distance[a], L) if dtype == np.float64 else err / L
    lim = 1e-12 if dtype == np.float64 else 1e-5
    assert rel.max() <= lim, f"distance error {rel.max():.3g} > {lim}"
    # The chosen face holds a point at the minimal distance (evaluated by the reference).
    e = master.element
    _, d2 = _closest_on_faces(e, slave[a], master.points[master.faces[c.face[a]]])
    derr = np.abs(np.sqrt(d2) - ref.distance[a]) / L
    assert derr.max() <= (1e-10 if dtype == np.float64 else 1e-5), f"face off by {derr.max():.3g}"
    # The point lies on the chosen face at xi, and the gap's sign agrees with the reference's.
    x, _ = ac._elements.interpolate(e, master.points[master.faces[c.face[a]]], c.xi[a])
    assert np.abs(x - c.point[a]).max() <= (1e-9 if dtype == np.float64 else 2e-5) * max(L, 1)
    gtol = 1e-9 * L if dtype == np.float64 else 2e-5 * L
    gerr = np.abs(c.gap[a] - ref.gap[a])
    assert gerr.max() <= gtol, f"gap off by {gerr.max():.3g}"
    if dtype == np.float64:
        same = c.face[a] == ref.face[a]
        assert same.all(), f"{(~same).sum()} faces differ from the tie rule's choice"
    return ref


#: The test files of about a minute or more on the 2-core machine, longest first (forty-ninth
#: session, test time a file in one run: test_detect 207 s, test_swept 181, test_sharding_devices
#: 180 (one child process of 158 s), test_jax_gradients 174 ... test_grid and test_node_mode
#: 53-54). Handed out longest first (pyproject's --no-loadscope-reorder: pytest-xdist would
#: order the files by their number of tests, which put the two-test sharding files last), the
#: two workers end within a short file of each other.
LONGEST = (
    "test_detect",
    "test_swept",
    "test_sharding_devices",
    "test_jax_gradients",
    "test_jax.py",
    "test_self_contact",
    "test_sharding.py",
    "test_projection",
    "test_stress",
    "test_grid",
    "test_node_mode",
    "test_warp.py",
    "test_invariance",
)


def pytest_collection_modifyitems(config, items):
    """The longest files first: pytest-xdist (--dist loadfile) hands out whole files in this
    order, so the two workers fill the short ones in at the end instead of one of them
    waiting on a long file there."""

    def rank(item):
        return next((i for i, f in enumerate(LONGEST) if f in item.nodeid), len(LONGEST))

    items.sort(key=rank)
