"""Mission families: a generalisation suite beyond the paper's rows (``docs/families.md``).

Each family varies one axis a real fleet varies on (team composition, skills, multi-unit
capabilities, binary tasks, task layout, time scale, depots, size) away from the paper's MA-AT
shape. A :class:`FamilyGenerator` is a frozen, seeded generator like
:class:`~hmrta.generators.ScenarioGenerator`: instance ``i`` of a set is a pure function of
``(generator parameters, seed, i)``.

Random streams are salted: instance ``i`` uses
``numpy.random.default_rng([seed, i, FAMILY_SALT, crc32(name)])``, so no family instance shares a
random stream with a paper row (``rng([seed, i])``), with the training stream
(``rng(config seed)``) or with another family.

Every instance is feasible: traits and requirements are redrawn until the whole team can satisfy
every task (as the paper generators do).
"""
from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from .generators import MAX_DRAWS, draw_traits, index_str, index_width
from .instance import DEFAULT_VELOCITY, Instance, Species, Task

FAMILIES_TABLE = "Families"  # the table name in ``hmrta bench --suite families``
FAMILY_SALT = 0x66616D73  # "fams": keeps family random streams apart from every other set
MAX_SKILLS = 5  # the learned policy's K_MAX (hmrta.rl.features): every family is within it
DEV_SEED = 2000  # dev sets (model selection); the test sets use the bench default seed, 1000
TRAIT_KINDS = ("one-hot", "binary", "multi")
LAYOUTS = ("uniform", "clustered")
DEPOTS = ("separate", "shared")


