"""A groom held as drawn (``groom.hold_shape``, ``Model.build(hold_shape=True)``): the rest bends that make the drawn
shape the strands' equilibrium under gravity, against Pinocchio's gravity torques, and the simulator holding it."""

import math
import warnings
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from _reference import chain_model, joint_torques
from conftest import require_ratboy
from scipy.spatial.transform import Rotation

from hairwarp.model import MAX_REST_BEND, Model, StrandParams, gravity_stiffness
from hairwarp.runner import Simulation
from hairwarp.scene import Scene
from hairwarp.solver import Solver

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def curled_strands(S=12):
    """Three strands drawn in 3D: a helix hanging sideways, a strand standing up and bending over, an S curve; their
    segments of unequal length."""
    t = np.linspace(0.0, 1.0, S + 1)
    helix = np.stack([0.03 * np.cos(6.0 * t) + 0.12 * t, 0.03 * np.sin(6.0 * t), -0.1 * t**1.3], axis=1)
    spike = np.stack([0.08 * t**2, 0.01 * t, 0.15 * np.sin(2.0 * t)], axis=1)
    wave = np.stack([0.2 * t, 0.02 * np.sin(9.0 * t), -0.05 * t - 0.02 * np.sin(5.0 * t)], axis=1)
    return np.stack([helix, spike + [0.05, 0.0, 0.0], wave + [0.0, 0.05, 0.0]])


def spring_torques(model, strand):
    """Each joint's spring torque (S, 3) at the model's initial pose, -K log(q_rest^-1 q0), in float64."""
    S = model.seg_per_strand
    part = slice(strand * S, (strand + 1) * S)
    q0 = model.joint_q0.numpy()[part].astype(float)
    rest = model.joint_rest_q.numpy()[part].astype(float)
    K = model.joint_stiffness.numpy()[part].astype(float)
    return joint_torques(q0, np.zeros((S, 3)), rest, K, np.zeros((S, 3)))


@pytest.mark.parametrize("root_scale", [1.0, 4.0])
def test_held_rest_bends_balance_the_weight_by_pinocchio(device, root_scale):
    # At the drawn pose every joint's spring must give the generalised force that holds the chain still, which is
    # Pinocchio's gravity term g(q) (M qdd + C qd + g = tau at qd = qdd = 0), in float64 from our own geometry.
    # The rest rotations are stored in float32: about 6e-8 in a quaternion, 1.2e-7 rad in a bend, times K (at most
    # 0.1 N m/rad here) is about 1e-8 N m against torques of 1e-4 to 1e-2 N m; the bound is 1e-5 of the largest.
    params = StrandParams(bend_stiffness=2e-4, root_stiffness_scale=root_scale)
    held = Model.build(curled_strands(), params, segments=12, device=device, hold_shape=True)
    free = Model.build(curled_strands(), params, segments=12, device=device)
    S = held.seg_per_strand
    for g in range(held.strand_count):
        part = slice(g * S, (g + 1) * S)
        pm = chain_model(held.seg_length.numpy()[part].astype(float), held.seg_mass.numpy()[part].astype(float),
                         held.seg_inertia.numpy()[part].astype(float), held.strand_root_pos.numpy()[g].astype(float))
        q = held.joint_q0.numpy()[part].astype(float).reshape(-1)
        weight = pin.computeGeneralizedGravity(pm, pm.createData(), q).reshape(S, 3)
        scale = np.abs(weight).max()
        assert scale > 1e-4  # the strands are loaded: their joints carry 1e-4 N m or more
        np.testing.assert_allclose(spring_torques(held, g), weight, rtol=0.0, atol=1e-5 * scale)
        # drawn as the unloaded rest, the springs give nothing at the drawn pose
        assert np.abs(spring_torques(free, g)).max() < 1e-6 * scale


def settle(scene_name, overrides, frames):
    """Vertex positions (G, S+1, 3) after each of ``frames`` frames with the head still, and the drawn ones."""
    sim = Simulation(Scene.load(SCENES / f"{scene_name}.toml", ['head.motion.kind="still"', *overrides]))
    S = sim.model.seg_per_strand
    out = []
    for _ in range(frames):
        sim.advance_frame()
        out.append(sim.stepper.state.vertex_positions.numpy().reshape(-1, S + 1, 3).copy())
    return np.array(out), sim.model.rest_vertex_positions, sim


def test_a_held_groom_stays_as_drawn_with_the_head_still():
    # The simulator's own equilibrium is the drawn shape: 1 s with the head still and its collider on, every vertex
    # within 20 um of where it was drawn (float32 forward kinematics of 1.6 m coordinates, 1.2e-7 m apart, summed
    # over its 8 segments, gives a few um), where the unheld groom sags by centimetres.
    held, drawn, _ = settle("tiny", ["groom.hold_shape=true"], 30)
    sag, _, _ = settle("tiny", [], 30)
    assert np.linalg.norm(held - drawn, axis=3).max() < 2e-5
    assert np.linalg.norm(sag[-1, :, -1] - drawn[:, -1], axis=1).max() > 0.01


