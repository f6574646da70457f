"""Behaviour cloning of a baseline (``pretrain``), with DAgger and expert iteration.

Cross-entropy on a baseline's choices (``pretrain.teacher``: ``greedy`` or the coalition-aware
``greedy-coalition``), so that later phases start from a baseline-level policy; or on a trained
policy's greedy decoding (``rl@CHECKPOINT``: distillation, e.g. into a narrower network). With
``pretrain.dagger`` > 0 that share of the instances is driven by the policy's own greedy
decoding and labelled by the teacher (DAgger, Ross et al. 2011), so the policy also learns to
recover from its own mistakes; with ``pretrain.dagger_teacher: solver`` the policy drives each
such mission to a random decision and a plan from that state (:mod:`hmrta.solvers.fromstate`)
labels the rest of it (:meth:`Imitation.solver_dagger`). With ``pretrain.samples`` > 0 (expert iteration) that many
sampled rollouts of the policy (``pretrain.temperature``) compete with the teacher's trajectory on
each teacher-driven instance (with ``pretrain.generated_teacher: policy``, on the generated
missions, with the policy's own greedy decoding: self-improvement), and the best of them (by
return, or by makespan with ``pretrain.select: makespan``) is cloned: the targets are never worse
than the teacher, and where the policy won they are its own, learnable choices. With ``pretrain.tau`` > 0
the targets are soft: with greedy-coalition half on the teacher's choice, half spread by its
coalition-start estimates; with a checkpoint teacher its own distribution.

The teacher-driven missions are labelled by :func:`teacher_labels`, a pure function of a
:class:`LabelJob`, mapped through the run's fan-out (``Trainer.fan_out``: Ray tasks with
``hmrta train --jobs N``; the same labels in the same order as in process).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch

from ..core import MissionState, Rules
from ..solvers.fromstate import plan_from_state
from .config import TEACHERS, teacher_checkpoint
from .features import collate, observe
from .rollout import makespans, returns, rollout
from .schedules import RouteTeacher

if TYPE_CHECKING:
    from .train import Trainer


class Imitation:
    """One iteration = ``pretrain.instances_per_iter`` fresh missions, labelled, then
    ``pretrain.epochs`` epochs of minibatch cross-entropy."""

    def __init__(self, run: "Trainer"):
        self.run = run

    def step(self) -> dict:
        run, lr_ = self.run, self.run.learner
        p = run.cfg.pretrain
        if p.schedules:  # the solver as teacher: missions with their routes (and generated ones)
            items = run.schedule_items(p.instances_per_iter) + [(inst, None) for inst in run._instances(p.generated)]
        else:
            items = [(inst, None) for inst in run._instances(p.instances_per_iter)]
        insts = [inst for inst, _ in items]
        own = []  # generated_teacher: policy: the missions its greedy decoding drives
        labels = Labels()
        name = resolved_teacher(p.teacher)  # (a checkpoint by its absolute path: Ray workers read the same file)
        teacher = make_teacher(name)
        if teacher_checkpoint(name) is not None:
            run.note_teacher(teacher.pol)
        tau, view = p.tau, lr_.model.cfg.view()
        on_policy, jobs = [], []  # DAgger states; the teacher-driven missions (LabelJob)
        estimates = []  # [len(on_policy)] decisions expected in each DAgger mission
        for inst, routes in items:
            seed = int(lr_.np_rng.integers(2**31))
            if routes is None and p.generated_teacher == "policy":
                own.append(MissionState(inst, seed=seed, rules=run.train_rules))
                continue
            if lr_.np_rng.random() < p.dagger:
                on_policy.append(MissionState(inst, seed=seed, rules=run.train_rules))  # the policy drives
                estimates.append(sum(map(len, routes)) if routes is not None else 2 * inst.n_tasks)
                continue
            jobs.append(LabelJob(inst, routes, seed, run.train_rules, name, tau, view))
        followed = [0, 0]  # decisions labelled by a schedule's routes, by the fallback teacher
        pool = []  # (the teacher's finished state, its label range) per teacher-driven mission
        mission: list[int] = []  # [n] the mission of each label (label_weight: mission)
        for k, done in enumerate(run.fan_out(teacher_labels, jobs)):  # Ray tasks with --jobs > 1 (item order kept)
            first = len(labels.acts)
            labels.extend(done.labels)
            mission += [k] * (len(labels.acts) - first)
            followed[0] += done.hits
            followed[1] += done.misses
            pool.append((done.state, first, len(labels.acts)))
        obs, deciders, acts, soft = labels.obs, labels.deciders, labels.acts, labels.soft
        lr_.model.eval()
        plan_stats = {}
        if on_policy and p.dagger_teacher == "solver":  # DAgger: the solver plans from a state the policy reached
            plan_stats = self.solver_dagger(on_policy, estimates, labels, mission, len(jobs), name)
        elif on_policy:  # DAgger: the teacher labels the states the policy visits
            def label(idx, o, nodes, act) -> None:
                for i in idx:
                    before = len(acts)
                    labels.add(on_policy[i], teacher, teacher, tau, view)
                    mission.extend([len(jobs) + i] * (len(acts) - before))
            rollout(lr_.model, on_policy, sample=False, before_step=label)
        if own:  # the trajectory to beat: the greedy decoding in float32, as RL(g.) runs; it labels nothing
            rollout(lr_.model, own, sample=False)
            run.episodes += len(own)
            run.decisions += sum(st.decisions for st in own)
            pool += [(st, len(acts), len(acts)) for st in own]
        pool_stats = self.pool(pool, obs, deciders, acts) if p.samples and pool else {}
        lr_.set_lr(p.lr)
        lr_.model.train()
        n = len(acts)
        weight = mission_weights(mission) if p.label_weight == "mission" else None  # [n] mean 1
        losses = []
        for _ in range(p.epochs):
            perm = lr_.np_rng.permutation(n)
            for lo in range(0, n, p.batch):
                idx = perm[lo:lo + p.batch]
                batch = {k: v.to(lr_.device) for k, v in collate([obs[i] for i in idx],
                                                                 [deciders[i] for i in idx]).items()}
                logits = lr_.model(**batch)  # [b, T]
                if tau > 0:  # [b, T] target distributions, zero-padded to the batch's rows
                    q = torch.zeros_like(logits)
                    for r, i in enumerate(idx):
                        q[r, :len(soft[i])] = torch.tensor(soft[i])  # (a copy: arrays from Ray are read-only)
                    logp = torch.log_softmax(logits, -1).masked_fill(~batch["action_mask"], 0.0)  # [b, T]
                    per_label = -(q * logp).sum(-1)  # [b]
                else:
                    target = torch.tensor([acts[i] for i in idx], device=lr_.device)
                    per_label = torch.nn.functional.cross_entropy(logits, target, reduction="none")  # [b]
                if weight is not None:  # every mission one unit
                    per_label = per_label * torch.as_tensor(weight[idx], dtype=per_label.dtype, device=lr_.device)
                loss = per_label.mean()
                lr_.opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(lr_.model.parameters(), run.cfg.train.grad_clip)
                lr_.optimizer_step()
                losses.append(loss.item())
        run.pretrain_done += 1
        extra = {"route_share": followed[0] / max(1, sum(followed))} if p.schedules else {}
        loss_ = {"bc_loss": float(np.mean(losses))} if losses else {}  # (none: no sample won)
        return {"iteration": run.pretrain_done, **loss_, "labels": n,
                "tasks": insts[0].n_tasks, "agents": insts[0].n_agents, **pool_stats, **plan_stats, **extra}

    def solver_dagger(self, on_policy: list[MissionState], estimates: list[int], labels: "Labels",
                      mission: list[int], first: int, teacher: str) -> dict:
        """``pretrain.dagger_teacher: solver``: the policy drives each DAgger mission to a decision
        drawn uniformly below its expected count (``estimates``); the solver plans the rest from
        that state (:func:`plan_from_state`) and the plan labels every decision from there on
        (:func:`plan_labels`, fanned out like the teacher's missions; ``teacher``: the teacher's
        name as the jobs carry it, :func:`resolved_teacher`). Returns the plans' mean makespan
        ratio to greedy-coalition's continuation from the same states."""
        run, lr_ = self.run, self.run.learner
        p = run.cfg.pretrain
        cuts = [int(lr_.np_rng.integers(0, max(1, e))) for e in estimates]
        reached: dict[int, MissionState] = {}

        def cut(idx, o, nodes, act) -> None:
            for i in idx:
                if i not in reached and on_policy[i].decisions >= cuts[i]:
                    reached[i] = on_policy[i].clone()
        rollout(lr_.model, on_policy, sample=False, before_step=cut)
        order = sorted(reached)
        jobs = [PlanJob(reached[i], p.dagger_evals, int(lr_.np_rng.integers(2**31)), teacher, p.tau,
                        lr_.model.cfg.view()) for i in order]
        ratios = []
        for i, done in zip(order, run.fan_out(plan_labels, jobs)):
            before = len(labels.acts)
            labels.extend(done.labels)
            mission.extend([first + i] * (len(labels.acts) - before))
            ratios.append(done.plan_ratio)
        return {"dagger_plan_ratio": float(np.mean(ratios))} if ratios else {}

    def pool(self, pool: list[tuple[MissionState, int, int]], obs: list, deciders: list, acts: list) -> dict:
        """Expert iteration (``pretrain.samples``): ``samples`` sampled rollouts of the policy compete
        with the teacher's trajectory on each pooled instance; where a sample has the better score
        (``pretrain.select``: the return -T - W, or the makespan), its decisions replace the
        teacher's labels of that instance. The targets are then never worse than the teacher and
        are, where the policy won, its own (learnable) choices.
        ``pool``: (the teacher's finished state, [first, end) of its labels) per instance; the other
        labels (DAgger's) are kept."""
        run, lr_ = self.run, self.run.learner
        p, t = run.cfg.pretrain, run.cfg.train
        S = int(p.samples)
        states = [MissionState(st.inst, seed=st.seed, rules=run.train_rules) for st, _, _ in pool for _ in range(S)]
        traj = rollout(lr_.model, states, sample=True, generator=lr_.torch_gen, record=True,
                       amp=lr_.amp, temperature=p.temperature)
        run.episodes += len(states)
        run.decisions += traj.decisions
        def score(sts: list[MissionState], t_max: float) -> np.ndarray:  # [E] higher is better
            return returns(sts, t_max) if p.select == "return" else -makespans(sts, t_max)
        R = score(states, t.t_max).reshape(len(pool), S)  # [I, S]
        Rt = score([st for st, _, _ in pool], t.t_max)  # [I] the teacher's
        win = R.max(1) > Rt + 1e-9  # [I] a sample beats the teacher
        keep = np.ones(len(acts), dtype=bool)
        for (_, first, end), w in zip(pool, win):
            keep[first:end] = not w  # drop the teacher's labels where a sample won
        obs[:] = [o for o, k in zip(obs, keep) if k]
        deciders[:] = [d for d, k in zip(deciders, keep) if k]
        acts[:] = [a for a, k in zip(acts, keep) if k]
        best = torch.as_tensor(np.flatnonzero(win) * S + R.argmax(1)[win])  # winning episodes
        for o, a, e in zip(traj.obs, traj.actions, traj.episode):
            for r in torch.isin(e, best).nonzero()[:, 0].tolist():  # rows of this step from a winner
                n_t, n_a = int(o["task_valid"][r].sum()), int(o["agent_valid"][r].sum())
                obs.append((o["tasks"][r, :n_t].numpy(), o["agents"][r, :n_a].numpy(),
                            o["action_mask"][r, :n_t].numpy()))
                deciders.append(int(o["decider"][r]))
                acts.append(int(a[r]))
        mk_t = np.array([st.makespan for st, _, _ in pool])  # [I]
        mk_best = np.array([s.makespan for s in states])[np.arange(len(pool)) * S + R.argmax(1)]  # [I]
        return {"teacher_makespan": float(mk_t.mean()), "pool_makespan": float(np.where(win, mk_best, mk_t).mean()),
                "teacher_wins": float(1 - win.mean())}


