"""End-to-end runs of scenes: the cache usd-core reads back, the preview, faults that stop a run with
a clear message and keep what was written, the swap parity and CPU graph capture."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom

import hairwarp as hw
from hairwarp.interactions import REBUILD_FRAMES
from hairwarp.runner import Simulation, Stepper, simulate


@pytest.fixture(scope="module")
def tiny():
    return hw.Scene.load(hw.Scene.default_path().parent / "tiny.toml")


def test_tiny_scene_writes_cache_and_preview(tiny, tmp_path):
    out = tmp_path / "tiny.usdc"
    result = simulate(tiny, out, frames=4, progress=False)
    assert result.cache_path == out and out.exists()
    assert result.preview_path is not None and result.preview_path.exists()
    stage = Usd.Stage.Open(str(out))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    times = curves.GetPointsAttr().GetTimeSamples()
    assert times == [0.0, 1.0, 2.0, 3.0, 4.0]
    counts = np.array(curves.GetCurveVertexCountsAttr().Get())
    S = tiny.sim.segments
    assert (counts == S + 1).all()
    pts = np.array(curves.GetPointsAttr().Get(4.0))
    assert np.isfinite(pts).all() and pts.shape == (counts.sum(), 3)
    # the articulated chain keeps its segment lengths exactly (to float32 round-off of the world sums)
    seg = np.linalg.norm(np.diff(pts.reshape(-1, S + 1, 3), axis=1), axis=2)
    first = np.linalg.norm(np.diff(np.array(curves.GetPointsAttr().Get(0.0)).reshape(-1, S + 1, 3), axis=1), axis=2)
    assert np.allclose(seg, first, rtol=1e-5)
    assert stage.GetTimeCodesPerSecond() == tiny.sim.fps


def test_fault_names_frame_stage_and_parameter_and_keeps_frames(tiny, tmp_path):
    # a stiff strand under explicit joint springs at 2 substeps per frame (h = 1/60 s): unstable
    scene = tiny.with_overrides(["sim.integrator=semi_implicit", "sim.substeps=2", "strands.bend_stiffness=5e-3"])
    out = tmp_path / "fault.usdc"
    with pytest.raises(hw.SimulationFault) as info:
        simulate(scene, out, frames=10, progress=False, preview=False)
    fault = info.value
    message = str(fault)
    assert f"frame {fault.frame}" in message and "dynamics" in message
    partial = tmp_path / "fault.partial" / "fault.usdc"  # the frames of a failed run; nothing at the output path
    assert "implicit_joints" in message and "substeps" in message and str(partial) in message
    assert not out.exists()
    stage = Usd.Stage.Open(str(partial))
    times = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides")).GetPointsAttr().GetTimeSamples()
    assert times == [float(f) for f in range(fault.frame)]


@pytest.mark.parametrize("integrator", ["rk4", "semi_implicit"])
def test_an_explicit_integrators_fault_gives_substeps_that_run(tiny, integrator):
    """rk4 and semi_implicit take the joint springs and damping explicitly: at the tiny scene's 8 substeps they fault
    in the first frame, and the fault names the substeps they need (``Solver.explicit_step_bound``); the tiny scene
    runs its 10 frames at that many (measured bounds: 515 and 375 substeps)."""
    import re

    scene = tiny.with_overrides([f"sim.integrator={integrator}", "sim.fault_retries=0"])
    sim = Simulation(scene)
    with pytest.raises(hw.SimulationFault) as info:
        sim.advance_frame()
    message = str(info.value)
    assert info.value.stage == "dynamics (aba + integrate)" and "implicit_joints" in message
    need = int(re.search(r"sim\.substeps = (\d+) or more, now 8", message).group(1))
    assert 8 < need <= 1000
    sim = Simulation(scene.with_overrides([f"sim.substeps={need}"]))
    for _ in range(scene.sim.frames):
        sim.advance_frame()
    assert np.isfinite(sim.guide_curves()[0]).all()


def test_an_explicit_integrators_fault_on_tiny_segments_names_them_and_not_millions_of_substeps(tiny):
    """Strands of 4 mm (0.5 mm segments) under semi_implicit need steps far too short to offer as substeps: the fault
    names the strand with the shortest segments and their length, and points to implicit_joints alone."""
    import re

    scene = tiny.with_overrides(["sim.integrator=\"semi_implicit\"", "groom.length=0.004"])
    sim = Simulation(scene)
    with pytest.raises(hw.SimulationFault) as info:
        sim.advance_frame()
    message = str(info.value)
    need = int(re.search(r"sim\.substeps = (\d+) or more", message).group(1))
    assert need > 10_000  # a closed form for the order: the twist rate grows as 1 / (segment length)^2
    named = float(re.search(r"strand \d+, whose segments are ([\d.]+) mm", message).group(1))
    # the shortest strand's segments; the message gives 3 significant digits: 2e-3 covers their rounding
    assert named == pytest.approx(1e3 * sim.model.seg_length.numpy().min(), rel=2e-3)
    assert "implicit_joints" in message and "that many substeps" not in message


def test_the_step_api_refuses_what_would_crash_or_do_nothing(tiny):
    """Arguments the kernels cannot take are refused with the argument's name: a state or a control of another
    model (a kernel reading past its arrays would end the process), one state as both input and output, no
    control, no finite step size, no substeps, a head pose that is not finite or no rotation, a zero root frame
    quaternion, a wind of the wrong size, a thread count that is not a count, and dense hair asked of a scene
    without any. Valid values still step."""
    sim = Simulation(tiny)
    solver, model = sim.solver, sim.model
    control = model.control()
    bigger = Simulation(tiny.with_overrides(["sim.segments=9"])).model
    bigger_strands = Simulation(tiny.with_overrides(["groom.count=12"])).model
    with pytest.raises(ValueError, match="state_in holds .* joints"):
        solver.step(bigger.state(), model.state(), control, 1 / 240)
    with pytest.raises(ValueError, match="state_out holds"):
        solver.step(model.state(), bigger.state(), control, 1 / 240)
    with pytest.raises(TypeError, match="control must be a hairwarp Control"):
        solver.step(model.state(), model.state(), None, 1 / 240)
    for dt in (None, np.inf, np.nan, 0.0):
        with pytest.raises(ValueError, match="dt must be"):
            hw.Solver(model).step(model.state(), model.state(), control, dt)
    with pytest.raises(ValueError, match="dt must be"):
        Stepper(solver, dt=np.inf)
    same = model.state()
    with pytest.raises(ValueError, match="the same state"):
        solver.step(same, same, control, 1 / 240)
    with pytest.raises(ValueError, match="a control of another model"):
        solver.step(model.state(), model.state(), hw.Control(bigger_strands, root_frames=True), 1 / 240)
    framed = hw.Control(model, root_frames=True)
    G = model.strand_count
    still = np.zeros((G, 6))
    poses = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (G, 1))
    poses[5, 3:] = 0.0
    with pytest.raises(ValueError, match="zero quaternion \\(strand 5\\)"):
        framed.set_root_frames(poses, still, still)
    poses[5, 3:] = (0.0, 0.0, 0.0, 5.0)  # normalised, as set_head does
    framed.set_root_frames(poses, still, still)
    assert framed.bases.xform.numpy()[5][3:] == pytest.approx([0.0, 0.0, 0.0, 1.0])
    for substeps in (0, -1, 2.5):
        with pytest.raises(ValueError, match="substeps must be"):
            Stepper(solver, dt=1 / 240, substeps=substeps)
    for bad in ({"position": (np.nan, 0.0, 0.0)}, {"rotation": (0.0, 0.0, 0.0, 0.0)}, {"rotation": (0.0, 0.0, 1.0)},
                {"linear_velocity": (1.0, 0.0)}):
        with pytest.raises(ValueError, match="position|rotation|velocity"):
            control.set_head(**bad)
    for wind in ((np.inf, 0.0, 0.0), (1.0, 0.0)):
        with pytest.raises(ValueError, match="wind velocity"):
            control.set_wind(wind)
    for threads in ("abc", 2.5, -1, "2"):
        with pytest.raises(ValueError, match="threads must be"):
            Simulation(tiny, threads=threads)
    # more threads than cores run, slower, with a warning naming the argument and the cores
    from hairwarp.executor import default_threads

    cores = default_threads()
    with pytest.warns(UserWarning, match=f"^threads = {cores + 1} is more than the {cores} cores this process"):
        Simulation(tiny, threads=cores + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Simulation(tiny, threads=cores)
    with pytest.raises(ValueError, match="no dense hair"):
        sim.dense_curves()
    # a quaternion off unit length is normalised, and the valid calls step
    control.set_head(rotation=(0.0, 0.0, 0.0, 2.0))
    assert control.head_xform.numpy()[0][3:] == pytest.approx([0.0, 0.0, 0.0, 1.0])
    control.set_wind((1.0, 0.0, 0.0))
    solver.step(model.state(), model.state(), control, 1 / 240)


@pytest.mark.parametrize("field", ["wind", "head_velocity", "head_xform"])
def test_nonfinite_control_written_in_place_is_named_as_the_fault(tiny, field):
    """A control array written in place (as a captured graph's inputs are) with a NaN is not checked on the way in;
    the fault it causes names the control's array and says to give it finite values, not the step size."""
    sim = Simulation(tiny)
    solver, model = sim.solver, sim.model
    control = model.control()
    array = getattr(control, field)
    values = array.numpy().copy()
    values.view(np.float32).reshape(-1)[0] = np.nan
    array.assign(values)
    s0, s1 = model.state(), model.state()
    solver.forward_kinematics(s0, control)
    for _ in range(3):
        solver.step(s0, s1, control, 1 / 240)
        s0, s1 = s1, s0
    with pytest.raises(hw.SimulationFault) as fault:
        solver.check(s0, frame=1)
    assert fault.value.stage == "control input"
    assert f"the control's {field} held non-finite values" in str(fault.value) and "finite values" in str(fault.value)


def test_a_simulation_drives_its_head_from_an_assigned_motion(tiny):
    """``sim.motion`` assigned mid-run drives the head from the next step on: a slide of 5 cm along x with a period
    of 1 s puts the head at 0.05 sin(2 pi t) at the end of frame 6 (t = 0.2 s at 30 fps); set_head on the control
    would be overwritten, and an object that is no motion is refused."""
    import hairwarp.motion as motion

    sim = Simulation(tiny)
    sim.advance_frame()
    sim.motion = motion.HeadMotion.from_config({"kind": "translate", "distance": 0.05, "period": 1.0, "start": 0.0,
                                                "ramp": 0.0})
    for _ in range(5):
        sim.advance_frame()
    t = 6 / tiny.sim.fps
    # float32 head position: 1e-7 m of 0.05 m
    assert sim.stepper.control.head_xform.numpy()[0][0] == pytest.approx(0.05 * np.sin(2 * np.pi * t), abs=1e-7)
    with pytest.raises(TypeError, match="evaluate"):
        sim.motion = 3


@pytest.mark.parametrize("scene_name, overrides", [
    # a keyframed turn (90 degrees in 0.4 s), at 2 substeps
    ("fast_turn.toml", ["groom.count=20", "sim.substeps=2", "links.enabled=false", "interactions.enabled=false"]),
    # roots on the character's sliding scalp: per-strand root frames
    ("character.toml", ["groom.count=20"]),
])
def test_head_accelerations_are_the_mean_over_each_step(scene_name, overrides):
    """Every step gives the control the motion's velocities at the step's end, and as accelerations their change
    over the step divided by the step: the hair takes over the step the head's own change of velocity (sampled at
    the step's end, the turn's accelerations differ from that by more than 10 %). The same for the root frames of a
    scalp binding. Reference: the scene's motion (and scalp binding) evaluated at the steps' ends."""
    scene = hw.Scene.load(hw.Scene.default_path().parent / scene_name,
                          overrides=["dense.count=0", "output.preview=false", *overrides])
    sim = Simulation(scene)
    control = sim.stepper.control
    given = []
    set_motion, set_frames = control.set_motion, control.set_root_frames
    control.set_motion = lambda sample: (given.append(["head", sample]), set_motion(sample))
    control.set_root_frames = lambda *frames: (given[-1].append(frames), set_frames(*frames))
    for _ in range(12):
        sim.advance_frame()
    dt, t, largest_gap = sim.stepper.dt, 0.0, 0.0
    for entry in given:
        t_end = t + dt  # the runner's own sum of steps
        sample = entry[1]
        truth = sim.motion.evaluate(t_end)
        start = sim.motion.evaluate(t)
        np.testing.assert_array_equal(sample.angular_velocity, truth.angular_velocity)
        np.testing.assert_array_equal(sample.linear_velocity, truth.linear_velocity)
        # float64 on the host: the difference of two velocities over dt, to round-off
        np.testing.assert_allclose(sample.angular_acceleration, (truth.angular_velocity - start.angular_velocity) / dt,
                                   rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(sample.linear_acceleration, (truth.linear_velocity - start.linear_velocity) / dt,
                                   rtol=1e-9, atol=1e-9)
        scale = max(np.linalg.norm(truth.angular_acceleration), 1e-9)
        largest_gap = max(largest_gap, np.linalg.norm(truth.angular_acceleration - sample.angular_acceleration) / scale)
        if sim.surface is not None:
            _, velocities, accelerations = entry[2]
            _, v_end, _ = sim.surface.root_frames(t_end)
            _, v_start, _ = sim.surface.root_frames(t)
            np.testing.assert_array_equal(velocities, v_end)
            np.testing.assert_allclose(accelerations, (v_end - v_start) / dt, rtol=1e-9, atol=1e-9)
        t = t_end
    assert len(given) == 12 * sim.stepper.substeps
    if sim.surface is None:
        assert largest_gap > 0.1  # the test sees steps whose mean is not the end's acceleration


def run_steps(tiny, steps, use_graph, substeps):
    sim = Simulation(tiny)
    stepper = Stepper(sim.solver, dt=tiny.step_dt, substeps=substeps, control=sim.stepper.control,
                      state=sim.state, use_graph=use_graph)
    for _ in range(steps):
        stepper.advance_frame(sim._before_step)
    wp.synchronize()
    return stepper.state.vertex_positions.numpy().copy(), stepper.parity


@pytest.mark.parametrize("substeps", [1, 3])
def test_graph_capture_replays_the_eager_steps(tiny, substeps):
    # CPU graph capture (Warp >= 1.19): replaying the captured step gives bit-identical states,
    # with an odd substep count so both parities' graphs are used.
    eager, parity_e = run_steps(tiny, 4, False, substeps)
    graph, parity_g = run_steps(tiny, 4, True, substeps)
    assert parity_e == parity_g == (4 * substeps) % 2
    np.testing.assert_array_equal(eager, graph)


@pytest.mark.parametrize("basis", ["linear", "catmullRom"])
def test_dense_hair_in_the_cache(tiny, tmp_path, basis):
    # dense curves read back by usd-core: one sample per frame, the counts of their basis, finite points,
    # and the guides marked as guides so renderers skip them
    scene = tiny.with_overrides(["dense.count=50", f"dense.basis={basis}", "dense.samples_per_segment=3"])
    out = tmp_path / "dense.usdc"
    simulate(scene, out, frames=2, progress=False, preview=False)
    stage = Usd.Stage.Open(str(out))
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/hair"))
    S = scene.sim.segments
    counts = np.array(hair.GetCurveVertexCountsAttr().Get())
    assert len(counts) == 50 and (counts == (3 * S + 1 if basis == "linear" else S + 1)).all()
    assert hair.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    pts = np.array(hair.GetPointsAttr().Get(2.0))
    assert pts.shape == (counts.sum(), 3) and np.isfinite(pts).all()
    if basis == "linear":
        assert hair.GetTypeAttr().Get() == "linear"
    else:
        assert (hair.GetTypeAttr().Get(), hair.GetBasisAttr().Get(), hair.GetWrapAttr().Get()) == \
            ("cubic", "catmullRom", "pinned")
    guides = UsdGeom.Imageable(stage.GetPrimAtPath("/World/Hair/guides"))
    assert guides.GetPurposeAttr().Get() == UsdGeom.Tokens.guide


def test_usd_animated_collider_moves_through_a_run(tiny, tmp_path):
    # A box authored by hand in a USD stage slides along x over the frames; as a [[colliders]] kind = "usd"
    # it must move in the run as authored and push the strands out of its way.
    from pxr import Gf, Sdf

    stage_path = tmp_path / "box.usda"
    stage = Usd.Stage.CreateNew(str(stage_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(30.0)
    mesh = UsdGeom.Mesh.Define(stage, Sdf.Path("/box"))
    h = 0.03
    corners = [(x, y, z) for z in (-h, h) for y in (-h, h) for x in (-h, h)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    mesh.CreatePointsAttr([Gf.Vec3f(*c) for c in corners])
    mesh.CreateFaceVertexCountsAttr([4] * 6)
    mesh.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    op = mesh.AddTranslateOp()
    start, end = np.array([-0.3, 0.0, 1.45]), np.array([0.3, 0.0, 1.45])
    for frame in (0, 10):
        op.Set(Gf.Vec3d(*(start + (end - start) * frame / 10)), Usd.TimeCode(frame))
    stage.GetRootLayer().Save()

    scene = tiny.with_overrides([
        "colliders[0].name=box", "colliders[0].kind=usd", f"colliders[0].file='{stage_path}'",
        "colliders[0].thickness=0.001", "head.motion.kind=still",
    ])
    out = tmp_path / "box.usdc"
    simulate(scene, out, frames=6, progress=False, preview=False)
    cache = Usd.Stage.Open(str(out))
    box = UsdGeom.Xformable(cache.GetPrimAtPath("/World/Colliders/box"))
    for frame in (0, 3, 6):
        m = np.array(box.ComputeLocalToWorldTransform(Usd.TimeCode(frame))).T  # USD stores row vectors
        # Keyframes ease between the two samples; the box moves monotonically from start toward end
        assert m[2, 3] == pytest.approx(1.45, abs=1e-6)
        assert start[0] - 1e-6 <= m[0, 3] <= end[0] + 1e-6
    xs = [np.array(box.ComputeLocalToWorldTransform(Usd.TimeCode(f))).T[0, 3] for f in range(7)]
    assert np.all(np.diff(xs) > 0)
    # no strand vertex ends up inside the box (closed form: all three coordinates within h of its centre)
    pts = np.array(UsdGeom.BasisCurves(cache.GetPrimAtPath("/World/Hair/guides")).GetPointsAttr().Get(6.0))
    centre = np.array(box.ComputeLocalToWorldTransform(Usd.TimeCode(6))).T[:3, 3]
    inside = np.all(np.abs(pts - centre) < h - 1e-4, axis=1)
    assert not inside.any()


def _jump_scene(gap, **extra):
    """The default scene, 100 guides, the head held still, then moved 0.5 m along x within ``gap`` seconds."""
    import tomllib

    import hairwarp as hw

    path = Path(__file__).resolve().parents[1] / "scenes" / "long_hair.toml"
    raw = tomllib.loads(path.read_text())
    raw["head"]["motion"] = {"kind": "keyframes", "interpolation": "monotone", "keys": [
        {"time": 0.0}, {"time": 0.5}, {"time": 0.5 + gap, "translate": [0.5, 0.0, 0.0]}]}
    overrides = ["dense.count=0", "groom.count=100"] + [f"{k}={v}" for k, v in extra.items()]
    return hw.Scene.from_dict(raw, path, overrides=overrides)


@pytest.mark.parametrize("gap", [0.001, 2.0 / 30.0])  # a cut, and a 0.5 m move in two frames
def test_head_jump_carries_the_hair_and_it_settles(gap):
    """A head that moves farther than head.teleport_distance within a frame carries the hair rigidly: no fault,
    and 1 s later the tips move at most 0.1 m/s (the head is still again)."""
    from hairwarp.runner import Simulation

    sim = Simulation(_jump_scene(gap))
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    previous = None
    for frame in range(1, 46):  # to 1 s after the jump
        sim.advance_frame()
        x = sim.guide_curves()[0].reshape(G, S + 1, 3)
        if frame == 45:
            speed = np.linalg.norm(x[:, -1] - previous[:, -1], axis=-1) * sim.scene.sim.fps
            assert np.sqrt((speed ** 2).mean()) <= 0.1
            assert np.abs(x[:, 0, 0] - 0.5 - sim.model.rest_vertex_positions[:, 0, 0]).max() < 1e-5  # roots moved
        previous = x



def test_a_nod_about_a_distant_pivot_is_no_teleport_a_jump_is():
    """The teleport test measures how far the hair's middle moves in a frame, not the head frame's origin: the
    shipped tiny nods about a pivot 1.5 m above its origin, which then swings ~0.2 m a frame while the hair moves
    centimetres (41 of its 80 steps were taken for teleports, the hair carried rigidly and stopped). The hair's own
    motion is read back from the run: no step teleports, and the fastest root moves far less than the threshold."""
    from hairwarp.runner import is_teleport

    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "tiny.toml", ["output.preview=false"]))
    teleports = []
    real = sim.solver.teleport
    sim.solver.teleport = lambda *a: (teleports.append(sim.stepper.time), real(*a))
    roots = [sim.guide_curves()[0].reshape(sim.model.strand_count, -1, 3)[:, 0].astype(float)]
    for _ in range(10):
        sim.advance_frame()
        roots.append(sim.guide_curves()[0].reshape(sim.model.strand_count, -1, 3)[:, 0].astype(float))
    assert teleports == []
    distance = sim.scene.head.teleport_distance
    assert np.linalg.norm(np.diff(roots, axis=0), axis=-1).max() < 0.5 * distance
    # the same nod, measured at the head frame's origin (the old test), crosses the threshold
    motion = sim.motion
    frame = 1.0 / sim.scene.sim.fps
    crossed = [is_teleport(motion.pose(t), motion.pose(t + frame), distance, 60.0)
               for t in np.arange(0.0, 0.3, frame / 8)]
    assert any(crossed)
    # a jump of the hair's middle past the threshold is one, in any direction; a turn past the angle is one
    centre = (0.0, 0.0, 1.5)
    still = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    assert is_teleport(still, ((0.0, 0.3, 0.0), (0.0, 0.0, 0.0, 1.0)), 0.2, 60.0, centre)
    assert not is_teleport(still, ((0.0, 0.1, 0.0), (0.0, 0.0, 0.0, 1.0)), 0.2, 60.0, centre)
    half = np.radians(70.0) / 2
    assert is_teleport(still, ((0.0, 0.0, 0.0), (0.0, 0.0, np.sin(half), np.cos(half))), 0.2, 60.0, centre)
    # a 20 degree turn about an axis through the hair's middle moves it nowhere: no teleport however far the origin
    half = np.radians(20.0) / 2
    q = np.array([np.sin(half), 0.0, 0.0, np.cos(half)])
    from scipy.spatial.transform import Rotation
    origin = np.array(centre) - Rotation.from_quat(q).apply(centre)  # the turned frame keeps the centre in place
    assert np.linalg.norm(origin) > 0.2 and not is_teleport(still, (origin, q), 0.2, 60.0, centre)

def test_solver_teleport_keeps_the_shape_relative_to_the_head():
    """``Solver.teleport`` moves the strands with the head pose and stops them."""
    import hairwarp as hw

    model = hw.Model.build(hw.scalp_groom(count=20, length=0.2, points=9), segments=8)
    solver = hw.Solver(model)
    s0, s1, control = model.state(), model.state(), model.control()
    solver.forward_kinematics(s0, control)
    for _ in range(20):
        solver.step(s0, s1, control, 1.0 / 240.0)
        s0, s1 = s1, s0
    before = s0.vertex_positions.numpy().astype(float)
    angle = 0.7
    control.set_head(position=(1.0, -2.0, 0.5), rotation=(0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)))
    solver.teleport(s0, control)
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    # float32 positions of metre-sized coordinates: a few 1e-7 m
    np.testing.assert_allclose(s0.vertex_positions.numpy(), before @ R.T + (1.0, -2.0, 0.5), atol=2e-6)
    np.testing.assert_array_equal(s0.joint_qd.numpy(), 0.0)
    np.testing.assert_allclose(s0.vertex_velocities.numpy(), 0.0, atol=1e-7)


def test_checkpoint_restores_the_run_exactly():
    """``Simulation.checkpoint`` then more frames then ``restore``: the state is the checkpoint's again, and the
    frames after it repeat bit for bit. (On the CPU a Warp array's ``numpy()`` is a view: taken as is, the
    checkpoint followed the run and ``restore`` went back to nowhere, 54 mm off on the tiny scene.)"""
    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "long_hair.toml",
                                   ["groom.count=40", "dense.count=0", "output.preview=false"]))
    for _ in range(10):  # into the turn's ramp: the head speeds up over the next frames
        sim.advance_frame()
    saved = sim.checkpoint()
    at_checkpoint = sim.guide_curves()[0].copy()
    bound = sim.solver.speed_bound()
    ahead = []
    for _ in range(3):
        sim.advance_frame()
        ahead.append(sim.guide_curves()[0].copy())
    assert not np.array_equal(ahead[-1], at_checkpoint)  # the run moved on
    assert sim.solver.speed_bound() > bound  # the turn speeds up: the speed fault's bound grew with it
    sim.restore(saved)
    assert sim.stepper.frame == 10
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)
    assert sim.solver.speed_bound() == bound  # the bound the run had there, not a fresh one
    for expected in ahead:
        sim.advance_frame()
        np.testing.assert_array_equal(sim.guide_curves()[0], expected)
    # a checkpoint whose stepper is no frame is refused, and changes nothing
    before = sim.guide_curves()[0].copy()
    for key, bad in (("stepper.frame", 1.5), ("stepper.parity", 2), ("stepper.time", np.nan)):
        with pytest.raises(ValueError, match="stepper.time, frame and parity"):
            sim.restore({**saved, key: np.array(bad)})
    np.testing.assert_array_equal(sim.guide_curves()[0], before)
    assert sim.stepper.frame == 13
    # a checkpoint written before the bound was kept in it restores too, the bound then from its own motion
    from hairwarp.runner import SPEED_KEY
    sim.restore({k: v for k, v in saved.items() if k != SPEED_KEY})
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)
    v = np.linalg.norm(sim.guide_curves()[1], axis=1).max()
    assert sim.solver.speed_terms()["start"] >= v * (1.0 - 1e-6)
    # a checkpoint of a version that kept each body contact's friction share alone (1 sticking, less sliding): it
    # keeps its share, and its slip is none where it stuck and sliding where it slid (kernels.articulated.STICK_SLIP)
    from hairwarp.kernels.articulated import STICK_SLIP
    old = {k: v for k, v in saved.items() if k not in ("solver.body_contacts.slip", "solver.body_contacts.share")}
    share = np.ones(len(saved["solver.body_contacts.slip"]), dtype=np.float32)
    share[::3] = 0.25
    old["solver.body_contacts.beta"] = share
    sim.restore(old)
    slip = sim.solver.body_contacts.slip.numpy()
    np.testing.assert_array_equal(sim.solver.body_contacts.share.numpy(), share)
    np.testing.assert_array_equal(slip[share < 1.0], np.float32(2.0 * STICK_SLIP))
    np.testing.assert_array_equal(slip[share >= 1.0], 0.0)
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)
    # a checkpoint of a version that kept neither the slip each body contact took away nor the time since it held its
    # vertex: none taken away, and held in the last step where it kept a force (long ago where none)
    contacts = sim.solver.body_contacts
    held = np.linalg.norm(saved["solver.body_contacts.force"], axis=-1) > 0.0
    assert held.any() and not held.all()
    sim.restore({k: v for k, v in saved.items() if k not in ("solver.body_contacts.removed",
                                                                "solver.body_contacts.away")})
    np.testing.assert_array_equal(contacts.removed.numpy(), 0.0)
    np.testing.assert_array_equal(contacts.away.numpy(), np.where(held, 0.0, 1.0))
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)
    # a checkpoint of a version that kept no links' forces of the last step (``Solver._warm_start``): none
    warm = sim.solver.links.link_warm
    warm.assign(np.ones(warm.shape + (3,), dtype=np.float32))
    sim.restore({k: v for k, v in saved.items() if k != "solver.links.link_warm"})
    np.testing.assert_array_equal(warm.numpy(), 0.0)
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)
    # ... nor the force the bodies' answer to the links' sweeps added (``kernels.sweeps.body_answer``): none
    answer = sim.solver.body_contacts.answer_force
    answer.assign(np.ones(answer.shape + (3,), dtype=np.float32))
    sim.restore({k: v for k, v in saved.items() if k != "solver.body_contacts.answer_force"})
    np.testing.assert_array_equal(answer.numpy(), 0.0)
    np.testing.assert_array_equal(sim.guide_curves()[0], at_checkpoint)


