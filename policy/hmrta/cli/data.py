"""``hmrta generate``, ``convert`` and ``keys``: mission sets, CTAS-D conversion, keystores."""
from __future__ import annotations

import json
from pathlib import Path

from .common import MAX_SET_TASKS, UserError, _load, _positive, _row_sizes, _seed, writable


def cmd_generate(args) -> int:
    from ..generators import ScenarioGenerator, index_width

    _positive("--count", args.count)
    _row_sizes(args)
    if args.count * args.tasks > MAX_SET_TASKS:  # the whole set is drawn in memory before it is written
        raise UserError(f"--count {args.count} x --tasks {args.tasks}: at most {MAX_SET_TASKS:,} tasks in one set "
                        f"(write several sets with other --seed values)")
    _seed(args.seed)
    writable("--out", args.out, folder=True)
    try:  # every instance is drawn before the folder is made: a row no team can do leaves nothing
        gen = ScenarioGenerator(args.scenario, args.agents, args.species, args.tasks, args.skills)
        instances = gen.generate(args.count, args.seed)
    except ValueError as e:
        raise UserError(str(e)) from None
    out = Path(args.out)
    made = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    width = index_width(args.count)
    name = f"{gen.name}_s{args.seed}"
    written: list[Path] = []
    try:
        for i, inst in enumerate(instances):
            written.append(out / f"{name}_{str(i).zfill(width)}.yaml")
            inst.save(written[-1])
    except BaseException:  # interrupted (or a write failed): no partial set is left behind
        for f in written:
            f.unlink(missing_ok=True)
        if made and not any(out.iterdir()):
            out.rmdir()
        raise
    print(f"wrote {args.count} instances to {out}/{name}_*.yaml")
    return 0


def robot_mapping(inst, config: dict) -> dict:
    """CTAS-D robot ids -> hmrta agent ids of the converted instance. Robots sharing pose and
    skillset form one species (in order of the lowest robot id); agents are numbered species-major,
    each species' robots in increasing id order."""
    robots = config["robots"]
    k = inst.skills
    slots: dict[int, list[str]] = {}
    for key in sorted(robots, key=int):
        r = robots[key]
        traits = [0.0] * k
        for sk, v in r["skillset"].items():
            traits[int(sk)] = float(v)
        sig = ((float(r["pose"]["x"]), float(r["pose"]["y"])), tuple(traits))
        s = next(i for i, sp in enumerate(inst.species) if (tuple(sp.depot), tuple(sp.traits)) == sig)
        slots.setdefault(s, []).append(key)
    offset, robot_to_agent = 0, {}
    for s, sp in enumerate(inst.species):
        ids = slots.get(s, [])
        if len(ids) != sp.count:  # the reader grouped robots otherwise: never write a wrong mapping
            raise RuntimeError(f"species {s}: {len(ids)} robots map to it, the instance has {sp.count}")
        for j, key in enumerate(ids):
            robot_to_agent[key] = offset + j
        offset += sp.count
    return robot_to_agent


MAPPING_FORMAT = "hmrta-robot-mapping/1"  # convert's OUT.mapping.json (docs/schemas)


def mapping_path(out: str | Path) -> Path:
    """Where ``convert --out OUT.yaml`` writes the robot id mapping: ``OUT.mapping.json``."""
    out = Path(out)
    return out.with_name(f"{out.stem}.mapping.json")


def cmd_convert(args) -> int:
    from ..formats import ctas_config
    from ..instance import InstanceError, atomic_write_text

    writable("--out", args.out, inputs=(args.input,))
    inst = _load(args.input, "hmrta-instance/1 holds no events", releases=True)  # release times it holds
    if Path(args.out).suffix.lower() == ".json":
        raise UserError(f"--out {args.out}: convert writes hmrta-instance/1 YAML; give a .yaml file name")
    try:
        ctas = ctas_config(args.input)  # read as the loader did (it has just read it)
    except InstanceError as e:  # (the file changed under us)
        raise UserError(str(e)) from None
    mapping = None
    if ctas is not None:  # CTAS-D: robots are renumbered species-major
        cfg, config = ctas
        mp = writable("the robot mapping of --out", mapping_path(args.out), inputs=(args.input,))  # never an input
        r2a = robot_mapping(inst, config)
        tasks = sorted(config["tasks"], key=int)  # task m of the mission: the m-th CTAS-D id in index order
        mapping = {"format": MAPPING_FORMAT, "source": str(cfg), "instance": str(args.out), "robot_to_agent": r2a,
                   "agent_to_robot": sorted(r2a, key=r2a.get), "task_to_index": {t: m for m, t in enumerate(tasks)},
                   "index_to_task": tasks}
    inst.save(args.out)
    print(f"wrote {args.out} ({inst.n_agents} agents in {inst.n_species} species, {inst.n_tasks} tasks)")
    if mapping is not None:
        atomic_write_text(mp, json.dumps(mapping, indent=1) + "\n")
        print(f"wrote {mp} (CTAS-D robot and task ids -> hmrta agent and task indices, agents numbered "
              f"species-major)")
    return 0


def cmd_keys(args) -> int:
    from ..keys import KeystoreError, create_keystore, robot_key_path

    if args.instance:
        inst = _load(args.instance)  # (a scenario: the robots its add_robot events add too)
        added = sum(e.get("type") == "add_agent" for e in inst.events)
        robots = [f"robot_{a}" for a in range(inst.n_agents + added)]
    else:
        robots = [r.strip() for r in args.robots.split(",")]
        if not all(robots):
            raise UserError(f"--robots {args.robots!r}: expected comma-separated robot names, found an empty one")
    try:
        create_keystore(args.out, robots, force=args.force)
    except KeystoreError as e:
        raise UserError(f"keys create: {e}") from None
    print(f"wrote keystore {args.out} for {len(robots)} robots: {Path(args.out) / 'keys.json'} (the task board's, "
          f"every key) and {robot_key_path(args.out, robots[0]).parent}/<robot>.key.json (give each robot only its own)")
    return 0
