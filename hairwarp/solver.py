"""``Solver.step``: the order of the stages of one time step, nothing else."""

from __future__ import annotations

import contextlib
import math
import time

import numpy as np
import warp as wp

from hairwarp.executor import Executor, launch
from hairwarp.interactions import contact_step_rate
from hairwarp.kernels import articulated, sweeps
from hairwarp.kernels import contacts as contact_kernels
from hairwarp.kernels import links as link_kernels
from hairwarp.kernels.types import Fault, Integrator

#: Fewest strands per chunk of the integrator and of the step's chains (forces, integration, push-out): one strand's
#: ABA and contact sweeps take a few microseconds, so 16 strands outweigh a chunk's hand-off (``hairwarp bench
#: threads``).
INTEGRATE_MIN_CHUNK = 16

#: Fewest strands per chunk of a Gauss-Seidel sweep over one colour of strands (``sweeps.link_sweep``): the
#: mohawk's last colours hold 39, 11 and 4 strands, and one strand's sweep takes about 6 us (8 against 16: a
#: frame 1-2 % faster on two threads, ``hairwarp bench threads``).
SWEEP_MIN_CHUNK = 8

#: Fewest segments per chunk of the air drag (~15 ns a segment: a second thread pays from ~4,000 segments on).
DRAG_MIN_CHUNK = 4096


#: Substeps a frame past which an explicit integrator's fault no longer offers them as a way out, only
#: ``implicit_joints``: the Ratboy mohawk's strands of a few millimetres asked for 14 million.
EXPLICIT_SUBSTEPS_WORTH_NAMING = 10_000


#: ``max_rotation_per_step``'s default [rad] (``sim.max_rotation_per_step``): a fault under a bound set below it names
#: the bound first.
DEFAULT_MAX_ROTATION = 1.0

#: Largest turn of a joint [rad] since the factors a step solves with were made (``Solver.factor_turn``): a strand
#: turned further makes its own (``sweeps.link_sweep``). At 0.2 rad, ``long_hair_shoulders`` without its colliders
#: faulted on its nod ten times as fast (docs/interactions.md, "Factors carried over steps").
FACTOR_TURN = 0.1

#: Steps that one factorisation of the strands' matrices serves in the links' sweeps after the free step, the first
#: of them making it (``Solver.plan_factors``; 1: every step its own). 8: a frame at the shipped 8 substeps.
FACTOR_STEPS = 8

#: Free-step rate (step times ``sqrt(k / m)``, :meth:`Solver._rates`) of the static links past which a fault of the
#: free step is theirs: on ``long_hair`` at 8 substeps links of 10 N/m a link (2.0; 3.5 N/m at 1 cm) run, 20 N/m
#: (2.8) whip at 18 m/s and 30 N/m (3.5) go non-finite, while ``links.enabled = false`` or ``links.response = "step"``
#: runs.
LINK_RATE_LIMIT = 2.0

#: Longest step [s] (exclusive) and largest links' free-step rate at which links solved after the free step put their
#: force of the last step into it (``Solver._warm_start``): 2 substeps of 30 fps and more, the mohawk from 4.
WARM_START_STEP = 1.0 / 45.0
WARM_START_RATE = 8.0

#: The strands' bending rate at a step (the step times the median joint's ``sqrt(k / I)`` about a bending axis,
#: ``Solver._bend_rate_per_second``) below which the links' warm start takes the force kept gated by their ends'
#: speed (:data:`WARM_GATE_SPEED`), not whole: limp strands have nothing of their own to hold back the free step's
#: answer to a force lagged a step. The stability grid's limp linked hair (EI 1e-7, 16 segments, rate 0.15 at 2
#: substeps) whipped to 3.2-5.7 m/s in four of six draws of gravity with the force whole (1.1 m/s at 8 substeps); gated,
#: 0.76 m/s in every draw, with the head still 8.4 mm/s in the 6th second against 1.8 (cold, 24: the crawl the warm
#: start is for). The shipped hair runs at 1.1 and more at every step to one a frame (EI 2e-4, 12 segments at 7
#: substeps; 8 segments 0.49), and takes the force whole as before.
WARM_START_BEND_RATE = 0.3

#: Largest typical rate of the links (``StaticLinks.warm_rate``, the 90th percentile of the linked segments' free-step
#: rates) at which they take the whole force of the last step, on one sweep a step; a step of ``n`` warm sweeps
#: (``StaticLinks.sweeps_at``) takes ``n ** WARM_START_RATE_GROWTH`` times it. The lagged force feeds back what the
#: sweeps leave unsolved, times about the rate squared, and grows from step to step where the sweeps take off less
#: than that: measured with no frame taken again (``sim.fault_retries = 0``), the links blew up at typical rates of
#: 1.74 (``long_hair_shoulders``, links 2x, frame 12), 1.77 (150 guides of 0.35 m turning 60 degrees in 0.4 s, links
#: within 2 cm, frame 24) and 2.15 (the mohawk, links 4x) on one sweep, held at 1.68 and 1.86; on 4 sweeps (1/120 s)
#: held 3.16 and blew up at 3.5; on 16 (1/60 s) held 5.47 and 6.01 and blew up at 6.32. Beyond the bound a step takes
#: the gated force (``WARM_GATE_SPEED``, with colliders) or none, on a cold step's sweeps, which held every rate of the
#: turn from 2.2 to 6.9 (5 to 50 N/m), where the whole force faulted every frame at 8 substeps from 10 N/m up (frames
#: taken again in 16 steps). The shipped scenes' typical rates are 0.65-1.23 at their 8 substeps.
WARM_START_TYPICAL_RATE = 1.6
WARM_START_RATE_GROWTH = 0.45

#: Speed [m/s] by which, at the steps those bounds leave out, each link's force of the last step that the free step
#: takes falls off with the speed its ends parted at in that step's answer: ``f / (1 + |u'|^2 / s^2)``
#: (``kernels.links.link_response_ends``, ``StaticLinks.warm_gate``; the sweeps solve the rest, so the step's linear
#: answer is the same). A link at rest carries its force whole, and the free step's body contacts take the load of
#: the links as well as the hair's weight; one whose ends jitter or part fast starts cold. Started cold, hair at rest
#: on a body at one step a frame traded its load between the free step's contacts and the links' sweeps every step
#: and never settled: ``long_hair_shoulders`` with its head still, tips at 9.6 mm/s in the 6th second (0.013 now, as
#: with the whole force); and five strands linked side by side gained 1.2 % of their energy in a frame against
#: a still sphere (``test_linked_strands_never_gain_energy_against_a_still_sphere``; their energy now only falls).
#: The whole force at one step a frame faulted the shoulders' frame 7 in motion (taken again in 2 steps) and sped limp
#: linked hair (EI 1e-7, 8 segments, no hair contacts) to 2.75 m/s; gated: no fault, and 1.43 m/s (1.62 cold) over
#: eight draws of gravity. At 0.01 m/s the shoulders rested at 0.2 mm/s, at 0.1 the limp hair reached 2.28 m/s.
#: Only where the scene has colliders (the load it shares is theirs to take) and links' free-step rates up to
#: ``WARM_GATE_RATE``: hair hanging free swung on at one step a frame with it (40 of the shoulders' strands without
#: colliders: 13.6 mm/s in the 4th second, 0.69 cold, 1.2 at 8 substeps), and links of 1,000 N/m on ``long_hair`` (rate
#: 33 at 8 substeps) faulted the response in the first frame.
WARM_GATE_SPEED = 0.03
WARM_GATE_RATE = 16.0

#: How far past the whole force's bound on the typical rate (``WARM_START_TYPICAL_RATE`` grown by the step's sweeps,
#: here those of a step that starts from the gated share) a step still takes the gated force. The lagged force that
#: the gate keeps whole where the ends move slowly feeds back what the sweeps leave, as the whole one does: on the
#: benchmark's turn (150 guides, links alone, 1/240 s, two sweeps) the joints' 99th-percentile speed over the run was
#: the cold step's at typical rates up to 1.40 times that bound (15 N/m), 1.25 times it at 1.62 (20 N/m) and twice
#: it at 1.98 (30 N/m); links of 30-250 N/m peaked at 20-102 rad/s gated against 7-13 cold, and 250 N/m faulted. On
#: ``long_hair_shoulders`` at one step a frame (25 sweeps) the shipped links (1.44) ran as cold ones do, and 1.15 and
#: 1.3 times them (1.55, 1.65) 1.23 and 1.14 times as fast.
WARM_GATE_TYPICAL_RATIO = 1.5

#: Shortest step [s] from which the hair contacts solved by the links' sweeps start from their last force
#: (``Solver.contact_warm_start``; the step from which ``response = "auto"`` solves them there,
#: ``runner.AUTO_RESPONSE_DT``), and at which the links take no warm start beside hair contacts solved after the free
#: step that start cold (on a GPU, which lists no contacts per segment, or at steps of ``WARM_START_STEP`` and longer;
#: ``Solver._warm_start``): the links' last force was
#: held in balance by the contacts' last force, which the free step did not take; at long steps it moved far on the
#: links' alone, and the response, linearised at the step's start, pulled it back past where it was. ``fast_turn``
#: (contacts solved after the free step, cold) at 2 substeps: a tip whipped to 8.3 m/s and 6 links broke by the step
#: with it (9.1 m/s in a frame taken again at the break step, on the push-out of the day before), 3.49 m/s and none
#: without, as at 8 and 16 substeps (3.52, 3.72); at 4 substeps 3.72 against 3.48. At its shipped 8 substeps, where its
#: contacts start cold, the links keep the warm start: without it the same rest (0.25 mm/s in the 6th second with the
#: head still, 0.226 with) costs 1.25x the frame (two sweeps a step where it starts cold, and no factors carried).
WARM_START_CONTACTS_STEP = 1.0 / 220.0

#: The strands' first bending mode at a step (the step times the median strand's cantilever rate ``1.875^2
#: sqrt(EI / (mu L^4))``, ``Solver._strand_rate_per_second``) from which the hair contacts take their last force at
#: one step a frame too (``Solver.contact_warm_start``), beside the links' gated one. The joints' own rate
#: (:data:`WARM_START_BEND_RATE`) grows with the segment count; this one is the strand's, whatever its segments.
#: Started cold at one step a frame, hair resting on other hair over a body traded its load between the head's
#: contacts and the hair's every step and never settled, with its head still (tips in the 6th second): ``long_hair``
#: 2.21 mm/s, ``fast_turn`` 4.30, ``character`` 2.19; warm 0.060, 0.63 and 0.046. The stability grid's 1-substep cells
#: with links and contacts at 8, 31 and 64 segments, four draws of gravity each (fastest vertex): EI 1e-7 (rate
#: 0.0024) burst at 16 and 31 segments warm (3.3, 3.7 m/s; 1.0-1.6 cold) and EI 1e-6 (0.0075) at 8 (3.4, 3.5; 0.95-1.4
#: cold), while EI 1e-5 (0.024) ran at 0.75-1.02 m/s warm against 0.87-1.56 cold and 2e-4 and 1e-2 as cold. The
#: shipped scenes run at 0.07-2.1 at one step a frame.
CONTACT_WARM_STRAND_RATE = 0.015

