"""Hair-hair interaction: static links (DESIGN §4.3) and dynamic contacts on triangle strips (§4.4).

Everything is built once, on the host, from the rest pose; the per-step methods only launch kernels, so a solver
step that calls them can be captured in a graph. The solver calls, each step, after forward kinematics of
``state_in`` and after zeroing its accumulators::

    links.apply(model, state_in, dt, seg_force, seg_torque, seg_implicit_mass)
    contacts.apply(model, state_in, dt, seg_force, seg_torque, seg_implicit_mass)

and, after integration and forward kinematics of ``state_out``::

    links.break_links(model, state_out)

``dt`` is the solver's one-element float32 device array. ``model`` needs ``seg_per_strand``, ``seg_length``,
``seg_mass`` and (links) ``joint_stiffness``; a state needs ``seg_xform``, ``joint_q`` (links read the head's
rotation from the root segments), ``vertex_positions``, ``vertex_velocities`` and ``fault``.

Once per output frame, outside a captured step, a runner reads ``links.broken_count()``,
``contacts.contact_count()`` and ``contacts.overflowed()``. Contact detection costs far more than the force pass;
with ``HairContacts.build(..., detect_each_step=False, margin=...)`` the runner calls ``contacts.detect(model,
state)`` itself (e.g. at the first substep of a frame) and each step only evaluates the stored pairs.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import warp as wp

from hairwarp.executor import _capturing, launch
from hairwarp.kernels import contacts as contact_kernels
from hairwarp.kernels import links as link_kernels
from hairwarp.kernels import sweeps as sweep_kernels
from hairwarp.kernels.types import REFERENCE_SEGMENT_LENGTH, Fault

# Strip triangles narrower than this fraction of the median width would make the density-scaled
# vertex-face stiffness k0 s0 / s unbounded; wider than its inverse they would make it vanish. A strip quad
# stretched wider than that (its two strands have parted) is no contact surface: there is no hair between them.
_MAX_DENSITY_SCALE = 4.0


class InteractionError(ValueError):
    """Bad input to a hair-hair interaction builder; the message names the argument or the strand."""


def _check_vertices(rest_vertices) -> np.ndarray:
    verts = np.asarray(rest_vertices, dtype=np.float64)
    if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[1] < 2 or verts.shape[0] < 1:
        raise InteractionError(f"rest_vertices: expected shape (G, S+1, 3) with S >= 1, got {verts.shape}")
    if not np.all(np.isfinite(verts)):
        strand = int(np.nonzero(~np.isfinite(verts).all(axis=(1, 2)))[0][0])
        raise InteractionError(f"rest_vertices: strand {strand} has a non-finite vertex")
    lengths = np.linalg.norm(np.diff(verts, axis=1), axis=2)
    if np.any(lengths <= 0.0):
        strand = int(np.nonzero(np.any(lengths <= 0.0, axis=1))[0][0])
        raise InteractionError(f"rest_vertices: strand {strand} has a zero-length segment")
    return verts


def closest_points_segments(p0, p1, q0, q1):
    """Closest points of segment pairs ``[p0, p1]`` and ``[q0, q1]`` (float64, arrays of shape (N, 3)).

    Returns ``(s, t, dist)``: the parameters of the closest points along each segment (0 at p0 / q0,
    1 at p1 / q1) and their distance. Ericson, *Real-Time Collision Detection*, 5.1.9.
    """
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    c = np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)
    denom = a * e - b * b
    parallel = denom <= 1e-12 * a * e
    s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0.0, 1.0))
    t = (b * s + f) / e
    low = t < 0.0
    high = t > 1.0
    s = np.where(low, np.clip(-c / a, 0.0, 1.0), s)
    s = np.where(high, np.clip((b - c) / a, 0.0, 1.0), s)
    t = np.clip(t, 0.0, 1.0)
    dist = np.linalg.norm((p0 + s[:, None] * d1) - (q0 + t[:, None] * d2), axis=1)
    return s, t, dist


def _nearest_segment_pairs(p0, p1, strand, neighbours: int, radius: float) -> np.ndarray:
    """Unordered pairs (a < b) such that b is among a's ``neighbours`` nearest segments of other strands within
    ``radius``, or a among b's (exact segment-segment distances; equal distances go to the lower index).

    The ``4n + 8`` nearest midpoints give each segment an upper bound of its n-th nearest distance; the segments whose
    boxes meet its box grown by that bound (a tree over the boxes, ``kernels.links.link_candidates``) hold every
    segment that can be nearer, so the choice is exact while the candidates stay near the ones chosen. (A ball about
    the midpoint, its radius the bound plus both half-lengths, held 750 candidates a segment for 3,000 guides of 12
    segments of 2.9 cm, and the search took 14.7 s of their 16 s of set-up; with the boxes it takes 0.9 s.)
    """
    from scipy.spatial import cKDTree

    count = len(p0)
    mid = 0.5 * (p0 + p1)
    tree = cKDTree(mid)
    k = min(count, 4 * neighbours + 8)
    idx = tree.query(mid, k=k)[1].reshape(count, k)
    i = np.repeat(np.arange(count), k)
    j = idx.ravel()
    other = strand[i] != strand[j]
    near = np.full(count * k, np.inf)
    near[other] = closest_points_segments(p0[i[other]], p1[i[other]], p0[j[other]], p1[j[other]])[2]
    near = np.sort(near.reshape(count, k), axis=1)
    bound = np.minimum(near[:, neighbours - 1] if k >= neighbours else np.inf, radius)

    i, j = _box_candidates(p0, p1, strand, bound)
    dist = closest_points_segments(p0[i], p1[i], p0[j], p1[j])[2]
    keep = dist <= bound[i]
    i, j, dist = i[keep], j[keep], dist[keep]
    # i's candidates by distance, then by index: keep the first n of each i.
    order = np.lexsort((j, dist, i))
    i, j = i[order], j[order]
    rank = np.arange(len(i)) - np.searchsorted(i, i, side="left")
    chosen = np.sort(np.stack([i[rank < neighbours], j[rank < neighbours]], axis=1), axis=1)
    return np.unique(chosen, axis=0) if len(chosen) else np.zeros((0, 2), np.int64)


def _box_candidates(p0, p1, strand, reach) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` of segments of different strands whose boxes meet, ``i``'s grown by ``reach[i]`` (finite) and
    by a float32 margin: every pair closer than that reach, and some farther (``kernels.links.link_candidates``, on
    the CPU)."""
    scale = max(float(np.abs(np.concatenate([p0, p1])).max()), 1.0)
    grow = reach + 8.0 * np.finfo(np.float32).eps * scale
    device = "cpu"
    lower = wp.array(np.minimum(p0, p1), dtype=wp.vec3, device=device)
    upper = wp.array(np.maximum(p0, p1), dtype=wp.vec3, device=device)
    bvh = wp.Bvh(lower, upper)
    args = [lower, upper, wp.array(grow, dtype=float, device=device),
            wp.array(strand.astype(np.int32), dtype=wp.int32, device=device), bvh.id]
    capacity = 64 * len(p0)
    while True:
        found = wp.zeros(1, dtype=wp.int32, device=device)
        a = wp.empty(capacity, dtype=wp.int32, device=device)
        b = wp.empty(capacity, dtype=wp.int32, device=device)
        wp.launch(link_kernels.link_candidates, dim=len(p0), inputs=[*args, capacity], outputs=[found, a, b],
                  device=device)
        n = int(found.numpy()[0])
        if n <= capacity:
            return a.numpy()[:n].astype(np.int64), b.numpy()[:n].astype(np.int64)
        capacity = n  # every pair counted: one more launch holds them


#: Fewest segments (or blocks, vertices) per chunk of the cheap per-element launches (``hairwarp.executor``).
SEGMENT_MIN_CHUNK = 256

#: Gauss-Seidel sweeps of the links' response per step (``StaticLinks.build``), at steps up to
#: :data:`SWEEP_REFERENCE_STEP`; longer steps take more, and steps that start cold twice as many
#: (``StaticLinks.sweeps_at``). With the links' warm start (``hairwarp.Solver._warm_start``) a sweep solves the change
#: of their forces over the step, and one sweep, its colours' order turned from step to step
#: (``Solver.sweep_turn``), keeps the hair about as near the converged sweeps as two symmetric ones did: tips against
#: 24 sweeps a step, 0.14 mm on ``long_hair_shoulders`` (0.081 on two; 2.6 with the colours always forward) and 3.6
#: mm on the Ratboy mohawk (3.7 on two, 4.2 always forward), for 12-20 % less time a frame.
DEFAULT_SWEEPS = 1

#: How many times the sweeps a step takes that starts cold (:meth:`StaticLinks.sweeps_at`): without the links' force
#: of the last step in its free step the sweeps solve all of it, as 2 a step did before the warm start. At one step a
#: frame, which starts cold, limp linked hair (EI 1e-7, 16 segments) on 13 sweeps peaked at 1.8 m/s, against 1.03 on
#: 25.
COLD_SWEEPS = 2

#: How the sweeps a warm step needs grow with its length (:meth:`StaticLinks.sweeps_at`): faster than a cold step's
#: (:data:`SWEEP_GROWTH`). The warm start takes off a share of the error the sweeps start from, which saves a sweep
#: where each leaves 0.37-0.53 of the error (1/240 s) but only a few of the 16 where each leaves 0.69-0.85 (1/60 s).
#: ``long_hair_shoulders`` at 2 substeps with its head still rests on 10, 12 or 16 sweeps a step (0.013 mm/s in the
#: 6th second) and on 8 (k ** 1.5) slid off again from the 4th second (1.8 mm/s).
WARM_SWEEP_GROWTH = 2.0

#: The step [s] up to which a step takes ``sweeps`` sweeps (twice as many cold); a longer step takes more
#: (:meth:`StaticLinks.sweeps_at`). At 2 steps a frame (1/60 s) the Ratboy mohawk, its links and hair contacts
#: solved by 2 sweeps, settled 20-40 mm below its 16-substep run and broke 315 links in its turns and shake (25 at 16
#: substeps). Limp hair (EI 1e-7, 64 segments) at 2 steps a frame burst on 2 or 4 sweeps (4.2 and 3.4 m/s at its
#: tips as it falls onto itself) and holds on 8.
SWEEP_REFERENCE_STEP = 1.0 / 240.0

#: How the sweeps a cold step needs grow with its length: the longer the step, the stiffer the links and contacts are
#: against the strands' inertia (``h c`` and ``h^2 k`` against ``m``), and the less a sweep takes off the error.
#: Measured on the Ratboy mohawk in its turn and its shake (the RMS of the vertex velocities against 64 sweeps), a
#: sweep leaves 0.37-0.53 of the error at 1/240 s, 0.57-0.75 at 1/120 s and 0.69-0.85 at 1/60 s: the error 2 sweeps
#: leave at 1/240 s (0.76-1.2 mm/s) takes 6-8 at 1/120 s and 14-16 at 1/60 s, k ** 1.5 times as many. With k
#: times as many (8 at 1/60 s) the error was 4.4-4.9 mm/s, and the mohawk broke 29-46 links in five runs with
#: gravity changed by 1e-5 (21-25 at 16 substeps); with 16, 16-32.
SWEEP_GROWTH = 1.5

#: Longest step [s] whose sweep count grows with it (:meth:`StaticLinks.sweeps_at`); longer steps take its count (25
#: with the default 1 sweep, cold). The sweeps run at every step. They once stood aside beyond this step, where limp
#: hair (EI 1e-7) on their answer burst at one step a frame (3.5-16 m/s at 16-64 segments). Then the first, Jacobi pass
#: alone put energy into linked hair there: five strands tied side by side and parted by a still sphere gained 20 % of
#: their energy in a frame, and ``long_hair`` with its head collider off and the head still swung on at 150 mm/s RMS,
#: tips up to 1.4 m/s. On the sweeps the rise is 1 % and that hair comes to rest (0.013 mm/s in the 8th second); the
#: tips at one step a frame run 5.2 mm RMS from 16 substeps instead of 11.8, and the limp cells peak at 1.35-1.94 m/s
#: (the first pass alone reached 2.65). On 2 sweeps the 64-segment limp cell burst (3.6 m/s).
SWEEP_GROWTH_STEP = 1.0 / 45.0

