"""Strand colliders: analytic primitives and closed triangle meshes, their placement and animation.

A ``Collider`` is geometry in its own local frame plus a rigid placement ``local_xform`` in its parent,
the head (``attach="head"``: it rides on ``Control.head_xform``) or the world (``attach="world"``:
static, or driven by a ``motion`` object, or posed each step with ``ColliderSet.set_pose``).
``ColliderSet`` puts a list of colliders on the device once and runs the per-step projection
(``hairwarp.kernels.body_collision.collide_strands``): vertices closer than ``thickness`` lose their
approach speed and rub on the object with Coulomb friction (``friction`` 1 is the seed's full velocity
match), vertices inside are pushed out onto the surface and the rest of the strand follows with its
segment lengths kept (Chang, Jin & Yu 2002).

Rest vertices that start inside a collider (real grooms have them: the TressFX Ratboy mohawk has roots
and first vertices up to 1 mm inside the body) are *exempt* from that collider: ``ColliderSet.mark_exempt``
marks every vertex inside a collider where the hair starts (``bind`` at the rest pose, ``hairwarp.Simulation`` the
head and the world colliders posed at time 0), the projection leaves such a vertex alone for that collider
until it is first seen clear of the contact layer (distance >= thickness), and from then on it collides
like any other. Pushing them out at the first step kicks the strands (the joint springs hold the rest
shape inside): on the Ratboy mohawk the first step then throws vertices at 1.4 m/s and the solver
flags a joint-speed fault within one simulated second, where exempt vertices start from rest and run fault-free.
A vertex that follows an exempt one still inside can rise by one segment length only, so it may stay
short of the surface until the strand lifts.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp

from hairwarp.executor import launch
from hairwarp.kernels.types import ColliderKind

# Rotation part of a placement must be orthonormal to this tolerance (float32 matrices written to
# text keep about 6 digits).
_ORTHONORMAL_TOL = 1.0e-4

# The exemption mask is an int32 per vertex, one bit per collider.
MAX_EXEMPT_COLLIDERS = 31


class ColliderError(ValueError):
    """A collider description or mesh file is invalid; the message names the collider or the file."""


class TfxMeshError(ColliderError):
    """A ``.tfxmesh`` file could not be read; the message names the file and the line."""


def __getattr__(name):
    """``read_tfxmesh``, which lives in :mod:`hairwarp.io.tfx`, imported from there on first use."""
    if name == "read_tfxmesh":
        from hairwarp.io.tfx import read_tfxmesh

        return read_tfxmesh
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _translation(offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = np.asarray(offset, dtype=float)
    return m


def _check_mesh_extent(vertices, what: str) -> None:
    """A ColliderError naming the farthest vertex when one lies beyond ``MAX_COORDINATE`` of the origin (a mesh in
    the wrong units: float32 resolves no millimetre there)."""
    from hairwarp.model import MAX_COORDINATE

    v = np.asarray(vertices, dtype=np.float64)
    if len(v) and np.abs(v).max() > MAX_COORDINATE:
        i = int(np.abs(v).max(axis=1).argmax())
        raise ColliderError(f"{what}: vertex {i} lies at ({', '.join(f'{x:.3g}' for x in v[i])}) m, beyond "
                            f"{MAX_COORDINATE:g} m of the origin, where float32 resolves no millimetre: check the "
                            f"file's units (scale)")


def _rigid_matrix(matrix, what: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ColliderError(f"{what}: placement must be a finite 4x4 matrix, got shape {m.shape}")
    r = m[:3, :3]
    if (np.abs(r.T @ r - np.eye(3)).max() > _ORTHONORMAL_TOL or np.linalg.det(r) <= 0.0
            or np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > 0.0):
        raise ColliderError(f"{what}: placement must be rigid (rotation and translation; put scale in the geometry)")
    return m


def matrix_to_transform(matrix) -> np.ndarray:
    """A rigid 4x4 matrix as Warp transform components (px, py, pz, qx, qy, qz, qw)."""
    m = np.asarray(matrix, dtype=float)
    r = m[:3, :3]
    tr = np.trace(r)
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = (0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = ((r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s)
    q = np.asarray(q) / np.linalg.norm(q)
    return np.concatenate([m[:3, 3], q])


def _check_obj_vertices(path: Path) -> None:
    """Raises ColliderError naming the first ``v`` line of an OBJ file whose coordinates are not finite numbers."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise ColliderError(f"{path}: cannot read ({exc.strerror or exc})") from None
    vertex = 0
    for number, line in enumerate(lines, 1):
        fields = line.split()
        if not fields or fields[0] != "v":
            continue
        vertex += 1
        try:
            ok = len(fields) >= 4 and np.isfinite([float(x) for x in fields[1:4]]).all()
        except ValueError:
            ok = False
        if not ok:
            raise ColliderError(f"{path}: line {number}: vertex {vertex} is not three finite numbers: "
                                f"{' '.join(fields[1:4])!r}")


