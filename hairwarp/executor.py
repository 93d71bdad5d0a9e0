"""CPU executor: one Warp launch split into chunks run on a pool of OS threads.

Warp runs a CPU launch on one thread, and its CPU ``atomic_add`` / ``atomic_or`` are plain read-modify-writes.
A launch of a kernel that takes ``tid_offset: int`` as its first parameter (its thread ``i`` works on element
``tid_offset + i``) can instead run as several launches of consecutive ranges, one per pool thread; Warp releases
the GIL inside a CPU launch, so the chunks run at once. On CUDA, or with one thread, it is one launch, as always.

Results never depend on the thread count:

- a kernel whose every element is written by one thread only (a strand, a segment, a dense vertex) gives the same
  bits whatever its range, so such launches are split into ``threads`` equal ranges (no smaller than
  ``min_chunk`` elements, below which a chunk costs more to hand to a thread than it runs);
- small integer arrays that threads OR or add into (fault bits, counters) are given to each chunk as a private
  zeroed copy and folded into the real array after the chunks join (integer OR and sums are exact, so the order
  does not matter): ``private_or`` and ``private_add``;
- stages that scatter floats (the hair contacts' forces) use :meth:`Executor.fixed_chunks`, a partition fixed by
  the work size alone, accumulate per chunk and reduce in chunk order; stages that append to a buffer take
  per-chunk buffers concatenated in chunk order (``HairContacts``), which is the order of one whole launch.

A captured Warp graph replays its launches on one thread, so ``hairwarp.Stepper`` does not capture on the CPU
when the executor has more than one thread.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp
from warp._src.context import _build_launch_bounds_from_tuple as _bounds
from warp._src.context import invoke as _invoke
from warp._src.context import pack_arg as _pack_arg

#: Fewest elements per chunk of a per-strand or per-segment launch: below this, handing the chunk to another
#: thread costs more than it saves (measured on the default scene's kernels, ``hairwarp bench threads``).
MIN_CHUNK = 64

#: Chunks of a scatter stage (a partition fixed by the work alone; see ``Executor.fixed_chunks``): enough for
#: 8 threads, few enough that the private buffers stay small.
SCATTER_CHUNKS = 8


def default_threads() -> int:
    """The cores this process may use (``os.sched_getaffinity``; ``os.cpu_count`` where that is missing)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def resolve_threads(threads) -> int:
    """``threads`` as a positive int: None or 0 mean :func:`default_threads`."""
    if threads is None or int(threads) == 0:
        return default_threads()
    threads = int(threads)
    if threads < 0:
        raise ValueError(f"threads must be >= 0 (0: every core this process may use), got {threads}")
    return threads


