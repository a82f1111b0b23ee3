"""The training methods of ``recipes/train.py`` and their families.

Examples:
    >>> from torchrl_mbmf.methods import METHODS, MODEL_BASED, PPO_METHODS
    >>> [m for m in METHODS if m in MODEL_BASED and m in PPO_METHODS]
    ['mpc', 'ppo_mpc']
"""

from __future__ import annotations

__all__ = ["GUIDED", "METHODS", "MODEL_BASED", "PPO_METHODS"]

#: Methods of ``recipes/train.py``.
METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc", "sac", "sac_mpc", "sac_mbpo")
#: Methods that learn a world model (``sac_mbpo`` learns from its rollouts, nothing plans).
MODEL_BASED: tuple[str, ...] = ("mpc", "ppo_mpc", "sac_mpc", "sac_mbpo")
#: Methods trained with PPO.
PPO_METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc")
#: Methods whose planner is guided by the policy.
GUIDED: tuple[str, ...] = ("ppo_mpc", "sac_mpc")
