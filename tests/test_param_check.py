"""Param.check: the one validation of a method parameter (strict for the API's JSON, lenient
for the CLI's text), and the router's strict check is it."""

from __future__ import annotations

import math

import pytest

from cfsr.methods.registry import Param, get_method, resolve_params

WINDOW = get_method("tfp").params["window"]
MODE = get_method("tfp").params["mode"]
ADAPTIVE = get_method("cfsr").params["adaptive"]


@pytest.mark.parametrize(
    ("param", "value", "want"),
    [(WINDOW, 32, 32), (WINDOW, 32.0, 32), (MODE, "centred", "centred"), (ADAPTIVE, False, False)],
)
def test_strict_takes_the_parameters_own_json_type(param: Param, value, want):
    got = param.check(value)
    assert got == want and type(got) is type(want)


@pytest.mark.parametrize(
    ("param", "value"),
    [(WINDOW, "32"), (WINDOW, True), (MODE, 1), (ADAPTIVE, 1), (ADAPTIVE, "true")],
)
def test_strict_refuses_another_type_naming_the_parameter(param: Param, value):
    with pytest.raises(ValueError, match=r"parameter p=.*expected"):
        param.check(value, name="p")


@pytest.mark.parametrize(
    ("param", "value", "want"),
    [(WINDOW, "32", 32), (ADAPTIVE, "yes", True), (MODE, "centred", "centred")],
)
def test_lenient_converts_text(param: Param, value, want):
    assert param.check(value, strict=False) == want


@pytest.mark.parametrize("value", [0, 10**9, math.nan, 32.5])
def test_both_refuse_what_is_out_of_range_or_not_whole(value):
    for strict in (True, False):
        with pytest.raises(ValueError, match="window"):
            WINDOW.check(value, strict, name="window")


def test_resolve_params_is_lenient_unless_asked():
    m = get_method("tfp")
    assert resolve_params(m, {"window": "32"})["window"] == 32
    with pytest.raises(ValueError, match="expected int"):
        resolve_params(m, {"window": "32"}, strict=True)
