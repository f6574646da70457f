"""hmrta-task: submit, cancel and list a running mission's tasks (operator interface).

    hmrta-task add --location 0.3,0.7 --requirements 1,0,2 --duration 3 [--id inspect-7]
    hmrta-task add --metres --location 12.5,30 ...   (map metres: divided by the mission's scale)
    hmrta-task cancel inspect-7        (or a task of the mission by its index: hmrta-task cancel 3)
    hmrta-task list

``add`` and ``cancel`` publish an ``hmrta-task-request/1`` on ``<ns>/hmrta/task_requests`` (``<ns>``:
``--mission-namespace``, default ``/``) and wait for the board's answer on
``<ns>/hmrta/task_events`` (``hmrta-task-event/1``): the request carries a
fresh ``request_id`` that the board echoes, so only the answer to this very request counts (never
a stored answer to an earlier request for the same task id); ``list`` asks the board for a
keyframe of its current version (``<ns>/hmrta/keyframe_requests``) and prints its tasks (the latched
keyframe when the board does not answer within a few seconds: a mission that is over). Exit
status: 0 accepted (or listed), 3 rejected by the board (the reason is printed), 1 no answer
within ``--timeout`` seconds (no board on this ROS domain?), 2 user error, 130 Ctrl-C while waiting.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
import uuid


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _floats(text: str) -> list[float]:
    try:
        return [_number(x) for x in text.split(",") if x.strip()]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected comma-separated finite numbers, got {text!r}") from None


def _point(text: str) -> list[float]:
    v = _floats(text)
    if len(v) != 2:
        raise argparse.ArgumentTypeError(f"expected x,y, got {text!r}")
    return v


def task_words(tasks: dict, m: int, clock: float | None) -> str:
    """What task ``m`` of a board state's ``tasks`` (hmrta-state/1) is doing, in words, at the
    mission clock ``clock`` (None: not heard): the state runs ahead of the clock (a coalition
    formed now starts when its last member arrives), so its times say more than its status."""
    status, start, finish = tasks["status"][m], tasks["start"][m], tasks["finish"][m]
    n = len(tasks["members"][m])

    def at(x) -> str:
        return "?" if x is None else f"{x:.3f}"

    if status == "empty":
        return "no robot committed yet"
    if status == "unreleased":
        return f"not known before t={at(tasks['release'][m])}"
    if status == "open":
        return f"coalition forming: {n} robot(s) committed"
    if status == "in_progress":
        if clock is not None and start is not None and clock < start:
            return f"coalition of {n} on its way: starts t={at(start)}, finishes t={at(finish)}"
        return f"under way since t={at(start)} ({n} robots), finishes t={at(finish)}"
    if status == "done":
        return f"finished t={at(finish)}"
    if status == "cancelled":
        return "cancelled by the operator" if tasks["cancelled_by_operator"][m] else \
            "cancelled: no robot left can do it"
    return ""


def _spin_until(node, done, until: float, step: float = 0.05) -> None:
    """Spin ``node`` until ``done()`` is true or the monotonic clock reaches ``until``."""
    import rclpy

    while not done() and time.monotonic() < until:
        rclpy.spin_once(node, timeout_sec=step)


def _domain(args) -> str:
    """The ROS domain this client uses: --domain-id, else $ROS_DOMAIN_ID, else ROS's default 0."""
    return str(args.domain_id if args.domain_id is not None else (os.environ.get("ROS_DOMAIN_ID") or 0))


