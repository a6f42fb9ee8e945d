"""``bftaichi update``: new poses for a run folder, without re-fusing its frames (issue 19;
the fusion state and the plan are :mod:`bftaichi.running.state`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError
from .state import STATE_FILE, Reposed, UpdatePlan, read_poses

__all__ = ["update_run"]


def update_run(out_dir: str | Path, poses_path: str | Path, *, progress: bool = True):
    """Move the frames of the run in ``out_dir`` to the poses of ``poses_path``
    (:func:`read_poses`) and rewrite its outputs; return the run's report, or None when no
    pose changed (nothing is rewritten)."""
    from ..config import load_config
    from .pipeline import open_frames, run

    out = Path(out_dir)
    for name, why in (("config.toml", "OUT_DIR must hold the outputs of `bftaichi run` or "
                       "`bftaichi fuse`"),
                      (STATE_FILE, "the run did not keep its fusion state: run it again with "
                       "--set run.keep_state=true")):
        if not (out / name).exists():
            raise DataError(f"{out / name} does not exist: {why}")
    cfg = load_config(out / "config.toml")
    try:
        with np.load(out / STATE_FILE) as z:
            state = {k: z[k] for k in z.files}
        names = [str(n) for n in state.pop("frame_names")]
        old = state.pop("poses")
    except (OSError, ValueError, KeyError) as e:
        raise DataError(f"{out / STATE_FILE} is not a readable fusion state ({e})") from None
    new_by_name = read_poses(poses_path, names)
    new = np.stack([new_by_name.get(n, old[i]) for i, n in enumerate(names)])
    moved = [i for i in range(len(names)) if not np.array_equal(new[i], old[i])]
    if not moved:
        return None
    frames = open_frames(cfg)
    if len(frames) != len(names):
        raise DataError(f"{STATE_FILE}: the run fused {len(names)} frames, the dataset "
                        f"{cfg.scene.data} now has {len(frames)}; re-run the fusion")
    plan = UpdatePlan(state=state, names=names, old=old, new=new, moved=moved,
                      source=str(Path(poses_path).resolve()))
    return run(cfg, out, overwrite=True, progress=progress, frames=Reposed(frames, new),
               update=plan)
