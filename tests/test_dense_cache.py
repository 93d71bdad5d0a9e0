"""The production cache: the default scene with 20,000 dense strands, simulated and written to USD, read back with
usd-core. Independent checks: pxr's own reading of every attribute, raw sizes of float32 arrays, the compliance
checker, and the dense curves recomputed from the guides read back from the file."""

from pathlib import Path

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom
from test_usd import _validation_errors

import hairwarp
from hairwarp.io.cache import cache_bytes
from hairwarp.runner import Simulation, simulate

DENSE_COUNT = 20_000
FRAMES = 3  # frames simulated after the first: FRAMES + 1 time samples
# Bytes per frame beyond the raw float32 points and velocities of both prims (24 bytes a vertex): the extents,
# the crate's per-sample bookkeeping and the static topology and widths spread over the frames (measured:
# 39.04 MB a frame for 39.03 MB of raw arrays, 37.2 MiB).
OVERHEAD = 0.01
# The dense curves recomputed from the guides read back from the file: the same float32 kernels on the same
# float32 inputs, so equal up to the head pose's float32 round trip.
DENSE_TOL = 1e-6


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    scene = hairwarp.Scene.default().with_overrides(
        [f"dense.count={DENSE_COUNT}", "dense.basis=linear", f"sim.frames={FRAMES}", "output.preview=false"])
    path = tmp_path_factory.mktemp("cache") / "long_hair.usdc"
    result = simulate(scene, path, progress=False)
    return scene, path, result


def test_one_time_sample_per_frame_counts_velocities_and_extent(cache):
    scene, path, result = cache
    assert result.frames == FRAMES and result.preview_path is None
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == scene.sim.fps
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES)
    frames = [float(f) for f in range(FRAMES + 1)]
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/hair"))
    guides = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    assert hair and guides
    points_per_curve = scene.dense.samples_per_segment * scene.sim.segments + 1
    hair_counts = np.asarray(hair.GetCurveVertexCountsAttr().Get())
    assert hair_counts.shape == (DENSE_COUNT,) and np.all(hair_counts == points_per_curve)
    assert hair.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    guide_counts = np.asarray(guides.GetCurveVertexCountsAttr().Get())
    assert np.all(guide_counts == scene.sim.segments + 1) and 250 <= len(guide_counts) <= 350
    assert guides.GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    raw = 0
    for prim, n in ((hair, int(hair_counts.sum())), (guides, int(guide_counts.sum()))):
        for attr in (prim.GetPointsAttr(), prim.GetVelocitiesAttr(), prim.GetExtentAttr()):
            assert attr.GetTimeSamples() == frames, attr.GetPath()
        for f in (frames[0], frames[-1]):
            p = np.asarray(prim.GetPointsAttr().Get(f))
            v = np.asarray(prim.GetVelocitiesAttr().Get(f))
            assert p.shape == v.shape == (n, 3) and p.dtype == v.dtype == np.float32
            assert np.all(np.isfinite(p)) and np.all(np.isfinite(v))
            lo, hi = np.asarray(prim.GetExtentAttr().Get(f))
            half = 0.5 * np.asarray(prim.GetWidthsAttr().Get()).max()
            np.testing.assert_allclose(lo, p.min(axis=0) - half, atol=1e-6)
            np.testing.assert_allclose(hi, p.max(axis=0) + half, atol=1e-6)
        raw += 2 * 12 * n
    # The hair settles under gravity over these frames (the head starts turning at 0.2 s): velocities not all zero.
    assert np.abs(np.asarray(hair.GetVelocitiesAttr().Get(frames[-1]))).max() > 0.0
    size = cache_bytes(path)
    per_frame = size / len(frames)
    assert raw <= per_frame <= (1.0 + OVERHEAD) * raw + 1e6 / len(frames), (per_frame, raw)


def test_cache_passes_the_compliance_checker(cache):
    assert _validation_errors(cache[1]) == []


def test_dense_curves_are_the_guides_read_back_interpolated(cache):
    """The dense curves at the last frame are DenseHair.evaluate of the guide points and velocities in the file
    at the head pose of that frame (with or without the push-out from the head collider)."""
    scene, path, _ = cache
    stage = Usd.Stage.Open(str(path))
    t = float(FRAMES)
    guides = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    hair = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/hair"))
    sim = Simulation(scene)
    control = sim.stepper.control
    control.set_motion(sim.motion.evaluate(t * sim.frame_dt))
    gx = wp.array(np.asarray(guides.GetPointsAttr().Get(t)), dtype=wp.vec3, device=sim.model.device)
    gv = wp.array(np.asarray(guides.GetVelocitiesAttr().Get(t)), dtype=wp.vec3, device=sim.model.device)
    cached_p = np.asarray(hair.GetPointsAttr().Get(t))
    cached_v = np.asarray(hair.GetVelocitiesAttr().Get(t))
    matches = []
    for colliders in (None, sim.collider_set):
        p, v = sim.dense.evaluate(gx, gv, control.head_xform, control.head_velocity, colliders=colliders)
        matches.append(np.allclose(p.numpy(), cached_p, rtol=0, atol=DENSE_TOL)
                       and np.allclose(v.numpy(), cached_v, rtol=0, atol=DENSE_TOL))
    assert any(matches)


def test_inline_and_background_writers_write_the_same_run(tmp_path):
    """``output.writer``: the tiny scene simulated twice on the CPU (deterministic), once per writer; usd-core reads
    back the same samples, exactly."""
    from test_usd import _assert_same_stage

    paths = {}
    for writer in ("inline", "background"):
        scene = hairwarp.Scene.load(Path(__file__).parents[1] / "scenes" / "tiny.toml").with_overrides(
            ["sim.frames=3", "output.preview=false", f"output.writer={writer}", "dense.count=200"])
        paths[writer] = simulate(scene, tmp_path / f"{writer}.usdc", progress=False).cache_path
    _assert_same_stage(paths["inline"], paths["background"])
