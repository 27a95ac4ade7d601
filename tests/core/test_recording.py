import io
import json
import zipfile
from dataclasses import replace

import numpy as np
import pytest

from edge.core import recording
from edge.core.errors import EdgeError, RecordingError
from tests.support.presses import recording_of


@pytest.fixture(scope="module")
def rec():
    return recording_of("otedama", 2)


def test_round_trip(tmp_path, rec):
    path = recording.save(rec, tmp_path / "a" / "x.press.npz")
    back = recording.load(path)
    for name in ("frames", "recv_time", "sensor_time", "seq", "tare", "gripper_time",
                 "gripper_width_m", "gripper_current_ma"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name))
    assert back.label == "otedama" and back.t_stop == rec.t_stop
    assert back.schema_version == recording.SCHEMA_VERSION
    assert not list(path.parent.glob("*.tmp")), "no temp file left behind"


@pytest.mark.parametrize("keep", [0.0, 0.3, 0.9, 0.999])
def test_truncated_file_is_refused_clearly(tmp_path, rec, keep):
    data = recording.to_bytes(rec)
    path = tmp_path / "t.press.npz"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(RecordingError) as err:
        recording.load(path)
    assert str(path) in str(err.value)
    assert "truncated or corrupt" in str(err.value) or "not a press recording" in str(err.value)
    assert isinstance(err.value, EdgeError)


def test_flipped_byte_is_caught_by_the_crc(tmp_path, rec):
    data = bytearray(recording.to_bytes(rec))
    data[len(data) // 3] ^= 0xFF
    with pytest.raises(RecordingError, match="truncated or corrupt"):
        recording.from_bytes(bytes(data))


def _rewrite(rec, **changes):
    buf = io.BytesIO(recording.to_bytes(rec))
    with np.load(buf) as npz:
        members = {k: npz[k] for k in npz.files}
    members.update(changes)
    out = io.BytesIO()
    np.savez(out, **members)
    return out.getvalue()


def test_malformed_contents_are_named(rec):
    meta = json.loads(str(_meta(rec)))
    cases = [
        (_rewrite(rec, frames=rec.frames.astype(np.int32)), "frames has dtype int32"),
        (_rewrite(rec, seq=rec.seq[:-1]), "seq has"),
        (_rewrite(rec, meta=np.array(json.dumps({**meta, "schema_version": 99}))),
         "schema version 99 is not supported"),
        (_rewrite(rec, meta=np.array(json.dumps({**meta, "t_stop": 1e9}))), "outside the frames"),
        (_rewrite(rec, meta=np.array(json.dumps({**meta, "label": ""}))), "label must be"),
        (_rewrite(rec, meta=np.array("{nope")), "not valid JSON"),
        (_rewrite(rec, recv_time=rec.recv_time[::-1].copy()), "goes backwards"),
    ]
    for data, needle in cases:
        with pytest.raises(RecordingError, match=needle):
            recording.from_bytes(data)


def _meta(rec):
    with np.load(io.BytesIO(recording.to_bytes(rec))) as npz:
        return npz["meta"]


def test_missing_member_and_foreign_zip(tmp_path):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("hello.txt", "hi")
    with pytest.raises(RecordingError):
        recording.from_bytes(buf.getvalue())
    with pytest.raises(RecordingError, match="cannot read"):
        recording.load(tmp_path / "nope.press.npz")


def test_a_press_is_identified_by_its_frames_not_its_file(tmp_path, rec):
    first = recording.save(rec, tmp_path / "a" / "otedama_000.press.npz")
    copy = recording.save(replace(rec, label="renamed", t_stop=rec.t_stop + 0.001),
                          tmp_path / "b" / "mochi_900.press.npz")
    digest = recording.frames_sha256(recording.load(first))
    assert recording.frames_sha256(recording.load(copy)) == digest
    frames = rec.frames.copy()
    frames[10, 5] += 1  # one count of one channel
    assert recording.frames_sha256(replace(rec, frames=frames)) != digest
