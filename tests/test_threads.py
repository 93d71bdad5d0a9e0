"""The CPU executor (``hairwarp.executor``): partitions, private reductions, and caches that are the same bits for
any thread count, read back with usd-core against the one-thread run."""

from pathlib import Path

import numpy as np
import pytest
import warp as wp
from pxr import Usd

import hairwarp as hw
from hairwarp.executor import Executor, default_threads
from hairwarp.runner import simulate

SCENES = Path(__file__).resolve().parents[1] / "scenes"

# these tests run more threads than a 2-core machine has on purpose: the bits must not depend on the count
pytestmark = pytest.mark.filterwarnings("ignore:(sim.)?threads = [0-9]+ is more than the [0-9]+ cores:UserWarning")


@wp.kernel
def _scatter(tid_offset: int, target: wp.array(dtype=wp.int32), value: wp.array(dtype=float),
             acc: wp.array(dtype=float), flags: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    i = tid_offset + wp.tid()
    wp.atomic_add(acc, target[i], value[i])
    wp.atomic_or(flags, 0, 1 << (i % 7))
    wp.atomic_add(count, 0, 1)


@wp.struct
class _Scale:
    factor: float
    offset: wp.array(dtype=float)


@wp.kernel
def _scaled(tid_offset: int, scale: _Scale, x: wp.array(dtype=float), y: wp.array(dtype=float)):
    i = tid_offset + wp.tid()
    y[i] = scale.factor * x[i] + scale.offset[0]


def test_prepared_launches_follow_new_arguments_and_struct_fields():
    """A launch's packed chunks are kept for the next launch with the same arguments: another array, another number
    or a struct field set in between are all seen, on one thread and on several."""
    x = wp.array(np.arange(1000, dtype=np.float32), dtype=float)
    for threads in (1, 3):
        ex = Executor("cpu", threads, min_chunk=10)
        scale = _Scale()
        scale.factor = 2.0
        scale.offset = wp.array([1.0], dtype=float)
        y, z = wp.zeros(1000, dtype=float), wp.zeros(1000, dtype=float)
        ex.launch(_scaled, 1000, [scale, x], [y])
        np.testing.assert_array_equal(y.numpy(), 2.0 * x.numpy() + 1.0)
        ex.launch(_scaled, 1000, [scale, x], [z])  # another output array
        np.testing.assert_array_equal(z.numpy(), y.numpy())
        scale.factor = 3.0  # a field of the same struct
        scale.offset = wp.array([-1.0], dtype=float)
        ex.launch(_scaled, 1000, [scale, x], [y])
        np.testing.assert_array_equal(y.numpy(), 3.0 * x.numpy() - 1.0)
        ex.close()


@wp.kernel
def _shifted(tid_offset: int, shift: wp.vec3, factor: float, x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3)):
    i = tid_offset + wp.tid()
    y[i] = factor * x[i] + shift


def test_prepared_launches_key_numbers_by_value():
    """A prepared launch is found again by its arguments: arrays and vectors by identity, numbers by value (another
    float object of the same value, or the same value as an int, reuses it; another value is seen), a list given
    for a vector, which has no hash, too; every launch computes what its arguments ask."""
    x = wp.array(np.arange(300, dtype=np.float32).reshape(100, 3), dtype=wp.vec3)
    for threads in (1, 3):
        ex = Executor("cpu", threads, min_chunk=10)
        y = wp.zeros(100, dtype=wp.vec3)
        shift = wp.vec3(1.0, 2.0, 3.0)
        for vector, factor, packed in ((shift, 2.0, 1), (shift, float("2.0"), 1), (shift, 2.5, 2),
                                       (wp.vec3(1.0, 2.0, -3.0), 2.5, 3), ([4.0, 5.0, 6.0], 2.5, 4), (shift, 2, 4)):
            ex.launch(_shifted, 100, [vector, factor, x], [y])
            np.testing.assert_array_equal(y.numpy(), float(factor) * x.numpy() + np.asarray(vector, np.float32))
            assert len(ex._prepared) == packed
        ex.close()


