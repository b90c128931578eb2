"""Compile every Warp CPU kernel the tests use, once, in a process of its own (conftest runs it
before the suite): the two pytest-xdist workers then load compiled kernels instead of both
compiling them. `python warp_warmup.py float32` compiles one precision's kernels (their
modules are apart: conftest runs both precisions at once, one process a core)."""

import sys

from arraycontact_warp._real import precision

import arraycontact as ac
from arraycontact import scenes
from arraycontact._backends import quiet_warp

quiet_warp()
dtypes = sys.argv[1:] or ["float32", "float64"]
for dtype in dtypes:  # every kernel overload first: each module compiles once (conftest too)
    precision(dtype).declare_all()
cases = [
    scenes.rough_surfaces(2**6),
    scenes.rough_surfaces(2**6, element="quad4"),
    scenes.rough_layers(2**6, quadratic=True),
    scenes.curved_patch(2, element="quad8", n_slaves=20),
    scenes.curved_patch(2, element="quad9", n_slaves=20),
]
for s in cases:
    for dtype in dtypes:
        for mode in ("exact", "node"):
            ac.detect(s.slave, s.master, backend="warp", dtype=dtype, mode=mode)
# Self-contact's kernels (another specialisation of the scans): tri3 and the other elements.
for element in ("tri3", "quad4"):
    s = scenes.two_bodies(200, element=element)
    for dtype in dtypes:
        for mode in ("exact", "node"):
            ac.detect_self(s.master, backend="warp", dtype=dtype, mode=mode, d_max=0.65)
# Swept detection's kernels: the tri3 specialisation and the other elements.
for element, n in (("tri3", 2**6), ("quad4", 2**6), ("tri6", 2**6)):
    st = scenes.closing_rough_surfaces(n, element=element)
    for dtype in dtypes:
        ac.detect_swept(
            st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="warp", dtype=dtype
        )
