"""Roots bound to a deforming surface (``groom.surface``): the root frames against the motion they must reproduce,
the step on per-strand frames against the step on the head, and the shipped character's sliding scalp."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _character import END, NECK_CM, SCALP_STEP, head_rotation_deg, scalp_points, scalp_rest_points
from scipy.spatial.transform import Rotation

import hairwarp as hw
from hairwarp.motion import cross_rows
from hairwarp.surface import HeadCarriedRoots, PointTrack, ScalpBinding, SurfaceError

SCENES = Path(__file__).resolve().parents[1] / "scenes"
# Y up in cm to Z up in m: (x, y, z) -> 0.01 (x, -z, y)
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _sphere(radius=0.1, centre=(0.0, 0.0, 1.6)):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return mesh.vertices + np.asarray(centre), mesh.faces


def _roots_on(vertices, faces, count, rng):
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    return trimesh.sample.sample_surface(mesh, count, seed=int(rng.integers(1 << 30)))[0]


def test_root_frames_of_a_rigidly_moving_mesh_are_the_motion():
    """A mesh carried by a rigid motion, sampled at 240 Hz: every strand's root frame is that motion (pose, angular
    velocity, the velocity and acceleration of its origin, angular acceleration). The points are interpolated by
    cubic Hermite curves, not by the motion's own rule: between samples their velocities agree to O(h^2) (h ~ 1 ms
    here: 2e-4 rad/s at 4 ms, 3e-5 at 1 ms, measured), accelerations to O(h), which bounds the tolerances; the
    times avoid the motions' ramp ends, where the accelerations have kinks."""
    rng = np.random.default_rng(1)
    motion = hw.motion.Compose(hw.motion.Turn(amplitude_deg=40.0, period=1.0, start=0.0, ramp=0.2,
                                              pivot=(0.0, 0.0, 1.5)),
                               hw.motion.Nod(amplitude_deg=20.0, period=0.7, start=0.1, ramp=0.2,
                                             pivot=(0.0, 0.0, 1.5)))
    vertices, faces = _sphere()
    times = np.arange(0.0, 1.5 + 1e-9, 1.0 / 960.0)
    world = np.array([vertices @ m[:3, :3].T + m[:3, 3] for m in (motion.evaluate(t).matrix() for t in times)])
    roots = _roots_on(vertices, faces, 25, rng)
    binding = ScalpBinding(PointTrack(times, world), faces, roots, head_rest=motion.evaluate(0.0).matrix())
    assert np.abs(binding.offset).max() < 1e-12  # sampled on the surface: nothing to move
    for t in (0.45, 0.55, 0.9, 1.21):
        s = motion.evaluate(t)
        xforms, vel, acc = binding.root_frames(t)
        m = s.matrix()
        q = Rotation.from_quat(xforms[:, 3:]).as_matrix()
        np.testing.assert_allclose(q, np.broadcast_to(m[:3, :3], q.shape), atol=1e-5)
        np.testing.assert_allclose(xforms[:, :3], np.broadcast_to(m[:3, 3], (25, 3)), atol=2e-5)  # 1.6 m lever
        np.testing.assert_allclose(vel[:, :3], np.broadcast_to(s.angular_velocity, (25, 3)), atol=5e-4)
        np.testing.assert_allclose(vel[:, 3:], np.broadcast_to(s.linear_velocity, (25, 3)), atol=1e-3)
        scale_w = np.abs(s.angular_acceleration).max()  # 15-25 rad/s^2
        np.testing.assert_allclose(acc[:, :3], np.broadcast_to(s.angular_acceleration, (25, 3)), atol=0.01 * scale_w)
        scale_a = np.abs(s.linear_acceleration).max()  # 28-34 m/s^2
        np.testing.assert_allclose(acc[:, 3:], np.broadcast_to(s.linear_acceleration, (25, 3)), atol=0.01 * scale_a)


