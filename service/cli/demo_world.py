"""``dqpose demo world``: one shared world fed by three producers in three processes: two
simulated ChArUco cameras (each in a process of its own, rendering and detecting the board the
simulated UR holds) and the simulated UR (its controller read through ur_rtde here), all
publishing into one server's ``World``; a subscriber prints the fused board ("box") pose against
the truth, and a ``Lookup`` gives the box in the tool frame (against the known mount). The
world is a frame tree (:mod:`dqpose.cli.demo_world_tree`): a table fixed in it, and a fourth
camera riding on the arm's tool that sees a mug on the table, looked up in the table's frame.

Measurement time is the host's clock (``time.time()``), which every producer here shares; the
arm holds still at its home pose, the cameras see it from either side (the scene of ``dqpose
demo fusion``)."""
from __future__ import annotations

import argparse
import contextlib
import math
import multiprocessing
import queue
import threading
import time

import numpy as np

from dqpose import dq, lie

ARM_RATE = 50.0            # arm reads published per second
CAMERA_RATE = 10.0         # frames per second per camera
ANSWER_RATE = 10.0         # fused answers per second of measurement time
ARM_SIGMA = (2e-3, 1e-3)   # rad, m: the arm's reading noise (one sigma per axis)
WINDOW = 0.5               # s: the world's window
MAX_DELAY = 0.15           # s of measurement time the world waits for a source that lags


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("demo world")
    g.add_argument("--seconds", type=float, default=4.0,
                   help="demo world: seconds the producers publish (default: %(default)s)")


def camera_process(target: str, name: str, E: np.ndarray, T_true: np.ndarray, ready, go,
                   start, seconds: float, seed: int, newest) -> None:
    """A camera in a process of its own: renders the board at ``T_true`` (world frame) from its
    extrinsic ``E`` every 1/CAMERA_RATE s from ``start.value`` (set once every producer is
    ``ready``; ``go`` says it is), detects it and publishes each detection, stamped with the
    clock, as a measurement of "box" from source ``name``; ``newest``: the time of the last one
    published."""
    from dqpose.drivers.camera import CharucoCamera
    from dqpose.drivers.sim.camera import BoardRenderer
    from dqpose.rpc.client import Batch, Client

    intr = _intrinsics()
    renderer = BoardRenderer(intrinsics=intr, pixels_per_metre=5000.0)
    cam = CharucoCamera(intr, renderer.board, name=name)
    rng = np.random.default_rng(seed)
    T_cam_box = dq.mul(dq.inv(E), T_true)
    cam.detect(renderer.render(T_cam_box, blur=0.8, noise=6.0, rng=rng))   # the slow first one
    ready.set()
    go.wait(120)
    t0 = start.value

    def frames():
        k = 0
        while (t := t0 + k / CAMERA_RATE) < t0 + seconds:
            time.sleep(max(0.0, t - time.time()))
            d = cam.detect(renderer.render(T_cam_box, blur=0.8, noise=6.0, rng=rng))
            k += 1
            if hasattr(d, "covariance"):
                newest.value = t
                yield Batch(d.pose[None], d.covariance[None], None, [name], ["box"],
                            np.array([t]))

    with Client(target) as c:
        for ack in c.publish(frames(), producer=name):
            for _, _, details in ack.errors:
                print(f"{name}: {details}", flush=True)


def _intrinsics():
    from dqpose.drivers.camera import Intrinsics
    return Intrinsics(K=np.array([[400.0, 0, 199.5], [0, 400.0, 149.5], [0, 0, 1]]),
                      size=(400, 300))


def last_tick(newest: dict, rate: float = ANSWER_RATE, body: str = "box") -> float:
    """The time of ``body``'s last tick a subscription at ``rate`` is answered once no more
    measurements come, given each source's newest measurement time (``-inf``: none): the last
    at or before the body's horizon (:mod:`dqpose.world_ticks`, the world's rule); ``-inf``
    when there is none."""
    from dqpose.world_ticks import Schedule, horizon
    h = horizon({k: t for k, t in newest.items() if math.isfinite(t)}, MAX_DELAY)
    if not math.isfinite(h):
        return -math.inf
    schedule = Schedule(rate)
    due = schedule.due(body, h, h - WINDOW)
    return schedule.time(body, due[-1]) if len(due) else -math.inf