@dataclass(frozen=True)
class FamilyGenerator:
    """One family row.

    family        short stable family name; the row name is ``<family>-<tasks>``
    tasks         number of tasks
    counts        agents per species (one entry per species; the team is fixed per row)
    skills        K (1..5)
    traits        ``one-hot``: species s has skill ``s mod K``; ``binary``: random 0/1 vectors;
                  ``multi``: random integer vectors in 0..trait_max. Binary and multi traits are
                  distinct across species (when there are enough vectors) and never all zero.
    trait_max     largest trait entry of ``multi`` traits
    requirement   ``additive`` (AT) or ``binary`` (BT)
    req_min, req_max  AT requirement entries uniform in req_min..req_max (BT: 0..1); all-zero rows
                  are redrawn
    layout        ``uniform`` task locations, or ``clustered``: ``clusters`` Gaussian clusters
                  (centres uniform in [0.1, 0.9]^2, standard deviation ``spread``, clipped to the
                  unit square), each task in a uniformly drawn cluster
    depots        ``separate``: one uniform depot per species; ``shared``: all species at one depot
    velocity      agent speed (map units per time unit; the paper's is 0.2)
    duration      task durations uniform in [lo, hi)
    """

    family: str
    tasks: int
    counts: tuple[int, ...]
    skills: int
    traits: str = "binary"
    trait_max: int = 1
    requirement: str = "additive"
    req_min: int = 0
    req_max: int = 2
    layout: str = "uniform"
    clusters: int = 3
    spread: float = 0.05
    depots: str = "separate"
    velocity: float = DEFAULT_VELOCITY
    duration: tuple[float, float] = (0.0, 5.0)

    def __post_init__(self) -> None:
        def bad(field: str, expected: str) -> ValueError:
            return ValueError(f"family {self.family!r}: {field}: expected {expected}, got {getattr(self, field)!r}")

        if not 1 <= self.skills <= MAX_SKILLS:
            raise bad("skills", f"1..{MAX_SKILLS}")
        if self.tasks < 1:
            raise bad("tasks", ">= 1")
        if not self.counts or min(self.counts) < 1:
            raise bad("counts", "a non-empty tuple of positive agent counts")
        if self.traits not in TRAIT_KINDS:
            raise bad("traits", " / ".join(TRAIT_KINDS))
        if self.traits == "one-hot" and len(self.counts) < self.skills:
            raise bad("counts", f"at least {self.skills} species with one-hot traits (one per skill)")
        if self.trait_max < 1 or (self.traits != "multi" and self.trait_max != 1):
            raise bad("trait_max", "1 (>= 1 with multi traits)")
        if self.requirement not in ("additive", "binary"):
            raise bad("requirement", "additive / binary")
        if not 0 <= self.req_min <= self.req_max or self.req_max < 1:
            raise bad("req_max", "0 <= req_min <= req_max, req_max >= 1")
        if self.layout not in LAYOUTS:
            raise bad("layout", " / ".join(LAYOUTS))
        if self.clusters < 1 or self.spread <= 0:
            raise bad("clusters", ">= 1 clusters of positive spread")
        if self.depots not in DEPOTS:
            raise bad("depots", " / ".join(DEPOTS))
        if self.velocity <= 0:
            raise bad("velocity", "> 0")
        if not 0 <= self.duration[0] <= self.duration[1]:
            raise bad("duration", "0 <= lo <= hi")

    # ---- sizes (the paper's kn, ks, km, kb) ----------------------------------------------------
    @property
    def name(self) -> str:
        return f"{self.family}-{self.tasks}"

    @property
    def agents(self) -> int:
        return sum(self.counts)

    @property
    def species(self) -> int:
        return len(self.counts)

    @property
    def additive(self) -> bool:
        return self.requirement == "additive"

    # ---- sampling ------------------------------------------------------------------------------
    def _traits(self, rng: np.random.Generator) -> np.ndarray:  # [species, skills]
        S, K = self.species, self.skills
        if self.traits == "one-hot":
            return np.eye(K)[np.arange(S) % K]
        hi = self.trait_max + 1
        return draw_traits(rng, S, K, hi, distinct=S <= hi**K - 1)  # distinct where there are enough vectors

    def _requirements(self, rng: np.random.Generator) -> np.ndarray:  # [tasks, skills]
        lo, hi = (self.req_min, self.req_max + 1) if self.additive else (0, 2)
        q = rng.integers(lo, hi, size=(self.tasks, self.skills))
        zero = q.sum(1) == 0
        while zero.any():
            q[zero] = rng.integers(lo, hi, size=(int(zero.sum()), self.skills))
            zero = q.sum(1) == 0
        return q.astype(np.float64)

    def _locations(self, rng: np.random.Generator) -> np.ndarray:  # [tasks, 2]
        if self.layout == "uniform":
            return rng.random((self.tasks, 2))
        centres = 0.1 + 0.8 * rng.random((self.clusters, 2))
        which = rng.integers(0, self.clusters, size=self.tasks)
        return np.clip(centres[which] + rng.normal(0.0, self.spread, size=(self.tasks, 2)), 0.0, 1.0)

    def sample(self, rng: np.random.Generator, name: str | None = None) -> Instance:
        counts = np.array(self.counts, dtype=np.float64)
        for _ in range(MAX_DRAWS):
            traits = self._traits(rng)
            req = self._requirements(rng)
            team = (traits * counts[:, None]).sum(0)
            if (req <= team).all() if self.additive else ((req > 0) <= (team > 0)).all():
                break
        else:
            raise ValueError(f"{self.name}: no feasible instance in {MAX_DRAWS} draws")
        if self.depots == "shared":
            depots = np.repeat(rng.random((1, 2)), self.species, axis=0)
        else:
            depots = rng.random((self.species, 2))
        locs = self._locations(rng)
        lo, hi = self.duration
        durs = lo + rng.random(self.tasks) * (hi - lo)
        species = tuple(
            Species(tuple(float(v) for v in traits[s]), int(self.counts[s]),
                    (float(depots[s, 0]), float(depots[s, 1])))
            for s in range(self.species)
        )
        tasks = tuple(
            Task((float(locs[m, 0]), float(locs[m, 1])), tuple(float(v) for v in req[m]), float(durs[m]))
            for m in range(self.tasks)
        )
        return Instance(self.requirement, self.velocity, self.skills, species, tasks, name or self.name)

    def rng(self, seed: int, index: int) -> np.random.Generator:
        return np.random.default_rng([seed, index, FAMILY_SALT, zlib.crc32(self.name.encode())])

    def instance(self, seed: int, index: int) -> Instance:
        return self.sample(self.rng(seed, index), f"{self.name}_s{seed}_{index_str(index, 1)}")

    def generate(self, count: int, seed: int) -> list[Instance]:
        width = index_width(count)
        return [self.sample(self.rng(seed, i), f"{self.name}_s{seed}_{index_str(i, width)}") for i in range(count)]


