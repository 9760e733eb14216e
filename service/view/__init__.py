"""``dqpose.view``: the viewer page of ``dqpose view FILE.mcap`` (the ``[view]`` extra: viser
serves its own three.js page): :mod:`~dqpose.view.timeline` reads a recording into each body's
poses and covariances over time, its plans and its arms; :mod:`~dqpose.view.page` draws them
where :mod:`~dqpose.view.layout` says, on a page :mod:`~dqpose.view.guard` keeps to itself."""
from __future__ import annotations

#: the modules of the [view] extra (with the [record] extra's reader)
MODULES = ("viser", "mcap", "foxglove_schemas_protobuf")
