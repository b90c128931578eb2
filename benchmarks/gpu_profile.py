"""One Warp detection on the GPU between cuProfilerStart and cuProfilerStop, for Nsight
Compute (GPU only). The rough_close scene at 2^k nodes per surface; warm-up calls first.

    ncu --clock-control none --profile-from-start off --section SpeedOfLight \
        python benchmarks/gpu_profile.py --log2 20
"""

import argparse
import ctypes
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from gpu import warp_plan  # noqa: E402
from run import make_scene  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument(
        "--lineinfo",
        action="store_true",
        help="kernels built with line information (for ncu's source counters) "
        "pointing at the generated CUDA source, whose comments name the Python "
        "lines",
    )
    a = ap.parse_args()
    import warp as wp

    from arraycontact._backends import quiet_warp

    quiet_warp()
    if a.lineinfo:  # before the modules are made: they take their options then
        wp.config.lineinfo = True
        wp.config.line_directives = False
    import arraycontact_warp as acw

    wp.init()
    p, xs, xm = warp_plan(make_scene("rough_close", a.log2))
    p.graphs = False  # launches one by one: each call runs the kernels it names
    for _ in range(3):
        acw.detect(p, xs, xm)
    wp.synchronize()
    cuda = ctypes.CDLL("libcuda.so.1")
    cuda.cuProfilerStart()
    p.master_ready = False  # the trees refitted, as a graph's replay does (see gpu_stages.py)
    acw.detect(p, xs, xm)
    wp.synchronize()
    cuda.cuProfilerStop()


if __name__ == "__main__":
    main()
