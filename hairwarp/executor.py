"""CPU executor: one Warp launch split into chunks run on a pool of OS threads.

Warp runs a CPU launch on one thread, and its CPU ``atomic_add`` / ``atomic_or`` are plain read-modify-writes.
A launch of a kernel that takes ``tid_offset: int`` as its first parameter (its thread ``i`` works on element
``tid_offset + i``) can instead run as several launches of consecutive ranges, one after the other on whichever
pool thread is free; Warp's CPU kernels run without the GIL, so the chunks run at once. On CUDA it is one launch.

Results never depend on the thread count:

- a kernel whose every element is written by one thread only (a strand, a segment, a dense vertex) gives the same
  bits whatever its range, so such launches are split into a few ranges per thread (no smaller than ``min_chunk``
  elements, below which a chunk costs more to hand to a thread than it runs), taken by the threads as they come
  free, which evens out strands of unequal cost;
- small integer arrays that threads OR or add into (fault bits, counters) are given to each chunk as a private
  zeroed copy and folded into the real array after the chunks join (integer OR and sums are exact, so the order
  does not matter): ``private_or`` and ``private_add``;
- stages that scatter floats into shared arrays either gather instead (each element sums its own terms in a fixed
  order: the links and the hair contacts, ``hairwarp.interactions``), or use :meth:`Executor.fixed_chunks`, a
  partition fixed by the work size alone, accumulate per chunk and reduce in chunk order (``private_sum``); stages
  that append to a buffer take per-chunk buffers concatenated in chunk order (``HairContacts``), which is the order
  of one whole launch.

Launches that each write only their own elements and read, of what an earlier one wrote, only the same elements
(a strand's forces, then its integration, then its push-out) can run as a *chain* (:meth:`Executor.chain`): every
chunk runs all of them in turn on one thread, one wake of the threads for the lot instead of one per launch. The
chunks are ranges of a unit the launches share (strands), so a per-segment launch's chunk holds the segments of
the strands its integration's chunk holds.

The chunks run in native code (``kernels.chunks``): the calling thread publishes a launch's chunks as a table and
runs them with the pool's threads, each of which takes chunks until none is left, without the GIL. Between tables
the pool's threads spin for :data:`SPIN_SECONDS` before they sleep, so the launches of a step find them awake:
a parallel launch costs the caller about what one plain launch does, not a thread's wake-up.

A launch's arguments are packed once: the chunks' argument blocks are kept, keyed by the kernel, the size and the
identity of every argument (the value of a number), and the next launch with the same arguments only calls the
kernel. Warp structs are passed by their live ctypes, compared at every launch with what the chunks' blocks hold and
copied into them when a field has changed since, so a changed field is seen.

A captured Warp graph replays its launches on one thread, so ``hairwarp.Stepper`` does not capture on the CPU
when the executor has more than one thread.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import threading
import time
import weakref

import numpy as np
import warp as wp
from warp._src.codegen import Struct as _Struct
from warp._src.context import _build_launch_bounds_from_tuple as _bounds
from warp._src.context import _get_apic_capture_for_device
from warp._src.context import pack_arg as _pack_arg

from hairwarp.kernels.chunks import pool_call

#: Fewest elements per chunk of a per-strand or per-segment launch: below this, handing the chunk to another
#: thread costs more than it saves (measured on the default scene's kernels, ``hairwarp bench threads``).
MIN_CHUNK = 64

#: Chunks per thread of a launch whose elements write only themselves: the threads take them as they come free,
#: so a thread whose strands cost more (more contacts, longer strands) does not keep the others waiting; the last
#: chunk leaves the others idle for at most its own time (an eighth of a thread's share).
CHUNKS_PER_THREAD = 8

#: How long a pool thread waits for the next launch, spinning, before it sleeps [s]: longer than the host work
#: between the launches of a step (the default scene's longest gap is about 0.15 ms), short enough that an idle
#: pool gives its cores back at once (OpenMP's threads spin for a similar while).
SPIN_SECONDS = 0.001

#: Most threads an executor takes: beyond the largest machines' cores (a pool of 10^5 threads took 40 s to start
#: and then failed, leaving its threads behind). Results are the same bits for any count, so no more is needed.
MAX_THREADS = 1024

#: Prepared launches kept per executor (argument lists seen; a step has two, one per state parity).
PREPARED_LIMIT = 512

_NUMBERS = (int, float, bool)

#: Marks a prepared launch's key built argument by argument (ids, numbers as 1-tuples), apart from every key of the
#: arguments themselves.
_BY_IDENTITY = object()


def default_threads() -> int:
    """The cores this process may use (``os.sched_getaffinity``; ``os.cpu_count`` where that is missing)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def resolve_threads(threads) -> int:
    """``threads`` as a positive int: None or 0 mean :func:`default_threads`."""
    if threads is None:
        return default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or not 0 <= threads <= MAX_THREADS:
        raise ValueError(f"threads must be an integer in [0, {MAX_THREADS}] (0: every core this process may use, "
                         f"{default_threads()} here), got {threads!r}")
    return int(threads) if threads else default_threads()


