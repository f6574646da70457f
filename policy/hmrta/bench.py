"""Benchmarks: methods side by side on generated rows (the paper's Tables I-IV, the paper's numbers
beside ours) or on a user's own missions, with paired per-instance comparisons and provenance.

Results are cached per (row, method, instance, variant) in ``<out>/cache.jsonl`` so an interrupted
run resumes where it stopped; tables are written as Markdown, JSON and CSV (:func:`save`). Every
results file carries its provenance (:func:`provenance`): code version, checkpoint name and hash,
library versions, CPU, threads, command line and date.
"""
from __future__ import annotations

import csv
import functools
import hashlib
import io
import json
import math
import os
import platform
import re
import subprocess
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import metadata, resources
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import yaml

from .generators import PAPER_ROWS, ScenarioGenerator, row_name
from .instance import Instance, atomic_write_text

PAPER_NAME = {"greedy": "Greedy", "rl": "RL(g.)", "rl-s10": "RL(s.10)", "cpsat": "CTAS-D"}  # paper counterpart
DISPLAY_NAME = {"greedy": "Greedy", "greedy-coalition": "Greedy-coalition", "rl": "RL(g.)", "rl-s10": "RL(s.10)",
                "rl-lookahead": "RL-lookahead", "portfolio": "Portfolio",
                "cpsat": "CP-SAT"}
TABLE_TITLES = {"SA-BT": "Table I: SA-BT", "SA-AT": "Table II: SA-AT", "MA-AT": "Table III: MA-AT",
                "MA-AT-large": "Table IV: MA-AT, large"}
BENCH_FORMAT = "hmrta-bench/1"  # results.json (docs/schemas/hmrta-bench-1.schema.json)
DEFAULT_BENCH_SEED = 1000  # never used by training (stream seed 0) or validation (990001)
# paired comparisons made when none are asked for, each when both methods are in the table: the
# learned policy and the default method against the two rules
DEFAULT_PAIRS = (("rl", "greedy"), ("rl", "greedy-coalition"), ("portfolio", "greedy"), ("portfolio", "greedy-coalition"))
TIE_TOLERANCE = 1e-9  # relative makespan difference counted as a tie
CSV_FIELDS = ("table", "row", "kn", "ks", "km", "kb", "method", "n", "success", "makespan_mean", "makespan_std",
              "awt_mean", "awt_std", "redundancy_mean", "redundancy_std", "compute_seconds", "gap_to_bound_mean")
# appended to CSV_FIELDS when a row holds dynamic missions (released tasks or timed events)
CSV_DYNAMIC_FIELDS = ("mean_response_mean", "mean_response_std", "max_response_mean", "max_response_std",
                      "lost_cancelled_mean", "lost_unsatisfiable_mean", "lost_rejected_mean")
LOST_KINDS = ("cancelled", "unsatisfiable", "rejected")


@functools.lru_cache(maxsize=1)
def paper_tables() -> dict:
    return yaml.safe_load(resources.files("hmrta").joinpath("data/paper_tables.yaml").read_text())


@dataclass(frozen=True)
class Row:
    """One generated row: ``count`` seeded instances of a scenario at one size."""

    table: str  # SA-BT, SA-AT, MA-AT, MA-AT-large
    agents: int
    species: int
    tasks: int
    skills: int

    kind = "generated"

    @property
    def scenario(self) -> str:
        return "MA-AT" if self.table == "MA-AT-large" else self.table

    @property
    def key(self) -> str:
        return row_name(self.table, self.agents, self.species, self.tasks, self.skills)

    @property
    def size(self) -> list:
        return [self.agents, self.species, self.tasks, self.skills]

    def generator(self) -> ScenarioGenerator:
        return ScenarioGenerator(self.scenario, self.agents, self.species, self.tasks, self.skills)

    def instances(self, count: int, seed: int) -> list[tuple[Any, Instance]]:
        """(cache identity, instance) pairs: instance i of the seeded set."""
        return list(enumerate(self.generator().generate(count, seed)))

    def paper(self) -> dict | None:
        for r in paper_tables().get(self.table, []):
            if (r["kn"], r["ks"], r["km"], r["kb"]) == (self.agents, self.species, self.tasks, self.skills):
                return r
        return None


@dataclass(frozen=True)
class MissionSet:
    """A row of a user's own missions (instance files, CTAS-D folders), in the given order."""

    name: str
    files: tuple[Path, ...]
    loaded: tuple[Instance, ...] = field(default=(), compare=False, repr=False)

    kind = "missions"
    table = "missions"

    @classmethod
    def load(cls, name: str, files: Iterable[str | Path]) -> "MissionSet":
        from .formats import load_instance

        files = tuple(Path(f) for f in files)
        return cls(name, files, tuple(load_instance(f) for f in files))

    @property
    def key(self) -> str:
        return f"missions:{self.name}"

    @property
    def size(self) -> list:
        """[agents, species, tasks, skills], each a number or a 'low-high' range."""
        cols = [[i.n_agents for i in self.loaded], [i.n_species for i in self.loaded],
                [i.n_tasks for i in self.loaded], [i.skills for i in self.loaded]]
        return [(min(c) if min(c) == max(c) else f"{min(c)}-{max(c)}") if c else 0 for c in cols]

    def instances(self, count: int, seed: int) -> list[tuple[Any, Instance]]:
        """(cache identity, instance) pairs; the identity follows the content, not just the name."""
        out = []
        for f, inst in zip(self.files, self.loaded):
            content = inst.to_dict() | ({"events": list(inst.events)} if inst.events else {})  # a scenario's events
            digest = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]
            out.append((f"{f.stem}@{digest}", inst))
        return out

    def paper(self) -> None:
        return None


