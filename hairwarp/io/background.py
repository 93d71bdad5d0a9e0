"""The cache writer in a second process: the simulation goes on while the frame layers are converted and saved.

:class:`BackgroundCacheWriter` (``output.writer = "background"`` in a scene) checks each frame in the caller, copies
it into shared memory and returns; a second process converts it, writes its layer and names it in the root, so with
a core to spare a frame costs about the larger of simulating it and writing it instead of their sum. Same files,
same guarantees as :class:`hairwarp.io.cache.CacheWriter`; a crash of usd-core (e.g. on a full disk) ends only that
process, and the caller reports it. Without a free core it only adds the copy and a second usd-core, which is why
it is not the default; :func:`hairwarp.benchmarks.dense.bench_dense_pipeline` measures both.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

from hairwarp.io.cache import CacheWriter
from hairwarp.io.cache_folder import CacheWriteError
from hairwarp.io.usd_common import UsdFileError, _reload_if_open

__all__ = ["BackgroundCacheWriter", "background_supported"]


_LIVE_WRITERS: weakref.WeakSet = weakref.WeakSet()
"""Background writers not closed yet; their processes are stopped at interpreter exit."""

_CHILD_CODE = ("import sys; sys.path[:0] = [p for p in {paths!r} if p not in sys.path]; "
               "from hairwarp.io.background import _background_main; "
               "_background_main(int(sys.argv[1]), int(sys.argv[2])); "
               "import os; sys.stderr.flush(); os._exit(0)")  # the cache is closed: skip the teardown of usd-core


def background_supported() -> bool:
    """Whether :class:`BackgroundCacheWriter` can run here: it passes file descriptors to its process (POSIX)."""
    return os.name == "posix"


def _anonymous_memory() -> int:
    """A file descriptor of an empty, nameless memory file (Linux ``memfd``, else an unlinked temporary file).

    Nothing names it, so nothing can leak: the memory goes when the last descriptor and mapping are closed, also
    when a process is killed.
    """
    if hasattr(os, "memfd_create"):
        return os.memfd_create("hairwarp-cache-frames", os.MFD_CLOEXEC)
    with tempfile.TemporaryFile(prefix="hairwarp-cache-frames-") as f:
        return os.dup(f.fileno())


def _error_text(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, (UsdFileError, CacheWriteError)) else f"{type(exc).__name__}: {exc}"


@atexit.register
def _stop_background_writers() -> None:
    """Stop the processes of writers never closed (their temporary files keep the frames saved, as inline)."""
    for writer in list(_LIVE_WRITERS):
        writer._abandon()


class BackgroundCacheWriter(CacheWriter):
    """A :class:`CacheWriter` whose ``Vt`` conversion, authoring and crate saves run in a second process.

    The interface, the file and the guarantees are those of :class:`CacheWriter`. :meth:`write_frame` checks the
    frame in the caller (a bad frame raises there at once, naming the file, the prim and the frame, and is not
    sent), copies its arrays into a ring of ``slots`` frame buffers in shared memory, hands the slot to the writer
    process and returns; when every slot is taken it waits for the oldest to be converted (back-pressure). The
    caller holds the working folder's lock and writes the checkpoints; the writer process converts each frame,
    writes its layer and names it in the root, so a crash of either process leaves every complete frame in the
    working folder. A failure in the writer process (e.g. a full disk) is raised by the next :meth:`write_frame` or
    by :meth:`close`, naming the file. :meth:`close` waits for the frames in flight, has the cache moved into place
    and ends the process.

    The process is started with the interpreter's executable (``multiprocessing``'s, see
    ``multiprocessing.set_executable``) and imports only hairwarp.io and usd-core: no fork of a process that runs
    Warp, and a script that creates a writer needs no ``if __name__ == "__main__"`` guard. It ignores SIGINT, SIGTERM
    and SIGHUP, so a stop reaches only the caller, which finishes or drops its frame and closes the pipe. POSIX only
    (:func:`background_supported`).

    Args:
        path, fps, start_frame, meters_per_unit, up_axis, comment, layout, resume: as :class:`CacheWriter`.
        slots: frame buffers in shared memory (each the size of one frame's points and velocities); two let the
            caller fill one while the writer converts the other.

    Attributes:
        timings: seconds per phase, summed over the frames: in the caller ``check`` (validation, extents),
            ``copy`` (into shared memory), ``wait`` (for a free slot); in the writer process ``convert`` (extents
            and ``Vt`` arrays), ``set``, ``save`` (complete once the cache is closed).
        frames_saved: frames the writer process has saved so far.
    """

    _EXTENTS_IN_CALLER = False  # the caller checks finiteness (4x cheaper); the writer process takes the extents

    def __init__(self, path, *, fps: float, start_frame: int = 0, meters_per_unit: float = 1.0, up_axis: str = "Z",
                 comment: str = "", layout: str = "clips", resume: bool = False, slots: int = 2):
        self._setup(path, fps, start_frame, meters_per_unit, up_axis, layout, comment)
        self._owner = True
        if not background_supported():
            raise UsdFileError(f"{self.path}: the background writer needs a POSIX system; use CacheWriter")
        if int(slots) < 1:
            raise UsdFileError(f"{self.path}: slots must be at least 1, not {slots!r}")
        self.timings = {"check": 0.0, "copy": 0.0, "wait": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0}
        self.frames_saved = 0
        self._slot_count = int(slots)
        self._free: list[int] = []
        self._layout: dict | None = None
        self._ring = None
        self._views: list[dict] = []
        self._failure: str | None = None
        self._failure_raised = False
        self._proc = None
        self._conn = None
        self._ring_fd = -1
        self._failure_is_write = False
        self.folder.acquire()
        try:
            self.resumed_after = self.folder.prepare(resume)
            if self.resumed_after is not None:
                self._frames = list(range(self.folder.frame_range()[0], self.resumed_after + 1))
            self._resumed_frames = len(self._frames)
            self._start(comment, resume)
        except BaseException:
            self.folder.release()
            raise

    # --- the process -----------------------------------------------------------------------------------------

    def _start(self, comment: str, resume: bool) -> None:
        import multiprocessing.connection
        import multiprocessing.spawn
        import socket
        import subprocess

        self.path.parent.mkdir(parents=True, exist_ok=True)  # as the inline writer: raised here, at once
        if not os.access(self.path.parent, os.W_OK | os.X_OK):
            raise UsdFileError(f"{self.path}: its folder is not writable")
        ours, theirs = socket.socketpair()
        try:
            self._ring_fd = _anonymous_memory()
            paths = [p for p in sys.path if isinstance(p, str)]
            self._proc = subprocess.Popen(
                [multiprocessing.spawn.get_executable(), "-c", _CHILD_CODE.format(paths=paths),
                 str(theirs.fileno()), str(self._ring_fd)],
                pass_fds=(theirs.fileno(), self._ring_fd), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            self._release_resources()
            raise
        finally:
            theirs.close()
        self._conn = multiprocessing.connection.Connection(ours.detach())
        _LIVE_WRITERS.add(self)
        # Not waited for: the process loads usd-core (about half a second) while the caller goes on.
        self._post(("open", {"path": str(self.path), "fps": self.fps, "start_frame": self.start_frame,
                             "meters_per_unit": self.meters_per_unit, "up_axis": self.up_axis, "comment": comment,
                             "layout": self.layout, "resume": resume, "owner": False,
                             "pipelined": False}))  # "saved" must mean the frame is complete

    def _died(self) -> UsdFileError:
        code = self._proc.poll() if self._proc is not None else None
        keeps = f"; {self.partial_path} keeps the frames saved before it" if self.partial_path.exists() else ""
        return UsdFileError(f"{self.path}: the background writer process ended unexpectedly (exit code {code})"
                            f" after saving {self.frames_saved} frames{keeps}")

    def _receive(self):
        """The next message of the writer process, waiting for it; raises if the process is gone."""
        while True:
            try:
                if self._conn.poll(0.5):
                    return self._conn.recv()
            except (EOFError, OSError):
                raise self._died() from None
            if self._proc.poll() is not None and not self._conn.poll(0):
                raise self._died()

    def _handle(self, message) -> tuple | None:
        """Book an asynchronous message (a slot released, a frame saved, a frame failed); return a reply."""
        kind = message[0]
        if kind == "released":
            self._free.append(message[1])
        elif kind == "saved":
            self.frames_saved += 1
            self.folder.prune_checkpoints(message[1])
            for key, seconds in message[2].items():
                self.timings[key] += seconds
        elif kind == "opened":
            pass
        elif kind == "failed":
            if self._failure is None:
                self._failure = f"{self.path}: the background writer failed at {message[1]}: {message[2]}"
                self._failure_is_write = len(message) > 3 and message[3]
        else:
            return message
        return None

    def _drain(self) -> None:
        """Book every message already arrived, without waiting."""
        try:
            while self._conn.poll(0):
                reply = self._handle(self._conn.recv())
                if reply is not None:
                    raise UsdFileError(f"{self.path}: unexpected reply of the background writer: {reply!r}")
        except (EOFError, OSError):
            raise self._died() from None

    def _post(self, message) -> None:
        """Send a request that has no reply (a failure comes back as a ``failed`` message)."""
        try:
            self._conn.send(message)
        except OSError:
            raise self._died() from None

    def _request(self, message):
        """Send a request and wait for its reply, booking the asynchronous messages that come first."""
        try:
            self._conn.send(message)
        except OSError:
            raise self._died() from None
        while True:
            reply = self._handle(self._receive())
            if reply is None:
                continue
            if reply[0] == "error":
                raise UsdFileError(reply[1])
            return reply[1]

    def _raise_failure(self) -> None:
        if self._failure is not None:
            self._failure_raised = True
            raise (CacheWriteError if self._failure_is_write else UsdFileError)(self._failure)

    # --- setup and frames ------------------------------------------------------------------------------------

    def _author_curves(self, spec: dict) -> None:
        self._drain()
        self._raise_failure()
        self._post(("add_curves", spec))

    def _author_mesh(self, spec: dict) -> None:
        self._drain()
        self._raise_failure()
        self._post(("add_mesh", spec))

    def write_frame(self, frame: int, curves: dict, xforms: dict | None = None, mesh_points: dict | None = None,
                    checkpoint: dict | None = None):
        """Check the frame here, queue it for the writer process, return (see :meth:`CacheWriter.write_frame`).

        Raises:
            UsdFileError: a bad frame (nothing is queued), or an earlier frame that failed in the writer process.
        """
        self._check_open()
        self._drain()
        self._raise_failure()
        t_start = time.perf_counter()
        prepared = self._prepare_frame(frame, curves, xforms, mesh_points)
        self.timings["check"] += time.perf_counter() - t_start
        if checkpoint is not None:  # written here, before the frame: the writer process names it in the root
            self.folder.write_checkpoint(prepared["frame"], checkpoint)
        self._author_frame(prepared)
        for name, _, v, _ in prepared["curves"]:
            self._curves[name]["velocities"] = v is not None

    def _author_frame(self, prepared: dict, converted=None) -> None:
        t_start = time.perf_counter()
        if self._layout is None:
            self._make_ring(prepared)
        while not self._free:
            self._handle(self._receive())
            self._raise_failure()
        slot = self._free.pop()
        t_slot = time.perf_counter()
        views = self._views[slot]
        curves = []
        for name, p, v, extent in prepared["curves"]:
            np.copyto(views[(name, "points")], p)
            if v is not None:
                np.copyto(views[(name, "velocities")], v)
            curves.append((name, v is not None, extent))
        meshes = {}
        for name, (p, extent) in prepared["meshes"].items():
            np.copyto(views[(name, "mesh")], p)
            meshes[name] = extent
        t_copied = time.perf_counter()
        try:
            self._conn.send(("frame", slot, prepared["frame"], curves, prepared["xforms"], meshes))
        except OSError:
            raise self._died() from None
        self._frames.append(prepared["frame"])
        self.timings["wait"] += t_slot - t_start
        self.timings["copy"] += t_copied - t_slot

    def _make_ring(self, prepared: dict) -> None:
        """Size the slots on the first frame (later frames have the same arrays) and share them with the process."""
        import mmap

        layout, size = {}, 0
        arrays = []
        for name, p, v, _ in prepared["curves"]:
            arrays.append(((name, "points"), p))
            if v is not None:
                arrays.append(((name, "velocities"), v))
        arrays += [((name, "mesh"), p) for name, (p, _) in prepared["meshes"].items()]
        for key, a in arrays:
            layout[key] = (size, len(a))
            size += -(-a.nbytes // 64) * 64  # 64-byte aligned
        slot_bytes = max(-(-size // mmap.PAGESIZE) * mmap.PAGESIZE, mmap.PAGESIZE)
        os.ftruncate(self._ring_fd, slot_bytes * self._slot_count)
        self._ring = mmap.mmap(self._ring_fd, slot_bytes * self._slot_count)
        self._views = [{key: np.frombuffer(self._ring, np.float32, 3 * n, s * slot_bytes + off).reshape(n, 3)
                        for key, (off, n) in layout.items()} for s in range(self._slot_count)]
        self._layout = layout
        self._post(("ring", slot_bytes, self._slot_count, layout))
        self._free = list(range(self._slot_count))[::-1]

    def flush(self) -> None:
        """Wait until the writer process has saved every frame given so far.

        Raises:
            UsdFileError: a frame failed in the writer process.
        """
        self._check_open()
        while self.frames_saved < len(self._frames) and self._failure is None:
            self._handle(self._receive())
        self._raise_failure()

    # --- closing ---------------------------------------------------------------------------------------------

    def close(self, keep_lock: bool = False) -> Path:
        """Wait for the frames in flight, save, rename the file into place and end the writer process. Idempotent.

        Args:
            keep_lock: hold the output's lock until :meth:`release`, as
                :meth:`hairwarp.io.cache.CacheWriter.close`; a close that fails releases it.

        Raises:
            UsdFileError: the writer process failed (at a frame, or saving); the message names the file and says
                what it keeps. A failure already raised by :meth:`write_frame` is not raised again.
        """
        if self._closed:
            return self.path
        error = None
        try:
            self._request(("close",))
        except UsdFileError as exc:
            error = exc
        finally:
            self._closed = True
            self._shutdown()
        if error is not None or self._failure is not None or not keep_lock:
            self.release()
        if self._failure is not None and not self._failure_raised:
            self._failure_raised = True
            raise (CacheWriteError if self._failure_is_write else UsdFileError)(
                self._failure + (f"; and at close: {error}" if error else ""))
        if error is not None and self._failure is None:
            raise error
        _reload_if_open(self.path)
        return self.path

    def _shutdown(self, timeout: float = 30.0) -> None:
        """End the process (it exits after ``close`` or when its pipe closes) and free the pipe and the ring."""
        import subprocess

        _LIVE_WRITERS.discard(self)
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._release_resources()

    def _release_resources(self) -> None:
        self._views = []
        if self._ring is not None:
            self._ring.close()
            self._ring = None
        if self._ring_fd >= 0:
            os.close(self._ring_fd)
            self._ring_fd = -1

    def _abandon(self) -> None:
        """Stop the process without closing the cache (the working folder keeps the frames saved so far)."""
        if not self._closed:
            self._closed = True
            self._shutdown(timeout=10.0)
            self.folder.release()

    def abandon(self) -> Path | None:
        """Stop without finishing, as :meth:`hairwarp.io.cache.CacheWriter.abandon`."""
        self._abandon()
        return self.folder.root if self.folder.root.exists() else None

    def __del__(self):
        try:
            self._abandon()
        except Exception:  # interpreter shutdown: the atexit hook or the closed pipe ends the process
            pass


def _background_main(conn_fd: int, ring_fd: int) -> None:
    """The writer process of :class:`BackgroundCacheWriter`: serves its requests until ``close`` or a closed pipe.

    Requests: ``("open", kwargs)`` (answered ``("opened", temporary path)``), ``("add_curves", spec)``,
    ``("add_mesh", spec)``, ``("ring", slot_bytes, slots, layout)``, ``("frame", slot, frame, curves, xforms,
    meshes)``, ``("close",)`` (answered ``("ok", path)`` or ``("error", message)``). A frame sends ``("released",
    slot)`` once its arrays are copied into ``Vt`` arrays, then ``("saved", frame, timings)``. A request that fails
    sends ``("failed", what, message)``; the later requests are then skipped (frames released unwritten), and
    ``close`` still saves what the stage holds.
    """
    import mmap
    import multiprocessing.connection
    import signal

    # The caller handles the stops (finishing or dropping its frame, then closing the pipe); this process ends when
    # the pipe closes, so a Ctrl-C or a kill of the process group must not end it half-way through a frame.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    _keep_freed_memory()
    conn = multiprocessing.connection.Connection(conn_fd)
    orphan = []

    def send(message):
        """Reply, unless the caller is gone: the frames it queued before are still written."""
        if not orphan:
            try:
                conn.send(message)
            except (BrokenPipeError, ConnectionResetError):
                orphan.append(True)
    writer, ring, failed = None, None, False
    views: list[dict] = []
    try:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):  # the caller is gone: the working folder keeps the frames saved so far
                break
            kind = message[0]
            if kind == "frame":
                _, slot, frame, curves, xforms, meshes = message
                released = []

                def release(slot=slot, released=released):
                    if not released:
                        released.append(True)
                        send(("released", slot))

                if failed:
                    release()
                    continue
                try:
                    before = dict(writer.timings)
                    v = views[slot]
                    prepared = {"frame": frame, "xforms": xforms,
                                "curves": [(name, v[(name, "points")], v[(name, "velocities")] if has_v else None,
                                            extent) for name, has_v, extent in curves],
                                "meshes": {name: (v[(name, "mesh")], extent) for name, extent in meshes.items()}}
                    writer._author_frame(prepared, converted=release)
                    del prepared
                    send(("saved", frame, {k: writer.timings[k] - before[k] for k in before if k != "check"}))
                except Exception as exc:  # reported to the caller, which raises it naming the file
                    failed = True
                    release()
                    send(("failed", f"frame {frame}", _error_text(exc), isinstance(exc, CacheWriteError)))
                continue
            if kind == "close":
                try:
                    send(("ok", str(writer.close()) if writer is not None else None))
                except Exception as exc:
                    send(("error", _error_text(exc)))
                break
            if failed:
                continue
            try:
                if kind == "open":
                    writer = CacheWriter(**message[1])
                    send(("opened", str(writer.partial_path)))
                elif kind == "add_curves":
                    writer._author_curves(message[1])
                elif kind == "add_mesh":
                    writer._author_mesh(message[1])
                elif kind == "ring":
                    _, slot_bytes, slots, layout = message
                    ring = mmap.mmap(ring_fd, slot_bytes * slots)
                    views = [{key: np.frombuffer(ring, np.float32, 3 * n, s * slot_bytes + off).reshape(n, 3)
                              for key, (off, n) in layout.items()} for s in range(slots)]
                else:
                    raise ValueError(f"unknown request {kind!r}")
            except Exception as exc:
                failed = True
                what = {"open": "opening the file", "add_curves": "adding curves", "add_mesh": "adding a mesh",
                        "ring": "mapping the shared frames"}.get(kind, kind)
                send(("failed", what, _error_text(exc), isinstance(exc, CacheWriteError)))
    finally:
        views = []
        if ring is not None:
            try:
                ring.close()
            except BufferError:  # a view still referenced by a traceback; the process ends anyway
                pass
        conn.close()


def _keep_freed_memory() -> None:
    """In the writer process: keep freed large blocks in the heap (glibc), so the ``Vt`` array of the next frame
    reuses pages already mapped instead of faulting fresh ones in (10x cheaper allocation for 100 MB arrays)."""
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    mallopt(m_mmap_threshold, 1 << 30)
    mallopt(m_trim_threshold, (1 << 31) - 1)


# --- static grooms ---------------------------------------------------------------------------------------------

