"""The ``dqpose.v1.HandEye`` service: Calibrate (:func:`service.handeye.calibrate`), solved off the
event loop.

Malformed pairs are ``INVALID_ARGUMENT`` naming the field (``pairs[3].camera_to_target...``);
data the calibration cannot be determined from (:class:`~service.errors.Infeasible`: too few
pairs, degenerate motion) is ``FAILED_PRECONDITION`` with the domain's reason and samples.
"""
from __future__ import annotations

import asyncio

from service import handeye
from service.errors import FieldError
from service.rpc.calls import Calls
from service.rpc.convert import calibrate_error, calibrate_from_msg, calibration_to_msg
from service.rpc._proto.dqpose.v1 import handeye_pb2 as pb
from service.rpc._proto.dqpose.v1 import handeye_pb2_grpc as pb_grpc


class HandEye:
    NAME = "dqpose.v1.HandEye"

    def __init__(self, cfg, calls: Calls):
        self.calls = calls
        self.max_poses = cfg.max_poses

    def calibrate(self, request: pb.CalibrateRequest) -> pb.CalibrateResponse:
        if len(request.pairs) > self.max_poses:
            raise FieldError(f"pairs: {len(request.pairs)} exceed the server limit of "
                             f"{self.max_poses} per request")
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

    def register(self, server) -> None:
        """The generated registration: every RPC with the proto's own (de)serializers."""
        pb_grpc.add_HandEyeServicer_to_server(self, server)

    async def Calibrate(self, request, context):
        # a refinement of tens of milliseconds holding the GIL: off the event loop, so other
        # calls' messages keep moving
        return await self.calls.unary("Calibrate",
                                      lambda r: asyncio.to_thread(self.calibrate, r),
                                      request, context)
