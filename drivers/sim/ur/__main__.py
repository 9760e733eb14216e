"""``python -m dqpose.drivers.sim.ur``: the simulated UR controller (:func:`.cli.main`)."""
import sys

from dqpose.drivers.sim.ur.cli import main

sys.exit(main())