def test_a_groom_is_held_at_the_heads_first_pose():
    # A head that starts tilted 60 deg about x (and stays so) sees gravity tilted in its frame: the shape is held
    # for that pose, within the same 20 um, where bends made for the upright head let the hair move by millimetres.
    tilted = ['head.motion.kind="keyframes"', "head.motion.keys=[{time = 0.0, rotate_deg = [60.0, 0.0, 0.0]}, "
              "{time = 5.0, rotate_deg = [60.0, 0.0, 0.0]}]", "groom.hold_shape=true"]
    sim = Simulation(Scene.load(SCENES / "tiny.toml", tilted))
    pose = sim.motion.evaluate(0.0)
    R = Rotation.from_quat(pose.rotation).as_matrix()
    assert abs(math.degrees(math.acos((np.trace(R) - 1) / 2)) - 60.0) < 1e-6
    S = sim.model.seg_per_strand
    drawn = sim.model.rest_vertex_positions @ R.T + pose.position
    for _ in range(30):
        sim.advance_frame()
    held = sim.stepper.state.vertex_positions.numpy().reshape(-1, S + 1, 3)
    assert np.linalg.norm(held - drawn, axis=2).max() < 2e-5
    upright = Model.build(sim.model.rest_vertex_positions, sim.model.params, segments=S, hold_shape=True)
    assert np.abs(upright.joint_rest_q.numpy() - sim.model.joint_rest_q.numpy()).max() > 1e-3
    # one rotation per strand (roots on a scalp mesh, each on its own frame) as the same for all; matrices as
    # quaternions; a wrong shape named
    G = sim.model.strand_count
    for rotation in (np.tile(pose.rotation, (G, 1)), R, np.tile(R, (G, 1, 1))):
        each = Model.build(sim.model.rest_vertex_positions, sim.model.params, segments=S, hold_shape=True,
                           hold_rotation=rotation)
        np.testing.assert_allclose(each.joint_rest_q.numpy(), sim.model.joint_rest_q.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match=r"hold_rotation must be .* got shape \(2, 4\)"):
        Model.build(sim.model.rest_vertex_positions, sim.model.params, segments=S, hold_shape=True,
                    hold_rotation=np.tile(pose.rotation, (2, 1)))


def test_a_strand_too_limp_to_hold_its_shape_is_named_and_bounded(device):
    # EI 1e-8 would need rest bends of many radians: the model warns, names a strand and keeps each bend within
    # MAX_REST_BEND, past which the springs' law turns back.
    params = StrandParams(bend_stiffness=1e-8)
    with pytest.warns(UserWarning, match=r"hold_shape: 3 of 3 strands are too limp .* \(first: strand 0;"):
        model = Model.build(curled_strands(), params, segments=12, device=device, hold_shape=True)
    for g in range(model.strand_count):
        bend = np.linalg.norm(spring_torques(model, g) / model.joint_stiffness.numpy()[g * 12:(g + 1) * 12], axis=1)
        assert bend.max() <= MAX_REST_BEND * (1 + 1e-6) and bend.max() > 0.9 * MAX_REST_BEND
    # a strand drawn in 3D puts part of its weight about its segments' own axes: without twist stiffness nothing
    # there can hold it
    with pytest.warns(UserWarning, match=r"hold_shape: 3 of 3 strands .* or one about an axis without stiffness"):
        Model.build(curled_strands(), StrandParams(twist_stiffness=0.0), segments=12, device=device, hold_shape=True)
    with pytest.raises(ValueError, match="hold_shape .* rest_vertices"):
        Model.build(curled_strands(), params, segments=12, device=device, hold_shape=True,
                    rest_vertices=curled_strands())


def test_the_mohawk_held_as_drawn_keeps_its_links_with_the_head_still():
    # The Ratboy mohawk drawn as the unloaded rest sags 4 cm at its tips in its first frames and stretches a link to
    # 19.8 mm of its 30 mm break length by frame 8 with the head still (23 mm while its hair contacts were solved in
    # the free step; 4 broke when every link had the same stiffness); held as drawn, it moves by under 0.1 mm and
    # keeps every link slack.
    require_ratboy("Ratboy_mohawk.tfx")
    require_ratboy("Ratboy_body.tfxmesh")
    for hold in (True, False):
        x, drawn, sim = settle("ratboy_mohawk", [f"groom.hold_shape={str(hold).lower()}"], 8)
        links, solver = sim.links, sim.solver
        assert links.response  # its force pass then leaves each link's ends, and applies no force
        links.apply_forces(sim.model, sim.stepper.state, solver.dt, solver.seg_force, solver.seg_torque)
        stretch = np.linalg.norm(links.link_point_b.numpy() - links.link_point_a.numpy(), axis=1).max()
        tips = math.sqrt((np.linalg.norm(x[-1, :, -1] - drawn[:, -1], axis=1) ** 2).mean())
        if hold:
            assert links.broken_count() == 0 and stretch < 1e-4
            assert np.linalg.norm(x[-1] - drawn, axis=2).max() < 1e-4
        else:
            assert stretch > 0.5 * links.break_length and tips > 0.02


