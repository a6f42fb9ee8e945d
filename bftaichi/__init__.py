"""bftaichi: CPU-first probabilistic signed-distance fusion (BayesFusion-SDF) on Taichi kernels.

The public API is small::

    import bftaichi as bf
    bf.init("cpu")                                   # optional; done on first use
    cfg = bf.load_config("scenes/bunny.toml")        # or bf.Config()
    vol = bf.TSDFVolume(voxel_size_m=0.01, trunc_m=0.04)
    for frame in bf.open_dataset("path/to/frames"):  # 7scenes / bfsdf layouts, lazily
        vol.integrate(frame.depth_m, frame.K, frame.T_W_C)
    mesh = vol.extract_mesh()                        # trimesh.Trimesh, world frame, metres
    report = bf.run(cfg, "out/bunny")                # the whole pipeline, files on disk
"""

import os as _os

# Taichi prints a banner on import; keep library output quiet unless the user asks for it.
_os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

__version__ = "0.1.0"

from .backend import init  # noqa: E402
from .config import Config, load_config  # noqa: E402
from .datasets import open_dataset  # noqa: E402
from .errors import BftaichiError, ConfigError, DataError, NoSurfaceError  # noqa: E402
from .frame import Frame  # noqa: E402
from .fusion import TSDFVolume  # noqa: E402
from .pipeline import run  # noqa: E402

__all__ = ["init", "Config", "load_config", "open_dataset", "Frame", "TSDFVolume", "run",
           "BftaichiError", "ConfigError", "DataError", "NoSurfaceError", "__version__"]
