"""One MCAP file being written, through foxglove-sdk's writer (Rust: ~2 us a message here, where
``mcap``'s Python writer took ~37 us, which the server's event loop paid for in interpreter-lock
waits): a :class:`~dqpose.record.sink.Sink` (its channels), chunked, zstd-compressed on the SDK's
own threads, chunk CRCs. A context of its own per file, so that files rotate without touching any
other sink. Not thread-safe: the writer process owns it.
"""
from __future__ import annotations

import os

import foxglove
from foxglove.mcap import MCAPWriteOptions

from dqpose.record.sink import Sink

#: what the file says wrote it (MCAP's header ``profile`` is left empty: no ROS profile)
LIBRARY = "dqpose"

#: a chunk's uncompressed size: the SDK compresses a chunk inside the ``log`` call that fills it,
#: holding the interpreter lock (~2-4 ms for 1 MB, which the server's event loop waited for;
#: 16 kB: ~0.1 ms)
CHUNK_BYTES = 16 << 10


class _Out:
    """The file the SDK writes through: the SDK logs a failed write and goes on (every later
    message failing too) without telling the caller, so the first ``OSError`` is kept here
    (:attr:`McapFile.error`) for the writer to see."""

    def __init__(self, path: str):
        self._f = open(path, "xb", buffering=0)      # x: never over another file
        self.error: OSError | None = None

    def write(self, data) -> int:
        try:
            return self._f.write(data)
        except OSError as e:
            self.error = self.error or e
            raise

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self._f.close()


class McapFile(Sink):
    def __init__(self, path: str | os.PathLike, chunk_size: int = CHUNK_BYTES):
        super().__init__()
        self.path = os.fspath(path)
        self._out = _Out(self.path)
        try:
            self._writer = foxglove.open_mcap(
                self._out, context=self._context,
                writer_options=MCAPWriteOptions(chunk_size=chunk_size, compression_threads=0))
        except BaseException:
            self._out.close()
            raise

    @property
    def error(self) -> OSError | None:
        """The first write that failed (the file is cut there: nothing after it is written)."""
        return self._out.error

    @property
    def size(self) -> int:
        """Bytes on disk so far (chunks are written when full: up to a chunk behind)."""
        try:
            return os.path.getsize(self.path)
        except OSError:
            return 0

    def close(self) -> None:
        """The last chunk, the summary (indexes, statistics) and the footer."""
        self.close_channels()
        try:
            self._writer.close()
        finally:
            self._out.close()
