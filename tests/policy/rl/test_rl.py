"""The learned policy: shapes and masks, padding invariance, batched == core simulator,
deterministic greedy rollouts, a tiny training run that improves, checkpoint round trip/resume."""
from __future__ import annotations

import copy
import json
import math
import re

import numpy as np
import pytest
import torch

from hmrta.core import MissionState, Rules
from hmrta.errors import MethodError
from hmrta.generators import ScenarioGenerator
from hmrta.rl.features import batch_observations
from hmrta.rl.inference import DEFAULT_CHECKPOINT, CheckpointError, LoadedPolicy, RLDecider, load_policy
from hmrta.rl.model import ModelConfig, PolicyNet
from hmrta.rl.rollout import returns, rollout
from hmrta.rl.train import DEFAULTS, Trainer, deep_update
from hmrta.sim import run

torch.set_num_threads(1)  # tiny forwards: one thread is fastest and deterministic
RULES = Rules(max_open=2, safety=True)
SMALL = ModelConfig(d_model=32, heads=4, ff_hidden=32)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return PolicyNet(SMALL).eval()


def _insts():
    return [ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(11, 0),
            ScenarioGenerator("MA-AT", 9, 3, 12, 5).instance(11, 1),
            ScenarioGenerator("SA-BT", 4, 2, 5, 2).instance(11, 2)]


def test_shapes_and_mask(model):
    states = [MissionState(i, seed=3, rules=RULES) for i in _insts()]
    obs, _ = batch_observations(states)
    B, T = obs["action_mask"].shape
    assert obs["tasks"].shape == (3, T, 15) and obs["agents"].shape[::2] == (3, 11)
    with torch.inference_mode():
        logits = model(**obs)
    assert logits.shape == (B, T)
    assert torch.isneginf(logits[~obs["action_mask"]]).all()
    assert torch.isfinite(logits[obs["action_mask"]]).all()
    # a masked action is never sampled
    probs = torch.softmax(logits, -1)
    draws = torch.multinomial(probs, 200, replacement=True, generator=torch.Generator().manual_seed(0))  # [B, 200]
    assert obs["action_mask"].gather(1, draws).all()


def test_padding_invariance(model):
    insts = _insts()
    states = [MissionState(i, seed=5, rules=RULES) for i in insts]
    with torch.inference_mode():
        together = model(**batch_observations(states)[0])
        for b, s in enumerate(states):
            alone = model(**batch_observations([s])[0])[0]
            n = len(alone)
            torch.testing.assert_close(together[b, :n], alone, rtol=1e-5, atol=1e-5)
            assert torch.isneginf(together[b, n:]).all()


@pytest.mark.parametrize("self_attention", [True, False])
@pytest.mark.parametrize("with_bias", [False, True])
def test_block_attention_is_torchs_multihead_attention(self_attention, with_bias):
    """Block.attend (the attention the network runs in training and inference alike) computes what
    nn.MultiheadAttention computes with the same parameters, padding and score bias; one query
    mission alone gives the same bits."""
    from hmrta.rl.model import Block

    torch.manual_seed(0)
    block = Block(32, 4, 16)
    B, Lq, Lk = 3, 7, (7 if self_attention else 5)
    q = torch.randn(B, Lq, 32)
    kv = q if self_attention else torch.randn(B, Lk, 32)
    ignore = torch.zeros(B, Lk, dtype=torch.bool)
    ignore[1, -2:] = True  # padding rows
    ignore[2, 0] = True
    bias = torch.randn(B * 4, Lq, Lk) if with_bias else None
    with torch.no_grad():
        got = block.attend(q, kv, ignore, bias)
        if bias is None:
            want = block.mha(q, kv, kv, key_padding_mask=ignore, need_weights=False)[0]
        else:
            masked = bias.masked_fill(ignore.repeat_interleave(4, 0)[:, None, :], float("-inf"))
            want = block.mha(q, kv, kv, attn_mask=masked, need_weights=False)[0]
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
        alone = block.attend(q[:1], q[:1] if self_attention else kv[:1], ignore[:1],
                             None if bias is None else bias[:4])
        block.train()  # the module's own (unfused) path
        ref = block.mha(q[:1], q[:1] if self_attention else kv[:1], q[:1] if self_attention else kv[:1],
                        key_padding_mask=None if bias is not None else ignore[:1],
                        attn_mask=None if bias is None else bias[:4].masked_fill(ignore[:1, None, :], float("-inf")),
                        need_weights=False)[0]
    assert torch.equal(alone, ref)


