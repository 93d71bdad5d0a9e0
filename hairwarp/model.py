"""The static description of a set of guide strands: ``StrandParams`` and ``Model``."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields

import numpy as np
import warp as wp

from hairwarp.motion import quat_to_matrix, right_jacobian_inv, skew
from hairwarp.state import Control, State


class ModelError(ValueError):
    """Invalid strand parameters or groom geometry; the message names the parameter or strand."""


def resolve_device(device=None, key: str = "device"):
    """The Warp device ``device`` names (the default device when None), or a ValueError in one line naming ``key``:
    Warp's own error for a CUDA device on a machine without one prints driver messages first."""
    if device is None or isinstance(device, wp.Device):
        return wp.get_device(device)
    name = str(device)
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"{key} = {name!r}: Warp finds no CUDA device on this machine; use \"cpu\"")
    try:
        return wp.get_device(name)
    except (ValueError, RuntimeError) as exc:
        raise ValueError(f"{key} = {name!r}: {exc}") from None


def _gravity(value) -> tuple[float, float, float]:
    """``value`` as 3 finite floats [m/s^2], or a ModelError naming gravity."""
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ModelError(f"gravity must be 3 finite numbers [m/s^2], got {value!r}")
    return tuple(float(g) for g in v)


@dataclass(frozen=True)
class StrandParams:
    """Physical parameters of the guide strands (each guide stands for a wisp of hair).

    Stiffness and damping are those of a continuous rod, so the look of a strand does not
    change with the number of segments it is cut into: joint k gets ``K = EI / l_k`` and
    ``C = damping / l_k``, with ``l_k`` the mean length of the two segments it joins (half the
    first segment's length at the clamped root, so static shapes converge at second order in S).

    Attributes:
        density: mass density of the segments [kg/m^3]; each segment is a thin solid cylinder.
        radius: cylinder radius [m].
        bend_stiffness: bending rigidity EI [N m^2].
        twist_stiffness: torsional rigidity GJ [N m^2]; ``None`` takes ``bend_stiffness / 1.3``
            (an isotropic rod with Poisson ratio 0.3).
        damping: internal (bending and twisting) damping of the rod [N m^2 s].
        root_stiffness_scale: factor on the root joint's stiffness and damping; a stiffer root
            holds the hairstyle's parting and volume.
        drag: linear air drag per unit length [N s/m^2]; 0 switches the drag and wind stage off.
    """

    density: float = 1300.0
    radius: float = 2.0e-3
    bend_stiffness: float = 2.0e-4
    twist_stiffness: float | None = None
    damping: float = 2.0e-7
    root_stiffness_scale: float = 1.0
    drag: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ModelError(f"StrandParams.{f.name} must be a finite number, got {value!r}")
            if value < 0.0:
                raise ModelError(f"StrandParams.{f.name} must be >= 0, got {value!r}")
        if self.density <= 0.0 or self.radius <= 0.0:
            raise ModelError("StrandParams.density and StrandParams.radius must be > 0")

    @property
    def twist(self) -> float:
        return self.bend_stiffness / 1.3 if self.twist_stiffness is None else self.twist_stiffness