#: The fewest sweeps a step takes, by the links' free-step rate at that step (:meth:`StaticLinks.free_step_rate`)
#: where it passes 8, :data:`hairwarp.solver.WARM_START_RATE`; below it a step's own count holds them, one sweep
#: where their typical rate allows the warm start (:meth:`StaticLinks.warm_rate`,
#: :data:`hairwarp.solver.WARM_START_TYPICAL_RATE`), else the two of a cold or gated step (on the turn below 5-50 N/m
#: held on two, rates 2.2-6.9, each frame at its own step): ``(rate up to, sweeps)`` for one sweep asked
#: (``links.sweeps``; more asked, that many times as many). Stiffness makes the links stiff against the strands'
#: inertia as a longer step does, but a step's count of its length alone held links of 70 N/m at most at 1/240 s (a
#: 60-degree turn of 150 guides of 0.35 m, 12 segments, links within 2 cm, 1.5 s; ``bench_spring_stability``): 100 N/m
#: (rate 9.8) blew up on the 2 sweeps a cold step takes. Between rates 12 and 19 whether fewer sweeps hold is a matter
#: of the run (6 held 150, 300 and 500 N/m and blew up at 200, 250 and 400; 8 at 200 and 250; 3 at 100), and 12 held
#: every stiffness measured from 120 to 7,000 N/m (rates 10.7-82); 4 held 80-100 N/m (rates 8.7-9.8), 16 held 10,000
#: (rate 98). Those runs took a faulted frame again in finer steps, beside the default scene's hair contacts, and took
#: the gated warm start past where it holds (:data:`hairwarp.solver.WARM_GATE_TYPICAL_RATIO`). With the links alone,
#: each frame at its step, their geometric stiffness in the sweeps (``kernels.sweeps.GEOMETRIC_STIFFNESS_FACTOR``) and
#: the gated force bounded, the step's own count holds every stiffness to 30,000 N/m at 1, 2, 4 and 8 substeps, and the
#: table keeps the links to their length: on the quick turn (60 guides, 0.5 s) links of 150, 1,000 and 10,000 N/m
#: ended 0.27-0.31 mm long on average on it against 0.72-0.81 on the cold step's two sweeps and 0.12-0.14 on 48, their
#: tips 22-28 mm from the 48-sweep run against 67.
STIFF_LINK_SWEEPS = ((8.0, 1), (10.0, 4), (85.0, 12), (math.inf, 16))

#: The percentile of the linked segments' free-step rates that :meth:`StaticLinks.warm_rate` takes.
WARM_RATE_PERCENTILE = 90.0

#: The vertex-face stiffness's largest density factor (``TriangleStrips.tri_stiffness_scale``, clamped to [1/4, 4]).
CONTACT_DENSITY_FACTOR = 4.0


def contact_step_rate(seg_mass, seg_length, stiffness: float, dt: float,
                      density: float = CONTACT_DENSITY_FACTOR) -> float:
    """The hair contacts' rate in a free step of ``dt`` seconds: ``dt sqrt(k / m)`` with ``k`` the stiffness
    ``stiffness`` (k0 [N/m]) times a density factor (``density``: the largest, :data:`CONTACT_DENSITY_FACTOR`, unless
    given; 1 for a strip of the typical density) and the median segment's length over
    :data:`REFERENCE_SEGMENT_LENGTH` (at least 1: a segment-segment contact's is k0), and ``m`` the median segment
    mass [kg] (``seg_mass``, ``seg_length`` per segment). ``interactions.response = "auto"`` solves contacts
    past ``hairwarp.runner.CONTACT_STEP_RATE`` after the free step, and a fault of the free step is theirs past
    ``hairwarp.solver.CONTACT_RATE_LIMIT``."""
    if not stiffness > 0.0:
        return 0.0
    length = max(1.0, float(np.median(np.asarray(seg_length, dtype=np.float64))) / REFERENCE_SEGMENT_LENGTH)
    mass = float(np.median(np.asarray(seg_mass, dtype=np.float64)))
    return float(dt) * math.sqrt(float(density) * length * float(stiffness) / mass)


#: Fewest segments per chunk of the gathers of link and contact forces (~20 ns a segment; in a step they run in the
#: integrator's chain, chunked by its strands).
GATHER_MIN_CHUNK = 256
#: The grain of :meth:`HairContacts._slots` and of the slots' sizes as they grow.
SLOT_GRAIN = 2048


