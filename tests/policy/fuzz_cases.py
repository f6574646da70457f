"""Seeded mutation fuzzer over every file the ``hmrta`` command line reads.

Formats and the command that reads each:

=============  ===========================================================================
instance       ``hmrta solve F --method greedy`` (hmrta-instance/1 YAML)
ctas           ``hmrta solve DIR/config.json`` (CTAS-D config)
routes         ``hmrta evaluate BASE F``
solution       ``hmrta bound BASE F`` and ``hmrta render BASE F --out X.png``
checkpoint     ``hmrta solve BASE --method rl --checkpoint F``
train-config   ``hmrta train --config F --check`` (validates, never trains)
=============  ===========================================================================

Each case starts from a valid file of its format and applies one mutation, byte-level
(truncation, random bytes, non-UTF-8, huge numbers, NaN/infinity, empty file, deep nesting, YAML
alias bombs, a folder, a FIFO, a missing or oversized file) or structure-level (wrong types,
missing and extra fields, negative / zero / huge counts, mismatched lengths, swapped values). A
case passes when the command succeeds (exit 0 or 3) or exits 2 with one line on stderr that names
the file, within the time bound; heavy cases (deep nesting, alias bombs, FIFOs) run in a
subprocess under a memory limit and a timeout. Everything is drawn from ``random.Random`` seeded
per case: the same seed gives the same files.
"""
from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import os
import random
import re
import subprocess
import sys
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import yaml

ROOT = Path(__file__).resolve().parents[2]
FORMATS = ("instance", "ctas", "routes", "solution", "checkpoint", "train-config")
TIME_LIMIT = 10.0  # seconds per case
MEMORY_LIMIT = 2 * 2**30  # address space of a heavy case's subprocess (bytes)
GOOD = ("ok", "user-error")


@dataclass
class Case:
    id: int
    fmt: str
    kind: str  # the mutation
    data: bytes | None  # file content; None for the special kinds (folder, missing, fifo)
    path: tuple = ()  # structure mutations: the keys / indices of the mutated value
    heavy: bool = False  # run in a subprocess with memory and time limits
    render: bool = False  # solution cases: `hmrta render` instead of `hmrta bound`

    def describe(self) -> str:
        where = ".".join(map(str, self.path))
        return f"#{self.id} {self.fmt}/{self.kind}" + (f" at {where}" if where else "")


@dataclass
class Outcome:
    case: Case
    outcome: str  # ok | user-error | bad-message | internal | hang | slow
    rc: Any
    seconds: float
    message: str
    names_field: bool | None = None  # structure mutations answered with exit 2: a path component named
    detail: str = ""


# ---------------------------------------------------------------------------------------------
# valid seed files
# ---------------------------------------------------------------------------------------------
@dataclass
class Seeds:
    work: Path
    base: Path  # the instance routes / solutions / checkpoints are read against
    instance: list[bytes] = field(default_factory=list)
    ctas: list[bytes] = field(default_factory=list)
    routes: list[bytes] = field(default_factory=list)
    solution: list[bytes] = field(default_factory=list)
    checkpoint: list[bytes] = field(default_factory=list)
    train_config: list[bytes] = field(default_factory=list)

    def of(self, fmt: str) -> list[bytes]:
        return getattr(self, fmt.replace("-", "_"))