def test_batch_runs_independent_launches_together():
    """Launches held in a batch run when it ends, with the results of launching them one by one."""
    x = wp.array(np.arange(5000, dtype=np.float32), dtype=float)
    scale = _Scale()
    scale.factor = 0.5
    scale.offset = wp.array([2.0], dtype=float)
    ex = Executor("cpu", 2, min_chunk=16)
    y, z = wp.zeros(5000, dtype=float), wp.zeros(5000, dtype=float)
    with ex.batch():
        ex.launch(_scaled, 5000, [scale, x], [y])
        ex.launch(_scaled, 5000, [scale, x], [z])
        assert not y.numpy().any() and not z.numpy().any()  # held until the block ends
    np.testing.assert_array_equal(y.numpy(), 0.5 * x.numpy() + 2.0)
    np.testing.assert_array_equal(z.numpy(), y.numpy())
    ex.close()


@wp.kernel
def _add_index(tid_offset: int, y: wp.array(dtype=float)):
    i = tid_offset + wp.tid()
    y[i] = y[i] * 0.5 + float(i % 13)


@wp.kernel
def _per_unit_sum(tid_offset: int, per: int, y: wp.array(dtype=float), out: wp.array(dtype=float)):
    u = tid_offset + wp.tid()
    acc = float(0.0)
    for k in range(per):
        acc += y[u * per + k]
    out[u] = acc


def test_chain_runs_each_chunk_through_every_launch_in_order():
    """Launches in a chain, one over the elements and one over their units, run chunk by chunk: the second reads
    what the first wrote for its own unit, and the result is numpy's, on 2, 3 and 8 threads. A launch the chain
    cannot take (explicit chunks) runs after what the chain holds, in launch order."""
    units, per = 203, 7
    x0 = np.random.default_rng(2).standard_normal(units * per).astype(np.float32)
    expect_y = x0 * np.float32(0.5) + (np.arange(units * per) % 13).astype(np.float32)
    expect_y = expect_y * np.float32(0.5) + (np.arange(units * per) % 13).astype(np.float32)
    for threads in (2, 3, 8):
        ex = Executor("cpu", threads, min_chunk=4)
        y = wp.array(x0, dtype=float)
        out = wp.zeros(units, dtype=float)
        with ex.chain(units, 4):
            ex.launch(_add_index, units * per, [], [y])
            ex.launch(_add_index, units * per, [], [y], chunks=[(0, units * per)])  # runs alone, second
            ex.launch(_per_unit_sum, units, [per, y], [out])
            assert not out.numpy().any()  # held until the block ends
        np.testing.assert_array_equal(y.numpy(), expect_y)
        sums = expect_y.reshape(units, per).astype(np.float64).sum(axis=1)
        # a float32 sum of 7 terms of size <= 15 against float64: round-off <= 7 * 2^-24 * 100, below 1e-4
        np.testing.assert_allclose(out.numpy(), sums, rtol=1e-5, atol=1e-4)
        with ex.batch(), ex.chain(units, 4), pytest.raises(ValueError, match="chain within a batch"):
            ex.launch(_add_index, units * per, [], [y], chunks=[(0, units * per)])
        ex.close()


@wp.kernel
def _slow_double(tid_offset: int, y: wp.array(dtype=float)):
    i = tid_offset + wp.tid()
    v = y[i]
    for _ in range(200000):  # long enough that a launch run beside it finishes first
        v = v * 1.0000001 + 1.0e-12
    y[i] = 2.0 * y[i] + (v - v)


@wp.kernel
def _add_one(tid_offset: int, y: wp.array(dtype=float)):
    i = tid_offset + wp.tid()
    y[i] = y[i] + 1.0


