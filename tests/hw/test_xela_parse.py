"""The xela_server frame parser: real frames, every dialect, hostile input."""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.core.errors import SensorError, SensorLayoutError
from edge.hw.xela import MAX_FRAME_CHARS, parse_frame, parse_layout_free
from edge.sim.xela_server import GARBAGE_FRAMES, encode_frame, welcome_frame

# A real frame, with its provenance and licence beside it.
FIXTURE = Path(__file__).resolve().parents[1] / "fixtures/xela/v1.8_uSPa46_two_sensors.json"


@pytest.fixture(scope="module")
def real_text() -> str:
    return FIXTURE.read_text()


def channel_pattern(pads: int = 2, taxels: int = 16) -> np.ndarray:
    """Value = pad*1000 + taxel*10 + axis: each channel says where it came from."""
    return np.array(
        [p * 1000 + t * 10 + a for p in range(pads) for t in range(taxels) for a in range(3)],
        dtype=np.uint16,
    )


def v17_frame(raw: np.ndarray, *, as_list: bool = False, seq: int = 7) -> dict:
    frame: dict = {"message": seq, "time": 1700000000.25, "sensors": 2}
    for i in range(2):
        words = raw[i * 48 : (i + 1) * 48].tolist()
        data = words if as_list else ",".join(f"{w:04X}" for w in words)
        frame[str(i + 1)] = {"data": data, "model": "XR1944", "taxels": 16, "calibrated": None}
    return frame


# -- the real frame ---------------------------------------------------------------------------


def test_real_frame_layout_free(real_text: str) -> None:
    frame = parse_layout_free(real_text)
    assert frame is not None
    assert frame.sensors == ("1", "2")
    assert frame.taxels == (24, 24)
    assert frame.models == ("uSPa46", "uSPa46")
    assert frame.seq == 19299
    assert frame.raw.dtype == np.uint16 and frame.raw.shape == (144,)
    assert frame.raw[:3].tolist() == [0x8125, 0x81B2, 0x92B8]
    assert frame.raw[72:75].tolist() == [0x809D, 0x81B6, 0x91C0]  # sensor 2 starts here
    print(frame.describe())


def test_real_frame_hex_and_integer_agree(real_text: str) -> None:
    obj = json.loads(real_text)
    with_integer = parse_layout_free(obj)
    for number in ("1", "2"):
        del obj[number]["integer"]
    from_hex = parse_layout_free(obj)
    assert with_integer is not None and from_hex is not None
    np.testing.assert_array_equal(with_integer.raw, from_hex.raw)


def test_real_frame_with_24_taxel_expectation(real_text: str) -> None:
    frame = parse_frame(real_text, 2, 24, expected_model="uSPa46")
    assert frame is not None and frame.raw.shape == (2 * 24 * 3,)
    assert frame.raw[0] == 0x8125


def test_real_frame_refused_for_xr1944_layout(real_text: str) -> None:
    with pytest.raises(SensorLayoutError) as err:
        parse_frame(real_text, 2, 16, expected_model="XR1944")
    message = str(err.value)
    print(message)
    for needed in ("XR1944", "16 taxels", "sensor 1", "uSPa46", "24 taxels"):
        assert needed in message
    assert isinstance(err.value, SensorError)


def test_wrong_number_of_sensors_refused(real_text: str) -> None:
    with pytest.raises(SensorLayoutError, match=r"configured 1 x .* 2 sensors") as err:
        parse_frame(real_text, 1, 24)
    print(err.value)
    obj = json.loads(real_text)
    del obj["2"]
    with pytest.raises(SensorLayoutError, match=r"configured 2 x .* 1 sensor:"):
        parse_frame(obj, 2, 24)


def _hex_only(text: str) -> dict:
    """The frame with `integer` removed, so the parser reads the hex `data`."""
    obj = json.loads(text)
    for number in ("1", "2"):
        del obj[number]["integer"]
    return obj