@contextlib.contextmanager
def one_thread():
    """torch on one thread while fuzzing: the policy networks are tiny, and thread start-up and
    contention would dominate each case."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def make_seeds(work: Path) -> Seeds:
    """Valid files of every format (small, so that valid mutants solve in milliseconds)."""
    import torch

    from hmrta.generators import ScenarioGenerator
    from hmrta.methods import solve
    from hmrta.rl.model import ModelConfig, PolicyNet

    work.mkdir(parents=True, exist_ok=True)
    inst = ScenarioGenerator("MA-AT", 4, 2, 3, 2).instance(7, 0)
    base = work / "base.yaml"
    inst.save(base)
    s = Seeds(work, base)
    s.instance = [inst.to_yaml().encode(), (ROOT / "tests" / "policy" / "data" / "example.yaml").read_bytes(),
                  ScenarioGenerator("SA-BT", 3, 3, 4, 3).instance(1, 0).to_yaml().encode()]
    s.ctas = [(ROOT / "tests" / "policy" / "data" / "ctas_small" / "config.json").read_bytes()]
    sol = solve(inst, "greedy", seed=0)
    s.routes = [json.dumps({"routes": sol.routes}).encode(), json.dumps(sol.to_dict()).encode()]
    failed = copy.deepcopy(sol.to_dict())
    failed.update(success=False, makespan=None, failure="deadlock", lower_bound=3.5, status="FEASIBLE")
    s.solution = [json.dumps(sol.to_dict(), indent=1).encode(), json.dumps(failed).encode()]
    torch.manual_seed(0)
    cfg = ModelConfig(d_model=16, heads=2, ff_hidden=16)
    ck = {"config": {"model": cfg.to_dict(), "rules": {"max_open": 2, "safety": True}}, "code_version": "fuzz",
          "iteration": 3, "model": PolicyNet(cfg).state_dict()}
    buf = io.BytesIO()
    torch.save(ck, buf)
    s.checkpoint = [buf.getvalue()]
    s.train_config = [p.read_bytes() for p in sorted((ROOT / "policy" / "configs").glob("*.yaml"))[:3]]
    return s


# ---------------------------------------------------------------------------------------------
# byte-level mutations
# ---------------------------------------------------------------------------------------------
NON_UTF8 = [b"\xff", b"\xfe\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\x80", b"\xf8\x88\x80\x80\x80", b"\xe2\x82"]
HUGE = [b"1e400", b"-1e400", b"1" + b"0" * 5000, b"9" * 400, b"1e-400", b"2e308", b"18446744073709551616",
        b"-9", b"123456789012345678901234567890", b"0x7fffffffffffffff", b"1_000_000"]
NANS = [b"NaN", b"Infinity", b"-Infinity", b".nan", b".inf", b"-.inf", b"nan", b"inf"]
EMPTY = [b"", b" \n", b"\xef\xbb\xbf", b"null", b"[]", b"{}", b"0", b"~", b"---\n...\n", b"\n\n\n"]
NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _bytes_truncate(r: random.Random, b: bytes) -> bytes:
    return b[:r.randrange(len(b))] if b else b


def _bytes_flip(r: random.Random, b: bytes) -> bytes:
    a = bytearray(b)
    for _ in range(r.randint(1, 8)):
        if a:
            a[r.randrange(len(a))] = r.randrange(256)
    return bytes(a)


def _bytes_insert(r: random.Random, b: bytes) -> bytes:
    i = r.randint(0, len(b))
    return b[:i] + bytes(r.randrange(256) for _ in range(r.randint(1, 16))) + b[i:]


def _bytes_delete(r: random.Random, b: bytes) -> bytes:
    if not b:
        return b
    i = r.randrange(len(b))
    return b[:i] + b[i + r.randint(1, 64):]


def _bytes_duplicate(r: random.Random, b: bytes) -> bytes:
    if not b:
        return b
    i = r.randrange(len(b))
    chunk = b[i:i + r.randint(1, 200)]
    j = r.randint(0, len(b))
    return b[:j] + chunk + b[j:]


def _bytes_non_utf8(r: random.Random, b: bytes) -> bytes:
    i = r.randint(0, len(b))
    return b[:i] + r.choice(NON_UTF8) + b[i:]


def _replace_number(r: random.Random, b: bytes, choices: list[bytes]) -> bytes:
    nums = list(NUMBER.finditer(b))
    if not nums:
        return b + r.choice(choices)
    m = r.choice(nums)
    return b[:m.start()] + r.choice(choices) + b[m.end():]


def _bytes_huge(r: random.Random, b: bytes) -> bytes:
    return _replace_number(r, b, HUGE)


def _bytes_nan(r: random.Random, b: bytes) -> bytes:
    return _replace_number(r, b, NANS)


def _bytes_empty(r: random.Random, b: bytes) -> bytes:
    return r.choice(EMPTY)


def _bytes_garbage(r: random.Random, b: bytes) -> bytes:
    return bytes(r.randrange(256) for _ in range(r.randint(1, 600)))


def _bytes_text_garbage(r: random.Random, b: bytes) -> bytes:
    alphabet = b"{}[]:,-\"' \n\t#&*!|>%@`0123456789abcxyz.eE+"
    return bytes(r.choice(alphabet) for _ in range(r.randint(1, 300)))


YAML_TRICKS = [b"!!python/object/apply:os.system ['touch PWNED']", b"!!python/name:os.system", b"2001-12-14",
               b"2001-13-45", b"!!binary aGVsbG8=", b"!!binary ***", b"!!set {a, b}", b"{<<: [1]}", b"*undefined",
               b"&a 1", b"!!float abc", b"!!int 0x1g", b"!!timestamp 99999-01-01", b"? [a]\n: 1", b"{[1]: 2}",
               b"\t1", b"'unterminated", b"!<tag:yaml.org,2002:str> 5", b"!custom 1", b"{a: 1, a: 2}",
               b"\"\\ud800\"", b"\"\\x00\"", b"1:20:30:40:50", b"0o777777777777777777777777", b"0b" + b"1" * 300]
JSON_TRICKS = [b'"\\ud800"', b'"\\udc80x"', b'{"a": 1, "a": 2}', b"[1,]", b"/* c */ 1", b"01", b"-", b"1e",
               b'"\\u0000"', b"true", b"[[[[[]]]]]", b'"' + b"x" * 100_000 + b'"', b"{\"\": {}}", b"1.0e+309"]


def _bytes_yaml_tricks(r: random.Random, b: bytes) -> bytes:
    if r.random() < 0.3:
        return b"\xef\xbb\xbf" + b if r.random() < 0.5 else b + b"\n--- {}\n"
    return _replace_value(r, b, YAML_TRICKS)


def _bytes_json_tricks(r: random.Random, b: bytes) -> bytes:
    if r.random() < 0.2:
        return b"\xef\xbb\xbf" + b
    return _replace_value(r, b, JSON_TRICKS)


def _replace_value(r: random.Random, b: bytes, choices: list[bytes]) -> bytes:
    """Replace a number or a quoted string token."""
    toks = list(NUMBER.finditer(b)) + list(re.finditer(rb'"[^"\\\n]*"', b))
    if not toks:
        return b + r.choice(choices)
    m = r.choice(toks)
    return b[:m.start()] + r.choice(choices) + b[m.end():]


BYTE_MUTATIONS: dict[str, Callable[[random.Random, bytes], bytes]] = {
    "truncate": _bytes_truncate, "random-bytes": _bytes_flip, "insert-bytes": _bytes_insert,
    "delete-span": _bytes_delete, "duplicate-span": _bytes_duplicate, "non-utf8": _bytes_non_utf8,
    "huge-number": _bytes_huge, "nan-inf": _bytes_nan, "empty": _bytes_empty, "garbage": _bytes_garbage,
    "text-garbage": _bytes_text_garbage, "yaml-tricks": _bytes_yaml_tricks, "json-tricks": _bytes_json_tricks,
}
TEXT_MUTATIONS = ("truncate", "random-bytes", "insert-bytes", "delete-span", "duplicate-span", "non-utf8",
                  "huge-number", "nan-inf", "empty", "garbage", "text-garbage")
BINARY_MUTATIONS = ("truncate", "random-bytes", "insert-bytes", "delete-span", "duplicate-span", "empty",
                    "garbage", "text-garbage")


# heavy byte-level cases: built whole, run in a subprocess
def _deep_json(r: random.Random, b: bytes) -> bytes:
    n = r.choice([100_000, 5_000, 40])
    kind = r.choice(["list", "object", "splice"])
    if kind == "list":
        return b"[" * n + b"]" * n
    if kind == "object":
        return b'{"a":' * n + b"1" + b"}" * n
    return _replace_number(r, b, [b"[" * n + b"]" * n])


def _deep_yaml(r: random.Random, b: bytes) -> bytes:
    n = r.choice([100_000, 5_000, 40])
    kind = r.choice(["flow", "block", "splice"])
    if kind == "flow":
        return b"[" * n + b"]" * n
    if kind == "block":
        return b"".join(b"  " * i + b"- \n" for i in range(min(n, 3000))) + b"  " * min(n, 3000) + b"x\n"
    return _replace_number(r, b, [b"[" * n + b"]" * n])


def _alias_bomb(r: random.Random, b: bytes) -> bytes:
    """Billion laughs: 9 levels of 9 aliases each (387 million strings when expanded)."""
    levels = [b'&l0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 9):
        levels.append(b"&l%d [" % i + b",".join([b"*l%d" % (i - 1)] * 9) + b"]")
    bomb = b"[" + b", ".join(levels) + b"]"
    where = r.choice(["whole", "name", "value", "recursive"])
    if where == "whole":
        return b"bomb: " + bomb + b"\n"
    if where == "recursive":
        return b"name: &a [1, *a]\n" + b
    if where == "name":  # a mapping key the validators read (and would quote in a message)
        return re.sub(rb"(?m)^name: .*$", b"name: " + bomb, b, count=1) if re.search(rb"(?m)^name:", b) \
            else b"name: " + bomb + b"\n" + b
    return _replace_number(r, b, [bomb])


# ---------------------------------------------------------------------------------------------
# structure-level mutations
# ---------------------------------------------------------------------------------------------
WRONG = ["text", "", [], {}, None, True, False, [1, 2], {"a": 1}, 1.5, -1, 0, 10**20, 1e308, "1", [[[]]],
         [None], {"x": [1, {"y": None}]}, -0.0, 2**63, "\u00e9\u4e2d"]


def _nodes(obj: Any, path: tuple = ()) -> list[tuple]:
    """Every (path) in a JSON-like tree (the root excluded)."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(path + (k,))
            out += _nodes(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append(path + (i,))
            out += _nodes(v, path + (i,))
    return out


def _get(obj: Any, path: tuple) -> Any:
    for k in path:
        obj = obj[k]
    return obj


def mutate_structure(r: random.Random, obj: Any, nodes: list[tuple] | None = None) -> tuple[str, tuple]:
    """Mutate ``obj`` in place; returns (kind, path of the mutated value)."""
    nodes = nodes if nodes is not None else _nodes(obj)
    if not nodes:
        return "none", ()
    path = r.choice(nodes)
    parent, key = _get(obj, path[:-1]), path[-1]
    value = parent[key]
    kind = r.choice(["delete", "extra-field", "wrong-type", "wrong-type", "negative-zero", "huge", "length",
                     "swap", "nan"])
    if kind == "delete":
        del parent[key]
    elif kind == "extra-field":
        target = value if isinstance(value, dict) else parent if isinstance(parent, dict) else None
        if target is None:
            parent.insert(key, copy.deepcopy(value)) if isinstance(parent, list) else None
            kind = "length"
        else:
            target[r.choice(["extra", "zzz", "Name", "0", "-1", "99"])] = r.choice(WRONG)
    elif kind == "wrong-type":
        parent[key] = copy.deepcopy(r.choice(WRONG))
    elif kind == "negative-zero":
        parent[key] = r.choice([-1, 0, -0.5, -(10**9), 0.0])
    elif kind == "huge":
        parent[key] = r.choice([10**9, 10**12, 2**31, 2**64, 10**400, 1e308, -1e308, 10**4000, 9_999, 10_001,
                                1e9, 1.0000001e9, 1e-9, 1e-12, 5e-324])
    elif kind == "length":
        if isinstance(value, list) and value and r.random() < 0.5:
            value.pop(r.randrange(len(value)))
        elif isinstance(value, list) and value:
            value.append(copy.deepcopy(r.choice(value)))
        elif isinstance(parent, list):
            parent.append(copy.deepcopy(value))
        else:
            parent[key] = [value, value]
    elif kind == "swap":
        other = _get(obj, r.choice(nodes))
        parent[key] = copy.deepcopy(other)
    elif kind == "nan":
        parent[key] = r.choice([math.nan, math.inf, -math.inf])
    return kind, path


def _dump_yaml(obj: Any) -> bytes:
    return yaml.safe_dump(obj, sort_keys=False, allow_unicode=True).encode()


def _dump_json(obj: Any) -> bytes:
    return json.dumps(obj).encode()


def _structure_case(r: random.Random, fmt: str, seed: bytes) -> tuple[bytes, str, tuple]:
    if fmt == "checkpoint":
        return _checkpoint_structure(r, seed)
    obj = yaml.safe_load(seed) if fmt in ("instance", "train-config") else json.loads(seed)
    kind, path = mutate_structure(r, obj)
    return (_dump_yaml(obj) if fmt in ("instance", "train-config") else _dump_json(obj)), kind, path


def _checkpoint_structure(r: random.Random, seed: bytes) -> tuple[bytes, str, tuple]:
    import torch

    ck = torch.load(io.BytesIO(seed), weights_only=True)
    choice = r.choice(["config", "config", "weights", "top"])
    if choice == "config":
        kind, path = mutate_structure(r, ck["config"])
        path = ("config",) + path
    elif choice == "weights":
        names = sorted(ck["model"])
        name = r.choice(names)
        kind = r.choice(["nan-weights", "shape", "dtype", "not-a-tensor", "delete", "extra-weight", "empty"])
        t = ck["model"][name]
        if kind == "nan-weights":
            ck["model"][name] = torch.full_like(t, r.choice([math.nan, math.inf]))
        elif kind == "shape":
            ck["model"][name] = torch.zeros(*(s + r.choice([1, -1]) if s > 1 else s + 1 for s in t.shape))
        elif kind == "dtype":
            ck["model"][name] = t.to(r.choice([torch.int64, torch.bool, torch.float16, torch.uint8]))
        elif kind == "not-a-tensor":
            ck["model"][name] = copy.deepcopy(r.choice(WRONG))
        elif kind == "delete":
            del ck["model"][name]
        elif kind == "extra-weight":
            ck["model"]["extra.weight"] = torch.zeros(3)
        else:
            ck["model"] = {}
        path = ("model", name)
    else:
        kind = r.choice(["delete", "wrong-type", "ema"])
        key = r.choice(["model", "config", "ema"])
        if kind == "delete":
            ck.pop(key, None)
        elif kind == "ema":
            ck["ema"] = {k: v + 1 for k, v in list(ck["model"].items())[: r.randint(0, len(ck["model"]))]}
            key = "ema"
        else:
            ck[key] = copy.deepcopy(r.choice(WRONG + [torch.zeros(2)]))
        path = (key,)
        if r.random() < 0.2:  # not a dict at all
            ck = r.choice([[ck], torch.zeros(3), "text", None, 7])
            path = ()
    buf = io.BytesIO()
    torch.save(ck, buf)
    return buf.getvalue(), kind, path


def malicious_checkpoint(marker: Path, legacy: bool = False) -> bytes:
    """A checkpoint whose pickle would create ``marker`` (run a shell command) if unpickled."""
    import pickle

    import torch

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    data = {"config": {"model": {}}, "model": Payload()}
    if legacy:
        return pickle.dumps(data, protocol=2)
    buf = io.BytesIO()
    torch.save(data, buf)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------------
# generation
# ---------------------------------------------------------------------------------------------
def generate(n: int, seed: int, seeds: Seeds, heavy_share: float = 0.0, formats: tuple = FORMATS) -> list[Case]:
    """``n`` cases, formats in turn, each drawn from ``random.Random((seed, i))``. With
    ``heavy_share`` > 0 that share of the cases are heavy (deep nesting, alias bombs, FIFOs);
    ``heavy_share=0`` gives only in-process cases."""
    cases = []
    for i in range(n):
        r = random.Random(f"{seed}:{i}")
        fmt = formats[i % len(formats)]
        cases.append(_case(r, i, fmt, seeds, heavy=r.random() < heavy_share))
    return cases


def _case(r: random.Random, i: int, fmt: str, seeds: Seeds, heavy: bool) -> Case:
    seed = r.choice(seeds.of(fmt))
    render = fmt == "solution" and r.random() < 0.3
    if heavy:
        options = ["deep-nesting", "fifo"] + (["alias-bomb"] * 2 if fmt in ("instance", "train-config") else [])
        if fmt == "checkpoint":
            options = ["fifo", "malicious-pickle"]
        kind = r.choice(options)
        if kind == "fifo":
            return Case(i, fmt, kind, None, heavy=True, render=render)
        if kind == "malicious-pickle":
            return Case(i, fmt, kind, b"", heavy=True)
        if kind == "alias-bomb":
            return Case(i, fmt, kind, _alias_bomb(r, seed), heavy=True, render=render)
        yaml_like = fmt in ("instance", "train-config")
        return Case(i, fmt, kind, (_deep_yaml if yaml_like else _deep_json)(r, seed), heavy=True, render=render)
    roll = r.random()
    if roll < 0.04:
        return Case(i, fmt, r.choice(["directory", "missing", "oversize"]), None, render=render)
    if roll < 0.5:
        data, kind, path = _structure_case(r, fmt, seed)
        return Case(i, fmt, kind, data, path=path, render=render)
    if fmt == "checkpoint":
        names = BINARY_MUTATIONS
    elif fmt in ("instance", "train-config"):
        names = TEXT_MUTATIONS + ("yaml-tricks",) * 3
    else:
        names = TEXT_MUTATIONS + ("json-tricks",) * 2
    kind = r.choice(names)
    return Case(i, fmt, kind, BYTE_MUTATIONS[kind](r, seed), render=render)


# ---------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------
def materialise(case: Case, seeds: Seeds, where: Path) -> tuple[list[str], Path]:
    """Write the case's file(s) under ``where``; returns (argv, the fuzzed path)."""
    where.mkdir(parents=True, exist_ok=True)
    name = {"instance": "mission.yaml", "ctas": "config.json", "routes": "routes.json",
            "solution": "solution.json", "checkpoint": "policy.pt", "train-config": "train.yaml"}[case.fmt]
    target = where / name
    if case.kind == "directory":
        target.mkdir()
    elif case.kind == "fifo":
        os.mkfifo(target)
    elif case.kind == "oversize":
        with open(target, "wb") as f:
            f.truncate(65 * 2**20 if case.fmt != "checkpoint" else 8)
    elif case.kind == "malicious-pickle":
        target.write_bytes(malicious_checkpoint(where / "PWNED", legacy=case.id % 2 == 1))
    elif case.kind != "missing":
        target.write_bytes(case.data or b"")
    base = str(seeds.base)
    argv = {
        "instance": ["solve", str(target), "--method", "greedy"],
        "ctas": ["solve", str(target), "--method", "greedy"],
        "routes": ["evaluate", base, str(target)],
        "solution": (["render", base, str(target), "--out", str(where / "out.png")] if case.render
                     else ["bound", base, str(target)]),
        "checkpoint": ["solve", base, "--method", "rl", "--checkpoint", str(target)],
        "train-config": ["train", "--config", str(target), "--check", "--run-dir", str(where / "run")],
    }[case.fmt]
    return argv, target


def run_in_process(argv: list[str]) -> tuple[Any, str, str, float]:
    from hmrta.cli import main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc: Any = main(argv)
        except SystemExit as e:
            rc = e.code if isinstance(e.code, int) else 1
        except BaseException:  # noqa: BLE001 - anything escaping main is a failure of the case
            rc = "crash"
            err.write(traceback.format_exc())
    return rc, out.getvalue(), err.getvalue(), time.perf_counter() - t0


_CHILD = ("import resource, sys\n"
          "resource.setrlimit(resource.RLIMIT_AS, ({mem}, {mem}))\n"
          "from hmrta.cli import main\n"
          "sys.exit(main(sys.argv[1:]))\n")


def run_subprocess(argv: list[str], timeout: float = TIME_LIMIT, memory: int = MEMORY_LIMIT) -> tuple[Any, str, str, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "policy") + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", _CHILD.format(mem=memory), *argv], capture_output=True,
                           text=True, timeout=timeout, env=env, stdin=subprocess.DEVNULL)
        rc: Any = p.returncode if p.returncode >= 0 else f"signal {-p.returncode}"
        return rc, p.stdout, p.stderr, time.perf_counter() - t0
    except subprocess.TimeoutExpired as e:
        err = e.stderr.decode(errors="replace") if isinstance(e.stderr, bytes) else (e.stderr or "")
        return "timeout", "", err, time.perf_counter() - t0


