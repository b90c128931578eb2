"""The time of every launch of one Warp detection (GPU), per scene of the suite: where a
detection's time goes. The launches one by one (graphs off), timed by Warp's CUDA activity
timing after warm-up calls, on the path a graph replays (the trees refitted: each call is
made a plan's first, whose refit check the host reads); "launches" counts them.

    python benchmarks/gpu_stages.py --log2 20 --only uniform graded_1000
    python benchmarks/gpu_stages.py --log2 17 --self spiral_strip crumpled_sheet
    python benchmarks/gpu_stages.py --log2 17 --self folded_sheet --element tri6
    python benchmarks/gpu_stages.py --log2 20 --swept rough_tri3 graded_100

With --swept, each step of `swept.py` twice: its swept detection and the static detection of
the step's end (default d_max), as swept.py times them.
"""

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
from suite import suite  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--self", nargs="*", help="self-contact scenes (arraycontact.scenes)")
    ap.add_argument("--element", default="quad4", help="the self-contact scenes' faces")
    ap.add_argument("--swept", nargs="*", help="swept steps (swept.py's names)")
    a = ap.parse_args()
    import arraycontact_warp as acw
    import warp as wp

    quiet_warp()
    for label, detect, slaves in _cases(a, acw, wp):
        for _ in range(3):
            detect()
        wp.synchronize()
        totals, counts = defaultdict(float), defaultdict(int)
        runs = 5
        for _ in range(runs):
            with wp.ScopedTimer(
                "detect", print=False, synchronize=True, cuda_filter=wp.TIMING_ALL
            ) as t:
                detect()
            for r in t.timing_results:
                totals[r.name] += r.elapsed / runs
                counts[r.name] += 1
        print(
            f"{label}: {slaves}; "
            f"total {sum(totals.values()):.3f} ms in {sum(counts.values()) // runs} launches"
        )
        for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:12]:
            print(f"   {ms:8.3f} ms  {counts[name] // runs:3d}x  {name}")


def _cases(a, acw, wp):
    """(label, a detection on the path a graph replays, counts) per scene asked for."""
    if a.swept is not None:
        yield from _swept_cases(a, acw, wp)
        return
    if a.self is not None:
        import arraycontact as ac

        for name in a.self:
            sc = getattr(ac.scenes, name)(2**a.log2, element=a.element)
            s = sc.master
            p = acw.plan_self(s, d_max=sc.params["d_max"], device="cuda", graphs=False)
            x = wp.array((s.points - p.origin).astype(np.float32), dtype=wp.vec3)
            p.origin = np.zeros(3)
            yield name, _first(p, lambda p=p, x=x: acw.detect_self(p, x)), f"{len(s.nodes)} nodes"
        return
    for label, make, f in suite(a.log2):
        if a.only and not any(label.startswith(o) for o in a.only):
            continue
        scene = make()
        d_max = f * scene.master.longest_edge
        p = acw.plan(scene.master, scene.slave, d_max=d_max, device="cuda", graphs=False)
        xs = wp.array((scene.slave - p.origin).astype(np.float32), dtype=wp.vec3)
        xm = wp.array((scene.master.points - p.origin).astype(np.float32), dtype=wp.vec3)
        p.origin = np.zeros(3)
        counts = f"{scene.master.n_faces} faces, {len(scene.slave)} slaves"
        yield label, _first(p, lambda p=p, xs=xs, xm=xm: acw.detect(p, xs, xm)), counts


def _swept_cases(a, acw, wp):
    from swept import steps

    for name in a.swept:
        st = steps(2**a.log2)[name]()
        p = acw.plan_swept(st.master, st.slave_x0, device="cuda")

        def arr(x, p=p):
            return wp.array((x - p.origin).astype(np.float32), dtype=wp.vec3)

        xs = [arr(st.slave_x0), arr(st.slave_x1), arr(st.master.points), arr(st.master_x1)]
        p.origin = np.zeros(3)
        counts = f"{st.master.n_faces} faces, {len(st.slave_x0)} slaves"
        yield f"{name} swept", lambda p=p, xs=xs: acw.detect_swept(p, *xs), counts
        m1 = st.master.with_points(st.master_x1)
        q = acw.plan(m1, st.slave_x1, device="cuda", graphs=False)
        ys = arr(st.slave_x1, q), arr(st.master_x1, q)
        q.origin = np.zeros(3)
        yield f"{name} static", _first(q, lambda q=q, ys=ys: acw.detect(q, *ys)), counts


def _first(p, call):
    """call, made a plan's first each time: the refit a graph replays, its check on the host."""

    def detect():
        p.master_ready = False
        call()

    return detect


if __name__ == "__main__":
    main()
