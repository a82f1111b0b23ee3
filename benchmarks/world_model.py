"""World-model costs: training samples/s (batch 512) and learned-env step cost at batch 1/15/120.

python benchmarks/world_model.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table, time_call, write

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_half_cheetah_env
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss
from torchrl_mbmf.trainers import fit_dynamics

NOTE = (
    "2 shared vCPUs with other jobs running at the same time: numbers are noisy; "
    "the end-to-end row includes the held-out evaluation and best-weight copies per epoch"
)


def main() -> None:
    torch.set_num_threads(2)
    torch.manual_seed(0)
    real = make_half_cheetah_env(seed=0)
    model = DeltaDynamicsModel(18, 6)
    n = 20_000
    s = torch.randn(n, 18)
    a = torch.rand(n, 6) * 2 - 1
    nxt = s + 0.1 * torch.randn(n, 18)
    r = torch.randn(n, 1)
    model.fit_normalizer(s, a, nxt, r)
    loss = DynamicsLoss(model)
    optim = torch.optim.Adam(model.parameters(), lr=1e-4)
    rows = []
    x, y = loss.scaled_pairs(s, a, nxt, r)
    for batch in (256, 512):
        idx = torch.randint(0, n, (batch,))

        def step(idx=idx):
            # fit_dynamics' inner step: data scaled once per fit, minibatches are index slices
            out = loss.scaled_loss(x[idx], y[idx])
            optim.zero_grad(set_to_none=True)
            out.backward()
            optim.step()

        def step_rescaling(idx=idx):
            # the same through the loss on raw tensors (rescales every minibatch)
            out = loss.squared_errors(s[idx], a[idx], nxt[idx], r[idx]).mean()
            optim.zero_grad(set_to_none=True)
            out.backward()
            optim.step()

        for what, fn in (
            ("fit_dynamics inner step", step),
            ("step rescaling each minibatch", step_rescaling),
        ):
            sec = time_call(fn, repeats=5, number=30)
            rows.append(
                {"what": what, "batch": batch, "ms": sec * 1e3, "samples_per_s": batch / sec}
            )
    data = TensorDict(
        state=s, action=a, next=TensorDict(state=nxt, reward=r, batch_size=[n]), batch_size=[n]
    )
    epochs = 3
    history = fit_dynamics(
        model, data, max_epochs=epochs, patience=epochs, fit_normalizer=False, seed=0
    )
    rows.append(
        {
            "what": f"fit_dynamics end to end ({n} transitions, {epochs} epochs)",
            "batch": 512,
            "ms": history.seconds / history.epochs * 1e3,
            "samples_per_s": history.num_train * history.epochs / history.seconds,
        }
    )
    env = LearnedDynamicsEnv(model, real)
    fused = env.fast_predictor()
    for batch in (1, 15, 120):
        td = env.reset(real.reset().expand(batch).clone())
        td["action"] = torch.rand(batch, 6) * 2 - 1
        state, action = td["state"], td["action"]
        with torch.no_grad():
            t_env = time_call(lambda td=td: env.step(td.clone()), repeats=5, number=100)
            t_pred = time_call(lambda s=state, a=action: env.predict(s, a), repeats=5, number=200)
            t_fused = time_call(lambda s=state, a=action: fused(s, a), repeats=5, number=200)
        for what, sec in (
            ("LearnedDynamicsEnv.step (tensordict)", t_env),
            ("LearnedDynamicsEnv.predict (tensors)", t_pred),
            ("fast_predictor (folded scaling)", t_fused),
        ):
            rows.append(
                {"what": what, "batch": batch, "ms": sec * 1e3, "samples_per_s": batch / sec}
            )
    print_table(rows)
    path = write("world_model", rows, {"model": "18+6 -> 500 -> 500 -> 19", "note": NOTE})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