#: The hair contacts' rate (``interactions.contact_step_rate``: the largest density factor and the median segment
#: mass) past which a fault of the free step is theirs: on ``long_hair`` at 8 substeps 300 N/m a contact (7.5; 105
#: N/m at 1 cm) runs and 1,000 N/m (13.7) goes non-finite; the shipped mohawk's contacts take 5.2.
CONTACT_RATE_LIMIT = 7.5

#: The rate (as :data:`LINK_RATE_LIMIT`'s) past which links or hair contacts solved after the free step drive a fault
#: of the dynamics or of the hair's speed: the shipped scenes run at up to 16 (the mohawk's links) and 33 (its
#: contacts) at one step a frame; ``long_hair``'s links of 1e5 N/m at 2 substeps (727) whip at 12 m/s.
RESPONSE_RATE_LIMIT = 100.0

#: The stage a fault names where the free dynamics drive it and no other stage does (``Solver._dynamics_driver``).
DYNAMICS_STAGE = "dynamics (aba + integrate)"

#: Step times the air drag's rate ``drag L / m`` past which a fault is the drag's: the shipped scenes take 0.008-0.013,
#: ``tiny`` with ``strands.density = 1e-3`` takes 1e4 and whips at 35 m/s (``strands.drag = 0`` runs).
DRAG_RATE_LIMIT = 1.0

#: The hair speed fault's bound over the speed the run's motion explains (:meth:`Solver.speed_bound`). The fastest
#: guide vertex at the end of any frame, as a multiple of that speed, measured on the shipped scenes under their
#: motions: 0.27-1.36 (the mohawk's tail tips slapping the body at 5.8 m/s); under harder ones on ``tiny`` and
#: ``long_hair`` with teleports off: a turn at ten times the shipped speed 1.15, a 3 rev/s spin 1.66, a 5 Hz slide
#: of 0.1 m (ten g) 2.30, a 30 degree nod at 6.7 Hz (22 rad/s) 1.95 and 3.18 (34.5 m/s; the run then faults in the
#: body contact). Blow-ups that ran to the end unreported measured 4.7-53 times it (light strands 4.7-13, an
#: undamped twist 16-53, links too stiff for the free step 6.8-55). 4 sits between the two. ``long_hair`` kept on that
#: slide for a second whips past it at every step (its free hair 5.4 and 4.8 times at 32 and 128 substeps): the
#: motion's whip, which the fault then names as such (``runner.WHIP_AGREEMENT``), with the margin among its advice.
SPEED_MARGIN = 4.0


class SimulationFault(RuntimeError):
    """A simulation left its bounds; the message names the frame, the stage and what to change."""

    def __init__(self, message: str, *, frame: int | None = None, stage: str = "", bits: int = 0):
        super().__init__(message)
        self.frame = frame
        self.stage = stage
        self.bits = bits


def forward_kinematics(model, state, control, executor=None):
    """World segment frames, vertex positions and velocities of ``state`` from its joints."""
    launch(
        executor,
        articulated.forward_kinematics,
        model.strand_count,
        [model.chains, control.bases, state.joint_q, state.joint_qd],
        [state.seg_xform, state.vertex_positions, state.vertex_velocities],
        device=model.device,
    )


def _dampers(n: int, device, inverse_inertias=None) -> articulated.InteractionResponse:
    """Zeroed damper arrays for ``n`` segments; the inverse inertias those of ``inverse_inertias`` (shared), or new."""
    d = articulated.InteractionResponse()
    for name in ("A", "B", "C"):
        setattr(d, name, wp.zeros(n, dtype=wp.mat33, device=device))
    d.force = wp.zeros(n, dtype=wp.vec3, device=device)
    d.torque = wp.zeros(n, dtype=wp.vec3, device=device)
    for name in ("phi_a", "phi_b", "phi_c"):
        setattr(d, name, getattr(inverse_inertias, name) if inverse_inertias is not None else
                wp.zeros(n, dtype=wp.mat33, device=device))
    return d


def _damper_factors(n: int, device) -> articulated.DamperFactors:
    """Zeroed factors of ``n`` segments' damper solves (``articulated.damper_solve``)."""
    factors = articulated.DamperFactors()
    for name in ("Dinv", "A", "B", "DA", "DB"):
        setattr(factors, name, wp.zeros(n, dtype=wp.mat33, device=device))
    factors.q = wp.zeros(n, dtype=wp.quat, device=device)
    return factors


def _check_built_for(model, name: str, segments: int, per_strand: int | None = None):
    """Refuse links or hair contacts built for other segments than ``model``'s: a kernel indexing another model's
    segments would read past this one's arrays."""
    if segments != model.seg_count or per_strand not in (None, model.seg_per_strand):
        raise ValueError(f"{name} were built for {segments} segments, not this model's {model.seg_count} "
                         f"({model.strand_count} strands x {model.seg_per_strand}): build them from this model's rest "
                         f"pose")


def _integrator(value) -> Integrator:
    if isinstance(value, Integrator):
        return value
    try:
        return Integrator[str(value).upper()]
    except KeyError:
        names = ", ".join(i.name.lower() for i in Integrator)
        raise ValueError(f"unknown integrator {value!r}; choose one of {names}") from None


def _warm_typical_bound(sweeps: int) -> float:
    """The typical free-step rate (``StaticLinks.warm_rate``) up to which a step of ``sweeps`` sweeps takes the links'
    whole force of the last step: ``WARM_START_TYPICAL_RATE`` grown by ``WARM_START_RATE_GROWTH``."""
    return WARM_START_TYPICAL_RATE * sweeps ** WARM_START_RATE_GROWTH


