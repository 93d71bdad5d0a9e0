"""The links' response: Gauss-Seidel sweeps between strands after the free step (``hairwarp.Solver``;
docs/interactions.md, "Links solved by sweeps").

The strands are coloured so that no two of a colour share a link (``hairwarp.interactions.strand_colors``); a sweep
solves the colours in turn, each colour's strands at once, one thread each (``link_sweep``), the next sweep the
colours in the opposite order (symmetric Gauss-Seidel). Every strand is solved from its free step with its partners
held at their latest answer, read linearised at the step's start (``answer``); in the first sweep, the partners
not yet solved at their free step.
"""

import warp as wp

from hairwarp.kernels.articulated import (
    CONTACT_PASSES,
    FULL_FRICTION,
    AbaScratch,
    BodyContacts,
    DamperFactors,
    InteractionResponse,
    SegmentLoads,
    StrandBases,
    StrandChains,
    contact_projector,
    damper_solve,
    finish_response,
    held_force,
    matched_friction,
    point_damper_blocks,
    shares_friction,
    spin_free_coupling,
    spin_free_rotation,
    spin_free_torque,
    strand_touches,
    strand_turn_rate,
)
from hairwarp.kernels.contacts import ContactBuffer, ContactResponse, SweepContacts, sweep_entry_force
from hairwarp.kernels.links import LinkEnds, end_slot, offset_end_velocity, seg_point_velocity
from hairwarp.kernels.spatial import skew

wp.set_module_options({"enable_backward": False})

#: How many times the bound of each link end's geometric stiffness, ``h^2 |f| |r|``, the sweeps add to its segment's
#: turn (``link_sweep``; ``hairwarp.StaticLinks.geometric_stiffness``). On the benchmark's turn (150 guides, links
#: within 2 cm, 45 frames, none taken again) at one step a frame, where the force over the step outgrows the step
#: start's ``k l``: without the term links of 10, 30, 100, 300 and 1,000 N/m blew up at frames 34, 19, 11, 9 and 6;
#: with the bound once 10 N/m held and the others blew up at frames 39, 20, 23 and 27; twice 30 N/m held, 100-1,000 at
#: frames 31-36; four times every one held, and 3,000 and 10,000 N/m too (at 2 and 8 substeps as well, to 30,000).
#: Four times moves the shipped scenes' tips against 32 substeps by no more than the scenes' own sensitivity
#: (``fast_turn`` 6.72 mm at 8 substeps, 6.91 without the term; 16.1 at 2, 15.7; the mohawk and the shoulders the same
#: to 0.6 mm). Those runs took the other kind of hair interaction beside the links; alone, the table held to 1,000
#: N/m from three times the bound (twice: 100-1,000 N/m blew up at 1.03-1.37 s).
GEOMETRIC_STIFFNESS_FACTOR = 4.0

#: The longest link, in arms of its end (the end's distance from its segment's origin), whose end takes the whole
#: geometric term (``link_sweep``; ``hairwarp.StaticLinks.geometric_arm_ratio``): an end on a link stretched further
#: takes the term of one stretched this far. The term is a damper on the segment's turn in the world, and where it
#: outweighed a limp segment's own inertia many times it flung the strand: limp linked hair (EI 1e-7, ``long_hair``
#: on its turn with links and contacts, the robustness suite's stability grid) whipped to 6.1 m/s at 8 and 16 segments
#: and 2 substeps (1.0 and 0.80 m/s with the term twice the bound, 1.00 without it), its tips' ends on links up to 28
#: times their arms (the top percent past 3.8). Stiff links stretch little: on the benchmark's turn at one step a frame
#: (100 and 1,000 N/m) no end passed 1.6 arms. At 4 arms every cell of the grid's limp row holds (0.71-1.40 m/s, none
#: taken again) and the stiff links' table above with it (at 2, a link of 30 N/m blew up at 1.40 s); the shipped
#: scenes' tips against 32 substeps: ``fast_turn`` 6.01 and 17.2 mm at 8 and 2 substeps (6.79 and 16.3 uncapped), the
#: shoulders and the mohawk the same to 0.01 mm.
GEOMETRIC_ARM_RATIO = 4.0


