"""Where a camera's frames come from: a folder of images in name order, one image, a video file,
a ``cv2.VideoCapture`` device read by a background thread that keeps only the newest frame
(:class:`LiveFrames`: ``read(timeout)`` can give up on a stalled camera), or any object with
``read(timeout=None)`` and ``close()``. ``read`` returns the next image, or None at the source's
end; :func:`open_frames` picks the source for a path or device index.
"""
from __future__ import annotations

import glob
import os
import threading
from typing import Optional, Union

import cv2
import numpy as np

__all__ = ["IMAGE_EXTENSIONS", "FolderFrames", "VideoFrames", "LiveFrames", "read_image",
           "open_frames"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


class FolderFrames:
    """Images of a folder in name order. An unreadable image raises ``ValueError``."""

    def __init__(self, folder: str):
        if not os.path.isdir(folder):
            raise ValueError(f"source: no such folder: {folder!r}")
        self.paths = sorted(p for p in glob.glob(os.path.join(folder, "*"))
                            if p.lower().endswith(IMAGE_EXTENSIONS))
        if not self.paths:
            raise ValueError(f"source: no images ({', '.join(IMAGE_EXTENSIONS)}) in {folder!r}")
        self._next = 0
        self.current: Optional[str] = None

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        if self._next >= len(self.paths):
            return None
        path = self.paths[self._next]
        self._next += 1
        self.current = path
        return read_image(path)

    def close(self) -> None:
        pass


class VideoFrames:
    """A ``cv2.VideoCapture`` device index or video file."""

    def __init__(self, source: Union[int, str]):
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            self.cap.release()
            what = f"camera device {source}" if isinstance(source, int) else f"video {source!r}"
            raise ValueError(f"source: cannot open {what}")
        self.current = source

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        ok, frame = self.cap.read()
        return frame if ok else None

    def close(self) -> None:
        self.cap.release()


class LiveFrames:
    """A live frame source (a camera device) read by a background thread that keeps only the
    newest frame: ``read(timeout)`` returns a frame not returned before, waits at most
    ``timeout`` seconds for one (then raises ``TimeoutError``: a stalled or unplugged camera must
    not hang a fusion loop), and returns None once the source has ended. A consumer slower than
    the camera skips frames instead of falling behind; ``dropped`` counts them."""

    def __init__(self, frames):
        self._frames = frames
        self.current = getattr(frames, "current", None)
        self._cond = threading.Condition()
        self._frame: Optional[np.ndarray] = None
        self._fresh = False
        self._ended = False
        self._error: Optional[BaseException] = None
        self._closing = False
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="camera-frames", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._closing:
                frame = self._frames.read()
                with self._cond:
                    if frame is None:
                        break
                    self.dropped += self._fresh
                    self._frame, self._fresh = frame, True
                    self._cond.notify_all()
        except Exception as e:   # handed to the reader, which raises it
            self._error = e
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def read(self, timeout: Optional[float] = None) -> Optional[np.ndarray]:
        with self._cond:
            if not self._cond.wait_for(lambda: self._fresh or self._ended, timeout):
                raise TimeoutError(f"no frame within {timeout:g} s")
            if self._fresh:
                self._fresh = False
                return self._frame
            if self._error is not None:
                raise self._error
            return None

    def close(self) -> None:
        self._closing = True
        self._frames.close()        # also unblocks a read() in progress on most backends
        self._thread.join(timeout=2.0)


def read_image(path: str) -> np.ndarray:
    if not os.path.isfile(path):
        raise ValueError(f"image: no such file: {path!r}")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"image: cannot decode {path!r} (not an image, or corrupt)")
    return img


def open_frames(source: Union[int, str]):
    """A device index (int or digit string), a folder of images, one image, a video file, or a
    frame source object (``read(timeout=None)`` and ``close()``), used as it is."""
    if isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.isdigit()):
        return LiveFrames(VideoFrames(int(source)))
    if callable(getattr(source, "read", None)) and callable(getattr(source, "close", None)):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError(f"source: expected a device index or a path, got {source!r}")
    source = os.fspath(source)
    if os.path.isdir(source):
        return FolderFrames(source)
    if not os.path.exists(source):
        raise ValueError(f"source: no such file or folder: {source!r}")
    if source.lower().endswith(IMAGE_EXTENSIONS):
        frames = FolderFrames.__new__(FolderFrames)
        frames.paths, frames._next, frames.current = [source], 0, None
        return frames
    return VideoFrames(source)
