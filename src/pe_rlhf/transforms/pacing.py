"""``RealtimePacing``: hold an env to a steady real-time step rate and measure how steady it was.

A person driving as mentor sees one frame per env step, so the step rate is the display's frame
rate. The transform sleeps before each step until the next tick of a fixed-rate clock and keeps the
recent frame times for :meth:`RealtimePacing.frame_stats`.
"""

from __future__ import annotations

import collections
import time

import numpy as np
from tensordict import TensorDictBase
from torchrl.envs import Transform

STAT_QUANTILES = (50, 95, 99)


class RealtimePacing(Transform):
    """Step at ``hz`` steps per second (deadline-based), recording each frame's time.

    Reads and writes no keys, and changes no spec: it only waits. The wait happens in
    ``_inv_call``, before the transforms in front of it see the action, so appended last it ticks
    just before the mentor is asked (and a human mentor's window is drawn) and the simulator moves.

    The clock: tick ``k`` is due at ``deadline_k = deadline_{k-1} + 1/hz``, so an early or late
    frame does not shift the ones after it (no drift, unlike sleeping ``1/hz`` after each step).
    A step that ends more than one period past its deadline re-anchors the clock at its tick
    (a long stall is one late frame, not a burst of catch-up frames). Resets don't touch the clock:
    their time falls into the frame of the first step after them.

    A frame's time is the interval between consecutive ticks; its jitter is
    ``|frame_time - 1/hz|``; a frame is late when its tick comes more than ``late_tolerance``
    periods after its deadline.

    Args:
        hz: target steps per second (> 0).
        history: frames kept for :meth:`frame_stats` (the most recent ones).
        late_tolerance: lateness, in periods, before a frame counts as late (default 0.1: 10 ms at 10 Hz).
    """

    def __init__(self, hz: float = 10.0, history: int = 100_000, late_tolerance: float = 0.1):
        if isinstance(hz, bool) or not isinstance(hz, (int, float)) or not np.isfinite(hz) or hz <= 0:
            raise ValueError(f"hz must be a finite number > 0 (steps per second), got {hz!r}")
        if int(history) < 1:
            raise ValueError(f"history must be >= 1 frames, got {history!r}")
        super().__init__(in_keys=[], out_keys=[])
        self.hz = float(hz)
        self.period = 1.0 / self.hz
        self.late_tolerance = float(late_tolerance)
        self._frame_times: collections.deque[float] = collections.deque(maxlen=int(history))
        self._late: collections.deque[bool] = collections.deque(maxlen=int(history))
        self._deadline: float | None = None  # the last tick's deadline
        self._last_tick: float | None = None

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.wait_for_tick()
        return tensordict

    def wait_for_tick(self) -> float:
        """Sleep until the next tick is due and record the frame; returns the tick time (perf_counter)."""
        if self._deadline is None:  # the first step starts the clock
            self._deadline = self._last_tick = time.perf_counter()
            return self._last_tick
        deadline = self._deadline + self.period
        delay = deadline - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        tick = time.perf_counter()
        lateness = tick - deadline
        self._frame_times.append(tick - self._last_tick)
        self._late.append(lateness > self.late_tolerance * self.period)
        self._deadline = tick if lateness > self.period else deadline
        self._last_tick = tick
        return tick

    def restart_clock(self) -> None:
        """Forget the clock (the next step starts it again); the recorded frames stay."""
        self._deadline = self._last_tick = None

    def clear_stats(self) -> None:
        """Drop the recorded frames (the clock keeps running)."""
        self._frame_times.clear()
        self._late.clear()

    def frame_stats(self, last: int | None = None) -> dict[str, float]:
        """Frame time and jitter in ms over the recorded frames (the ``last`` ones when given).

        Keys: ``frames``, ``late_frames``, ``frame_ms_{mean,std,p50,p95,p99,max}`` and
        ``jitter_ms_{mean,std,p50,p95,p99,max}``; NaN statistics when no frame was recorded yet.
        """
        times = list(self._frame_times)
        late = list(self._late)
        if last is not None:
            times, late = times[len(times) - min(int(last), len(times)):], late[len(late) - min(int(last), len(late)):]
        frame_ms = 1000.0 * np.asarray(times, dtype=np.float64)
        stats = {"frames": float(len(times)), "late_frames": float(sum(late))}
        stats.update(_summary("frame_ms", frame_ms))
        stats.update(_summary("jitter_ms", np.abs(frame_ms - 1000.0 * self.period)))
        return stats

    def __repr__(self) -> str:
        return f"{type(self).__name__}(hz={self.hz})"


def _summary(name: str, values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {f"{name}_{s}": float("nan") for s in ("mean", "std", *(f"p{q}" for q in STAT_QUANTILES), "max")}
    out = {f"{name}_mean": float(values.mean()), f"{name}_std": float(values.std())}
    out.update({f"{name}_p{q}": float(np.percentile(values, q)) for q in STAT_QUANTILES})
    out[f"{name}_max"] = float(values.max())
    return out