def mission_weights(mission: list[int]) -> np.ndarray:
    """Per-label loss weights under which every mission counts the same: a label of a mission
    with c labels weighs 1 / c, scaled so that the weights average 1 ([n] for n labels)."""
    m = np.asarray(mission, dtype=np.int64)  # [n]
    if not len(m):
        return np.ones(0)
    _, inv, counts = np.unique(m, return_inverse=True, return_counts=True)
    w = 1.0 / counts[inv]  # [n]
    return w * (len(m) / w.sum())


@dataclass
class Labels:
    """Labelled decisions: the observation (task rows, robot rows, mask), the decider's row, the
    teacher's choice (its row in the observation) and, with ``tau`` > 0, the soft target."""
    obs: list = field(default_factory=list)
    deciders: list = field(default_factory=list)
    acts: list = field(default_factory=list)
    soft: list = field(default_factory=list)

    def add(self, st: MissionState, decide: Callable[[MissionState], int], teacher, tau: float,
            view: dict) -> int:
        """Record ``decide``'s choice at ``st`` as the network observes it (``view``: the model
        config's :meth:`~hmrta.rl.model.ModelConfig.view`; ``teacher``'s estimates for the soft
        target); returns it."""
        tf, af, mask, nodes, row = observe(st, **view)
        n = decide(st)
        hit = np.flatnonzero(nodes == n)
        if len(hit):  # (outside the observation window only on missions beyond the training scale)
            self.obs.append((tf, af, mask))
            self.deciders.append(row)
            self.acts.append(int(hit[0]))
            if tau > 0:
                self.soft.append(soft_target(teacher, st, nodes, int(hit[0]), tau))
        return n

    def extend(self, other: "Labels") -> None:
        self.obs += other.obs
        self.deciders += other.deciders
        self.acts += other.acts
        self.soft += other.soft


