"""Articulated strands: forward kinematics, Featherstone's ABA, time integration.

One thread per strand. A strand is a serial chain of S rigid segments; joint k is a 3-DOF
spherical joint between segment k and its parent (segment k-1, or the head for k = 0).
Segment k's frame has its origin at vertex k and the segment along body -z; the child joint
sits at the parent's (0, 0, -L). All dynamics quantities are in body frames (Featherstone's
local convention, RBDA ch. 7); see ``spatial.py`` for the vector and quaternion conventions.

Because a spherical joint's motion subspace is ``S = [I3; 0]``, the joint-space inertia of
joint k is the rotational block ``A`` of the articulated inertia, ``U = I^A S = [A; B^T]``, and
with no armature the inertia passed to the parent has only a translational block. Armature
``hC + h^2 K`` (the implicit joint springs) makes the general blocks necessary, so the code keeps
them; the three passes are ``aba_forward_pass1``, ``aba_backward_pass`` and ``aba_forward_pass2``.
"""

import warp as wp

from hairwarp.kernels.spatial import (
    inertia_shift_z,
    quat_exp,
    quat_log,
    rotate_blocks,
    rotate_symmetric,
    scale_rows,
    segment_inertia_blocks,
    skew,
    skew_z_left,
    skew_z_right,
    transpose_scale_columns,
)
from hairwarp.kernels.types import Fault

wp.set_module_options({"enable_backward": False})


@wp.struct
class StrandChains:
    """The model's chain arrays, as the ABA kernels read them (see ``hairwarp.Model``)."""

    seg_per_strand: int
    seg_length: wp.array(dtype=float)
    seg_mass: wp.array(dtype=float)
    seg_inertia: wp.array(dtype=wp.vec3)
    strand_root_pos: wp.array(dtype=wp.vec3)
    joint_rest_q: wp.array(dtype=wp.quat)
    joint_stiffness: wp.array(dtype=wp.vec3)
    joint_damping: wp.array(dtype=wp.vec3)
    gravity: wp.vec3


@wp.struct
class SegmentLoads:
    """External loads of a step: force [N] and torque [N m] about each segment's origin (world), the
    semi-implicit inertia [kg] of interaction springs at each centre of mass; flags say which are in use."""

    seg_force: wp.array(dtype=wp.vec3)
    seg_torque: wp.array(dtype=wp.vec3)
    seg_implicit_mass: wp.array(dtype=float)
    has_force: int
    has_implicit_mass: int


@wp.struct
class BodyContacts:
    """Body contacts of a step, one entry per vertex (``G*(S+1)``), found by
    ``body_collision.detect_body_contacts`` at the step's start and solved here, inside the step.

    ``normal`` (world, unit; zero: no candidate), ``object_velocity`` [m/s] of the collider's surface point at
    the step's end, ``gap`` [m] the distance at the step's start less the contact layer (the approach the
    step may still make), ``friction`` (the collider's, 0 frictionless to 1 full match). Persistent across
    steps, of the last step in which a collider held the vertex: ``slip`` [m/s], the vertex's speed over the surface
    at that step's end, ``force`` [N, world], the force the collider put on it, and ``removed`` [m/s], how much
    slower over the surface the contact left it than its free velocity, from which the next step's friction starts
    (``contact_friction``); ``away`` [s], the time since that step (kept for CONTACT_MEMORY, then cleared); at steps
    of CONTINUOUS_FRICTION_STEP and longer, ``share``, the tangential share of the damper in [0, 1] (1 sticking,
    less sliding; ``matched_friction``), and ``answer_force`` [N, world], the whole contact force the vertex ended
    the bodies' answer to the links' sweeps with (``kernels.sweeps.body_answer``). Of the last step alone:
    ``step_force`` [N, world], the mean force over its free step (``held_force``), and ``answer_start``, the answer's
    force the step starts from. ``enabled`` = 0: no colliders; ``stiffness`` is ``h c`` per kilogram of the strand
    (see ``body_contact_solve``).
    """

    enabled: int
    stiffness: float
    normal: wp.array(dtype=wp.vec3)
    object_velocity: wp.array(dtype=wp.vec3)
    gap: wp.array(dtype=float)
    friction: wp.array(dtype=float)
    slip: wp.array(dtype=float)
    share: wp.array(dtype=float)
    force: wp.array(dtype=wp.vec3)
    removed: wp.array(dtype=float)
    away: wp.array(dtype=float)
    # the mean force [N, world] the colliders put on each vertex over the last free step, its parts' forces weighted
    # by their lengths (``integrate_euler``; kept at steps of the share law's length, for strands with candidates):
    # what the bodies' answer after it starts from (``held_force``)
    step_force: wp.array(dtype=wp.vec3)
    # the whole contact force [N, world] each vertex ended the last step's answer to the links' sweeps with (the free
    # step's and the answer's, in its cone; ``kernels.sweeps.body_answer``), persistent: what the next step's answer
    # starts from (``answer_start``, taken at its first sweep), so that its damper answers only the change
    answer_force: wp.array(dtype=wp.vec3)
    answer_start: wp.array(dtype=wp.vec3)


@wp.struct
class InteractionResponse:
    """The hair interactions' dampers of a step, per segment, in its own frame about its origin (its top vertex),
    linearised at the step's start: the blocks ``A, B, C`` of the spatial inertia ``h c P`` of its point dampers
    [kg m^2, kg m, kg] (``kernels.contacts.contact_response_gather``), and their forces [N] and torques [N m] on the
    free end-of-step velocities; ``interaction_response`` solves them with the strand's own inertia. ``phi_a``,
    ``phi_b``, ``phi_c``: each segment's inverse inertia in its strand at the step's start, from which a pair's
    dampers take the effective mass of each of its ends (``articulated_inverse_mass``, ``split_factor``)."""

    A: wp.array(dtype=wp.mat33)
    B: wp.array(dtype=wp.mat33)
    C: wp.array(dtype=wp.mat33)
    force: wp.array(dtype=wp.vec3)
    torque: wp.array(dtype=wp.vec3)
    # each segment's inverse spatial inertia within its strand (``strand_inverse_inertia``), blocks
    # [[phi_a, phi_b], [phi_b^T, phi_c]] in its own frame about its origin [1/(kg m^2), 1/(kg m), 1/kg]
    phi_a: wp.array(dtype=wp.mat33)
    phi_b: wp.array(dtype=wp.mat33)
    phi_c: wp.array(dtype=wp.mat33)


@wp.struct
class StrandBases:
    """The moving frames the strands' roots ride on: ``per_strand`` = 0, every strand on element 0 (the head, the
    ``Control.head_*`` arrays themselves); 1, strand ``s`` on element ``s`` (roots bound to a deforming surface,
    ``Control.set_root_frames``). ``xform`` maps the groom's head frame to the world; ``velocity`` is (world
    angular velocity [rad/s], world velocity of the frame's origin [m/s]); ``acceleration`` (world angular
    acceleration [rad/s^2], classical acceleration of the origin [m/s^2])."""

    xform: wp.array(dtype=wp.transform)
    velocity: wp.array(dtype=wp.spatial_vector)
    acceleration: wp.array(dtype=wp.spatial_vector)
    per_strand: int


@wp.struct
class AbaScratch:
    """Per-segment ABA workspace: bias forces p, velocity-product accelerations c, ``D^-1 A``,
    ``D^-1 B``, ``D^-1 u`` and the joint accelerations; allocated once by the solver."""

    p: wp.array(dtype=wp.spatial_vector)
    c: wp.array(dtype=wp.spatial_vector)
    DA: wp.array(dtype=wp.mat33)
    DB: wp.array(dtype=wp.mat33)
    Du: wp.array(dtype=wp.vec3)
    qdd: wp.array(dtype=wp.vec3)


@wp.struct
class DamperFactors:
    """Per segment, what the inward pass of a solve with dampers makes of the strand's matrix (``damper_solve``):
    ``D^-1``, the articulated blocks ``A``, ``B`` (dampers and children included) and ``D^-1 A``, ``D^-1 B``, kept
    for later solves of the same matrix with other forces (the step's later sweeps, or the later steps' that the
    links' response lets keep them: ``hairwarp.Solver.factor_steps``)."""

    Dinv: wp.array(dtype=wp.mat33)
    A: wp.array(dtype=wp.mat33)
    B: wp.array(dtype=wp.mat33)
    DA: wp.array(dtype=wp.mat33)
    DB: wp.array(dtype=wp.mat33)
    # the joints the factors were made at (``kernels.sweeps.link_sweep``: a strand whose joints have turned far from
    # them since makes its own again)
    q: wp.array(dtype=wp.quat)


@wp.func
def head_body_motion(head_xform: wp.transform, head_velocity: wp.spatial_vector, head_acceleration: wp.spatial_vector,
                     gravity: wp.vec3):
    """Head spatial velocity and acceleration in the head frame, gravity folded in.

    Control gives world angular/linear velocity of the head origin and classical accelerations.
    The body-frame spatial acceleration is d/dt of the body-frame velocity,
    ``(R^T alpha, R^T a - omega_b x v_b)``; gravity enters as a base acceleration of -g (RBDA 5.3).
    """
    R = wp.transform_get_rotation(head_xform)
    w_b = wp.quat_rotate_inv(R, wp.spatial_top(head_velocity))
    v_b = wp.quat_rotate_inv(R, wp.spatial_bottom(head_velocity))
    a_ang = wp.quat_rotate_inv(R, wp.spatial_top(head_acceleration))
    a_lin = wp.quat_rotate_inv(R, wp.spatial_bottom(head_acceleration) - gravity) - wp.cross(w_b, v_b)
    return wp.spatial_vector(w_b, v_b), wp.spatial_vector(a_ang, a_lin)


@wp.func
def joint_offset(chains: StrandChains, strand: int, k: int, i: int):
    """Position of joint k in its parent's frame: the root in the head frame, else the parent's tip."""
    if k == 0:
        return chains.strand_root_pos[strand]
    return wp.vec3(0.0, 0.0, -chains.seg_length[i - 1])


