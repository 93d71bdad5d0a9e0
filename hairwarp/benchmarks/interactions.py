"""Cost of hair-hair interactions (static links and contacts) next to the dynamics step, on the Ratboy mohawk.

:func:`bench_interactions` runs the ``ratboy_mohawk`` scene with links and contacts on into its motion, then times,
interleaved on the same state, each stage a step pays: the dynamics step alone, the link forces and the link
breaking, the BVH refit, the vertex-face and segment-segment detection, and the contact forces over the stored
pairs; and that for each detection margin asked (``0``: detection in every step).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import warp as wp

from hairwarp.benchmarks.common import interleaved_medians, ratboy_assets, ratboy_mohawk_scene, timed_samples

# Detection margins [m] compared: 0 detects in every step; the others once per frame (the runner's default is
# the scene's interactions.margin, 4 mm).
MARGINS = (0.0, 0.001, 0.002, 0.004)


def bench_interactions(quick: bool = False, device=None, *, groom_path=None, body_path=None,
                       motion_frames: int | None = None, repeats: int | None = None, margins=MARGINS,
                       overrides=(), missed_frames: int = 0) -> dict:
    """Cost per step of links, strip refit and contacts (detection and forces apart) next to the dynamics step.

    The ``ratboy_mohawk`` scene with every guide (2,219 x 31 segments; ``quick``: every 5th) and
    ``links.enabled`` and ``interactions.enabled`` at the scene defaults (plus ``overrides``, ``key=value``
    strings) runs ``motion_frames`` frames into its turn. From that state each stage is timed (median of
    ``repeats``, interleaved): ``dynamics`` (a solver without colliders, links or contacts), ``links`` (breaking
    and forces, one pass), and, for every margin in ``margins``, a :class:`hairwarp.interactions.HairContacts` built as
    the scene's but with that margin: ``refit`` (strip quad and segment boxes, both BVHs refit; with a margin > 0
    the trees' fit a frame as the runner pays it: ``rebuild`` every ``interactions.REBUILD_FRAMES`` frames on the
    CPU, ``refit_only`` in between, every frame on CUDA), ``vertex_face`` and ``segment_segment`` (detection after
    the fit), ``forces`` (the pass over the stored pairs). The per-step
    cost of the interactions is ``links + forces + response + (refit + detection) / substeps`` for a margin > 0
    (detection once per frame) and ``links + forces + response + refit + detection`` for margin 0, ``response`` the
    scene's solve of the links and contacts after the free step where it has one (``Solver._respond``: the scene's
    free step with it less without it; the mohawk ships ``links.response = "step"``). With ``missed_frames``, what
    each margin > 0 costs in accuracy: the scene run again with ``interactions.margin`` at that margin, as far into
    its motion, then :func:`missed_pairs` over that many frames (``"missed"`` of the margin's row; margin 0, a
    detection at every step, misses none).

    Returns:
        ``{"status": "ok", "device", "strands", "segments", "substeps", "dt", "links", "strip_quads",
        "dynamics_s", "links_s", "response_s", "broken_links", "margins": [{"margin", "stored", "active",
        "refit_s", "vertex_face_s", "segment_segment_s", "forces_s", "per_step_s", "per_dynamics"}], ...}``,
        times in seconds, or ``{"status": "skipped", "message"}`` when the assets are missing.
    """
    from hairwarp.interactions import REBUILD_FRAMES
    from hairwarp.runner import Simulation
    from hairwarp.solver import Solver

    groom_path, body_path, skipped = ratboy_assets(groom_path, body_path)
    if skipped:
        return skipped
    device = wp.get_device(device)
    if motion_frames is None:
        motion_frames = 4 if quick else 15
    if repeats is None:
        repeats = 3 if quick else 9
    t_start = time.perf_counter()
    scene = ratboy_mohawk_scene(groom_path, body_path, device, 450 if quick else 0,
                                ["links.enabled=true", "interactions.enabled=true", *overrides])
    sim = Simulation(scene, device=device)
    for _ in range(motion_frames):
        sim.advance_frame()
    model, stepper = sim.model, sim.stepper
    state, control, dt, substeps = stepper.state, stepper.control, stepper.dt, stepper.substeps
    links, base = sim.links, sim.contacts
    out_state = model.state()
    # on the simulation's threads: timed in turn with its stages, a pool of its own would find the other's threads
    # still spinning after their last launch
    dynamics = Solver(model, scene.sim.integrator, max_rotation_per_step=float(scene.sim.max_rotation_per_step),
                      executor=sim.solver.executor)
    dynamics.set_dt(dt)
    n = model.seg_count
    force = wp.zeros(n, dtype=wp.vec3, device=device)
    torque = wp.zeros(n, dtype=wp.vec3, device=device)
    mass = wp.zeros(n, dtype=float, device=device)
    dt_arr = wp.array([dt], dtype=float, device=device)
    broken = links.link_broken  # applying the links may break some: their flags are put back after the timing
    broken_before = broken.numpy().copy()
    total_before = links.link_broken_total.numpy().copy()
    stages = {
        "dynamics": lambda: dynamics.step(state, out_state, control, dt),
        "links": lambda: links.apply(model, state, dt_arr, force, torque, mass),
    }
    solver = sim.solver
    if solver.responders:
        # the links' and contacts' response after the free step (``links.response`` / ``interactions.response``,
        # "step" or "auto" at long steps): the scene's solver's free step with and without it, over a frame's steps
        # as the stepper takes them (``plan_factors`` before each: the frame's first step makes the factors its later
        # ones solve with, ``Solver.factor_steps``), per step
        free = model.state()

        def free_steps(respond: bool):
            solver.expire_factors()  # the frame's first step makes its factors, as the stepper has it
            for _ in range(substeps):
                solver.plan_factors()
                solver._integrate(state, free, control)
                if respond:
                    solver._respond(state, free, control)

        stages["free step"] = lambda: free_steps(False)
        stages["free step + response"] = lambda: free_steps(True)
    common = interleaved_medians(stages, device, repeats)
    response = max(common.get("free step + response", 0.0) - common.get("free step", 0.0), 0.0) / substeps
    broken.assign(broken_before)
    links.link_broken_total.assign(total_before)
    frames = _frame_costs(scene, ratboy_mohawk_scene(groom_path, body_path, device, 450 if quick else 0, [
        *overrides, "links.enabled=false", "interactions.enabled=false"]), device, motion_frames,
        REBUILD_FRAMES * (1 if quick else 2))

    rows = []
    for margin in margins:
        # margin 0: detected in every step, inside the step (refit trees); else once a frame, between the steps
        each_step = margin <= 0.0
        # on the simulation's threads, as its own contacts
        contacts = _contacts_like(base, model, margin, base.capacity, solver.executor)
        contacts.detect(model, state)
        stored = contacts.contact_count()

        def vertex_face(c=contacts):
            c.contact_counter.zero_()
            c.detect_vertex_face(model, state)

        def segment_segment(c=contacts):
            c.contact_counter.zero_()
            c.detect_segment_segment(model, state)

        # The detection as the runner pays it (``HairContacts.detect``: bounds, both trees fitted, both kinds of
        # contact, on several threads at once): between steps (margin > 0) the trees on the CPU rebuilt every
        # REBUILD_FRAMES frames and refit in between, on CUDA rebuilt every frame; inside the step (margin 0) refit.
        # Its parts alone, for the table: the trees' fit, each kind of contact.
        stages = {"detect": lambda c=contacts: c.detect(model, state, rebuild=False),
                  "refit": lambda c=contacts: c.refit(model, state)}
        if not each_step:
            stages["detect_rebuilt"] = lambda c=contacts: c.detect(model, state, rebuild=True)
            stages["rebuild"] = lambda c=contacts: c.refit(model, state, rebuild=True)
        stages.update({"vertex_face": vertex_face, "segment_segment": segment_segment})
        times = interleaved_medians(stages, device, repeats)
        if not each_step:
            rebuilt = 1.0 if device.is_cuda else 1.0 / REBUILD_FRAMES
            for part, fitted in (("refit", "rebuild"), ("detect", "detect_rebuilt")):
                times[f"{part}_only"] = times[part]
                times[part] = rebuilt * times[fitted] + (1.0 - rebuilt) * times[part]
        contacts.detect(model, state)

        def forces(c=contacts):
            c.apply_forces(model, state, dt_arr)
            c.gather(model, force, torque, mass)

        times.update(interleaved_medians({"forces": forces}, device, repeats))
        active = _active_contacts(contacts, model, state)
        detection = times["detect"]
        per_step = common["links"] + times["forces"] + response
        per_step += detection if each_step else detection / substeps
        missed = None
        if missed_frames and not each_step:
            run = Simulation(ratboy_mohawk_scene(groom_path, body_path, device, 450 if quick else 0, [
                "links.enabled=true", "interactions.enabled=true", *overrides, f"interactions.margin={margin!r}"]),
                device=device)
            for _ in range(motion_frames):
                run.advance_frame()
            missed = missed_pairs(run, missed_frames)
        rows.append({"margin": float(margin), "detect": "step" if each_step else "frame", "stored": stored,
                     "active": active, "overflowed": contacts.overflowed(),
                     **{f"{k}_s": v for k, v in times.items()}, "detection_s": detection,
                     "per_step_s": per_step, "per_dynamics": per_step / common["dynamics"], "missed": missed})
    return {"status": "ok", "device": str(device), "strands": model.strand_count, "segments": model.seg_per_strand,
            "substeps": substeps, "dt": dt, "time_in_motion_s": motion_frames * sim.frame_dt,
            "links": links.link_count, "broken_links": links.broken_count(),
            "strip_quads": base.strips.quad_count if base.strips is not None else 0,
            "threshold": base.threshold, "scene_margin": base.margin,
            "dynamics_s": common["dynamics"], "links_s": common["links"], "response_s": response,
            "response": [part.__class__.__name__ for part in solver.responders],
            "frames": frames, "margins": rows, "wall_s": time.perf_counter() - t_start}


def _frame_costs(scene, without, device, motion_frames: int, frames: int, dynamics_repeats: int = 0) -> dict:
    """The whole frame's cost of ``scene`` and of the same scene ``without`` its links and contacts, each a fresh
    run ``motion_frames`` frames into its motion, then ``frames`` frames each, in turn (mean wall time a frame, with
    the trees rebuilt as often as the runner does them): what the interactions add a step, read off the runs as they
    pay it rather than summed from stages timed alone. With ``dynamics_repeats``, also the dynamics step on the first
    run's state (a solver without colliders, links or contacts, on its threads), timed that many times in all, a
    share after each pair of frames, so that it samples the same spell of the machine as the frames (timed once after
    them, a change of the machine's pace between the two went whole into the ratio), each share behind an untimed
    step (the frames leave its arrays out of the caches: ``long_hair``'s first step after them took 0.76 ms, the
    next 0.57, medians of 16); the median. Returns ``{"frames", "substeps", "with_s", "without_s", "per_step_s"}``
    and ``"dynamics_s"``."""
    from hairwarp.executor import _park_pools
    from hairwarp.runner import Simulation
    from hairwarp.solver import Solver

    sims = {"with": Simulation(scene, device=device), "without": Simulation(without, device=device)}
    for sim in sims.values():
        for _ in range(motion_frames):
            sim.advance_frame()
    sim = sims["with"]
    model, stepper = sim.model, sim.stepper
    step_dynamics = None
    if dynamics_repeats:
        dynamics = Solver(model, scene.sim.integrator, max_rotation_per_step=float(scene.sim.max_rotation_per_step),
                          executor=sim.solver.executor)
        dynamics.set_dt(stepper.dt)
        out_state = model.state()

        def step_dynamics():
            dynamics.step(stepper.state, out_state, stepper.control, stepper.dt)
    seconds = {name: 0.0 for name in sims}
    dynamics_s = []
    for frame in range(frames):
        for name, run in sims.items():
            _park_pools()  # the other run's threads asleep, not spinning beside this one's
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            run.advance_frame()
            wp.synchronize_device(device)
            seconds[name] += time.perf_counter() - t0
        if step_dynamics is not None:
            # this frame's share of the repeats: dynamics_repeats over the frames in all
            share = (frame + 1) * dynamics_repeats // frames - frame * dynamics_repeats // frames
            if share:
                _park_pools()
                # behind an untimed step: the frames left its arrays out of the caches, as no step of a run does
                dynamics_s += timed_samples(step_dynamics, device, share)
    with_s, without_s = seconds["with"] / frames, seconds["without"] / frames
    substeps = stepper.substeps
    out = {"frames": frames, "substeps": substeps, "with_s": with_s, "without_s": without_s,
           "per_step_s": (with_s - without_s) / substeps, "strands": model.strand_count,
           "segments": model.seg_per_strand, "links": sim.links.link_count if sim.links is not None else 0,
           "contacts": sim.contacts is not None and bool(sim.contacts.enabled),
           "stored": sim.contacts.contact_count() if sim.contacts is not None else 0,
           "response": [part.__class__.__name__ for part in sim.solver.responders]}
    if dynamics_s:
        out["dynamics_s"] = float(np.median(dynamics_s))
    return out


# The shipped scenes with links or hair contacts (``scenes/``), each timed with and without them by
# ``bench_scene_interactions``; the Ratboy mohawk where its assets are found.
INTERACTION_SCENES = ("long_hair", "long_hair_shoulders", "fast_turn", "character", "ratboy_mohawk")


def bench_scene_interactions(quick: bool = False, device=None, names=None) -> dict:
    """What the links and hair contacts add a step in each shipped scene as it ships (``_frame_costs``: the scene
    with and without them, ``links.enabled`` and ``interactions.enabled`` off), against the scene's dynamics step:
    the goal's figure (all interactions at most 2x the dynamics) scene by scene, each at its own density, forms
    (``response``) and settings; and, over the same frames of a run of its own, what finding the hair contacts once a
    frame misses (``missed``: :func:`missed_pairs`, None without hair contacts). Returns ``{"status": "ok", "rows":
    [{"scene", "strands", "segments", "substeps", "links", "contacts", "response", "frames", "with_s", "without_s",
    "per_step_s", "dynamics_s", "per_dynamics", "missed"}] or {"scene", "status": "skipped", "message"}}``;
    ``names`` default :data:`INTERACTION_SCENES`."""
    from hairwarp.interactions import REBUILD_FRAMES
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    device = wp.get_device(device)
    root = Path(Scene.default_path()).parent
    motion, frames, repeats = (10, REBUILD_FRAMES, 9) if quick else (20, 2 * REBUILD_FRAMES, 15)
    rows = []
    for name in INTERACTION_SCENES if names is None else names:
        overrides = [f"sim.device='{device}'"]
        if name == "ratboy_mohawk":
            groom, body, skipped = ratboy_assets()
            if skipped:
                rows.append({"scene": name, **skipped})
                continue
            overrides += [f"groom.file='{groom}'", f"head.file='{body}'"]
        scene = Scene.load(root / f"{name}.toml", overrides)
        without = Scene.load(root / f"{name}.toml", [*overrides, "links.enabled=false", "interactions.enabled=false"])
        fr = _frame_costs(scene, without, device, motion, frames, dynamics_repeats=repeats)
        # what finding the pairs once a frame misses over the same frames, in a run of its own (checking every step
        # would weigh on the timed one)
        sim = Simulation(scene, device=device)
        for _ in range(motion):
            sim.advance_frame()
        rows.append({"scene": name, "status": "ok", **fr, "per_dynamics": fr["per_step_s"] / fr["dynamics_s"],
                     "missed": missed_pairs(sim, frames)})
    return {"status": "ok", "device": str(device), "rows": rows}


def _active_contacts(contacts, model, state) -> int:
    """Stored contacts that repel now: their two points closer than the threshold and than their rest gap (host
    read, for the report)."""
    return int(np.count_nonzero(_repelling(contacts, model, state, contacts.contact_list())))


def _pair_keys(found: dict) -> np.ndarray:
    """One int64 per contact of ``found`` (``HairContacts.contact_list``) naming its pair of elements: its kind, side
    a and, for a vertex-face contact, the quad rather than its triangle (which of the two is the nearer is taken
    anew at every step)."""
    b = np.where(found["kind"] == 0, found["b"] // 2, found["b"]).astype(np.int64)
    return (found["kind"].astype(np.int64) << 62) | (found["a"].astype(np.int64) << 31) | b


def _repelling(contacts, model, state, found: dict) -> np.ndarray:
    """Which contacts of ``found`` repel at ``state``: their two points closer than the threshold and than their
    rest gap (float64 from the float32 positions, host read)."""
    x = state.vertex_positions.numpy().astype(np.float64)
    S = model.seg_per_strand
    tris = contacts.strips.indices.numpy().reshape(-1, 3) if contacts.strips is not None else np.zeros((1, 3), int)
    vf = found["kind"] == 0
    w = found["w"].astype(np.float64)
    xa = np.empty((len(w), 3))
    xb = np.empty((len(w), 3))
    xa[vf] = x[found["a"][vf]]
    xb[vf] = np.einsum("ni,nij->nj", w[vf], x[tris[found["b"][vf]]])
    a, b = found["a"][~vf], found["b"][~vf]
    va, vb = a + a // S, b + b // S
    xa[~vf] = x[va] + w[~vf, :1] * (x[va + 1] - x[va])
    xb[~vf] = x[vb] + w[~vf, 1:2] * (x[vb + 1] - x[vb])
    reach = np.minimum(contacts.threshold, found["gap"])
    return np.linalg.norm(xa - xb, axis=1) < reach


class MissedPairs:
    """What a list of hair contact pairs found ahead of the steps (``interactions.detect = "frame"``: once a frame,
    within ``threshold + margin``) misses: called on a state, it finds the pairs that repel there with a detection at
    that very state (a :class:`hairwarp.interactions.HairContacts` built as ``contacts`` but with no margin, its trees
    rebuilt) and returns ``(repelling, missed)``: how many there are, and how many of them the stored list of
    ``contacts`` lacks. A missed pair pushes nothing until a later detection finds it: in that time the two strands
    may pass into each other."""

    def __init__(self, contacts, model, executor=None):
        self.contacts, self.model = contacts, model
        self.probe = _contacts_like(contacts, model, 0.0, 2 * contacts.capacity, executor)

    def __call__(self, state) -> tuple[int, int]:
        probe = self.probe
        probe.detect(self.model, state, rebuild=True)
        if probe.overflowed():
            raise RuntimeError(f"MissedPairs: more than {probe.capacity} pairs within the threshold")
        found = probe.contact_list()
        want = _pair_keys(found)[_repelling(probe, self.model, state, found)]
        have = _pair_keys(self.contacts.contact_list())
        return len(want), int(np.count_nonzero(~np.isin(want, have)))


def _contacts_like(base, model, margin: float, capacity: int, executor):
    """A :class:`hairwarp.interactions.HairContacts` built as ``base`` (a scene's) but with ``margin`` (0: found in
    every step) and ``capacity``, on ``executor``'s threads."""
    from hairwarp.interactions import HairContacts

    contacts = HairContacts.build(
        model.rest_vertex_positions, base.strips, threshold=base.threshold, stiffness=base.stiffness,
        damping=base.damping, friction=base.friction, slip_velocity=base.slip_velocity, capacity=capacity,
        alignment_cutoff=base.alignment_cutoff, segment_segment=base.segment_segment, margin=float(margin),
        detect_each_step=margin <= 0.0, skip_neighbour_strips=base.skip_neighbour_strips, rest_gaps=base.rest_gaps,
        device=base.device)
    contacts.executor = executor
    return contacts


def missed_pairs(sim, frames: int) -> dict:
    """Run ``frames`` frames of ``sim`` (a :class:`hairwarp.Simulation` whose hair contacts are found once a frame),
    checking the stored pairs at the end of every step with :class:`MissedPairs`. Returns ``{"frames", "steps",
    "repelling_per_step", "missed_share", "worst_step_share"}`` (the share of all repelling pairs over the steps,
    and the largest at one step), or None where the scene finds its pairs at every step or has no hair contacts."""
    contacts = sim.contacts
    if contacts is None or contacts.detect_each_step:
        return None
    check, stepper = MissedPairs(contacts, sim.model, sim.solver.executor), sim.stepper
    counts = []
    step = stepper.step

    def checked_step():
        step()
        counts.append(check(stepper.state))

    stepper.step = checked_step  # the instance's step, which its frames call
    try:
        for _ in range(frames):
            sim.advance_frame()
    finally:
        del stepper.step
    counts = np.array(counts, dtype=np.int64).reshape(-1, 2)
    per_step = counts[:, 1] / np.maximum(counts[:, 0], 1)
    return {"frames": frames, "steps": len(counts), "repelling_per_step": float(counts[:, 0].mean()),
            "missed_share": float(counts[:, 1].sum() / max(counts[:, 0].sum(), 1)),
            "worst_step_share": float(per_step.max()) if len(per_step) else 0.0}


def render_comparison(scene_path, out_png, *, frame: int, view="three_quarter_back", overrides=(), device=None,
                      size_px=(1600, 800)) -> dict:
    """The same frame of a scene with its links and contacts and without them, side by side (dense hair if the scene
    has it, else the guides), with the head. Returns ``{"png", "frame", "time_s", "volume_m3": [with, without],
    "seconds": [with, without]}``, volume being that of the convex hull of the guide vertices."""
    from scipy.spatial import ConvexHull

    from hairwarp.preview import render_frames
    from hairwarp.runner import Simulation, _merged_world_mesh
    from hairwarp.scene import Scene

    panels, meshes, volumes, seconds = [], [], [], []
    for on in (True, False):
        flag = "true" if on else "false"
        scene = Scene.load(scene_path, [*overrides, f"links.enabled={flag}", f"interactions.enabled={flag}"])
        sim = Simulation(scene, device=device)
        t0 = time.perf_counter()
        for _ in range(frame):
            sim.advance_frame()
        seconds.append(time.perf_counter() - t0)
        points, _ = sim.guide_curves()
        volumes.append(float(ConvexHull(points).volume))
        if sim.dense is not None:
            state, control = sim.stepper.state, sim.stepper.control
            hair, _ = sim.dense.evaluate(state.vertex_positions, None, control.head_xform, control.head_velocity,
                                         hermite=True)
            panels.append({"hair": (hair.numpy(), sim.dense.curve_vertex_counts(True))})
        else:
            G, S = sim.model.strand_count, sim.model.seg_per_strand
            panels.append({"guides": (points, np.full(G, S + 1, np.int32))})
        meshes.append(_merged_world_mesh(sim.collider_meshes(frame * sim.frame_dt)))
    t = frame * sim.frame_dt
    titles = [f"links and contacts: hull {volumes[0] * 1e3:.2f} L", f"without: hull {volumes[1] * 1e3:.2f} L"]
    render_frames(panels, out_png, titles=[f"{s}   (t = {t:.2f} s)" for s in titles], meshes=meshes, view=view,
                  size_px=size_px)
    return {"png": str(out_png), "frame": frame, "time_s": t, "volume_m3": volumes, "seconds": seconds}


# Stiffnesses [N/m, a link between 1 cm segments, a contact at 1 cm of hair; the scene's segments are 2.9 cm] of the
# stability sweep (links or contacts alone), at h = 1/240 s: steps of about 1.5x up to 300, where both limits lie.
STABILITY_STIFFNESS = (1.0, 1.5, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0, 70.0, 100.0, 150.0, 200.0, 300.0,
                       1000.0, 3000.0, 10000.0, 30000.0)
# A joint spinning faster than this [rad/s] (80 % of the fault bound at h = 1/240 s) counts as blown up.
BLOW_UP_SPEED = 200.0


def _stability_scene(kind: str, stiffness: float, quick: bool, overrides=()):
    from hairwarp.scene import Scene

    # no frame taken again, for a whip or a fault: taken in finer steps, the springs' growth at the step would not
    # show (links of 10-50 N/m faulted every frame at 8 substeps, each taken again in 16 steps, and were counted held)
    base = [f"groom.count={60 if quick else 150}", "sim.segments=12", "sim.substeps=8", "dense.count=0",
            "head.motion.kind=turn", "head.motion.amplitude_deg=60", "head.motion.period=0.8",
            "head.motion.start=0.0", "head.motion.ramp=0.1", "sim.whip_ratio=0", "sim.fault_retries=0", *overrides]
    # the one kind alone: the default scene ships both (with the other kind's on, the links' sweep ran beside its
    # contacts of 7 N/m, and the contacts' frames with a link broken were taken again at the links' break step)
    if kind == "links":
        base += ["links.enabled=true", f"links.stiffness={stiffness}", "links.damping=0.002", "links.radius=0.02",
                 "links.break_length=1.0", "interactions.enabled=false"]
    elif kind == "contacts":
        base += ["interactions.enabled=true", f"interactions.stiffness={stiffness}", "interactions.damping=0.002",
                 "interactions.threshold=0.003", "interactions.detect='step'", "interactions.capacity=200000",
                 "links.enabled=false"]
    else:
        raise ValueError(f"kind must be 'links' or 'contacts', got {kind!r}")
    return Scene.load(Scene.default_path(), base)


def run_until_fault(kind: str, stiffness: float, *, implicit: bool, quick: bool = False, device=None,
                    overrides=()) -> float | None:
    """Run a head turn (60 degrees, 0.8 s period; 60 guides of 12 segments, ``quick``, else 150) with only links or
    only contacts (``kind``) of ``stiffness`` [N/m] at h = 1/240 s, implicit as shipped (the links' per-link
    backward Euler, the contacts' response inside the step) or explicit (``implicit`` False); return the
    time [s] at which it blew up (a fault, a non-finite state or a joint faster than ``BLOW_UP_SPEED``), or None if it
    ran ``0.5 s`` (``quick``) or 1.5 s stably, every frame at that step (none taken again in finer steps).
    ``overrides``: more scene ``key=value`` strings."""
    from hairwarp.runner import Simulation
    from hairwarp.solver import SimulationFault

    if not implicit:
        overrides = [*overrides, 'interactions.response="mass"', 'links.response="link"']
    sim = Simulation(_stability_scene(kind, stiffness, quick, overrides), device=device)
    for part in (sim.links, sim.contacts):
        if part is not None:
            part.implicit_springs = bool(implicit)
    for frame in range(1, (15 if quick else 45) + 1):
        try:
            sim.advance_frame()
        except SimulationFault:
            return frame * sim.frame_dt
        qd = sim.state.joint_qd.numpy()
        if not np.all(np.isfinite(qd)) or np.abs(qd).max() > BLOW_UP_SPEED:
            return frame * sim.frame_dt
    return None


def bench_spring_stability(quick: bool = False, device=None, stiffness=STABILITY_STIFFNESS) -> dict:
    """The largest stable link and contact stiffness at h = 1/240 s, implicit as shipped and explicit.

    Returns ``{"dt", "rows": [{"kind", "implicit", "stiffness": [...], "blow_up_s": [... or None],
    "largest_stable"}]}``; a sweep stops at its first blow-up.
    """
    rows = []
    for kind in ("links", "contacts"):
        for implicit in (True, False):
            tried, blown = [], []
            for k in stiffness:
                t = run_until_fault(kind, k, implicit=implicit, quick=quick, device=device)
                tried.append(float(k))
                blown.append(t)
                if t is not None:
                    break
            stable = [k for k, t in zip(tried, blown, strict=True) if t is None]
            rows.append({"kind": kind, "implicit": implicit, "stiffness": tried, "blow_up_s": blown,
                         "largest_stable": max(stable) if stable else None})
    return {"dt": 1.0 / 240.0, "rows": rows}


# Goal of the interactions: links, refit, detection and contact forces together per step, against the dynamics step.
GOAL_PER_DYNAMICS = 2.0
# The Ratboy mohawk scene's own guide count (``scenes/ratboy_mohawk.toml``: every 5th of 2,219 guides).
SCENE_MAX_STRANDS = 450


def _goal_row(cost: dict, margin: float) -> dict | None:
    """The goal's figures of one guide count: the stages' sum at ``margin`` and, where measured, the whole frames'
    difference (what a run pays: ``_frame_costs``), the larger of the two against the goal."""
    if cost.get("status") != "ok":
        return None
    for row in cost["margins"]:
        if abs(row["margin"] - margin) < 1e-12:
            frames = cost.get("frames")
            per_step = max(row["per_step_s"], frames["per_step_s"]) if frames else row["per_step_s"]
            per_dynamics = per_step / cost["dynamics_s"]
            return {"strands": cost["strands"], "margin": margin, "per_step_s": per_step,
                    "stages_per_dynamics": row["per_dynamics"],
                    "frames_per_dynamics": frames["per_step_s"] / cost["dynamics_s"] if frames else None,
                    "dynamics_s": cost["dynamics_s"], "per_dynamics": per_dynamics,
                    "meets": per_dynamics <= GOAL_PER_DYNAMICS}
    return None


def suite_interactions(config, out, log=lambda message: None) -> dict:
    """The ``interactions`` suite of ``hairwarp bench``: the cost of each interaction stage per step next to the
    dynamics on the Ratboy mohawk, every guide (2,219) and the scene's own 444, in one run; the largest stable link
    and contact stiffness, implicit as shipped and explicit; and (full runs) the picture of one frame with and
    without interactions (``interactions.png`` in ``out``). ``config``: a
    :class:`hairwarp.benchmarks.common.BenchConfig`."""
    from hairwarp.interactions import REBUILD_FRAMES
    from hairwarp.scene import Scene

    quick, device = bool(config.quick), config.device
    margin = float(Scene.load(Scene.default_path()).interactions.margin)
    costs = {}
    for label, strands in (("all_guides", 0), ("scene_guides", SCENE_MAX_STRANDS)):
        if quick and strands == 0:
            continue
        log(f"interactions: cost per step, Ratboy mohawk, groom.max_strands={strands}")
        # what each margin misses, on the scene's own guides (every guide: a minute a margin more)
        costs[label] = bench_interactions(quick=quick, device=device, margins=(0.0, margin) if quick else MARGINS,
                                          overrides=(f"groom.max_strands={strands}",),
                                          missed_frames=(REBUILD_FRAMES if quick else 2 * REBUILD_FRAMES)
                                          if strands else 0)
    log("interactions: largest stable stiffness at 1/240 s")
    stability = bench_spring_stability(quick=quick, device=device,
                                       stiffness=STABILITY_STIFFNESS[:12:3] if quick else STABILITY_STIFFNESS)
    picture = None
    if not quick:
        log("interactions: with and without, side by side")
        scene_path = Path(Scene.default_path()).parent / "fast_turn.toml"
        # t = 2 s: the head turned 90 degrees in 0.4 s and back, and has been still for 1 s
        picture = render_comparison(scene_path, Path(out) / "interactions.png", frame=60, device=device)
    log("interactions: each shipped scene with and without its links and contacts")
    scenes = bench_scene_interactions(quick=quick, device=device)
    for row in scenes["rows"]:
        if row.get("status") == "ok":
            row["meets"] = row["per_dynamics"] <= GOAL_PER_DYNAMICS
    goal = {label: _goal_row(cost, margin) for label, cost in costs.items()}
    data = {"goal_per_dynamics": GOAL_PER_DYNAMICS, "scene_margin": margin, "cost": costs, "goal": goal,
            "scenes": scenes, "stability": stability, "picture": picture}
    data["detection_chart"] = chart_detection(data, Path(out) / "bench_detection.png")
    data["files"] = [f for f in (picture["png"] if picture else None, data["detection_chart"]) if f]
    return data


def _missed_frames(data: dict) -> str:
    """The frames over which the margins' misses were counted, in words."""
    frames = {row["missed"].get("frames") for cost in data.get("cost", {}).values() if cost.get("status") == "ok"
              for row in cost["margins"] if row.get("missed")}
    return f"{frames.pop()}" if len(frames) == 1 and None not in frames else "the measured"


def _missed_words(row: dict) -> str:
    """A margin row's misses for the table: share over the steps (worst step), none at a detection a step, a dash
    where not measured."""
    if row.get("detect") == "step":
        return "0 (every step)"
    m = row.get("missed")
    return f"{m['missed_share'] * 100:.2g} % ({m['worst_step_share'] * 100:.2g} %)" if m else "–"


def chart_detection(data: dict, path) -> str | None:
    """The detection margins' cost per step (x the dynamics step) against the share of repelling pairs their lists
    miss, one point a margin (a detection in every step at 0), for the cost rows that measured their misses."""
    from hairwarp.benchmarks.report import _pyplot

    costs = [c for c in data.get("cost", {}).values() if c.get("status") == "ok"
             and any(r.get("missed") for r in c["margins"])]
    if not costs:
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for cost in costs:
        xs, ys, labels = [], [], []
        for row in cost["margins"]:
            if row.get("detect") == "step" or row.get("missed"):
                xs.append(0.0 if row.get("detect") == "step" else 100.0 * row["missed"]["missed_share"])
                ys.append(row["per_dynamics"])
                labels.append("every step" if row.get("detect") == "step" else f"{row['margin'] * 1e3:g} mm")
        order = sorted(range(len(xs)), key=lambda i: xs[i])  # from a detection every step to the widest miss
        xs, ys, labels = [xs[i] for i in order], [ys[i] for i in order], [labels[i] for i in order]
        ax.plot(xs, ys, "o-", label=f"Ratboy mohawk, {cost['strands']} guides")
        for x, y, text in zip(xs, ys, labels, strict=True):
            ax.annotate(text, (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.axhline(data.get("goal_per_dynamics", GOAL_PER_DYNAMICS), color="0.4", ls="--", lw=1, label="goal")
    ax.set_xlabel("repelling pairs missed by the stored list [% over the steps]")
    ax.set_ylabel("interactions per step [x the dynamics step]")
    ax.set_title("Detection margin: cost against what it misses")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return str(path)


def md_interactions(data: dict) -> list[str]:
    """The report section of the ``interactions`` suite."""
    lines = ["## Interactions (`hairwarp bench interactions`)", ""]
    if data.get("picture"):
        p = data["picture"]
        lines += [f"![with and without interactions]({Path(p['png']).name})", "",
                  f"`scenes/fast_turn.toml` at t = {p['time_s']:.2f} s; convex hull of the guides "
                  f"{p['volume_m3'][0] * 1e3:.2f} L with links and contacts, {p['volume_m3'][1] * 1e3:.2f} L "
                  "without.", ""]
    first = next((c for c in data.get("cost", {}).values() if c.get("status") == "ok"), {})
    lines += [f"Cost per step on the Ratboy mohawk scene in motion ({first.get('segments')} segments, "
              f"{first.get('substeps')} substeps; detection once per frame within the margin, margin 0: detection in "
              "every step), each stage timed on the same state, interleaved, medians, on the simulation's threads; "
              "`per step` = links + contact forces + response + detection / substeps. `detection`: as the runner "
              "pays it (`HairContacts.detect`: bounds, both trees fitted, both kinds of contact at once on the "
              "threads; on the CPU the trees rebuilt every 8th frame and refit between), its parts alone beside it "
              "(`refit`, the trees' fit so averaged; `vertex-face`, `segment-segment`); `response`: the scene's solve "
              "of its links (and contacts) after the free step (its `response = \"step\"`: one sweep a step), the "
              "free steps of a frame with it less without it, the frame's first step making the factors its later "
              "ones solve with, as a run does.", "",
              "*missed* (where measured): the pairs that repel at the end of a step (a detection at that state: "
              "closer than the threshold and their rest gap) that the frame's stored list lacks, over the steps of "
              f"{_missed_frames(data)} frames of the scene run again with that margin as far into its motion, and at "
              "its worst step; a detection in every step (margin 0) misses none. The chart below draws the two "
              "against each other.", "",
              "| guides | margin | stored / active pairs | links ms | response ms | detection ms (refit, vertex-face, "
              "segment-segment) | forces ms | per step ms | dynamics ms | × dynamics | missed (worst step) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for cost in data.get("cost", {}).values():
        if cost.get("status") != "ok":
            lines.append(f"| – | – | {cost.get('message', cost.get('status'))} | | | | | | | | |")
            continue
        for row in cost["margins"]:
            lines.append(
                f"| {cost['strands']} | {row['margin'] * 1e3:g} mm | {row['stored']} / {row['active']} | "
                f"{cost['links_s'] * 1e3:.2f} | {cost.get('response_s', 0.0) * 1e3:.2f} | "
                f"{row['detect_s'] * 1e3:.2f} ({row['refit_s'] * 1e3:.2f}, {row['vertex_face_s'] * 1e3:.2f}, "
                f"{row['segment_segment_s'] * 1e3:.2f}) | {row['forces_s'] * 1e3:.2f} | "
                f"{row['per_step_s'] * 1e3:.2f} | {cost['dynamics_s'] * 1e3:.2f} | {row['per_dynamics']:.2f} | "
                f"{_missed_words(row)} |")
    if data.get("detection_chart"):
        lines += ["", f"![cost against missed pairs]({Path(data['detection_chart']).name})"]
    lines += ["", "Whole frames (the check on the stages' sum): the scene run with its links and contacts and without "
              "them, each from its start into the motion, the same frames in turn, mean wall time a frame; their "
              "difference over the substeps is what the interactions add a step as a run pays it, with what the "
              "stages timed alone leave out (the interactions' host work between launches, their arrays evicted from "
              "the caches by the rest of the step).", "",
              "| guides | frames | with ms | without ms | interactions per step ms | × dynamics |",
              "|---|---|---|---|---|---|"]
    for cost in data.get("cost", {}).values():
        fr = cost.get("frames") if cost.get("status") == "ok" else None
        if fr:
            lines.append(f"| {cost['strands']} | {fr['frames']} | {fr['with_s'] * 1e3:.1f} | "
                         f"{fr['without_s'] * 1e3:.1f} | {fr['per_step_s'] * 1e3:.2f} | "
                         f"{fr['per_step_s'] / cost['dynamics_s']:.2f} |")
    lines.append("")
    for g in data.get("goal", {}).values():
        if g is None:
            continue
        frames = f", whole frames {g['frames_per_dynamics']:.2f}×" if g.get("frames_per_dynamics") is not None else ""
        lines.append(f"- Goal (all interactions ≤ {data['goal_per_dynamics']:g}× the dynamics, the larger of the two "
                     f"figures), {g['strands']} guides, margin {g['margin'] * 1e3:g} mm: stages "
                     f"{g['stages_per_dynamics']:.2f}×{frames} — {'**meets**' if g['meets'] else '**does not meet**'}.")
    scenes = data.get("scenes", {}).get("rows", [])
    if scenes:
        lines += ["", "Each shipped scene with links or hair contacts, as it ships, run with them and without them "
                  "(`links.enabled`, `interactions.enabled` off) as above, against its own dynamics step: the goal at "
                  "each scene's density, forms and settings (`response`: what it solves after the free step at its "
                  "step; `stored`: the hair contacts' pairs at the last frame timed). What finding the pairs once a "
                  "frame costs in accuracy, over the same frames of another run of the scene: at the end of every "
                  "step a detection at that state finds the pairs that repel there (closer than the threshold and "
                  "their rest gap); *missed*: the share of them that the frame's stored list lacks, over all steps "
                  "and at the worst step. A missed pair pushes nothing until the next frame's detection finds it, "
                  "while its strands may pass into each other (`interactions.detect = \"step\"` misses none, at a "
                  "detection a step: the margin 0 rows above).", "",
                  "| scene | guides × segments | substeps | links | contacts | response | with ms | without ms "
                  "| interactions per step ms | dynamics ms | × dynamics | goal | repelling a step "
                  "| missed (worst step) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in scenes:
            if r.get("status") != "ok":
                lines.append(f"| {r['scene']} | {r.get('message', r.get('status'))} | | | | | | | | | | | | |")
                continue
            m = r.get("missed")
            missed = (f"{m['repelling_per_step']:.0f} | {m['missed_share'] * 100:.2g} % "
                      f"({m['worst_step_share'] * 100:.2g} %)") if m else "– | –"
            lines.append(f"| {r['scene']} | {r['strands']} × {r['segments']} | {r['substeps']} | {r['links']} | "
                         f"{r.get('stored', 0) if r['contacts'] else 'off'} | {', '.join(r['response']) or '–'} | "
                         f"{r['with_s'] * 1e3:.1f} | {r['without_s'] * 1e3:.1f} | {r['per_step_s'] * 1e3:.2f} | "
                         f"{r['dynamics_s'] * 1e3:.2f} | {r['per_dynamics']:.2f} | {'✓' if r['meets'] else '✗'} | "
                         f"{missed} |")
    st = data.get("stability")
    if st:
        lines += ["", f"Largest stable stiffness at h = {st['dt']:.4g} s (a head turn with links alone or contacts "
                      "alone, every frame at that step: none taken again in finer steps; a sweep stops at its first "
                      "blow-up):", "",
                  "| springs | implicit (as shipped) | largest stable [N/m] | first blow-up |", "|---|---|---|---|"]
        for r in st["rows"]:
            blown = [(k, t) for k, t in zip(r["stiffness"], r["blow_up_s"], strict=True) if t is not None]
            first = f"{blown[0][0]:g} N/m at {blown[0][1]:.2f} s" if blown else "none in the sweep"
            lines.append(f"| {r['kind']} | {'yes' if r['implicit'] else 'no'} | {r['largest_stable']} | {first} |")
    return lines