class Solver:
    """Advances guide strands by one time step.

    Args:
        model: the :class:`hairwarp.Model`.
        integrator: "implicit_joints" (default; joint springs implicit, stable for stiff hair at
            frame-rate steps), "semi_implicit" (symplectic Euler) or "rk4" (fourth order, for
            accuracy studies).
        colliders: a :class:`hairwarp.colliders.ColliderSet`, or None.
        links: a :class:`hairwarp.interactions.StaticLinks`, or None.
        contacts: a :class:`hairwarp.interactions.HairContacts`, or None.
        max_rotation_per_step: fault bound [rad]: a joint bending further than this in one step (or in
            one of the parts a step is split into where segments turn fast: at most 16) means the step no
            longer resolves the motion.
        speed_margin: fault bound on the guides' speed, as a multiple of the speed the motion explains
            (:meth:`speed_bound`; default :data:`SPEED_MARGIN`, inf: no bound).
        threads: CPU threads the launches of a step run on (:class:`hairwarp.executor.Executor`); None or 0:
            every core this process may use. Results are the same bits for any count. Ignored on CUDA.
        executor: another solver's :class:`hairwarp.executor.Executor` (its ``executor``) to run this one's launches
            on its threads, instead of a pool of this solver's own (then give no ``threads``). Two solvers of one
            process that step in turn then never compete for the cores: an idle pool's threads spin a millisecond
            for the next launch, which another pool's launch right after loses to them.

    Everything a step needs is allocated here. ``step`` only launches kernels on
    ``model.device`` and never copies to the host, so it can be captured in a graph; the step
    size lives in a one-element device array, so a captured graph follows a new ``dt``.

    ``sweep_turn`` (0 or 1) is the order of the strands' colours in the next step's first sweep of links solved after
    the free step, forward or back; a step of an odd count of sweeps turns it, so that one sweep a step runs the
    colours forward and back in turn. :class:`hairwarp.Stepper` sets it before each step from the step's place in its
    frame, every frame starting forward (a checkpoint, taken between frames, and the graphs captured per parity and
    turn keep it): turned by the run's parity instead, a frame of one step and 25 sweeps ended on the other way round
    from the frame before, and hair at rest flickered (``long_hair_shoulders`` without its colliders at one step a
    frame: tips at 1.93 mm/s in the 6th second, every other frame back where it was; 0.017 started alike). A caller
    that steps the solver itself and restores a run sets it as it was.

    ``factor_steps`` (:data:`FACTOR_STEPS`) is how many steps one factorisation of the strands' matrices serves in
    those sweeps where a step takes one (:meth:`plan_factors`; 1: every step its own). :class:`hairwarp.Stepper`
    calls :meth:`expire_factors` at every frame's start; a caller that steps the solver itself and restores a run
    calls it after the restore, for the same bits as the run that went through it. ``factor_turn``
    (:data:`FACTOR_TURN`, rad) bounds how far a strand's joints may have turned since the factors it would solve with
    were made: past it, the strand makes its own in that step and keeps them.
    """

    def __init__(self, model, integrator="implicit_joints", *, colliders=None, links=None, contacts=None,
                 max_rotation_per_step: float = DEFAULT_MAX_ROTATION, speed_margin: float = SPEED_MARGIN,
                 threads: int | None = None, executor: Executor | None = None):
        self.model = model
        if executor is not None:
            if threads is not None:
                raise ValueError("give threads or an executor to share, not both (the executor's threads run it)")
            if not isinstance(executor, Executor) or executor.device != wp.get_device(model.device):
                raise ValueError(f"executor must be a hairwarp.executor.Executor on the model's device "
                                 f"{model.device}, got {executor!r}")
        self.executor = executor if executor is not None else Executor(model.device, threads)
        self.integrator = _integrator(integrator)
        self.colliders = colliders
        self.links = links
        if links is not None:
            _check_built_for(model, "links", len(links.seg_transport))
            # built here, from the host, rather than in a first step that may be captured in a graph
            links.seg_damper_weight(model)
        if contacts is not None:
            _check_built_for(model, "contacts", contacts.strand_count * contacts.seg_per_strand,
                             contacts.seg_per_strand)
        self.contacts = contacts
        if isinstance(max_rotation_per_step, bool) \
                or not isinstance(max_rotation_per_step, int | float | np.integer | np.floating) \
                or not max_rotation_per_step > 0.0:  # NaN fails too; inf: no bound
            raise ValueError(f"max_rotation_per_step must be an angle > 0 [rad] (inf: no bound), got "
                             f"{max_rotation_per_step!r}")
        self.max_rotation_per_step = float(max_rotation_per_step)
        if isinstance(speed_margin, bool) or not isinstance(speed_margin, int | float | np.integer | np.floating) \
                or not speed_margin > 0.0:
            raise ValueError(f"speed_margin must be a number > 0 (inf: no bound), got {speed_margin!r}")
        self.speed_margin = float(speed_margin)
        device = model.device
        n = model.seg_count
        # the length a kernel indexes each array of a State by (``_check_state``)
        self._state_sizes = (("joint_q", n), ("joint_qd", n), ("seg_xform", n), ("vertex_positions", model.vert_count),
                             ("vertex_velocities", model.vert_count), ("fault", 1))

        self.dt = wp.zeros(1, dtype=float, device=device)
        # the hair speed check of every output frame (``check``): each strand's fastest vertex, and the bound
        self.strand_speed = wp.zeros(model.strand_count, dtype=float, device=device)
        self._speed_bound = wp.zeros(1, dtype=float, device=device)
        # the hair's own speed where the run starts (a state given velocities, a checkpoint): measured before the
        # first step, or by ``measure_start_speed``
        self._start_pending = True
        self._start_speed_host = 0.0
        length = model.seg_length.numpy().astype(np.float64).reshape(model.strand_count, -1)
        self._reach = np.cumsum(length[:, ::-1], axis=1)[:, ::-1]  # from each joint to its strand's tip [m]
        self._longest_strand = float(self._reach[:, 0].max())
        self._dt_host = None
        self._control = None  # the control of the last step, read back only on a fault, to name non-finite input
        scratch = articulated.AbaScratch()
        scratch.p = wp.zeros(n, dtype=wp.spatial_vector, device=device)
        scratch.c = wp.zeros(n, dtype=wp.spatial_vector, device=device)
        scratch.DA = wp.zeros(n, dtype=wp.mat33, device=device)
        scratch.DB = wp.zeros(n, dtype=wp.mat33, device=device)
        scratch.Du = wp.zeros(n, dtype=wp.vec3, device=device)
        scratch.qdd = wp.zeros(n, dtype=wp.vec3, device=device)
        self.scratch = scratch
        self.joint_qdd = scratch.qdd
        if self.integrator == Integrator.RK4:
            self.rk_q = wp.zeros(n, dtype=wp.quat, device=device)
            self.rk_w = wp.zeros(n, dtype=wp.vec3, device=device)
            self.rk_dq = wp.zeros(n, dtype=wp.vec3, device=device)
            self.rk_dw = wp.zeros(n, dtype=wp.vec3, device=device)

        self.has_drag = model.drag > 0.0
        self.has_forces = self.has_drag or links is not None or contacts is not None
        # Links and hair contacts whose forces are solved after the free step (the links, and the hair contacts with
        # them, by sweeps: ``sweeps.link_sweep``; hair contacts alone in one pass:
        # ``articulated.interaction_response``); the hair contacts add their semi-implicit inertia to the free step
        # where they are not.
        self.responders = [part for part in (links, contacts) if part is not None and part.response]
        self.has_implicit_mass = contacts is not None and not contacts.response
        m = n if self.responders else 1
        dampers = self.dampers = _dampers(m, device)
        # the links' Gauss-Seidel sweeps (``sweeps.link_sweep``): the free step's result each sweep starts from; the
        # hair contacts' dampers, held through the sweeps (``held``) or whole as the contacts' gather leaves them for
        # the sweeps to solve (``swept``); the sweeps' dampers (``solved``: the links' and the contacts', their blocks
        # the same in every sweep, built again for a strand the sweeps solve again); the inverse inertias shared
        self.link_sweeps = links is not None and links.response and links.sweeps > 0 and links.link_count > 0
        # the order of the colours in a step's first sweep: forward (0) or back (1); a step of an odd count of sweeps
        # turns it for the next (``hairwarp.Stepper`` sets it from the step's place in its frame before each step)
        self.sweep_turn = 0
        self._kept_rates = {}  # name -> (stiffness, rate at a step of 1 s): ``_rate_per_second``
        self._warm_start_allowed = True
        self._held_written = True  # whether the hair contacts' held dampers may hold a step's values (``_respond``)
        if self.link_sweeps:
            self.free_q = wp.zeros(n, dtype=wp.quat, device=device)
            self.free_qd = wp.zeros(n, dtype=wp.vec3, device=device)
            self.free_velocities = wp.zeros(model.vert_count, dtype=wp.vec3, device=device)
            self.answered_velocities = wp.zeros(model.vert_count, dtype=wp.vec3, device=device)
            # the answers as each sweep leaves them, read by the next for strands of one colour (by parity)
            self.answered_sweeps = [wp.zeros(model.vert_count, dtype=wp.vec3, device=device) for _ in range(2)]
            self.held = _dampers(n, device, dampers)
            self.swept = _dampers(n, device, dampers)
            self.solved = _dampers(n, device, dampers)
            self.factors = _damper_factors(n, device)
            # whether a step of one sweep solves with the factors an earlier step kept, or keeps its own
            # (``plan_factors``): [reuse, keep], read by the sweep's launch
            self.carried = wp.zeros(2, dtype=wp.int32, device=device)
            self._carried_set = (0, 0)
            # the three settings on the device, copied into ``carried`` when it changes (no allocation in a step)
            self._carried_presets = {flags: wp.array(flags, dtype=wp.int32, device=device)
                                     for flags in ((0, 0), (1, 0), (0, 1))}
        self.factor_steps = FACTOR_STEPS
        self.factor_turn = FACTOR_TURN
        # with :meth:`profile_stages`, the seconds each stage of the steps took, by name; None: not timed
        self.stage_seconds = None
        self._factor_age = None  # steps since the kept factors were made (None: none to use; set_dt expires them)
        m = n if self.has_forces else 1
        self.seg_force = wp.zeros(m, dtype=wp.vec3, device=device)
        self.seg_torque = wp.zeros(m, dtype=wp.vec3, device=device)
        self.seg_implicit_mass = wp.zeros(n if self.has_implicit_mass else 1, dtype=float, device=device)
        self.loads = self._loads(self.seg_force, self.seg_torque, self.has_forces, self.seg_implicit_mass,
                                 self.has_implicit_mass)
        from hairwarp.colliders import ColliderSet, body_contacts

        if colliders is not None and not isinstance(colliders, ColliderSet):
            raise TypeError(f"colliders must be a hairwarp ColliderSet, got {type(colliders).__name__}")

        has_colliders = colliders is not None and len(colliders) > 0
        if has_colliders and colliders.model is not model:
            if colliders.model is not None:
                raise ValueError("colliders: this ColliderSet is bound to another model, whose solver reads its "
                                 "contacts; build a ColliderSet for each model")
            colliders.bind(model)
        for stage in (colliders, links, contacts):
            if stage is not None:
                stage.executor = self.executor
        self.body_contacts = colliders.contacts if has_colliders else body_contacts(1, device, enabled=False)
        if self.link_sweeps:
            # the bodies' answer to each sweep at long steps (``sweeps.body_answer``): its dampers, their factors and
            # the code of each vertex they were made for
            m = n if has_colliders else 1
            self.answered = _dampers(m, device, dampers if has_colliders else None)
            self.answer_factors = _damper_factors(m, device)
            self.answer_codes = wp.zeros(model.vert_count if has_colliders else 1, dtype=wp.int32, device=device)
            self.answer_states = wp.zeros(model.vert_count if has_colliders else 1, dtype=float, device=device)
        self._no_body_contacts = body_contacts(1, device, enabled=False)  # the response's: dampers only
        # what the links' sweeps read of the hair contacts where they hold them (``kernels.sweeps.link_sweep``)
        self._no_sweep_contacts = [wp.zeros(1, dtype=wp.vec2i, device=device), contact_kernels.ContactBuffer(),
                                   contact_kernels.ContactResponse(), wp.zeros(1, dtype=wp.int32, device=device),
                                   contact_kernels.SweepContacts(), 0, wp.zeros(1, dtype=wp.vec3, device=device),
                                   wp.zeros(1, dtype=wp.vec3, device=device)]

    @staticmethod
    def _loads(seg_force, seg_torque, has_force, seg_implicit_mass, has_implicit_mass):
        loads = articulated.SegmentLoads()
        loads.seg_force = seg_force
        loads.seg_torque = seg_torque
        loads.seg_implicit_mass = seg_implicit_mass
        loads.has_force = int(has_force)
        loads.has_implicit_mass = int(has_implicit_mass)
        return loads

    # -- the step -------------------------------------------------------------------------

    def step(self, state_in, state_out, control, dt: float):
        """Advance ``state_in`` by ``dt`` seconds into ``state_out``.

        ``state_in`` must hold its world quantities (a state from ``model.state()`` or from a
        previous step does; after editing its joints call :meth:`forward_kinematics`).
        """
        self._check_step_arguments(state_in, state_out, control)
        self.set_dt(dt)
        self._control = control
        if self._start_pending and not self.model.device.is_capturing:
            # the speed the run starts with, before the first step: measured after it, a step that blows up would
            # raise the bound it is checked against (not inside a graph capture, which reads nothing back: a
            # captured first step leaves it to the next eager one)
            self.measure_start_speed(state_in)
        if not self.model.device.is_capturing:
            self.plan_factors()  # a captured step reads what the host sets before each replay
        body = self.body_contacts.enabled
        self._force_passes(state_in, control, detect_body=body)
        # Each strand's forces, integration and push-out read, of what the others write, only its own: one chain of
        # chunks of strands (one wake of the threads, not four). The forward kinematics of state_out is fused in;
        # the fault bits of state_in (force stages included) carry over.
        with self._fused(self.executor.chain(self.model.strand_count, INTEGRATE_MIN_CHUNK)):
            if self.has_forces:
                self._gather_forces()
            with self._stage("dynamics"):
                self._integrate(state_in, state_out, control)
            if body and not self.responders:
                # state_in: the swept test, from the detection's distances at the start
                with self._stage("body collision"):
                    self.colliders.project(self.model, state_out, control, self.dt, state_in, detected=True)
        if self.responders:
            timed = self.stage_seconds is not None  # the push-out timed apart from the response
            with self._stage("response"):
                self._respond(state_in, state_out, control, project=body and not timed)
            if body and timed:
                with self._stage("body collision"):
                    self.colliders.project(self.model, state_out, control, self.dt, state_in, detected=True)

    def profile_stages(self, on: bool = True):
        """Time every stage of the steps from now on (:attr:`stage_seconds`: seconds by stage, summed over the steps;
        ``on`` False: stop). Profiled, the stages run one after another, each synchronised and timed apart, rather than
        fused into one launch over the threads: a step takes a little longer, with the same result, bit for bit. The
        stages: ``dynamics`` (the free step and the drag), ``body collision`` (detection and push-out), ``links``
        (their forces and their gather), ``hair contacts: detection`` (where it runs in the step), ``hair contacts:
        forces``, and ``response`` (links and contacts solved after the free step)."""
        self.stage_seconds = {} if on else None

    def _stage(self, name: str):
        """A block timed as stage ``name`` while profiling (:meth:`profile_stages`; not inside a graph capture, which
        cannot synchronise), else nothing."""
        if self.stage_seconds is None or self.model.device.is_capturing:
            return _NOT_TIMED
        return _StageTimer(self.stage_seconds, name, self.model.device)

    def _fused(self, block):
        """``block`` (an executor's chain or batch, which fuses launches over the threads), or, while profiling,
        nothing: each stage's launches run, and are timed, on their own."""
        return block if self.stage_seconds is None else _NOT_TIMED

    def _check_step_arguments(self, state_in, state_out, control):
        """States of this model's size and a control: a kernel reading past a smaller state's arrays would crash the
        process, not raise."""
        self._check_control(control)
        for name, state in (("state_in", state_in), ("state_out", state_out)):
            self._check_state(name, state)
        if state_in is state_out:
            raise ValueError("state_in and state_out are the same state: a step reads the one while it writes the "
                             "other (use two, model.state(), and swap them after each step)")

    def _check_state(self, name: str, state):
        """``state`` a :class:`hairwarp.State` of this model: every array of the size a kernel indexes it by (run at
        every step: one pass over the arrays, the message built only on a failure)."""
        sizes = self._state_sizes
        for key, size in sizes:
            a = getattr(state, key, None)
            if not isinstance(a, wp.array):
                raise TypeError(f"{name} must be a hairwarp State (model.state()), got {type(state).__name__}")
            if a.shape[0] != size:
                wrong = [f"{k} {getattr(state, k).shape[0]}" for k, n in sizes
                         if isinstance(getattr(state, k, None), wp.array) and getattr(state, k).shape[0] != n]
                raise ValueError(f"{name} holds {', '.join(wrong)} elements, this model {self.model.seg_count} joints "
                                 f"and {self.model.vert_count} vertices: a state of another model (use model.state())")

    def _check_control(self, control):
        if control is None or not hasattr(control, "wind"):
            raise TypeError(f"control must be a hairwarp Control (model.control()), got {type(control).__name__}")
        frames = control.bases.xform.shape[0]
        if control.bases.per_strand and frames != self.model.strand_count:
            raise ValueError(f"control holds root frames of {frames} strands, this model has "
                             f"{self.model.strand_count}: a control of another model (use model.control())")

    def set_dt(self, dt: float):
        """Store the step size in the device array the kernels read (outside a capture)."""
        if dt != self._dt_host or self._dt_host is None:
            if isinstance(dt, bool) or not isinstance(dt, int | float | np.floating | np.integer) \
                    or not 0.0 < dt < math.inf:
                raise ValueError(f"dt must be a finite number of seconds > 0, got {dt!r}")
            self.dt.fill_(float(dt))
            self._dt_host = dt
            self._set_warm_start()
            self.expire_factors()

    @property
    def warm_start_allowed(self) -> bool:
        """Whether links solved after the free step may start a step from their last force (``_warm_start``, at
        steps that allow it); :class:`hairwarp.Simulation` turns it off in a frame it takes again, whose start is a
        motion the step did not resolve (the last force, put into the next free step, fed it: limp linked hair at one
        step a frame, taken again in 2 steps, whipped to 5.5 m/s). Takes effect at the next step."""
        return self._warm_start_allowed

    @warm_start_allowed.setter
    def warm_start_allowed(self, allowed: bool):
        if bool(allowed) != self._warm_start_allowed:
            self._warm_start_allowed = bool(allowed)
            if self._dt_host is not None:
                self._set_warm_start()
                self.expire_factors()

    def _set_warm_start(self):
        contacts = self.contacts
        if contacts is not None:
            warm = self.contact_warm_start(self._dt_host)
            if contacts.warm_start and not warm:
                contacts.clear_warm()  # stale when a later step turns it on again
            contacts.warm_start = warm
            contacts.warm_gate = WARM_GATE_SPEED
        if self.links is None:
            return
        warm = self._warm_start(self._dt_host)
        gate = 0.0
        if not warm and WARM_GATE_SPEED > 0.0 and self._warm_start(self._dt_host, gated=True):
            warm, gate = True, WARM_GATE_SPEED
        elif warm and WARM_GATE_SPEED > 0.0 and self._dt_host * self._bend_rate_per_second() < WARM_START_BEND_RATE:
            gate = WARM_GATE_SPEED  # limp strands: the force kept falls off with the ends' speed (WARM_START_BEND_RATE)
        if self.links.warm_start and (not warm or gate != self.links.warm_gate):
            # forces kept while the warm start was on would be stale when a later step turns it on again
            self.links.link_warm.zero_()
        self.links.warm_start = warm
        self.links.warm_gate = gate

    def expire_factors(self):
        """Make the next step of links solved after the free step factor its matrices afresh (``plan_factors``):
        :class:`hairwarp.Stepper` calls it at the start of every frame, so that a frame taken again or a run resumed
        from a checkpoint solves as the run that went through it did."""
        self._factor_age = None

    def plan_factors(self):
        """Decide, before a step, whether its sweep of the links solved after the free step factors the strands'
        matrices afresh or solves with those an earlier step kept, and set it where the sweep reads it
        (``carried``; :class:`hairwarp.Stepper` calls it before replaying a captured step).

        A step of one sweep (``links.sweeps_at``) that starts from the links' last force (the warm start) and holds
        no hair contacts of its own may solve with the factors of a step at most :attr:`factor_steps` - 1 before it:
        the matrix, the strand's inertia with its links' dampers, changes with the strands' joints and the links'
        directions, little over a few steps of 1/240 s, and the answer is that of a matrix a few steps old applied
        to this step's forces. The factors are the sweep's costliest part (a 3 x 3 inverse and block products a
        segment); the forces, the answer and the strands' own update are this step's. A strand whose joints have turned
        by more than :attr:`factor_turn` since its factors were made makes its own in the sweep (a violent shake
        turns them by tenths of a radian a frame). Measured, docs/interactions.md ("Factors carried over steps"). A
        link that breaks keeps its damper in the carried factors until the next are made."""
        if not self.link_sweeps:
            return
        links = self.links
        count = self._step_sweeps()
        contacts_respond = self.contacts is not None and self.contacts.response
        carries = count == 1 and links.warm_start and not contacts_respond and self.factor_steps > 1
        age = self._factor_age
        if not carries:
            flags, self._factor_age = (0, 0), None
        elif age is not None and age + 1 < self.factor_steps:
            flags, self._factor_age = (1, 0), age + 1
        else:
            flags, self._factor_age = (0, 1), 0
        if flags != self._carried_set:  # the device array keeps the last flags set
            wp.copy(self.carried, self._carried_presets[flags])
            self._carried_set = flags

    def _warm_start(self, dt: float, gated: bool = False) -> bool:
        """Whether links solved after the free step put their force of the last step into it at steps of ``dt``
        (``StaticLinks.link_warm``, kept after each step's sweeps), the response then solving the change: for the linear
        part of the step the same answer (``kernels.links.link_response_ends``), but the free step's body contacts carry
        the hair's weight with its links. Without, the sweeps moved the held vertices without their contacts and the two
        solves traded the load every step: ``long_hair_shoulders`` with its head still crept at 0.18 mm/s in the 6th
        second at its 8 substeps, 3.7 times the same hair without its colliders, one strand sliding along the shoulders'
        capsule ever faster (1.6 mm/s), and 5.5 mm/s at 2 substeps; with the warm start 0.019 and 0.013 (2 and 16 sweeps
        a step; on the one sweep a step it allows, 0.026 at 8 substeps). At steps shorter than ``WARM_START_STEP`` and a
        free-step rate (``StaticLinks.free_step_rate``) within ``WARM_START_RATE``: the limp linked hair of the
        stability grid jitters at one step a frame, and its lagged force fed that until it burst (4.5-5.5 m/s); the
        mohawk at 2 substeps (rate 8.7) broke 2 links that no 16-substep run breaks. And a typical rate
        (``StaticLinks.warm_rate``) within ``WARM_START_TYPICAL_RATE`` grown by the step's count of warm sweeps: past
        it the lagged force grows from step to step (links of 10 N/m on ``long_hair`` faulted 14 of 30 frames at 8
        substeps, each taken again in 16 steps). Not where hair contacts are
        solved after the free step too, at steps from ``WARM_START_CONTACTS_STEP`` on (their last force is not
        carried), nor in a frame taken again (:attr:`warm_start_allowed`).

        With ``gated``: whether it takes the gated force (:data:`WARM_GATE_SPEED`) where the bounds of step and rate
        leave out the whole one, as :meth:`_set_warm_start` asks: with colliders, a rate up to
        :data:`WARM_GATE_RATE` and a typical rate within :data:`WARM_GATE_TYPICAL_RATIO` times the whole force's
        bound on the sweeps of a step started so; the other conditions hold as they are."""
        links = self.links
        if not links.response or (dt >= WARM_START_STEP and not gated) or not self._warm_start_allowed:
            return False
        contacts = self.contacts
        if contacts is not None and contacts.enabled and contacts.response \
                and dt >= WARM_START_CONTACTS_STEP * (1.0 - 1e-9) and not self.contact_warm_start(dt):
            return False
        if gated:
            return self._gated_links_hold(dt)
        rate, typical = dt * self._link_rate_per_second(), dt * self._warm_rate_per_second()
        return rate <= WARM_START_RATE and typical <= _warm_typical_bound(links.sweeps_at(dt))

    def _gated_links_hold(self, dt: float) -> bool:
        """Whether the links' gated force of the last step (:data:`WARM_GATE_SPEED`) holds at steps of ``dt``: where
        a body holds the hair (the load the force shares is its to take), with links not too stiff for a force lagged
        a step (a free-step rate up to :data:`WARM_GATE_RATE`, a typical rate within :data:`WARM_GATE_TYPICAL_RATIO`
        times the whole force's bound on the sweeps of a step started so)."""
        rate, typical = dt * self._link_rate_per_second(), dt * self._warm_rate_per_second()
        sweeps = self.links.sweeps_starting(dt, rate, cold=True)
        return (self.body_contacts.enabled and rate <= WARM_GATE_RATE
                and typical <= WARM_GATE_TYPICAL_RATIO * _warm_typical_bound(sweeps))

    def contact_warm_start(self, dt: float) -> bool:
        """Whether the hair contacts, solved by the links' sweeps after the free step, put each segment's contact
        force of the last step into it at steps of ``dt`` (``HairContacts.warm_start``), the sweeps then solving the
        change, as the links do (:meth:`_warm_start`): at steps from ``WARM_START_CONTACTS_STEP`` up to
        ``WARM_START_STEP`` (exclusive: 2 to 7 substeps of 30 fps), on the CPU (the sweeps solve the contacts where each
        segment lists its own), not in a frame taken again (:attr:`warm_start_allowed`). Each contact keeps its force
        by the gate of ``WARM_GATE_SPEED`` on its pair's relative speed (``kernels.contacts.contact_warm_forces``).
        From ``WARM_START_STEP`` on (one step a frame) only where :meth:`contacts_cold_at_frame_rate` finds nothing
        against it: a body holds the hair, the strands are not limp and the links take their gated force beside.

        Started cold, a strand resting on other hair over the head fell in the free step, which the head's contacts
        caught and took its whole weight; the sweeps then pushed it off the head with the hair contacts' springs, and
        in the next step it fell again: hair never settled at long steps (``long_hair`` with its head still, 2.9 mm/s
        in the 6th second at 2 substeps with 81 tips moving more than 0.1 mm a frame, 2.5 at 4, 2.4 at one step a
        frame; ``fast_turn`` 3.3 and 2.0 at 2 and 4 substeps). With the warm start, and the links' with it: 0.17 and
        0.31 mm/s, ``fast_turn`` 0.028 and 0.092, no tip moving (docs/interactions.md, "Hair contacts start from their
        last force at long steps"). Whole, the lagged force drove violent motion: ``fast_turn`` at 4 substeps
        broke 28 links (none at 16 substeps) and took 3 frames again after whips, the mohawk broke 19 (2); gated, none
        and 3."""
        contacts = self.contacts
        if not (dt is not None and self.link_sweeps and contacts is not None and contacts.sweeps_contacts
                and dt >= WARM_START_CONTACTS_STEP * (1.0 - 1e-9) and self._warm_start_allowed):
            return False
        return dt < WARM_START_STEP or self.contacts_cold_at_frame_rate(dt) is None

    def contacts_cold_at_frame_rate(self, dt: float) -> str | None:
        """Why hair contacts solved by the links' sweeps start each step cold at a step ``dt`` of ``WARM_START_STEP``
        or longer (one step a frame), or None where they take their last force there (:meth:`contact_warm_start`).

        - Without colliders: the links' force is then not carried (:meth:`_gated_links_hold`), and the contacts' alone,
          held in balance by the links' last force that the free step did not take, kept hair hanging free swinging:
          with its head shape none and its head still, ``long_hair`` 2.81 mm/s in the 6th second warm against 0.28
          cold, ``fast_turn`` 10.9 against 0.43, ``character`` 7.14 against 0.56.
        - Limp strands (a first bending mode at the step below :data:`CONTACT_WARM_STRAND_RATE`): they jitter at one
          step a frame, and the lagged force fed the jitter until it burst.
        - Links too stiff for their gated force (:meth:`_gated_links_hold`), which the contacts' last force balanced."""
        if not self.body_contacts.enabled:
            return "without colliders, where the links carry no force from step to step beside them"
        rate = dt * self._strand_rate_per_second()
        if rate < CONTACT_WARM_STRAND_RATE:
            return (f"for strands this limp (their first bending mode turns {rate:.2g} rad a step, under "
                    f"{CONTACT_WARM_STRAND_RATE:g}), whose jitter a force carried from step to step feeds")
        if not self._gated_links_hold(dt):
            return "beside links too stiff to carry their force from step to step"
        return None

    def _strand_rate_per_second(self) -> float:
        """The strands' first bending mode per second of step (:data:`CONTACT_WARM_STRAND_RATE`): the median over the
        strands of a clamped rod's ``1.875^2 sqrt(EI / (mu L^4))``, ``EI`` the median of its joints' bending stiffness
        times their lengths (the root's, scaled, left out), ``mu`` its mass per length; read from the host once."""
        def rate(mass):
            G, S = self.model.strand_count, self.model.seg_per_strand
            k = self.model.joint_stiffness.numpy().astype(np.float64)[:, 0].reshape(G, S)
            length = self.model.seg_length.numpy().astype(np.float64).reshape(G, S)
            if S > 1:
                ei = np.median(k[:, 1:] * 0.5 * (length[:, 1:] + length[:, :-1]), axis=1)
            else:
                ei = k[:, 0] * 0.5 * length[:, 0]
            total = length.sum(axis=1)
            mu = mass.astype(np.float64).reshape(G, S).sum(axis=1) / total
            return float(np.median(1.8751 ** 2 * np.sqrt(ei / (mu * total ** 4))))
        return self._rate_per_second("strand", 0.0, rate)

    def _bend_rate_per_second(self) -> float:
        """The strands' bending rate per second of step (:data:`WARM_START_BEND_RATE`): the median over the joints of
        ``sqrt(k / I)`` about a bending axis (``_joint_inertia``); read from the host once."""
        return self._rate_per_second("bend", 0.0, lambda mass: float(np.median(np.sqrt(
            self.model.joint_stiffness.numpy().astype(np.float64)[:, 0] / self._joint_inertia()[:, 0]))))

    def _joint_inertia(self) -> np.ndarray:
        """Each joint's child segment's inertia [kg m^2] about the joint, per axis (float64, (G S, 3)): about its
        centre, and about the joint for bending (host read)."""
        m = self.model
        mass = m.seg_mass.numpy().astype(np.float64)
        length = m.seg_length.numpy().astype(np.float64)
        inertia = m.seg_inertia.numpy().astype(np.float64).copy()
        inertia[:, :2] += (mass * length * length / 4.0)[:, None]  # bending: about the joint, not the centre
        return inertia

    def _step_sweeps(self) -> int:
        """The links' sweeps this step takes (``StaticLinks.step_sweeps``: by its length, how it starts and the
        free-step rate at it of the links, or of the hair contacts where the sweeps solve them too, the stiffer)."""
        rate = self._link_rate_per_second()
        contacts = self.contacts
        if contacts is not None and contacts.response and contacts.sweeps_contacts:
            # at a strip of the typical density: the densest strips' rate (twice this) gave the mohawk's contacts more
            # sweeps than the step's count at 3-7 substeps and in its frames taken again at the break step, which they
            # do not need (2 links broken at 4 substeps on them, 3 on the step's count)
            rate = max(rate, self._rate_per_second("contacts", contacts.stiffness, lambda mass: contact_step_rate(
                mass, self.model.seg_length.numpy(), contacts.stiffness, 1.0, density=1.0)))
        return self.links.step_sweeps(self._dt_host, self._dt_host * rate)

    def _rate_per_second(self, name: str, stiffness: float, rate) -> float:
        """A free-step rate per second of step, ``rate(seg_mass)``, read from the host once per ``stiffness`` of the
        springs it is ``name``'s: a new step size costs no copy."""
        kept = self._kept_rates.get(name)
        if kept is None or kept[0] != stiffness:
            kept = self._kept_rates[name] = (stiffness, rate(self.model.seg_mass.numpy()))
        return kept[1]

    def _link_rate_per_second(self) -> float:
        """The links' free-step rate per second of step (``StaticLinks.free_step_rate``)."""
        return self._rate_per_second("links", self.links.stiffness, lambda mass: self.links.free_step_rate(mass, 1.0))

    def _warm_rate_per_second(self) -> float:
        """The links' typical free-step rate per second of step (``StaticLinks.warm_rate``)."""
        return self._rate_per_second("warm", self.links.stiffness, lambda mass: self.links.warm_rate(mass, 1.0))

    def forward_kinematics(self, state, control):
        """Recompute the world quantities of ``state`` from its joints."""
        self._check_state("state", state)
        self._check_control(control)
        forward_kinematics(self.model, state, control, self.executor)

    def teleport(self, state, control):
        """Carry the strands of ``state`` rigidly to the head pose of ``control`` and stop them (a cut, a respawn).

        The joint rotations are relative to the head, so the strands keep their shape; their joint velocities are
        zeroed, the world quantities recomputed, and the body contacts' history cleared. Call it between steps, on
        the state the next step reads, after setting the new pose on ``control`` (give it the head's velocity after
        the jump, usually zero). Host launches only: not for inside a captured graph.
        """
        self._check_state("state", state)
        self._check_control(control)
        state.joint_qd.zero_()
        forward_kinematics(self.model, state, control, self.executor)
        if self.body_contacts.enabled:
            self.colliders.reset_contacts()
        if self.links is not None:
            self.links.link_warm.zero_()
        if self.contacts is not None:
            self.contacts.clear_warm()


    def _accumulate_forces(self, state, control, detect_body: bool = False):
        """The external forces on the segments (drag, links, hair contacts), and with ``detect_body`` the body
        contact candidates of the step (solved inside the integration)."""
        self._force_passes(state, control, detect_body)
        if self.has_forces:
            self._gather_forces()

    def _force_passes(self, state, control, detect_body: bool = False):
        """The first passes of :meth:`_accumulate_forces`: drag, the links' and contacts' own sides, the body
        detection. These do not depend on each other, except that drag and the links add into the same segments
        in that order: on several threads they run as one batch of chunks (one wake of the threads, not four)."""
        model = self.model
        if not self.has_forces:
            if detect_body:
                with self._stage("body collision"):
                    self.colliders.detect(model, state, control, self.dt)
            return
        ex = self.executor
        ex.zero(self.seg_force, self.seg_torque, *([self.seg_implicit_mass] if self.has_implicit_mass else []))
        if self.contacts is not None and self.contacts.detect_each_step:
            with self._stage("hair contacts: detection"):
                self.contacts.detect(model, state)
        with self._fused(ex.batch()):
            # per strand: drag, then its links' side
            with self._fused(ex.chain(model.strand_count, INTEGRATE_MIN_CHUNK)):
                if self.has_drag:
                    with self._stage("dynamics"):
                        ex.launch(
                            articulated.air_drag, model.seg_count,
                            [model.seg_per_strand, model.seg_length, model.drag, control.wind, state.vertex_positions,
                             state.vertex_velocities],
                            [self.seg_force, self.seg_torque], min_chunk=DRAG_MIN_CHUNK,
                        )
                if self.links is not None:
                    with self._stage("links"):
                        self.links.apply_forces(model, state, self.dt, self.seg_force, self.seg_torque)
                if detect_body:
                    with self._stage("body collision"):
                        self.colliders.detect(model, state, control, self.dt)
            if self.contacts is not None:
                with self._stage("hair contacts: forces"):
                    self.contacts.apply_forces(model, state, self.dt)

    def _gather_forces(self):
        """The second passes of :meth:`_accumulate_forces`: every segment adds its links' and its contacts' shares,
        in this order, as one thread would: the same bits for any thread count."""
        model = self.model
        if self.links is not None:
            with self._stage("links"):
                self.links.gather(model, self.seg_force, self.seg_torque, self.seg_implicit_mass)
        if self.contacts is not None:
            with self._stage("hair contacts: forces"):
                self.contacts.gather(model, self.seg_force, self.seg_torque, self.seg_implicit_mass)

    def _integrate(self, state_in, state_out, control):
        model = self.model
        head = [control.bases, self.dt]
        outputs = [state_out.joint_q, state_out.joint_qd, state_out.seg_xform, state_out.vertex_positions,
                   state_out.vertex_velocities, state_out.fault]
        if self.integrator == Integrator.RK4:
            inputs = [model.chains, self.max_rotation_per_step, *head, self.loads, state_in.joint_q,
                      state_in.joint_qd, state_in.fault, self.body_contacts, self.dampers, self.scratch,
                      self.rk_q, self.rk_w, self.rk_dq, self.rk_dw]
            kernel = articulated.integrate_rk4
        else:
            implicit = int(self.integrator == Integrator.IMPLICIT_JOINTS)
            inputs = [model.chains, self.max_rotation_per_step, *head, implicit, self.loads, state_in.joint_q,
                      state_in.joint_qd, state_in.fault, self.body_contacts, self.dampers, self.scratch]
            kernel = articulated.integrate_euler
        # one thread per strand; the fault bits (ORed by any strand) are private per chunk
        self.executor.launch(kernel, model.strand_count, inputs, outputs, min_chunk=INTEGRATE_MIN_CHUNK,
                             private_or=[len(inputs) + len(outputs) - 1])

    def _respond(self, state_in, state_out, control, project: bool = False):
        """The links' and hair contacts' velocity response on the free step's result, then with ``project`` the body
        push-out.

        With links, block Gauss-Seidel sweeps over the strands' colours (``sweeps.link_sweep``; ``links.sweeps_at``
        of the step), from the free step: each colour's strands answer their links and hair contacts, the strands at
        their other ends held at their latest answer (on a GPU the hair contacts are held as dampers, each side's
        share of the pair's backward-Euler damper, split by the two sides' inverse inertias in their strands:
        ``articulated.strand_inverse_inertia``, ``prepare_response``); at steps of the share law's length the bodies
        then answer each strand's sweep (``sweeps.body_answer``). Hair contacts alone are answered in one pass,
        every strand every pair at once with those split dampers (Jacobi between strands;
        ``articulated.interaction_response``), which is exact for a lone pair."""
        model, ex = self.model, self.executor
        implicit = int(self.integrator == Integrator.IMPLICIT_JOINTS)
        links = self.links if self.link_sweeps else None
        contacts = self.contacts if self.contacts is not None and self.contacts.response else None
        # the sweeps this step takes (``StaticLinks.step_sweeps``)
        count = self._step_sweeps() if links is not None else 0
        if links is None and contacts is None:  # responders without a pair: links asked for, none built
            if project:
                with ex.chain(model.strand_count, INTEGRATE_MIN_CHUNK):
                    self.colliders.project(model, state_out, control, self.dt, state_in, detected=True)
            return
        dampers = self.dampers
        held = self.held if links is not None else dampers  # the hair contacts' dampers
        if contacts is not None or self._held_written or model.device.is_cuda or model.device.is_capturing:
            # only the hair contacts' gather writes them: links alone read them zero, as made, and on the CPU they
            # are not zeroed again (0.16 ms a frame of the mohawk's calling thread, the pool's threads waiting); a
            # captured step, replayed after steps of another kind, zeroes them always
            ex.zero(held.A, held.B, held.C, held.force, held.torque)
        self._held_written = contacts is not None
        if contacts is not None:
            # every strand's inverse inertia at the step's start, which each contact's split reads at both its sides
            ex.launch(articulated.strand_inverse_inertia, model.strand_count,
                      [model.chains, self.dt, implicit, self.loads, state_in.joint_q, contacts.entry_counts()],
                      [dampers], min_chunk=INTEGRATE_MIN_CHUNK)
            contacts.prepare_response(model, state_in, state_out, self.dt, dampers)
        if links is not None:
            links.prepare_response(model, state_in, state_out, self.dt)
        # the sweeps solve the hair contacts too, where each segment has its list of them (the CPU)
        contacts_swept = links is not None and contacts is not None and contacts.sweeps_contacts
        # each segment gathers its contacts' and its links' dampers (in this order, into its own blocks), reading
        # other strands' velocities, which the response then rewrites: a chain of its own, the response another
        with ex.chain(model.strand_count, INTEGRATE_MIN_CHUNK):
            if contacts is not None:
                contacts.gather_response(model, state_in, state_out, self.dt, held,
                                         *((self.swept, links.strand_color_array) if contacts_swept else ()))
            if links is not None:
                ex.launch(sweeps.sweep_start, model.strand_count,
                          [model.seg_per_strand, state_out.joint_q, state_out.joint_qd, state_out.vertex_velocities,
                           int(contacts_swept)],
                          [self.free_q, self.free_qd, self.free_velocities, self.answered_velocities,
                           self.answered_sweeps[0]],
                          min_chunk=INTEGRATE_MIN_CHUNK)
        outputs = [state_out.joint_q, state_out.joint_qd, state_out.seg_xform, state_out.vertex_positions,
                   state_out.vertex_velocities, state_out.fault]
        if links is None:
            inputs = [model.chains, self.max_rotation_per_step, control.bases, self.dt, implicit, self.loads,
                      state_in.joint_q, dampers, self._no_body_contacts, self.scratch]
            with ex.chain(model.strand_count, INTEGRATE_MIN_CHUNK):
                ex.launch(articulated.interaction_response, model.strand_count, inputs, outputs,
                          min_chunk=INTEGRATE_MIN_CHUNK, private_or=[len(inputs) + len(outputs) - 1])
                if project:
                    self.colliders.project(model, state_out, control, self.dt, state_in, detected=True)
            return
        inputs = [model.chains, links.seg_link_start, links.seg_b_start, links.b_slot_link, links.link_seg_a,
                  links.link_seg_b, links.stiffness, links.damping, links.link_scale,
                  float(links.geometric_stiffness), float(links.geometric_arm_ratio), links.link_point_a,
                  links.link_point_b, links.link_broken, links.ends, control.bases, self.dt, implicit, self.loads,
                  state_in.joint_q, state_in.seg_xform, state_in.vertex_positions, self.free_q, self.free_qd,
                  self.free_velocities, self.answered_velocities]
        held_on = [held, int(contacts_swept), *(contacts.sweep_inputs() if contacts_swept else self._no_sweep_contacts),
                   self.swept, self.solved, self.scratch, self.factors]
        # symmetric Gauss-Seidel: the colours forward, then back (always forward, the sweeps' error leaned one way
        # at every step, and hair at rest on a body crept); an odd count's last sweep goes the way the next step's
        # first comes back; every sweep after the first solves the same matrices
        turn = self.sweep_turn if count % 2 else 0
        factor_cos_half = math.cos(0.5 * self.factor_turn)
        self.sweep_turn = (self.sweep_turn + count) % 2
        def sweep_colors(sweep, order, redo):
            before, after = self.answered_sweeps[sweep % 2], self.answered_sweeps[1 - sweep % 2]
            for strands in order:
                args = [strands, *inputs, before, after, links.strand_color_array, *held_on, int(sweep > 0),
                        int(sweep == 0 and count > 1), self.carried, factor_cos_half, int(sweep >= count - 1),
                        int(redo), links.strand_redo, self.body_contacts, self.answered, self.answer_factors,
                        self.answer_codes, self.answer_states]
                # the fault bits (the last output) are private per chunk
                ex.launch(sweeps.link_sweep, len(strands), args, outputs, min_chunk=SWEEP_MIN_CHUNK,
                          private_or=[len(args) + len(outputs) - 1])

        for sweep in range(count):
            sweep_colors(sweep, links.color_views if (sweep + turn) % 2 == 0 else reversed(links.color_views), False)
        # at steps up to BREAK_SOLVED_STEP a link that the answer carries past its break breaks within the step, and
        # the strands it tied are solved again without it (``link_response_ends``); on a GPU or in a capture the
        # sweep that does so always runs, its strands unmarked returning at once
        break_solved = self._dt_host is not None and self._dt_host <= float(link_kernels.BREAK_SOLVED_STEP)
        if links.update_warm(model, state_in, self.answered_velocities, self.dt, break_solved) and break_solved:
            if model.device.is_cuda or model.device.is_capturing or ex.host_view(links.strand_redo).any():
                sweep_colors(count, links.color_views, True)
                links.update_warm(model, state_in, self.answered_velocities, self.dt)
        if contacts_swept and contacts.warm_start:  # their force in the answer, for the next free step
            contacts.update_warm(model, state_in, self.answered_velocities)
        if project:
            with ex.chain(model.strand_count, INTEGRATE_MIN_CHUNK):
                self.colliders.project(model, state_out, control, self.dt, state_in, detected=True)

    # -- tools ----------------------------------------------------------------------------

    def joint_accelerations(self, state, control, *, dt: float = 0.0, implicit: bool = False,
                            seg_force=None, seg_torque=None, seg_implicit_mass=None) -> wp.array:
        """Joint accelerations of ``state`` [rad/s^2] by ABA alone.

        The external forces are those the solver's stages accumulate now, or ``seg_force`` and
        ``seg_torque`` (world, torque about each segment's origin) when given, with
        ``seg_implicit_mass`` (the semi-implicit inertia of interaction springs [kg]). With ``implicit``
        it solves ``(M + hC + h^2 K) qdd = -K theta - (C + hK) w - bias`` as the ``implicit_joints``
        integrator does with step ``dt``.
        """
        model = self.model
        self._check_state("state", state)
        self._check_control(control)
        self.dt.fill_(float(dt))
        self._dt_host = None
        if seg_force is not None:
            extra = self.seg_implicit_mass if seg_implicit_mass is None else seg_implicit_mass
            loads = self._loads(seg_force, seg_torque, True, extra, seg_implicit_mass is not None)
        else:
            if self.has_forces:
                self._accumulate_forces(state, control)
            loads = self.loads
        wp.launch(
            articulated.aba_accelerations,
            dim=model.strand_count,
            inputs=[model.chains, control.bases, self.dt, int(implicit), loads, state.joint_q, state.joint_qd],
            outputs=[self.scratch],
            device=model.device,
        )
        return self.joint_qdd

    def persistent_arrays(self) -> dict[str, wp.array]:
        """Device arrays the stages keep from one step or frame to the next besides the :class:`State`: what a
        checkpoint must hold for a run to go on exactly (``Simulation.checkpoint``). A stage that keeps state across
        steps adds its arrays here, and only here. Scratch that every step rewrites before reading is left out.

        Returns:
            name -> array: ``links.link_broken`` and ``links.link_broken_total`` (links break for good),
            ``links.link_warm`` (each link's force of the last step, which the next free step takes),
            ``colliders.vert_exempt`` (vertices inside a collider at rest leave the exemption once out),
            ``contacts.contact_counter`` and ``contacts.contact_overflow`` (the last step's count, read for the
            frame's report, and the sticky overflow flag; the pairs themselves are detected anew at every frame
            or step from the state), ``contacts.warm_force`` and ``contacts.warm_torque`` (each segment's hair contact
            force of the last step, which the next free step takes), ``body_contacts.slip``, ``body_contacts.share``,
            ``body_contacts.force``, ``body_contacts.removed`` and ``body_contacts.away`` (each vertex's speed over
            its collider, its friction share at long steps, the force the collider put on it and the slip it took
            away in the last step it held the vertex, from which the next step starts, and the time since), and
            ``body_contacts.answer_force`` (each vertex's contact force at the end of the bodies' answer to the
            links' sweeps, from which the next step's answer starts).
        """
        out = {}
        if self.body_contacts.enabled:
            out["body_contacts.slip"] = self.body_contacts.slip
            out["body_contacts.share"] = self.body_contacts.share
            out["body_contacts.force"] = self.body_contacts.force
            out["body_contacts.removed"] = self.body_contacts.removed
            out["body_contacts.away"] = self.body_contacts.away
            out["body_contacts.answer_force"] = self.body_contacts.answer_force
        if self.links is not None:
            out["links.link_broken"] = self.links.link_broken
            out["links.link_broken_total"] = self.links.link_broken_total
            out["links.link_warm"] = self.links.link_warm
        if self.colliders is not None and self.colliders.vert_exempt is not None:
            out["colliders.vert_exempt"] = self.colliders.vert_exempt
        if self.contacts is not None:
            out["contacts.contact_counter"] = self.contacts.contact_counter
            out["contacts.contact_overflow"] = self.contacts.contact_overflow
            out["contacts.warm_force"] = self.contacts.warm_force
            out["contacts.warm_torque"] = self.contacts.warm_torque
        return out

    def measure_start_speed(self, state):
        """Take ``state``'s own motion as the run's start (the first step does, on the state it starts from; a run
        restored from a checkpoint calls it): hair set moving at the start is explained by its start
        (``speed_terms``). The larger of its fastest vertex and what its joint velocities move a tip at most
        (``sum |w_k| r_k``, ``r_k`` from joint k to the tip), so joint velocities set without
        :meth:`forward_kinematics` count too. Reads the state from the device, once."""
        self._check_state("state", state)
        G = self.model.strand_count
        w = np.linalg.norm(state.joint_qd.numpy().astype(np.float64).reshape(G, -1, 3), axis=2)
        v = np.linalg.norm(state.vertex_velocities.numpy().astype(np.float64), axis=1)
        speeds = np.concatenate([(w * self._reach).sum(axis=1), v])
        self._start_speed_host = float(speeds.max()) if np.isfinite(speeds).all() else 0.0
        self._start_pending = False

    def speed_terms(self, control=None) -> dict[str, float]:
        """The speeds [m/s] :meth:`speed_bound` adds up: ``carried``, the fastest the head or the root frames have
        carried a point of the hair (``Control.carried_speed``); ``colliders``, the fastest a world collider has
        moved a point of itself; ``wind``, the strongest wind; ``fall``, ``sqrt(2 |g| L)`` for the longest strand
        ``L`` (a strand swinging down from level under gravity); ``start``, the hair's own speed where the run started
        (:meth:`measure_start_speed`). ``control``: default the last step's."""
        control = self._control if control is None else control
        g = self.model.gravity
        return {
            "start": self._start_speed_host,
            "carried": float(getattr(control, "carried_speed", 0.0)),
            "colliders": float(getattr(self.colliders, "peak_speed", 0.0)) if self.colliders is not None else 0.0,
            "wind": float(getattr(control, "wind_speed", 0.0)),
            "fall": math.sqrt(2.0 * math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]) * self._longest_strand),
        }

    def restore_speed_terms(self, control, terms: dict[str, float]):
        """Put back what :meth:`speed_terms` had seen (``start``, ``carried``, ``colliders``, ``wind``), as a
        checkpoint holds them: a restored run is checked against the bound it had."""
        self._start_speed_host = float(terms["start"])
        self._start_pending = False
        control.carried_speed = float(terms["carried"])
        control.wind_speed = float(terms["wind"])
        if self.colliders is not None:
            self.colliders.peak_speed = float(terms["colliders"])

    def fastest_guide(self) -> tuple[float, float] | None:
        """The fastest guide vertex at the last :meth:`check` [m/s] and the speed the run's motion explains [m/s]
        (the sum of :meth:`speed_terms`, which :meth:`speed_bound` takes ``speed_margin`` times); None where that
        check measured no speed (no step yet, or ``speed_margin`` infinite). One small read from the device."""
        if self._control is None or not self.speed_margin < math.inf:
            return None
        return float(self.strand_speed.numpy().max()), sum(self.speed_terms().values())

    def speed_bound(self, control=None) -> float:
        """The fastest [m/s] a guide vertex may move at the end of a frame: ``speed_margin`` times the sum of
        :meth:`speed_terms`, the speed the run's own motion explains. Hair that whips faster than a few times what
        moves it is a blow-up that has not yet turned into a non-finite state."""
        return self.speed_margin * sum(self.speed_terms(control).values())

    def check(self, state, frame: int, *, substeps: int | None = None):
        """Raise :class:`SimulationFault` if a stage flagged a fault; call once per output frame.

        First checks the speed of every guide vertex against :meth:`speed_bound` (one launch, after a step has
        run), then reads one integer from the device. Contact overflow is not fatal and is returned as the
        bit so the caller can report it.
        """
        if self._control is not None and self.speed_margin < math.inf:
            self._check_state("state", state)
            self._speed_bound.fill_(self.speed_bound())
            self.executor.launch(articulated.hair_speed, self.model.strand_count,
                                 [self.model.seg_per_strand, self._speed_bound, state.vertex_velocities],
                                 [self.strand_speed, state.fault], min_chunk=INTEGRATE_MIN_CHUNK, private_or=[4])
        bits = int(state.fault.numpy()[0])
        fatal = bits & ~int(Fault.CONTACT_OVERFLOW)
        if fatal:
            raise self._fault(Fault(bits), frame, substeps)
        return Fault(bits)

    def explicit_step_bound(self) -> float:
        """The longest step [s] at which joint springs and damping taken explicitly (``semi_implicit``, ``rk4``) stay
        stable, by a linear estimate: each joint axis an oscillator of the child segment's inertia about the joint
        (about its own axis ``m r^2 / 2``, the least for thin strands), a chain's fastest mode twice the joint's
        own; within the bound of the integrator, ``h w <= 2.8`` (RK4) or 2 (Euler), for the spring's ``w`` and the
        damper's rate alike. It errs on the safe side. Substeps a frame that the shipped scenes need, measured
        (10 and 5 frames) against this estimate: tiny 515 (689) under rk4 and 375 (964) under semi_implicit;
        long_hair 430 (563) and 620 (788)."""
        return self._explicit_step_limit()[0]

    def _explicit_step_limit(self) -> tuple[float, int]:
        """:meth:`explicit_step_bound` and the segment whose joint sets it."""
        m = self.model
        inertia = self._joint_inertia()
        rate = np.maximum(np.sqrt(m.joint_stiffness.numpy() / inertia), m.joint_damping.numpy() / inertia)
        reach = 2.8 if self.integrator == Integrator.RK4 else 2.0
        fastest = int(np.argmax(rate.max(axis=1)))
        return float(reach / (2.0 * rate[fastest].max())), fastest

    def _fault(self, bits: Fault, frame: int, substeps: int | None) -> SimulationFault:
        """The fault of the stage that drives it, with advice that works for that stage.

        The bits say where a bound was crossed; the stage that drives the crossing is found from the step's
        parameters (``_dynamics_driver``): the integrate stage is where links, hair contacts, air drag or an
        undamped twist show up first, and the body contact response is where hair blown or whipped into a still
        collider does. Each piece of advice was run on the case it names (``tests/test_faults.py``).
        """
        dt = self._dt_host
        per_frame = f" ({substeps} substep{'s' if substeps != 1 else ''} per frame)" if substeps else ""
        step = f"dt = {dt:.3g} s{per_frame}"
        more = "raise sim.substeps" if substeps else "use a smaller dt"
        bound = f"{self.max_rotation_per_step:g} rad in one step (sim.max_rotation_per_step)"
        fatal = bits & ~Fault.CONTACT_OVERFLOW
        rotation_only = not fatal & ~(Fault.JOINT_SPEED | Fault.COLLISION_SPEED)
        bad_input = _nonfinite_control(self._control)
        if bad_input:
            stage = "control input"
            what = f"the control's {bad_input} held non-finite values, which the step took"
            advice = ("give the control finite values (set_head, set_wind and set_root_frames refuse others; an "
                      "array written in place is not checked)")
        elif rotation_only and self.max_rotation_per_step < DEFAULT_MAX_ROTATION:
            # a bound set below its default: the bound, not the hair, is what the run crossed
            stage = ("collision (body contact)" if bits & Fault.COLLISION_SPEED and not bits & Fault.JOINT_SPEED
                     else DYNAMICS_STAGE)
            what = f"a joint bent more than {bound}"
            advice = (f"raise sim.max_rotation_per_step (now {self.max_rotation_per_step:g}, default "
                      f"{DEFAULT_MAX_ROTATION:g}; a bound it sets below the default stops hair that is fine), or "
                      f"{more} (now {step})")
        elif self._contacts_overrun(bits):
            # a threshold far past a wisp's thickness stacks hundreds of contacts on each vertex: no step holds them
            stage = "hair contacts (more pairs than slots)"
            what = "the strands blew up under far more hair contact pairs than the slots hold"
            advice = f"{self.contacts.overflow_advice()}; more substeps do not help"
        elif bits & Fault.INTERACTION_RESPONSE:
            stage = "links and hair contacts (response)"
            what = "their response after the free step changed a joint by more than half a turn, or left it non-finite"
            advice = self._response_advice(dt)
        elif bits & (Fault.NONFINITE_COLLISION | Fault.COLLISION_SPEED) and not bits & (
                Fault.NONFINITE_DYNAMICS | Fault.JOINT_SPEED):
            what = ("the body contact response produced an invalid strand" if bits & Fault.NONFINITE_COLLISION
                    else f"the body contact response bent a joint more than {bound}")
            stage, advice = self._collision_advice(dt, more, step)
        else:
            if bits & Fault.NONFINITE_DYNAMICS:
                what = "the joint state became non-finite"
            elif bits & Fault.JOINT_SPEED:
                what = f"a joint bent more than {bound}"
            else:
                what = self._speed_report()
            stage, advice = self._dynamics_driver(dt, substeps, more, step)
        message = f"simulation fault at frame {frame} in {stage}: {what}. To fix: {advice}."
        return SimulationFault(message, frame=frame, stage=stage, bits=int(bits))

    def _contacts_overrun(self, bits: Fault) -> bool:
        """Whether the frame's hair contacts overflowed their slots with ``interactions.THRESHOLD_PAIRS`` a guide
        vertex or more (``HairContacts.overflow_advice``), which drives any fault beside them."""
        contacts = self.contacts
        return bool(bits & Fault.CONTACT_OVERFLOW) and contacts is not None and contacts.threshold_overrun()

    def _response_advice(self, dt: float) -> str:
        """Advice for a fault the links' and hair contacts' response drives: lower the stiffer of the two for its
        segments' mass (both, within a factor 10 of each other), turn it off, or take the links in the free step."""
        rates = self._rates(dt, responders=True)
        top = max(rates.get("links", 0.0), rates.get("contacts", 0.0))
        parts, off = [], []
        for name, key, part in (("links", "links", self.links), ("contacts", "interactions", self.contacts)):
            if part is not None and rates.get(name, 0.0) >= 0.1 * top:
                parts.append(f"lower {key}.stiffness (now {part.stiffness:g} N/m)")
                off.append(f"{key}.enabled = false")
        advice = ", ".join(parts) + (f", or turn them off ({' or '.join(off)})" if off else "")
        if self.links is not None and self.links.response and "links.enabled = false" in off:
            advice += ', or solve the links in the free step (links.response = "link")'
        return advice

    def _speed_report(self) -> str:
        """What the hair speed check found: the fastest guide vertex against the bound and its terms."""
        speeds = self.strand_speed.numpy()
        strand = int(np.argmax(speeds))
        terms = self.speed_terms()
        parts = ", ".join(f"{name} {value:.3g}" for name, value in (
            ("start", terms["start"]), ("head and roots", terms["carried"]), ("colliders", terms["colliders"]),
            ("wind", terms["wind"]), ("free fall", terms["fall"])) if value > 0.0)
        speed = f"{float(speeds[strand]):.3g} m/s" if np.isfinite(speeds[strand]) else "a non-finite speed"
        return (f"a guide vertex moved at {speed} (strand {strand}), more than "
                f"sim.speed_margin = {self.speed_margin:g} times the {sum(terms.values()):.3g} m/s the motion "
                f"explains ({parts} m/s)")

    def _rates(self, dt: float, responders: bool = False) -> dict[str, float]:
        """Each free-step force stage's rate times the step (a stiff explicit spring: ``h sqrt(k/m)``), for
        ``_dynamics_driver``; a stage that is off, or solved after the free step (its response) unless
        ``responders``, has none."""
        model = self.model
        mass = model.seg_mass.numpy().astype(np.float64)
        rates = {}
        links = self.links
        if links is not None and (responders or not links.response) and links.link_count > 0 \
                and links.stiffness > 0.0:
            rates["links"] = links.free_step_rate(mass, dt)
        contacts = self.contacts
        if contacts is not None and (responders or not contacts.response) and contacts.stiffness > 0.0:
            rates["contacts"] = contact_step_rate(mass, model.seg_length.numpy(), contacts.stiffness, dt)
        if model.drag > 0.0:
            rates["drag"] = dt * float((model.drag * model.seg_length.numpy() / mass).max())
        return rates

    def _dynamics_driver(self, dt: float, substeps: int | None, more: str, step: str) -> tuple[str, str]:
        """The stage that drives a fault of the free step (a non-finite joint, a joint or a vertex too fast), and
        advice that works for it, in this order: links or hair contacts stiffer than the free step holds, or far
        stiffer than even their response after it holds, air drag on strands too light for it, an undamped twist, an
        explicit integrator's step bound, then the step."""
        model = self.model
        rates = self._rates(dt)
        stiff = [(label, key, part, rates[rate], limit) for label, key, rate, part, limit in (
            ("static links", "links", "links", self.links, LINK_RATE_LIMIT),
            ("hair contacts", "interactions", "contacts", self.contacts, CONTACT_RATE_LIMIT))
            if rates.get(rate, 0.0) > limit]
        if stiff:
            # the rate goes as sqrt(k): the stiffness at the limit is k (limit / rate)^2
            fixes = [f'{key}.response = "step" (solved after the free step), {key}.stiffness <= '
                     f'{part.stiffness * (limit / rate) ** 2:.3g} N/m (now {part.stiffness:g}), or '
                     f'{key}.enabled = false' for _, key, part, rate, limit in stiff]
            stage = " and ".join(label for label, *_ in stiff) + " (forces in the free step)"
            advice = (f"their springs are too stiff for the free step at {step}, which takes them explicitly; "
                      f"more substeps do not help. Set " + "; and ".join(fixes))
            return stage, advice
        # the wind's drag changes a vertex's velocity by up to (drag L / m) h |wind| a step, explicitly
        windy = self._wind_driver(dt, more, step, kick=rates.get("drag", 0.0) * self.speed_terms()["wind"])
        if windy is not None:
            return windy
        responding = self._rates(dt, responders=True)
        if any(part is not None and part.response and responding.get(name, 0.0) > RESPONSE_RATE_LIMIT
               for name, part in (("links", self.links), ("contacts", self.contacts))):
            # springs this stiff whip the hair even solved after the free step (``RESPONSE_RATE_LIMIT``)
            return "links and hair contacts (response)", self._response_advice(dt)
        if rates.get("drag", 0.0) > DRAG_RATE_LIMIT:
            linear = float((model.seg_mass.numpy() / model.seg_length.numpy()).min())
            stage = "air drag (strands.drag) on light strands"
            advice = (f"the strands weigh {linear:.3g} kg/m, so light that the air drag (strands.drag = "
                      f"{model.drag:g}) would stop them {rates['drag']:.3g} times over within one step (drag L / m "
                      f"times the step; it is taken explicitly), which neither more substeps nor more drag resolve: "
                      f"give them the weight of a wisp of hair "
                      f"(raise strands.density or strands.radius), or set strands.drag = 0")
            return stage, advice
        stiffness = model.joint_stiffness.numpy()
        damping = model.joint_damping.numpy()
        stiff = bool(np.any(stiffness > 0.0))
        free_twist = stiff and not np.any(stiffness[:, 2] > 0.0) and not np.any(damping > 0.0)
        explicit = self.integrator in (Integrator.SEMI_IMPLICIT, Integrator.RK4)
        stage = DYNAMICS_STAGE
        if free_twist:
            advice = ("without damping or twist stiffness the twist about each segment's own axis, which has the "
                      "least inertia (m r^2 / 2), is free and undamped, and no step size holds it: give "
                      "strands.damping a value (2e-7, the default, holds it)")
            if explicit:
                advice += (f' and use integrator = "implicit_joints" ({self.integrator.name.lower()} takes the '
                           f"joint springs explicitly, and more substeps alone do not help)")
            return stage, advice
        if explicit and stiff:
            name = self.integrator.name.lower()
            bound, seg = self._explicit_step_limit()
            count = math.ceil(dt * substeps / bound) if substeps else 0
            need = (f"sim.substeps = {count} or more, now {substeps}" if substeps
                    else f"dt <= {bound:.2g} s, now {dt:.3g} s")
            S = model.seg_per_strand
            shortest = float(model.seg_length.numpy()[seg])
            advice = (f"{name} takes the joint springs and damping explicitly, and these strands need steps of "
                      f"about {bound:.2g} s for them ({need}; the fastest joint is on strand {seg // S}, whose "
                      f"segments are {shortest * 1e3:.3g} mm): use integrator = \"implicit_joints\" (no such "
                      f"bound)")
            if count <= EXPLICIT_SUBSTEPS_WORTH_NAMING:
                advice += (", that many substeps, or lower strands.damping and strands.twist_stiffness (the twist "
                           "about a strand's own axis has the least inertia, m r^2 / 2, and sets the bound)")
            return stage, advice
        if not stiff:
            return stage, (f"a chain without joint stiffness whips freely: give strands.bend_stiffness a value, raise "
                           f"strands.damping or strands.drag, or {more} (now {step})")
        return stage, f"{more} (now {step}), raise strands.drag or strands.damping, or slow the head motion"

    def _resolved_speed(self, dt: float) -> float:
        """The speed [m/s] at which a vertex stopped (by a contact) or swung within one step turns the shortest
        segment by ``max_rotation_per_step``: ``max_rotation_per_step * l / dt``."""
        return self.max_rotation_per_step * float(self.model.seg_length.numpy().min()) / dt

    def _wind_driver(self, dt: float, more: str, step: str, lead: str = "", kick: float | None = None
                     ) -> tuple[str, str] | None:
        """The wind as the stage that drove a fault, with its advice, where ``kick`` (the speed it gives a vertex in
        a step; default the wind's own, which hair it blows reaches) is at least half the speed a step resolves
        (``_resolved_speed``); else None. Raising the drag, the advice for hair that swings too fast, would blow
        such hair harder."""
        wind = self.speed_terms()["wind"]
        resolved = self._resolved_speed(dt)
        if (wind if kick is None else kick) < 0.5 * resolved:
            return None
        if kick is not None:
            lead = ((f"{lead}, " if lead else "") + f"the wind at {wind:.3g} m/s changes the strands' velocities by "
                    f"up to {kick:.3g} m/s a step, more than a step resolves (about {resolved:.3g} m/s)")
        else:
            lead = f"{lead}, blown by the wind at {wind:.3g} m/s"
        return "air drag (wind.velocity)", (f"{lead}: lower wind.velocity, or {more} (now {step}; a step resolves "
                                            f"speeds in proportion to the substeps)")

    def _collision_advice(self, dt: float, more: str, step: str) -> tuple[str, str]:
        """Stage and advice of a body contact fault: a collider that moved too fast for the step (its own speed,
        known from the control and the collider poses), or hair that reached a slow one too fast, and what drove
        the hair."""
        terms = self.speed_terms()
        collider = terms["carried"] + terms["colliders"]
        # a vertex stopped at speed u by a contact on a segment of length l turns it at u / l: the bound is crossed
        # from u = max_rotation_per_step * l / dt on
        resolved = self._resolved_speed(dt)
        stage = "collision (body contact)"
        if collider >= 0.5 * resolved:
            return stage, (f"the head or a collider moved at up to {collider:.3g} m/s, too far for the step (a contact "
                           f"resolves about {resolved:.3g} m/s): set head.teleport_distance for cuts and jumps, slow "
                           f"the collider, or {more} (now {step})")
        hair = float(self.strand_speed.numpy().max()) if self._control is not None else 0.0
        hair = (f"; guides at up to {hair:.3g} m/s" if math.isfinite(hair) and hair > 0.0
                else "; some guides non-finite" if not math.isfinite(hair) else "")
        lead = (f"the head and colliders moved at most {collider:.3g} m/s, but the hair reached them faster than a "
                f"contact resolves in one step (about {resolved:.3g} m/s{hair})")
        windy = self._wind_driver(dt, more, step, lead)
        if windy is not None:
            return windy
        driver, advice = self._dynamics_driver(dt, None, more, step)
        return driver, f"{lead}: {advice}"