@dataclasses.dataclass
class Collider:
    """One strand collider.

    Attributes:
        name: unique name, used in messages.
        kind: ``ColliderKind`` (SPHERE, CAPSULE, PLANE, MESH).
        radius: sphere or capsule radius [m].
        half_height: capsule half length of its axis segment, along local z [m].
        mesh: ``trimesh.Trimesh`` in the collider's local frame [m]; MESH only. Must be closed for the
            inside test (a warning names a collider that is not).
        local_xform: rigid 4x4 placement of the local frame in the parent (head or world).
        attach: ``"head"`` (follows ``Control.head_xform``) or ``"world"``.
        motion: for a world collider, an object with ``evaluate(t)`` returning a sample with
            ``matrix()`` (4x4), ``linear_velocity`` (of its origin) and ``angular_velocity``, in world
            (e.g. ``hairwarp.HeadMotion``); None for a static one.
        thickness: contact layer [m]: vertices closer than this lose their approach speed and feel
            friction. Pushed-out vertices land just above the surface (``PUSH_MARGIN``, 10 um), not at the
            top of the layer, so a push is no larger than the penetration it undoes.
        friction: Coulomb friction: a vertex in contact may change its slip relative to the object by at
            most ``mu`` times the approach speed it lost, ``mu = friction / (1 - friction)`` (0.5 gives
            mu = 1), so friction does not depend on the step size; 0 = frictionless, 1 = the seed's full
            velocity match (the vertex takes the object's velocity). Where static friction holds, the
            slip is also taken off the step's displacement, so a resting vertex does not creep.
    """

    name: str
    kind: ColliderKind
    radius: float = 0.0
    half_height: float = 0.0
    radii: Any = None
    mesh: Any = None
    local_xform: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    attach: str = "head"
    motion: Any = None
    thickness: float = 1.0e-3
    friction: float = 0.5

    def __post_init__(self):
        what = f"collider {self.name!r}"
        try:
            self.kind = ColliderKind(self.kind)
        except ValueError:
            raise ColliderError(f"{what}: unknown kind {self.kind!r}") from None
        if self.attach not in ("head", "world"):
            raise ColliderError(f"{what}: attach must be 'head' or 'world', got {self.attach!r}")
        if self.attach == "head" and self.motion is not None:
            raise ColliderError(f"{what}: a head-attached collider follows the head; motion needs attach='world'")
        self.local_xform = _rigid_matrix(self.local_xform, what)
        for key in ("radius", "half_height", "thickness", "friction"):
            value = float(getattr(self, key))
            if not np.isfinite(value) or value < 0.0:
                raise ColliderError(f"{what}: {key} must be a finite number >= 0, got {value}")
            setattr(self, key, value)
        if self.friction > 1.0:
            raise ColliderError(f"{what}: friction must lie in [0, 1], got {self.friction}")
        if self.kind in (ColliderKind.SPHERE, ColliderKind.CAPSULE) and self.radius <= 0.0:
            raise ColliderError(f"{what}: radius must be > 0, got {self.radius}")
        if self.kind == ColliderKind.MESH:
            self._check_mesh(what)
        if self.kind == ColliderKind.ELLIPSOID:
            r = np.asarray(self.radii if self.radii is not None else (), dtype=float)
            if r.shape != (3,) or not np.all(np.isfinite(r)) or np.any(r <= 0.0):
                raise ColliderError(f"{what}: radii must be three numbers > 0, got {self.radii!r}")
            self.radii = r

    def _check_mesh(self, what: str):
        import trimesh

        if not isinstance(self.mesh, trimesh.Trimesh) or len(self.mesh.faces) == 0:
            raise ColliderError(f"{what}: a MESH collider needs a trimesh.Trimesh with faces")
        if not np.all(np.isfinite(self.mesh.vertices)):
            raise ColliderError(f"{what}: mesh has non-finite vertices")
        _check_mesh_extent(self.mesh.vertices, what)
        closed = self.mesh.is_watertight
        if not closed:
            merged = self.mesh.copy()
            merged.merge_vertices()
            closed = merged.is_watertight
        if not closed:
            warnings.warn(f"{what}: mesh is not watertight; its inside test may be wrong", stacklevel=3)
        elif self.mesh.volume < 0.0:
            warnings.warn(f"{what}: mesh faces point inward; flipped", stacklevel=3)
            self.mesh = self.mesh.copy()
            self.mesh.invert()

    @classmethod
    def sphere(cls, radius: float, *, center=(0.0, 0.0, 0.0), name: str = "sphere", **options) -> Collider:
        """A sphere of ``radius`` [m] at ``center`` in its parent; ``options``: attach, motion, thickness, friction."""
        return cls(name=name, kind=ColliderKind.SPHERE, radius=radius, local_xform=_translation(center), **options)

    @classmethod
    def capsule(cls, radius: float, half_height: float, *, local_xform=None, name: str = "capsule",
                **options) -> Collider:
        """A capsule of ``radius`` around the local z segment ``[-half_height, half_height]`` [m]."""
        return cls(name=name, kind=ColliderKind.CAPSULE, radius=radius, half_height=half_height,
                   local_xform=np.eye(4) if local_xform is None else local_xform, **options)

    @classmethod
    def plane(cls, *, point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), name: str = "plane", **options) -> Collider:
        """The half-space below the plane through ``point`` with outward ``normal`` (in its parent)."""
        n = np.asarray(normal, dtype=float)
        if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0.0:
            raise ColliderError(f"collider {name!r}: plane normal must be a non-zero 3-vector, got {normal!r}")
        n = n / np.linalg.norm(n)
        helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(helper, n)
        x /= np.linalg.norm(x)
        m = _translation(point)
        m[:3, :3] = np.stack([x, np.cross(n, x), n], axis=1)
        return cls(name=name, kind=ColliderKind.PLANE, local_xform=m, **options)

    @classmethod
    def from_trimesh(cls, mesh, *, local_xform=None, name: str = "mesh", **options) -> Collider:
        """A mesh collider from a ``trimesh.Trimesh`` given in the collider's local frame [m]."""
        return cls(name=name, kind=ColliderKind.MESH, mesh=mesh,
                   local_xform=np.eye(4) if local_xform is None else local_xform, **options)

    @classmethod
    def from_mesh_file(cls, path, *, up_axis: str = "Z", scale: float = 1.0, name: str | None = None,
                       **options) -> Collider:
        """A mesh collider from a file: OBJ, PLY, STL, GLB (through trimesh) or TressFX ``.tfxmesh``.

        Args:
            path: the mesh file.
            up_axis: the file's up axis, "Z" or "Y" ((x, y, z) -> (x, -z, y)); a ``.tfxmesh`` is Y-up by
                definition and always turned, whatever this says.
            scale: multiplies the points (file units to metres).
            name: collider name; the file stem by default.
            **options: ``local_xform``, ``attach``, ``motion``, ``thickness``, ``friction``.

        Raises:
            ColliderError: unreadable file, no triangles, bad ``up_axis`` or ``scale``.
        """
        import trimesh

        path = Path(path)
        axis = str(up_axis).upper()
        if axis not in ("Y", "Z"):
            raise ColliderError(f"{path}: up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not (np.isfinite(scale) and scale > 0.0):
            raise ColliderError(f"{path}: scale must be > 0, got {scale!r}")
        if path.suffix.lower() == ".tfxmesh":
            from hairwarp.io.tfx import read_tfxmesh

            mesh = read_tfxmesh(path)
            _check_mesh_extent(mesh.vertices * scale, str(path))
        else:
            if path.suffix.lower() == ".obj":
                _check_obj_vertices(path)
            try:
                # Unprocessed first: processing drops non-finite vertices and every face using them, silently.
                mesh = trimesh.load(str(path), force="mesh", process=False)
            except Exception as exc:
                raise ColliderError(f"{path}: cannot load mesh ({exc})") from exc
            if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
                raise ColliderError(f"{path}: no triangles in the file")
            bad = np.flatnonzero(~np.isfinite(mesh.vertices).all(axis=1))
            if bad.size:
                raise ColliderError(f"{path}: vertex {int(bad[0])} is not finite "
                                    f"({', '.join(f'{x:g}' for x in mesh.vertices[bad[0]])})")
            _check_mesh_extent(mesh.vertices * scale, str(path))  # before processing: its merge overflows there
            mesh.process()
            if axis == "Y":
                v = mesh.vertices
                mesh = trimesh.Trimesh(vertices=np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1), faces=mesh.faces,
                                       process=False)
        if scale != 1.0:
            mesh = trimesh.Trimesh(vertices=mesh.vertices * scale, faces=mesh.faces, process=False)
        return cls.from_trimesh(mesh, name=path.stem if name is None else name, **options)

    @classmethod
    def ellipsoid(cls, center=(0.0, 0.0, 0.0), radii=(0.09, 0.1, 0.115), subdivisions: int | None = None, *,
                  name: str = "head", local_xform=None, **options) -> Collider:
        """An ellipsoid, e.g. a generated head; ``radii`` [m] along its local x, y, z.

        Analytic by default (exact closest points by a few Newton steps, a closed-form swept test); with
        ``subdivisions`` a closed mesh instead, the icosphere of that many subdivisions scaled to ``radii``.
        ``local_xform`` (4x4, rigid) places it turned in its parent instead of at ``center``.
        """
        r = np.asarray(radii, dtype=float)
        if r.shape != (3,) or not np.all(np.isfinite(r)) or np.any(r <= 0.0):
            raise ColliderError(f"collider {name!r}: radii must be three numbers > 0, got {radii!r}")
        place = _translation(center) if local_xform is None else np.asarray(local_xform, dtype=float)
        if subdivisions is None:
            return cls(name=name, kind=ColliderKind.ELLIPSOID, radii=r, local_xform=place, **options)
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=int(subdivisions))
        mesh = trimesh.Trimesh(vertices=sphere.vertices * r, faces=sphere.faces, process=False)
        return cls.from_trimesh(mesh, local_xform=place, name=name, **options)


