"""Torch threads of the command line: inference (solve, bench, demo) runs torch on one thread unless
``--threads`` says otherwise, greedy-only runs never import torch, and training waits passively.

Each case runs in a fresh interpreter, so that this process's torch settings are untouched and
the thread settings meet torch before anything else has used it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torch")

EXAMPLE = Path(__file__).parent / "data" / "example.yaml"
ROOT = Path(__file__).resolve().parents[2]


def _run(code: str, env: dict | None = None, timeout: float = 120.0) -> dict:
    """Run ``code`` (which binds ``out``, a JSON-able dict) in a fresh interpreter; return ``out``."""
    full = "import json, sys\n" + code + "\nprint('@@' + json.dumps(out))\n"
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    e.update(env or {})
    p = subprocess.run([sys.executable, "-c", full], capture_output=True, text=True, timeout=timeout, env=e,
                       cwd=ROOT, check=False)
    assert p.returncode == 0, p.stderr[-3000:]
    line = [x for x in p.stdout.splitlines() if x.startswith("@@")][-1]
    return json.loads(line[2:])


def _solve(args: list[str]) -> dict:
    return _run(f"""
from hmrta.cli import main
rc = main({args!r})
torch = sys.modules.get("torch")
out = {{"rc": rc, "torch": torch is not None,
        "threads": torch.get_num_threads() if torch else None,
        "interop": torch.get_num_interop_threads() if torch else None,
        "hooks": sum(type(f).__name__ == "TorchThreads" for f in sys.meta_path)}}
""")


def test_rl_solve_runs_torch_on_one_thread_by_default():
    out = _solve(["solve", str(EXAMPLE), "--method", "rl", "--no-progress"])
    assert out["rc"] == 0 and out["torch"]
    assert out["threads"] == 1 and out["interop"] == 1
    assert out["hooks"] == 0  # the import hook is gone after the command


def test_threads_option_sets_the_count():
    out = _solve(["solve", str(EXAMPLE), "--method", "rl", "--threads", "2", "--no-progress"])
    assert out["rc"] == 0 and out["threads"] == 2 and out["interop"] == 2


def test_demo_with_rl_runs_on_one_thread():
    out = _solve(["demo", "--method", "rl-sample", "--samples", "2", "--no-progress"])
    assert out["rc"] == 0 and out["threads"] == 1


def test_greedy_solve_never_imports_torch():
    out = _solve(["solve", str(EXAMPLE), "--method", "greedy", "--no-progress"])
    assert out["rc"] == 0
    assert out["torch"] is False and out["hooks"] == 0


def test_threads_already_imported_torch_is_set_at_once():
    out = _run(f"""
import torch
torch.set_num_threads(2)
from hmrta.cli import main
rc = main(["solve", {str(EXAMPLE)!r}, "--method", "greedy", "--no-progress"])
out = {{"rc": rc, "threads": torch.get_num_threads()}}
""")
    assert out == {"rc": 0, "threads": 1}


def test_bench_provenance_records_the_effective_threads(tmp_path):
    for n in (1, 2):
        out = _run(f"""
from hmrta.cli import main
rc = main(["bench", "--scenario", "MA-AT", "--agents", "4", "--species", "2", "--tasks", "4", "--skills", "3",
           "--count", "1", "--methods", "greedy,rl", "--threads", "{n}", "--no-progress",
           "--out", {str(tmp_path / str(n))!r}])
out = {{"rc": rc, "threads": sys.modules["torch"].get_num_threads()}}
""")
        assert out == {"rc": 0, "threads": n}
        prov = json.loads((tmp_path / str(n) / "results.json").read_text())["provenance"]
        assert prov["torch_threads"] == n


def test_bad_threads_is_a_user_error(capsys):
    from hmrta.cli import main

    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--threads", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["hmrta: error: --threads: expected a number of threads in [1, 1024], got 0"]
    assert main(["solve", str(EXAMPLE), "--method", "greedy", "--threads", "99999"]) == 2  # (no upper bound before)
    assert capsys.readouterr().err.strip().endswith("expected a number of threads in [1, 1024], got 99999")
    assert main(["train", "--check", "--threads", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--threads: expected a number of threads in [1, 1024]" in err[0]


@pytest.mark.parametrize("preset", [None, "ACTIVE"])
def test_train_sets_a_passive_wait_policy_before_torch_loads(preset):
    env = {} if preset is None else {"OMP_WAIT_POLICY": preset}
    out = _run("""
from hmrta.cli import main
import os
seen = {}
class Watch:  # the environment at the moment torch is first imported
    def find_spec(self, name, path=None, target=None):
        if name == "torch" and "policy" not in seen:
            seen["policy"] = os.environ.get("OMP_WAIT_POLICY")
        return None
sys.meta_path.insert(0, Watch())
rc = main(["train", "--config", "policy/configs/default.yaml", "--check"])
out = {"rc": rc, "at_import": seen.get("policy")}
""", env=env)
    assert out == {"rc": 0, "at_import": preset or "PASSIVE"}


def test_help_explains_the_threads():
    from hmrta.cli import build_parser

    p = build_parser()
    sub = next(a for a in p._actions if a.dest == "cmd").choices
    for cmd in ("solve", "bench", "demo"):
        text = " ".join(sub[cmd].format_help().split())
        assert "--threads N" in text and "collapses" in text and "(default: 1)" in text, cmd
    assert "OMP_WAIT_POLICY=PASSIVE" in " ".join(sub["train"].format_help().split())
