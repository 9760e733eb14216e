"""``dqpose export FILE.mcap --ros2 OUT_DIR``: a recording as a ROS 2 bag (rosbag2, MCAP storage)
for ``ros2 bag play`` and RViz: ``PoseWithCovarianceStamped`` per fused pose (ROS's covariance
convention), ``/tf``, ``nav_msgs/Path`` of each body and plan (``dqpose.record.ros2``)."""
from __future__ import annotations

import os

from dqpose.cli.common import fail, missing_extra


def configure(name: str, p) -> None:
    p.description = __doc__.split("\n\n")[0].replace("``", "")
    p.add_argument("file", metavar="FILE.mcap", help="a recording (dqpose serve --record)")
    p.add_argument("--ros2", metavar="OUT_DIR", required=True,
                   help="the bag's folder (must not exist yet)")
    p.set_defaults(func=_export)


def _export(args) -> int:
    from dqpose.errors import MissingExtra, require

    try:
        require("mcap", "foxglove_schemas_protobuf", "rosbags")
        from dqpose.record.reader import read
        from dqpose.record.ros2 import export
    except (MissingExtra, ModuleNotFoundError) as e:
        return missing_extra("export", e)
    if os.path.exists(args.ros2):
        return fail("export", f"--ros2 {args.ros2}: exists already (rosbag2 writes a new folder)")
    try:
        rec = read(args.file)
        counts = export(rec, args.ros2)
    except OSError as e:
        return fail("export", f"{e.filename or args.file}: {e.strerror or e}")
    except ValueError as e:
        return fail("export", str(e))
    for topic, n in counts.items():
        print(f"{topic}: {n}")
    print(f"wrote {sum(counts.values())} messages to {args.ros2}")
    return 0
