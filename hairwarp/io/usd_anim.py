"""Animation from USD: a Mesh prim's world poses over time (animated colliders), and the head's motion from an
xform prim or from a joint of a UsdSkel skeleton."""

from __future__ import annotations

import difflib

import numpy as np

from hairwarp.io.usd_common import UsdFileError, _open_stage, _prims, _stage_to_metres_z, _triangles
from hairwarp.model import MAX_COORDINATE

__all__ = ["head_motion_from_usd", "mesh_motion", "read_animated_collider", "read_animated_mesh",
           "read_prim_motion", "read_surface_track"]


# A world transform's scale, shear or mirror (the symmetric factor of its polar decomposition) is baked into the
# vertices when it stays within this (relative, float64 matrices of float32 or float64 authored ops) of its value
# at the first time sample; colliders move rigidly.
_CONSTANT_SCALE_RTOL = 1.0e-6


def _seconds(stage, codes) -> np.ndarray:
    """Time codes as seconds of the run: from the stage's start time code where it has one authored (a shot that
    starts at frame 1001 plays from the run's first frame), else from time code 0; ``timeCodesPerSecond`` codes a
    second. One time, 0, when there is no code."""
    if not len(codes):
        return np.zeros(1)
    origin = stage.GetStartTimeCode() if stage.HasAuthoredTimeCodeRange() else 0.0
    rate = stage.GetTimeCodesPerSecond() or 24.0
    if not (np.isfinite(rate) and rate > 0.0):
        raise UsdFileError(f"{stage.GetRootLayer().identifier}: timeCodesPerSecond = {rate!r}; it must be a finite "
                           f"number > 0")
    return (np.asarray(codes, dtype=np.float64) - origin) / rate


def _every_code(codes) -> list[float]:
    """``codes`` and every whole time code between the first and the last: a rigid motion read at each of the
    stage's frames follows USD's own interpolation of its transform ops (a rotateY keyed 0 then 270 degrees turns
    the long way round, a translate and a rotate keyed together move the prim along USD's path), which keyframes
    through the authored samples alone would not (they turn the short way, about another centre)."""
    if len(codes) < 2:
        return list(codes)
    first, last = float(codes[0]), float(codes[-1])
    whole = np.arange(np.ceil(first), np.floor(last) + 1.0)
    return sorted(set(map(float, codes)) | set(map(float, whole)))


def _find_mesh(stage, prim_path, path):
    from pxr import UsdGeom

    if prim_path is None:
        prim = next(_prims(stage, UsdGeom.Mesh), None)
        if prim is None:
            raise UsdFileError(f"{path}: no Mesh prim in the stage")
        return prim
    prim = stage.GetPrimAtPath(str(prim_path))
    if not prim or not prim.IsValid():
        raise UsdFileError(f"{path}: no prim at {prim_path}")
    if not prim.IsA(UsdGeom.Mesh):
        raise UsdFileError(f"{path}: {prim_path} is a {prim.GetTypeName() or 'typeless prim'}, not a Mesh")
    return prim


def _transform_times(prim) -> set[float]:
    """Time codes of the transform samples of a prim and of every ancestor (its world matrix depends on them)."""
    from pxr import UsdGeom

    times: set[float] = set()
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable:
            times.update(xformable.GetTimeSamples())
        prim = prim.GetParent()
    return times


