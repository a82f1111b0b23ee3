"""PPO-MPC on Pendulum-v1 with stock TorchRL parts: the docs' tutorial, run by the test suite.

python docs/snippets/pendulum_mbmf.py
"""

# ruff: noqa: E402 (each section imports what it uses: the tutorial shows them one by one)

from __future__ import annotations

import torch

# --8<-- [start:env]
from torchrl_mbmf.envs import make_gym_state_env

real = make_gym_state_env("Pendulum-v1", seed=0)
print(real.observation_spec["state"].shape, real.action_spec.shape)  # (3,) state, (1,) action
# --8<-- [end:env]

# --8<-- [start:model]
from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.world_model import fit_dynamics

data = collect_random_transitions(real, 1000, seed=0)  # real steps: count them in the budget
model = DeltaDynamicsModel(3, 1, hidden_sizes=(64, 64))
history = fit_dynamics(model, data, lr=1e-3, batch_size=128, max_epochs=10, seed=0)
print(f"held-out loss {history.val_loss[0]:.3f} -> {min(history.val_loss):.3f}")
# --8<-- [end:model]

# --8<-- [start:planner]
from torchrl.envs.utils import check_env_specs

from torchrl_mbmf.envs import LearnedDynamicsEnv
from torchrl_mbmf.modules import PolicyGuidedMPCPlanner, make_ppo_actor_critic

model_env = LearnedDynamicsEnv(model, real)  # reset from real states, step the model
check_env_specs(model_env)
actor, critic = make_ppo_actor_critic(real, hidden_sizes=(64, 64))
planner = PolicyGuidedMPCPlanner(model_env, actor, num_candidates=15, horizon=10)
# --8<-- [end:planner]

# --8<-- [start:loop]
from torchrl.collectors import Collector
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
loss = ClipPPOLoss(actor, critic, entropy_coeff=1e-4, critic_coeff=0.5)
optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
collector = Collector(
    real, planner, frames_per_batch=200, total_frames=600, auto_register_policy_transforms=False
)
for i, batch in enumerate(collector):  # each batch: 200 real steps chosen by the planner
    data.extend(batch)  # every real transition joins the model's dataset
    with torch.no_grad():
        gae(batch)
    for _ in range(4):  # PPO epochs on the planner's batch (its log-probs are the actor's)
        for minibatch in batch.reshape(-1).split(50):
            out = loss(minibatch)
            optim.zero_grad()
            (out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]).backward()
            optim.step()
    fit_dynamics(model, data, lr=1e-3, batch_size=128, max_epochs=2, seed=i)  # warm refit
    finished = batch["next", "episode_reward"][batch["next", "done"]]
    print(f"batch {i}: return of the episodes that ended {finished.mean():.1f}")
collector.shutdown()
# --8<-- [end:loop]
