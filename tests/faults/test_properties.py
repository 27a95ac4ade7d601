"""Bad input, as properties (hypothesis).

- The HTTP API of a running daemon, fed hostile JSON and multipart bodies and random
  paths under /v1/episodes/: always a 4xx with a JSON error, never a crash (the next
  /healthz answers), never an arm motion, never an episode.
- The config loader: any nested dict gives a Config or a ConfigError naming a field.
- The recordings loader: random bytes and mutated valid files give only RecordingError.
- The XELA frame parser (beyond tests/hw/test_xela_parse.py): huge numbers, non-JSON
  values in mappings, and hex data that must parse to exactly the words it encodes.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import datetime as dt
import http.client
import io
import json
import math
import threading
import typing
import zipfile
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from edge.core import recording
from edge.core.config import Config, config_from_dict
from edge.core.errors import ConfigError, RecordingError, SensorError
from edge.hw.xela import parse_frame
from edge.sim.robot import SimRobot
from tests.support.daemon import QUICK_OBJECT, Daemon, base_config, fast_config

API_EXAMPLES = settings(max_examples=60, deadline=None,
                        suppress_health_check=[HealthCheck.function_scoped_fixture,
                                               HealthCheck.too_slow])
FIELDS = ("candidates", "wait", "image", "timeout_s")
MOTORS = (11, 12, 13, 14, 15)


# --- a daemon in its own thread, shared by the API properties ----------------------------

class ThreadedDaemon:
    """SimRobot + the daemon on an event loop in a thread; tests talk HTTP to it."""

    def __init__(self, state: Path) -> None:
        self.state = state
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="daemon-loop",
                                       daemon=True)

    def run(self, coro, timeout_s: float = 30.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    def __enter__(self) -> ThreadedDaemon:
        self.thread.start()

        async def start():
            self.robot = await SimRobot(QUICK_OBJECT, seed=11, cfg=base_config()).start()
            self.daemon = await Daemon(self.robot, fast_config(), self.state).__aenter__()

        self.run(start())
        self.port = self.daemon.api.port
        self.positions = self.motor_positions()
        return self

    def __exit__(self, *exc) -> None:
        async def stop():
            await self.daemon.__aexit__(None, None, None)
            await self.robot.stop()

        try:
            self.run(stop())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10)
            self.loop.close()

    def motor_positions(self) -> tuple[float, ...]:
        return tuple(self.robot.dxl.true_position(i) for i in MOTORS)

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: dict[str, str] | None = None) -> tuple[int, str, bytes]:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        try:
            conn.request(method, path, body=body, headers=headers or {})
            resp = conn.getresponse()
            return resp.status, resp.getheader("Content-Type", ""), resp.read()
        finally:
            conn.close()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    with ThreadedDaemon(tmp_path_factory.mktemp("api-properties")) as d:
        yield d


def assert_refused_clearly(d: ThreadedDaemon, status: int, ctype: str, body: bytes) -> dict:
    """A 4xx with a JSON error; the daemon alive, the arm still, no episode, no press."""
    assert 400 <= status < 500, (status, body[:300])
    assert ctype.startswith("application/json"), (status, ctype, body[:300])
    answer = json.loads(body)
    assert isinstance(answer.get("error"), str) and answer["error"], answer
    health_status, _, health = d.request("GET", "/healthz")
    assert health_status in (200, 503) and "sensor_fresh" in json.loads(health), health
    assert d.motor_positions() == pytest.approx(d.positions, abs=1.0)
    assert d.daemon.store.ids() == [] and d.daemon.runtime.press.state == "idle"
    return answer


# --- hostile recognize bodies ---------------------------------------------------------------

json_leaf = (st.none() | st.booleans() | st.integers() | st.integers(-10**30, 10**30)
             | st.floats() | st.text(max_size=30))
json_values = st.recursive(
    json_leaf,
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=12), kids,
                                                               max_size=4),
    max_leaves=20)

bad_candidates = st.one_of(
    json_values.filter(lambda v: not isinstance(v, list)),  # not a list
    st.just([]),
    st.lists(json_values.filter(lambda v: not isinstance(v, str)), min_size=1, max_size=4)
    .map(lambda xs: ["ok", *xs]),  # a non-string among strings
    st.text(min_size=1, max_size=10).map(lambda s: ["a", s, s]),  # a duplicate
    st.sampled_from(["", " ", "\t\n"]).map(lambda s: [s]),  # blank
    st.text(min_size=81, max_size=120).filter(lambda s: s.strip() and len(s.strip()) > 80)
    .map(lambda s: [s]),  # too long
    st.sampled_from(["a\x00b", "tab\there", "new\nline", "\x1b[31m"]).map(lambda s: [s]),
    st.integers(33, 60).map(lambda n: [f"label{i}" for i in range(n)]),  # too many
)
bad_wait = json_values.filter(lambda v: not isinstance(v, bool))
bad_timeout = st.one_of(
    st.floats(allow_nan=True).filter(lambda v: not (0 < v <= 600)),
    st.integers().filter(lambda v: not (0 < v <= 600)),
    st.booleans(), st.text(max_size=5), st.none().map(lambda _: [1]))
bad_image = st.one_of(
    json_values.filter(lambda v: not isinstance(v, str)),
    st.text(max_size=40).filter(lambda s: s.strip() != ""),  # not base64 or not an image
    st.binary(max_size=64).map(lambda b: base64.b64encode(b).decode()),  # no image magic
    st.sampled_from([b"\xff\xd8\xff", b"\x89PNG\r\n\x1a\n"]).flatmap(  # magic, no image
        lambda magic: st.binary(max_size=64).map(lambda b: base64.b64encode(magic + b)
                                                 .decode())),
    st.just(""),
)


@st.composite
def invalid_json_bodies(draw):
    """A JSON body that must be refused: invalid by construction, one defect at least."""
    kind = draw(st.sampled_from(["not-object", "unknown-field", "bad-field", "no-candidates"]))
    if kind == "not-object":
        return draw(json_values.filter(lambda v: not isinstance(v, dict)))
    body = {"candidates": ["canele", "melon_pan"]}
    if draw(st.booleans()):
        body["wait"] = draw(st.booleans())
    if kind == "unknown-field":
        key = draw(st.text(max_size=20).filter(lambda k: k not in FIELDS))
        body[key] = draw(json_values)
    elif kind == "no-candidates":
        del body["candidates"]
        body.update(draw(st.dictionaries(st.sampled_from(["wait", "timeout_s"]),
                                         json_values, max_size=2)))
    else:
        field = draw(st.sampled_from(FIELDS))
        body[field] = draw({"candidates": bad_candidates, "wait": bad_wait,
                            "timeout_s": bad_timeout, "image": bad_image}[field])
    return body


@API_EXAMPLES
@given(body=invalid_json_bodies())
@example(body={"candidates": ["canele"], "image": base64.b64encode(b"\x89PNG\r\n\x1a\n")
               .decode()})  # the magic alone: once accepted, and the arm pressed
def test_api_hostile_json_bodies_get_a_clear_4xx(daemon, body):
    status, ctype, raw = daemon.request("POST", "/v1/recognize", json.dumps(body).encode(),
                                        {"Content-Type": "application/json"})
    assert_refused_clearly(daemon, status, ctype, raw)


raw_bodies = st.one_of(
    st.binary(max_size=200),
    st.text(max_size=200).map(str.encode),
    st.integers(1, 200_000).map(lambda n: b"[" * n + b"]" * n),  # absurd nesting
    st.integers(1, 200_000).map(lambda n: b'{"candidates": ' + b"[" * n),  # truncated
    # (never valid in any charset: latin-1 reads any byte)
    st.sampled_from([b"\xff\xfe{}", b'{"candidates": [], "\xff": 1}', b"null", b"{}"]),
)


@API_EXAMPLES
@given(body=raw_bodies, ctype=st.sampled_from([
    "application/json", "application/json; charset=latin-1", "application/json; charset=bogus",
    "text/plain", "application/x-www-form-urlencoded", "", "image/jpeg"]))
@example(body=b"[" * 100_000 + b"]" * 100_000, ctype="application/json")
def test_api_raw_bodies_get_a_clear_4xx(daemon, body, ctype):
    headers = {"Content-Type": ctype} if ctype else {}
    status, rtype, raw = daemon.request("POST", "/v1/recognize", body, headers)
    assert_refused_clearly(daemon, status, rtype, raw)


part_names = st.one_of(st.sampled_from(FIELDS), st.text(min_size=1, max_size=10).filter(
    lambda s: '"' not in s and "\r" not in s and "\n" not in s))
part_content = st.one_of(st.binary(max_size=100), json_values.map(lambda v: json.dumps(v)
                                                                   .encode()))


@st.composite
def hostile_multipart(draw):
    boundary = "vtzeroboundary"
    parts = draw(st.lists(st.tuples(part_names, part_content,
                                    st.sampled_from(["", "; charset=utf-8",
                                                     "; charset=bogus-42", "; charset=utf-16"])),
                          max_size=4))
    poison = draw(st.sampled_from(["unknown", "no-candidates", "bad-candidates", "broken"]))
    if poison == "unknown":
        parts.insert(draw(st.integers(0, len(parts))), ("colour", b"red", ""))
    elif poison == "no-candidates":
        parts = [p for p in parts if p[0] != "candidates"]
    elif poison == "broken":  # broken, and no candidates either: refused twice over
        parts = [p for p in parts if p[0] != "candidates"]
    elif poison == "bad-candidates":
        parts = [p for p in parts if p[0] != "candidates"]
        bad = json.dumps(draw(bad_candidates), allow_nan=True).encode()
        parts.append(("candidates", bad, ""))
    chunks = []
    for name, content, charset in parts:
        ctype = "image/jpeg" if name == "image" else f"text/plain{charset}"
        chunks.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n'
                      f"Content-Type: {ctype}\r\n\r\n".encode() + content + b"\r\n")
    body = b"".join(chunks)
    if poison == "broken":  # no closing boundary, or a cut in the middle, or no boundary
        body = draw(st.sampled_from([body, body[: len(body) // 2], b"--x\r\n" + body]))
        header = draw(st.sampled_from([f"multipart/form-data; boundary={boundary}",
                                       "multipart/form-data", "multipart/form-data; boundary="]))
        if not body:
            body = b"--"
    else:
        body += f"--{boundary}--\r\n".encode()
        header = f"multipart/form-data; boundary={boundary}"
    return body, header


@API_EXAMPLES
@given(multipart=hostile_multipart())
def test_api_hostile_multipart_bodies_get_a_clear_4xx(daemon, multipart):
    body, header = multipart
    status, ctype, raw = daemon.request("POST", "/v1/recognize", body,
                                        {"Content-Type": header})
    assert_refused_clearly(daemon, status, ctype, raw)


def test_api_multipart_part_over_the_body_limit_is_refused_while_read(daemon):
    limit = daemon.daemon.cfg.api.max_body_bytes
    body = (b'--b\r\nContent-Disposition: form-data; name="image"\r\n'
            b"Content-Type: image/jpeg\r\n\r\n\xff\xd8\xff" + bytes(limit + 1000)
            + b'\r\n--b\r\nContent-Disposition: form-data; name="candidates"\r\n\r\n'
            b'["canele"]\r\n--b--\r\n')
    status, ctype, raw = daemon.request("POST", "/v1/recognize", body,
                                        {"Content-Type": "multipart/form-data; boundary=b"})
    answer = assert_refused_clearly(daemon, status, ctype, raw)
    assert status == 413 and "too large" in answer["error"]


path_text = st.text(max_size=40)


@API_EXAMPLES
@given(segment=path_text, raw=st.booleans(), method=st.sampled_from(["GET", "POST",
                                                                      "DELETE"]))
@example(segment="..%2F..%2Fetc%2Fpasswd", raw=True, method="GET")
@example(segment="a/b", raw=True, method="GET")
@example(segment="", raw=True, method="GET")
def test_api_random_episode_paths_get_a_clear_4xx(daemon, segment, raw, method):
    if raw:
        # As typed, minus what HTTP cannot carry in a request line.
        path = "".join(ch if 0x21 <= ord(ch) < 0x7f and ch not in "?#" else quote(ch)
                       for ch in segment)
    else:
        path = quote(segment, safe="")
    status, ctype, body = daemon.request(method, "/v1/episodes/" + path)
    answer = assert_refused_clearly(daemon, status, ctype, body)
    assert status in (400, 404, 405), (status, answer)


# --- the config loader -----------------------------------------------------------------------

SECTIONS = {f.name: f.type for f in dataclasses.fields(Config)}
HINTS = typing.get_type_hints(Config)
SCHEMA_PATHS = {"top level", "poses"} | {
    f"{section}.{field.name}"
    for section, tp in HINTS.items() if dataclasses.is_dataclass(tp)
    for field in dataclasses.fields(tp)}

toml_leaf = st.one_of(
    st.booleans(), st.integers(), st.integers(-(10**400), 10**400),
    st.floats(), st.floats(allow_nan=False, allow_infinity=False, min_value=-1e3,
                           max_value=1e3),
    st.text(max_size=20), st.sampled_from(["http://[::1", "http://x:99999", "ws://h",
                                            "http://u:p@h/v1", "http://h/v1?q=1", "", "{out}"]),
    st.datetimes(), st.dates(), st.times())
toml_values = st.recursive(
    toml_leaf,
    lambda kids: st.lists(kids, max_size=5) | st.dictionaries(st.text(max_size=8), kids,
                                                               max_size=3),
    max_leaves=12)


def section_fields(section: str) -> list[str]:
    tp = HINTS[section]
    return [f.name for f in dataclasses.fields(tp)] if dataclasses.is_dataclass(tp) else []


@st.composite
def config_dicts(draw):
    raw: dict = {}
    for section in draw(st.lists(st.sampled_from(sorted(SECTIONS)), max_size=4, unique=True)):
        fields = section_fields(section)
        if not fields:  # mode, poses
            raw[section] = draw(toml_values)
            continue
        value = {name: draw(toml_values) for name in draw(
            st.lists(st.sampled_from(fields), max_size=4, unique=True))}
        if draw(st.booleans()):
            value = draw(toml_values) if draw(st.booleans()) else value
        raw[section] = value
    if draw(st.booleans()):
        raw[draw(st.text(max_size=10))] = draw(toml_values)
    return raw


def named_paths(raw: dict, prefix: str = "") -> set[str]:
    out = set()
    for key, value in raw.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        out.add(path)
        if isinstance(value, dict):
            out |= named_paths(value, path)
    return out


@settings(max_examples=150, deadline=None)
@given(raw=config_dicts())
@example(raw={"press": {"x_th": 10**400}})
@example(raw={"vlm": {"base_url": "http://[::1", "model": "m"}})
@example(raw={"vlm": {"base_url": "http://h:99999/v1", "model": "m"}})
def test_config_loader_only_raises_config_error_naming_a_field(raw):
    try:
        cfg = config_from_dict(raw, source="fuzz.toml")
    except ConfigError as exc:
        message = str(exc)
        assert message.startswith("fuzz.toml: ")
        names = SCHEMA_PATHS | named_paths(raw)
        assert any(name in message for name in names), message
    else:
        assert isinstance(cfg, Config)


# --- the recordings loader -------------------------------------------------------------------

def valid_recording() -> recording.Recording:
    n, c = 40, 96
    t = np.arange(n) * 0.008 + 100.0
    rng = np.random.default_rng(0)
    return recording.Recording(
        frames=rng.integers(30000, 40000, (n, c)).astype(np.uint16), recv_time=t,
        sensor_time=t + 5.0, seq=np.arange(n, dtype=np.int64), tare=np.full(c, 33000.0),
        t_stop=float(t[20]), label="canele", threshold=0.004, sensor_model="XR1944",
        gripper_time=t[::4], gripper_width_m=np.linspace(0.008, 0.001, 10),
        gripper_current_ma=np.linspace(0, 300, 10))


VALID = recording.to_bytes(valid_recording())


def only_recording_errors(data: bytes) -> None:
    try:
        rec = recording.from_bytes(data, "fuzz.press.npz")
    except RecordingError as exc:
        assert str(exc).startswith("fuzz.press.npz: "), exc
    else:
        assert rec.frames.dtype == np.uint16 and rec.frames.ndim == 2


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=300), magic=st.sampled_from(
    [b"", b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY\x01\x00", b"\x93NUMPY\x02\x00v\x00",
     b"\x80\x04"]))
@example(data=np.lib.format.magic(1, 0)[6:] + b"v\x00{'descr': '<u2', 'fortran_order': False,"
         b" 'shape': (2,), }" + b" " * 48 + b"\n\x00\x00\x00\x00", magic=b"\x93NUMPY")
def test_recordings_loader_random_bytes(data, magic):
    only_recording_errors(magic + data)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(edits=st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255),
                                st.sampled_from(["flip", "cut", "insert", "delete"])),
                      min_size=1, max_size=4))
def test_recordings_loader_mutated_bytes(edits):
    data = bytearray(VALID)
    for pos, value, how in edits:
        pos %= max(len(data), 1)
        if how == "flip":
            data[pos] ^= value or 1
        elif how == "cut":
            del data[pos:]
        elif how == "insert":
            data[pos:pos] = bytes([value])
        elif data:
            del data[pos]
        if not data:
            break
    only_recording_errors(bytes(data))


MEMBERS = ("meta", "frames", "recv_time", "sensor_time", "seq", "tare", "gripper_time",
           "gripper_width_m", "gripper_current_ma")
any_arrays = st.one_of(
    st.builds(lambda dtype, shape: np.zeros(shape, dtype=dtype),
              st.sampled_from(["u2", "f8", "i8", "f4", "u1", "U5", "?", "c8"]),
              st.lists(st.integers(0, 5), max_size=3).map(tuple)),
    st.just(np.full(40, np.nan)), st.just(np.full(40, np.inf)),
    st.just(np.arange(40, dtype=np.float64)[::-1]),
    st.just(np.zeros((40, 0), dtype=np.uint16)), st.just(np.zeros((40, 95), dtype=np.uint16)),
    st.just(np.zeros((1, 96), dtype=np.uint16)))
meta_texts = st.one_of(
    json_values.map(json.dumps),
    st.text(max_size=50),
    st.integers(1, 300_000).map(lambda n: "[" * n + "]" * n),
    st.dictionaries(st.sampled_from(["schema_version", "t_stop", "label", "threshold",
                                     "sensor_model", "source", "software_version", "extra"]),
                    json_values).map(lambda d: json.dumps({"schema_version": 1, **d})))


@settings(max_examples=150, deadline=None)
@given(changes=st.dictionaries(st.sampled_from(MEMBERS),
                               st.one_of(any_arrays, meta_texts.map(np.array), st.none()),
                               min_size=1, max_size=3),
       extra=st.booleans())
@example(changes={"meta": np.array("[" * 200_000 + "]" * 200_000)}, extra=False)
def test_recordings_loader_structurally_mutated_files(changes, extra):
    with np.load(io.BytesIO(VALID), allow_pickle=False) as npz:
        members = {name: npz[name] for name in npz.files}
    for name, value in changes.items():
        if value is None:
            members.pop(name, None)
        else:
            members[name] = value
    if extra:
        members["unexpected"] = np.zeros(3)
    buf = io.BytesIO()
    np.savez(buf, **members)
    only_recording_errors(buf.getvalue())


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def huge_header_npz() -> bytes:
    """Every member's header claims 175 TiB; the data is 100 bytes."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<u2", "fortran_order": False,
                                                "shape": (10**12, 96)})
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for member in MEMBERS:
            zf.writestr(f"{member}.npy", head.getvalue() + bytes(100))
    return buf.getvalue()


