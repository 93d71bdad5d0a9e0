"""Faults name the stage that drives them, with advice that runs: each test provokes one on a small scene, checks the
stage and the advice, and runs the advice. The hair speed check is compared with the velocities read back, and the
speed it takes as explained with finite differences of the head's poses."""

import math
from pathlib import Path

import numpy as np
import pytest

import hairwarp as hw
from hairwarp.motion import quat_to_matrix
from hairwarp.runner import Simulation
from hairwarp.solver import SimulationFault

SCENES = Path(__file__).resolve().parents[1] / "scenes"
TINY = SCENES / "tiny.toml"
LONG_HAIR = SCENES / "long_hair.toml"


def _run(path, overrides, frames):
    """Advance a scene ``frames`` frames; the fault it raised, or None when it ran to the end."""
    sim = Simulation(hw.Scene.load(path, ["output.preview=false", "sim.fault_retries=0", *overrides]))
    try:
        for _ in range(frames):
            sim.advance_frame()
    except SimulationFault as fault:
        return fault
    return None


def _advice(fault) -> str:
    return str(fault).split("To fix:", 1)[1]


def test_strand_constants_hold_at_their_bound():
    """The strands' stiffnesses and damping run at the top of their range without a fault or a frame taken again
    (EI 1e24 made the joint state non-finite in the first frame, which the fault then blamed on the step), and a
    value past it is refused at load, naming the key."""
    from hairwarp.scene import STRAND_CONSTANT_RANGE, SceneError

    top = STRAND_CONSTANT_RANGE.strip("[]").split(",")[1].strip()
    keys = ("strands.bend_stiffness", "strands.twist_stiffness", "strands.damping")
    assert _run(TINY, [f"{key}={top}" for key in keys], 6) is None
    for key in keys:
        with pytest.raises(SceneError, match=f"{key}: must be in"):
            hw.Scene.load(TINY, [f"{key}={10.0 * float(top)}"])


def test_hair_speed_check_matches_the_velocities_read_back():
    """The per-strand speeds the check writes are the norms of the vertex velocities (a non-finite one reads inf),
    and the fault bit is set exactly when one exceeds the bound."""
    sim = Simulation(hw.Scene.load(TINY, ["output.preview=false"]))
    sim.advance_frame()
    solver, state = sim.solver, sim.stepper.state
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    bound = solver.speed_bound()
    rng = np.random.default_rng(3)
    v = rng.normal(0.0, 0.2 * bound, (G, S + 1, 3))
    v[2, 5] = [0.0, 0.0, 1.5 * bound]  # one vertex past the bound
    v[4, 1] = [np.nan, 0.0, 0.0]
    state.vertex_velocities.assign(v.reshape(-1, 3).astype(np.float32))
    with pytest.raises(SimulationFault) as info:
        solver.check(state, 2)
    expected = np.linalg.norm(v.astype(np.float32), axis=2).max(axis=1)
    expected[4] = np.inf
    # the kernel's float32 norm against numpy's of the same float32 vectors: a few ulps apart
    np.testing.assert_allclose(solver.strand_speed.numpy(), expected, rtol=1e-6)
    assert info.value.bits & hw.Fault.HAIR_SPEED and "sim.speed_margin" in str(info.value)
    # below the bound: no fault
    state.fault.zero_()
    state.vertex_velocities.assign(np.full((G * (S + 1), 3), 0.1 * bound, dtype=np.float32))
    assert solver.check(state, 3) == hw.Fault.NONE