class Executor:
    """Runs launches of ``tid_offset`` kernels on ``threads`` OS threads (the calling thread and a pool).

    Args:
        device: the Warp device; on CUDA every launch is one launch and ``threads`` is 1.
        threads: CPU threads; None or 0: every core this process may use.
        min_chunk: fewest elements in a chunk (see :data:`MIN_CHUNK`).
    """

    def __init__(self, device=None, threads=None, *, min_chunk: int = MIN_CHUNK):
        self.device = wp.get_device(device)
        self.threads = 1 if self.device.is_cuda else resolve_threads(threads)
        self.min_chunk = max(1, int(min_chunk))
        self._pool = None
        self._private = {}
        self._lock = threading.Lock()

    @property
    def parallel(self) -> bool:
        """Whether launches may run on more than one thread."""
        return self.threads > 1

    def close(self):
        """Stop the pool's threads (a later launch starts them again)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __del__(self):
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)

    # -- partitions ----------------------------------------------------------------------

    def chunks(self, n: int, min_chunk: int | None = None) -> list[tuple[int, int]]:
        """``(start, count)`` of the ranges a launch of ``n`` elements runs as: at most ``threads`` of them, equal
        to within one element, none below ``min_chunk`` (one range when ``n`` is small)."""
        m = self.min_chunk if min_chunk is None else max(1, int(min_chunk))
        k = max(1, min(self.threads, n // m))
        return _split(n, k)

    @staticmethod
    def fixed_chunks(n: int, count: int) -> list[tuple[int, int]]:
        """``count`` ranges of ``n`` elements fixed by ``n`` and ``count`` alone (not the thread count), for stages
        whose results depend on where the chunks start: they accumulate per chunk and reduce in chunk order."""
        return _split(n, max(1, min(int(count), n)) if n > 0 else 1)

    # -- running -------------------------------------------------------------------------

    def run(self, tasks):
        """Call every function of ``tasks`` (no arguments), spread over the threads; return when all are done.

        Task ``i`` runs on thread ``i % threads``; the calling thread takes its share first.
        """
        tasks = list(tasks)
        t = min(self.threads, len(tasks))
        if t <= 1:
            for task in tasks:
                task()
            return
        if self._pool is None:
            with self._lock:
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(max_workers=self.threads - 1, thread_name_prefix="hairwarp")

        def group(j):
            for task in tasks[j::t]:
                task()

        futures = [self._pool.submit(group, j) for j in range(1, t)]
        error = None
        try:
            group(0)
        except BaseException as e:  # wait for the others before raising: they may write the same arrays
            error = e
        for f in futures:
            try:
                f.result()
            except BaseException as e:
                error = error or e
        if error is not None:
            raise error

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
        if self.device.is_cuda or _capturing(self.device):
            # a graph capture records launches made through wp.launch only, and replays them on one thread
            wp.launch(kernel, dim=dim, inputs=[0, *args], device=self.device)
            return
        if chunks is None:
            if not self.parallel:
                wp.launch(kernel, dim=dim, inputs=[0, *args], device=self.device)
                return
            chunks = self.chunks(dim, min_chunk)
        chunks = [c for c in chunks if c[1] > 0] if dim > 0 else []
        if not chunks:
            return
        if len(chunks) == 1 and not per_chunk:
            start, count = chunks[0]
            wp.launch(kernel, dim=count, inputs=[start, *args], device=self.device)
            return
        private = [(i, "sum") for i in private_sum]
        if self.parallel:  # one thread at a time: the kernel's own integer read-modify-writes do not race
            private += [(i, "or") for i in private_or] + [(i, "add") for i in private_add]
        base = wp.launch(kernel, dim=chunks[0][1], inputs=[0, *args], device=self.device, record_cmd=True)
        scratch = {i: self._private_buffers(args[i], len(chunks), i) for i, _ in private}
        replace = dict(per_chunk or {})
        for i, _ in private:
            replace[i] = scratch[i]
        packed = {i: [_pack(kernel, i + 1, v, self.device) for v in values] for i, values in replace.items()}
        hooks, adj = base.hooks, kernel.adj.kernel_dim
        cmds = []
        for c, (start, count) in enumerate(chunks):
            params = list(base.params)
            params[0] = _bounds((count,), adj)
            params[1] = ctypes.c_int32(start)
            for i, values in packed.items():
                params[i + 2] = values[c]  # params: bounds, tid_offset, then the arguments
            cmds.append(params)

        def task(c):
            def go():
                for i, _ in private:
                    scratch[i][c].zero_()
                _invoke(kernel, hooks, cmds[c], False)
            return go

        self.run(task(c) for c in range(len(cmds)))
        for i, op in private:
            dst = args[i].numpy()  # a view on the CPU
            parts = [s.numpy() for s in scratch[i]]
            if op == "or":
                dst |= np.bitwise_or.reduce(parts, axis=0)
            elif op == "add":
                dst += np.sum(parts, axis=0, dtype=dst.dtype)
            else:
                for part in parts:  # in chunk order: the same bits whichever thread ran which chunk
                    dst += part

    def _private_buffers(self, array, count: int, slot: int):
        key = (array.shape, array.dtype, slot)
        have = self._private.get(key, [])
        while len(have) < count:
            have.append(wp.zeros(array.shape, dtype=array.dtype, device=self.device))
        self._private[key] = have
        return have[:count]


def _capturing(device) -> bool:
    """Whether a Warp graph capture on the CPU is recording (then every launch is one recorded launch)."""
    from warp._src.context import _get_apic_capture_for_device

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
