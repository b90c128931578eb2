"""Nsight Compute source counters of one Warp kernel per Python line (GPU machine only: it
imports ncu's own `ncu_report` module). Warp's generated CUDA source names the Python line of
each statement in a comment; this sums instructions executed (per warp and per thread) and
stall samples over those lines.

    ncu --clock-control none --profile-from-start off -k regex:_face_kernel \\
        --section SourceCounters --import-source yes -o prof \\
        python benchmarks/gpu_profile.py --lineinfo
    python3 benchmarks/ncu_lines.py prof.ncu-rep ~/.cache/warp/*/wp_arraycontact_warp._detect_*/*.cu
"""

import collections
import glob
import re
import sys

sys.path.append(sorted(glob.glob("/opt/nvidia/nsight-compute/*/extras/python"))[-1])
import ncu_report  # noqa: E402

METRICS = ("inst_executed", "thread_inst_executed", "smsp__pcsamp_sample_count")


def python_lines(cu_path):
    """CUDA line -> (function, Python line and text) from the comments Warp writes."""
    where, func, last = {}, "?", None
    for n, line in enumerate(open(cu_path), 1):
        m = re.match(r'^(?:static CUDA_CALLABLE|extern "C" __global__)[^(]*\s(\w+)\(', line)
        if m:
            func = m.group(1)
        m = re.search(r"//\s*(.*?)\s*<L (\d+)>", line)
        if m:
            last = f"L{m.group(2)} {m.group(1)[:70]}"
        where[n] = (func, last)
    return where


def main(report, cu_path, top=25):
    action = ncu_report.load_report(report).range_by_idx(0).action_by_idx(0)
    where = python_lines(cu_path)
    for name in METRICS:
        metric = action.metric_by_name(name)
        ids = metric.correlation_ids()
        sums = collections.Counter()
        for i in range(metric.num_instances()):
            info = action.source_info(ids.as_uint64(i))
            f = info.file_name() if info else "?"
            key = where.get(info.line(), ("?", None)) if f.endswith(".cu") else (f, info.line())
            sums[key] += metric.as_double(i)
        total = sum(sums.values()) or 1.0
        print(f"== {name}: {total:.4g}")
        for key, v in sums.most_common(top):
            print(f"{100 * v / total:6.2f}%  {key[0]}  {key[1]}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
