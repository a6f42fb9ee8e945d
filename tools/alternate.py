#!/usr/bin/env python
"""One command run in several checkouts in turn, round after round: a series that says which
build is faster on a shared machine, where one run moves by +-15 % (docs/measurements.md, "The
accumulator's row: two cache lines").

Each round runs the command once in every directory given, in the order given, with that
directory as the working directory (a tool under ``tools/`` then imports its own checkout's
``bftaichi``: tools/checkout.py). The figure is the first group of ``--pattern`` (a regular
expression) in the command's output; a run without it stops the series with its output.
Printed: per directory its median, mean and best, its ratio of medians to the first
directory's, and every value in the order run::

    git worktree add ../before HEAD~1
    python tools/alternate.py ../before . --rounds 8 -- \\
        python tools/bench_observe.py $PWD/../shared/data/rgbd/7scenes-redkitchen --timed 40 --loop 8

The default pattern reads ``tools/bench_observe.py --loop``'s milliseconds per frame. Give
data paths as absolute paths: each run starts in its own directory.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from pathlib import Path

DEFAULT_PATTERN = r"(?:rays|misfit) ([0-9.]+) ms per frame"


def run_series(dirs, command, rounds: int, pattern: str, echo=print) -> dict:
    """``{dir: [figure per round]}``: ``command`` run ``rounds`` times in each of ``dirs`` in
    turn. Raises RuntimeError naming the directory and showing the output when a run exits
    non-zero or prints no match of ``pattern``."""
    regex = re.compile(pattern)
    values = {d: [] for d in dirs}
    for r in range(rounds):
        for d in dirs:
            done = subprocess.run(command, cwd=d, capture_output=True, text=True)
            out = done.stdout + done.stderr
            match = regex.search(out)
            if done.returncode != 0 or match is None:
                raise RuntimeError(f"{d}: round {r + 1} exited {done.returncode} and printed "
                                   f"{'no' if match is None else 'a'} match of {pattern!r}; "
                                   f"its output ends:\n{out[-2000:]}")
            values[d].append(float(match.group(1)))
            echo(f"round {r + 1}, {d}: {values[d][-1]:g}")
    return values


def table(values: dict) -> str:
    """A markdown table of the series (the ratio of medians against the first directory)."""
    first = statistics.median(next(iter(values.values())))
    rows = ["| checkout | median | mean | best | median / first's | runs |",
            "|---|---|---|---|---|---|"]
    for d, v in values.items():
        med = statistics.median(v)
        rows.append(f"| {d} | {med:.2f} | {statistics.mean(v):.2f} | {min(v):.2f} | "
                    f"{med / first:.3f} | {' '.join(f'{x:g}' for x in v)} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("dirs", nargs="+", help="checkouts (directories) to run the command in")
    ap.add_argument("--rounds", type=int, default=8, help="runs per directory (default 8)")
    ap.add_argument("--pattern", default=DEFAULT_PATTERN,
                    help="regular expression whose first group is the figure (default: "
                    "bench_observe --loop's ms per frame)")
    argv = sys.argv[1:] if argv is None else list(argv)
    cut = argv.index("--") if "--" in argv else len(argv)  # the command follows the first --
    args, command = ap.parse_args(argv[:cut]), argv[cut + 1:]
    if not command:
        ap.error("give the command after --, e.g. -- python tools/bench_observe.py ... --loop 8")
    if args.rounds < 1:
        ap.error(f"--rounds must be at least 1, got {args.rounds}")
    missing = [d for d in args.dirs if not Path(d).is_dir()]
    if missing:
        ap.error(f"not a directory: {', '.join(missing)}")
    try:
        values = run_series(args.dirs, command, args.rounds, args.pattern)
    except RuntimeError as e:
        print(f"alternate.py: {e}", file=sys.stderr)
        return 1
    print(table(values))
    return 0


if __name__ == "__main__":
    sys.exit(main())