def _rows() -> tuple[FamilyGenerator, ...]:
    G = FamilyGenerator
    return (
        # team composition
        G("homog", 50, (20,), 1, traits="one-hot", req_min=1, req_max=5),  # the public benchmark shape
        G("homog", 100, (40,), 1, traits="one-hot", req_min=1, req_max=5),
        G("few-large", 20, (8, 8), 3),
        G("few-large", 100, (20, 20), 5),
        G("many-small", 10, (1, 2) * 5, 5),
        G("many-small", 50, (1, 2) * 5, 5),
        # capabilities and requirements of several units
        G("multi-unit", 20, (3, 3, 3, 3), 4, traits="multi", trait_max=3, req_max=4),
        G("multi-unit", 50, (4,) * 5, 5, traits="multi", trait_max=3, req_max=4),
        # binary tasks
        G("binary", 30, (4,) * 4, 5, requirement="binary"),
        # task layout
        G("clustered", 50, (5,) * 5, 5, layout="clustered", clusters=3, spread=0.05),
        # time scales: cheap travel, expensive travel, long tasks
        G("fast-robots", 50, (5,) * 5, 5, velocity=1.0),
        G("slow-robots", 20, (3,) * 4, 4, velocity=0.05),
        G("long-tasks", 50, (5,) * 5, 5, duration=(10.0, 30.0)),
        # depots
        G("shared-depot", 50, (5,) * 5, 5, depots="shared"),
    )


FAMILY_ROWS: tuple[FamilyGenerator, ...] = _rows()
FAMILY_NAMES: tuple[str, ...] = tuple(dict.fromkeys(g.family for g in FAMILY_ROWS))


@dataclass(frozen=True)
class FamilyRow:
    """A family as a bench row (the paper-table layout of ``hmrta.bench``, no paper columns)."""

    gen: FamilyGenerator
    table: str = FAMILIES_TABLE

    @property
    def key(self) -> str:
        return self.gen.name

    agents = property(lambda self: self.gen.agents)
    species = property(lambda self: self.gen.species)
    tasks = property(lambda self: self.gen.tasks)
    skills = property(lambda self: self.gen.skills)

    def generator(self) -> FamilyGenerator:
        return self.gen

    def paper(self) -> None:
        return None


def family_suite(families: Iterable[str] | None = None, max_tasks: int | None = None) -> list[FamilyRow]:
    """Bench rows of the named families (default: all), optionally only rows up to ``max_tasks``."""
    wanted = list(families) if families else list(FAMILY_NAMES)
    unknown = [f for f in wanted if f not in FAMILY_NAMES]
    if unknown:
        raise ValueError(f"unknown family {unknown[0]!r} (expected one of {', '.join(FAMILY_NAMES)})")
    return [FamilyRow(g) for g in FAMILY_ROWS
            if g.family in wanted and (max_tasks is None or g.tasks <= max_tasks)]


# ---- broad training distribution (domain randomisation over the family axes) --------------------
BROAD_SALT = 0x62726F64  # "brod": keeps broad-training streams apart from the family and paper sets


