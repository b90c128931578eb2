"""The time of every launch of one Warp detection (GPU), per scene of the suite: where a
detection's time goes. The launches one by one (graphs off), timed by Warp's CUDA activity
timing after warm-up calls, on the path a graph replays (the trees refitted: each call is
made a plan's first, whose refit check the host reads); "launches" counts them.

    python benchmarks/gpu_stages.py --log2 20 --only uniform graded_1000
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
    a = ap.parse_args()
    import arraycontact_warp as acw
    import warp as wp

    quiet_warp()
    for label, make, f in suite(a.log2):
        if a.only and not any(label.startswith(o) for o in a.only):
            continue
        scene = make()
        p = acw.plan(
            scene.master,
            scene.slave,
            d_max=f * scene.master.longest_edge,
            device="cuda",
            graphs=False,
        )
        xs = wp.array((scene.slave - p.origin).astype(np.float32), dtype=wp.vec3)
        xm = wp.array((scene.master.points - p.origin).astype(np.float32), dtype=wp.vec3)
        p.origin = np.zeros(3)
        for _ in range(3):
            acw.detect(p, xs, xm)
        wp.synchronize()
        totals, counts = defaultdict(float), defaultdict(int)
        runs = 5
        for _ in range(runs):
            p.master_ready = False
            with wp.ScopedTimer(
                "detect", print=False, synchronize=True, cuda_filter=wp.TIMING_ALL
            ) as t:
                acw.detect(p, xs, xm)
            for r in t.timing_results:
                totals[r.name] += r.elapsed / runs
                counts[r.name] += 1
        print(
            f"{label}: {scene.master.n_faces} faces, {len(scene.slave)} slaves; "
            f"total {sum(totals.values()):.3f} ms in {sum(counts.values()) // runs} launches"
        )
        for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:12]:
            print(f"   {ms:8.3f} ms  {counts[name] // runs:3d}x  {name}")


if __name__ == "__main__":
    main()
