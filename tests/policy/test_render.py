"""Rendering: a PNG with map + Gantt, and an animated GIF; timelines consistent with the solution."""
from __future__ import annotations

import contextlib
import io
import json
import re

import numpy as np
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


def test_a_name_in_a_script_the_font_lacks_draws_without_a_warning_per_character(tmp_path, case):
    import dataclasses
    import warnings

    inst, sol = case
    inst = dataclasses.replace(inst, name="倉庫の点検")
    sol = dataclasses.replace(sol, instance=inst.name)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (matplotlib warned once per missing glyph and figure)
        assert render(inst, sol, tmp_path / "fig.png") == [tmp_path / "fig.png"]


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


@pytest.mark.parametrize("frames, fps, bad", [(0, 10, "frames"), (-5, 10, "frames"), (8, 0, "fps"), (8, -1, "fps"),
                                              (1001, 10, "frames"), (10 ** 8, 10, "frames"), (8, 51, "fps")])
def test_gif_frames_and_fps_are_checked_before_any_image(tmp_path, case, frames, fps, bad):
    inst, sol = case
    for out in (tmp_path / "sub" / "fig.png", tmp_path / "anim.gif"):
        with pytest.raises(ValueError, match=f"{bad}: expected an integer in 1.."):
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


def test_a_run_that_stopped_shows_the_work_under_way(tmp_path):
    """A run stopped by its time limit: the coalitions complete then (``in_progress``) are worked
    to their planned finish on their members' rows, drawn apart from the work done; robots on
    their way to a task end with that trip, and nobody is drawn going home after the stop."""
    from hmrta.baselines import Greedy
    from hmrta.core import Rules
    from hmrta.sim import simulate

    inst = ScenarioGenerator("MA-AT", 15, 5, 20, 5).instance(1, 0)
    sol = simulate(inst, Greedy(), 0, Rules(t_max=12.0, safety=True), "greedy")
    sol = Solution.from_dict(json.loads(json.dumps(sol.to_dict())))  # as read from its file
    running = {r["task"]: r for r in sol.extra["in_progress"]}
    assert running
    tl = agent_timeline(inst, sol)
    for a, segs in enumerate(tl):
        done = [m for m in sol.routes[a] if sol.tasks[m]["finish"] == sol.tasks[m]["finish"]]  # (NaN: not done)
        planned = [s for s in segs if s.get("planned")]
        assert [s["task"] for s in segs if s["kind"] == "work" and not s.get("planned")] == done
        nxt = sol.routes[a][len(done):]
        if nxt:  # committed to a task not done: the trip there is its last travel, no trip home
            travel = [s for s in segs if s["kind"] == "travel"]
            assert travel[-1]["task"] == nxt[0] and all(s["task"] is not None for s in segs)
            if nxt[0] in running:
                r = running[nxt[0]]
                assert [(s["task"], s["t0"], s["t1"]) for s in planned] == [(nxt[0], r["start"], r["finish"])]
                assert a in r["members"]
        assert not planned or nxt and nxt[0] in running
    f = _figure_of(inst, sol)
    gantt = f.ax_g
    # the map: every route line ends at the task its robot was committed to, none back at a depot
    ends = np.array([ln.get_xydata()[-1] for ln in f.ax_map.get_lines()])  # [R, 2]
    assert len(ends) == sum(bool(r) for r in sol.routes)
    assert np.abs(ends[:, None] - inst.task_locations[None]).max(-1).min(1).max() < 0.02
    labels = [t.get_text() for t in gantt.get_legend().get_texts()]
    assert "under way when it stopped (to the planned finish)" in labels
    hatched = [c for c in gantt.collections if c.get_hatch() == "xx"]
    assert len(hatched) == 1 and len(hatched[0].get_paths()) == sum(len(r["members"]) for r in running.values())
    assert render(inst, sol, tmp_path / "stopped.png", gif=True, frames=4)[0].exists()


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
    inst, sol = case
    p, lines = _refused(tmp_path, inst, _foreign(sol, **change), expect)
    assert lines[0].startswith(f"hmrta: error: {p}")
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "y.png").exists()


