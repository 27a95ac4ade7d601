"""The compute process: the same answers as in-process, a crash costs one call, a model
changed on disk is refused, and the daemon, not a signal, ends the worker."""

import asyncio
import io
import json
import os
import shutil
import signal
import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from edge.core import preprocess, recording
from edge.core.errors import ComputeError, ImageError, ModelError, PreprocessError
from edge.core.model import Familiarity, load_model, model_ref
from edge.runtime import compute
from edge.runtime.compute import ComputeWorker, analyse_press, fuse_presses
from edge.vlm.images import check_image, prepare_for_vlm
from tests.support.daemon import ROOT
from tests.support.featured import featured_model
from tests.support.presses import recording_of
from tests.vlm.helpers import image_bytes

pytestmark = pytest.mark.asyncio
MODELS = ROOT / "models"


@pytest.fixture(scope="module")
def model():
    return load_model(MODELS)


async def test_analysis_in_the_worker_equals_the_model_in_process(model):
    rec = recording_of("boiled_kiri_mochi", 5)
    photo = image_bytes(1600, 1200)
    async with ComputeWorker() as worker:
        result = await worker.run(analyse_press, model_ref(MODELS), rec)
        assert worker.pid() not in (None, os.getpid())
        # The photo, prepared for the VLM (while the press runs), and the press as a file
        # (once the question has left): the same worker.
        prepared, data_url = await worker.run(prepare_for_vlm, photo, 512, 200_000)
        press_npz = await worker.run(recording.to_bytes, rec)
    x = preprocess.model_input(rec.recv_time, preprocess.recording_units(rec), rec.t_stop)
    z_here, code_here = model.encode(x)
    np.testing.assert_allclose(result.z, np.asarray(z_here).reshape(-1), atol=1e-6)
    assert result.code == code_here and result.topk == model.topk(z_here, 3)
    assert result.description == model.describe([label for label, _ in result.topk])
    with np.load(io.BytesIO(result.model_io_npz)) as arrays:
        np.testing.assert_allclose(arrays["x"], x)
    assert max(prepared.width, prepared.height) <= 512 and len(prepared.data) <= 200_000
    assert data_url.startswith(b"data:image/jpeg;base64,")
    np.testing.assert_array_equal(recording.from_bytes(press_npz).frames, rec.frames)


@pytest.fixture(scope="module")
def featured(tmp_path_factory):
    """A model directory whose database has features (made outside the test's loop: the
    recorder runs one of its own)."""
    return featured_model(tmp_path_factory.mktemp("featured"))


async def test_the_familiarity_is_ranked_on_the_presses_channel_means(featured):
    # A database with features: one press's model input at offset 0, or the mean of the
    # presses' for a fused recognition (its embedding plays no part).
    ref, db = model_ref(featured), load_model(featured).database
    fam = Familiarity(db)
    recs = [recording_of("macaron", s) for s in (3, 4)]
    xs = [preprocess.model_input(r.recv_time, preprocess.recording_units(r), r.t_stop)
          for r in recs]
    async with ComputeWorker() as worker:
        one = await worker.run(analyse_press, ref, recs[0])
        both = await worker.run(fuse_presses, ref, recs, "votes")
    want_one = fam.percentile(np.zeros(db.dim), xs[0].mean(axis=0))
    want_both = fam.percentile(np.zeros(db.dim), np.mean([x.mean(axis=0) for x in xs], axis=0))
    print(f"familiarity of one press {one.familiarity}, of two fused {both.familiarity}")
    assert one.familiarity == want_one and both.familiarity == want_both
    assert one.unfamiliar == (want_one >= 95)
    # The shipped model's database has no features: the embedding's ratio, as before.
    shipped = load_model(MODELS)
    old = analyse_press(model_ref(MODELS), recs[0])
    if shipped.database.feature is None:
        assert old.familiarity == Familiarity(shipped.database).percentile(np.asarray(old.z))


async def test_the_analysis_on_the_window_through_its_first_frame_past_equals_the_whole(model):
    """The press hands its window over as soon as the first frame at or past the crop's
    last sample has arrived (the recording's margin comes in later): the same answer as
    the whole recording gives; a frame fewer and the crop is refused, not extrapolated."""
    rec = recording_of("boiled_kiri_mochi", 5)
    ref = model_ref(MODELS)
    past = int(np.searchsorted(rec.recv_time, rec.t_stop + ref.window.last_sample_s))
    assert past < len(rec.recv_time) - 5  # the recording reaches further: its margin

    def through(n: int):
        return replace(rec, frames=rec.frames[:n], recv_time=rec.recv_time[:n],
                       sensor_time=rec.sensor_time[:n], seq=rec.seq[:n])

    whole, early = analyse_press(ref, rec), analyse_press(ref, through(past + 1))
    assert early.z == whole.z and early.topk == whole.topk
    assert early.model_io_npz == whole.model_io_npz
    with pytest.raises(PreprocessError, match="leaves the stream"):
        analyse_press(ref, through(past))


async def test_the_crop_is_the_window_the_model_states(tmp_path):
    """A model trained on another window is fed that window, not the default one."""
    models = tmp_path / "models"
    shutil.copytree(MODELS, models)
    manifest = json.loads((models / "manifest.json").read_text())
    manifest["encoder"]["window"].update(before_s=0.5, after_s=0.5)  # same length
    (models / "manifest.json").write_text(json.dumps(manifest))
    ref = model_ref(models)
    spec = preprocess.WindowSpec(before_s=0.5, after_s=0.5)
    assert ref.window == spec
    rec = recording_of("boiled_kiri_mochi", 5)
    result = analyse_press(ref, rec)
    units = preprocess.recording_units(rec)
    with np.load(io.BytesIO(result.model_io_npz)) as arrays:
        np.testing.assert_allclose(arrays["window"], preprocess.crop(rec.recv_time, units,
                                                                     rec.t_stop, spec))
        assert not np.allclose(arrays["window"], preprocess.crop(rec.recv_time, units,
                                                                 rec.t_stop))


