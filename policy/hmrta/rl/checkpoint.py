"""Checkpoint files, for training and inference alike: ``save / load / export / average``.

A checkpoint is a torch archive holding one dict of tensors and plain data:

- ``checkpoint_format``: the layout version (1). Files without the key are format 0, the layout
  written before the key existed (identical otherwise), and load unchanged.
- ``config``: the resolved training config (model, rules, every section); ``code_version``.
- ``model``: the network's weights; ``ema``: the moving average of the weights (``train.ema``),
  which is what validation scored and what inference uses when present.
- training checkpoints (``save``): ``optimizer``, the counters (``iteration``, ``pretrain_done``,
  ``distill_done``, ``episodes``, ``decisions``), ``best_val``, ``greedy_val`` and the random
  streams (``np_rng``, ``torch_gen``, ``torch_rng``, ``py_rng``), so a resumed run continues exactly.
- inference checkpoints (``export``): weights, config, counters and an optional ``summary``.
- ``lineage`` (``average``; a training run started from another run's checkpoint, ``--init``): how
  the file was made: its source files with their sha256 (and their own lineage).

A checkpoint is read with ``torch.load(..., weights_only=True)``: its pickle may build tensors,
dicts, lists and plain values only, never call a function, so a crafted file cannot run code.
Whatever is wrong with a file (missing, a folder or special file, not a torch archive, truncated,
a pickle that asks for anything beyond weights, weights of the wrong type, shape or value, a
format from a newer version) is a :class:`~hmrta.rl.checkpoint_info.CheckpointError` with one
line naming the file and the field. Every write is atomic (a temporary file, then a rename).
The torch-free reader of a checkpoint's config and rules is :mod:`hmrta.rl.checkpoint_info`.
"""
from __future__ import annotations

import math
import pickle
import re
import subprocess
import warnings
from pathlib import Path
from typing import Any

import torch

from ..reading import short
from .checkpoint_info import COUNTERS, CheckpointError, checkpoint_path, cut_short, existing, sha256, torch_file

FORMAT_VERSION = 1
# the training counters a checkpoint holds (each an integer >= 0: :func:`counter`)


def _torch_reason(e: Exception) -> str:
    """What torch's error on reading a file says, in one line and in the file's terms (its C++
    reader's messages name internal records and ask for bug reports; its weights-only unpickler
    wraps the reason in advice about weights_only)."""
    text = re.sub(r"\s*\(Could this error message be improved\?.*?\)", "", str(e), flags=re.S)
    if isinstance(e, pickle.UnpicklingError):
        inner = re.search(r"WeightsUnpickler error:\s*(.*?)(?:\n\n|$)", text, re.S)
        text = " ".join((inner.group(1) if inner else text).split())[:200] or "a weights-only read failed"
    if (isinstance(e, (UnicodeDecodeError, KeyError)) or "invalid load key" in text
            or text.startswith("Unsupported operand")):
        return "not a torch checkpoint file"  # bytes that are no pickle at all (torch's legacy reader on them)
    if isinstance(e, EOFError):
        return "empty, or cut short"
    if "hasRecord" in text or "PytorchStreamReader" in text or "inline_container" in text:
        return "a zip archive without a torch checkpoint's records, or a damaged one"
    first = (text.strip().splitlines() or [""])[0][:200]
    return f"{type(e).__name__}: {first}"


