"""K agents' vmapped convolutions without grouping (`layouts.vmapped_convs`: one
batched GEMM, "gemm", or K plain convolutions, "split"; the agent loops
"vmap_gemm" and "vmap_split").

References: each agent's plain `nn.Conv` (the layer) and each agent's update run
alone (`step.update_pair`, the plain convolutions); K of them vmapped on either
path must equal them within float32 rounding, outputs and gradients, and the
vmapped program must hold no grouped convolution (plain `vmap` does: the control
that shows the count can fail) and, for "gemm", no convolution at all.
"""

import dataclasses
import re

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dmcr_jax.benchmarks.learner import filled_buffers
from dmcr_jax.train import layouts, sac
from dmcr_jax.train import step as train_step

pytestmark = pytest.mark.xdist_group("agent_gemm")

K = 3


def convolutions(hlo: str) -> tuple[int, int]:
  """(convolutions, grouped ones: feature or batch group count > 1) in HLO text."""
  convs = re.findall(r"= \S+ convolution\(.*", hlo)
  grouped = [c for c in convs if re.search(r"(feature|batch)_group_count=(?!1\b)\d+", c)]
  return len(convs), len(grouped)


@pytest.mark.parametrize("form", layouts.VMAPPED_CONVS)
def test_vmapped_conv_is_each_agents_nn_conv_without_grouping(form):
  # Both layouts, both strides, odd non-square sides: K agents' Conv vmapped
  # inside vmapped_convs(form) gives each agent's nn.Conv output and the gradients
  # (kernel, bias, input) of a random functional, with no grouped convolution.
  rng = np.random.default_rng(0)
  normal = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
  cases = [(impl, s) for impl in layouts.IMPLS for s in (1, 2)]
  x = normal(K, 2, 11, 12, 5)
  params = {"params": {"kernel": normal(K, 3, 3, 5, 4), "bias": normal(K, 4)}}
  weights = {s: normal(K, 2, (11 - 3) // s + 1, (12 - 3) // s + 1, 4) for s in (1, 2)}

  def grads(layer, p, x, w):
    y, vjp = jax.vjp(lambda p, x: layouts.to_pixels(layer.apply(p, x)), p, x)
    return y, *vjp(w)

  def vmapped(params, x):
    return [jax.vmap(lambda p, x, w, i=i, s=s: grads(layouts.Conv(4, s, impl=i), p, x, w))(
        params, x, weights[s]) for i, s in cases]

  def batched(params, x):
    with layouts.vmapped_convs(form):
      return vmapped(params, x)

  got = jax.jit(batched)(params, x)
  for case, out in zip(cases, got):
    for k in range(K):
      pick = lambda t: jax.tree.map(lambda a: a[k], t)
      ref = nn.Conv(4, (3, 3), strides=case[1], padding="VALID")
      expect = grads(ref, pick(params), x[k], weights[case[1]][k])
      for g, e in zip(jax.tree.leaves(pick(out)), jax.tree.leaves(expect), strict=True):
        np.testing.assert_allclose(g, e, rtol=1e-5, atol=1e-5 * np.abs(e).max(),
                                   err_msg=str(case))
  # Per case a forward, an input- and a kernel-gradient convolution: none left
  # (gemm) or K plain ones each (split); plain vmap groups all of them.
  hlo = lambda fn: jax.jit(fn).lower(params, x).as_text(dialect="hlo")
  assert convolutions(hlo(batched)) == ((0, 0) if form == "gemm" else (3 * 4 * K, 0))
  assert convolutions(hlo(vmapped)) == (3 * 4, 3 * 4)
  # Unvmapped inside it, the convolution is the plain one.
  with layouts.vmapped_convs(form):
    one = jax.jit(lambda p, x: layouts.Conv(4, 2, impl="pixels").apply(p, x))
    text = one.lower(jax.tree.map(lambda a: a[0], params), x[0]).as_text(dialect="hlo")
  assert convolutions(text) == (1, 0)
  with pytest.raises(ValueError, match="gemm, split"):
    with layouts.vmapped_convs("grouped"):
      pass


@pytest.mark.slow
def test_vmap_gemm_agents_update_as_each_agent_alone():
  # K agents' update pair in one vmapped program on the GEMM path (the agent loop
  # "vmap_gemm", as `train` runs it) against each agent's update pair alone with
  # plain convolutions: the same parameters after it and the same losses.
  cfg = sac.SACConfig(batch_size=4, conv_channels=4, feature_dim=8, hidden_dim=16, lam=0.1)
  obs_shape, action_size = (16, 16, 9), 2
  agents = jax.jit(jax.vmap(lambda k: sac.init_agent(k, obs_shape, action_size, cfg)))(
      jax.random.split(jax.random.key(0), K))
  buffers = filled_buffers(K, 64, 16, 3, action_size)
  spec = train_step.StepSpec(agents=K, num_envs=1, warmup_steps=0, utd=1.0, sac=cfg,
                             agent_loop="vmap_gemm", low=(-1.0,) * action_size,
                             high=(1.0,) * action_size)
  names = train_step.metric_names(agents, buffers, cfg)
  key = jax.random.key(5)
  update = jax.jit(lambda agents, spec: train_step.update_agents(
      agents, buffers, key, 1, spec, names), static_argnums=1)
  lowered = update.lower(agents, spec)
  assert convolutions(lowered.as_text(dialect="hlo")) == (0, 0)
  new, metrics = lowered.compile()(agents)
  alone = jax.jit(lambda agent, buffer, k: train_step.update_pair(agent, buffer, k, cfg))
  keys = jax.random.split(key, K)  # update_agents' key of agent k, pair 0
  host = jax.device_get((agents, buffers, new.params, metrics))
  for k in range(K):
    pick = lambda t: jax.tree.map(lambda a: a[k], t)
    agent, buffer, params, agent_metrics = pick(host)
    ref, ref_metrics = alone(agent, buffer, jax.random.fold_in(keys[k], 0))
    for g, e in zip(jax.tree.leaves(params), jax.tree.leaves(ref.params), strict=True):
      np.testing.assert_allclose(g, e, rtol=1e-4, atol=1e-5)
    for name in ("critic_loss", "lam_loss", "actor_loss", "alpha_loss"):
      np.testing.assert_allclose(agent_metrics[name], ref_metrics[name], rtol=1e-4,
                                 err_msg=name)
  # The control: plain vmap gives grouped convolutions. Acting takes the same path.
  vmap = dataclasses.replace(spec, agent_loop="vmap")
  assert convolutions(update.lower(agents, vmap).as_text(dialect="hlo"))[1] > 0
  learner = train_step.init_learner(agents, buffers, key, 0, spec)
  obs = jnp.zeros((K, 16, 16, 9), jnp.uint8)
  acting = lambda s: train_step.act_jit.lower(learner, obs, spec=s).as_text(dialect="hlo")
  assert convolutions(acting(spec)) == (0, 0) and convolutions(acting(vmap))[1] > 0


def test_learner_benchmark_measures_each_new_loop_at_one_agent_too():
  from dmcr_jax.benchmarks import learner
  loops = ["map", "vmap", "vmap_gemm", "vmap_split"]
  assert learner.loops_for(8, loops) == loops
  assert learner.loops_for(1, loops) == ["vmap", "vmap_gemm", "vmap_split"]
  assert learner.loops_for(1, ["map"]) == ["vmap"]
  row = dict(kind="scanned", agents=1, dtype="bfloat16", agent_loop="vmap_gemm")
  assert learner.variant(row) == "K=1 bfloat16 vmap_gemm"
  assert learner.variant(dict(row, agent_loop="vmap")) == "K=1 bfloat16"


def test_roofline_counts_flops_and_bytes_of_convolutions_and_dots():
  # A 3×3 VALID convolution (4 images 10×10×3 → 8×8×5), tanh, a dot with a 5×7
  # matrix: FLOPs and bytes against the hand count, plain, vmapped over K = 3
  # (grouped) and on the GEMM path (dots).
  from dmcr_jax.benchmarks import learner_roofline as L
  f = lambda x, k, w: jnp.sum(jnp.tanh(layouts.conv_valid(x, k)) @ w)
  args = (jnp.zeros((4, 10, 10, 3)), jnp.zeros((3, 3, 3, 5)), jnp.zeros((5, 7)))
  conv_flops, dot_flops = 2 * 4 * 8 * 8 * 5 * 27, 2 * 4 * 8 * 8 * 7 * 5
  costs = L.hlo_costs(jax.jit(f).lower(*args).as_text(dialect="hlo"))
  assert costs["convolution"] == dict(flops=conv_flops, ops=1,
                                      bytes=4 * (4 * 10 * 10 * 3 + 3 * 3 * 3 * 5 + 4 * 8 * 8 * 5))
  assert costs["dot"]["flops"] == dot_flops
  assert costs["elementwise"]["flops"] == 4 * 8 * 8 * 5  # the tanh
  batched = tuple(jnp.zeros((K,) + a.shape) for a in args)
  grouped = L.hlo_costs(jax.jit(jax.vmap(f)).lower(*batched).as_text(dialect="hlo"))
  assert grouped["convolution"]["ops"] == 0
  assert grouped["grouped convolution"]["flops"] == K * conv_flops

  def gemm(*a):
    with layouts.vmapped_convs("gemm"):
      return jax.vmap(f)(*a)
  dots = L.hlo_costs(jax.jit(gemm).lower(*batched).as_text(dialect="hlo"))
  assert dots["convolution"]["ops"] == 0
  assert dots["dot"]["flops"] == K * (conv_flops + dot_flops)
