"""What the Execute robustness tests share: the simulated arms as a server drives them (each in a
process of its own, as ``dqpose serve`` opens them where it can), what their simulators saw, a
real server on 127.0.0.1 owning them, and plans that start where an arm is."""
from __future__ import annotations

import contextlib
import random
import threading

import numpy as np
import pytest

from dqpose import dq, trajectory
from tests._polling import wait_until
from tests.rpc._grpc_server import ServerThread

#: within every arm's own limits (the UR's and the PiPER's: 0.25 m/s, 1 rad/s, 2 m/s^2, 4 rad/s^2)
LIMITS = trajectory.Limits(max_linear_velocity=0.1, max_angular_velocity=0.5,
                           max_linear_acceleration=0.5, max_angular_acceleration=1.0,
                           max_linear_jerk=5.0, max_angular_jerk=10.0)
#: the arms' data watchdog: a shared, loaded test machine pauses a simulator for longer than a
#: real controller's 0.1 s now and then
STALE_AFTER = 0.5
#: how far behind its set-points an arm may follow: a starved simulator trails further here
TRACKING_LAG = 0.15
#: a plan of several seconds over a few centimetres: long enough to interfere with
SLOW = trajectory.Limits(max_linear_velocity=0.02, max_angular_velocity=0.1,
                         max_linear_acceleration=0.2, max_angular_acceleration=0.5,
                         max_linear_jerk=2.0, max_angular_jerk=5.0)


def offset(pose: np.ndarray, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> np.ndarray:
    """``pose`` moved by (dx, dy, dz) in the base frame, same orientation."""
    q, t = dq.to_pose(pose)
    return dq.from_pose(q, t + [dx, dy, dz])


def distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(dq.to_pose(a)[1] - dq.to_pose(b)[1]))


class URRig:
    """The simulated UR (its hooks: protective stop, a paused data stream, the commands it
    received) and the arm on it through ur_rtde, in a process of its own."""

    name = "ur"

    def __init__(self, process: bool = True, sim_args: tuple = (), **arm_options):
        pytest.importorskip("rtde_control")
        from dqpose import drivers
        from dqpose.drivers.rotvec import pose_from_rotvec
        from dqpose.drivers.sim import ur as ursim
        self._ursim = ursim
        self.sim = ursim.URSimProcess(args=sim_args)
        self.home_rotvec = np.array([0.4, -0.1, 0.3, 2.2, 2.2, 0.0])
        self.home = pose_from_rotvec(self.home_rotvec)
        self.arm = drivers.open_arm(f"ur:{self.sim.host}", process=process,
                                    stale_after=STALE_AFTER, tracking_lag=TRACKING_LAG,
                                    **arm_options)
        self._mark = 0

    def reset(self) -> None:
        """At home, at rest, faults cleared; what the controller receives from here on is the
        test's."""
        self.sim.protective_stop(False)
        # a UR's protective stop latches until released and recovered (a person's decision on
        # a real cell, the test's here)
        assert wait_until(self._recovered, timeout=5, poll=0.05)
        self.arm.stop()
        self.sim.set_pose(self.home_rotvec)
        assert wait_until(lambda: distance(self.arm.tool_pose()[1], self.home) < 1e-9
                          and not self.arm.state().faults, timeout=5)
        self._mark = self.sim.log()["next"]

    def _recovered(self) -> bool:
        from dqpose.drivers.base import ArmError
        if not self.arm.state().faults:
            return True
        try:
            self.arm.recover()
        except ArmError:
            return False
        return not self.arm.state().faults

    def fault(self) -> None:
        self.sim.protective_stop(True)

    def lose_data(self, seconds: float) -> None:
        self.sim.call("pause_stream", seconds=seconds)

    def setpoints(self) -> int:
        """Servo set-points the controller received since :meth:`reset`."""
        return sum(1 for e in self.sim.log(self._mark, keys=["cmd"])["entries"]
                   if e["cmd"] == self._ursim.SERVOL)

    def moving(self) -> bool:
        st = self.sim.state()
        return st["moving"] or st["servoing"]

    def pose(self) -> np.ndarray:
        from dqpose.drivers.rotvec import pose_from_rotvec
        return pose_from_rotvec(self.sim.state()["pose"])

    def close(self) -> None:
        self.arm.close()
        self.sim.close()