@dataclass
class LabelJob:
    """One teacher-driven mission to label: a pure function of these fields (so it runs the same
    in this process or as a Ray task). ``routes``: a schedule to follow (None: the teacher alone)."""
    inst: Any
    routes: list | None
    seed: int
    rules: Rules
    teacher: str
    tau: float
    view: dict  # ModelConfig.view(): units and window of the observation


@dataclass
class LabelResult:
    """What :func:`teacher_labels` returns for one :class:`LabelJob`."""
    labels: Labels
    state: MissionState  # the finished mission (expert iteration compares its return)
    hits: int = 0  # decisions that followed the routes
    misses: int = 0  # decisions the teacher took where the routes had nothing admissible
    plan_ratio: float = 1.0  # plan_labels: the plan's makespan over greedy-coalition's from the same state


def teacher_labels(job: LabelJob) -> LabelResult:
    """Drive ``job``'s mission to the end by its teacher (a schedule's routes, falling back to the
    named teacher), labelling every decision. ``hmrta train --jobs N`` runs these as Ray tasks."""
    teacher = make_teacher(job.teacher)
    decide = teacher if job.routes is None else RouteTeacher(job.routes, teacher)
    st = MissionState(job.inst, seed=job.seed, rules=job.rules)
    labels = Labels()
    while not st.done:
        st.step(labels.add(st, decide, teacher, job.tau, job.view))
    hits, misses = (decide.hits, decide.misses) if job.routes is not None else (0, 0)
    return LabelResult(labels, st, hits, misses)


