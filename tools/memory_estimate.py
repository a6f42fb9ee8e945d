#!/usr/bin/env python
"""The memory estimate of bftaichi.running.resources against the measured peak RSS of real runs.

For each scene and voxel size: :func:`bftaichi.running.resources.estimate_memory` here, then
``bftaichi.run`` in a fresh subprocess (so peaks do not mix) that reports its own peak RSS
(``VmHWM``) at the end; prints both and their ratio as a markdown table::

    python tools/memory_estimate.py                               # redkitchen, 2 cm and 1 cm
    python tools/memory_estimate.py scenes/default.toml --voxels 0.01 --set run.stages=full

Plots and the preview are off in the measured runs (``run.plots=false``, ``run.preview=false``)
so that only the pipeline is measured. ``tsdf.trunc_m`` stays the scene's unless ``--set``
changes it.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]

# The measured child: run the pipeline, print the report's counts and the process's peak RSS.
_CHILD = r"""
import json, sys
from bftaichi.config import load_config
from bftaichi.running.pipeline import run
from bftaichi.running.resources import PeakRSS
scene, out, *sets = sys.argv[1:]
cfg = load_config(scene or None, sets)
report = run(cfg, out, overwrite=True, progress=False)
# The run's PeakRSS resets the kernel's high-water mark at each stage, so VmHWM now holds only
# the peak since the last stage began: the whole run's peak is the larger of it and the
# highest stage peak the report recorded.
peak = None
for line in open("/proc/self/status"):
    if line.startswith("VmHWM:"):
        peak = int(line.split()[1]) * 1024
stage_peak = ((report.get("memory") or {}).get("peak_rss") or {}).get("peak")
if stage_peak and (peak is None or stage_peak > peak):
    peak = int(stage_peak)
print(json.dumps({"peak_bytes": peak, "counts": report["counts"],
                  "seconds": report["seconds"]["total"]}))
"""


def measure(scene: str, sets: list[str], out: str) -> dict:
    """Peak RSS (bytes) and counts of ``bftaichi.run`` in a fresh Python process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _CHILD, scene, out, *sets], capture_output=True,
                          text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"run failed ({scene} {' '.join(sets)}):\n{proc.stderr[-3000:]}")
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    res["wall_s"] = time.perf_counter() - t0
    # ru_maxrss of the children is their maximum so far (KiB): this child's when it is larger
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    res["ru_maxrss_bytes"] = after * 1024 if after > before else None
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=["scenes/redkitchen.toml"],
                    help="scene files (default: scenes/redkitchen.toml); '' = the built-in scene")
    ap.add_argument("--voxels", type=float, nargs="+", default=[0.02, 0.01],
                    help="voxel sizes, metres (default 0.02 0.01)")
    ap.add_argument("--set", dest="sets", action="append", default=[],
                    help="section.key=value override for every run (repeatable)")
    ap.add_argument("--estimate-only", action="store_true", help="skip the measured runs")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = ap.parse_args(argv)

    from bftaichi.config import load_config
    from bftaichi.running.pipeline import open_frames
    from bftaichi.running.resources import estimate_memory

    mib = 2 ** 20
    rows = []
    print("| scene | voxel | trunc | band voxels est / run | estimate | measured peak | "
          "est / measured | estimate s | run s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        for vs in args.voxels:
            sets = [*args.sets, f"tsdf.voxel_size_m={vs}", "run.plots=false",
                    "run.preview=false"]
            cfg = load_config(scene or None, sets)
            est = estimate_memory(cfg, open_frames(cfg))
            row = {"scene": cfg.scene.name, "voxel_size_m": vs, "trunc_m": cfg.tsdf.trunc_m,
                   "estimate": est}
            meas = None
            if not args.estimate_only:
                with tempfile.TemporaryDirectory(prefix="bftaichi-mem-") as out:
                    meas = measure(scene, sets, out)
                row["measured"] = meas
            rows.append(row)
            band = est["inputs"]["band_voxels"] or est["inputs"]["observed_voxels"]
            if meas:
                c = meas["counts"]
                run_band = c.get("band_voxels", c["observed_voxels"])
                cells = [f"{band} / {run_band}", f"{est['peak_bytes'] / mib:.0f} MiB",
                         f"{meas['peak_bytes'] / mib:.0f} MiB",
                         f"{est['peak_bytes'] / meas['peak_bytes']:.2f}",
                         f"{est['seconds']:.2f}", f"{meas['seconds']:.1f}"]
            else:
                cells = [f"{band} / -", f"{est['peak_bytes'] / mib:.0f} MiB", "-", "-",
                         f"{est['seconds']:.2f}", "-"]
            print(f"| {cfg.scene.name} | {vs * 1000:g} mm | {cfg.tsdf.trunc_m * 1000:g} mm | "
                  + " | ".join(cells) + " |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