def test_carried_speed_bounds_the_head_motion_by_finite_differences():
    """``Control.carried_speed`` is at least the fastest a point of the hair at rest moves with the head, taken by
    central differences of the motion's poses, and not much more (it bounds the hair by a ball). Teleports off, so
    every step's head sample is the motion's own (a teleport hands the control a still head)."""
    sim = Simulation(hw.Scene.load(TINY, ["output.preview=false", "head.teleport_distance=inf"]))
    rest = sim.model.rest_vertex_positions.reshape(-1, 3)
    motion, h = sim.motion, 1e-5
    fastest = 0.0
    for _ in range(6):
        sim.advance_frame()
    for t in np.arange(1, 6 * 8 + 1) * sim.scene.step_dt:
        ends = []
        for s in (t - h, t + h):
            position, rotation = motion.pose(s)
            ends.append(rest @ quat_to_matrix(np.asarray(rotation)).T + np.asarray(position))
        fastest = max(fastest, float(np.linalg.norm(ends[1] - ends[0], axis=1).max() / (2 * h)))
    carried = sim.stepper.control.carried_speed
    # 1e-3: central differences at h = 1e-5 s of a float64 pose are good to far better than that, while the
    # control's head pose and velocity are float32 (about 1e-7 relative)
    assert fastest > 0.1 and fastest * (1 - 1e-3) <= carried <= 2.0 * fastest


def test_light_strands_name_the_air_drag_and_drag_zero_runs():
    """Strands of 1e-3 kg/m^3 whip at tens of m/s that stay finite (exit 0 before): the speed check stops them,
    names the air drag, and says more substeps do not help (measured: 32 and 128 fault earlier); drag 0 runs. With
    no head under them: on the head its friction holds them back (6-9 m/s over 10 frames, under the bound, since a
    contact held again takes its friction from the last one)."""
    light = ["strands.density=1e-3", 'head.shape="none"']
    fault = _run(TINY, light, 10)
    assert fault is not None and fault.stage.startswith("air drag") and fault.bits & hw.Fault.HAIR_SPEED
    assert "strands.drag = 0" in _advice(fault) and "neither more substeps" in _advice(fault)
    assert _run(TINY, [*light, "sim.substeps=32"], 10) is not None
    assert _run(TINY, [*light, "strands.drag=0"], 10) is None


@pytest.mark.parametrize("integrator", ["implicit_joints", "semi_implicit"])
def test_undamped_free_twist_asks_for_damping_not_substeps(integrator):
    """No damping and no twist stiffness: the twist whips at any step (16 substeps, and 704 under semi_implicit,
    faulted before), so the advice is damping, and implicit_joints for an explicit integrator; both run."""
    base = ["strands.damping=0", "strands.twist_stiffness=0", f'sim.integrator="{integrator}"']
    fault = _run(TINY, [*base, "sim.substeps=16"], 10)
    assert fault is not None and fault.stage == "dynamics (aba + integrate)"
    advice = _advice(fault)
    assert "strands.damping" in advice and "sim.substeps =" not in advice
    assert ('"implicit_joints"' in advice) == (integrator == "semi_implicit")
    fixed = ["strands.damping=2e-7", "strands.twist_stiffness=0", 'sim.integrator="implicit_joints"']
    assert _run(TINY, [*fixed, "sim.substeps=16"], 10) is None


def _free_step_fault_and_its_advice(path, scene, key: str, stiffness: str, stage: str):
    """Springs of ``key`` (links / interactions) too stiff for the free step fault naming ``stage``; each way out the
    advice gives runs: their response after the free step, the stiffness it computes, turning them off."""
    fault = _run(path, [*scene, f"{key}.stiffness={stiffness}"], 6)
    assert fault is not None and fault.stage.startswith(stage), fault
    advice = _advice(fault)
    assert "more substeps do not help" in advice and f"{key}.enabled = false" in advice
    assert f'{key}.response = "step"' in advice
    computed = float(advice.split(f"{key}.stiffness <= ")[1].split()[0])
    assert _run(path, [*scene, f"{key}.stiffness={stiffness}", f'{key}.response="step"'], 6) is None
    assert _run(path, [*scene, f"{key}.stiffness={computed}"], 6) is None
    assert _run(path, [*scene, f"{key}.stiffness={stiffness}", f"{key}.enabled=false"], 6) is None


def test_stiff_links_in_the_free_step_name_the_links_and_their_response_runs():
    """Links of 1,000 N/m taken in the free step (8 substeps, ``links.response = "link"``: ``"auto"`` would solve
    links this stiff after it) blow up; the fault names the links."""
    _free_step_fault_and_its_advice(LONG_HAIR, ["groom.count=60", "dense.count=0", "interactions.enabled=false",
                                                'links.response="link"'], "links", "1000", "static links")


