"""The CPU executor's thread pool loop (``hairwarp.executor``), in native code.

A chunk is a launch's CPU entry point with its bounds and argument block, as ``wp.launch`` calls it. Run from
Python, every chunk would release and take back the GIL, and every parallel launch would wake a sleeping thread
(about 60 microseconds here, as long as a small launch's whole work) and wait for it. Here a launch's chunks are a
table, and the threads run it without the GIL:

- the calling thread *leads*: it publishes the table in a control block, runs chunks as the others do, and returns
  once every chunk has run;
- the pool's threads *serve*: they take the chunks of whatever table is published, and between tables spin for a
  short while (``budget`` clock ticks) before going back to sleep in Python, so the launches of a step find them
  awake.

A thread takes the next task with a compare-and-swap on one 64-bit word that holds the table's generation and its
next task. The leader seals that word (its task half all ones) before it writes a new table's fields and opens it
after: a thread that read the spent word of the last table and then the new table's count would otherwise claim
with the old word, run a task of the new table twice and count it done twice, so that the leader could return while
a task still ran (one launch in 50 on two threads, found by ``tests/test_threads.py``). Tasks are taken in table
order as threads come free; a task runs its entries in turn (a chain's launches on one chunk).

Control block (int64): ``[0]`` generation << 32 | next task, ``[1]`` tasks done, ``[2]`` task_start, ``[3]``
entries, ``[4]`` task count, ``[5]`` park (serving threads go to sleep). The table: ``task_start`` (task count + 1
int32; task ``t`` runs entries ``task_start[t] .. task_start[t + 1]``) and ``entries`` (three uint64 an entry: the
entry point, its launch bounds, its argument block). Host addresses: CPU only; on CUDA this compiles to nothing.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

#: ``mode`` of :func:`pool_call`.
LEAD = wp.constant(0)
SERVE = wp.constant(1)
CLOCK = wp.constant(2)

_POOL = """
#if !defined(__CUDA_ARCH__)
    typedef void (*entry_point)(void*, void*);
    const long long SEALED = 0xffffffffLL;  // the next-task half of a word while its table is being published
    long long* c = (long long*)control;
    unsigned long long spins = 0;
#if defined(__x86_64__) || defined(__i386__)
#define HW_TICKS() __builtin_ia32_rdtsc()
#define HW_PAUSE() __builtin_ia32_pause()
#elif defined(__aarch64__)
#define HW_TICKS() ({ unsigned long long v_; __asm__ __volatile__("mrs %0, cntvct_el0" : "=r"(v_)); v_; })
#define HW_PAUSE() __asm__ __volatile__("yield")
#else
#define HW_TICKS() (++spins)
#define HW_PAUSE() ((void)0)
#endif
    if (mode == 2) {
        *(unsigned long long*)state = HW_TICKS();
        return;
    }
    if (mode == 0) {
        const long long generation = ((__atomic_load_n(&c[0], __ATOMIC_RELAXED) >> 32) + 1) & 0xffffffffLL;
        // Seal first: a thread that read the last table's spent word and then this table's larger count must not
        // claim with that word; sealed, its claim fails (and the fence keeps the seal ahead of the fields).
        __atomic_store_n(&c[0], (generation << 32) | SEALED, __ATOMIC_RELAXED);
        __atomic_thread_fence(__ATOMIC_RELEASE);
        __atomic_store_n(&c[2], (long long)task_start, __ATOMIC_RELAXED);
        __atomic_store_n(&c[3], (long long)entries, __ATOMIC_RELAXED);
        __atomic_store_n(&c[4], (long long)task_count, __ATOMIC_RELAXED);
        __atomic_store_n(&c[1], 0LL, __ATOMIC_RELAXED);
        __atomic_store_n(&c[0], generation << 32, __ATOMIC_RELEASE);
    }
    unsigned long long idle_since = HW_TICKS();
    for (;;) {
        long long word = __atomic_load_n(&c[0], __ATOMIC_ACQUIRE);
        const long long count = __atomic_load_n(&c[4], __ATOMIC_RELAXED);
        const long long t = word & 0xffffffffLL;
        if (t < count) {
            // the table's fields as published with this word; used only if the word still holds this generation
            const int* start = (const int*)__atomic_load_n(&c[2], __ATOMIC_RELAXED);
            const unsigned long long* entry = (const unsigned long long*)__atomic_load_n(&c[3], __ATOMIC_RELAXED);
            __atomic_thread_fence(__ATOMIC_ACQUIRE);  // fields read from a later table: the claim below sees its seal
            if (__atomic_compare_exchange_n(&c[0], &word, word + 1, false, __ATOMIC_ACQ_REL, __ATOMIC_RELAXED)) {
                for (int k = start[t]; k < start[t + 1]; ++k)
                    ((entry_point)entry[3 * k])((void*)entry[3 * k + 1], (void*)entry[3 * k + 2]);
                __atomic_fetch_add(&c[1], 1LL, __ATOMIC_RELEASE);
                idle_since = HW_TICKS();
            }
            continue;
        }
        if (mode == 0) {
            while (__atomic_load_n(&c[1], __ATOMIC_ACQUIRE) < count)
                HW_PAUSE();
            break;
        }
        if (__atomic_load_n(&c[5], __ATOMIC_RELAXED) != 0 || HW_TICKS() - idle_since > budget)
            break;
        HW_PAUSE();
    }
    if (mode == 1)
        __atomic_store_n((int*)state, 0, __ATOMIC_RELEASE);
#undef HW_TICKS
#undef HW_PAUSE
#endif
"""


@wp.func_native(_POOL)
def _pool(mode: int, control: wp.uint64, task_start: wp.uint64, entries: wp.uint64, task_count: int,
          state: wp.uint64, budget: wp.uint64): ...


@wp.kernel
def pool_call(mode: int, control: wp.uint64, task_start: wp.uint64, entries: wp.uint64, task_count: int,
              state: wp.uint64, budget: wp.uint64):
    """One thread's part (launch with dim 1). ``LEAD``: publish the table and run it to its end; ``SERVE``: run the
    published tables' tasks until idle for ``budget`` ticks or parked, then store 0 (asleep) at ``state``;
    ``CLOCK``: store the clock's ticks at ``state`` (uint64)."""
    _pool(mode, control, task_start, entries, task_count, state, budget)
