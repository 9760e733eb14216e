"""The simulated devices ``dqpose serve --sims`` starts beside the server (``make run``), so a
fresh machine has something to point the drivers at.

- ``ur``: a simulated UR e-series controller (RTDE 30004, dashboard 29999, script 30003) on the
  first free loopback address from 127.0.0.20, in its own process:
  ``URArm(host)`` or ``rtde_receive.RTDEReceiveInterface(host)``.
- ``camera``: views of the default ChArUco board from 20 random poses, rendered into a folder
  with ``poses.json`` (the true ``T_camera_board`` of each and the intrinsics):
  ``CharucoCamera(DEFAULT_INTRINSICS, source=folder)``.

The PiPER simulator needs a CAN bus shared between processes (SocketCAN ``vcan0`` on Linux, set up
as root); start it with ``dqpose sim piper --interface socketcan --channel vcan0``.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from typing import Optional

DEVICES = ("ur", "camera")


class Fleet(contextlib.ExitStack):
    """Starts the simulators on entry and stops them on exit; ``info`` lists one dict per device
    (``device`` plus where to reach it)."""

    def __init__(self, devices=DEVICES, camera_dir: Optional[str] = None):
        super().__init__()
        unknown = sorted(set(devices) - set(DEVICES))
        if unknown:
            raise ValueError(f"sims: unknown device {unknown[0]!r}; expected one of "
                             f"{', '.join(DEVICES)}")
        self.devices, self.camera_dir = tuple(devices), camera_dir
        self.info: list[dict] = []

    def __enter__(self) -> "Fleet":
        super().__enter__()
        try:
            if "ur" in self.devices:
                from drivers.sim.ursim import URSimProcess
                try:
                    sim = self.enter_context(URSimProcess())
                except RuntimeError as e:   # as OSError: the CLI reports it in one line
                    raise OSError(f"sims: {e}") from None
                self.info.append({"device": "ur", "host": sim.host,
                                  "use": f"drivers.ur.URArm({sim.host!r})"})
            if "camera" in self.devices:
                self.info.append(self._camera())
        except BaseException:
            self.close()
            raise
        return self

    def _camera(self) -> dict:
        import argparse

        from drivers.sim import camera
        folder = self.camera_dir
        if folder is None:
            folder = self.enter_context(tempfile.TemporaryDirectory(prefix="dqpose-camera-"))
        args = argparse.Namespace(out=folder, count=20, seed=0, blur=0.5, noise=1.0,
                                  intrinsics=None, board=None)
        with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
            if camera.run(args) != 0:
                raise OSError(f"sims: cannot render the camera views into {folder}")
        return {"device": "camera", "images": folder,
                "use": f"drivers.camera.CharucoCamera(drivers.sim.camera.DEFAULT_INTRINSICS, "
                       f"source={folder!r})"}