def test_decoder_layers_fold_keys_and_values_into_the_query():
    """Block.forward_one (the decoder's two layers: one query row, keys and values folded into
    the query) is the block's own forward in exact arithmetic: equal to float rounding, with
    padding and a masked prefix, and its gradients too (training runs it)."""
    from hmrta.rl.model import Block

    torch.manual_seed(1)
    block = Block(32, 4, None)
    with torch.no_grad():  # biases away from zero, so that dropping the key bias is tested
        block.mha.in_proj_bias.normal_()
    B, L = 3, 9
    q = torch.randn(B, 1, 32, requires_grad=True)
    kv = torch.randn(B, L, 32, requires_grad=True)
    ignore = torch.zeros(B, L, dtype=torch.bool)
    ignore[1, -3:] = True
    ignore[2, :4] = True
    got, want = block.forward_one(q, kv, ignore), block(q, kv, ignore)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    g_got = torch.autograd.grad(got.square().sum(), [q, kv, block.mha.in_proj_weight])
    g_want = torch.autograd.grad(want.square().sum(), [q, kv, block.mha.in_proj_weight])
    for a, b in zip(g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert torch.equal(g_got[1][1, -3:], torch.zeros(3, 32))  # padding rows get no gradient


def test_network_is_its_unfolded_definition(model):
    """The network's decoder and pointer, folded (Block.forward_one; (wk^T wq q) . x), against
    their definition written out: the blocks' own forward and wk applied to every task row."""
    from hmrta.rl.model import _masked_mean

    obs = batch_observations([MissionState(i, seed=0, rules=RULES) for i in _insts()])[0]
    net = model

    def unfolded(tasks, agents, task_valid, agent_valid, action_mask, decider):
        t_ign, a_ign = ~task_valid, ~agent_valid
        te = net.task_enc(*(2 * [net.task_embed(tasks)]), t_ign)
        ae = net.agent_enc(*(2 * [net.agent_embed(agents)]), a_ign)
        tx, ax = net.task_cross(te, ae, a_ign), net.agent_cross(ae, te, t_ign)
        me = ax[torch.arange(ax.shape[0]), decider]
        q = net.query(torch.cat([me, _masked_mean(tx, task_valid), _masked_mean(ax, agent_valid)], -1))
        q = net.dec1(q[:, None], torch.cat([tx, ax], 1), torch.cat([t_ign, a_ign], 1))
        q = net.dec2(q, tx, ~action_mask)
        compat = torch.einsum("bd,btd->bt", net.wq(q[:, 0]), net.wk(tx)) / math.sqrt(net.cfg.d_model)
        return (net.cfg.clip * torch.tanh(compat)).masked_fill(~action_mask, float("-inf"))

    with torch.no_grad():
        got, want = net(**obs), unfolded(**obs)
    assert torch.equal(torch.isfinite(got), obs["action_mask"]) and torch.equal(torch.isfinite(want), obs["action_mask"])
    m = obs["action_mask"]
    torch.testing.assert_close(got[m], want[m], rtol=1e-5, atol=1e-5)


def test_travel_bias_option(tmp_path):
    """model.travel_bias: with zero slopes the network computes exactly what it computed without
    the option (so older checkpoints resume into it); with slopes set it differs, keeps padding
    invariance and never lets a masked action through."""
    torch.manual_seed(0)
    plain = PolicyNet(SMALL).eval()
    biased = PolicyNet(ModelConfig(d_model=32, heads=4, ff_hidden=32, travel_bias=True)).eval()
    missing = biased.load_state_dict(plain.state_dict(), strict=False).missing_keys
    assert missing == ["travel_slope"]
    states = [MissionState(i, seed=5, rules=RULES) for i in _insts()]
    obs = batch_observations(states)[0]
    with torch.inference_mode():
        assert torch.equal(plain(**obs), biased(**obs))
        biased.travel_slope.copy_(torch.linspace(-1.0, 2.0, 8).reshape(2, 4))
        together = biased(**obs)
        assert not torch.equal(together, plain(**obs))
        assert torch.isneginf(together[~obs["action_mask"]]).all() and torch.isfinite(together[obs["action_mask"]]).all()
        for b, s in enumerate(states):
            alone = biased(**batch_observations([s])[0])[0]
            torch.testing.assert_close(together[b, :len(alone)], alone, rtol=1e-5, atol=1e-5)
    # a trainer with the option starts from a checkpoint without it (slopes at 0)
    FixedTrainer.fixed = _insts()[0]
    src = FixedTrainer(_tiny_cfg(), tmp_path / "a", device="cpu", log=lambda s: None)
    src.save(tmp_path / "a.pt")
    tr = FixedTrainer(_tiny_cfg(model={"travel_bias": True}), tmp_path / "b", device="cpu", log=lambda s: None)
    tr.load(tmp_path / "a.pt")
    assert torch.equal(tr.model.travel_slope, torch.zeros(2, 4))
    tr.train_step()  # and trains
    assert not torch.equal(tr.model.travel_slope, torch.zeros(2, 4))


def test_a_checkpoint_without_the_coalition_column_resumes_into_a_network_with_it(tmp_path):
    """A trainer observing "mission+coalition" starts from a "mission" checkpoint: the extra task
    input gets zero weights, so the logits are those of the checkpoint (the column is ignored) until
    it trains; the checkpoint's optimiser state and averaged weights are not taken."""
    FixedTrainer.fixed = _insts()[0]
    src = FixedTrainer(_tiny_cfg(model={"scale": "mission"}), tmp_path / "a", device="cpu", log=lambda s: None)
    src.train_step()
    src.save(tmp_path / "a.pt")
    tr = FixedTrainer(_tiny_cfg(model={"scale": "mission+coalition", "task_features": 16}), tmp_path / "b",
                      device="cpu", log=lambda s: None)
    tr.load(tmp_path / "a.pt")
    assert torch.equal(tr.model.task_embed.weight[:, -1], torch.zeros(tr.model.task_embed.weight.shape[0]))
    assert tr.ema is None and not tr.opt.state
    states = [MissionState(i, seed=5, rules=RULES) for i in _insts()]
    with torch.inference_mode():
        src.model.eval(), tr.model.eval()
        plain = src.model(**batch_observations(states, scale="mission")[0])
        widened = tr.model(**batch_observations(states, scale="mission+coalition")[0])
    torch.testing.assert_close(widened, plain, rtol=1e-5, atol=1e-5)
    tr.train_step()  # and trains, the new column too
    assert tr.model.task_embed.weight[:, -1].abs().sum() > 0


def test_batched_rollout_equals_core_simulator(model):
    insts = _insts()
    batched = [MissionState(i, seed=7, rules=RULES) for i in insts]
    rollout(model, batched, sample=False)
    pol = LoadedPolicy(model, {"rules": RULES.to_dict()}, "<memory>", {})
    for inst, b in zip(insts, batched):
        single = run(inst, RLDecider(pol, sample=False, seed=0), seed=7, rules=RULES)
        assert single.success and b.success
        assert single.routes == b.routes
        assert single.makespan == b.makespan
        np.testing.assert_array_equal(single.start, b.start)


@pytest.mark.parametrize("which", ["default", "broad", "coalition-team"])
def test_traced_inference_network_gives_the_networks_logits_bit_for_bit(which):
    """The traced, frozen network that inference runs (TracedPolicy) against the network itself:
    one graph for every window and batch size, every logit equal."""
    from hmrta.families import BroadGenerator
    from hmrta.rl.features import concat_batches
    from hmrta.rl.model import TracedPolicy

    pol = load_policy(None if which == "default" else DEFAULT_CHECKPOINT.with_name(f"{which}.pt"))
    net, rules, scale = pol.net, pol.rules, pol.net.cfg.scale
    assert isinstance(pol.model, TracedPolicy) and pol.model.net is net  # what inference runs
    traced = TracedPolicy(net)
    insts = [ScenarioGenerator("MA-AT", 30, 5, 60, 5).instance(3, 0), *_insts(),
             *(BroadGenerator(max_tasks=20).sample(np.random.default_rng(k)) for k in range(3))]
    batches = []
    for k, inst in enumerate(insts):
        st = MissionState(inst, seed=k, rules=rules)
        with torch.inference_mode():
            while not st.done:
                obs, nodes = batch_observations([st], scale=scale)
                batches.append(obs)
                st.step(int(nodes[0][int(net(**obs)[0].argmax())]))
    assert len({(b["tasks"].shape[1], b["agents"].shape[1]) for b in batches}) >= 3
    with torch.inference_mode():
        for b in batches[::3]:
            assert torch.equal(traced(**b), net(**b))
        for size in (10, 3):  # batches (sampling, lookahead branches): the same graph
            for lo in range(0, 30, size):
                joined = concat_batches(batches[lo:lo + size])
                assert torch.equal(traced(**joined), net(**joined))
    assert traced._graph is not None


def test_traced_inference_runs_a_travel_bias_network_as_it_is():
    from hmrta.rl.model import TracedPolicy

    torch.manual_seed(3)
    net = PolicyNet(ModelConfig(d_model=32, heads=4, ff_hidden=32, travel_bias=True)).eval()
    traced = TracedPolicy(net)
    obs = batch_observations([MissionState(i, seed=0, rules=RULES) for i in _insts()])[0]
    with torch.inference_mode():
        assert torch.equal(traced(**obs), net(**obs))
    assert traced._graph is None


def test_observation_window_on_large_missions(model):
    from hmrta.rl.features import observe

    inst = ScenarioGenerator("MA-AT", 30, 5, 60, 5).instance(3, 0)  # beyond 50 tasks / 25 agents
    st = MissionState(inst, seed=2, rules=Rules(max_open=None, safety=True))
    tf, af, mask, nodes, row = observe(st)
    full = st.mask()
    assert tf.shape == (51, 15) and af.shape == (25, 11) and nodes[0] == 0
    assert (full[nodes] == mask).all()  # rows map to the right nodes
    assert mask[1:].sum() == min(50, full[1:].sum())  # admissible tasks come first
    here = st.position(st.agent)
    d = np.hypot(*(inst.task_locations - here).T)
    inside = nodes[1:] - 1
    outside = np.setdiff1d(np.flatnonzero(full[1:]), inside)
    if len(outside):  # every admissible task left out is farther than every admissible one kept
        assert d[outside].min() >= d[inside[full[1:][inside]]].max()
    assert af[row, 8:10].tolist() == [0.0, 0.0]  # the decider sees itself at relative (0, 0)
    # windowed batched rollout == per-decision policy on the core simulator
    b = MissionState(inst, seed=2, rules=RULES)
    rollout(model, [b], sample=False)
    pol = LoadedPolicy(model, {"rules": RULES.to_dict()}, "<memory>", {})
    single = run(inst, RLDecider(pol, sample=False, seed=0), seed=2, rules=RULES)
    assert b.success and single.routes == b.routes and single.makespan == b.makespan


def test_lost_robot_has_no_skills_in_the_observation():
    from hmrta.rl.features import observe

    inst = _insts()[1]
    st = MissionState(inst, seed=1, rules=RULES)
    lost = (st.agent + 1) % inst.n_agents
    st.drop_agent(lost)
    tf, af, mask, nodes, row = observe(st)
    assert (af[lost, :5] == 0).all() and af[row, :5].any()


def test_greedy_rollouts_are_deterministic(model):
    inst = _insts()[1]
    a = [MissionState(inst, seed=1, rules=RULES) for _ in range(2)]
    rollout(model, a[:1], sample=False)
    rollout(model, a[1:], sample=False)
    assert a[0].routes == a[1].routes and a[0].makespan == a[1].makespan


class FixedTrainer(Trainer):
    """Trains on one fixed instance (to check that learning happens at all)."""

    fixed = None

    def _instances(self, n, task_range=None):
        return [self.fixed] * n


def _tiny_cfg(**over):
    cfg = deep_update(DEFAULTS, {
        "model": SMALL.to_dict(),
        "train": {"instances_per_iter": 2, "rollouts": 10, "lr": 3e-3, "amp": False, "rescore_chunk": 512},
        "validation": {"every": 1000, "rows": [[4, 2, 5, 2, 2]]},
    })
    return deep_update(cfg, over)


def test_tiny_training_run_improves(tmp_path):
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    tr = FixedTrainer(_tiny_cfg(), tmp_path, device="cpu", log=lambda s: None)
    rows = [tr.train_step() for _ in range(30)]
    first = np.mean([r["makespan"] for r in rows[:5]])
    last = np.mean([r["makespan"] for r in rows[-5:]])
    loss_first = -np.mean([r["reward"] for r in rows[:5]])  # expected cost of the sampled policy
    loss_last = -np.mean([r["reward"] for r in rows[-5:]])
    assert last < first, (first, last)
    assert loss_last < loss_first
    assert rows[-1]["entropy"] < rows[0]["entropy"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU that torch can use")
def test_every_training_phase_runs_with_the_network_on_a_gpu(tmp_path):
    """``hmrta train --device cuda``: observations are built on the CPU and every forward pass runs
    where the network is. Cloning (with DAgger and soft targets), lookahead distillation,
    REINFORCE with self-imitation, in-process validation, save and resume; greedy decoding on the
    GPU decides as on the CPU."""
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(pretrain={"iterations": 2, "instances_per_iter": 2, "lr": 3e-3, "epochs": 1, "batch": 64,
                              "teacher": "greedy-coalition", "dagger": 0.5, "tau": 0.5},
                    distill={"instances_per_iter": 2, "snapshot_prob": 0.5, "steps": 2, "batch": 64,
                             "buffer": 2, "lr": 3e-3},
                    train={"sil": {"coef": 1.0, "steps": 2, "batch": 64, "buffer": 2}, "ema": 0.9, "amp": True})
    tr = FixedTrainer(cfg, tmp_path, device="cuda", log=lambda s: None)
    assert next(tr.learner.model.parameters()).is_cuda
    rows = [tr.pretrain_step(), tr.distill_step(), tr.train_step(), tr.train_step()]
    assert all(np.isfinite(v) for r in rows for k, v in r.items() if "loss" in k)
    assert tr.validate()["val_success"] == 1.0
    tr.save(tmp_path / "last.pt")
    again = FixedTrainer(cfg, tmp_path, device="cuda", log=lambda s: None)  # a resume on the GPU
    again.load(tmp_path / "last.pt", same_run=True)
    assert np.isfinite(again.train_step()["loss"])
    cpu = Trainer(cfg, tmp_path / "cpu", device="cpu", log=lambda s: None)
    cpu.load(tmp_path / "last.pt")
    insts = ScenarioGenerator("MA-AT", 6, 2, 8, 3).generate(4, 11)
    on = {}
    for name, net in (("cuda", tr.eval_model()), ("cpu", cpu.eval_model())):
        states = [MissionState(i, seed=0, rules=RULES) for i in insts]
        rollout(net, states, sample=False)
        on[name] = [s.makespan for s in states]
    assert on["cuda"] == pytest.approx(on["cpu"])  # (random weights: no near-ties between logits)


def test_concatenated_batches_of_different_widths_score_as_each_alone(model):
    from hmrta.rl.features import concat_batches

    states = [MissionState(i, seed=5, rules=RULES) for i in _insts()]
    alone = [batch_observations([s])[0] for s in states]
    assert len({b["tasks"].shape[1] for b in alone}) > 1  # widths differ
    joined = concat_batches(alone)
    with torch.inference_mode():
        together = model(**joined)
        for b, obs in enumerate(alone):
            one = model(**obs)[0]
            torch.testing.assert_close(together[b, :len(one)], one, rtol=1e-5, atol=1e-5)
            assert torch.isneginf(together[b, len(one):]).all()


def test_reinforce_on_the_broad_distribution_with_relative_advantages(tmp_path):
    """Each iteration mixes missions of the broad generator (sizes, team shapes and time scales
    differ within one batch); relative advantages give every mission the same weight."""
    cfg = _tiny_cfg(train={"instances_per_iter": 3, "rollouts": 4, "advantage": "relative",
                           "distribution": {"generator": "broad", "tasks": [5, 12]}})
    tr = Trainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    insts = tr._instances(6)
    assert len({(i.n_agents, i.n_tasks, i.skills) for i in insts}) > 1
    assert all(5 <= i.n_tasks <= 12 for i in insts)
    before = [p.clone() for p in tr.learner.model.parameters()]
    rows = [tr.train_step() for _ in range(2)]
    assert all(np.isfinite(r["loss"]) and r["success"] == 1.0 for r in rows)
    assert any(not torch.equal(a, b) for a, b in zip(before, tr.learner.model.parameters()))


def test_the_mixed_distribution_draws_broad_paper_and_single_skill_missions(tmp_path):
    """generator: mixed: each mission from the broad generator, the paper's MA-AT distribution or
    the single-skill teams, over the task range; seeded by the run's seed."""
    cfg = _tiny_cfg(train={"distribution": {"generator": "mixed", "tasks": [5, 12], "skills": 3,
                                            "species": [2, 3], "per_species": [2, 2]}})
    insts = Trainer(cfg, tmp_path / "a", device="cpu", log=lambda s: None)._instances(30)
    kinds = [i.name.split("_")[0].split("-5-12")[0] for i in insts]
    assert set(kinds) == {"broad", "MA-AT", "single-skill"}
    assert all(5 <= i.n_tasks <= 12 for i in insts)
    for i, kind in zip(insts, kinds):
        if kind == "MA-AT":  # the distribution's team ranges and skills
            assert i.skills == 3 and i.n_species in (2, 3) and i.n_agents == 2 * i.n_species
        if kind == "single-skill":  # one skill per species
            assert (i.traits.sum(1) == 1).all() and i.skills == i.n_species
    again = Trainer(cfg, tmp_path / "b", device="cpu", log=lambda s: None)._instances(30)
    assert [i.to_dict() for i in again] == [i.to_dict() for i in insts]


def test_self_imitation_with_partial_rescoring_improves(tmp_path):
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(train={"rescore_fraction": 0.3, "sil": {"coef": 1.0, "steps": 2, "batch": 64, "buffer": 3}})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    rows = [tr.train_step() for _ in range(30)]
    assert len(tr.sil_buffer) == 3  # the last `buffer` iterations only
    for entry in tr.sil_buffer:  # replayed targets are admissible actions of the best rollouts
        assert entry["action_mask"].gather(1, entry["target"][:, None]).all()
    assert all(r["best_makespan"] <= r["makespan"] for r in rows)
    assert np.isfinite([r["sil_loss"] for r in rows]).all()
    first = np.mean([r["makespan"] for r in rows[:5]])
    last = np.mean([r["makespan"] for r in rows[-5:]])
    assert last < first, (first, last)
    assert rows[-1]["sil_loss"] < rows[0]["sil_loss"]


@pytest.mark.parametrize("tau,teacher", [(0.0, "policy"), (0.5, "policy"), (0.5, "greedy-coalition")])
def test_lookahead_distillation_targets_are_never_worse_and_learned(tmp_path, tau, teacher):
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(distill={"instances_per_iter": 2, "snapshot_prob": 0.5, "steps": 4, "batch": 64,
                             "buffer": 2, "lr": 3e-3, "tau": tau, "teacher": teacher})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)

    def argmax_makespan():  # mean over fixed decision-order seeds
        states = [MissionState(FixedTrainer.fixed, seed=s, rules=RULES) for s in range(8)]
        rollout(tr.model, states, sample=False)
        return np.mean([s.makespan for s in states])

    before = argmax_makespan()
    rows = [tr.distill_step() for _ in range(25)]
    assert tr.distill_done == 25 and len(tr.distill_buffer) == 2
    assert all(r["lookahead_gain"] >= 0 and r["labels"] > 0 for r in rows)  # targets never cost more
    for entry in tr.distill_buffer:  # target distributions over admissible actions only
        assert (entry["target"][~entry["action_mask"]] == 0).all()
        torch.testing.assert_close(entry["target"].sum(1), torch.ones(len(entry["target"])))
        assert ((entry["target"] == 1) | (entry["target"] == 0)).all() == (tau == 0)
    # the argmax rollout moves towards its own one-step lookahead improvement
    assert argmax_makespan() < before
    tr.save(tmp_path / "last.pt")
    t2 = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    t2.load(tmp_path / "last.pt")
    assert t2.distill_done == 25


@pytest.mark.parametrize("dagger,tau", [(0.0, 0.0), (1.0, 0.0), (0.5, 0.5)])
def test_behaviour_cloning_learns_the_coalition_teacher(tmp_path, dagger, tau):
    """BC of greedy-coalition, on the teacher's own trajectories or (DAgger) the policy's: the
    argmax policy agrees with the teacher more often afterwards."""
    from hmrta.baselines import CoalitionGreedy

    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(pretrain={"iterations": 12, "instances_per_iter": 2, "lr": 3e-3, "epochs": 2, "batch": 64,
                              "teacher": "greedy-coalition", "dagger": dagger, "tau": tau})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    teacher = CoalitionGreedy()
    before = _agreement(tr, teacher)
    rows = [tr.pretrain_step() for _ in range(12)]
    assert tr.pretrain_done == 12 and all(r["labels"] > 0 for r in rows)
    assert rows[-1]["bc_loss"] < rows[0]["bc_loss"]
    assert _agreement(tr, teacher) > before


def test_a_checkpoint_teachers_soft_targets_are_its_distribution_on_the_students_rows():
    """pretrain.tau > 0 with rl@CHECKPOINT: each target is the teacher's softmax(logits / tau) at
    that state, carried onto the rows the student observes (the same rows under the same window;
    a narrower student window keeps the shared rows, renormalised)."""
    from hmrta.rl.features import observe
    from hmrta.rl.imitation import soft_target
    from hmrta.rl.inference import CheckpointTeacher

    pol = load_policy("default")
    teacher = CheckpointTeacher(pol)
    inst = ScenarioGenerator("MA-AT", 20, 4, 120, 3).instance(3, 0)  # wider than a 50-task window
    st = MissionState(inst, seed=0, rules=pol.rules)
    checked = 0
    while not st.done and checked < 12:
        n = teacher(st)
        nodes, p = teacher.distribution(st, 1.0)
        assert abs(p.sum() - 1) < 1e-5
        best = int(np.argmax(p))  # the choice is the distribution's, decoded by the depot rule
        if pol.model.cfg.greedy_depot == "majority" and best == 0 and p[0] < 0.5 and p[1:].max() > 0:
            best = 1 + int(np.argmax(p[1:]))
        assert nodes[best] == n
        tf, af, mask, same, row = observe(st, **pol.model.cfg.view())
        r = int(np.flatnonzero(same == n)[0])
        q = soft_target(teacher, st, same, r, 1.0)
        assert np.array_equal(same, nodes) and np.allclose(q, p, atol=1e-6)
        assert (q[~mask] == 0).all()
        sharp = soft_target(teacher, st, same, r, 0.05)  # a lower temperature sharpens it
        assert sharp.max() >= q.max() - 1e-6
        narrow = observe(st, max_tasks=50, max_agents=25, scale=pol.model.cfg.scale)[3]  # [51]: the nearest of them
        assert np.isin(narrow, nodes).all()
        shared = p[np.searchsorted(nodes, narrow)]  # [51]
        assert np.allclose(soft_target(teacher, st, narrow, 0, 1.0), shared / shared.sum(), atol=1e-6)
        st.step(n)
        checked += 1
    assert checked == 12


def _agreement(tr, teacher) -> float:
    """The share of ``teacher``'s decisions, on its own trajectories of the fixed mission (four
    seeds), that the trainer's network copies by its argmax."""
    from hmrta.rl.features import collate, observe

    hits = total = 0
    for seed in range(4):
        st = MissionState(FixedTrainer.fixed, seed=seed, rules=RULES)
        while not st.done:
            tf, af, mask, nodes, row = observe(st)
            with torch.inference_mode():
                mine = int(nodes[int(tr.model.eval()(**collate([(tf, af, mask)], [row])).argmax())])
            n = teacher(st)
            hits, total = hits + (mine == n), total + 1
            st.step(n)
    return hits / total


@pytest.mark.parametrize("tau", [0.0, 1.0])
def test_a_checkpoint_teacher_labels_its_greedy_decoding_and_is_learned(tmp_path, tau):
    """pretrain.teacher: rl@CHECKPOINT (distilling a trained policy, e.g. into a narrower network):
    its label jobs drive a mission as ``hmrta solve --method rl`` with that checkpoint does, every
    decision labelled, and a student's agreement with it grows."""
    from pathlib import Path

    from hmrta.rl.imitation import LabelJob, make_teacher, resolved_teacher, teacher_labels
    from hmrta.rl.inference import solve_rl
    from hmrta.solution import solution_from_state

    pol = load_policy("default")
    name = resolved_teacher("rl@default")
    assert name == f"rl@{Path(pol.path).resolve()}"  # the file Ray workers read, wherever they run
    inst = ScenarioGenerator("MA-AT", 6, 2, 12, 3).instance(7, 0)
    done = teacher_labels(LabelJob(inst, None, 0, pol.rules, name, 0.0, SMALL.view()))
    assert solution_from_state(done.state, "rl", 0, 0.0).routes == solve_rl(inst, 0, "default").routes
    assert len(done.labels.acts) == done.state.decisions

    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(pretrain={"iterations": 10, "instances_per_iter": 2, "lr": 3e-3, "epochs": 2, "batch": 64,
                              "teacher": "rl@default", "dagger": 0.5, "tau": tau})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    teacher = make_teacher(name)
    before = _agreement(tr, teacher)
    rows = [tr.pretrain_step() for _ in range(10)]
    assert all(r["labels"] > 0 for r in rows) and rows[-1]["bc_loss"] < rows[0]["bc_loss"]
    assert _agreement(tr, teacher) > before
    # the teacher is in the lineage once, by its file and sha256 (hmrta checkpoint info shows it)
    from hmrta.rl.checkpoint_info import lineage_lines

    assert [e["op"] for e in tr.lineage] == ["teacher"]
    assert tr.lineage[0]["sources"][0]["sha256"] == pol.sha256
    assert lineage_lines(tr.lineage)[0] == "taught by"


def _farthest_labels(inst):
    """A poor but valid teacher's labelled trajectory: always the farthest admissible task.
    Returns (observations, deciders, actions, the finished state)."""
    from hmrta.rl.features import observe

    def farthest(st):
        cand = np.flatnonzero(st.mask()[1:])
        if len(cand) == 0:
            return 0
        d = np.hypot(*(inst.task_locations[cand] - st.positions()[st.agent]).T)
        return 1 + int(cand[np.argmax(d)])

    obs, deciders, acts = [], [], []
    st = MissionState(inst, seed=0, rules=RULES)
    while not st.done:
        tf, af, mask, nodes, row = observe(st)
        obs.append((tf, af, mask)), deciders.append(row)
        acts.append(farthest(st))  # (no observation window: row = node)
        st.step(acts[-1])
    return obs, deciders, acts, st


def test_expert_iteration_ranks_the_pool_by_makespan_or_return(tmp_path):
    """pretrain.select: ``makespan`` clones the sample of the shortest makespan; ``return``
    (-T - W) the sample of the best return, here another one (the same six samples both times)."""
    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 1)
    FixedTrainer.fixed = inst
    cfg = _tiny_cfg(pretrain={"iterations": 1, "instances_per_iter": 1, "teacher": "greedy-coalition",
                              "samples": 6, "temperature": 1.0, "select": "makespan"})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    tr.model.eval()
    picked = {}
    for select in ("return", "makespan"):
        tr.cfg.pretrain.select = select
        tr.learner.torch_gen.manual_seed(0)  # a draw where the two rankings disagree
        obs, deciders, acts, st = _farthest_labels(inst)
        stats = tr._pool([(st, 0, len(acts))], obs, deciders, acts)
        assert stats["teacher_wins"] == 0.0
        picked[select] = stats["pool_makespan"]
    tr.learner.torch_gen.manual_seed(0)
    states = [MissionState(inst, seed=0, rules=RULES) for _ in range(6)]
    rollout(tr.model, states, sample=True, generator=tr.learner.torch_gen, record=True, amp=False, temperature=1.0)
    mk = np.array([s.makespan for s in states])
    best_return = mk[np.argmax(returns(states, tr.cfg.train.t_max))]
    assert picked["makespan"] == pytest.approx(mk.min()) and picked["return"] == pytest.approx(best_return)
    assert mk.min() < best_return


