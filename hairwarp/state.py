"""Per-step arrays (``State``) and animated inputs (``Control``)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from hairwarp.motion import cross_rows, rotate_floats


class State:
    """What a step reads and writes. Create with ``model.state()``.

    Attributes:
        joint_q: joint rotations, parent from child, quat (x, y, z, w), (G*S,).
        joint_qd: joint angular velocities relative to the parent [rad/s], child frame, vec3 (G*S,).
        seg_xform: world frame of each segment (origin at its top vertex, segment along body -z),
            transform (G*S,).
        vertex_positions: world vertex positions [m], vec3 (G*(S+1),), root first.
        vertex_velocities: world vertex velocities [m/s], vec3 (G*(S+1),).
        fault: bits of :class:`hairwarp.Fault` set on the device by the stage that found a
            problem, int32 (1,); sticky across steps.
    """

    def __init__(self, model):
        device = model.device
        self.joint_q = wp.zeros(model.seg_count, dtype=wp.quat, device=device)
        self.joint_qd = wp.zeros(model.seg_count, dtype=wp.vec3, device=device)
        self.seg_xform = wp.zeros(model.seg_count, dtype=wp.transform, device=device)
        self.vertex_positions = wp.zeros(model.vert_count, dtype=wp.vec3, device=device)
        self.vertex_velocities = wp.zeros(model.vert_count, dtype=wp.vec3, device=device)
        self.fault = wp.zeros(1, dtype=wp.int32, device=device)

    def assign(self, other: State):
        """Copy every array of ``other`` (a state of the same model) into this state, in place."""
        names = ("joint_q", "joint_qd", "seg_xform", "vertex_positions", "vertex_velocities", "fault")
        if not isinstance(other, State):
            raise TypeError(f"other must be a hairwarp State, got {type(other).__name__}")
        for name in names:  # every check before the first copy: a refused one changes nothing
            mine, theirs = getattr(self, name), getattr(other, name)
            if theirs.shape != mine.shape:
                raise ValueError(f"other holds {theirs.shape[0]} elements of {name}, this state {mine.shape[0]}: a "
                                 f"state of another model")
        for name in names:
            wp.copy(getattr(self, name), getattr(other, name))


def _vector(name: str, value) -> np.ndarray:
    """``value`` as 3 finite floats, or a ValueError naming ``name``."""
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 numbers, got {value!r}") from None
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return v


def _head_values(position, rotation, angular_velocity, linear_velocity, angular_acceleration, linear_acceleration):
    """The pose (7), velocities (6) and accelerations (6) ``set_head`` stores. Valid values take one check of the
    lot (set every step: a few microseconds); others are checked one by one for a message that names them."""
    try:
        pose = np.concatenate((np.asarray(position, float).reshape(-1), np.asarray(rotation, float).reshape(-1)))
        velocity = np.concatenate((np.asarray(angular_velocity, float).reshape(-1),
                                   np.asarray(linear_velocity, float).reshape(-1)))
        acceleration = np.concatenate((np.asarray(angular_acceleration, float).reshape(-1),
                                       np.asarray(linear_acceleration, float).reshape(-1)))
        fast = pose.shape == (7,) and velocity.shape == (6,) and acceleration.shape == (6,)
    except (TypeError, ValueError):
        fast = False
    if fast and np.isfinite(pose).all() and np.isfinite(velocity).all() and np.isfinite(acceleration).all():
        norm_sq = float(pose[3:] @ pose[3:])
        if abs(norm_sq - 1.0) <= 2.0e-6:  # a unit quaternion to float32 rounding: stored as given
            return pose, velocity, acceleration
    return (_head_pose(position, rotation),
            np.concatenate([_vector("angular_velocity", angular_velocity),
                            _vector("linear_velocity", linear_velocity)]),
            np.concatenate([_vector("angular_acceleration", angular_acceleration),
                            _vector("linear_acceleration", linear_acceleration)]))


def _head_pose(position, rotation) -> np.ndarray:
    """Position and rotation (quaternion x, y, z, w) as 7 floats; a quaternion off unit length by more than float32
    rounding is normalised, a zero or non-finite one refused."""
    p = _vector("position", position)
    try:
        q = np.asarray(rotation, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"rotation must be a quaternion (x, y, z, w), got {rotation!r}") from None
    norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
    if q.shape != (4,) or not np.isfinite(q).all() or norm < 1.0e-6:
        raise ValueError(f"rotation must be a non-zero quaternion (x, y, z, w) of finite numbers, got {rotation!r}")
    if abs(norm - 1.0) > 1.0e-6:
        q = q / norm
    return np.concatenate([p, q])


def _unit_quaternions(xforms: np.ndarray) -> np.ndarray:
    """``(G, 7)`` poses with their quaternions (columns 3-6) of unit length: a zero one is refused, naming its strand,
    one off unit length by more than float32 rounding normalised (a quaternion of length 5 put a root 84 m up)."""
    norm = np.linalg.norm(xforms[:, 3:].astype(np.float64), axis=1)
    zero = np.flatnonzero(norm < 1.0e-6)
    if len(zero):
        raise ValueError(f"set_root_frames: xforms has a zero quaternion (strand {int(zero[0])})")
    off = np.abs(norm - 1.0) > 1.0e-6
    if off.any():
        xforms = xforms.copy()
        xforms[off, 3:] = (xforms[off, 3:] / norm[off, None]).astype(np.float32)
    return xforms


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors ``v`` (n, 3) rotated by unit quaternions ``q`` (n, 4; x, y, z, w)."""
    u, w = q[:, :3], q[:, 3:]
    t = 2.0 * cross_rows(u, v)
    return v + w * t + cross_rows(u, t)