class PiperRig:
    """The simulated PiPER on python-can's udp_multicast bus (in this process, with its hooks),
    and the arm on it in a process of its own."""

    name = "piper"

    def __init__(self, process: bool = True, **arm_options):
        pytest.importorskip("msgpack")      # python-can's udp_multicast encodes with it
        import can

        from dqpose import drivers
        from dqpose.drivers.sim.piper import PiperSim
        group = f"239.74.{random.randrange(256)}.{random.randrange(1, 255)}"
        self.bus = can.Bus(interface="udp_multicast", channel=group)
        self.sim = PiperSim(self.bus).start()
        self.home = self.sim.pose
        self.arm = drivers.open_arm(f"piper:udp_multicast:{group}", process=process,
                                    stale_after=STALE_AFTER, tracking_lag=TRACKING_LAG,
                                    **arm_options)
        self._mark = 0

    def reset(self) -> None:
        self.sim.clear_faults()
        self.sim.pause_feedback(False)
        self.sim.set_pose(self.home)
        assert wait_until(lambda: distance(self.arm.tool_pose()[1], self.home) < 1e-6
                          and not self.arm.state().faults, timeout=5)
        self.arm.stop()
        assert wait_until(lambda: self.sim.target is not None
                          and distance(self.sim.target, self.home) < 1e-6, timeout=5)
        self._mark = len(self.sim.log)

    def fault(self) -> None:
        self.sim.emergency_stop()

    def lose_data(self, seconds: float) -> None:
        self.sim.pause_feedback(True)
        threading.Timer(seconds, self.sim.pause_feedback, (False,)).start()

    def setpoints(self) -> int:
        return sum(1 for _, kind, _ in self.sim.log[self._mark:] if kind == "end_pose")

    def moving(self) -> bool:
        target = self.sim.target
        return target is not None and distance(self.sim.pose, target) > 1e-9

    def pose(self) -> np.ndarray:
        return self.sim.pose

    def close(self) -> None:
        self.arm.close()
        self.sim.close()
        self.bus.shutdown()


RIGS = {"ur": URRig, "piper": PiperRig}


def serve(rigs, **config):
    """A server on 127.0.0.1 owning ``rigs``' arms by their names (the executor as ``dqpose
    serve`` makes it)."""
    from dqpose.drivers.executor import Executor
    from dqpose.rpc.server import ServerConfig
    return ServerThread(ServerConfig(port=0, arms={r.name: r.arm for r in rigs},
                                     executor=Executor, **config))


@contextlib.contextmanager
def served_rigs(**rig_options):
    """One rig of each kind (``rig_options`` passed to each) and a server owning their arms:
    ``({name: rig}, server)``; the rigs closed afterwards."""
    made = []
    try:
        for cls in RIGS.values():
            made.append(cls(**rig_options))
        with serve(made) as server:
            yield {r.name: r for r in made}, server
    finally:
        for r in made:
            r.close()


@pytest.fixture(scope="module")
def rigs():
    """:func:`served_rigs` for a module's tests (import it with :func:`rig`)."""
    with served_rigs() as made:
        yield made


@pytest.fixture(params=list(RIGS))
def rig(rigs, request):
    """Each arm in turn, reset: ``(rig, a Client of the server, the server)``."""
    from dqpose.rpc.client import Client

    by_name, server = rigs
    r = by_name[request.param]
    r.reset()
    with Client(server.target) as c:
        yield r, c, server


def run_out(it):
    """The records of an Execute iterator ``it`` and the RpcError it ended with (None: OK)."""
    from dqpose.rpc.client import RpcError

    got = []
    try:
        for fb in it:
            got.append(fb)
    except RpcError as e:
        return got, e
    return got, None


def block(server) -> threading.Event:
    """Holds the server's event loop (a handler that never yields, as a hung server would)
    until the returned event is set."""
    import asyncio
    release = threading.Event()
    started = threading.Event()

    async def hang():
        started.set()
        release.wait(30)

    asyncio.run_coroutine_threadsafe(hang(), server.loop)
    assert started.wait(10)
    return release