def test_roots_carried_by_the_head_ride_on_its_motion_not_the_scalps():
    """A scalp its stage turns one way while the head's motion (from elsewhere) nods: the roots carried by the head
    (``HeadCarriedRoots``) take the scalp's frames at time 0, the head's pose there, and follow the head's motion
    from it: every root frame is the head's pose, angular velocity and acceleration, and the velocity and
    acceleration of its origin (float64 throughout: to 1e-9), wherever the scalp has gone."""
    rng = np.random.default_rng(4)
    scalp = hw.motion.Turn(amplitude_deg=40.0, period=1.0, start=0.0, ramp=0.2, pivot=(0.0, 0.0, 1.5))
    head = hw.motion.Nod(amplitude_deg=20.0, period=0.7, start=0.1, ramp=0.2, pivot=(0.0, 0.0, 1.5))
    vertices, faces = _sphere()
    times = np.arange(0.0, 1.5 + 1e-9, 1.0 / 240.0)
    world = np.array([vertices @ m[:3, :3].T + m[:3, 3] for m in (scalp.evaluate(t).matrix() for t in times)])
    rest = head.evaluate(0.0).matrix()
    binding = ScalpBinding(PointTrack(times, world), faces, _roots_on(vertices, faces, 20, rng), head_rest=rest)
    assert binding.animated
    carried = HeadCarriedRoots(binding, rest)
    for t in (0.0, 0.45, 0.9, 1.21):
        s = head.evaluate(t)
        xforms, vel, acc = carried.root_frames(s)
        m = s.matrix()
        np.testing.assert_allclose(Rotation.from_quat(xforms[:, 3:]).as_matrix(), np.broadcast_to(m[:3, :3],
                                   (20, 3, 3)), atol=1e-9)
        np.testing.assert_allclose(xforms[:, :3], np.broadcast_to(m[:3, 3], (20, 3)), atol=1e-9)
        for got, want in ((vel[:, :3], s.angular_velocity), (vel[:, 3:], s.linear_velocity),
                          (acc[:, :3], s.angular_acceleration), (acc[:, 3:], s.linear_acceleration)):
            np.testing.assert_allclose(got, np.broadcast_to(want, (20, 3)), atol=1e-9)
    # where the scalp itself took them by then: its turn, not the nod
    moved = binding.root_frames(0.9)[0][:, :3] - carried.root_frames(head.evaluate(0.9))[0][:, :3]
    assert np.linalg.norm(moved, axis=1).max() > 0.05


def _wobbling_binding(seed: int) -> ScalpBinding:
    """30 roots on a sphere whose surface wobbles over 1 s (11 samples, up to 1 cm)."""
    rng = np.random.default_rng(seed)
    vertices, faces = _sphere()
    times = np.linspace(0.0, 1.0, 11)
    wobble = [vertices + 0.01 * np.sin(3.0 * t + 7.0 * vertices[:, [1, 2, 0]]) for t in times]
    return ScalpBinding(PointTrack(times, np.array(wobble)), faces, _roots_on(vertices, faces, 30, rng),
                        max_distance=0.02)


def test_root_frame_velocities_are_the_derivatives_of_the_frames():
    """On a deforming mesh, the returned angular and linear velocities equal central differences of the returned
    poses (float64; eps = 1e-5 s gives O(eps^2) truncation, well under the tolerance)."""
    binding = _wobbling_binding(2)
    eps = 1e-5
    for t in (0.25, 0.61):
        x, vel, _ = binding.root_frames(t)
        xm, _, _ = binding.root_frames(t - eps)
        xp, _, _ = binding.root_frames(t + eps)
        rot = Rotation.from_quat(xp[:, 3:]) * Rotation.from_quat(xm[:, 3:]).inv()
        np.testing.assert_allclose(vel[:, :3], rot.as_rotvec() / (2 * eps), atol=1e-5)
        np.testing.assert_allclose(vel[:, 3:], (xp[:, :3] - xm[:, :3]) / (2 * eps), atol=1e-5)
        # the bound points ride along: what the roots' velocity must be
        p = binding.root_points(t)
        v_root = vel[:, 3:] + np.cross(vel[:, :3], p - x[:, :3])
        np.testing.assert_allclose(v_root, (binding.root_points(t + eps) - binding.root_points(t - eps)) / (2 * eps),
                                   atol=1e-5)


