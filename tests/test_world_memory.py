"""dqpose.world's memory after a burst of large fits: the answers it keeps (so that a repeated
question is not fitted again) are bounded by the measurements their fits describe, not only by
their number. Before the bound a world kept up to 4,096 fits whatever their size: the bystander
benchmark's P3 row (1,000-measurement windows answered at every time) left the server 56 MB
above its baseline for good, ~75 bytes a measurement of every fit kept."""
import gc
import tracemalloc

import numpy as np

from dqpose import lie
from dqpose.world import World, WorldOptions


def test_the_fits_a_world_keeps_hold_a_bounded_number_of_measurements():
    n = 1000
    world = World(options=WorldOptions(window=1.0, buffer=10.0))
    poses = lie.se3_exp(1e-3 * np.random.default_rng(0).normal(size=(n, 6)))
    times = np.arange(n) * 1e-3
    world.ingest(["box"] * n, ["cam"] * n, times, poses, np.repeat(np.eye(6)[None] * 1e-6, n, 0))
    gc.collect()
    tracemalloc.start()
    try:
        for t in times[::2]:            # 500 answers, each fusing the 1,000 measurements
            world.pose("box", float(t))
        gc.collect()
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # ~75 bytes of each measurement a fit describes: 500 fits kept would be ~37 MB
    assert held < 8e6, held
