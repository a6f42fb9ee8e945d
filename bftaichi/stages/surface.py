"""Marching cubes over a sparse set of voxels, and trilinear sampling of per-voxel fields.

Voxel ``ijk`` (integer index) has its centre at ``(ijk + 0.5) * voxel_size`` (world metres,
DESIGN.md section 2). A marching-cubes *cell* is the cube whose 8 corners are the voxel centres
``ijk + {0,1}^3``; it is named by its lowest corner. A cell is meshed only if all 8 corner voxels
are observed, so the edge of the observed region (the band edge of DESIGN.md section 3.7) makes no
false surface.

The sparse voxels are scattered into dense chunks of at most ``chunk_cells^3`` cells over the
bounding box of the observed voxels (chunks that hold no voxel are never built). Neighbouring chunks
share one layer of voxels, so every cell belongs to exactly one chunk. scikit-image's Lewiner
marching cubes meshes each chunk; its vertices are then identified with the grid edge they lie on
and re-placed from the global voxel values in float64, so a vertex on a chunk seam gets the same key
and the same position from both chunks and is merged (a closed surface stays watertight).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kernels.layout import column_max, column_min

from ..checks import check_range
from ..errors import BftaichiError

__all__ = ["MeshConfig", "VertexEdges", "extract_mesh", "sample_field", "sample_gradient",
           "vertex_variance"]


@dataclass
class MeshConfig:
    """``[mesh]``: marching cubes over the TSDF."""

    min_weight: float = 1.0
    """A cell produces triangles only if all 8 corner voxels have weight >= this. 1 = seen at least
    once; raise it (Open3D uses 3, "seen from 3 viewpoints") to drop surfaces seen by few frames."""

    def check(self) -> None:
        check_range("mesh.min_weight", self.min_weight, 0.0, lo_open=True)


#: Default chunk edge in cells: a 129^3 float32 chunk is 8.6 MB, small enough for any machine
#: and large enough that the per-chunk overhead of skimage stays negligible.
DEFAULT_CHUNK_CELLS = 128
#: Largest allowed chunk edge: skimage returns chunk-local float32 vertex coordinates, whose
#: rounding error (half an ulp, 1.5e-5 voxel at 256) must stay far below _IDENT_TOL.
MAX_CHUNK_CELLS = 256
#: A chunk-local vertex coordinate within this distance (voxels) of an integer lies on that grid
#: plane. Far above the float32 error of skimage's output, far below any real edge fraction.
_IDENT_TOL = 1e-4
#: An edge crossing closer than this fraction of the edge to a corner is snapped onto that corner.
#: Must exceed _IDENT_TOL so that a chunk that sees the vertex on the corner and a chunk that sees
#: it on the edge reach the same key; moves a vertex by at most 1e-3 voxel.
_SNAP_T = 1e-3
#: skimage's regulariser of the edge interpolation weights 1 / (eps + |f - level|).
_EPS = float(np.spacing(1.0))
#: A corner whose trilinear weight is below this may be unobserved in sample_field (see there).
_WEIGHT_TOL = 1e-3
#: Largest index span per axis: keys are linearised into int64.
_MAX_SPAN = 1 << 19

_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


# --------------------------------------------------------------------------------------------
# input validation
# --------------------------------------------------------------------------------------------

def _check_voxels(ijk, values, observed, voxel_size, channels: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Validate the sparse voxel arrays; return (ijk int64 (N,3), values float64 (N,), or
    (N, C) with ``channels``, observed bool (N,), voxel_size), rows sorted by ijk. Raises
    BftaichiError naming the argument."""
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise BftaichiError(f"ijk must have shape (N, 3), got {ijk.shape}")
    if ijk.size and not np.issubdtype(ijk.dtype, np.integer):
        raise BftaichiError(f"ijk must be an integer array (voxel indices), got dtype {ijk.dtype}")
    n = ijk.shape[0]
    values = np.asarray(values)
    if not (values.shape == (n,) or channels and values.ndim == 2 and values.shape[0] == n
            and values.shape[1] >= 1):
        want = f"({n},) or ({n}, C)" if channels else f"({n},)"
        raise BftaichiError(f"values must have shape {want} to match ijk, got {values.shape}")
    if n and not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
        raise BftaichiError(f"values must be a float array, got dtype {values.dtype}")
    observed = np.asarray(observed)
    if observed.shape != (n,):
        raise BftaichiError(f"observed must have shape ({n},) to match ijk, got {observed.shape}")
    if n and observed.dtype != np.bool_:
        raise BftaichiError(f"observed must be a bool array, got dtype {observed.dtype}")
    try:
        voxel_size = float(voxel_size)
    except (TypeError, ValueError):
        raise BftaichiError(f"voxel_size must be a number (metres), got {voxel_size!r}") from None
    if not np.isfinite(voxel_size) or voxel_size <= 0:
        raise BftaichiError(f"voxel_size must be a positive finite number (metres), got {voxel_size}")

    ijk = ijk.astype(np.int64, copy=False)
    values = values.astype(np.float64, copy=False)
    observed = observed.astype(bool, copy=False)
    if n == 0:
        return ijk.reshape(0, 3), values, observed, voxel_size
    if not np.all(np.isfinite(values[observed])):
        finite = np.isfinite(values) if values.ndim == 1 else np.isfinite(values).all(axis=1)
        bad = np.flatnonzero(observed & ~finite)[0]
        raise BftaichiError(f"values must be finite where observed; row {bad} "
                            f"(ijk {ijk[bad].tolist()}) is {values[bad]}")
    lo = column_min(ijk)
    span = column_max(ijk) - lo + 1
    if np.any(span > _MAX_SPAN):
        raise BftaichiError(f"ijk spans {span.tolist()} voxels; at most {_MAX_SPAN} per axis "
                            "are supported")
    key = _linear_key(ijk, lo, span)
    if np.all(key[1:] > key[:-1]):  # sorted and unique already (a band is): no copies
        return ijk, values, observed, voxel_size
    order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    ijk, values, observed = ijk[order], values[order], observed[order]
    dup = np.all(ijk[1:] == ijk[:-1], axis=1)
    if np.any(dup):
        first = np.flatnonzero(dup)[0]
        raise BftaichiError(f"ijk holds voxel {ijk[first].tolist()} more than once")
    return ijk, values, observed, voxel_size


