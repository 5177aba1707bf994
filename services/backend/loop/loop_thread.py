"""The loop closer in a thread of its own (:class:`ThreadedLoopCloser`): the back end only enqueues keyframe
events and reads the newest correction, so that ``estimator/state`` never waits for a pose-graph solve."""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np

from services.backend.loop.history import KeyframeRecord
from services.backend.loop.loop_closer import LoopCloser, VerifiedLoop
from services.backend.loop.saved_map import save_sparse
from services.backend.loop.verification import FeatureSet

log = logging.getLogger("sigmaslam.loop")


class ThreadedLoopCloser:
    """Runs a :class:`LoopCloser` in its own thread; ``submit_*`` only enqueue (oldest dropped when full).

    With ``synchronous`` (``loop.synchronous``) there is no thread: every event is handled in the caller's
    thread as it is submitted, so a run over recorded data gives the same trajectory every time (evaluation);
    the live back end keeps the thread, so that ``estimator/state`` never waits for a pose-graph solve."""

    def __init__(self, closer: LoopCloser, synchronous: bool = False) -> None:
        self.closer = closer
        self.synchronous = synchronous
        self._q: queue.Queue = queue.Queue()
        self._lock = threading.Lock()
        self._correction = np.eye(4)
        self._keyframes = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        self.generation = 0  # increases after every pose-graph solve
        self._solves = 0
        self.dropped = 0
        self.errors = 0
        self.busy_s = 0.0  # time spent handling events (with ``synchronous``: inside the caller's calls)
        self._verified: list[VerifiedLoop] = []
        self._aligned = closer.aligned
        self.saved = 0  # sparse maps written
        self._thread = None
        if not synchronous:
            self._thread = threading.Thread(target=self._run, name="loop-closer", daemon=True)
            self._thread.start()

    def _put(self, item) -> None:
        if self.synchronous:
            self._handle(item)
            return
        if self._q.qsize() >= self.closer.cfg.queue_depth:
            try:
                self._q.get_nowait()
                self.dropped += 1
            except queue.Empty:
                pass
        self._q.put(item)

    def submit_features(self, stamp_ns: int, fs: FeatureSet) -> None:
        self._put(("features", int(stamp_ns), fs))

    def submit_record(self, rec: KeyframeRecord) -> None:
        self._put(("record", rec))

    def submit_map_to_map(self, term) -> None:
        self._put(("m2m", term))

    def submit_window(self, stamps_ns: np.ndarray, T_WS: np.ndarray) -> None:
        """The window's keyframe poses (frame W, uncorrected) after an optimisation: for loops applied early."""
        self._put(("window", np.array(stamps_ns, np.int64), np.array(T_WS, float)))

    def submit_status(self, stamp_ns: int, status: str, T_pub: np.ndarray | None = None) -> None:
        self._put(("status", int(stamp_ns), status, T_pub))

    def submit_save(self, path, session: dict, window: list = ()) -> None:
        """Write the sparse map (:meth:`LoopCloser.sparse_map`, with the window's keyframe records ``window``) to
        ``path`` in the loop thread (never dropped)."""
        if self.synchronous:
            self._handle(("save", path, session, list(window)))
        else:
            self._q.put(("save", path, session, list(window)))

    @property
    def aligned(self) -> bool:
        """Whether the published frame is the saved map's (always, without a saved map)."""
        with self._lock:
            return self._aligned

    def correction(self) -> np.ndarray:
        with self._lock:
            return self._correction.copy()

    def corrected_keyframes(self) -> tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(generation, (states, stamps, T_WS)) of the pose-graph nodes as of the latest correction."""
        with self._lock:
            return self.generation, self._keyframes

    def take_verified(self) -> list[VerifiedLoop]:
        """Loops verified since the last call (the back end's o2p terms learn the old landmarks a keyframe sees)."""
        with self._lock:
            out, self._verified = self._verified, []
        return out

    def snapshot(self) -> tuple[np.ndarray, int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(correction, generation, corrected keyframes) of one and the same solve (the loop thread may finish
        another between two separate calls)."""
        with self._lock:
            return self._correction.copy(), self.generation, self._keyframes

    def drain(self, timeout_s: float = 30.0) -> bool:
        """Wait until everything submitted so far is processed."""
        if self.synchronous:  # nothing waits
            return True
        done = threading.Event()
        self._q.put(("mark", done))
        return done.wait(timeout_s)

    def close(self) -> None:
        if self._thread is not None:
            self._q.put(("stop",))
            self._thread.join(timeout=10)

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item[0] == "stop":
                return
            if item[0] == "mark":
                item[1].set()
                continue
            self._handle(item)

    def _handle(self, item) -> None:
        """One event: features, status, a keyframe record or a map-to-map term; publishes the correction."""
        c, kind = self.closer, item[0]
        t0 = time.perf_counter()
        try:
            if kind == "features":
                found = c.add_keyframe_features(item[1], item[2])
                if found:
                    with self._lock:
                        self._verified.extend(found)
            elif kind == "status":
                aligned = c.aligned
                c.note_status(item[1], item[2], item[3])
                if c.aligned != aligned:  # the session moved into a saved map's frame: publish that
                    self._publish(c)
            elif kind == "window":
                if c.note_window(item[1], item[2]):
                    self._publish(c)
            elif kind == "save":
                m = c.sparse_map(item[2], item[3])
                if m is not None:
                    save_sparse(m, item[1])
                    self.saved += 1
            else:
                (c.add_record if kind == "record" else c.add_map_to_map)(item[1])
                self._publish(c)
        except Exception:  # noqa: BLE001 - a bad keyframe must not kill loop closing; counted and logged
            self.errors += 1
            log.exception("loop closer: %s event failed", kind)
        finally:
            self.busy_s += time.perf_counter() - t0

    def _publish(self, c: LoopCloser) -> None:
        """The correction (and, after a solve, the corrected keyframes) for the back end's next state."""
        corr = c.correction()
        solved = len(c.solve_ms) != self._solves
        snap = c.corrected_keyframes() if solved else None
        with self._lock:
            self._correction = corr
            self._aligned = c.aligned
            if solved:  # past keyframes moved: a new generation of corrected nodes
                self._solves = len(c.solve_ms)
                self._keyframes = snap
                self.generation += 1
