#!/usr/bin/env python
"""Run-to-run determinism: the same input run twice must give byte-identical outputs.

Runs each scene file twice (``bftaichi.run``) and fuses a recorded dataset twice (``bftaichi fuse``),
each run into its own temporary folder, and prints for every output file ``identical`` or the
first difference (PLY: the first differing byte and the largest vertex / attribute change;
``band.npz``: per array, the largest absolute difference)::

    python tools/determinism.py                              # scenes/bunny.toml + redkitchen 0:100
    python tools/determinism.py scenes/default.toml --data ../shared/data/rgbd/7scenes-redkitchen \\
        --voxel 0.02 --frames 0:100
    python tools/determinism.py scenes/default.toml --no-data --set synthetic.n_views=6

Plots and the preview page are turned off (they are not compared). Exit status 0 if every file
of every input is identical, 1 otherwise.
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

import bftaichi  # noqa: E402
from bftaichi.cli import main as cli_main  # noqa: E402
from bftaichi.io import read_mesh_ply  # noqa: E402

OUTPUTS = ("mesh.ply", "tsdf_mesh.ply", "band.npz")
"""The files compared: the posterior mesh, the TSDF mesh and the band arrays."""

QUIET_SETS = ("run.plots=false", "run.preview=false")
"""Outputs not compared are not written (they would only cost time)."""

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def _first_byte_difference(a: bytes, b: bytes) -> int:
    """Offset of the first differing byte (the shorter length if one is a prefix of the other)."""
    n = min(len(a), len(b))
    diff = np.flatnonzero(np.frombuffer(a[:n], np.uint8) != np.frombuffer(b[:n], np.uint8))
    return int(diff[0]) if diff.size else n


def _max_abs_difference(x: np.ndarray, y: np.ndarray) -> str:
    """``identical``, a shape/dtype mismatch, or the largest ``|x - y|`` (NaN-aware)."""
    if x.shape != y.shape or x.dtype != y.dtype:
        return f"shape/dtype {x.shape} {x.dtype} vs {y.shape} {y.dtype}"
    if np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"):
        return "identical"
    d = np.abs(x.astype(np.float64) - y.astype(np.float64))
    n_diff = int(np.count_nonzero(~(d == 0)))
    return f"max |diff| {np.nanmax(d):.3g} ({n_diff} of {x.size} values differ)"


def _describe_ply(a: Path, b: Path) -> str:
    va, fa, xa = read_mesh_ply(a)
    vb, fb, xb = read_mesh_ply(b)
    parts = [f"vertices {_max_abs_difference(va, vb)}", f"faces {_max_abs_difference(fa, fb)}"]
    parts += [f"{k} {_max_abs_difference(xa[k], xb[k])}" for k in sorted(set(xa) & set(xb))]
    return "; ".join(parts)


def _describe_npz(a: bytes, b: bytes) -> str:
    with np.load(io.BytesIO(a)) as za, np.load(io.BytesIO(b)) as zb:
        names = sorted(set(za.files) | set(zb.files))
        parts = [f"{k} {_max_abs_difference(za[k], zb[k])}" if k in za.files and k in zb.files
                 else f"{k} only in one run" for k in names]
    if all(p.endswith(" identical") for p in parts):
        # same arrays in different bytes: the zip container differs (timestamps, order)
        ia = [(i.filename, i.date_time) for i in zipfile.ZipFile(io.BytesIO(a)).infolist()]
        ib = [(i.filename, i.date_time) for i in zipfile.ZipFile(io.BytesIO(b)).infolist()]
        parts.append(f"zip entries {ia} vs {ib}")
    return "; ".join(parts)


def compare_outputs(dir_a: Path, dir_b: Path) -> list[tuple[str, bool, str]]:
    """(file, identical?, description) for each of :data:`OUTPUTS` in two run folders."""
    rows = []
    for name in OUTPUTS:
        pa, pb = dir_a / name, dir_b / name
        if not (pa.is_file() and pb.is_file()):
            rows.append((name, False, f"missing in run {'1' if not pa.is_file() else '2'}"))
            continue
        a, b = pa.read_bytes(), pb.read_bytes()
        if a == b:
            rows.append((name, True, f"identical ({len(a):,} bytes)"))
            continue
        what = f"differs from byte {_first_byte_difference(a, b):,} ({len(a):,} vs {len(b):,} bytes): "
        what += _describe_npz(a, b) if name.endswith(".npz") else _describe_ply(pa, pb)
        rows.append((name, False, what))
    return rows


def _run_scene(scene: str, sets: list[str], out: Path) -> None:
    cfg = bftaichi.load_config(scene, [*sets, *QUIET_SETS])
    bftaichi.run(cfg, out, progress=False)


def _fuse_data(data: str, voxel: float, frames: str, sets: list[str], out: Path) -> None:
    args = ["fuse", data, "--voxel", str(voxel), "--out", str(out), "-q"]
    if frames:
        args += ["--frames", frames]
    for s in (*sets, *QUIET_SETS):
        args += ["--set", s]
    rc = cli_main(args)
    if rc != 0:
        raise SystemExit(f"bftaichi {' '.join(args)} failed with exit code {rc}")


def check_twice(label: str, produce, tmp: Path) -> bool:
    """Run ``produce(out_dir)`` twice, print the comparison under ``label``; True if identical."""
    seconds = []
    for k in (1, 2):
        t0 = time.perf_counter()
        produce(tmp / f"run{k}")
        seconds.append(time.perf_counter() - t0)
    rows = compare_outputs(tmp / "run1", tmp / "run2")
    print(f"{label} (2 runs, {seconds[0]:.1f} s + {seconds[1]:.1f} s):")
    width = max(len(name) for name, _, _ in rows)
    for name, _, what in rows:
        print(f"  {name:<{width}}  {what}")
    return all(ok for _, ok, _ in rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="*", default=["scenes/bunny.toml"],
                   help="scene files to run twice [default: scenes/bunny.toml]")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override applied to every scene run")
    p.add_argument("--data", default=str(DEFAULT_DATA),
                   help="dataset folder fused twice [default: ../shared/data/rgbd/7scenes-redkitchen]")
    p.add_argument("--no-data", action="store_true", help="skip the dataset")
    p.add_argument("--voxel", type=float, default=0.02, help="voxel size of the dataset runs, m")
    p.add_argument("--frames", default="0:100", help="frames of the dataset [default: 0:100]")
    p.add_argument("--data-set", dest="data_sets", action="append", default=[],
                   metavar="SECTION.KEY=VALUE", help="override applied to the dataset runs")
    args = p.parse_args(argv)

    bftaichi.init("cpu")
    ok = True
    with tempfile.TemporaryDirectory(prefix="bftaichi-determinism-") as tmp:
        tmp = Path(tmp)
        for i, scene in enumerate(args.scenes):
            work = tmp / f"scene{i}"
            ok &= check_twice(scene, lambda out: _run_scene(scene, args.sets, out), work)
        if not args.no_data:
            label = f"{args.data} (--voxel {args.voxel} --frames {args.frames or 'all'})"
            ok &= check_twice(label, lambda out: _fuse_data(args.data, args.voxel, args.frames,
                                                            args.data_sets, out), tmp / "data")
    print("all outputs identical" if ok else "outputs DIFFER between runs")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
