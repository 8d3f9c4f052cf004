"""ambhil.loop.units, the one parser of quantities with units: each kind and unit to SI, times in
controller periods (``1.5T``, ``T``), spans (``START:STOP:COUNT`` and lists), one-line errors that
name what was expected; and the parsers built on it (scene faults, ``study timing`` flags)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from ambhil.loop import units
from ambhil.loop.units import Time, UnitError


@pytest.mark.parametrize("text, si", [
    ("150us", 150e-6), ("150µs", 150e-6), ("0.2ms", 0.2e-3), ("200ms", 0.2), ("0.2s", 0.2), ("5ns", 5e-9),
    (" 20 us ", 20e-6), ("3e-5", 3e-5), (3e-5, 3e-5), (2, 2.0), (np.float64(0.5), 0.5), ("0", 0.0),
])
def test_times(text, si):
    assert units.time(text) == pytest.approx(si, rel=1e-15)
    assert units.quantity(text, "time") == units.time(text)


def test_time_arithmetic_is_the_plain_product():
    """number * factor, nothing else: the same float as the parsers it replaced."""
    assert units.time("150us") == 150.0 * 1e-6
    assert units.time("1.5T", 1e-4) == 1.5 * 1e-4
    assert units.speed("3000rpm") == 3000.0 * (2 * math.pi / 60)


@pytest.mark.parametrize("text, value", [("1.5T", 1.5), ("T", 1.0), ("0T", 0.0), (" 2 T", 2.0), ("3T", 3.0)])
def test_times_in_periods(text, value):
    spec = units.time_spec(text)
    assert spec == Time(value, True) and spec.in_periods
    assert units.time(text, 2e-4) == pytest.approx(value * 2e-4, rel=1e-15)
    assert str(spec) == f"{value:g}T"


def test_a_time_in_periods_needs_the_period():
    with pytest.raises(UnitError, match="in periods needs a sample rate"):
        units.time("1.5T")
    assert units.time_spec("20us").seconds(None) == 20 * 1e-6  # seconds need no period
    assert str(units.time_spec("20us")) == "2e-05s"


@pytest.mark.parametrize("text, hz", [
    ("10k", 1e4), ("10kHz", 1e4), ("10000", 1e4), ("1M", 1e6), ("1MHz", 1e6), ("250Hz", 250.0), ("250hz", 250.0),
    ("5khz", 5e3), ("5K", 5e3), ("1m", 1e6), (" 10 k ", 1e4), ("1e4", 1e4), (1000, 1000.0),
])
def test_rates(text, hz):
    assert units.rate(text) == pytest.approx(hz, rel=1e-15)


@pytest.mark.parametrize("bad", ["0", "-1k", 0.0, "0Hz"])
def test_a_rate_is_positive(bad):
    with pytest.raises(UnitError, match=r"--rate: a rate must be > 0"):
        units.rate(bad, "--rate")


@pytest.mark.parametrize("text, rad_s", [
    ("3000rpm", 3000 * 2 * math.pi / 60), ("50Hz", 50 * 2 * math.pi), ("50hz", 50 * 2 * math.pi),
    ("314rad/s", 314.0), ("314", 314.0), (314, 314.0), ("3000RPM", 3000 * 2 * math.pi / 60), ("0", 0.0),
])
def test_speeds(text, rad_s):
    assert units.speed(text) == pytest.approx(rad_s, rel=1e-15)


@pytest.mark.parametrize("text, amps", [("2.5A", 2.5), ("300mA", 0.3), ("2", 2.0), (0.5, 0.5)])
def test_currents(text, amps):
    assert units.current(text) == pytest.approx(amps, rel=1e-15)


@pytest.mark.parametrize("kind, bad", [
    ("time", "soon"), ("time", "20 parsecs"), ("time", "1.5X"), ("time", True), ("time", None), ("time", [1]),
    ("rate", "fast"), ("speed", "3000 rpms"), ("speed", False), ("current", "2.5V"), ("time", ""),
])
def test_errors_name_what_was_expected_on_one_line(kind, bad):
    with pytest.raises(UnitError) as e:
        units.quantity(bad, kind, "--flag")
    msg = str(e.value)
    assert msg.startswith(f"--flag: expected a {kind} such as {units.EXAMPLES[kind]}, got {bad!r}")
    assert "\n" not in msg
    assert isinstance(e.value, ValueError)  # callers that catch ValueError still do


def test_time_spec_errors_mention_periods():
    with pytest.raises(UnitError, match=r"^--delay: expected a time such as .* or 1.5T \(periods\), got 'xT'$"):
        units.time_spec("xT", "--delay")
    with pytest.raises(UnitError, match=r"^time: expected a time"):
        units.time("abc")


def test_spans():
    assert np.array_equal(units.span("0:1:5", float, "x"), np.linspace(0.0, 1.0, 5))
    assert np.array_equal(units.span("2k:50k:20", units.rate, "--rates", log=True), np.geomspace(2e3, 5e4, 20))
    assert np.array_equal(units.span("0:150us:16", units.time, "--delays"), np.linspace(0.0, 150e-6, 16))
    assert units.span("5k, 10k,20k", units.rate, "--rates").tolist() == [5e3, 1e4, 2e4]
    assert units.span("20k,5k", units.rate, "--rates").tolist() == [2e4, 5e3]  # as written, not sorted
    assert units.span("1,,2,", float, "x").tolist() == [1.0, 2.0]  # empty items skipped


@pytest.mark.parametrize("bad", ["1:2", "1:2:3:4", "1:2:0", "1:2:x", "a:2:3", "1,b"])
def test_span_errors(bad):
    with pytest.raises(UnitError, match=r"^--x: expected START:STOP:COUNT or a comma list, got "):
        units.span(bad, units.rate, "--x")


def test_span_errors_carry_the_item_problem():
    with pytest.raises(UnitError, match=r"got '0:50k:3' \(--rates: a rate must be > 0, got '0'\)"):
        units.span("0:50k:3", lambda t: units.rate(t, "--rates"), "--rates", log=True)


# ------------------------------------------------------------------ the parsers built on units
def test_study_timing_flags():
    from ambhil.bridge.cli.study_timing import parse_delays, parse_delays_us, parse_rates
    assert parse_rates("10k,5k").tolist() == [5e3, 1e4]  # a list is sorted
    assert np.array_equal(parse_rates("2k:50k:20"), np.geomspace(2e3, 5e4, 20))
    assert parse_rates("5khz,1m").tolist() == [5e3, 1e6]
    v, periods = parse_delays("0:3T:24")
    assert periods and np.array_equal(v, np.linspace(0.0, 3.0, 24))
    v, periods = parse_delays("0.5:3T:4")  # a bare START counts in STOP's periods
    assert periods and v.tolist() == np.linspace(0.5, 3.0, 4).tolist()
    v, periods = parse_delays(":T:3")
    assert periods and v.tolist() == [0.0, 0.5, 1.0]
    v, periods = parse_delays("0,20us,50us")
    assert not periods and v.tolist() == [0.0, 20 * 1e-6, 50 * 1e-6]
    assert parse_delays("0,1T")[1] and parse_delays("0,1T")[0].tolist() == [0.0, 1.0]
    assert np.array_equal(parse_delays_us("0:100:5"), np.linspace(0.0, 100.0, 5) * 1e-6)
    for bad in ("0,1T,20us", "0.5s:3T:4", "1T:150us:3", "0:3T"):
        with pytest.raises(ValueError, match=r"^--delays: expected START:STOP:COUNT with STOP in periods"):
            parse_delays(bad)
    for bad in ("0", "abc", "2k:50k"):
        with pytest.raises(ValueError, match=r"^--rates: expected START:STOP:COUNT \(e.g. 2k:50k:20\)"):
            parse_rates(bad)
    with pytest.raises(ValueError, match=r"^--delays-us: expected START:STOP:COUNT in microseconds"):
        parse_delays_us("10,20")


def test_timing_study_latency():
    from ambhil.loop import timing_study as ts
    assert ts.parse_latency("uniform:20us").width == 20 * 1e-6
    assert ts.parse_latency("normal:0.1ms", 0.01).width == pytest.approx(1e-4, rel=1e-15)
    with pytest.raises(ValueError, match=r"^--jitter: expected a time"):
        ts.parse_latency("uniform:soon")
    with pytest.raises(ValueError, match=r"^--jitter must be uniform:WIDTH"):
        ts.parse_latency("box:20us")


def test_scene_fault_quantities_take_units():
    from ambhil.loop.scene import load_scene, with_fault_flags
    from ambhil.loop.scene_table import SceneError
    sc = load_scene("scenes/paper_3amb.toml")
    f = with_fault_flags(sc, ["speed_trip:at=200ms,to=3000rpm,over=0.1s",
                              "sensor_bias:at=150us,axis=A.x,value=1e-6"]).faults.faults
    assert f[-2].start == 200 * 1e-3 and dict(f[-2].params) == {"to": 3000 * (2 * math.pi / 60), "over": 0.1}
    assert f[-1].start == 150 * 1e-6 and dict(f[-1].params)["value"] == 1e-6
    with pytest.raises(SceneError, match=r"key 'to': must be a speed such as 3000rpm, 50Hz or 314rad/s, got 'fast'"):
        with_fault_flags(sc, ["speed_trip:at=0.1s,to=fast"])
    with pytest.raises(SceneError, match=r"key 'value': must be a number, got '1um'"):
        with_fault_flags(sc, ["sensor_bias:at=0.1s,axis=A.x,value=1um"])
