"""The result of Algorithm 1: the Gaussian posterior of the SDF over the narrow band
(:class:`Posterior`), what ``band.npz`` holds of it, and its surface (step 7).

Coordinates: the band's ``ijk`` are local; voxel ``ijk`` is at world
``origin + (ijk + 0.5) * voxel_size`` (``origin`` float64, zeros for a scene near the world
origin). :meth:`Posterior.extract_mesh` returns world coordinates (``local=True``: the local
frame); ``mesh.ply`` holds world coordinates (float64 ``x y z`` when the origin is not zero)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .errors import DataError
from .geometry import points_in_world
from .stages.band import Band
from .stages.observe import ObservationConfig

__all__ = ["Posterior", "VERTEX_ATTRS", "mesh_attrs", "read_band"]

#: band.npz arrays of the DESIGN.md section 4 contract, and those that let planning and
#: evaluation reload the posterior's observation model (not written by older versions).
BAND_ARRAYS = ("ijk", "voxel_size", "mean", "var", "tsdf", "weight")
#: band.npz's ``origin`` (float64 (3,), metres) of the local grid; absent in older versions
#: (whose grid is the world's: zeros).
ORIGIN_ARRAY = "origin"
MODEL_ARRAYS = ("observation", "trunc_m", "bootstrap_trunc_m", "sigma_extra_m", "sigma_corr_m")
#: |grad mean| is floored here for ``sigma_pos = sigma / |grad mean|`` (dimensionless; an SDF
#: has slope 1). Where the mean is nearly flat (thin structures, where the two sides' bands
#: meet, or far from the data) the position is not determined by the SDF's std alone, and an
#: unbounded ratio would swamp the colour scale; 0.1 caps sigma_pos at 10 sigma.
MIN_GRADIENT = 0.1

#: The float vertex properties of ``mesh.ply`` after ``x y z`` (DESIGN.md section 4), metres:
#: the std of the SDF at the vertex and of the surface position along the normal.
VERTEX_ATTRS = ("sigma", "sigma_pos")


def mesh_attrs(mesh: trimesh.Trimesh) -> dict:
    """The :data:`VERTEX_ATTRS` of a mesh from :meth:`Posterior.extract_mesh`, for
    :func:`~bftaichi.io.write_mesh_ply`."""
    return {name: mesh.vertex_attributes[name] for name in VERTEX_ATTRS}


def read_band(path) -> dict[str, np.ndarray]:
    """The arrays of a ``band.npz`` (:meth:`Posterior.band_arrays`, or the ``ijk, voxel_size,
    tsdf, weight`` of a ``run.stages = "tsdf_only"`` run), checked so that no reader fails
    deeper: an intact .npz archive; ``ijk`` (N, 3) integers, unique and sorted, ``tsdf`` and
    ``weight`` (N,) finite floats, weight >= 0 (:func:`kernels.band.check_voxels`; returned
    as int32 / float32); ``voxel_size`` one positive finite float; where present, ``mean``,
    ``var`` (N,) and ``cov`` (N, 3) finite floats, ``origin`` 3 finite floats, the scalars
    of the observation model finite floats >= 0 and ``observation`` a string. Arrays of other
    names are returned unchecked (a newer version may add some).

    Raises DataError naming the file and what is wrong."""
    from kernels.band import check_voxels

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: band file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    # zipfile, zlib and numpy's .npy header parser raise many types on a damaged archive; an
    # .npy file (not an archive) loads as one array, which has no context manager
    except Exception as e:  # noqa: BLE001 - re-raised as DataError naming the file
        raise DataError(f"{path}: cannot read the band, the .npz archive is damaged or "
                        f"truncated ({type(e).__name__}: {e})") from None
    missing = [k for k in ("ijk", "voxel_size", "tsdf", "weight") if k not in data]
    if missing:
        raise DataError(f"{path}: missing arrays {', '.join(missing)}")
    floats = ("voxel_size", "tsdf", "weight", "mean", "var", "cov", ORIGIN_ARRAY,
              *MODEL_ARRAYS[1:])
    for name in floats:
        if name in data and data[name].dtype.kind != "f":
            raise DataError(f"{path}: array {name} has dtype {data[name].dtype}, not floating "
                            "point")
    try:
        data["ijk"], data["tsdf"], data["weight"] = check_voxels(
            data["ijk"], data["tsdf"], data["weight"], what="array")
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    n = len(data["ijk"])
    shapes = {"voxel_size": (), "mean": (n,), "var": (n,), "cov": (n, 3), ORIGIN_ARRAY: (3,),
              **{name: () for name in MODEL_ARRAYS}}
    for name, shape in shapes.items():
        if name in data and data[name].shape != shape:
            raise DataError(f"{path}: array {name} has shape {data[name].shape}, not {shape}"
                            f"{f' (ijk has {n} voxels)' if n in shape else ''}")
        if name in data and name != "observation" and not np.isfinite(data[name]).all():
            raise DataError(f"{path}: array {name} holds NaN or inf")
    if not data["voxel_size"] > 0:
        raise DataError(f"{path}: voxel_size = {data['voxel_size']} is not positive")
    negative = [name for name in MODEL_ARRAYS[1:] if name in data and data[name] < 0]
    if negative:
        raise DataError(f"{path}: {negative[0]} = {data[negative[0]]} is negative")
    if "observation" in data and data["observation"].dtype.kind != "U":
        raise DataError(f"{path}: array observation has dtype {data['observation'].dtype}, "
                        "not a string of settings")
    return data


@dataclass(eq=False)
class Posterior:
    """The Gaussian posterior of the SDF over the narrow band.

    Attributes:
        band: the :class:`~bftaichi.stages.band.Band` (its ``ijk``, ``tsdf`` and ``weight``
            are also attributes of the posterior).
        voxel_size: metres.
        mean: (N,) float32 MAP signed distance, metres (positive in free space).
        var: (N,) float32 estimated marginal variance ``diag(Q^-1)``, metres^2.
        cov: (N, 3) float32 estimated covariance of each voxel with its +x, +y, +z neighbour,
            ``(Q^-1)_{i, i+e}``, metres^2 (0 where the neighbour is not in the band), from the
            same probes as ``var`` (:func:`~bftaichi.stages.variance.estimate_variance`); None
            for a band.npz of an older version, whose vertex sigma is then the bound
            interpolated from ``var`` (:meth:`extract_mesh`).
        observation: the observation model of the solve (None for a band.npz of an older
            version): what the planner must reproduce to predict a new view's information.
        trunc_m: the observation truncation tau, metres; ``bootstrap_trunc_m``: alpha tau.
        sigma_extra_m: the extra per-pixel noise fitted to the frames, metres
            (``observation.fit_noise``; 0 without a fit); ``sigma_corr_m``: its part shared by
            neighbouring pixels (0 in a band.npz of an older version).
        solver: MAP PCG stats (converged, iterations, relative_residual, free_space).
        variance: probe stats (probes, method, iterations, not_converged).
        observations: counts of the observation pass and the noise fit.
        seconds: wall time of each sub-stage (band, noise, observe, prior, map, variance).
        origin: (3,) float64 world position of the local grid's origin, metres: voxel ``ijk``
            is at world ``origin + (ijk + 0.5) * voxel_size`` (zeros: the grid is the world's).
    """

    band: Band
    voxel_size: float
    mean: np.ndarray
    var: np.ndarray
    cov: np.ndarray | None = None
    observation: ObservationConfig | None = None
    trunc_m: float = 0.0
    bootstrap_trunc_m: float = 0.0
    sigma_extra_m: float = 0.0
    sigma_corr_m: float = 0.0
    solver: dict = field(default_factory=dict)
    variance: dict = field(default_factory=dict)
    observations: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _sdf_field: object = field(default=None, init=False, repr=False)  # built by query()

    ijk = property(lambda self: self.band.ijk, doc="(N, 3) int32 band voxel indices (local "
                   "grid), sorted.")
    tsdf = property(lambda self: self.band.tsdf, doc="(N,) float32 bootstrap TSDF, metres.")
    weight = property(lambda self: self.band.weight, doc="(N,) float32 bootstrap weight.")

    @property
    def sigma(self) -> np.ndarray:
        """(N,) float32 posterior standard deviation, metres."""
        return np.sqrt(np.maximum(self.var, 0)).astype(np.float32)

    def band_arrays(self) -> dict:
        """The arrays of ``band.npz``: the DESIGN.md section 4 contract (``ijk, voxel_size,
        mean, var, tsdf, weight``), ``cov`` ((N, 3) float32 m^2, see the class docstring; left
        out when None), the observation model (``observation``: its settings as a JSON
        string, ``trunc_m``, ``bootstrap_trunc_m``, ``sigma_extra_m``, ``sigma_corr_m``; float64,
        metres) and ``origin`` ((3,) float64 metres, always written)."""
        arrays = {"ijk": self.ijk, "voxel_size": np.float32(self.voxel_size), "mean": self.mean,
                  "var": self.var, "tsdf": self.tsdf, "weight": self.weight,
                  ORIGIN_ARRAY: np.asarray(self.origin, np.float64)}
        if self.cov is not None:
            arrays["cov"] = self.cov
        if self.observation is not None:
            arrays.update(observation=np.array(json.dumps(asdict(self.observation))),
                          trunc_m=np.float64(self.trunc_m),
                          bootstrap_trunc_m=np.float64(self.bootstrap_trunc_m),
                          sigma_extra_m=np.float64(self.sigma_extra_m),
                          sigma_corr_m=np.float64(self.sigma_corr_m))
        return arrays

    @classmethod
    def load(cls, path) -> "Posterior":
        """The posterior saved as ``band.npz`` by a run (``mean`` and ``var`` must be there:
        a ``run.stages = "tsdf_only"`` run has no posterior). A band.npz of an older version
        without ``cov`` loads with ``cov = None``: :meth:`extract_mesh` then gives every vertex
        the interpolated marginal bound as ``sigma`` (above the std of the SDF: by 27-35 %
        median on the spheres of tools/vertex_sigma_accuracy.py).
        Raises DataError naming the file (:func:`read_band` says what it checks)."""
        from .checks import check_finite
        from .running.folder import reading

        with reading(Path(path).parent):  # not while a run commits
            data = read_band(path)
        missing = [k for k in BAND_ARRAYS if k not in data]
        if missing:
            hint = " (a run.stages = 'tsdf_only' run has no posterior)" if "mean" in missing else ""
            raise DataError(f"{path}: missing arrays {', '.join(missing)}{hint}")
        origin = np.asarray(data.get(ORIGIN_ARRAY, np.zeros(3)), np.float64)
        model = {}
        if all(k in data for k in MODEL_ARRAYS if k != "sigma_corr_m"):
            try:
                obs = ObservationConfig(**json.loads(str(data["observation"])))
                check_finite("observation", obs)
                obs.check()
            except (ValueError, TypeError) as e:  # also ConfigError, a ValueError
                raise DataError(f"{path}: the array 'observation' is not this version's "
                                f"observation settings ({e})") from None
            model = {"observation": obs, "trunc_m": float(data["trunc_m"]),
                     "bootstrap_trunc_m": float(data["bootstrap_trunc_m"]),
                     "sigma_extra_m": float(data["sigma_extra_m"]),
                     "sigma_corr_m": float(data["sigma_corr_m"]) if "sigma_corr_m" in data
                     else 0.0}
        band = Band.from_voxels(data["ijk"], data["tsdf"], data["weight"])
        return cls(band=band, voxel_size=float(data["voxel_size"]),
                   mean=data["mean"].astype(np.float32), var=data["var"].astype(np.float32),
                   cov=data["cov"].astype(np.float32) if "cov" in data else None, **model,
                   origin=origin)

    def save(self, out_dir) -> Path:
        """Write ``mesh.ply`` (:meth:`extract_mesh`, vertex ``sigma sigma_pos``) and ``band.npz``
        (:meth:`band_arrays`) into ``out_dir`` (DESIGN.md section 4), atomically; return the
        folder. :meth:`load` reads the band back."""
        from .io import ensure_out_dir
        from .running.folder import staged

        out = ensure_out_dir(out_dir)
        with staged(out) as staging:  # both files replaced together, one writer at a time
            self._write(staging)
        return out

    def _write(self, folder: Path) -> None:
        """``mesh.ply`` and ``band.npz`` into ``folder``."""
        from .io import write_mesh_ply, write_npz

        mesh = self.extract_mesh(local=True)
        write_mesh_ply(folder / "mesh.ply", mesh.vertices, mesh.faces,
                       vertex_attrs=mesh_attrs(mesh), origin=self.origin)
        write_npz(folder / "band.npz", **self.band_arrays())

    def extract_mesh(self, *, local: bool = False) -> trimesh.Trimesh:
        """Step 7: marching cubes at ``mean = 0`` over cells whose 8 corners are band voxels
        observed by the bootstrap (weight > 0), with vertex attributes (:data:`VERTEX_ATTRS`).
        Vertices in world coordinates (float64 ``origin + vertex``), or with ``local`` in the
        local grid's frame (the float32 marching-cubes vertices, what the viewer and the
        kernels take).

        ``sigma`` (metres): the posterior std of the SDF interpolated at the vertex,
        ``sqrt(a_v^T Q^-1 a_v)`` (DESIGN.md 3.7). A vertex lies on the grid edge between
        voxels i and i + e (:class:`~bftaichi.stages.surface.VertexEdges`), so this needs
        ``var`` at both and ``cov`` between them (:func:`~bftaichi.stages.surface.
        vertex_variance`). Where that is not at hand (``cov`` None: a band.npz of an older
        version; Lewiner's cell-centre vertices; an edge end outside the band) it falls back to
        the trilinear interpolation of ``var``, an upper bound (it ignores the correlation of
        the two voxels: 27-35 % above, median, on the spheres of
        tools/vertex_sigma_accuracy.py).

        ``sigma_pos`` (metres): the std of the surface position along the normal,
        ``sigma / |grad mean|``, the gradient that of the trilinear interpolant of ``mean`` in
        the vertex's cell (:func:`~bftaichi.stages.surface.sample_gradient`), floored at
        :data:`MIN_GRADIENT` (taken as 1, an SDF's slope, where a cell corner is missing).

        Why observed corners only: in the one-voxel dilation around the band, nothing but the
        prior sets the mean, and the membrane prior flattens it toward the anchors and 0, which
        makes zero crossings where no surface was seen (measured on the default scene: 12 % of
        vertices more than 1 cm from the truth, 92 % of those in cells with an unobserved
        corner)."""
        from .stages.surface import extract_mesh, sample_field, sample_gradient, vertex_variance

        vertices, faces, edges = extract_mesh(self.ijk, self.mean, self.weight > 0,
                                              self.voxel_size, return_edges=True)
        mesh = trimesh.Trimesh(vertices if local else points_in_world(vertices, self.origin),
                               faces, process=False)
        sigma = sigma_pos = np.zeros(0, np.float32)
        if len(vertices):
            everywhere = np.ones(len(self.ijk), bool)
            var = np.full(len(vertices), np.nan)
            if self.cov is not None:
                var = vertex_variance(self.ijk, self.var, self.cov, edges)
            bound = ~np.isfinite(var)
            var[bound] = sample_field(self.ijk, self.var, everywhere, self.voxel_size,
                                      vertices[bound])
            sigma = np.sqrt(np.maximum(np.nan_to_num(var), 0))
            grad = np.linalg.norm(sample_gradient(self.ijk, self.mean, everywhere,
                                                  self.voxel_size, vertices), axis=1)
            grad = np.maximum(np.nan_to_num(grad, nan=1.0), MIN_GRADIENT)
            sigma, sigma_pos = sigma.astype(np.float32), (sigma / grad).astype(np.float32)
        mesh.vertex_attributes["sigma"] = sigma
        mesh.vertex_attributes["sigma_pos"] = sigma_pos
        return mesh

    def query(self, points_W) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The posterior at arbitrary points, from numpy: ``(sdf, grad, sigma, observed)``.

        Args:
            points_W: (M, 3) or (3,) world points, metres (the frame of the input poses).
        Returns:
            ``sdf`` (M,) float32 trilinear posterior mean, metres, positive in free space;
            ``grad`` (M, 3) float32 unit normal (the normalised analytic gradient of that
            trilinear mean, world frame); ``sigma`` (M,) float32 posterior std of the SDF,
            ``sqrt(trilinear var)``, metres; ``observed`` (M,) bool, True where all 8 corners
            of the point's cell are band voxels the bootstrap observed. Where ``observed`` is
            False, ``sdf`` and ``sigma`` are NaN and ``grad`` is 0.

        The values are those of :class:`kernels.SDFField`'s accessors (the same ``@ti.func``,
        run by one kernel over the points), so a Taichi program and a numpy caller read the
        same numbers. Initialises Taichi on the CPU if nothing has."""
        pts = np.asarray(points_W, dtype=np.float64)
        if pts.ndim == 1 and pts.shape == (3,):
            pts = pts[None]
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"query: points_W must have shape (M, 3), got {pts.shape}")
        from kernels.embed import query_points

        local = np.ascontiguousarray(pts - self.origin)  # NaN rows stay unobserved
        m = len(local)
        sdf, sigma = np.empty(m, np.float32), np.empty(m, np.float32)
        grad, observed = np.zeros((m, 3), np.float32), np.zeros(m, np.uint8)
        if m and len(self.ijk):
            query_points(self._field(), local, sdf, grad, sigma, observed)
        seen = observed.astype(bool)
        sdf[~seen] = np.nan
        sigma[~seen] = np.nan
        grad[~seen] = 0.0
        return sdf, grad, sigma, seen

    def to_dense(self, bounds_min, bounds_max) -> dict:
        """The voxels of a world box as dense arrays, NaN where the bootstrap did not observe.

        Args:
            bounds_min, bounds_max: (3,) world corners of the box, metres.
        Returns:
            a dict: ``sdf`` and ``sigma`` (X, Y, Z) float32 arrays, metres (the posterior mean
            and std of every voxel whose centre lies in the box; NaN where the voxel is not a
            band voxel with ``weight > 0``); ``origin_W`` (3,) float64 the world centre of
            voxel ``[0, 0, 0]``; ``voxel_size`` metres. Voxel ``[a, b, c]`` is centred at
            ``origin_W + (a, b, c) * voxel_size``. Values at voxel centres are the band's own
            (no interpolation); :meth:`query` interpolates between them."""
        lo, hi = (np.asarray(b, np.float64) for b in (bounds_min, bounds_max))
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all()
                                                         and np.isfinite(hi).all()):
            raise ValueError("to_dense: bounds_min and bounds_max must be finite 3-vectors")
        if (hi < lo).any():
            raise ValueError(f"to_dense: bounds_max {hi} is below bounds_min {lo}")
        vs = self.voxel_size
        i0 = np.ceil((lo - self.origin) / vs - 0.5).astype(np.int64)  # first centre >= lo
        i1 = np.floor((hi - self.origin) / vs - 0.5).astype(np.int64)  # last centre <= hi
        shape = np.maximum(i1 - i0 + 1, 0)
        if np.prod(shape, dtype=np.float64) * 8 > 8 << 30:
            raise ValueError(f"to_dense: the box holds {shape.tolist()} voxels, more than 8 GiB "
                             "of output: ask for a smaller box")
        sdf = np.full(tuple(shape), np.nan, np.float32)
        sigma = np.full(tuple(shape), np.nan, np.float32)
        rel = self.ijk.astype(np.int64) - i0
        inside = ((rel >= 0) & (rel < shape)).all(axis=1) & (self.weight > 0)
        at = tuple(rel[inside].T)
        sdf[at] = self.mean[inside]
        sigma[at] = np.sqrt(np.maximum(self.var[inside], 0))
        return {"sdf": sdf, "sigma": sigma, "origin_W": self.origin + (i0 + 0.5) * vs,
                "voxel_size": vs}

    def _field(self):
        """The :class:`kernels.SDFField` of this posterior (built once, local frame)."""
        if self._sdf_field is None:
            from kernels.embed import SDFField

            from . import backend
            if not backend.is_initialized():
                backend.init()
            self._sdf_field = SDFField.from_posterior(self)
        return self._sdf_field

    def warm_start(self, ijk: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """``x0`` with the voxels of ``ijk`` that this posterior also holds set to its mean
        (a PCG start when frames are added)."""
        return warm_start(self.ijk, self.mean, ijk, x0)


def warm_start(prev_ijk: np.ndarray, prev_mean: np.ndarray, ijk: np.ndarray,
               x0: np.ndarray) -> np.ndarray:
    """``x0`` with the voxels of ``ijk`` that ``prev_ijk`` (a band's voxels in its order, or a
    subset of them; not empty) holds set to ``prev_mean``."""
    from kernels.layout import block_key_np

    k_prev = block_key_np(np.asarray(prev_ijk, np.int64))  # one int64 per voxel, ascending
    k_new = block_key_np(np.asarray(ijk, np.int64))
    pos = np.clip(np.searchsorted(k_prev, k_new), 0, len(k_prev) - 1)
    same = k_prev[pos] == k_new
    out = np.array(x0, np.float32, copy=True)
    out[same] = prev_mean[pos[same]]
    return out
