"""Launches over independent threads, split on the CPU into parts run at once (Warp runs a
CPU launch on one core and releases the GIL): the per-slave kernels and the trees' builds.
And independent chains of launches run at once on the CPU (the topology's). On the CPU Warp's
atomics are plain read-modify-writes: a kernel that uses them is never split."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from functools import partial

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


def load(kernel, dev):
    """Load kernel's module on dev as its launches there will, before threads launch its
    kernels (two threads must not compile a module). Warp builds a module once per block size
    and a CPU launch runs blocks of 1, while `Module.load` alone builds the module's default
    256 (on a cold kernel cache that was a second compile of the module, and the threads then
    compiled the stale block-1 build at once: the topology's module three times over)."""
    kernel.module.load(dev, block_dim=1 if dev.is_cpu else None)


def load_at_once(dev, kernels):
    """Load the modules of `kernels` [(kernel, a GPU's block size for it, or None: its module's
    default)] on dev, one thread a module (as Warp's `force_load`: a module's compilation runs
    outside the GIL)."""
    jobs = [
        _get_pool().submit(k.module.load, dev, block_dim=1 if dev.is_cpu else block)
        for k, block in kernels
    ]
    for j in jobs:
        j.result()


def _get_pool():
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(CPU_PARTS, thread_name_prefix="arraycontact-warp")
    return _pool


def concurrently(dev, *chains):
    """Call the functions `chains` (each launching kernels whose modules are loaded, on
    arrays no other chain writes): on the CPU at once, the first in the calling thread; on a
    GPU one after the other (their launches queue on one stream). The `launch`es of a chain
    in the pool run whole (waiting on its parts, it could wait for ever); the first chain's
    are split as anywhere, their parts taken by the pool's threads as the others finish."""
    dev = wp.get_device(dev)
    if dev.is_cuda or CPU_PARTS < 2 or len(chains) < 2:
        for c in chains:
            c()
        return
    jobs = [_get_pool().submit(_in_chain, c) for c in chains[1:]]
    chains[0]()
    for j in jobs:
        j.result()


_chain = threading.local()  # .on: this thread runs a chain of `concurrently`


def _in_chain(c):
    _chain.on = True
    try:
        c()
    finally:
        _chain.on = False


#: A generic kernel's overload by its arguments' kinds (see `_concrete`).
_overloads = {}


def _kind(v):
    return type(v), getattr(v, "dtype", None), getattr(v, "ndim", None)


def _concrete(kernel, args):
    """kernel's overload for these arguments. Warp infers it on every launch of a generic
    kernel (a third of a millisecond for the detection's three on a GPU's host, most of a
    first call on a small scene); the arguments' kinds name it at a tenth of that cost."""
    if not kernel.is_generic:
        return kernel
    key = (kernel, tuple(_kind(v) for v in args))
    k = _overloads.get(key)
    if k is None:
        k = _overloads[key] = kernel._add_normalized_overload(kernel.infer_argument_types(args))
    return k


def _same(a, b) -> bool:
    """Would argument b pack as a does (the same array, struct or value)?"""
    if a is b:
        return True
    if isinstance(a, wp.array) and isinstance(b, wp.array):
        return (a.ptr, a.shape, a.strides, a.dtype) == (b.ptr, b.shape, b.strides, b.dtype)
    if type(a) is not type(b):
        return False
    if isinstance(a, (bool, int, float)) or wp.types.is_value(a) or wp.types.is_vector(a):
        return bool(a == b)
    return False  # a struct: the same object only


def _replay(cmds, kernel, n, args, dev, record_only, block, key=None):
    """kernel's launch through the command recorded in `cmds` (a plan's) under `key` (default
    the kernel), its arguments packed again only where they changed: Warp packs every
    argument of every launch, 50-100 us a launch of the detection's kernels on an H100's
    host, which a first call or a call without a graph pays; a recorded command's launch
    takes about 5."""
    key = kernel if key is None else key
    hit = cmds.get(key)
    if hit is None:
        cmd = wp.launch(kernel, n, inputs=args, device=dev, record_cmd=True, block_dim=block)
        cmds[key] = (cmd, list(args), [n])
    else:
        cmd, old, dim = hit
        for i, (a, b) in enumerate(zip(args, old)):
            if not _same(a, b):
                cmd.set_param_at_index(i, a)
                old[i] = a
        if dim[0] != n:
            cmd.set_dim(n)
            dim[0] = n
    if not record_only:
        cmd.launch()


def replayed(cmds, key, kernel, n, inputs, dev, record_only=False):
    """A launch of one thread grid on a GPU through the command recorded in `cmds` under
    `key` (see _replay; record_only: record it, do not launch); elsewhere, or without cmds,
    a plain launch (record_only: none)."""
    dev = wp.get_device(dev)
    if cmds is not None and dev.is_cuda:
        _replay(cmds, _concrete(kernel, inputs), n, list(inputs), dev, record_only, 256, key)
    elif not record_only:
        wp.launch(kernel, n, inputs=inputs, device=dev)


def launch(
    kernel,
    n,
    inputs,
    outputs,
    dev,
    order=None,
    first=None,
    cmds=None,
    record_only=False,
    cuts=None,
    block=256,
):
    """Launch a kernel over n independent threads (the slaves, a tree's items). inputs[order]:
    the order the threads take (a part takes its slice), or inputs[first]: the first of the
    part (its threads take first + t). cmds: a plan's recorded commands, which a launch in one
    part replays (record_only: record, do not launch). cuts: a plan's dict where a launch in
    parts keeps the cuts that would have balanced its parts' times (`_balanced`), for its next
    launch of this kernel and size; a kernel new to the plan starts from the plan's last cuts
    of its size (where a closest-node kernel runs before the face scan, as it did in every
    one-call detection, its cuts foretell the scan's: at 2^16 36007 and 36855 of 65536 on
    quad4). block: a GPU's threads a block."""
    dev = wp.get_device(dev)
    kernel = _concrete(kernel, [*inputs, *outputs])
    one = dev.is_cuda or CPU_PARTS < 2 or n < MIN_PART * CPU_PARTS or getattr(_chain, "on", 0)
    if cmds is not None and one:
        _replay(cmds, kernel, n, [*inputs, *outputs], dev, record_only, block)
        return
    if record_only:
        return
    if dev.is_cuda:
        wp.launch(kernel, n, inputs=inputs, outputs=outputs, device=dev, block_dim=block)
        return
    key = (kernel, tuple(type(v) for v in inputs))
    if one or key not in _loaded:
        wp.launch(kernel, n, inputs=inputs, outputs=outputs, device=dev)
        _loaded.add(key)
        return
    load(kernel, dev)  # another kernel's new overload may have made the module stale
    at = None if cuts is None else cuts.get((kernel, n), cuts.get(n))
    if at is None or len(at) != CPU_PARTS + 1:
        at = np.linspace(0, n, CPU_PARTS + 1).astype(int)
    times = np.zeros(CPU_PARTS)
    parts = []
    for i, (a, b) in enumerate(zip(at[:-1], at[1:])):
        part = list(inputs)
        if order is not None:
            part[order] = inputs[order][a:b]
        else:
            part[first] = int(a)
        parts.append(partial(_timed, times, i, kernel, int(b - a), part, outputs, dev))
    # The first part in this thread, which would wait idle; the others on the pool's threads,
    # or here too where none has taken them yet (busy with another chain of `concurrently`).
    jobs = [_get_pool().submit(part) for part in parts[1:]]
    parts[0]()
    for job, part in zip(jobs, parts[1:]):
        if job.cancel():
            part()
        else:
            job.result()
    if cuts is not None:
        cuts[(kernel, n)] = cuts[n] = _balanced(at, times)


def _timed(times, i, kernel, n, inputs, outputs, dev):
    t = time.perf_counter()
    wp.launch(kernel, n, inputs=inputs, outputs=outputs, device=dev)
    times[i] = time.perf_counter() - t


def _balanced(at, times):
    """Cuts that would have given the parts equal times, the work spread evenly within each
    part: the slaves' work varies along their order (the quad4 face scan's halves, 2^16: 25
    and 35 ms), and from one step to the next little. Halfway there, so that a change of the
    work's spread does not swing them; each part keeps a quarter of an even share."""
    work = np.concatenate([[0.0], np.cumsum(times)])
    if not work[-1] > 0:
        return at
    even = np.interp(np.linspace(0.0, work[-1], len(at)), work, at)
    new = np.round((even + at) / 2).astype(int)
    least = max(at[-1] // (4 * (len(at) - 1)), 1)
    for i in range(1, len(new) - 1):  # (at[0] = 0 and at[-1] = n stay)
        new[i] = min(max(new[i], new[i - 1] + least), at[-1] - least * (len(new) - 1 - i))
    return new