def _rigid_factor(linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``linear = R K`` with R a rotation and K symmetric (the polar decomposition; a mirror goes into K)."""
    u, sv, vt = np.linalg.svd(linear)
    d = np.ones(3)
    if np.linalg.det(u @ vt) < 0.0:
        d[2] = -1.0
    rot = u @ np.diag(d) @ vt
    return rot, rot.T @ linear


def read_animated_mesh(path, prim_path=None):
    """A Mesh prim and its animation, in metres, Z up: for colliders that follow a USD animation.

    The world transform of the prim (its own transform ops and its ancestors') is read at every time code where
    any of them, or the prim's points, has a sample; ``metersPerUnit`` and ``upAxis`` are converted as by the
    other readers. A scale, shear or mirror that is the same at every sample is baked into the vertices (the
    winding is reversed with a mirror) so that the returned matrices are rigid; polygons are split into fans and
    a ``leftHanded`` orientation is turned into right-handed winding, so the faces point outward as authored.

    Args:
        path: a .usd, .usda, .usdc or .usdz file.
        prim_path: the Mesh prim; None takes the first Mesh in traversal order.

    Returns:
        ``(vertices, faces, times, matrices)``: vertices [m] in the mesh's own frame, float64 ``(V, 3)``, or
        ``(T, V, 3)`` when the points themselves are time-sampled (then one set per time); faces ``(F, 3)`` int64;
        times [s] ``(T,)`` (time codes from the stage's authored start, ``_seconds``; the frames between the
        samples too when only transforms are animated, ``_every_code``; a stage with no sample gives one time, 0,
        read at the default time); matrices ``(T, 4, 4)`` rigid world poses, column convention
        (``p_world = M @ [p, 1]``).
        ``vertices`` moved by ``matrices[i]`` is the mesh in the world at ``times[i]``.

    Raises:
        UsdFileError: missing or unreadable file, no Mesh prim (or ``prim_path`` is not one), a scale that changes
            with time, or a point count that changes with time.
    """
    return _read_animated_mesh(path, prim_path)[:4]


def read_surface_track(path, prim_path, *, interpolation: str = "smooth"):
    """A Mesh prim's points in the world over time, for roots bound to a deforming scalp (``groom.surface``).

    Args:
        path: the USD file.
        prim_path: the Mesh prim (skinned, blend-shaped or only moved: any animation of its points or transforms).
        interpolation: of the points between time samples, as ``head.motion.interpolation``.

    Returns:
        ``(track, faces)``: a :class:`hairwarp.surface.PointTrack` of the world points [m] (Z up) at the time
        samples of :func:`read_animated_mesh`, and the (F, 3) faces.

    Raises:
        UsdFileError: as :func:`read_animated_mesh`.
    """
    from hairwarp.surface import PointTrack

    vertices, faces, times, matrices, _ = _read_animated_mesh(path, prim_path)
    local = np.broadcast_to(vertices, (len(times),) + vertices.shape[-2:])
    world = np.einsum("tij,tvj->tvi", matrices[:, :3, :3], local) + matrices[:, None, :3, 3]
    return PointTrack(times, world, interpolation), faces


def _rigid_world_poses(prim, time_codes, codes, c4, where):
    """The prim's world matrices at ``time_codes`` as rigid poses in metres, Z up (column convention), and the
    constant scale/shear/mirror factored out of them (the same at every sample, else an error)."""
    from pxr import UsdGeom

    usd = [np.array(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim), dtype=np.float64) for tc in time_codes]
    return _rigid_poses(usd, codes, c4, where)


def _rigid_poses(usd_matrices, codes, c4, where):
    """Row-vector USD world matrices in stage units as rigid poses in metres, Z up (column convention), and the
    constant scale/shear/mirror factored out of them (the same at every sample, else an error)."""
    c4_inv = np.linalg.inv(c4)
    matrices = np.empty((len(usd_matrices), 4, 4))
    scale = None
    for i, m_usd in enumerate(usd_matrices):
        # Row-vector USD matrix in stage units -> column convention in metres, Z up, acting on metre Z-up points.
        world = c4 @ m_usd.T @ c4_inv
        at = f"at time code {codes[i]:g}" if i < len(codes) else "at its default time"
        if not np.isfinite(world).all():
            raise UsdFileError(f"{where}: its world transform {at} is not finite")
        if np.abs(world[:3, 3]).max() > MAX_COORDINATE:
            raise UsdFileError(f"{where}: its world transform {at} puts it at "
                               f"({', '.join(f'{x:.3g}' for x in world[:3, 3])}) m, beyond {MAX_COORDINATE:g} m of "
                               f"the origin, where float32 resolves no millimetre (the stage's units?)")
        rot, k = _rigid_factor(world[:3, :3])
        if scale is None:
            scale = k
        elif np.abs(k - scale).max() > _CONSTANT_SCALE_RTOL * max(np.abs(scale).max(), 1e-300):
            raise UsdFileError(f"{where}: its world scale changes with time (at time code {codes[i]:g}); "
                               "it moves rigidly, so only a constant scale can be taken out of it")
        matrices[i] = np.eye(4)
        matrices[i, :3, :3] = rot
        matrices[i, :3, 3] = world[:3, 3]
    return matrices, scale


def _keyed(key: str, message: str) -> UsdFileError:
    """A UsdFileError about the argument ``key`` (prim, joint): a scene's reader names its ``head.motion`` key."""
    exc = UsdFileError(message)
    exc.key = key
    return exc


def _names(items, most: int = 12) -> str:
    items = list(items)
    more = f", ... ({len(items)} in all)" if len(items) > most else ""
    return ", ".join(items[:most]) + more


def _find_joint(tokens: list[str], joint, where: str) -> int:
    """Index of ``joint`` in a skeleton's ``joints``: its path token, or its last name when no other joint has it."""
    if joint is None:
        raise _keyed("joint", f"{where} is a Skeleton: give the joint that carries the head, one of its joints "
                              f"({_names(tokens)})")
    joint = str(joint).strip("/")
    if joint in tokens:
        return tokens.index(joint)
    named = [i for i, t in enumerate(tokens) if t.rsplit("/", 1)[-1] == joint]
    if len(named) == 1:
        return named[0]
    if named:
        raise _keyed("joint", f"{where}: {len(named)} joints are named {joint!r}; give its path: "
                              f"{_names(tokens[i] for i in named)}")
    last = {t.rsplit("/", 1)[-1]: t for t in tokens}
    close = difflib.get_close_matches(joint, list(tokens) + list(last), n=6, cutoff=0.6)
    close = list(dict.fromkeys(last.get(c, c) for c in close))
    hint = f"close: {_names(close)}" if close else f"its joints: {_names(tokens)}"
    raise _keyed("joint", f"{where}: no joint {joint!r} in the skeleton ({hint})")


def _joint_poses(stage, prim, joint, c4, where):
    """Times [s] and rigid world poses (metres, Z up, column convention) of a skeleton's joint, the token used."""
    from pxr import Usd, UsdGeom, UsdSkel

    skel = UsdSkel.Skeleton(prim)
    tokens = [str(t) for t in (skel.GetJointsAttr().Get() or [])]
    if not tokens:
        raise _keyed("prim", f"{where} is a Skeleton with no joints")
    index = _find_joint(tokens, joint, where)
    where = f"{where} joint {tokens[index]}"
    query = UsdSkel.Cache().GetSkelQuery(skel)
    anim = query.GetAnimQuery() if query else None
    codes = set(_transform_times(prim))
    if anim:
        codes.update(anim.GetJointTransformTimeSamples())
    elif not codes:
        raise _keyed("prim", f"{where}: the skeleton has no bound animation (skel:animationSource) and no "
                             "transform samples, so the joint would stay still at its rest pose")
    codes = _every_code(sorted(codes))
    time_codes = [Usd.TimeCode(t) for t in codes] or [Usd.TimeCode.Default()]
    usd = []
    for tc in time_codes:
        skel_space = query.ComputeJointSkelTransforms(tc) if query else []
        if len(skel_space) != len(tokens):
            raise _keyed("prim", f"{where}: UsdSkel cannot compute the joints' transforms (are restTransforms "
                                 "authored, one per joint, where the animation leaves joints out?)")
        to_world = np.array(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim), dtype=np.float64)
        # Row vectors: a point in the joint's frame goes to skeleton space, then to the world.
        usd.append(np.array(skel_space[index], dtype=np.float64) @ to_world)
    matrices, _ = _rigid_poses(usd, codes, c4, where)
    return _seconds(stage, codes), matrices


def read_prim_motion(path, prim_path: str, joint: str | None = None):
    """The world motion of a transformable prim (a head xform) or of a joint of a UsdSkel skeleton prim.

    Without ``joint``, the prim's own world pose is read at every time code where the prim or an ancestor has a
    transform sample. With ``joint`` (``prim_path`` a ``Skeleton``), the pose is the joint's skeleton-space
    transform (UsdSkel, from the skeleton's bound ``SkelAnimation`` and its ``restTransforms``) times the
    skeleton prim's local-to-world, read at every time code of the animation's joint transforms and of the
    prim's (and its ancestors') transforms. One pose at the default time when there is no sample.

    Args:
        path: the USD file.
        prim_path: absolute path of the prim.
        joint: a joint of the skeleton: its path token as in the skeleton's ``joints`` (``Hips/Spine/Neck/Head``),
            or its last name (``Head``) when no other joint has that name.

    Returns:
        ``(times [s] (T,), matrices (T, 4, 4))``: rigid world poses in metres, Z up, column convention. A
        constant scale is left out; one that changes with time is an error.

    Raises:
        UsdFileError: missing or unreadable file, no such prim or not transformable, a changing scale; a
            skeleton without ``joint``, a joint it does not have, ``joint`` for a prim that is not a skeleton,
            a skeleton with neither an animation nor a transform sample. The message names the file and prim;
            ``exc.key`` is the argument at fault (``"prim"`` or ``"joint"``) where there is one.
    """
    from pxr import Usd, UsdGeom, UsdSkel

    stage = _open_stage(path)
    prim = stage.GetPrimAtPath(prim_path) if prim_path and str(prim_path).startswith("/") else None
    if prim is None or not prim.IsValid():
        raise _keyed("prim", f"{path}: no prim {prim_path!r} (give its absolute path, e.g. /Character/Head)")
    where = f"{path}: {prim_path}"
    kind = prim.GetTypeName() or "typeless prim"
    c4 = np.eye(4)
    c4[:3, :3] = _stage_to_metres_z(stage)
    if prim.IsA(UsdSkel.Skeleton):
        return _joint_poses(stage, prim, joint, c4, where)
    if joint is not None:
        skels = [str(p.GetPath()) for p in Usd.PrimRange(prim) if p.IsA(UsdSkel.Skeleton)]
        hint = f"; its skeletons: {_names(skels)}" if skels else ""
        raise _keyed("joint", f"{where} is a {kind}, not a Skeleton: a joint ({joint!r}) is read from a UsdSkel "
                              f"Skeleton prim{hint}")
    if not UsdGeom.Xformable(prim):
        raise _keyed("prim", f"{where} is a {kind}, not transformable")
    codes = _every_code(sorted(_transform_times(prim)))
    time_codes = [Usd.TimeCode(t) for t in codes] or [Usd.TimeCode.Default()]
    matrices, _ = _rigid_world_poses(prim, time_codes, codes, c4, where)
    return _seconds(stage, codes), matrices


def head_motion_from_usd(path, prim_path: str, *, joint: str | None = None, interpolation: str = "smooth"):
    """A head motion that follows a prim of a USD stage, or a joint of a skeleton prim, relative to its first
    sample (the poses of :func:`read_prim_motion`).

    The groom is built in the world at rest; the head frame there is the prim's pose at its first sample, so
    ``M_head(t) = M(t) M(t_0)^-1``: at ``t_0`` the head is at rest, and after it moves as the prim does. The
    samples become :class:`hairwarp.motion.Keyframes` (``interpolation`` as there; the pose holds before the
    first and after the last sample).
    """
    from hairwarp.colliders import matrix_to_transform
    from hairwarp.motion import Keyframes

    times, matrices = read_prim_motion(path, prim_path, joint)
    first_inv = np.linalg.inv(matrices[0])
    rel = np.array([m @ first_inv for m in matrices])
    xf = np.array([matrix_to_transform(x) for x in rel]).reshape(-1, 7)
    return Keyframes(times, xf[:, :3], xf[:, 3:], interpolation=interpolation)


def _read_animated_mesh(path, prim_path):
    """:func:`read_animated_mesh`, and the prim's name."""
    from pxr import Usd, UsdGeom

    stage = _open_stage(path)
    prim = _find_mesh(stage, prim_path, path)
    where = f"{path}: {prim.GetPath()}"
    mesh = UsdGeom.Mesh(prim)
    conv = _stage_to_metres_z(stage)
    c4 = np.eye(4)
    c4[:3, :3] = conv
    points_attr = mesh.GetPointsAttr()
    point_times = points_attr.GetTimeSamples()
    codes = sorted(_transform_times(prim) | set(point_times))
    if not point_times:  # a rigid motion: read at every frame, as the head's (``_every_code``)
        codes = _every_code(codes)
    time_codes = [Usd.TimeCode(t) for t in codes] or [Usd.TimeCode.Default()]
    times = _seconds(stage, codes)

    matrices, scale = _rigid_world_poses(prim, time_codes, codes, c4, where)

    first = time_codes[0]
    faces = _triangles(mesh, first)
    if (mesh.GetOrientationAttr().Get(first) == UsdGeom.Tokens.leftHanded) != (np.linalg.det(scale) < 0.0):
        faces = faces[:, ::-1].copy()

    def local_points(tc):
        pts = np.asarray(points_attr.Get(tc) or [], dtype=np.float64).reshape(-1, 3)
        # Metres Z up in the mesh frame, with the constant scale applied: (K C p) as rows.
        return pts @ (scale @ conv).T

    if point_times:
        frames = [local_points(tc) for tc in time_codes]
        counts = {len(f) for f in frames}
        if len(counts) != 1:
            raise UsdFileError(f"{where}: the number of points changes with time ({sorted(counts)})")
        vertices = np.stack(frames)
    else:
        vertices = local_points(first)
    if vertices.size == 0 or faces.size == 0:
        raise UsdFileError(f"{where}: the mesh has no points or no faces")
    if faces.min() < 0 or faces.max() >= vertices.shape[-2]:
        raise UsdFileError(f"{where}: face vertex indices out of range for {vertices.shape[-2]} points")
    return vertices, faces, times, matrices, prim.GetName()


def mesh_motion(times, matrices):
    """A rigid motion through sampled world poses, e.g. those of :func:`read_animated_mesh`.

    The poses become the keys of a :class:`hairwarp.motion.Keyframes` (about the world origin): translation by
    cubic Hermite with Catmull-Rom tangents, rotation by a cubic Hermite in the tangent space of SO(3), so
    position and velocity are continuous and ``evaluate(t)`` gives analytic world velocities and accelerations.
    The pose is held before the first and after the last sample, so the velocity is zero there. Usable as a
    world collider's ``motion`` (``Collider(..., attach="world", motion=mesh_motion(times, matrices))``) or as a
    head motion.

    Args:
        times: strictly increasing sample times [s], (T,).
        matrices: rigid world poses, (T, 4, 4), column convention; consecutive ones under 180 degrees apart.

    Returns:
        The :class:`hairwarp.motion.Keyframes`; its ``evaluate(t)`` returns a ``MotionSample`` with ``matrix()``,
        ``linear_velocity`` (of the frame origin), ``angular_velocity``, ``linear_acceleration`` and
        ``angular_acceleration``, world.
    """
    from hairwarp.colliders import matrix_to_transform
    from hairwarp.motion import Keyframes

    m = np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4)
    xf = np.array([matrix_to_transform(x) for x in m]).reshape(-1, 7)
    return Keyframes(np.asarray(times, dtype=np.float64).reshape(-1), xf[:, :3], xf[:, 3:])


