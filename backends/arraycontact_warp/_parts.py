"""Launches over independent threads, split on the CPU into parts run at once (Warp runs a
CPU launch on one core and releases the GIL): the per-slave kernels and the trees' builds."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

#: Warp runs a CPU launch on one core, releasing the GIL: on the CPU the per-slave kernels run
#: in this many parts at once, one thread each (slaves are independent; a part is a run of
#: the slaves' order, so its threads' neighbours stay neighbours). 2 cores: 1.8x on a kernel.
CPU_PARTS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
#: Fewer threads than this a part: one launch (a thread's start costs more than their work).
MIN_PART = 512
_pool = None
#: (kernel, argument types) launched once whole in the calling thread: its overload is
#: compiled and loaded, so threads may launch it.
_loaded = set()


def launch(kernel, n, inputs, outputs, dev, order=None, first=None):
    """Launch a kernel over n independent threads (the slaves, a tree's items). inputs[order]:
    the order the threads take (a part takes its slice), or inputs[first]: the first of the
    part (its threads take first + t)."""
    global _pool
    dev = wp.get_device(dev)
    if dev.is_cuda:
        wp.launch(kernel, n, inputs=inputs, outputs=outputs, device=dev)
        return
    key = (kernel, tuple(type(v) for v in inputs))
    if CPU_PARTS < 2 or n < MIN_PART * CPU_PARTS or key not in _loaded:
        wp.launch(kernel, n, inputs=inputs, outputs=outputs, device=dev)
        _loaded.add(key)
        return
    kernel.module.load(dev)  # another kernel's new overload may have made the module stale
    if _pool is None:
        _pool = ThreadPoolExecutor(CPU_PARTS, thread_name_prefix="arraycontact-warp")
    cuts = np.linspace(0, n, CPU_PARTS + 1).astype(int)
    jobs = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        part = list(inputs)
        if order is not None:
            part[order] = inputs[order][a:b]
        else:
            part[first] = int(a)
        jobs.append(
            _pool.submit(wp.launch, kernel, int(b - a), inputs=part, outputs=outputs, device=dev)
        )
    for j in jobs:
        j.result()