def _grains(n: int) -> int:
    """``n`` slots rounded up to a whole number of :data:`SLOT_GRAIN`."""
    return -(-int(n) // SLOT_GRAIN) * SLOT_GRAIN

#: Fewest strands per chunk of the hair contacts' per-strand pass that keeps their forces for the next step
#: (``HairContacts.update_warm``).
WARM_MIN_CHUNK = 16


def strand_colors(strand_a, strand_b, strand_count: int) -> np.ndarray:
    """A colour per strand such that no two strands joined by a pair (``strand_a[i]``, ``strand_b[i]``) share one:
    greedy, the strands with the most partners first (Welsh and Powell), ties by index, so the colours are fixed by
    the pairs alone. A scalp's links make a near-planar graph of strands: 6 to 9 colours on the shipped scenes.
    Colours of one size do not pay: the mohawk's 147, 147, 96, 39, 11 and 4 strands, taken each by the colour its
    partners leave with the fewest strands so far instead, came out at 74 each, and its sweeps on two threads ran
    1.49 and 1.47 ms a step against 1.45 and 1.43 (one thread 2.46 against 2.45)."""
    strand_a = np.asarray(strand_a, dtype=np.int64)
    strand_b = np.asarray(strand_b, dtype=np.int64)
    pairs = np.unique(np.sort(np.stack([strand_a, strand_b], axis=1), axis=1), axis=0) if len(strand_a) else \
        np.zeros((0, 2), np.int64)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    start = np.searchsorted(both[:, 0], np.arange(strand_count + 1))
    degree = np.diff(start)
    colors = np.full(strand_count, -1, dtype=np.int32)
    for g in np.lexsort((np.arange(strand_count), -degree)):
        taken = set(colors[both[start[g]:start[g + 1], 1]].tolist())
        c = 0
        while c in taken:
            c += 1
        colors[g] = c
    return colors


class StaticLinks:
    """Breakable zero-rest-length springs between each segment and its nearest segments on other strands.

    Attributes:
        device: Warp device of the arrays.
        link_count: number of links L.
        seg_a, seg_b: numpy int32 (L,), the two segments of each link (flat ``g*S + k``); ``seg_a`` is the longer
            (the lower index on a tie) and carries the rest offset.
        frac_a, frac_b: numpy float64 (L,), attachment parameters along each segment (0 = vertex k, 1 = vertex k+1).
        rest_offset: numpy float64 (L, 3), r0 = x_b - x_a at rest [m], head frame.
        rest_axis: numpy float64 (L, 3), unit axis of segment a at rest, head frame; the offset follows a's axis from
            it by the least rotation (see ``kernels.links``).
        stiffness: k_s [N/m], damping: k_d [N s/m], of a link between segments :data:`REFERENCE_SEGMENT_LENGTH` long.
        scale: numpy float64 (L,), each link's factor on them, the mean length of its two segments over
            :data:`REFERENCE_SEGMENT_LENGTH`; link_scale: the same on the device.
        break_length: |l| [m] beyond which a link breaks for good.
        implicit_springs: whether each link's force is solved implicitly over the step (``kernels.links.link_forces``).
        link_seg_a, link_seg_b, link_frac_a, link_frac_b, link_rest_offset: the same on the device.
        seg_rest_axis: vec3 (G*S,) on the device, every segment's rest axis; seg_transport: quat (G*S,), scratch
            of the rotations carrying rest offsets to the segments' twist-free frames
            (``kernels.links.segment_transport``, for :meth:`break_links`).
        seg_link_start: int32 (G*S+1,) on the device: the links of segment a (as their side a) are
            ``seg_link_start[a]`` to ``seg_link_start[a + 1] - 1``.
        link_broken: int32 (L,) on the device, 1 once a link broke.
        link_broken_total: int32 (1,) on the device, the number of broken links.
        sweeps: the response's Gauss-Seidel sweeps per step of up to 1/240 s (``build``, :meth:`sweeps_at`).
        strand_colors: numpy int32 (G,), each strand's colour, no two linked strands sharing one
            (:func:`strand_colors`); strand_color_array: the same on the device; color_strands: int32 (G,) on the
            device, the strands by colour; color_views: a view of ``color_strands`` per colour, in order.
        strand_redo: int32 (G,) on the device, 1 where a link of the strand broke within the last step by the sweeps'
            answer (:meth:`update_warm`), which the sweeps then solve again.
        executor: the solver's :class:`hairwarp.executor.Executor` (set when a Solver takes the links), or None.
    """

    executor = None
    #: How many times the bound of each end's geometric stiffness the links' sweeps after the free step add to its
    #: segment's turn (``kernels.sweeps.GEOMETRIC_STIFFNESS_FACTOR``; 0 only to measure what it holds)
    geometric_stiffness = sweep_kernels.GEOMETRIC_STIFFNESS_FACTOR
    #: The longest link, in arms of its end, whose end takes that term whole (``kernels.sweeps.GEOMETRIC_ARM_RATIO``;
    #: a large number only to measure what it holds)
    geometric_arm_ratio = sweep_kernels.GEOMETRIC_ARM_RATIO

    @classmethod
    def build(
        cls,
        rest_vertices,
        *,
        neighbours: int = 3,
        radius: float,
        stiffness: float,
        damping: float,
        break_length: float,
        implicit_springs: bool = True,
        response: bool = False,
        sweeps: int = DEFAULT_SWEEPS,
        device=None,
    ) -> StaticLinks:
        """Link every segment to its ``neighbours`` nearest segments of other strands within ``radius``.

        Candidates come from a k-d tree of segment midpoints, then exact segment-segment distances pick the
        nearest; a pair chosen from both sides is one link. The link attaches at the two closest points, with the
        rest offset that makes it exactly slack at rest.

        Args:
            rest_vertices: (G, S+1, 3) vertex positions of the pose the links hold [m], in the head frame (the
                model's ``rest_vertex_positions``): rest offsets and axes are kept in that frame.
            neighbours: links made per segment (n of the seed).
            radius: largest segment-segment distance that gets a link [m].
            stiffness: spring stiffness k_s [N/m] of a link between segments :data:`REFERENCE_SEGMENT_LENGTH` long;
                each link takes it times the mean length of its two segments over that length (:attr:`scale`).
            damping: damping k_d [N s/m], scaled the same way.
            break_length: a link breaks for good when |l| exceeds this [m].
            implicit_springs: each link's force is its backward-Euler force over the step against a bound of the
                inverse masses at its ends (``kernels.links.link_forces``), which keeps stiff links stable at
                frame-rate steps without adding inertia to the hair they tie; False leaves them explicit, for
                comparison. Not used with ``response``.
            response: each link's force over the step is solved after the free step, inside the strands'
                dynamics, on the relative motion of its ends (``kernels.sweeps.link_sweep``;
                :class:`hairwarp.Solver` runs it), for steps of 1/220 s and longer (the scenes'
                ``links.response = "auto"``). The per-link solve it replaces bounds each end's inverse mass by its
                free segment's, which at 2 substeps a frame softened the links tenfold.
            sweeps: with ``response``, block Gauss-Seidel sweeps over the strands' colours per step of up to
                :data:`SWEEP_REFERENCE_STEP`, more at longer steps (:meth:`sweeps_at`;
                ``kernels.sweeps.link_sweep``): each strand is solved with the strands it is linked to or touches
                (its hair contacts, on the CPU) held at their latest velocities; more sweeps converge toward the
                backward-Euler step of the whole lattice and its contacts. The count is taken on the host at each
                step, so a step captured in a graph keeps the count of the step it was captured at.
            device: Warp device.
        """
        verts = _check_vertices(rest_vertices)
        G, S = verts.shape[0], verts.shape[1] - 1
        for name, value in (("radius", radius), ("break_length", break_length)):
            if not value > 0.0:
                raise InteractionError(f"{name} must be > 0, got {value}")
        for name, value in (("stiffness", stiffness), ("damping", damping)):
            if not 0.0 <= value < math.inf:
                raise InteractionError(f"{name} must be a finite number >= 0, got {value}")
        if int(neighbours) < 1:
            raise InteractionError(f"neighbours must be >= 1, got {neighbours}")
        if int(sweeps) < 1:
            raise InteractionError(f"sweeps must be >= 1, got {sweeps}")
        p0 = verts[:, :-1].reshape(-1, 3)
        p1 = verts[:, 1:].reshape(-1, 3)
        pairs = _nearest_segment_pairs(p0, p1, np.repeat(np.arange(G), S), int(neighbours), float(radius))
        # The rest offset hangs on segment a's frame as a lever: on the longer segment of the pair. On a stub
        # strand's tiny segments (45 um on the Ratboy mohawk) a lever of the link radius turns the joint ~100x
        # faster than the segment's own length allows, and a turning head blows the strand up.
        length = np.linalg.norm(p1 - p0, axis=1)
        swap = length[pairs[:, 1]] > length[pairs[:, 0]]
        a = np.where(swap, pairs[:, 1], pairs[:, 0])
        b = np.where(swap, pairs[:, 0], pairs[:, 1])
        order = np.lexsort((b, a))  # by segment a: neighbouring threads read neighbouring frames
        a, b = a[order], b[order]
        fa, fb, _ = closest_points_segments(p0[a], p1[a], p0[b], p1[b])

        xa = p0[a] + fa[:, None] * (p1[a] - p0[a])
        xb = p0[b] + fb[:, None] * (p1[b] - p0[b])
        r0 = xb - xa
        axis = (p1[a] - p0[a]) / length[a, None]

        links = cls()
        links.device = wp.get_device(device)
        links.stiffness = float(stiffness)
        links.damping = float(damping)
        links.break_length = float(break_length)
        links.implicit_springs = bool(implicit_springs)
        links.response = bool(response)
        # with ``response``: the free step takes each link's force of the last step (``link_warm``) and the response
        # the change (set by ``hairwarp.Solver.set_dt`` for each step)
        links.warm_start = False
        # with ``warm_start`` at long steps: the speed [m/s] by which the force kept falls off with the ends' relative
        # speed (``kernels.links.link_response_ends``); 0 keeps it whole (set with ``warm_start``)
        links.warm_gate = 0.0
        links.seg_a = a.astype(np.int32)
        links.seg_b = b.astype(np.int32)
        links.frac_a = fa
        links.frac_b = fb
        links.rest_offset = r0
        links.rest_axis = axis
        # each link's share of the lattice: the mean length of the segments it joins against REFERENCE_SEGMENT_LENGTH
        links.scale = 0.5 * (length[a] + length[b]) / REFERENCE_SEGMENT_LENGTH
        # each end's free-segment inverse mass times its mass, ``1 + 12 |r|^2 / L^2``
        # (``kernels.links.point_inverse_mass``), ``r`` from the segment's centre to the end: a's end carries the rest
        # offset, which the transport turns with the segment, so |r| keeps its rest length
        arm_a = (fa - 0.5)[:, None] * (p1[a] - p0[a]) + r0
        arm_b = (fb - 0.5)[:, None] * (p1[b] - p0[b])
        links.lever_a = 1.0 + 12.0 * np.sum(arm_a * arm_a, axis=1) / length[a] ** 2
        links.lever_b = 1.0 + 12.0 * np.sum(arm_b * arm_b, axis=1) / length[b] ** 2
        links._seg_damper_weight = None
        links.link_count = len(a)
        n = max(links.link_count, 1)
        dev = links.device
        links.link_seg_a = wp.array(links.seg_a if len(a) else np.zeros(n, np.int32), dtype=wp.int32, device=dev)
        links.link_seg_b = wp.array(links.seg_b if len(a) else np.zeros(n, np.int32), dtype=wp.int32, device=dev)
        links.link_frac_a = wp.array(fa if len(a) else np.zeros(n), dtype=float, device=dev)
        links.link_frac_b = wp.array(fb if len(a) else np.zeros(n), dtype=float, device=dev)
        links.link_rest_offset = wp.array(r0 if len(a) else np.zeros((n, 3)), dtype=wp.vec3, device=dev)
        links.link_rest_axis = wp.array(axis if len(a) else np.zeros((n, 3)), dtype=wp.vec3, device=dev)
        links.link_scale = wp.array(links.scale if len(a) else np.zeros(n), dtype=float, device=dev)
        links.link_broken = wp.zeros(n, dtype=wp.int32, device=dev)
        links.link_broken_total = wp.zeros(1, dtype=wp.int32, device=dev)
        rest_axis = (p1 - p0) / length[:, None]
        links.seg_rest_axis = wp.array(rest_axis, dtype=wp.vec3, device=dev)
        links.seg_transport = wp.zeros(G * S, dtype=wp.quat, device=dev)
        # Links by segment a (sorted so above): segment a's links are seg_link_start[a] .. seg_link_start[a + 1] - 1.
        links.seg_link_start = wp.array(np.searchsorted(a, np.arange(G * S + 1)).astype(np.int32), dtype=wp.int32,
                                        device=dev)
        # Segment b's shares by b (in link order): link l leaves its share in slot link_b_slot[l], segment b sums
        # slots seg_b_start[b] .. seg_b_start[b + 1] - 1 (``kernels.links.link_gather``).
        by_b = np.argsort(b, kind="stable")
        slot = np.empty(len(b), np.int64)
        slot[by_b] = np.arange(len(b))
        links.link_b_slot = wp.array(slot.astype(np.int32) if len(a) else np.zeros(n, np.int32), dtype=wp.int32,
                                     device=dev)
        links.seg_b_start = wp.array(np.searchsorted(b[by_b], np.arange(G * S + 1)).astype(np.int32),
                                     dtype=wp.int32, device=dev)
        links.b_force = wp.zeros(n, dtype=wp.vec3, device=dev)
        links.b_torque = wp.zeros(n, dtype=wp.vec3, device=dev)
        # the response's: each link's ends at the step's start, and the link of each of b's slots
        links.link_point_a = wp.zeros(n, dtype=wp.vec3, device=dev)
        links.link_point_b = wp.zeros(n, dtype=wp.vec3, device=dev)
        # each link's force of the last step as the response answered it [N, world, on a's end]: ``warm_start``
        links.link_warm = wp.zeros(n, dtype=wp.vec3, device=dev)
        links.b_slot_link = wp.array(by_b.astype(np.int32) if len(a) else np.zeros(n, np.int32), dtype=wp.int32,
                                     device=dev)
        # what the sweeps read of each link end, a ends then b slots
        links.ends = link_kernels.LinkEnds()
        for name, size in (("force", 2 * n), ("arm", 2 * n), ("axis", n), ("twist_g", n), ("twist_m", n),
                           ("kept_g", n), ("kept_m", n)):
            setattr(links.ends, name, wp.zeros(size, dtype=wp.vec3, device=dev))
        # the response's sweeps: strands coloured so that no two of a colour are linked
        links.sweeps = int(sweeps)
        links.strand_colors = strand_colors(a // S, b // S, G)
        order = np.lexsort((np.arange(G), links.strand_colors)).astype(np.int32)
        links.color_strands = wp.array(order, dtype=wp.int32, device=dev)
        links.strand_color_array = wp.array(links.strand_colors.astype(np.int32), dtype=wp.int32, device=dev)
        bounds = np.searchsorted(links.strand_colors[order], np.arange(links.strand_colors.max(initial=0) + 2))
        links.color_views = [links.color_strands[int(lo):int(hi)] for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]
        # links broken within a step by the sweeps' answer (``update_warm``), and the strands the sweeps solve again
        links.strand_redo = wp.zeros(G, dtype=wp.int32, device=dev)
        return links

    def _transport(self, model, state):
        wp.launch(link_kernels.segment_transport, dim=len(self.seg_transport),
                  inputs=[model.seg_per_strand, self.seg_rest_axis, state.seg_xform, state.joint_q],
                  outputs=[self.seg_transport], device=self.device)

    def apply(self, model, state, dt, seg_force, seg_torque, seg_implicit_mass):
        """Break the links of ``state`` stretched past ``break_length``, and accumulate the forces of the others into
        the solver's per-segment arrays (launch only).

        Breaking and forces share one pass over the links: a link breaks at the start of the step in which it
        would act stretched past its break length (as :meth:`break_links` applied to the previous step's end would
        have found it) and acts no more.
        """
        self.apply_forces(model, state, dt, seg_force, seg_torque)
        self.gather(model, seg_force, seg_torque, seg_implicit_mass)

    def apply_forces(self, model, state, dt, seg_force, seg_torque):
        """The first pass of :meth:`apply`: breaking, and each segment a's side of its links (b's shares are left
        for :meth:`gather`). Independent of the hair contacts' and the colliders' passes."""
        if self.link_count == 0:
            return
        inputs = [
            model.seg_per_strand, model.seg_length, model.seg_mass, self.seg_rest_axis,
            self.seg_link_start, self.link_seg_b, self.link_frac_a, self.link_frac_b, self.link_rest_offset,
            self.stiffness, self.damping, self.link_scale, self.seg_damper_weight(model), self.break_length,
            int(self.implicit_springs),
            state.seg_xform, state.joint_q, state.vertex_positions, state.vertex_velocities, dt, self.link_b_slot,
            int(self.response), int(self.warm_start), self.link_warm,
        ]
        n = len(inputs)
        seg_count = len(self.seg_transport)
        # A thread adds into its own segment a and leaves b's share in a slot of b's; then each segment b gathers
        # its slots. No segment is written by two threads: the same bits however the segments are split.
        launch(self.executor, link_kernels.link_forces, seg_count, inputs,
               [seg_force, seg_torque, self.link_broken, self.link_broken_total, self.b_force, self.b_torque,
                self.link_point_a, self.link_point_b, self.ends.twist_g, self.ends.twist_m],
               device=self.device, min_chunk=SEGMENT_MIN_CHUNK, private_add=[n + 3])

    def seg_damper_weight(self, model):
        """Per segment, the sum over the links it carries (either end) of each link's scale times the bound of its
        end's inverse mass (``kernels.links.point_inverse_mass``) [1/kg], on the device (float32, ``G*S``; built on
        the first call from ``model``'s masses): ``h (h k + c)`` times this (``k`` the link stiffness, whose
        backward-Euler force damps over the step too, ``c`` the damping) is the share of its velocity the segment's
        links' dampers, each solved alone in the free step, take from it in one step (``kernels.links.link_forces``
        caps their damping where it passes one). Links that break keep their share: the cap errs toward less damping,
        never toward a damper that reverses its segment."""
        if self._seg_damper_weight is None:
            mass = model.seg_mass.numpy().astype(np.float64)
            weight = np.zeros(len(mass))
            if self.link_count:
                weight = (np.bincount(self.seg_a, self.scale * self.lever_a / mass[self.seg_a], minlength=len(mass))
                          + np.bincount(self.seg_b, self.scale * self.lever_b / mass[self.seg_b], minlength=len(mass)))
            self._seg_damper_weight = wp.array(weight, dtype=float, device=self.device)
        return self._seg_damper_weight

    def damping_load(self, model, dt: float) -> np.ndarray:
        """Per linked segment, how many times what its links' dampers may take in a step of ``dt`` the damping asks
        (``kernels.links.damper_cap``, in float64 on the host): ``h c W`` over what the stiffness's own damper of the
        step, ``h^2 k W``, leaves of 1 (``W``: :meth:`seg_damper_weight`; inf where it leaves none). Past 1 the
        free step caps the segment's links' damping."""
        weight = self.seg_damper_weight(model).numpy().astype(np.float64)
        weight = weight[weight > 0.0]
        room = 1.0 - dt * dt * self.stiffness * weight * float(self.implicit_springs)
        damper = dt * self.damping * weight
        return np.divide(damper, room, out=np.full_like(damper, np.inf), where=room > 0.0)

    def prepare_response(self, model, state_in, state_out, dt):
        """What the sweeps read of each link end over the step (:attr:`ends`): its force on its own free velocities
        (``state_out``'s) and the link's axis (``link_response_ends``; launch only)."""
        if self.link_count == 0:
            return
        self._response_ends(model, state_in, state_out.vertex_velocities, dt, answered=False, break_solved=False)

    def update_warm(self, model, state_in, answered_velocities, dt, break_solved: bool = False) -> bool:
        """Keep each link's force of the step as the sweeps answered it (:attr:`link_warm`), which the next step's
        free step takes with :attr:`warm_start` (``link_response_ends`` with ``answered``; launch only). With
        ``break_solved``, links whose ends the answer carries past their break length break within the step instead,
        their strands marked in :attr:`strand_redo` (zeroed first). With :attr:`warm_gate` each link keeps the share
        of its force that its ends' parting speed leaves. Returns whether it launched."""
        if self.link_count == 0 or not (self.warm_start or break_solved):
            return False
        if break_solved:
            if self.executor is not None:
                self.executor.zero(self.strand_redo)
            else:
                self.strand_redo.zero_()
        self._response_ends(model, state_in, answered_velocities, dt, answered=True, break_solved=break_solved)
        return True

    def _response_ends(self, model, state_in, velocities, dt, *, answered: bool, break_solved: bool):
        inputs = [model.seg_per_strand, self.stiffness, self.damping, self.link_scale, self.link_point_a,
                  self.link_point_b, self.link_broken, self.link_seg_a, self.link_seg_b, self.link_b_slot,
                  int(self.warm_start), self.link_warm, state_in.vertex_positions, velocities, dt, int(answered),
                  int(break_solved), self.break_length, self.warm_gate]
        # the count of links broken adds up per chunk where they may break (``hairwarp.executor``)
        launch(self.executor, link_kernels.link_response_ends, self.link_count, inputs,
               [self.ends, self.link_broken_total, self.strand_redo], device=self.device, min_chunk=GATHER_MIN_CHUNK,
               private_add=[len(inputs) + 1] if break_solved else [])

    def free_step_rate(self, seg_mass: np.ndarray, dt: float) -> float:
        """The links' rate in a free step of ``dt`` seconds: ``dt sqrt(k / m)`` with ``k`` the most link stiffness
        on one segment (each link's scaled by its segments' lengths, :attr:`scale`) and ``m`` the median segment
        mass of ``seg_mass`` (kg, per segment); 0 without links or stiffness. The scenes' ``links.response =
        "auto"`` solves links past ``hairwarp.runner.LINK_STEP_RATE`` after the free step, and a fault of the
        free step is theirs past ``hairwarp.solver.LINK_RATE_LIMIT``."""
        if self.link_count == 0 or not self.stiffness > 0.0:
            return 0.0
        seg_mass = np.asarray(seg_mass, dtype=np.float64)
        per_segment = self._segment_scale(len(seg_mass)).max()
        return dt * math.sqrt(per_segment * self.stiffness / float(np.median(seg_mass)))

    def _segment_scale(self, seg_count: int) -> np.ndarray:
        """Per segment, the summed :attr:`scale` of the link ends it carries (float64, ``seg_count``)."""
        ends = np.concatenate([self.seg_a, self.seg_b])
        return np.bincount(ends, weights=np.tile(self.scale, 2), minlength=seg_count)

    def warm_rate(self, seg_mass: np.ndarray, dt: float) -> float:
        """The links' typical rate in a free step of ``dt`` seconds, which bounds their warm start
        (``hairwarp.Solver._warm_start``): the :data:`WARM_RATE_PERCENTILE` th percentile over the linked segments of
        ``dt sqrt(k / m)``, ``k`` the segment's summed link stiffness (each link's scaled, :attr:`scale`) and ``m`` its
        own mass (kg, ``seg_mass`` per segment); 0 without links or stiffness. Where :meth:`free_step_rate` takes the
        stiffest segment against the median mass, this takes the many stiff ones: the lagged force grows where they
        tie the hair together, not at a few short segments of a groom whose segments' lengths vary 70-fold (the Ratboy
        mohawk, whose stiffest segment's rate is twice this)."""
        if self.link_count == 0 or not self.stiffness > 0.0:
            return 0.0
        seg_mass = np.asarray(seg_mass, dtype=np.float64)
        per_segment = self._segment_scale(len(seg_mass))
        linked = per_segment > 0.0
        rates = np.sqrt(per_segment[linked] * self.stiffness / seg_mass[linked])
        return dt * float(np.percentile(rates, WARM_RATE_PERCENTILE))

    def step_sweeps(self, dt: float, rate: float = 0.0) -> int:
        """The sweeps a step of ``dt`` seconds takes as the links start it now (:attr:`warm_start`,
        :attr:`warm_gate`, set by the solver for the step): a warm step's count where it takes the whole force of the
        last step, a cold step's where it takes none or the gated share; and at least the count
        :data:`STIFF_LINK_SWEEPS` gives links of free-step ``rate`` (:meth:`free_step_rate` at ``dt``)."""
        return self.sweeps_starting(dt, rate, cold=not self.warm_start or self.warm_gate > 0.0)

    def sweeps_starting(self, dt: float, rate: float, cold: bool) -> int:
        """The sweeps a step of ``dt`` seconds takes with links of free-step ``rate``, started ``cold`` (with none
        or the gated share of the last force) or warm: :meth:`sweeps_at`, and at least the count
        :data:`STIFF_LINK_SWEEPS` gives the rate."""
        count = max(1, self.sweeps_at(dt, cold=cold))
        stiff = next(n for limit, n in STIFF_LINK_SWEEPS if rate <= limit)
        return max(count, self.sweeps * stiff)

    def sweeps_at(self, dt: float, cold: bool = False) -> int:
        """The sweeps a step of ``dt`` seconds takes. One that starts from the links' force of the last step
        (:attr:`warm_start`): :attr:`sweeps` up to :data:`SWEEP_REFERENCE_STEP`, and a step k times as long
        k ** :data:`WARM_SWEEP_GROWTH` times as many (rounded up). One that starts ``cold``: :data:`COLD_SWEEPS` times
        as many up to that step and k ** :data:`SWEEP_GROWTH` times those at longer ones. Steps longer than
        :data:`SWEEP_GROWTH_STEP` take its count. With the default 1: 1 at 8 substeps of 30 fps, 16 at 2, and 25 at
        one step a frame, which starts cold (or from the gated share of the last force, :attr:`warm_gate`, which
        takes a cold step's count: :meth:`step_sweeps`)."""
        k = min(float(dt), SWEEP_GROWTH_STEP) / SWEEP_REFERENCE_STEP
        base, growth = (self.sweeps * COLD_SWEEPS, SWEEP_GROWTH) if cold else (self.sweeps, WARM_SWEEP_GROWTH)
        return max(base, math.ceil(base * k ** growth - 1e-9))

    def gather(self, model, seg_force, seg_torque, seg_implicit_mass):
        """The second pass of :meth:`apply`: every segment b adds its shares. ``seg_implicit_mass`` is left as it
        is (the links' implicit part is in their forces); it is taken so that links and contacts share the call."""
        if self.link_count == 0:
            return
        seg_count = len(self.seg_transport)
        launch(self.executor, link_kernels.link_gather, seg_count, [self.seg_b_start, self.b_force, self.b_torque],
               [seg_force, seg_torque], device=self.device, min_chunk=GATHER_MIN_CHUNK)

    def break_links(self, model, state):
        """Break, for good, the links of ``state`` stretched past ``break_length`` (launch only): the test that
        :meth:`apply` makes in its pass, for a state no force is computed at."""
        if self.link_count == 0:
            return
        self._transport(model, state)
        wp.launch(
            link_kernels.link_break,
            dim=self.link_count,
            inputs=[
                model.seg_length, self.link_seg_a, self.link_seg_b, self.link_frac_a, self.link_frac_b,
                self.link_rest_offset, self.break_length, state.seg_xform, self.seg_transport,
            ],
            outputs=[self.link_broken, self.link_broken_total],
            device=self.device,
        )

    def broken_count(self) -> int:
        """Number of broken links (host read; call once per output frame, outside a captured step)."""
        return int(self.link_broken_total.numpy()[0])

    def reset(self):
        """Mend every link (for a new run from the rest pose)."""
        self.link_broken.zero_()
        self.link_broken_total.zero_()


class TriangleStrips:
    """Triangle strips between guide strands with adjacent roots (topology; :class:`HairContacts` keeps their BVH).

    Pair ``p = (a, b)`` and segment ``k`` make quad ``q = S p + k``, split into triangles
    ``2q = (a_k, b_k, a_{k+1})`` and ``2q + 1 = (b_k, b_{k+1}, a_{k+1})``, as indices ``g*(S+1) + k`` into the
    guide vertex array, so the strips follow the state's vertices without a copy.

    Attributes:
        device: Warp device.
        strand_count: G. seg_per_strand: S. pair_count: number of strand pairs P. quad_count: S P.
        tri_count: 2 S P.
        pairs: numpy int32 (P, 2), the strand pairs (a < b).
        tri_width: numpy float64 (2SP,), rest length of each triangle's "horizontal" edge (a_k b_k or
            a_{k+1} b_{k+1}) [m]; width_ref: its median s0.
        max_width: 4 s0 [m]: a quad whose current horizontal edges are wider is no contact surface (at that width
            its density factor s0 / s would fall below the clamp; the strands have parted, there is no hair between
            them). On the Ratboy mohawk this drops 5 % of the quads at rest, the most stretched, whose boxes hold
            20 % of what a vertex meets; once the hair falls, 9 % holding 60 %.
        indices: int32 (3 * 2SP,) on the device, the triangles.
        tri_stiffness_scale: float32 (2SP,) on the device, s0 / s clamped to [1/4, 4], the density factor of the
            vertex-face stiffness.
        strip_pairs: vec2i (P,) on the device, ``pairs``.
        strand_neighbour_start, strand_neighbours: int32 (G+1,) and (2P,) on the device: the root neighbours of
            strand g (the other strands of its strips) are ``strand_neighbours[start[g]:start[g+1]]``.
    """

    @classmethod
    def build(
        cls, rest_vertices, root_uv=None, grid_shape=None, *, max_edge_ratio: float = 2.0, device=None
    ) -> TriangleStrips:
        """Pair strands with adjacent roots and build their strips.

        Adjacency comes from ``grid_shape = (rows, cols)`` (strand ``r*cols + c``, pairs along rows and
        columns), else from the Delaunay triangulation of ``root_uv`` (G, 2), else from the convex hull of the
        3-D root positions (or, for roots in a plane, a Delaunay triangulation in that plane). Triangulation edges
        longer than ``max_edge_ratio`` times the median edge are dropped (they bridge gaps, not neighbours).
        """
        verts = _check_vertices(rest_vertices)
        G, S = verts.shape[0], verts.shape[1] - 1
        if grid_shape is not None:
            rows, cols = (int(x) for x in grid_shape)
            if rows * cols != G:
                raise InteractionError(f"grid_shape {grid_shape} holds {rows * cols} strands, the groom has {G}")
            idx = np.arange(G).reshape(rows, cols)
            pairs = np.concatenate([
                np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1),
                np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1),
            ])
        else:
            if not max_edge_ratio > 1.0:
                raise InteractionError(f"max_edge_ratio must be > 1, got {max_edge_ratio}")
            pairs = _root_adjacency(verts[:, 0], root_uv, max_edge_ratio)
        pairs = np.sort(pairs.reshape(-1, 2), axis=1).astype(np.int32)
        pairs = np.unique(pairs, axis=0) if len(pairs) else pairs

        strips = cls()
        strips.device = wp.get_device(device)
        strips.strand_count, strips.seg_per_strand = G, S
        strips.pairs = pairs
        strips.pair_count = len(pairs)
        strips.quad_count = S * len(pairs)
        strips.tri_count = 2 * S * len(pairs)
        both = np.concatenate([pairs, pairs[:, ::-1]]) if len(pairs) else np.zeros((0, 2), np.int32)
        both = both[np.lexsort((both[:, 1], both[:, 0]))]
        start = np.searchsorted(both[:, 0], np.arange(G + 1)).astype(np.int32)
        strips.strand_neighbour_start = wp.array(start, dtype=wp.int32, device=strips.device)
        strips.strand_neighbours = wp.array(both[:, 1].copy() if len(both) else np.zeros(1, np.int32),
                                            dtype=wp.int32, device=strips.device)
        if strips.pair_count == 0:
            strips.tri_width = np.zeros(0)
            strips.width_ref = 0.0
            strips.max_width = 0.0
            strips.indices = wp.zeros(3, dtype=wp.int32, device=strips.device)
            strips.tri_stiffness_scale = wp.zeros(1, dtype=float, device=strips.device)
            strips.strip_pairs = wp.zeros(1, dtype=wp.vec2i, device=strips.device)
            return strips
        strips.strip_pairs = wp.array(pairs, dtype=wp.vec2i, device=strips.device)

        k = np.arange(S)
        va = pairs[:, 0:1] * (S + 1) + k  # (P, S): vertex a_k
        vb = pairs[:, 1:2] * (S + 1) + k
        tri = np.stack([
            np.stack([va, vb, va + 1], axis=-1),
            np.stack([vb, vb + 1, va + 1], axis=-1),
        ], axis=2).reshape(-1, 3)  # (P, S, 2, 3) -> (2SP, 3)
        flat = verts.reshape(-1, 3)
        # Horizontal edge: a_k b_k for the first triangle of a segment pair, a_{k+1} b_{k+1} for the second.
        width = np.stack([
            np.linalg.norm(flat[va] - flat[vb], axis=-1),
            np.linalg.norm(flat[va + 1] - flat[vb + 1], axis=-1),
        ], axis=2).reshape(-1)
        strips.tri_width = width
        strips.width_ref = float(np.median(width))
        strips.max_width = _MAX_DENSITY_SCALE * strips.width_ref
        scale = strips.width_ref / np.maximum(width, strips.width_ref / _MAX_DENSITY_SCALE)
        scale = np.maximum(scale, 1.0 / _MAX_DENSITY_SCALE)
        strips.indices = wp.array(tri.reshape(-1).astype(np.int32), dtype=wp.int32, device=strips.device)
        strips.tri_stiffness_scale = wp.array(scale, dtype=float, device=strips.device)
        return strips


