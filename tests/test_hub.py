"""dqpose.hub, in process: a world's steps in its one order: producers' sequences and acks, the
answers a step makes due (its budget shared by every subscription, the earlier subscription
served first), each subscription handed its answers once a step, and the hooks a recording
writes each step with, run under the world's lock in that order."""
from __future__ import annotations

import numpy as np
import pytest

from dqpose import hub as hub_module
from dqpose import limits
from dqpose.fusion import Source
from dqpose.fusion.bounds import TrackerBounds
from dqpose.hub import Hub, Interest, Rows, Subscription
from dqpose.world import WorldBounds, WorldError, WorldOptions

RATE = 20.0


class Written:
    """An encoder whose answers say what they are: ``b"fused box 1.05 r3"``, ``b"error ..."``."""

    @staticmethod
    def fused(p, request: int, measurements: list) -> bytes:
        return f"fused {p.body} {p.time:.6g} r{request} {measurements}".encode()

    @staticmethod
    def error(body: str, time: float, request: int, text: str) -> bytes:
        return f"error {body} r{request}: {text}".encode()

    @staticmethod
    def relative(p) -> bytes:
        return f"relative {p.body} {p.time:.6g}".encode()

    fit_error = staticmethod(str)


def rows(bodies, times, sources=None) -> Rows:
    """One measurement of each body at each time (identity poses, unit covariances)."""
    n = len(bodies)
    return Rows(np.arange(n), tuple(bodies), tuple(sources or ["cam"] * n),
                np.asarray(times, np.float64), np.tile([1.0, 0, 0, 0, 0, 0, 0, 0], (n, 1)),
                np.tile(np.eye(6) * 1e-4, (n, 1, 1)), None)


def step(h: Hub, producer: str, anonymous: str, sequence: int, r, hook=None, offered=None):
    """A Publish request of rows ``r`` (None: refused whole) as one step of ``h``."""
    n = len(r.index) if offered is None else offered
    return h.publish(producer, anonymous, sequence, r, n, hook)


def made(bounds: limits.Limits = limits.DEFAULT) -> Hub:
    h = Hub("test", Written(), TrackerBounds.of(bounds))
    h.configure([Source("cam")], {}, WorldOptions(window=0.2, buffer=2.0, max_delay=0.0))
    return h


def test_sequences_are_acked_repeats_refused_and_gaps_named():
    h = made()
    first = step(h, "cam", "call1", 1, rows(["box"], [0.0]))
    assert (first.request, first.acked_through, first.notes, first.used) == (0, 1, (), True)
    again = step(h, "cam", "call1", 1, rows(["box"], [0.01]))
    assert not again.used and again.acked_through == 1 and h.requests == 1   # not counted
    assert str(again.notes[0]) == "sequence 1 already in the world (acked through 1); not " \
                                  "fused again"
    gap = step(h, "cam", "call2", 4, rows(["box"], [0.02]))
    assert gap.used and gap.acked_through == 4
    assert gap.notes[0].named("requests[7]") == "requests[7]: sequences 2..3 of producer " \
                                                "'cam' never arrived"
    bad = step(h, "a/b", "call3", 9, rows(["box"], [0.03]))
    assert not bad.used and bad.acked_through == 0 and h.requests == 3
    assert bad.notes[0].field == "producer" and "none of it was used" in bad.notes[0].text
    # a call's own key is forgotten when the call ends: its sequences start again
    step(h, "", "call4", 5, rows(["box"], [0.04]))
    h.forget("call4")
    assert step(h, "", "call4", 1, rows(["box"], [0.05])).notes == ()


def test_a_request_refused_whole_is_counted_and_acked_but_not_used():
    h = made()
    got = step(h, "cam", "call", 3, None, offered=5)
    # numbered all the same: the next request's measurements start at 5
    assert got.used and got.acked_through == 3 and h.requests == 1 and h.measurements == 5
    assert not h.world.bodies


def test_the_producers_remembered_are_bounded(monkeypatch):
    monkeypatch.setattr(hub_module, "MAX_PRODUCERS", 2)
    h = made()
    for k, p in enumerate(("a", "b", "c")):
        step(h, p, "call", 1, rows(["box"], [0.01 * k]))
    # "a" was forgotten (acked longest ago): its next request names no gap
    assert step(h, "a", "call", 5, rows(["box"], [0.05])).notes == ()
    assert step(h, "c", "call", 5, rows(["box"], [0.06])).notes != ()