@wp.func
def answer(strand: int, S: int, seg_xform_in: wp.array(dtype=wp.transform),
           vertex_positions_in: wp.array(dtype=wp.vec3), joint_qd: wp.array(dtype=wp.vec3),
           free_qd: wp.array(dtype=wp.vec3), free_velocities: wp.array(dtype=wp.vec3),
           answered_velocities: wp.array(dtype=wp.vec3)):
    """What the strand's neighbours see of its answer ``joint_qd`` (``link_sweep``): its free vertex velocities plus
    the change of its joint velocities carried by the frames of the step's start, as the response solve takes it
    (``J(q_start) dw``). The end-of-step velocities would show the neighbours the whole motion turned through the
    step, a coupling that no longer mirrors their own: with it the sweeps diverged on a stiff lattice at 2 steps a
    frame."""
    vbase = strand * (S + 1)
    dv = wp.vec3()
    dw = wp.vec3()
    for k in range(S):
        i = strand * S + k
        dw = dw + wp.quat_rotate(wp.transform_get_rotation(seg_xform_in[i]), joint_qd[i] - free_qd[i])
        dv = dv + wp.cross(dw, vertex_positions_in[vbase + k + 1] - vertex_positions_in[vbase + k])
        answered_velocities[vbase + k + 1] = free_velocities[vbase + k + 1] + dv


#: Largest turn [rad] of a strand's segment over a step, in its free step or in a sweep's answer, at which the bodies
#: answer the sweep (``body_answer``): the contacts, found at the step's start and linearised there, do not hold where
#: the vertices of a strand turning farther go. ``long_hair_shoulders`` in a 100 m/s wind at 4 substeps (segments at
#: 300-400 rad/s, 3 rad over the step) faulted in the answer without a bound, and in a later step's contacts with a
#: bound of 2 rad; five linked strands striking a still sphere at one step a frame need the answer (frictionless, 4
#: N/m: 9.5 % of their energy gained in the frame of the strike with a bound of 0.25 rad, 0.1 % with 0.5 and 1 rad).
ANSWER_TURN = wp.constant(1.0)

#: A vertex's state in a pass of ``body_answer``: held (may be released), released, held for good, and sliding (its
#: force left the friction cone: held by the normal alone).
HOLDS = wp.constant(0.0)
RELEASED = wp.constant(1.0)
HELD_FOR_GOOD = wp.constant(-1.0)
SLIDES = wp.constant(2.0)


@wp.func
def forget_answer(strand: int, S: int, codes: wp.array(dtype=wp.int32), states: wp.array(dtype=float)):
    """Start ``strand``'s answers of a step (``body_answer``): no factors kept, every vertex held."""
    for k in range(S):
        codes[strand * (S + 1) + k + 1] = -1
        states[strand * (S + 1) + k + 1] = HOLDS


@wp.func
def start_answer_forces(contacts: BodyContacts, strand: int, S: int, answers: int):
    """At a step's first sweep: what each vertex of ``strand`` starts its answer from (``answer_start``), the contact
    force it ended the last step's answer with (``answer_force``), where the step answers the strand (``answers``) and
    the vertex has a candidate; none elsewhere. The step's answer then writes its own."""
    for k in range(S):
        vi = strand * (S + 1) + k + 1
        start = wp.vec3()
        if answers != 0 and wp.length_sq(contacts.normal[vi]) > 0.0:
            start = contacts.answer_force[vi]
        contacts.answer_start[vi] = start
        contacts.answer_force[vi] = wp.vec3()


@wp.func
def answer_warm(last: wp.vec3, held: wp.vec3, n: wp.vec3, code: int):
    """The force a vertex held with ``code`` (1 sticking, 2 sliding) starts its answer from, beside the free step's
    ``held``: what brings it to ``last``, its whole contact force at the end of the last step's answer; whole where
    it sticks, along the normal ``n`` where it slides; none where the last step's answer left it no force (it did not
    hold the vertex, or it was released)."""
    if wp.length_sq(last) == 0.0:
        return wp.vec3()
    if code == 1:
        return last - held
    return wp.dot(last - held, n) * n


@wp.func
def in_cone(force: wp.vec3, n: wp.vec3, friction: float):
    """``force`` [N] as a contact of normal ``n`` and ``friction`` can put it: none that pulls, its tangential part
    cut to the cone of its normal part (``matched_friction``'s cut; none frictionless)."""
    if wp.dot(force, n) <= 0.0:
        return wp.vec3()
    kept, _share = matched_friction(force, n, 1.0, friction)
    return kept


