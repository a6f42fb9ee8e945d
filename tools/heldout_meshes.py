#!/usr/bin/env python
"""Meshes the model was never developed on, for the development suite (issue 15).

The suite's seven meshes (``../shared/data/meshes``) are the ones every model change was judged
on, so its figures may flatter the model. These five were not looked at before the model was
fixed (2026-12-06), and need no download:

==========  ================================================================================
head        a robot head (``meshcat/viewer/data/head_multisense.obj``, shipped with meshcat):
            a low-polygon CAD model, open, many small parts
disk        a slotted disk (``meshcat/tests/data/slotted_disk.stl``): flat faces, sharp
            edges, through-slots
torus       a torus, radii 0.1 and 0.035 (``trimesh.creation.torus``)
capsule     a capsule, radius 0.05, 0.2 between the centres (``trimesh.creation.capsule``)
bracket     an L-shaped bracket (an extruded L, 0.3 x 0.2 x 0.12, 5 cm thick): flat faces,
            one concave edge, subdivided to 1 cm triangles
==========  ================================================================================

Write them as OBJ into ``OUT/meshes`` and run the suite on them::

    python tools/heldout_meshes.py /tmp/heldout
    python tools/suite.py --data /tmp/heldout --meshes head,disk,torus,capsule,bracket --no-sphere

(``python tools/suite.py --heldout`` does both, in a temporary folder.)
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

import numpy as np

#: The held-out meshes, in the suite's order.
HELDOUT = ("head", "disk", "torus", "capsule", "bracket")


def _bracket():
    """An L extruded along z, its faces outward, subdivided to 1 cm edges."""
    import trimesh

    outline = np.array([(0, 0), (0.3, 0), (0.3, 0.05), (0.06, 0.05), (0.06, 0.2), (0, 0.2)])
    n, height = len(outline), 0.12
    vertices = np.vstack([np.c_[outline, np.zeros(n)], np.c_[outline, np.full(n, height)]])
    faces = []
    for a, b, c in ((0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)):  # a fan from the L's corner
        faces += [(a, c, b), (a + n, b + n, c + n)]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh.subdivide_to_size(0.01)


def heldout_mesh(name: str):
    """The held-out mesh ``name`` (a trimesh.Trimesh, its own units)."""
    import trimesh

    if name == "head":
        path = resources.files("meshcat") / "viewer" / "data" / "head_multisense.obj"
        return trimesh.load(str(path), force="mesh")
    if name == "disk":
        path = resources.files("meshcat") / "tests" / "data" / "slotted_disk.stl"
        return trimesh.load(str(path), force="mesh")
    if name == "torus":
        return trimesh.creation.torus(0.1, 0.035, major_sections=96, minor_sections=48)
    if name == "capsule":
        return trimesh.creation.capsule(height=0.2, radius=0.05, count=[48, 48])
    if name == "bracket":
        return _bracket()
    raise ValueError(f"no held-out mesh {name!r} (one of {', '.join(HELDOUT)})")


def write_heldout(out: Path, names=HELDOUT) -> Path:
    """Write the meshes as ``out/meshes/<name>.obj`` (no materials); return ``out``."""
    folder = Path(out) / "meshes"
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        obj = heldout_mesh(name).export(file_type="obj", include_texture=False,
                                        include_normals=False)
        (folder / f"{name}.obj").write_text(obj)
    return Path(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path, help="folder to write meshes/<name>.obj into")
    args = ap.parse_args(argv)
    write_heldout(args.out)
    print(f"wrote {', '.join(HELDOUT)} into {args.out / 'meshes'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