def paper_suite(tables: Iterable[str] | None = None) -> list[Row]:
    tables = list(tables or PAPER_ROWS)
    return [Row(t, *r) for t in tables for r in PAPER_ROWS[t]]


def _mean_std(values: Iterable[float | None]) -> tuple[float, float]:
    v = np.array([x for x in values if x is not None], dtype=float)
    return (float(v.mean()), float(v.std())) if len(v) else (math.nan, math.nan)


def response_record(sol) -> dict:
    """A solve's response figures for the bench cache: mean and max response time (finish -
    release) over its done tasks, the tasks lost by kind, and whether the mission is dynamic
    (released tasks or timed events). A static mission's tasks are all released at 0."""
    dyn = sol.extra.get("dynamic")
    if dyn is not None:
        return {"dynamic": True, "mean": dyn["mean_response"], "max": dyn["max_response"],
                "lost": {k: int(dyn["tasks_lost"][k]) for k in LOST_KINDS}}
    fin = [t["finish"] for t in sol.tasks if t["finish"] == t["finish"]]
    return {"dynamic": False, "mean": float(np.mean(fin)) if fin else None, "max": float(max(fin)) if fin else None,
            "lost": {k: 0 for k in LOST_KINDS}}


def summarise(results: list[dict]) -> dict:
    """mean/std over solved instances, plus success rate and mean compute seconds. When a result
    comes from a dynamic mission, ``dynamic`` adds the response figures over every mission of the
    row that has them (solved or not: a task done is a task answered): mean/std of the per-mission
    mean and max response time, and the mean number of tasks lost per mission by kind."""
    ok = [r for r in results if r["success"]]
    def ms(key):
        return _mean_std(r[key] for r in ok)
    out = {
        "n": len(results), "success": len(ok) / len(results) if results else math.nan,
        "makespan": ms("makespan"), "awt": ms("awt"), "redundancy": ms("redundancy"),
        "compute_seconds": float(np.mean([r["compute_seconds"] for r in results])) if results else math.nan,
        "gap_to_bound": ms("gap") if ok and all("gap" in r for r in ok) else None,
    }
    left: dict[str, dict] = {}  # a portfolio's candidates left out: on how many missions, and why
    for r in results:
        for c, why in (r.get("left_out") or {}).items():
            left.setdefault(c, {"missions": 0, "reason": why})["missions"] += 1
    if left:
        out["left_out"] = left
    resp = [r["response"] for r in results if r.get("response")]
    if any(x["dynamic"] for x in resp):
        out["dynamic"] = {
            "n": len(resp), "n_dynamic": sum(x["dynamic"] for x in resp),
            "mean_response": _mean_std(x["mean"] for x in resp),
            "max_response": _mean_std(x["max"] for x in resp),
            "tasks_lost": {k: float(np.mean([x["lost"][k] for x in resp])) for k in LOST_KINDS},
        }
    return out