def test_the_step_apis_tools_refuse_what_would_crash_or_go_wrong_silently(tiny, tmp_path):
    """The calls a Warp programmer makes between steps check what the kernels would index past or take silently,
    each in one line naming the argument, and change nothing when they refuse: another model's state given to
    ``forward_kinematics``, ``teleport`` or ``joint_accelerations`` (a kernel reading past a smaller state's arrays
    ended the process), a state whose ``joint_qd`` alone is short, ``State.assign`` across models, one ColliderSet
    for two models, links or hair contacts of another model, a collider velocity that is not 3 finite numbers, a
    gravity that is not finite, a fractional segment count, a rotation bound that is not a positive angle, a bool
    step size, and arguments of the wrong kind."""
    from hairwarp.colliders import Collider, ColliderError, ColliderSet
    from hairwarp.model import ModelError

    sim = Simulation(tiny)
    solver, model = sim.solver, sim.model
    control = model.control()
    small = hw.Model.build(hw.scalp_groom(count=2, length=0.2, points=8), segments=3)
    for call in (solver.forward_kinematics, solver.teleport, solver.joint_accelerations):
        with pytest.raises(ValueError, match="state holds .* a state of another model"):
            call(small.state(), control)
    short = model.state()
    short.joint_qd = wp.zeros(3, dtype=wp.vec3)
    with pytest.raises(ValueError, match="state_in holds joint_qd 3 elements"):
        solver.step(short, model.state(), control, 1 / 240)
    with pytest.raises(TypeError, match="state must be a hairwarp State"):
        solver.teleport(None, control)

    mine = model.state()
    before = mine.joint_q.numpy().copy()
    for other in (small.state(), hw.Model.build(hw.scalp_groom(count=400, length=0.2, points=8), segments=9).state()):
        with pytest.raises(ValueError, match="a state of another model"):
            mine.assign(other)
    assert np.array_equal(mine.joint_q.numpy(), before)

    ball = Collider.sphere(0.05, name="ball", center=(0.0, 0.0, -1.0), attach="world")
    shared = ColliderSet([ball], "cpu")
    hw.Solver(model, colliders=shared)
    with pytest.raises(ValueError, match="bound to another model"):
        hw.Solver(small, colliders=shared)
    with pytest.raises(TypeError, match="colliders must be a hairwarp ColliderSet"):
        hw.Solver(model, colliders=[ball])
    # links and hair contacts built from another model's rest pose (a step with such links ended the process, such
    # contacts ran on silently)
    other = hw.Model.build(hw.scalp_groom(count=20, length=0.2, points=8), segments=3)
    for name, part in (("links", hw.StaticLinks.build(other.rest_vertex_positions, radius=0.05, stiffness=1.0,
                                                      damping=0.001, break_length=0.1)),
                       ("contacts", hw.HairContacts.build(other.rest_vertex_positions, threshold=0.002, stiffness=7.0,
                                                          damping=0.0035, capacity=1024))):
        built = f"{name} were built for {other.seg_count} segments, not this model's 6 "
        with pytest.raises(ValueError, match=built):
            hw.Solver(small, **{name: part})
        hw.Solver(other, **{name: part})
    posed = shared.world_matrices()
    for velocity in ((0.0, np.nan, 0.0), (1.0, 2.0)):
        with pytest.raises(ColliderError, match="collider 'ball': linear_velocity must be 3"):
            shared.set_pose("ball", np.eye(4), linear_velocity=velocity)
    assert np.array_equal(shared.world_matrices(), posed)  # refused: nothing set

    groom = hw.scalp_groom(count=2, length=0.2, points=8)
    with pytest.raises(ModelError, match="gravity must be 3 finite numbers"):
        hw.Model.build(groom, segments=3, gravity=(0.0, 0.0, np.nan))
    for segments in (2.7, "8", True):
        with pytest.raises(ModelError, match="segments must be a whole number"):
            hw.Model.build(groom, segments=segments)
    for bound in (-1.0, 0.0, np.nan, "1"):
        with pytest.raises(ValueError, match="max_rotation_per_step must be an angle > 0"):
            hw.Solver(model, max_rotation_per_step=bound)
    with pytest.raises(ValueError, match="dt must be"):
        solver.step(model.state(), model.state(), control, True)
    with pytest.raises(TypeError, match="sample must be a hairwarp MotionSample"):
        control.set_motion(None)
    with pytest.raises(TypeError, match="overrides must be a list"):
        hw.Scene.load(tiny.source, overrides="sim.frames=3")
    with pytest.raises(TypeError, match="scene must be a hairwarp Scene, a scene file's path"):
        Simulation(5)
    for frames in (-3, 2.5):
        with pytest.raises(ValueError, match="frames must be a whole number >= 0"):
            simulate(tiny, tmp_path / "x.usdc", frames=frames, progress=False)
    assert not any(tmp_path.iterdir())
    if not wp.is_cuda_available():
        with pytest.raises(ValueError, match="device = 'cuda': Warp finds no CUDA device on this machine"):
            hw.Model.build(groom, segments=3, device="cuda")


