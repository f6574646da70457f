"""Shared process plumbing for HMRTA executables: environment defaults, executor, spinning."""
from __future__ import annotations

import contextlib
import difflib
import os
import random
import re
import signal
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.task import Future

from . import console

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
def starting(prog: str, user_errors: tuple[type[BaseException], ...] = (ValueError,), args: list[str] | None = None):
    """Around a node process's start-up: rclpy initialised on the command line ``args`` (None:
    the caller initialised it), then the body (the nodes' construction). A user error (one of
    ``user_errors``, a malformed ``--ros-args`` argument, a parameter of the wrong type) is one
    line on stderr and exit 2; Ctrl-C is one line and exit 130. Either way rclpy is shut down.

    rclpy's own SIGINT / SIGTERM handlers are not installed: a Ctrl-C here is a plain
    KeyboardInterrupt, never a context shut down under a node being built (an RCLError, or a C++
    abort); :func:`spin_nodes` handles the signals once the nodes spin."""
    from rclpy.exceptions import InvalidParameterTypeException, NameValidationException
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.signals import SignalHandlerOptions

    try:
        try:
            _interrupted_before()
            if args is not None:
                check_ros_args(args)
                rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
            yield
            _interrupted_before()  # a Ctrl-C a library swallowed while the nodes were built
        except _rclpy.RCLError as e:
            text = ros_error_text(str(e), args or [])
            if text is None:
                raise
            raise RosArgsError(text) from None
        except NameValidationException as e:  # a bad name or namespace (rclpy validates after rcl refused it)
            raise RosArgsError(f"--ros-args: {e}") from None
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        console = sys.modules.get("hmrta_msgs_py.console")
        if console is not None:
            console.stopped(prog)  # SIGINT 130, SIGTERM 143, one line
        print(f"{prog}: interrupted during start-up", file=sys.stderr)
        raise SystemExit(130) from None
    except (InvalidParameterTypeException, RosArgsError, *user_errors) as e:
        text = parameter_type_text(str(e)) if isinstance(e, InvalidParameterTypeException) else str(e)
        print(f"{prog}: {text}", file=sys.stderr)
        rclpy.try_shutdown()
        warnings.simplefilter("ignore")  # rclpy's warnings about the node it failed to build
        raise SystemExit(2) from None


def _interrupted_before() -> None:
    """KeyboardInterrupt if a Ctrl-C came during start-up (:data:`hmrta_msgs_py.console.INTERRUPTED`)
    though no KeyboardInterrupt reached here."""
    console = sys.modules.get("hmrta_msgs_py.console")
    if console is not None and console.INTERRUPTED:
        raise KeyboardInterrupt


class RosArgsError(ValueError):
    """A malformed ``--ros-args`` argument (one line naming it)."""


# what each kind of --ros-args argument rcl failed to parse should look like
_ROS_ARG_FORMS = {
    "parameter override rule": "expected -p NAME:=VALUE (VALUE in YAML: 10, 10.0, true, text, '[a, b]')",
    "remap rule": "expected -r FROM:=TO (a namespace is absolute: -r __ns:=/robot_1)",
    "params file": "expected --params-file FILE, a readable YAML file of NODE: {ros__parameters: {NAME: VALUE}}",
    "log level": "expected --log-level LEVEL or NAME:=LEVEL (LEVEL: debug, info, warn, error, fatal)",
    "enclave": "expected -e /ENCLAVE (an absolute name)",
}


