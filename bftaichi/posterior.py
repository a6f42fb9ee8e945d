"""The result of Algorithm 1: the Gaussian posterior of the SDF over the narrow band
(:class:`Posterior`), what ``band.npz`` holds of it, and its surface (step 7)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .errors import DataError
from .stages.band import Band
from .stages.observe import ObservationConfig

__all__ = ["Posterior"]

#: band.npz arrays of the DESIGN.md section 4 contract, and those that let planning and
#: evaluation reload the posterior's observation model (not written by older versions).
BAND_ARRAYS = ("ijk", "voxel_size", "mean", "var", "tsdf", "weight")
MODEL_ARRAYS = ("observation", "trunc_m", "bootstrap_trunc_m", "sigma_extra_m")


@dataclass(eq=False)
class Posterior:
    """The Gaussian posterior of the SDF over the narrow band.

    Attributes:
        band: the :class:`~bftaichi.stages.band.Band` (its ``ijk``, ``tsdf`` and ``weight``
            are also attributes of the posterior).
        voxel_size: metres.
        mean: (N,) float32 MAP signed distance, metres (positive in free space).
        var: (N,) float32 estimated marginal variance ``diag(Q^-1)``, metres^2.
        observation: the observation model of the solve (None for a band.npz of an older
            version): what the planner must reproduce to predict a new view's information.
        trunc_m: the observation truncation tau, metres; ``bootstrap_trunc_m``: alpha tau.
        sigma_extra_m: the extra per-pixel noise fitted to the frames, metres
            (``observation.fit_noise``; 0 without a fit).
        solver: MAP PCG stats (converged, iterations, relative_residual, free_space).
        variance: probe stats (probes, method, iterations, not_converged).
        observations: counts of the observation pass and the noise fit.
        seconds: wall time of each sub-stage (band, noise, observe, prior, map, variance).
    """

    band: Band
    voxel_size: float
    mean: np.ndarray
    var: np.ndarray
    observation: ObservationConfig | None = None
    trunc_m: float = 0.0
    bootstrap_trunc_m: float = 0.0
    sigma_extra_m: float = 0.0
    solver: dict = field(default_factory=dict)
    variance: dict = field(default_factory=dict)
    observations: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)

    ijk = property(lambda self: self.band.ijk, doc="(N, 3) int32 band voxel indices, sorted.")
    tsdf = property(lambda self: self.band.tsdf, doc="(N,) float32 bootstrap TSDF, metres.")
    weight = property(lambda self: self.band.weight, doc="(N,) float32 bootstrap weight.")

    @property
    def sigma(self) -> np.ndarray:
        """(N,) float32 posterior standard deviation, metres."""
        return np.sqrt(np.maximum(self.var, 0)).astype(np.float32)

    def band_arrays(self) -> dict:
        """The arrays of ``band.npz``: the DESIGN.md section 4 contract (``ijk, voxel_size,
        mean, var, tsdf, weight``) and the observation model (``observation``: its settings as
        a JSON string, ``trunc_m``, ``bootstrap_trunc_m``, ``sigma_extra_m``; float64, metres)."""
        arrays = {"ijk": self.ijk, "voxel_size": np.float32(self.voxel_size), "mean": self.mean,
                  "var": self.var, "tsdf": self.tsdf, "weight": self.weight}
        if self.observation is not None:
            arrays.update(observation=np.array(json.dumps(asdict(self.observation))),
                          trunc_m=np.float64(self.trunc_m),
                          bootstrap_trunc_m=np.float64(self.bootstrap_trunc_m),
                          sigma_extra_m=np.float64(self.sigma_extra_m))
        return arrays

    @classmethod
    def load(cls, path) -> "Posterior":
        """The posterior saved as ``band.npz`` by a run (``mean`` and ``var`` must be there:
        a ``run.stages = "tsdf_only"`` run has no posterior). Raises DataError naming the file."""
        try:
            with np.load(path) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise DataError(f"{path}: cannot read the band ({e})") from None
        missing = [k for k in BAND_ARRAYS if k not in data]
        if missing:
            hint = " (a run.stages = 'tsdf_only' run has no posterior)" if "mean" in missing else ""
            raise DataError(f"{path}: missing arrays {', '.join(missing)}{hint}")
        n = len(data["ijk"])
        if data["ijk"].shape != (n, 3) or any(data[k].shape != (n,) for k in
                                              ("mean", "var", "tsdf", "weight")):
            raise DataError(f"{path}: arrays ijk (N, 3) and mean/var/tsdf/weight (N,) disagree")
        model = {}
        if all(k in data for k in MODEL_ARRAYS):
            try:
                obs = ObservationConfig(**json.loads(str(data["observation"])))
            except (ValueError, TypeError) as e:
                raise DataError(f"{path}: the array 'observation' is not this version's "
                                f"observation settings ({e})") from None
            model = {"observation": obs, "trunc_m": float(data["trunc_m"]),
                     "bootstrap_trunc_m": float(data["bootstrap_trunc_m"]),
                     "sigma_extra_m": float(data["sigma_extra_m"])}
        band = Band.from_voxels(data["ijk"], data["tsdf"], data["weight"])
        return cls(band=band, voxel_size=float(data["voxel_size"]),
                   mean=data["mean"].astype(np.float32), var=data["var"].astype(np.float32),
                   **model)

    def save(self, out_dir) -> Path:
        """Write ``mesh.ply`` (:meth:`extract_mesh`, vertex ``sigma``) and ``band.npz``
        (:meth:`band_arrays`) into ``out_dir`` (DESIGN.md section 4), atomically; return the
        folder. :meth:`load` reads the band back."""
        from .io import ensure_out_dir, write_mesh_ply, write_npz

        out = ensure_out_dir(out_dir)
        mesh = self.extract_mesh()
        write_mesh_ply(out / "mesh.ply", mesh.vertices, mesh.faces,
                       vertex_attrs={"sigma": mesh.vertex_attributes["sigma"]})
        write_npz(out / "band.npz", **self.band_arrays())
        return out

    def extract_mesh(self) -> trimesh.Trimesh:
        """Step 7: marching cubes at ``mean = 0`` over cells whose 8 corners are band voxels
        observed by the bootstrap (weight > 0), with vertex attribute ``sigma`` (metres,
        trilinear from the voxel variances).

        Why observed corners only: in the one-voxel dilation around the band, nothing but the
        prior sets the mean, and the membrane prior flattens it toward the anchors and 0, which
        makes zero crossings where no surface was seen (measured on the default scene: 12 % of
        vertices more than 1 cm from the truth, 92 % of those in cells with an unobserved
        corner)."""
        from .stages.surface import extract_mesh, sample_field

        vertices, faces = extract_mesh(self.ijk, self.mean, self.weight > 0, self.voxel_size)
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        sigma = np.zeros(0, np.float32)
        if len(vertices):
            var = sample_field(self.ijk, self.var, np.ones(len(self.ijk), bool), self.voxel_size,
                               vertices)
            sigma = np.sqrt(np.maximum(np.nan_to_num(var), 0)).astype(np.float32)
        mesh.vertex_attributes["sigma"] = sigma
        return mesh

    def warm_start(self, ijk: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """``x0`` with the voxels of ``ijk`` that this posterior also holds set to its mean
        (a PCG start when frames are added)."""
        from kernels.layout import block_key_np

        k_prev = block_key_np(np.asarray(self.ijk, np.int64))  # one int64 per voxel, ascending
        k_new = block_key_np(np.asarray(ijk, np.int64))
        pos = np.clip(np.searchsorted(k_prev, k_new), 0, len(k_prev) - 1)
        same = k_prev[pos] == k_new
        out = np.array(x0, np.float32, copy=True)
        out[same] = self.mean[pos[same]]
        return out
