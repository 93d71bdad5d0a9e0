"""Enums and constants shared by kernels and host code.

Kernels compare against these values directly (``IntEnum`` and ``IntFlag`` members are
compile-time constants inside ``@wp.kernel``); ``hairwarp`` re-exports them.
"""

import enum

import warp as wp

wp.set_module_options({"enable_backward": False})

#: The segment length [m] at which a static link or a hair contact has the scene's stiffness and damping
#: (``links.stiffness``, ``interactions.stiffness``). Every segment makes ``links.neighbours`` links and every vertex
#: its vertex-face contacts, so a strand cut into twice the segments has twice as many: each link's stiffness and
#: damping scale with the mean length of the two segments it joins, a vertex-face contact's with its vertex's segment
#: length, and the hair is tied and pressed apart the same whatever the segment count, as the rods' stiffness per
#: joint is (``hairwarp.StrandParams``). With the same values on every link and contact the Ratboy mohawk at 31
#: segments was twice as tightly tied as at 16, and its tips ran 26 mm RMS apart over its turns and shake; scaled,
#: 7.1 mm (1.6 mm without links or contacts).
REFERENCE_SEGMENT_LENGTH = wp.constant(0.01)


class Integrator(enum.IntEnum):
    """Time integrators of the articulated strands.

    Attributes:
        SEMI_IMPLICIT: ``w += h qdd`` then ``q <- q exp(h w)``, joint springs explicit: symplectic Euler in form,
            but the chain's velocity-product terms make it gain energy on rotating strands (a free 20-segment
            strand spun at 10 rad/s gains +62 %, +18 %, +7.7 %, +3.7 % in 1 s at dt 2e-4, 1e-4, 5e-5, 2.5e-5:
            first order in dt), and a stiff spring bounds its step. For accuracy studies use RK4.
        IMPLICIT_JOINTS: the same with joint springs and damping taken at the end of the step
            (``D + hC + h^2 K`` inside ABA); stable for stiff hair at frame-rate steps, and dissipative: with no
            damping and no drag a 0.2 m strand of 10 segments (EI 1e-4 N m^2) swinging from horizontal at
            dt = 1/240 s loses 88 % of its energy in 2 s (0.64 to 0.075 mJ), where both explicit schemes blow up.
            First order, reached only where it damps the strand's bending modes away or resolves them: a mode of
            frequency w loses w^2 h / 2 of its amplitude a second, and modes with w^2 h T ~ 1 (T the time run) pass
            from damped away to kept as the step shrinks. On ``long_hair``'s strand (12 segments of 0.35 m, EI
            2e-4 N m^2, modes 2 to 4 at 20-110 rad/s), swinging free for 1 s, each halving of the step from 16 to
            2048 steps a frame divides the difference between runs by 1.5-1.8 (order 0.6-0.85), where
            ``SEMI_IMPLICIT`` divides it by 1.9-2.0 once stable; at EI 2e-3 by 1.89 (``tests/test_dynamics.py``,
            ``test_integrators_are_first_order_with_joint_springs``).
            Most of that damping is the spring's: taken at the step's end, ``-K (theta + h w')`` damps the joint by
            ``h K`` besides its own ``C``. Tried and not kept (2026-12-06): the damping ``max(C - h K, 0)`` instead
            of ``C``, leaving the hair its own damping at steps shorter than ``C / K`` (1 ms on ``long_hair``). A
            12-segment strand came 2.9 times closer to its 2048-step run at 32 steps a frame, and ``long_hair``'s
            free hair converged at first order (its runs 0.145 and 0.071 mm apart at 32-64 and 64-128 substeps,
            against 0.36 and 0.21); but its scenes with colliders converged no faster (orders 0.3-0.4 between
            successive runs), and linked hair lost the damping that carried it through violent motion: the
            shoulders' nod ten times as fast faulted at 32 substeps without colliders (a vertex at 46 m/s) and took
            frames again in finer steps at 8.
            A part of a step in which a segment turns more than 0.05 rad takes its velocity terms at its midpoint
            velocity (``kernels.articulated.MIDPOINT_ROTATION``): explicit, they grew a whipping strand's energy
            until it went NaN; so, a free strand of 12 segments set turning at 40 rad/s a joint with no damping
            keeps 15-27 % of its 1.45 J over 1 s at dt = 1/240 s, and free hair on a head turning ten times the
            shipped speed whips no faster at 8 substeps (10.7 m/s) than at 128 (11.2 m/s).
        RK4: classical fourth-order Runge-Kutta on the Lie group; for accuracy studies.
    """

    SEMI_IMPLICIT = 0
    IMPLICIT_JOINTS = 1
    RK4 = 2


class Fault(enum.IntFlag):
    """Bits of ``State.fault``, set on the device by the stage that found the problem.

    Attributes:
        NONFINITE_DYNAMICS: a joint acceleration, velocity or rotation became NaN or infinite in ABA.
        JOINT_SPEED: the free dynamics sped a joint up until it bends more than ``max_rotation_per_step``
            radians in one step, or in one part of a step that turns fast (``integrate_euler``).
        NONFINITE_COLLISION: the body contact response or the push-out produced a non-finite joint or vertex.
        COLLISION_SPEED: the body contact response sped a joint up until it bends further than
            ``max_rotation_per_step`` in one step (or part of one).
        CONTACT_OVERFLOW: more contacts than the buffers hold; some were dropped.
        INTERACTION_RESPONSE: the response of the links, hair contacts and body contacts after the free step
            (``interaction_response``) produced a non-finite joint, or changed a joint's velocity by more than half
            a turn of bend over the step.
        HAIR_SPEED: a guide vertex moved faster than the run's speed bound (``Solver.speed_bound``: a few times the
            fastest the head, the root frames, the colliders and the wind carried the hair, plus a free fall over
            the longest strand), read at the end of an output frame (``articulated.hair_speed``): hair that whips
            at tens of m/s on a head moving at a few is a blow-up that had not yet turned into a non-finite state.
    """

    NONE = 0
    NONFINITE_DYNAMICS = 1
    JOINT_SPEED = 2
    NONFINITE_COLLISION = 4
    COLLISION_SPEED = 8
    CONTACT_OVERFLOW = 16
    INTERACTION_RESPONSE = 32
    HAIR_SPEED = 64


class ColliderKind(enum.IntEnum):
    """Shapes of strand colliders.

    Attributes:
        SPHERE: centre at the collider origin, ``radius``.
        CAPSULE: segment from ``-half_height`` to ``+half_height`` along local z, ``radius``.
        PLANE: local z = 0, normal +z; the half-space z < 0 is inside.
        MESH: a closed triangle mesh in a ``wp.Mesh``.
        ELLIPSOID: centre at the collider origin, semi-axes ``radii`` along local x, y, z (the collider's bounds).
    """

    SPHERE = 0
    CAPSULE = 1
    PLANE = 2
    MESH = 3
    ELLIPSOID = 4