class _Workers:
    """``count`` OS threads that serve the tables the calling thread leads (``kernels.chunks``), and run Python jobs
    (:meth:`Executor.run`) handed to each by a lock of its own.

    A thread is asleep (``state`` 0) on its lock or awake (1): serving, spinning between tables, or about to. The
    leader wakes the sleeping ones before it leads a table and never waits for them: it runs every chunk no one
    else has taken. A serving thread that finds nothing for :data:`SPIN_SECONDS`, or is parked, stores 0 and
    sleeps again.
    """

    def __init__(self, count: int, calls, spin_seconds: float):
        self.count = count
        self.calls = calls
        self.control = _control_block()
        self.state = np.zeros(count, dtype=np.int32)
        self._jobs = [None] * count
        self._errors = [None] * count
        self._go = [threading.Lock() for _ in range(count)]
        self._done = [threading.Lock() for _ in range(count)]
        for lock in (*self._go, *self._done):
            lock.acquire()
        budget = calls.ticks(spin_seconds)
        self._serve = [calls.serve(self.control, self.state, i, budget) for i in range(count)]
        self._local = threading.local()
        self._threads = [threading.Thread(target=self._loop, args=(i,), name=f"hairwarp-{i + 1}", daemon=True)
                         for i in range(count)]
        started = 0
        try:
            for t in self._threads:
                t.start()
                started += 1
        except RuntimeError as e:  # the system's limit on threads: stop the ones started, say so
            self.count, self._threads = started, self._threads[:started]
            self.close()
            raise RuntimeError(f"could not start {count + 1} CPU threads ({started + 1} started: {e}); set fewer "
                               f"threads (sim.threads, --threads or threads=)") from None
        _POOLS.add(self)

    def _loop(self, i: int):
        self._local.worker = True
        go, done, serve = self._go[i], self._done[i], self._serve[i]
        while True:
            go.acquire()
            job = self._jobs[i]
            if job is None:
                done.release()
                return
            if job is _SERVE:
                serve()  # returns once idle or parked, having stored state 0
                continue
            try:
                job()
            except BaseException as e:  # handed to the caller, which waits for every worker before raising
                self._errors[i] = e
            self._jobs[i] = None
            done.release()

    def in_worker(self) -> bool:
        return getattr(self._local, "worker", False)

    def wake(self, k: int):
        """Wake the sleeping ones of the first ``k`` threads to serve."""
        state = self.state
        for i in range(k):
            if state[i] == 0:
                state[i] = 1
                self._jobs[i] = _SERVE
                self._go[i].release()

    def park(self):
        """Send the serving threads to sleep and wait until they are (before Python jobs, or closing)."""
        if not self.state.any():
            return
        self.control[5] = 1
        while self.state.any():
            time.sleep(0)
        self.control[5] = 0

    def start(self, job, k: int):
        """Run the Python callable ``job`` on the first ``k`` threads (parked first)."""
        self.park()
        for i in range(k):
            self._jobs[i] = job
            self._go[i].release()

    def join(self, k: int):
        """Wait for the first ``k`` threads' jobs; the first error any raised, or None."""
        error = None
        for i in range(k):
            self._done[i].acquire()
            if self._errors[i] is not None:
                error = error or self._errors[i]
                self._errors[i] = None
        return error

    def close(self):
        self.park()
        for i in range(self.count):
            self._jobs[i] = None
            self._go[i].release()
        for t in self._threads:
            t.join()


