"""torch's CPU threads for the learned policy's methods (``--threads``)."""
from __future__ import annotations

import sys

from .common import UserError

MAX_THREADS = 1024  # torch threads a process may ask for (99,999 exhausted the address space as rclpy loaded)


def check_threads(flag: str, n: int | None) -> None:
    """UserError naming ``flag`` unless ``n`` (None: not given) is a number of threads in [1, MAX_THREADS]."""
    if n is None:
        return
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_THREADS:
        raise UserError(f"{flag}: expected a number of threads in [1, {MAX_THREADS}], got {n}")


THREADS_HELP = ("torch CPU threads of the learned policy's methods (rl, rl-sample, rl-lookahead, portfolio). "
                "One suits inference: a decision's forward pass is too small to share between threads, and "
                "torch's own choice (a thread per core) collapses when other processes keep the cores busy "
                "(on 2 cores beside two busy processes, 10 to 100 times slower than one thread)")


def set_torch_threads(torch, n: int) -> None:
    """``n`` intra-op and (when still possible) inter-op threads for ``torch``."""
    torch.set_num_threads(n)
    try:
        torch.set_num_interop_threads(n)
    except RuntimeError:  # only before any inter-op parallel work, and once per process
        pass


class TorchThreads:
    """Sets torch's CPU threads as soon as torch is imported, without importing it (greedy-only
    runs never load torch): a meta-path finder that, the first time ``torch`` is imported, lets the
    other finders locate it and sets the threads right after the module has run. Where torch is
    already imported, the threads are set at once. ``remove()`` uninstalls the finder."""

    def __init__(self, n: int):
        self.n = n
        if "torch" not in sys.modules:
            sys.meta_path.insert(0, self)
        elif sys.modules["torch"] is not None:  # (None: an import of torch is blocked)
            set_torch_threads(sys.modules["torch"], n)

    def remove(self) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        import importlib.util

        self.remove()  # once, and the other finders locate torch
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run, n = spec.loader.exec_module, self.n

        def exec_module(module) -> None:
            run(module)
            set_torch_threads(module, n)

        spec.loader.exec_module = exec_module  # this spec's own loader object
        return spec


def _threads(args) -> TorchThreads | None:
    n = getattr(args, "threads", None)
    if n is None or args.cmd == "train":  # training sets its own (cmd_train)
        return None
    check_threads("--threads", n)
    return TorchThreads(n)