def test_the_weights_stiffness_is_pinocchios_gravity_derivative(device):
    # How the weight's torques change as the joints turn, which decides whether a held shape stands: against
    # Pinocchio's derivative of its gravity term (dg/dq, g = -tau), float64 from our float32 geometry; the bound
    # is 1e-6 of the largest entry (the geometry's float32 rounding, 1e-7, times lever sums).
    model = Model.build(curled_strands(), StrandParams(), segments=12, device=device)
    S = model.seg_per_strand
    mass = model.seg_mass.numpy().astype(float).reshape(-1, S)
    ours = gravity_stiffness(model.rest_vertex_positions, mass, (0.0, 0.0, -9.81))
    for g in range(model.strand_count):
        part = slice(g * S, (g + 1) * S)
        pm = chain_model(model.seg_length.numpy()[part].astype(float), mass[g],
                         model.seg_inertia.numpy()[part].astype(float), model.strand_root_pos.numpy()[g].astype(float))
        dg = pin.computeGeneralizedGravityDerivatives(pm, pm.createData(), model.joint_q0.numpy()[part].astype(float)
                                                     .reshape(-1))
        np.testing.assert_allclose(ours[g], -dg, rtol=0.0, atol=1e-6 * np.abs(dg).max())


def test_a_standing_strand_taller_than_greenhills_height_is_named_and_falls(device):
    # A straight heavy column clamped upright stands when shorter than Greenhill's height (7.837 EI / (rho A g))^(1/3)
    # (from the first root of J_{-1/3}; Timoshenko & Gere, Theory of Elastic Stability) and buckles when taller. The
    # model names the strands at 1.03 times that height as unstable and keeps those at 0.97 (40 segments: the
    # discrete chain's threshold lies within 3 %). Pushed at 0.5 mm/s and let go for 2 s, a strand at 0.8 times the
    # height stands within 0.1 mm, one at 1.5 times falls past 1 cm.
    EI, S = 2e-4, 40
    params = StrandParams(bend_stiffness=EI, damping=0.0)
    height = (7.837 * EI / (params.density * math.pi * params.radius**2 * 9.81)) ** (1.0 / 3.0)
    factors = (0.97, 1.03, 0.8, 1.5)
    verts = np.zeros((len(factors), S + 1, 3))
    for g, f in enumerate(factors):
        verts[g, :, 0] = 0.05 * g
        verts[g, :, 2] = np.linspace(0.0, f * height, S + 1)
    model = Model.build(verts, params, segments=S, device=device, hold_shape=True)
    assert model.hold_unstable.tolist() == [False, True, False, True]
    solver = Solver(model, "implicit_joints")
    s0, s1, control = model.state(), model.state(), model.control()
    push = np.zeros((len(factors) * S, 3))
    push[S - 1::S, 0] = 1e-3 / (0.05 * height)  # the tip segments turning: 0.5 mm/s at the tips
    s0.joint_qd.assign(push.astype(np.float32))
    for _ in range(480):
        solver.step(s0, s1, control, 1.0 / 240.0)
        s0, s1 = s1, s0
    tips = s0.vertex_positions.numpy().reshape(len(factors), S + 1, 3)[:, -1]
    moved = np.linalg.norm(tips - verts[:, -1], axis=1)
    assert moved[2] < 1e-4 and moved[3] > 0.01, moved


def test_a_run_names_the_held_strands_that_would_fall_unless_links_tie_them(tmp_path):
    # long_hair at half its stiffness, held as drawn: some of its strands buckle from the drawn shape under their
    # weight alone, which the run says in one warning naming a strand; with the scene's links tying them no warning
    # is given (the model still lists them), and at its own stiffness none of these 120 is unstable.
    soft = ["groom.hold_shape=true", "strands.bend_stiffness=1e-4", "groom.count=120"]
    with pytest.warns(UserWarning, match=r"groom.hold_shape: \d+ of 120 strands cannot stand as drawn \(first: strand "
                                         r"\d+\): too soft for their weight"):
        alone = Simulation(Scene.load(SCENES / "long_hair.toml", [*soft, "links.enabled=false"]))
    assert alone.model.hold_unstable.sum() > 5
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="groom.hold_shape")
        tied = Simulation(Scene.load(SCENES / "long_hair.toml", soft))
        stiff = Simulation(Scene.load(SCENES / "long_hair.toml", ["groom.hold_shape=true", "groom.count=120",
                                                                  "links.enabled=false"]))
    assert tied.model.hold_unstable.sum() == alone.model.hold_unstable.sum()
    assert not stiff.model.hold_unstable.any()
    # with links the run's notes say it instead (``hairwarp run`` prints them after its summary)
    from hairwarp.runner import simulate

    result = simulate(Scene.load(SCENES / "long_hair.toml", [*soft, "dense.count=0", "output.preview=false"]),
                      tmp_path / "tied.usdc", frames=1, progress=False)
    count = int(tied.model.hold_unstable.sum())
    assert (f"groom.hold_shape: {count} of 120 guides would buckle from their drawn shape on their own springs; only "
            f"their links hold them up") in result.notes