@pytest.mark.parametrize("data", [npy_bytes(np.zeros(3)), npy_bytes(np.array("x")),
                                  huge_header_npz()], ids=["npy", "npy-str", "huge-header"])
def test_recordings_loader_refuses_foreign_and_hostile_files(data):
    only_recording_errors(data)


def test_recordings_loader_refuses_a_zip_of_other_things():
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("meta.npy", b"not an array")
        zf.writestr("frames.npy", b"\x93NUMPY garbage")
    only_recording_errors(buf.getvalue())


# --- the XELA frame parser (what tests/hw/test_xela_parse.py does not already cover) -------

def frame_obj(words: list[int], data: object = None, **top) -> dict:
    half = len(words) // 2
    obj = {"message": 1, "time": 1.5, "sensors": 2}
    for i, chunk in enumerate((words[:half], words[half:])):
        obj[str(i + 1)] = {"data": ",".join(f"{w:04X}" for w in chunk) if data is None
                           else data, "model": "XR1944", "taxels": 16}
    obj.update(top)
    return obj


huge_numbers = st.one_of(st.integers(-(10**400), 10**400), st.floats(),
                         st.integers(2**63 - 2, 2**64 + 2))


@settings(max_examples=200, deadline=None)
@given(key=st.sampled_from(["message", "time", "sensors"]), value=huge_numbers)
@example(key="time", value=10**400)
@example(key="message", value=10**400)
def test_xela_huge_numbers_only_sensor_errors(key, value):
    obj = frame_obj([0] * 96, **{key: value})
    for msg in (obj, json.dumps(obj)):
        try:
            frame = parse_frame(msg, 2, 16)
        except SensorError:
            continue
        assert frame is not None and frame.raw.shape == (96,)
        np.array([frame.seq], dtype=np.int64)  # what the ring buffer stores
        assert math.isfinite(frame.time)