def _root_adjacency(roots: np.ndarray, root_uv, max_edge_ratio: float) -> np.ndarray:
    """Edges (E, 2) between strands whose roots are neighbours, without the long edges of the triangulation."""
    from scipy.spatial import ConvexHull, Delaunay, QhullError

    G = len(roots)
    if G < 2:
        return np.zeros((0, 2), np.int32)
    if G == 2:
        return np.array([[0, 1]], np.int32)
    if root_uv is not None:
        pts = np.asarray(root_uv, dtype=np.float64)
        if pts.shape != (G, 2):
            raise InteractionError(f"root_uv: expected shape ({G}, 2), got {pts.shape}")
        simplices = Delaunay(pts).simplices
    else:
        pts = roots
        try:
            simplices = ConvexHull(roots).simplices
        except QhullError:
            # Roots in a plane (or a line): triangulate in their principal plane.
            centred = roots - roots.mean(axis=0)
            basis = np.linalg.svd(centred, full_matrices=False)[2][:2]
            pts = centred @ basis.T
            try:
                simplices = Delaunay(pts).simplices
            except QhullError:
                order = np.argsort(pts[:, 0])
                return np.stack([order[:-1], order[1:]], axis=1).astype(np.int32)
    edges = np.concatenate([simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    length = np.linalg.norm(pts[edges[:, 0]] - pts[edges[:, 1]], axis=1)
    return edges[length <= max_edge_ratio * np.median(length)].astype(np.int32)


#: Fewest blocks per chunk of the bounds and detection launches (``hairwarp.executor``).
BLOCK_MIN_CHUNK = 64

#: Chunks per thread of a detection launch: each has a contact buffer of the full capacity of its own.
DETECT_CHUNKS_PER_THREAD = 4

#: Frames between rebuilds of the hair contacts' BVHs on the CPU, which the runner refits in between
#: (``HairContacts.detect``). On the Ratboy mohawk's 444 guides in motion, detection a frame took 7.6 ms refit against
#: 10.3 rebuilt on one thread (5.7 and 4.4 on two); a rebuild every 8 frames 7.9.
REBUILD_FRAMES = 8

#: Fewest force threads per chunk of the contact forces (each takes a run of 1/256 of the stored contacts).
FORCE_MIN_CHUNK = 16

#: Pairs found a guide vertex from which an overflow of the contacts' slots is put down to the threshold rather than
#: to the capacity (:meth:`HairContacts.overflow_advice`): hair pressed together finds a few (``fast_turn``'s turn 18
#: at its densest, ``long_hair`` 2), a threshold far past a wisp's thickness hundreds (``long_hair`` with
#: ``interactions.threshold`` 0.03, 0.1 and 0.2 m: 101, 828 and 2,600; at 0.2 m it blew up in its second frame at
#: any step).
THRESHOLD_PAIRS = 64

#: Where a detection finds more pairs than slots (and fewer than :data:`THRESHOLD_PAIRS` a guide vertex), the slots
#: grow to this many times the pairs found (:meth:`HairContacts.detect`), so hair that keeps gathering does not grow
#: them at every frame.
GROWTH = 1.25


class HairContacts:
    """Vertex-face (guide vertices against strips) and segment-segment contacts, with fixed-capacity buffers.

    Attributes:
        device: Warp device. strand_count: G. seg_per_strand: S.
        strips: the :class:`TriangleStrips`, or None (no vertex-face contacts).
        segment_segment: whether segment-segment contacts are detected.
        threshold: contact distance [m]; margin: extra detection distance [m]; detect_each_step: see ``build``;
            stiffness: k0 [N/m]; damping: normal damping [N s/m]; friction: mu;
            slip_velocity: regularisation speed of the Coulomb law [m/s]; capacity: contact slots;
            alignment_cutoff: least ``1 - |T_a . T_b|`` of a contact; skip_neighbour_strips, implicit_springs: see
            ``build``.
        seg_lowers, seg_uppers: vec3 (G*S,), segment boxes grown by threshold + margin; seg_dir: their unit
            directions.
        seg_block_lowers, seg_block_uppers: vec3, the boxes of blocks of ``SEG_BLOCK`` consecutive segments of a
            strand, in the ``seg_bvh``; seg_block_axes, seg_block_spreads: vec3, vec2, the cones of their directions.
        quad_lowers, quad_uppers, quad_plane, quad_slab, quad_dir: per strip quad (``S P``): grown box, mean plane,
            slab half-width and along-strand direction (see ``kernels.contacts.strip_bounds``).
        vertex_tangents: vec3 (G*(S+1),), the unit strand tangents of the last detection.
        strip_lowers, strip_uppers: vec3, the boxes of blocks of ``QUAD_BLOCK`` consecutive quads of a strip, in the
            ``strip_bvh``; strip_axes, strip_spreads: vec3, vec2, the cones of their quads' directions. A
            ``wp.Bvh`` rather than a ``wp.Mesh``: ``Bvh.refit`` is recorded by a CPU graph capture, ``Mesh.refit``
            is not (Warp 1.19), and the boxes read the state's vertices directly.
        contact_kind: int32 (capacity,): ``CONTACT_VERTEX_FACE`` (a = vertex, b = triangle, w = barycentric
            weights) or ``CONTACT_SEGMENT_SEGMENT`` (a, b = segments, w = (s, t, 0) along each).
        contact_a, contact_b: int32 (capacity,). contact_w: vec3 (capacity,).
        contact_gap: float32 (capacity,), the distance of the pair's two elements in the rest pose (``rest_gaps``)
            or the threshold [m]: it repels below ``min(threshold, gap)``.
        rest_positions: vec3 (G*(S+1),), ``rest_vertices`` on the device.
        contact_counter: int32 (1,), contacts found in the last step (may exceed the capacity).
        contact_overflow: int32 (1,), 1 once a step found more contacts than the capacity (sticky).
        buffer: the ``kernels.contacts.ContactBuffer`` of these arrays, as the kernels take them.
        sweep_contacts: the ``kernels.contacts.SweepContacts`` the links' sweeps solve in a step, listed by
            :meth:`gather_response` (on the CPU).
        warm_force, warm_torque: vec3 (G*S,), each segment's contact force [N, world] and torque about its origin
            [N m, world] in the last step's answer of the links' sweeps, kept by :meth:`update_warm` for the next free
            step where :attr:`warm_start` is set.
        executor: the solver's :class:`hairwarp.executor.Executor` (set when a Solver takes the contacts), or None.
    """

    executor = None
    #: Whether the free step takes each segment's contact force of the last step (:attr:`warm_force`,
    #: :attr:`warm_torque`), the links' sweeps solving the change (set by the solver: ``Solver.contact_warm_start``)
    warm_start = False
    #: Speed [m/s] of a pair's relative motion at which its force kept for the next step is halved
    #: (``kernels.contacts.contact_warm_forces``; 0: kept whole)
    warm_gate = 0.0
    _chunk_buffers = None
    _chunk_slots = None  # slots of each chunk's buffer (``_chunk_contact_buffers``)
    _order_views = None  # host views of the contact arrays (``_canonical_order``)
    #: Grow the slots where a detection finds more pairs than they hold (:meth:`detect`; :attr:`grown` lists each
    #: time: the slots before and the pairs found). Off, such a detection keeps what fits and raises the overflow flags.
    grows = False
    #: add the contacts' forces with atomics as on a GPU (one thread, for tests), not by the per-segment gather
    scatter = False
    #: The pair rate up to which a contact solved after the free step takes its stiffness
    #: (``kernels.contacts.CONTACT_RESPONSE_RATE_LIMIT``; read when the response's buffers are made)
    response_rate_limit = contact_kernels.CONTACT_RESPONSE_RATE_LIMIT

    @classmethod
    def build(
        cls,
        rest_vertices,
        strips: TriangleStrips | None = None,
        *,
        threshold: float,
        stiffness: float,
        damping: float = 0.0,
        friction: float = 0.0,
        slip_velocity: float = 1.0e-3,
        capacity: int,
        alignment_cutoff: float = 1.0e-2,
        segment_segment: bool = True,
        margin: float = 0.0,
        detect_each_step: bool = True,
        skip_neighbour_strips: bool = True,
        rest_gaps: bool = True,
        implicit_springs: bool = True,
        response: bool = False,
        device=None,
    ) -> HairContacts:
        """Allocate the segment and strip BVHs and the contact buffers.

        Args:
            rest_vertices: (G, S+1, 3) vertex positions for the initial BVH [m].
            strips: strips for vertex-face contacts, or None.
            threshold: pairs closer than this interact [m].
            stiffness: repulsion stiffness k0 [N/m] (vertex-face: scaled by the strip's density factor).
            damping: normal damping [N s/m].
            friction: Coulomb coefficient mu.
            slip_velocity: tangential speed below which friction fades linearly to zero [m/s].
            capacity: contact slots per step (both kinds together).
            alignment_cutoff: pairs with ``1 - |T_a . T_b|`` below this are not contacts; their repulsion is below
                this fraction of a right-angle crossing's. 1e-2 (8 degrees) drops most neighbour pairs of a combed
                groom, and on the Ratboy mohawk in motion a fifth of the repelling pairs, which give 1 % of the
                repulsion; 0 keeps every pair.
            segment_segment: detect segment-segment contacts.
            margin: detection looks ``threshold + margin`` far [m], so a list detected now still holds the pairs
                that come within the threshold while the strands move less than the margin.
            detect_each_step: detect in every :meth:`apply`; when False, :meth:`apply` only evaluates the stored
                pairs at the current positions and the caller runs :meth:`detect` (e.g. once per output frame,
                with a margin covering the motion of a frame), which is where the time goes.
            skip_neighbour_strips: a vertex does not meet the strips of its root neighbours, only those of its own
                strand are skipped otherwise. Those strips are the walls of the cells the strand is a corner of
                (the analogue of a mesh vertex skipping its adjacent faces): in a dense groom they lie within the
                threshold at rest, so they would push the style apart and make most of the contacts (60 % on the
                2,219-guide Ratboy mohawk), while the neighbours themselves are held by links and met by
                segment-segment contacts.
            rest_gaps: a pair (two segments, or a vertex and a strip quad) closer than the threshold in
                ``rest_vertices`` (the groom) repels only below that rest distance, so the groom is an equilibrium,
                and neighbours sliding along each other are not pushed apart. On the Ratboy mohawk 106,000
                pairs are within 2 mm in the groom itself; pushed apart at k = 20 N/m (up to 100 times a segment's
                weight) they burst the style and drive the strands into the body.
            implicit_springs: add to the solver's ``seg_implicit_mass`` the part of the active contacts' summed
                ``h^2 k + h c`` beyond each segment's own mass (the semi-implicit treatment of the repulsion);
                False leaves it explicit, for comparison. Not used with ``response``.
            response: solve the contacts' forces over the step after the free step, inside the strands'
                dynamics, on the relative motion of each pair (``kernels.articulated.interaction_response``;
                :class:`hairwarp.Solver` runs it after the free step), for steps of 1/220 s and longer (the
                scenes' ``interactions.response = "auto"``). The semi-implicit inertia it replaces resisted every
                acceleration of the hair, also the head's, and at one step a frame made a third of the segments of
                ``fast_turn`` a hundred times heavier.
            device: Warp device.
        """
        verts = _check_vertices(rest_vertices)
        G, S = verts.shape[0], verts.shape[1] - 1
        if not threshold > 0.0:
            raise InteractionError(f"threshold must be > 0, got {threshold}")
        for name, value in (("stiffness", stiffness), ("damping", damping), ("friction", friction)):
            if not 0.0 <= value < math.inf:
                raise InteractionError(f"{name} must be a finite number >= 0, got {value}")
        if not slip_velocity > 0.0:
            raise InteractionError(f"slip_velocity must be > 0, got {slip_velocity}")
        if not 0.0 <= alignment_cutoff < 1.0:
            raise InteractionError(f"alignment_cutoff must be in [0, 1), got {alignment_cutoff}")
        if not margin >= 0.0:
            raise InteractionError(f"margin must be >= 0, got {margin}")
        if int(capacity) < 1:
            raise InteractionError(f"capacity must be >= 1, got {capacity}")
        if strips is not None and (strips.strand_count, strips.seg_per_strand) != (G, S):
            raise InteractionError(
                f"strips were built for {strips.strand_count} strands of {strips.seg_per_strand} segments, "
                f"rest_vertices has {G} of {S}"
            )

        contacts = cls()
        dev = contacts.device = wp.get_device(device)
        contacts.strand_count, contacts.seg_per_strand = G, S
        contacts.strips = strips if strips is not None and strips.pair_count > 0 else None
        contacts.segment_segment = bool(segment_segment) and G > 1
        contacts.threshold = float(threshold)
        contacts.margin = float(margin)
        contacts.detect_each_step = bool(detect_each_step)
        contacts.stiffness = float(stiffness)
        contacts.damping = float(damping)
        contacts.friction = float(friction)
        contacts.slip_velocity = float(slip_velocity)
        contacts.alignment_cutoff = float(alignment_cutoff)
        contacts.capacity = int(capacity)
        contacts.grown = []

        contacts.skip_neighbour_strips = bool(skip_neighbour_strips)
        contacts.rest_gaps = bool(rest_gaps)
        contacts.implicit_springs = bool(implicit_springs)
        contacts.response = bool(response)
        seg_blocks = G * -(-S // contact_kernels.SEG_BLOCK)
        contacts.seg_lowers = wp.zeros(G * S, dtype=wp.vec3, device=dev)
        contacts.seg_uppers = wp.zeros(G * S, dtype=wp.vec3, device=dev)
        contacts.seg_block_lowers = wp.zeros(seg_blocks, dtype=wp.vec3, device=dev)
        contacts.seg_block_uppers = wp.zeros(seg_blocks, dtype=wp.vec3, device=dev)
        contacts.seg_dir = wp.zeros(G * S, dtype=wp.vec3, device=dev)
        contacts.seg_block_axes = wp.zeros(seg_blocks, dtype=wp.vec3, device=dev)
        contacts.seg_block_spreads = wp.zeros(seg_blocks, dtype=wp.vec2, device=dev)
        contacts.seg_bvh = None
        contacts.strip_bvh = None
        rest = contacts.rest_positions = wp.array(verts.reshape(-1, 3), dtype=wp.vec3, device=dev)
        if contacts.segment_segment:
            contacts._segment_bounds(S, rest)
            contacts.seg_bvh = wp.Bvh(contacts.seg_block_lowers, contacts.seg_block_uppers)
        if contacts.strips is not None:
            quads = contacts.strips.quad_count
            quad_blocks = contacts.strips.pair_count * -(-S // contact_kernels.QUAD_BLOCK)
            contacts.quad_lowers = wp.zeros(quads, dtype=wp.vec3, device=dev)
            contacts.quad_uppers = wp.zeros(quads, dtype=wp.vec3, device=dev)
            contacts.quad_plane = wp.zeros(quads, dtype=wp.vec4, device=dev)
            contacts.quad_slab = wp.zeros(quads, dtype=float, device=dev)
            contacts.quad_dir = wp.zeros(quads, dtype=wp.vec3, device=dev)
            contacts.vertex_tangents = wp.zeros(G * (S + 1), dtype=wp.vec3, device=dev)
            contacts.strip_lowers = wp.zeros(quad_blocks, dtype=wp.vec3, device=dev)
            contacts.strip_uppers = wp.zeros(quad_blocks, dtype=wp.vec3, device=dev)
            contacts.strip_axes = wp.zeros(quad_blocks, dtype=wp.vec3, device=dev)
            contacts.strip_spreads = wp.zeros(quad_blocks, dtype=wp.vec2, device=dev)
            contacts._strip_bounds(S, rest)
            contacts.strip_bvh = wp.Bvh(contacts.strip_lowers, contacts.strip_uppers)

        contacts.seg_spring_mass = wp.zeros(G * S, dtype=float, device=dev)
        contacts.seg_entry_start = wp.zeros(G * S + 1, dtype=wp.int32, device=dev)
        # the contacts the links' sweeps solve in a step (``kernels.contacts.SweepContacts``)
        contacts.sweep_contacts = contact_kernels.SweepContacts()
        contacts.sweep_contacts.end = wp.zeros(G * S, dtype=wp.int32, device=dev)
        # each segment's contact force of the last step, which the next free step takes (``warm_start``)
        contacts.warm_force = wp.zeros(G * S, dtype=wp.vec3, device=dev)
        contacts.warm_torque = wp.zeros(G * S, dtype=wp.vec3, device=dev)
        # without the lists (a GPU), the response's split counts one contact a segment (``contact_response_split``)
        contacts._one_count = wp.zeros(1, dtype=wp.int32, device=dev)
        contacts._seg_cursor = wp.zeros(G * S, dtype=wp.int32, device=dev)
        contacts.contact_counter = wp.zeros(1, dtype=wp.int32, device=dev)
        contacts.contact_overflow = wp.zeros(1, dtype=wp.int32, device=dev)
        contacts._allocate_slots()
        if contacts.strips is None:
            # The force kernel takes strip arrays even when only segments collide.
            contacts._strip_pairs = wp.zeros(1, dtype=wp.vec2i, device=dev)
            contacts._tri_scale = wp.zeros(1, dtype=float, device=dev)
        else:
            contacts._strip_pairs = contacts.strips.strip_pairs
            contacts._tri_scale = contacts.strips.tri_stiffness_scale
        return contacts

    def _allocate_slots(self):
        """The arrays of :attr:`capacity` slots, anew: the pairs, their force entries, the segments' and the sweeps'
        lists of them, the response's factors. At the build, and where a detection finds more pairs than slots
        (:meth:`detect`)."""
        dev, cap = self.device, self.capacity
        # Threads of the force pass, each striding over the stored contacts: enough to fill a GPU, few enough
        # that a large, mostly empty buffer costs nothing on a CPU.
        self.force_threads = min(cap, 1 << 16 if dev.is_cuda else 256)
        self.contact_kind = wp.zeros(cap, dtype=wp.int32, device=dev)
        self.contact_a = wp.zeros(cap, dtype=wp.int32, device=dev)
        self.contact_b = wp.zeros(cap, dtype=wp.int32, device=dev)
        self.contact_w = wp.zeros(cap, dtype=wp.vec3, device=dev)
        self.contact_gap = wp.zeros(cap, dtype=float, device=dev)
        # Each contact's forces go to its entries 4 slot + e, which the segments then gather (see ``apply``).
        self.entry_force = wp.zeros(4 * cap, dtype=wp.vec3, device=dev)
        self.entry_torque = wp.zeros(4 * cap, dtype=wp.vec3, device=dev)
        self.entry_mass = wp.zeros(4 * cap, dtype=float, device=dev)
        self.seg_entries = wp.zeros(4 * cap, dtype=wp.int32, device=dev)
        sweep = self.sweep_contacts
        sweep.entries = wp.zeros(4 * cap, dtype=wp.int32, device=dev)
        sweep.friction = wp.zeros(4 * cap, dtype=float, device=dev)
        sweep.free = wp.zeros(4 * cap, dtype=wp.vec3, device=dev)
        buf = contact_kernels.ContactBuffer()
        buf.capacity = cap
        buf.kind, buf.a, buf.b = self.contact_kind, self.contact_a, self.contact_b
        buf.w, buf.gap = self.contact_w, self.contact_gap
        buf.counter, buf.overflow = self.contact_counter, self.contact_overflow
        self.buffer = buf
        self._allocate_response(self.response)
        self._chunk_buffers = None
        self._chunk_slots = None
        self._order_views = None

    def _allocate_response(self, on: bool):
        """The :class:`kernels.contacts.ContactResponse` the force pass leaves for the response (one-element arrays
        when it is off)."""
        dev, cap = self.device, self.capacity if on else 1
        r = contact_kernels.ContactResponse()
        r.enabled = int(on)
        r.friction = self.friction
        r.slip_velocity = self.slip_velocity
        r.rate_limit = float(self.response_rate_limit)
        r.normal = wp.zeros(cap, dtype=wp.vec3, device=dev)
        r.coef = wp.zeros(cap, dtype=float, device=dev)
        r.target = wp.zeros(cap, dtype=float, device=dev)
        r.weights = wp.zeros(cap, dtype=wp.vec4, device=dev)
        r.point = wp.zeros(4 * cap, dtype=wp.vec3, device=dev)
        r.share = wp.zeros(4 * cap, dtype=float, device=dev)
        r.split = wp.zeros(cap, dtype=wp.vec3, device=dev)
        self._response_buffer = r
        self.response = bool(on)

    def prepare_response(self, model, state_in, state_out, dt, dampers):
        """Each contact's split factors of its two sides, from the strands' inverse inertias in ``dampers``
        (``contact_response_split``; launch only): what :meth:`gather_response` reads."""
        if not self.enabled:
            return
        launch(self.executor, contact_kernels.contact_response_split, self._slots(),
               [model.seg_per_strand, self._strip_pairs, self.buffer, self.entry_counts(), state_in.seg_xform, dt,
                dampers], [self._response_buffer], device=self.device, min_chunk=GATHER_MIN_CHUNK)

    def entry_counts(self):
        """The segments' lists of the stored contacts' entries (``seg_entry_start``, built once per detection), or
        an array of one element where there are none (on a GPU): what the kernels that count a segment's contacts
        take."""
        return self._one_count if self.device.is_cuda else self.seg_entry_start

    def _slots(self) -> int:
        """The buffer slots a launch over the stored contacts covers: on the CPU the stored count (a host read of
        its counter, free there), rounded up to :data:`SLOT_GRAIN` so that a launch is packed again only when the
        count crosses a grain; on a GPU, where reading it would wait for the device, the whole capacity (the threads
        past the count return at once)."""
        if self.device.is_cuda or _capturing(self.device):
            return self.capacity
        n = min(int(self.contact_counter.numpy()[0]), self.capacity)
        return min(self.capacity, max(SLOT_GRAIN, _grains(n)))

    def gather_response(self, model, state_in, state_out, dt, dampers, swept=None, colors=None):
        """Add every segment's contact dampers for the velocity response (``response``) to ``dampers`` (a
        :class:`kernels.articulated.InteractionResponse`), from the free step's end velocities in ``state_out``, the
        frames of ``state_in`` and :meth:`prepare_response`; with ``swept``, store the blocks of the same dampers
        whole there and list the contacts for the links' sweeps, whose strands have ``colors``
        (:attr:`sweeps_contacts`; launch only)."""
        if not self.enabled:
            return
        inputs = [model.seg_per_strand, self._strip_pairs, self.buffer, self._response_buffer]
        if self.device.is_cuda or self.scatter:
            launch(self.executor, contact_kernels.contact_response_scatter, self.capacity,
                   [*inputs, state_in.seg_xform, state_out.vertex_velocities, dt], [dampers],
                   device=self.device, chunks=[(0, self.capacity)])
        else:
            launch(self.executor, contact_kernels.contact_response_gather, len(self._seg_cursor),
                   [*inputs, self.seg_entry_start, self.seg_entries, state_in.seg_xform, state_out.vertex_velocities,
                    dt, int(swept is not None), colors if colors is not None else self._one_count],
                   [dampers, swept if swept is not None else dampers, self.sweep_contacts], device=self.device,
                   min_chunk=GATHER_MIN_CHUNK)

    @property
    def sweeps_contacts(self) -> bool:
        """Whether the links' sweeps solve these contacts too (``kernels.contacts.sweep_entry_force``), which needs each
        segment's list of contacts: on the CPU (where ``gather_response`` gathers); a GPU holds them as dampers split
        between their sides."""
        return self.enabled and self.response and not (self.device.is_cuda or self.scatter)

    def sweep_inputs(self) -> list:
        """What ``kernels.sweeps.link_sweep`` reads of the contacts (after its ``contacts_swept`` flag)."""
        return [self._strip_pairs, self.buffer, self._response_buffer, self.seg_entry_start, self.sweep_contacts,
                int(self.warm_start), self.warm_force, self.warm_torque]

    def update_warm(self, model, state_in, answered_velocities):
        """Keep each segment's contact force in the links' sweeps' answer (``answered_velocities``, linearised at
        the frames of ``state_in``), which the next free step takes with :attr:`warm_start`
        (``kernels.contacts.contact_warm_forces``, gated by :attr:`warm_gate`; launch only)."""
        launch(self.executor, contact_kernels.contact_warm_forces, model.strand_count,
               [model.seg_per_strand, *self.sweep_inputs()[:5], state_in.seg_xform, answered_velocities,
                float(self.warm_gate)], [self.warm_force, self.warm_torque], device=self.device,
               min_chunk=WARM_MIN_CHUNK)

    def clear_warm(self):
        """Forget the contacts' forces of the last step (a teleport, or the warm start turned off)."""
        self.warm_force.zero_()
        self.warm_torque.zero_()

    @property
    def enabled(self) -> bool:
        """Whether any contact kind is detected."""
        return self.strips is not None or self.segment_segment

    def _strip_bounds(self, S, vertex_positions):
        launch(self.executor, contact_kernels.strip_bounds, len(self.strip_lowers),
               [S, self.threshold + self.margin, self.strips.max_width, self.strips.strip_pairs, vertex_positions],
               [self.quad_lowers, self.quad_uppers, self.quad_plane, self.quad_slab, self.quad_dir,
                self.strip_lowers, self.strip_uppers, self.strip_axes, self.strip_spreads], device=self.device,
               min_chunk=BLOCK_MIN_CHUNK)

    def _segment_bounds(self, S, vertex_positions):
        launch(self.executor, contact_kernels.segment_bounds, len(self.seg_block_lowers),
               [S, self.threshold + self.margin, vertex_positions],
               [self.seg_lowers, self.seg_uppers, self.seg_dir, self.seg_block_lowers, self.seg_block_uppers,
                self.seg_block_axes, self.seg_block_spreads], device=self.device, min_chunk=SEGMENT_MIN_CHUNK)

    def refit(self, model, state, rebuild: bool = False):
        """Fit the strip and segment BVHs to ``state``: refit (launch only; :meth:`detect` does it first), or with
        ``rebuild`` rebuild them (on the host for a CPU tree: not in a captured step)."""
        S = model.seg_per_strand
        trees = []
        for bvh, bounds in ((self.strip_bvh, self._strip_bounds), (self.seg_bvh, self._segment_bounds)):
            if bvh is not None:
                bounds(S, state.vertex_positions)
                trees.append(bvh.rebuild if rebuild else bvh.refit)
        # Warp refits or rebuilds a CPU tree on one thread: the two trees (independent) go to two threads.
        if self.executor is not None and not _capturing(self.device):
            self.executor.run(trees)
        else:
            for fit in trees:
                fit()

    def detect(self, model, state, rebuild: bool | None = None):
        """Fit the strip and segment BVHs to ``state`` and fill the contact buffers.

        Inside :meth:`apply` (``detect_each_step``) the BVHs are refit, so a captured step stays valid. Called by a
        runner between steps (``detect_each_step=False``) they are rebuilt with ``rebuild`` (None: always), which
        keeps the trees tight as the hair moves far from the pose they were built in, else refit: the runner rebuilds
        them every :data:`REBUILD_FRAMES` frames on the CPU. There the contacts are then put in one order, by their
        kind and sides (:meth:`_canonical_order`), whatever tree found them: a refit tree and a rebuilt one walk the
        quads in other orders, and the forces, summed per segment in slot order, would differ in their last bits.

        With :attr:`grows`, a detection that finds more pairs than slots grows them (:data:`GROWTH`) and detects again,
        so nothing is dropped; not in a graph capture, nor on a GPU in every step (it reads the count back), nor where
        the pairs pass :data:`THRESHOLD_PAIRS` a guide vertex (a threshold far past a wisp's thickness: the overflow
        flags then say so).
        """
        if rebuild is None:
            rebuild = not self.detect_each_step
        grows = self.grows and not _capturing(self.device) and not (self.device.is_cuda and self.detect_each_step)
        overflowed = grows and self.overflowed()
        self._detect_pairs(model, state, rebuild)
        found = self.contact_count() if grows and not overflowed else 0
        if found > self.capacity and not self.threshold_overrun():
            # More pairs than slots: grow them to hold these and a quarter more, and find the pairs again (the trees
            # are fitted again, as in the first try). The overflow of the first try is forgotten: nothing was dropped.
            self.grown.append((self.capacity, found))
            self.capacity = _grains(found * GROWTH)
            self._allocate_slots()
            self.contact_overflow.zero_()
            bits = state.fault.numpy()
            bits[0] &= ~int(Fault.CONTACT_OVERFLOW)
            state.fault.assign(bits)
            self._detect_pairs(model, state, rebuild)
        if not self.detect_each_step and not self.device.is_cuda and not _capturing(self.device):
            self._canonical_order()
        self._segment_lists(model)

    def _detect_pairs(self, model, state, rebuild: bool):
        """Fit the trees and fill the contact buffers (the body of :meth:`detect`)."""
        self.contact_counter.zero_()
        if self._overlapped_detection():
            self._fit_and_detect(model, state, rebuild=rebuild)
        else:
            self.refit(model, state, rebuild=rebuild)
            self.detect_vertex_face(model, state)
            self.detect_segment_segment(model, state)

    def _canonical_order(self):
        """Sort the stored contacts by kind, side a and side b (host views of CPU arrays; one contact per pair of
        sides, so the order is total). The detection appends them block by block in element order, each block's in
        the order its tree query meets them: nearly sorted, which a stable sort takes in one pass."""
        n = min(int(self.contact_counter.numpy()[0]), self.capacity)
        if n < 2:
            return
        views = self._order_views
        if views is None:
            views = self._order_views = [a.numpy() for a in (self.contact_kind, self.contact_a, self.contact_b,
                                                             self.contact_w, self.contact_gap)]
        kind, a, b = views[0][:n], views[1][:n], views[2][:n]
        key = (kind.astype(np.int64) << 62) | (a.astype(np.int64) << 31) | b.astype(np.int64)
        order = np.argsort(key, kind="stable")
        if np.all(order[1:] > order[:-1]):
            return
        for v in views:
            v[:n] = v[:n][order]

    def _overlapped_detection(self) -> bool:
        """Whether :meth:`detect` runs as :meth:`_fit_and_detect`: both kinds of contact, on several CPU threads,
        not in a graph capture."""
        ex = self.executor
        return (ex is not None and ex.parallel and not self.device.is_cuda and self.strips is not None
                and self.segment_segment and not _capturing(self.device))

    def _fit_and_detect(self, model, state, rebuild: bool):
        """:meth:`refit`, :meth:`detect_vertex_face` and :meth:`detect_segment_segment` as one set of tasks on the
        executor's threads: the segment tree, then its contacts' chunks, go on while the strip tree (the larger:
        2.8 times the boxes on the mohawk) is still being fitted, which Warp does on one thread. Run one after the
        other, a thread sat idle for the difference of the two trees (0.9 of the mohawk's 6.4 ms of detection on two
        threads). The contacts are the same, in the same order: every chunk appends to a buffer of its own, and the
        buffers are concatenated in element order, vertex-face first, as one thread finds them."""
        while not self._fit_and_detect_once(model, state, rebuild):
            pass  # a chunk found more pairs than its buffer holds: grown, detect again

    def _fit_and_detect_once(self, model, state, rebuild: bool) -> bool:
        """One try of :meth:`_fit_and_detect`; False where a chunk's buffer was short (grown for the next try)."""
        S, ex, fault = model.seg_per_strand, self.executor, state.fault
        with ex.batch():
            self._strip_bounds(S, state.vertex_positions)
            self._segment_bounds(S, state.vertex_positions)
            self._vertex_tangents(S, state)
        vf_dim = self.strand_count * -(-S // contact_kernels.VERTEX_BLOCK)
        vf_chunks = ex.chunks(vf_dim, BLOCK_MIN_CHUNK, per_thread=DETECT_CHUNKS_PER_THREAD)
        ss_chunks = ex.chunks(len(self.seg_block_lowers), BLOCK_MIN_CHUNK, per_thread=DETECT_CHUNKS_PER_THREAD)
        bufs, views, counter, overflow = self._chunk_contact_buffers(len(vf_chunks) + len(ss_chunks))
        counter.zero_()
        overflow.zero_()
        before = int(fault.numpy()[0])
        vf_inputs, ss_inputs = self._vertex_face_inputs(S, state), self._segment_segment_inputs(S, state)
        vf = ex.prepare(contact_kernels.vertex_face_contacts, vf_dim, vf_inputs, [self.buffer, fault],
                        chunks=vf_chunks, per_chunk={len(vf_inputs): bufs[:len(vf_chunks)]},
                        private_or=[len(vf_inputs) + 1])
        ss = ex.prepare(contact_kernels.segment_segment_contacts, len(self.seg_block_lowers), ss_inputs,
                        [self.buffer, fault], chunks=ss_chunks, per_chunk={len(ss_inputs): bufs[len(vf_chunks):]},
                        private_or=[len(ss_inputs) + 1])
        seg_fitted, strip_fitted = threading.Event(), threading.Event()
        failed = []

        def fit(bvh, fitted):
            def task():
                try:
                    bvh.rebuild() if rebuild else bvh.refit()
                except BaseException:
                    failed.append(bvh)
                    raise
                finally:
                    fitted.set()
            return task

        def chunk(prep, c, fitted):
            def task():
                fitted.wait()  # the tree tasks come first: a thread is fitting it
                if not failed:
                    prep.call(c)
            return task

        # the trees first (every thread that waits on one waits on a thread fitting it), then half the segment tree's
        # chunks (the smaller tree is fitted first), the vertex-face chunks, and the other half last: the threads end
        # on the small chunks (a mohawk's vertex-face chunk costs three of its segment-segment ones), so none waits
        # long for the last (the mohawk on two threads, 60 detections interleaved with the order before, three
        # runs: 3.7-4.0 ms against 3.8-4.1, each detection 3-4 % shorter than its pair)
        half = (len(ss_chunks) + 1) // 2
        ex.run([fit(self.seg_bvh, seg_fitted), fit(self.strip_bvh, strip_fitted),
                *(chunk(ss, c, seg_fitted) for c in range(half)),
                *(chunk(vf, c, strip_fitted) for c in range(len(vf_chunks))),
                *(chunk(ss, c, seg_fitted) for c in range(half, len(ss_chunks)))])
        ex.finish(vf)
        ex.finish(ss)
        return self._append_chunk_contacts(views, len(vf_chunks) + len(ss_chunks), fault, before)

    def _segment_lists(self, model):
        """Per segment, the entries of the stored contacts that push it (one thread: a counting sort over the
        contacts, exact and in slot order, once per detection; not on a GPU, where ``gather`` scatters)."""
        if self.device.is_cuda:
            return
        launch(self.executor, contact_kernels.contact_segment_lists, 1,
               [model.seg_per_strand, len(self._seg_cursor), self._strip_pairs, self.buffer, self._seg_cursor],
               [self.seg_entry_start, self.seg_entries], device=self.device)

    def detect_vertex_face(self, model, state):
        """Append the vertex-face contacts of ``state`` to the buffers (launch only; BVH refit by :meth:`refit`)."""
        if self.strips is None:
            return
        S = model.seg_per_strand
        self._vertex_tangents(S, state)
        self._detect_launch(contact_kernels.vertex_face_contacts,
                            self.strand_count * -(-S // contact_kernels.VERTEX_BLOCK),
                            self._vertex_face_inputs(S, state), state.fault)

    def _vertex_tangents(self, S, state):
        if self.alignment_cutoff > 0.0:
            launch(self.executor, contact_kernels.vertex_tangents, len(self.vertex_tangents),
                   [S, state.vertex_positions], [self.vertex_tangents], device=self.device, min_chunk=SEGMENT_MIN_CHUNK)

    def _vertex_face_inputs(self, S, state):
        strips = self.strips
        return [S, self.threshold + self.margin, self.alignment_cutoff, self.threshold,
                int(self.rest_gaps), int(self.skip_neighbour_strips), self.strip_bvh.id, self.rest_positions,
                strips.strip_pairs, strips.strand_neighbour_start, strips.strand_neighbours, state.vertex_positions,
                self.quad_lowers, self.quad_uppers, self.quad_plane, self.quad_slab, self.quad_dir, self.strip_axes,
                self.strip_spreads, self.vertex_tangents]

    def detect_segment_segment(self, model, state):
        """Append the segment-segment contacts of ``state`` to the buffers (launch only; BVH refit by
        :meth:`refit`)."""
        if not self.segment_segment:
            return
        self._detect_launch(contact_kernels.segment_segment_contacts, len(self.seg_block_lowers),
                            self._segment_segment_inputs(model.seg_per_strand, state), state.fault)

    def _segment_segment_inputs(self, S, state):
        return [S, self.threshold + self.margin, self.alignment_cutoff, self.threshold, int(self.rest_gaps),
                self.seg_bvh.id, self.rest_positions, state.vertex_positions, self.seg_lowers, self.seg_uppers,
                self.seg_dir, self.seg_block_axes, self.seg_block_spreads]

    def _detect_launch(self, kernel, dim, inputs, fault):
        """One detection launch appending to the buffers in element order, whatever the thread count.

        On several threads each chunk appends to a buffer of its own (full capacity, so a chunk drops nothing one
        launch would keep), and the chunks' contacts are concatenated in chunk order behind those already stored:
        the order of one launch, which takes each element in turn.
        """
        ex = self.executor
        n = len(inputs)
        parallel = ex is not None and ex.parallel and not _capturing(self.device)
        chunks = ex.chunks(dim, BLOCK_MIN_CHUNK, per_thread=DETECT_CHUNKS_PER_THREAD) if parallel else [(0, dim)]
        if len(chunks) == 1:
            launch(ex, kernel, dim, inputs, [self.buffer, fault], device=self.device)
            return
        while True:
            bufs, views, counter, overflow = self._chunk_contact_buffers(len(chunks))
            counter.zero_()
            overflow.zero_()
            before = int(fault.numpy()[0])
            ex.launch(kernel, dim, inputs, [self.buffer, fault], chunks=chunks, per_chunk={n: bufs},
                      private_or=[n + 1])
            if self._append_chunk_contacts(views, len(chunks), fault, before):
                return  # else a chunk's buffer was short (grown, nothing appended): this launch again

    def _append_chunk_contacts(self, views, count: int, fault, before: int) -> bool:
        """Concatenate the contacts of the first ``count`` chunk buffers, in chunk order, behind those stored (host
        views of CPU arrays: the executor runs chunks on the CPU only), and return True. Where a chunk found more
        pairs than its buffer holds and less than the capacity, append nothing, put the overflow bit of ``fault`` back
        as it was ``before`` the launch, grow the chunks' buffers (:data:`GROWTH`) and return False: the caller
        detects again, so a chunk drops nothing one launch would keep."""
        counts, overflows, mains, total = views["counter"], views["overflow"], views["main"], views["total"]
        most = int(counts[:count].max(initial=0))
        if most > self._chunk_slots and self._chunk_slots < self.capacity:
            bits = fault.numpy()
            bits[0] = (int(bits[0]) & ~int(Fault.CONTACT_OVERFLOW)) | (before & int(Fault.CONTACT_OVERFLOW))
            self._chunk_slots = min(self.capacity, _grains(most * GROWTH))
            self._chunk_buffers = None
            return False
        pos = int(total[0])
        for c in range(count):
            take = max(0, min(int(counts[c]), self.capacity - pos))
            if take:
                for dst, src in zip(mains, views["chunks"][c]):
                    dst[pos:pos + take] = src[:take]
            pos += int(counts[c])
        total[0] = pos
        if pos > self.capacity or np.any(overflows[:count]):
            self.contact_overflow.numpy()[0] = 1
            fault.numpy()[0] |= int(Fault.CONTACT_OVERFLOW)
        return True

    def _chunk_contact_buffers(self, count):
        """``count`` contact buffers of :attr:`_chunk_slots` each, one for each chunk of a detection launch on the
        CPU's threads, with host views of them. Each starts at twice its share of the capacity (a buffer of the whole
        capacity for every chunk took 1.8 GB more on 16 threads than on 2 for the Ratboy mohawk's 2,219 guides) and
        grows where a chunk finds more (:meth:`_append_chunk_contacts`), up to the capacity."""
        have = self._chunk_buffers
        if have is None or len(have[0]) < count:
            dev = self.device
            if self._chunk_slots is None:
                self._chunk_slots = min(self.capacity, _grains(-(-2 * self.capacity // max(count, 1))))
            cap = self._chunk_slots
            counter = wp.zeros(count, dtype=wp.int32, device=dev)
            overflow = wp.zeros(count, dtype=wp.int32, device=dev)
            bufs = []
            for c in range(count):
                buf = contact_kernels.ContactBuffer()
                buf.capacity = cap
                buf.kind = wp.zeros(cap, dtype=wp.int32, device=dev)
                buf.a = wp.zeros(cap, dtype=wp.int32, device=dev)
                buf.b = wp.zeros(cap, dtype=wp.int32, device=dev)
                buf.w = wp.zeros(cap, dtype=wp.vec3, device=dev)
                buf.gap = wp.zeros(cap, dtype=float, device=dev)
                buf.counter = counter[c:c + 1]
                buf.overflow = overflow[c:c + 1]
                bufs.append(buf)
            main = [self.contact_kind, self.contact_a, self.contact_b, self.contact_w, self.contact_gap]
            views = {"counter": counter.numpy(), "overflow": overflow.numpy(), "total": self.contact_counter.numpy(),
                     "main": [a.numpy() for a in main],
                     "chunks": [[a.numpy() for a in (b.kind, b.a, b.b, b.w, b.gap)] for b in bufs]}
            self._chunk_buffers = have = (bufs, views, counter, overflow)
        bufs, views, counter, overflow = have
        return bufs[:count], views, counter, overflow

    def apply(self, model, state, dt, seg_force, seg_torque, seg_implicit_mass):
        """Detect the contacts of ``state`` (unless ``detect_each_step`` is off) and accumulate their forces into the
        solver's arrays (launch only)."""
        if not self.enabled:
            return
        if self.detect_each_step:
            self.detect(model, state)
        self.apply_forces(model, state, dt)
        self.gather(model, seg_force, seg_torque, seg_implicit_mass)

    def apply_forces(self, model, state, dt):
        """The first pass of :meth:`apply`, on the stored contacts (detected before): each contact's forces into its
        entries. Independent of the links' and the colliders' passes."""
        if not self.enabled:
            return
        inputs = [
            model.seg_per_strand, model.seg_length, model.seg_mass, self._strip_pairs,
            self._tri_scale,
            self.threshold, self.stiffness, self.damping, self.friction, self.slip_velocity, self.alignment_cutoff,
            self.strips.max_width if self.strips is not None else 0.0, self.force_threads,
            int(not self.device.is_cuda), int(self.implicit_springs), state.vertex_positions, state.vertex_velocities,
            dt, self.buffer, self._response_buffer,
        ]
        # A contact leaves its forces in entries of its own, then every segment adds the entries that push it, in
        # slot order: no element is written by two threads, so the sums are the same bits however they are split.
        launch(self.executor, contact_kernels.contact_forces, self.force_threads, inputs,
               [self.entry_force, self.entry_torque, self.entry_mass], device=self.device,
               min_chunk=FORCE_MIN_CHUNK)

    def gather(self, model, seg_force, seg_torque, seg_implicit_mass):
        """The second pass of :meth:`apply`: every segment adds the entries of the contacts that push it (on a GPU
        every contact adds its entries to its segments with atomics, in any order). With ``response`` the forces are
        the response's, and there is nothing to add but, with :attr:`warm_start`, each segment's force of the last
        step (``kernels.contacts.contact_warm_add``)."""
        if not self.enabled:
            return
        if self.response:
            if self.warm_start:
                launch(self.executor, contact_kernels.contact_warm_add, len(self.warm_force),
                       [self.warm_force, self.warm_torque], [seg_force, seg_torque], device=self.device,
                       min_chunk=GATHER_MIN_CHUNK)
            return
        if self.device.is_cuda or self.scatter:
            launch(self.executor, contact_kernels.contact_scatter, self.capacity,
                   [model.seg_per_strand, self._strip_pairs, self.buffer, self.entry_force, self.entry_torque,
                    self.entry_mass], [seg_force, seg_torque, self.seg_spring_mass], device=self.device,
                   chunks=[(0, self.capacity)])
            if self.implicit_springs:
                launch(self.executor, link_kernels.add_excess_mass, len(self.seg_spring_mass),
                       [model.seg_mass, self.seg_spring_mass], [seg_implicit_mass], device=self.device,
                       min_chunk=SEGMENT_MIN_CHUNK)
            return
        launch(self.executor, contact_kernels.contact_gather, len(self._seg_cursor),
               [model.seg_mass, int(self.implicit_springs), self.seg_entry_start, self.seg_entries, self.entry_force,
                self.entry_torque, self.entry_mass, self.seg_spring_mass], [seg_force, seg_torque, seg_implicit_mass],
               device=self.device, min_chunk=GATHER_MIN_CHUNK)

    def rebuild(self):
        """Rebuild both BVHs from their current boxes (optional, e.g. once per frame after large motion)."""
        for bvh in (self.seg_bvh, self.strip_bvh):
            if bvh is not None:
                bvh.rebuild()

    def contact_count(self) -> int:
        """Contacts found in the last step, including any dropped for want of capacity (host read)."""
        return int(self.contact_counter.numpy()[0])

    def overflow_advice(self) -> str:
        """What a run whose contacts overflowed should change (host read of the last detection's count): the
        threshold where it found :data:`THRESHOLD_PAIRS` a guide vertex or more, else the capacity."""
        found = self.contact_count()
        said = f"{found:,} hair contact pairs were found for {self.capacity:,} slots and the rest dropped"
        per_vertex = self._pairs_per_vertex(found)
        if per_vertex < THRESHOLD_PAIRS:
            return f"{said}; raise interactions.capacity"
        return (f"{said} ({per_vertex:,.0f} a guide vertex); lower interactions.threshold (now {self.threshold:g} m: "
                f"the thickness of a wisp a guide stands for, a few millimetres), or raise interactions.capacity")

    def threshold_overrun(self) -> bool:
        """Whether the last detection found :data:`THRESHOLD_PAIRS` pairs a guide vertex or more (host read)."""
        return self._pairs_per_vertex(self.contact_count()) >= THRESHOLD_PAIRS

    def _pairs_per_vertex(self, found: int) -> float:
        """``found`` pairs per guide vertex (roots left out)."""
        return found / (self.strand_count * self.seg_per_strand)

    def overflowed(self) -> bool:
        """Whether any step since the build (or :meth:`reset_overflow`) found more contacts than the capacity."""
        return bool(self.contact_overflow.numpy()[0])

    def reset_overflow(self):
        """Clear the sticky overflow flag."""
        self.contact_overflow.zero_()

    def contact_list(self) -> dict:
        """The last step's stored contacts as numpy arrays ``kind, a, b, w, gap`` (host read, for reports and
        tests)."""
        n = min(self.contact_count(), self.capacity)
        return {
            "kind": self.contact_kind.numpy()[:n].copy(),
            "a": self.contact_a.numpy()[:n].copy(),
            "b": self.contact_b.numpy()[:n].copy(),
            "w": self.contact_w.numpy()[:n].copy(),
            "gap": self.contact_gap.numpy()[:n].copy(),
        }