def test_a_simulation_takes_its_scene_as_a_path_or_a_dict(tiny):
    """``Simulation`` and ``simulate`` take a scene file's path or its tables as well as a Scene: the same run."""
    import tomllib

    by_scene, by_path = Simulation(tiny), Simulation(str(tiny.source))
    raw = tomllib.loads(Path(tiny.source).read_text())
    by_dict = Simulation(hw.Scene.from_dict(raw, source=tiny.source))
    for sim in (by_scene, by_path, by_dict):
        sim.advance_frame()
    x = by_scene.guide_curves()[0]
    assert np.array_equal(by_path.guide_curves()[0], x) and np.array_equal(by_dict.guide_curves()[0], x)


def test_checkpoint_restores_a_run_whose_sweeps_turn_step_by_step():
    """Links solved after the free step by an odd count of sweeps a step run their colours forward and back in turn
    (``Solver.sweep_turn``, set from the step's place in its frame): a restored run repeats the frames after the
    checkpoint bit for bit, though each frame of 5 steps ends on the other parity."""
    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "long_hair.toml",
                                   ["groom.count=40", "dense.count=0", "output.preview=false", "sim.substeps=5",
                                    'links.response="step"', 'interactions.response="mass"']))
    links = sim.solver.links
    for _ in range(4):
        sim.advance_frame()
    # (the contacts in the free step: the sweeps solve the links alone)
    assert links.warm_start and links.sweeps_at(sim.stepper.dt) % 2 == 1  # 3 a step: the turn matters
    _assert_frames_repeat_after_restore(sim, 3)