@pytest.mark.parametrize("substeps", [8, 4])
def test_stiff_hair_contacts_in_the_free_step_name_the_contacts(substeps):
    """Contacts of 1e5 N/m in the free step (the mass form, ``interactions.response = "mass"``, at 8 and 4 substeps:
    ``"auto"`` solves contacts this stiff after it) were blamed on the dynamics with "raise substeps"; the fault names
    the contacts."""
    _free_step_fault_and_its_advice(TINY, ["interactions.enabled=true", f"sim.substeps={substeps}",
                                           'interactions.response="mass"'], "interactions", "1e5", "hair contacts")


def test_a_threshold_far_past_a_wisp_names_the_hair_contacts_and_the_threshold():
    """A threshold of 0.5 m finds hundreds of pairs a guide vertex, far past the slots, and blows up within ten
    frames at any step (the 7th here; the 2nd before the vertex-face push faded in from the strands' lines); the fault
    was blamed on the dynamics with "raise sim.substeps". It names the hair contacts and the threshold, and the run
    with a wisp's threshold finishes. A run grows slots too few for a wisp's threshold
    (``tests/test_interaction_scenes.py``); where they are not grown, their overflow is put down to the capacity
    alone."""

    small = ["groom.count=60", "dense.count=0"]
    fault = _run(LONG_HAIR, [*small, "interactions.threshold=0.5"], 10)
    assert fault is not None and fault.stage == "hair contacts (more pairs than slots)", fault
    assert "lower interactions.threshold (now 0.5 m" in _advice(fault)
    assert _run(LONG_HAIR, [*small, "interactions.threshold=0.003"], 4) is None
    sim = Simulation(hw.Scene.load(LONG_HAIR, [*small, "output.preview=false", "interactions.capacity=4"]))
    sim.contacts.grows = False
    assert sim.advance_frame() & hw.Fault.CONTACT_OVERFLOW
    assert sim.contacts.overflow_advice().endswith(" slots and the rest dropped; raise interactions.capacity")


def test_auto_solves_hair_contacts_too_stiff_for_the_free_step_after_it(tmp_path):
    """At the shipped 8 substeps ``interactions.response = "auto"`` keeps contacts in the free step up to the rate
    ``runner.CONTACT_STEP_RATE`` and solves stiffer ones after it: contacts of 1e5 N/m, which fault in the free step
    (above), run, and the run's notes say why and which stiffness would keep them in the free step; ``tiny``'s own
    stay there, with no note."""
    from hairwarp.runner import CONTACT_STEP_RATE

    over = ["output.preview=false", "interactions.enabled=true", "sim.substeps=8"]
    sim = Simulation(hw.Scene.load(TINY, over))
    assert not sim.contacts.response and sim.stiff_contacts_note is None
    assert _run(TINY, [*over, "interactions.stiffness=1e5"], 6) is None
    sim = Simulation(hw.Scene.load(TINY, [*over, "interactions.stiffness=1e5"]))
    note = sim.stiff_contacts_note
    assert sim.contacts.response and note.startswith('interactions.response = "auto" solved the hair contacts after')
    softer = float(note.split("interactions.stiffness <= ")[1].split()[0])
    sim = Simulation(hw.Scene.load(TINY, [*over, f"interactions.stiffness={0.99 * softer}"]))  # printed to 3 digits
    assert not sim.contacts.response, CONTACT_STEP_RATE
    result = hw.simulate(hw.Scene.load(TINY, [*over, "interactions.stiffness=1e5", "sim.frames=2"]),
                         tmp_path / "stiff.usdc", preview=False, progress=False)
    assert any("solved the hair contacts after the free step" in n for n in result.notes)


