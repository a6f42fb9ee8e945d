#!/usr/bin/env python
"""Runs per hour of ``bftaichi batch`` against Ray workers (issue 20, item 5).

Writes a manifest of ``--runs`` copies of a scene (each its own name; the default: the built-in
tabletop at 160x120 with 12 views, a ~10 s run) and times ``bftaichi batch`` over it with each
``--workers`` count, whole process (Ray's start included), on this machine; prints runs per hour
and the speed-up, and with ``--plot`` draws them::

    python tools/bench_batch.py                        # 6 runs, 1 and 2 workers
    python tools/bench_batch.py --runs 8 --workers 1 2 --plot docs/batch_scaling.png
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
SMALL = ("synthetic.width=160", "synthetic.height=120", "synthetic.fx=131.25",
         "synthetic.fy=131.25", "synthetic.cx=79.5", "synthetic.cy=59.5", "synthetic.n_views=12",
         "run.plots=false", "run.preview=false")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=Path, default=ROOT / "scenes" / "default.toml")
    ap.add_argument("--set", dest="sets", action="append", default=None,
                    help="overrides of every run [default: the small tabletop above]")
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    sets = args.sets if args.sets is not None else list(SMALL)
    tmp = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    manifest = tmp / "runs.toml"
    manifest.write_text("".join(
        f'[[run]]\nscene = {json.dumps(str(args.scene.resolve()))}\nname = "run{i}"\n'
        f'set = [{", ".join(json.dumps(s) for s in sets)}]\n\n' for i in range(args.runs)))
    # one run first, so the Taichi offline cache is warm for every measured batch
    subprocess.run([sys.executable, "-m", "bftaichi.cli", "run", str(args.scene), "--out",
                    str(tmp / "warm"), "-q", *[a for s in sets for a in ("--set", s)]],
                   check=True, env=checkout.child_env())
    rows = []
    for w in args.workers:
        out = tmp / f"out{w}"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "bftaichi.cli", "batch", str(manifest),
                               "--out", str(out), "--workers", str(w), "-q"],
                              env=checkout.child_env())
        seconds = time.perf_counter() - t0
        record = json.loads((out / "batch.json").read_text())
        run_s = [r["seconds"] for r in record["runs"] if r["status"] == "ok"]
        rows.append({"workers": w, "seconds": seconds, "runs_per_hour": 3600 * args.runs / seconds,
                     "ok": record["counts"]["ok"], "exit": proc.returncode,
                     "median_run_s": sorted(run_s)[len(run_s) // 2] if run_s else None})
        print(f"{w} worker(s): {args.runs} runs in {seconds:.1f} s = "
              f"{rows[-1]['runs_per_hour']:.0f} runs/hour ({record['counts']['ok']} ok; median "
              f"run {rows[-1]['median_run_s']:.1f} s)", flush=True)
    base = rows[0]["runs_per_hour"]
    for r in rows[1:]:
        print(f"speed-up {r['workers']} against {rows[0]['workers']} worker(s): "
              f"{r['runs_per_hour'] / base:.2f}x")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(4.5, 3.2))
        ax.plot([r["workers"] for r in rows], [r["runs_per_hour"] for r in rows], "o-",
                label="measured")
        ax.plot([r["workers"] for r in rows], [base * r["workers"] / rows[0]["workers"]
                                               for r in rows], "--", color="grey",
                label="linear")
        ax.set_xlabel("Ray workers (CPUs)")
        ax.set_ylabel("runs per hour")
        ax.set_xticks([r["workers"] for r in rows])
        ax.set_title(f"bftaichi batch, {args.runs} runs, this 2-core machine", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