def _shoulders_at_one_step_a_frame(colliders: bool):
    """40 of ``long_hair_shoulders``' strands with the head still, at one step a frame, with or without colliders."""
    from hairwarp.benchmarks.robustness import build, head_still, raw_scene, set_key, without_colliders

    raw = head_still(raw_scene("long_hair_shoulders"))
    raw = set_key(set_key(raw if colliders else without_colliders(raw), "sim.substeps", 1), "groom.count", 40)
    return Simulation(build(raw, "long_hair_shoulders", overrides=["dense.count=0"]))


def _tips_over(sim, frames: int) -> np.ndarray:
    """The guide tips [m] after each of ``frames`` frames, (frames, G, 3)."""
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    tips = []
    for _ in range(frames):
        sim.advance_frame()
        tips.append(sim.guide_curves()[0].reshape(G, S + 1, 3)[:, S].astype(float))
    return np.asarray(tips)


def test_linked_hair_at_rest_does_not_flicker_at_one_step_a_frame():
    """At one step a frame the links solved after the free step take 25 sweeps a step, an odd count: turned by the
    run's parity, every frame ended its sweeps the other way round from the frame before, and hair at rest flickered
    between two shapes (here the fastest tip moved 0.74 mm a frame after 4 s and came back the next, 0.03 mm in two
    frames). Every frame now starts its sweeps the same way (``Solver.sweep_turn`` from the step's place in its frame):
    0.016 mm a frame, settling. Bound 0.1 mm, between the two."""
    sim = _shoulders_at_one_step_a_frame(colliders=False)
    links = sim.solver.links
    assert links.response and links.step_sweeps(sim.stepper.dt) == 25  # an odd count
    tips = _tips_over(sim, 120)
    assert np.linalg.norm(tips[-1] - tips[-2], axis=1).max() < 1e-4