async def test_errors_raised_in_the_worker_arrive_as_raised(model):
    async with ComputeWorker() as worker:
        with pytest.raises(ImageError, match="not a JPEG or PNG"):
            await worker.run(check_image, b"GIF89a not a picture")
        assert await worker.run(check_image, image_bytes(64, 48)) == ("JPEG", 64, 48)
        assert worker.restarts == 0


async def test_a_crashed_worker_fails_one_call_and_is_replaced(model):
    rec = recording_of("stainless_cube", 1)
    async with ComputeWorker() as worker:
        first = worker.pid()
        with pytest.raises(ComputeError, match="died during _exit"):
            await worker.run(os._exit, 3)  # as a decoder crash would end it
        assert worker.restarts == 1
        out = await worker.run(analyse_press, model_ref(MODELS), rec)
        assert worker.pid() != first and out.description  # from the new worker


async def test_a_model_changed_on_disk_is_refused_until_reloaded(tmp_path, model):
    copy = tmp_path / "models"
    shutil.copytree(MODELS, copy)
    loaded = model_ref(copy)
    rec = recording_of("stainless_cube", 2)
    async with ComputeWorker() as worker:
        manifest = copy / "manifest.json"
        manifest.write_text(manifest.read_text().replace('"schema_version"',
                                                         '"note": "edited", "schema_version"'))
        with pytest.raises(ModelError, match="changed since the daemon loaded them; send SIGHUP"):
            await worker.run(analyse_press, loaded, rec)
        reloaded = model_ref(copy)  # what SIGHUP does
        assert (await worker.run(analyse_press, reloaded, rec)).description


def _pool_threads() -> list[threading.Thread]:
    # concurrent.futures' manager thread: one left running when the interpreter exits raced
    # the exit hook and printed an EBADF traceback after a clean exit.
    return [t for t in threading.enumerate() if type(t).__name__ == "_ExecutorManagerThread"]


async def test_ending_the_worker_joins_its_pool_and_kills_a_call_that_does_not_end(
        monkeypatch):
    async with ComputeWorker() as worker:
        assert await worker.run(check_image, image_bytes(32, 32)) == ("JPEG", 32, 32)
    assert _pool_threads() == []

    monkeypatch.setattr(compute, "STOP_TIMEOUT_S", 0.5)
    worker = ComputeWorker()
    await worker.start()
    pid = worker.pid()
    call = asyncio.create_task(worker.run(time.sleep, 60))
    await asyncio.sleep(0.3)  # the call has begun in the worker
    t0 = time.monotonic()
    await worker.stop()
    took = time.monotonic() - t0
    print(f"a worker stuck in a call ended after {took:.2f} s")
    assert 0.5 <= took < 10 and _gone(pid) and _pool_threads() == []
    with pytest.raises(ComputeError, match="died during sleep"):
        await call
    assert worker.restarts == 0  # ended by its owner: not replaced


async def test_the_worker_outlives_sigint_and_sigterm(model):
    async with ComputeWorker() as worker:
        pid = worker.pid()
        for sig in (signal.SIGINT, signal.SIGTERM):
            os.kill(pid, sig)
        assert await worker.run(check_image, image_bytes(32, 32)) == ("JPEG", 32, 32)
        assert worker.pid() == pid and worker.restarts == 0
    # Closed by its owner: the process goes away.
    for _ in range(200):
        if _gone(pid):
            break
        await asyncio.sleep(0.01)
    else:
        raise AssertionError(f"compute worker {pid} still runs after close()")


def _gone(pid: int) -> bool:
    """Exited: no such process, or a zombie waiting for its parent to reap it."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rpartition(")")[2].split()[0] == "Z"
    except OSError:
        return True


async def test_the_daemon_looks_a_press_up_with_the_references_taught_in_its_state_dir(
        tmp_path):
    from edge.app import model_ref as daemon_model_ref
    from edge.core.config import Config
    from edge.runtime.compute import teach_press
    from edge.runtime.references import references_dir

    cfg = Config()
    cfg = replace(cfg, runtime=replace(cfg.runtime, models_dir=str(MODELS),
                                       state_dir=str(tmp_path / "state")))
    ref = daemon_model_ref(cfg)
    assert ref.references == references_dir(tmp_path / "state").resolve()
    # A reload reads the new file's model but keeps the running state directory.
    moved = replace(cfg, runtime=replace(cfg.runtime, state_dir=str(tmp_path / "other")))
    assert daemon_model_ref(moved, cfg.runtime.state_dir).references == ref.references
    new = "boiled_kiri_mochi"  # a FoodReplica object the shipped model has no class for
    before = analyse_press(ref, replace(recording_of(new, 17), label="unknown"))
    teach_press(ref, replace(recording_of(new, 1), label="unknown"), new,
                "boiled kiri mochi (a rice cake)", "api")
    after = analyse_press(ref, replace(recording_of(new, 17), label="unknown"))
    print("before", before.topk, before.familiarity, "after", after.topk, after.familiarity)
    assert new not in dict(before.topk) and new in dict(after.topk)
    assert after.references and not before.references
