"""Pictures of a solution (``hmrta render``): a map and a Gantt chart, optionally an animated GIF.

* Map (left): species depots as squares (species colour), tasks as small pies whose wedges show the
  required skills (skill colour, wedge size = amount), each agent's route as a line in its species
  colour (agents of a species are offset slightly and dashed differently so they stay apart).
* Gantt (right): one row per agent (species-major, coloured by species); per visit a light bar for
  travel, a hatched red bar for waiting at the task for the coalition, and a solid bar with the
  task id for the work itself; a dashed line marks the makespan.
* GIF: the agents moving over the map with a time cursor on the Gantt chart (matplotlib PillowWriter).

Times are recomputed from the solution's task starts/finishes and straight-line travel: an agent
leaves a task at its finish, arrives after the travel time and waits until the task's start.
"""
from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .instance import Instance
from .solution import Solution, check_solution

# pastel skill colours (tasks) so they do not read as the saturated species colours (routes)
SKILL_COLORS = ["#fbb4ae", "#b3cde3", "#ccebc5", "#decbe4", "#fed9a6", "#ffffcc", "#e5d8bd", "#fddaec"]
LINESTYLES = ["-", "--", ":", "-."]


def _species_colors(n: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


def agent_timeline(inst: Instance, sol: Solution) -> list[list[dict[str, Any]]]:
    """Per agent, a list of segments {kind: travel|wait|work, t0, t1, task, p0, p1} in time order.
    ``task`` is the task id (None for the final trip home); p0/p1 are positions [2]."""
    out = []
    for a, route in enumerate(sol.routes):
        home = tuple(inst.depots[a])
        here, t = home, 0.0
        segs: list[dict[str, Any]] = []
        for m in route:
            tk = sol.tasks[m]
            st, fin = tk.get("start"), tk.get("finish")
            if st is None or fin is None or not math.isfinite(st) or not math.isfinite(fin):
                break
            loc = tuple(inst.task_locations[m])
            arr = t + inst.travel_time(here, loc)
            arr = min(arr, st)
            segs.append({"kind": "travel", "t0": t, "t1": arr, "task": m, "p0": here, "p1": loc})
            if st > arr + 1e-9:
                segs.append({"kind": "wait", "t0": arr, "t1": st, "task": m, "p0": loc, "p1": loc})
            segs.append({"kind": "work", "t0": st, "t1": fin, "task": m, "p0": loc, "p1": loc})
            here, t = loc, fin
        if here != home:
            segs.append({"kind": "travel", "t0": t, "t1": t + inst.travel_time(here, home), "task": None,
                         "p0": here, "p1": home})
        out.append(segs)
    return out


def _position(segs: list[dict[str, Any]], home: tuple, t: float) -> tuple[float, float]:
    pos = home
    for s in segs:
        if t < s["t0"]:
            break
        if t <= s["t1"]:
            if s["kind"] == "travel" and s["t1"] > s["t0"]:
                f = (t - s["t0"]) / (s["t1"] - s["t0"])
                return (s["p0"][0] + f * (s["p1"][0] - s["p0"][0]), s["p0"][1] + f * (s["p1"][1] - s["p0"][1]))
            return s["p1"]
        pos = s["p1"]
    return pos


def _title(inst: Instance, sol: Solution) -> str:
    if not sol.success:
        return f"{inst.name} — {sol.method}: FAILED ({sol.extra.get('failure', 'unknown reason')})"
    t = f"{inst.name} — {sol.method}: makespan {sol.makespan:.2f}, AWT {sol.awt:.2f}"
    lb = sol.extra.get("lower_bound")
    if isinstance(lb, (int, float)) and lb > 0:
        t += f", lower bound {lb:.2f} (gap {100 * (sol.makespan - lb) / sol.makespan:.1f}%)"
    st = sol.extra.get("status")
    if st:
        t += f" [{st}]"
    return t


def _draw_map(ax, inst: Instance, sol: Solution, colors: list) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Wedge

    S, K = inst.n_species, inst.skills
    ax.set_xlim(-0.05, 1.05)
    ax.set_ylim(-0.05, 1.05)
    ax.set_aspect("equal")
    ax.set_title("map: depots (squares), tasks (required skills), routes")
    ax.grid(alpha=0.2)
    # routes: one line per agent, offset within the species
    counts = [0] * S  # robots of each species; robots added during a mission come last
    idx_in_species = []  # [A] each robot's rank within its species
    for s in inst.agent_species.tolist():
        idx_in_species.append(counts[s])
        counts[s] += 1
    for a, route in enumerate(sol.routes):
        if not route:
            continue
        s = int(inst.agent_species[a])
        pts = np.array([inst.depots[a]] + [inst.task_locations[m] for m in route] + [inst.depots[a]])  # [n,2]
        k = idx_in_species[a]
        off = (k - (counts[s] - 1) / 2) * 0.006
        ax.plot(pts[:, 0] + off, pts[:, 1] + off, color=colors[s], lw=1.4, alpha=0.8,
                ls=LINESTYLES[k % len(LINESTYLES)], zorder=2)
        for p, q in zip(pts[:-1], pts[1:]):  # direction arrows at segment midpoints
            mid = (p + q) / 2 + off
            d = q - p
            if np.hypot(*d) > 0.04:
                ax.annotate("", xy=mid + d * 0.02, xytext=mid - d * 0.02,
                            arrowprops=dict(arrowstyle="->", color=colors[s], lw=1.2), zorder=2)
    # tasks as pies of required skills
    r = 0.022
    q = np.asarray(inst.requirements, dtype=float)  # [M,K]
    for m in range(inst.n_tasks):
        x, y = inst.task_locations[m]
        tot = q[m].sum()
        ang = 90.0
        for k in range(K):
            if q[m, k] <= 0:
                continue
            sweep = 360.0 * q[m, k] / tot
            ax.add_patch(Wedge((x, y), r, ang, ang + sweep, facecolor=SKILL_COLORS[k % len(SKILL_COLORS)],
                               edgecolor="#444444", lw=0.6, zorder=4))
            ang += sweep
        ax.text(x + r * 1.1, y + r * 1.1, str(m), fontsize=7, zorder=5)
    for s in range(S):
        x, y = inst.species_depots[s]
        ax.scatter([x], [y], marker="s", s=140, color=colors[s], edgecolor="black", lw=1.0, zorder=6)
        ax.text(x, y, str(s), fontsize=7, ha="center", va="center", color="white", weight="bold", zorder=7)
    handles = [Line2D([], [], marker="s", color=colors[s], ls="-", mec="black",
                      label=f"species {s}: {inst.species[s].count} x {_traits(inst.species[s].traits)}")
               for s in range(S)]
    used = [k for k in range(K) if (q[:, k] > 0).any()]
    handles += [Patch(facecolor=SKILL_COLORS[k % len(SKILL_COLORS)], edgecolor="#444444", label=f"task needs skill {k}") for k in used]
    ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.06), ncol=2, frameon=False)


