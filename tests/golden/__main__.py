"""``python -m tests.golden [--update] [NAME ...]``: check (or rewrite) the golden traces."""

from __future__ import annotations

import argparse
import json
import sys

import hil  # noqa: F401  (pins OpenBLAS's kernels before numpy loads)
from tests import golden
from tests.golden import ticks as per_tick


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.golden", description=__doc__)
    ap.add_argument("--update", action="store_true",
                    help="rewrite golden.json with what the code gives now")
    ap.add_argument("names", nargs="*",
                    help=f"scenarios, or {golden.FAULTS} for the fault table (default: all)")
    args = ap.parse_args(argv)
    unknown = set(args.names) - set(golden.BY_NAME) - {golden.FAULTS}
    if unknown:
        print(f"error: unknown scenario(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    names = args.names or [s.name for s in golden.SCENARIOS] + [golden.FAULTS]
    want = golden.load() if golden.GOLDEN_FILE.exists() else {}
    got, failed = dict(want), []
    if golden.FAULTS in names:
        names.remove(golden.FAULTS)
        if not _faults(args.update):
            failed.append(golden.FAULTS)
    for name in names:
        s = golden.BY_NAME[name]
        cols: list = [] if s.per_tick else None
        res = golden.run(s, ticks=cols)
        got[name] = res
        problems = golden.diff(want.get(name), res) if name in want else ["not in golden.json"]
        if s.per_tick:
            # the per-tick trace first: it names the first differing tick and field
            if args.update:
                per_tick.save(name, cols[0])
            elif per_tick.path(name).exists():
                problems = per_tick.differences(per_tick.load(name), cols[0]) + problems
            else:
                problems = [f"no per-tick trace {per_tick.path(name)}"] + problems
        status = "ok" if not problems else ("updated" if args.update else "DIFFERS")
        print(f"{name:24s} {status:8s} trace {res['trace_sha256'][:12]}  "
              f"bus.log {res['buslog_sha256'][:12]}  {res['frames_logged']} frames")
        if problems and not args.update:
            failed.append(name)
            for p in problems:
                print(f"    {p}")
    if args.update and names:
        if any(golden.BY_NAME[n].per_tick for n in names):
            print(f"wrote {per_tick.DIR}")
        order = [s.name for s in golden.SCENARIOS]
        golden.GOLDEN_FILE.write_text(json.dumps({k: got[k] for k in order if k in got},
                                                 indent=1) + "\n")
        print(f"wrote {golden.GOLDEN_FILE}")
    if args.update:
        return 0
    print("verdict: " + ("PASS" if not failed else f"FAIL ({', '.join(failed)})"))
    return 1 if failed else 0


def _faults(update: bool) -> bool:
    """Check (or rewrite) the fault table; False when it differs and is not rewritten."""
    try:
        res = golden.run_faults()
    except RuntimeError as e:
        print(f"{golden.FAULTS:24s} FAILED   {e}")
        return False
    want = golden.load_faults() if golden.FAULTS_FILE.exists() else None
    problems = golden.diff(want, res) if want is not None else ["not in faults.json"]
    status = "ok" if not problems else ("updated" if update else "DIFFERS")
    print(f"{golden.FAULTS:24s} {status:8s} {len(res['results'])} faults over the hub")
    if update:
        golden.FAULTS_FILE.write_text(json.dumps(res, indent=1) + "\n")
        print(f"wrote {golden.FAULTS_FILE}")
        return True
    for p in problems:
        print(f"    {p}")
    return not problems


if __name__ == "__main__":
    sys.exit(main())
