"""``python -m hmrta.cli``: the ``hmrta`` command."""
import sys

from ..errors import forget_handled_interrupt
from . import main

status = main()
if status == 130:  # a Ctrl-C, handled: the status says so (not a death by SIGINT)
    forget_handled_interrupt()
sys.exit(status)
