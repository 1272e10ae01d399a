"""The sim state (qpos + times) shared from the sim server process to the camera processes.

A ring of snapshots in ``multiprocessing.shared_memory``, each slot guarded by a seqlock:
the single writer (the sim loop) bumps a slot's sequence counter to odd, writes, bumps it to
even; readers copy and retry when the counter was odd or changed under them. No locks, so a
slow camera can never stall the 1 kHz sim loop. The ring (32 slots, ~0.5 s at 60 Hz) lets
every camera render the snapshot nearest to a common trigger time even when the CPU wakes
it late, so three camera processes still produce one time-matched set, like hardware-synced
cameras.

On simulated time (lockstep) the sim also *requests* camera frames: at each frame instant it
writes the state into a separate frame slot, bumps the frame counter and does not step on
until every registered camera has taken that frame (copied its qpos; rendering happens
afterwards, while the sim runs on). Cameras register a slot of their own (their index in
lab.yaml) when they connect and leave it when they disconnect, so the sim waits only for
cameras that exist; one that dies registered is dropped by the sim after its stall timeout.

Layout (little-endian): header uint64 [writes, nq, slots, frames]; cameras uint64
[registered, taken] x MAX_CAMERAS; the frame slot; the ring. A slot = uint64 seq | float64
sim_time | int64 stamp_ns | float64 qpos[nq].
"""

from __future__ import annotations

import contextlib
import os
import time
from multiprocessing import shared_memory

import numpy as np

HEADER = 32
SLOT_HEADER = 24
SLOTS = 32
MAX_CAMERAS = 8
CAMERAS = 16 * MAX_CAMERAS  # (registered, taken) per camera slot
ENV_VAR = "EQUIDIFF_TWIN_SHM"
_WRITTEN_HERE: set[str] = set()  # blocks this process created (and so must stay tracked)


class SharedStateError(RuntimeError):
    """No twin is publishing state under this name, or the state does not match the model."""


def default_name() -> str:
    """One twin per ROS domain: the name is derived from ROS_DOMAIN_ID unless set explicitly."""
    return os.environ.get(ENV_VAR) or f"equidiff_twin_{os.environ.get('ROS_DOMAIN_ID', '0')}"


def _slot_bytes(nq: int) -> int:
    return SLOT_HEADER + 8 * nq


def _frame_offset() -> int:
    return HEADER + CAMERAS


def _ring_offset(nq: int) -> int:
    return HEADER + CAMERAS + _slot_bytes(nq)


def _slot_views(buf, off: int, nq: int):
    return (
        np.ndarray(1, np.uint64, buf, off),
        np.ndarray(1, np.float64, buf, off + 8),
        np.ndarray(1, np.int64, buf, off + 16),
        np.ndarray(nq, np.float64, buf, off + SLOT_HEADER),
    )


def _write_slot(views, qpos: np.ndarray, sim_time: float, stamp_ns: int) -> None:
    seq, t, stamp, q = views
    seq[0] += 1  # odd: writing
    q[:] = qpos
    t[0] = sim_time
    stamp[0] = stamp_ns
    seq[0] += 1  # even: consistent


def _read_slot(buf, off: int, nq: int, retries: int = 100):
    """(qpos copy, sim_time, stamp_ns) of a seqlocked slot; None if never written or torn for good."""
    seq_view = np.ndarray(1, np.uint64, buf, off)
    for _ in range(retries):
        seq = int(seq_view[0])
        if seq % 2 == 0 and seq > 0:
            sim_time = float(np.ndarray(1, np.float64, buf, off + 8)[0])
            stamp = int(np.ndarray(1, np.int64, buf, off + 16)[0])
            qpos = np.ndarray(nq, np.float64, buf, off + SLOT_HEADER).copy()
            if int(seq_view[0]) == seq:
                return qpos, sim_time, stamp
        elif seq == 0:
            return None  # never written
        time.sleep(0.0001)
    return None


def _camera_views(buf) -> np.ndarray:
    return np.ndarray((MAX_CAMERAS, 2), dtype=np.uint64, buffer=buf, offset=HEADER)


class StateWriter:
    def __init__(self, nq: int, name: str | None = None, slots: int = SLOTS):
        self.name = name or default_name()
        size = _ring_offset(nq) + slots * _slot_bytes(nq)
        try:
            self._shm = shared_memory.SharedMemory(self.name, create=True, size=size)
        except FileExistsError:  # left over by a killed twin: take it over
            stale = shared_memory.SharedMemory(self.name)
            stale.close()
            stale.unlink()
            self._shm = shared_memory.SharedMemory(self.name, create=True, size=size)
        _WRITTEN_HERE.add(self.name)
        self.nq, self.slots = nq, slots
        self._header = np.ndarray(4, dtype=np.uint64, buffer=self._shm.buf)
        self._header[:] = (0, nq, slots, 0)
        self._cameras = _camera_views(self._shm.buf)
        self._cameras[:] = 0
        self._frame = _slot_views(self._shm.buf, _frame_offset(), nq)
        self._slots = [_slot_views(self._shm.buf, _ring_offset(nq) + i * _slot_bytes(nq), nq) for i in range(slots)]

    def write(self, qpos: np.ndarray, sim_time: float, stamp_ns: int) -> None:
        _write_slot(self._slots[int(self._header[0]) % self.slots], qpos, sim_time, stamp_ns)
        self._header[0] += 1

    # -- lockstep frames ---------------------------------------------------------------------
    def request_frame(self, qpos: np.ndarray, sim_time: float, stamp_ns: int) -> int:
        """Publish the state of a frame instant for the cameras; returns the frame's number (1, 2, ...)."""
        _write_slot(self._frame, qpos, sim_time, stamp_ns)
        self._header[3] += 1
        return int(self._header[3])

    def cameras_behind(self, frame: int) -> list[int]:
        """Registered camera slots that have not yet taken frame ``frame``."""
        return [i for i in range(MAX_CAMERAS) if self._cameras[i, 0] and int(self._cameras[i, 1]) < frame]

    def drop_camera(self, slot: int) -> None:
        """Stop waiting for a camera (it stalled); it registers again when it reconnects."""
        self._cameras[slot, 0] = 0

    def close(self) -> None:
        if self._shm is None:
            return
        del self._header, self._slots, self._cameras, self._frame
        self._shm.close()
        try:
            self._shm.unlink()
        except FileNotFoundError:
            pass
        _WRITTEN_HERE.discard(self.name)
        self._shm = None


