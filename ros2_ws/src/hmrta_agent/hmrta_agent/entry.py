"""Console scripts of hmrta_agent (setup.py): each imports its node module only when it runs, so
that a Ctrl-C during the imports ends quietly (:mod:`hmrta_msgs_py.console`)."""
from hmrta_msgs_py.console import run


def agent_node() -> None:
    run("agent_node", "hmrta_agent.agent_node")