def test_linked_hair_resting_on_a_body_comes_to_rest_at_one_step_a_frame():
    """At one step a frame the links solved after the free step started every step cold: the free step's body
    contacts carried the hair's weight without its links, the sweeps then moved the held vertices without their
    contacts, and the two traded the load every step. Hair resting on the head and shoulders jittered: here the tips
    at 12.3 mm/s in the 5th second, the fastest 1.03 mm in the last frame. The free step now takes the share of each
    link's last force that its ends' parting speed leaves (``WARM_GATE_SPEED``): 0.56 mm/s and 0.014 mm. Bounds 2
    mm/s and 0.1 mm, between the two."""
    sim = _shoulders_at_one_step_a_frame(colliders=True)
    links = sim.solver.links
    assert links.warm_start and links.warm_gate > 0.0 and sim.collider_set is not None
    tips = _tips_over(sim, 150)
    speed = np.linalg.norm(np.diff(tips[-31:], axis=0), axis=2) * sim.scene.sim.fps
    assert np.sqrt(np.mean(speed**2)) < 2e-3
    assert np.linalg.norm(tips[-1] - tips[-2], axis=1).max() < 1e-4


def _assert_frames_repeat_after_restore(sim, frames: int):
    """Run ``frames`` frames from a checkpoint, restore it, and run them again: the same guide curves, bit for bit."""
    saved = sim.checkpoint()
    ahead = []
    for _ in range(frames):
        sim.advance_frame()
        ahead.append(sim.guide_curves()[0].copy())
    sim.restore(saved)
    for expected in ahead:
        sim.advance_frame()
        np.testing.assert_array_equal(sim.guide_curves()[0], expected)


