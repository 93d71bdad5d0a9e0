"""Roots bound to a deforming surface: each guide root on a triangle of an animated scalp mesh.

A skinned or blend-shaped scalp stretches and slides under the hair; a rigid head frame cannot carry the roots
then. :class:`ScalpBinding` puts each root on the closest triangle of the mesh at rest (barycentric
coordinates, the root moved onto the surface) and gives each strand, at any time, the rigid frame of its
triangle: origin at the root's barycentric point, axes from the triangle's first edge and its normal. A strand's
*root frame* is the map from the groom's head frame to the world that carries the rest triangle onto the moved
one, ``P(t) = F(t) F(0)^-1 H(0)`` (``F`` the triangle's frame, ``H(0)`` the head pose at rest), with its world
velocity and acceleration: the step then roots every strand on its own frame (``Control.set_root_frames``) as it
roots all of them on the head otherwise. The mesh's points are interpolated in time as keyframes are
(:func:`hairwarp.motion.hermite_tangents`), so the frames' velocities and accelerations are those of the
interpolated motion.
"""

from __future__ import annotations

import numpy as np

from hairwarp.motion import (
    KEY_INTERPOLATIONS,
    cross_rows,
    hermite_basis,
    hermite_interval,
    hermite_tangents,
    quat_to_matrix,
)

#: Time step of the central differences that give a root frame's angular acceleration [s]; the frames' rotations
#: are cubic within a key interval, so the difference is exact there to O(eps^2) ~ 1e-8 relative.
_ALPHA_EPS = 1.0e-4


class SurfaceError(ValueError):
    """A groom cannot be bound to the surface (the message names the strand and the distance)."""


class PointTrack:
    """Points sampled at key times, interpolated by cubic Hermite curves; held before the first and after the
    last key (zero velocity there).

    Args:
        times: (T,) strictly increasing [s].
        points: (T, N, 3) [m].
        interpolation: as :class:`hairwarp.motion.Keyframes`.
    """

    def __init__(self, times, points, interpolation: str = "smooth"):
        if interpolation not in KEY_INTERPOLATIONS:
            raise ValueError(f"unknown interpolation {interpolation!r}; choose one of {', '.join(KEY_INTERPOLATIONS)}")
        self.times = np.asarray(times, dtype=np.float64).reshape(-1)
        self.points = np.asarray(points, dtype=np.float64)
        if self.points.shape[0] != self.times.size:
            raise ValueError(f"{self.times.size} times for {self.points.shape[0]} point samples")
        if np.any(np.diff(self.times) <= 0.0):
            raise ValueError("point sample times must increase strictly")
        self.interpolation = interpolation
        if self.times.size > 1:
            self._tan0, self._tan1 = hermite_tangents(self.times, self.points, interpolation)

    def subset(self, indices) -> PointTrack:
        """The track of the points at ``indices`` (the same curves: tangents are per point)."""
        out = PointTrack.__new__(PointTrack)
        out.times, out.interpolation = self.times, self.interpolation
        out.points = self.points[:, indices]
        if self.times.size > 1:
            out._tan0, out._tan1 = self._tan0[:, indices], self._tan1[:, indices]
        return out

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions [m], velocities [m/s] and accelerations [m/s^2] at ``t``, (N, 3) each."""
        tk, d = self.times, self.points
        if t <= tk[0] or t >= tk[-1]:
            p = d[0] if t <= tk[0] else d[-1]
            return p.copy(), np.zeros_like(p), np.zeros_like(p)
        i = int(np.searchsorted(tk, t, side="right")) - 1
        h = tk[i + 1] - tk[i]
        return hermite_interval(d, self._tan0, self._tan1, i, (t - tk[i]) / h, h)

    def evaluate_many(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`evaluate` at each of ``times``, (T, N, 3) each: one pass of array operations, each time the same
        bits as alone (the same products and sums, element by element)."""
        tk, d = self.times, self.points
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        inside = (t > tk[0]) & (t < tk[-1])
        # outside the keys: held at the first or the last, at rest
        p = np.where((t <= tk[0])[:, None, None], d[0], d[-1]).astype(np.float64)
        v, a = np.zeros_like(p), np.zeros_like(p)
        if inside.any():
            ti = t[inside]
            i = np.searchsorted(tk, ti, side="right") - 1
            h = tk[i + 1] - tk[i]
            (h00, h10, h01, h11), (d00, d10, d01, d11), (e00, e10, e01, e11) = hermite_basis((ti - tk[i]) / h)
            d0, d1, m0, m1 = d[i], d[i + 1], self._tan0[i], self._tan1[i]

            def col(x):
                return x[:, None, None]

            h_ = col(h)
            p[inside] = col(h00) * d0 + col(h10 * h) * m0 + col(h01) * d1 + col(h11 * h) * m1
            v[inside] = (col(d00) * d0 + col(d10 * h) * m0 + col(d01) * d1 + col(d11 * h) * m1) / h_
            a[inside] = (col(e00) * d0 + col(e10 * h) * m0 + col(e01) * d1 + col(e11 * h) * m1) / col(h * h)
        return p, v, a


