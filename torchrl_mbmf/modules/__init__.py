from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel

__all__ = ["DeltaDynamicsModel", "make_ppo_actor_critic", "make_sac_actor_critic"]
