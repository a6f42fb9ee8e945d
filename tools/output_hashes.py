#!/usr/bin/env python
"""Refactor check: the outputs of fixed inputs must keep the bytes recorded in a fixture.

A refactor proves itself by giving the same bytes for the same inputs. This script runs each
case below, hashes ``mesh.ply``, ``tsdf_mesh.ply`` and every array of ``band.npz`` (sha256 of
dtype, shape and data, so a container difference such as zip timestamps does not count but any
value does), plus the top-5 next-best views of the bunny, and compares them with the fixture
``tools/output_hashes.json``::

    python tools/output_hashes.py                 # compare every case with the fixture
    python tools/output_hashes.py --only default  # one case
    python tools/output_hashes.py --record        # (re)write the fixture from this checkout

``band.npz`` may gain arrays (a newer run writes more); every array the fixture lists must be
identical. The fixture holds the hashes recorded at commit ``recorded_at`` on this project's CI
machine; a different CPU or LLVM may round differently, so record once per machine before a
refactor and compare after it. Exit status 0 if every recorded hash matches, 1 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

from bftaichi.cli import main as cli_main  # noqa: E402

FIXTURE = ROOT / "tools" / "output_hashes.json"
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"
QUIET = ("--set", "run.plots=false", "--set", "run.preview=false", "-q")

CASES = {
    "default": ["run", "scenes/default.toml"],
    "bunny": ["run", "scenes/bunny.toml", "--set", "nbv.enabled=true"],
    "bunny_far": ["run", "scenes/bunny_far.toml"],
    "seed_sphere": ["run", "scenes/seed_sphere.toml"],
    "redkitchen100": ["fuse", str(DATA), "--voxel", "0.02", "--frames", "0:100"],
}
"""Name -> bftaichi arguments (without --out). The cases issue 14 names."""


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hash_outputs(out: Path) -> dict:
    """sha256 of each mesh file, of each band array, and the NBV top 5 if the run ranked views."""
    h = {name: _sha((out / name).read_bytes()) for name in ("mesh.ply", "tsdf_mesh.ply")}
    with np.load(io.BytesIO((out / "band.npz").read_bytes())) as z:
        for key in sorted(z.files):
            a = np.ascontiguousarray(z[key])
            h[f"band.npz:{key}"] = _sha(f"{a.dtype.str}{a.shape}".encode() + a.tobytes())
    nbv = out / "nbv.json"
    if nbv.is_file():
        ranking = json.loads(nbv.read_text())["candidates"][:5]
        h["nbv_top5"] = [{"index": r["index"], "utility": r["utility"]} for r in ranking]
    return h


def run_case(name: str, tmp: Path) -> dict:
    out = tmp / name
    rc = cli_main([*CASES[name], "--out", str(out), *QUIET])
    if rc != 0:
        raise SystemExit(f"case {name}: bftaichi exited with {rc}")
    return hash_outputs(out)


def compare(recorded: dict, now: dict) -> list[str]:
    """Lines describing each difference; empty if every recorded entry matches."""
    bad = []
    for key, want in recorded.items():
        got = now.get(key)
        if key == "nbv_top5":
            continue  # reported separately: may change with the planner's Observer (issue 14)
        if got != want:
            bad.append(f"{key}: {'missing' if got is None else 'differs'}")
    return bad


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", action="append", choices=sorted(CASES), help="run only these cases")
    p.add_argument("--record", action="store_true", help="write the fixture instead of comparing")
    args = p.parse_args(argv)
    names = args.only or list(CASES)
    fixture = json.loads(FIXTURE.read_text()) if FIXTURE.is_file() else {"cases": {}}
    ok = True
    with tempfile.TemporaryDirectory(prefix="bftaichi-hashes-") as tmp:
        for name in names:
            if name == "redkitchen100" and not DATA.is_dir():
                print(f"{name}: skipped ({DATA} is missing)")
                continue
            now = run_case(name, Path(tmp))
            if args.record:
                fixture["cases"][name] = now
                print(f"{name}: recorded {len(now)} hashes")
                continue
            recorded = fixture["cases"].get(name)
            if recorded is None:
                print(f"{name}: not in the fixture")
                ok = False
                continue
            bad = compare(recorded, now)
            added = sorted(set(now) - set(recorded))
            print(f"{name}: {'identical' if not bad else 'DIFFERS'} "
                  f"({len(recorded) - len(bad)} of {len(recorded)} recorded hashes match"
                  + (f"; new: {', '.join(added)}" if added else "") + ")")
            for line in bad:
                print(f"  {line}")
            if "nbv_top5" in recorded:
                for label, rows in (("before", recorded["nbv_top5"]), ("after", now["nbv_top5"])):
                    print(f"  nbv top 5 {label}: " + ", ".join(
                        f"#{r['index']} {r['utility']:.6g}" for r in rows))
            ok &= not bad
    if args.record:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                                capture_output=True, text=True).stdout.strip()
        fixture["recorded_at"] = commit
        FIXTURE.write_text(json.dumps(fixture, indent=1) + "\n")
        print(f"wrote {FIXTURE}")
        return 0
    print("all recorded hashes match" if ok else "outputs DIFFER from the fixture")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