#: The job that sends a pool thread to serve tables.
_SERVE = object()

#: Every live pool: parked when the interpreter exits, so that no thread still spins in a kernel module that Warp
#: is unloading.
_POOLS = weakref.WeakSet()


@atexit.register
def _park_pools():
    for pool in list(_POOLS):
        pool.park()


class _PoolCalls:
    """``kernels.chunks.pool_call`` packed once for direct calls: its entry point, bounds and argument type."""

    def __init__(self, device):
        base = wp.launch(pool_call, dim=1, inputs=[0, 0, 0, 0, 0, 0, 0], device=device, record_cmd=True)
        labels = [a.label for a in pool_call.adj.args]
        self._args = type("PoolCallArgs", (ctypes.Structure,),
                          {"_fields_": [(label, type(p)) for label, p in zip(labels, base.params[1:])]})
        self._bounds = _bounds((1,), pool_call.adj.kernel_dim)
        self._forward = base.hooks.forward
        clock = np.zeros(2, dtype=np.uint64)
        read = self._call(2, 0, 0, 0, 0, clock.ctypes.data, 0)
        t0 = time.perf_counter()
        read()
        first = int(clock[0])
        time.sleep(0.01)
        read()
        self.rate = (int(clock[0]) - first) / (time.perf_counter() - t0)  # clock ticks per second

    def ticks(self, seconds: float) -> int:
        """``seconds`` in clock ticks (a count of spins where the machine has no clock to read)."""
        return max(0, int(seconds * self.rate)) if self.rate > 0 else int(seconds * 1e7)

    def _call(self, mode, control, start, entries, count, state, budget):
        block = self._args(mode, control, start, entries, count, state, budget)
        bounds, forward = ctypes.byref(self._bounds), self._forward
        ref = ctypes.byref(block)

        def call():
            forward(bounds, ref)

        call.block = block  # kept alive with the call
        return call

    def lead(self, control, table):
        """The calling thread's call leading ``table`` through ``control``."""
        return self._call(0, control.ctypes.data, table.start.ctypes.data, table.entries.ctypes.data,
                          table.task_count, 0, 0)

    def serve(self, control, state, i, budget: int):
        """Pool thread ``i``'s call: it serves ``control`` and stores 0 at ``state[i]`` when it stops."""
        return self._call(1, control.ctypes.data, 0, 0, 0, state.ctypes.data + 4 * i, budget)


def _control_block():
    """A control block of ``kernels.chunks`` (eight int64)."""
    return np.zeros(8, dtype=np.int64)


class _Prepared:
    """The packed chunks of one launch: an argument block per chunk, the private buffers and how they fold."""

    __slots__ = ("keep", "forward", "calls", "entries", "structs", "loaded", "zero", "fold")

    def run_chunk(self, c: int):
        self.load_structs()
        self.call(c)

    def call(self, c: int):
        """Run chunk ``c`` on this thread (without the GIL), its structs as last loaded."""
        bounds, args, _ = self.calls[c]
        self.forward(bounds, args)

    def load_structs(self):
        """Copy into every chunk's block the structs whose live ctypes changed since they were last copied (a field
        set since the packing is seen). Comparing a struct's bytes costs a fraction of copying it into every chunk's
        block, which on the mohawk's step took 6 % of the frame on two threads."""
        loaded = self.loaded
        for k, (name, value) in enumerate(self.structs):
            now = bytes(value)
            if now != loaded[k]:
                for _, _, block in self.calls:
                    setattr(block, name, value)
                loaded[k] = now