def _wrapped(data: str) -> str:
    """`data` as a wrapped, indented capture carries it: line breaks every 37 characters
    (inside words as often as not), a CRLF, tabs and spaces around commas."""
    parts = [data[i : i + 37] for i in range(0, len(data), 37)]
    text = "\n".join(parts[:3]) + "\r\n" + "\n".join(parts[3:])
    return text.replace(",", " ,\t", 5).replace(",", ",  ", 7)


def test_real_frame_with_raw_whitespace_inside_data(real_text: str) -> None:
    clean = _hex_only(real_text)
    obj = copy.deepcopy(clean)
    for number in ("1", "2"):
        obj[number]["data"] = _wrapped(obj[number]["data"])
    # json.dumps escapes the control characters; undo that so they are raw in the text, as
    # in a capture (only `data` holds any: the other strings are plain names).
    text = json.dumps(obj, indent=2).replace("\\n", "\n").replace("\\r", "\r")
    text = text.replace("\\t", "\t")
    assert "\r\n" in text and "\t" in text  # (indent=2 alone puts neither in)
    with pytest.raises(json.JSONDecodeError, match="control character"):
        json.loads(text)  # strict JSON refuses it: the parser must not
    frame = parse_frame(text, 2, 24, expected_model="uSPa46")
    reference = parse_frame(clean, 2, 24, expected_model="uSPa46")
    from_integer = parse_frame(real_text, 2, 24, expected_model="uSPa46")
    assert frame is not None and reference is not None and from_integer is not None
    np.testing.assert_array_equal(frame.raw, reference.raw)
    np.testing.assert_array_equal(frame.raw, from_integer.raw)
    assert frame.raw[:3].tolist() == [0x8125, 0x81B2, 0x92B8]


@pytest.mark.parametrize(
    ("data", "bad"),
    [
        ("0000,0\n0G0,0000", "0\n0G0"),  # a non-hex letter stays one, whitespace or not
        ("0000,00\x0100,0000", "00\x0100"),  # other control characters are not whitespace
        ("0000,10 000,0000", "10 000"),  # five digits once the space is gone
        ("0000, \n\t ,0000", " \n\t "),  # nothing but whitespace
        ("0000 0000 0000", "0000 0000 0000"),  # spaces do not separate words: commas do
    ],
    ids=["letter", "control", "five-digits", "blank", "no-commas"],
)
def test_garbage_with_whitespace_still_refused(data: str, bad: str) -> None:
    text = '{"message": 1, "time": 1.0, "1": {"data": "' + data + '"}}'
    with pytest.raises(SensorError, match="not a 16-bit hex word") as err:
        parse_frame(text, 1, 1)
    assert repr(bad) in str(err.value)  # the word as it came, whitespace shown


# -- dialects -----------------------------------------------------------------------------------


@pytest.mark.parametrize("as_list", [False, True], ids=["1.7-hex", "1.7.7-ints"])
def test_v17_xr1944_frames(as_list: bool) -> None:
    raw = channel_pattern()
    frame = parse_frame(json.dumps(v17_frame(raw, as_list=as_list)), 2, 16)
    assert frame is not None
    np.testing.assert_array_equal(frame.raw, raw)
    # Channel convention: pad*48 + taxel*3 + axis.
    assert frame.raw[1 * 48 + 5 * 3 + 2] == 1000 + 50 + 2
    assert frame.seq == 7 and frame.time == 1700000000.25


def test_sensors_ordered_by_number_not_by_key_order() -> None:
    raw = channel_pattern()
    obj = v17_frame(raw)
    reordered = {"2": obj["2"], "message": obj["message"], "1": obj["1"], "time": obj["time"]}
    frame = parse_frame(json.dumps(reordered), 2, 16)
    assert frame is not None and frame.sensors == ("1", "2")
    np.testing.assert_array_equal(frame.raw, raw)
    # "10" sorts after "9" numerically, not between "1" and "2".
    many = {"message": 1, "time": 1.0}
    for n in (10, 9, 1):
        many[str(n)] = {"data": [n] * 3}
    parsed = parse_layout_free(many)
    assert parsed is not None and parsed.sensors == ("1", "9", "10")
    assert parsed.raw.tolist() == [1, 1, 1, 9, 9, 9, 10, 10, 10]


