"""``python -m hmrta_msgs_py.run_node PROG MODULE [ARGS ...]``: run a node module as its console
script runs it (:func:`hmrta_msgs_py.console.run`), its signal handling in place before the module's
imports. How ``hmrta-mission`` starts its children: started as ``python -m MODULE``, a node
interrupted in its first second (loading rclpy, numpy) left a ``KeyboardInterrupt`` traceback in
its log instead of the one line ``interrupted during start-up``. A signal even before
:mod:`~hmrta_msgs_py.console` has loaded is noted here first and said the same way. (The
launcher starts its children with SIGINT ignored, so that none comes while the interpreter
itself starts; it is taken over here, on the first line.)"""
import signal
import sys

_EARLY: list[int] = []


def _note(sig: int, frame) -> None:
    _EARLY.append(sig)


if __name__ == "__main__":
    term = signal.signal(signal.SIGTERM, _note)
    signal.signal(signal.SIGINT, _note)
    from hmrta_msgs_py import console

    signal.signal(signal.SIGINT, signal.default_int_handler)  # (console.run installs its own over these)
    signal.signal(signal.SIGTERM, term)
    prog, module, *rest = sys.argv[1:]
    sys.argv = [prog, *rest]  # what the node reads, as from its console script
    if _EARLY:
        console.INTERRUPTED.extend(_EARLY)
        console.stopped(prog)
    console.run(prog, module)
