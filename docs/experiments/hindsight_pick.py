#!/usr/bin/env python
"""Per case, the best of several suite runs chosen with hindsight: an upper bound on what a
rule that picks a setting per scene (e.g. ``prior.curvature``) could gain, not a rule.

Reads ``--json`` files of ``tools/suite.py`` (the same cases, each run with one setting), picks
for every case the run whose row is best by ``--by`` (``cd``: the lowest posterior Chamfer
distance, which needs the ground truth; ``nll``: the lowest NLL minus the constant's), and
prints the targets that choice meets (``tools/suite.py``'s rules), its geometric mean CD
ratio, and which run each case took::

    python tools/suite.py --set prior.curvature=0.25 --json c025.json
    python tools/suite.py --json c05.json
    python tools/suite.py --set prior.curvature=1.0 --json c1.json
    python docs/experiments/hindsight_pick.py c025.json c05.json c1.json --by cd
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))

from suite import summary  # noqa: E402

KEYS = {"cd": "cd_post", "nll": "nll_vs_constant"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="tools/suite.py --json files")
    ap.add_argument("--by", choices=sorted(KEYS), default="cd",
                    help="what 'best' means per case (default cd)")
    args = ap.parse_args(argv)
    runs = {p.name: json.loads(p.read_text())["rows"] for p in args.runs}
    cases = [c for c in next(iter(runs.values())) if all(c in rows for rows in runs.values())]
    if not cases:
        raise SystemExit("hindsight_pick: the runs have no case in common")
    key = KEYS[args.by]
    picked, chosen = {}, {}
    for case in cases:
        name = min(runs, key=lambda n: runs[n][case][key])
        picked[case], chosen[case] = runs[name][case], name
    for name, rows in runs.items():
        print(f"{name}: {summary({c: rows[c] for c in cases})}")
    print(f"best of each case by {args.by}: {summary(picked)}")
    for case in cases:
        print(f"  {case}: {chosen[case]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