@pytest.mark.parametrize("calibrated", ["absent", None, "list"])
def test_calibrated_tolerated(calibrated: object) -> None:
    obj = v17_frame(channel_pattern())
    for n in ("1", "2"):
        if calibrated == "absent":
            del obj[n]["calibrated"]
        elif calibrated == "list":
            obj[n]["calibrated"] = [0.0] * 48
    assert parse_frame(obj, 2, 16) is not None


@pytest.mark.parametrize("dialect", ["1.7", "1.7.7", "1.8"])
def test_emulator_encoding_round_trips(dialect: str) -> None:
    raw = np.random.default_rng(1).integers(0, 65536, 96, dtype=np.uint16)
    text = encode_frame(42, 123.5, raw, dialect=dialect)  # type: ignore[arg-type]
    frame = parse_frame(text, 2, 16, expected_model="XR1944")
    assert frame is not None and frame.seq == 42 and frame.models == ("XR1944", "XR1944")
    np.testing.assert_array_equal(frame.raw, raw)


def test_emulator_writes_data_words_as_the_server_does() -> None:
    # xela_server 1.7/1.8: each word four upper-case hex digits, comma-separated.
    raw = np.zeros(96, dtype=np.uint16)
    raw[:5] = (0, 0xA, 0xFF, 0x1000, 0xFFFF)
    frame = json.loads(encode_frame(1, 1.0, raw, dialect="1.8"))
    assert frame["1"]["data"] == ",".join(["0000", "000A", "00FF", "1000", "FFFF"]
                                          + ["0000"] * 43)
    assert frame["2"]["data"] == ",".join(["0000"] * 48)
    assert frame["1"]["integer"][:5] == [0, 10, 255, 4096, 65535]


def test_welcome_is_skipped() -> None:
    assert parse_frame(welcome_frame(2), 2, 16) is None
    assert parse_frame('{"message": "Welcome"}', 2, 16) is None


def test_missing_top_level_time_falls_back() -> None:
    obj = {"message": 3, "1": {"data": [1, 2, 3], "time": 5.5}}
    frame = parse_layout_free(obj)
    assert frame is not None and frame.time == 5.5
    del obj["1"]["time"]
    frame = parse_layout_free(obj)
    assert frame is not None and np.isnan(frame.time)  # unknown; the seq still counts


def test_lowercase_and_short_hex_words() -> None:
    obj = {"message": 1, "time": 1.0, "1": {"data": "ff, 1,abcd"}}
    frame = parse_layout_free(obj)
    assert frame is not None and frame.raw.tolist() == [0xFF, 1, 0xABCD]


# -- refusals ----------------------------------------------------------------------------------


