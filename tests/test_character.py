"""A character from USD: the head's motion read from a stage, and the shipped character scene on it."""

from pathlib import Path

import numpy as np
from _character import END, NECK_CM, head_rotation_deg, write_character_stage
from scipy.spatial.transform import Rotation

import hairwarp as hw

SCENES = Path(__file__).resolve().parents[1] / "scenes"
# Y up in cm to Z up in m: (x, y, z) -> 0.01 (x, -z, y)
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def test_head_motion_equals_the_stage_at_every_sample(tmp_path):
    """The head frame at each time sample is the prim's world pose (from its authored ops, converted to metres Z up
    here, independently of the reader) relative to its first sample."""
    from hairwarp.io.usd_anim import head_motion_from_usd

    path = tmp_path / "character.usda"
    write_character_stage(path)
    motion = head_motion_from_usd(path, "/Character/Head")
    neck = 0.01 * Y_TO_Z @ np.asarray(NECK_CM)
    for code in range(0, END + 1, 2):
        R = Y_TO_Z @ Rotation.from_euler("xyz", head_rotation_deg(code), degrees=True).as_matrix() @ Y_TO_Z.T
        expect = np.eye(4)  # about the neck: T(neck) R T(-neck), the first sample being the identity
        expect[:3, :3] = R
        expect[:3, 3] = neck - R @ neck
        # float64 throughout; the stage stores the angles as float32 (7 digits)
        np.testing.assert_allclose(motion.evaluate(code / 24.0).matrix(), expect, atol=1e-6)


def test_skeleton_head_joint_moves_as_the_head_prim(tmp_path):
    """The stage's skeleton carries the same head motion on its Head joint (a SkelAnimation's rotations instead of
    a rotateXYZ op): both sources give the same world poses and the same head motion."""
    from hairwarp.io.usd_anim import head_motion_from_usd, read_prim_motion

    path = tmp_path / "character.usda"
    write_character_stage(path)
    times, prim_poses = read_prim_motion(path, "/Character/Head")
    joint_times, joint_poses = read_prim_motion(path, "/Character/Rig/Skel", "Head")
    np.testing.assert_array_equal(joint_times, times)
    # Both are read at every frame of the stage; at the authored samples (every second frame) float32 angles on one
    # side and float32 quaternions on the other agree to 1e-7 of a rotation at 1.5 m. Between them USD interpolates
    # the prim's Euler angles linearly and the joint's rotations by slerp: 1.8e-6 m apart at most here.
    authored = np.round(times * 24.0) % 2 == 0
    np.testing.assert_allclose(joint_poses[authored], prim_poses[authored], rtol=0, atol=1e-6)
    np.testing.assert_allclose(joint_poses, prim_poses, rtol=0, atol=5e-6)
    by_prim = head_motion_from_usd(path, "/Character/Head")
    by_joint = head_motion_from_usd(path, "/Character/Rig/Skel", joint="Hips/Spine/Neck/Head")
    # the shipped scene on the joint instead of the prim
    on_joint = hw.Scene.load(SCENES / "character.toml", overrides=["head.motion.prim='/Character/Rig/Skel'",
                                                                   "head.motion.joint='Head'"]).head_motion()
    for t in np.linspace(0.0, END / 24.0, 145):  # between samples as above
        np.testing.assert_allclose(by_joint.evaluate(t).matrix(), by_prim.evaluate(t).matrix(), rtol=0, atol=5e-6)
        np.testing.assert_allclose(on_joint.evaluate(t).matrix(), by_prim.evaluate(t).matrix(), rtol=0, atol=5e-6)


def test_shipped_character_stage_is_the_generated_one(tmp_path):
    """scenes/character.usda is what tests/_character.py writes (so the scene's input is reproducible)."""
    from pxr import Usd

    path = tmp_path / "character.usda"
    write_character_stage(path)
    shipped = Usd.Stage.Open(str(SCENES / "character.usda"))
    made = Usd.Stage.Open(str(path))
    for prim in made.Traverse():
        other = shipped.GetPrimAtPath(prim.GetPath())
        assert other.IsValid(), prim.GetPath()
        for attr in prim.GetAttributes():
            theirs = other.GetAttribute(attr.GetName())
            assert attr.GetTimeSamples() == theirs.GetTimeSamples()
            for t in attr.GetTimeSamples() or [Usd.TimeCode.Default()]:
                assert attr.Get(t) == theirs.Get(t), (attr.GetPath(), t)


def test_a_head_motion_that_leaves_the_scalp_behind_carries_the_roots():
    """The character's roots ride on its scalp mesh as the stage animates it. Held still by an override of the head's
    motion, the head and its collider stop while the scalp goes on turning (up to 40 degrees in the first second):
    the roots then ride on the head from the scalp's first pose, so over 0.5 s they stay where they were (float32
    forward kinematics: 1e-6 m), where on the scalp they moved by centimetres, and the run says so in one warning
    naming the key; as shipped, head and scalp move together and nothing is said."""
    import warnings

    over = ["dense.count=0", "output.preview=false"]
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*groom.surface")
        shipped = hw.Simulation(hw.Scene.load(SCENES / "character.toml", over))
    assert shipped.surface is not None
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        still = hw.Simulation(hw.Scene.load(SCENES / "character.toml", [*over, 'head.motion.kind="still"']))
    named = [str(w.message) for w in seen if "groom.surface" in str(w.message)]
    assert len(named) == 1 and "/Character/Head/Scalp" in named[0] and "head.motion (still)" in named[0], named
    S = still.model.seg_per_strand
    roots = lambda sim: sim.stepper.state.vertex_positions.numpy().reshape(-1, S + 1, 3)[:, 0].astype(float)  # noqa: E731
    start = roots(still)
    for _ in range(15):
        still.advance_frame()
    assert np.abs(roots(still) - start).max() < 1e-6
    scalp = still.surface.root_points(0.5) - still.surface.root_points(0.0)
    assert np.linalg.norm(scalp, axis=1).max() > 0.01  # where the scalp took them