def check_ros_args(args: list[str]) -> None:
    """RosArgsError (one line naming the argument) if ``args`` has a ``--ros-args`` argument rcl
    cannot parse, or a node namespace that is not absolute; else nothing. Starts nothing."""
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.utilities import remove_ros_args

    from rclpy.exceptions import NameValidationException
    from rclpy.validate_namespace import validate_namespace
    from rclpy.validate_node_name import validate_node_name

    for kind, name in _name_remaps(args):  # before rcl, which logs a warning of its own for a bad one
        if kind == "__ns" and not name.startswith("/"):
            raise RosArgsError(f"--ros-args: -r __ns:={name}: expected an absolute namespace such as "
                               f"/{name or 'robot_1'}")
        try:
            (validate_namespace if kind == "__ns" else validate_node_name)(name)
        except NameValidationException as e:
            why = re.sub(r"^Invalid [\w ]+: ", "", str(e).splitlines()[0]).rstrip(":")
            example = "a namespace such as /robot_1" if kind == "__ns" else "a node name such as agent"
            raise RosArgsError(f"--ros-args: -r {kind}:={name}: expected {example} ({why})") from None
    try:
        remove_ros_args(args)
    except _rclpy.RCLError as e:
        raise RosArgsError(ros_error_text(str(e), args) or f"--ros-args: {_first_error(str(e))}") from None


def without_ros_args(prog: str, argv: list[str]) -> list[str]:
    """``argv`` without its ROS arguments (for a node's own argparse, before rclpy starts); a
    malformed one is one line on stderr and exit 2."""
    from rclpy.utilities import remove_ros_args

    try:
        check_ros_args(argv)
    except RosArgsError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    return remove_ros_args(argv)


# the periods a node's timers may take (seconds): rclpy keeps a period in int64 nanoseconds (1e300 s
# overflowed), and a period of ~0 ns fires without end, starving the signal handlers (1e-300 s left a
# node that no SIGINT stopped)
MIN_PERIOD, MAX_PERIOD = 1e-3, 86400.0


def check_period(name: str, seconds: float, off: bool = False) -> None:
    """ValueError naming ``name`` unless ``seconds`` is a timer period in [MIN_PERIOD, MAX_PERIOD]
    (``off``: 0 too, meaning no timer)."""
    if off and seconds == 0:
        return
    if not MIN_PERIOD <= seconds <= MAX_PERIOD:  # (NaN fails too)
        raise ValueError(f"{name}: expected a number of seconds in [{MIN_PERIOD:g}, {MAX_PERIOD:g}]"
                         f"{' (0: none)' if off else ''}, got {seconds!r}")


def writable_file(param: str, path: str) -> Path:
    """``path``, the file named by parameter ``param`` (a board's result or journal, a recording),
    checked at start as every ``--out`` of the CLI is (:func:`hmrta.cli.common.writable`): not a
    folder, not a FIFO or device, a place where a file can be made (a probe file is written and
    removed). ValueError "PARAM: PATH: why" otherwise, so that no mission runs to its end to lose
    its file, and no node blocks on a FIFO."""
    from hmrta.cli.common import UserError, writable

    try:
        return writable(f"{param}:", Path(path).absolute())
    except UserError as e:
        raise ValueError(str(e)) from None


def no_own_arguments(prog: str, argv: list[str]) -> None:
    """For a node whose settings are all ROS parameters: anything on its command line outside
    ``--ros-args`` (``task_board --method greedy``) is one line on stderr and exit 2, not silently
    left out (the node would run with the parameter's default)."""
    rest = without_ros_args(prog, argv)[1:]
    if rest:
        print(f"{prog}: unrecognized arguments: {' '.join(rest)} (its settings are ROS parameters: "
              f"{prog} --ros-args -p NAME:=VALUE; {prog} --help lists them)", file=sys.stderr)
        raise SystemExit(2)


def _name_remaps(args: list[str]) -> list[tuple[str, str]]:
    """(``__ns`` or ``__node``, value) of the ``-r [NODE:]__ns:=NS`` and ``-r [NODE:]__node:=NAME``
    remappings in the ``--ros-args`` sections of ``args``."""
    out, ros, i = [], False, 0
    while i < len(args):
        a = args[i]
        if a == "--ros-args":
            ros = True
        elif a == "--":
            ros = False
        elif ros and a in ("-r", "--remap") and i + 1 < len(args):
            i += 1
            src, sep, dst = args[i].partition(":=")
            kind = src.rpartition(":")[2]
            if sep and kind in ("__ns", "__node"):
                out.append((kind, dst))
        i += 1
    return out


