"""Compile every Warp CPU kernel the tests use, in a process of its own (conftest runs it
before the suite): the tests then load compiled kernels instead of compiling them beside
XLA's compilations. Warp compiles CPU kernels with an LLVM of its own; in one process with the
suite's many XLA compilations (another LLVM), a later XLA compilation crashed (segfault or
abort in backend_compile, in test_stress) after Warp had compiled there."""

import numpy as np
import warp as wp

import arraycontact as ac
from arraycontact import scenes

wp.config.quiet = True
cases = [scenes.rough_surfaces(2**6), scenes.rough_surfaces(2**6, element="quad4"),
         scenes.rough_layers(2**6, quadratic=True),
         scenes.curved_patch(2, element="quad8", n_slaves=20),
         scenes.curved_patch(2, element="quad9", n_slaves=20)]
for s in cases:
    for dtype in ("float32", "float64"):
        for mode in ("exact", "node"):
            ac.detect(s.slave, s.master, backend="warp", dtype=dtype, mode=mode)