def test_root_frames_of_many_times_at_once_are_each_times_own():
    """``root_frames_at`` (a runner's frame of steps in one pass) gives each time the bits ``root_frames`` gives it
    alone, whatever else is in the batch: a run resumed mid-frame takes its first step's frames alone and must repeat
    the uninterrupted run. And the angular accelerations are the derivative of the angular velocities (central
    differences of ``root_frames`` at +-1e-4 s, as it takes them)."""
    binding = _wobbling_binding(3)
    steps = [0.3 + k / 240.0 for k in range(8)]
    for batch in (steps, steps[::-1], steps[3:5]):
        for t, frames in zip(batch, binding.root_frames_at(batch), strict=True):
            for got, alone in zip(frames, binding.root_frames(t), strict=True):
                np.testing.assert_array_equal(got, alone)
        # without the accelerations (a runner's, which takes each step's mean): the same poses and velocities
        for t, (pose, velocity, none) in zip(batch, binding.root_frames_at(batch, accelerations=False), strict=True):
            alone = binding.root_frames(t)
            np.testing.assert_array_equal(pose, alone[0])
            np.testing.assert_array_equal(velocity, alone[1])
            assert none is None
    _, w_minus, _ = binding.root_frames(0.5 - 1e-4)
    _, w_plus, _ = binding.root_frames(0.5 + 1e-4)
    _, _, acc = binding.root_frames(0.5)
    # the same float64 differences, so only round-off is between them (1e-3 of a rate, 1e-6 rad/s^2 near zero); the
    # check is on the batch's layout: its two neighbours of each time taken the other way round flip the sign
    np.testing.assert_allclose(acc[:, :3], (w_plus[:, :3] - w_minus[:, :3]) / 2e-4, rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("interpolation", ["smooth", "monotone", "linear"])
def test_a_track_evaluated_at_many_times_gives_each_times_own_bits(interpolation):
    """``PointTrack.evaluate_many`` (the root frames' one pass over a frame's steps) gives each time the bits of
    ``evaluate`` alone, held at the first and the last key outside them; and the row-wise cross product it goes with
    gives ``np.cross``'s bits."""
    rng = np.random.default_rng(5)
    times = np.cumsum(rng.uniform(0.05, 0.2, 9))
    track = PointTrack(times, rng.normal(0.0, 0.01, (9, 40, 3)), interpolation)
    asked = np.concatenate([[times[0] - 0.1, times[0], times[-1], times[-1] + 1.0], times[2:5],
                            rng.uniform(times[0], times[-1], 12)])
    many = track.evaluate_many(asked)
    for k, t in enumerate(asked):
        for got, alone in zip(many, track.evaluate(t), strict=True):
            np.testing.assert_array_equal(got[k], alone)
    a, b = rng.normal(size=(2, 7, 5, 3))
    np.testing.assert_array_equal(cross_rows(a, b), np.cross(a, b))
    np.testing.assert_array_equal(cross_rows(a[0, 0], b), np.cross(a[0, 0], b))


def test_a_root_far_from_the_surface_is_named():
    vertices, faces = _sphere()
    roots = vertices[:3].copy()
    roots[1] *= 1.05  # 8 cm out
    with pytest.raises(SurfaceError, match="strand 1 lies"):
        ScalpBinding(PointTrack([0.0], vertices[None]), faces, roots)


def test_per_strand_frames_at_the_head_step_the_same_bits():
    """The default scene (links, hair contacts, the head collider: every stage that reads the roots' frame) on a
    turning head, once on the head and once with every strand's root frame set to the head's: the same bits."""
    from hairwarp.runner import Simulation

    scene = hw.Scene.load(SCENES / "long_hair.toml", overrides=["groom.count=40", "dense.count=0",
                                                               "head.motion.start=0.0"])
    plain, per_strand = Simulation(scene, threads=1), Simulation(scene, threads=1)
    G = per_strand.model.strand_count
    control = per_strand.model.control(root_frames=True)
    per_strand.stepper.control = control
    head_step = per_strand._before_step

    def before_step(t, ctl):
        head_step(t, ctl)
        ctl.set_root_frames(*(np.tile(a.numpy().astype(np.float64), (G, 1))
                              for a in (ctl.head_xform, ctl.head_velocity, ctl.head_acceleration)))

    per_strand._before_step = before_step
    for _ in range(8):
        plain.advance_frame()
        per_strand.advance_frame()
    a, b = plain.guide_curves(), per_strand.guide_curves()
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert np.abs(a[0] - plain.model.rest_vertex_positions.reshape(-1, 3)).max() > 0.01  # the hair did move


def _scalp_world(code: float):
    """The character's scalp in the world at a time code, from the generator and the head's authored ops (not
    from the readers): metres, Z up."""
    R = Rotation.from_euler("xyz", head_rotation_deg(code), degrees=True).as_matrix()
    stage_points = scalp_points(code) @ R.T + np.asarray(NECK_CM)
    return 0.01 * stage_points @ Y_TO_Z.T


@pytest.mark.parametrize("frames", [24])
def test_character_roots_stay_on_the_sliding_scalp(frames):
    """The shipped character scene: at every frame the guide roots lie on the scalp mesh within 1e-5 m (float32 at
    1.6 m), at the frames where the stage has a sample against the mesh built here from the generator, at the
    others against the binding's interpolated points; and the skin's slide takes the roots centimetres away from
    where the rigid head alone would carry them."""
    import trimesh

    from hairwarp.runner import Simulation

    scene = hw.Scene.load(SCENES / "character.toml", overrides=["dense.count=0", "groom.count=40"])
    sim = Simulation(scene)
    G, S = sim.model.strand_count, sim.model.seg_per_strand
    rest_roots = sim.model.rest_vertex_positions.reshape(G, S + 1, 3)[:, 0]
    _, counts, indices = scalp_rest_points()
    tris, at = [], 0
    for n in counts:  # fans, as a DCC splits polygons
        tris += [(indices[at], indices[at + k], indices[at + k + 1]) for k in range(1, n - 1)]
        at += n
    slide = 0.0
    for frame in range(1, frames + 1):
        sim.advance_frame()
        t = frame * sim.frame_dt
        roots = sim.guide_curves()[0].reshape(G, S + 1, 3)[:, 0].astype(np.float64)
        np.testing.assert_allclose(roots, sim.surface.root_points(t), atol=1e-5)
        code = frame  # the scene runs at the stage's 24 time codes per second
        if code % SCALP_STEP == 0:
            mesh = trimesh.Trimesh(vertices=_scalp_world(code), faces=np.asarray(tris), process=False)
            _, distance, _ = trimesh.proximity.closest_point(mesh, roots)
            assert distance.max() < 1e-5, (frame, distance.max())
        m = sim.head_matrix(t)
        slide = max(slide, float(np.abs(roots - (rest_roots @ m[:3, :3].T + m[:3, 3])).max()))
    assert slide > 0.005
    assert END >= frames


def test_surface_errors_through_the_cli(tmp_path):
    """A scene whose roots are far from its surface: one line naming the strand, rc 2, nothing written."""
    scene = tmp_path / "far.toml"
    scene.write_text((SCENES / "character.toml").read_text().replace(
        'scalp_center = [0.0, 0.0, 1.6]', 'scalp_center = [0.0, 0.0, 1.7]').replace(
        'file = "character.usda"', f'file = "{SCENES / "character.usda"}"'))
    out = tmp_path / "out" / "far.usdc"
    proc = subprocess.run([sys.executable, "-m", "hairwarp", "run", str(scene), "-o", str(out), "--frames", "2"],
                          capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "groom.surface" in lines[0] and "strand" in lines[0], proc.stderr
    assert not out.exists()
