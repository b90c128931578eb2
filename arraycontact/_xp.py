"""The few array operations whose spelling differs between NumPy and jax.numpy.

Capacities: NumPy runs eagerly and may size arrays from data (`size=None`); JAX needs a static
`size`. Every helper takes that size and reports the true count, so callers can flag overflow.
"""

from __future__ import annotations

import math

import numpy as np


def is_numpy(xp):
    return xp is np


def lead(xp, a, ndim):
    """`a` with leading axes of length 1 up to `ndim` axes: broadcasts written out (the tests
    run JAX with implicit rank promotion turned into an error)."""
    a = xp.asarray(a)
    return xp.reshape(a, (1,) * (ndim - a.ndim) + tuple(a.shape))


def norm(xp, v):
    """Euclidean norm over the last axis (einsum on NumPy: a reduce over an axis of 3 is slow)."""
    if is_numpy(xp):
        return np.sqrt(np.einsum("...k,...k->...", v, v))
    return xp.sqrt(xp.sum(v * v, -1))


def einsum(xp, spec, a, b):
    """Two-operand einsum (`spec` like "...ka,...k->...a", an optional leading "..." per
    operand) over small named axes. JAX: a broadcast product and a sum, which XLA fuses with
    the arithmetic around it; jnp.einsum lowers to dot_general, whose batched tiny products
    run as a batched GEMM on a GPU and a loop of small matrix products on the CPU (the quad4
    projection's Newton iterations at 2^20 slaves: 268 ms on an H200, 56x the Warp search)."""
    if is_numpy(xp):
        return np.einsum(spec, a, b)
    ins, out = spec.split("->")
    ops = [(s.removeprefix("..."), x) for s, x in zip(ins.split(","), (a, b))]
    out = out.removeprefix("...")
    summed = [c for c in dict.fromkeys(ins.replace(",", "").replace(".", "")) if c not in out]
    target = list(out) + summed
    batch = max(x.ndim - len(s) for s, x in ops)
    terms = []
    for s, x in ops:
        nb = x.ndim - len(s)
        # The operand's named axes in the target's order, then length-1 axes for the rest.
        x = xp.transpose(x, list(range(nb)) + [nb + s.index(c) for c in target if c in s])
        shape = list(x.shape[:nb])
        it = iter(x.shape[nb:])
        shape += [next(it) if c in s else 1 for c in target]
        terms.append(xp.reshape(x, [1] * (batch - nb) + shape))
    prod = terms[0] * terms[1]
    return xp.sum(prod, tuple(range(prod.ndim - len(summed), prod.ndim))) if summed else prod


def rows_dot(xp, x, a):
    """x @ a.T for x [..., k] and a small constant matrix a [m, k] (JAX: fused, as einsum)."""
    if is_numpy(xp):
        return x @ a.T
    return einsum(xp, "...k,mk->...m", x, a)


def segment_min(xp, data, ids, n, sorted=False, slots=None):
    """Minimum of `data` per segment id (the dtype's largest value for an empty segment).
    sorted: the ids are non-decreasing (a reduce over runs on NumPy, a hint on JAX). slots:
    the ids are each segment's `slots` rows in turn (reduced as columns, no scatter)."""
    if slots is not None:  # (column by column: see _select.select_closest)
        rows = data.reshape(n, slots)
        out = rows[:, 0]
        for j in range(1, slots):
            out = xp.minimum(out, rows[:, j])
        return out
    if is_numpy(xp):
        big = np.inf if data.dtype.kind == "f" else np.iinfo(data.dtype).max
        out = np.full(n, big, data.dtype)
        if sorted and len(ids):
            starts = np.r_[0, np.nonzero(np.diff(ids))[0] + 1]
            out[ids[starts]] = np.minimum.reduceat(data, starts)
        else:
            np.minimum.at(out, ids, data)
        return out
    import jax

    return jax.ops.segment_min(data, ids, num_segments=n, indices_are_sorted=sorted)


def segment_sum(xp, data, ids, n):
    """Sum of `data` rows per segment id (zero for an empty segment)."""
    if is_numpy(xp):
        if data.ndim <= 2 and data.dtype.kind == "f":  # bincount: 10-20x np.add.at's speed
            cols = data.reshape(len(data), math.prod(data.shape[1:])).T  # (no -1: rows may be 0)
            out = np.stack([np.bincount(ids, c, minlength=n) for c in cols], -1)
            return out.astype(data.dtype).reshape((n,) + data.shape[1:])
        out = np.zeros((n,) + data.shape[1:], data.dtype)
        np.add.at(out, ids, data)
        return out
    import jax

    return jax.ops.segment_sum(data, ids, num_segments=n)


def compact(xp, mask, size):
    """Indices of the true entries of `mask` (padded with 0 up to `size`) and their count."""
    count = xp.sum(mask.astype(np.int32))
    if is_numpy(xp):
        idx = np.nonzero(mask)[0]
        if size is not None:
            idx = np.pad(idx[:size], (0, max(size - len(idx), 0)))
        return idx, count
    return xp.nonzero(mask, size=size, fill_value=0)[0], count


def expand(xp, counts, size):
    """Enumerate segments of the given lengths as flat pairs.

    Returns, for k in range(size): the segment of k, its rank within the segment, whether k is
    below the total, and the total (which may exceed `size`: overflow)."""
    ends = xp.cumsum(counts)
    total = ends[-1] if counts.shape[0] else xp.asarray(0)
    if size is None:  # eager and exact: a repeat is linear where a search is not
        seg = np.repeat(np.arange(len(counts)), counts)
        rank = np.arange(len(seg)) - np.repeat(ends - counts, counts)
        return seg, rank, np.ones(len(seg), bool), total
    k = xp.arange(size, dtype=counts.dtype)
    seg = xp.searchsorted(ends, k, side="right")
    seg = xp.minimum(seg, max(counts.shape[0] - 1, 0))
    rank = k - (ends[seg] - counts[seg]) if counts.shape[0] else k
    return seg, rank, k < total, total


def fori(xp, n, body, state, stop=None):
    """state = body(i, state) for i in range(n): a Python loop on NumPy, `lax.fori_loop` on JAX
    (one traced body instead of n unrolled copies keeps compile times short). stop(state): a
    scalar saying the remaining iterations would change nothing (every lane done): the loop
    ends there (`lax.while_loop` on JAX)."""
    if is_numpy(xp):
        for i in range(n):
            if stop is not None and stop(state):
                break
            state = body(i, state)
        return state
    from jax import lax

    if stop is None:
        return lax.fori_loop(0, n, body, state)
    return lax.while_loop(
        lambda c: (c[0] < n) & ~stop(c[1]), lambda c: (c[0] + 1, body(c[0], c[1])), (0, state)
    )[1]
