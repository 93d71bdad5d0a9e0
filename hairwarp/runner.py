"""Headless runs: a scene advanced frame by frame into a USD cache and a preview picture.

:class:`Stepper` owns what every embedding of ``Solver.step`` needs: substeps per frame, the
swap parity of the two states, optional graph capture, and the fault check once per frame.
:class:`Simulation` builds everything a scene asks for; :func:`simulate` is ``hairwarp run``.
"""

from __future__ import annotations

import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from hairwarp.interactions import REBUILD_FRAMES
from hairwarp.kernels.types import Fault
from hairwarp.model import Model, resolve_device
from hairwarp.motion import MotionSample, rotate_floats
from hairwarp.solver import DYNAMICS_STAGE, WARM_START_STEP, SimulationFault, Solver
from hairwarp.state import hair_ball

#: Shortest step [s] at which ``response = "auto"`` (links and hair contacts) solves their forces after the free step,
#: on the relative motion of each pair (``kernels.articulated.interaction_response``): at 7 substeps of 30 fps and
#: fewer. There it keeps links whole and the hair in one piece (``fast_turn`` at 2 substeps: 13 broken links
#: instead of 9,830), where the semi-implicit mass made a third of the segments a hundred times heavier. From 3 to
#: 6 substeps the finer-step forms broke links by the thousand (the mohawk: 4,870, 2,583, 1,495 and 610 broken in
#: its 2.5 s, against 168, 128, 117 and 69 with the response; ``fast_turn`` at 4: 458 against 4); at the shipped
#: 8 substeps they settle hair at rest sooner (``docs/interactions.md``). The body contacts' friction changes law at
#: the same step (``kernels.articulated.CONTINUOUS_FRICTION_STEP``).
AUTO_RESPONSE_DT = 1.0 / 220.0

#: Links' free-step rate (``StaticLinks.free_step_rate``: the step times ``sqrt(k / m)``, ``k`` the most link
#: stiffness on one segment) past which ``links.response = "auto"`` solves them after the free step at any step. In
#: the free step each link's backward-Euler force is solved alone, against a bound of its ends' inverse masses, and
#: where several links pull one segment their forces overshoot: ``long_hair_shoulders`` at 2.4 N/m at 1 cm (rate 1.53
#: at its 8 substeps) with its head still gained up to 5.4e-3 J in a frame in the step (4e-4 of its energy),
#: 2.6e-7 J solved after it (round-off). Measured with the head still, hair contacts off, the largest rise over a
#: frame in 5 s: ``long_hair`` at rates 0.62 (shipped), 0.74 and 0.87: 1.1e-7, 2.4e-7 and 6.8e-7 of its energy;
#: ``long_hair_shoulders`` at 0.77 and 0.99: 1.6e-7 and 2.2e-5. Five strands tied side by side and parted by a
#: sphere (``tests/test_collision_scenes.py``) gain from a lower rate: 2.3e-5 a frame at 0.56, 9.4e-5 at 0.67, none
#: at 0.47. Below the rate the free step's form stays: it costs less.
LINK_STEP_RATE = 0.7

#: How many times what the median linked segment's dampers may take in a step (``kernels.links.damper_cap``: the
#: bound less the stiffness's own damper of the step) the links' damping in the free step may ask before the run
#: notes that most of it is capped: ``character`` ships 1.35 times it at its 10 substeps, where the cap holds back
#: only the busier segments' links.
LINK_DAMPING_NOTE_LOAD = 2.0

#: The fewest guide segments a curl of the scalp generator (``groom.curl_period``) spans before a run warns that the
#: guides cannot draw it: four draw a helix's turn as a square in projection, fewer as a zigzag.
CURL_SEGMENTS = 4

#: Hair contacts' free-step rate (``interactions.contact_step_rate``: the step times ``sqrt(k / m)``, with their largest
#: density factor and the median segment) past which ``interactions.response = "auto"`` solves them after the free step
#: at any step, as :data:`LINK_STEP_RATE` does the links. In the free step their spring is explicit beside a
#: semi-implicit mass. On the stability benchmark's turn at 1/240 s (``bench_spring_stability``) with the default
#: scene's links beside them it held contacts of 70 N/m (rate 5.5) and blew up at 100 (6.5); with the contacts alone,
#: over three draws of gravity (relative changes 0, +-1e-5), 45 and 50 N/m (4.4, 4.6) held in all three, 55 (4.8) and 65
#: (5.25) blew up in one, 60, 70 and 80 (5.05-5.9) in two, 100 (6.5) in three, at 1.03-1.37 s (since the vertex-face
#: push fades in from the strands' lines, 2026-12-07; before it 55 N/m held in all three and 65 blew up in three).
#: Solved after it the same contacts hold the benchmark's whole sweep. The shipped scenes' contacts lie below it
#: (1.7-1.8 at their steps) but the mohawk's (5.2, its segments of a few millimetres), which ``"auto"`` solves after the
#: free step: its tips then lie 1.55 mm RMS from a 32-substep run over 45 frames against 6.44 in the free step, for 1.24
#: times the frame. In the free step below it they cost less.
CONTACT_STEP_RATE = 4.5

#: Fastest guide vertex of a run, as a multiple of the speed its motion explains (``Solver.speed_bound`` over
#: ``sim.speed_margin``), from which the run's notes say that hair whipping this hard may be the step's
#: (``Simulation.whip_note``). Measured peaks: the shipped scenes 0.51-1.21; a 3 rev/s spin and the shipped motions
#: played ten times as fast at 32 substeps 1.17-1.60 (``long_hair`` at its 8: 1.40); at the shipped 8 substeps, where
#: linked hair whips harder than at finer steps, 2.23 (``long_hair_shoulders``' nod, 19.0 m/s against 9.9 at 32),
#: 2.27 (its spin, 26.3 against 16.5) and 2.29 (``fast_turn``'s spin, 21.7 against 15.1); since the links' sweeps take
#: their geometric stiffness the shoulders' nod peaks at 1.81 (15.4 m/s) and its spin at 16.9 m/s. ``sim.whip_ratio``
#: (2 by default) takes the frames past it again in finer steps (the nod 11.7 m/s, the spins 18.3 and 16.4-17.0), so
#: the note is left for guides that whip so even then, or with those retakes off.
WHIP_NOTE_RATIO = 2.0

#: Two takes of a frame whose fastest guide vertices lie within this fraction of each other agree: the step does not
#: make that speed. A frame taken again for a whip (``sim.whip_ratio``) in which the finer take agrees with the one
#: before it is kept as taken, and the motion, not the step, drives its whip: ``long_hair`` slid 0.1 m at 5 Hz (ten
#: g) whips its tips at 28-31 m/s at 32 and 128 substeps alike, 5 times the speed its motion explains, and its
#: frames taken in 8 and 16 steps end at 13.8 and 14.5 m/s, 22.6 and 22.6, 19.8 and 18.4; a step's own whip parts its
#: takes far more (the shoulders' nod ten times as fast 19.0 m/s at 8 steps, 10.6 at 16; frame 18 of the slide 36.3
#: and 23.8).
WHIP_AGREEMENT = 0.25

#: Frames after one whose whip proved the motion's (:data:`WHIP_AGREEMENT`) that are not taken again for a whip: such
#: motion whips the hair frame after frame, and each frame would be taken three times for nothing (the slide above:
#: 48 of 60 frames, 4 times the run's time).
WHIP_REST_FRAMES = 15

_STATE_ARRAYS = ("joint_q", "joint_qd", "seg_xform", "vertex_positions", "vertex_velocities", "fault")


def _agree(a: float, b: float) -> bool:
    """Whether two takes' fastest guide vertices [m/s] lie within :data:`WHIP_AGREEMENT` of the larger. A finer take
    much faster than the one before does not agree: the step may still drive that whip (the shoulders' spin at 3
    rev/s, frame 19: 3.98 times the speed the motion explains in 16 steps, 1.43 in 32; counted as not slowed by
    16 steps, the frame was kept at 46.1 m/s, against 18.3 with its take in 32)."""
    return abs(a - b) <= WHIP_AGREEMENT * max(a, b)


def _host_copy(array) -> np.ndarray:
    """A host copy of ``array`` that does not change with it (a CPU array's ``numpy()`` is a view)."""
    host = array.numpy()
    return host.copy() if array.device.is_cpu else host


class Stepper:
    """Advances a solver by whole frames of ``substeps`` steps, swapping two states.

    Args:
        solver: the :class:`hairwarp.Solver`.
        dt: step size [s].
        substeps: steps per frame.
        control: the :class:`hairwarp.Control` the steps read; ``before_step(t, control)`` may
            update it from the host before each step, with ``t`` the time at the step's end: the
            step puts the new state's roots on the head pose the control holds.
        state: the :class:`hairwarp.State` to start from (a state of the solver's model, used in place as the
            first of the two); default ``model.state()``, the groom's shape at rest.
        use_graph: capture one step per parity in a Warp graph and replay it; default on CUDA. Never on the
            CPU with a solver of more than one thread: a graph would replay on one.
    """

    def __init__(self, solver: Solver, *, dt: float, substeps: int = 1, control=None, state=None, use_graph=None):
        model = solver.model
        self.solver = solver
        if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
            raise ValueError(f"substeps must be an integer >= 1 (steps per frame), got {substeps!r}")
        if isinstance(dt, bool) or not isinstance(dt, int | float | np.floating | np.integer) or not 0 < dt < math.inf:
            raise ValueError(f"dt must be a finite number of seconds > 0, got {dt!r}")
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.control = control if control is not None else model.control()
        self.states = [state if state is not None else model.state(), model.state()]
        if state is not None:
            self.states[1].assign(state)
        self.parity = 0
        self.time = 0.0
        self.frame = 0
        # A captured graph replays its launches on one thread: on the CPU with several threads the eager step,
        # whose launches the executor spreads over the threads, is the faster (hairwarp.executor).
        executor = getattr(solver, "executor", None)
        threaded = executor is not None and executor.parallel
        self.use_graph = (model.device.is_cuda if use_graph is None else bool(use_graph)) and not threaded
        self._graphs = {}  # (parity, sweep turn) -> the captured step
        self._frame_step = 0  # the step's index in its frame: the links' sweeps turn by it (``step``)
        solver.set_dt(self.dt)

    @property
    def state(self):
        """The current state (the one the last step wrote)."""
        return self.states[self.parity]

    def step(self):
        s_in, s_out = self.states[self.parity], self.states[1 - self.parity]
        # the links' sweeps: a step of an odd count goes the other way round its colours from the step before it in
        # the frame, every frame starting the same way (``Solver.sweep_turn``); a graph keeps the way it was captured
        # with, one per parity and way
        turn = self._frame_step % 2
        self.solver.sweep_turn = turn
        if self.use_graph:
            graph = self._graphs.get((self.parity, turn))
            if graph is None:
                # the first step of each parity and way runs eagerly (loading the modules), the graph is captured after
                self.solver.step(s_in, s_out, self.control, self.dt)
                self.solver.sweep_turn = turn
                with wp.ScopedCapture(device=self.solver.model.device) as capture:
                    self.solver.step(s_in, s_out, self.control, self.dt)
                self._graphs[(self.parity, turn)] = capture.graph
            else:
                self.solver.plan_factors()  # what the captured sweep reads (``Solver.plan_factors``)
                wp.capture_launch(graph)
        else:
            self.solver.step(s_in, s_out, self.control, self.dt)
        self.parity = 1 - self.parity
        self._frame_step += 1
        self.time += self.dt

    def step_dt(self, substeps: int | None = None) -> float:
        """The step [s] of a frame taken in ``substeps`` equal steps (None, or the stepper's own count: its step).
        :class:`Simulation` samples the head at the ends of these steps, keyed by the times this stepper reaches."""
        if substeps is None or substeps == self.substeps:
            return self.dt
        return self.dt * self.substeps / int(substeps)

    def advance_frame(self, before_step=None, substeps: int | None = None):
        """Run one frame of substeps, then check for faults (one integer read from the device).

        With ``substeps`` (this frame only) the frame is taken in that many equal steps instead, eagerly (a graph
        replays the steps it was captured with); the frame ends at the time the usual steps reach.
        """
        if substeps is None or substeps == self.substeps:
            return self._frame(before_step)
        if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
            raise ValueError(f"substeps must be an integer >= 1 (steps in this frame), got {substeps!r}")
        n, dt, graph = self.substeps, self.dt, self.use_graph
        end = self.time
        for _ in range(n):
            end += dt  # the time the frame's usual steps reach, to the bit
        self.substeps, self.dt, self.use_graph = int(substeps), self.step_dt(substeps), False
        try:
            bits = self._frame(before_step)
        finally:
            self.substeps, self.dt, self.use_graph = n, dt, graph
            self.solver.set_dt(dt)  # a graph replays without setting it
        self.time = end
        return bits

    def _frame(self, before_step):
        # every frame makes its own factors for the links' sweeps: a frame taken again, or a run resumed at it, solves
        # as the run that went through it did
        self.solver.expire_factors()
        self._frame_step = 0
        for _ in range(self.substeps):
            if before_step is not None:
                before_step(self.time + self.dt, self.control)
            self.step()
        self.frame += 1
        return self.solver.check(self.state, self.frame, substeps=self.substeps)


