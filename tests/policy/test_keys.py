"""Mission keystore and robot authentication (hmrta.keys, `hmrta keys create`): issue 18, point 2.

Signed choices and statuses round-trip through JSON text; forged (another robot's name, a changed
field), replayed, unsigned and unknown-robot messages are rejected with their reason; key files are
private (0600) and written atomically; the CLI exits 0 / 2."""
from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from hmrta import keys as K
from hmrta.cli import main

ROBOTS = ["robot_0", "robot_1", "robot_2"]


class Clock:
    """A settable microsecond clock for deterministic counters."""

    def __init__(self, t: int = 1_000):
        self.t = t

    def __call__(self) -> int:
        return self.t


@pytest.fixture
def store(tmp_path) -> tuple[Path, dict[str, bytes]]:
    path = tmp_path / "ks"
    return path, K.create_keystore(path, ROBOTS)


def choice(robot: str = "robot_1", version: int = 7, node: int = 3) -> dict:
    return {"schema": "hmrta-choice/1", "robot": robot, "session": "abc123", "version": version, "node": node,
            "seq": 1, "compute_ms": 0.25}


def status(robots=("robot_0", "robot_2")) -> dict:
    return {"schema": "hmrta-status/1", "robots": list(robots), "session": "abc123", "seq": 4, "host": "h:1"}


def wire(payload: dict) -> dict:
    """What the receiver decodes: the payload sent as compact JSON text, as the codecs do."""
    return json.loads(json.dumps(payload, separators=(",", ":")))


# ---------------------------------------------------------------------------------------------
# signing and verification
# ---------------------------------------------------------------------------------------------
def test_round_trip_choice_and_status(store):
    _, keys = store
    agent = K.Signer({"robot_1": keys["robot_1"]}, Clock(500))
    host = K.Signer({"robot_0": keys["robot_0"], "robot_2": keys["robot_2"]}, Clock(500))
    board = K.Verifier(keys)
    c = agent.sign(choice())
    assert c["counter"] == 500 and set(c["mac"]) == {"robot_1"} and len(c["mac"]["robot_1"]) == 64
    assert {k: v for k, v in c.items() if k not in ("mac", "counter")} == choice()  # the payload is unchanged
    assert board.verify(wire(c)) is None
    s = host.sign(status())
    assert set(s["mac"]) == {"robot_0", "robot_2"}
    assert board.verify(wire(s)) is None
    # key order and whitespace on the wire do not matter: the MAC covers the canonical form
    reordered = json.loads(json.dumps(dict(reversed(list(c.items()))), indent=3))
    c2 = agent.sign(choice(version=8))
    assert board.verify(json.loads(json.dumps(dict(reversed(list(c2.items()))), indent=3))) is None
    assert board.verify(reordered).startswith("replayed")  # (c itself was already accepted)


def test_forged_choice_with_another_robots_name_is_rejected(store):
    """The attack of the issue: a choice in another robot's name (right session, board version,
    admissible node), signed with the sender's own key or an invented one."""
    _, keys = store
    board = K.Verifier(keys)
    me = K.Signer({"robot_0": keys["robot_0"]}, Clock())
    forged = me.sign(choice("robot_1"), robots=["robot_0"])  # robot_0's MAC on robot_1's choice
    assert board.verify(wire(forged)).startswith("unsigned: no MAC of 'robot_1'")
    forged["mac"] = {"robot_1": forged["mac"]["robot_0"]}  # robot_0's MAC relabelled as robot_1's
    reason = board.verify(wire(forged))
    assert reason.startswith(K.FORGED) and "robot_1" in reason and K.rejection_code(reason) == "forged"
    wrong_key = K.Signer({"robot_1": bytes(32)}, Clock()).sign(choice("robot_1"))  # a guessed key
    assert board.verify(wire(wrong_key)).startswith(K.FORGED)
    both = me.sign(choice("robot_1"), robots=["robot_0"])
    both["mac"]["robot_1"] = both["mac"]["robot_0"]
    assert board.verify(wire(both)).startswith(K.FORGED)  # a MAC of a robot the choice does not name
    # nothing forged moved robot_1's counter: its own next choice is accepted
    assert board.verify(wire(K.Signer({"robot_1": keys["robot_1"]}, Clock(1)).sign(choice()))) is None


@pytest.mark.parametrize("field,value", [("node", 4), ("version", 8), ("session", "other"), ("robot", "robot_2"),
                                         ("counter", 10**6), ("compute_ms", 0.26), ("extra", 1)])