class Model:
    """Guide strands as articulated chains: geometry, mass, stiffness and rest shape.

    Built once with :meth:`build`, then read-only during a step. Per-segment arrays have
    ``seg_count = strand_count * seg_per_strand`` entries, index ``g * S + k`` (k = 0 at the root).

    Attributes:
        device: the Warp device every array lives on.
        strand_count: number of guide strands G.
        seg_per_strand: segments per strand S.
        seg_count, vert_count: G*S and G*(S+1).
        seg_length: segment length [m], float32 (G*S,).
        seg_mass: segment mass [kg], float32 (G*S,).
        seg_inertia: principal moments about the centre of mass [kg m^2], vec3 (G*S,), body axes.
        strand_root_pos: root point in the head frame [m], vec3 (G,).
        joint_rest_q: rest rotation of each joint (parent from child), quat (G*S,).
        joint_stiffness: (bend, bend, twist) [N m/rad], vec3 (G*S,), child frame.
        joint_damping: (bend, bend, twist) [N m s/rad], vec3 (G*S,), child frame.
        joint_q0: initial joint rotations, quat (G*S,) (the groom's own shape); with ``hold_shape`` the
            equilibrium of the joints at ``joint_rest_q`` under gravity.
        hold_unstable: with ``hold_shape``, numpy bool (G,): the strands whose held shape is an unstable rest on
            their own springs (they buckle under their weight; :func:`unstable_strands`), which links to stiffer
            neighbours or a body under them may still hold; None without ``hold_shape``.
        gravity: [m/s^2], world.
        drag: air drag per unit length [N s/m^2] (0: off).
        rest_vertex_positions: numpy (G, S+1, 3) float64, world pose at build time (head at identity).
        root_uv: numpy (G, 2) scalp coordinates of the roots, or None.
        root_normal: numpy (G, 3) scalp normals at the roots, or None.
        grid_shape: (rows, cols) of a generator's root grid, or None.
        params: the :class:`StrandParams` it was built with.
    """

    def __init__(self):
        raise TypeError("use Model.build(groom, params, segments=...)")

    @classmethod
    def build(
        cls,
        groom,
        params: StrandParams | None = None,
        *,
        segments: int = 20,
        device=None,
        gravity=(0.0, 0.0, -9.81),
        rest_vertices=None,
        hold_shape: bool = False,
        hold_rotation=None,
    ) -> Model:
        """Build a model from a groom, resampled to ``segments`` equal segments per strand.

        Args:
            groom: a :class:`hairwarp.Groom`, or an array (G, segments+1, 3) of vertices already
                resampled (root first, metres, Z up).
            params: strand parameters; defaults to ``StrandParams()``.
            segments: simulation segments per strand S.
            device: Warp device ("cpu", "cuda:0"); the default device when None.
            gravity: gravitational acceleration [m/s^2], world.
            rest_vertices: optional (G, segments+1, 3) rest shape when it differs from the
                initial shape given by ``groom``.
            hold_shape: make the groom's shape the strands' equilibrium under ``gravity``: each joint's rest
                bend is offset by the bend that takes the weight of the strand beyond it
                (:func:`gravity_rest_bends`), so the hair starts at rest as drawn instead of sagging from it.
                Not with ``rest_vertices``.
            hold_rotation: with ``hold_shape``, the rotation from the groom's frame to the world at which the
                shape is held: the head's first pose (a quaternion (x, y, z, w) or a 3 x 3 matrix), or each
                strand's root frame's (G, 4) or (G, 3, 3); default the identity (the head at its build pose).
        """
        params = params or StrandParams()
        if isinstance(segments, bool) or not isinstance(segments, int | np.integer) or segments < 1:
            raise ModelError(f"segments must be a whole number >= 1, got {segments!r}")
        S = int(segments)
        gravity = _gravity(gravity)
        device = resolve_device(device)
        verts = _vertices_of(groom, S)
        rest = verts if rest_vertices is None else _vertices_of(rest_vertices, S)
        if rest.shape != verts.shape:
            raise ModelError(f"rest_vertices has shape {rest.shape}, the groom {verts.shape}")
        if hold_shape and rest_vertices is not None:
            raise ModelError("hold_shape makes the groom's shape the rest under gravity: give it or rest_vertices")

        self = object.__new__(cls)
        self.device = device
        G = verts.shape[0]
        self.strand_count = G
        self.seg_per_strand = S
        self.seg_count = G * S
        self.vert_count = G * (S + 1)
        self.params = params
        self._gravity = wp.vec3(*gravity)
        self.drag = float(params.drag)
        self.rest_vertex_positions = rest
        self.hold_unstable = None
        self.root_uv = getattr(groom, "root_uv", None)
        self.root_normal = getattr(groom, "root_normal", None)
        self.grid_shape = getattr(groom, "grid_shape", None)

        lengths = np.linalg.norm(np.diff(verts, axis=1), axis=2)  # (G, S)
        short = np.flatnonzero(lengths.min(axis=1) <= 0.0)
        if short.size:
            raise ModelError(f"strand {short[0]} has a zero-length segment after resampling to {S} segments")
        r = params.radius
        mass = params.density * math.pi * r * r * lengths
        i_perp = mass * (3.0 * r * r + lengths**2) / 12.0
        i_axial = 0.5 * mass * r * r
        inertia = np.stack([i_perp, i_perp, i_axial], axis=-1)

        # joint k joins segments k-1 and k: discrete rod stiffness EI / (mean length); the root joint
        # bends the half segment next to the clamp, EI / (L0 / 2), which makes static shapes converge at
        # second order in S (first order with EI / L0; measured by `hairwarp bench accuracy`)
        l_joint = 0.5 * lengths
        l_joint[:, 1:] = 0.5 * (lengths[:, 1:] + lengths[:, :-1])
        scale = np.ones((G, S))
        scale[:, 0] = params.root_stiffness_scale
        bend = params.bend_stiffness / l_joint * scale
        twist = params.twist / l_joint * scale
        stiffness = np.stack([bend, bend, twist], axis=-1)
        damp = params.damping / l_joint * scale
        damping = np.stack([damp, damp, damp], axis=-1)

        q0 = rest_joint_rotations(verts)
        if hold_shape:
            held_gravity = _gravity_in_groom(gravity, hold_rotation, G)
            bends, limp = gravity_rest_bends(verts, mass, stiffness, held_gravity)
            self.hold_unstable = unstable_strands(verts, mass, stiffness, bends, held_gravity) & ~limp
            if limp.any():
                warnings.warn(f"hold_shape: {int(limp.sum())} of {G} strands are too limp to hold the groom's shape "
                              f"under gravity (first: strand {int(np.flatnonzero(limp)[0])}; a rest bend of more "
                              f"than {math.degrees(MAX_REST_BEND):.0f} deg, or one about an axis without stiffness, "
                              f"would be needed); they sag from it (raise the bend or twist stiffness)", stacklevel=2)
            rest_q = rest_joint_rotations(verts, bends)
        else:
            rest_q = q0 if rest_vertices is None else rest_joint_rotations(rest)

        def arr(a, dtype):
            return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=self.device)

        self.seg_length = arr(lengths.reshape(-1), float)
        self.seg_mass = arr(mass.reshape(-1), float)
        self.seg_inertia = arr(inertia.reshape(-1, 3), wp.vec3)
        self.strand_root_pos = arr(verts[:, 0], wp.vec3)
        self.joint_rest_q = arr(rest_q.reshape(-1, 4), wp.quat)
        self.joint_q0 = arr(q0.reshape(-1, 4), wp.quat)
        self.joint_stiffness = arr(stiffness.reshape(-1, 3), wp.vec3)
        self.joint_damping = arr(damping.reshape(-1, 3), wp.vec3)

        from hairwarp.kernels.articulated import StrandChains

        chains = StrandChains()
        chains.seg_per_strand = S
        chains.seg_length = self.seg_length
        chains.seg_mass = self.seg_mass
        chains.seg_inertia = self.seg_inertia
        chains.strand_root_pos = self.strand_root_pos
        chains.joint_rest_q = self.joint_rest_q
        chains.joint_stiffness = self.joint_stiffness
        chains.joint_damping = self.joint_damping
        chains.gravity = self._gravity
        self.chains = chains
        """The chain arrays bundled for the ABA kernels (the same arrays, not copies)."""
        return self

    @property
    def gravity(self) -> wp.vec3:
        """Gravitational acceleration [m/s^2], world."""
        return self._gravity

    @gravity.setter
    def gravity(self, value):
        self._gravity = wp.vec3(*_gravity(value))
        self.chains.gravity = self._gravity

    def state(self) -> State:
        """A new state in the initial configuration (the groom's shape), at rest, with its world quantities."""
        state = State(self)
        state.joint_q.assign(self.joint_q0)
        from hairwarp.solver import forward_kinematics

        forward_kinematics(self, state, self.control())
        return state

    def control(self, *, root_frames: bool = False) -> Control:
        """New animated inputs: head at its build pose, at rest, no wind; ``root_frames``: a root frame per strand
        (see :class:`hairwarp.Control`)."""
        return Control(self, root_frames=root_frames)


