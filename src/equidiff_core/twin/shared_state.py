"""The sim state (qpos + times) shared from the sim server process to the camera processes.

A seqlock over ``multiprocessing.shared_memory``: one writer (the sim loop) bumps a sequence
counter to odd, writes, bumps it to even; readers copy and retry when the counter was odd
or changed under them. No locks, so a slow camera can never stall the 1 kHz sim loop.
Layout (little-endian): uint64 seq | uint64 nq | float64 sim_time | int64 stamp_ns | float64 qpos[nq].
"""

from __future__ import annotations

import os
import time
from multiprocessing import shared_memory

import numpy as np

HEADER = 32
ENV_VAR = "EQUIDIFF_TWIN_SHM"
_WRITTEN_HERE: set[str] = set()  # blocks this process created (and so must stay tracked)


class SharedStateError(RuntimeError):
    """No twin is publishing state under this name, or the state does not match the model."""


def default_name() -> str:
    """One twin per ROS domain: the name is derived from ROS_DOMAIN_ID unless set explicitly."""
    return os.environ.get(ENV_VAR) or f"equidiff_twin_{os.environ.get('ROS_DOMAIN_ID', '0')}"


class StateWriter:
    def __init__(self, nq: int, name: str | None = None):
        self.name = name or default_name()
        size = HEADER + 8 * nq
        try:
            self._shm = shared_memory.SharedMemory(self.name, create=True, size=size)
        except FileExistsError:  # left over by a killed twin: take it over
            stale = shared_memory.SharedMemory(self.name)
            stale.close()
            stale.unlink()
            self._shm = shared_memory.SharedMemory(self.name, create=True, size=size)
        _WRITTEN_HERE.add(self.name)
        self._header = np.ndarray(4, dtype=np.uint64, buffer=self._shm.buf)
        self._times = np.ndarray(2, dtype=np.float64, buffer=self._shm.buf, offset=16)
        self._stamp = np.ndarray(1, dtype=np.int64, buffer=self._shm.buf, offset=24)
        self._qpos = np.ndarray(nq, dtype=np.float64, buffer=self._shm.buf, offset=HEADER)
        self._header[:2] = (0, nq)

    def write(self, qpos: np.ndarray, sim_time: float, stamp_ns: int) -> None:
        self._header[0] += 1  # odd: writing
        self._qpos[:] = qpos
        self._times[0] = sim_time
        self._stamp[0] = stamp_ns
        self._header[0] += 1  # even: consistent

    def close(self) -> None:
        if self._shm is None:
            return
        del self._header, self._times, self._stamp, self._qpos
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
    try:
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")  # noqa: SLF001
    except Exception:  # pragma: no cover - tracker absent or already unregistered
        pass


class StateReader:
    def __init__(self, name: str | None = None, nq: int | None = None):
        self.name = name or default_name()
        try:
            self._shm = shared_memory.SharedMemory(self.name)
        except FileNotFoundError as err:
            raise SharedStateError(f"no twin state in shared memory {self.name!r}: is twin_node running "
                                   f"on this ROS_DOMAIN_ID (or {ENV_VAR} set to its name)?") from err
        if self.name not in _WRITTEN_HERE:
            _untrack(self._shm)
        self._header = np.ndarray(4, dtype=np.uint64, buffer=self._shm.buf)
        self.nq = int(self._header[1])
        if nq is not None and nq != self.nq:
            raise SharedStateError(f"twin state has {self.nq} positions, the camera's model {nq}: "
                                   "the twin and camera use different scene configs")

    def read(self, retries: int = 1000) -> tuple[np.ndarray, float, int]:
        """(qpos copy, sim_time, stamp_ns) of one consistent snapshot."""
        buf = self._shm.buf
        for _ in range(retries):
            seq = int(self._header[0])
            if seq % 2 == 0 and seq > 0:
                qpos = np.frombuffer(buf, dtype=np.float64, count=self.nq, offset=HEADER).copy()
                sim_time = float(np.frombuffer(buf, dtype=np.float64, count=1, offset=16)[0])
                stamp = int(np.frombuffer(buf, dtype=np.int64, count=1, offset=24)[0])
                if int(self._header[0]) == seq:
                    return qpos, sim_time, stamp
            time.sleep(0.0002)
        raise SharedStateError(f"no consistent twin state in {self.name!r} after {retries} tries")

    def close(self) -> None:
        if self._shm is not None:
            del self._header
            self._shm.close()
            self._shm = None
