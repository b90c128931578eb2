"""The Warp face-scan kernel's register cap against its time (GPU only): the same kernel
compiled with cuda_max_registers = each value given (0: no cap) and launched through
`arraycontact_warp.detect` on the rough_close scene; CUDA activity timing of the kernel,
median of the repeats, outputs checked equal to the shipped kernel's.

    python benchmarks/gpu_registers.py --log2 20 --caps 0 56 64 72 96 128
"""

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
from gpu import kernel_resources, warp_plan  # noqa: E402
from run import make_scene  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--caps", type=int, nargs="*", default=[0, 56, 64, 72, 96, 128])
    ap.add_argument("--repeats", type=int, default=20)
    a = ap.parse_args()
    import arraycontact_warp as acw
    import warp as wp
    from arraycontact_warp import _detect

    quiet_warp()
    wp.init()
    p, xs, xm = warp_plan(make_scene("rough_close", a.log2))
    p.graphs = False  # launches one by one: each call runs the kernels it names
    acw.detect(p, xs, xm)
    shipped = {k: v.numpy().copy() for k, v in p.out.items()}
    base = _detect._face_kernel
    # The shipped module's options; a module of its own per variant.
    options = {"enable_backward": False, "max_unroll": 1}
    try:
        for cap in a.caps:
            extra = {"cuda_max_registers": cap} if cap else {}
            _detect._face_kernel = wp.kernel(module="unique", module_options=options, **extra)(
                base.func
            )
            acw.detect(p, xs, xm)
            times = []
            for _ in range(a.repeats):
                with wp.ScopedTimer(
                    "k", cuda_filter=wp.TIMING_KERNEL, synchronize=True, print=False
                ) as t:
                    acw.detect(p, xs, xm)
                times.append(sum(r.elapsed for r in t.timing_results if "_face_kernel" in r.name))
            same = all(
                np.array_equal(v.numpy(), shipped[k], equal_nan=True) for k, v in p.out.items()
            )
            print(
                f"cap {cap or 'none'}: kernel {statistics.median(times):.3f} ms, "
                f"same outputs {same}",
                flush=True,
            )
    finally:
        _detect._face_kernel = base
    for name, v in kernel_resources("cuda").items():
        if "_face_kernel" in name:
            print(f"{name}: {v['registers']} registers, {v['local_bytes']} local bytes")


if __name__ == "__main__":
    main()