@dataclass
class PlanJob:
    """A mission state the policy reached, to be planned from and labelled (a pure function of these
    fields, like :class:`LabelJob`)."""
    state: MissionState
    evals: int
    seed: int
    teacher: str
    tau: float
    view: dict  # ModelConfig.view(): units and window of the observation


def plan_labels(job: PlanJob) -> LabelResult:
    """Plan the rest of ``job``'s mission from its state (:func:`plan_from_state`) and drive it to
    the end by the plan's routes (the teacher where a planned choice is not admissible, or where
    the teacher's own continuation was the better plan), labelling every decision."""
    teacher = make_teacher(job.teacher)
    plan = plan_from_state(job.state, job.evals, job.seed)
    decide = teacher if plan.routes is None else RouteTeacher(plan.routes, teacher)
    st = job.state.clone()
    labels = Labels()
    while not st.done:
        st.step(labels.add(st, decide, teacher, job.tau, job.view))
    hits, misses = (decide.hits, decide.misses) if plan.routes is not None else (0, 0)
    ratio = plan.makespan / plan.greedy_coalition if plan.greedy_coalition > 0 else 1.0
    return LabelResult(labels, st, hits, misses, ratio)


def resolved_teacher(name: str) -> str:
    """``pretrain.teacher`` with a checkpoint teacher's file as an absolute path (``rl@/...``):
    the name the label jobs carry, the same file wherever they run."""
    ck = teacher_checkpoint(name)
    if ck is None:
        return name
    from .checkpoint_info import checkpoint_path, existing

    return f"rl@{existing(checkpoint_path(ck)).resolve()}"