# ---------------------------------------------------------------------------------------------
# paired comparisons
# ---------------------------------------------------------------------------------------------
def t_cdf(t: float, df: int) -> float:
    """Student's t distribution function P(T <= t) for an integer number of degrees of freedom
    (closed form, Abramowitz & Stegun 26.7.3-4)."""
    if df < 1:
        raise ValueError("df must be >= 1")
    theta = math.atan(t / math.sqrt(df))
    s, c = math.sin(theta), math.cos(theta)
    c2 = c * c
    if df % 2:  # odd
        series, coef = 0.0, 1.0
        for j in range((df - 1) // 2):
            if j:
                coef *= 2 * j / (2 * j + 1)
            series += coef * c2 ** j
        a = 2 / math.pi * (theta + s * c * series)
    else:
        series, coef = 0.0, 1.0
        for j in range(df // 2):
            if j:
                coef *= (2 * j - 1) / (2 * j)
            series += coef * c2 ** j
        a = s * series
    return 0.5 + 0.5 * a


def t_quantile(p: float, df: int) -> float:
    """Inverse of :func:`t_cdf` for 0.5 <= p < 1 (bisection to 1e-12)."""
    lo, hi = 0.0, 1.0
    while t_cdf(hi, df) < p:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if t_cdf(mid, df) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12:
            break
    return 0.5 * (lo + hi)


def paired_comparison(a: list[dict], b: list[dict], name_a: str = "a", name_b: str = "b") -> dict:
    """Per-instance comparison of two methods' results on the same instances (lower makespan wins).

    An instance one method solved and the other did not is a win for the one that solved it; both
    failing is a tie; otherwise makespans within a relative :data:`TIE_TOLERANCE` tie. The mean
    difference ``a - b`` (negative: ``a`` shorter) and its 95% t-interval are over the instances
    both solved (``n_paired``); ``relative`` is that mean over the mean makespan of ``b`` there,
    which long missions dominate in a mixed set; ``ratio`` weighs every mission alike: the geometric
    mean of the per-mission ratios ``a / b`` over the pairs with both makespans positive (None when
    there is none)."""
    if len(a) != len(b):
        raise ValueError(f"paired comparison needs the same instances ({len(a)} vs {len(b)} results)")
    wins = ties = losses = 0
    diffs, base, logs = [], [], []
    for ra, rb in zip(a, b):
        if ra["success"] and rb["success"]:
            d = float(ra["makespan"]) - float(rb["makespan"])
            diffs.append(d)
            base.append(float(rb["makespan"]))
            if float(ra["makespan"]) > 0 and float(rb["makespan"]) > 0:
                logs.append(math.log(float(ra["makespan"]) / float(rb["makespan"])))
            if abs(d) <= TIE_TOLERANCE * max(1.0, abs(float(rb["makespan"]))):
                ties += 1
            elif d < 0:
                wins += 1
            else:
                losses += 1
        elif ra["success"]:
            wins += 1
        elif rb["success"]:
            losses += 1
        else:
            ties += 1
    n = len(diffs)
    mean = float(np.mean(diffs)) if n else math.nan
    ci = None
    if n >= 2:
        half = t_quantile(0.975, n - 1) * float(np.std(diffs, ddof=1)) / math.sqrt(n)
        ci = [mean - half, mean + half]
    mb = float(np.mean(base)) if n else math.nan
    return {"a": name_a, "b": name_b, "n": len(a), "wins": wins, "ties": ties, "losses": losses,
            "n_paired": n, "mean_diff": mean, "ci95": ci,
            "relative": mean / mb if n and mb > 0 else math.nan,
            "ratio": math.exp(float(np.mean(logs))) if logs else None}


def comparison_pairs(methods: list[str], pairs: Iterable[tuple[str, str]] | None) -> list[tuple[str, str]]:
    """The pairs to compare: the given ones, or :data:`DEFAULT_PAIRS` present among ``methods``."""
    if pairs is None:
        return [p for p in DEFAULT_PAIRS if p[0] in methods and p[1] in methods]
    out = []
    for a, b in pairs:
        for m in (a, b):
            if m not in methods:
                raise ValueError(f"--compare {a},{b}: {m!r} is not one of the benchmarked methods "
                                 f"({', '.join(methods)})")
        if a == b:
            raise ValueError(f"--compare {a},{b}: expected two different methods")
        out.append((a, b))
    return out


# ---------------------------------------------------------------------------------------------
# provenance
# ---------------------------------------------------------------------------------------------
def _git(args: list[str], cwd: Path) -> str | None:
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}  # read only: never take the index lock
    try:
        r = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=10, env=env)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def code_version() -> str:
    """``git describe --always --dirty`` of the checkout this package runs from (dirty: tracked
    files modified), or ``hmrta <version>`` for an installed package."""
    from . import __version__

    here = Path(__file__).resolve().parent
    if _git(["ls-files", "--error-unmatch", "__init__.py"], here) is None:  # not a tracked checkout
        return f"hmrta {__version__}"
    desc = _git(["describe", "--always"], here)
    if not desc:
        return f"hmrta {__version__}"
    dirty = _git(["status", "--porcelain", "--untracked-files=no"], here)
    return desc + ("-dirty" if dirty else "")


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, val = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware") and val.strip():
                return val.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def provenance(methods: list[str], solve_opts: dict[str, Any], command: str | None = None,
               ran: Iterable[str] | None = None) -> dict:
    """What produced a results file: code version, checkpoint (for rl methods: file name and
    sha256), library versions, CPU model and cores, torch threads, command line, UTC date.
    ``ran``: the method specs that solved something (default: every spec of the runs, see
    :func:`run_specs`); a checkpoint is listed only when one of them read it."""
    from . import __version__
    from .methods import parse

    def describe(ck: str | None) -> dict:
        from .rl.checkpoint_info import SHIPPED_DIR, checkpoint_path

        path = checkpoint_path(ck)
        return {"name": path.name, "sha256": file_sha256(path) if path.is_file() else None,
                "shipped": path.resolve().parent == SHIPPED_DIR.resolve()}

    ran = {s for m in methods for s in run_specs(m, solve_opts)} if ran is None else set(ran)
    # the default checkpoint: read by a spec that ran without one of its own (rl, not rl@broad)
    reads_default = any(uses_checkpoint(s) and "checkpoint" not in parse(s)[1] for s in ran)
    checkpoint = describe(solve_opts.get("checkpoint")) if reads_default else None
    own = {spec: describe(ck) for m in methods for spec, ck in own_checkpoints(m, solve_opts).items()
           if spec in ran}
    torch_threads = sys.modules["torch"].get_num_threads() if "torch" in sys.modules else None
    return {
        "code_version": code_version(),
        "checkpoint": checkpoint,
        **({"own_checkpoints": own} if own else {}),  # METHOD@CHECKPOINT specs (methods or candidates)
        "versions": {"hmrta": __version__, "python": platform.python_version(), "numpy": _version("numpy"),
                     "torch": _version("torch"), "ortools": _version("ortools")},
        "cpu": {"model": cpu_model(), "cores": os.cpu_count()},
        # load averages (1, 5, 15 min) when the file was written: compute times are only as
        # comparable as the machine was quiet
        "load_average": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "torch_threads": torch_threads,
        "command": command,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def uses_checkpoint(method: str) -> bool:
    """Whether a method's results depend on the policy checkpoint (it takes a checkpoint option:
    the rl methods and portfolio)."""
    from .methods import get, parse

    return get(parse(method)[0]).option("checkpoint") is not None


def run_specs(method: str, solve_opts: dict[str, Any]) -> list[str]:
    """The method specs a run of ``method`` solves with: the method itself, or a portfolio's candidates."""
    from .methods import get, parse
    from .portfolio import candidate_methods

    return candidate_methods(solve_opts.get("candidates")) if get(parse(method)[0]).choose else [method]


def own_checkpoints(method: str, solve_opts: dict[str, Any]) -> dict[str, str]:
    """{spec: checkpoint} of the specs of a run (:func:`run_specs`) that name a checkpoint of
    their own (``rl@broad``)."""
    from .methods import parse

    implied = {s: parse(s)[1] for s in run_specs(method, solve_opts)}
    return {s: o["checkpoint"] for s, o in implied.items() if "checkpoint" in o}


def fixed_rules(method: str, solve_opts: dict[str, Any]) -> dict[str, dict]:
    """The rules of ``method`` (a portfolio: of each of its candidates) that are fixed in code,
    by method name: the baselines'. The learned policy's rules are its checkpoint's."""
    from .methods import get, parse, rules

    out = {}
    for n in run_specs(method, solve_opts):
        name = parse(n)[0]
        if get(name).rules is not None and not uses_checkpoint(name):
            out[name] = rules(name).to_dict()
    return out


def method_variant(method: str, solve_opts: dict[str, Any]) -> str:
    """What a cached result depends on besides (row, method, instance, seed): the solve options and,
    for the learned policy, the checkpoint's content. A retrained checkpoint or another time limit
    therefore never reuses stale cached results."""
    from .methods import get, parse

    parts: dict[str, Any] = {"opts": {k: solve_opts[k] for k in sorted(solve_opts)}}
    name, implied = parse(method)
    defaults = {o.name: o.default for o in get(name).options
                if o.name not in solve_opts and o.name not in implied and o.name != "checkpoint"}
    if defaults:  # the options left at their defaults, so a changed default re-solves
        parts["defaults"] = defaults
    rules = fixed_rules(method, solve_opts)
    if rules:  # a baseline's rules (a portfolio: its candidates'), so a changed rule re-solves
        parts["rules"] = rules
    if uses_checkpoint(method):
        from .rl.checkpoint_info import checkpoint_path

        def content(ck: str | None) -> str | None:
            path = checkpoint_path(ck)
            return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else None

        parts["checkpoint"] = content(solve_opts.get("checkpoint"))
        own = own_checkpoints(method, solve_opts)
        if own:  # rl@broad, or a portfolio's candidates with checkpoints of their own
            parts["own_checkpoints"] = {spec: content(ck) for spec, ck in sorted(own.items())}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _options_for(method: str, solve_opts: dict[str, Any]) -> dict[str, Any]:
    """The shared options this method takes (others are left out, not errors)."""
    from .methods import options_for

    return options_for(method, solve_opts)


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------
def _row_instances(row, count: int, seed: int) -> list[tuple[Any, Instance]]:
    """A row's (cache identity, instance) pairs: its own ``instances`` or its seeded generator's."""
    if hasattr(row, "instances"):
        return row.instances(count, seed)
    return list(enumerate(row.generator().generate(count, seed)))


def _row_size(row) -> list:
    return list(row.size) if hasattr(row, "size") else [row.agents, row.species, row.tasks, row.skills]


def _solve_record(job: tuple) -> dict:
    """One cache record: ``job`` = (row key, method, instance identity, seed, variant, instance,
    options); the instance is solved with ``seed=0`` (a module-level function: it runs in
    :mod:`hmrta.fanout` workers as well as here)."""
    row_key, method, ident, row_seed, variant, inst, opts = job
    from . import methods as M

    sol = M.solve(inst, method, seed=0, **opts)
    r = {"row": row_key, "method": method, "index": ident, "seed": row_seed,
         "variant": variant, "success": sol.success,
         "makespan": sol.makespan, "awt": sol.awt, "redundancy": sol.redundancy,
         "compute_seconds": sol.compute_seconds, "response": response_record(sol)}
    lb = sol.extra.get("lower_bound")
    if lb is not None:
        r["solver_bound"] = lb
    left_out = (sol.extra.get("portfolio") or {}).get("left_out")
    if left_out:  # a portfolio's default candidates that could not run on this mission, with the reason
        r["left_out"] = dict(left_out)
    return r


def read_cache(path: Path) -> dict[tuple, dict]:
    """The records of a bench cache (``cache.jsonl``: one :func:`_solve_record` a line) by
    (row, method, instance identity, seed, variant); a later record of the same key replaces an
    earlier one. A last line cut short by an interruption is left out. Raises InputError naming
    the file, the line and the field of anything else that is not such a record (a damaged or
    edited cache would otherwise be read as results)."""
    from .reading import InputError, decode_text, read_bytes

    lines = decode_text(read_bytes(path, max_bytes=2**30), str(path)).splitlines()
    cache: dict[tuple, dict] = {}
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
        except json.JSONDecodeError as e:
            if n == len(lines):
                continue  # cut short by an interruption: solved again
            raise InputError(f"{path}:{n}: not JSON ({e.msg}); {_CACHE_FIX}") from None
        _check_cache_record(r, f"{path}:{n}")
        cache[(r["row"], r["method"], r["index"], r["seed"], r.get("variant"))] = r
    return cache


_CACHE_FIX = "a damaged cache: remove the line (or the file) and those results are solved again"


def _check_cache_record(r: Any, where: str) -> None:
    """InputError("<where>: <field>: expected ..., got ...") unless ``r`` is a record as
    :func:`_solve_record` writes it."""
    from .reading import InputError, short

    def bad(key: str, want: str, got: Any) -> None:
        raise InputError(f"{where}: {key}: expected {want}, got {short(got)} ({_CACHE_FIX})")

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if not isinstance(r, dict):
        bad("record", "a JSON object", r)
    for k in ("row", "method"):
        if not isinstance(r.get(k), str):
            bad(k, "a string", r.get(k))
    if not isinstance(r.get("index"), (int, str)) or isinstance(r.get("index"), bool):
        bad("index", "an integer or a string", r.get("index"))
    if not isinstance(r.get("seed"), int) or isinstance(r.get("seed"), bool):
        bad("seed", "an integer", r.get("seed"))
    if r.get("variant") is not None and not isinstance(r["variant"], str):
        bad("variant", "a string", r["variant"])
    if not isinstance(r.get("success"), bool):
        bad("success", "true or false", r.get("success"))
    for k in ("makespan", "awt", "redundancy", "compute_seconds"):
        if not number(r.get(k)):
            bad(k, "a number", r.get(k))
    if r["success"] and not (math.isfinite(r["makespan"]) and r["makespan"] >= 0):
        bad("makespan", "a finite number >= 0 (the result is a success)", r["makespan"])
    if not (math.isfinite(r["compute_seconds"]) and r["compute_seconds"] >= 0):
        bad("compute_seconds", "a finite number >= 0", r["compute_seconds"])
    if r.get("solver_bound") is not None and not number(r["solver_bound"]):
        bad("solver_bound", "a number", r["solver_bound"])
    left = r.get("left_out")
    if left is not None and not (isinstance(left, dict) and all(isinstance(v, str) for v in left.values())):
        bad("left_out", "an object of candidate: reason", left)
    resp = r.get("response")
    if resp is None:
        return
    if not isinstance(resp, dict) or not isinstance(resp.get("dynamic"), bool):
        bad("response", 'an object with "dynamic" true or false', resp)
    for k in ("mean", "max"):
        if resp.get(k) is not None and not number(resp[k]):
            bad(f"response.{k}", "a number or null", resp[k])
    lost = resp.get("lost")
    if not isinstance(lost, dict) or any(not isinstance(lost.get(k), int) or isinstance(lost.get(k), bool)
                                         for k in LOST_KINDS):
        bad("response.lost", f"an object of whole numbers for {', '.join(LOST_KINDS)}", lost)


def run_bench(rows: list, methods: list[str], count: int, seed: int, out_dir: Path | None,
              solve_opts: dict[str, Any], progress: bool = True, with_bounds: bool = False,
              log: Callable[[str], None] = print, compare: Iterable[tuple[str, str]] | None = None,
              command: str | None = None, workers: int = 1, ray_address: str | None = None) -> dict:
    """Run every method on every row (:class:`Row` or :class:`MissionSet`); returns the summary
    (see :func:`save`). ``compare``: method pairs for paired comparisons (None: the defaults).
    ``workers`` > 1 or ``ray_address``: the uncached solves run as Ray tasks (:mod:`hmrta.fanout`,
    torch on one thread per task), then the tables are made exactly as in a serial run."""
    from tqdm import tqdm

    from . import methods as M
    from .deps import require

    pairs = comparison_pairs(methods, compare)
    for m in methods:  # a missing optional dependency is reported before any work
        rec = M.get(M.parse(m)[0])
        for mod in rec.needs:
            require(mod, f"method {rec.name}")
    from .fanout import Fanout

    fan = Fanout(workers, ray_address)  # a missing Ray is reported before any work, too
    cache_path = out_dir / "cache.jsonl" if out_dir else None
    cache = read_cache(cache_path) if cache_path and cache_path.exists() else {}
    sets = [(row, _row_instances(row, count, seed)) for row in rows]
    if out_dir:  # once the instances are drawn: a row that cannot be drawn leaves no empty folder
        out_dir.mkdir(parents=True, exist_ok=True)
    total = sum(len(insts) for _, insts in sets) * len(methods)
    bar = tqdm(total=total, desc="bench", disable=not progress, unit="solve", file=sys.stderr)
    fh = open(cache_path, "a") if cache_path else None
    # the test-set seed and size say what a generated row is; a user's missions are given, not drawn
    drawn = any(getattr(row, "kind", "generated") != "missions" for row in rows)
    summary: dict[str, Any] = {"format": BENCH_FORMAT, **({"seed": seed, "count": count} if drawn else {}),
                               "methods": methods, "rows": []}
    opts = {m: _options_for(m, solve_opts) for m in methods}
    variants = {m: method_variant(m, opts[m]) for m in methods}
    if cache:  # what this run can take from the cache: the same mission, method and options
        wanted = [(row.key, m, ident, 0 if getattr(row, "kind", "generated") == "missions" else seed, variants[m])
                  for row, insts in sets for m in methods for ident, _ in insts]
        log(f"resuming: {sum(k in cache for k in wanted)} of {len(wanted)} results cached in {cache_path} (the "
            f"others are solved: new, or their mission or options changed)")

    def store(key: tuple, r: dict) -> None:
        cache[key] = r
        if fh:
            fh.write(json.dumps(r) + "\n")
            fh.flush()

    try:
        if fan.distributed:  # the uncached solves fanned out; the loop below then finds them cached
            jobs: dict[tuple, tuple] = {}
            for row, insts in sets:
                row_seed = 0 if getattr(row, "kind", "generated") == "missions" else seed
                for method in methods:
                    for ident, inst in insts:
                        key = (row.key, method, ident, row_seed, variants[method])
                        if key not in cache:
                            jobs.setdefault(key, (row.key, method, ident, row_seed, variants[method], inst,
                                                  opts[method]))
            keys = list(jobs)
            if keys:
                log(f"solving {len(keys)} uncached items on {fan.slots()} Ray CPUs")

            def arrived(i: int, r: dict) -> None:
                store(keys[i], r)
                bar.update(1)
                bar.set_postfix(row=r["row"], method=r["method"])

            fan.map(_solve_record, [jobs[k] for k in keys], on_result=arrived)
            bar.reset(total=total)
        for row, insts in sets:
            kind = getattr(row, "kind", "generated")
            row_seed = 0 if kind == "missions" else seed
            bounds = None
            if with_bounds:
                from .bounds import lower_bounds

                # a mission with events has none: a cancellation or a lost robot can undercut any bound
                bounds = [None if inst.events else lower_bounds(inst)["best"] for _, inst in insts]
            per_method: dict[str, list[dict]] = {}
            for method in methods:
                res = []
                for ident, inst in insts:
                    key = (row.key, method, ident, row_seed, variants[method])
                    if key not in cache:
                        store(key, _solve_record((row.key, method, ident, row_seed, variants[method], inst,
                                                  opts[method])))
                    res.append(dict(cache[key]))
                    bar.update(1)
                    bar.set_postfix(row=row.key, method=method)
                per_method[method] = res
            if bounds is not None:  # best bound per instance: cheap bounds and every solver's proven bound
                for i, b in enumerate(bounds):
                    if b is None:
                        continue
                    b = max([b] + [res[i].get("solver_bound") or 0.0 for res in per_method.values()])
                    for res in per_method.values():
                        if res[i]["success"]:
                            m = res[i]["makespan"]  # the gap as hmrta bound and CP-SAT give it
                            res[i]["gap"] = (m - b) / m if m > 0 else 0.0
            entry: dict[str, Any] = {
                "row": row.key, "table": row.table, "kind": kind, "size": _row_size(row),
                "results": {m: summarise(r) for m, r in per_method.items()},
                "comparisons": [paired_comparison(per_method[a], per_method[b], a, b) for a, b in pairs],
                "makespans": {m: [r["makespan"] if r["success"] else None for r in res]
                              for m, res in per_method.items()},
            }
            if kind == "missions":
                entry["name"] = row.name
                entry["instances"] = [str(f) for f in row.files]
            elif not isinstance(row, Row):  # e.g. a mission family: named rows
                entry["name"] = row.key
            elif row.paper() is not None:
                entry["kind"] = "paper"
            summary["rows"].append(entry)
    finally:
        bar.close()
        fan.close()
        if fh:
            fh.close()
    left = left_out_summary(summary)
    for m, lo in left.items():
        for (n, of, why), cs in _grouped(lo).items():
            log(f"{m}: left out {', '.join(cs)} on {n} of {of} mission(s) ({why})")

    ran = [s for m in methods for s in run_specs(m, solve_opts)  # unless left out of all the run's missions
           if s not in left.get(m, {}) or left[m][s][0] < left[m][s][1]]
    summary["provenance"] = provenance(methods, solve_opts, command, ran=ran)
    if fan.distributed:  # solves ran side by side: their compute seconds shared the machine(s)
        summary["provenance"]["fanout"] = {"workers": workers, "ray_address": ray_address}
    return summary


def _grouped(left: dict[str, Any]) -> dict[Any, list[str]]:
    """The candidates of ``left`` (candidate -> what is said of it, hashable) by what is said of them."""
    by: dict[Any, list[str]] = {}
    for c, said in left.items():
        by.setdefault(said, []).append(c)
    return by


def left_out_summary(summary: dict) -> dict[str, dict[str, tuple[int, int, str]]]:
    """{method: {candidate: (missions it was left out of, the method's missions in every row, a
    reason)}} of a summary: a portfolio's default candidates that could not run."""
    out: dict[str, dict[str, tuple[int, int, str]]] = {}
    for m in summary["methods"]:
        res = [r["results"][m] for r in summary["rows"] if m in r["results"]]
        total = sum(x["n"] for x in res)
        left: dict[str, tuple[int, int, str]] = {}
        for x in res:
            for c, lo in (x.get("left_out") or {}).items():
                left[c] = (left.get(c, (0, 0, ""))[0] + lo["missions"], total, lo["reason"])
        if left:
            out[m] = left
    return out


# ---------------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------------
def _pm(v: tuple[float, float] | None, nd: int = 2) -> str:
    if v is None or v[0] is None or (isinstance(v[0], float) and math.isnan(v[0])):
        return "—"
    return f"{v[0]:.{nd}f} ± {v[1]:.{nd}f}"


def _paper_vals(p: dict | None, method: str) -> dict | None:
    if not p:
        return None
    name = PAPER_NAME.get(method)
    vals = p.get(name) if name else None
    if not vals:
        return None
    red = (p.get("redundancy") or {}).get(name)
    return {"success": vals[0], "makespan": (vals[1], vals[2]) if vals[1] is not None else None,
            "awt": (vals[3], vals[4]) if vals[3] is not None else None, "compute_seconds": vals[5],
            "redundancy": tuple(red) if red else None}


def _title(table: str, rows: list[dict], summary: dict) -> str:
    """A paper table's title only when every row is a paper row; otherwise what the rows are."""
    if table == "missions":
        n = sum(next(iter(r["results"].values()))["n"] for r in rows) if rows and rows[0]["results"] else 0
        return f"Missions ({n} instances)"
    per = f"{summary['count']} instances per row, seed {summary['seed']}"
    if table in TABLE_TITLES and all(r.get("kind") == "paper" for r in rows):
        return f"{TABLE_TITLES[table]} ({per})"
    if table in TABLE_TITLES:
        scenario = "MA-AT" if table == "MA-AT-large" else table
        return f"{scenario} scenario, generated rows ({per})"
    return f"{table} ({per})"


def provenance_markdown(prov: dict | None) -> list[str]:
    if not prov:
        return []
    v = prov.get("versions") or {}
    libs = ", ".join(f"{k} {v[k]}" for k in ("hmrta", "python", "numpy", "torch", "ortools") if v.get(k))
    cpu = prov.get("cpu") or {}
    lines = [f"- command: `{prov.get('command') or 'hmrta bench'}`",
             f"- date (UTC): {prov.get('date')}",
             f"- code: {prov.get('code_version')}"]
    ck = prov.get("checkpoint")
    if ck:
        lines.append(f"- checkpoint: {ck['name']}{' (shipped)' if ck.get('shipped') else ''}, "
                     f"sha256 {ck.get('sha256') or 'missing'}")
    for spec, c in (prov.get("own_checkpoints") or {}).items():
        lines.append(f"- checkpoint of {spec}: {c['name']}{' (shipped)' if c.get('shipped') else ''}, "
                     f"sha256 {c.get('sha256') or 'missing'}")
    lines.append(f"- software: {libs}")
    threads = prov.get("torch_threads")
    load = prov.get("load_average")
    lines.append(f"- machine: {cpu.get('model')}, {cpu.get('cores')} cores"
                 + (f"; torch threads {threads}" if threads is not None else "")
                 + (f"; load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} (1 / 5 / 15 min)" if load else ""))
    return lines + [""]


def _signed(v: float, nd: int = 2) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:+.{nd}f}"


