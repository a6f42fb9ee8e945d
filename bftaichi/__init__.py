"""bftaichi: CPU-first probabilistic signed-distance fusion (BayesFusion-SDF) on Taichi kernels.

The public API is small::

    import bftaichi as bf
    bf.init("cpu")                                   # optional; done on first use
    recon = bf.Reconstructor(bf.Config.from_toml("scenes/bunny.toml"))   # or bf.Config()
    for frame in bf.open_dataset("path/to/frames"):  # every supported layout, lazily
        recon.integrate(frame.depth_m, frame.K, frame.T_W_C)
    post = recon.solve()                             # bf.Posterior: mean, var, band, stats
    mesh = post.extract_mesh()                       # trimesh.Trimesh, vertex attribute sigma
    ranked = bf.nbv.rank(post, bf.nbv.candidates_around(post), recon.K, recon.image_size)
    recon.save("out/")                               # mesh.ply, tsdf_mesh.ply, band.npz
    report = bf.run(bf.load_config("scenes/bunny.toml"), "out/bunny")   # the whole pipeline

``bf.TSDFVolume`` is the bootstrap alone; ``kernels`` holds the Taichi code for embedding.
"""

import os as _os

# Taichi prints a banner on import; keep library output quiet unless the user asks for it.
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

from .backend import init, _skip_frozen_frame_scans  # noqa: E402

_skip_frozen_frame_scans()  # before Taichi is imported: ~0.3 s of every process's start
del _skip_frozen_frame_scans
from .config import Config, load_config  # noqa: E402
from .formats import open_dataset  # noqa: E402
from .errors import BftaichiError, ConfigError, DataError, NoSurfaceError  # noqa: E402
from .frame import Frame  # noqa: E402
from .stages.integrate import TSDFVolume  # noqa: E402
from .running.pipeline import run  # noqa: E402
from .posterior import Posterior  # noqa: E402
from .reconstructor import Reconstructor  # noqa: E402
from .version import __version__  # noqa: E402
from .planning import nbv  # noqa: E402

__all__ = ["init", "Config", "load_config", "open_dataset", "Frame", "TSDFVolume",
           "Reconstructor", "Posterior", "nbv", "run",
           "BftaichiError", "ConfigError", "DataError", "NoSurfaceError", "__version__"]
