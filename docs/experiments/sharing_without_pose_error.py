"""The noise fit's frames-sharing estimate on dense synthetic captures without any pose error
(docs/measurements.md, "The frames' shared pose error in the variance"): close views agree
better than far ones wherever the bootstrap's own error depends on the view, which must not
read as a shared pose error. Prints the fit per capture::

    python docs/experiments/sharing_without_pose_error.py
"""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
import bftaichi as bf  # noqa: E402
from bftaichi.frame import local_frames  # noqa: E402
from bftaichi.running.pipeline import open_frames  # noqa: E402
from bftaichi.stages.band import build_band  # noqa: E402
from bftaichi.stages.observe import estimate_extra_noise  # noqa: E402

CAPTURES = {  # the default tabletop at 320x240 unless said
    "spiral, 1 turn, 120 views": ["synthetic.n_views=120", "synthetic.trajectory=spiral",
                                  "synthetic.turns=1"],
    "ring, 120 views": ["synthetic.n_views=120", "synthetic.trajectory=ring"],
    "spiral, quarter turn, 120 views": ["synthetic.n_views=120", "synthetic.trajectory=spiral",
                                        "synthetic.turns=0.25"],
    "hemisphere, 200 views": ["synthetic.n_views=200", "synthetic.trajectory=hemisphere"],
    "sphere, spiral half turn, 120 views, 5 mm": [
        "synthetic.mesh=sphere", "synthetic.n_views=120", "synthetic.trajectory=spiral",
        "synthetic.turns=0.5", "tsdf.voxel_size_m=0.005", "tsdf.trunc_m=0.01"],
}
keys = ("sigma_extra_m", "frames_sharing_noise", "sharing_z", "shared_fraction")
print("| capture | " + " | ".join(keys) + " |\n|" + "---|" * (1 + len(keys)))
for name, sets in CAPTURES.items():
    cfg = bf.load_config(None, sets)
    recon = bf.Reconstructor(cfg)
    for f in open_frames(cfg):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    fit = estimate_extra_noise(local_frames(recon.frames, recon.origin), band, cfg.observation,
                               cfg.tsdf.voxel_size_m, cfg.tsdf.bootstrap_trunc_m,
                               (cfg.scene.depth_min_m, cfg.scene.depth_max_m))
    cells = ["-" if fit.get(k) is None else f"{fit[k]:.4g}" for k in keys]
    print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
