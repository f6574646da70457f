"""hmrta.fanout and hmrta bench --jobs: the same results in process and on a local Ray with 2 CPUs."""
from __future__ import annotations

import functools
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from hmrta import bench
from hmrta import methods as M
from hmrta.deps import MissingDependency
from hmrta.fanout import Fanout, fanout_map
from hmrta.generators import ScenarioGenerator

ROOT = Path(__file__).resolve().parents[2]


def _records(out: Path) -> dict:
    """cache records keyed by (row, method, index), without the timing."""
    recs = {}
    for line in (out / "cache.jsonl").read_text().splitlines():
        r = json.loads(line)
        r.pop("compute_seconds")
        recs[(r["row"], r["method"], r["index"])] = r
    return recs


def test_in_process_map_keeps_order_and_calls_back():
    seen = []
    assert fanout_map(abs, [-3, 1, -2], on_result=lambda i, r: seen.append((i, r))) == [3, 1, 2]
    assert seen == [(0, 3), (1, 1), (2, 2)]
    assert not Fanout(1).distributed


def test_missing_ray_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MissingDependency, match=r"needs ray.*pip install 'hmrta\[ray\]'"):
        Fanout(2)
    assert fanout_map(abs, [-1]) == [1]  # one worker never needs Ray


def test_bad_workers_is_a_user_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hmrta.cli", "bench", "--scenario", "SA-AT", "--agents", "4",
                        "--species", "2", "--tasks", "5", "--skills", "2", "--count", "1", "--methods", "greedy",
                        "--jobs", "0", "--no-progress"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1].endswith("--jobs: expected a positive integer, got 0")


def test_a_ray_address_that_is_not_a_ray_cluster_is_a_user_error_within_the_timeout():
    """Nothing listening, a server that never answers (a plain TCP port) and one that answers in
    HTTP/1 (a dashboard): one line each within the timeout, where Ray would wait without limit.
    An authentication failure of a real cluster names RAY_AUTH_MODE."""
    import http.server
    import socket
    import threading
    import time

    from hmrta.errors import MethodError
    from hmrta.fanout import _join_error, _reachable

    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen()
    web = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    web.RequestHandlerClass.log_message = lambda *a: None
    threading.Thread(target=web.serve_forever, daemon=True).start()
    try:
        for port, says in ((silent.getsockname()[1], "not a Ray cluster's GCS"),
                           (web.server_address[1], "not a Ray cluster's GCS")):
            t0 = time.monotonic()
            with pytest.raises(MethodError, match=says):
                _reachable(f"127.0.0.1:{port}", timeout=1.0)
            assert time.monotonic() - t0 < 5.0
        with pytest.raises(MethodError, match="expected HOST:PORT"):
            _reachable("nohost", timeout=1.0)
    finally:
        web.shutdown()
        silent.close()

    class AuthenticationError(Exception):
        pass

    try:
        try:
            raise AuthenticationError("RPC error: InvalidAuthToken")
        except AuthenticationError as cause:
            raise ConnectionError("Failed to connect to Ray cluster") from cause
    except ConnectionError as e:
        assert "RAY_AUTH_MODE=token" in str(_join_error("h:6379", e))


@pytest.mark.parametrize("text,expect", [("10.0.0.2:6379", ("10.0.0.2", 6379)), ("head:1", ("head", 1)),
                                         ("[::1]:6379", ("::1", 6379)), ("nohost", None), (":6379", None),
                                         ("h:0", None), ("h:65536", None), ("h:63a", None), ("h:", None)])
def test_a_ray_address_is_read_by_one_rule_for_the_command_line_and_the_connection(text, expect):
    import argparse

    from hmrta.cli.parser import _ray_address
    from hmrta.errors import MethodError
    from hmrta.fanout import _reachable, split_address

    if expect is not None:
        assert split_address(text) == expect and _ray_address(text) == text
        return
    with pytest.raises(ValueError, match=re.escape(f"expected HOST:PORT (the Ray head's GCS address, e.g. "
                                                   f"10.0.0.2:6379), got {text!r}")):
        split_address(text)
    with pytest.raises(argparse.ArgumentTypeError, match="expected HOST:PORT"):
        _ray_address(text)
    with pytest.raises(MethodError, match="--ray-address: expected HOST:PORT"):
        _reachable(text, timeout=1.0)


def test_bench_on_two_ray_workers_matches_serial(tmp_path):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'hmrta[ray]')")
    import ray

    rows = [bench.Row("SA-AT", 4, 2, 8, 2), bench.Row("MA-AT", 6, 2, 6, 2)]
    methods = ["greedy", "greedy-coalition"]
    kw = dict(progress=False, log=lambda s: None)
    serial = bench.run_bench(rows, methods, 3, 7, tmp_path / "serial", {}, **kw)
    # half of it already cached: the fanned-out run solves only the rest and resumes the cache
    part = tmp_path / "ray"
    part.mkdir()
    lines = (tmp_path / "serial" / "cache.jsonl").read_text().splitlines()
    (part / "cache.jsonl").write_text("\n".join(lines[: len(lines) // 2]) + "\n")
    fanned = bench.run_bench(rows, methods, 3, 7, part, {}, workers=2, **kw)
    assert not ray.is_initialized()  # the Ray it started is shut down
    assert _records(part) == _records(tmp_path / "serial")
    assert len((part / "cache.jsonl").read_text().splitlines()) == len(lines)  # nothing solved twice
    assert [r["makespans"] for r in fanned["rows"]] == [r["makespans"] for r in serial["rows"]]
    assert fanned["provenance"]["fanout"] == {"workers": 2, "ray_address": None}
    bench.save(fanned, part)
    assert (part / "results.md").is_file()

    # routes too, solve by solve, with results in the items' order
    insts = ScenarioGenerator("SA-AT", 4, 2, 8, 2).generate(4, 11)
    solve = functools.partial(M.solve, method="greedy-coalition", seed=0)
    arrived = []
    with Fanout(2) as fan:
        sols = fan.map(solve, insts, on_result=lambda i, r: arrived.append(i))
        with pytest.raises(M.MethodError):  # a worker's exception comes back as itself
            fan.map(functools.partial(M.solve, method="no-such-method"), insts[:1])
    assert not ray.is_initialized()
    assert sorted(arrived) == [0, 1, 2, 3]
    here = [solve(i) for i in insts]
    assert [s.routes for s in sols] == [s.routes for s in here]
    assert [s.makespan for s in sols] == [s.makespan for s in here]
