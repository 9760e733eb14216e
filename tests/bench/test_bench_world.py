"""The world benchmark's harness, small: its producers' measurements reach the world and its
subscribers' answers are matched to the measurement that made each due, against a real
``dqpose serve`` process and the relay; and its Lookup rows time real answers."""
import os

import numpy as np
import pytest

from dqpose.rpc.client import Client
from tests.bench import bench_world as bw
from tests.bench import world_publish as wp
from tests.bench.bench_grpc import ServerProcess


def test_publish_row_acks_every_measurement_and_answers_every_body_at_its_ticks():
    server = ServerProcess("aio", quiet_log=True)
    try:
        with Client(server.target) as c:
            c.configure_world(window=0.2)
        r = wp.run(server.target, 2, 1, 6, 300.0, 2.0, server.rss_mb, server.cpu_seconds)
        with Client(server.target) as c:
            poses = {b: c.lookup("", f"b{b}") for b in range(6)}
    finally:
        server.stop()
    # every measurement sent was acked (the rate counts acked ones): ~300/s over 2 s
    assert 150 < r["rate"] < 450, r
    assert r["ended"] == ""
    # each body answered at 30 Hz for ~2 s, and each answer matched to a measurement sent
    # before it arrived (a latency is an arrival minus a send time: positive)
    assert 6 * 30 * 2 * 0.5 < r["answers"] * 2.0 < 6 * 30 * 2 * 1.5, r
    assert 0.0 < r["p50"] <= r["p99"] < 10_000.0, r
    # the server worked (fits, answers) and its threads cannot use more than the machine's cores
    assert 0.0 < r["cores"] <= (os.cpu_count() or 1) + 0.1, r
    assert 0.0 < r["client_cores"] <= (os.cpu_count() or 1) + 0.1, r
    truth, _ = wp.scene_poses(6)
    for b, p in poses.items():     # the world fused the static poses the producers sent
        assert np.allclose(p.pose, truth[b], atol=1e-9) or np.allclose(p.pose, -truth[b],
                                                                        atol=1e-9), b


@pytest.mark.parametrize("rpc", ["SubscribeBatches", "Subscribe"])
def test_relay_row_answers_like_the_world_without_fusing(rpc):
    relay = wp.RelayProcess(700)
    try:
        r = wp.run(relay.target, 1, 1, 4, 200.0, 2.0, relay.rss_mb, rpc=rpc)
    finally:
        relay.stop()
    assert r["ended"] == "" and 4 * 30 * 2 * 0.5 < r["answers"] * 2.0 < 4 * 30 * 2 * 1.5, r
    assert 650 < r["size"] < 800, r         # answers of the size it was asked for
    # Subscribe: one answer a message; SubscribeBatches: what was ready, at least one
    assert r["per_message"] == 1.0 if rpc == "Subscribe" else r["per_message"] >= 1.0, r


def test_lookup_rows_time_real_answers():
    rows = bw.lookup_rows(5)
    # 3 cases x (after new data, repeated) x 2 worlds, and the first case after 1 ms idle
    assert len(rows) == 13
    assert sum("1 ms idle" in r[1] for r in rows) == 1
    for row in rows:
        assert np.isfinite(float(row[2])) and float(row[2]) > 0.0, row


@pytest.mark.parametrize("load,polled", [(False, False), (False, True), (True, True)])
def test_rpc_lookup_row_times_the_servers_lookups(load, polled):
    (row,) = bw.rpc_lookup_rows(5, load=load, polled=polled)
    assert row[0] == "Lookup (gRPC)" and float(row[2]) > 0.0, row
    assert ("published" in row[1]) == load, row
    assert ("polled" in row[1]) == polled, row
    assert row[4].endswith("5 calls"), row      # each Lookup found in the server's call log


def test_ingest_row_fits_the_ticks_it_made_due():
    (row,) = bw.ingest_rows(300)
    # 300 messages span 0.15 s of stamps: 100 bodies at 30 Hz make ~450 ticks due
    fits_per_s = float(row[4].split(" fits/s")[0])
    meas_per_s = float(row[2])
    assert 300 < fits_per_s / meas_per_s * 3000 < 600, row


def test_answer_rows_time_the_fit_and_the_message_of_each_tick():
    rows = bw.answer_rows(300)
    assert [r[1] for r in rows] == ["a tick's fit (World.pose)",
                                    "its FusedPose bytes (the C writer)",
                                    "the same by protobuf (fused_to_msg, serialized)"]
    assert all(float(r[2]) > 0.0 for r in rows), rows
    ticks = int(rows[0][4].split(" ticks")[0])
    assert 300 < ticks < 600, rows                  # as test_ingest_row_fits_the_ticks_it_made_due
    assert int(rows[0][4].split(", ")[1].split(" measurements")[0]) > 1, rows


def test_publish_request_rows_time_both_paths():
    rows = bw.publish_request_rows(requests=20, rounds=1, history=0.1)
    assert [r[1] for r in rows] == ["a request from its bytes (measurements decoded in C)",
                                    "the same request parsed (protobuf path)"]
    assert all(float(r[2]) > 0.0 for r in rows), rows