class _Table:
    """Chunks of launches laid out for ``kernels.chunks``: task ``t`` runs its entries in turn; the threads take the
    tasks in order as they come free. Holds the launches it points into."""

    __slots__ = ("groups", "task_count", "start", "entries", "_leads")

    def __init__(self, groups):
        self.groups = groups
        tasks = [[prep.entries[c] for prep in group] for group in groups for c in range(len(group[0].calls))]
        self.task_count = len(tasks)
        self.start = np.cumsum([0, *map(len, tasks)], dtype=np.int32)
        self.entries = np.array([e for task in tasks for e in task], dtype=np.uint64).reshape(-1)
        self._leads = {}

    def lead(self, calls, control):
        """Publish the table in ``control`` and run it with whoever serves that block; return when it has run."""
        have = self._leads.get(id(control))
        if have is None or have[0] is not control:  # kept with its control block, whose address the call holds
            have = self._leads[id(control)] = (control, calls.lead(control, self))
        have[1]()


class _Chain:
    """The launches a :meth:`Executor.chain` holds, and the chunks of its units (``scaled``: their element ranges
    for ``m`` elements a unit, kept by the executor for the next chain over the same units)."""

    __slots__ = ("units", "chunks", "preps", "_scaled")

    def __init__(self, units: int, chunks, scaled: dict):
        self.units, self.chunks, self.preps, self._scaled = units, chunks, [], scaled

    def scaled(self, m: int):
        """The chunks of a launch over ``m`` elements a unit (a tuple: part of the launch's key)."""
        have = self._scaled.get(m)
        if have is None:
            have = self._scaled[m] = tuple((m * start, m * count) for start, count in self.chunks)
        return have


