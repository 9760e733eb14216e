"""The server's bounds on what one request or one stream may cost: the one table of them.

Every field of :class:`Limits` is a limit: its default, unit and meaning are here and nowhere
else; ``ServerConfig.limits`` holds the values a server runs with and ``dqpose serve`` has one
flag per field (the field's name with dashes: ``max_output_rate`` is ``--max-output-rate``,
:func:`add_flags`). A request over a limit is refused before anything of its size is allocated,
with :class:`OverLimit` (gRPC ``RESOURCE_EXHAUSTED``, or an error entry in a stream) naming the
request's field, the limit and its flag (:func:`over`).

Cost model (one core of the 2-core test machine, docs/benchmarks/server-load.md#limits); defaults
keep the costliest legal request near a second of one worker's time:

* StreamFuse: ticks are computed in closed form (no loop over skipped ticks), so a message costs
  its decoding (~7 µs a measurement) plus its answers. An answer fuses its body's window:
  ~13 µs a measurement (constant twist; its message included) and ~0.17 ms around it
  (:func:`answer_cost`). ``max_fused_per_request`` bounds the sum over one message's answers
  (75,000: ~1 s); ticks beyond it are skipped, the latest kept, and said so (:class:`Budget`,
  which bounds a World Publish request's Subscribe answers, all its subscribers', alike: the
  costliest legal requests took 0.3-0.9 s of a server's CPU, docs/benchmarks/world.md).
  A tick is exact in floating point while ``|time| * output_rate`` stays below 2^50
  (``max_time * max_output_rate``, checked at start).
* A stream keeps at most ``max_stream_measurements`` (100,000: ~40 MB) in its windows, a body
  at most ``max_window`` (1,000: an answer of ~80 kB, ~5 ms to fuse); finding a body's window
  scans the stream's (~0.1 ms at 100,000), within ``ANSWER_ROWS``.
* Robust fits: the consensus compares every measurement with at most 64 candidate centres
  (C, ~0.8 µs a pair), then the gate refits (~4 µs a measurement, in C) at most 50 times:
  ``max_robust`` 2,000 measurements is ~0.1 s typically, ~0.7 s at worst.
* A fit with ``acceleration_psd`` solves a dense ``6n × 6n`` system (NumPy, O(n³)) around a
  motion fit of its own: ~4 ms at 5 measurements, ~70 ms at 50, ~120 ms at 100 (load 4);
  ``max_correlated`` 100, times the gate's 50 refits at worst. It always runs in the worker
  pool (a Fuse that asks for it, and :data:`CORRELATED_ROWS` in a StreamFuse answer's cost).
* HandEye Calibrate compares every two pairs (the all-pairs closed form, the screw-congruence
  and duplicate checks, per-sample medians over pairs: O(n²) by construction), then refines in
  O(n): ``max_pairs`` 200 is ~0.7 s. The corner level is linear in the corners (its normal
  equations solved view by view): ~0.1 ms a corner, ``max_corners`` 10,000 ~1 s.
* Trajectories: a plan costs ~16 µs a waypoint (10,000: 0.16 s) and ~20 µs a streamed sample
  (``max_plan_samples`` 100,000: ~2 s of the worker pool, the writes on the event loop ~50 µs
  each); Execute's ``max_execute_waypoints`` is Plan's bound on waypoints.
* Everything else is linear in the request's size, bounded by ``max_poses`` and
  ``max_message_bytes``; a request larger than ``INLINE_BYTES`` runs in the worker pool.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from dqpose.errors import FieldError

#: a request of at most this many bytes is served on the event loop (its work, linear in its
#: size, stays under ~1 ms); a larger one in the worker pool (``workers``)
INLINE_BYTES = 4096
#: StreamFuse answers costing at most this many measurements (:func:`answer_cost`: ~1 ms) are
#: fused on the event loop, costlier ones in the worker pool
INLINE_ROWS = 75


def answer_cost(rows: int, robust: bool = False, correlated: bool = False) -> int:
    """What fusing a window of ``rows`` measurements into one StreamFuse answer costs, in
    measurements of a plain fit (~13 µs each on the test machine, the answer's message
    included): ~0.17 ms for any answer, 4x the rows for a robust fit, and the dense solve of an
    ``acceleration_psd`` fit (:data:`CORRELATED_ROWS` and ~40 a row around its dense solve)."""
    cost = ANSWER_ROWS + rows * (4 if robust else 1)
    return cost + (CORRELATED_ROWS + 40 * rows + rows ** 3 // 500 if correlated else 0)


#: what an answer costs besides its window's measurements, in measurements (~0.17 ms)
ANSWER_ROWS = 13
#: what an ``acceleration_psd`` fit costs besides its rows, in measurements (~4 ms): measured
#: 4.4 / 4.8 / 17 / 71 / 119 ms at 5 / 10 / 20 / 50 / 100 rows at a load of 4, so even a small
#: one is fused in the worker pool, never on the event loop
CORRELATED_ROWS = 300
#: ticks are exact while |time| * rate stays below this (a double's integers are exact to 2^53)
EXACT_TICKS = 2.0**50


class OverLimit(FieldError):
    """A request over one of the server's :class:`Limits`: ``RESOURCE_EXHAUSTED``. The text
    starts with the request's field, like any :class:`FieldError`, and names the limit and its
    ``dqpose serve`` flag."""


def _limit(default, unit: str, meaning: str, lo=0):
    return field(default=default, metadata={"unit": unit, "meaning": meaning, "lo": lo})


@dataclass(frozen=True)
class Limits:
    """The limits a server enforces (defaults: the cost model in the module docstring)."""

    workers: int = _limit(
        2, "threads", "worker threads shared by every service: what grows with a request runs "
                      "there, off the event loop (a request waits for a free one)", lo=1)
    max_robust: int = _limit(
        2000, "measurements", "measurements in one robust fit (Fuse with options.robust, a "
                              "StreamFuse body's window in a robust stream)", lo=1)
    max_correlated: int = _limit(
        100, "measurements", "measurements in one fit with options.acceleration_psd (its "
                             "cost grows with their cube)", lo=1)
    max_pairs: int = _limit(
        200, "pairs", "HandEye Calibrate: pose pairs per request (its closed form and data "
                      "checks compare every two)", lo=3)
    max_corners: int = _limit(
        10_000, "corners", "HandEye Calibrate: board corners per request, all pairs together",
        lo=4)
    max_iterations: int = _limit(
        1000, "iterations", "Blend: max_iterations of an iterative blend (DIB: ~20 ns a pose an "
                            "iteration)", lo=1)
    max_plan_samples: int = _limit(
        100_000, "samples", "Plan: samples one plan streams (duration x rate_hz); Smooth: "
                            "samples of its output", lo=2)
    max_execute_waypoints: int = _limit(
        10_000, "waypoints", "Execute: waypoints of one plan (planned in ~16 us each; the arm "
                             "samples the plan as it goes, so its duration is not limited)",
        lo=2)
    max_output_rate: float = _limit(
        1000.0, "Hz", "StreamFuse output_rate, answers per second of measurement time per body",
        lo=1e-9)
    max_time: float = _limit(
        1e10, "s", "largest |time| of a measurement or a fusion time (seconds on any clock; "
                   "Unix time is 1.8e9), so that a time keeps microseconds", lo=1.0)
    max_time_jump: float = _limit(
        60.0, "s", "StreamFuse and World: how far after its body's newest a measurement may "
                   "be taken; one further is refused, unless the body's next one confirms the "
                   "jump (in a world, one from another producer while others feed the body)",
        lo=1e-9)
    max_window: int = _limit(
        1000, "measurements", "StreamFuse: measurements in one body's window (the oldest are "
                              "left out beyond it); each answer lists them", lo=1)
    max_stream_measurements: int = _limit(
        100_000, "measurements", "StreamFuse: measurements all of one stream's windows hold "
                                 "(~0.4 kB each); more are refused", lo=1)
    max_fused_per_request: int = _limit(
        75_000, "measurements", "StreamFuse and World: the cost of one message's answers (a "
                                "Publish request's, all its subscribers'), in measurements "
                                "fused (an answer counts its window and "
                                f"{ANSWER_ROWS} more, a robust one 4x its window); "
                                "ticks beyond it are skipped (the latest kept)", lo=1)
    max_subscriptions: int = _limit(
        256, "streams", "World Subscribe/SubscribeBatches and WatchArm streams open on the "
                        "server, all worlds and peers together", lo=1)
    max_world_subscriptions: int = _limit(
        64, "streams", "World Subscribe/SubscribeBatches streams open in one world", lo=1)
    max_peer_subscriptions: int = _limit(
        16, "streams", "Subscribe/SubscribeBatches and WatchArm streams of one peer (its bearer "
                       "token when the server has one, else its host), each counted until its "
                       "client has closed it", lo=1)
    max_world_waits: int = _limit(
        64, "lookups", "World Lookups waiting (LookupRequest.wait) in one world at once", lo=1)
    max_peer_waits: int = _limit(
        16, "lookups", "World Lookups of one peer waiting (LookupRequest.wait) at once", lo=1)
    max_peer_streams: int = _limit(
        64, "streams", "streams of any RPC of one peer (BlendStream, StreamFuse, Publish, "
                       "Subscribe, Plan, Execute, WatchArm...), each counted until its client "
                       "has closed it", lo=1)
    max_write_wait: float = _limit(
        1.0, "s", "a subscription (World Subscribe, WatchArm) whose client reads nothing for "
                  "this long, a write waiting, is ended RESOURCE_EXHAUSTED and its slot freed",
        lo=1e-3)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """``ValueError("name: problem")`` for the first value out of range."""
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            integral = f.type in ("int", int)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or (
                    integral and not isinstance(v, int)):
                raise LimitConfigError(f.name, f"must be {'an integer' if integral else 'a number'}"
                                               f", got {v!r}")
            if not (math.isfinite(v) and v >= f.metadata["lo"]):
                raise LimitConfigError(f.name, f"must be finite and >= {f.metadata['lo']:g}, "
                                               f"got {v!r}")
        if self.max_time * self.max_output_rate > EXACT_TICKS:
            raise LimitConfigError("max_time", f"max_time * max_output_rate must stay below "
                                               f"2^50 (ticks exact), got {self.max_time:g} s * "
                                               f"{self.max_output_rate:g} Hz")


class LimitConfigError(ValueError):
    """A limit the server cannot start with; ``setting`` names it (the ``ServerConfig`` field
    convention: its flag is the name with dashes)."""

    def __init__(self, setting: str, problem: str):
        super().__init__(f"{setting}: {problem}")
        self.setting, self.problem = setting, problem


DEFAULT = Limits()


def flag(name: str) -> str:
    """The ``dqpose serve`` flag of limit ``name``."""
    return "--" + name.replace("_", "-")


def over(where: str, what: str, limits: Limits, name: str) -> OverLimit:
    """``"{where}: {what}, over the server's limit max_x = v unit (dqpose serve --max-x)"``."""
    return OverLimit(f"{where}: {over_text(what, name, getattr(limits, name))}")


def over_text(what: str, name: str, value: float) -> str:
    """:func:`over`'s text after its field, limit ``name`` being ``value``."""
    f = Limits.__dataclass_fields__[name]
    return (f"{what}, over the server's limit {name} = {value:.6g} {f.metadata['unit']} "
            f"(dqpose serve {flag(name)})")


