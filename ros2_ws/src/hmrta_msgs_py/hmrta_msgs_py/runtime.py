"""Shared process plumbing for HMRTA executables: environment defaults, executor, spinning."""
from __future__ import annotations

import contextlib
import os
import random
import sys
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.task import Future

DISCOVERY_VAR = "ROS_AUTOMATIC_DISCOVERY_RANGE"

# nodes hosted many to a process: no parameter services, no /rosout publisher
LEAN_NODE = {"start_parameter_services": False, "enable_rosout": False}


def local_env(env: dict[str, str] | None = None, domain_id: int | None = None) -> dict[str, str]:
    """A copy of ``env`` (default os.environ) with DDS discovery kept on this machine unless the
    caller chose otherwise (``ROS_AUTOMATIC_DISCOVERY_RANGE`` unset -> LOCALHOST), and a ROS
    domain: ``domain_id`` if given, else the caller's ``ROS_DOMAIN_ID``, else a random one in
    100..199 so that concurrent missions on one machine never meet."""
    out = dict(os.environ if env is None else env)
    out.setdefault(DISCOVERY_VAR, "LOCALHOST")
    if domain_id is not None:
        out["ROS_DOMAIN_ID"] = str(domain_id)
    elif not out.get("ROS_DOMAIN_ID"):
        out["ROS_DOMAIN_ID"] = str(random.randint(100, 199))
    return out


@contextlib.contextmanager
def starting(prog: str, user_errors: tuple[type[BaseException], ...] = (ValueError,)):
    """Around a node's construction (rclpy initialised): a user error (one of ``user_errors``, or
    a parameter of the wrong type) is one line on stderr and exit 2; Ctrl-C while it loads the
    mission or the policy is one line and exit 130. Either way rclpy is shut down."""
    from rclpy.exceptions import InvalidParameterTypeException

    try:
        yield
    except (InvalidParameterTypeException, *user_errors) as e:
        hint = (" (a number parameter needs a decimal point: -p NAME:=10.0, not 10)"  # ROS reads 10 as an integer
                if isinstance(e, InvalidParameterTypeException) else "")
        print(f"{prog}: {e}{hint}", file=sys.stderr)
        rclpy.try_shutdown()
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(f"{prog}: interrupted during start-up", file=sys.stderr)
        rclpy.try_shutdown()
        raise SystemExit(130) from None


def declare_method_parameters(node) -> tuple[str, dict]:
    """Declare ``method`` and every live method option (the table
    :func:`hmrta_msgs_py.params.method_parameters`, generated from :data:`hmrta.methods.METHODS`)
    on ``node``; return the method and the options given (unset ones omitted). Raises MethodError
    for an unknown method or an option it does not take."""
    from hmrta.methods import live_spec

    from .params import method_parameters

    method_param, *option_params = method_parameters()
    method = node.declare_parameter(method_param.name, method_param.default).value
    opts = {}
    for p in option_params:
        value = node.declare_parameter(p.name, p.default).value
        if value != p.default:  # ROS has no None: the default stands for "not given"
            opts[p.name] = value
    # the spec's shorthand and own checkpoint (rl-s5: sampled decisions, live one per turn; rl@broad)
    name, options = live_spec(method, opts)
    return name, options


def parameters_help(params) -> str:
    """One line per ROS parameter (:class:`hmrta_msgs_py.params.Param`): name, type, default, meaning."""
    return "\n".join(f"  {p.name} ({p.type}, default {p.default!r}): {p.help}" for p in params)


def help_requested(argv: list[str], prog: str, description: str, params) -> None:
    """If ``argv`` asks for help (``-h`` / ``--help`` before any ``--ros-args``), print the usage,
    ``description`` and the node's ROS parameters, and exit 0; else return. Call it first thing
    in ``main()``: it starts nothing."""
    args = list(argv[1:])
    if "--ros-args" in args:
        args = args[:args.index("--ros-args")]
    if not any(a in ("-h", "--help") for a in args):
        return
    print(f"usage: {prog} [-h] [--ros-args -p NAME:=VALUE ... -r FROM:=TO ...]\n")
    print(description.strip() + "\n")
    print("ROS parameters (--ros-args -p NAME:=VALUE):")
    print(parameters_help(params))
    raise SystemExit(0)


def make_executor():
    """The events executor when this rclpy has it (much lower latency with many nodes in one
    process), else the single-threaded executor. ``HMRTA_EXECUTOR=single`` forces the latter."""
    if os.environ.get("HMRTA_EXECUTOR", "events") != "single":
        try:
            from rclpy.experimental import EventsExecutor

            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def spin_nodes(nodes: list, until: Future | None = None, on_exit: Callable[[], None] | None = None) -> None:
    """Spin nodes on one executor until ``until`` completes, Ctrl-C / SIGTERM or external
    shutdown; then destroy the nodes and shut rclpy down (ros2/demos style).

    Spins in bounded slices: the experimental events executor busy-waits and ignores signals
    when asked to spin without a timeout."""
    executor = make_executor()
    for n in nodes:
        executor.add_node(n)
    until = until if until is not None else Future()
    try:
        while rclpy.ok() and not until.done():
            executor.spin_until_future_complete(until, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if on_exit is not None:
            on_exit()
        for n in nodes:
            n.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