def _refused(tmp_path, inst, d: dict, expect: str):
    """Write solution ``d`` to sol.json and the mission beside it; render() and `hmrta render` both
    refuse it with ``expect`` (one line, exit 2). Returns (the solution's path, stderr's lines)."""
    from hmrta.cli import main
    from hmrta.solution import SolutionError

    p = tmp_path / "sol.json"
    p.write_text(json.dumps(d))
    bad = Solution.from_dict(json.loads(p.read_text()), str(p))
    with pytest.raises(SolutionError, match=re.escape(expect)):
        render(inst, bad, tmp_path / "x.png", source=str(p))
    ip = tmp_path / "inst.yaml"
    inst.save(ip)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(["render", str(ip), str(p), "--out", str(tmp_path / "y.png")]) == 2
    lines = err.getvalue().splitlines()
    assert len(lines) == 1 and expect in lines[0], lines
    return p, lines


def test_an_image_name_without_a_format_suffix_is_refused_before_anything_is_written(tmp_path, case):
    inst, sol = case
    with pytest.raises(ValueError, match="format as suffix"):
        render(inst, sol, tmp_path / "fig", gif=True, frames=2)
    assert not list(tmp_path.iterdir())


# --- missions that changed while they ran -----------------------------------------------------
CHANGING = {"format": "hmrta-instance/1", "name": "changes", "requirement_type": "additive", "velocity": 0.2,
            "skills": 3,
            "species": [{"traits": [1, 0, 0], "count": 2, "depot": [0.1, 0.1]},
                        {"traits": [0, 1, 0], "count": 2, "depot": [0.9, 0.9]},
                        {"traits": [0, 0, 1], "count": 1, "depot": [0.1, 0.9]}],  # robot 4: the only one with skill 2
            "tasks": [{"location": [0.5, 0.2], "requirements": [1, 0, 0], "duration": 2},
                      {"location": [0.3, 0.6], "requirements": [1, 1, 0], "duration": 3},
                      {"location": [0.8, 0.5], "requirements": [0, 2, 0], "duration": 1},
                      {"location": [0.6, 0.8], "requirements": [0, 0, 1], "duration": 4},
                      {"location": [0.2, 0.4], "requirements": [0, 0, 1], "duration": 2}]}
EVENTS = [{"t": 0.5, "type": "add_task", "id": "late", "location": [0.7, 0.2], "requirements": [1, 0, 0],
           "duration": 1},
          {"t": 1.0, "type": "cancel_task", "id": 2},                       # by the operator
          {"t": 1.5, "type": "add_robot", "species": 0, "position": [0.5, 0.5]},
          {"t": 2.0, "type": "lose_robot", "robot": 4},                     # tasks 3 and 4: unsatisfiable
          {"t": 5.0, "type": "lose_robot", "robot": 1}]                     # after its task 0 (done at 4.06)


@pytest.fixture(scope="module")
def changed():
    """A scenario with every kind of change, solved by greedy; the solution read back from its JSON
    (what a user has) with the mission as it ended."""
    from hmrta.scenario import scenario_from_dict
    from hmrta.solution import final_instance

    scen = scenario_from_dict({"format": "hmrta-scenario/1", "instance": CHANGING, "events": EVENTS}, "s.yaml")
    sol = Solution.from_dict(json.loads(json.dumps(solve(scen, "greedy", seed=0).to_dict())))
    return final_instance(scen, sol), sol


def _figure_of(inst, sol):
    from hmrta.render import _figure, mission_changes

    return _figure(inst, sol, mission_changes(inst, sol))