def _frame_with(**sensor1: object) -> dict:
    obj = v17_frame(channel_pattern())
    obj["1"] = {**obj["1"], **sensor1}
    return obj


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        ("not json", "not JSON"),
        (b"\xff\xfe", "not JSON"),
        ("[1, 2]", "JSON object"),
        ('"text"', "JSON object"),
        ("{}", "'message'"),
        ('{"message": 1}', "no sensor keys"),
        ('{"message": 1, "time": "now", "1": {"data": "0000,0000,0000"}}', "'time'"),
        ('{"message": true, "time": 1}', "'message'"),
        ('{"message": 1, "time": NaN, "1": {"data": "0000,0000,0000"}}', "'time'"),
        ('{"message": 1, "time": 1.0}', "no sensor keys"),
        ('{"message": 1, "time": 1.0, "1": 5}', "not an object"),
        ('{"message": 1, "time": 1.0, "1": {}}', "no 'data'"),
        ('{"message": 1, "time": 1.0, "1": {"data": 5}}', "hex string or a list"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,0000"}}', "x, y, z"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,00G0,0000"}}', "not a 16-bit hex"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,10000,0000"}}', "not a 16-bit hex"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,0x10,0000"}}', "not a 16-bit hex"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,-001,0000"}}', "not a 16-bit hex"),
        ('{"message": 1, "time": 1.0, "1": {"data": "0000,,0000"}}', "not a 16-bit hex"),
        ('{"message": 1, "time": 1.0, "1": {"data": [0, 70000, 0]}}', "0..65535"),
        ('{"message": 1, "time": 1.0, "1": {"data": [0, -1, 0]}}', "0..65535"),
        ('{"message": 1, "time": 1.0, "1": {"data": [0, 1.5, 0]}}', "not an int"),
        ('{"message": 1, "time": 1.0, "1": {"data": [0, true, 0]}}', "not an int"),
        ('{"message": 1, "time": 1.0, "1": {"integer": [0, "1", 0]}}', "not an int"),
        ('{"message": 1, "time": 1.0, "1": {"data": [0, 0, 0], "taxels": 4}}', "says 4 taxels"),
        ("[" * 100_000 + "]" * 100_000, "not JSON|exceeds"),
        ("x" * (MAX_FRAME_CHARS + 1), "exceeds"),
    ],
)
def test_malformed_frames_refused_with_reason(bad: str | bytes, match: str) -> None:
    with pytest.raises(SensorError, match=match) as err:
        parse_frame(bad, 1, 1)
    assert not isinstance(err.value, SensorLayoutError)


@pytest.mark.parametrize("garbage", GARBAGE_FRAMES)
def test_emulator_garbage_is_refused(garbage: str) -> None:
    with pytest.raises(SensorError):
        parse_frame(garbage, 2, 16)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=5), children, max_size=5)
    ),
    max_leaves=30,
)


def _only_sensor_errors(msg: object) -> None:
    try:
        frame = parse_frame(msg, 2, 16)  # type: ignore[arg-type]
    except SensorError:
        return
    assert frame is None or frame.raw.dtype == np.uint16


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200) | st.binary(max_size=200))
def test_random_text_only_raises_sensor_error(text: str | bytes) -> None:
    _only_sensor_errors(text)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(json_values)
def test_random_json_only_raises_sensor_error(value: object) -> None:
    _only_sensor_errors(json.dumps(value))
    if isinstance(value, dict):
        _only_sensor_errors(value)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(["message", "time", "1", "2", "data", "integer", "taxels", "model"]),
    json_values,
)
def test_mutated_frames_only_raise_sensor_error(key: str, value: object) -> None:
    """Replace one field, top level or inside sensor 1, of a valid frame with random JSON."""
    obj = v17_frame(channel_pattern())
    top, inner = copy.deepcopy(obj), copy.deepcopy(obj)
    top[key] = value
    inner["1"][key] = value
    _only_sensor_errors(json.dumps(top))
    _only_sensor_errors(json.dumps(inner))


# -- cost -------------------------------------------------------------------------------------


def test_parse_cost_per_frame(real_text: str) -> None:
    """Runs at 125 Hz on a small computer: print the cost of one parse, bound it loosely."""
    raw = channel_pattern()
    texts = {
        "1.7 XR1944 hex": json.dumps(v17_frame(raw)),
        "1.8 XR1944": encode_frame(1, 1.0, raw, dialect="1.8"),
        "1.8 real uSPa46 (calibrated)": real_text,
    }
    for name, text in texts.items():
        taxels = 24 if "uSPa46" in name else 16
        n = 2000
        t0 = time.perf_counter()
        for _ in range(n):
            parse_frame(text, 2, taxels)
        per_frame_us = (time.perf_counter() - t0) / n * 1e6
        print(f"parse {name}: {per_frame_us:.1f} us/frame ({len(text)} chars)")
        assert per_frame_us < 5000  # generous: ~100 us on a laptop core


