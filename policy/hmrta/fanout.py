"""Work fanned out over processes or machines: one function mapped over work items, in this
process or as Ray tasks (the only module that talks to Ray).

- ``workers=1`` and no address: the items run here, one after the other (Ray is not needed).
- ``workers=N > 1``: a local Ray with ``N`` CPUs is started (``ray.init(num_cpus=N)``) and shut
  down again when the :class:`Fanout` closes.
- ``address="HEAD:6379"``: the items run on an existing Ray cluster (``ray start --head`` on one
  machine, ``ray start --address HEAD:6379`` on the others; hmrta installed on every node).

Each Ray task takes one CPU and runs torch on ``threads`` threads (default one: many small
solves in parallel beat one solve on many threads). Results come back in the items' order;
``on_result(i, result)`` is called as each arrives (in completion order), so callers can write a
resumable cache as they go. Every wait has a timeout: no result for ``timeout`` seconds is an
error and the outstanding tasks are cancelled. An exception raised by the function in a worker is
raised again here as itself (a user error stays a user error).
"""
from __future__ import annotations

import logging
import os
import sys
from typing import Any, Callable, Iterable, Sequence

DEFAULT_TIMEOUT = 3600.0  # seconds without any result before a fanned-out map gives up
WHAT = "work fanned out on Ray (--jobs N > 1 / --ray-address)"


class FanoutTimeout(RuntimeError):
    """No result came back within the timeout (an internal error: a worker hung or died)."""


def _set_threads(n: int) -> None:
    torch = sys.modules.get("torch")
    if torch is not None and torch.get_num_threads() != n:
        torch.set_num_threads(n)


def _call(fn: Callable, item: Any, threads: int) -> Any:
    """Run ``fn(item)`` in a worker with torch on ``threads`` threads (set before the call when
    torch is loaded already, and again after it in case the call loaded torch: OMP_NUM_THREADS,
    set for the workers, covers the first call)."""
    _set_threads(threads)
    try:
        return fn(item)
    finally:
        _set_threads(threads)


