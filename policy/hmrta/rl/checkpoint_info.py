"""What a checkpoint says about itself, read without torch: its resolved config and its rules.

A checkpoint is a torch zip archive whose ``data.pkl`` holds a dict (``model``, ``config``, ...).
This module reads that pickle with a whitelist unpickler that knows only the few globals torch
writes for plain state dicts (tensors become ``None``; their storages are never read), so the
task board and other torch-free processes learn the rules a policy was trained under without
building the network. Anything else in the pickle (a global outside the whitelist, as a file
crafted to run code would need) is refused with a :class:`CheckpointError`.
"""
from __future__ import annotations

import functools
import hashlib
import io
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

from ..errors import MethodError

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[1] / "checkpoints" / "default.pt"

MAX_FILE_BYTES = 512 * 2**20  # larger files are not taken for checkpoints
MAX_PICKLE_BYTES = 16 * 2**20  # the pickle holds the config and tensor references only (kilobytes)

# (module, name) pairs torch.save writes for a dict of tensors and plain data
_ALLOWED = {("collections", "OrderedDict"), ("torch._utils", "_rebuild_tensor_v2"),
            ("torch._utils", "_rebuild_parameter"), ("torch", "Size")}


class CheckpointError(MethodError):
    """Missing, unreadable or incompatible checkpoint (a user error)."""


SHIPPED_DIR = DEFAULT_CHECKPOINT.parent


def shipped_checkpoints() -> list[str]:
    """The names of the checkpoints shipped with the package (``default``, ``broad``, ...)."""
    return sorted(p.stem for p in SHIPPED_DIR.glob("*.pt"))


def _via(path: Path) -> str:
    """' (named by $HMRTA_CHECKPOINT)' when ``path`` is the checkpoint that variable names."""
    env = os.environ.get("HMRTA_CHECKPOINT")
    return " (named by $HMRTA_CHECKPOINT)" if env and checkpoint_path(env) == Path(path) else ""


def missing(path: Path) -> CheckpointError:
    """The error for a checkpoint file that is not there (names the shipped ones)."""
    return CheckpointError(f"{path}{_via(path)}: no such checkpoint (shipped: {', '.join(shipped_checkpoints())}; "
                           "or train one with `hmrta train`)")


def checkpoint_path(checkpoint: str | Path | None = None) -> Path:
    """The checkpoint file an rl method uses: the given one, $HMRTA_CHECKPOINT, or the shipped
    ``default.pt``. A bare name of a shipped checkpoint (``broad``: :func:`shipped_checkpoints`)
    is that checkpoint, whatever files are in the current folder (a file named so is ``./broad``),
    so that the portfolio's candidates and the nodes of a live mission read the same policy
    wherever they run."""
    given = checkpoint or os.environ.get("HMRTA_CHECKPOINT")
    if not given:
        return DEFAULT_CHECKPOINT
    path, name = Path(given), str(given)
    if path.suffix == "" and "/" not in name and (SHIPPED_DIR / f"{name}.pt").is_file():
        return SHIPPED_DIR / f"{name}.pt"
    if "/" not in str(path) and (SHIPPED_DIR / f"{path}.pt").is_file():
        return path.absolute()  # ./broad, which Path writes as broad: the file here, also when read again
    return path


def existing(path: Path) -> Path:
    """``path`` when it is a regular file; else the CheckpointError that says what it is: not
    there (:func:`missing`), a folder, or something else (a FIFO or device would block a read)."""
    if path.is_file():
        return path
    if not path.exists():
        raise missing(path)
    if path.is_dir():
        raise CheckpointError(f"{path}{_via(path)}: is a folder, expected a checkpoint file")
    raise CheckpointError(f"{path}{_via(path)}: not a regular file, expected a checkpoint file")


def torch_file(p: str | Path) -> bool:
    """Whether a file begins as a torch checkpoint does: a zip archive (what torch.save writes) or a
    pickle (its legacy form). Bytes that are neither get one reason, "not a torch checkpoint file",
    where torch's readers fail on them with whatever they tripped on (an IndexError on a text file)."""
    try:
        with open(p, "rb") as f:
            head = f.read(4)
    except OSError:
        return True  # (unreadable: the reader's own error says so)
    return not head or head == b"PK\x03\x04" or head[:1] == b"\x80"  # (empty: the readers say "empty")


def cut_short(p: str | Path) -> str | None:
    """Why a file that cannot be read as a checkpoint is not one, when it is a zip archive (as a
    torch checkpoint is) without the end of one: copied or downloaded in part. None otherwise."""
    try:
        with open(p, "rb") as f:
            zipped = f.read(4) == b"PK\x03\x04"
        cut = zipped and not zipfile.is_zipfile(p)
        return "a zip archive cut short: copied or downloaded in part?" if cut else None
    except OSError:
        return None


class _Mapping(dict):
    """What an OrderedDict of the checkpoint reads as: a dict that also takes the attributes torch
    pickles with it (a module's ``state_dict()`` carries ``_metadata``)."""


class _Unpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return _Mapping
        if (module, name) in _ALLOWED or (module == "torch" and name.endswith("Storage")):
            return _tensor_placeholder
        raise pickle.UnpicklingError(f"global {module}.{name} is not allowed in a checkpoint")

    def persistent_load(self, pid: Any) -> None:  # tensor storages: not read
        return None


def _tensor_placeholder(*_: Any, **__: Any) -> None:
    return None