def test_checkpoint_restores_a_run_whose_hair_contacts_start_from_their_last_force():
    """At 2 substeps the links' sweeps solve the hair contacts after the free step, which takes each segment's contact
    force of the last step (``Solver.contact_warm_start``; the links' warm start with it): the checkpoint keeps those
    forces, and a restored run repeats the frames after it bit for bit (restored with none, its guide points ran up to
    0.13 mm off in the next 3 frames). A checkpoint of a version that kept none restores with none."""
    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "long_hair.toml",
                                   ["groom.count=40", "dense.count=0", "output.preview=false", "sim.substeps=2"]))
    for _ in range(4):
        sim.advance_frame()
    contacts = sim.solver.contacts
    assert contacts.warm_start and sim.solver.links.warm_start and np.abs(contacts.warm_force.numpy()).max() > 0
    _assert_frames_repeat_after_restore(sim, 3)
    saved = sim.checkpoint()
    sim.restore({k: v for k, v in saved.items() if not k.startswith("solver.contacts.warm_")})
    assert not contacts.warm_force.numpy().any() and not contacts.warm_torque.numpy().any()


def test_checkpoint_restores_a_run_whose_bodies_answer_starts_from_its_last_force():
    """At one step a frame the bodies' answer to the links' sweeps starts from the contact force each vertex ended the
    last step's answer with (``BodyContacts.answer_force``): the checkpoint keeps it, and a restored run repeats the
    frames after it bit for bit; restored without it (a checkpoint of an earlier version), the answer starts cold and
    the frames differ."""
    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "long_hair_shoulders.toml",
                                   ["groom.count=40", "dense.count=0", "output.preview=false", "sim.substeps=1",
                                    'head.motion.kind="still"']))
    for _ in range(12):
        sim.advance_frame()
    answer = sim.solver.body_contacts.answer_force
    assert np.abs(answer.numpy()).max() > 0
    _assert_frames_repeat_after_restore(sim, 3)
    saved = sim.checkpoint()
    sim.advance_frame()
    expected = sim.guide_curves()[0].copy()
    sim.restore({k: v for k, v in saved.items() if k != "solver.body_contacts.answer_force"})
    assert not answer.numpy().any()
    sim.advance_frame()
    assert not np.array_equal(sim.guide_curves()[0], expected)