def test_a_changed_field_breaks_the_mac(store, field, value):
    _, keys = store
    board = K.Verifier(keys)
    c = K.Signer(keys, Clock()).sign(choice())
    c[field] = value
    if field == "robot":  # now names robot_2, whose MAC is absent
        assert board.verify(wire(c)).startswith(K.UNSIGNED)
        c["mac"] = {"robot_2": c["mac"]["robot_1"]}
    reason = board.verify(wire(c))
    assert reason is not None and reason.startswith(K.FORGED), reason


def test_status_mac_must_cover_every_robot_it_names(store):
    _, keys = store
    board = K.Verifier(keys)
    s = K.Signer({"robot_0": keys["robot_0"]}, Clock()).sign(status(("robot_0",)))
    s["robots"] = ["robot_0", "robot_2"]  # claim a second robot without its key
    assert board.verify(wire(s)).startswith(K.UNSIGNED)
    s["mac"]["robot_2"] = s["mac"]["robot_0"]
    assert board.verify(wire(s)).startswith(K.FORGED)


def test_a_refusal_in_a_status_is_signed_by_the_robot_that_refuses(store):
    """A status's ``refused`` robots speak through it: each needs its own MAC, as its robots do (a
    refusal drops a robot from a mission that has not started)."""
    _, keys = store
    board = K.Verifier(keys)
    refusal = {**status(()), "refused": [{"robot": "robot_1", "why": "wrong method"}]}
    assert K.claimed_robots(refusal) == ["robot_1"]
    assert K.claimed_robots({**status(("robot_0", "robot_1")), "refused": refusal["refused"]}) == ["robot_0", "robot_1"]
    assert K.claimed_robots(status(())) is None and K.claimed_robots({**status(()), "refused": ["x"]}) is None
    s = K.Signer({"robot_1": keys["robot_1"]}, Clock()).sign(refusal)
    assert set(s["mac"]) == {"robot_1"} and board.verify(wire(s)) is None
    forged = K.Signer({"robot_0": keys["robot_0"]}, Clock(10**6)).sign(status(("robot_0",)))
    forged["refused"] = [{"robot": "robot_2", "why": "spoofed"}]  # a refusal for another robot, without its key
    assert board.verify(wire(forged)).startswith(K.UNSIGNED)


def test_replayed_messages_are_rejected(store):
    _, keys = store
    board = K.Verifier(keys)
    clock = Clock(100)
    agent = K.Signer({"robot_1": keys["robot_1"]}, clock)
    first, second = agent.sign(choice(version=7)), agent.sign(choice(version=9))
    assert (first["counter"], second["counter"]) == (100, 101)
    assert board.verify(wire(first)) is None
    assert board.verify(wire(first)) == "replayed (counter 100 <= last 100 of 'robot_1')"
    assert board.verify(wire(second)) is None
    assert board.verify(wire(first)) == "replayed (counter 100 <= last 101 of 'robot_1')"  # out of order: old
    assert K.rejection_code(board.verify(wire(second))) == "replayed"
    # choices and statuses are separate streams (different topics may overtake each other)
    s = K.Signer({"robot_1": keys["robot_1"]}, Clock(50)).sign(status(("robot_1",)))
    assert board.verify(wire(s)) is None
    # a restarted agent process continues above its predecessor (its counter starts at the clock)
    clock.t = 10_000
    restarted = K.Signer({"robot_1": keys["robot_1"]}, clock)
    assert board.verify(wire(restarted.sign(choice(version=12)))) is None
    # a counter never goes backwards within a process, even if the clock does
    clock.t = 5
    assert restarted.sign(choice())["counter"] == 10_001


def test_unsigned_unknown_and_malformed_are_rejected(store):
    _, keys = store
    board = K.Verifier(keys)
    assert board.verify(wire(choice())) == "unsigned: no mac field"
    good = K.Signer(keys, Clock()).sign(choice())
    assert board.verify({k: v for k, v in good.items() if k != "counter"}) == "unsigned: no counter field"
    stranger = K.Signer({"intruder": bytes(range(32))}, Clock()).sign(choice("intruder"))
    reason = board.verify(wire(stranger))
    assert reason == "unknown robot 'intruder': not in the mission keystore"
    assert K.rejection_code(reason) == "unknown_robot"
    bad = [({**good, "counter": True}, K.UNSIGNED), ({**good, "counter": -1}, K.UNSIGNED),
           ({**good, "counter": 2**63}, K.UNSIGNED), ({**good, "counter": "1"}, K.UNSIGNED),
           ({**good, "mac": "ab" * 32}, K.UNSIGNED), ({**good, "mac": {"robot_1": 5}}, K.FORGED),
           ({**good, "mac": {"robot_1": good["mac"]["robot_1"].upper()}}, K.FORGED),
           ({**good, "compute_ms": float("nan")}, K.FORGED),
           ({k: v for k, v in good.items() if k != "robot"}, K.UNSIGNED), ([1, 2], K.UNSIGNED)]
    for payload, prefix in bad:
        reason = board.verify(payload)
        assert reason is not None and reason.startswith(prefix), (payload, reason)
    assert board.verify(wire(good)) is None  # none of the bad ones moved the counter


