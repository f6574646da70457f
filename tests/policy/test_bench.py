"""bench: resumable per-instance cache that never serves results of another checkpoint or option."""
from __future__ import annotations

import json
import shutil

from hmrta.bench import Row, method_variant, run_bench
from hmrta.rl.inference import DEFAULT_CHECKPOINT

ROW = Row("MA-AT", 6, 2, 8, 3)


def _bench(out, opts):
    return run_bench([ROW], ["greedy"], 2, 5, out, opts, progress=False, log=lambda s: None)


def _makespans(summary):
    return summary["rows"][0]["results"]["greedy"]["makespan"][0]


def test_cache_is_reused_only_for_the_same_variant(tmp_path):
    first = _bench(tmp_path, {})
    lines = (tmp_path / "cache.jsonl").read_text().splitlines()
    assert len(lines) == 2
    # tamper with the cached makespans: a resumed run must serve them (it does not recompute) ...
    tampered = [json.loads(x) | {"makespan": 1000.0} for x in lines]
    (tmp_path / "cache.jsonl").write_text("".join(json.dumps(r) + "\n" for r in tampered))
    assert _makespans(_bench(tmp_path, {})) == 1000.0
    # ... but other solve options are another variant: recomputed, the true figures come back
    assert _makespans(_bench(tmp_path, {"time_limit": 3.0})) == _makespans(first)


def test_rl_variant_follows_the_checkpoint_content(tmp_path):
    a = tmp_path / "a.pt"
    shutil.copy(DEFAULT_CHECKPOINT, a)
    v1 = method_variant("rl", {"checkpoint": str(a)})
    assert v1 == method_variant("rl", {"checkpoint": str(a)})
    a.write_bytes(a.read_bytes() + b"\0")  # retrained / replaced weights
    assert method_variant("rl", {"checkpoint": str(a)}) != v1
    assert method_variant("greedy", {}) != method_variant("greedy", {"time_limit": 1.0})