def _normalized(u: np.ndarray, ud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors of the rows of ``u`` and their time derivatives, ``(I - n n^T) u' / |u|``."""
    length = np.linalg.norm(u, axis=1, keepdims=True)
    n = u / length
    nd = (ud - n * np.sum(n * ud, axis=1, keepdims=True)) / length
    return n, nd


def triangle_frames(p0, p1, p2, v0, v1, v2):
    """Rotation matrices of triangles (columns: first edge, normal x edge, normal) and their world angular
    velocities from the corners' velocities.

    Args:
        p0, p1, p2: (G, 3) corners [m]; v0, v1, v2: (G, 3) their velocities [m/s].

    Returns:
        ``(R, omega)``: (G, 3, 3) and (G, 3) [rad/s], ``omega^ = R' R^T``.
    """
    e1, e2 = p1 - p0, p2 - p0
    e1d, e2d = v1 - v0, v2 - v0
    t, td = _normalized(e1, e1d)
    n, nd = _normalized(cross_rows(e1, e2), cross_rows(e1d, e2) + cross_rows(e1, e2d))
    b = cross_rows(n, t)
    bd = cross_rows(nd, t) + cross_rows(n, td)
    R = np.stack([t, b, n], axis=2)
    Rd = np.stack([td, bd, nd], axis=2)
    W = Rd @ np.transpose(R, (0, 2, 1))
    omega = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1)
    return R, omega


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(G, 3, 3) rotation matrices to (G, 4) quaternions (x, y, z, w), w >= 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return q * np.where(q[:, 3:4] < 0.0, -1.0, 1.0)