#: Fewest strands per chunk of the per-strand collision launches (``hairwarp.executor``).
STRAND_MIN_CHUNK = 16


def _collider_size(col) -> float:
    """The farthest [m] a point of ``col`` lies from its origin (0 for a plane, which no turn moves along itself)."""
    if col.kind == ColliderKind.MESH and col.mesh is not None:
        return float(np.linalg.norm(np.asarray(col.mesh.vertices, dtype=float), axis=1).max())
    if col.kind == ColliderKind.ELLIPSOID and col.radii is not None:
        return float(np.max(col.radii))
    if col.kind == ColliderKind.CAPSULE:
        return float(col.radius + col.half_height)
    if col.kind == ColliderKind.SPHERE:
        return float(col.radius)
    return 0.0


class ColliderSet:
    """Colliders on the device and the per-step strand projection.

    Device arrays: ``shapes``, a ``hairwarp.kernels.body_collision.ColliderShapes`` of one entry per collider
    (kind, attachment, local pose, sizes, contact layer, friction, mesh id and bounds), built once; per step
    ``collider_xform`` (world pose) and ``collider_velocity`` (world angular, linear velocity of
    the collider origin), rewritten in place by ``set_pose`` and ``update``. The projection reads a
    head-attached collider's pose from ``Control.head_xform`` and ``head_velocity`` on the device, so a
    captured step follows the head without host updates; for such colliders the two per-step arrays only
    mirror the pose given to ``update`` (for output).

    Args:
        colliders: the colliders; names must be unique.
        device: Warp device.
        model: if given, ``bind(model)`` is called.
        swept: also test each vertex's path over the step relative to a sphere or capsule (its previous
            position estimated from its velocity and the collider's), and push a vertex that entered it
            out on the side it came in from; False tests the end positions only.
    """

    def __init__(self, colliders, device=None, *, model=None, swept: bool = True):
        self.colliders = list(colliders)
        self.swept = bool(swept)
        self.device = wp.get_device(device)
        self.executor = None  # the solver's hairwarp.executor.Executor, set when a Solver takes this set
        names = [c.name for c in self.colliders]
        duplicate = next((n for n in names if names.count(n) > 1), None)
        if duplicate is not None:
            raise ColliderError(f"collider {duplicate!r}: names must be unique")
        count = len(self.colliders)
        self.count = count
        self._index = {n: i for i, n in enumerate(names)}
        self._xform_host = np.zeros((count, 7), dtype=np.float32)
        self._velocity_host = np.zeros((count, 6), dtype=np.float32)
        self._world_host = np.tile(np.eye(4), (count, 1, 1))
        #: the fastest [m/s] a world collider has moved any point of itself (origin speed + angular speed times its
        #: size), over every pose set so far: the hair speed fault's bound takes it in (``Solver.speed_bound``)
        self.peak_speed = 0.0
        self._size = [_collider_size(c) for c in self.colliders]
        bound_lo = np.zeros((count, 3), dtype=np.float32)
        bound_hi = np.zeros((count, 3), dtype=np.float32)
        far = np.zeros(count, dtype=np.float32)
        mesh_ids = np.zeros(count, dtype=np.uint64)
        self.meshes: list[wp.Mesh | None] = []
        for i, col in enumerate(self.colliders):
            self._set_world(i, col.local_xform, np.zeros(3), np.zeros(3))
            if col.attach == "world" and col.motion is not None:
                self._pose_from_motion(i, col, 0.0)
            mesh = None
            if col.kind == ColliderKind.MESH:
                points = np.asarray(col.mesh.vertices, dtype=np.float32)
                mesh = wp.Mesh(points=wp.array(points, dtype=wp.vec3, device=self.device),
                               indices=wp.array(np.asarray(col.mesh.faces, dtype=np.int32).ravel(), dtype=wp.int32,
                                                device=self.device),
                               )
                mesh_ids[i] = mesh.id
                bound_lo[i] = points.min(axis=0)
                bound_hi[i] = points.max(axis=0)
                # Farther than any inside point can be from the surface, so the unbounded query is exact.
                far[i] = 10.0 * float(np.linalg.norm(bound_hi[i] - bound_lo[i])) + 10.0
            elif col.kind == ColliderKind.ELLIPSOID:
                bound_lo[i] = -col.radii  # the kernels read an ellipsoid's semi-axes from its bounds
                bound_hi[i] = col.radii
            self.meshes.append(mesh)

        def arr(values, dtype):
            return wp.array(values, dtype=dtype, device=self.device)

        from hairwarp.kernels.body_collision import ColliderShapes

        def per_collider(key):
            return np.array([getattr(c, key) for c in self.colliders], dtype=np.float32)

        shapes = ColliderShapes()
        shapes.count = count
        shapes.kind = arr(np.array([int(c.kind) for c in self.colliders], dtype=np.int32), wp.int32)
        shapes.attach = arr(np.array([c.attach == "head" for c in self.colliders], dtype=np.int32), wp.int32)
        shapes.local_xform = arr(
            np.array([matrix_to_transform(c.local_xform) for c in self.colliders], dtype=np.float32).reshape(count, 7),
            wp.transform)
        shapes.radius = arr(per_collider("radius"), float)
        shapes.half_height = arr(per_collider("half_height"), float)
        shapes.thickness = arr(per_collider("thickness"), float)
        shapes.friction = arr(per_collider("friction"), float)
        shapes.mesh = arr(mesh_ids, wp.uint64)
        shapes.bound_lo = arr(bound_lo, wp.vec3)
        shapes.bound_hi = arr(bound_hi, wp.vec3)
        shapes.far = arr(far, float)
        self.shapes = shapes
        self.collider_xform = arr(self._xform_host, wp.transform)
        self.collider_velocity = arr(self._velocity_host, wp.spatial_vector)
        self._no_previous = wp.zeros(1, dtype=wp.vec3, device=self.device)
        self.vert_exempt: wp.array | None = None
        """Per-vertex exemption bits (bit c: vertex inside collider c at rest, not yet seen clear), shape
        (G*(S+1),), int32; allocated by ``bind``."""
        self.contacts = None
        """The per-vertex body contacts of a step (``hairwarp.kernels.articulated.BodyContacts``); made by
        ``bind``. ``contacts.force`` holds the force each collider put on each vertex in the last step [N, world]."""
        self.start_clearance: wp.array | None = None
        """A lower bound of each vertex's distance to the colliders at the start of the step [m], written by
        :meth:`detect` and read by :meth:`project` (``detected``); allocated by ``bind``."""
        self.model = None
        if model is not None:
            self.bind(model)

    def __len__(self) -> int:
        return self.count

    def index(self, key) -> int:
        """Index of a collider given by index or name."""
        if isinstance(key, str):
            if key not in self._index:
                raise ColliderError(f"collider {key!r}: no such collider (have {sorted(self._index)})")
            return self._index[key]
        i = int(key)
        if not 0 <= i < self.count:
            raise ColliderError(f"collider index {key} out of range [0, {self.count})")
        return i

    def _set_world(self, i: int, matrix, linear_velocity, angular_velocity):
        self._world_host[i] = matrix
        self._xform_host[i] = matrix_to_transform(matrix)
        self._velocity_host[i, :3] = angular_velocity
        self._velocity_host[i, 3:] = linear_velocity
        if self.colliders[i].attach == "world":  # a head-attached one moves with the head, which the control tracks
            speed = float(np.linalg.norm(linear_velocity) + np.linalg.norm(angular_velocity) * self._size[i])
            if speed > self.peak_speed:
                self.peak_speed = speed

    def _pose_from_sample(self, i: int, col: Collider, sample):
        parent = np.asarray(sample.matrix(), dtype=float)
        world = parent @ col.local_xform
        w = np.asarray(sample.angular_velocity, dtype=float)
        v = np.asarray(sample.linear_velocity, dtype=float) + np.cross(w, world[:3, 3] - parent[:3, 3])
        self._set_world(i, world, v, w)

    def _pose_from_motion(self, i: int, col: Collider, t: float):
        self._pose_from_sample(i, col, col.motion.evaluate(t))

    def set_pose(self, key, matrix, linear_velocity=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 0.0)):
        """Set a world collider's world pose (rigid 4x4) and velocity [m/s, rad/s, world] for the next step.

        ``linear_velocity`` is that of the collider origin. Head-attached colliders follow
        ``Control.head_xform`` and cannot be posed here.
        """
        i = self.index(key)
        col = self.colliders[i]
        if col.attach == "head":
            raise ColliderError(f"collider {col.name!r} rides on the head; set Control.head_xform instead")
        from hairwarp.state import _vector

        pose = _rigid_matrix(matrix, f"collider {col.name!r}")
        try:  # every check before the first change: a refused pose changes nothing
            v, w = _vector("linear_velocity", linear_velocity), _vector("angular_velocity", angular_velocity)
        except ValueError as e:
            raise ColliderError(f"collider {col.name!r}: {e}") from None
        self._set_world(i, pose, v, w)
        self.collider_xform.assign(self._xform_host)
        self.collider_velocity.assign(self._velocity_host)

    def update(self, t: float, head_sample=None):
        """Pose every animated collider at time ``t`` [s]: world colliders from their ``motion``,
        head-attached ones from ``head_sample`` (a ``HeadMotion`` sample; the projection itself reads the
        head from ``Control``). Static world colliders keep their pose. Copies to the device in place."""
        for i, col in enumerate(self.colliders):
            if col.attach == "head":
                if head_sample is not None:
                    self._pose_from_sample(i, col, head_sample)
            elif col.motion is not None:
                self._pose_from_motion(i, col, t)
        if self.count:
            self.collider_xform.assign(self._xform_host)
            self.collider_velocity.assign(self._velocity_host)

    def world_matrices(self) -> np.ndarray:
        """World 4x4 poses of the colliders as last set on the host, shape (C, 4, 4)."""
        return self._world_host.copy()

    def signed_distance(self, points, head_xform=None):
        """Exact signed distances of world points to every collider (setup and diagnostics; allocates).

        Args:
            points: (N, 3) world points [m].
            head_xform: 4x4 head pose for head-attached colliders (identity if None).

        Returns:
            ``(distance (N, C), closest (N, C, 3), normal (N, C, 3))`` as numpy arrays: signed distance [m]
            (> 0 outside), closest surface point [m] and outward unit normal, world frame.
        """
        from hairwarp.kernels.body_collision import collider_distances

        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        n = len(pts)
        head = np.eye(4) if head_xform is None else _rigid_matrix(head_xform, "head_xform")
        d = wp.empty((n, self.count), dtype=float, device=self.device)
        cp = wp.empty((n, self.count), dtype=wp.vec3, device=self.device)
        nrm = wp.empty((n, self.count), dtype=wp.vec3, device=self.device)
        if n and self.count:
            wp.launch(collider_distances, dim=(n, self.count), device=self.device, inputs=[
                self.shapes, self.collider_xform, self.collider_velocity,
                wp.array(matrix_to_transform(head)[None].astype(np.float32), dtype=wp.transform, device=self.device),
                wp.zeros(1, dtype=wp.spatial_vector, device=self.device),
                wp.array(pts, dtype=wp.vec3, device=self.device),
            ], outputs=[d, cp, nrm])
        return d.numpy(), cp.numpy(), nrm.numpy()

    def bind(self, model):
        """Allocate the per-vertex state for ``model`` and mark rest vertices inside a collider as exempt.

        Roots are never exempt: the projection never moves them.

        The rest pose is ``model.rest_vertex_positions`` with the head at identity and world colliders at
        their current pose. Call once, before the first ``project`` (and before capturing a step).
        """
        self.mark_exempt(model, model.rest_vertex_positions)
        self.contacts = body_contacts(model.vert_count, self.device, enabled=self.count > 0)
        self.start_clearance = wp.zeros(model.vert_count if self.count > 0 else 1, dtype=float, device=self.device)
        # each vertex's last query of each collider (detect_body_contacts): its point and the distance found
        from hairwarp.kernels.body_collision import UNBOUNDED

        memo = max(model.vert_count * self.count, 1)
        self.memo_point = wp.zeros(memo, dtype=wp.vec3, device=self.device)
        self.memo_distance = wp.full(memo, -UNBOUNDED, dtype=float, device=self.device)
        self.model = model

    def mark_exempt(self, model, positions, head_xform=None) -> list[dict]:
        """Mark the vertices of ``positions`` that lie inside a collider as exempt from it (module docstring):
        ``bind`` does so at the rest pose with the head at the identity; a run whose hair starts elsewhere (the head
        posed at its first time, world colliders at theirs) marks its start state again before the first step, or a
        world collider would exempt vertices the start keeps clear of it and collide with those it starts through.

        Args:
            model: the bound model.
            positions: (G*(S+1), 3) world vertex positions [m], or a ``wp.array`` of them.
            head_xform: 4x4 head pose the positions are taken at (identity if None).

        Returns:
            Per collider with vertices inside: ``{"name", "vertices", "strands", "deepest"}`` (the deepest [m]).
        """
        if isinstance(positions, wp.array):
            positions = positions.numpy()
        pts = np.asarray(positions, dtype=float).reshape(model.strand_count, -1, 3)
        bits = np.zeros(pts.shape[:2], dtype=np.int32)
        found = []
        if self.count:
            distance = self.signed_distance(pts[:, 1:].reshape(-1, 3), head_xform)[0]
            for c in range(min(self.count, MAX_EXEMPT_COLLIDERS)):
                inside = (distance[:, c] < 0.0).reshape(model.strand_count, -1)
                bits[:, 1:] |= np.where(inside, np.int32(1 << c), np.int32(0))
                if inside.any():
                    found.append({"name": self.colliders[c].name, "vertices": int(inside.sum()),
                                  "strands": int(inside.any(axis=1).sum()),
                                  "deepest": float(-distance[:, c].min())})
        if self.vert_exempt is not None and self.vert_exempt.shape[0] == bits.size:
            self.vert_exempt.assign(bits.ravel())  # in place: a solver's launches hold the array
        else:
            self.vert_exempt = wp.array(bits.ravel(), dtype=wp.int32, device=self.device)
        return found

    @property
    def exempt_count(self) -> int:
        """Number of vertices still exempt from at least one collider (reads the device)."""
        return 0 if self.vert_exempt is None else int(np.count_nonzero(self.vert_exempt.numpy()))

    def detect(self, model, state, control, dt_array):
        """Find the body contact candidates of the step that starts from ``state`` (one launch).

        The step's integrator solves them (``Solver.step`` calls this before integrating).
        """
        from hairwarp.kernels.body_collision import detect_body_contacts

        if self.count == 0:
            return
        self._check_bound(model)
        c = self.contacts
        launch(self.executor, detect_body_contacts, model.strand_count, [
            model.seg_per_strand, model.seg_length, self.shapes, model.chains.gravity, self.collider_xform,
            self.collider_velocity, control.head_xform, control.head_velocity, dt_array,
            state.vertex_positions, state.vertex_velocities, self.vert_exempt, self.memo_point, self.memo_distance,
        ], [c.normal, c.object_velocity, c.gap, c.friction, self.start_clearance], device=self.device,
               min_chunk=STRAND_MIN_CHUNK)

    def reset_contacts(self):
        """Forget the contacts' friction history (after a teleport)."""
        if self.contacts is not None and self.count:
            self.contacts.slip.fill_(0.0)
            self.contacts.share.fill_(1.0)
            self.contacts.force.zero_()
            self.contacts.removed.zero_()
            self.contacts.away.fill_(1.0)
            self.contacts.normal.zero_()
            self.contacts.answer_force.zero_()

    def _check_bound(self, model):
        if self.model is not model:
            raise RuntimeError("ColliderSet: call bind(model) with this model first (at setup)")

    def project(self, model, state, control, dt_array, state_in=None, *, detected: bool = False):
        """Push the strands of ``state`` that ended the step inside a collider back out, in place (one launch; none
        without colliders): positions, and the joint velocities only to scale them down where the same ones at the
        moved configuration would raise the strand's kinetic energy (``kernels.body_collision.collide_strands``).

        Args:
            model: the model passed to ``bind``.
            state: ``joint_q``, ``joint_qd``, ``seg_xform``, ``vertex_positions``, ``vertex_velocities`` (current
                forward kinematics) and ``fault``; all rewritten in place.
            control: ``head_xform`` and ``head_velocity``.
            dt_array: one-element float32 device array, the step [s].
            state_in: the state the step started from; its ``vertex_positions`` give the swept test each
                vertex's path over the step. Without it the start is estimated from the velocities, which
                fails for vertices that turn through large angles in one step.
            detected: :meth:`detect` ran on ``state_in`` for this step (``Solver.step`` does): vertices whose
                path over the step stayed farther from every collider than the detection found skip their
                queries. Only with ``state_in``.
        """
        from hairwarp.kernels.body_collision import collide_strands

        if self.count == 0:
            return
        self._check_bound(model)
        inputs = [
            model.chains, int(self.swept), self.shapes, self.collider_xform, self.collider_velocity, control.head_xform,
            control.head_velocity, control.bases, dt_array,
            int(state_in is not None), self._no_previous if state_in is None else state_in.vertex_positions,
            int(detected), self.start_clearance, self.vert_exempt,
            state.joint_q, state.joint_qd, state.seg_xform, state.vertex_positions, state.vertex_velocities,
            state.fault,
        ]
        # one thread per strand, each writing its own strand; the fault bits are private per chunk
        launch(self.executor, collide_strands, model.strand_count, inputs, device=self.device,
               min_chunk=STRAND_MIN_CHUNK, private_or=[len(inputs) - 1])


