"""The launch files, run against small stand-ins of ``launch`` / ``launch_ros`` (not installable
here): every launch argument maps onto a parameter the target node really declares (read from
the node sources), every board and robot parameter is exposed, external robots get no agent, a
fleet file gives one agent per robot with its remaps."""
from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

from test_help import NODE_SOURCES, declared_parameters

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "ros2_ws" / "src"
MISSION = SRC / "hmrta_coordinator" / "launch" / "mission.launch.py"
FLEET = SRC / "hmrta_coordinator" / "launch" / "fleet.launch.py"
AGENT = SRC / "hmrta_agent" / "launch" / "agent.launch.py"
EXECUTABLES = {("hmrta_coordinator", "task_board"): "task_board", ("hmrta_coordinator", "sim_robot"): "sim_robot",
               ("hmrta_agent", "agent_node"): "agent_node"}
# launch arguments that are not node parameters, and what they are
LAUNCH_ONLY = {
    MISSION: {"fleet": "fleet file", "remaps": "board remappings"},
    FLEET: {"fleet": "fleet file", "board": "start the board", "remaps": "board remappings"},
    AGENT: {"goal_topic": "goal remapping", "pose_topic": "pose remapping"},
}
# launch defaults that differ from the node's on purpose
OWN_DEFAULTS = {MISSION: {"output": "mission.json"}, FLEET: {"output": "mission.json"}, AGENT: {"robot": "robot_0"}}
# the nodes each launch file starts, and the parameters it sets itself rather than by argument
TARGETS = {MISSION: {"task_board": (), "sim_robot": (), "agent_node": ("robot", "index", "species", "key_file")},
           FLEET: {"task_board": (), "agent_node": ("robot", "index", "species", "key_file")},
           AGENT: {"agent_node": ()}}


class Action:
    def __init__(self, *args, **kw):
        self.args, self.kw = args, kw


class LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


def fake_launch() -> dict[str, types.ModuleType]:
    def mod(name, **attrs):
        m = types.ModuleType(name)
        m.__dict__.update(attrs)
        return m

    class DeclareLaunchArgument(Action):
        def __init__(self, name, default_value=None, description=""):
            super().__init__(name)
            self.name, self.default_value, self.description = name, default_value, description

    class LaunchDescription(Action):
        def __init__(self, entities):
            super().__init__()
            self.entities = list(entities)

    return {
        "launch": mod("launch", LaunchDescription=LaunchDescription),
        "launch.actions": mod("launch.actions", DeclareLaunchArgument=DeclareLaunchArgument,
                              OpaqueFunction=type("OpaqueFunction", (Action,), {}),
                              Shutdown=type("Shutdown", (Action,), {})),
        "launch.substitutions": mod("launch.substitutions", LaunchConfiguration=LaunchConfiguration),
        "launch_ros": mod("launch_ros"),
        "launch_ros.actions": mod("launch_ros.actions", Node=type("Node", (Action,), {})),
        "launch_ros.parameter_descriptions": mod("launch_ros.parameter_descriptions",
                                                 ParameterValue=type("ParameterValue", (Action,), {})),
    }


