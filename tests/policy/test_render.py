"""Rendering: a PNG with map + Gantt, and an animated GIF; timelines consistent with the solution."""
from __future__ import annotations

import contextlib
import io
import json
import re

import pytest

pytest.importorskip("matplotlib")

from hmrta.generators import ScenarioGenerator  # noqa: E402
from hmrta.methods import solve  # noqa: E402
from hmrta.render import agent_timeline, render  # noqa: E402
from hmrta.solution import Solution  # noqa: E402


@pytest.fixture(scope="module")
def case():
    inst = ScenarioGenerator("MA-AT", 9, 3, 8, 3).instance(4, 0)
    return inst, solve(inst, "greedy", seed=0)


def test_png(tmp_path, case):
    inst, sol = case
    out = render(inst, sol, tmp_path / "fig.png")
    assert out == [tmp_path / "fig.png"]
    data = out[0].read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20000


def test_gif(tmp_path, case):
    from PIL import Image

    inst, sol = case
    seen = []
    out = render(inst, sol, tmp_path / "fig.png", gif=True, frames=6, progress=lambda i, n: seen.append((i, n)))
    assert [p.suffix for p in out] == [".png", ".gif"]
    assert seen == [(i, 6) for i in range(1, 7)]  # after each frame
    with Image.open(out[1]) as im:
        assert im.format == "GIF" and im.n_frames == 6
    only = render(inst, sol, tmp_path / "anim.gif", frames=3)
    assert only == [tmp_path / "anim.gif"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.gif", "fig.gif", "fig.png"]  # no temp files


@pytest.mark.parametrize("frames, fps, bad", [(0, 10, "frames"), (-5, 10, "frames"), (8, 0, "fps"), (8, -1, "fps")])
def test_gif_frames_and_fps_are_checked_before_any_image(tmp_path, case, frames, fps, bad):
    inst, sol = case
    for out in (tmp_path / "sub" / "fig.png", tmp_path / "anim.gif"):
        with pytest.raises(ValueError, match=f"{bad}: expected a positive integer"):
            render(inst, sol, out, gif=True, frames=frames, fps=fps)
    assert list(tmp_path.iterdir()) == []  # no png, no folder, no temp file


def test_timeline_matches_solution(case):
    inst, sol = case
    tl = agent_timeline(inst, sol)
    assert len(tl) == inst.n_agents
    for a, segs in enumerate(tl):
        works = [s["task"] for s in segs if s["kind"] == "work"]
        assert works == sol.routes[a]
        for s in segs:
            assert s["t1"] >= s["t0"] - 1e-12
            if s["kind"] == "work":
                assert s["t0"] == sol.tasks[s["task"]]["start"] and s["t1"] == sol.tasks[s["task"]]["finish"]
        if segs:  # ends at home at its return time
            assert segs[-1]["t1"] == pytest.approx(sol.agents[a]["return_time"])
        # waiting per agent sums to the solution's AWT on average
    wait = sum(s["t1"] - s["t0"] for segs in tl for s in segs if s["kind"] == "wait")
    assert wait / inst.n_agents == pytest.approx(sol.awt, abs=1e-6)


def test_failed_solution_and_mismatch(tmp_path, case):
    inst, sol = case
    failed = Solution(inst.name, "x", 0, False, float("nan"), float("nan"), float("nan"), 0.0,
                      [[] for _ in range(inst.n_agents)],
                      [{"start": float("nan"), "finish": float("nan"), "members": []} for _ in range(inst.n_tasks)],
                      [{"species": int(s), "return_time": float("nan")} for s in inst.agent_species],
                      {"failure": "deadlock"})
    assert render(inst, failed, tmp_path / "f.png")[0].exists()
    other = ScenarioGenerator("MA-AT", 15, 5, 8, 5).instance(4, 0)
    with pytest.raises(ValueError, match="does not match"):
        render(other, sol, tmp_path / "g.png")


def _foreign(sol, **change):
    d = json.loads(json.dumps(sol.to_dict()))
    for k, v in change.items():
        d[k] = v(d) if callable(v) else v
    return d


@pytest.mark.parametrize("change,expect", [
    ({"instance": "another"}, "it is for instance 'another', not"),
    ({"tasks": lambda d: d["tasks"][:-1], "routes": lambda d: [[m for m in r if m < len(d["tasks"]) - 1]
                                                                for r in d["routes"]]},
     "9 routes / 7 tasks, expected 9 / 8"),
    ({"agents": lambda d: d["agents"][:-1], "routes": lambda d: d["routes"][:-1],
      "tasks": lambda d: [{**t, "members": [a for a in t["members"] if a < 8]} for t in d["tasks"]]},
     "8 routes / 8 tasks, expected 9 / 8"),
    ({"agents": lambda d: [{**a, "species": (a["species"] + 1) % 3} for a in d["agents"]]},
     "agents[0].species: solution does not match the instance"),
])
def test_render_refuses_a_solution_of_another_instance(tmp_path, case, change, expect):
    """A solution that does not belong to the instance is refused (one line naming the solution
    file and what differs), by render() and by `hmrta render`, and no image is written."""
    from hmrta.cli import main
    from hmrta.solution import SolutionError

    inst, sol = case
    p = tmp_path / "sol.json"
    p.write_text(json.dumps(_foreign(sol, **change)))
    bad = Solution.from_dict(json.loads(p.read_text()), str(p))
    with pytest.raises(SolutionError, match=re.escape(expect)):
        render(inst, bad, tmp_path / "x.png", source=str(p))
    ip = tmp_path / "inst.yaml"
    inst.save(ip)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["render", str(ip), str(p), "--out", str(tmp_path / "y.png")]) == 2
    lines = err.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"hmrta: error: {p}") and expect in lines[0], lines
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()


def test_an_image_name_without_a_format_suffix_is_refused_before_anything_is_written(tmp_path, case):
    inst, sol = case
    with pytest.raises(ValueError, match="format as suffix"):
        render(inst, sol, tmp_path / "fig", gif=True, frames=2)
    assert not list(tmp_path.iterdir())