def test_chain_of_one_chunk_in_a_batch_keeps_its_order():
    """A chain too small to split (fewer units than a chunk) within a batch still runs its launches in order on one
    thread: run as separate launches of the batch, the second would read the array before the first wrote it."""
    for threads in (2, 3):
        ex = Executor("cpu", threads, min_chunk=16)
        y = wp.array(np.arange(8, dtype=np.float32), dtype=float)
        other = wp.zeros(8, dtype=float)
        with ex.batch():
            with ex.chain(8, 16):
                ex.launch(_slow_double, 8, [], [y])
                ex.launch(_add_one, 8, [], [y])
            ex.launch(_add_one, 8, [], [other])
        np.testing.assert_array_equal(y.numpy(), 2.0 * np.arange(8, dtype=np.float32) + 1.0)
        np.testing.assert_array_equal(other.numpy(), np.ones(8, dtype=np.float32))
        ex.close()


def test_small_scene_with_links_same_bits_on_two_threads():
    """The tiny scene with links (8 strands: every per-strand launch one chunk, run beside the other launches of its
    batch) gives the same guide points on 2 threads as on 1, run after run."""
    scene = hw.Scene.load(SCENES / "tiny.toml", overrides=["links.enabled=true", "output.preview=false",
                                                           "dense.count=0"])
    tips = []
    for threads in (1, 2, 2, 2):
        sim = hw.Simulation(scene, threads=threads)
        for _ in range(4):
            sim.advance_frame()
        tips.append(sim.guide_curves()[0])
    for x in tips[1:]:
        np.testing.assert_array_equal(x, tips[0])


def test_solvers_sharing_an_executor_step_as_each_alone():
    """A solver may run on another's executor (``Solver(executor=...)``): its steps are the same bits as on a pool of
    its own, both solvers stepping in turn on the one pool; a thread count as well, or an executor of another kind,
    is refused."""
    from hairwarp.solver import Solver

    model = hw.Model.build(hw.Groom.from_polylines(
        [np.stack([np.full(9, 0.01 * g), np.zeros(9), -np.linspace(0.0, 0.16, 9)], axis=1) for g in range(200)]),
        hw.StrandParams(), segments=8)
    first = Solver(model, threads=2)
    shared, own = Solver(model, executor=first.executor), Solver(model, threads=2)
    assert shared.executor is first.executor
    control = model.control()
    start = model.state()
    start.joint_qd.assign(np.random.default_rng(1).normal(0.0, 1.0, (model.seg_count, 3)).astype(np.float32))
    first.forward_kinematics(start, control)
    ends = {}
    for name, solver in (("first", first), ("shared", shared), ("own", own)):
        ends[name] = model.state()
        solver.step(start, ends[name], control, 1.0 / 240.0)
    for name in ("shared", "own"):
        for key in ("joint_q", "joint_qd", "vertex_positions"):
            np.testing.assert_array_equal(getattr(ends[name], key).numpy(), getattr(ends["first"], key).numpy())
    with pytest.raises(ValueError, match="not both"):
        Solver(model, threads=1, executor=first.executor)
    with pytest.raises(ValueError, match="Executor"):
        Solver(model, executor=object())


