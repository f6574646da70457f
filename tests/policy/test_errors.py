"""hmrta.errors: what an error came from, and the exit status of a handled Ctrl-C."""
from __future__ import annotations

import os
import subprocess
import sys

from hmrta.errors import caused_by_interrupt

# a module that meets a KeyboardInterrupt inside code run by PyRun_String (as rclpy's and Ray's
# extensions run some), handles it, and exits with 130; FORGET: whether it clears the note first
INTERRUPTED_MODULE = """
import ctypes, os, sys
run = ctypes.pythonapi.PyRun_String
run.restype = ctypes.py_object
run.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
try:
    run(b"raise KeyboardInterrupt", 257, {"__builtins__": __builtins__}, {})
except KeyboardInterrupt:
    pass
if os.environ["FORGET"] == "1":
    from hmrta.errors import forget_handled_interrupt
    forget_handled_interrupt()
sys.exit(130)
"""


def test_a_handled_interrupt_leaves_the_exit_status_of_a_python_m_process_alone(tmp_path):
    (tmp_path / "handled_interrupt.py").write_text(INTERRUPTED_MODULE)
    codes = {}
    for forget in ("0", "1"):
        env = dict(os.environ, FORGET=forget, PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
        codes[forget] = subprocess.run([sys.executable, "-m", "handled_interrupt"], env=env, timeout=60).returncode
    # without it CPython ends the process by SIGINT (what makes this test able to fail)
    assert codes == {"0": -2, "1": 130}


def test_caused_by_interrupt_follows_causes_and_contexts():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise ImportError("initialization failed") from e
    except ImportError as e:
        assert caused_by_interrupt(e)
    assert not caused_by_interrupt(ImportError("no module named x"))
    assert not caused_by_interrupt(None)