def _nonfinite_control(control) -> str:
    """The names of the arrays of ``control`` (None: none) that hold non-finite values, or ''."""
    if control is None:
        return ""
    arrays = {"head_xform": control.head_xform, "head_velocity": control.head_velocity,
              "head_acceleration": control.head_acceleration, "wind": control.wind}
    if control.bases.per_strand:
        arrays.update({"root frames": control.bases.xform, "root frame velocities": control.bases.velocity,
                       "root frame accelerations": control.bases.acceleration})
    return ", ".join(name for name, a in arrays.items() if not np.isfinite(a.numpy()).all())


def state_arrays(state) -> dict[str, np.ndarray]:
    """Host copies of a state's arrays (for tests and tools; not for the step loop)."""
    return {name: getattr(state, name).numpy() for name in
            ("joint_q", "joint_qd", "seg_xform", "vertex_positions", "vertex_velocities")}


_NOT_TIMED = contextlib.nullcontext()


class _StageTimer:
    """Adds the wall time of its block, from a synchronised device to a synchronised device, to ``seconds[name]``
    (``Solver.profile_stages``)."""

    __slots__ = ("seconds", "name", "device", "start")

    def __init__(self, seconds: dict, name: str, device):
        self.seconds, self.name, self.device = seconds, name, device

    def __enter__(self):
        wp.synchronize_device(self.device)
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        wp.synchronize_device(self.device)
        self.seconds[self.name] = self.seconds.get(self.name, 0.0) + time.perf_counter() - self.start