def _first_error(text: str) -> str:
    """rcl's error text without the source locations (', at FILE:LINE')."""
    return re.split(r", at /\S+:\d+", text)[0]


def ros_error_text(text: str, args: list[str]) -> str | None:
    """One line for an rcl error about the command line (an argument it cannot parse, a node
    name or namespace it refuses), or None for any other rcl error."""
    m = re.search(r"Couldn't parse (.+?): '(.*?)'\. Error: (.*)", text)
    if m:
        kind, arg, why = m.groups()
        why = _first_error(why)
        form = _ROS_ARG_FORMS.get(kind, f"rcl: {why}")
        detail = f" ({why})" if kind == "params file" and "error not set" not in why else ""
        value = arg.partition(":=")[2]
        if kind == "parameter override rule" and value.startswith("[") and ":" in value and '"' not in value \
                and "'" not in value:  # a YAML flow list of ROBOT:TYPE entries, unquoted (rcl cannot read them)
            name = arg.partition(":=")[0].split()[-1]  # (rcl quotes it with its -p)
            items = ", ".join(f'"{x.strip()}"' for x in value.strip("[]").split(",") if x.strip())
            detail += f"; entries with a colon need quotes: -p '{name}:=[{items}]'"
        return f"--ros-args: cannot parse {arg!r}: {form}{detail}"
    if "error creating node" in text and ("namespace" in text or "node name" in text):
        why = _first_error(text.split("error creating node: ", 1)[1]).replace("node name must", "a name must")
        ns = [v for k, v in _name_remaps(args) if k == "__ns"]
        return f"--ros-args: -r __ns:={ns[-1]}: {why}" if ns else f"--ros-args: {why}"
    return None


_PARAM_TYPES = {"BOOL": "a boolean", "INTEGER": "an integer", "DOUBLE": "a decimal number",
                "STRING": "a string", "BYTE_ARRAY": "a list of bytes", "BOOL_ARRAY": "a list of booleans",
                "INTEGER_ARRAY": "a list of integers", "DOUBLE_ARRAY": "a list of decimal numbers",
                "STRING_ARRAY": "a list of strings", "NOT_SET": "nothing"}


def parameter_type_text(text: str) -> str:
    """rclpy's InvalidParameterTypeException text as one line naming the parameter, the type it
    expects and what it got; a double given as an integer is told to add the decimal point."""
    m = re.match(r"Trying to set parameter '(.+?)' to '(.*)' of type '(\w+)', expecting type '(?:Type\.)?(\w+)'",
                 text, re.S)
    if not m:
        return text
    name, value, got, want = m.groups()
    if got == "BOOL":
        value = value.lower()  # as it was written
    wanted = "a boolean (true or false)" if want == "BOOL" else _PARAM_TYPES.get(want, want.lower())
    out = f"{name}: expected {wanted}, got {value} ({_PARAM_TYPES.get(got, got.lower())})"
    if want == "DOUBLE" and got == "INTEGER":  # ROS reads 10 as an integer
        out += f"; write it with a decimal point: -p {name}:={value}.0"
    elif want == "STRING" and got.endswith("_ARRAY"):  # a YAML list for a text parameter
        items = [x.strip().strip("'\"") for x in value.strip("[]").split(",") if x.strip()]
        out += f"; a list here is comma-separated text: -p {name}:={','.join(items)}"
    elif want == "STRING":  # YAML typed it
        out += f"; quote it to pass it as text: -p '{name}:=\"{value}\"'"
    elif want == "STRING_ARRAY" and got.endswith("_ARRAY"):
        out += f"; quote the items: -p '{name}:=[\"a\", \"b\"]'"
    return out


def parameters_read_at_start(cls):
    """Class decorator of a node that reads its parameters once, in ``__init__``: once it is built,
    setting any of them (``ros2 param set``) is refused with the reason, instead of being accepted
    and ignored (a later ``ros2 param get`` would then report a value not in effect). rclpy's own
    ``use_sim_time`` stays settable."""
    import functools

    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        init(self, *args, **kwargs)
        self.add_on_set_parameters_callback(_refuse_changes)

    cls.__init__ = __init__
    return cls


