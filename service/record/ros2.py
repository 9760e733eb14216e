"""A recording as a ROS 2 bag (rosbag2, MCAP storage, CDR messages) through ``rosbags``, no ROS
installation: each fused pose as ``geometry_msgs/PoseWithCovarianceStamped`` on
``/fused/<body>/pose`` (its covariance converted once, by :func:`dqpose.lie.cov_to_ros`), the
bodies' frames on ``/tf`` (``tf2_msgs/TFMessage``), each body's fused path and each plan as
``nav_msgs/Path`` (``/fused/<body>/path``, ``/plans/<name>``), and each World configuration's
frames fixed in their parents on ``/tf_static`` (:func:`dqpose.record.views.static_transforms`:
stamped 0, offered as tf2's static broadcaster offers it, reliable and transient local with a
depth of 1, so that ``ros2 bag play`` latches it). A fused pose's header stamp is
its own time (``FusedPose.time``, as in its Foxglove views: a tf lookup at a time finds the pose
of that time), the bag's timestamp of each message its arrival, as the recording's log time; a
plan is stamped with its arrival. The fused poses are decoded with the schema the recording
embeds (one that does not decode is a ``Damaged`` recording); a pose time beyond a ROS stamp's
int32 seconds is a ``ValueError`` naming it.
"""
from __future__ import annotations

import os

import numpy as np
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from dqpose import dq, lie
from dqpose.record.reader import Recording
from dqpose.record.types import FUSED_POSE, WORLD_CONFIG
from dqpose.record.views import WORLD, static_transforms, time_ns

STORE = Stores.ROS2_HUMBLE
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"
#: tf2_ros's StaticTransformBroadcaster's QoS (0: the default, infinite)
LATCHED = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
              QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


def export(rec: Recording, out_dir: str | os.PathLike) -> dict[str, int]:
    """Writes the bag into ``out_dir`` (which must not exist: rosbag2's rule); returns the
    messages written per topic."""
    ts = get_typestore(STORE)
    T = ts.types
    counts: dict[str, int] = {}
    paths: dict[str, list] = {}
    Fused = rec.message_class(FUSED_POSE) if FUSED_POSE in rec.schemas else None

    def header(ns: int):
        if not -2**31 <= ns // 10**9 < 2**31:
            raise ValueError(f"a time of {ns / 1e9:.6g} s is beyond a ROS 2 stamp (int32 "
                             f"seconds)")
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id=WORLD)

    def pose(p, o):
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=p.z),
            orientation=T["geometry_msgs/msg/Quaternion"](x=o.x, y=o.y, z=o.z, w=o.w))

    with Writer(os.fspath(out_dir), version=9, storage_plugin=StoragePlugin.MCAP) as w:
        connections: dict = {}

        def write(topic: str, msgtype: str, ns: int, msg, qos=()) -> None:
            c = connections.get(topic)
            if c is None:
                c = connections[topic] = w.add_connection(topic, msgtype, typestore=ts,
                                                          offered_qos_profiles=qos)
            w.write(c, ns, ts.serialize_cdr(msg, msgtype))
            counts[topic] = counts.get(topic, 0) + 1

        def transform(h, parent: str, child: str, t, q):
            return T["geometry_msgs/msg/TransformStamped"](
                header=T["std_msgs/msg/Header"](stamp=h.stamp, frame_id=parent),
                child_frame_id=child, transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=t.x, y=t.y, z=t.z),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q.x, y=q.y, z=q.z, w=q.w)))

        for e in rec.events:
            kind = rec.calls[e.call].answer_type if e.kind == "answer" else ""
            if kind == WORLD_CONFIG and rec.calls[e.call].rpc.endswith("/Configure"):
                tfs = static_transforms(rec.decode(rec.message_class(WORLD_CONFIG), e.data, e.ns,
                                                   e.file)).transforms
                if tfs:
                    write("/tf_static", TF, e.ns, T[TF](transforms=[
                        transform(header(0), x.parent_frame_id, x.child_frame_id,
                                  x.translation, x.rotation) for x in tfs]), (LATCHED,))
            if Fused is None or kind != FUSED_POSE:
                continue
            f = rec.decode(Fused, e.data, e.ns, e.file)
            if f.HasField("error") or not f.HasField("pose") or len(f.covariance) != 36:
                continue
            p, o = f.pose.position, f.pose.orientation
            cov = lie.cov_to_ros(dq.from_pose([o.w, o.x, o.y, o.z], [p.x, p.y, p.z]),
                                 np.asarray(f.covariance).reshape(6, 6))
            try:
                h = header(time_ns(f.time))
            except ValueError as ex:
                raise ValueError(f"the fused pose of {f.body!r} at {e.ns} ns: {ex}") from None
            write(f"/fused/{f.body}/pose", POSE, e.ns, T[POSE](
                header=h, pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=pose(p, o), covariance=cov.ravel())))
            write("/tf", TF, e.ns, T[TF](transforms=[transform(h, WORLD, f.body, p, o)]))
            paths.setdefault(f.body, []).append((e.ns, h, pose(p, o)))
        for body, poses in paths.items():
            ns, h, _ = poses[-1]
            write(f"/fused/{body}/path", PATH, ns, T[PATH](header=h, poses=[
                T["geometry_msgs/msg/PoseStamped"](header=ph, pose=q) for _, ph, q in poses]))
        if rec.plans:
            Poses = rec.message_class("foxglove.PosesInFrame")
            for name, ns, data in rec.plans:
                m = rec.decode(Poses, data, ns)
                write(f"/plans/{name}", PATH, ns, T[PATH](header=header(ns), poses=[
                    T["geometry_msgs/msg/PoseStamped"](header=header(ns),
                                                       pose=pose(q.position, q.orientation))
                    for q in m.poses]))
    return counts