def classify(case: Case, rc: Any, err: str, seconds: float, target: Path) -> Outcome:
    lines = err.splitlines()
    msg = lines[-1] if lines else ""
    if rc == "timeout":
        return Outcome(case, "hang", rc, seconds, msg, detail=err[-2000:])
    if rc in (0, 3):
        kind = "ok"
    elif rc == 2:
        one = len(lines) == 1 and lines[0].startswith("hmrta: error: ") and str(target) in lines[0]
        kind = "user-error" if one else "bad-message"
    else:
        kind = "internal"
    if kind in GOOD and seconds > TIME_LIMIT:
        kind = "slow"
    names = None
    if kind == "user-error" and case.path:
        names = names_a_field(msg, case.path)
    return Outcome(case, kind, rc, seconds, msg, names, detail="" if kind in GOOD else err[-3000:])


def names_a_field(msg: str, path: tuple) -> bool:
    """Does the message name some component of the mutated path (a key, or an index as [i])?"""
    for k in path:
        if isinstance(k, int):
            if f"[{k}]" in msg:
                return True
        elif str(k) and str(k) in msg:
            return True
    return False


def run_case(case: Case, seeds: Seeds, where: Path, subprocess_heavy: bool = True) -> Outcome:
    argv, target = materialise(case, seeds, where)
    if case.heavy and subprocess_heavy:
        rc, _, err, secs = run_subprocess(argv)
    else:
        rc, _, err, secs = run_in_process(argv)
    o = classify(case, rc, err, secs, target)
    if case.kind == "malicious-pickle" and (where / "PWNED").exists():
        o.outcome, o.detail = "internal", "the checkpoint's pickle ran a command"
    return o