def test_self_improvement_clones_only_samples_that_beat_the_greedy_decoding(tmp_path):
    """pretrain.generated_teacher: policy: the policy's greedy decoding is the trajectory to beat
    and labels nothing itself. Samples that only repeat it (temperature near 0) teach nothing and
    leave the weights as they are; samples that beat it are cloned."""
    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    FixedTrainer.fixed = inst
    cfg = _tiny_cfg(pretrain={"iterations": 2, "instances_per_iter": 3, "lr": 3e-3, "epochs": 1, "batch": 64,
                              "teacher": "greedy-coalition", "samples": 6, "temperature": 1e-3,
                              "generated_teacher": "policy", "select": "makespan"})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    start = {k: v.clone() for k, v in tr.model.state_dict().items()}
    row = tr.pretrain_step()
    assert row["labels"] == 0 and row["teacher_wins"] == 1.0 and "bc_loss" not in row
    assert all(torch.equal(v, start[k]) for k, v in tr.model.state_dict().items())
    tr.cfg.pretrain.temperature = 1.0
    row = tr.pretrain_step()
    assert row["teacher_wins"] < 1.0 and row["labels"] > 0 and row["pool_makespan"] < row["teacher_makespan"]
    with pytest.raises(ValueError, match="generated_teacher: policy needs policy samples"):
        FixedTrainer(_tiny_cfg(pretrain={"generated_teacher": "policy"}), tmp_path / "b", device="cpu",
                     log=lambda s: None)


def test_expert_iteration_clones_the_best_of_teacher_and_samples(tmp_path):
    """pretrain.samples: where a policy sample beats the teacher's trajectory, that sample's own
    decisions replace the teacher's labels (replaying them reproduces the sample's schedule);
    where the teacher wins, its labels stay; and the phase runs end to end."""
    from hmrta.rl.features import observe

    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    FixedTrainer.fixed = inst
    cfg = _tiny_cfg(pretrain={"iterations": 4, "instances_per_iter": 2, "lr": 3e-3, "epochs": 1, "batch": 64,
                              "teacher": "greedy-coalition", "samples": 6, "temperature": 1.0})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    obs, deciders, acts, st = _farthest_labels(inst)
    teacher_labels = list(acts)
    n = len(acts)
    other = ("dagger-obs", 0, 7)  # labels of other instances (e.g. DAgger's) after the pooled range stay
    obs.append(other[0]), deciders.append(other[1]), acts.append(other[2])
    stats = tr._pool([(st, 0, n)], obs, deciders, acts)
    assert stats["teacher_wins"] == 0.0 and stats["pool_makespan"] < stats["teacher_makespan"] == st.makespan
    assert (obs[0], deciders[0], acts[0]) == other
    obs, deciders, acts = obs[1:], deciders[1:], acts[1:]
    assert acts != teacher_labels and len(acts) == len(obs) == len(deciders)
    replay = MissionState(inst, seed=0, rules=RULES)
    for (tf, af, mask), row, a in zip(obs, deciders, acts):
        assert mask[a] and np.allclose(observe(replay)[0], tf) and observe(replay)[4] == row
        replay.step(a)
    assert replay.done and replay.makespan == pytest.approx(stats["pool_makespan"])

    # a teacher no sample beats keeps its labels: here the policy's own argmax trajectory against
    # near-argmax samples (temperature 1e-3), which tie with it
    own = MissionState(inst, seed=0, rules=RULES)
    rollout(tr.model.eval(), [own], sample=False)
    tr.cfg.pretrain.temperature = 1e-3
    labels = [0, 1, 2]
    kept = tr._pool([(own, 0, 3)], [None] * 3, [0] * 3, labels)
    assert kept["teacher_wins"] == 1.0 and labels == [0, 1, 2]
    tr.cfg.pretrain.temperature = 1.0

    rows = [tr.pretrain_step() for _ in range(4)]
    assert tr.pretrain_done == 4 and all(r["labels"] > 0 and 0 <= r["teacher_wins"] <= 1 for r in rows)


def test_weight_averaging_is_validated_checkpointed_and_shipped(tmp_path):
    """train.ema: a moving average of the weights follows every update; validation scores it, it
    survives save/load, export ships it, and load_policy uses it from a training checkpoint."""
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(5, 3)
    cfg = _tiny_cfg(train={"ema": 0.9},
                    pretrain={"iterations": 3, "instances_per_iter": 2, "lr": 3e-3, "epochs": 1, "batch": 64,
                              "teacher": "greedy-coalition"})
    tr = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    start = {k: v.clone() for k, v in tr.model.state_dict().items()}
    for _ in range(3):
        tr.pretrain_step()
    raw = {k: v.clone() for k, v in tr.model.state_dict().items()}
    k = next(k for k, v in raw.items() if v.is_floating_point() and not torch.equal(v, start[k]))
    assert not torch.equal(tr.ema[k], raw[k]) and not torch.equal(tr.ema[k], start[k])
    assert torch.equal(tr.eval_model().state_dict()[k], tr.ema[k])
    assert torch.equal(tr.model.state_dict()[k], raw[k])  # evaluating never touches the trained weights

    tr.save(tmp_path / "last.pt")
    t2 = FixedTrainer(cfg, tmp_path, device="cpu", log=lambda s: None)
    t2.load(tmp_path / "last.pt")
    assert torch.equal(t2.ema[k], tr.ema[k]) and torch.equal(t2.model.state_dict()[k], raw[k])
    tr.export(tmp_path / "shipped.pt")
    for ck in ("shipped.pt", "last.pt"):
        assert torch.equal(load_policy(tmp_path / ck).net.state_dict()[k], tr.ema[k])
    off = FixedTrainer(_tiny_cfg(), tmp_path / "off", device="cpu", log=lambda s: None)
    off.pretrain_step() if off.cfg.pretrain.iterations else off.train_step()
    assert off.ema is None and off.eval_model() is off.model


def test_checkpoint_round_trip_and_resume(tmp_path):
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    ref = FixedTrainer(_tiny_cfg(), tmp_path / "a", device="cpu")
    for _ in range(3):
        ref.train_step()
    t1 = FixedTrainer(_tiny_cfg(), tmp_path / "b", device="cpu")
    for _ in range(2):
        t1.train_step()
    t1.save(tmp_path / "b" / "last.pt")
    t2 = FixedTrainer(_tiny_cfg(), tmp_path / "b", device="cpu")
    t2.load(tmp_path / "b" / "last.pt")
    assert t2.iteration == 2 and t2.episodes == t1.episodes
    t2.train_step()
    for (k, v), (k2, v2) in zip(ref.model.state_dict().items(), t2.model.state_dict().items()):
        torch.testing.assert_close(v, v2, msg=k)
    # export -> load_policy round trip
    t2.export(tmp_path / "small.pt")
    pol = load_policy(tmp_path / "small.pt")
    assert pol.config["model"]["d_model"] == 32 and pol.rules == Rules(max_open=2, safety=True)


