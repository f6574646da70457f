"""Mission keystore and message authentication of robots (HMAC-SHA256), middleware-independent.

Every robot of a mission holds its own secret key (32 random bytes); the task board holds all of
them. A robot's messages carry a MAC over their payload, so the board can tell a robot's own
messages from forged ones (another robot's name, a changed field) and from replays.

Keystore (``hmrta keys create --robots robot_0,robot_1 --out KEYSTORE``), a folder (mode 0700)::

    KEYSTORE/keys.json                  hmrta-keystore/1: every robot's key (the board's file)
    KEYSTORE/robots/<robot>.key.json    hmrta-robot-key/1: one robot's key (give each robot only its own)

Key files are mode 0600 and are refused when group or others may read them. Keys are hex text.

Signed payload: a JSON object (a choice, a status) gains two fields:

* ``counter``: integer, strictly increasing per signing process (microseconds of wall time at
  start, then +1 per message), so a restarted process continues above its predecessor;
* ``mac``: object ``{robot: hex HMAC-SHA256}``, one entry per robot the payload speaks for
  (``robot`` of a choice, ``robots`` of a status), each computed with that robot's key over the
  canonical JSON of the payload without ``mac`` (keys sorted, no whitespace, ASCII, no NaN):
  ``json.dumps(payload_without_mac, sort_keys=True, separators=(",", ":"), ensure_ascii=True)``.

The MAC thereby covers every other field: the schema, the board session and version a choice
answers, the chosen node, the counter. :class:`Verifier` checks the MACs and that each robot's
counter grows per message kind (``schema``: choices and statuses travel on different topics and
may overtake each other); it rejects with a reason string starting with ``unsigned``,
``unknown robot``, ``bad MAC (forged)`` or ``replayed``.
"""
from __future__ import annotations

import hmac
import json
import os
import re
import secrets
import shutil
import stat
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from hashlib import sha256
from pathlib import Path
from typing import Any

KEYSTORE_FORMAT = "hmrta-keystore/1"
ROBOT_KEY_FORMAT = "hmrta-robot-key/1"
KEYS_FILE = "keys.json"
ROBOTS_DIR = "robots"
KEY_BYTES = 32
MAX_COUNTER = 2**63 - 1
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,255}\Z")  # a ROS name token (robots are namespaces)
_HEX_MAC = re.compile(r"[0-9a-f]{64}\Z")

# rejection codes (first words of the reason strings :meth:`Verifier.verify` returns)
UNSIGNED, UNKNOWN_ROBOT, FORGED, REPLAYED = "unsigned", "unknown robot", "bad MAC (forged)", "replayed"


class KeystoreError(ValueError):
    """A keystore or key file is missing, malformed or unsafe (one line, names the file and field)."""


# ---------------------------------------------------------------------------------------------
# keystore files
# ---------------------------------------------------------------------------------------------
def check_robot_name(name: Any) -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise KeystoreError(f"robot name {name!r}: expected letters, digits and '_' (not starting with a digit)")
    return name


def robot_key_path(keystore: str | os.PathLike, robot: str) -> Path:
    return Path(keystore) / ROBOTS_DIR / f"{check_robot_name(robot)}.key.json"


def _write_private(path: Path, data: dict[str, Any]) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        os.fchmod(fh.fileno(), 0o600)
        json.dump(data, fh, indent=1)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())