def _follow(client, T_true, start: float, seconds: float, producers, newest, out) -> list:
    """Prints a row per answer of a subscription to the box (its error against ``T_true``)
    until the world's last once every one of ``producers`` (threads, processes) has ended:
    :func:`last_tick` of the measurement times they published last (``newest``: a shared
    ``Value`` by source). A busy machine's
    stalled controller ends the arm's reads before the cameras' last frames, and then the
    box's data end before the tick at ``seconds - 0.2`` the demo waited for: it never came
    (the subscription's deadline ended the demo with a traceback). Returns ``(mm, deg)`` of
    each fused answer."""
    from dqpose.cli.demo_fusion_scene import pose_error
    from dqpose.cli.readout import Readout
    answers: queue.Queue = queue.Queue()

    def read():         # a thread: the stream's next answer is awaited while producers end
        try:
            for a in client.subscribe(["box"], ANSWER_RATE, timeout=seconds + 15.0):
                answers.put(a)
        except BaseException as e:
            answers.put(e)
        answers.put(None)
    threading.Thread(target=read, name="demo world answers", daemon=True).start()
    table = Readout(start=start, delay=True)
    print(f"the fused box, times in s since the producers started; delay: from the "
          f"measurement time to this row\n{table.header(' error vs truth mm deg')}",
          file=out, flush=True)
    errors: list = []
    end, last = None, -math.inf
    while end is None or last < end:
        try:
            a = answers.get(timeout=0.1)
        except queue.Empty:
            pass                    # none yet: have the producers ended?
        else:
            if a is None:
                break
            if isinstance(a, BaseException):
                raise a
            extra = ""
            if a.fused is not None:
                deg, mm = pose_error(a.fused.mean, T_true)
                errors.append((mm, deg))
                extra = f" {mm:14.2f} {deg:7.3f}"
            print(table.row(a, extra), file=out, flush=True)
            last = a.time
        if end is None and not any(p.is_alive() for p in producers):
            end = last_tick({n: v.value for n, v in newest.items()})
    return errors


def _configure(client, offset, extrinsics, names, rng) -> None:
    """The world: the arm (its flange the body "tool", the board at ``offset`` on it, its base
    the world), the cameras at ``extrinsics``, the tree's wrist camera and table."""
    from dqpose.cli import demo_world_tree
    from dqpose.fusion import Source
    tree = demo_world_tree.frames(rng)
    client.configure_world(
        [Source("ur", body_offset=offset), Source("ur_flange")]
        + [Source(n, extrinsic=E) for n, E in zip(names, extrinsics)] + tree["sources"],
        arms={"ur": "ur_flange"}, window=WINDOW, max_delay=MAX_DELAY,
        twist_covariance=np.diag([0.05] * 3 + [0.02] * 3) ** 2, statics=tree["statics"])


def _publisher(target: str, reads, producer: str) -> threading.Thread:
    """A thread publishing ``reads`` (``Batch`` es) as ``producer``, started."""
    from dqpose.rpc.client import Client

    def run():
        with Client(target) as c:
            for _ in c.publish(reads, producer=producer):
                pass
    thread = threading.Thread(target=run, daemon=True, name=f"demo world {producer}")
    thread.start()
    return thread


