"""Which view ``dqpose handeye capture`` takes next: a spread of rotations first, then the
solver's next-best pose among candidate views (``--choose``)."""
from __future__ import annotations

CHOICES = ("next-best", "spread", "random")
_CANDIDATES = 200        # candidate views the next one is chosen from
_SPREAD_FIRST = 3        # views chosen for their spread of rotations before the solver chooses


class ViewPlan:
    """The views taken so far and the choice of the next (spread first, then next-best)."""

    def __init__(self, setup: str, start_flange, start_detection, board, rng,
                 choose: str = "next-best"):
        import numpy as np

        from dqpose import dq
        from dqpose.drivers.sim.camera import random_view
        from dqpose.handeye.setups import EYE_IN_HAND
        self.setup = setup
        start_view = start_detection.pose
        self.flanges, self.views = [start_flange], [start_view]
        self.covariances = [start_detection.covariance]
        # A first guess: the camera at the flange (eye-in-hand) or the board at the flange
        # (eye-to-hand); the solver's answer replaces it once there is one.
        ident = dq.from_pose(np.array([1.0, 0, 0, 0]), np.zeros(3))
        if setup == EYE_IN_HAND:
            self.x = ident
            self.z = dq.mul(dq.mul(start_flange, self.x), start_view)
        else:
            self.z = ident
            self.x = dq.mul(dq.mul(start_flange, self.z), dq.inv(start_view))
        d = float(np.linalg.norm(dq.to_pose(start_view)[1]))
        self.candidates = [random_view(rng, board, distance=(0.8 * d, 1.25 * d),
                                       max_tilt_deg=40.0, max_roll_deg=60.0)
                           for _ in range(_CANDIDATES)]
        self.calibration = None
        self.choose = choose
        self.taken = 1           # views taken, the start's included (detected or not)

    def add(self, flange, detection) -> None:
        import numpy as np

        from dqpose import handeye
        self.flanges.append(flange)
        self.views.append(detection.pose)
        self.covariances.append(detection.covariance)
        if len(self.views) > _SPREAD_FIRST:
            try:
                self.calibration = handeye.calibrate(
                    np.array(self.flanges), np.array(self.views), self.setup,
                    camera_covariance=np.array(self.covariances))
                self.x, self.z = self.calibration.x, self.calibration.z
            except ValueError:      # not yet determined: keep the guess and the spread rule
                self.calibration = None

    def drop(self, k: int) -> None:
        self.candidates.pop(k)

    def rule(self) -> str:
        """How the next view is chosen: the solver's next-best pose once it has an answer, the
        view whose rotation is farthest from every view taken before (``choose`` "spread":
        always), or the candidates as they come (``choose`` "random")."""
        if self.choose == "random":
            return "random"
        if self.choose == "next-best" and self.calibration is not None:
            return "next-best pose"
        return "rotation spread"

    def order(self, flanges) -> list:
        """Candidate indices, best first, by :meth:`rule`."""
        import numpy as np
        rule = self.rule()
        if rule == "random":
            return list(range(len(flanges)))
        if rule == "next-best pose":
            from dqpose import handeye
            return list(handeye.next_best_pose(self.calibration, np.array(self.flanges),
                                               np.array(self.views), np.array(flanges)))
        from dqpose.drivers.base import pose_delta
        gaps = [min(pose_delta(c, v)[1] for v in self.views) for c in self.candidates]
        return list(np.argsort(gaps)[::-1])