def load(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The checkpoint's top-level dict, unpickled weights-only (no code runs), of a format this
    version reads (``checkpoint_format`` 0 or 1). A bare shipped name (``broad``) is read too."""
    p = existing(checkpoint_path(path))
    try:
        with warnings.catch_warnings():  # e.g. about the pickle protocol: the outcome is what counts
            warnings.simplefilter("ignore")
            ck = torch.load(p, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        text = str(e)
        g = re.search(r"GLOBAL ([\w.]+)", text)
        if g:  # a pickle that would call or build something beyond weights: never executed
            raise CheckpointError(f"{p}: refused: its pickle asks for {g.group(1)} (a checkpoint may hold only "
                                  f"tensors and plain data)") from None
        raise CheckpointError(f"{p}: not a readable hmrta checkpoint ({_torch_reason(e)})") from None
    except Exception as e:  # noqa: BLE001 - corrupt, truncated, not a torch file, ...
        why = cut_short(p) or (_torch_reason(e) if torch_file(p) else "not a torch checkpoint file")
        raise CheckpointError(f"{p}: not a readable hmrta checkpoint ({why})") from None
    if not isinstance(ck, dict):
        raise CheckpointError(f"{p}: not an hmrta checkpoint (expected a dict, got {type(ck).__name__})")
    format_version(ck, p)
    return ck


load_checkpoint = load


def weights(ck: dict, key: str, path: str | Path, required: bool = True) -> dict[str, torch.Tensor] | None:
    """``ck[key]`` as a state dict: names to tensors, floating values all finite."""
    if key not in ck or ck[key] is None:
        if required:
            raise CheckpointError(f"{path}: not an hmrta checkpoint (missing key {key!r})")
        return None
    sd = ck[key]
    if not isinstance(sd, dict) or not sd:
        raise CheckpointError(f"{path}: {key}: expected a mapping of weight names to tensors, got {short(sd)}")
    for name, t in sd.items():
        if not isinstance(name, str) or not isinstance(t, torch.Tensor):
            raise CheckpointError(f"{path}: {key}[{short(name)}]: expected a tensor, got {short(t)}")
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"{path}: {key}[{name!r}]: non-finite weights (NaN or infinity)")
    return sd


def check_shapes(model: torch.nn.Module, sd: dict[str, torch.Tensor], path: str | Path, key: str = "model",
                 optional: frozenset[str] = frozenset()) -> None:
    """Every weight of ``sd`` present in ``model`` with the same shape, and every parameter of the
    model in ``sd`` (except ``optional`` ones): checked before anything is copied."""
    want = model.state_dict()
    for name, t in sd.items():
        if name not in want:
            raise CheckpointError(f"{path}: {key}[{name!r}]: weights do not match the network (unexpected weight)")
        if tuple(t.shape) != tuple(want[name].shape):
            raise CheckpointError(f"{path}: {key}[{name!r}]: weights do not match the network (shape "
                                  f"{list(t.shape)}, the network's is {list(want[name].shape)})")
    missing = [n for n in want if n not in sd and n not in optional]
    if missing:
        raise CheckpointError(f"{path}: {key}: weights do not match the network (missing {missing[0]!r})")


def widen_task_inputs(model: torch.nn.Module, sd: dict[str, torch.Tensor]) -> bool:
    """A checkpoint observed without the coalition-start column (scale ``mission``) loading into a
    network that takes it (``mission+coalition``): its task input weights get a zero column for it,
    so the network starts from the same function. Returns whether ``sd`` was widened (in place)."""
    name = "task_embed.weight"
    want, have = model.state_dict().get(name), sd.get(name)
    if want is None or have is None or have.dim() != 2 or tuple(want.shape) != (have.shape[0], have.shape[1] + 1):
        return False
    sd[name] = torch.cat([have, have.new_zeros(have.shape[0], 1)], 1)  # [d, F + 1]
    return True


def counter(ck: dict, key: str, path: str | Path, default: Any = 0) -> Any:
    """A non-negative integer counter of a training checkpoint."""
    v = ck.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise CheckpointError(f"{path}: {key}: expected an integer >= 0, got {short(v)}")
    return v


_ADAM_STATE = ("step", "exp_avg", "exp_avg_sq", "max_exp_avg_sq")


def check_optimizer(sd: Any, opt: torch.optim.Optimizer, path: str | Path) -> None:
    """A saved optimiser state that fits ``opt``: the same parameter groups and hyperparameters
    (of the same types, finite), and per-parameter state tensors of the parameters' shapes."""
    where = f"{path}: optimizer"
    tmpl = opt.state_dict()
    if not isinstance(sd, dict) or set(sd) != {"state", "param_groups"}:
        raise CheckpointError(f"{where}: expected a mapping with keys 'state' and 'param_groups', got {short(sd)}")
    groups = sd["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(tmpl["param_groups"]):
        raise CheckpointError(f"{where}.param_groups: expected {len(tmpl['param_groups'])} group(s), got {short(groups)}")
    for i, (g, t) in enumerate(zip(groups, tmpl["param_groups"])):
        if not isinstance(g, dict) or set(g) != set(t):
            raise CheckpointError(f"{where}.param_groups[{i}]: expected keys {sorted(t)}, got {short(g)}")
        if g["params"] != t["params"]:
            raise CheckpointError(f"{where}.param_groups[{i}].params: do not match the network's parameters")
        for k, v in t.items():
            if k != "params" and not _same_kind(g[k], v):
                raise CheckpointError(f"{where}.param_groups[{i}].{k}: expected a value like {short(v)}, "
                                      f"got {short(g[k])}")
        betas = g.get("betas", (0.0, 0.0))
        if not all(0 <= b < 1 for b in betas) or g.get("eps", 1.0) <= 0 or g.get("weight_decay", 0) < 0:
            raise CheckpointError(f"{where}.param_groups[{i}]: expected betas in [0, 1), eps > 0 and "
                                  f"weight_decay >= 0, got {short({k: g.get(k) for k in ('betas', 'eps', 'weight_decay')})}")
    shapes = [tuple(p.shape) for grp in opt.param_groups for p in grp["params"]]
    amsgrad = {pid: bool(g.get("amsgrad")) for g in groups for pid in g["params"]}
    state = sd["state"]
    if not isinstance(state, dict):
        raise CheckpointError(f"{where}.state: expected a mapping, got {short(state)}")
    for pid, st in state.items():
        if isinstance(pid, bool) or not isinstance(pid, int) or not 0 <= pid < len(shapes):
            raise CheckpointError(f"{where}.state[{short(pid)}]: not a parameter of the network")
        keys = list(_ADAM_STATE if amsgrad.get(pid) else _ADAM_STATE[:3])
        if not isinstance(st, dict) or set(st) != set(keys):
            raise CheckpointError(f"{where}.state[{pid}]: expected a mapping with keys {keys}, got {short(st)}")
        for k, v in st.items():
            want = () if k == "step" else shapes[pid]
            if not isinstance(v, torch.Tensor) or tuple(v.shape) != want or not v.is_floating_point():
                raise CheckpointError(f"{where}.state[{pid}].{k}: expected a float tensor of shape {list(want)}, "
                                      f"got {short(v)}")
            if not bool(torch.isfinite(v).all()) or (k != "exp_avg" and bool((v < 0).any())):
                raise CheckpointError(f"{where}.state[{pid}].{k}: expected finite values" +
                                      ("" if k == "exp_avg" else " >= 0"))


def _same_kind(v: Any, like: Any) -> bool:
    if isinstance(like, bool) or like is None:
        return type(v) is type(like)
    if isinstance(like, (int, float)):
        return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
    if isinstance(like, (tuple, list)):
        return (isinstance(v, (tuple, list)) and len(v) == len(like)
                and all(_same_kind(a, b) for a, b in zip(v, like)))
    return type(v) is type(like)


def format_version(ck: dict, path: str | Path) -> int:
    """The layout version of a loaded checkpoint (0: written before versions were stored)."""
    v = ck.get("checkpoint_format", 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise CheckpointError(f"{path}: checkpoint_format: expected an integer >= 0, got {short(v)}")
    if v > FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint_format: {v} is newer than this hmrta reads (at most "
                              f"{FORMAT_VERSION}); upgrade hmrta")
    return v


def code_version() -> str:
    """The git revision of the code (``-dirty`` with local changes), stored in every checkpoint."""
    try:
        root = Path(__file__).resolve().parents[3]
        out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "policy/hmrta"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return (out.stdout.strip() or "unknown") + ("-dirty" if dirty else "")
    except Exception:
        return "unknown"


def save(path: str | Path, data: dict) -> None:
    """Write a checkpoint atomically, stamped with the current ``checkpoint_format``. Non-finite
    weights (``model``, ``ema``) are refused (RuntimeError): a run never keeps poisoned weights."""
    path = Path(path)
    for key in ("model", "ema"):
        sd = data.get(key) or {}
        if not all(torch.isfinite(v).all() for v in sd.values() if v.is_floating_point()):
            raise RuntimeError(f"refusing to save non-finite weights to {path}")
    tmp = path.with_name(path.name + ".tmp")
    try:
        torch.save({"checkpoint_format": FORMAT_VERSION, **data}, tmp)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()


def export(path: str | Path, config: dict, weights_: dict[str, torch.Tensor], meta: dict | None = None,
           summary: dict | None = None) -> None:
    """Write a small inference checkpoint: weights (on the CPU), resolved config, code version,
    ``meta`` (counters, validation scores) and an optional summary."""
    d = {"config": config, "code_version": code_version(), **(meta or {}),
         "model": {k: v.detach().cpu() for k, v in weights_.items()}}
    if summary:
        d["summary"] = summary
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    save(path, d)


def export_checkpoint(ck: dict, dst: str | Path, source: str | Path = "checkpoint") -> str:
    """Write the inference checkpoint of a training checkpoint's content ``ck`` (a run's file as
    loaded, or a trainer's state) to ``dst``: the weights inference uses (:func:`policy_weights`),
    its resolved config, counters, validation scores, lineage and summary as they are. Returns
    which weights ("ema" or "model")."""
    which, sd = policy_weights(ck, source)
    meta = {k: ck.get(k) for k in (*COUNTERS, "best_val", "greedy_val")}
    meta["lineage"] = ck.get("lineage") if isinstance(ck.get("lineage"), list) else []
    export(dst, ck["config"], sd, meta, ck.get("summary") if isinstance(ck.get("summary"), dict) else None)
    return which


def export_run_checkpoint(src: str | Path, dst: str | Path) -> str:
    """:func:`export_checkpoint` of a run's checkpoint file ``src`` (its best.pt or last.pt)."""
    ck = load(src)
    if not isinstance(ck.get("config"), dict):
        raise CheckpointError(f"{src}: config: expected a mapping (the training config)")
    return export_checkpoint(ck, dst, src)


def policy_weights(ck: dict, path: str | Path) -> tuple[str, dict[str, torch.Tensor]]:
    """(``"ema"`` or ``"model"``, state dict): the weights inference uses, the moving average
    when the checkpoint has one (validation scored those)."""
    which = "ema" if ck.get("ema") is not None else "model"
    return which, weights(ck, which, path)  # type: ignore[return-value]


def _network(ck: dict, path: str | Path) -> tuple[dict, dict]:
    """(resolved model config, resolved rules) of a checkpoint, validated."""
    from ..core import Rules, parse_rules
    from .model import ModelConfig

    config = ck.get("config")
    if not isinstance(config, dict):
        raise CheckpointError(f"{path}: config: expected a mapping (the training config), got {type(config).__name__}")
    try:
        model = ModelConfig.from_dict(config.get("model"), "config.model").to_dict()
        rules = config.get("rules", {})
        if not isinstance(rules, dict):
            raise ValueError(f"config.rules: expected a mapping, got {type(rules).__name__}")
        rules = parse_rules({**Rules().to_dict(), **rules}, "config.rules").to_dict()
    except ValueError as e:
        raise CheckpointError(f"{path}: {e}") from None
    return model, rules


# model settings chosen at inference, not by the weights: sources may differ in them (the written
# file takes the first source's unless ``average`` sets them)
INFERENCE_SETTINGS = frozenset({"window_tasks", "window_agents", "greedy_depot"})


def average(paths: list[str | Path], out: str | Path, window: tuple[int, int] | None = None,
            greedy_depot: str | None = None) -> dict:
    """Average the weights (each file's moving average when it has one) of checkpoints of the same
    network and rules, and write them to ``out`` (atomically) with the first file's resolved
    config and a lineage entry naming every source with its sha256. Checkpoints whose model
    config (but for its :data:`INFERENCE_SETTINGS`, taken from the first file) or rules differ
    are refused (CheckpointError naming the file and the key). ``window`` (tasks, robots) sets the
    observation window of the written config (``model.window_tasks``, ``model.window_agents``; it
    changes what the network is shown, not its weights) and is recorded in the lineage entry; so
    is ``greedy_depot`` (``model.greedy_depot``: how greedy decoding picks the depot). Returns
    the lineage entry."""
    from .model import PolicyNet, ModelConfig

    if not paths:
        raise CheckpointError("average: expected at least one checkpoint")
    if window is not None:
        try:
            ModelConfig.from_dict({"window_tasks": window[0], "window_agents": window[1]}, "window")
        except ValueError as e:
            raise CheckpointError(f"average: {e}") from None
    if greedy_depot is not None:
        try:
            ModelConfig.from_dict({"greedy_depot": greedy_depot}, "greedy_depot")
        except ValueError as e:
            raise CheckpointError(f"average: {e}") from None
    first = Path(paths[0])
    sums: dict[str, torch.Tensor] = {}
    ref: tuple[dict, dict] | None = None
    sources, config, dtypes = [], None, {}
    for p in map(checkpoint_path, paths):  # a bare shipped name (broad) is read too
        ck = load(p)
        model_cfg, rules = _network(ck, p)
        if ref is None:
            ref, config = (model_cfg, rules), ck["config"]
            with torch.device("meta"):
                net = PolicyNet(ModelConfig(**model_cfg))
        else:
            for what, mine, theirs in (("config.model", model_cfg, ref[0]), ("config.rules", rules, ref[1])):
                diff = [k for k in theirs if mine.get(k) != theirs.get(k) and k not in INFERENCE_SETTINGS]
                if diff:
                    k = diff[0]
                    raise CheckpointError(f"{p}: {what}.{k} is {short(mine.get(k))} but {short(theirs.get(k))} in "
                                          f"{first}: only checkpoints of the same network and rules can be averaged")
        which, sd = policy_weights(ck, p)
        check_shapes(net, sd, p, which)
        for k, v in sd.items():
            if k not in sums:
                sums[k], dtypes[k] = (v.double() if v.is_floating_point() else v.clone()), v.dtype
            elif v.is_floating_point():
                sums[k] += v.double()
            elif not torch.equal(sums[k], v):
                raise CheckpointError(f"{p}: {which}[{k!r}]: differs from {first}'s (an integer buffer is not averaged)")
        if set(sd) != set(sums):
            raise CheckpointError(f"{p}: {which}: holds other weights than {first}'s")
        sources.append({"path": str(p), "sha256": sha256(p), "weights": which,
                        "code_version": ck.get("code_version") if isinstance(ck.get("code_version"), str) else None,
                        "lineage": ck.get("lineage") if isinstance(ck.get("lineage"), list) else []})
    n = len(sources)
    avg = {k: (v / n).to(dtypes[k]) if dtypes[k].is_floating_point else v for k, v in sums.items()}
    entry = {"op": "average", "sources": sources}
    model = dict(ref[0])
    if window is not None:
        model.update(window_tasks=int(window[0]), window_agents=int(window[1]))
        entry["window"] = [int(window[0]), int(window[1])]
    if greedy_depot is not None:
        model["greedy_depot"] = greedy_depot
        entry["greedy_depot"] = greedy_depot
    if window is not None or greedy_depot is not None:
        config = {**config, "model": model}
    save(out, {"config": config, "code_version": code_version(), "model": avg, "lineage": [entry]})
    return entry
