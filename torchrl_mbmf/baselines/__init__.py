"""Reference implementations run beside ours (``baselines.sb3``: Stable-Baselines3).

Nothing here is imported by the rest of the package; ``torchrl_mbmf.baselines.sb3`` needs
Stable-Baselines3 installed.
"""