def summary(outcomes: list[Outcome]) -> str:
    """Counts per outcome and per format (and per mutation for anything not ok / user-error)."""
    kinds = ["ok", "user-error", "bad-message", "internal", "hang", "slow"]
    by_fmt = Counter((o.case.fmt, o.outcome) for o in outcomes)
    lines = [f"{'format':<14}" + "".join(f"{k:>13}" for k in kinds) + f"{'total':>8}"]
    for fmt in FORMATS:
        n = sum(v for (f, _), v in by_fmt.items() if f == fmt)
        if n:
            lines.append(f"{fmt:<14}" + "".join(f"{by_fmt[(fmt, k)]:>13}" for k in kinds) + f"{n:>8}")
    tot = Counter(o.outcome for o in outcomes)
    lines.append(f"{'all':<14}" + "".join(f"{tot[k]:>13}" for k in kinds) + f"{len(outcomes):>8}")
    heavy = [o for o in outcomes if o.case.heavy]
    if heavy:
        hc = Counter(o.outcome for o in heavy)
        lines.append(f"{'(subprocess)':<14}" + "".join(f"{hc[k]:>13}" for k in kinds) + f"{len(heavy):>8}")
    named = [o.names_field for o in outcomes if o.names_field is not None]
    if named:
        lines.append(f"structure mutations refused with exit 2: {sum(named)}/{len(named)} messages name a mutated "
                     f"key or index")
    by_kind = Counter(o.case.kind for o in outcomes)
    lines.append("mutations: " + ", ".join(f"{k} {v}" for k, v in sorted(by_kind.items())))
    per_fmt = Counter()
    for o in outcomes:
        per_fmt["subprocess" if o.case.heavy else o.case.fmt] += o.seconds
    lines.append("seconds by format: " + ", ".join(f"{k} {v:.1f}" for k, v in per_fmt.most_common()))
    secs = sorted(o.seconds for o in outcomes)
    if secs:
        lines.append(f"seconds per case: median {secs[len(secs) // 2]:.3f}, max {secs[-1]:.3f} "
                     f"(limit {TIME_LIMIT:g}), total {sum(secs):.1f}")
    return "\n".join(lines)