def _method_name(method: str, paper: bool = False) -> str:
    """How a table names a method; ``paper``: in a table with the paper's columns, which also says
    the paper's method those columns show when it is another one (CP-SAT beside the paper's CTAS-D)."""
    base, at, ck = method.partition("@")
    m = re.fullmatch(r"rl-s(\d+)", base)
    name = DISPLAY_NAME.get(method) or (f"RL(s.{m.group(1)}){at}{ck}" if m else method)  # rl-s3: RL(s.3)
    theirs = PAPER_NAME.get(method)
    return f"{name} (vs paper {theirs})" if paper and theirs and theirs != name else name


def comparisons_markdown(rows: list[dict], paper: bool = False) -> list[str]:
    comps = [(r, c) for r in rows for c in r.get("comparisons") or []]
    if not comps:
        return []
    out = ["Paired comparisons per instance (makespan of A minus B; a win is a shorter makespan, or A "
           "solved an instance B failed; interval: 95% t-interval of the mean difference; relative: the "
           "mean difference over B's mean makespan, which long missions dominate; ratio: the geometric "
           "mean of A / B over the missions, each weighing alike):", "",
           "| row | A vs B | wins / ties / losses | mean difference | 95% interval | relative | ratio |",
           "|---|---|---|---|---|---|---|"]
    for r, c in comps:
        ci = c.get("ci95")
        rel = c.get("relative")
        out.append(f"| {_row_label(r)} | {_method_name(c['a'], paper)} vs {_method_name(c['b'], paper)} | "
                   f"{c['wins']} / {c['ties']} / {c['losses']} | {_signed(c['mean_diff'])} | "
                   + (f"[{ci[0]:+.2f}, {ci[1]:+.2f}]" if ci and ci[0] is not None else "—") + " | "
                   + ("—" if rel is None or (isinstance(rel, float) and math.isnan(rel)) else f"{rel * 100:+.1f}%")
                   + " | " + ("—" if c.get("ratio") is None else f"{c['ratio']:.3f}") + " |")
    return out + [""]