def test_train_cli_rejects_init_or_reseed_without_resume(tmp_path, capsys):
    from hmrta.cli import main

    for extra in (["--reseed"], ["--init", str(tmp_path / "x.pt")]):
        assert main(["train", "--run-dir", str(tmp_path / "run"), *extra]) == 2
        assert "only apply with --resume" in capsys.readouterr().err
    assert main(["train", "--run-dir", str(tmp_path / "run"), "--jobs", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--jobs: expected a positive integer" in err[0]
    assert not (tmp_path / "run").exists()


def test_train_finds_the_shipped_configs_by_name_from_any_directory(tmp_path, monkeypatch, capsys):
    """The training configs ship with the package (hmrta/configs): the default and any other by
    its name work outside a checkout too; a file of that name in the working directory wins."""
    from hmrta.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["train", "--check"]) == 0
    assert "a valid training config (name 'default')" in capsys.readouterr().out
    assert main(["train", "--config", "coalition-team", "--check"]) == 0
    assert "(name 'coalition-team')" in capsys.readouterr().out
    (tmp_path / "default").write_text("name: mine\n")
    assert main(["train", "--check"]) == 0
    assert "(name 'mine')" in capsys.readouterr().out
    assert main(["train", "--config", "nosuch", "--check"]) == 2
    capsys.readouterr()
    # --check checks the command line as the run would: --init without --resume, nothing to resume
    assert main(["train", "--check", "--init", "x.pt"]) == 2
    assert "--init and --reseed only apply with --resume" in capsys.readouterr().err
    assert main(["train", "--check", "--resume"]) == 2
    assert "--resume: no checkpoint runs/mine/last.pt to continue" in capsys.readouterr().err
    # a dataset a config names is looked for before anything is written (from here: relative paths miss)
    assert main(["train", "--config", "schedules", "--check"]) == 2
    assert "pretrain.schedules: policy/datasets/" in capsys.readouterr().err
    assert main(["train", "--config", "schedules", "--run-dir", str(tmp_path / "run")]) == 2
    assert not (tmp_path / "run").exists()
    # so is a checkpoint to distil (pretrain.teacher: rl@CHECKPOINT)
    (tmp_path / "distil.yaml").write_text("version: 1\npretrain: {iterations: 1, teacher: rl@nosuch.pt}\n")
    assert main(["train", "--config", "distil.yaml", "--run-dir", str(tmp_path / "run")]) == 2
    assert "distil.yaml: pretrain.teacher: nosuch.pt: no such checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_continuation_under_another_validation_set_or_rules_needs_reseed(tmp_path, capsys):
    """A resumed run keeps the checkpoint's best validation score, so it is refused (naming the
    key, the state untouched) when the config scores it on another validation set or under other
    rules; --reseed forgets the score and goes on. How often validation runs may change."""
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    t1 = FixedTrainer(_tiny_cfg(), tmp_path / "a", device="cpu", log=lambda s: None)
    t1.train_step()
    t1.best_val = 12.5
    t1.save(tmp_path / "a" / "last.pt")
    for over, key in (({"validation": {"rows": [[4, 2, 6, 2, 2]]}}, "validation.rows"),
                      ({"validation": {"seed": 5}}, "validation.seed"),
                      ({"rules": {"max_open": None}}, "rules.max_open")):
        t2 = FixedTrainer(_tiny_cfg(**over), tmp_path / "b", device="cpu", log=lambda s: None)
        before = {k: v.clone() for k, v in t2.model.state_dict().items()}
        with pytest.raises(CheckpointError, match=re.escape(key) + ".*pass --reseed"):
            t2.load(tmp_path / "a" / "last.pt")
        assert t2.iteration == 0 and all(torch.equal(v, before[k]) for k, v in t2.model.state_dict().items())
        t2.load(tmp_path / "a" / "last.pt", reseed=True)
        assert t2.iteration == 1 and t2.best_val == math.inf
    t3 = FixedTrainer(_tiny_cfg(validation={"every": 7}), tmp_path / "c", device="cpu", log=lambda s: None)
    t3.load(tmp_path / "a" / "last.pt")
    assert t3.best_val == 12.5


def test_reseeded_resume_keeps_weights_but_not_the_random_streams(tmp_path):
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    t1 = FixedTrainer(_tiny_cfg(), tmp_path / "a", device="cpu", log=lambda s: None)
    t1.train_step()
    t1.best_val = 12.5
    t1.save(tmp_path / "a" / "last.pt")
    same = FixedTrainer(_tiny_cfg(), tmp_path / "b", device="cpu", log=lambda s: None)
    same.load(tmp_path / "a" / "last.pt")
    cfg = _tiny_cfg()
    cfg["seed"] = 99
    new = FixedTrainer(cfg, tmp_path / "c", device="cpu", log=lambda s: None)
    new.load(tmp_path / "a" / "last.pt", reseed=True)
    fresh = np.random.default_rng(99).integers(2**31, size=4)
    for k, v in t1.model.state_dict().items():
        assert torch.equal(new.model.state_dict()[k], v) and torch.equal(same.model.state_dict()[k], v)
    assert new.iteration == same.iteration == 1 and new.episodes == t1.episodes
    assert same.best_val == 12.5 and new.best_val == math.inf
    assert np.array_equal(new.np_rng.integers(2**31, size=4), fresh)
    assert np.array_equal(same.np_rng.integers(2**31, size=4), t1.np_rng.integers(2**31, size=4))


def test_mismatching_checkpoint_is_a_clear_error(tmp_path):
    tr = Trainer(_tiny_cfg(), tmp_path, device="cpu")
    tr.export(tmp_path / "ok.pt")
    ck = torch.load(tmp_path / "ok.pt", weights_only=True)
    bad = copy.deepcopy(ck)
    bad["config"]["model"]["d_model"] = 64
    torch.save(bad, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="do not match"):
        load_policy(tmp_path / "bad.pt")
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_policy(tmp_path / "junk.pt")
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_policy(tmp_path / "missing.pt")
    bad = copy.deepcopy(ck)
    bad["config"]["rules"]["max_open"] = "teams"
    torch.save(bad, tmp_path / "rules.pt")
    with pytest.raises(CheckpointError, match=re.escape("rules.max_open: expected a positive integer, null")):
        load_policy(tmp_path / "rules.pt")


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.exists(), reason="no shipped checkpoint")
def test_shipped_checkpoint_solves():
    from hmrta.methods import solve

    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(4242, 0)
    g = solve(inst, "rl", seed=0)
    s = solve(inst, "rl-s4", seed=0)
    assert g.success and s.success and s.extra["samples"] == 4
    from hmrta.solution import evaluate_routes

    for sol in (g, s):
        assert evaluate_routes(inst, sol.routes).makespan <= sol.makespan + 1e-9
    # the solution names the checkpoint that planned it
    from hmrta.rl.checkpoint_info import checkpoint_path, sha256

    assert g.extra["checkpoint"] == {"path": str(DEFAULT_CHECKPOINT), "sha256": sha256(DEFAULT_CHECKPOINT)}
    b = solve(inst, "rl", seed=0, checkpoint="broad").to_dict()["checkpoint"]
    assert b["path"] == str(checkpoint_path("broad")) and b["sha256"] == sha256(checkpoint_path("broad"))


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.exists(), reason="no shipped checkpoint")
def test_sampling_temperature_is_the_same_live_and_offline():
    """A live sampled agent and a sampled rollout of one mission, same seed and temperature, make
    the same choices; the temperature changes them (so both paths apply it)."""
    pol = load_policy(None)
    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(4242, 0)
    seen = {}
    for t in (1.0, 0.3):
        offline = MissionState(inst, seed=0, rules=pol.rules)
        rollout(pol.model, [offline], sample=True, generator=torch.Generator().manual_seed(5), temperature=t)
        decide, live = RLDecider(pol, True, 5, t), MissionState(inst, seed=0, rules=pol.rules)
        while not live.done:
            live.step(decide(live))
        assert live.routes == offline.routes and live.makespan == offline.makespan
        seen[t] = offline.makespan
    assert seen[1.0] != seen[0.3]
    with pytest.raises(MethodError, match="temperature: expected a positive number"):
        RLDecider(pol, True, 5, 0.0)


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.exists(), reason="no shipped checkpoint")
def test_rl_sample_temperature_option():
    from hmrta.methods import SAMPLE_TEMPERATURE, decider, solve

    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(4242, 0)
    assert solve(inst, "rl-s2", seed=0).extra["temperature"] == SAMPLE_TEMPERATURE
    assert solve(inst, "rl-s2", seed=0, temperature=0.5).extra["temperature"] == 0.5
    assert decider("rl-sample", temperature=0.5)[0].temperature == 0.5
    with pytest.raises(MethodError, match="rl-sample: option temperature: expected a number >= 0.01"):
        solve(inst, "rl-s2", temperature=0)


CHECKPOINTS = [("default.pt", None), ("coalition-open.pt", None), ("broad.pt", None), ("coalition-team.pt", "team"),
               ("compact.pt", None)]


@pytest.mark.parametrize("name,max_open", CHECKPOINTS)
def test_shipped_checkpoints_run_under_their_own_max_open_rule(name, max_open):
    from hmrta.core import OPEN, team_cap
    from hmrta.methods import decider, solve
    from hmrta.solution import evaluate_routes

    path = DEFAULT_CHECKPOINT.with_name(name)
    if not path.exists():
        pytest.skip(f"no checkpoint {name}")
    pol = load_policy(path)
    assert pol.rules == Rules(max_open=max_open, safety=True)
    inst = ScenarioGenerator("MA-AT", 25, 5, 50, 5).instance(4242, 0)
    sol = solve(inst, "rl", seed=0, checkpoint=str(path))
    assert sol.success and evaluate_routes(inst, sol.routes).makespan <= sol.makespan + 1e-9
    state = MissionState(inst, seed=0, rules=pol.rules)
    rollout(pol.model, [state], sample=False)
    assert state.success and state.makespan == pytest.approx(sol.makespan)

    decide, rules = decider("rl", checkpoint=str(path))
    opened = []

    def watch(st):  # the number of open tasks at each decision
        opened.append(int((st.status == OPEN).sum()))
        return decide(st)

    live = run(inst, watch, 0, rules)
    assert live.makespan == pytest.approx(sol.makespan)
    assert max(opened) > 2  # more open tasks at once than greedy's max_open = 2
    if max_open == "team":
        assert team_cap(inst) > 2 and max(opened) <= team_cap(inst)


def test_lookahead_is_never_worse_than_its_policy(model):
    from hmrta.rl.inference import lookahead_step

    for inst in _insts():
        base = MissionState(inst, seed=3, rules=RULES)
        rollout(model, [base], sample=False)
        la = MissionState(inst, seed=3, rules=RULES)
        while not la.done:
            lookahead_step(model, [la])
        assert la.success
        assert -returns([la], 1000.0)[0] <= -returns([base], 1000.0)[0] + 1e-6  # cost T + W


def test_shipped_checkpoint_lookahead_method_and_decider():
    from hmrta.methods import decider, solve

    inst = ScenarioGenerator("MA-AT", 6, 2, 8, 3).instance(4242, 1)
    la = solve(inst, "rl-lookahead", seed=0)
    rl = solve(inst, "rl", seed=0)
    assert la.success and la.method == "rl-lookahead"
    assert la.makespan + la.redundancy <= rl.makespan + rl.redundancy + 1e-6
    decide, rules = decider("rl-lookahead")  # the live agents' per-decision form: same schedule
    live = run(inst, decide, 0, rules)
    assert live.routes == la.routes and live.makespan == la.makespan


