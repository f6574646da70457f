"""Seeded scenario generators (SPEC §2).

Every instance is a pure function of ``(generator parameters, seed, index)``: instance ``i`` of a
set uses ``numpy.random.default_rng([seed, i])``, so sets are reproducible and any single instance
can be regenerated without the others.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .instance import DEFAULT_VELOCITY, MAX_AGENTS, MAX_SKILLS, MAX_TASKS, Instance, Species, Task

SCENARIOS = ("SA-BT", "SA-AT", "MA-AT", "MA-BT")

# Paper rows (agents, species, tasks, skills), SPEC §2.
PAPER_ROWS: dict[str, list[tuple[int, int, int, int]]] = {
    "SA-BT": [(9, 3, 20, 3), (25, 5, 20, 5), (25, 5, 50, 5), (50, 5, 50, 5)],
    "SA-AT": [(9, 3, 20, 3), (15, 5, 20, 5), (25, 5, 20, 5), (50, 5, 50, 5)],
    "MA-AT": [(9, 3, 20, 3), (15, 5, 20, 5), (25, 5, 20, 5), (25, 5, 50, 5), (50, 5, 50, 5)],
    "MA-AT-large": [(50, 5, 200, 5), (150, 10, 500, 5), (150, 5, 500, 5)],
}


MAX_DRAWS = 10_000  # redraws of (traits, requirements) before giving up (paper rows need <= 3)
MIN_TRAIT_ODDS = 1e-4  # below this chance of a whole draw of traits being valid, draw them directly


def draw_traits(rng: np.random.Generator, species: int, skills: int, values: int, distinct: bool) -> np.ndarray:
    """Species traits [species, skills] with entries in 0..values-1, no row all zero and, with
    ``distinct``, no two rows equal. Whole matrices are drawn until one is valid; where a draw is
    valid with a chance below MIN_TRAIT_ODDS (e.g. 25 species among the 31 non-zero vectors of 5
    skills: 3e-7, minutes of redraws), the rows are drawn directly from the non-zero vectors
    instead, which gives the same distribution (every valid matrix alike) from another random
    stream. Every mission whose draw was valid with a chance above that is drawn as before."""
    n = values ** skills  # vectors, the zero vector included
    odds = 1.0
    for i in range(species):  # the chance that a whole draw is valid
        odds *= ((n - 1 - i) if distinct else (n - 1)) / n
        if odds < MIN_TRAIT_ODDS:
            break
    if odds >= MIN_TRAIT_ODDS:
        while True:
            t = rng.integers(0, values, size=(species, skills))
            if t.sum(1).min() > 0 and (not distinct or len({tuple(r) for r in t}) == species):
                return t.astype(np.float64)
    codes = rng.choice(n - 1, size=species, replace=not distinct) + 1  # [species] non-zero vectors by number
    digits = values ** np.arange(skills)[::-1]  # [skills] place value of each skill
    return ((codes[:, None] // digits) % values).astype(np.float64)  # [species, skills]


def row_name(scenario: str, agents: int, species: int, tasks: int, skills: int) -> str:
    return f"{scenario}_{agents}-{species}-{tasks}-{skills}"


@dataclass(frozen=True)
class ScenarioGenerator:
    """One paper scenario row: trait kind (SA/MA) x requirement kind (AT/BT) x sizes."""

    scenario: str
    agents: int
    species: int
    tasks: int
    skills: int
    velocity: float = DEFAULT_VELOCITY
    max_duration: float = 5.0

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise ValueError(f"scenario: expected one of {', '.join(SCENARIOS)}, got {self.scenario!r}")
        if self.species < 1 or self.skills < 1 or self.tasks < 0:
            raise ValueError("species and skills must be >= 1 and tasks >= 0")
        if self.skills > MAX_SKILLS:  # what a mission file may hold
            raise ValueError(f"skills ({self.skills}): a mission has at most {MAX_SKILLS}")
        if self.agents < self.species:
            raise ValueError(f"agents ({self.agents}) must be at least species ({self.species}): one agent or more "
                             f"per species")
        if self.agents % self.species:
            raise ValueError(f"agents ({self.agents}) must be a multiple of species ({self.species})")
        if self.agents > MAX_AGENTS:  # what a mission file may hold: the set must read back
            raise ValueError(f"agents ({self.agents}): a mission holds at most {MAX_AGENTS}")
        if self.tasks > MAX_TASKS:
            raise ValueError(f"tasks ({self.tasks}): a mission holds at most {MAX_TASKS}")
        if self.multi_skill and self.species > 2**self.skills - 1:
            raise ValueError(f"species ({self.species}): MA needs distinct non-zero trait vectors, so at most "
                             f"{2**self.skills - 1} species with {self.skills} skills")
        if not self.multi_skill and self.species < self.skills:
            # one-hot species cover only `species` skills: tasks needing the others are never feasible
            raise ValueError(f"species ({self.species}): SA needs at least as many species as skills ({self.skills})")

    @property
    def multi_skill(self) -> bool:
        return self.scenario.startswith("MA")

    @property
    def additive(self) -> bool:
        return self.scenario.endswith("AT")

    @property
    def name(self) -> str:
        return row_name(self.scenario, self.agents, self.species, self.tasks, self.skills)

    # ------------------------------------------------------------------------------------------
    def _traits(self, rng: np.random.Generator) -> np.ndarray:  # [species, skills]
        if not self.multi_skill:
            return np.eye(self.skills)[np.arange(self.species) % self.skills]
        return draw_traits(rng, self.species, self.skills, 2, distinct=True)

    def _requirements(self, rng: np.random.Generator) -> np.ndarray:  # [tasks, skills]
        hi = 3 if self.additive else 2
        q = rng.integers(0, hi, size=(self.tasks, self.skills))
        zero = q.sum(1) == 0
        while zero.any():  # redraw all-zero rows
            q[zero] = rng.integers(0, hi, size=(int(zero.sum()), self.skills))
            zero = q.sum(1) == 0
        return q.astype(np.float64)

    def sample(self, rng: np.random.Generator, name: str | None = None) -> Instance:
        per = self.agents // self.species
        for _ in range(MAX_DRAWS):
            traits = self._traits(rng)
            req = self._requirements(rng)
            team = traits.sum(0) * per  # [skills]
            ok = (req <= team).all() if self.additive else ((req > 0) <= (team > 0)).all()
            if ok:
                break
        else:  # e.g. AT with one agent per species: requirements of 2 are rarely coverable
            raise ValueError(f"{self.name}: no feasible instance in {MAX_DRAWS} draws (too few agents per skill "
                             f"for these requirements: more agents, or fewer tasks)")
        depots = rng.random((self.species, 2))
        locs = rng.random((self.tasks, 2))
        durs = rng.random(self.tasks) * self.max_duration
        species = tuple(
            Species(tuple(float(v) for v in traits[s]), per, (float(depots[s, 0]), float(depots[s, 1])))
            for s in range(self.species)
        )
        tasks = tuple(
            Task((float(locs[m, 0]), float(locs[m, 1])), tuple(float(v) for v in req[m]), float(durs[m]))
            for m in range(self.tasks)
        )
        return Instance(
            "additive" if self.additive else "binary", self.velocity, self.skills, species, tasks,
            name or self.name,
        )

    def instance(self, seed: int, index: int) -> Instance:
        _check_seed(seed)
        return self.sample(np.random.default_rng([seed, index]), f"{self.name}_s{seed}_{index_str(index, 1)}")

    def generate(self, count: int, seed: int) -> list[Instance]:
        _check_seed(seed)
        width = index_width(count)
        return [
            self.sample(np.random.default_rng([seed, i]), f"{self.name}_s{seed}_{index_str(i, width)}")
            for i in range(count)
        ]


def _check_seed(seed: int) -> None:
    if seed < 0:  # numpy's seed sequences take non-negative integers only
        raise ValueError(f"seed: expected a non-negative integer, got {seed}")


def index_width(count: int) -> int:
    return max(3, len(str(max(count - 1, 0))))


def index_str(i: int, width: int) -> str:
    return str(i).zfill(width)


@dataclass(frozen=True)
class TrainingGenerator:
    """The paper's training distribution: MA-AT, 15-50 tasks, 3-5 species, 3-5 agents/species, K=5.

    ``tasks``, ``species`` and ``per_species`` are inclusive ranges; a curriculum narrows them.
    """

    tasks: tuple[int, int] = (15, 50)
    species: tuple[int, int] = (3, 5)
    per_species: tuple[int, int] = (3, 5)
    skills: int = 5
    scenario: str = "MA-AT"

    def sample(self, rng: np.random.Generator) -> Instance:
        s = int(rng.integers(self.species[0], self.species[1] + 1))
        n = int(rng.integers(self.per_species[0], self.per_species[1] + 1))
        m = int(rng.integers(self.tasks[0], self.tasks[1] + 1))
        return ScenarioGenerator(self.scenario, s * n, s, m, self.skills).sample(rng, f"train_{s * n}-{s}-{m}")

    def stream(self, seed: int) -> Iterator[Instance]:
        rng = np.random.default_rng(seed)
        while True:
            yield self.sample(rng)