def _refuse_changes(params):
    from rcl_interfaces.msg import SetParametersResult

    names = [p.name for p in params if p.name != "use_sim_time"]
    if not names:
        return SetParametersResult(successful=True)
    return SetParametersResult(successful=False, reason=f"{', '.join(names)}: read once at start-up; restart the "
                                                        f"node with -p NAME:=VALUE to change it")


def declare_method_parameters(node) -> tuple[str, dict]:
    """Declare ``method`` and every option of a method a node runs (the table
    :func:`hmrta_msgs_py.params.method_parameters`, generated from :data:`hmrta.methods.METHODS`)
    on ``node``; return the live method and the options given that it takes (unset ones omitted),
    or, for a method that chooses per mission (portfolio), that method and every option given.
    Raises MethodError for an unknown method, an option value out of range, or a portfolio's
    checkpoint (its own or ``$HMRTA_CHECKPOINT``) or candidates that cannot run here; an option
    given that the method does not take is logged as ignored."""
    from hmrta.methods import MethodError, chooses, live_spec, node_options
    from hmrta.portfolio import checked

    from .params import method_parameters

    method_param, *option_params = method_parameters()
    method = node.declare_parameter(method_param.name, method_param.default).value
    opts = {}
    for p in option_params:
        value = node.declare_parameter(p.name, p.default).value
        if value != p.default:  # ROS has no None: the default stands for "not given"
            # checked even when the method does not take it, so that every node refuses the same values
            try:
                opts[p.name] = node_options()[p.name].coerce(method, value)
            except MethodError as e:
                raise MethodError(str(e).replace(f"{method}: option ", "", 1)) from None
    if chooses(method):  # portfolio: its options as given (the board chooses, agents adopt: hmrta.methods.adopt)
        checked(opts.get("checkpoint"), opts.get("candidates"))  # now, not when the board's choice runs
        return method, opts
    # the spec's shorthand and own checkpoint (rl-s5: sampled decisions, live one per turn; rl@broad)
    name, options = live_spec(method, opts)  # (of the options given, those the method takes)
    ignored = sorted(k for k in opts if k not in options)
    if ignored:  # (hmrta-mission refuses them; a launch file may set them for every node of a fleet)
        node.get_logger().warning(f"method {method} takes no {', '.join(ignored)}: "
                                  f"{'it is' if len(ignored) == 1 else 'they are'} ignored")
    return name, options


def parameters_help(params, width: int = 100) -> str:
    """Each ROS parameter (:class:`hmrta_msgs_py.params.Param`): name, type, default and meaning,
    wrapped at ``width`` columns; a meaning that lists choices ('a: ... | b: ...', the methods) gets
    a line per choice."""
    import textwrap

    lines = []
    for p in params:
        head = f"  {p.name} ({p.type}, default {p.default!r}): "
        w = max(width, len(head) + 40)  # (a long default: the meaning starts on its line all the same)
        first, *choices = p.help.split(" | ")
        lines += textwrap.wrap(first, w, initial_indent=head, subsequent_indent=" " * 6, break_on_hyphens=False)
        for c in choices:
            lines += textwrap.wrap(c, w, initial_indent=" " * 6 + "| ", subsequent_indent=" " * 8,
                                   break_on_hyphens=False)
    return "\n".join(lines)


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


SPUN = False  # spin_nodes was entered: an interrupt from now on is not one during start-up


# seconds the process may take, once its nodes stop, to destroy them, shut rclpy down and exit
TEARDOWN_TIMEOUT = 30.0
TEARDOWN_VAR = "HMRTA_TEARDOWN_TIMEOUT"  # overrides it (seconds, a positive number)
FINAL_GRACE = 5.0  # seconds after the timeout: the backstop that needs no Python (status 1)

# (exit status, what to add to the watchdog's line) replacing the nodes' own status once their
# teardown began: a crash (1, its traceback), or a signal that interrupted the teardown (128 + the
# signal, as console.stopped reports it)
_OVERRIDE: list[tuple[int, str]] = []