#: The checkpoint's entry for the hair speed fault's bound (``Solver.speed_terms``), and the terms it holds, in order.
SPEED_KEY = "solver.speed_terms"
SPEED_TERMS = ("start", "carried", "colliders", "wind")

#: The checkpoint's entry for the last frame not taken again for a whip (``Simulation._whipped``): a resumed run rests
#: as the whole run would.
WHIP_REST_KEY = "runner.whip_rest_until"


def _upgraded(arrays: dict) -> dict:
    """A checkpoint as this version keeps it. Earlier versions kept no links' or hair contacts' forces of the last
    step (taken as none) and each body contact's friction share alone
    (``solver.body_contacts.beta``, 1 sticking, less sliding), which this one keeps as ``share`` beside the contact's
    slip speed (``solver.body_contacts.slip``): a sticking vertex had none, a sliding one is taken as sliding
    (``kernels.articulated.STICK_SLIP``)."""
    out = dict(arrays)
    if "solver.links.link_broken" in out and "solver.links.link_warm" not in out:
        # links' forces of the last step (``Solver._warm_start``), kept since 2026-12-05: the next step starts cold
        out["solver.links.link_warm"] = np.zeros((len(np.asarray(out["solver.links.link_broken"])), 3), np.float32)
    if "solver.contacts.contact_counter" in out and "solver.contacts.warm_force" not in out:
        # hair contacts' forces of the last step (``Solver.contact_warm_start``), kept since 2026-12-06: none
        segments = len(np.asarray(out["state0.joint_q"]))
        out["solver.contacts.warm_force"] = np.zeros((segments, 3), np.float32)
        out["solver.contacts.warm_torque"] = np.zeros((segments, 3), np.float32)
    if "solver.body_contacts.force" in out and "solver.body_contacts.away" not in out:
        # the slip each contact took away and the time since it last held its vertex, kept since 2026-12-06: a vertex
        # then held had its force kept, any other none
        held = np.linalg.norm(np.asarray(out["solver.body_contacts.force"], dtype=np.float32), axis=-1) > 0.0
        out["solver.body_contacts.removed"] = np.zeros(len(held), np.float32)
        out["solver.body_contacts.away"] = np.where(held, 0.0, 1.0).astype(np.float32)
    if "solver.body_contacts.force" in out and "solver.body_contacts.answer_force" not in out:
        # each vertex's contact force at the end of the bodies' answer to the links' sweeps, kept since 2026-12-07: none
        out["solver.body_contacts.answer_force"] = np.zeros_like(np.asarray(out["solver.body_contacts.force"],
                                                                             dtype=np.float32))
    old = "solver.body_contacts.beta"
    if old not in out or "solver.body_contacts.slip" in out:
        return out
    from hairwarp.kernels.articulated import STICK_SLIP

    share = np.asarray(out.pop(old), dtype=np.float32)
    out["solver.body_contacts.share"] = share
    out["solver.body_contacts.slip"] = np.where(share >= 1.0, 0.0, 2.0 * float(STICK_SLIP)).astype(np.float32)
    return out


def is_teleport(before, after, distance: float, angle_deg: float, centre=(0.0, 0.0, 0.0)) -> bool:
    """Whether the head jumped between two motion samples (or ``(position, rotation)`` poses): it carried the point
    ``centre`` (head frame; the middle of the hair, :func:`hairwarp.state.hair_ball`) farther than ``distance`` [m],
    or it turned by more than ``angle_deg``.

    The hair's middle, not the head frame's origin: a nod about a pivot far from the origin swings the origin much
    farther than the hair (the shipped ``tiny`` nods about a point 1.5 m above its origin, which then moved 0.2 m in
    a frame, a teleport at 41 of 80 steps, while its hair moved 3 cm). Turns are the angle's: a spin moves the hair's
    tips fast, but continuously.
    """
    (p0, q0), (p1, q1) = (_pose(before), _pose(after))
    # plain floats: two tests a step, run between the kernels on one thread
    a, b = np.asarray(q1, dtype=float).tolist(), np.asarray(q0, dtype=float).tolist()
    c0 = [u + v for u, v in zip(np.asarray(p0, dtype=float).tolist(), rotate_floats(b, centre))]
    c1 = [u + v for u, v in zip(np.asarray(p1, dtype=float).tolist(), rotate_floats(a, centre))]
    if math.dist(c1, c0) > distance:
        return True
    cos_half = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return 2.0 * math.degrees(math.acos(min(cos_half, 1.0))) > angle_deg


def _step_mean(start, end, dt: float):
    """``end`` with the accelerations the mean over a step of ``dt`` from ``start``: (v_end - v_start) / dt."""
    v0, v1 = np.asarray(start.linear_velocity, dtype=float), np.asarray(end.linear_velocity, dtype=float)
    w0, w1 = np.asarray(start.angular_velocity, dtype=float), np.asarray(end.angular_velocity, dtype=float)
    return MotionSample(end.position, end.rotation, v1, w1, (v1 - v0) / dt, (w1 - w0) / dt)


def _step_mean_frames(start, end, dt: float):
    """The root frames ``end`` (``ScalpBinding.root_frames``) with their accelerations the mean over the step, as
    :func:`_step_mean`; None without a scalp binding."""
    if end is None:
        return None
    return end[0], end[1], (end[1] - start[1]) / dt


def _pose(sample):
    return sample if isinstance(sample, tuple) else (sample.position, sample.rotation)