def _row_label(r: dict) -> str:
    return r.get("name") or ", ".join(map(str, r["size"]))


def _name_column(table: str) -> str:
    from .families import FAMILIES_TABLE

    return {"missions": "missions", FAMILIES_TABLE: "family"}.get(table, "row")


def to_markdown(summary: dict) -> str:
    out = provenance_markdown(summary.get("provenance"))
    rows_by_table: dict[str, list[dict]] = {}
    for r in summary["rows"]:
        rows_by_table.setdefault(r["table"], []).append(r)
    for table, rows in rows_by_table.items():
        show_red = table.startswith("MA-AT") or table == "missions"
        show_gap = any(res.get("gap_to_bound") for r in rows for res in r["results"].values())
        show_paper = any(r.get("kind") == "paper" for r in rows)
        show_dyn = any(res.get("dynamic") for r in rows for res in r["results"].values())
        out.append(f"### {_title(table, rows, summary)}")
        out.append("")
        named = any(r.get("name") for r in rows)
        head = ([_name_column(table)] if named else []) + ["kn, ks, km, kb", "method", "success", "makespan", "AWT"]
        if show_dyn:
            head += ["mean response", "max response", "tasks lost (cancelled / unsatisfiable / rejected)"]
        if show_red:
            head.append("redundancy")
        head.append("compute s")
        if show_gap:
            head.append("gap to bound")
        if show_paper:
            head += ["paper success", "paper makespan", "paper AWT"] + (["paper redundancy"] if show_red else []) \
                + ["paper compute s"]
        out.append("| " + " | ".join(head) + " |")
        out.append("|" + "---|" * len(head))
        for r in rows:
            paper = Row(table, *r["size"]).paper() if r.get("kind") == "paper" else None
            for method, res in r["results"].items():
                cells = ([r.get("name") or ""] if named else []) + [
                    ", ".join(map(str, r["size"])), _method_name(method, show_paper),
                    f"{res['success'] * 100:.0f}%", _pm(res["makespan"]), _pm(res["awt"])]
                if show_dyn:
                    d = res.get("dynamic")
                    cells += ([_pm(d["mean_response"]), _pm(d["max_response"]),
                               " / ".join(f"{d['tasks_lost'][k]:.2f}" for k in LOST_KINDS)] if d else ["—"] * 3)
                if show_red:
                    cells.append(_pm(res["redundancy"], 3))
                cells.append(f"{res['compute_seconds']:.3f}")
                if show_gap:
                    g = res.get("gap_to_bound")
                    cells.append(f"{g[0] * 100:.1f}%" if g else "—")
                if show_paper:
                    pv = _paper_vals(paper, method)
                    if pv:
                        cells += [f"{pv['success'] * 100:.0f}%", _pm(pv["makespan"]), _pm(pv["awt"])]
                        if show_red:
                            cells.append(_pm(pv["redundancy"], 3))
                        cells.append(f"{pv['compute_seconds']}" if pv["compute_seconds"] is not None else "—")
                    else:
                        cells += ["—"] * (4 + show_red)
                out.append("| " + " | ".join(cells) + " |")
        out.append("")
        for r in rows:  # a portfolio that could not simulate every candidate says which, and why
            for method, res in r["results"].items():
                for (n, why), cs in _grouped({c: (x["missions"], x["reason"])
                                              for c, x in (res.get("left_out") or {}).items()}).items():
                    out.append(f"- {_method_name(method, show_paper)} ({_row_label(r)}): left out {', '.join(cs)} on "
                               f"{n} of {res['n']} mission(s): {why}")
        if out[-1] != "":
            out.append("")
        out += comparisons_markdown(rows, show_paper)
    return "\n".join(out) + "\n"