def test_checkpoint_restores_a_run_whose_sweeps_carry_factors_over_steps():
    """One sweep a step of links solved after the free step solves with the factors of the strands' matrices that
    an earlier step of the frame made (``Solver.plan_factors``, 8 steps a factorisation); every frame makes its own
    (``Stepper`` expires them at its start), so a run restored at a frame whose steps are not a multiple of that
    count repeats the frames after the checkpoint bit for bit, though the factors in memory are those of frames
    ahead of it."""
    sim = Simulation(hw.Scene.load(hw.Scene.default_path().parent / "long_hair.toml",
                                   ["groom.count=40", "dense.count=0", "output.preview=false", "sim.substeps=10",
                                    'links.response="step"']))
    solver = sim.solver
    for _ in range(3):
        sim.advance_frame()
    # 10 steps a frame of one sweep each: the frame's 1st and 9th make factors, the others carry them
    assert solver.links.warm_start and solver.links.sweeps_at(sim.stepper.dt) == 1 and solver.factor_steps == 8
    assert solver._factor_age == 1
    _assert_frames_repeat_after_restore(sim, 3)


def _contacts_scene():
    return hw.Scene.load(hw.Scene.default_path().parent / "long_hair.toml",
                         ["groom.count=60", "dense.count=0", "output.preview=false"])


def _stored_contacts(contacts) -> list[np.ndarray]:
    n = contacts.contact_count()
    return [a.numpy()[:n].copy() for a in (contacts.contact_kind, contacts.contact_a, contacts.contact_b,
                                           contacts.contact_w, contacts.contact_gap)]


def test_contacts_found_by_a_refit_tree_are_those_of_a_rebuilt_one():
    """On the CPU the runner refits the hair contacts' trees between rebuilds every ``REBUILD_FRAMES`` frames. A refit
    tree walks the quads in another order than a rebuilt one, but the stored contacts are put in one order
    (``HairContacts._canonical_order``): the same contacts in the same slots, to the bit, after the hair has moved
    from the pose the trees were built in."""
    sim = Simulation(_contacts_scene())
    for _ in range(5):
        sim.advance_frame()
    contacts, state = sim.contacts, sim.stepper.state
    contacts.detect(sim.model, state, rebuild=False)
    refit = _stored_contacts(contacts)
    contacts.detect(sim.model, state, rebuild=True)
    rebuilt = _stored_contacts(contacts)
    assert len(refit[0]) > 100
    for a, b in zip(refit, rebuilt):
        np.testing.assert_array_equal(a, b)


def test_a_run_restored_between_tree_rebuilds_repeats_its_frames():
    """A fresh simulation restored from a checkpoint at frame 9 refits trees built at its set-up, in the groom's
    pose, where the run that took the checkpoint refits those it rebuilt at frame 8 from the pose the hair had
    moved to: its next frames are the same bits."""
    sim = Simulation(_contacts_scene())
    for _ in range(9):
        sim.advance_frame()
    assert sim.stepper.frame % REBUILD_FRAMES == 1
    saved = sim.checkpoint()
    ahead = []
    for _ in range(3):
        sim.advance_frame()
        ahead.append(sim.guide_curves()[0].copy())
    fresh = Simulation(_contacts_scene())
    fresh.restore(saved)
    for expected in ahead:
        fresh.advance_frame()
        np.testing.assert_array_equal(fresh.guide_curves()[0], expected)


def test_restore_poses_the_head_for_the_checkpoints_time(tiny):
    """After ``restore`` the control holds the head of the checkpoint's time, not of the frame the run had reached:
    what is read before the next step (dense hair, collider meshes) follows it. The run from there is the same bits
    as the run that took the checkpoint."""
    sim = Simulation(tiny)
    for _ in range(3):
        sim.advance_frame()
    saved = sim.checkpoint()
    head = sim.stepper.control.head_xform.numpy().copy()
    for _ in range(5):
        sim.advance_frame()
    assert not np.array_equal(sim.stepper.control.head_xform.numpy(), head)  # the head turned since
    sim.restore(saved)
    expected = sim.motion.evaluate(float(saved["stepper.time"])).matrix()
    pose = sim.stepper.control.head_xform.numpy()[0]
    # atol 1e-6: the control holds float32, whose spacing near a pose component of 1 (m or unit quaternion) is 1e-7
    assert np.allclose(pose[:3], expected[:3, 3], atol=1e-6)
    from scipy.spatial.transform import Rotation

    assert np.allclose(Rotation.from_quat(pose[3:]).as_matrix(), expected[:3, :3], atol=1e-6)
    sim.advance_frame()
    again = Simulation(tiny)
    for _ in range(4):
        again.advance_frame()
    assert np.array_equal(sim.guide_curves()[0], again.guide_curves()[0])