def test_body_contact_fault_on_a_still_head_names_the_wind():
    """A still head in a 500 m/s wind at one step a frame faulted as "a collider moved or jumped too far": the head's
    own speed is known, so the fault names the wind; more substeps run."""
    still = ['head.motion.kind="still"', "wind.velocity=[500.0, 0.0, 0.0]", "sim.substeps=1"]
    fault = _run(TINY, still, 6)
    assert fault is not None and fault.stage == "air drag (wind.velocity)", fault
    assert "moved at most 0 m/s" in str(fault) and "wind.velocity" in _advice(fault)
    assert _run(TINY, [*still, "sim.substeps=16"], 6) is None


WINDY = ['head.motion.kind="still"', "wind.velocity=[700.0, 0.0, 0.0]", "sim.substeps=2", "output.preview=false"]


def test_a_frame_that_faults_is_taken_again_in_twice_the_steps():
    """A still head in a 700 m/s wind faults at 2 substeps (the case above); with ``sim.fault_retries`` (2 by default)
    each such frame is taken again from its start in 4 steps and the run goes on. The frame taken again is, to the
    bit, the frame a run of 4 substeps takes from the same start; its note names the frames and the stage."""
    retried = Simulation(hw.Scene.load(TINY, WINDY))
    finer = Simulation(hw.Scene.load(TINY, [*WINDY, "sim.substeps=4", "sim.fault_retries=0"]))
    retried.advance_frame()
    finer.advance_frame()
    assert retried.retaken_frames == 1 and retried.retakes == [(1, 4, "air drag (wind.velocity)")]
    for name in ("joint_q", "joint_qd", "vertex_positions", "vertex_velocities"):
        np.testing.assert_array_equal(getattr(retried.state, name).numpy(), getattr(finer.state, name).numpy(),
                                      err_msg=name)
    for _ in range(5):
        retried.advance_frame()
    assert retried.retaken_frames >= 3 and retried.stepper.frame == 6
    from hairwarp.runner import _retakes_note

    note = _retakes_note(retried)
    assert note.startswith(f"{retried.retaken_frames} frames faulted at 2 substeps")
    assert "frame 1 in 4 steps (air drag" in note and "raise sim.substeps" in note


def test_a_run_shows_and_notes_the_frames_taken_again(tmp_path, capsys):
    """Through ``hw.simulate``, the frames taken again show in the progress line as they come (``retaken``) and in
    the run's notes at its end, and the cache holds every frame."""
    from pxr import Usd

    result = hw.simulate(hw.Scene.load(TINY, WINDY), tmp_path / "windy.usdc", preview=False)
    import re

    err = capsys.readouterr().err
    note = [n for n in result.notes if " taken again in more steps" in n]
    assert len(note) == 1, result.notes
    count = int(re.match(r"(\d+) frames? faulted at 2 substeps", note[0]).group(1))
    assert 1 <= count <= 10
    progress = [line for line in err.splitlines() if line.startswith("frame 10/10")]
    assert progress and f"retaken {count}" in progress[-1], err
    stage = Usd.Stage.Open(str(tmp_path / "windy.usdc"))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == 10


def test_a_frame_that_faults_at_every_retry_stops_the_run_naming_them():
    """Links of 1,000 N/m in the free step fault at 8 substeps and at 16 and 32 as well: the run stops with the fault
    of the last, which says the frame was taken again in 16 and 32 steps."""
    overrides = ["groom.count=60", "dense.count=0", "interactions.enabled=false", "links.stiffness=1000",
                 'links.response="link"']
    sim = Simulation(hw.Scene.load(LONG_HAIR, ["output.preview=false", *overrides]))
    with pytest.raises(SimulationFault) as info:
        for _ in range(6):
            sim.advance_frame()
    fault = info.value
    assert fault.stage == "static links (forces in the free step)", fault
    assert "taken again in 16 and 32 steps (sim.fault_retries = 2), and faulted each time" in str(fault)
    assert sim.retakes == [(fault.frame, 16, fault.stage), (fault.frame, 32, fault.stage)]


