"""``python -m hmrta.cli``: the ``hmrta`` command."""
import sys

from . import main

sys.exit(main())