@wp.func
def body_answer(
    chains: StrandChains,
    strand: int,
    h: float,
    implicit: int,
    loads: SegmentLoads,
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    contacts: BodyContacts,
    scratch: AbaScratch,
    solved: InteractionResponse,
    answered: InteractionResponse,
    factors: DamperFactors,
    codes: wp.array(dtype=wp.int32),
    states: wp.array(dtype=float),
    seg_xform_in: wp.array(dtype=wp.transform),
    vertex_positions_in: wp.array(dtype=wp.vec3),
    free_qd: wp.array(dtype=wp.vec3),
    free_velocities: wp.array(dtype=wp.vec3),
    answered_velocities: wp.array(dtype=wp.vec3),
):
    """The bodies' answer to what a sweep did to a strand the free step left on them (``link_sweep``, at steps of the
    share law's length: ``shares_friction``): ``joint_qd``, the sweep's answer, corrected in place.

    Each vertex the free step held (its mean force there, ``held_force``) or that the answer takes into a collider
    faster than its gap allows takes the body contact's damper ``-c P (v - v_target)`` from the answer (as
    ``body_contact_solve`` takes it from the free velocities; ``v`` the vertex's velocity in the answer as the sweeps
    read it, ``answer``: its free velocity plus the change, linearised at the step's start), sticking (``P = I``)
    where the collider has friction, else along the normal, solved with the strand's inertia and the sweep's dampers
    (``solved``): with the sweep's own solve, the strand's links and its body contacts solved together (the answer's
    linear part is exact). The force
    the free step put on the vertex is part of its contact: the answer may take it back, not reverse it. A pass
    whose total force on a vertex pulls it toward the body releases it, and the next solves again from the answer
    with the free step's force on it undone; one whose force leaves the friction cone slides, held by the normal
    alone; a released vertex that then goes in is held for good: at most ``CONTACT_PASSES`` solves, the active set
    of ``body_contact_solve``. The free step's contact state (``contacts``) stays as it wrote it.

    As the free step's contacts do, a held vertex starts from the force it ended the last step's answer with
    (``contacts.answer_start``; ``answer_warm``), so that the damper answers only the change and a vertex at rest
    keeps no residual velocity into the body (cold, the damper left ``F / c`` of the links' pull ``F`` each step:
    ``character``'s tips at one step a frame sank 0.1-0.3 mm a step into the torso's top, which the push-out lifted).
    The pass that stands writes each held vertex's whole force, in its cone (``in_cone``), to
    ``contacts.answer_force``, none where no pass stands.

    Its matrix changes only with the vertices held and how: the factors of its last solve (``factors``) are kept with
    each vertex's code (``codes``: 0 free, 1 sticking, 2 sliding, -1 none kept), and a solve whose codes are the same
    reuses them (``damper_solve``). Each vertex's state (``states``) carries over to the next sweep, whose first pass
    then holds the set the last one ended with: the active set settles over the sweeps as their answers do, and most
    sweeps solve once with the factors kept. A step's first sweep starts every vertex held and makes the factors
    afresh (``forget_answer``)."""
    S = chains.seg_per_strand
    vbase = strand * (S + 1)
    mass = float(0.0)
    for k in range(S):
        i = strand * S + k
        mass += chains.seg_mass[i]
        scratch.p[i] = wp.spatial_vector(joint_qd[i], wp.vec3())  # the answer each pass solves from
        scratch.c[i] = wp.spatial_vector(states[vbase + k + 1], 0.0, 0.0, 0.0, 0.0, 0.0)
    hc = contacts.stiffness * mass
    c = hc / h
    kept = int(0)  # 1 once a pass's answer stands (its forces kept for the next step: ``answer_force``)
    for _it in range(CONTACT_PASSES):
        # Each vertex's velocity in the answer, as its neighbours see it (``answer``); the dampers of the vertices
        # held, in the segments' frames at the step's start, and a released one's undoing
        answer(strand, S, seg_xform_in, vertex_positions_in, joint_qd, free_qd, free_velocities, answered_velocities)
        active = int(0)
        changed = int(0)
        for k in range(S):
            i = strand * S + k
            vi = vbase + k + 1
            L = chains.seg_length[i]
            R = wp.transform_get_rotation(seg_xform_in[i])
            v = answered_velocities[vi]
            state = wp.spatial_top(scratch.c[i])[0]
            n = contacts.normal[vi]
            code = int(0)
            target = float(0.0)
            F = wp.vec3()
            M = wp.mat33()
            if wp.length_sq(n) > 0.0:
                target = -wp.max(contacts.gap[vi], 0.0) / h
                rel = v - contacts.object_velocity[vi] - target * n
                start = held_force(contacts, vi)
                warm = contacts.answer_start[vi]
                if state != RELEASED and (wp.dot(rel, n) < 0.0 or wp.length_sq(start) > 0.0
                                          or wp.length_sq(warm) > 0.0):
                    code = 2
                    beta = float(0.0)
                    if state != SLIDES and contacts.friction[vi] > 0.0:
                        code = 1
                        beta = 1.0
                    P = contact_projector(wp.quat_rotate_inv(R, n), beta)
                    M = hc * P
                    F = (wp.quat_rotate_inv(R, answer_warm(warm, start, n, code))
                         - c * (P * wp.quat_rotate_inv(R, rel)))
                elif state == RELEASED:
                    F = -wp.quat_rotate_inv(R, start)
                if wp.length_sq(F) > 0.0 or code != 0:
                    active = 1
            scratch.c[i] = wp.spatial_vector(state, float(code), target, 0.0, 0.0, 0.0)
            tip = wp.vec3(0.0, 0.0, -L)
            if code != codes[vi]:  # the segment's blocks as the factors to be made hold them (else as they are)
                changed = 1
                Ac, Bc = point_damper_blocks(tip, M)
                answered.A[i] = solved.A[i] + Ac
                answered.B[i] = solved.B[i] + Bc
                answered.C[i] = solved.C[i] + M
            answered.force[i] = F
            answered.torque[i] = spin_free_torque(tip, F)
        if active == 0:
            break
        damper_solve(chains, strand, h, implicit, loads, joint_q, joint_qd, scratch, answered, factors, 1 - changed, 1)
        if changed != 0:
            for k in range(S):
                codes[vbase + k + 1] = int(wp.spatial_top(scratch.c[strand * S + k])[1])
        # The solved velocities; each held vertex's whole force (the free step's and the answer's)
        answer(strand, S, seg_xform_in, vertex_positions_in, joint_qd, free_qd, free_velocities, answered_velocities)
        pulled = int(0)
        for k in range(S):
            i = strand * S + k
            vi = vbase + k + 1
            v = answered_velocities[vi]
            flags = wp.spatial_top(scratch.c[i])
            state = flags[0]
            sticks = flags[1] == 1.0
            n = contacts.normal[vi]
            contacts.answer_force[vi] = wp.vec3()
            if flags[1] > 0.0:
                rel = v - contacts.object_velocity[vi] - flags[2] * n
                held = held_force(contacts, vi)
                force = (held + answer_warm(contacts.answer_start[vi], held, n, int(flags[1]))
                         - c * (contact_projector(n, wp.where(sticks, 1.0, 0.0)) * rel))
                fn = wp.dot(force, n)
                friction = contacts.friction[vi]
                contacts.answer_force[vi] = in_cone(force, n, friction)
                if fn <= 0.0:
                    if state != HELD_FOR_GOOD:
                        state = RELEASED
                        pulled = 1
                elif sticks and friction < FULL_FRICTION:
                    if wp.length(force - fn * n) > friction / (1.0 - friction) * fn:
                        state = SLIDES
                        pulled = 1
            elif state == RELEASED:
                if wp.dot(v - contacts.object_velocity[vi], n) < flags[2]:
                    state = HELD_FOR_GOOD
                    pulled = 1
            scratch.c[i] = wp.spatial_vector(state, flags[1], flags[2], 0.0, 0.0, 0.0)
        if pulled == 0:
            kept = 1
            break
        # solved again from the sweep's answer; an active set still changing after the last pass is not trusted:
        # the answer stays as the sweep left it (the push-out after the step keeps the strand out of the bodies)
        for k in range(S):
            joint_qd[strand * S + k] = wp.spatial_top(scratch.p[strand * S + k])
    for k in range(S):
        states[vbase + k + 1] = wp.spatial_top(scratch.c[strand * S + k])[0]
        if kept == 0:
            contacts.answer_force[vbase + k + 1] = wp.vec3()


