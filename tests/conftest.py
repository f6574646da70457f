"""Shared fixtures for the hmrta test suite (kept minimal)."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

DATA = Path(__file__).parent / "policy" / "data"

# A small valid `hmrta-instance/1` mapping: 3 skills, team traits [2, 1, 2].
VALID = {
    "format": "hmrta-instance/1",
    "name": "valid",
    "requirement_type": "additive",
    "velocity": 0.2,
    "skills": 3,
    "species": [
        {"traits": [1, 0, 1], "count": 2, "depot": [0.1, 0.8]},
        {"traits": [0, 1, 0], "count": 1, "depot": [0.5, 0.5]},
    ],
    "tasks": [
        {"location": [0.5, 0.9], "requirements": [0, 1, 1], "duration": 3.5},
        {"location": [0.2, 0.2], "requirements": [2, 1, 0], "duration": 0},
    ],
}


@pytest.fixture
def valid_dict():
    """A fresh deep copy of a valid instance mapping (mutate freely)."""
    return copy.deepcopy(VALID)


@pytest.fixture
def data_dir() -> Path:
    return DATA


@pytest.fixture
def write_yaml(tmp_path):
    """write_yaml(obj_or_text, name='inst.yaml') -> Path of a file under tmp_path."""

    def _write(obj, name: str = "inst.yaml") -> Path:
        p = tmp_path / name
        p.write_text(obj if isinstance(obj, str) else yaml.safe_dump(obj, sort_keys=False))
        return p

    return _write