#: ``h c`` of a body contact's damper per kilogram of its strand: a contact leaves a tenth of an approach or a
#: slip it stops in the step it starts (the warm-started force of the steps after leaves none at rest). Stiffer
#: dampers outgrow float32 in the articulated inertias they stiffen (a held vertex's damper against the tiny
#: inertia of a segment's roll about its own axis): two runs of ``long_hair`` whose gravity differs by 1e-5
#: parted at the free vertices between the root and a held one by 0.0002 mm/s at 10 (1e-5 of their speed, the
#: data's own change), by 0.7-1.1 mm/s at 100 (7 % of their speed) and by more than their speed at 1000, where
#: the impulses of two adjacent contacts also differed from a float64 solve by 20 %. That noise fed the
#: branching of hair on the head: at 10 the tips' difference to a 32-substep run (head collider alone) is 23-39 %
#: smaller at 2 to 16 substeps (docs/collision.md).
CONTACT_STIFFNESS = 10.0


def body_contacts(vert_count: int, device, *, enabled: bool = True):
    """A :class:`hairwarp.kernels.articulated.BodyContacts` of ``vert_count`` vertices (one element when not
    ``enabled``: the integrators skip body contacts)."""
    from hairwarp.kernels.articulated import BodyContacts

    n = vert_count if enabled else 1
    c = BodyContacts()
    c.enabled = int(enabled)
    c.stiffness = CONTACT_STIFFNESS
    c.normal = wp.zeros(n, dtype=wp.vec3, device=device)
    c.object_velocity = wp.zeros(n, dtype=wp.vec3, device=device)
    c.gap = wp.zeros(n, dtype=float, device=device)
    c.friction = wp.zeros(n, dtype=float, device=device)
    c.slip = wp.zeros(n, dtype=float, device=device)
    c.share = wp.full(n, 1.0, dtype=float, device=device)
    c.force = wp.zeros(n, dtype=wp.vec3, device=device)
    c.removed = wp.zeros(n, dtype=float, device=device)
    c.away = wp.full(n, 1.0, dtype=float, device=device)
    c.step_force = wp.zeros(n, dtype=wp.vec3, device=device)
    c.answer_force = wp.zeros(n, dtype=wp.vec3, device=device)
    c.answer_start = wp.zeros(n, dtype=wp.vec3, device=device)
    return c


