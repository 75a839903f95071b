"""CPU onnxruntime sessions for the detector and the embedder, with their thread option measured.

onnxruntime's intra-op threads either spin between operators (its default) or sleep. Which is
faster depends on the machine's load at the time, not on the model. NanoDet-m 416, 1 frame per call,
32 frames of the bench clip, sessions interleaved on the same inputs, on 2 cores that another job
also used (ms per frame, while the job ran / while it paused): spinning threads 45-52 / 15;
sleeping threads 24-33 / 16.6-17.7; 1 thread 27-30 / 27. So :class:`MeasuredSession` holds both
sessions of one model and times them on the calls themselves. Their outputs are identical: they
differ only in how idle threads wait (a test holds this).

The spinning session stops spinning when a run ends (``session.force_spinning_stop``): threads left
spinning after a run slowed whatever ran next (the other session's next frame took 31 ms instead
of 23 ms), which would also bias the measurement. ``bench/detect_throughput.py`` (138 frames, 2 cores,
3 rounds a run): quiet, five runs took 0.93-1.16x the time of a bare session with onnxruntime's
defaults (median 0.99; the two options are within a few per cent there, and the bare session's
own time varied from 22.1 to 27.5 ms a frame between runs); beside one busy process, the detector
chose sleeping threads and took 0.73-0.79x of it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ARMS = ("sleep", "spin")
"""The two thread options: threads that sleep between operators, threads that spin."""


def load_session(model: Path | bytes, threads: int = 2, spin: bool = False):  # -> onnxruntime.InferenceSession
    """A CPU onnxruntime session of a model file or serialized model: sequential execution,
    ``threads`` intra-op threads that spin between operators if ``spin``, else sleep."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    if spin:  # threads stop spinning when a run ends: they spin between operators, not between runs
        opts.add_session_config_entry("session.force_spinning_stop", "1")
    try:
        return ort.InferenceSession(model if isinstance(model, bytes) else str(model), opts,
                                    providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        what = "serialized model" if isinstance(model, bytes) else str(model)
        raise ValueError(f"{what}: not a loadable ONNX model: {e}") from None


@dataclass
class ArmTimes:
    """What one thread option has cost: calls made, and the seconds per input row of each timed one."""

    calls: int = 0
    history: list[float] = field(default_factory=list, repr=False)

    def recent(self, window: int) -> float:
        """Median seconds per row of the last ``window`` timed calls (inf: none yet)."""
        return float(np.median(self.history[-window:])) if self.history else float("inf")


class MeasuredSession:
    """One model in two sessions, threads sleeping and threads spinning; each call goes to the one
    that has been faster here lately.

    The first call of each session warms it up (memory arenas; not timed). Then the two alternate
    until each has ``first_samples`` timed calls; afterwards every call goes to the session whose
    median seconds per input row over its last ``window`` timed calls is lower, except every
    ``explore_every``-th, which goes to the other so that a change in the machine's load is seen.
    Medians, not means: one call slowed by something else on the machine must not decide (with a
    single timed call each and a smoothed mean, 1 round in 3 of the bench chose the slower option on
    a quiet machine). With one thread there is nothing to choose: one session. Calls must come from
    one thread at a time (as the stages make them).
    """

    def __init__(self, model: Path | bytes, threads: int = 2, *, explore_every: int = 16, first_samples: int = 3,
                 window: int = 5):
        self.explore_every, self.first_samples, self.window = explore_every, first_samples, window
        arms = ARMS if threads > 1 else ARMS[:1]
        self.sessions = {arm: load_session(model, threads, spin=arm == "spin") for arm in arms}
        self.times = {arm: ArmTimes() for arm in arms}
        self._calls = 0

    def get_inputs(self):
        return self.sessions[ARMS[0]].get_inputs()

    def get_outputs(self):
        return self.sessions[ARMS[0]].get_outputs()

    @property
    def choice(self) -> str:
        """The thread option now preferred ('sleep' or 'spin')."""
        return min(self.times, key=lambda arm: self.times[arm].recent(self.window))

    def _next_arm(self) -> str:
        short = [arm for arm in self.times if len(self.times[arm].history) < self.first_samples]
        if short:  # warm-ups, then the first timed calls of each, alternating
            return min(short, key=lambda arm: self.times[arm].calls)
        best = self.choice
        if len(self.times) > 1 and self._calls % self.explore_every == 0:
            return next(arm for arm in self.times if arm != best)
        return best

    def run(self, output_names, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """``InferenceSession.run`` on the session chosen (class docstring)."""
        arm = self._next_arm()
        t0 = time.perf_counter()
        out = self.sessions[arm].run(output_names, feeds)
        seconds = time.perf_counter() - t0
        self._calls += 1
        times = self.times[arm]
        times.calls += 1
        if times.calls > 1:  # the first call warmed the session up
            times.history.append(seconds / max(len(next(iter(feeds.values()))), 1))
        return out

    def summary(self) -> dict:
        """Per option: calls and the median of its timed ms per input row; and the option preferred."""
        return {"choice": self.choice, **{arm: {"calls": t.calls, "ms_per_row": round(1000 * float(np.median(t.history)), 2)
                                                if t.history else None} for arm, t in self.times.items()}}