@wp.func
def aba_forward_pass1(
    chains: StrandChains,
    strand: int,
    head_rot: wp.quat,
    v_head: wp.spatial_vector,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    scratch: AbaScratch,
):
    """Outward pass: body velocities, velocity-product accelerations c and bias forces p."""
    S = chains.seg_per_strand
    w_p = wp.spatial_top(v_head)
    v_p = wp.spatial_bottom(v_head)
    R_world = head_rot
    for k in range(S):
        i = strand * S + k
        q = joint_q[i]
        w = joint_qd[i]
        r = joint_offset(chains, strand, k, i)
        om = wp.quat_rotate_inv(q, w_p) + w
        vl = wp.quat_rotate_inv(q, v_p + wp.cross(w_p, r))
        scratch.c[i] = wp.spatial_vector(wp.cross(om, w), wp.cross(vl, w))

        m = chains.seg_mass[i]
        L = chains.seg_length[i]
        com = wp.vec3(0.0, 0.0, -0.5 * L)
        A, B = segment_inertia_blocks(m, L, chains.seg_inertia[i], 0.0)
        n_I = A * om + B * vl
        f_I = m * (vl + wp.cross(om, com))
        p_ang = wp.cross(om, n_I) + wp.cross(vl, f_I)
        p_lin = wp.cross(om, f_I)
        R_world = R_world * q
        if loads.has_force != 0:
            p_ang = p_ang - wp.quat_rotate_inv(R_world, loads.seg_torque[i])
            p_lin = p_lin - wp.quat_rotate_inv(R_world, loads.seg_force[i])
        if loads.has_implicit_mass != 0:
            # The semi-implicit spring inertia m_e resists the point's true acceleration, but gravity
            # enters ABA as a base acceleration, which would give m_e a weight: hold it up with -m_e g.
            lift = wp.quat_rotate_inv(R_world, -loads.seg_implicit_mass[i] * chains.gravity)
            p_ang = p_ang - wp.cross(com, lift)
            p_lin = p_lin - lift
        scratch.p[i] = wp.spatial_vector(p_ang, p_lin)
        w_p = om
        v_p = vl


@wp.func
def segment_articulated_blocks(chains: StrandChains, loads: SegmentLoads, i: int, cA: wp.mat33, cB: wp.mat33,
                               cC: wp.mat33):
    """Blocks (A, B, C) of segment ``i``'s articulated inertia about its origin, its own frame: the segment (with
    the interaction springs' semi-implicit mass at its centre of mass) and its child's passed-on blocks."""
    extra = float(0.0)
    if loads.has_implicit_mass != 0:
        extra = loads.seg_implicit_mass[i]
    m = chains.seg_mass[i]
    A0, B0 = segment_inertia_blocks(m, chains.seg_length[i], chains.seg_inertia[i], extra)
    return A0 + cA, B0 + cB, (m + extra) * wp.identity(n=3, dtype=float) + cC


@wp.func
def joint_armature(chains: StrandChains, i: int, h: float, implicit: int):
    """The implicit joints' armature ``h C + h^2 K`` of joint ``i`` [kg m^2] (zero without ``implicit``): what
    taking its springs and dampers at the end of a step of ``h`` seconds adds to the joint's inertia."""
    if implicit != 0:
        return h * chains.joint_damping[i] + h * h * chains.joint_stiffness[i]
    return wp.vec3()


@wp.func
def blocks_to_parent(Rm: wp.mat33, DA: wp.mat33, DB: wp.mat33, armature: wp.vec3, B: wp.mat33, C: wp.mat33,
                     z: float):
    """What a segment's articulated inertia passes to its parent through its spherical joint, ``I^A - U D^-1 U^T``
    (``D = A + diag(armature)``; ``DA``, ``DB`` = ``D^-1 A``, ``D^-1 B``), rotated into the parent's frame
    (``Rm``) and shifted to its origin from the joint at ``(0, 0, z)``: the blocks (cA, cB, cC)."""
    Aa, Ba, Ca = rotate_blocks(Rm, transpose_scale_columns(DA, armature), scale_rows(DB, armature),
                               C - wp.transpose(B) * DB)
    cA, cB = inertia_shift_z(Aa, Ba, Ca, z)
    return cA, cB, Ca


@wp.func
def factor_joint(chains: StrandChains, i: int, k: int, h: float, implicit: int, joint_q: wp.array(dtype=wp.quat),
                 A: wp.mat33, B: wp.mat33, C: wp.mat33):
    """Segment ``i`` (``k``-th of its strand) in an inward pass, its articulated blocks ``A``, ``B``, ``C`` given:
    ``D^-1`` (``D = A + diag(armature)``, the implicit joints' armature), ``D^-1 A``, ``D^-1 B``, and the blocks it
    passes to its parent (``blocks_to_parent``; zero for a root segment)."""
    armature = joint_armature(chains, i, h, implicit)
    Dinv = wp.inverse(A + wp.diag(armature))
    DA = Dinv * A
    DB = Dinv * B
    cA = wp.mat33()
    cB = wp.mat33()
    cC = wp.mat33()
    if k > 0:
        cA, cB, cC = blocks_to_parent(wp.quat_to_matrix(joint_q[i]), DA, DB, armature, B, C,
                                      -chains.seg_length[i - 1])
    return Dinv, DA, DB, cA, cB, cC


@wp.func
def bias_to_parent(chains: StrandChains, i: int, joint_q: wp.array(dtype=wp.quat), A: wp.mat33, B: wp.mat33,
                   Du: wp.vec3, n_: wp.vec3, f: wp.vec3):
    """The bias force (torque ``n_``, force ``f``) that segment ``i`` passes to its parent in an inward pass, its
    joint's answer ``Du`` given: rotated into the parent's frame and moved to its origin."""
    Rm = wp.quat_to_matrix(joint_q[i])
    z = -chains.seg_length[i - 1]
    na = Rm * (n_ + A * Du)
    fa = Rm * (f + wp.transpose(B) * Du)
    return na + wp.cross(wp.vec3(0.0, 0.0, z), fa), fa


@wp.func
def aba_backward_pass(
    chains: StrandChains,
    strand: int,
    dt: float,
    implicit: int,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    scratch: AbaScratch,
):
    """Inward pass: articulated inertias and bias forces, tip to root.

    The chain has one child per body, so the child's contribution is carried in registers.
    Stores ``D^-1 A``, ``D^-1 B`` and ``D^-1 u`` for the second outward pass.
    """
    S = chains.seg_per_strand
    cA = wp.mat33()
    cB = wp.mat33()
    cC = wp.mat33()
    cn = wp.vec3()
    cf = wp.vec3()
    for kk in range(S):
        k = S - 1 - kk
        i = strand * S + k
        A, B, C = segment_articulated_blocks(chains, loads, i, cA, cB, cC)
        p = scratch.p[i]
        n = wp.spatial_top(p) + cn
        f = wp.spatial_bottom(p) + cf

        q = joint_q[i]
        w = joint_qd[i]
        K = chains.joint_stiffness[i]
        Cd = chains.joint_damping[i]
        theta = quat_log(wp.quat_inverse(chains.joint_rest_q[i]) * q)
        tau = -wp.cw_mul(K, theta) - wp.cw_mul(Cd, w)
        D = A
        armature = wp.vec3()
        if implicit != 0:
            # springs and dampers at the end of the step: (M + hC + h^2 K) qdd = -K theta - (C + hK) w - bias
            tau = tau - dt * wp.cw_mul(K, w)
            armature = dt * Cd + dt * dt * K
            D = A + wp.diag(armature)
        Dinv = wp.inverse(D)
        u = tau - n
        DA = Dinv * A
        DB = Dinv * B
        Du = Dinv * u
        scratch.DA[i] = DA
        scratch.DB[i] = DB
        scratch.Du[i] = Du

        if k > 0:
            c = scratch.c[i]
            c_ang = wp.spatial_top(c)
            c_lin = wp.spatial_bottom(c)
            R = wp.quat_to_matrix(q)
            z = -chains.seg_length[i - 1]  # the joint sits at (0, 0, z) in the parent
            r = wp.vec3(0.0, 0.0, z)
            Ca = C - wp.transpose(B) * DB
            if implicit != 0:
                # I^a = I^A - U D^-1 U^T keeps all three blocks when D = A + diag(d) carries armature d. With A and
                # D symmetric, A - A D^-1 A = (D^-1 A)^T diag(d) and B - A D^-1 B = diag(d) D^-1 B: scalings of the
                # stored products instead of 3x3 products, and no cancellation when d is small against A.
                Aa = transpose_scale_columns(DA, armature)
                Ba = scale_rows(DB, armature)
                na = n + Aa * c_ang + Ba * c_lin + A * Du
                fa = f + wp.transpose(Ba) * c_ang + Ca * c_lin + wp.transpose(B) * Du
                Aa, Ba, Ca = rotate_blocks(R, Aa, Ba, Ca)
                cA, cB = inertia_shift_z(Aa, Ba, Ca, z)
            else:
                # D = A: the rotational and coupling blocks vanish and the joint passes its torque,
                # so only the translational block travels to the parent
                na = tau
                fa = f + Ca * c_lin + wp.transpose(B) * Du
                Ca = rotate_symmetric(R, Ca)
                cB = skew_z_left(Ca, z)
                cA = -skew_z_right(cB, z)
            na = R * na
            fa = R * fa
            cC = Ca
            cn = na + wp.cross(r, fa)
            cf = fa


@wp.func
def aba_forward_pass2(
    chains: StrandChains,
    strand: int,
    a_head: wp.spatial_vector,
    joint_q: wp.array(dtype=wp.quat),
    scratch: AbaScratch,
):
    """Second outward pass: body accelerations and joint accelerations ``qdd = D^-1 (u - U^T a')``."""
    S = chains.seg_per_strand
    a_ang_p = wp.spatial_top(a_head)
    a_lin_p = wp.spatial_bottom(a_head)
    for k in range(S):
        i = strand * S + k
        q = joint_q[i]
        r = joint_offset(chains, strand, k, i)
        c = scratch.c[i]
        a_ang = wp.quat_rotate_inv(q, a_ang_p) + wp.spatial_top(c)
        a_lin = wp.quat_rotate_inv(q, a_lin_p + wp.cross(a_ang_p, r)) + wp.spatial_bottom(c)
        qdd = scratch.Du[i] - scratch.DA[i] * a_ang - scratch.DB[i] * a_lin
        scratch.qdd[i] = qdd
        a_ang_p = a_ang + qdd
        a_lin_p = a_lin


@wp.func
def aba_strand(
    chains: StrandChains,
    strand: int,
    dt: float,
    implicit: int,
    head_rot: wp.quat,
    v_head: wp.spatial_vector,
    a_head: wp.spatial_vector,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    scratch: AbaScratch,
):
    """Joint accelerations of one strand [rad/s^2, child frame] into ``scratch.qdd``, by the three ABA passes."""
    aba_forward_pass1(chains, strand, head_rot, v_head, loads, joint_q, joint_qd, scratch)
    aba_backward_pass(chains, strand, dt, implicit, loads, joint_q, joint_qd, scratch)
    aba_forward_pass2(chains, strand, a_head, joint_q, scratch)


# Coulomb coefficient of the scenes' friction f in [0, 1): mu = f / (1 - f); f = 1 holds the vertex (mu infinite).
FULL_FRICTION = wp.constant(1.0)

