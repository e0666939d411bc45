"""Fuzzed MJCF: the shipped scenes mutated (elements dropped or repeated, numbers set to 0, negative, 1e40, nan,
garbage text, bytes that are not UTF-8) and fed to ``kamino.load_mjcf``, then stepped once when they load. Every
failure must be a kamino error (``ModelError``, ``ValueError``, ``TypeError``, naming what is wrong), never another
exception and never a hang (each example runs under a time bound)."""

from __future__ import annotations

import contextlib
import re
import signal
import warnings
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import kamino

SCENES = Path(kamino.__file__).resolve().parent / "bench" / "scenes"
#: small scenes (a few bodies: one step each is cheap once Warp's kernels are loaded)
SOURCES = [(SCENES / name).read_text() for name in ("fourbar.xml", "fourbar_connect.xml")]
#: a number inside an attribute value
NUMBER = re.compile(r"(?<=[\s\"])-?\d+(?:\.\d*)?(?:e-?\d+)?(?=[\s\"])")
#: a self-closing element (dropped or repeated whole)
ELEMENT = re.compile(r"<[a-z]+\b[^<>]*/>")
#: what a number becomes
BAD_NUMBERS = ["0", "-1", "-0.5", "1e40", "1e-30", "1e31", "nan", "inf", "-inf", "garbage", ""]
#: the seconds an example may take (a load and one step take well under one)
TIME_BOUND_S = 20


class Hang(Exception):
    """An example ran past :data:`TIME_BOUND_S`."""


@contextlib.contextmanager
def time_bound(seconds: float):
    """Raise :class:`Hang` in the main thread once ``seconds`` have passed (SIGALRM)."""

    def expire(signum, frame):
        raise Hang(f"example ran past {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@st.composite
def mutated_mjcf(draw) -> str | bytes:
    """A shipped scene with one to three mutations; bytes when a mutation inserts bytes that are not UTF-8."""
    text = draw(st.sampled_from(SOURCES))
    raw = None
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["number", "number", "drop", "repeat", "text", "bytes"]))
        if kind == "number" and (spans := [m.span() for m in NUMBER.finditer(text)]):
            a, b = draw(st.sampled_from(spans))
            text = text[:a] + draw(st.sampled_from(BAD_NUMBERS)) + text[b:]
        elif kind in ("drop", "repeat") and (spans := [m.span() for m in ELEMENT.finditer(text)]):
            a, b = draw(st.sampled_from(spans))
            text = text[:a] + (text[a:b] * 2 if kind == "repeat" else "") + text[b:]
        elif kind == "text":
            at = draw(st.integers(0, len(text)))
            text = text[:at] + draw(st.text(max_size=12)) + text[at:]
        elif kind == "bytes":
            at = draw(st.sampled_from([m.end() for m in re.finditer(r'name="', text)] or [len(text)]))
            raw = text[:at].encode() + draw(st.sampled_from([b"\xff\xfe", b"\x80", b"\xc3("])) + text[at:].encode()
    return raw if raw is not None else text


def load_and_step(source: str | bytes) -> str:
    """``"rejected"`` (a kamino error), ``"failed"`` (rejected when stepped) or ``"stepped"``."""
    try:
        model = kamino.load_mjcf(source)
    except (kamino.ModelError, ValueError, TypeError):
        return "rejected"
    try:
        kamino.step(model, kamino.init_state(model), backend="warp")
    except (ValueError, TypeError):
        return "failed"
    return "stepped"


@pytest.fixture(scope="module")
def warm_warp(tmp_path_factory):
    """One step of an unmutated scene: Warp's kernels load here, outside the examples' time bound. The module runs
    in a temporary folder: MuJoCo writes its warnings (a 'NaN' in the XML) to MUJOCO_LOG.TXT in the working
    folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp_path_factory.mktemp("fuzz"))
        assert load_and_step(SOURCES[0]) == "stepped"
        yield


@settings(max_examples=80, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(source=mutated_mjcf())
def test_mutated_scenes_fail_only_with_kamino_errors(warm_warp, source):
    with warnings.catch_warnings(), time_bound(TIME_BOUND_S):
        warnings.simplefilter("ignore")
        assert load_and_step(source) in ("rejected", "failed", "stepped")