def test_measurement_errors_name_the_requests_measurement():
    h = made()
    r = rows(["box", "box", "box"], [0.0, 1e11, 0.01])
    got = step(h, "cam", "call", 1, r._replace(index=np.array([0, 2, 5])), offered=6)
    (e,) = got.errors
    assert e.index == 2 and e.field == "time" and e.limit == "max_time"
    assert e.named("requests[0].measurements").startswith("requests[0].measurements[2].time: ")
    assert h.measurements == 6


def test_each_subscription_gets_its_answers_once_a_step_in_order():
    h = made()
    got: dict[str, list] = {"all": [], "box": [], "zero": []}
    calls: dict[str, int] = {k: 0 for k in got}

    def to(name):
        def deliver(answers):
            calls[name] += 1
            got[name].extend(answers)
        return deliver

    h.subscribe(Subscription(Interest(None, RATE), to("all")))
    h.subscribe(Subscription(Interest(frozenset({"box"}), RATE), to("box")))
    h.subscribe(Subscription(Interest(frozenset({"cup"}), 0.0), to("zero")))
    step(h, "cam", "call", 1, rows(["box", "cup"] * 3, [0.0, 0.0, 0.1, 0.1, 0.2, 0.2]))
    assert calls == {"all": 1, "box": 1, "zero": 1}
    assert got["box"] and all(a.startswith(b"fused box") for a in got["box"])
    # a tick answered for two subscriptions is made once: the same bytes
    assert set(got["box"]) <= set(got["all"])
    assert any(a.startswith(b"fused cup") for a in got["all"])
    assert got["zero"] and all(a.startswith(b"fused cup") for a in got["zero"])
    # a closed subscription is answered no more, even before it is taken out
    h.subscriptions[0].closed = True
    step(h, "cam", "call", 2, rows(["box"], [0.3]))
    assert calls["all"] == 1 and calls["box"] == 2
    h.unsubscribe(h.subscriptions[1])
    assert [s.interest.bodies for s in h.subscriptions] == [None, frozenset({"cup"})]


def test_the_budget_serves_the_earlier_subscription_first():
    """One step's answers share the request's budget: an earlier subscription's ticks are
    fitted first, the later one's beyond the budget skipped and named. (Subscriptions were a
    set, in an order of their own: which subscriber got the answers was not the order they
    came in, and a replay of a recording could hand them to the other.)"""
    bounds = limits.Limits(max_fused_per_request=limits.answer_cost(3))
    for trial in range(20):
        h = made(bounds)
        got: dict[str, list] = {"first": [], "second": []}
        body = {"first": f"a{trial}", "second": f"b{trial}"}
        for name in ("first", "second"):
            h.subscribe(Subscription(Interest(frozenset({body[name]}), 0.0),
                                     got[name].extend))
        step(h, "cam", "call", 1, rows([body["first"], body["second"]], [0.0, 0.0]))
        assert [a.split()[0] for a in got["first"]] == [b"fused"], trial
        (skip,) = got["second"]
        assert skip.startswith(b"error " + body["second"].encode()) and \
            b"max_fused_per_request" in skip, trial


def test_an_internal_subscription_is_served_after_the_clients():
    """The recorder's subscription comes first (made with its world) but is served last within
    a request's budget: recording a world never takes a client's answers."""
    bounds = limits.Limits(max_fused_per_request=limits.answer_cost(3))
    h = made(bounds)
    got: dict[str, list] = {"recorder": [], "client": []}
    h.subscribe(Subscription(Interest(frozenset({"a"}), 0.0), got["recorder"].extend,
                             internal=True))
    h.subscribe(Subscription(Interest(frozenset({"b"}), 0.0), got["client"].extend))
    step(h, "cam", "call", 1, rows(["a", "b"], [0.0, 0.0]))
    assert [a.split()[0] for a in got["client"]] == [b"fused"]
    (skip,) = got["recorder"]
    assert skip.startswith(b"error a") and b"max_fused_per_request" in skip


def test_a_hook_runs_under_the_lock_in_the_order_of_the_steps():
    h = made()
    order = []

    def hook(name):
        def run():
            assert h.lock.locked()
            order.append(name)
        return run

    sub = Subscription(Interest(None, RATE), lambda answers: order.append("answers"))
    h.subscribe(sub, hook("subscribe"))
    step(h, "cam", "call", 1, rows(["box", "box"], [0.0, 0.1]), hook("publish"))
    h.count(hook("count"))
    h.configure([Source("cam")], {}, WorldOptions(window=0.3), hook("configure"))
    h.unsubscribe(sub, hook("unsubscribe"))
    assert order == ["subscribe", "publish", "answers", "count", "configure", "unsubscribe"]
    with pytest.raises(WorldError, match="^options.window: must be positive"):
        h.configure([Source("cam")], {}, WorldOptions(window=-1.0), hook("refused"))
    assert order[-1] == "refused" and not h.lock.locked()


