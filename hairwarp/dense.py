"""Dense hair from guide strands: root sampling, interpolation weights and per-frame evaluation.

Every rendered strand is bound at setup to the guides around its root (barycentric weights in a
Delaunay triangulation of the roots' scalp coordinates, or bilinear weights on a generator's root
grid). Once per output frame :meth:`DenseHair.evaluate` launches two kernels from
``hairwarp.kernels.interpolate``: interpolation of the dense vertices, then cubic Hermite
densification with Catmull-Rom tangents (DESIGN.md §4.5, seed: dense hair). Given body colliders,
a third launch between the two lifts interpolated vertices out of them (:meth:`DenseHair.push_out`).

The per-frame operator is affine in the guide vertices, so velocities for motion blur come out
of the same kernels applied to the guide velocities.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from hairwarp.executor import launch
from hairwarp.kernels import interpolate as _k

# Boundary triangles of the Delaunay triangulation are dropped while their longest 3-D edge is
# longer than this multiple of the median edge length (they bridge a gap in the scalp) ...
_MAX_EDGE_RATIO = 2.5
# ... or their shape quality 4*sqrt(3)*area / sum(edge^2) (1 = equilateral, 0 = flat) is below this
# (hull slivers). A right isosceles triangle of a regular grid scores 0.87.
_MIN_TRIANGLE_QUALITY = 0.15
# Roots whose smallest principal extent is below this fraction of the largest lie on a plane;
# their scalp coordinates are taken in that plane instead of projecting about their centroid.
_PLANAR_RATIO = 0.05
# Phong shape factor of the root lift: on a sphere the full projection (1) lifts a flat point by
# twice its depth below the sphere, to leading order; 1/2 puts it on the sphere.
_PHONG_SHAPE = 0.5
# Barycentric weights within this of 0 are set to 0 (round-off of a root placed on an edge or a guide).
_WEIGHT_EPS = 1e-9


class DenseHairError(ValueError):
    """Invalid input to :meth:`DenseHair.build`; the message names the argument or the strand."""


def scalp_uv(roots: np.ndarray) -> np.ndarray:
    """2-D scalp coordinates of root points, for triangulating them.

    Nearly planar roots are projected onto their principal plane. Otherwise they are projected
    about their centroid (which lies inside a convex scalp cap, so every ray from it meets the cap
    once) onto the unit sphere, then mapped to the plane by Lambert's azimuthal equal-area
    projection about the mean direction; the map is one-to-one for caps up to nearly a full sphere.

    Args:
        roots: (G, 3) root positions [m].

    Returns:
        (G, 2) float64 coordinates: metres in the planar case, radians-like units otherwise.
    """
    roots = np.asarray(roots, dtype=np.float64)
    centroid = roots.mean(axis=0)
    rel = roots - centroid
    _, sv, vt = np.linalg.svd(rel, full_matrices=False)
    if sv[0] == 0.0 or sv[-1] <= _PLANAR_RATIO * sv[0]:
        return rel @ vt[:2].T
    dist = np.linalg.norm(rel, axis=1)
    if np.any(dist <= 1e-9 * sv[0]):
        raise DenseHairError("scalp_uv: a root coincides with the roots' centroid; pass root_uv explicitly")
    dirs = rel / dist[:, None]
    axis = dirs.mean(axis=0)
    axis /= np.linalg.norm(axis)
    e1 = vt[0] - (vt[0] @ axis) * axis
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    # Lambert azimuthal equal-area: radius 2 sin(theta / 2) = sqrt(2 (1 - cos theta)).
    cos_t = np.clip(dirs @ axis, -1.0, 1.0)
    tangent = np.stack([dirs @ e1, dirs @ e2], axis=1)
    norm = np.linalg.norm(tangent, axis=1)
    scale = np.sqrt(2.0 * (1.0 - cos_t)) / np.where(norm > 0.0, norm, 1.0)
    return tangent * scale[:, None]


def _triangle_metrics(p: np.ndarray, tri: np.ndarray):
    """3-D areas, longest edges and shape qualities of triangles ``tri`` over points ``p``."""
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    e2 = np.stack([((b - a) ** 2).sum(1), ((c - b) ** 2).sum(1), ((a - c) ** 2).sum(1)], axis=1)
    quality = 4.0 * np.sqrt(3.0) * area / np.maximum(e2.sum(1), 1e-300)
    return area, np.sqrt(e2.max(1)), quality, np.sqrt(e2)


def triangulate_roots(root_uv: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Delaunay triangles of the roots in scalp coordinates, without the gap-bridging boundary ones.

    Boundary triangles that are slivers or much longer than the typical edge (in 3-D) are peeled
    off repeatedly, so hair is not interpolated across a gap between separate patches of scalp or
    along the thin triangles of a convex hull. Interior triangles are always kept.

    Args:
        root_uv: (G, 2) scalp coordinates.
        roots: (G, 3) root positions [m], for the 3-D edge lengths.

    Returns:
        (T, 3) int64 guide indices, counter-clockwise in ``root_uv``.
    """
    from scipy.spatial import Delaunay

    tri = Delaunay(root_uv).simplices.astype(np.int64)
    area, longest, quality, edges = _triangle_metrics(roots, tri)
    median_edge = float(np.median(edges))
    bad = (longest > _MAX_EDGE_RATIO * median_edge) | (quality < _MIN_TRIANGLE_QUALITY)
    keep = np.ones(len(tri), dtype=bool)
    while True:
        # An edge used by one kept triangle is on the current boundary.
        kept = tri[keep]
        e = np.sort(np.concatenate([kept[:, [0, 1]], kept[:, [1, 2]], kept[:, [2, 0]]]), axis=1)
        uniq, counts = np.unique(e, axis=0, return_counts=True)
        boundary = {tuple(x) for x in uniq[counts == 1]}
        peel = [
            i
            for i in np.flatnonzero(keep & bad)
            if any(tuple(sorted((tri[i, a], tri[i, b]))) in boundary for a, b in ((0, 1), (1, 2), (2, 0)))
        ]
        if not peel:
            break
        keep[peel] = False
    out = tri[keep]
    if len(out) == 0:
        raise DenseHairError("root_uv: no usable triangle between the guide roots (are the roots collinear?)")
    # Counter-clockwise in uv, so signed barycentric tests work.
    u = root_uv[out]
    ab, ac = u[:, 1] - u[:, 0], u[:, 2] - u[:, 0]
    cross = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    out[cross < 0] = out[cross < 0][:, [0, 2, 1]]
    return out