#: Slip speed [m/s] up to which a body contact sticks (``contact_friction``); between it and twice it the law turns
#: continuously into Coulomb's sliding force.
STICK_SLIP = wp.constant(1.0e-3)

#: Shortest step [s] at which body contacts take the share law (``matched_friction``: a new contact sticks, as the
#: seed's velocity matching does) instead of friction continuous in the state (``contact_friction``): steps this long
#: do not resolve a contact that lasts a step or two. The boundary of the interactions' ``response = "auto"``
#: (``hairwarp.runner.AUTO_RESPONSE_DT``): the shipped 8 substeps take the continuous law, 7 and fewer the share law
#: (as do the frames taken again at ``links.break_step``). Limp hair (EI 1e-7, 64 segments) brushing the head at one
#: step a frame whipped to 4.6 m/s with the continuous law, to 2.3-3.4 m/s over seven gravity draws with it and a
#: contact's first step sticking, and to 2.2-2.3 m/s with the share law.
CONTINUOUS_FRICTION_STEP = wp.constant(1.0 / 220.0)

#: Time [s] a body contact's force, slip and the slip it took away are kept after a step in which it did not hold its
#: vertex, its force fading to none over it, for the friction of the vertex held again (continuous friction only;
#: the share law clears them at once, as it always did). Friction takes the last contact's normal force, and a
#: contact's first step had none: a vertex between two held ones on a curved head, held and let go by turns (a
#: third of its steps), slid there without friction, the more often the shorter the step (``long_hair``'s vertices
#: so held 42 times in 12 frames at 64 substeps, 292 times at 256). On the head collider alone runs a step apart
#: parted by 0.40 mm at 64-128 and 128-256 substeps; with the memory by 0.18 and 0.13 mm. A time, not a count of
#: steps, so that the friction converges as the step shrinks: the longest step that takes continuous friction.
CONTACT_MEMORY = wp.constant(CONTINUOUS_FRICTION_STEP)

#: Most solves of a strand's body contacts in a step (``body_contact_solve``): each one after the first leaves out
#: the vertices whose damper pulled in the one before, and takes back for good those released that then went in.
CONTACT_PASSES = wp.constant(4)

#: Largest growth rate [1/s] of a strand's velocities that the explicit velocity terms of ABA may add in a spinning
#: frame (``integrate_euler``). Symplectic Euler on the Coriolis term of a base spinning at Omega grows a velocity by
#: ``sqrt(1 + 4 h^2 Omega^2)`` per step, about ``2 h Omega^2`` per second: at 3 rev/s and 8 steps a frame that is
#: 3 /s, more than drag and damping take out, and free hair blew up within half a second. A step whose base turns
#: fast is taken in ``n`` equal parts, ``2 (h / n) Omega^2 <= GYRO_GROWTH``, at most MAX_SPLIT; the shipped turn
#: (3.3 rad/s at 4.2 ms: 0.09 /s) never splits.
GYRO_GROWTH = wp.constant(0.3)
MAX_SPLIT = wp.constant(16)

#: Largest turn [rad] of a segment relative to the base in one part of a step (``integrate_euler``). The velocity
#: products of ABA are explicit: a chain whose segments turn by about a radian in a step gains energy and blows up
#: (a limp strand, EI 1e-7, released at one step a frame: 61 m/s by frame 11). A step whose fastest segment would
#: turn farther is taken in ``ceil(h w / SPLIT_ROTATION)`` parts, at most MAX_SPLIT; the shipped scenes at their
#: substeps stay below it (a strand swinging at 10 rad/s turns 0.04 rad in 4.2 ms).
SPLIT_ROTATION = wp.constant(0.25)

#: Turn [rad] of a strand's fastest segment over one part of an ``implicit_joints`` step above which the part's
#: velocity terms are taken at its midpoint velocity (``integrate_euler``). Explicit velocity products turn a
#: velocity by ``h w`` and lengthen it by ``sqrt(1 + h^2 w^2)``: a growth of ``h w^2 / 2`` per second that splitting
#: the step does not stop (at SPLIT_ROTATION per part, a segment whipping at 300 rad/s grows by 4 % a millisecond).
#: Free hair on a head turning ten times the shipped speed blew up so at 8, 16 and 32 substeps, where 128 substeps
#: whip the tips at up to 11.2-11.5 m/s. The implicit midpoint rule keeps a turning velocity's length;
#: MIDPOINT_ITERATIONS fixed-point passes of ABA (each from the part's start velocity) approach it, and contract
#: while ``h w`` stays below 1, which the split keeps. The shipped scenes at their substeps stay below this turn
#: (``long_hair`` never reaches it).
MIDPOINT_ROTATION = wp.constant(0.05)
MIDPOINT_ITERATIONS = wp.constant(2)


#: Spin inertia that the response's solve (``interaction_response``, ``damper_solve``) gives each segment about its
#: own axis, in multiples of its joint's largest armature ``h C + h^2 K`` (``spin_hold``). No damper of the response
#: sees that spin (``point_damper_blocks``) and it weighs m r^2 / 2, but a curved strand rolling about its own axis
#: relieves the armature of the bend rates the dampers impose: a joint bent by theta is relieved of a bend rate d by a
#: roll of ``d / theta``, unbounded on a straight strand. Limp hair of 64 segments at one step a frame (``long_hair``,
#: EI 1e-7: an armature 14,000 times the spin inertia) rolled at up to 12 rad/s, 0.4 rad over the step, and the update
#: ``q exp(h dw)`` turned the roll into bending (a tip left at 2.2 m/s where the solve's own linearisation gave 0.43,
#: 3.8 m/s a frame later: the robustness grid's burst). With a spin inertia equal to the armature the roll is
#: ``theta d / (1 + theta^2)``, at most half the bend rate it relieves, so it turns a segment no farther than the step
#: bends it. Held a hundred times harder, the response of strands of few segments stiffened against their dampers:
#: limp hair of 8 segments at one step a frame burst in 3 of 17 draws (3.1-4.7 m/s; none without the hold, none with
#: it at 1).
SPIN_HOLD = wp.constant(1.0)


@wp.func
def spin_hold(chains: StrandChains, i: int, h: float, implicit: int):
    """The rotational block [kg m^2, segment frame] that holds segment ``i``'s spin about its own axis in the
    response's solve: ``SPIN_HOLD`` times the largest armature of its joint (zero without ``implicit``, where the
    spin has no armature to relieve and the solve leaves it alone)."""
    a = joint_armature(chains, i, h, implicit)
    return wp.diag(wp.vec3(0.0, 0.0, SPIN_HOLD * wp.max(a[0], wp.max(a[1], a[2]))))


@wp.func
def contact_friction(warm: wp.vec3, n: wp.vec3, slip: float, free_slip: float, friction: float, c: float):
    """A held vertex's friction in this step, from its last contact (``warm``, the force the collider put on it, and
    ``slip``, its speed over the surface at that step's end) and this step's ``free_slip`` (its speed over the
    surface before the contact acts, less what the contact took off it in its last step): the tangential force it
    starts from and the share ``beta`` of the contact damper ``c`` along the surface. Returns ``(W, beta)``.

    Every quantity is a continuous function of the state, so the solve makes no stick or slip decision that a small
    change of the data could flip. Sticking (``slip`` <= STICK_SLIP) it starts
    from the last tangential force, brought into the cone of the last normal force, and a damper answers the change
    with at most the rest of the cone: at the cone's edge nothing more holds the vertex back and it slides; at rest
    the carried force holds it exactly. Sliding (``slip`` >= 2 STICK_SLIP) no force is carried over and the damper
    gives Coulomb's force. In between the two blend. Each damper's force is measured at an estimate of the slip the
    step ends with: the larger of the last slip and ``free_slip``, this step's slip before the contact acts less
    what the contact took off it in its last step (what the loads it bears add to the slip over a step, which
    friction takes back when the vertex rests or slides steadily). So steady sliding takes exactly Coulomb's force,
    a slip that falls over the step a little less, and a vertex struck within the step stays near the cone. (The
    estimate took off what gravity alone adds over the step: a vertex that a strand hanging over the head pulls
    along the surface, its load the hanging part's weight, was taken to end the step as fast as its free step left
    it, its friction fell short of the cone by that ratio, and it crept: ``long_hair``'s tips on a still head at
    friction 0.6 crept 5-13 mm/s, faster the longer the step, and runs a step apart parted by 1.6-1.7 mm from 32 to
    256 substeps.) Every damper is at most ``c`` (the whole contact's, ``beta`` 1). The normal force is the last
    contact's: a contact's first step has no friction, and a changing normal force acts on friction a step late;
    both vanish with the step (at steps of CONTINUOUS_FRICTION_STEP and longer ``matched_friction`` holds
    instead)."""
    fn = wp.max(wp.dot(warm, n), 0.0)
    ft = warm - wp.dot(warm, n) * n
    if friction >= FULL_FRICTION:
        return ft, 1.0
    if friction <= 0.0:
        return wp.vec3(), 0.0
    limit = friction / (1.0 - friction) * fn
    if limit <= 0.0:
        return wp.vec3(), 0.0
    ftl = wp.length(ft)
    if ftl > limit:
        ft = (limit / ftl) * ft
        ftl = limit
    stick = wp.clamp(2.0 - slip / STICK_SLIP, 0.0, 1.0)
    # the rest of the cone, or Coulomb's force, at the slip the step ends with, estimated (at least STICK_SLIP)
    reference = c * wp.max(wp.max(slip, free_slip), STICK_SLIP)
    hold = (limit - ftl) / reference
    slide = limit / reference
    return stick * ft, wp.min(1.0, stick * hold + (1.0 - stick) * slide)


@wp.func
def contact_start(contacts: BodyContacts, vi: int, n: wp.vec3, free_slip: float, c: float, matched: int):
    """What a held vertex's damper starts from: the force it holds before the damper answers the step's motion
    (the last contact's normal force, fading over CONTACT_MEMORY after it, and the friction ``contact_friction``
    carries over), and the damper's share ``beta`` along the surface, given the vertex's ``free_slip`` [m/s], its
    speed over the surface before the contact acts; with ``matched`` the last step's whole force and the share it
    kept (``matched_friction``). Returns ``(force, beta)``."""
    warm = contacts.force[vi] * wp.max(1.0 - contacts.away[vi] / CONTACT_MEMORY, 0.0)
    if matched != 0:
        return warm, contacts.share[vi]
    carried, beta = contact_friction(warm, n, contacts.slip[vi], free_slip - contacts.removed[vi],
                                     contacts.friction[vi], c)
    return wp.max(wp.dot(warm, n), 0.0) * n + carried, beta


