"""The live view (``dqpose serve --live [HOST:PORT]``): foxglove-sdk's WebSocket server (protocol
``foxglove.sdk.v1``, which Foxglove and Lichtblick open as a "Foxglove WebSocket" connection)
carrying the recording's channels as they are logged, a :class:`~dqpose.record.sink.Sink` of
the writer process, so that neither the server's sockets nor its clients cost the gRPC server
anything. Messages logged while no client subscribes to a channel are not kept.
"""
from __future__ import annotations

import foxglove

from dqpose.record.sink import Sink

#: messages waiting per client at most; beyond, the oldest are dropped (a slow viewer)
BACKLOG = 4096


class LiveServer(Sink):
    """Serves its channels on ``host:port`` (0: a free port, then :attr:`port` says which);
    the SDK's ``RuntimeError`` when it cannot bind."""

    def __init__(self, host: str, port: int):
        super().__init__()
        self.host = host
        self._server = foxglove.start_server(name="dqpose", host=host, port=port,
                                             context=self._context,
                                             message_backlog_size=BACKLOG)
        self.port = self._server.port

    def close(self) -> None:
        self.close_channels()
        self._server.stop()
