"""The simulated devices ``dqpose serve --sims`` starts beside the server (``make run``), so a
fresh machine has something to point the drivers at.

- ``ur``: a simulated UR e-series controller (RTDE 30004, dashboard 29999, script 30003) on the
  first free loopback address from 127.0.0.20, in its own process:
  ``drivers.open_arm("ur:<host>")`` or ``rtde_receive.RTDEReceiveInterface(host)``.
- ``piper``: a simulated PiPER in its own process on python-can's ``udp_multicast`` bus, on a
  multicast group of its own (so two fleets on one machine do not share an arm):
  ``drivers.open_arm("piper:udp_multicast:<group>")``.
- ``camera``: views of the default ChArUco board from 20 random poses, rendered into a folder
  with ``poses.json`` (the true ``T_camera_board`` of each and the intrinsics):
  ``drivers.open_source("charuco:<folder>", intrinsics="<folder>/poses.json")``.

Each ``info`` entry's ``use`` is that call (an ``error`` instead says why a device that needs a
missing package was left out). :meth:`Fleet.target` is what an arm spec's TARGET ``sim`` stands
for (``dqpose serve --sims --arm piper=piper:sim``): the PiPER's group is random, so a user could
not name it. The simulator processes end with the server, even when it is killed; the camera
folder is removed on a clean exit only.
"""
from __future__ import annotations

import contextlib
import os
import random
import tempfile
from typing import Optional

DEVICES = ("ur", "piper", "camera")


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
        self._targets: dict[str, str] = {}     # arm kind -> its simulator's target

    def __enter__(self) -> "Fleet":
        super().__enter__()
        try:
            if "ur" in self.devices:
                from dqpose.drivers.sim.ur import URSimProcess
                try:
                    sim = self.enter_context(URSimProcess())
                except RuntimeError as e:   # as OSError: the CLI reports it in one line
                    raise OSError(f"sims: {e}") from None
                self.info.append({"device": "ur", "host": sim.host, "spec": f"ur:{sim.host}",
                                  "use": f"drivers.open_arm('ur:{sim.host}')"})
                self._targets["ur"] = sim.host
            if "piper" in self.devices:
                self.info.append(self._piper())
            if "camera" in self.devices:
                self.info.append(self._camera())
        except BaseException:
            self.close()
            raise
        return self

    def target(self, kind: str) -> str:
        """The TARGET of the simulated arm of ``kind`` (``"ur"``: its host; ``"piper"``:
        ``udp_multicast:<group>``); ``ValueError`` saying why there is none."""
        if kind in self._targets:
            return self._targets[kind]
        why = next((i["error"] for i in self.info if i["device"] == kind and "error" in i),
                   None)
        if why:
            raise ValueError(f"the simulated {kind} was {why}")
        arms = ", ".join(self._targets) or "none"
        raise ValueError(f"no simulated {kind} arm (the simulated arms: {arms})")

    def _piper(self) -> dict:
        import importlib.util

        from dqpose.drivers.sim.piper import PiperSimProcess
        if importlib.util.find_spec("msgpack") is None:
            # python-can's udp_multicast encodes frames with msgpack (python-can[multicast])
            return {"device": "piper", "error": "not started: python-can's udp_multicast bus "
                    "needs msgpack (pip install 'python-can[multicast]')"}
        # 239.74.0.0/16 is organisation-local; a random group keeps fleets apart
        group = f"239.74.{random.randrange(256)}.{random.randrange(1, 255)}"
        try:
            sim = self.enter_context(PiperSimProcess("udp_multicast", group))
        except RuntimeError as e:
            raise OSError(f"sims: {e}") from None
        self._targets["piper"] = f"udp_multicast:{group}"
        return {"device": "piper", "bus": "udp_multicast", "channel": group, "pid": sim.pid,
                "spec": sim.spec, "use": f"drivers.open_arm('{sim.spec}')"}

    def _camera(self) -> dict:
        import argparse

        from dqpose.drivers.sim import camera
        folder = self.camera_dir
        if folder is None:
            folder = self.enter_context(tempfile.TemporaryDirectory(prefix="dqpose-camera-"))
        args = argparse.Namespace(out=folder, count=20, seed=0, blur=0.5, noise=1.0,
                                  intrinsics=None, board=None)
        with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
            if camera.run(args) != 0:
                raise OSError(f"sims: cannot render the camera views into {folder}")
        spec, intrinsics = f"charuco:{folder}", os.path.join(folder, "poses.json")
        return {"device": "camera", "images": folder, "spec": spec,
                "use": f"drivers.open_source({spec!r}, intrinsics={intrinsics!r})"}