@wp.func
def matched_friction(force: wp.vec3, n: wp.vec3, share: float, friction: float):
    """Friction at steps of CONTINUOUS_FRICTION_STEP and longer, from the force a held vertex's solve found (with the
    damper's tangential share ``share``): outside the cone of its normal force it is cut back to it and the share
    scaled so that the next step's damper meets the cone; inside, the next step sticks (share 1), as does a new
    contact. A vertex that sticks at the cone's edge in one run and slides in another parts from it, which a step
    that does not resolve the contact cannot tell apart anyway; sticking at once damps limp hair brushing the head
    at one step a frame. Returns ``(force, next share)``."""
    fn = wp.dot(force, n)
    ft = force - fn * n
    ftl = wp.length(ft)
    if friction < FULL_FRICTION:
        limit = friction / (1.0 - friction) * fn
        if ftl > limit:
            return fn * n + (limit / ftl) * ft, share * limit / ftl
    return force, 1.0


@wp.func
def contact_projector(n: wp.vec3, beta: float):
    """``n n^T + beta (I - n n^T)``: the contact damper's directions, normal whole, tangential by ``beta``."""
    nn = wp.outer(n, n)
    return nn + beta * (wp.identity(n=3, dtype=float) - nn)


@wp.func
def shares_friction(step_dt: float) -> int:
    """1 where a step of ``step_dt`` seconds takes the share law's friction (``matched_friction``), 0 where it takes
    the continuous one: steps of CONTINUOUS_FRICTION_STEP and longer."""
    return wp.where(step_dt >= CONTINUOUS_FRICTION_STEP, 1, 0)


@wp.func
def forget_contact(contacts: BodyContacts, vi: int, h: float, matched: int):
    """A vertex no collider holds in this step: its last contact's slip, force and share kept for CONTACT_MEMORY
    (continuous friction), then none to carry over."""
    if contacts.away[vi] >= CONTACT_MEMORY:
        return  # cleared already: most vertices, far from every collider
    away = contacts.away[vi] + h
    if matched != 0 or away >= CONTACT_MEMORY:
        contacts.slip[vi] = 0.0
        contacts.share[vi] = 1.0
        contacts.force[vi] = wp.vec3()
        contacts.removed[vi] = 0.0
        away = CONTACT_MEMORY
    contacts.away[vi] = away


@wp.func
def release_contacts(contacts: BodyContacts, vbase: int, S: int, h: float, matched: int):
    """A strand none of whose vertices 1..S a collider holds in this step (``forget_contact``)."""
    for k in range(S):
        forget_contact(contacts, vbase + k + 1, h, matched)


@wp.func
def strand_touches(contacts: BodyContacts, vbase: int, S: int):
    """1 where one of the vertices 1..S of the strand whose root is vertex ``vbase`` has a body contact candidate in
    this step, else 0."""
    for k in range(S):
        if wp.length_sq(contacts.normal[vbase + k + 1]) > 0.0:
            return 1
    return 0


@wp.func
def held_force(contacts: BodyContacts, vi: int):
    """The mean force [N, world] the colliders put on vertex ``vi`` over this step's free step (zero where none held
    it): what an answer after it to the forces solved later (``kernels.sweeps.body_answer``) starts from. The mean,
    not the force of the free step's last part: a vertex held in the last of several parts alone was given that
    force over the part, and an answer over the whole step could take back more than it had (limp linked hair on
    ``long_hair``'s turn at 2 substeps whipped to 2.8 m/s, 0.73 without the answer)."""
    return contacts.step_force[vi]


@wp.func
def forget_held_force(contacts: BodyContacts, vbase: int, S: int):
    """Start the mean force over the step of the strand at ``vbase``'s vertices 1..S (``add_held_force``)."""
    for k in range(S):
        contacts.step_force[vbase + k + 1] = wp.vec3()


@wp.func
def add_held_force(contacts: BodyContacts, vbase: int, S: int, weight: float):
    """Add ``weight`` times the force each vertex 1..S of the strand at ``vbase`` took in the body contact solve just
    made (``contacts.force`` where it held the vertex: ``away`` 0) to its mean over the step (``step_force``)."""
    for k in range(S):
        vi = vbase + k + 1
        if contacts.away[vi] <= 0.0:
            contacts.step_force[vi] = contacts.step_force[vi] + weight * contacts.force[vi]


@wp.func(inline=True)
def body_contact_solve(
    chains: StrandChains,
    strand: int,
    dt: float,
    step_dt: float,
    implicit: int,
    X_head: wp.transform,
    V_head: wp.spatial_vector,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    contacts: BodyContacts,
    scratch: AbaScratch,
    dampers: InteractionResponse,
    with_dampers: int,
):
    """Body contact as part of the step: correct the free joint velocities ``joint_qd`` (in place) by impulses
    computed with the strand's own articulated inertia. With ``with_dampers`` the hair interactions' dampers
    (``InteractionResponse``) join the solve, each segment's spin held (``spin_hold``); ``interaction_response`` runs
    it so with ``contacts`` disabled, on the dampers alone.

    Each vertex whose free end-of-step velocity would take it into a collider's contact layer (deeper than its
    ``gap`` allows) gets a damper ``F = -c P (v - v_target)`` toward the surface point's velocity, normal whole
    and tangential by its friction share ``beta`` (``contact_projector``), taken at the end of the step:
    ``(M_eff + h c J^T P J) dw = -h c J^T P (J w* - v_target)``. That is an ABA with no velocity terms, the
    dampers' ``h c P`` as point inertias at the vertices and their forces as loads, ``M_eff`` the step's own
    (the implicit joint armature and interaction-spring masses included): one more inward and outward pass,
    O(S). ``h c`` is ``contacts.stiffness`` times the strand's mass, so a contact leaves at most
    ``1 / stiffness`` of the approach and the slip it stops; the backward-Euler damper against a static
    body only removes energy (MuJoCo's soft constraints work the same way, Todorov 2014). The force of the
    vertex's last step acts as well (warm start), so the damper answers only the change: a resting vertex's
    residual velocity goes to zero instead of to ``F / c``, and it neither sinks nor creeps.

    Friction is Coulomb's on the normal force of the vertex's last step, a continuous function of the state
    (``contact_friction``): sticking, the last tangential force (inside the cone) carried over and the damper
    answering the change, so static friction holds exactly; sliding, a damper that gives Coulomb's force at the last
    slip. Nothing is cut after the solve, so the velocities are those of the forces applied, and no stick or slip
    decision that a tiny change of the data could flip changes the trajectory: two runs whose gravity differs by
    1e-5 stay 0.10 mm RMS apart over 2 s (``long_hair`` at 32 substeps, head collider alone; 0.95 mm when the cone
    cut the solved force and a share kept from step to step switched between sticking and sliding). At steps of
    CONTINUOUS_FRICTION_STEP and longer, which do not resolve a contact's time, that share law holds instead
    (``matched_friction``). Writes ``contacts.slip``, ``contacts.share`` and ``contacts.force`` of every vertex.

    Contacts only push: the solve treats the held dampers as two-sided, so a pass in which a vertex's damper
    pulls it toward the body (its neighbours' stops carried it in) is undone and the strand solved again from
    its free velocities without that vertex; a vertex released that the solve without it takes into the body
    faster than its gap allows is taken back for good. At most ``CONTACT_PASSES`` solves (an active set; each
    one more inward and outward pass, on the strands that need it). Two-sided, such pulls sucked stiff strands
    onto the head and whipped their tails (4-5 m/s at 64 segments and 240 steps a second, 0.3 m/s now).
    """
    S = chains.seg_per_strand
    vbase = strand * (S + 1)
    h = dt
    mass = float(0.0)
    for k in range(S):
        mass += chains.seg_mass[strand * S + k]
    hc = contacts.stiffness * mass
    c = hc / h
    matched = shares_friction(step_dt)  # the whole step's, when it is taken in parts

    # An active set over the contacts (see the docstring): at most CONTACT_PASSES solves.
    for it in range(CONTACT_PASSES):
        any_pulled = int(0)
        # Outward: world frames and free tip velocities; which vertices the dampers hold, their inertias and loads.
        R = wp.transform_get_rotation(X_head)
        omega = wp.spatial_top(V_head)
        x = wp.transform_point(X_head, chains.strand_root_pos[strand])
        v = wp.spatial_bottom(V_head) + wp.cross(omega, x - wp.transform_get_translation(X_head))
        active = int(0)
        for k in range(S):
            i = strand * S + k
            vi = vbase + k + 1
            R = R * joint_q[i]
            omega = omega + wp.quat_rotate(R, joint_qd[i])
            d = wp.quat_rotate(R, wp.vec3(0.0, 0.0, -chains.seg_length[i]))
            v = v + wp.cross(omega, d)
            n = wp.vec3()
            held = float(0.0)
            target = float(0.0)
            beta = float(0.0)
            released = float(0.0)
            if it > 0:
                released = wp.spatial_bottom(scratch.c[i])[0]
            if contacts.enabled != 0:  # else only the dampers (``interaction_response`` without colliders)
                n = contacts.normal[vi]
            if wp.length_sq(n) > 0.0:
                target = -wp.max(contacts.gap[vi], 0.0) / step_dt  # a part of a step closes its share of the gap
                if released <= 0.0 and wp.dot(v - contacts.object_velocity[vi], n) < target:
                    held = 1.0
            M = wp.mat33()
            F = wp.vec3()
            free_slip = float(0.0)  # the vertex's speed over the surface before the contact acts
            if held > 0.0:
                active = 1
                free = v - contacts.object_velocity[vi]
                free_slip = wp.length(free - wp.dot(free, n) * n)
                start, beta = contact_start(contacts, vi, n, free_slip, c, matched)
                n_b = wp.quat_rotate_inv(R, n)
                P = contact_projector(n_b, beta)
                M = hc * P
                rel = wp.quat_rotate_inv(R, free) - target * n_b
                F = wp.quat_rotate_inv(R, start) - c * (P * rel)
            scratch.c[i] = wp.spatial_vector(held, target, beta, released, free_slip, 0.0)
            scratch.DB[i] = M
            tip = wp.vec3(0.0, 0.0, -chains.seg_length[i])
            scratch.p[i] = wp.spatial_vector(-wp.cross(tip, F), -F)
            if with_dampers != 0:
                if wp.trace(dampers.C[i]) > 0.0:
                    active = 1
        if active == 0:
            if contacts.enabled != 0:
                release_contacts(contacts, vbase, S, h, matched)
            return

        # Inward: articulated inertias with the dampers' point inertias, the loads' bias; no joint torque (the
        # springs acted in the free step; their implicit share is the armature).
        cA = wp.mat33()
        cB = wp.mat33()
        cC = wp.mat33()
        cn = wp.vec3()
        cf = wp.vec3()
        eye = wp.identity(n=3, dtype=float)
        zero = wp.mat33()
        for kk in range(S):
            k = S - 1 - kk
            i = strand * S + k
            extra = float(0.0)
            if loads.has_implicit_mass != 0:
                extra = loads.seg_implicit_mass[i]
            m = chains.seg_mass[i]
            L = chains.seg_length[i]
            A0, B0 = segment_inertia_blocks(m, L, chains.seg_inertia[i], extra)
            M = scratch.DB[i]
            Ac, Bc = inertia_shift_z(zero, zero, M, -L)
            A = A0 + Ac + cA
            B = B0 + Bc + cB
            C = (m + extra) * eye + M + cC
            p = scratch.p[i]
            n_ = wp.spatial_top(p) + cn
            f = wp.spatial_bottom(p) + cf
            if with_dampers != 0:
                A = A + dampers.A[i] + spin_hold(chains, i, dt, implicit)
                B = B + dampers.B[i]
                C = C + dampers.C[i]
                n_ = n_ - dampers.torque[i]
                f = f - dampers.force[i]
            Dinv, DA, DB, cA, cB, cC = factor_joint(chains, i, k, dt, implicit, joint_q, A, B, C)
            Du = -(Dinv * n_)
            scratch.DA[i] = DA
            scratch.DB[i] = DB
            scratch.Du[i] = Du
            if k > 0:
                cn, cf = bias_to_parent(chains, i, joint_q, A, B, Du, n_, f)

        # Outward: the velocity change dw = h qdd (the head's motion is prescribed: no change at the base), the
        # final tip velocities, and from them each damper's force, the normal force and the friction share.
        a_ang_p = wp.vec3()
        a_lin_p = wp.vec3()
        R = wp.transform_get_rotation(X_head)
        omega = wp.spatial_top(V_head)
        v = wp.spatial_bottom(V_head) + wp.cross(omega, x - wp.transform_get_translation(X_head))
        for k in range(S):
            i = strand * S + k
            vi = vbase + k + 1
            q = joint_q[i]
            r = joint_offset(chains, strand, k, i)
            a_ang = wp.quat_rotate_inv(q, a_ang_p)
            a_lin = wp.quat_rotate_inv(q, a_lin_p + wp.cross(a_ang_p, r))
            qdd = scratch.Du[i] - scratch.DA[i] * a_ang - scratch.DB[i] * a_lin
            a_ang_p = a_ang + qdd
            a_lin_p = a_lin
            w_free = joint_qd[i]
            w = w_free + h * qdd
            joint_qd[i] = w
            R = R * q
            omega = omega + wp.quat_rotate(R, w)
            v = v + wp.cross(omega, wp.quat_rotate(R, wp.vec3(0.0, 0.0, -chains.seg_length[i])))
            flags = scratch.c[i]
            slip = float(0.0)
            share = float(1.0)
            removed = float(0.0)
            force = wp.vec3()
            state = wp.spatial_bottom(flags)[0]  # 0 may be released, 1 released, -1 taken back for good
            if wp.spatial_top(flags)[0] > 0.0:
                n = contacts.normal[vi]
                target = wp.spatial_top(flags)[1]
                rel = v - contacts.object_velocity[vi] - target * n
                # the force it started from (the free velocity moves only the share), and the damper's share as
                # the solve had it
                start, unused = contact_start(contacts, vi, n, 0.0, c, matched)
                beta = wp.spatial_top(flags)[2]
                force = start - c * (contact_projector(n, beta) * rel)
                fn = wp.dot(force, n)
                slip = wp.length(rel - wp.dot(rel, n) * n)
                removed = wp.max(wp.spatial_bottom(flags)[1] - slip, 0.0)
                if fn <= 0.0:
                    force = wp.vec3()  # it pulled: the vertex leaves (it will not be held from its free velocity)
                    slip = 0.0
                    removed = 0.0
                    if state == 0.0:
                        state = 1.0
                        any_pulled = 1
                elif matched != 0:
                    force, share = matched_friction(force, n, beta, contacts.friction[vi])
            elif state > 0.0:
                # released in an earlier pass: if the solve without it now takes it into the body faster than its
                # gap allows, it is held again, for good (no vertex goes back and forth)
                n = contacts.normal[vi]
                if wp.dot(v - contacts.object_velocity[vi], n) < wp.spatial_top(flags)[1]:
                    state = -1.0
                    any_pulled = 1
            # kept for after the passes: the contacts' force, slip and the slip they took away, the vertices
            # released, the free velocity
            top = wp.spatial_top(flags)
            scratch.c[i] = wp.spatial_vector(top[0], top[1], top[2], state, slip, share)
            scratch.Du[i] = force
            scratch.p[i] = wp.spatial_vector(w_free, wp.vec3(removed, 0.0, 0.0))
        if any_pulled == 0:
            break
        if it < CONTACT_PASSES - 1:
            # A damper pulled the vertex toward the body: contacts push only. Solve again from the free velocities
            # without the vertices that pulled (and with those that, released, went in).
            for k in range(S):
                joint_qd[strand * S + k] = wp.spatial_top(scratch.p[strand * S + k])
    if contacts.enabled != 0:
        for k in range(S):
            i = strand * S + k
            vi = vbase + k + 1
            force = scratch.Du[i]
            if wp.length_sq(force) > 0.0:
                contacts.slip[vi] = wp.spatial_bottom(scratch.c[i])[1]
                contacts.share[vi] = wp.spatial_bottom(scratch.c[i])[2]
                contacts.force[vi] = force
                contacts.removed[vi] = wp.spatial_bottom(scratch.p[i])[0]
                contacts.away[vi] = 0.0
            else:
                forget_contact(contacts, vi, h, matched)