def _vertices_of(groom, segments: int) -> np.ndarray:
    if isinstance(groom, np.ndarray) or isinstance(groom, (list, tuple)):
        verts = np.asarray(groom, dtype=np.float64)
        if verts.ndim != 3 or verts.shape[1] != segments + 1 or verts.shape[2] != 3:
            raise ModelError(
                f"vertex array must have shape (G, {segments + 1}, 3) for {segments} segments, got {verts.shape}"
            )
        _check_extent(list(verts), "groom")
    else:
        _check_extent(groom.strands, getattr(groom, "source", "groom"))
        verts = np.asarray(groom.resample(segments), dtype=np.float64)
    if verts.shape[0] == 0:
        raise ModelError("the groom has no strands")
    bad = np.flatnonzero(~np.isfinite(verts).all(axis=(1, 2)))
    if bad.size:
        raise ModelError(f"strand {bad[0]} has non-finite vertices")
    return verts


#: Farthest a guide vertex may lie from the origin [m]: float32 resolves no millimetre beyond it (its spacing there
#: is 1 mm), and grooms read in the wrong units or scaled twice land there (a file at 1e18 passed every check and
#: faulted at frame 1 with advice to raise the substeps).
MAX_COORDINATE = 8000.0


def _check_extent(strands, source: str) -> None:
    for i, s in enumerate(strands):
        a = np.abs(np.asarray(s, dtype=np.float64))
        if a.size and np.nanmax(a) > MAX_COORDINATE:
            j = int(np.nanargmax(a.max(axis=-1)))
            raise ModelError(f"{source}: strand {i} vertex {j} lies at {_fmt_point(s[j])} m, beyond "
                             f"{MAX_COORDINATE:g} m of the origin, where float32 resolves no millimetre: check the "
                             f"file's units (groom.scale)")