def test_a_profiled_run_times_each_stage_and_writes_the_same_cache(tmp_path, capsys):
    """``hairwarp run --profile`` (``simulate(profile=True)``): a small ``fast_turn`` (links and hair contacts solved
    after the free step, a body collider) times every stage it has, their sum at most the frames' wall time and most
    of it, and the cache is the plain run's, bit for bit (read back with usd-core: profiling runs the stages one
    after another, not fused over the threads, and changes no arithmetic). The CLI prints the table."""
    from hairwarp.cli import STAGES, main

    path = hw.Scene.default_path().parent / "fast_turn.toml"
    over = ["groom.count=40", "dense.count=0", "output.preview=false", "sim.frames=4"]
    scene = hw.Scene.load(path, over)
    plain = simulate(scene, tmp_path / "plain.usdc", progress=False)
    profiled = simulate(scene, tmp_path / "profiled.usdc", progress=False, profile=True)
    assert plain.stage_seconds is None
    stages = profiled.stage_seconds
    assert set(stages) == {name for name, _ in STAGES}
    assert all(seconds > 0.0 for seconds in stages.values())
    assert 0.5 * profiled.frame_seconds < sum(stages.values()) <= profiled.frame_seconds
    points = []
    for out in ("plain", "profiled"):
        stage = Usd.Stage.Open(str(tmp_path / f"{out}.usdc"))
        curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
        points.append(np.array([curves.GetPointsAttr().Get(float(t)) for t in range(5)]))
    np.testing.assert_array_equal(points[0], points[1])

    capsys.readouterr()
    assert main(["run", str(path), "-o", str(tmp_path / "cli.usdc"), "--profile",
                 *[a for o in over for a in ("-s", o)]]) == 0
    text = capsys.readouterr().out
    assert "time by stage" in text and all(f"  {name} " in text for name, _ in STAGES)


def _tiny_over_a_floor(floor_z: float, head_lift: float) -> hw.Scene:
    """``tiny`` with its head held ``head_lift`` [m] above its rest pose from time 0 (keyframes) and a world plane
    (a floor) at height ``floor_z``."""
    import tomllib

    d = tomllib.loads((hw.Scene.default_path().parent / "tiny.toml").read_text())
    d["head"] = {"motion": {"kind": "keyframes", "keys": [{"time": 0.0, "translate": [0.0, 0.0, head_lift]},
                                                          {"time": 1.0, "translate": [0.0, 0.0, head_lift]}]}}
    d["colliders"] = [{"name": "floor", "kind": "plane", "translate": [0.0, 0.0, floor_z], "attach": "world"}]
    return hw.Scene.from_dict(d)


@pytest.mark.parametrize("head_lift", [0.0, 0.3])
def test_exemptions_are_marked_where_the_hair_starts(head_lift):
    """A vertex inside a collider where the run starts is exempt from it, and a run whose hair starts deeper than
    ``START_INSIDE_DEPTH`` in one warns, naming it, its vertices, strands and depth (the hair passes through it).
    The start is the head posed at time 0: a world plane that cuts through the hair at the head's rest pose but
    not where the head starts (lifted 0.3 m) exempts nothing; marking the rest pose exempted 22 vertices of
    ``long_hair_shoulders`` its nodding start keeps clear of the shoulders. Checked against the plane's distance
    from the start state's own vertices."""
    from hairwarp.runner import START_INSIDE_DEPTH

    rest = Simulation(_tiny_over_a_floor(-10.0, 0.0)).model.rest_vertex_positions.reshape(-1, 3)
    floor_z = float(np.quantile(rest[:, 2], 0.3))  # through the lower hair at the rest pose
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim = Simulation(_tiny_over_a_floor(floor_z, head_lift))
    x = sim.state.vertex_positions.numpy().astype(np.float64).reshape(sim.model.strand_count, -1, 3)
    inside = x[:, :, 2] < floor_z
    inside[:, 0] = False  # roots never collide, never exempt
    np.testing.assert_array_equal(sim.collider_set.vert_exempt.numpy().reshape(inside.shape) != 0, inside)
    said = [str(w.message) for w in caught if "start inside" in str(w.message)]
    if head_lift > 0.0:
        assert not inside.any() and sim.start_inside == [] and said == []
        return
    deepest = float(floor_z - x[:, :, 2][inside].min())
    assert deepest > START_INSIDE_DEPTH and inside.sum() > 0
    (c,) = sim.start_inside
    assert c["name"] == "floor" and c["vertices"] == inside.sum() and c["strands"] == inside.any(axis=1).sum()
    assert c["deepest"] == pytest.approx(deepest, abs=1e-5)  # float32 distances of points ~1.5 m from the origin
    (message,) = said
    assert f"collider 'floor': {inside.sum()} vertices of {inside.any(axis=1).sum()} strands start inside" in message
    assert f"{1e3 * deepest:.3g} mm deep" in message


@pytest.mark.parametrize("name", ["tiny", "long_hair", "long_hair_shoulders", "fast_turn", "character",
                                  "ratboy_mohawk"])
def test_shipped_scenes_start_clear_of_their_colliders(name):
    """No shipped scene starts its hair deeper than ``START_INSIDE_DEPTH`` inside a collider (the run would warn,
    and the hair pass through it: ``character`` drawn with seed 0 put a tip 22 mm into its torso for the whole
    shot); the Ratboy's roots sink up to 1.03 mm into its body, which the exemption is for."""
    from conftest import require_ratboy

    from hairwarp.runner import START_INSIDE_DEPTH

    if name == "ratboy_mohawk":
        require_ratboy("Ratboy_mohawk.tfx")
    scene = hw.Scene.load(hw.Scene.default_path().parent / f"{name}.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Ratboy's groom drops its shortest strands, saying so
        sim = Simulation(scene.with_overrides(["dense.count=0"]))
    assert all(c["deepest"] <= START_INSIDE_DEPTH for c in sim.start_inside), sim.start_inside
