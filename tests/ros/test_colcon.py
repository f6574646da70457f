"""ros2_ws builds with colcon from PyPI (ros2_ws/colcon-requirements.txt, in a venv of its own):
``colcon build --symlink-install`` lays out the install tree ``ros2 run`` / ``ros2 launch`` expect,
with links into the sources, and a greedy mission runs from the installed executables. Also:
each package's ``package.xml`` declares exactly what its Python files import."""
from __future__ import annotations

import ast
import fcntl
import hashlib
import json
import os
import random
import re
import shutil
import subprocess
import sys
import urllib.request
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
WS = ROOT / "ros2_ws"
SRC = WS / "src"
PACKAGES = ("hmrta_msgs_py", "hmrta_agent", "hmrta_coordinator")
REQUIREMENTS = WS / "colcon-requirements.txt"
PYPI_PROBE = "https://pypi.org/simple/colcon-core/"


def console_scripts(pkg: str) -> list[str]:
    """The console scripts a package's setup.py declares ('name = module:function')."""
    tree = ast.parse((SRC / pkg / "setup.py").read_text())
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str):
            m = re.fullmatch(r"\s*([\w.-]+)\s*=\s*[\w.]+:\w+\s*", n.value)
            if m:
                out.append(m.group(1))
    return out


def _colcon_venv() -> Path:
    """A venv with the pinned colcon, kept in .venv/colcon-<hash of the pins> (rebuilt when the
    pins change; made under a lock, marked complete last)."""
    pins = REQUIREMENTS.read_bytes()
    key = hashlib.sha256(pins + sys.version.encode()).hexdigest()[:12]
    base = Path(sys.prefix)  # the project's venv: gitignored, removed by make clean-venv
    venv = base / f"colcon-{key}"
    done = venv / ".complete"
    with open(base / ".colcon-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if done.exists():
            return venv
        shutil.rmtree(venv, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
        py = venv / "bin" / "python"
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PIP_REQUIRE_VIRTUALENV")}
        r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", "-r",
                            str(REQUIREMENTS)], capture_output=True, text=True, timeout=600, env=env)
        if r.returncode != 0:
            shutil.rmtree(venv, ignore_errors=True)
            try:
                urllib.request.urlopen(PYPI_PROBE, timeout=15).close()
            except OSError as e:
                pytest.skip(f"PyPI is unreachable ({e}): cannot install colcon")
            raise AssertionError(f"pip install -r {REQUIREMENTS.name} failed:\n{r.stdout[-2000:]}{r.stderr[-3000:]}")
        done.write_text(pins.decode())
        return venv


def _sourced_env(install: Path, base: dict[str, str]) -> dict[str, str]:
    """``base`` after ``. install/setup.sh`` (what a user does before ros2 run)."""
    r = subprocess.run(["sh", "-c", '. "$1/setup.sh" && env -0', "sh", str(install)], capture_output=True,
                       env=base, timeout=60)
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    return dict(line.split("=", 1) for line in r.stdout.decode().split("\0") if "=" in line)


@pytest.fixture(scope="module")
def colcon_build(tmp_path_factory):
    """(workspace folder, colcon output) after colcon build --symlink-install of ros2_ws/src."""
    venv = _colcon_venv()
    ws = tmp_path_factory.mktemp("colcon_ws")
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH", "VIRTUAL_ENV")
           and not k.startswith("COLCON")}
    env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '/usr/bin:/bin')}"
    r = subprocess.run([str(venv / "bin" / "colcon"), "--log-base", str(ws / "log"), "build", "--symlink-install",
                        "--base-paths", str(SRC), "--build-base", str(ws / "build"), "--install-base",
                        str(ws / "install"), "--event-handlers", "console_direct-"],
                       cwd=ws, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, f"colcon build failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return ws, r.stdout + r.stderr


def test_colcon_builds_every_package(colcon_build):
    ws, out = colcon_build
    for pkg in PACKAGES:
        assert re.search(rf"Finished <<< {pkg}\b", out), f"{pkg} was not built:\n{out[-2000:]}"
    assert "Failed" not in out and "Aborted" not in out


def test_install_tree(colcon_build):
    ws, _ = colcon_build
    install = ws / "install"
    for pkg in PACKAGES:
        prefix = install / pkg
        share = prefix / "share" / pkg
        # the ament index (how ros2 run / ros2 launch find a package) and the manifest
        assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / pkg).is_file(), pkg
        assert (share / "package.xml").resolve() == (SRC / pkg / "package.xml").resolve()
        # console scripts where ros2 run looks: <prefix>/lib/<pkg>/<executable>
        scripts = console_scripts(pkg)
        for name in scripts:
            exe = prefix / "lib" / pkg / name
            assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} missing or not executable"
        if scripts:
            assert sorted(p.name for p in (prefix / "lib" / pkg).iterdir()) == sorted(scripts)
        # launch files, linked to the sources
        launch_src = sorted((SRC / pkg / "launch").glob("*.launch.py"))
        for f in launch_src:
            installed = share / "launch" / f.name
            assert installed.is_symlink(), f"{installed} is a copy: --symlink-install did not link"
            assert installed.resolve() == f.resolve()
        for f in sorted((SRC / pkg / "config").glob("*.yaml")):
            assert (share / "config" / f.name).resolve() == f.resolve(), f"{f.name} not installed"
        if (share / "launch").is_dir():
            assert sorted(p.name for p in (share / "launch").iterdir()) == [f.name for f in launch_src]
    assert console_scripts("hmrta_agent") == ["agent_node"]
    assert {"task_board", "sim_robot", "mission", "hmrta-mission"} <= set(console_scripts("hmrta_coordinator"))


