"""The ``dqpose.v1.HandEye`` service: Calibrate (:func:`dqpose.handeye.calibrate`), solved off the
event loop (the server's worker pool), within the limits ``max_pairs`` and ``max_corners``.

Malformed pairs are ``INVALID_ARGUMENT`` naming the field (``pairs[3].camera_to_target...``);
data the calibration cannot be determined from (:class:`~dqpose.errors.Infeasible`: too few
pairs, degenerate motion) is ``FAILED_PRECONDITION`` with the domain's reason and samples.
"""
from __future__ import annotations

from typing import Any

import grpc
from google.protobuf.message import DecodeError

from dqpose import handeye, limits
from dqpose.errors import FieldError
from dqpose.rpc._proto.dqpose.v1 import handeye_pb2 as pb
from dqpose.rpc.calls import Calls
from dqpose.rpc.checks import check_count
from dqpose.rpc.handeye_convert import calibrate_error, calibrate_from_msg, calibration_to_msg


class HandEye:
    NAME = "dqpose.v1.HandEye"

    def __init__(self, cfg, calls: Calls):
        self.calls = calls
        self.max_poses = cfg.max_poses
        self.limits = cfg.limits

    def calibrate(self, request: pb.CalibrateRequest) -> pb.CalibrateResponse:
        n = len(request.pairs)
        check_count("pairs", n, self.max_poses)
        if n > self.limits.max_pairs:
            raise limits.over("pairs", f"{n} pairs", self.limits, "max_pairs")
        corners = sum(len(p.corners.image_points) for p in request.pairs) // 2
        if corners > self.limits.max_corners:
            raise limits.over("pairs", f"{corners} corners in all (PosePair.corners)",
                              self.limits, "max_corners")
        args = calibrate_from_msg(request)
        try:
            result = handeye.calibrate(args.base_flange, args.camera_target, args.setup,
                                       robust=args.robust,
                                       camera_covariance=args.camera_covariance,
                                       robot_covariance=args.robot_covariance,
                                       corners=args.corners, refine_focal=args.refine_focal,
                                       pixel_sigma=args.pixel_sigma)
        except ValueError as e:
            raise calibrate_error(e) from None
        return calibration_to_msg(result)

    def calibrate_bytes(self, data: bytes) -> bytes:
        """What Calibrate serves: ``CalibrateResponse`` bytes for ``CalibrateRequest`` bytes."""
        try:
            request = pb.CalibrateRequest.FromString(data)
        except DecodeError:
            raise FieldError("request: not a valid dqpose.v1.CalibrateRequest message") from None
        return self.calibrate(request).SerializeToString()

    def register(self, server) -> None:
        """Calibrate takes and returns bytes: parsed, solved and written in the worker pool."""
        handlers: dict[str, grpc.RpcMethodHandler[Any, Any]] = {
            "Calibrate": grpc.unary_unary_rpc_method_handler(
                self.Calibrate, request_deserializer=None, response_serializer=None)}
        generic = grpc.method_handlers_generic_handler(self.NAME, handlers)
        server.add_generic_rpc_handlers((generic,))
        server.add_registered_method_handlers(self.NAME, handlers)

    async def Calibrate(self, request: bytes, context):
        # tens of milliseconds to seconds of solver: off the event loop, so other calls,
        # health and signals are answered meanwhile
        return await self.calls.unary("Calibrate",
                                      lambda r: self.calls.work(self.calibrate_bytes, r),
                                      request, context)
