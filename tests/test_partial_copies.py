"""Partial and subsampled copies of a sequence (issue [formats2]): users copy the first N images,
or every k-th, out of a sequence and keep its whole trajectory. Each format's loader must then
load exactly those frames with their own poses, refuse two files of one frame number, and name
an image that has no pose.

The fixtures are those of tests/test_datasets_formats.py (4 views of the tabletop, written in
each format's conventions). CO3D is not here: its frames are the entries of
``frame_annotations.jgz`` and each entry names its own files, so a copy edits that file.
"""

from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from bftaichi.errors import DataError
from test_datasets_formats import SPECS, load, scene, tum_stamp, write  # noqa: F401 (fixture)

#: formats whose poses live in one trajectory file, indexed by frame number
ONE_FILE = ("replica", "redwood", "folder")
FORMATS = ("7scenes", "tum", "replica", "scannet", "redwood", "folder", "folder_tcw")


def _keep_only(root: Path, name: str, keep) -> None:
    """Delete the depth images (and colour) of the frames not in ``keep``; the poses stay."""
    for k in range(4):
        if k in keep:
            continue
        depth = SPECS[name].depth_file(root, k)
        depth.unlink()
        for colour in depth.parent.parent.glob(f"*/{depth.stem}.jpg"):
            colour.unlink()
        if name == "replica":
            (depth.parent / f"frame{k:06d}.jpg").unlink()
    if name == "tum":  # TUM lists its images: a copy lists what it holds
        listing = root / "depth.txt"
        lines = listing.read_text().splitlines(keepends=True)
        listing.write_text("".join(line for line in lines if line.startswith("#")
                                   or any(f"{tum_stamp(k):.6f}" in line for k in keep)))


def _frames(ds):
    return [(f.name, f.depth_m, f.T_W_C) for f in ds]


@pytest.mark.parametrize("keep", [(0, 1), (0, 2), (1, 3)], ids=["first-2", "every-2nd", "odd"])
@pytest.mark.parametrize("name", FORMATS)
def test_a_partial_copy_loads_its_frames_with_their_own_poses(tmp_path, scene, name, keep):
    root = write(tmp_path, scene, name)
    full = _frames(load(root, name))
    assert len(full) == 4
    copy = shutil.copytree(root, tmp_path / "copy")
    _keep_only(copy, name, keep)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        part = _frames(load(copy, name))
    assert [n for n, _, _ in part] == [full[k][0] for k in keep]
    for (_, depth, T), k in zip(part, keep):
        np.testing.assert_array_equal(depth, full[k][1])
        np.testing.assert_array_equal(T, full[k][2])
    counts = [str(w.message) for w in caught if "poses for" in str(w.message)]
    if name in ONE_FILE:  # one warning, with both counts
        assert len(counts) == 1 and "4 poses for 2 depth images" in counts[0], counts
    else:
        assert not counts


@pytest.mark.parametrize("name, original, duplicate", [
    ("7scenes", "seq-01/frame-000001.depth.png", "seq-01/frame-1.depth.png"),
    ("replica", "results/depth000001.png", "results/depth1.png"),
    ("scannet", "depth/1.png", "depth/01.png"),
    ("redwood", "depth/000001.png", "depth/1.png"),
    ("folder", "depth/0001.png", "depth/1.png"),
    ("folder_tcw", "depth/1.npy", "depth/001.npy"),
])
def test_two_files_of_one_frame_number_are_refused_naming_both(tmp_path, scene, name, original,
                                                              duplicate):
    root = write(tmp_path, scene, name)
    shutil.copy(root / original, root / duplicate)
    for suffix in (".pose.txt",):  # 7-Scenes: the duplicate has its pose file too
        if name == "7scenes":
            shutil.copy(root / original.replace(".depth.png", suffix),
                         root / duplicate.replace(".depth.png", suffix))
    with pytest.raises(DataError) as e:
        load(root, name)
    message = str(e.value)
    assert Path(original).name in message and Path(duplicate).name in message, message
    assert "same frame number 1" in message


@pytest.mark.parametrize("name, trajectory, drop", [
    ("replica", "traj.txt", lambda text: "".join(text.splitlines(True)[:2])),  # frames 0-1
    ("folder", "poses.txt", lambda text: "".join(text.splitlines(True)[:2])),
    ("redwood", "trajectory.log", lambda text: "".join(text.splitlines(True)[:10])),
])
def test_an_image_without_a_pose_is_named(tmp_path, scene, name, trajectory, drop):
    """The trajectory holds frames 0-1 only; the copy holds images 0-3: image 2 has no pose."""
    root = write(tmp_path, scene, name)
    path = root / trajectory
    path.write_text(drop(path.read_text()))
    with pytest.raises(DataError, match=re.escape(SPECS[name].depth_file(root, 2).name)
                       + r".*no pose for frame number 2"):
        load(root, name)


def test_the_issue_case_four_replica_images_and_a_2000_line_trajectory(tmp_path, scene):
    """What another library ships for its tests: results/ with 4 images, the sequence's whole
    traj.txt (2000 lines). The 4 images take lines 0-3."""
    root = write(tmp_path, scene, "replica")
    traj = root / "traj.txt"
    lines = traj.read_text().splitlines(True)
    traj.write_text("".join(lines + [lines[0]] * 1996))
    with pytest.warns(UserWarning, match="2000 poses for 4 depth images"):
        ds = load(root, "replica")
    full = _frames(load(write(tmp_path / "ref", scene, "replica"), "replica"))
    for (n, depth, T), (n0, depth0, T0) in zip(_frames(ds), full):
        assert n == n0
        np.testing.assert_array_equal(T, T0)