@wp.func
def moment_inertia(S: wp.mat33):
    """``trace(S) I - S`` of a sum of outer products ``S = sum w r r^T``, i.e. ``sum w (|r|^2 I - r r^T)``, each
    diagonal entry the sum of the other two (no difference of the large and the small along an arm)."""
    return wp.mat33(S[1, 1] + S[2, 2], -S[0, 1], -S[0, 2],
                    -S[1, 0], S[0, 0] + S[2, 2], -S[1, 2],
                    -S[2, 0], -S[2, 1], S[0, 0] + S[1, 1])


@wp.func
def joints_turned(strand: int, S: int, joint_q: wp.array(dtype=wp.quat), kept_q: wp.array(dtype=wp.quat),
                  cos_half: float):
    """1 where a joint of ``strand`` has turned from ``kept_q`` by more than the angle whose half-angle cosine is
    ``cos_half`` (``|q . q_kept| < cos_half``), else 0."""
    turned = int(0)
    for k in range(S):
        i = strand * S + k
        if wp.abs(wp.dot(joint_q[i], kept_q[i])) < cos_half:
            turned = 1
    return turned


@wp.func
def copy_answer(strand: int, S: int, answered: wp.array(dtype=wp.vec3), copy: wp.array(dtype=wp.vec3)):
    """Copy ``strand``'s answered vertex velocities into ``copy``, where the next sweep reads them for the strands
    of its colour (``link_sweep``'s ``answered_before``)."""
    for k in range(S + 1):
        v = strand * (S + 1) + k
        copy[v] = answered[v]