def _linear_key(idx: np.ndarray, lo: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """Row-major linear index of integer points ``idx`` (..., 3) inside the box ``[lo, lo+dims)``."""
    rel = idx - lo
    return (rel[..., 0] * dims[1] + rel[..., 1]) * dims[2] + rel[..., 2]


# --------------------------------------------------------------------------------------------
# marching cubes
# --------------------------------------------------------------------------------------------

def extract_mesh(ijk: np.ndarray, values: np.ndarray, observed: np.ndarray, voxel_size: float,
                 level: float = 0.0, *, chunk_cells: int = DEFAULT_CHUNK_CELLS,
                 return_edges: bool = False) -> tuple:
    """Iso-surface ``values == level`` of a sparse voxel field, by marching cubes.

    Args:
        ijk: (N, 3) integer voxel indices (int32 in bftaichi); each voxel at most once. Row order
            does not matter: rows are sorted by ijk first, so the output is deterministic.
        values: (N,) float signed distance in metres (or any field), positive in front of the
            surface (free space), negative behind it. Must be finite where ``observed``.
        observed: (N,) bool. A cell yields triangles only if all 8 corner voxels are present and
            observed.
        voxel_size: voxel edge in metres.
        level: iso-value (same unit as ``values``).
        chunk_cells: cells per chunk edge (1..256). Memory per chunk is about
            ``20 * (chunk_cells + 1)^3`` bytes (43 MB at the default 128).
        return_edges: also return each vertex's grid feature (:class:`VertexEdges`): the
            identification the seam merge uses, for callers that need a vertex's trilinear
            weights (step 7's vertex sigma).

    Returns:
        vertices (V, 3) float32 world metres, faces (F, 3) int32. Faces are wound so that their
        right-hand normals point toward increasing ``values`` (out of the object, into free
        space). Vertices on the seam of two chunks are merged, crossings within 1e-3 of an edge
        from a voxel centre are snapped onto it, degenerate faces are dropped, and every
        returned vertex is used by a face.
        Empty arrays of shape (0, 3) when there is no observed crossing of ``level``.
        With ``return_edges``, a third value, the :class:`VertexEdges` of the vertices.

    Raises:
        BftaichiError (a ValueError) naming the bad argument.
    """
    from skimage.measure import marching_cubes

    ijk, values, observed, voxel_size = _check_voxels(ijk, values, observed, voxel_size)
    try:
        level = float(level)
    except (TypeError, ValueError):
        raise BftaichiError(f"level must be a number, got {level!r}") from None
    if not np.isfinite(level):
        raise BftaichiError(f"level must be finite, got {level}")
    if isinstance(chunk_cells, bool) or not isinstance(chunk_cells, (int, np.integer)) \
            or not 1 <= chunk_cells <= MAX_CHUNK_CELLS:
        raise BftaichiError(f"chunk_cells must be an integer in [1, {MAX_CHUNK_CELLS}], "
                            f"got {chunk_cells!r}")
    chunk_cells = int(chunk_cells)

    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    if return_edges:
        empty += (VertexEdges.empty(),)
    ijk, values = ijk[observed], values[observed]
    if len(ijk) == 0:
        return empty
    lo = column_min(ijk)
    rel = ijk - lo                        # voxel_idx relative to the bounding box, >= 0
    n_cells = column_max(rel)             # cells per axis in the bounding box
    if np.any(n_cells < 1):
        return empty
    # Vertex keys live on the voxel grid of the box, plus one margin layer.
    key_dims = n_cells + 2
    grid_keys_end = int(np.prod(key_dims)) * 4    # < 2^60 since each span <= _MAX_SPAN

    # --- assign voxels to chunks. Chunk q covers cells [q*C, (q+1)*C) and so voxels
    # [q*C, (q+1)*C] per axis: a voxel on a chunk boundary also belongs to the previous chunk.
    c = chunk_cells
    q = rel // c
    boundary = (rel % c == 0) & (rel > 0)
    n_chunks = (n_cells + c - 1) // c     # chunks per axis that hold cells
    rows, chunk_idx = [], []
    bits = boundary @ np.array([4, 2, 1])  # which axes a voxel sits on a chunk boundary of
    for shift in _CORNERS:                # 8 combinations of "also in the previous chunk" per axis
        need = int(shift @ np.array([4, 2, 1]))
        if need == 0:                     # every voxel, in its own chunk
            keep = np.all(q < n_chunks, axis=1)   # the last voxel layer may open an empty chunk
            rows.append(np.flatnonzero(keep))
            chunk_idx.append(q[keep])
            continue
        sel = (bits & need) == need       # on a boundary along every axis the shift moves
        qs = q[sel] - shift
        keep = np.all(qs < n_chunks, axis=1)
        rows.append(np.flatnonzero(sel)[keep])
        chunk_idx.append(qs[keep])
    rows = np.concatenate(rows)
    chunk_idx = np.concatenate(chunk_idx)
    chunk_key = (chunk_idx[:, 0] * n_chunks[1] + chunk_idx[:, 1]) * n_chunks[2] + chunk_idx[:, 2]
    # a stable sort's order depends only on the keys' order: through 16 bits where they fit,
    # numpy sorts them by radix
    narrow = chunk_key.astype(np.int16) if int(np.prod(n_chunks)) <= 1 << 15 else chunk_key
    order = np.argsort(narrow, kind="stable")
    rows, chunk_idx, chunk_key = rows[order], chunk_idx[order], chunk_key[order]
    starts = np.flatnonzero(np.r_[True, chunk_key[1:] != chunk_key[:-1]])
    ends = np.r_[starts[1:], len(chunk_key)]

    level32 = np.float32(level)
    key_parts, pos_parts, face_parts = [], [], []
    n_vertices = 0
    n_centre = 0
    for s, e in zip(starts, ends):
        origin = chunk_idx[s] * c                         # chunk's first voxel, box-relative
        shape = np.minimum(c, n_cells - origin) + 1       # voxels per axis in this chunk
        local = rel[rows[s:e]] - origin
        vol = np.full(shape, level, dtype=np.float32)
        obs = np.zeros(shape, dtype=bool)
        vol[local[:, 0], local[:, 1], local[:, 2]] = values[rows[s:e]]
        obs[local[:, 0], local[:, 1], local[:, 2]] = True

        # A cell (named by its lowest corner) is meshed if its 8 corners are observed and the
        # level crosses it (skimage's corner test is `value - level > 0`).
        # in float64, as skimage compares; the same in float32 when level is a float32 value
        above = vol > level32 if level32 == level else vol.astype(np.float64) > level
        all_obs = _cell_reduce(obs, np.logical_and)
        any_above = _cell_reduce(above, np.logical_or)
        all_above = _cell_reduce(above, np.logical_and)
        active = all_obs & any_above & ~all_above
        if not active.any():
            continue
        # skimage (0.19-0.26, _marching_cubes_lewiner_cy.pyx) visits the cell with lowest corner
        # (x, y, z) only if mask[x+1, y+1, z+1]: the mask is read at the cell's highest corner.
        # tests/test_meshing.py checks that an unobserved corner removes every cell touching it.
        mask = np.zeros(shape, dtype=bool)
        mask[1:, 1:, 1:] = active
        # 'descent' gives faces whose right-hand normals point toward larger values (checked on a
        # sphere SDF in tests/test_meshing.py).
        verts, faces, _, _ = marching_cubes(vol, level, gradient_direction="descent",
                                            allow_degenerate=True, mask=mask)

        keys, pos, is_centre = _vertex_keys(verts.astype(np.float64), vol, level, origin, key_dims)
        # Lewiner's cell-centre vertices are never shared: give each its own key past the grid.
        keys[is_centre] = grid_keys_end + n_centre + np.arange(int(is_centre.sum()))
        n_centre += int(is_centre.sum())
        key_parts.append(keys)
        pos_parts.append(pos)
        face_parts.append(faces.astype(np.int64) + n_vertices)
        n_vertices += len(verts)

    if not face_parts:
        return empty
    keys = np.concatenate(key_parts)
    pos = np.concatenate(pos_parts)
    faces = np.concatenate(face_parts)

    # Merge vertices with equal keys (chunk seams, snapped corners); positions of equal keys are
    # equal by construction. np.unique sorts the keys, so the vertex order is deterministic.
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    pos = pos[first]
    degenerate = ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
                  | (faces[:, 0] == faces[:, 2]))
    faces = faces[~degenerate]
    if len(faces) == 0:
        return empty
    referenced = np.zeros(len(pos), bool)  # the vertices faces use, renumbered in order
    referenced[faces] = True
    used = np.flatnonzero(referenced)
    faces = (np.cumsum(referenced) - 1)[faces]
    vertices = (pos[used] + lo + 0.5) * voxel_size
    out = vertices.astype(np.float32), faces.astype(np.int32)
    if return_edges:
        out += (VertexEdges.from_keys(keys[first][used], pos[used], lo, key_dims, grid_keys_end),)
    return out