def test_a_free_step_fault_a_strong_wind_drives_names_the_wind():
    """A still head in a 3000 m/s wind: its drag changes a vertex's velocity by 23 m/s in a step of 8 substeps, where
    a step resolves 4.9 m/s, and the free step goes non-finite in the first frame. The fault names the wind and
    advises a lower wind or more substeps, not the dynamics' more drag, which would blow the hair harder; with a
    tenth of the wind the scene runs."""
    still = ['head.motion.kind="still"', "wind.velocity=[3000.0, 0.0, 0.0]"]
    fault = _run(TINY, still, 3)
    assert fault is not None and fault.stage == "air drag (wind.velocity)", fault
    # the kick by hand: drag per metre over the mass per metre of a keratin cylinder, times the step and the wind
    scene = hw.Scene.load(TINY)
    s = scene.strands
    kick = s.drag / (s.density * math.pi * s.radius ** 2) / (scene.sim.fps * scene.sim.substeps) * 3000.0
    assert f"{kick:.3g} m/s a step" in str(fault)
    assert "wind.velocity" in _advice(fault) and "strands.drag" not in _advice(fault)
    assert _run(TINY, ['head.motion.kind="still"', "wind.velocity=[300.0, 0.0, 0.0]"], 3) is None


def test_a_bound_set_below_its_default_is_named():
    fault = _run(TINY, ["sim.max_rotation_per_step=0.01", "sim.substeps=32"], 4)
    assert fault is not None and "sim.max_rotation_per_step (now 0.01" in _advice(fault)
    assert _run(TINY, ["sim.substeps=32"], 4) is None


def test_frames_kept_before_a_speed_fault_are_those_of_the_run_and_resume_finishes(tmp_path):
    """The frames written before a speed fault hold the velocities the same run had at those frames, all within
    the bound, and the fault frame is the first whose velocities (read back) exceed it; a resume with the advice
    (no drag) finishes from the last kept frame. (``sim.whip_ratio = 0``: no frame is taken again for its speed, so
    the run unchecked takes the same steps. Strands of 1e-2 kg/m^3: faulted at frame 5, 4 frames kept.)"""
    from pxr import Usd, UsdGeom

    from hairwarp.runner import simulate

    light = ["output.preview=false", "strands.density=1e-2", "sim.whip_ratio=0"]
    out = tmp_path / "tiny.usdc"
    with pytest.raises(SimulationFault) as info:
        simulate(hw.Scene.load(TINY, light), out, frames=10, progress=False)
    frame = info.value.frame
    # the same run unchecked: the fastest vertex and the bound of every frame
    sim = Simulation(hw.Scene.load(TINY, [*light, "sim.speed_margin=inf"]))
    speeds, bounds = [], []
    for _ in range(frame):
        sim.advance_frame()
        speeds.append(np.linalg.norm(sim.stepper.state.vertex_velocities.numpy(), axis=1).max())
        bounds.append(hw.Scene.load(TINY).sim.speed_margin * sum(sim.solver.speed_terms().values()))
    assert speeds[-1] > bounds[-1] and all(s <= b for s, b in zip(speeds[:-1], bounds[:-1]))
    stage = Usd.Stage.Open(str(tmp_path / "tiny.partial" / "tiny.usdc"))
    guides = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    kept = [np.linalg.norm(np.asarray(guides.GetVelocitiesAttr().Get(f)), axis=1).max() for f in range(1, frame)]
    # the cache holds float32 velocities, the same the run had; 1e-5 covers the norm taken in another order
    np.testing.assert_allclose(kept, speeds[:-1], rtol=1e-5)
    simulate(hw.Scene.load(TINY, [*light, "strands.drag=0"]), out, frames=10, progress=False, resume=True)
    assert Usd.Stage.Open(str(out)).GetEndTimeCode() == 10.0


def test_response_fault_advises_the_stiff_part_only():
    """Links of 1e6 N/m solved after the free step (2 substeps) fault in the response in the first frame: the stage
    named is the response, the advice is the links' (the contacts keep their shipped 20 N/m), and solving the links
    in the free step, which it offers, runs. (At 1e5 N/m the hair whipped to 4.5 m/s and faulted at frame 6 while
    the body contact's dampers were 100 times the strand's mass; at 10 times it runs, at 0.94 m/s at most.)"""
    scene = ["groom.count=60", "dense.count=0", "sim.substeps=2", "links.stiffness=1e6"]
    fault = _run(LONG_HAIR, scene, 8)
    assert fault is not None and fault.stage == "links and hair contacts (response)", fault
    assert fault.bits & (hw.Fault.INTERACTION_RESPONSE | hw.Fault.HAIR_SPEED)
    advice = _advice(fault)
    assert "links.stiffness" in advice and "interactions.stiffness" not in advice
    assert _run(LONG_HAIR, [*scene, 'links.response="link"'], 8) is None