@functools.lru_cache(maxsize=16)
def _read(path: str, mtime_ns: int) -> dict:
    if os.path.getsize(path) > MAX_FILE_BYTES:
        raise CheckpointError(f"{path}: larger than {MAX_FILE_BYTES // 2**20} MiB: not an hmrta checkpoint")
    try:
        with zipfile.ZipFile(path) as z:
            pkl = [i for i in z.infolist() if i.filename.endswith("/data.pkl") or i.filename == "data.pkl"]
            if len(pkl) != 1:
                raise CheckpointError(f"{path}: not an hmrta checkpoint (no single data.pkl in the archive)")
            if pkl[0].file_size > MAX_PICKLE_BYTES:  # checked before anything is decompressed
                raise CheckpointError(f"{path}: its data.pkl unpacks to {pkl[0].file_size} bytes (at most "
                                      f"{MAX_PICKLE_BYTES}): not an hmrta checkpoint")
            with z.open(pkl[0]) as fh:  # reads at most the declared size
                data = _Unpickler(io.BytesIO(fh.read(MAX_PICKLE_BYTES + 1))).load()
    except CheckpointError:
        raise
    except zipfile.BadZipFile:  # (a torch checkpoint is a zip archive)
        raise CheckpointError(f"{path}: not a readable hmrta checkpoint "
                              f"({cut_short(path) or 'not a torch checkpoint file'})") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
            IndexError, KeyError, RecursionError, MemoryError) as e:
        why = f"{type(e).__name__}: {e}" if torch_file(path) else "not a torch checkpoint file"
        raise CheckpointError(f"{path}: not a readable hmrta checkpoint ({why})") from None
    if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
        raise CheckpointError(f"{path}: not an hmrta checkpoint (expected a dict with a 'config' mapping)")
    return data


def read_config(checkpoint: str | Path | None = None) -> dict:
    """The resolved training config stored in a checkpoint (no torch needed)."""
    path = existing(checkpoint_path(checkpoint))
    return _read(str(path.resolve()), path.stat().st_mtime_ns)["config"]


def sha256(path: str | Path) -> str:
    """The hex sha256 of a file (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# the training counters a checkpoint carries (cloning, distillation and REINFORCE iterations, episodes,
# decisions)
COUNTERS = ("iteration", "pretrain_done", "distill_done", "episodes", "decisions")


def describe(checkpoint: str | Path | None = None) -> dict:
    """What a checkpoint says about itself, without torch: its path and sha256, checkpoint format
    (0 before formats were numbered), the code version that wrote it, its resolved config (model,
    rules, training), which weights it holds, its training counters and its lineage."""
    path = checkpoint_path(checkpoint)
    if not path.is_file():
        raise missing(path)
    data = _read(str(path.resolve()), path.stat().st_mtime_ns)
    out: dict[str, Any] = {"path": str(path), "sha256": sha256(path),
                           "format": data.get("checkpoint_format", 0),
                           "code_version": data.get("code_version"),
                           "weights": [k for k in ("model", "ema") if isinstance(data.get(k), dict)]}
    for k in (*COUNTERS, "best_val"):
        if isinstance(data.get(k), (int, float)) and not isinstance(data.get(k), bool):
            out[k] = data[k]
    out["config"] = data["config"]
    out["lineage"] = data["lineage"] if isinstance(data.get("lineage"), list) else []
    return out


def lineage_lines(lineage: list, depth: int = 0) -> list[str]:
    """A lineage as indented lines, newest step first: each step's operation, its settings and
    its sources (path, sha256 prefix, weights, code version), their own lineage below them.
    A ``teacher`` step is the checkpoint whose decisions were cloned (``pretrain.teacher:
    rl@CHECKPOINT``). Entries that are not what ``checkpoint average`` or training writes are
    shown as unreadable."""
    lines = []
    for e in lineage:
        if not isinstance(e, dict) or not isinstance(e.get("sources"), list):
            lines.append("  " * depth + "(unreadable lineage entry)")
            continue
        sets = [f"{k} {e[k]}" for k in ("window", "greedy_depot") if k in e]
        if e.get("op") == "teacher":
            head = "taught by"
        else:
            head = f"{e.get('op', '?')}" + (f" ({', '.join(sets)})" if sets else "") + " of"
        lines.append("  " * depth + head)
        for s in e["sources"]:
            if not isinstance(s, dict):
                lines.append("  " * (depth + 1) + "(unreadable source)")
                continue
            sha = s.get("sha256") if isinstance(s.get("sha256"), str) else "?"
            code = f", code {s['code_version']}" if isinstance(s.get("code_version"), str) else ""
            lines.append("  " * (depth + 1) + f"{s.get('path', '?')} (sha256 {sha[:12]}…, {s.get('weights', '?')}{code})")
            if isinstance(s.get("lineage"), list) and depth < 32:
                lines += lineage_lines(s["lineage"], depth + 2)
    return lines


def checkpoint_rules(checkpoint: str | Path | None = None):
    """The state-machine rules the checkpoint's policy was trained under and must run under."""
    from ..core import Rules, parse_rules

    path = checkpoint_path(checkpoint)
    rules = read_config(path).get("rules", {})
    if not isinstance(rules, dict):
        raise CheckpointError(f"{path}: config.rules: expected a mapping, got {type(rules).__name__}")
    try:  # configs name only the rules they set; the strict reader checks the rest (as load_policy does)
        return parse_rules({**Rules().to_dict(), **rules}, "config.rules")
    except ValueError as e:
        raise CheckpointError(f"{path}: {e}") from None
