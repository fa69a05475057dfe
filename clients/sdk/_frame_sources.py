"""Where the bridge's frames come from: a folder of images, or a camera through OpenCV.

A source yields :class:`Frame`: the encoded image, and when it was captured. A folder's
images are sent as they are (no decoding, so the light client needs no OpenCV for them);
a camera's frames are read by OpenCV (a device index such as ``0``, a device path, a stream
URL such as ``rtsp://...`` or a video file) and encoded as JPEG. A camera is read on its own
thread, keeping only its newest frame: a frame read late describes a place the vehicle has
left. A recording (a video file, or one served over HTTP) is played at its own frame rate,
as a camera would deliver it, so that the bridge samples it as it samples a live camera.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
MISSING_OPENCV = ("reading a camera needs OpenCV: pip install opencv-python-headless "
                  "(a folder of images needs nothing more)")


@dataclass(frozen=True)
class Frame:
    """An encoded image (JPEG or PNG), with ``name`` for messages."""

    data: bytes
    name: str
    taken_at: datetime
    """The wall-clock time the frame was taken (for a folder: when it was read)."""
    read_at: float
    """``time.monotonic()`` at ``taken_at``: how old a pose is, is measured from it."""
    captured_at: datetime | None = None
    """The capture time to tell the service, when it is not ``taken_at``."""


def folder_frames(folder: Path, *, loop: bool = False, interval_s: float | None = None
                  ) -> Iterator[Frame]:
    """The images of ``folder`` in name order (once, or over and over with ``loop``).

    ``interval_s``: the time between the images' captures, when a recorded flight is played
    faster or slower than it was flown; the service's motion model then sees the flight's
    own timing (the first image's capture time is when it is read).
    """
    paths = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise ValueError(f"no JPEG or PNG images in {folder}")
    first: datetime | None = None
    i = 0
    while True:
        for p in paths:
            now = datetime.now(UTC)
            first = first or now
            captured = None if interval_s is None else first + timedelta(seconds=i * interval_s)
            yield Frame(p.read_bytes(), p.name, now, time.monotonic(), captured)
            i += 1
        if not loop:
            return


def capture_source(source: str) -> int | str:
    """What ``cv2.VideoCapture`` opens for ``source``: a device index for digits (``"0"``,
    ``"2"``), else the string as it is (``/dev/video0``, ``rtsp://...``, ``flight.avi``)."""
    return int(source) if source.isdigit() else source


class Camera:
    """An OpenCV capture (``cv2.VideoCapture``) read continuously on a thread.

    :meth:`latest` gives the newest frame not given before, waiting for one up to
    ``timeout`` seconds. Its name is ``frame-N``, N the frame's number in the capture
    (from 1), so that a recording's frames can be told apart.
    """

    def __init__(self, source: str, *, quality: int = 90) -> None:
        try:
            import cv2
        except ImportError as exc:
            raise ImportError(MISSING_OPENCV) from exc
        self._cv2 = cv2
        self._capture = cv2.VideoCapture(capture_source(source))
        if not self._capture.isOpened():
            raise OSError(f"cannot open camera {source!r}")
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        length = self._capture.get(cv2.CAP_PROP_FRAME_COUNT)
        # a live source has no length (0 or -1) and delivers at its own pace
        self.period: float | None = 1.0 / fps if length > 0 and fps > 0 else None
        """Seconds between a recording's frames; None for a live source."""
        self._quality = quality
        self._cond = threading.Condition()
        self._latest: tuple[int, object, datetime, float] | None = None
        self._index = 0
        """The capture's frames read or skipped so far (the reader's own)."""
        self._given = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="camera", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        start = time.monotonic()
        while not self._stop.is_set():
            ok = self._keep_pace(start) if self.period is not None else True
            if ok:
                ok, image = self._capture.read()
            if not ok:
                with self._cond:
                    self._stop.set()
                    self._cond.notify_all()
                return
            self._index += 1
            with self._cond:
                self._latest = (self._index, image, datetime.now(UTC), time.monotonic())
                self._cond.notify_all()

    def _keep_pace(self, start: float) -> bool:
        """Wait for the recording's next frame to be due; skip those already past, as a
        live camera does not wait for a slow reader. False at the recording's end."""
        missed = int((time.monotonic() - start) / self.period) - self._index
        for _ in range(max(missed, 0)):
            if not self._capture.grab():
                return False
            self._index += 1
        self._stop.wait(max(start + self._index * self.period - time.monotonic(), 0.0))
        return True

    def latest(self, timeout: float = 5.0) -> Frame | None:
        """The newest frame; None when the capture ended or gave nothing for ``timeout`` s."""
        def fresh() -> bool:
            return self._latest is not None and self._latest[0] > self._given

        with self._cond:
            self._cond.wait_for(lambda: fresh() or self._stop.is_set(), timeout)
            if not fresh():
                return None
            self._given, image, at, read_at = self._latest
        ok, buf = self._cv2.imencode(".jpg", image,
                                     [self._cv2.IMWRITE_JPEG_QUALITY, self._quality])
        if not ok:
            return None
        return Frame(buf.tobytes(), f"frame-{self._given}", at, read_at)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._capture.release()


def camera_frames(source: str) -> Iterator[Frame]:
    """The newest frame of the camera each time one is asked for, until it ends."""
    camera = Camera(source)
    try:
        while (frame := camera.latest()) is not None:
            yield frame
    finally:
        camera.close()
