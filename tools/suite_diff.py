#!/usr/bin/env python
"""Two runs of the development suite side by side: what a model change moved, case by case.

Reads two ``--json`` files of ``tools/suite.py`` (the rows of the same cases; a case only one
run has is listed as such) and prints the summary line of each; then, over the cases both runs
have, the scores the target counts hide: the mean NLL minus the best constant's (a proper
score: calibration and sharpness in one number; lower is better), the geometric mean of the
AUSE ratio new / old and the mean Spearman; then one row per case whose
missed targets or any of whose figures, rounded as printed, changed: the CD ratio (and on the
surface the frames saw: nan for a run from before the suite split it), the coverage at 1 / 2 / 3
sigma, the NLL minus the best constant's, AUSE and Spearman, each as
old -> new, and the missed targets of both::

    python tools/suite.py --json before.json
    python tools/suite.py --set prior.curvature=0.2 --json after.json
    python tools/suite_diff.py before.json after.json
    python tools/suite_diff.py before.json after.json --all     # every case, moved or not
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from suite import misses, summary  # noqa: E402

#: (label, value of a row, format): a figure moved when its formatted value changed
FIGURES = (
    ("CD ratio", lambda r: r["cd_post"] / r["cd_tsdf"], "{:.3f}"),
    ("seen CD ratio", lambda r: (r["cd_seen_post"] / r["cd_seen_tsdf"] if "cd_seen_post" in r
                                 else math.nan), "{:.3f}"),  # nan: a run from before the split
    ("cov 1/2/3 sigma (%)", lambda r: tuple(100 * r[f"coverage@{k}sigma"] for k in (1, 2, 3)),
     "{:.0f} / {:.0f} / {:.1f}"),
    ("NLL - const", lambda r: r["nll_vs_constant"], "{:+.2f}"),
    ("AUSE (mm)", lambda r: 1000 * r["ause"], "{:.3f}"),
    ("Spearman", lambda r: r["spearman"], "{:.2f}"),
)


def _load(path: Path) -> tuple[dict, list]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"error: {path}: cannot read a suite.py --json file ({e})")
    if not isinstance(data, dict) or not isinstance(data.get("rows"), dict):
        raise SystemExit(f"error: {path}: no 'rows' (write it with tools/suite.py --json)")
    return data["rows"], data.get("sets", [])


def _fmt(fmt: str, v) -> str:
    return fmt.format(*v) if isinstance(v, tuple) else fmt.format(v)


def compare(old: dict, new: dict, every: bool = False) -> list[str]:
    """Markdown lines: a header and one row per case that moved (every case with ``every``)."""
    head = "| case | " + " | ".join(label for label, *_ in FIGURES) + " | misses |"
    lines = [head, "|" + "---|" * (len(FIGURES) + 2)]
    for name in list(old) + [n for n in new if n not in old]:
        if name not in old or name not in new:
            lines.append(f"| {name} | only in {'the first' if name in old else 'the second'} "
                         "run |" + " |" * len(FIGURES))
            continue
        a, b = old[name], new[name]
        miss_a, miss_b = misses(name, a), misses(name, b)
        cells, moved = [], miss_a != miss_b
        for _, value, fmt in FIGURES:
            sa, sb = _fmt(fmt, value(a)), _fmt(fmt, value(b))
            moved |= sa != sb and "nan" not in (sa, sb)  # one run without that figure: no move
            cells.append(f"{sa} -> {sb}" if sa != sb else sb)
        if moved or every:
            missed = f"{', '.join(miss_a) or '-'} -> {', '.join(miss_b) or '-'}"
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {missed} |")
    return lines


def scores(old: dict, new: dict) -> str:
    """Mean NLL minus the constant's (old -> new), geometric mean AUSE ratio (new / old) and
    mean Spearman (old -> new) over the cases both runs have."""
    both = [n for n in old if n in new]
    if not both:
        return "no case in both runs"

    def mean(rows, key):
        return sum(rows[n][key] for n in both) / len(both)

    ause = math.exp(sum(math.log(new[n]["ause"] / old[n]["ause"]) for n in both) / len(both))
    return (f"over the {len(both)} cases of both: mean NLL - const "
            f"{mean(old, 'nll_vs_constant'):+.3f} -> {mean(new, 'nll_vs_constant'):+.3f}; "
            f"AUSE new / old {ause:.3f} (geometric mean); mean Spearman "
            f"{mean(old, 'spearman'):.3f} -> {mean(new, 'spearman'):.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("old", type=Path, help="suite.py --json of the run before")
    ap.add_argument("new", type=Path, help="suite.py --json of the run after")
    ap.add_argument("--all", action="store_true", help="list every case, not only those that moved")
    args = ap.parse_args(argv)
    old, sets_old = _load(args.old)
    new, sets_new = _load(args.new)
    print(f"before ({' '.join(sets_old) or 'no overrides'}): {summary(old)}")
    print(f"after ({' '.join(sets_new) or 'no overrides'}): {summary(new)}")
    print(scores(old, new))
    print()
    lines = compare(old, new, args.all)
    print("\n".join(lines) if len(lines) > 2 else "no case moved")
    return 0


if __name__ == "__main__":
    sys.exit(main())