class Simulation:
    """Everything a scene asks for, built on one device, advanced frame by frame.

    Args:
        scene: a :class:`hairwarp.Scene`, a scene file's path, or its tables as a dict.
        device: Warp device; default ``sim.device``.
        threads: CPU threads; default ``sim.threads`` (0 or None there: every core this process may use).

    Attributes:
        scene, model, solver, stepper, motion, groom.
        frame_dt: time between output frames [s].
        break_step: ``links.break_step`` [s], the longest step at which a link may break (0: any).
        refined_frames: frames taken again in steps of ``break_step`` because a link broke in them.
        fault_retries: ``sim.fault_retries``, the times a frame that faults is taken again, each in twice the steps.
        whip_ratio: ``sim.whip_ratio``; a frame whose guides end it faster than this many times the speed the motion
            explains is taken again as one that faults ("whip" its stage), up to ``fault_retries`` times.
        retaken_frames: frames taken again after a fault or a whip; ``retakes``, ``(frame, steps it ran in, stage)``
            of each.
        start_inside: per collider the hair starts inside, ``{"name", "vertices", "strands", "deepest"}`` [m]
            (``ColliderSet.mark_exempt``); the run warns past ``START_INSIDE_DEPTH``.
    """

    def __init__(self, scene, *, device=None, threads: int | None = None):
        from hairwarp.scene import Scene

        scene = Scene.coerce(scene)
        sim = scene.sim
        self.scene = scene
        self.groom = scene.build_groom()
        _check_groom_memory(scene, self.groom)
        self.motion = scene.head_motion()
        head_rest = self.motion.evaluate(0.0).matrix()
        bound = scene.bind_surface(self.groom, head_rest)
        self.surface = None  # hairwarp.surface.ScalpBinding: roots on a deforming scalp
        # a scalp its stage animates under a head motion from elsewhere: the roots ride on the head from the scalp's
        # first pose (hairwarp.surface.HeadCarriedRoots), as the head's collider does
        self._carried = None
        if bound is not None:
            self.groom, self.surface = bound
            if scene.head.motion.kind != "usd" and self.surface.animated:
                from hairwarp.surface import HeadCarriedRoots

                self._carried = HeadCarriedRoots(self.surface, head_rest)
        # a groom held as drawn is held at the first pose: the head's, or each root's frame on a bound scalp
        hold_rotation = None
        if scene.groom.hold_shape:
            hold_rotation = (self.surface.root_frames(0.0)[0][:, 3:] if self.surface is not None
                             else self.motion.evaluate(0.0).rotation)
        self.model = Model.build(self.groom, scene.strand_params(), segments=int(sim.segments),
                                 device=device or sim.device, gravity=tuple(sim.gravity),
                                 hold_shape=bool(scene.groom.hold_shape), hold_rotation=hold_rotation)
        unstable = self.model.hold_unstable
        if unstable is not None and unstable.any() and not scene.links.enabled:
            warnings.warn(f"groom.hold_shape: {int(unstable.sum())} of {self.model.strand_count} strands cannot stand "
                          f"as drawn (first: strand {int(np.flatnonzero(unstable)[0])}): too soft for their weight, "
                          f"they buckle and fall from it (raise strands.bend_stiffness, tie them with links, or let "
                          f"the groom sag: groom.hold_shape = false)", stacklevel=2)
        self._warn_undrawn_curls(scene)
        self.frame_dt = scene.frame_dt
        self.colliders = self._build_colliders(scene)
        self._display_meshes = None  # (vertices, faces) of each collider in its frame, made once (collider_meshes)
        collider_set = None
        if self.colliders:
            from hairwarp.colliders import ColliderSet

            collider_set = ColliderSet(self.colliders, self.model.device, model=self.model)
        self.collider_set = collider_set
        self._moving_colliders = any(c.attach == "world" and c.motion is not None for c in self.colliders)
        head = scene.head
        self._teleport_limits = (float(head.teleport_distance), float(head.teleport_angle_deg),
                                 hair_ball(self.model)[0])
        self._wind = None  # the wind last set on the control
        self._poses = {}  # step number -> head pose, for the teleport test
        self._applied_at_start = None  # (t, what _applied(t) gave): the head at the next step's start
        self._ahead = {}  # step end time -> what _applied gave, for the frame being advanced
        self._surface_ahead = {}  # step end time -> the scalp's root frames, for the frame being advanced
        # set where ``links.response = "auto"`` solves stiff links after the free step, or "link" keeps them in it
        self.stiff_links_note = None
        self.link_damping_note = None  # set where the links' damping in the free step is mostly capped
        self.links = self._build_links(scene.links)
        self.break_step = float(scene.links.break_step)
        self.refined_frames = 0  # frames taken again because a link broke in them (``links.break_step``)
        # the frame whose fastest guide vertex came nearest the hair speed bound: (its speed over the speed the motion
        # explains, the frame, the speed [m/s], the explained speed [m/s]); ``whip_note`` reads it
        self.peak_speed = (0.0, 0, 0.0, 0.0)
        self.fault_retries = int(sim.fault_retries)
        self.whip_ratio = float(sim.whip_ratio)
        # (frame, [(steps, fastest guide vertex [m/s]) of its whipping takes]) of each frame whose whip finer steps did
        # not slow (``_whipped``); frames up to ``_whip_rest_until`` are not taken again for a whip
        self.motion_whips = []
        self._whip_rest_until = -1
        # (frame, the steps it ran in, the stage of the fault that made it, or "whip") of each retry
        self.retakes = []
        # set where ``interactions.response = "auto"`` solves stiff hair contacts after the free step
        self.stiff_contacts_note = None
        self.contacts = self._build_contacts(scene.interactions)
        self.solver = Solver(self.model, sim.integrator, colliders=collider_set, links=self.links,
                             contacts=self.contacts, max_rotation_per_step=float(sim.max_rotation_per_step),
                             speed_margin=float(sim.speed_margin),
                             threads=int(sim.threads) if threads is None else threads)
        self.contact_rest_note = self._contact_rest_note(scene.interactions)
        self._warn_oversubscribed(self.solver.executor.threads, "sim.threads" if threads is None else "threads")
        control = self.model.control(root_frames=self.surface is not None)
        control.set_motion(self.motion.evaluate(0.0))
        if self.surface is not None:
            control.set_root_frames(*self.surface.root_frames(0.0))
        state = self.model.state()
        self.solver.forward_kinematics(state, control)
        self.start_inside = []  # per collider the hair starts inside: ``ColliderSet.mark_exempt``
        if collider_set is not None:
            # the exemptions of the hair as it starts, the head and the world colliders posed at time 0
            self.start_inside = collider_set.mark_exempt(self.model, state.vertex_positions, self.head_matrix(0.0))
            self._warn_started_inside(self.start_inside)
        self.stepper = Stepper(self.solver, dt=scene.step_dt, substeps=int(sim.substeps), control=control,
                               state=state)
        self.dense = self._build_dense(scene.dense)
        if self.dense is not None:
            self.dense.executor = self.solver.executor

    def _response(self, choice: str) -> bool:
        """Whether links or contacts take the response after the free step (``links.response``,
        ``interactions.response``): ``auto`` takes it at steps of ``AUTO_RESPONSE_DT`` or longer (and links past
        ``LINK_STEP_RATE``, contacts past ``CONTACT_STEP_RATE`` at any step: ``_build_links``, ``_build_contacts``)."""
        if choice == "auto":
            return self.scene.step_dt >= AUTO_RESPONSE_DT * (1.0 - 1e-9)
        return choice == "step"

    def _build_links(self, cfg):
        if not cfg.enabled:
            return None
        from hairwarp.interactions import StaticLinks

        links = StaticLinks.build(self.model.rest_vertex_positions, neighbours=int(cfg.neighbours),
                                  radius=float(cfg.radius), stiffness=float(cfg.stiffness),
                                  damping=float(cfg.damping), break_length=float(cfg.break_length),
                                  response=self._response(cfg.response), sweeps=int(cfg.sweeps),
                                  device=self.model.device)
        if cfg.response in ("auto", "link") and not links.response:
            rate = links.free_step_rate(self.model.seg_mass.numpy(), self.scene.step_dt)
            if rate > LINK_STEP_RATE and cfg.response == "link":  # as asked, though they may gain energy
                self.stiff_links_note = (
                    f"links.response = \"link\" solves each link alone in the free step, but at this step they are "
                    f"too stiff for it (free-step rate {rate:.3g}, past {LINK_STEP_RATE:g}): strands they tie may gain "
                    f"energy (docs/interactions.md); links.response = \"auto\" solves them after the free step, or "
                    f"links.stiffness <= {float(cfg.stiffness) * (LINK_STEP_RATE / rate) ** 2:.3g} N/m keeps them "
                    f"stable in it")
            elif rate > LINK_STEP_RATE:  # too stiff for the free step's per-link solve
                links.response = True
                self.stiff_links_note = (
                    f"links.response = \"auto\" solved the links after the free step: at this step they are too "
                    f"stiff for it (free-step rate {rate:.3g}, past {LINK_STEP_RATE:g}), where they would gain "
                    f"energy (docs/interactions.md). links.stiffness <= "
                    f"{float(cfg.stiffness) * (LINK_STEP_RATE / rate) ** 2:.3g} N/m keeps them in the free step, "
                    f"which costs less")
        if not links.response and links.link_count and links.damping > 0.0:
            self.link_damping_note = self._link_damping_note(links)
        if links.link_count == 0:
            roots = np.asarray(self.model.rest_vertex_positions, dtype=float).reshape(
                self.model.strand_count, -1, 3)[:, 0]
            spacing = ""
            if len(roots) > 1:
                gaps = [np.sort(np.linalg.norm(roots - r, axis=1))[1] for r in roots[:2000]]
                spacing = f" (the guides' roots lie {1e3 * float(np.median(gaps)):.3g} mm from their nearest)"
            warnings.warn(f"links.enabled: no link was built: no segment of another strand lies within links.radius = "
                          f"{float(cfg.radius):g} m{spacing}; raise links.radius, or set links.enabled = false",
                          stacklevel=2)
        return links

    @staticmethod
    def _warn_oversubscribed(threads: int, name: str):
        """Warn where the run asks for more CPU threads than the cores this process may use: they take turns on
        them, and the run is slower (``long_hair`` on 2 cores: 9 % at 3 threads, 15 % at 4, twice the time at 16)."""
        from hairwarp.executor import default_threads

        cores = default_threads()
        if threads > cores:
            warnings.warn(f"{name} = {threads} is more than the {cores} cores this process may use: the threads take "
                          f"turns on them and the run is slower; {name} = 0 takes every core", stacklevel=3)

    @staticmethod
    def _warn_started_inside(found: list[dict]):
        """Warn where the hair starts deeper than :data:`START_INSIDE_DEPTH` inside a collider: its vertices there
        are exempt from it until they come out (``hairwarp.colliders``), so the hair passes through it."""
        for c in found:
            if c["deepest"] > START_INSIDE_DEPTH:
                warnings.warn(f"collider {c['name']!r}: {c['vertices']} vertices of {c['strands']} strands start "
                              f"inside it, up to {1e3 * c['deepest']:.3g} mm deep; they pass through it until they "
                              f"come out: place it clear of the groom at the scene's start (the head as "
                              f"head.motion has it at time 0)", stacklevel=3)

    def _warn_undrawn_curls(self, scene):
        """Warn where the scalp generator's curls are shorter than :data:`CURL_SEGMENTS` of the guides' segments: the
        guides, resampled to ``sim.segments``, draw them as a zigzag, and the dense hair follows the guides."""
        groom = scene.groom
        if groom.generator != "scalp" or not float(groom.curl) > 0.0:
            return
        period = float(groom.curl_period)
        segments = int(scene.sim.segments)
        # along the drawn helix: the resampled guides' chords cut across the curls and come out shorter
        length = float(np.median([np.linalg.norm(np.diff(np.asarray(strand, dtype=np.float64), axis=0), axis=1).sum()
                                  for strand in self.groom.strands]))
        if period * segments >= CURL_SEGMENTS * length:
            return
        chords = float(np.median(self.model.seg_length.numpy().astype(np.float64).reshape(-1, segments).sum(axis=1)))
        warnings.warn(f"groom.curl: a curl (groom.curl_period = {period:g} m) spans {period * segments / length:.2g} "
                      f"of the guides' segments at sim.segments = {segments}: the guides draw it as a zigzag, "
                      f"{1e3 * chords:.3g} mm long where the groom draws {1e3 * length:.3g} mm, and the dense hair "
                      f"follows them; {CURL_SEGMENTS} segments a curl need sim.segments >= "
                      f"{math.ceil(CURL_SEGMENTS * length / period)}", stacklevel=3)

    def _link_damping_note(self, links) -> str | None:
        """The run's note where the links' damping in the free step is past :data:`LINK_DAMPING_NOTE_LOAD` times what
        the median linked segment's dampers may take in a step (``kernels.links.damper_cap``), else None."""
        load = links.damping_load(self.model, self.scene.step_dt)
        median = float(np.median(load))
        if median <= LINK_DAMPING_NOTE_LOAD:
            return None
        return (f"links.damping = {links.damping:g} N s/m asks {median:.3g} times what the median linked segment's "
                f"links can take in a step: in the free step each link's damper is capped where its segments' links "
                f"together would take more than their velocity ({np.mean(load > 1.0):.0%} of the linked segments at "
                f"this step; docs/interactions.md), so more damping holds the hair no firmer; "
                f"{links.damping / median:.3g} N s/m acts whole on half of them")

    def _build_contacts(self, cfg):
        if not cfg.enabled:
            return None
        from hairwarp.interactions import HairContacts, TriangleStrips, contact_step_rate

        model = self.model
        strips = None
        if cfg.vertex_face:
            strips = TriangleStrips.build(model.rest_vertex_positions, model.root_uv, model.grid_shape,
                                          device=model.device)
        per_frame = cfg.detect == "frame"
        response = self._response(cfg.response)
        if cfg.response == "auto" and not response:
            rate = contact_step_rate(model.seg_mass.numpy(), model.seg_length.numpy(), float(cfg.stiffness),
                                     self.scene.step_dt)
            if rate > CONTACT_STEP_RATE:  # too stiff for the free step's semi-implicit mass
                response = True
                self.stiff_contacts_note = (
                    f"interactions.response = \"auto\" solved the hair contacts after the free step: at this step "
                    f"they are too stiff for it (free-step rate {rate:.3g}, past {CONTACT_STEP_RATE:g}), where they "
                    f"would blow up (docs/interactions.md). interactions.stiffness <= "
                    f"{float(cfg.stiffness) * (CONTACT_STEP_RATE / rate) ** 2:.3g} N/m keeps them in the free step, "
                    f"which costs less")
        contacts = HairContacts.build(
            model.rest_vertex_positions, strips, threshold=float(cfg.threshold), stiffness=float(cfg.stiffness),
            damping=float(cfg.damping), friction=float(cfg.friction), segment_segment=bool(cfg.segment_segment),
            capacity=int(cfg.capacity) or 16 * model.seg_count, margin=float(cfg.margin) if per_frame else 0.0,
            detect_each_step=not per_frame, response=response, device=model.device,
        )
        contacts.grows = True  # hair that gathers (curls, a collapse) finds more pairs than a run can foresee
        return contacts

    def _contact_rest_note(self, cfg) -> str | None:
        """The run's note where its hair contacts are solved after the free step at steps too long for them to settle
        as they start each step cold (``Solver.contact_warm_start``: without the links' sweeps, on a GPU, or at one
        step a frame where ``Solver.contacts_cold_at_frame_rate`` says why), else None."""
        contacts, dt = self.contacts, self.scene.step_dt
        if contacts is None or not contacts.response or dt < AUTO_RESPONSE_DT * (1.0 - 1e-9) \
                or self.solver.contact_warm_start(dt):
            return None
        if self.model.device.is_cuda:
            why = "on a GPU"
        elif not self.solver.link_sweeps:
            why = "without the links' sweeps, which carry their force from step to step"
        elif not self.solver.body_contacts.enabled:
            return None  # nothing to trade the hair's load with: started cold, it settles (docs/interactions.md)
        else:
            reason = self.solver.contacts_cold_at_frame_rate(dt) or "in a frame taken again"
            why = f"at steps of {WARM_START_STEP:.3g} s and longer {reason}"
        return (f"hair contacts solved after the free step start each step cold at this step ({dt:.3g} s, "
                f"interactions.response = \"{cfg.response}\"; {why}): hair resting on the body may keep crawling by a "
                f"few mm/s with the head still (docs/interactions.md, \"Hair contacts start from their last force at "
                f"long steps\"); with links, steps from {AUTO_RESPONSE_DT:.3g} s to under {WARM_START_STEP:.3g} s "
                f"settle, as do shorter ones, and interactions.response = \"mass\" settles gentle motion but breaks "
                f"links in violent motion")

    def _build_dense(self, cfg):
        if not cfg.count and cfg.density is None:
            return None
        from hairwarp.dense import DenseHair, DenseHairError

        model = self.model
        available = _available_memory()
        max_count = None if available is None else max(available // _dense_strand_bytes(self.scene), 1)
        try:
            return DenseHair.build(
                model.rest_vertex_positions, model.root_uv, count=cfg.count or None, density=cfg.density,
                grid_shape=model.grid_shape, root_normal=model.root_normal, seed=int(cfg.seed),
                length_variation=float(cfg.length_variation), tip_spread=float(cfg.tip_spread),
                clumping=float(cfg.clumping), samples_per_segment=int(cfg.samples_per_segment),
                with_velocities=bool(cfg.velocities), device=model.device, max_count=max_count,
            )
        except DenseHairError as exc:  # one line naming the scene and its key
            key = "dense.count" if cfg.count else "dense.density"
            raise DenseHairError(f"{self.scene.source or self.scene.name}: {key}: {exc}") from None

    def dense_curves(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Host copies of the dense hair's points and velocities for this frame (Hermite samples for
        ``basis = "linear"``, interpolated vertices for ``"catmullRom"``)."""
        if self.dense is None:
            raise ValueError(f"scene {self.scene.name!r} has no dense hair: set dense.count (or dense.density)")
        s, c = self.stepper.state, self.stepper.control
        hermite = self.scene.dense.basis == "linear"
        velocities = s.vertex_velocities if self.scene.dense.velocities else None
        colliders = self.collider_set if self.scene.dense.push_out else None
        points, vel = self.dense.evaluate(s.vertex_positions, velocities, c.head_xform, c.head_velocity,
                                          hermite=hermite, colliders=colliders)
        return points.numpy(), (vel.numpy() if vel is not None else None)

    @staticmethod
    def _build_colliders(scene) -> list:
        """The head's collider (``[head]``) and the ``[[colliders]]`` of the scene."""
        from hairwarp.colliders import Collider

        out = []
        head = scene.head
        contact = {"thickness": float(head.thickness), "friction": float(head.friction), "attach": "head"}
        if head.shape == "sphere":
            out.append(Collider.sphere(float(head.radii[0]), center=tuple(head.center), name="head", **contact))
        elif head.shape == "ellipsoid":
            out.append(Collider.ellipsoid(tuple(head.center), tuple(head.radii), name="head", **contact))
        elif head.shape == "mesh":
            out.append(_mesh_collider(head.file, head.up_axis, head.scale, head.translate, np.zeros(3), "head",
                                      contact))
        for i, c in enumerate(scene.colliders):
            try:
                out.append(Simulation._build_collider(c))
            except ValueError as exc:  # ColliderError, UsdFileError: name the scene's collider too
                raise type(exc)(f"colliders[{i}] ({c.name}): {exc}") from None
        return out

    @staticmethod
    def check_colliders(scene) -> list:
        """Build the scene's colliders, reading their files, as a run would before its first step: a file or prim
        that a run would refuse raises here (ValueError naming the scene file and the collider), for checks before
        anything runs (``hairwarp info``, batches and wedges). Returns them."""
        try:
            return Simulation._build_colliders(scene)
        except ValueError as exc:
            where = scene.source if scene.source is not None else scene.name
            raise type(exc)(f"{where}: {exc}") from None

    @staticmethod
    def _build_collider(c):
        """One ``[[colliders]]`` table's collider."""
        from hairwarp.colliders import Collider
        from hairwarp.motion import euler_xyz_deg_to_quat, quat_to_matrix

        place = np.eye(4)
        place[:3, :3] = quat_to_matrix(euler_xyz_deg_to_quat(c.rotate_deg))
        place[:3, 3] = c.translate
        opts = {"thickness": float(c.thickness), "friction": float(c.friction), "attach": c.attach}
        if c.kind == "sphere":
            return Collider.sphere(float(c.radius), center=tuple(c.translate), name=c.name, **opts)
        if c.kind == "capsule":
            return Collider.capsule(float(c.radius), float(c.half_height), local_xform=place, name=c.name, **opts)
        if c.kind == "plane":
            return Collider.plane(point=tuple(c.translate), normal=tuple(place[:3, 2]), name=c.name, **opts)
        if c.kind == "ellipsoid":
            return Collider.ellipsoid(tuple(c.translate), tuple(c.radii), name=c.name, local_xform=place, **opts)
        if c.kind == "usd":
            from hairwarp.io.usd_anim import read_animated_collider

            opts.pop("attach")  # "world": the scene checks that no other is given
            return read_animated_collider(c.file, c.prim, name=c.name, **opts)
        return _mesh_collider(c.file, c.up_axis, c.scale, c.translate, c.rotate_deg, c.name, opts)

    def collider_meshes(self, t: float) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
        """(name, local vertices, faces, world matrix at time t) of every collider, for the cache and previews."""
        head_m = self.head_matrix(t)
        if self._display_meshes is None:  # the shapes do not change: tessellated once (0.8 ms a frame before)
            self._display_meshes = [tuple(_read_only(np.array(a)) for a in _display_mesh(col))
                                    for col in self.colliders]
        out = []
        for col, (verts, faces) in zip(self.colliders, self._display_meshes, strict=True):
            if col.attach == "head":
                world = head_m @ col.local_xform
            elif col.motion is not None:
                world = col.motion.evaluate(t).matrix() @ col.local_xform
            else:
                world = col.local_xform
            out.append((col.name, verts, faces, world))
        return out

    def _before_step(self, t, control):
        start = self.stepper.time
        now = self._ahead.pop(t, None) or self._applied(t)
        teleport, sample, frames = now
        if not teleport:
            # The head's accelerations over the step: the mean, (v(t) - v(start)) / dt, of the velocities the control
            # holds at the step's start and end, so that the hair takes over the step the head's own change of
            # velocity. Sampled at the step's end they gave it that change wrong by O(dt^2) a step, O(dt) in the
            # end (fast_turn at 2 substeps: tips 26.4 mm RMS from the 16-substep run, 24.6 with the mean).
            before = self._applied_at_start
            if before is None or before[0] != start:  # the first step, after a restore or a new motion
                before = (start, self._applied(start))
            _, sample_0, frames_0 = before[1]
            sample, frames = _step_mean(sample_0, sample, self.stepper.dt), _step_mean_frames(frames_0, frames,
                                                                                          self.stepper.dt)
        self._applied_at_start = (t, now)
        control.set_motion(sample)
        if frames is not None:
            control.set_root_frames(*frames)
        if teleport:
            self.solver.teleport(self.stepper.state, control)
        wind = self.scene.wind_at(t)
        if wind != self._wind:  # a host-to-device copy: only when the wind changes
            control.set_wind(wind)
            self._wind = wind
        if self._moving_colliders:
            self.collider_set.update(t)

    def _applied(self, t: float):
        """``(teleport, sample, root frames or None)``: the head (and the scalp's root frames) a step ending at ``t``
        gives the control, its accelerations as sampled. A cut, or a move faster than a frame can show (the frame
        before ``t`` or the one after it, since the motion is known ahead): the hair rides along rigidly, at rest
        relative to the head, all the while: velocities and accelerations zero."""
        sample = self.motion.evaluate(t)
        limits = self._teleport_limits
        if (is_teleport(self._pose_a_frame_from(t, -1), sample, *limits)
                or is_teleport(sample, self._pose_a_frame_from(t, 1), *limits)):
            still = MotionSample(sample.position, sample.rotation, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
            frames = self._root_frames(t, sample)
            if frames is not None:
                frames = (frames[0], np.zeros_like(frames[1]), np.zeros_like(frames[1]))
            return True, still, frames
        return False, sample, self._root_frames(t, sample)

    def _root_frames(self, t: float, sample):
        """The roots' frames for a step ending at ``t`` with the head at ``sample``: on the scalp as its stage
        animates it, or carried by the head (``_carried``); None without a scalp binding."""
        if self._carried is not None:
            return self._carried.root_frames(sample)
        if self.surface is None:
            return None
        frames = self._surface_ahead.get(t)  # taken with the frame's other steps' (``_frame``)
        return frames if frames is not None else self.surface.root_frames(t)

    def _pose_a_frame_from(self, t: float, direction: int):
        """The head pose a frame after (``direction`` 1) or before (-1) ``t``, for the teleport test. Each is
        computed once: the pose a frame after a step is the one a frame before the step two frames on (kept by
        step number; keyframes take 7 us a pose and 18 a sample, in plain floats)."""
        dt = self.stepper.dt
        key = round(t / dt) + direction * round(self.frame_dt / dt)
        cache = self._poses
        pose = cache.get(key)
        if pose is None:
            pose = cache[key] = self.motion.pose(t + direction * self.frame_dt)
            if len(cache) > 4 * max(1, self.stepper.substeps):
                for old in sorted(cache)[: len(cache) // 2]:
                    del cache[old]
        return pose

    @property
    def motion(self):
        """The head's motion (a :class:`hairwarp.HeadMotion`: ``evaluate(t)`` and ``pose(t)``), the scene's
        ``[head.motion]`` unless assigned; every step sets the control from it."""
        return self._motion

    @motion.setter
    def motion(self, motion):
        if not (callable(getattr(motion, "evaluate", None)) and callable(getattr(motion, "pose", None))):
            raise TypeError(f"motion must have evaluate(t) and pose(t), as a hairwarp.HeadMotion; got "
                            f"{type(motion).__name__}")
        self._motion = motion
        self._poses = {}  # the teleport test's poses were the old motion's
        self._applied_at_start = None  # so was the control's head at the step's start
        self._ahead = {}

    def advance_frame(self) -> Fault:
        """Simulate one output frame (the scene's substeps, the head and colliders posed for each).

        A frame that faults is taken again from its start in twice the steps, up to ``sim.fault_retries`` times
        (:attr:`retakes` lists them): a frame the step does not resolve is simulated in steps that do, and the run
        stops only when the last of them faults too. So is a frame whose fastest guide vertex ends it past
        ``sim.whip_ratio`` times the speed the motion explains, and the last take is kept: on motion several times a
        scene's own, linked hair whips harder at 8 substeps than at fine steps (``long_hair_shoulders`` on its nod
        played ten times as fast: 15.4 m/s at 8, 9.9 at 32; without its links' geometric stiffness 19.0, and 11.7 with
        its one whipping frame taken again in 16).

        At steps longer than ``links.break_step`` a frame in which a link breaks, or that ends with one stretched past
        its break length, is taken again from its start in steps no longer than the break step
        (:attr:`refined_frames` counts them): a link breaks only on motion such a step resolves.

        Returns:
            the frame's :class:`hairwarp.Fault` bits that did not stop it: ``CONTACT_OVERFLOW`` (more hair contacts
            than the buffers hold; see :meth:`frame_stats`), else 0.

        Raises:
            SimulationFault: the frame left the solver's bounds at every step it was taken in (the message names the
                frame, the stage and what to change).
        """
        bits = self._advance_frame()
        fastest = self.solver.fastest_guide()
        if fastest is not None and fastest[1] > 0.0:
            ratio = fastest[0] / fastest[1]
            if math.isfinite(ratio) and ratio > self.peak_speed[0]:
                self.peak_speed = (ratio, self.stepper.frame, *fastest)
        return bits

    def whip_note(self) -> str | None:
        """A note where a frame's whip proved the motion's (:attr:`motion_whips`: its finer take whipped as fast), or
        else where a frame's fastest guide vertex passed :data:`WHIP_NOTE_RATIO` times the speed the run's motion
        explains (:attr:`peak_speed`); None where neither."""
        if self.motion_whips:
            frame, takes = self.motion_whips[0]
            shown = " and ".join(f"{v:.3g} m/s in {n} steps" for n, v in takes)
            others = len(self.motion_whips) - 1
            more = "" if others == 0 else f", and {others} frame{'s' if others > 1 else ''} more"
            return (f"frame {frame}: guides whipped past sim.whip_ratio = {self.whip_ratio:g} times the speed the "
                    f"motion explains at finer steps too ({shown}){more}: the "
                    f"motion drives that whip, not the step, so such frames were kept as taken (and the "
                    f"{WHIP_REST_FRAMES} after each not taken again for a whip); where the hair should not whip so, "
                    f"raise strands.drag or slow the head motion")
        ratio, frame, speed, explained = self.peak_speed
        if ratio < WHIP_NOTE_RATIO:
            return None
        margin = self.solver.speed_margin
        steps = [n for f, n, _ in self.retakes if f == frame]
        again = f" in the {max(steps)} steps it was taken again in" if steps else ""
        return (f"frame {frame}: guides reached {speed:.3g} m/s{again}, {ratio:.2g} times the {explained:.3g} m/s the "
                f"motion explains (at sim.speed_margin = {margin:g} times a run faults); on motion this fast a longer "
                f"step can whip hair harder than finer ones (long_hair_shoulders on its nod played ten times as fast: "
                f"15.4 m/s at 8 substeps, 9.9 at 32): compare a run with more substeps (now {self.stepper.substeps})")

    def _advance_frame(self) -> Fault:
        fine = self._break_substeps()
        if fine is None and self.fault_retries == 0:
            return self._frame()
        saved = self.checkpoint()
        if fine is None:
            return self._frame_retaken(saved)[0]
        # A link's break is for good and cuts its force off at once: decided on motion that the step does not
        # resolve, it tore links that no run at fine steps tears (the Ratboy mohawk's last shake at 2 substeps: 8
        # links, 33-37 mm against 27 mm at most at 16 substeps; long_hair_shoulders at one step a frame: 23).
        broken = self.links.broken_count()
        bits, steps = self._frame_retaken(saved)
        self.links.break_links(self.model, self.stepper.state)  # what the next step's force pass would break
        if self.links.broken_count() == broken:
            return bits
        self.restore(saved)
        bits = self._frame_retaken(saved, max(fine, steps))[0]
        self.links.break_links(self.model, self.stepper.state)
        self.refined_frames += 1
        return bits

    def _frame_retaken(self, saved: dict, substeps: int | None = None) -> tuple[Fault, int]:
        """The frame in ``substeps`` steps (None: the stepper's), from the checkpoint ``saved`` of its start; after a
        fault, or where its fastest guide vertex ended it past ``sim.whip_ratio`` times the speed the motion explains
        (:meth:`_whipped`), again from there in twice the steps, up to :attr:`fault_retries` times. Returns its bits
        and the steps it ran in."""
        steps = self.stepper.substeps if substeps is None else int(substeps)
        tried = []  # (steps, the fastest guide vertex [m/s] or None, the fault or None) of each take
        while True:
            try:
                bits = self._frame_in(steps)
            except SimulationFault as fault:
                tried.append((steps, self._fastest_speed(), fault))
                if len(tried) > self.fault_retries:
                    if len(tried) == 1:
                        raise
                    raise self._retried_fault(fault, tried) from None
                stage = fault.stage
            else:
                whip = None if len(tried) >= self.fault_retries else self._whipped(tried, steps)
                if whip is None:
                    return bits, steps
                tried.append((steps, whip, None))
                stage = "whip"
            self.restore(saved)
            steps *= 2
            self.retakes.append((self.stepper.frame + 1, steps, stage))

    def _fastest_speed(self) -> float | None:
        """The fastest guide vertex at the last check [m/s], or None where it measured none."""
        fastest = self.solver.fastest_guide()
        return None if fastest is None else fastest[0]

    def _retried_fault(self, fault: SimulationFault, tried: list) -> SimulationFault:
        """The fault of a frame that faulted in every take ``tried``. Where each was the hair's speed alone and the
        last two takes' fastest vertices agree (:data:`WHIP_AGREEMENT`; a take kept for a whip counts with the faulted
        ones), finer steps do not slow the hair, and the advice says what does."""
        again = " and ".join(str(n) for n, _, _ in tried[1:])
        retried = f"taken again in {again} steps (sim.fault_retries = {self.fault_retries})"
        speeds = [v for _, v, _ in tried]
        # the dynamics' own stage only (a stage that drives the speed, air drag on light strands or stiff springs,
        # keeps its advice); a take kept for a whip (no fault) counts as one whose speed went past the bounds
        if (all(f is None or (f.bits == int(Fault.HAIR_SPEED) and f.stage == DYNAMICS_STAGE) for _, _, f in tried)
                and None not in speeds and _agree(speeds[-2], speeds[-1])):
            what = str(fault).split(" To fix: ")[0]
            whips = ", ".join(f"{v:.3g}" for v in speeds[:-1]) + f" and {speeds[-1]:.3g} m/s"
            return SimulationFault(
                f"{what} The frame was {retried}, and its guides whipped at {whips}: finer steps do not slow "
                f"them, so the motion drives this whip, not the step. To fix: where the hair should whip so, raise "
                f"sim.speed_margin (now {self.solver.speed_margin:g}; the hair may move that many times the speed "
                f"the motion explains); else raise strands.drag (now {self.model.drag:g}) or slow the head motion.",
                frame=fault.frame, stage=fault.stage, bits=fault.bits)
        return SimulationFault(f"{fault} (The frame was {retried}, and faulted each time.)", frame=fault.frame,
                               stage=fault.stage, bits=fault.bits)

    def _frame_in(self, steps: int) -> Fault:
        """The frame in ``steps`` steps; at other than the stepper's own, with no warm start from its last step."""
        if steps == self.stepper.substeps:
            return self._frame()
        self._poses = {}  # kept by step number: another step size
        self.solver.warm_start_allowed = False
        try:
            return self._frame(steps)
        finally:
            self._poses = {}
            self.solver.warm_start_allowed = True

    def _whipped(self, tried: list, steps: int) -> float | None:
        """The fastest guide vertex [m/s] of the frame just taken in ``steps`` steps where it ended past
        ``sim.whip_ratio`` times the speed the motion explains and the frame is to be taken again in finer steps;
        else None (also where that ratio is 0 or the speed bound is off). None too where the take agrees with a
        whipping take before it in ``tried`` (:data:`WHIP_AGREEMENT`): the motion drives that whip
        (:attr:`motion_whips`), and the next :data:`WHIP_REST_FRAMES` frames are not taken again for one."""
        frame = self.stepper.frame
        if not self.whip_ratio > 0.0 or frame <= self._whip_rest_until:
            return None
        fastest = self.solver.fastest_guide()
        if fastest is None or not fastest[0] > self.whip_ratio * fastest[1] > 0.0:
            return None
        before = [(n, v) for n, v, fault in tried if fault is None]
        if before and _agree(before[-1][1], fastest[0]):
            self.motion_whips.append((frame, [*before, (steps, fastest[0])]))
            self._whip_rest_until = frame + WHIP_REST_FRAMES
            return None
        return fastest[0]

    @property
    def retaken_frames(self) -> int:
        """Frames taken again after a fault (:attr:`retakes`), each once however many retries it took."""
        return len({frame for frame, _, _ in self.retakes})

    def _break_substeps(self) -> int | None:
        """The steps a frame is taken again in when a link breaks in it (``links.break_step``), or None: no links,
        no break step, or steps no longer than it."""
        links = self.links
        if links is None or links.link_count == 0 or not self.break_step > 0.0:
            return None
        st = self.stepper
        if st.dt <= self.break_step * (1.0 + 1e-9):
            return None
        return max(st.substeps + 1, math.ceil(st.dt * st.substeps / self.break_step - 1e-9))

    def _frame(self, substeps: int | None = None) -> Fault:
        """The frame's steps (the stepper's, or ``substeps`` of them), the hair contacts found at its start."""
        if self.contacts is not None and not self.contacts.detect_each_step:
            # pairs for this frame, within the margin; on the CPU the trees are rebuilt every REBUILD_FRAMES frames
            # and refit in between (the contacts' order does not depend on which: HairContacts.detect)
            rebuild = self.model.device.is_cuda or self.stepper.frame % REBUILD_FRAMES == 0
            with self.solver._stage("hair contacts: detection"):
                self.contacts.detect(self.model, self.stepper.state, rebuild=rebuild)
        # the head at the end of each of the frame's steps, sampled together before the kernels: the same Python
        # between them ran 3-6 times slower (its caches cold), on one thread while the others waited
        st, t = self.stepper, self.stepper.time
        n, dt = (st.substeps if substeps is None else substeps), st.step_dt(substeps)
        ends = []
        for _ in range(n):
            t = t + dt  # as Stepper.advance_frame forms it, and then its time
            ends.append(t)
        if self.surface is not None and self._carried is None:
            # the scalp's frames at all the steps' ends at once; their accelerations are each step's mean
            # (``_step_mean_frames``), not the frames' own
            self._surface_ahead = dict(zip(ends, self.surface.root_frames_at(ends, accelerations=False), strict=True))
        self._ahead = {t_end: self._applied(t_end) for t_end in ends}
        try:
            return st.advance_frame(self._before_step, substeps)
        finally:
            self._ahead, self._surface_ahead = {}, {}

    def frame_stats(self) -> dict:
        """Counters of the frame just simulated (one small read each): broken links, contacts."""
        stats = {}
        if self.links is not None:
            stats["broken_links"] = self.links.broken_count()
        if self.contacts is not None:
            stats["contacts"] = self.contacts.contact_count()
        return stats

    @property
    def state(self):
        """The current :class:`hairwarp.State` (the one the last step wrote); read it, or edit its joints between
        frames and call ``solver.forward_kinematics`` on it."""
        return self.stepper.state

    def checkpoint(self) -> dict[str, np.ndarray]:
        """Host copies of everything the run needs to go on from here exactly: both states of the stepper (every
        array of :class:`hairwarp.State`), its time [s], frame and parity, and the solver's
        :meth:`hairwarp.Solver.persistent_arrays`."""
        st = self.stepper
        # ``numpy()`` of a CPU array is a view of it: copied, or the checkpoint would follow the run
        out = {f"state{i}.{name}": _host_copy(getattr(s, name)) for i, s in enumerate(st.states)
               for name in _STATE_ARRAYS}
        out["stepper.time"] = np.array(st.time, dtype=np.float64)
        out["stepper.frame"] = np.array(st.frame, dtype=np.int64)
        out["stepper.parity"] = np.array(st.parity, dtype=np.int64)
        out.update({f"solver.{k}": _host_copy(a) for k, a in self.solver.persistent_arrays().items()})
        # what the hair speed fault's bound has seen so far (host floats): a resumed run checks against the same bound
        terms = self.solver.speed_terms(st.control)
        out[SPEED_KEY] = np.array([terms[k] for k in SPEED_TERMS], dtype=np.float64)
        out[WHIP_REST_KEY] = np.array(self._whip_rest_until, dtype=np.int64)
        return out

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Put the run back where :meth:`checkpoint` was taken (in place: captured graphs stay valid), the head,
        root frames, wind and colliders posed for its time.

        Raises:
            ValueError: the arrays are not those of this simulation (another scene, groom or feature set).
        """
        st = self.stepper
        arrays = _upgraded(arrays)
        targets = {f"state{i}.{name}": getattr(s, name) for i, s in enumerate(st.states) for name in _STATE_ARRAYS}
        targets.update({f"solver.{k}": a for k, a in self.solver.persistent_arrays().items()})
        expected = set(targets) | {"stepper.time", "stepper.frame", "stepper.parity"}
        if set(arrays) - {SPEED_KEY, WHIP_REST_KEY} != expected:
            raise ValueError(f"the checkpoint does not fit this scene: it holds {sorted(set(arrays) - expected)} "
                             f"more and {sorted(expected - set(arrays))} less than the simulation")
        for key, target in targets.items():  # every check before the first change: a refused one changes nothing
            value = np.asarray(arrays[key])
            if value.shape != target.numpy().shape:
                raise ValueError(f"the checkpoint does not fit this scene: {key} has shape {value.shape}, the "
                                 f"simulation {target.numpy().shape} (another groom, segment count or feature set)")
        time_s, frame, parity = (float(np.asarray(arrays[f"stepper.{k}"]).reshape(()))
                                 for k in ("time", "frame", "parity"))
        if not (math.isfinite(time_s) and time_s >= 0.0 and frame >= 0.0 and frame.is_integer()
                and parity in (0.0, 1.0)):
            raise ValueError(f"the checkpoint's stepper.time, frame and parity must be a time >= 0 [s], a whole "
                             f"frame >= 0 and 0 or 1, got {time_s}, {frame} and {parity}")
        for key, target in targets.items():
            target.assign(np.asarray(arrays[key]))
        st.time = time_s
        st.frame = int(frame)
        st.parity = int(parity)
        self._whip_rest_until = int(np.asarray(arrays.get(WHIP_REST_KEY, -1)).reshape(()))
        speeds = np.asarray(arrays.get(SPEED_KEY, ()), dtype=np.float64).reshape(-1)
        if len(speeds) == len(SPEED_TERMS) and np.isfinite(speeds).all():
            # the bound the run had (a checkpoint written before these were kept: the checkpoint's own motion)
            self.solver.restore_speed_terms(st.control, dict(zip(SPEED_TERMS, speeds.tolist())))
        else:
            self.solver.measure_start_speed(st.state)
        # the head, the root frames, the wind and the colliders as the checkpoint's time has them: what is read
        # before the next step (the dense hair, the colliders' meshes) follows the head there, not where the run was
        _, sample, frames = self._applied(time_s)
        control = st.control
        control.set_motion(sample)
        if frames is not None:
            control.set_root_frames(*frames)
        self._wind = self.scene.wind_at(time_s)
        control.set_wind(self._wind)
        self._applied_at_start = None
        if self._moving_colliders:
            self.collider_set.update(time_s)

    def guide_curves(self) -> tuple[np.ndarray, np.ndarray]:
        """Host copies of the guide vertex positions and velocities, (G*(S+1), 3) each."""
        s = self.stepper.state
        return s.vertex_positions.numpy().copy(), s.vertex_velocities.numpy().copy()

    def head_matrix(self, t: float) -> np.ndarray:
        return self.motion.evaluate(t).matrix()


#: Depth [m] inside a collider past which a run warns that the hair starts through it (``Simulation``): real grooms
#: sink roots and first vertices into the scalp by a millimetre or so (the TressFX Ratboy's by up to 1.03 mm), which
#: the exemption is for; deeper is a collider placed through the hair.
START_INSIDE_DEPTH = 0.005

#: The checkpoint entry of a run's scene (JSON), which ``--resume`` compares with the scene it is given.
RESUME_SCENE_KEY = "run.scene"

#: Scene keys a resumed run may change: how long it runs and how, not what it simulates or writes.
RESUME_FREE_KEYS = ("sim.frames", "sim.device", "sim.threads", "output.preview", "output.preview_frames",
                    "output.writer")


def _flat_scene(scene) -> dict:
    """``scene``'s values by dotted key, less :data:`RESUME_FREE_KEYS`."""
    flat = {}

    def walk(node, prefix):
        for key, value in node.items():
            path = f"{prefix}{key}"
            if isinstance(value, dict):
                walk(value, path + ".")
            elif path not in RESUME_FREE_KEYS:
                flat[path] = value

    walk(scene.to_dict(), "")
    return flat


def _resume_scene(scene) -> str:
    import json

    return json.dumps(_flat_scene(scene), sort_keys=True, default=str)


#: Scene keys (and key prefixes) of what a cache holds besides the simulation: the strands and their curves, the
#: colliders' meshes, the stage's units and time codes. A resumed run that changes one would write a cache whose
#: frames do not fit together.
RESUME_FIXED_KEYS = ("scene.", "groom.", "dense.", "output.", "sim.fps", "sim.segments", "head.shape", "head.file",
                     "head.center", "head.radii", "head.up_axis", "head.scale", "head.translate", "colliders")


def _check_resumed_scene(scene, saved, out_path) -> str | None:
    """Compare the scene a run resumes with with the stopped run's (but for :data:`RESUME_FREE_KEYS`). A change of
    what the cache holds (:data:`RESUME_FIXED_KEYS`: a dense hair count, the groom, the stage's units) is refused;
    a change of the simulation (more substeps after a fault, another stiffness) is taken from the frame resumed
    after, and the returned note says which."""
    import json

    if saved is None:  # a checkpoint written before runs kept their scene
        return None
    before = json.loads(str(saved))
    now = json.loads(_resume_scene(scene))
    changed = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))

    def listed(keys):
        text = ", ".join(f"{k} ({now.get(k)!r}, was {before.get(k)!r})" for k in keys[:3])
        return text + (f" and {len(keys) - 3} more" if len(keys) > 3 else "")

    fixed = [k for k in changed if k.startswith(RESUME_FIXED_KEYS)]
    if fixed:
        raise ValueError(f"{out_path}: cannot resume: the cache's frames would not fit together: {listed(fixed)}; "
                         f"resume with the stopped run's values, or run without --resume to start afresh")
    if changed:
        return f"resuming with a changed simulation: {listed(changed)}, from the frame resumed after"
    return None


def _cache_writer(scene, out_path, notes: list, resume: bool):
    """The writer ``output.writer`` asks for: the inline :class:`hairwarp.io.cache.CacheWriter` or a
    :class:`hairwarp.io.background.BackgroundCacheWriter` (the simulation goes on while a second process converts and
    saves each frame); the inline one, with a note, where the background writer cannot run."""
    from hairwarp.io.background import BackgroundCacheWriter, background_supported
    from hairwarp.io.cache import CacheWriter

    out = scene.output
    options = {"fps": float(scene.sim.fps), "comment": f"scene: {scene.name}", "layout": out.layout,
               "resume": resume, "up_axis": out.up_axis, "meters_per_unit": float(out.meters_per_unit),
               "start_frame": int(out.start_frame)}
    if scene.output.writer == "background":
        if background_supported():
            return BackgroundCacheWriter(out_path, **options)
        notes.append("output.writer = background needs a POSIX system; the cache was written inline")
    return CacheWriter(out_path, **options)


def cache_root_uv(groom, root_uv) -> np.ndarray | None:
    """Texture coordinates of the guide roots for the cache (``primvars:st``, ``groom_root_uv``): the groom's own
    ``surface_uv`` when its file had them, else its 2-D root chart ``root_uv`` moved and scaled uniformly into the
    unit square (a planar map of the scalp without seams), else None."""
    if getattr(groom, "surface_uv", None) is not None:
        return np.asarray(groom.surface_uv, dtype=np.float64)
    if root_uv is None:
        return None
    uv = np.asarray(root_uv, dtype=np.float64)
    lo = uv.min(axis=0)
    span = float(np.max(uv.max(axis=0) - lo))
    return (uv - lo) / span if span > 0.0 else np.zeros_like(uv)


def _dense_widths(dense, guide_widths: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per-vertex widths of the dense curves from the guides' (G, S+1): the guides' widths at the same fraction
    of the strand, blended with each dense strand's guide weights."""
    G, n = guide_widths.shape
    blended = np.einsum("dj,djk->dk", dense.guide_weight, guide_widths[dense.guide_index])  # (D, S+1)
    m = int(counts[0])
    if m == n:
        return blended.ravel()
    t = np.linspace(0.0, 1.0, m)
    s = np.linspace(0.0, 1.0, n)
    return np.array([np.interp(t, s, row) for row in blended]).ravel()


class RunStopped(Exception):
    """A run stopped by a signal (SIGINT, SIGTERM, SIGHUP) after its last complete frame.

    Attributes:
        signum: the signal; the ``hairwarp`` command exits with 128 + signum.
    """

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.signum = signum


_STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")


class _Stops:
    """While active, SIGINT, SIGTERM and SIGHUP ask the run to stop after the frame in flight (``requested``); a
    second one drops that frame at once (KeyboardInterrupt). The previous handlers come back on exit. Only the
    main thread can take signals; elsewhere this does nothing."""

    def __init__(self):
        self.requested: int | None = None
        self._previous = {}

    def _handle(self, signum, _frame):
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = signum

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            for name in _STOP_SIGNALS:
                sig = getattr(signal, name, None)
                if sig is not None:
                    self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc):
        import signal

        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        return False


def _estimate_memory(scene, strands: int | None = None) -> int:
    """Device and host memory [bytes] of the run's arrays for ``strands`` guides, by default the generator's count
    (a groom file's, none: it has its count only once read, ``_check_groom_memory``)."""
    S = int(scene.sim.segments)
    if strands is None:
        strands = int(scene.groom.count) if scene.groom.generator else 0
    points = int(getattr(scene.groom, "points", 0) or S + 1)
    # the generator's float64 polylines, a few copies while it grows them
    guides = strands * S * GUIDE_SEGMENT_BYTES + strands * points * 24 * 4
    return guides + int(scene.dense.count or 0) * _dense_strand_bytes(scene)


#: Memory [bytes] a guide segment takes: two states, the ABA workspace, the model, links and contact slots (about
#: 2 KB, measured loosely from the arrays each allocates).
GUIDE_SEGMENT_BYTES = 2048


def _check_groom_memory(scene, groom) -> None:
    """A groom read from a file has its strand count only once read: the run's arrays for its guides (and dense
    hair by count) checked against the memory at hand, as ``_preflight`` checks a generated groom's, before any is
    allocated (ValueError, one line naming the file and the keys that lower it)."""
    from hairwarp.io.usd_common import _human_bytes

    available = _available_memory()
    if scene.groom.generator or available is None:
        return
    G, S = groom.strand_count, int(scene.sim.segments)
    need = _estimate_memory(scene, G)
    if need > available:
        raise ValueError(f"{scene.groom.file}: {G:,} guides of {S} segments need about {_human_bytes(need)} of memory "
                         f"for the run's arrays, {_human_bytes(available)} are available: lower groom.max_strands or "
                         f"sim.segments")


def _dense_strand_bytes(scene) -> int:
    """Memory [bytes] a dense strand of the scene takes: its vertices' points (and velocities), four times over
    (device arrays, host copies, the Vt arrays of the frame), and 256 bytes for its binding as it is made (float64
    weights and scalp coordinates)."""
    S = int(scene.sim.segments)
    verts = S * (int(scene.dense.samples_per_segment) if scene.dense.basis == "linear" else 1) + 1
    return 4 * verts * 12 * (2 if scene.dense.velocities else 1) + 256


def _frame_bytes(scene, sim) -> int:
    """Bytes of one binary cache frame of the built run: its curves' points (and velocities) as written, float32,
    and 2 KiB of transforms and bookkeeping. Counted from the built simulation, not the scene: a groom file's guides
    (the Ratboy mohawk's frame was taken for 2 KiB against the 183 KiB it writes) and dense hair set by
    ``dense.density`` have their counts only there."""
    n = 2048
    if scene.output.guides:
        n += sim.model.strand_count * (sim.model.seg_per_strand + 1) * 24
    if sim.dense is not None:
        verts = int(sim.dense.curve_vertex_counts(scene.dense.basis == "linear").sum())
        n += verts * 12 * (2 if scene.dense.velocities else 1)
    return n


def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _preflight(scene, out_path: Path, frames: int, device) -> None:
    """The checks a run makes before building anything; each raises ValueError with one line naming the key or
    the path: the cache's suffix and folder, the device, and memory for the arrays the scene asks for."""
    from hairwarp.io.usd_common import USD_SUFFIXES, _human_bytes, check_usd_path

    check_usd_path(out_path)
    if out_path.is_dir():
        raise ValueError(f"{out_path}: is a folder; name the cache file, e.g. {out_path / (scene.name + '.usdc')}")
    if out_path.suffix.lower() not in USD_SUFFIXES:
        raise ValueError(f"{out_path}: a cache must end in one of {', '.join(USD_SUFFIXES)}, not "
                         f"{out_path.suffix or 'no suffix'!r}")
    resolve_device(device or scene.sim.device, "sim.device")
    memory = _estimate_memory(scene)
    available = _available_memory()
    if available is not None and memory > available:
        raise ValueError(f"{scene.name}: the run needs about {_human_bytes(memory)} of memory for its arrays, "
                         f"{_human_bytes(available)} are available: lower groom.count, sim.segments or dense.count")


def _kept(cache) -> str:
    """Where the frames of a run that did not finish are, for its message."""
    if cache.last_frame is None:
        return "no frame was complete"
    first = cache.last_frame - cache.frames_written + 1
    at = (f"the cache at {cache.path} is untouched" if Path(cache.path).exists()
          else f"nothing was written at {cache.path}")
    frames = f"frame {first} is" if first == cache.last_frame else f"frames {first}-{cache.last_frame} are"
    return (f"{frames} in {cache.partial_path} (hairwarp run --resume continues "
            f"from there, with a changed simulation too, such as more substeps; {at})")


def _mesh_collider(path, up_axis, scale, translate, rotate_deg, name, options):
    from hairwarp.colliders import Collider
    from hairwarp.motion import euler_xyz_deg_to_quat, quat_to_matrix

    col = Collider.from_mesh_file(path, up_axis=up_axis, scale=float(scale), name=name, **options)
    place = np.eye(4)
    place[:3, :3] = quat_to_matrix(euler_xyz_deg_to_quat(rotate_deg))
    place[:3, 3] = translate
    col.local_xform = place @ col.local_xform
    return col


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a``, no longer writable (an array handed out again and again)."""
    a.setflags(write=False)
    return a


def _display_mesh(col) -> tuple[np.ndarray, np.ndarray]:
    """A triangle mesh of a collider in its local frame (analytic shapes tessellated for display).

    The analytic shapes are tessellated here in numpy (a latitude-longitude grid) rather than by trimesh: a run whose
    colliders are all analytic then never imports trimesh and scipy, 0.7 s of every ``hairwarp run``'s start-up."""
    from hairwarp.kernels.types import ColliderKind

    if col.kind == ColliderKind.MESH:
        return np.asarray(col.mesh.vertices, dtype=np.float64), np.asarray(col.mesh.faces, dtype=np.int32)
    if col.kind == ColliderKind.SPHERE:
        return _lat_long_mesh(np.full(3, col.radius), 0.0)
    if col.kind == ColliderKind.CAPSULE:
        return _lat_long_mesh(np.full(3, col.radius), col.half_height)
    if col.kind == ColliderKind.ELLIPSOID:
        return _lat_long_mesh(np.asarray(col.radii, dtype=np.float64), 0.0)
    # a 1 m square of the plane z = 0, 1 mm thick
    corners = np.array([[x, y, z] for z in (-5e-4, 5e-4) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
    return corners, np.asarray(faces, dtype=np.int32)


def _lat_long_mesh(radii, half_height: float, rings: int = 32, sectors: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A closed latitude-longitude mesh of the ellipsoid of ``radii`` about z, its upper half lifted by
    ``half_height`` and its lower half lowered by as much (a capsule; 0: the ellipsoid). ``rings`` is even and
    ``sectors`` a multiple of 4, so the poles, the equator and the four axis points lie on it: the mesh reaches
    every radius exactly."""
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]  # from the +z pole, poles excluded
    if half_height > 0.0:
        theta = np.insert(theta, rings // 2, np.pi / 2)  # the equator twice: the capsule's cylinder between
    phi = np.linspace(0.0, 2.0 * np.pi, sectors, endpoint=False)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (len(theta), sectors))], axis=-1)
    ring = ring * radii
    lift = np.where(np.arange(len(theta)) < rings // 2, half_height, -half_height)
    ring[..., 2] += lift[:, None]
    verts = np.concatenate([[[0.0, 0.0, radii[2] + half_height]], ring.reshape(-1, 3),
                            [[0.0, 0.0, -radii[2] - half_height]]])
    n, last = len(theta), len(verts) - 1
    j = np.arange(sectors)
    jn = (j + 1) % sectors
    faces = [np.stack([np.zeros(sectors, int), 1 + j, 1 + jn], axis=1)]
    for r in range(n - 1):
        a, b = 1 + r * sectors, 1 + (r + 1) * sectors
        faces.append(np.stack([a + j, b + j, b + jn], axis=1))
        faces.append(np.stack([a + j, b + jn, a + jn], axis=1))
    base = 1 + (n - 1) * sectors
    faces.append(np.stack([np.full(sectors, last), base + jn, base + j], axis=1))
    return verts, np.concatenate(faces).astype(np.int32)


def _merged_world_mesh(meshes):
    """One (vertices, faces) in world space of all collider meshes, or None."""
    if not meshes:
        return None
    verts, faces, offset = [], [], 0
    for _, v, f, world in meshes:
        verts.append(v @ world[:3, :3].T + world[:3, 3])
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


@dataclass
class RunResult:
    """What :func:`simulate` produced.

    Attributes:
        frames: the frames the cache holds after its first (``sim.frames``), those of a resumed run included.
        seconds: wall time of the whole call: building the simulation, the frames, the cache's close, the preview.
        seconds_per_frame: wall time per frame this run simulated, of the frames alone (writing them included).
        resumed_frames: frames after the first that the stopped run had simulated (0 for a run that did not
            resume); this run simulated ``frames - resumed_frames``.
        frame_seconds: wall time of the frames alone.
        stage_seconds: with ``profile``, the frames' wall time by stage (``Solver.profile_stages``, the hair contacts'
            detection once a frame, ``output``: the frames' curves, checkpoints and writes), else None.
    """

    cache_path: Path
    preview_path: Path | None
    frames: int
    seconds: float
    seconds_per_frame: float
    notes: list[str] = field(default_factory=list)
    frame_stats: list[dict] = field(default_factory=list)
    resumed_frames: int = 0
    frame_seconds: float = 0.0
    stage_seconds: dict | None = None


class _Progress:
    """One line on the terminal: frame, speed, time left; a line per 10 % when not a terminal.

    The speed is that of the frames simulated since the first one written (frame 0 costs no step, and the first
    step loads the kernels), so no estimate is shown until one frame has been simulated."""

    def __init__(self, total: int, enabled: bool, stream=None):
        self.total = total
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.base = 0
        self._clock = False
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._last_decile = -1

    def note(self, line: str):
        """One line of its own (what a run found, the estimated cache size)."""
        if self.enabled:
            self.stream.write(line + "\n")
            self.stream.flush()

    def restart(self, first: int):
        """Frames before ``first`` were written by an earlier run."""
        self.base = first

    def update(self, done: int, stats: dict | None = None):
        if not self.enabled:
            return
        now = time.perf_counter()
        if not self._clock and done > self.base:  # the clock starts once the first simulated frame is out
            self.start, self.base, self._clock = now, done, True
        elapsed = now - self.start
        line = f"frame {done}/{self.total}"
        if done > self.base and elapsed > 0:
            rate = (done - self.base) / elapsed
            line += f"  {rate:.2f} frames/s  {(self.total - done) / rate:.0f} s left"
        if stats:
            line += "  " + "  ".join(f"{k.replace('_', ' ')} {v}" for k, v in stats.items())
        if self.tty:
            self.stream.write("\r" + line.ljust(60))
            if done == self.total:
                self.stream.write("\n")
        else:
            decile = (10 * done) // self.total
            if decile != self._last_decile:
                self._last_decile = decile
                self.stream.write(line + "\n")
        self.stream.flush()


def simulate(scene, out_path, *, frames: int | None = None, device=None, progress: bool = True,
             preview: bool | None = None, resume: bool = False, profile: bool = False) -> RunResult:
    """Run ``scene`` headless and write its USD cache to ``out_path`` and a preview PNG beside it.

    The cache is written frame by frame in ``<stem>.partial/`` beside ``out_path`` and moved there when the run
    succeeds (see :mod:`hairwarp.io.cache`); SIGINT, SIGTERM and SIGHUP stop the run after the frame in flight.

    Args:
        scene: a :class:`hairwarp.Scene`, a scene file's path, or its tables as a dict.
        out_path: the cache (.usdc, .usd or .usda).
        frames: output frames after the first (a whole number >= 0); default ``sim.frames``.
        device: Warp device; default ``sim.device``.
        progress: report progress on stderr.
        preview: render the preview picture; default ``output.preview``.
        profile: time the frames stage by stage (:attr:`RunResult.stage_seconds`; the stages then run one after
            another, a little slower, with the same result).
        resume: continue the run a stop or a fault left in the working folder after its last complete frame; where
            the cache is complete and its preview missing (a run stopped while drawing it), draw the preview from
            the cache.

    Raises:
        ValueError: a check before the first step failed (the output, the device, memory, disk space), or
            another run writes the same cache (one line, naming the path or the key).
        SimulationFault: the run left its bounds; the message names the frame, the stage and the
            parameter to change, and where the complete frames are.
        RunStopped: a signal stopped the run; the message says where the complete frames are.
        hairwarp.io.cache_folder.CacheWriteError: the disk filled up or failed; the message names the path, the
            space needed and where the complete frames are.
        hairwarp.preview.PreviewWriteError: the cache is complete and in place, but its preview could not be
            written (the message says both).
    """
    from hairwarp.io.cache_folder import CacheComplete, CacheWriteError
    from hairwarp.scene import Scene

    t_start = time.perf_counter()
    scene = Scene.coerce(scene)
    out_path = Path(out_path)
    if frames is not None and (isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 0):
        raise ValueError(f"frames must be a whole number >= 0, got {frames!r}")
    frames = int(scene.sim.frames if frames is None else frames)
    preview = bool(scene.output.preview if preview is None else preview)
    _preflight(scene, out_path, frames, device)
    notes, all_stats = [], []
    report = _Progress(frames, progress)
    # One stop handler from the lock to the preview: a signal while the simulation is built (a second or more) was
    # the default's, which ended the process silently and left the lock behind.
    with _Stops() as stops:
        try:
            cache = _cache_writer(scene, out_path, notes, resume)
        except CacheComplete:
            # a complete cache with its preview missing, of the frames asked for: the preview drawn from it
            if not preview or out_path.with_suffix(".png").exists() or _cached_frames(out_path) != frames:
                raise
            return _preview_of_complete_cache(scene, out_path, frames, notes, t_start)
        try:
            if cache.folder.found:
                report.note(cache.folder.found)
            sim = Simulation(scene, device=device)
            if profile:
                sim.solver.profile_stages()
            start = 0
            if cache.resumed_after is not None:
                # Frames are stored at time code output.start_frame + frame; the checkpoints are named by time code.
                first = cache.folder.frame_range()[0]
                if first != cache.start_frame:
                    raise ValueError(f"{out_path}: cannot resume: the stopped run starts at frame {first}, "
                                     f"output.start_frame is {cache.start_frame}")
                if cache.resumed_after - cache.start_frame > frames:
                    raise ValueError(f"{out_path}: cannot resume: the stopped run is at frame "
                                     f"{cache.resumed_after}, past sim.frames = {frames}")
                saved = cache.folder.read_checkpoint(cache.resumed_after)
                changed = _check_resumed_scene(scene, saved.pop(RESUME_SCENE_KEY, None), out_path)
                if changed:
                    notes.append(changed)
                    report.note(changed)
                sim.restore(saved)
                start = cache.resumed_after - cache.start_frame + 1
            _check_disk_space(cache, scene, sim, frames, start, preview, report)
            if stops.requested is not None:
                raise RunStopped(f"stopped by {_signal_name(stops.requested)} before frame {start}.", stops.requested)
            t_frames = time.perf_counter()
            kept = _run_frames(sim, scene, cache, frames, start, report, notes, all_stats, stops)
            frame_seconds = time.perf_counter() - t_frames
            cache.close(keep_lock=True)  # until the preview is written: a second run would replace the cache
        except SimulationFault as fault:
            cache.abandon()
            raise SimulationFault(f"{fault} {_kept(cache).capitalize()}.", frame=fault.frame, stage=fault.stage,
                                  bits=fault.bits) from None
        except CacheWriteError as exc:
            cache.abandon()
            raise CacheWriteError(f"{cache.path}: {exc}; {_kept(cache)}") from None
        except RunStopped as stop:
            cache.abandon()
            raise RunStopped(f"{stop} {_kept(cache).capitalize()}.", stop.signum) from None
        except BaseException:
            cache.abandon()
            raise

        from hairwarp.preview import PreviewWriteError

        preview_path = None
        try:  # the cache is complete: a stop now skips only the picture
            if preview:
                preview_path = _draw_preview(scene, sim, out_path, start, kept)
        except KeyboardInterrupt:
            pass  # a second signal: stop drawing at once
        except PreviewWriteError as exc:
            raise PreviewWriteError(f"the cache {out_path} is complete ({frames + 1} frames), the preview is "
                                    f"missing: {exc}") from None
        finally:
            cache.release()
        if stops.requested is not None:
            raise RunStopped(f"stopped by {_signal_name(stops.requested)} while drawing the preview; the cache "
                             f"{out_path} is complete ({frames + 1} frames), the preview may be missing (hairwarp "
                             f"run --resume draws it from the cache).", stops.requested)
    seconds = time.perf_counter() - t_start
    resumed = max(start - 1, 0)  # frame 0 is the rest pose, not simulated
    stages = dict(sim.solver.stage_seconds) if sim.solver.stage_seconds is not None else None
    return RunResult(out_path, preview_path, frames, seconds, frame_seconds / max(frames - resumed, 1), notes,
                     all_stats, resumed, frame_seconds, stages)


USDA_BYTES_FACTOR = 4.0
"""Bytes of a ``.usda`` cache per byte of its binary estimate, for the disk-space check: its numbers are text (a
float32 written as 9-15 characters and a separator); measured 2.1-3.4 on the default scene's frames (3.46 MB against
an estimate of 1.02 MB), 2.8 on its topology."""

PREVIEW_BYTES_PER_PIXEL = 0.5
"""Bytes of a preview PNG per pixel, for the disk-space check: 0.33 measured on tiny's sheet, 0.47 on the default
scene's (3,000 dense strands)."""


def _disk_needed(scene, sim, frame_bytes: int, frames: int, start: int, preview: bool,
                 text: float = 1.0) -> dict[str, int]:
    """Bytes the run still writes on the cache's disk, by part: the frames (twice where the cache's close rewrites
    them: flattened, or small frames gathered into clips), the topology layer (what its own space check asks: the
    collider meshes and the curves' static arrays, uncompressed), the state stored with each frame (two at once:
    the last frame's goes once the next one's is in place) and the preview. ``text``: the topology's bytes per byte
    of its binary size (``USDA_BYTES_FACTOR`` for a text cache)."""
    from hairwarp.io.cache import CHUNK_BYTES
    from hairwarp.preview import sheet_size

    parts = {"frames": frame_bytes * (frames + 1 - start)}
    if scene.output.layout == "single" or (frame_bytes * 2 <= CHUNK_BYTES and frames > 0):
        parts["frames"] += frame_bytes * (frames + 1)
    if start == 0:  # a resumed run's topology is on the disk already
        curves = [(sim.model.strand_count, sim.model.strand_count * (sim.model.seg_per_strand + 1))]
        if sim.dense is not None:
            counts = sim.dense.curve_vertex_counts(scene.dense.basis == "linear")
            curves.append((len(counts), int(counts.sum())))
        meshes = sim.collider_meshes(0.0)
        parts["topology"] = int(text * (sum(32 * n + 4 * v for n, v in curves)
                                        + sum(24 * len(faces) + 24 * len(verts) for _, verts, faces, _ in meshes)))
    state = {**sim.checkpoint(), RESUME_SCENE_KEY: np.array(_resume_scene(scene))}
    parts["state"] = 2 * sum(a.nbytes for a in state.values())
    if preview:
        width, height = sheet_size(min(int(scene.output.preview_frames), frames + 1))
        parts["preview"] = int(width * height * PREVIEW_BYTES_PER_PIXEL)
    return parts


def _check_disk_space(cache, scene, sim, frames: int, start: int, preview: bool, report) -> None:
    """Print what the run will write on the cache's disk and refuse a run that cannot fit there (one line,
    ValueError), counting the frames, the topology, the stored state and the preview (the frames alone passed a
    48-100 KiB disk for tiny, whose run then failed at frame 0)."""
    from hairwarp.io.cache_folder import free_bytes
    from hairwarp.io.usd_common import _human_bytes

    frame_bytes = _frame_bytes(scene, sim)
    text = USDA_BYTES_FACTOR if Path(cache.path).suffix.lower() == ".usda" else 1.0
    frame_bytes = int(frame_bytes * text)
    parts = _disk_needed(scene, sim, frame_bytes, frames, start, preview, text)
    total = sum(parts.values()) + 65536  # each write's own check keeps this much spare
    count = frames + 1 - start
    listed = ", ".join(f"{name} {_human_bytes(n)}" for name, n in parts.items())
    report.note(f"cache    {cache.path}: about {_human_bytes(frame_bytes * (frames + 1))} "
                f"({_human_bytes(frame_bytes)} per frame x {frames + 1} frames"
                + (f", {count} of them to write" if start else "") + f"); the run needs about "
                f"{_human_bytes(total)} on its disk ({listed})")
    free = free_bytes(cache.folder.dir)
    if total > free:
        raise ValueError(f"{cache.path}: the run needs about {_human_bytes(total)} on its disk ({listed}), "
                         f"{_human_bytes(free)} are free on its disk: free space, or lower sim.frames or dense.count")


def _cached_frames(out_path: Path) -> int:
    """The frames after the first that the cache at ``out_path`` holds."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(out_path))
    return int(round(stage.GetEndTimeCode() - stage.GetStartTimeCode()))


def _preview_of_complete_cache(scene, out_path: Path, frames: int, notes: list, t_start: float) -> RunResult:
    """``--resume`` where the run's cache is complete but its preview missing (a run stopped or killed while drawing
    it): the preview drawn from the cache, no frame simulated."""
    from hairwarp.preview import preview_cache

    path = preview_cache(out_path, out_path.with_suffix(".png"), frames=int(scene.output.preview_frames))
    notes.append(f"the cache {out_path} was complete; its missing preview was drawn from it")
    return RunResult(out_path, path, frames, time.perf_counter() - t_start, 0.0, notes, [], frames, 0.0, None)


def _draw_preview(scene, sim, out_path: Path, start: int, kept: list) -> Path | None:
    """Draw the run's preview beside its cache from the frames ``_run_frames`` kept; returns its path, or None when
    no frame was kept."""
    if start > 0:  # the frames before the resume are in the cache only
        from hairwarp.preview import preview_cache

        return preview_cache(out_path, out_path.with_suffix(".png"), frames=int(scene.output.preview_frames))
    if not kept:
        return None
    from hairwarp.preview import frame_title, render_frames, sheet_size

    first = int(scene.output.start_frame)
    return render_frames(
        [c for _, c, _ in kept],
        out_path.with_suffix(".png"),
        titles=[frame_title(first + f, f * sim.frame_dt) for f, _, _ in kept],
        meshes=[m for _, _, m in kept] if sim.colliders else None,
        size_px=sheet_size(len(kept)),
    )


def _signal_name(signum: int) -> str:
    import signal

    return signal.Signals(signum).name


def _run_frames(sim, scene, cache, frames: int, start: int, report, notes, all_stats, stops) -> list:
    """Declare the cache's prims, then simulate and write frames ``start`` .. ``frames`` (each with its checkpoint);
    returns the frames kept for the preview."""
    model = sim.model
    G, S = model.strand_count, model.seg_per_strand
    counts = np.full(G, S + 1, dtype=np.int32)
    meshes0 = sim.collider_meshes(0.0)
    shown = set(np.linspace(0, frames, min(int(scene.output.preview_frames), frames + 1)).round().astype(int))
    kept = []
    overflow_noted = False
    grown_seen = len(sim.contacts.grown) if sim.contacts is not None else 0
    grown_first = start if grown_seen else None  # grown at the first detection, before the first step
    dense = sim.dense
    guide_uv = cache_root_uv(sim.groom, model.root_uv)
    guide_widths = sim.groom.resampled_widths(S)  # (G, S+1) from the groom file, or None
    if dense is not None:
        hermite = scene.dense.basis == "linear"
        cache_counts = dense.curve_vertex_counts(hermite)
        dense_uv = (None if guide_uv is None
                    else np.einsum("dj,djc->dc", dense.guide_weight, guide_uv[dense.guide_index]))
        widths = tuple(scene.dense.width) if guide_widths is None else _dense_widths(dense, guide_widths, cache_counts)
        cache.add_curves("hair", cache_counts, widths=widths, kind="dense", basis=scene.dense.basis, root_uv=dense_uv)
    if scene.output.guides:
        # with dense hair the guides are a guide purpose: renderers skip them, viewports may show them
        widths = tuple(scene.output.guide_width) if guide_widths is None else guide_widths.ravel()
        cache.add_curves("guides", counts, widths=widths, kind="guides",
                         purpose="guide" if dense is not None else "default", root_uv=guide_uv)
    for name, verts, faces, _ in meshes0:
        cache.add_mesh(name, verts, faces, purpose=scene.output.collider_purpose)
    t0 = cache.start_frame
    run_scene = np.array(_resume_scene(scene))  # kept in every checkpoint, for --resume
    report.restart(start)
    stages = sim.solver.stage_seconds  # profiled: what a frame spends besides its steps goes to "output"
    for frame in range(start, frames + 1):
        if frame > 0:
            bits = sim.advance_frame()
            if bits & Fault.CONTACT_OVERFLOW and not overflow_noted:
                overflow_noted = True
                notes.append(f"frame {frame}: {sim.contacts.overflow_advice()}")
            if sim.contacts is not None and len(sim.contacts.grown) > grown_seen:
                grown_seen, grown_first = len(sim.contacts.grown), frame if grown_first is None else grown_first
        t_output = time.perf_counter()
        stats = sim.frame_stats()
        all_stats.append(stats)
        points, velocities = sim.guide_curves()
        meshes = sim.collider_meshes(frame * sim.frame_dt)
        curves = {"guides": (points, velocities)} if scene.output.guides else {}
        if dense is not None:
            curves["hair"] = sim.dense_curves()
        cache.write_frame(t0 + frame, curves, xforms={name: world for name, _, _, world in meshes} or None,
                          checkpoint={**sim.checkpoint(), RESUME_SCENE_KEY: run_scene})
        if frame in shown:
            mesh = _merged_world_mesh(meshes)
            if dense is not None:  # the preview shows what renders: the dense hair
                shown_curves = {"hair": (curves["hair"][0].copy(), cache_counts)}
            else:
                shown_curves = {"guides": (points, counts)}
            kept.append((frame, shown_curves, mesh))
        if stages is not None:
            stages["output"] = stages.get("output", 0.0) + time.perf_counter() - t_output
        # frames taken again after a fault show as they come, not only in the notes at the end
        report.update(frame, {**stats, "retaken": sim.retaken_frames} if sim.retaken_frames else stats)
        if stops.requested is not None and frame < frames:
            raise RunStopped(f"stopped by {_signal_name(stops.requested)} after frame {frame}.", stops.requested)
    unstable = sim.model.hold_unstable
    if unstable is not None and unstable.any() and sim.links is not None:  # without links the build warned
        notes.append(f"groom.hold_shape: {int(unstable.sum())} of {sim.model.strand_count} guides would buckle from "
                     f"their drawn shape on their own springs; only their links hold them up")
    if grown_first is not None:
        notes.append(f"frame {grown_first}: {_slots_grown_note(sim.contacts)}")
    if sim.refined_frames:
        notes.append(f"{sim.refined_frames} frames were taken again in steps of links.break_step "
                     f"({sim.break_step:.3g} s): links broke in them at the scene's longer steps")
    notes.extend(note for note in (_retakes_note(sim), _retakes_note(sim, whips=True)) if note is not None)
    notes.extend(note for note in (sim.stiff_links_note, sim.link_damping_note, sim.stiff_contacts_note,
                                   sim.contact_rest_note) if note is not None)
    whip = sim.whip_note()
    if whip is not None:
        notes.append(whip)
    return kept


def _slots_grown_note(contacts) -> str:
    """What the run's note says where the hair contacts' slots grew (:attr:`HairContacts.grown`)."""
    first, most = contacts.grown[0][0], max(found for _, found in contacts.grown)
    times = "" if len(contacts.grown) == 1 else f" ({len(contacts.grown)} times)"
    return (f"the hair contacts' slots grew from {first:,} to {contacts.capacity:,}{times} to hold up to {most:,} "
            f"pairs, none dropped; interactions.capacity = {contacts.capacity} starts a run there")


def _retakes_note(sim, whips: bool = False) -> str | None:
    """The run's note on its frames taken again after a fault (``sim.fault_retries``), or with ``whips`` on those
    taken again only because their guides whipped (``sim.whip_ratio``) and slowed in finer steps: how many, the first
    few with the steps they ran in and what made them, and what would spare them; None where there are none."""
    last, whipped = {}, {}
    for frame, steps, stage in sim.retakes:
        last[frame] = (steps, stage)  # the steps it finally ran in
        whipped[frame] = whipped.get(frame, True) and stage == "whip"
    motion = {frame for frame, _ in sim.motion_whips}  # the motion's whips: its own note (``whip_note``)
    last = {f: taken for f, taken in last.items() if whipped[f] == whips and f not in motion}
    if not last:
        return None
    shown = ", ".join(f"{f} in {n} steps" + ("" if whips else f" ({stage})")
                      for f, (n, stage) in list(last.items())[:4])
    more = f" and {len(last) - 4} more" if len(last) > 4 else ""
    n = sim.stepper.substeps
    at = f"at {n} substep{'s' if n != 1 else ''}"
    one = len(last) == 1
    frames, were = f"{len(last)} frame{'' if one else 's'}", "was" if one else "were"
    if whips:
        return (f"{frames} whipped {'its' if one else 'their'} guides past sim.whip_ratio = {sim.whip_ratio:g} times "
                f"the speed the motion explains {at} and {were} taken again in more steps: frame {shown}{more}; "
                f"motion this fast wants more sim.substeps")
    return (f"{frames} faulted {at} and {were} taken again in more steps: frame {shown}{more}; raise "
            f"sim.substeps to run {'it' if one else 'them'} at the scene's own steps")