def _not_keystore(folder: Path) -> str:
    """Why ``folder`` is not a keystore this module wrote ('' when it is one): what it holds
    beyond ``keys.json`` (format hmrta-keystore) and ``robots/*.key.json``."""
    extra = sorted(p.name for p in folder.iterdir() if p.name not in (KEYS_FILE, ROBOTS_DIR))
    if extra:
        return f"it holds {', '.join(extra[:3])}{', ...' if len(extra) > 3 else ''}"
    try:
        fmt = json.loads((folder / KEYS_FILE).read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        fmt = None
    if fmt != KEYSTORE_FORMAT:
        return f"no {KEYS_FILE} of format {KEYSTORE_FORMAT}"
    robots = folder / ROBOTS_DIR
    if robots.exists():
        if not robots.is_dir() or robots.is_symlink():
            return f"{ROBOTS_DIR} is not a folder"
        other = sorted(p.name for p in robots.iterdir() if not (p.name.endswith(".key.json") and p.is_file()))
        if other:
            return f"{ROBOTS_DIR}/ holds {', '.join(other[:3])}{', ...' if len(other) > 3 else ''}"
    return ""


def create_keystore(path: str | os.PathLike, robots: Iterable[str], *, force: bool = False) -> dict[str, bytes]:
    """Write a new keystore for ``robots`` at ``path`` (a folder) and return ``{robot: key}``.

    Atomic: the folder is assembled beside ``path`` and renamed into place, so ``path`` holds
    either the complete new keystore or what was there before. An existing non-empty ``path`` is
    replaced only with ``force``, and only when it is a keystore (``keys.json`` and ``robots/``,
    nothing else)."""
    names = [check_robot_name(r) for r in robots]
    if not names:
        raise KeystoreError("robots: expected at least one robot name")
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise KeystoreError(f"robots: duplicate name(s) {', '.join(dup)}")
    out = Path(path)
    if out.exists() or out.is_symlink():
        if not out.is_dir() or out.is_symlink():
            raise KeystoreError(f"{out}: exists and is not a folder")
        if any(out.iterdir()) and not force:
            foreign = _not_keystore(out)
            raise KeystoreError(f"{out}: is not a keystore ({foreign}) and not empty; give the new one a folder of "
                                f"its own" if foreign else
                                f"{out}: holds a keystore already; pass --force to replace it")
    target = Path(os.path.abspath(out))  # "." and ".." resolved: the folder is renamed by its own name
    cwd = Path.cwd()
    if target == cwd or target in cwd.parents:
        raise KeystoreError(f"{out}: is the current folder or holds it (it cannot be replaced); give the keystore "
                            f"a folder of its own")
    if out.is_dir() and any(out.iterdir()):
        foreign = _not_keystore(out)
        if foreign:
            raise KeystoreError(f"{out}: is not a keystore ({foreign}); --force replaces only a keystore, "
                                f"so give the new one a folder of its own")
    parent = target.parent
    if not parent.is_dir():
        try:  # as every other --out: the folders above it are made
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise KeystoreError(f"{out}: cannot make its parent folder {parent} ({e.strerror})") from None
    keys = {n: secrets.token_bytes(KEY_BYTES) for n in names}
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=parent))  # mode 0700
    except OSError as e:
        raise KeystoreError(f"{out}: cannot write in {parent} ({e.strerror})") from None
    old = None
    try:
        _write_private(tmp / KEYS_FILE, {"format": KEYSTORE_FORMAT, "robots": {n: k.hex() for n, k in keys.items()}})
        (tmp / ROBOTS_DIR).mkdir(mode=0o700)
        for n, k in keys.items():
            _write_private(tmp / ROBOTS_DIR / f"{n}.key.json", {"format": ROBOT_KEY_FORMAT, "robot": n, "key": k.hex()})
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=parent))
            os.rename(target, old / "keystore")
        os.rename(tmp, target)
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:  # put the old keystore back (if it was moved at all), then drop its holder
            if (old / "keystore").exists() and not target.exists():
                os.rename(old / "keystore", target)
            shutil.rmtree(old, ignore_errors=True)
        if isinstance(e, OSError):
            raise KeystoreError(f"{out}: cannot write the keystore ({e.strerror})") from None
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return keys