@pytest.fixture
def launch_file(monkeypatch):
    """run(path, **args) -> (declared arguments {name: (default, description)}, started nodes)."""
    for name, m in fake_launch().items():
        monkeypatch.setitem(sys.modules, name, m)

    def run(path: Path, **given: str):
        spec = importlib.util.spec_from_file_location(f"launch_under_test_{path.stem.split('.')[0]}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        ld = module.generate_launch_description()
        declared = {e.name: (e.default_value, e.description) for e in ld.entities if hasattr(e, "default_value")}
        unknown = set(given) - set(declared)
        assert not unknown, f"{path.name} has no launch argument {unknown}"
        context = types.SimpleNamespace(launch_configurations={**{k: v[0] for k, v in declared.items()}, **given})
        nodes = []
        for e in ld.entities:
            if type(e).__name__ == "OpaqueFunction":
                nodes += e.kw["function"](context)
        return declared, nodes

    return run


def node_of(n) -> str:
    return EXECUTABLES[(n.kw["package"], n.kw["executable"])]


def params_of(n) -> dict:
    out = {}
    for p in n.kw.get("parameters", []):
        out.update(p)
    return out


DECLARED = {node: declared_parameters(src) for node, src in NODE_SOURCES.items()}


@pytest.mark.parametrize("path", [MISSION, FLEET, AGENT], ids=lambda p: p.name)
def test_arguments_map_onto_declared_parameters(launch_file, path):
    args, _ = launch_file(path, **({"fleet": str(SRC / "hmrta_coordinator" / "config" / "fleet.yaml")} if path == FLEET else {}))
    targets = TARGETS[path]
    for name, (default, description) in args.items():
        assert description, f"{path.name}: argument {name} has no description"
        if name in LAUNCH_ONLY[path]:
            continue
        owners = [node for node in targets if name in DECLARED[node]]
        assert owners, f"{path.name}: argument {name} is no parameter of {', '.join(targets)}"
        for node in owners:
            typ, node_default = DECLARED[node][name]
            node_default = OWN_DEFAULTS[path].get(name, node_default)
            if typ != "string_array":
                assert str(default).lower() == str(node_default).lower(), \
                    f"{path.name}: {name} defaults to {default!r}, {node} to {node_default!r}"
    # every parameter is exposed, but those the launch file sets per robot
    for node, own in targets.items():
        missing = sorted(set(DECLARED[node]) - set(args) - set(own))
        assert not missing, f"{path.name} does not expose {node} parameters {missing}"


def test_mission_launch_starts_board_sim_and_one_agent_per_robot(launch_file):
    _, nodes = launch_file(MISSION, seed="3", method="random")
    kinds = [node_of(n) for n in nodes]
    assert kinds.count("task_board") == 1 and kinds.count("sim_robot") == 1 and kinds.count("agent_node") == 15
    for n in nodes:
        node = node_of(n)
        unknown = set(params_of(n)) - set(DECLARED[node])
        assert not unknown, f"{node} is given parameters it does not declare: {unknown}"
    board = params_of(nodes[0])
    # unset method option; an empty string array (ROS cannot type an empty list: the node's default)
    assert set(DECLARED["task_board"]) - set(board) <= {"checkpoint", "pose_types"}
    assert board["seed"] == 3 and board["method"] == "random" and board["robot_names"][14] == "robot_14"
    assert nodes[0].kw["on_exit"] is not None
    agents = [n for n in nodes if node_of(n) == "agent_node"]
    assert [n.kw["namespace"] for n in agents] == [f"/robot_{i}" for i in range(15)]
    assert all(params_of(a)["seed"] == 3 and params_of(a)["method"] == "random" for a in agents)


def test_mission_launch_passes_real_fleet_parameters(launch_file):
    _, nodes = launch_file(MISSION, scale="2.5", frame_id="odom", arrival_tolerance="0.25",
                           real_time_departures="true", time_scale="1.0", exit_on_done="false",
                           remaps="/robot_1/pose:=/tb3_1/pose_stamped", checkpoint="/x.pt")
    board, sim = params_of(nodes[0]), params_of(nodes[1])
    assert (board["scale"], board["frame_id"], board["arrival_tolerance"], board["real_time_departures"]) == \
        (2.5, "odom", 0.25, True)
    assert board["exit_on_done"] is False and sim["exit_on_done"] is False and sim["time_scale"] == 1.0
    assert board["checkpoint"] == "/x.pt"
    assert nodes[0].kw["remappings"] == [("/robot_1/pose", "/tb3_1/pose_stamped")]


def test_external_robots_get_no_agent(launch_file, tmp_path):
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("robots:\n  - {name: robot_4, namespace: /tb3_4, pose_topic: /tb3_4/pose,"
                     " goal_topic: /tb3_4/goal_pose}\n")
    _, nodes = launch_file(MISSION, external="robot_1,robot_2", fleet=str(fleet))
    agents = {params_of(n)["robot"] for n in nodes if node_of(n) == "agent_node"}
    assert agents == {f"robot_{i}" for i in range(15)} - {"robot_1", "robot_2", "robot_4"}
    assert params_of(nodes[1])["external"] == ["robot_1", "robot_2", "robot_4"]
    assert ("/robot_4/pose", "/tb3_4/pose") in nodes[0].kw["remappings"]


def test_mission_launch_rejects_unknown_external(launch_file):
    with pytest.raises(ValueError, match="external: robot_99 not among"):
        launch_file(MISSION, external="robot_99")


def test_fleet_launch_one_agent_per_robot(launch_file):
    fleet = SRC / "hmrta_coordinator" / "config" / "fleet.yaml"
    from hmrta_coordinator.launching import load_fleet

    robots = load_fleet(fleet)
    _, nodes = launch_file(FLEET, fleet=str(fleet), method="random", seed="5")
    assert [node_of(n) for n in nodes] == ["agent_node"] * len(robots)
    for n, r in zip(nodes, robots):
        assert n.kw["namespace"] == r.namespace and params_of(n)["robot"] == r.name
        assert params_of(n)["seed"] == 5 and params_of(n)["method"] == "random"
        pose = [("pose", r.pose_topic)] if r.pose_topic != f"{r.namespace}/pose" else []
        assert n.kw["remappings"] == ([("goal_pose", r.goal_topic)] if r.goal_topic != "goal_pose" else []) + pose
        assert params_of(n).get("species", -1) == r.species
        assert params_of(n).get("pose_type", "PoseStamped") == r.pose_type
        assert set(params_of(n)) <= set(DECLARED["agent_node"])
    _, nodes = launch_file(FLEET, fleet=str(fleet), board="true")
    assert node_of(nodes[0]) == "task_board" and len(nodes) == len(robots) + 1
    assert set(params_of(nodes[0])) <= set(DECLARED["task_board"])
    assert sorted(nodes[0].kw["remappings"]) == sorted((f"/{r.name}/pose", r.pose_topic) for r in robots
                                                       if r.pose_topic != f"/{r.name}/pose")


def test_a_fleet_robot_agent_reads_its_pose_as_the_board_does(launch_file, tmp_path):
    """The agent stops a dropped robot at its pose: it subscribes the fleet file's pose topic and
    type, as the board does (the pose_type argument where the fleet file has none)."""
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("robots:\n  - {name: robot_1, namespace: /tb3_1, pose_topic: /tb3_1/amcl_pose,"
                     " pose_type: PoseWithCovarianceStamped, goal_topic: /tb3_1/goal_pose}\n"
                     "  - {name: robot_2, namespace: /tb3_2, pose_topic: /tb3_2/pose}\n"
                     "  - {name: robot_3, namespace: /tb3_3, pose_topic: /tb3_3/odom, pose_type: Odometry}\n")
    _, nodes = launch_file(FLEET, fleet=str(fleet), board="true")
    board, a1, a2, a3 = nodes
    assert params_of(a1)["pose_type"] == "PoseWithCovarianceStamped" and params_of(a3)["pose_type"] == "Odometry"
    assert params_of(a2)["pose_type"] == "PoseStamped"
    assert a1.kw["remappings"] == [("goal_pose", "/tb3_1/goal_pose"), ("pose", "/tb3_1/amcl_pose")]
    assert a2.kw["remappings"] == [] and a3.kw["remappings"] == [("pose", "/tb3_3/odom")]
    assert sorted(params_of(board)["pose_types"]) == ["robot_1:PoseWithCovarianceStamped", "robot_3:Odometry"]
    _, nodes = launch_file(FLEET, fleet=str(fleet), board="true", pose_type="Odometry")
    assert [params_of(n)["pose_type"] for n in nodes[1:]] == ["PoseWithCovarianceStamped", "Odometry", "Odometry"]
    assert params_of(nodes[0])["pose_type"] == "Odometry"


def test_agent_launch(launch_file):
    _, nodes = launch_file(AGENT, robot="robot_3", goal_topic="/tb3_3/goal_pose", keystore="/k")
    (n,) = nodes
    assert n.kw["namespace"] == "/robot_3" and n.kw["remappings"] == [("goal_pose", "/tb3_3/goal_pose")]
    assert params_of(n)["robot"] == "robot_3" and params_of(n)["keystore"] == "/k"
    assert set(params_of(n)) <= set(DECLARED["agent_node"])
    _, (n,) = launch_file(AGENT, robot="robot_3", pose_topic="/tb3_3/amcl_pose", pose_type="PoseWithCovarianceStamped")
    assert n.kw["remappings"] == [("goal_pose", "goal_pose"), ("pose", "/tb3_3/amcl_pose")]
    assert params_of(n)["pose_type"] == "PoseWithCovarianceStamped"
    _, (n,) = launch_file(AGENT, robot="robot_3", mission_namespace="/fleet1/")
    assert n.kw["namespace"] == "/fleet1/robot_3" and params_of(n)["mission_namespace"] == "/fleet1/"


def test_launch_files_in_a_mission_namespace(launch_file, tmp_path):
    """mission_namespace reaches every node; simulated robots' agents run in <ns>/<robot>; a fleet
    robot's default topics and the board's pose remaps are in the mission namespace."""
    _, nodes = launch_file(MISSION, mission_namespace="/fleet1")
    assert all(params_of(n)["mission_namespace"] == "/fleet1" for n in nodes)
    agents = [n for n in nodes if node_of(n) == "agent_node"]
    assert [n.kw["namespace"] for n in agents] == [f"/fleet1/robot_{i}" for i in range(15)]
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("robots:\n  - {name: robot_4}\n  - {name: robot_5, namespace: /tb3_5, pose_topic: /tb3_5/pose}\n")
    _, nodes = launch_file(FLEET, fleet=str(fleet), board="true", mission_namespace="/fleet1")
    assert [n.kw["namespace"] for n in nodes[1:]] == ["/fleet1/robot_4", "/tb3_5"]
    assert nodes[0].kw["remappings"] == [("/fleet1/robot_5/pose", "/tb3_5/pose")]
    with pytest.raises(ValueError, match="mission_namespace: expected an absolute ROS namespace"):
        launch_file(MISSION, mission_namespace="fleet1")


@pytest.mark.parametrize("text,error", [
    ("robots: []\n", r"robots: expected a non-empty list"),
    ("robots:\n  - {namespace: /a}\n", r"robots\[0\]\.name: expected a robot name"),
    ("robots:\n  - {name: r0, pose_type: Twist}\n", r"robots\[0\]\.pose_type: expected one of PoseStamped"),
    ("robots:\n  - {name: r0, colour: red}\n", r"robots\[0\]: unknown field 'colour'"),
    ("robots:\n  - {name: r0, species: -3}\n", r"robots\[0\]\.species: expected a species index"),
    ("robots:\n  - {name: r0}\n  - {name: r0}\n", r"robots: a robot is listed twice"),
    ("robots: [\n", r"cannot read the fleet file"),
])
def test_fleet_file_errors_name_file_and_field(tmp_path, text, error):
    from hmrta_coordinator.launching import load_fleet

    f = tmp_path / "fleet.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=rf"^{f}: {error}"):
        load_fleet(f)


def test_fleet_file_defaults(tmp_path):
    from hmrta_coordinator.launching import FleetRobot, load_fleet

    f = tmp_path / "fleet.yaml"
    f.write_text("robots:\n  - {name: robot_2}\n")
    assert load_fleet(f) == [FleetRobot("robot_2", "/robot_2", "/robot_2/pose")]
    assert load_fleet(f, "/fleet1") == [FleetRobot("robot_2", "/fleet1/robot_2", "/fleet1/robot_2/pose")]
