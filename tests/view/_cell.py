"""A robot cell's recording as a server records it (through the recorder, read back by the
reader): a World configured with two arms, the UR at the world's origin and the PiPER 0.7 m
along y turned to face it; each arm's plan and Execute run along the same path in its own base
frame (drawn at one place, the two would overlap); two bodies fused with sub-millimetre
position sigmas (invisible at their true size), the box moving 5 cm, the cup still."""
from __future__ import annotations

import math

import numpy as np

from dqpose import dq

#: T_world_base of each arm (scalar-first quaternion, position)
BASES = {"ur": ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
         "piper": ((0.0, 0.0, 0.0, 1.0), (0.0, 0.7, 0.0))}       # 180 degrees about z
#: the path each arm runs, in its own base frame
PATH = np.stack([np.linspace(0.30, 0.45, 30), 0.05 * np.sin(np.linspace(0, math.pi, 30)),
                 np.full(30, 0.20)], axis=1)
#: the bodies' positions over time (world frame) and their position sigma (m)
BODIES = {"box": np.stack([np.linspace(0.30, 0.35, 20), np.full(20, 0.35), np.full(20, 0.05)],
                          axis=1),
          "cup": np.tile([-0.30, 0.35, 0.05], (20, 1))}
SIGMA = 3e-4
LABELS = ("world", "box", "cup", "ur base", "piper base", "ur tool", "piper tool")


def base(arm: str) -> np.ndarray:
    q, t = BASES[arm]
    return dq.from_pose(np.array(q), np.array(t))


def record_cell(directory) -> str:
    from dqpose.record.recorder import Recorder
    from dqpose.rpc._proto.dqpose.v1 import fusion_pb2 as fpb
    from dqpose.rpc._proto.dqpose.v1 import trajectories_pb2 as tpb
    from dqpose.rpc._proto.dqpose.v1 import world_pb2 as wpb
    from dqpose.rpc.geometry import dq_to_pose

    recorder = Recorder(directory)
    config = wpb.WorldConfig(arms=[wpb.ArmSource(arm=a, source=f"{a}_flange") for a in BASES])
    for arm in BASES:
        dq_to_pose(base(arm), config.sources.add(name=f"{arm}_flange").extrinsic)
    call = recorder.call("dqpose.v1.World/Configure", wpb.WorldConfig, wpb.WorldConfig)
    call.request(config)
    call.answer(config)
    call.end("OK")
    level = np.array([[1.0, 0, 0, 0]] * len(PATH))
    for arm in BASES:
        recorder.plan(arm, dq.from_pose(level, PATH))
        run = recorder.call("dqpose.v1.Trajectories/Execute", tpb.ExecuteRequest,
                            tpb.ExecutionFeedback)
        run.request(tpb.ExecuteRequest(arm=arm))
        for k, p in enumerate(PATH):
            fb = tpb.ExecutionFeedback(time=0.1 * k, state=tpb.EXECUTION_WORKING)
            dq_to_pose(dq.from_pose([1.0, 0, 0, 0], p), fb.commanded)
            dq_to_pose(dq.from_pose([1.0, 0, 0, 0], p), fb.actual)
            run.answer(fb)
        run.end("OK")
    cov = np.diag([1e-6] * 3 + [SIGMA ** 2] * 3).ravel()
    fuse = recorder.call("dqpose.v1.Fusion/StreamFuse", fpb.FuseStreamRequest, fpb.FusedPose)
    for k in range(20):
        for body, path in BODIES.items():
            answer = fpb.FusedPose(body=body, time=0.1 * k, covariance=cov)
            dq_to_pose(dq.from_pose([1.0, 0, 0, 0], path[k]), answer.pose)
            fuse.answer(answer)
    fuse.end("OK")
    recorder.close()
    (f,) = recorder.files
    return f