def hair_ball(model) -> tuple[list[float], float]:
    """A ball holding the groom's rest shape in the head frame: its centre (the middle of the bounding box, a list
    of 3 floats [m]) and radius [m]. How fast a head motion moves the hair, and how far, is bounded by that ball's
    motion (the hair speed fault's bound, the teleport test)."""
    points = np.asarray(model.rest_vertex_positions, dtype=float).reshape(-1, 3)
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    return centre.tolist(), float(np.linalg.norm(points - centre, axis=1).max())


def _carried_speed(pose, velocity, centre, reach: float) -> float:
    """The fastest [m/s] a head pose and velocity (``_head_values``) move a point of a ball of radius ``reach``
    about ``centre`` (head frame): ``|v + w x R c| + |w| reach``. Plain floats: it runs at every step."""
    wx, wy, wz, vx, vy, vz = velocity.tolist()
    rx, ry, rz = rotate_floats(pose[3:7].tolist(), centre)
    ux, uy, uz = vx + wy * rz - wz * ry, vy + wz * rx - wx * rz, vz + wx * ry - wy * rx
    return math.sqrt(ux * ux + uy * uy + uz * uz) + math.sqrt(wx * wx + wy * wy + wz * wz) * reach


class Control:
    """Animated inputs of a step; device arrays updated in place so captured graphs see new values.

    Attributes:
        head_xform: world transform of the head, transform (1,); the groom's roots ride on it, and so do
            head-attached colliders and the dense hair.
        head_velocity: (world angular velocity [rad/s], world velocity of the head origin [m/s]),
            spatial_vector (1,).
        head_acceleration: (world angular acceleration [rad/s^2], classical acceleration of the
            head origin [m/s^2]), spatial_vector (1,).
        wind: wind velocity [m/s], world, vec3 (1,); acts through the air drag.
        bases: the frames the strands' roots ride on (``hairwarp.kernels.articulated.StrandBases``): the head
            arrays themselves, or with ``root_frames=True`` one frame per strand, set by :meth:`set_root_frames`.
        carried_speed: the fastest [m/s] any head or root frame set so far carried a point of the hair in its rest
            shape (host float; set by :meth:`set_head` and :meth:`set_root_frames`, not by writes into the arrays).
        wind_speed: the strongest wind [m/s] :meth:`set_wind` set so far. Both feed the hair speed fault's bound
            (``Solver.speed_bound``).

    Args:
        model: the :class:`hairwarp.Model`.
        root_frames: give every strand its own root frame (roots bound to a deforming surface,
            :class:`hairwarp.surface.ScalpBinding`); the frames start as the head's build pose.
    """

    def __init__(self, model, *, root_frames: bool = False):
        device = model.device
        self.head_xform = wp.array([wp.transform_identity()], dtype=wp.transform, device=device)
        self.head_velocity = wp.zeros(1, dtype=wp.spatial_vector, device=device)
        self.head_acceleration = wp.zeros(1, dtype=wp.spatial_vector, device=device)
        self.wind = wp.zeros(1, dtype=wp.vec3, device=device)
        self._host_views = None
        self.strand_count = int(model.strand_count)
        # what the hair speed fault's bound needs of the groom (``Solver.speed_bound``): its centre and reach in the
        # head frame, each root and each strand's length for root frames
        rest = np.asarray(model.rest_vertex_positions, dtype=float).reshape(self.strand_count, -1, 3)
        self._hair_centre, self._hair_reach = hair_ball(model)
        self._roots = rest[:, 0]
        self._strand_reach = np.linalg.norm(rest - rest[:, :1], axis=2).max(axis=1)
        self.carried_speed = 0.0
        self.wind_speed = 0.0
        from hairwarp.kernels.articulated import StrandBases

        self.bases = StrandBases()
        if root_frames:
            identity = np.tile(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32), (self.strand_count, 1))
            self.bases.xform = wp.array(identity, dtype=wp.transform, device=device)
            self.bases.velocity = wp.zeros(self.strand_count, dtype=wp.spatial_vector, device=device)
            self.bases.acceleration = wp.zeros(self.strand_count, dtype=wp.spatial_vector, device=device)
            self.bases.per_strand = 1
        else:
            self.bases.xform = self.head_xform
            self.bases.velocity = self.head_velocity
            self.bases.acceleration = self.head_acceleration
            self.bases.per_strand = 0

    @property
    def root_frames(self) -> bool:
        """Whether every strand has its own root frame (``Control(model, root_frames=True)``)."""
        return bool(self.bases.per_strand)

    def set_head(self, position=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0, 1.0), linear_velocity=(0.0, 0.0, 0.0),
                 angular_velocity=(0.0, 0.0, 0.0), linear_acceleration=(0.0, 0.0, 0.0),
                 angular_acceleration=(0.0, 0.0, 0.0)):
        """Set the head pose (rotation as quaternion x, y, z, w) and its world velocities and accelerations."""
        values = _head_values(position, rotation, angular_velocity, linear_velocity, angular_acceleration,
                              linear_acceleration)
        if not self.root_frames:
            speed = _carried_speed(values[0], values[1], self._hair_centre, self._hair_reach)
            if speed > self.carried_speed:
                self.carried_speed = speed
        arrays = (self.head_xform, self.head_velocity, self.head_acceleration)
        if self.head_xform.device.is_cpu:
            # straight into the arrays' host memory: three assigns cost ~50 us, paid every step
            if self._host_views is None:
                self._host_views = tuple(a.numpy() for a in arrays)
            for view, value in zip(self._host_views, values):
                view[0] = value
            return
        for array, value in zip(arrays, values):
            array.assign(np.asarray([value], dtype=np.float32))

    def set_motion(self, sample):
        """Set the head from a motion sample (``hairwarp.motion.MotionSample``)."""
        if not all(hasattr(sample, k) for k in ("position", "rotation", "linear_velocity", "angular_velocity")):
            raise TypeError(f"sample must be a hairwarp MotionSample (HeadMotion.evaluate(t)), got "
                            f"{type(sample).__name__}")
        self.set_head(sample.position, sample.rotation, sample.linear_velocity, sample.angular_velocity,
                      sample.linear_acceleration, sample.angular_acceleration)

    def set_root_frames(self, xforms, velocities, accelerations):
        """Set every strand's root frame: the map from the groom's head frame to the world that strand's root rides
        on, as the head pose does for all of them without ``root_frames``.

        Args:
            xforms: (G, 7) positions and quaternions (x, y, z, w) [m].
            velocities: (G, 6) world angular velocity [rad/s] and world velocity of the frame's origin [m/s].
            accelerations: (G, 6) world angular acceleration [rad/s^2] and classical acceleration of the
                origin [m/s^2].

        Raises:
            ValueError: the control was made without ``root_frames=True``, an array has the wrong shape or
                non-finite values, or a quaternion is zero. Quaternions off unit length by more than float32
                rounding are normalised, as :meth:`set_head` does.
        """
        if not self.root_frames:
            raise ValueError("this control has no per-strand root frames: make it with Control(model, "
                             "root_frames=True)")
        G = self.strand_count
        for name, value, width, target in (("xforms", xforms, 7, self.bases.xform),
                                           ("velocities", velocities, 6, self.bases.velocity),
                                           ("accelerations", accelerations, 6, self.bases.acceleration)):
            a = np.asarray(value, dtype=np.float32)
            if a.shape != (G, width):
                raise ValueError(f"set_root_frames: {name} must have shape ({G}, {width}), got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"set_root_frames: {name} has non-finite values (strand "
                                 f"{int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])})")
            if name == "xforms":
                a = _unit_quaternions(a)
                frames = a
            elif name == "velocities":
                # each root's velocity, v + w x (R r), and its strand turned rigidly about it
                w, v = a[:, :3].astype(float), a[:, 3:].astype(float)
                roots = _rotate(frames[:, 3:].astype(float), self._roots)
                speed = float((np.linalg.norm(v + cross_rows(w, roots), axis=1)
                               + np.linalg.norm(w, axis=1) * self._strand_reach).max())
                if speed > self.carried_speed:
                    self.carried_speed = speed
            if target.device.is_cpu:  # straight into the array's host memory, as set_head does
                target.numpy()[:] = a
            else:
                target.assign(a)

    def set_wind(self, velocity):
        """Set the wind velocity [m/s], world."""
        wind = _vector("wind velocity", velocity)
        self.wind_speed = max(self.wind_speed, float(np.linalg.norm(wind)))
        self.wind.assign(np.asarray([wind], dtype=np.float32))
