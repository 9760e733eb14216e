"""What the PiPER tests share: the codec's quantisation and random reachable poses."""
import math

import numpy as np

from dqpose.drivers.euler import dq_from_xyz_sxyz

# Half a unit of quantisation per axis: 0.5 um and 0.0005 deg.
POS_Q = math.sqrt(3) * 0.5e-6
ANG_Q = math.radians(0.0005) * 3


def random_poses(rng, n):
    xyz = np.column_stack([rng.uniform(0.1, 0.4, n), rng.uniform(-0.25, 0.25, n),
                           rng.uniform(0.1, 0.4, n)])
    e = np.column_stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-1.4, 1.4, n),
                         rng.uniform(-np.pi, np.pi, n)])
    return dq_from_xyz_sxyz(xyz, e)