@pytest.mark.parametrize("capacity, chunk_slots", [(0, None), (500, None), (0, 64)])
def test_detection_on_threads_finds_the_contacts_of_one_thread_in_its_order(capacity, chunk_slots):
    """On several threads the trees are fitted and the contacts found as one set of tasks (the segment tree's
    contacts while the strip tree is still being fitted): the stored contacts, their per-segment lists and the
    fault bits are those of one thread, slot for slot; with too few slots (500 for about 900, not grown) the same
    ones are kept and both report the overflow. Each chunk of a launch appends to a buffer of its own: where one
    holds fewer pairs than its chunk finds (64 slots), it grows and the chunk is taken again, with no overflow."""
    scene = hw.Scene.load(SCENES / "long_hair.toml", overrides=[
        "groom.count=120", "output.preview=false", f"interactions.capacity={capacity}"])
    sims = {threads: hw.Simulation(scene, threads=threads) for threads in (1, 2, 3)}
    for sim in sims.values():
        sim.contacts.grows = False
        sim.contacts._chunk_slots = chunk_slots
        sim.advance_frame()
        sim.contacts.detect(sim.model, sim.state)
        assert (sim.contacts._overlapped_detection() is (sim.solver.executor.threads > 1))
    ref = sims[1].contacts
    found = int(ref.contact_counter.numpy()[0])
    assert found > 100
    assert bool(ref.contact_overflow.numpy()[0]) == bool(capacity)  # 500 slots are too few, the default enough
    assert found > ref.capacity if capacity else found < ref.capacity
    kept = min(found, ref.capacity)
    for threads in (2, 3):
        c = sims[threads].contacts
        assert int(c.contact_counter.numpy()[0]) == found
        for name in ("contact_kind", "contact_a", "contact_b", "contact_w", "contact_gap"):
            np.testing.assert_array_equal(getattr(c, name).numpy()[:kept], getattr(ref, name).numpy()[:kept],
                                          err_msg=f"{threads} threads: {name}")
        for name in ("seg_entry_start", "seg_entries", "contact_overflow"):
            np.testing.assert_array_equal(getattr(c, name).numpy(), getattr(ref, name).numpy(),
                                          err_msg=f"{threads} threads: {name}")
        np.testing.assert_array_equal(sims[threads].state.fault.numpy(), sims[1].state.fault.numpy())
        if chunk_slots is not None:
            assert c._chunk_slots > chunk_slots  # grown: some chunk found more than 64 pairs