def test_start_speed_bounds_what_joint_velocities_set_without_kinematics_give():
    """Joint velocities set on a state without ``forward_kinematics`` (its vertex velocities still zero) count in
    the speed a run starts with: the start term is at least the fastest vertex the kinematics then give, so the
    first frame's check does not take the hair's own start for a blow-up."""
    model = hw.Model.build(hw.scalp_groom(count=6, length=0.2, points=9), segments=8)
    solver = hw.Solver(model)
    state, control = model.state(), model.control()
    w = np.random.default_rng(3).normal(0.0, 20.0, (model.seg_count, 3)).astype(np.float32)
    state.joint_qd.assign(w)
    assert not np.any(state.vertex_velocities.numpy())
    solver.measure_start_speed(state)
    start = solver.speed_terms(control)["start"]
    solver.forward_kinematics(state, control)
    fastest = float(np.linalg.norm(state.vertex_velocities.numpy(), axis=1).max())
    assert fastest <= start * (1.0 + 1e-5)  # float32 kinematics against a float64 sum
    # and the first frame's check passes: the hair moves at what it was given
    s1 = model.state()
    solver.step(state, s1, control, 1.0 / 240.0)
    solver.check(s1, 1)


def test_a_frame_taken_again_solves_its_links_without_the_warm_start():
    """Links solved after the free step start each step from their force of the last (the warm start) at steps
    shorter than 1/45 s, but not in a frame taken again after a fault: its start is a motion the step did not resolve,
    and the last force, put into the next free step, fed it (limp linked hair at one step a frame, taken again in 2
    steps, whipped to 5.5 m/s). ``long_hair_shoulders`` in a 95 m/s wind at 2 substeps faults in its first frame:
    taken again in 4 steps, the frame is to the bit a 4-substep frame without the warm start, not the same 4 steps
    with it (which may fault in this wind, as they did before the links' sweeps took their geometric stiffness), and
    the frames after take it again."""
    shoulders = SCENES / "long_hair_shoulders.toml"
    # a wind in which 2 substeps fault in the first frame and 4 do not (at 90 and 100 m/s 4 substeps fault too)
    windy = [*WINDY, "wind.velocity=[95.0, 0.0, 0.0]"]
    retried = Simulation(hw.Scene.load(shoulders, windy))
    finer, warm = (Simulation(hw.Scene.load(shoulders, [*windy, "sim.substeps=4", "sim.fault_retries=0"]))
                   for _ in range(2))
    finer.solver.warm_start_allowed = False
    for sim in (retried, finer):
        sim.advance_frame()
    assert retried.retakes[:1] == [(1, 4, "air drag (wind.velocity)")] and not finer.solver.links.warm_start
    for name in ("joint_q", "joint_qd", "vertex_positions", "vertex_velocities"):
        np.testing.assert_array_equal(getattr(retried.state, name).numpy(), getattr(finer.state, name).numpy(),
                                      err_msg=name)
    assert warm.solver.links.warm_start
    try:
        warm.advance_frame()  # the same 4 steps with the warm start: another answer, or none
    except hw.SimulationFault:
        pass
    else:
        assert not np.array_equal(warm.state.joint_qd.numpy(), retried.state.joint_qd.numpy())
    assert retried.solver.links.warm_start  # back at its own 2 substeps, the next frame takes it