def test_mission_changes_are_read_from_the_solution(changed, case):
    from hmrta.render import mission_changes
    from hmrta.solution import SolutionError

    inst, sol = changed
    ch = mission_changes(inst, sol)
    assert ch.lost == {4: 2.0, 1: 5.0}
    assert ch.joined == {5: (1.5, (0.5, 0.5))}
    assert ch.cancelled == {2: (1.0, True), 3: (2.0, False), 4: (2.0, False)}
    assert sol.routes[1] == [0]  # lost on its way to the next task, which left its route
    at = {e["agent"]: tuple(e["at"]) for e in sol.extra["dynamic"]["events"] if e["type"] == "drop_agent"}
    assert ch.lost_at == {1: (at[1], 5.0), 4: (at[4], 2.0)}  # where they stopped, part-way: there since the loss
    assert at[1] != tuple(inst.task_locations[0])
    tl = agent_timeline(inst, sol)
    # robot 1: its task, then its last leg up to where it stopped at the loss; no trip home
    assert [(s["kind"], s["task"]) for s in tl[1][-2:]] == [("work", 0), ("travel", None)]
    assert tl[1][-1]["t1"] == 5.0 and tl[1][-1]["p1"] == at[1]
    assert tl[1][-1]["t1"] - tl[1][-1]["t0"] == pytest.approx(inst.travel_time(tl[1][-1]["p0"], at[1]))
    # robot 4: lost on its first leg, from its depot
    assert [(s["kind"], s["t0"], s["t1"], s["p1"]) for s in tl[4]] == [("travel", 0.0, 2.0, at[4])]
    # without the recorded movements (a solution of route evaluation, or an older file) the
    # timeline is rebuilt from the routes and the events
    # a robot lost where it had arrived earlier (``since``): its last leg ends at that arrival
    moved = json.loads(json.dumps(sol.to_dict()))
    del moved["moves"]
    rec = next(e for e in moved["dynamic"]["events"] if e.get("agent") == 1)
    rec["since"] = 4.5
    leg = agent_timeline(inst, Solution.from_dict(moved))[1][-1]
    assert (leg["t1"], leg["p1"]) == (4.5, at[1]) and leg["t0"] == tl[1][-1]["t0"]
    rec["since"] = 6.0  # after the loss: refused
    with pytest.raises(SolutionError, match=r"dynamic.events\[\d\].since: expected a time in \[0, 5\]"):
        mission_changes(inst, Solution.from_dict(moved))
    # a record without "at" (written before the log carried it): the robot where it was last known
    old = json.loads(json.dumps(sol.to_dict()))
    del old["moves"]
    for e in old["dynamic"]["events"]:
        e.pop("at", None)
    old_tl = agent_timeline(inst, Solution.from_dict(old))
    assert old_tl[1][-1]["kind"] == "work" and old_tl[4] == []
    assert (tl[5][0]["t0"], tl[5][0]["p0"]) == (1.5, (0.5, 0.5))  # a joined robot starts where and when it appeared
    assert mission_changes(*case) == type(ch)()  # a plain mission: nothing happened