# the HTTP/2 client connection preface and an empty SETTINGS frame: a gRPC server (Ray's GCS)
# answers with a frame of its own, its SETTINGS (frame type 4, the fourth byte of the header)
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def split_address(text: str) -> tuple[str, int]:
    """``(host, port)`` of a Ray head's ``HOST:PORT`` (an IPv6 host in brackets: ``[::1]:6379``);
    ValueError saying what was expected otherwise."""
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected HOST:PORT (the Ray head's GCS address, e.g. 10.0.0.2:6379), got {text!r}")
    return host, int(port)


def _reachable(address: str, timeout: float = 10.0) -> None:
    """A one-line user error, within about ``timeout`` seconds, when nothing listens at HOST:PORT
    or what listens there does not speak gRPC as Ray's GCS does (Ray itself would wait for the
    cluster without a limit: at the client port 10001's sibling, a dashboard, any other server)."""
    import socket

    from .errors import MethodError

    try:
        sock = socket.create_connection(split_address(address), timeout=timeout)
    except ValueError as e:
        raise MethodError(f"--ray-address: {e}") from None
    except OSError as e:
        raise MethodError(f"--ray-address {address}: no Ray cluster reachable within {timeout:g} s ({e})") from None
    if os.environ.get("RAY_USE_TLS", "").strip().lower() in ("1", "true", "yes"):
        sock.close()  # a TLS cluster: its GCS answers a TLS handshake, not a plain preface; Ray checks it
        return
    with sock:
        try:
            sock.sendall(_H2_PREFACE)
            head = b""
            while len(head) < 9:
                chunk = sock.recv(9 - len(head))
                if not chunk:
                    break
                head += chunk
        except OSError:
            head = b""
    if len(head) < 9 or head[3] != 4:
        raise MethodError(f"--ray-address {address}: something listens there, but not a Ray cluster's GCS (no gRPC "
                          f"answer within {timeout:g} s): give the head node's address as `ray start --head` "
                          f"printed it (HOST:6379 by default; not the client server's 10001 nor the dashboard's "
                          f"8265)")


def _join_error(address: str, e: BaseException):
    """A one-line user error for a Ray cluster that answers but does not let this process join."""
    from .errors import MethodError

    chain, c = [], e
    while c is not None and len(chain) < 5:
        chain.append(c)
        c = c.__cause__ or c.__context__
    if any("Authentication" in type(x).__name__ or "InvalidAuthToken" in str(x) for x in chain):
        return MethodError(f"--ray-address {address}: the cluster uses token authentication (`ray start --head` turns "
                           f"it on): run with RAY_AUTH_MODE=token and the cluster's token in ~/.ray/auth_token (copy it "
                           f"from the head node) or in RAY_AUTH_TOKEN")
    return MethodError(f"--ray-address {address}: cannot join the Ray cluster ({' '.join(str(e).split())[:300]})")


class Fanout:
    """Maps picklable functions over picklable items; see the module docstring. Use as a context
    manager (or call :meth:`close`): a Ray started here is shut down on exit. ``use_ray``: Ray
    (True) or this process (False) whatever the workers; None: Ray when ``workers > 1`` or an
    address is given."""

    def __init__(self, workers: int = 1, address: str | None = None, threads: int = 1,
                 timeout: float = DEFAULT_TIMEOUT, use_ray: bool | None = None):
        if workers < 1:
            raise ValueError(f"workers: expected a positive integer, got {workers}")
        if threads < 1:
            raise ValueError(f"threads: expected a positive integer, got {threads}")
        self.workers, self.address, self.threads, self.timeout = workers, address, threads, timeout
        self._ray = None
        self._started = False
        self._remote = None
        if use_ray or (use_ray is None and (workers > 1 or address)):
            from .deps import require

            self._ray = require("ray", WHAT)

    @property
    def distributed(self) -> bool:
        return self._ray is not None

    def _ensure_ray(self):
        ray = self._ray
        if self._remote is not None:
            return ray
        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": str(self.threads), "MKL_NUM_THREADS": str(self.threads)}}
            kw: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False, runtime_env=env,
                                       logging_level=logging.WARNING)
            if self.address:
                _reachable(self.address)
                try:
                    ray.init(address=self.address, **kw)
                except (ConnectionError, RuntimeError) as e:  # Ray's cause chained (e.g. AuthenticationError)
                    raise _join_error(self.address, e) from None
            else:
                ray.init(num_cpus=self.workers, **kw)
            self._started = True
        self._remote = ray.remote(num_cpus=1, max_retries=0)(_call)
        return ray

    def slots(self) -> int:
        """How many items run at once: the CPUs Ray has (1 in-process)."""
        if not self.distributed:
            return 1
        ray = self._ensure_ray()
        return max(1, int(ray.cluster_resources().get("CPU", self.workers)))

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any],
            on_result: Callable[[int, Any], None] | None = None,
            progress: bool | str = False) -> list:
        """``[fn(x) for x in items]``, fanned out; ``on_result(i, r)`` as each result arrives;
        ``progress``: a progress bar on stderr (a string: its label)."""
        items = list(items)
        bar = None
        if progress and items:
            from tqdm import tqdm

            bar = tqdm(total=len(items), desc=progress if isinstance(progress, str) else "fanout",
                       unit="item", file=sys.stderr)
        try:
            if not self.distributed:
                out = []
                for i, x in enumerate(items):
                    r = _call(fn, x, self.threads)
                    out.append(r)
                    if on_result:
                        on_result(i, r)
                    if bar:
                        bar.update(1)
                return out
            return self._ray_map(fn, items, on_result, bar)
        finally:
            if bar:
                bar.close()

    def _ray_map(self, fn, items: Sequence, on_result, bar) -> list:
        ray = self._ensure_ray()
        window = 2 * self.slots()  # tasks in flight: every CPU busy, the rest queued here
        fn_ref = ray.put(fn)
        results: list = [None] * len(items)
        pending: dict = {}
        nxt = 0
        try:
            while nxt < len(items) or pending:
                while nxt < len(items) and len(pending) < window:
                    pending[self._remote.remote(fn_ref, items[nxt], self.threads)] = nxt
                    nxt += 1
                done, _ = ray.wait(list(pending), num_returns=1, timeout=self.timeout)
                if not done:
                    raise FanoutTimeout(f"no result from the Ray workers in {self.timeout:g} s "
                                        f"({len(pending)} tasks outstanding)")
                for ref in done:
                    i = pending.pop(ref)
                    try:
                        r = ray.get(ref, timeout=self.timeout)
                    except ray.exceptions.RayTaskError as e:
                        cause = getattr(e, "cause", None)
                        if isinstance(cause, BaseException):
                            raise cause from None
                        raise
                    results[i] = r
                    if on_result:
                        on_result(i, r)
                    if bar:
                        bar.update(1)
        finally:
            for ref in pending:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # already finished or gone
                    pass
        return results

    def close(self) -> None:
        if self._started and self._ray is not None and self._ray.is_initialized():
            self._ray.shutdown()
        self._started = False
        self._remote = None

    def __enter__(self) -> "Fanout":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def fanout_map(fn: Callable[[Any], Any], items: Iterable[Any], workers: int = 1, address: str | None = None,
               threads: int = 1, timeout: float = DEFAULT_TIMEOUT,
               on_result: Callable[[int, Any], None] | None = None, progress: bool | str = False) -> list:
    """One-shot :meth:`Fanout.map` (a local Ray is started and shut down around it)."""
    with Fanout(workers, address, threads, timeout) as f:
        return f.map(fn, items, on_result=on_result, progress=progress)