def test_signer_refuses_robots_it_has_no_key_for(store):
    _, keys = store
    s = K.Signer({"robot_0": keys["robot_0"]})
    with pytest.raises(KeyError, match="robot_1"):
        s.sign(choice("robot_1"))
    with pytest.raises(ValueError, match="names no robot"):
        s.sign({"schema": "x"})


# ---------------------------------------------------------------------------------------------
# keystore files
# ---------------------------------------------------------------------------------------------
def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_keystore_files_are_private_and_load_back(store):
    path, keys = store
    assert sorted(keys) == ROBOTS and all(len(k) == 32 for k in keys.values()) and len(set(keys.values())) == 3
    assert _mode(path) == 0o700 and _mode(path / "robots") == 0o700
    assert _mode(path / "keys.json") == 0o600
    assert sorted(p.name for p in (path / "robots").iterdir()) == [f"{r}.key.json" for r in ROBOTS]
    for r in ROBOTS:
        f = K.robot_key_path(path, r)
        assert _mode(f) == 0o600
        assert K.load_key_file(f) == (r, keys[r])
    assert K.load_keystore(path) == keys == K.load_keystore(path / "keys.json")
    assert K.load_keystore(path, ["robot_2", "robot_0"]) == {"robot_2": keys["robot_2"], "robot_0": keys["robot_0"]}
    with pytest.raises(K.KeystoreError, match=r"keys.json: robots: no key for robot_7"):
        K.load_keystore(path, ["robot_0", "robot_7"])
    assert json.loads((path / "keys.json").read_text())["format"] == "hmrta-keystore/1"


def test_loading_refuses_readable_or_malformed_key_files(store, tmp_path):
    path, _ = store
    f = path / "keys.json"
    f.chmod(0o644)
    with pytest.raises(K.KeystoreError, match=r"keys.json: permissions 0644 are too open"):
        K.load_keystore(path)
    f.chmod(0o600)
    cases = {
        "garbage.json": b"\xff\xfe not json",
        "list.json": b"[1]",
        "format.json": b'{"format": "hmrta-keystore/9", "robots": {"robot_0": "00"}}',
        "hex.json": json.dumps({"format": "hmrta-keystore/1", "robots": {"robot_0": "zz" * 32}}).encode(),
        "short.json": json.dumps({"format": "hmrta-keystore/1", "robots": {"robot_0": "ab" * 16}}).encode(),
        "name.json": json.dumps({"format": "hmrta-keystore/1", "robots": {"../x": "ab" * 32}}).encode(),
        "empty.json": json.dumps({"format": "hmrta-keystore/1", "robots": {}}).encode(),
    }
    for name, data in cases.items():
        p = tmp_path / name
        p.write_bytes(data)
        p.chmod(0o600)
        with pytest.raises(K.KeystoreError) as e:
            K.load_keystore(p)
        assert str(e.value).startswith(str(p)) and "\n" not in str(e.value), name
    with pytest.raises(K.KeystoreError, match="no such file"):
        K.load_keystore(tmp_path / "nope")
    (tmp_path / "folder").mkdir()
    with pytest.raises(K.KeystoreError, match=r"folder: not a keystore \(no keys.json in it; create one with hmrta keys\)"):
        K.load_keystore(tmp_path / "folder")
    with pytest.raises(K.KeystoreError, match="format: expected 'hmrta-robot-key/1'"):
        K.load_key_file(path / "keys.json")


