"""Console scripts of hmrta_coordinator (setup.py): each imports its module only when it runs, so
that a Ctrl-C during the imports ends quietly (:mod:`hmrta_msgs_py.console`)."""
from hmrta_msgs_py.console import run


def task_board() -> None:
    run("task_board", "hmrta_coordinator.task_board")


def sim_robot() -> None:
    run("sim_robot", "hmrta_coordinator.sim_robot")


def recorder() -> None:
    run("recorder", "hmrta_coordinator.recorder")


def mission() -> None:
    run("hmrta-mission", "hmrta_coordinator.mission")


def task_cli() -> None:
    run("hmrta-task", "hmrta_coordinator.task_cli")
