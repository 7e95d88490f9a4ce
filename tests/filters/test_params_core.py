"""filters.params itself: every Check takes a good value, and a bad one raises a one-line
ParamError naming the key; validate runs the declared checks on a frozen dataclass."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from filters.params import (ParamError, array, as_given, checks, choice, docs, instance_of, integer, number, optional,
                            param, require, several, string, switch, validate, vec3)


def _rejects(check, value, key="k"):
    with pytest.raises(ParamError) as err:
        check(key, value)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{key}: ") and err.value.key == key
    assert isinstance(err.value, ValueError)
    return text


@pytest.mark.parametrize("check, good, stored, bad", [
    (integer(), -3, -3, 1.5),
    (integer(1), 2, 2, 0),
    (integer(0, 5), 5, 5, 6),
    (integer(1, numpy=True), np.int64(4), 4, np.float64(4.0)),
    (number(), -2, -2.0, math.nan),
    (number(0, lo_open=True), 0.5, 0.5, 0.0),
    (number(0, hi=1, hi_open=True), 0.0, 0.0, 1.0),
    (number(0, lo_open=True, hi=1), 1, 1.0, 1.5),
    (number(finite=False), math.inf, math.inf, "1.0"),
    (number(numpy=True), np.float32(0.25), 0.25, np.array([1.0])),
    (choice("a", "b"), "b", "b", "c"),
    (switch(), True, True, 1),
    (switch(numpy=True), np.bool_(False), False, "yes"),
    (string(), "x", "x", 3),
    (optional(integer(1)), None, None, 0),
    (optional(integer(1)), 3, 3, -1),
    (several(integer(0), 2), (1, 2), [1, 2], (1,)),
    (several(number(), "+"), [1, 2.5], [1.0, 2.5], []),
])
def test_check_accepts_good_and_rejects_bad(check, good, stored, bad):
    out = check("k", good)
    assert out == stored and type(out) is type(stored)
    _rejects(check, bad)


def test_integer_rejects_bools_and_numpy_integers_unless_asked():
    for c in (integer(), integer(0), integer(0, numpy=True)):
        assert "got True" in _rejects(c, True)
    _rejects(integer(0), np.int64(1))
    assert _rejects(integer(1), 0) == "k: expected a positive integer, got 0"


def test_number_message_and_bounds_text():
    assert _rejects(number(0, lo_open=True), -1.0) == "k: expected a positive finite number, got -1.0"
    assert _rejects(number(0, lo_open=True, hi=1, hi_open=True), 1.0) == "k: expected a number in (0, 1), got 1.0"
    assert _rejects(number(hi=2), 3) == "k: expected a finite number <= 2, got 3"
    _rejects(number(), True)
    _rejects(number(), np.float32(1.0))  # numpy scalars only with numpy=True (np.float64 is a float)
    assert number()("k", np.float64(2.0)) == 2.0


def test_array_returns_a_read_only_float_array():
    a = array((2,))("k", [1, 2])
    assert a.dtype == float and not a.flags.writeable
    np.testing.assert_array_equal(a, [1.0, 2.0])
    v = vec3()("k", (1, 2, 3))
    assert v.shape == (3,) and not v.flags.writeable
    _rejects(vec3(), (1, 2))
    _rejects(vec3(), (1, 2, math.nan))
    _rejects(array(), "abc")
    assert "got shape (2, 2)" in _rejects(array((3, -1)), np.zeros((2, 2)))


def test_array_bounds_nan_and_batch_axes():
    pos = array(lo=0, lo_open=True)
    assert pos("k", 2.0).shape == ()
    text = _rejects(pos, np.zeros((4, 4)))  # a multi-line repr is brought onto one line
    assert "got array(" in text
    batch = array((..., -1, 3), finite=False, nan=True)
    assert batch("k", np.full((5, 2, 4, 3), np.nan)).shape == (5, 2, 4, 3)
    assert batch("k", np.zeros((4, 3))).shape == (4, 3)
    _rejects(batch, np.zeros(3))
    _rejects(batch, np.zeros((4, 2)))
    _rejects(array(finite=False), [math.nan])
    assert array(finite=False)("k", [math.inf])[0] == math.inf


def test_array_copy_false_is_a_read_only_view_of_the_callers_array():
    src = np.arange(6.0).reshape(2, 3)
    out = array((-1, 3), copy=False)("k", src)
    assert np.shares_memory(out, src) and not out.flags.writeable and src.flags.writeable
    cp = array((-1, 3))("k", src)
    assert not np.shares_memory(cp, src)


@dataclass(frozen=True)
class _Cfg:
    n: int = param(2, check=integer(1), doc="a count")
    gain: float = param(0.5, check=number(0), doc="a gain")
    axis: np.ndarray = param((0.0, 0.0, 1.0), check=vec3(), doc="an axis")
    lo: float = param(0.0, check=number(), doc="lower end")
    hi: float = param(1.0, check=number(), doc="upper end")

    def __post_init__(self):
        validate(self)
        require(self.lo < self.hi, "hi", f"expected > lo = {self.lo:g}, got {self.hi:g}")


def test_instance_of_stores_the_object_and_names_the_class():
    class Settings:
        pass

    one = Settings()
    assert instance_of(Settings)("s", one) is one
    assert instance_of(Settings, none=True)("s", None) is None
    assert "expected a tests" not in _rejects(instance_of(Settings, what="a Settings"), {"a": 1}, "s")
    assert _rejects(instance_of(Settings), None, "s").endswith("Settings, got None")
    text = _rejects(instance_of(Settings, none=True, what="a Settings or None"), "x" * 200, "s")
    assert text.startswith("s: expected a Settings or None, got 'xxx") and len(text) < 120  # one short line


def test_as_given_keeps_the_value_and_the_checks_message():
    t = (1.0, 2.0)
    assert as_given(array(lo=0.0))("w", t) is t  # a tuple stays the caller's tuple (hashable)
    assert _rejects(as_given(array(lo=0.0, what="finite speeds >= 0")), (1.0, -2.0), "w") == \
        _rejects(array(lo=0.0, what="finite speeds >= 0"), (1.0, -2.0), "w")


def test_validate_on_a_frozen_dataclass_stores_what_the_checks_return():
    c = _Cfg(gain=1)
    assert type(c.gain) is float and isinstance(c.axis, np.ndarray) and not c.axis.flags.writeable
    assert list(checks(_Cfg)) == ["n", "gain", "axis", "lo", "hi"] and docs(_Cfg)["gain"] == "a gain"
    with pytest.raises(ParamError, match=r"^n: expected a positive integer, got 0$"):
        _Cfg(n=0)
    with pytest.raises(ParamError, match=r"^gain: "):
        _Cfg(gain=-1.0)
    with pytest.raises(ParamError, match=r"^hi: expected > lo = 2, got 1$"):
        _Cfg(lo=2.0)


def test_require():
    require(True, "k", "never")
    with pytest.raises(ParamError, match=r"^k: why$"):
        require(False, "k", "why")


def test_param_needs_a_check_and_a_doc():
    with pytest.raises(TypeError):
        param(1, check=integer(), doc="")
    with pytest.raises(TypeError):
        param(1, check=None, doc="x")