def make_teacher(name: str) -> Callable[[MissionState], int]:
    """The teacher named ``name``: a baseline (``TEACHERS``), or ``rl@CHECKPOINT``: that
    checkpoint's greedy decoding (:class:`~hmrta.rl.inference.CheckpointTeacher`; loaded once per process,
    CheckpointError if it cannot be)."""
    ck = teacher_checkpoint(name)
    if ck is None:
        return TEACHERS[name]()
    from .inference import CheckpointTeacher, load_policy

    return CheckpointTeacher(load_policy(ck))


def soft_target(teacher, st: MissionState, nodes: np.ndarray, row: int, tau: float) -> np.ndarray:
    """[1+W] the soft target at ``st`` over the observation's rows ``nodes`` (the teacher's choice
    at ``row``). A checkpoint teacher: its distribution softmax(logits / tau), on the rows both
    observe (renormalised; all on ``row`` if they share none). greedy-coalition: half on its
    choice, half spread by its coalition-start estimates, softmax(-(start - earliest) / tau) over
    the admissible tasks in the observation."""
    if hasattr(teacher, "distribution"):  # a checkpoint teacher
        tnodes, p = teacher.distribution(st, tau)  # [T'] ascending, [T']
        at = np.minimum(np.searchsorted(tnodes, nodes), len(tnodes) - 1)  # [1+W] (nodes ascending too)
        q = np.where(tnodes[at] == nodes, p[at], 0.0).astype(np.float32)  # [1+W]
        total = float(q.sum())
        if not total > 0:
            q[:] = 0.0
            q[row] = 1.0
            return q
        return q / total
    q = np.zeros(len(nodes), dtype=np.float32)
    q[row] = 0.5
    cand, start, _ = teacher.estimates(st)
    pos = {int(n): r for r, n in enumerate(nodes)}
    rows = np.array([pos.get(1 + int(j), -1) for j in cand])  # [C] observation row of each candidate
    ok = (rows >= 0) & np.isfinite(start)
    if not ok.any():
        q[row] = 1.0
        return q
    w = np.exp(-(start[ok] - start[ok].min()) / tau)  # [C']
    q[rows[ok]] += 0.5 * w / w.sum()
    return q