def _fmt_point(p) -> str:
    return "(" + ", ".join(f"{float(x):.3g}" for x in p) + ")"


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation matrices taking unit vectors a to b, (N, 3) -> (N, 3, 3) (Rodrigues)."""
    c = np.cross(a, b)
    d = np.einsum("ni,ni->n", a, b)
    s = np.linalg.norm(c, axis=1)
    axis = np.zeros_like(a)
    ok = s > 1e-12
    axis[ok] = c[ok] / s[ok, None]
    flip = (~ok) & (d < 0.0)
    if flip.any():  # opposite vectors: turn by pi about any perpendicular axis
        p = np.cross(a[flip], [1.0, 0.0, 0.0])
        weak = np.linalg.norm(p, axis=1) < 1e-6
        p[weak] = np.cross(a[flip][weak], [0.0, 1.0, 0.0])
        axis[flip] = p / np.linalg.norm(p, axis=1, keepdims=True)
    angle = np.arctan2(s, d)
    K = skew(axis)
    eye = np.broadcast_to(np.eye(3), K.shape)
    sa, ca = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return eye + sa * K + (1.0 - ca) * (K @ K)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to unit quaternions (..., 4) in (x, y, z, w), w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    q = np.empty((len(flat), 4))
    tr = np.trace(flat, axis1=1, axis2=2)
    for n, (m, t) in enumerate(zip(flat, tr)):
        if t > 0.0:
            s = 2.0 * math.sqrt(t + 1.0)
            q[n] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        else:
            j = int(np.argmax(np.diag(m)))
            a, b = (j + 1) % 3, (j + 2) % 3
            s = 2.0 * math.sqrt(max(1.0 + m[j, j] - m[a, a] - m[b, b], 1e-300))
            v = np.empty(4)
            v[j] = 0.25 * s
            v[a] = (m[a, j] + m[j, a]) / s
            v[b] = (m[b, j] + m[j, b]) / s
            v[3] = (m[b, a] - m[a, b]) / s
            q[n] = v
    q *= np.where(q[:, 3:4] < 0.0, -1.0, 1.0)
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).reshape(R.shape[:-2] + (4,))


def segment_rotations(vertices: np.ndarray) -> np.ndarray:
    """World rotations (G, S, 3, 3) of the segments of a polyline set, with no twist.

    Segment k's body -z points along its direction; the first segment takes the minimal
    rotation from world -z, each next one the minimal rotation from its parent (parallel
    transport), so the frames carry no twist.
    """
    d = np.diff(vertices, axis=1)
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    G, S, _ = d.shape
    R = np.empty((G, S, 3, 3))
    R[:, 0] = _rotation_between(np.broadcast_to([0.0, 0.0, -1.0], (G, 3)).copy(), d[:, 0])
    for k in range(1, S):
        R[:, k] = _rotation_between(d[:, k - 1], d[:, k]) @ R[:, k - 1]
    return R


def rest_joint_rotations(vertices: np.ndarray, bends: np.ndarray | None = None) -> np.ndarray:
    """Joint rotations (G, S, 4) (x, y, z, w) that reproduce the vertices with the head at identity; with ``bends``
    (G, S, 3), rotation vectors in each joint's child frame [rad], the rotations ``q`` with ``log(q^-1 q_v) =
    bends``, ``q_v`` the vertices' own (the rest that the joint springs, ``-K log(q_rest^-1 q)``, hold the vertices
    away from by ``K bends``)."""
    R = segment_rotations(vertices)
    parent = np.empty_like(R)
    parent[:, 0] = np.eye(3)
    parent[:, 1:] = R[:, :-1]
    relative = np.swapaxes(parent, -1, -2) @ R
    if bends is not None:
        relative = relative @ rotation_matrices(-np.asarray(bends, dtype=np.float64))
    return matrix_to_quat(relative)


def rotation_matrices(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (axis times angle [rad]; Rodrigues)."""
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0 - angle**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - angle**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * K + b * (K @ K)


