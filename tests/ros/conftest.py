"""Fixtures for the ROS tests: real rclpy over DDS, each test in its own ROS domain, discovery on
this machine only, every process started is stopped at teardown."""
from __future__ import annotations

import os
import random
import time
from pathlib import Path
from typing import Callable

import pytest

# DDS discovery stays on this machine unless the caller opened it up explicitly
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

rclpy = pytest.importorskip("rclpy")
try:
    import hmrta_agent  # noqa: F401
    import hmrta_coordinator  # noqa: F401
    import hmrta_msgs_py  # noqa: F401
except ImportError as e:
    raise ImportError(
        "tests/ros need the ROS 2 packages in the venv: .venv/bin/pip install --no-deps --no-build-isolation "
        "-e ros2_ws/src/hmrta_msgs_py -e ros2_ws/src/hmrta_agent -e ros2_ws/src/hmrta_coordinator") from e

_RECENT: list[int] = []  # the domains given out latest (every test stops what it started at teardown)
_RNG = random.Random(os.getpid() ^ time.time_ns())


def _domain() -> int:
    """A domain in 100..199, at random among those that none of the latest 50 tests of this
    process got: a process a test left to die (a killed DDS participant lingers for its lease)
    never meets the next tests. (The suite has more ROS tests than the range has domains, so
    domains are reused. Tests run one at a time: nothing here keeps two pytest processes apart.)"""
    d = _RNG.choice([d for d in range(100, 200) if d not in _RECENT])
    _RECENT.append(d)
    del _RECENT[:-50]
    return d


class Graph:
    """An rclpy context of the test process on its own domain, with a spin-until helper."""

    def __init__(self, domain: int):
        from rclpy.executors import SingleThreadedExecutor

        self.domain = domain
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def node(self, name: str, **kw):
        n = rclpy.create_node(name, context=self.context, start_parameter_services=False, enable_rosout=False, **kw)
        self.nodes.append(n)
        self.executor.add_node(n)
        return n

    def spin_until(self, cond: Callable[[], bool], timeout: float, what: str = "condition") -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        for n in self.nodes:
            self.executor.remove_node(n)
            n.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def domain() -> int:
    """A ROS domain none of the latest 50 tests of this session used (_domain)."""
    return _domain()


@pytest.fixture
def graph(domain):
    g = Graph(domain)
    yield g
    g.close()


@pytest.fixture
def mission_procs(tmp_path, domain):
    """make(instance_path, **MissionProcesses options) -> started MissionProcesses on this test's
    domain; all of them are stopped at teardown."""
    from hmrta_coordinator.mission import MissionProcesses
    from hmrta_msgs_py.runtime import local_env

    made = []

    def make(instance: Path, robots: list[str], start: bool = True, **kw) -> MissionProcesses:
        env = local_env(domain_id=domain)
        env["ROS_LOG_DIR"] = str(tmp_path / "ros_logs")
        p = MissionProcesses(Path(instance), robots, kw.pop("out", tmp_path / "result.json"), tmp_path / "logs",
                             env, **kw)
        made.append(p)
        if start:
            p.start()
        return p

    yield make
    for p in made:
        p.stop(grace=3.0)
        for c in p.children():
            assert c.proc.poll() is not None, f"{c.name} is still running"


def save_instance(inst, path: Path) -> Path:
    inst.save(path)
    return path


def pytest_configure(config):
    # rosidl's parser imports lark, which uses modules Python deprecates
    config.addinivalue_line("filterwarnings", "ignore::DeprecationWarning:lark.*")