def test_a_model_not_what_the_configuration_says_is_refused_naming_both() -> None:
    obj = v17_frame(channel_pattern())
    with pytest.raises(SensorLayoutError) as err:
        parse_frame(obj, 2, 16, expected_model="uSPa44")
    print(err.value)
    for needed in ("configured 2 x uSPa44", "model XR1944", "sensor.model"):
        assert needed in str(err.value)
    # The same model in other letters, or a server that names none, is taken at its layout.
    assert parse_frame(obj, 2, 16, expected_model="xr1944") is not None
    for n in ("1", "2"):
        del obj[n]["model"]
    assert parse_frame(obj, 2, 16, expected_model="uSPa44") is not None


# -- the whole-frame decode against the checks one sensor at a time ----------------------------


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(1, 4), min_size=1, max_size=3),  # taxels of each sensor
    st.sampled_from(["hex", "list", "integer", "mixed"]),
    st.integers(0, 2**31),
)
def test_frame_words_match_per_sensor_checks(taxels: list[int], style: str, seed: int) -> None:
    """The frame's words decoded at once are the words each sensor's own check reads."""
    from edge.hw.xela import _frame_words, _sensor_words

    rng = np.random.default_rng(seed)
    sensors = []
    for i, n in enumerate(taxels):
        words = rng.integers(0, 65536, 3 * n).tolist()
        as_hex = style == "hex" or (style == "mixed" and i % 2 == 0)
        sensor: dict = {"data": ",".join(f"{w:04X}" for w in words) if as_hex else words}
        if style == "integer":
            sensor = {"data": "not read", "integer": words}
        sensors.append(sensor)
    each = [_sensor_words(s, 1, str(i + 1)) for i, s in enumerate(sensors)]
    decoded = _frame_words(sensors)
    if style == "mixed" and len(taxels) > 1:
        assert decoded is None  # (the checks one sensor at a time read it)
        return
    assert decoded is not None
    np.testing.assert_array_equal(decoded[0], np.concatenate(each))
    assert decoded[0].dtype == np.uint16
    assert decoded[1] == [len(a) for a in each]


@pytest.mark.parametrize("text", [
    # What msgspec refuses and the standard decoder reads: parsed as before.
    '{"message": 1, "time": 1.0, "1": {"data": "0001,00\n02,0003"}}',  # a raw newline
    '{"message": 1, "time": 1.0, "1": {"data": [1, 2, 3], "note": "\\ud800"}}',  # lone surrogate
    '{"message": 1, "time": 1.0, "1": {"data": [1, 2, 3], "gain": 1e999}}',  # a float over range
    '{"message": 1, "time": 1.0, "1": {"data": [1, 2, 3], "id": 123456789012345678901234567890}}',
])
def test_lenient_frames_still_parse(text: str) -> None:
    for msg in (text, text.encode("utf-16"), text.encode("utf-8", "surrogatepass")):
        frame = parse_layout_free(msg)
        assert frame is not None and frame.raw.tolist() == [1, 2, 3]


@pytest.mark.parametrize(("text", "match"), [
    # Integers beyond 64 bits: the faults are said with the frame's numbers.
    ('{"message": 1, "time": 1.0, "1": {"data": [0, 123456789012345678901234567890, 0]}}',
     r"0\.\.65535, got 0\.\.123456789012345678901234567890$"),
    ('{"message": 123456789012345678901234567890, "time": 1.0, "1": {"data": [0, 0, 0]}}',
     "got 123456789012345678901234567890$"),
])
def test_huge_integers_named_as_sent(text: str, match: str) -> None:
    with pytest.raises(SensorError, match=match):
        parse_frame(text, 1, 1)