def _gravity_in_groom(gravity, rotation, strands: int) -> np.ndarray:
    """``gravity`` (world) in the groom's frame held at ``rotation`` (see ``Model.build``'s ``hold_rotation``):
    (3,) for one rotation, (G, 3) for one per strand."""
    g = np.asarray(gravity, dtype=np.float64)
    if rotation is None:
        return g
    R = np.asarray(rotation, dtype=np.float64)
    if R.shape in ((4,), (strands, 4)) and np.isfinite(R).all():
        R = quat_to_matrix(R / np.linalg.norm(R, axis=-1, keepdims=True))
    if R.shape not in ((3, 3), (strands, 3, 3)) or not np.isfinite(R).all():
        raise ModelError(f"hold_rotation must be a quaternion (x, y, z, w) or a 3 x 3 rotation, one or one per "
                         f"strand ({strands}), got shape {np.shape(rotation)}")
    return np.einsum("...ji,j->...i", R, g)


#: Largest rest bend [rad] that ``gravity_rest_bends`` gives a joint: a strand that would need more is too limp to
#: hold its shape (the springs' law, ``-K log(q_rest^-1 q)``, turns back at pi), and its joints keep the bound.
MAX_REST_BEND = 0.5 * math.pi


def gravity_rest_bends(vertices: np.ndarray, mass: np.ndarray, stiffness: np.ndarray, gravity) -> tuple:
    """The joints' rest bends that make the polylines ``vertices`` (G, S+1, 3) the strands' static equilibrium
    under ``gravity`` [m/s^2] in their frame, (3,) or one per strand (G, 3) (inverse statics; Derouet-Jourdan et
    al. 2010, *Stable inverse dynamic curves*).

    At rest every joint's spring takes the weight of the strand beyond it: joint i (at vertex i) carries the torque
    ``tau_i = sum_{j >= i} (c_j - x_i) x m_j g`` of the segments' weights (``c_j`` their centres, ``mass`` (G, S)
    [kg]), which in the joint's child frame the spring balances with ``K theta_i = R_i^T tau_i`` (``stiffness``
    (G, S, 3) [N m/rad] per axis). O(S) per strand by suffix sums of ``m_j`` and ``m_j c_j``.

    Returns:
        ``(bends, limp)``: ``theta`` (G, S, 3) [rad] for :func:`rest_joint_rotations`, each joint's at most
        :data:`MAX_REST_BEND` (scaled down to it, and none about an axis without stiffness); ``limp`` (G,) bool,
        the strands one of whose joints needed more.
    """
    x = np.asarray(vertices, dtype=np.float64)
    K = np.asarray(stiffness, dtype=np.float64)
    g = np.asarray(gravity, dtype=np.float64)
    torque = np.cross(_outboard_moments(x, mass), g[:, None, :] if g.ndim == 2 else g)
    local = np.einsum("gsji,gsj->gsi", segment_rotations(x), torque)
    stiff = K > 0.0
    bends = np.where(stiff, local / np.where(stiff, K, 1.0), 0.0)
    scale = 1e-9 * np.abs(torque).max(initial=0.0)  # torques below this are round-off
    unheld = (~stiff & (np.abs(local) > scale)).any(axis=2)
    angle = np.linalg.norm(bends, axis=2)
    over = angle > MAX_REST_BEND
    bends[over] *= (MAX_REST_BEND / angle[over])[:, None]
    return bends, (over | unheld).any(axis=1)