def _read_private(path: Path) -> dict[str, Any]:
    try:
        st = path.stat()
    except FileNotFoundError:
        raise KeystoreError(f"{path}: no such file") from None
    except OSError as e:
        raise KeystoreError(f"{path}: cannot read ({e.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise KeystoreError(f"{path}: not a regular file")
    if st.st_mode & 0o077:
        raise KeystoreError(f"{path}: permissions {stat.S_IMODE(st.st_mode):04o} are too open for a key file "
                            f"(expected 0600: chmod 600 {path})")
    if st.st_size > 16 * 1024 * 1024:
        raise KeystoreError(f"{path}: too large for a key file ({st.st_size} bytes)")
    try:
        d = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise KeystoreError(f"{path}: not a JSON key file ({type(e).__name__})") from None
    except OSError as e:
        raise KeystoreError(f"{path}: cannot read ({e.strerror})") from None
    if not isinstance(d, dict):
        raise KeystoreError(f"{path}: expected a JSON object")
    return d


def _key(v: Any, where: str) -> bytes:
    if not isinstance(v, str) or not re.fullmatch(f"[0-9a-fA-F]{{{2 * KEY_BYTES}}}", v):
        raise KeystoreError(f"{where}: expected {2 * KEY_BYTES} hex digits")
    return bytes.fromhex(v)


def load_keystore(path: str | os.PathLike, robots: Sequence[str] | None = None) -> dict[str, bytes]:
    """``{robot: key}`` from a keystore folder (or its ``keys.json``); with ``robots``, exactly
    those (each must have a key)."""
    p = Path(path)
    f = p / KEYS_FILE if p.is_dir() else p
    if p.is_dir() and not f.exists():
        raise KeystoreError(f"{p}: not a keystore (no {KEYS_FILE} in it; create one with hmrta keys)")
    d = _read_private(f)
    if d.get("format") != KEYSTORE_FORMAT:
        raise KeystoreError(f"{f}: format: expected {KEYSTORE_FORMAT!r}, got {d.get('format')!r}")
    entries = d.get("robots")
    if not isinstance(entries, dict) or not entries:
        raise KeystoreError(f"{f}: robots: expected an object {{robot: hex key}}")
    keys: dict[str, bytes] = {}
    for name, v in entries.items():
        try:
            check_robot_name(name)
        except KeystoreError as e:
            raise KeystoreError(f"{f}: robots: {e}") from None
        keys[name] = _key(v, f"{f}: robots.{name}")
    if robots is None:
        return keys
    missing = [r for r in robots if r not in keys]
    if missing:
        raise KeystoreError(f"{f}: robots: no key for {', '.join(missing[:5])}{'...' if len(missing) > 5 else ''}")
    return {r: keys[r] for r in robots}


def load_key_file(path: str | os.PathLike) -> tuple[str, bytes]:
    """(robot, key) from one robot's key file (``robots/<robot>.key.json``)."""
    f = Path(path)
    d = _read_private(f)
    if d.get("format") != ROBOT_KEY_FORMAT:
        raise KeystoreError(f"{f}: format: expected {ROBOT_KEY_FORMAT!r}, got {d.get('format')!r}")
    try:
        robot = check_robot_name(d.get("robot"))
    except KeystoreError as e:
        raise KeystoreError(f"{f}: robot: {e}") from None
    return robot, _key(d.get("key"), f"{f}: key")


# ---------------------------------------------------------------------------------------------
# signing and verification
# ---------------------------------------------------------------------------------------------
def canonical(payload: Mapping[str, Any]) -> bytes:
    """The bytes a MAC covers: the payload without ``mac`` as canonical JSON."""
    body = {k: v for k, v in payload.items() if k != "mac"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode("ascii")


def mac(key: bytes, payload: Mapping[str, Any]) -> str:
    return hmac.new(key, canonical(payload), sha256).hexdigest()


def claimed_robots(payload: Mapping[str, Any]) -> list[str] | None:
    """The robots a payload speaks for: ``robot`` (a choice) or ``robots`` and the robots of
    ``refused`` (a status: the robots it reports and those whose agents refuse the mission); None
    if none."""
    if isinstance(payload.get("robot"), str):
        return [payload["robot"]]
    rs, refused = payload.get("robots"), payload.get("refused", [])
    if not isinstance(rs, list) or not all(isinstance(r, str) for r in rs):
        return None
    if not isinstance(refused, list) or not all(isinstance(r, Mapping) and isinstance(r.get("robot"), str)
                                                  for r in refused):
        return None
    names = list(dict.fromkeys([*rs, *(r["robot"] for r in refused)]))
    return names or None


class Signer:
    """Signs the payloads of the robots whose keys it holds (one process: one signer).

    ``counter`` starts at the wall clock in microseconds and grows by one per message (never
    below the clock), so a restarted process continues above the counters its predecessor used
    (unless the wall clock was set back meanwhile)."""

    def __init__(self, keys: Mapping[str, bytes], clock_us: Callable[[], int] | None = None):
        if not keys:
            raise KeystoreError("signer: no keys")
        self.keys = dict(keys)
        self._clock_us = clock_us or (lambda: time.time_ns() // 1000)
        self.counter = 0

    def sign(self, payload: Mapping[str, Any], robots: Sequence[str] | None = None) -> dict[str, Any]:
        """A copy of ``payload`` with ``counter`` and ``mac`` (one MAC per robot it speaks for)."""
        names = list(robots) if robots is not None else claimed_robots(payload)
        if not names:
            raise ValueError("sign: the payload names no robot (expected 'robot' or 'robots')")
        missing = [r for r in names if r not in self.keys]
        if missing:
            raise KeyError(f"sign: no key for robot(s) {', '.join(missing)}")
        self.counter = max(self.counter + 1, int(self._clock_us()))
        body = {k: v for k, v in payload.items() if k != "mac"}
        body["counter"] = self.counter
        data = canonical(body)
        body["mac"] = {r: hmac.new(self.keys[r], data, sha256).hexdigest() for r in names}
        return body


class Verifier:
    """Checks signed payloads against the keystore; keeps the last counter per robot and kind.

    ``verify(payload)`` returns None when every robot the payload speaks for signed it with a
    counter above its last accepted one, else the reason. A message that fails never moves a
    counter. Memory: one counter per (known robot, schema)."""

    def __init__(self, keys: Mapping[str, bytes]):
        self.keys = dict(keys)
        self.last: dict[tuple[str, str], int] = {}

    def verify(self, payload: Any, robots: Sequence[str] | None = None) -> str | None:
        if not isinstance(payload, Mapping):
            return f"{UNSIGNED}: not a JSON object"
        names = list(robots) if robots is not None else claimed_robots(payload)
        if not names:
            return f"{UNSIGNED}: the payload names no robot"
        macs, counter = payload.get("mac"), payload.get("counter")
        if macs is None or counter is None:
            return f"{UNSIGNED}: no {'mac' if macs is None else 'counter'} field"
        if not isinstance(counter, int) or isinstance(counter, bool) or not 0 <= counter <= MAX_COUNTER:
            return f"{UNSIGNED}: counter: expected an integer in 0..2^63-1, got {str(counter)[:40]!r}"
        if not isinstance(macs, Mapping):
            return f"{UNSIGNED}: mac: expected an object {{robot: hex MAC}}"
        for r in names:
            if r not in self.keys:
                return f"{UNKNOWN_ROBOT} {r[:64]!r}: not in the mission keystore"
        missing = [r for r in names if r not in macs]
        if missing:
            return f"{UNSIGNED}: no MAC of {missing[0][:64]!r}"
        extra = [r for r in macs if r not in names]
        if extra:
            return f"{FORGED}: MAC of {str(extra[0])[:64]!r}, a robot the payload does not name"
        try:
            data = canonical(payload)
        except (TypeError, ValueError, RecursionError) as e:
            return f"{FORGED}: the payload has no canonical form ({type(e).__name__})"
        for r in names:
            m = macs[r]
            if not isinstance(m, str) or not _HEX_MAC.match(m):
                return f"{FORGED}: MAC of {r!r} is not 64 lowercase hex digits"
            if not hmac.compare_digest(hmac.new(self.keys[r], data, sha256).hexdigest(), m):
                return f"{FORGED}: MAC of {r!r} does not match its key"
        kind = str(payload.get("schema", payload.get("format", "")))
        for r in names:
            last = self.last.get((r, kind))
            if last is not None and counter <= last:
                return f"{REPLAYED} (counter {counter} <= last {last} of {r!r})"
        for r in names:
            self.last[(r, kind)] = counter
        return None


def rejection_code(reason: str) -> str:
    """Reason string -> short code for a rejection message: unsigned | unknown_robot | forged | replayed."""
    for prefix, code in ((UNSIGNED, "unsigned"), (UNKNOWN_ROBOT, "unknown_robot"), (FORGED, "forged"),
                         (REPLAYED, "replayed")):
        if reason.startswith(prefix):
            return code
    return "unauthenticated"
