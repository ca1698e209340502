"""The one URL-option parser (twin/io/options.py) and the openers that use it: typed fields, defaults, ranges;
unknown keys, bad booleans, bad numbers, NaN and out-of-range values are one-line errors naming the URL and the
key, the same for every scheme."""

from __future__ import annotations

import math

import pytest
from io_helpers import synthetic_frames

from twin.io.options import Option, parse_bool, parse_options
from twin.io.record import Recorder
from twin.io.source import open_source

SPEC = {"rate": Option("float", default=100.0, low=0.0, low_open=True, high=1e4), "n": Option("int", low=1),
        "on": Option("bool"), "mode": Option("str", choices=("a", "b")), "ids": Option("ints", low=0, high=9),
        "speed": Option("float", low=0.0, low_open=True, words={"max": None})}


def test_typed_values_and_defaults():
    got = parse_options("x://", {"n": "3", "on": "Yes", "mode": "b", "ids": "1,2,9", "speed": "max"}, SPEC)
    assert got == {"rate": 100.0, "n": 3, "on": True, "mode": "b", "ids": [1, 2, 9], "speed": None}
    assert parse_options("x://", {}, SPEC) == {"rate": 100.0}
    assert [parse_bool(v) for v in ("1", "true", "ON", "yes", "0", "False", "off", "no")] == [True] * 4 + [False] * 4


@pytest.mark.parametrize(("query", "message"), [
    ({"nope": "1"}, "'x://?q': unknown option 'nope'; known: ids, mode, n, on, rate, speed"),
    ({"on": "maybe"}, "'x://?q': option on='maybe': expected a boolean (1/0, true/false, yes/no, on/off)"),
    ({"rate": "fast"}, "'x://?q': option rate='fast': expected a number in (0, 10000]"),
    ({"rate": "nan"}, "'x://?q': option rate='nan': expected a number in (0, 10000]"),
    ({"rate": "inf"}, "'x://?q': option rate='inf': expected a number in (0, 10000]"),
    ({"rate": "0"}, "'x://?q': option rate='0': expected a number in (0, 10000]"),
    ({"rate": "1e5"}, "'x://?q': option rate='1e5': expected a number in (0, 10000]"),
    ({"n": "2.5"}, "'x://?q': option n='2.5': expected an integer in [1, inf)"),
    ({"mode": "c"}, "'x://?q': option mode='c': expected one of a, b"),
    ({"ids": "1,x"}, "'x://?q': option ids='1,x': expected comma-separated integers in [0, 9]"),
    ({"ids": "10"}, "'x://?q': option ids='10': expected comma-separated integers in [0, 9]"),
    ({"speed": "-1"}, "'x://?q': option speed='-1': expected a number in (0, inf) or max"),
])
def test_bad_values_are_one_line_errors_naming_the_url_and_the_key(query, message):
    with pytest.raises(ValueError) as err:
        parse_options("x://?q", query, SPEC)
    assert str(err.value) == message and "\n" not in message


#: a URL of every registered scheme that gets as far as its options (no device needed: options come first)
URLS = {"illumisense": "illumisense://127.0.0.1:9", "hyperion": "hyperion://127.0.0.1:9",
        "fispec": "fispec:///dev/null", "synthetic": "synthetic://", "sim": "sim://static"}
BOOLS = {"illumisense": "wait", "hyperion": "wait", "fispec": "wait", "synthetic": "truth", "sim": "realtime",
         "replay": "salvage"}
NUMBERS = {"illumisense": "resync_timeout", "hyperion": "stream_port", "fispec": "reply_timeout",
           "synthetic": "rate", "sim": "rate", "replay": "speed"}


@pytest.fixture(scope="module")
def urls(tmp_path_factory):
    path = tmp_path_factory.mktemp("options") / "r.h5"
    frames = synthetic_frames(5)
    with Recorder(path) as rec:
        rec.append(frames)
    return {**URLS, "replay": f"replay://{path}"}


@pytest.mark.parametrize("scheme", sorted(BOOLS))
def test_every_opener_refuses_the_same_mistakes_the_same_way(urls, scheme):
    url = urls[scheme]
    sep = "&" if "?" in url else "?"
    for query, what in (("bogus=1", "unknown option 'bogus'"),
                        (f"{BOOLS[scheme]}=maybe", f"option {BOOLS[scheme]}='maybe': expected a boolean"),
                        (f"{NUMBERS[scheme]}=nan", f"option {NUMBERS[scheme]}='nan': expected"),
                        (f"{NUMBERS[scheme]}=-5", f"option {NUMBERS[scheme]}='-5': expected")):
        with pytest.raises(ValueError) as err:
            open_source(url + sep + query).close()
        text = str(err.value)
        assert what in text and "\n" not in text, text
        assert url.split("?")[0].split("://")[0] in text  # names the URL


def test_a_boolean_means_the_same_for_every_opener(tmp_path):
    """`salvage=on` salvages (it silently did not), as `wait=on` waits."""
    path = tmp_path / "cut.h5"
    with Recorder(path, flush_frames=10) as rec:
        rec.append(synthetic_frames(200))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.8)])
    with pytest.raises(OSError, match="damaged"):
        open_source(f"replay://{path}")
    for word in ("on", "yes", "true", "1", "ON"):
        src = open_source(f"replay://{path}?salvage={word}&speed=max")
        n = sum(1 for _ in src)
        assert n > 0 and src.salvage
    src = open_source("synthetic://?truth=off&pace=max&frames=2")
    assert src.read_batch(2, 1.0).truth is None and not math.isnan(src.rate)