class ScalpBinding:
    """Guide roots bound to the triangles of an animated mesh.

    Args:
        track: the mesh's world points over time (:class:`PointTrack`, metres).
        faces: (F, 3) triangle vertex indices.
        roots: (G, 3) the guide roots in the world at rest (``t = rest_time``) [m].
        head_rest: 4x4 head pose at rest (the groom's head frame in the world), identity when None.
        max_distance: farthest a root may lie from the surface at rest [m]; farther is a groom made for
            another surface.
        rest_time: the time the groom's rest shape belongs to [s].

    Attributes:
        triangle: (G,) the face each root is bound to. barycentric: (G, 3) its coordinates there.
        offset: (G, 3) [m] what the root moved to land on the surface (the strand moves with it).
    """

    def __init__(self, track: PointTrack, faces, roots, *, head_rest=None, max_distance: float = 0.01,
                 rest_time: float = 0.0, where: str = "groom.surface"):
        import trimesh

        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        roots = np.asarray(roots, dtype=np.float64).reshape(-1, 3)
        rest, _, _ = track.evaluate(rest_time)
        mesh = trimesh.Trimesh(vertices=rest, faces=faces, process=False)
        closest, distance, tri = trimesh.proximity.closest_point(mesh, roots)
        far = np.flatnonzero(distance > max_distance)
        if far.size:
            s = int(far[np.argmax(distance[far])])
            raise SurfaceError(f"{where}: the root of strand {s} lies {distance[s] * 1e3:.1f} mm from the surface "
                               f"(max_distance {max_distance * 1e3:g} mm; {far.size} of {len(roots)} roots are "
                               f"farther): is this the groom's own scalp, in the same units and place?")
        self.triangle = np.asarray(tri, dtype=np.int64)
        corners = faces[self.triangle]
        bary = trimesh.triangles.points_to_barycentric(rest[corners], closest)
        self.barycentric = np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(axis=1, keepdims=True)
        # Only the bound triangles' corners are evaluated over time.
        self._used, inverse = np.unique(corners, return_inverse=True)
        self._corners = inverse.reshape(-1, 3)
        self.track = track.subset(self._used)
        self.rest_time = float(rest_time)
        o0, R0 = (x[0] for x in self._frames_at([rest_time])[:2])
        self.offset = o0 - roots
        H = np.eye(4) if head_rest is None else np.asarray(head_rest, dtype=np.float64)
        # P(t) = F(t) F(0)^-1 H(0): rotation R(t) R0^T Rh, translation o(t) + R(t) c with c = R0^T (t_h - o0)
        self._R0T_Rh = np.transpose(R0, (0, 2, 1)) @ H[:3, :3]
        self._c = np.einsum("gji,gj->gi", R0, H[:3, 3] - o0)

    def _frames_at(self, times):
        """The bound points, their frames, the frames' angular velocities and the points' velocities and
        accelerations at each of ``times``: arrays of a leading axis of ``len(times)`` (one pass of array operations
        over all of them; each time's the same bits as alone)."""
        p, v, a = self.track.evaluate_many(times)  # (T, N, 3)
        c = self._corners
        w = self.barycentric[None, :, :, None]
        o = np.sum(w * p[:, c], axis=2)
        od = np.sum(w * v[:, c], axis=2)
        odd = np.sum(w * a[:, c], axis=2)
        T, G = len(times), len(c)
        corner = [(p[:, c[:, k]].reshape(-1, 3), v[:, c[:, k]].reshape(-1, 3)) for k in range(3)]
        R, omega = triangle_frames(corner[0][0], corner[1][0], corner[2][0], corner[0][1], corner[1][1], corner[2][1])
        return o, R.reshape(T, G, 3, 3), omega.reshape(T, G, 3), (od, odd)

    def root_points(self, t: float) -> np.ndarray:
        """The bound points on the surface at ``t``, (G, 3) [m]: where the roots belong."""
        return self._frames_at([t])[0][0]

    def root_frames(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every strand's root frame at ``t``, as :meth:`hairwarp.Control.set_root_frames` takes them.

        Returns:
            ``(xforms (G, 7), velocities (G, 6), accelerations (G, 6))``: position and quaternion (x, y, z, w) of
            the map from the head frame to the world; world angular velocity and the velocity of its origin; world
            angular acceleration (central difference of the angular velocity) and the origin's acceleration.
        """
        return self.root_frames_at([t])[0]

    def root_frames_at(self, times, accelerations: bool = True) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`root_frames` at each of ``times``, each the same bits as alone, in one pass of array operations over
        all of them: a runner takes a frame's steps together (``Simulation``), where a call a step spent its time in
        numpy's overhead on a few hundred roots (the character scene: about 1.7 ms a step, a third of its frame).
        Without ``accelerations`` the third array of each is None, and the frames are evaluated at the times alone
        (the angular accelerations' central differences take two more): a runner takes each step's accelerations
        as the mean over the step of the velocities (``runner._step_mean_frames``)."""
        offsets = (0.0, -_ALPHA_EPS, _ALPHA_EPS) if accelerations else (0.0,)
        o, R, omega, (od, odd) = self._frames_at([t + d for t in times for d in offsets])
        # with accelerations every third time is one asked for; the two after it, its angular velocity just before
        # and just after
        k = len(offsets)
        o, R, od, odd, omega_at = o[0::k], R[0::k], od[0::k], odd[0::k], omega[0::k]
        rot = R @ self._R0T_Rh
        r = np.sum(R * self._c[:, None, :], axis=-1)  # frame origin less the bound point
        origin = o + r
        v_origin = od + cross_rows(omega_at, r)
        quats = _matrix_to_quat(rot.reshape(-1, 3, 3)).reshape(*rot.shape[:2], 4)
        poses = [np.concatenate([origin[i], quats[i]], axis=1) for i in range(len(quats))]
        velocities = [np.concatenate([omega_at[i], v_origin[i]], axis=1) for i in range(len(quats))]
        if not accelerations:
            return [(pose, velocity, None) for pose, velocity in zip(poses, velocities, strict=True)]
        alpha = (omega[2::3] - omega[1::3]) / (2.0 * _ALPHA_EPS)
        a_origin = odd + cross_rows(alpha, r) + cross_rows(omega_at, cross_rows(omega_at, r))
        return [(pose, velocity, np.concatenate([alpha[i], a_origin[i]], axis=1))
                for i, (pose, velocity) in enumerate(zip(poses, velocities, strict=True))]

    @property
    def animated(self) -> bool:
        """Whether the bound triangles move over the track's samples."""
        points = self.track.points
        return points.shape[0] > 1 and float(np.ptp(points, axis=0).max()) > 0.0


class HeadCarriedRoots:
    """Root frames that ride rigidly on the head: a :class:`ScalpBinding`'s frames at its rest time, in the head
    frame of that instant, carried by the head's motion.

    For a scalp that its stage animates while the head's motion comes from elsewhere (a scene's ``head.motion``
    that is not ``usd``): the roots then stay where the head puts them, as the head's collider does, instead of
    following the scalp's own animation away from it.

    Args:
        binding: the roots on the scalp.
        head_rest: 4x4 head pose at the binding's rest time (the groom's head frame in the world).
    """

    def __init__(self, binding: ScalpBinding, head_rest):
        H = np.asarray(head_rest, dtype=np.float64)
        xforms, _, _ = binding.root_frames(binding.rest_time)
        self._origin = (xforms[:, :3] - H[:3, 3]) @ H[:3, :3]  # in the head frame
        self._rotation = H[:3, :3].T @ quat_to_matrix(xforms[:, 3:])

    def root_frames(self, sample) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every root's frame for the head at ``sample`` (a :class:`hairwarp.motion.MotionSample`), as
        :meth:`ScalpBinding.root_frames` gives them: the head's angular velocity and acceleration, and its
        origin's velocity and acceleration carried to each root."""
        R = quat_to_matrix(sample.rotation)
        r = self._origin @ R.T
        w, alpha = np.asarray(sample.angular_velocity, float), np.asarray(sample.angular_acceleration, float)
        xforms = np.concatenate([sample.position + r, _matrix_to_quat(R @ self._rotation)], axis=1)
        velocity = sample.linear_velocity + np.cross(w, r)
        acceleration = sample.linear_acceleration + np.cross(alpha, r) + np.cross(w, np.cross(w, r))
        count = len(r)
        return (xforms, np.concatenate([np.tile(w, (count, 1)), velocity], axis=1),
                np.concatenate([np.tile(alpha, (count, 1)), acceleration], axis=1))