@dataclass(frozen=True)
class BroadGenerator:
    """Training missions drawn across every axis of the families (domain randomisation): each
    instance first draws a :class:`FamilyGenerator` (team shape, skills, trait kind, requirement kind
    and range, layout, depots, speed, durations, 10..``max_tasks`` tasks), then a mission of it.

    Team shapes, each with probability ``1/4``: ``paper`` (3-5 species of 3-5 robots, binary traits,
    K = 5, requirements 0..2: the paper's training distribution), ``homog`` (one species of 6-25
    robots with one skill, requirements 1..5), ``few-large`` (2-3 species of 4-10), ``many-small``
    (6-10 species of 1-2). Outside ``paper``: K in 1..5 (as the shape allows), traits one-hot, binary
    or multi (entries 0..2-3, requirements up to 4), 20% binary tasks, 25% clustered tasks, 20% one
    shared depot, speed log-uniform in [0.05, 1], durations [0, 5) or, one time in five, [10, 30).

    ``team_scale`` (low, high) > 1 grows the teams for larger missions: every species' robot count
    is multiplied by one factor per instance, drawn log-uniform in the range (rounded, at least 1),
    so the same shapes reach 100+ robots. At (1, 1), the default, nothing more is drawn.

    Instance ``i`` of seed ``s`` is a pure function of ``(min_tasks, max_tasks, s, i)`` (and of
    ``team_scale`` when it is not (1, 1)) on a salted stream (``BROAD_SALT``), never one of a
    family's or a paper row's.
    """

    max_tasks: int = 30
    min_tasks: int = 10
    team_scale: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self) -> None:
        if not 1 <= self.min_tasks <= self.max_tasks:
            raise ValueError(f"broad generator: expected 1 <= min_tasks <= max_tasks, got "
                             f"{self.min_tasks}..{self.max_tasks}")
        lo, hi = self.team_scale
        if not 1.0 <= lo <= hi:
            raise ValueError(f"broad generator: expected team_scale (low, high) with 1 <= low <= high, "
                             f"got {self.team_scale}")

    def _grow(self, rng: np.random.Generator, counts: tuple[int, ...]) -> tuple[int, ...]:
        lo, hi = self.team_scale
        if (lo, hi) == (1.0, 1.0):
            return counts
        f = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        return tuple(max(1, round(c * f)) for c in counts)

    @property
    def name(self) -> str:
        return f"broad-{self.min_tasks}-{self.max_tasks}"

    def family(self, rng: np.random.Generator) -> FamilyGenerator:
        """The family of one instance (drawn from ``rng``)."""
        m = int(rng.integers(self.min_tasks, self.max_tasks + 1))
        shape = ("paper", "homog", "few-large", "many-small")[int(rng.integers(4))]
        if shape == "paper":
            s, n = int(rng.integers(3, 6)), int(rng.integers(3, 6))
            return FamilyGenerator("broad", m, self._grow(rng, (n,) * s), 5)
        if shape == "homog":
            return FamilyGenerator("broad", m, self._grow(rng, (int(rng.integers(6, 26)),)), 1, traits="one-hot",
                                   req_min=1, req_max=int(rng.integers(2, 6)), **self._world(rng))
        if shape == "few-large":
            counts = tuple(int(c) for c in rng.integers(4, 11, size=int(rng.integers(2, 4))))
        else:
            counts = tuple(int(c) for c in rng.integers(1, 3, size=int(rng.integers(6, 11))))
        counts = self._grow(rng, counts)
        traits = ("one-hot", "binary", "multi")[int(rng.integers(3))]
        k_hi = min(MAX_SKILLS, len(counts)) if traits == "one-hot" else MAX_SKILLS
        K = int(rng.integers(1, k_hi + 1))
        trait_max = int(rng.integers(2, 4)) if traits == "multi" else 1
        req = ({"requirement": "binary"} if rng.random() < 0.2 else
               {"req_max": int(rng.integers(2, 5)) if traits == "multi" else 2})
        return FamilyGenerator("broad", m, counts, K, traits=traits, trait_max=trait_max, **req,
                               **self._world(rng))

    @staticmethod
    def _world(rng: np.random.Generator) -> dict:
        return {"layout": "clustered" if rng.random() < 0.25 else "uniform",
                "clusters": int(rng.integers(2, 5)),
                "depots": "shared" if rng.random() < 0.2 else "separate",
                "velocity": float(np.exp(rng.uniform(np.log(0.05), np.log(1.0)))),
                "duration": (10.0, 30.0) if rng.random() < 0.2 else (0.0, 5.0)}

    def sample(self, rng: np.random.Generator, name: str | None = None) -> Instance:
        for _ in range(100):  # a drawn family whose requirements the team can never cover is redrawn
            fam = self.family(rng)
            try:
                return fam.sample(rng, name or self.name)
            except ValueError:
                continue
        raise ValueError(f"{self.name}: no feasible family in 100 draws")

    def rng(self, seed: int, index: int) -> np.random.Generator:
        return np.random.default_rng([seed, index, BROAD_SALT, self.min_tasks, self.max_tasks])

    def instance(self, seed: int, index: int) -> Instance:
        return self.sample(self.rng(seed, index), f"{self.name}_s{seed}_{index}")

    def generate(self, count: int, seed: int) -> list[Instance]:
        return [self.instance(seed, i) for i in range(count)]
