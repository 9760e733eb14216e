"""The World service's calls of :class:`dqpose.rpc.client.Client` (world.proto): Configure,
Publish, Subscribe and Lookup, each with the client's world header; Publish and Subscribe reopened
through :mod:`dqpose.rpc.resume` when the client has ``reconnect``."""
from __future__ import annotations

from typing import TYPE_CHECKING, Iterable, Iterator, Optional, Sequence

import grpc
import numpy as np

from dqpose import fusion
from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
from dqpose.rpc.client_arrays import stream_answer
from dqpose.rpc.client_types import Ack, Batch, Relative, StreamAnswer, rpc_errors
from dqpose.rpc.fusion_convert import DEFAULT_PROBABILITY
from dqpose.rpc.geometry import pose_to_dq
from dqpose.rpc.resume import Resuming, reopened, replica_of
from dqpose.rpc.wire import publish_request_wire

WORLD = wpb.DESCRIPTOR.services_by_name["World"].full_name
if TYPE_CHECKING:   # the stubs' generics: grpc's own classes take no parameters at run time
    _Streams = grpc.StreamStreamMultiCallable[bytes, bytes]


class WorldCalls:
    """The World service's methods of the client; the channel, its metadata, ``timeout``,
    ``reconnect``, ``world``, ``_call`` and ``_seen`` are the client's (:meth:`_world_stubs`
    makes the stubs on its channel)."""

    channel: grpc.Channel
    metadata: Optional[tuple]
    timeout: float
    reconnect: float
    world: Optional[str]

    def _call(self, method, request):
        raise NotImplementedError

    def _seen(self, replica: Optional[str]) -> None:
        raise NotImplementedError

    def _world_stubs(self) -> None:
        self._configure_world = self.channel.unary_unary(
            f"/{WORLD}/Configure", request_serializer=wpb.WorldConfig.SerializeToString,
            response_deserializer=wpb.WorldConfig.FromString)
        self._publish: _Streams = self.channel.stream_stream(f"/{WORLD}/Publish")
        self._subscribe: grpc.UnaryStreamMultiCallable = self.channel.unary_stream(
            f"/{WORLD}/SubscribeBatches",
            request_serializer=wpb.SubscribeRequest.SerializeToString)
        self._lookup = self.channel.unary_unary(
            f"/{WORLD}/Lookup", request_serializer=wpb.LookupRequest.SerializeToString,
            response_deserializer=wpb.RelativePose.FromString)
        # the last WorldConfig this client's world accepted: sent again before a World stream
        # reopens (its world may have moved to a replica that never had it)
        self.world_config: Optional[wpb.WorldConfig] = None

    def configure_world(self, sources: Iterable[fusion.Source] = (), arms=None,
                        **options) -> wpb.WorldConfig:
        """Sets the server's world: its sources (:class:`dqpose.fusion.Source`, with
        ``extrinsic_covariance``), ``arms`` (arm name -> source name) and ``options``
        (:func:`dqpose.rpc.world_convert.world_config`'s: robust, probability, max_skew,
        max_extrapolation, window, twist_covariance, acceleration_psd, buffer, max_delay).
        Returns the ``WorldConfig`` in force."""
        from dqpose.rpc.world_convert import world_config
        return self.configure_world_msg(world_config(sources, arms, **options))

    def configure_world_msg(self, config: wpb.WorldConfig) -> wpb.WorldConfig:
        """:meth:`configure_world` of a ready ``WorldConfig``; the client keeps it to send again
        when a World stream reopens."""
        answer = self._call(self._configure_world, config)
        self.world_config = config
        return answer

    def _configure_again(self) -> None:
        """Before a World stream reopens: the last configuration sent again (grpc's errors
        raised as they are: the stream's reopening decides)."""
        if self.world_config is not None:
            self._configure_world(self.world_config, timeout=self.timeout,
                                  metadata=self.metadata)

    def publish(self, batches: Iterable, producer: str = "",
                first_sequence: int = 1) -> Iterator[Ack]:
        """Publishes :class:`Batch` es (each measurement naming its body) into the world as one
        ``Publish`` stream, numbered ``first_sequence``, ``first_sequence + 1``, ... under
        ``producer`` (0: unnumbered); yields one :class:`Ack` per batch, in order. A batch that
        cannot be sent (wrong shape) ends the stream and raises its ``ValueError`` after the
        acks before it. With ``reconnect``, a stream whose replica went away is reopened (the
        world's last configuration sent first) and the batches after the last ``acked_through``
        are sent again (numbered, a batch the world already had is acked with an error, never
        fused twice); every batch gets its one ack."""
        def requests():
            for i, b in enumerate(batches):
                b = b if isinstance(b, Batch) else Batch(*b)
                seq = first_sequence + i if first_sequence else 0
                try:
                    # the bytes protobuf would write, without a message a measurement
                    data = publish_request_wire(b, producer, seq)
                except ValueError as e:
                    raise ValueError(f"batches[{i}].{e}") from None
                yield data

        return self._publish_bytes(requests())

    def publish_requests(self, requests: Iterable[wpb.PublishRequest]) -> Iterator[Ack]:
        """:meth:`publish` of ready ``PublishRequest`` messages (``dqpose world publish``)."""
        return self._publish_bytes(r.SerializeToString() for r in requests)

    def _publish_bytes(self, requests: Iterator[bytes]) -> Iterator[Ack]:
        # one ack per request, in order: an ack's place acknowledges its request, as its
        # acked_through does the sequences up to it
        stream = Resuming(self._publish, requests, b"", None,
                          metadata=self.metadata, reconnect=self.reconnect,
                          before=self._configure_again, seen=self._seen)
        acks = stream.answers()
        try:
            with rpc_errors():
                for _, data in acks:
                    a = wpb.PublishAck.FromString(data)
                    yield Ack(a.acked_through, tuple((e.request, e.measurement, e.details)
                                                     for e in a.errors))
        finally:
            acks.close()
        if stream.failed:
            raise stream.failed[0]

    def subscribe(self, bodies: Sequence[str] = (), rate_hz: float = 0.0,
                  relative_to: str = "", *, timeout: Optional[float] = None,
                  probability: float = DEFAULT_PROBABILITY) -> Iterator[StreamAnswer]:
        """The world's fused poses of ``bodies`` (empty: all) as they fall due (see
        world.proto: paced on measurement time), as :class:`StreamAnswer` s; with
        ``relative_to`` a body, ``fused.mean``/``covariance`` are ``T_relative_to_body``. The
        stream has no deadline unless ``timeout``; close the iterator (or cancel) to end it.
        With ``reconnect``, a stream whose replica went away is opened again (the world's last
        configuration sent first): answers go on from what the world's new replica receives
        (its ``request`` numbers restart there)."""
        request = wpb.SubscribeRequest(bodies=list(bodies), rate_hz=rate_hz,
                                       relative_to=relative_to)
        answers = reopened(lambda: self._subscribe(request, timeout=timeout,
                                                   metadata=self.metadata),
                           self.reconnect, self._configure_again, self.world, self._seen)
        try:
            with rpc_errors():
                # SubscribeBatches: Subscribe's answers, those ready together in one message
                for data in answers:
                    for a in wpb.FusedPoseBatch.FromString(data).poses:
                        yield stream_answer(a, probability)
        finally:
            answers.close()     # the call cancelled when the caller closes this iterator

    def lookup(self, target: str, source: str, time: float = 0.0, wait: float = 0.0,
               source_time: float = 0.0, fixed_frame: str = "") -> Relative:
        """``T_target_source`` at ``time`` (0: the newest both are known at; "" is the world
        frame) with its covariance, tf2's lookupTransform order; with ``source_time`` the source
        at that time through ``fixed_frame`` ("": the world), tf2's advanced lookupTransform.
        ``wait`` (s, up to 10): until the world can answer (tf2's waitForTransform), the call's
        deadline extended by it. An unknown frame raises :class:`RpcError` NOT_FOUND, a time
        the world does not know FAILED_PRECONDITION."""
        request = wpb.LookupRequest(target=target, source=source, time=time, wait=wait,
                                    source_time=source_time, fixed_frame=fixed_frame)
        deadline = None if self.timeout is None else self.timeout + (wait if wait > 0 else 0.0)
        with rpc_errors(self._seen):
            r, call = self._lookup.with_call(request, timeout=deadline, metadata=self.metadata)
        self._seen(replica_of(call))
        return Relative(pose_to_dq(r.pose),
                        np.array(r.covariance, dtype=np.float64).reshape(6, 6), r.time)