@settings(max_examples=200, deadline=None)
@given(value=st.one_of(
    st.lists(st.one_of(st.integers(-(2**70), 2**70), st.floats(), st.booleans(), st.none(),
                       st.binary(max_size=3)), min_size=48, max_size=48),
    st.tuples(st.integers(0, 65535)), st.binary(max_size=20), st.frozensets(st.integers()),
    st.builds(object), st.just(math.nan), st.just(dt.datetime(2020, 1, 1))))
def test_xela_mapping_with_python_values_only_sensor_errors(value):
    """parse_frame also takes an already-decoded mapping: values JSON never holds."""
    obj = frame_obj([0] * 96)
    obj["1"]["integer"] = value
    try:
        frame = parse_frame(obj, 2, 16)
    except SensorError:
        return
    assert frame is not None and frame.raw.dtype == np.uint16 and frame.raw.shape == (96,)


@settings(max_examples=60, deadline=None)
@given(words=st.lists(st.integers(0, 0xFFFF), min_size=96, max_size=96),
       style=st.lists(st.tuples(st.booleans(), st.booleans(), st.sampled_from(["", " ", "  "])),
                      min_size=96, max_size=96))
def test_xela_hex_data_parses_to_exactly_its_words(words, style):
    """Upper or lower case, padded or not, spaces around: always the same 16-bit words."""
    def fmt(w, s):
        lower, padded, space = s
        text = f"{w:04x}" if padded else f"{w:x}"
        return space + (text if lower else text.upper()) + space

    data = [",".join(fmt(w, s) for w, s in zip(words[i:i + 48], style[i:i + 48],
                                              strict=True)) for i in (0, 48)]
    obj = frame_obj(words)
    obj["1"]["data"], obj["2"]["data"] = data
    frame = parse_frame(json.dumps(obj), 2, 16)
    assert frame is not None
    assert frame.raw.tolist() == words


def test_config_file_with_an_absurd_integer_is_refused_clearly(tmp_path):
    from edge.core.config import load_config

    path = tmp_path / "big.toml"
    path.write_text("[press]\nx_th = " + "9" * 5000 + "\n")
    with pytest.raises(ConfigError, match=r"big\.toml is not valid TOML"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"api\.port = <an integer of \d+ bits>"):
        config_from_dict({"api": {"port": 10**5000}})
