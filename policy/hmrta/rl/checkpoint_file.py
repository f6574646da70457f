"""Loading checkpoint files safely: weights-only unpickling and a checked layout.

A checkpoint is read with ``torch.load(..., weights_only=True)``: its pickle may build tensors,
dicts, lists and plain values only, never call a function, so a crafted file cannot run code.
Whatever is wrong with a file (missing, a folder or special file, not a torch archive, truncated,
a pickle that asks for anything beyond weights, weights of the wrong type, shape or value) is a
:class:`~hmrta.rl.checkpoint_info.CheckpointError` with one line naming the file and the field.
"""
from __future__ import annotations

import math
import pickle
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from ..reading import short
from .checkpoint_info import CheckpointError


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The checkpoint's top-level dict, unpickled weights-only (no code runs)."""
    p = Path(path)
    if not p.exists():
        raise CheckpointError(f"{p}: no such checkpoint (train one with `hmrta train`)")
    if p.is_dir():
        raise CheckpointError(f"{p}: is a folder, expected a checkpoint file")
    if not p.is_file():  # a FIFO or device would block or never end
        raise CheckpointError(f"{p}: not a regular file")
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
        inner = re.search(r"WeightsUnpickler error: (.*?)(?:\n\n|$)", text, re.S)
        why = " ".join((inner.group(1) if inner else text).split())[:200] or "a weights-only read failed"
        raise CheckpointError(f"{p}: not a readable hmrta checkpoint (UnpicklingError: {why})") from None
    except Exception as e:  # noqa: BLE001 - corrupt, truncated, not a torch file, ...
        first = (str(e).strip().splitlines() or [""])[0][:200]
        raise CheckpointError(f"{p}: not a readable hmrta checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(ck, dict):
        raise CheckpointError(f"{p}: not an hmrta checkpoint (expected a dict, got {type(ck).__name__})")
    return ck


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