@pytest.mark.parametrize("text,message", [
    ("version: 1\ntrain: {rollout: 3}\n", "unknown key 'train.rollout'"),
    ("version: 1\ndistill: {tau: 0.5, taus: 1}\n", "unknown key 'distill.taus'"),
    ("version: 1\nvalidaton: {every: 3}\n", "unknown key 'validaton'"),
    ("version: 1\npretrain: {teacher: oracle}\n", "pretrain.teacher: expected one of greedy, greedy-coalition"),
    ("version: 1\npretrain: {dagger: 2}\n", "pretrain.dagger: expected a share in [0, 1]"),
    ("version: 1\npretrain: {tau: 1}\n", "pretrain.tau: soft targets need a teacher with start estimates"),
    ("version: 1\npretrain: {teacher: [rl@default]}\n", "pretrain.teacher: expected one of greedy, greedy-coalition"),
    ("version: 1\npretrain: {teacher: 'rl@'}\n", "or rl@CHECKPOINT (a shipped checkpoint's name or a path), got 'rl@'"),
    ("version: 1\npretrain: {samples: -1}\n", "pretrain.samples: expected an integer >= 0"),
    ("version: 1\npretrain: {samples: 4, select: regret}\n", "pretrain.select: expected return or makespan"),
    ("version: 1\ntrain: {ema: 1.0}\n", "train.ema: expected a decay in [0, 1)"),
    ("version: 1\npretrain: {samples: 4, temperature: 0}\n", "pretrain.temperature: expected a number in (0, inf)"),
    ("version: 1\npretrain: {teacher: greedy-coalition, samples: 4, tau: 0.5}\n", "pretrain.samples needs hard targets"),
    ("version: 1\ndistill: {teacher: cpsat}\n", "distill.teacher: expected one of policy, greedy, greedy-coalition"),
    ("version: 1\ntrain: 3\n", "train: expected a mapping"),
    ("version: 1\nrules: {max_open: teams}\n", "rules.max_open: expected a positive integer, null (no limit) or 'team'"),
    ("version: 1\nrules: {max_open: 0}\n", "rules.max_open: expected a positive integer"),
    ("version: 1\ntrain: {distribution: {generator: paper}}\n", "train.distribution.generator: expected ma-at, broad or mixed"),
    ("version: 1\ntrain: {distribution: {team_scale: [1, 3]}}\n", "train.distribution.team_scale: grows the teams of broad missions only"),
    ("version: 1\ntrain: {advantage: scaled}\n", "train.advantage: expected raw or relative"),
    ("version: 2\n", "version: expected 1"),
    ("[1, 2]\n", "expected a mapping"),
    ("", "empty (expected a training config"),
    ("# settings to come\n", "empty (expected a training config"),
])
def test_config_errors_name_the_key(tmp_path, text, message):
    from hmrta.rl.train import load_config

    f = tmp_path / "c.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=re.escape(message)):
        load_config(f)