@pytest.mark.parametrize("lists", [True, False])
def test_links_take_a_warm_start_beside_contacts_solved_after_the_free_step_only_with_theirs(monkeypatch, lists):
    """The links' warm start carries their last force into the free step; where the hair contacts are solved after the
    free step too and started cold, their last force, which held the links' in balance, was not carried, and at long
    steps the free step moved far on the links' alone (``fast_turn`` at 2 substeps: a tip whipped to 8.3 m/s and links
    broke by the step). The links' sweeps now carry the contacts' force too (``Solver.contact_warm_start``, from
    ``WARM_START_CONTACTS_STEP`` on, where each segment lists its contacts: the CPU), and the links take theirs beside
    it. Without the lists (a GPU, or ``HairContacts.scatter``) the contacts start cold from that step on, and so do
    the links; at ``fast_turn``'s shipped 8 substeps, or with the contacts in the free step, the links take theirs."""
    from hairwarp.interactions import HairContacts
    from hairwarp.solver import WARM_START_CONTACTS_STEP

    monkeypatch.setattr(HairContacts, "scatter", not lists)
    fast_turn = SCENES / "fast_turn.toml"
    assert 1.0 / 240.0 < WARM_START_CONTACTS_STEP < 1.0 / 60.0
    for substeps, response, warm, contacts_warm in ((8, "step", True, False), (2, "step", lists, lists),
                                                    (2, "mass", True, False)):
        sim = Simulation(hw.Scene.load(fast_turn, ["output.preview=false", "dense.count=0", "groom.count=60",
                                                   f"sim.substeps={substeps}", f'interactions.response="{response}"']))
        sim.advance_frame()
        assert sim.solver.contacts.response is (response == "step")
        assert sim.solver.links.warm_start is warm, (substeps, response)
        assert sim.solver.contacts.warm_start is contacts_warm, (substeps, response)


# long_hair slid 0.1 m to and fro at 5 Hz (ten g): its guides whip at 20-30 m/s at any step
SLIDE = ['head.motion.kind="translate"', "head.motion.distance=0.1", "head.motion.period=0.2", "head.motion.ramp=0",
         "dense.count=0", "output.preview=false"]


@pytest.mark.slow  # 5 s
def test_a_whip_that_finer_steps_do_not_slow_is_named_the_motions():
    """``long_hair`` slid at ten g, its speed margin 3 (the bound 17.4 m/s, 3 times the 5.8 m/s the motion explains),
    whips its guides past the bound in frame 18 at 8 substeps and as fast in that frame taken again in 16 and 32 steps
    (19.4, 19.5 and 19.3 m/s): the fault says finer steps do not slow them and advises the speed margin, the drag or
    a slower motion, not more substeps. A run of its own at 32 substeps without the bound whips past it too by that
    frame, as fast as the takes (21.7 m/s in frame 15). With the margin raised as advised the run goes on; frame 12,
    whose whip 16 steps did not slow either (16.0 and 14.9 m/s), is kept as taken, and the frames after it are not
    taken again for a whip (``runner.WHIP_REST_FRAMES``). (At the default margin 4 the bound lies at the slide's own
    whips, 20-24 m/s at 32 substeps from frame 15 on, and whether a frame's takes agree changes with any change of
    the forces.)"""
    import re

    from hairwarp.runner import WHIP_AGREEMENT, WHIP_REST_FRAMES

    sim = Simulation(hw.Scene.load(LONG_HAIR, [*SLIDE, "sim.speed_margin=3"]))
    with pytest.raises(SimulationFault) as info:
        for _ in range(30):
            sim.advance_frame()
    fault = info.value
    assert fault.stage == "dynamics (aba + integrate)" and "finer steps do not slow them" in str(fault), fault
    assert "sim.speed_margin" in _advice(fault) and "sim.substeps" not in _advice(fault)
    takes = [float(v) for v in re.search(r"whipped at ([\d.]+), ([\d.]+) and ([\d.]+) m/s", str(fault)).groups()]
    margin, explained = (float(v) for v in re.search(r"sim.speed_margin = ([\d.]+) times the ([\d.]+) m/s",
                                                          str(fault)).groups())
    fine = Simulation(hw.Scene.load(LONG_HAIR, [*SLIDE, "sim.substeps=32", "sim.speed_margin=inf"]))
    fastest = 0.0
    for _ in range(fault.frame):
        fine.advance_frame()
        fastest = max(fastest, float(np.linalg.norm(fine.state.vertex_velocities.numpy(), axis=1).max()))
    # the separate fine run (its motion the same, its step a quarter) whips past the bound, within the takes' own
    # agreement of the fastest of them
    assert fastest > margin * explained and abs(fastest - max(takes)) <= WHIP_AGREEMENT * max(takes), (fastest, takes)

    held = Simulation(hw.Scene.load(LONG_HAIR, [*SLIDE, "sim.speed_margin=8"]))
    for _ in range(30):
        held.advance_frame()
    frame, kept = held.motion_whips[0]
    assert [n for n, _ in kept] == [8, 16] and held.whip_note().startswith(f"frame {frame}: guides whipped past")
    resting = range(frame + 1, frame + WHIP_REST_FRAMES + 1)
    assert not [r for r in held.retakes if r[0] in resting and r[2] == "whip"], held.retakes