def test_symlink_install_runs_the_sources(colcon_build):
    """Sourcing the install tree puts the packages on the path through links to the sources: an
    edit in ros2_ws/src takes effect without rebuilding."""
    ws, _ = colcon_build
    env = _sourced_env(ws / "install", {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(ws)})
    code = ("import json, hmrta_agent, hmrta_coordinator, hmrta_msgs_py\n"
            "from ament_index_python.packages import get_package_prefix, get_package_share_directory\n"
            "print(json.dumps({m.__name__: [m.__file__, get_package_prefix(m.__name__),"
            " get_package_share_directory(m.__name__)] for m in (hmrta_agent, hmrta_coordinator, hmrta_msgs_py)}))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    for pkg, (file, prefix, share) in json.loads(r.stdout).items():
        assert Path(file).is_relative_to(ws / "build" / pkg), f"{pkg} imported from {file}, not the colcon tree"
        assert Path(file).resolve() == (SRC / pkg / pkg / "__init__.py").resolve()
        assert Path(prefix) == ws / "install" / pkg and Path(share) == ws / "install" / pkg / "share" / pkg


def test_greedy_mission_from_installed_executables(colcon_build, tmp_path):
    """ros2 run hmrta_coordinator mission, the way a ROS install runs it (the project's
    interpreter, which has rclpy and the core), on the built-in example: same as the offline
    rollout."""
    from hmrta.formats import load_instance
    from hmrta.methods import solve
    from hmrta_coordinator.mission import default_instance

    ws, _ = colcon_build
    env = _sourced_env(ws / "install", {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(ws)})
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOG_DIR=str(tmp_path / "ros_logs"))
    seed, out = 2, tmp_path / "mission.json"
    exe = ws / "install" / "hmrta_coordinator" / "lib" / "hmrta_coordinator" / "mission"
    r = subprocess.run([sys.executable, str(exe), "--method", "greedy", "--seed", str(seed), "--out", str(out),
                        "--no-plot", "--quiet", "--agents-per-process", "15", "--timeout", "150",
                        "--domain-id", str(random.randint(200, 232))],
                       capture_output=True, text=True, env=env, timeout=200, cwd=tmp_path)
    assert r.returncode == 0, f"mission exited {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    result = json.loads(out.read_text())
    ref = json.loads(json.dumps(solve(load_instance(default_instance()), "greedy", seed).to_dict()))
    for k in ("success", "routes", "tasks", "agents", "makespan"):
        assert result[k] == ref[k], f"{k}: the mission from the colcon install differs from the offline rollout"