def test_one_rollout_is_refused_where_reinforce_runs(tmp_path, capsys):
    """REINFORCE's baseline is the mean return of a mission's rollouts: with one rollout every
    advantage is 0 and nothing is learned. A config without REINFORCE iterations may keep one."""
    from hmrta.cli import main
    from hmrta.rl.train import load_config

    one = tmp_path / "one.yaml"
    one.write_text("version: 1\ntrain: {rollouts: 1}\n")
    assert main(["train", "--config", str(one), "--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{one}: train.rollouts: expected at least 2 when train.iterations > 0, got 1 " \
                              f"(REINFORCE's baseline is the mean return" in err[0], err
    bc = tmp_path / "bc.yaml"
    bc.write_text("version: 1\ntrain: {rollouts: 1, iterations: 0}\n")
    assert load_config(bc)["train"]["rollouts"] == 1
    assert main(["train", "--config", str(bc), "--check"]) == 0
    # the command line's values are checked with the file's, and the message says which were given
    assert main(["train", "--config", str(bc), "--check", "--iterations", "1234567"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bc} (with --iterations 1234567): train.rollouts: expected at least 2" in err[0], err
    assert main(["train", "--config", str(one), "--check", "--iterations", "0", "--max-minutes", "1.5"]) == 0


def test_shipped_configs_load():
    from pathlib import Path

    from hmrta.rl.train import load_config

    configs = sorted((Path(__file__).resolve().parents[3] / "policy" / "configs").glob("*.yaml"))
    assert configs
    for c in configs:
        load_config(c)


def test_soft_bc_targets_follow_the_teachers_estimates():
    from hmrta.baselines import CoalitionGreedy
    from hmrta.rl.features import observe

    inst = ScenarioGenerator("MA-AT", 9, 3, 20, 3).instance(7, 0)
    st = MissionState(inst, seed=0, rules=RULES)
    teacher = CoalitionGreedy()
    checked = 0
    while not st.done:
        tf, af, mask, nodes, row = observe(st)
        n = teacher(st)
        r = int(np.flatnonzero(nodes == n)[0])
        q = Trainer._soft_target(teacher, st, nodes, r, 0.5)
        assert abs(q.sum() - 1) < 1e-5 and (q[~mask] == 0).all() and q.argmax() == r
        cand, start, _ = teacher.estimates(st)
        if mask.sum() > 1 and np.isfinite(start).sum() > 1:  # later estimates weigh less
            later = [int(np.flatnonzero(nodes == 1 + j)[0]) for j, s_ in zip(cand, start) if s_ > start.min() + 1]
            assert all(q[k] < q[r] for k in later)
            checked += 1
        st.step(n)
    assert checked > 5


def _every_phase_cfg():
    return deep_update(DEFAULTS, {
        "model": {"d_model": 16, "heads": 2, "ff_hidden": 16},
        "train": {"iterations": 2, "instances_per_iter": 2, "rollouts": 3, "lr": 3e-3, "amp": False, "ema": 0.9,
                  "rescore_fraction": 0.5, "sil": {"coef": 0.5, "steps": 1, "batch": 32, "buffer": 2},
                  "distribution": {"tasks": [4, 6], "species": [2, 2], "per_species": [2, 2], "skills": 3}},
        "pretrain": {"iterations": 2, "instances_per_iter": 2, "epochs": 1, "batch": 32,
                     "teacher": "greedy-coalition", "dagger": 0.5, "samples": 2},
        "distill": {"iterations": 2, "instances_per_iter": 2, "snapshot_prob": 0.5, "steps": 2, "batch": 32,
                    "tau": 0.5},
        "validation": {"every": 2, "rows": [[4, 2, 5, 2, 2]]},
        "checkpoint": {"every": 1},
    })


def test_seeded_run_of_every_phase_reproduces_its_recorded_values(tmp_path):
    """A seeded two-iteration run of every phase (BC with DAgger and expert iteration, lookahead
    distillation, REINFORCE with partial re-scoring and self-imitation, EMA, validation and
    checkpoints) gives the losses and weights recorded for it: the training code may be reshaped,
    its results may not change."""
    import csv

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        tr = Trainer(_every_phase_cfg(), tmp_path / "run", device="cpu", log=lambda s: None)
        res = tr.run(progress=False)
    finally:
        torch.set_num_threads(n)
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    got = [(r["phase"], int(r["iteration"]), float(r["bc_loss"] or r["loss"] or r["val_makespan"]),
            float(r["sil_loss"] or "nan"), int(r["labels"] or -1)) for r in rows]
    nan = math.nan
    want = [("bc", 1, 1.8015784621238708, nan, 46), ("bc", 2, 1.4033966064453125, nan, 28),
            ("val", 2, 24.369571318417815, nan, -1),
            ("distill", 1, 1.62417334318161, nan, 14), ("distill", 2, 1.4130224585533142, nan, 9),
            ("val", 2, 24.369571318417815, nan, -1),
            ("rl", 1, -0.42113640904426575, 0.7628831267356873, -1), ("rl", 2, 10.0768461227417, 0.8291908502578735, -1),
            ("val", 2, 26.108525443933438, nan, -1)]
    assert [(p, i, lab) for p, i, _, _, lab in got] == [(p, i, lab) for p, i, _, _, lab in want]
    for g, w in zip(got, want):
        assert g[2] == pytest.approx(w[2], rel=1e-5, abs=1e-6), (g, w)
        assert (math.isnan(g[3]) and math.isnan(w[3])) or g[3] == pytest.approx(w[3], rel=1e-5), (g, w)
    assert res["episodes"] == 98 and res["best_val"] == pytest.approx(24.369571318417815)
    assert res["greedy_val"] == pytest.approx(23.549595311821527)
    wsum = float(sum(v.double().abs().sum() for v in tr.model.state_dict().values()))
    esum = float(sum(v.double().abs().sum() for v in tr.ema.values()))
    assert wsum == pytest.approx(1641.945950626381, rel=1e-6) and esum == pytest.approx(1641.4687872076267, rel=1e-6)
    # what a run writes is read like a shipped checkpoint: its description, its rules, a solve
    from hmrta.methods import rules, solve
    from hmrta.rl.checkpoint_info import describe

    inst = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(0, 0)
    for name in ("best.pt", "last.pt"):
        path = tmp_path / "run" / name
        d = describe(path)
        assert d["weights"] == ["model", "ema"] and d["config"]["model"]["d_model"] == 16
        assert 0 < d["episodes"] <= 98 and (d["episodes"] == 98) == (name == "last.pt")
        assert rules("rl", checkpoint=str(path)) is not None
        assert solve(inst, "rl", 0, checkpoint=str(path)).success


def _exported(tmp_path, name, seed=0, **over):
    cfg = _tiny_cfg(**over)
    cfg["seed"] = seed
    tr = Trainer(cfg, tmp_path / name, device="cpu", log=lambda s: None)
    path = tmp_path / f"{name}.pt"
    tr.export(path)
    return path, {k: v.clone() for k, v in tr.model.state_dict().items()}


def test_checkpoint_average_of_itself_and_of_two(tmp_path, capsys):
    import hashlib

    from hmrta.cli import main
    from hmrta.methods import solve
    from hmrta.rl.checkpoint import FORMAT_VERSION, average, load

    a, wa = _exported(tmp_path, "a", seed=1)
    b, wb = _exported(tmp_path, "b", seed=2)
    assert any(not torch.equal(wa[k], wb[k]) for k in wa)
    entry = average([a, a], tmp_path / "aa.pt")  # with itself: the same weights, bit for bit
    aa = load(tmp_path / "aa.pt")
    assert all(torch.equal(aa["model"][k], wa[k]) for k in wa)
    assert aa["checkpoint_format"] == FORMAT_VERSION and aa["config"] == load(a)["config"]
    sha = hashlib.sha256(a.read_bytes()).hexdigest()
    assert [s["sha256"] for s in entry["sources"]] == [sha, sha] and aa["lineage"] == [entry]
    assert main(["checkpoint", "average", str(a), str(b), "--out", str(tmp_path / "ab.pt")]) == 0
    capsys.readouterr()
    ab = load(tmp_path / "ab.pt")
    for k in wa:
        if wa[k].is_floating_point():
            torch.testing.assert_close(ab["model"][k], (wa[k] + wb[k]) / 2)
    assert [s["path"] for s in ab["lineage"][0]["sources"]] == [str(a), str(b)]
    # shipped checkpoints by their names, as everywhere else
    assert main(["checkpoint", "average", "coalition-team", "coalition-team", "--out", str(tmp_path / "ct.pt")]) == 0
    capsys.readouterr()
    assert all(s["path"].endswith("checkpoints/coalition-team.pt") for s in load(tmp_path / "ct.pt")["lineage"][0]["sources"])
    pol = load_policy(tmp_path / "ab.pt")  # the result loads and solves
    assert pol.rules == Rules(max_open=2, safety=True)
    inst = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    assert solve(inst, "rl", seed=0, checkpoint=str(tmp_path / "ab.pt")).success
    assert not list(tmp_path.glob("*.tmp"))


def test_checkpoint_average_never_overwrites_a_source_and_replaces_a_file_only_with_force(tmp_path, capsys):
    import hashlib

    from hmrta.cli import main

    a, _ = _exported(tmp_path, "a", seed=1)
    b, _ = _exported(tmp_path, "b", seed=2)
    sha = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in (a, b)}
    other = tmp_path / "notes.pt"
    other.write_text("not a checkpoint\n")
    for out, extra, what in ((a, [], "one of the checkpoints"), (b, ["--force"], "one of the checkpoints"),
                             (tmp_path / "." / "b.pt", ["--force"], "one of the checkpoints"),
                             (other, [], "pass --force")):
        assert main(["checkpoint", "average", str(a), str(b), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and what in err, err
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in (a, b)} == sha
    assert other.read_text() == "not a checkpoint\n"
    assert main(["checkpoint", "average", str(a), str(b), "--out", str(other), "--force"]) == 0
    capsys.readouterr()
    assert load_policy(other) is not None
    # one line by default, the lineage entry with --json; a missing folder of --out is created
    new = tmp_path / "new" / "ab.pt"
    assert main(["checkpoint", "average", str(a), str(b), "--out", str(new)]) == 0
    said = capsys.readouterr().out
    assert said == (f"averaged 2 checkpoint(s) into {new} (sha256 {hashlib.sha256(new.read_bytes()).hexdigest()}; "
                    f"its lineage: hmrta checkpoint info {new})\n")
    assert main(["checkpoint", "average", str(a), "--out", str(tmp_path / "a2.pt"), "--json"]) == 0
    entry = json.loads(capsys.readouterr().out)
    assert entry["out"] == str(tmp_path / "a2.pt") and [s["sha256"] for s in entry["sources"]] == [sha[a]]


def test_checkpoint_average_uses_the_moving_average_and_refuses_other_networks(tmp_path, capsys):
    from hmrta.cli import main
    from hmrta.rl.checkpoint import average, load

    a, _ = _exported(tmp_path, "a", seed=1)
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    tr = FixedTrainer(_tiny_cfg(train={"ema": 0.5}), tmp_path / "e", device="cpu", log=lambda s: None)
    tr.train_step()
    tr.save(tmp_path / "e.pt")  # a training checkpoint: its moving average is averaged
    average([tmp_path / "e.pt"], tmp_path / "ee.pt")
    assert all(torch.equal(load(tmp_path / "ee.pt")["model"][k], v) for k, v in tr.ema.items())
    assert load(tmp_path / "ee.pt")["lineage"][0]["sources"][0]["weights"] == "ema"

    wide, _ = _exported(tmp_path, "wide", model={"d_model": 64})
    rules, _ = _exported(tmp_path, "rules", rules={"max_open": None})
    for other, key in ((wide, "config.model.d_model"), (rules, "config.rules.max_open")):
        out = tmp_path / "no.pt"
        with pytest.raises(CheckpointError, match=re.escape(key) + ".*only checkpoints of the same network"):
            average([a, other], out)
        assert main(["checkpoint", "average", str(a), str(other), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(other) in err and key in err
        assert not out.exists()


def test_checkpoint_format_versions(tmp_path):
    """Files without checkpoint_format (format 0: the shipped ones) load unchanged; files written
    now carry format 1; a newer format is refused with a clear error."""
    from hmrta.rl.checkpoint import FORMAT_VERSION, load, save

    for name in ("coalition-team.pt", "coalition-open.pt"):  # shipped in format 0
        p = DEFAULT_CHECKPOINT.with_name(name)
        if p.exists():
            assert "checkpoint_format" not in torch.load(p, weights_only=True)
            assert load(p)["config"]["model"]
    FixedTrainer.fixed = ScenarioGenerator("MA-AT", 4, 2, 5, 2).instance(5, 4)
    tr = FixedTrainer(_tiny_cfg(), tmp_path / "run", device="cpu", log=lambda s: None)
    tr.save(tmp_path / "last.pt")
    ck = torch.load(tmp_path / "last.pt", weights_only=True)
    assert ck["checkpoint_format"] == FORMAT_VERSION == 1
    old = {k: v for k, v in ck.items() if k != "checkpoint_format"}
    torch.save(old, tmp_path / "v0.pt")
    tr.load(tmp_path / "v0.pt")  # format 0 resumes
    for bad, msg in ((2, "checkpoint_format: 2 is newer than this hmrta reads"),
                     ("1", "checkpoint_format: expected an integer >= 0")):
        torch.save({**old, "checkpoint_format": bad}, tmp_path / "bad.pt")
        with pytest.raises(CheckpointError, match=msg):
            load(tmp_path / "bad.pt")
        with pytest.raises(CheckpointError, match=msg):
            tr.load(tmp_path / "bad.pt")
    with pytest.raises(RuntimeError, match="non-finite"):
        save(tmp_path / "nan.pt", {"model": {"w": torch.tensor([math.nan])}})
    assert not (tmp_path / "nan.pt").exists()


def test_typed_config_round_trips_and_names_bad_keys():
    from hmrta.rl.config import TrainConfig, defaults

    cfg = TrainConfig.from_dict(defaults())
    assert cfg.to_dict() == DEFAULTS and cfg.train.sil.buffer == 16 and cfg.model.ff_hidden == 128
    with pytest.raises(ValueError, match=re.escape("x.yaml: train.sil.batch: expected an integer >= 1, got 0")):
        TrainConfig.from_dict(deep_update(DEFAULTS, {"train": {"sil": {"batch": 0}}}), "x.yaml")
    with pytest.raises(ValueError, match=re.escape("unknown key 'train.sil.bach'")):
        TrainConfig.from_dict(deep_update(DEFAULTS, {"train": {"sil": {"bach": 0}}}))
    from hmrta.rl.config import DistillConfig

    with pytest.raises(ValueError, match="distill.teacher: expected one of policy"):
        DistillConfig(teacher="oracle")  # validated on construction


def _rescaled(inst, time=1.0, length=1.0, skill=None):
    """The same mission with every time x ``time`` (durations up, speed down), the map x ``length``
    (positions and speed), and capabilities and requirements of skill k x ``skill[k]``."""
    from dataclasses import replace
    f = np.ones(inst.skills) if skill is None else np.asarray(skill, float)
    sp = tuple(replace(s, traits=tuple(float(v) for v in np.asarray(s.traits) * f),
                       depot=tuple(float(v) * length for v in s.depot)) for s in inst.species)
    tk = tuple(replace(t, location=tuple(float(v) * length for v in t.location),
                       requirements=tuple(float(v) for v in np.asarray(t.requirements) * f),
                       duration=t.duration * time) for t in inst.tasks)
    return replace(inst, velocity=inst.velocity * length / time, species=sp, tasks=tk, _cache={})


@pytest.mark.parametrize("change", [dict(time=2.0), dict(time=0.37), dict(length=0.5),
                                    dict(skill=[2.0, 3.0, 1.0, 0.5, 4.0]),
                                    dict(time=3.0, length=0.6, skill=[2.0, 2.0, 2.0, 2.0, 2.0])])
@pytest.mark.parametrize("scale", ["mission", "mission+coalition"])
def test_mission_scale_observation_is_scale_free(change, scale):
    """Under scale "mission" (and with the coalition-start column), a mission and the same mission
    with times, map or capabilities and requirements rescaled are observed alike at every decision;
    under "fixed" they are not."""
    from hmrta.baselines import BASELINES
    from hmrta.rl.features import observe
    base = ScenarioGenerator("MA-AT", 9, 3, 12, 5).instance(11, 1)
    other = _rescaled(base, **change)
    teacher = BASELINES["greedy-coalition"]()
    a, b = MissionState(base, seed=3, rules=RULES), MissionState(other, seed=3, rules=RULES)
    differs = 0
    while not a.done:
        for i, (x, y) in enumerate(zip(observe(a, scale=scale), observe(b, scale=scale))):
            np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5, err_msg=f"output {i} at t={a.clock}")
        fx, fy = observe(a)[:2], observe(b)[:2]
        differs += not all(np.allclose(x, y, rtol=1e-4, atol=1e-5) for x, y in zip(fx, fy))
        n = teacher(a)
        a.step(n)
        b.step(n)
    assert b.done and math.isclose(b.makespan, a.makespan * change.get("time", 1.0), rel_tol=1e-9)
    assert differs > 0  # the fixed scales do see the change


def test_coalition_column_is_greedy_coalitions_start_estimate():
    """scale "mission+coalition": the "mission" observation plus one task column, greedy-coalition's
    estimate of when the task's coalition can start if the decider joins (from now, in the
    observation's time unit, clipped), 0 for the depot and the tasks the decider cannot take; also
    through the observation window. The network then takes one more task feature."""
    from hmrta.baselines import CoalitionGreedy
    from hmrta.rl.features import COALITION_CAP, TASK_FEATURES, mission_scales, observe
    gc = CoalitionGreedy()
    for inst, tasks in ((ScenarioGenerator("SA-AT", 15, 5, 20, 5).instance(3, 0), None),
                        (ScenarioGenerator("MA-AT", 30, 5, 80, 5).instance(5, 0), 20)):
        st = MissionState(inst, seed=1, rules=RULES)
        checked = 0
        while not st.done:
            kw = {} if tasks is None else {"max_tasks": tasks}
            base, ext = observe(st, scale="mission", **kw), observe(st, scale="mission+coalition", **kw)
            assert ext[0].shape == (base[0].shape[0], TASK_FEATURES + 1)
            np.testing.assert_array_equal(ext[0][:, :-1], base[0])
            for x, y in zip(base[1:], ext[1:]):
                np.testing.assert_array_equal(x, y)
            col, mask, nodes = ext[0][:, -1], ext[2], ext[3]
            assert col[0] == 0 and np.all(col[~mask] == 0) and np.all(col[mask] >= 0) and col.max() <= COALITION_CAP
            cand, start, mine = gc.estimates(st)
            if len(cand):
                want = np.minimum((start - st.clock) / mission_scales(st).time, COALITION_CAP)
                rows = {int(n): r for r, n in enumerate(nodes)}
                seen = [(rows[1 + int(j)], w) for j, w in zip(cand, want) if 1 + int(j) in rows]
                np.testing.assert_allclose([col[r] for r, _ in seen], [w for _, w in seen], rtol=1e-6)
                checked += len(seen)
            st.step(gc(st))
        assert checked > 50
    from hmrta.rl.model import ModelConfig
    assert ModelConfig.from_dict({"scale": "mission+coalition", "task_features": TASK_FEATURES + 1}).task_features == 16
    with pytest.raises(ValueError, match="model.task_features: expected 16"):
        ModelConfig.from_dict({"scale": "mission+coalition"})


def test_mission_scale_is_the_fixed_scale_on_paper_missions():
    """The mission units come out near the fixed ones on the paper's missions (module docstring of
    hmrta.rl.features), so a fixed-scale network observes them almost unchanged."""
    from hmrta.rl.features import mission_scales
    insts = ScenarioGenerator("MA-AT", 25, 5, 50, 5).generate(20, 7)
    sc = [mission_scales(MissionState(i, seed=0)) for i in insts]
    assert abs(np.mean([s.time for s in sc]) - 10.0) < 0.6
    assert abs(np.mean([s.length for s in sc]) - 1.0) < 0.06
    assert all(np.allclose(s.cap, 1.0) for s in sc)


def test_a_resumed_run_keeps_the_columns_of_its_log(tmp_path):
    """log.csv: a run resumed on a log written with fewer columns (an older version) appends rows
    under that log's header, so every row has as many fields as the header."""
    import csv

    cfg = _tiny_cfg(train={"iterations": 1}, pretrain={"iterations": 1, "instances_per_iter": 1, "epochs": 1})
    Trainer(cfg, tmp_path, device="cpu", log=lambda s: None).run(progress=False)
    log = tmp_path / "log.csv"
    rows = list(csv.reader(open(log)))
    assert rows[0][-1] == "dagger_plan_ratio"
    with open(log, "w", newline="") as f:  # as an older version wrote it
        csv.writer(f).writerows([r[:-1] for r in rows])
    tr = Trainer(_tiny_cfg(train={"iterations": 2}, pretrain={"iterations": 1, "instances_per_iter": 1, "epochs": 1}),
                 tmp_path, device="cpu", log=lambda s: None)
    tr.load(tmp_path / "last.pt")
    tr.run(progress=False)
    after = list(csv.reader(open(log)))
    assert len(after) > len(rows) and {len(r) for r in after} == {len(rows[0]) - 1}


def test_the_observation_window_is_the_checkpoints_and_every_inference_path_uses_it(tmp_path, capsys):
    """``checkpoint average --window`` writes the window into the config; the rollout, the live
    decider and the labeller then observe the mission through it (here: 8 tasks, 3 robots, on a
    mission of 12 tasks and 6 robots), and the weights are unchanged."""
    from hmrta.cli import main
    from hmrta.rl.checkpoint import load
    from hmrta.rl.features import observe
    from hmrta.rl.imitation import Labels

    a, wa = _exported(tmp_path, "a", seed=1)
    out = tmp_path / "w.pt"
    assert main(["checkpoint", "average", str(a), "--out", str(out), "--window", "8", "3"]) == 0
    capsys.readouterr()
    ck = load(out)
    assert (ck["config"]["model"]["window_tasks"], ck["config"]["model"]["window_agents"]) == (8, 3)
    assert ck["lineage"][0]["window"] == [8, 3] and all(torch.equal(ck["model"][k], wa[k]) for k in wa)
    pol, base = load_policy(out), load_policy(a)
    assert pol.model.cfg.view() == {"scale": base.model.cfg.scale, "max_tasks": 8, "max_agents": 3}
    inst = ScenarioGenerator("MA-AT", 6, 2, 12, 2).instance(5, 3)
    seen = []

    class Spy:  # the traced network, recording the widths it is shown
        cfg = pol.model.cfg

        def __call__(self, **obs):
            seen.append((obs["tasks"].shape[1], obs["agents"].shape[1]))
            return pol.model(**obs)

    st = MissionState(inst, seed=0, rules=pol.rules)
    rollout(Spy(), [st], sample=False)
    assert st.success and seen and set(seen) == {(9, 3)}  # depot + 8 tasks, 3 robots: every decision windowed
    live = MissionState(inst, seed=0, rules=pol.rules)  # the live decider sees the same: the same mission
    decide = RLDecider(pol, sample=False, seed=0)
    while not live.done:
        live.step(decide(live))
    assert live.makespan == st.makespan and live.decisions == st.decisions
    labels = Labels()
    st = MissionState(inst, seed=0, rules=pol.rules)
    labels.add(st, lambda s: int(np.flatnonzero(s.mask())[-1]), None, 0.0, pol.model.cfg.view())
    assert labels.obs[0][0].shape[0] == 1 + 8 and labels.obs[0][1].shape[0] == 3
    assert observe(st, **base.model.cfg.view())[0].shape[0] == 1 + 12  # the default window shows it whole
    with pytest.raises(SystemExit):
        main(["checkpoint", "average", str(a), "--out", str(out), "--window", "8"])
    capsys.readouterr()
    assert main(["checkpoint", "average", str(a), "--out", str(tmp_path / "bad.pt"), "--window", "0", "3"]) == 2
    assert "hmrta: error: --window: expected TASKS ROBOTS, each an integer in [1, 100000], got 0 3" in \
        capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()


def test_greedy_rows_decide_the_depot_by_the_checkpoints_rule():
    """"argmax" takes the most likely row; "majority" goes home only on at least half the
    probability, else takes the most likely task (never an inadmissible one)."""
    from hmrta.rl.rollout import greedy_rows

    p = torch.tensor([[0.4, 0.3, 0.3],  # depot most likely, tasks together more likely
                      [0.6, 0.2, 0.2],  # depot on its own majority
                      [0.3, 0.7, 0.0],  # a task most likely
                      [0.2, 0.0, 0.0]])  # no admissible task: the depot (probabilities need not sum to 1 here)
    logits = torch.log(p)  # [4, 3]; log 0 = -inf, the network's inadmissible rows
    assert greedy_rows(logits).tolist() == [0, 0, 1, 0]
    assert greedy_rows(logits, "argmax").tolist() == [0, 0, 1, 0]
    assert greedy_rows(logits, "majority").tolist() == [1, 0, 1, 0]
    assert greedy_rows(logits[:, :1], "majority").tolist() == [0, 0, 0, 0]  # the depot alone
    with pytest.raises(ValueError, match="greedy_depot"):
        greedy_rows(logits, "total")
    with pytest.raises(ValueError, match=r"model.greedy_depot: expected one of argmax, majority"):
        ModelConfig.from_dict({"greedy_depot": "first"})
    assert ModelConfig.from_dict({}).greedy_depot == "argmax"  # checkpoints without the key: argmax


def test_greedy_depot_is_the_checkpoints_and_live_decides_as_the_rollout(tmp_path, capsys):
    """``checkpoint average --greedy-depot`` writes the rule into the config and lineage with the
    weights unchanged; the rollout (RL(g.)) and the live decider follow it decision for decision.
    The mission is one where the two rules part (the argmax parks a robot at the depot while the
    tasks together are more likely)."""
    from hmrta.cli import main
    from hmrta.rl.checkpoint import load

    src = load(DEFAULT_CHECKPOINT)
    inst = ScenarioGenerator("MA-AT", 6, 2, 10, 2).instance(7, 1)
    runs = {}
    for rule in ("argmax", "majority"):
        out = tmp_path / f"{rule}.pt"
        assert main(["checkpoint", "average", str(DEFAULT_CHECKPOINT), "--out", str(out), "--greedy-depot", rule]) == 0
        capsys.readouterr()
        ck = load(out)
        assert ck["config"]["model"]["greedy_depot"] == rule and ck["lineage"][0]["greedy_depot"] == rule
        assert all(torch.equal(ck["model"][k], src["model"][k]) for k in src["model"])
        pol = load_policy(out)
        assert pol.model.cfg.greedy_depot == rule
        st = MissionState(inst, seed=0, rules=pol.rules)
        rollout(pol.model, [st], sample=False)
        live = MissionState(inst, seed=0, rules=pol.rules)
        decide = RLDecider(pol, sample=False, seed=0)
        while not live.done:
            live.step(decide(live))
        assert st.success and live.routes == st.routes and live.makespan == st.makespan
        assert live.decisions == st.decisions
        runs[rule] = st
    assert runs["majority"].decisions < runs["argmax"].decisions  # 17 against 39 decisions
    assert runs["majority"].makespan < runs["argmax"].makespan
    with pytest.raises(SystemExit):
        main(["checkpoint", "average", str(DEFAULT_CHECKPOINT), "--out", str(tmp_path / "x.pt"), "--greedy-depot", "first"])
    assert "invalid choice" in capsys.readouterr().err and not (tmp_path / "x.pt").exists()


def test_checkpoint_info_reads_a_checkpoint_without_building_it(tmp_path, capsys):
    """``hmrta checkpoint info`` prints what the file says about itself (sha256, network, greedy
    decoding, rules, lineage), as JSON with ``--json``; a missing or foreign file exits 2 with
    one line."""
    import hashlib

    from hmrta.cli import main
    from hmrta.rl.checkpoint_info import describe, lineage_lines

    d = describe("default")
    assert d["sha256"] == hashlib.sha256(DEFAULT_CHECKPOINT.read_bytes()).hexdigest()
    assert d["config"]["model"]["greedy_depot"] == "majority" and d["weights"] == ["model"]
    lines = lineage_lines(d["lineage"])
    assert lines[0] == "average (greedy_depot majority) of" and "window [100, 25]" in "\n".join(lines)
    assert main(["checkpoint", "info"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == str(DEFAULT_CHECKPOINT) and "greedy depot  majority" in out
    assert main(["checkpoint", "info", "broad", "--json"]) == 0
    broad = json.loads(capsys.readouterr().out)
    assert broad["sha256"] == describe("broad")["sha256"] and "greedy_depot" not in broad["config"]["model"]
    a, _ = _exported(tmp_path, "a", seed=1)  # a file of this version: format, code version, no lineage
    info = describe(a)
    assert info["format"] >= 1 and info["lineage"] == [] and info["config"]["model"]["greedy_depot"] == "argmax"
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    for bad in (str(tmp_path / "none.pt"), str(tmp_path / "junk.pt")):
        assert main(["checkpoint", "info", bad]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and bad in err


def test_lookahead_breaks_ties_with_the_checkpoints_greedy_choice(monkeypatch):
    """Where every action costs the same, lookahead keeps the policy's own choice: the greedy row
    by the checkpoint's rule (here a state where "majority" and the argmax part)."""
    import hmrta.rl.inference as inf
    from hmrta.rl.rollout import greedy_rows

    pol = load_policy()  # default.pt: greedy_depot majority
    assert pol.model.cfg.greedy_depot == "majority"
    st = MissionState(ScenarioGenerator("MA-AT", 6, 2, 10, 2).instance(7, 1), seed=0, rules=pol.rules)
    while not st.done:  # the first decision where the two rules part
        obs, nodes = batch_observations([st], **pol.model.cfg.view())
        with torch.inference_mode():
            logits = pol.model(**obs)
        if int(logits.argmax()) != int(greedy_rows(logits, "majority")[0]):
            break
        st.step(int(nodes[0][int(logits.argmax())]))
    assert not st.done
    monkeypatch.setattr(inf, "action_costs", lambda model, decisions, t_max: (
        [np.where(mask, 1.0, np.inf) for _, _, mask in decisions], []))  # all admissible actions tie
    assert inf.lookahead_choices(pol.model, [st]) == [int(nodes[0][int(greedy_rows(logits, "majority")[0])])]


def test_checkpoint_average_takes_inference_settings_from_the_first_file(tmp_path, capsys):
    """Sources that differ only in inference settings (window, greedy decoding) are averaged; the
    written file has the first one's unless --window / --greedy-depot set them."""
    from hmrta.cli import main
    from hmrta.rl.checkpoint import load

    a, _ = _exported(tmp_path, "a", seed=1)
    b, _ = _exported(tmp_path, "b", seed=2)
    bm = tmp_path / "bm.pt"
    assert main(["checkpoint", "average", str(b), "--out", str(bm), "--greedy-depot", "majority",
                 "--window", "8", "3"]) == 0
    for first, second, want in ((a, bm, ("argmax", 50)), (bm, a, ("majority", 8))):
        out = tmp_path / "ab.pt"
        assert main(["checkpoint", "average", str(first), str(second), "--out", str(out), "--force"]) == 0
        m = load(out)["config"]["model"]
        assert (m["greedy_depot"], m["window_tasks"]) == want
    assert main(["checkpoint", "average", str(a), str(bm), "--out", str(out), "--greedy-depot", "majority",
                 "--force"]) == 0
    assert load(out)["config"]["model"]["greedy_depot"] == "majority"
    capsys.readouterr()


def test_the_cli_offers_every_greedy_decoding():
    """``--greedy-depot`` takes every value of ModelConfig.greedy_depot (the parser is built
    without importing torch, so it spells them out)."""
    from hmrta.cli import build_parser
    from hmrta.rl.model import GREEDY_DEPOT

    for rule in GREEDY_DEPOT:
        args = build_parser().parse_args(["checkpoint", "average", "a.pt", "--out", "b.pt", "--greedy-depot", rule])
        assert args.greedy_depot == rule


def test_an_unreadable_checkpoint_is_named_in_the_files_terms(tmp_path):
    """A file torch cannot read is one line saying what it is (no torch internals, no request to
    report a bug), for a zip without torch's records, a cut-short checkpoint, text, random bytes and
    an empty file."""
    import random
    import zipfile

    from hmrta.rl.checkpoint import load
    from hmrta.rl.checkpoint_info import read_config

    with zipfile.ZipFile(tmp_path / "zip.pt", "w") as z:
        z.writestr("a/data.pkl", b"garbage")
    (tmp_path / "cut.pt").write_bytes(DEFAULT_CHECKPOINT.read_bytes()[:3000])
    (tmp_path / "text.pt").write_text("hello\n")
    (tmp_path / "passwd.pt").write_text("root:x:0:0:root:/root:/bin/bash\n")  # torch's legacy reader: IndexError
    (tmp_path / "random.pt").write_bytes(random.Random(3).randbytes(100))
    (tmp_path / "empty.pt").write_bytes(b"")
    for name, want in (("zip", "a zip archive without a torch checkpoint's records"),
                       ("cut", "a zip archive cut short: copied or downloaded in part?"),
                       ("text", "not a torch checkpoint file"), ("passwd", "not a torch checkpoint file"),
                       ("random", "not a torch checkpoint file"), ("empty", "empty, or cut short")):
        with pytest.raises(CheckpointError) as e:
            load(tmp_path / f"{name}.pt")
        msg = str(e.value)
        assert msg == f"{tmp_path / name}.pt: not a readable hmrta checkpoint ({want}" + (
            ", or a damaged one)" if "records" in want else ")"), msg
    for name in ("text", "passwd", "random"):  # the torch-free reader (hmrta-mission, the nodes) alike
        with pytest.raises(CheckpointError, match=r"not a readable hmrta checkpoint \(not a torch checkpoint file\)$"):
            read_config(tmp_path / f"{name}.pt")


def test_the_checkpoint_of_a_method_is_a_user_error_when_it_is_no_file(tmp_path):
    """checkpoint_of (a board's and an agent's record of the policy they run) raised
    FileNotFoundError on a name that is neither a file nor a shipped checkpoint: the board died
    with a traceback."""
    from hmrta.methods import checkpoint_of

    with pytest.raises(CheckpointError, match="nosuch: no such checkpoint"):
        checkpoint_of("rl", {"checkpoint": "nosuch"})
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        checkpoint_of("rl", {"checkpoint": str(tmp_path / "gone.pt")})
    assert checkpoint_of("greedy", {"checkpoint": "nosuch"}) is None  # (a method that takes none)
    assert checkpoint_of("rl", {"checkpoint": "broad"})["path"].endswith("broad.pt")


def test_a_checkpoint_that_is_a_fifo_or_a_folder_is_named_so_by_every_reader(tmp_path):
    """A FIFO was 'no such checkpoint' in the torch-free readers (hmrta-mission, the nodes)."""
    import os

    from hmrta.methods import checkpoint_of
    from hmrta.rl.checkpoint import load
    from hmrta.rl.checkpoint_info import read_config

    os.mkfifo(tmp_path / "pipe.pt")
    for name, why in (("pipe.pt", "not a regular file, expected a checkpoint file"),
                      (".", "is a folder, expected a checkpoint file")):
        path = str(tmp_path / name)
        for read in (load, read_config, lambda p: checkpoint_of("rl", {"checkpoint": p}),
                     lambda p: load_policy(p)):
            with pytest.raises(CheckpointError, match=f"{re.escape(why)}$"):
                read(path)


def _same_state(a: Trainer, b: Trainer) -> None:
    for (k, v), (_, v2) in zip(a.model.state_dict().items(), b.model.state_dict().items()):
        torch.testing.assert_close(v, v2, msg=k, rtol=0, atol=0)
    assert a.np_rng.bit_generator.state == b.np_rng.bit_generator.state
    assert torch.equal(a.torch_gen.get_state(), b.torch_gen.get_state())
    assert (a.pretrain_done, a.iteration, a.episodes) == (b.pretrain_done, b.iteration, b.episodes)


def test_a_ctrl_c_within_an_iteration_and_the_resume_is_exact(tmp_path):
    """hmrta train's SIGINT / SIGTERM raises KeyboardInterrupt wherever the run is (here at the
    end of iteration 2's step, before its row is logged): last.pt holds the state after the last
    finished iteration, so that --resume ends where an uninterrupted run ends (weights, random
    streams, counters); the log holds each row once."""
    import csv

    def cfg(n):
        return _tiny_cfg(train={"iterations": n}, pretrain={"iterations": 2, "instances_per_iter": 1, "epochs": 1})

    ref = Trainer(cfg(4), tmp_path / "ref", device="cpu", log=lambda s: None)
    ref.run(progress=False)

    class StopsInTwo(Trainer):
        def train_step(self):
            row = super().train_step()
            if self.iteration == 2:  # the signal arrives in iteration 2
                raise KeyboardInterrupt
            return row

    run = tmp_path / "run"
    t1 = StopsInTwo(cfg(4), run, device="cpu", log=lambda s: None)
    with pytest.raises(KeyboardInterrupt):
        t1.run(progress=False)
    assert t1.iteration == 2 and t1.saved_last
    t2 = Trainer(cfg(4), run, device="cpu", log=lambda s: None)
    t2.load(run / "last.pt", same_run=True)  # --resume
    t2.run(progress=False)
    _same_state(t2, ref)
    rows = [(r["phase"], r["iteration"]) for r in csv.DictReader(open(run / "log.csv"))]
    assert rows == [(r["phase"], r["iteration"]) for r in csv.DictReader(open(tmp_path / "ref" / "log.csv"))]


def test_a_run_cut_short_within_an_iteration_saves_the_state_after_the_last_finished_one(tmp_path):
    """An iteration cut short (Ctrl-C, SIGTERM, a lost Ray cluster) writes last.pt as of the latest
    finished iteration, not the state within the failed one, and --resume ends where an
    uninterrupted run ends; a fresh run that failed before its first iteration leaves no last.pt
    (a run folder it would lock). The rows of the iteration done again are not logged twice."""
    import csv

    def cfg(n):
        return _tiny_cfg(train={"iterations": n}, pretrain={"iterations": 0}, checkpoint={"every": 2})

    class FailsAt(Trainer):
        fail_at = 1

        def train_step(self):
            if self.iteration + 1 == self.fail_at:
                raise RuntimeError("cut short")
            return super().train_step()

    fresh = tmp_path / "fresh"
    with pytest.raises(RuntimeError):
        FailsAt(cfg(5), fresh, device="cpu", log=lambda s: None).run(progress=False)
    assert not (fresh / "last.pt").exists()
    run = tmp_path / "run"
    FailsAt.fail_at = 4
    t1 = FailsAt(cfg(5), run, device="cpu", log=lambda s: None)
    with pytest.raises(RuntimeError):
        t1.run(progress=False)
    assert t1.iteration == 3 and t1.saved_last
    t2 = Trainer(cfg(5), run, device="cpu", log=lambda s: None)
    t2.load(run / "last.pt")
    assert t2.iteration == 3  # the state after iteration 3, not one within iteration 4
    t2.run(progress=False)
    rl = [int(r["iteration"]) for r in csv.DictReader(open(run / "log.csv")) if r["phase"] == "rl"]
    assert rl == [1, 2, 3, 4, 5]
    ref = Trainer(cfg(5), tmp_path / "ref", device="cpu", log=lambda s: None)
    ref.run(progress=False)
    _same_state(t2, ref)


def test_hmrta_train_stops_on_sigint_and_saves_the_state_after_the_last_finished_iteration(tmp_path):
    """A real SIGINT to ``hmrta train`` stops it at once (a grace period of seconds suffices) and
    writes last.pt as of the latest finished iteration (the log's last row), exit 130."""
    import csv
    import signal
    import subprocess
    import sys
    import time

    from hmrta.rl.checkpoint import load
    from hmrta.rl.train import write_config

    cfg = _tiny_cfg(train={"iterations": 10000}, pretrain={"iterations": 0})
    write_config(cfg, tmp_path / "tiny.yaml")
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "hmrta.cli", "train", "--config", str(tmp_path / "tiny.yaml"), "--run-dir", str(run),
           "--threads", "1", "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            log = run / "log.csv"
            if log.exists() and sum(r["phase"] == "rl" for r in csv.DictReader(open(log))) >= 2:
                break
            time.sleep(0.2)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "stopped: checkpoint saved to" in err and "the iteration under way is done again" in err, err
    assert "Traceback" not in err
    rl = [int(r["iteration"]) for r in csv.DictReader(open(run / "log.csv")) if r["phase"] == "rl"]
    assert rl[-1] - 1 <= load(run / "last.pt")["iteration"] <= rl[-1] and rl[-1] >= 2  # (its row may be written)


def test_a_resume_says_which_settings_changed_refuses_a_new_seed_and_shows_where_validation_differs(tmp_path):
    from hmrta.rl.checkpoint_info import CheckpointError

    cfg = _tiny_cfg(train={"iterations": 1}, pretrain={"iterations": 0})
    Trainer(cfg, tmp_path, device="cpu", log=lambda s: None).run(progress=False)
    last = tmp_path / "last.pt"
    tr = Trainer(deep_update(cfg, {"train": {"iterations": 3, "lr": 1e-3}}), tmp_path / "b", device="cpu")
    tr.load(last)
    assert tr.changed_keys() == ["train.lr: 0.003 -> 0.001"]  # the run length is expected to change
    tr = Trainer(deep_update(cfg, {"pretrain": {"schedules": "data.jsonl"}}), tmp_path / "b2", device="cpu")
    tr.load(last)
    assert tr.changed_keys() == ["pretrain.schedules: None -> 'data.jsonl'"]  # a setting that was null
    with pytest.raises(CheckpointError, match="seed 0, this config has 8: .* pass --reseed"):
        Trainer(deep_update(cfg, {"seed": 8}), tmp_path / "c", device="cpu").load(last, same_run=True)
    Trainer(deep_update(cfg, {"seed": 8}), tmp_path / "c", device="cpu").load(last)  # --init: another run's
    Trainer(deep_update(cfg, {"seed": 8}), tmp_path / "c", device="cpu").load(last, reseed=True)
    rows = cfg["validation"]["rows"]
    with pytest.raises(CheckpointError, match=r"validation.rows \(length\) = 1, this config has 2"):
        Trainer(deep_update(cfg, {"validation": {"rows": rows + [[6, 2, 8, 2, 2]]}}), tmp_path / "d",
                device="cpu").load(last)
    with pytest.raises(CheckpointError, match=r"validation.rows\[0\]\[4\] = 2, this config has 3"):
        Trainer(deep_update(cfg, {"validation": {"rows": [rows[0][:4] + [3]]}}), tmp_path / "e",
                device="cpu").load(last)


def test_a_reseeded_continuation_scores_its_starting_weights_into_best_pt(tmp_path):
    """--resume --reseed --init: the continuation starts at the checkpoint's iteration with no
    score of its own; it validates its starting weights first, so best.pt exists (and --export
    ships the best weights, not the last)."""
    cfg = _tiny_cfg(train={"iterations": 1}, pretrain={"iterations": 0})
    Trainer(cfg, tmp_path / "a", device="cpu", log=lambda s: None).run(progress=False)
    tr = Trainer(deep_update(cfg, {"train": {"iterations": 2}}), tmp_path / "b", device="cpu", log=lambda s: None)
    tr.load(tmp_path / "a" / "last.pt", reseed=True)
    assert tr.iteration == 1 and tr.best_val == math.inf
    res = tr.run(progress=False)
    assert (tmp_path / "b" / "best.pt").exists() and math.isfinite(res["best_val"])


def test_a_run_from_another_runs_weights_keeps_them_as_best_until_beaten(tmp_path):
    """--init (here with --reseed): the starting weights are scored before cloning and are the
    run's first best.pt, so that best.pt (and an export) is never worse than them; without later
    validations they stay the best."""
    from hmrta.rl.checkpoint import load, policy_weights

    Trainer(_tiny_cfg(train={"iterations": 1}, pretrain={"iterations": 0}), tmp_path / "a", device="cpu",
            log=lambda s: None).run(progress=False)
    src = tmp_path / "a" / "last.pt"
    cfg = _tiny_cfg(train={"iterations": 0},
                    pretrain={"iterations": 2, "instances_per_iter": 2, "teacher": "greedy-coalition"})
    tr = Trainer(cfg, tmp_path / "b", device="cpu", log=lambda s: None)
    tr.load(src, reseed=True)
    res = tr.run(progress=False)
    assert tr.pretrain_done == 2 and math.isfinite(res["best_val"])
    rows = (tmp_path / "b" / "log.csv").read_text().splitlines()
    assert rows[1].startswith("val,") and sum(r.startswith("bc,") for r in rows) == 2, rows
    _, start = policy_weights(load(src), src)
    _, best = policy_weights(load(tmp_path / "b" / "best.pt"), tmp_path / "b" / "best.pt")
    assert all(torch.equal(start[k], best[k]) for k in start)  # (validation.every 1000: scored once)


def test_train_export_writes_the_runs_best_weights_with_their_lineage(tmp_path, capsys):
    """hmrta train --export: the weights inference uses of the run's best.pt (its moving average),
    its counters and lineage as they are (not an ``init`` of the run's own file), into a folder
    made for it; never over the run's own last.pt or best.pt (its resume state)."""
    import yaml

    from hmrta.cli import main
    from hmrta.rl.checkpoint import load, policy_weights

    cfg = _tiny_cfg(train={"iterations": 2, "ema": 0.9}, pretrain={"iterations": 0},
                    validation={"every": 1, "rows": [[4, 2, 5, 2, 2]]})
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    run, out = tmp_path / "run", tmp_path / "new" / "folder" / "mine.pt"
    train = ["train", "--config", str(path), "--run-dir", str(run), "--no-progress", "--threads", "1"]
    for own in ("last.pt", "best.pt", "config.yaml", "log.csv"):
        assert main([*train, "--export", str(run / own)]) == 2
        assert f"is the run's own {own}" in capsys.readouterr().err
    from hmrta.rl.checkpoint_info import SHIPPED_DIR

    for argv in ([*train, "--resume", "--init", "compact", "--export", str(SHIPPED_DIR / "compact.pt")],
                 [*train, "--export", str(path)]):  # the --init checkpoint by its shipped name, the config
        assert main(argv) == 2 and "is an input of this command" in capsys.readouterr().err
    assert not run.exists()
    assert main([*train, "--export", str(out)]) == 0
    assert "(the moving average)" in capsys.readouterr().err
    best, mine = load(run / "best.pt"), load(out)
    assert mine["lineage"] == best["lineage"] == [] and mine["iteration"] == best["iteration"]
    which, sd = policy_weights(best, run / "best.pt")
    assert which == "ema" and all(torch.equal(sd[k], mine["model"][k]) for k in sd)
    assert "optimizer" not in mine and mine["config"] == best["config"]
    assert load_policy(out).config == best["config"]
    capsys.readouterr()
    assert main(["checkpoint", "info", str(out)]) == 0  # every training counter, the cloning phase's too
    said = capsys.readouterr().out
    for label, key in (("iteration", "iteration"), ("cloning", "pretrain_done"), ("decisions", "decisions")):
        assert re.search(rf"^  {label} +{mine[key]}$", said, re.M), (label, said)


def test_checkpoint_info_refuses_what_the_loaders_refuse(tmp_path, capsys):
    """hmrta checkpoint info is as strict as solve and --resume: a newer format, bad rules, a
    negative counter and a file that is not a checkpoint are one line each, exit 2."""
    import copy

    from hmrta.cli import main
    from hmrta.rl.checkpoint import load, save

    ck = load(DEFAULT_CHECKPOINT)
    rules = copy.deepcopy(ck["config"])
    rules["rules"]["max_open"] = "lots"
    cases = {"format": ({**ck, "checkpoint_format": 99}, "is newer than this hmrta reads"),
             "counter": ({**ck, "iteration": -5}, "iteration: expected an integer >= 0, got -5"),
             "rules": ({**ck, "config": rules}, "config.rules.max_open")}
    for name, (data, says) in cases.items():
        save(tmp_path / f"{name}.pt", data)
        assert main(["checkpoint", "info", str(tmp_path / f"{name}.pt")]) == 2, name
        assert says in capsys.readouterr().err, name
    (tmp_path / "text.pt").write_text("hello")
    assert main(["checkpoint", "info", str(tmp_path / "text.pt")]) == 2
    assert "not a torch checkpoint file" in capsys.readouterr().err


def test_a_run_started_from_another_runs_checkpoint_records_it_in_its_lineage(tmp_path, capsys):
    from hmrta.cli import main
    from hmrta.rl.checkpoint import load
    from hmrta.rl.checkpoint_info import sha256

    cfg = _tiny_cfg(train={"iterations": 1}, pretrain={"iterations": 0})
    Trainer(cfg, tmp_path / "a", device="cpu", log=lambda s: None).run(progress=False)
    src = tmp_path / "a" / "last.pt"
    tr = Trainer(deep_update(cfg, {"train": {"iterations": 2}}), tmp_path / "b", device="cpu", log=lambda s: None)
    tr.load(src, reseed=True)
    tr.run(progress=False)
    tr.export(tmp_path / "b.pt")
    for f in (tmp_path / "b" / "last.pt", tmp_path / "b.pt"):
        (entry,) = load(f)["lineage"]
        assert entry["op"] == "init" and entry["reseed"] and entry["sources"][0]["sha256"] == sha256(src)
    again = Trainer(deep_update(cfg, {"train": {"iterations": 3}}), tmp_path / "b", device="cpu", log=lambda s: None)
    again.load(tmp_path / "b" / "last.pt", same_run=True)  # --resume of the same run: carried on
    assert again.lineage == load(tmp_path / "b" / "last.pt")["lineage"]
    assert main(["checkpoint", "info", str(tmp_path / "b.pt")]) == 0
    assert f"init of\n      {src}" in capsys.readouterr().out