def teardown_limit() -> float:
    """``HMRTA_TEARDOWN_TIMEOUT`` when it is a positive finite number of seconds, else
    ``TEARDOWN_TIMEOUT``."""
    try:
        limit = float(os.environ.get(TEARDOWN_VAR, TEARDOWN_TIMEOUT))
    except ValueError:
        return TEARDOWN_TIMEOUT
    return limit if 0 < limit < float("inf") else TEARDOWN_TIMEOUT


def teardown_watchdog(prog: str, exit_status: Callable[[], int | None] | None = None) -> None:
    """Started when a process's nodes stop: should the rest of its life (destroying the nodes,
    shutting the middleware down, the interpreter's exit) take longer than :func:`teardown_limit`
    seconds, it prints the Python stack of every thread and one line on stderr, and ends the
    process with the status it would have had: ``exit_status()`` (None or no function: 0), 1
    after a crash, 128 + the signal that interrupted the teardown. So a middleware that hangs in
    its teardown never keeps a finished node alive (its work, such as a board's result, is
    written before). A daemon timer: it ends with the process. Where Python code can no longer
    run (late in the interpreter's finalization), a backstop ``FINAL_GRACE`` s later prints the
    stacks and exits with status 1."""
    import faulthandler

    limit = teardown_limit()

    def expired() -> None:
        code, note = _OVERRIDE[-1] if _OVERRIDE else (None, "")
        if code is None:
            try:
                code = exit_status() if exit_status is not None else None
            except Exception:  # (the process's state is what it is: exit all the same)
                code = 1
        code = 0 if code is None else int(code)
        try:
            faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
            flush = threading.Thread(target=sys.stdout.flush, daemon=True)  # (what was printed, if it can)
            flush.start()
            flush.join(1.0)
            os.write(2, f"{prog}: still shutting down {limit:g} s after its nodes stopped (the stacks above say "
                        f"where); exiting with status {code}{note}\n".encode())
        finally:
            os._exit(code)

    timer = threading.Timer(limit, expired)
    timer.daemon = True
    timer.start()
    faulthandler.dump_traceback_later(limit + FINAL_GRACE, exit=True)


def spin_nodes(nodes: list, until: Future | None = None, on_exit: Callable[[], None] | None = None,
               stopped: Callable[[str], str] | None = None,
               exit_status: Callable[[], int | None] | None = None, drain: float = 0.0) -> str | None:
    """Spin nodes on one executor until ``until`` completes, Ctrl-C / SIGTERM or external
    shutdown; then destroy the nodes and shut rclpy down (ros2/demos style). Returns the name of
    the signal that stopped it (SIGINT, SIGTERM), or None.

    In an HMRTA console script, once ``on_exit`` (if given) has run, the rest of the process's
    life is bounded by :func:`teardown_watchdog`, which exits with ``exit_status()`` should it
    run out.

    First warns about parameters given that no node declares. A signal before ``until`` is done
    is logged as one line (``stopped(signal)``, if given, says what was left undone).
    ``drain`` > 0: after a signal, the callbacks of what has already arrived run for up to that
    many seconds before ``on_exit`` (a recorder keeps the messages its readers hold).
    Spins in bounded slices (a signal is acted on within 0.5 s): the experimental events
    executor busy-waits and ignores signals when asked to spin without a timeout."""
    global SPUN
    SPUN = True
    # the stop handlers first: a supervisor (or a test) that signals the process as soon as it sees
    # the warnings below must get the stop of a running node (logged, exit status 0), not a start-up
    # interruption
    signals = _stop_on_signals()
    until = until if until is not None else Future()
    executor = None
    try:  # (a second signal raises KeyboardInterrupt at once, also while the executor is made)
        warn_unknown_parameters(nodes)
        executor = make_executor()
        for n in nodes:
            executor.add_node(n)
        while rclpy.ok() and not until.done() and "signal" not in signals:
            executor.spin_until_future_complete(until, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except BaseException:  # a crash: its traceback follows the teardown, and the status is 1
        import traceback

        _OVERRIDE.append((1, f"; it had crashed:\n{traceback.format_exc()}"))
        raise
    finally:
        signals["teardown"] = "yes"  # a signal from now on interrupts the teardown
        sig = signals.get("signal")
        if sig is not None and not until.done() and nodes:
            text = stopped(sig) if stopped is not None else f"stopped by {sig}"
            nodes[0].get_logger().info(text)
        if drain > 0 and sig is not None and executor is not None and rclpy.ok():
            _drain(executor, drain)
        if on_exit is not None:
            on_exit()
        if console.SCRIPT:  # (a process of someone else's that hosts nodes is left alone)
            teardown_watchdog(console.SCRIPT[0], exit_status)
        for n in nodes:
            n.destroy_node()
        if executor is not None:
            executor.shutdown()
        rclpy.try_shutdown()
    return sig


def _drain(executor, seconds: float) -> None:
    """Run the callbacks ready on ``executor`` (messages already received) for up to ``seconds``;
    a second signal (KeyboardInterrupt) ends it early, and so does a failing callback (said on
    stderr)."""
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=min(0.02, max(0.0, deadline - time.monotonic())))
    except KeyboardInterrupt:
        pass
    except Exception as e:  # noqa: BLE001 (the stop goes on: what was received is kept)
        sys.stderr.write(f"while taking the messages already received: {type(e).__name__}: {e}\n")