def barycentric_weights(root_uv: np.ndarray, triangles: np.ndarray, query_uv: np.ndarray):
    """Triangle and barycentric weights of scalp points in a root triangulation.

    Args:
        root_uv: (G, 2) guide root scalp coordinates.
        triangles: (T, 3) guide indices.
        query_uv: (N, 2) points.

    Returns:
        ``(triangle, weights)``: (N,) int64 index into ``triangles`` (-1 when outside every triangle)
        and (N, 3) float64 weights, non-negative and summing to 1 inside.
    """
    query_uv = np.asarray(query_uv, dtype=np.float64).reshape(-1, 2)
    a = root_uv[triangles[:, 0]]
    m = np.stack([root_uv[triangles[:, 1]] - a, root_uv[triangles[:, 2]] - a], axis=2)  # (T, 2, 2)
    inv = np.linalg.inv(m)
    tol = _WEIGHT_EPS
    chunk = max(1, 2**20 // len(triangles))
    found = np.full(len(query_uv), -1, dtype=np.int64)
    weights = np.zeros((len(query_uv), 3))
    for start in range(0, len(query_uv), chunk):
        q = query_uv[start : start + chunk]
        l12 = np.einsum("tij,ntj->nti", inv, q[:, None, :] - a[None])  # (n, T, 2)
        lam = np.concatenate([1.0 - l12.sum(2, keepdims=True), l12], axis=2)
        inside = lam.min(2) >= -tol
        has = inside.any(1)
        first = np.argmax(inside, axis=1)
        rows = np.arange(len(q))
        found[start : start + len(q)] = np.where(has, first, -1)
        weights[start : start + len(q)] = lam[rows, first]
    weights = np.where(weights < _WEIGHT_EPS, 0.0, weights)
    weights /= np.maximum(weights.sum(1, keepdims=True), 1e-300)
    return found, weights


#: Fewest dense vertices (or samples) per chunk of the interpolation and Hermite launches, and fewest dense
#: strands per chunk of the push-out (``hairwarp.executor``).
DENSE_MIN_CHUNK = 1024
STRAND_MIN_CHUNK = 32


class DenseHair:
    """Dense strands interpolated from guides, evaluated on the device once per output frame.

    Build with :meth:`build`. ``D = dense_count`` strands share the guides' segment count S; the
    interpolated vertices are ``D*(S+1)`` (``d*(S+1) + k``, root first) and the Hermite samples
    ``D*P`` with ``P = points_per_curve = M*S + 1`` (``d*P + m``).

    Per-frame operator (kernel ``dense_interpolate``), for dense strand d and vertex k:
    ``x_k = sum_i w_i g_i(u) + c f (g_n(u) - sum_i w_i g_i(u)) + R (o_root + f o_tip)`` with
    ``u = s k`` the length-scaled parameter, ``g(u)`` the guide polyline at u (linear between
    vertices), ``f = k / S``, ``n`` the clump guide, ``c`` the clumping and ``R`` the head rotation.
    Since the weights sum to 1 and ``sum_i w_i g_i(0)`` is the weighted guide roots, this is the
    dense root plus the weighted guide offsets from their roots (DESIGN.md §4.5).

    Attributes:
        device: the Warp device of every array.
        guide_count: number of guides G.
        seg_per_strand: segments per strand S (guides and dense strands).
        dense_count: number of dense strands D.
        samples_per_segment: Hermite samples per segment M.
        points_per_curve: ``M*S + 1`` Hermite samples per dense strand.
        clumping: pull toward the clump guide at the tip, in [0, 1].
        guide_index: numpy (D, 4) int32 guides of each dense strand (unused slots 0).
        guide_weight: numpy (D, 4) float64 weights (unused slots 0); non-negative, sum 1.
        clump_guide: numpy (D,) int32, the guide whose root is nearest to the dense root.
        length_scale: numpy (D,) float64 in ``[1 - length_variation, 1]``.
        root_uv: numpy (G, 2) guide root scalp coordinates (the ones given or made), or None on a grid.
        dense_root_uv: numpy (D, 2) dense roots in scalp coordinates; on a grid, (row, col) coordinates.
        dense_root_position: numpy (D, 3) rest dense roots (head frame) [m], including the scalp lift.
        dense_root_normal: numpy (D, 3) interpolated unit scalp normals, or None without ``root_normal``.
        triangles: numpy (T, 3) guide triangles used for barycentric weights, or None on a grid.
        grid_shape: (rows, cols) or None.
        dense_guide_index: vec4i (D,); dense_guide_weight: vec4 (D,); dense_length_scale: float32 (D,);
            dense_clump_guide: int32 (D,); dense_root_offset, dense_tip_offset: vec3 (D,) [m], head frame.
        dense_vertices, dense_velocities: interpolated vertices [m] / [m/s], vec3 (D*(S+1),), world.
        curve_points, curve_velocities: Hermite samples [m] / [m/s], vec3 (D*P,), world.
        executor: the :class:`hairwarp.executor.Executor` its launches run on (a simulation gives it its
            solver's), or None for one launch each.
    """

    executor = None

    def __init__(self):
        raise TypeError("use DenseHair.build(guide_rest, root_uv, count=... | density=...)")

    @classmethod
    def build(
        cls,
        guide_rest,
        root_uv=None,
        *,
        count: int | None = None,
        density: float | None = None,
        grid_shape: tuple[int, int] | None = None,
        root_normal=None,
        seed: int = 0,
        length_variation: float = 0.0,
        tip_spread: float = 0.0,
        clumping: float = 0.0,
        samples_per_segment: int = 4,
        root_samples=None,
        with_velocities: bool = True,
        device=None,
        max_count: int | None = None,
    ) -> DenseHair:
        """Sample dense roots, bind them to guides and allocate every per-frame buffer.

        Args:
            guide_rest: (G, S+1, 3) guide rest vertices [m], head frame (world at build time), root first.
            root_uv: (G, 2) scalp coordinates of the guide roots; when None, made by :func:`scalp_uv`.
                Ignored with ``grid_shape``.
            count: number of dense strands.
            density: dense strands per square metre of scalp (area of the 3-D root triangles or grid
                cells); exactly one of ``count``, ``density`` and ``root_samples`` is given.
            grid_shape: (rows, cols) when the guides come from a generator's grid, guide ``r*cols + c``;
                roots are then sampled per cell with bilinear weights instead of a triangulation.
            root_normal: optional (G, 3) scalp normals at the guide roots (or one (3,) normal). Dense
                roots, which interpolate the flat triangles or cells between guide roots, are then lifted
                onto the curved scalp by Phong projection (Boubekeur & Alexa 2008) with shape factor 1/2: half-way
                to the weighted mean of the root's projections onto the guides' tangent planes, which is on
                the sphere to leading order when the scalp is one. The lift is fixed in the head frame.
            seed: seeds root sampling and per-strand variation (independent streams).
            length_variation: each strand's length scale is uniform in ``[1 - length_variation, 1]``.
            tip_spread: radius [m] of a uniform random disk, normal to the rest strand's root-to-tip
                direction, in which each tip is offset; the offset grows linearly from 0 at the root.
                Fixed in the head frame.
            clumping: in [0, 1]; vertex k moves toward the clump guide (nearest guide root) by
                ``clumping * k / S`` of the way, so with 1 every tip meets its guide.
            samples_per_segment: Hermite samples per segment M (1 gives the interpolated vertices).
            root_samples: optional (N, 2) explicit dense roots instead of sampling: scalp coordinates in
                the triangulation, or (row, col) grid coordinates with ``grid_shape``.
            with_velocities: allocate the velocity buffers used by ``evaluate(..., guide_velocities)``.
            device: Warp device; the default device when None.
            max_count: the most dense strands ``count`` or ``density`` may ask for (the memory at hand), checked
                before anything of their size is allocated.
        """
        guide_rest = np.asarray(guide_rest, dtype=np.float64)
        if guide_rest.ndim != 3 or guide_rest.shape[2] != 3 or guide_rest.shape[1] < 2 or guide_rest.shape[0] < 1:
            raise DenseHairError(f"guide_rest must have shape (G, S+1, 3) with S >= 1, got {guide_rest.shape}")
        if not np.all(np.isfinite(guide_rest)):
            bad = int(np.flatnonzero(~np.isfinite(guide_rest).all(axis=(1, 2)))[0])
            raise DenseHairError(f"guide_rest: guide strand {bad} has a non-finite vertex")
        if not 0.0 <= length_variation < 1.0:
            raise DenseHairError(f"length_variation must be in [0, 1), got {length_variation}")
        if not tip_spread >= 0.0:
            raise DenseHairError(f"tip_spread must be >= 0, got {tip_spread}")
        if not 0.0 <= clumping <= 1.0:
            raise DenseHairError(f"clumping must be in [0, 1], got {clumping}")
        if int(samples_per_segment) < 1:
            raise DenseHairError(f"samples_per_segment must be >= 1, got {samples_per_segment}")
        if sum(x is not None for x in (count, density, root_samples)) != 1:
            raise DenseHairError("give exactly one of count, density and root_samples")

        G, n_vert = guide_rest.shape[:2]
        roots = guide_rest[:, 0]
        seq = np.random.SeedSequence(seed)
        rng_roots, rng_vary = (np.random.default_rng(s) for s in seq.spawn(2))

        self = object.__new__(cls)
        self.device = wp.get_device(device)
        self.guide_count = G
        self.seg_per_strand = n_vert - 1
        self.samples_per_segment = int(samples_per_segment)
        self.points_per_curve = self.samples_per_segment * self.seg_per_strand + 1
        self.clumping = float(clumping)
        self.grid_shape = None
        self.triangles = None
        self.root_uv = None
        self._max_count = None if max_count is None else int(max_count)  # read by the binders' _sample_count

        if grid_shape is not None and min(int(x) for x in grid_shape) < 2 and root_samples is None \
                and int(np.prod(grid_shape)) == G:
            # a generator's grid of one row or column (a few guides: 1 x 7 for 7) spans no cell: the roots'
            # triangulation binds them instead, as for a groom without a grid
            grid_shape = None
        if grid_shape is not None:
            index, weight, sample_uv = self._bind_grid(roots, grid_shape, count, density, root_samples, rng_roots)
        else:
            index, weight, sample_uv = self._bind_triangles(roots, root_uv, count, density, root_samples, rng_roots)
        D = len(index)
        if D == 0:
            raise DenseHairError("no dense strand to build: count or density gives 0 strands")
        self.dense_count = D
        self.guide_index = index.astype(np.int32)
        self.guide_weight = weight
        self.dense_root_uv = sample_uv
        flat_root = np.einsum("dj,djc->dc", weight, roots[index])

        root_offset = np.zeros((D, 3))
        self.dense_root_normal = None
        if root_normal is not None:
            normals = np.broadcast_to(np.asarray(root_normal, dtype=np.float64), (G, 3))
            length = np.linalg.norm(normals, axis=1)
            if not np.all(np.isfinite(length)) or np.any(length <= 0.0):
                bad = int(np.flatnonzero(~(length > 0.0))[0]) if np.any(~(length > 0.0)) else 0
                raise DenseHairError(f"root_normal: the normal of guide strand {bad} is zero or not finite")
            normals = normals / length[:, None]
            nrm = normals[index]  # (D, 4, 3)
            rel = flat_root[:, None, :] - roots[index]
            proj = flat_root[:, None, :] - np.einsum("djc,djc->dj", rel, nrm)[..., None] * nrm
            root_offset = _PHONG_SHAPE * (np.einsum("dj,djc->dc", weight, proj) - flat_root)
            dn = np.einsum("dj,djc->dc", weight, nrm)
            self.dense_root_normal = dn / np.maximum(np.linalg.norm(dn, axis=1, keepdims=True), 1e-300)
        self.dense_root_position = flat_root + root_offset

        from scipy.spatial import cKDTree

        self.clump_guide = cKDTree(roots).query(flat_root)[1].astype(np.int32)
        self.length_scale = rng_vary.uniform(1.0 - length_variation, 1.0, D) if length_variation > 0 else np.ones(D)

        tip_offset = np.zeros((D, 3))
        if tip_spread > 0.0:
            tip_offset = self._tip_offsets(guide_rest, index, weight, tip_spread, rng_vary)

        self._has_offsets = bool(root_normal is not None or tip_spread > 0.0)
        dev = self.device
        self.dense_guide_index = wp.array(self.guide_index, dtype=wp.vec4i, device=dev)
        self.dense_guide_weight = wp.array(weight, dtype=wp.vec4, device=dev)
        self.dense_length_scale = wp.array(self.length_scale, dtype=wp.float32, device=dev)
        self.dense_clump_guide = wp.array(self.clump_guide, dtype=wp.int32, device=dev)
        self.dense_root_offset = wp.array(root_offset, dtype=wp.vec3, device=dev)
        self.dense_tip_offset = wp.array(tip_offset, dtype=wp.vec3, device=dev)
        self._identity_xform = wp.array([wp.transform_identity()], dtype=wp.transform, device=dev)
        self._zero_velocity = wp.zeros(1, dtype=wp.spatial_vector, device=dev)
        self._push_counts = wp.zeros(2, dtype=wp.int32, device=dev)

        n_dense_vert = D * n_vert
        n_curve = D * self.points_per_curve
        self.dense_vertices = wp.zeros(n_dense_vert, dtype=wp.vec3, device=dev)
        self.curve_points = wp.zeros(n_curve, dtype=wp.vec3, device=dev)
        self.dense_velocities = wp.zeros(n_dense_vert, dtype=wp.vec3, device=dev) if with_velocities else None
        self.curve_velocities = wp.zeros(n_curve, dtype=wp.vec3, device=dev) if with_velocities else None
        return self

    # ------------------------------------------------------------------ binding (setup time)

    def _bind_triangles(self, roots, root_uv, count, density, root_samples, rng):
        G = len(roots)
        if G < 3:
            raise DenseHairError(f"dense hair is interpolated between guides, at least 3, got {G}")
        if root_uv is None:
            root_uv = scalp_uv(roots)
        root_uv = np.asarray(root_uv, dtype=np.float64)
        if root_uv.shape != (G, 2) or not np.all(np.isfinite(root_uv)):
            raise DenseHairError(f"root_uv must be a finite ({G}, 2) array, got shape {root_uv.shape}")
        tri = triangulate_roots(root_uv, roots)
        self.root_uv = root_uv
        self.triangles = tri
        if root_samples is not None:
            sample_uv = np.asarray(root_samples, dtype=np.float64).reshape(-1, 2)
            which, bary = barycentric_weights(root_uv, tri, sample_uv)
            if np.any(which < 0):
                bad = int(np.flatnonzero(which < 0)[0])
                raise DenseHairError(
                    f"root_samples: dense root {bad} at {sample_uv[bad]} is outside the root triangulation"
                )
        else:
            area = _triangle_metrics(roots, tri)[0]
            n = self._sample_count(count, density, area.sum(), self._max_count)
            which = _allocate(area, n, rng)
            # Uniform point in a triangle: reflect the unit square's upper half (area-preserving).
            r = rng.random((n, 2))
            flip = r.sum(1) > 1.0
            r[flip] = 1.0 - r[flip]
            bary = np.column_stack([1.0 - r.sum(1), r])
            sample_uv = np.einsum("dj,djc->dc", bary, root_uv[tri[which]])
        index = np.zeros((len(which), 4), dtype=np.int64)
        weight = np.zeros((len(which), 4))
        index[:, :3] = tri[which]
        weight[:, :3] = bary
        index = np.where(weight > 0.0, index, 0)
        return index, weight, sample_uv

    def _bind_grid(self, roots, grid_shape, count, density, root_samples, rng):
        rows, cols = (int(x) for x in grid_shape)
        if rows < 2 or cols < 2 or rows * cols != len(roots):
            raise DenseHairError(f"grid_shape {tuple(grid_shape)} needs rows, cols >= 2 and rows*cols = {len(roots)}")
        self.grid_shape = (rows, cols)
        if root_samples is not None:
            rc = np.asarray(root_samples, dtype=np.float64).reshape(-1, 2)
            outside = (rc[:, 0] < 0) | (rc[:, 0] > rows - 1) | (rc[:, 1] < 0) | (rc[:, 1] > cols - 1)
            if np.any(outside | ~np.isfinite(rc).all(1)):
                bad = int(np.flatnonzero(outside | ~np.isfinite(rc).all(1))[0])
                raise DenseHairError(f"root_samples: dense root {bad} at {rc[bad]} is outside the {rows}x{cols} grid")
            r0 = np.minimum(np.floor(rc[:, 0]).astype(np.int64), rows - 2)
            c0 = np.minimum(np.floor(rc[:, 1]).astype(np.int64), cols - 2)
            v, u = rc[:, 0] - r0, rc[:, 1] - c0
        else:
            g = roots.reshape(rows, cols, 3)
            a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
            area = (
                0.5
                * (
                    np.linalg.norm(np.cross(b - a, d - a), axis=2) + np.linalg.norm(np.cross(d - a, c - a), axis=2)
                ).ravel()
            )
            n = self._sample_count(count, density, area.sum(), self._max_count)
            cell = _allocate(area, n, rng)
            r0, c0 = cell // (cols - 1), cell % (cols - 1)
            v, u = rng.random(n), rng.random(n)
        base = r0 * cols + c0
        index = np.stack([base, base + 1, base + cols, base + cols + 1], axis=1)
        weight = np.stack([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v], axis=1)
        index = np.where(weight > 0.0, index, 0)
        return index, weight, np.column_stack([r0 + v, c0 + u])

    @staticmethod
    def _sample_count(count, density, area, max_count=None):
        if count is not None:
            if int(count) < 1:
                raise DenseHairError(f"count must be >= 1, got {count}")
            n, asked = int(count), f"count {int(count):,}"
        else:
            if not density > 0.0:
                raise DenseHairError(f"density must be > 0 strands/m^2, got {density}")
            n = int(round(density * area))
            asked = f"density {density:g} strands/m^2 gives {n:,} strands on {area:.3g} m^2 of scalp"
            if n == 0:
                raise DenseHairError(f"{asked}: none to build")
        if max_count is not None and n > max_count:
            raise DenseHairError(f"{asked}, past the {max_count:,} that fit in memory")
        return n

    def _tip_offsets(self, guide_rest, index, weight, tip_spread, rng):
        S = self.seg_per_strand
        # Rest dense strand's root-to-tip direction: its tip at the scaled length, after clumping.
        u = self.length_scale * S
        j = np.minimum(u.astype(np.int64), S - 1)
        t = (u - j)[:, None]

        def guide_at(g):
            return (1 - t[..., None]) * guide_rest[g, j[:, None]] + t[..., None] * guide_rest[g, j[:, None] + 1]

        tip = np.einsum("dj,djc->dc", weight, guide_at(index))
        tip += self.clumping * (guide_at(self.clump_guide[:, None])[:, 0] - tip)
        axis = tip - np.einsum("dj,djc->dc", weight, guide_rest[index, 0])
        length = np.linalg.norm(axis, axis=1, keepdims=True)
        axis = np.where(length > 0, axis / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
        helper = np.where(np.abs(axis[:, [2]]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(axis, e1)
        radius = tip_spread * np.sqrt(rng.random(len(axis)))
        angle = rng.uniform(0.0, 2.0 * np.pi, len(axis))
        return (radius * np.cos(angle))[:, None] * e1 + (radius * np.sin(angle))[:, None] * e2

    # ------------------------------------------------------------------ per frame (launches only)

    def _check(self, guide_array, name):
        if guide_array.shape[0] != self.guide_count * (self.seg_per_strand + 1):
            raise DenseHairError(
                f"{name} has {guide_array.shape[0]} entries, expected G*(S+1) = "
                f"{self.guide_count * (self.seg_per_strand + 1)}"
            )

    def _interpolate(self, guide_x, head_xform, head_velocity, velocity, out):
        launch(
            self.executor,
            _k.dense_interpolate,
            out.shape[0],
            [
                self.seg_per_strand,
                self.dense_guide_index,
                self.dense_guide_weight,
                self.dense_length_scale,
                self.dense_clump_guide,
                self.dense_root_offset,
                self.dense_tip_offset,
                self.clumping,
                int(self._has_offsets),
                guide_x,
                int(velocity),
                self._identity_xform if head_xform is None else head_xform,
                self._zero_velocity if head_velocity is None else head_velocity,
            ],
            [out],
            device=self.device,
            min_chunk=DENSE_MIN_CHUNK,
        )
        return out

    def interpolate(self, guide_vertices: wp.array, head_xform: wp.array | None = None) -> wp.array:
        """Interpolate the dense vertices from the guides' current vertices.

        Args:
            guide_vertices: vec3 (G*(S+1),) guide vertices [m], world (e.g. ``State.vertex_positions``).
            head_xform: wp.transform (1,) head pose (``Control.head_xform``); it turns the head-frame root
                lift and tip spread. Identity when None.

        Returns:
            ``dense_vertices``, vec3 (D*(S+1),) [m], world; the same array on every call.
        """
        self._check(guide_vertices, "guide_vertices")
        return self._interpolate(guide_vertices, head_xform, None, False, self.dense_vertices)

    def densify(self, dense_vertices: wp.array | None = None, out: wp.array | None = None) -> wp.array:
        """Hermite-sample dense strands (``dense_vertices`` when None) into ``out`` (``curve_points`` when None).

        Args:
            dense_vertices: vec3 (D*(S+1),) strand vertices; any per-vertex vec3 quantity works (e.g.
                ``dense_velocities`` into ``out=curve_velocities``).
            out: vec3 (D*points_per_curve,) destination.

        Returns:
            ``out``, vec3 (D*points_per_curve,); the same array on every call.
        """
        src = self.dense_vertices if dense_vertices is None else dense_vertices
        dst = self.curve_points if out is None else out
        if dst.shape[0] != self.dense_count * self.points_per_curve:
            raise DenseHairError(f"out has {dst.shape[0]} entries, expected D*points_per_curve")
        return self._densify(src, dst)

    def _densify(self, src, out):
        if src.shape[0] != self.dense_count * (self.seg_per_strand + 1):
            raise DenseHairError(f"dense_vertices has {src.shape[0]} entries, expected D*(S+1)")
        launch(self.executor, _k.hermite_samples, out.shape[0], [self.seg_per_strand, self.samples_per_segment, src],
               [out], device=self.device, min_chunk=DENSE_MIN_CHUNK)
        return out

    def push_out(self, colliders, head_xform: wp.array | None = None, dense_vertices: wp.array | None = None,
                 head_velocity: wp.array | None = None) -> wp.array:
        """Lift interpolated vertices out of body colliders, keeping segment lengths (one launch, in place).

        Interpolated hair can cut into the head where the guides around it pass on either side. Every
        vertex after the root that lies inside a collider or within its ``thickness`` is moved to
        ``thickness`` above the surface: it turns about the previous vertex on the sphere of its segment
        (so that segment keeps its length) until it clears the tangent plane at its closest surface point,
        re-queried up to ``PUSH_ITERATIONS`` times; only where the sphere cannot reach that far (the
        previous vertex is deep, e.g. a root under the surface) is it put at the closest point plus
        ``thickness`` along the normal. The rest of the strand then follows by the seed's rule
        ``p'_{k+1} = p'_k + L_k (p_{k+1} - p'_k) / |p_{k+1} - p'_k|``, with ``L_k`` the interpolated
        segment lengths. Roots are never moved; strands clear of every contact layer are not written.
        Velocities are left as interpolated. The colliders are queried as the guides' projection queries
        them (``hairwarp.kernels.body_collision``), at their pose on the device: head-attached ones at
        ``head_xform``, world ones at ``ColliderSet.collider_xform`` (set by ``update`` / ``set_pose``).

        Call it after :meth:`interpolate` and before :meth:`densify`, or pass ``colliders`` to
        :meth:`evaluate`, which does both. Pushed-vertex counts of the last call: :attr:`push_counts`.

        Args:
            colliders: a :class:`hairwarp.colliders.ColliderSet` on this device (no launch when empty or None).
            head_xform: wp.transform (1,) head pose (``Control.head_xform``), identity when None.
            dense_vertices: vec3 (D*(S+1),) strands to push out, world; ``dense_vertices`` when None.
            head_velocity: wp.spatial_vector (1,) (``Control.head_velocity``); not used by the push, only
                passed to the collider pose function. Zero when None.

        Returns:
            The pushed array (``dense_vertices`` unless another one is given).
        """
        src = self.dense_vertices if dense_vertices is None else dense_vertices
        if src.shape[0] != self.dense_count * (self.seg_per_strand + 1):
            raise DenseHairError(f"dense_vertices has {src.shape[0]} entries, expected D*(S+1)")
        self._push_counts.zero_()
        if colliders is None or colliders.count == 0:
            return src
        if colliders.device != self.device:
            raise DenseHairError(f"colliders are on {colliders.device}, dense hair on {self.device}")
        # one thread per dense strand, in place; the pushed-vertex counters are private per chunk
        launch(
            self.executor,
            _k.dense_push_out,
            self.dense_count,
            [
                self.seg_per_strand,
                colliders.shapes,
                colliders.collider_xform,
                colliders.collider_velocity,
                self._identity_xform if head_xform is None else head_xform,
                self._zero_velocity if head_velocity is None else head_velocity,
                self._push_counts,
            ],
            [src],
            device=self.device,
            min_chunk=STRAND_MIN_CHUNK,
            private_add=[6],
        )
        return src

    @property
    def push_counts(self) -> tuple[int, int]:
        """``(lifted, projected)`` vertices of the last :meth:`push_out`: lifted ones kept every segment length,
        projected ones (out of their segment's reach) changed the length of the segment ending at them.
        Reads the device (diagnostics, not per frame)."""
        lifted, projected = self._push_counts.numpy()
        return int(lifted), int(projected)

    def evaluate(
        self,
        guide_vertices: wp.array,
        guide_velocities: wp.array | None = None,
        head_xform: wp.array | None = None,
        head_velocity: wp.array | None = None,
        hermite: bool = True,
        colliders=None,
    ) -> tuple[wp.array, wp.array | None]:
        """Interpolate, push out of the colliders (when given) and densify positions and, when given,
        velocities (for motion blur).

        Args:
            guide_vertices: vec3 (G*(S+1),) guide vertices [m], world.
            guide_velocities: vec3 (G*(S+1),) guide vertex velocities [m/s], world, or None.
            head_xform: wp.transform (1,) head pose, identity when None.
            head_velocity: wp.spatial_vector (1,) head (angular, linear) velocity (``Control.head_velocity``);
                its angular part moves the head-frame offsets. Zero when None.
            hermite: densify with Hermite samples; False returns the interpolated vertices (for
                Catmull-Rom curves, which a renderer evaluates itself).
            colliders: a :class:`hairwarp.colliders.ColliderSet`: the interpolated vertices are pushed out
                of it (:meth:`push_out`) before densifying; None (default) skips the pass at no cost.

        Returns:
            ``(points, velocities)``, each vec3 (D*points_per_curve,) (or (D*(S+1),) without ``hermite``),
            or None for velocities.
        """
        self.interpolate(guide_vertices, head_xform)
        if colliders is not None:
            self.push_out(colliders, head_xform, head_velocity=head_velocity)
        if hermite:
            self._densify(self.dense_vertices, self.curve_points)
        if guide_velocities is None:
            return (self.curve_points if hermite else self.dense_vertices), None
        if self.dense_velocities is None:
            raise DenseHairError("velocities requested from a DenseHair built with with_velocities=False")
        self._check(guide_velocities, "guide_velocities")
        self._interpolate(guide_velocities, head_xform, head_velocity, True, self.dense_velocities)
        if not hermite:
            return self.dense_vertices, self.dense_velocities
        self._densify(self.dense_velocities, self.curve_velocities)
        return self.curve_points, self.curve_velocities

    # ------------------------------------------------------------------ output helpers

    def curve_vertex_counts(self, hermite: bool = True) -> np.ndarray:
        """Vertices per dense curve, int32 (D,): ``points_per_curve`` or S+1 (``hermite=False``)."""
        n = self.points_per_curve if hermite else self.seg_per_strand + 1
        return np.full(self.dense_count, n, dtype=np.int32)

    def widths(self, root_width: float, tip_width: float, hermite: bool = True) -> np.ndarray:
        """Per-vertex widths [m], float32 (D*n,), tapering linearly in the curve parameter from root to tip."""
        n = self.points_per_curve if hermite else self.seg_per_strand + 1
        taper = root_width + (tip_width - root_width) * np.linspace(0.0, 1.0, n)
        return np.tile(taper, self.dense_count).astype(np.float32)


def _allocate(area: np.ndarray, n: int, rng) -> np.ndarray:
    """Cell index of each of ``n`` samples, area-proportional with systematic resampling.

    Every cell gets ``floor`` or ``ceil`` of its expected count (lower variance than independent
    draws, so no bald patches), in a random order.
    """
    cdf = np.cumsum(area)
    cdf /= cdf[-1]
    pos = (rng.random() + np.arange(n)) / n
    cells = np.minimum(np.searchsorted(cdf, pos, side="right"), len(area) - 1)
    return rng.permutation(cells)


def bench_dense(
    counts=(10_000, 100_000),
    guides: int = 300,
    segments: int = 20,
    repeats: int = 3,
    device=None,
    samples_per_segment: int = 4,
) -> dict:
    """Time dense interpolation and Hermite densification per output frame.

    Guides are wavy strands of 0.3 m on a scalp cap of radius 0.1 m (Fibonacci lattice); dense hair
    uses length variation, tip spread and clumping, so the timed kernels do all their work.

    Args:
        counts: dense strand counts to time.
        guides: number of guides G.
        segments: segments per strand S.
        repeats: timed repetitions per figure; the median is reported.
        device: Warp device; the default device when None.
        samples_per_segment: Hermite samples per segment M.

    Returns:
        ``{"device", "guides", "segments", "samples_per_segment", "repeats", "results": [{"count",
        "interpolate_s", "hermite_s", "evaluate_velocities_s", "vertices", "points", "build_s"}, ...]}``,
        times in seconds per frame (median, after one warm-up call).
    """
    device = wp.get_device(device)
    guide_rest, normals = _bench_guides(guides, segments)
    guide_x = wp.array(guide_rest.reshape(-1, 3), dtype=wp.vec3, device=device)
    guide_v = wp.array(np.full((guide_x.shape[0], 3), 0.1), dtype=wp.vec3, device=device)

    from hairwarp.benchmarks.common import timed_samples

    def timed(fn):
        return float(np.median(timed_samples(fn, device, repeats)))

    results = []
    for n in counts:
        t0 = time.perf_counter()
        hair = DenseHair.build(
            guide_rest,
            count=int(n),
            root_normal=normals,
            seed=1,
            length_variation=0.2,
            tip_spread=0.005,
            clumping=0.3,
            samples_per_segment=samples_per_segment,
            device=device,
        )
        build_s = time.perf_counter() - t0
        results.append(
            {
                "count": int(n),
                "interpolate_s": timed(lambda h=hair: h.interpolate(guide_x)),
                "hermite_s": timed(lambda h=hair: h.densify()),
                "evaluate_velocities_s": timed(lambda h=hair: h.evaluate(guide_x, guide_v)),
                "vertices": int(hair.dense_vertices.shape[0]),
                "points": int(hair.curve_points.shape[0]),
                "build_s": build_s,
            }
        )
    return {
        "device": str(device),
        "guides": guides,
        "segments": segments,
        "samples_per_segment": samples_per_segment,
        "repeats": repeats,
        "results": results,
    }


def _bench_guides(guides: int, segments: int):
    """Wavy guides hanging from a scalp cap (Fibonacci lattice on the upper 60 degrees of a sphere)."""
    radius, length = 0.1, 0.3
    i = np.arange(guides) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(np.radians(60.0))) * i / guides
    phi = np.pi * (1.0 + 5.0**0.5) * i
    sin_t = np.sqrt(1.0 - cos_t**2)
    normals = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    s = np.linspace(0.0, length, segments + 1)
    down = np.array([0.0, 0.0, -1.0])
    # Out along the normal, then bending down, with a small wave.
    direction = normals[:, None, :] * np.exp(-s / 0.05)[None, :, None] + down * (1 - np.exp(-s / 0.05))[None, :, None]
    wave = 0.01 * np.sin(s / 0.03)[None, :, None] * np.cross(normals, down)[:, None, :]
    pts = (
        radius * normals[:, None, :]
        + np.cumsum(direction * (length / segments), axis=1)
        - direction[:, :1] * (length / segments)
        + wave
    )
    return pts, normals
