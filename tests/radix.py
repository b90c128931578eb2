"""Test helpers for the trees' groups (arraycontact._grid.grouping, arraycontact_warp._grid):
an independent top-down split of the keys' radix tree, and point sets that stress it."""

import numpy as np

from arraycontact import scenes

W = 8


def radix_groups(keys, units):
    """Independent of the build: the binary radix tree of the sorted keys (equal keys told
    apart by their positions), split top-down at the highest differing bit; `units`: runs of
    positions [a, b) that are nodes of it. Returns the largest nodes holding at most W units."""
    comp = [(int(k) << 32) | p for p, k in enumerate(keys)]
    starts = sorted(a for a, _ in units)
    ends = sorted(b for _, b in units)
    out = []

    def split(a, b):
        inside = np.searchsorted(ends, b, "right") - np.searchsorted(starts, a, "left")
        if inside <= W:
            out.append((a, b))
            return
        bit = (comp[a] ^ comp[b - 1]).bit_length() - 1
        cut = next(p for p in range(a, b) if comp[p] >> bit & 1)
        split(a, cut)
        split(cut, b)

    split(0, len(keys))
    return sorted(out)


def grid_points(kind, rng):
    if kind == "fine_patch":  # a graded mesh's nodes (sizes 1 to 1000)
        return scenes.fine_patch(12).master.points
    if kind == "clusters":  # clusters over six decades of size in 3D: groups of 3.5 on average
        c = rng.uniform(0, 1, (12, 3))
        r = 10.0 ** rng.uniform(-6, 0, (3000, 1))
        return c[rng.integers(0, 12, 3000)] + r * rng.normal(size=(3000, 3))
    if kind == "caterpillar":  # each radix node peels one point: groups of one
        s = 2.0 ** -np.arange(40)
        rows = [np.stack([s, s * 0 + y, s * 0], 1) for y in (0.0, 1.0)]
        return np.concatenate(rows + [rng.uniform(5, 6, (50, 3))])
    # "repeated": 300 of 500 points at one place (equal keys)
    x = rng.uniform(0, 1, (500, 3))
    x[100:400] = x[0]
    return x