def test_a_speed_fault_after_a_whip_take_is_named_by_whether_finer_steps_slowed_it():
    """A frame whose first take was kept for a whip (no fault) and whose finer takes then faulted on the hair's speed:
    the fault weighs the whip take's speed with theirs (it failed on that take, which carries no fault), and calls the
    whip the motion's where the last two takes agree within ``runner.WHIP_AGREEMENT``, the step's where finer steps
    slowed it (the shoulders' nod ten times as fast: 19.0, then 10.6 m/s) or ran it much faster (the ten-g slide's
    frame 16: 28.4 and 39.7 m/s in 16 and 32 steps; the shoulders' 3 rev/s spin, whose take in 16 steps whipped
    faster than in 8 and in 32 steps slowed to a third)."""
    from hairwarp.kernels.types import Fault
    from hairwarp.solver import DYNAMICS_STAGE

    sim = Simulation(hw.Scene.load(TINY, ["output.preview=false", "dense.count=0"]))

    def speed_fault(v):
        return SimulationFault(f"simulation fault at frame 16 in {DYNAMICS_STAGE}: a guide vertex moved at {v} m/s.",
                               frame=16, stage=DYNAMICS_STAGE, bits=int(Fault.HAIR_SPEED))

    motion = sim._retried_fault(speed_fault(30.0), [(8, 27.1, None), (16, 28.4, speed_fault(28.4)),
                                                    (32, 30.0, speed_fault(30.0))])
    assert "whipped at 27.1, 28.4 and 30 m/s: finer steps do not slow them" in str(motion)
    assert "sim.speed_margin" in _advice(motion) and "sim.substeps" not in _advice(motion)
    for takes in ([(8, 19.0, None), (16, 10.6, speed_fault(10.6))],
                  [(8, 27.1, None), (16, 28.4, speed_fault(28.4)), (32, 39.7, speed_fault(39.7))]):
        step = sim._retried_fault(takes[-1][2], takes)
        assert "faulted each time" in str(step) and "finer steps do not slow" not in str(step)


def test_a_run_resumed_while_it_rests_from_whips_repeats_its_frames():
    """A run restored from a checkpoint taken within the frames after a whip the motion drives (not taken again for
    one: ``runner.WHIP_REST_FRAMES``) rests as the whole run does, so its frames are the same bits (the slide at ten
    g, its margin raised: frame 12's whip kept, the checkpoint at frame 15)."""
    scene = hw.Scene.load(LONG_HAIR, [*SLIDE, "sim.speed_margin=8"])
    whole = Simulation(scene)
    for _ in range(15):
        whole.advance_frame()
    saved = whole.checkpoint()
    assert whole.motion_whips and whole.motion_whips[0][0] < 15 < whole.motion_whips[0][0] + 15
    for _ in range(10):
        whole.advance_frame()
    resumed = Simulation(scene)
    resumed.restore(saved)
    for _ in range(10):
        resumed.advance_frame()
    assert [r for r in resumed.retakes] == [r for r in whole.retakes if r[0] > 15]
    np.testing.assert_array_equal(resumed.state.vertex_positions.numpy(), whole.state.vertex_positions.numpy())