# --- package.xml against the imports ------------------------------------------------------------
# Python module (top level, or a longer dotted prefix) -> rosdep keys it needs
MODULE_KEYS: dict[str, tuple[str, ...]] = {
    "rclpy": ("rclpy",), "std_msgs": ("std_msgs",), "geometry_msgs": ("geometry_msgs",),
    "rosgraph_msgs": ("rosgraph_msgs",), "visualization_msgs": ("visualization_msgs",),
    "builtin_interfaces": ("builtin_interfaces",), "nav_msgs": ("nav_msgs",), "tf2_ros": ("tf2_ros",),
    "rcl_interfaces": ("rcl_interfaces",),
    "launch": ("launch",), "launch_ros": ("launch_ros",), "ament_index_python": ("ament_index_python",),
    "numpy": ("python3-numpy",), "yaml": ("python3-yaml",), "tqdm": ("python3-tqdm",), "torch": ("python3-torch",),
    "matplotlib": ("python3-matplotlib",),
    "mcap": ("python3-mcap-pip",),  # the recorder (pip: mcap; rosdep has no rule: skip-keys)
    "hmrta_msgs_py": ("hmrta_msgs_py",), "hmrta_agent": ("hmrta_agent",), "hmrta_coordinator": ("hmrta_coordinator",),
    # the core (pip-installed from policy/) and what it needs at run time: its dependencies, and
    # the extras of the parts imported (hmrta.render: plot)
    "hmrta": ("python3-hmrta-pip", "python3-numpy", "python3-yaml", "python3-tqdm"),
    "hmrta.render": ("python3-matplotlib",),
}
CORE_KEY = "python3-hmrta-pip"


def imported_keys(pkg: str) -> dict[str, set[str]]:
    """rosdep key -> files needing it, from the imports of the package's modules and launch files
    (setup.py excluded: a build-time file), and from executables it starts by module or package
    name (``-m hmrta_agent.agent_node``, ``Node(package="hmrta_agent")``)."""
    files = [f for f in (SRC / pkg).rglob("*.py") if "__pycache__" not in f.parts and f.name != "setup.py"]
    out: dict[str, set[str]] = {}
    for f in files:
        tree = ast.parse(f.read_text(), str(f))
        mods: set[str] = set()
        for n in ast.walk(tree):
            if isinstance(n, ast.Import):
                mods |= {a.name for a in n.names}
            elif isinstance(n, ast.ImportFrom) and n.level == 0:
                mods.add(n.module)
            elif isinstance(n, ast.Constant) and isinstance(n.value, str):
                m = re.fullmatch(r"(hmrta_agent|hmrta_coordinator|hmrta_msgs_py)(\.\w+)*", n.value)
                if m:
                    mods.add(m.group(1))
        for mod in mods:
            top = mod.split(".")[0]
            if top in sys.stdlib_module_names or top == pkg:
                continue
            assert top in MODULE_KEYS, f"{f.relative_to(ROOT)} imports {mod}: add its rosdep key to MODULE_KEYS"
            keys = set(MODULE_KEYS[top])
            keys |= {k for prefix, ks in MODULE_KEYS.items() if "." in prefix
                     and (mod == prefix or mod.startswith(prefix + ".")) for k in ks}
            for k in keys:
                out.setdefault(k, set()).add(f.name)
    return out


def declared_depends(pkg: str, tag: str = "exec_depend") -> list[str]:
    root = ET.parse(SRC / pkg / "package.xml").getroot()
    return [e.text.strip() for e in root.findall(tag)] + [e.text.strip() for e in root.findall("depend")]


@pytest.mark.parametrize("pkg", PACKAGES)
def test_package_xml_matches_imports(pkg):
    declared = declared_depends(pkg)
    assert len(declared) == len(set(declared)), f"{pkg}/package.xml lists a dependency twice"
    needed = imported_keys(pkg)
    missing = sorted(set(needed) - set(declared))
    extra = sorted(set(declared) - set(needed))
    assert not missing, f"{pkg}/package.xml lacks " + ", ".join(f"{k} (for {', '.join(sorted(needed[k]))})"
                                                                for k in missing)
    assert not extra, f"{pkg}/package.xml declares {extra}, which nothing in {pkg} imports"
    root = ET.parse(SRC / pkg / "package.xml").getroot()
    assert root.get("format") == "3" and root.findtext("name") == pkg
    assert root.find("export/build_type").text == "ament_python"


def test_import_map_is_not_vacuous():
    agent, board = imported_keys("hmrta_agent"), imported_keys("hmrta_coordinator")
    assert {"rclpy", CORE_KEY, "hmrta_msgs_py", "launch_ros"} <= set(agent)  # torch comes with the core ([rl])
    assert {"python3-matplotlib", "hmrta_agent", "visualization_msgs", "python3-tqdm"} <= set(board)