def _traits(tr) -> str:
    return "[" + ",".join(f"{v:g}" for v in tr) + "]"


def _draw_gantt(ax, inst: Instance, sol: Solution, colors: list, timeline) -> None:
    from matplotlib.patches import Patch

    A = inst.n_agents
    h = 0.7
    for a in range(A):
        s = int(inst.agent_species[a])
        y = A - 1 - a
        for seg in timeline[a]:
            w = seg["t1"] - seg["t0"]
            if w <= 0:
                continue
            if seg["kind"] == "travel":
                ax.barh(y, w, left=seg["t0"], height=h * 0.45, color=colors[s], alpha=0.3, edgecolor="none")
            elif seg["kind"] == "wait":
                ax.barh(y, w, left=seg["t0"], height=h, color="#ffdddd", edgecolor="#cc3333", hatch="///", lw=0.5)
            else:
                ax.barh(y, w, left=seg["t0"], height=h, color=colors[s], edgecolor="black", lw=0.5)
                if w > 0.025 * max(sol.makespan, 1e-9):
                    ax.text(seg["t0"] + w / 2, y, str(seg["task"]), ha="center", va="center", fontsize=6,
                            color="white" if _dark(colors[s]) else "black")
    ax.set_yticks(range(A))
    ax.set_yticklabels([f"a{a} (s{int(inst.agent_species[a])})" for a in range(A)][::-1], fontsize=7)
    for lab, a in zip(ax.get_yticklabels(), range(A - 1, -1, -1)):
        lab.set_color(colors[int(inst.agent_species[a])])
    if sol.success and math.isfinite(sol.makespan):
        ax.axvline(sol.makespan, color="black", ls="--", lw=1)
        ax.text(sol.makespan, A - 0.4, f"makespan {sol.makespan:.2f} ", fontsize=7, va="bottom", ha="right")
    ax.set_xlabel("time")
    ax.set_ylim(-0.7, A - 0.1)
    end = max((seg["t1"] for segs in timeline for seg in segs), default=0.0)  # the last drawn time
    ax.set_xlim(0, max(sol.makespan if math.isfinite(sol.makespan) else 0, end, 1e-6) * 1.03)
    ax.set_title("Gantt: per agent travel / wait / work (task id)")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(handles=[Patch(color="grey", alpha=0.3, label="travel"),
                       Patch(facecolor="#ffdddd", edgecolor="#cc3333", hatch="///", label="wait"),
                       Patch(facecolor="grey", edgecolor="black", label="work")],
              fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.08), ncol=3, frameon=False)


