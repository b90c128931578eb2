"""Where a plan's set-up time goes: a Python profile of one plan of a Surface it has not seen
(its topology made then), after a first plan of a small scene has compiled the kernels.

    python benchmarks/setup_profile.py --log2 20 --device cuda      # the Warp plan
    python benchmarks/setup_profile.py --log2 16 --device cpu --jax  # and the JAX plans

Prints the functions by their own time (the host's work; a device's work shows up where the
host waits for it: the reads of the topology's scalars).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time

import arraycontact as ac
from arraycontact._backends import quiet_warp


def _profile(label, fn, top):
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    fn()
    pr.disable()
    total = time.perf_counter() - t0
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(top)
    print(f"## {label}: {1e3 * total:.1f} ms\n")
    print("\n".join(s.getvalue().splitlines()[4:]))


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--jax", action="store_true", help="also the JAX plans (both searches)")
    ap.add_argument("--top", type=int, default=20)
    a = ap.parse_args()
    import arraycontact_warp as acw
    import warp as wp

    quiet_warp()
    small = ac.scenes.rough_surfaces(2**10)
    acw.plan(small.master, small.slave, device=a.device)
    wp.synchronize_device(a.device)
    s = ac.scenes.rough_surfaces(2**a.log2)
    m = s.master

    def fresh():
        return ac.Surface(m.points, m.faces, m.element.name)

    def warp_plan(surface):
        acw.plan(surface, s.slave, device=a.device)
        wp.synchronize_device(a.device)

    surface = fresh()
    _profile(f"Warp plan, 2^{a.log2}, {a.device}, new Surface", lambda: warp_plan(surface), a.top)
    _profile("the same Surface again", lambda: warp_plan(surface), a.top)
    if a.jax:
        import arraycontact_jax as acj
        import numpy as np

        for search in ("jax", "warp"):
            acj.plan(small.master, small.slave, dtype=np.float32, search=search)
            surface = fresh()
            _profile(
                f"JAX plan, search={search!r}, new Surface",
                lambda surface=surface, search=search: acj.plan(
                    surface, s.slave, dtype=np.float32, search=search
                ),
                a.top,
            )


if __name__ == "__main__":
    main()