def _cell_reduce(a: np.ndarray, op) -> np.ndarray:
    """``op`` (logical and / or) of the 8 corners of every cell of the voxel array ``a``: (X-1,
    Y-1, Z-1), cell (x, y, z) over voxels x..x+1, y..y+1, z..z+1, one axis at a time."""
    a = op(a[:-1], a[1:])
    a = op(a[:, :-1], a[:, 1:])
    return op(a[:, :, :-1], a[:, :, 1:])


@dataclass
class VertexEdges:
    """The grid feature each marching-cubes vertex lies on (:func:`extract_mesh`,
    ``return_edges=True``), from the keys that merge vertices across chunk seams.

    Attributes:
        ijk: (V, 3) int64 voxel at the feature's lower end: the edge's first voxel, or the voxel
            a vertex was snapped onto (undefined, 0, for cell-centre vertices).
        axis: (V,) int8: 0, 1, 2 for a vertex on the edge from ``ijk`` to ``ijk + e_axis``;
            3 for a vertex on the voxel centre ``ijk`` (snapped, weight 1); -1 for Lewiner's
            cell-centre vertices of ambiguous cases (weights over the whole cell).
        t: (V,) float64 fraction along the edge from ``ijk`` (0 unless ``axis`` is 0..2): the
            vertex's trilinear weights are ``1 - t`` on ``ijk`` and ``t`` on ``ijk + e_axis``.
    """

    ijk: np.ndarray
    axis: np.ndarray
    t: np.ndarray

    @classmethod
    def empty(cls) -> "VertexEdges":
        return cls(np.zeros((0, 3), np.int64), np.zeros(0, np.int8), np.zeros(0))

    @classmethod
    def from_keys(cls, keys, pos, lo, key_dims, grid_keys_end) -> "VertexEdges":
        """Decode :func:`_vertex_keys`' keys (``4 * point_key + axis``; centre vertices at
        ``grid_keys_end`` and above) and box-relative positions ``pos`` (V, 3)."""
        centre = keys >= grid_keys_end
        point = np.where(centre, 0, keys // 4)
        axis = np.where(centre, -1, keys % 4).astype(np.int8)
        rel = np.stack(np.unravel_index(point, tuple(key_dims)), axis=1) - 1  # key origin -1
        t = np.zeros(len(keys))
        on_edge = np.flatnonzero(axis < 3)
        on_edge = on_edge[axis[on_edge] >= 0]
        t[on_edge] = pos[on_edge, axis[on_edge]] - rel[on_edge, axis[on_edge]]
        ijk = np.where(centre[:, None], 0, rel + lo)
        return cls(ijk.astype(np.int64), axis, t)


def _vertex_keys(verts: np.ndarray, vol: np.ndarray, level: float, origin: np.ndarray,
                 key_dims: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Identify skimage's chunk-local vertices with grid features and re-place them.

    Each marching-cubes vertex lies on a grid point, on a grid edge (one fractional coordinate) or,
    for Lewiner's ambiguous cases, inside a cell (two or more fractional coordinates).

    Returns:
        keys (V,) int64: ``4 * point_key + axis`` for a crossing of the edge from that grid point
            along ``axis``, ``4 * point_key + 3`` for a grid point; undefined for centre vertices.
        pos (V, 3) float64: box-relative grid coordinates (voxels). Edge crossings are
            recomputed in float64 from the two end values with skimage's own interpolation
            ``t = (eps + |f0|) / (2 eps + |f0| + |f1|)`` (f = value - level), so every chunk
            that sees an edge places its vertex identically.
        is_centre (V,) bool.
    """
    r = np.round(verts)
    frac = np.abs(verts - r) >= _IDENT_TOL
    n_frac = frac.sum(axis=1)
    is_centre = n_frac >= 2
    is_edge = n_frac == 1

    point = r.astype(np.int64)            # chunk-local grid point for point vertices
    keys = np.zeros(len(verts), dtype=np.int64)
    pos = verts + origin                  # centre vertices keep skimage's position

    axis = np.argmax(frac, axis=1)
    ev = np.flatnonzero(is_edge)
    ax = axis[ev]
    p0 = point[ev].copy()
    p0[np.arange(len(ev)), ax] = np.floor(verts[ev, ax]).astype(np.int64)
    p1 = p0.copy()
    p1[np.arange(len(ev)), ax] += 1
    f0 = np.abs(vol[p0[:, 0], p0[:, 1], p0[:, 2]].astype(np.float64) - level)
    f1 = np.abs(vol[p1[:, 0], p1[:, 1], p1[:, 2]].astype(np.float64) - level)
    t = (_EPS + f0) / (2.0 * _EPS + f0 + f1)
    snap0 = t < _SNAP_T
    snap1 = t > 1.0 - _SNAP_T
    on_edge = ~(snap0 | snap1)
    # snapped crossings become grid points
    point[ev[snap0]] = p0[snap0]
    point[ev[snap1]] = p1[snap1]
    is_point = ~is_centre
    is_point[ev[on_edge]] = False

    pts = point[is_point] + origin
    keys[is_point] = _linear_key(pts, -1, key_dims) * 4 + 3
    pos[is_point] = pts
    ee = ev[on_edge]
    e0 = p0[on_edge] + origin
    keys[ee] = _linear_key(e0, -1, key_dims) * 4 + ax[on_edge]
    epos = e0.astype(np.float64)
    epos[np.arange(len(ee)), ax[on_edge]] += t[on_edge]
    pos[ee] = epos
    return keys, pos, is_centre


# --------------------------------------------------------------------------------------------
# trilinear sampling
# --------------------------------------------------------------------------------------------

def sample_field(ijk: np.ndarray, values: np.ndarray, observed: np.ndarray, voxel_size: float,
                 points: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a per-voxel field at world points.

    The field is known at voxel centres ``(ijk + 0.5) * voxel_size``; a point is interpolated from
    the 8 voxels of the cell that contains it. Corners whose trilinear weight is below 1e-3 may be
    missing or unobserved (they are dropped and the remaining weights renormalised, changing the
    result by at most 0.1 % of the local value range): this keeps mesh vertices that lie on the
    outer face of an observed cell (float32 round-off included) from turning NaN.

    Args:
        ijk, values, observed: the sparse field, as for :func:`extract_mesh` (values may be any
            per-voxel float, e.g. the posterior std; must be finite where observed). ``values``
            may also be (N, C), several fields over the same voxels (colour channels): the
            cells are looked up once, and each column comes out as it would alone.
        voxel_size: voxel edge in metres.
        points: (P, 3) float world metres, finite.

    Returns:
        (P,) float32 interpolated values, or (P, C) for (N, C) values; NaN where a
        contributing voxel is absent or unobserved.
    """
    corners = _cell_corners(ijk, values, observed, voxel_size, points, channels=True)
    shape = (len(np.asarray(points)),) + np.shape(values)[1:]
    out = np.full(shape, np.nan, dtype=np.float32)
    if corners is None:
        return out
    f, found, gather = corners
    w = np.prod(np.where(_CORNERS[None, :, :] == 1, f[:, None, :], 1.0 - f[:, None, :]), axis=2)
    needed = w >= _WEIGHT_TOL
    ok = np.all(found | ~needed, axis=1)
    wf = np.where(found, w, 0.0)
    wsum = np.sum(wf, axis=1)
    ok &= wsum > 0
    columns = out if out.ndim == 2 else out[:, None]  # a view: (P, 1) of (P,) values
    for c in range(columns.shape[1]):  # each column as on its own
        vsum = np.sum(wf * gather(c), axis=1)
        columns[ok, c] = (vsum[ok] / wsum[ok]).astype(np.float32)
    return out


def sample_gradient(ijk: np.ndarray, values: np.ndarray, observed: np.ndarray,
                    voxel_size: float, points: np.ndarray) -> np.ndarray:
    """(P, 3) float64 gradient of the trilinear interpolant of a per-voxel field at world
    points, in value units per metre (dimensionless for an SDF in metres), from the 8 voxels of
    the cell that contains each point (arguments as :func:`sample_field`). NaN rows where one
    of the 8 is absent or unobserved. On a cell face the interpolant's normal derivative jumps;
    this is the one-sided derivative of the cell ``floor`` picks."""
    corners = _cell_corners(ijk, values, observed, voxel_size, points)
    out = np.full((len(points), 3), np.nan)
    if corners is None:
        return out
    f, found, gather = corners
    vals = gather(0)
    ok = found.all(axis=1)
    lin = np.where(_CORNERS[None, :, :] == 1, f[:, None, :], 1.0 - f[:, None, :])  # (P, 8, 3)
    slope = np.where(_CORNERS == 1, 1.0, -1.0)                                     # (8, 3)
    for a in range(3):  # d/dx_a of prod_b lin_b: replace factor a by its derivative
        dw = slope[None, :, a] * np.prod(np.delete(lin, a, axis=2), axis=2)       # (P, 8)
        out[ok, a] = np.sum(dw * vals, axis=1)[ok] / voxel_size
    return out


def _cell_corners(ijk, values, observed, voxel_size, points, channels: bool = False):
    """The cell of each point and its 8 corner voxels: ``(f, found, gather)`` with f (P, 3)
    the point's fractional position in its cell (voxels, [0, 1)), found (P, 8) bool (corner
    present and observed; order :data:`_CORNERS`) and ``gather(c)`` the corners' values (P, 8)
    float64 (0 where not found) of column ``c`` of (N, C) ``values`` (``channels``), or of
    (N,) ``values``; None when there are no points or no observed voxel. Validates the
    arguments."""
    ijk, values, observed, voxel_size = _check_voxels(ijk, values, observed, voxel_size,
                                                      channels)
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise BftaichiError(f"points must have shape (P, 3), got {points.shape}")
    if points.size and not (np.issubdtype(points.dtype, np.floating)
                            or np.issubdtype(points.dtype, np.integer)):
        raise BftaichiError(f"points must be a float array (metres), got dtype {points.dtype}")
    points = points.astype(np.float64, copy=False)
    if not np.all(np.isfinite(points)):
        raise BftaichiError("points must be finite (world metres)")
    if len(points) == 0 or not observed.any():
        return None
    ijk, values = ijk[observed], values[observed]

    g = points / voxel_size - 0.5         # continuous voxel_idx
    base = np.floor(g).astype(np.int64)
    f = g - base                          # (P, 3) in [0, 1)
    corners = base[:, None, :] + _CORNERS[None, :, :]                   # (P, 8, 3)

    lo = column_min(ijk)
    dims = column_max(ijk) - lo + 1
    keys = _linear_key(ijk, lo, dims)     # sorted ascending, since ijk is sorted
    # (P, 8): every coordinate in [lo, lo + dims), one axis at a time (numpy reduces a last
    # axis of length 3 slowly)
    inside = np.ones(corners.shape[:2], bool)
    for a in range(3):
        inside &= (corners[..., a] >= lo[a]) & (corners[..., a] < lo[a] + dims[a])
    ck = np.where(inside, _linear_key(np.where(inside[..., None], corners, lo), lo, dims), -1)
    pos = np.clip(np.searchsorted(keys, ck), 0, len(keys) - 1)
    found = inside & (keys[pos] == ck)

    def gather(c: int) -> np.ndarray:
        return np.where(found, (values if values.ndim == 1 else values[:, c])[pos], 0.0)

    return f, found, gather


# --------------------------------------------------------------------------------------------
# the variance of the interpolated field at a vertex
# --------------------------------------------------------------------------------------------

def vertex_variance(ijk: np.ndarray, var: np.ndarray, cov: np.ndarray,
                    edges: VertexEdges) -> np.ndarray:
    """``a_v^T C a_v`` for each vertex v of :func:`extract_mesh` (``edges``: its
    :class:`VertexEdges`), C the covariance of a per-voxel field given by its diagonal ``var``
    (N,) and the covariances ``cov`` (N, 3) of each voxel with its +x, +y, +z neighbour
    (DESIGN.md 3.7). ``ijk`` (N, 3) integer, sorted lexicographically (the band's order).

    A vertex on the edge from voxel i along axis e has the two trilinear weights 1 - t on i
    and t on i + e, so ``a^T C a = (1-t)^2 C_ii + 2 t (1-t) C_i,i+e + t^2 C_i+e,i+e``; a
    vertex on a voxel centre has ``C_ii``. (V,) float64; NaN for cell-centre vertices and
    where a voxel is not in ``ijk`` (callers fall back to another estimate there)."""
    from kernels.layout import block_key_np

    out = np.full(len(edges.axis), np.nan)
    if len(ijk) == 0 or len(out) == 0:
        return out
    keys = block_key_np(np.asarray(ijk, np.int64))  # one int64 per voxel, ascending

    def lookup(points):
        k = block_key_np(points)
        pos = np.clip(np.searchsorted(keys, k), 0, len(keys) - 1)
        return np.where(keys[pos] == k, pos, -1)

    var = np.asarray(var, np.float64)
    axis = edges.axis.astype(np.int64)
    grid = np.flatnonzero(axis >= 0)
    i = lookup(edges.ijk[grid])
    on_point = (axis[grid] == 3) & (i >= 0)
    out[grid[on_point]] = var[i[on_point]]
    e = grid[axis[grid] < 3]
    i = i[axis[grid] < 3]
    step = np.zeros((len(e), 3), np.int64)
    step[np.arange(len(e)), axis[e]] = 1
    j = lookup(edges.ijk[e] + step)
    ok = (i >= 0) & (j >= 0)
    e, i, j, t = e[ok], i[ok], j[ok], edges.t[e[ok]]
    c = np.asarray(cov, np.float64)[i, axis[e]]
    out[e] = (1 - t) ** 2 * var[i] + 2 * t * (1 - t) * c + t ** 2 * var[j]
    return out
