"""Device drivers (arms, pose sources) and their simulators.

Backends are chosen by name, as python-can chooses a bus by ``interface``:
``open_arm("ur:192.168.1.10")``, ``open_arm("piper:socketcan:can0")``,
``open_source("charuco:/path/to/images", intrinsics="camera.yaml")``. The text after the first
colon is the backend's channel; keyword arguments go to the backend (``limits=``, ...). An arm's
name is an arm spec (:mod:`dqpose.drivers.spec`): ``KIND:TARGET[?key=value&...]``, its keys those of
:data:`ARM_KEYS`. Backend modules are imported only when opened.
"""
from __future__ import annotations

import importlib
from typing import Optional

from dqpose.drivers.backends import ARMS, SOURCES, split_backend
from dqpose.drivers.spec import ARM_KEYS, ArmSpec, arm_class, open_here, parse_arm_spec

__all__ = ["ARMS", "SOURCES", "ARM_KEYS", "ArmSpec", "parse_arm_spec", "open_arm", "open_source",
           "process_problem"]


def _open(kind: str, table: dict, spec: str, kwargs: dict):
    module, cls, channel = _backend(kind, table, spec)
    return getattr(importlib.import_module(module), cls).open(channel, **kwargs)


def _backend(kind: str, table: dict, spec: str) -> tuple[str, str, str]:
    """(module, class, channel) of ``spec``, else ``ValueError`` naming ``kind``."""
    if not isinstance(spec, str):
        raise ValueError(f"{kind}: expected '<backend>:<channel>', got {spec!r}")
    name, channel = split_backend(kind, table, spec)
    module, cls = table[name].split(":")
    return module, cls, channel


def process_problem(spec: str) -> Optional[str]:
    """Why the arm ``spec`` cannot live in a process of its own on this machine (the
    processor's store order, or a connection that does not reach across processes), or None."""
    from dqpose.drivers.armproc import check_store_order
    from dqpose.drivers.base import ArmError
    try:
        check_store_order()
    except ArmError as e:
        return str(e)
    s = parse_arm_spec(spec)
    return arm_class(s).process_problem(s.target)


def open_arm(spec, process: bool = False, **kwargs):
    """An :class:`~drivers.base.Arm` by its spec (a string or an :class:`ArmSpec`):
    ``"ur:<host>"`` or ``"piper:<python-can interface>:<channel>"``, with any
    ``?key=value&...`` of :data:`ARM_KEYS`; those and ``kwargs`` (which win) are the backend's
    keyword arguments. It returns once the arm's first state has arrived (``tool_pose()`` works
    right away), else raises :class:`~drivers.base.ArmError` saying why.

    ``process=True``: the arm lives in a child process of its own, where an
    :class:`~drivers.executor.Executor` on it runs its control loop
    (:class:`dqpose.drivers.armproc.ArmProcess`; its bus must reach across processes: not
    python-can's ``virtual``)."""
    s = spec if isinstance(spec, ArmSpec) else parse_arm_spec(spec)
    if process:
        from dqpose.drivers.armproc import ArmProcess
        return ArmProcess(s.channel, **{**s.options, **kwargs})
    return open_here(s, **kwargs)


def open_source(spec: str, **kwargs):
    """A :class:`~drivers.base.PoseSource` by name: ``"charuco:<folder, video or camera index>"``
    (keyword ``intrinsics=`` is required)."""
    return _open("source", SOURCES, spec, kwargs)
