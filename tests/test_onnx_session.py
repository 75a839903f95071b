"""onnxruntime sessions with their thread option measured (tasks/detection/onnx_session.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from cadestate.config import DetectConfig
from tasks.detection.models import nanodet as nd
from tasks.detection.onnx_session import MeasuredSession

needs_nanodet = pytest.mark.skipif(not nd.is_built(nd.default_cache_dir()),
                                   reason="the NanoDet-m model is not built (`make models`, which `make test` runs)")


SLOW_S = 0.3
"""How much slower the losing option is made: far above what another job's load adds to a call on a
shared 2-core machine (at 0.05 s the decisions below flipped while rooms rendered beside the tests)."""


class Slowed:
    """A real onnxruntime session whose runs take ``extra_s`` longer (a machine where it is slow)."""

    def __init__(self, session, extra_s: float) -> None:
        self.session, self.extra_s = session, extra_s

    def run(self, names, feeds):
        time.sleep(self.extra_s)
        return self.session.run(names, feeds)


def detector_session() -> tuple[MeasuredSession, dict]:
    from tasks.detection.detectors import load_detector

    detector = load_detector(DetectConfig())
    frames = np.random.default_rng(0).integers(0, 256, (detector.batch_size, 360, 640, 3), np.uint8)
    x, _ = detector.inputs(list(frames))  # as the detect stage feeds it: a 640x360 frame's canvas
    return detector.session, {detector.session.get_inputs()[0].name: x}


@needs_nanodet
def test_both_thread_options_give_the_same_bits_and_are_set_as_named():
    session, feeds = detector_session()
    options = {arm: s.get_session_options() for arm, s in session.sessions.items()}
    assert {arm: o.get_session_config_entry("session.intra_op.allow_spinning") for arm, o in options.items()} == \
        {"sleep": "0", "spin": "1"}
    assert all(o.intra_op_num_threads == 2 for o in options.values())
    sleep, spin = (session.sessions[arm].run(None, feeds) for arm in ("sleep", "spin"))
    assert len(sleep) == len(spin) and all(np.array_equal(a, b) for a, b in zip(sleep, spin))


def arms_called(session: MeasuredSession, feeds: dict, n: int) -> list[str]:
    """The option each of ``n`` calls went to."""
    arms = []
    for _ in range(n):
        before = {arm: t.calls for arm, t in session.times.items()}
        session.run(None, feeds)
        arms.append(next(arm for arm, t in session.times.items() if t.calls > before[arm]))
    return arms


@needs_nanodet
def test_calls_go_to_the_faster_option_and_follow_a_change_of_load():
    session, feeds = detector_session()
    real = dict(session.sessions)
    session.sessions["spin"] = Slowed(real["spin"], SLOW_S)  # spinning loses on this "machine"
    arms = arms_called(session, feeds, 20)
    assert arms[:8] == ["sleep", "spin"] * 4  # a warm-up, then 3 timed calls each, alternating
    assert session.choice == "sleep"
    assert arms[8:] == ["spin" if i % 16 == 0 else "sleep" for i in range(8, 20)]  # every 16th call explores
    session.sessions["spin"], session.sessions["sleep"] = real["spin"], Slowed(real["sleep"], SLOW_S)  # the load changes
    arms = arms_called(session, feeds, 60)
    assert session.choice == "spin" and arms[-8:] == ["spin"] * 8  # 3 explorations made the fast ones the median
    summary = session.summary()
    assert summary["choice"] == "spin" and summary["sleep"]["calls"] + summary["spin"]["calls"] == 80


@needs_nanodet
def test_one_slow_call_does_not_decide():
    session, feeds = detector_session()
    real = dict(session.sessions)
    session.sessions["spin"] = Slowed(real["spin"], 0.0)
    session.sessions["sleep"] = Slowed(real["sleep"], SLOW_S)  # sleeping loses ...
    assert arms_called(session, feeds, 3) == ["sleep", "spin", "sleep"]  # warm-ups, sleeping's first timed call
    session.sessions["spin"].extra_s = 2 * SLOW_S  # ... but spinning's first timed call is held up by something else
    assert arms_called(session, feeds, 1) == ["spin"]
    session.sessions["spin"].extra_s = 0.0
    assert arms_called(session, feeds, 4) == ["sleep", "spin"] * 2
    assert session.choice == "spin"


@needs_nanodet
def test_one_thread_has_one_session():
    from tasks.detection.detectors import detector_path

    session = MeasuredSession(detector_path(DetectConfig()), threads=1)
    assert list(session.sessions) == ["sleep"]
    x = np.zeros((1, 3, 416, 416), np.float32)
    assert session.run(None, {session.get_inputs()[0].name: x})[0].shape[0] == 1
    assert session.choice == "sleep" and session.summary()["sleep"]["calls"] == 1