class Executor:
    """Runs launches of ``tid_offset`` kernels on ``threads`` OS threads (the calling thread and a pool).

    Args:
        device: the Warp device; on CUDA every launch is one launch and ``threads`` is 1.
        threads: CPU threads; None or 0: every core this process may use.
        min_chunk: fewest elements in a chunk (see :data:`MIN_CHUNK`).
        chunks_per_thread: chunks per thread of a launch whose elements write only themselves (see
            :data:`CHUNKS_PER_THREAD`).
    """

    def __init__(self, device=None, threads=None, *, min_chunk: int = MIN_CHUNK,
                 chunks_per_thread: int = CHUNKS_PER_THREAD):
        self.device = wp.get_device(device)
        self.threads = 1 if self.device.is_cuda else resolve_threads(threads)
        self.min_chunk = max(1, int(min_chunk))
        self.chunks_per_thread = max(1, int(chunks_per_thread))
        self._workers = None
        self._private = {}
        self._prepared = {}
        self._lock = threading.Lock()
        self._busy = threading.Lock()
        self._batch = None
        self._chain = None
        self._tables = {}
        self._calls = None
        self._chain_chunks = {}
        self._views = {}

    @property
    def parallel(self) -> bool:
        """Whether launches may run on more than one thread."""
        return self.threads > 1

    def close(self):
        """Stop the pool's threads (a later launch starts them again)."""
        if self._workers is not None:
            self._workers.close()
            self._workers = None

    def __del__(self):
        workers = getattr(self, "_workers", None)
        if workers is not None:
            try:
                workers.close()
            except Exception:  # interpreter shutdown
                pass

    def zero(self, *arrays):
        """Zero ``arrays``: on the CPU outside a graph capture by their host views, kept (a Warp ``zero_`` costs as
        much Python as a small launch, and a step zeroes eight arrays); else ``zero_``, which a capture records."""
        if self.device.is_cuda or _capturing(self.device):
            for a in arrays:
                a.zero_()
            return
        for a in arrays:
            self.host_view(a).fill(0)

    def host_view(self, array) -> np.ndarray:
        """The numpy view of a CPU ``array``, made once and kept (``array.numpy()`` builds a new one each call)."""
        have = self._views.get(id(array))
        if have is None or have[0] is not array:
            have = self._views[id(array)] = (array, array.numpy())
        return have[1]

    # -- partitions ----------------------------------------------------------------------

    def chunks(self, n: int, min_chunk: int | None = None, per_thread: int | None = None) -> list[tuple[int, int]]:
        """``(start, count)`` of the ranges a launch of ``n`` elements that write only themselves runs as: up to
        ``chunks_per_thread`` per thread, equal to within one element, none below ``min_chunk`` (one range when
        ``n`` is small or there is one thread)."""
        if self.threads <= 1:
            return [(0, n)]
        m = self.min_chunk if min_chunk is None else max(1, int(min_chunk))
        per_thread = self.chunks_per_thread if per_thread is None else per_thread
        k = max(1, min(self.threads * per_thread, n // m))
        return _split(n, k)

    @staticmethod
    def fixed_chunks(n: int, count: int) -> list[tuple[int, int]]:
        """``count`` ranges of ``n`` elements fixed by ``n`` and ``count`` alone (not the thread count), for stages
        whose results depend on where the chunks start: they accumulate per chunk and reduce in chunk order."""
        return _split(n, max(1, min(int(count), n)) if n > 0 else 1)

    # -- running -------------------------------------------------------------------------

    def _pool(self):
        if self._workers is None:
            with self._lock:
                if self._workers is None:
                    # more threads than cores: a spinning thread would take a core from one with work
                    spin = SPIN_SECONDS if self.threads <= default_threads() else 0.0
                    self._workers = _Workers(self.threads - 1, self._pool_calls(), spin)
        return self._workers

    def run(self, tasks):
        """Call every function of ``tasks`` (no arguments), spread over the threads; return when all are done.

        The threads take the tasks in order as they come free, the calling thread among them. From inside a task,
        or while another thread runs tasks on this executor, the tasks run one after the other on the caller.
        """
        tasks = list(tasks)
        self._run_indexed(len(tasks), lambda i: tasks[i]())

    def _run_indexed(self, n: int, call):
        """``call(i)`` for every ``i < n``, on up to ``threads`` threads taking the next index as they come free."""
        k = min(self.threads, n) - 1
        if k <= 0 or (self._workers is not None and self._workers.in_worker()) or not self._busy.acquire(False):
            for i in range(n):
                call(i)
            return
        try:
            workers = self._pool()
            order = iter(range(n))  # shared: next() on it is atomic under the GIL

            def job():
                for i in order:
                    call(i)

            workers.start(job, k)
            error = None
            try:
                job()
            except BaseException as e:  # wait for the others before raising: they may write the same arrays
                error = e
            error = workers.join(k) or error
        finally:
            self._busy.release()
        if error is not None:
            raise error

    @contextlib.contextmanager
    def batch(self):
        """Within the block, launches through :meth:`launch` are held and run together when it ends: the chunks of
        all of them on one wake of the threads, in launch order as threads come free. Only for launches that are
        independent of each other (none reads what another writes), with nothing in the block reading their
        results; one thread, a graph capture or a block within a block run each launch at once, as always. A
        :meth:`chain` in the block is one of its launches."""
        if not self.parallel or self._batch is not None or _capturing(self.device):
            yield
            return
        self._batch = held = []
        try:
            yield
        finally:
            self._batch = None
        self._run_groups(held)

    @contextlib.contextmanager
    def chain(self, units: int, min_chunk: int | None = None):
        """Within the block, launches over ``units`` or a multiple of it (strands, their segments, their vertices)
        are held and run when it ends, chunk by chunk: the threads take the chunks of :meth:`chunks` ``(units,
        min_chunk)`` as they come free, and each runs every held launch on its chunk's elements in launch order.

        Only for launches whose every element is written by its own thread and that read, of what another launch of
        the block writes, only their own elements (those of the same units); the private reductions fold when the
        block ends, so none may read what another folds. A launch the chain cannot take (explicit ``chunks``,
        ``per_chunk``, ``private_sum``, or a size that is no multiple of ``units``) first runs what is held, then
        runs alone: the launch order stands. One thread or a graph capture run each launch at once, as always; so
        does a chain of one chunk, except within a :meth:`batch`: there its launches stay one task, run in order
        (one by one, the batch would run them at once on different threads, racing where they write the same array).
        """
        if not self.parallel or self._chain is not None or _capturing(self.device):
            yield
            return
        have = self._chain_chunks.get((units, min_chunk))
        if have is None:
            chunks = self.chunks(units, min_chunk)
            have = self._chain_chunks[(units, min_chunk)] = (chunks, {})
        chunks, scaled = have
        if len(chunks) == 1 and self._batch is None:
            yield
            return
        self._chain = held = _Chain(units, chunks, scaled)
        try:
            yield
        finally:
            self._chain = None
        self._flush_chain(held)

    def _flush_chain(self, chain):
        group, chain.preps = chain.preps, []
        if not group:
            return
        if self._batch is not None:
            self._batch.append(group)
        else:
            self._run_groups([group])

    def _run_groups(self, groups):
        """Run groups of prepared launches with equal chunk counts, chunk ``c`` of a group running each of its
        launches' chunk ``c`` in turn, the threads taking the chunks as they come free (``kernels.chunks``); then
        fold their private buffers in launch order."""
        # one launch, the most common table: the launch's id alone (the other keys hold tuples of ids)
        key = (id(groups[0][0]),) if len(groups) == 1 and len(groups[0]) == 1 else \
            tuple(tuple(map(id, group)) for group in groups)
        table = self._tables.get(key)
        if table is None:
            if len(self._tables) >= PREPARED_LIMIT:
                self._tables.pop(next(iter(self._tables)))
            table = self._tables[key] = _Table(groups)
        for group in groups:
            for prep in group:
                prep.load_structs()
        k = min(self.threads, table.task_count) - 1
        if k <= 0 or (self._workers is not None and self._workers.in_worker()) or not self._busy.acquire(False):
            # on this thread alone: a control block of its own, which no pool thread serves (held through the call)
            control = _control_block()
            self._pool_calls().lead(control, table)()
            del control
        else:
            try:
                workers = self._pool()
                workers.wake(k)
                table.lead(workers.calls, workers.control)
            finally:
                self._busy.release()
        for group in groups:
            for prep in group:
                _fold(prep)

    def _pool_calls(self):
        if self._calls is None:
            self._calls = _PoolCalls(self.device)
        return self._calls

    def launch(self, kernel, dim: int, inputs, outputs=(), *, min_chunk: int | None = None,
               private_or=(), private_add=(), private_sum=(), chunks=None, per_chunk=None):
        """Launch ``kernel`` (first parameter ``tid_offset: int``) over ``dim`` elements.

        Args:
            kernel, dim, inputs, outputs: as ``wp.launch``, without ``tid_offset`` in ``inputs``.
            min_chunk: fewest elements per chunk (default: the executor's).
            private_or, private_add: indices into ``[*inputs, *outputs]`` of small int32 arrays the kernel ORs or
                adds into: with more than one thread each chunk gets a zeroed private copy, folded into the array
                after the chunks (exact, so in any order).
            private_sum: indices of float arrays the kernel scatters into: each chunk accumulates into a zeroed
                private copy, added to the array in chunk order; give ``chunks`` a partition fixed by the work alone
                (:meth:`fixed_chunks`), and the sums are the same bits for any thread count.
            chunks: the ``(start, count)`` ranges to run (default :meth:`chunks`).
            per_chunk: ``{index: [value per chunk]}``: arguments (indices as above) that differ between chunks.
        """
        args = [*inputs, *outputs]
        if self.device.is_cuda or _get_apic_capture_for_device(self.device) is not None:
            # a graph capture records launches made through wp.launch only, and replays them on one thread
            wp.launch(kernel, dim=dim, inputs=[0, *args], device=self.device)
            return
        chain = self._chain
        if chain is not None:
            if chunks is None and not per_chunk and not private_sum and dim % chain.units == 0:
                chunks = chain.scaled(dim // chain.units)
            elif self._batch is not None:
                raise ValueError(f"{kernel.key}: a launch a chain cannot take (explicit chunks, per_chunk, private_sum "
                                 f"or a size of {dim}, no multiple of {chain.units}) in a chain within a batch")
            else:
                self._flush_chain(chain)  # what the chain holds runs first
                chain = None
        prep = self._prepared_launch(kernel, dim, args, min_chunk, private_or, private_add, private_sum, chunks,
                                     per_chunk)
        n = len(prep.calls)
        if n == 0:
            return
        if chain is not None:
            chain.preps.append(prep)
            return
        if self._batch is not None:
            self._batch.append([prep])
            return
        if n == 1:
            prep.run_chunk(0)
            _fold(prep)
        else:
            self._run_groups([[prep]])

    def prepare(self, kernel, dim: int, inputs, outputs=(), *, chunks, per_chunk=None, private_or=()):
        """The packed chunks of a launch (arguments as :meth:`launch`; CPU only, not while capturing) for a caller
        that runs them itself from tasks of :meth:`run`, interleaved with host work the chunks wait for: call
        ``load_structs()`` once, then ``call(c)`` for every chunk ``c`` (on any thread, each once), then
        :meth:`finish`. The private buffers are zeroed here."""
        prep = self._prepared_launch(kernel, dim, [*inputs, *outputs], None, private_or, (), (), chunks, per_chunk)
        prep.load_structs()
        return prep

    @staticmethod
    def finish(prep):
        """Fold the private buffers of a launch from :meth:`prepare` once all its chunks have run."""
        _fold(prep)

    def _prepared_launch(self, kernel, dim, args, min_chunk, private_or, private_add, private_sum, chunks, per_chunk):
        """The prepared launch for these arguments (packed at the first call, then kept), its private buffers
        zeroed."""
        head = (kernel, dim, min_chunk, tuple(private_or), tuple(private_add), tuple(private_sum),
                None if chunks is None else tuple(chunks),
                None if not per_chunk else tuple((i, tuple(map(id, v))) for i, v in sorted(per_chunk.items())))
        try:
            # the arguments themselves: arrays and structs compare by identity, numbers by value (a tenth of the
            # Python of a key built argument by argument, which on the mohawk's 143 launches a frame cost 0.7 ms of
            # the calling thread, while the pool's threads wait)
            key = (*head, *args)
            prep = self._prepared.get(key)
        except TypeError:  # an argument without a hash (a Warp vector, a list): by identity, numbers by value
            key = (*head, _BY_IDENTITY, *[(a,) if a.__class__ in _NUMBERS else id(a) for a in args])
            prep = self._prepared.get(key)
        if prep is None:
            prep = self._prepare(kernel, dim, args, min_chunk, private_or, private_add, private_sum, chunks,
                                 per_chunk)
            if len(self._prepared) >= PREPARED_LIMIT:
                self._prepared.pop(next(iter(self._prepared)))
            self._prepared[key] = prep
        for parent in prep.zero:
            parent.fill(0)  # host views of the private buffers (CPU arrays)
        return prep

    def _prepare(self, kernel, dim, args, min_chunk, private_or, private_add, private_sum, chunks, per_chunk):
        """Pack the arguments of every chunk once (see :meth:`launch`)."""
        prep = _Prepared()
        prep.keep = (args, per_chunk)  # the key holds ids: keep the objects alive while it is used
        prep.calls, prep.entries, prep.structs, prep.loaded, prep.zero, prep.fold = [], [], [], [], [], []
        if chunks is None:
            chunks = self.chunks(dim, min_chunk)
        chunks = [c for c in chunks if c[1] > 0] if dim > 0 else []
        if not chunks:
            return prep
        private = [(i, "sum") for i in private_sum] if len(chunks) > 1 else []
        if self.parallel and len(chunks) > 1:  # one thread: the kernel's own integer read-modify-writes do not race
            private += [(i, "or") for i in private_or] + [(i, "add") for i in private_add]
        base = wp.launch(kernel, dim=chunks[0][1], inputs=[0, *args], device=self.device, record_cmd=True)
        replace = {i: list(v) for i, v in (per_chunk or {}).items()}
        for i, op in private:
            parent, views = self._private_buffers(args[i], len(chunks), (kernel, i))
            replace[i] = views
            prep.zero.append(parent.numpy())
            prep.fold.append((op, args[i].numpy(), parent.numpy()))  # host views of CPU arrays
        packed = {i: [_pack(kernel, i + 1, v, self.device) for v in values] for i, values in replace.items()}
        labels = [a.label for a in kernel.adj.args]
        fields = [(label, type(p)) for label, p in zip(labels, base.params[1:])]
        args_struct = type("ArgsStruct", (ctypes.Structure,), {"_fields_": fields})
        struct_args = [j for j, a in enumerate(kernel.adj.args) if isinstance(a.type, _Struct)]
        prep.forward = base.hooks.forward
        entry_point = ctypes.cast(prep.forward, ctypes.c_void_p).value
        prep.entries = []
        keep = []
        for c, (start, count) in enumerate(chunks):
            params = list(base.params[1:])
            params[0] = ctypes.c_int32(start)
            for i, values in packed.items():
                params[i + 1] = values[c]  # params: tid_offset, then the arguments
            block = args_struct()
            for (label, _), value in zip(fields, params):
                setattr(block, label, value)
            bounds = _bounds((count,), kernel.adj.kernel_dim)
            keep.append((bounds, block, params))
            prep.calls.append((ctypes.byref(bounds), ctypes.byref(block), block))
            prep.entries.append((entry_point, ctypes.addressof(bounds), ctypes.addressof(block)))
        prep.keep = (args, per_chunk, keep)
        # structs are re-read at each launch (their live ctypes); the same for every chunk unless given per chunk
        for j in struct_args:
            if j - 1 in packed:
                continue
            prep.structs.append((labels[j], base.params[1 + j]))
            prep.loaded.append(None)  # copied at the first launch
        return prep

    def _private_buffers(self, array, count: int, slot):
        """A zeroed ``(count, *shape)`` array for private copies of ``array`` and its ``count`` views, one per
        kernel and argument (``slot``): launches held together fold their own."""
        key = (array.shape, array.dtype, slot, count)
        have = self._private.get(key)
        if have is None:
            parent = wp.zeros((count, *array.shape), dtype=array.dtype, device=self.device)
            have = self._private[key] = (parent, [parent[c] for c in range(count)])
        return have


def _fold(prep: _Prepared):
    """Fold the private buffers of a prepared launch's chunks into their arrays (nothing to do where every chunk left
    its copy zero, as the fault bits nearly always are: a count of nonzero entries costs a sixth of a reduction)."""
    for op, dst, parts in prep.fold:
        if op != "sum" and not np.count_nonzero(parts):
            continue
        if op == "or":
            dst |= np.bitwise_or.reduce(parts, axis=0)
        elif op == "add":
            dst += np.sum(parts, axis=0, dtype=dst.dtype)
        else:
            for part in parts:  # in chunk order: the same bits whichever thread ran which chunk
                dst += part


def _capturing(device) -> bool:
    """Whether a Warp graph capture on the CPU is recording (then every launch is one recorded launch)."""
    return _get_apic_capture_for_device(device) is not None


def _pack(kernel, index, value, device):
    arg = kernel.adj.args[index]
    return _pack_arg(kernel, arg.type, arg.label, value, device, False)


def _split(n: int, k: int) -> list[tuple[int, int]]:
    q, r = divmod(n, k)
    out, start = [], 0
    for c in range(k):
        count = q + (1 if c < r else 0)
        out.append((start, count))
        start += count
    return out


def launch(executor, kernel, dim: int, inputs, outputs=(), *, device=None, **kw):
    """``executor.launch(...)``, or one plain launch with ``tid_offset = 0`` when ``executor`` is None."""
    if executor is None:
        kw.pop("chunks", None)
        wp.launch(kernel, dim=dim, inputs=[0, *inputs, *outputs], device=device)
    else:
        executor.launch(kernel, dim, inputs, outputs, **kw)