def _stop_on_signals() -> dict[str, str]:
    """Handle SIGINT and SIGTERM while the nodes spin: the first one is noted (``signal``: its
    name) and ends the spin after the callback running now, the context still valid (the stop is
    logged and the nodes are destroyed cleanly); a second one raises KeyboardInterrupt at once.
    Returns the dict that gets ``signal``. In a thread other than the main one: nothing."""
    from rclpy.signals import SignalHandlerOptions, get_current_signal_handlers_options, uninstall_signal_handlers

    got: dict[str, str] = {}
    if threading.current_thread() is not threading.main_thread():
        return got
    if get_current_signal_handlers_options() != SignalHandlerOptions.NO:
        uninstall_signal_handlers()  # rclpy's would shut the context down under the nodes

    def noted(sig: int, frame) -> None:
        if "teardown" in got:  # the process then ends as console.stopped says: 128 + the signal
            _OVERRIDE.append((128 + sig, ""))
            raise KeyboardInterrupt
        if "signal" in got:
            raise KeyboardInterrupt
        got["signal"] = signal.Signals(sig).name

    signal.signal(signal.SIGINT, noted)
    signal.signal(signal.SIGTERM, noted)
    return got


def unknown_parameters(node) -> list[tuple[str, str | None]]:
    """(name, closest declared name or None) of every parameter given to ``node`` (``-p``, a
    parameters file, overrides) that it does not declare."""
    given = set(getattr(node, "_parameter_overrides", {}) or {})  # rclpy keeps no public list of them
    declared = set(node._parameters) if hasattr(node, "_parameters") else set()
    return [(name, closest(name, declared)) for name in sorted(given - declared)]


def closest(name: str, names) -> str | None:
    """The one name of ``names`` most like ``name`` (a likely misspelling), or None: none is
    close, or several are equally close."""
    scored = sorted(((difflib.SequenceMatcher(None, name, n).ratio(), n) for n in set(names)), reverse=True)
    if not scored or scored[0][0] < 0.6 or (len(scored) > 1 and scored[1][0] == scored[0][0]):
        return None
    return scored[0][1]