class Budget:
    """What one request's answers may still cost, ``max_fused_per_request`` measurements fused,
    an answer :func:`answer_cost` of those it fuses: a StreamFuse message's, a World Publish
    request's for all its subscribers. Which answers are given is decided before any is fused:
    a body's answers beyond what is left are skipped, its latest kept (:meth:`take`), and one
    error says which (:meth:`skipped`)."""

    def __init__(self, max_fused_per_request: int):
        self.limit = max_fused_per_request
        self.left = self.limit

    @property
    def spent(self) -> int:
        return self.limit - self.left

    def take(self, due: int, rows: int, robust: bool = False,
             correlated: bool = False) -> tuple[int, int]:
        """How many of a body's ``due`` answers, each fusing ``rows`` measurements (as
        :func:`answer_cost` takes them), are given, the latest; and what one costs. Charged."""
        cost = answer_cost(rows, robust, correlated)
        k = min(due, self.left // cost)
        self.left -= k * cost
        return k, cost

    def skipped(self, where: str, body: str, what: str, cost: int) -> OverLimit:
        """The error of ``body``'s answers ``what`` ("5 ticks from 1 s to 2 s") that
        :meth:`take` left out, each costing ``cost``."""
        return OverLimit(f"{where}: " + over_text(
            f"body {body!r}: {what} not answered: the answers would cost more ({cost} "
            f"measurements fused an answer)", "max_fused_per_request", self.limit))


def beyond_time(where: str, t: float, limits: Limits) -> OverLimit:
    """A time (a measurement's, a fusion time) beyond ``+-max_time``: every service's refusal of
    it, naming ``where``."""
    return OverLimit(f"{where}: {beyond_time_text(t, limits.max_time)}")


def beyond_time_text(t: float, max_time: float) -> str:
    """:func:`beyond_time`'s text after its field."""
    return over_text(f"{t:.6g} s is beyond +-{max_time:.6g} s", "max_time", max_time)


def add_flags(parser) -> None:
    """One ``dqpose serve`` flag per limit, with its default, unit and meaning."""
    for f in dataclasses.fields(Limits):
        parser.add_argument(flag(f.name), type=int if f.type in ("int", int) else float,
                            default=f.default, metavar=f.metadata["unit"].split()[0].upper(),
                            help=f"{f.metadata['meaning']} (default: %(default)s)")


def from_args(args) -> Limits:
    """The :class:`Limits` of parsed ``dqpose serve`` flags (:func:`add_flags`)."""
    return Limits(**{f.name: getattr(args, f.name) for f in dataclasses.fields(Limits)})
