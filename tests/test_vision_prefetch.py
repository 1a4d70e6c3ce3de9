"""The pipelined frame reader (decoding in a background thread) against the plain one."""

from __future__ import annotations

import gc
import threading
import time
import warnings

import cv2
import numpy as np
import pytest

from ajtwin.vision import extract as extract_module
from ajtwin.vision.extract import (
    PrefetchedFrames,
    TruncatedVideoWarning,
    VisionInputError,
    open_source,
)


def _write_video(path, count=12, shape=(48, 64), codec="mp4v"):
    """A small video (MPEG-4 by default) whose frames differ (a moving gradient plus noise)."""
    rng = np.random.default_rng(3)
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter_fourcc(*codec), 25, (shape[1], shape[0]), False
    )
    assert writer.isOpened()
    ramp = np.add.outer(np.arange(shape[0]), np.arange(shape[1])).astype(float)
    for k in range(count):
        frame = (ramp * 2 + 9 * k + rng.normal(0, 3, shape)).clip(0, 255).astype(np.uint8)
        writer.write(frame)
    writer.release()
    return path


def _same_frames(a, b):
    assert [(i, t) for i, t, _ in a] == [(i, t) for i, t, _ in b]
    for (_, _, fa), (_, _, fb) in zip(a, b, strict=True):
        assert fa.dtype == fb.dtype == np.uint8
        np.testing.assert_array_equal(fa, fb)


def _wait_stopped(reader, seconds=5.0):
    deadline = time.monotonic() + seconds
    while reader.running and time.monotonic() < deadline:
        time.sleep(0.01)
    return not reader.running


@pytest.mark.parametrize(
    "depth,name,codec", [(1, "v.avi", "mp4v"), (4, "v.mp4", "mp4v"), (2, "v.avi", "MJPG")]
)
def test_prefetched_yields_exactly_the_plain_frames(tmp_path, depth, name, codec):
    source = open_source(_write_video(tmp_path / name, codec=codec))
    plain = list(source)
    assert len(plain) == 12 and plain[3][1] == pytest.approx(3 / 25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a whole video: no truncation warning
        with source.prefetched(depth) as reader:
            piped = list(reader)
    _same_frames(plain, piped)
    assert not reader.running
    assert next(iter(reader), None) is None  # exhausted stays exhausted


def test_prefetched_truncated_video_warns_in_the_caller(tmp_path):
    from ajtwin.cli.vision import render

    video = tmp_path / "cam.avi"
    render.main(["--out", str(video), "--duration", "10", "--size", "320x240"],
                standalone_mode=False)  # fmt: skip
    data = video.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) * 2 // 5])
    source = open_source(cut)
    with pytest.warns(TruncatedVideoWarning, match=r"cut\.avi: decoded \d of the 10 frames"):
        plain = list(source)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = source.prefetched(2)
        piped = list(reader)
    truncation = [w for w in caught if issubclass(w.category, TruncatedVideoWarning)]
    assert len(truncation) == 1 and "decoded" in str(truncation[0].message)
    assert truncation[0].filename == __file__  # issued where the caller iterates
    assert 1 <= len(piped) < 10
    _same_frames(plain, piped)
    assert _wait_stopped(reader)


def test_prefetched_exception_in_consumer_stops_the_thread(tmp_path, monkeypatch):
    path = _write_video(tmp_path / "v.avi", count=30)
    reads = []
    original = cv2.VideoCapture

    class Counting:
        def __init__(self, *a):
            self._c = original(*a)

        def read(self):
            reads.append(threading.current_thread().name)
            return self._c.read()

        def __getattr__(self, name):
            return getattr(self._c, name)

    source = open_source(path)
    monkeypatch.setattr(extract_module.cv2, "VideoCapture", Counting)
    with pytest.raises(RuntimeError, match="the consumer failed"):
        with source.prefetched(depth=2) as reader:
            for index, _, _ in reader:
                if index == 3:
                    time.sleep(0.3)  # a slow consumer: the decoder must wait, not run ahead
                    ahead = len(reads)
                    raise RuntimeError("the consumer failed")
    assert not reader.running  # close() joined it
    # frames 0..3 handed out, 2 in the queue, 1 decoded and waiting to be queued
    assert 4 <= ahead <= 4 + 2 + 1
    assert len(reads) <= ahead + 1
    assert all(name.startswith("ajtwin-decode") for name in reads)


def test_prefetched_decode_error_is_raised_at_its_frame(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(4):
        cv2.imwrite(str(folder / f"f{k}.png"), np.full((20, 30), 40 * k + 10, np.uint8))
    (folder / "f2.png").write_bytes(b"not a png")
    source = open_source(folder)
    got = []
    reader = source.prefetched(3)
    with pytest.raises(VisionInputError, match=r"f2\.png: not a readable image"):
        for item in reader:
            got.append(item)
    assert [i for i, _, _ in got] == [0, 1]
    assert got[1][2][0, 0] == 50
    assert _wait_stopped(reader)


def test_abandoned_reader_is_stopped_on_collection(tmp_path):
    source = open_source(_write_video(tmp_path / "v.avi", count=30))
    reader = source.prefetched(1)
    next(reader)
    thread = reader._thread
    del reader
    gc.collect()
    thread.join(timeout=5)
    assert not thread.is_alive()


def test_prefetch_depth_must_be_positive(tmp_path):
    source = open_source(_write_video(tmp_path / "v.avi", count=2))
    with pytest.raises(ValueError, match="depth must be >= 1"):
        PrefetchedFrames(source, 0)


# --------------------------------------------------------------------------- #
# The trimmed feature work gives the same numbers as the plain OpenCV path
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("shape", [(1080, 1920), (48, 64), (50, 66), (1081, 1922)])
def test_area_downscale_is_bit_identical_to_opencv(shape):
    rng = np.random.default_rng(shape[1])
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    # ties (block sums that end in exactly .5) on purpose: a column pattern of 0/1/2
    ties = (np.arange(shape[1]) % 3).astype(np.uint8)[None, :].repeat(shape[0], 0) + 100
    for gray in (noise, ties):
        for q in (1, 2, 4):
            expected = cv2.resize(
                gray, (shape[1] // q, shape[0] // q), interpolation=cv2.INTER_AREA
            )
            np.testing.assert_array_equal(extract_module.area_downscale(gray, q), expected)


def test_extractor_results_unchanged_by_the_fast_downscale(monkeypatch):
    from ajtwin.vision.profile import line_profile
    from ajtwin.vision.render import RenderSettings, render_frame

    r = np.arange(-160.0, 160.0, 0.05)
    frames = [
        render_frame(
            r,
            line_profile(r, 43.0, 29.0, 15.0),
            (1080, 1920),
            RenderSettings.from_defaults(tilt_deg=tilt, raggedness_um=1.0),
            rng=np.random.default_rng(int(tilt) + 20),
        )
        for tilt in (-8.0, 3.0)
    ]
    fast = [extract_module.LineExtractor(0.75).process(f) for f in frames]
    monkeypatch.setattr(
        extract_module,
        "area_downscale",
        lambda g, q: cv2.resize(
            g, (g.shape[1] // q, g.shape[0] // q), interpolation=cv2.INTER_AREA
        ),
    )
    plain = [extract_module.LineExtractor(0.75).process(f) for f in frames]
    for a, b in zip(fast, plain, strict=True):
        assert a.status == b.status == "ok"
        assert a.row() == b.row() and a.angle_deg == b.angle_deg
        assert [x.shoulders for x in a.batches] == [x.shoulders for x in b.batches]