def to_csv(summary: dict) -> str:
    """One line per (row, method) with the figures of the JSON summary (columns :data:`CSV_FIELDS`,
    then :data:`CSV_DYNAMIC_FIELDS` when a row holds dynamic missions; empty for the other rows)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    show_dyn = any(res.get("dynamic") for r in summary["rows"] for res in r["results"].values())
    w.writerow(CSV_FIELDS + (CSV_DYNAMIC_FIELDS if show_dyn else ()))

    def num(v):
        return "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else repr(float(v))

    for r in summary["rows"]:
        for method, res in r["results"].items():
            gap = res.get("gap_to_bound")
            line = [r["table"], r["row"], *r["size"], method, res["n"], num(res["success"]),
                    num(res["makespan"][0]), num(res["makespan"][1]), num(res["awt"][0]), num(res["awt"][1]),
                    num(res["redundancy"][0]), num(res["redundancy"][1]), num(res["compute_seconds"]),
                    num(gap[0]) if gap else ""]
            if show_dyn:
                d = res.get("dynamic")
                line += ([num(d["mean_response"][0]), num(d["mean_response"][1]), num(d["max_response"][0]),
                          num(d["max_response"][1])] + [num(d["tasks_lost"][k]) for k in LOST_KINDS]
                         if d else [""] * len(CSV_DYNAMIC_FIELDS))
            w.writerow(line)
    return buf.getvalue()


def save(summary: dict, out_dir: Path) -> list[Path]:
    """Write ``results.json``, ``results.md`` and ``results.csv`` into ``out_dir`` (atomically)."""
    out_dir = Path(out_dir)
    paths = [out_dir / "results.json", out_dir / "results.md", out_dir / "results.csv"]
    atomic_write_text(paths[0], json.dumps(clean(summary), indent=1) + "\n")
    atomic_write_text(paths[1], to_markdown(summary))
    atomic_write_text(paths[2], to_csv(summary))
    return paths


def clean(o: Any) -> Any:
    """NaN/inf -> None, tuples -> lists (strict JSON)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    return o