def _dark(c) -> bool:
    r, g, b = c[:3]
    return 0.299 * r + 0.587 * g + 0.114 * b < 0.55


def _figure(inst: Instance, sol: Solution):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = _species_colors(inst.n_species)
    timeline = agent_timeline(inst, sol)
    fig = plt.figure(figsize=(15, 7.2))
    gs = fig.add_gridspec(1, 2, width_ratios=[1, 1.45], wspace=0.18)
    ax_map = fig.add_subplot(gs[0])
    ax_g = fig.add_subplot(gs[1])
    _draw_map(ax_map, inst, sol, colors)
    _draw_gantt(ax_g, inst, sol, colors, timeline)
    fig.suptitle(_title(inst, sol), fontsize=11)
    fig.subplots_adjust(left=0.04, right=0.98, top=0.91, bottom=0.17)
    return fig, ax_map, ax_g, colors, timeline


def render(inst: Instance, solution: Solution, out_path: str | Path, gif: bool = False,
           frames: int = 80, fps: int = 10, dpi: int = 110, source: str = "solution",
           progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Write the map + Gantt figure to ``out_path`` (format from its suffix, e.g. .png/.svg/.pdf).
    With ``gif=True`` also write an animation beside it (``out_path`` with suffix .gif; if
    ``out_path`` itself ends in .gif only the animation is written). Returns the written paths.
    ``progress(done, total)`` is called after each frame of the animation. A solution that does
    not belong to the instance (name, agent and task counts, species, task ids) raises
    :class:`~hmrta.solution.SolutionError` naming ``source``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    check_solution(inst, solution, source)
    out = Path(out_path)
    if not out.suffix:  # matplotlib would take the format from the temporary file's name
        raise ValueError(f"expected an image file name with its format as suffix (.png, .svg, .pdf, .gif), got {out}")
    if gif or out.suffix.lower() == ".gif":  # before anything is written
        for name, v in (("frames", frames), ("fps", fps)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name}: expected a positive integer, got {v!r}")
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
    written = []
    if out.suffix.lower() != ".gif":
        fig, *_ = _figure(inst, solution)
        with _atomic(out) as tmp:
            fig.savefig(tmp, dpi=dpi)
        plt.close(fig)
        written.append(out)
    if gif or out.suffix.lower() == ".gif":
        g = out if out.suffix.lower() == ".gif" else out.with_suffix(".gif")
        _animate(inst, solution, g, frames, fps, progress)
        written.append(g)
    return written


@contextlib.contextmanager
def _atomic(path: Path):
    """A temporary path beside ``path`` (same suffix, so the image format is the same), renamed
    onto ``path`` once written: never a half-written image."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        yield tmp
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _animate(inst: Instance, sol: Solution, path: Path, frames: int, fps: int,
             progress: Callable[[int, int], None] | None = None) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    fig, ax_map, ax_g, colors, timeline = _figure(inst, sol)
    T = sol.makespan if sol.success and math.isfinite(sol.makespan) else max(
        (s["t1"] for segs in timeline for s in segs), default=1.0)
    homes = [tuple(inst.depots[a]) for a in range(inst.n_agents)]
    dots = ax_map.scatter([p[0] for p in homes], [p[1] for p in homes], s=38, zorder=9,
                          c=[colors[int(s)] for s in inst.agent_species], edgecolors="black", linewidths=0.8)
    cursor = ax_g.axvline(0.0, color="red", lw=1.5)
    clock = ax_map.text(0.98, 0.02, "", transform=ax_map.transAxes, ha="right", va="bottom", fontsize=10,
                        zorder=10, bbox=dict(facecolor="white", edgecolor="grey", alpha=0.85))
    starts = np.array([t["start"] if t["start"] is not None else np.inf for t in sol.tasks], dtype=float)
    fins = np.array([t["finish"] if t["finish"] is not None else np.inf for t in sol.tasks], dtype=float)
    ring = ax_map.scatter(inst.task_locations[:, 0], inst.task_locations[:, 1], s=230, facecolors="none",
                          edgecolors="none", linewidths=2.0, zorder=8)

    def frame(i):
        t = T * i / max(frames - 1, 1)
        dots.set_offsets(np.array([_position(timeline[a], homes[a], t) for a in range(inst.n_agents)]))
        cursor.set_xdata([t, t])
        clock.set_text(f"t = {t:6.2f}")
        ec = np.where((starts <= t) & (t < fins), "red", np.where(fins <= t, "black", "none"))
        ring.set_edgecolors(list(ec))
        return dots, cursor, clock, ring

    anim = FuncAnimation(fig, frame, frames=frames, blit=False)
    with _atomic(path) as tmp:
        anim.save(str(tmp), writer=PillowWriter(fps=fps), dpi=60,
                  progress_callback=None if progress is None else lambda i, n: progress(i + 1, n))
    plt.close(fig)
