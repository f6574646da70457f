"""A replica of the task board's state machine, kept by applying the events the board publishes.

The board publishes every version it reaches as a small header (``hmrta-board/2``) carrying the
events applied since the previous version (the records of its journal, in order) and a digest of
its state (:func:`hmrta.board_core.state_digest`); now and then, and when a replica asks, it also
publishes a *keyframe*: the same header with every robot's latest legs and the full state
snapshot. A :class:`Replica` starts from a keyframe and applies each version's events with the
board's own code (:class:`hmrta.board_core.BoardCore`). The state machine is deterministic, so the
replica's state equals the board's after every version; the digest checks it.

* **Gaps.** A version whose previous version is not the replica's (a message was lost) is kept,
  and the replica asks for a keyframe (:meth:`Replica.request`); the versions kept are applied on
  top of the keyframe once it comes.
* **Divergence.** An event that does not apply, or a state whose digest (or revision) differs
  from the board's, drops the replica's state; it asks for a keyframe.
* **Late joiners.** The keyframe a subscriber gets first may be old (``latched``: the last one
  the board published, before versions the subscriber never saw): the replica loads it but is not
  :attr:`~Replica.current` until a later version applies on top of it, or the board confirms that
  it is the latest (a replica at the board's version that asks gets the header again).
* **No keyframe at all.** A reader that knows the mission (instance, seed, rules) and holds the
  stream from version 1 can start from the board's version 0 (:meth:`Replica.genesis`): the
  initial state the board itself starts from. Version 1's digest checks it like any other.
* **Never a hang.** While it is not current, :meth:`Replica.request` returns a request (the
  replica's version and the reason) at once and then every ``retry`` seconds, so the caller asks
  again and logs why for as long as no keyframe comes.

Nothing here imports ROS: the agent node, ``sim_robot``, the launcher and the replay of recordings
map their messages onto it. Headers are read through attributes (:class:`Frame`, the codec's
``Board``, the board's ``View``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from .board_core import BOARD_FORMAT, BoardCore, BoardState, Header, state_digest
from .core import Rules
from .instance import Instance


@dataclass(frozen=True)
class Frame(Header):
    """The header of one board version (hmrta-board/2), as a replica reads it."""
    until: float | None = None  # keyframes: the mission time the board's state may reach

    @classmethod
    def from_header(cls, d: dict[str, Any]) -> "Frame":
        """From a decoded header (KeyError / TypeError / ValueError when a field is missing or
        mistyped; the ROS codec validates headers fully)."""
        if d.get("format") != BOARD_FORMAT:
            raise ValueError(f"expected format {BOARD_FORMAT!r}, got {d.get('format')!r}")
        return cls(str(d["session"]), int(d["version"]), int(d["prev"]), int(d["rev"]), str(d["phase"]),
                   None if d["decider"] is None else int(d["decider"]), float(d["clock"]), float(d["horizon"]),
                   int(d["n_done"]), int(d["n_cancelled"]), int(d["n_tasks"]), tuple(int(a) for a in d["lost"]),
                   tuple(d["ev"]), str(d["digest"]), None if d.get("until") is None else float(d["until"]))


class Replica(BoardCore):
    """The board's state machine rebuilt from its messages (see the module docstring).

    Feed it every board message in the order received with :meth:`receive`; read
    :attr:`state` (a :class:`hmrta.board_core.BoardState`), :attr:`head` (the header of its version),
    :meth:`legs`; decide only while :attr:`current`. ``now`` gives wall seconds (the retry
    period of :meth:`request`)."""

    def __init__(self, *, retry: float = 1.0, max_ahead: int = 10000, now: Callable[[], float] = time.monotonic):
        self.retry, self.max_ahead, self.now = retry, max_ahead, now
        self.session: str | None = None
        self.counts: dict[str, int] = {}  # what receive() did, by outcome
        self._reset()

    def _reset(self) -> None:
        self.state: BoardState | None = None  # type: ignore[assignment]
        self.rev = 0
        self.lost: dict[int, str] = {}
        self.version = -1
        self.head: Any = None  # the header of the replica's version
        self.digest = ""
        self.live = False  # its version came from a message received live (not possibly old)
        self.ahead: dict[int, Any] = {}  # headers that do not apply yet, by the version they follow
        self.why = "no keyframe yet"  # why it is not current
        self.asked_at: float | None = None  # when it last asked for a keyframe (None: not asking)
        self.asking_since: float | None = None  # when it started asking (this time)

    @property
    def synced(self) -> bool:
        """It holds a state (from a keyframe, maybe not the latest)."""
        return self.state is not None

    @property
    def current(self) -> bool:
        """It holds the board's state at a version it received live, with no later version it
        could not apply: safe to decide on."""
        return self.state is not None and self.live and not self.ahead

    # ------------------------------------------------------------------------------------------
    def receive(self, f: Any, keyframe: Callable[[], tuple[Sequence[Any], dict[str, Any]]] | None = None,
                inst: Instance | None = None, latched: bool = False) -> str:
        """Take one board message: its header ``f`` and, for a keyframe, ``keyframe()`` giving
        (legs, state snapshot), called only when the replica loads it (``inst``: the mission's
        instance). ``latched``: this keyframe may be old (the first one a subscriber got).
        Returns what happened: ``applied`` (its events), ``loaded`` (the keyframe), ``confirmed``
        (the replica's own version again), ``old``, ``ahead`` (kept until a keyframe comes),
        ``diverged`` (the state was dropped) or ``bad`` (a keyframe that does not load)."""
        out = self._receive(f, keyframe, inst, latched)
        self.counts[out] = self.counts.get(out, 0) + 1
        if self.current:
            self.asked_at = self.asking_since = None
        return out

    def _receive(self, f: Any, keyframe, inst, latched: bool) -> str:
        if f.session != self.session:
            self.session = f.session
            self._reset()
        failed = None
        if self.state is not None:
            if f.version < self.version:
                return "old"
            if f.version == self.version:
                if f.digest == self.digest and f.rev == self.rev:
                    self.live = self.live or not latched
                    return "confirmed"
                failed = self._diverged(f"version {f.version}: the board's state digest is {f.digest}, this "
                                        f"replica's {self.digest}")
            elif f.prev == self.version:
                failed = self._apply(f)
                if failed == "applied":
                    self.live = self.live or not latched
                    self._drain()
                    return failed
            elif not self.ahead:
                self.why = f"missed version(s) {self.version + 1}..{f.prev} (got {f.version} after {self.version})"
        if keyframe is not None and inst is not None:
            try:
                legs, snap = keyframe()
                self._load(f, legs, snap, inst)
            except (KeyError, TypeError, ValueError, IndexError) as e:
                self.state, self.version, self.live = None, -1, False
                self.why = f"keyframe {f.version} does not load: {e}"
                return "bad"
            self.live = not latched
            self._drain()
            return "loaded"
        if failed is not None:
            return failed
        self.ahead[f.prev] = f
        while len(self.ahead) > self.max_ahead:
            del self.ahead[min(self.ahead)]
        return "ahead"

    def genesis(self, session: str, inst: Instance, seed: int, rules: Rules) -> None:
        """Start from the board's version 0 of ``session``: the state the board builds before its
        first version (``BoardState(inst, seed, rules)``, the mission's seed and rules). For a
        reader that has the stream from version 1 but no keyframe (a listener whose keyframe
        subscription matched after the board died); it is :attr:`current` once version 1 applies,
        and a version 1 whose digest differs drops it, as any divergence does."""
        self.session = session
        self._reset()
        self.state = BoardState(inst, seed=seed, rules=rules)
        self._scenario_losses()  # (robots a scenario loses at time 0, as the board counts them)
        self.version, self.rev, self.digest = 0, 0, state_digest(self.state)
        self.why = "at version 0 (the mission's initial state): waiting for version 1"

    def _load(self, f: Any, legs: Sequence[Any], snap: dict[str, Any], inst: Instance) -> None:
        st = BoardState.from_keyframe(inst, snap, legs, f.until if f.until is not None else 0.0)
        digest = state_digest(st)
        if digest != f.digest:
            raise ValueError(f"its state's digest is {digest}, its header says {f.digest}")
        self.state, self.rev, self.version, self.head, self.digest = st, int(f.rev), int(f.version), f, digest
        self.lost = {int(a): "" for a in f.lost}

    def _apply(self, f: Any) -> str:
        try:
            for ev in f.events:
                self.apply_event(ev)
        except (KeyError, TypeError, ValueError, IndexError) as e:  # EventRejected is a ValueError
            return self._diverged(f"version {f.version}: an event does not apply ({type(e).__name__}: {e})")
        if self.rev != f.rev:
            return self._diverged(f"version {f.version}: state revision {self.rev}, the board's is {f.rev}")
        digest = state_digest(self.state)
        if digest != f.digest:
            return self._diverged(f"version {f.version}: state digest {digest}, the board's is {f.digest}")
        self.version, self.head, self.digest = int(f.version), f, digest
        return "applied"

    def _diverged(self, why: str) -> str:
        self.state, self.version, self.live = None, -1, False
        self.why = why
        return "diverged"

    def _drain(self) -> None:
        """Apply the kept versions that follow on from the replica's version."""
        for prev in [p for p in self.ahead if p < self.version]:
            del self.ahead[prev]
        while self.state is not None and self.version in self.ahead:
            f = self.ahead.pop(self.version)
            if self._apply(f) != "applied":
                return
            self.live = True
        if self.ahead and self.state is not None:
            nxt = min(self.ahead)
            self.why = f"missed version(s) {self.version + 1}..{nxt} (have {self.version}, got later ones)"

    # ------------------------------------------------------------------------------------------
    def request(self) -> tuple[int, str] | None:
        """A keyframe request to send now, ``(the replica's version or -1, why)``, or None: one
        at once when the replica stops being current, then one every ``retry`` seconds until it
        is current again. Nothing before any board message was heard."""
        if self.session is None or self.current:
            self.asked_at = self.asking_since = None
            return None
        now = self.now()
        if self.asked_at is not None and now - self.asked_at < self.retry:
            return None
        self.asked_at = now
        if self.asking_since is None:
            self.asking_since = now
        why = self.why if self.state is None or self.ahead else \
            f"confirming version {self.version} (a keyframe that may be old)"
        return (self.version if self.state is not None else -1), why

    def legs(self, a: int, after: int | None = None) -> tuple[int, tuple] | None:
        """Robot a's legs (``(seq, legs)``: see :meth:`hmrta.board_core.BoardState.legs`), or None
        (lost, or not in the replica's state)."""
        st = self.state
        return None if st is None or a >= st.A else st.legs(a, after)