def test_a_subscription_that_cannot_wait_is_not_added_while_a_step_holds_the_lock():
    h = made()
    sub = Subscription(Interest(None, RATE), lambda answers: None)
    with h.lock:
        assert not h.subscribe(sub, wait=False)
    assert not h.subscriptions
    assert h.subscribe(sub, wait=False) and h.subscriptions == (sub,)


def test_rate_zero_answers_each_body_a_request_brought_once_at_its_newest():
    h = made()
    got: list = []
    h.subscribe(Subscription(Interest(None, 0.0), got.extend))
    step(h, "cam", "call", 1, rows(["box", "cup", "box"], [0.0, 0.01, 0.02]))
    step(h, "cam", "call", 2, rows(["cup"], [0.005]))      # older than the cup's newest
    # box first (its first measurement came first), each at its newest; the measurements
    # each answer fused, numbered in the world's order
    assert got == [b"fused box 0.02 r0 [0, 2]", b"fused cup 0.01 r0 [1]",
                   b"fused cup 0.01 r1 [1, 3]"]


def test_a_body_whose_window_holds_more_than_a_fit_takes_is_said_so_once():
    h = made()
    h.world.bounds = WorldBounds(max_measurements_per_body=2)     # a fit takes two at most
    h.configure([Source("cam")], {}, WorldOptions(window=0.2, buffer=2.0, max_delay=0.0))
    got: list = []
    h.subscribe(Subscription(Interest(None, 0.0), got.extend))
    for k in range(3):
        step(h, "cam", "call", k + 1, rows(["box", "box"], [0.02 * k, 0.02 * k + 0.01]))
    said = [a for a in got if a.startswith(b"error")]
    assert len(said) == 1 and b"its window holds more measurements than its fits take" in said[0]
    assert got[-1] == b"fused box 0.05 r2 [4, 5]"          # the last two: the window's cap


def test_a_billion_ticks_due_at_once_are_counted_not_listed():
    """A body whose time leapt across a wide window: its ticks are a range until the budget
    cuts them; the latest it affords answered, each made once for the two subscriptions of that
    rate, the rest named by one skip entry each. (The hub listed every tick's time first: 1e9
    floats, the process killed by the kernel's OOM killer.)"""
    h = Hub("test", Written(), TrackerBounds.of(limits.Limits(
        max_fused_per_request=10 * limits.answer_cost(2), max_time_jump=2e6)),
        bounds=WorldBounds(max_buffer=2e6))
    h.configure([Source("cam")], {}, WorldOptions(window=1e6, buffer=1e6, max_delay=0.0))
    got: dict[str, list] = {"first": [], "second": []}
    for name in got:
        h.subscribe(Subscription(Interest(None, 1000.0), got[name].extend))
    step(h, "cam", "call", 1, rows(["box"], [0.0]))
    step(h, "cam", "call", 2, rows(["box"], [1e6]))
    for name, answers in got.items():
        fused = [a for a in answers if a.startswith(b"fused") and b" r1 " in a]
        assert len(fused) == 10, name
        (skip,) = [a for a in answers if a.startswith(b"error") and b" r1:" in a]
        assert b": 999999990 ticks from " in skip and b"max_fused_per_request" in skip, name
    assert got["first"][-10:] == got["second"][-10:]


def test_subscriptions_asking_the_same_get_what_each_would_get_alone():
    """A step makes a body's answers once for the subscriptions that ask the same with the
    same next tick and the same note said: each still gets what it gets as a world's only
    subscription, its window's capped note once, and one that came later its own ticks."""
    def run(only=None) -> dict:
        h = made()
        h.world.bounds = WorldBounds(max_measurements_per_body=2)     # a fit takes two
        h.configure([Source("cam")], {}, WorldOptions(window=0.2, buffer=2.0, max_delay=0.0))
        got: dict[str, list] = {"early": [], "again": [], "late": []}

        def join(name):
            if only in (None, name):
                h.subscribe(Subscription(Interest(None, RATE), got[name].extend))
        join("early")
        join("again")
        for k in range(8):
            if k == 3:
                join("late")
            step(h, "cam", "call", k + 1,
                 rows(["box", "cup", "box"], [0.03 * k, 0.03 * k, 0.03 * k + 0.01]))
        return got

    together = run()
    for name in together:
        assert together[name] == run(name)[name], name
    assert together["early"] == together["again"]
    assert together["late"] and together["late"] != together["early"][-len(together["late"]):]
    assert sum(a.startswith(b"error box") for a in together["again"]) == 1