def warn_unknown_parameters(nodes: list) -> None:
    """Warn once per process about each parameter given that its nodes do not declare (rclpy
    ignores them silently), naming the closest declared one and the node that has it, if any."""
    from .params import NODES, node_parameters

    seen: set[str] = set()
    for n in nodes:
        for name, close in unknown_parameters(n):
            if name in seen:
                continue
            seen.add(name)
            others = [k for k in NODES if any(p.name == name for p in node_parameters(k))]
            hint = (f"; did you mean {close}?" if close else "") + (f" ({name} is a parameter of {', '.join(others)})"
                                                                     if others else "")
            n.get_logger().warning(f"unknown parameter {name!r} ignored: {n.get_fully_qualified_name()} has no such "
                                   f"parameter{hint} (see {Path(sys.argv[0]).stem or n.get_name()} --help)")
    for n in nodes[:1]:  # every rclpy node has it; said once per process
        try:
            sim_time = n.get_parameter("use_sim_time").value
        except Exception:  # noqa: BLE001 - a node without it (rclpy declares it on every node)
            sim_time = False
        if sim_time is True:
            n.get_logger().warning("use_sim_time:=true changes nothing here: the mission runs on its own clock "
                                   "(clock_topic, default <mission_namespace>/hmrta/clock, published by sim_robot) "
                                   "and timeouts on wall time; a simulator's /clock moves nothing (docs/ros.md, Time)")


def mission_namespaces(node) -> list[str]:
    """The mission namespaces in which something publishes a mission on ``node``'s domain (topics
    ``<ns>/hmrta/mission`` with a publisher), as far as discovery knows now."""
    out = []
    try:
        found = node.get_topic_names_and_types()
    except Exception:  # noqa: BLE001 (the context is shutting down)
        return out
    for name, _ in found:
        if name.endswith("/hmrta/mission") and node.count_publishers(name) > 0:
            out.append(name[:-len("/hmrta/mission")] or "/")
    return sorted(out)


class BoardSilence:
    """When to warn that no task board is heard: ``after`` wall seconds without a message from
    it, then every 3 x ``after`` while the silence lasts (``after`` 0: never). ``mission`` is
    the topics of the node's mission namespace (default the root's)."""

    def __init__(self, after: float, now: Callable[[], float] = time.monotonic, mission=None):
        from .topics import MissionTopics

        self.after, self.now = after, now
        self.mission = mission or MissionTopics()
        self.since = now()  # the start, or the latest message heard
        self.ever = False  # whether a board was heard at all
        self.due = after

    def heard(self) -> str | None:
        """A message from the board: the silence ends. Where it was warned of, the line to log."""
        quiet, warned, ever = self.now() - self.since, self.due > self.after, self.ever
        self.since, self.ever, self.due = self.now(), True, self.after
        if not warned:
            return None
        return (f"the task board is heard again after {quiet:.0f} s" if ever else
                f"a task board is heard, after {quiet:.0f} s")

    def check(self, version: int | None = None, elsewhere: Callable[[], list[str]] | None = None) -> str | None:
        """The warning to log now, or None. ``elsewhere`` (called only for the warning that no
        board was ever heard): the mission namespaces in which a mission has a publisher on this
        domain (:func:`mission_namespaces`), named when this node's is not among them."""
        quiet = self.now() - self.since
        if self.after <= 0 or quiet < self.due:
            return None
        self.due += 3 * self.after
        if not self.ever:
            env, T = os.environ, self.mission
            others = sorted(set(elsewhere() if elsewhere is not None else ()) - {T.namespace})
            seen = (f"; a board publishes in mission namespace {', '.join(others)}: is this node's mission_namespace "
                    f"right?" if others else "")
            return (f"no task board heard for {quiet:.0f} s (nothing on {T.mission} or {T.board}): is task_board "
                    f"running, with the same ROS_DOMAIN_ID ({env.get('ROS_DOMAIN_ID') or 'unset: 0'}), "
                    f"{DISCOVERY_VAR} ({env.get(DISCOVERY_VAR) or 'unset: SUBNET'}) and mission_namespace "
                    f"({T.namespace}) as this process?{seen} (A mission that is over has no board: it exits "
                    f"when it is done.) Still waiting")
        return (f"the task board has not been heard for {quiet:.0f} s"
                + (f" (its latest version {version})" if version is not None else "")
                + ": it stopped, or the network to it is down; still waiting (a board restarted on its journal "
                  "resumes the mission)")

