"""The benchmarks' records: one JSON-lines file per benchmark and machine in `results/`,
`<benchmark>_<machine>.jsonl` (machine: cpu, h100, h200, h200x2, ...), every record carrying
its run id, date, commit and command. `report.py` makes every table of RESULTS.md and GPU.md
from these files; nothing in those tables is typed by hand."""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).parent
RESULTS = HERE / "results"


def machine(device: str, n_devices: int = 1) -> str:
    """The machine part of a record file's name: 'cpu', 'h100', 'h200', 'h200x2', ..."""
    d = device.lower()
    name = next((g for g in ("h100", "h200", "a100", "l40s") if g in d), None)
    if name is None:
        name = "cpu" if ("cpu" in d or "x86" in d or "arm" in d) else "gpu"
    return name if n_devices == 1 else f"{name}x{n_devices}"


def meta(run: str | None = None) -> dict:
    """Run id (default: the time now), date, commit and command of a benchmark run. A copy of
    the tree on another machine may carry a stale .git: ARRAYCONTACT_COMMIT wins."""
    commit = (
        os.environ.get("ARRAYCONTACT_COMMIT")
        or subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE
        ).stdout.strip()
        or None
    )
    now = datetime.datetime.now()
    return dict(
        run=run or now.strftime("%Y%m%d-%H%M%S"),
        date=now.date().isoformat(),
        commit=commit,
        command="python benchmarks/" + " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
    )


def append(benchmark: str, record: dict, run_meta: dict, out=None, n_devices: int = 1) -> Path:
    """Append `record` (with `run_meta` first) to `<out>/<benchmark>_<machine>.jsonl`, the
    machine taken from the record's `device`. out: a folder (default results/)."""
    folder = Path(out) if out else RESULTS
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{benchmark}_{machine(record['device'], n_devices)}.jsonl"
    with open(path, "a") as fh:
        fh.write(json.dumps({**run_meta, **record}) + "\n")
    return path


def load(benchmark: str, machine: str | None = None) -> list[dict]:
    """The records of a benchmark (on one machine, or on all), in file order (oldest first).
    All machines: not the A/B tries kept beside them (`<benchmark>_tries_*.jsonl`), which
    would otherwise sort after the machines' files and pass for their newest records."""
    pattern = f"{benchmark}_{machine or '*'}.jsonl"
    out = []
    for path in sorted(RESULTS.glob(pattern)):
        if machine in (None, "*") and path.stem[len(benchmark) + 1 :].startswith("tries"):
            continue
        out += [json.loads(line) for line in open(path) if line.strip()]
    return out


def newest(records: list[dict], *key: str) -> list[dict]:
    """Each configuration's newest record (the last in file order), configurations in the
    order they first appear; key: the fields that name a configuration."""
    latest = {}
    for r in records:
        k = tuple(json.dumps(r.get(f), sort_keys=True) for f in key)
        latest.setdefault(k, None)
        latest[k] = r
    return list(latest.values())


def run_of(records: list[dict], run: str | None = None) -> list[dict]:
    """The records of run `run` (default: the newest run)."""
    if not records:
        return []
    run = run or records[-1]["run"]
    return [r for r in records if r["run"] == run]


def commit(r: dict) -> str:
    """A record's commit; older records name the commit that added them instead."""
    return r.get("commit") or f"before {r.get('recorded_in', '?')}"


def markdown(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)