@wp.func
def strand_turn_rate(chains: StrandChains, strand: int, joint_q: wp.array(dtype=wp.quat),
                     joint_qd: wp.array(dtype=wp.vec3)):
    """Largest angular speed [rad/s] of a segment of the strand relative to its base."""
    R = wp.quat_identity()
    omega = wp.vec3()
    fastest = float(0.0)
    for k in range(chains.seg_per_strand):
        i = strand * chains.seg_per_strand + k
        R = R * joint_q[i]
        omega = omega + wp.quat_rotate(R, joint_qd[i])
        fastest = wp.max(fastest, wp.length(omega))
    return fastest


@wp.func
def bend_rate(w: wp.vec3):
    """The bending part [rad/s] of a joint velocity (child frame, the segment along -z): the fault checks leave out
    the twist about the segment's own axis. That axis carries a thin segment's smallest inertia (m r^2 / 2, 1/30
    of the bending one at the shipped radius): contacts holding a limp strand at two vertices at one step a frame
    set it twisting at 34 rad/s with 6e-7 J, moving no vertex."""
    return wp.sqrt(w[0] * w[0] + w[1] * w[1])


@wp.func
def flag_joint(w: wp.vec3, w_start: wp.vec3, q: wp.quat, dt: float, max_rotation: float,
               fault: wp.array(dtype=wp.int32)):
    """Set fault bits for a non-finite joint state, or a joint that the free dynamics sped up (from ``w_start``)
    until it bends too far in one step; speed that a contact gave it is the contact's (``flag_contact_response``)."""
    if not (wp.isfinite(w) and wp.isfinite(q)):
        wp.atomic_or(fault, 0, int(Fault.NONFINITE_DYNAMICS))
    elif bend_rate(w) * dt > max_rotation and bend_rate(w) > bend_rate(w_start):
        wp.atomic_or(fault, 0, int(Fault.JOINT_SPEED))


@wp.func
def flag_contact_response(w_free: wp.vec3, w: wp.vec3, dt: float, max_rotation: float,
                          fault: wp.array(dtype=wp.int32)):
    """Set collision fault bits when the body contact response, not the free dynamics, left the bounds: a
    non-finite velocity, or a contact that sped the joint up until it bends more than ``max_rotation`` in the step.
    Returns 1 when it set a bit."""
    if wp.isfinite(w_free):
        if not wp.isfinite(w):
            wp.atomic_or(fault, 0, int(Fault.NONFINITE_COLLISION))
            return 1
        elif bend_rate(w) * dt > max_rotation and bend_rate(w) > bend_rate(w_free):
            wp.atomic_or(fault, 0, int(Fault.COLLISION_SPEED))
            return 1
    return 0


@wp.kernel
def aba_accelerations(
    # Model:
    chains: StrandChains,
    # Control:
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # In:
    implicit: int,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    # Out:
    scratch: AbaScratch,
):
    """One thread per strand: joint accelerations only, into ``scratch.qdd`` [rad/s^2, child frame].

    With ``implicit`` != 0 it solves ``(M + hC + h^2 K) qdd = tau - bias`` as ``implicit_joints`` does.
    """
    strand = wp.tid()
    b = strand * bases.per_strand
    v_head, a_head = head_body_motion(bases.xform[b], bases.velocity[b], bases.acceleration[b], chains.gravity)
    aba_strand(chains, strand, dt[0], implicit, wp.transform_get_rotation(bases.xform[b]), v_head, a_head, loads,
               joint_q, joint_qd, scratch)