@wp.kernel
def sweep_start(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    seg_per_strand: int,
    # The free step's result:
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # With ``contacts_swept``, the copy the first sweep reads of its own colour's answers (``link_sweep``)
    contacts_swept: int,
    # Out: what every sweep starts from (``link_sweep``)
    free_q: wp.array(dtype=wp.quat),
    free_qd: wp.array(dtype=wp.vec3),
    free_velocities: wp.array(dtype=wp.vec3),
    answered_velocities: wp.array(dtype=wp.vec3),
    answered_copy: wp.array(dtype=wp.vec3),
):
    """One thread per strand: keep the free step's joints and vertex velocities for the sweeps, and start their
    answers from the free step's velocities (one launch the executor splits over the threads)."""
    strand = tid_offset + wp.tid()
    S = seg_per_strand
    for k in range(S):
        i = strand * S + k
        free_q[i] = joint_q[i]
        free_qd[i] = joint_qd[i]
    for k in range(S + 1):
        v = strand * (S + 1) + k
        free_velocities[v] = vertex_velocities[v]
        answered_velocities[v] = vertex_velocities[v]
        if contacts_swept != 0:
            answered_copy[v] = vertex_velocities[v]


@wp.kernel
def link_sweep(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # The strands of one colour (no two of them linked):
    color_strands: wp.array(dtype=wp.int32),
    # Model:
    chains: StrandChains,
    seg_link_start: wp.array(dtype=wp.int32),
    seg_b_start: wp.array(dtype=wp.int32),
    b_slot_link: wp.array(dtype=wp.int32),
    link_seg_a: wp.array(dtype=wp.int32),
    link_seg_b: wp.array(dtype=wp.int32),
    link_stiffness: float,
    link_damping: float,
    link_scale: wp.array(dtype=float),
    # each end's force adds this many times the bound of its geometric stiffness to its segment's turn (0: none;
    # ``link_sweep``, ``GEOMETRIC_STIFFNESS_FACTOR``)
    link_geometric: float,
    # ... at most the term of a link this many arms of its end long (``GEOMETRIC_ARM_RATIO``)
    link_geometric_arms: float,
    # Scratch: the ends the force pass left; what ``link_response_ends`` kept of each end (``LinkEnds``)
    link_point_a: wp.array(dtype=wp.vec3),
    link_point_b: wp.array(dtype=wp.vec3),
    link_broken: wp.array(dtype=wp.int32),
    ends: LinkEnds,
    # Control:
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # State: the step's start; the free step's end
    implicit: int,
    loads: SegmentLoads,
    joint_q_in: wp.array(dtype=wp.quat),
    seg_xform_in: wp.array(dtype=wp.transform),
    vertex_positions_in: wp.array(dtype=wp.vec3),
    free_q: wp.array(dtype=wp.quat),
    free_qd: wp.array(dtype=wp.vec3),
    free_velocities: wp.array(dtype=wp.vec3),
    # In and out: the vertex velocities of each strand's latest answer, linearised at the step's start; the same
    # as the last sweep left them, read for strands of this colour (solved at once with this one), and where this
    # sweep leaves them for the next
    answered_velocities: wp.array(dtype=wp.vec3),
    answered_before: wp.array(dtype=wp.vec3),
    answered_after: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.int32),
    # The hair contacts' dampers, split between their sides: held through the sweeps where ``contacts_swept`` is 0
    # (on a GPU, which has no contact lists per segment), else solved in them (``contacts`` ... ``sweep_contacts``)
    held: InteractionResponse,
    contacts_swept: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    contacts: ContactBuffer,
    response: ContactResponse,
    seg_entry_start: wp.array(dtype=wp.int32),
    sweep_contacts: SweepContacts,
    # With ``contacts_warm`` the free step took each segment's hair contact force of the last step, which the sweeps
    # leave out of the contacts' forces (``hairwarp.HairContacts.warm_start``): [N, world] and [N m, world]
    contacts_warm: int,
    contact_warm_force: wp.array(dtype=wp.vec3),
    contact_warm_torque: wp.array(dtype=wp.vec3),
    # The hair contacts' dampers as the contacts' gather left them whole, with ``contacts_swept``
    dampers: InteractionResponse,
    # The sweeps' dampers: their blocks, built by the step's first sweep (``held`` or ``dampers``, and the links') and
    # the same in every later one; their forces, written here
    solved: InteractionResponse,
    # Scratch: with ``reuse`` (every sweep of a step after its first; ``carried``) the factors of the strand's matrix
    # that the first made (or an earlier step)
    scratch: AbaScratch,
    factors: DamperFactors,
    reuse: int,
    # 1 on a step's first sweep when later ones follow, which read the factors and arms it keeps
    keep: int,
    # For a step of one sweep: [0] 1 where it solves with the factors and arms an earlier step kept (no blocks built,
    # no factorisation), [1] 1 where it keeps its own for later steps (``hairwarp.Solver.factor_steps``); read at
    # the launch, so a captured step follows what the host set before it replays
    carried: wp.array(dtype=wp.int32),
    # In a step that solves with an earlier step's factors, a strand whose joints have turned by more than the angle
    # whose half-angle cosine this is since they were made (``factors.q``) makes its own and keeps them
    factor_cos_half: float,
    # 1 on the step's last sweep, whose answer the strand keeps: only then its joints are turned and its forward
    # kinematics run (the sweeps before read only ``answered_velocities``, from the joint velocities)
    last: int,
    # 1 on a sweep after the last that solves again, from its free step and with its factors made afresh, only the
    # strands marked in ``strand_redo`` (a link of theirs broke within the step: ``links.link_response_ends``)
    redo: int,
    strand_redo: wp.array(dtype=wp.int32),
    # The step's body contacts, as the free step left them (disabled: no colliders), which answer each sweep at
    # long steps (``body_answer``): its dampers, their factors, each vertex's code and state
    body: BodyContacts,
    answered: InteractionResponse,
    answer_factors: DamperFactors,
    answer_codes: wp.array(dtype=wp.int32),
    answer_states: wp.array(dtype=float),
    # Out: the strand answered, from the free step's result
    joint_q_out: wp.array(dtype=wp.quat),
    joint_qd_out: wp.array(dtype=wp.vec3),
    seg_xform_out: wp.array(dtype=wp.transform),
    vertex_positions_out: wp.array(dtype=wp.vec3),
    vertex_velocities_out: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand of one colour: the strand's answer to its links' backward-Euler forces over the step, the
    strands it is linked to held at their latest answer (block Gauss-Seidel between strands).

    A link's force over the step is ``k l - P u'``, ``P = h k I + c n n^T``, ``u'`` the end-of-step velocity of a's
    end relative to b's. Solving strand i alone with every other strand held, its end of each link takes the
    damper ``h P`` (the pair's whole point inertia) and the force ``+-(k l) - P (v_own - v_other)``, ``v_own`` its
    end's velocity from the free step (``free_velocities``), ``v_other`` the other end's latest answer
    (``answered_velocities``: this sweep's where its colour came first, else the last sweep's, else its free
    step's). Its hair contacts are solved the same way (``kernels.contacts.sweep_entry_force``: the whole damper,
    toward the other side's latest answer; less each segment's contact force of the last step where the free step
    took it, ``contacts_warm``), or, on a GPU, held as dampers split between their sides (``held``). The strand is
    then solved from its free step (``damper_solve``; ``finish_response`` on the step's last sweep only) and its
    answer published (``answer``). A colour's strands share no link, so they are solved at once, and
    each sees what the earlier colours gave: every sweep lowers the links' implicit step's error in its energy norm
    (the step's matrix is symmetric positive definite), so unlike Jacobi between strands it cannot overshoot,
    whatever the ends' masses; more sweeps converge to the backward-Euler answer of the whole lattice. Not
    momentum, sweep by sweep: the first strand of a stiff pair solved goes nearly to its partner's free velocity,
    which the later sweeps take back by degrees (a lone pair at h^2 k / m_eff ~ 50, its ends parting at 0.3 m/s
    each: 0.16 m/s off after 8 sweeps, 0.026 after 32); hair moving with its neighbours, as links hold it, has
    little of it. Hair contacts can join two strands of one colour, which a sweep then solves at once (Jacobi, each
    with the whole damper): the colours are the links', fixed for the run.

    With ``link_geometric`` the blocks also take each end's geometric stiffness (Andrews, Teichmann and Kry 2017,
    "Geometric stiffness for real-time constrained multibody dynamics"): the end's force ``f`` (``k l`` at the step's
    start) turns with its segment, a turn ``d theta`` changing its torque by ``[f]x [r]x d theta`` at the arm ``r``,
    which the solve, linearised at the step's start, leaves out and the step then takes explicitly; stiff links pulling
    hard at the roots' segments flung them (200 N/m on the benchmark's turn at 1/240 s, 20-40 rad/s and then a
    fault). ``link_geometric`` times its bound, ``h^2 |f| |r|``, on the segment's two turns across its axis keeps the
    matrix symmetric positive definite and only slows a turn under a large force; an end's ``|l|`` counts at most
    ``link_geometric_arms`` times its arm.

    At steps of the share law's length (``shares_friction``: 7 substeps of 30 fps and fewer) the bodies answer each
    sweep (``body_answer``): the strand's links and its body contacts are then solved together, the strands it is
    linked to held. Without, the sweeps drove vertices the free step held into the bodies, and the push-out after the
    step lifted them: five linked strands falling onto a still sphere at one step a frame gained up to 0.7 % of their
    energy in a frame, and hair at rest on the shoulders was pushed out by 1.2 mm a step on average. At shorter steps
    the sweeps' answers stay within the contacts' layers (the push-out moves nothing at 8 substeps) and the answer is
    left out: there, its sticking friction against the free step's continuous law slowed the shoulders' settling
    (0.084 mm/s in the 6th second against 0.028, and 0.043 without the shoulders)."""
    strand = color_strands[tid_offset + wp.tid()]
    if redo != 0 and strand_redo[strand] == 0:
        return
    S = chains.seg_per_strand
    h = dt[0]
    link_count = link_point_a.shape[0]
    reusing = int(reuse)
    keeping = int(keep)
    if redo != 0:
        # its matrix lost the broken links' dampers: factors made afresh, kept where the frame's later steps carry
        reusing = 0
        keeping = int(carried[0] != 0 or carried[1] != 0)
    elif carried[0] != 0:
        reusing = 1
        # factors made at a shape the strand has since left solve another matrix, which under violent motion flung
        # tips at 30-40 m/s (a head spinning at 3 rev/s): made afresh, and kept for the frame's later steps
        if joints_turned(strand, S, joint_q_in, factors.q, factor_cos_half) != 0:
            reusing = 0
            keeping = 1
    if carried[1] != 0:
        keeping = 1
    if keeping != 0 and reusing == 0:
        for k in range(S):
            factors.q[strand * S + k] = joint_q_in[strand * S + k]
    for k in range(S):
        seg = strand * S + k
        joint_q_out[seg] = free_q[seg]
        joint_qd_out[seg] = free_qd[seg]
        force = held.force[seg]
        torque = held.torque[seg]
        xf = seg_xform_in[seg]
        R = wp.transform_get_rotation(xf)
        origin = wp.transform_get_translation(xf)
        if contacts_swept != 0:
            force = wp.vec3()
            torque = wp.vec3()
            for j in range(seg_entry_start[seg], sweep_contacts.end[seg]):
                f = wp.quat_rotate_inv(R, sweep_entry_force(j, strand, S, strip_pairs, contacts, response,
                                                            sweep_contacts, answered_velocities, answered_before,
                                                            colors))
                force += f
                r = wp.quat_rotate_inv(R, response.point[sweep_contacts.entries[j]] - origin)
                torque += spin_free_torque(r, f)
            if contacts_warm != 0:  # the free step took the segment's contact force of the last step
                force -= wp.quat_rotate_inv(R, contact_warm_force[seg])
                warm = wp.quat_rotate_inv(R, contact_warm_torque[seg])
                torque -= wp.vec3(warm[0], warm[1], 0.0)
        a_first = seg_link_start[seg]
        a_last = seg_link_start[seg + 1]
        b_first = seg_b_start[seg]
        b_last = seg_b_start[seg + 1]
        # the first sweep of a step builds the segment's damper blocks, the same in every later one: its hair
        # contacts' (held, or those the contacts' gather left here) and its link ends' point inertias ``h P``
        A = wp.mat33()
        B = wp.mat33()
        C = wp.mat33()
        if reusing == 0:
            A = held.A[seg]
            B = held.B[seg]
            C = held.C[seg]
            if contacts_swept != 0:
                A = dampers.A[seg]
                B = dampers.B[seg]
                C = dampers.C[seg]
        if a_first != a_last or b_first != b_last:
            Rt = wp.transpose(wp.quat_to_matrix(R))
            # an end's point inertia h P at its arm r (the segment's frame), P = h k I + c n n^T, has the blocks
            # A = -[r]x h P [r]x = h (h k (|r|^2 I - r r^T) + c m m^T), B = [r]x h P = h (h k [r]x + c m n^T) and
            # C = h P, m = r x n; summed by their moments, with w = h^2 k: (sum w |r|^2) I - sum w r r^T
            # (``moment_inertia``), [sum w r]x and (sum w) I, the dampers' parts end by end; the spin about the
            # segment's axis goes at the end (``spin_free_rotation``, ``spin_free_coupling``)
            w_sum = float(0.0)
            g_sum = float(0.0)
            wr_sum = wp.vec3()
            wrr_sum = wp.mat33()
            Ad = wp.mat33()
            Bd = wp.mat33()
            Cd = wp.mat33()
            for j in range(a_first, b_last - b_first + a_last):
                link, side, slot = end_slot(j, a_last, b_first, link_count, b_slot_link)
                if link_broken[link] == 0:
                    q = link_point_b[link]
                    other = link_seg_b[link]
                    own = link_point_a[link]
                    if side < 0.0:
                        q = link_point_a[link]
                        other = link_seg_a[link]
                        own = link_point_b[link]
                    # f = +-(k l) - P (v_own - v_other): the end's own part as ``link_response_ends`` kept it, P
                    # on the other end's latest answer
                    v = wp.vec3()
                    if side < 0.0:
                        # the other end is a's offset end, which its transport's twist moves too
                        v = offset_end_velocity(other, S, vertex_positions_in, answered_velocities, q,
                                                ends.twist_g[link], ends.twist_m[link])
                    else:
                        v = seg_point_velocity(other, S, vertex_positions_in, answered_velocities, q)
                    n = ends.axis[link]
                    scale = link_scale[link]
                    hk = h * link_stiffness * scale
                    c = link_damping * scale
                    arm = wp.vec3()
                    # an a end's twist (``links.offset_twist``) in the segment's frame: its velocity per turn w is
                    # -[r]x w - (w . g) m, J = -[r]x - m g^T (zero for a b end)
                    tg = wp.vec3()
                    tm = wp.vec3()
                    if reusing == 0:
                        arm = Rt * (own - origin)
                        w = h * hk
                        w_sum += w
                        wr_sum += w * arm
                        wrr_sum += wp.outer(w * arm, arm)
                        nl = Rt * n
                        m = wp.cross(arm, nl)
                        hc = h * c
                        if link_geometric > 0.0:
                            arm_length = wp.length(arm)
                            g_sum += h * hk * wp.min(wp.length(link_point_b[link] - link_point_a[link]),
                                                     link_geometric_arms * arm_length) * arm_length
                        Ad += wp.outer(hc * m, m)
                        Bd += wp.outer(hc * m, nl)
                        Cd += wp.outer(hc * nl, nl)
                        if side > 0.0:
                            tg = Rt * ends.twist_g[link]
                            tg = wp.vec3(tg[0], tg[1], 0.0)  # across the axis (round-off off it)
                            tm = Rt * ends.twist_m[link]
                            # J^T hP J and J^T hP less their parts without the twist: with p = hP m and
                            # q = [r]x p, -q g^T - g q^T + (m . p) g g^T and -g p^T
                            tp = w * tm + hc * wp.dot(nl, tm) * nl
                            tq = wp.cross(arm, tp)
                            Ad += wp.dot(tm, tp) * wp.outer(tg, tg) - wp.outer(tq, tg) - wp.outer(tg, tq)
                            Bd -= wp.outer(tg, tp)
                        if keeping != 0:
                            ends.arm[slot] = arm
                            if side > 0.0:
                                ends.kept_g[link] = tg
                                ends.kept_m[link] = tm
                    else:
                        arm = ends.arm[slot]
                        if side > 0.0:
                            tg = ends.kept_g[link]
                            tm = ends.kept_m[link]
                    f = Rt * (ends.force[slot] + hk * v + c * wp.dot(n, v) * n)
                    force += f
                    torque += spin_free_torque(arm, f) - wp.dot(tm, f) * tg
            if reusing == 0:
                eye = wp.identity(n=3, dtype=float)
                solved.A[seg] = spin_free_rotation(A + moment_inertia(wrr_sum) + Ad + (link_geometric * g_sum) * eye)
                solved.B[seg] = spin_free_coupling(B + skew(wr_sum) + Bd)
                solved.C[seg] = C + w_sum * eye + Cd
        elif reusing == 0:
            solved.A[seg] = A
            solved.B[seg] = B
            solved.C[seg] = C
        solved.force[seg] = force
        solved.torque[seg] = torque
    # the strand's answer from its free step, with the factors of the step's first sweep kept
    for k in range(S):
        scratch.qdd[strand * S + k] = joint_qd_out[strand * S + k]
    damper_solve(chains, strand, h, implicit, loads, joint_q_in, joint_qd_out, scratch, solved, factors, reusing,
                 keeping)
    b = strand * bases.per_strand
    answers = int(0)
    if body.enabled != 0:
        answers = shares_friction(h) * strand_touches(body, strand * (S + 1), S)
        if reuse == 0 and redo == 0:  # the step's first sweep: the answer's forces start from the last step's
            start_answer_forces(body, strand, S, answers)
    if answers != 0:
        if reuse == 0 or redo != 0:  # the step's first sweep, or one solving again: the answer's set afresh
            forget_answer(strand, S, answer_codes, answer_states)
        for k in range(S):  # none unless this sweep's answer stands
            body.answer_force[strand * (S + 1) + k + 1] = wp.vec3()
        # (a strand turning faster than ``ANSWER_TURN`` is left to the push-out after the step)
        if h * wp.max(strand_turn_rate(chains, strand, joint_q_in, free_qd),
                      strand_turn_rate(chains, strand, joint_q_in, joint_qd_out)) <= ANSWER_TURN:
            body_answer(chains, strand, h, implicit, loads, joint_q_in, joint_qd_out, body, scratch, solved, answered,
                        answer_factors, answer_codes, answer_states, seg_xform_in, vertex_positions_in, free_qd,
                        free_velocities, answered_velocities)
    if last != 0:
        finish_response(chains, strand, bases.xform[b], bases.velocity[b], h, scratch, joint_q_out, joint_qd_out,
                        seg_xform_out, vertex_positions_out, vertex_velocities_out, fault, 1)
    answer(strand, S, seg_xform_in, vertex_positions_in, joint_qd_out, free_qd, free_velocities, answered_velocities)
    if contacts_swept != 0:
        copy_answer(strand, S, answered_velocities, answered_after)