def bench_collision(device=None, quick: bool = False, *, strands: int = 2000, segments: int = 31,
                    groom_path=None, body_path=None, repeats: int = 10) -> dict:
    """Time ``ColliderSet.project`` on a groom against a body mesh.

    By default a generated groom (``scalp_groom``) on a closed ellipsoid head mesh; with ``groom_path``
    and ``body_path`` (e.g. the TressFX Ratboy ``.tfx`` and ``.tfxmesh``) those files instead. Two
    states are timed: the rest pose, and the rest pose with every joint turned by up to 0.3 rad at random
    so that many vertices start inside.

    Args:
        device: Warp device; the default device when None.
        quick: fewer strands (a fifth) and repeats, for smoke runs.
        strands: generated guide strands.
        segments: segments per strand S.
        groom_path: a groom file for ``Groom.load``; needs ``body_path``.
        body_path: a mesh file for ``Collider.from_mesh_file``.
        repeats: timed repetitions per figure; the median is reported.

    Returns:
        ``{"device", "strands", "segments", "body_triangles", "exempt_vertices", "results": [{"state",
        "project_s", "vertices_moved", "max_depth_after_m"}, ...]}``, times in seconds per call (median
        after one warm-up call); the depth is over vertices that are not exempt and follow one outside.
    """
    import time

    from hairwarp.groom import Groom, scalp_groom
    from hairwarp.model import Model

    device = wp.get_device(device)
    if quick:
        strands, repeats = max(strands // 5, 1), 3
    if groom_path is not None and body_path is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            groom = Groom.load(groom_path, min_length=0.0)
        body = Collider.from_mesh_file(body_path)
    else:
        center, radii = (0.0, 0.0, 1.6), (0.085, 0.1, 0.11)
        groom = scalp_groom(strands, 0.3, points=segments + 1, scalp_center=center, scalp_radii=radii)
        body = Collider.ellipsoid(center, radii, subdivisions=5)
    model = Model.build(groom, segments=segments, device=device)
    colliders = ColliderSet([body], device, model=model)
    exempt = colliders.exempt_count
    control = model.control()
    dt = wp.array([1.0 / 600.0], dtype=float, device=device)
    rest = model.state()
    perturbed = model.state()
    rng = np.random.default_rng(0)
    q = rest.joint_q.numpy()
    angle = rng.uniform(-0.3, 0.3, (len(q), 3))
    half = 0.5 * np.linalg.norm(angle, axis=1, keepdims=True)
    dq = np.concatenate([np.sinc(half / np.pi) * 0.5 * angle, np.cos(half)], axis=1)
    x1, y1, z1, w1 = q.T
    x2, y2, z2, w2 = dq.T
    perturbed.joint_q.assign(np.stack([w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                                       w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2],
                                      axis=1).astype(np.float32))
    from hairwarp.solver import forward_kinematics

    forward_kinematics(model, perturbed, control)
    work = model.state()
    results = []
    for name, source in (("rest", rest), ("perturbed", perturbed)):
        samples = []
        for _ in range(repeats + 1):
            work.assign(source)
            colliders.bind(model)
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            colliders.project(model, work, control, dt)
            wp.synchronize_device(device)
            samples.append(time.perf_counter() - t0)
        before = source.vertex_positions.numpy()
        after = work.vertex_positions.numpy()
        depth = colliders.signed_distance(after)[0][:, 0].reshape(model.strand_count, -1)
        # Behind a vertex that is inside (exempt) the next one can rise by one segment length only.
        reachable = (colliders.vert_exempt.numpy().reshape(depth.shape) == 0)[:, 1:] & (depth[:, :-1] >= 0.0)
        results.append({"state": name, "project_s": float(np.median(samples[1:])),
                        "vertices_moved": int(np.count_nonzero(np.any(after != before, axis=1))),
                        "max_depth_after_m": float(max(0.0, -depth[:, 1:][reachable].min(initial=0.0)))})
    return {"device": str(device), "strands": model.strand_count, "segments": segments,
            "body_triangles": int(len(body.mesh.faces)), "exempt_vertices": exempt, "results": results}
