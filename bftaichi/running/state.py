"""A run's fusion state, and what ``bftaichi update`` does with it (issue 19).

A run made with ``--set run.keep_state=true`` also writes ``fusion_state.npz``: the TSDF's
integer sums over every observed voxel (``ijk`` int32 x3, ``tsdf_sum`` int64, ``count`` int32
[, ``rgb_sum`` int32 x4]: 24 bytes a voxel, 40 with colour), the grid ``origin`` and, per
frame, its ``frame_names`` and the ``poses`` (N, 4, 4) it was fused with.
:func:`bftaichi.running.update.update_run`
restores that TSDF, subtracts each frame whose pose changed at its old pose and adds it at the
new one (exactly: :meth:`bftaichi.TSDFVolume.remove`), then runs the posterior and every output
as ``bftaichi run`` does, on the frames at their new poses, and replaces the folder's outputs
together (staged, like a run). ``report.json`` gains ``update``: the frames that moved.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry import check_pose

__all__ = ["STATE_FILE", "UpdatePlan", "Reposed", "save_state", "read_poses"]

STATE_FILE = "fusion_state.npz"


@dataclass
class UpdatePlan:
    """What :func:`bftaichi.running.pipeline.run` does instead of integrating every frame."""

    state: dict  # the TSDF's saved state (TSDFVolume.state)
    names: list[str]  # every frame's name, in the run's order
    old: np.ndarray  # (N, 4, 4) the poses the state was fused with
    new: np.ndarray  # (N, 4, 4) the poses now
    moved: list[int]  # positions of the frames whose pose changed
    source: str  # the poses file or folder

    def apply(self, recon, frames, clean) -> None:
        """Load the state into ``recon``'s (new) TSDF and move the frames that moved;
        ``frames`` the dataset at its recorded poses, ``clean`` the depth cleaning
        Reconstructor.integrate applies."""
        recon.tsdf.load_state(self.state)
        for i in self.moved:
            f = frames[i]
            if f.name != self.names[i]:
                raise DataError(f"{STATE_FILE}: frame {i} is {self.names[i]!r} in the saved "
                                f"state but {f.name!r} in the dataset now; re-run the fusion")
            depth = clean(f.depth_m)
            recon.tsdf.remove(depth, f.K, self.old[i], rgb=f.rgb, name=f.name)
            recon.tsdf.integrate(depth, f.K, self.new[i], rgb=f.rgb, name=f.name)

    def summary(self) -> dict:
        return {"poses": self.source, "moved": [self.names[i] for i in self.moved],
                "n_moved": len(self.moved), "n_frames": len(self.names)}


class Reposed:
    """A frame source whose frames carry the poses of ``poses`` (N, 4, 4), in order."""

    def __init__(self, frames, poses: np.ndarray):
        self.frames, self.poses = frames, poses
        for key in ("K", "image_size", "name", "gt_mesh", "gt_mesh_path"):
            if hasattr(frames, key):
                setattr(self, key, getattr(frames, key))

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int):
        return replace(self.frames[i], T_W_C=self.poses[i])

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def save_state(path: Path, tsdf, names: list[str], poses: list[np.ndarray]) -> int:
    """Write ``fusion_state.npz`` (see the module docstring); return its size in bytes."""
    from ..io import write_npz

    write_npz(path, frame_names=np.array(names, dtype=str),
              poses=np.asarray(poses, np.float64).reshape(-1, 4, 4), **tsdf.state())
    return path.stat().st_size


def read_poses(path: str | Path, names: list[str]) -> dict[str, np.ndarray]:
    """New poses ``T_W_C`` by frame name, from

    * a folder of per-frame files, each a 4x4 matrix (``<name>.txt`` or ``<name>.pose.txt``, the
      7-Scenes and folder layouts; frames without a file keep their pose); or
    * a text file with one pose per line: ``name`` and 16 numbers (row-major 4x4), or 16
      numbers alone on exactly one line per frame, in the run's frame order (Replica's
      ``traj.txt``);
    * a TUM trajectory, ``timestamp tx ty tz qx qy qz qw`` per line (the ``tum`` format's
      ``groundtruth.txt``): a line whose first field is a frame's name gives that frame's pose;
      when none does and the frames are named by their timestamps (TUM's depth stems), each
      frame takes the line nearest in time within 0.02 s (the ``tum`` loader's rule), and the
      frames without one keep their pose;
    * an Open3D ``.log`` trajectory (the ``redwood`` format): one block per frame of the run,
      in its order.

    Every pose is checked (finite, rigid); errors name the file and line."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"--poses: {path} does not exist")
    known = set(names)
    out: dict[str, np.ndarray] = {}
    if path.is_dir():
        for f in sorted(path.glob("*.txt")):
            name = f.name[:-len(".pose.txt")] if f.name.endswith(".pose.txt") else f.stem
            if name not in known:
                continue
            try:
                T = np.loadtxt(f, dtype=np.float64).reshape(4, 4)
            except ValueError as e:
                raise DataError(f"{f}: not a 4x4 matrix ({e})") from None
            out[name] = check_pose(T, str(f))
        if not out:
            raise DataError(f"--poses: no file in {path} is named after a frame of the run "
                            f"(e.g. {names[0]}.txt or {names[0]}.pose.txt)")
        return out
    if path.suffix == ".log":
        return _read_log_poses(path, names)
    rows = [(n, line.replace(",", " ").split()) for n, line in
            enumerate(path.read_text().splitlines(), 1)
            if line.strip() and not line.lstrip().startswith("#")]
    if rows and all(len(tokens) == 8 for _, tokens in rows):
        return _read_tum_poses(path, rows, names)
    unnamed = []
    for n, tokens in rows:
        named = len(tokens) == 17
        if len(tokens) not in (16, 17):
            raise DataError(f"{path}:{n}: expected 16 numbers (a row-major 4x4 T_W_C), "
                            f"optionally after a frame name; got {len(tokens)} fields")
        try:
            values = np.array([float(v) for v in tokens[named:]])
        except ValueError:
            raise DataError(f"{path}:{n}: not a list of numbers") from None
        T = check_pose(values.reshape(4, 4), f"{path}:{n}")
        if named:
            if tokens[0] not in known:
                raise DataError(f"{path}:{n}: no frame of the run is named {tokens[0]!r}")
            out[tokens[0]] = T
        else:
            unnamed.append(T)
    if unnamed and out:
        raise DataError(f"{path}: mixes named and unnamed poses")
    if unnamed:
        if len(unnamed) != len(names):
            raise DataError(f"{path}: {len(unnamed)} unnamed poses for a run of {len(names)} "
                            "frames; give one per frame, or put each frame's name first")
        out = dict(zip(names, unnamed))
    if not out:
        raise DataError(f"{path}: no poses")
    return out


def _read_log_poses(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    """An Open3D ``.log`` trajectory, one block per frame of the run in its order."""
    from ..formats.readers import pose_from_values
    from ..formats.redwood import RedwoodDataset

    blocks = RedwoodDataset._read_log(path)
    if len(blocks) != len(names):
        raise DataError(f"{path}: {len(blocks)} poses for a run of {len(names)} frames; an "
                        ".log gives one per frame, in the run's order")
    return {name: pose_from_values(values, f"{path}: lines {lineno}-{lineno + 4}")
            for name, (_, lineno, values) in zip(names, blocks)}


def _read_tum_poses(path: Path, rows: list, names: list[str]) -> dict[str, np.ndarray]:
    """``timestamp|name tx ty tz qx qy qz qw`` lines (see :func:`read_poses`)."""
    from ..formats.tum import _nearest, _quaternion_pose

    def pose(n, tokens):
        try:
            values = np.array([float(v) for v in tokens[1:]])
        except ValueError:
            raise DataError(f"{path}:{n}: not 'timestamp tx ty tz qx qy qz qw'") from None
        return _quaternion_pose(values, f"{path}:{n}")

    known = set(names)
    out = {tokens[0]: pose(n, tokens) for n, tokens in rows if tokens[0] in known}
    if out:
        return out
    try:
        stamps = np.array([float(name) for name in names])
        times = np.array([float(tokens[0]) for _, tokens in rows])
    except ValueError:
        raise DataError(f"{path}: no line's first field is a frame name of the run (e.g. "
                        f"{names[0]!r}), and the frames are not named by timestamps") from None
    order = np.argsort(times, kind="stable")
    pick, gap = _nearest(times[order], stamps)
    out = {name: pose(*rows[order[k]]) for name, k, g in zip(names, pick, gap) if g <= 0.02}
    if not out:
        raise DataError(f"{path}: no pose within 0.02 s of a frame of the run")
    return out