@wp.kernel
def integrate_euler(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    max_rotation: float,
    # Control:
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # State in:
    implicit: int,
    loads: SegmentLoads,
    joint_q_in: wp.array(dtype=wp.quat),
    joint_qd_in: wp.array(dtype=wp.vec3),
    fault_in: wp.array(dtype=wp.int32),
    contacts: BodyContacts,
    dampers: InteractionResponse,
    # Scratch:
    scratch: AbaScratch,
    # Out:
    joint_q_out: wp.array(dtype=wp.quat),
    joint_qd_out: wp.array(dtype=wp.vec3),
    seg_xform_out: wp.array(dtype=wp.transform),
    vertex_positions_out: wp.array(dtype=wp.vec3),
    vertex_velocities_out: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand: ABA, the body contacts' impulses (``body_contact_solve``, with ``contacts``
    enabled), then ``q <- q exp(h w)``: symplectic Euler ``w += h qdd`` with the springs explicit, or with
    ``implicit`` != 0 the ``implicit_joints`` integrator (joint springs and damping at the end of the step).
    A step whose base spins fast (``GYRO_GROWTH``) or whose segments turn fast (``SPLIT_ROTATION``) is taken in
    equal parts, each with its own body contact solve; with ``implicit``, a part whose segments still turn fast
    takes its velocity terms at its midpoint velocity (``MIDPOINT_ROTATION``).
    Writes ``joint_q_out``, ``joint_qd_out`` [rad/s, child frame], the new state's world frames and
    vertices (forward kinematics, fused), and fault bits.
    """
    strand = tid_offset + wp.tid()
    if strand == 0:
        # faults are sticky: the new state starts from the old state's bits (a superset of its own)
        wp.atomic_or(fault, 0, fault_in[0])
    S = chains.seg_per_strand
    h = dt[0]
    b = strand * bases.per_strand
    X_base = bases.xform[b]
    V_base = bases.velocity[b]
    v_head, a_head = head_body_motion(X_base, V_base, bases.acceleration[b], chains.gravity)
    head_rot = wp.transform_get_rotation(X_base)
    # A base that spins fast (GYRO_GROWTH) or segments that turn fast (SPLIT_ROTATION): the step in parts, each an
    # ABA, the body contacts and an update, the loads and the base's motion held over the step. Each part's length
    # comes from the velocities at its start, after the last part's contacts, so a strand that a contact sets
    # spinning takes the rest of the step in smaller parts.
    spin_rate = 2.0 * wp.length_sq(wp.spatial_top(V_base)) / GYRO_GROWTH  # parts per second the base asks for
    for k in range(S):
        i = strand * S + k
        joint_qd_out[i] = joint_qd_in[i]
        joint_q_out[i] = joint_q_in[i]
    vbase = strand * (S + 1)
    # Most strands have no body contact candidate in a step (the mohawk in motion: 429 of 2,219): they skip the
    # contact solve's passes (its velocities would be the free ones).
    touching = int(0)
    # the contact force's mean over the step, kept for the bodies' answer after it (``held_force``), which only steps
    # of the share law's length take
    keeps_mean = int(0)
    if contacts.enabled != 0:
        touching = strand_touches(contacts, vbase, S)
        if touching != 0 and shares_friction(h) != 0:
            keeps_mean = 1
            forget_held_force(contacts, vbase, S)
        if touching == 0:
            release_contacts(contacts, vbase, S, h, shares_friction(h))
    t_left = h
    part = int(0)
    collided = int(0)
    while t_left > 0.0:
        fastest = strand_turn_rate(chains, strand, joint_q_out, joint_qd_out)
        turn_rate = fastest / SPLIT_ROTATION
        parts = wp.max(wp.min(int(wp.ceil(t_left * wp.max(spin_rate, turn_rate))), MAX_SPLIT - part), 1)
        for k in range(S):
            vertex_velocities_out[vbase + k] = joint_qd_out[strand * S + k]  # the part's start, for a retry
        hs = float(0.0)
        retry = int(1)
        while retry != 0:
            retry = 0
            hs = t_left
            if parts > 1:
                hs = t_left / float(parts)
            # free velocities: ABA at the part's start (scratch.qdd keeps them for the fault check)
            aba_strand(chains, strand, hs, implicit, head_rot, v_head, a_head, loads, joint_q_out, joint_qd_out,
                       scratch)
            for k in range(S):
                i = strand * S + k
                w = joint_qd_out[i] + hs * scratch.qdd[i]
                joint_qd_out[i] = w
                scratch.qdd[i] = w
            if implicit != 0 and fastest * hs > MIDPOINT_ROTATION:
                # fast turning: the velocity terms at the part's midpoint velocity (MIDPOINT_ROTATION)
                for _it in range(MIDPOINT_ITERATIONS):
                    for k in range(S):
                        i = strand * S + k
                        joint_qd_out[i] = 0.5 * (vertex_velocities_out[vbase + k] + scratch.qdd[i])
                    aba_strand(chains, strand, hs, implicit, head_rot, v_head, a_head, loads, joint_q_out,
                               joint_qd_out, scratch)
                    for k in range(S):
                        i = strand * S + k
                        w = vertex_velocities_out[vbase + k] + hs * scratch.qdd[i]
                        joint_qd_out[i] = w
                        scratch.qdd[i] = w
            # the body contacts' impulses, linearised at the part's start
            if contacts.enabled != 0:
                if touching != 0:
                    body_contact_solve(chains, strand, hs, h, implicit, X_base, V_base, loads, joint_q_out,
                                       joint_qd_out, contacts, scratch, dampers, 0)
                # contacts that set segments turning fast: the part again, shorter, so the geometry they were
                # linearised at still holds (a strand without candidates is checked the same way: its free step
                # alone may turn faster than the part's start said, and a wind-blown strand relies on the split)
                turn_rate = strand_turn_rate(chains, strand, joint_q_out, joint_qd_out) / SPLIT_ROTATION
                needed = wp.min(int(wp.ceil(t_left * turn_rate)), MAX_SPLIT - part)
                if needed > parts:
                    parts = needed
                    retry = 1
                    for k in range(S):
                        joint_qd_out[strand * S + k] = vertex_velocities_out[vbase + k]
        if keeps_mean != 0:
            add_held_force(contacts, vbase, S, hs / h)
        t_left = t_left - hs
        part += 1
        for k in range(S):
            i = strand * S + k
            w = joint_qd_out[i]
            if collided == 0:  # after a contact's fault the speeds it gave are its own, not the dynamics'
                flag_joint(scratch.qdd[i], vertex_velocities_out[vbase + k], joint_q_out[i], hs, max_rotation, fault)
            if touching != 0:
                collided = collided | flag_contact_response(scratch.qdd[i], w, hs, max_rotation, fault)
            q = wp.normalize(joint_q_out[i] * quat_exp(hs * w))
            if not wp.isfinite(q):
                wp.atomic_or(fault, 0, int(Fault.NONFINITE_DYNAMICS))
            joint_q_out[i] = q
    fk_strand(chains, strand, X_base, V_base, joint_q_out, joint_qd_out, seg_xform_out, vertex_positions_out,
              vertex_velocities_out)


#: Largest bend [rad] that the response after the free step (``interaction_response``) may add to a joint over a
#: step: half a turn is no motion a step resolves. ``max_rotation_per_step`` bounds the speed the free dynamics
#: reach; this bounds the response's own change, which stops fast pairs and may rightly be large at one step a
#: frame.
RESPONSE_ROTATION = wp.constant(3.14159)


@wp.func
def point_damper_blocks(r: wp.vec3, M: wp.mat33):
    """Blocks (A, B) of a point inertia ``M`` at ``r`` (a segment's frame) about the segment's origin, its C block
    being ``M``, without the spin about the segment's own axis (local z): the vertex velocities that measure the
    dampers' velocities do not show that spin, and a thin segment's spin inertia is tiny, so a damper that could
    turn it would set it spinning unseen (``kernels.links`` leaves it out of the links' torque for the same
    reason)."""
    rx = skew(r)
    return spin_free_rotation(-(rx * M * rx)), spin_free_coupling(rx * M)


@wp.func
def spin_free_rotation(A: wp.mat33):
    """``A`` without its row and column of the spin about the segment's axis (local z; ``point_damper_blocks``)."""
    return wp.mat33(A[0, 0], A[0, 1], 0.0, A[1, 0], A[1, 1], 0.0, 0.0, 0.0, 0.0)


@wp.func
def spin_free_coupling(B: wp.mat33):
    """``B`` without its row of the spin about the segment's axis (local z; ``point_damper_blocks``)."""
    return wp.mat33(B[0, 0], B[0, 1], B[0, 2], B[1, 0], B[1, 1], B[1, 2], 0.0, 0.0, 0.0)


@wp.func
def add_damper(dampers: InteractionResponse, seg: int, A: wp.mat33, B: wp.mat33, C: wp.mat33, force: wp.vec3,
               torque: wp.vec3):
    """Add summed damper blocks, forces and torques (``point_damper_blocks``, ``spin_free_torque``) to segment
    ``seg``'s ``InteractionResponse``; each segment is written by its own thread only."""
    dampers.A[seg] = dampers.A[seg] + A
    dampers.B[seg] = dampers.B[seg] + B
    dampers.C[seg] = dampers.C[seg] + C
    dampers.force[seg] = dampers.force[seg] + force
    dampers.torque[seg] = dampers.torque[seg] + torque


@wp.func
def spin_free_torque(r: wp.vec3, f: wp.vec3):
    """``r x f`` (a segment's frame) without its component about the segment's own axis (see
    ``point_damper_blocks``)."""
    t = wp.cross(r, f)
    return wp.vec3(t[0], t[1], 0.0)


# Largest ratio of a pair's summed inverse masses to one end's (``split_factor``): an end this much heavier than
# the other barely moves, and a larger point inertia only costs float32 digits in the solve.
MAX_SPLIT_FACTOR = wp.constant(1.0e3)


@wp.func
def articulated_inverse_mass(dampers: InteractionResponse, seg: int, xf: wp.transform, p: wp.vec3, e: wp.vec3):
    """Inverse mass [1/kg] that the world point ``p`` of segment ``seg`` (frame ``xf``) shows along the world unit
    vector ``e``, its strand free to answer: ``f^T Phi f`` with ``f = (r x e, e)`` the spatial force of a unit
    force at the point, ``Phi`` the segment's inverse inertia (``strand_inverse_inertia``)."""
    R = wp.transform_get_rotation(xf)
    r = wp.quat_rotate_inv(R, p - wp.transform_get_translation(xf))
    el = wp.quat_rotate_inv(R, e)
    t = wp.cross(r, el)
    return wp.dot(t, dampers.phi_a[seg] * t) + 2.0 * wp.dot(t, dampers.phi_b[seg] * el) + wp.dot(
        el, dampers.phi_c[seg] * el)


@wp.func
def split_factor(own: float, other: float):
    """How much of a pair's damper one end takes as its point inertia, ``(W_own + W_other) / W_own`` (its inverse
    mass ``own``, the other end's ``other``), so that each end, solved alone with its own strand, gets the pair's
    backward-Euler force.

    Two ends of effective masses m_a, m_b joined by a damper ``P`` (the pair's force ``F - P u'``, ``u'`` their
    relative velocity at the step's end) are solved exactly, one at a time, by a damper ``P (m_a + m_b) / m_b`` on
    a toward their centre-of-mass velocity (and the same on b with the masses swapped): the force on the free
    velocities is the pair's own, ``F - P u``, and only the point inertia depends on the masses. With equal masses
    that is ``2 P`` toward the mean. With unequal ones ``2 P`` is wrong both ways: it shoves the heavy end (a point
    near a strand's root, where the whole strand turns on a short lever) with the force the light end never takes
    back, which put energy into limp hair at one step a frame (strand-pair ends' masses differ by orders of
    magnitude there), and it stiffens the light one."""
    if own <= 0.0:
        return MAX_SPLIT_FACTOR
    return wp.clamp((own + other) / own, 1.0, MAX_SPLIT_FACTOR)


# A pair whose damper over the step, h P, holds the lighter end's inverse mass W to at least this share of its
# motion (h P W >= SPLIT_STIFFNESS^-1) shares that end's mass among the end's pairs in full (``shared_inverse_mass``).
SPLIT_STIFFNESS = wp.constant(10.0)


@wp.func
def shared_inverse_mass(own: float, other: float, pairs: float, stiffness: float):
    """The other end's inverse mass as one end's pair takes it, the other end's segment having ``pairs`` pairs and
    this pair's damper over the step being ``stiffness`` (``h P`` along its force) [kg]: ``other`` times a share of
    the pairs that grows from none, for ends of equal mass or a pair that hardly moves the other end in a step, to
    all, for an other end twice as light as this one or lighter that the pair's damper holds (mass splitting
    where it is needed).

    Solved one strand at a time, a heavy end (a point near a root, which turns its whole strand on a short lever)
    tied to a light one takes the pair's force that the light end, held by its other pairs too, can only take once:
    every heavy neighbour of a light segment shoved it with the whole force, which put energy into limp hair at
    one step a frame. Seen through its share of the light end's mass, each heavy end takes its share. Between
    ends of like masses, or where the pair is soft over the step, the light end takes every force it is given and
    the split is not needed; split there, a dense lattice of links answers a stretch by a fraction of what it is
    (at 2 steps a frame ``fast_turn`` broke 43 links instead of 3; the Ratboy mohawk at its 8 substeps 120 instead
    of 44)."""
    blend = float(0.0)
    if own > 0.0:
        blend = wp.clamp(other / own - 1.0, 0.0, 1.0) * wp.clamp(SPLIT_STIFFNESS * stiffness * other - 1.0, 0.0, 1.0)
    return other * (1.0 + (wp.max(pairs, 1.0) - 1.0) * blend)


@wp.kernel
def strand_inverse_inertia(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    # Control:
    dt: wp.array(dtype=float),
    # State in:
    implicit: int,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    # Scratch: the hair contacts' entries per segment (``kernels.contacts.contact_segment_lists``), or one element
    seg_entry_start: wp.array(dtype=wp.int32),
    # Out: ``phi_a``, ``phi_b``, ``phi_c`` (the inward pass keeps ``D^-1``, ``D^-1 A``, ``D^-1 B`` there meanwhile)
    dampers: InteractionResponse,
):
    """One thread per strand: each segment's inverse spatial inertia ``Phi`` within its strand [blocks in its own
    frame about its origin], the head's motion prescribed: the spatial acceleration of the segment under a spatial
    force on it alone is ``Phi f``. It is what the response solve's matrix, without the dampers, shows at each
    segment: the implicit joint armature and the interaction springs' masses are in it.

    The articulated inertias come from the inward pass (as ``aba_backward_pass``, inertias only); then outward,
    ``Phi_i = Psi^T X Phi_p X^T Psi + S D^-1 S^T`` with ``Psi = 1 - U D^-1 S^T`` and ``Phi`` of the head zero
    (the recursion of the operational-space inverse inertia, Featherstone, RBDA section 7.3 and Wensing et al. 2012):
    O(S), one more inward and outward pass. A force on the child moves the parent through the joint by what the
    child's articulated inertia passes on, ``X^T Psi f``; the child's acceleration is the parent's carried over
    (projected by ``Psi^T``) plus the joint's own answer ``S D^-1 S^T f``.

    Only the hair contacts' split reads it, at the segments of the stored contacts: where ``seg_entry_start`` holds
    the segments' lists of them (on the CPU), a strand none of whose segments has one is left as it was (the
    mohawk in motion: 154 of 444 strands)."""
    strand = tid_offset + wp.tid()
    S = chains.seg_per_strand
    if seg_entry_start.shape[0] > (strand + 1) * S:
        if seg_entry_start[(strand + 1) * S] == seg_entry_start[strand * S]:
            return
    h = dt[0]
    cA = wp.mat33()
    cB = wp.mat33()
    cC = wp.mat33()
    eye = wp.identity(n=3, dtype=float)
    for kk in range(S):
        k = S - 1 - kk
        i = strand * S + k
        A, B, C = segment_articulated_blocks(chains, loads, i, cA, cB, cC)
        Dinv, DA, DB, cA, cB, cC = factor_joint(chains, i, k, h, implicit, joint_q, A, B, C)
        dampers.phi_a[i] = Dinv
        dampers.phi_b[i] = DA
        dampers.phi_c[i] = DB
    Pa = wp.mat33()
    Pb = wp.mat33()
    Pc = wp.mat33()
    for k in range(S):
        i = strand * S + k
        Dinv = dampers.phi_a[i]
        E = eye - wp.transpose(dampers.phi_b[i])  # I - A D^-1
        G = -wp.transpose(dampers.phi_c[i])  # -B^T D^-1
        if k > 0:
            # the parent's Phi in this segment's frame: X Phi X^T, X = [[R^T, 0], [-R^T [r]x, R^T]], r the joint's
            # place in the parent
            Rm = wp.quat_to_matrix(joint_q[i])
            Rt = wp.transpose(Rm)
            rx = skew(wp.vec3(0.0, 0.0, -chains.seg_length[i - 1]))
            Q = Pb + Pa * rx
            P22 = Rt * (Pc + wp.transpose(Pb) * rx - rx * Q) * Rm
            P12 = Rt * Q * Rm
            P11 = Rt * Pa * Rm
            T2 = wp.transpose(P12) * E + P22 * G
            Pa = wp.transpose(E) * (P11 * E + P12 * G) + wp.transpose(G) * T2 + Dinv
            Pb = wp.transpose(E) * P12 + wp.transpose(G) * P22
            Pc = P22
        else:
            Pa = Dinv
        dampers.phi_a[i] = Pa
        dampers.phi_b[i] = Pb
        dampers.phi_c[i] = Pc


@wp.func
def damper_solve(
    chains: StrandChains,
    strand: int,
    h: float,
    implicit: int,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    scratch: AbaScratch,
    dampers: InteractionResponse,
    factors: DamperFactors,
    reuse: int,
    keep: int,
):
    """``body_contact_solve`` without body contacts, the same bits: ``(M_eff + h J^T C J) dw = J^T F`` with the
    dampers' point inertias and forces and the segments' spins held (``spin_hold``), ``joint_qd`` corrected in place.
    With ``keep`` its inward pass keeps the matrix's factors (``factors``); with ``reuse`` it reads them instead, for
    the same matrix with other forces (O(S) vector work, no 3 x 3 inverse or block product)."""
    S = chains.seg_per_strand
    cA = wp.mat33()
    cB = wp.mat33()
    cC = wp.mat33()
    cn = wp.vec3()
    cf = wp.vec3()
    for kk in range(S):
        k = S - 1 - kk
        i = strand * S + k
        n_ = cn - dampers.torque[i]
        f = cf - dampers.force[i]
        A = wp.mat33()
        B = wp.mat33()
        Dinv = wp.mat33()
        if reuse == 0:
            A, B, C = segment_articulated_blocks(chains, loads, i, cA, cB, cC)
            A = A + dampers.A[i] + spin_hold(chains, i, h, implicit)
            B = B + dampers.B[i]
            C = C + dampers.C[i]
            Dinv, DA, DB, cA, cB, cC = factor_joint(chains, i, k, h, implicit, joint_q, A, B, C)
            scratch.DA[i] = DA
            scratch.DB[i] = DB
            if keep != 0:
                factors.Dinv[i] = Dinv
                factors.A[i] = A
                factors.B[i] = B
                factors.DA[i] = DA
                factors.DB[i] = DB
        else:
            Dinv = factors.Dinv[i]
            A = factors.A[i]
            B = factors.B[i]
        Du = -(Dinv * n_)
        scratch.Du[i] = Du
        if k > 0:
            cn, cf = bias_to_parent(chains, i, joint_q, A, B, Du, n_, f)
    a_ang_p = wp.vec3()
    a_lin_p = wp.vec3()
    for k in range(S):
        i = strand * S + k
        q = joint_q[i]
        r = joint_offset(chains, strand, k, i)
        a_ang = wp.quat_rotate_inv(q, a_ang_p)
        a_lin = wp.quat_rotate_inv(q, a_lin_p + wp.cross(a_ang_p, r))
        qdd = wp.vec3()
        if reuse == 0:
            qdd = scratch.Du[i] - scratch.DA[i] * a_ang - scratch.DB[i] * a_lin
        else:
            qdd = scratch.Du[i] - factors.DA[i] * a_ang - factors.DB[i] * a_lin
        a_ang_p = a_ang + qdd
        a_lin_p = a_lin
        joint_qd[i] = joint_qd[i] + h * qdd


@wp.func
def finish_response(
    chains: StrandChains,
    strand: int,
    X_base: wp.transform,
    V_base: wp.spatial_vector,
    h: float,
    scratch: AbaScratch,
    joint_q_out: wp.array(dtype=wp.quat),
    joint_qd_out: wp.array(dtype=wp.vec3),
    seg_xform_out: wp.array(dtype=wp.transform),
    vertex_positions_out: wp.array(dtype=wp.vec3),
    vertex_velocities_out: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
    always_fk: int,
):
    """The end of a strand's response (``interaction_response``, ``kernels.sweeps.link_sweep``):
    ``q <- q exp(h dw)`` with ``dw`` the answer's change of the free velocities
    (kept in ``scratch.qdd``), the response's fault checks, and the forward kinematics of the strand."""
    S = chains.seg_per_strand
    changed = always_fk
    for k in range(S):
        i = strand * S + k
        w_free = scratch.qdd[i]
        w = joint_qd_out[i]
        dw = w - w_free
        if wp.length_sq(dw) > 0.0:
            changed = 1
            q_new = wp.normalize(joint_q_out[i] * quat_exp(h * dw))
            if not (wp.isfinite(w) and wp.isfinite(q_new)):
                wp.atomic_or(fault, 0, int(Fault.INTERACTION_RESPONSE))
            elif bend_rate(dw) * h > RESPONSE_ROTATION:
                # the response's own change bends the joint by more than the bound in the step (a stiff contact
                # that stops a joint may leave its outboard joints fast: that is the free motion's, not this)
                wp.atomic_or(fault, 0, int(Fault.INTERACTION_RESPONSE))
            joint_q_out[i] = q_new
    if changed != 0:
        fk_strand(chains, strand, X_base, V_base, joint_q_out, joint_qd_out, seg_xform_out, vertex_positions_out,
                  vertex_velocities_out)


@wp.kernel
def interaction_response(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    max_rotation: float,
    # Control:
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # State in:
    implicit: int,
    loads: SegmentLoads,
    joint_q_in: wp.array(dtype=wp.quat),
    dampers: InteractionResponse,
    contacts: BodyContacts,
    # Scratch:
    scratch: AbaScratch,
    # In and out: the free step's result, corrected
    joint_q_out: wp.array(dtype=wp.quat),
    joint_qd_out: wp.array(dtype=wp.vec3),
    seg_xform_out: wp.array(dtype=wp.transform),
    vertex_positions_out: wp.array(dtype=wp.vec3),
    vertex_velocities_out: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand: the links' and hair contacts' forces over the step, solved after the free step with the
    strand's own inertia.

    The free step took none of them. A pair's backward-Euler force over the step is ``k d - D v_n'`` for a contact
    (``D = h k + c``) and ``k l - P u'`` for a link (``P = h k I + c n n^T``), with the pair's end-of-step velocity;
    each strand takes its side as a damper ``s D`` (``s P``) toward the pair's centre-of-mass velocity from the free
    step (Jacobi between strands; ``s`` the side's ``split_factor``, 2 for ends of equal mass), which acts on the
    pair's relative motion only: hair that
    the head carries along is carried whatever the stiffness, where the semi-implicit mass resisted every
    acceleration (at one step a frame it made a third of ``fast_turn``'s segments a hundred times heavier).
    ``(M_eff + h J^T C J) dw = J^T F`` is ``body_contact_solve`` with the dampers' point inertias and forces per
    segment (``InteractionResponse``) added, ``contacts`` disabled: one inward and one outward pass, ``M_eff`` the
    step's own (implicit joint armature included) with each segment's spin held (``SPIN_HOLD``), linearised at the
    step's start. Then ``w += dw``,
    ``q <- q exp(h dw)`` and the forward kinematics of the corrected strand; the push-out after the step keeps the
    strands out of the bodies. (Holding the body contacts of the free step in this solve too cost one step a frame
    its stability: ``long_hair_shoulders`` faulted.) With links, Gauss-Seidel sweeps over the strands solve links
    and hair contacts instead (``kernels.sweeps``).
    """
    strand = tid_offset + wp.tid()
    S = chains.seg_per_strand
    h = dt[0]
    b = strand * bases.per_strand
    X_base = bases.xform[b]
    V_base = bases.velocity[b]
    for k in range(S):
        scratch.qdd[strand * S + k] = joint_qd_out[strand * S + k]  # the free velocities, for dw
    body_contact_solve(chains, strand, h, h, implicit, X_base, V_base, loads, joint_q_in, joint_qd_out, contacts,
                       scratch, dampers, 1)
    finish_response(chains, strand, X_base, V_base, h, scratch, joint_q_out, joint_qd_out, seg_xform_out,
                    vertex_positions_out, vertex_velocities_out, fault, 0)


@wp.kernel
def integrate_rk4(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    max_rotation: float,
    # Control:
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # State in:
    loads: SegmentLoads,
    joint_q_in: wp.array(dtype=wp.quat),
    joint_qd_in: wp.array(dtype=wp.vec3),
    fault_in: wp.array(dtype=wp.int32),
    contacts: BodyContacts,
    dampers: InteractionResponse,
    # Scratch:
    scratch: AbaScratch,
    rk_q: wp.array(dtype=wp.quat),
    rk_w: wp.array(dtype=wp.vec3),
    rk_dq: wp.array(dtype=wp.vec3),
    rk_dw: wp.array(dtype=wp.vec3),
    # Out:
    joint_q_out: wp.array(dtype=wp.quat),
    joint_qd_out: wp.array(dtype=wp.vec3),
    seg_xform_out: wp.array(dtype=wp.transform),
    vertex_positions_out: wp.array(dtype=wp.vec3),
    vertex_velocities_out: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand: classical RK4 on the Lie group, as MuJoCo's ``RK4`` does.

    Stage configurations are ``q0 exp(c h w)``; the update is ``q0 exp(h/6 (w1 + 2w2 + 2w3 + w4))``.
    External loads stay fixed over the step; body contacts act after it (``body_contact_solve``). Writes
    ``joint_q_out``, ``joint_qd_out``, the new state's world frames and vertices, and fault bits.
    """
    strand = tid_offset + wp.tid()
    if strand == 0:
        # faults are sticky: the new state starts from the old state's bits (a superset of its own)
        wp.atomic_or(fault, 0, fault_in[0])
    S = chains.seg_per_strand
    h = dt[0]
    b = strand * bases.per_strand
    X_base = bases.xform[b]
    V_base = bases.velocity[b]
    v_head, a_head = head_body_motion(X_base, V_base, bases.acceleration[b], chains.gravity)
    head_rot = wp.transform_get_rotation(X_base)
    for k in range(S):
        i = strand * S + k
        rk_q[i] = joint_q_in[i]
        rk_w[i] = joint_qd_in[i]
        rk_dq[i] = wp.vec3()
        rk_dw[i] = wp.vec3()
    for stage in range(4):
        aba_strand(chains, strand, h, 0, head_rot, v_head, a_head, loads, rk_q, rk_w, scratch)
        weight = 2.0
        step = 0.5 * h
        if stage == 0 or stage == 3:
            weight = 1.0
        if stage == 2:
            step = h
        for k in range(S):
            i = strand * S + k
            w = rk_w[i]
            qdd = scratch.qdd[i]
            rk_dq[i] = rk_dq[i] + weight * w
            rk_dw[i] = rk_dw[i] + weight * qdd
            if stage < 3:
                rk_q[i] = wp.normalize(joint_q_in[i] * quat_exp(step * w))
                rk_w[i] = joint_qd_in[i] + step * qdd
    for k in range(S):
        i = strand * S + k
        w = joint_qd_in[i] + (h / 6.0) * rk_dw[i]
        q = wp.normalize(joint_q_in[i] * quat_exp((h / 6.0) * rk_dq[i]))
        flag_joint(w, joint_qd_in[i], q, h, max_rotation, fault)
        joint_qd_out[i] = w
        joint_q_out[i] = q
        rk_w[i] = w
    if contacts.enabled != 0:
        # Contact impulses after the update, with the explicit inertia (RK4's stages would not stay stable with
        # the stiff dampers inside them); the velocity change also moves the configuration over the step.
        body_contact_solve(chains, strand, h, h, 0, X_base, V_base, loads, joint_q_in, joint_qd_out, contacts,
                           scratch, dampers, 0)
        if shares_friction(h) != 0:
            forget_held_force(contacts, strand * (S + 1), S)
            add_held_force(contacts, strand * (S + 1), S, 1.0)
        for k in range(S):
            i = strand * S + k
            w = joint_qd_out[i]
            flag_contact_response(rk_w[i], w, h, max_rotation, fault)
            joint_q_out[i] = wp.normalize(joint_q_out[i] * quat_exp(h * (w - rk_w[i])))
    fk_strand(chains, strand, X_base, V_base, joint_q_out, joint_qd_out, seg_xform_out, vertex_positions_out,
              vertex_velocities_out)


@wp.func
def fk_strand(
    chains: StrandChains,
    strand: int,
    X_h: wp.transform,
    v_head: wp.spatial_vector,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    seg_xform: wp.array(dtype=wp.transform),
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
):
    """World segment frames, vertex positions [m] and velocities [m/s] of one strand, root to tip."""
    S = chains.seg_per_strand
    R = wp.transform_get_rotation(X_h)
    p_h = wp.transform_get_translation(X_h)
    omega = wp.spatial_top(v_head)
    x = wp.transform_point(X_h, chains.strand_root_pos[strand])
    v = wp.spatial_bottom(v_head) + wp.cross(omega, x - p_h)
    vbase = strand * (S + 1)
    for k in range(S):
        i = strand * S + k
        R = R * joint_q[i]
        omega = omega + wp.quat_rotate(R, joint_qd[i])
        seg_xform[i] = wp.transform(x, R)
        vertex_positions[vbase + k] = x
        vertex_velocities[vbase + k] = v
        d = wp.quat_rotate(R, wp.vec3(0.0, 0.0, -chains.seg_length[i]))
        x = x + d
        v = v + wp.cross(omega, d)
    vertex_positions[vbase + S] = x
    vertex_velocities[vbase + S] = v


@wp.kernel
def forward_kinematics(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    # Control:
    bases: StrandBases,
    # State in:
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    # Out:
    seg_xform: wp.array(dtype=wp.transform),
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
):
    """One thread per strand: world segment frames, vertex positions [m] and velocities [m/s]."""
    strand = tid_offset + wp.tid()
    b = strand * bases.per_strand
    fk_strand(chains, strand, bases.xform[b], bases.velocity[b], joint_q, joint_qd, seg_xform, vertex_positions,
              vertex_velocities)


@wp.kernel
def air_drag(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    seg_length: wp.array(dtype=float),
    drag: float,
    # Control:
    wind: wp.array(dtype=wp.vec3),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
):
    """One thread per segment: linear air drag toward the wind, ``F = -drag L (v_mid - wind)``.

    Adds the force [N, world] at the segment's midpoint to ``seg_force`` and its moment about
    the segment origin [N m] to ``seg_torque``.
    """
    i = tid_offset + wp.tid()
    strand = i // seg_per_strand
    k = i - strand * seg_per_strand
    a = strand * (seg_per_strand + 1) + k
    x0 = vertex_positions[a]
    x1 = vertex_positions[a + 1]
    v_mid = 0.5 * (vertex_velocities[a] + vertex_velocities[a + 1])
    F = -drag * seg_length[i] * (v_mid - wind[0])
    seg_force[i] = seg_force[i] + F
    seg_torque[i] = seg_torque[i] + wp.cross(0.5 * (x1 - x0), F)


@wp.kernel
def hair_speed(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    # In:
    speed_bound: wp.array(dtype=float),
    # State in:
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Out:
    strand_speed: wp.array(dtype=float),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand: the fastest of its vertices [m/s, world] into ``strand_speed`` (its own element; inf
    for a non-finite velocity), and ``Fault.HAIR_SPEED`` when that exceeds ``speed_bound[0]``. Run once per output
    frame by ``Solver.check``; ``fault`` is ORed, private per chunk on the CPU."""
    strand = tid_offset + wp.tid()
    first = strand * (seg_per_strand + 1)
    fastest = float(0.0)
    for k in range(seg_per_strand + 1):
        v = vertex_velocities[first + k]
        speed = wp.length(v)
        if not wp.isfinite(v):
            speed = float(wp.inf)
        fastest = wp.max(fastest, speed)
    strand_speed[strand] = fastest
    if fastest > speed_bound[0]:
        wp.atomic_or(fault, 0, int(Fault.HAIR_SPEED))


__all__ = [
    "aba_accelerations",
    "air_drag",
    "forward_kinematics",
    "hair_speed",
    "integrate_euler",
    "integrate_rk4",
]