def _outboard_moments(x: np.ndarray, mass) -> np.ndarray:
    """``d_i = sum_{j >= i} m_j (c_j - x_i)`` (G, S, 3) [kg m]: the first moment of the strand beyond joint i about
    it, whose weight's torque there is ``d_i x g``."""
    m = np.asarray(mass, dtype=np.float64)
    centres = 0.5 * (x[:, :-1] + x[:, 1:])
    outboard_mass = np.cumsum(m[:, ::-1], axis=1)[:, ::-1]
    outboard_moment = np.cumsum((m[..., None] * centres)[:, ::-1], axis=1)[:, ::-1]
    return outboard_moment - outboard_mass[..., None] * x[:, :-1]


def gravity_stiffness(vertices: np.ndarray, mass, gravity) -> np.ndarray:
    """How the weight's generalised force on each joint changes as each joint turns: ``dtau_i / ddelta_k``
    (G, 3S, 3S) [N m/rad], ``delta_k`` a turn of joint k about its child frame's axes (as its velocity is given)
    and ``tau_i`` in joint i's child frame, at the polylines ``vertices`` (G, S+1, 3) under ``gravity`` (3,) or (G, 3).

    Turning joint k by ``w`` (world) turns everything beyond it about its joint: for ``k <= i`` joint i's frame and
    moment ``d_i`` turn with it and the torque changes by ``[d_i] [g] w``; for ``k > i`` only the part beyond k moves,
    ``d_i`` by ``w x d_k``, and the torque by ``[g] [d_k] w`` (``d`` of :func:`_outboard_moments`)."""
    x = np.asarray(vertices, dtype=np.float64)
    G, S = x.shape[0], x.shape[1] - 1
    g = np.broadcast_to(np.asarray(gravity, dtype=np.float64), (G, 3))
    d = _outboard_moments(x, mass)
    R = segment_rotations(x)
    dg = skew(d) @ skew(g)[:, None]  # row i, columns k <= i
    gd = skew(g)[:, None] @ skew(d)  # column k, rows i < k
    blocks = np.where((np.arange(S)[:, None] >= np.arange(S)[None, :])[None, :, :, None, None],
                      dg[:, :, None], gd[:, None, :])
    blocks = np.swapaxes(R, -1, -2)[:, :, None] @ blocks @ R[:, None, :]
    return blocks.transpose(0, 1, 3, 2, 4).reshape(G, 3 * S, 3 * S)


def unstable_strands(vertices: np.ndarray, mass, stiffness, bends, gravity, chunk: int = 128) -> np.ndarray:
    """Whether each strand held at ``vertices`` (G, S+1, 3) by joint springs ``stiffness`` (G, S, 3) bent ``bends``
    (G, S, 3) from their rest (:func:`gravity_rest_bends`) would fall from there: (G,) bool.

    The drawn shape of a held groom is an equilibrium, but a standing strand too soft for its weight buckles from it
    (a heavy column taller than Greenhill's height, ``(7.84 EI / (rho A g))^(1/3)``, as a flagpole does). Its
    stiffness against small turns of its joints is the springs' ``K J_r^-1(theta)`` (``J_r`` the rotation log's
    Jacobian) less what the weight gives (:func:`gravity_stiffness`); the rest is stable where the symmetric part is
    positive definite (Derouet-Jourdan et al. 2010 check the same of their inverse statics). O(S^3) per strand, in
    chunks of ``chunk`` strands."""
    x = np.asarray(vertices, dtype=np.float64)
    G, S = x.shape[0], x.shape[1] - 1
    g = np.broadcast_to(np.asarray(gravity, dtype=np.float64), (G, 3))
    K = np.asarray(stiffness, dtype=np.float64)
    springs = K[..., :, None] * right_jacobian_inv(bends)  # (G, S, 3, 3)
    out = np.zeros(G, dtype=bool)
    for first in range(0, G, chunk):
        part = slice(first, min(first + chunk, G))
        H = -gravity_stiffness(x[part], np.asarray(mass)[part], g[part])
        n = H.shape[0]
        H = H.reshape(n, S, 3, S, 3)
        H[:, np.arange(S), :, np.arange(S), :] += np.swapaxes(springs[part], 0, 1)
        H = H.reshape(n, 3 * S, 3 * S)
        H = 0.5 * (H + np.swapaxes(H, -1, -2))
        scale = np.abs(H).max(axis=(1, 2))
        out[part] = np.linalg.eigvalsh(H)[:, 0] < -1e-9 * scale
    return out