def test_thread_counts_past_the_limit_are_refused_and_a_failed_pool_stops_its_threads(tmp_path, capsys,
                                                                                      monkeypatch):
    """More than ``MAX_THREADS`` is refused by the API, the scene and the command (exit 2, one line) before any
    thread starts; a pool the system cannot start stops the threads it started and says what to change."""
    import threading

    from hairwarp.cli import main
    from hairwarp.executor import MAX_THREADS
    from hairwarp.scene import SCHEMA, SceneError

    with pytest.raises(ValueError, match=f"in \\[0, {MAX_THREADS}\\]"):
        Executor("cpu", MAX_THREADS + 1)
    assert SCHEMA["sim"].fields["threads"].range == f"[0, {MAX_THREADS}]"
    with pytest.raises(SceneError, match="sim.threads"):
        hw.Scene.load(SCENES / "tiny.toml", overrides=[f"sim.threads={MAX_THREADS + 1}"])
    with pytest.raises(SystemExit) as stop:
        main(["run", str(SCENES / "tiny.toml"), "-o", str(tmp_path / "t.usdc"), "--threads", "99999"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and f"at most {MAX_THREADS}" in err and "Traceback" not in err
    assert not any(tmp_path.iterdir())

    before = threading.active_count()
    start, started = threading.Thread.start, []

    def start_three(thread):  # the system's limit, reached at the fourth thread
        if len(started) == 3:
            raise RuntimeError("can't start new thread")
        started.append(thread)
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", start_three)
    ex = Executor("cpu", 8, min_chunk=1)
    with pytest.raises(RuntimeError, match="could not start 8 CPU threads \\(4 started"):
        ex.launch(_add_one, 64, [], [wp.zeros(64, dtype=float)])
    monkeypatch.undo()
    for t in started:
        t.join(timeout=5.0)
    assert threading.active_count() == before


def test_pool_threads_sleep_when_idle_and_every_chunk_runs():
    """Between launches the pool's threads spin, then sleep (their state 0) once idle for ``SPIN_SECONDS``: an idle
    simulation gives its cores back. A launch wakes them again and every chunk runs once, whichever took it."""
    import time

    from hairwarp import executor as executor_module

    ex = Executor("cpu", 3, min_chunk=1)
    n = 4096
    count = wp.zeros(1, dtype=wp.int32)
    target = wp.array(np.arange(n, dtype=np.int32) % 5, dtype=wp.int32)
    value = wp.array(np.ones(n, dtype=np.float32), dtype=float)
    for _ in range(3):
        acc, flags = wp.zeros(5, dtype=float), wp.zeros(1, dtype=wp.int32)
        count.zero_()
        ex.launch(_scatter, n, [target, value], [acc, flags, count], chunks=Executor.fixed_chunks(n, 64),
                  private_sum=[2], private_or=[3], private_add=[4])
        assert count.numpy()[0] == n
        np.testing.assert_array_equal(acc.numpy(), np.bincount(np.arange(n) % 5))
        state = ex._workers.state
        deadline = time.monotonic() + 2.0 + 100 * executor_module.SPIN_SECONDS
        while state.any() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not state.any(), "pool threads still spinning long after the last launch"
    ex.close()


@wp.kernel
def _count(tid_offset: int, count: wp.array(dtype=wp.int32)):
    wp.atomic_add(count, 0, 1)


def test_back_to_back_tables_run_every_chunk_exactly_once():
    """Tiny launches back to back, each table larger than the last now and then, on two threads (one of them a pool
    thread spinning between tables): every chunk runs once and the launch returns after all of them. A pool thread
    that read the spent claim word of one table and the next table's larger count once claimed with the old word,
    ran a chunk twice and let the launch return early (about one launch in 50 here, before the leader sealed the
    word while it published a table). Counted per chunk in private counters, exact integers."""
    ex = Executor("cpu", 2, min_chunk=1)
    count = wp.zeros(1, dtype=wp.int32)
    view = count.numpy()
    wrong = []
    for i in range(20000):
        n = 2 + i % 7
        view[0] = 0
        ex.launch(_count, n, [], [count], chunks=Executor.fixed_chunks(n, n), private_add=[0])
        if view[0] != n:
            wrong.append((i, n, int(view[0])))
    ex.close()
    assert not wrong, f"{len(wrong)} of 20000 launches ran a chunk twice or returned early, e.g. {wrong[:3]}"


def test_zero_clears_host_views_and_arrays_outside_the_executor_cache():
    ex = Executor("cpu", 2)
    a = wp.array(np.arange(10, dtype=np.float32), dtype=float)
    b = wp.array(np.ones((4, 3), dtype=np.float32), dtype=wp.vec3)
    ex.zero(a, b)
    assert not a.numpy().any() and not b.numpy().any()
    a.assign(np.full(10, 3.0, dtype=np.float32))
    ex.zero(a)  # the kept view sees the new values
    assert not a.numpy().any()
    ex.close()


def test_partitions():
    ex = Executor("cpu", 3, min_chunk=10)
    assert ex.chunks(5) == [(0, 5)]  # below the break-even: one chunk
    assert ex.chunks(31) == [(0, 11), (11, 10), (21, 10)]
    # fixed chunks depend on the work alone
    assert Executor.fixed_chunks(10, 4) == [(0, 3), (3, 3), (6, 2), (8, 2)] == Executor("cpu", 1).fixed_chunks(10, 4)
    assert Executor("cpu", 0).threads == default_threads()
    assert Executor("cuda:0" if wp.is_cuda_available() else "cpu", 4).threads == (1 if wp.is_cuda_available() else 4)


def test_private_reductions_match_numpy():
    """A scatter into shared floats summed per fixed chunk in chunk order gives the same bits on 1, 2, 3 and 8
    threads; OR-ed bits and counted ints are exact; both against numpy."""
    rng = np.random.default_rng(1)
    n, m = 5000, 37
    target = wp.array(rng.integers(0, m, n).astype(np.int32), dtype=wp.int32)
    value = wp.array(rng.standard_normal(n).astype(np.float32), dtype=float)
    results = []
    for threads in (1, 2, 3, 8):
        ex = Executor("cpu", threads, min_chunk=1)
        acc = wp.zeros(m, dtype=float)
        flags = wp.zeros(1, dtype=wp.int32)
        count = wp.zeros(1, dtype=wp.int32)
        ex.launch(_scatter, n, [target, value], [acc, flags, count], chunks=Executor.fixed_chunks(n, 8),
                  private_sum=[2], private_or=[3], private_add=[4])
        assert flags.numpy()[0] == 127 and count.numpy()[0] == n
        results.append(acc.numpy())
    for r in results[1:]:
        np.testing.assert_array_equal(r, results[0])
    expect = np.zeros(m)
    np.add.at(expect, target.numpy(), value.numpy().astype(np.float64))
    np.testing.assert_allclose(results[0], expect, atol=1e-4)


def _samples(path) -> dict:
    """Every value of every attribute of a stage (time samples and defaults), read back by usd-core."""
    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            times = attr.GetTimeSamples()
            for t in times or [None]:
                value = attr.Get(t) if t is not None else attr.Get()
                if value is not None:
                    out[(str(attr.GetPath()), t)] = np.asarray(value)
    return out


@pytest.mark.parametrize("scene, overrides", [
    # the default scene: links, contacts detected once per frame, a head collider, dense hair pushed out
    ("long_hair.toml", ["groom.count=120", "dense.count=400"]),
    # a fast turn with links, contacts and colliders, contacts detected every step
    ("fast_turn.toml", ["groom.count=120", "interactions.detect=\"step\""]),
    # at 2 substeps: the links' and contacts' response after the free step (response = "auto")
    ("fast_turn.toml", ["groom.count=120", "sim.substeps=2"]),
])
def test_cache_same_bits_for_any_thread_count(tmp_path, scene, overrides):
    """The cache of a run is the same, array for array, on 1, 2, 3 and 8 threads (time samples compared, not file
    bytes: the layers carry no timestamps but usd-core may order a file's sections differently)."""
    base = hw.Scene.load(SCENES / scene, overrides=["sim.frames=5", "output.preview=false", *overrides])
    caches = {}
    for threads in (1, 2, 3, 8):
        s = base.with_overrides([f"sim.threads={threads}"])
        result = simulate(s, tmp_path / f"t{threads}" / "cache.usdc", progress=False)
        caches[threads] = _samples(result.cache_path)
        if threads == 1:
            stats = result.frame_stats
    ref = caches[1]
    assert any(k[0].endswith(".points") for k in ref)
    assert any(int(f.get("contacts") or 0) > 0 for f in stats), "the run found no hair contacts to test"
    for threads in (2, 3, 8):
        assert caches[threads].keys() == ref.keys()
        for key, value in ref.items():
            np.testing.assert_array_equal(caches[threads][key], value, err_msg=f"{threads} threads: {key}")


def test_frames_taken_again_are_the_same_bits_for_any_thread_count():
    """``long_hair_shoulders`` with limp hair at one step a frame takes the frames in which links break again at
    ``links.break_step`` (``hairwarp.runner.Simulation.advance_frame``): which frames, and their results, are the same
    on 1 and 3 threads."""
    from hairwarp.runner import Simulation

    runs = {}
    for threads in (1, 3):
        sim = Simulation(hw.Scene.load(SCENES / "long_hair_shoulders.toml", overrides=[
            "sim.substeps=1", "dense.count=0", "output.preview=false", "strands.bend_stiffness=1e-6",
            f"sim.threads={threads}"]))
        taken = []
        for frame in range(1, 13):
            before = sim.refined_frames
            sim.advance_frame()
            if sim.refined_frames > before:
                taken.append(frame)
        runs[threads] = taken, sim.checkpoint()
    taken, ref = runs[1]
    assert taken, "no frame was taken again: the test needs one"
    assert runs[3][0] == taken
    for key, value in ref.items():
        np.testing.assert_array_equal(runs[3][1][key], value, err_msg=key)