def test_lost_robots_and_cancelled_tasks_are_marked(changed):
    """The map has an X per lost robot where it stopped (part-way along its leg), the Gantt chart an X at the end of its row at the loss time with
    the time written beside; cancelled tasks have a cross (grey: operator, dark red: unsatisfiable)
    over a greyed disc, and the legends say so."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection, PatchCollection, PathCollection
    from matplotlib.colors import to_rgba

    inst, sol = changed
    f = _figure_of(inst, sol)
    try:
        A = inst.n_agents
        x_map = [c for c in f.ax_map.collections if isinstance(c, PathCollection) and len(c.get_offsets()) == 2]
        assert len(x_map) == 1
        at = {e["agent"]: e["at"] for e in sol.extra["dynamic"]["events"] if e["type"] == "drop_agent"}
        assert np.allclose(x_map[0].get_offsets(), [at[1], at[4]])  # robots 1 and 4 (sorted)
        assert np.allclose(x_map[0].get_facecolor(), [f.colors[0], f.colors[2]])  # species colours
        x_gantt = [c for c in f.ax_g.collections if isinstance(c, PathCollection) and len(c.get_offsets()) == 2]
        assert np.allclose(x_gantt[0].get_offsets(), [[5.0, A - 1 - 1], [2.0, A - 1 - 4]])  # (time, row)
        texts = {t.get_text() for t in f.ax_g.texts}
        assert {"lost 5.00", "lost 2.00", "joined 1.50"} <= texts
        crosses = [c for c in f.ax_map.collections if isinstance(c, LineCollection)]
        assert len(crosses) == 1
        segs = np.array(crosses[0].get_segments())  # [2C, 2, 2] two strokes per cancelled task 2, 3, 4
        assert np.allclose(segs.mean(axis=1)[::2], inst.task_locations[[2, 3, 4]])
        assert [tuple(c) for c in crosses[0].get_colors()[::2]] == [to_rgba("#777777"), to_rgba("#8b0000"),
                                                                    to_rgba("#8b0000")]
        discs = [c for c in f.ax_map.collections if isinstance(c, PatchCollection) and len(c.get_paths()) == 3]
        assert len(discs) == 1
        legend = {t.get_text() for ax in (f.ax_map, f.ax_g) for t in ax.get_legend().get_texts()}
        assert {"task cancelled by the operator (\u00d7 when)", "task unsatisfiable after a loss (\u00d7 when)",
                "robot lost (map: X where it stopped)", "robot joined", "task released / added"} <= legend
        assert "2 robots lost, 1 joined, 1 task cancelled, 2 unsatisfiable after a loss" in f.fig._suptitle.get_text()
        # the GIF shows each marker from its time on: the lost robots' X ...
        lost_x = f.timed[-1]
        lost_x.show(3.0)
        assert list(lost_x.art.get_facecolor()[:, 3]) == [0.0, 1.0]  # robot 4 (lost at 2), not yet robot 1
        lost_x.show(5.0)
        assert list(lost_x.art.get_facecolor()[:, 3]) == [1.0, 1.0]
        f.timed[1].show(1.5)  # ... and the crosses: task 2 cancelled at 1, tasks 3 and 4 at 2
        assert list(crosses[0].get_colors()[:, 3]) == [1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    finally:
        plt.close(f.fig)


def test_a_changed_mission_renders_png_and_gif(tmp_path, changed, capsys):
    import yaml
    from PIL import Image

    from hmrta.cli import main

    inst, sol = changed
    out = render(inst, sol, tmp_path / "c.png", gif=True, frames=5)
    assert [p.name for p in out] == ["c.png", "c.gif"] and out[0].stat().st_size > 20000
    with Image.open(out[1]) as im:
        assert (im.n_frames, im.size) == (5, (900, 432))
    # `hmrta render SCENARIO SOLUTION` draws the mission as it ended
    (tmp_path / "s.yaml").write_text(yaml.safe_dump({"format": "hmrta-scenario/1", "instance": CHANGING,
                                                     "events": EVENTS}))
    (tmp_path / "sol.json").write_text(json.dumps(sol.to_dict()))
    assert main(["render", str(tmp_path / "s.yaml"), str(tmp_path / "sol.json"), "--out", str(tmp_path / "d.png")]) == 0
    assert (tmp_path / "d.png").stat().st_size > 20000
    # the scenario's solution given with the mission without its events: said as such
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(CHANGING))
    assert main(["solve", str(tmp_path / "s.yaml"), "--method", "greedy", "--out", str(tmp_path / "s.json")]) in (0, 3)
    capsys.readouterr()
    assert main(["render", str(tmp_path / "base.yaml"), str(tmp_path / "s.json"), "--out", str(tmp_path / "e.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "it is the solution of a mission with events" in err[0], err


@pytest.mark.parametrize("event, expect", [
    ({"type": "drop_agent", "t": 1.0, "agent": 9, "cancelled": []},
     "dynamic.events[0].agent: expected an index in 0..5, got 9"),
    ({"type": "drop_agent", "t": "soon", "agent": 1}, "dynamic.events[0].t: expected a finite time >= 0, got 'soon'"),
    ({"type": "drop_agent", "t": 1.0, "agent": 1, "cancelled": [7]},
     "dynamic.events[0].cancelled[0]: expected an index in 0..5"),
    ({"type": "cancel_task", "t": 1.0, "name": "nope"}, "dynamic.events[0].name: expected the client id of a task"),
    ({"type": "add_agent", "t": 1.0, "id": 5, "position": [0.5]},
     "dynamic.events[0].position: expected a point [x, y]"),
])
def test_events_that_do_not_fit_the_mission_are_refused(tmp_path, changed, event, expect):
    """An event record in the solution naming a robot or task the mission lacks is refused (one line
    naming the solution file and the field), by render() and by `hmrta render`; no image is written.
    A rejected event changed nothing and is skipped."""
    inst, sol = changed
    d = sol.to_dict()
    d["dynamic"] = {**d["dynamic"], "events": [event]}
    _refused(tmp_path, inst, d, f"{tmp_path / 'sol.json'}: {expect}")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["inst.yaml", "sol.json"]
    d["dynamic"]["events"] = [{**event, "rejected": "why"}]
    assert render(inst, Solution.from_dict(d), tmp_path / "ok.png")[0].exists()


# --- GIF speed: the static picture is drawn once ------------------------------------------------
def test_gif_draws_the_figure_once_and_blits_the_same_frames(tmp_path, case, monkeypatch):
    """The GIF draws the whole figure once, not once per frame, and keeps its frames: count, size
    (900 x 432), frame time (1/fps); its first frame is the full figure at the GIF's resolution but
    for the moving artists (robots at their depots, clock, cursor), and the robots move."""
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure
    from PIL import Image, ImageSequence

    inst, sol = case
    draws = []
    full_draw = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda self, renderer: (draws.append(1), full_draw(self, renderer))[1])
    out = render(inst, sol, tmp_path / "a.gif", frames=12, fps=5)[0]
    assert len(draws) == 1
    monkeypatch.undo()
    with Image.open(out) as im:
        assert (im.n_frames, im.size, im.info["duration"], im.info["loop"]) == (12, (900, 432), 200, 0)
        frames = [np.asarray(fr.convert("RGB"), dtype=int) for fr in ImageSequence.Iterator(im)]  # [432, 900, 3] each
    f = _figure_of(inst, sol)
    f.fig.savefig(tmp_path / "full.png", dpi=60)
    plt.close(f.fig)
    with Image.open(tmp_path / "full.png") as im:
        full = np.asarray(im.convert("RGB"), dtype=int)  # [432, 900, 3]
    assert full.shape == frames[0].shape
    assert (np.abs(frames[0] - full).sum(-1) > 60).mean() < 0.03  # only the moving artists differ
    assert (np.abs(frames[0] - frames[6]).sum(-1) > 60).mean() > 0.001  # and they move


@pytest.mark.parametrize("method", ["greedy", "greedy-coalition"])
def test_the_drawing_of_a_mission_with_release_times_is_what_happened(method):
    """Tasks released during the mission: robots go home and come back, leave later than their
    last finish. The timeline follows the recorded movements (``extra["moves"]``): no robot is at
    a task before its release (a back-dated departure never precedes it either), the drawn waits
    are the solution's AWT, every segment follows the one before, and every robot ends home at its
    return time."""
    import dataclasses

    from hmrta.methods import solve

    checked = detours = 0
    for i, inst in enumerate(ScenarioGenerator("MA-AT", 9, 3, 20, 3).generate(4, 5)):
        rng = np.random.default_rng(i)
        inst = dataclasses.replace(inst, tasks=tuple(
            dataclasses.replace(t, release=float(rng.random() * 30) if rng.random() < 0.6 else 0.0)
            for t in inst.tasks), _cache={})
        sol = Solution.from_dict(json.loads(json.dumps(solve(inst, method, 0).to_dict())))
        detours += sum(len(mv) > len(r) + 1 for mv, r in zip(sol.extra["moves"], sol.routes))  # home and back
        tl = agent_timeline(inst, sol)
        waits = [sum(s["t1"] - s["t0"] for s in segs if s["kind"] == "wait") for segs in tl]
        assert np.mean(waits) == pytest.approx(sol.awt, abs=1e-9)
        for a, segs in enumerate(tl):
            for s in segs:
                if s["task"] is not None and s["kind"] in ("wait", "work"):
                    assert s["t0"] >= inst.tasks[s["task"]].release, (a, s)
                    checked += 1
            for x, y in zip(segs, segs[1:]):
                assert y["t0"] >= x["t1"] - 1e-9 and np.allclose(y["p0"], x["p1"])
            assert segs[-1]["kind"] == "travel" and segs[-1]["t1"] == pytest.approx(sol.agents[a]["return_time"])
            assert np.allclose(segs[-1]["p1"], inst.depots[a])
    assert checked > 100 and detours > 0


def test_a_solution_of_another_version_of_the_mission_is_refused(tmp_path, capsys):
    """``hmrta solve`` records the mission it planned (instance_sha256): render and bound refuse
    the solution for the same-named mission with other durations (exit 2, one line), and take it
    for the mission it was planned for."""
    from hmrta.cli import main

    mission = tmp_path / "m.yaml"
    mission.write_text(CHANGING if isinstance(CHANGING, str) else json.dumps(CHANGING))
    sol = tmp_path / "m.json"
    assert main(["solve", str(mission), "--method", "greedy", "--out", str(sol)]) == 0
    assert json.loads(sol.read_text())["instance_sha256"]
    other = tmp_path / "v2"
    other.mkdir()
    data = json.loads(json.dumps(__import__("yaml").safe_load(mission.read_text())))
    for t in data["tasks"]:
        t["duration"] = float(t["duration"]) + 1.0
    (other / "m.yaml").write_text(json.dumps(data))
    capsys.readouterr()
    for argv in (["render", str(other / "m.yaml"), str(sol), "--out", str(tmp_path / "x.png")],
                 ["bound", str(other / "m.yaml"), str(sol)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "planned for another version of the mission" in err[0]
    assert main(["render", str(mission), str(sol), "--out", str(tmp_path / "x.png")]) == 0


def _cancelled_at(t: float, method: str):
    """(scenario, its solution by ``method``, read back): robot 0 at (0, 0) and robot 1 at (1, 1),
    both needed at task 0 (near robot 0), which the operator cancels at ``t``; task 1 needs one."""
    from hmrta.scenario import scenario_from_dict

    scen = scenario_from_dict({"format": "hmrta-scenario/1", "instance": {
        "format": "hmrta-instance/1", "name": "cx", "requirement_type": "additive", "velocity": 1.0, "skills": 1,
        "species": [{"traits": [1], "count": 1, "depot": [0.0, 0.0]}, {"traits": [1], "count": 1, "depot": [1.0, 1.0]}],
        "tasks": [{"location": [0.1, 0.0], "requirements": [2], "duration": 5},
                  {"location": [0.9, 1.0], "requirements": [1], "duration": 1}]},
        "events": [{"t": t, "type": "cancel_task", "id": 0}]}, "s.yaml")
    return scen, Solution.from_dict(json.loads(json.dumps(solve(scen, method, seed=0).to_dict())))


def test_a_wait_at_a_task_cancelled_before_it_started_is_drawn():
    """Robot 0 waits at task 0 for a second robot that never comes, until the task is cancelled at
    1.0: the drawing shows that wait (the AWT counts it), its legs unlabelled (the task left its
    route)."""
    from hmrta.solution import final_instance

    scen, sol = _cancelled_at(1.0, "greedy")
    tl = agent_timeline(final_instance(scen, sol, "s"), sol)
    assert [(s["kind"], s["task"]) for s in tl[0]] == [("travel", None), ("wait", 0), ("travel", None)]
    assert tl[0][1]["t1"] == pytest.approx(1.0)
    assert np.mean([sum(s["t1"] - s["t0"] for s in segs if s["kind"] == "wait") for segs in tl]) == pytest.approx(sol.awt)


def test_work_at_a_task_cancelled_in_progress_is_drawn_until_the_cancellation():
    """Both robots work at task 0 from its start (robot 1's arrival) until the operator cancels it
    at 3.0 (the log's cancel record says when it had ``started``): drawn as work, not as a wait,
    so the drawn waits are the AWT."""
    from hmrta.solution import final_instance

    scen, sol = _cancelled_at(3.0, "greedy-coalition")
    cancel = next(e for e in sol.extra["dynamic"]["events"] if e["type"] == "cancel_task")
    start = float(np.hypot(0.9, 1.0))  # robot 1's arrival completes the coalition
    assert cancel["started"] == pytest.approx(start) and sorted(cancel["freed"]) == [0, 1]
    tl = agent_timeline(final_instance(scen, sol, "s"), sol)
    for segs in tl:
        work = [s for s in segs if s["kind"] == "work" and s["task"] == 0]
        assert len(work) == 1 and work[0]["t0"] == pytest.approx(start) and work[0]["t1"] == pytest.approx(3.0)
        for x, y in zip(segs, segs[1:]):
            assert y["t0"] >= x["t1"] - 1e-9 and np.allclose(y["p0"], x["p1"])
    assert np.mean([sum(s["t1"] - s["t0"] for s in segs if s["kind"] == "wait") for segs in tl]) == pytest.approx(sol.awt)


@pytest.mark.parametrize("species", [3, 20])
def test_legends_stay_under_their_own_plot_and_inside_the_figure(species):
    # 20 species (with the task skills, 25 entries) once drew the map's legend across the Gantt's
    inst = ScenarioGenerator("MA-AT", species, species, 6, 5).instance(0, 0)
    f = _figure_of(inst, solve(inst, "greedy", seed=0))
    r = f.fig.canvas.get_renderer()
    leg_map, leg_g = (ax.get_legend().get_window_extent(r) for ax in (f.ax_map, f.ax_g))
    assert leg_map.x1 <= leg_g.x0 and leg_map.x1 <= f.ax_g.get_window_extent(r).x0
    for leg in (leg_map, leg_g):
        assert leg.y0 >= 0 and leg.x1 <= f.fig.bbox.width
    if species == 3:  # a small team keeps the figure's size
        assert tuple(f.fig.get_size_inches()) == (15, 7.2)
    import matplotlib.pyplot as plt

    plt.close(f.fig)