def main(argv: list[str] | None = None) -> int:
    from hmrta.cli import Parser  # bad arguments: one line
    from hmrta.instance import CONTROL, MAX_VALUE

    p = Parser(prog="hmrta-task", description=__doc__.split("\n\n")[0])
    p.add_argument("--timeout", type=_number, default=10.0, help="seconds to wait for the board (default 10)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS domain 0..232 (default: $ROS_DOMAIN_ID)")
    p.add_argument("--mission-namespace", default="/", metavar="NS",
                   help="the mission's namespace (its nodes' mission_namespace: topics NS/hmrta/...; default /)")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="{add,cancel,list}")
    a = sub.add_parser("add", help="submit a task")
    a.add_argument("--location", type=_point, required=True, metavar="X,Y",
                   help="in the unit square [0, 1] (mission coordinates); with --metres, in metres")
    a.add_argument("--metres", action="store_true",
                   help="--location is in metres on the mission's map (its frame_id, as the robots' poses): "
                        "divided by the mission's scale, read from its board")
    a.add_argument("--requirements", type=_floats, required=True, metavar="R1,R2,...",
                   help=f"one per skill of the mission, each in [0, {MAX_VALUE:g}], not all 0")
    a.add_argument("--duration", type=_number, required=True,
                   help=f"the work's duration (mission time units), in [0, {MAX_VALUE:g}] as in a mission file")
    a.add_argument("--id", default=None, help="client task id (default: a random one)")
    c = sub.add_parser("cancel", help="cancel a task by its id")
    c.add_argument("id", help="an operator's task id, or a task of the mission by its index (hmrta-task list)")
    ls = sub.add_parser("list", help="the mission's tasks and their status, the board's state clock and the mission clock")
    ls.add_argument("--clock-topic", default=None, help="the mission clock's topic, if the mission renamed it "
                                                        "(its nodes' clock_topic; default NS/hmrta/clock)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.timeout <= 0:
        p.error("--timeout: expected a positive number")
    from hmrta_msgs_py.topics import MissionTopics, check_mission_namespace

    try:
        T = MissionTopics(check_mission_namespace(args.mission_namespace, "--mission-namespace"))
    except ValueError as e:
        p.error(str(e))
    if getattr(args, "clock_topic", None) is not None:
        from hmrta_msgs_py.topics import check_clock_topic

        try:
            check_clock_topic(args.clock_topic, "--clock-topic")
        except ValueError as e:
            p.error(str(e))
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        p.error(f"--domain-id: expected a ROS domain id in 0..232, got {args.domain_id}")
    if args.cmd == "add":  # a mission file's bounds (hmrta.instance): what the board accepts too
        if not 0 <= args.duration <= MAX_VALUE:
            a.error(f"--duration: expected a number in [0, {MAX_VALUE:g}], got {args.duration:g}")
        if not all(0 <= r <= MAX_VALUE for r in args.requirements) or not any(args.requirements):
            a.error(f"--requirements: expected numbers in [0, {MAX_VALUE:g}], at least one of them non-zero, got "
                    f"{','.join(f'{r:g}' for r in args.requirements)}")
        if not all(0 <= v <= (math.inf if args.metres else 1) for v in args.location):
            want = "metres >= 0 (--metres)" if args.metres else "in the unit square [0, 1]"
            a.error(f"--location: expected x,y {want}, got {args.location[0]:g},{args.location[1]:g}")
        if args.id is not None and not args.id.strip():
            a.error("--id: expected a task id (leave the option out for a random one), got an empty one")
        if args.id is not None and CONTROL.search(args.id):  # (the board refuses it)
            a.error(f"--id: expected a task id on one line, got a control character in {args.id!a}")
    if args.cmd == "cancel":
        if not args.id.strip():
            c.error("id: expected a task id (hmrta-task list shows them), got an empty one")
        if CONTROL.search(args.id):
            c.error(f"id: expected a task id on one line, got a control character in {args.id!a}")

    import rclpy
    from rclpy.executors import ExternalShutdownException
    from std_msgs.msg import String

    from hmrta_msgs_py import topics
    from hmrta_msgs_py.codec import (DecodeError, KeyframeRequest, TaskRequest, board_from_msg,
                                     keyframe_request_to_msg, task_event_from_msg, task_request_to_msg)

    rclpy.init(args=[], domain_id=args.domain_id) if args.domain_id is not None else rclpy.init(args=[])
    node = rclpy.create_node(f"hmrta_task_{uuid.uuid4().hex[:6]}")
    deadline = time.monotonic() + args.timeout
    try:
        if args.cmd == "list":
            from rosgraph_msgs.msg import Clock

            from hmrta_msgs_py.codec import clock_from_msg

            got: list = []
            now: list = []  # the mission clock (latched): the state's clock stays at the last completion while closing
            node.create_subscription(String, T.keyframe, got.append, topics.KEYFRAME_QOS)
            node.create_subscription(Clock, args.clock_topic or T.clock, lambda m: now.append(clock_from_msg(m)),
                                     topics.CLOCK_QOS)
            ask = node.create_publisher(String, T.keyframe_requests, topics.KEYFRAME_REQUEST_QOS)
            _spin_until(node, lambda: got, deadline, step=0.1)
            if not got:
                print(f"hmrta-task: no board within {args.timeout:g} s (nothing on {T.keyframe}: is a mission running "
                      f"on ROS domain {_domain(args)}, in mission namespace {T.namespace}? hmrta-mission prints "
                      f"its domain and namespace: --domain-id, --mission-namespace)", file=sys.stderr)
                return 1
            try:
                b = board_from_msg(got[-1])
            except DecodeError as e:
                print(f"hmrta-task: unreadable board: {e}", file=sys.stderr)
                return 1
            # the latched keyframe may be older than the board's version: ask for the current one
            fresh = min(deadline, time.monotonic() + 3.0)
            n = len(got)
            while len(got) == n and time.monotonic() < fresh:
                if ask.get_subscription_count() > 0:
                    ask.publish(keyframe_request_to_msg(KeyframeRequest(b.session, -1, "hmrta-task list")))
                end = time.monotonic() + 0.5
                _spin_until(node, lambda: len(got) != n, min(end, fresh))
            try:
                b = board_from_msg(got[-1])
            except DecodeError as e:
                print(f"hmrta-task: unreadable board: {e}", file=sys.stderr)
                return 1
            t = b.state["tasks"]
            names = t.get("names") or [None] * len(t["status"])
            _spin_until(node, lambda: now, deadline)  # the latched clock, if not heard yet (discovery)
            clock = f"mission clock {now[-1]:.3f}" if now else "mission clock not heard"
            print(f"board {b.version}, phase {b.phase}, state at t={b.clock:.3f} (its last event), {clock}: "
                  f"{b.n_done}/{b.n_tasks} tasks done")
            for m, status in enumerate(t["status"]):
                print(f"  {m:4d} {names[m] or '-':>16} {status:<11} {task_words(t, m, now[-1] if now else None)}")
            return 0
        rid = args.id if args.cmd == "cancel" or args.id is not None else f"task-{uuid.uuid4().hex[:8]}"
        task = None
        if args.cmd == "add" and args.metres:  # metres -> mission coordinates: the mission's scale
            from hmrta_msgs_py.codec import mission_from_msg

            missions: list = []
            node.create_subscription(String, T.mission, missions.append, topics.MISSION_SUB_QOS)
            _spin_until(node, lambda: missions, deadline)
            if not missions:
                print(f"hmrta-task: no mission heard on {T.mission} within {args.timeout:g} s (its scale turns "
                      f"--metres into mission coordinates)", file=sys.stderr)
                return 1
            try:
                scale = mission_from_msg(missions[-1]).scale
            except DecodeError as e:
                print(f"hmrta-task: unreadable mission: {e}", file=sys.stderr)
                return 1
            x, y = args.location
            if not (x <= scale and y <= scale):
                print(f"hmrta-task: error: --location {x:g},{y:g} m is outside the mission's map, [0, {scale:g}] m on "
                      f"each axis (scale {scale:g} m per mission unit)", file=sys.stderr)
                return 2
            args.location = [x / scale, y / scale]
        if args.cmd == "add":
            task = {"location": args.location, "requirements": args.requirements, "duration": args.duration}
        answers: list = []
        nonce = uuid.uuid4().hex  # this request's id: the board echoes it in its answer

        def on_event(msg: String) -> None:
            try:
                e = task_event_from_msg(msg)
            except DecodeError:
                return
            if e.request_id == nonce and e.event in ("accepted", "rejected"):
                answers.append(e)

        node.create_subscription(String, T.task_events, on_event, topics.TASK_EVENT_QOS)
        pub = node.create_publisher(String, T.task_requests, topics.TASK_REQUEST_QOS)
        _spin_until(node, lambda: pub.get_subscription_count() > 0, deadline)
        if pub.get_subscription_count() == 0:
            print(f"hmrta-task: no board listens on {T.task_requests} (waited {args.timeout:g} s)",
                  file=sys.stderr)
            return 1
        pub.publish(task_request_to_msg(TaskRequest(args.cmd, rid, task, nonce)))
        _spin_until(node, lambda: answers, deadline)
        if not answers:
            print(f"hmrta-task: no answer to {args.cmd} {rid!r} within {args.timeout:g} s", file=sys.stderr)
            return 1
        e = answers[0]
        if e.event == "rejected":
            print(f"hmrta-task: {args.cmd} {rid!r} rejected: {e.reason}", file=sys.stderr)
            return 3
        print(f"{rid}: {args.cmd} accepted at t={e.t:.3f}" + (f" (task {e.task})" if e.task is not None else ""))
        return 0
    except (KeyboardInterrupt, ExternalShutdownException):  # Ctrl-C while it waits (rclpy's handler shuts down)
        print(f"hmrta-task: interrupted while waiting for the board ({args.cmd})", file=sys.stderr)
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