def _untrack(shm: shared_memory.SharedMemory) -> None:
    # Python < 3.13 registers every attached block with the resource tracker, which unlinks it
    # when the *reader* exits; a reader must never destroy the writer's block.
    from multiprocessing import resource_tracker

    with contextlib.suppress(Exception):  # the tracker absent or the block already unregistered
        resource_tracker.unregister(shm._name, "shared_memory")


class StateReader:
    def __init__(self, name: str | None = None, nq: int | None = None):
        self.name = name or default_name()
        try:
            self._shm = shared_memory.SharedMemory(self.name)
        except FileNotFoundError as err:
            raise SharedStateError(
                f"no twin state in shared memory {self.name!r}: is twin_node running "
                f"on this ROS_DOMAIN_ID (or {ENV_VAR} set to its name)?"
            ) from err
        if self.name not in _WRITTEN_HERE:
            _untrack(self._shm)
        self._header = np.ndarray(4, dtype=np.uint64, buffer=self._shm.buf)
        self.nq, self.slots = int(self._header[1]), int(self._header[2])
        self._slot: int | None = None  # this camera's registration (lockstep frames)
        if nq is not None and nq != self.nq:
            raise SharedStateError(
                f"twin state has {self.nq} positions, the camera's model {nq}: "
                "the twin and camera use different scene configs"
            )

    def _read_slot(self, i: int):
        return _read_slot(self._shm.buf, _ring_offset(self.nq) + i * _slot_bytes(self.nq), self.nq)

    def read(self, wait_s: float = 1.0) -> tuple[np.ndarray, float, int]:
        """(qpos copy, sim_time, stamp_ns) of the newest consistent snapshot."""
        deadline = time.monotonic() + wait_s
        while True:
            writes = int(self._header[0])
            if writes > 0:
                got = self._read_slot((writes - 1) % self.slots)
                if got is not None:
                    return got
            if time.monotonic() > deadline:
                raise SharedStateError(f"no consistent twin state in {self.name!r}")
            time.sleep(0.001)

    def read_nearest(self, stamp_ns: int) -> tuple[np.ndarray, float, int]:
        """The snapshot whose stamp is nearest ``stamp_ns`` (the newest if all are older)."""
        best, best_dt = None, None
        for i in range(self.slots):
            got = self._read_slot(i)
            if got is None:
                continue
            dt = abs(got[2] - stamp_ns)
            if best_dt is None or dt < best_dt:
                best, best_dt = got, dt
        return best if best is not None else self.read()

    # -- lockstep frames (a camera's side) -----------------------------------------------------
    def register(self, slot: int) -> None:
        """Ask the sim to wait for this camera at every frame instant from now on."""
        if not 0 <= slot < MAX_CAMERAS:
            raise SharedStateError(f"camera slot {slot} is outside 0..{MAX_CAMERAS - 1}")
        cams = _camera_views(self._shm.buf)
        cams[slot, 1] = self._header[3]  # frames requested so far count as taken
        cams[slot, 0] = 1
        self._slot = slot

    def unregister(self) -> None:
        if self._slot is not None and self._shm is not None:
            _camera_views(self._shm.buf)[self._slot, 0] = 0
            self._slot = None

    def take_frame(self, after: int, timeout_s: float, poll_s: float = 0.003) -> tuple[int, np.ndarray, float, int]:
        """Wait for the first frame numbered above ``after``, take it (the sim may step on) and
        return (frame, qpos, sim_time, stamp_ns); SharedStateError after ``timeout_s``. Polling every
        few ms holds the sim a little per frame; polling every 1 ms, three idle cameras woke thousands of
        times a second on a machine with few cores, each wake-up competing with the sim's 1 kHz loop."""
        deadline = time.monotonic() + timeout_s
        while True:
            frame = int(self._header[3])
            if frame > after:
                got = _read_slot(self._shm.buf, _frame_offset(), self.nq)
                if got is not None:
                    if self._slot is not None:
                        cams = _camera_views(self._shm.buf)
                        cams[self._slot, 1] = frame
                        cams[self._slot, 0] = 1  # back in, if the sim had dropped us as stalled
                    return (frame, *got)
            if time.monotonic() > deadline:
                raise SharedStateError(f"no frame requested by the twin within {timeout_s} s")
            time.sleep(poll_s)

    def close(self) -> None:
        if self._shm is not None:
            self.unregister()
            del self._header
            self._shm.close()
            self._shm = None