def main(args: argparse.Namespace, out=None) -> int:
    from dqpose import drivers
    from dqpose.cli.common import local_server, open_arm
    from dqpose.cli.demo_fusion_scene import BOARD_OFFSET, HOME, cameras
    from dqpose.cli.demo_world_tree import looked_up, report, wrist_reads
    from dqpose.drivers.base import ArmError
    from dqpose.drivers.sim.camera import BoardRenderer
    from dqpose.drivers.sim.ur import URSimProcess
    from dqpose.rpc.client import Batch, Client

    seconds = args.seconds
    offset = dq.from_pose(np.array(BOARD_OFFSET[0]), np.array(BOARD_OFFSET[1]))
    rng = np.random.default_rng(0)
    cov = np.diag(np.repeat(np.square(ARM_SIGMA), 3))
    with contextlib.ExitStack() as stack:
        target = getattr(args, "server", None) or stack.enter_context(local_server())
        sim = stack.enter_context(URSimProcess())
        sim.set_pose(np.array(HOME))
        spec = f"ur:{sim.host}"
        arm = stack.enter_context(open_arm(spec, process=drivers.process_problem(spec) is None,
                                           simulated=True))
        _, T_flange = arm.tool_pose()
        T_true = dq.mul(T_flange, offset)
        board = BoardRenderer(intrinsics=_intrinsics(), pixels_per_metre=5000.0).board
        extrinsics = cameras(T_true, board, _intrinsics())
        client = stack.enter_context(Client(target))
        names = ("camera1", "camera2")
        _configure(client, offset, extrinsics, names, rng)
        ctx = multiprocessing.get_context("spawn")
        go, shared_start = ctx.Event(), ctx.Value("d", 0.0)
        ready = [ctx.Event() for _ in names]
        newest = {n: ctx.Value("d", -math.inf) for n in ("ur", *names, "wrist")}
        procs = [ctx.Process(target=camera_process, args=(target, n, E, T_true, r, go,
                                                         shared_start, seconds, k + 1,
                                                         newest[n]),
                             daemon=True)
                 for k, (n, E, r) in enumerate(zip(names, extrinsics, ready))]
        for p in procs:
            p.start()
            stack.callback(p.join, 10)
        for r, p in zip(ready, procs):      # each camera's start-up (imports, first detection)
            if not r.wait(120):
                raise RuntimeError(f"the camera process {p.pid} did not start in 120 s")
        start = shared_start.value = time.time() + 0.2
        go.set()

        def arm_reads():
            k = 0
            while (t := start + k / ARM_RATE) < start + seconds:
                time.sleep(max(0.0, t - time.time()))
                k += 1
                try:
                    _, T = arm.tool_pose()
                except ArmError as e:
                    # a reading the controller did not give in time is one the world does
                    # without (it fuses what arrives); the demo goes on and says so
                    print(f"arm: no reading at {t - start:.2f} s ({e})", file=out, flush=True)
                    continue
                reading = dq.mul(T, lie.se3_exp(rng.normal(0.0, 1.0, 6)
                                                * np.repeat(ARM_SIGMA, 3)))
                newest["ur"].value = t
                yield Batch(np.array([reading, reading]), np.array([cov, cov]), None,
                            ["ur", "ur_flange"], ["box", "tool"], np.array([t, t]))

        publishers = [_publisher(target, arm_reads(), "ur"), _publisher(
            target, wrist_reads(T_flange, start, seconds, newest["wrist"],
                                np.random.default_rng(1)), "wrist")]
        errors = _follow(client, T_true, start, seconds, [*publishers, *procs],
                         {n: v for n, v in newest.items() if n != "wrist"}, out)
        for p in publishers:
            p.join(seconds + 10)
        print(file=out)
        mm, _ = looked_up(client, "tool", "box", offset, start, "box in the tool frame",
                          "the mount", out)
        mug = report(client, start, out)
    return _summary(errors, mm, mug, out)


def _summary(errors: list, mm: float, mug: tuple[float, float], out) -> int:
    """The fused box's errors (``(mm, deg)`` each), the looked-up one's ``mm`` and the mug's
    ``(mm, sigma mm)`` on the table summed up, then the verdict; the exit code."""
    if not errors:
        print("dqpose demo world: no fused answer arrived", file=out)
        return 1
    e = np.array(errors)
    print(f"fused box: {len(e)} answers, median error {np.median(e[:, 0]):.2f} mm "
          f"{np.median(e[:, 1]):.3f} deg", file=out)
    print(f"verdict: producers in three processes fed one world, and its fused box stayed "
          f"within {np.median(e[:, 0]):.2f} mm (median) of the truth; looked up in the tool "
          f"frame it is {mm:.2f} mm from where it is mounted; the mug the wrist camera on the tool "
          f"sees is {mug[0]:.2f} mm from where it stands on the static table (1 sigma "
          f"{mug[1]:.2f} mm)", file=out)
    return 0