def read_animated_collider(path, prim_path=None, *, name: str | None = None, **options):
    """A world collider that follows a Mesh prim's animation in a USD file (rigid; see :func:`read_animated_mesh`).

    Args:
        path: the USD file.
        prim_path: the Mesh prim; None takes the first one.
        name: collider name; the prim's name by default.
        **options: ``thickness``, ``friction`` of :class:`hairwarp.colliders.Collider`.

    Returns:
        A MESH :class:`hairwarp.colliders.Collider` with ``attach="world"`` and ``motion`` from :func:`mesh_motion`
        (static when the stage has a single sample).

    Raises:
        UsdFileError: as :func:`read_animated_mesh`, and for time-sampled points (a deforming mesh cannot be a
            rigid collider).
    """
    import trimesh

    from hairwarp.colliders import Collider

    vertices, faces, times, matrices, prim_name = _read_animated_mesh(path, prim_path)
    if vertices.ndim == 3:
        raise UsdFileError(f"{path}: mesh {prim_name!r} deforms (time-sampled points); a collider must be rigid")
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    motion = mesh_motion(times, matrices) if len(times) > 1 else None
    local = np.eye(4) if motion is not None else matrices[0]
    return Collider.from_trimesh(mesh, local_xform=local, name=name or prim_name, attach="world", motion=motion,
                                 **options)