def test_create_is_atomic_and_never_overwrites_by_accident(store, monkeypatch):
    path, keys = store
    with pytest.raises(K.KeystoreError, match="holds a keystore already; pass --force to replace it"):
        K.create_keystore(path, ["robot_9"])
    assert K.load_keystore(path) == keys
    real = K._write_private
    calls = []

    def failing(p, data):
        calls.append(p)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        real(p, data)

    monkeypatch.setattr(K, "_write_private", failing)
    with pytest.raises(K.KeystoreError, match="cannot write the keystore .No space left on device."):
        K.create_keystore(path, ["robot_9", "robot_8"], force=True)
    assert K.load_keystore(path) == keys  # the old keystore is untouched
    assert [p.name for p in path.parent.iterdir()] == ["ks"]  # no half-written leftovers
    monkeypatch.setattr(K, "_write_private", real)
    new = K.create_keystore(path, ["robot_9"], force=True)
    assert K.load_keystore(path) == new and sorted(new) == ["robot_9"]
    assert sorted(p.name for p in path.parent.iterdir()) == ["ks"]
    # a failed swap puts the old keystore back and leaves no holder folder
    real_rename = K.os.rename

    def busy(src, dst):  # the new keystore cannot be moved into place
        if Path(src).name.startswith(".ks.tmp-"):
            raise OSError(16, "Device or resource busy")
        real_rename(src, dst)

    monkeypatch.setattr(K.os, "rename", busy)
    with pytest.raises(K.KeystoreError, match="cannot write the keystore .Device or resource busy."):
        K.create_keystore(path, ["robot_7"], force=True)
    monkeypatch.setattr(K.os, "rename", real_rename)
    assert K.load_keystore(path) == new and sorted(p.name for p in path.parent.iterdir()) == ["ks"]
    with pytest.raises(K.KeystoreError, match="duplicate name"):
        K.create_keystore(path.parent / "dup", ["a", "a"])
    with pytest.raises(K.KeystoreError, match="robot name"):
        K.create_keystore(path.parent / "bad", ["robot/1"])
    (path.parent / "file").write_text("x")
    with pytest.raises(K.KeystoreError, match="not a folder"):
        K.create_keystore(path.parent / "file", ["a"])


def test_force_replaces_only_a_keystore(tmp_path, store):
    """--force replaces a keystore, never some other folder: one with other files, a keys.json of
    another format, or foreign files among the robot keys is refused and left as it was."""
    path, keys = store
    cases = {"photos": {"a.jpg": "jpg", "b.txt": "b"},
             "other-json": {"keys.json": '{"format": "something-else"}'},
             "extra": {"keys.json": (path / "keys.json").read_text(), "notes.md": "mine"},
             "robots-extra": {"keys.json": (path / "keys.json").read_text(), "robots/readme.txt": "x"}}
    for name, files in cases.items():
        d = tmp_path / name
        for rel, text in files.items():
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            (d / rel).write_text(text)
        with pytest.raises(K.KeystoreError, match="is not a keystore.*--force replaces only a keystore"):
            K.create_keystore(d, ["robot_0"], force=True)
        with pytest.raises(K.KeystoreError, match="is not a keystore.*give the new one a folder of its own") as e:
            K.create_keystore(d, ["robot_0"])  # without --force: not told that --force would do
        assert "--force" not in str(e.value)
        assert {str(p.relative_to(d)): p.read_text() for p in d.rglob("*") if p.is_file()} == files, name
    new = K.create_keystore(path, ["robot_5"], force=True)  # a keystore is replaced
    assert K.load_keystore(path) == new != keys


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def test_cli_keys_create(tmp_path, capsys):
    out = tmp_path / "ks"
    assert main(["keys", "create", "--robots", "robot_0, robot_1,scout", "--out", str(out)]) == 0
    assert sorted(K.load_keystore(out)) == ["robot_0", "robot_1", "scout"]
    assert "wrote keystore" in capsys.readouterr().out
    before = (out / "keys.json").read_bytes()
    assert main(["keys", "create", "--robots", "robot_0", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hmrta: error: keys create:") and "--force" in err and "\n" not in err
    assert (out / "keys.json").read_bytes() == before
    inst = Path(__file__).resolve().parents[2] / "policy" / "hmrta" / "data" / "example.yaml"
    from hmrta.formats import load_instance

    A = load_instance(inst).n_agents
    assert main(["keys", "create", "--instance", str(inst), "--out", str(out), "--force"]) == 0
    assert sorted(K.load_keystore(out)) == sorted(f"robot_{a}" for a in range(A))
    deep = tmp_path / "a" / "b" / "ks"  # its parent folders are made, as for every other --out
    assert main(["keys", "create", "--robots", "robot_0", "--out", str(deep)]) == 0
    assert sorted(K.load_keystore(deep)) == ["robot_0"]
    capsys.readouterr()
    for args in (["--robots", "robot_0,robot_0"], ["--robots", "9lives"], ["--robots", ","],
                 ["--instance", str(tmp_path / "missing.yaml")]):
        assert main(["keys", "create", *args, "--out", str(tmp_path / "other")]) == 2, args
        err = capsys.readouterr().err.strip()
        assert err.startswith("hmrta: error:") and "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "other").exists()
    for args in ([], ["--robots", "a", "--instance", str(inst)]):  # exactly one of --robots / --instance
        with pytest.raises(SystemExit) as e:
            main(["keys", "create", *args, "--out", str(tmp_path / "other")])
        assert e.value.code == 2
